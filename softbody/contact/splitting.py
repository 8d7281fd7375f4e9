"""Diagonal splittings of the PD matrix for the contact solver's iteration, and their theory.

The contact solver (:class:`softbody.contact.Contact`) splits the PD matrix
``A = M/h^2 + L`` as ``P - (D - L)`` with ``P = M/h^2 + D`` diagonal and iterates
``x <- P^{-1} (b + (D - L) x)``, so that each iteration inverts a diagonal only. A
:class:`Splitting` chooses ``D``: :class:`Naive` ``0``, :class:`Diagonal` ``diag(L)``
(the published choice) and the default :class:`ScaledDiagonal` ``2 diag(L)``, whose
convergence is proved in its docstring (with the projections held fixed, and locally at
every strict minimum for the iteration that re-projects).

With the projections held fixed and no contact active, the iteration matrix is
``T = P^{-1} (D - L) = (M + h^2 D)^{-1} h^2 (D - L)`` (the velocity form's), and the
iteration converges for every right-hand side iff ``rho(T) < 1``:
:func:`splitting_spectral_radius` measures ``rho(T)`` for a scene on the host (scipy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as splinalg
from jaxtyping import Array, Float
from scipy import sparse

__all__ = ["Diagonal", "Naive", "ScaledDiagonal", "Splitting", "splitting_spectral_radius"]


class Splitting:
    """A diagonal splitting ``D`` of the PD stiffness ``L = A - M/h^2`` (a small strategy).

    The splitting iteration with projections held fixed is ``x <- P^{-1} (b + (D - L) x)``
    with ``P = M/h^2 + D``; its iteration matrix ``T = P^{-1} (D - L)`` equals the
    velocity form's ``(M + h^2 D)^{-1} h^2 (D - L)``. It converges for every right-hand
    side iff the spectral radius ``rho(T) < 1``; see :func:`splitting_spectral_radius`.
    """

    def diagonal(self, stiffness: Float[Array, "n 1"]) -> Float[Array, "n 1"]:
        """``D`` from ``diag(L)``.

        Arguments:
            stiffness: ``(n, 1)`` the diagonal of ``L`` (non-negative).

        Returns:
            ``(n, 1)`` the diagonal of ``D``.
        """
        raise NotImplementedError


@dataclass(frozen=True)
class Naive(Splitting):
    """``D = 0``: only the mass is inverted. ``rho(T) = h^2 lambda_max(M^-1 L)``, which is far
    above 1 for any stiff body and time step worth simulating (kept for the stability study)."""

    def diagonal(self, stiffness):
        return jnp.zeros_like(stiffness)


@dataclass(frozen=True)
class Diagonal(Splitting):
    """``D = diag(L)`` (Jacobi), the published choice.

    Its iteration matrix has eigenvalues in ``[-3 d/(m/h^2 + d), 1)`` in the worst case
    (``d`` a diagonal entry of ``L``): it converges when ``L <= 2 diag(L)`` (e.g. on meshes
    whose ``L`` is an M-matrix: structured grids with non-obtuse tets) or when the inertia
    dominates, and can diverge otherwise (unstructured meshes, stiff materials, long time
    steps): see :func:`splitting_spectral_radius`.
    """

    def diagonal(self, stiffness):
        return stiffness


@dataclass(frozen=True)
class ScaledDiagonal(Splitting):
    """``D = scale * diag(L)``; with ``scale >= 2`` (the default) convergence is guaranteed.

    **Theorem.** Let ``L = sum_e K_e + Lambda`` with every ``K_e`` symmetric positive
    semi-definite and nonzero only on the (at most 4) vertices of element ``e``, and
    ``Lambda >= 0`` diagonal. (The PD matrix has this form: corotated, volume, damping and
    actuator terms add ``w_e G_e G_e^T`` per tet, mass damping is diagonal; rows of fixed
    vertices are dropped.) Let ``M > 0`` be the lumped masses on the free vertices and
    ``D = 2 diag(L)``. Then every eigenvalue of ``T = (M/h^2 + D)^{-1} (D - L)`` lies in
    ``[-beta, beta]`` with ``beta = max_i 2 d_i / (m_i/h^2 + 2 d_i) < 1``, ``d = diag(L)``.

    *Proof.* (1) ``L <= 4 diag(L)``: for a PSD ``K`` on 4 indices with columns ``k_a`` of
    ``K^{1/2}``, ``u^T K u = |sum_a u_a k_a|^2 <= (sum_a |u_a| |k_a|)^2
    <= 4 sum_a u_a^2 |k_a|^2 = 4 sum_a K_aa u_a^2`` (Cauchy-Schwarz twice); sum over the
    elements, and ``Lambda`` is diagonal. (2) ``P = M/h^2 + D`` is diagonal positive, so
    ``T`` is similar to the symmetric ``P^{-1/2} (D - L) P^{-1/2}``: its eigenvalues are real
    and are Rayleigh quotients ``u^T (D - L) u / u^T P u``. (3) Since ``L >= 0``,
    ``D - L <= D``; by (1), ``D - L >= 2 diag(L) - 4 diag(L) = -D``. Hence
    ``|u^T (D - L) u| <= u^T D u`` and ``|lambda| <= max_u u^T D u / (u^T M u/h^2 + u^T D u)
    <= max_i d'_i / (m_i/h^2 + d'_i) = beta`` with ``d' = 2 d``, and ``beta < 1`` because
    every ``m_i > 0``. QED. The velocity form ``(M + h^2 D)^{-1} h^2 (D - L)`` is the same
    matrix. A larger ``scale`` keeps the bound (``beta`` grows towards 1, so convergence
    slows); for ``scale < 2`` the bound fails for some meshes. For statics (no mass) the
    bound is ``rho < 1`` iff ``L`` is definite, i.e. enough vertices are fixed.

    **The iteration that re-projects.** :class:`~softbody.contact.Contact` runs the local
    step in every iteration, so near a solution its map (contact state fixed) linearises to
    ``I - P^{-1} H`` on the unconstrained directions, ``H`` the step objective's true
    Hessian. PD's quadratic model with the projections of ``x`` majorises the energy and
    touches it at ``x``, so ``H <= A = P - (D - L)``, and by (3) ``P^{-1} A`` has
    eigenvalues in ``[1 - beta, 1 + beta]``. Hence ``P^{-1} H`` has eigenvalues in
    ``(0, 1 + beta]`` wherever ``H`` is positive definite (a strict minimum), and the
    linearised map's in ``[-beta, 1)``: the default converges locally at every strict
    minimum. (Terms that the PD matrix does not contain, such as cavity pressure, are
    outside this argument.) Because ``H`` is smaller than ``A`` (the volume term's PD block
    is isotropic, its Hessian rank one per tet), the published splittings can converge in
    the full iteration where the frozen-projection radius exceeds 1; the
    ``friction-stability`` benchmark measures both. Measured there (6 meshes of 125-1419
    vertices, ``E`` = 1e4-1e7 Pa, ``nu`` = 0.45, ``h`` = 1/1000-1/30 s): frozen-projection
    radius of the default 0.66 to ``1 - 1.5e-8`` (always below ``beta``), of
    :class:`Diagonal` 0.49-1.39 (above 1 on every unstructured mesh once
    ``E h^2`` is large: gmsh cube 1.03, ball 1.06, caterpillar 1.09, quadruped 1.23,
    finger 1.39), of :class:`Naive` 2 to 1.7e8; the plain full iteration diverged with
    Naive in 95 of 96 cases and never with the other two, whose contraction per iteration
    is 0.99-0.9999 for stiff bodies and long steps (hence the acceleration).

    Attributes:
        scale: the factor on ``diag(L)`` (> 0).

    Raises:
        ValueError: a non-positive or non-finite ``scale``.
    """

    scale: float = 2.0

    def __post_init__(self):
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"ScaledDiagonal.scale must be a positive number, got {self.scale!r}")

    def diagonal(self, stiffness):
        return self.scale * stiffness

    @staticmethod
    def bound(mass: np.ndarray, stiffness: np.ndarray, dt: float) -> float:
        """The theorem's ``beta`` for ``scale = 2``: ``max_i 2 d_i / (m_i/h^2 + 2 d_i)``.

        Arguments:
            mass: ``(n,)`` lumped masses of the free vertices, kg.
            stiffness: ``(n,)`` their ``diag(L)``, N/m.
            dt: the time step, s (> 0).

        Returns:
            The bound on the spectral radius, in ``[0, 1)``.
        """
        mass, d = np.asarray(mass, np.float64).ravel(), np.asarray(stiffness, np.float64).ravel()
        return float(np.max(2 * d / (mass / dt**2 + 2 * d)))


def _pd_split(model, prep):
    """Free-vertex ``(mass (f,), L (f, f) scipy CSR, dt)`` of a compiled dynamic scene and its
    prepared data (:func:`softbody.model.prepare`)."""
    h = model.options.dt
    a = model.pattern.to_scipy(np.asarray(prep.data)).tocsr()
    mass = np.asarray(prep.mass)[:, 0]
    free = np.flatnonzero(np.asarray(model.free_mask)[:, 0] > 0)
    stiffness = (a - sparse.diags(mass / h**2))[free][:, free].tocsr()
    return mass[free], stiffness, h


def splitting_spectral_radius(model, prep, splitting: Splitting) -> float:
    """Spectral radius of the splitting iteration matrix with the projections held fixed.

    ``rho((M/h^2 + D)^{-1} (D - L))`` over the free vertices, for the scene's PD matrix
    (with the volume weight of the scene's step: 1 with
    :class:`~softbody.contact.Contact`). Computed on the host with scipy (``eigsh`` on
    the symmetric similar matrix ``P^{-1/2} (D - L) P^{-1/2}``; dense ``eigvalsh`` below
    500 vertices).

    Arguments:
        model, prep: a compiled dynamic scene (:func:`softbody.model.build`) and its
            prepared data (:func:`softbody.model.prepare` of its params).
        splitting: the :class:`Splitting`.

    Returns:
        The spectral radius (< 1: the iteration converges).
    """
    mass, stiffness, h = _pd_split(model, prep)
    d = np.asarray(splitting.diagonal(jnp.asarray(stiffness.diagonal())[:, None]))[:, 0]
    return _spectral_radius(mass, stiffness, h, d)


def _spectral_radius(mass, stiffness, h: float, d) -> float:
    """``rho((M/h^2 + diag(d))^{-1} (diag(d) - L))`` for free-vertex ``mass`` (f,), ``L`` (f, f)."""
    scale = 1.0 / np.sqrt(mass / h**2 + d)
    s = sparse.diags(scale) @ (sparse.diags(d) - stiffness) @ sparse.diags(scale)
    if s.shape[0] < 500:
        return float(np.max(np.abs(np.linalg.eigvalsh(s.toarray()))))
    vals = splinalg.eigsh(s.tocsc(), k=1, which="LM", return_eigenvectors=False, tol=1e-10)
    return float(np.max(np.abs(vals)))


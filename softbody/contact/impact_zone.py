"""Collision response as a quadratic programme, and its exact backward: a reference.

An impact zone (Liang, Lin and Koltun, "Differentiable Cloth Simulation for Inverse
Problems", NeurIPS 2019) moves the vertices ``x`` (``n = 3 * vertices`` coordinates) as
little as the masses allow to positions ``z`` that satisfy every contact constraint::

    z* = argmin_z 1/2 (z - x)^T W (z - x)   subject to   G z + h <= 0

with ``W = diag(w)``, ``w > 0`` (the vertex masses, one per coordinate), ``G`` the
``(m, n)`` constraint Jacobian (a vertex-triangle or edge-edge row couples up to four
vertices) and ``h`` the ``(m,)`` offsets. This module is a host-side (numpy) reference:
an oracle for gradient tests of body-body contact, not a path the simulator runs.

**Forward** (:func:`solve`). The Lagrangian dual is ``max_{lam >= 0} -1/2 lam^T A lam +
lam^T b`` with ``A = G W^-1 G^T``, ``b = G x + h``, and ``z = x - W^-1 G^T lam``. In the
scaled unknowns ``y = W^(1/2) (z - x)`` the problem is the least-distance programme
``min |y|`` s.t. ``Gh y <= -b``, ``Gh = G W^(-1/2)``, which Lawson and Hanson (Solving
Least Squares Problems, ch. 23) reduce to the non-negative least squares problem
``min_{u >= 0} |[Gh^T; b^T] u - e_{n+1}|``; then ``lam = u / (1 - b^T u)``, and
``1 - b^T u = 0`` means the constraints are infeasible. :func:`solve` runs their active-set
NNLS on its normal equations (``C = A + b b^T``, ``m x m``): each iteration frees the most
violated constraint and solves on the free set. Unlike the same iteration on the dual
alone, a free set of NNLS never has dependent columns (in exact arithmetic), so redundant
or parallel constraints (more rows than coordinates, say) need no special care: the rows
with ``lam > 0`` at the end are linearly independent.

**Backward.** Let ``a`` be the active rows (``lam_a > 0``; strict complementarity and
independent active rows are assumed, so the solution is a smooth function of the inputs
near them and the inactive rows stay slack). On them the KKT conditions are equalities::

    W (z - x) + G_a^T lam_a = 0,    G_a z + h_a = 0.

Differentiating, ``K [dz; dlam] = -[dW (z - x) - W dx + dG_a^T lam_a; dG_a z + dh_a]``
with the symmetric ``K = [[W, G_a^T], [G_a, 0]]``. For an upstream gradient ``gz =
dL/dz``, solve the adjoint system ``K [u; v] = [gz; 0]``; then
``dL = -u . (dW (z - x) - W dx + dG_a^T lam_a) - v . (dG_a z + dh_a)``, so::

    dL/dx = W u,   dL/dw = -u * (z - x),   dL/dG_a = -(lam_a u^T + v z^T),   dL/dh_a = -v

and the inactive rows of ``dL/dG``, ``dL/dh`` are zero. :func:`backward_kkt` solves the
``(n + k) x (n + k)`` system densely (``k`` active rows): ``O((n + k)^3)``.
:func:`backward_qr` eliminates ``u``: ``u = W^-1 (gz - G_a^T v)`` and ``G_a u = 0`` give
``(G_a W^-1 G_a^T) v = G_a W^-1 gz``. With the reduced QR factorisation ``Q R =
W^(-1/2) G_a^T`` (``Q`` ``(n, k)``, ``R`` ``(k, k)``), ``G_a W^-1 G_a^T = R^T R``, so::

    v = R^-1 Q^T W^(-1/2) gz,    u = W^(-1/2) (I - Q Q^T) W^(-1/2) gz

in ``O(n k^2)``. ``softbody bench impact-zone`` times both on cloth-sized problems.

:func:`qp` wraps the forward and the QR backward as a JAX function with a custom VJP.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import qr, solve_triangular

#: a row is active when its multiplier exceeds this fraction of the largest multiplier
ACTIVE_RTOL = 1e-9
#: ``1 - b^T u`` at or below this (scaled problem) means the constraints are infeasible
INFEASIBLE = 1e-12


class Gradients(NamedTuple):
    """Gradients of a loss ``L`` with respect to the inputs of :func:`solve`."""

    dx: np.ndarray  #: ``(n,)``: dL/dx
    dw: np.ndarray  #: ``(n,)``: dL/dw (the diagonal of W)
    dG: np.ndarray  #: ``(m, n)``: dL/dG; zero on inactive rows
    dh: np.ndarray  #: ``(m,)``: dL/dh; zero on inactive rows


def _check_shapes(x, w, G, h) -> None:
    """Check the problem's dimensions (anything with ``shape``: numpy or JAX arrays)."""
    for name, a, ndim in (("x", x, 1), ("w", w, 1), ("G", G, 2), ("h", h, 1)):
        if len(a.shape) != ndim:
            kind = "a vector (1-D)" if ndim == 1 else "a matrix (2-D)"
            raise ValueError(f"{name} must be {kind}, got shape {tuple(a.shape)}; pass {name} "
                             f"with {ndim} dimension(s)")
    n = x.shape[0]
    if tuple(w.shape) != (n,):
        raise ValueError(f"w has shape {tuple(w.shape)} but x has {n} entries; pass one weight "
                         f"(mass) per coordinate, shape ({n},)")
    if G.shape[1] != n:
        raise ValueError(f"G has shape {tuple(G.shape)} but x has {n} entries; G must be (m, {n}): "
                         f"one row per constraint, one column per coordinate")
    if tuple(h.shape) != (G.shape[0],):
        raise ValueError(f"h has shape {tuple(h.shape)} but G has {G.shape[0]} rows; pass one "
                         f"offset per constraint, shape ({G.shape[0]},)")


def _finite(**arrays) -> None:
    for name, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} has non-finite entries (nan or inf); pass finite values")


def _check(x, w, G, h) -> tuple[np.ndarray, ...]:
    """The problem's arrays as float arrays, after checking shapes and values."""
    x, w, G, h = (np.asarray(a, dtype=float) for a in (x, w, G, h))
    _check_shapes(x, w, G, h)
    _finite(x=x, w=w, G=G, h=h)
    if not np.all(w > 0):
        raise ValueError(f"w must be positive (W = diag(w) is the mass matrix), got min(w) = "
                         f"{w.min()}; give every coordinate a positive mass")
    return x, w, G, h


def solve(x, w, G, h, *, tol: float = 1e-12,
          max_iter: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The collision response: ``argmin_z 1/2 (z - x)^T W (z - x)`` s.t. ``G z + h <= 0``.

    Arguments:
        x: ``(n,)`` positions before the response.
        w: ``(n,)`` positive diagonal of ``W`` (masses, one per coordinate).
        G: ``(m, n)`` constraint Jacobian.
        h: ``(m,)`` constraint offsets.
        tol: the largest constraint violation accepted, as a fraction of the largest
            violation at ``x``, ``max(G x + h)``.
        max_iter: at most this many active-set iterations, each a solve on the free set
            (default ``10 m + 10``).

    Returns:
        ``(z, lam)``: the ``(n,)`` solution and the ``(m,)`` multipliers ``lam >= 0``, with
        ``W (z - x) + G^T lam = 0`` and ``lam_i = 0`` on slack rows.

    Raises:
        ValueError: shapes that do not fit, ``w <= 0``, non-finite input, or constraints
            that no ``z`` satisfies.
        RuntimeError: not converged in ``max_iter`` iterations.
    """
    x, w, G, h = _check(x, w, G, h)
    m = h.size
    b = G @ x + h
    scale = b.max(initial=0.0)
    if scale <= 0:  # x already satisfies every constraint
        return x.copy(), np.zeros(m)
    max_iter = 10 * m + 10 if max_iter is None else max_iter
    b = b / scale  # the least-distance programme is homogeneous in b: lam scales with it
    Gh = G / np.sqrt(w)
    C = Gh @ Gh.T + np.outer(b, b)
    u, free, solves = np.zeros(m), np.zeros(m, bool), 0
    while True:
        rho = 1.0 - b @ u
        if rho <= INFEASIBLE:
            raise ValueError("the constraints G z + h <= 0 have no solution (the contact set is "
                             "infeasible); check the constraint rows and offsets")
        violation = np.where(free, -np.inf, (b - C @ u) / rho)  # (G z + h) / scale at u
        i = int(np.argmax(violation))
        if violation[i] <= tol:
            lam = scale * u / rho
            return x - (G.T @ lam) / w, lam
        free[i] = True
        while solves < max_iter:  # solve on the free set, stepping back while any turns <= 0
            solves += 1
            s = np.zeros(m)
            s[free] = np.linalg.solve(C[np.ix_(free, free)], b[free])
            if np.all(s[free] > 0):
                u = s
                break
            blocked = np.flatnonzero(free & (s <= 0))
            ratios = u[blocked] / (u[blocked] - s[blocked])
            u = u + ratios.min() * (s - u)
            u[blocked[np.argmin(ratios)]] = 0.0
            free &= u > 0
            u[~free] = 0.0
        else:
            break
    raise RuntimeError(f"the active-set iteration did not converge in {max_iter} iterations; "
                       f"raise max_iter or loosen tol (now {tol})")


def _check_solution(x, w, G, h, z, lam, dz) -> tuple[np.ndarray, ...]:
    x, w, G, h = _check(x, w, G, h)
    z, lam, dz = (np.asarray(a, dtype=float) for a in (z, lam, dz))
    for name, a, size in (("z", z, x.size), ("dz", dz, x.size), ("lam", lam, h.size)):
        if a.shape != (size,):
            raise ValueError(f"{name} has shape {a.shape}, expected ({size},); pass the "
                             f"(z, lam) that solve returned and dz = dL/dz of shape ({x.size},)")
    _finite(z=z, lam=lam, dz=dz)
    return x, w, G, h, z, lam, dz


def _active(lam: np.ndarray) -> np.ndarray:
    """The active rows: multipliers above :data:`ACTIVE_RTOL` times the largest."""
    largest = lam.max(initial=0.0)
    return lam > ACTIVE_RTOL * largest if largest > 0 else np.zeros(lam.size, bool)


def _gradients(x, w, G, z, lam, active, u, v) -> Gradients:
    """The gradients from the adjoint solution ``(u, v)`` (``v`` on the active rows)."""
    dG, dh = np.zeros_like(G), np.zeros(lam.size)
    dG[active] = -(np.outer(lam[active], u) + np.outer(v, z))
    dh[active] = -v
    return Gradients(w * u, -u * (z - x), dG, dh)


_DEPENDENT = ("the active constraint rows are linearly dependent, so the multipliers and the "
              "backward are not unique; remove duplicate or redundant contact rows")


def backward_kkt(x, w, G, h, z, lam, dz) -> Gradients:
    """Gradients of ``L(z)`` through :func:`solve` from the full KKT system, solved densely.

    Arguments:
        x, w, G, h: the problem, as passed to :func:`solve`: ``(n,)``, ``(n,)``, ``(m, n)``,
            ``(m,)``.
        z, lam: its solution, ``(n,)`` and ``(m,)``.
        dz: ``(n,)`` upstream gradient ``dL/dz``.

    Returns:
        :class:`Gradients` ``(dx, dw, dG, dh)``, shaped like ``x, w, G, h``.

    Raises:
        ValueError: shapes that do not fit, ``w <= 0``, non-finite input, or linearly
            dependent active rows.
    """
    x, w, G, h, z, lam, dz = _check_solution(x, w, G, h, z, lam, dz)
    active = _active(lam)
    Ga, n = G[active], x.size
    K = np.zeros((n + Ga.shape[0],) * 2)
    K[np.arange(n), np.arange(n)] = w
    K[:n, n:] = Ga.T
    K[n:, :n] = Ga
    try:
        uv = np.linalg.solve(K, np.concatenate([dz, np.zeros(Ga.shape[0])]))
    except np.linalg.LinAlgError:
        raise ValueError(_DEPENDENT) from None
    return _gradients(x, w, G, z, lam, active, uv[:n], uv[n:])


def backward_qr(x, w, G, h, z, lam, dz) -> Gradients:
    """Gradients of ``L(z)`` through :func:`solve` from the QR form, ``O(n k^2)`` for ``k`` rows.

    Arguments and returns as :func:`backward_kkt`, whose gradients it equals to rounding.

    Raises:
        ValueError: shapes that do not fit, ``w <= 0``, non-finite input, or linearly
            dependent active rows.
    """
    x, w, G, h, z, lam, dz = _check_solution(x, w, G, h, z, lam, dz)
    active = _active(lam)
    r = 1.0 / np.sqrt(w)
    Q, R = qr((G[active] * r).T, mode="economic", check_finite=False)
    diag = np.abs(np.diag(R))
    if diag.size and diag.min() <= 1e3 * np.finfo(float).eps * diag.max() * np.sqrt(x.size):
        raise ValueError(_DEPENDENT)
    g = r * dz
    c = Q.T @ g
    return _gradients(x, w, G, z, lam, active, r * (g - Q @ c), solve_triangular(R, c))


def qp(x, w, G, h):
    """:func:`solve`'s ``z`` as a JAX function, differentiable by :func:`backward_qr`.

    Both directions run on the host (``jax.pure_callback``), so it works under ``jax.jit``
    and ``jax.grad``; under ``jax.vmap`` it solves the problems one by one.

    Arguments:
        x, w, G, h: JAX or numpy arrays, ``(n,)``, ``(n,)``, ``(m, n)``, ``(m,)``.

    Returns:
        ``(n,)`` the solution ``z`` (JAX's default float dtype).

    Raises:
        ValueError: shapes that do not fit (at trace time). Bad values (``w <= 0``,
            non-finite, infeasible) fail inside the callback, when it runs.
    """
    x, w, G, h = (jnp.asarray(a, dtype=jnp.result_type(float)) for a in (x, w, G, h))
    _check_shapes(x, w, G, h)
    return _qp(x, w, G, h)


def _host(function, like):
    """``function`` on numpy copies of its arguments, its results cast to ``like``'s dtypes."""
    def call(*args):
        return tuple(np.asarray(r, a.dtype) for r, a in zip(function(*map(np.asarray, args)), like))

    return call


def _qp_fwd(x, w, G, h):
    like = (jax.ShapeDtypeStruct(x.shape, x.dtype), jax.ShapeDtypeStruct(h.shape, x.dtype))
    z, lam = jax.pure_callback(_host(solve, like), like, x, w, G, h, vmap_method="sequential")
    return z, (x, w, G, h, z, lam)


def _qp_bwd(res, dz):
    like = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in res[:4])
    return jax.pure_callback(_host(backward_qr, like), like, *res, dz, vmap_method="sequential")


_qp = jax.custom_vjp(lambda x, w, G, h: _qp_fwd(x, w, G, h)[0])
_qp.defvjp(_qp_fwd, _qp_bwd)

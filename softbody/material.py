"""Materials and the physical weights of the projective-dynamics energy.

Energy per tet (volume ``V``, deformation gradient ``F``, its rotation ``R``, maximiser of
``tr(R^T F)``, see :mod:`softbody.rotation`)::

    psi(F) = V * [ w_s / 2 * ||F - R||^2  +  w_v / 2 * ||F - P_v(F)||^2 ]

* The **corotated (ARAP) term** projects ``F`` onto SO(3).
* The **volume term** projects ``F`` onto the volume-preserving matrices
  ``{G : det G = 1}`` along ``R``: ``P_v(F) = F + c R`` shifts every signed singular value
  by the same ``c``, the root of ``det(S + c I) = 1`` (``S = sym(R^T F)``) with ``S + c I``
  positive definite (:func:`softbody.elastic.volume_shift`, a Newton iteration on a
  cubic in the invariants of ``S``: no eigendecomposition). So
  ``||F - P_v||^2 = 3 c^2``. Near rest ``c = (3 - tr(R^T F)) / 3 + O(|H|^2)``, and the two
  terms are the corotated linear-elastic energy
  ``mu ||F - R||^2 + lambda / 2 (tr(R^T F) - 3)^2`` to second order. At large strain
  the target matters: a wall stretched in its plane can only thin until its stretches
  multiply to 1. (Targeting ``tr(R^T F) = 3`` instead, the sum of the stretches, makes
  the stress linear in the stretches: a free wall stretched by ``1 + e`` in both in-plane
  directions thins to ``1 - 2 nu e / (1 - nu)``, zero at ``e = 61 %`` for nu = 0.45; the
  example finger's chamber wall inverted at 100 % strain, 23 kPa. The
  shift along ``R`` is not the closest point of ``{det = 1}``, which would need an
  eigendecomposition per tet; its distance is larger, by up to ``sqrt(3)`` for a thin
  wall, so the term's curvature can exceed ``w_v``, the weight in the PD matrix.)

**Physical weights.** Write ``F = I + H`` with ``|H|`` small and ``eps = sym(H)``. Then
``R = I + skew(H) + O(|H|^2)``, so ``F - R = eps + O(|H|^2)`` and
``tr(R^T F) - 3 = tr(eps) + O(|H|^2)``, giving::

    psi / V = w_s / 2 * |eps|^2 + w_v / 6 * tr(eps)^2 + O(|H|^3).

Linear elasticity's energy density is ``mu |eps|^2 + lambda / 2 tr(eps)^2``, with
``mu = E / (2 (1 + nu))`` and ``lambda = E nu / ((1 + nu)(1 - 2 nu))``. Matching term by
term: ``w_s = 2 mu`` and ``w_v = 3 lambda``. So ``E`` and ``nu`` mean what an engineer
means; the static cantilever test checks this against scikit-fem's linear elasticity.
(Weighting the volume term by ``lambda`` instead, as some published PD code does,
makes the material three times too compressible in its bulk modulus.)

**Damping** (Rayleigh, as dissipation potentials of the implicit-Euler step, ``h`` the
time step, ``x_n`` the positions at the start of the step):

* mass-proportional ``alpha`` [1/s]: ``alpha / (2 h) (x - x_n)^T M (x - x_n)``;
* stiffness-proportional ``beta`` [s]: ``beta / (2 h) * V w_s * |sym(R_n^T (F - F_n))|^2``,
  the corotated strain-rate energy. It vanishes for rigid motion (to first order) and is
  a PD term whose projection (onto ``{R_n W : W skew}``, a linear subspace) is exact.
  A scene pays for it only if some material had ``beta > 0`` when it was built (so the
  gradient with respect to ``beta`` needs a positive starting value).

Mass is lumped: each tet gives a quarter of ``density * V`` to each of its vertices.
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: The allowed values of each material field: name -> (test, what the value must be). The
#: tests work elementwise on arrays, so :class:`Material` (one number each) and
#: ``Params.replace`` (one value per material) check against the same rules.
RULES: dict[str, tuple[Callable, str]] = {
    "E": (lambda v: v > 0, "Young's modulus must be a positive number of pascals"),
    "nu": (lambda v: (v > -1) & (v < 0.5),
           "Poisson's ratio must lie in (-1, 0.5); 0.5 (incompressible) is not supported, use 0.49"),
    "density": (lambda v: v > 0, "density must be positive (kg/m^3)"),
    "alpha": (lambda v: v >= 0, "mass damping alpha must be >= 0 (1/s)"),
    "beta": (lambda v: v >= 0, "stiffness damping beta must be >= 0 (s)"),
}


def check_values(where: str, name: str, value) -> np.ndarray:
    """Check a concrete material value (a number or an array of them) against :data:`RULES`.

    Arguments:
        where: how the message names the value, e.g. ``"Material.E"``.
        name: the field, a key of :data:`RULES`.
        value: a number or an array-like of numbers (not a JAX tracer).

    Returns:
        ``value`` as a float64 numpy array (0-d for a number).

    Raises:
        TypeError: ``value`` is not numeric (text, a bool, ``None``, ...).
        ValueError: some entry is NaN, inf or outside the allowed range.
    """
    ok, why = RULES[name]
    real = isinstance(value, numbers.Real) and not isinstance(value, bool)
    try:  # float(): a Fraction or another real number type that numpy would keep as an object
        array = np.asarray(float(value) if real else value)
    except (TypeError, ValueError):  # ragged nesting and the like
        array = np.asarray(None)
    if array.dtype.kind not in "iuf":
        hint = " (write the number without quotes)" if isinstance(value, (str, bytes)) else ""
        raise TypeError(f"{where} = {value!r} is not a number{hint}: {why}")
    array = array.astype(np.float64)
    bad = ~(np.isfinite(array) & ok(array))
    if np.any(bad):
        shown = value if array.ndim == 0 else array.tolist()
        raise ValueError(f"{where} = {shown!r}: {why}")
    return array


@dataclass(frozen=True)
class Material:
    """An isotropic material.

    Attributes:
        E: Young's modulus, Pa (> 0).
        nu: Poisson's ratio, in (-1, 0.5).
        density: kg/m^3 (> 0).
        alpha: mass-proportional damping, 1/s (>= 0).
        beta: stiffness-proportional damping, s (>= 0).

    Raises:
        TypeError: a value is not a number (e.g. the text ``"1e5"``), naming the field.
        ValueError: naming the bad value and the allowed range.
    """

    E: float = 1e6
    nu: float = 0.45
    density: float = 1000.0
    alpha: float = 0.0
    beta: float = 0.0

    def __post_init__(self):
        for name in RULES:
            value = getattr(self, name)
            if check_values(f"Material.{name}", name, value).ndim != 0:
                raise TypeError(f"Material.{name} = {value!r} is not a single number: {RULES[name][1]}")

    @property
    def mu(self) -> float:
        """Shear modulus, Pa."""
        return self.E / (2 * (1 + self.nu))

    @property
    def lam(self) -> float:
        """Lame's first parameter, Pa."""
        return self.E * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))


def pd_weights(E, nu):
    """PD weights ``(w_s, w_v) = (2 mu, 3 lambda)`` for Young's modulus and Poisson's ratio.

    Works on floats and on JAX arrays (differentiable). See the module docstring.
    """
    return E / (1 + nu), 3 * E * nu / ((1 + nu) * (1 - 2 * nu))

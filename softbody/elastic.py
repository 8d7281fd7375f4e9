"""Per-tet kinematics and the elastic PD energy (see :mod:`softbody.material`).

Matrices are batched in structure-of-arrays layout ``(3, 3, t)``. ``G_e`` is the ``4 x 3``
gradient operator of tet ``e``'s linear shape functions (rows ``-sum_k Dm^-1[k]`` for
vertex 0 and ``Dm^-1[k]`` for vertex ``k + 1``), so that ``F_e = sum_a x_a g_a^T``.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from softbody import rotation as rot

Array = jax.Array


def rest_geometry(model, morph: Array) -> tuple[Array, Array]:
    """Inverse rest edge matrices ``(3, 3, t)`` and rest volumes ``(t,)`` of the morphed mesh."""
    x = jnp.asarray(model.mesh.points) + morph
    dm = _edges(model, x)
    cof = rot._cofactor(dm)
    det = rot.det3(dm)
    return rot.transpose(cof) / det, det / 6.0


def _edges(model, x: Array) -> Array:
    """``Ds[i, k, t] = x[tet[k+1], i] - x[tet[0], i]``, shape ``(3, 3, t)``."""
    # One gather per coordinate from a contiguous column: XLA's CPU gathers of whole rows
    # of an (n, 3) array followed by a transpose are several times slower.
    corners = jnp.asarray(model.mesh.tets.T)  # (4, t)
    xe = jnp.stack([x[:, i][corners] for i in range(3)])  # (3, 4, t)
    return xe[:, 1:, :] - xe[:, :1, :]


def deformation_gradient(model, dminv: Array, x: Array) -> Array:
    """Deformation gradients ``F = Ds Dm^-1``, shape ``(3, 3, t)``, of positions ``x`` ``(n, 3)``."""
    return rot.matmul(_edges(model, x), dminv)


def corner_incidence(tets: np.ndarray, n: int) -> np.ndarray:
    """Each vertex's tet corners: ``(n, K)`` int32 flat indices ``a * t + e`` (corner ``a`` of
    tet ``e``; ``K`` the largest valence, at least 1), padded with ``4 t``.

    Arguments:
        tets: ``(t, 4)`` vertex indices in ``[0, n)``; n: the number of vertices (those of
            rigid bodies are in no tet).
    """
    t = len(tets)
    flat = np.asarray(tets, np.int64).T.reshape(-1)  # position a * t + e holds tets[e, a]
    valence = np.bincount(flat, minlength=n)
    order = np.argsort(flat, kind="stable")
    rank = np.arange(flat.size) - np.repeat(np.cumsum(valence) - valence, valence)
    table = np.full((n, int(valence.max(initial=1))), 4 * t, np.int32)
    table[flat[order], rank] = order
    return table


def shape_gradients(dminv: Array) -> Array:
    """``G`` with shape ``(4, 3, t)``: the gradients of the four linear shape functions."""
    return jnp.concatenate([-dminv.sum(axis=0, keepdims=True), dminv], axis=0)


def local_matrices(dminv: Array, weight: Array) -> Array:
    """Per-tet ``weight_e * G_e G_e^T``, shape ``(t, 4, 4)`` (the scalar PD stiffness blocks)."""
    g = shape_gradients(dminv)
    return jnp.einsum("ajt,bjt,t->tab", g, g, weight)


def scatter_stress(model, dminv: Array, stress: Array) -> Array:
    """Nodal gradient ``sum_e P_e`` mapped through ``G_e``: ``(n, 3)`` from ``P`` ``(3, 3, t)``.

    ``stress`` is ``dE_e/dF_e`` (volume included); vertex ``a`` of tet ``e`` receives
    ``P_e g_a``.
    """
    g = shape_gradients(dminv)  # (4, 3, t)
    # Corner forces by coordinate, (3, 4 t) with column a * t + e, and a zero column that
    # the padding of the incidence table points at. Summing them per vertex by a gather
    # over that table is ~4x faster on CPU than XLA's scatter-add into (n, 3). Summing the
    # K gathered rows one by one is ~1.5x faster than XLA's reduce over them, and one
    # (K, n) gather per coordinate (not K gathers) keeps the reverse-mode transpose to one
    # scatter-add (~4x faster than K of them).
    s, g = rot.entries(stress), rot.entries(g)
    corner = jnp.stack([
        jnp.concatenate([s[i][0] * g[a][0] + s[i][1] * g[a][1] + s[i][2] * g[a][2]
                         for a in range(4)] + [jnp.zeros(1, stress.dtype)])
        for i in range(3)
    ])
    incidence = jnp.asarray(model.corner_incidence.T)  # (K, n)
    gathered = [jnp.unstack(corner[i][incidence]) for i in range(3)]  # K rows (n,) each
    return jnp.stack([sum(rows) for rows in gathered], axis=1)


#: ``(a, b)``, ``a <= b``, of a symmetric ``9 x 9`` matrix's packed upper triangle, row by row.
_UPPER = [(a, b) for a in range(9) for b in range(a, 9)]


def stress_derivative_product(model, dminv: Array, dpdf: Array) -> Callable[[Array], Array]:
    """The linear map ``v -> sum_e G_e^T (dP/dF)_e (G_e v)``: ``(n, 3) -> (n, 3)``.

    It is the Hessian-vector product of ``sum_e Psi_e(F_e)`` given each tet's stress
    derivative, i.e. :func:`scatter_stress` of ``dP/dF`` applied to
    :func:`deformation_gradient` of ``v``. With the native library (float64) the product
    runs as one compiled C++ loop over tets (:func:`softbody.native.tet_hessian_operator`),
    2.2x faster than the XLA loops used otherwise (0.35 vs 0.77 ms a call on the shared
    cantilever). ``dP/dF``, the second derivative of an energy, is symmetric, and is
    stored symmetrised (45 entries a tet).

    Arguments:
        dminv: ``(3, 3, t)`` inverse rest edge matrices.
        dpdf: ``(9, 3, 3, t)`` ``dP_ij / dF_kl`` indexed ``[3 k + l, i, j, e]``.

    Returns:
        A function of ``v`` ``(n, 3)`` returning ``(n, 3)``.
    """
    from softbody import native

    t = dpdf.shape[-1]
    if dpdf.dtype == jnp.float64 and native.available():
        m = dpdf.reshape(9, 9, t)
        packed = jnp.stack([m[a, a] if a == b else 0.5 * (m[a, b] + m[b, a]) for a, b in _UPPER])
        return native.tet_hessian_operator(packed, dminv.reshape(9, t), np.asarray(model.mesh.tets))

    def product(v):
        df = deformation_gradient(model, dminv, v).reshape(9, -1)
        dp = jnp.stack([sum(dpdf[k, i, j] * df[k] for k in range(9)) for i in range(3) for j in range(3)])
        return scatter_stress(model, dminv, dp.reshape(3, 3, -1))

    return product


#: Newton steps of :func:`volume_shift`: from its upper-bound start they reach round-off
#: in at most 10 on random ``F = I + 3 N(0, 1)`` (4 to 7 for strains below 30 %).
_SHIFT_STEPS = 12


@jax.custom_jvp
def volume_shift(s: Array, det_target: Array) -> Array:
    """The uniform shift ``c`` ``(t,)`` with ``det(S + c I) = D`` and ``S + c I`` positive definite.

    Arguments:
        s: symmetric ``(3, 3, t)`` (``sym(R^T F)``, whose eigenvalues are the signed
            singular values of ``F``); det_target: ``D > 0``, ``(t,)``.

    ``p(c) = det(S + c I) - D`` is a cubic in the invariants of ``S``, increasing and convex
    for ``c > -sigma_min``, where its root is unique: Newton's method from a point right of
    the root (``c0 = D^(1/3) - m + sqrt(2/3) |dev S|``, which makes ``sigma_min + c0 >=
    D^(1/3)``) decreases monotonically onto it. No eigendecomposition is needed. The
    derivative follows from the implicit function theorem:
    ``dc = (dD - cof(S + c I) : dS) / tr cof(S + c I)``.
    """
    eye = jnp.eye(3, dtype=s.dtype)[:, :, None]
    i1 = rot.trace(s)
    i2 = 0.5 * (i1 * i1 - rot.dot(s, s))
    i3 = rot.det3(s)
    dev = s - eye * (i1 / 3.0)
    c = jnp.cbrt(det_target) - i1 / 3.0 + jnp.sqrt(2.0 / 3.0 * rot.dot(dev, dev))

    def newton(_, c):
        p = ((c + i1) * c + i2) * c + i3 - det_target
        return c - p / ((3.0 * c + 2.0 * i1) * c + i2)

    # A loop, not unrolled: XLA's CPU fusion recomputes unrolled steps (4x slower, measured).
    return jax.lax.fori_loop(0, _SHIFT_STEPS, newton, c)


@volume_shift.defjvp
def _volume_shift_jvp(primals, tangents):
    s, det_target = primals
    ds, dd = tangents
    c = volume_shift(s, det_target)
    cof = rot._cofactor(s + c * jnp.eye(3, dtype=s.dtype)[:, :, None])
    return c, (dd - rot.dot(cof, ds)) / rot.trace(cof)


def corotated(f: Array, r: Array, volume: Array, w_s: Array, w_v: Array, target=3.0) -> tuple[Array, Array]:
    """Corotated + volume energy per tet ``(t,)`` and its stress ``dE/dF`` ``(3, 3, t)``.

    The volume term is ``V w_v / 2 |F - P_v(F)|^2 = 3/2 V w_v c^2`` with
    ``P_v(F) = F + c R`` the shift of all signed singular values by ``c`` onto
    ``det = D`` (:func:`volume_shift`; see :mod:`softbody.material`). Its stress is
    ``-3 V w_v c R cof(S + c I) / tr cof(S + c I)`` with ``S = sym(R^T F)``.

    Arguments:
        f: deformation gradients ``(3, 3, t)``; r: their rotations ``(3, 3, t)`` (the
            maximisers of ``tr(R^T F)``); volume, w_s, w_v: ``(t,)``.
        target: ``3 s``, where the volume term aims at ``det F = s^3``: 3 (rest volume),
            or ``(t,)``.
    """
    d = f - r
    a = rot.matmul(rot.transpose(r), f)
    s = 0.5 * (a + rot.transpose(a))
    det_target = jnp.broadcast_to((jnp.asarray(target, f.dtype) / 3.0) ** 3, volume.shape)
    c = volume_shift(s, det_target)
    cof = rot._cofactor(s + c * jnp.eye(3, dtype=f.dtype)[:, :, None])
    energy = volume * (0.5 * w_s * rot.dot(d, d) + 1.5 * w_v * c * c)
    stress = volume * (w_s * d - (3.0 * w_v * c / rot.trace(cof)) * rot.matmul(r, cof))
    return energy, stress


def strain_rate_damping(f: Array, f_n: Array, r_n: Array, volume: Array, w_b: Array, h: float):
    """Stiffness-proportional damping energy ``(t,)`` and stress ``(3, 3, t)``.

    ``V beta w_s / (2 h) |sym(R_n^T (F - F_n))|^2``: see :mod:`softbody.material`.
    """
    e = rot.matmul(rot.transpose(r_n), f - f_n)
    sym = 0.5 * (e + rot.transpose(e))
    energy = volume * w_b / (2 * h) * rot.dot(sym, sym)
    stress = (volume * w_b / h) * rot.matmul(r_n, sym)
    return energy, stress

"""Per-tet kinematics and the elastic PD energy (see :mod:`softbody.material`).

Matrices are batched in structure-of-arrays layout ``(3, 3, t)``. ``G_e`` is the ``4 x 3``
gradient operator of tet ``e``'s linear shape functions (rows ``-sum_k Dm^-1[k]`` for
vertex 0 and ``Dm^-1[k]`` for vertex ``k + 1``), so that ``F_e = sum_a x_a g_a^T``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

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
    xe = x[jnp.asarray(model.mesh.tets)]  # (t, 4, 3)
    return jnp.transpose(xe[:, 1:, :] - xe[:, :1, :], (2, 1, 0))


def deformation_gradient(model, dminv: Array, x: Array) -> Array:
    """Deformation gradients ``F = Ds Dm^-1``, shape ``(3, 3, t)``, of positions ``x`` ``(n, 3)``."""
    return rot.matmul(_edges(model, x), dminv)


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
    per_vertex = jnp.einsum("ijt,ajt->tai", stress, g)  # (t, 4, 3)
    return jnp.zeros((model.n_vertices, 3), stress.dtype).at[jnp.asarray(model.mesh.tets)].add(per_vertex)


def corotated(f: Array, r: Array, volume: Array, w_s: Array, w_v: Array, target=3.0) -> tuple[Array, Array]:
    """Corotated + volume energy per tet ``(t,)`` and its stress ``dE/dF`` ``(3, 3, t)``.

    Arguments:
        f: deformation gradients ``(3, 3, t)``; r: their rotations ``(3, 3, t)``;
        volume, w_s, w_v: ``(t,)``.
        target: the volume term's target ``tr(R^T F)``: 3 (rest volume), or ``(t,)``.
    """
    d = f - r
    c = rot.dot(r, f) - target  # tr(R^T F) - target
    energy = volume * (0.5 * w_s * rot.dot(d, d) + w_v / 6.0 * c * c)
    stress = volume * (w_s * d + (w_v * c / 3.0) * r)
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

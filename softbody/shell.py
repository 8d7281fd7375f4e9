"""Thin membranes: triangle elements of the step objective (a
:class:`~softbody._interfaces.VertexTerm`), e.g. a fabric layer bonded to a soft body's
surface.

Per triangle of rest area ``A`` and thickness ``t``, plane stress with physical weights::

    A t [mu |F - R|^2 + lam*/2 (tr(R^T F) - 2)^2],    lam* = E nu / (1 - nu^2)

``F`` ``(3, 2)`` maps the rest triangle's own 2-D frame to space and ``R`` is its polar
factor (orthonormal columns). With ``C = F^T F``, ``tr(R^T F) = tr sqrt(C) =
sqrt(tr C + 2 sqrt(det C))`` and ``|F - R|^2 = tr C - 2 tr sqrt(C) + 2``: closed forms, no
SVD, finite with finite derivatives at rest (``C = I``). For a stretch without shear
(``F = R S``, ``S`` diagonal) the energy is exactly that of linear plane-stress elasticity
in the Biot strain ``S - I``, so uniform stretches pass the patch test to round-off; small
strains of any kind agree with plane-stress linear elasticity to first order.

Each triangle adds the ``3 x 3`` block ``A t (2 mu + 2 lam*) G G^T`` (``G`` its shape
gradients) to the prefactored PD matrix: ``2 mu`` for the rotation term, and ``2 lam*``
bounds the area term's rank-one Hessian (``|R|^2 = 2``), as ``3 lambda`` does for a tet's
volume term.

An areal density gives each vertex a third of its triangles' mass (inertia and weight).

Not yet here: bending, shells without a tet body, contact of shell faces.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import VertexTerm
from softbody._types import SceneError
from softbody.meshing import TetMesh

Array = jax.Array


class MembraneParams(eqx.Module):
    """Design parameters of a membrane: Young's modulus ``E`` (Pa), Poisson's ratio ``nu``,
    thickness (m) and areal density (kg/m^2), scalars."""

    E: Array
    nu: Array
    thickness: Array
    areal_density: Array


def _rest_frames(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's shape gradients ``(m, 3, 2)`` (``F = sum_a x_a g_a^T`` maps its own
    orthonormal rest frame to space) and its area ``(m,)``."""
    p = points[triangles]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    normal = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(normal, axis=1)
    u = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    w = np.cross(normal / (2 * area)[:, None], u)
    dm = np.stack([np.stack([np.sum(u * e1, 1), np.sum(u * e2, 1)], 1),
                   np.stack([np.sum(w * e1, 1), np.sum(w * e2, 1)], 1)], 1)
    dminv = np.linalg.inv(dm)
    return np.concatenate([-dminv.sum(axis=1, keepdims=True), dminv], axis=1), area


@dataclass(frozen=True, eq=False)
class Membrane(VertexTerm):
    """A membrane on triangles of a body's vertices (the module docstring's energy).

    Build it with :meth:`on` from a mesh and its triangles; give it to the body,
    ``SoftBody(mesh, material, actuators=[membrane])`` (its indices then follow the body
    into the scene), or to ``build(..., terms=[membrane])`` on a scene's indices.

    Attributes:
        triangles: ``(m, 3)`` vertex indices.
        gradients: ``(m, 3, 2)`` shape gradients: ``F = sum_a x_a g_a^T`` (each triangle's own
            rest frame).
        area: ``(m,)`` rest areas, m^2.
        E, nu, thickness, areal_density: initial design parameters
            (``params.actuators[i]``, :class:`MembraneParams`): Pa, -, m, kg/m^2. A
            membrane built with areal density 0 has no mass (and no gradient with respect
            to it); otherwise each triangle adds a third of its mass to each vertex.
    """

    triangles: np.ndarray
    gradients: np.ndarray
    area: np.ndarray
    E: float
    nu: float
    thickness: float
    areal_density: float = 0.0

    mesh_indices: ClassVar = {"triangles": "vertices"}

    @classmethod
    def on(cls, mesh, triangles, *, E: float, nu: float, thickness: float,
           areal_density: float = 0.0) -> "Membrane":
        """A membrane on ``triangles`` of ``mesh``, flat or curved at rest as the mesh is.

        Arguments:
            mesh: the body's :class:`~softbody.meshing.TetMesh`, or its points ``(n, 3)``
                (the membrane's rest shape).
            triangles: ``(m, 3)`` vertex indices, or the name of a region of the mesh whose
                faces they are.
            E: Young's modulus, Pa (> 0); nu: Poisson's ratio in ``[0, 0.5)``; thickness: m (> 0);
                areal_density: kg/m^2 (>= 0; 0: a membrane without mass).

        Raises:
            SceneError: an unknown region or one without faces, indices outside the mesh,
                a degenerate (zero-area) triangle, or non-physical material values.
        """
        regions = mesh.regions if isinstance(mesh, TetMesh) else {}
        points = np.asarray(mesh.points if isinstance(mesh, TetMesh) else mesh, np.float64)
        if isinstance(triangles, str):
            if triangles not in regions:
                raise SceneError(f"Membrane: no region {triangles!r} in the mesh; it has {sorted(regions)}")
            name, triangles = triangles, regions[triangles].faces
            if len(triangles) == 0:
                raise SceneError(f"Membrane: region {name!r} names no triangles (faces); select a surface region")
        tri = np.asarray(triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or len(tri) == 0 or not np.issubdtype(tri.dtype, np.integer):
            raise SceneError(f"Membrane: triangles must be (m, 3) vertex indices with m >= 1, got {tri.dtype} of "
                             f"shape {tri.shape}")
        if tri.min() < 0 or tri.max() >= len(points):
            raise SceneError(f"Membrane: triangle indices must lie in [0, {len(points)})")
        if not (np.isfinite(E) and E > 0 and np.isfinite(thickness) and thickness > 0 and 0 <= nu < 0.5
                and np.isfinite(areal_density) and areal_density >= 0):
            raise SceneError(f"Membrane needs E > 0, thickness > 0, 0 <= nu < 0.5 and areal_density >= 0, got E={E}, "
                             f"nu={nu}, thickness={thickness}, areal_density={areal_density}")
        scale = np.ptp(points[tri.ravel()], axis=0).max()
        doubled = np.linalg.norm(np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]]),
                                 axis=1)
        bad = np.flatnonzero(doubled <= 1e-12 * scale**2)
        if len(bad):
            raise SceneError(f"Membrane: {len(bad)} degenerate (zero-area) triangles, e.g. {tri[bad[0]].tolist()}; "
                             "remove them from the selection")
        gradients, area = _rest_frames(points, tri)
        return cls(tri.astype(np.int32), gradients, area, float(E), float(nu), float(thickness), float(areal_density))

    def init_params(self) -> MembraneParams:
        return MembraneParams(E=jnp.asarray(self.E), nu=jnp.asarray(self.nu), thickness=jnp.asarray(self.thickness),
                              areal_density=jnp.asarray(self.areal_density))

    def prepare(self, model, params: MembraneParams, dminv, volume) -> tuple:
        """``(mu t A (m,), lam* t A (m,), rho_A A (m,))``: the weights of the two terms and
        the mass per triangle."""
        mu = params.E / (2.0 * (1.0 + params.nu))
        lam = params.E * params.nu / (1.0 - params.nu**2)
        area = jnp.asarray(self.area)
        return mu * area * params.thickness, lam * area * params.thickness, params.areal_density * area

    def mass(self, prep):
        """A third of each triangle's mass on each of its vertices (``None`` without density)."""
        if self.areal_density == 0.0:
            return None
        return jnp.broadcast_to(prep[2][:, None] / 3.0, self.triangles.shape)

    def stencil(self) -> np.ndarray:
        return self.triangles

    def blocks(self, prep) -> Array:
        mu_at, lam_at, _ = prep
        g = jnp.asarray(self.gradients)
        return (2.0 * mu_at + 2.0 * lam_at)[:, None, None] * jnp.einsum("mai,mbi->mab", g, g)

    def energy_and_gradient(self, x, prep, activation):
        mu_at, lam_at, _ = prep
        g = jnp.asarray(self.gradients)
        tri = jnp.asarray(self.triangles)

        def energy(x):
            f = jnp.einsum("mak,mai->mki", x[tri], g)  # (m, 3, 2)
            c = jnp.einsum("mki,mkj->mij", f, f)
            tr_c = c[:, 0, 0] + c[:, 1, 1]
            det_c = jnp.maximum(c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] ** 2, 0.0)
            tr_s = jnp.sqrt(tr_c + 2.0 * jnp.sqrt(det_c))
            return jnp.sum(mu_at * (tr_c - 2.0 * tr_s + 2.0) + 0.5 * lam_at * (tr_s - 2.0) ** 2)

        return jax.value_and_grad(energy)(x)

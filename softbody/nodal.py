"""Nodally averaged volume: linear tets that do not lock for nearly incompressible materials.

Linear tets with a per-tet volume term lock as ``nu -> 0.5``: a gmsh mesh has 3.5 to 6 tets
per vertex, and asking every one to keep its volume leaves almost no motion (a silicone
beam at ``nu = 0.499`` sags a quarter of what it should, ``softbody bench locking``). The average
nodal pressure element (Bonet and Burton 1998) asks each *vertex patch* (the tets around a
vertex) to keep its volume instead: about ``n`` constraints for ``3 n`` unknowns.

Per vertex ``v`` with patch rest volume ``V_v0 = sum_{e ni v} V_e0 / 4``::

    J_v = sum_{e ni v} V_e(x) / 4 / V_v0,       E_vol = sum_v kappa_v V_v0 / 2 (J_v - 1)^2

``V_e(x)`` the current volume of tet ``e``, ``kappa_v V_v0 = sum_{e ni v} lambda_e V_e0 / 4``
(Lame's ``lambda = w_v / 3`` of each tet's material). The tets keep their corotated term
``w_s / 2 |F - R|^2 = mu |eps|^2 + O(|H|^3)``, so near rest the energy is linear
elasticity's ``mu |eps|^2 + lambda / 2 tr(eps)^2`` with the volume change measured per patch.
The term is a :class:`~softbody._interfaces.VolumeElement`: the tets it covers lose their
own volume term. Its stress on a tet is ``V_e0 pbar_e cof F_e`` with ``pbar_e`` the mean of
its four vertices' pressures ``kappa_v (J_v - 1)``: the averaged nodal pressure.

In the prefactored PD matrix each covered tet keeps the block its own volume term had,
``gamma 3 lambda V_e0 G_e G_e^T`` (``gamma`` the step's ``volume_weight``: 1 for plain PD
and with contact, 0.2 for L-BFGS alone). With ``gamma = 1`` it majorises the patch term's
Hessian at rest: by Cauchy-Schwarz, ``(sum_e dV_e / 4)^2 <= V_v0 sum_e dV_e^2 / (4 V_e0)``,
so ``sum_v kappa_v / V_v0 (dV_v)^2 <= sum_e lambda_e dV_e^2 / V_e0``, the per-tet volume
Hessian, which ``3 lambda V_e0 G_e G_e^T`` bounds. The patch Hessian couples more than
four vertices, so it cannot enter the matrix as it is: the matrix is the one of the locking
tets, and the iteration counts at ``nu -> 0.5`` stay those of stiff volume terms.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import VolumeElement
from softbody._types import SceneError
from softbody.elastic import local_matrices
from softbody.meshing import TetMesh

Array = jax.Array

@dataclass(frozen=True, eq=False)
class NodalVolume(VolumeElement):
    """The nodally averaged volume energy of the module docstring on some tets of a body.

    Build it with :meth:`on` and give it to the body,
    ``SoftBody(mesh, material, actuators=[NodalVolume.on(mesh)])`` (its indices then follow
    the body into the scene), or to ``build(..., terms=[...])`` on a scene's indices. Its
    weights come from the materials of its tets (``params.E``, ``params.nu``: it has no
    design parameters of its own).

    Attributes:
        tets: ``(m,)`` tet indices covered.
        corners: ``(m, 4)`` their vertex indices.
        local: ``(m, 4)`` the corners numbered within the term's vertices (``0 .. p - 1``).
        n_local: ``p``, the number of distinct vertices of the covered tets.
    """

    tets: np.ndarray
    corners: np.ndarray
    local: np.ndarray
    n_local: int

    mesh_indices: ClassVar = {"tets": "tets", "corners": "vertices"}

    @classmethod
    def on(cls, mesh: TetMesh, tets=None) -> NodalVolume:
        """The term on ``tets`` of ``mesh``.

        Arguments:
            mesh: the body's :class:`~softbody.meshing.TetMesh`.
            tets: ``None`` (every tet), the name of a region of the mesh (its tets), or
                ``(m,)`` tet indices.

        Returns:
            A :class:`NodalVolume`.

        Raises:
            SceneError: a mesh that is not a ``TetMesh``, an unknown region or one without
                tets, or indices that are not distinct tet indices of the mesh.
        """
        if not isinstance(mesh, TetMesh):
            raise SceneError(f"NodalVolume.on needs the body's TetMesh, got {type(mesh).__name__}")
        if tets is None:
            idx = np.arange(len(mesh.tets))
        elif isinstance(tets, str):
            if tets not in mesh.regions:
                raise SceneError(f"NodalVolume: no region {tets!r} in the mesh; it has {sorted(mesh.regions)}")
            idx = np.asarray(mesh.regions[tets].tets)
            if idx.size == 0:
                raise SceneError(f"NodalVolume: region {tets!r} has no tets; select a volume region")
        else:
            idx = np.asarray(tets)
            if idx.ndim != 1 or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer):
                raise SceneError(f"NodalVolume: tets must be (m,) tet indices with m >= 1, got {idx.dtype} of "
                                 f"shape {idx.shape}")
            if idx.min() < 0 or idx.max() >= len(mesh.tets) or len(np.unique(idx)) != idx.size:
                raise SceneError(f"NodalVolume: tets must be distinct indices in [0, {len(mesh.tets)})")
        corners = np.asarray(mesh.tets)[idx].astype(np.int32)
        vertices, local = np.unique(corners, return_inverse=True)
        return cls(idx.astype(np.int32), corners, local.reshape(corners.shape).astype(np.int32), int(vertices.size))

    def prepare(self, model, params, dminv, volume, w_v=None) -> tuple:
        """``(rest (p,), stiffness (p,), blocks (m, 4, 4))``: each vertex's patch rest volume
        ``V_v0``, its ``kappa_v V_v0`` and the PD blocks, from the scene's inverse edge
        matrices ``(3, 3, t)``, tet volumes ``(t,)`` and volume weights ``w_v = 3 lambda`` ``(t,)``."""
        idx = jnp.asarray(self.tets)
        v0, lam = volume[idx], w_v[idx] / 3.0
        local = jnp.asarray(self.local)
        rest = jnp.zeros(self.n_local, v0.dtype).at[local].add(jnp.broadcast_to(v0[:, None] / 4.0, local.shape))
        stiff = jnp.zeros(self.n_local, v0.dtype).at[local].add(jnp.broadcast_to((lam * v0)[:, None] / 4.0,
                                                                                   local.shape))
        blocks = local_matrices(dminv[:, :, idx], model.step.volume_weight * 3.0 * lam * v0)
        return rest, stiff, blocks

    def stencil(self) -> np.ndarray:
        """The covered tets' corners ``(m, 4)``."""
        return self.corners

    def blocks(self, prep) -> Array:
        """``(m, 4, 4)``: ``gamma 3 lambda V_e0 G_e G_e^T`` per covered tet."""
        return prep[2]

    def patch_ratios(self, x, prep) -> Array:
        """``(p,)``: each patch's volume ratio ``J_v`` at positions ``x`` ``(n, 3)``."""
        xe = x[jnp.asarray(self.corners)]  # (m, 4, 3)
        e = xe[:, 1:, :] - xe[:, :1, :]  # (m, 3, 3), rows: edges
        vol = jnp.einsum("mi,mi->m", e[:, 0], jnp.cross(e[:, 1], e[:, 2])) / 6.0
        local = jnp.asarray(self.local)
        patch = jnp.zeros(self.n_local, x.dtype).at[local].add(jnp.broadcast_to(vol[:, None] / 4.0, local.shape))
        return patch / prep[0]

    def energy(self, x, prep) -> Array:
        """The volume energy ``E_vol`` (scalar) at positions ``x`` ``(n, 3)``."""
        return 0.5 * jnp.sum(prep[1] * (self.patch_ratios(x, prep) - 1.0) ** 2)

    def energy_and_gradient(self, x, prep, activation):
        """``(E_vol, dE_vol/dx (n, 3))`` at positions ``x`` ``(n, 3)``."""
        return jax.value_and_grad(self.energy)(x, prep)

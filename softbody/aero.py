"""Air drag and wind on triangles (a :class:`~softbody._interfaces.DissipationTerm`): cloth
falling, flags and sails, a sheet blown against an obstacle.

The force on each triangle of rest area ``A`` is the form of the cloth simulators since
Narain et al. (arcsim), with ``u`` the triangle's velocity relative to the air (the mean of
its vertices' velocities minus the wind ``w``), ``n`` its unit normal, ``u_n = u . n`` and
``u_t = u - u_n n``::

    f = -A (rho |u_n| u_n n + c u_t)

a pressure drag across the sheet (air density ``rho``, kg/m^3) and a viscous drag along
it (coefficient ``c``, N s/m^3), each vertex taking a third. It derives from the
dissipation potential ``D(u) = A (rho |u_n|^3 / 3 + c |u_t|^2 / 2)``, convex in the
velocities with the normal held, so an implicit step adds ``h D`` to its objective with
the normals of the step's start (:class:`~softbody._interfaces.DissipationTerm`): a flat
sheet falling in still air reaches the terminal speed ``sqrt(rho_A g / rho)`` exactly (at
its steady state the step balances weight and drag), and the step stays as well posed as
without air. The rest area stands for the current one (cloth barely stretches).

``rho``, ``c`` and ``w`` are differentiable design parameters (``params.actuators[i]``,
:class:`DragParams`): a wind can be identified from a sheet's motion, or optimised.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import DissipationTerm
from softbody._types import SceneError
from softbody.shell import triangle_selection

Array = jax.Array

#: Air at 20 degrees C and sea level, kg/m^3.
AIR_DENSITY = 1.204


class DragParams(eqx.Module):
    """Design parameters of a drag term: air density ``density`` (kg/m^3, scalar), the
    viscous coefficient along the sheet ``friction`` (N s/m^3, scalar) and the wind
    velocity ``wind`` (m/s, ``(3,)``)."""

    density: Array
    friction: Array
    wind: Array


@dataclass(frozen=True, eq=False)
class Drag(DissipationTerm):
    """Air drag and wind on triangles of a body's vertices (the module docstring's force).

    Build it with :meth:`on`; give it to the body, ``SoftBody(mesh, material,
    actuators=[drag])`` (its indices then follow the body into the scene), or to
    ``build(..., terms=[drag])`` on a scene's indices (a :func:`~softbody.shell.shell_body`
    alone: ``build(sheet, terms=[Drag.on(mesh, "sheet", wind=...)])``).

    Attributes:
        triangles: ``(m, 3)`` vertex indices; their order sets the normal ``n`` (either side
            gives the same force).
        area: ``(m,)`` rest areas, m^2.
        density, friction, wind: initial design parameters (``params.actuators[i]``,
            :class:`DragParams`): kg/m^3, N s/m^3, m/s ``(3,)``.
    """

    triangles: np.ndarray
    area: np.ndarray
    density: float
    friction: float
    wind: tuple[float, float, float]

    mesh_indices: ClassVar = {"triangles": "vertices"}

    @classmethod
    def on(cls, mesh, triangles, *, density: float = AIR_DENSITY, friction: float = 0.0,
           wind=(0.0, 0.0, 0.0)) -> Drag:
        """Drag on ``triangles`` of ``mesh``.

        Arguments:
            mesh: the body's :class:`~softbody.meshing.TetMesh`, or its points ``(n, 3)``.
            triangles: ``(m, 3)`` vertex indices, or the name of a region of the mesh whose
                faces they are (a sheet from :mod:`softbody.meshing.sheet`: ``"sheet"``; a
                solid's outside: its surface triangles, ``mesh.surface``).
            density: air density, kg/m^3 (>= 0; default: air at 20 C, 1.204).
            friction: viscous drag along the sheet, N s/m^3 (>= 0; default 0).
            wind: the air's velocity, m/s, three numbers.

        Raises:
            SceneError: what :func:`softbody.shell.triangle_selection` refuses, a negative or
                non-finite density or friction, or a wind that is not three finite numbers.
        """
        wind_a = np.asarray(wind, np.float64) if np.ndim(wind) == 1 else np.full(0, np.nan)
        if wind_a.shape != (3,) or not np.all(np.isfinite(wind_a)):
            raise SceneError(f"Drag: wind must be three finite numbers (m/s), got {wind!r}")
        if not (np.isfinite(density) and density >= 0 and np.isfinite(friction) and friction >= 0):
            raise SceneError(f"Drag needs density >= 0 (kg/m^3; air: {AIR_DENSITY}) and friction >= 0 (N s/m^3), "
                             f"got density={density}, friction={friction}")
        points, tri = triangle_selection(mesh, triangles, "Drag")
        p = points[tri]
        area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
        return cls(tri.astype(np.int32), area, float(density), float(friction), tuple(float(w) for w in wind_a))

    def init_params(self) -> DragParams:
        return DragParams(density=jnp.asarray(self.density), friction=jnp.asarray(self.friction),
                          wind=jnp.asarray(self.wind))

    def prepare(self, model, params: DragParams, dminv, volume) -> DragParams:
        """The design parameters themselves."""
        return params

    def dissipation(self, v, x, prep: DragParams, activation):
        tri = jnp.asarray(self.triangles)
        area = jnp.asarray(self.area)
        p = x[tri]
        normal = jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normal = normal / jnp.linalg.norm(normal, axis=1, keepdims=True)
        u = jnp.mean(v[tri], axis=1) - prep.wind  # (m, 3) relative to the air
        u_n = jnp.sum(u * normal, axis=1)
        u_t = u - u_n[:, None] * normal
        d = area * (prep.density * jnp.abs(u_n) ** 3 / 3.0 + 0.5 * prep.friction * jnp.sum(u_t * u_t, axis=1))
        face = area[:, None] * (prep.density * (jnp.abs(u_n) * u_n)[:, None] * normal + prep.friction * u_t)
        grad = jnp.zeros_like(v).at[tri].add(jnp.broadcast_to(face[:, None, :] / 3.0, tri.shape + (3,)))
        return jnp.sum(d), grad

"""Thin sheets: triangle elements of the step objective (each a
:class:`~softbody._interfaces.VertexTerm`): a fabric layer bonded to a soft body's surface,
or cloth and thin shells on their own.

* :class:`Membrane`: in-plane stretching and shearing (below), with the sheet's mass.
* :class:`Bending`: quadratic bending on the interior edges (hinges), with the plate's
  bending stiffness ``D = E t^3 / (12 (1 - nu^2))`` (see the class for its limits).
* :func:`shell_body`: a body that is only a sheet (a mesh of triangles without tets, e.g.
  from :mod:`softbody.meshing.sheet`), with both terms; it steps with the static solve and
  the implicit integrators like any other body.

Per triangle of rest area ``A`` and thickness ``t``, the membrane's plane stress with
physical weights::

    A t [mu |F - R|^2 + lam*/2 (tr(R^T F) - 2)^2],    lam* = E nu / (1 - nu^2)

``F`` ``(3, 2)`` maps the rest triangle's own 2-D frame to space and ``R`` is its polar
factor (orthonormal columns). With ``C = F^T F``, ``tr(R^T F) = tr sqrt(C) =
sqrt(tr C + 2 sqrt(det C))`` and ``|F - R|^2 = tr C - 2 tr sqrt(C) + 2``: closed forms, no
SVD, finite with finite derivatives at rest (``C = I``). For a stretch without shear
(``F = R S``, ``S`` diagonal) the energy is exactly that of linear plane-stress elasticity
in the Biot strain ``S - I``, so uniform stretches pass the patch test to round-off; small
strains of any kind agree with plane-stress linear elasticity to first order.

Each triangle adds the ``3 x 3`` block ``A t (2 mu + 2 w lam*) G G^T`` (``G`` its shape
gradients) to the prefactored PD matrix: ``2 mu`` for the rotation term, and ``2 lam*``
bounds the area term's rank-one Hessian (``|R|^2 = 2``), as ``3 lambda`` does for a tet's
volume term, and takes the same scale ``w`` (the scene's ``model.step.volume_weight``:
L-BFGS in plain coordinates learns the rest; measured on a 1 m cloth falling from two
corners, 543-1195 iterations a step at w = 0.2 against 662-2033 at 1).

An areal density gives each vertex a third of its triangles' mass (inertia and weight).

The PD matrix is one scalar matrix for the three axes, so a flat sheet's membrane blocks
also weigh on its out-of-plane motion: a static solve of a sheet whose sag is resisted by
bending alone converges slowly (thousands of iterations for a stiff plate); dynamics at
cloth time steps converge in a few iterations.

Air drag and wind on a sheet: :class:`softbody.aero.Drag`. Not yet here: contact of sheet
faces (with themselves or other bodies).
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


def triangle_selection(mesh, triangles, owner: str) -> tuple[np.ndarray, np.ndarray]:
    """A term's triangles, checked: the rest points ``(n, 3)`` float64 and the triangles
    ``(m, 3)`` int64.

    Arguments:
        mesh: a :class:`~softbody.meshing.TetMesh`, or its points ``(n, 3)``.
        triangles: ``(m, 3)`` vertex indices, or the name of a region of the mesh whose faces
            they are.
        owner: the term's name, which starts every message.

    Raises:
        SceneError: an unknown region or one without faces, an empty selection, indices
            that are not ``(m, 3)`` integers inside the mesh, or a degenerate (zero-area)
            triangle.
    """
    regions = mesh.regions if isinstance(mesh, TetMesh) else {}
    points = np.asarray(mesh.points if isinstance(mesh, TetMesh) else mesh, np.float64)
    if isinstance(triangles, str):
        if triangles not in regions:
            raise SceneError(f"{owner}: no region {triangles!r} in the mesh; it has {sorted(regions)}")
        name, triangles = triangles, regions[triangles].faces
        if len(triangles) == 0:
            raise SceneError(f"{owner}: region {name!r} names no triangles (faces); select a surface region")
    tri = np.asarray(triangles)
    if tri.size == 0:
        raise SceneError(f"{owner}: the triangle selection names no triangles (shape {tri.shape}); give (m, 3) "
                         "vertex indices with m >= 1 or a surface region's name, e.g. "
                         "mesh.regions[name].faces")
    if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
        raise SceneError(f"{owner}: triangles must be (m, 3) vertex indices with m >= 1, got {tri.dtype} of "
                         f"shape {tri.shape}")
    if tri.min() < 0 or tri.max() >= len(points):
        raise SceneError(f"{owner}: triangle indices must lie in [0, {len(points)})")
    scale = np.ptp(points[tri.ravel()], axis=0).max()
    doubled = np.linalg.norm(np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]]),
                             axis=1)
    bad = np.flatnonzero(doubled <= 1e-12 * scale**2)
    if len(bad):
        raise SceneError(f"{owner}: {len(bad)} degenerate (zero-area) triangles, e.g. {tri[bad[0]].tolist()}; "
                         "remove them from the selection")
    return points, tri.astype(np.int64)


def _check_sheet(triangles: np.ndarray) -> None:
    """Raise unless the triangles ``(m, 3)`` (each of non-zero area) are distinct and no edge
    belongs to more than two of them (a manifold sheet, with or without boundary)."""
    tri = np.asarray(triangles, np.int64)
    _, first, counts = np.unique(np.sort(tri, axis=1), axis=0, return_index=True, return_counts=True)
    if counts.max() > 1:
        twice = tri[first[np.argmax(counts)]]
        raise SceneError(f"Membrane: {int(np.sum(counts > 1))} triangles are given more than once, e.g. "
                         f"{twice.tolist()} ({counts.max()} times), which would count their stiffness and mass "
                         "as often; give each triangle once")
    _check_manifold(tri, "Membrane: ", "give each sheet meeting there its own Membrane (and Bending)")


def _check_manifold(tri: np.ndarray, owner: str, fix: str) -> None:
    """Raise a :class:`SceneError` starting with ``owner`` and ending with ``fix`` where an edge
    belongs to more than two of the triangles ``tri`` ``(m, 3)``."""
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    key, counts = np.unique(edges, axis=0, return_counts=True)
    if counts.max(initial=0) > 2:
        raise SceneError(f"{owner}the triangles are not a manifold surface: {int(np.sum(counts > 2))} edges are "
                         f"shared by more than two triangles, e.g. edge {key[np.argmax(counts)].tolist()} by "
                         f"{counts.max()}; {fix}")


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
           areal_density: float = 0.0) -> Membrane:
        """A membrane on ``triangles`` of ``mesh``, flat or curved at rest as the mesh is.

        Arguments:
            mesh: the body's :class:`~softbody.meshing.TetMesh`, or its points ``(n, 3)``
                (the membrane's rest shape).
            triangles: ``(m, 3)`` vertex indices, or the name of a region of the mesh whose
                faces they are.
            E: Young's modulus, Pa (> 0); nu: Poisson's ratio in ``[0, 0.5)``; thickness: m (> 0);
                areal_density: kg/m^2 (>= 0; 0: a membrane without mass).

        Raises:
            SceneError: an unknown region or one without faces, an empty selection, indices
                outside the mesh, a degenerate (zero-area) triangle, a triangle given twice, an
                edge shared by more than two triangles (a non-manifold sheet), or non-physical
                material values (e.g. thickness <= 0).
        """
        if not (np.isfinite(E) and E > 0 and np.isfinite(thickness) and thickness > 0 and 0 <= nu < 0.5
                and np.isfinite(areal_density) and areal_density >= 0):
            raise SceneError(f"Membrane needs E > 0, thickness > 0, 0 <= nu < 0.5 and areal_density >= 0, got E={E}, "
                             f"nu={nu}, thickness={thickness}, areal_density={areal_density}")
        points, tri = triangle_selection(mesh, triangles, "Membrane")
        _check_sheet(tri)
        gradients, area = _rest_frames(points, tri)
        return cls(tri.astype(np.int32), gradients, area, float(E), float(nu), float(thickness), float(areal_density))

    def init_params(self) -> MembraneParams:
        return MembraneParams(E=jnp.asarray(self.E), nu=jnp.asarray(self.nu), thickness=jnp.asarray(self.thickness),
                              areal_density=jnp.asarray(self.areal_density))

    def prepare(self, model, params: MembraneParams, dminv, volume) -> tuple:
        """``(mu t A (m,), lam* t A (m,), rho_A A (m,), w)``: the weights of the two terms,
        the mass per triangle, and the scale ``w`` of the area term's blocks in the PD matrix
        (the scene's volume-term scale, ``model.step.volume_weight``: 0.2 for L-BFGS in
        plain coordinates, 1 where contact or a skeleton needs the matrix to bound the
        Hessian; 1 without a model)."""
        mu = params.E / (2.0 * (1.0 + params.nu))
        lam = params.E * params.nu / (1.0 - params.nu**2)
        area = jnp.asarray(self.area)
        weight = 1.0 if model is None else model.step.volume_weight
        return mu * area * params.thickness, lam * area * params.thickness, params.areal_density * area, weight

    def mass(self, prep):
        """A third of each triangle's mass on each of its vertices (``None`` without density)."""
        if self.areal_density == 0.0:
            return None
        return jnp.broadcast_to(prep[2][:, None] / 3.0, self.triangles.shape)

    def stencil(self) -> np.ndarray:
        return self.triangles

    def blocks(self, prep) -> Array:
        mu_at, lam_at, _, weight = prep
        g = jnp.asarray(self.gradients)
        return (2.0 * mu_at + 2.0 * weight * lam_at)[:, None, None] * jnp.einsum("mai,mbi->mab", g, g)

    def energy_and_gradient(self, x, prep, activation):
        mu_at, lam_at = prep[:2]
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


class BendingParams(eqx.Module):
    """Design parameters of a bending term: Young's modulus ``E`` (Pa), Poisson's ratio
    ``nu`` and thickness (m), scalars; the bending stiffness is
    ``D = E t^3 / (12 (1 - nu^2))``."""

    E: Array
    nu: Array
    thickness: Array


def hinges(triangles: np.ndarray) -> np.ndarray:
    """The interior edges of a triangle mesh with their two triangles' opposite vertices.

    Arguments:
        triangles: ``(m, 3)`` vertex indices.

    Returns:
        ``(e, 4)`` int: per interior edge ``(x0, x1, x2, x3)``, the edge ``x0 x1`` shared by
        the triangles ``x0 x1 x2`` and ``x0 x1 x3`` (edges of one triangle, the boundary,
        are left out).

    Raises:
        SceneError: an edge shared by more than two triangles (a non-manifold mesh).
    """
    tri = np.asarray(triangles, np.int64)
    sides = np.concatenate([tri[:, [0, 1, 2]], tri[:, [1, 2, 0]], tri[:, [2, 0, 1]]])  # (edge, opposite)
    key = np.sort(sides[:, :2], axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    _check_manifold(tri, "", "bend each sheet separately")
    order = np.argsort(inverse, kind="stable")
    pair = order[np.flatnonzero(counts[inverse[order]] == 2)].reshape(-1, 2)
    first, second = sides[pair[:, 0]], sides[pair[:, 1]]
    return np.stack([first[:, 0], first[:, 1], first[:, 2], second[:, 2]], axis=1)


def _cot(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The cotangent of each triangle ``a b c``'s angle at ``a``."""
    u, v = b - a, c - a
    return np.sum(u * v, axis=1) / np.linalg.norm(np.cross(u, v), axis=1)


def hinge_weights(points: np.ndarray, stencil: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cotangent weights of each hinge and its two triangles' area.

    ``sum_a k_a x_a`` vanishes for any flat placement of the hinge's four vertices and, for
    a hinge in the plane, equals ``|e|`` times the jump of the slope of an out-of-plane
    displacement across the edge.

    Arguments:
        points: ``(n, 3)`` rest positions; stencil: ``(e, 4)`` hinges (:func:`hinges`).

    Returns:
        ``(k (e, 4), area (e,))``: ``k = (c1 + c1', c0 + c0', -(c0 + c1), -(c0' + c1'))``,
        ``c0, c1`` the cotangents of triangle ``x0 x1 x2``'s angles at ``x0`` and ``x1``
        (primed: triangle ``x0 x1 x3``); ``area = A1 + A2``, m^2.
    """
    x0, x1, x2, x3 = (points[stencil[:, i]] for i in range(4))
    c0, c1 = _cot(x0, x1, x2), _cot(x1, x0, x2)
    d0, d1 = _cot(x0, x1, x3), _cot(x1, x0, x3)
    k = np.stack([c1 + d1, c0 + d0, -(c0 + c1), -(d0 + d1)], axis=1)
    area = 0.5 * (np.linalg.norm(np.cross(x1 - x0, x2 - x0), axis=1) + np.linalg.norm(np.cross(x1 - x0, x3 - x0),
                                                                                      axis=1))
    return k, area


@dataclass(frozen=True, eq=False)
class Bending(VertexTerm):
    """Quadratic bending of a sheet of triangles (Bergou et al. 2006): per interior edge
    (a hinge of two triangles, areas ``A1, A2``, cotangent weights ``k``
    (:func:`hinge_weights``))::

        D / (2 (A1 + A2)) (|sum_a k_a x_a| - |sum_a k_a X_a|)^2,    D = E t^3 / (12 (1 - nu^2))

    (``X`` the rest positions). For a flat rest shape this is ``D/(2 (A1 + A2)) |sum_a k_a
    x_a|^2``, quadratic in the positions: each hinge adds its exact Hessian, the ``4 x 4``
    block ``D / (A1 + A2) k k^T``, to the prefactored PD matrix, so the term costs the
    nonlinear solver nothing. ``sum_a k_a x_a`` is ``|e|`` times the hinge's angle for an
    isometric bend, so a sheet bent into a cylinder of curvature ``kappa`` stores
    ``D/2 kappa^2`` per area, exactly on grids of square cells. gmsh's unstructured meshes
    converge to a slightly stiffer plate: a clamped circular plate's sag reaches 1.020,
    0.993, 0.985 of plate theory at ``h = a/40, a/80, a/160``. Limits: per hinge the energy
    sees one slope jump, so its Gaussian-curvature part is set by the mesh (on unstructured
    meshes like a Poisson's ratio of about -1/3), not by ``nu``. Plates with clamped edges do
    not see it; free edges do: a gmsh cantilever strip of width ``L/5`` sags 1.23, 1.09, 1.08
    times ``q L^4 / (8 D)`` at ``h = L/20, L/40, L/80``. A curved rest shape
    (``|sum k X| > 0``) keeps the magnitude of its rest curvature, in PD form (the
    projection onto ``|p| = |sum k X|``, Bouaziz et al. 2014):
    it cannot tell a bend from its mirror image and is not smooth where a hinge is flat.

    Attributes:
        stencil_: ``(e, 4)`` hinges (:func:`hinges`); weights: ``(e, 4)`` cotangent
            weights; area: ``(e,)`` ``A1 + A2``, m^2; rest: ``(e,)`` ``|sum_a k_a X_a|``, m.
        E, nu, thickness: initial design parameters (``params.actuators[i]``,
            :class:`BendingParams`).
    """

    stencil_: np.ndarray
    weights: np.ndarray
    area: np.ndarray
    rest: np.ndarray
    E: float
    nu: float
    thickness: float

    mesh_indices: ClassVar = {"stencil_": "vertices"}

    @classmethod
    def on(cls, mesh, triangles, *, E: float, nu: float, thickness: float) -> Bending:
        """Bending of the sheet ``triangles`` of ``mesh``, flat or curved at rest as the
        mesh is.

        Arguments:
            mesh: a :class:`~softbody.meshing.TetMesh` (with or without tets), or its points
                ``(n, 3)``.
            triangles: ``(m, 3)`` vertex indices, or the name of a region whose faces they are.
            E: Young's modulus, Pa (> 0); nu: Poisson's ratio in ``[0, 0.5)``; thickness: m (> 0).

        Raises:
            SceneError: as :meth:`Membrane.on` (unknown or empty region, bad indices,
                degenerate triangles, non-physical values), a non-manifold sheet, or a sheet
                without interior edges.
        """
        sheet = Membrane.on(mesh, triangles, E=E, nu=nu, thickness=thickness)  # the same checks
        points = np.asarray(mesh.points if isinstance(mesh, TetMesh) else mesh, np.float64)
        stencil = hinges(sheet.triangles)
        if len(stencil) == 0:
            raise SceneError("Bending: the triangles share no edge, so nothing can bend; give a connected sheet")
        weights, area = hinge_weights(points, stencil)
        rest = np.linalg.norm(np.einsum("ea,eak->ek", weights, points[stencil]), axis=1)
        rest[rest <= 1e-12 * np.linalg.norm(np.ptp(points[stencil.ravel()], axis=0))] = 0.0  # flat to round-off
        return cls(stencil.astype(np.int32), weights, area, rest, float(E), float(nu), float(thickness))

    def init_params(self) -> BendingParams:
        return BendingParams(E=jnp.asarray(self.E), nu=jnp.asarray(self.nu), thickness=jnp.asarray(self.thickness))

    def prepare(self, model, params: BendingParams, dminv, volume) -> Array:
        """``(e,)``: each hinge's weight ``D / (A1 + A2)``, N/m."""
        stiffness = params.E * params.thickness**3 / (12.0 * (1.0 - params.nu**2))
        return stiffness / jnp.asarray(self.area)

    def stencil(self) -> np.ndarray:
        return self.stencil_

    def blocks(self, prep) -> Array:
        k = jnp.asarray(self.weights)
        return prep[:, None, None] * k[:, :, None] * k[:, None, :]

    def energy_and_gradient(self, x, prep, activation):
        k = jnp.asarray(self.weights)
        stencil = jnp.asarray(self.stencil_)
        rest = jnp.asarray(self.rest)
        curved = bool(np.any(self.rest > 0))

        def energy(x):
            y = jnp.einsum("ea,eak->ek", k, x[stencil])  # (e, 3)
            squared = jnp.sum(y * y, axis=1)
            if not curved:
                return 0.5 * jnp.sum(prep * squared)
            curved_here = rest > 0.0  # (|y| - r)^2 there, |y|^2 (smooth at y = 0) on hinges flat at rest
            norm = jnp.sqrt(jnp.where(curved_here, squared, 1.0))
            return 0.5 * jnp.sum(prep * jnp.where(curved_here, (norm - rest) ** 2, squared))

        return jax.value_and_grad(energy)(x)


def shell_body(mesh: TetMesh, *, E: float, nu: float, thickness: float, areal_density: float,
               fixed=None, motion=None, name: str | None = None, triangles="sheet", bending: bool = True):
    """A body that is only a sheet (cloth, a thin shell): a mesh of triangles without tets,
    with a :class:`Membrane` (its mass, from the areal density) and a :class:`Bending` term.

    Arguments:
        mesh: a :class:`~softbody.meshing.TetMesh` without tets whose triangles cover every
            vertex (e.g. :func:`softbody.meshing.sheet.rectangle`).
        E, nu, thickness, areal_density: Pa (> 0), ``[0, 0.5)``, m (> 0), kg/m^2 (> 0).
        fixed, motion, name: as :class:`~softbody.scene.SoftBody`'s (held vertices, their
            prescribed motion, the body's name).
        triangles: the sheet's triangles, ``(m, 3)`` indices or a region name (default: the
            region ``"sheet"`` that :mod:`softbody.meshing.sheet` makes).
        bending: add the bending term (``False``: a membrane alone, which has no stiffness
            out of its plane).

    Returns:
        A :class:`~softbody.scene.SoftBody` for :func:`softbody.model.build`; its terms are
        ``actuators[0]`` (the membrane) and ``actuators[1]`` (the bending), whose design
        parameters are ``params.actuators[0]`` and ``[1]`` in a scene of this body alone.

    Raises:
        SceneError: a mesh with tets (give its sheets to ``SoftBody(actuators=[...])``
            instead), vertices on no triangle (they would have no mass), a zero areal
            density, or what :meth:`Membrane.on` and :meth:`Bending.on` refuse.
    """
    from softbody.scene import SoftBody  # the scene imports the terms' module, not the reverse

    if not isinstance(mesh, TetMesh):
        raise SceneError(f"shell_body: mesh must be a softbody.meshing.TetMesh without tets, got {type(mesh).__name__}")
    if mesh.n_tets:
        raise SceneError(f"shell_body: the mesh has {mesh.n_tets} tets; a sheet on a solid body goes into "
                         "SoftBody(mesh, material, actuators=[Membrane.on(...), Bending.on(...)])")
    if not (np.isfinite(areal_density) and areal_density > 0):
        raise SceneError(f"shell_body: areal_density must be > 0 kg/m^2 (a sheet's vertices have no other mass), "
                         f"got {areal_density}")
    membrane = Membrane.on(mesh, triangles, E=E, nu=nu, thickness=thickness, areal_density=areal_density)
    loose = np.setdiff1d(np.arange(mesh.n_vertices), membrane.triangles)
    if len(loose):
        raise SceneError(f"shell_body: {len(loose)} vertices lie on no triangle of the sheet (e.g. {loose[:5].tolist()}); "
                         "they would have no mass and no stiffness: remove them from the mesh")
    terms = [membrane] + ([Bending.on(mesh, membrane.triangles, E=E, nu=nu, thickness=thickness)] if bending else [])
    return SoftBody(mesh, fixed=fixed, motion=motion, actuators=terms, name=name)

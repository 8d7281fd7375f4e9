"""Rigid bodies: a closed triangle surface with a density or a mass, and its exact inertia.

A :class:`RigidBody` has six degrees of freedom and no tets. Its surface comes from a
``(points, triangles)`` pair, a :class:`~softbody.meshing.TetMesh` (its boundary) or an
STL/OBJ file; it is checked when the body is made (closed, manifold, consistently and
outward oriented, not self-intersecting, enclosing a volume), and its mass, centre of mass
and inertia tensor are those of the polyhedron the surface bounds, exactly (up to
rounding).

:func:`mass_properties` integrates ``1``, ``x`` and ``x x^T`` over the enclosed volume by
the divergence theorem: the volume is the signed sum of the tetrahedra joining a reference
point to each oriented triangle, whose integrals are closed forms (Tonon, J. Math. Stat.
1(1), 2004; Eberly, "Polyhedral mass properties"). The reference point is the mean of the
surface's vertices, so a body far from the origin loses no digits to cancellation.

Example::

    from softbody import meshing
    from softbody.rigid import RigidBody

    ball = RigidBody(meshing.mesh(meshing.Sphere(0.05), 0.01), density=1000.0, name="ball")
    print(ball.mass, ball.centre, ball.principal[0])
"""

from __future__ import annotations

import math
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path

import numpy as np

from softbody._types import SceneError
from softbody.meshing import (
    MeshError,
    TetMesh,
    check_surface,
    nonmanifold_edges,
    open_edges,
    read_surface,
)

#: A surface as :class:`RigidBody` accepts it.
Surface = tuple | TetMesh | str | Path

#: A closed surface enclosing less than this fraction of its bounding box's cube of the
#: diagonal counts as enclosing no volume.
DEGENERATE_VOLUME = 1e-12

#: Largest deviation of ``R^T R`` from the identity accepted for a rotation matrix.
ROTATION_TOL = 1e-8


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class MassProperties:
    """Mass properties of a solid of uniform density.

    Attributes:
        mass: kg.
        volume: m^3.
        centre: ``(3,)`` centre of mass, m.
        inertia: ``(3, 3)`` inertia tensor about the centre of mass, kg m^2
            (``sum m (|r|^2 I - r r^T)`` with ``r`` measured from the centre).
    """

    mass: float
    volume: float
    centre: np.ndarray
    inertia: np.ndarray


def _positive(value: object, what: str) -> float:
    """``value`` as a positive finite float, or a :class:`SceneError` naming it."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{what} must be a positive number, got {value!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise SceneError(f"{what} must be positive and finite, got {x}; give a value > 0 in SI units")
    return x


def _surface_arrays(points: object, triangles: object) -> tuple[np.ndarray, np.ndarray]:
    """``points (n, 3)`` float64 and ``triangles (f, 3)`` int64, checked for shape, range and finiteness."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MeshError(f"surface points must have shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise MeshError(f"{int((~np.isfinite(p)).any(axis=1).sum())} surface points are not finite; "
                        "remove or repair them")
    if t.ndim != 2 or t.shape[1] != 3 or len(t) < 4:
        raise MeshError(f"a closed surface needs at least 4 triangles (f, 3), got shape {t.shape}")
    if not np.issubdtype(t.dtype, np.integer):
        raise MeshError(f"triangles must hold integer vertex indices, got dtype {t.dtype}")
    if t.min() < 0 or t.max() >= len(p):
        raise MeshError(f"triangle vertex indices must lie in [0, {len(p)}), got [{t.min()}, {t.max()}]")
    return p, t.astype(np.int64)


def _check_closed_and_oriented(points: np.ndarray, triangles: np.ndarray) -> None:
    """Refuse a surface with open or non-manifold edges, or whose triangles disagree on orientation.

    On a closed, consistently oriented surface every directed edge ``(i, j)`` of a triangle
    is met by the reverse edge ``(j, i)`` of its neighbour, never by a second ``(i, j)``.
    """
    holes, shared = open_edges(triangles), nonmanifold_edges(triangles)
    if len(holes) or len(shared):
        raise MeshError(f"surface is not closed: {len(holes)} open edges and {len(shared)} non-manifold edges "
                        f"(first: {np.concatenate([holes, shared])[:3].tolist()}); mass properties need a closed "
                        "surface: softbody.meshing.check_surface names the defects and how to repair them")
    directed = triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    edges, counts = np.unique(directed, axis=0, return_counts=True)
    twice = edges[counts > 1]
    if len(twice):
        where = np.round(points[twice[0]], 6).tolist()
        raise MeshError(f"surface is not consistently oriented: {len(twice)} edges are traversed in the same "
                        f"direction by both their triangles (first: vertices {twice[0].tolist()} at {where}); "
                        "reverse the vertex order of the flipped triangles so that all normals point out "
                        "(a mesh-repair tool's 'unify normals' does this)")


def mass_properties(points: np.ndarray, triangles: np.ndarray, density: float) -> MassProperties:
    """Exact mass, volume, centre of mass and inertia of the solid a closed surface bounds.

    The integrals of ``1``, ``x`` and ``x x^T`` over the solid are sums over the triangles
    of those over the tetrahedra joining a reference point (the mean vertex) to each
    oriented triangle, in float64. Exact for the polyhedron up to rounding. A hollow
    solid is given by its outer surface plus inner surfaces whose normals point into the
    hollows (out of the material).

    The surface is checked to be closed and consistently oriented (every edge shared by
    two triangles that traverse it in opposite directions), not for self-intersections
    (:class:`RigidBody` checks those too, through :func:`softbody.meshing.check_surface`).

    Arguments:
        points: ``(n, 3)`` vertex positions, m.
        triangles: ``(f, 3)`` vertex indices, counter-clockwise seen from outside (normals
            pointing out of the solid).
        density: kg/m^3 (> 0, finite).

    Returns:
        :class:`MassProperties`, the inertia about the centre of mass.

    Raises:
        MeshError: on bad shapes, indices or non-finite points, open or non-manifold
            edges, inconsistently oriented triangles, an inward-oriented surface (refused,
            not flipped: the message says to reverse the triangles' vertex order), or a
            surface enclosing no volume.
        SceneError: on a density that is not positive and finite.
    """
    density = _positive(density, "density")
    p, t = _surface_arrays(points, triangles)
    _check_closed_and_oriented(p, t)
    used = p[np.unique(t)]
    origin = used.mean(axis=0)
    a, b, c = (p[t[:, k]] - origin for k in range(3))
    six_v = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 x signed volume of each tetrahedron
    s = a + b + c
    volume = float(six_v.sum() / 6.0)
    diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    if abs(volume) <= DEGENERATE_VOLUME * diag**3:
        raise MeshError(f"surface encloses no volume ({volume:.3g} m^3 within a bounding box of diagonal "
                        f"{diag:.3g} m): it is flat or folded onto itself; give the surface of a solid")
    if volume < 0:
        raise MeshError(f"surface is oriented inward: its triangles' normals point into the solid (signed volume "
                        f"{volume:.6g} m^3); refused rather than flipped: reverse every triangle's vertex order "
                        "(triangles[:, ::-1]) so that the normals point out")
    first = (six_v @ s) / 24.0  # integral of x - origin
    second = (np.einsum("i,ij,ik->jk", six_v, a, a) + np.einsum("i,ij,ik->jk", six_v, b, b)
              + np.einsum("i,ij,ik->jk", six_v, c, c) + np.einsum("i,ij,ik->jk", six_v, s, s)) / 120.0
    centre = first / volume
    spread = second - volume * np.outer(centre, centre)  # integral of r r^T about the centre
    spread = (spread + spread.T) / 2
    inertia = density * (np.trace(spread) * np.eye(3) - spread)
    return MassProperties(mass=density * volume, volume=volume, centre=_frozen(origin + centre),
                          inertia=_frozen(inertia))


def _vector(value: object, what: str) -> np.ndarray:
    v = np.asarray(value, dtype=np.float64) if value is not None else None
    if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
        raise SceneError(f"{what} must be 3 finite numbers, got {value!r}")
    return _frozen(v)


def _rotation(value: object, what: str) -> np.ndarray:
    r = np.asarray(value, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise SceneError(f"{what} must be a finite (3, 3) rotation matrix, got {value!r}")
    off = float(np.abs(r.T @ r - np.eye(3)).max())
    if off > ROTATION_TOL or np.linalg.det(r) < 0:
        raise SceneError(f"{what} is not a rotation (|R^T R - I| = {off:.2g}, det {np.linalg.det(r):.6g}); give an "
                         "orthonormal matrix with determinant +1 (e.g. scipy's Rotation.as_matrix())")
    return _frozen(r)


def _read(surface: object) -> tuple[np.ndarray, np.ndarray]:
    """``(points, triangles)`` of the accepted surface kinds (a TetMesh keeps only its boundary's vertices)."""
    if isinstance(surface, TetMesh):
        used, tri = np.unique(surface.surface, return_inverse=True)
        return surface.points[used], tri.reshape(-1, 3)
    if isinstance(surface, (str, Path)):
        return _surface_arrays(*read_surface(surface))
    if isinstance(surface, tuple) and len(surface) == 2:
        return _surface_arrays(*surface)
    raise SceneError(f"surface must be (points, triangles), a softbody.meshing.TetMesh or the path of an STL/OBJ "
                     f"file, got {type(surface).__name__}")


@dataclass(frozen=True, eq=False)
class RigidBody:
    """A free rigid body bounded by a closed triangle surface, of uniform density.

    The surface as given is the body's reference placement; its initial placement moves
    the centre of mass to ``x0`` and rotates the body about it by ``R0``: a reference point
    ``p`` starts at ``x0 + R0 (p - centre)``. All checks run when the body is made.

    Arguments:
        surface: ``(points (n, 3), triangles (f, 3))`` with outward normals; a
            :class:`~softbody.meshing.TetMesh` (its boundary surface; cavities count as
            hollows); or the path of an STL/OBJ file in metres (read by
            :func:`softbody.meshing.read_surface`; for a file in other units, pass
            ``read_surface(path, scale=...)`` instead).
        density: kg/m^3; give exactly one of ``density`` and ``mass``.
        mass: total mass, kg.
        name: a label for results and viewers.
        x0: initial centre of mass ``(3,)``, m (default: the surface's own centre).
        R0: initial rotation ``(3, 3)`` about the centre of mass (default: identity).
        v0: initial velocity of the centre of mass ``(3,)``, m/s.
        omega0: initial angular velocity ``(3,)``, rad/s, in world axes.

    Attributes:
        points, triangles: the surface in its reference placement (``(n, 3)`` float64,
            ``(f, 3)`` int64).
        properties: its :class:`MassProperties`.
        density, mass: both resolved from the one given (``mass = density * volume``).

    Raises:
        MeshError: on a surface that is not closed, is non-manifold, self-intersecting,
            inconsistently or inward oriented, has zero-area triangles or encloses no
            volume (from :func:`softbody.meshing.check_surface` and
            :func:`mass_properties`), or an unreadable file.
        SceneError: on neither or both of ``density`` and ``mass``, either not positive
            and finite, a pose or velocity that is not 3 finite numbers, ``R0`` not a
            rotation, or an unknown kind of surface.
    """

    surface: Surface
    _: KW_ONLY
    density: float | None = None
    mass: float | None = None
    name: str | None = None
    x0: np.ndarray | None = None
    R0: np.ndarray | None = None
    v0: np.ndarray = (0.0, 0.0, 0.0)
    omega0: np.ndarray = (0.0, 0.0, 0.0)
    points: np.ndarray = field(init=False, repr=False)
    triangles: np.ndarray = field(init=False, repr=False)
    properties: MassProperties = field(init=False, repr=False)

    def __post_init__(self):
        if (self.density is None) == (self.mass is None):
            given = "both" if self.density is not None else "neither"
            raise SceneError(f"RigidBody needs exactly one of density (kg/m^3) or mass (kg), got {given}; "
                             "give one, e.g. RigidBody(surface, density=1000.0)")
        known = _positive(self.density, "density") if self.mass is None else _positive(self.mass, "mass")
        if self.name is not None and not isinstance(self.name, str):
            raise SceneError(f"name must be a string, got {self.name!r}")
        x0 = None if self.x0 is None else _vector(self.x0, "x0")
        R0 = _frozen(np.eye(3)) if self.R0 is None else _rotation(self.R0, "R0")
        v0, omega0 = _vector(self.v0, "v0"), _vector(self.omega0, "omega0")
        points, triangles = _read(self.surface)
        check_surface(points, triangles)
        unit = mass_properties(points, triangles, 1.0)
        density = known if self.mass is None else known / unit.volume
        mass = density * unit.volume if self.mass is None else known
        props = MassProperties(mass=mass, volume=unit.volume, centre=unit.centre,
                               inertia=_frozen(density * unit.inertia))
        triangles = np.array(triangles, dtype=np.int64)
        triangles.setflags(write=False)
        for name, value in (("points", _frozen(points)), ("triangles", triangles), ("properties", props),
                            ("density", density), ("mass", mass), ("x0", props.centre if x0 is None else x0),
                            ("R0", R0), ("v0", v0), ("omega0", omega0)):
            object.__setattr__(self, name, value)

    @property
    def volume(self) -> float:
        """Enclosed volume, m^3."""
        return self.properties.volume

    @property
    def centre(self) -> np.ndarray:
        """Centre of mass ``(3,)`` of the reference placement, m."""
        return self.properties.centre

    @property
    def inertia(self) -> np.ndarray:
        """Inertia tensor ``(3, 3)`` about the centre of mass, reference axes, kg m^2."""
        return self.properties.inertia

    @property
    def principal(self) -> tuple[np.ndarray, np.ndarray]:
        """Principal moments ``(3,)`` (ascending, kg m^2) and axes ``(3, 3)`` (columns, a
        right-handed frame): ``inertia == axes @ diag(moments) @ axes.T``."""
        moments, axes = np.linalg.eigh(self.inertia)
        if np.linalg.det(axes) < 0:
            axes[:, 2] *= -1
        return moments, axes

    def surface_at(self, x: np.ndarray | None = None, R: np.ndarray | None = None) -> np.ndarray:
        """The surface's vertices ``(n, 3)`` with the centre of mass at ``x`` and rotation ``R``.

        Arguments:
            x: centre of mass ``(3,)`` (default ``x0``).
            R: rotation ``(3, 3)`` from the reference placement (default ``R0``).

        Raises:
            SceneError: if ``x`` is not 3 finite numbers or ``R`` is not a rotation.
        """
        x = self.x0 if x is None else _vector(x, "x")
        R = self.R0 if R is None else _rotation(R, "R")
        return x + (self.points - self.centre) @ R.T

    def scene_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices a scene gives this body, at its initial placement, and each one's
        share of the mass.

        A scene moves a rigid body as a 6-dof root of its skeleton (see
        :mod:`softbody.scene`) and stores it as vertices with lumped masses: its surface
        vertices, then six interior points. The shares are chosen so that the lumped
        masses have *exactly* the body's mass, centre of mass and inertia tensor: the
        surface vertices carry a fraction ``eps`` of the mass equally (so that every vertex
        has a mass, as contact needs), and the six interior points ``c + delta +- d_k e_k``
        carry the rest, ``delta`` cancelling the surface vertices' first moment and
        ``(d_k, e_k)`` the principal values and axes of the second moment left over,
        ``S - eps T - (1 - eps) delta delta^T`` with ``S = tr(I)/2 - I`` the solid's second
        moment per unit mass (``I`` the inertia per unit mass) and ``T`` the surface
        vertices'. ``eps = min(0.1, lambda_min(S) / (4 lambda_max(T)))`` keeps that
        leftover positive definite (at least half of ``S``'s smallest eigenvalue).

        Returns:
            ``(points (n_s + 6, 3), share (n_s + 6,))``: positions (surface vertices in
            this body's order, then the interior points) and shares summing to 1.
        """
        centre, unit = self.centre, self.inertia / self.mass
        spread = np.trace(unit) / 2 * np.eye(3) - unit  # S: second moment per unit mass about the centre
        r = self.points - centre
        first = r.mean(axis=0)
        surface = r.T @ r / len(r)  # T, about the centre
        eps = min(0.1, float(np.linalg.eigvalsh(spread)[0] / (4 * np.linalg.eigvalsh(surface)[-1])))
        delta = -eps / (1 - eps) * first
        rest = spread - eps * surface - (1 - eps) * np.outer(delta, delta)
        values, axes = np.linalg.eigh((rest + rest.T) / 2)
        reach = np.sqrt(3 * values / (1 - eps)) * axes  # column k: d_k e_k
        inner = delta + np.concatenate([reach.T, -reach.T])
        local = np.concatenate([r, inner])
        share = np.concatenate([np.full(len(r), eps / len(r)), np.full(6, (1 - eps) / 6)])
        return self.x0 + local @ self.R0.T, share

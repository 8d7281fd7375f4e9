"""The bodies of a scene and their concatenation into one vertex array.

A scene is a list of bodies plus what acts between them (a skeleton, obstacles, joint
actuators: the arguments of :func:`softbody.model.build`). A :class:`SoftBody` is a tet
mesh with its materials, its held vertices (:class:`Fix`), their prescribed motion and the
actuators on its elements, all given in the body's own terms (its region names, its
vertex and tet indices). A :class:`~softbody.rigid.RigidBody` is a closed surface with
a mass: it joins the scene as its surface vertices and six interior points whose lumped
masses have exactly its mass, centre of mass and inertia
(:meth:`~softbody.rigid.RigidBody.scene_vertices`), no tets, and moves as a 6-dof root
link of the scene's skeleton (a :class:`~softbody.skeleton.Free` joint about its centre
of mass, the link and its bone region named after the body). :func:`assemble`
concatenates the bodies into one :class:`~softbody.meshing.TetMesh`, so the PD matrix
stays one scalar ``n x n`` matrix, factorised once, and every solver, adjoint and the
skeleton's condensation apply unchanged. Bodies touch each other only through what acts
between them.

Names: a body's ``name`` qualifies what it brings to the scene: its regions are
``"<name>/<region>"`` in the scene's mesh, which also has a region ``"<name>"`` with all of
the body's vertices, tets and surface faces; its materials are ``"<name>/<region>"``
(``"<name>/default"`` for the rest of the body); its actuator channels are
``"<name>/<channel>"``. A scene of one soft body may leave it unnamed: the scene's mesh is
then the body's own, with its names unchanged. Rigid bodies are always named: their name
is their region, link and bone.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Mapping, NamedTuple, Sequence

import numpy as np

from softbody._interfaces import Term
from softbody._types import SceneError
from softbody.material import Material
from softbody.meshing import TetMesh
from softbody.meshing.mesh import Region
from softbody.contact.obstacles import check_motion
from softbody.rigid import RigidBody
from softbody.skeleton import Free, Link

AXES = "xyz"


@dataclasses.dataclass(frozen=True)
class Fix:
    """Vertices held in chosen components of their position (a part of ``SoftBody(fixed=...)``).

    ``Fix("clamp")`` holds every component (a clamp, what a bare selection means);
    ``Fix(selection, axes="y")`` holds only ``y``: the vertices slide freely in ``x`` and
    ``z``, as on a roller or a symmetry plane ``y = const``; holding ``z`` on every vertex of
    a one-layer extrusion (``Fix(lambda p: np.ones(len(p), bool), axes="z")``) makes it
    plane strain.

    Arguments:
        where: a region name, vertex indices, or a predicate ``points (n, 3) -> bool mask (n,)``.
        axes: the held components, a non-empty subset of ``"xyz"`` (world axes).

    Raises:
        SceneError: axes that are not a non-empty subset of ``"xyz"``.
    """

    where: str | Sequence[int] | Callable
    axes: str = AXES

    def __post_init__(self):
        if (not isinstance(self.axes, str) or not self.axes or len(set(self.axes)) != len(self.axes)
                or not set(self.axes) <= set(AXES)):
            raise SceneError(f"Fix.axes must name held components once each from 'xyz' (e.g. 'xyz', 'y', 'xz'), "
                             f"got {self.axes!r}")


@dataclasses.dataclass(frozen=True, eq=False)
class SoftBody:
    """A deformable body of a scene: a tet mesh with its materials, held vertices and actuators.

    Arguments:
        mesh: the :class:`~softbody.meshing.TetMesh`.
        material: one :class:`~softbody.material.Material`, or a mapping from the mesh's
            region names to materials (``"default"`` for the rest).
        fixed: the held vertices: a region name, vertex indices (of this mesh) or a
            predicate ``points (n, 3) -> bool mask (n,)`` (clamped in all three
            components), a :class:`Fix` (``Fix("symmetry", axes="y")`` holds only ``y``: a
            roller or a symmetry plane), a list of :class:`Fix` parts, or ``None`` (free).
        motion: a prescribed rigid motion of the held vertices (a moving clamp):
            ``t -> (R (3, 3), p (3,))``, JAX-traceable in the time ``t`` (s); at time ``t``
            a held vertex with rest position ``X`` (morph included) sits at ``R X + p`` in
            its held components. ``None``: they stay where they start.
        actuators: actuator terms built on this mesh (muscles, cavities, pneumatic cells;
            joint actuators act on the scene's skeleton and go to ``build(actuators=...)``).
        name: the body's name in the scene (see the module docstring); a scene of several
            bodies needs a unique name for each. No ``"/"``.

    Raises:
        SceneError: a mesh that is not a ``TetMesh``, a bad name, actuators that are not
            actuator terms.
    """

    mesh: TetMesh
    material: Material | Mapping[str, Material] = Material()
    fixed: str | Sequence[int] | Callable | Fix | Sequence[Fix] | None = dataclasses.field(default=None, kw_only=True)
    motion: Callable | None = dataclasses.field(default=None, kw_only=True)
    actuators: Sequence[Term] = dataclasses.field(default=(), kw_only=True)
    name: str | None = dataclasses.field(default=None, kw_only=True)

    def __post_init__(self):
        if not isinstance(self.mesh, TetMesh):
            raise SceneError(f"SoftBody.mesh must be a softbody.meshing.TetMesh, got {type(self.mesh).__name__}")
        if self.name is not None and (not isinstance(self.name, str) or not self.name or "/" in self.name):
            raise SceneError(f"SoftBody.name must be a non-empty string without '/', or None; got {self.name!r}")
        actuators = tuple(self.actuators)
        for i, term in enumerate(actuators):
            if not isinstance(term, Term):
                raise SceneError(f"actuators[{i}] is a {type(term).__name__}, not an actuator; give terms from "
                                 "softbody.actuators (Muscle, CavityPressure, CavityVolume, PneumaticCells) or "
                                 "subclasses of softbody._interfaces.Term")
        object.__setattr__(self, "actuators", actuators)


@dataclasses.dataclass(frozen=True)
class BodyPart:
    """Where a body sits in the scene's arrays (``Model.bodies``).

    Attributes:
        name: the body's name (``None`` for the one unnamed body of a scene).
        vertices: ``(start, stop)``: its vertices are ``start <= i < stop`` of the scene's.
        tets: ``(start, stop)``: its tets.
        fixed: ``(k,)`` int32 scene indices of its vertices with a held component.
        motion: its held vertices' prescribed motion ``t -> (R, p)``, or ``None``.
        rigid: the :class:`~softbody.rigid.RigidBody` for a rigid body, else ``None``.
        mass_share: a rigid body's ``(stop - start,)`` share of its mass per vertex (see
            :meth:`~softbody.rigid.RigidBody.scene_vertices`), else ``None``.
    """

    name: str | None
    vertices: tuple[int, int]
    tets: tuple[int, int]
    fixed: np.ndarray
    motion: Callable | None = None
    rigid: RigidBody | None = None
    mass_share: np.ndarray | None = None


class Assembly(NamedTuple):
    """The bodies of a scene as one vertex array (what :func:`assemble` returns)."""

    mesh: TetMesh  # the scene's mesh: every body's vertices and tets, names qualified
    material_names: tuple[str, ...]
    materials: list[Material]
    tet_material: np.ndarray  # (t,) int32 index into material_names
    held: np.ndarray  # (n, 3) bool: the held components of every vertex
    terms: tuple[Term, ...]  # the bodies' actuator terms, on the scene's indices
    parts: tuple[BodyPart, ...]
    links: tuple[Link, ...]  # one Free root link per rigid body


def _selection(mesh: TetMesh, where) -> np.ndarray:
    """The vertex indices a region name, index list or predicate selects (non-empty)."""
    if isinstance(where, str):
        if where not in mesh.regions:
            raise SceneError(f"fixed region {where!r} is not in the mesh; it has {sorted(mesh.regions)}")
        idx = mesh.regions[where].vertices
    elif callable(where):
        mask = np.asarray(where(mesh.points), bool)
        if mask.shape != (mesh.n_vertices,):
            raise SceneError(f"the fixed predicate must return a boolean mask of shape ({mesh.n_vertices},)")
        idx = np.flatnonzero(mask)
    else:
        idx = np.unique(np.asarray(where, np.int64))
        if idx.size and (idx.min() < 0 or idx.max() >= mesh.n_vertices):
            raise SceneError("fixed vertex indices out of range")
    if len(idx) == 0:
        raise SceneError(f"the fixed selection {where if isinstance(where, str) else ''!s} holds no vertices; "
                         "check the region or predicate, or pass fixed=None for a free body")
    return np.asarray(idx, np.int64)


def _fixed_mask(mesh: TetMesh, fixed) -> np.ndarray:
    """``(n, 3)`` bool: the held components of every vertex (see :class:`SoftBody`'s ``fixed``)."""
    held = np.zeros((mesh.n_vertices, 3), bool)
    if fixed is None:
        return held
    several = isinstance(fixed, (list, tuple)) and any(isinstance(f, Fix) for f in fixed)
    if several and not all(isinstance(f, Fix) for f in fixed):
        raise SceneError("fixed is a list mixing Fix parts with other items: give one selection, one Fix, or a "
                         "list of Fix parts (e.g. [Fix('clamp'), Fix('symmetry', axes='y')])")
    for part in fixed if several else [fixed]:
        part = part if isinstance(part, Fix) else Fix(part)
        held[np.ix_(_selection(mesh, part.where), [AXES.index(a) for a in part.axes])] = True
    return held


def _materials(mesh: TetMesh, material) -> tuple[list[str], list[Material], np.ndarray]:
    """A body's material names (its own region names, ``"default"`` first), materials and
    ``(t,)`` material index per tet."""
    if isinstance(material, Material):
        return ["default"], [material], np.zeros(mesh.n_tets, np.int32)
    if not isinstance(material, Mapping):
        raise SceneError("material must be a Material or a mapping region name -> Material "
                         "(key 'default' for tets in no named region)")
    names, mats = ["default"], [material.get("default", Material())]
    tet_material = np.zeros(mesh.n_tets, np.int32)
    for name, mat in material.items():
        if name == "default":
            continue
        if not isinstance(mat, Material):
            raise SceneError(f"material[{name!r}] must be a Material, got {type(mat).__name__}")
        reg = mesh.region(name) if name in mesh.regions else None
        if reg is None:
            raise SceneError(f"material region {name!r} is not in the mesh; it has {sorted(mesh.regions)}")
        if reg.tets.size == 0:
            raise SceneError(f"material region {name!r} has no tets (is it a surface region?)")
        tet_material[reg.tets] = len(names)
        names.append(name)
        mats.append(mat)
    return names, mats, tet_material


def _bodies(bodies) -> tuple[SoftBody | RigidBody, ...]:
    """The scene's bodies as a tuple, checked: at least one, unique names, names where several
    and on every rigid body."""
    bodies = (bodies,) if isinstance(bodies, (SoftBody, RigidBody)) else bodies
    if isinstance(bodies, TetMesh):
        raise SceneError("build takes bodies, not a mesh: wrap it, build(SoftBody(mesh, material, fixed=...))")
    try:
        bodies = tuple(bodies)
    except TypeError:
        raise SceneError(f"build takes a SoftBody or RigidBody or a list of them, got {type(bodies).__name__}") from None
    if not bodies:
        raise SceneError("a scene needs at least one body: build(SoftBody(mesh, material))")
    for i, body in enumerate(bodies):
        if not isinstance(body, (SoftBody, RigidBody)):
            raise SceneError(f"bodies[{i}] is a {type(body).__name__}, not a SoftBody or RigidBody; wrap meshes as "
                             "SoftBody(mesh, material, name=...)")
        if isinstance(body, RigidBody) and (not body.name or "/" in body.name):
            raise SceneError(f"bodies[{i}] is a rigid body named {body.name!r}: a rigid body in a scene needs a "
                             "name without '/' (its region, link and bone): RigidBody(surface, mass=..., name='box')")
    names = [b.name for b in bodies]
    if len(bodies) > 1 and None in names:
        raise SceneError(f"a scene of {len(bodies)} bodies names each of them: SoftBody(..., name='arm'); "
                         f"unnamed: bodies {[i for i, n in enumerate(names) if n is None]}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise SceneError(f"body names must be unique in a scene, got {repeated} more than once; rename the bodies")
    return bodies


def _qualify(name: str | None, item: str) -> str:
    return item if name is None else f"{name}/{item}"


class _Piece(NamedTuple):
    """What one body brings to the scene's mesh, in its own indices."""

    points: np.ndarray  # (n, 3)
    tets: np.ndarray  # (t, 4)
    surface: np.ndarray  # (f, 3)
    regions: Mapping[str, Region]
    fields: Mapping[str, np.ndarray]


def _piece(body: SoftBody | RigidBody) -> _Piece:
    if isinstance(body, RigidBody):
        points, _ = body.scene_vertices()
        return _Piece(points, np.zeros((0, 4), np.int64), body.triangles, {}, {})
    mesh = body.mesh
    return _Piece(mesh.points, mesh.tets, np.asarray(mesh.surface), mesh.regions, mesh.fields)


def _mesh(bodies, pieces: list[_Piece], starts: np.ndarray, tet_starts: np.ndarray) -> TetMesh:
    """The scene's mesh: the bodies' vertices and tets in order, regions qualified by body name."""
    if len(bodies) == 1 and bodies[0].name is None:
        return bodies[0].mesh
    regions, fields = {}, {}
    for body, piece, v0, t0 in zip(bodies, pieces, starts, tet_starts):
        regions[body.name] = Region(np.arange(len(piece.points)) + v0, np.arange(len(piece.tets)) + t0,
                                    piece.surface + v0)
        for key, reg in piece.regions.items():
            regions[_qualify(body.name, key)] = Region(reg.vertices + v0, reg.tets + t0, reg.faces + v0)
    for key in {k for piece in pieces for k in piece.fields}:
        shapes = {np.asarray(p.fields[key]).shape[1:] for p in pieces if key in p.fields}
        if len(shapes) > 1:
            raise SceneError(f"the bodies' meshes have field {key!r} with different shapes per tet {sorted(shapes)}; "
                             "rename it in one of them")
        shape = shapes.pop()
        # A body without the field gets zeros (nothing reads it there: its actuators are its own).
        fields[key] = np.concatenate([np.asarray(p.fields[key], np.float64) if key in p.fields
                                      else np.zeros((len(p.tets), *shape)) for p in pieces])
    return TetMesh(np.concatenate([p.points for p in pieces]),
                   np.concatenate([p.tets + v0 for p, v0 in zip(pieces, starts)]),
                   np.concatenate([p.surface + v0 for p, v0 in zip(pieces, starts)]), regions, fields)


def assemble(bodies: SoftBody | RigidBody | Sequence[SoftBody | RigidBody]) -> Assembly:
    """Concatenate a scene's bodies into one vertex array.

    Arguments:
        bodies: one :class:`SoftBody` or :class:`~softbody.rigid.RigidBody`, or a sequence
            of them.

    Returns:
        An :class:`Assembly`: the scene's mesh (bodies in the given order, names qualified
        as the module docstring says), its materials, the ``(n, 3)`` held components, the
        actuator terms on the scene's indices, each body's :class:`BodyPart` and the root
        link of each rigid body.

    Raises:
        SceneError: no bodies, something that is not a body, missing or repeated names (a
            rigid body always needs one), unknown regions, an empty fixed selection, a motion without held
            vertices or not of the form ``t -> (R, p)``, joint actuators in a body,
            repeated channel names.
    """
    bodies = _bodies(bodies)
    pieces = [_piece(body) for body in bodies]
    sizes = np.array([len(p.points) for p in pieces])
    tet_sizes = np.array([len(p.tets) for p in pieces])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    tet_starts = np.concatenate([[0], np.cumsum(tet_sizes)[:-1]])
    names, mats, tet_material, held, terms, parts, links = [], [], [], [], [], [], []
    for body, v0, t0, size, tet_size in zip(bodies, starts, tet_starts, sizes, tet_sizes):
        span = (int(v0), int(v0 + size)), (int(t0), int(t0 + tet_size))
        if isinstance(body, RigidBody):
            held.append(np.zeros((size, 3), bool))
            parts.append(BodyPart(body.name, *span, np.zeros(0, np.int32), rigid=body,
                                  mass_share=body.scene_vertices()[1]))
            links.append(Link(body.name, body.name, None, Free(origin=tuple(body.x0))))
            continue
        body_names, body_mats, body_tet_material = _materials(body.mesh, body.material)
        tet_material.append(body_tet_material + len(names))
        names.extend(_qualify(body.name, m) for m in body_names)
        mats.extend(body_mats)
        body_held = _fixed_mask(body.mesh, body.fixed)
        held.append(body_held)
        fixed = np.flatnonzero(body_held.any(axis=1)).astype(np.int32) + int(v0)
        if body.motion is not None:
            check_motion(body.motion, "SoftBody", SceneError)
            if len(fixed) == 0:
                who = "the body" if body.name is None else f"body {body.name!r}"
                raise SceneError(f"the motion of {who} moves its held vertices, but it has none: give the body "
                                 "fixed=...")
        terms.extend(term.placed(_qualify(body.name, ""), int(v0), int(t0)) for term in body.actuators)
        parts.append(BodyPart(body.name, *span, fixed, body.motion))
    return Assembly(_mesh(bodies, pieces, starts, tet_starts), tuple(names), mats,
                    np.concatenate(tet_material) if tet_material else np.zeros(0, np.int32),
                    np.concatenate(held), tuple(terms), tuple(parts), tuple(links))

"""Describe a robot's solid geometry and mesh it with gmsh's OpenCASCADE kernel.

Shapes are small immutable descriptions (a constructive-solid-geometry tree); nothing
touches gmsh until :func:`mesh` builds the tree, so shapes can be made, combined and
reused freely. Lengths are in metres, angles in radians.

Primitives: :class:`Box`, :class:`Cylinder`, :class:`Sphere`, :class:`Capsule`,
:class:`CAD` (a solid from a STEP, IGES or BREP file).

Operations: ``a + b`` (union), ``a - b`` (difference), ``a & b`` (intersection),
``shape.translate(offset)``, ``shape.rotate(angle, axis, center)``.

Names for the simulator (they become :class:`~softbody.meshing.Region` s of the mesh):

- ``Tag(shape, "bone:spine")``: a solid piece that is part of the body; wherever it
  ends up inside the final solid, its tets and vertices form the region
  ``"bone:spine"``. The mesh conforms to its boundary.
- ``body.mark("muscle:top", where)``: name the part of the body inside ``where``
  without adding material (``where`` outside the body is ignored).
- ``body - Cavity(shape, "chamber")``: cut a cavity; its wall triangles, oriented into
  the cavity, and their vertices form the region ``"cavity:chamber"``. A cavity must be
  subtracted (appear on the right of ``-``).
- Boundary selections are given to :func:`mesh`: ``select={"fixed": OnPlane("x", 0.0)}``
  makes the vertices on the plane x = 0 (and the surface triangles among them) the
  region ``"fixed"``. See :class:`OnPlane`, :class:`InBox`.

Regions may overlap. The same tag name used twice names the union of its pieces.

Example::

    body = Box((0.1, 0.02, 0.02), center=(0.05, 0, 0))
    chamber = Cavity(Box((0.07, 0.012, 0.006), center=(0.05, 0, 0.005)), "chamber")
    m = mesh(body - chamber, size=0.004, select={"fixed": OnPlane("x", 0.0)})
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence, Union

import gmsh
import numpy as np

from . import _gmsh
from .mesh import MeshError, Region, TetMesh
from .quality import check_quality

DimTags = list[tuple[int, int]]
Vector = Union[Sequence[float], np.ndarray]

#: Smallest acceptable gamma quality (3 x inradius / circumradius, 1 for a regular tet)
#: unless the caller lowers it; see :func:`softbody.meshing.check_quality`.
DEFAULT_MIN_QUALITY = 0.1

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def _vec(v: Vector | str, what: str, unit: bool = False) -> tuple[float, float, float]:
    if isinstance(v, str):
        if v.lower() not in _AXES:
            raise MeshError(f"{what}: unknown axis {v!r}; use 'x', 'y', 'z' or a 3-vector")
        v = _AXES[v.lower()]
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise MeshError(f"{what} must be 3 finite numbers, got {v!r}")
    if unit:
        n = np.linalg.norm(a)
        if n == 0:
            raise MeshError(f"{what} must not be the zero vector")
        a = a / n
    return (float(a[0]), float(a[1]), float(a[2]))


def _positive(x: float, what: str) -> float:
    x = float(x)
    if not (math.isfinite(x) and x > 0):
        raise MeshError(f"{what} must be a positive finite length, got {x}")
    return x


@dataclass
class _Build:
    """State of one build: the registered cavities and tags, as OCC copies."""

    cavities: list[tuple[str, DimTags]] = field(default_factory=list)
    tags: list[tuple[str, DimTags]] = field(default_factory=list)
    removing: bool = False  # True while building the right-hand side of a difference


class Shape:
    """A solid described by a CSG tree; see the module docstring for the operations."""

    def __add__(self, other: "Shape") -> "Shape":
        return _Boolean("fuse", self, _check_shape(other))

    def __sub__(self, other: "Shape") -> "Shape":
        return _Boolean("cut", self, _check_shape(other))

    def __and__(self, other: "Shape") -> "Shape":
        return _Boolean("intersect", self, _check_shape(other))

    def translate(self, offset: Vector) -> "Shape":
        """This shape moved by ``offset``.

        Arguments:
            offset: ``(3,)`` displacement in metres.

        Returns:
            The moved shape (tags and cavities inside it move with it).

        Raises:
            MeshError: if ``offset`` is not 3 finite numbers.
        """
        return _Moved(self, ("translate", _vec(offset, "offset")))

    def rotate(self, angle: float, axis: Vector | str, center: Vector = (0.0, 0.0, 0.0)) -> "Shape":
        """This shape rotated about an axis (right-hand rule).

        Arguments:
            angle: radians.
            axis: ``"x"``, ``"y"``, ``"z"`` or a direction ``(3,)``.
            center: a point ``(3,)`` on the axis.

        Returns:
            The rotated shape (tags and cavities inside it turn with it).

        Raises:
            MeshError: on a non-finite angle or a zero or non-finite axis.
        """
        if not math.isfinite(angle):
            raise MeshError(f"rotation angle must be finite, got {angle}")
        return _Moved(self, ("rotate", float(angle), _vec(axis, "rotation axis", unit=True),
                             _vec(center, "rotation center")))

    def mark(self, name: str, where: "Shape") -> "Shape":
        """This shape, with the part of it inside ``where`` named ``name``.

        Arguments:
            name: the region name (e.g. ``"muscle:top"``).
            where: a shape; it adds no material, only its overlap with the final solid
                counts. The mesh conforms to its boundary.

        Returns:
            The same solid; its mesh gets the region ``name`` (tets and vertices).

        Raises:
            MeshError: on an empty name; at meshing time, if the overlap is empty.
        """
        return _Marked(self, _check_name(name), _check_shape(where))

    def _build(self, ctx: _Build) -> DimTags:
        raise NotImplementedError


def _check_shape(s: object) -> Shape:
    if not isinstance(s, Shape):
        raise TypeError(f"expected a Shape (Box, Cylinder, ...), got {type(s).__name__}")
    return s


def _check_name(name: str) -> str:
    if not isinstance(name, str) or not name.strip():
        raise MeshError(f"region names must be non-empty strings, got {name!r}")
    return name


@dataclass(frozen=True)
class Box(Shape):
    """An axis-aligned box.

    Arguments:
        size: edge lengths ``(lx, ly, lz)``, or one number for a cube.
        center: centre ``(3,)``.
    """

    size: Vector | float
    center: Vector = (0.0, 0.0, 0.0)

    def _build(self, ctx: _Build) -> DimTags:
        s = np.broadcast_to(np.asarray(self.size, dtype=np.float64), (3,))
        lx, ly, lz = (_positive(v, "Box size") for v in s)
        cx, cy, cz = _vec(self.center, "Box center")
        return [(3, gmsh.model.occ.addBox(cx - lx / 2, cy - ly / 2, cz - lz / 2, lx, ly, lz))]


@dataclass(frozen=True)
class Cylinder(Shape):
    """A circular cylinder.

    Arguments:
        radius: radius.
        length: length along the axis.
        center: centre of the axis segment ``(3,)``.
        axis: ``"x"``, ``"y"``, ``"z"`` or a direction ``(3,)``.
    """

    radius: float
    length: float
    center: Vector = (0.0, 0.0, 0.0)
    axis: Vector | str = "x"

    def _build(self, ctx: _Build) -> DimTags:
        r, L = _positive(self.radius, "Cylinder radius"), _positive(self.length, "Cylinder length")
        a = np.array(_vec(self.axis, "Cylinder axis", unit=True)) * L
        c = np.array(_vec(self.center, "Cylinder center")) - a / 2
        return [(3, gmsh.model.occ.addCylinder(*c, *a, r))]


@dataclass(frozen=True)
class Sphere(Shape):
    """A sphere of ``radius`` about ``center`` ``(3,)``."""

    radius: float
    center: Vector = (0.0, 0.0, 0.0)

    def _build(self, ctx: _Build) -> DimTags:
        r = _positive(self.radius, "Sphere radius")
        return [(3, gmsh.model.occ.addSphere(*_vec(self.center, "Sphere center"), r))]


@dataclass(frozen=True)
class Capsule(Shape):
    """A cylinder with hemispherical ends.

    Arguments:
        radius: radius.
        length: total length, tip to tip, along the axis (at least ``2 * radius``).
        center: centre ``(3,)``.
        axis: ``"x"``, ``"y"``, ``"z"`` or a direction ``(3,)``.
    """

    radius: float
    length: float
    center: Vector = (0.0, 0.0, 0.0)
    axis: Vector | str = "x"

    def _build(self, ctx: _Build) -> DimTags:
        r, L = _positive(self.radius, "Capsule radius"), _positive(self.length, "Capsule length")
        if L < 2 * r:
            raise MeshError(f"Capsule length {L} is shorter than its diameter {2 * r}; "
                            "use a Sphere or lengthen it")
        c = np.array(_vec(self.center, "Capsule center"))
        a = np.array(_vec(self.axis, "Capsule axis", unit=True))
        half = (L - 2 * r) / 2
        shape: Shape = Sphere(r, c - half * a) + Sphere(r, c + half * a)
        if half > 0:
            shape = shape + Cylinder(r, 2 * half, c, a)
        return shape._build(ctx)


@dataclass(frozen=True)
class CAD(Shape):
    """The solids in a STEP (``.step``, ``.stp``), IGES or BREP file, in metres.

    gmsh converts the file's units to metres. Files holding only surfaces are refused.
    """

    path: str | Path

    def _build(self, ctx: _Build) -> DimTags:
        path = Path(self.path)
        if not path.is_file():
            raise FileNotFoundError(f"no CAD file at {path}")
        try:
            out = gmsh.model.occ.importShapes(str(path), highestDimOnly=True)
        except Exception as err:
            raise _gmsh.gmsh_error(f"reading {path}", err,
                                   "check that it is a valid STEP, IGES or BREP file") from None
        solids = [dt for dt in out if dt[0] == 3]
        if not solids:
            raise MeshError(f"{path} holds no solid (only {len(out)} entities of dimension "
                            f"{sorted({d for d, _ in out})}); export it as a closed solid body")
        return solids


@dataclass(frozen=True)
class Tag(Shape):
    """A solid piece of the body whose tets and vertices form the region ``name``.

    Use it where material is added (``body + Tag(bone, "bone:spine")``); to name part of
    an existing body use :meth:`Shape.mark`.
    """

    shape: Shape
    name: str

    def _build(self, ctx: _Build) -> DimTags:
        _check_name(self.name)
        if ctx.removing:
            raise MeshError(f"Tag {self.name!r} is subtracted, so it would hold no material; "
                            "use Cavity(shape, name) for a hollow, or body.mark(name, where)")
        dimtags = _check_shape(self.shape)._build(ctx)
        ctx.tags.append((self.name, gmsh.model.occ.copy(dimtags)))
        return dimtags


@dataclass(frozen=True)
class Cavity(Shape):
    """A hollow cut from the body: ``body - Cavity(shape, name)``.

    The cavity's wall triangles (oriented into the cavity) and their vertices form the
    region ``"cavity:<name>"``.
    """

    shape: Shape
    name: str

    def _build(self, ctx: _Build) -> DimTags:
        _check_name(self.name)
        if not ctx.removing:
            raise MeshError(f"Cavity {self.name!r} must be subtracted from a solid: "
                            "write body - Cavity(shape, name)")
        dimtags = _check_shape(self.shape)._build(ctx)
        ctx.cavities.append((self.name, gmsh.model.occ.copy(dimtags)))
        return dimtags


@dataclass(frozen=True)
class _Boolean(Shape):
    op: str
    a: Shape
    b: Shape

    def _build(self, ctx: _Build) -> DimTags:
        a = self.a._build(ctx)
        removing = ctx.removing
        ctx.removing = removing != (self.op == "cut")
        try:
            b = self.b._build(ctx)
        finally:
            ctx.removing = removing
        try:
            out, _ = getattr(gmsh.model.occ, self.op)(a, b)
        except Exception as err:
            raise _gmsh.gmsh_error(f"boolean {self.op}", err,
                                   "avoid exactly tangent or coincident faces") from None
        out = [dt for dt in out if dt[0] == 3]
        if not out:
            what = {"cut": "removes the whole solid", "intersect": "is empty (the shapes do not overlap)",
                    "fuse": "is empty"}[self.op]
            raise MeshError(f"boolean {self.op} {what}; check the shapes' sizes and positions")
        return out


@dataclass(frozen=True)
class _Moved(Shape):
    shape: Shape
    how: tuple

    def _build(self, ctx: _Build) -> DimTags:
        n_cav, n_tag = len(ctx.cavities), len(ctx.tags)
        dimtags = self.shape._build(ctx)
        # Registered copies made inside this subtree move with it.
        targets = list(dimtags)
        for _, dts in ctx.cavities[n_cav:] + ctx.tags[n_tag:]:
            targets += dts
        if self.how[0] == "translate":
            gmsh.model.occ.translate(targets, *self.how[1])
        else:
            _, angle, axis, center = self.how
            gmsh.model.occ.rotate(targets, *center, *axis, angle)
        return dimtags


@dataclass(frozen=True)
class _Marked(Shape):
    shape: Shape
    name: str
    where: Shape

    def _build(self, ctx: _Build) -> DimTags:
        dimtags = self.shape._build(ctx)
        removing = ctx.removing
        ctx.removing = False
        try:
            ctx.tags.append((self.name, self.where._build(ctx)))
        finally:
            ctx.removing = removing
        return dimtags


# ---------------------------------------------------------------------------------------
# Boundary selections


@dataclass(frozen=True)
class OnPlane:
    """Select the vertices on the plane ``dot(p, axis) == value``.

    Arguments:
        axis: ``"x"``, ``"y"``, ``"z"`` or a normal ``(3,)`` (normalised).
        value: the plane's offset along ``axis``, in metres.
        tol: distance tolerance; default ``1e-6`` times the mesh's bounding-box diagonal.
    """

    axis: Vector | str
    value: float
    tol: float | None = None

    def __call__(self, points: np.ndarray, scale: float) -> np.ndarray:
        n = np.array(_vec(self.axis, "OnPlane axis", unit=True))
        tol = 1e-6 * scale if self.tol is None else self.tol
        return np.abs(points @ n - self.value) <= tol


@dataclass(frozen=True)
class InBox:
    """Select the vertices inside the axis-aligned box ``lo <= p <= hi`` (inclusive).

    Arguments:
        lo, hi: corners ``(3,)``.
        tol: tolerance; default ``1e-6`` times the mesh's bounding-box diagonal.
    """

    lo: Vector
    hi: Vector
    tol: float | None = None

    def __call__(self, points: np.ndarray, scale: float) -> np.ndarray:
        tol = 1e-6 * scale if self.tol is None else self.tol
        lo, hi = np.array(_vec(self.lo, "InBox lo")), np.array(_vec(self.hi, "InBox hi"))
        return np.all((points >= lo - tol) & (points <= hi + tol), axis=1)


#: A selection: :class:`OnPlane`, :class:`InBox`, or any ``f(points (n, 3), scale) -> (n,) bool``
#: where ``scale`` is the mesh's bounding-box diagonal (for tolerances).
Selection = Callable[[np.ndarray, float], np.ndarray]


def select_regions(mesh: TetMesh, select: Mapping[str, Selection]) -> TetMesh:
    """Add vertex-selection regions to a mesh.

    Each region holds the selected vertices and the surface triangles whose three
    vertices are all selected (outward oriented); it has no tets.

    Arguments:
        mesh: the mesh.
        select: region name -> selection (:class:`OnPlane`, :class:`InBox` or a callable).

    Returns:
        A new :class:`TetMesh` with the regions added.

    Raises:
        MeshError: when a selection matches no vertex or clashes with an existing region.
    """
    if not select:
        return mesh
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    scale = float(np.linalg.norm(hi - lo))
    new = {}
    for name, where in select.items():
        _check_name(name)
        if name in mesh.regions:
            raise MeshError(f"selection {name!r} clashes with an existing region of that name")
        mask = np.asarray(where(mesh.points, scale), dtype=bool)
        if mask.shape != (mesh.n_vertices,):
            raise MeshError(f"selection {name!r} must return one bool per vertex "
                            f"({mesh.n_vertices},), got shape {mask.shape}")
        if not mask.any():
            raise MeshError(f"selection {name!r} matched no vertex; the mesh spans "
                            f"{np.round(lo, 6).tolist()} to {np.round(hi, 6).tolist()} "
                            "(check the plane's value or the box's corners)")
        faces = mesh.surface[mask[mesh.surface].all(axis=1)]
        new[name] = Region(np.flatnonzero(mask), faces=faces)
    return mesh.with_regions(**new)


# ---------------------------------------------------------------------------------------
# Meshing


def mesh(
    shape: Shape,
    size: float,
    *,
    sizes: Mapping[str, float] | None = None,
    select: Mapping[str, Selection] | None = None,
    min_quality: float = DEFAULT_MIN_QUALITY,
    curvature: int = 12,
) -> TetMesh:
    """Tetrahedralise a shape with gmsh (OpenCASCADE kernel, Delaunay 3D, deterministic).

    Arguments:
        shape: the solid (see the module docstring).
        size: target element edge length in metres.
        sizes: region name -> local edge length, for tagged regions (``"bone:spine"``) and
            cavities (``"cavity:chamber"``, applied on its walls).
        select: region name -> boundary selection (:class:`OnPlane`, :class:`InBox`, callable).
        min_quality: refuse meshes whose worst tet has gamma quality below this
            (0 accepts any non-inverted mesh). A first mesh below it is optimised once
            more (Netgen's optimiser, then gmsh's) before being refused.
        curvature: at least this many elements per 2*pi of curvature on curved faces
            (0 turns it off).

    Returns:
        A :class:`TetMesh` with regions ``<tag name>`` (vertices, tets),
        ``"cavity:<name>"`` (vertices, faces into the cavity) and the selections.

    Raises:
        MeshError: on bad sizes, unknown region names in ``sizes``, empty booleans, tags or
            cavities that end up outside the solid, gmsh failures, and meshes below
            ``min_quality`` (the message says how to refine or lower it).
    """
    _check_shape(shape)
    size = _positive(size, "size")
    sizes = {k: _positive(h, f"size of region {k!r}") for k, h in (sizes or {}).items()}
    with _gmsh.session():
        ctx = _Build()
        solid = shape._build(ctx)
        kept, tag_vols, walls = _fragment(solid, ctx)
        local = []
        for name, h in sizes.items():
            if name in tag_vols:
                local.append((h, "VolumesList", tag_vols[name]))
            elif name in walls:
                local.append((h, "SurfacesList", walls[name]))
            else:
                raise MeshError(f"sizes names an unknown region {name!r}; the shape has "
                                f"{sorted(tag_vols) + sorted(walls)}")
        _gmsh.set_sizes(size, curvature, local)
        _gmsh.generate(min_quality)
        points, tets, slices, node_index = _gmsh.extract(kept)
        slice_of = dict(zip(kept, slices))
        regions = {}
        for name, vols in tag_vols.items():
            idx = np.concatenate([slice_of[v] for v in vols])
            regions[name] = Region(np.unique(tets[idx]), tets=idx)
        wall_tris = {name: _gmsh.triangles(s, node_index) for name, s in walls.items()}
    m = TetMesh(points, tets)
    for name, tris in wall_tris.items():
        faces = _orient_like(tris, m.surface)
        regions[name] = Region(np.unique(faces), faces=faces)
    m = select_regions(m.with_regions(**regions), select or {})
    check_quality(m, min_quality)
    return m


def _fragment(solid: DimTags, ctx: _Build) -> tuple[list[int], dict[str, list[int]], dict[str, list[int]]]:
    """Make tags and cavities conformal with the solid; drop everything outside it.

    Returns:
        ``(kept volumes, tag name -> volumes, "cavity:<name>" -> wall surfaces)``.
    """
    occ = gmsh.model.occ
    extra = ctx.cavities + ctx.tags
    if not extra:
        occ.synchronize()
        return sorted(t for _, t in solid), {}, {}
    tools = [dt for _, dts in extra for dt in dts]
    try:
        _, pieces = occ.fragment(solid, tools)
    except Exception as err:
        raise _gmsh.gmsh_error("making tagged parts conformal (fragment)", err,
                               "avoid exactly tangent or coincident faces") from None
    occ.synchronize()

    def vols(maps: list[DimTags]) -> set[int]:
        return {t for m in maps for d, t in m if d == 3}

    kept = vols(pieces[: len(solid)])
    groups: list[tuple[str, set[int]]] = []
    i = len(solid)
    for name, dts in extra:
        groups.append((name, vols(pieces[i: i + len(dts)])))
        i += len(dts)
    n_cav = len(ctx.cavities)
    up = {s: set(gmsh.model.getAdjacencies(2, s)[0].tolist()) for _, s in gmsh.model.getEntities(2)}
    walls: dict[str, list[int]] = {}
    for name, vs in groups[:n_cav]:
        void = vs - kept
        key = f"cavity:{name}"
        found = sorted(s for s, adj in up.items() if adj & void and adj & kept)
        if not found:
            raise MeshError(f"Cavity {name!r} does not lie inside the solid (it has no wall); "
                            "move it into the body")
        walls[key] = sorted(set(walls.get(key, [])) | set(found))
    tag_vols: dict[str, list[int]] = {}
    for name, vs in groups[n_cav:]:
        if name in walls:
            raise MeshError(f"region name {name!r} is used by both a tag and a cavity")
        tag_vols[name] = sorted(set(tag_vols.get(name, [])) | (vs & kept))
    for name, vs in tag_vols.items():
        if not vs:
            raise MeshError(f"tagged region {name!r} has no volume inside the solid; "
                            "move its shape into the body")
    drop = [(3, t) for _, t in gmsh.model.getEntities(3) if t not in kept]
    if drop:
        occ.remove(drop, recursive=True)
        occ.synchronize()
    return sorted(kept), tag_vols, walls


def _orient_like(faces: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``faces`` with each row replaced by the equally-noded row of ``reference``.

    Raises:
        MeshError: when a face is not in ``reference`` (a cavity wall that is not on the
            mesh boundary).
    """
    ref_key = np.sort(reference, axis=1)
    key = np.sort(faces, axis=1)
    dtype = np.dtype([("a", np.int64), ("b", np.int64), ("c", np.int64)])
    ref_view = np.ascontiguousarray(ref_key, dtype=np.int64).view(dtype).ravel()
    order = np.argsort(ref_view)
    want = np.ascontiguousarray(key, dtype=np.int64).view(dtype).ravel()
    pos = np.searchsorted(ref_view, want, sorter=order)
    pos = order[np.minimum(pos, len(order) - 1)]
    missing = (ref_key[pos] != key).any(axis=1)
    if missing.any():
        raise MeshError(f"{int(missing.sum())} cavity wall triangles are not on the mesh boundary; "
                        "the cavity overlaps a tagged part in a way gmsh could not resolve")
    return reference[pos]

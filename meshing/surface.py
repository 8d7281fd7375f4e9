"""Mesh a robot given as a closed triangle surface (STL, OBJ) or a CAD solid (STEP).

Triangle surfaces are checked before gmsh sees them: zero-area triangles, open edges
(holes), non-manifold edges (shared by more than two triangles) and self-intersections
(two triangles that cross, touch or overlap anywhere but in the edge or vertex they share,
degenerate contacts included) are refused with a message that names the first few. A
surface that passes is tetrahedralised by gmsh, by default after remeshing the surface to
the requested element size (gmsh's surface classification, which keeps sharp edges).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import gmsh
import meshio
import numpy as np

from . import _gmsh
from .geometry import CAD, DEFAULT_MIN_QUALITY, Selection, mesh, select_regions
from .mesh import MeshError, TetMesh
from .quality import check_quality

SURFACE_SUFFIXES = (".stl", ".obj")
CAD_SUFFIXES = (".step", ".stp", ".iges", ".igs", ".brep")
#: self-intersection tolerance, relative to the bounding-box diagonal
CONTACT_EPS = 1e-9


def read_surface(path: str | Path, *, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle surface from an STL or OBJ file.

    Vertices with identical coordinates are merged; OBJ quads are split in two triangles.

    Arguments:
        path: ``.stl`` or ``.obj`` file.
        scale: factor applied to the coordinates (e.g. 0.001 for a file in millimetres).

    Returns:
        ``(points (n, 3) float64, faces (f, 3) int64)``.

    Raises:
        FileNotFoundError: if there is no such file.
        MeshError: on another suffix, or a file holding no triangles.
    """
    path = Path(path)
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise MeshError(f"{path}: expected one of {SURFACE_SUFFIXES}, got {path.suffix!r}")
    if not path.is_file():
        raise FileNotFoundError(f"no surface file at {path}")
    with np.errstate(over="ignore"):  # meshio's binary-STL size test overflows on ASCII files
        raw = meshio.read(path)
    tris = []
    for block in raw.cells:
        if block.type == "triangle":
            tris.append(block.data)
        elif block.type == "quad":
            tris += [block.data[:, [0, 1, 2]], block.data[:, [0, 2, 3]]]
    if not tris:
        raise MeshError(f"{path} holds no triangles (cell types: {[c.type for c in raw.cells]})")
    points = np.asarray(raw.points, dtype=np.float64)[:, :3] * scale
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    faces = inverse.ravel()[np.concatenate(tris)]
    return unique, faces.astype(np.int64)


def _edges(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges ``(e, 2)`` (sorted pairs) and how many triangles use each."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def open_edges(faces: np.ndarray) -> np.ndarray:
    """Edges ``(k, 2)`` used by only one triangle (the rims of holes)."""
    e, n = _edges(np.asarray(faces))
    return e[n == 1]


def nonmanifold_edges(faces: np.ndarray) -> np.ndarray:
    """Edges ``(k, 2)`` shared by more than two triangles."""
    e, n = _edges(np.asarray(faces))
    return e[n > 2]


def self_intersections(points: np.ndarray, faces: np.ndarray, *, eps: float = CONTACT_EPS) -> np.ndarray:
    """Pairs of triangles that meet where the triangles of a closed surface may not.

    Two triangles of a closed surface may meet only in what they share: a common edge (and
    then they must not fold onto each other) or a common vertex. Everything else counts,
    the degenerate cases included: an edge piercing a triangle, an edge touching an edge,
    a vertex on a triangle, coplanar triangles that overlap, and two triangles sharing a
    vertex that run on into each other from it. Vertices with equal coordinates count as
    shared. Closest points and plane sides come from orientation determinants in float64,
    with ``eps`` times the bounding-box diagonal as the tolerance: features closer than
    that count as touching.

    Candidate pairs come from a k-d tree on the triangle centroids (bounding spheres that
    overlap) pruned by bounding boxes, O(f log f) for meshes of even element size; the
    candidates are tested together in numpy.

    Arguments:
        points: ``(n, 3)``.
        faces: ``(f, 3)`` triangles of non-zero area.
        eps: tolerance relative to the bounding-box diagonal.

    Returns:
        ``(k, 2)`` int64 triangle index pairs ``i < j``, sorted.
    """
    return _meetings(np.asarray(points, dtype=np.float64), np.asarray(faces, dtype=np.int64), eps)[0]


def _meetings(p: np.ndarray, f: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`self_intersections`' pairs ``(k, 2)``, and a point ``(k, 3)`` where each pair meets."""
    from scipy.spatial import cKDTree  # scipy.spatial takes ~0.5 s to import: only when needed

    none = np.zeros((0, 2), np.int64), np.zeros((0, 3))
    if len(f) < 2:
        return none
    tol = eps * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
    tri = p[f]
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    pairs = cKDTree(centroid).query_pairs(2 * radius.max() + tol, output_type="ndarray")
    if len(pairs) == 0:
        return none
    i, j = pairs[:, 0], pairs[:, 1]
    d = np.linalg.norm(centroid[i] - centroid[j], axis=1)
    lo, hi = tri.min(axis=1) - tol, tri.max(axis=1) + tol
    keep = (d <= radius[i] + radius[j] + tol) & np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    i, j = i[keep], j[keep]
    g = np.unique(p, axis=0, return_inverse=True)[1].ravel()[f]  # one index per location
    same = g[i][:, :, None] == g[j][:, None, :]  # (m, 3, 3): vertex a of i is vertex b of j
    in_j, in_i = same.any(axis=2), same.any(axis=1)  # which vertices of i (of j) are shared
    # Triangles whose unshared vertices all lie on one side of the other's plane (beyond
    # tol) meet at most in what they share: most candidates, on any surface but a flat one.
    normal = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    apart = np.zeros(len(i), bool)
    for one, other, mine in ((i, j, in_i), (j, i, in_j)):
        side = np.einsum("mvx,mx->mv", tri[other] - tri[one][:, :1], normal[one])
        one_side = np.all((side > tol) | mine, axis=1) | np.all((side < -tol) | mine, axis=1)
        apart |= ~mine.all(axis=1) & one_side
    i, j, in_i, in_j = i[~apart], j[~apart], in_i[~apart], in_j[~apart]
    shared = in_j.sum(axis=1)
    hit = shared == 3  # the same triangle twice
    where = centroid[i].copy()
    # No common vertex: any contact counts.
    k = np.flatnonzero(shared == 0)
    a, b = tri[i[k]], tri[j[k]]
    h, w = np.zeros(len(k), bool), np.zeros((len(k), 3))
    for s, t in ((0, 1), (1, 2), (2, 0)):
        for one, other in ((a, b), (b, a)):
            h, w = _first(h, w, *_segment_meets(one[:, s], one[:, t], other, tol))
    hit[k], where[k] = h, w
    # One common vertex v, A = (v, a1, a2), B = (v, b1, b2): the opposite edges must stay off
    # the other triangle, and the edges from v must not run into it.
    k = np.flatnonzero(shared == 1)
    a = _rolled(tri[i[k]], np.argmax(in_j[k], axis=1))
    b = _rolled(tri[j[k]], np.argmax(in_i[k], axis=1))
    h, w = _segment_meets(a[:, 1], a[:, 2], b, tol)
    h, w = _first(h, w, *_segment_meets(b[:, 1], b[:, 2], a, tol))
    for one, other in ((a, b), (b, a)):
        for s in (1, 2):
            h, w = _first(h, w, _runs_into(one[:, s], other, tol), one[:, 0])
    hit[k], where[k] = h, w
    # A common edge (v1, v2), A = (v1, v2, a), B = (v1, v2, b) up to order, left only when
    # a and b lie in each other's planes: A must not fold onto B (a on b's side of the edge).
    k = np.flatnonzero(shared == 2)
    a = _rolled(tri[i[k]], np.argmin(in_j[k], axis=1) + 1)
    b = _rolled(tri[j[k]], np.argmin(in_i[k], axis=1) + 1)
    edge = a[:, 1] - a[:, 0]
    hit[k] = _dot(np.cross(edge, a[:, 2] - a[:, 0]), np.cross(edge, b[:, 2] - a[:, 0])) > 0
    where[k] = (a[:, 0] + a[:, 1]) / 2
    out = np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1)[hit]
    order = np.lexsort(out.T[::-1])
    return out[order], where[hit][order]


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", u, v)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _rolled(t: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Triangles ``(m, 3, 3)`` with their vertices cycled to begin at index ``start`` (m,)."""
    return t[np.arange(len(t))[:, None], (start[:, None] + np.arange(3)) % 3]


def _first(hit: np.ndarray, where: np.ndarray, new: np.ndarray,
           at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Add the hits ``new`` (located ``at``) to ``hit``, keeping the earlier location of each."""
    fresh = new & ~hit
    return hit | new, np.where(fresh[:, None], at, where)


def _inside(x: np.ndarray, t: np.ndarray, n: np.ndarray, tol: float) -> np.ndarray:
    """Whether points ``x`` (m, 3) lie within ``tol`` of triangles ``t``' prisms along unit normals ``n``."""
    ok = np.ones(len(x), bool)
    for s, e in ((0, 1), (1, 2), (2, 0)):
        edge = t[:, e] - t[:, s]
        ok &= _dot(np.cross(edge, x - t[:, s]), n) >= -tol * np.linalg.norm(edge, axis=1)
    return ok


def _segment_meets(p: np.ndarray, q: np.ndarray, t: np.ndarray,
                   tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Whether segments ``pq`` (m, 3) come within ``tol`` of triangles ``t`` (m, 3, 3), and where.

    They do when the segment crosses the triangle's plane inside it, an end lies within
    ``tol`` of it, or the segment comes within ``tol`` of one of its edges (which covers
    segments lying in the plane).
    """
    n = _unit(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]))
    dp, dq = _dot(p - t[:, 0], n), _dot(q - t[:, 0], n)
    across = dp * dq < 0
    x = p + (dp / np.where(across, dp - dq, 1.0))[:, None] * (q - p)
    hit, where = across & _inside(x, t, n, tol), x
    for end, d in ((p, dp), (q, dq)):
        hit, where = _first(hit, where, (np.abs(d) <= tol) & _inside(end, t, n, tol), end)
    for s, e in ((0, 1), (1, 2), (2, 0)):
        gap, mid = _segment_gap(p, q, t[:, s], t[:, e])
        hit, where = _first(hit, where, gap <= tol, mid)
    return hit, where


def _segment_gap(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray,
                 q2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance between segments ``p1q1`` and ``p2q2`` (m, 3), and the midpoint of their closest points.

    Ericson, Real-Time Collision Detection, 5.1.9. The distance is measured between two
    points of the segments, so rounding can only overstate it.
    """
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e, f = _dot(d1, d1), _dot(d2, d2), _dot(d2, r)
    b, c = _dot(d1, d2), _dot(d1, r)
    denom = a * e - b * b
    crossing = denom > 1e-12 * a * e  # not parallel
    s = np.where(crossing, np.clip((b * f - c * e) / np.where(crossing, denom, 1.0), 0, 1), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a, 0, 1), np.where(t > 1, np.clip((b - c) / a, 0, 1), s))
    t = np.clip(t, 0, 1)
    x1, x2 = p1 + s[:, None] * d1, p2 + t[:, None] * d2
    return np.linalg.norm(x1 - x2, axis=1), (x1 + x2) / 2


def _runs_into(w: np.ndarray, t: np.ndarray, tol: float) -> np.ndarray:
    """Whether the segments from ``t[:, 0]`` to ``w`` (m, 3) run into triangles ``t`` beyond that vertex.

    They do when ``w`` lies within ``tol`` of the triangle's plane and inside its angle at
    ``t[:, 0]`` (within ``tol`` of both sides).
    """
    v, e1, e2 = t[:, 0], t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    n = _unit(np.cross(e1, e2))
    x = w - v
    return ((np.abs(_dot(x, n)) <= tol)
            & (_dot(np.cross(e1, x), n) >= -tol * np.linalg.norm(e1, axis=1))
            & (_dot(np.cross(x, e2), n) >= -tol * np.linalg.norm(e2, axis=1)))


def _where(points: np.ndarray, idx: np.ndarray) -> str:
    return str(np.round(points[np.asarray(idx)], 6).tolist())


def check_surface(points: np.ndarray, faces: np.ndarray) -> None:
    """Refuse a triangle surface that cannot bound a solid.

    Arguments:
        points: ``(n, 3)``.
        faces: ``(f, 3)``.

    Raises:
        MeshError: on zero-area triangles, open edges, non-manifold edges or
            self-intersections, naming how many and where the first ones are, and what
            to do about them.
    """
    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
        raise MeshError(f"a closed surface needs at least 4 triangles (f, 3), got shape {f.shape}")
    tri = p[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    tiny = np.flatnonzero(area <= 1e-12 * area.max())
    if len(tiny):
        raise MeshError(f"surface has {len(tiny)} zero-area triangles (first: triangle {tiny[0]}, "
                        f"vertices {f[tiny[0]].tolist()} at {_where(p, f[tiny[0]])}); remove them "
                        "(e.g. 'remove degenerate faces' in a mesh-repair tool)")
    problems = []
    for edges, what, fix in (
        (open_edges(f), "open edges", "close the holes"),
        (nonmanifold_edges(f), "non-manifold edges (shared by more than two triangles)",
         "split or merge the bodies that touch along them"),
    ):
        if len(edges):
            first = "; ".join(f"vertices {e.tolist()} at {_where(p, e)}" for e in edges[:3])
            problems.append(f"{len(edges)} {what} (first: {first}); {fix}")
    if problems:
        raise MeshError("surface is not watertight: " + "; and ".join(problems)
                        + " (a mesh-repair tool such as MeshLab or Blender's 3D-Print toolbox can)")
    cross, where = _meetings(p, f, CONTACT_EPS)
    if len(cross):
        first = "; ".join(f"triangles {a} and {b} at {np.round(x, 6).tolist()}"
                          for (a, b), x in zip(cross[:3], where))
        raise MeshError(f"surface intersects itself: {len(cross)} pairs of triangles cross, touch or overlap "
                        f"(first: {first}); overlapping bodies written into one file must be united "
                        "(boolean union in CAD, or a mesh-repair tool such as MeshLab or Blender's 3D-Print "
                        "toolbox) or moved apart before meshing")


def tetrahedralize(
    points: np.ndarray,
    faces: np.ndarray,
    size: float,
    *,
    remesh: bool = True,
    select: Mapping[str, Selection] | None = None,
    min_quality: float = DEFAULT_MIN_QUALITY,
) -> TetMesh:
    """Check a closed triangle surface and fill it with tets (gmsh, Delaunay 3D).

    Arguments:
        points: ``(n, 3)`` vertex positions in metres.
        faces: ``(f, 3)`` triangles of a closed, manifold, non-self-intersecting surface.
        size: target element edge length in metres.
        remesh: remesh the surface at ``size`` first (keeping edges sharper than 40
            degrees); with ``False`` the given triangles are the mesh's boundary.
        select: region name -> boundary selection, as in :func:`softbody.meshing.mesh`.
        min_quality: refuse meshes whose worst tet's gamma is below this (after one
            more optimisation pass, as in :func:`softbody.meshing.mesh`).

    Returns:
        The :class:`TetMesh`, with the selected regions.

    Raises:
        MeshError: from :func:`check_surface`; when gmsh fails to prepare the surface
            (the message suggests ``remesh=False``) or to fill it (e.g. gmsh's "PLC
            Error": the message says the surface crosses or touches itself or is not one
            closed surface and how to repair it, and with ``remesh`` that a smaller size or
            ``remesh=False`` may avoid crossings made by remeshing); on poor quality.
    """
    points = np.asarray(points, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    check_surface(points, faces)
    if not (np.isfinite(size) and size > 0):
        raise MeshError(f"size must be a positive finite length, got {size}")
    with _gmsh.session():
        surf = gmsh.model.addDiscreteEntity(2)
        used = np.unique(faces)
        gmsh.model.mesh.addNodes(2, surf, (used + 1).tolist(), points[used].ravel().tolist())
        gmsh.model.mesh.addElementsByType(surf, 2, [], (faces + 1).ravel().tolist())
        surfaces = [surf]
        try:
            if remesh:
                gmsh.model.mesh.classifySurfaces(np.radians(40), True, True, np.pi)
                gmsh.model.mesh.createGeometry()
                surfaces = [t for _, t in gmsh.model.getEntities(2)]
            loop = gmsh.model.geo.addSurfaceLoop(surfaces)
            vol = gmsh.model.geo.addVolume([loop])
            gmsh.model.geo.synchronize()
        except Exception as err:
            raise _gmsh.gmsh_error("preparing the surface", err,
                                   "try remesh=False (--keep-surface) to use the triangles as given") from None
        _gmsh.set_sizes(size, curvature=0)
        try:
            _gmsh.generate(min_quality)
            pts, tets, _, _ = _gmsh.extract([vol])
        except MeshError as err:
            raise _volume_failure(err, remesh, size) from None
    m = select_regions(TetMesh(pts, tets), select or {})
    check_quality(m, min_quality)
    return m


def _volume_failure(err: MeshError, remesh: bool, size: float) -> MeshError:
    """The error for a checked surface that gmsh could not fill with tets, with the advice that fits.

    gmsh's own exception, when it raised one, is ``err``'s context (kept by ``raise ... from
    None``); its message (e.g. "PLC Error: A segment and a facet intersect at point") is quoted.
    """
    cause = err.__context__
    said = (f"gmsh: {str(cause).strip() or 'no message'}" if isinstance(cause, Exception)
            else str(err).split(";")[0])
    repair = ("the surface passed softbody's checks, but gmsh finds that it crosses or touches itself or "
              "is not one closed surface (e.g. separate bodies written into one file that overlap or touch): "
              "repair it, e.g. boolean-union the parts in CAD or with a mesh-repair tool (MeshLab, Blender's "
              "3D-Print toolbox), and export one closed solid")
    if remesh:
        advice = (f"remeshing the surface at size {size:g} may have made thin walls or close parts cross: try "
                  f"remesh=False (--keep-surface) or a smaller size; if that fails too, {repair}")
    else:
        advice = f"{repair}; a smaller size will not help"
    return MeshError(f"meshing the solid inside the surface failed ({said}); {advice}")


def mesh_file(
    path: str | Path,
    size: float,
    *,
    scale: float = 1.0,
    remesh: bool = True,
    select: Mapping[str, Selection] | None = None,
    min_quality: float = DEFAULT_MIN_QUALITY,
) -> TetMesh:
    """Mesh the solid in an STL/OBJ surface file or a STEP/IGES/BREP CAD file.

    Arguments:
        path: the file; its suffix picks the reader.
        size: target element edge length in metres.
        scale: factor on STL/OBJ coordinates (STL has no units; 0.001 for millimetres).
            CAD files carry units and are converted to metres.
        remesh: for STL/OBJ, see :func:`tetrahedralize`.
        select: region name -> boundary selection.
        min_quality: refuse meshes whose worst tet's gamma is below this.

    Returns:
        The :class:`TetMesh`.

    Raises:
        FileNotFoundError: if there is no such file.
        MeshError: on an unsupported suffix, a bad surface, or a failed or poor mesh.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in CAD_SUFFIXES:
        if scale != 1.0:
            raise MeshError("scale applies to STL/OBJ files only; CAD files carry their own units")
        return mesh(CAD(path), size, select=select, min_quality=min_quality)
    if suffix in SURFACE_SUFFIXES:
        points, faces = read_surface(path, scale=scale)
        return tetrahedralize(points, faces, size, remesh=remesh, select=select, min_quality=min_quality)
    raise MeshError(f"cannot mesh {path}: expected one of {SURFACE_SUFFIXES + CAD_SUFFIXES}")

"""Mesh a robot given as a closed triangle surface (STL, OBJ) or a CAD solid (STEP).

Triangle surfaces are checked before gmsh sees them: zero-area triangles, open edges
(holes), non-manifold edges (shared by more than two triangles) and self-intersections
(two triangles crossing) are refused with a message that names the first few. A surface
that passes is tetrahedralised by gmsh, by default after remeshing the surface to the
requested element size (gmsh's surface classification, which keeps sharp edges).
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


def self_intersections(points: np.ndarray, faces: np.ndarray, *, eps: float = 1e-9) -> np.ndarray:
    """Pairs of triangles that cross each other.

    Candidate pairs come from a k-d tree on the triangle centroids (bounding spheres that
    overlap) pruned by bounding boxes, O(f log f) for meshes of even element size; each
    candidate is tested by whether an edge of one triangle pierces the interior of the
    other. Triangles sharing an edge, and contacts only at shared vertices, do not count;
    overlapping coplanar triangles are not detected.

    Arguments:
        points: ``(n, 3)``.
        faces: ``(f, 3)``.
        eps: relative tolerance of the piercing test.

    Returns:
        ``(k, 2)`` int64 triangle index pairs ``i < j``.
    """
    from scipy.spatial import cKDTree  # scipy.spatial takes ~0.5 s to import: only when needed

    p = np.asarray(points, dtype=np.float64)
    f = np.asarray(faces)
    tri = p[f]
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max(axis=1)
    pairs = cKDTree(centroid).query_pairs(2 * radius.max(), output_type="ndarray")
    if len(pairs) == 0:
        return np.zeros((0, 2), np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    d = np.linalg.norm(centroid[i] - centroid[j], axis=1)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    keep = (d <= radius[i] + radius[j]) & np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    # Triangles sharing an edge can only overlap if coplanar, which is not tested: skip them.
    shared = (f[i][:, :, None] == f[j][:, None, :]).sum(axis=(1, 2))
    keep &= shared < 2
    i, j = i[keep], j[keep]
    hit = _pierces(tri[i], tri[j], eps) | _pierces(tri[j], tri[i], eps)
    out = np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1)[hit]
    return out[np.lexsort(out.T[::-1])]


def _pierces(a: np.ndarray, b: np.ndarray, eps: float) -> np.ndarray:
    """Whether any edge of triangles ``a`` (m, 3, 3) crosses the interior of ``b`` (m, 3, 3)."""
    e1, e2 = b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]
    hit = np.zeros(len(a), dtype=bool)
    for s, t in ((0, 1), (1, 2), (2, 0)):
        p0, d = a[:, s], a[:, t] - a[:, s]
        h = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, h)
        scale = np.linalg.norm(d, axis=1) * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
        ok = np.abs(det) > eps * scale  # not parallel to the triangle's plane
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        sv = p0 - b[:, 0]
        u = inv * np.einsum("ij,ij->i", sv, h)
        q = np.cross(sv, e1)
        v = inv * np.einsum("ij,ij->i", d, q)
        w = inv * np.einsum("ij,ij->i", e2, q)  # position along the edge, 0..1
        hit |= ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (w > eps) & (w < 1 - eps)
    return hit


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
    cross = self_intersections(p, f)
    if len(cross):
        a, b = cross[0]
        raise MeshError(f"surface intersects itself: {len(cross)} pairs of triangles cross (first: "
                        f"triangles {a} and {b} near {np.round(p[f[a]].mean(axis=0), 6).tolist()}); union the "
                        "overlapping parts or separate them before meshing")


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
        MeshError: from :func:`check_surface`, on gmsh failures (the message suggests
            ``remesh=False`` or a smaller size) and on poor quality.
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
        _gmsh.generate(min_quality)
        pts, tets, _, _ = _gmsh.extract([vol])
    m = select_regions(TetMesh(pts, tets), select or {})
    check_quality(m, min_quality)
    return m


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

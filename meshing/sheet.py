"""Flat sheets as triangle meshes: cloth and thin shells (:func:`rectangle`, :func:`disc`:
gmsh OCC, 2-D Delaunay; :func:`grid`: structured, without gmsh).

A sheet is a :class:`~softbody.meshing.TetMesh` without tets: its ``surface`` holds the
triangles (normals along ``+z``), its region ``"sheet"`` all vertices and triangles, and
any ``select`` regions their vertices and the triangles among them (as
:func:`~softbody.meshing.select_regions` makes them). :func:`softbody.shell.shell_body`
makes a body of it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import gmsh
import numpy as np

from ._gmsh import gmsh_error, session
from .geometry import Selection, select_regions
from .mesh import MeshError, Region, TetMesh

_TRIANGLE = 2


def _sheet(make, size: float, select: Mapping[str, Selection] | None, what: str) -> TetMesh:
    """Mesh the plane surface that ``make()`` adds to a fresh gmsh model."""
    if not (np.isfinite(size) and size > 0):
        raise MeshError(f"{what}: size must be a positive edge length in metres, got {size}")
    with session("sheet"):
        try:
            make()
            gmsh.model.occ.synchronize()
            gmsh.option.setNumber("Mesh.MeshSizeMax", size)
            gmsh.option.setNumber("Mesh.MeshSizeMin", 0.0)
            gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 24)
            gmsh.option.setNumber("Mesh.Algorithm", 5)  # Delaunay: deterministic
            gmsh.model.mesh.generate(2)
        except Exception as err:  # noqa: BLE001 (gmsh raises bare Exception with its last error)
            raise gmsh_error(f"{what} meshing", err, "try another size") from None
        types, _, nodes = gmsh.model.mesh.getElements(2)
        raw = np.concatenate([n for t, n in zip(types, nodes) if t == _TRIANGLE]).reshape(-1, 3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
    used = np.unique(raw)
    order = np.argsort(tags)
    points = coords.reshape(-1, 3)[order[np.searchsorted(tags, used, sorter=order)]]
    points[:, 2] = 0.0
    tri = np.searchsorted(used, raw).astype(np.int32)
    p = points[tri]
    up = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[:, 2]
    tri[up < 0] = tri[up < 0][:, [0, 2, 1]]
    mesh = TetMesh(points, np.zeros((0, 4), np.int32), tri,
                   {"sheet": Region(np.arange(len(points)), faces=tri)})
    return select_regions(mesh, select or {})


def rectangle(width: float, height: float, size: float, *, x0: float = 0.0,
              select: Mapping[str, Selection] | None = None) -> TetMesh:
    """The rectangle ``x0 <= x <= x0 + width``, ``0 <= y <= height`` in the plane ``z = 0``,
    as triangles of edge length about ``size``; with ``x0 < 0`` its edges follow the line
    ``x = 0`` too (e.g. the edge of a clamp holding ``x <= 0``).

    Arguments:
        width, height: the sides, m (> 0); x0: where the rectangle starts along ``x``, m.
        size: target edge length, m (> 0).
        select: region name -> selection (e.g. ``{"clamp": OnPlane("x", 0.0)}``).

    Returns:
        A :class:`~softbody.meshing.TetMesh` without tets (see the module docstring).

    Raises:
        MeshError: non-positive sides or size, a selection that matches no vertex, or a
            gmsh failure.
    """
    if not (width > 0 and height > 0):
        raise MeshError(f"rectangle: width and height must be > 0, got {width}, {height}")

    def make():
        sheet = gmsh.model.occ.addRectangle(x0, 0.0, 0.0, width, height)
        if x0 < 0 < x0 + width:
            line = gmsh.model.occ.addLine(gmsh.model.occ.addPoint(0.0, 0.0, 0.0),
                                          gmsh.model.occ.addPoint(0.0, height, 0.0))
            gmsh.model.occ.fragment([(2, sheet)], [(1, line)])

    return _sheet(make, size, select, "rectangle")


def disc(radius: float, size: float, *, rings: Sequence[float] = (),
         select: Mapping[str, Selection] | None = None) -> TetMesh:
    """The disc of ``radius`` about the origin in the plane ``z = 0``, as triangles of edge
    length about ``size``.

    Arguments:
        radius: m (> 0); size: target edge length, m (> 0).
        rings: radii ``0 < r < radius`` of circles that edges of the mesh follow (e.g. the
            edge of a clamp: ``select={"clamp": lambda p, s: np.hypot(p[:, 0], p[:, 1]) >= r - 1e-9}``).
        select: region name -> selection.

    Returns:
        A :class:`~softbody.meshing.TetMesh` without tets (see the module docstring).

    Raises:
        MeshError: a non-positive radius or size, a selection that matches no vertex, or a
            gmsh failure.
    """
    if not radius > 0:
        raise MeshError(f"disc: radius must be > 0, got {radius}")
    rings = sorted(float(r) for r in rings)
    if rings and not (rings[0] > 0 and rings[-1] < radius):
        raise MeshError(f"disc: rings must lie strictly between 0 and the radius {radius}, got {rings}")

    def make():
        outer = gmsh.model.occ.addDisk(0.0, 0.0, 0.0, radius, radius)
        if rings:
            circles = [gmsh.model.occ.addCircle(0.0, 0.0, 0.0, r) for r in rings]
            gmsh.model.occ.fragment([(2, outer)], [(1, c) for c in circles])

    return _sheet(make, size, select, "disc")


def grid(width: float, height: float, cells: tuple[int, int], *,
         select: Mapping[str, Selection] | None = None) -> TetMesh:
    """The rectangle ``0 <= x <= width``, ``0 <= y <= height`` in the plane ``z = 0`` as a
    structured grid of ``cells[0] x cells[1]`` rectangles, each cut into two triangles by a
    diagonal that alternates between neighbouring cells (no preferred direction): the
    ``(nx + 1) x (ny + 1)`` vertices of a cloth benchmark (vertex ``i (ny + 1) + j`` at
    ``(i width / nx, j height / ny)``), without gmsh.

    Arguments:
        width, height: the sides, m (> 0); cells: ``(nx, ny)``, integers >= 1.
        select: region name -> selection.

    Returns:
        A :class:`~softbody.meshing.TetMesh` without tets (see the module docstring).

    Raises:
        MeshError: non-positive sides, cell counts that are not integers >= 1, or a
            selection that matches no vertex.
    """
    if not (np.isfinite(width) and np.isfinite(height) and width > 0 and height > 0):
        raise MeshError(f"grid: width and height must be > 0, got {width}, {height}")
    if len(cells) != 2 or not all(isinstance(c, (int, np.integer)) and c >= 1 for c in cells):
        raise MeshError(f"grid: cells must be two integers >= 1 (cells along x and y), got {cells!r}")
    nx, ny = int(cells[0]), int(cells[1])
    a, b = np.meshgrid(np.linspace(0.0, width, nx + 1), np.linspace(0.0, height, ny + 1), indexing="ij")
    points = np.stack([a.ravel(), b.ravel(), np.zeros(a.size)], axis=1)
    idx = np.arange(a.size).reshape(nx + 1, ny + 1)
    i, j = (m.ravel() for m in np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"))
    p, q, r, s = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
    odd = ((i + j) % 2 == 1)[:, None]
    first = np.where(odd, np.stack([p, q, r], 1), np.stack([p, q, s], 1))
    second = np.where(odd, np.stack([p, r, s], 1), np.stack([q, r, s], 1))
    tri = np.concatenate([first, second]).astype(np.int32)  # counter-clockwise: normals along +z
    mesh = TetMesh(points, np.zeros((0, 4), np.int32), tri,
                   {"sheet": Region(np.arange(len(points)), faces=tri)})
    return select_regions(mesh, select or {})

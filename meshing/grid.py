"""Structured tet grids: a box of hexahedral cells, each split into 6 tets.

Useful where a gmsh mesh is not needed: convergence studies with exact refinement,
benchmarks shared with grid-based simulators, and quick tests.
"""

from __future__ import annotations

import numpy as np

from .mesh import Region, TetMesh

# The 6 tets of a unit cube around the diagonal 0-6 (Kuhn/Freudenthal split), vertices
# numbered x + 2y + 4z; each positively oriented.
_CUBE = np.array([(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
_KUHN = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


def grid_box(size=(1.0, 1.0, 1.0), cells=(4, 4, 4), origin=(0.0, 0.0, 0.0)) -> TetMesh:
    """A box meshed as a structured grid of ``cells`` hexahedra, each split into 6 tets.

    Arguments:
        size: box edge lengths ``(lx, ly, lz)`` in metres.
        cells: number of cells along each axis.
        origin: the corner with the smallest coordinates.

    Returns:
        A :class:`TetMesh` with regions ``"xmin"``, ``"xmax"``, ``"ymin"``, ``"ymax"``,
        ``"zmin"``, ``"zmax"`` (the vertices on each face); ``"fixed"`` = ``"xmin"`` and
        ``"tip"`` = ``"xmax"`` for cantilever use.

    Raises:
        ValueError: non-positive sizes or cell counts.
    """
    size, cells, origin = np.asarray(size, float), np.asarray(cells, int), np.asarray(origin, float)
    if size.shape != (3,) or cells.shape != (3,) or np.any(size <= 0) or np.any(cells < 1):
        raise ValueError(f"grid_box needs 3 positive sizes and cell counts, got size={size}, cells={cells}")
    nx, ny, nz = cells
    axes = [np.linspace(o, o + s, c + 1) for o, s, c in zip(origin, size, cells)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    points = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)

    def vid(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    corners = np.stack([vid(i + int(c[0]), j + int(c[1]), k + int(c[2])) for c in _CUBE], axis=1)
    tets = corners[:, _KUHN].reshape(-1, 4)
    regions = {}
    for axis, name in enumerate("xyz"):
        lo, hi = axes[axis][0], axes[axis][-1]
        regions[f"{name}min"] = Region(np.flatnonzero(np.isclose(points[:, axis], lo)))
        regions[f"{name}max"] = Region(np.flatnonzero(np.isclose(points[:, axis], hi)))
    regions["fixed"] = regions["xmin"]
    regions["tip"] = regions["xmax"]
    return TetMesh(points, tets.astype(np.int32), regions=regions)

"""softbody.meshing: robot geometry to checked tetrahedral meshes (gmsh OCC).

This folder (``meshing/`` in the repository) installs as ``softbody.meshing``.

Build a solid from primitives and booleans, name its parts, mesh it::

    from softbody import meshing as sm

    body = sm.Box((0.09, 0.02, 0.02), center=(0.045, 0, 0))
    chamber = sm.Cavity(sm.Box((0.07, 0.014, 0.006), center=(0.045, 0, 0.004)), "chamber")
    mesh = sm.mesh(body - chamber, size=0.004, select={"fixed": sm.OnPlane("x", 0.0)})
    print(sm.quality_report(mesh))
    sm.save(mesh, "finger.msh")

Region names: ``"cavity:<name>"`` (wall triangles facing into the cavity),
``"bone:<name>"``, ``"muscle:<name>"`` and other tags (tets and vertices), and selections
such as ``"fixed"`` and ``"tip"`` (vertices, and the surface triangles among them).
Example robots: :data:`EXAMPLES` (``cantilever``, ``finger``, ``quadruped``,
``caterpillar``, ``cube``, ``ball``). Surfaces: :func:`mesh_file` (STL, OBJ, STEP).
Structured boxes without gmsh: :func:`grid_box`. Flat sheets of triangles (cloth, thin
shells; no tets): :mod:`softbody.meshing.sheet` (``rectangle``, ``disc``, ``grid``).
"""

from .examples import EXAMPLES, ball, cantilever, caterpillar, cube, finger, quadruped
from .geometry import (
    CAD,
    DEFAULT_MIN_QUALITY,
    Box,
    Capsule,
    Cavity,
    Cylinder,
    InBox,
    OnPlane,
    Selection,
    Shape,
    Sphere,
    Tag,
    mesh,
    select_regions,
)
from . import sheet
from .grid import grid_box
from .io import load, save
from .mesh import MeshError, Region, TetMesh, boundary_faces, signed_volumes
from .quality import (
    QualityReport,
    RegionSummary,
    check_quality,
    dihedral_angles,
    enclosed_volume,
    gamma,
    quality_report,
)
from .surface import (
    check_surface,
    mesh_file,
    nonmanifold_edges,
    open_edges,
    read_surface,
    self_intersections,
    tetrahedralize,
)

__all__ = [
    "MeshError", "Region", "TetMesh", "boundary_faces", "signed_volumes", "grid_box",
    "Shape", "Box", "Cylinder", "Sphere", "Capsule", "CAD", "Tag", "Cavity",
    "OnPlane", "InBox", "Selection", "mesh", "select_regions", "DEFAULT_MIN_QUALITY",
    "QualityReport", "RegionSummary", "quality_report", "check_quality", "gamma",
    "dihedral_angles", "enclosed_volume",
    "save", "load",
    "read_surface", "check_surface", "open_edges", "nonmanifold_edges", "self_intersections",
    "tetrahedralize", "mesh_file",
    "sheet",
    "EXAMPLES", "cantilever", "finger", "quadruped", "caterpillar", "cube", "ball",
]

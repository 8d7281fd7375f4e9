"""softbody.meshing: robot geometry to checked tetrahedral meshes (gmsh OCC).

This folder (``meshing/`` in the repository) installs as ``softbody.meshing``.
"""

from .mesh import MeshError, Region, TetMesh, boundary_faces, signed_volumes

__all__ = ["MeshError", "Region", "TetMesh", "boundary_faces", "signed_volumes"]

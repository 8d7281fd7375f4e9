"""The tetrahedral mesh every later stage consumes.

A :class:`TetMesh` is immutable and validated when it is made: positively oriented,
non-degenerate tets, outward boundary triangles, named regions whose indices are in range.
Regions carry vertex indices, element (tet) indices and, where it makes sense, triangles
(a cavity's inner surface, oriented into the cavity). Region names follow
``"kind:name"`` (``"cavity:left"``, ``"bone:spine"``, ``"muscle:back"``) or plain
``"fixed"``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping

import numpy as np


class MeshError(ValueError):
    """A mesh or a geometry failed a check; the message names the defect and the fix."""


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Region:
    """A named subset of a mesh.

    Attributes:
        vertices: ``(k,)`` int32, sorted unique vertex indices.
        tets: ``(m,)`` int32, sorted unique element indices (may be empty for surface regions).
        faces: ``(f, 3)`` int32 triangles (may be empty); for a cavity they face into it.
    """

    vertices: np.ndarray
    tets: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))

    def __post_init__(self):
        v = np.unique(np.asarray(self.vertices, dtype=np.int64)).astype(np.int32)
        t = np.unique(np.asarray(self.tets, dtype=np.int64)).astype(np.int32)
        f = np.asarray(self.faces, dtype=np.int32).reshape(-1, 3)
        object.__setattr__(self, "vertices", _frozen(v))
        object.__setattr__(self, "tets", _frozen(t))
        object.__setattr__(self, "faces", _frozen(f))


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volume of each tet, ``(t,)``; positive for positively oriented tets."""
    p = points[tets]
    d = p[:, 1:] - p[:, :1]
    return np.linalg.det(d) / 6.0


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles of a positively oriented tet mesh, ``(f, 3)``, outward normals."""
    tets = np.asarray(tets)
    # Faces opposite vertex 0..3, ordered so their normals point out of the tet.
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1].astype(np.int32)


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A validated, immutable tetrahedral mesh.

    Attributes:
        points: ``(n, 3)`` float64 vertex positions in metres.
        tets: ``(t, 4)`` int32 vertex indices, positively oriented (signed volume > 0);
            ``t = 0`` only with a given ``surface`` (a scene of rigid bodies only).
        surface: ``(f, 3)`` int32 boundary triangles with outward normals. Computed from
            ``tets`` when not given.
        regions: name -> :class:`Region`.
        fields: name -> per-tet array ``(t, ...)`` (e.g. ``"fibre"``: ``(t, 3)`` directions).

    Raises:
        MeshError: on bad shapes, non-finite points, out-of-range indices, or inverted or
            degenerate tets (the message counts them and says how to fix them).
    """

    points: np.ndarray
    tets: np.ndarray
    surface: np.ndarray | None = None
    regions: Mapping[str, Region] = field(default_factory=dict)
    fields: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        pts = np.asarray(self.points, dtype=np.float64)
        tets = np.asarray(self.tets)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MeshError(f"points must have shape (n, 3), got {pts.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4 or (len(tets) == 0 and self.surface is None):
            raise MeshError(f"tets must have shape (t, 4) with t > 0 (t = 0 only with a given surface: the "
                            f"scene of rigid bodies), got {tets.shape}")
        if not np.all(np.isfinite(pts)):
            raise MeshError(f"{int((~np.isfinite(pts)).any(axis=1).sum())} points are not finite")
        if tets.size and (tets.min() < 0 or tets.max() >= len(pts)):
            raise MeshError(f"tet indices must lie in [0, {len(pts)}), got [{tets.min()}, {tets.max()}]")
        tets = tets.astype(np.int32)
        vol = signed_volumes(pts, tets)
        scale = np.abs(vol).max(initial=0.0)
        inverted = int((vol < 0).sum())
        degenerate = int((np.abs(vol) <= 1e-12 * scale).sum())
        if inverted or degenerate:
            raise MeshError(
                f"{inverted} inverted and {degenerate} degenerate (zero-volume) tets; "
                "reorder inverted tets' vertices (swap two) and remove or remesh degenerate ones"
            )
        surface = boundary_faces(tets) if self.surface is None else np.asarray(self.surface, np.int32)
        if surface.ndim != 2 or surface.shape[1] != 3:
            raise MeshError(f"surface must have shape (f, 3), got {surface.shape}")
        regions = {}
        for name, reg in dict(self.regions).items():
            if not isinstance(reg, Region):
                reg = Region(**reg) if isinstance(reg, Mapping) else Region(np.asarray(reg))
            for what, idx, bound in (("vertices", reg.vertices, len(pts)), ("tets", reg.tets, len(tets)),
                                     ("faces", reg.faces, len(pts))):
                if idx.size and (idx.min() < 0 or idx.max() >= bound):
                    raise MeshError(f"region {name!r}: {what} index out of range [0, {bound})")
            regions[name] = reg
        fields = {}
        for name, val in dict(self.fields).items():
            val = np.asarray(val)
            if val.shape[:1] != (len(tets),):
                raise MeshError(f"field {name!r} must have one row per tet ({len(tets)}), got {val.shape}")
            fields[name] = _frozen(val)
        object.__setattr__(self, "points", _frozen(pts))
        object.__setattr__(self, "tets", _frozen(tets))
        object.__setattr__(self, "surface", _frozen(surface))
        object.__setattr__(self, "regions", MappingProxyType(regions))
        object.__setattr__(self, "fields", MappingProxyType(fields))

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def volumes(self) -> np.ndarray:
        """Volume of each tet, ``(t,)``, all positive."""
        return signed_volumes(self.points, self.tets)

    def region(self, name: str) -> Region:
        """The region called ``name``.

        Raises:
            KeyError: naming the regions that exist.
        """
        try:
            return self.regions[name]
        except KeyError:
            raise KeyError(f"no region {name!r} in this mesh; it has {sorted(self.regions)}") from None

    def with_regions(self, **regions: Region) -> "TetMesh":
        """A copy with regions added or replaced."""
        return TetMesh(self.points, self.tets, self.surface, {**self.regions, **regions}, self.fields)

    def __repr__(self) -> str:
        return (f"TetMesh({self.n_vertices} vertices, {self.n_tets} tets, {len(self.surface)} surface "
                f"triangles, regions={sorted(self.regions)})")

"""Tet quality: a report for people and a check that refuses poor meshes.

The quality measure is gamma, ``3 * inradius / circumradius``: 1 for a regular
tetrahedron, 0 for a flat one. It is the same number as gmsh's ``"gamma"`` quality
(``gmsh.model.mesh.getElementQualities(tags, "gamma")``), computed here in numpy so that
any :class:`TetMesh` (loaded from a file, morphed) can be checked. Slivers (four nearly
coplanar vertices) have small gamma and small dihedral angles; they make projective
dynamics' per-tet projections ill-conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import MeshError, TetMesh, signed_volumes

# Faces of a tet as vertex triples, and the pairs of faces meeting at each of its 6 edges.
_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
_EDGE_FACES = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


def gamma(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Gamma quality ``3 * inradius / circumradius`` of each tet.

    Arguments:
        points: ``(n, 3)`` vertex positions.
        tets: ``(t, 4)`` vertex indices.

    Returns:
        ``(t,)`` in [0, 1]; 1 for a regular tet, 0 for a degenerate one.
    """
    p = np.asarray(points, dtype=np.float64)[np.asarray(tets)]
    e = p[:, 1:] - p[:, :1]
    vol = np.abs(np.linalg.det(e)) / 6.0
    area = sum(0.5 * np.linalg.norm(np.cross(p[:, f[1]] - p[:, f[0]], p[:, f[2]] - p[:, f[0]]), axis=1)
               for f in _FACES)
    a, b, c = e[:, 0], e[:, 1], e[:, 2]
    # circumcentre offset from vertex 0: (|a|^2 b x c + |b|^2 c x a + |c|^2 a x b) / (12 V)
    num = ((a * a).sum(1)[:, None] * np.cross(b, c) + (b * b).sum(1)[:, None] * np.cross(c, a)
           + (c * c).sum(1)[:, None] * np.cross(a, b))
    with np.errstate(divide="ignore", invalid="ignore"):
        r_in = 3.0 * vol / area
        r_circ = np.linalg.norm(num, axis=1) / (12.0 * vol)
        q = 3.0 * r_in / r_circ
    return np.where(vol > 0, np.nan_to_num(q, nan=0.0), 0.0)


def dihedral_angles(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Interior dihedral angles of each tet in degrees, ``(t, 6)`` (one per edge)."""
    p = np.asarray(points, dtype=np.float64)[np.asarray(tets)]
    tri = p[:, _FACES]  # (t, 4, 3 vertices, 3)
    n = np.cross(tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        n = n / np.linalg.norm(n, axis=2, keepdims=True)
    cos = -(n[:, _EDGE_FACES[:, 0]] * n[:, _EDGE_FACES[:, 1]]).sum(axis=2)
    return np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0)))


def enclosed_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by a closed triangle surface whose normals point INTO it.

    This is the orientation of a cavity region's faces; for outward-facing triangles
    the result is minus the volume.

    Arguments:
        points: ``(n, 3)``.
        faces: ``(f, 3)`` triangles.

    Returns:
        The volume in cubic metres (divergence theorem).
    """
    p = np.asarray(points, dtype=np.float64)[np.asarray(faces)]
    return float(-np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0)


@dataclass(frozen=True)
class RegionSummary:
    """Counts for one region; ``cavity_volume`` only for ``"cavity:"`` regions."""

    name: str
    n_vertices: int
    n_tets: int
    n_faces: int
    cavity_volume: float | None = None


@dataclass(frozen=True)
class QualityReport:
    """Size and quality of a tet mesh (gamma quality, see the module docstring).

    Attributes:
        n_vertices, n_tets, n_surface: counts.
        n_inverted: tets with signed volume <= 0 (0 for any valid :class:`TetMesh`).
        min_quality, median_quality: gamma, 1 for a regular tet.
        min_dihedral: smallest interior dihedral angle, degrees.
        max_dihedral: largest interior dihedral angle, degrees.
        volume: total volume, cubic metres.
        regions: one :class:`RegionSummary` per region, sorted by name.
        fields: per-tet field names and their shapes.
    """

    n_vertices: int
    n_tets: int
    n_surface: int
    n_inverted: int
    min_quality: float
    median_quality: float
    min_dihedral: float
    max_dihedral: float
    volume: float
    regions: tuple[RegionSummary, ...]
    fields: tuple[tuple[str, tuple[int, ...]], ...]

    def __str__(self) -> str:
        lines = [
            f"{self.n_vertices} nodes, {self.n_tets} tets, {self.n_surface} surface triangles, "
            f"{self.n_inverted} inverted",
            f"quality (gamma): min {self.min_quality:.3f}, median {self.median_quality:.3f}; "
            f"dihedral angles {self.min_dihedral:.1f} to {self.max_dihedral:.1f} deg",
            f"volume {self.volume:.6g} m^3 ({self.volume * 1e6:.4g} cm^3)",
        ]
        if self.regions:
            lines.append("regions:")
            width = max(len(r.name) for r in self.regions)
            for r in self.regions:
                parts = [f"{r.n_vertices} vertices"]
                if r.n_tets:
                    parts.append(f"{r.n_tets} tets")
                if r.n_faces:
                    parts.append(f"{r.n_faces} faces")
                if r.cavity_volume is not None:
                    parts.append(f"encloses {r.cavity_volume * 1e6:.4g} cm^3")
                lines.append(f"  {r.name:<{width}}  " + ", ".join(parts))
        if self.fields:
            lines.append("fields: " + ", ".join(f"{n} {s}" for n, s in self.fields))
        return "\n".join(lines)


def quality_report(mesh: TetMesh) -> QualityReport:
    """Measure a mesh.

    Arguments:
        mesh: the mesh.

    Returns:
        A :class:`QualityReport`; ``str(report)`` is a readable summary.
    """
    vol = signed_volumes(mesh.points, mesh.tets)
    q = gamma(mesh.points, mesh.tets)
    dih = dihedral_angles(mesh.points, mesh.tets)
    regions = tuple(
        RegionSummary(name, len(r.vertices), len(r.tets), len(r.faces),
                      enclosed_volume(mesh.points, r.faces) if name.startswith("cavity:") else None)
        for name, r in sorted(mesh.regions.items())
    )
    return QualityReport(
        n_vertices=mesh.n_vertices,
        n_tets=mesh.n_tets,
        n_surface=len(mesh.surface),
        n_inverted=int((vol <= 0).sum()),
        min_quality=float(q.min()),
        median_quality=float(np.median(q)),
        min_dihedral=float(dih.min()),
        max_dihedral=float(dih.max()),
        volume=float(vol.sum()),
        regions=regions,
        fields=tuple((n, tuple(v.shape[1:])) for n, v in sorted(mesh.fields.items())),
    )


def check_quality(mesh: TetMesh, min_quality: float) -> None:
    """Refuse a mesh whose worst tet is below ``min_quality`` (gamma).

    Arguments:
        mesh: the mesh.
        min_quality: threshold in [0, 1); 0 accepts any valid mesh.

    Raises:
        MeshError: naming how many tets are below the threshold, the worst value and where
            it is, and how to refine or lower the threshold.
        ValueError: if ``min_quality`` is outside [0, 1).
    """
    if not 0.0 <= min_quality < 1.0:
        raise ValueError(f"min_quality must lie in [0, 1), got {min_quality}")
    q = gamma(mesh.points, mesh.tets)
    bad = q < min_quality
    if bad.any():
        worst = int(np.argmin(q))
        where = mesh.points[mesh.tets[worst]].mean(axis=0)
        raise MeshError(
            f"{int(bad.sum())} of {mesh.n_tets} tets have quality (gamma) below {min_quality}; "
            f"the worst is {q[worst]:.3g} (tet {worst} near {np.round(where, 4).tolist()}). "
            "Refine (smaller size, or a local size for the region there), or accept it with a "
            "lower threshold (min_quality=..., --min-quality on the command line)"
        )

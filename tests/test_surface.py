"""Self-intersection check of imported triangle surfaces, degenerate contacts included, and
the advice given when gmsh still cannot fill a surface."""

from __future__ import annotations

import re

import meshio
import numpy as np
import pytest

import softbody.meshing.surface as surface
from softbody import cli
from softbody.meshing import MeshError, ball, check_surface, cube, mesh_file, read_surface, self_intersections

# A unit cube, two triangles a face, outward normals.
CORNERS = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
QUADS = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
CUBE = np.array([t for a, b, c, d in QUADS for t in ([a, b, c], [a, c, d])])


def two_cubes(shift) -> tuple[np.ndarray, np.ndarray]:
    """The unit cube and a copy moved by ``shift``, as one surface (12 + 12 triangles)."""
    return np.vstack([CORNERS, CORNERS + shift]), np.vstack([CUBE, CUBE + 8])


def closed_surface(m) -> tuple[np.ndarray, np.ndarray]:
    """A gmsh mesh's boundary as ``(points, faces)`` holding only the surface vertices."""
    used = np.unique(m.surface)
    remap = np.full(m.n_vertices, -1)
    remap[used] = np.arange(len(used))
    return m.points[used], remap[m.surface]


@pytest.fixture
def no_gmsh(monkeypatch):
    """Fail the test if the surface importer opens a gmsh session."""
    def session(*args, **kwargs):
        raise AssertionError("the surface reached gmsh")
    monkeypatch.setattr(surface._gmsh, "session", session)


def test_half_overlapping_cubes_stl_is_refused_before_gmsh(tmp_path, no_gmsh, capsys):
    # Every crossing of these two cubes lies in a face plane or along an edge or diagonal:
    # the faces y=0, y=1, z=0, z=1 overlap in their planes and each cube's inner face
    # meets the other's faces edge-on.
    path = tmp_path / "two_cubes.stl"
    points, faces = two_cubes([0.5, 0, 0])
    meshio.Mesh(points, [("triangle", faces)]).write(path)
    pattern = (r"surface intersects itself: \d+ pairs of triangles cross, touch or overlap "
               r"\(first: triangles (\d+) and (\d+) at \[([-\d.e, ]+)\].*boolean union")
    with pytest.raises(MeshError, match=pattern) as err:
        mesh_file(path, 0.3)
    points, faces = read_surface(path)
    pairs = self_intersections(points, faces)
    assert len(pairs) > 0 and np.all(pairs[:, 0] < 12) and np.all(pairs[:, 1] >= 12)  # one from each cube
    a, b, at = re.search(pattern, str(err.value)).groups()
    at = np.array([float(v) for v in at.split(",")])
    for t in (int(a), int(b)):  # the point named lies on both triangles named
        corner, edges = points[faces[t, 0]], (points[faces[t, 1:]] - points[faces[t, 0]]).T
        uv = np.linalg.lstsq(edges, at - corner, rcond=None)[0]
        assert np.allclose(corner + edges @ uv, at) and uv.min() >= -1e-9 and uv.sum() <= 1 + 1e-9
    # `softbody mesh two_cubes.stl` says the same and exits with status 1.
    assert cli.main(["mesh", str(path), "--size", "0.3"]) == 1
    assert "intersects itself" in capsys.readouterr().err


def test_each_cube_alone_passes():
    check_surface(CORNERS, CUBE)
    assert len(self_intersections(*two_cubes([2.0, 0, 0]))) == 0  # apart


UNIT = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]  # in z = 0; every case below pairs it with a second triangle


@pytest.mark.parametrize("second, meets", [
    ([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.3, 0.1, 1]], True),      # an edge pierces the inside
    ([[0.2, 0.2, 0], [1.2, 0.2, 0], [0.2, 1.2, 0]], True),       # coplanar, overlapping
    ([[2, 0, 0], [3, 0, 0], [2, 1, 0]], False),                  # coplanar, apart
    ([[0.5, 0, 0], [1.5, 0, 0], [0.5, -1, 0]], True),            # coplanar, edges overlap on a line
    ([[1.5, 0, 0], [2.5, 0, 0], [1.5, -1, 0]], False),           # coplanar, edges on one line, apart
    ([[0.5, -0.5, 0], [0.5, 0.5, 0], [0.5, 0, 1]], True),        # its edge lies across the triangle
    ([[0.5, 0, 0], [0.5, -1, 1], [0.5, -1, -1]], True),          # a vertex on an edge
    ([[0.5, 0.5, 0], [0.5, 0.5, 1], [0.5, 1.5, 0]], True),       # edge on edge (the diagonal)
    ([[0.2, 0.2, 0], [0.2, 0.2, 1], [0.3, 0.5, 1]], True),       # a vertex on the face
    ([[0.2, 0.2, 1e-3], [0.2, 0.2, 1], [0.3, 0.5, 1]], False),   # just above it
    ([[0, 0, 0], [1, 0.5, 0], [0.5, 1, 0]], True),               # shares a vertex, coplanar overlap
    ([[0, 0, 0], [0.5, 0.3, 0], [0.2, 0.2, 1]], True),           # shares a vertex, an edge runs in
    ([[0, 0, 0], [2, 0, 0], [0, -1, 1]], True),                  # shares a vertex, edges overlap
    ([[0, 0, 0], [0.3, 0.3, -1], [0.3, 0.3, 1]], True),          # shares a vertex, far edge pierces
    ([[0, 0, 0], [-1, 0, 0.5], [0, -1, 0.5]], False),            # shares only the vertex
    ([[0, 0, 0], [-1, 0, 0], [0, -1, 0]], False),                # shares only the vertex, coplanar
    ([[0, 0, 0], [1, 0, 0], [0.5, 0.5, 0]], True),               # shares an edge, folded onto it
    ([[0, 0, 0], [1, 0, 0], [0.5, -0.5, 0]], False),             # shares an edge, flat
    ([[0, 0, 0], [1, 0, 0], [0.5, 0.5, 0.1]], False),            # shares an edge, sharp ridge
    ([[0, 1, 0], [1, 0, 0], [0, 0, 0]], True),                   # the same triangle again
])
def test_degenerate_contacts_count_and_shared_edges_and_vertices_do_not(second, meets):
    # Separate vertex rows: equal coordinates must count as shared.
    points = np.array(UNIT + second, float)
    got = self_intersections(points, [[0, 1, 2], [3, 4, 5]])
    assert got.tolist() == ([[0, 1]] if meets else [])
    scaled = self_intersections(points * 1e-3 + [5e-3, 0, 0], [[0, 1, 2], [3, 4, 5]])  # millimetres, moved
    assert scaled.tolist() == got.tolist()


@pytest.fixture(scope="module")
def gmsh_cube() -> tuple[np.ndarray, np.ndarray]:
    return closed_surface(cube())


@pytest.mark.parametrize("name", ["cube", "sphere", "two disjoint cubes", "cube with a cavity"])
def test_valid_closed_surfaces_pass(name, gmsh_cube):
    # gmsh's own boundaries: flat faces of many coplanar triangles, and a curved one.
    points, faces = gmsh_cube
    if name == "sphere":
        points, faces = closed_surface(ball(radius=0.05, size=0.015))
    elif name == "two disjoint cubes":
        points, faces = np.vstack([points, points + [0.06, 0, 0]]), np.vstack([faces, faces + len(points)])
    elif name == "cube with a cavity":  # an inner copy at half size, turned inside out
        c = points.mean(axis=0)
        points, faces = np.vstack([points, c + 0.5 * (points - c)]), np.vstack([faces, faces[:, ::-1] + len(points)])
    assert len(self_intersections(points, faces)) == 0
    check_surface(points, faces)


def test_cubes_sharing_a_face_are_refused_as_non_manifold():
    points, faces = two_cubes([1.0, 0, 0])
    unique, inverse = np.unique(points, axis=0, return_inverse=True)  # as read from one file
    with pytest.raises(MeshError, match="non-manifold edges"):
        check_surface(unique, inverse.ravel()[faces])


@pytest.mark.parametrize("remesh", [False, True])
def test_gmsh_plc_error_gets_surface_advice(remesh, monkeypatch):
    # With the check bypassed, the overlapping cubes reach gmsh, which refuses them.
    monkeypatch.setattr(surface, "check_surface", lambda points, faces: None)
    with pytest.raises(MeshError) as err:
        surface.tetrahedralize(*two_cubes([0.5, 0, 0]), 0.3, remesh=remesh)
    message = str(err.value)
    assert "PLC Error" in message  # gmsh's own words
    assert "crosses or touches itself" in message and "boolean-union the parts" in message
    assert "smaller --size" not in message
    if remesh:
        assert "--keep-surface" in message
    else:
        assert "a smaller size will not help" in message


def test_cubes_touching_at_a_corner_get_surface_advice():
    # The corner is a shared vertex, which the check lets through; gmsh's remeshed surface
    # then holds no volume.
    points, faces = two_cubes([1.0, 1, 1])
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    with pytest.raises(MeshError, match=r"inside the surface failed \(gmsh produced no tetrahedra\); "
                                        r"remeshing the surface at size 0.3 .*--keep-surface.*boolean-union"):
        surface.tetrahedralize(unique, inverse.ravel()[faces], 0.3)

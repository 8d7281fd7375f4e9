"""Mesh files (.msh, .vtu) and surface import (STL, OBJ, STEP) with their checks."""

from __future__ import annotations

import struct

import gmsh
import meshio
import numpy as np
import pytest

from softbody.cli import main
from softbody.meshing import (
    Box,
    InBox,
    MeshError,
    OnPlane,
    Region,
    TetMesh,
    ball,
    check_surface,
    cube,
    finger,
    load,
    mesh,
    mesh_file,
    quadruped,
    read_surface,
    save,
    self_intersections,
    tetrahedralize,
)


def oriented_set(faces: np.ndarray) -> set[tuple[int, ...]]:
    """Triangles as a set, each rotated to start at its smallest index (orientation kept)."""
    return {tuple(np.roll(f, -int(np.argmin(f)))) for f in np.asarray(faces).tolist()}


def assert_same_mesh(a: TetMesh, b: TetMesh) -> None:
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.tets, b.tets)
    assert oriented_set(a.surface) == oriented_set(b.surface)
    assert sorted(a.regions) == sorted(b.regions)
    for name, ra in a.regions.items():
        rb = b.regions[name]
        np.testing.assert_array_equal(ra.vertices, rb.vertices)
        np.testing.assert_array_equal(ra.tets, rb.tets)
        assert len(ra.faces) == len(rb.faces) and oriented_set(ra.faces) == oriented_set(rb.faces)
    assert sorted(a.fields) == sorted(b.fields)
    for name in a.fields:
        np.testing.assert_array_equal(a.fields[name], b.fields[name])


@pytest.fixture(scope="module")
def robots() -> list[TetMesh]:
    return [finger(), quadruped()]


# ---------------------------------------------------------------------------------------
# .msh / .vtu


@pytest.mark.parametrize("suffix", [".msh", ".vtu"])
def test_round_trip_keeps_regions_and_fields(robots, tmp_path, suffix):
    for i, m in enumerate(robots):
        path = save(m, tmp_path / f"robot{i}{suffix}")
        assert_same_mesh(m, load(path))


@pytest.mark.parametrize("suffix", [".msh", ".vtu"])
def test_round_trip_of_custom_surface_reversed_faces_and_matrix_fields(tmp_path, suffix):
    base = cube()
    inward = base.surface[0, ::-1]  # a boundary face turned inwards: no tet has it outward
    m = TetMesh(base.points, base.tets, base.surface[::2],
                {"odd": Region([0, 5], tets=[3], faces=inward[None]), "empty": Region([])},
                {"F": np.tile(np.eye(3), (base.n_tets, 1, 1)), "a": np.arange(base.n_tets, dtype=float)})
    back = load(save(m, tmp_path / f"m{suffix}"))
    assert_same_mesh(m, back)
    assert back.fields["F"].shape == (base.n_tets, 3, 3)


def test_saved_msh_opens_in_gmsh_and_pyvista(robots, tmp_path):
    path = save(robots[1], tmp_path / "q.msh")
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        assert len(gmsh.model.mesh.getNodes()[0]) == robots[1].n_vertices
    finally:
        gmsh.finalize()
    pv = pytest.importorskip("pyvista")
    grid = pv.read(path)
    assert grid.n_cells == robots[1].n_tets and "region:bone:spine" in grid.cell_data


def test_save_never_overwrites_without_force(tmp_path):
    m = cube()
    path = save(m, tmp_path / "c.vtu")
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="force=True.*--force"):
        save(ball(), path)
    assert path.read_bytes() == before
    save(ball(), path, force=True)
    assert load(path).n_vertices == ball().n_vertices


def test_unsupported_suffix_and_non_tet_faces_are_refused(tmp_path):
    m = cube()
    with pytest.raises(MeshError, match=r"unsupported mesh file type '\.obj'"):
        save(m, tmp_path / "c.obj")
    a, b = m.tets[0, :2]
    far = np.setdiff1d(np.arange(m.n_vertices), m.tets[(m.tets == a).any(axis=1)])[0]
    bad = TetMesh(m.points, m.tets, regions={"bad": Region([a, b, far], faces=[[a, b, far]])})
    with pytest.raises(MeshError, match="not a face of any tet"):
        save(bad, tmp_path / "bad.msh")


def test_load_reorients_foreign_tets(tmp_path):
    m = cube()
    flipped = m.tets[:, [1, 0, 2, 3]]
    meshio.Mesh(m.points, [("tetra", flipped)]).write(tmp_path / "foreign.vtu")
    back = load(tmp_path / "foreign.vtu")
    assert np.all(back.volumes() > 0)
    assert back.volumes().sum() == pytest.approx(m.volumes().sum())


# ---------------------------------------------------------------------------------------
# Damaged mesh files


@pytest.fixture(scope="module")
def cube_files(tmp_path_factory) -> dict[str, bytes]:
    """The bytes of the example cube written by :func:`save` as ``.msh`` and ``.vtu``."""
    folder = tmp_path_factory.mktemp("cube")
    return {suffix: save(cube(), folder / f"cube{suffix}").read_bytes() for suffix in (".msh", ".vtu")}


def halfway_into(data: bytes, section: str) -> bytes:
    """``data`` cut halfway between the start of a gmsh section and its end marker."""
    start, end = data.index(f"${section}\n".encode()), data.index(f"$End{section}\n".encode())
    return data[: (start + end) // 2]


@pytest.mark.parametrize("section", ["Nodes", "Elements", "NodeData", "ElementData"])
def test_truncated_msh_names_the_section_it_ends_in(cube_files, tmp_path, section):
    cut = tmp_path / "cut.msh"
    cut.write_bytes(halfway_into(cube_files[".msh"], section))
    with pytest.raises(MeshError, match=rf"cut\.msh: the file ends inside its \${section} section "
                                        r"\(truncated or damaged\): write it again with `softbody mesh`"):
        load(cut)


def test_msh_cut_before_an_end_marker_is_not_read_as_a_mesh_without_regions(cube_files, tmp_path):
    """meshio reads this file with a warning, without the region sections after the tets."""
    data = cube_files[".msh"]
    cut = tmp_path / "cut.msh"
    cut.write_bytes(data[: data.index(b"$EndElements")])
    with pytest.raises(MeshError, match=r"cut\.msh: the file ends inside its \$Elements section"):
        load(cut)


def test_msh_damaged_inside_its_tets_is_named(cube_files, tmp_path):
    data = bytearray(cube_files[".msh"])
    start, end = data.index(b"$Elements\n"), data.index(b"$EndElements\n")
    middle = (start + end) // 2
    data[middle:middle + 64] = b"\xff" * 64  # vertex numbers far beyond the mesh's
    bad = tmp_path / "bad.msh"
    bad.write_bytes(bytes(data))
    with pytest.raises(MeshError, match=r"bad\.msh is not a complete gmsh \.msh file \(truncated or damaged"):
        load(bad)


def test_msh_whose_node_count_is_damaged_is_named(cube_files, tmp_path):
    """A damaged count in the binary $Nodes header asks meshio for exabytes."""
    data = bytearray(cube_files[".msh"])
    header = data.index(b"$Nodes\n") + len(b"$Nodes\n")  # blocks, nodes, min tag, max tag (uint64)
    assert struct.unpack_from("<4Q", data, header)[1] == cube().n_vertices
    struct.pack_into("<Q", data, header + 8, 1 << 58)
    bad = tmp_path / "bad.msh"
    bad.write_bytes(bytes(data))
    with pytest.raises(MeshError, match=r"bad\.msh: reading it asked for more memory than there is .*"
                                        r"the file is damaged, or too big for this machine"):
        load(bad)


@pytest.mark.parametrize("suffix, kind", [(".msh", r"a gmsh \.msh file \(it does not start with \$MeshFormat\)"),
                                          (".vtu", r"a VTK XML \.vtu file \(it does not start with an XML tag\)")])
def test_text_and_empty_files_are_not_meshes(tmp_path, suffix, kind):
    text = tmp_path / f"notes{suffix}"
    text.write_text("these are notes about the finger, not a mesh\n")
    with pytest.raises(MeshError, match=rf"notes\{suffix} is not {kind}; write it again with `softbody mesh`"):
        load(text)
    (tmp_path / f"empty{suffix}").write_bytes(b"")
    with pytest.raises(MeshError, match=rf"empty\{suffix} is empty"):
        load(tmp_path / f"empty{suffix}")


def test_truncated_vtu_is_named(cube_files, tmp_path):
    data = cube_files[".vtu"]
    half = tmp_path / "half.vtu"
    half.write_bytes(data[: len(data) // 2])
    with pytest.raises(MeshError, match=r"half\.vtu is not a complete VTK \.vtu file \(truncated or damaged"):
        load(half)


def test_softbody_run_reports_a_truncated_mesh_without_a_traceback(cube_files, tmp_path, capsys):
    cut = tmp_path / "cut.msh"
    cut.write_bytes(halfway_into(cube_files[".msh"], "Elements"))
    out = tmp_path / "result.npz"
    assert main(["run", str(cut), "--steps", "1", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"softbody run: {cut}: the file ends inside its $Elements section") and "Traceback" not in err
    assert not out.exists()


# ---------------------------------------------------------------------------------------
# Surfaces


@pytest.fixture(scope="module")
def sphere_surface() -> tuple[np.ndarray, np.ndarray]:
    b = ball(radius=0.05, size=0.015)
    used = np.unique(b.surface)
    remap = np.full(b.n_vertices, -1)
    remap[used] = np.arange(len(used))
    return b.points[used], remap[b.surface]


def test_watertight_stl_is_meshed(sphere_surface, tmp_path):
    points, faces = sphere_surface
    path = tmp_path / "ball.stl"
    meshio.Mesh(points * 1000, [("triangle", faces)]).write(path)  # in millimetres
    m = mesh_file(path, 0.01, scale=0.001, select={"bottom": InBox((-1, -1, -1), (1, 1, 0.01))})
    assert m.points[m.region("bottom").vertices, 2].max() <= 0.01
    assert np.all(m.volumes() > 0) and m.volumes().sum() == pytest.approx(4 / 3 * np.pi * 0.05**3, rel=0.06)
    kept = mesh_file(path, 0.01, scale=0.001, remesh=False)

    def by_coordinates(p, f):
        return {tuple(sorted(map(tuple, np.round(p[t], 9).tolist()))) for t in f}

    assert by_coordinates(kept.points, kept.surface) == by_coordinates(points, faces)


def test_obj_quads_are_read(tmp_path):
    path = tmp_path / "cube.obj"
    corners = "\n".join(f"v {x} {y} {z}" for z in (0, 1) for y in (0, 1) for x in (0, 1))
    quads = "f 1 3 4 2\nf 5 6 8 7\nf 1 2 6 5\nf 3 7 8 4\nf 1 5 7 3\nf 2 4 8 6"
    path.write_text(corners + "\n" + quads + "\n")
    points, faces = read_surface(path, scale=0.05)
    assert faces.shape == (12, 3)
    check_surface(points, faces)
    m = tetrahedralize(points, faces, 0.02)
    assert m.volumes().sum() == pytest.approx(0.05**3, rel=1e-9)


def test_open_stl_is_refused_naming_the_open_edges(sphere_surface, tmp_path):
    points, faces = sphere_surface
    path = tmp_path / "open.stl"
    meshio.Mesh(points, [("triangle", faces[1:])]).write(path)
    with pytest.raises(MeshError, match=r"not watertight: 3 open edges \(first: vertices \[\d+, \d+\] at .*close the holes"):
        mesh_file(path, 0.01)


def test_nonmanifold_surface_is_refused(sphere_surface):
    points, faces = sphere_surface
    # A fin sticking out of one edge: that edge is shared by three triangles.
    a, b = faces[0, 0], faces[0, 1]
    tip = points[[a, b]].mean(axis=0) * 1.5
    pts = np.vstack([points, tip])
    fin = np.array([[a, b, len(points)], [b, a, len(points)]])
    with pytest.raises(MeshError, match="non-manifold edges"):
        check_surface(pts, np.vstack([faces, fin]))


def test_self_intersecting_surface_is_refused(sphere_surface):
    points, faces = sphere_surface
    two = np.vstack([points, points + [0.03, 0, 0]])
    both = np.vstack([faces, faces + len(points)])
    with pytest.raises(MeshError, match=r"intersects itself: \d+ pairs of triangles cross"):
        tetrahedralize(two, both, 0.01)
    apart = np.vstack([points, points + [0.2, 0, 0]])
    assert len(self_intersections(apart, both)) == 0
    assert len(self_intersections(points, faces)) == 0


def test_triangle_crossing_test():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0],                  # in z = 0
                    [0.2, 0.2, -1], [0.2, 0.2, 1], [0.3, 0.1, 1],      # pierces it
                    [0, 0, 0], [-1, 0, 1.0], [0, -1, 1.0]], float)    # touches at a vertex only
    faces = np.array([[0, 1, 2], [3, 4, 5], [0, 7, 8]])
    np.testing.assert_array_equal(self_intersections(pts, faces), [[0, 1]])


def test_step_file_is_meshed_in_metres(tmp_path):
    path = tmp_path / "part.step"
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 100, 50, 20)  # millimetres (gmsh's default STEP unit)
        gmsh.model.occ.synchronize()
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    m = mesh_file(path, 0.01, select={"fixed": OnPlane("x", 0.0)})
    assert m.volumes().sum() == pytest.approx(0.1 * 0.05 * 0.02, rel=1e-9)
    assert np.allclose(m.points.max(axis=0), [0.1, 0.05, 0.02])
    with pytest.raises(MeshError, match="STL/OBJ files only"):
        mesh_file(path, 0.01, scale=0.001)


def test_missing_and_unknown_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        mesh_file(tmp_path / "nope.stl", 0.01)
    with pytest.raises(MeshError, match="expected one of"):
        mesh_file(tmp_path / "robot.ply", 0.01)
    assert mesh(Box(0.05), 0.02).n_tets > 0  # gmsh is left usable after the errors

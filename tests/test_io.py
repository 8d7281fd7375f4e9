"""Result files: .npz round trip, overwrite protection, ParaView (.vtu/.pvd) and XDMF export."""

import itertools
import json
import zipfile

import meshio
import numpy as np
import pytest

from softbody.cli import main
from softbody.io import (
    Result,
    ResultError,
    VertexStrain,
    color_options,
    read_vtu_series,
    to_vtu_series,
    to_xdmf,
    vertex_activation,
    vertex_strain,
    vertex_values,
    write_metrics,
)
from softbody.meshing.mesh import Region, TetMesh
from softbody.meshing.sheet import grid


def box_mesh(nx=4, ny=2, nz=2, size=(0.2, 0.05, 0.05)):
    """A structured box of ``nx*ny*nz`` cubes, each split into 6 positively oriented tets.

    Returns ``points (n, 3)`` and ``tets (t, 4)``.
    """
    axes = [np.linspace(0.0, s, k + 1) for s, k in zip(size, (nx, ny, nz))]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(len(points)).reshape(nx + 1, ny + 1, nz + 1)
    tets = []
    for i, j, k in itertools.product(range(nx), range(ny), range(nz)):
        for order in itertools.permutations(range(3)):  # Kuhn split: one tet per axis order
            corner = [0, 0, 0]
            tet = [idx[i, j, k]]
            for axis in order:
                corner[axis] = 1
                tet.append(idx[i + corner[0], j + corner[1], k + corner[2]])
            tets.append(tet)
    tets = np.array(tets)
    p = points[tets]
    flip = np.linalg.det(p[:, 1:] - p[:, :1]) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return points, tets


def box_result(frames=3, with_extras=True, lift=0.0):
    """A cantilever-like box bending upwards over ``frames`` frames (frame 0 at rest).

    With extras: a ``muscle:top`` region (the upper half's tets) driven by channel ``top``, a ``fixed`` region, a
    ``pressure`` field, a loss history, obstacles, one skeleton segment and metadata.
    ``lift`` raises the body off the ground by that many metres.
    """
    points, tets = box_mesh()
    upper = np.flatnonzero(points[tets].mean(axis=1)[:, 2] > 0.025)
    top = Region(np.unique(tets[upper]), tets=upper)
    fixed = np.flatnonzero(points[:, 0] < 1e-9)
    mesh = TetMesh(points, tets, regions={"muscle:top": top, "fixed": fixed})
    s = np.linspace(0.0, 1.0, frames)
    # Bend about the y axis: z grows with x^2, stronger in later frames.
    x = np.repeat(points[None], frames, axis=0)
    x[:, :, 2] += lift + 2.0 * s[:, None] * points[None, :, 0] ** 2
    x[:, :, 0] *= 1.0 - 0.3 * s[:, None] * points[None, :, 2] / 0.05
    if not with_extras:
        return Result.from_mesh(mesh, x, dt=0.01)
    return Result.from_mesh(
        mesh, x, dt=0.01,
        activation=s[:, None] * np.array([[1.0, 0.5]]),
        channel_names=["top", "spare"],
        fields={"pressure": np.outer(s, points[:, 0])},
        loss_history=np.geomspace(1.0, 1e-3, 20),
        obstacles=[{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]},
                   {"type": "sphere", "center": np.array([0.3, 0.0, 0.05]), "radius": 0.03,
                    "name": "ball"}],
        skeleton=np.stack([np.stack([xf[0], xf[-1]])[None] for xf in x]),
        metadata={"material": {"E": 1e5, "nu": np.float64(0.45)}, "steps": np.int64(frames)},
    )


def test_save_load_round_trip(tmp_path):
    res = box_result()
    path = res.save(tmp_path / "sub" / "result.npz")
    back = Result.load(path)
    for name in ("points", "tets", "surface", "x", "activation", "loss_history", "skeleton"):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))
    assert back.dt == res.dt
    assert back.channel_names == ("top", "spare")
    assert set(back.fields) == {"pressure"}
    np.testing.assert_array_equal(back.fields["pressure"], res.fields["pressure"])
    assert set(back.regions) == {"muscle:top", "fixed"}
    np.testing.assert_array_equal(back.regions["muscle:top"].vertices, res.regions["muscle:top"].vertices)
    assert back.obstacles == res.obstacles
    assert back.obstacles[1] == {"type": "sphere", "center": [0.3, 0.0, 0.05], "radius": 0.03, "name": "ball"}
    assert back.metadata == {"material": {"E": 1e5, "nu": 0.45}, "steps": 3}


def test_minimal_round_trip(tmp_path):
    res = box_result(frames=1, with_extras=False)
    back = Result.load(res.save(tmp_path / "r.npz"))
    assert back.activation is None and back.loss_history is None and back.skeleton is None
    assert back.obstacles == () and back.metadata == {} and back.n_frames == 1


def test_no_overwrite_without_force(tmp_path):
    path = tmp_path / "result.npz"
    box_result(frames=2).save(path)
    before = path.read_bytes()
    other = box_result(frames=3)
    with pytest.raises(FileExistsError, match="force=True"):
        other.save(path)
    assert path.read_bytes() == before
    other.save(path, force=True)
    assert Result.load(path).n_frames == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.npz"]  # no temporary files left

    metrics = tmp_path / "metrics.json"
    write_metrics(metrics, {"loss": np.float64(0.5), "curve": np.arange(3)})
    assert json.loads(metrics.read_text()) == {"curve": [0, 1, 2], "loss": 0.5}
    with pytest.raises(FileExistsError, match="--force"):
        write_metrics(metrics, {"loss": 1.0})
    write_metrics(metrics, {"loss": 1.0}, force=True)
    assert json.loads(metrics.read_text()) == {"loss": 1.0}


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no result file"):
        Result.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(ResultError, match="not a softbody result"):
        Result.load(tmp_path / "other.npz")
    res = box_result(frames=2, with_extras=False)
    res.save(tmp_path / "full.npz")
    with np.load(tmp_path / "full.npz") as data:
        partial = {k: data[k] for k in data.files if k not in ("x", "surface")}
    np.savez(tmp_path / "partial.npz", **partial)
    with pytest.raises(ResultError, match=r"lacks the entries \['surface', 'x'\]"):
        Result.load(tmp_path / "partial.npz")
    with pytest.raises(ValueError, match="end in .npz"):
        res.save(tmp_path / "result.h5")



# --------------------------------------------------------------------------- damaged result files


def saved_result_bytes(tmp_path) -> bytes:
    """The bytes of a real result file written by :meth:`Result.save`."""
    return box_result().save(tmp_path / "result.npz").read_bytes()


def test_truncated_or_corrupted_result_is_named_as_damaged(tmp_path):
    data = saved_result_bytes(tmp_path)
    half = tmp_path / "half.npz"
    half.write_bytes(data[: len(data) // 2])
    with pytest.raises(ResultError, match=r"half\.npz is not a complete softbody result file "
                                          r"\(truncated or damaged zip archive\): re-run the simulation"):
        Result.load(half)
    # The archive's index is intact but the bytes of the positions are overwritten: only
    # reading that entry finds the damage (its checksum no longer matches).
    with zipfile.ZipFile(tmp_path / "result.npz") as archive:
        entry = archive.getinfo("x.npy")
    assert entry.file_size > 1000
    start = entry.header_offset + 30 + len(entry.filename) + len(entry.extra) + entry.file_size // 2
    corrupt = bytearray(data)
    corrupt[start:start + 64] = b"\xff" * 64
    (tmp_path / "corrupt.npz").write_bytes(bytes(corrupt))
    with pytest.raises(ResultError, match=r"corrupt\.npz is not a complete softbody result file "
                                          r"\(truncated or damaged zip archive: entry 'x'\)"):
        Result.load(tmp_path / "corrupt.npz")


def test_files_that_are_not_npz_archives_are_named_without_suggesting_pickle(tmp_path):
    text = tmp_path / "notes.npz"
    text.write_text("dt = 0.01\nthese are notes, not a result\n")
    with pytest.raises(ResultError, match=r"notes\.npz is not a NumPy \.npz archive") as err:
        Result.load(text)
    assert "pickle" not in str(err.value)
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(ResultError, match=r"empty\.npz is empty"):
        Result.load(tmp_path / "empty.npz")
    np.save(tmp_path / "array.npy", np.zeros(3))
    (tmp_path / "array.npy").rename(tmp_path / "array.npz")
    with pytest.raises(ResultError, match=r"array\.npz holds a single NumPy array \(\.npy\)"):
        Result.load(tmp_path / "array.npz")


def test_result_entries_of_the_wrong_kind_are_named(tmp_path):
    """An .npz written by something else, with the format entry but entries of other kinds."""
    with np.load(box_result(frames=2, with_extras=False).save(tmp_path / "full.npz")) as data:
        full = {k: data[k] for k in data.files}
    cases = {
        "dt": (np.array([0.01, 0.02]), r"entry 'dt' must be one number, got shape \(2,\)"),
        "version": (np.array("one"), r"entry 'version' must be one integer"),
        "metadata": (np.array("{not json"), r"entry 'metadata' is not valid JSON"),
        "points": (np.array([None, None, None], dtype=object),
                   r"entry 'points' is not a plain NumPy array of numbers; the file was not written by Result.save"),
    }
    for key, (value, message) in cases.items():
        path = tmp_path / f"bad_{key}.npz"
        np.savez(path, **{**full, key: value})
        with pytest.raises(ResultError, match=message) as err:
            Result.load(path)
        assert f"bad_{key}.npz" in str(err.value) and "pickle" not in str(err.value)
    np.savez(tmp_path / "no_vertices.npz", **{k: v for k, v in full.items() if k != "region/fixed/vertices"})
    with pytest.raises(ResultError, match=r"region 'fixed' has \['faces', 'tets'\] but no vertices"):
        Result.load(tmp_path / "no_vertices.npz")


def test_view_and_render_refuse_a_damaged_result_without_a_traceback(tmp_path, capsys, monkeypatch):
    viewer = pytest.importorskip("softbody.viewer")
    data = saved_result_bytes(tmp_path)
    half = tmp_path / "half.npz"
    half.write_bytes(data[: len(data) // 2])

    def no_server(*args, **kwargs):
        raise AssertionError("softbody view started a server for a damaged file")

    monkeypatch.setattr(viewer.viser, "ViserServer", no_server)
    assert main(["view", str(half), "--port", "0"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"softbody view: {half} is not a complete softbody result file "
                          "(truncated or damaged zip archive)")
    assert "Traceback" not in err

    out = tmp_path / "frame.png"
    assert main(["render", str(half), "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"softbody render: {half} is not a complete softbody result file")
    assert not out.exists()


def test_validation_names_the_problem():
    res = box_result(frames=2, with_extras=False)
    base = dict(points=res.points, tets=res.tets, surface=res.surface, x=res.x, dt=0.01)
    with pytest.raises(ResultError, match=r"x\[None\]"):
        Result(**{**base, "x": res.x[0]})
    bad = res.x.copy()
    bad[1, 0, 0] = np.nan
    with pytest.raises(ResultError, match="not finite from frame 1"):
        Result(**{**base, "x": bad})
    with pytest.raises(ResultError, match="dt must be a positive"):
        Result(**{**base, "dt": 0.0})
    with pytest.raises(ResultError, match="unknown type 'cone'"):
        Result(**base, obstacles=[{"type": "cone"}])
    with pytest.raises(ResultError, match=r"lacks \['radius'\]"):
        Result(**base, obstacles=[{"type": "sphere", "center": [0, 0, 0]}])
    with pytest.raises(ResultError, match="reserved"):
        Result(**base, fields={"strain": np.zeros((2, res.n_vertices))})
    with pytest.raises(ResultError, match="channel_names"):
        Result(**base, activation=np.zeros((2, 2)), channel_names=["a"])
    with pytest.raises(ResultError, match="JSON"):
        Result(**base, metadata={"f": object()})


def test_derived_quantities():
    res = box_result(frames=3)
    strain = vertex_strain(res)
    assert strain.shape == (3, res.n_vertices)
    np.testing.assert_allclose(strain[0], 0.0, atol=1e-12)
    assert strain[2].max() > strain[1].max() > 0.01
    # Rigid motion: rotation plus translation gives no strain.
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    rigid = Result(res.points, res.tets, res.surface, np.stack([res.points, res.points @ rot.T + 1.0]), 0.1)
    np.testing.assert_allclose(vertex_strain(rigid), 0.0, atol=1e-12)

    # A sheet (no tets) takes its triangles' in-plane Green strain: stretched 2 % along x and
    # -1 % along y, |E|_F = |((1.02^2 - 1)/2, (0.99^2 - 1)/2)| on every vertex; 0 when moved rigidly.
    sheet = grid(0.3, 0.2, (6, 4))
    stretched = sheet.points * [1.02, 0.99, 1.0]
    frames = np.stack([sheet.points, stretched, sheet.points @ rot.T + 1.0])
    strain = vertex_strain(Result(sheet.points, sheet.tets, sheet.surface, frames, 0.1))
    np.testing.assert_allclose(strain[1], np.hypot(0.5 * (1.02**2 - 1), 0.5 * (0.99**2 - 1)), rtol=1e-12)
    np.testing.assert_allclose(strain[[0, 2]], 0.0, atol=1e-12)
    # A solid's surface triangles do not count: its vertices are in tets.
    assert VertexStrain(res.points, res.tets, res.surface).triangles.shape == (0, 3)

    assert color_options(res) == ["strain", "displacement", "activation", "pressure"]
    act = vertex_activation(res)
    top = res.regions["muscle:top"].vertices
    np.testing.assert_allclose(act[2, top], 1.0)
    assert np.all(np.delete(act[2], top) == 0.0)
    np.testing.assert_allclose(vertex_values(res, "displacement")[0], 0.0)
    with pytest.raises(ResultError, match="offers"):
        vertex_values(res, "temperature")


def test_vtu_series_round_trip(tmp_path):
    res = box_result(frames=3)
    pvd = to_vtu_series(res, tmp_path / "vtu")
    assert sorted(p.name for p in (tmp_path / "vtu").iterdir()) == [
        "frame_00000.vtu", "frame_00001.vtu", "frame_00002.vtu", "series.json", "series.pvd"]
    frame = meshio.read(tmp_path / "vtu" / "frame_00002.vtu")
    np.testing.assert_allclose(frame.points, res.x[2])
    np.testing.assert_allclose(frame.point_data["displacement"], res.x[2] - res.points)
    np.testing.assert_allclose(frame.point_data["activation"], vertex_activation(res)[2])
    np.testing.assert_allclose(frame.point_data["activation:spare"], 0.5)
    np.testing.assert_allclose(frame.point_data["pressure"], res.fields["pressure"][2])
    np.testing.assert_array_equal(frame.cells_dict["tetra"], res.tets)

    back = read_vtu_series(pvd)
    np.testing.assert_allclose(back.points, res.points, atol=1e-12)
    np.testing.assert_allclose(back.x, res.x)
    np.testing.assert_allclose(back.activation, res.activation)
    assert back.channel_names == res.channel_names and back.dt == res.dt
    np.testing.assert_allclose(back.fields["pressure"], res.fields["pressure"])
    np.testing.assert_array_equal(back.regions["muscle:top"].vertices, res.regions["muscle:top"].vertices)
    assert back.obstacles == res.obstacles and back.metadata == res.metadata
    assert len(back.surface) == len(res.surface)

    with pytest.raises(FileExistsError, match="force=True"):
        to_vtu_series(res, tmp_path / "vtu")
    to_vtu_series(box_result(frames=2), tmp_path / "vtu", force=True)
    assert read_vtu_series(pvd).n_frames == 2


def test_damaged_vtu_series_files_are_named(tmp_path):
    pvd = to_vtu_series(box_result(frames=2), tmp_path / "vtu")
    side = tmp_path / "vtu" / "series.json"
    good_side = side.read_text()
    side.write_text(good_side[: len(good_side) // 2])
    with pytest.raises(ResultError, match=r"series\.json is not valid JSON \(.*\): write the series again "
                                          "with to_vtu_series"):
        read_vtu_series(pvd)
    side.write_text(good_side)

    good_pvd = pvd.read_bytes()
    pvd.write_bytes(good_pvd[: len(good_pvd) // 2])
    with pytest.raises(ResultError, match=r"series\.pvd is not a complete \.pvd collection \(not well-formed XML: "
                                          r".*\): write the series again with to_vtu_series"):
        read_vtu_series(pvd)
    pvd.write_bytes(good_pvd)

    frame = tmp_path / "vtu" / "frame_00001.vtu"
    data = frame.read_bytes()
    frame.write_bytes(data[: len(data) // 2])
    with pytest.raises(ResultError, match=r"frame 1 of .*series\.pvd: .*frame_00001\.vtu is not a complete VTK "
                                          r"\.vtu file \(truncated or damaged\): write the series again with "
                                          "to_vtu_series"):
        read_vtu_series(pvd)
    frame.write_text("frame 1 was here\n")
    with pytest.raises(ResultError, match=r"frame 1 of .*series\.pvd: .*frame_00001\.vtu is not a VTK XML \.vtu "
                                          r"file \(it does not start with an XML tag\)"):
        read_vtu_series(pvd)
    frame.rename(frame.with_suffix(".vtk"))
    pvd.write_text(pvd.read_text().replace("frame_00001.vtu", "frame_00001.vtk"))
    with pytest.raises(ResultError, match=r"frame_00001\.vtk, which is not a \.vtu file"):
        read_vtu_series(pvd)


def test_xdmf_writes_and_reads_back(tmp_path):
    res = box_result(frames=3)
    path = to_xdmf(res, tmp_path / "traj.xdmf")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["traj.xdmf"]  # self-contained
    with meshio.xdmf.TimeSeriesReader(path) as reader:
        points, cells = reader.read_points_cells()
        np.testing.assert_allclose(points, res.points)
        np.testing.assert_array_equal(cells[0].data, res.tets)
        for k in range(3):
            t, point_data, _ = reader.read_data(k)
            assert t == pytest.approx(k * res.dt)
            np.testing.assert_allclose(point_data["position"], res.x[k])
            np.testing.assert_allclose(point_data["displacement"], res.x[k] - res.points)
            np.testing.assert_allclose(point_data["pressure"], res.fields["pressure"][k])
    with pytest.raises(FileExistsError):
        to_xdmf(res, path)

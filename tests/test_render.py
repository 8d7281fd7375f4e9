"""Offscreen renders: PNG, GIF and MP4 of a two-frame trajectory are drawn and move; a
sheet (a body without tets) is drawn lit from either side, in renders and in the viewer.

Rendering runs in a subprocess through the real command line (``softbody render``), so a
crash of the GL stack fails the test with its output instead of killing pytest.
"""

import subprocess
import sys

import imageio.v3 as iio
import imageio_ffmpeg
import numpy as np
import pytest
from test_io import box_result

from softbody.io import Result
from softbody.meshing import sheet
from softbody.render import plot_loss, render
from softbody.viewer import view

SIZE = (320, 240)


def cli_render(*args, timeout=120):
    proc = subprocess.run([sys.executable, "-m", "softbody.cli", "render", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, (
        f"softbody render {' '.join(map(str, args))} exited with {proc.returncode} "
        f"(a negative status is a crash; offscreen rendering needs libegl1 and Mesa: "
        f"run `bash scripts/setup.sh test`)\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}")
    return proc


def foreground(img):
    """Mask of pixels that differ clearly from the background (sampled along the top edge)."""
    img = img[..., :3].astype(float)
    background = img[:8].reshape(-1, 3)
    dist = np.min(np.linalg.norm(img[:, :, None, :] - background[None, None, ::97], axis=-1), axis=-1)
    return dist > 30


def assert_drawn(img, what):
    assert img.ndim == 3 and img.shape[:2] == SIZE[::-1], f"{what}: unexpected shape {img.shape}"
    assert img.std() > 20, f"{what}: image is nearly uniform (std {img.std():.1f}): nothing was drawn"
    frac = foreground(img).mean()
    assert 0.05 < frac < 0.95, f"{what}: {frac:.1%} of pixels differ from the background"


def assert_moved(first, last, what):
    diff = np.abs(first[..., :3].astype(float) - last[..., :3].astype(float)).max(axis=-1)
    assert (diff > 40).mean() > 0.005, f"{what}: first and last frames are (nearly) the same"


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    return box_result(frames=2).save(tmp_path_factory.mktemp("render") / "result.npz")


def test_png_gif_mp4(result_file, tmp_path):
    size = f"{SIZE[0]}x{SIZE[1]}"
    cli_render(result_file, "-o", tmp_path / "first.png", "--frame", "0", "--size", size)
    cli_render(result_file, "-o", tmp_path / "last.png", "--size", size, "--color-by", "displacement")
    first, last = iio.imread(tmp_path / "first.png"), iio.imread(tmp_path / "last.png")
    assert_drawn(first, "PNG frame 0")
    assert_drawn(last, "PNG frame -1")
    assert_moved(first, last, "PNG")

    cli_render(result_file, "-o", tmp_path / "anim.gif", "--size", size, "--fps", "5")
    gif = iio.imread(tmp_path / "anim.gif", index=None)
    assert gif.shape[0] == 2, f"GIF has {gif.shape[0]} frames, expected 2"
    for k in range(2):
        assert_drawn(gif[k], f"GIF frame {k}")
    assert_moved(gif[0], gif[1], "GIF")

    cli_render(result_file, "-o", tmp_path / "anim.mp4", "--size", size, "--color-by", "activation")
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "anim.mp4"))
    meta = next(reader)
    w, h = meta["size"]
    assert (w, h) == (320, 240)  # already multiples of 16
    mp4 = [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]
    assert len(mp4) == 2, f"MP4 has {len(mp4)} frames, expected 2"
    for k in range(2):
        assert_drawn(mp4[k], f"MP4 frame {k}")
    assert_moved(mp4[0], mp4[1], "MP4")

    # No overwrite without --force; with it the file is replaced.
    proc = subprocess.run([sys.executable, "-m", "softbody.cli", "render", str(result_file),
                           "-o", str(tmp_path / "first.png")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "--force" in proc.stderr
    assert np.array_equal(iio.imread(tmp_path / "first.png"), first)
    cli_render(result_file, "-o", tmp_path / "first.png", "--size", size, "--force")
    assert not np.array_equal(iio.imread(tmp_path / "first.png"), first)


def test_render_rejects_bad_requests(result_file, tmp_path):
    with pytest.raises(ValueError, match=r"\.png"):
        render(result_file, tmp_path / "out.jpg")
    with pytest.raises(IndexError, match="out of range for 2 frames"):
        render(result_file, tmp_path / "out.png", frame=5)
    with pytest.raises(ValueError, match="offers"):
        render(result_file, tmp_path / "out.png", color_by="temperature")
    assert list(tmp_path.iterdir()) == []


def test_plot_loss(tmp_path):
    path = plot_loss(np.geomspace(10.0, 0.01, 30), tmp_path / "loss.png")
    img = iio.imread(path)
    assert img.shape[0] > 200 and img.std() > 10
    with pytest.raises(FileExistsError, match="force"):
        plot_loss([1.0, 0.5], path)
    with pytest.raises(ValueError, match="non-empty"):
        plot_loss([], tmp_path / "empty.png")


def sheet_result(flip=False):
    """A 0.4 m square of cloth (gmsh triangles, no tets) over two frames: flat 11 cm up,
    then dropped 5 cm and draped, its rim 8 cm below its centre. ``flip`` reverses the
    triangles' winding, so that the camera, above, sees their back faces."""
    mesh = sheet.rectangle(0.4, 0.4, 0.04, x0=-0.2)
    flat = mesh.points + [0.0, -0.2, 0.11]
    draped = flat - [0.0, 0.0, 0.05]
    draped[:, 2] -= 2.0 * (flat[:, 0] ** 2 + flat[:, 1] ** 2)
    surface = mesh.surface[:, ::-1] if flip else mesh.surface
    return Result(flat, mesh.tets, surface, np.stack([flat, draped]), 0.01, regions=dict(mesh.regions))


def test_a_sheet_renders_lit_from_either_side(tmp_path):
    """A result without tets renders (its default colouring included) and the sheet fills
    a good part of the frame; seen from the back of its triangles it is as bright as from
    their front (both faces lit: within 10 %, measured equal to 1 %)."""
    size = f"{SIZE[0]}x{SIZE[1]}"
    shown = {}
    for flip in (False, True):
        path = sheet_result(flip).save(tmp_path / f"sheet{int(flip)}.npz")
        cli_render(path, "-o", tmp_path / f"strain{int(flip)}.png", "--size", size)
        assert_drawn(iio.imread(tmp_path / f"strain{int(flip)}.png"), f"sheet, flip={flip}")
        render(path, tmp_path / f"plain{int(flip)}.png", color_by=None, ground=False, window_size=SIZE)
        shown[flip] = iio.imread(tmp_path / f"plain{int(flip)}.png")[..., :3].astype(float)
    mask = foreground(shown[False])
    assert 0.1 < mask.mean() < 0.9, f"the sheet covers {mask.mean():.1%} of the frame"
    assert np.array_equal(mask, foreground(shown[True])), "the sheet's outline changed with its triangles' winding"
    front, back = shown[False][mask].mean(), shown[True][mask].mean()
    assert abs(back - front) < 0.1 * front, (front, back)


def test_the_viewer_draws_a_sheet_from_both_sides():
    """The viewer draws a sheet's triangles double-sided (a closed body's from the front),
    and after a colouring with many levels one with a single level shows each triangle
    once (the levels drawn before are hidden)."""
    result = sheet_result()
    viewer = view(result, port=0, block=False)
    try:
        viewer.playing = False
        viewer.frame = 1
        assert viewer.body.side == "double"
        viewer.color_by = "displacement"
        levels = set(viewer.body.active)
        assert len(levels) > 3 and set(viewer.body.handles) - levels, "no level drawn before is out of use"
        for mode in ("displacement", "none", "regions"):
            viewer.color_by = mode
            visible = [h for h in viewer.body.handles.values() if h.visible]
            assert sum(len(h.faces) for h in visible) == len(result.surface), mode
            assert all(h.side == "double" for h in visible)
    finally:
        viewer.stop()
    closed = view(box_result(frames=2), port=0, block=False)
    try:
        assert closed.body.side == "front"
    finally:
        closed.stop()

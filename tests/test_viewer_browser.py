"""The browser viewer, served by a real viser server and drawn by Debian's headless chromium.

The ``browser`` tests drive chromium over the DevTools protocol (``tests/cdp.py``): they
load the page, wait for the scene, and check from screenshots that the mesh is drawn and
that moving the timeline (or a live control) moves it. The other tests check the server
side without a browser.
"""

import argparse
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from cdp import CHROMIUM, Chromium
from test_io import box_result

from softbody.io import Result, ResultError
from softbody.viewer import LiveViewer, PlaybackViewer, run, start_frame, view, view_live

SIZE = (960, 640)


def scene(img):
    """The part of the page left of the control panel, as float RGB."""
    return img[:, : int(0.62 * img.shape[1])].astype(float)


def changed(a, b, threshold=30.0):
    """Mask of scene pixels whose colour differs between two screenshots."""
    return np.abs(scene(a) - scene(b)).max(axis=-1) > threshold


def screenshot_when(page, condition, what, timeout=40.0):
    """Poll screenshots until two in a row show the same scene and satisfy ``condition``."""
    deadline = time.monotonic() + timeout
    previous = page.screenshot()
    while time.monotonic() < deadline:
        current = page.screenshot()
        if np.array_equal(scene(current), scene(previous)) and condition(current):
            return current
        previous = current
    pytest.fail(f"timed out after {timeout} s waiting for {what}")


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.fail(f"Debian's chromium is missing ({CHROMIUM}); the browser tests need it: "
                    "run `bash scripts/setup.sh test` (it installs chromium and fonts-dejavu-core)")
    with Chromium(window_size=SIZE) as chromium:
        yield chromium


@pytest.fixture
def playback():
    viewer = view(box_result(frames=3), port=0, block=False)
    yield viewer
    viewer.stop()


def lift_step(rest):
    """A trivial live step: the body floats up by 5 cm times control 0 and leans by control 1."""
    def step(state, controls):
        offset = np.array([0.0, 0.0, 0.05]) * controls[0] + np.array([0.0, 0.05, 0.0]) * controls[1] * rest[:, 2:] / 0.05
        return state + 1, rest + offset
    return step


@pytest.mark.browser
def test_playback_in_browser(browser, playback):
    assert playback.server.get_host() == "127.0.0.1" and playback.url.startswith("http://127.0.0.1:")
    playback.playing = False  # a result opens playing; these checks want still frames
    playback.frame = 0
    page = browser.new_page()
    try:
        page.navigate(playback.url)
        page.wait_for_text("frame 0 / 2")
        shown = screenshot_when(page, lambda img: scene(img).std() > 10, "the scene to render")

        # The mesh's screen region: where hiding the body changes the picture.
        playback.body.set_visible(False)
        hidden = screenshot_when(page, lambda img: changed(img, shown).any(), "the body to disappear")
        mesh = changed(shown, hidden)
        assert mesh.mean() > 0.02, f"the mesh covers only {mesh.mean():.2%} of the view"
        drawn, background = scene(shown)[mesh], scene(hidden)[mesh]
        assert np.abs(drawn.mean(axis=0) - background.mean(axis=0)).max() > 40, \
            "the mesh's pixels look like the background"
        playback.body.set_visible(True)
        back = screenshot_when(page, lambda img: changed(img, hidden).mean() > 0.5 * mesh.mean(),
                               "the body to return")
        assert changed(back, shown).mean() < 0.1 * mesh.mean()

        # Move the timeline from the server: every open page follows.
        playback.frame = 2
        page.wait_for_text("frame 2 / 2")
        moved = screenshot_when(page, lambda img: changed(img, shown).mean() > 0.01, "frame 2 to be drawn")
        assert changed(moved, shown).mean() > 0.2 * mesh.mean(), "the picture barely changed between frames"
    finally:
        page.close()


@pytest.mark.browser
def test_live_in_browser(browser):
    res = box_result(frames=1, with_extras=False)
    live = view_live(res, lift_step(res.points), 0, ["lift", "lean"], port=0, block=False, rate=20)
    page = browser.new_page()
    try:
        page.navigate(live.url)
        page.wait_for_text("Steps per second")
        rest = screenshot_when(page, lambda img: scene(img).std() > 10, "the live scene to render")
        steps = live.steps
        live.set_controls([1.0, 0.5])
        lifted = screenshot_when(page, lambda img: changed(img, rest).mean() > 0.01, "the body to rise")
        assert live.steps > steps
        np.testing.assert_allclose(live.x[:, 2] - res.points[:, 2], 0.05)
        assert changed(lifted, rest).mean() > 0.01
    finally:
        page.close()
        live.stop()


def test_playback_server_state(playback):
    res = playback.result
    assert isinstance(playback, PlaybackViewer)
    playback.playing = False
    playback.frame = 0
    opts = list(playback.gui["color_by"].options)
    assert opts == ["strain", "displacement", "activation", "pressure", "regions", "none"]
    for mode in opts:
        playback.color_by = mode
        coloring = playback.coloring(mode)
        assert coloring.levels.shape[1] == len(res.surface)
        # The body's meshes hold exactly the surface, at the shown frame's positions.
        visible = [h for h in playback.body.handles.values() if h.visible]
        assert sum(len(h.faces) for h in visible) == len(res.surface)
        corners = np.concatenate([h.vertices[h.faces].reshape(-1, 3) for h in visible])
        assert np.allclose(np.sort(corners, axis=0), np.sort(res.x[0][res.surface].reshape(-1, 3), axis=0), atol=1e-6)
        playback.body.set_visible(False)
        assert not any(h.visible for h in playback.body.handles.values())
        playback.body.set_visible(True)  # only the levels in use come back
        assert sum(len(h.faces) for h in playback.body.handles.values() if h.visible) == len(res.surface)
    assert "0.8387" in playback.coloring("strain").legend
    with pytest.raises(ResultError, match="offers"):
        playback.color_by = "temperature"
    with pytest.raises(IndexError):
        playback.frame = 3
    playback.frame = -1
    assert playback.frame == 2 and "frame 2 / 2" in playback.gui["clock"].content
    assert "top: **1.000**" in playback.gui["activation"].content

    playback.gui["region:muscle:top"].value = True
    handle, used = playback._overlays["muscle:top"]
    assert handle.visible and np.allclose(handle.vertices, res.x[2, used])

    playback.frame = 0
    playback.gui["speed"].value = 0.05  # 0.5 ms of simulated time per real ms: a frame every 0.2 s
    playback.gui["play"].value = True
    deadline = time.monotonic() + 5
    while playback.frame == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    playback.gui["play"].value = False
    assert playback.frame > 0, "Play did not advance the timeline"


def test_live_server_state():
    res = box_result(frames=1, with_extras=False)
    calls = []

    def step(state, controls):
        calls.append(controls.copy())
        if state >= 5:
            raise RuntimeError("solver diverged")
        return lift_step(res.points)(state, controls)

    live = view_live(res, step, 0, ["lift", "lean"], ranges=[(0, 2), (-1, 1)], port=0, block=False, rate=100)
    try:
        assert isinstance(live, LiveViewer) and live.url.startswith("http://127.0.0.1:")
        np.testing.assert_array_equal(calls[0], [0.0, -1.0])  # sliders start at the range minimum
        deadline = time.monotonic() + 5
        while live.error is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert live.error == "RuntimeError: solver diverged" and not live.gui["run"].value
        assert "solver diverged" in live.gui["status"].content
        with pytest.raises(ValueError, match="outside its range"):
            live.set_controls([3.0, 0.0])
        live.set_controls([2.0, 0.0])
        live.reset()
        deadline = time.monotonic() + 5
        while live.steps < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        np.testing.assert_allclose(live.x[:, 2] - res.points[:, 2], 0.1)
    finally:
        live.stop()

    with pytest.raises(ValueError, match="x of shape"):
        view_live(res, lambda s, u: (s, np.zeros(3)), 0, ["a"], port=0, block=False)


def test_view_command_reports_a_missing_file(tmp_path, capsys):
    args = argparse.Namespace(result=str(tmp_path / "none.npz"), host="127.0.0.1", port=0, color_by="strain")
    assert run(args) == 1
    assert "no result file" in capsys.readouterr().err


def test_minimal_result_and_bad_colouring():
    res = box_result(frames=1, with_extras=False)
    with pytest.raises(ResultError, match="offers"):
        view(res, port=0, block=False, color_by="activation")
    with view(res, port=0, block=False, color_by=None) as viewer:
        assert list(viewer.gui["color_by"].options) == ["strain", "displacement", "regions", "none"]
        assert viewer.gui["frame"].disabled and viewer.color_by == "none"
        assert not viewer.playing and viewer.frame == 0
        viewer.playing = True  # one frame: nothing to play
        assert not viewer.playing
        assert "frame 0 / 0" in viewer.gui["clock"].content


def test_result_opens_playing_on_its_most_displaced_frame():
    res = box_result(frames=4, with_extras=False)
    x = res.x.copy()
    x[2, :, 2] += 0.3  # frame 2 lifted far above the others
    res = Result(res.points, res.tets, res.surface, x, dt=1.0)  # a frame a second at real time
    assert start_frame(res) == 2
    assert start_frame(Result(res.points, res.tets, res.surface, res.x[:1], dt=1.0)) == 0
    with view(res, port=0, block=False, color_by=None) as viewer:
        assert viewer.playing and viewer.gui["loop"].value and viewer.frame == 2
        viewer.playing = False
        held = viewer.frame
        time.sleep(1.2)
        assert viewer.frame == held, "the timeline moved after a pause"
        viewer.gui["speed"].value = 4.0
        viewer.playing = True
        deadline = time.monotonic() + 5
        while viewer.frame == held and time.monotonic() < deadline:
            time.sleep(0.02)
        assert viewer.frame != held, "playback did not resume"


def differs(a, b, threshold=60.0):
    """Mask of pixels (whole page) whose colour differs between two screenshots by more than
    ``threshold`` in some channel; 60 ignores the body's shadow on the floor (at most ~48)."""
    return np.abs(a.astype(float) - b.astype(float)).max(axis=-1) > threshold


PANEL_BOX = """(() => {
  const panel = [...document.querySelectorAll('[data-dock-region], [data-floating-window]')]
    .find(e => e.innerText.includes('softbody result'));
  const canvas = document.querySelector('canvas');
  if (!panel || !canvas) return null;
  const p = panel.getBoundingClientRect(), c = canvas.getBoundingClientRect();
  return {panel: [p.left, p.top, p.right, p.bottom], canvas: [c.left, c.top, c.right, c.bottom]};
})()"""


@pytest.mark.browser
def test_result_opens_moving_beside_the_panel(browser, tmp_path):
    """At 1280 x 800 a result file opens with the body moving, framed left of the GUI panel."""
    path = box_result(frames=40).save(tmp_path / "result.npz")  # 0.4 s of bending, looped
    viewer = view(path, port=0, block=False)
    page = browser.new_page()
    try:
        page.send("Emulation.setDeviceMetricsOverride", width=1280, height=800, deviceScaleFactor=1, mobile=False)
        page.navigate(viewer.url)
        page.wait_for_text("softbody result")
        page.wait_for_text("frame ")
        assert page.evaluate("[innerWidth, innerHeight]") == [1280, 800]
        boxes = page.evaluate(PANEL_BOX)
        assert boxes is not None, "no control panel or canvas in the page"
        (pl, pt, pr, pb), (cl, ct, cr, cb) = ([int(round(v)) for v in boxes[k]] for k in ("panel", "canvas"))
        free = (cl, min(cr, pl))  # columns of the canvas that the panel leaves uncovered

        # (a) Playback runs without a click: the picture keeps changing and so does the frame
        # number. Two changes in a row, so that the body first appearing is not taken for motion.
        # The frame number is read at intervals well below the 0.4 s loop (readings a screenshot
        # apart are about one loop apart and can show the same frame), before the screenshots,
        # so that the pause below follows the last two of them at once.
        frames, deadline = [], time.monotonic() + 20
        while len(set(frames) - {None}) < 3:
            if time.monotonic() > deadline:
                pytest.fail(f"the page's frame number did not advance: {frames}")
            frames.append(page.evaluate("document.body.innerText.match(/frame (\\d+) \\//)?.[1]"))
            time.sleep(0.07)
        shots, moves = [page.screenshot()], 0
        deadline = time.monotonic() + 20
        while moves < 2:
            if time.monotonic() > deadline:
                pytest.fail(f"the body did not move on its own ({moves} changes in 20 s): playback did not start")
            time.sleep(0.3)
            shots.append(page.screenshot())
            moving = differs(shots[-1][:, free[0]:free[1]], shots[-2][:, free[0]:free[1]], 30.0)
            moves = moves + 1 if moving.mean() > 0.002 else 0
        assert viewer.playing and viewer.gui["loop"].value

        # (b) Paused (the camera is still the initial one), with the panel hidden but keeping its
        # place, so that a body behind a floating panel would show: where is the body drawn?
        viewer.playing = False
        page.evaluate("document.querySelectorAll('[data-dock-region], [data-floating-window]')"
                      ".forEach(e => { e.style.visibility = 'hidden'; })")
        shown = screenshot_when(page, lambda img: scene(img).std() > 10, "the paused frame")
        viewer.body.set_visible(False)
        background = screenshot_when(page, lambda img: differs(img, shown).mean() > 0.01, "the body to disappear")
        viewer.body.set_visible(True)
        back = screenshot_when(page, lambda img: differs(img, background).mean() > 0.01, "the body to return")
        for name, img in {"playing0": shots[-2], "playing1": shots[-1], "paused": shown,
                          "background": background}.items():
            iio.imwrite(tmp_path / f"{name}.png", img)
        body = differs(shown, background) & differs(back, background)  # ignores UI that changed meanwhile
        assert body.mean() > 0.02, f"the body covers only {body.mean():.2%} of the page"
        hidden = body[pt:pb, pl:pr].sum() / body.sum()
        assert hidden < 0.02, f"the control panel covers {hidden:.0%} of the body"
        rows, cols = np.flatnonzero(body.any(axis=1)), np.flatnonzero(body.any(axis=0))
        assert cols[0] > free[0] + 2 and cols[-1] < free[1] - 2 and rows[0] > ct + 2 and rows[-1] < cb - 2, \
            f"the body (columns {cols[0]}-{cols[-1]}, rows {rows[0]}-{rows[-1]}) is cut off by the free " \
            f"part of the canvas (columns {free[0]}-{free[1]}, rows {ct}-{cb})"
        offset = ((cols[0] + cols[-1]) / 2 - sum(free) / 2) / (free[1] - free[0])
        assert abs(offset) < 0.1, f"the body's centre is {offset:+.0%} of the free width off its centre"
        # The motion seen in (a) was the body's: the changed pixels lie in the columns the body
        # covers in those two shots (it swings between frames, so the paused frame's columns
        # can miss part of it), give or take its shadow.
        moved = differs(shots[-1], shots[-2], 30.0)[:, free[0]:free[1]]
        seen = (differs(shots[-1], background) | differs(shots[-2], background))[ct:cb, free[0]:free[1]]
        seen_cols = np.flatnonzero(seen.any(axis=0))
        assert seen_cols.size, "the body is in neither of the playing screenshots"
        span = np.zeros(moved.shape[1], bool)
        span[max(seen_cols[0] - 50, 0):seen_cols[-1] + 50] = True
        assert moved[:, span].sum() > 0.9 * moved.sum(), "the picture changed away from the body"
    finally:
        page.close()
        viewer.stop()

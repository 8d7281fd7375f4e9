"""``softbody demo`` and ``softbody run`` end to end.

The quick demo runs once, through the real command line in a subprocess (its renders use
the GL stack; a crash there fails the test with its output instead of killing pytest).
Its task is reachable by construction (the target is a static pose of the arm), so a
working optimiser brings the tip from 40 % of the arm's length away to within a few
per cent; the checks below leave a margin of about four times what it reaches.
"""

import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from softbody.cli import main
from softbody.demo import ARM_LENGTH, OUTPUTS, QUICK, TARGET
from softbody.io import Result


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    argv = [sys.executable, "-m", "softbody.cli", "demo", "--no-view", "--quick", "--out", str(out)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=600, stdin=subprocess.DEVNULL)
    assert proc.returncode == 0, f"softbody demo failed ({proc.returncode})\n{proc.stdout}\n{proc.stderr}"
    return out, proc.stdout


@pytest.mark.slow
def test_demo_writes_every_output(quick_demo):
    out, stdout = quick_demo
    for name in OUTPUTS:
        assert (out / name).stat().st_size > 0, f"{name} is empty"
    png = iio.imread(out / "render.png")
    assert png.shape[:2] == QUICK.window[::-1]
    assert png[..., :3].std() > 10, "the render is blank"
    frames = iio.imread(out / "render.mp4")
    assert len(frames) == QUICK.steps + 1
    moved = np.abs(frames[-1].astype(float) - frames[0].astype(float)).mean()
    assert moved > 1, "the arm does not move in the video"
    assert iio.imread(out / "loss.png").ndim == 3
    # Not a terminal: no viewer, but the way to open one.
    assert f"softbody view {out / 'result.npz'}" in stdout
    assert "tip error" in stdout
    # Not a terminal: no spinner, so a line says what the long silence is.
    compiling, compiled = stdout.index("compiling the rollout"), stdout.index("compiled the rollout")
    assert compiling < compiled and "tracing" in stdout[compiled:]


def test_demo_optimises_the_reach(quick_demo):
    out, _ = quick_demo
    m = json.loads((out / "metrics.json").read_text())
    assert m["quick"] is True
    assert m["optimiser"]["iterations"] == QUICK.iterations
    assert 100 <= m["mesh"]["vertices"] <= 1500
    # The arm starts straight, about 0.4 L from the target.
    assert m["initial_tip_distance_fraction"] > 0.3
    assert m["final_loss"] < m["initial_loss"] / 20
    assert m["final_tip_distance_fraction"] < 0.05
    assert m["final_tip_distance_m"] == pytest.approx(m["final_tip_distance_fraction"] * ARM_LENGTH)
    assert m["solver_iterations_per_step"]["all_converged"]
    for phase in ("mesh", "compile", "simulate", "optimise", "render", "total"):
        assert m["wall_time_s"][phase] > 0
    phases = ("mesh", "compile", "simulate", "optimise")
    assert m["wall_time_s"]["total"] >= sum(m["wall_time_s"][p] for p in phases)
    assert m["timings"] == m["wall_time_s"]
    assert m["timings"]["compile"] > m["timings"]["compile_trace"] > 0
    assert 0 <= m["compilation_cache"]["loaded"] <= m["compilation_cache"]["programs"]


def test_demo_result_holds_the_optimised_trajectory(quick_demo):
    out, _ = quick_demo
    m = json.loads((out / "metrics.json").read_text())
    r = Result.load(out / "result.npz")
    assert r.n_frames == QUICK.steps + 1
    assert r.dt == pytest.approx(QUICK.dt)
    assert r.channel_names == ("muscle:top", "muscle:bottom", "muscle:left", "muscle:right")
    assert r.activation.shape == (QUICK.steps + 1, 4)
    assert np.all((r.activation >= 0) & (r.activation <= 1))
    assert len(r.loss_history) == QUICK.iterations + 1
    assert r.loss_history[0] == pytest.approx(m["initial_loss"])
    assert r.loss_history[-1] == pytest.approx(m["final_loss"])
    tip = r.x[-1, r.regions["tip"].vertices].mean(axis=0)
    assert np.linalg.norm(tip - TARGET) == pytest.approx(m["final_tip_distance_m"])
    # The clamped face stays put.
    fixed = r.regions["fixed"].vertices
    np.testing.assert_allclose(r.x[-1, fixed], r.points[fixed], atol=1e-12)
    assert [o["name"] for o in r.obstacles] == ["target", "mount"]


def test_demo_refuses_a_non_empty_folder(quick_demo, capsys):
    out, _ = quick_demo
    before = {name: (out / name).stat().st_mtime_ns for name in OUTPUTS}
    assert main(["demo", "--no-view", "--quick", "--out", str(out)]) == 1
    assert "--force" in capsys.readouterr().err
    assert before == {name: (out / name).stat().st_mtime_ns for name in OUTPUTS}


def test_demo_refuses_a_file_as_folder(tmp_path, capsys):
    path = tmp_path / "taken"
    path.write_text("mine")
    assert main(["demo", "--no-view", "--out", str(path)]) == 1
    assert "is a file" in capsys.readouterr().err
    assert path.read_text() == "mine"


def test_run_writes_a_loadable_result(tmp_path, capsys):
    out = tmp_path / "sag.npz"
    assert main(["run", "cantilever", "--size", "0.04", "--E", "1e5", "--steps", "5", "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "iterations per step" in printed and f"wrote {out}" in printed
    r = Result.load(out)
    assert r.n_frames == 6 and r.dt == pytest.approx(0.01)
    assert len(r.metadata["iterations_per_step"]) == 5
    assert r.metadata["options"]["fixed"] == "fixed"
    fixed, tip = r.regions["fixed"].vertices, r.regions["tip"].vertices
    np.testing.assert_allclose(r.x[:, fixed], r.x[:1, fixed].repeat(6, axis=0), atol=1e-12)
    sag = r.x[:, tip, 2].mean(axis=1) - r.points[tip, 2].mean()
    assert np.all(np.diff(sag) < 0), f"the tip should fall under gravity, got {sag}"
    # Not overwritten without --force.
    assert main(["run", "cantilever", "--size", "0.04", "--steps", "5", "-o", str(out)]) == 1
    assert "--force" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["nosuch"], "neither an example"),
    (["missing.msh"], "no mesh file"),
    (["cantilever", "--size", "0.04", "--fixed", "base"], "no region 'base'"),
    (["cantilever", "--size", "0.04", "--nu", "0.5"], "Poisson"),
])
def test_run_explains_bad_input(tmp_path, capsys, argv, message):
    out = tmp_path / "r.npz"
    assert main(["run", *argv, "-o", str(out)]) == 1
    assert message in capsys.readouterr().err
    assert not out.exists()

"""Sweeps on Ray (softbody.control.sweep, ``softbody sweep``): the same metrics as one point
after another in-process, no point lost when a worker dies, stop and resume without running
a finished point twice, failing points recorded, bad input refused before Ray starts, and
CMA-ES populations evaluated on the workers giving the serial run.

The sweeps run on a local Ray cluster on 127.0.0.1 that this module starts and stops (two
CPUs). The scene is a coarse clamped beam (5 x 1 x 1 cells, 24 vertices, 8 steps) under
gravity, over Young's modulus and the time step; the time step is static (each value is
its own compiled program), so each worker builds one model per time step and keeps it.
"""

import functools
import json
import os
import signal
import socket
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import cli
from softbody import control as sc
from softbody.control import sweep as sw
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout

ray = pytest.importorskip("ray", reason="the sweep tests need Ray: pip install softbody[test]")

METRICS = ["tip_dz", "iterations"]
#: the 64-point grid: 16 moduli x 4 time steps
GRID = {"E": [float(e) for e in np.geomspace(2e4, 2e6, 16)], "dt": [0.005, 0.01, 0.02, 0.04]}


# ------------------------------------------------------------------------------ the scene


def beam_setup(log=None):
    """The scene: the mesh, its tip and a cache of one compiled model per time step."""
    if log is not None:
        with open(log, "a") as f:
            f.write(f"{os.getpid()}\n")
    mesh = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
    return {"mesh": mesh, "tip": mesh.region("tip").vertices, "models": {}}


def beam_point(scene, E, dt, n_steps=8):
    """The tip's vertical displacement after ``n_steps`` steps and the mean PD iterations."""
    models = scene["models"]
    if dt not in models:
        models[dt] = build(SoftBody(scene["mesh"], Material(E=1e5, nu=0.45, density=1000.0), fixed="fixed"),
                           options=Options(dt=dt, tol=1e-8))
    model, params = models[dt]
    p = params.replace(E=jnp.full_like(params.E, E))
    traj = rollout(model, p, initial_state(model, p), n_steps=n_steps)
    tip = scene["tip"]
    return {"tip_dz": float(traj.x[-1, tip, 2].mean() - scene["mesh"].points[tip, 2].mean()),
            "iterations": float(np.mean(traj.info.iterations))}


def killing_point(scene, E, dt, *, marker, victim):
    """``beam_point``, except that the victim point kills its worker process the first time."""
    if (E, dt) == victim and not os.path.exists(marker):
        with open(marker, "w") as f:
            f.write(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return beam_point(scene, E, dt)


def counted_point(scene, E, dt, *, log):
    """``beam_point``, logging every evaluation (one line each, appended)."""
    with open(log, "a") as f:
        f.write(f"{E!r},{dt!r}\n")
    return beam_point(scene, E, dt)


def _counts(log):
    with open(log) as f:
        return [line.strip() for line in f if line.strip()]


@pytest.fixture(scope="module")
def cluster():
    """A local Ray cluster on 127.0.0.1 with 2 CPUs, for this module only."""
    if ray.is_initialized():
        ray.shutdown()
    ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
             configure_logging=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def reference():
    """The 64 points' metrics, one after another in this process."""
    scene = beam_setup()
    return [beam_point(scene, **p) for p in sw.grid(GRID)]


def _metrics(result):
    return [{m: float(r[m]) for m in METRICS} for r in result.rows]


# ------------------------------------------------------------------------------ bad input (no Ray)


@pytest.fixture
def no_ray(monkeypatch):
    """Make starting Ray or a worker pool fail the test: input must be checked first."""
    def forbidden(*args, **kwargs):
        raise AssertionError("Ray or a worker pool started before the input was checked")

    monkeypatch.setattr(ray, "init", forbidden)
    monkeypatch.setattr(sw.Pool, "__init__", forbidden)


def test_an_unknown_parameter_is_refused_before_ray_starts(no_ray, tmp_path):
    with pytest.raises(sw.SweepError, match=r"unknown parameter 'youngs'.*accepts \['E', 'dt', 'n_steps'\]"):
        sw.run_sweep(beam_point, sw.grid({"youngs": [1e5], "dt": [0.01]}), setup=beam_setup, metrics=METRICS,
                     out=tmp_path / "s.csv")
    with pytest.raises(sw.SweepError, match=r"requires \['dt'\], which the sweep does not give"):
        sw.run_sweep(beam_point, sw.grid({"E": [1e5]}), setup=beam_setup, metrics=METRICS, out=tmp_path / "s.csv")
    with pytest.raises(sw.SweepError, match="not among|metric names .* collide"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=["E"], out=tmp_path / "s.csv")
    assert not (tmp_path / "s.csv").exists()


def test_an_empty_grid_is_refused_before_ray_starts(no_ray, tmp_path):
    with pytest.raises(sw.SweepError, match="the grid of parameter 'E' is empty"):
        sw.grid({"E": [], "dt": [0.01]})
    with pytest.raises(sw.SweepError, match="names no parameters"):
        sw.grid({})
    with pytest.raises(sw.SweepError, match="the sweep has no points"):
        sw.run_sweep(beam_point, [], setup=beam_setup, metrics=METRICS, out=tmp_path / "s.csv")
    with pytest.raises(sw.SweepError, match="n >= 1"):
        sw.random_design({"E": (1e4, 1e6)}, 0)


def test_an_unreachable_cluster_is_refused_quickly_before_ray_starts(no_ray, tmp_path):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(sw.SweepError, match=rf"cannot reach the Ray cluster at '127.0.0.1:{port}'.*ray start --head"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=METRICS, out=tmp_path / "s.csv",
                     address=f"127.0.0.1:{port}")
    with pytest.raises(sw.SweepError, match="is not HOST:PORT"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=METRICS, out=tmp_path / "s.csv",
                     address="headnode")


def test_an_existing_table_needs_resume_or_overwrite_and_the_same_points(no_ray, tmp_path):
    out = tmp_path / "s.csv"
    out.write_text("index,E,dt,tip_dz,iterations,seconds,worker,pid,worker_seq,attempts,error\n"
                   "0,1000.0,0.01,-0.1,10.0,0.1,0,1,1,1,\n")
    with pytest.raises(sw.SweepError, match="exists: pass resume=True"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=METRICS, out=out)
    with pytest.raises(sw.SweepError, match="grid or design changed"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=METRICS, out=out, resume=True)
    with pytest.raises(sw.SweepError, match="columns .* differ"):
        sw.run_sweep(beam_point, sw.grid(GRID), setup=beam_setup, metrics=["tip_dz"], out=out, resume=True)


def test_the_cli_refuses_bad_specs_before_ray_starts(no_ray, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    base = {"scene": "test_sweep.py:beam_point", "grid": GRID, "metrics": METRICS}
    spec.write_text(json.dumps(dict(base, workrs=2)))
    assert cli.main(["sweep", str(spec)]) == 1
    assert "unknown keys ['workrs']" in capsys.readouterr().err
    spec.write_text(json.dumps(dict(base, scene=f"{__file__}:beam_point", setup=f"{__file__}:beam_setup",
                                    grid={"E": [1e5], "dt": []})))
    assert cli.main(["sweep", str(spec)]) == 1
    assert "the grid of parameter 'dt' is empty" in capsys.readouterr().err
    spec.write_text(json.dumps(dict(base, scene=f"{__file__}:beam_point", setup=f"{__file__}:beam_setup",
                                    grid={"E": [1e5], "h": [0.01]})))
    assert cli.main(["sweep", str(spec)]) == 1
    assert "unknown parameter 'h'" in capsys.readouterr().err


def test_importing_softbody_does_not_need_ray_and_a_missing_ray_names_the_install(monkeypatch, tmp_path):
    code = "import sys, softbody, softbody.control.sweep; assert 'ray' not in sys.modules, 'ray imported'"
    subprocess.run([sys.executable, "-c", code], check=True, env=dict(os.environ, SOFTBODY_COMPILATION_CACHE="0"))
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(sw.SweepError, match=r"pip install softbody\[sweep\]"):
        sw.run_sweep(beam_point, sw.grid({"E": [1e5], "dt": [0.01]}), setup=beam_setup, metrics=METRICS,
                     out=tmp_path / "s.csv")


# ------------------------------------------------------------------------------ sweeps on Ray


@pytest.mark.slow  # 64 points on two Ray workers and the 64 in-process references: ~3 min
def test_a_64_point_sweep_gives_the_in_process_metrics(cluster, reference, tmp_path):
    setups = tmp_path / "setups.log"
    res = sw.run_sweep(beam_point, sw.grid(GRID), setup=functools.partial(beam_setup, log=str(setups)),
                       metrics=METRICS, out=tmp_path / "beam.csv", workers=2, plot=("E", "tip_dz"),
                       progress_every=2.0)
    assert res.complete and res.evaluated == 64 and res.failed == 0 and res.skipped == 0
    assert [r["index"] for r in res.rows] == list(range(64))
    assert _metrics(res) == reference  # exactly
    assert all(r["attempts"] == 1 and r["error"] == "" for r in res.rows)
    for r, p in zip(res.rows, sw.grid(GRID)):
        assert (float(r["E"]), float(r["dt"])) == (p["E"], p["dt"])
    # each worker process built its scene once and ran many points on it
    pids = {r["pid"] for r in res.rows}
    assert len(pids) == 2 and sorted(_counts(setups)) == sorted(pids)
    assert max(int(r["worker_seq"]) for r in res.rows if r["pid"] == next(iter(pids))) > 1
    assert res.plot.exists() and res.plot.stat().st_size > 1000
    # a stiffer beam sags less (the metric is not a constant)
    dz = {(r["E"], r["dt"]): float(r["tip_dz"]) for r in res.rows}
    assert dz[(repr(GRID["E"][0]), "0.01")] < dz[(repr(GRID["E"][-1]), "0.01")] < 0


@pytest.mark.slow  # 64 points, a worker killed and replaced: ~2 min
def test_a_worker_killed_mid_point_loses_no_point(cluster, reference, tmp_path):
    points = sw.grid(GRID)
    victim = 21
    marker = tmp_path / "killed"
    fn = functools.partial(killing_point, marker=str(marker), victim=(points[victim]["E"], points[victim]["dt"]))
    res = sw.run_sweep(fn, points, setup=beam_setup, metrics=METRICS, out=tmp_path / "beam.csv", workers=2,
                       plot=False, progress=False)
    assert marker.exists(), "the victim point never ran"
    killed_pid = int(marker.read_text())
    assert res.complete and res.failed == 0 and res.replaced == 1
    assert [r["index"] for r in res.rows] == list(range(64))
    assert _metrics(res) == reference
    attempts = {r["index"]: r["attempts"] for r in res.rows}
    assert attempts.pop(victim) == 2 and set(attempts.values()) == {1}
    assert all(r["pid"] != str(killed_pid) for r in res.rows if r["index"] == victim)


@pytest.mark.slow  # three sweeps, each starting its workers: ~2-4 min
def test_a_stopped_sweep_resumes_with_only_the_missing_points(cluster, reference, tmp_path):
    points = sw.grid(GRID)[:16]
    log, out = tmp_path / "evaluations.log", tmp_path / "beam.csv"
    fn = functools.partial(counted_point, log=str(log))
    first = sw.run_sweep(fn, points, setup=beam_setup, metrics=METRICS, out=out, workers=2, max_points=6,
                         plot=False, progress=False)
    assert not first.complete and first.evaluated == 6 and len(first.rows) == 6
    assert len(_counts(log)) == 6
    with open(out, "a") as f:  # a row cut short by a killed sweep
        f.write("9,5e4,0.0")
    second = sw.run_sweep(fn, points, setup=beam_setup, metrics=METRICS, out=out, workers=2, resume=True,
                          progress=False)
    assert second.complete and second.skipped == 6 and second.evaluated == 10
    evaluations = _counts(log)
    assert len(evaluations) == 16 and len(set(evaluations)) == 16  # no point twice
    assert [r["index"] for r in second.rows] == list(range(16))
    assert _metrics(second) == reference[:16]
    third = sw.run_sweep(fn, points, setup=beam_setup, metrics=METRICS, out=out, resume=True, progress=False)
    assert third.evaluated == 0 and third.skipped == 16 and len(_counts(log)) == 16


def test_a_raising_point_is_recorded_with_its_message(cluster, tmp_path):
    points = sw.grid({"E": [1e5, 3e5], "dt": [0.01, 0.5]})
    res = sw.run_sweep(beam_point, points, setup=beam_setup, metrics=METRICS, out=tmp_path / "beam.csv",
                       workers=1, plot=("E", "tip_dz"), progress=False)
    assert res.complete and res.evaluated == 4 and res.failed == 2
    for r in res.rows:
        if r["dt"] == "0.5":
            assert r["error"].startswith("SceneError: Options.dt = 0.5 s is too large")
            assert r["tip_dz"] == "" and r["attempts"] == 1
        else:
            assert r["error"] == "" and float(r["tip_dz"]) < 0
    assert res.plot.exists()


def sum_point(a, b):
    return {"s": a + b, "p": a * b}


def test_the_cli_runs_a_spec_and_resumes_it(cluster, tmp_path, capsys):
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"scene": f"{__file__}:sum_point", "grid": {"a": [1, 2, 3], "b": [0.5, 2.0]},
                                "metrics": ["s", "p"], "workers": 2, "out": str(tmp_path / "table.csv"),
                                "plot": ["a", "p"]}))
    assert cli.main(["sweep", str(spec), "--max-points", "4", "--quiet"]) == 1  # not complete yet
    assert cli.main(["sweep", str(spec), "--resume", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "6/6 points" in out and "2 run now, 4 from before, 0 failed" in out
    rows = sw.read_table(tmp_path / "table.csv")
    assert sorted(r["index"] for r in rows) == list(range(6))
    assert {(r["a"], r["b"], r["s"]) for r in rows} == {(str(a), repr(b), repr(a + b))
                                                         for a in (1, 2, 3) for b in (0.5, 2.0)}
    assert (tmp_path / "table.png").exists()


def wave_point(a, k):
    """A traceable point function (for vectorize)."""
    return {"y": jnp.sin(k * a) * jnp.exp(-a)}


def test_vectorize_batches_points_with_equal_static_values_under_vmap(cluster, tmp_path):
    points = sw.grid({"a": [0.1 * i for i in range(6)], "k": [1.0, 2.0]})  # k varies fastest
    res = sw.run_sweep(wave_point, points, metrics=["y"], out=tmp_path / "w.csv", workers=2, batch=3,
                       vectorize=True, static=["k"], plot=False, progress=False)
    assert res.complete and res.failed == 0
    for r, p in zip(res.rows, points):
        assert float(r["y"]) == pytest.approx(float(np.sin(p["k"] * p["a"]) * np.exp(-p["a"])), rel=1e-14)
    # four batches of three points, each of one k: the points of a batch share its time
    batches = {}
    for r in res.rows:
        batches.setdefault(r["seconds"], set()).add(r["k"])
    assert sorted(len(b) for b in batches.values()) == [1, 1, 1, 1]
    assert sorted(sum(1 for r in res.rows if r["seconds"] == t) for t in batches) == [3, 3, 3, 3]


# ------------------------------------------------------------------------------ CMA-ES populations


def _codesign_problem():
    """The co-design problem of tests/test_control.py, smaller: a clamped 3-cell beam with a
    top and a bottom muscle channel; fibre weights, stiffness and controls reach a target."""
    from softbody.actuators import Muscle

    mesh = grid_box((0.1, 0.02, 0.02), (3, 1, 1))
    centre_z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    muscle = Muscle(np.arange(mesh.n_tets), np.tile([1.0, 0.0, 0.0], (mesh.n_tets, 1)),
                    np.where(centre_z > 0.01, 0, 1), ("top", "bottom"), stiffness=1e5)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, alpha=2.0), fixed="fixed",
                                   actuators=[muscle]), options=Options(dt=0.01, tol=1e-9, max_iter=400))
    design = sc.Design(model, params, muscles=True, max_weight=3.0, stiffness=["default"],
                       stiffness_range=(5e4, 2e5))
    loss = sc.TargetPosition(model, "tip", (0.095, 0.01, 0.02), over=2)
    problem = sc.CoDesignProblem(model, params, loss, sc.ControlGrid(4, 2, 1), design)
    return problem, problem.init(0.3)


def codesign_objective(problem, theta):
    return problem.objective(problem.project(theta))


def codesign_setup():
    from jax.flatten_util import ravel_pytree

    problem, theta0 = _codesign_problem()
    unravel = ravel_pytree(theta0)[1]
    return jax.jit(lambda x: codesign_objective(problem, unravel(x)))


def codesign_point(value, x):
    return {"loss": float(value(jnp.asarray(x)))}


@pytest.mark.slow
def test_cmaes_populations_on_sweep_workers_give_the_serial_run(cluster):
    problem, theta0 = _codesign_problem()
    kwargs = {"sigma0": 0.3, "budget": 18, "popsize": 6, "seed": 5, "progress": False}
    serial = sc.cmaes(functools.partial(codesign_objective, problem), theta0, **kwargs)
    with sc.SweepPool(codesign_point, setup=codesign_setup, metrics=["loss"], workers=2) as pool:
        evaluate = sc.population_evaluator(pool)
        parallel = sc.cmaes(None, theta0, evaluate=evaluate, **kwargs)
    assert len(evaluate.outcomes) == 18 and len({o.pid for o in evaluate.outcomes}) == 2
    np.testing.assert_array_equal(parallel.best_loss_history, serial.best_loss_history)
    np.testing.assert_array_equal(parallel.best_x_history, serial.best_x_history)
    assert parallel.best_loss == serial.best_loss < float(codesign_objective(problem, theta0))

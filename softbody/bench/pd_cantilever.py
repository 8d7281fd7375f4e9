"""Forward PD on the tet cantilever shared with DiffPD (2673 nodes, 12288 tets, 25 frames).

The scene (``data/diffpd_tet_cantilever.npz``): a 0.32 x 0.08 x 0.08 m beam, clamped at
x = 0, twisted up to 90 degrees at the tip, under gravity and a constant force, with 192
muscle tets along its bottom edge (fibre +x, stiffness 1e5, DiffPD's target stretch
``a0`` -> our activation ``1 - a0``); E = 1e6 Pa, nu = 0.45, density 1e3 kg/m^3,
dt = 0.01 s. DiffPD on this machine: 1.65-2.22 s forward per frame (1 thread), ~104 PD
iterations per frame at relative tolerance 1e-4 (its residual definition, which
:class:`softbody.model.Options` uses too).

Reported: forward seconds per frame (median over repeated 25-frame rollouts, compile
excluded), compile time, iterations per frame, the local/global split per iteration,
the loss ``w_q . q_T + w_v . v_T`` and its error against a tight-tolerance (1e-9) run.
"""

from __future__ import annotations

import time
from importlib import resources
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

DIFFPD = {"forward_s_per_frame": 1.65, "iterations_per_frame": 104, "loss": 14.8846, "backward_s_per_frame": 0.35}


def load_scene(tol: float = 1e-4, **option_overrides):
    """The shared cantilever as ``(model, params, state0, controls, forces, scene)``."""
    from softbody.actuators.muscle import Muscle
    from softbody.material import Material
    from softbody.meshing import Region, TetMesh
    from softbody.model import Options, build, initial_state
    from softbody.scene import SoftBody

    with resources.files("softbody.bench").joinpath("data/diffpd_tet_cantilever.npz").open("rb") as fh:
        scene = dict(np.load(fh))
    mesh = TetMesh(scene["vertices"], scene["elements"], regions={"fixed": Region(scene["dirichlet_nodes"])})
    act = scene["act_elements"]
    muscle = Muscle(act, np.tile([1.0, 0.0, 0.0], (len(act), 1)), np.arange(len(act)),
                    tuple(f"m{i}" for i in range(len(act))), stiffness=1e5)
    frames = int(scene["frames"])
    options = Options(**{"dt": float(scene["dt"]), "tol": tol, "max_iter": 2000, **option_overrides})
    model, params = build(SoftBody(mesh, Material(E=1e6, nu=0.45, density=1e3), fixed="fixed", actuators=[muscle]),
                          options=options)
    state0 = initial_state(model, params, x=scene["q0"].reshape(-1, 3), v=scene["v0"].reshape(-1, 3))
    controls = jnp.broadcast_to(1.0 - jnp.asarray(scene["a0"]), (frames, len(act)))
    forces = jnp.broadcast_to(jnp.asarray(scene["f0"].reshape(-1, 3)), (frames,) + mesh.points.shape)
    return model, params, state0, controls, forces, scene


def loss_of(traj, scene) -> jax.Array:
    """DiffPD's loss ``w_q . q_T + w_v . v_T``."""
    return jnp.dot(jnp.asarray(scene["w_q"]), traj.x[-1].ravel()) + jnp.dot(jnp.asarray(scene["w_v"]), traj.v[-1].ravel())


def _split(model, params, state0, controls, forces):
    """Milliseconds per local step (objective evaluation) and per global solve."""
    from softbody.model import prepare
    from softbody.objective import step_objective

    prep = jax.jit(lambda p: prepare(model, p))(params)
    evaluate, _ = step_objective(model, prep, state0.x, state0.v, state0.rot, controls[0], forces[0])
    solver = model.linear_solver
    x = state0.x + 1e-3

    def repeat(f, n=50):
        def body(c, _):
            return f(c), None
        return jax.jit(lambda c: jax.lax.scan(body, c, None, length=n)[0])

    local = repeat(lambda x: x + 1e-9 * evaluate(x, state0.rot)[1])
    solve = repeat(lambda x: x + 1e-9 * solver.solve(model.pattern, prep.factor, x))
    out = {}
    for name, f in (("local_ms_per_iteration", local), ("global_ms_per_iteration", solve)):
        jax.block_until_ready(f(x))
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            jax.block_until_ready(f(x))
            times.append((time.perf_counter() - t0) / 50 * 1e3)
        out[name] = float(np.median(times))
    return out


def run(out: Path, quick: bool) -> dict:
    from softbody import progress
    from softbody.simulate import rollout

    repeats = 2 if quick else 5
    with progress.task("pd-cantilever: loading and building the shared scene"):
        model, params, state0, controls, forces, scene = load_scene(tol=1e-4)
    frames = controls.shape[0]
    solver = type(model.linear_solver).__name__
    t0 = time.perf_counter()
    # One compiled rollout: reported around, not per step (see softbody.progress).
    with progress.compiling(f"pd-cantilever: compiling and running the {frames}-frame rollout ({solver})",
                            key=f"bench/pd-cantilever/rollout/{solver}", cached=not model.linear_solver.host_callback):
        traj = rollout(model, params, state0, controls=controls, forces=forces, throw=False)  # all_converged
        jax.block_until_ready(traj.x)
    first = time.perf_counter() - t0
    times = []
    with progress.task("pd-cantilever: timed rollouts", total=repeats) as bar:
        for _ in range(repeats):
            t0 = time.perf_counter()
            traj = rollout(model, params, state0, controls=controls, forces=forces, throw=False)  # all_converged
            jax.block_until_ready(traj.x)
            times.append(time.perf_counter() - t0)
            bar.advance(note=f"{times[-1] / frames:.3f} s per frame")
    per_frame = float(np.median(times)) / frames
    loss = float(loss_of(traj, scene))
    iterations = np.asarray(traj.info.iterations)
    evaluations = np.asarray(traj.info.evaluations)

    with progress.task("pd-cantilever: reference rollout at tolerance 1e-9 (compiles again)"):
        ref_model, ref_params, ref_state, *_ = load_scene(tol=1e-9)
        ref = rollout(ref_model, ref_params, ref_state, controls=controls, forces=forces)
        ref_loss = float(loss_of(ref, scene))
    with progress.task("pd-cantilever: timing the local step and the global solve"):
        split = _split(model, params, state0, controls, forces)

    figures = {
        "forward_s_per_frame": per_frame,
        "forward_s_per_frame_runs": [t / frames for t in times],
        "compile_s": max(first - float(np.median(times)), 0.0),
        "tolerance": 1e-4,
        "iterations_per_frame": float(iterations.mean()),
        "evaluations_per_frame": float(evaluations.mean()),
        "all_converged": bool(np.all(np.asarray(traj.info.converged))),
        "loss": loss,
        "loss_tight_tolerance": ref_loss,
        "loss_rel_error": abs(loss - ref_loss) / abs(ref_loss),
        **split,
        "linear_solver": type(model.linear_solver).__name__,
        "method": repr(model.step),
        "diffpd": DIFFPD,
        "speedup_vs_diffpd": DIFFPD["forward_s_per_frame"] / per_frame,
    }
    _plot(out / "pd-cantilever.png", figures, iterations)
    return figures


def _plot(path: Path, figures: dict, iterations: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    names = ["DiffPD (C++, 1 thread)", "softbody"]
    vals = [figures["diffpd"]["forward_s_per_frame"], figures["forward_s_per_frame"]]
    a.bar(names, vals, color=["0.6", "C0"])
    a.set_ylabel("forward seconds per frame")
    a.set_title(f"shared cantilever, rel. tol 1e-4: {figures['speedup_vs_diffpd']:.1f}x")
    for i, v in enumerate(vals):
        a.text(i, v, f"{v:.3f} s", ha="center", va="bottom")
    b.plot(np.arange(1, len(iterations) + 1), iterations, "o-", label="softbody")
    b.axhline(figures["diffpd"]["iterations_per_frame"], color="0.5", ls="--", label="DiffPD (mean)")
    b.set_xlabel("frame")
    b.set_ylabel("iterations")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

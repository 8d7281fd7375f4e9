"""Trajectory optimisation: a pneumatic finger reaches a target with its tip.

The finger (:func:`softbody.meshing.finger`, 90 mm long, one chamber above its neutral
axis; silicone-like E = 200 kPa) is clamped at its base and hangs under gravity. The
chamber's gauge pressure (0 to 60 kPa, :class:`softbody.actuators.CavityPressure`) is the
control: 6 knots over 0.5 s, linearly interpolated to the 25 steps of 20 ms, kept in
bounds by a sigmoid. The target is a point the finger can reach (where its tip rests
under a steady 40 kPa, which the optimiser is not told); the loss is the squared
distance of the tip's centroid to it over the last 5 frames (reach it and stay), plus a
small penalty on pressure changes. Adam runs on the knots through the simulation
(implicit adjoint); the optimisation checkpoints itself and ``--resume`` continues it.

Run::

    python examples/finger_reach.py --out results/finger

Writes ``metrics.json`` (``tip_error_m``, ``tip_error_fraction_of_length``, ...),
``loss.png``, ``pressure.png`` and ``tip_path.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax.numpy as jnp
import numpy as np
import optax

from softbody import control as sc
from softbody import progress
from softbody.actuators import CavityPressure
from softbody.io import check_overwrite, write_metrics
from softbody.material import Material
from softbody.meshing import finger
from softbody.model import Options, build
from softbody.scene import SoftBody
from softbody.simulate import solve_static

LENGTH = 0.09
P_MAX, P_HIDDEN = 6e4, 4e4
N_STEPS, N_KNOTS, DT = 25, 6, 0.02


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results (and start afresh)")
    parser.add_argument("--resume", action="store_true", help="continue the optimisation checkpointed in --out")
    parser.add_argument("--iterations", type=int, default=40, help="gradient iterations")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force or args.resume)
    checkpoint = args.out / "checkpoint.npz"
    if checkpoint.exists() and not args.resume:
        check_overwrite(checkpoint, args.force)
        checkpoint.unlink()
    start = time.perf_counter()

    with progress.task("meshing the finger and finding the target (a static solve: compiles)"):
        mesh = finger(length=LENGTH, size=0.008)
        chamber = CavityPressure.from_regions(mesh, ["cavity:chamber"], min_pressure=0.0, max_pressure=P_MAX)
        model, params = build(SoftBody(mesh, Material(E=2e5, nu=0.4, density=1100.0, alpha=10.0), fixed="fixed",
                                       actuators=[chamber]),
                              options=Options(dt=DT, tol=1e-6, max_iter=500))
        tip = mesh.regions["tip"].vertices
        weights = sc.centroid_weights(model, tip)
        x_hidden, _ = solve_static(model, params, activation=jnp.asarray([P_HIDDEN]))
    target = weights @ np.asarray(x_hidden)[tip]
    print(f"finger: {mesh.n_vertices} vertices, {mesh.n_tets} tets; target tip position {np.round(target, 4)} m")

    reach = sc.TargetPosition(model, "tip", target, over=5)
    loss = reach + 1e-6 * sc.Smoothness(scale=P_MAX)
    grid = sc.ControlGrid(N_STEPS, 1, N_KNOTS, lower=0.0, upper=P_MAX)
    problem = sc.ControlProblem(model, params, loss, grid)
    result = sc.optimize_controls(problem, 1e4, optimizer=optax.adam(0.1), n_iter=args.iterations,
                                  checkpoint=checkpoint)
    progress.say("simulating the optimised and the initial pressures")
    traj = problem.simulate(jnp.asarray(result.theta))
    tip_path = np.asarray(traj.x)[:, tip].transpose(0, 2, 1) @ weights  # (T + 1, 3)
    error = float(np.linalg.norm(tip_path[-1] - target))
    start_path = np.asarray(problem.simulate(problem.init(1e4)).x)[:, tip].transpose(0, 2, 1) @ weights
    print(f"tip error {error * 1e3:.2f} mm = {error / LENGTH:.2%} of the finger length "
          f"(from {np.linalg.norm(start_path[-1] - target) * 1e3:.1f} mm)")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.semilogy(result.loss)
    ax.set_xlabel("iteration (simulation + adjoint)")
    ax.set_ylabel("loss (m$^2$)")
    ax.set_title("Finger reach: Adam through the simulation")
    fig.tight_layout()
    fig.savefig(args.out / "loss.png", dpi=120)

    t = np.arange(N_STEPS) * DT
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(t, result.controls[:, 0] / 1e3, label="optimised")
    knot_t = np.linspace(0, (N_STEPS - 1) * DT, N_KNOTS)
    ax.plot(knot_t, result.knots[:, 0] / 1e3, "o", label="knots")
    ax.axhline(P_HIDDEN / 1e3, color="grey", ls=":", label="steady pressure of the target")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("chamber pressure (kPa)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "pressure.png", dpi=120)

    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(start_path[:, 0] * 1e3, start_path[:, 2] * 1e3, "--", label="initial (10 kPa)")
    ax.plot(tip_path[:, 0] * 1e3, tip_path[:, 2] * 1e3, ".-", label="optimised")
    ax.plot(target[0] * 1e3, target[2] * 1e3, "r*", ms=12, label="target")
    circle = plt.Circle((target[0] * 1e3, target[2] * 1e3), 0.02 * LENGTH * 1e3, fill=False, color="r", ls=":")
    ax.add_patch(circle)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("tip x (mm)")
    ax.set_ylabel("tip z (mm)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "tip_path.png", dpi=120)

    metrics = {
        "tip_error_m": error, "tip_error_fraction_of_length": error / LENGTH,
        "initial_tip_error_m": float(np.linalg.norm(start_path[-1] - target)),
        "finger_length_m": LENGTH, "target_m": target.tolist(), "best_loss": result.best_loss,
        "iterations": result.optimization.iterations, "simulations": result.simulations,
        "optimisation_wall_time_s": result.wall_time, "vertices": mesh.n_vertices, "tets": mesh.n_tets,
        "steps": N_STEPS, "knots": N_KNOTS, "pressure_knots_pa": result.knots[:, 0].tolist(),
        "wall_time_s": time.perf_counter() - start,
    }
    write_metrics(args.out / "metrics.json", metrics, force=True)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

"""Locomotion: a soft caterpillar learns to crawl on the ground with muscles and friction.

The body is a 120 x 20 x 20 mm block of soft material (E = 100 kPa) lying on a plane
with Coulomb friction (static 0.8, kinetic 0.6), meshed as a coarse structured grid (78
vertices, 144 tets) to keep each gradient (50 steps with contact) cheap. Four segments
along its length each carry a top and a bottom muscle layer with fibres along the body:
8 channels, activations in [0, 0.5]. The gait is periodic: 5 knots per channel over a 0.25 s period,
linearly interpolated (40 variables). Adam maximises the distance the centroid moves
along +x in two periods (0.5 s, from rest), differentiating through the contact and
friction solver; CMA-ES gets the same number of simulations on the same variables. Both
gaits are then run for 2 s (8 periods) to measure the distance in body lengths.

Run::

    python examples/crawler.py --out results/crawler

Writes ``metrics.json`` (``distance_body_lengths``, ``simulations``,
``cmaes_distance_same_budget``, physical ``checks`` of each 2 s run, the optimised
``gait_knots``, ...), ``distance_vs_simulations.png`` (training distance
against simulations for both methods), ``paths.png`` (top view of both centroids' paths
over the 2 s run) and ``gait.png`` (the optimised activations over one period).
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
from softbody.actuators import Muscle
from softbody.io import check_overwrite, write_metrics
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build
from softbody.scene import SoftBody
from softbody.contact.obstacles import Plane

LENGTH, WIDTH, HEIGHT = 0.12, 0.02, 0.02
N_SEGMENTS = 4
DT, PERIOD, N_KNOTS, A_MAX = 0.01, 25, 5, 0.5
TRAIN_PERIODS, EVAL_PERIODS = 2, 8


def caterpillar():
    """The body, its 8 muscle channels (segment x top/bottom) and the compiled scene."""
    mesh = grid_box((LENGTH, WIDTH, HEIGHT), (12, 1, 2), origin=(0.0, -WIDTH / 2, 0.0))
    centre = mesh.points[mesh.tets].mean(axis=1)
    segment = np.minimum((centre[:, 0] / (LENGTH / N_SEGMENTS)).astype(int), N_SEGMENTS - 1)
    bottom = centre[:, 2] < HEIGHT / 2
    names = tuple(f"{layer}{s}" for s in range(N_SEGMENTS) for layer in ("top", "bottom"))
    muscle = Muscle(np.arange(mesh.n_tets), np.tile([1.0, 0.0, 0.0], (mesh.n_tets, 1)),
                           2 * segment + bottom, names, stiffness=3e5)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, alpha=1.0), actuators=[muscle]),
                          options=Options(dt=DT, tol=1e-6, max_iter=1000), obstacles=[Plane(mu_s=0.8, mu_k=0.6)])
    return mesh, model, params


def sanity(traj) -> dict:
    """Physical checks of a rollout: does the body stay on the ground, intact, converged?

    Returns the deepest penetration of the ground (m; the contact solver keeps vertices
    at z >= 0), the highest the centroid rises above its rest height (m; a crawl, not a
    hop), the fraction of steps whose solve converged, and the most inverted tets.
    """
    x = np.asarray(traj.x)
    centroid_z = x[:, :, 2].mean(axis=1)
    return {"min_vertex_z_m": float(x[:, :, 2].min()),
            "max_centroid_rise_m": float(centroid_z.max() - centroid_z[0]),
            "converged_fraction": float(np.mean(np.asarray(traj.info.converged))),
            "max_inverted_tets": int(np.max(np.asarray(traj.info.inverted)))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--iterations", type=int, default=40, help="gradient iterations = simulation budget")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial gait (shared by both methods)")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    start = time.perf_counter()

    with progress.task("meshing and building the caterpillar"):
        mesh, model, params = caterpillar()
    distance = sc.ForwardDistance(model, axis=(1.0, 0.0, 0.0))
    grid = sc.ControlGrid(TRAIN_PERIODS * PERIOD, model.n_channels, N_KNOTS, period=PERIOD, upper=A_MAX)
    problem = sc.ControlProblem(model, params, distance, grid)
    theta0 = jnp.asarray(np.random.default_rng(args.seed).normal(scale=0.5, size=grid.shape))
    print(f"caterpillar: {mesh.n_vertices} vertices, {mesh.n_tets} tets, {model.n_channels} channels, "
          f"{theta0.size} gait variables")

    adam = sc.optimize_controls(problem, theta0, optimizer=optax.adam(0.2), n_iter=args.iterations)
    cma_start = time.perf_counter()
    cma = sc.cmaes(problem.objective, theta0, sigma0=0.5, budget=adam.simulations, seed=args.seed + 1)
    cma_time = time.perf_counter() - cma_start

    long_grid = sc.ControlGrid(EVAL_PERIODS * PERIOD, model.n_channels, N_KNOTS, period=PERIOD, upper=A_MAX)
    evaluation = sc.ControlProblem(model, params, distance, long_grid)
    runs, travelled, checks = {}, {}, {}
    gaits = (("gradient", adam.theta), ("cmaes", cma.best_theta), ("initial", theta0))
    for name, theta in progress.track(gaits, f"running each gait for {EVAL_PERIODS * PERIOD * DT:.1f} s",
                                      note=lambda item: item[0]):
        traj = evaluation.simulate(jnp.asarray(theta))
        runs[name], travelled[name] = np.asarray(traj.x), float(distance.travelled(traj))
        checks[name] = sanity(traj)
    print(f"checks of the gradient gait's run: {checks['gradient']}")
    seconds = EVAL_PERIODS * PERIOD * DT
    print(f"over {seconds:.1f} s: gradient gait {travelled['gradient'] / LENGTH:.2f} body lengths, CMA-ES "
          f"{travelled['cmaes'] / LENGTH:.2f}, initial {travelled['initial'] / LENGTH:.2f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(np.arange(1, adam.simulations + 1), -np.minimum.accumulate(adam.loss) * 1e3, "o-", ms=3,
            label="Adam through the simulation")
    ax.plot(cma.simulations, -cma.best_loss_history * 1e3, "s-", ms=3, label="CMA-ES")
    ax.set_xlabel("simulations")
    ax.set_ylabel(f"best distance in {TRAIN_PERIODS * PERIOD * DT:.1f} s (mm)")
    ax.set_title("Caterpillar gait: same simulation budget")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "distance_vs_simulations.png", dpi=120)

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, x in runs.items():
        c = x.mean(axis=1)
        ax.plot(c[:, 0] * 1e3, c[:, 1] * 1e3, label=f"{name} ({travelled[name] / LENGTH:.2f} body lengths)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_title(f"Centroid paths over {seconds:.1f} s (top view)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "paths.png", dpi=120)

    fig, ax = plt.subplots(figsize=(6, 3.5))
    image = ax.imshow(adam.controls[:PERIOD].T, aspect="auto", origin="lower", vmin=0, vmax=A_MAX,
                      extent=(0, PERIOD * DT, -0.5, model.n_channels - 0.5))
    ax.set_yticks(range(model.n_channels), model.channel_names)
    ax.set_xlabel("time in period (s)")
    fig.colorbar(image, label="activation")
    fig.tight_layout()
    fig.savefig(args.out / "gait.png", dpi=120)

    metrics = {
        "distance_body_lengths": travelled["gradient"] / LENGTH, "distance_m": travelled["gradient"],
        "cmaes_distance_same_budget": travelled["cmaes"] / LENGTH,
        "initial_gait_distance_body_lengths": travelled["initial"] / LENGTH,
        "evaluation_seconds": seconds, "body_length_m": LENGTH,
        "simulations": adam.simulations, "cmaes_simulations": cma.n_simulations,
        "training_distance_m": -adam.best_loss, "cmaes_training_distance_m": -cma.best_loss,
        "gradient_wall_time_s": adam.wall_time, "cmaes_wall_time_s": cma_time,
        "lateral_drift_m": float(runs["gradient"][-1].mean(axis=0)[1] - runs["gradient"][0].mean(axis=0)[1]),
        "vertices": mesh.n_vertices, "tets": mesh.n_tets, "variables": int(theta0.size),
        "checks": checks, "gait_knots": np.asarray(adam.knots).tolist(),
        "wall_time_s": time.perf_counter() - start,
    }
    write_metrics(args.out / "metrics.json", metrics, force=args.force)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

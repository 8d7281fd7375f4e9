"""CMA-ES over the caterpillar's fibre placement and gait, its populations evaluated on Ray
sweep workers, against the same run evaluated one candidate after another in this process.

The problem is ``codesign_crawler.py``'s (the muscle's per-tet fibre weights within the
budget and the cap, the gait on its control grid, the distance crawled in the training
periods as the loss), started from the uniform layout and the same random gait. CMA-ES
(:func:`softbody.control.cmaes`) asks for the same candidates for the same seed whoever
evaluates them, so with equal values the two runs are one search: the script checks that
their best-loss and best-point histories are equal and compares the wall times. The sweep
side is :class:`softbody.control.SweepPool` with
:func:`~softbody.control.sweep.population_evaluator`: each worker builds the caterpillar
once and reuses its compiled objective for every candidate it gets.

Run::

    python examples/codesign_sweep.py --out results/codesign_sweep [--workers 2] [--budget 128]

Writes ``metrics.json``: ``same_result`` (histories equal), ``max_loss_difference``,
``serial_wall_s``, ``sweep_wall_s`` (each with its compilation and, for the sweep, Ray's
start), ``speedup``, ``best_distance_mm``, ``simulations``, ``workers``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX, softbody and Ray (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from softbody import control as sc
from softbody import progress
from softbody.io import check_overwrite, write_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
from codesign_crawler import initial_gait, training_problem  # noqa: E402

SIGMA0 = 0.3


def start(problem, seed: int):
    """The search's start: the uniform layout and the random gait of ``codesign_crawler.py``."""
    return {"controls": initial_gait(problem.grid, seed), "weights": (jnp.ones(problem.model.mesh.n_tets),)}


def objective(problem, theta):
    """The loss of a candidate, projected onto the design's constraints first."""
    return problem.objective(problem.project(theta))


def setup():
    """On each worker: the compiled objective of a flat candidate."""
    _, problem = training_problem()
    unravel = ravel_pytree(start(problem, 0))[1]
    return jax.jit(lambda x: objective(problem, unravel(x)))


def point(compiled, x):
    """One candidate's loss (the negative distance crawled, m)."""
    return {"loss": float(compiled(jnp.asarray(x)))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--workers", type=int, default=2, help="Ray workers (default 2)")
    parser.add_argument("--budget", type=int, default=128, help="simulations of each run (default 128)")
    parser.add_argument("--popsize", type=int, default=8, help="CMA-ES population (default 8)")
    parser.add_argument("--seed", type=int, default=1, help="CMA-ES seed (default 1)")
    parser.add_argument("--address", default=None, help="a Ray cluster's address (default: a local Ray)")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    args.out.mkdir(parents=True, exist_ok=True)

    with progress.task("meshing and building the caterpillar"):
        _, problem = training_problem()
    theta0 = start(problem, 0)
    options = {"sigma0": SIGMA0, "budget": args.budget, "popsize": args.popsize, "seed": args.seed,
               "progress": False}

    with progress.task(f"CMA-ES, {args.budget} simulations one after another"):
        t0 = time.perf_counter()
        serial = sc.cmaes(lambda theta: objective(problem, theta), theta0, **options)
        serial_s = time.perf_counter() - t0
    with progress.task(f"CMA-ES, {args.budget} simulations on {args.workers} sweep workers"):
        t0 = time.perf_counter()
        with sc.SweepPool(point, setup=setup, metrics=["loss"], workers=args.workers, address=args.address) as pool:
            evaluate = sc.population_evaluator(pool)
            swept = sc.cmaes(None, theta0, evaluate=evaluate, **options)
        sweep_s = time.perf_counter() - t0

    same = bool(np.array_equal(serial.best_loss_history, swept.best_loss_history)
                and np.array_equal(serial.best_x_history, swept.best_x_history))
    difference = float(np.max(np.abs(serial.best_loss_history - swept.best_loss_history)))
    workers_used = len({o.pid for o in evaluate.outcomes})
    print(f"serial {serial_s:.1f} s, {workers_used} sweep workers {sweep_s:.1f} s ({serial_s / sweep_s:.2f}x); "
          f"best distance {-serial.best_loss * 1e3:.2f} mm (sweep {-swept.best_loss * 1e3:.2f} mm); "
          f"same histories: {same}", flush=True)
    metrics = {"same_result": same, "max_loss_difference": difference, "serial_wall_s": serial_s,
               "sweep_wall_s": sweep_s, "speedup": serial_s / sweep_s, "best_distance_mm": -swept.best_loss * 1e3,
               "simulations": int(swept.simulations[-1]), "workers": workers_used, "popsize": args.popsize,
               "seed": args.seed, "sigma0": SIGMA0}
    write_metrics(args.out / "metrics.json", metrics, force=args.force)
    print(f"wrote {args.out / 'metrics.json'}", flush=True)
    return metrics


if __name__ == "__main__":
    main()

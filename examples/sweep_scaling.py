"""Sweep scaling: a 64-point beam sweep (``sweep_beam.py``, 32 moduli x 2 time steps) on 1
and 2 local Ray workers, and batched under ``jax.vmap``. Each point is a 100-step rollout of
a 10 x 2 x 2-cell beam (about 1 s on one core here), so the points, not the start-up,
set the wall time; ``--cells 5,1,1 --steps 8`` gives the quick 0.1 s points of
``sweep_beam.json``.

Each run starts its own local Ray (counted in the wall time) and fresh worker processes,
which compile their programs (one per time step) on their first point at that time step,
or load them from softbody's persistent compilation cache. Reported per configuration:
the median wall time of ``--repeats`` runs, and from the table the seconds spent on the
points that compiled (each worker's first point at each time step) and on the rest.

Run::

    python examples/sweep_scaling.py --out results/sweep-scaling

Writes ``metrics.json`` and the last run's tables.
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX, softbody and Ray (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import numpy as np

from softbody import progress
from softbody.control import sweep as sw
from softbody.io import check_overwrite, write_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
import sweep_beam

GRID = {"E": [float(e) for e in np.geomspace(2e4, 2e5, 32)], "dt": [0.01, 0.02]}


def split_compile(rows) -> tuple[float, float]:
    """Seconds on points that compiled (first per worker process and time step) and on the rest."""
    seen, compile_s, run_s = set(), 0.0, 0.0
    for r in sorted(rows, key=lambda r: int(r["worker_seq"])):
        key = (r["pid"], r["dt"])
        if key in seen:
            run_s += float(r["seconds"])
        else:
            seen.add(key)
            compile_s += float(r["seconds"])
    return compile_s, run_s


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cells", default="10,2,2", help="the beam's cells along x,y,z (default 10,2,2)")
    parser.add_argument("--steps", type=int, default=100, help="rollout steps per point (default 100)")
    args = parser.parse_args(argv)
    cells = tuple(int(c) for c in args.cells.split(","))
    point = functools.partial(sweep_beam.point, n_steps=args.steps)
    setup = functools.partial(sweep_beam.setup, cells=cells)
    check_overwrite(args.out / "metrics.json", args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    points = sw.grid(GRID)
    configs = {"1 worker": {"workers": 1}, "2 workers": {"workers": 2},
               "2 workers, vmap batches of 16": {"workers": 2, "batch": 16, "vectorize": True, "static": ["dt"]}}
    results = {}
    for name, kwargs in configs.items():
        walls, splits = [], []
        for rep in range(args.repeats):
            out = args.out / f"{name.replace(' ', '_').replace(',', '')}.csv"
            # the sweep's own progress line goes to stderr; this task says on stdout what runs
            with progress.task(f"{name}: run {rep + 1}/{args.repeats} ({len(points)} points)", done=None):
                res = sw.run_sweep(point, points, setup=setup,
                                   metrics=["tip_dz", "iterations"], out=out, overwrite=True, plot=False,
                                   progress=False, **kwargs)
            assert res.complete and res.failed == 0, res.rows
            walls.append(res.wall_s)
            splits.append(split_compile(res.rows))
            print(f"{name}: run {rep + 1}: {res.wall_s:.1f} s (points that compiled {splits[-1][0]:.1f} s, "
                  f"the rest {splits[-1][1]:.1f} s)", flush=True)
        results[name] = {"wall_s": walls, "median_wall_s": statistics.median(walls),
                         "compile_point_s": [c for c, _ in splits], "other_points_s": [r for _, r in splits]}
    base = results["1 worker"]["median_wall_s"]
    for r in results.values():
        r["speedup_vs_1_worker"] = base / r["median_wall_s"]
    write_metrics(args.out / "metrics.json", {"points": len(points), "grid": GRID, "cells": list(cells),
                                              "steps": args.steps, "results": results},
                  force=args.force)
    for name, r in results.items():
        print(f"{name}: median {r['median_wall_s']:.1f} s, speed-up {r['speedup_vs_1_worker']:.2f}")


if __name__ == "__main__":
    main()

"""Co-design: where to put the caterpillar's muscle fibres, optimised together with its gait.

The body, ground, friction, channels and gait parameterisation are those of
``examples/crawler.py``; what changes is the muscle's per-tet fibre weight ``w`` (its
local strength), now a design variable. Every layout has the same total weight (the
budget: the caterpillar's 144 tets at ``w = 1`` on average, each tet capped at
``w <= 2``), so a layout only moves fibre from one place to another.

* Hand-placed layouts (uniform, bottom layer only, top layer only, front half, rear
  half): for each, Adam optimises the gait alone (the weights are
  frozen) from the same initial gait for the same number of gradient iterations.
* Co-design (:func:`softbody.control.codesign`): Adam optimises the gait and the
  weights together (projected onto the budget and the cap after every step), starting
  from the uniform layout and the same initial gait, with the same number of iterations.

Every result is then run for 2 s (8 periods) and its distance measured in body lengths.

Run::

    python examples/codesign_crawler.py --out results/codesign

Writes ``metrics.json`` (``optimised_distance``, ``best_hand_distance``, ``best_hand_layout``,
``hand_layouts``: the distance of each, ...), ``layouts.png`` (distance of every layout)
and ``weights.png`` (the optimised fibre weights along the body, top and bottom layers).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax.numpy as jnp
import numpy as np
import optax

from softbody import control as sc
from softbody import progress
from softbody.io import check_overwrite, write_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
from crawler import (A_MAX, DT, EVAL_PERIODS, LENGTH, N_KNOTS, PERIOD, TRAIN_PERIODS,  # noqa: E402
                     caterpillar, sanity)

MAX_WEIGHT = 2.0
LEARNING_RATE = 0.2


def hand_layouts(mesh) -> dict[str, np.ndarray]:
    """Hand-placed fibre weights ``(t,)``, each summing to the number of tets (capped at 2)."""
    centre = mesh.points[mesh.tets].mean(axis=1)
    s = centre[:, 0] / LENGTH  # 0 at the rear, 1 at the front
    bottom = centre[:, 2] < centre[:, 2].mean()
    masks = {
        "uniform": np.ones(len(s), bool),
        "bottom layer": bottom,
        "top layer": ~bottom,
        "rear half": s < 0.5,
        "front half": s >= 0.5,
    }
    layouts = {}
    for name, mask in masks.items():
        w = mask * (len(s) / mask.sum())
        assert w.max() <= MAX_WEIGHT and np.isclose(w.sum(), len(s))
        layouts[name] = w
    return layouts


def training_problem():
    """The caterpillar's mesh and its co-design problem over the training periods: the gait
    on the control grid, the muscle's fibre weights within the budget and the cap, the
    distance travelled along x as the loss."""
    mesh, model, params = caterpillar()
    distance = sc.ForwardDistance(model, axis=(1.0, 0.0, 0.0))
    grid = sc.ControlGrid(TRAIN_PERIODS * PERIOD, model.n_channels, N_KNOTS, period=PERIOD, upper=A_MAX)
    design = sc.Design(model, params, muscles=[0], budget=float(mesh.n_tets), max_weight=MAX_WEIGHT)
    return mesh, sc.CoDesignProblem(model, params, distance, grid, design)


def initial_gait(grid, seed: int):
    """The random gait every run starts from: knot values ``N(0, 0.5^2)`` of the seed."""
    return jnp.asarray(np.random.default_rng(seed).normal(scale=0.5, size=grid.shape))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--iterations", type=int, default=15, help="gradient iterations per layout")
    parser.add_argument("--seed", type=int, default=0, help="seed of the initial gait (shared by every run)")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    start = time.perf_counter()

    with progress.task("meshing and building the caterpillar"):
        mesh, problem = training_problem()
    model, params, distance, grid, design = problem.model, problem.params, problem.loss, problem.grid, problem.design
    n_tets = mesh.n_tets
    long_grid = sc.ControlGrid(EVAL_PERIODS * PERIOD, model.n_channels, N_KNOTS, period=PERIOD, upper=A_MAX)
    evaluation = sc.CoDesignProblem(model, params, distance, long_grid, design)
    gait0 = initial_gait(grid, args.seed)

    # One optimiser object per role, so that every frozen-layout run reuses one compiled iteration.
    frozen = optax.multi_transform({"gait": optax.adam(LEARNING_RATE), "design": optax.set_to_zero()},
                                   {"controls": "gait", "weights": ("design",)})
    joint = optax.adam(LEARNING_RATE)

    def run(layout, optimizer, label):
        theta0 = {"controls": gait0, "weights": (jnp.asarray(layout),)}
        res = sc.codesign(problem, theta0, optimizer=optimizer, n_iter=args.iterations)
        progress.say(f"{label}: running the result for {long_grid.n_steps * DT:.1f} s")
        traj = evaluation.simulate(res.theta)
        metres = float(distance.travelled(traj))
        checks[label] = sanity(traj)
        print(f"{label:>14}: {-res.best_loss * 1e3:6.2f} mm in {grid.n_steps * DT:.1f} s (training), "
              f"{metres / LENGTH:.3f} body lengths in {long_grid.n_steps * DT:.1f} s "
              f"({res.optimization.wall_time:.0f} s)")
        return res, metres

    hand, hand_training, hand_time, checks = {}, {}, 0.0, {}
    layouts = hand_layouts(mesh)
    for i, (name, w) in enumerate(layouts.items()):
        progress.say(f"layout {i + 1}/{len(layouts) + 1}: {name} (fixed fibres, gait optimised)")
        res, metres = run(w, frozen, name)
        hand[name], hand_training[name] = metres / LENGTH, -res.best_loss
        hand_time += res.optimization.wall_time
    best_hand = max(hand, key=hand.get)
    progress.say(f"layout {len(layouts) + 1}/{len(layouts) + 1}: co-design (fibres and gait optimised)")
    co, co_metres = run(np.ones(n_tets), joint, "co-design")
    weights = np.asarray(co.theta["weights"][0])
    print(f"co-design {co_metres / LENGTH:.3f} body lengths against the best hand layout ({best_hand}) "
          f"{hand[best_hand]:.3f}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    names = list(hand) + ["co-design"]
    values = [hand[n] for n in hand] + [co_metres / LENGTH]
    fig, ax = plt.subplots(figsize=(7, 3.8))
    ax.bar(names, values, color=["tab:blue"] * len(hand) + ["tab:orange"])
    ax.set_ylabel(f"distance in {long_grid.n_steps * DT:.0f} s (body lengths)")
    ax.set_title(f"Fibre layouts, each with its gait optimised ({args.iterations} iterations)")
    ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    fig.savefig(args.out / "layouts.png", dpi=120)

    centre = mesh.points[mesh.tets].mean(axis=1)
    bottom = centre[:, 2] < centre[:, 2].mean()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for layer, mask in (("top", ~bottom), ("bottom", bottom)):
        order = np.argsort(centre[mask, 0])
        ax.plot(centre[mask, 0][order] * 1e3, weights[mask][order], "o", ms=4, label=f"{layer} layer")
    ax.axhline(1.0, color="grey", ls=":", label="uniform (start)")
    ax.set_xlabel("x of the tet's centre (mm, rear to front)")
    ax.set_ylabel("fibre weight")
    ax.set_title("Co-designed fibre placement")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "weights.png", dpi=120)

    metrics = {
        "optimised_distance": co_metres / LENGTH, "best_hand_distance": hand[best_hand],
        "best_hand_layout": best_hand, "hand_layouts": hand,
        "optimised_training_distance_m": -co.best_loss, "hand_training_distance_m": hand_training,
        "distance_unit": "body lengths", "evaluation_seconds": long_grid.n_steps * DT,
        "training_seconds": grid.n_steps * DT, "iterations_per_layout": args.iterations,
        "weight_budget": float(n_tets), "max_weight": MAX_WEIGHT,
        "optimised_weight_sum": float(weights.sum()), "optimised_weight_range": [float(weights.min()),
                                                                                 float(weights.max())],
        "optimised_bottom_share": float(weights[bottom].sum() / weights.sum()),
        "optimised_front_half_share": float(weights[centre[:, 0] >= LENGTH / 2].sum() / weights.sum()),
        "checks": checks, "hand_wall_time_s": hand_time, "codesign_wall_time_s": co.optimization.wall_time,
        "wall_time_s": time.perf_counter() - start,
    }
    write_metrics(args.out / "metrics.json", metrics, force=args.force)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

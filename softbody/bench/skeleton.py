"""Cost of rigid bones in reduced coordinates against the same soft body without them.

The scene: a 0.44 x 0.04 x 0.04 m bar (a structured grid of 44 x 4 x 4 cells, 1125
vertices), clamped at x = 0, under gravity, E = 1e5 Pa, nu = 0.3, density 1e3 kg/m^3,
dt = 0.01 s. With ``k`` joints, ``k`` bones (each the 2 x 3 x 3 interior vertices of
one cell) form a chain of revolute joints about y, the first hinged to the world; with
0 joints one bone is welded to the world (``Fixed``). The baseline has no skeleton and
runs plain local-global PD (:class:`~softbody.solvers.LocalGlobal`), the iteration
:class:`~softbody.skeleton.SkeletonPD` generalises, on the same prefactored matrix.

Reported per configuration: seconds per iteration and per step (median over repeated
rollouts, compile excluded), iterations per step, and the time per iteration relative to
the baseline; ``overhead_20_joints`` is that ratio for 20 joints. The skeleton's time
includes its per-step condensation (:func:`~softbody.skeleton.schur_factor`, one solve
per bone vertex), amortised over the step's iterations.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

JOINTS = (0, 1, 5, 20)


def scene(n_joints: int | None):
    """``(model, params, state0)`` of the bar with ``n_joints`` joints (``None``: no skeleton)."""
    from softbody.material import Material
    from softbody.meshing import Region
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build, initial_state
    from softbody.skeleton import Fixed, Link, Revolute, Skeleton, SkeletonPD
    from softbody.solvers import LocalGlobal

    mesh = grid_box((0.44, 0.04, 0.04), (44, 4, 4))
    method = LocalGlobal()
    if n_joints is not None:
        p, links = mesh.points, []
        for i in range(max(n_joints, 1)):
            x0 = 0.02 + 0.02 * i
            inside = np.all((p >= [x0 - 1e-9, 0.01 - 1e-9, 0.01 - 1e-9]) & (p <= [x0 + 0.01 + 1e-9, 0.03 + 1e-9,
                                                                                  0.03 + 1e-9]), axis=1)
            mesh = mesh.with_regions(**{f"bone:{i}": Region(np.flatnonzero(inside),
                                                            np.flatnonzero(inside[mesh.tets].all(axis=1)))})
            joint = Revolute((0.0, 1.0, 0.0), (x0, 0.02, 0.02)) if n_joints else Fixed()
            links.append(Link(str(i), f"bone:{i}", str(i - 1) if i else None, joint))
        method = SkeletonPD(Skeleton(links).bind(mesh))
    model, params = build(mesh, Material(E=1e5, nu=0.3, density=1e3), fixed="xmin",
                          options=Options(dt=0.01, max_iter=500, method=method))
    return model, params, initial_state(model, params)


def _measure(n_joints, n_steps: int, repeats: int) -> dict:
    from softbody.simulate import rollout

    model, params, state0 = scene(n_joints)
    t0 = time.perf_counter()
    jax.block_until_ready(rollout(model, params, state0, n_steps=n_steps).x)
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        traj = rollout(model, params, state0, n_steps=n_steps)
        jax.block_until_ready(traj.x)
        times.append(time.perf_counter() - t0)
    seconds = float(np.median(times))
    iterations = int(np.sum(traj.info.iterations))
    return {"joints": n_joints, "n_vertices": model.n_vertices, "seconds_per_step": seconds / n_steps,
            "seconds_per_iteration": seconds / iterations, "iterations_per_step": iterations / n_steps,
            "converged": bool(np.all(traj.info.converged)), "first_run_s": compile_s}


def run(out: Path, quick: bool) -> dict:
    n_steps, repeats = (5, 1) if quick else (20, 3)
    baseline = _measure(None, n_steps, repeats)
    rows = [_measure(k, n_steps, repeats) for k in JOINTS]
    for row in rows:
        row["relative_time_per_iteration"] = row["seconds_per_iteration"] / baseline["seconds_per_iteration"]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    labels = ["none"] + [str(k) for k in JOINTS]
    a.bar(labels, [1.0] + [r["relative_time_per_iteration"] for r in rows], color=["grey"] + ["C0"] * len(rows))
    a.set_xlabel("joints")
    a.set_ylabel("time per iteration / no skeleton")
    a.set_title("skeleton overhead per iteration")
    b.bar(labels, [baseline["iterations_per_step"]] + [r["iterations_per_step"] for r in rows],
          color=["grey"] + ["C1"] * len(rows))
    b.set_xlabel("joints")
    b.set_ylabel("iterations per step")
    b.set_title(f"bar, {baseline['n_vertices']} vertices, dt = 0.01 s")
    fig.tight_layout()
    fig.savefig(Path(out) / "skeleton.png", dpi=120)
    plt.close(fig)
    overhead = next(r for r in rows if r["joints"] == 20)["relative_time_per_iteration"]
    return {"n_steps": n_steps, "baseline": baseline, "skeleton": rows, "overhead_20_joints": overhead}

"""Wall time per simulated second against problem size and against parallel scenes.

* Size: a clamped rubber beam (E = 1 MPa, nu = 0.45, 1000 kg/m^3, under gravity from rest,
  dt = 0.01 s, L-BFGS to rel. tol 1e-4) on ``grid_box`` meshes of about 500 to 30k
  vertices, with the default solver (sparse Cholesky on the host) and with the JAX-native
  Jacobi-PCG; ``steps`` steps are timed after compilation and scaled to one simulated
  second.
* Batch: ``B`` copies of a ~500-vertex beam with different Young's moduli, stepped together
  by ``jax.vmap`` over the parameters, with the JAX-native dense Cholesky solver (no host
  callback), for B = 1, 4, 16, 64. Reported per batch and per scene; the throughput gain is
  ``B * t(1) / t(B)``.

Times are medians of ``repeats`` runs of the compiled rollout (one run where it takes over
20 s; compilation reported apart).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

#: (cells) of the size sweep: 500, 2304, 8064, 29160 vertices (as in pd-scaling).
CELLS = [(19, 4, 4), (35, 7, 7), (55, 11, 11), (89, 17, 17)]
#: batch sizes of the vmap sweep
BATCHES = (1, 4, 16, 64)


def _beam(cells):
    from softbody.meshing.grid import grid_box

    return grid_box((0.05 * cells[0] / cells[1], 0.05, 0.05), cells)


def _build(mesh, dt, solver):
    from softbody.material import Material
    from softbody.model import Options, build
    from softbody.scene import SoftBody

    return build(SoftBody(mesh, Material(E=1e6, nu=0.45, density=1000.0, alpha=1.0), fixed="fixed"),
                 options=Options(dt=dt, tol=1e-4, max_iter=500, linear_solver=solver))


def _time_compiled(compiled, args, repeats, long: float = 20.0):
    """Median wall time of ``repeats`` calls (one call when it takes over ``long`` s)."""
    import jax

    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
        if times[0] > long:
            break
    return float(np.median(times)), out


def size_sweep(cells_list, steps: int, repeats: int, dt: float = 0.01, pcg_max_vertices: int = 3000) -> list:
    """Rows ``{vertices, dofs, solver, s_per_simulated_s, iterations_per_step, compile_s}``."""
    import jax

    from softbody import linsolve, progress, simulate
    from softbody.model import initial_state

    rows = []
    for cells in cells_list:
        mesh = _beam(cells)
        solvers = {"SparseCholesky (host)": linsolve.SparseCholesky(), "PCG (JAX)": linsolve.PCG(tol=1e-8)}
        for name, solver in solvers.items():
            if name.startswith("PCG") and mesh.n_vertices > pcg_max_vertices:
                rows.append({"vertices": mesh.n_vertices, "solver": name,
                             "skipped": f"over {pcg_max_vertices} vertices (Jacobi-PCG: ~0.2 s per solve "
                                        "at 8k, ~1 s at 30k)"})
                continue
            model, params = _build(mesh, dt, solver)
            state = initial_state(model, params)
            t0 = time.perf_counter()
            # throw=False: the row reports the converged fraction
            compiled = jax.jit(lambda p, s: simulate.rollout(model, p, s, n_steps=steps, throw=False)).lower(
                params, state).compile()
            compile_s = time.perf_counter() - t0
            wall, traj = _time_compiled(compiled, (params, state), repeats)
            row = {"vertices": mesh.n_vertices, "dofs": 3 * (mesh.n_vertices - len(model.fixed)), "solver": name,
                   "steps": steps, "wall_s": wall, "s_per_simulated_s": wall / (steps * dt),
                   "iterations_per_step": float(np.mean(traj.info.iterations)),
                   "converged_fraction": float(np.mean(traj.info.converged)),
                   "compile_s": compile_s}
            progress.say(f"scaling: {mesh.n_vertices:6d} vertices {name:22s} {row['s_per_simulated_s']:9.2f} s per "
                         f"simulated s ({row['iterations_per_step']:.1f} it/step, compile {compile_s:.1f} s)")
            rows.append(row)
    return rows


def batch_sweep(cells, batches, steps: int, repeats: int, dt: float = 0.01) -> list:
    """Rows ``{batch, s_per_simulated_s, per_scene_s_per_simulated_s, throughput_gain, compile_s}``."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from softbody import linsolve, progress, simulate
    from softbody.model import initial_state

    mesh = _beam(cells)
    model, params = _build(mesh, dt, linsolve.DenseCholesky())
    state = initial_state(model, params)
    rows = []
    for b in batches:
        moduli = jnp.geomspace(5e5, 2e6, b)[:, None]
        batched = eqx.tree_at(lambda p: p.E, params, moduli)
        axes = eqx.tree_at(lambda p: p.E, jax.tree.map(lambda _: None, params), 0, is_leaf=lambda x: x is None)

        def run(p, s):
            return simulate.rollout(model, p, s, n_steps=steps)

        fn = jax.jit(jax.vmap(run, in_axes=(axes, None)))
        t0 = time.perf_counter()
        compiled = fn.lower(batched, state).compile()
        compile_s = time.perf_counter() - t0
        wall, traj = _time_compiled(compiled, (batched, state), repeats)
        rows.append({"batch": b, "vertices": mesh.n_vertices, "solver": "DenseCholesky (JAX)", "steps": steps,
                     "wall_s": wall, "s_per_simulated_s": wall / (steps * dt),
                     "per_scene_s_per_simulated_s": wall / (steps * dt) / b,
                     "iterations_per_step": float(np.mean(traj.info.iterations)),
                     "compile_s": compile_s})
        progress.say(f"scaling: batch {b:3d}: {rows[-1]['s_per_simulated_s']:8.2f} s per simulated s "
                     f"({rows[-1]['per_scene_s_per_simulated_s']:.3f} per scene, compile {compile_s:.1f} s)")
    for r in rows:
        r["throughput_gain"] = r["batch"] * rows[0]["wall_s"] / r["wall_s"]
    return rows


def run(out: Path, quick: bool) -> dict:
    t_start = time.perf_counter()
    if quick:
        size = size_sweep(CELLS[:2], steps=5, repeats=1)
        batch = batch_sweep((9, 2, 2), (1, 4, 16), steps=5, repeats=1)
    else:
        size = size_sweep(CELLS, steps=5, repeats=3, pcg_max_vertices=3000)
        batch = batch_sweep(CELLS[0], BATCHES, steps=5, repeats=3)
    _plot(out / "scaling.png", size, batch)
    ok = [r for r in size if "s_per_simulated_s" in r and r["solver"].startswith("Sparse")]
    exponent = float(np.polyfit(np.log([r["dofs"] for r in ok]), np.log([r["s_per_simulated_s"] for r in ok]), 1)[0]) \
        if len(ok) > 1 else None
    return {"size": size, "batch": batch, "size_exponent_sparse_cholesky": exponent,
            "best_throughput_gain": max(r["throughput_gain"] for r in batch),
            "total_s": time.perf_counter() - t_start}


def _plot(path: Path, size, batch) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    for name in dict.fromkeys(r["solver"] for r in size):
        ok = [r for r in size if r["solver"] == name and "s_per_simulated_s" in r]
        a.loglog([r["dofs"] for r in ok], [r["s_per_simulated_s"] for r in ok], "o-", label=name)
    a.set_xlabel("free degrees of freedom")
    a.set_ylabel("wall s per simulated s (dt 0.01 s)")
    a.set_title("size (L-BFGS, rel. tol 1e-4)")
    a.legend()
    bs = [r["batch"] for r in batch]
    b.loglog(bs, [r["s_per_simulated_s"] for r in batch], "o-", label="whole batch")
    b.loglog(bs, [r["per_scene_s_per_simulated_s"] for r in batch], "s-", label="per scene")
    b.set_xlabel("scenes under jax.vmap")
    b.set_ylabel("wall s per simulated s")
    b.set_title(f"batch ({batch[0]['vertices']} vertices, dense Cholesky in JAX)")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""Time per PD iteration against mesh size, for each linear solver.

Structured beams (about 5:1:1, 6 tets per cell) of 500, 2304, 8064 and 29160 vertices,
E = 1e6 Pa, nu = 0.45, clamped at one end. One PD iteration is one local step (the
objective's value and gradient: deformation gradients, rotations, stresses, scatter) and
one global solve with 3 right-hand sides; each is timed in a compiled loop of 20 and the
median of 3 repeats is reported, in milliseconds.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

CELLS = [(19, 4, 4), (35, 7, 7), (55, 11, 11), (89, 17, 17)]  # 500, 2304, 8064, 29160 vertices


def _time(f, x, repeats=3, n=20):
    def body(c, _):
        return f(c), None

    loop = jax.jit(lambda c: jax.lax.scan(body, c, None, length=n)[0])
    jax.block_until_ready(loop(x))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(loop(x))
        times.append((time.perf_counter() - t0) / n * 1e3)
    return float(np.median(times))


def run(out: Path, quick: bool) -> dict:
    from softbody import linsolve, progress
    from softbody.native import available as native_available
    from softbody.material import Material
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build, initial_state, prepare
    from softbody.scene import SoftBody
    from softbody.objective import step_objective

    solvers = {"SparseCholesky": linsolve.SparseCholesky(), "DenseCholesky": linsolve.DenseCholesky(),
               **({"SparseLDL": linsolve.SparseLDL()} if native_available() else {}),
               "PCG": linsolve.PCG(tol=1e-8)}
    rows = []
    for cells in progress.track(CELLS[:2] if quick else CELLS, "pd-scaling: mesh sizes", unit="sizes",
                                note=lambda cells: f"{cells} cells, every solver"):
        mesh = grid_box((0.05 * cells[0] / cells[1], 0.05, 0.05), cells)
        n = mesh.n_vertices
        for name, solver in solvers.items():
            if name == "DenseCholesky" and n > 9000:
                rows.append({"vertices": n, "solver": name, "skipped": "dense factor needs > 5 GB"})
                continue
            if name == "PCG" and n > 9000 and quick:
                continue
            model, params = build(SoftBody(mesh, Material(E=1e6, nu=0.45), fixed="fixed"),
                                  options=Options(dt=0.01, linear_solver=solver))
            s0 = initial_state(model, params)
            t0 = time.perf_counter()
            prep = jax.block_until_ready(jax.jit(lambda p: prepare(model, p))(params))
            setup = time.perf_counter() - t0
            evaluate, _ = step_objective(model, prep, s0.x, s0.v, s0.rot, None, None)
            x = s0.x + 1e-3
            local = _time(lambda x: x + 1e-9 * evaluate(x, s0.rot)[1], x)
            solve = _time(lambda x: x + 1e-9 * solver.solve(model.pattern, prep.factor, x), x)
            rows.append({"vertices": n, "tets": mesh.n_tets, "solver": name, "local_ms": local,
                         "solve_ms": solve, "iteration_ms": local + solve, "setup_s": setup})
    _plot(out / "pd-scaling.png", rows)
    best = {}
    for r in rows:
        if "iteration_ms" in r and r["iteration_ms"] < best.get(r["vertices"], (np.inf,))[0]:
            best[r["vertices"]] = (r["iteration_ms"], r["solver"])
    return {"rows": rows, "fastest": {str(k): {"iteration_ms": v[0], "solver": v[1]} for k, v in best.items()}}


def _plot(path: Path, rows) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for name in dict.fromkeys(r["solver"] for r in rows):
        ok = [r for r in rows if r["solver"] == name and "iteration_ms" in r]
        if ok:
            ax.loglog([r["vertices"] for r in ok], [r["iteration_ms"] for r in ok], "o-", label=f"{name}")
    ok = [r for r in rows if r["solver"] == "SparseCholesky" and "local_ms" in r]
    ax.loglog([r["vertices"] for r in ok], [r["local_ms"] for r in ok], "k--", label="local step alone")
    ax.set_xlabel("vertices")
    ax.set_ylabel("ms per PD iteration (local + global)")
    ax.set_title("PD iteration cost, float64, 2-core CPU")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

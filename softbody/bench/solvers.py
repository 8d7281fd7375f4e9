"""Benchmark ``solvers``: time per linear solve against matrix size for each linear solver.

The matrices are PD global-step matrices ``M/h^2 + sum_e w vol_e G_e G_e^T`` of structured
tet grids (a 4:1:1 beam of hex cells, each split into 6 tets; no vertices fixed), with
``n`` = 256, 500, 2048, 8112 and 30400 vertices (``quick``: up to 2048). For each solver
in :mod:`softbody.linsolve` it measures

- the time per solve of 3 right-hand sides (float64) inside a jitted ``lax.scan`` of many
  solves sharing one factorisation, each right-hand side depending on the previous
  solution (so nothing is hoisted out of the loop): the median over repeats, divided by
  the number of solves. PCG starts cold (no warm start) at its default tolerance;
- the factorisation time (jitted ``factorize``, median over repeats);
- the relative residual ``|A x - b| / |b|`` of one solve;
- for :class:`~softbody.linsolve.SparseCholesky`, the host callback's overhead: the time
  per solve in the scan minus cholespy's own solve time called from Python.

Dense Cholesky is skipped where its matrix and workspace would exceed ~4 GB. Writes
``out/solvers.png``. Run with ``OPENBLAS_NUM_THREADS=1`` (recorded in the figures): with
more BLAS threads than cores, LAPACK's Cholesky slows down many times over.

The tet-grid generator and the PD matrix assembly here are also used by the linear
solvers' tests.
"""

from __future__ import annotations

import itertools
import os
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve, progress

#: vertices per axis of the benchmark grids (n = 256, 500, 2048, 8112, 30400); the smallest
#: brackets the size where dense and sparse Cholesky tie
GRID_SHAPES = ((16, 4, 4), (20, 5, 5), (32, 8, 8), (48, 13, 13), (76, 20, 20))

#: largest dense matrix (with Cholesky workspace, about three n x n float64 arrays) timed
DENSE_MEMORY_LIMIT = 4e9


def tet_grid(shape: tuple[int, int, int], spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A box of ``(nx-1) x (ny-1) x (nz-1)`` cubic cells, each split into 6 tets.

    Every cell is split along its main diagonal (the Kuhn triangulation), so the tets of
    neighbouring cells share faces. All tets are positively oriented.

    Arguments:
        shape: ``(nx, ny, nz)`` vertices per axis, each at least 2.
        spacing: cell edge length in metres.

    Returns:
        ``points`` ``(nx*ny*nz, 3)`` float64 and ``tets`` ``(6*(nx-1)*(ny-1)*(nz-1), 4)``
        int32 (vertex indices, vertex ``(i, j, k)`` has index ``(i*ny + j)*nz + k``).

    Raises:
        ValueError: if a dimension has fewer than 2 vertices or the spacing is not positive.
    """
    shape = tuple(int(s) for s in shape)
    if len(shape) != 3 or min(shape) < 2:
        raise ValueError(f"tet_grid: shape must be 3 vertex counts >= 2, got {shape}")
    if not spacing > 0:
        raise ValueError(f"tet_grid: spacing must be positive, got {spacing}")
    _, ny, nz = shape
    ijk = np.stack(np.meshgrid(*(np.arange(s) for s in shape), indexing="ij"), axis=-1)
    points = spacing * ijk.reshape(-1, 3).astype(np.float64)
    stride = np.array([ny * nz, nz, 1])
    corners = (stride * ijk[:-1, :-1, :-1].reshape(-1, 3)).sum(axis=1)
    tets = []
    for axes in itertools.permutations(range(3)):  # one tet per path from corner 000 to 111
        steps = np.cumsum([np.zeros(3, int)] + [np.eye(3, dtype=int)[a] for a in axes], axis=0)
        tets.append(corners[:, None] + steps @ stride)
    tets = np.concatenate(tets).astype(np.int32)
    edges = points[tets[:, 1:]] - points[tets[:, :1]]
    flip = np.linalg.det(edges) < 0
    tets[flip, 1], tets[flip, 2] = tets[flip, 2], tets[flip, 1]
    return points, tets


def pd_matrix(
    points: np.ndarray,
    tets: np.ndarray,
    *,
    density: float = 1e3,
    young: float = 1e6,
    poisson: float = 0.45,
    dt: float = 0.01,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scalar PD global-step matrix ``M/h^2 + sum_e w vol_e G_e G_e^T`` as COO entries.

    ``G_e`` (4 x 3) holds the gradients of the tet's linear shape functions; the weight
    ``w = 2 mu + lambda`` (Lame parameters of ``young``, ``poisson``) is that of the PD
    corotated plus volume terms; ``M`` is the lumped mass (a quarter of each tet's mass
    to each of its vertices).

    Arguments:
        points: ``(n, 3)`` rest positions, metres.
        tets: ``(m, 4)`` positively oriented tets.
        density: kg/m^3. young: Pa. poisson: Poisson ratio. dt: time step, s.

    Returns:
        ``rows``, ``cols``, ``values``: ``(16 m + n,)`` COO entries with repeats (sum them,
        e.g. with :meth:`softbody.linsolve.SparsityPattern.from_coo`).

    Raises:
        ValueError: if a tet is inverted or degenerate.
    """
    n = len(points)
    shape_matrix = np.transpose(points[tets[:, 1:]] - points[tets[:, :1]], (0, 2, 1))
    volume = np.linalg.det(shape_matrix) / 6.0
    if np.any(volume <= 0):
        raise ValueError(f"pd_matrix: {np.sum(volume <= 0)} tets are inverted or degenerate")
    inverse = np.linalg.inv(shape_matrix)  # row i: gradient of shape function i + 1
    gradients = np.concatenate([-inverse.sum(axis=1, keepdims=True), inverse], axis=1)
    mu = young / (2 * (1 + poisson))
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    stiffness = (2 * mu + lam) * volume[:, None, None] * gradients @ gradients.transpose(0, 2, 1)
    mass = np.bincount(tets.ravel(), np.repeat(density * volume / 4, 4), minlength=n)
    rows = np.concatenate([np.repeat(tets, 4, axis=1).ravel(), np.arange(n)])
    cols = np.concatenate([np.tile(tets, (1, 4)).ravel(), np.arange(n)])
    values = np.concatenate([stiffness.ravel(), mass / dt**2])
    return rows, cols, values


def grid_system(shape: tuple[int, int, int]) -> tuple[linsolve.SparsityPattern, np.ndarray]:
    """Pattern and ``(nnz,)`` values of :func:`pd_matrix` on :func:`tet_grid` ``(shape)``."""
    rows, cols, values = pd_matrix(*tet_grid(shape))
    pattern, index = linsolve.SparsityPattern.from_coo(shape[0] * shape[1] * shape[2], rows, cols)
    return pattern, np.bincount(index, values, minlength=pattern.nnz)


def _solvers() -> dict[str, linsolve.LinearSolver]:
    solvers = {
        "DenseCholesky": linsolve.DenseCholesky(),
        "PCG": linsolve.PCG(),
        "SparseLU": linsolve.SparseLU(),
    }
    if linsolve.cholespy is not None:
        solvers["SparseCholesky"] = linsolve.SparseCholesky()
    return solvers


def _timed(fn, budget_s: float, repeats: int = 5) -> float:
    """Median seconds of ``fn()`` after one warm-up call, over up to ``repeats`` runs
    (fewer when they would take longer than ``budget_s``; at least one)."""
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    count = int(np.clip(budget_s // max(first, 1e-9), 1, repeats))
    times = []
    for _ in range(count):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _time_per_solve(solver, pattern, factor, b) -> float:
    """Seconds per solve inside a jitted scan of solves sharing ``factor``."""

    def rollout(factor, b, steps):
        def step(x, _):
            return solver.solve(pattern, factor, b + 1e-3 * x), None

        return jax.lax.scan(step, jnp.zeros_like(b), None, length=steps)[0]

    single = jax.jit(lambda factor, b: rollout(factor, b, 1))
    estimate = _timed(lambda: single(factor, b).block_until_ready(), budget_s=0.5, repeats=3)
    steps = int(np.clip(0.5 / estimate, 3, 200))
    many = jax.jit(lambda factor, b: rollout(factor, b, steps))
    return _timed(lambda: many(factor, b).block_until_ready(), budget_s=5.0) / steps


def _cholespy_solve_time(factor, b) -> float:
    """Seconds per solve of cholespy alone (no JAX), for the callback-overhead figure."""
    solve = linsolve._CACHE.get(int(factor.aux))
    rhs = np.array(b)
    return _timed(lambda: solve(rhs), budget_s=2.0, repeats=50)


def _measure(solver, pattern, values: np.ndarray, b: jax.Array) -> dict:
    """Factorisation time, time per solve and residual of one solver on one matrix."""
    data = jnp.asarray(values)
    factorize = jax.jit(lambda data: solver.factorize(pattern, data))
    figures = {
        "factorize_s": _timed(
            lambda: jax.block_until_ready(factorize(data)), budget_s=10.0, repeats=3
        )
    }
    factor = factorize(data)
    x = np.asarray(jax.jit(lambda factor, b: solver.solve(pattern, factor, b))(factor, b))
    residual = pattern.to_scipy(values) @ x - b
    figures["relative_residual"] = float(np.linalg.norm(residual) / np.linalg.norm(b))
    figures["per_solve_ms"] = 1e3 * _time_per_solve(solver, pattern, factor, b)
    if isinstance(solver, linsolve.SparseCholesky):
        host_ms = 1e3 * _cholespy_solve_time(factor, b)
        figures["callback_overhead_ms"] = figures["per_solve_ms"] - host_ms
    return figures


def run(out: Path, quick: bool) -> dict:
    """Time every linear solver on the grid matrices; writes ``out/solvers.png``.

    Arguments:
        out: output directory (exists).
        quick: time only the matrices up to n = 2048.

    Returns:
        ``{"sizes", "grid_shapes", "per_solve_ms", "factorize_s", "relative_residual",
        "callback_overhead_ms", "auto_choice", "openblas_num_threads"}``; per-solver lists
        follow ``sizes``, with ``None`` where a solver was skipped.
    """
    shapes = GRID_SHAPES[:3] if quick else GRID_SHAPES
    solvers = _solvers()
    sizes = [int(np.prod(s)) for s in shapes]
    per_solve = {name: [] for name in solvers}
    factorize = {name: [] for name in solvers}
    residual = {name: [] for name in solvers}
    overhead = []
    rng = np.random.default_rng(0)
    for shape, n in progress.track(list(zip(shapes, sizes)), "solvers: matrix sizes", unit="sizes",
                                   note=lambda case: f"n = {case[1]}, every solver"):
        pattern, values = grid_system(shape)
        b = jnp.asarray(rng.standard_normal((n, 3)))
        for name, solver in solvers.items():
            if name == "DenseCholesky" and 3 * 8.0 * n * n > DENSE_MEMORY_LIMIT:
                figures = {"factorize_s": None, "per_solve_ms": None, "relative_residual": None}
            else:
                figures = _measure(solver, pattern, values, b)
            factorize[name].append(figures["factorize_s"])
            per_solve[name].append(figures["per_solve_ms"])
            residual[name].append(figures["relative_residual"])
            if "callback_overhead_ms" in figures:
                overhead.append(figures["callback_overhead_ms"])
        linsolve.clear_factor_cache()
    _plot(out / "solvers.png", sizes, per_solve, factorize)
    return {
        "sizes": sizes,
        "grid_shapes": [list(s) for s in shapes],
        "per_solve_ms": per_solve,
        "factorize_s": factorize,
        "relative_residual": residual,
        "callback_overhead_ms": overhead,
        "auto_choice": {str(n): type(linsolve.auto_solver(n)).__name__ for n in sizes},
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
    }


def _plot(path: Path, sizes, per_solve, factorize) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_solve, ax_factor) = plt.subplots(1, 2, figsize=(10, 4))
    for name in per_solve:
        points = [(n, t) for n, t in zip(sizes, per_solve[name]) if t is not None]
        ax_solve.plot(*zip(*points), "o-", label=name)
        points = [(n, t) for n, t in zip(sizes, factorize[name]) if t is not None]
        ax_factor.plot(*zip(*points), "o-", label=name)
    ax_solve.set(
        xscale="log",
        yscale="log",
        xlabel="n (vertices)",
        ylabel="ms per solve (3 right-hand sides)",
    )
    ax_factor.set(xscale="log", yscale="log", xlabel="n (vertices)", ylabel="factorisation, s")
    ax_solve.set_title("time per solve")
    ax_factor.set_title("factorisation")
    for ax in (ax_solve, ax_factor):
        ax.grid(True, which="both", alpha=0.3)
    ax_solve.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

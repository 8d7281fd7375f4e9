"""Benchmarks: ``softbody bench NAME --out DIR`` writes ``DIR/NAME.json`` and PNG charts.

An existing ``DIR/NAME.json`` (an earlier run's results) is replaced only with ``--force``;
the command refuses before running anything.

Each benchmark is a module ``softbody.bench.<name>`` (dashes become underscores) with
``run(out: pathlib.Path, quick: bool) -> dict``: it writes its charts into ``out`` and
returns the figures, which are written to ``out/<name>.json`` together with the machine
and package versions. Benchmarks measure; they never assert. They report their cases and
compiles through :mod:`softbody.progress` (a bar on a terminal, lines on a pipe); the
driver wraps the whole run in a progress task, so a pipe hears from it at least every
~10 s.
"""

from __future__ import annotations

import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path

#: benchmark name -> what it measures
BENCHMARKS = {
    "pd-cantilever": "forward PD on the shared DiffPD tet cantilever (2673 nodes, 25 frames)",
    "solvers": "time per linear solve against matrix size for each linear solver",
    "skeleton": "time per iteration with 0, 1, 5, 20 skeleton joints relative to the same soft bar without bones",
    "friction-stability": "spectral radius and convergence of the contact splittings (naive, diagonal, default) over meshes, stiffness and time step",
    "pd-scaling": "time per PD iteration (local + global) against mesh size for each linear solver",
    "gradients": "implicit/unrolled backward cost, finite-difference check, memory against horizon",
    "pareto": "speed against accuracy of PD, Newton, diffrax and explicit Euler on a vibrating cantilever; stability map",
    "scaling": "wall time per simulated second against degrees of freedom and against scenes batched by jax.vmap",
    "contact-pairs": "bodies touching bodies: a cube resting on a slab, a block sliding to rest (stopping distance against v0^2/(2 g mu_k) and a plane obstacle), a stack of three boxes, iterations per step, share of choosing the rows",
    "many-bodies": "N = 1, 4, 16, 64, 256 soft cubes dropped onto the ground and onto each other under one Touch: time, memory and iterations per step against N, its fitted exponent, broad-phase share",
    "impact-zone": "backward of the collision-response QP: QR form against the full KKT solve at 16x16, 32x32, 64x64 cloth sizes",
    "rl-pendulum": "SAC, SAC + sample enhancement, SAC + policy enhancement (one-step Jacobians) and rejax's PPO on an N-link pendulum: best relative reward against training samples, samples to reach SAC's final reward",
    "locking": "static deflection of a silicone cantilever (nu = 0.3 to 0.499) per element (linear tets, nodally averaged volume) against scikit-fem's P2 / Taylor-Hood reference; iterations",
}


def add_arguments(parser):
    """Arguments of ``softbody bench``."""
    parser.add_argument("name", choices=sorted(BENCHMARKS), help="which benchmark")
    parser.add_argument("--out", default="bench-out", help="output directory (default: bench-out)")
    parser.add_argument("--quick", action="store_true", help="a smaller, faster variant (for smoke tests)")
    parser.add_argument("--force", action="store_true",
                        help="replace the results of an earlier run in --out")


def median_seconds(fn, *args, repeats: int) -> float:
    """The median wall time of ``fn(*args)`` over ``repeats`` calls after one untimed call
    (which compiles a jitted ``fn``), each waited for (``jax.block_until_ready``)."""
    import jax

    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    times.sort()
    middle = len(times) // 2
    return times[middle] if len(times) % 2 else (times[middle - 1] + times[middle]) / 2


def environment() -> dict:
    """Machine and package versions recorded beside every benchmark's figures."""
    import jax
    import numpy

    return {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "numpy": numpy.__version__,
        "backend": jax.default_backend(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def check_output(name: str, out: Path, force: bool = False) -> Path:
    """Check that benchmark ``name`` may write into ``out``, before it runs.

    Arguments:
        name: the benchmark.
        out: its output directory (created later if missing).
        force: allow replacing ``out/<name>.json`` from an earlier run.

    Returns:
        The path of the JSON it will write, ``out/<name>.json``.

    Raises:
        NotADirectoryError: ``out``, or a folder above it, is a file.
        FileExistsError: ``out/<name>.json`` exists and ``force`` is false.
    """
    out = Path(out)
    for folder in (out, *out.parents):
        if folder.exists():
            if not folder.is_dir():
                raise NotADirectoryError(f"--out {out}: {folder} is a file, not a directory; "
                                         f"name a directory for the results")
            break
    path = out / f"{name}.json"
    if path.exists() and not force:
        raise FileExistsError(f"{path} already exists (an earlier run's results); pass --force "
                              f"to replace them or choose another --out")
    return path


def run_benchmark(name: str, out: Path, quick: bool = False, force: bool = False) -> dict:
    """Run one benchmark and write ``out/<name>.json``.

    Arguments:
        name: the benchmark (a key of :data:`BENCHMARKS`).
        out: the output directory; created if missing.
        quick: run the smaller, faster variant.
        force: replace the results of an earlier run.

    Returns:
        The figures, as written to the JSON.

    Raises:
        ValueError: unknown benchmark.
        NotADirectoryError, FileExistsError: see :func:`check_output`.
    """
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {sorted(BENCHMARKS)}")
    from softbody import progress

    path = check_output(name, out, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The benchmark reports its own cases (softbody.progress); this task keeps a pipe from
    # going silent for more than ~10 s whatever the benchmark does (a long compile, say).
    with progress.task(f"bench {name}" + (" (quick)" if quick else "")):
        module = importlib.import_module(f"softbody.bench.{name.replace('-', '_')}")
        figures = module.run(path.parent, quick)
    figures = {"benchmark": name, "quick": quick, **figures, "environment": environment()}
    path.write_text(json.dumps(figures, indent=2, default=float))
    return figures


#: how many top-level numeric figures the command prints (the JSON holds all of them)
SHOWN_FIGURES = 6


def summary(figures: dict, written: list[Path]) -> str:
    """The lines ``softbody bench`` ends with.

    Arguments:
        figures: a benchmark's figures, as :func:`run_benchmark` returns them.
        written: the files the run wrote (the JSON, the PNGs).

    Returns:
        The first :data:`SHOWN_FIGURES` top-level numeric figures, one a line, then a
        ``wrote PATH`` line per file.
    """
    numbers = [(k, v) for k, v in figures.items() if k != "quick" and isinstance(v, (int, float))]
    shown = numbers[:SHOWN_FIGURES]
    lines = [f"  {k}: {v}" if isinstance(v, (bool, int)) else f"  {k}: {v:.4g}" for k, v in shown]
    return "\n".join(lines + [f"wrote {p}" for p in written])


def run(args) -> int:
    """Run ``softbody bench``; returns the exit status (0 done, 2 output refused)."""
    out = Path(args.out)
    try:
        path = check_output(args.name, out, args.force)
    except (NotADirectoryError, FileExistsError) as err:
        print(f"softbody bench: {err}", file=sys.stderr)
        return 2
    quick = " (quick)" if args.quick else ""
    print(f"softbody bench {args.name}: running{quick} ... writing to {out}", flush=True)
    before = {p: p.stat().st_mtime_ns for p in out.glob("*.png")}
    figures = run_benchmark(args.name, out, args.quick, args.force)
    charts = sorted(p for p in out.glob("*.png") if before.get(p) != p.stat().st_mtime_ns)
    print(f"softbody bench {args.name}: done (all figures in the JSON)", flush=True)
    print(summary(figures, [path, *charts]))
    return 0

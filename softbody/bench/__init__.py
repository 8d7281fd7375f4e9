"""Benchmarks: ``softbody bench NAME --out DIR`` writes ``DIR/NAME.json`` and PNG charts.

Each benchmark is a module ``softbody.bench.<name>`` (dashes become underscores) with
``run(out: pathlib.Path, quick: bool) -> dict``: it writes its charts into ``out`` and
returns the figures, which are written to ``out/<name>.json`` together with the machine
and package versions. Benchmarks measure; they never assert.
"""

from __future__ import annotations

import importlib
import json
import os
import platform
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
}


def add_arguments(parser):
    parser.add_argument("name", choices=sorted(BENCHMARKS), help="which benchmark")
    parser.add_argument("--out", default="bench-out", help="output directory (default: bench-out)")
    parser.add_argument("--quick", action="store_true", help="a smaller, faster variant (for smoke tests)")


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


def run_benchmark(name: str, out: Path, quick: bool = False) -> dict:
    """Run one benchmark and write ``out/<name>.json``; returns the figures."""
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {sorted(BENCHMARKS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    module = importlib.import_module(f"softbody.bench.{name.replace('-', '_')}")
    figures = module.run(out, quick)
    figures = {"benchmark": name, "quick": quick, **figures, "environment": environment()}
    (out / f"{name}.json").write_text(json.dumps(figures, indent=2, default=float))
    return figures


def run(args) -> int:
    figures = run_benchmark(args.name, Path(args.out), args.quick)
    print(json.dumps({k: v for k, v in figures.items() if not isinstance(v, (list, dict))}, indent=2, default=float))
    print(f"wrote {Path(args.out) / (args.name + '.json')}")
    return 0

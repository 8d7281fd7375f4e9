"""Fidelity advisor: the cheapest PD set-up (mesh, time step, tolerance) that meets an error.

``softbody advise cantilever --tol 1e-2`` reads a measured speed/accuracy front (the runs of
``softbody bench pareto``, from ``--from DIR`` or ``--from DIR/pareto.json``) or, without
``--from``, measures a small one (two coarse meshes, a few time steps and tolerances, a short
horizon), keeps the projective-dynamics runs whose relative tip-trajectory error is at most ``tol``, and
picks the one with the least wall time. It reports the choice, its measured error and
time, and the faster configurations it passed over with the errors that ruled them out.

The advice holds for the measured scene and horizon: errors of implicit Euler grow with
the simulated time (phase error), so a longer run needs a re-measured front.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

from softbody.bench.pareto import Cantilever, measure_front

#: scene name -> the scene's factory (a :class:`~softbody.bench.pareto.Cantilever`-like object)
SCENES = {"cantilever": Cantilever}

#: The small front measured when no ``--from`` is given: half a period of the first mode
#: (implicit Euler's numerical damping, ~ omega^2 h t / 2 of the amplitude, needs
#: dt ~ 1e-4 s for 1% over that span), on the 24- and 99-vertex meshes.
SMALL_FRONT = {"scene": Cantilever(duration=0.05, divisions=(1, 2)),
               "pd_dts": (1 / 300, 1 / 1000, 1 / 3000, 1 / 10000, 1 / 30000), "pd_tols": (1e-6,),
               "bdf2_dts": (1 / 100, 1 / 300, 1 / 1000, 1 / 3000),
               "coarse_dts": (1 / 1000, 1 / 10000), "coarse_tols": (1e-6,)}


#: the fields :func:`advise` reads from a projective-dynamics row of the front
PD_FIELDS = ("mesh_k", "vertices", "dt", "tol")


class AdviceError(ValueError):
    """No measured configuration meets the requested error, or the input is unusable."""


@dataclasses.dataclass(frozen=True)
class Advice:
    """The advisor's choice.

    Attributes:
        choice: the chosen run (a row of the front: ``method``, ``mesh_k``, ``vertices``,
            ``dt``, ``tol``, ``wall_s``, ``rel_error``).
        tol: the requested relative error.
        candidates: how many PD runs met ``tol``.
        passed_over: faster PD runs that missed ``tol`` (fastest first).
    """

    choice: dict
    tol: float
    candidates: int
    passed_over: tuple

    def explain(self) -> str:
        """A few lines saying what was chosen and why."""
        c = self.choice
        lines = [
            f"choice: {c['method']} on the {c['vertices']}-vertex mesh ({5 * c['mesh_k']}x{c['mesh_k']}x"
            f"{c['mesh_k']} cells), dt = {c['dt']:.4g} s, tol = {c['tol']:g}",
            f"why: the fastest of {self.candidates} measured PD set-ups whose tip-trajectory error is "
            f"<= {self.tol:g}: error {c['rel_error']:.3g}, {c['wall_s'] * 1e3:.1f} ms per run "
            f"(compilation excluded). Errors are against diffrax on the front's finest mesh over its "
            f"horizon; a longer run accumulates more phase and damping error.",
        ]
        for r in self.passed_over[:3]:
            lines.append(f"  faster but too inaccurate: {r['vertices']} vertices, dt = {r['dt']:.4g} s, "
                         f"tol = {r['tol']:g} ({r['method']}): error {r['rel_error']:.3g}, "
                         f"{r['wall_s'] * 1e3:.1f} ms")
        return "\n".join(lines)


def advise(rows, tol: float) -> Advice:
    """Pick the cheapest PD row with ``rel_error <= tol``.

    Arguments:
        rows: front rows (dicts with ``method``, ``mesh_k``, ``vertices``, ``dt``, ``tol``,
            ``wall_s``, ``rel_error``), as in ``pareto.json``'s ``runs``.
        tol: the requested relative error (> 0).

    Returns:
        An :class:`Advice`.

    Raises:
        AdviceError: ``tol <= 0``, no PD rows, or none meets ``tol`` (the message gives the
            best error measured).
    """
    if not (tol > 0 and math.isfinite(tol)):
        raise AdviceError(f"--tol must be a positive relative error (e.g. 1e-2), got {tol!r}")
    pd = [r for r in rows if str(r.get("method", "")).startswith("PD")]
    if not pd:
        raise AdviceError("the front holds no projective-dynamics runs; run `softbody bench pareto --out DIR` "
                          "and pass --from DIR")
    ok = [r for r in pd if r["rel_error"] <= tol]
    if not ok:
        best = min(pd, key=lambda r: r["rel_error"])
        others = [r for r in rows if r["rel_error"] <= tol]
        hint = ""
        if others:
            o = min(others, key=lambda r: r["wall_s"])
            knobs = ", ".join(f"{k} = {o[k]:g}" for k in ("dt", "rtol") if k in o)
            hint = (f"; of the other methods, {o['method']} ({knobs}) reaches {o['rel_error']:.3g} in "
                    f"{o['wall_s'] * 1e3:.0f} ms")
        raise AdviceError(
            f"no measured PD set-up reaches a relative error of {tol:g}; the most accurate reaches "
            f"{best['rel_error']:.3g} (dt = {best['dt']:.4g} s, tol = {best['tol']:g}, {best['vertices']} "
            f"vertices){hint}. Loosen --tol, or measure a finer front with `softbody bench pareto`")
    choice = min(ok, key=lambda r: r["wall_s"])
    faster = sorted((r for r in pd if r["wall_s"] < choice["wall_s"] and r["rel_error"] > tol),
                    key=lambda r: r["wall_s"])
    return Advice(choice=choice, tol=tol, candidates=len(ok), passed_over=tuple(faster))


def load_front(source, scene_name: str) -> tuple[Path, list]:
    """The runs of a front written by ``softbody bench pareto``.

    Arguments:
        source: the ``pareto.json`` file, or the directory holding it.
        scene_name: the scene the advice is for (a key of :data:`SCENES`).

    Returns:
        ``(path, runs)``: the file read and its ``runs``.

    Raises:
        AdviceError: no such file, not JSON, not a pareto result (no ``scene`` or ``runs``,
            a run lacking a field the advice needs), or measured on another scene.
    """
    path = Path(source)
    if path.is_dir():
        path = path / "pareto.json"
    if not path.is_file():
        raise AdviceError(f"{path} does not exist; write it with `softbody bench pareto --out DIR` "
                          f"and pass --from DIR")
    try:
        data = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise AdviceError(f"{path} is not JSON ({err}); pass the pareto.json that "
                          f"`softbody bench pareto` writes") from None
    if not (isinstance(data, dict) and isinstance(data.get("scene"), dict)
            and isinstance(data.get("runs"), list)):
        raise AdviceError(f"{path} is not a pareto benchmark result (it has no 'scene' and 'runs'); "
                          f"pass the pareto.json that `softbody bench pareto` writes")
    for i, row in enumerate(data["runs"]):
        pd = isinstance(row, dict) and str(row.get("method", "")).startswith("PD")
        needed = ("method", "wall_s", "rel_error") + (PD_FIELDS if pd else ())
        missing = [k for k in needed if not isinstance(row, dict) or k not in row]
        if missing:
            raise AdviceError(f"{path} is not a pareto benchmark result: run {i} lacks "
                              f"{', '.join(missing)}")
    expected = dataclasses.asdict(SCENES[scene_name]())
    measured = data["scene"]
    differs = {k for k in expected if k not in ("duration", "divisions") and measured.get(k) != expected[k]}
    if differs:
        raise AdviceError(f"{path} was measured on another scene (differs in {sorted(differs)})")
    return path, data["runs"]


def tolerance(text: str) -> float:
    """``--tol``'s type: a relative error strictly between 0 and 1.

    Raises:
        argparse.ArgumentTypeError: ``text`` is not such a number (argparse prints the
            message and exits with status 2).
    """
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a relative error between 0 and 1 "
                                         f"(exclusive); give e.g. 1e-2 for 1%")
    return value


def add_arguments(parser):
    """Arguments of ``softbody advise``."""
    parser.add_argument("scene", choices=sorted(SCENES), help="the scene to advise on")
    parser.add_argument("--tol", type=tolerance, default=1e-2,
                        help="requested relative error of the tip trajectory, between 0 and 1 "
                             "(default: 0.01)")
    parser.add_argument("--from", dest="source", default=None, metavar="DIR|FILE",
                        help="pareto.json written by `softbody bench pareto`, or its directory "
                             "(default: measure a small front, a few minutes)")


def run(args) -> int:
    """Run ``softbody advise``; returns the exit status (0 advice given, 2 bad input or none)."""
    from softbody import progress

    try:
        if args.source is not None:
            path, rows = load_front(args.source, args.scene)
            print(f"front: {len(rows)} runs from {path}")
        else:
            grid = SMALL_FRONT
            print(f"measuring a small front on the {args.scene} scene ({grid['scene'].duration} s simulated)...",
                  flush=True)
            # each run says when it starts and ends; the task keeps a pipe from going silent
            # for more than ~10 s in between (compiles)
            with progress.task(f"advise: measuring the {args.scene} front", announce=False):
                rows, _ = measure_front(grid["scene"], grid, methods=("PD L-BFGS", "PD BDF2", "PD mesh"))
        advice = advise(rows, args.tol)
    except AdviceError as err:
        print(f"softbody advise: {err}", file=sys.stderr)
        return 2
    print(advice.explain(), flush=True)
    return 0

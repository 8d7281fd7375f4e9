"""No long silent waits (issue 42): ``softbody run``, ``softbody bench``, ``softbody advise`` and
the examples, read through a pipe as a log reader would, say what they do within 5 s, never
go quiet for more than ~10 s, and end with a summary.

Each command runs in a subprocess with stdout (and stderr) on a pipe; a thread timestamps
every line as it arrives. The checks:

* the first line within :data:`FIRST_LINE_S` (5 s) of the start;
* no gap between two lines (nor between the last line and the end) above :data:`MAX_GAP_S`.
  :mod:`softbody.progress` prints a ``still ...`` line after 8 s of silence; the limit is
  12 s, leaving 4 s for a loaded machine (these run on a shared 2-core machine beside other
  jobs);
* a summary at the end (the command's own last lines).

The fake benchmark and the stand-in front of ``softbody advise`` set
``SOFTBODY_PROGRESS_EVERY=1`` and sleep silently for a few seconds, so that the ``still ...``
lines are checked in a few seconds rather than tens. The real ``softbody advise`` (minutes)
and the examples (their first 30 s, then the process is stopped: none has a mode of a few
seconds) are in the slow tier.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

#: seconds from the start to the first line
FIRST_LINE_S = 5.0
#: the largest allowed silence: the helper's 8 s plus a 4 s margin for a loaded machine
MAX_GAP_S = 12.0
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


class Log:
    """The timestamped lines of a subprocess, read from its pipe as they come."""

    def __init__(self, argv, cwd, env=None, stop_after: float | None = None, stop_at_first_line: bool = False,
                 timeout: float = 300.0):
        environ = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **(env or {})}
        environ.pop("SOFTBODY_PROGRESS", None)
        self.start = time.monotonic()
        proc = subprocess.Popen(argv, cwd=cwd, env=environ, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, text=True, bufsize=1)
        self.lines: list[tuple[float, str]] = []
        first = threading.Event()

        def read():
            for line in proc.stdout:
                self.lines.append((time.monotonic() - self.start, line.rstrip("\n")))
                first.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        self.stopped = False
        try:
            if stop_at_first_line:
                first.wait(timeout)
                self.stopped = proc.poll() is None
            elif stop_after is not None:
                try:
                    proc.wait(stop_after)
                except subprocess.TimeoutExpired:
                    self.stopped = True
            else:
                proc.wait(timeout)
        finally:
            self.end = time.monotonic() - self.start
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            reader.join(10)
        self.returncode = proc.returncode

    @property
    def text(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def first(self) -> float:
        assert self.lines, "no output at all"
        return self.lines[0][0]

    def largest_gap(self) -> tuple[float, str]:
        """The longest silence and the line that ended it ("(end)" for the end)."""
        times = [0.0] + [t for t, _ in self.lines] + [self.end]
        names = [line for _, line in self.lines] + ["(end)"]
        return max((b - a, name) for a, b, name in zip(times, times[1:], names))

    def check(self, first: float = FIRST_LINE_S, gap: float = MAX_GAP_S) -> None:
        assert self.first() <= first, f"first line after {self.first():.1f} s:\n{self.dump()}"
        silence, line = self.largest_gap()
        assert silence <= gap, f"{silence:.1f} s of silence before {line!r}:\n{self.dump()}"

    def dump(self) -> str:
        return "\n".join(f"{t:7.1f} | {line}" for t, line in self.lines) + f"\n{self.end:7.1f} | (end)"


def softbody(*args) -> list[str]:
    return [sys.executable, "-m", "softbody.cli", *args]


# --------------------------------------------------------------------------------------
# the helper itself
# --------------------------------------------------------------------------------------


def test_plain_lines_name_the_task_count_and_time_and_end_with_a_summary(monkeypatch, capsys):
    from softbody import progress

    monkeypatch.setenv("SOFTBODY_PROGRESS", "plain")
    with progress.task("cases", total=2, unit="cases") as t:
        t.advance(note="first")
        t.advance(note="second")
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith("] cases ...") and lines[0].startswith("[")
    assert any("cases: 2/2 cases, second" in line for line in lines)
    assert lines[-1].endswith(" s") and "cases: done, 2/2 cases in" in lines[-1]


def test_a_failing_task_says_it_stopped_and_the_error_propagates(monkeypatch, capsys):
    from softbody import progress

    monkeypatch.setenv("SOFTBODY_PROGRESS", "plain")
    with pytest.raises(RuntimeError, match="boom"), progress.task("work"):
        raise RuntimeError("boom")
    assert "work: stopped after" in capsys.readouterr().out.splitlines()[-1]


def test_the_terminal_mode_runs_and_keeps_the_summaries(monkeypatch, capsys):
    """``SOFTBODY_PROGRESS=bar`` (a rich display; here on captured output) with the optimisers'
    ``progress_bar`` inside a task: no clash of two live displays, the summaries printed."""
    from softbody import progress
    from softbody.control.optimize import progress_bar

    monkeypatch.setenv("SOFTBODY_PROGRESS", "bar")
    with progress.task("outer"), progress_bar(True) as bar:
        k = bar.add_task("inner", total=3, stats="compiling")
        for i in range(3):
            bar.update(k, completed=i + 1, stats=f"loss {i}")
    out = capsys.readouterr().out
    assert "inner: done, 3/3 in" in out and "outer: done in" in out


# --------------------------------------------------------------------------------------
# softbody run, softbody bench, softbody advise through a pipe
# --------------------------------------------------------------------------------------


def test_run_speaks_within_5_s_and_never_goes_quiet(tmp_path):
    out = tmp_path / "result.npz"
    log = Log(softbody("run", "cantilever", "--size", "0.04", "--steps", "5", "-o", str(out)), cwd=tmp_path)
    assert log.returncode == 0, log.dump()
    log.check()
    assert "softbody run cantilever: 5 steps of 0.01 s" in log.lines[0][1]
    assert "compiling and simulating 5 steps" in log.text
    assert log.lines[-2][1].startswith("simulated 5 steps") and log.lines[-1][1] == f"wrote {out}"


def test_bench_of_a_cheap_real_benchmark_reports_its_cases(tmp_path):
    log = Log(softbody("bench", "impact-zone", "--quick", "--out", str(tmp_path)), cwd=tmp_path)
    assert log.returncode == 0, log.dump()
    log.check()
    assert log.lines[0][1] == f"softbody bench impact-zone: running (quick) ... writing to {tmp_path}"
    assert "impact-zone: cloth sizes: 1/1, 16x16" in log.text
    assert "softbody bench impact-zone: done (all figures in the JSON)" in log.text
    assert log.lines[-1][1].startswith("wrote ")


FAKE_BENCHMARK = """
import sys, time, types
from softbody import cli

def run(out, quick):
    time.sleep({sleep})  # a long compile: silent
    return {{"forward_s_per_frame": 0.1}}

module = types.ModuleType("softbody.bench.pd_cantilever")
module.run = run
sys.modules["softbody.bench.pd_cantilever"] = module
sys.exit(cli.main(["bench", "pd-cantilever", "--quick", "--out", {out!r}]))
"""


def test_bench_driver_speaks_while_a_benchmark_is_silent(tmp_path):
    """A benchmark that prints nothing for 5 s: the driver's task says ``still running``
    every second (``SOFTBODY_PROGRESS_EVERY=1``), the summary follows."""
    code = FAKE_BENCHMARK.format(sleep=5, out=str(tmp_path))
    log = Log([sys.executable, "-c", code], cwd=tmp_path, env={"SOFTBODY_PROGRESS_EVERY": "1"})
    assert log.returncode == 0, log.dump()
    log.check(gap=4.0)
    assert sum("bench pd-cantilever (quick): still running" in line for _, line in log.lines) >= 3, log.dump()
    assert "forward_s_per_frame: 0.1" in log.text and log.lines[-1][1].startswith("wrote ")


STAND_IN_FRONT = """
import sys, time
import numpy as np
from softbody import advisor, cli
from softbody.bench import pareto

class Reference:
    def error(self, t, u):
        return float(u[0, 0])

def measure_front(scene, grid, methods=None):
    # the real per-run reporting (pareto._entry) around stand-in runs that sleep silently
    rows = []
    for dt, error in ((1e-3, 0.05), (1e-4, 0.005)):
        run = lambda: (time.sleep({sleep}), (np.zeros(2), np.full((2, 3), error), 0.01 / dt * 1e-4, 1.0, {{}}))[1]
        rows.append(pareto._entry("PD L-BFGS", {{"dt": dt, "tol": 1e-6, "mesh_k": 2}}, Reference(), run, 99))
    return rows, Reference()

advisor.measure_front = measure_front
sys.exit(cli.main(["advise", "cantilever", "--tol", "0.01"]))
"""


def test_advise_reports_each_run_of_the_front_and_the_choice(tmp_path):
    """``softbody advise`` with a stand-in for the measuring (the real one takes minutes: see
    the slow test below): each run is announced, ``still running`` while it is silent, its
    result reported, the advice ends the output."""
    log = Log([sys.executable, "-c", STAND_IN_FRONT.format(sleep=3)], cwd=tmp_path,
              env={"SOFTBODY_PROGRESS_EVERY": "1"})
    assert log.returncode == 0, log.dump()
    log.check(gap=4.0)
    assert log.lines[0][1].startswith("measuring a small front on the cantilever scene")
    assert "PD L-BFGS dt=0.001, tol=1e-06, mesh_k=2 (99 vertices) ..." in log.text
    assert "PD L-BFGS dt=0.001, tol=1e-06, mesh_k=2 (99 vertices): still running" in log.text
    assert log.lines[-2][1].startswith("why: the fastest of 1 measured PD set-ups"), log.dump()


@pytest.mark.slow
def test_advise_measuring_its_small_front_never_goes_quiet(tmp_path):
    log = Log(softbody("advise", "cantilever"), cwd=tmp_path, timeout=1200)
    assert log.returncode == 0, log.dump()
    log.check()
    assert any(line.startswith("choice: PD") for _, line in log.lines), log.dump()


@pytest.mark.slow
def test_bench_pd_cantilever_quick_never_goes_quiet(tmp_path):
    """The benchmark that was silent for 93 s: a line per phase and timed rollout."""
    log = Log(softbody("bench", "pd-cantilever", "--quick", "--out", str(tmp_path)), cwd=tmp_path, timeout=900)
    assert log.returncode == 0, log.dump()
    log.check()
    assert "pd-cantilever: timed rollouts: done, 2/2" in log.text and log.lines[-1][1].startswith("wrote ")


# --------------------------------------------------------------------------------------
# the examples: their first 30 s (none has a mode of a few seconds)
# --------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("script", ["sysid_cantilever.py", "finger_reach.py", "crawler.py", "codesign_crawler.py"])
def test_an_example_speaks_within_5_s_and_stays_audible(script, tmp_path):
    """Stopped after 30 s: the first line within 5 s, before the imports; then progress
    (compiles announced, ``still ...`` lines, iterations) with no silence above 12 s."""
    log = Log([sys.executable, str(EXAMPLES / script), "--out", str(tmp_path / "out")], cwd=tmp_path,
              stop_after=30)
    log.check()
    assert log.lines[0][1] == f"{script}: starting (importing JAX and softbody) ..."
    assert len(log.lines) >= 3, log.dump()


def test_the_sweep_example_speaks_before_its_imports(tmp_path):
    """Only the first line (stopped then, before Ray starts)."""
    log = Log([sys.executable, str(EXAMPLES / "sweep_scaling.py"), "--out", str(tmp_path / "out")], cwd=tmp_path,
              stop_at_first_line=True, timeout=30)
    assert log.first() <= FIRST_LINE_S, log.dump()
    assert log.lines[0][1] == "sweep_scaling.py: starting (importing JAX and softbody) ..."


@pytest.mark.slow
def test_sysid_example_ends_with_its_summary(tmp_path):
    """The whole system-identification example with a small CMA-ES budget."""
    log = Log([sys.executable, str(EXAMPLES / "sysid_cantilever.py"), "--out", str(tmp_path / "out"),
               "--cmaes-budget", "24"], cwd=tmp_path, timeout=900)
    assert log.returncode == 0, log.dump()
    log.check()
    assert "Levenberg-Marquardt fit (compiles the Jacobian first): done" in log.text
    assert log.lines[-1][1].startswith(f"wrote {tmp_path / 'out' / 'metrics.json'}")

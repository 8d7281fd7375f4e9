"""``softbody bench``: no overwriting without --force, the summary it prints; the gradient
benchmark's child-process guard: memory cap, time limit, skipped horizons."""

import json
import sys
import types

import pytest

from softbody import cli
from softbody.bench import gradients


@pytest.fixture
def fake_benchmark(monkeypatch):
    """Stand in a fast module for ``softbody.bench.pd_cantilever``: it writes a tiny real PNG
    and returns a few figures; ``calls`` records the output directories it ran with."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    calls = []

    def run(out, quick):
        calls.append(out)
        plt.imsave(out / "pd-cantilever.png", [[0.0, 1.0], [1.0, 0.0]])
        return {"forward_s_per_frame": 0.1234567, "iterations_per_frame": 72.6, "all_converged": True,
                "method": "LBFGS()", "forward_s_per_frame_runs": [0.12, 0.13], "diffpd": {"forward_s_per_frame": 1.65}}

    module = types.ModuleType("softbody.bench.pd_cantilever")
    module.run = run
    monkeypatch.setitem(sys.modules, "softbody.bench.pd_cantilever", module)
    return calls


def test_bench_refuses_to_overwrite_earlier_results_without_force(tmp_path, fake_benchmark, capsys):
    earlier = tmp_path / "pd-cantilever.json"
    earlier.write_text('{"forward_s_per_frame": 0.2}')
    assert cli.main(["bench", "pd-cantilever", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"softbody bench: {earlier} already exists" in err and "--force" in err
    assert fake_benchmark == [] and earlier.read_text() == '{"forward_s_per_frame": 0.2}'

    assert cli.main(["bench", "pd-cantilever", "--out", str(tmp_path), "--force"]) == 0
    assert fake_benchmark == [tmp_path]
    assert json.loads(earlier.read_text())["forward_s_per_frame"] == 0.1234567


def test_bench_refuses_an_out_that_is_a_file(tmp_path, fake_benchmark, capsys):
    for target in (tmp_path / "notes.txt", tmp_path / "notes.txt" / "sub"):
        (tmp_path / "notes.txt").write_text("mine")
        assert cli.main(["bench", "pd-cantilever", "--out", str(target), "--force"]) == 2
        err = capsys.readouterr().err
        assert f"softbody bench: --out {target}: {tmp_path / 'notes.txt'} is a file, not a directory" in err
        assert fake_benchmark == [] and (tmp_path / "notes.txt").read_text() == "mine"


def test_bench_says_what_it_runs_then_summarises_figures_and_files(tmp_path, fake_benchmark, capsys):
    out = tmp_path / "results"
    out.mkdir()
    (out / "older.png").write_bytes(b"not rewritten by this run")
    assert cli.main(["bench", "pd-cantilever", "--quick", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"softbody bench pd-cantilever: running (quick) ... writing to {out}"
    text = "\n".join(lines)
    assert "forward_s_per_frame: 0.1235" in text and "iterations_per_frame: 72.6" in text
    assert "all_converged: True" in text
    assert f"wrote {out / 'pd-cantilever.json'}" in text and f"wrote {out / 'pd-cantilever.png'}" in text
    assert "older.png" not in text
    assert "{" not in text and "environment" not in text  # no JSON dump


def test_a_child_past_the_memory_cap_is_stopped_and_reported():
    grow = "import time\nblocks = []\nwhile True:\n    blocks.append(bytearray(50 * 2**20))\n    time.sleep(0.05)\n"
    why, peak, _, _ = gradients._watch([sys.executable, "-c", grow], timeout=60, cap_mb=300)
    assert why is not None and "out of memory" in why
    assert peak > 300


def test_a_child_past_the_time_limit_is_stopped_and_a_finished_one_is_not():
    why, _, _, _ = gradients._watch([sys.executable, "-c", "import time; time.sleep(30)"], timeout=1, cap_mb=1e6)
    assert why is not None and why.startswith("over 1 s")
    why, _, stdout, _ = gradients._watch([sys.executable, "-c", "print('{}')"], timeout=30, cap_mb=1e6)
    assert why is None and stdout.strip() == "{}"


def test_a_horizon_predicted_past_the_limit_is_not_started(monkeypatch):
    started = []

    def fake_watch(cmd, timeout, cap_mb):
        horizon = int(cmd[-1])
        started.append(horizon)
        row = {"adjoint": cmd[-2], "horizon": horizon, "gradient_s": 0.2 * horizon, "compile_s": 0.0}
        return None, 1.0, json.dumps(row) + "\n", ""

    monkeypatch.setattr(gradients, "_watch", fake_watch)
    rows = gradients.memory_table([50, 100, 500, 1000], ["implicit"], timeout=150, cap_mb=1e6)
    assert started == [50, 100, 500]  # 1000 steps would take ~200 s by the 500-step run
    assert rows[-1]["horizon"] == 1000 and rows[-1]["error"].startswith("not run: ~200 s")

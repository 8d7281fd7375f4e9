"""The gradient benchmark's child-process guard: memory cap, time limit, skipped horizons."""

import json
import sys

from softbody.bench import gradients


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

"""The README's first script runs as written and prints what it promises."""

import pathlib
import re
import subprocess
import sys

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def _first_script() -> str:
    text = README.read_text()
    section = text[text.index("## A first script"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_first_script_runs(tmp_path):
    script = tmp_path / "first.py"
    script.write_text(_first_script())
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.strip().splitlines()
    assert re.fullmatch(r"\(51, \d+, 3\) \d+(\.\d+)?", lines[0]), lines
    grad = float(re.search(r"\[([-+0-9.e]+)\]", lines[1]).group(1))
    assert grad > 0  # a stiffer beam sags less: the tip ends higher

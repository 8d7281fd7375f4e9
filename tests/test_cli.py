"""The ``softbody`` entry point: negative numbers as option values, and ``softbody advise``'s
argument checks (made before anything is measured) and help text."""

import dataclasses
import json

import numpy as np
import pytest

from softbody import advisor, cli
from softbody.bench.pareto import Cantilever
from softbody.io import Result

# --------------------------------------------------------------------------------------
# Negative numbers are values
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def coarse_mesh(tmp_path_factory):
    """The example cantilever meshed coarsely (170 vertices) by ``softbody mesh``."""
    path = tmp_path_factory.mktemp("mesh") / "cantilever.msh"
    assert cli.main(["mesh", "cantilever", "--size", "0.04", "-o", str(path)]) == 0
    return path


def test_run_reads_negative_numbers_in_exponent_and_decimal_forms_as_values(coarse_mesh, tmp_path):
    out = tmp_path / "result.npz"
    argv = ["run", str(coarse_mesh), "--steps", "2", "--gravity", "-1e1", "-.5", "-2E-3", "-o", str(out)]
    assert cli.main(argv) == 0
    result = Result.load(out)
    assert result.metadata["options"]["gravity"] == [-10.0, -0.5, -0.002]
    assert np.all(np.isfinite(result.x))


def test_a_negative_single_value_reaches_the_commands_own_check(coarse_mesh, tmp_path, capsys):
    """``--E -1e5`` is a value (refused as a material), not an unknown option ``-1e5``."""
    out = tmp_path / "result.npz"
    assert cli.main(["run", str(coarse_mesh), "--E", "-1e5", "--steps", "1", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "softbody run: Material.E = -100000.0" in err
    assert not out.exists()


def test_an_option_among_numbers_is_still_an_option(coarse_mesh, tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["run", str(coarse_mesh), "--gravity", "0", "-1e5", "-o", str(tmp_path / "r.npz")])
    assert stop.value.code == 2
    assert "argument --gravity: expected 3 arguments" in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# softbody advise: every argument checked before measuring
# --------------------------------------------------------------------------------------


@pytest.fixture
def no_measuring(monkeypatch):
    """Make measuring a front fail the test: argument checks must come first."""
    def measure_front(*args, **kwargs):
        raise AssertionError("softbody advise started measuring before checking its arguments")

    monkeypatch.setattr(advisor, "measure_front", measure_front)


@pytest.mark.parametrize("tol", ["0", "-0.1", "-1e-2", "1", "1.5", "nan", "inf", "a lot"])
def test_advise_refuses_a_bad_tol_before_measuring(tol, no_measuring, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["advise", "cantilever", "--tol", tol])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"argument --tol: {tol!r}" in err and "between 0 and 1" in err


def _front_file(path, scene=None, runs=None):
    """A pareto.json like ``softbody bench pareto`` writes, with three PD runs."""
    runs = runs if runs is not None else [
        {"method": "PD L-BFGS", "dt": 1e-2, "tol": 1e-6, "mesh_k": 2, "vertices": 99, "wall_s": 0.1,
         "rel_error": 0.9},
        {"method": "PD L-BFGS", "dt": 1e-3, "tol": 1e-6, "mesh_k": 2, "vertices": 99, "wall_s": 0.5,
         "rel_error": 0.3},
        {"method": "PD L-BFGS", "dt": 1e-4, "tol": 1e-6, "mesh_k": 2, "vertices": 99, "wall_s": 4.0,
         "rel_error": 0.05},
    ]
    data = {"benchmark": "pareto", "scene": scene or dataclasses.asdict(Cantilever()), "runs": runs}
    path.write_text(json.dumps(data))
    return path


def test_advise_reads_a_front_from_a_directory_or_its_file(tmp_path, no_measuring, capsys):
    front = _front_file(tmp_path / "pareto.json")
    for source in (tmp_path, front):
        assert cli.main(["advise", "cantilever", "--tol", "0.4", "--from", str(source)]) == 0
        out = capsys.readouterr().out
        assert f"front: 3 runs from {front}" in out
        assert "choice: PD L-BFGS on the 99-vertex mesh (10x2x2 cells), dt = 0.001 s" in out


def test_advise_refuses_a_missing_front_before_measuring(tmp_path, no_measuring, capsys):
    assert cli.main(["advise", "cantilever", "--from", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'nowhere'} does not exist" in err and "softbody bench pareto" in err
    assert cli.main(["advise", "cantilever", "--from", str(tmp_path)]) == 2  # a directory without pareto.json
    assert f"{tmp_path / 'pareto.json'} does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("content, why", [
    ("not json {", "is not JSON"),
    ("[1, 2]", "is not a pareto benchmark result"),
    (json.dumps({"benchmark": "gradients", "fd_rel_error": 1e-5}), "is not a pareto benchmark result"),
    (json.dumps({"scene": dataclasses.asdict(Cantilever()), "runs": [{"method": "PD L-BFGS"}]}),
     "run 0 lacks"),
])
def test_advise_refuses_a_file_that_is_not_a_pareto_front(content, why, tmp_path, no_measuring, capsys):
    path = tmp_path / "front.json"
    path.write_text(content)
    assert cli.main(["advise", "cantilever", "--from", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"softbody advise: {path} ") and why in err


def test_advise_refuses_a_front_of_another_scene(tmp_path, no_measuring, capsys):
    scene = {**dataclasses.asdict(Cantilever()), "E": 1e7}
    front = _front_file(tmp_path / "pareto.json", scene=scene)
    assert cli.main(["advise", "cantilever", "--from", str(front)]) == 2
    assert "was measured on another scene (differs in ['E'])" in capsys.readouterr().err


def test_advise_help_shows_the_defaults(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["advise", "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 0.01)" in text
    assert "(default: measure a small front" in text

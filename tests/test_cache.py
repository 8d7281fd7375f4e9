"""The persistent compilation cache (:mod:`softbody.cache`), in fresh processes.

Each check runs a child Python with ``SOFTBODY_CACHE_DIR`` in ``tmp_path``; the child
compiles one small softbody program (the step objective of a coarse cantilever: its
elastic energy and gradient), or a one-line program where only the settings matter, and
reports JAX's compilation-cache monitoring events. The children set
``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0`` so that what is written does not depend on
how fast this machine compiles.
"""

import json
import os
import subprocess
import sys

import pytest

from softbody import cache
from softbody.cli import main

#: The child's start: counts JAX's compilation-cache events.
HEAD = r"""
import json
import numpy as np
import jax, jax.monitoring
events = []
jax.monitoring.register_event_listener(lambda name, **kw: events.append(name))
import softbody
from softbody import cache
"""
#: The child's end: one JSON line with the events since ``events.clear()`` and where the cache is.
REPORT = r"""
print(json.dumps({
    "hits": events.count("/jax/compilation_cache/cache_hits"),
    "writes": events.count("/jax/compilation_cache/cache_misses"),
    "folder": None if cache.active() is None else str(cache.active()),
    "jax_dir": jax.config.jax_compilation_cache_dir,
}))
"""
#: Compiles one softbody program: the step objective (elastic energy and its gradient) of a
#: coarse cantilever.
CHILD = HEAD + r"""
from softbody import meshing
from softbody.material import Material
from softbody.model import build, initial_state, prepare
from softbody.objective import step_objective
from softbody.scene import SoftBody

mesh = meshing.examples.cantilever(length=0.1, width=0.02, height=0.02, size=0.02)
model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.45, density=1000), fixed="fixed"))
state = initial_state(model, params)
prep = prepare(model, params)
evaluate, _ = step_objective(model, prep, state.x, state.v, state.rot, jax.numpy.zeros(0), None)
x = state.x + 1e-3
events.clear()  # count only the program below
phi, grad, _ = jax.jit(evaluate)(x, state.rot)
assert np.isfinite(np.asarray(phi)) and np.isfinite(np.asarray(grad)).all(), (phi, grad)
""" + REPORT
#: Compiles a one-line program: for the checks of where (and whether) programs are written.
LIGHT = HEAD + r"""
x = jax.numpy.ones(3)
events.clear()
jax.jit(lambda x: 2 * x)(x).block_until_ready()
""" + REPORT


def child(tmp_path, code=CHILD, **env):
    """Run ``code`` in a fresh interpreter with softbody's cache in ``tmp_path``; returns
    (its JSON report or None, stderr)."""
    environ = {k: v for k, v in os.environ.items()
               if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "SOFTBODY_COMPILATION"))}
    environ.update(SOFTBODY_CACHE_DIR=str(tmp_path), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", **env)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=environ)
    assert proc.returncode == 0, f"child failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    lines = proc.stdout.strip().splitlines()
    return (json.loads(lines[-1]) if lines else None), proc.stderr


def entries(tmp_path):
    return cache.entries(tmp_path / "xla")


def test_a_second_process_loads_what_the_first_compiled(tmp_path):
    first, _ = child(tmp_path)
    assert first["folder"] == first["jax_dir"] == str(tmp_path / "xla")
    assert first["writes"] == 1 and first["hits"] == 0
    written = entries(tmp_path)
    assert len(written) >= 1
    second, _ = child(tmp_path)
    assert second["hits"] == 1 and second["writes"] == 0, "the second process compiled again"
    assert entries(tmp_path) == written


def test_off_switch_writes_nothing(tmp_path):
    report, _ = child(tmp_path, LIGHT, SOFTBODY_COMPILATION_CACHE="0")
    assert report["folder"] is None and report["jax_dir"] is None
    assert report["writes"] == 0
    assert not (tmp_path / "xla").exists()


def test_a_users_own_jax_cache_wins(tmp_path):
    own = tmp_path / "mine"
    report, _ = child(tmp_path, LIGHT, JAX_COMPILATION_CACHE_DIR=str(own))
    assert report["folder"] is None and report["jax_dir"] == str(own)
    assert cache.entries(own) and not (tmp_path / "xla").exists()


def test_default_threshold_and_users_threshold(tmp_path):
    code = "import jax, softbody; print(jax.config.jax_persistent_cache_min_compile_time_secs)"
    environ = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    environ["SOFTBODY_CACHE_DIR"] = str(tmp_path)
    run = lambda **env: subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,  # noqa: E731
                                       timeout=120, env={**environ, **env}).stdout.split()[-1]
    assert float(run()) == cache.MIN_COMPILE_TIME_S
    assert float(run(JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="7")) == 7.0


def test_an_unwritable_folder_falls_back_with_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    report, stderr = child(blocker / "cache", LIGHT)
    assert report["folder"] is None and report["jax_dir"] is None
    assert report["writes"] == 0 and report["hits"] == 0
    warning = [line for line in stderr.splitlines() if "compilation cache" in line]
    assert len(warning) == 1 and "cannot write to" in warning[0] and "SOFTBODY_CACHE_DIR" in warning[0]


def test_prune_keeps_the_most_recently_used(tmp_path):
    for k, name in enumerate(("old", "mid", "new")):
        path = tmp_path / f"{name}-cache"
        path.write_bytes(b"x" * 1000)
        os.utime(path, (1000 + k, 1000 + k))
    assert cache.prune(tmp_path, 2500) == 1
    assert [p.name for p in cache.entries(tmp_path)] == ["mid-cache", "new-cache"]
    assert cache.prune(tmp_path, 2500) == 0


def test_cache_clear_and_info(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SOFTBODY_CACHE_DIR", str(tmp_path))
    child(tmp_path, LIGHT)
    library = tmp_path / "softbody-0123456789abcdef.so"
    library.write_bytes(b"stand-in for the native library")
    assert main(["cache", "info"]) == 0
    info = capsys.readouterr().out
    assert str(tmp_path / "xla") in info and f"in {len(entries(tmp_path))} compiled programs" in info
    assert main(["cache", "clear"]) == 0
    assert "deleted" in capsys.readouterr().out
    assert entries(tmp_path) == [] and library.exists()
    assert main(["cache", "clear", "--all"]) == 0
    assert not library.exists()


def test_a_bad_size_cap_is_named(monkeypatch, capsys):
    monkeypatch.setenv(cache.MAX_MB_VARIABLE, "lots")
    with pytest.raises(ValueError, match="SOFTBODY_COMPILATION_CACHE_MB='lots'"):
        cache.max_bytes()
    assert main(["cache", "info"]) == 1
    assert "positive number of megabytes" in capsys.readouterr().err


ROLLOUT = r"""
import json, jax, softbody
from softbody import cache, meshing
from softbody.material import Material
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout
mesh = meshing.examples.cantilever(length=0.1, width=0.02, height=0.02, size=0.02)
model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.45, density=1000), fixed="fixed"), options=Options(dt=0.01))
rollout(model, params, initial_state(model, params), n_steps=2)
print(json.dumps([p.name for p in cache.entries()]))
"""


def test_a_rollout_is_cached(tmp_path):
    """A small scene (DenseCholesky) rolled out at top level compiles to a program without
    host callbacks, which JAX writes to the cache."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SOFTBODY_COMPILATION"))}
    environ.update(SOFTBODY_CACHE_DIR=str(tmp_path))
    proc = subprocess.run([sys.executable, "-c", ROLLOUT], capture_output=True, text=True, timeout=300, env=environ)
    assert proc.returncode == 0, proc.stderr
    assert any(name.startswith("jit__rollout-") for name in json.loads(proc.stdout.splitlines()[-1]))

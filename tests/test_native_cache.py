"""Programs with the native sparse solver and the native failure check hold no host
callback: JAX's persistent compilation cache writes them, and ``rollout(..., throw=True)``
under ``jax.jit`` still raises its message."""

import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.linsolve import SparseLDL
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import SimulationError, rollout

#: 0.1 x 0.02 x 0.02 m beam on 5 x 1 x 1 cells (24 vertices), clamped at x = 0.
BEAM = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
RUBBER = Material(E=1e5, nu=0.3, density=1000.0)

#: A rollout with the native solver and ``throw=True`` under ``jax.jit``, in a child process
#: whose JAX cache is a fresh folder: prints the cache's file names.
CHILD = r"""
import json, os, jax
import softbody
from softbody.linsolve import SparseLDL
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout
mesh = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0), fixed="fixed"),
                      options=Options(dt=0.01, linear_solver=SparseLDL()))
def tip_height(E):
    p = params.replace(E=E)
    return rollout(model, p, initial_state(model, p), n_steps=2).x[-1, :, 2].mean()
program = jax.jit(tip_height)
assert "callback" not in program.lower(params.E).as_text()
print(float(program(params.E)))
print(json.dumps(sorted(os.listdir(os.environ["JAX_COMPILATION_CACHE_DIR"]))))
"""


def test_a_checked_sparse_ldl_rollout_under_jit_is_written_to_the_cache(tmp_path):
    environ = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "SOFTBODY_COMPILATION"))}
    environ.update(JAX_COMPILATION_CACHE_DIR=str(tmp_path), JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0")
    proc = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=600, env=environ,
                          check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    height, names = proc.stdout.strip().splitlines()[-2:]
    assert 0 < float(height) < 0.01  # it sags from 0.01, the mean height at rest
    assert any(name.startswith("jit_tip_height-") for name in json.loads(names)), names


def test_throw_under_jit_raises_the_step_message_from_a_program_without_callbacks():
    """A tolerance no single iteration meets, with a 1-iteration cap: every step fails."""
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"),
                          options=Options(dt=0.01, tol=1e-12, max_iter=1, linear_solver=SparseLDL()))
    state = initial_state(model, params)
    with pytest.raises(SimulationError) as caught:
        rollout(model, params, state, n_steps=3)
    message = str(caught.value)
    assert message.startswith("step 0: stopped at the iteration cap (1 iterations")
    program = jax.jit(lambda p: rollout(model, p, state, n_steps=3).x[-1])
    assert "callback" not in program.lower(params).as_text()
    with pytest.raises(jax.errors.JaxRuntimeError, match=re.escape(message)):
        jax.block_until_ready(program(params))
    # under vmap the check takes the members one by one; trajectories that succeed pass unchanged
    fine = Options(dt=0.01, linear_solver=SparseLDL())
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"), options=fine)
    state = initial_state(model, params)
    batched = jax.jit(jax.vmap(lambda E: rollout(model, params.replace(E=E), state, n_steps=2).x[-1]))
    x = np.asarray(batched(jnp.stack([params.E, 2 * params.E])))
    assert np.all(np.isfinite(x))
    np.testing.assert_allclose(x[0], rollout(model, params, state, n_steps=2).x[-1], rtol=1e-12, atol=1e-15)

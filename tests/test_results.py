"""Per-step result codes (``StepInfo.result``) and ``throw=``: each failure kind from a real
failing scene, reported at the right step with ``throw=False``, raised with one message
with ``throw=True``, and the same message when the call is traced under ``jax.jit``."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import native
from softbody.explicit import explicit_rollout
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import (RESULTS, ImplicitEuler, SimulationError, _Messages, check_trajectory, integrate,
                               rollout, solve_static)

#: 0.1 x 0.02 x 0.02 m beam on 5 x 1 x 1 cells (24 vertices, 30 tets), clamped at x = 0.
BEAM = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
RUBBER = Material(E=1e5, nu=0.3, density=1000.0)
#: A tolerance no single iteration meets: every step stops at a 1-iteration cap.
CAPPED = Options(dt=0.01, tol=1e-12, max_iter=1)


def _message(call) -> str:
    with pytest.raises(SimulationError) as caught:
        call()
    return str(caught.value)


def _traced_raises(call, message: str):
    """``call()`` (a jitted function) raises at run time with ``message`` in its text."""
    with pytest.raises(Exception, match=re.escape(message)):
        jax.block_until_ready(call())


@pytest.fixture(scope="module")
def beam():
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"))
    state = initial_state(model, params)
    # One compiled program for every load below: the forces are its argument.
    traced = jax.jit(lambda forces: rollout(model, params, state, forces=forces).x)
    return model, params, state, traced


def _loads(model, step: int, vertices, fz: float) -> np.ndarray:
    forces = np.zeros((3, model.n_vertices, 3))
    forces[step:, vertices, 2] = fz
    return forces


def test_codes_are_plain_integers():
    assert [int(c) for c in RESULTS] == [0, 1, 2, 3, 4, 5]
    assert [c.name for c in RESULTS] == ["success", "max_iterations", "nonfinite", "inverted", "overflow", "tunnelled"]
    assert "iteration cap" in RESULTS.max_iterations.message


def test_a_normal_rollout_succeeds_at_every_step(beam):
    model, params, state, traced = beam
    traj = rollout(model, params, state, forces=_loads(model, 0, BEAM.regions["tip"].vertices, -0.01))
    assert traj.info.result.dtype == jnp.int32
    np.testing.assert_array_equal(traj.info.result, [RESULTS.success] * 3)
    assert bool(traj.info.converged.all())
    assert np.isfinite(np.asarray(traced(jnp.zeros((3, model.n_vertices, 3))))).all()


def test_the_iteration_cap_is_reported_and_raised_the_same_traced_or_not():
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"), options=CAPPED)
    state = initial_state(model, params)
    traj = rollout(model, params, state, n_steps=3, throw=False)
    np.testing.assert_array_equal(traj.info.result, [RESULTS.max_iterations] * 3)
    assert np.all(np.asarray(traj.info.iterations) == 1) and np.all(np.asarray(traj.info.residual) > 1e-12)
    message = _message(lambda: rollout(model, params, state, n_steps=3))
    assert message.startswith("step 0: stopped at the iteration cap (1 iterations")
    assert "tol = 1e-12" in message and "Raise Options.max_iter, loosen Options.tol, or reduce Options.dt" in message
    _traced_raises(lambda: jax.jit(lambda p: rollout(model, p, state, n_steps=3).x[-1])(params), message)


def test_a_non_finite_step_is_reported_and_raised_the_same_traced_or_not(beam):
    """A finite but absurd load (1e300 N) from step 1 on overflows the objective there."""
    model, params, state, traced = beam
    forces = _loads(model, 1, slice(None), 1e300)
    traj = rollout(model, params, state, forces=forces, throw=False)
    np.testing.assert_array_equal(traj.info.result, [RESULTS.success, RESULTS.nonfinite, RESULTS.nonfinite])
    message = _message(lambda: rollout(model, params, state, forces=forces))
    assert message.startswith("step 1: the force residual became non-finite (NaN/inf)")
    _traced_raises(lambda: traced(jnp.asarray(forces)), message)


def test_inverted_tets_are_reported_and_raised_the_same_traced_or_not(beam):
    """10 kN on one tip corner pushes it through its tets by the second step."""
    model, params, state, traced = beam
    forces = _loads(model, 0, BEAM.regions["tip"].vertices[0], -1e4)
    traj = rollout(model, params, state, forces=forces, throw=False)
    np.testing.assert_array_equal(traj.info.result, [RESULTS.success, RESULTS.inverted, RESULTS.inverted])
    assert int(traj.info.inverted[0]) == 0 and int(traj.info.inverted[1]) > 0
    message = _message(lambda: rollout(model, params, state, forces=forces))
    assert message.startswith("step 1: more tets inverted (det F <= 0) than in the initial state")
    _traced_raises(lambda: traced(jnp.asarray(forces)), message)


def test_check_trajectory_raises_what_rollout_raises_from_a_program_without_callbacks(beam):
    """``rollout(..., throw=False)`` under ``jit`` compiles without host callbacks (which
    would keep the program out of the persistent compilation cache), and so does
    ``throw=True`` when its check is native; ``check_trajectory`` on the output raises the
    message ``rollout`` raises."""
    model, params, state, _ = beam
    forces = _loads(model, 0, BEAM.regions["tip"].vertices[0], -1e4)
    message = _message(lambda: rollout(model, params, state, forces=forces))
    program = jax.jit(lambda f: rollout(model, params, state, forces=f, throw=False))
    assert "callback" not in program.lower(jnp.asarray(forces)).as_text()
    checked = jax.jit(lambda f: rollout(model, params, state, forces=f)).lower(forces).as_text()
    assert ("callback" in checked) != native.available()
    assert _message(lambda: check_trajectory(model, program(jnp.asarray(forces)))) == message
    fine = program(jnp.zeros_like(jnp.asarray(forces)))
    assert check_trajectory(model, fine) is fine
    with pytest.raises(TypeError, match="computed trajectory"):
        jax.jit(lambda f: check_trajectory(model, rollout(model, params, state, forces=f, throw=False)).x)(forces)


def test_a_matrix_that_is_not_positive_definite_fails_the_first_step(beam):
    """A negative Young's modulus makes the PD matrix indefinite: the dense factor is NaN
    (an arithmetic check, no run-time callback) and the first step reports non-finite."""
    model, params, _, _ = beam
    bad = eqx.tree_at(lambda p: p.E, params, -params.E)  # params.replace refuses E <= 0 before compiling
    state = initial_state(model, bad)
    traj = rollout(model, bad, state, n_steps=2, throw=False)
    np.testing.assert_array_equal(traj.info.result, [RESULTS.nonfinite] * 2)
    message = _message(lambda: rollout(model, bad, state, n_steps=2))
    assert message.startswith("step 0:") and "not positive definite" in message


def test_static_solve_at_its_cap_is_reported_and_raised_the_same_traced_or_not():
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"), options=CAPPED)
    x, info = solve_static(model, params, throw=False)
    assert int(info.result) == RESULTS.max_iterations and not bool(info.converged)
    message = _message(lambda: solve_static(model, params))
    assert message.startswith("the static solve stopped at the iteration cap (1 iterations")
    _traced_raises(lambda: jax.jit(lambda p: solve_static(model, p)[0])(params), message)


def test_explicit_rollout_past_its_stability_limit_reports_nonfinite():
    model, params = build(SoftBody(BEAM, Material(E=1e7, nu=0.3, density=1000.0), fixed="fixed"),
                          options=Options(dt=1e-3))
    state = initial_state(model, params)
    traj = explicit_rollout(model, params, state, n_steps=200, throw=False)
    result = np.asarray(traj.info.result)
    first = int(np.argmax(result != RESULTS.success))
    assert result[first] == RESULTS.nonfinite and np.all(result[first:] == RESULTS.nonfinite)
    assert np.all(result[:first] == RESULTS.success)
    message = _message(lambda: explicit_rollout(model, params, state, n_steps=200))
    assert message.startswith(f"step {first}: the explicit state became non-finite at dt = 0.001 s")


# ------------------------------------------------------------------------------ the one loop


class _BlowsUpAt(ImplicitEuler):
    """Implicit Euler whose step ``k`` (by the state's time) ends with NaN positions."""

    def __init__(self, k: int):
        self.k = k

    def step(self, model, prep, state, memory, activation, force):
        new, memory, info = super().step(model, prep, state, memory, activation, force)
        broken = jnp.round(state.t / model.options.dt) == self.k
        return eqx.tree_at(lambda s: s.x, new, jnp.where(broken, jnp.nan, new.x)), memory, info


def test_every_integrator_runs_in_the_one_loop():
    """The loop of rollouts sets the codes and holds the state for any integrator: a step
    that goes non-finite is reported at its index, the state is not advanced past it and
    every later step carries the code; the closed loop (a policy choosing the controls
    from the state) gives the open loop's steps bit for bit when it chooses the same
    controls."""
    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"))
    state = initial_state(model, params)
    traj, activations, failed, branch = jax.jit(lambda p: integrate(_BlowsUpAt(2), model, p, state, 5))(params)
    result = np.asarray(traj.info.result)
    np.testing.assert_array_equal(result, [RESULTS.success] * 2 + [RESULTS.nonfinite] * 3)
    assert bool(failed) and activations is None
    assert _Messages(ImplicitEuler().templates(model, "rollout"), 5)[int(branch)].startswith(
        "step 2: the positions became non-finite")
    plain = rollout(model, params, state, n_steps=5)
    np.testing.assert_allclose(traj.x[:3], plain.x[:3], rtol=0, atol=1e-15)  # round-off of another program
    assert np.isnan(traj.x[3]).all()  # the failing step's own positions, then not advanced
    np.testing.assert_array_equal(traj.x[4:], np.broadcast_to(traj.x[3], traj.x[4:].shape))

    loads = np.zeros((5, model.n_vertices, 3))
    loads[1:, BEAM.regions["tip"].vertices, 2] = -2.0
    open_loop, _, _, _ = jax.jit(lambda p: integrate(ImplicitEuler(), model, p, state, 5, (None, loads)))(params)
    closed, _, _, _ = jax.jit(lambda p: integrate(ImplicitEuler(), model, p, state, 5, loads,
                                                  choose=lambda s, f: (None, f)))(params)
    for a, b in zip(jax.tree.leaves(open_loop), jax.tree.leaves(closed)):
        np.testing.assert_array_equal(a, b)

"""The reinforcement-learning environment (softbody.control.env): gymnax-style reset/step,
batches by vmap, exact one-step Jacobians against central differences with and without
contact, the contact-switch flag, and bad input refused before compiling.

Scenes (float64, tight tolerance so that the implicit derivative of the exact step solution
matches finite differences of the computed one):

* a two-link pendulum: two bones (revolute joints about y, the shoulder hinged to the
  world) in a soft skin, 20 vertices, a joint torque on the shoulder and a servo on the
  elbow; no contact;
* a crawler: a 60 x 20 x 20 mm soft block (16 vertices) with a top and a bottom muscle
  layer, resting on a friction plane (mu_s 0.8, mu_k 0.6): contact.
"""

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from softbody.actuators import Muscle
from softbody.actuators.joints import JointServo, JointTorque
from softbody.control import ControlError, Observations
from softbody.control import env as E
from softbody.meshing.grid import grid_box
from test_skeleton import _box_region

from softbody._types import RESULTS, State
from softbody.contact.obstacles import Plane
from softbody.gradients import central_difference, random_directions
from softbody.material import Material
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import Trajectory, contact_forces
from softbody.skeleton import Link, Revolute, Skeleton

KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def pendulum():
    """A two-link pendulum in a soft skin, released horizontal: (model, params, env)."""
    mesh = grid_box((0.08, 0.02, 0.02), (4, 1, 1))
    mesh = mesh.with_regions(**{"bone:upper": _box_region(mesh, (0, 0, 0), (0.02, 0.02, 0.02)),
                                "bone:fore": _box_region(mesh, (0.06, 0, 0), (0.08, 0.02, 0.02))})
    skeleton = Skeleton([Link("upper", "bone:upper", None, Revolute((0.0, 1.0, 0.0), (0.0, 0.01, 0.01))),
                         Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.05, 0.01, 0.01)))])
    model, params = build(SoftBody(mesh, Material(E=2e4, nu=0.3, density=1000.0)), skeleton=skeleton,
                          actuators=[JointTorque(["upper"]), JointServo(["fore"], stiffness=0.05)],
                          options=Options(dt=0.01, tol=1e-10, max_iter=500))
    env = E.Env(model, params, observation=E.JointAngles(model),
                reward=E.Height(model, "xmax") + 0.01 * E.ActionPenalty(),
                action_map=E.ActionMap(model, low=[-2e-3, -0.5], high=[2e-3, 0.5]), episode_length=3,
                reset_noise=E.ResetNoise(joint=0.05))
    return model, params, env


@pytest.fixture(scope="module")
def crawler():
    """A soft block with two muscle layers on a friction plane: (model, params, env)."""
    width, height = 0.02, 0.02
    mesh = grid_box((0.06, width, height), (3, 1, 1), origin=(0.0, -width / 2, 0.0))
    bottom = mesh.points[mesh.tets].mean(axis=1)[:, 2] < height / 2
    muscle = Muscle(np.arange(mesh.n_tets), np.tile([1.0, 0.0, 0.0], (mesh.n_tets, 1)), bottom.astype(int),
                    ("top", "bottom"), stiffness=3e5)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, alpha=1.0), actuators=[muscle]),
                          options=Options(dt=0.01, tol=1e-10, max_iter=3000), obstacles=[Plane(mu_s=0.8, mu_k=0.6)])
    env = E.Env(model, params, observation=E.Concat(E.Positions(model, "xmax"), Observations(model)),
                reward=E.Progress(model) + 0.01 * E.ActionPenalty(), episode_length=4,
                reset_noise=E.ResetNoise(position=1e-4, velocity=1e-3))
    return model, params, env


def _rel(ad, fd) -> float:
    return float(np.linalg.norm(np.asarray(ad) - np.asarray(fd)) / np.linalg.norm(np.asarray(fd)))


def _richardson(fn, x, d, eps):
    """The vector version of :func:`softbody.gradients.central_difference`: central
    differences at ``eps`` and ``eps / 2``, Richardson-extrapolated (O(eps^4))."""
    def central(h):
        return (np.asarray(fn(x + h * d)) - np.asarray(fn(x - h * d))) / (2 * h)

    return (4 * central(eps / 2) - central(eps)) / 3


def _check_jacobians(env, state, action, eps_a, eps_s, seed=0):
    """ds'/da, dr/da (two random unit action directions), ds'/ds and dr/ds (a random
    direction of the free vertices' positions and velocities) against Richardson-
    extrapolated central differences of the computed step: the largest relative errors
    ``{name: error}`` and the :class:`StepJacobian`."""
    jac = E.step_jacobian(env, state, action)
    assert int(jac.result) == 0
    key = jax.random.PRNGKey(1)

    def next_state(a):
        return E.flatten_state(env.step_env(key, state, a)[1].sim)

    def reward(a):
        return env.step_env(key, state, a)[2]

    def from_state(s):
        moved = E.EnvState(sim=E.unflatten_state(s, state.sim), start=state.start, steps=state.steps,
                           inverted0=state.inverted0)
        return env.step_env(key, moved, action)

    errors = {"ds/da": 0.0, "dr/da": 0.0, "ds/ds": 0.0, "dr/ds": 0.0}
    for d in random_directions(action, {"a0": 1.0, "a1": 1.0}, seed=seed).values():
        fd = _richardson(next_state, action, d, eps_a)
        assert np.linalg.norm(fd) > 0  # the action moves the body
        errors["ds/da"] = max(errors["ds/da"], _rel(jac.ds_da @ d, fd))
        fdr = central_difference(reward, action, d, eps_a)
        errors["dr/da"] = max(errors["dr/da"], abs(float(jac.dr_da @ d) - fdr) / abs(fdr))
    s0 = E.flatten_state(state.sim)
    free = np.repeat(np.asarray(env.model.free_mask)[:, 0] > 0, 3)
    # positions in mm, velocities in 0.1 m/s: a direction of the size of a step's motion
    mask = np.concatenate([free * 1e-3, free * 1e-1])
    d = jnp.asarray(np.random.default_rng(seed).standard_normal(s0.size) * mask)
    d = d / jnp.linalg.norm(d)
    fd = _richardson(lambda s: E.flatten_state(from_state(s)[1].sim), s0, d, eps_s)
    errors["ds/ds"] = _rel(jac.ds_ds @ d, fd)
    fdr = central_difference(lambda s: from_state(s)[2], s0, d, eps_s)
    errors["dr/ds"] = abs(float(jac.dr_ds @ d) - fdr) / abs(fdr)
    return errors, jac


@pytest.mark.slow  # ~3 min on the 2-core machine: compiling the step and its forward-mode Jacobian
def test_pendulum_step_jacobians_match_central_differences(pendulum):
    """No contact: a skeleton in reduced coordinates, torque and servo channels."""
    model, params, env = pendulum
    _, state = env.reset(KEY)
    action = jnp.array([0.3, -0.4])
    _, state, _, _, _ = env.step_env(KEY, state, action)  # swinging: nonzero velocities
    errors, jac = _check_jacobians(env, state, action, eps_a=1e-3, eps_s=1e-4)
    print("pendulum Jacobian relative errors:", errors)
    assert jac.ds_da.shape == (6 * model.n_vertices, 2) and jac.ds_ds.shape == (6 * model.n_vertices,) * 2
    assert all(e <= 1e-5 for e in errors.values()), errors


@pytest.mark.slow  # ~3 min on the 2-core machine
def test_crawler_step_jacobians_match_central_differences_through_contact(crawler):
    """Contact with friction: some vertices touch the plane throughout, and no perturbation
    used by the differences changes the contact set (contact_changes says so)."""
    model, params, env = crawler
    _, state = env.reset(KEY)
    action = jnp.array([-0.6, 0.2])
    _, state, _, _, _ = env.step_env(KEY, state, action)
    new = env.step_env(KEY, state, action)[1]
    traj_x = jnp.stack([state.sim.x, new.sim.x])
    traj = Trajectory(x=traj_x, v=jnp.stack([state.sim.v, new.sim.v]), info=None)
    _, contact = contact_forces(model, params, traj, controls=env.action_map(action)[None], t0=state.sim.t)
    assert int(jnp.sum(contact > 0)) >= 2, contact  # on the ground (the reset noise tilts it a little)
    for d in ([1e-3, 0.0], [0.0, -1e-3]):
        assert int(E.contact_changes(env, state, action, jnp.asarray(d))) == 0
    # eps_s 3e-3 along a unit state direction (~3 um, 0.3 mm/s): smaller steps let the contact
    # iteration's stopping noise show (2.5e-6 at 1e-3, 1e-5 at 3e-4, 1.5e-4 at 1e-5)
    errors, jac = _check_jacobians(env, state, action, eps_a=1e-3, eps_s=3e-3)
    print("crawler Jacobian relative errors (contact):", errors)
    assert all(e <= 1e-5 for e in errors.values()), errors
    # Without contact, on the same program: the body lifted 5 mm, at rest, touches nothing in the step.
    lifted = state.sim.x + jnp.array([0.0, 0.0, 5e-3])
    air = E.EnvState(sim=State(x=lifted, v=jnp.zeros_like(lifted), rot=state.sim.rot, t=state.sim.t),
                     start=state.start, steps=state.steps, inverted0=state.inverted0)
    assert float(env.step_env(KEY, air, action)[1].sim.x[:, 2].min()) > 1e-3
    errors, _ = _check_jacobians(env, air, action, eps_a=1e-3, eps_s=3e-3)
    print("crawler Jacobian relative errors (no contact):", errors)
    assert all(e <= 1e-5 for e in errors.values()), errors


@pytest.mark.slow
def test_contact_changes_flags_a_perturbation_that_crosses_a_switch(crawler):
    """The flag sees a perturbation that crosses a switch: from full bottom contraction to
    full top contraction the contact set changes (vertices lift, land, stick or slide),
    where no perturbation changes nothing."""
    model, params, env = crawler
    _, state = env.reset(KEY)
    action = jnp.array([-1.0, 1.0])
    _, state, _, _, _ = env.step_env(KEY, state, action)
    assert int(E.contact_changes(env, state, action, jnp.array([0.0, 0.0]))) == 0
    assert int(E.contact_changes(env, state, action, jnp.array([2.0, -2.0]))) > 0


def test_episode_runs_ends_and_resets(crawler):
    """After episode_length steps done is set and the state is a fresh episode's (steps 0,
    time 0, the reset noise's start); rewards are finite and the steps converge."""
    model, params, env = crawler
    obs, state = env.reset(KEY)
    obs2, state2 = env.reset(jax.random.PRNGKey(7))
    assert float(jnp.abs(state2.sim.x - state.sim.x).max()) > 1e-6  # another key, another start
    assert float(jnp.abs(state.sim.x - model.mesh.points).max()) < 1e-3  # near the rest shape
    rewards, dones = [], []
    for k in range(env.episode_length):
        obs, state, reward, done, info = env.step(jax.random.PRNGKey(k), state, jnp.array([0.5, -0.5]))
        assert int(info["result"]) == 0
        rewards.append(float(reward))
        dones.append(bool(done))
    assert dones == [False] * (env.episode_length - 1) + [True]
    assert bool(info["truncated"])
    assert int(state.steps) == 0 and float(state.sim.t) == 0.0
    np.testing.assert_array_equal(np.asarray(state.sim.x), np.asarray(state.start.x))
    assert obs.shape == (env.observation_size,) and bool(jnp.all(jnp.isfinite(obs)))
    assert all(np.isfinite(rewards)) and len(set(rewards)) > 1


@pytest.mark.slow  # ~3 min: compiling the skeleton's reset and step
def test_pendulum_reset_noise_moves_joints_and_keeps_bones_rigid(pendulum):
    """Joint noise poses the bones by forward kinematics: the observed joint angles are the
    skeleton's coordinates, nonzero, and each bone keeps its shape."""
    model, params, env = pendulum
    rig = model.rig
    obs, state = env.reset(KEY)
    z = rig.coordinates(state.sim.x[jnp.asarray(rig.bone)])
    np.testing.assert_allclose(np.asarray(obs[:2]), np.asarray(z[:2]), atol=1e-12)
    assert float(jnp.abs(obs[:2]).max()) > 1e-3
    x, x0 = np.asarray(state.sim.x)[rig.bone], np.asarray(model.mesh.points)[rig.bone]
    for link in range(2):
        b = rig.vertex_link == link
        dist = np.linalg.norm(x[b][:, None] - x[b][None], axis=-1)
        dist0 = np.linalg.norm(x0[b][:, None] - x0[b][None], axis=-1)
        assert np.abs(dist - dist0).max() < 1e-12
    obs, state, reward, done, info = env.step(KEY, state, jnp.array([1.0, -1.0]))
    assert int(info["result"]) == 0 and float(jnp.abs(obs[2:]).max()) > 0  # swinging: nonzero rates


def test_batched_step_equals_single_steps(crawler):
    """batch_step (one jit(vmap)) gives each environment what its own step gives (to the
    solver's tolerance: a batched while loop may run a member past its own convergence)."""
    model, params, env = crawler
    keys = jax.random.split(KEY, 3)
    obs, states = env.batch_reset(keys)
    assert obs.shape == (3, env.observation_size)
    actions = jnp.array([[-1.0, 1.0], [0.0, 0.0], [0.5, -0.25]])
    out = env.batch_step(keys, states, actions)
    for i in range(3):
        state_i = jax.tree.map(lambda a, i=i: a[i], states)
        single = env.step(keys[i], state_i, actions[i])
        np.testing.assert_allclose(np.asarray(out[0][i]), np.asarray(single[0]), rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(float(out[2][i]), float(single[2]), rtol=1e-6, atol=1e-12)
    assert len({float(r) for r in out[2]}) == 3


def test_nonfinite_action_under_jit_ends_the_episode_without_simulating(crawler):
    """Traced, a NaN action cannot be refused: the step holds the state, reports
    RESULTS.nonfinite with reward 0 and done, and the auto-reset starts a new episode."""
    model, params, env = crawler
    _, state = env.reset(KEY)
    _, state, _, _, _ = env.step(KEY, state, jnp.array([0.2, 0.2]))
    obs, new, reward, done, info = env._step_jit(KEY, state, jnp.array([jnp.nan, 0.0]), params)  # as under jit
    assert int(info["result"]) == int(RESULTS.nonfinite) and bool(done) and float(reward) == 0.0
    assert not bool(info["truncated"])
    assert int(new.steps) == 0 and bool(jnp.all(jnp.isfinite(obs)))


# ----------------------------------------------------------------------------- bad input


@pytest.fixture
def nothing_compiles(monkeypatch):
    """A context in which compiling anything, or reaching the environment's simulated
    step, fails the test: bad input must be refused first."""
    compiled = []

    def listener(name, duration, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            compiled.append(name)

    def forbidden(*args, **kwargs):
        raise AssertionError("reached the simulated step: the input was not checked first")

    jax.monitoring.register_event_duration_secs_listener(listener)

    @contextlib.contextmanager
    def window():
        with monkeypatch.context() as m:
            m.setattr(E, "_transition", forbidden)
            compiled.clear()
            yield
            assert not compiled, "something was compiled before the input was refused"

    try:
        yield window
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def test_bad_actions_are_refused_before_compiling(crawler, nothing_compiles):
    model, params, env = crawler
    fresh = E.Env(model, params, observation=env.observation, reward=env.reward, episode_length=4)
    _, state = env.reset(KEY)
    wrong, nan = np.zeros(3), np.array([0.1, np.nan])
    batch_states = jax.tree.map(lambda a: jnp.stack([a, a]), state)
    keys = jax.random.split(KEY, 2)
    with nothing_compiles():
        with pytest.raises(ControlError, match=r"action has shape \(3,\) but this environment takes \(2,\)"):
            fresh.step(KEY, state, wrong)
        with pytest.raises(ControlError, match=r"for a batch use env.batch_step"):
            fresh.step(KEY, state, np.zeros((5, 2)))
        with pytest.raises(ControlError, match=r"action holds NaN or inf \(entries \[1\]\)"):
            fresh.step(KEY, state, nan)
        with pytest.raises(ControlError, match=r"action holds NaN or inf"):
            E.step_jacobian(fresh, state, nan)
        with pytest.raises(ControlError, match=r"action has shape \(3,\)"):
            E.contact_changes(fresh, state, np.zeros(2), wrong)
        with pytest.raises(ControlError, match=r"actions have shape \(3, 2\) but this batch needs \(2, 2\)"):
            fresh.batch_step(keys, batch_states, np.zeros((3, 2)))
        with pytest.raises(ControlError, match=r"actions hold NaN or inf \(first in row 1\)"):
            fresh.batch_step(keys, batch_states, np.array([[0.0, 0.0], [np.inf, 0.0]]))
        with pytest.raises(ControlError, match=r"a batch of states goes through env.batch_step"):
            fresh.step(KEY, batch_states, np.zeros(2))


def test_bad_rewards_observations_and_action_maps_are_refused_when_made(pendulum, crawler, nothing_compiles):
    model, params, env = crawler
    pmodel = pendulum[0]
    with nothing_compiles():
        with pytest.raises(ControlError, match=r"the reward must return a real scalar \(shape \(\)\), got shape \(16,\)"):
            E.Env(model, params, observation=env.observation, reward=lambda tr: tr.next_state.x[:, 2])
        with pytest.raises(ControlError, match=r"the reward failed on a transition"):
            E.Env(model, params, observation=env.observation, reward=lambda tr: tr.velocity)
        with pytest.raises(ControlError, match=r"the observation must return a real vector of its size \(7,\)"):
            class Wrong:
                size = 7

                def __call__(self, state, start):
                    return state.x[0]

            E.Env(model, params, observation=Wrong(), reward=env.reward)
        with pytest.raises(ControlError, match=r"episode_length must be a whole number of steps >= 1"):
            E.Env(model, params, observation=env.observation, reward=env.reward, episode_length=0)
        with pytest.raises(ControlError, match=r"channel 'torque:upper' has the range \[-inf, inf\].*low=..., high="):
            E.ActionMap(pmodel)
        with pytest.raises(ControlError, match=r"leaves the channel's bounds"):
            E.ActionMap(pmodel, low=[-1.0, -4.0], high=[1.0, 0.5])
        with pytest.raises(ControlError, match=r"unknown channel\(s\) \['middle'\]"):
            E.ActionMap(model, ["middle"])
        with pytest.raises(ControlError, match=r"JointAngles needs a scene with a skeleton"):
            E.JointAngles(model)


def test_rewards_combine_and_action_map_is_affine(crawler):
    model, params, env = crawler
    amap = E.ActionMap(model, ["bottom"], low=0.1, high=0.3, rest=0.05)
    np.testing.assert_allclose(np.asarray(amap(jnp.array([-1.0]))), [0.05, 0.1])
    np.testing.assert_allclose(np.asarray(amap(jnp.array([0.0]))), [0.05, 0.2])
    np.testing.assert_allclose(np.asarray(amap(jnp.array([7.0]))), [0.05, 0.3])  # clipped
    rest = initial_state(model, params)  # the block's centroid is 10 mm up
    moved = State(x=rest.x + jnp.array([0.002, 0.0, 0.001]), v=rest.v, rot=rest.rot, t=rest.t)
    tr = E.Transition(state=rest, action=jnp.array([0.5, -1.0]), activation=jnp.zeros(2), next_state=moved,
                      start=rest)
    progress, height, effort = E.Progress(model), E.Height(model, reference=0.01), E.ActionPenalty(scale=0.5)
    assert float(progress(tr)) == pytest.approx(0.002)
    assert float(height(tr)) == pytest.approx(0.011 - 0.01)
    assert float(effort(tr)) == pytest.approx(-(1.0 + 4.0))
    combined = 2 * progress + height - 0.1 * effort
    assert float(combined(tr)) == pytest.approx(0.004 + 0.001 + 0.5)

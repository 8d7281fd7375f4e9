"""Reinforcement learning with simulation gradients (softbody.control.rl): sample
enhancement's virtual samples against the real step (first order), policy enhancement's
action gradient against reverse-mode differentiation through the real step, SAC learning
the one-link pendulum, rejax's PPO through the gymnax adapter, and bad input refused.

The scene is the benchmark's pendulum (softbody.bench.rl_pendulum.pendulum_env): a chain
of rigid cubes joined by soft ones, hanging under gravity, joint torques; float64,
tolerance 1e-10 where derivatives are compared.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from softbody.control import ControlError, rl
from softbody.control import env as E

from softbody import simulate
from softbody.bench.rl_pendulum import pendulum_env
from softbody.model import prepare

KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def two_links():
    """The two-link pendulum (tight tolerance) and a moving state with an action inside [-1, 1]."""
    env = pendulum_env(2, tol=1e-10)
    _, state = env.reset(KEY)
    for i in range(5):
        _, state, *_ = env.step_env(jax.random.PRNGKey(i), state, jnp.array([0.8, -0.6]))
    return env, state, jnp.array([0.3, -0.2])


@pytest.mark.slow
def test_virtual_samples_match_the_real_step_to_first_order(two_links):
    env, state, action = two_links
    jac = E.step_jacobian(env, state, action, wrt_state=False)
    obs0, _, r0, _, _ = env.step_env(KEY, state, action)
    direction = jnp.array([0.6, 0.8])
    errors, changes = [], []
    for h in (0.1, 0.05, 0.025):
        a_k, obs_k, r_k, valid = rl.virtual_samples(env, state, action, (h * direction)[None], jac)
        assert bool(valid[0]) and np.allclose(a_k[0], action + h * direction)
        obs, _, r, _, _ = env.step_env(KEY, state, action + h * direction)
        errors.append(float(jnp.linalg.norm(obs_k[0] - obs) + abs(r_k[0] - r)))
        changes.append(float(jnp.linalg.norm(obs - obs0) + abs(r - r0)))
    # Second-order error: halving the offset quarters it, and it is far below the change itself.
    assert 3.0 < errors[0] / errors[1] < 5.0 and 3.0 < errors[1] / errors[2] < 5.0, errors
    assert errors[0] < 0.05 * changes[0], (errors, changes)


@pytest.mark.slow
def test_policy_enhanced_action_gradient_is_the_gradient_through_the_real_step(two_links):
    env, state, action = two_links
    model, params = env.model, env.params
    o, m, gamma = env.observation_size, env.action_size, 0.9
    actor = rl.Actor(o, m, (16, 16), jax.random.PRNGKey(1))
    critic = rl.Critic(o, m, (16, 16), jax.random.PRNGKey(2))
    jac = E.step_jacobian(env, state, action, wrt_state=False)
    next_obs = env.observation(E.unflatten_state(jac.next_state, state.sim), state.start)
    batch = {"action": action[None], "reward": jac.reward[None], "next_obs": next_obs[None], "terminal": jnp.zeros(1),
                 "dobs_da": rl._next_obs_jacobian(env, state, jac)[None], "dr_da": jac.dr_da[None]}
    model_grad = rl.model_action_gradient(actor, critic, gamma, batch)[0]

    def q(a):  # r(s, a) + gamma Q(s'(s, a), mu(s')) through the simulation step, reverse mode
        activation = env.action_map(a)
        new, _ = simulate.step(model, prepare(model, params), state.sim, activation)
        r = env.reward(E.Transition(state=state.sim, action=a, activation=activation, next_state=new,
                                    start=state.start))
        o2 = env.observation(new, state.start)
        return r + gamma * critic.min(o2, actor.deterministic(o2))

    reference = jax.grad(q)(action)
    assert float(jnp.linalg.norm(reference)) > 1e-3
    np.testing.assert_allclose(model_grad, reference, rtol=1e-6, atol=1e-9)


@pytest.mark.slow
def test_sac_learns_the_one_link_pendulum_above_a_random_policy():
    env = pendulum_env(1)
    agent = rl.SAC(env, rl.SACConfig(warmup=200))
    state = agent.init(0)
    state, _ = agent.train(state, 1500)
    learned = float(jnp.mean(agent.evaluate(state, jax.random.PRNGKey(7), episodes=4)))
    rng = np.random.default_rng(0)
    random_returns = []
    for e in range(4):
        _, st = env.reset(jax.random.PRNGKey(100 + e))
        total = 0.0
        for i in range(env.episode_length):
            _, st, r, _, _ = env.step_env(KEY, st, jnp.asarray(rng.uniform(-1, 1, env.action_size)))
            total += float(r)
        random_returns.append(total)
    assert learned > max(random_returns) + 10.0, (learned, random_returns)


@pytest.mark.slow
def test_sac_runs_are_reproducible_and_pure():
    env = pendulum_env(1, episode_length=20)
    agent = rl.SAC(env, rl.SACConfig(warmup=10, batch_size=8, buffer_size=64, hidden=(8,)))
    a, ra = agent.train(agent.init(3), 30)
    b, rb = agent.train(agent.init(3), 30)
    c, _ = agent.train(agent.init(4), 30)
    np.testing.assert_array_equal(ra[0], rb[0])
    leaves = lambda s: jax.tree.leaves(s.actor)
    assert all(np.array_equal(x, y) for x, y in zip(leaves(a), leaves(b)))
    assert not all(np.array_equal(x, y) for x, y in zip(leaves(a), leaves(c)))
    assert int(a.samples) == 30 and int(a.buffer.size) == 30 and int(a.virtual) == 0


@pytest.mark.parametrize("field, value, words", [
    ("gamma", 1.0, "gamma must be in [0, 1)"),
    ("learning_rate", -1e-3, "learning_rate must be > 0"),
    ("batch_size", 0, "batch_size must be a whole number >= 1"),
    ("virtual_samples", 2.5, "virtual_samples must be a whole number"),
    ("tau", float("nan"), "tau must be in (0, 1]"),
    ("hidden", (), "hidden must be a non-empty tuple"),
    ("buffer_size", 4, "must hold at least one batch"),
    ("policy_enhancement", "yes", "policy_enhancement must be True or False"),
])
def test_bad_hyperparameters_are_refused(field, value, words):
    with pytest.raises(ControlError, match=words.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        rl.SACConfig(**{field: value})


def test_bad_input_is_refused_before_compiling(monkeypatch):
    env = pendulum_env(2)
    # Nothing may be simulated or compiled on the way to these errors.
    monkeypatch.setattr(E, "_transition", lambda *a: pytest.fail("simulated"))
    monkeypatch.setattr(E, "_jacobian_fn", lambda *a: pytest.fail("compiled"))
    with pytest.raises(ControlError, match="env must be a softbody.control.env.Env"):
        rl.SAC("pendulum")
    with pytest.raises(ControlError, match="config must be a SACConfig"):
        rl.SAC(env, {"gamma": 0.9})
    agent = rl.SAC(env, rl.SACConfig(num_envs=2))
    with pytest.raises(ControlError, match=r"steps \(3\) must be a multiple of num_envs \(2\)"):
        agent._iterations(3)
    with pytest.raises(ControlError, match="state must be the SACState"):
        agent.train({"actor": None}, 2)
    with pytest.raises(ControlError, match=r"obs has shape \(3,\); this agent takes \(4,\)"):
        agent.act(None, jnp.zeros(3))
    _, state = env.reset(KEY)
    with pytest.raises(ControlError, match=r"action has shape \(3,\) but this environment takes \(2,\)"):
        E.step_jacobian(env, state, jnp.zeros(3))
    with pytest.raises(ControlError, match=r"d_actions has shape \(2,\); give \(k, 2\)"):
        rl.virtual_samples(env, state, jnp.zeros(2), jnp.zeros(2), None)
    batch = {"action": jnp.zeros((3, 2)), "reward": jnp.zeros(3), "next_obs": jnp.zeros((3, 4)), "terminal": jnp.zeros(3),
                 "dobs_da": jnp.zeros((3, 4, 3)), "dr_da": jnp.zeros((3, 2))}
    with pytest.raises(ControlError, match="batch shapes disagree"):
        rl.model_action_gradient(None, None, 0.9, batch)
    with pytest.raises(ControlError, match=r"batch lacks \['dobs_da', 'dr_da'\]"):
        rl.model_action_gradient(None, None, 0.9, {**batch, "dobs_da": None, "dr_da": None})
    with pytest.raises(ControlError, match="eval_every"):
        rl.ppo(env, 1000, eval_every=150)


def test_a_non_scalar_reward_is_refused_when_the_environment_is_made():
    env = pendulum_env(1)
    with pytest.raises(ControlError, match="the reward must return a real scalar"):
        E.Env(env.model, env.params, observation=env.observation, reward=lambda t: t.next_state.x[:, 0],
              action_map=env.action_map)


def test_ppo_without_rejax_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "rejax", None)
    with pytest.raises(ImportError, match=r"pip install softbody\[rl\]"):
        rl.ppo(pendulum_env(1), 1000, eval_every=100)


@pytest.mark.slow
def test_ppo_from_rejax_trains_and_is_evaluated_each_epoch():
    pytest.importorskip("rejax")
    env = pendulum_env(1)
    _, train = rl.ppo(env, 300, eval_every=100, num_envs=4, num_steps=25)
    _, returns = jax.jit(train)(KEY)
    assert returns.shape == (4, 1)
    assert np.all(np.isfinite(np.asarray(returns))) and np.all(np.asarray(returns) >= -100.0)

"""Reinforcement learning with simulation gradients: one soft actor-critic agent (SAC,
equinox + optax) whose options use the environment's exact one-step Jacobians
(:func:`softbody.control.env.step_jacobian`), after Qiao et al., ICML 2021
("Efficient Differentiable Simulation of Articulated Bodies"), and a PPO baseline from a
maintained library (rejax).

* **Sample enhancement** (``SACConfig(virtual_samples=K)``): every real transition
  ``(s, a, r, s')`` also stores ``K`` nearby virtual ones, ``a_k = clip(a + da_k)``,
  ``s'_k = s' + ds'/da da_k``, ``r_k = r + dr/da . da_k`` (``da_k`` Gaussian of standard
  deviation ``virtual_scale``; the observation of ``s'_k`` is computed from the
  linearised state). In a scene with contact a virtual sample whose ``a_k`` changes the
  contact set (:func:`softbody.control.env.contact_changes`) is discarded: not stored.
* **Policy enhancement** (``SACConfig(policy_enhancement=True)``): the actor's action
  gradient is taken through a one-step model of the simulation instead of the critic,
  ``dQ/da = dr/da + gamma dQ(s', mu(s'))/ds' ds'/da`` (``mu`` the actor's deterministic
  action, ``Q`` the smaller of the two critics); the model is the stored transition
  linearised in the action, so the actor loss is
  ``alpha log pi(a~|o) - [r + dr/da (a~ - a) + gamma (1 - terminal) Q(o'(a~), mu(o'(a~)))]``
  with ``o'(a~) = o' + do'/da (a~ - a)``; its action gradient at ``a~ = a`` is the formula
  above (:func:`model_action_gradient`).

Both need one forward-mode Jacobian per real sample (``m`` tangent solves of the step's
Hessian, ``m`` the action size) on top of the step itself.

The agent is pure: :meth:`SAC.init` makes a :class:`SACState` (networks, optimiser
states, replay buffer, the environments' states, the PRNG key) from a seed, and
:meth:`SAC.train` advances it by a number of environment steps in one compiled
``lax.scan`` (collect a step of ``num_envs`` environments, store it, take gradient
steps), so that seeds batch by ``jax.vmap`` (:meth:`SAC.train_seeds`). The same seed gives
the same run.

PPO is rejax's (``pip install softbody[rl]``; :func:`ppo`), on the environment through
:class:`GymnaxEnv`, gymnax's interface as rejax 0.1.3 calls it.

Bad input is refused with a :class:`~softbody.control.ControlError` before anything is
compiled: hyperparameters out of range, an environment that is not an
:class:`~softbody.control.env.Env`; batches of :func:`model_action_gradient` and
:func:`virtual_samples` of the wrong shapes.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from . import env as E
from .errors import ControlError

Array = jax.Array

__all__ = [
    "SAC",
    "Actor",
    "Buffer",
    "Critic",
    "GymnaxEnv",
    "SACConfig",
    "SACState",
    "evaluate_policy",
    "model_action_gradient",
    "ppo",
    "ppo_policy",
    "virtual_samples",
]

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


# --------------------------------------------------------------------------- configuration


def _whole(v, name: str, low: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
        raise ControlError(f"{name} must be a whole number >= {low}, got {v!r}")
    return int(v)


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """Hyperparameters of :class:`SAC` (checked when made).

    Attributes:
        hidden: widths of the hidden layers of the actor and of each critic (tanh).
        learning_rate: Adam's step for the actor, the critics and the temperature, > 0.
        gamma: discount in [0, 1).
        tau: target-critic averaging in (0, 1].
        batch_size: transitions per gradient step, >= 1.
        buffer_size: replay capacity (real and virtual transitions), >= batch_size.
        warmup: environment steps (per environment) of uniform random actions before the
            policy acts and the gradient steps start, >= 0.
        updates_per_step: gradient steps per environment step of each environment, >= 1.
        init_alpha: the entropy temperature's start, > 0 (learned towards
            ``target_entropy``, default ``-action_size``).
        target_entropy: the temperature's target; ``None`` for ``-action_size``.
        num_envs: environments stepped together (one ``vmap``), >= 1.
        virtual_samples: sample enhancement: virtual transitions per real one, >= 0 (0: off).
        virtual_scale: standard deviation of the virtual action offsets ``da``, > 0.
        policy_enhancement: the actor's action gradient through the one-step model.
    """

    hidden: tuple = (64, 64)
    learning_rate: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.01
    batch_size: int = 128
    buffer_size: int = 100_000
    warmup: int = 200
    updates_per_step: int = 1
    init_alpha: float = 0.1
    target_entropy: float | None = None
    num_envs: int = 1
    virtual_samples: int = 0
    virtual_scale: float = 0.1
    policy_enhancement: bool = False

    def __post_init__(self):
        def whole(name, low):
            _whole(getattr(self, name), f"SACConfig.{name}", low)

        def real(name, ok, what):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) \
                    or not math.isfinite(v) or not ok(v):
                raise ControlError(f"SACConfig.{name} must be {what}, got {v!r}")

        hidden = self.hidden
        if not isinstance(hidden, (tuple, list)) or not hidden or \
                not all(isinstance(h, (int, np.integer)) and not isinstance(h, bool) and h >= 1 for h in hidden):
            raise ControlError(f"SACConfig.hidden must be a non-empty tuple of layer widths >= 1, got {hidden!r}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in hidden))
        real("learning_rate", lambda v: v > 0, "> 0")
        real("gamma", lambda v: 0 <= v < 1, "in [0, 1)")
        real("tau", lambda v: 0 < v <= 1, "in (0, 1]")
        real("init_alpha", lambda v: v > 0, "> 0")
        real("virtual_scale", lambda v: v > 0, "> 0")
        if self.target_entropy is not None:
            real("target_entropy", lambda v: True, "a finite number or None")
        whole("batch_size", 1)
        whole("buffer_size", 1)
        whole("warmup", 0)
        whole("updates_per_step", 1)
        whole("num_envs", 1)
        whole("virtual_samples", 0)
        if self.buffer_size < self.batch_size:
            raise ControlError(f"SACConfig.buffer_size ({self.buffer_size}) must hold at least one batch "
                               f"(batch_size {self.batch_size})")
        if not isinstance(self.policy_enhancement, bool):
            raise ControlError(f"SACConfig.policy_enhancement must be True or False, got {self.policy_enhancement!r}")

    @property
    def uses_jacobian(self) -> bool:
        """Whether the agent needs the one-step Jacobians (either enhancement)."""
        return self.virtual_samples > 0 or self.policy_enhancement


# --------------------------------------------------------------------------- networks


class Actor(eqx.Module):
    """A tanh-squashed Gaussian policy: an MLP maps the observation ``(obs,)`` to the mean
    and log standard deviation ``(m,)`` each of the pre-squash Gaussian."""

    mlp: eqx.nn.MLP

    def __init__(self, obs_size: int, action_size: int, hidden: tuple, key):
        self.mlp = eqx.nn.MLP(obs_size, 2 * action_size, hidden[0], len(hidden), activation=jnp.tanh, key=key)

    def distribution(self, obs: Array) -> tuple[Array, Array]:
        """``(mean (m,), log_std (m,))`` of the pre-squash Gaussian."""
        out = self.mlp(obs)
        mean, log_std = jnp.split(out, 2)
        return mean, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)

    def deterministic(self, obs: Array) -> Array:
        """The action ``tanh(mean)`` ``(m,)``."""
        return jnp.tanh(self.distribution(obs)[0])

    def sample(self, obs: Array, key) -> tuple[Array, Array]:
        """A squashed sample ``(m,)`` and its log density (a scalar)."""
        mean, log_std = self.distribution(obs)
        eps = jax.random.normal(key, mean.shape, mean.dtype)
        u = mean + jnp.exp(log_std) * eps
        a = jnp.tanh(u)
        logp = jnp.sum(-0.5 * eps ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi))
        logp = logp - jnp.sum(2 * (jnp.log(2.0) - u - jax.nn.softplus(-2 * u)))
        return a, logp


class Critic(eqx.Module):
    """Two Q networks ``Q_i(obs, action)`` (clipped double Q)."""

    q1: eqx.nn.MLP
    q2: eqx.nn.MLP

    def __init__(self, obs_size: int, action_size: int, hidden: tuple, key):
        k1, k2 = jax.random.split(key)
        self.q1 = eqx.nn.MLP(obs_size + action_size, "scalar", hidden[0], len(hidden), activation=jnp.tanh, key=k1)
        self.q2 = eqx.nn.MLP(obs_size + action_size, "scalar", hidden[0], len(hidden), activation=jnp.tanh, key=k2)

    def __call__(self, obs: Array, action: Array) -> tuple[Array, Array]:
        x = jnp.concatenate([obs, action])
        return self.q1(x), self.q2(x)

    def min(self, obs: Array, action: Array) -> Array:
        return jnp.minimum(*self(obs, action))


# --------------------------------------------------------------------------- replay buffer


class Buffer(eqx.Module):
    """A circular replay buffer of fixed capacity ``c`` (all arrays preallocated).

    Attributes:
        obs, next_obs: ``(c, obs)``; action: ``(c, m)``; reward, terminal: ``(c,)``;
        dobs_da: ``(c, obs, m)`` the next observation's action Jacobian ``do'/da``;
        dr_da: ``(c, m)`` (both zero unless the agent uses the Jacobians);
        size: transitions stored (<= c); position: the next slot to write.
    """

    obs: Array
    action: Array
    reward: Array
    next_obs: Array
    terminal: Array
    dobs_da: Array
    dr_da: Array
    size: Array
    position: Array

    @staticmethod
    def empty(capacity: int, obs_size: int, action_size: int, jacobians: bool) -> Buffer:
        c, o, m = capacity, obs_size, action_size
        cj = c if jacobians else 1
        z = lambda *s: jnp.zeros(s, jnp.float64)
        return Buffer(obs=z(c, o), action=z(c, m), reward=z(c), next_obs=z(c, o), terminal=z(c),
                      dobs_da=z(cj, o, m), dr_da=z(cj, m), size=jnp.zeros((), jnp.int32),
                      position=jnp.zeros((), jnp.int32))

    @property
    def capacity(self) -> int:
        return self.obs.shape[0]

    def add(self, obs, action, reward, next_obs, terminal, dobs_da, dr_da, valid) -> Buffer:
        """Store ``k`` transitions (leading axis ``k`` on each argument); rows with
        ``valid`` false are skipped (the kept ones are written contiguously)."""
        k = obs.shape[0]
        c = self.capacity
        order = jnp.argsort(~valid, stable=True)  # kept rows first
        count = jnp.sum(valid).astype(jnp.int32)
        slots = (self.position + jnp.arange(k)) % c
        # Rows beyond ``count`` are written to a slot past the end (dropped).
        slots = jnp.where(jnp.arange(k) < count, slots, c)

        def put(store, rows):
            return store.at[slots].set(rows[order], mode="drop")

        jac = self.dobs_da.shape[0] == c
        return Buffer(obs=put(self.obs, obs), action=put(self.action, action), reward=put(self.reward, reward),
                      next_obs=put(self.next_obs, next_obs), terminal=put(self.terminal, terminal),
                      dobs_da=put(self.dobs_da, dobs_da) if jac else self.dobs_da,
                      dr_da=put(self.dr_da, dr_da) if jac else self.dr_da,
                      size=jnp.minimum(self.size + count, c), position=(self.position + count) % c)

    def sample(self, key, batch: int):
        """``batch`` transitions drawn uniformly from those stored (with replacement)."""
        i = jax.random.randint(key, (batch,), 0, jnp.maximum(self.size, 1))
        jac = self.dobs_da.shape[0] == self.capacity
        return {"obs": self.obs[i], "action": self.action[i], "reward": self.reward[i], "next_obs": self.next_obs[i],
                    "terminal": self.terminal[i], "dobs_da": self.dobs_da[i] if jac else None,
                    "dr_da": self.dr_da[i] if jac else None}


# --------------------------------------------------------------------------- the state


class SACState(eqx.Module):
    """Everything a :class:`SAC` run carries (a pytree; batched by ``vmap`` over seeds).

    Attributes:
        actor, critic, target: the networks (``target`` the critics' running average).
        log_alpha: the entropy temperature's log.
        actor_opt, critic_opt, alpha_opt: optax states.
        buffer: the :class:`Buffer`.
        env_state: the ``num_envs`` environments' :class:`~softbody.control.env.EnvState`
            (leading axis ``num_envs``); obs: ``(num_envs, obs)``.
        episode_return: ``(num_envs,)`` the running episodes' returns so far;
        last_return: ``(num_envs,)`` each environment's last finished episode's return (NaN before one).
        steps: environment steps taken per environment; samples: real transitions
            collected (all environments); virtual: virtual transitions stored.
        key: the PRNG key.
    """

    actor: Actor
    critic: Critic
    target: Critic
    log_alpha: Array
    actor_opt: Any
    critic_opt: Any
    alpha_opt: Any
    buffer: Buffer
    env_state: Any
    obs: Array
    episode_return: Array
    last_return: Array
    steps: Array
    samples: Array
    virtual: Array
    key: Array


# --------------------------------------------------------------------------- one-step model


def _obs_of_flat(env: E.Env, s: Array, like, start) -> Array:
    return env.observation(E.unflatten_state(s, like), start)


def virtual_samples(env: E.Env, state: E.EnvState, action: Array, d_actions: Array, jac: E.StepJacobian,
                    params=None, check_contact: bool | None = None):
    """Sample enhancement's virtual transitions around one real step.

    ``a_k = clip(a + da_k, -1, 1)``, ``s'_k = s' + ds'/da (a_k - a)``,
    ``r_k = r + dr/da . (a_k - a)``, ``o'_k = obs(s'_k)``.

    Arguments:
        env: the :class:`~softbody.control.env.Env`.
        state: the step's start :class:`~softbody.control.env.EnvState` (unbatched).
        action: ``(m,)`` the real action.
        d_actions: ``(k, m)`` the offsets.
        jac: the step's :class:`~softbody.control.env.StepJacobian` (from
            :func:`~softbody.control.env.step_jacobian` at ``(state, action)``).
        params: the scene's parameters, or ``None`` for ``env.params``.
        check_contact: simulate each ``a_k`` to find contact switches
            (:func:`~softbody.control.env.contact_changes`); default: where the scene has
            contact.

    Returns:
        ``(actions (k, m), next_obs (k, obs), rewards (k,), valid (k,) bool)``: ``valid``
        false where ``a_k`` changes the contact set (discard those).

    Raises:
        ControlError: ``d_actions`` not of shape ``(k, m)``.
    """
    m = env.action_size
    if jnp.ndim(d_actions) != 2 or jnp.shape(d_actions)[1] != m:
        raise ControlError(f"d_actions has shape {tuple(jnp.shape(d_actions))}; give (k, {m}): k offsets of the "
                           f"{m}-entry action")
    params = env._params(params)
    check = env.model.has_contact if check_contact is None else bool(check_contact)
    return _virtual(env, params, state, action, d_actions, jac, check)


def _virtual(env, params, state, action, d_actions, jac, check):
    a_k = jnp.clip(action + d_actions, -1.0, 1.0)
    da = a_k - action
    s_k = jac.next_state + da @ jac.ds_da.T
    r_k = jac.reward + da @ jac.dr_da
    like = E.unflatten_state(jac.next_state, state.sim)
    obs_k = jax.vmap(lambda s: _obs_of_flat(env, s, like, state.start))(s_k)
    if check:
        changes = jax.vmap(lambda d: E._contact_fn(env)(params, state, action, d))(da)
        valid = changes == 0
    else:
        valid = jnp.ones(a_k.shape[0], bool)
    return a_k, obs_k, r_k, valid


def _next_obs_jacobian(env: E.Env, state: E.EnvState, jac: E.StepJacobian) -> Array:
    """``do'/da`` ``(obs, m)``: the next observation's derivative along each action entry."""
    like = E.unflatten_state(jac.next_state, state.sim)
    f = lambda s: _obs_of_flat(env, s, like, state.start)
    return jax.vmap(lambda col: jax.jvp(f, (jac.next_state,), (col,))[1], in_axes=1, out_axes=1)(jac.ds_da)


def _model_q(actor: Actor, critic: Critic, gamma, a_pi, t) -> Array:
    """The one-step model's Q of action ``a_pi`` for one stored transition ``t``."""
    da = a_pi - t["action"]
    o_next = t["next_obs"] + t["dobs_da"] @ da
    r = t["reward"] + t["dr_da"] @ da
    v = critic.min(o_next, actor.deterministic(o_next))
    return r + gamma * (1.0 - t["terminal"]) * v


def model_action_gradient(actor: Actor, critic: Critic, gamma: float, batch: dict) -> Array:
    """Policy enhancement's action gradient ``dQ/da = dr/da + gamma dQ(s', mu(s'))/ds' ds'/da``
    of each stored transition, at its own action.

    Arguments:
        actor, critic: the networks (``mu`` = ``actor.deterministic``, ``Q`` = ``critic.min``).
        gamma: the discount.
        batch: a dict of ``b`` transitions as :meth:`Buffer.sample` returns them (``action``
            ``(b, m)``, ``reward`` ``(b,)``, ``next_obs`` ``(b, obs)``, ``terminal`` ``(b,)``,
            ``dobs_da`` ``(b, obs, m)``, ``dr_da`` ``(b, m)``).

    Returns:
        ``(b, m)``.

    Raises:
        ControlError: a missing entry or inconsistent shapes.
    """
    need = ("action", "reward", "next_obs", "terminal", "dobs_da", "dr_da")
    missing = [k for k in need if batch.get(k) is None]
    if missing:
        raise ControlError(f"batch lacks {missing}: model_action_gradient needs the Jacobians (an agent with "
                           "policy_enhancement or virtual_samples stores them)")
    b, m = jnp.shape(batch["action"])
    o = jnp.shape(batch["next_obs"])[1]
    if jnp.shape(batch["dobs_da"]) != (b, o, m) or jnp.shape(batch["dr_da"]) != (b, m) \
            or jnp.shape(batch["reward"]) != (b,):
        raise ControlError(f"batch shapes disagree: action (b, m) = {(b, m)}, next_obs (b, obs) = {(b, o)}; need "
                           f"dobs_da {(b, o, m)}, dr_da {(b, m)}, reward {(b,)}")
    t = {k: batch[k] for k in need}
    return jax.vmap(jax.grad(lambda a, t: _model_q(actor, critic, gamma, a, t)))(batch["action"], t)


# --------------------------------------------------------------------------- the agent


def _polyak(target, online, tau):
    return jax.tree.map(lambda t, o: (1 - tau) * t + tau * o if eqx.is_inexact_array(t) else t, target, online)


@dataclasses.dataclass(frozen=True, eq=False)
class SAC:
    """Soft actor-critic on a softbody :class:`~softbody.control.env.Env`, with the
    simulation-gradient options of the module docstring.

    Arguments:
        env: the environment (actions in ``[-1, 1]``, ``(m,)``; observations ``(obs,)``).
        config: a :class:`SACConfig`.

    Raises:
        ControlError: ``env`` not an ``Env`` or ``config`` not a ``SACConfig`` (the
            config's own values are checked when it is made).

    Example::

        agent = SAC(env, SACConfig(virtual_samples=4))
        state = agent.init(0)                       # a seed or a PRNG key
        state, returns = agent.train(state, 1000)   # 1000 steps of each environment
        print(agent.evaluate(state, jax.random.PRNGKey(1)))
    """

    env: E.Env
    config: SACConfig = SACConfig()

    def __post_init__(self):
        if not isinstance(self.env, E.Env):
            raise ControlError(f"env must be a softbody.control.env.Env, got {type(self.env).__name__}")
        if not isinstance(self.config, SACConfig):
            raise ControlError(f"config must be a SACConfig, got {type(self.config).__name__}")

    # -- construction

    def init(self, seed) -> SACState:
        """A fresh run.

        Arguments:
            seed: an int or a ``jax.random`` key.

        Returns:
            The :class:`SACState` (environments reset, buffer empty).
        """
        key = jax.random.PRNGKey(seed) if isinstance(seed, (int, np.integer)) else seed
        return self._init_jit(key)

    @functools.cached_property
    def _init_jit(self):
        return eqx.filter_jit(self._init)

    def _optimizer(self):
        return optax.adam(self.config.learning_rate)

    def _init(self, key) -> SACState:
        cfg, env = self.config, self.env
        o, m = env.observation_size, env.action_size
        ka, kc, ke, key = jax.random.split(key, 4)
        actor = Actor(o, m, cfg.hidden, ka)
        critic = Critic(o, m, cfg.hidden, kc)
        opt = self._optimizer()
        log_alpha = jnp.log(jnp.asarray(cfg.init_alpha, jnp.float64))
        obs, env_state = jax.vmap(env._reset, in_axes=(0, None))(jax.random.split(ke, cfg.num_envs), env.params)
        capacity = cfg.buffer_size
        n = cfg.num_envs
        return SACState(actor=actor, critic=critic, target=critic, log_alpha=log_alpha,
                        actor_opt=opt.init(eqx.filter(actor, eqx.is_inexact_array)),
                        critic_opt=opt.init(eqx.filter(critic, eqx.is_inexact_array)),
                        alpha_opt=opt.init(log_alpha),
                        buffer=Buffer.empty(capacity, o, m, cfg.uses_jacobian), env_state=env_state, obs=obs,
                        episode_return=jnp.zeros(n), last_return=jnp.full(n, jnp.nan, jnp.float64),
                        steps=jnp.zeros((), jnp.int32), samples=jnp.zeros((), jnp.int32),
                        virtual=jnp.zeros((), jnp.int32), key=key)

    # -- acting

    def act(self, state: SACState, obs: Array, key=None) -> Array:
        """The policy's action ``(m,)`` for an observation ``(obs,)``: a sample with a
        ``key``, ``tanh(mean)`` without."""
        if jnp.shape(obs) != (self.env.observation_size,):
            raise ControlError(f"obs has shape {tuple(jnp.shape(obs))}; this agent takes "
                               f"({self.env.observation_size},)")
        if key is None:
            return state.actor.deterministic(obs)
        return state.actor.sample(obs, key)[0]

    # -- one environment step (per environment)

    def _env_step(self, key, env_state, obs, action):
        cfg, env, params = self.config, self.env, self.env.params
        k_step, k_reset, k_virt = jax.random.split(key, 3)
        next_obs, new, reward, done, info = env._step_env(k_step, env_state, action, params)
        terminal = (done & ~info["truncated"]).astype(jnp.float64)
        m, o = env.action_size, env.observation_size
        if cfg.uses_jacobian:
            jac = E._jacobian_fn(env, False, None)(params, env_state, action)
            ok = jac.result == 0
            dobs_da = jnp.where(ok, _next_obs_jacobian(env, env_state, jac), 0.0)
            dr_da = jnp.where(ok, jac.dr_da, 0.0)
        else:
            jac, ok = None, jnp.asarray(True)
            dobs_da, dr_da = jnp.zeros((1, o, m)), jnp.zeros((1, m))
        rows = {"obs": obs[None], "action": action[None], "reward": reward[None], "next_obs": next_obs[None],
                    "terminal": terminal[None], "dobs_da": dobs_da[None] if cfg.uses_jacobian else dobs_da,
                    "dr_da": dr_da[None] if cfg.uses_jacobian else dr_da, "valid": jnp.ones(1, bool)}
        if cfg.virtual_samples:
            k = cfg.virtual_samples
            d = cfg.virtual_scale * jax.random.normal(k_virt, (k, m))
            a_k, obs_k, r_k, valid = _virtual(env, params, env_state, action, d, jac, env.model.has_contact)
            # Virtual samples only around a real step that succeeded and did not end in a failure.
            valid = valid & ok & ~(done & ~info["truncated"])
            rows = {key_: jnp.concatenate([rows[key_], extra]) for key_, extra in (
                ("obs", jnp.broadcast_to(obs, (k, o))), ("action", a_k), ("reward", r_k), ("next_obs", obs_k),
                ("terminal", jnp.broadcast_to(terminal, (k,))),
                ("dobs_da", jnp.broadcast_to(dobs_da, (k, o, m))), ("dr_da", jnp.broadcast_to(dr_da, (k, m))),
                ("valid", valid))}
        obs_reset, state_reset = env._reset(k_reset, params)
        pick = lambda a, b: jnp.where(done, a, b)
        obs_after = pick(obs_reset, next_obs)
        state_after = jax.tree.map(pick, state_reset, new)
        return rows, obs_after, state_after, reward, done

    # -- the gradient step

    def _update(self, state: SACState, key) -> SACState:
        cfg = self.config
        k_batch, k_next, k_pi = jax.random.split(key, 3)
        batch = state.buffer.sample(k_batch, cfg.batch_size)
        alpha = jnp.exp(state.log_alpha)
        opt = self._optimizer()
        keys_next = jax.random.split(k_next, cfg.batch_size)
        a_next, logp_next = jax.vmap(state.actor.sample)(batch["next_obs"], keys_next)
        q_next = jax.vmap(state.target.min)(batch["next_obs"], a_next)
        y = batch["reward"] + cfg.gamma * (1.0 - batch["terminal"]) * (q_next - alpha * logp_next)
        y = jax.lax.stop_gradient(y)

        def critic_loss(critic):
            q1, q2 = jax.vmap(critic)(batch["obs"], batch["action"])
            return jnp.mean((q1 - y) ** 2 + (q2 - y) ** 2)

        grads = eqx.filter_grad(critic_loss)(state.critic)
        updates, critic_opt = opt.update(grads, state.critic_opt, eqx.filter(state.critic, eqx.is_inexact_array))
        critic = eqx.apply_updates(state.critic, updates)

        keys_pi = jax.random.split(k_pi, cfg.batch_size)
        frozen_actor = state.actor  # a constant here: the gradient flows through a_pi only

        def actor_loss(actor):
            a_pi, logp = jax.vmap(actor.sample)(batch["obs"], keys_pi)
            if cfg.policy_enhancement:
                t = {k: batch[k] for k in ("action", "reward", "next_obs", "terminal", "dobs_da", "dr_da")}
                q = jax.vmap(lambda a, t: _model_q(frozen_actor, critic, cfg.gamma, a, t))(a_pi, t)
            else:
                q = jax.vmap(critic.min)(batch["obs"], a_pi)
            return jnp.mean(alpha * logp - q), logp

        (_, logp), grads = eqx.filter_value_and_grad(actor_loss, has_aux=True)(state.actor)
        updates, actor_opt = opt.update(grads, state.actor_opt, eqx.filter(state.actor, eqx.is_inexact_array))
        actor = eqx.apply_updates(state.actor, updates)

        target_entropy = -float(self.env.action_size) if cfg.target_entropy is None else cfg.target_entropy
        entropy_gap = jax.lax.stop_gradient(-jnp.mean(logp) - target_entropy)
        g_alpha = entropy_gap  # d/dlog_alpha of log_alpha * (entropy - target)
        step, alpha_opt = opt.update(g_alpha, state.alpha_opt, state.log_alpha)
        log_alpha = optax.apply_updates(state.log_alpha, step)
        target = _polyak(state.target, critic, cfg.tau)
        return dataclasses.replace(state, actor=actor, critic=critic, target=target, log_alpha=log_alpha,
                                   actor_opt=actor_opt, critic_opt=critic_opt, alpha_opt=alpha_opt)

    # -- one iteration: every environment steps once, then gradient steps

    def _iteration(self, state: SACState, _):
        cfg = self.config
        n, m = cfg.num_envs, self.env.action_size
        key, k_act, k_env, k_upd = jax.random.split(state.key, 4)
        warm = state.steps < cfg.warmup
        random_actions = jax.random.uniform(k_act, (n, m), minval=-1.0, maxval=1.0)
        policy_actions = jax.vmap(state.actor.sample)(state.obs, jax.random.split(k_act, n))[0]
        actions = jnp.where(warm, random_actions, policy_actions)
        rows, obs, env_state, reward, done = jax.vmap(self._env_step)(
            jax.random.split(k_env, n), state.env_state, state.obs, actions)
        flat = {k: v.reshape((-1,) + v.shape[2:]) for k, v in rows.items()}
        buffer = state.buffer.add(**flat)
        returns = state.episode_return + reward
        last = jnp.where(done, returns, state.last_return)
        stored = jnp.sum(flat["valid"]).astype(jnp.int32)
        state = dataclasses.replace(state, buffer=buffer, env_state=env_state, obs=obs,
                                    episode_return=jnp.where(done, 0.0, returns), last_return=last,
                                    steps=state.steps + 1, samples=state.samples + n,
                                    virtual=state.virtual + stored - n, key=key)

        dynamic, static = eqx.partition(state, eqx.is_array)

        def learn(dynamic):
            def one(dynamic, k):
                return eqx.partition(self._update(eqx.combine(dynamic, static), k), eqx.is_array)[0], None
            dynamic, _ = jax.lax.scan(one, dynamic, jax.random.split(k_upd, cfg.updates_per_step * n))
            return dynamic

        dynamic = jax.lax.cond(warm | (state.buffer.size < cfg.batch_size), lambda d: d, learn, dynamic)
        return eqx.combine(dynamic, static), (reward, done)

    def _train(self, state: SACState, iterations: int):
        dynamic, static = eqx.partition(state, eqx.is_array)

        def body(dynamic, _):
            new, out = self._iteration(eqx.combine(dynamic, static), None)
            return eqx.partition(new, eqx.is_array)[0], out

        dynamic, out = jax.lax.scan(body, dynamic, None, length=iterations)
        return eqx.combine(dynamic, static), out

    @functools.cached_property
    def _programs(self) -> dict:
        return {}

    def _train_jit(self, iterations: int, seeds: bool, episodes: int = 0):
        key = ("train", iterations, seeds, episodes)
        if key not in self._programs:
            self._programs[key] = self._make_train(iterations, seeds, episodes)
        return self._programs[key]

    def _make_train(self, iterations: int, seeds: bool, episodes: int):
        def f(state, key=None):
            state, out = self._train(state, iterations)
            if episodes:  # the evaluation in the same program (one compile)
                out = evaluate_policy(self.env, state.actor.deterministic, key, episodes)
            return state, out

        return eqx.filter_jit(eqx.filter_vmap(f) if seeds else f)

    def _iterations(self, steps) -> int:
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise ControlError(f"steps must be a whole number of environment steps >= 1, got {steps!r}")
        n = self.config.num_envs
        if steps % n:
            raise ControlError(f"steps ({steps}) must be a multiple of num_envs ({n}): each iteration steps every "
                               "environment once")
        return steps // n

    def train(self, state: SACState, steps: int):
        """Collect ``steps`` real samples (``steps / num_envs`` iterations) and learn.

        Arguments:
            state: from :meth:`init` or an earlier :meth:`train`.
            steps: real samples to collect (all environments together), a multiple of
                ``num_envs``.

        Returns:
            ``(state, (rewards, dones))``, the per-step rewards and episode ends
            ``(steps / num_envs, num_envs)``.

        Raises:
            ControlError: a bad ``steps`` or ``state`` (before compiling).
        """
        if not isinstance(state, SACState):
            raise ControlError(f"state must be the SACState of SAC.init, got {type(state).__name__}")
        return self._train_jit(self._iterations(steps), False)(state, )

    def init_seeds(self, seeds) -> SACState:
        """:meth:`init` of several seeds at once (a leading axis on every leaf)."""
        keys = jnp.stack([jax.random.PRNGKey(int(s)) for s in seeds])
        return eqx.filter_jit(eqx.filter_vmap(self._init))(keys)

    def train_seeds(self, states: SACState, steps: int, eval_keys=None, episodes: int = 1):
        """:meth:`train` of a batch of runs from :meth:`init_seeds`, one ``vmap``.

        Arguments:
            states: the runs (leading axis: seeds).
            steps: as :meth:`train`.
            eval_keys: ``(seeds,)`` keys: then the program also evaluates each run's
                deterministic policy after training (as :meth:`evaluate`) and returns its
                ``(seeds, episodes)`` returns instead of the step rewards.
            episodes: episodes per evaluation.

        Returns:
            ``(states, (rewards, dones))`` or, with ``eval_keys``, ``(states, returns)``.
        """
        if not isinstance(states, SACState):
            raise ControlError(f"states must be the SACState of SAC.init_seeds, got {type(states).__name__}")
        iterations = self._iterations(steps)
        if eval_keys is None:
            return self._train_jit(iterations, True)(states)
        return self._train_jit(iterations, True, _whole(episodes, "episodes"))(states, eval_keys)

    def evaluate(self, state: SACState, key, episodes: int = 1) -> Array:
        """Returns of the deterministic policy (``tanh(mean)``) over whole episodes.

        Arguments:
            state: the agent's state (unbatched).
            key: the reset noise's key.
            episodes: episodes to run (batched).

        Returns:
            ``(episodes,)`` the episodes' returns.
        """
        return self._evaluate_jit(_whole(episodes, "episodes"), False)(state, key)

    def evaluate_seeds(self, states: SACState, keys, episodes: int = 1) -> Array:
        """:meth:`evaluate` of a batch of runs (one ``vmap``): ``(seeds, episodes)``."""
        return self._evaluate_jit(_whole(episodes, "episodes"), True)(states, keys)

    def _evaluate_jit(self, episodes: int, seeds: bool):
        key = ("evaluate", episodes, seeds)
        if key not in self._programs:
            f = lambda state, key: evaluate_policy(self.env, state.actor.deterministic, key, episodes)
            self._programs[key] = eqx.filter_jit(eqx.filter_vmap(f) if seeds else f)
        return self._programs[key]


def evaluate_policy(env: E.Env, policy, key, episodes: int = 1, steps: int | None = None) -> Array:
    """The returns of ``policy(obs) -> action`` over ``episodes`` episodes (batched by
    ``vmap``), each ``steps`` long (default ``env.episode_length``; an episode that fails
    earlier stops collecting reward)."""
    steps = env.episode_length if steps is None else int(steps)
    _whole(episodes, "episodes")

    def one(k):
        obs, st = env._reset(k, env.params)

        def body(carry, k):
            obs, st, alive, total = carry
            obs, st, r, done, _ = env._step_env(k, st, policy(obs), env.params)
            total = total + jnp.where(alive, r, 0.0)
            return (obs, st, alive & ~done, total), None

        (_, _, _, total), _ = jax.lax.scan(body, (obs, st, jnp.asarray(True), jnp.zeros(())),
                                           jax.random.split(k, steps))
        return total

    return jax.vmap(one)(jax.random.split(key, episodes))


# --------------------------------------------------------------------------- PPO (rejax)


def _rejax():
    try:
        import gymnax  # noqa: F401
        import rejax
    except ImportError as err:
        raise ImportError(f"PPO comes from rejax, which is not installed ({err}); install it with "
                          "`pip install softbody[rl]`") from None
    return rejax


def GymnaxEnv(env: E.Env):
    """The environment under gymnax's interface as rejax 0.1.3 calls it
    (``step(key, state, action, params) -> (obs, state, reward, done, info)`` with
    auto-reset, ``reset``, ``action_space``, ``observation_space``); the parameters are
    ``env.params``.

    Raises:
        ImportError: gymnax missing (``pip install softbody[rl]``).
    """
    _rejax()
    from gymnax.environments import spaces

    class _Gymnax:
        def __init__(self, env):
            self.env = env

        def __deepcopy__(self, memo):  # rejax deep-copies its config; a compiled scene is immutable
            return self

        @property
        def default_params(self):
            return self.env.params

        @property
        def name(self):
            return "softbody.Env"

        # rejax keeps its running statistics in float32: observations and rewards go out in
        # float32, actions come back to float64 for the simulation.
        def reset(self, key, params=None):
            obs, st = self.env._reset(key, self.env.params if params is None else params)
            return obs.astype(jnp.float32), st

        def step(self, key, state, action, params=None):
            obs, st, r, done, info = self.env._step(key, state, jnp.asarray(action, jnp.float64),
                                                    self.env.params if params is None else params)
            return obs.astype(jnp.float32), st, r.astype(jnp.float32), done, {"truncated": info["truncated"]}

        def action_space(self, params=None):
            m = self.env.action_size
            return spaces.Box(-np.ones(m, np.float32), np.ones(m, np.float32), (m,), jnp.float32)

        def observation_space(self, params=None):
            o = self.env.observation_size
            return spaces.Box(np.full(o, -np.inf, np.float32), np.full(o, np.inf, np.float32), (o,), jnp.float32)

        @property
        def num_actions(self):
            return self.env.action_size

    return _Gymnax(env)


def ppo_policy(algo, ts):
    """The deterministic policy of a trained rejax PPO: its mean action, clipped to ``[-1, 1]``.

    Arguments:
        algo: the rejax ``PPO`` (from :func:`ppo`); ts: its train state.

    Returns:
        ``policy(obs (size,)) -> action (n_actions,)`` float64, traceable.
    """
    def policy(obs):
        if algo.normalize_observations:
            obs = algo.normalize_obs(ts.obs_rms_state, obs)
        mean = algo.actor.apply(ts.actor_ts.params, obs.astype(jnp.float32)[None],
                                method=lambda mod, o: mod._action_dist(o).mean())
        return jnp.clip(mean[0], -1.0, 1.0).astype(jnp.float64)

    return policy


def ppo(env: E.Env, total_steps: int, *, eval_every: int, num_envs: int = 4, num_steps: int = 25,
        eval_episodes: int = 1, **config):
    """rejax's PPO on a softbody environment, evaluated as :meth:`SAC.evaluate` does.

    Arguments:
        env: the environment.
        total_steps: real samples to train on (all environments together).
        eval_every: samples between evaluations of the deterministic policy (its mean
            action), a multiple of ``num_envs * num_steps``.
        num_envs, num_steps: environments and steps per PPO rollout.
        eval_episodes: episodes per evaluation.
        config: more of rejax's PPO options (``learning_rate``, ``num_epochs``,
            ``num_minibatches``, ``gamma``, ...).

    Returns:
        ``(algo, train)``: the rejax ``PPO`` and a pure ``train(key) -> (train_state,
        returns)``, ``returns`` ``(1 + total_steps / eval_every, eval_episodes)`` (the
        first before training; none where ``skip_initial_evaluation=True``), batchable
        over keys by ``jax.vmap``.

    Raises:
        ImportError: rejax missing (``pip install softbody[rl]``).
        ControlError: bad step counts.
    """
    for name, v in (("total_steps", total_steps), ("eval_every", eval_every), ("num_envs", num_envs),
                    ("num_steps", num_steps), ("eval_episodes", eval_episodes)):
        _whole(v, name)
    rollout = num_envs * num_steps
    if eval_every % rollout or total_steps % eval_every:
        raise ControlError(f"eval_every ({eval_every}) must be a multiple of num_envs * num_steps ({rollout}) and "
                           f"divide total_steps ({total_steps})")
    rejax = _rejax()
    gym = GymnaxEnv(env)
    options = {"num_epochs": 4, "num_minibatches": 4, "learning_rate": 3e-4, "gamma": 0.99, "normalize_observations": True,
                   "agent_kwargs": {"activation": "tanh", "hidden_layer_sizes": (64, 64)}}
    options.update(config)
    options.update(total_timesteps=int(total_steps), eval_freq=int(eval_every), num_envs=int(num_envs),
                   num_steps=int(num_steps))
    # As rejax's PPO.create, with our evaluation instead of its default one.
    networks = rejax.PPO.create_agent(options, gym, env.params)

    def eval_callback(algo, ts, rng):
        return evaluate_policy(env, ppo_policy(algo, ts), rng, eval_episodes)

    algo = rejax.PPO(env=gym, env_params=env.params, eval_callback=eval_callback, **networks, **options)
    return algo, algo.train

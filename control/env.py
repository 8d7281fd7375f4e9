"""Reinforcement-learning environments over any softbody scene, in gymnax's pure style,
and exact one-step Jacobians.

An :class:`Env` wraps a compiled scene (``model, params = softbody.build(...)``: soft
bodies, skeletons with joint actuators, obstacles with friction) with three small parts:

* an :class:`ActionMap`: the action vector, each entry in ``[-1, 1]`` (entries outside are
  clipped), maps affinely onto a range of each actuator channel it drives
  (``low + (action + 1) / 2 * (high - low)``); the default range is the channel's own
  bounds (``model.channel_bounds``), unbounded channels (a joint torque) need a range;
* an observation: a callable ``obs(state, start) -> (size,)`` of the simulation
  :class:`~softbody.model.State` and the episode's start state with a ``size``
  attribute: :class:`softbody.control.Observations` (region centroids, clocks),
  :class:`JointAngles` (a skeleton's joint angles and rates), :class:`Positions` (the
  positions and velocities of vertices), or several of them in a :class:`Concat`;
* a reward: a callable ``reward(transition) -> scalar`` of a :class:`Transition`
  (start state, action, activation, next state, episode start): :class:`Progress`
  (a region's forward distance in the step), :class:`Height` (a region's height),
  :class:`ActionPenalty` (minus the squared action); ``+`` and scalar ``*`` combine them.

The functions are pure and traceable, as gymnax's::

    env = Env(model, params, observation=JointAngles(model), reward=Height(model, "tip"),
              action_map=ActionMap(model, low=-0.01, high=0.01), episode_length=100)
    obs, state = env.reset(key)                                  # params default to env.params
    obs, state, reward, done, info = env.step(key, state, action)

and batch by ``jax.vmap`` (:meth:`Env.batch_reset`, :meth:`Env.batch_step`: one compiled
``jit(vmap(...))`` each; the parameters are shared, so the batch factorises the PD
matrix once). An episode is ``done`` after ``episode_length`` steps, or at once where a
step fails badly (non-finite state or inverted tets, see below); :meth:`Env.step` then
resets that environment (gymnax's auto-reset), :meth:`Env.step_env` does not.

:func:`step_jacobian` gives the exact one-step Jacobians ``ds'/da``, ``dr/da``, ``ds'/ds``
and ``dr/ds`` by forward-mode implicit differentiation
(:class:`~softbody.gradients.ImplicitForward`; through contact the contact set is held
fixed, which is what the implicit derivative of the step's fixed point does), and
:func:`contact_changes` says whether a perturbed action ``a + da`` changes the contact set
(so that virtual samples that cross a stick/slide/separation switch can be discarded).

The simulation state ``s`` of the Jacobians is ``concatenate([x.ravel(), v.ravel()])``:
positions then velocities, each vertex-major (entry ``3 i + k`` of either half is vertex
``i``'s component ``k``), ``6 n`` numbers; :func:`flatten_state` and
:func:`unflatten_state` convert.

Failures and bad input:

* Refused before anything is compiled, with a :class:`~softbody.control.ControlError`
  naming the problem and the fix: an action of the wrong shape (under ``jax.vmap`` the
  shape is per environment), a non-finite action given as a concrete array, a reward that
  does not return a scalar or an observation that does not return a vector (checked with
  ``jax.eval_shape`` when the environment is made), an action map with unbounded or
  out-of-bounds ranges.
* Under ``jax.jit``/``jax.vmap`` (a traced action) a non-finite action cannot be refused:
  the step is then not simulated (the state is held), ``info["result"]`` is
  :data:`RESULTS.nonfinite <softbody._types.RESULTS>`, the reward is 0 and ``done`` is
  true, so :meth:`Env.step` starts a new episode. A step whose state becomes non-finite or
  that inverts more tets than the episode's start had ends the episode the same way (its
  reward is 0); a step that stops at the iteration cap goes on, with
  ``info["result"] == RESULTS.max_iterations``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody import simulate
from softbody._types import RESULTS, Model, Params, State
from softbody.elastic import deformation_gradient
from softbody.gradients import ImplicitForward
from softbody.model import initial_state, prepare
from softbody.rotation import cold_start

from .errors import ControlError
from .losses import centroid_weights, region_vertices

Array = jax.Array

__all__ = [
    "ActionMap",
    "ActionPenalty",
    "Concat",
    "Env",
    "EnvState",
    "Height",
    "JointAngles",
    "Positions",
    "Progress",
    "ResetNoise",
    "Reward",
    "RewardSum",
    "ScaledReward",
    "StepJacobian",
    "Transition",
    "contact_changes",
    "flatten_state",
    "step_jacobian",
    "unflatten_state",
]


def _is_traced(tree) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(tree))


# --------------------------------------------------------------------------- actions


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class ActionMap:
    """The map from an action vector to the scene's actuator activations.

    Action entry ``j`` drives channel ``channels[j]``: it is clipped to ``[-1, 1]`` and
    mapped affinely onto ``[low_j, high_j]`` (``-1 -> low``, ``1 -> high``); channels no
    action drives hold ``rest``. The derivative with respect to an action entry beyond
    ``[-1, 1]`` is zero (the clip).

    Arguments:
        model: the compiled scene.
        channels: names of the driven channels (of ``model.channel_names``), in action
            order; ``None`` (default) for all of them.
        low, high: the activation range of each driven channel, a number or one per
            driven channel; ``None`` (default) takes the channel's bounds
            (``model.channel_bounds``). The range must be finite and inside the bounds.
        rest: the activations of the channels no action drives, a number or
            ``(n_channels,)`` (clipped to the bounds; default 0).

    Raises:
        ControlError: an unknown or repeated channel, no channels, an unbounded channel
            without a range, a range outside the channel's bounds or with ``low >= high``.
    """

    channels: tuple[int, ...]
    low: np.ndarray
    high: np.ndarray
    rest: np.ndarray

    def __init__(self, model: Model, channels: Sequence[str] | None = None, *, low=None, high=None, rest=0.0):
        names = list(model.channel_names)
        if model.n_channels == 0:
            raise ControlError("the scene has no actuator channels to act on; give a body actuators "
                               "(SoftBody(..., actuators=[...])) or the skeleton joint actuators (build(actuators=[...]))")
        if channels is None:
            index = list(range(len(names)))
        else:
            if isinstance(channels, str):
                raise ControlError(f"channels must be a sequence of channel names, got the string {channels!r}; "
                                   f"write [{channels!r}]")
            unknown = [c for c in channels if c not in names]
            if unknown:
                raise ControlError(f"unknown channel(s) {unknown}; the scene's channels are {names}")
            index = [names.index(c) for c in channels]
            if not index or len(set(index)) != len(index):
                raise ControlError(f"give at least one channel, each once; got {list(channels)}")
        lower, upper = (np.asarray(b, np.float64)[index] for b in model.channel_bounds)
        lo = lower if low is None else np.broadcast_to(np.asarray(low, np.float64), (len(index),))
        hi = upper if high is None else np.broadcast_to(np.asarray(high, np.float64), (len(index),))
        for j, c in enumerate(index):
            name = names[c]
            if not (np.isfinite(lo[j]) and np.isfinite(hi[j])):
                raise ControlError(
                    f"channel {name!r} has the range [{lo[j]:g}, {hi[j]:g}]: an action in [-1, 1] needs a finite "
                    f"range to map onto; give ActionMap(model, low=..., high=...) (e.g. a torque range in N m)")
            if not lo[j] < hi[j]:
                raise ControlError(f"channel {name!r}: low = {lo[j]:g} must be below high = {hi[j]:g}")
            if lo[j] < lower[j] or hi[j] > upper[j]:
                raise ControlError(f"channel {name!r}: the range [{lo[j]:g}, {hi[j]:g}] leaves the channel's bounds "
                                   f"[{lower[j]:g}, {upper[j]:g}]; give a range inside them")
        all_lower, all_upper = model.channel_bounds
        rest = np.broadcast_to(np.asarray(rest, np.float64), (model.n_channels,))
        if not np.all(np.isfinite(rest)):
            raise ControlError(f"rest activations must be finite, got {rest}")
        object.__setattr__(self, "channels", tuple(index))
        object.__setattr__(self, "low", np.array(lo))
        object.__setattr__(self, "high", np.array(hi))
        object.__setattr__(self, "rest", np.clip(rest, all_lower, all_upper))

    @property
    def size(self) -> int:
        """The action's length: the number of driven channels."""
        return len(self.channels)

    def __call__(self, action: Array) -> Array:
        """The activations ``(n_channels,)`` of an action ``(size,)``."""
        u = (jnp.clip(action, -1.0, 1.0) + 1.0) / 2.0
        driven = jnp.asarray(self.low) + u * jnp.asarray(self.high - self.low)
        return jnp.asarray(self.rest).at[jnp.asarray(self.channels)].set(driven)


# --------------------------------------------------------------------------- observations


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class JointAngles:
    """A skeleton's joint angles (rad; slides of prismatic joints in m) and, optionally,
    their rates (rad/s, m/s), read off the bone positions and velocities.

    Arguments:
        model: a compiled scene with a skeleton.
        joints: link names of revolute or prismatic joints; ``None`` (default) for all of them.
        velocities: also observe the rates (the angles' derivative along ``v``).

    Raises:
        ControlError: no skeleton, an unknown link, or a link without an angle or slide.
    """

    rig: Any
    dofs: np.ndarray
    velocities: bool

    def __init__(self, model: Model, joints: Sequence[str] | None = None, *, velocities: bool = True):
        rig = model.rig
        if rig is None:
            raise ControlError("JointAngles needs a scene with a skeleton (build(..., skeleton=Skeleton([...])))")
        scalar = [i for i, link in enumerate(rig.links) if type(link.joint).__name__ in ("Revolute", "Prismatic")]
        if joints is None:
            chosen = scalar
        else:
            names = [link.name for link in rig.links]
            unknown = [j for j in joints if j not in names]
            if unknown:
                raise ControlError(f"unknown joint(s) {unknown}; the skeleton's links are {names}")
            chosen = [names.index(j) for j in joints]
            bad = [names[i] for i in chosen if i not in scalar]
            if bad:
                raise ControlError(f"link(s) {bad} have no angle or slide (Free or Fixed joints); name revolute or "
                                   "prismatic joints")
        if not chosen:
            raise ControlError("the skeleton has no revolute or prismatic joint to observe")
        object.__setattr__(self, "rig", rig)
        object.__setattr__(self, "dofs", np.asarray([rig.dof_start[i] for i in chosen]))
        object.__setattr__(self, "velocities", bool(velocities))

    @property
    def size(self) -> int:
        """``joints`` (or ``2 * joints`` with velocities)."""
        return len(self.dofs) * (2 if self.velocities else 1)

    def _angles(self, x_bone):
        return self.rig.joint_values(self.rig.coordinates(x_bone))[jnp.asarray(self.dofs)]

    def __call__(self, state: State, start: State) -> Array:
        """``(size,)``: the angles, then the rates."""
        bone = jnp.asarray(self.rig.bone)
        if not self.velocities:
            return self._angles(state.x[bone])
        angles, rates = jax.jvp(self._angles, (state.x[bone],), (state.v[bone],))
        return jnp.concatenate([angles, rates])


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class Positions:
    """Positions (relative to the episode's start, divided by ``length_scale``) and
    velocities (divided by ``velocity_scale``) of chosen vertices: ``6 k`` numbers.

    Arguments:
        model: the compiled scene.
        vertices: a region name, vertex indices, or ``None`` (every vertex).
        length_scale, velocity_scale: the units (m, m/s), > 0.

    Raises:
        ControlError: an unknown region, an empty selection, non-positive scales.
    """

    idx: np.ndarray
    length_scale: float
    velocity_scale: float

    def __init__(self, model: Model, vertices=None, *, length_scale: float = 0.01, velocity_scale: float = 0.1):
        for name, v in (("length_scale", length_scale), ("velocity_scale", velocity_scale)):
            if not (math.isfinite(v) and v > 0):
                raise ControlError(f"{name} must be positive, got {v}")
        object.__setattr__(self, "idx", region_vertices(model, vertices))
        object.__setattr__(self, "length_scale", float(length_scale))
        object.__setattr__(self, "velocity_scale", float(velocity_scale))

    @property
    def size(self) -> int:
        return 6 * len(self.idx)

    def __call__(self, state: State, start: State) -> Array:
        idx = jnp.asarray(self.idx)
        return jnp.concatenate([((state.x[idx] - start.x[idx]) / self.length_scale).ravel(),
                                (state.v[idx] / self.velocity_scale).ravel()])


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class Concat:
    """Several observations side by side (in the order given).

    Raises:
        ControlError: none given, or one without a ``size``.
    """

    parts: tuple

    def __init__(self, *parts):
        if not parts:
            raise ControlError("Concat needs at least one observation")
        for p in parts:
            if not (callable(p) and isinstance(getattr(p, "size", None), (int, np.integer))):
                raise ControlError(f"{p!r} is not an observation: give a callable obs(state, start) with an int size")
        object.__setattr__(self, "parts", tuple(parts))

    @property
    def size(self) -> int:
        return sum(int(p.size) for p in self.parts)

    def __call__(self, state: State, start: State) -> Array:
        return jnp.concatenate([jnp.atleast_1d(p(state, start)) for p in self.parts])


# --------------------------------------------------------------------------- rewards


class Transition(eqx.Module):
    """One step, as a reward sees it.

    Attributes:
        state: the simulation :class:`~softbody.model.State` the step started from.
        action: ``(action_size,)`` the action as given (before clipping).
        activation: ``(n_channels,)`` the activations it became.
        next_state: the state the step ended in.
        start: the episode's start state.
    """

    state: State
    action: Array
    activation: Array
    next_state: State
    start: State


class Reward:
    """Base class: ``reward(transition) -> scalar``; ``+`` adds rewards, ``*`` scales one
    by a number, unary ``-`` negates."""

    def __call__(self, transition: Transition) -> Array:
        raise NotImplementedError

    def __add__(self, other):
        if not isinstance(other, Reward):
            return NotImplemented
        mine = self.terms if isinstance(self, RewardSum) else (self,)
        theirs = other.terms if isinstance(other, RewardSum) else (other,)
        return RewardSum(mine + theirs)

    def __mul__(self, factor):
        if isinstance(factor, Reward) or not np.isscalar(factor) or not np.isfinite(factor):
            return NotImplemented
        return ScaledReward(self, float(factor))

    __rmul__ = __mul__

    def __neg__(self):
        return ScaledReward(self, -1.0)

    def __sub__(self, other):
        if not isinstance(other, Reward):
            return NotImplemented
        return self + (-other)


@dataclasses.dataclass(frozen=True, eq=False)
class RewardSum(Reward):
    """The sum of several rewards."""

    terms: tuple

    def __call__(self, transition):
        return sum(term(transition) for term in self.terms)


@dataclasses.dataclass(frozen=True, eq=False)
class ScaledReward(Reward):
    """A reward times a constant."""

    term: Reward
    factor: float

    def __call__(self, transition):
        return self.factor * self.term(transition)


def _unit(axis, what: str) -> np.ndarray:
    a = np.asarray(axis, np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or not np.linalg.norm(a) > 0:
        raise ControlError(f"{what} must be 3 finite numbers, not all zero; got {axis!r}")
    return a / np.linalg.norm(a)


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class Progress(Reward):
    """The distance (m) a region's centroid moves along ``axis`` in the step (its sum over
    an episode is the distance travelled, :class:`softbody.control.ForwardDistance`'s).

    Arguments:
        model: the compiled scene.
        axis: ``(3,)`` the forward direction (normalised here).
        region: a region name, vertex indices, or ``None`` (every vertex); the centroid is
            volume-weighted (:func:`softbody.control.centroid_weights`).

    Raises:
        ControlError: an unknown region or a zero axis.
    """

    idx: np.ndarray
    weights: np.ndarray
    axis: np.ndarray

    def __init__(self, model: Model, axis=(1.0, 0.0, 0.0), region=None):
        idx = region_vertices(model, region)
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "weights", centroid_weights(model, idx))
        object.__setattr__(self, "axis", _unit(axis, "axis"))

    def __call__(self, transition):
        w, idx = jnp.asarray(self.weights), jnp.asarray(self.idx)
        d = w @ (transition.next_state.x[idx] - transition.state.x[idx])
        return d @ jnp.asarray(self.axis)


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class Height(Reward):
    """The height (m) of a region's centroid along ``axis`` at the step's end, minus
    ``reference`` (default 0).

    Arguments:
        model: the compiled scene.
        region: a region name, vertex indices (one index: a point), or ``None``.
        axis: ``(3,)`` the up direction (normalised here; default ``+z``).
        reference: subtracted from the height, m.

    Raises:
        ControlError: an unknown region, a zero axis or a non-finite reference.
    """

    idx: np.ndarray
    weights: np.ndarray
    axis: np.ndarray
    reference: float

    def __init__(self, model: Model, region=None, *, axis=(0.0, 0.0, 1.0), reference: float = 0.0):
        if not math.isfinite(reference):
            raise ControlError(f"reference must be finite, got {reference}")
        idx = region_vertices(model, region)
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "weights", centroid_weights(model, idx))
        object.__setattr__(self, "axis", _unit(axis, "axis"))
        object.__setattr__(self, "reference", float(reference))

    def __call__(self, transition):
        c = jnp.asarray(self.weights) @ transition.next_state.x[jnp.asarray(self.idx)]
        return c @ jnp.asarray(self.axis) - self.reference


@dataclasses.dataclass(frozen=True, eq=False, init=False)
class ActionPenalty(Reward):
    """Minus the action effort, ``-sum_j (clip(action_j, -1, 1) / scale_j)^2``.

    Arguments:
        scale: a number or one per action entry, > 0.

    Raises:
        ControlError: a non-positive or non-finite scale.
    """

    scale: np.ndarray

    def __init__(self, scale=1.0):
        s = np.asarray(scale, np.float64)
        if s.ndim > 1 or not np.all(np.isfinite(s)) or not np.all(s > 0):
            raise ControlError(f"scale must be a positive number or one per action entry, got {scale!r}")
        object.__setattr__(self, "scale", s)

    def __call__(self, transition):
        a = jnp.clip(transition.action, -1.0, 1.0) / jnp.asarray(self.scale)
        return -jnp.sum(a * a)


# --------------------------------------------------------------------------- the environment


class EnvState(eqx.Module):
    """An environment's state (a pytree; batched along a leading axis under ``vmap``).

    Attributes:
        sim: the simulation :class:`~softbody.model.State` (``x``, ``v`` ``(n, 3)``, ...).
        start: the episode's start state (observations and rewards may read it).
        steps: int32, steps taken in this episode.
        inverted0: int, inverted tets of the start state (a step that ends with more fails).
    """

    sim: State
    start: State
    steps: Array
    inverted0: Array


@dataclasses.dataclass(frozen=True)
class ResetNoise:
    """Random perturbation of an episode's start state.

    Soft free vertices (neither held nor bone) get independent Gaussian offsets of
    standard deviation ``position`` (m) and velocities of ``velocity`` (m/s); a
    skeleton's joints get Gaussian tangent offsets of ``joint`` (rad, or m for
    slides; a Free root's 6 tangent entries too), applied to the bones by its forward
    kinematics, so bones stay rigid and joints stay joined. Held vertices stay put.

    Raises:
        ControlError: a negative or non-finite standard deviation.
    """

    position: float = 0.0
    velocity: float = 0.0
    joint: float = 0.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0):
                raise ControlError(f"ResetNoise.{f.name} must be a finite standard deviation >= 0, got {v!r}")

    def __call__(self, key, model: Model, x, v):
        """Perturbed ``(x, v)`` ``(n, 3)``."""
        kx, kv, kj = jax.random.split(key, 3)
        soft = np.asarray(model.free_mask).min(axis=1, keepdims=True) > 0
        if model.rig is not None:
            soft = soft & (np.asarray(model.rig.is_bone) == 0)
        soft = jnp.asarray(soft, x.dtype)
        x = x + self.position * soft * jax.random.normal(kx, x.shape, x.dtype)
        v = v + self.velocity * soft * jax.random.normal(kv, v.shape, v.dtype)
        if model.rig is not None and self.joint > 0:
            rig = model.rig
            bone = jnp.asarray(rig.bone)
            z = rig.retract(rig.coordinates(x[bone]), self.joint * jax.random.normal(kj, (rig.n_dofs,), x.dtype))
            x = x.at[bone].set(rig.positions(z))
        return x, v


def _transition(env: Env, params: Params, state: EnvState, action):
    """The pure step (no auto-reset): ``(next EnvState, reward, done, info)``. The one
    place a step is simulated (tests replace it to show that bad input never gets here)."""
    model = env.model
    prep = prepare(model, params)
    finite_action = jnp.all(jnp.isfinite(action))
    safe_action = jnp.where(finite_action, action, 0.0)
    activation = env.action_map(safe_action)
    sim, info = simulate.step(model, prep, state.sim, activation)
    result, _ = simulate.step_result(sim, info, state.inverted0, inputs_finite=finite_action)
    failed = (result == int(RESULTS.nonfinite)) | (result == int(RESULTS.inverted))
    sim = jax.tree.map(lambda new, old: jnp.where(failed, old, new), sim, state.sim)
    reward = env.reward(Transition(state=state.sim, action=action, activation=activation, next_state=sim,
                                   start=state.start))
    reward = jnp.where(failed, 0.0, reward)
    steps = state.steps + 1
    done = (steps >= env.episode_length) | failed
    new = EnvState(sim=sim, start=state.start, steps=steps, inverted0=state.inverted0)
    info = {"result": result, "iterations": info.iterations, "truncated": (steps >= env.episode_length) & ~failed}
    return new, reward, done, info


@dataclasses.dataclass(frozen=True, eq=False)
class Env:
    """A reinforcement-learning environment over a compiled softbody scene (module docstring).

    Arguments:
        model, params: from :func:`softbody.build`; ``params`` are the default parameters
            (:attr:`default_params`) wherever a method is given ``params=None``.
        observation: ``obs(state, start) -> (size,)`` with an int ``size`` (see the
            module docstring); checked with ``jax.eval_shape``.
        reward: ``reward(transition) -> scalar`` (a :class:`Reward` or any callable of a
            :class:`Transition`); checked with ``jax.eval_shape``.
        action_map: an :class:`ActionMap` (default ``ActionMap(model)``: every channel over
            its bounds, which must then be finite).
        episode_length: steps per episode (>= 1).
        reset_noise: a :class:`ResetNoise` (or ``fn(key, model, x, v) -> (x, v)``), or
            ``None`` for a deterministic start.
        state0: the episode's nominal start :class:`~softbody.model.State` (default: the
            rest shape at rest, :func:`softbody.initial_state`).

    Raises:
        ControlError: a reward that does not return a real scalar, an observation that
            does not return a real vector of its ``size``, a bad ``episode_length``, an
            action map of another model, or a ``state0`` of the wrong shapes: all before
            anything is compiled.

    Attributes:
        action_size: the action's length; actions live in ``[-1, 1]``.
        observation_size: the observation's length.
    """

    model: Model
    params: Params
    observation: Callable
    reward: Callable
    action_map: ActionMap | None = None
    episode_length: int = 200
    reset_noise: Callable | None = None
    state0: State | None = None

    def __post_init__(self):
        if self.action_map is None:
            object.__setattr__(self, "action_map", ActionMap(self.model))
        if not isinstance(self.action_map, ActionMap):
            raise ControlError(f"action_map must be a softbody.control.env.ActionMap, got {type(self.action_map).__name__}")
        if len(self.action_map.rest) != self.model.n_channels:
            raise ControlError("the action map belongs to a model with another number of channels; make it with "
                               "ActionMap(model) of this model")
        if isinstance(self.episode_length, bool) or not isinstance(self.episode_length, (int, np.integer)) \
                or self.episode_length < 1:
            raise ControlError(f"episode_length must be a whole number of steps >= 1, got {self.episode_length!r}")
        size = getattr(self.observation, "size", None)
        if not callable(self.observation) or not isinstance(size, (int, np.integer)):
            raise ControlError("observation must be a callable obs(state, start) with an int attribute size, e.g. "
                               "softbody.control.Observations(model) or JointAngles(model)")
        if not callable(self.reward):
            raise ControlError("reward must be a callable reward(transition) -> scalar, e.g. Progress(model)")
        n = self.model.n_vertices
        if self.state0 is not None:
            for name in ("x", "v"):
                if jnp.shape(getattr(self.state0, name)) != (n, 3):
                    raise ControlError(f"state0.{name} has shape {jnp.shape(getattr(self.state0, name))} but this "
                                       f"model has {n} vertices: give ({n}, 3) (softbody.initial_state(model, params, x=...))")
        state = jax.eval_shape(lambda: initial_state(self.model, self.params))
        try:
            obs = jax.eval_shape(self.observation, state, state)
        except Exception as err:  # noqa: BLE001 (any failure of the user's callable is reported)
            raise ControlError(f"the observation failed on this scene's state: {type(err).__name__}: {err}") from None
        if getattr(obs, "shape", None) != (int(size),) or not jnp.issubdtype(obs.dtype, jnp.floating):
            raise ControlError(f"the observation must return a real vector of its size ({int(size)},), got "
                               f"{getattr(obs, 'shape', type(obs).__name__)} {getattr(obs, 'dtype', '')}; fix its size "
                               "attribute or what it returns")
        action = jax.ShapeDtypeStruct((self.action_map.size,), jnp.float64)
        transition = Transition(state=state, action=action, activation=jax.ShapeDtypeStruct(
            (self.model.n_channels,), jnp.float64), next_state=state, start=state)
        try:
            out = jax.eval_shape(self.reward, transition)
        except Exception as err:  # noqa: BLE001
            raise ControlError(f"the reward failed on a transition of this scene: {type(err).__name__}: {err}") from None
        if not (hasattr(out, "shape") and out.shape == () and jnp.issubdtype(out.dtype, jnp.floating)):
            what = f"shape {out.shape} {out.dtype}" if hasattr(out, "shape") else type(out).__name__
            raise ControlError(f"the reward must return a real scalar (shape ()), got {what}; reduce it to one number "
                               "per step (e.g. jnp.sum or jnp.mean), or combine rewards with + and *")

    # -- gymnax-style properties

    @property
    def default_params(self) -> Params:
        """The scene's parameters given at construction."""
        return self.params

    @property
    def action_size(self) -> int:
        return self.action_map.size

    @property
    def num_actions(self) -> int:
        """gymnax's name for :attr:`action_size`."""
        return self.action_map.size

    @property
    def observation_size(self) -> int:
        return int(self.observation.size)

    @property
    def action_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(-ones, ones)``: the box actions live in (entries outside are clipped)."""
        return -np.ones(self.action_size), np.ones(self.action_size)

    # -- checks (Python, before tracing)

    def _check_action(self, action) -> None:
        shape = jnp.shape(action)
        if shape != (self.action_size,):
            channels = [self.model.channel_names[c] for c in self.action_map.channels]
            batch = ("; for a batch use env.batch_step / jax.vmap over the leading axis"
                     if len(shape) == 2 and shape[-1] == self.action_size else "")
            raise ControlError(f"action has shape {tuple(shape)} but this environment takes ({self.action_size},): one "
                               f"entry in [-1, 1] per driven channel {channels}{batch}")
        if not _is_traced(action):
            a = np.asarray(action)
            if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
                bad = np.flatnonzero(~np.isfinite(a.astype(np.float64))).tolist()
                raise ControlError(f"action holds NaN or inf (entries {bad}); give finite values in [-1, 1] (under "
                                   "jax.jit a non-finite action ends the episode with info['result'] == "
                                   "RESULTS.nonfinite instead)")

    def _check_state(self, state) -> None:
        if not isinstance(state, EnvState):
            raise ControlError(f"state must be the EnvState that reset/step returned, got {type(state).__name__}")
        n = self.model.n_vertices
        if jnp.shape(state.sim.x) != (n, 3):
            raise ControlError(f"state.sim.x has shape {jnp.shape(state.sim.x)} but this model has {n} vertices "
                               f"({n}, 3); a batch of states goes through env.batch_step or jax.vmap")

    def _params(self, params) -> Params:
        if params is None:
            return self.params
        if not isinstance(params, Params):
            raise ControlError(f"params must be softbody Params (or None for env.params), got {type(params).__name__}")
        return params

    # -- the pure functions

    def _reset(self, key, params):
        model = self.model
        base = self.state0 if self.state0 is not None else initial_state(model, params)
        x, v = base.x, base.v
        if self.reset_noise is not None:
            x, v = self.reset_noise(key, model, x, v)
        sim = initial_state(model, params, x=x, v=v)
        sim = dataclasses.replace(sim, t=jnp.asarray(base.t, jnp.float64))
        prep = prepare(model, params)
        state = EnvState(sim=sim, start=sim, steps=jnp.zeros((), jnp.int32),
                         inverted0=simulate.inverted_tets(model, prep, x))
        return self.observation(sim, sim), state

    def reset(self, key, params: Params | None = None):
        """Start an episode.

        Arguments:
            key: a ``jax.random`` key (the reset noise's).
            params: the scene's parameters, or ``None`` for :attr:`default_params`.

        Returns:
            ``(obs (observation_size,), EnvState)``.
        """
        return self._reset_jit(key, self._params(params))

    @functools.cached_property
    def _reset_jit(self):
        return jax.jit(self._reset)

    def _step_env(self, key, state, action, params):
        new, reward, done, info = _transition(self, params, state, action)
        return self.observation(new.sim, new.start), new, reward, done, info

    def _step(self, key, state, action, params):
        obs, new, reward, done, info = self._step_env(key, state, action, params)
        obs_reset, state_reset = self._reset(jax.random.fold_in(key, 1), params)
        pick = lambda a, b: jnp.where(done, a, b)
        return (pick(obs_reset, obs), jax.tree.map(pick, state_reset, new), reward, done, info)

    @functools.cached_property
    def _step_jit(self):
        return jax.jit(self._step)

    @functools.cached_property
    def _step_env_jit(self):
        return jax.jit(self._step_env)

    def step(self, key, state: EnvState, action, params: Params | None = None):
        """One step, and a new episode where this one ends (gymnax's auto-reset).

        Arguments:
            key: a ``jax.random`` key (the reset noise's where the episode ends).
            state: the :class:`EnvState` from :meth:`reset` or the last step.
            action: ``(action_size,)``, entries in ``[-1, 1]`` (clipped beyond).
            params: the scene's parameters, or ``None`` for :attr:`default_params`.

        Returns:
            ``(obs, state, reward, done, info)``: the next observation ``(observation_size,)``
            and state (the new episode's first where ``done``), the reward (a scalar of the
            step taken), ``done`` (bool: the episode ended at this step) and ``info``, a
            dict of ``result`` (the step's :class:`~softbody._types.RESULTS` code),
            ``iterations`` (solver iterations) and ``truncated`` (the episode ended by its
            length, not by a failure).

        Raises:
            ControlError: an action of the wrong shape, a concrete non-finite action, or a
                state that is not this environment's (before compiling).
        """
        self._check_state(state)
        self._check_action(action)
        return self._step_jit(key, state, jnp.asarray(action, jnp.float64), self._params(params))

    def step_env(self, key, state: EnvState, action, params: Params | None = None):
        """As :meth:`step`, without the auto-reset: the step as taken, also where ``done``."""
        self._check_state(state)
        self._check_action(action)
        return self._step_env_jit(key, state, jnp.asarray(action, jnp.float64), self._params(params))

    # -- batches

    @functools.cached_property
    def _batch_reset_jit(self):
        return jax.jit(jax.vmap(self._reset, in_axes=(0, None)))

    @functools.cached_property
    def _batch_step_jit(self):
        return jax.jit(jax.vmap(self._step, in_axes=(0, 0, 0, None)))

    def batch_reset(self, keys, params: Params | None = None):
        """:meth:`reset` of ``b`` environments (one ``jit(vmap(...))``), sharing ``params``.

        Arguments:
            keys: ``(b,)`` keys (``jax.random.split(key, b)``).
            params: shared parameters, or ``None``.

        Returns:
            ``(obs (b, observation_size), EnvState)`` with a leading axis ``b`` on every leaf.
        """
        return self._batch_reset_jit(keys, self._params(params))

    def batch_step(self, keys, states: EnvState, actions, params: Params | None = None):
        """:meth:`step` of ``b`` environments (one ``jit(vmap(...))``), sharing ``params``
        (so the PD matrix is factorised once for the batch).

        Arguments:
            keys: ``(b,)`` keys; states: a batched :class:`EnvState`; actions:
                ``(b, action_size)``; params: shared parameters, or ``None``.

        Returns:
            As :meth:`step`, each with a leading axis ``b``.

        Raises:
            ControlError: actions not of shape ``(b, action_size)`` matching the states'
                batch, concrete non-finite actions (before compiling).
        """
        b = jnp.shape(states.sim.x)[0] if jnp.ndim(states.sim.x) == 3 else None
        shape = jnp.shape(actions)
        if b is None or shape != (b, self.action_size):
            raise ControlError(f"actions have shape {tuple(shape)} but this batch needs ({b}, {self.action_size}): one "
                               "row of action_size entries per environment of the batched state")
        if not _is_traced(actions):
            a = np.asarray(actions)
            if not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
                row = int(np.argmax(~np.isfinite(a.astype(np.float64)).all(axis=1)))
                raise ControlError(f"actions hold NaN or inf (first in row {row}); give finite values in [-1, 1] "
                                   "(under jax.jit a non-finite action ends that episode with info['result'] == "
                                   "RESULTS.nonfinite instead)")
        return self._batch_step_jit(keys, states, jnp.asarray(actions, jnp.float64), self._params(params))


# --------------------------------------------------------------------------- Jacobians


def flatten_state(state: State) -> Array:
    """``s = concatenate([x.ravel(), v.ravel()])`` ``(6 n,)`` of a simulation state."""
    return jnp.concatenate([state.x.reshape(-1), state.v.reshape(-1)])


def unflatten_state(s: Array, like: State) -> State:
    """The :class:`~softbody.model.State` with ``x``, ``v`` from ``s`` ``(6 n,)`` and the
    rotations and time of ``like``."""
    n3 = like.x.size
    return dataclasses.replace(like, x=s[:n3].reshape(like.x.shape), v=s[n3:].reshape(like.v.shape))


class StepJacobian(eqx.Module):
    """The one-step Jacobians of :func:`step_jacobian` (``s`` as in :func:`flatten_state`,
    ``6 n`` entries; ``m`` = ``action_size``).

    Attributes:
        next_state: ``(6 n,)`` ``s'``, the state the step ends in.
        reward: the step's reward ``r``.
        ds_da: ``(6 n, m)`` ``ds'/da``.
        dr_da: ``(m,)`` ``dr/da``.
        ds_ds: ``(6 n, 6 n)`` ``ds'/ds``, or ``None`` (not asked for).
        dr_ds: ``(6 n,)`` ``dr/ds``, or ``None``.
        result: the step's :class:`~softbody._types.RESULTS` code (the Jacobians hold only
            for ``success``).
    """

    next_state: Array
    reward: Array
    ds_da: Array
    dr_da: Array
    ds_ds: Array | None
    dr_ds: Array | None
    result: Array


def _forward_model(model: Model, adjoint) -> Model:
    adjoint = adjoint if adjoint is not None else ImplicitForward()
    if not isinstance(adjoint, ImplicitForward):
        raise ControlError(f"step_jacobian needs a forward-mode adjoint (softbody.ImplicitForward), got "
                           f"{type(adjoint).__name__}")
    if isinstance(model.options.adjoint, ImplicitForward) and adjoint == model.options.adjoint:
        return model
    return dataclasses.replace(model, options=dataclasses.replace(model.options, adjoint=adjoint))


@functools.lru_cache(maxsize=32)
def _jacobian_fn(env: Env, with_state: bool, adjoint):
    model = _forward_model(env.model, adjoint)

    def one(params, state: EnvState, action):
        prep = prepare(model, params)
        rot = state.sim.rot

        def f(s, a):
            start = unflatten_state(s, state.sim)
            if model.stiffness_damping:  # the objective reads the start rotations: make them a function of x
                start = dataclasses.replace(start, rot=cold_start(deformation_gradient(model, prep.dminv, start.x)))
            else:
                start = dataclasses.replace(start, rot=rot)
            activation = env.action_map(a)
            new, info = simulate.step(model, prep, start, activation)
            r = env.reward(Transition(state=start, action=a, activation=activation, next_state=new,
                                      start=state.start))
            return (flatten_state(new), r), info

        def outputs(s, a):
            out, info = f(s, a)
            return out, (out, info)

        s0 = flatten_state(state.sim)
        # One forward-mode pass (one primal solve, one tangent solve per input column).
        argnums = (0, 1) if with_state else 1
        jac, ((s1, r), info) = jax.jacfwd(outputs, argnums=argnums, has_aux=True)(s0, action)
        if with_state:
            (ds_ds, ds_da), (dr_ds, dr_da) = jac
        else:
            (ds_da, dr_da), ds_ds, dr_ds = jac, None, None
        result = RESULTS.of(finite=jnp.all(jnp.isfinite(s1)) & jnp.isfinite(info.residual),
                            converged=info.converged, inverted=info.inverted, inverted0=state.inverted0,
                            overflow=info.overflow, tunnelled=info.tunnelled)
        return StepJacobian(next_state=s1, reward=r, ds_da=ds_da, dr_da=dr_da, ds_ds=ds_ds, dr_ds=dr_ds,
                            result=result)

    return jax.jit(one)


def step_jacobian(env: Env, state: EnvState, action, params: Params | None = None, *, wrt_state: bool = True,
                  adjoint: ImplicitForward | None = None) -> StepJacobian:
    """The exact one-step Jacobians of an environment's step by forward-mode implicit
    differentiation.

    The step is :meth:`Env.step_env`'s simulation step (no reset), differentiated at the
    converged step solution (``jax.jacfwd`` through a copy of the model with the
    :class:`~softbody.gradients.ImplicitForward` adjoint): each column solves one linear
    system with the step's Hessian. The derivative is that of the *exact* step solution,
    so build the scene with a tight ``Options(tol=...)`` (1e-8 or below) where it must match
    finite differences. Through contact the contact set (which vertices touch, stick or
    slide) is held fixed: the Jacobian is one-sided where a perturbation would switch it;
    :func:`contact_changes` tells. Actions are differentiated before the action map's clip
    (zero beyond ``[-1, 1]``). The start rotations are the state's warm start (the solution
    does not depend on them), except in scenes with stiffness damping (``beta > 0``),
    whose objective reads them: there they are recomputed from ``x`` and differentiated.

    Batch with ``jax.vmap(lambda st, a: step_jacobian(env, st, a), in_axes=(0, 0))``.

    Arguments:
        env: the :class:`Env`.
        state: its :class:`EnvState` (unbatched).
        action: ``(action_size,)``.
        params: the scene's parameters, or ``None`` for ``env.params``.
        wrt_state: also compute ``ds'/ds`` and ``dr/ds`` (``6 n`` more columns).
        adjoint: the :class:`~softbody.gradients.ImplicitForward` to use (default
            ``ImplicitForward()``, whose linear-solve tolerance follows ``Options.tol``).

    Returns:
        A :class:`StepJacobian` (``s`` laid out as :func:`flatten_state`).

    Raises:
        ControlError: the action's shape or values, or the state (as :meth:`Env.step`);
            an adjoint that is not forward mode.
    """
    env._check_state(state)
    env._check_action(action)
    _forward_model(env.model, adjoint)
    return _jacobian_fn(env, bool(wrt_state), adjoint)(env._params(params), state, jnp.asarray(action, jnp.float64))


@functools.lru_cache(maxsize=32)
def _contact_fn(env: Env):
    model = env.model

    def states(params, sim: State, activation):
        prep = prepare(model, params)
        new, info = simulate.step(model, prep, sim, activation)
        traj = simulate.Trajectory(x=jnp.stack([sim.x, new.x]), v=jnp.stack([sim.v, new.v]),
                                   info=jax.tree.map(lambda a: a[None], info))
        _, contact = simulate.contact_forces(model, params, traj, controls=activation[None], t0=sim.t)
        return contact[0]

    def changes(params, state: EnvState, action, d_action):
        a = env.action_map(action)
        b = env.action_map(action + d_action)
        both = jax.vmap(states, in_axes=(None, None, 0))(params, state.sim, jnp.stack([a, b]))
        return jnp.sum(both[0] != both[1])

    return jax.jit(changes)


def contact_changes(env: Env, state: EnvState, action, d_action, params: Params | None = None) -> Array:
    """How many vertices change contact state (none, stick, slide:
    :data:`softbody.contact.CONTACT_STATES`) between the step with ``action`` and the step
    with ``action + d_action``: 0 where the perturbation keeps the contact set that
    :func:`step_jacobian` holds fixed (its first-order prediction is then valid along
    ``d_action``), more where it crosses a switch (discard such virtual samples).

    Both steps are simulated (two steps and two contact reports,
    :func:`softbody.simulate.contact_forces`): exact, not a prediction. In a scene without
    contact the answer is 0 without simulating. Batch with ``jax.vmap``.

    Arguments:
        env, state, action: as :func:`step_jacobian`.
        d_action: ``(action_size,)`` the perturbation.
        params: the scene's parameters, or ``None``.

    Returns:
        An int scalar: the number of vertices whose contact state differs.

    Raises:
        ControlError: bad shapes or non-finite values of ``action`` or ``d_action``.
    """
    env._check_state(state)
    env._check_action(action)
    env._check_action(d_action)
    if not env.model.has_contact:
        return jnp.zeros((), jnp.int32)
    return _contact_fn(env)(env._params(params), state, jnp.asarray(action, jnp.float64),
                            jnp.asarray(d_action, jnp.float64))

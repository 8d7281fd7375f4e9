"""Closed-loop control: a small MLP policy trained through the differentiable simulation.

At every step the policy reads an observation of the current state and outputs the
activations of that step, so the rollout is the one loop of every rollout
(:func:`softbody.simulate.integrate`) with ``observe -> policy`` choosing each step's
controls (:func:`policy_rollout`); the gradient of a trajectory loss flows back through
the simulation *and* through the feedback loop.

Observations (:class:`Observations`), all dimensionless:

* per region, its centroid's displacement from the initial centroid divided by a length
  scale, and its centroid velocity divided by a velocity scale (6 numbers per region);
* per period, ``sin(2 pi t / period)`` and ``cos(2 pi t / period)`` (a clock, so a policy
  can produce gaits).

The policy (:class:`MLPPolicy`) is an :class:`equinox.nn.MLP` whose outputs go through a
sigmoid onto the actuator bounds ``[lower, upper]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from softbody.model import Model, Params, State, initial_state
from softbody.simulate import Trajectory, _check_fit, _Messages, _raise_failure, integrate, integrator_of

from .errors import ControlError
from .losses import Loss, centroid_weights, region_vertices
from .optimize import OptimizeResult, minimize

Array = jax.Array

__all__ = ["Observations", "MLPPolicy", "PolicyResult", "policy_rollout", "train_policy"]


@dataclass(frozen=True, eq=False, init=False)
class Observations:
    """What a policy sees (see the module docstring).

    Arguments:
        model: the compiled scene.
        regions: region names (or None for the whole body) whose centroids are observed.
        periods: clock periods in seconds (each adds a sine and a cosine).
        length_scale: metres per unit of observed displacement (> 0).
        velocity_scale: m/s per unit of observed velocity (> 0).

    Raises:
        ControlError: unknown regions, non-positive scales or periods, nothing to observe.
    """

    idx: tuple[np.ndarray, ...]
    weights: tuple[np.ndarray, ...]
    periods: tuple[float, ...]
    length_scale: float
    velocity_scale: float

    def __init__(self, model: Model, regions: Sequence[str | None] = (None,), *, periods: Sequence[float] = (),
                 length_scale: float = 0.01, velocity_scale: float = 0.1):
        if not regions and not periods:
            raise ControlError("observations need at least one region or one clock period")
        for name, v in (("length_scale", length_scale), ("velocity_scale", velocity_scale)):
            if not (math.isfinite(v) and v > 0):
                raise ControlError(f"{name} must be positive, got {v}")
        if not all(math.isfinite(p) and p > 0 for p in periods):
            raise ControlError(f"clock periods must be positive seconds, got {list(periods)}")
        idx = tuple(region_vertices(model, r) for r in regions)
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "weights", tuple(centroid_weights(model, i) for i in idx))
        object.__setattr__(self, "periods", tuple(float(p) for p in periods))
        object.__setattr__(self, "length_scale", float(length_scale))
        object.__setattr__(self, "velocity_scale", float(velocity_scale))

    @property
    def size(self) -> int:
        """The observation's length: ``6 * regions + 2 * periods``."""
        return 6 * len(self.idx) + 2 * len(self.periods)

    def __call__(self, state: State, state0: State) -> Array:
        """The observation ``(size,)`` of ``state``, relative to the initial state ``state0``."""
        parts = []
        for idx, w in zip(self.idx, self.weights):
            w = jnp.asarray(w)
            c, c0 = w @ state.x[idx], w @ state0.x[idx]
            parts += [(c - c0) / self.length_scale, (w @ state.v[idx]) / self.velocity_scale]
        for period in self.periods:
            phase = 2 * jnp.pi * state.t / period
            parts.append(jnp.stack([jnp.sin(phase), jnp.cos(phase)]))
        return jnp.concatenate(parts)


class MLPPolicy(eqx.Module):
    """An MLP from observations to activations in ``[lower, upper]`` (a sigmoid output).

    Arguments:
        n_inputs: the observation size (:attr:`Observations.size`).
        n_channels: the model's ``n_channels``.
        key: a ``jax.random`` key for the initial weights.
        width, depth: hidden layer width and number of hidden layers.
        lower, upper: activation bounds (a number or one per channel), ``lower < upper``.
        bias: the initial output, as a fraction of each channel's range in (0, 1): the
            last layer starts near zero so the first rollouts are gentle.

    Raises:
        ControlError: bad sizes or bounds.
    """

    mlp: eqx.nn.MLP
    lower: tuple[float, ...] = eqx.field(static=True)
    upper: tuple[float, ...] = eqx.field(static=True)

    def __init__(self, n_inputs: int, n_channels: int, key, *, width: int = 32, depth: int = 2,
                 lower=0.0, upper=1.0, bias: float = 0.5):
        if n_inputs < 1 or n_channels < 1 or width < 1 or depth < 0:
            raise ControlError(f"bad policy sizes: inputs {n_inputs}, channels {n_channels}, width {width}, "
                               f"depth {depth}")
        lo = np.broadcast_to(np.asarray(lower, np.float64), (n_channels,))
        hi = np.broadcast_to(np.asarray(upper, np.float64), (n_channels,))
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise ControlError(f"policy bounds must be finite with lower < upper, got {lo}, {hi}")
        if not 0 < bias < 1:
            raise ControlError(f"bias must lie in (0, 1), got {bias}")
        mlp = eqx.nn.MLP(n_inputs, n_channels, width, depth, activation=jnp.tanh, key=key)
        last = mlp.layers[-1]
        mlp = eqx.tree_at(lambda m: (m.layers[-1].weight, m.layers[-1].bias), mlp,
                          (0.1 * last.weight, jnp.full(n_channels, math.log(bias / (1 - bias)))))
        self.mlp = mlp
        self.lower = tuple(float(v) for v in lo)
        self.upper = tuple(float(v) for v in hi)

    def __call__(self, obs: Array) -> Array:
        """Activations ``(n_channels,)`` for the observation ``obs``."""
        lo, hi = jnp.asarray(self.lower), jnp.asarray(self.upper)
        return lo + (hi - lo) * jax.nn.sigmoid(self.mlp(obs))


def _check_policy(model: Model, policy, observations: Observations) -> None:
    try:
        out = jax.eval_shape(policy, jax.ShapeDtypeStruct((observations.size,), jnp.float64))
    except (TypeError, ValueError) as err:
        raise ControlError(f"the policy does not accept observations of size {observations.size}: {err}") from None
    if out.shape != (model.n_channels,):
        raise ControlError(f"the policy maps {observations.size} observations to shape {out.shape}; the model "
                           f"has {model.n_channels} channels ({list(model.channel_names)})")


def policy_rollout(model: Model, params: Params, policy, observations: Observations, n_steps: int,
                   state0: State | None = None, *, throw: bool = True) -> tuple[Trajectory, Array]:
    """Simulate ``n_steps`` with the policy in the loop.

    Arguments:
        model, params: the compiled scene.
        policy: a callable ``obs (size,) -> activations (n_channels,)`` (e.g. :class:`MLPPolicy`).
        observations: the :class:`Observations` it reads.
        n_steps: the number of steps (>= 1).
        state0: the initial state (default: the rest shape).
        throw: raise for the first step whose result is not success (see
            :func:`softbody.simulate.rollout`, the same messages); ``False`` returns the
            codes in ``trajectory.info.result`` instead.

    Returns:
        ``(trajectory, controls)``: the :class:`~softbody.simulate.Trajectory` and the
        ``(n_steps, n_channels)`` activations the policy chose.

    Raises:
        ControlError: ``n_steps`` not a whole number >= 1, or a policy output of the wrong shape.
        softbody.model.SceneError: ``params`` or ``state0`` of another model (shapes named).
        softbody.simulate.SimulationError: with ``throw=True``, a step stopped at the
            iteration cap, became non-finite or inverted more tets than ``state0`` had;
            traced (inside :func:`train_policy`'s gradient) the same message is raised at
            run time as an equinox error.
    """
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)):
        raise ControlError(f"n_steps must be a whole number of steps, got {n_steps!r}; round a computed count, "
                           "e.g. n_steps=round(duration / dt)")
    if n_steps < 1:
        raise ControlError(f"n_steps must be >= 1, got {n_steps}")
    _check_fit(model, params=params, state0=state0)
    state0 = initial_state(model, params) if state0 is None else state0
    _check_policy(model, policy, observations)
    traj, controls, failed, branch = _policy_rollout(model, params, policy, observations, int(n_steps), state0)
    if not throw:
        return traj, controls
    return _raise_failure((traj, controls), failed, branch,
                          _Messages(integrator_of(model).templates(model, "policy_rollout"), int(n_steps)))


@eqx.filter_jit
def _policy_rollout(model, params, policy, observations, n_steps, state0):
    def choose(state, _):
        return policy(observations(state, state0)), None

    return integrate(integrator_of(model), model, params, state0, n_steps, choose=choose)


@dataclass
class PolicyResult:
    """The outcome of :func:`train_policy`.

    Attributes:
        policy: the best policy found.
        best_loss: its loss.
        loss: ``(k,)`` loss history (one simulation each).
        optimization: the full :class:`~softbody.control.optimize.OptimizeResult`.
    """

    policy: eqx.Module
    best_loss: float
    loss: np.ndarray
    optimization: OptimizeResult


def train_policy(
    model: Model,
    params: Params,
    policy: eqx.Module,
    observations: Observations,
    loss: Loss,
    n_steps: int,
    *,
    state0: State | None = None,
    optimizer: optax.GradientTransformation | None = None,
    n_iter: int = 100,
    checkpoint: str | Path | None = None,
    resume: bool = True,
    callback=None,
    progress: bool = True,
) -> PolicyResult:
    """Train a policy's weights by gradient descent through closed-loop rollouts.

    Arguments:
        model, params: the compiled scene.
        policy: an equinox module (e.g. :class:`MLPPolicy`); its inexact arrays are trained.
        observations: what it reads.
        loss: ``loss(traj, controls) -> scalar`` of the closed-loop rollout.
        n_steps: the horizon.
        state0: the initial state (default: the rest shape).
        optimizer: an optax transformation (default ``optax.adam(1e-2)``).
        n_iter: gradient evaluations (simulations).
        checkpoint, resume: see :func:`~softbody.control.optimize.minimize`.
        callback: ``callback(k, weights_k, loss_k)`` after each evaluation.
        progress: show a progress bar.

    Returns:
        :class:`PolicyResult`.

    Raises:
        ControlError: see :func:`policy_rollout` and :func:`~softbody.control.optimize.minimize`.
    """
    weights, static = eqx.partition(policy, eqx.is_inexact_array)
    state0 = initial_state(model, params) if state0 is None else state0
    _check_policy(model, policy, observations)

    def objective(w):
        traj, controls = policy_rollout(model, params, eqx.combine(w, static), observations, n_steps, state0)
        return loss(traj, controls)

    fingerprint = {"kind": "policy", "n_steps": int(n_steps), "observations": observations.size,
                   "channels": list(model.channel_names)}
    res = minimize(objective, weights, optimizer=optimizer or optax.adam(1e-2), n_iter=n_iter,
                   checkpoint=checkpoint, resume=resume, fingerprint=fingerprint, callback=callback,
                   progress=progress, description="policy training")
    return PolicyResult(policy=eqx.combine(res.best_theta, static), best_loss=res.best_loss, loss=res.loss,
                        optimization=res)

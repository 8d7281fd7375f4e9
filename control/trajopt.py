"""Open-loop trajectory optimisation: activations over time, found by gradient descent
through the simulation.

**Parameterisation** (:class:`ControlGrid`). The decision variables are ``K`` knots per
channel; the ``(T, C)`` per-step controls are a fixed linear map of the knot values
(``controls = W @ knots``, ``W`` of shape ``(T, K)``):

* ``n_knots=None``: one knot per step (``W = I``);
* ``n_knots=K``: knots evenly spread from the first step to the last, linear
  interpolation between them (``K = 1``: constant controls);
* ``period=P``: ``K`` knots spread over one period of ``P`` steps, linear interpolation
  that wraps around, repeated for the whole horizon (gaits).

**Bounds** ``lower <= a <= upper`` (per channel; ``[0, 1]`` for muscles, pascals for
cavities) are kept by one of two documented schemes, chosen by ``bounding``:

* ``"sigmoid"`` (default): the variables are logits ``theta``, knot values
  ``lower + (upper - lower) sigmoid(theta)``. Unconstrained optimisation; the bounds are
  approached but never reached, and gradients shrink near them.
* ``"clip"``: the variables are the knot values themselves, projected onto the bounds
  after every update (projected gradient descent). Bounds are reached exactly; Adam's
  step size is then in activation units.

Bounds act on the knots; linear interpolation of in-bound knots stays in bounds.

:class:`ControlProblem` ties a scene, a loss and a grid into ``objective(theta)``;
:func:`optimize_controls` minimises it with optax (Adam by default) and
:func:`softbody.control.baselines.cmaes` with CMA-ES on the same variables.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from softbody.model import Model, Params, State, initial_state
from softbody.simulate import Trajectory, rollout

from .errors import ControlError
from .losses import Loss
from .optimize import OptimizeResult, minimize

Array = jax.Array

__all__ = ["ControlGrid", "ControlProblem", "TrajOptResult", "optimize_controls"]


def _interpolation(n_steps: int, n_knots: int, period: int | None) -> np.ndarray:
    """The ``(n_steps, n_knots)`` linear-interpolation matrix (rows sum to 1)."""
    w = np.zeros((n_steps, n_knots))
    steps = np.arange(n_steps)
    if period is not None:
        u = (steps % period) * n_knots / period
        j0 = np.floor(u).astype(int) % n_knots
        f = u - np.floor(u)
        np.add.at(w, (steps, j0), 1.0 - f)
        np.add.at(w, (steps, (j0 + 1) % n_knots), f)
    elif n_knots == 1:
        w[:, 0] = 1.0
    else:
        u = steps * (n_knots - 1) / max(n_steps - 1, 1)
        j0 = np.minimum(np.floor(u).astype(int), n_knots - 2)
        f = u - j0
        w[steps, j0] = 1.0 - f
        w[steps, j0 + 1] = f
    return w


@dataclass(frozen=True, eq=False, init=False)
class ControlGrid:
    """How decision variables ``theta`` ``(K, C)`` map to per-step controls ``(T, C)``.

    See the module docstring for the schemes.

    Arguments:
        n_steps: the horizon ``T`` (>= 1).
        n_channels: ``C``, the model's ``n_channels``.
        n_knots: knots per channel ``K`` (``None``: one per step; else ``1 <= K <= T``,
            or ``K <= period`` with a period).
        period: steps per period for periodic controls (``None``: not periodic).
        lower, upper: bounds, a number or one per channel; ``lower < upper``, finite for
            ``"sigmoid"``.
        bounding: ``"sigmoid"`` or ``"clip"``.

    Raises:
        ControlError: inconsistent sizes, bounds or an unknown ``bounding``.
    """

    n_steps: int
    n_channels: int
    n_knots: int
    period: int | None
    lower: np.ndarray
    upper: np.ndarray
    bounding: str
    matrix: np.ndarray  # (T, K)

    def __init__(self, n_steps: int, n_channels: int, n_knots: int | None = None, *, period: int | None = None,
                 lower=0.0, upper=1.0, bounding: str = "sigmoid"):
        n_steps, n_channels = int(n_steps), int(n_channels)
        if n_steps < 1 or n_channels < 1:
            raise ControlError(f"a control grid needs n_steps >= 1 and n_channels >= 1, got {n_steps}, {n_channels}")
        if period is not None and not 1 <= int(period):
            raise ControlError(f"period must be a positive number of steps, got {period}")
        span = n_steps if period is None else int(period)
        n_knots = span if n_knots is None else int(n_knots)
        if not 1 <= n_knots <= span:
            raise ControlError(f"n_knots must lie in [1, {span}] ({'the period' if period else 'n_steps'}), "
                               f"got {n_knots}")
        if bounding not in ("sigmoid", "clip"):
            raise ControlError(f"bounding must be 'sigmoid' or 'clip', got {bounding!r}")
        lower = np.broadcast_to(np.asarray(lower, np.float64), (n_channels,)).copy()
        upper = np.broadcast_to(np.asarray(upper, np.float64), (n_channels,)).copy()
        if np.any(np.isnan(lower)) or np.any(np.isnan(upper)) or not np.all(lower < upper):
            raise ControlError(f"bounds must satisfy lower < upper per channel, got {lower}, {upper}")
        if bounding == "sigmoid" and not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise ControlError("sigmoid bounding needs finite bounds; use bounding='clip' for unbounded channels")
        for name, value in (("n_steps", n_steps), ("n_channels", n_channels), ("n_knots", n_knots),
                            ("period", None if period is None else int(period)), ("lower", lower),
                            ("upper", upper), ("bounding", bounding)):
            object.__setattr__(self, name, value)
        object.__setattr__(self, "matrix", _interpolation(n_steps, n_knots, self.period))

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of the decision variables, ``(K, C)``."""
        return (self.n_knots, self.n_channels)

    def knots(self, theta: Array) -> Array:
        """Knot values ``(K, C)`` (in bounds) of the variables ``theta`` ``(K, C)``."""
        if self.bounding == "sigmoid":
            lo, hi = jnp.asarray(self.lower), jnp.asarray(self.upper)
            return lo + (hi - lo) * jax.nn.sigmoid(theta)
        return theta

    def controls(self, theta: Array) -> Array:
        """Per-step controls ``(T, C)`` of the variables ``theta`` ``(K, C)``.

        Raises:
            ControlError: ``theta`` of the wrong shape.
        """
        if tuple(jnp.shape(theta)) != self.shape:
            raise ControlError(f"control variables must have shape {self.shape} (knots, channels), "
                               f"got {tuple(jnp.shape(theta))}")
        return jnp.asarray(self.matrix) @ self.knots(theta)

    def project(self, theta: Array) -> Array:
        """The feasible point nearest ``theta`` (clipping for ``"clip"``; identity for ``"sigmoid"``)."""
        if self.bounding == "clip":
            return jnp.clip(theta, jnp.asarray(self.lower), jnp.asarray(self.upper))
        return theta

    def init(self, value=0.5) -> Array:
        """Variables ``(K, C)`` whose knots equal ``value``.

        Arguments:
            value: a number, one per channel ``(C,)``, or knot values ``(K, C)``, within
                the bounds. For ``"sigmoid"``, values closer than 1e-6 of the range to a
                bound are moved that far inside (a logit of exactly a bound is infinite).

        Raises:
            ControlError: a shape that does not broadcast to ``(K, C)``, or values out of bounds.
        """
        v = np.asarray(value, np.float64)
        try:
            v = np.broadcast_to(v, self.shape).copy()
        except ValueError:
            raise ControlError(f"initial controls must be a number, ({self.n_channels},) or {self.shape}, "
                               f"got shape {v.shape}") from None
        if not np.all(np.isfinite(v)) or np.any(v < self.lower) or np.any(v > self.upper):
            raise ControlError(f"initial controls must lie within the bounds [{self.lower}, {self.upper}]")
        if self.bounding == "clip":
            return jnp.asarray(v)
        span = self.upper - self.lower
        u = np.clip((v - self.lower) / span, 1e-6, 1 - 1e-6)
        return jnp.asarray(np.log(u) - np.log1p(-u))

    def describe(self) -> dict:
        """A JSON-able summary (stored in checkpoints)."""
        return {"n_steps": self.n_steps, "n_channels": self.n_channels, "n_knots": self.n_knots,
                "period": self.period, "lower": self.lower.tolist(), "upper": self.upper.tolist(),
                "bounding": self.bounding}


class ControlProblem:
    """A scene, a loss and a control grid: ``objective(theta) = loss(rollout(controls(theta)), controls)``.

    Arguments:
        model, params: the compiled scene (:func:`softbody.model.build`).
        loss: a :class:`~softbody.control.losses.Loss` (or any ``(traj, controls) -> scalar``).
        grid: the :class:`ControlGrid`.
        state0: the initial state (default: rest, :func:`~softbody.model.initial_state`).
        forces: optional ``(T, n, 3)`` external forces, N.

    Raises:
        ControlError: the grid's channels or horizon do not match the model or forces,
            the model has no actuators, or the loss is not callable.
    """

    def __init__(self, model: Model, params: Params, loss: Loss, grid: ControlGrid, *,
                 state0: State | None = None, forces=None):
        if model.n_channels == 0:
            raise ControlError("the model has no actuator channels to optimise; build it with actuators=[...]")
        if grid.n_channels != model.n_channels:
            raise ControlError(f"the control grid has {grid.n_channels} channels but the model has "
                               f"{model.n_channels} ({list(model.channel_names)})")
        if not callable(loss):
            raise ControlError(f"loss must be callable as loss(traj, controls), got {type(loss).__name__}")
        if forces is not None:
            forces = jnp.asarray(forces, jnp.float64)
            if forces.shape != (grid.n_steps, model.n_vertices, 3):
                raise ControlError(f"forces must have shape ({grid.n_steps}, {model.n_vertices}, 3), "
                                   f"got {tuple(forces.shape)}")
        self.model, self.params, self.loss, self.grid = model, params, loss, grid
        self.state0 = initial_state(model, params) if state0 is None else state0
        self.forces = forces

    def controls(self, theta: Array) -> Array:
        """Per-step controls ``(T, C)`` of ``theta``."""
        return self.grid.controls(theta)

    def simulate(self, theta: Array, params: Params | None = None) -> Trajectory:
        """The rollout driven by ``theta`` (with ``params`` instead of the problem's, if given)."""
        return rollout(self.model, self.params if params is None else params, self.state0,
                       self.controls(theta), self.forces, self.grid.n_steps)

    def objective(self, theta: Array) -> Array:
        """The scalar loss of the rollout driven by ``theta`` (traceable, differentiable)."""
        controls = self.controls(theta)
        traj = rollout(self.model, self.params, self.state0, controls, self.forces, self.grid.n_steps)
        return self.loss(traj, controls)

    def init(self, value=0.5) -> Array:
        """Variables whose knots equal ``value`` (see :meth:`ControlGrid.init`)."""
        return self.grid.init(value)


@dataclass
class TrajOptResult:
    """The outcome of :func:`optimize_controls`.

    Attributes:
        controls: ``(T, C)`` the best controls found.
        knots: ``(K, C)`` their knot values.
        theta: ``(K, C)`` their variables.
        best_loss: their loss.
        loss: ``(k,)`` loss history (one entry per gradient evaluation = simulation).
        grad_norm: ``(k,)`` gradient norms.
        optimization: the full :class:`~softbody.control.optimize.OptimizeResult`.
    """

    controls: np.ndarray
    knots: np.ndarray
    theta: np.ndarray
    best_loss: float
    loss: np.ndarray
    grad_norm: np.ndarray
    optimization: OptimizeResult

    @property
    def simulations(self) -> int:
        """Number of simulations run (each a forward rollout and its adjoint)."""
        return self.optimization.iterations

    @property
    def wall_time(self) -> float:
        return self.optimization.wall_time


def optimize_controls(
    problem: ControlProblem,
    init: Any = 0.5,
    *,
    optimizer: optax.GradientTransformation | None = None,
    n_iter: int = 100,
    target: float | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = True,
    checkpoint_every: int = 10,
    callback=None,
    progress: bool = True,
) -> TrajOptResult:
    """Optimise open-loop controls by gradient descent through the simulation.

    Arguments:
        problem: the :class:`ControlProblem`.
        init: initial knot values (see :meth:`ControlGrid.init`), or variables ``(K, C)``
            given as a JAX array (e.g. a previous result's ``theta``).
        optimizer: an optax transformation (default ``optax.adam(0.05)``).
        n_iter: gradient evaluations (simulations).
        target: stop once the loss is <= ``target``.
        checkpoint, resume, checkpoint_every: see :func:`~softbody.control.optimize.minimize`.
        callback: ``callback(k, theta_k, loss_k)`` after each evaluation.
        progress: show a progress bar.

    Returns:
        :class:`TrajOptResult`.

    Raises:
        ControlError: bad initial values, a non-finite loss or gradient, a checkpoint of
            another problem.
    """
    grid = problem.grid
    theta0 = init if isinstance(init, jax.Array) else problem.init(init)
    if tuple(theta0.shape) != grid.shape:
        raise ControlError(f"initial variables must have shape {grid.shape}, got {tuple(theta0.shape)}")
    fingerprint = {"kind": "controls", "grid": grid.describe(), "n_vertices": problem.model.n_vertices,
                   "channels": list(problem.model.channel_names)}
    res = minimize(problem.objective, grid.project(theta0), optimizer=optimizer, n_iter=n_iter, project=grid.project,
                   target=target, checkpoint=checkpoint, resume=resume, checkpoint_every=checkpoint_every,
                   fingerprint=fingerprint, callback=callback, progress=progress, description="trajectory opt")
    best = res.best_theta
    return TrajOptResult(controls=np.asarray(grid.controls(best)), knots=np.asarray(grid.knots(best)),
                         theta=np.asarray(best), best_loss=res.best_loss, loss=res.loss, grad_norm=res.grad_norm,
                         optimization=res)

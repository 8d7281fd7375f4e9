"""Co-design: optimise a robot's design and its controls together.

The variables are a dict pytree ``theta`` with the control variables of a
:class:`~softbody.control.trajopt.ControlGrid` (key ``"controls"``) and whichever design
groups a :class:`Design` enables:

* ``"weights"``: the per-tet fibre weights of chosen muscle terms (where the muscle is,
  and how strong). Constraint: each term's weights lie in ``[0, max_weight]`` and sum to
  its actuator ``budget``: after every update they are projected onto that capped simplex
  (Euclidean projection ``w = clip(v - tau, 0, max_weight)``, ``tau`` found by bisection).
* ``"log_E"``: the log of Young's modulus of chosen materials, clipped to
  ``[log E_min, log E_max]``.
* ``"morph"``: rest-shape offsets of a region's free vertices, in units of
  ``max_morph`` (m); each vertex's offset is clipped to the ball of radius 1, so no vertex
  moves more than ``max_morph``. Keep it well below the element size: larger offsets can
  invert tets.

All groups have order-one variables, so one Adam learning rate suits them together.
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

from softbody.actuators import Muscle
from softbody.model import Model, Params, State, initial_state
from softbody.simulate import Trajectory, rollout

from .errors import ControlError
from .losses import Loss, region_vertices
from .optimize import OptimizeResult, minimize
from .trajopt import ControlGrid

Array = jax.Array

__all__ = ["Design", "CoDesignProblem", "CoDesignResult", "codesign", "project_capped_simplex"]


def project_capped_simplex(v: Array, total: float, cap: float = math.inf) -> Array:
    """Euclidean projection of ``v`` ``(m,)`` onto ``{w : 0 <= w <= cap, sum w = total}``.

    The projection is ``clip(v - tau, 0, cap)`` with the ``tau`` that meets the sum,
    found by bisection (the sum decreases monotonically in ``tau``). Needs
    ``0 <= total <= m cap``.
    """
    v = jnp.asarray(v)
    lo = jnp.min(v) - min(cap, total)  # every entry at min(cap, total) or more: the sum is >= total
    hi = jnp.max(v)  # every entry 0

    def body(_, bracket):
        lo, hi = bracket
        mid = 0.5 * (lo + hi)
        above = jnp.sum(jnp.clip(v - mid, 0.0, cap)) > total
        return jnp.where(above, mid, lo), jnp.where(above, hi, mid)

    lo, hi = jax.lax.fori_loop(0, 200, body, (lo, hi))
    return jnp.clip(v - 0.5 * (lo + hi), 0.0, cap)


@dataclass(frozen=True, eq=False, init=False)
class Design:
    """The design groups to optimise and their constraints.

    Arguments:
        model, params: the compiled scene and its starting parameters.
        muscles: indices (in ``model.terms``) of the :class:`~softbody.actuators.Muscle`
            terms whose fibre weights are designed, or ``True`` for all of them.
        budget: each designed term's total weight (a number or one per term; default:
            the sum of its starting weights).
        max_weight: the cap on a tet's weight (default: no cap).
        stiffness: material names (``model.material_names``) whose ``E`` is designed.
        stiffness_range: ``(E_min, E_max)`` in Pa, ``0 < E_min < E_max``.
        morph: a region whose free vertices may move, or None.
        max_morph: the largest offset of a vertex, m (> 0 with ``morph``).

    Raises:
        ControlError: nothing to design, terms that are not muscles, infeasible budgets,
            unknown materials or regions, starting values outside the constraints.
    """

    muscles: tuple[int, ...]
    budget: tuple[float, ...]
    max_weight: float
    materials: tuple[int, ...]
    log_range: tuple[float, float]
    morph_vertices: np.ndarray | None
    max_morph: float

    def __init__(self, model: Model, params: Params, *, muscles: Sequence[int] | bool = (), budget=None,
                 max_weight: float | None = None, stiffness: Sequence[str] = (),
                 stiffness_range: tuple[float, float] = (1e4, 1e8), morph: str | None = None,
                 max_morph: float = 0.0):
        if muscles is True:
            muscles = [i for i, t in enumerate(model.terms) if isinstance(t, Muscle)]
        muscles = tuple(int(i) for i in (muscles or ()))
        for i in muscles:
            if not (0 <= i < len(model.terms)) or not isinstance(model.terms[i], Muscle):
                raise ControlError(f"muscles[{i}] is not a Muscle term of the model "
                                   f"(terms: {[type(t).__name__ for t in model.terms]})")
        cap = math.inf if max_weight is None else float(max_weight)
        if not cap > 0:
            raise ControlError(f"max_weight must be positive, got {max_weight}")
        start = [np.asarray(params.actuators[i].weights) for i in muscles]
        budgets = [float(w.sum()) for w in start] if budget is None else list(
            np.broadcast_to(np.asarray(budget, np.float64), (len(muscles),)))
        for i, w, b in zip(muscles, start, budgets):
            if not (math.isfinite(b) and 0 < b <= len(w) * cap):
                raise ControlError(f"muscle term {i}: the budget {b} must be positive and at most "
                                   f"{len(w)} tets x max_weight {cap}")
        names = list(model.material_names)
        unknown = [s for s in stiffness if s not in names]
        if unknown:
            raise ControlError(f"unknown materials {unknown}; the model has {names}")
        e_lo, e_hi = (float(v) for v in stiffness_range)
        if not (0 < e_lo < e_hi < math.inf):
            raise ControlError(f"stiffness_range must satisfy 0 < E_min < E_max, got {stiffness_range}")
        morph_vertices = None
        if morph is not None:
            if not (math.isfinite(max_morph) and max_morph > 0):
                raise ControlError(f"max_morph must be a positive distance in metres, got {max_morph}")
            idx = region_vertices(model, morph)
            morph_vertices = np.setdiff1d(idx, model.fixed)
            if morph_vertices.size == 0:
                raise ControlError(f"region {morph!r} has no free vertices to morph")
        if not (muscles or stiffness or morph is not None):
            raise ControlError("nothing to design: give muscles, stiffness or morph")
        object.__setattr__(self, "muscles", muscles)
        object.__setattr__(self, "budget", tuple(budgets))
        object.__setattr__(self, "max_weight", cap)
        object.__setattr__(self, "materials", tuple(names.index(s) for s in stiffness))
        object.__setattr__(self, "log_range", (math.log(e_lo), math.log(e_hi)))
        object.__setattr__(self, "morph_vertices", morph_vertices)
        object.__setattr__(self, "max_morph", float(max_morph))

    def describe(self) -> dict:
        """A JSON-able summary (stored in checkpoints)."""
        return {"muscles": list(self.muscles), "budget": list(self.budget), "max_weight": str(self.max_weight),
                "materials": list(self.materials), "log_range": list(self.log_range),
                "morph_vertices": None if self.morph_vertices is None else len(self.morph_vertices),
                "max_morph": self.max_morph}


class CoDesignProblem:
    """Design and controls together: ``objective(theta) = loss(rollout(params(theta), controls(theta)))``.

    Arguments:
        model, params: the compiled scene and its starting parameters.
        loss: ``loss(traj, controls) -> scalar``.
        grid: the :class:`~softbody.control.trajopt.ControlGrid` of the controls.
        design: the :class:`Design`.
        state0: the initial state (default: at rest in the current rest shape; with a
            morph design the rest shape changes, so the initial state must be the default).

    Raises:
        ControlError: a grid that does not match the model, or ``state0`` with a morph design.
    """

    def __init__(self, model: Model, params: Params, loss: Loss, grid: ControlGrid, design: Design, *,
                 state0: State | None = None):
        if grid.n_channels != model.n_channels:
            raise ControlError(f"the control grid has {grid.n_channels} channels but the model has "
                               f"{model.n_channels} ({list(model.channel_names)})")
        if state0 is not None and design.morph_vertices is not None:
            raise ControlError("with a morph design the initial state is the (designed) rest shape; "
                               "do not pass state0")
        self.model, self.params, self.loss, self.grid, self.design = model, params, loss, grid, design
        self.state0 = state0

    def init(self, controls=0.5, params: Params | None = None) -> dict:
        """Variables for starting ``controls`` (see :meth:`ControlGrid.init`) and the design in
        ``params`` (default: the problem's), projected onto the constraints."""
        p = self.params if params is None else params
        d = self.design
        theta = {"controls": self.grid.init(controls)}
        if d.muscles:
            theta["weights"] = tuple(jnp.asarray(p.actuators[i].weights) for i in d.muscles)
        if d.materials:
            theta["log_E"] = jnp.log(p.E[jnp.asarray(d.materials)])
        if d.morph_vertices is not None:
            theta["morph"] = p.morph[jnp.asarray(d.morph_vertices)] / d.max_morph
        return self.project(theta)

    def project(self, theta: dict) -> dict:
        """The feasible point nearest ``theta`` (group by group)."""
        d = self.design
        out = dict(theta, controls=self.grid.project(theta["controls"]))
        if "weights" in theta:
            out["weights"] = tuple(project_capped_simplex(w, b, d.max_weight)
                                   for w, b in zip(theta["weights"], d.budget))
        if "log_E" in theta:
            out["log_E"] = jnp.clip(theta["log_E"], *d.log_range)
        if "morph" in theta:
            m = theta["morph"]
            norm = jnp.sqrt(jnp.sum(m * m, axis=1, keepdims=True))
            out["morph"] = m / jnp.maximum(norm, 1.0)
        return out

    def params_of(self, theta: dict) -> Params:
        """The scene parameters of the design in ``theta``."""
        d, p = self.design, self.params
        if "weights" in theta:
            actuators = list(p.actuators)
            for i, w in zip(d.muscles, theta["weights"]):
                actuators[i] = eqx.tree_at(lambda a: a.weights, actuators[i], w)
            p = eqx.tree_at(lambda q: q.actuators, p, tuple(actuators))
        if "log_E" in theta:
            p = eqx.tree_at(lambda q: q.E, p, p.E.at[jnp.asarray(d.materials)].set(jnp.exp(theta["log_E"])))
        if "morph" in theta:
            morph = p.morph.at[jnp.asarray(d.morph_vertices)].set(theta["morph"] * d.max_morph)
            p = eqx.tree_at(lambda q: q.morph, p, morph)
        return p

    def simulate(self, theta: dict) -> Trajectory:
        """The rollout of the design and controls in ``theta``."""
        params = self.params_of(theta)
        state0 = _rest_state(self.model, params) if self.state0 is None else self.state0
        return rollout(self.model, params, state0, self.grid.controls(theta["controls"]), None, self.grid.n_steps)

    def objective(self, theta: dict) -> Array:
        """The loss of the rollout of ``theta`` (traceable, differentiable)."""
        return self.loss(self.simulate(theta), self.grid.controls(theta["controls"]))


def _rest_state(model: Model, params: Params) -> State:
    """The state at rest in the (morphed) rest shape, differentiable in the positions.

    The rotations are only the first step's warm start: they are taken without a
    derivative (differentiating their cold-start iteration adds nothing and compiles slowly).
    """
    state = initial_state(model, jax.lax.stop_gradient(params))
    return eqx.tree_at(lambda s: s.x, state, jnp.asarray(model.mesh.points) + params.morph)


@dataclass
class CoDesignResult:
    """The outcome of :func:`codesign`.

    Attributes:
        params: the best design's scene parameters.
        controls: ``(T, C)`` its controls.
        theta: its variables.
        best_loss: its loss.
        loss: ``(k,)`` loss history (one simulation each).
        optimization: the full :class:`~softbody.control.optimize.OptimizeResult`.
    """

    params: Params
    controls: np.ndarray
    theta: dict
    best_loss: float
    loss: np.ndarray
    optimization: OptimizeResult


def codesign(
    problem: CoDesignProblem,
    init=0.5,
    *,
    optimizer: optax.GradientTransformation | None = None,
    n_iter: int = 100,
    checkpoint: str | Path | None = None,
    resume: bool = True,
    callback=None,
    progress: bool = True,
) -> CoDesignResult:
    """Optimise design and controls together by projected gradient descent.

    Arguments:
        problem: the :class:`CoDesignProblem`.
        init: starting control knots (see :meth:`ControlGrid.init`) or a full variables
            dict (e.g. a previous result's ``theta``).
        optimizer: an optax transformation (default ``optax.adam(0.05)``).
        n_iter: gradient evaluations (simulations).
        checkpoint, resume: see :func:`~softbody.control.optimize.minimize`.
        callback: ``callback(k, theta_k, loss_k)`` after each evaluation.
        progress: show a progress bar.

    Returns:
        :class:`CoDesignResult`.
    """
    theta0 = problem.project(init) if isinstance(init, dict) else problem.init(init)
    fingerprint = {"kind": "codesign", "grid": problem.grid.describe(), "design": problem.design.describe(),
                   "n_vertices": problem.model.n_vertices}
    res = minimize(problem.objective, theta0, optimizer=optimizer, n_iter=n_iter, project=problem.project,
                   checkpoint=checkpoint, resume=resume, fingerprint=fingerprint, callback=callback,
                   progress=progress, description="co-design")
    best = res.best_theta
    return CoDesignResult(params=problem.params_of(best), controls=np.asarray(problem.grid.controls(best["controls"])),
                          theta=best, best_loss=res.best_loss, loss=res.loss, optimization=res)

"""Derivative-free baseline: CMA-ES (the ``cma`` package) on the same variables as the
gradient methods, counting simulations, to measure what gradients buy.

:func:`cmaes` minimises any scalar function of a pytree ``theta`` (for instance
:meth:`softbody.control.trajopt.ControlProblem.objective`, or a system-identification
cost) with the ask-and-tell interface of :class:`cma.CMAEvolutionStrategy`. One
objective evaluation is one simulation; the history records, after every generation, the
number of simulations so far and the best point and value found so far, so that a
derivative-free run and a gradient run can be compared on the same simulation budget.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .errors import ControlError
from .optimize import progress_bar

__all__ = ["CMAResult", "cmaes"]


@dataclass
class CMAResult:
    """The outcome of :func:`cmaes`.

    Attributes:
        best_theta: the best evaluated point (a pytree like ``theta0``).
        best_loss: its objective.
        simulations: ``(g,)`` simulations run after each generation.
        best_loss_history: ``(g,)`` best objective so far after each generation.
        best_x_history: ``(g, d)`` the best point so far (flattened) after each generation.
        failed: number of evaluations whose simulation failed.
        elapsed: ``(g,)`` wall-clock seconds after each generation (compilation included).
        unravel: maps a flat ``(d,)`` vector back to a pytree like ``theta0``.
    """

    best_theta: Any
    best_loss: float
    simulations: np.ndarray
    best_loss_history: np.ndarray
    best_x_history: np.ndarray
    elapsed: np.ndarray
    failed: int
    unravel: Callable

    @property
    def n_simulations(self) -> int:
        return int(self.simulations[-1]) if len(self.simulations) else 0


def cmaes(
    fun: Callable[[Any], jax.Array] | None,
    theta0,
    *,
    sigma0: float,
    budget: int,
    popsize: int | None = None,
    lower: float | np.ndarray | None = None,
    upper: float | np.ndarray | None = None,
    seed: int = 0,
    target: float | None = None,
    stop: Callable[[Any, float], bool] | None = None,
    progress: bool = True,
    evaluate: Callable[[list[np.ndarray]], Sequence[float]] | None = None,
) -> CMAResult:
    """Minimise ``fun(theta)`` with CMA-ES within a budget of simulations.

    Arguments:
        fun: scalar, JAX-traceable function of the pytree ``theta`` (compiled once).
            A simulation that fails (a non-finite value, or any of the simulator's step
            errors: non-finite state, the iteration cap, inverted tets) counts as a
            simulation and is ranked below every finite value seen, so the search moves
            away from it.
        theta0: the initial mean (a pytree of float arrays).
        sigma0: the initial step size, in the units of ``theta`` (> 0).
        budget: the maximum number of evaluations (simulations); the last generation is
            truncated to fit.
        popsize: the population size (default: CMA-ES's ``4 + 3 ln d``).
        lower, upper: box bounds on the flattened variables (a number or ``(d,)``), or None.
        seed: the random seed (> 0 values give reproducible runs; 0 is mapped to 1).
        target: stop when the best value is <= ``target``.
        stop: ``stop(best_theta, best_loss) -> bool`` after each generation (e.g. a
            parameter-error threshold in a study).
        progress: show a progress bar.
        evaluate: ``evaluate(xs) -> values``, the objective of a whole population at once
            (a list of flat ``(d,)`` candidates, in the order CMA-ES asked for them), e.g.
            on sweep workers: :func:`softbody.control.sweep.population_evaluator`. ``nan``
            marks a failed simulation. Default: ``fun`` compiled here, one candidate after
            another. The search is the same either way: the same seed asks for the same
            candidates, so equal values give an equal run. ``fun`` may be None with it.

    Returns:
        :class:`CMAResult`.

    Raises:
        ControlError: ``budget < 1`` or ``sigma0 <= 0``, or neither ``fun`` nor ``evaluate``.
    """
    import cma

    if int(budget) < 1:
        raise ControlError(f"budget must be >= 1 simulation, got {budget}")
    if not (math.isfinite(sigma0) and sigma0 > 0):
        raise ControlError(f"sigma0 must be a positive step size, got {sigma0}")
    if fun is None and evaluate is None:
        raise ControlError("give the objective fun, or evaluate for whole populations")
    x0, unravel = ravel_pytree(jax.tree.map(jnp.asarray, theta0))
    d = x0.size
    if evaluate is None:
        value = jax.jit(lambda x: fun(unravel(x)))

        def evaluate(xs):
            return [_evaluate(value, x) for x in xs]
    opts = {"seed": int(seed) or 1, "verbose": -9, "maxfevals": int(budget)}
    if popsize is not None:
        opts["popsize"] = int(popsize)
    if lower is not None or upper is not None:
        lo = -np.inf if lower is None else lower
        hi = np.inf if upper is None else upper
        opts["bounds"] = [np.broadcast_to(lo, (d,)).tolist(), np.broadcast_to(hi, (d,)).tolist()]
    es = cma.CMAEvolutionStrategy(np.asarray(x0, np.float64), float(sigma0), opts)
    sims, failed, best_x, best_f = 0, 0, np.asarray(x0, np.float64), math.inf
    hist_sims, hist_f, hist_x, hist_t = [], [], [], []
    penalty = None
    start = time.perf_counter()
    with progress_bar(progress) as bar:
        task = bar.add_task("CMA-ES", total=int(budget), stats="compiling")
        while sims < budget:
            xs = es.ask()
            xs = xs[: budget - sims]
            fs = [float(f) for f in evaluate(xs)]
            if len(fs) != len(xs):
                raise ControlError(f"evaluate returned {len(fs)} values for {len(xs)} candidates")
            sims += len(xs)
            failed += sum(not math.isfinite(f) for f in fs)
            finite = [f for f in fs if math.isfinite(f)]
            if finite:
                worst = max(finite)
                penalty = worst + abs(worst) + 1.0 if penalty is None else max(penalty, worst + abs(worst) + 1.0)
            told = [f if math.isfinite(f) else (penalty if penalty is not None else 1e300) for f in fs]
            for x, f in zip(xs, fs):
                if math.isfinite(f) and f < best_f:
                    best_f, best_x = f, np.asarray(x, np.float64)
            if len(xs) == es.popsize:
                es.tell(xs, told)
            hist_sims.append(sims)
            hist_f.append(best_f)
            hist_x.append(best_x.copy())
            hist_t.append(time.perf_counter() - start)
            bar.update(task, completed=sims, stats=f"best {best_f:.4e}")
            best_theta = unravel(jnp.asarray(best_x))
            if (target is not None and best_f <= target) or (stop is not None and stop(best_theta, best_f)):
                break
    return CMAResult(best_theta=unravel(jnp.asarray(best_x)), best_loss=best_f, simulations=np.asarray(hist_sims),
                     best_loss_history=np.asarray(hist_f), best_x_history=np.asarray(hist_x),
                     elapsed=np.asarray(hist_t), failed=failed, unravel=unravel)


#: The start of the simulator's message for a failed step (softbody.simulate's check): "step 12: ..."
_STEP_FAILED = re.compile(r"\bstep \d+: ")


def _evaluate(value, x) -> float:
    """``value(x)`` as a float; ``nan`` when a step of its simulation failed (non-finite
    state, the iteration cap, inverted tets, ...: what sweep workers record as a failed
    point, so that a search evaluated here and one on workers rank it alike)."""
    try:
        return float(value(jnp.asarray(x)))
    except jax.errors.JaxRuntimeError as err:
        if not _STEP_FAILED.search(str(err)):
            raise
        return math.nan

"""The gradient-descent loop shared by trajectory optimisation, co-design, policies and
system identification: optax updates, a projection, progress, history, checkpoints.

:func:`minimize` compiles one function that evaluates the objective and its gradient at
the current iterate and returns the optimiser's next iterate (projected onto the
feasible set, if a projection is given), then calls it once per iteration. Iteration
``k`` evaluates the iterate ``theta_k``; the result's ``best_theta`` is the evaluated
iterate with the lowest objective, its ``last_theta`` the iterate the optimiser would
evaluate next.

The compiled iteration is cached per ``(fun, optimizer, project)`` objects, so pass the
same objects (e.g. a problem's bound ``objective`` method) to reuse it across runs.

**Checkpoints** are one ``.npz`` file holding the iterate, the optimiser state, the best
iterate so far, the history and the iteration count, written atomically every
``checkpoint_every`` iterations, at the end, and when the loop is interrupted. Calling
:func:`minimize` again with the same checkpoint path resumes from it; because the loop is
deterministic, the continuation is bitwise identical to an uninterrupted run. A checkpoint
records a ``fingerprint`` of the problem (sizes, settings) and the shapes of every array,
and refuses to resume a different problem.
"""

from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax

from softbody.io import writing_to

from .errors import ControlError

__all__ = ["OptimizeResult", "minimize", "progress_bar"]

CHECKPOINT_FORMAT = "softbody.control.checkpoint"
CHECKPOINT_VERSION = 1


@dataclass
class OptimizeResult:
    """The outcome of :func:`minimize`.

    Attributes:
        best_theta: the evaluated iterate with the lowest objective (a pytree like ``theta0``).
        best_loss: its objective value.
        best_iteration: its iteration index.
        last_theta: the iterate the optimiser would evaluate next (resume point).
        loss: ``(k,)`` objective at each evaluated iterate.
        grad_norm: ``(k,)`` global norm of each gradient.
        elapsed: ``(k,)`` wall-clock seconds since the start (summed over resumed runs),
            compilation included.
        iterations: number of evaluated iterates ``k`` (= gradient evaluations).
        stopped: why the loop ended: ``"n_iter"`` or ``"target"``.
    """

    best_theta: Any
    best_loss: float
    best_iteration: int
    last_theta: Any
    loss: np.ndarray
    grad_norm: np.ndarray
    elapsed: np.ndarray
    iterations: int
    stopped: str

    @property
    def wall_time(self) -> float:
        """Total wall-clock seconds (summed over resumed runs)."""
        return float(self.elapsed[-1]) if len(self.elapsed) else 0.0


def progress_bar(enabled: bool):
    """A progress display (or a silent stand-in when ``enabled`` is false).

    A bar on a terminal and, on a pipe or file, a plain flushed line per update (at most
    one a second) and at least one every ~10 s (:mod:`softbody.progress`). It offers the
    calls of :class:`rich.progress.Progress` that the loops here use:
    ``task = progress.add_task(description, total=n, stats="...")`` and
    ``progress.update(task, completed=k, stats="...")``.
    """
    from softbody.progress import Bar

    return Bar(enabled)


#: ``optax.adam(0.05)``, the default optimiser (one shared instance, so that repeated runs
#: of the same problem reuse the compiled iteration).
DEFAULT_OPTIMIZER = optax.adam(0.05)


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _iteration(fun, optimizer, project, theta, opt_state):
    """Objective and gradient at ``theta`` and the optimiser's next (projected) iterate.

    Compiled once per ``(fun, optimizer, project)``: a second run of the same problem
    with the same optimiser object (a resume, say) reuses the compiled code.
    """
    loss, grad = jax.value_and_grad(fun)(theta)
    updates, opt_state = optimizer.update(grad, opt_state, theta)
    new = optax.apply_updates(theta, updates)
    if project is not None:
        new = project(new)
    return loss, optax.tree.norm(grad), new, opt_state


def _leaves(tree) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in jax.tree.leaves(tree)]


def _save(path: Path, carry, history: dict, meta: dict) -> None:
    arrays = {f"leaf_{i:04d}": leaf for i, leaf in enumerate(_leaves(carry))}
    arrays.update({f"history_{k}": np.asarray(v, np.float64) for k, v in history.items()})
    meta = dict(meta, format=CHECKPOINT_FORMAT, version=CHECKPOINT_VERSION, n_leaves=len(arrays) - len(history))
    with writing_to(path, force=True) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, meta=np.asarray(json.dumps(meta)), **arrays)


def _load(path: Path, template, fingerprint: dict):
    try:
        data = np.load(path, allow_pickle=False)
        meta = json.loads(str(data["meta"]))
    except (OSError, ValueError, KeyError) as err:
        raise ControlError(f"{path} is not a readable optimisation checkpoint ({err}); "
                           "delete it or pass another checkpoint path") from None
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise ControlError(f"{path} is not an optimisation checkpoint (format {meta.get('format')!r})")
    if meta.get("fingerprint") != fingerprint:
        raise ControlError(f"{path} was written for another problem: its settings {meta.get('fingerprint')} "
                           f"differ from this run's {fingerprint}; use another checkpoint path")
    leaves, tree = jax.tree.flatten(template)
    if meta["n_leaves"] != len(leaves):
        raise ControlError(f"{path} holds {meta['n_leaves']} arrays but this problem's state has {len(leaves)} "
                           "(a different optimiser or parameterisation?); use another checkpoint path")
    loaded = []
    for i, ref in enumerate(leaves):
        a = data[f"leaf_{i:04d}"]
        if a.shape != np.shape(ref) or a.dtype != np.asarray(ref).dtype:
            raise ControlError(f"{path}: array {i} has shape {a.shape} {a.dtype}, this problem expects "
                               f"{np.shape(ref)} {np.asarray(ref).dtype}; use another checkpoint path")
        loaded.append(jnp.asarray(a))
    history = {k[len("history_"):]: list(data[k]) for k in data.files if k.startswith("history_")}
    return jax.tree.unflatten(tree, loaded), history, meta


def minimize(
    fun: Callable[[Any], jax.Array],
    theta0,
    *,
    optimizer: optax.GradientTransformation | None = None,
    n_iter: int = 100,
    project: Callable[[Any], Any] | None = None,
    target: float | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = True,
    checkpoint_every: int = 10,
    fingerprint: dict | None = None,
    callback: Callable[[int, Any, float], None] | None = None,
    progress: bool = True,
    description: str = "optimising",
) -> OptimizeResult:
    """Minimise ``fun(theta)`` by gradient steps of an optax optimiser.

    Arguments:
        fun: a scalar, JAX-traceable function of the pytree ``theta`` (compiled once,
            together with its gradient and the optimiser update).
        theta0: the starting point (a pytree of float arrays), already feasible.
        optimizer: an optax transformation (default :data:`DEFAULT_OPTIMIZER`,
            ``optax.adam(0.05)``).
        n_iter: the number of iterates to evaluate (gradient evaluations), >= 1.
        project: ``theta -> theta`` onto the feasible set, applied after every update
            (traced; e.g. clipping to bounds).
        target: stop as soon as an evaluated objective is <= ``target``.
        checkpoint: a ``.npz`` path: resume from it if it exists (and ``resume``), and
            keep it up to date.
        resume: resume from an existing checkpoint; with ``False`` an existing file is an
            error (nothing is overwritten unasked).
        checkpoint_every: iterations between checkpoint writes.
        fingerprint: JSON-able description of the problem, stored in and checked against
            the checkpoint.
        callback: ``callback(k, theta_k, loss_k)`` after each evaluation (host side).
        progress: show a rich progress bar.
        description: the progress bar's label.

    Returns:
        :class:`OptimizeResult`.

    Raises:
        ControlError: ``n_iter < 1``; a non-finite objective or gradient (naming the
            iteration); a checkpoint for another problem; an existing checkpoint with
            ``resume=False``.
    """
    if int(n_iter) < 1:
        raise ControlError(f"n_iter must be >= 1, got {n_iter}")
    if int(checkpoint_every) < 1:
        raise ControlError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    optimizer = DEFAULT_OPTIMIZER if optimizer is None else optimizer
    fingerprint = json.loads(json.dumps(fingerprint or {}, default=str))
    theta0 = jax.tree.map(jnp.asarray, theta0)

    iteration = functools.partial(_iteration, fun, optimizer, project)
    carry = (theta0, optimizer.init(theta0), theta0)  # iterate, optimiser state, best iterate
    history = {"loss": [], "grad_norm": [], "elapsed": []}
    k, best_loss, best_iteration = 0, math.inf, -1
    path = None if checkpoint is None else Path(checkpoint)
    if path is not None and path.exists():
        if not resume:
            raise ControlError(f"checkpoint {path} exists; pass resume=True to continue it, or another path")
        carry, history, meta = _load(path, carry, fingerprint)
        k, best_loss, best_iteration = meta["iteration"], meta["best_loss"], meta["best_iteration"]
        best_loss = math.inf if best_loss is None else best_loss
    offset = history["elapsed"][-1] if history["elapsed"] else 0.0
    stopped = "target" if (target is not None and best_loss <= target) else "n_iter"
    written = k

    def save():
        if path is not None:
            _save(path, carry, history, {"iteration": k, "best_loss": best_loss if math.isfinite(best_loss) else None,
                                         "best_iteration": best_iteration, "fingerprint": fingerprint})

    start = time.perf_counter()
    try:
        with progress_bar(progress) as bar:
            task = bar.add_task(description, total=int(n_iter), completed=k, stats="compiling")
            while k < n_iter and stopped != "target":
                theta, opt_state, best = carry
                loss, gnorm, new, new_state = iteration(theta, opt_state)
                loss, gnorm = float(loss), float(gnorm)
                if not (math.isfinite(loss) and math.isfinite(gnorm)):
                    raise ControlError(f"iteration {k}: the objective ({loss}) or its gradient norm ({gnorm}) is "
                                       "not finite; lower the learning rate, tighten bounds, or check the scene")
                if loss < best_loss:
                    best, best_loss, best_iteration = theta, loss, k
                history["loss"].append(loss)
                history["grad_norm"].append(gnorm)
                history["elapsed"].append(offset + time.perf_counter() - start)
                if callback is not None:
                    callback(k, theta, loss)
                k += 1
                if target is not None and loss <= target:
                    stopped = "target"
                    carry = (theta, opt_state, best)
                else:
                    carry = (new, new_state, best)
                bar.update(task, completed=k, stats=f"loss {loss:.4e}  best {best_loss:.4e}  |g| {gnorm:.2e}")
                if k - written >= checkpoint_every:
                    save()
                    written = k
    finally:
        if k != written:
            save()
    return OptimizeResult(
        best_theta=carry[2], best_loss=best_loss, best_iteration=best_iteration, last_theta=carry[0],
        loss=np.asarray(history["loss"]), grad_norm=np.asarray(history["grad_norm"]),
        elapsed=np.asarray(history["elapsed"]), iterations=k, stopped=stopped)

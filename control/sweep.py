"""Design and parameter sweeps on Ray: many points, many workers, one table, resumable.

A sweep runs a user's point function ``fn(scene, **point) -> {metric: value}`` over a set
of parameter points and streams one row per finished point into a CSV table:

* the points: :func:`grid` (the Cartesian product of values per parameter),
  :func:`random_design` (``n`` points drawn uniformly, or log-uniformly, within bounds) or
  any list of dicts; an ask/tell optimiser's populations go through :class:`Pool` (CMA-ES:
  ``cmaes(..., evaluate=population_evaluator(pool))``, see
  :func:`softbody.control.baselines.cmaes`);
* the workers: Ray actors, each running on one CPU. Each builds its scene once
  (``setup()``, a picklable function, e.g. meshing and ``build``) on its first point and
  then reuses it, and with it the programs JAX compiled for it, for every later point;
* the cluster: by default a local Ray started on demand with ``workers`` CPUs and stopped
  at the end; ``address=`` joins a running cluster (``ray start --head`` on one node,
  ``ray start --address=HEAD:6379`` on the others; see docs/sweeps.md), and a Ray that the
  caller already initialised is used as it is;
* the table (:func:`run_sweep`'s ``out``): columns ``index``, each parameter, each metric,
  ``seconds`` (the point's wall time on its worker), ``worker`` (the worker's slot),
  ``pid``, ``worker_seq`` (1 for the first point a worker process ran: it pays for
  compiling), ``attempts`` and ``error``; one row is written and flushed as each point
  finishes, and a PNG of a metric against a parameter is written at the end;
* faults: a point whose function raises (non-convergence, inverted tets, a bad parameter:
  any ``Exception``) is a row with the error's message, not the end of the sweep; a
  worker process that dies mid-point is replaced by a fresh one and the point retried
  (``max_retries`` times, then a row with the error); a sweep stopped (interrupted,
  killed, or ``max_points``) continues with ``resume=True``, which keeps the table's
  finished rows and runs only the points missing from it or recorded with an error.

Bad input (unknown or missing parameter names, an empty grid, mismatched metrics, an
unreachable cluster address, an existing table without ``resume``/``overwrite``) is
refused with a :class:`SweepError` before any Ray process starts.

Ray is an optional dependency (``pip install softbody[sweep]``): it is imported only when
a sweep starts its workers.

The command line ``softbody sweep SPEC`` (:func:`run`) reads a JSON or Python spec and
calls :func:`run_sweep` (:func:`load_spec` lists the keys).
"""

from __future__ import annotations

import argparse
import collections
import csv
import functools
import importlib
import importlib.util
import inspect
import itertools
import json
import math
import os
import socket
import sys
import sysconfig
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ControlError

__all__ = ["SweepError", "SweepResult", "Outcome", "Pool", "grid", "random_design", "run_sweep", "read_table",
           "plot_table", "population_evaluator", "load_spec", "check_address"]

#: the table's columns after the parameters and metrics
TAIL_COLUMNS = ("seconds", "worker", "pid", "worker_seq", "attempts", "error")
#: what to install when Ray is missing
INSTALL_HINT = "pip install softbody[sweep]  (or: pip install 'ray>=2.9')"


class SweepError(ControlError):
    """Bad sweep input (names, grids, addresses, tables); the message names the problem and the fix."""


# --------------------------------------------------------------------------------- designs


def grid(values: Mapping[str, Sequence]) -> list[dict]:
    """The Cartesian product of each parameter's values, the first parameter varying slowest.

    Arguments:
        values: parameter name -> its values (a non-empty sequence of numbers or strings).

    Returns:
        One dict per point, ``len = prod(len(v))``, in ``itertools.product`` order.

    Raises:
        SweepError: no parameters, or a parameter with no values.
    """
    if not values:
        raise SweepError("the grid names no parameters: give a dict of name -> list of values")
    names = list(values)
    lists = []
    for name in names:
        vals = values[name]
        if isinstance(vals, (str, bytes)) or not isinstance(vals, Iterable):
            raise SweepError(f"grid parameter {name!r} must be a list of values, got {vals!r}")
        vals = list(np.asarray(vals).tolist()) if isinstance(vals, np.ndarray) else list(vals)
        if not vals:
            raise SweepError(f"the grid of parameter {name!r} is empty: give it at least one value "
                             "(or leave the parameter out)")
        lists.append(vals)
    return [dict(zip(names, combo)) for combo in itertools.product(*lists)]


def random_design(bounds: Mapping[str, Sequence[float]], n: int, *, seed: int = 0,
                  log: Sequence[str] = ()) -> list[dict]:
    """``n`` points drawn independently and uniformly within ``bounds``.

    Arguments:
        bounds: parameter name -> ``(low, high)``, ``low < high``, finite.
        n: the number of points (>= 1).
        seed: the seed of :func:`numpy.random.default_rng` (the same seed, the same points).
        log: parameters drawn log-uniformly (their bounds must be positive).

    Returns:
        One dict of floats per point.

    Raises:
        SweepError: no parameters, ``n < 1``, bad bounds, ``log`` naming a parameter not in
            ``bounds`` or with non-positive bounds.
    """
    if not bounds:
        raise SweepError("the random design names no parameters: give bounds as name -> [low, high]")
    if int(n) != n or n < 1:
        raise SweepError(f"a random design needs n >= 1 points, got {n!r}")
    unknown = [name for name in log if name not in bounds]
    if unknown:
        raise SweepError(f"log names {unknown}, which have no bounds; bounds are given for {list(bounds)}")
    rng = np.random.default_rng(seed)
    columns = {}
    for name, b in bounds.items():
        lo, hi = (float(v) for v in b) if len(b) == 2 else (math.nan, math.nan)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise SweepError(f"bounds of {name!r} must be [low, high] with finite low < high, got {b!r}")
        u = rng.random(int(n))
        if name in log:
            if lo <= 0:
                raise SweepError(f"{name!r} is drawn log-uniformly, so its bounds must be positive, got {b!r}")
            columns[name] = np.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            columns[name] = lo + u * (hi - lo)
    return [{name: float(col[i]) for name, col in columns.items()} for i in range(int(n))]


# --------------------------------------------------------------------------------- checks


def _point_names(points: Sequence[Mapping]) -> list[str]:
    if not isinstance(points, Sequence) or isinstance(points, (str, bytes)):
        raise SweepError(f"points must be a list of dicts (see grid, random_design), got {type(points).__name__}")
    if len(points) == 0:
        raise SweepError("the sweep has no points: the grid or design is empty")
    names = list(points[0])
    if not names:
        raise SweepError("the points name no parameters")
    for i, p in enumerate(points):
        if not isinstance(p, Mapping) or list(p) != names:
            got = list(p) if isinstance(p, Mapping) else type(p).__name__
            raise SweepError(f"point {i} has parameters {got}, point 0 has {names}: every point must name "
                             "the same parameters in the same order")
    return names


def check_parameters(fn: Callable, names: Sequence[str], *, with_scene: bool) -> None:
    """Check that ``fn`` accepts the parameters ``names`` as keyword arguments and that every
    argument it requires is among them.

    Arguments:
        fn: the point function, ``fn(scene, **point)`` (``with_scene``) or ``fn(**point)``.
        names: the sweep's parameter names.
        with_scene: whether ``fn``'s first argument is the scene from ``setup()``.

    Raises:
        SweepError: a name that ``fn`` does not accept, or a required argument of ``fn``
            missing from the sweep.
    """
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin or C function: nothing to check
        return
    params = list(sig.parameters.values())
    if with_scene:
        positional = [p for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        if not positional and not any(p.kind is p.VAR_POSITIONAL for p in params):
            raise SweepError(f"the point function {_name(fn)} takes no argument for the scene: with setup= "
                             "it is called as fn(scene, **point)")
        if positional:
            params = [p for p in params if p is not positional[0]]
    accepts_any = any(p.kind is p.VAR_KEYWORD for p in params)
    keyword = {p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    unknown = [n for n in names if n not in keyword]
    if unknown and not accepts_any:
        raise SweepError(f"unknown parameter {unknown[0]!r}" + (f" (and {unknown[1:]})" if unknown[1:] else "")
                         + f": the point function {_name(fn)} accepts {sorted(keyword)}; rename the parameter "
                         "in the grid/design or add the argument to the function")
    required = [p.name for p in params if p.default is p.empty
                and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in names]
    if required:
        raise SweepError(f"the point function {_name(fn)} requires {required}, which the sweep does not give: "
                         "add them to the grid/design or give them defaults")


def check_address(address: str | None, timeout: float = 3.0) -> None:
    """Check quickly that a Ray cluster's address accepts connections (``ray.init`` would
    otherwise wait a long time on an unreachable one).

    Arguments:
        address: ``None`` or ``"local"`` (a new local Ray: nothing to check), ``"auto"``
            (the cluster this machine joined: checked by Ray), ``"HOST:PORT"`` (the head's
            GCS port, 6379 by default) or ``"ray://HOST:PORT"`` (Ray Client, 10001).
        timeout: seconds to wait for the TCP connection.

    Raises:
        SweepError: a malformed address, or nothing listening at it.
    """
    if address in (None, "local", "auto"):
        return
    if not isinstance(address, str):
        raise SweepError(f"address must be a string such as '10.0.0.5:6379', got {address!r}")
    rest = address.split("://", 1)[1] if "://" in address else address
    host, _, port = rest.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SweepError(f"address {address!r} is not HOST:PORT (e.g. '10.0.0.5:6379' or 'ray://10.0.0.5:10001')")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as err:
        raise SweepError(f"cannot reach the Ray cluster at {address!r} ({err}); start it there with "
                         f"`ray start --head --port={port}`, or check the host, the port and the firewall "
                         "(leave address unset for a local Ray)") from None


def _import_ray():
    try:
        import ray
    except ImportError:
        raise SweepError(f"sweeps run on Ray, which is not installed: {INSTALL_HINT}") from None
    return ray


def _name(fn) -> str:
    fn = getattr(fn, "func", fn)
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"


# --------------------------------------------------------------------------------- pickling


def _by_value_modules(objs) -> set[str]:
    """Modules of ``objs`` (functions, partials) that a worker may not import by name: not
    installed in site-packages, not the standard library and not softbody (a test module,
    a spec file, a script's ``__main__``). cloudpickle ships their functions by value."""
    installed = {os.path.realpath(p) for key in ("purelib", "platlib", "stdlib", "platstdlib")
                 if (p := sysconfig.get_paths().get(key))}
    out = set()
    stack = list(objs)
    while stack:
        obj = stack.pop()
        if isinstance(obj, functools.partial):
            stack.extend([obj.func, *obj.args, *obj.keywords.values()])
            continue
        module = getattr(obj, "__module__", None)
        if not callable(obj) or not module or module == "__main__" or module.split(".")[0] == "softbody":
            continue
        mod = sys.modules.get(module)
        path = getattr(mod, "__file__", None)
        if path and not any(os.path.realpath(path).startswith(p + os.sep) for p in installed):
            out.add(module)
    return out


def _dumps(*objs) -> bytes:
    from ray import cloudpickle

    modules = [sys.modules[m] for m in _by_value_modules(objs)]
    for m in modules:
        cloudpickle.register_pickle_by_value(m)
    try:
        return cloudpickle.dumps(objs)
    finally:
        for m in modules:
            cloudpickle.unregister_pickle_by_value(m)


# --------------------------------------------------------------------------------- workers


@dataclass
class Outcome:
    """One evaluated point.

    Attributes:
        index: the point's index in the sweep.
        point: its parameters.
        metrics: metric name -> float (empty when it failed).
        seconds: the evaluation's wall time on the worker (a vectorized batch's time is
            shared equally by its points).
        worker: the worker's slot (0 .. workers-1; a replaced worker keeps its slot).
        pid: the worker's process id.
        worker_seq: the point's rank among those its worker process ran (1: the first,
            which includes compiling).
        attempts: how many times the point was started (> 1 after a worker died).
        error: ``""`` or the error's ``"Type: message"``.
    """

    index: int
    point: dict
    metrics: dict = field(default_factory=dict)
    seconds: float = math.nan
    worker: int = -1
    pid: int = -1
    worker_seq: int = 0
    attempts: int = 1
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


class _Worker:
    """A Ray actor's state: the scene (built on the first call) and the point function."""

    def __init__(self, payload: bytes, slot: int, vectorize: bool, static: tuple[str, ...]):
        from ray import cloudpickle

        self.fn, self.setup = cloudpickle.loads(payload)
        self.slot, self.vectorize, self.static = slot, vectorize, static
        self.scene, self.built, self.setup_s, self.seq = None, False, 0.0, 0
        self.batched = {}

    def pid(self) -> int:
        return os.getpid()

    def _scene(self):
        if not self.built:
            t0 = time.perf_counter()
            self.scene = self.setup() if self.setup is not None else None
            self.setup_s = time.perf_counter() - t0
            self.built = True
        return self.scene

    def _call(self, point):
        return self.fn(self.scene, **point) if self.setup is not None else self.fn(**point)

    def run(self, items: list[tuple[int, dict]], metrics: tuple[str, ...]) -> dict:
        """Evaluate ``items`` ``[(index, point)]``; returns ``{"rows": [...], "setup_s": s}``
        or ``{"setup_error": message}``."""
        try:
            self._scene()
        except Exception as err:  # noqa: BLE001 - reported to the driver, which stops the sweep
            return {"setup_error": _message(err)}
        rows = None
        if self.vectorize and len(items) > 1:
            rows = self._run_batched(items, metrics)
        if rows is None:
            rows = [self._run_one(index, point, metrics) for index, point in items]
        return {"rows": rows, "setup_s": self.setup_s}

    def _row(self, index, values, seconds, error):
        self.seq += 1
        return {"index": index, "metrics": values, "seconds": seconds, "worker": self.slot, "pid": os.getpid(),
                "worker_seq": self.seq, "error": error}

    def _run_one(self, index, point, metrics):
        t0 = time.perf_counter()
        try:
            values = _metrics_of(self._call(point), metrics)
            error = ""
        except Exception as err:  # noqa: BLE001 - a failed point is a row, not the end of the sweep
            values, error = {}, _message(err)
        return self._row(index, values, time.perf_counter() - t0, error)

    def _run_batched(self, items, metrics):
        """The points through one ``jit(vmap(fn))`` (per static values and batch size);
        ``None`` when it raises (the caller then runs them one by one)."""
        import jax
        import jax.numpy as jnp

        points = [p for _, p in items]
        static = {k: points[0][k] for k in self.static}
        traced = [k for k in points[0] if k not in static]
        key = (tuple(sorted(static.items())), len(points))
        t0 = time.perf_counter()
        try:
            f = self.batched.get(key)
            if f is None:
                scene, fn, with_scene = self.scene, self.fn, self.setup is not None

                def one(values):
                    kwargs = dict(static, **values)
                    out = fn(scene, **kwargs) if with_scene else fn(**kwargs)
                    return {m: jnp.asarray(out[m]) for m in metrics}

                f = self.batched[key] = jax.jit(jax.vmap(one))
            out = f({k: jnp.asarray([p[k] for p in points]) for k in traced})
            out = {m: np.asarray(v) for m, v in out.items()}
        except Exception:  # noqa: BLE001 - fall back to one at a time, which records each point's error
            return None
        seconds = (time.perf_counter() - t0) / len(points)
        rows = []
        for i, (index, _) in enumerate(items):
            values = {m: float(out[m][i]) for m in metrics}
            rows.append(self._row(index, values, seconds, ""))
        return rows


def _metrics_of(out, metrics: Sequence[str]) -> dict:
    if not isinstance(out, Mapping):
        raise TypeError(f"the point function must return a dict of metrics {list(metrics)}, "
                        f"got {type(out).__name__}")
    missing = [m for m in metrics if m not in out]
    if missing:
        raise KeyError(f"the point function's result lacks metrics {missing} (it has {sorted(out)})")
    return {m: float(out[m]) for m in metrics}


def _message(err: BaseException) -> str:
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


class Pool:
    """Ray actors that each build a scene once and evaluate points on it, replacing any that die.

    Use it as a context manager (:meth:`close` kills the actors and stops a Ray it started)::

        with Pool(point, setup=build_scene, workers=4) as pool:
            for outcome in pool.imap(enumerate(points)):
                ...

    Arguments:
        fn: the point function: ``fn(scene, **point) -> {metric: value}`` with ``setup``,
            ``fn(**point)`` without. Raising any ``Exception`` marks that point failed.
        metrics: the metric names to keep from ``fn``'s result (each converted by ``float``).
        setup: a picklable function of no arguments returning the scene, called once in
            each worker process, on its first point.
        workers: the number of actors (one CPU each); default: the local CPU count, or the
            cluster's CPUs with ``address``.
        address: ``None`` for a local Ray started here (or the one this process already
            initialised), else a cluster (see :func:`check_address`).
        max_retries: how often a point whose worker died is started again, on a fresh worker.
        batch: points sent to a worker per call.
        vectorize: evaluate each batch with ``jax.jit(jax.vmap(fn))``: ``fn`` must then be
            traceable in its non-``static`` parameters and return scalars.
        static: parameters that stay Python values under ``vectorize`` (e.g. a time step
            that changes the compiled scene); a batch holds points with equal ones.
        runtime_env: passed to ``ray.init`` when this pool starts or joins Ray.

    Raises:
        SweepError: Ray missing (the message says what to install), bad ``workers``,
            ``max_retries`` or ``batch``, an unreachable ``address``.
    """

    def __init__(self, fn: Callable, *, metrics: Sequence[str], setup: Callable | None = None,
                 workers: int | None = None, address: str | None = None, max_retries: int = 2, batch: int = 1,
                 vectorize: bool = False, static: Sequence[str] = (), runtime_env: dict | None = None):
        if workers is not None and (int(workers) != workers or workers < 1):
            raise SweepError(f"workers must be a whole number >= 1, got {workers!r}")
        if int(max_retries) != max_retries or max_retries < 0:
            raise SweepError(f"max_retries must be a whole number >= 0, got {max_retries!r}")
        if int(batch) != batch or batch < 1:
            raise SweepError(f"batch must be a whole number >= 1, got {batch!r}")
        if not metrics or len(set(metrics)) != len(metrics):
            raise SweepError(f"metrics must be a non-empty list of distinct names, got {metrics!r}")
        check_address(address)
        self.fn, self.setup, self.metrics = fn, setup, tuple(metrics)
        self.max_retries, self.batch, self.vectorize, self.static = int(max_retries), int(batch), bool(vectorize), \
            tuple(static)
        self._ray = ray = _import_ray()
        self.started_ray = False
        if not ray.is_initialized():
            kwargs = {"include_dashboard": False, "configure_logging": False, "log_to_driver": True}
            if runtime_env:
                kwargs["runtime_env"] = runtime_env
            if address in (None, "local"):
                ray.init(address="local", num_cpus=int(workers or os.cpu_count() or 1), **kwargs)
            else:
                ray.init(address=address, **kwargs)
            self.started_ray = True
        self._actors, self.replaced, self.setup_s = [], 0, {}
        try:
            if workers is None:
                workers = max(1, int(ray.cluster_resources().get("CPU", 1)))
            self.workers = int(workers)
            self._payload = _dumps(fn, setup)
            self._remote = ray.remote(num_cpus=1, max_restarts=0, max_task_retries=0)(_Worker)
            self._actors = [self._spawn(i) for i in range(self.workers)]
        except BaseException:
            self.close()  # do not leave a Ray we started running
            raise

    def _spawn(self, slot: int):
        return self._remote.remote(self._payload, slot, self.vectorize, self.static)

    def __enter__(self) -> Pool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def pids(self) -> list[int]:
        """The process ids of the current workers (waits for them to start)."""
        return self._ray.get([a.pid.remote() for a in self._actors])

    def close(self) -> None:
        """Kill the workers; stop Ray if this pool started it."""
        ray = self._ray
        for actor in getattr(self, "_actors", []):
            try:
                ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001, S110 - already dead
                pass
        self._actors = []
        if self.started_ray and ray.is_initialized():
            ray.shutdown()
        self.started_ray = False

    def _batches(self, queue: collections.deque) -> list:
        """Take the queue's head and up to ``batch - 1`` more items with the same ``static``
        values (the first found, in queue order)."""
        first = queue.popleft()
        items = [first]
        if self.batch == 1 or not queue:
            return items
        key = tuple(first[1].get(k) for k in self.static)
        rest = collections.deque()
        while queue:
            item = queue.popleft()
            if len(items) < self.batch and tuple(item[1].get(k) for k in self.static) == key:
                items.append(item)
            else:
                rest.append(item)
        queue.extend(rest)
        return items

    def imap(self, items: Iterable[tuple[int, dict]]) -> Iterator[Outcome]:
        """Evaluate ``(index, point)`` items on the workers, yielding outcomes as they finish.

        A worker that dies (its process killed, out of memory, its node lost) is replaced by a
        fresh one and its unfinished points go back to the head of the queue, up to
        ``max_retries`` times each; after that the point's outcome carries the error.

        Arguments:
            items: ``(index, point)`` pairs.

        Returns:
            An iterator of :class:`Outcome`, in the order the points finish.

        Raises:
            SweepError: ``setup()`` raised on a worker (the sweep cannot go on).
        """
        ray = self._ray
        from ray.exceptions import RayActorError, RayError, RayTaskError

        queue = collections.deque((int(i), dict(p), 1) for i, p in items)
        idle = list(range(len(self._actors)))
        inflight: dict = {}
        try:
            while queue or inflight:
                while idle and queue:
                    slot = idle.pop()
                    batch = self._batches(queue)
                    ref = self._actors[slot].run.remote([(i, p) for i, p, _ in batch], self.metrics)
                    inflight[ref] = (slot, batch)
                ready, _ = ray.wait(list(inflight), num_returns=1)
                for ref in ready:
                    slot, batch = inflight.pop(ref)
                    try:
                        result = ray.get(ref)
                    except RayTaskError as err:  # the worker's own code failed: record, keep the worker
                        for i, p, attempts in batch:
                            yield Outcome(i, p, attempts=attempts, worker=slot, error=_message(err.cause or err))
                        idle.append(slot)
                        continue
                    except (RayActorError, RayError) as err:  # the worker died: replace it, retry its points
                        self._replace(slot)
                        idle.append(slot)
                        for i, p, attempts in reversed(batch):
                            if attempts > self.max_retries:
                                yield Outcome(i, p, attempts=attempts, worker=slot,
                                              error=f"worker died {attempts} times running this point "
                                                    f"(max_retries={self.max_retries}); last: {_message(err)}")
                            else:
                                queue.appendleft((i, p, attempts + 1))
                        continue
                    idle.append(slot)
                    if "setup_error" in result:
                        raise SweepError(f"setup() of the scene raised on worker {slot}: {result['setup_error']}")
                    self.setup_s[slot] = result["setup_s"]
                    points = {i: (p, attempts) for i, p, attempts in batch}
                    for row in result["rows"]:
                        p, attempts = points[row["index"]]
                        yield Outcome(row["index"], p, row["metrics"], row["seconds"], row["worker"], row["pid"],
                                      row["worker_seq"], attempts, row["error"])
        finally:
            for ref in inflight:
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001, S110 - best effort on the way out
                    pass

    def _replace(self, slot: int) -> None:
        try:
            self._ray.kill(self._actors[slot], no_restart=True)
        except Exception:  # noqa: BLE001, S110 - already gone
            pass
        self._actors[slot] = self._spawn(slot)
        self.replaced += 1

    def map(self, points: Sequence[Mapping]) -> list[Outcome]:
        """Evaluate ``points`` and return their outcomes in the points' order (see :meth:`imap`)."""
        out = {o.index: o for o in self.imap(enumerate(points))}
        return [out[i] for i in range(len(points))]


def population_evaluator(pool: Pool, metric: str | None = None, parameter: str = "x") -> Callable:
    """An ask/tell optimiser's population evaluator on a :class:`Pool`.

    Arguments:
        pool: whose point function takes the flat candidate as ``parameter``
            (``fn(scene, x=...)``) and returns ``metric``.
        metric: the objective's metric name (default: the pool's first).
        parameter: the candidate's argument name.

    Returns:
        ``evaluate(xs) -> list[float]`` for a list of flat candidates, in their order; a
        failed point (an exception, or its worker dying more than ``max_retries`` times)
        gives ``nan``, which :func:`softbody.control.baselines.cmaes` ranks below every
        finite value. Pass it as ``cmaes(..., evaluate=...)``.
    """
    metric = metric or pool.metrics[0]
    if metric not in pool.metrics:
        raise SweepError(f"metric {metric!r} is not among the pool's metrics {list(pool.metrics)}")

    def evaluate(xs):
        outcomes = pool.map([{parameter: np.asarray(x, np.float64)} for x in xs])
        evaluate.outcomes.extend(outcomes)
        return [o.metrics[metric] if o.ok else math.nan for o in outcomes]

    evaluate.outcomes = []
    return evaluate


# --------------------------------------------------------------------------------- the table


def _fmt(value) -> str:
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    return str(value)


def _columns(names, metrics) -> list[str]:
    return ["index", *names, *metrics, *TAIL_COLUMNS]


def read_table(path: str | os.PathLike) -> list[dict]:
    """The rows of a sweep table, as written (strings), plus ``index`` and ``attempts`` as
    ints; a last line cut short by a killed sweep is dropped.

    Arguments:
        path: the CSV written by :func:`run_sweep`.

    Returns:
        A list of dicts, one per row, keyed by column.

    Raises:
        SweepError: the file is not a sweep table (no ``index`` ... ``error`` header).
    """
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if not header or header[0] != "index" or tuple(header[-len(TAIL_COLUMNS):]) != TAIL_COLUMNS:
            raise SweepError(f"{path} is not a sweep table (its header is {header}); move it away or name "
                             "another output")
        rows = []
        for line in reader:
            if len(line) != len(header):
                continue  # a row cut short when the sweep was killed
            row = dict(zip(header, line))
            try:
                row["index"], row["attempts"] = int(row["index"]), int(row["attempts"])
            except ValueError:
                continue
            rows.append(row)
    return rows


def _resume_rows(path: Path, names, metrics, points) -> dict[int, dict]:
    """The finished rows of an earlier run's table, checked against this sweep."""
    rows = read_table(path)
    with open(path, newline="") as f:
        header = next(csv.reader(f))
    expected = _columns(names, metrics)
    if header != expected:
        raise SweepError(f"cannot resume {path}: its columns {header} differ from this sweep's {expected}; "
                         "resume with the same parameters and metrics, or write to another file")
    done = {}
    for row in rows:
        i = row["index"]
        if row["error"] or not 0 <= i < len(points):
            continue
        wanted = [_fmt(points[i][n]) for n in names]
        if [row[n] for n in names] != wanted:
            raise SweepError(f"cannot resume {path}: its row for point {i} has {[row[n] for n in names]} but the "
                             f"sweep's point {i} is {wanted}; the grid or design changed (same seed, same "
                             "values, same order needed), so write to another file")
        done[i] = row
    return done


class _Progress:
    def __init__(self, total: int, done: int, every: float, enabled: bool, label: str = "sweep"):
        self.total, self.done, self.failed, self.retried = total, done, 0, 0
        self.every, self.enabled, self.label = every, enabled, label
        self.start = self.last = time.perf_counter()
        self.new = 0

    def update(self, outcome: Outcome) -> None:
        self.done += 1
        self.new += 1
        self.failed += bool(outcome.error)
        self.retried += outcome.attempts > 1
        now = time.perf_counter()
        if now - self.last >= self.every:
            self.last = now
            self.line()

    def line(self) -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.start
        rate = self.new / elapsed if elapsed > 0 else 0.0
        left = self.total - self.done
        eta = f"{left / rate:.0f} s" if rate > 0 else "?"
        print(f"{self.label}: {self.done}/{self.total} points ({self.failed} failed, {self.retried} retried), "
              f"{rate:.2f} points/s, ETA {eta}", file=sys.stderr, flush=True)


@dataclass
class SweepResult:
    """The outcome of :func:`run_sweep`.

    Attributes:
        path: the table (CSV).
        plot: the PNG written, or None.
        rows: every row of the table (see :func:`read_table`), sorted by index.
        evaluated: points evaluated by this call (finished rows it added).
        failed: rows of this call with an error.
        skipped: points already finished in the table (``resume``).
        complete: every point has a row (False after ``max_points`` stopped it early).
        wall_s: this call's wall time, s.
        workers: worker count; replaced: workers replaced after dying.
        setup_s: each worker slot's scene set-up time (its last process), s.
    """

    path: Path
    plot: Path | None
    rows: list[dict]
    evaluated: int
    failed: int
    skipped: int
    complete: bool
    wall_s: float
    workers: int
    replaced: int
    setup_s: dict

    def column(self, name: str) -> np.ndarray:
        """One column over the rows (floats; ``nan`` where empty, e.g. a failed point's metric)."""
        return np.asarray([float(r[name]) if r[name] != "" else math.nan for r in self.rows])


def run_sweep(fn: Callable, points: Sequence[Mapping], *, metrics: Sequence[str], out: str | os.PathLike,
          setup: Callable | None = None, workers: int | None = None, address: str | None = None,
          resume: bool = False, overwrite: bool = False, max_retries: int = 2, max_points: int | None = None,
          batch: int = 1, vectorize: bool = False, static: Sequence[str] = (),
          plot: tuple[str, str] | bool | None = True, progress: bool = True, progress_every: float = 5.0,
          runtime_env: dict | None = None) -> SweepResult:
    """Evaluate ``fn`` at every point on Ray workers, streaming rows into the table ``out``.

    Arguments:
        fn: the point function, ``fn(scene, **point) -> {metric: value}`` with ``setup``
            (``fn(**point)`` without); picklable (a module-level function or a
            ``functools.partial`` of one). Any ``Exception`` it raises is recorded as that
            point's error.
        points: a list of dicts with the same parameter names (:func:`grid`,
            :func:`random_design`).
        metrics: the names of the metrics to record from ``fn``'s result.
        out: the CSV table; a PNG beside it (same name, ``.png``) gets the plot.
        setup: builds the scene once per worker (picklable, no arguments).
        workers: the number of workers (default: the CPUs of the local machine or cluster).
        address: ``None``: a local Ray with ``workers`` CPUs, started and stopped here (or
            the Ray this process already initialised); else a cluster's address
            (``"HOST:6379"``, ``"ray://HOST:10001"``, ``"auto"``), checked before connecting.
        resume: continue the table ``out``: its rows without error are kept and their
            points skipped; the rest run (rows with an error are dropped and run again).
        overwrite: replace an existing ``out`` (without ``resume``).
        max_retries: how often a point is started again after its worker died.
        max_points: stop after this many points have finished in this call (a sweep in
            parts; continue with ``resume=True``).
        batch, vectorize, static: see :class:`Pool` (``batch`` points per call; with
            ``vectorize`` one ``jax.vmap`` over each batch).
        plot: ``(parameter, metric)`` to plot, ``True`` for the first of each, or
            ``False``/``None`` for no plot.
        progress: print a progress line to stderr every ``progress_every`` seconds.
        runtime_env: passed to ``ray.init`` when the sweep starts or joins Ray.

    Returns:
        :class:`SweepResult`.

    Raises:
        SweepError: before any worker starts: no points or an empty grid, parameter names
            that ``fn`` does not accept or required arguments it lacks, metrics that are
            empty or collide with parameters, ``static`` names that are not parameters, a
            ``plot`` naming unknown columns, ``out`` existing without ``resume`` or
            ``overwrite``, a table to resume with other columns or points, an unreachable
            ``address``, Ray not installed. After starting: ``setup()`` raising on a worker.
        KeyboardInterrupt: re-raised after the workers are stopped; the rows written so far
            stay in the table (continue with ``resume=True``).
    """
    t_start = time.perf_counter()
    names = _point_names(points)
    metrics = tuple(metrics)
    if not metrics or len(set(metrics)) != len(metrics) or not all(isinstance(m, str) and m for m in metrics):
        raise SweepError(f"metrics must be a non-empty list of distinct names, got {list(metrics)}")
    clash = [m for m in metrics if m in names or m in ("index", *TAIL_COLUMNS)]
    if clash:
        raise SweepError(f"metric names {clash} collide with parameter or table columns; rename them")
    check_parameters(fn, names, with_scene=setup is not None)
    if setup is not None and not callable(setup):
        raise SweepError(f"setup must be a function of no arguments returning the scene, got {setup!r}")
    unknown_static = [s for s in static if s not in names]
    if unknown_static:
        raise SweepError(f"static names {unknown_static}, which are not parameters {names}")
    if max_points is not None and (int(max_points) != max_points or max_points < 1):
        raise SweepError(f"max_points must be a whole number >= 1, got {max_points!r}")
    if plot is True:
        plot = (names[0], metrics[0])
    if plot and (len(plot) != 2 or plot[0] not in names or plot[1] not in metrics):
        raise SweepError(f"plot must be (parameter, metric) with a parameter of {names} and a metric of "
                         f"{list(metrics)}, got {plot!r}")
    out = Path(out)
    if out.exists() and out.is_dir():
        raise SweepError(f"out {out} is a folder: name the CSV file to write, e.g. {out / 'sweep.csv'}")
    done: dict[int, dict] = {}
    if out.exists() and not resume and not overwrite:
        raise SweepError(f"{out} exists: pass resume=True (--resume) to continue it, overwrite=True (--force) "
                         "to replace it, or name another file")
    if resume and out.exists():
        done = _resume_rows(out, names, metrics, points)
    check_address(address)

    columns = _columns(names, metrics)
    todo = [(i, p) for i, p in enumerate(points) if i not in done]
    if max_points is not None:
        todo = todo[: int(max_points)]
    out.parent.mkdir(parents=True, exist_ok=True)
    # the table starts again from the kept rows (dropping errors and a line cut short)
    tmp = out.with_name(out.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for i in sorted(done):
            writer.writerow([done[i][c] for c in columns])
    os.replace(tmp, out)

    evaluated = failed = 0
    pool = None
    bar = _Progress(len(points), len(done), progress_every, progress)
    if todo:
        pool = Pool(fn, metrics=metrics, setup=setup, workers=workers, address=address, max_retries=max_retries,
                    batch=batch, vectorize=vectorize, static=static, runtime_env=runtime_env)
        try:
            with open(out, "a", newline="") as f:
                writer = csv.writer(f)
                for o in pool.imap(todo):
                    writer.writerow([o.index, *(_fmt(o.point[n]) for n in names),
                                     *(_fmt(o.metrics[m]) if m in o.metrics else "" for m in metrics),
                                     _fmt(o.seconds), o.worker, o.pid, o.worker_seq, o.attempts, o.error])
                    f.flush()
                    evaluated += 1
                    failed += bool(o.error)
                    bar.update(o)
        finally:
            pool.close()
    bar.line()
    rows = sorted(read_table(out), key=lambda r: r["index"])
    png = None
    if plot:
        png = plot_table(rows, plot[0], plot[1], out.with_suffix(".png"),
                         group=next((n for n in names if n != plot[0]), None))
    return SweepResult(path=out, plot=png, rows=rows, evaluated=evaluated, failed=failed, skipped=len(done),
                       complete=len({r["index"] for r in rows}) == len(points), wall_s=time.perf_counter() - t_start,
                       workers=pool.workers if pool else 0, replaced=pool.replaced if pool else 0,
                       setup_s=dict(pool.setup_s) if pool else {})


def plot_table(rows: Sequence[Mapping] | str | os.PathLike, x: str, y: str, path: str | os.PathLike, *,
               group: str | None = None, max_groups: int = 8) -> Path:
    """Plot metric ``y`` against parameter ``x`` from a sweep table; failed points as crosses.

    Arguments:
        rows: the rows (:func:`read_table`) or the table's path.
        x, y: a numeric parameter and a metric.
        path: the PNG to write.
        group: a second parameter: one line per value when it has at most ``max_groups``
            values (else the points are coloured by it).
        max_groups: see ``group``.

    Returns:
        ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not isinstance(rows, Sequence):
        rows = read_table(rows)
    ok = [r for r in rows if not r["error"]]
    bad = [r for r in rows if r["error"]]
    fig, ax = plt.subplots(figsize=(6, 4))
    groups = sorted({r[group] for r in ok}, key=_sort_key) if group else [None]
    if group and len(groups) <= max_groups:
        for g in groups:
            sel = sorted((r for r in ok if r[group] == g), key=lambda r: float(r[x]))
            ax.plot([float(r[x]) for r in sel], [float(r[y]) for r in sel], "o-", ms=3, label=f"{group} = {g}")
        ax.legend(fontsize=7)
    else:
        c = [float(r[group]) for r in ok] if group else None
        sc = ax.scatter([float(r[x]) for r in ok], [float(r[y]) for r in ok], c=c, s=10)
        if group:
            fig.colorbar(sc, ax=ax, label=group)
    if bad:
        ax.plot([float(r[x]) for r in bad], np.full(len(bad), np.nan), "x")
        ax.set_title(f"{len(bad)} failed point(s) not shown", fontsize=8)
    xs = [float(r[x]) for r in ok]
    if xs and min(xs) > 0 and max(xs) / min(xs) > 20:
        ax.set_xscale("log")
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _sort_key(text: str):
    try:
        return (0, float(text), "")
    except ValueError:
        return (1, 0.0, text)


# --------------------------------------------------------------------------------- spec + CLI

#: keys of a sweep spec
SPEC_KEYS = ("scene", "setup", "grid", "random", "points", "metrics", "workers", "out", "address", "max_retries",
             "plot", "batch", "vectorize", "static", "runtime_env")


def _resolve(ref, base: Path, what: str):
    """``"pkg.module:name"`` or ``"file.py:name"`` (relative to the spec's folder) -> the object."""
    if callable(ref):
        return ref
    if not isinstance(ref, str) or ":" not in ref:
        raise SweepError(f"spec {what!r} must be 'module:function' or 'file.py:function', got {ref!r}")
    target, _, attr = ref.rpartition(":")
    if target.endswith(".py"):
        path = Path(target) if Path(target).is_absolute() else base / target
        if not path.is_file():
            raise SweepError(f"spec {what!r}: no file {path}")
        module = _load_file(path)
    else:
        try:
            module = importlib.import_module(target)
        except ImportError as err:
            raise SweepError(f"spec {what!r}: cannot import {target!r} ({err})") from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise SweepError(f"spec {what!r}: {target} has no {attr!r}") from None


def _load_file(path: Path):
    name = "softbody_sweep_spec_" + "".join(c if c.isalnum() else "_" for c in str(path.resolve()))
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def load_spec(path: str | os.PathLike) -> dict:
    """Read a sweep spec: a JSON file, or a Python file defining a dict ``SPEC``.

    Keys: ``scene`` (the point function, ``"module:function"``, ``"file.py:function"``
    relative to the spec's folder, or in a Python spec the function itself), ``setup``
    (optional, the same forms), one of ``grid`` (name -> list of values), ``random``
    (``{"n": 64, "seed": 0, "bounds": {name: [low, high]}, "log": [names]}``) or ``points``
    (a list of dicts), ``metrics`` (list of names), and optionally ``workers``, ``out``
    (relative to the current folder; default: the spec's file name with ``.csv``), ``address``,
    ``max_retries``, ``plot`` (``[parameter, metric]``), ``batch``, ``vectorize``,
    ``static``, ``runtime_env``.

    Arguments:
        path: the spec file (``.json`` or ``.py``).

    Returns:
        Keyword arguments for :func:`run_sweep`, with ``fn`` and ``points``.

    Raises:
        SweepError: a missing or unreadable file, unknown keys, none or several of
            ``grid``/``random``/``points``, missing ``scene`` or ``metrics``, references
            that do not resolve, or a bad grid or design.
    """
    path = Path(path)
    if not path.is_file():
        raise SweepError(f"no sweep spec {path}: give a .json file or a .py file defining SPEC")
    if path.suffix == ".py":
        spec = getattr(_load_file(path), "SPEC", None)
        if not isinstance(spec, dict):
            raise SweepError(f"{path} defines no dict SPEC")
    else:
        try:
            spec = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise SweepError(f"{path} is not valid JSON: {err}") from None
        if not isinstance(spec, dict):
            raise SweepError(f"{path} must hold a JSON object with keys {list(SPEC_KEYS)}")
    unknown = [k for k in spec if k not in SPEC_KEYS]
    if unknown:
        raise SweepError(f"unknown keys {unknown} in {path}; the keys are {list(SPEC_KEYS)}")
    for key in ("scene", "metrics"):
        if key not in spec:
            raise SweepError(f"{path} names no {key!r}")
    designs = [k for k in ("grid", "random", "points") if k in spec]
    if len(designs) != 1:
        raise SweepError(f"{path} must give exactly one of 'grid', 'random' or 'points', got {designs or 'none'}")
    base = path.parent
    kwargs = {"fn": _resolve(spec["scene"], base, "scene"), "metrics": list(spec["metrics"])}
    if spec.get("setup") is not None:
        kwargs["setup"] = _resolve(spec["setup"], base, "setup")
    if "grid" in spec:
        if not isinstance(spec["grid"], dict):
            raise SweepError(f"'grid' in {path} must be an object of name -> list of values")
        kwargs["points"] = grid(spec["grid"])
    elif "random" in spec:
        r = spec["random"]
        extra = [k for k in r if k not in ("n", "seed", "bounds", "log")] if isinstance(r, dict) else None
        if extra is None or extra or "n" not in r or "bounds" not in r:
            raise SweepError(f"'random' in {path} must be {{'n': N, 'bounds': {{name: [low, high]}}, 'seed': S, "
                             f"'log': [names]}}, got {r!r}")
        kwargs["points"] = random_design(r["bounds"], r["n"], seed=r.get("seed", 0), log=r.get("log", ()))
    else:
        kwargs["points"] = list(spec["points"])
    kwargs["out"] = Path(spec.get("out", path.with_suffix(".csv").name))
    for key in ("workers", "address", "max_retries", "batch", "vectorize", "static", "runtime_env"):
        if key in spec:
            kwargs[key] = spec[key]
    if "plot" in spec:
        kwargs["plot"] = tuple(spec["plot"]) if spec["plot"] else None
    return kwargs


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody sweep``."""
    parser.add_argument("spec", help="the sweep spec: a .json file or a .py file defining SPEC "
                                     "(keys: scene, setup, grid|random|points, metrics, workers, out, address, ...)")
    parser.add_argument("--workers", type=int, help="number of workers (overrides the spec)")
    parser.add_argument("--address", help="a running Ray cluster, HOST:PORT or ray://HOST:PORT (overrides the spec)")
    parser.add_argument("--out", help="the CSV table (overrides the spec)")
    parser.add_argument("--resume", action="store_true", help="continue the table: skip its finished points")
    parser.add_argument("--force", action="store_true", help="replace an existing table")
    parser.add_argument("--max-points", type=int, help="stop after this many points (continue with --resume)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    """``softbody sweep``: run the spec's sweep; prints a summary, returns 0 when every point
    has a row without error, 1 on bad input or when points failed or remain."""
    try:
        kwargs = load_spec(args.spec)
        for key in ("workers", "address", "out"):
            if getattr(args, key) is not None:
                kwargs[key] = getattr(args, key)
        fn, points = kwargs.pop("fn"), kwargs.pop("points")
        result = run_sweep(fn, points, resume=args.resume, overwrite=args.force, max_points=args.max_points,
                       progress=not args.quiet, **kwargs)
    except SweepError as err:
        print(f"softbody sweep: {err}", file=sys.stderr)
        return 1
    failed = sum(bool(r["error"]) for r in result.rows)
    print(f"softbody sweep: {len(result.rows)}/{len(points)} points in {result.path} ({result.evaluated} run now, "
          f"{result.skipped} from before, {failed} failed) in {result.wall_s:.1f} s"
          + (f"; plot {result.plot}" if result.plot else ""))
    return 0 if result.complete and not failed else 1

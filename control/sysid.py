"""System identification: material (and damping, friction) parameters from observed motion.

The data are the positions of a few marker vertices over time, possibly noisy
(:class:`Observation`; :func:`synthesize` makes synthetic ones). The estimate minimises the
least-squares misfit of the simulated markers::

    C(z) = 1/2 sum_{k=1..T} sum_markers |x_k(theta(z)) - y_k|^2 / sigma^2

over unconstrained variables ``z``: ``theta = exp(z)`` for the positive quantities
(Young's modulus ``E``, ``density``, mass damping ``alpha``, stiffness damping ``beta``,
obstacle friction), ``nu = 0.5 sigmoid(z)`` for Poisson's ratio (kept in (0, 0.5)). Log
variables make relative errors the natural scale and keep every iterate physical.

Two methods:

* ``"lm"`` (default): Levenberg-Marquardt. Each iteration simulates once with ``p``
  forward-mode tangents (``jax.jvp``, vmapped), giving the residuals and their Jacobian
  together, and solves ``(J^T J + lambda diag(J^T J)) dz = -J^T r`` (``lambda`` starts at 1e-2,
  shrinks tenfold after an accepted step and grows tenfold after a rejected one).
  The tangents are implicit: the estimate runs on a copy of the model with the
  :class:`~softbody.gradients.ImplicitForward` adjoint, which solves one linear system
  per step and tangent with the converged step's Hessian instead of differentiating
  the solver's iterations, so any iteration method serves (the model's own by default)
  and the Jacobian is that of the exact step solutions: give the model a tight ``tol``
  (1e-9 on the cantilever example). Scenes with obstacles use the contact solver's own
  implicit derivative. Near the optimum the Gauss-Newton matrix also gives standard
  errors of the estimates.
* ``"adam"``: optax Adam on ``C(z)`` with the model's own adjoint (reverse mode),
  through :func:`softbody.control.optimize.minimize`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from softbody.gradients import ImplicitForward
from softbody.model import Model, Params, State, initial_state
from softbody.simulate import RESULTS, rollout
from softbody.solvers import NonlinearSolver

from .errors import ControlError
from .losses import region_vertices
from .optimize import minimize, progress_bar

Array = jax.Array

__all__ = ["ESTIMABLE", "Observation", "SysIdProblem", "SysIdResult", "identify", "synthesize"]

#: Names :func:`identify` can estimate and what each means.
ESTIMABLE = {
    "E": "Young's modulus per material, Pa (log variable)",
    "nu": "Poisson's ratio per material, in (0, 0.5) (logit variable)",
    "density": "density per material, kg/m^3 (log variable)",
    "alpha": "mass damping per material, 1/s (log variable; start it > 0)",
    "beta": "stiffness damping per material, s (log variable; the model must be built with beta > 0)",
    "friction": "friction coefficient per obstacle, mu_s = mu_k (log variable; needs obstacles)",
}


@dataclass(frozen=True, eq=False)
class Observation:
    """Observed marker positions.

    Attributes:
        markers: ``(k,)`` vertex indices of the markers.
        positions: ``(T + 1, k, 3)`` their positions, m; row 0 is the initial frame (not
            fitted: the simulation starts from the given initial state).
        controls: ``(T, C)`` actuator activations applied during the observation, or None.
        forces: ``(T, n, 3)`` external forces, or None.
        noise: the standard deviation of the marker noise, m, if known (> 0), else None;
            it scales the residuals (and so the reported standard errors).

    Raises:
        ControlError: inconsistent shapes or non-finite positions.
    """

    markers: np.ndarray
    positions: np.ndarray
    controls: np.ndarray | None = None
    forces: np.ndarray | None = None
    noise: float | None = None

    def __post_init__(self):
        markers = np.asarray(self.markers, np.int64).ravel()
        pos = np.asarray(self.positions, np.float64)
        if pos.ndim != 3 or pos.shape[1:] != (len(markers), 3) or pos.shape[0] < 2:
            raise ControlError(f"positions must have shape (T + 1, {len(markers)}, 3) with T >= 1 for "
                               f"{len(markers)} markers, got {pos.shape}")
        if not np.all(np.isfinite(pos)):
            raise ControlError("observed positions have non-finite values (drop missing frames or markers)")
        if self.noise is not None and not (math.isfinite(self.noise) and self.noise > 0):
            raise ControlError(f"noise must be a positive standard deviation in metres or None, got {self.noise}")
        object.__setattr__(self, "markers", markers)
        object.__setattr__(self, "positions", pos)

    @property
    def n_steps(self) -> int:
        return self.positions.shape[0] - 1


def synthesize(model: Model, params: Params, markers: str | Sequence[int] | None, n_steps: int, *,
               noise: float = 0.0, seed: int = 0, state0: State | None = None, controls=None,
               forces=None) -> Observation:
    """A synthetic observation: simulate, read the markers, add Gaussian noise.

    The noise's standard deviation is ``noise`` times the peak marker displacement
    (the largest ``|x_k - x_0|`` over frames and markers), independently per coordinate;
    the initial frame is noise-free (it is the known initial state).

    Arguments:
        model, params: the scene with the true parameters.
        markers: a region name, vertex indices, or None (every vertex).
        n_steps: the number of steps ``T``.
        noise: relative noise level (0.01 = 1 % of the peak displacement), >= 0.
        seed: the noise's random seed.
        state0, controls, forces: as for :func:`softbody.simulate.rollout`.

    Returns:
        :class:`Observation` with ``noise`` set to the absolute standard deviation (None
        for noise-free data).

    Raises:
        ControlError: unknown markers or a negative noise level.
    """
    if not (math.isfinite(noise) and noise >= 0):
        raise ControlError(f"noise must be a relative level >= 0, got {noise}")
    idx = region_vertices(model, markers)
    state0 = initial_state(model, params) if state0 is None else state0
    traj = rollout(model, params, state0, controls, forces, n_steps)
    clean = np.asarray(traj.x)[:, idx]
    sigma = noise * float(np.linalg.norm(clean - clean[0], axis=-1).max())
    rng = np.random.default_rng(seed)
    noisy = clean + sigma * rng.standard_normal(clean.shape)
    noisy[0] = clean[0]
    return Observation(idx, noisy, None if controls is None else np.asarray(controls),
                       None if forces is None else np.asarray(forces), sigma if sigma > 0 else None)


def _get(params: Params, name: str) -> Array:
    if name == "friction":
        return jnp.stack([p.mu_s for p in params.obstacles])
    return getattr(params, name)


def _set(params: Params, name: str, value: Array) -> Params:
    if name == "friction":
        obstacles = tuple(p.replace(mu_s=value[i], mu_k=value[i]) for i, p in enumerate(params.obstacles))
        return eqx.tree_at(lambda q: q.obstacles, params, obstacles)
    return eqx.tree_at(lambda q: getattr(q, name), params, value)


def _to_variable(name: str, value: Array) -> Array:
    if name == "nu":
        u = 2.0 * value
        return jnp.log(u) - jnp.log1p(-u)
    return jnp.log(value)


def _from_variable(name: str, z: Array) -> Array:
    if name == "nu":
        return 0.5 * jax.nn.sigmoid(z)
    return jnp.exp(z)


class SysIdProblem:
    """The least-squares misfit of a scene to an observation, in unconstrained variables.

    Arguments:
        model, params: the scene; ``params`` holds the starting values of the estimated
            quantities and the known values of the rest.
        observation: the :class:`Observation`.
        estimate: names from :data:`ESTIMABLE`.
        state0: the initial state (default: the rest shape).

    Raises:
        ControlError: unknown or repeated names, quantities that cannot be estimated in
            this scene (friction without obstacles, beta without stiffness damping),
            starting values outside their domain, or an observation that does not fit the
            model (marker indices, control or force shapes).
    """

    def __init__(self, model: Model, params: Params, observation: Observation, estimate: Sequence[str] = ("E",),
                 *, state0: State | None = None):
        estimate = tuple(estimate)
        unknown = [name for name in estimate if name not in ESTIMABLE]
        if unknown or not estimate or len(set(estimate)) != len(estimate):
            raise ControlError(f"estimate must list distinct names from {sorted(ESTIMABLE)}, got {list(estimate)}")
        if "friction" in estimate and not model.obstacles:
            raise ControlError("cannot estimate friction: the scene has no obstacles")
        if "beta" in estimate and not model.stiffness_damping:
            raise ControlError("cannot estimate beta: the model was built without stiffness damping; build it "
                               "with a Material whose beta > 0 (the starting guess)")
        for name in estimate:
            v = np.asarray(_get(params, name))
            ok = (v > 0) & (v < 0.5) if name == "nu" else v > 0
            if not np.all(np.isfinite(v) & ok):
                raise ControlError(f"the starting value of {name} ({v}) is outside its domain: {ESTIMABLE[name]}")
        if observation.markers.max() >= model.n_vertices:
            raise ControlError(f"marker indices reach {observation.markers.max()} but the model has "
                               f"{model.n_vertices} vertices")
        for what, a, shape in (("controls", observation.controls, (observation.n_steps, model.n_channels)),
                               ("forces", observation.forces, (observation.n_steps, model.n_vertices, 3))):
            if a is not None and a.shape != shape:
                raise ControlError(f"the observation's {what} have shape {a.shape}, the model needs {shape}")
        self.model, self.params, self.observation, self.estimate = model, params, observation, estimate
        self.state0 = initial_state(model, params) if state0 is None else state0
        self.sizes = [int(np.size(_get(params, name))) for name in estimate]
        self.sigma = observation.noise or 1.0

    @property
    def n_residuals(self) -> int:
        return self.observation.n_steps * len(self.observation.markers) * 3

    def pack(self, params: Params) -> Array:
        """The variables ``z`` ``(p,)`` of the estimated quantities in ``params``."""
        return jnp.concatenate([jnp.ravel(_to_variable(n, _get(params, n))) for n in self.estimate])

    def unpack(self, z: Array, params: Params | None = None) -> Params:
        """``params`` (default: the problem's) with the estimated quantities set from ``z``."""
        params = self.params if params is None else params
        offset = 0
        for name, size in zip(self.estimate, self.sizes):
            params = _set(params, name, _from_variable(name, z[offset:offset + size]))
            offset += size
        return params

    def values(self, z: Array) -> dict[str, np.ndarray]:
        """The estimated quantities of ``z`` by name (numpy arrays)."""
        p = self.unpack(jnp.asarray(z))
        return {name: np.asarray(_get(p, name)) for name in self.estimate}

    def residuals(self, z: Array, model: Model | None = None, *, throw: bool = True) -> Array:
        """``(m,)`` scaled misfits ``(x_sim - y) / sigma`` over frames 1..T, markers, coordinates.

        Arguments:
            z: ``(p,)`` variables; model: the model to simulate (default: the problem's).
            throw: as for :func:`~softbody.simulate.rollout`: raise for a failed step
                (``True``), or (``False``) return NaN misfits when any step failed. The
                latter compiles without a host callback, so the persistent compilation
                cache keeps the program, and suits searches that rank a failed
                simulation last (CMA-ES, the LM trial steps).

        Raises:
            SimulationError: with ``throw=True``, a step failed (see ``rollout``).
        """
        obs = self.observation
        traj = rollout(model or self.model, self.unpack(z), self.state0, obs.controls, obs.forces, obs.n_steps,
                       throw=throw)
        r = ((traj.x[1:, obs.markers] - jnp.asarray(obs.positions[1:])) / self.sigma).ravel()
        return r if throw else jnp.where(jnp.all(traj.info.result == int(RESULTS.success)), r, jnp.nan)

    def cost(self, z: Array, model: Model | None = None, *, throw: bool = True) -> Array:
        """``C(z) = |r(z)|^2 / 2`` (NaN for a failed simulation with ``throw=False``)."""
        r = self.residuals(z, model, throw=throw)
        return 0.5 * jnp.sum(r * r)


@dataclass
class SysIdResult:
    """The outcome of :func:`identify`.

    Attributes:
        values: the estimates by name (arrays: per material or per obstacle).
        params: the scene's parameters with the estimates in place.
        std: relative standard errors of each estimate (from the Gauss-Newton matrix at
            the optimum, for ``"lm"`` with a known noise level; else None).
        cost: ``(k,)`` the misfit ``C`` after each iteration (first entry: the start).
        history: the estimates after each iteration (a list of dicts, like ``cost``).
        iterations: iterations run (``"lm"``: simulations with forward-mode derivatives,
            rejected trial steps included; ``"adam"``: gradient evaluations).
        simulations: simulations run (each with its derivatives).
        rms_residual: root-mean-square marker misfit at the estimate, m.
        converged: a proposed step (``"lm"``) fell below ``xtol``.
        wall_time: seconds, compilation included.
    """

    values: dict
    params: Params
    std: dict | None
    cost: np.ndarray
    history: list
    iterations: int
    simulations: int
    rms_residual: float
    converged: bool
    wall_time: float


def identify(
    model: Model,
    params: Params,
    observation: Observation,
    estimate: Sequence[str] = ("E",),
    *,
    init: Mapping[str, float | Sequence[float]] | None = None,
    method: str = "lm",
    n_iter: int = 20,
    xtol: float = 1e-6,
    jacobian_solver: NonlinearSolver | None = None,
    optimizer: optax.GradientTransformation | None = None,
    state0: State | None = None,
    callback=None,
    progress: bool = True,
) -> SysIdResult:
    """Estimate parameters from an observed trajectory (see the module docstring).

    Arguments:
        model, params: the scene; ``params`` holds the known values.
        observation: the :class:`Observation`.
        estimate: names from :data:`ESTIMABLE`.
        init: starting guesses by name (a number, or one per material/obstacle); names
            not given start from ``params``.
        method: ``"lm"`` or ``"adam"``.
        n_iter: iteration cap (LM: simulations; Adam: gradient evaluations).
        xtol: LM stops when a proposed step ``|dz|_inf`` (a relative change of the
            positive quantities) falls below it.
        jacobian_solver: the nonlinear solver the LM copy of the model runs (default:
            the model's own; the implicit tangents do not depend on it).
        optimizer: the optax transformation for ``"adam"`` (default ``optax.adam(0.05)``).
        state0: the initial state (default: the rest shape).
        callback: ``callback(k, values)`` after each iteration with the current estimates.
        progress: show a progress bar.

    Returns:
        :class:`SysIdResult`.

    Raises:
        ControlError: see :class:`SysIdProblem`; an unknown method; bad ``init`` values.
    """
    if method not in ("lm", "adam"):
        raise ControlError(f"method must be 'lm' or 'adam', got {method!r}")
    for name, value in (init or {}).items():
        if name not in estimate:
            raise ControlError(f"init gives {name!r}, which is not being estimated ({list(estimate)})")
        current = _get(params, name)
        try:
            value = jnp.broadcast_to(jnp.asarray(value, jnp.float64), current.shape)
        except ValueError:
            raise ControlError(f"init[{name!r}] must be a number or {current.shape[0]} values") from None
        params = _set(params, name, value)
    problem = SysIdProblem(model, params, observation, estimate, state0=state0)
    start = time.perf_counter()
    if method == "adam":
        return _identify_adam(problem, optimizer, n_iter, callback, progress, start)
    solver = jacobian_solver or model.step.solver
    lm_model = dataclasses.replace(
        model, options=dataclasses.replace(model.options, adjoint=ImplicitForward(), solver=solver),
        step=dataclasses.replace(model.step, solver=solver))
    return _identify_lm(problem, lm_model, n_iter, xtol, callback, progress, start)


def _finish(problem: SysIdProblem, z, best_cost, cost, history, iterations, simulations, converged, start,
            std=None):
    return SysIdResult(values=problem.values(z), params=problem.unpack(jnp.asarray(z)), std=std,
                       cost=np.asarray(cost), history=history, iterations=iterations, simulations=simulations,
                       rms_residual=problem.sigma * math.sqrt(2 * best_cost / problem.n_residuals),
                       converged=converged, wall_time=time.perf_counter() - start)


def _identify_lm(problem: SysIdProblem, lm_model: Model, n_iter, xtol, callback, progress, start):
    p = int(sum(problem.sizes))

    # throw=False: a trial step whose simulation fails gets NaN residuals and is rejected like
    # one that raises the cost, and the program holds no host callback (the persistent
    # compilation cache keeps it).
    @jax.jit
    def residuals_and_jacobian(z):
        f = lambda z: problem.residuals(z, lm_model, throw=False)  # noqa: E731
        r, jt = jax.vmap(lambda t: jax.jvp(f, (z,), (t,)), out_axes=(None, 0))(jnp.eye(p))
        return r, jt.T

    z = np.asarray(problem.pack(problem.params))
    r, jac = (np.asarray(a) for a in residuals_and_jacobian(jnp.asarray(z)))
    if not np.all(np.isfinite(r)):
        problem.residuals(jnp.asarray(z), lm_model)  # raises SimulationError, naming the failed step
        raise ControlError("the simulation from the starting values gives non-finite residuals; check the "
                           "observation and the starting values")
    cost = [0.5 * float(r @ r)]
    history = [problem.values(z)]
    lam, converged, k = 1e-2, False, 0
    with progress_bar(progress) as bar:
        task = bar.add_task("system id (LM)", total=int(n_iter), stats=f"cost {cost[-1]:.4e}")
        while k < n_iter and not converged:
            grad, gn = jac.T @ r, jac.T @ jac
            scale = np.maximum(np.diag(gn), 1e-12 * max(np.diag(gn).max(), 1e-300))
            dz = np.linalg.solve(gn + lam * np.diag(scale), -grad)
            r_new, jac_new = (np.asarray(a) for a in residuals_and_jacobian(jnp.asarray(z + dz)))
            k += 1
            c_new = 0.5 * float(r_new @ r_new)
            if math.isfinite(c_new) and c_new < cost[-1]:
                z, r, jac = z + dz, r_new, jac_new
                lam = max(lam / 10.0, 1e-12)
            else:
                lam *= 10.0
            converged = float(np.abs(dz).max()) < xtol or lam > 1e12
            cost.append(min(c_new, cost[-1]) if math.isfinite(c_new) else cost[-1])
            history.append(problem.values(z))
            if callback is not None:
                callback(k, history[-1])
            bar.update(task, completed=k, stats=f"cost {cost[-1]:.4e}  lambda {lam:.1e}  |dz| {np.abs(dz).max():.1e}")
    std = None
    if problem.observation.noise is not None:
        cov = np.linalg.pinv(jac.T @ jac)  # residuals are scaled by the noise: this is cov(z)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        std, offset = {}, 0
        for name, size in zip(problem.estimate, problem.sizes):
            s = sd[offset:offset + size]
            if name == "nu":  # d nu / dz = nu (1 - 2 nu) for nu = 0.5 sigmoid(z)
                nu = history[-1]["nu"]
                s = s * (1.0 - 2.0 * nu)
            std[name] = s
            offset += size
    return _finish(problem, z, cost[-1], cost, history, k, k + 1, converged, start, std)


def _identify_adam(problem: SysIdProblem, optimizer, n_iter, callback, progress, start):
    history = []

    def record(k, z, loss):
        history.append(problem.values(z))
        if callback is not None:
            callback(k, history[-1])

    res = minimize(problem.cost, problem.pack(problem.params), optimizer=optimizer, n_iter=n_iter, callback=record,
                   progress=progress, description="system id (Adam)")
    z = np.asarray(res.best_theta)
    return _finish(problem, z, res.best_loss, res.loss, history, res.iterations, res.iterations, False, start)

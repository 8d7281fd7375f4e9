"""Implicit-Euler projective-dynamics steps, rollouts and static equilibria.

One step from ``(x_n, v_n)`` with time step ``h`` minimises::

    Phi(x) = 1/(2 h^2) |x - s|_M^2 + alpha/(2h) |x - x_n|_M^2 + E(x) + D(x; x_n)

with the inertial prediction ``s = x_n + h v_n + h^2 (g + M^-1 f_ext)``, ``E`` the elastic
and actuator energies and ``D`` the strain-rate damping; then ``v_{n+1} = (x_{n+1} - x_n)/h``.
The step stops when ``|grad Phi| <= tol |M s / h^2| + atol`` over the free degrees of
freedom or after ``max_iter`` iterations, and reports its iteration count and residual.

Actuator terms (``model.terms``) come in three kinds, told apart by the methods they have:

* ``energy_and_stress(F_sub, prep, a) -> (energy (m,), dE/dF (3, 3, m))`` on the tets
  ``prep.tets``: PD-style element terms (muscles); their PD matrix blocks
  ``prep.local_matrices`` ``(m, 4, 4)`` are added to the prefactored matrix.
* ``energy_and_gradient(x, prep, a) -> (energy, dE/dx (n, 3))``: vertex terms (cavity
  pressure as ``-p V_cavity(x)``); they leave the matrix alone (``prep.local_matrices``
  is ``None``).
* ``volume_targets(prep, a) -> (tets (m,), s (m,))``: the volume term of those tets
  targets ``tr(R^T F) = 3 s`` instead of 3 (pneumatic cells: ``s = a^(1/3)``).

Every term also has ``channel_names``, ``init_params()`` and
``prepare(model, params, dminv, volume)``.

Controls have one layout: an array ``(n_steps, n_channels)`` of actuator activations in
the order of ``model.channel_names`` (each actuator term's channels, in the order the
terms were given to :func:`softbody.model.build`). External forces are a separate
optional ``(n_steps, n, 3)`` array in newtons.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody import rotation as rot
from softbody.elastic import corotated, deformation_gradient, scatter_stress, strain_rate_damping
from softbody.model import Model, Params, Prepared, SceneError, State, prepare
from softbody.solvers import StepProblem

Array = jax.Array


class SimulationError(RuntimeError):
    """The simulation produced non-finite values; the message names the step and quantity."""


class StepInfo(eqx.Module):
    """Per-step solver statistics (arrays; stacked over steps in a rollout)."""

    iterations: Array
    evaluations: Array
    residual: Array  # |grad Phi| / (|M s / h^2| + atol / tol): the relative residual reached
    converged: Array


class Trajectory(eqx.Module):
    """A rollout: positions and velocities ``(n_steps + 1, n, 3)`` and per-step :class:`StepInfo`."""

    x: Array
    v: Array
    info: StepInfo


def _objective(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force, *, static: bool):
    """The step objective's ``evaluate`` and its convergence scale."""
    h = model.options.dt
    gravity = jnp.asarray(model.options.gravity)
    free = jnp.asarray(model.free_mask)
    mass = prep.mass
    load = mass * gravity + (0.0 if force is None else force)
    if static:
        s = x_n
        scale = jnp.sqrt(jnp.sum((load * free) ** 2))
    else:
        s = x_n + h * v_n + h * h * load / jnp.maximum(mass, 1e-300)
        s = jnp.where(free > 0, s, x_n)
        scale = jnp.sqrt(jnp.sum((mass * s * free) ** 2)) / h**2
    damped = not static
    f_n = deformation_gradient(model, prep.dminv, x_n)
    r_n = rot.quat_to_mat(q_n)
    iters = model.options.rotation_iterations

    # Each term's slice of the activation vector, and the volume targets (fixed per step).
    slices, offset = [], 0
    for term in model.terms:
        slices.append(activation[offset:offset + len(term.channel_names)])
        offset += len(term.channel_names)
    target = 3.0
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if hasattr(term, "volume_targets"):
            idx, s_t = term.volume_targets(tp, a)
            target = (jnp.full(model.n_tets, 3.0) if isinstance(target, float) else target).at[idx].set(3.0 * s_t)

    def evaluate(x, q):
        f = deformation_gradient(model, prep.dminv, x)
        r, q = rot.rotation(f, q, iters)
        energy, stress = corotated(f, r, prep.volume, prep.w_s, prep.w_v, target)
        energy = jnp.sum(energy)
        if damped:
            e_d, s_d = strain_rate_damping(f, f_n, r_n, prep.volume, prep.w_b, h)
            energy, stress = energy + jnp.sum(e_d), stress + s_d
        vertex_grad = 0.0
        for term, tp, a in zip(model.terms, prep.terms, slices):
            if hasattr(term, "energy_and_stress"):
                idx = jnp.asarray(tp.tets)
                e_t, s_t = term.energy_and_stress(f[:, :, idx], tp, a)
                energy = energy + jnp.sum(e_t)
                stress = stress.at[:, :, idx].add(s_t)
            if hasattr(term, "energy_and_gradient"):
                e_t, g_t = term.energy_and_gradient(x, tp, a)
                energy, vertex_grad = energy + e_t, vertex_grad + g_t
        grad = scatter_stress(model, prep.dminv, stress) + vertex_grad
        if static:
            phi = energy - jnp.sum(load * x)
            grad = grad - load
        else:
            dx, dn = x - s, x - x_n
            phi = (energy + 0.5 * jnp.sum(mass * dx * dx) / h**2
                   + 0.5 * jnp.sum(prep.mass_alpha * dn * dn) / h)
            grad = grad + mass * dx / h**2 + prep.mass_alpha * dn / h
        return phi, grad * free, q

    return evaluate, scale


def _solve(model: Model, prep: Prepared, state: State, activation, force, *, static: bool):
    evaluate, scale = _objective(model, prep, state.x, state.v, state.rot, activation, force, static=static)
    solver = model.linear_solver
    pattern = model.pattern
    opts = model.options
    free = jnp.asarray(model.free_mask)
    problem = StepProblem(
        evaluate=evaluate,
        precondition=lambda g: solver.solve(pattern, prep.factor, g),
        matvec=lambda x: pattern.matvec(prep.data, x),
        diagonal=prep.data[jnp.asarray(model.diag_to_data)][:, None],
        x_n=state.x, v_n=state.v, mass=prep.mass, free=free, dt=0.0 if static else opts.dt,
        time=state.t, obstacles=tuple(zip(model.obstacles, prep.obstacles)))
    threshold = opts.tol * scale + opts.atol
    x0 = state.x if static else jnp.where(free > 0, state.x + opts.dt * state.v, state.x)
    sol = model.method.run(problem, x0, state.rot, threshold, opts.max_iter)
    info = StepInfo(iterations=sol.iterations, evaluations=sol.evaluations,
                    residual=sol.gnorm / (scale + opts.atol / opts.tol),
                    converged=sol.gnorm <= threshold)
    return sol, info


def _activation(model: Model, activation):
    if activation is None:
        return jnp.zeros(model.n_channels)
    return jnp.asarray(activation)


def step(model: Model, prep: Prepared, state: State, activation=None, force=None) -> tuple[State, StepInfo]:
    """One implicit-Euler PD step.

    Arguments:
        model: the compiled scene; prep: :func:`softbody.model.prepare` of its params.
        state: the current :class:`State`.
        activation: ``(n_channels,)`` actuator activations, or ``None`` (zeros).
        force: ``(n, 3)`` external forces in newtons, or ``None``.

    Returns:
        ``(next_state, info)``.
    """
    sol, info = _solve(model, prep, state, _activation(model, activation), force, static=False)
    v = (sol.x - state.x) / model.options.dt
    return State(x=sol.x, v=v, rot=sol.q, t=state.t + model.options.dt), info


def _check_controls(model: Model, controls, forces, n_steps):
    if controls is not None:
        controls = jnp.asarray(controls)
        if controls.ndim != 2 or controls.shape[1] != model.n_channels:
            raise SceneError(
                f"controls must have shape (n_steps, {model.n_channels}) (channels {list(model.channel_names)}), "
                f"got {tuple(controls.shape)}")
        n_steps = controls.shape[0] if n_steps is None else n_steps
        if controls.shape[0] != n_steps:
            raise SceneError(f"controls have {controls.shape[0]} rows but n_steps = {n_steps}")
    if forces is not None:
        forces = jnp.asarray(forces)
        if forces.ndim != 3 or forces.shape[1:] != (model.n_vertices, 3):
            raise SceneError(f"forces must have shape (n_steps, {model.n_vertices}, 3), got {tuple(forces.shape)}")
        n_steps = forces.shape[0] if n_steps is None else n_steps
        if forces.shape[0] != n_steps:
            raise SceneError(f"forces have {forces.shape[0]} rows but n_steps = {n_steps}")
    if n_steps is None or int(n_steps) < 1:
        raise SceneError("give n_steps >= 1 (or controls/forces whose first axis is the number of steps)")
    return controls, forces, int(n_steps)


@functools.partial(jax.jit, static_argnums=(0, 5))
def _rollout(model: Model, params: Params, state0: State, controls, forces, n_steps: int):
    prep = prepare(model, params)

    def body(carry, inputs):
        state, bad = carry
        a, f = inputs
        a = _activation(model, a)
        new, info = step(model, prep, state, a, f)
        finite = jnp.all(jnp.isfinite(new.x)) & jnp.all(jnp.isfinite(new.v))
        new = jax.tree.map(lambda n, o: jnp.where(bad, o, n), new, state)
        return (new, bad | ~finite), (new.x, new.v, info, bad | ~finite)

    (_, _), (xs, vs, info, bad) = jax.lax.scan(body, (state0, jnp.asarray(False)), (controls, forces),
                                               length=n_steps)
    xs = jnp.concatenate([state0.x[None], xs])
    vs = jnp.concatenate([state0.v[None], vs])
    return Trajectory(x=xs, v=vs, info=info), bad


def rollout(model: Model, params: Params, state0: State, controls=None, forces=None,
            n_steps: int | None = None) -> Trajectory:
    """Simulate ``n_steps`` implicit-Euler steps (one compiled ``lax.scan``).

    Arguments:
        model, params: from :func:`softbody.model.build`.
        state0: initial :class:`State` (:func:`softbody.model.initial_state`).
        controls: ``(n_steps, n_channels)`` activations, or ``None``.
        forces: ``(n_steps, n, 3)`` external forces, or ``None``.
        n_steps: number of steps (taken from controls/forces when omitted).

    Returns:
        A :class:`Trajectory` with ``x, v`` of shape ``(n_steps + 1, n, 3)`` (the first row is
        ``state0``) and per-step statistics.

    Raises:
        SceneError: bad control or force shapes (before compiling).
        SimulationError: the state became non-finite; names the first bad step and quantity.
            Under an outer ``jit``/``grad`` the check cannot raise a Python error; it
            becomes an ``equinox.error_if`` runtime error instead.
    """
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps)
    traj, bad = _rollout(model, params, state0, controls, forces, n_steps)
    if isinstance(bad, jax.core.Tracer):
        xs = eqx.error_if(traj.x, jnp.any(bad), "softbody: the simulation became non-finite (NaN/inf)")
        return Trajectory(x=xs, v=traj.v, info=traj.info)
    bad = np.asarray(bad)
    if bad.any():
        k = int(np.argmax(bad))
        xs, vs = np.asarray(traj.x[k + 1]), np.asarray(traj.v[k + 1])
        what = "positions" if not np.isfinite(xs).all() else "velocities"
        res = float(traj.info.residual[k])
        raise SimulationError(
            f"step {k}: {what} became non-finite (step residual {res:.3g}, "
            f"{int(traj.info.iterations[k])} iterations). Reduce dt, check loads and activations, "
            "or raise max_iter.")
    return traj


def solve_static(model: Model, params: Params, force=None, activation=None, x0=None):
    """Static equilibrium under gravity, external forces and activations.

    Minimises ``E(x) - f . x`` with the same PD machinery (no inertia, no damping).

    Arguments:
        force: ``(n, 3)`` external forces in newtons, or ``None``.
        activation: ``(n_channels,)`` or ``None``.
        x0: initial guess ``(n, 3)`` (default: the rest shape).

    Returns:
        ``(x, info)``: positions ``(n, 3)`` and :class:`StepInfo`.

    Raises:
        SceneError: when the model has no fixed vertices (the equilibrium is not unique).
    """
    if len(model.fixed) == 0:
        raise SceneError("a static solve needs fixed vertices (build the model with fixed=...)")
    return _solve_static(model, params, force, _activation(model, activation), x0)


@functools.partial(jax.jit, static_argnums=0)
def _solve_static(model, params, force, activation, x0):
    from softbody.model import initial_state

    prep = prepare(model, params, static=True)
    state = initial_state(model, params, x=x0)
    sol, info = _solve(model, prep, state, activation, force, static=True)
    return sol.x, info

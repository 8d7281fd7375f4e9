"""Implicit-Euler projective-dynamics steps, rollouts and static equilibria.

One step from ``(x_n, v_n)`` with time step ``h`` minimises::

    Phi(x) = 1/(2 h^2) |x - s|_M^2 + alpha/(2h) |x - x_n|_M^2 + E(x) + D(x; x_n)

with the inertial prediction ``s = x_n + h v_n + h^2 (g + M^-1 f_ext)``, ``E`` the elastic
and actuator energies and ``D`` the strain-rate damping; then ``v_{n+1} = (x_{n+1} - x_n)/h``.
The step stops when ``|grad Phi| <= tol |M s / h^2| + atol`` over the free degrees of
freedom or after ``max_iter`` iterations, and reports its iteration count and residual.

Actuator terms (``model.terms``) come in three kinds, one base class each
(:mod:`softbody._interfaces`):

* :class:`~softbody._interfaces.ElementActuator`,
  ``energy_and_stress(F_sub, prep, a) -> (energy (m,), dE/dF (3, 3, m))`` on the tets
  ``prep.tets``: PD-style element terms (muscles); their PD matrix blocks
  ``prep.local_matrices`` ``(m, 4, 4)`` are added to the prefactored matrix.
* :class:`~softbody._interfaces.VertexActuator`,
  ``energy_and_gradient(x, prep, a) -> (energy, dE/dx (n, 3))``: vertex terms (cavity
  pressure as ``-p V_cavity(x)``); they leave the matrix alone (``prep.local_matrices``
  is ``None``).
* :class:`~softbody._interfaces.VolumeActuator`,
  ``volume_targets(prep, a) -> (tets (m,), s (m,))``: the volume term of those tets
  targets ``det F = s^3`` instead of 1 (pneumatic cells: ``s = a^(1/3)``).

Every term also has ``channel_names``, ``channel_bounds()``, ``init_params()`` and
``prepare(model, params, dminv, volume)``. Concrete activations outside a channel's bounds
(a muscle's [0, 1], a cavity's pressure limits, ...) are refused with a :class:`SceneError`
before anything compiles; inside a traced computation (an optimisation) they are clipped
to the bounds, with zero gradient beyond: parametrise bounded controls there (e.g.
:class:`softbody.control.ControlGrid`).

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

from softbody._types import Model, Params, Prepared, SceneError, State, StepInfo
from softbody.elastic import deformation_gradient
from softbody.gradients import segment_length
from softbody.model import initial_state, prepare
from softbody.rotation import det3

Array = jax.Array


class SimulationError(RuntimeError):
    """The simulation produced non-finite values or inverted tets; the message names the
    step, the quantity and the actuator activations there."""


#: What to try when a simulation inverts tets or blows up under an actuator load.
_FIXES = ("Lower the load or the activations, refine the mesh where it deforms most, or stiffen "
          "the material (a pressurised cavity past its pressure maximum balloons without bound: "
          "drive it by volume with CavityVolume instead)")


def _inverted(model: Model, prep: Prepared, x) -> Array:
    """Number of tets with ``det F <= 0`` at positions ``x`` ``(n, 3)``."""
    return jnp.sum(det3(deformation_gradient(model, prep.dminv, x)) <= 0)


def _describe(model: Model, activation) -> str:
    """``"activations {channel: value, ...}"`` (or ``"no actuators"``) for error messages."""
    if model.n_channels == 0:
        return "no actuators"
    values = np.asarray(activation).ravel()
    pairs = (f"{n!r}: {v:.6g}" for n, v in zip(model.channel_names, values))
    return "activations {" + ", ".join(pairs) + "}"


def _row(controls, k: int):
    """Row ``k`` of the controls (``()`` when there are none)."""
    return () if controls is None else controls[k]


class Trajectory(eqx.Module):
    """A rollout: positions and velocities ``(n_steps + 1, n, 3)`` and per-step :class:`StepInfo`."""

    x: Array
    v: Array
    info: StepInfo


def _check_bounds(model: Model, controls, where) -> None:
    """Refuse concrete activations outside their channels' bounds (traced ones pass: the
    terms clip them). ``controls`` is ``(n_channels,)`` or ``(n_steps, n_channels)``;
    ``where(index)`` names an offending entry in the message."""
    if controls is None or isinstance(controls, jax.core.Tracer) or model.n_channels == 0:
        return
    values = np.asarray(controls)
    lower, upper = model.channel_bounds
    bad = np.argwhere((values < lower) | (values > upper))
    if len(bad):
        index = tuple(int(i) for i in bad[0])
        c = index[-1]
        raise SceneError(
            f"{where(index)} = {values[index]:.6g} is outside channel {model.channel_names[c]!r}'s range "
            f"[{lower[c]:.6g}, {upper[c]:.6g}] ({len(bad)} value(s) out of range); give values in range "
            "(to optimise bounded controls, parametrise them, e.g. softbody.control.ControlGrid)")


def _activation(model: Model, activation):
    if activation is None:
        return jnp.zeros(model.n_channels)
    activation = jnp.asarray(activation)
    if activation.shape != (model.n_channels,):
        raise SceneError(f"activation must have shape ({model.n_channels},) (channels {list(model.channel_names)}), "
                         f"got {tuple(activation.shape)}")
    _check_bounds(model, activation, lambda i: f"activation[{i[0]}]")
    return activation


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
    sol, info = model.options.adjoint.solve(model, prep, state, _activation(model, activation), force, static=False)
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
    for name, value in (("controls", controls), ("forces", forces)):
        if value is None or isinstance(value, jax.core.Tracer):
            continue  # traced: the in-loop check names the step instead
        bad_rows = ~np.isfinite(np.asarray(value)).reshape(value.shape[0], -1).all(axis=1)
        if bad_rows.any():  # numpy, not jnp: under an outer jit a jnp test of a constant is traced
            raise SceneError(f"{name} hold NaN or inf (first at step {int(np.argmax(bad_rows))}); give finite values")
    _check_bounds(model, controls, lambda i: f"controls[{i[0]}, {i[1]}] (step {i[0]})")
    if n_steps is None or int(n_steps) < 1:
        raise SceneError("give n_steps >= 1 (or controls/forces whose first axis is the number of steps)")
    return controls, forces, int(n_steps)


@functools.partial(jax.jit, static_argnums=(0, 5))
def _rollout(model: Model, params: Params, state0: State, controls, forces, n_steps: int):
    prep = prepare(model, params)

    def body(carry, inputs):
        state, bad = carry
        a, f = inputs
        new, info = step(model, prep, state, _activation(model, a), f)
        # A non-finite residual is a step that could not start (an overflowing load, say):
        # the positions it returns are finite but not a solution.
        finite = jnp.all(jnp.isfinite(new.x)) & jnp.all(jnp.isfinite(new.v)) & jnp.isfinite(info.residual)
        new = jax.tree.map(lambda n, o: jnp.where(bad, o, n), new, state)
        return (new, bad | ~finite), (new.x, new.v, info, bad | ~finite)

    inputs = (controls, forces)
    inverted0 = _inverted(model, prep, state0.x)
    carry = (state0, jnp.asarray(False))
    if model.options.adjoint.segment_checkpoints and n_steps > 3:
        # Nested scans: the outer one keeps only segment-start states; each segment is
        # rematerialised in the backward pass (O(sqrt(n_steps)) states in memory).
        k = segment_length(n_steps)
        segments = jax.tree.map(lambda a: a.reshape((n_steps // k, k) + a.shape[1:]), inputs)

        @jax.checkpoint
        def segment(carry, seg_inputs):
            return jax.lax.scan(body, carry, seg_inputs, length=k)

        _, (xs, vs, info, bad) = jax.lax.scan(segment, carry, segments, length=n_steps // k)
        xs, vs, info, bad = jax.tree.map(lambda a: a.reshape((n_steps,) + a.shape[2:]), (xs, vs, info, bad))
    else:
        _, (xs, vs, info, bad) = jax.lax.scan(body, carry, inputs, length=n_steps)
    xs = jnp.concatenate([state0.x[None], xs])
    vs = jnp.concatenate([state0.v[None], vs])
    return Trajectory(x=xs, v=vs, info=info), bad, inverted0


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
        SceneError: bad control or force shapes, or NaN/inf in them (before compiling).
        SimulationError: the state or a step's residual became non-finite, or a step ended with more inverted
            tets (``det F <= 0``) than ``state0`` had; names the first bad step, the
            quantity and the activations there. Under an outer ``jit``/``grad`` the check
            cannot raise a Python error; it becomes an ``equinox.error_if`` runtime error
            instead.
    """
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps)
    traj, bad, inverted0 = _rollout(model, params, state0, controls, forces, n_steps)
    new_inversions = traj.info.inverted > inverted0
    if isinstance(bad, jax.core.Tracer) or isinstance(inverted0, jax.core.Tracer):
        xs = eqx.error_if(traj.x, jnp.any(bad), "softbody: the simulation became non-finite (NaN/inf)")
        xs = eqx.error_if(xs, jnp.any(new_inversions),
                          f"softbody: the simulation inverted tets. {_FIXES}.")
        return Trajectory(x=xs, v=traj.v, info=traj.info)
    bad, new_inversions = np.asarray(bad), np.asarray(new_inversions)
    first_bad = int(np.argmax(bad)) if bad.any() else None
    first_inverted = int(np.argmax(new_inversions)) if new_inversions.any() else None
    # Inverted tets usually come first and make the objective NaN: name the cause.
    if first_inverted is not None and (first_bad is None or first_inverted <= first_bad):
        k = first_inverted
        raise SimulationError(
            f"step {k}: {int(traj.info.inverted[k])} tets inverted (det F <= 0; the initial "
            f"state had {int(inverted0)}) under {_describe(model, _row(controls, k))}. {_FIXES}.")
    if first_bad is not None:
        k = first_bad
        xs, vs = np.asarray(traj.x[k + 1]), np.asarray(traj.v[k + 1])
        what = ("positions" if not np.isfinite(xs).all() else
                "velocities" if not np.isfinite(vs).all() else "the force residual")
        res = float(traj.info.residual[k])
        raise SimulationError(
            f"step {k}: {what} became non-finite (step residual {res:.3g}, "
            f"{int(traj.info.iterations[k])} iterations; {_describe(model, _row(controls, k))}). "
            f"Reduce dt, check loads and activations, or raise max_iter. {_FIXES}.")
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
        SimulationError: the solution is non-finite (e.g. the load exceeds what the body can
            carry, such as a cavity pressure past its maximum, where no equilibrium exists),
            or has more inverted tets than ``x0``; names the count and the activations.
            Under an outer ``jit``/``grad`` it is an ``equinox.error_if`` runtime error.
    """
    if len(model.fixed) == 0:
        raise SceneError("a static solve needs fixed vertices (build the model with fixed=...)")
    activation = _activation(model, activation)
    x, info, inverted0 = _solve_static(model, params, force, activation, x0)
    finite = jnp.all(jnp.isfinite(x))
    if isinstance(x, jax.core.Tracer) or isinstance(info.inverted, jax.core.Tracer):
        x = eqx.error_if(x, ~finite, "softbody: the static solve became non-finite (NaN/inf)")
        x = eqx.error_if(x, info.inverted > inverted0,
                         f"softbody: the static solve inverted tets. {_FIXES}.")
        return x, info
    if not bool(finite):
        raise SimulationError(
            f"the static solve became non-finite after {int(info.iterations)} iterations under "
            f"{_describe(model, activation)}: no equilibrium was found near x0 (the load may "
            f"exceed what the body can carry). {_FIXES}.")
    if int(info.inverted) > int(inverted0):
        raise SimulationError(
            f"the static solution has {int(info.inverted)} inverted tets (det F <= 0; x0 had "
            f"{int(inverted0)}) under {_describe(model, activation)}. {_FIXES}.")
    return x, info


@functools.partial(jax.jit, static_argnums=0)
def _solve_static(model, params, force, activation, x0):
    prep = prepare(model, params, static=True)
    state = initial_state(model, params, x=x0)
    sol, info = model.options.adjoint.solve(model, prep, state, activation, force, static=True)
    return sol.x, info, _inverted(model, prep, state.x)

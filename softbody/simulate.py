"""Implicit-Euler projective-dynamics steps, rollouts and static equilibria.

One step from ``(x_n, v_n)`` with time step ``h`` minimises::

    Phi(x) = 1/(2 h^2) |x - s|_M^2 + alpha/(2h) |x - x_n|_M^2 + E(x) + D(x; x_n)

with the inertial prediction ``s = x_n + h v_n + h^2 (g + M^-1 f_ext)``, ``E`` the elastic
and actuator energies and ``D`` the strain-rate damping; then ``v_{n+1} = (x_{n+1} - x_n)/h``.
The step stops when ``|grad Phi| <= tol |M s / h^2| + atol`` over the free degrees of
freedom or after ``max_iter`` iterations, and reports its iteration count, residual and
result code (:class:`~softbody._types.RESULTS`: success, max_iterations, nonfinite,
inverted, overflow). :func:`rollout` and :func:`solve_static` raise :class:`SimulationError` for
any step that did not succeed unless called with ``throw=False``; then the codes are in
``info.result``. The message is the same whether the call is traced (under an outer
``jax.jit`` or ``jax.grad``, where the compiled program fails with it at run time, as a
``jax.errors.JaxRuntimeError``) or not.

Energy terms (``model.terms``: actuators and user terms) come in four kinds, one base class each
(:mod:`softbody._interfaces`):

* :class:`~softbody._interfaces.ElementTerm`,
  ``energy_and_stress(F_sub, prep, a) -> (energy (m,), dE/dF (3, 3, m))`` on the tets
  ``prep.tets``: PD-style element terms (muscles); their PD matrix blocks
  ``prep.local_matrices`` ``(m, 4, 4)`` are added to the prefactored matrix.
* :class:`~softbody._interfaces.VertexTerm`,
  ``energy_and_gradient(x, prep, a) -> (energy, dE/dx (n, 3))``: vertex terms (cavity
  pressure as ``-p V_cavity(x)``, springs); those with a ``stencil()`` add ``blocks(prep)``
  ``(m, k, k)`` on vertex tuples to the prefactored matrix, the others leave it alone.
* :class:`~softbody._interfaces.VolumeTerm`,
  ``volume_targets(prep, a) -> (tets (m,), s (m,))``: the volume term of those tets
  targets ``det F = s^3`` instead of 1 (pneumatic cells: ``s = a^(1/3)``).
* :class:`~softbody._interfaces.DissipationTerm`,
  ``dissipation(v, x, prep, a) -> (D, dD/dv (n, 3))``: forces ``-dD/dv`` of the velocities
  (air drag and wind); a step adds ``h D((x - x_n)/h)`` with the geometry at ``x_n``.

Every term also has ``channel_names``, ``channel_bounds()``, ``init_params()`` and
``prepare(model, params, dminv, volume)``. Concrete activations outside a channel's bounds
(a muscle's [0, 1], a cavity's pressure limits, ...) are refused with a :class:`SceneError`
before anything compiles; inside a traced computation (under ``jax.jit``, ``jax.grad`` or
``jax.vmap``, e.g. an optimisation) their values are unknown, so they are clipped to the
bounds without an error or a flag (checking would need a host callback in the compiled
program), with zero gradient beyond: parametrise bounded controls there (e.g.
:class:`softbody.control.ControlGrid`).

Controls have one layout: an array ``(n_steps, n_channels)`` of actuator activations in
the order of ``model.channel_names`` (each actuator term's channels: the bodies' terms in
the order of the bodies, then the scene's joint actuators). External forces are a separate
optional ``(n_steps, n, 3)`` array in newtons.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import Integrator
from softbody._types import RESULTS, Model, Params, Prepared, SceneError, State, StepInfo
from softbody.contact.report import report
from softbody.elastic import deformation_gradient
from softbody.model import clamp, initial_state, prepare
from softbody.objective import accelerations, step_problem
from softbody.rotation import cold_start, det3

Array = jax.Array


class SimulationError(RuntimeError):
    """A step failed (:class:`~softbody._types.RESULTS`): it stopped at the iteration cap,
    became non-finite, inverted tets, overflowed a contact search or let surfaces pass through each other. The message names the first failing step, what
    failed and the fix. Traced (under an outer ``jax.jit``/``jax.grad``) the compiled
    program fails with the same message at run time instead: a
    ``jax.errors.JaxRuntimeError`` that contains it (from a native check on CPU; from
    equinox elsewhere, an ``equinox.EquinoxRuntimeError`` under ``equinox.filter_jit``)."""


#: What to try when a simulation inverts tets or blows up under an actuator load.
_FIXES = ("Lower the load or the activations, refine the mesh where it deforms most, or stiffen "
          "the material (a pressurised cavity past its pressure maximum balloons without bound: "
          "drive it by volume with CavityVolume instead)")


def inverted_tets(model: Model, prep: Prepared, x) -> Array:
    """Number of tets with ``det F <= 0`` at positions ``x`` ``(n, 3)`` (an int array)."""
    return jnp.sum(det3(deformation_gradient(model, prep.dminv, x)) <= 0)


def step_result(new: State, info: StepInfo, inverted0, *, inputs_finite=True) -> tuple[Array, Array]:
    """The result code of one step (:class:`~softbody._types.RESULTS`) and whether it ended finite.

    A non-finite residual is a step that could not start (an overflowing load, say): the
    positions it returns are finite but not a solution, so it counts as non-finite.

    Arguments:
        new: the state the step ended in; info: its :class:`StepInfo`.
        inverted0: inverted tets at the rollout's start (:func:`inverted_tets`): a step
            is ``inverted`` where it ends with more.
        inputs_finite: false where the step's inputs were not finite (it is then
            ``nonfinite`` whatever it computed).

    Returns:
        ``(code, finite)``: the int32 code and the bool ``finite``.
    """
    finite = (jnp.all(jnp.isfinite(new.x)) & jnp.all(jnp.isfinite(new.v)) & jnp.isfinite(info.residual)
              & inputs_finite)
    code = RESULTS.of(finite=finite, converged=info.converged, inverted=info.inverted, inverted0=inverted0,
                      overflow=info.overflow, tunnelled=info.tunnelled)
    return code, finite


#: What a failure message can name, in the order of its branch: the iteration cap, the
#: positions / velocities / force residual going non-finite, inverted tets, an overflowing
#: contact search, surfaces that passed through each other.
_VARIANTS = ("max_iterations", "positions", "velocities", "force residual", "inverted", "overflow", "tunnelled")

#: The message of a step whose contact search between bodies overflowed.
_OVERFLOW = ("{where}: the contact search between bodies found more candidate pairs than its capacity holds, so "
             "contacts may be missing; rebuild with a larger capacity, softbody.contact.pairs.Touch(..., capacity=...) "
             "(softbody.contact.broad_phase.required_capacity measures what a configuration needs).")


#: The message of a step in which surfaces kept apart by rows between bodies passed through each other.
_TUNNELLED = ("{where}: surfaces kept apart by rows between bodies passed through each other (a vertex crossed a "
              "triangle or an edge crossed an edge of the other body during the step; the rows, chosen at the step's "
              "start and predicted end, missed it): a body moved farther in one step than the contact search sees. "
              "Reduce Options.dt (now {dt:g} s) or the speeds.")


def _step_templates(model: Model, call: str = "rollout") -> tuple[str, ...]:
    """One message per :data:`_VARIANTS` entry for a failing rollout step (``{step}``
    stands for its index); ``call`` names the function in the advice."""
    o = model.options
    cap = (f"step {{step}}: stopped at the iteration cap ({o.max_iter} iterations, Options.max_iter) without "
           f"meeting its tolerance (relative force residual <= tol = {o.tol:g}); {call}(..., throw=False) returns "
           f"the residual it reached in info.residual. Raise Options.max_iter, loosen Options.tol, or reduce "
           f"Options.dt (now {o.dt:g} s).")
    nonfinite = ("step {step}: the %s became non-finite (NaN/inf). Reduce dt, check the loads and the "
                 f"activations at that step, or raise max_iter. {_FIXES}. (A system matrix that is not "
                 "positive definite, from a non-positive mass, stiffness or time step, shows here too.)")
    inverted = (f"step {{step}}: more tets inverted (det F <= 0) than in the initial state; {call}(..., "
                f"throw=False) returns the counts in info.inverted. {_FIXES}.")
    return (cap, *(nonfinite % what for what in _VARIANTS[1:4]), inverted, _OVERFLOW.format(where="step {step}"),
            _TUNNELLED.format(where="step {step}", dt=o.dt))


def _static_templates(model: Model) -> tuple[str, ...]:
    """As :func:`_step_templates` for :func:`solve_static` (no step)."""
    o = model.options
    cap = (f"the static solve stopped at the iteration cap ({o.max_iter} iterations, Options.max_iter) without "
           f"meeting its tolerance (relative force residual <= tol = {o.tol:g}); solve_static(..., throw=False) "
           "returns the residual it reached in info.residual. Raise Options.max_iter or loosen Options.tol.")
    nonfinite = ("the static solve's %s became non-finite (NaN/inf): no equilibrium was found near x0 (the load "
                 f"may exceed what the body can carry). {_FIXES}.")
    inverted = (f"the static solution has more inverted tets (det F <= 0) than x0; solve_static(..., "
                f"throw=False) returns the count in info.inverted. {_FIXES}.")
    return (cap, *(nonfinite % what for what in _VARIANTS[1:4]), inverted, _OVERFLOW.format(where="the static solve"),
            _TUNNELLED.format(where="the static solve", dt=o.dt))


@dataclasses.dataclass(frozen=True)
class _Messages:
    """The failure messages of ``n_steps`` steps, entry ``variant * n_steps + step``
    (the branches of the run-time check). Formatted on demand: only the entry that is
    raised is ever built."""

    templates: tuple[str, ...]
    n_steps: int

    def __len__(self) -> int:
        return len(self.templates) * self.n_steps

    def __getitem__(self, index) -> str:
        variant, k = divmod(int(index), self.n_steps)
        return self.templates[variant].replace("{step}", str(k))


def _first_failure(result, x_after, v_after):
    """``(failed, branch)``: whether any step's code is not success, and the branch
    ``variant * n_steps + k`` of the first failing step ``k`` (``result (n_steps,)``;
    ``x_after``, ``v_after`` ``(n_steps, n, 3)`` the states the steps ended in)."""
    failed = result != int(RESULTS.success)
    k = jnp.argmax(failed)
    code = result[k]
    what = jnp.where(~jnp.all(jnp.isfinite(x_after[k])), 1, jnp.where(~jnp.all(jnp.isfinite(v_after[k])), 2, 3))
    variant = jnp.select([code == int(RESULTS.max_iterations), code == int(RESULTS.nonfinite),
                          code == int(RESULTS.overflow), code == int(RESULTS.tunnelled)], [0, what, 5, 6], 4)
    return jnp.any(failed), variant * result.shape[0] + k


def _raise_failure(tree, failed, branch, messages: _Messages):
    """``tree`` unchanged; raise ``messages[branch]`` when ``failed``: a
    :class:`SimulationError` now when the flags are concrete, else (traced) a run-time
    error of the compiled program with the same text (:func:`_fail_at_run_time`)."""
    if isinstance(failed, jax.core.Tracer) or isinstance(branch, jax.core.Tracer):
        return _fail_at_run_time(tree, failed, branch, messages)
    if bool(failed):
        raise SimulationError(messages[int(branch)])
    return tree


def _fail_at_run_time(tree, failed, branch, messages: _Messages):
    """``tree`` unchanged; the compiled program fails with ``messages[branch]`` when
    ``failed`` (traced flags), raising a ``jax.errors.JaxRuntimeError`` that contains it.

    On CPU with the native library this is an XLA FFI call (:data:`softbody.native.CHECK_TARGET`,
    given the messages' templates as an attribute), which keeps the program fit for JAX's
    persistent compilation cache; elsewhere (other platforms, no C++ compiler) it is
    ``equinox.branched_error_if``, a host callback. Either is tied to ``tree`` (the check
    returns a zero that is added to every leaf), so it runs when ``tree`` is used, and, as
    equinox's, to its primal values only; under ``vmap`` the native check takes the members
    one by one.
    """
    from softbody import native

    if not native.available():
        return eqx.branched_error_if(tree, failed, branch, messages)
    templates = "\x1f".join(messages.templates)

    def on_cpu(failed, branch):
        return jax.ffi.ffi_call(native.CHECK_TARGET, jax.ShapeDtypeStruct((), jnp.int32), vmap_method="sequential")(
            failed, branch, messages=templates, n_steps=np.int64(messages.n_steps))

    def elsewhere(failed, branch):
        return eqx.branched_error_if(jnp.zeros((), jnp.int32), failed, branch, messages)

    token = jax.lax.platform_dependent(jnp.asarray(failed, bool), jnp.asarray(branch, jnp.int32), cpu=on_cpu,
                                       default=elsewhere)
    return jax.tree.map(lambda leaf: leaf + token.astype(jnp.result_type(leaf)), tree)  # 0, kept by XLA


@contextlib.contextmanager
def _forward_mode_hint():
    """Name the fix when forward-mode autodiff (``jax.jvp``/``jacfwd``) meets the reverse-mode
    :class:`~softbody.gradients.Implicit` adjoint (JAX's own message names neither)."""
    try:
        yield
    except TypeError as err:
        if "forward-mode" in str(err) and "custom_vjp" in str(err):
            raise TypeError(
                "softbody: the Implicit adjoint differentiates in reverse mode (jax.grad, jax.vjp) only; "
                "for forward mode (jax.jvp, jax.jacfwd) build the scene with "
                "Options(adjoint=softbody.ImplicitForward())") from err
        raise


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


class ImplicitEuler(Integrator):
    """Implicit-Euler PD steps (the module docstring), each solved by the scene's composed
    step (``model.step``) and differentiated by its adjoint (``model.options.adjoint``):
    the default integrator of :func:`rollout` and the closed-loop policies
    (``Options(integrator=None)``). In a scene with a prescribed ``motion`` the fixed
    vertices end a step where the motion puts them at ``t + dt`` (their velocity is their
    displacement over the step divided by ``dt``). It keeps no memory."""

    def init(self, model: Model, params: Params, state0: State) -> tuple[Prepared, tuple]:
        return prepare(model, params), ()

    def step(self, model: Model, prep: Prepared, state: State, memory, activation, force):
        start = _step_start(model, prep, state)
        sol, info = model.options.adjoint.solve(model, prep, start, activation, force)
        v = (sol.x - state.x) / prep.dt
        return State(x=sol.x, v=v, rot=sol.q, t=state.t + prep.dt, contact=sol.forces), memory, info

    def templates(self, model: Model, call: str) -> tuple[str, ...]:
        return _step_templates(model, call)

    def starts(self, model: Model, prep: Prepared, xs, vs, t0, activation0, force0):
        """What each step of a computed trajectory solved: ``(x, v, t)``, the ``(T, n, 3)``
        positions, velocities and ``(T,)`` times its implicit-Euler step (of size
        ``prep.dt``) started from (before a clamp motion moved the fixed vertices), from the
        ``(T + 1, n, 3)`` ``xs``, ``vs`` and the first step's activation and force
        (:func:`contact_forces` rebuilds the steps from them)."""
        return xs[:-1], vs[:-1], t0 + prep.dt * jnp.arange(xs.shape[0] - 1)


class BDF2(ImplicitEuler):
    """Second-order backward differentiation (BDF2) PD steps: ``Options(integrator=BDF2())``.

    With ``h`` the time step, BDF2 for ``x' = v``, ``M v' = f(x, v)`` reads
    ``x_{n+1} = xi + h' v_{n+1}``, ``v_{n+1} = nu + h' M^-1 f_{n+1}`` with ``h' = 2h/3``,
    ``xi = (4 x_n - x_{n-1})/3`` and ``nu = (4 v_n - v_{n-1})/3``: exactly an implicit-Euler
    step of size ``h'`` from the state ``(xi, nu)``. So each step minimises the ordinary
    step objective (the same elastic, actuator, damping and contact terms, the same
    solvers and adjoints) with the inertial prediction ``xi + h' nu + h'^2 M^-1 f_ext`` and
    the PD matrix ``M/h'^2 + L``, prefactored once per rollout, and ``v_{n+1} =
    (x_{n+1} - xi)/h'`` (also the velocity mass damping, strain-rate damping and friction
    see). The step ends at ``t + h``: obstacles and clamp motions are taken there. The
    memory is ``(x_{n-1}, v_{n-1})``; the first step takes the past from the initial
    accelerations ``a_0`` (:func:`softbody.objective.accelerations`, one force
    evaluation): ``x_{-1} = x_0 - h v_0 + h^2 a_0 / 2``, ``v_{-1} = v_0 - h a_0``, second-order
    accurate, so the first step's velocity error is ``O(h^2)`` and the global error stays
    second order (a plainer start, ``x_{-1} = x_0 - h v_0``, ``v_{-1} = v_0``, errs by
    ``O(h)`` in the first velocity and makes the method first order).

    The local error is ``O(h^3)`` and the method is A-stable (L-stable in the linear
    test equation), with far less numerical damping than implicit Euler: see
    ``tests/test_bdf2.py`` for the observed order against a diffrax reference.
    """

    @staticmethod
    def _past(model: Model, prep: Prepared, state: State, activation, force):
        """``(x_{-1}, v_{-1})``: the second-order accurate past of a first step from ``state``."""
        h = model.options.dt
        a, _ = accelerations(model, prep, state, activation, force)
        return state.x - h * state.v + 0.5 * h * h * a, state.v - h * a

    @staticmethod
    def _blend(now, past):
        """BDF2's start ``(4 now - past) / 3`` of positions or velocities."""
        return (4.0 * now - past) / 3.0

    def init(self, model: Model, params: Params, state0: State) -> tuple[Prepared, tuple]:
        # The implicit stage has the step size h' = 2h/3: its matrix M/h'^2 + L, prefactored once.
        return prepare(model, params, dt=2.0 * model.options.dt / 3.0), (state0.x, state0.v, jnp.asarray(True))

    def step(self, model: Model, prep: Prepared, state: State, memory, activation, force):
        h = model.options.dt
        x_prev, v_prev, first = memory
        x_prev, v_prev = jax.lax.cond(first, lambda: self._past(model, prep, state, activation, force),
                                      lambda: (x_prev, v_prev))
        start = State(x=self._blend(state.x, x_prev), v=self._blend(state.v, v_prev), rot=state.rot,
                      t=state.t + h / 3.0, contact=state.contact)
        new, _, info = super().step(model, prep, start, (), activation, force)
        return (State(x=new.x, v=new.v, rot=new.rot, t=state.t + h, contact=new.contact),
                (state.x, state.v, jnp.asarray(False)), info)

    def starts(self, model: Model, prep: Prepared, xs, vs, t0, activation0, force0):
        h = model.options.dt
        state0 = State(x=xs[0], v=vs[0], rot=cold_start(deformation_gradient(model, prep.dminv, xs[0])), t=t0)
        x_past, v_past = self._past(model, prep, state0, activation0, force0)
        x_prev = jnp.concatenate([x_past[None], xs[:-2]])
        v_prev = jnp.concatenate([v_past[None], vs[:-2]])
        times = t0 + h * jnp.arange(xs.shape[0] - 1) + h / 3.0
        return self._blend(xs[:-1], x_prev), self._blend(vs[:-1], v_prev), times


def integrator_of(model: Model) -> Integrator:
    """The scene's integrator (``Options.integrator``; ``None`` is implicit Euler)."""
    return model.options.integrator or ImplicitEuler()


def step(model: Model, prep: Prepared, state: State, activation=None, force=None) -> tuple[State, StepInfo]:
    """One implicit-Euler PD step (:class:`ImplicitEuler`, whatever ``Options.integrator``).

    Arguments:
        model: the compiled scene; prep: :func:`softbody.model.prepare` of its params.
        state: the current :class:`State`.
        activation: ``(n_channels,)`` actuator activations, or ``None`` (zeros).
            Concrete values outside a channel's bounds (``model.channel_bounds``, e.g. a
            muscle's ``[0, 1]``) are refused; traced ones (under ``jax.jit``, ``jax.grad``,
            ``jax.vmap``) cannot be checked and are clipped to the bounds without an error or
            a flag, with zero gradient beyond them.
        force: ``(n, 3)`` external forces in newtons, or ``None``.

    Returns:
        ``(next_state, info)``; ``info.result`` is not set (0): :func:`rollout` sets it.

    Raises:
        SceneError: the scene's integrator (``Options.integrator``) is not implicit Euler:
            one step of another would need its memory (use :func:`rollout`); a state or
            ``prep`` of another model, a ``force`` not ``(n, 3)`` or an ``activation`` of
            the wrong shape or (when concrete) out of its channels' bounds.
    """
    integrator = integrator_of(model)
    if type(integrator) is not ImplicitEuler:
        raise SceneError(f"step takes one implicit-Euler step, but this scene's integrator is "
                         f"{type(integrator).__name__}() (Options.integrator), whose steps need the earlier states: "
                         "use rollout(..., n_steps=k), or build the scene with Options(integrator=None)")
    _check_fit(model, state=state, prep=prep)
    _check_force(model, force, "force")
    new, _, info = integrator.step(model, prep, state, (), _activation(model, activation), force)
    return new, info


def _step_start(model: Model, prep: Prepared, state: State) -> State:
    """The state a step starts from: with a prescribed motion, the fixed vertices moved to
    where the clamp is at the step's end."""
    if not model.moving:
        return state
    return eqx.tree_at(lambda s: s.x, state, clamp(model, state.x, prep.x_rest, state.t + prep.dt))


def contact_forces(model: Model, params: Params, traj: Trajectory, controls=None, forces=None,
                   t0: float = 0.0) -> tuple[Array, Array]:
    """The contact forces and contact states of every step of a trajectory.

    Each step's solution is a fixed point of the contact iteration, at which the force the
    contact rows exert on a vertex is the step objective's gradient there (each step rebuilt
    as the scene's integrator built it, ``starts``)
    (:func:`softbody.contact.report.report`); the states are the contact step's decision
    at the solution. Computed from the trajectory (one objective evaluation per step, all
    steps at once), so rollouts carry no contact arrays.

    Arguments:
        model, params: the scene and parameters of the rollout.
        traj: its :class:`Trajectory` (``x``, ``v`` of shape ``(T + 1, n, 3)``).
        controls, forces: the rollout's controls ``(T, n_channels)`` and external forces
            ``(T, n, 3)``, or ``None``.
        t0: the time of the rollout's first state, s (moving obstacles read it).

    Returns:
        ``(force (T, n, 3), state (T, n))``: at the end of each step, the force on each
        vertex from the contact rows (obstacles and other bodies; N; zero off contact) and
        its int8 state, a code into :data:`softbody.contact.CONTACT_STATES` (0: none, 1:
        stick, 2: slide).

    Raises:
        SceneError: the scene has no contact, or shapes that do not fit.
    """
    if model.step.contact is None:
        raise SceneError("contact_forces needs a scene with obstacles or other contact rows; this one has none")
    n_steps = traj.x.shape[0] - 1
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps)
    return _contact_forces(model, params, traj.x, traj.v, controls, forces, jnp.asarray(t0, jnp.float64))


def contact_fields(model: Model, params: Params, traj: Trajectory, controls=None, forces=None,
                   t0: float = 0.0) -> dict[str, np.ndarray]:
    """:func:`contact_forces` as per-vertex fields of a result file, one row per frame.

    Pass them as ``Result(fields=...)`` (:class:`softbody.io.Result`): the viewer's and
    ``softbody render``'s "colour by" list then offers them, and the ParaView export
    writes them. Rows between bodies report on both sides (the touching vertex and the
    triangle's or edge's vertices), obstacles on the vertex they hold.

    Arguments:
        model, params, traj, controls, forces, t0: as for :func:`contact_forces`.

    Returns:
        ``{"contact_force": (T + 1, n), "contact_state": (T + 1, n)}`` float64: each
        vertex's contact force magnitude (N) and state code (0: none, 1: stick, 2: slide,
        :data:`softbody.contact.CONTACT_STATES`) at the end of each step; frame 0, the
        initial state, is zero (no step has acted there).

    Raises:
        SceneError: as :func:`contact_forces`.
    """
    force, state = (np.asarray(a) for a in contact_forces(model, params, traj, controls, forces, t0))
    first = np.zeros((1, force.shape[1]))
    return {"contact_force": np.concatenate([first, np.linalg.norm(force, axis=-1)]),
            "contact_state": np.concatenate([first, state.astype(np.float64)])}


@functools.partial(jax.jit, static_argnums=0)
def _contact_forces(model, params, xs, vs, controls, forces, t0):
    integrator = integrator_of(model)
    prep, _ = integrator.init(model, params, State(x=xs[0], v=vs[0], rot=None, t=t0))
    first = (_activation(model, None if controls is None else controls[0]), None if forces is None else forces[0])
    x_start, v_start, times = integrator.starts(model, prep, xs, vs, t0, *first)
    free = jnp.asarray(model.free_mask)

    def one(x_n, v_n, t, x, a, f):
        q_n = cold_start(deformation_gradient(model, prep.dminv, x_n))
        state = _step_start(model, prep, State(x=x_n, v=v_n, rot=q_n, t=t))
        problem, _, threshold, _ = step_problem(model, prep, state, _activation(model, a), f)
        q = cold_start(deformation_gradient(model, prep.dminv, jnp.where(free > 0, x, state.x)))
        return report(model.step.contact, problem, model.step.coordinates, x, q, threshold, model.options.max_iter)

    return jax.vmap(one, in_axes=(0, 0, 0, 0, None if controls is None else 0, None if forces is None else 0))(
        x_start, v_start, times, xs[1:], controls, forces)


def _check_fit(model: Model, **given) -> None:
    """Refuse states, params and prepared operators whose shapes do not fit ``model`` (shapes
    are static: this works on traced values too). ``given`` maps the name an argument has
    in the caller (``state0`` or ``state``: a :class:`State`; ``params``; ``prep``: a
    :class:`Prepared`) to it, or to ``None``.

    Raises:
        SceneError: naming the argument's field, its shape, the shape the model needs and
            where a fitting one comes from.
    """
    n, t, m = model.n_vertices, model.n_tets, len(model.material_names)
    fields = {"params": ({"morph": (n, 3), "E": (m,)}, "the params build returned with this model"),
              "prep": ({"x_rest": (n, 3), "volume": (t,)}, "prepare(model, params) with this model's params")}
    state = ({"x": (n, 3), "v": (n, 3), "rot": (4, t), "contact": (model.n_contact_rows, 3)},
             "initial_state(model, params) with this model's params")
    for owner, value in given.items():
        shapes, fix = fields.get(owner, state)
        for field, shape in shapes.items():
            got = getattr(value, field, None)
            if got is not None and jnp.shape(got) != shape:
                raise SceneError(f"{owner}.{field} has shape {jnp.shape(got)} but this model ({n} vertices, {t} tets, "
                                 f"{m} material(s)) needs {shape}: it belongs to another model; use {fix}")


def _check_force(model: Model, force, name: str) -> None:
    """Refuse a one-step external force that is not ``None`` or ``(n, 3)``."""
    if force is not None and jnp.shape(force) != (model.n_vertices, 3):
        raise SceneError(f"{name} must have shape ({model.n_vertices}, 3) (newtons on each of the model's vertices) "
                         f"or be None, got {jnp.shape(force)}")


def _check_controls(model: Model, controls, forces, n_steps, params=None, state0=None):
    if n_steps is not None and (isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer))):
        raise SceneError(f"n_steps must be a whole number of steps, got {n_steps!r}; round a computed count, "
                         "e.g. n_steps=round(duration / dt)")
    _check_fit(model, state0=state0, params=params)
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


def open_loop(state: State, inputs):
    """The controls and forces of a step given in advance: ``inputs = (activation, force)``
    (either may be ``None``); see :func:`integrate`."""
    return inputs


def integrate(integrator: Integrator, model: Model, params: Params, state0: State, n_steps: int,
              inputs=(None, None), choose=open_loop):
    """The one loop of every rollout (traceable; one ``lax.scan``): ``n_steps`` steps of
    ``integrator`` from ``state0``, with per-step result codes.

    Each step's code (:class:`~softbody._types.RESULTS`) is ``inverted`` where it ends with
    more inverted tets than ``state0``, else ``nonfinite`` where its state or residual is
    not finite, else ``max_iterations`` where it did not converge. After a ``nonfinite``
    step the state is held and every later step carries that code. The adjoint owns the
    loop (:meth:`softbody.gradients.Adjoint.loop`): one that asks for segment checkpoints
    (:class:`~softbody.gradients.Unrolled`) nests the scan, keeping only segment-start
    states for the backward pass.

    Arguments:
        integrator: the :class:`~softbody._interfaces.Integrator`.
        model, params: the scene; state0: the initial :class:`State`.
        n_steps: the number of steps (static).
        inputs: a pytree whose leaves have ``n_steps`` rows, scanned with the steps
            (default: no controls and no forces for :func:`open_loop`).
        choose: ``(state, inputs_k) -> (activation (n_channels,) or None, force (n, 3) or
            None)``, the controls of step ``k`` from its start state and its inputs:
            :func:`open_loop` (default) reads them from ``inputs = (controls, forces)``; a
            closed loop computes them from the state (a policy).

    Returns:
        ``(trajectory, activations, failed, branch)``: the :class:`Trajectory`, the
        ``(n_steps, n_channels)`` activations the steps used (or ``None`` where
        ``choose`` gave none), whether a step failed and the failure branch of the first
        one (see :func:`_first_failure`).
    """
    prep, memory0 = integrator.init(model, params, state0)
    inverted0 = inverted_tets(model, prep, state0.x)
    if model.n_contact_rows and state0.contact is None:  # the steps carry the contact forces
        state0 = dataclasses.replace(state0, contact=jnp.zeros((model.n_contact_rows, 3), state0.x.dtype))

    def body(carry, inputs_k):
        state, memory, bad = carry
        a, f = choose(state, inputs_k)
        new, new_memory, info = integrator.step(model, prep, state, memory, _activation(model, a), f)
        result, finite = step_result(new, info, inverted0)
        info = dataclasses.replace(info, result=jnp.where(bad, int(RESULTS.nonfinite), result).astype(jnp.int32))
        new, new_memory = jax.tree.map(lambda n, o: jnp.where(bad, o, n), (new, new_memory), (state, memory))
        return (new, new_memory, bad | ~finite), (new.x, new.v, info, a)

    carry = (state0, memory0, jnp.asarray(False))
    _, out = model.options.adjoint.loop(body, carry, inputs, n_steps)
    xs, vs, info, activations = out
    failed, branch = _first_failure(info.result, xs, vs)
    xs = jnp.concatenate([state0.x[None], xs])
    vs = jnp.concatenate([state0.v[None], vs])
    return Trajectory(x=xs, v=vs, info=info), activations, failed, branch


@functools.partial(jax.jit, static_argnums=(0, 5))
def _rollout(model: Model, params: Params, state0: State, controls, forces, n_steps: int):
    traj, _, failed, branch = integrate(integrator_of(model), model, params, state0, n_steps, (controls, forces))
    return traj, failed, branch


def rollout(model: Model, params: Params, state0: State, controls=None, forces=None,
            n_steps: int | None = None, *, throw: bool = True) -> Trajectory:
    """Simulate ``n_steps`` implicit-Euler steps (one compiled ``lax.scan``).

    Arguments:
        model, params: from :func:`softbody.model.build`.
        state0: initial :class:`State` (:func:`softbody.model.initial_state`).
        controls: ``(n_steps, n_channels)`` activations, or ``None``.
            Concrete values outside a channel's bounds (``model.channel_bounds``, e.g. a
            muscle's ``[0, 1]``) are refused; traced ones (under ``jax.jit``, ``jax.grad``,
            ``jax.vmap``) cannot be checked and are clipped to the bounds without an error or
            a flag, with zero gradient beyond them.
        forces: ``(n_steps, n, 3)`` external forces, or ``None``.
        n_steps: number of steps (taken from controls/forces when omitted).
        throw: raise :class:`SimulationError` for the first step whose
            ``info.result`` is not ``RESULTS.success`` (the default); ``False`` returns
            the trajectory with the codes instead and never raises for a failed step.

    Returns:
        A :class:`Trajectory` with ``x, v`` of shape ``(n_steps + 1, n, 3)`` (the first row is
        ``state0``) and per-step :class:`StepInfo`; ``info.result`` holds each step's
        :class:`~softbody._types.RESULTS` code (``inverted``: more inverted tets than
        ``state0`` had). After a ``nonfinite`` step the state is held and every later
        step carries that code.

    Raises:
        SceneError: bad control or force shapes, or NaN/inf in them, concrete controls
            outside their channels' bounds, ``n_steps`` not a whole number >= 1, or a state
            or params whose shapes do not fit the model (before compiling), whatever
            ``throw``.
        SimulationError: with ``throw=True``, a step stopped at the iteration cap without
            meeting its tolerance, its state or residual became non-finite, or it ended
            with more inverted tets (``det F <= 0``) than ``state0``; the message names the
            first failing step, what failed and the fix. Traced (under an outer
            ``jit``/``grad``) the compiled program fails with the same message at run time:
            a ``jax.errors.JaxRuntimeError`` containing it, raised where the result is
            used (e.g. ``block_until_ready``). On CPU with the native library the check is
            an XLA FFI call, which JAX's persistent compilation cache keeps; elsewhere it is
            an equinox runtime check (a host callback, which the cache does not keep: there
            pass ``throw=False`` and call :func:`check_trajectory` on the result instead).
    """
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps, params, state0)
    with _forward_mode_hint():
        traj, failed, branch = _rollout(model, params, state0, controls, forces, n_steps)
    if not throw:
        return traj
    return _raise_failure(traj, failed, branch, _Messages(integrator_of(model).templates(model, "rollout"), n_steps))


def check_trajectory(model: Model, traj: Trajectory) -> Trajectory:
    """Raise for the first failed step of a computed trajectory, as ``rollout`` would.

    Under an outer ``jax.jit`` or ``jax.grad``, ``rollout(..., throw=True)`` fails the
    compiled program at run time (a ``jax.errors.JaxRuntimeError``); without the native
    library, or off the CPU, its check is a Python host callback, and JAX does not keep such
    programs in its persistent compilation cache. Calling ``rollout(..., throw=False)``
    inside the compiled function and ``check_trajectory`` on what it returns gives the same
    errors as a :class:`SimulationError`, from a program without a check (``softbody demo``
    does this).

    Arguments:
        model: the model the trajectory was simulated with (for the messages).
        traj: a :class:`Trajectory` with concrete arrays, ``x, v`` ``(n_steps + 1, n, 3)``
            and ``info`` per step.

    Returns:
        ``traj`` unchanged.

    Raises:
        SimulationError: a step's ``info.result`` is not ``RESULTS.success``; the message
            names the first failing step, what failed and the fix (as ``rollout``'s).
        TypeError: ``traj`` holds tracers (call it on the compiled function's output).
    """
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(traj)):
        raise TypeError("softbody.simulate.check_trajectory needs a computed trajectory; inside jax.jit or jax.grad use "
                        "rollout(..., throw=True), or call check_trajectory on the compiled function's output")
    failed, branch = _first_failure(jnp.asarray(traj.info.result), jnp.asarray(traj.x[1:]), jnp.asarray(traj.v[1:]))
    return _raise_failure(traj, failed, branch, _Messages(_step_templates(model), int(traj.info.result.shape[0])))


def solve_static(model: Model, params: Params, force=None, activation=None, x0=None, *, throw: bool = True):
    """Static equilibrium under gravity, external forces and activations.

    Minimises ``E(x) - f . x`` with the same PD machinery (no inertia, no damping).

    Arguments:
        force: ``(n, 3)`` external forces in newtons, or ``None``.
        activation: ``(n_channels,)`` or ``None``.
            Concrete values outside a channel's bounds (``model.channel_bounds``, e.g. a
            muscle's ``[0, 1]``) are refused; traced ones (under ``jax.jit``, ``jax.grad``,
            ``jax.vmap``) cannot be checked and are clipped to the bounds without an error or
            a flag, with zero gradient beyond them.
        x0: initial guess ``(n, 3)`` (default: the rest shape, with a prescribed ``motion``
            its fixed vertices where the motion puts them at ``t = 0``), which also holds the
            fixed vertices' positions.
        throw: raise :class:`SimulationError` when ``info.result`` is not
            ``RESULTS.success`` (the default); ``False`` returns ``(x, info)`` whatever the
            result.

    Returns:
        ``(x, info)``: positions ``(n, 3)`` and :class:`StepInfo`, whose ``result`` is the
        :class:`~softbody._types.RESULTS` code (``inverted``: more inverted tets than ``x0``).

    Raises:
        SceneError: when the model has no fixed vertices (the equilibrium is not unique);
            params of another model, a ``force`` not ``(n, 3)``, an ``x0`` not ``(n, 3)``
            or an ``activation`` of the wrong shape or (when concrete) out of its channels'
            bounds.
        SimulationError: with ``throw=True``, the solve stopped at the iteration cap, its
            solution is non-finite (e.g. the load exceeds what the body can carry, such as
            a cavity pressure past its maximum, where no equilibrium exists), or it has more
            inverted tets than ``x0``. Traced (under an outer ``jit``/``grad``) the same
            message is raised at run time, as in :func:`rollout`.
    """
    if len(model.fixed) == 0:
        raise SceneError("a static solve needs fixed vertices (build the model with fixed=...)")
    _check_fit(model, params=params)
    _check_force(model, force, "force")
    activation = _activation(model, activation)
    with _forward_mode_hint():
        x, info, failed, branch = _solve_static(model, params, force, activation, x0)
    if not throw:
        return x, info
    return _raise_failure((x, info), failed, branch, _Messages(_static_templates(model), 1))


@functools.partial(jax.jit, static_argnums=0)
def _solve_static(model, params, force, activation, x0):
    prep = prepare(model, params, static=True)
    state = initial_state(model, params, x=x0)
    sol, info = model.options.adjoint.solve(model, prep, state, activation, force)
    failed, branch = _first_failure(info.result[None], sol.x[None], jnp.zeros_like(sol.x)[None])
    return sol.x, info, failed, branch

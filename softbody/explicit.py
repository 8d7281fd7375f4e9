"""Semi-implicit (symplectic) Euler: an explicit integrator of the same semi-discrete model.

One step with time step ``h`` from ``(x_n, v_n)``::

    v_{n+1} = v_n + h M^-1 (f(x_n) - alpha M v_n - f_beta(x_n, v_n) + f_d(x_n, v_n) + M g + f_ext)
    x_{n+1} = x_n + h v_{n+1}

with ``f = -dE/dx`` the simulator's elastic and actuator forces (the gradient of
:func:`softbody.objective.step_objective`'s static objective, so every term the implicit
solver sees is here too), ``alpha M v`` the mass damping, ``f_beta`` the strain-rate
damping force ``beta w_s V R sym(R^T F')`` (the limit the ODE reference uses) and ``f_d`` the
dissipation terms' forces (air drag, wind). Rotations are warm-started from the previous
step (``options.rotation_iterations`` Newton steps), which at explicit time steps is
converged to round-off.

Each step costs one force evaluation and no solve, but the step must resolve the fastest
mode of the mesh: undamped and linearised, the scheme is stable exactly when
``h < 2 / omega_max`` (:func:`critical_time_step`), and ``omega_max`` grows like the wave
speed over the smallest element size. Stiffness damping lowers the limit further.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody.elastic import deformation_gradient
from softbody import rotation as rot
from softbody.model import Model, Params, State, prepare
from softbody._interfaces import Capabilities, Integrator
from softbody._types import StepInfo
from softbody.objective import accelerations, step_objective
from softbody.simulate import _VARIANTS, Trajectory, _Messages, _check_controls, _raise_failure, integrate

Array = jax.Array


@dataclass(frozen=True)
class SymplecticEuler(Integrator):
    """Semi-implicit Euler steps (the module docstring) of size ``dt``, a traced value (one
    compiled program for any step size). Each step's :class:`~softbody._types.StepInfo`
    records one force evaluation and zero solver iterations (``residual`` 0,
    ``converged`` True, ``inverted`` not counted: 0); the loop
    (:func:`softbody.simulate.integrate`) marks a non-finite step."""

    dt: Array

    capabilities: ClassVar[Capabilities] = Capabilities(
        refuses={"contact": "has no contact handling",
                 "skeleton": "has no joint constraints",
                 "rigid bodies": "has no joint constraints (rigid bodies are root links of reduced coordinates)",
                 "motion": "does not move fixed vertices"},
        instead="step such a scene with softbody.simulate.rollout and an implicit integrator "
                "(Options(integrator=None) or BDF2())")

    def init(self, model: Model, params: Params, state0: State):
        return prepare(model, params, static=True), ()

    def step(self, model: Model, prep, state: State, memory, activation, force):
        free = jnp.asarray(model.free_mask)
        acc, q = accelerations(model, prep, state, activation, force)
        v = state.v + self.dt * acc
        x = state.x + self.dt * v * free
        zero = jnp.asarray(0)
        info = StepInfo(iterations=zero, evaluations=jnp.asarray(1), residual=jnp.asarray(0.0),
                        converged=jnp.asarray(True), inverted=zero, result=jnp.asarray(0, jnp.int32),
                        fallback=jnp.asarray(False), overflow=jnp.asarray(False), tunnelled=jnp.asarray(0, jnp.int32))
        return State(x=x, v=v, rot=q, t=state.t + self.dt, contact=state.contact), memory, info

    def templates(self, model: Model, call: str) -> tuple[str, ...]:
        unstable = (f"step {{step}}: the explicit state became non-finite at dt = {model.options.dt:g} s; the step "
                    "exceeds the stability limit (softbody.explicit.critical_time_step gives it): reduce dt or use "
                    "the implicit softbody.simulate.rollout")
        return (unstable,) * len(_VARIANTS)  # one per failure branch


@functools.partial(jax.jit, static_argnums=(0, 5))
def _explicit(model: Model, params: Params, state0: State, controls, forces, n_steps: int, dt):
    """The loop of :func:`explicit_rollout`; ``dt`` is traced (one program for any step size).
    Returns ``(trajectory, failed, branch)`` as :func:`softbody.simulate.integrate`."""
    state0 = eqx.tree_at(lambda s: s.v, state0, state0.v * jnp.asarray(model.free_mask))
    traj, _, failed, branch = integrate(SymplecticEuler(jnp.asarray(dt)), model, params, state0, n_steps,
                                        (controls, forces))
    return traj, failed, branch


def explicit_rollout(model: Model, params: Params, state0: State, controls=None, forces=None,
                     n_steps: int | None = None, *, throw: bool = True) -> Trajectory:
    """``n_steps`` semi-implicit Euler steps of size ``model.options.dt`` (:class:`SymplecticEuler`
    in the loop of every rollout, :func:`softbody.simulate.integrate`).

    Arguments:
        model, params: from :func:`softbody.model.build` (scenes without contact or a
            skeleton: the explicit step has no contact or joint constraints).
        state0: the initial :class:`~softbody.model.State`.
        controls: ``(n_steps, n_channels)`` activations, or ``None``.
        forces: ``(n_steps, n, 3)`` external forces in newtons, or ``None``.
        n_steps: number of steps (taken from controls/forces when omitted).
        throw: raise :class:`~softbody.simulate.SimulationError` for the first non-finite
            step (the default); ``False`` returns the trajectory with the codes instead.

    Returns:
        A :class:`~softbody.simulate.Trajectory` with ``x, v`` of shape ``(n_steps + 1, n, 3)``
        (the first row is ``state0``, its velocities zero on fixed vertices); its ``info``
        records one force evaluation and zero solver iterations per step (``residual`` 0,
        ``converged`` True, ``inverted`` not counted: 0) and ``result``
        ``RESULTS.nonfinite`` from the first non-finite step on (the state is held there),
        ``RESULTS.success`` before it.

    Raises:
        SceneError: bad control or force shapes; a scene with contact, a skeleton, rigid
            bodies or a prescribed motion (:attr:`SymplecticEuler.capabilities`).
        SimulationError: with ``throw=True``, the state became non-finite (the step
            exceeded the stability limit, see :func:`critical_time_step`); names the first
            bad step. Traced, the same message is raised at run time as an equinox error.
    """
    SymplecticEuler.capabilities.check(model.features, "explicit_rollout")
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps, params=params, state0=state0)
    traj, failed, branch = _explicit(model, params, state0, controls, forces, n_steps, model.options.dt)
    if not throw:
        return traj
    return _raise_failure(traj, failed, branch,
                          _Messages(SymplecticEuler(model.options.dt).templates(model, "explicit_rollout"), n_steps))


def critical_time_step(model: Model, params: Params, x=None, iterations: int = 300) -> float:
    """The undamped stability limit ``2 / omega_max`` of semi-implicit Euler at ``x``.

    ``omega_max^2`` is the largest eigenvalue of ``M^-1 K`` over the free degrees of
    freedom, ``K`` the Hessian of the elastic energy at ``x`` (default: the rest shape),
    found by power iteration on ``M^-1/2 K M^-1/2`` with Hessian-vector products. The
    Rayleigh quotient approaches ``omega_max^2`` from below, so the returned step is an
    upper bound that converges from above (5e-5 above the dense eigenvalue's on the
    99-vertex test beam at the default ``iterations``): stay a margin below it.

    Arguments:
        model, params: the scene.
        x: ``(n, 3)`` positions to linearise at, or ``None`` for the rest shape.
        iterations: power iterations.

    Returns:
        ``2 / omega_max`` in seconds.
    """
    prep = prepare(model, params, static=True)
    x = prep.x_rest if x is None else jnp.asarray(x)
    q0 = rot.cold_start(deformation_gradient(model, prep.dminv, x))
    evaluate, _ = step_objective(model, prep, x, jnp.zeros_like(x), q0, jnp.zeros(model.n_channels), None)
    q = jax.lax.fori_loop(0, 16, lambda _, q: rot.rotation(deformation_gradient(model, prep.dminv, x), q, 1)[1], q0)
    scale = jnp.asarray(model.free_mask) / jnp.sqrt(jnp.maximum(prep.mass, 1e-300))

    @jax.jit
    def power(u):
        def body(_, c):
            u, _ = c
            w = scale * jax.jvp(lambda y: evaluate(y, q)[1], (x,), (scale * u,))[1]
            lam = jnp.sum(u * w)
            return w / jnp.sqrt(jnp.sum(w * w)), lam

        return jax.lax.fori_loop(0, iterations, body, (u, jnp.asarray(0.0)))[1]

    u = jnp.asarray(np.random.default_rng(0).normal(size=x.shape)) * jnp.asarray(model.free_mask)
    lam = float(power(u / jnp.linalg.norm(u)))
    return 2.0 / np.sqrt(lam)

"""Air drag and wind on sheets (softbody.aero.Drag, a dissipation term of the step
objective): the terminal speed of a falling sheet, the implicit-Euler recurrences of a
sheet blown by an oblique wind and their first-order convergence to the ODE's closed
form, the explicit integrator's forces, gradients with respect to the air's parameters
against central differences, and bad input refused before compiling."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from softbody.meshing import sheet

from softbody.aero import Drag
from softbody.explicit import SymplecticEuler, explicit_rollout
from softbody.gradients import ImplicitForward, central_difference, check_grad, random_directions
from softbody.model import Options, SceneError, State, build, initial_state
from softbody.reference import diffrax_rollout, newton_step
from softbody.shell import shell_body
from softbody.simulate import rollout

jax.config.update("jax_enable_x64", True)

RHO_A, RHO = 0.1, 1.2  # a light fabric (kg/m^2) in air (kg/m^3)


def _scene(options, *, wind=(0.0, 0.0, 0.0), friction=0.0, gravity=True, fixed=None, n=4):
    """A free (or ``fixed``) 0.1 m square fabric sheet in the x-y plane (normal z) with drag
    on its triangles: ``(model, params)``."""
    mesh = sheet.grid(0.1, 0.1, (n, n))
    body = shell_body(mesh, E=1e5, nu=0.3, thickness=1e-3, areal_density=RHO_A, fixed=fixed)
    drag = Drag.on(mesh, "sheet", density=RHO, friction=friction, wind=wind)
    options = dataclasses.replace(options, gravity=options.gravity if gravity else (0.0, 0.0, 0.0))
    return build(body, terms=[drag], options=options)


def test_a_flat_sheet_falls_at_its_terminal_speed():
    """From rest under gravity, every vertex ends at ``sqrt(rho_A g / rho)``: the implicit
    step's steady state balances weight and drag exactly, and the gap closes by a factor
    ``1 + 2 g h / v_t`` a step (1e-13 after 150 steps); what is left is the solves'
    tolerance (1e-10 of ``|M s / h^2|``: ~1e-8 m/s here). The sheet stays flat."""
    model, params = _scene(Options(dt=0.01, tol=1e-10, atol=0.0))
    assert model.features == {"velocity forces"}
    traj = rollout(model, params, initial_state(model, params), n_steps=150)
    v_t = np.sqrt(RHO_A * 9.81 / RHO)
    v = np.asarray(traj.v[-1])
    assert np.abs(v[:, 2] + v_t).max() < 1e-6 * v_t
    assert np.abs(v[:, :2]).max() < 1e-9
    assert np.ptp(np.asarray(traj.x[-1])[:, 2]) < 1e-9


def _recurrences(u0_n, u0_t, h, steps, friction):
    """Implicit Euler for ``rho_A u_n' = -rho |u_n| u_n`` and ``rho_A u_t' = -c u_t``."""
    k = h * RHO / RHO_A
    u_n, u_t = [u0_n], [u0_t]
    for _ in range(steps):  # u + k |u| u = u_prev, with u of u_prev's sign
        s = np.sign(u_n[-1])
        u_n.append(s * (np.sqrt(1 + 4 * k * abs(u_n[-1])) - 1) / (2 * k))
        u_t.append(u_t[-1] / (1 + h * friction / RHO_A))
    return np.asarray(u_n), np.asarray(u_t)


def test_an_oblique_wind_moves_a_free_sheet_by_the_implicit_euler_recurrences_to_first_order():
    """No gravity; wind (3, 0, 4) m/s on a sheet at rest. Across the sheet, the relative
    speed obeys ``rho_A u' = -rho |u| u`` (closed form ``u0 / (1 + rho |u0| t / rho_A)``);
    along it, ``rho_A u' = -c u``. The rollout follows both implicit-Euler recurrences to the
    solves' tolerance, and its error against the closed forms halves with the step."""
    wind, friction, t_end = np.array([3.0, 0.0, 4.0]), 0.05, 0.2
    errors = []
    for h in (0.01, 0.005):
        steps = round(t_end / h)
        model, params = _scene(Options(dt=h, tol=1e-12, atol=0.0), wind=tuple(wind), friction=friction,
                                    gravity=False)
        traj = rollout(model, params, initial_state(model, params), n_steps=steps)
        v = np.asarray(traj.v)  # (steps + 1, n, 3): uniform, the sheet translates
        assert np.abs(v - v[:, :1]).max() < 1e-9
        u_n, u_t = _recurrences(-wind[2], -wind[0], h, steps, friction)
        np.testing.assert_allclose(v[:, 0, 2] - wind[2], u_n, rtol=0, atol=1e-8)
        np.testing.assert_allclose(v[:, 0, 0] - wind[0], u_t, rtol=0, atol=1e-8)
        exact_n = -wind[2] / (1 + RHO * wind[2] * t_end / RHO_A)
        exact_t = -wind[0] * np.exp(-friction * t_end / RHO_A)
        errors.append((abs(u_n[-1] - exact_n), abs(u_t[-1] - exact_t)))
    ratios = np.asarray(errors[0]) / np.asarray(errors[1])
    assert np.all((ratios > 1.8) & (ratios < 2.2)), ratios


def test_the_explicit_integrator_takes_the_drag_at_the_steps_start():
    """Semi-implicit Euler's forces come from the static objective, which holds the drag at
    the state's velocities: from ``v0`` in a wind, ``v1 = v0 + h a(v0)`` with
    ``a = -rho |u_n| u_n n / rho_A - c u_t / rho_A``."""
    h, wind, friction = 1e-4, np.array([1.0, -2.0, 5.0]), 0.03
    options = Options(dt=h, integrator=SymplecticEuler(jnp.asarray(h)))
    model, params = _scene(options, wind=tuple(wind), friction=friction, gravity=False)
    state = initial_state(model, params)
    v0 = np.array([0.2, 0.1, -0.5])
    state = State(x=state.x, v=jnp.broadcast_to(jnp.asarray(v0), state.v.shape), rot=state.rot, t=state.t,
                  contact=state.contact)
    traj = explicit_rollout(model, params, state, n_steps=1)
    u = v0 - wind
    a = -(RHO * abs(u[2]) * u[2] * np.array([0, 0, 1.0]) + friction * np.array([u[0], u[1], 0.0])) / RHO_A
    np.testing.assert_allclose(np.asarray(traj.v[1]), np.broadcast_to(v0 + h * a, state.v.shape), rtol=1e-12,
                               atol=1e-12)


def test_the_newton_reference_steps_a_hanging_sheet_in_a_wind_as_the_simulator_does():
    """Two steps of the sheet hung by two corners in an oblique wind: Newton's method on the
    same objective (the drag's Hessian in its matrix) converges in a few iterations to the
    PD solver's positions."""
    model, params = _hanging(None)
    traj = rollout(model, params, initial_state(model, params), n_steps=2)
    state = initial_state(model, params)
    for k in range(2):
        state, iterations = newton_step(model, params, state, tol=1e-12)
        assert iterations <= 8
        np.testing.assert_allclose(np.asarray(state.x), np.asarray(traj.x[k + 1]), rtol=0, atol=1e-10)


def _hanging(adjoint):
    """The sheet hung from two corners, gravity and an oblique wind."""
    def corners(p):
        return np.isclose(p[:, 1], 0.1) & (np.isclose(p[:, 0], 0) | np.isclose(p[:, 0], 0.1))

    return _scene(Options(dt=0.01, tol=1e-12, atol=0.0, max_iter=3000, adjoint=adjoint), wind=(1.0, 0.5, 3.0),
                  friction=0.2, fixed=corners)


@pytest.mark.parametrize("adjoint", [None, pytest.param(ImplicitForward(), marks=pytest.mark.slow)],
                         ids=["implicit", "forward"])
def test_gradients_with_respect_to_the_air_match_central_differences(adjoint):
    """d(a loss of the sheet after 5 steps)/d(log density, log friction, wind) against
    central differences (Richardson, eps 1e-2) through the implicit adjoint, reverse and
    forward: relative error <= 1e-6 (measured 1e-7 and below). ``Unrolled()`` (the
    iterations differentiated as they ran) is off by ~2e-7 in absolute terms in every
    direction, 4e-5 relative in the smallest (friction's)."""
    model, params = _hanging(adjoint)
    state0 = initial_state(model, params)

    def loss(args):
        log_rho, log_c, wind = args
        membrane, bending, drag = params.actuators
        drag = dataclasses.replace(drag, density=drag.density * jnp.exp(log_rho),
                                   friction=drag.friction * jnp.exp(log_c), wind=wind)
        x = rollout(model, params.replace(actuators=(membrane, bending, drag)), state0, n_steps=5).x[-1]
        return jnp.sum(x[:, 2]) + jnp.sum(x[:, 0] ** 2) + jnp.sum(x[:, 1])

    args = (jnp.asarray(0.0), jnp.asarray(0.0), params.actuators[2].wind)
    zero = jax.tree.map(jnp.zeros_like, args)
    directions = {"log_density": (jnp.asarray(1.0), zero[1], zero[2]),
                  "log_friction": (zero[0], jnp.asarray(1.0), zero[2]),
                  "wind": (zero[0], zero[1], jnp.ones(3))}
    if isinstance(adjoint, ImplicitForward):
        fn = jax.jit(loss)
        for name, d in random_directions(args, directions).items():
            ad = float(jax.jvp(fn, (args,), (d,))[1])
            fd = central_difference(fn, args, d, 1e-2)
            assert abs(ad - fd) <= 1e-6 * abs(fd), (name, ad, fd)
        return
    for name, r in check_grad(loss, args, directions=directions, eps=1e-2).items():
        assert r["rel_error"] <= 1e-6, (name, r)


def test_bad_drag_is_refused_and_diffrax_refuses_velocity_forces(no_compiling):
    mesh = sheet.grid(0.1, 0.1, (2, 2))
    points, tris = mesh.points, mesh.surface
    for message, kwargs in {"density >= 0": dict(density=-1.0), "friction >= 0": dict(friction=np.nan),
                            "three finite numbers": dict(wind=(1.0, 2.0)),
                            "names no triangles": dict(triangles=np.zeros((0, 3), int)),
                            "must lie in": dict(triangles=np.array([[0, 1, 10**6]]))}.items():
        with pytest.raises(SceneError, match=message):
            Drag.on(points, kwargs.pop("triangles", tris), **kwargs)
    model, params = _scene(Options(dt=0.01))
    with pytest.raises(SceneError, match="diffrax_rollout .*velocity forces"):
        diffrax_rollout(model, params, initial_state(model, params), 0.01, [0.01])

"""BDF2 time stepping (``Options(integrator=BDF2())``): second order in time against
diffrax's solution of the same semi-discrete ODE, stable at long steps, gradients through
it (both adjoints) against central differences, and dry friction on an incline."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import reference
from softbody.actuators import Muscle
from softbody.gradients import Implicit, Unrolled, check_grad
from softbody.elastic import corotated, deformation_gradient
from softbody.material import Material
from softbody.meshing import examples
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state, prepare
from softbody.contact.obstacles import Plane
from softbody.rotation import polar
from softbody.scene import SoftBody
from softbody.simulate import BDF2, contact_forces, rollout

from incline import G, acceleration, ramped_gravity, rot_y

# The dropped rubber cantilever of the implicit-Euler order test (99 vertices; mass and
# stiffness damping; the first bending period is ~0.07 s).
BEAM = grid_box((0.1, 0.02, 0.02), (10, 2, 2), origin=(0.0, -0.01, -0.01))
RUBBER = Material(E=1e6, nu=0.3, density=1000.0, alpha=1.0, beta=1e-3)
DURATION = 0.04


def _errors(integrator, dts, x_ref, coarsest):
    """Largest vertex distance to ``x_ref`` over the common output times, per step size."""
    errors = []
    for dt in dts:
        model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"),
                              options=Options(dt=dt, tol=1e-10, max_iter=5000, integrator=integrator))
        traj = rollout(model, params, initial_state(model, params), n_steps=int(round(DURATION / dt)))
        stride = int(round(coarsest / dt))
        errors.append(float(jnp.linalg.norm(traj.x[stride::stride] - x_ref, axis=-1).max()))
    return errors


@pytest.mark.parametrize("dts", [
    (1e-3, 5e-4, 2.5e-4),
    pytest.param((2e-3, 1e-3, 5e-4, 2.5e-4), marks=pytest.mark.slow),
])
def test_bdf2_is_second_order_in_time(dts):
    """PD rollouts (tol 1e-10) against diffrax's Tsit5 (rtol 1e-8 on displacements, orders
    below BDF2's finest error of ~7e-7 m): the log-log slope of the error against dt is
    2 (measured 1.89 over 2e-3 ... 2.5e-4 s, 1.97 over the finest three; implicit Euler's
    is 0.94 on the same scene, with 80x the error at 2.5e-4 s)."""
    import diffrax

    model, params = build(SoftBody(BEAM, RUBBER, fixed="fixed"), options=Options(dt=dts[0]))
    ts = dts[0] * np.arange(1, int(round(DURATION / dts[0])) + 1)
    x_ref = reference.diffrax_rollout(model, params, initial_state(model, params), DURATION, ts,
                                      solver=diffrax.Tsit5())
    errors = _errors(BDF2(), dts, x_ref, dts[0])
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    print(f"BDF2 errors {dict(zip(dts, errors))}; slope {slope:.3f}")
    assert 1.8 <= slope <= 2.2


def test_bdf2_is_stable_at_long_steps():
    """A bar released bent, no damping, no gravity, at dt = 1/30 s (many times its first
    period for E = 1e7 Pa): the step is A-stable, so nothing grows; its energy falls."""
    bar = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
    xi = bar.points[:, 0] / 0.1
    bent = bar.points + np.stack([np.zeros_like(xi), np.zeros_like(xi), 5e-3 * xi**2], axis=1)
    for young in (1e4, 1e7):
        model, params = build(SoftBody(bar, Material(E=young, nu=0.3, density=1000.0), fixed="xmin"),
                              options=Options(dt=1 / 30, gravity=(0.0, 0.0, 0.0), tol=1e-8, max_iter=5000,
                                              integrator=BDF2()))
        traj = rollout(model, params, initial_state(model, params, x=bent), n_steps=30)
        deflection = np.abs(np.asarray(traj.x) - bar.points).max(axis=(1, 2))
        assert np.all(np.isfinite(deflection)) and deflection.max() <= deflection[0] * (1 + 1e-6), (young, deflection)


@pytest.mark.parametrize("adjoint", [Implicit(), pytest.param(Unrolled(), marks=pytest.mark.slow)],
                         ids=["Implicit", "Unrolled"])
def test_bdf2_gradients_match_central_differences(adjoint):
    """d(tip position after 5 steps)/d(log E, muscle activation, initial velocity), BDF2 with
    each adjoint, against central differences (Richardson-extrapolated): within 1e-6
    (measured: Implicit 1.4e-8 to 1.5e-7, Unrolled 7e-10 to 1.3e-7; implicit Euler on the
    same scene 2e-11 to 2e-9). BDF2 hardly damps the bar's fast axial modes, which the
    muscle excites: over 8 steps the Unrolled derivative, whose iterates lag the
    positions', was 1.07e-6 off in the activation."""
    bar = grid_box((0.06, 0.01, 0.01), (4, 1, 1))
    upper = np.arange(bar.n_tets)
    muscle = Muscle(upper, np.tile([1.0, 0.0, 0.0], (len(upper), 1)), np.zeros(len(upper)), ("m",))
    model, params = build(SoftBody(bar, Material(E=1e5, nu=0.3, density=1000.0, alpha=0.5), fixed="xmin",
                                   actuators=[muscle]),
                          options=Options(dt=0.01, tol=1e-12, atol=0.0, max_iter=500, adjoint=adjoint,
                                          integrator=BDF2()))
    tip = bar.regions["xmax"].vertices
    free = jnp.asarray(model.free_mask)

    def loss(theta):
        p = params.replace(E=jnp.exp(theta["logE"]))
        s0 = initial_state(model, p, v=theta["v0"] * free * jnp.array([0.0, 0.3, 1.0]))
        traj = rollout(model, p, s0, controls=jnp.full((5, 1), theta["a"]), throw=False)
        return jnp.sum(traj.x[-1, tip])

    theta = {"logE": jnp.log(params.E), "a": jnp.asarray(0.3), "v0": jnp.asarray(0.05)}
    masks = {k: {j: (j == k) for j in theta} for k in theta}
    errors = check_grad(loss, theta, directions=masks, eps=1e-5, verbose=False)
    for kind, err in errors.items():
        assert abs(err["fd"]) > 1e-8, (kind, err)
        assert err["rel_error"] <= 1e-6, (kind, err)


def test_a_cube_sticks_and_slides_on_an_incline_with_bdf2():
    """The incline of the contact tests with BDF2: at tan(theta) = 0.9 mu_s the cube stays
    put once set down and the plane carries its weight; at 1.1 mu_s it slides at
    g (sin - mu_k cos) within 5 %, every contact vertex sliding, the plane carrying
    m g cos(theta) within 1 % and the friction force mu_k times that within 0.1 %
    (measured 3e-5)."""
    edge, mu_s, mu_k, dt = 0.05, 0.5, 0.4, 0.01
    mesh = grid_box((edge,) * 3, (3, 3, 3), origin=(-edge / 2, -edge / 2, 0.0))
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, beta=0.01)), obstacles=[Plane(mu_s=mu_s, mu_k=mu_k)],
                          options=Options(dt=dt, gravity=(0.0, 0.0, 0.0), tol=1e-8, max_iter=3000, integrator=BDF2()))
    mass = np.asarray(prepare(model, params).mass)
    # Sticking: mu_k = mu_s, as in the contact tests (between the two, a body rung by its
    # set-down can start a slide that kinetic friction cannot stop: physical stick-slip).
    weight = mass.sum() * G
    for ratio, kinetic, n_steps in ((0.9, mu_s, 50), (1.1, mu_k, 40)):
        theta = np.arctan(ratio * mu_s)
        r = rot_y(theta)
        x0 = mesh.points @ r.T
        plane = params.obstacles[0].replace(normal=jnp.asarray(r[:, 2]), mu_k=jnp.asarray(kinetic))
        p = params.replace(obstacles=(plane,))
        forces = ramped_gravity(mass, n_steps, dt)
        traj = rollout(model, p, initial_state(model, p, x=x0), forces=forces)
        assert bool(np.all(traj.info.converged))
        along = ((np.asarray(traj.x) - x0) @ r[:, 0]).mean(axis=1)
        force, state = (np.asarray(a) for a in contact_forces(model, p, traj, forces=forces))
        if ratio < 1:
            assert np.abs(along[40:] - along[40]).max() < 1e-7, "the body must not creep"
            # at rest the plane carries the weight (the steps' contact forces, rebuilt as
            # BDF2 built them)
            np.testing.assert_allclose(force[40:].sum(axis=1), np.broadcast_to([0.0, 0.0, weight], (10, 3)),
                                       atol=1e-3 * weight)
        else:
            expected = G * (np.sin(theta) - mu_k * np.cos(theta))
            a = acceleration(along, dt, 15)
            assert abs(a - expected) < 0.05 * expected, (a, expected)
            touching = state[15:] > 0
            assert touching.sum(axis=1).min() >= 4 and np.all(state[15:][touching] == 2)  # sliding
            normal = (force[15:] @ r[:, 2]).sum(axis=1)
            np.testing.assert_allclose(normal, weight * np.cos(theta), rtol=0.01)
            # on the kinetic cone's edge: rebuilt from the steps' implicit-Euler starts
            # instead of BDF2's, this ratio came out 0.52-0.63
            tangential = np.linalg.norm(force[15:].sum(axis=1) - normal[:, None] * r[:, 2], axis=-1)
            np.testing.assert_allclose(tangential, mu_k * normal, rtol=1e-3)


@pytest.mark.slow
def test_a_ball_dropped_with_bdf2_comes_to_rest_without_gaining_energy():
    """The contact tests' coarse gmsh ball (208 vertices, air drag alpha = 5) dropped 1 cm
    onto a rough floor with BDF2 steps, 3 s: elastic + kinetic + gravitational energy
    falls at every step (measured: the largest change -5.9e-11 J of 0.298 J), no vertex
    ends a step below the floor, and the ball comes to rest."""
    mesh = examples.ball(radius=0.05, clearance=0.01, size=0.02)
    model, params = build(SoftBody(mesh, Material(E=2e4, nu=0.3, alpha=5.0)), obstacles=[Plane(mu_s=0.6, mu_k=0.5)],
                          options=Options(dt=0.01, tol=1e-8, max_iter=3000, integrator=BDF2()))
    traj = rollout(model, params, initial_state(model, params), n_steps=300)
    prep = prepare(model, params)

    def energy(x, v):
        f = deformation_gradient(model, prep.dminv, x)
        elastic, _ = corotated(f, polar(f), prep.volume, prep.w_s, prep.w_v)
        return jnp.sum(elastic) + 0.5 * jnp.sum(prep.mass * v * v) + G * jnp.sum(prep.mass[:, 0] * x[:, 2])

    total = np.asarray(jax.vmap(energy)(traj.x, traj.v))
    assert np.all(np.diff(total) <= 1e-12 * total[0]), np.diff(total).max()
    assert np.asarray(traj.x)[..., 2].min() > -1e-12
    assert np.abs(np.asarray(traj.v[-1])).max() < 1e-4

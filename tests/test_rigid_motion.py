"""Free rigid bodies in scenes, against analytic physics and a diffrax reference: a thrown
body's momentum and path, torque-free spin of an asymmetric body (first order with implicit
Euler, second order with BDF2), gradients through a rigid body's rotation against central
differences, a rigid body beside a soft one, and the refusals."""

import jax.numpy as jnp
import numpy as np
import pytest

import diffrax
from softbody.gradients import Implicit, Unrolled, check_grad
from softbody.io import Result
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.contact.obstacles import Plane
from softbody.reference import newton_rollout
from softbody.rigid import RigidBody
from softbody.scene import SoftBody
from softbody.simulate import BDF2, rollout
from softbody.skeleton import Link, Revolute, Skeleton, SkeletonError

from test_rigid import box, rotation

G = np.array([0.0, 0.0, -9.81])
BRICK = box((0.3, 0.2, 0.1))


def _brick(**pose):
    return RigidBody(BRICK, density=500.0, name="brick", **pose)


def _centre_and_momenta(model, body, x, v):
    """Centre of mass ``(k, 3)``, momentum ``(k, 3)`` and angular momentum about the centre
    ``(k, 3)`` of a rigid body's lumped vertex masses over a trajectory."""
    part = model.body(body.name)
    start, stop = part.vertices
    m = body.mass * part.mass_share
    x, v = np.asarray(x)[:, start:stop], np.asarray(v)[:, start:stop]
    centre = np.einsum("v,kvi->ki", m, x) / body.mass
    return (centre, np.einsum("v,kvi->ki", m, v),
            np.einsum("v,kvi->ki", m, np.cross(x - centre[:, None], v)))


def test_lumped_masses_have_the_bodys_inertia_and_velocities_its_twist():
    body = _brick(x0=(0.5, -0.2, 1.0), R0=rotation((1, 2, 3), 0.3), v0=(1.0, 0.0, 2.0), omega0=(0.3, 5.0, 0.2))
    model, params = build(body)
    part = model.body("brick")
    assert part.vertices == (0, len(BRICK[0]) + 6) and model.rig.n_dofs == 6
    np.testing.assert_allclose(params.rigid_mass, [body.mass])
    prep = prepare(model, params)
    m = np.asarray(prep.mass[:, 0])
    assert m.min() > 0 and abs(m.sum() - body.mass) <= 1e-12 * body.mass
    s0 = initial_state(model, params)
    centre, momentum, spin = _centre_and_momenta(model, body, s0.x[None], s0.v[None])
    np.testing.assert_allclose(centre[0], body.x0, atol=1e-14)
    np.testing.assert_allclose(momentum[0], body.mass * body.v0, rtol=0, atol=1e-13 * body.mass)
    world = body.R0 @ body.inertia @ body.R0.T
    np.testing.assert_allclose(spin[0], world @ body.omega0, rtol=1e-12)


def test_a_thrown_body_keeps_its_momentum_exactly_and_its_path_to_first_order():
    """Implicit Euler moves the centre by ``h v_n + h^2 g`` a step: the momentum is
    ``m (v0 + g t)`` to rounding, and the centre trails the parabola by exactly
    ``g h t / 2`` (measured: momentum 1.6e-12 relative, path 4e-15 m off that)."""
    body = _brick(x0=(0.0, 0.0, 1.0), R0=rotation((1, 2, 3), 0.3), v0=(1.0, 0.0, 2.0), omega0=(0.3, 5.0, 0.2))
    dt, n = 0.01, 50
    model, params = build(body, options=Options(dt=dt, tol=1e-10))
    traj = rollout(model, params, initial_state(model, params), n_steps=n)
    assert bool(traj.info.converged.all())
    t = dt * np.arange(n + 1)[:, None]
    centre, momentum, _ = _centre_and_momenta(model, body, traj.x, traj.v)
    np.testing.assert_allclose(momentum, body.mass * (body.v0 + G * t), rtol=0, atol=1e-10 * body.mass)
    parabola = body.x0 + body.v0 * t + 0.5 * G * t**2
    np.testing.assert_allclose(centre - parabola, 0.5 * G * dt * t, rtol=0, atol=1e-12)


def _spin_reference(body, T):
    """The body's orientation at ``T`` from Euler's equations, by diffrax (Tsit5, rtol 1e-11)."""
    inertia = jnp.asarray(body.inertia)

    def rhs(t, y, args):
        R, w = y[:9].reshape(3, 3), y[9:]  # w: body-frame angular velocity
        wx = jnp.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        return jnp.concatenate([(R @ wx).ravel(), jnp.linalg.solve(inertia, jnp.cross(inertia @ w, w))])

    y0 = jnp.concatenate([jnp.asarray(body.R0).ravel(), body.R0.T @ body.omega0])
    sol = diffrax.diffeqsolve(diffrax.ODETerm(rhs), diffrax.Tsit5(), 0.0, T, 1e-3, y0,
                              stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-12), max_steps=100000)
    return np.asarray(sol.ys[-1, :9]).reshape(3, 3)


def _spin_errors(body, integrator, dt, T, reference):
    """Angular-momentum drift per simulated second and orientation error (rad) at ``T``."""
    model, params = build(body, options=Options(dt=dt, tol=1e-10, integrator=integrator))
    traj = rollout(model, params, initial_state(model, params), n_steps=round(T / dt))
    assert bool(traj.info.converged.all())
    centre, _, spin = _centre_and_momenta(model, body, traj.x[-1:], traj.v[-1:])
    surface = np.asarray(traj.x[-1, :len(BRICK[0])]) - centre
    u, _, vt = np.linalg.svd(surface.T @ (body.points - body.centre))
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    turn = R @ reference.T
    angle = np.arccos(np.clip((np.trace(turn) - 1) / 2, -1, 1))
    spin0 = body.R0 @ body.inertia @ body.R0.T @ body.omega0
    return np.linalg.norm(spin[0] - spin0) / np.linalg.norm(spin0) / T, angle


@pytest.mark.parametrize("integrator, order", [(None, 1), (BDF2(), 2)], ids=["ImplicitEuler", "BDF2"])
def test_torque_free_spin_converges_to_eulers_equations(integrator, order):
    """An asymmetric brick (0.3 x 0.2 x 0.1 m) spinning at 6 rad/s about a generic axis, no
    gravity torque, 1 s. Halving the step divides the orientation error against diffrax by
    ``2^order`` (accepted: within 20%). Measured, angular-momentum drift per second and
    orientation error at dt 1/100, 1/200, 1/400 s: implicit Euler 0.23, 0.14, 0.075 and
    51, 29, 16 degrees (it damps the spin); BDF2 3.9e-3, 9.1e-4, 2.2e-4 and 2.1, 0.51,
    0.13 degrees."""
    body = _brick(R0=rotation((1, 2, 3), 0.3), omega0=(0.4, 6.0, 0.3))
    T = 1.0
    reference = _spin_reference(body, T)
    (drift1, angle1), (drift2, angle2) = (_spin_errors(body, integrator, dt, T, reference) for dt in (1 / 100, 1 / 200))
    assert 0.8 * 2**order <= angle1 / angle2 <= 1.2 * 2**order, (angle1, angle2)
    assert drift2 < drift1


@pytest.mark.parametrize("adjoint", [Implicit(), Unrolled()], ids=["Implicit", "Unrolled"])
def test_gradients_through_a_rigid_bodys_rotation_match_central_differences(adjoint):
    """d(weighted positions of a spinning brick after 6 steps)/d(initial spin, initial
    velocity) against central differences: within 1e-6 (measured 2e-10 to 8e-10 with
    either adjoint)."""
    body = _brick(omega0=(0.4, 6.0, 0.3))
    model, params = build(body, options=Options(dt=0.01, tol=1e-12, atol=0.0, adjoint=adjoint))
    weights = jnp.asarray(np.random.default_rng(0).standard_normal((model.n_vertices, 3)))
    arm = jnp.asarray(model.mesh.points) - jnp.asarray(body.x0)

    def loss(theta):
        v = theta["v"] + jnp.cross(theta["omega"], arm)
        traj = rollout(model, params, initial_state(model, params, v=v), n_steps=6, throw=False)
        return jnp.sum(weights * traj.x[-1])

    theta = {"omega": jnp.asarray(body.omega0), "v": jnp.array([0.5, 0.0, 1.0])}
    masks = {k: {j: (j == k) for j in theta} for k in theta}
    for kind, err in check_grad(loss, theta, directions=masks, eps=1e-5, verbose=False).items():
        assert abs(err["fd"]) > 1e-4, (kind, err)
        assert err["rel_error"] <= 1e-6, (kind, err)


def test_a_rigid_body_beside_a_soft_one_leaves_it_as_it_was(tmp_path):
    """A soft beam moves as in a scene of its own next to a spinning brick (to the solver's
    tolerance: the bodies share one solve), and the result file carries both bodies."""
    beam = grid_box((0.06, 0.01, 0.01), (4, 1, 1))
    soft = SoftBody(beam, Material(E=1e5, nu=0.3, density=1000.0), fixed="xmin", name="beam")
    options = Options(dt=0.01, tol=1e-12, atol=0.0, max_iter=400)
    alone, p_alone = build(soft, options=options)
    both, p_both = build([soft, _brick(x0=(1.0, 0.0, 0.0), omega0=(0.4, 6.0, 0.3))], options=options)
    x_alone = rollout(alone, p_alone, initial_state(alone, p_alone), n_steps=5).x
    traj = rollout(both, p_both, initial_state(both, p_both), n_steps=5)
    # The shared solve stops at a force residual of tol |M s| / h^2 (s ~ x: the 3 kg brick at
    # 1 m dominates), which moves a beam vertex by at most that over its m / h^2 (measured:
    # 2.9e-10 m against a bound of 2e-8 m).
    mass = np.asarray(prepare(both, p_both).mass[:, 0])
    bound = 1e-12 * np.linalg.norm(mass[:, None] * np.asarray(both.mesh.points)) / mass[:beam.n_vertices].min()
    np.testing.assert_allclose(traj.x[:, :beam.n_vertices], x_alone, rtol=0, atol=bound)
    loaded = Result.load(Result.from_mesh(both.mesh, traj.x, 0.01).save(tmp_path / "scene.npz"))
    assert {"beam", "brick"} <= set(loaded.regions)
    brick = both.mesh.regions["brick"]
    np.testing.assert_array_equal(loaded.regions["brick"].faces, brick.faces)
    assert set(brick.faces.ravel()) <= set(loaded.surface.ravel())


def test_rigid_bodies_are_refused_where_they_cannot_go(no_compiling):
    beam = grid_box((0.06, 0.01, 0.01), (4, 1, 1))
    soft = SoftBody(beam, Material(), name="brick")
    with pytest.raises(SceneError, match="needs a name"):
        build(RigidBody(BRICK, density=500.0))
    with pytest.raises(SceneError, match="unique"):
        build([soft, _brick()])
    with pytest.raises(SceneError, match="mass must be positive"):
        RigidBody(BRICK, mass=-1.0, name="brick")
    arm = SoftBody(beam, Material(), name="arm")
    bone = Skeleton((Link("hinge", "brick", None, Revolute((0, 0, 1), (0, 0, 0))),))
    with pytest.raises(SkeletonError, match="cannot be a bone"):
        build([arm, _brick(x0=(1.0, 0.0, 0.0))], skeleton=bone)
    model, params = build(_brick())
    with pytest.raises(SceneError, match="static solve has no equilibrium"):
        prepare(model, params, static=True)
    with pytest.raises(SceneError, match="Newton reference"):
        newton_rollout(model, params, initial_state(model, params), n_steps=2)

"""Sheets against obstacles with friction: a cloth dropped on a sphere, a flat sheet on an
incline. Obstacles act per vertex, so a :func:`~softbody.shell.shell_body`'s vertices meet
them as a solid body's surface vertices do (the sheet's faces do not take part: between
its vertices a face may cut a curved obstacle by up to its sagitta, ``h^2 / (8 R)``).
"""

import jax.numpy as jnp
import numpy as np
import pytest
from test_contact import with_plane

from softbody.contact.obstacles import Plane, Sphere
from softbody.meshing import TetMesh, sheet
from softbody.model import Options, build, initial_state, prepare
from softbody.shell import shell_body
from softbody.simulate import contact_forces, rollout
from softbody.solvers import LocalGlobal

from incline import G, acceleration, ramped_gravity, rot_y

NU = 0.3
#: cotton-like fabric, as tests/test_cloth.py's: E t = 2000 N/m, 0.2 kg/m^2
FABRIC = {"E": 4e6, "nu": NU, "thickness": 5e-4, "areal_density": 0.2}
MU_S, MU_K = 0.5, 0.4
DT = 0.01


def _lifted(mesh, points):
    """``mesh`` with its vertices moved to ``points``."""
    return TetMesh(points, mesh.tets, mesh.surface, mesh.regions)


# ----------------------------------------------------------------------------- a drape


RADIUS, SIDE, GAP = 0.1, 0.4, 0.01


@pytest.fixture(scope="module")
def drape():
    """A 0.4 m square of fabric (gmsh, h = 4 cm, 162 vertices), centred 1 cm above a rough
    sphere of radius 0.1 m (``mu_s`` 0.5, ``mu_k`` 0.4), dropped: 1.5 s at dt = 1/100 s,
    rolled out without raising (11 of its steps stop short of the tolerance: see
    :func:`test_every_step_of_the_drape_converges`) so that the tests can say what holds."""
    flat = sheet.rectangle(SIDE, SIDE, 0.04, x0=-SIDE / 2)
    mesh = _lifted(flat, flat.points + [0.0, -SIDE / 2, RADIUS + GAP])
    sphere = Sphere(center=(0.0, 0.0, 0.0), radius=RADIUS, mu_s=MU_S, mu_k=MU_K)
    model, params = build(shell_body(mesh, **FABRIC), obstacles=[sphere],
                          options=Options(dt=DT, tol=1e-6, max_iter=3000, solver=LocalGlobal()))
    traj = rollout(model, params, initial_state(model, params), n_steps=150, throw=False)
    return mesh, model, params, sphere, traj


def test_a_cloth_dropped_on_a_sphere_drapes_it_without_penetration_and_comes_to_rest(drape):
    """No vertex ends a step inside the sphere (its own signed distance; the contact step
    projects each vertex onto the obstacle's surface, so only round-off remains: bound
    1e-12 m, as for solid bodies); the cloth hangs over it (its rim well below the top);
    its rms speed at the end is below 1 % of the speed of the drop (kinetic energy below
    1e-4 of ``m g`` times the fall of its centre of mass); and the sphere carries its
    weight. The contact forces balance the momentum, ``sum f = m (g + a)`` with ``a`` the
    centre of mass's acceleration, to 1e-3 of ``m g`` (the residual tolerance 1e-6 of
    ``|M s / h^2|`` leaves about 1e-4 of it); at rest they add up to ``(0, 0, m g)``
    within 1 %: what is left of the swinging, an rms speed ``v`` at pendulum frequencies
    ``sqrt(g / l) ~ 10 /s`` for ``l ~ R``, accelerates the centre of mass by ``~10 v``,
    0.3 % of ``g`` at ``v`` = 3 mm/s."""
    _, model, params, sphere, traj = drape
    x, v = np.asarray(traj.x), np.asarray(traj.v)
    phi = np.stack([np.asarray(sphere.distance(jnp.asarray(xs), params.obstacles[0], 0.0)[0]) for xs in x])
    assert phi.min() > -1e-12, phi.min()
    assert x[-1, :, 2].min() < -0.5 * RADIUS  # it drapes: the corners hang well below the top
    mass = np.asarray(prepare(model, params).mass).ravel()
    m = mass.sum()
    assert m == pytest.approx(FABRIC["areal_density"] * SIDE**2, rel=1e-12)
    fall = (x[0, :, 2] - x[-1, :, 2]) @ mass / m
    kinetic = 0.5 * np.sum(mass[:, None] * v[-1] ** 2)
    assert fall > 0 and kinetic < 1e-4 * m * G * fall, (kinetic, m * G * fall)
    force, state = (np.asarray(a)[-10:] for a in contact_forces(model, params, traj))
    com_acceleration = np.diff(np.einsum("i,tik->tk", mass, v) / m, axis=0)[-10:] / DT
    np.testing.assert_allclose(force.sum(axis=1), m * (com_acceleration + [0.0, 0.0, G]), atol=1e-3 * m * G)
    np.testing.assert_allclose(force.sum(axis=1), np.broadcast_to([0.0, 0.0, m * G], (10, 3)), atol=0.01 * m * G)
    assert (state > 0).sum(axis=1).min() >= 3  # it rests on more than one vertex


@pytest.mark.xfail(strict=True, reason="the contact iteration stalls on 11 of the drape's 150 steps (relative "
                                       "residual 5e-6 to 4e-3 after 3000 iterations, tolerance 1e-6)")
def test_every_step_of_the_drape_converges(drape):
    """Every step of the drape meets its tolerance: not yet. The splitting iteration's sweep
    divides by the diagonal ``M/h^2 + D``; a fabric's membrane is stiff against its small
    vertex masses (``E t h_t^2 / (rho_A h^2)`` = 625 here, ``h_t`` the time step), and the
    plain sweep contracts by about ``1 - 1e-4`` per iteration (measured on the landing step:
    1.6e-3 after 10000 iterations, 8.9e-5 after 40000). Anderson mixing brings most steps to
    1e-6 in 500-800 iterations, but the landing (steps 5-7) and some steps as it settles stall at 5e-6 to 4e-3, with
    or without friction (``mu`` 0 stalls too), with the active-set iteration as well, and
    after 20000 iterations still. A sheet landing flat on a plane converges in 1-2."""
    assert np.asarray(drape[-1].info.converged).all()


# ----------------------------------------------------------------------------- an incline


@pytest.fixture(scope="module")
def sheet_on_plane():
    """A 10 cm square of the fabric (gmsh, h = 2.5 cm) lying on a rough plane that the
    tests tilt (``mu_s`` 0.5; ``mu_k`` set per test), 1 s at dt = 1/100 s; gravity is
    ramped up over 0.1 s as external forces (see ``incline``)."""
    mesh = sheet.rectangle(0.1, 0.1, 0.025, x0=-0.05)
    mesh = _lifted(mesh, mesh.points - [0.0, 0.05, 0.0])
    model, params = build(shell_body(mesh, **FABRIC), obstacles=[Plane(mu_s=MU_S, mu_k=MU_K)],
                          options=Options(dt=DT, gravity=(0.0, 0.0, 0.0), tol=1e-8, max_iter=3000,
                                          solver=LocalGlobal()))
    return mesh, model, params, np.asarray(prepare(model, params).mass)


def _on_incline(scene, tan_theta, mu_k, n_steps=100):
    """Roll the sheet out on the plane tilted by ``theta`` about y; returns each frame's
    displacement of every vertex along the slope (downhill), ``(T + 1, n)``, and the
    trajectory."""
    mesh, model, params, mass = scene
    r = rot_y(np.arctan(tan_theta))
    x0 = mesh.points @ r.T
    params = with_plane(params, normal=r[:, 2], mu_k=mu_k)
    traj = rollout(model, params, initial_state(model, params, x=x0), forces=ramped_gravity(mass, n_steps, DT))
    return (np.asarray(traj.x) - x0) @ r[:, 0], traj


def test_a_sheet_sticks_on_an_incline_below_the_static_threshold(sheet_on_plane):
    """tan(theta) = 0.9 mu_s: every step converges and, over the whole second, the sheet
    neither moves along the slope nor leaves the plane beyond round-off (1e-12 m). Unlike
    a solid block (whose edges micro-slip while its weight ramps up), a flat sheet has every
    vertex on the plane: each one's friction holds its own weight's slope component, so
    the membrane carries no load and nothing deforms."""
    along, traj = _on_incline(sheet_on_plane, 0.9 * MU_S, MU_S)
    assert np.asarray(traj.info.converged).all()
    assert np.abs(along).max() < 1e-12
    normal = np.asarray(traj.x) @ rot_y(np.arctan(0.9 * MU_S))[:, 2]
    assert np.abs(normal).max() < 1e-12


def test_a_sheet_slides_down_an_incline_with_kinetic_friction(sheet_on_plane):
    """tan(theta) = 1.1 mu_s, mu_k = 0.8 mu_s: every step converges, the sheet stays on
    the plane, and its centre of mass accelerates at ``g (sin(theta) - mu_k cos(theta))``
    within 1e-4 (relative). Implicit Euler moves a body under constant forces along an
    exact parabola, and a flat sheet has no rocking: every vertex slides on the kinetic
    cone's edge from the ramp's end. What is left is the step's residual, at most 1e-8 of
    ``|M s / h^2|`` (``s`` within 0.7 m of the origin): a force on the centre of mass of
    at most ``1e-8 m 0.7 / h^2``, 5e-5 of ``m a``. Fit after 0.15 s (the ramp's 0.1 s and
    the start of the slide)."""
    theta = np.arctan(1.1 * MU_S)
    along, traj = _on_incline(sheet_on_plane, 1.1 * MU_S, MU_K)
    assert np.asarray(traj.info.converged).all()
    expected = G * (np.sin(theta) - MU_K * np.cos(theta))
    a = acceleration(along.mean(axis=1), DT, 15)
    assert abs(a - expected) < 1e-4 * expected, (a, expected)
    normal = np.asarray(traj.x) @ rot_y(theta)[:, 2]
    assert np.abs(normal).max() < 1e-12

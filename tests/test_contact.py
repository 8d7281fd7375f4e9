"""Contact and dry friction: obstacle geometry, analytic friction physics, the splitting's
spectral radius, and gradients through contact.

Physics scenes use structured grid boxes (fast to mesh and compile) and one coarse gmsh
ball; the splitting study uses gmsh meshes, whose PD matrices are not M-matrices.
Friction needs a tighter step tolerance than the core's default (1e-4 of ``|M s / h^2|``,
which let a sliding cube's acceleration err by 2-4 %), so these scenes use 1e-6 to 1e-8.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import io
from softbody.contact import law as contact_law
from softbody.contact import CONTACT_STATES, Contact
from softbody.material import Material
from softbody.meshing import examples
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.contact.obstacles import (
    Box,
    Capsule,
    HeightField,
    Moving,
    ObstacleError,
    ObstacleRows,
    Plane,
    PlaneParams,
    Sphere,
    from_dict,
    nearest_obstacle,
)
from softbody.simulate import contact_forces, rollout, step
from softbody.solvers import LBFGS, LocalGlobal, StepProblem, Vertices
from softbody.contact.splitting import Diagonal, Naive, ScaledDiagonal, _pd_split, splitting_spectral_radius

from incline import G, acceleration, ramped_gravity, rot_y

EDGE = 0.1  # cube edge, m (density 1000: mass 1 kg)
MU_S, MU_K = 0.5, 0.4
DT = 0.01
#: scenes that touch from the first step never take the contact-free path: a cheap solver
#: for it (plain PD) compiles faster than the default L-BFGS
TOUCHING = LocalGlobal()


# ----------------------------------------------------------------------------- geometry


def test_signed_distances_normals_and_velocities():
    pts = jnp.array([[0.0, 0.0, 2.0], [0.2, 0.1, 0.3], [3.0, 0.0, 0.0]])
    cases = [
        (Plane(point=(0, 0, 1), normal=(0, 0, 2)), [1.0, -0.7, -1.0], [[0, 0, 1]] * 3),
        (
            Sphere(center=(0, 0, 0), radius=1.0),
            [1.0, np.sqrt(0.14) - 1, 2.0],
            [[0, 0, 1], np.array([0.2, 0.1, 0.3]) / np.sqrt(0.14), [1, 0, 0]],
        ),
        (
            Box(center=(0, 0, 0), half_extents=(1, 0.5, 0.5)),
            [1.5, -0.2, 2.0],
            [[0, 0, 1], [0, 0, 1], [1, 0, 0]],
        ),
        (
            Capsule(p0=(0, 0, 0), p1=(1, 0, 0), radius=0.5),
            [1.5, np.sqrt(0.1) - 0.5, 1.5],
            [[0, 0, 1], np.array([0, 0.1, 0.3]) / np.sqrt(0.1), [1, 0, 0]],
        ),
    ]
    for ob, phi_ref, n_ref in cases:
        phi, normal, vel = jax.jit(ob.distance)(pts, ob.init_params(), 0.0)
        np.testing.assert_allclose(phi, phi_ref, atol=1e-12, err_msg=ob.kind)
        np.testing.assert_allclose(normal, np.asarray(n_ref, float), atol=1e-12, err_msg=ob.kind)
        np.testing.assert_array_equal(vel, 0.0)

    # a rotated box: the point (2, 0, 0) lies 1 m out of the face whose axis is world x
    c, s = np.cos(0.4), np.sin(0.4)
    rz = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    box = Box(half_extents=(1, 1, 1), rotation=rz)
    phi, normal, _ = box.distance(jnp.array([[2 * c, 2 * s, 0.0]]), box.init_params(), 0.0)
    np.testing.assert_allclose(phi, [1.0], atol=1e-12)
    np.testing.assert_allclose(normal, [[c, s, 0.0]], atol=1e-12)

    # a height field sloping up along x at 0.5: distance (z - H)/sqrt(1.25)
    hf = HeightField(origin=(0, 0), spacing=(1, 1), heights=[[0, 0], [0.5, 0.5], [1.0, 1.0]])
    phi, normal, _ = hf.distance(
        jnp.array([[0.5, 0.5, 1.0], [5.0, 0.5, 1.5]]), hf.init_params(), 0.0
    )
    np.testing.assert_allclose(phi, [0.75 / np.sqrt(1.25), 0.5], atol=1e-12)
    np.testing.assert_allclose(normal[0], np.array([-0.5, 0, 1]) / np.sqrt(1.25), atol=1e-12)
    np.testing.assert_allclose(normal[1], [0, 0, 1], atol=1e-12)  # flat beyond the grid


def test_distances_vmap_over_obstacle_parameters():
    pts = jnp.array([[0.0, 0.0, 2.0], [0.3, -0.2, 0.1]])
    for ob in (Plane(), Sphere(), Box(), Capsule(), HeightField()):
        base = ob.init_params()
        batch = jax.tree.map(lambda a: jnp.stack([a, a]), base).replace(mu_s=jnp.array([0.2, 0.9]))
        phi, normal, vel = jax.vmap(lambda p: ob.distance(pts, p, 0.0))(batch)
        assert phi.shape == (2, 2) and normal.shape == vel.shape == (2, 2, 3)
        np.testing.assert_allclose(phi[0], ob.distance(pts, base, 0.0)[0])


def test_per_vertex_contact_rule():
    """Separate, stick, slide and bounce, vertex by vertex, against a plane z = 0."""
    h, mu_s, mu_k = 0.01, 0.5, 0.3
    x_n = jnp.zeros((5, 3))
    v_n = jnp.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, -2.0], [0, 0, 0]])
    y = jnp.array(
        [
            [0.1, 0.0, 0.01],  # above the plane: separating, untouched
            [0.004, 0.0, -0.01],  # slip 0.004 <= mu_s * depth 0.005: sticks
            [0.03, 0.04, -0.01],  # slip 0.05 > 0.005: slides back by mu_k * depth
            [0.0, 0.0, -0.01],  # arrives at 2 m/s with restitution 0.5
            [0.0, 0.0, -0.01],
        ]
    )
    plane = Plane(mu_s=mu_s, mu_k=mu_k)
    params = plane.init_params()
    frame = list(nearest_obstacle(((plane, params),), y, 0.0))
    frame[5] = jnp.array([0.0, 0.0, 0.0, 0.5, 0.0])  # per-vertex restitution
    free = jnp.array([[1.0], [1.0], [1.0], [1.0], [0.0]])  # the last vertex is fixed: untouched
    x = np.asarray(contact_law._contact_step(y, x_n, v_n, h, tuple(frame), free))
    np.testing.assert_allclose(x[0], y[0])
    np.testing.assert_allclose(x[1], [0.0, 0.0, 0.0], atol=1e-15)
    slip = np.array([0.03, 0.04]) * (1 - mu_k * 0.01 / 0.05)
    np.testing.assert_allclose(x[2], [slip[0], slip[1], 0.0], atol=1e-15)
    np.testing.assert_allclose(x[3], [0.0, 0.0, h * 0.5 * 2.0], atol=1e-15)  # leaves at e v_in
    np.testing.assert_allclose(x[4], y[4])

    # a moving obstacle: sticking means moving with its surface, x_n + h u
    belt = Moving(Plane(mu_s=mu_s), lambda t: (jnp.eye(3), jnp.array([0.2 * t, 0.0, 0.0])))
    frame = nearest_obstacle(((belt, belt.init_params()),), y[1:2], 0.0)
    x = contact_law._contact_step(y[1:2], x_n[1:2], v_n[1:2], h, frame, free[:1])
    np.testing.assert_allclose(x, [[0.2 * h, 0.0, 0.0]], atol=1e-15)


def test_moving_obstacle_pose_and_velocity():
    def spin(t):
        c, s = jnp.cos(2.0 * t), jnp.sin(2.0 * t)
        return jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), jnp.array(
            [0.1 * t, 0.0, 0.0]
        )

    jaw = Moving(Box(half_extents=(1, 1, 1)), spin)
    x = jnp.array([[2.0, 0.0, 0.0]])
    phi, normal, vel = jaw.distance(x, jaw.init_params(), 0.0)
    np.testing.assert_allclose(phi, [1.0], atol=1e-12)
    np.testing.assert_allclose(normal, [[1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(vel, [[0.1, 4.0, 0.0]], atol=1e-12)  # dp/dt + omega x r
    d = jaw.to_dict(time=np.pi / 4)  # a quarter turn: axes rotated by 90 degrees
    np.testing.assert_allclose(d["rotation"], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(d["center"], [0.1 * np.pi / 4, 0, 0], atol=1e-12)
    with pytest.raises(ObstacleError, match="rotation"):
        Moving(Plane(), lambda t: (2.0 * jnp.eye(3), jnp.zeros(3)))
    with pytest.raises(ObstacleError, match="non-finite"):
        Moving(Plane(), lambda t: (jnp.eye(3), jnp.full(3, jnp.nan)))


def test_obstacle_validation_and_result_format():
    with pytest.raises(ObstacleError, match="mu_k=0.6 exceeds the static one mu_s=0.5"):
        Plane(mu_s=0.5, mu_k=0.6)
    with pytest.raises(ObstacleError, match=">= 0"):
        Sphere(mu_s=-0.1)
    with pytest.raises(ObstacleError, match="restitution"):
        Plane(restitution=1.5)
    with pytest.raises(ObstacleError, match="non-finite"):
        Sphere(center=(0, np.inf, 0))
    with pytest.raises(ObstacleError, match="non-zero"):
        Plane(normal=(0, 0, 0))
    with pytest.raises(ObstacleError, match="rotation matrix"):
        Box(rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ObstacleError, match="positive"):
        Capsule(radius=0.0)
    with pytest.raises(ObstacleError, match="2 x 2"):
        HeightField(heights=[[0.0, 1.0]])
    with pytest.raises(ObstacleError, match="unknown obstacle type 'cone'"):
        from_dict({"type": "cone"})
    with pytest.raises(ObstacleError, match="missing"):
        from_dict({"type": "sphere", "center": [0, 0, 0]})

    obstacles = [
        Plane(normal=(0.1, 0, 1), mu_s=0.8, mu_k=0.6),
        Sphere(center=(0, 0, 1), radius=0.2),
        Box(center=(1, 0, 0), half_extents=(0.1, 0.2, 0.3)),
        Capsule(restitution=0.3),
        HeightField(heights=np.arange(6.0).reshape(3, 2)),
    ]
    dicts = [ob.to_dict() for ob in obstacles]
    mesh = grid_box(cells=(1, 1, 1))
    result = io.Result(
        points=mesh.points,
        tets=mesh.tets,
        surface=mesh.surface,
        x=mesh.points[None],
        dt=0.01,
        obstacles=dicts,
    )  # the viewer's format accepts them
    assert [o["type"] for o in result.obstacles] == [o.kind for o in obstacles]
    for ob, d in zip(obstacles, dicts):
        back = from_dict(d)
        for f in dataclasses.fields(ob.init_params()):
            np.testing.assert_allclose(
                getattr(back.init_params(), f.name),
                getattr(ob.init_params(), f.name),
                err_msg=f"{ob.kind}.{f.name}",
            )


def test_obstacle_parameters_are_typed_pytrees():
    """``init_params`` gives the shape's equinox module; updates go through ``replace`` or
    ``eqx.tree_at``, unknown fields are refused, and ``to_dict`` writes the updated values
    in the unchanged result format."""
    params = Plane(mu_s=0.5, mu_k=0.4).init_params()
    assert type(params) is PlaneParams
    assert [f.name for f in dataclasses.fields(params)] == [
        "mu_s",
        "mu_k",
        "restitution",
        "point",
        "normal",
    ]
    assert float(params.mu_k) == 0.4 and params.mu_k.dtype == jnp.float64
    tilted = params.replace(mu_k=jnp.asarray(0.3), normal=jnp.array([0.0, 1.0, 1.0]))
    assert float(tilted.mu_k) == 0.3 and float(params.mu_k) == 0.4  # a copy
    assert float(eqx.tree_at(lambda p: p.mu_s, params, jnp.asarray(0.7)).mu_s) == 0.7
    with pytest.raises(ObstacleError, match=r"PlaneParams has no field\(s\) \['mu'\]"):
        params.replace(mu=0.1)
    d = Plane().to_dict(tilted)
    assert d == {
        "type": "plane",
        "point": [0.0, 0.0, 0.0],
        "normal": [0.0, 1.0, 1.0],
        "mu_s": 0.5,
        "mu_k": 0.3,
        "restitution": 0.0,
    }
    mesh = grid_box(cells=(1, 1, 1))
    _, scene = build(SoftBody(mesh, Material()), obstacles=[Plane(mu_s=0.5, mu_k=0.4)])
    scene = eqx.tree_at(lambda p: p.obstacles[0].mu_k, scene, jnp.asarray(0.2))
    assert float(scene.obstacles[0].mu_k) == 0.2 and isinstance(scene.obstacles[0], PlaneParams)


def test_contact_rejects_bad_settings_and_mismatched_parameters():
    with pytest.raises(ValueError, match="Splitting"):
        Contact(splitting="diag")
    with pytest.raises(ValueError, match="history"):
        Contact(history=-1)
    with pytest.raises(ValueError, match="warm_start must be True or False"):
        Contact(warm_start=1)
    for floor in (-0.1, float("nan")):
        with pytest.raises(ValueError, match="rigid_floor must be a number >= 0"):
            Contact(rigid_floor=floor)
    with pytest.raises(ValueError, match="scale"):
        ScaledDiagonal(0.0)
    for blocks in (((1, 4),), ((0, 2), (3, 4)), ((0, 0),), ((0, 2, 4),)):
        with pytest.raises(ValueError, match="consecutive vertex ranges"):
            Contact(blocks=blocks)
    x = jnp.zeros((4, 3))
    problem = StepProblem(
        evaluate=None,
        precondition=None,
        diagonal=jnp.ones((4, 1)),
        x_n=x,
        v_n=x,
        mass=jnp.ones((4, 1)),
        free=jnp.ones((4, 1)),
        dt=0.01,
        time=jnp.asarray(0.0),
        rows=((ObstacleRows((Plane(),)), ({"point": jnp.zeros(3)},)),),
    )
    with pytest.raises(ObstacleError, match="must be the PlaneParams made by init_params"):
        Contact().run(problem, Vertices(), LBFGS(), x, None, 1e-6, 10)
    wrong = ((ObstacleRows((Plane(),)), (Sphere().init_params(),)),)
    with pytest.raises(ObstacleError, match="got a SphereParams"):
        Contact().run(problem._replace(rows=wrong), Vertices(), LBFGS(), x, None, 1e-6, 10)
    model, params = build(SoftBody(grid_box(cells=(1, 1, 1)), Material(), fixed="xmin"))
    traj = rollout(model, params, initial_state(model, params), n_steps=1)
    with pytest.raises(SceneError, match="contact_forces needs a scene with obstacles"):
        contact_forces(model, params, traj)
    with pytest.raises(ObstacleError, match="obstacle 0 is a str"):
        Contact().run(problem._replace(rows=((ObstacleRows(("floor",)), ({},)),)), Vertices(), LBFGS(), x, None,
                      1e-6, 10)


# ----------------------------------------------------------------------------- friction physics


@pytest.fixture(scope="module")
def cube_scene():
    """A soft 1 kg cube (4^3 cells) and a plane whose pose and friction the tests set.

    Stiffness-proportional damping (``beta``, which does not resist rigid sliding) lets the
    cube's rocking settle within the test's 0.4 s.

    Gravity enters as external forces ramped up over 0.1 s (see ``incline``).
    """
    mesh = grid_box((EDGE,) * 3, (4, 4, 4), origin=(-EDGE / 2, -EDGE / 2, 0.0))
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, beta=0.01)),
                          options=Options(dt=DT, gravity=(0.0, 0.0, 0.0), tol=1e-8, max_iter=3000,
                                          solver=TOUCHING), obstacles=[Plane(mu_s=MU_S, mu_k=MU_K)])
    mass = np.asarray(prepare(model, params).mass)
    return mesh, model, params, mass


def gravity(mass, n_steps):
    return ramped_gravity(mass, n_steps, DT)


def with_plane(params, **values):
    """``params`` with the plane's parameters updated."""
    values = {k: jnp.asarray(v, jnp.float64) for k, v in values.items()}
    plane = params.obstacles[0].replace(**values)
    return eqx.tree_at(lambda p: p.obstacles[0], params, plane)


def on_incline(cube_scene, tan_theta, mu_k, n_steps):
    """Roll the cube out, set down on a plane tilted by theta about y (gravity -z).

    Returns ``(com, bottom, traj, contact)``: the centre of mass's and the bottom vertices'
    displacements along the slope (downhill) per frame, the trajectory, and its contact
    forces and states (``contact_forces``).
    """
    mesh, model, params, mass = cube_scene
    r = rot_y(np.arctan(tan_theta))
    x0 = mesh.points @ r.T
    params = with_plane(params, normal=r[:, 2], mu_k=mu_k)
    forces = gravity(mass, n_steps)
    traj = rollout(model, params, initial_state(model, params, x=x0), forces=forces)
    along = (np.asarray(traj.x) - x0) @ r[:, 0]
    contact = contact_forces(model, params, traj, forces=forces)
    return along.mean(axis=1), along[:, mesh.regions["zmin"].vertices], traj, contact


def test_cube_sticks_below_and_slides_above_the_static_threshold(cube_scene):
    # tan(theta) = 0.9 mu_s: once set down (edge micro-slip while the load ramps up), it stays
    com, bottom, traj, contact = on_incline(cube_scene, 0.9 * MU_S, MU_S, 50)
    assert np.asarray(traj.info.converged).all()
    assert np.abs(bottom[40:] - bottom[40]).max() < 1e-7, (
        "contact vertices must not slip while sticking"
    )
    assert np.abs(com[40:] - com[40]).max() < 1e-7, "the body must not creep"
    assert np.abs(bottom).max() < 2e-4
    # At rest the plane carries the weight: bottom vertices only, all sticking, inside the
    # cone (the uphill edge carries the least and may carry nothing).
    mesh, mass = cube_scene[0], cube_scene[3].sum()
    force, state = (np.asarray(a)[40:] for a in contact)
    bottom_vertices = mesh.regions["zmin"].vertices
    assert np.all(np.isin(state[:, bottom_vertices], [CONTACT_STATES.index("none"), CONTACT_STATES.index("stick")]))
    assert (state[:, bottom_vertices] > 0).sum(axis=1).min() >= 15
    assert np.all(np.delete(state, bottom_vertices, axis=1) == CONTACT_STATES.index("none"))
    np.testing.assert_allclose(force.sum(axis=1), np.broadcast_to([0.0, 0.0, mass * G], (10, 3)),
                               atol=1e-3 * mass * G)
    n = rot_y(np.arctan(0.9 * MU_S))[:, 2]
    touching = state > 0
    normal = force @ n
    tangential = np.linalg.norm(force - normal[..., None] * n, axis=-1)
    assert np.all(normal[touching] > 0) and np.all(tangential[touching] <= MU_S * normal[touching] * (1 + 1e-6))

    # tan(theta) = 1.1 mu_s: it slides with a = g (sin - mu_k cos), mu_k = 0.8 mu_s
    theta = np.arctan(1.1 * MU_S)
    com, bottom, traj, contact = on_incline(cube_scene, 1.1 * MU_S, MU_K, 40)
    assert np.asarray(traj.info.converged).all()
    expected = G * (np.sin(theta) - MU_K * np.cos(theta))
    a = acceleration(com, DT, 15)  # after the ramp and its transient
    assert abs(a - expected) < 0.05 * expected, (a, expected)
    normal_height = np.asarray(traj.x) @ rot_y(theta)[:, 2]
    assert normal_height.min() > -1e-12, "no vertex may end a step below the incline"
    # Sliding: every contact vertex is on the kinetic cone's edge, and the plane carries
    # the weight's normal part (m g cos theta: no acceleration across the plane).
    force, state = (np.asarray(a)[15:] for a in contact)
    touching = state > 0
    assert np.all(state[touching] == CONTACT_STATES.index("slide")) and touching.sum(axis=1).min() >= 4
    n = rot_y(theta)[:, 2]
    normal = force @ n
    tangential = np.linalg.norm(force - normal[..., None] * n, axis=-1)
    # r = grad Phi at the solution, whose residual norm is at most tol |M s / h^2|: each
    # vertex's normal and tangential parts are off by at most that much.
    masses = cube_scene[3]
    residual = 1e-8 * np.linalg.norm(masses * np.asarray(traj.x)[16:], axis=(1, 2)) / DT**2
    assert np.all(np.abs(tangential - MU_K * normal)[touching] <= (1 + MU_K) * np.broadcast_to(
        residual[:, None], touching.shape)[touching])
    mass = masses.sum()
    np.testing.assert_allclose(normal.sum(axis=1), mass * G * np.cos(theta), rtol=0.01)


def test_cube_pushed_below_and_above_static_friction(cube_scene):
    mesh, model, params, mass = cube_scene
    side = mesh.regions["xmin"].vertices
    state0 = initial_state(model, params)
    n = 50

    def push(total):
        f = gravity(mass, n)
        f[10:, side, 0] = total / len(side)  # push once the cube has settled
        traj = rollout(model, params, state0, forces=f)
        assert np.asarray(traj.info.converged).all()
        return np.asarray(traj.x).mean(axis=1)[:, 0]

    m = mass.sum()
    com = push(0.5 * MU_S * m * G)
    assert np.abs(com[40:] - com[40]).max() < 1e-7, "below mu_s m g the cube must come to rest"
    assert np.abs(com - com[0]).max() < 1e-3, "only elastic deformation may shift the centre"
    force = 1.5 * MU_S * m * G
    com = push(force)
    expected = force / m - MU_K * G
    a = acceleration(com, DT, 15)
    assert abs(a - expected) < 0.05 * expected, (a, expected)


@pytest.fixture(scope="module")
def ball_drop():
    """A coarse gmsh ball (208 vertices) dropped from 1 cm onto a rough floor, 3 s.

    Landing on a vertex of its polyhedral surface, it tips onto a face and rocks; air drag
    (mass damping ``alpha``) lets it come to rest within the run.
    """
    mesh = examples.ball(radius=0.05, clearance=0.01, size=0.02)
    model, params = build(SoftBody(mesh, Material(E=2e4, nu=0.3, alpha=5.0)),
                          options=Options(dt=DT, tol=1e-8, max_iter=3000), obstacles=[Plane(mu_s=0.6, mu_k=0.5)])
    traj = rollout(model, params, initial_state(model, params), n_steps=300)
    return mesh, traj


def test_dropped_ball_comes_to_rest_without_penetration_or_drift(ball_drop):
    mesh, traj = ball_drop
    x, v = np.asarray(traj.x), np.asarray(traj.v)
    assert np.asarray(traj.info.converged).all()
    assert x[..., 2].min() > -1e-12, "penetration beyond the tolerance"
    touch = int(np.argmax(x[..., 2].min(axis=1) < 1e-9))
    assert 3 < touch < 7  # falls 1 cm in 0.045 s
    assert np.abs(v[-1]).max() < 1e-4, "the ball must come to rest"
    com = x.mean(axis=1)
    assert np.abs(com[-50:] - com[-50]).max() < 3e-5, "a resting ball must not drift or sink"


def test_free_fall_needs_no_contact_work(ball_drop):
    _, traj = ball_drop
    x = np.asarray(traj.x)
    assert (x[1:4, :, 2].min(axis=1) > 1e-3).all()
    # the contact-free steps ran L-BFGS: a few iterations, not the splitting's many
    assert np.asarray(traj.info.iterations)[:3].max() < 15


def test_moving_plate_carries_a_sticking_cube(cube_scene):
    """A plate sliding at 5 cm/s under the cube drags it along through static friction."""
    mesh = cube_scene[0]
    speed = 0.05
    plate = Moving(
        Plane(mu_s=MU_S, mu_k=MU_K), lambda t: (jnp.eye(3), jnp.array([speed * t, 0.0, 0.0]))
    )
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3)),
                          options=Options(dt=DT, tol=1e-8, max_iter=3000, solver=TOUCHING), obstacles=[plate])
    traj = rollout(model, params, initial_state(model, params), n_steps=60)
    v = np.asarray(traj.v)[-10:, mesh.regions["zmin"].vertices]
    np.testing.assert_allclose(v[..., 0], speed, atol=1e-6)
    assert np.abs(np.asarray(traj.v)[-1].mean(axis=0)[0] - speed) < 0.05 * speed


# ----------------------------------------------------------------------------- the splitting


@pytest.fixture(scope="module")
def gmsh_cube():
    return examples.cube(edge=0.05, size=0.0125)


def test_default_splitting_converges_where_the_published_ones_fail(gmsh_cube):
    grid = grid_box((EDGE,) * 3, (3, 3, 3))
    for mesh, E, dt in [(gmsh_cube, 1e7, 1 / 30), (gmsh_cube, 1e4, 1e-3), (grid, 1e7, 1 / 30)]:
        model, params = build(SoftBody(mesh, Material(E=E, nu=0.45)),
                              options=Options(dt=dt), obstacles=[Plane()])
        prep = prepare(model, params)
        rho = splitting_spectral_radius(model, prep, ScaledDiagonal())
        mass, stiffness, h = _pd_split(model, prep)
        assert rho <= ScaledDiagonal.bound(mass, stiffness.diagonal(), h) < 1, (E, dt, rho)
        assert splitting_spectral_radius(model, prep, Naive()) > 2
    # Jacobi (the published D = diag(L)) diverges on the unstructured mesh, stiff and soft alike
    # once the inertia is small; it converges on the structured grid, whose L is an M-matrix.
    model, params = build(SoftBody(gmsh_cube, Material(E=1e7, nu=0.45)),
                          options=Options(dt=1 / 30), obstacles=[Plane()])
    assert splitting_spectral_radius(model, prepare(model, params), Diagonal()) > 1.02
    model, params = build(SoftBody(grid, Material(E=1e7, nu=0.45)),
                          options=Options(dt=1 / 30), obstacles=[Plane()])
    assert splitting_spectral_radius(model, prepare(model, params), Diagonal()) < 1


def test_full_iteration_diverges_with_naive_and_converges_with_default():
    """The plain splitting iteration (no acceleration) on a cube resting on the ground."""
    mesh = grid_box((EDGE,) * 3, (2, 2, 2))
    residuals = {}
    for splitting in (Naive(), ScaledDiagonal()):
        opts = Options(dt=DT, max_iter=400, solver=LocalGlobal(), contact=Contact(splitting=splitting, history=0))
        model, params = build(SoftBody(mesh, Material(E=1e4, nu=0.3)), options=opts, obstacles=[Plane()])
        prep = prepare(model, params)
        _, info = jax.jit(lambda prep, s: step(model, prep, s))(prep, initial_state(model, params))
        residuals[type(splitting).__name__] = (
            bool(info.converged),
            float(info.residual),
            int(info.iterations),
        )
    assert residuals["ScaledDiagonal"][0], residuals
    # Naive blows up (to NaN after ~360 iterations); the step reports its best iterate, unconverged
    assert not residuals["Naive"][0] and residuals["Naive"][1] > 10 * opts.tol, residuals


# ----------------------------------------------------------------------------- gradients


@pytest.mark.slow
def test_gradient_through_sliding_contact_matches_finite_differences():
    """d(slide distance)/d(mu_k) and d/d(incline angle): the contact step's implicit derivative."""
    mesh = grid_box((EDGE,) * 3, (2, 2, 2), origin=(-EDGE / 2, -EDGE / 2, 0.0))
    opts = Options(dt=DT, tol=1e-11, max_iter=1500, solver=TOUCHING)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3)),
                          options=opts, obstacles=[Plane(mu_s=MU_S, mu_k=MU_K)])
    n_steps = 10

    def slide(mu_k, theta):
        r = jnp.array(
            [
                [jnp.cos(theta), 0.0, jnp.sin(theta)],
                [0.0, 1.0, 0.0],
                [-jnp.sin(theta), 0.0, jnp.cos(theta)],
            ]
        )
        x0 = jnp.asarray(mesh.points) @ r.T
        p = with_plane(params, normal=r[:, 2], mu_k=mu_k)
        traj = rollout(model, p, initial_state(model, p, x=x0), n_steps=n_steps)
        return jnp.mean(traj.x[-1] - x0, axis=0) @ r[:, 0]

    theta = float(np.arctan(0.7))  # well above the static threshold tan(theta) = 0.5
    grad = jax.grad(slide, argnums=(0, 1))(MU_K, theta)
    eps = 1e-5
    fd = (
        (slide(MU_K + eps, theta) - slide(MU_K - eps, theta)) / (2 * eps),
        (slide(MU_K, theta + eps) - slide(MU_K, theta - eps)) / (2 * eps),
    )
    t = n_steps * DT  # rigid sliding from rest: s = g (sin - mu_k cos) t^2 / 2
    assert float(grad[0]) == pytest.approx(-0.5 * G * np.cos(theta) * t**2, rel=0.1)
    for g, f in zip(grad, fd):
        assert np.isfinite(float(g))
        assert abs(float(g) - float(f)) <= 1e-4 * abs(float(f)), (grad, fd)

"""A body thrown at 10 m/s against a 5 mm plate at dt = 1/60 s (softbody.contact.pairs.Touch):
it moves 16.7 cm a step, 33 plate thicknesses, so the step that meets the plate predicts it
8 cm beyond. The rows chosen for that step hold it on the plate's near side, and a soft cube
thrown so stops on the plate with every step converged."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.contact.pairs import Touch
from softbody.rigid import RigidBody
from softbody.scene import SoftBody
from softbody.simulate import rollout
from softbody._types import RESULTS

from test_rigid import box

DT, SPEED, THICKNESS = 1 / 60, 10.0, 1e-3
PLATE_H, EDGE = 0.005, 0.02
# a 6 x 6 cm plate, 5 mm thick (1 cm cells), its top at z = 0, held
PLATE = grid_box((0.06, 0.06, PLATE_H), (6, 6, 1), origin=(-0.03, -0.03, -PLATE_H))
N_PLATE = PLATE.n_vertices
# the body's centre lands off the plate's grid lines (no side of it through a plate vertex)
AIM = np.array([0.0025, 0.0035])
# the search's capacity: every (vertex, triangle) pair of the two surfaces is a candidate of a
# step that moves 16.7 cm (the default, 64 per surface vertex, overflows and says so)
CAPACITY = 20000


def _velocity(angle, speed=SPEED):
    """The throw's velocity, ``angle`` degrees from the plate's normal, towards +x."""
    a = np.radians(angle)
    return speed * np.array([np.sin(a), 0.0, -np.cos(a)])


def _scene(kind, angle, base, rows=True, max_iter=3000, speed=SPEED, mu=0.5):
    """The held plate and a 2 cm cube (soft: 27 vertices, E = 1e6 Pa; or rigid), its base
    ``base`` above the plate's top on the line of its throw through ``AIM``; and its start
    state, thrown at ``speed``; friction ``mu``."""
    v = _velocity(angle, speed)
    centre = np.append(AIM, EDGE / 2) + v * base / v[2]
    if kind == "soft":
        body = SoftBody(grid_box((EDGE,) * 3, (2, 2, 2), origin=centre - EDGE / 2),
                        Material(E=1e6, nu=0.3, density=1000.0), name="body")
    else:
        body = RigidBody(box((EDGE,) * 3, centre=centre), density=1000.0, name="body")
    plate = SoftBody(PLATE, Material(E=1e6, nu=0.3, density=1000.0), fixed=lambda p: np.ones(len(p), bool),
                     name="plate")
    touch = Touch("body", "plate", mu_s=mu, thickness=THICKNESS, capacity=CAPACITY)
    model, params = build([plate, body], rows=[touch] if rows else [],
                          options=Options(dt=DT, tol=1e-8, max_iter=max_iter))
    state = initial_state(model)
    return model, params, eqx.tree_at(lambda s: s.v, state, state.v.at[N_PLATE:].set(jnp.asarray(v)))


@pytest.mark.parametrize("kind", ["soft", "rigid"])
@pytest.mark.parametrize("angle", [0.0, 30.0])
def test_the_rows_of_the_impact_step_hold_the_body_on_the_near_side(kind, angle):
    """The step that meets the plate, its base 8.3 cm (half a step) above it along the throw
    and predicted 8.3 cm beyond: every row is satisfied where the body lands on the plate
    (moved along its throw to rest at the thickness), the plate's vertices under it closing
    their rows there, and those rows see the predicted end through the plate. (A vertex
    paired with the face of the other body nearest the predicted end, the far or a side
    face beyond which it passes, had a row that held it below the plate: 90 of the 124 rows
    of the soft cube thrown normally, 63 obliquely.)"""
    v = _velocity(angle)
    half = 0.5 * DT * -v[2]
    model, params, _ = _scene(kind, angle, half)
    x_start = jnp.asarray(model.mesh.points)
    x_end = x_start.at[N_PLATE:].add(DT * jnp.asarray(v))
    landed = x_start.at[N_PLATE:].add(jnp.asarray(v) * (half - THICKNESS) / -v[2])
    generator, p = model.rows[0], params.rows[0]
    selection = generator.select(x_start, x_end, p)
    assert not bool(selection[1])  # the search held every candidate
    phi = np.asarray(generator.frame(landed, selection, p).phi)
    assert phi.min() > -1e-12  # no row holds the body anywhere but on the plate's near side
    closed = np.abs(phi) < 1e-12
    assert closed.sum() >= 4  # the plate's vertices under the base hold it at the thickness
    through = np.asarray(generator.frame(x_end, selection, p).phi)
    assert np.all(through[closed] < -PLATE_H)  # and at the predicted end see it through the plate


def _through(x):
    """Per step ``(k,)`` bool: a vertex of the body ``x`` ``(k, b, 3)`` lies beyond the held plate
    (below its bottom face) or inside it (below its top face within its footprint)."""
    over = np.all(np.abs(x[..., :2]) <= 0.03, axis=-1)
    return np.any(x[..., 2] < -PLATE_H, axis=-1) | np.any(over & (x[..., 2] < 0.0), axis=-1)


def test_a_cube_thrown_at_the_plate_stops_on_it_with_every_step_converged():
    """The soft cube thrown normally at 10 m/s, its base half a step above the plate: every
    step converges (the impact step's iteration starts where the cube first touches the
    plate, ``softbody.contact.solver._first_touch``: 1241 iterations, the most of any step
    2961, against no convergence in 30000 from the predicted end), no step leaves a vertex
    inside or beyond the plate, and the cube ends at rest on it (restitution 0): its
    momentum gone, its base at the contact thickness. Thrown without the rows, the body
    passes the plate in its first step: what the check sees."""
    v = _velocity(0.0)
    model, params, state = _scene("soft", 0.0, 0.5 * DT * -v[2], max_iter=6000)
    traj = rollout(model, params, state, n_steps=8, throw=False)
    x = np.asarray(traj.x)[1:, N_PLATE:]
    print("iterations", np.asarray(traj.info.iterations), "base", x[-1, :, 2].min())
    assert np.all(np.asarray(traj.info.converged))
    assert np.all(np.asarray(traj.info.result) == int(RESULTS.success))
    assert not np.any(_through(x))
    speed = np.linalg.norm(np.asarray(traj.v)[-1, N_PLATE:].mean(axis=0))
    assert speed < 1e-3 * SPEED  # 10 m/s stopped: its centre moves by less than 1 cm/s
    assert abs(x[-1, :, 2].min() - THICKNESS) < 0.05 * THICKNESS
    # without the rows: the straight flight under gravity, through the plate in one step
    t = DT * np.arange(1, 3)[:, None, None]
    free = np.asarray(state.x)[N_PLATE:] + t * v + 0.5 * t**2 * np.array([0.0, 0.0, -9.81])
    assert np.all(_through(free))


def test_a_rigid_cube_landing_at_1_m_s_rests_on_the_plate_with_every_step_converged():
    """The rigid cube landing normally at 1 m/s without friction, its base half a step above
    the plate: every step converges (281, 53, 11 iterations) and the cube rests at the contact
    thickness, stopped. The pair rows on a rigid part take several sweeps an iteration; when
    each sweep made the rows' frame again, the light cube's tilt turned its rows' forces with
    its bottom face and their torque drove the next sweep's tilt: it rocked by +-0.024 rad
    from sweep to sweep and the impact step stopped at the 30000 cap (frictionless, residual
    7e-5), the cube passing the plate in the next step."""
    v = _velocity(0.0, 1.0)
    model, params, state = _scene("rigid", 0.0, 0.5 * DT * -v[2], max_iter=3000, speed=1.0, mu=0.0)
    traj = rollout(model, params, state, n_steps=3, throw=False)
    x = np.asarray(traj.x)[1:, N_PLATE:]
    assert np.all(np.asarray(traj.info.converged))
    assert np.all(np.asarray(traj.info.result) == int(RESULTS.success))
    assert not np.any(_through(x))
    assert abs(x[-1, :, 2].min() - THICKNESS) < 0.05 * THICKNESS
    assert np.linalg.norm(np.asarray(traj.v)[-1, N_PLATE:].mean(axis=0)) < 1e-2  # 1 m/s stopped

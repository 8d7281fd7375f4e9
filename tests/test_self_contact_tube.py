"""Self-contact (issue 40, bodies touch bodies): a soft tube squashed flat between a moving
plate and the ground until its inner walls touch. With ``Touch("tube", self_contact=True)``
its surface never intersects itself (the meshing module's test) and every step converges;
without it the walls pass into each other."""

import jax.numpy as jnp
import numpy as np
from softbody.meshing import self_intersections
from softbody.meshing.geometry import Cylinder, mesh
from softbody.meshing.mesh import boundary_faces

from softbody._types import RESULTS
from softbody.contact.obstacles import Box, Moving, Plane
from softbody.contact.pairs import Touch
from softbody.material import Material
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout

DT, THICKNESS = 0.02, 1e-3
#: a 2 cm tube along x, outer radius 1 cm, wall 2.5 mm, lying on the ground
RADIUS, WALL, LENGTH = 0.01, 0.0025, 0.02
#: the plate's underside starts one contact thickness above the tube and comes down at
#: SPEED until it is two walls above the ground (the walls then meet with nothing between
#: them; the contact holds them half a thickness apart), where it stays for two steps
TOP, SPEED = 2 * RADIUS + THICKNESS, 0.1
STOP = (TOP - 2 * WALL) / SPEED
N_STEPS = round(STOP / DT) + 2


def _plate(t):
    return jnp.eye(3), jnp.array([0.0, 0.0, TOP + 0.005 - SPEED * jnp.minimum(t, STOP)])


def _gap(x, upper, lower):
    """The least height of the vertices ``upper`` above the triangles ``lower`` ``(k, 3)`` that
    lie under them (negative: a vertex has passed below them)."""
    p, t = x[upper], x[lower]
    a, e1, e2 = t[:, 0, :2], t[:, 1, :2] - t[:, 0, :2], t[:, 2, :2] - t[:, 0, :2]
    w = p[:, None, :2] - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    u = (w[..., 0] * e2[:, 1] - w[..., 1] * e2[:, 0]) / det
    v = (e1[:, 0] * w[..., 1] - e1[:, 1] * w[..., 0]) / det
    z = (1 - u - v) * t[:, 0, 2] + u * t[:, 1, 2] + v * t[:, 2, 2]
    return float(np.min(np.where((u >= 0) & (v >= 0) & (u + v <= 1), p[:, None, 2] - z, np.inf)))


def test_self_contact_holds_a_squashed_tube():
    """A soft tube (282 vertices) pressed flat by a plate coming down at 10 cm/s: its inner
    wall's upper half comes down onto its lower half (their gap, 15 mm at rest, where the
    wall is flattened: |y| < 0.6 of the inner radius) and with self-contact rests on it at the
    contact's distance (half the thickness); the surface never intersects itself and every
    step succeeds. Without self-contact the walls pass into each other."""
    body = (Cylinder(RADIUS, LENGTH, center=(0.0, 0.0, RADIUS), axis="x")
            - Cylinder(RADIUS - WALL, 1.5 * LENGTH, center=(0.0, 0.0, RADIUS), axis="x"))
    tube = mesh(body, size=0.005)
    faces = boundary_faces(tube.tets)
    rest = tube.points
    inner = np.abs(np.hypot(rest[:, 1], rest[:, 2] - RADIUS) - (RADIUS - WALL)) < 1e-6
    flat = inner & (np.abs(rest[:, 1]) < 0.6 * (RADIUS - WALL))
    upper, below = flat & (rest[:, 2] > RADIUS), flat & (rest[:, 2] < RADIUS)
    lower = faces[below[faces].all(axis=1)]
    plate = Moving(Box(half_extents=(0.02, 0.02, 0.005), mu_s=0.3), _plate)
    for contact in (True, False):
        rows = [Touch("tube", self_contact=True, mu_s=0.3, thickness=THICKNESS)] if contact else []
        soft = SoftBody(tube, Material(E=5e4, nu=0.3, density=1000.0), name="tube")
        model, params = build([soft], obstacles=[Plane(mu_s=0.3), plate], rows=rows,
                              options=Options(dt=DT, tol=1e-6, max_iter=3000))
        traj = rollout(model, params, initial_state(model), n_steps=N_STEPS, throw=False)
        x = np.asarray(traj.x)
        crossings = [len(self_intersections(xi, faces)) for xi in x]
        gaps = np.array([_gap(xi, upper, lower) for xi in x])
        # open at rest: the bore's chord at |y| = 0.6 r is 1.6 r
        assert gaps[0] > 1.6 * (RADIUS - WALL)
        if contact:
            results = np.asarray(traj.info.result)
            assert np.all(results == RESULTS.success), (results, np.asarray(traj.info.iterations))
            assert max(crossings) == 0, crossings
            # the last three steps (the plate down, then held): the walls rest on each other
            assert np.all(np.abs(gaps[-3:] - THICKNESS / 2) < THICKNESS / 4), gaps
        else:
            assert crossings[-1] > 0 and gaps[-1] < 0, (crossings, gaps)

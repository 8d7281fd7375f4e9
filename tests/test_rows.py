"""The contact-row seam: a row generator written here, in the test file alone (a few vertices
kept above a moving plane, with friction), runs through ``build``, ``rollout``, the contact
solver, its report and both gradient modes; the obstacles are one generator among others."""

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody._interfaces import Frame, Rows
from softbody._types import SceneError, State
from softbody.contact import Contact
from softbody.gradients import ImplicitForward, Unrolled, central_difference, check_grad, random_directions
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.contact.obstacles import Plane
from softbody.scene import SoftBody
from softbody.simulate import contact_forces, rollout


@dataclass(frozen=True, eq=False)
class AbovePlane(Rows):
    """Keeps the vertices ``vertices`` above the plane ``z = height + speed t`` (moving along
    its normal at ``speed``), with friction ``mu`` (static = kinetic) and no bounce. Its
    design parameters are the plane's height and ``mu``."""

    vertices: np.ndarray  # (k,) vertex indices
    height: float = 0.0
    speed: float = 0.0
    mu: float = 0.0

    def init_params(self):
        return {"height": jnp.asarray(self.height), "mu": jnp.asarray(self.mu)}

    def frame(self, points, index, params, time):
        m = points.shape[0]
        mine = jnp.isin(index, jnp.asarray(self.vertices))
        phi = jnp.where(mine, points[:, 2] - (params["height"] + self.speed * time), jnp.inf)
        normal = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), (m, 3))
        velocity = jnp.broadcast_to(jnp.asarray([0.0, 0.0, self.speed]), (m, 3))
        mu = jnp.broadcast_to(params["mu"], (m,))
        return Frame(phi, normal, velocity, mu, mu, jnp.zeros(m))


CUBE = grid_box((0.04,) * 3, (2, 2, 2), origin=(0.0, 0.0, 0.0005))
SOFT = Material(E=1e4, nu=0.3, density=1000.0)
CONTACT = Options(dt=0.005, tol=1e-12, max_iter=5000)
SLIDE = (0.2, 0.05, 0.0)  # m/s: the cube's initial velocity, sliding as it lands


def _slide(**scene):
    """8 steps of the cube dropping 0.5 mm and sliding on what ``scene`` puts below it."""
    model, params = build(SoftBody(CUBE, SOFT), options=CONTACT, **scene)
    state = initial_state(model, params, v=np.broadcast_to(SLIDE, (model.n_vertices, 3)))
    traj = rollout(model, params, state, n_steps=8)
    assert bool(np.all(traj.info.converged))
    return np.asarray(traj.x)


def test_rows_on_every_vertex_are_the_plane_obstacle():
    """The same plane written as rows on every vertex steps as the ``Plane`` obstacle does
    (the cube lands and slides against friction 0.4); beside the obstacle, rows 1 cm below
    it are never the deepest and change nothing: the solver keeps the deepest row."""
    every = np.arange(CUBE.n_vertices)
    obstacle = _slide(obstacles=[Plane(mu_s=0.4, mu_k=0.4)])
    rows = _slide(rows=[AbovePlane(every, mu=0.4)])
    assert obstacle[..., 2].min() > -1e-9 and obstacle[-1, :, 0].mean() > CUBE.points[:, 0].mean() + 1e-3
    np.testing.assert_allclose(rows, obstacle, rtol=0, atol=1e-12)
    both = _slide(obstacles=[Plane(mu_s=0.4, mu_k=0.4)], rows=[AbovePlane(every, height=-0.01, mu=0.0)])
    np.testing.assert_allclose(both, obstacle, rtol=0, atol=1e-12)


BAR = grid_box((0.1, 0.02, 0.02), (4, 1, 1))
BOTTOM = BAR.points[:, 2] < 1e-9
TIP = np.flatnonzero((BAR.points[:, 0] > 0.099) & BOTTOM)  # the 2 bottom vertices of the free end
RISE = 0.05  # m/s: the plane under the tip rises at 5 cm/s
BENT = Options(dt=0.01, tol=1e-12, max_iter=20000, contact=Contact(adjoint_tol=1e-13))


def _bar(options=BENT, **rows):
    """The bar clamped at x = 0, sagging under gravity, the bottom of its tip kept above a
    plane that starts at it and rises, with friction 0.1."""
    generator = AbovePlane(TIP, height=0.0, speed=RISE, mu=0.1, **rows)
    return build(SoftBody(BAR, SOFT, fixed="xmin"), rows=[generator], options=options)


def test_a_rising_plane_lifts_the_tip_and_the_report_sees_its_rows():
    """The tip rides on the rising plane (on it to 1e-9 m over the last steps); the bottom
    vertices next to it are not held and lag below it; the contact report gives upward
    forces and a contact state on the tip vertices alone."""
    model, params = _bar()
    n = 12
    traj = rollout(model, params, initial_state(model, params), n_steps=n)
    assert bool(np.all(traj.info.converged))
    x = np.asarray(traj.x)
    t = np.arange(n + 1) * BENT.dt
    surface = RISE * t
    assert np.all(x[:, TIP, 2] >= surface[:, None] - 1e-9)
    np.testing.assert_allclose(x[-4:, TIP, 2], np.broadcast_to(surface[-4:, None], (4, len(TIP))), atol=1e-9)
    others = np.flatnonzero((BAR.points[:, 0] > 0.07) & (BAR.points[:, 0] < 0.099) & BOTTOM)
    assert np.all(x[-1, others, 2] < surface[-1])  # not held: the bottom next to the tip lags behind it
    force, state = contact_forces(model, params, traj)
    force, state = np.asarray(force), np.asarray(state)
    off = np.setdiff1d(np.arange(model.n_vertices), TIP)
    assert np.all(state[-4:, TIP] > 0) and not np.any(state[:, off])
    assert np.all(force[-4:, TIP, 2] > 0) and np.all(force[:, off] == 0)


def test_rows_are_refused_before_compiling(no_compiling):
    """An object that is no row generator, and the unrolled adjoint (which cannot
    differentiate the contact iteration), are refused by ``build``."""
    with pytest.raises(SceneError, match=r"rows\[0\] is a Plane, not a contact row generator"):
        build(SoftBody(BAR, SOFT, fixed="xmin"), rows=[Plane()])
    with pytest.raises(SceneError, match=r"Options\(adjoint=Unrolled\(\)\).*the scene has contact"):
        _bar(Options(adjoint=Unrolled()))


@pytest.mark.parametrize("adjoint", [None, pytest.param(ImplicitForward(), marks=pytest.mark.slow)],
                         ids=["implicit", "forward"])
def test_gradients_through_rows(adjoint):
    """Reverse mode (``check_grad``) and forward mode (``jax.jvp``) through 6 steps of the
    lifted tip swinging sideways at 0.1 m/s (it slides on the plane in every step: the loss
    is smooth there), with respect to the generator's height and friction, E and the
    initial velocity, against central differences at eps 1e-4 (relative error <= 1e-6;
    measured 2e-9 to 7e-8)."""
    model, params = _bar(BENT if adjoint is None else dataclasses.replace(BENT, adjoint=adjoint))
    state = initial_state(model, params)
    v0 = jnp.zeros((model.n_vertices, 3)).at[:, 1].set(0.1)

    def loss(args):
        p, log_e, v = args
        p = p.replace(E=p.E * jnp.exp(log_e))
        x = rollout(model, p, State(x=state.x, v=v, rot=state.rot, t=state.t), n_steps=6).x[-1]
        return jnp.sum(x[:, 2]) + jnp.sum(x[:, 1] ** 2) * 1e2 + jnp.sum((x - x.mean(axis=0)) ** 2)

    args = (params, jnp.zeros_like(params.E), v0)
    zero = jax.tree.map(jnp.zeros_like, args)
    rows = lambda **on: zero[0].replace(rows=({k: jnp.asarray(on.get(k, 0.0)) for k in ("height", "mu")},))
    directions = {"height": (rows(height=1.0), zero[1], zero[2]), "mu": (rows(mu=1.0), zero[1], zero[2]),
                  "log_E": (zero[0], jnp.ones_like(args[1]), zero[2]), "v0": (zero[0], zero[1], jnp.ones_like(v0))}
    eps = 1e-4
    if adjoint is None:
        for name, r in check_grad(loss, args, directions=directions, eps=eps).items():
            assert r["rel_error"] <= 1e-6, (name, r)
        return
    fn = jax.jit(loss)
    for name, d in random_directions(args, directions).items():
        ad = float(jax.jit(lambda a, d: jax.jvp(loss, (a,), (d,))[1])(args, d))
        fd = central_difference(fn, args, d, eps)
        assert abs(ad - fd) <= 1e-6 * abs(fd), (name, ad, fd)


def test_rows_act_on_a_rigid_body_through_its_coordinates():
    """A rigid brick sliding onto the plane: the plane as rows on every vertex steps as the
    ``Plane`` obstacle does (to 1e-12), the rows reaching its surface vertices through the
    reduced coordinates' contact sweep as the obstacle's do."""
    from test_rigid import box

    from softbody.rigid import RigidBody

    brick = RigidBody(box((0.04, 0.03, 0.02)), density=800.0, name="brick", x0=(0.0, 0.0, 0.0105), v0=(0.3, 0.0, -0.2))
    trajs = []
    for scene in ({"obstacles": [Plane(mu_s=0.3, mu_k=0.3)]}, {"rows": [AbovePlane(np.arange(8), mu=0.3)]}):
        model, params = build(brick, options=Options(dt=0.005, tol=1e-12, max_iter=5000), **scene)
        traj = rollout(model, params, initial_state(model, params), n_steps=8)
        assert bool(np.all(traj.info.converged))
        trajs.append(np.asarray(traj.x))
    assert trajs[0][..., 2].min() > -1e-9 and trajs[0][-1, :, 0].mean() > 1e-3
    np.testing.assert_allclose(trajs[1], trajs[0], rtol=0, atol=1e-12)

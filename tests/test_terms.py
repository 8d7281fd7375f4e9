"""The energy-term seam: a term written here, in the test file alone (springs between two
bodies, with their blocks of the PD matrix), runs through ``build``, ``rollout``, local-global
and L-BFGS steps, the contact solver and every gradient mode."""

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

from softbody._interfaces import VertexTerm
from softbody._types import SceneError, State
from softbody.contact import Contact
from softbody.gradients import ImplicitForward, Unrolled, central_difference, check_grad, random_directions
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state, prepare
from softbody.contact.obstacles import Plane
from softbody.scene import SoftBody
from softbody.simulate import rollout
from softbody.solvers import LocalGlobal


@dataclass(frozen=True, eq=False)
class Spring(VertexTerm):
    """Springs of rest length ``rest`` between vertex pairs, each of stiffness ``k``:
    ``E = k/2 sum (|x_i - x_j| - rest)^2``, in PD form ``k/2 |x_i - x_j - p|^2`` with ``p``
    the difference projected onto the rest length, so each pair's block of the PD matrix
    is ``k [[1, -1], [-1, 1]]``. Its design parameter is ``log k``."""

    pairs: np.ndarray  # (m, 2) vertex indices
    rest: float
    stiffness: float

    mesh_indices: ClassVar = {"pairs": "vertices"}

    def init_params(self):
        return jnp.log(jnp.asarray(self.stiffness))

    def prepare(self, model, log_k, dminv, volume):
        return jnp.exp(log_k)

    def stencil(self):
        return self.pairs

    def blocks(self, k):
        return k * jnp.broadcast_to(jnp.asarray([[1.0, -1.0], [-1.0, 1.0]]), (len(self.pairs), 2, 2))

    def energy_and_gradient(self, x, k, activation):
        def energy(x):
            d = x[self.pairs[:, 0]] - x[self.pairs[:, 1]]
            return 0.5 * k * jnp.sum((jnp.sqrt(jnp.sum(d * d, axis=1)) - self.rest) ** 2)

        return jax.value_and_grad(energy)(x)


EDGE, GAP, K = 0.04, 0.02, 100.0
MATERIAL = Material(E=1e5, nu=0.3, density=1000.0)


def _cubes(z0=0.0):
    """Two 4 cm cubes (2 x 2 x 2 cells each), 2 cm apart along x."""
    return (grid_box((EDGE,) * 3, (2, 2, 2), origin=(0.0, 0.0, z0)),
            grid_box((EDGE,) * 3, (2, 2, 2), origin=(EDGE + GAP, 0.0, z0)))


def _pair(z0=0.0, material=MATERIAL, **options):
    """The two cubes, their facing faces joined vertex to vertex by 9 springs of rest length
    2 cm; the model, params and spring."""
    a, b = _cubes(z0)
    ends = []
    for mesh, face, offset in ((a, "xmax", 0), (b, "xmin", a.n_vertices)):
        idx = mesh.regions[face].vertices
        p = mesh.points[idx]
        ends.append(idx[np.lexsort((p[:, 2], p[:, 1]))] + offset)
    spring = Spring(np.stack(ends, axis=1), GAP, K)
    model, params = build([SoftBody(a, material, name="a"), SoftBody(b, material, name="b")], terms=[spring],
                          **options)
    return model, params, spring


def test_spring_blocks_join_the_pd_matrix():
    """The matrix with the springs minus the one without is ``k`` times the springs' graph
    Laplacian; with one end of every spring held, only the free end's diagonal changes."""
    model, _, spring = _pair()
    a, b = _cubes()

    def difference(fixed):
        bodies = [SoftBody(a, MATERIAL, fixed=fixed, name="a"), SoftBody(b, MATERIAL, name="b")]
        (with_springs, p), (plain, q) = build(bodies, terms=[spring]), build(bodies)
        return (with_springs.pattern.to_scipy(np.asarray(prepare(with_springs, p).data))
                - plain.pattern.to_scipy(np.asarray(prepare(plain, q).data))).toarray()

    i, j = spring.pairs.T
    m, n = len(i), model.n_vertices
    incidence = sp.coo_matrix((np.r_[np.ones(m), -np.ones(m)], (np.r_[np.arange(m), np.arange(m)], np.r_[i, j])),
                              (m, n))
    laplacian = K * (incidence.T @ incidence)
    np.testing.assert_allclose(difference(None), laplacian.toarray(), atol=1e-9 * K)
    expected = np.zeros((n, n))
    expected[i, i] = expected[j, j] = K  # held rows keep their diagonal only; no coupling
    np.testing.assert_allclose(difference("xmax"), expected, atol=1e-9 * K)


def test_springs_pass_momentum_and_local_global_agrees_with_lbfgs():
    """Without gravity, cube a moving at 0.5 m/s towards cube b: the springs' internal
    forces conserve the total momentum (to the steps' residual), hand most of it to b within
    0.2 s (~5 periods of the spring-mass pair), and local-global PD, which relies on the
    springs' blocks in its matrix, reaches the same trajectory as L-BFGS."""
    trajs = {}
    for name, solver in (("lbfgs", None), ("local-global", LocalGlobal())):
        model, params, _ = _pair(options=Options(dt=0.01, gravity=(0.0, 0.0, 0.0), tol=1e-10, max_iter=20000,
                                                 solver=solver))
        v0 = np.zeros((model.n_vertices, 3))
        v0[slice(*model.body("a").vertices), 0] = 0.5
        traj = rollout(model, params, initial_state(model, params, v=v0), n_steps=20)
        assert bool(np.all(traj.info.converged)), name
        trajs[name] = traj
    mass = np.asarray(prepare(model, params).mass)
    momentum = (mass[None] * np.asarray(trajs["lbfgs"].v)).sum(axis=1)  # (steps + 1, 3)
    np.testing.assert_allclose(momentum, np.broadcast_to(momentum[0], momentum.shape), atol=1e-9 * momentum[0, 0])
    b = slice(*model.body("b").vertices)
    p_b = (mass[b] * np.asarray(trajs["lbfgs"].v)[:, b]).sum(axis=1)[:, 0]
    assert p_b.max() > 0.5 * momentum[0, 0]
    assert np.abs(np.asarray(trajs["lbfgs"].x) - np.asarray(trajs["local-global"].x)).max() < 1e-7


def _directions(args):
    """Random directions in the spring's log stiffness, the log Young's moduli and the
    initial velocity, for ``args = (params, log E scale, v0)``."""
    zero = jax.tree.map(jnp.zeros_like, args)
    return {"log_k": (zero[0].replace(actuators=(1.0,)), zero[1], zero[2]),
            "log_E": (zero[0], jnp.ones_like(args[1]), zero[2]),
            "v0": (zero[0], zero[1], jnp.ones_like(args[2]))}


def _gradients_match(model, params, n_steps, eps):
    """Reverse mode (``check_grad``) or, with ``ImplicitForward``, forward mode
    (``jax.jvp``) against central differences at ``eps`` (relative error <= 1e-6), from
    the cubes moving apart at 0.6 m/s and sideways at 0.1 m/s."""
    state = initial_state(model, params)
    a = slice(*model.body("a").vertices)
    v0 = jnp.zeros((model.n_vertices, 3)).at[:, 0].set(0.3).at[:, 1].set(0.1).at[a, 0].set(-0.3)

    def loss(args):
        p, log_e, v = args
        p = p.replace(E=p.E * jnp.exp(log_e))
        x = rollout(model, p, State(x=state.x, v=v, rot=state.rot, t=state.t), n_steps=n_steps).x
        return jnp.sum(x[-1, :, 0] ** 2) + jnp.sum(x[-1, :, 2]) + jnp.sum((x[-1] - x[-1].mean(axis=0)) ** 2)

    args = (params, jnp.zeros_like(params.E), v0)
    directions = _directions(args)
    if isinstance(model.options.adjoint, ImplicitForward):
        fn = jax.jit(loss)
        for name, d in random_directions(args, directions).items():
            ad = float(jax.jit(lambda a, d: jax.jvp(loss, (a,), (d,))[1])(args, d))
            fd = central_difference(fn, args, d, eps)
            assert abs(ad - fd) <= 1e-6 * abs(fd), (name, ad, fd)
        return
    for name, r in check_grad(loss, args, directions=directions, eps=eps).items():
        assert r["rel_error"] <= 1e-6, (name, r)


SLOW = pytest.mark.slow


@pytest.mark.parametrize("adjoint", [None, pytest.param(ImplicitForward(), marks=SLOW),
                                     pytest.param(Unrolled(), marks=SLOW)], ids=["implicit", "forward", "unrolled"])
def test_spring_gradients_without_contact(adjoint):
    """Gradients through 5 steps of the spring-joined cubes under gravity (a's left face
    clamped) with respect to ``log k``, E and the initial velocity."""
    a, b = _cubes()
    _, _, spring = _pair()
    model, params = build([SoftBody(a, MATERIAL, fixed="xmin", name="a"), SoftBody(b, MATERIAL, name="b")],
                          terms=[spring], options=Options(dt=0.01, tol=1e-12, max_iter=2000, adjoint=adjoint))
    _gradients_match(model, params, 5, eps=1e-4)


@pytest.mark.parametrize("adjoint", [None, pytest.param(ImplicitForward(), marks=SLOW)], ids=["implicit", "forward"])
def test_spring_gradients_with_contact(adjoint):
    """Softer cubes (E 1e4 Pa) drop 0.5 mm onto a friction plane (mu 0.4) and slide: every
    step converges, no vertex ends below the plane by more than 1e-6 m, and the gradients
    through the contact solver's fixed point match central differences. At eps 1e-2
    (Richardson: truncation O(eps^4)); smaller steps meet the forward solves' noise (the
    splitting stops at residual 1e-12: measured log k relative errors 6e-8, 2e-8, 6e-6 at
    eps 1e-2, 1e-3, 1e-4), and at dt 0.01 s the splitting needs ~2000 iterations a step."""
    model, params, _ = _pair(z0=0.0005, material=Material(E=1e4, nu=0.3, density=1000.0),
                             obstacles=[Plane(mu_s=0.4, mu_k=0.4)],
                             options=Options(dt=0.005, tol=1e-12, max_iter=5000, adjoint=adjoint,
                                             contact=Contact(adjoint_tol=1e-13)))
    traj = rollout(model, params, initial_state(model, params), n_steps=5)
    assert bool(np.all(traj.info.converged))
    assert float(np.asarray(traj.x)[..., 2].min()) > -1e-6
    _gradients_match(model, params, 5, eps=1e-2)


def test_bad_stencils_are_refused_before_compiling(no_compiling):
    """A stencil of the wrong width, indices outside the scene, a tuple repeating a vertex
    and an object that is no term are refused by ``build``, naming the problem."""
    a, _ = _cubes()
    cases = {"2 <= k <= 4": Spring(np.zeros((3, 5), int), GAP, K),
             "must lie in": Spring(np.array([[0, 10_000]]), GAP, K),
             "repeats a vertex": Spring(np.array([[1, 1]]), GAP, K),
             "not an energy term": object()}
    for message, term in cases.items():
        with pytest.raises(SceneError, match=message):
            build(SoftBody(a, MATERIAL), terms=[term])

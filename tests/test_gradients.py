"""Gradients through rollouts against central finite differences (float64, real gmsh mesh)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.actuators.muscle import Muscle
from softbody.gradients import Implicit, ImplicitForward, Unrolled, central_difference, directional, random_directions
from softbody.material import Material
from softbody.meshing import Region, examples
from softbody.model import Options, State, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout

T = 4
KINDS = ("logE", "nu", "density", "alpha", "beta", "morph", "x0", "v0", "activation", "force")


def _mesh():
    mesh = examples.cantilever(length=0.1, width=0.02, height=0.02, size=0.01)
    centroid_z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    top = np.flatnonzero(centroid_z > np.median(centroid_z))
    return mesh.with_regions(**{"muscle:top": Region(np.unique(mesh.tets[top]), tets=top)})


def _problem(adjoint, mesh=None):
    mesh = _mesh() if mesh is None else mesh
    muscle = Muscle.from_regions(mesh, ["muscle:top"], stiffness=2e4)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000, alpha=0.5, beta=0.01), fixed="fixed",
                                   actuators=[muscle]),
                          options=Options(dt=0.01, tol=1e-12, atol=0.0, max_iter=300, adjoint=adjoint))
    state0 = initial_state(model, params)
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.standard_normal((mesh.n_vertices, 3)))
    theta = {
        "logE": jnp.log(params.E), "nu": params.nu, "density": params.density / 1000,
        "alpha": params.alpha, "beta": params.beta * 100, "morph": params.morph,
        "x0": state0.x, "v0": jnp.asarray(0.01 * rng.standard_normal((mesh.n_vertices, 3))),
        "activation": jnp.full((T, 1), 0.3), "force": jnp.asarray(1e-3 * rng.standard_normal((T, mesh.n_vertices, 3))),
    }

    def loss(th):
        p = params.replace(E=jnp.exp(th["logE"]), nu=th["nu"], density=th["density"] * 1000, alpha=th["alpha"],
                           beta=th["beta"] / 100, morph=th["morph"])
        s0 = State(x=th["x0"], v=th["v0"], rot=state0.rot, t=state0.t)
        traj = rollout(model, p, s0, controls=th["activation"], forces=th["force"], n_steps=T)
        return jnp.sum(traj.x[-1] * w) + 0.01 * jnp.sum(traj.v[-1] * w)

    return loss, theta


def _directions(theta, kinds=KINDS):
    """Masks for :func:`random_directions`: one direction per kind, moving only that kind."""
    return {k: {j: (1.0 if j == k else 0.0) for j in theta} for k in kinds}


@pytest.fixture(scope="module")
def implicit_problem():
    return _problem(Implicit())


@pytest.fixture(scope="module")
def implicit_gradient(implicit_problem):
    """The Implicit adjoint's reverse-mode gradient of the loss (all kinds)."""
    loss, theta = implicit_problem
    return jax.jit(jax.grad(loss))(theta)


@pytest.fixture(scope="module")
def unrolled_problem():
    """The Unrolled loss, jitted, and its point. It is the finite differences' reference for
    every mode: its forward runs 20 iterations past the tolerance, so its values are
    converged to round-off. The Implicit forward stops at ``tol``; where a parameter moves
    the loss only slightly (alpha, beta: ~1e-4 per unit), the jitter of where it stops,
    divided by the step, reached 5e-6 of the derivative in a fresh install (1.5e-7 here)."""
    loss, theta = _problem(Unrolled())
    return jax.jit(loss), theta


@pytest.fixture(scope="module")
def gradients(implicit_gradient, unrolled_problem):
    """Per mode, each kind's derivative along a random unit direction against the
    reference's central differences along it (the same differences for both modes), and
    the mode's gradient."""
    reference, theta = unrolled_problem
    grads = {"Implicit": implicit_gradient, "Unrolled": jax.jit(jax.grad(reference))(theta)}
    out = {mode: ({}, g) for mode, g in grads.items()}
    for kind, d in random_directions(theta, _directions(theta)).items():
        # eps = 3e-5: the det-targeting volume term is nonlinear enough that the
        # Richardson-extrapolated differences' O(eps^4) truncation reached 1.2e-6 on alpha at
        # eps = 1e-4 (1.5e-7 at 3e-5).
        fd = central_difference(reference, theta, d, 3e-5)
        for mode, g in grads.items():
            ad = directional(g, d)
            out[mode][0][kind] = {"ad": ad, "fd": fd, "rel_error": abs(ad - fd) / max(abs(fd), 1e-300)}
    return out


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["Implicit", "Unrolled"])
@pytest.mark.parametrize("kind", KINDS)
def test_gradient_matches_finite_differences(gradients, mode, kind):
    err = gradients[mode][0][kind]
    assert abs(err["fd"]) > 1e-8, "the loss does not depend on this parameter: the check would be vacuous"
    assert err["rel_error"] <= 1e-6, err


@pytest.mark.slow
def test_modes_agree(gradients):
    g_imp = gradients["Implicit"][1]
    g_unr = gradients["Unrolled"][1]
    for k in KINDS:
        a, b = np.asarray(g_imp[k]), np.asarray(g_unr[k])
        assert np.linalg.norm(a - b) <= 1e-6 * np.linalg.norm(b), k


FORWARD_KINDS = ("logE", "density", "v0", "activation", "force")


@pytest.fixture(scope="module")
def forward_jacobian(implicit_gradient):
    """``jax.jacfwd`` through :class:`ImplicitForward` of the loss along one random unit
    direction per parameter kind (a Jacobian with one column per kind), the reverse-mode
    (Implicit) derivatives along them, and the directions."""
    loss, theta = _problem(ImplicitForward())
    directions = list(random_directions(theta, _directions(theta, FORWARD_KINDS), seed=7).values())

    def along(c):
        return loss(jax.tree.map(lambda t, *ds: t + sum(ci * di for ci, di in zip(c, ds)), theta, *directions))

    jac = np.asarray(jax.jit(jax.jacfwd(along))(jnp.zeros(len(FORWARD_KINDS))))
    rev = np.array([directional(implicit_gradient, d) for d in directions])
    return jac, rev, directions


@pytest.mark.slow
@pytest.mark.parametrize("index", range(len(FORWARD_KINDS)), ids=FORWARD_KINDS)
def test_forward_implicit_jacobian_matches_finite_differences(forward_jacobian, unrolled_problem, index):
    """Each column against the central differences of the Unrolled forward (converged to
    round-off, see ``unrolled_problem``) along its direction."""
    jac, _, directions = forward_jacobian
    reference, theta = unrolled_problem
    fd = central_difference(reference, theta, directions[index], 3e-5)
    assert abs(fd) > 1e-8, "the loss does not depend on this parameter: the check would be vacuous"
    assert abs(jac[index] - fd) <= 1e-6 * abs(fd), (jac[index], fd)


def test_forward_implicit_agrees_with_reverse_implicit(forward_jacobian):
    jac, rev, _ = forward_jacobian
    np.testing.assert_allclose(jac, rev, rtol=1e-8, atol=0)


def _tiny(adjoint, **material):
    from softbody.meshing.grid import grid_box

    mesh = grid_box((0.06, 0.02, 0.02), (3, 1, 1))
    model, params = build(SoftBody(mesh, Material(**{"E": 1e5, "nu": 0.3, **material}), fixed="fixed"),
                          options=Options(dt=0.01, tol=1e-12, atol=0.0, adjoint=adjoint))
    return model, params, initial_state(model, params)


@pytest.mark.slow
def test_jacfwd_unrolled_matches_grad():
    model, params, s0 = _tiny(Unrolled())

    def tip(log_e):
        p = params.replace(E=jnp.exp(log_e))
        return rollout(model, p, s0, n_steps=3).x[-1, :, 2].sum()

    x = jnp.log(params.E)
    fwd = jax.jacfwd(tip)(x)
    rev = jax.grad(tip)(x)
    np.testing.assert_allclose(fwd, rev, rtol=1e-9)


@pytest.mark.slow
def test_vmap_of_grad_over_two_parameter_sets():
    model, params, s0 = _tiny(Implicit())

    def tip(log_e):
        p = params.replace(E=jnp.exp(log_e))
        return rollout(model, p, s0, n_steps=3).x[-1, :, 2].sum()

    batch = jnp.stack([jnp.log(params.E), jnp.log(params.E) + 0.5])
    batched = jax.vmap(jax.grad(tip))(batch)
    single = jnp.stack([jax.grad(tip)(batch[0]), jax.grad(tip)(batch[1])])
    np.testing.assert_allclose(batched, single, rtol=1e-9)
    assert not np.allclose(batched[0], batched[1]), "two parameter sets should give two gradients"


@pytest.mark.slow
@pytest.mark.parametrize("adjoint", [Implicit(), Unrolled()], ids=["implicit", "unrolled"])
def test_gradient_finite_at_rest(adjoint):
    """From rest with no load every tet stays at F = I: the gradient must be finite (SVD's is NaN)."""
    from softbody.meshing.grid import grid_box

    mesh = grid_box((0.06, 0.02, 0.02), (3, 1, 1))
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3), fixed="fixed"),
                          options=Options(dt=0.01, gravity=(0.0, 0.0, 0.0), tol=1e-12, adjoint=adjoint))
    s0 = initial_state(model, params)

    def loss(p):
        return jnp.sum(rollout(model, p, s0, n_steps=2).x[-1] ** 2)

    g = jax.grad(loss)(params)
    for leaf in jax.tree.leaves(g):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(jnp.abs(g.E).max()) < 1e-18  # nothing moves, so E has no influence (up to roundoff)


@pytest.mark.slow
@pytest.mark.parametrize("adjoint", [Implicit(), Unrolled()], ids=["implicit", "unrolled"])
def test_gradient_finite_through_inverted_tets(adjoint):
    """A step from a state with inverted tets (the tip face pushed through its cells)."""
    from softbody.elastic import deformation_gradient, rest_geometry
    from softbody.rotation import cold_start, det3

    model, params, s0 = _tiny(adjoint)
    mesh = model.mesh
    x0 = np.array(mesh.points)
    x0[mesh.region("tip").vertices, 0] -= 0.035  # the last cell is 0.02 long: its tets invert
    dminv, _ = rest_geometry(model, params.morph)
    f0 = deformation_gradient(model, dminv, jnp.asarray(x0))
    assert int((det3(f0) < 0).sum()) > 0, "the setup must hold inverted tets"
    state = State(x=jnp.asarray(x0), v=s0.v, rot=cold_start(f0), t=s0.t)

    def loss(p):
        return jnp.sum(rollout(model, p, state, n_steps=1).x[-1] ** 2)

    g = jax.grad(loss)(params)
    for leaf in jax.tree.leaves(g):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert float(jnp.abs(g.E).max()) > 0


@pytest.mark.parametrize("use_native", [True, False], ids=["native", "xla"])
def test_stress_derivative_product_is_the_hessian_vector_product(monkeypatch, use_native):
    """``stress_derivative_product`` against autodiff of ``1/2 sum_e D_e : K_e D_e``,
    ``D_e`` the deformation gradient of ``x`` and ``K_e`` random symmetric, on the gmsh
    mesh; under ``vmap`` too (the native call runs batch members one by one)."""
    from softbody import native
    from softbody.elastic import deformation_gradient, rest_geometry, stress_derivative_product

    if use_native:
        assert native.available(), native.unavailable_reason()
    else:
        monkeypatch.setattr(native, "available", lambda: False)
    mesh = _mesh()
    model, _ = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000), fixed="fixed"))
    dminv, _ = rest_geometry(model, jnp.zeros_like(jnp.asarray(mesh.points)))
    rng = np.random.default_rng(1)
    k = rng.standard_normal((9, 9, mesh.n_tets))
    k = jnp.asarray(k + k.transpose(1, 0, 2))  # [kl, ij, e]

    def energy(x):
        d = deformation_gradient(model, dminv, x).reshape(9, -1)
        return 0.5 * jnp.einsum("ae,abe,be->", d, k, d)

    x = jnp.asarray(rng.standard_normal((mesh.n_vertices, 3)))
    v = jnp.asarray(rng.standard_normal((2, mesh.n_vertices, 3)))
    expected = jnp.stack([jax.jvp(jax.grad(energy), (x,), (vi,))[1] for vi in v])
    product = jax.jit(jax.vmap(stress_derivative_product(model, dminv, k.reshape(9, 3, 3, -1))))
    text = jax.jit(stress_derivative_product(model, dminv, k.reshape(9, 3, 3, -1))).lower(v[0]).as_text()
    assert ("softbody_tet_hessian_product" in text) == use_native
    np.testing.assert_allclose(product(v), expected, rtol=0, atol=1e-12 * float(jnp.abs(expected).max()))


def test_tet_hessian_operator_names_bad_shapes_and_indices():
    """The native product refuses operands that do not match the mesh, and vertex indices
    outside ``v``, with the expected shapes in the message (the kernel does not check)."""
    from softbody import native

    assert native.available(), native.unavailable_reason()
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    k, dminv = jnp.zeros((45, 2)), jnp.zeros((9, 2))
    with pytest.raises(ValueError, match=r"expected k \(45, t\), dminv \(9, t\)"):
        native.tet_hessian_operator(k[:, :1], dminv, tets)
    apply = native.tet_hessian_operator(k, dminv, tets)
    with pytest.raises(ValueError, match=r"indices in \[0, 4\)"):
        apply(jnp.zeros((4, 3)))
    assert apply(jnp.ones((5, 3))).shape == (5, 3)


@pytest.mark.slow  # ~3 min of CPU, mostly compiling the skeleton step's forward and reverse derivatives
def test_forward_implicit_in_a_skeleton_chart_agrees_with_reverse():
    """A skeleton's steps are stationary only in its reduced coordinates (the bone carries
    joint forces): forward mode runs in the same chart as the adjoint. A bar with one
    hinged bone under a shoulder torque, 3 steps; the tip height's derivative along a
    direction in (torques, log E) from jvp through ImplicitForward against Implicit's
    gradient (3e-11 apart when written)."""
    from softbody.actuators.joints import JointTorque
    from softbody.meshing.grid import grid_box
    from softbody.skeleton import Link, Revolute, Skeleton

    mesh = grid_box((0.2, 0.04, 0.04), (5, 2, 2))
    p = mesh.points
    inside = np.all((p >= np.array([0.03, 0.0, 0.0]) - 1e-9) & (p <= np.array([0.13, 0.04, 0.04]) + 1e-9), axis=1)
    mesh = mesh.with_regions(**{"bone:upper": Region(np.flatnonzero(inside),
                                                     np.flatnonzero(inside[mesh.tets].all(axis=1)))})
    skeleton = Skeleton([Link("upper", "bone:upper", None, Revolute((0.0, 1.0, 0.0), (0.02, 0.02, 0.02)))])
    tip = jnp.asarray(np.flatnonzero(mesh.points[:, 0] > 0.2 - 1e-9))

    def make(adjoint):
        model, params = build(SoftBody(mesh, Material(E=1e4, nu=0.3, density=1000.0), fixed="xmin"),
                              skeleton=skeleton, actuators=[JointTorque(["upper"])],
                              options=Options(dt=0.01, tol=1e-12, max_iter=300, adjoint=adjoint))
        s0 = initial_state(model, params)

        def loss(th):
            q = params.replace(E=jnp.exp(th["log_E"]))
            return jnp.mean(rollout(model, q, s0, controls=th["torque"]).x[-1][tip, 2]) * 1e3  # mm

        return loss, {"torque": jnp.full((3, 1), 2e-3), "log_E": jnp.log(params.E)}

    forward, theta = make(ImplicitForward())
    reverse, _ = make(Implicit())
    d = {"torque": jnp.asarray([[1.0], [-0.5], [0.3]]), "log_E": jnp.ones_like(theta["log_E"])}
    jvp = float(jax.jit(lambda th: jax.jvp(forward, (th,), (d,))[1])(theta))
    g = jax.jit(jax.grad(reverse))(theta)
    rev = sum(float(jnp.sum(g[k] * d[k])) for k in theta)
    assert abs(rev) > 1e-3, "the tip must move with the torques and the modulus"
    assert abs(jvp - rev) <= 1e-8 * abs(rev), (jvp, rev)

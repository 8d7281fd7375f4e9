"""The nodally averaged volume element (:class:`softbody.nodal.NodalVolume`): its energy
against closed forms, its place in the prepared scene, bad input, gradients with respect to
E and nu against central differences (float64), volume conservation through a large
deformation at nu = 0.499, and the silicone cantilever against scikit-fem (slow)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import rotation
from softbody.actuators import PneumaticCells
from softbody.elastic import corotated, deformation_gradient
from softbody.gradients import Implicit, central_difference
from softbody.material import Material
from softbody.meshing import examples
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.nodal import NodalVolume
from softbody.scene import SoftBody
from softbody.simulate import rollout

MATERIAL = Material(E=1e5, nu=0.49, density=1070.0)


@pytest.fixture(scope="module")
def cube():
    """A gmsh cube (5 cm) with the element on every tet: mesh, model, prepared data."""
    mesh = examples.cube(size=0.02)
    model, params = build(SoftBody(mesh, MATERIAL, actuators=[NodalVolume.on(mesh)]))
    return mesh, model, prepare(model, params, static=True)


def test_energy_of_a_uniform_dilation_and_of_a_rotation(cube):
    """``x = s X``: every patch has ``J_v = s^3``, so the energy is exactly
    ``lambda / 2 V (s^3 - 1)^2`` (``V`` the body's volume, the sum of the patch volumes); a
    rigid motion keeps every patch volume, energy 0 (round-off: ~1e-16 of the dilation's)."""
    mesh, model, prep = cube
    term, tp = model.terms[0], prep.terms[0]
    x0 = jnp.asarray(mesh.points)
    s = 1.01
    expected = 0.5 * MATERIAL.lam * float(jnp.sum(prep.volume)) * (s**3 - 1) ** 2
    assert float(term.energy(s * x0, tp)) == pytest.approx(expected, rel=1e-12)
    axis = np.array([0.2, -0.4, 0.4]) / np.linalg.norm([0.2, -0.4, 0.4])
    k = np.cross(np.eye(3), axis)  # the cross-product matrix of the axis
    q = np.eye(3) + np.sin(1.1) * k + (1 - np.cos(1.1)) * k @ k  # Rodrigues: 1.1 rad about the axis
    moved = x0 @ jnp.asarray(q).T + jnp.asarray([0.3, -0.1, 0.2])
    energy, grad = term.energy_and_gradient(moved, tp, None)
    assert abs(float(energy)) <= 1e-14 * expected
    assert float(jnp.abs(grad).max()) <= 1e-10 * MATERIAL.lam * float(jnp.max(prep.volume)) ** (2 / 3)


def test_small_uniform_strain_is_linear_elasticity(cube):
    """The tets' corotated term (their volume weight dropped) plus the patch volumes give
    linear elasticity's ``V (mu |eps|^2 + lambda / 2 tr(eps)^2)`` for ``x = (I + eps) X``,
    up to the next order in the strain: a relative difference O(|eps|) = O(1e-4)."""
    mesh, model, prep = cube
    rng = np.random.default_rng(1)
    a = rng.standard_normal((3, 3))
    eps = 1e-4 * (a + a.T) / np.linalg.norm(a + a.T)
    x = jnp.asarray(mesh.points @ (np.eye(3) + eps).T)
    f = deformation_gradient(model, prep.dminv, x)
    r, _ = rotation.rotation(f, rotation.cold_start(f), 20)
    assert float(jnp.abs(prep.w_v).max()) == 0.0  # the covered tets lost their own volume term
    tets = float(jnp.sum(corotated(f, r, prep.volume, prep.w_s, prep.w_v)[0]))
    total = tets + float(model.terms[0].energy(x, prep.terms[0]))
    volume = float(jnp.sum(prep.volume))
    linear = volume * (MATERIAL.mu * np.sum(eps * eps) + 0.5 * MATERIAL.lam * np.trace(eps) ** 2)
    assert total == pytest.approx(linear, rel=1e-3)


def test_prepare_moves_the_volume_weight_of_covered_tets_only():
    """On half the tets: their volume weight is 0, the others keep ``3 lambda``; the PD
    matrix is the plain scene's (the term's blocks are the volume blocks its tets gave up)."""
    mesh = examples.cube(size=0.02)
    half = np.arange(len(mesh.tets) // 2)
    model, params = build(SoftBody(mesh, MATERIAL, actuators=[NodalVolume.on(mesh, half)]))
    plain_model, plain_params = build(SoftBody(mesh, MATERIAL))
    prep, plain = prepare(model, params), prepare(plain_model, plain_params)
    w_v = 3 * MATERIAL.lam
    assert np.all(np.asarray(prep.w_v)[half] == 0.0)
    np.testing.assert_allclose(np.asarray(prep.w_v)[len(half):], w_v, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(prep.data), np.asarray(plain.data), rtol=1e-12,
                               atol=1e-12 * float(jnp.abs(plain.data).max()))


@pytest.mark.parametrize("tets, match", [
    ("nowhere", "no region 'nowhere'"),
    (np.array([0, 0]), "distinct"),
    (np.array([-1]), "distinct"),
    (np.zeros((2, 2), int), r"\(m,\) tet indices"),
    (np.array([], int), r"\(m,\) tet indices"),
])
def test_bad_selections_are_refused(tets, match):
    mesh = examples.cube(size=0.025)
    with pytest.raises(SceneError, match=match):
        NodalVolume.on(mesh, tets)


def test_a_mesh_that_is_not_a_tet_mesh_is_refused():
    with pytest.raises(SceneError, match="needs the body's TetMesh"):
        NodalVolume.on(np.zeros((4, 3)))


@pytest.mark.slow
def test_gradients_with_respect_to_E_and_nu_match_central_differences():
    """nu = 0.49, a clamped beam swinging down for 3 steps: the implicit adjoint's
    derivatives of a random linear function of the final positions and velocities with
    respect to log E and nu against Richardson-extrapolated central differences (float64,
    steps converged to a relative residual of 1e-13), within 1e-6."""
    jax.config.update("jax_enable_x64", True)
    mesh = examples.cantilever(length=0.1, width=0.02, height=0.02, size=0.01)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.49, density=1070.0), fixed="fixed",
                                   actuators=[NodalVolume.on(mesh)]),
                          options=Options(dt=0.01, tol=1e-13, atol=0.0, max_iter=5000, adjoint=Implicit()))
    state0 = initial_state(model, params)
    w = jnp.asarray(np.random.default_rng(0).standard_normal((mesh.n_vertices, 3)))

    @jax.jit
    def loss(theta):
        p = params.replace(E=jnp.exp(theta[0])[None], nu=theta[1][None])
        traj = rollout(model, p, state0, n_steps=3)
        return jnp.sum(traj.x[-1] * w) + 0.01 * jnp.sum(traj.v[-1] * w)

    theta = jnp.asarray([np.log(1e5), 0.49])
    grad = jax.jit(jax.grad(loss))(theta)
    for k, name in enumerate(("log E", "nu")):
        d = jnp.zeros(2).at[k].set(1.0)
        fd = central_difference(loss, theta, d, 1e-4 if k == 0 else 1e-5)
        print(f"{name}: adjoint {float(grad[k]):.10e}, central differences {fd:.10e}, "
              f"relative error {abs(float(grad[k]) - fd) / abs(fd):.2e}")
        assert float(grad[k]) == pytest.approx(fd, rel=1e-6)


@pytest.mark.slow
def test_volume_is_kept_through_a_large_swing():
    """nu = 0.499, E = 100 kPa: a 10 cm clamped beam released from straight swings down
    under gravity (its static sag would be ~40 % of its length) for 0.2 s. Every step
    converges and the body's volume stays within 0.5 % of its rest volume (the patch
    volumes are held by lambda = 500 mu: a stress of order mu changes them by ~0.2 %)."""
    mesh = examples.cantilever(length=0.1, width=0.02, height=0.02, size=0.01)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.499, density=1070.0), fixed="fixed",
                                   actuators=[NodalVolume.on(mesh)]),
                          options=Options(dt=0.01, tol=1e-6, max_iter=5000))
    traj = rollout(model, params, initial_state(model, params), n_steps=20, throw=False)
    prep = prepare(model, params)
    x = np.asarray(traj.x)
    edges = x[:, mesh.tets[:, 1:]] - x[:, mesh.tets[:, :1]]  # (T, t, 3, 3)
    volume = np.linalg.det(edges).sum(axis=1) / 6.0
    rest = float(jnp.sum(prep.volume))
    drift = np.abs(volume / rest - 1)
    tip = mesh.regions["tip"].vertices
    sag = -(x[:, tip, 2].mean(axis=1) - mesh.points[tip, 2].mean())
    iterations = np.asarray(traj.info.iterations)
    print(f"tip sag max {sag.max() * 1e3:.1f} mm; volume drift max {drift.max():.2e}; iterations per step "
          f"median {np.median(iterations):.0f}, max {iterations.max()}")
    assert bool(np.all(np.asarray(traj.info.converged)))
    assert sag.max() >= 0.02  # a large deformation: the tip drops by more than a fifth of the length
    assert drift.max() <= 5e-3


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="measured: the nodal element's deflections on the 3614-vertex beam are up to 4.1, "
                                       "5.8 and 7.5 % below the reference at nu = 0.45, 0.49, 0.499 (3.0 % at nu = 0.3: "
                                       "the linear tets' bending stiffness); the goal is 3 %")
@pytest.mark.parametrize("nu", [0.45, 0.49, 0.499])
def test_silicone_cantilever_within_3_percent_of_the_reference(nu):
    """The issue's goal: the 3 x 3 x 10 cm silicone beam of ``softbody bench locking``
    (3614 vertices), its weight and its tip load each, within 3 % of scikit-fem's
    small-deflection P2 (nu = 0.45) or Taylor-Hood (0.49, 0.499) tip deflection (30 cells
    along the beam: within 0.4 % of the 20-cell one). The corotated model's geometric
    nonlinearity moves the sag by ~0.4 %.

    The static solves stop at a relative residual of 1e-6 (the benchmark's 1e-9 takes ~1.5 x
    the iterations): measured, every deflection here is then within 6e-8 of its value at
    1e-9 (relative, the larger of the two loads: nu = 0.45: 4.7e-8, 0.49: 6.0e-8, 0.499:
    2.3e-8), two millionths of the 3 % the check allows."""
    from softbody.bench import locking

    reference = locking.reference_deflections(nu, 30)
    mesh, force, deflection = locking.beam(0.003)
    for case in locking._solve(mesh, force, deflection, "nodal", (nu,), tol=1e-6):
        error = abs(case["deflection_m"] / reference[case["load"]] - 1)
        print(f"nu = {nu}, {case['load']}: {case['deflection_m'] * 1e3:.4f} mm against "
              f"{reference[case['load']] * 1e3:.4f} mm, error {error:.3f}")
        assert case["converged"]
        assert error <= 0.03


def test_two_elements_on_the_same_tets_are_refused():
    mesh = examples.cube(size=0.025)
    with pytest.raises(SceneError, match="cover the same tets"):
        build(SoftBody(mesh, MATERIAL, actuators=[NodalVolume.on(mesh), NodalVolume.on(mesh, np.array([0, 1]))]))


def test_volume_targets_on_covered_tets_are_refused():
    """Pneumatic cells act on the per-tet volume term, which the element's tets lack: refused
    before compiling where they overlap, accepted on the tets the element leaves out."""
    mesh = examples.cube(size=0.025)
    cells = PneumaticCells(np.arange(4), np.zeros(4), ("air",))
    with pytest.raises(SceneError, match="volume targets on tets that a volume element"):
        build(SoftBody(mesh, MATERIAL, actuators=[NodalVolume.on(mesh), cells]))
    build(SoftBody(mesh, MATERIAL, actuators=[NodalVolume.on(mesh, np.arange(4, mesh.n_tets)), cells]))


def test_the_element_follows_its_body_into_a_scene():
    """On the second of two bodies: its tets (after the first body's) lose their volume
    weight, the first body's keep it, and the term's corners are the second body's vertices."""
    mesh = examples.cube(size=0.025)
    term = NodalVolume.on(mesh)
    model, params = build([SoftBody(mesh, MATERIAL, name="a"), SoftBody(mesh, MATERIAL, name="b", actuators=[term])])
    t, n = len(mesh.tets), mesh.n_vertices
    placed = model.terms[0]
    np.testing.assert_array_equal(placed.tets, term.tets + t)
    np.testing.assert_array_equal(placed.corners, term.corners + n)
    w_v = np.asarray(prepare(model, params).w_v)
    assert np.all(w_v[t:] == 0.0) and np.all(w_v[:t] > 0.0)

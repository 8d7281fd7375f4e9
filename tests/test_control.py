"""Tests of softbody.control: losses, the optimisation loop and its checkpoints, trajectory
optimisation, CMA-ES, system identification, policies and co-design.

Scenes are tiny (a 3-cell clamped beam) so that each compiled objective costs seconds;
tests that simulate share one scene and, where they can, one compiled objective.
"""

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from softbody.actuators import Muscle
from softbody.gradients import check_grad
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state
from softbody.scene import SoftBody
from softbody.contact.obstacles import Plane
from softbody.simulate import SimulationError, Trajectory, rollout
from softbody import control as sc
from softbody.control import ControlError

LENGTH = 0.1


@pytest.fixture(scope="module")
def scene():
    """A clamped 3-cell beam along +x with a top and a bottom muscle channel (fibres along x)."""
    mesh = grid_box((LENGTH, 0.02, 0.02), (3, 1, 1))
    centre_z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    muscle = Muscle(np.arange(mesh.n_tets), np.tile([1.0, 0.0, 0.0], (mesh.n_tets, 1)),
                    np.where(centre_z > 0.01, 0, 1), ("top", "bottom"), stiffness=1e5)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, alpha=2.0), fixed="fixed",
                                   actuators=[muscle]),
                          options=Options(dt=0.01, tol=1e-9, max_iter=400))
    return model, params


def _fake_trajectory(model, n_steps=4, seed=0):
    rng = np.random.default_rng(seed)
    x = jnp.asarray(model.mesh.points)[None] + 0.01 * rng.standard_normal((n_steps + 1, model.n_vertices, 3))
    return Trajectory(x=x, v=jnp.zeros_like(x), info=None)


# ------------------------------------------------------------------------------------- losses


def _all_losses(model, n_steps):
    ref = np.asarray(_fake_trajectory(model, n_steps, seed=1).x)[:, model.mesh.regions["tip"].vertices]
    return {
        "target_final": sc.TargetPosition(model, "tip", (0.09, 0.01, 0.0)),
        "target_all_xz": sc.TargetPosition(model, "tip", (0.09, 0.01, 0.0), over="all", axes=(0, 2)),
        "target_last2": sc.TargetPosition(model, None, (0.05, 0.01, 0.01), over=2),
        "forward": sc.ForwardDistance(model, axis=(1.0, 0.5, 0.0)),
        "tracking": sc.Tracking(model, ref, "tip"),
        "effort": sc.Effort(scale=[1.0, 2.0]),
        "smoothness": sc.Smoothness(),
        "sum": sc.TargetPosition(model, "tip", (0.09, 0.01, 0.0)) + 0.1 * sc.Effort() + sc.Smoothness() * 2.0,
    }


def test_loss_gradients_match_central_differences(scene):
    model, _ = scene
    traj = _fake_trajectory(model)
    controls = jnp.asarray(np.random.default_rng(2).uniform(size=(4, 2)))
    for name, loss in _all_losses(model, 4).items():
        def f(args, loss=loss):
            x, a = args
            return loss(Trajectory(x=x, v=traj.v, info=None), a)

        # Smooth (at most quadratic) functions in float64: central differences with
        # eps = 1e-6 are exact up to round-off, ~1e-16 / 1e-6 relative.
        out = check_grad(f, (traj.x, controls), eps=1e-6, verbose=False,
                         directions={"positions": (1.0, 0.0), "controls": (0.0, 1.0)})
        for part, r in out.items():
            assert abs(r["ad"] - r["fd"]) <= 1e-7 * max(abs(r["fd"]), 1e-12), (name, part, r)
        assert max(abs(r["ad"]) for r in out.values()) > 0, name


def test_loss_values(scene):
    model, _ = scene
    n = model.n_vertices
    shift = jnp.asarray([0.03, -0.01, 0.02])
    x0 = jnp.asarray(model.mesh.points)
    x = jnp.stack([x0, x0 + 0.5 * shift, x0 + shift])
    traj = Trajectory(x=x, v=jnp.zeros_like(x), info=None)
    a = jnp.asarray([[0.1, 0.2], [0.4, 0.2]])
    forward = sc.ForwardDistance(model, axis=(2.0, 0.0, 0.0))
    assert float(forward.travelled(traj)) == pytest.approx(0.03, rel=1e-12)
    assert float(forward(traj, a)) == pytest.approx(-0.03, rel=1e-12)
    # A rigid shift moves every centroid by the shift, whatever the weights.
    tip = model.mesh.regions["tip"].vertices
    w = sc.centroid_weights(model, tip)
    target = np.asarray(w @ np.asarray(x0)[tip]) + np.asarray(shift)
    assert float(sc.TargetPosition(model, "tip", target)(traj, a)) == pytest.approx(0.0, abs=1e-30)
    over_all = sc.TargetPosition(model, "tip", target, over="all")(traj, a)
    assert float(over_all) == pytest.approx(0.5 * 0.25 * float(shift @ shift), rel=1e-12)
    assert float(sc.Tracking(model, np.asarray(x), None)(traj, a)) == pytest.approx(0.0, abs=1e-30)
    assert float(sc.Effort()(traj, a)) == pytest.approx((0.01 + 0.04 + 0.16 + 0.04) / 2, rel=1e-12)
    assert float(sc.Smoothness()(traj, a)) == pytest.approx(0.09, rel=1e-12)
    assert float(sc.Smoothness()(traj, a[:1])) == 0.0
    assert n == x.shape[1]


def test_bad_losses_fail_clearly(scene):
    model, _ = scene
    with pytest.raises(ControlError, match="unknown region 'tipp'.*'tip'"):
        sc.TargetPosition(model, "tipp", (0, 0, 0))
    with pytest.raises(ControlError, match="unknown region"):
        sc.ForwardDistance(model, region="head")
    with pytest.raises(ControlError, match="3 finite numbers"):
        sc.TargetPosition(model, "tip", (0, 0))
    with pytest.raises(ControlError, match="over must be"):
        sc.TargetPosition(model, "tip", (0, 0, 0), over="last")
    with pytest.raises(ControlError, match="out of range|must lie in"):
        sc.Tracking(model, np.zeros((3, 1, 3)), [10**6])
    with pytest.raises(ControlError, match=r"reference must have shape \(T \+ 1, 4, 3\)"):
        sc.Tracking(model, np.zeros((3, 5, 3)), "tip")
    with pytest.raises(ControlError, match="positive"):
        sc.Effort(scale=0.0)
    traj = _fake_trajectory(model, 4)
    with pytest.raises(ControlError, match="the trajectory has 5 frames but the reference 3"):
        sc.Tracking(model, np.zeros((3, 4, 3)), "tip")(traj, None)
    with pytest.raises(ControlError, match=r"needs the \(T, C\) controls"):
        sc.Effort()(traj, jnp.zeros(3))


# ---------------------------------------------------------------------------- control grids


def test_control_grid_interpolation_and_bounds():
    grid = sc.ControlGrid(9, 2, 3, bounding="clip")
    knots = jnp.asarray([[0.0, 1.0], [1.0, 0.0], [0.5, 0.5]])
    a = np.asarray(grid.controls(knots))
    assert a.shape == (9, 2)
    np.testing.assert_allclose(a[[0, 4, 8]], knots, atol=1e-15)  # knots at steps 0, 4, 8
    np.testing.assert_allclose(a[2], [0.5, 0.5], atol=1e-15)  # halfway between knots 0 and 1
    np.testing.assert_allclose(grid.matrix.sum(axis=1), 1.0, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(grid.project(jnp.asarray([[2.0, -1.0]] * 3))), [[1.0, 0.0]] * 3)
    assert np.array_equal(sc.ControlGrid(5, 1).matrix, np.eye(5))
    periodic = sc.ControlGrid(8, 1, 2, period=4)
    np.testing.assert_allclose(periodic.matrix[:, 0], [1, 0.5, 0, 0.5, 1, 0.5, 0, 0.5], atol=1e-15)
    sig = sc.ControlGrid(6, 2, 2, lower=[0.0, -1e4], upper=[1.0, 3e4])
    values = np.asarray([[0.2, 0.0], [0.7, 2e4]])
    np.testing.assert_allclose(np.asarray(sig.knots(sig.init(values))), values, rtol=1e-12, atol=1e-9)
    assert np.all(np.asarray(sig.knots(jnp.full((2, 2), 50.0))) <= [1.0, 3e4])


def test_bad_controls_fail_clearly(scene):
    model, params = scene
    with pytest.raises(ControlError, match=r"n_knots must lie in \[1, 5\]"):
        sc.ControlGrid(5, 2, 6)
    with pytest.raises(ControlError, match="lower < upper"):
        sc.ControlGrid(5, 2, lower=1.0, upper=0.0)
    with pytest.raises(ControlError, match="finite bounds"):
        sc.ControlGrid(5, 2, upper=np.inf)
    with pytest.raises(ControlError, match="bounding"):
        sc.ControlGrid(5, 2, bounding="tanh")
    grid = sc.ControlGrid(5, 2, 3)
    with pytest.raises(ControlError, match=r"shape \(3, 2\).*got \(5, 2\)"):
        grid.controls(jnp.zeros((5, 2)))
    with pytest.raises(ControlError, match="within the bounds"):
        grid.init(1.5)
    with pytest.raises(ControlError, match=r"a number, \(2,\) or \(3, 2\)"):
        grid.init(np.zeros(4))
    loss = sc.TargetPosition(model, "tip", (0.1, 0.01, 0.0))
    with pytest.raises(ControlError, match=r"grid has 3 channels but the model has 2 \(\['top', 'bottom'\]\)"):
        sc.ControlProblem(model, params, loss, sc.ControlGrid(5, 3))
    with pytest.raises(ControlError, match="forces must have shape"):
        sc.ControlProblem(model, params, loss, grid, forces=np.zeros((4, model.n_vertices, 3)))
    with pytest.raises(SceneError, match="controls must have shape"):
        rollout(model, params, initial_state(model, params), np.zeros((5, 3)))


# ----------------------------------------------------------------- optimisation and resume


def test_minimize_resume_is_bitwise_identical(tmp_path):
    """On an analytic objective: a run split by a checkpoint equals an uninterrupted one."""
    def rosenbrock(t):  # a curved valley: Adam's state matters to the path
        return (1 - t["a"]) ** 2 + 10 * (t["b"] - t["a"] ** 2) ** 2

    theta0 = {"a": jnp.asarray(-1.0), "b": jnp.asarray(1.5)}
    opt = optax.adam(0.1)
    full = sc.minimize(rosenbrock, theta0, optimizer=opt, n_iter=40, progress=False)
    path = tmp_path / "ck.npz"
    first = sc.minimize(rosenbrock, theta0, optimizer=opt, n_iter=15, checkpoint=path, checkpoint_every=4,
                        progress=False)
    assert first.iterations == 15 and path.exists()
    resumed = sc.minimize(rosenbrock, theta0, optimizer=opt, n_iter=40, checkpoint=path, progress=False)
    np.testing.assert_array_equal(resumed.loss, full.loss)
    np.testing.assert_array_equal(resumed.grad_norm, full.grad_norm)
    assert resumed.best_iteration == full.best_iteration
    for k in ("a", "b"):
        assert float(resumed.best_theta[k]) == float(full.best_theta[k])
        assert float(resumed.last_theta[k]) == float(full.last_theta[k])
    assert full.loss[-1] < 0.5 * full.loss[0], full.loss
    with pytest.raises(ControlError, match="exists; pass resume=True"):
        sc.minimize(rosenbrock, theta0, optimizer=opt, n_iter=40, checkpoint=path, resume=False, progress=False)
    with pytest.raises(ControlError, match="another problem"):
        sc.minimize(rosenbrock, theta0, optimizer=opt, n_iter=40, checkpoint=path, fingerprint={"x": 1},
                    progress=False)
    with pytest.raises(ControlError, match="holds 9 arrays but this problem's state has 4"):
        sc.minimize(rosenbrock, theta0, optimizer=optax.sgd(0.1), n_iter=40, checkpoint=path, progress=False)
    (tmp_path / "junk.npz").write_text("not a checkpoint")
    with pytest.raises(ControlError, match="not a readable optimisation checkpoint"):
        sc.minimize(rosenbrock, theta0, n_iter=2, checkpoint=tmp_path / "junk.npz", progress=False)
    with pytest.raises(ControlError, match="not finite"):
        sc.minimize(lambda t: jnp.log(t - 2.0), jnp.asarray(1.0), n_iter=2, progress=False)


@pytest.mark.slow
def test_trajopt_reduces_loss_and_resumes_identically(scene, tmp_path):
    model, params = scene
    # Reach a point above the beam's resting tip: the top muscle must contract.
    loss = sc.TargetPosition(model, "tip", (0.095, 0.01, 0.02), over=3) + 1e-4 * sc.Effort()
    problem = sc.ControlProblem(model, params, loss, sc.ControlGrid(8, 2, 3))
    opt = optax.adam(0.2)
    full = sc.optimize_controls(problem, 0.1, optimizer=opt, n_iter=8, progress=False)
    assert full.loss[-1] < 0.5 * full.loss[0], full.loss
    assert full.best_loss == full.loss.min()
    assert full.controls.shape == (8, 2) and np.all((full.controls > 0) & (full.controls < 1))
    assert full.knots[:, 0].mean() > full.knots[:, 1].mean()  # top contracts more than bottom
    np.testing.assert_allclose(float(problem.objective(jnp.asarray(full.theta))), full.best_loss, rtol=1e-12)

    path = tmp_path / "trajopt.npz"
    sc.optimize_controls(problem, 0.1, optimizer=opt, n_iter=5, checkpoint=path, progress=False)
    resumed = sc.optimize_controls(problem, 0.1, optimizer=opt, n_iter=8, checkpoint=path, progress=False)
    np.testing.assert_array_equal(resumed.loss, full.loss)
    np.testing.assert_array_equal(resumed.theta, full.theta)
    assert json.loads(str(np.load(path)["meta"]))["iteration"] == 8

    # CMA-ES on the same variables, through the same compiled objective's source.
    res = sc.cmaes(problem.objective, problem.init(0.1), sigma0=1.0, budget=10, popsize=5, progress=False)
    assert res.n_simulations == 10 and list(res.simulations) == [5, 10]
    assert res.best_loss <= float(problem.objective(problem.init(0.1)))
    assert res.best_loss == pytest.approx(float(problem.objective(res.best_theta)), rel=1e-12)


def test_cmaes_on_a_quadratic_counts_simulations():
    center = jnp.asarray([0.3, -0.2, 0.5])
    res = sc.cmaes(lambda t: jnp.sum((t["x"] - center) ** 2), {"x": jnp.zeros(3)}, sigma0=0.5, budget=400,
                   seed=3, target=1e-8, progress=False)
    assert res.best_loss <= 1e-8 and res.n_simulations <= 400
    np.testing.assert_allclose(np.asarray(res.best_theta["x"]), center, atol=1e-3)
    assert np.all(np.diff(res.best_loss_history) <= 0)
    capped = sc.cmaes(lambda t: jnp.sum(t ** 2), jnp.ones(2), sigma0=0.3, budget=7, popsize=5, progress=False)
    assert capped.n_simulations == 7
    with pytest.raises(ControlError, match="budget"):
        sc.cmaes(lambda t: jnp.sum(t ** 2), jnp.ones(2), sigma0=0.3, budget=0)


def test_cmaes_ranks_a_simulation_stopped_at_the_iteration_cap_last_instead_of_stopping():
    """A candidate whose rollout stops at the iteration cap is a failed simulation (as on sweep
    workers), not the end of the search: here every one of them is."""
    model, params = build(SoftBody(grid_box((0.1, 0.02, 0.02), (3, 1, 1)), Material(E=1e5, nu=0.3),
                                   fixed="fixed"), options=Options(dt=0.01, tol=1e-12, max_iter=1))
    state = initial_state(model, params)

    def loss(log_e):
        traj = rollout(model, params.replace(E=params.E * jnp.exp(log_e)), state, n_steps=2)
        return jnp.sum(traj.x[-1, :, 2])

    res = sc.cmaes(loss, jnp.zeros(1), sigma0=0.1, budget=4, popsize=4, progress=False)
    assert res.failed == 4 and res.best_loss == math.inf


# ------------------------------------------------------------------------ system identification


def test_sysid_residuals_without_throw_are_nan_for_a_failed_simulation(scene):
    """throw=False (the LM fit's and CMA-ES's programs, kept by the compilation cache): a
    simulation that stops at its iteration cap gives NaN misfits; throw=True raises."""
    model, params = scene
    obs = sc.synthesize(model, params, "tip", 2)
    problem = sc.SysIdProblem(model, params, obs)
    capped = dataclasses.replace(model, options=dataclasses.replace(model.options, tol=1e-14, max_iter=1))
    z = problem.pack(params)
    assert np.all(np.isfinite(np.asarray(problem.residuals(z, throw=False))))
    assert np.all(np.isnan(np.asarray(problem.residuals(z, capped, throw=False))))
    assert np.isnan(float(problem.cost(z, capped, throw=False)))
    with pytest.raises(SimulationError, match="iteration cap"):
        problem.residuals(z, capped)


@pytest.mark.slow
def test_sysid_recovers_young_modulus(scene):
    model, params = scene
    obs = sc.synthesize(model, params, "tip", 15)  # the beam released under gravity, noise-free
    res = sc.identify(model, params, obs, ("E",), init={"E": 2.0e5}, n_iter=12, progress=False)
    # Noise-free data from the same discretisation: the misfit vanishes at the true E, up to
    # the two step solvers' tolerances (relative 1e-9 of the step's force scale).
    assert abs(res.values["E"][0] / 1e5 - 1.0) < 1e-4, res.values
    assert res.iterations <= 12 and res.cost[-1] < 1e-6 * res.cost[0]
    assert np.all(np.diff(res.cost) <= 0)
    with pytest.raises(ControlError, match="estimate must list distinct names"):
        sc.identify(model, params, obs, ("youngs",), progress=False)
    with pytest.raises(ControlError, match="no obstacles"):
        sc.identify(model, params, obs, ("friction",), progress=False)
    with pytest.raises(ControlError, match="outside its domain"):
        sc.identify(model, params, obs, ("nu",), init={"nu": 0.6}, progress=False)
    with pytest.raises(ControlError, match=r"positions must have shape \(T \+ 1, 2, 3\)"):
        sc.Observation([0, 1], np.zeros((4, 3, 3)))
    with pytest.raises(ControlError, match="unknown region"):
        sc.synthesize(model, params, "markers", 3)


# ------------------------------------------------------------------------------ policies


@pytest.mark.slow
def test_policy_training_reduces_loss(scene):
    model, params = scene
    obs = sc.Observations(model, ["tip"], periods=[0.1], length_scale=0.01, velocity_scale=0.1)
    assert obs.size == 8
    policy = sc.MLPPolicy(obs.size, model.n_channels, jax.random.PRNGKey(0), width=8, depth=1, bias=0.1)
    loss = sc.TargetPosition(model, "tip", (0.095, 0.01, 0.02), over=3)
    traj, controls = sc.policy_rollout(model, params, policy, obs, 6)
    assert traj.x.shape == (7, model.n_vertices, 3) and controls.shape == (6, 2)
    assert np.all((np.asarray(controls) > 0) & (np.asarray(controls) < 1))
    res = sc.train_policy(model, params, policy, obs, loss, 6, optimizer=optax.adam(0.1), n_iter=6, progress=False)
    assert res.loss[-1] < 0.7 * res.loss[0], res.loss
    assert float(loss(*sc.policy_rollout(model, params, res.policy, obs, 6))) == pytest.approx(res.best_loss, rel=1e-9)
    with pytest.raises(ControlError, match="does not accept observations of size 8"):
        sc.policy_rollout(model, params, sc.MLPPolicy(5, 2, jax.random.PRNGKey(0)), obs, 3)
    with pytest.raises(ControlError, match="model has 2 channels"):
        sc.policy_rollout(model, params, sc.MLPPolicy(8, 3, jax.random.PRNGKey(0)), obs, 3)


# ------------------------------------------------------------------------------- co-design


def test_capped_simplex_projection():
    rng = np.random.default_rng(0)
    for cap in (math.inf, 0.4):
        v = jnp.asarray(rng.normal(size=20))
        w = np.asarray(sc.project_capped_simplex(v, 3.0, cap))
        assert w.sum() == pytest.approx(3.0, abs=1e-12)
        assert w.min() >= 0 and w.max() <= cap
        # Optimality (KKT): entries strictly inside (0, cap) are v - tau for one tau.
        inside = (w > 1e-12) & (w < cap - 1e-12)
        tau = np.asarray(v)[inside] - w[inside]
        np.testing.assert_allclose(tau, tau[0], atol=1e-12)
    w0 = jnp.full(10, 0.3)
    np.testing.assert_allclose(np.asarray(sc.project_capped_simplex(w0, 3.0)), w0, atol=1e-14)


@pytest.mark.slow
def test_codesign_improves_design_and_respects_constraints(scene):
    model, params = scene
    loss = sc.TargetPosition(model, "tip", (0.095, 0.01, 0.02), over=3)
    design = sc.Design(model, params, muscles=True, max_weight=3.0, stiffness=["default"],
                       stiffness_range=(5e4, 2e5), morph="tip", max_morph=0.002)
    problem = sc.CoDesignProblem(model, params, loss, sc.ControlGrid(8, 2, 1), design)
    res = sc.codesign(problem, 0.3, optimizer=optax.adam(0.1), n_iter=6, progress=False)
    assert res.loss[-1] < 0.7 * res.loss[0], res.loss
    w = np.asarray(res.params.actuators[0].weights)
    assert w.sum() == pytest.approx(model.n_tets, rel=1e-12) and w.min() >= 0 and w.max() <= 3.0
    assert 5e4 <= float(res.params.E[0]) <= 2e5
    morph = np.asarray(res.params.morph)
    assert np.linalg.norm(morph, axis=1).max() <= 0.002 * (1 + 1e-12)
    assert np.all(morph[model.fixed] == 0)
    with pytest.raises(ControlError, match="nothing to design"):
        sc.Design(model, params)
    with pytest.raises(ControlError, match="unknown materials"):
        sc.Design(model, params, stiffness=["rubber"])
    with pytest.raises(ControlError, match="budget"):
        sc.Design(model, params, muscles=[0], budget=100.0, max_weight=1.0)
    with pytest.raises(ControlError, match="not a Muscle term"):
        sc.Design(model, params, muscles=[3])


@pytest.mark.slow
def test_muscle_gait_gradient_through_contact_matches_central_differences():
    """Muscle activations differentiate through the contact solver's implicit derivative.

    That derivative closes over each step's data with ``jax.closure_convert``, which hoists
    only floating-point values: traced integer muscle indices used to leak and the
    gradient failed to compile.
    """
    mesh = grid_box((LENGTH, 0.02, 0.02), (3, 1, 1))
    centre_z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    muscle = Muscle(np.arange(mesh.n_tets), np.tile([1.0, 0.0, 0.0], (mesh.n_tets, 1)),
                    np.where(centre_z > 0.01, 0, 1), ("top", "bottom"), stiffness=1e5)
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, alpha=2.0), actuators=[muscle]),
                          options=Options(dt=0.01, tol=1e-11, max_iter=2000), obstacles=[Plane(mu_s=0.8, mu_k=0.6)])
    loss = sc.ForwardDistance(model)
    n_steps = 4
    problem = sc.ControlProblem(model, params, loss, sc.ControlGrid(n_steps, 2))
    theta = jnp.asarray(np.random.default_rng(0).normal(size=(n_steps, 2)))
    r = check_grad(problem.objective, theta, eps=2e-4, verbose=False)["all"]
    # Richardson-extrapolated central differences (eps and eps / 2): truncation O(eps^4) is
    # negligible and the steps converge to 1e-11 of their force scale. Through friction the
    # rollout is only piecewise smooth (stick and slip), and the agreement measured on this
    # scene depends on the direction: 5e-6 and 4.4e-5 on two random ones. The bound is the
    # one the contact tests use for the same implicit derivative; a derivative that drops
    # the activations' effect (zero, or missing the contact impulses) misses it by far.
    assert abs(r["fd"]) > 0 and abs(r["ad"] - r["fd"]) <= 1e-4 * abs(r["fd"]), r

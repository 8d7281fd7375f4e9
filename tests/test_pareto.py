"""Speed against accuracy: explicit Euler's stability limit, the fidelity advisor, and
scenes that compile only the machinery they use (float64, real grid meshes)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import advisor, explicit
from softbody.bench import pareto
from softbody.simulate import SimulationError, rollout

#: 0.1 x 0.02 x 0.02 m beam on 10 x 2 x 2 cells (99 vertices), E = 1 MPa, released from
#: its static deflection under a 0.4 N tip load (~8 mm).
SCENE = pareto.Cantilever(divisions=(2,))


def _dense_critical_dt(model, params):
    """``2 / sqrt(max eig(M^-1/2 K M^-1/2))`` from the dense Hessian of the elastic energy at rest."""
    from softbody import rotation as rot
    from softbody.elastic import deformation_gradient
    from softbody.model import prepare
    from softbody.objective import step_objective

    prep = prepare(model, params)
    x = prep.x_rest
    q = rot.cold_start(deformation_gradient(model, prep.dminv, x))
    evaluate, _ = step_objective(model, prep, x, x * 0, q, jnp.zeros(0), None)
    k = np.asarray(jax.jacfwd(lambda y: evaluate(y, q)[1])(x)).reshape(3 * model.n_vertices, -1)
    free = np.repeat(model.free_mask[:, 0] > 0, 3)
    m = np.repeat(np.asarray(prep.mass[:, 0]), 3)[free]
    lam = np.linalg.eigvalsh(k[np.ix_(free, free)] / np.sqrt(np.outer(m, m))).max()
    return 2.0 / np.sqrt(lam)


@pytest.fixture(scope="module")
def critical_dt():
    model, params = SCENE.build(2)
    dt = explicit.critical_time_step(model, params)
    return dt, _dense_critical_dt(model, params)


def test_power_iteration_finds_the_stability_limit(critical_dt):
    """The power-iteration estimate of 2 / omega_max agrees with the dense eigenvalue (it
    approaches from above as the iteration converges, so a 1% band is generous)."""
    power, dense = critical_dt
    print(f"critical dt: power iteration {power:.6e} s, dense {dense:.6e} s")
    assert dense <= power * (1 + 1e-9) and power == pytest.approx(dense, rel=1e-2)


@pytest.mark.parametrize("factor, stable", [(0.9, True), (1.15, False)])
def test_explicit_euler_diverges_above_its_stability_limit(critical_dt, factor, stable):
    """Undamped semi-implicit Euler is stable exactly for dt < 2 / omega_max. At 0.9 of the
    limit the free vibration stays within its initial amplitude over 400 steps; at 1.15 the
    highest mode's amplification |lambda| = 2.6 per step (from lambda^2 - (2 - w^2 dt^2)
    lambda + 1 = 0) takes round-off to overflow well within 400 steps."""
    dt = factor * critical_dt[1]
    model, params = SCENE.build(2, dt=dt)
    state = SCENE.initial_state(model, params)
    if stable:
        traj = explicit.explicit_rollout(model, params, state, n_steps=400)
        u = SCENE.tip_displacement(traj.x)
        amplitude = np.linalg.norm(u, axis=1)
        print(f"dt {dt:.3e}: tip amplitude {amplitude[0]:.3e} -> max {amplitude.max():.3e} m")
        assert pareto._bounded(u, True)
    else:
        with pytest.raises(SimulationError, match="stability limit"):
            explicit.explicit_rollout(model, params, state, n_steps=400)


def test_pd_stays_bounded_at_a_thirtieth_of_a_second(critical_dt):
    """Implicit Euler with PD at dt = 1/30 s, ~400x the explicit limit: finite, and the tip
    never moves more than its initial deflection (implicit Euler only dissipates)."""
    model, params = SCENE.build(2, dt=1 / 30, tol=1e-6)
    state = SCENE.initial_state(model, params)
    traj = rollout(model, params, state, n_steps=15)
    u = SCENE.tip_displacement(traj.x)
    amplitude = np.linalg.norm(u, axis=1)
    print(f"explicit limit {critical_dt[1]:.3e} s; PD at 1/30 s: tip {amplitude[0]:.3e} -> max "
          f"{amplitude[1:].max():.3e} m")
    assert np.isfinite(u).all() and amplitude[1:].max() <= amplitude[0]


def test_explicit_matches_the_ode_reference_at_small_steps():
    """Well below the stability limit, explicit Euler tracks the diffrax reference over
    0.05 s (about half a period). Its positions obey the second-order Verlet recursion, but
    starting from rest it takes x_1 = x_0 + h^2 a_0 instead of x_0 + h^2 a_0 / 2: a velocity
    error of h a_0 / 2, so the error is first order, ~ omega h / 2 of the motion (1.2e-3
    at h = 4e-5 for the first mode); halving dt halves it."""
    scene = pareto.Cantilever(duration=0.05, divisions=(2,))
    ref = pareto.reference(scene, samples=500, rtol=1e-8, check=True)
    errors = []
    for dt in (4e-5, 2e-5):
        t, u, *_ = pareto.run_explicit(scene, 2, dt)
        errors.append(ref.error(t, u))
    print(f"explicit errors {errors}, reference self-error {ref.self_error:.2e}")
    assert ref.self_error < 1e-4
    assert errors[0] < 5e-3
    assert 1.8 <= errors[0] / errors[1] <= 2.2


# --------------------------------------------------------------------------------------
# The advisor
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_front():
    scene = pareto.Cantilever(duration=0.1, divisions=(1, 2))
    grid = {"pd_dts": (1 / 100, 1 / 300), "pd_tols": (1e-4,), "coarse_dts": (1 / 100, 1 / 300),
            "coarse_tols": (1e-4,)}
    rows, ref = pareto.measure_front(scene, grid, methods=("PD L-BFGS", "PD mesh"))
    return scene, rows, ref


@pytest.mark.slow
def test_advisor_choice_meets_the_tolerance_when_rerun(small_front):
    """Ask for an error between the best and the worst measured: the advisor must pick a
    set-up that, simulated again from scratch, meets it, and no faster one that meets it."""
    scene, rows, ref = small_front
    errors = sorted(r["rel_error"] for r in rows)
    assert errors[0] < errors[-1]
    tol = float(np.sqrt(errors[0] * errors[-1]))
    advice = advisor.advise(rows, tol)
    c = advice.choice
    print(advice.explain())
    t, u, *_ = pareto.run_pd(scene, c["mesh_k"], c["dt"], c["tol"])
    rerun = ref.error(t, u)
    print(f"requested {tol:.3g}; re-run error {rerun:.3g}")
    assert rerun <= tol
    assert all(r["wall_s"] >= c["wall_s"] for r in rows if r["rel_error"] <= tol)
    assert advice.passed_over or c["wall_s"] == min(r["wall_s"] for r in rows)


def test_advisor_says_when_nothing_meets_the_tolerance(small_front):
    _, rows, _ = small_front
    best = min(r["rel_error"] for r in rows)
    with pytest.raises(advisor.AdviceError, match="no measured PD set-up reaches"):
        advisor.advise(rows, best / 10)
    with pytest.raises(advisor.AdviceError, match="positive"):
        advisor.advise(rows, 0.0)


# --------------------------------------------------------------------------------------
# Model no more than the scene needs
# --------------------------------------------------------------------------------------


def _equations(jaxpr) -> int:
    """Number of equations in a jaxpr, sub-jaxprs (loops, conds, custom rules) included."""
    count = 0
    for eqn in jaxpr.eqns:
        count += 1
        for p in eqn.params.values():
            for sub in p if isinstance(p, (list, tuple)) else (p,):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None:
                    count += _equations(inner if hasattr(inner, "eqns") else inner.jaxpr)
    return count


def _step_size(model, params):
    from softbody.model import initial_state, prepare
    from softbody.simulate import step

    state = initial_state(model, params)
    return _equations(jax.make_jaxpr(lambda p, s: step(model, prepare(model, p), s))(params, state).jaxpr)


def test_no_contact_or_skeleton_work_without_obstacles_or_bones():
    """Without obstacles the default step is plain L-BFGS: the same program as asking for
    L-BFGS explicitly. A far-away plane (never touched) adds the contact machinery, and a
    skeleton adds its reduced solve; both make the step's program larger."""
    from softbody.material import Material
    from softbody.model import Options, build
    from softbody.scene import SoftBody
    from softbody.contact.obstacles import Plane
    from softbody.skeleton import Fixed, Link, Skeleton
    from softbody.solvers import LBFGS

    from softbody.meshing import Region

    mesh = SCENE.mesh(2)
    material = Material(E=1e6, nu=0.3)
    plain, p_plain = build(SoftBody(mesh, material, fixed="fixed"))
    assert type(plain.step.solver) is LBFGS and plain.step.contact is None and plain.rig is None
    explicit_lbfgs, p_lbfgs = build(SoftBody(mesh, material, fixed="fixed"), options=Options(solver=LBFGS()))
    contact, p_contact = build(SoftBody(mesh, material, fixed="fixed"), obstacles=[Plane(point=(0.0, 0.0, -10.0))])
    assert type(contact.step.contact).__name__ == "Contact"
    inside = mesh.points[:, 0] >= 0.08 - 1e-9
    bones = mesh.with_regions(**{"bone:b": Region(np.flatnonzero(inside),
                                                  np.flatnonzero(inside[mesh.tets].all(axis=1)))})
    skeleton, p_skeleton = build(SoftBody(bones, material, fixed="fixed"),
                                 skeleton=Skeleton([Link("b", "bone:b", None, Fixed())]))
    sizes = {name: _step_size(m, p) for name, (m, p) in {
        "default": (plain, p_plain), "L-BFGS": (explicit_lbfgs, p_lbfgs), "contact": (contact, p_contact),
        "skeleton": (skeleton, p_skeleton)}.items()}
    print("jaxpr equations per step:", sizes)
    assert sizes["default"] == sizes["L-BFGS"]
    assert sizes["contact"] > sizes["default"] and sizes["skeleton"] > sizes["default"]

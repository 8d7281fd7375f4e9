"""Prescribed motion of fixed vertices (a moving clamp): the clamp is followed exactly,
Galilean invariance holds, a dragged bar takes the clamp's velocity, gradients pass
through clamped steps, and bad motions are refused before compiling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.explicit import explicit_rollout
from softbody.gradients import check_grad
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout

BAR = grid_box((0.1, 0.02, 0.02), (5, 1, 1))
U = jnp.array([0.05, 0.0, 0.02])  # clamp velocity, m/s
DT = 0.01


def translating(t):
    return jnp.eye(3), U * t


def test_a_clamp_and_a_bar_moving_together_translate_rigidly():
    """Clamp and bar start with the same velocity, no gravity: implicit Euler is Galilean
    invariant, so the bar translates rigidly (elastic forces stay zero), to the step
    tolerance, and the clamped vertices sit exactly on the clamp."""
    model, params = build(SoftBody(BAR, Material(E=1e5, nu=0.3), fixed="xmin", motion=translating),
                          options=Options(dt=DT, gravity=(0.0, 0.0, 0.0), tol=1e-10))
    state0 = initial_state(model, params, v=jnp.broadcast_to(U, (BAR.n_vertices, 3)))
    traj = rollout(model, params, state0, n_steps=20)
    t = DT * np.arange(21)[:, None, None]
    rigid = BAR.points[None] + np.asarray(U) * t
    fixed = model.fixed
    assert np.abs(np.asarray(traj.x)[:, fixed] - rigid[:, fixed]).max() < 1e-15
    assert np.abs(np.asarray(traj.x) - rigid).max() < 1e-9
    assert np.abs(np.asarray(traj.v) - np.asarray(U)).max() < 1e-7


def test_a_clamp_drags_a_bar_from_rest_to_its_own_velocity():
    """The clamp starts moving along the bar's axis at 5 cm/s with the bar at rest; the bar
    is pushed along, and stiffness damping (which does not resist rigid motion) lets its
    vibration settle: after 0.5 s every vertex moves with the clamp (within 1%)."""
    model, params = build(SoftBody(BAR, Material(E=1e5, nu=0.3, beta=0.01), fixed="xmin",
                                   motion=lambda t: (jnp.eye(3), jnp.array([0.05, 0.0, 0.0]) * t)),
                          options=Options(dt=DT, gravity=(0.0, 0.0, 0.0)))
    traj = rollout(model, params, initial_state(model, params), n_steps=50)
    v = np.asarray(traj.v[-1])
    np.testing.assert_allclose(v[:, 0], 0.05, rtol=0.01)
    assert np.abs(v[:, 1:]).max() < 5e-4
    assert float(np.asarray(traj.x[-1])[:, 0].mean() - BAR.points[:, 0].mean()) > 0.02  # it moved ~2.5 cm


@pytest.mark.slow
def test_gradient_through_clamped_steps_matches_central_differences():
    """The tip height after 5 steps of a bar hanging from a clamp that rises and tilts,
    differentiated with respect to log E and the initial velocity (Implicit adjoint,
    float64), against Richardson-extrapolated central differences (eps 1e-3: truncation
    O(eps^4); at 1e-4 the solver's stopping noise gave 6e-7 along v0, 1.4e-7 here)."""
    def motion(t):
        c, s = jnp.cos(0.5 * t), jnp.sin(0.5 * t)
        return jnp.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]), jnp.array([0.0, 0.0, 0.1]) * t

    model, params = build(SoftBody(BAR, Material(E=1e4, nu=0.3), fixed="xmin", motion=motion),
                          options=Options(dt=DT, tol=1e-12, max_iter=500))
    tip = jnp.asarray(np.flatnonzero(BAR.points[:, 0] > 0.1 - 1e-9))
    state0 = initial_state(model, params)

    def loss(theta):
        p = params.replace(E=jnp.exp(theta["log_E"]))
        s = state0.__class__(x=state0.x, v=state0.v + theta["v0"], rot=state0.rot, t=state0.t)
        return jnp.mean(rollout(model, p, s, n_steps=5).x[-1][tip, 2]) * 1e3  # mm

    theta = {"log_E": jnp.log(params.E), "v0": jnp.zeros((BAR.n_vertices, 3))}
    kinds = {k: {j: float(j == k) for j in theta} for k in theta}
    for kind, r in check_grad(loss, theta, directions=kinds, eps=1e-3, verbose=False).items():
        assert abs(r["ad"]) > 1e-3, (kind, r)
        assert r["rel_error"] <= 1e-6, (kind, r)


def test_bad_motions_are_refused_before_compiling(no_compiling):
    with pytest.raises(SceneError, match="has none: give the body fixed="):
        build(SoftBody(BAR, Material(), motion=translating))
    with pytest.raises(SceneError, match="motion must be a function"):
        build(SoftBody(BAR, Material(), fixed="xmin", motion=(np.eye(3), np.zeros(3))))
    with pytest.raises(SceneError, match=r"motion\(0.0\) must return a finite rotation"):
        build(SoftBody(BAR, Material(), fixed="xmin", motion=lambda t: (jnp.eye(3), jnp.zeros(2))))
    with pytest.raises(SceneError, match="is not a rotation"):
        build(SoftBody(BAR, Material(), fixed="xmin", motion=lambda t: (2 * jnp.eye(3), jnp.zeros(3))))
    with pytest.raises(SceneError, match=r"motion\(0.0\) failed"):
        build(SoftBody(BAR, Material(), fixed="xmin", motion=lambda t: (jnp.eye(3),)))
    model, params = build(SoftBody(BAR, Material(), fixed="xmin", motion=translating))
    with pytest.raises(ValueError, match="explicit_rollout does not move fixed vertices"):
        explicit_rollout(model, params, initial_state(model, params), n_steps=2)

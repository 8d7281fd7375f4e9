"""The L-BFGS direction in matrix form against the textbook two-loop recursion, and the
solvers run in a chart that a test defines."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody._interfaces import Chart
from softbody.solvers import LBFGS, LocalGlobal, lbfgs_direction


def two_loop(g, pairs, h0):
    """Nocedal and Wright's Algorithm 7.4 over ``pairs`` (oldest first)."""
    q, alphas = g.copy(), []
    for s, y in reversed(pairs):
        a = (s @ q) / (s @ y)
        alphas.append(a)
        q = q - a * y
    r = h0 * q
    for (s, y), a in zip(pairs, reversed(alphas)):
        r = r + (a - (y @ r) / (s @ y)) * s
    return -r


@pytest.mark.parametrize("count", [0, 1, 3, 4, 6, 11])
def test_ring_buffer_direction_equals_the_two_loop_recursion(count):
    rng = np.random.default_rng(count)
    m, n = 4, 9
    h0 = rng.uniform(0.5, 2.0, n)  # a diagonal initial inverse Hessian
    hessian = np.diag(rng.uniform(1.0, 3.0, n)) + 0.1 * np.ones((n, n))
    s_hist, y_hist, rho, sy = np.zeros((m, n)), np.zeros((m, n)), np.zeros(m), np.zeros((m, m))
    pairs = []
    for c in range(count):  # store pairs as LBFGS.run does: pair c in slot c % m
        s = rng.normal(size=n)
        y = hessian @ s  # curvature pairs of a convex quadratic: s . y > 0
        slot = c % m
        s_hist[slot], y_hist[slot], rho[slot] = s, y, 1.0 / (s @ y)
        sy[slot, :] = y_hist @ s
        sy[:, slot] = s_hist @ y
        pairs.append((s, y))
    g = rng.normal(size=n)
    got = lbfgs_direction(jnp.asarray(g), jnp.asarray(s_hist), jnp.asarray(y_hist), jnp.asarray(rho),
                          jnp.asarray(count), jnp.asarray(sy), lambda r: jnp.asarray(h0) * r)
    want = two_loop(g, pairs[-m:], h0)
    assert np.max(np.abs(np.asarray(got) - want)) <= 1e-12 * np.max(np.abs(want))


class CircleChart(Chart):
    """A chart defined here alone: one point on the unit circle in the xy-plane, its
    tangent the angle (1,), moved by rotating. The solvers of softbody.solvers run in it
    unchanged, as they run in vertex and skeleton coordinates."""

    backtracks = 10

    def __init__(self, energy, h0: float):
        self.energy, self.h0 = energy, h0

    def start(self, x0):
        return jnp.arctan2(x0[0, 1], x0[0, 0])

    def positions(self, theta):
        return jnp.stack([jnp.cos(theta), jnp.sin(theta), 0.0])[None]

    def evaluate(self, theta, q):
        x = self.positions(theta)
        phi, g = jax.value_and_grad(self.energy)(x)
        return phi, g, q

    def gradient(self, theta, g):
        r = jnp.sum(g[0] * jnp.stack([-jnp.sin(theta), jnp.cos(theta), 0.0]))[None]  # dPhi/dtheta
        return r, jnp.abs(r[0]), ()

    def precondition(self, theta, data, r):
        return self.h0 * r

    def move(self, theta, step):
        return theta + step[0]

    def pair(self, theta, data, g, new, data_new, g_new, step):
        return step, self.gradient(new, g_new)[0] - self.gradient(theta, g)[0]


@pytest.mark.parametrize("solver", [LBFGS(history=3), LocalGlobal()], ids=["lbfgs", "local-global"])
def test_solvers_run_in_a_chart_defined_outside_the_package(solver):
    """A point on a circle pulled by a spring towards (cos 1, sin 1) against a quartic
    term in x (a smooth non-quadratic energy of the angle, curvature about 1). The
    minimiser solves the stationarity condition (bisection); the solvers stop at
    |dPhi/dtheta| <= 1e-8, so the point is within about 1e-8 / curvature of it. With an
    initial inverse Hessian three times too large, the Armijo halving of the chart's
    search is what makes the plain step converge. (Armijo's test reads differences of
    Phi: it cannot resolve gradients much below sqrt(eps) |Phi|.)"""
    target = jnp.array([np.cos(1.0), np.sin(1.0), 0.0])

    def energy(x):
        return 0.5 * jnp.sum((x[0] - target) ** 2) + 0.05 * x[0, 0] ** 4

    chart = CircleChart(energy, h0=3.0)  # 1 / curvature is ~1: a step three times too long
    sol = solver.run(chart, jnp.array([[1.0, 0.0, 0.0]]), jnp.zeros(1), jnp.asarray(1e-8), 200)

    def slope(theta):  # dPhi/dtheta, decreasing through zero at the minimiser in (0, 1.2)
        return float(chart.gradient(theta, jax.grad(energy)(chart.positions(theta)))[0][0])

    lo, hi = 0.0, 1.2
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if slope(mid) < 0 else (lo, mid)
    want = chart.positions(0.5 * (lo + hi))
    assert float(sol.gnorm) <= 1e-8 and int(sol.iterations) < 200
    assert np.max(np.abs(np.asarray(sol.x) - np.asarray(want))) < 2e-8
    assert int(sol.evaluations) > int(sol.iterations) + 1  # the search halved some steps

"""The L-BFGS direction in matrix form against the textbook two-loop recursion."""

import jax.numpy as jnp
import numpy as np
import pytest

from softbody.solvers import lbfgs_direction


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

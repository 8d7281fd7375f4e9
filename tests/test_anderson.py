"""Anderson mixing (softbody.contact.anderson): separate blocks mix as each would alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.contact import anderson


def _problem(seed, size, rho):
    """A contracting affine map ``u -> J u + b`` with spectral radius ``rho``."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((size, size)))
    j = q @ np.diag(rho * rng.uniform(-1, 1, size)) @ q.T
    return jnp.asarray(j), jnp.asarray(rng.standard_normal(size))


def _iterates(maps, x0, labels, m=5, steps=12, blocks=None):
    """The Anderson iterates of ``x -> maps(x)`` from ``x0``, entries in the blocks ``labels``."""
    hist = anderson.init(m, x0.size, x0.dtype, labels, blocks)
    x, out = x0, []
    for _ in range(steps):
        x, hist = anderson.mix(x, maps(x), jnp.ones(x.size), hist, jnp.asarray(False), m, labels)
        out.append(x)
    return jnp.stack(out)


def test_blocks_mix_as_each_alone():
    """Two independent problems (sizes 7 and 5) iterated together with one block each give
    each problem's own iterates (to rounding); with one block for both they do not."""
    (j1, b1), (j2, b2) = _problem(0, 7, 0.99), _problem(1, 5, 0.5)

    def both(x):
        return jnp.concatenate([j1 @ x[:7] + b1, j2 @ x[7:] + b2])

    x0 = jnp.zeros(12)
    together = _iterates(both, x0, np.repeat([0, 1], [7, 5]))
    alone1 = _iterates(lambda x: j1 @ x + b1, x0[:7], None)
    alone2 = _iterates(lambda x: j2 @ x + b2, x0[7:], None)
    np.testing.assert_allclose(together[:, :7], alone1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(together[:, 7:], alone2, rtol=0, atol=1e-12)
    mixed = _iterates(both, x0, None)
    assert np.abs(np.asarray(mixed[:, :7] - alone1)).max() > 1e-6


def test_blocks_found_under_jit_mix_as_static_ones():
    """Labels computed inside a compiled function (the contact iteration finds its blocks
    from the step's rows), with a label that no entry carries, give the iterates of the same
    blocks given as static labels; without their number they are refused."""
    (j1, b1), (j2, b2) = _problem(0, 7, 0.99), _problem(1, 5, 0.5)

    def both(x):
        return jnp.concatenate([j1 @ x[:7] + b1, j2 @ x[7:] + b2])

    x0 = jnp.zeros(12)
    static = _iterates(both, x0, np.repeat([0, 1], [7, 5]))
    traced = jax.jit(lambda shift: _iterates(both, x0, jnp.where(jnp.arange(12) < 7, 0, 2) + shift, blocks=4))(0)
    np.testing.assert_allclose(traced, static, rtol=0, atol=1e-12)
    with pytest.raises(TypeError, match="number of blocks"):
        jax.jit(lambda labels: anderson.init(5, 12, x0.dtype, labels))(jnp.zeros(12, int))
    assert anderson.init(5, 12, x0.dtype, jnp.asarray([0, 2] * 6))[2].shape == (3, 5, 5)  # concrete: counted


def test_iterate_keeps_the_best_and_stops_where_it_is_told():
    """The contact iterations' loop: on a contraction (rho 0.99) it reaches the tolerance
    with Anderson far sooner than the plain map would (0.99^k), and returns the fixed
    point; on a map that never improves (a rotation) ``patience`` stops it after four
    spans and the returned iterate is the first output, the best one; a cache rides along
    and a ``reset`` restarts without harm."""
    j, b = _problem(2, 9, 0.99)
    u = jnp.linalg.solve(jnp.eye(9) - j, b)

    def contraction(x, q, cache):
        gx = j @ x + b
        return gx, q, jnp.linalg.norm(gx - x), cache + 1, jnp.asarray(False)

    x, q, k, r, cache = anderson.iterate(contraction, jnp.zeros(9), jnp.zeros(()), jnp.asarray(0),
                                        weight=jnp.ones(9), threshold=1e-10, cap=500, history=5, restart=10.0)
    assert r <= 1e-10 and int(k) < 100 and int(cache) == int(k)  # the plain map needs ~2300
    np.testing.assert_allclose(x, u, rtol=0, atol=1e-8)

    turn = jnp.asarray([[0.0, -1.0], [1.0, 0.0]])

    def rotation(x, q, cache):
        gx = turn @ x
        return gx, q, jnp.linalg.norm(gx - x) * (1.0 + cache), cache + 1, jnp.asarray(True)

    x, _, k, r, _ = anderson.iterate(rotation, jnp.asarray([1.0, 0.0]), jnp.zeros(()), jnp.asarray(0.0),
                                     weight=jnp.ones(2), threshold=1e-12, cap=1000, history=3, restart=10.0,
                                     patience=5)
    assert int(k) == 1 + 4 * 5  # the first (the best), then 4 patience spans without a better one
    np.testing.assert_allclose(x, [0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(r, np.sqrt(2.0))

"""Anderson mixing (softbody.anderson): separate blocks mix as each would alone."""

import jax.numpy as jnp
import numpy as np

from softbody import anderson


def _problem(seed, size, rho):
    """A contracting affine map ``u -> J u + b`` with spectral radius ``rho``."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((size, size)))
    j = q @ np.diag(rho * rng.uniform(-1, 1, size)) @ q.T
    return jnp.asarray(j), jnp.asarray(rng.standard_normal(size))


def _iterates(maps, x0, labels, m=5, steps=12):
    """The Anderson iterates of ``x -> maps(x)`` from ``x0``, entries in the blocks ``labels``."""
    hist = anderson.init(m, x0.size, x0.dtype, labels)
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

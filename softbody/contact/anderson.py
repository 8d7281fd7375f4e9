"""Anderson acceleration (type II) of fixed-point iterations ``x <- G(x)``, for the contact
solver's forward solve and the linear solve of its implicit derivative.

From the pair ``(x, G(x))`` of each iteration, :func:`mix` keeps the last ``m``
differences of (weighted) residuals ``G(x) - x`` and of map outputs, and returns the
output combination whose residual combination is smallest in least squares
(regularised; the Gram matrix of the residual differences is updated one row per
iteration, so an update costs ``O(m N)``). A restart clears the history, after which the
next iterate is the plain ``G(x)``; ``m = 0`` is the plain iteration. The history is a
tuple of fixed-shape arrays (:func:`init`), so the iteration runs inside
``jax.lax.while_loop``. :func:`linear_solve` applies the same mixing to ``u = J u + b``
to solve ``(I - J) u = b`` when ``rho(J) < 1``.

The acceleration is a heuristic with no convergence guarantee of its own: :func:`iterate`,
the one loop of the contact iterations (the splitting of :class:`softbody.contact.Contact`
and the active set of :class:`softbody.contact.active_set.ActiveSet`), keeps the best iterate and
restarts when the residual grows.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def _count(labels, blocks: int | None) -> int:
    """The number of blocks: ``blocks`` if given, else one more than the largest static label."""
    if blocks is not None:
        return int(blocks)
    if isinstance(labels, jax.core.Tracer):
        raise TypeError("labels computed under jit need their number of blocks (blocks=...)")
    return int(np.max(labels)) + 1


def init(m: int, size: int, dtype, labels=None, blocks: int | None = None):
    """An empty Anderson history.

    Arguments:
        m: the history length (0 allowed: the plain iteration keeps no history).
        size: ``N``, the number of unknowns (the iterate's size).
        dtype: the iterate's floating-point type.
        labels: the block of each entry, as :func:`mix` takes them (``None``: one block).
        blocks: the number of blocks ``B`` (static), needed where ``labels`` is a traced
            array (blocks found during the step); default one more than the largest label.

    Returns:
        ``(dR (m, N), dG (m, N), Gram, r (N,), g (N,), count ())``: residual and output
        differences, the Gram matrix of the residual differences (``(m, m)``; with ``labels``
        ``(B, m, m)``, one per block), the last weighted residual and output,
        and the number of pairs seen since the last restart.

    Raises:
        TypeError: ``labels`` traced (computed under ``jit``) without ``blocks``.
    """
    return (
        jnp.zeros((m, size), dtype),
        jnp.zeros((m, size), dtype),
        jnp.zeros((m, m) if labels is None else (_count(labels, blocks), m, m), dtype),
        jnp.zeros(size, dtype),
        jnp.zeros(size, dtype),
        jnp.asarray(0),
    )


def mix(x, gx, weight, hist, restart, m: int, labels: np.ndarray | None = None):
    """One Anderson (type II) update from the pair ``(x, G(x))``: returns ``(x_next, hist)``.

    The last ``m`` differences of residuals ``weight * (G(x) - x)`` and of map outputs give
    the mixing coefficients by regularised least squares (their Gram matrix is updated one
    row per iteration); ``restart`` clears the history (the next iterate is then the plain
    ``G(x)``). ``m = 0`` is the plain iteration. With ``labels`` each block of entries gets
    coefficients of its own, from its own entries of the differences: the update of
    independent sub-problems (bodies that do not touch) is then theirs alone, as if each
    were iterated by itself (one set of coefficients for all mixes their histories, and a
    block that has converged slows the others).

    Arguments:
        x: the current iterate (any shape, ``N`` entries).
        gx: ``G(x)``, the map's output (the shape of ``x``).
        weight: ``(N,)`` weights of the residual entries (zero drops an entry).
        hist: the history (:func:`init` with the same ``labels``, or this function's
            previous output).
        restart: a boolean scalar: clear the history before this pair.
        m: the history length (static), as given to :func:`init`.
        labels: ``(N,)`` ints ``0 .. B - 1`` (static, or traced with ``B`` given to
            :func:`init`), the block of each flattened entry; ``None``: one block. A label
            that no entry carries is an empty block (its coefficients are zero).

    Returns:
        ``(x_next, hist)``: the next iterate (the shape of ``x``) and the updated history.
    """
    if m == 0:
        return gx, hist
    d_r, d_g, gram, prev_r, prev_g, count = hist
    r = weight * (gx - x).ravel()
    g = gx.ravel()
    slot = jnp.maximum(count - 1, 0) % m
    push = count >= 1
    d_r = jnp.where(push, d_r.at[slot].set(r - prev_r), d_r)
    d_g = jnp.where(push, d_g.at[slot].set(g - prev_g), d_g)
    if labels is None:
        row = d_r @ d_r[slot]
        gram = jnp.where(push, gram.at[slot, :].set(row).at[:, slot].set(row), gram)
    else:
        blocks = gram.shape[0]
        rows = jax.ops.segment_sum((d_r * d_r[slot]).T, labels, blocks)  # (B, m)
        gram = jnp.where(push, gram.at[:, slot, :].set(rows).at[:, :, slot].set(rows), gram)
    count = jnp.where(restart, 1, count + 1)
    valid = (jnp.arange(m) < jnp.minimum(count - 1, m)).astype(r.dtype)
    gram_valid = gram * valid[:, None] * valid[None, :]
    if labels is None:
        reg = 1e-10 * jnp.trace(gram_valid) + jnp.finfo(r.dtype).tiny
        gamma = jnp.linalg.solve(gram_valid + jnp.diag(reg + (1.0 - valid)), valid * (d_r @ r))
        x_next = g - gamma @ d_g
    else:
        reg = 1e-10 * jnp.trace(gram_valid, axis1=1, axis2=2) + jnp.finfo(r.dtype).tiny  # (B,)
        system = gram_valid + reg[:, None, None] * jnp.eye(m) + jnp.diag(1.0 - valid)
        rhs = jax.ops.segment_sum((d_r * r).T, labels, blocks) * valid  # (B, m)
        gamma = jnp.linalg.solve(system, rhs[..., None])[..., 0]  # (B, m)
        x_next = g - jnp.sum(gamma[labels].T * d_g, axis=0)
    return x_next.reshape(x.shape), (d_r, d_g, gram, r, g, count)


def iterate(step, x0, q0, cache=(), *, weight, threshold, cap, history: int, restart: float,
            labels=None, blocks: int | None = None, patience: int | None = None):
    """Anderson-accelerated fixed-point iteration that keeps its best iterate.

    Each iteration maps the iterate by ``step``, keeps the output with the smallest
    residual so far, and mixes (:func:`mix`) the pair into the next iterate; the history
    restarts when the residual exceeds ``restart`` times the best one, when ``step`` says
    so (a structural change: contacts made or broken), and every ``patience`` iterations
    without progress. A diverging iteration (NaN residuals) keeps the best iterate.

    Arguments:
        step: ``(x, q, cache) -> (x_new, q_new, r, cache_new, reset)``: the map, the
            residual ``r`` of ``x`` (a scalar), data carried to the next iteration, and a
            boolean that restarts the history (or ``None``: never).
        x0, q0: the start iterate (any shape) and its companion (rotations); cache: the
            first ``cache`` (a pytree; ``()``: none).
        weight: ``(x0.size,)`` Anderson weights; labels, blocks: Anderson blocks and their
            number (see :func:`init` and :func:`mix`).
        threshold: stop when the residual of the last iterate is at most this; cap: the
            iteration cap (may be traced).
        history: Anderson history length; restart: the residual growth (> 1) that
            restarts it.
        patience: ``None``, or restart after this many iterations without a better
            residual and stop after four times as many.

    Returns:
        ``(best_x, best_q, iterations, best_r, cache)``: the map output with the smallest
        residual, its residual, the iteration count and the last cache.
    """
    inf = jnp.asarray(jnp.inf, x0.dtype)

    def body(c):
        x, q, k, best_x, best_q, best_r, _, hist, cache, stall = c
        x_new, q_new, r, new_cache, reset = step(x, q, cache)
        better = r < best_r
        best_x = jnp.where(better, x_new, best_x)
        best_q = jnp.where(better, q_new, best_q)
        if patience is not None:
            stall = jnp.where(better, 0, stall + 1)
        grown = r > restart * best_r
        if reset is not None:
            grown = grown | reset
        if patience is not None:
            grown = grown | (stall % patience == patience - 1)
        best_r = jnp.where(better, r, best_r)
        x_next, hist = mix(x, x_new, weight, hist, grown, history, labels)
        return x_next, q_new, k + 1, best_x, best_q, best_r, r, hist, new_cache, stall

    def going(c):
        more = (c[6] > threshold) & (c[2] < cap)
        return more if patience is None else more & (c[9] < 4 * patience)

    stall = None if patience is None else jnp.asarray(0)
    init_ = (x0, q0, jnp.asarray(0), x0, q0, inf, inf, init(history, x0.size, x0.dtype, labels, blocks), cache,
             stall)
    _, _, k, best_x, best_q, best_r, _, _, cache, _ = jax.lax.while_loop(going, body, init_)
    return best_x, best_q, k, best_r, cache


def linear_solve(matvec, b, *, history: int, rtol: float, max_iter: int, labels: np.ndarray | None = None):
    """Solve ``matvec(u) = b``, ``matvec = I - J``, ``rho(J) < 1``: Anderson on ``u = J u + b``.

    Arguments:
        matvec: ``u -> (I - J) u``, linear.
        b: the right-hand side (any shape).
        history: the Anderson history length (>= 1).
        rtol: stop when ``|J u + b - u| <= rtol |b|``.
        max_iter: iteration cap (the last iterate is returned when it is reached).
        labels: the block of each flattened entry, mixed separately (see :func:`mix`), or
            ``None``.

    Returns:
        ``u``, the shape of ``b``.
    """
    bnorm = jnp.linalg.norm(b.ravel())
    threshold = rtol * bnorm

    def body(c):
        u, k, _, hist = c
        tu = u - matvec(u) + b
        residual = jnp.linalg.norm((tu - u).ravel())
        u, hist = mix(u, tu, jnp.ones(u.size, u.dtype), hist, jnp.asarray(False), history, labels)
        return u, k + 1, residual, hist

    start = (
        b,
        jnp.asarray(0),
        jnp.asarray(jnp.inf, b.dtype),
        init(history, b.size, b.dtype, labels),
    )
    u, *_ = jax.lax.while_loop(lambda c: (c[2] > threshold) & (c[1] < max_iter), body, start)
    return u

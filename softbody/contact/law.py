"""The contact law of one row: the per-vertex contact step (stick, slide, separate) of
obstacle rows and the projected Jacobi update of pair rows' forces, and the contact states
they report (see :mod:`softbody.contact.solver` for the iteration that applies them)."""

from __future__ import annotations

import jax.numpy as jnp

from softbody._interfaces import PairFrame
from softbody.contact.obstacles import norm, unit

#: The contact states that :meth:`Contact.report` gives, by code.
CONTACT_STATES = ("none", "stick", "slide")

# m/s: the tangential speed relative to the surface it meets above which a row counts as
# sliding at a step's start. Rows whose compliance the iteration only bounds (the pair rows,
# a rigid part's obstacle rows: relaxed Jacobi updates, not the exact per-vertex step) meet
# one cone per step: the kinetic one where the row slides at the step's start (measured
# with the start's normal, so that no row changes class within a step), else the static
# one, with a continuous projection on it. Testing the static cone and then sliding
# on the kinetic one within a step (mu_s > mu_k) makes the update discontinuous: with the
# bounded compliance there is a range of tangential loads where neither sticking nor sliding
# is a fixed point, and coupled rows flip between them without end (a tumbling brick's
# impact stalled at a residual of 1e-5-1e-4 with every history length; a 2 cm rigid cube
# dropped onto another on the ground, mu_s = 0.5, mu_k = 0.4, stopped at the 3000 cap in
# its impact step and converges in 15 iterations with one cone). A contact that starts to
# slip within a step is held by the static cone for that step and meets the kinetic one from
# the next. Resting contacts (drift 1e-8 m in 0.4 s, 2.5e-8 m/s) stay far below it.
SLIDING_SPEED = 1e-4

# m: the gap of a point on which a row generator puts no row (its frame's phi is inf there):
# finite, so that products with it in the contact step stay finite.
_FAR = 1e30


def _spread(frame: PairFrame, force, n: int):
    """``(n, 3)``: the rows' forces ``force`` ``(m, 3)`` (each on its touching vertex) on the
    vertices, by the rows' weights (the reactions on the touched triangles included)."""
    return jnp.zeros((n, 3), force.dtype).at[frame.vertices.ravel()].add(
        (frame.weights[:, :, None] * force[:, None, :]).reshape(-1, 3))


def _sliding(start: PairFrame, v_n):
    """``(m,)`` bool: the pair rows that slide at the step's start (their relative tangential
    speed, in the frame ``start`` of the step's start positions, above :data:`SLIDING_SPEED`).
    The start's normal, not the iterate's: a row's class must not change within a step."""
    v_rel = jnp.sum(start.weights[:, :, None] * v_n[start.vertices], axis=1)
    return norm(_tangential(v_rel, start.normal)) > SLIDING_SPEED


def _pair_update(frame: PairFrame, force, z, x_n, v_n, h, compliance, sliding):
    """One projected Jacobi update of the pair rows' forces ``force`` ``(m, 3)`` (N, world
    frame, on each row's touching vertex) at trial positions ``z`` ``(n, 3)``.

    Each row's force is corrected by what closes its gap and cancels its relative slip
    through the row's compliance ``W = sum_a w_a^2 c_a / P_a`` (``compliance`` ``(n, 1)``:
    ``c_a / P_a``, the vertex's sweep compliance times the number of rows on it, zero on
    held vertices), then projected on the friction cone: normal part ``>= 0``; stick if
    the tangential part fits the cone, else the cone's edge against the slip. One cone per
    row and step (see :data:`SLIDING_SPEED`): ``mu_k`` where the row slides at the step's
    start (``sliding`` ``(m,)``, :func:`_sliding`), else ``mu_s``. At a fixed point
    (``force`` unchanged) every row is complementary: a positive normal force on a closed
    gap (at the restitution's target), a zero force on an open one, and Coulomb's law
    tangentially.
    """
    live = frame.phi < _FAR
    w = frame.weights[:, :, None]  # (m, 4, 1)
    normal = frame.normal
    W = jnp.sum(frame.weights**2 * compliance[frame.vertices, 0], axis=1)  # (m,)
    W = jnp.where(live & (W > 0), W, 1.0)
    v_rel = jnp.sum(w * v_n[frame.vertices], axis=1)
    approach = jnp.sum(v_rel * normal, axis=-1)
    depth = h * frame.restitution * jnp.maximum(-approach, 0.0) - frame.phi
    f_n = jnp.sum(force * normal, axis=-1)
    f_n_new = jnp.maximum(f_n + depth / W, 0.0)
    slip = _tangential(jnp.sum(w * (z[frame.vertices] - x_n[frame.vertices]), axis=1), normal)
    trial = _tangential(force, normal) - slip / W[:, None]
    mu = jnp.where(sliding, frame.mu_k, frame.mu_s)
    stick = norm(trial) <= mu * f_n_new
    f_t = jnp.where(stick[:, None], trial, (mu * f_n_new)[:, None] * unit(trial, jnp.zeros_like(trial)))
    return jnp.where(live[:, None], f_n_new[:, None] * normal + f_t, 0.0)


def _contact_step(y, x_n, v_n, h, frame, free):
    """The per-vertex contact step (positions form): returns the corrected positions.

    ``y`` ``(n, 3)`` are the sweep's positions, ``frame`` the nearest obstacle's
    ``(phi, normal, velocity, mu_s, mu_k, e)`` at ``y``, ``free`` ``(n, 1)``. The impulse on
    vertex ``i`` is ``h P_i (x_i - y_i)``; ``P_i`` scales its normal and tangential parts
    alike, so the cone test needs displacements only.
    """
    touching, _, correction = _contact_state(y, x_n, v_n, h, frame, free)
    return y + jnp.where(touching[:, None], correction, 0.0)


def _positions(x, n: int):
    """The positions ``(n, 3)``: the first ``n`` rows of a contact iterate ``(n + e, 3)``."""
    return x if x.shape[0] == n else x[:n]


def _tangential(v, normal):
    """The part of ``v`` ``(n, 3)`` along the obstacle, orthogonal to the unit ``normal`` ``(n, 3)``."""
    return v - jnp.sum(v * normal, axis=-1, keepdims=True) * normal


def _contact_state(y, x_n, v_n, h, frame, free):
    """The contact step's decision per vertex: ``(touching (n,), stick (n,), correction (n, 3))``
    (arguments as for :func:`_contact_step`)."""
    phi, normal, vel, mu_s, mu_k, e = frame
    approach = jnp.sum((v_n - vel) * normal, axis=-1)  # < 0: moving into the obstacle
    depth = h * e * jnp.maximum(-approach, 0.0) - phi  # normal correction that reaches the target
    touching = (depth > 0) & (free[:, 0] > 0)
    slip_t = _tangential(y - x_n - h * vel, normal)  # displacement relative to the obstacle's material
    slip_len = norm(slip_t)
    stick = slip_len <= mu_s * depth
    slide = -(mu_k * depth)[:, None] * unit(slip_t, jnp.zeros_like(slip_t))
    correction = depth[:, None] * normal + jnp.where(stick[:, None], -slip_t, slide)
    return touching, stick, correction


"""Contact forces and states at a step's solution: what :func:`softbody.simulate.contact_forces`
reports, from the contact iteration's fixed point (see :mod:`softbody.contact.solver`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from softbody._interfaces import Coordinates
from softbody.contact.law import _contact_state, _spread, _tangential
from softbody.contact.obstacles import norm
from softbody.contact.rows import _frames, _Pairs
from softbody.contact.solver import Contact
from softbody.solvers import StepProblem


def report(solver: Contact, problem: StepProblem, coordinates: Coordinates, x, q, threshold, max_iter: int):
    """The contact forces and states at a step's solution.

    At the fixed point the force residual ``grad Phi - r`` vanishes, so the force the
    obstacles exert on a vertex in contact is ``r = grad Phi(x)``; a vertex is in contact
    where the contact step acts at ``x``, and slides where it ends the step displaced
    along the obstacle (see the comment in the code for the threshold). The forces on
    vertices that coordinates move as a whole (a skeleton's skin: rigid bodies, bones)
    are the extra rows of the iteration run again from ``x`` (the body barely moves,
    its forces build up) to ``threshold``; so are the forces of pair rows on such
    vertices (grad Phi there also holds the part's own constraint forces).

    Arguments:
        solver: the step's contact solver (:class:`~softbody.contact.solver.Contact`).
        problem: the step; coordinates: its unknowns.
        x: ``(n, 3)`` the step's solution; q: ``(4, t)`` rotations of ``x``.
        threshold, max_iter: the step's force tolerance and iteration cap.

    Returns:
        ``(force (n, 3), state (n,))``: forces in N (zero off contact) and int8 states
        ``CONTACT_STATES`` (0: no contact, 1: sticking, 2: sliding).
    """
    p = solver._sweep_diagonal(problem)
    pairs = _Pairs.select(problem, x)
    iteration = solver.map(problem, coordinates, pairs)
    parts = iteration.parts
    n, rows = x.shape[0], x.shape[0] + len(parts.owners)
    rigid_pairs = pairs.size and parts.rigid is not None
    if len(parts.owners) or rigid_pairs:
        # forces on what moves as a whole (skin, rigid parts' pair rows): the iteration
        # run again from x (the body barely moves, its forces build up) to threshold
        solved = solver._iterate(iteration, iteration.lift(x), q, threshold, max_iter)
    x, _ = parts.place(x)
    _, g, _ = problem.evaluate(x, q)
    y = x - g / p
    frame = _frames(problem.rows, y, jnp.arange(x.shape[0]), problem.time + problem.dt)
    contact, _, _ = _contact_state(y, problem.x_n, problem.v_n, problem.dt, frame, parts.touching)
    force = jnp.where(contact[:, None], g, 0.0)
    normal, vel, mu_s, mu_k = frame[1], frame[2], frame[3], frame[4]
    # Stick or slide from the solution itself: a sticking vertex ends the step with no
    # tangential displacement relative to the obstacle; a sliding one keeps at least
    # (mu_s - mu_k) depth of it (its sweep slip exceeded mu_s depth, the kinetic cone
    # took back mu_k depth), with depth = r_n / P the normal force over the vertex's
    # sweep weight. Half that margin separates the two robustly (the decision of the
    # contact step itself is a tie at the cone's edge).
    weight = p[:, 0]
    if len(parts.owners):
        owners = jnp.asarray(parts.owners)
        skin = parts.forces(solved.x[:rows])
        frame_skin = _frames(problem.rows, x[owners], owners, problem.time + problem.dt)
        pushed = jnp.sum(skin * frame_skin[1], axis=-1) > 0
        contact = contact.at[owners].set(pushed)
        force = force.at[owners].set(jnp.where(pushed[:, None], skin, 0.0))
        normal, vel = normal.at[owners].set(frame_skin[1]), vel.at[owners].set(frame_skin[2])
        mu_s, mu_k = mu_s.at[owners].set(frame_skin[3]), mu_k.at[owners].set(frame_skin[4])
        weight = weight.at[owners].set(parts.scale[:, 0])
    slip_t = norm(_tangential(x - problem.x_n - problem.dt * vel, normal))
    depth = jnp.maximum(jnp.sum(force * normal, axis=-1), 0.0) / weight
    sliding = slip_t > jnp.maximum(0.5 * (mu_s - mu_k), 1e-6) * depth
    state = jnp.where(contact, jnp.where(sliding, 2, 1), 0).astype(jnp.int8)
    if pairs.size:
        force, state = _report_pairs(solver, problem, pairs, x, g, p, force, state)
    if rigid_pairs:  # on rigid parts grad Phi is not the rows' force (the part's constraints take a share)
        on_rigid = (np.asarray(parts.rigid.body) >= n) & (state > 0)
        force = jnp.where(on_rigid[:, None], _spread(pairs.frame(x), solved.x[rows:], n), force)
    return force, state

def _report_pairs(solver: Contact, problem: StepProblem, pairs: _Pairs, x, g, p, force, state):
    """:func:`report` on the vertices of the pair rows: a row acts where its gap is closed
    (within ``margin``) and the force on its touching vertex pushes along its normal;
    the force on each vertex of an acting row is ``grad Phi`` there (the sum of the
    rows' forces and reactions on it), and the row slides where its relative slip
    exceeds the margin between the cones (as for the vertex rows, with the row's
    compliance ``W = sum_a w_a^2 / P_a``)."""
    n = x.shape[0]
    frame = pairs.frame(x)
    push = jnp.sum(g[frame.vertices[:, 0]] * frame.normal, axis=-1)
    acting = (frame.phi <= solver.margin) & (push > 0)
    W = jnp.sum(frame.weights**2 / p[frame.vertices, 0], axis=1)
    slip = norm(_tangential(jnp.sum(frame.weights[:, :, None] * (x - problem.x_n)[frame.vertices], axis=1),
                            frame.normal))
    sliding = slip > jnp.maximum(0.5 * (frame.mu_s - frame.mu_k), 1e-6) * push * W
    code = jnp.where(acting, jnp.where(sliding, 2, 1), 0).astype(jnp.int8)
    on = (frame.weights != 0) & acting[:, None]  # (m, 4): the vertices each acting row moves
    row_state = jnp.zeros(n, jnp.int8).at[frame.vertices.ravel()].max(jnp.where(on, code[:, None], 0).ravel())
    touched = row_state > 0
    return jnp.where(touched[:, None], g, force), jnp.maximum(state, row_state)

"""The contact solver's fast iteration: an active-set method on the prefactored PD matrix.

:class:`~softbody.contact.Contact` solves each implicit-Euler step with contact as the
fixed point of its splitting map (see :mod:`softbody.contact`): PD's local step, one sweep
``y = x - grad Phi / P`` with the diagonal ``P = M/h^2 + D``, and the per-vertex contact
step. That map contracts by 0.99-0.9999 per iteration on stiff bodies and long steps.
:class:`ActiveSet` finds *the same fixed point* with the prefactored PD matrix ``A``
instead of the diagonal. Its unknowns are the positions; the contact forces are those
that balance the candidate vertices (the ``m`` free vertices nearest to the obstacles at
the step's start). One iteration from ``x`` is:

1. PD's local step: ``g = grad Phi(x)``; the candidates' forces ``g_C``;
2. the splitting's per-vertex contact step at the candidates' sweep positions
   ``x_i - g_i / P_i`` (the very decision the splitting takes): a candidate is free,
   sticking (its target ``z_i`` fixes all three components) or sliding (its target fixes
   the normal component; the kinetic friction force of the contact step is its
   tangential force ``r_i``). ``Pi_i`` projects on the fixed components (``I``, ``n n^T``
   or 0);
3. the global step of the other vertices: ``y = x - A^-1 (g - J g_C)``;
4. the force change: the known part ``kappa = (I - Pi)(r - g_C)`` (forces released,
   friction forces of sliding vertices) and, on the fixed components, the part ``mu``
   that puts them on their targets, from the candidates' block of the Delassus operator
   ``W = (A^-1)_CC`` (``m x m`` per coordinate, dense; one solve with ``m``
   right-hand sides per step)::

       (Pi W Pi + I - Pi) mu = Pi (z - y_C - W kappa),
       x_new = y + A^-1 J (kappa + mu)

   (the ``3m x 3m`` matrix is factorised again only when a candidate's state changes).

``A (x_new - x) = J (g_C + kappa + mu) - g``: the new iterate is balanced by the new
forces, and the force residual ``|g - J (g_C + kappa + mu)|`` is the splitting's. At a
fixed point the forces balance ``g``, the fixed components sit on their targets and the
sliding vertices carry their friction forces: every candidate's contact step returns its
own position, which is the splitting map's fixed point, exactly. Sticking vertices are
placed exactly in each iteration, so with a stable active set this is PD's local-global
iteration with those vertices held, accelerated by Anderson mixing as the contact-free
solve is by L-BFGS.

Where it stands (``softbody bench friction-stability``, the first step of six meshes
resting on frictional ground, ``E`` 1e4-1e7 Pa, ``h`` 1/1000-1/30 s, 96 cases, 2-core
CPU): all 96 converge, 2 through the fallback; 45 iterations per step at the median and
750 at most, against 150 and 1431 for the splitting; 2.0x less wall time over all cases,
3.25x on the 1419-vertex quadruped (5.4x at ``E`` = 1e7 Pa, ``h`` = 1/30 s: 164
iterations against 1431), but 0.56-1.03x on the meshes under 350 vertices, where one
iteration's dense work (``3m``-sized solves, a factorisation per state change) costs
more than the local steps it saves. It is not the default: most vertices under load slide
by tiny amounts (the Poisson bulge), and with ``mu_s > mu_k`` a step has several
equilibria; the two iterations can pick different ones, and in the crawler example
(``examples/crawler.py``) a trajectory that took this iteration's reached a state where
the splitting then needed more than the example's 1000 iterations.

The same map, with its active set frozen at the solution, carries the step's implicit
derivative (:func:`softbody.contact.fixed_point.fixed_point`): its fixed points are the
splitting's, so the derivative is the same, and its linearisation contracts like the
forward iteration does. ``A`` and ``W`` only precondition the map: at a fixed point the
map's derivative with respect to them vanishes, so they are held constant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from softbody.contact import anderson
from softbody._interfaces import Capabilities
from softbody.solvers import Solution, StepProblem

__all__ = ["ActiveSet", "Delassus"]


class Delassus(NamedTuple):
    """The candidate vertices of one step and their block of ``A^-1``."""

    index: jax.Array  # (m,) int: the candidates
    valid: jax.Array  # (m,) bool: False for padding (held vertices, when too few are free)
    w: jax.Array  # (m, m): (A^-1)_CC, zero on padding


@dataclass(frozen=True)
class ActiveSet:
    """The contact solver's fast iteration (see the module docstring).

    Attributes:
        max_contacts: the number of candidate vertices ``m`` (static; at most half the
            scene's vertices, rounded up). A vertex that touches an obstacle without
            being among the ``m`` nearest at the step's start is left to the splitting
            iteration, which then finishes the step (``StepInfo.fallback``). Costs per
            step: ``m`` solves with the prefactored matrix, and a dense ``3m x 3m``
            Cholesky factorisation per change of a candidate's state.
        history: Anderson history length (0: the plain iteration).
        max_iter: iterations before the splitting iteration takes over (also bounded by
            the step's own cap).
        patience: iterations without a new smallest residual after which the Anderson
            history is cleared; after four such spans the splitting iteration takes over.

    Raises:
        ValueError: a bad attribute.
    """

    capabilities = Capabilities(
        refuses={**{feature: ("works in vertex coordinates (its Delassus operator is the vertices'); the reduced "
                              "coordinates of a skeleton or of rigid bodies run the splitting alone")
                    for feature in ("skeleton", "rigid bodies")},
                 "pair contact": "projects rows on one vertex each; rows between bodies run in the splitting"},
        instead="use Contact(active_set=None)")

    max_contacts: int = 128
    history: int = 20
    max_iter: int = 200
    patience: int = 16

    def __post_init__(self):
        for name in ("max_contacts", "max_iter", "patience"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"ActiveSet.{name} must be an integer >= 1, got {value!r}")
        if int(self.history) != self.history or self.history < 0:
            raise ValueError(f"ActiveSet.history must be an integer >= 0, got {self.history!r}")

    def delassus(self, problem: StepProblem, clearance) -> Delassus:
        """The step's candidates and their Delassus block.

        Arguments:
            problem: the step (vertex coordinates).
            clearance: ``(n,)`` each vertex's distance to the nearest obstacle at the
                step's start (``inf`` on held vertices): the ``m`` smallest are the
                candidates.

        Returns:
            :class:`Delassus`.
        """
        n = clearance.shape[0]
        m = min(int(self.max_contacts), -(-n // 2))
        _, index = jax.lax.top_k(-clearance, m)
        valid = jnp.isfinite(clearance[index])
        pick = jax.nn.one_hot(index, n, dtype=problem.x_n.dtype).T  # J, (n, m)
        w = problem.precondition(pick)[index] * valid[:, None] * valid[None, :]
        return Delassus(index, valid, w)

    def map(self, problem: StepProblem, law: Callable, delassus: Delassus, p):
        """One iteration.

        Arguments:
            problem: the step (vertex coordinates).
            law: the splitting's per-vertex contact step on the candidates,
                ``(y (m, 3), index (m,), valid (m,)) -> (touching (m,), stick (m,),
                correction (m, 3), normal (m, 3))`` for sweep positions ``y``.
            delassus: the step's :class:`Delassus`.
            p: ``(n, 1)`` the splitting's sweep diagonal ``P``.

        Returns:
            ``(iteration, cache0)``: ``iteration(x, q, cache) -> (x_new, q_new, residual,
            cache)``, where ``cache`` holds the candidates' contact states ``(m,)`` and the
            Cholesky factor of their matrix (factorised again when a state changes), and
            the empty cache to start from.
        """
        index, valid, w = delassus
        m = index.shape[0]
        dtype = w.dtype
        eye3 = jnp.eye(3, dtype=dtype)
        p_c = p[index]

        def factor(touching, sticking, normal):
            nn = normal[:, :, None] * normal[:, None, :]
            proj = jnp.where(sticking[:, :, None], eye3, jnp.where(touching[:, None, None], nn, 0.0))
            k = w[:, None, :, None] * jnp.einsum("iab,jbc->iajc", proj, proj)
            k = k + jnp.eye(m, dtype=dtype)[:, None, :, None] * (eye3 - proj)[:, :, None, :]
            return jax.scipy.linalg.cholesky(k.reshape(3 * m, 3 * m), lower=True)

        def iteration(x, q, cache):
            _, g, q = problem.evaluate(x, q)
            g_c = g[index] * valid[:, None]
            y_c = x[index] - g_c / p_c
            touching, stick, correction, normal = law(y_c, index, valid)
            sticking = (touching & stick)[:, None]

            def apply(v):  # the projector on the fixed components, vertex by vertex
                along = normal * jnp.sum(normal * v, axis=-1, keepdims=True)
                return jnp.where(sticking, v, jnp.where(touching[:, None], along, 0.0))

            # 0 free, 1 sliding, 2 sticking: the matrix is factorised again when a state
            # changes (normals that turn with the iterate keep the last factorisation, which
            # changes the iteration but not its fixed point)
            state = touching.astype(jnp.int8) + (touching & stick).astype(jnp.int8)
            old, chol = cache
            chol = jax.lax.cond(jnp.all(state == old), lambda: chol, lambda: factor(touching, sticking, normal))
            r = jnp.where(touching[:, None], p_c * correction, 0.0)
            y = x - problem.precondition(g.at[index].add(-g_c))
            kappa = (r - g_c) - apply(r - g_c)
            rhs = apply(y_c + correction - y[index] - w @ kappa)
            mu = apply(jax.scipy.linalg.cho_solve((chol, True), rhs.ravel()).reshape(m, 3))
            delta = (kappa + mu) * valid[:, None]
            x_new = y + problem.precondition(jnp.zeros_like(x).at[index].add(delta))
            others = problem.free * g.at[index].set(0.0)
            residual = jnp.sqrt(jnp.sum(others**2) + jnp.sum(delta**2))
            return x_new, q, residual, (state, chol)

        cache0 = (jnp.full(m, -1, jnp.int8), jnp.zeros((3 * m, 3 * m), dtype))
        return iteration, cache0

    def run(self, iteration: Callable, cache, weight, x0, q0, threshold, max_iter):
        """Iterate from ``(x0, q0)`` with Anderson mixing.

        Arguments:
            iteration, cache: from :meth:`map`.
            weight: ``(n * 3,)`` Anderson weights of the position entries.
            x0, q0: start positions ``(n, 3)`` and rotations.
            threshold: the force residual to reach; max_iter: the step's cap.

        Returns:
            ``(solution, cache)``: the :class:`~softbody.solvers.Solution` of the iterate
            with the smallest residual (its map output), and the last active set and factor.
        """
        def step(x, q, cache):
            x_new, q_new, r, new_cache = iteration(x, q, cache)
            # Contacts made or broken start a new quasi-Newton model, and so does a run of
            # iterations without progress (a history of round-off); a vertex turning
            # between sticking and sliding (at the cone's edge, where both are nearly
            # right) does not.
            return x_new, q_new, r, new_cache, jnp.any((new_cache[0] > 0) != (cache[0] > 0))

        # It stops at the tolerance, at its cap, or after 4 patience spans without progress.
        best_x, best_q, k, best_r, cache = anderson.iterate(
            step, x0, q0, cache, weight=weight, threshold=threshold, cap=jnp.minimum(max_iter, self.max_iter),
            history=self.history, restart=10.0, patience=self.patience)
        return Solution(best_x, best_q, k, k, best_r), cache

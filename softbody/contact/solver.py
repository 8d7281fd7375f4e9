"""The contact solver: implicit-Euler steps with contact and dry friction.

**Rows.** Contact is a set of rows (:class:`softbody._interfaces.Rows`): each keeps a
vertex out of something, with its gap, normal, the velocity of the surface it meets,
friction coefficients and restitution (:class:`softbody._interfaces.Frame`). The scene's
obstacles (signed distance functions, :mod:`softbody.contact.obstacles`) are one generator of rows
(:class:`softbody.contact.obstacles.ObstacleRows`); ``build(rows=...)`` adds others (a plane that
holds a few vertices, ...). Where several rows reach a vertex the solver keeps the deepest;
it sees nothing of the generators but their rows.

**Rows between bodies.** A pair generator (:class:`~softbody._interfaces.PairRows`, e.g.
:class:`softbody.contact.pairs.Touch`) gives rows that couple a vertex with a triangle of another
surface (:class:`~softbody._interfaces.PairFrame`: up to 4 vertices, weights ``(1, -u, -v,
-w)``), chosen once per step. Their forces act on both sides, so they cannot be projected
vertex by vertex: the iterate carries each row's force ``f_r`` (N, on its touching vertex,
world frame), the sweep takes the rows' forces into its right-hand side, and each
iteration updates them by a projected Jacobi step at the new positions (normal part
``f_n + depth / W_r >= 0``, tangential part on the friction cone, ``W_r = sum_a w_a^2 c_a /
P_a`` the row's compliance with each vertex's ``P_a`` shared among its ``c_a`` rows) and
moves the vertices by the change. At a fixed point the forces balance ``grad Phi`` and every
row is complementary (a closed gap with a pushing force, or an open one with none) with
Coulomb's law tangentially, exactly where rows share vertices. See :func:`_pair_update`.
A step whose predicted end lies deep inside another body starts its iteration where its
first contact closes along the predicted motion (:func:`_first_touch`), not at that end.
Rows on rigid parts take several sweeps an iteration, each moving the part; those sweeps
keep the rows' frame (normals, weights) of the sweeps' start and move only the gaps with
the positions. With the frame made again at every sweep a light rigid body's tilt turned
its rows' forces with its faces, and their torque drove the next sweep's tilt: a 2 cm rigid
cube landing at 1 m/s on a held plate rocked by +-0.024 rad from sweep to sweep, its impact
step at the 30000 cap; it now converges in 281 iterations.
With ``Contact(warm_start=True)`` the forces start where the last step left them
(:attr:`softbody._types.State.contact`, a warm start that changes the iterations, not the
fixed point; so do the coordinates' extra rows, the skin forces of bones and rigid
bodies): a soft block resting on a soft slab (tolerance 1e-10) takes 1-5 iterations a step
once at rest, 90 from zero forces; a 2 cm rigid box on it (1e-8) 1-3, 134-400 from zero.

**The contact solver** :class:`Contact` solves each implicit-Euler step
``min Phi(x)`` subject to non-penetration and Coulomb friction with the design's
velocity-space splitting iteration::

    (M + h^2 D) v^{k+1} = f - h^2 (L - D) v^k + xi^k

``A = M/h^2 + L`` is the PD matrix, ``D`` a diagonal splitting (:mod:`softbody.contact.splitting`:
:class:`~softbody.contact.splitting.Naive`: 0, :class:`~softbody.contact.splitting.Diagonal`: ``diag(L)``,
the default :class:`~softbody.contact.splitting.ScaledDiagonal`: ``2 diag(L)``, whose convergence
is proved in its docstring) and ``xi`` the contact impulse, *added* to the right-hand
side. The right-hand side ``f`` is PD's: each iteration first runs PD's local
step at the current iterate (the projections), which gives ``grad Phi``, so that one
iteration in positions form (``x = x_n + h v``) reads::

    y = x^k - P^{-1} grad Phi(x^k),        P = M/h^2 + D           (one splitting sweep)
    x^{k+1}_i = y_i + xi_i / (h P_i)       per vertex, in its contact frame

(``b - (L - D) x = P x - grad Phi`` with ``b = A x - grad Phi`` PD's right-hand side, so
the matrix product cancels). The per-vertex contact step, for a vertex whose sweep
position ``y_i`` lies inside the nearest obstacle (``phi(y_i) < 0``), works on the impulse
``xi_i = h P_i (x_i - y_i)`` that a vertex of "mass" ``h^2 P_i`` needs:

* separating (``phi(y_i) >= 0``): no impulse;
* otherwise cancel the normal momentum: move ``y_i`` back to the surface along the normal
  (to ``phi = h e v_in`` with restitution ``e`` and incoming normal speed ``v_in``);
* stick if the tangential impulse that cancels the tangential motion relative to the
  obstacle fits the static cone (``|xi_t| <= mu_s xi_n``), else slide on the kinetic
  cone's edge (``|xi_t| = mu_k xi_n``, opposing the slip).

At a fixed point ``x^{k+1} = x^k`` the force residual ``grad Phi - r`` (``r = xi / h`` the
contact forces) vanishes, ``r`` lies in the friction cone and every contact vertex is on
the surface: the step's equilibrium. With the projections held fixed and no contact
active, the iteration matrix is ``T = P^{-1} (D - L) = (M + h^2 D)^{-1} h^2 (D - L)``, the
matrix whose spectral radius :func:`softbody.contact.splitting.splitting_spectral_radius` measures.

**The fast iteration.** ``Contact(active_set=ActiveSet())`` first runs
:class:`~softbody.contact.active_set.ActiveSet`, an active-set iteration on the prefactored PD
matrix whose fixed point is this map's, exactly; the map then checks its result in one
evaluation and finishes the step where it stopped short (``StepInfo.fallback``). The
implicit derivative is taken through the fast map then (see
:mod:`softbody.contact.active_set`). It is not the default yet: see that module for what it
costs and where it falls short. Scenes with a skeleton cannot use it (reduced
coordinates have no vertex Delassus operator yet).

Scheme, convergence criterion and costs of the splitting iteration:

* One iteration = one local step (``problem.evaluate``) + one diagonal sweep + the
  per-vertex contact step; no linear solve. The iterate with the smallest residual is
  returned after the contact step, so every vertex ends on or outside every obstacle
  (exactly for planes, spheres, boxes and capsules; to second order in the step for
  height fields; a vertex wedged between two obstacles is projected out of the deeper
  one only).
* Convergence: ``|grad Phi(x^k) - r^k| = |P (x^{k+1} - x^k)| <= threshold`` over the free
  degrees of freedom, the core's force tolerance (``Options.tol``/``atol``); at most
  ``max_iter`` iterations. ``Solution.gnorm`` is that residual.
* Anderson acceleration (``history`` > 0, :mod:`softbody.contact.anderson`) of the fixed-point
  map, weighted by ``sqrt(P)``, with restarts when the residual grows tenfold over the best
  one; the plain map is contracting (see :class:`~softbody.contact.splitting.ScaledDiagonal`), the
  acceleration is a safeguarded heuristic on top. ``history=0`` runs the plain splitting
  iteration of the design. To a relative residual of 1e-6 on the first step of a resting
  342-vertex gmsh cube (soft ``E`` = 1e4 Pa, ``h`` = 1/30 s) the plain iteration
  contracts by 0.9992 per iteration (over 10000 iterations); Anderson with history 5 took
  2318, 10: 1499, 20: 458 and 30 (the default): 261. Over the benchmark's 96 cases the
  default converged in all, in 4-1384 iterations (median 150; the most for the stiff
  1419-vertex quadruped at ``h`` = 1/30 s).
* Scenes pay for contact only when they touch: a step where no vertex of ``x_n + h v_n``
  is within ``margin`` of an obstacle runs the step's contact-free solver (L-BFGS with the prefactored
  PD matrix); if that result penetrates an obstacle the step is redone with contact.
  Contact masks are per-vertex booleans, so shapes are fixed under ``jit``/``vmap``.

**Gradients through contact.** The solve is never differentiated. The positions it
returns, a fixed point ``x* = F(x*; theta)`` of the map above, carry the implicit
derivative of :func:`softbody.contact.fixed_point.fixed_point` (with the contact state of ``x*``
held fixed), whose linear system is solved by the same Anderson iteration; see
:mod:`softbody.contact.fixed_point` for what it sees and what it costs. ``theta`` is everything
the step depends on: material and actuator parameters, the state, obstacle poses and
friction.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import Capabilities, ContactSweep, Coordinates, PairFrame
from softbody.contact import anderson
from softbody.contact.active_set import ActiveSet
from softbody.contact.fixed_point import closure_convert, fixed_point
from softbody.contact.law import (_FAR, CONTACT_STATES, SLIDING_SPEED, _contact_state, _contact_step, _pair_update,
                                  _positions, _sliding, _spread, _tangential)
from softbody.contact.obstacles import norm
from softbody.contact.rows import _frames, _Pairs
from softbody.contact.splitting import Naive, ScaledDiagonal, Splitting
from softbody.solvers import NonlinearSolver, Solution, StepProblem

__all__ = ["CONTACT_STATES", "Contact", "ContactMap"]


# --------------------------------------------------------------------------------------
# The contact solver
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Contact:
    """Implicit-Euler steps with contact and dry friction by the splitting iteration
    (optionally after an active-set iteration on the prefactored matrix,
    :mod:`softbody.contact.active_set`).

    The contact constraint's part of a composed step (:class:`~softbody.solvers.Step`),
    chosen by :func:`~softbody.model.build` for a scene with contact rows, obstacles or others (set
    ``Options(contact=Contact(...))`` to change its settings). See the module docstring for
    the scheme; in short, each iteration is PD's local step, one sweep of
    ``(M/h^2 + D) x^{k+1} = b - (L - D) x^k`` and the per-vertex contact step, accelerated
    by Anderson mixing, until ``|grad Phi - r| <= threshold``. The step's coordinates
    decide which unknowns the sweep moves (:meth:`~softbody._interfaces.Coordinates.contact_sweep`);
    steps that touch nothing run the step's contact-free solver in them.

    Attributes:
        splitting: the :class:`~softbody.contact.splitting.Splitting` ``D`` (default
            :class:`~softbody.contact.splitting.ScaledDiagonal`, whose convergence is proved;
            :class:`~softbody.contact.splitting.Diagonal` and :class:`~softbody.contact.splitting.Naive`
            for studies).
        active_set: ``None`` (default) for the splitting iteration alone, or the fast
            iteration to run before it (:class:`~softbody.contact.active_set.ActiveSet`; not in
            scenes with a skeleton).
        history: Anderson history length (0: the plain splitting iteration).
        restart: Anderson restarts when the residual exceeds ``restart`` times the best
            one so far (> 1).
        margin: a step runs the contact-free solver (no contact work) when every free
            vertex of ``x_n`` and ``x_n + h v_n`` is farther than ``margin`` (m) from every
            obstacle; if its result penetrates an obstacle the step is redone with contact.
        adjoint_tol, adjoint_max_iter: relative tolerance and iteration cap of the linear
            solve of the implicit derivative (Anderson-accelerated, like the forward solve).
            ``adjoint_tol=None`` (default) follows the forward tolerance
            (:attr:`softbody._types.Options.adjoint_tol`: ``Options.tol`` clipped to
            [1e-10, 1e-5]; ``build`` resolves it). The adjoint iterates about as slowly as the
            forward solve: on the first 60 steps of ``examples/grasp.py``'s soft cube (tol
            1e-4) a gradient cost 14.0x the forward run at 1e-10 (the default before) and
            4.4x at 1e-5 (adjoint iterations per step: median 856 and 342), the two
            gradients 2.3e-5 apart relative (one core, 2026-12-07).
        blocks: ``((start, stop), ...)`` vertex ranges whose Anderson coefficients are
            separate (:func:`softbody.contact.anderson.mix`), or ``()`` (default) for the
            scene's own: one per body, bodies that rows between bodies couple sharing one
            (:attr:`softbody._types.Model.contact_blocks`), so that bodies that do not touch
            each other converge as each would alone; in a step with pair rows the forward
            iteration joins only the bodies that the step's rows join (:func:`_touching_groups`).
        warm_start: start each step's force rows from those the last step left
            (:attr:`softbody._types.State.contact`) instead of zero (default ``False``). It
            changes the iterations, not the fixed point, but where a step has several (dry
            friction, rows chosen again after a penetrating result) it can pick another:
            ``examples/pile_push.py``'s gradient run, which reaches its threshold in 12
            simulations without it, stalled at 62 mm^2 with it, its pushes' impact steps
            passing surfaces through each other (``RESULTS.tunnelled``).
        rigid_floor: the sweep diagonal ``P`` of a free vertex without elastic stiffness (a
            rigid body's: its ``P`` is its share of the body's inertia alone) is at least
            ``rigid_floor`` times the median ``P`` of the free vertices with stiffness (default
            0.01; 0: the inertia alone). A larger ``D`` on some vertices keeps the splitting's
            convergence proof (see :class:`~softbody.contact.splitting.ScaledDiagonal`) and
            does not move the fixed point; it makes a light rigid body as stiff in the
            iteration as the soft bodies that press on it. With the inertia alone, the pair
            rows between a soft body and a light rigid body under it (a box on the ground,
            a box between two soft fingers) see the rigid side as ~1000x more compliant than
            the soft vertex, and the iteration spends hundreds of iterations a step trading
            forces between them: a 2 cm soft cube resting on a 4 g rigid cube took 200-450
            iterations a step, 51-68 at 0.01; at 50 kg/m^3 most steps stopped at the cap, none
            at 0.01; ``examples/grasp.py``'s rigid box (30 kPa, 150 steps) had six steps at the
            6000 cap, every step converges at 0.01 (median 170 iterations, max 367; the
            rollout 218 s once compiled, one core: 10 ms an iteration, 3.4 ms for the soft
            cube's, the rigid part's 30 pair sweeps an iteration). Larger floors slow a rigid
            body's own motion in the iteration (a rigid cube landing on a soft one: one
            impact step at the 3000 cap at 1; ``softbody bench many-bodies``' mixed 16
            cubes: the lower layer's landing on the ground at the cap at 0.01).

    The PD matrix is prefactored with the true volume weight (``volume_weight = 1``):
    its diagonal defines ``P``.

    Raises:
        ValueError: a bad attribute (negative history, ``restart <= 1``, ...).
        ObstacleError: (in ``run``) an object in the scene's obstacles that is not an
            obstacle, or parameters that do not match it (a row generator's ``check``).
    """

    capabilities = Capabilities(
        refuses={"partly held vertices": "holds vertices in all three components only (its contact step projects whole "
                                         "vertices)"},
        instead="model the support as an obstacle (softbody.contact.obstacles.Plane) or clamp the vertices fully")

    splitting: Splitting = field(default_factory=ScaledDiagonal)
    active_set: ActiveSet | None = None
    history: int = 30
    restart: float = 10.0
    margin: float = 1e-6
    adjoint_tol: float | None = None
    adjoint_max_iter: int = 20000
    blocks: tuple = ()
    warm_start: bool = False
    rigid_floor: float = 0.01

    def __post_init__(self):
        if not isinstance(self.splitting, Splitting):
            raise ValueError(
                f"Contact.splitting must be a Splitting (Naive(), Diagonal(), ScaledDiagonal()), "
                f"got {self.splitting!r}"
            )
        if self.active_set is not None and not isinstance(self.active_set, ActiveSet):
            raise ValueError(f"Contact.active_set must be an ActiveSet or None, got {self.active_set!r}")
        if int(self.history) != self.history or self.history < 0:
            raise ValueError(f"Contact.history must be an integer >= 0, got {self.history!r}")
        if not self.restart > 1:
            raise ValueError(f"Contact.restart must exceed 1, got {self.restart!r}")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"Contact.margin must be a distance >= 0 (m), got {self.margin!r}")
        if not (math.isfinite(self.rigid_floor) and self.rigid_floor >= 0):
            raise ValueError(f"Contact.rigid_floor must be a number >= 0 (a fraction of the stiff vertices' median "
                             f"sweep diagonal; 0 turns it off), got {self.rigid_floor!r}")
        if not isinstance(self.warm_start, bool):
            raise ValueError(f"Contact.warm_start must be True or False, got {self.warm_start!r}")
        if not ((self.adjoint_tol is None or self.adjoint_tol > 0) and int(self.adjoint_max_iter) >= 1):
            raise ValueError(f"Contact.adjoint_tol must be None (follow Options.tol) or > 0 and adjoint_max_iter "
                             f">= 1, got {self.adjoint_tol!r} and {self.adjoint_max_iter!r}")
        blocks = tuple(tuple(int(i) for i in b) for b in self.blocks)
        if any(len(b) != 2 or not 0 <= b[0] < b[1] for b in blocks) or (blocks and blocks[0][0] != 0) or any(
                a[1] != b[0] for a, b in zip(blocks, blocks[1:])):
            raise ValueError(f"Contact.blocks must be consecutive vertex ranges (start, stop) from 0, got {self.blocks!r}")
        object.__setattr__(self, "blocks", blocks)

    def _labels(self, blocks, owners: np.ndarray, pairs: _Pairs) -> np.ndarray | None:
        """The Anderson block of each flattened entry of the iterate ``(n + e + m, 3)``, or
        ``None`` for one block: each vertex's from :attr:`blocks` where set, else the
        scene's ``blocks`` (``(n,)``, :attr:`softbody._types.Model.contact_blocks`); an extra
        row in its vertex's block, a pair row in its generator's (whose vertices share one)."""
        if self.blocks:
            vertex = np.repeat(np.arange(len(self.blocks)), [b - a for a, b in self.blocks])
        elif blocks is not None:
            vertex = np.asarray(blocks)
        else:
            return None
        rows = [np.full(generator.size, vertex[generator.vertices()[0]]) for generator, _, _ in pairs.rows]
        return np.repeat(np.concatenate([vertex, vertex[owners], *rows]), 3)

    def run(self, problem: StepProblem, coordinates: Coordinates, solver: NonlinearSolver, x0, q0, threshold,
            max_iter: int) -> Solution:
        """Solve one step with contact.

        The solve itself is never differentiated: the positions it returns carry the
        implicit derivative of the fixed point (see the module docstring), in forward and
        reverse mode alike.

        Arguments:
            problem: the step (:class:`~softbody.solvers.StepProblem`).
            coordinates: the step's unknowns; solver: its contact-free iteration.
            x0, q0: ``(n, 3)`` start positions, ``(4, t)`` their rotations.
            threshold: the force residual to reach; max_iter: the iteration cap (of the
                splitting iteration; the fast iteration before it has its own,
                ``ActiveSet.max_iter``).

        Returns:
            :class:`~softbody.solvers.Solution` with the positions after the last contact
            step (non-penetrating), the rotations of the local step, the iteration and
            local-step counts, and the force residual ``|grad Phi - r|``.

        Raises:
            ObstacleError, ValueError: the scene's obstacles or their parameters are
                malformed (each row generator's ``check``).
            ValueError: the Naive splitting in a static solve (nothing to invert).
        """
        for generator, params in problem.rows:
            generator.check(params)
        if problem.dt == 0 and isinstance(self.splitting, Naive):
            raise ValueError(
                "the Naive splitting has nothing to invert in a static solve (no mass): "
                "use ScaledDiagonal() or Diagonal()"
            )
        pairs = _Pairs.select(problem, x0)
        iteration = self.map(problem, coordinates, pairs)
        n = x0.shape[0]
        free = problem.free[:, 0] > 0
        vertices = jnp.arange(n)

        def distance(x, t):  # per vertex, to the vertex rows
            return jnp.where(free, _frames(problem.rows, x, vertices, t).phi, jnp.inf)

        start = jax.lax.stop_gradient(
            jnp.minimum(distance(problem.x_n, problem.time), distance(x0, problem.time + problem.dt)))
        fast = None
        if self.active_set is not None:
            delassus = jax.lax.stop_gradient(self.active_set.delassus(problem, start))
            fast = self.active_set.map(problem, self._law(problem), delassus, self._sweep_diagonal(problem))
        solve, consts = jax.closure_convert(
            lambda x0, q0: self._solve(
                problem, coordinates, solver, iteration, fast, start, distance, x0, q0, threshold, max_iter
            ),
            x0,
            q0,
        )
        sol, cache, selection = solve(*jax.lax.stop_gradient((x0, q0, *consts)))
        if pairs.size:  # the rows the solve ended with
            pairs = pairs.chosen(selection)
            iteration = self.map(problem, coordinates, pairs)
            crossed, search_overflow = pairs.crossed(problem.x_n, _positions(sol.x, n))
            # a crossing search that overflowed may have missed crossings: where it found
            # none that is an overflow, where it found some the step tunnelled anyway
            sol = sol._replace(overflow=pairs.overflow | (search_overflow & (crossed == 0)), tunnelled=crossed)
        fixed_point_map = iteration.apply
        if fast is None:
            position = lambda x, q: fixed_point_map(x, q)[0]  # noqa: E731
        else:
            # The fast map carries the derivative (its linearisation contracts like its
            # iteration) unless the splitting finished the step: then a vertex outside the
            # candidates may touch, and only the splitting map sees it.
            def position(x, q):
                return jax.lax.cond(sol.fallback, lambda: fixed_point_map(x, q)[0],
                                    lambda: fast[0](x, q, cache)[0])
        position, consts = closure_convert(position, sol.x, sol.q)
        linear_solve = functools.partial(
            anderson.linear_solve,
            history=max(int(self.history), 1),
            rtol=self.adjoint_tol,
            max_iter=self.adjoint_max_iter,
            labels=iteration.labels,
        )
        forces = jax.lax.stop_gradient(sol.x[n:]) if sol.x.shape[0] > n else None
        return sol._replace(x=_positions(fixed_point(position, linear_solve, sol.x, sol.q, *consts), n), forces=forces)

    def map(self, problem: StepProblem, coordinates: Coordinates, pairs: _Pairs = _Pairs(())) -> "ContactMap":
        """The fixed-point map of one iteration, on the iterate ``X`` ``(n + e + m, 3)``: the
        positions, the coordinates' extra rows (see
        :class:`~softbody._interfaces.ContactSweep`) and the forces of the step's ``m`` pair
        rows (N, on each row's touching vertex; see :func:`_pair_update`).

        Arguments:
            problem: the step; coordinates: its unknowns; pairs: the step's pair rows.

        Returns:
            A :class:`ContactMap`.
        """
        h = problem.dt
        p = self._sweep_diagonal(problem)
        parts = coordinates.contact_sweep(problem, p, self._law(problem))
        touching, n, t_end = parts.touching, problem.x_n.shape[0], problem.time + h
        vertices = jnp.arange(n)
        extra, m = len(parts.owners), pairs.size
        rows = n + extra

        if parts.rigid is None:  # every vertex moves alone, with compliance 1 / P
            loaded, body = touching, np.arange(n)

            def compliance(count):
                return touching * count / p
        else:
            loaded = problem.free
            c, body = parts.rigid.compliance, np.asarray(parts.rigid.body)

            def compliance(count):
                return c * count
        parts_count = int(body.max()) + 1 if n else 0
        start = pairs.frame(problem.x_n) if m else None  # the rows at the step's start
        sliding = _sliding(start, problem.v_n) if m else None
        earlier = np.tril(np.ones((4, 4), bool), -1)  # [j, i]: slot i comes before slot j

        def split(pair):
            """``(n, 1)``: each vertex's compliance times the number of live rows on its part
            (mass splitting; a row counts once per part, however many of its vertices lie on it)."""
            live = _acting(pair)
            label = jnp.asarray(body)[pair.vertices]
            repeat = jnp.any((label[:, :, None] == label[:, None, :]) & live[:, None, :] & earlier, axis=2)
            once = (live & ~repeat).ravel().astype(pair.phi.dtype)
            count = jnp.zeros(parts_count, pair.phi.dtype).at[label.ravel()].add(once)
            return compliance(jnp.maximum(count[body], 1.0)[:, None])

        def apply(x, q):
            x, force = (x[:rows], x[rows:]) if m else (x, None)
            placed, aux = parts.place(x)
            _, g, q = problem.evaluate(placed, q)
            if m:  # the pair rows' forces join the sweep's right-hand side (rigid parts' rows too)
                g = g - loaded * _spread(pairs.frame(_positions(placed, n)), force, n)
            y = placed - g / p  # one splitting sweep
            frame = _frames(problem.rows, y, vertices, t_end)
            x_new = jnp.where(
                touching > 0, _contact_step(y, problem.x_n, problem.v_n, h, frame, touching), placed
            )
            x_new, rest = parts.sweep(x, x_new, g, aux)
            if m:  # the pair rows' forces, updated at the new positions, move them
                respond = None if parts.rigid is None else parts.rigid.respond(aux)

                def update(carry, _, start):
                    """One update of the rows' forces and the positions' response to it, in the
                    rows' frame ``start`` ``(frame, z0)`` where the sweeps began, each gap moved
                    with the positions since (the first update's move is zero)."""
                    x_new, force = carry
                    z = _positions(x_new, n)
                    frame, z0 = start
                    shift = jnp.sum(frame.weights[:, :, None] * (z - z0)[frame.vertices], axis=1)
                    moved = jnp.sum(frame.normal * shift, axis=-1)
                    pair = frame._replace(phi=jnp.where(frame.phi < _FAR, frame.phi + moved, frame.phi))
                    force_new = _pair_update(pair, force, z, problem.x_n, problem.v_n, h, split(pair), sliding)
                    delta = _spread(pair, force_new - force, n)
                    if parts.rigid is None:
                        return (x_new.at[:n].add(touching * delta / p), force_new), None
                    return (respond(x_new, delta), force_new), None

                z0 = _positions(x_new, n)
                update = functools.partial(update, start=(pairs.frame(z0), z0))
                if parts.rigid is None:
                    (x_new, force_new), _ = update((x_new, force), None)
                else:  # rows on rigid parts couple through the part's motion: several sweeps
                    before = x_new[n:]  # the extra rows' forces, which the sweeps may relax too
                    (x_new, force_new), _ = jax.lax.scan(update, (x_new, force), None, length=parts.rigid.sweeps)
                    rest = jnp.concatenate([rest, (parts.scale * (x_new[n:] - before)).ravel()])
                rest = jnp.concatenate([rest, (force_new - force).ravel()])
                x_new = jnp.concatenate([x_new, force_new])
            residual = norm(jnp.concatenate([(touching * p * (_positions(x_new, n) - placed)).ravel(), rest]))
            return x_new, q, residual  # = |grad Phi(x) - r|

        weight = jnp.broadcast_to(jnp.sqrt(p) * problem.free, problem.x_n.shape).ravel()
        if extra:
            weight = jnp.concatenate([weight, jnp.broadcast_to(jnp.sqrt(parts.scale), (extra, 3)).ravel()])
        if m:  # a force row weighs as its touching vertex's compliance (force / sqrt(P): sqrt(N m))
            touching_vertex = start.vertices[:, 0]
            weight = jnp.concatenate([weight, jnp.repeat(1.0 / jnp.sqrt(p[touching_vertex, 0]), 3)])

        def lift(x, forces=None):
            if not extra + m:
                return x
            return jnp.concatenate([x, jnp.zeros((extra + m, 3), x.dtype) if forces is None else forces])

        labels = self._labels(problem.blocks, parts.owners, pairs)
        joined = (start, problem.bodies, parts.owners) if m and not self.blocks and problem.bodies is not None else None
        return ContactMap(apply, weight, labels, lift, parts, pairs, joined)

    def _law(self, problem: StepProblem):
        """The per-vertex contact step on some vertices, as :class:`~softbody.contact.active_set.ActiveSet` takes it."""
        h = problem.dt
        t_end = problem.time + h
        # one cone a step for kinetic=True: the kinetic one where a vertex slides at the step's
        # start (law.SLIDING_SPEED), measured once, in the start's frame (the iterate's normal
        # would let a vertex change class within the step)
        start = _frames(problem.rows, problem.x_n, jnp.arange(problem.x_n.shape[0]), problem.time)
        moving = norm(_tangential(problem.v_n - start.velocity, start.normal)) > SLIDING_SPEED

        def law(y, index, valid, kinetic=False):
            frame = _frames(problem.rows, y, index, t_end)
            if kinetic:
                mu = jnp.where(moving[index], frame.mu_k, frame.mu_s)
                frame = frame._replace(mu_s=mu, mu_k=mu)
            touching, stick, correction = _contact_state(
                y, problem.x_n[index], problem.v_n[index], h, frame, valid[:, None].astype(y.dtype))
            return touching, stick, correction, frame[1]

        return law

    def _sweep_diagonal(self, problem: StepProblem):
        """``P = M/h^2 + D`` ``(n, 1)`` of the splitting sweep (1 on fixed vertices, which never
        move; a scene with contact holds vertices in all three components or none)."""
        h = problem.dt
        inertia = problem.mass / h**2 if h > 0 else jnp.zeros_like(problem.mass)
        stiffness = jnp.maximum(problem.diagonal - inertia, 0.0)
        p = inertia + self.splitting.diagonal(stiffness)
        free = problem.free > 0
        if self.rigid_floor:  # vertices without stiffness (a rigid body's) sweep no lighter than this
            stiff = free & (stiffness > 0)
            level = jnp.nanmedian(jnp.where(stiff, p, jnp.nan))
            floor = jnp.where(jnp.any(stiff), self.rigid_floor * level, 0.0)
            p = jnp.where(free & ~stiff, jnp.maximum(p, floor), p)
        return jnp.where(free, p, 1.0)

    def _solve(
        self, problem: StepProblem, coordinates, solver, iteration, fast, start, distance, x0, q0,
        threshold, max_iter: int
    ):
        """The forward solve: the free-step shortcut, else the contact iteration.

        Returns ``(solution, cache, selection)``: the solution on the iterate ``(n + e + m,
        3)``, the cache of the fast iteration's last active set (``None`` without one) and
        the selection of the pair rows it solved with (``()`` without pair rows)."""

        t_end = problem.time + problem.dt
        n = x0.shape[0]
        pairs = iteration.pairs
        near = jnp.min(start)
        if pairs.size:
            near = jnp.minimum(near, jnp.minimum(pairs.gap(problem.x_n), pairs.gap(x0)))
        near = near <= self.margin
        no = jnp.asarray(False)
        cache0 = None if fast is None else fast[1]
        # the force rows start where the last step left them (State.contact), if asked
        lifted = iteration.lift(x0, problem.forces0 if self.warm_start else None)

        def contact():
            if fast is None:
                return self._iterate(iteration, lifted, q0, threshold, max_iter)._replace(fallback=no), cache0
            quick, cache = self.active_set.run(fast[0], fast[1], iteration.weight, x0, q0, threshold, max_iter)
            # The splitting map checks the result in one evaluation (its fixed point is the
            # same) and finishes the step where a vertex outside the candidates touches. Where
            # the fast iteration stopped short, the splitting starts afresh from the step's
            # start (a stalled iterate can lie farther from the solution), with a budget of
            # its own: the step's cap.
            done = quick.gnorm <= threshold
            check = self._iterate(iteration, jnp.where(done, quick.x, x0), jnp.where(done, quick.q, q0),
                                  threshold, max_iter)
            return check._replace(iterations=check.iterations + quick.iterations,
                                  evaluations=check.evaluations + quick.evaluations,
                                  fallback=~done | (check.iterations > 1)), cache

        def free_step():  # the solver sees no rows: it is contact-free by definition
            sol = solver.run(coordinates.chart(problem._replace(rows=())), x0, q0, threshold, max_iter)
            return sol._replace(x=iteration.lift(sol.x), fallback=no), cache0

        def skipped():
            zero = jnp.asarray(0)
            return Solution(lifted, q0, zero, zero, jnp.asarray(jnp.inf, x0.dtype), no), cache0

        # Each branch is traced once: the contact iteration runs when the start is near an
        # obstacle or when the free step's result penetrates one.
        sol, cache = jax.lax.cond(near, skipped, free_step)
        x1 = _positions(sol.x, n)
        if not pairs.size:
            def redo():
                again, cache = contact()
                return again._replace(evaluations=again.evaluations + sol.evaluations), cache

            return *jax.lax.cond(near | (jnp.min(distance(x1, t_end)) < 0), redo, lambda: (sol, cache)), ()

        # Pair rows: those of the free step's end where it ran, else of the predicted end
        reached = _Pairs.select(problem, x1)
        selection = jax.tree.map(lambda a, b: jnp.where(near, a, b), pairs.selection, reached.selection)
        penetrates = (jnp.min(distance(x1, t_end)) < 0) | (reached.gap(x1) < 0)

        def redo_pairs():
            first = _first_touch(pairs.chosen(selection), problem, x0, self.margin)
            again, selection_used = self._iterate_pairs(problem, coordinates, pairs, selection,
                                                        lifted.at[:n].set(first), q0, threshold, max_iter)
            return again._replace(evaluations=again.evaluations + sol.evaluations), selection_used

        sol, selection = jax.lax.cond(near | penetrates, redo_pairs, lambda: (sol, selection))
        return sol, cache, selection

    def _iterate_pairs(self, problem, coordinates, pairs: _Pairs, selection, lifted, q0, threshold, max_iter: int):
        """The contact iteration with pair rows from the iterate ``lifted`` ``(n + e + m, 3)``:
        solved with the rows of ``selection``; if its result meets rows it did not have (a
        vertex inside a triangle that it was not paired with at the start), solved once more
        from the start with the rows of its result. Returns ``(solution, the selection of
        its rows)``."""
        n, zero = problem.x_n.shape[0], jnp.asarray(0)

        def attempt(carry):
            selection, previous, k, _ = carry
            sol = self._iterate(self.map(problem, coordinates, pairs.chosen(selection)), lifted, q0, threshold,
                                max_iter)
            sol = sol._replace(iterations=sol.iterations + previous.iterations,
                               evaluations=sol.evaluations + previous.evaluations)
            x1 = _positions(sol.x, n)
            reached = _Pairs.select(problem, x1)
            again = (reached.gap(x1) < -self.margin) & (k == 0)  # a row it did not have is penetrated
            return jax.tree.map(lambda a, b: jnp.where(again, a, b), reached.selection, selection), sol, k + 1, again

        start = Solution(lifted, q0, zero, zero, jnp.asarray(jnp.inf, lifted.dtype), jnp.asarray(False))
        selection, sol, _, _ = jax.lax.while_loop(lambda c: (c[2] == 0) | c[3], attempt,
                                                  (selection, start, zero, jnp.asarray(False)))
        return sol, selection

    def _iterate(self, iteration: "ContactMap", x0, q0, threshold, max_iter: int) -> Solution:
        """Anderson-accelerated fixed-point iteration of ``iteration`` from the iterate ``x0``
        ``(n + e, 3)``; returns the best iterate's map output."""
        def step(x, q, cache):
            return *iteration.apply(x, q), cache, None

        best_x, best_q, k, best_r, _ = anderson.iterate(
            step, x0, q0, weight=iteration.weight, threshold=threshold, cap=max_iter, history=self.history,
            restart=self.restart, **iteration.mixing)
        return Solution(best_x, best_q, k, k, best_r)


def _first_touch(pairs: _Pairs, problem: StepProblem, x_end, margin: float):
    """The contact iteration's first positions ``(n, 3)`` in a step with pair rows.

    The rows predicted to pass the other surface (their gaps ``a`` at the step's start
    ``x_n`` and ``b`` at its predicted end ``x_end``, ``b < a`` and ``b`` below minus the rows'
    thickness, :meth:`~softbody._interfaces.PairRows.contact_distance`, or ``margin`` if larger)
    close at the fraction ``t = a / (a - b)`` of the step (gaps interpolated linearly; 0 for
    a row closed at the start). Each body's free vertices start at ``x_n + t (x_end - x_n)`` with
    the smallest ``t`` of the rows it takes part in (``problem.bodies``; the whole scene's
    smallest without them): where its first contact of the step closes, not deep inside
    the other body. A body without such rows (in flight, resting, sliding, settling onto
    another) starts at ``x_end`` itself, bit for bit as before.

    Why: the pair rows' forces see each vertex through its sweep compliance ``1 / P``,
    which a stiff body's elasticity dominates. From an end deep inside another body the
    first updates push with forces that move one vertex against its neighbours (about
    1000x what stopping the body needs), and the iteration spends its budget bringing them
    down. From where the body first touches, the forces grow from zero to the impact's, as
    for a resting contact. A soft 2 cm cube (E = 1e6 Pa) thrown at a held 5 mm plate at
    ``dt = 1/60`` s, friction 0.5: at 10 m/s (its end predicted 8 cm beyond the plate) the
    impact step converges in 1241 iterations, against none in 30000 from the predicted end;
    at 1 m/s in 185 and 155 (the impact and the step after it), against a stall at the
    3000 cap.
    """
    x_n = problem.x_n
    start, end = pairs.frame(x_n), pairs.frame(x_end)
    a, b = start.phi, end.phi
    depth = jnp.concatenate([jnp.full(generator.size, jnp.maximum(generator.contact_distance(params), margin))
                             for generator, params, _ in pairs.rows])
    entering = (b < -depth) & (a > b) & (a < _FAR)
    t = jnp.where(entering, jnp.clip(a / jnp.where(entering, a - b, 1.0), 0.0, 1.0), 1.0)  # (m,)
    if problem.bodies is None:
        t = jnp.min(t)
    else:  # per body: the smallest t of the rows with a vertex on it
        bodies = np.asarray(problem.bodies)
        label = jnp.asarray(bodies)
        on = jnp.where(start.weights != 0, t[:, None], 1.0)  # (m, 4)
        t = jnp.ones(int(bodies.max()) + 1, x_n.dtype).at[label[start.vertices]].min(on)[label][:, None]
    return jnp.where((problem.free > 0) & (t < 1.0), x_n + t * (x_end - x_n), x_end)


def _acting(frame: PairFrame):
    """``(m, 4)`` bool: the slots of rows that are there (a finite gap) on which the row acts
    (a nonzero weight)."""
    return (frame.phi < _FAR)[:, None] & (frame.weights != 0)


def _touching_groups(start: PairFrame, bodies, owners: np.ndarray):
    """The Anderson blocks of the forward iteration in a step with pair rows: the bodies
    that the step's rows join (``start``, the rows' frame at the step's start: a row joins
    the bodies of its vertices), each group of them one block.

    Returns ``(labels, count)``: ``labels`` ``(3 (n + e + m),)`` traced ints, the group of
    each flattened entry of the iterate (a group is named by its smallest body; an extra row
    in its vertex's, a pair row in its touching vertex's), and ``count``, the number of
    bodies (static).

    Why not :attr:`softbody._types.Model.contact_blocks`, which joins every body that a row
    generator names: one generator over a pile of separate stacks then mixes them all with
    one set of coefficients, and a stack that has converged slows the others. The 16 cubes
    of ``softbody bench many-bodies``' soft-and-rigid scene (eight separate stacks of two
    under one :class:`~softbody.contact.pairs.Touch`, 30 steps): with one block, every step
    from the upper layer's landing (step 5) on stopped at the iteration cap (5 of 30 steps
    succeeded, 359 s of CPU); with these groups 28 of 30 succeed (steps 5 and 15 at the cap;
    median 578 iterations; 145 s). The implicit derivative's linear solve keeps the static
    blocks (:attr:`ContactMap.labels`).
    """
    body = np.asarray(bodies)
    count = int(body.max()) + 1
    live = _acting(start)
    row_bodies = jnp.asarray(body)[start.vertices]  # (m, 4)

    def join(carry):
        label, _ = carry
        low = jnp.min(jnp.where(live, label[row_bodies], count), axis=1)  # (m,) each row's smallest
        new = label.at[row_bodies.ravel()].min(jnp.where(live, low[:, None], count).ravel())
        new = new[new]  # a body's label is a body whose own label is no larger
        return new, jnp.any(new != label)

    label, _ = jax.lax.while_loop(lambda c: c[1], join, (jnp.arange(count), jnp.asarray(True)))
    vertex = label[jnp.asarray(body)]
    entries = jnp.concatenate([vertex, vertex[jnp.asarray(owners, int)], vertex[start.vertices[:, 0]]])
    return jnp.repeat(entries, 3), count


class ContactMap(NamedTuple):
    """One iteration of the contact solver (:meth:`Contact.map`).

    Attributes:
        apply: ``(X, q) -> (X_new, q_new, |grad Phi(x) - r|)`` on the iterate ``X``
            ``(n + e, 3)``.
        weight: ``(3 (n + e),)`` Anderson weights: ``sqrt(P)`` on the positions (zero on
            fixed vertices), ``sqrt(scale)`` on the extra rows.
        labels: the Anderson block of each flattened entry (static), or ``None``.
        lift: ``(x (n, 3), forces=None) -> X``: positions with the force rows ``forces``
            ``(e + m, 3)`` (zero where ``None``).
        parts: the coordinates' :class:`~softbody._interfaces.ContactSweep`.
        pairs: the step's pair rows (their selection).
        joined: what :func:`_touching_groups` finds the forward iteration's Anderson blocks
            from (the pair rows' frame at the step's start, each vertex's body, the extra
            rows' owners), or ``None``: ``labels``. Read only by :attr:`mixing`, so the maps
            built for the implicit derivative do not find them.
    """

    apply: Callable
    weight: jax.Array
    labels: np.ndarray | None
    lift: Callable
    parts: ContactSweep
    pairs: _Pairs = _Pairs(())
    joined: tuple | None = None

    @property
    def mixing(self) -> dict:
        """The forward iteration's Anderson blocks, as :func:`softbody.contact.anderson.iterate`
        takes them (the implicit derivative's linear solve keeps the static :attr:`labels`)."""
        if self.joined is None:
            return {"labels": self.labels}
        labels, count = _touching_groups(*self.joined)
        return {"labels": labels, "blocks": count}

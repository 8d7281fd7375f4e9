"""Nonlinear iterations for one implicit step: plain local-global PD and L-BFGS.

Both minimise the step objective ``Phi(x)`` described by a :class:`StepProblem`, chiefly
two callables:

* ``evaluate(x, q) -> (phi, g, q)``: the objective, its gradient ``(n, 3)`` (zero on fixed
  vertices) and the rotations of ``x`` (warm-started from ``q``). This is PD's local step.
* ``precondition(g) -> A^-1 g``: the global step with the prefactored PD matrix ``A``.

Plain PD is ``x <- x - A^-1 g(x)``: the local-global iteration written as a preconditioned
gradient step; with exact projections it decreases ``Phi`` monotonically. L-BFGS (Liu et
al. 2017, the forward solver DiffPD uses) takes ``A`` as its initial Hessian, so its first
step is a PD step, and adds curvature from the last ``history`` steps; an Armijo
backtracking line search keeps it a descent method, and when the search fails it falls
back to the plain PD step, which always descends.

Both are one loop, :func:`descend`, written against a chart
(:class:`~softbody._interfaces.Chart`: a point, the gradient as a tangent, the
preconditioner, a move along a tangent), so that the same L-BFGS and the same
local-global run in plain vertex coordinates and in a skeleton's reduced coordinates
(which backtrack by halving before giving up on a step: joint servos are not in the PD
matrix). Each solver is a small frozen dataclass (static: changing it recompiles) with
``run(chart, x0, q0, threshold, max_iter, unrolled=False) -> Solution``.

**The composed step.** :func:`softbody.model.build` composes each scene's :class:`Step`
from three parts: the coordinates (:class:`Vertices` here, or a skeleton's
:class:`softbody.skeleton.Reduced`), the contact constraint
(:class:`softbody.contact.Contact` where the scene has contact rows: obstacles or other
row generators) and the solver chosen in
``Options(solver=...)``. The coordinates run the solver (vertex coordinates run it as it
is; reduced coordinates hand it their chart); the contact
constraint runs its splitting iteration in the coordinates and hands the steps that touch
nothing to the solver. Adjoints see only the step (its chart and its solution).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import Chart, ContactSweep, Coordinates

Array = jax.Array


class StepProblem(NamedTuple):
    """What an iteration method sees of one implicit step.

    Attributes:
        evaluate: ``(x, q) -> (phi, g, q)``, see the module docstring.
        precondition: ``g -> A^-1 g`` with the prefactored PD matrix.
        diagonal: ``(n, 1)`` diagonal of ``A``.
        x_n, v_n: ``(n, 3)`` state at the start of the step.
        mass: ``(n, 1)`` lumped masses.
        free: ``(n, 1)`` 1 on free vertices, 0 on held ones (``(n, 3)`` per component with
            partly held vertices).
        dt: the time step (0 for static solves).
        time: the time at the start of the step, s.
        rows: ``((generator, params), ...)``: the scene's contact row generators
            (:class:`~softbody._interfaces.Rows`; its obstacles are one) and their
            parameters; ``()`` without contact.
        prepared: the coordinates' per-rollout data (:meth:`Step.prepare`).
        blocks: ``(n,)`` static ints, each vertex's block of Anderson coefficients in the
            contact iteration (:attr:`softbody._types.Model.contact_blocks`), or ``None``
            for one block.
        forces0: ``(e + m, 3)`` force rows to start the contact iteration from
            (:attr:`softbody._types.State.contact`; the contact solver never differentiates
            its solve, so no derivative flows through them), or ``None`` for zero.
        bodies: ``(n,)`` static ints, each vertex's body
            (:attr:`softbody._types.Model.vertex_bodies`), or ``None`` for one body.
    """

    evaluate: Callable
    precondition: Callable
    diagonal: Array
    x_n: Array
    v_n: Array
    mass: Array
    free: Array
    dt: float
    time: Array
    rows: tuple = ()
    prepared: object = None
    blocks: object = None
    forces0: object = None
    bodies: object = None


class Solution(NamedTuple):
    """Result of one step's nonlinear solve."""

    x: Array  # (n, 3) positions
    q: Array  # (4, t) rotations of x
    iterations: Array  # int: iterations (global solves of the search direction)
    evaluations: Array  # int: local steps (objective evaluations), line-search trials included
    gnorm: Array  # final |g|
    fallback: Array = False  # bool: a contact step's fast iteration fell short (see StepInfo.fallback)
    overflow: Array = False  # bool: a contact search overflowed its capacity (see StepInfo.overflow)
    tunnelled: Array = 0  # int: surface pairs that passed through each other (see StepInfo.tunnelled)
    forces: Array | None = None  # (e + m, 3): the contact iteration's force rows at the solution (State.contact)


class NonlinearSolver:
    """Base class of the nonlinear iterations, written once against a
    :class:`~softbody._interfaces.Chart` so that they run in any coordinates.

    ``volume_weight`` scales the volume term's weight in the prefactored matrix.
    """

    volume_weight: float = 1.0

    def run(self, chart: Chart, x0: Array, q0: Array, threshold: Array, max_iter: int,
            unrolled: bool | Unroll = False) -> Solution:
        """Iterate from ``(x0, q0)`` in ``chart`` until its gradient norm is
        ``<= threshold`` or ``max_iter`` iterations.

        ``unrolled=True`` or an :class:`Unroll` runs a fixed-trip loop (see
        :func:`iterate`) that reverse-mode autodiff can differentiate.
        """
        raise NotImplementedError


def _norm(g):
    return jnp.sqrt(jnp.sum(g * g))


@dataclass(frozen=True)
class Unroll:
    """How :func:`iterate` unrolls its loop for reverse mode.

    Attributes:
        extra: iterations run after convergence (see :func:`iterate`).
        remat: rematerialise each iteration in the backward pass (``jax.checkpoint``), so
            the tape keeps one loop state per iteration instead of every intermediate of
            the local step; on the shared 12288-tet cantilever that is 2.3 instead of
            10.4 GB for 3 steps at ``max_iter=120``, and half the time.
    """

    extra: int = 0
    remat: bool = True


def iterate(cond, body, init, max_iter: int, unrolled: bool | Unroll):
    """``while cond(c): c = body(c)`` with at most ``max_iter`` trips.

    ``unrolled=False``: a ``lax.while_loop`` (fast; not reverse-differentiable).
    ``unrolled=Unroll(extra=k)`` (``True`` is ``Unroll()``): a ``lax.scan`` of
    ``max_iter + k`` trips whose body is skipped by ``lax.cond`` once ``cond`` has failed
    and ``k`` further iterations have run, so reverse mode differentiates the iterations
    exactly as they ran. The further iterations barely move a converged iterate but let its
    derivative catch up: derivatives of fixed-point iterates converge with a lag behind
    the iterates. The tape holds ``max_iter + k`` trips, run or skipped: keep ``max_iter``
    near the iterations a step needs.
    """
    if unrolled is False:
        return jax.lax.while_loop(cond, body, init)
    unroll = Unroll() if unrolled is True else unrolled
    extra = unroll.extra
    if unroll.remat:
        body = jax.checkpoint(body, prevent_cse=False)

    def trip(carry, _):
        c, after = carry
        run = cond(c) | (after < extra)
        after = after + (run & ~cond(c)).astype(after.dtype)
        return (jax.lax.cond(run, body, lambda c: c, c), after), None

    return jax.lax.scan(trip, (init, jnp.asarray(0)), None, length=max_iter + extra)[0][0]


@dataclass(frozen=True)
class LocalGlobal(NonlinearSolver):
    """Plain projective dynamics: alternate local projections and the global solve.

    Its monotone decrease of the objective needs the PD matrix with the true weights, so
    ``volume_weight`` is fixed at 1. In a chart whose plain step may not descend
    (``Chart.backtracks`` > 0: a skeleton's joint servos are not in the matrix) a step
    that fails Armijo's test is halved.
    """

    def run(self, chart, x0, q0, threshold, max_iter, unrolled=False):
        return descend(chart, 0, x0, q0, threshold, max_iter, unrolled)


def lbfgs_direction(g: Array, s_hist: Array, y_hist: Array, rho: Array, count: Array, sy: Array,
                    precondition: Callable) -> Array:
    """The L-BFGS search direction ``-H g`` by the two-loop recursion in matrix form.

    The history is a ring buffer of ``m`` pairs: pair number ``c`` (from 0) sits in slot
    ``c % m``. In age order (oldest first) the first loop's alphas solve
    ``(I + diag(rho) triu(A, 1)) alpha = rho * S g`` and the second loop's ``c = alpha - beta``
    solve ``(I + diag(rho) tril(A^T, -1)) c = alpha - rho * Y r`` with ``A = S Y^T``, so the
    history enters through four ``(m, N)`` products instead of ``4 m`` vector operations.
    Unfilled slots get ``rho = 0``, which zeroes their alpha and c.

    Arguments:
        g: the gradient, any shape with ``N`` entries.
        s_hist, y_hist: ``(m, N)`` steps and gradient changes by slot.
        rho: ``(m,)`` ``1 / (s . y)`` by slot; count: pairs stored so far (int).
        sy: ``(m, m)`` ``A = S Y^T`` by slot (``A[i, j] = s_i . y_j``).
        precondition: ``r -> H0 r`` (the initial inverse Hessian).

    Returns:
        ``-H g``, shaped like ``g``.
    """
    m = s_hist.shape[0]
    eye = jnp.eye(m, dtype=g.dtype)
    order = (count - m + jnp.arange(m)) % m
    valid = jnp.arange(m) >= m - jnp.minimum(count, m)
    rho_o = jnp.where(valid, rho[order], 0.0)
    a_o = sy[order][:, order]
    upper = eye + rho_o[:, None] * jnp.triu(a_o, 1)
    alpha = jax.scipy.linalg.solve_triangular(upper, rho_o * (s_hist @ g.reshape(-1))[order], lower=False)
    r = precondition(g - (jnp.zeros(m, g.dtype).at[order].set(alpha) @ y_hist).reshape(g.shape))
    lower = eye + rho_o[:, None] * jnp.tril(a_o.T, -1)
    c = jax.scipy.linalg.solve_triangular(lower, alpha - rho_o * (y_hist @ r.reshape(-1))[order], lower=True)
    return -(r + (jnp.zeros(m, g.dtype).at[order].set(c) @ s_hist).reshape(g.shape))


def empty_history(m: int, size: int, dtype) -> tuple:
    """An L-BFGS history of ``m`` pairs of ``(size,)`` vectors holding none yet:
    ``(s_hist, y_hist, rho, count, sy)`` as :func:`lbfgs_direction` and :func:`store_pair`
    take them."""
    return (jnp.zeros((m, size), dtype), jnp.zeros((m, size), dtype), jnp.zeros(m, dtype), jnp.asarray(0),
            jnp.zeros((m, m), dtype))


def store_pair(history: tuple, s: Array, y: Array) -> tuple:
    """Add the curvature pair ``(s, y)`` to an L-BFGS history, if ``s . y`` is positive.

    Arguments:
        history: ``(s_hist (m, N), y_hist (m, N), rho (m,), count, sy (m, m))`` as
            :func:`lbfgs_direction` takes them.
        s, y: ``(N,)`` the step and the change of the gradient.

    Returns:
        The history with the pair in slot ``count % m`` (unchanged when ``s . y`` is not
        positive relative to ``|s| |y|``: the pair would break positive definiteness).
    """
    s_hist, y_hist, rho, count, sy_hist = history
    m = s_hist.shape[0]
    sy = jnp.sum(s * y)
    store = sy > 1e-12 * jnp.sqrt(jnp.sum(s * s) * jnp.sum(y * y))
    slot = count % m
    s_hist = s_hist.at[slot].set(jnp.where(store, s, s_hist[slot]))
    y_hist = y_hist.at[slot].set(jnp.where(store, y, y_hist[slot]))
    # The new pair's row s . Y^T and column S . y of A = S Y^T.
    sy_new = sy_hist.at[slot, :].set(y_hist @ s).at[:, slot].set(s_hist @ y)
    sy_hist = jnp.where(store, sy_new, sy_hist)
    rho = rho.at[slot].set(jnp.where(store, 1.0 / jnp.where(store, sy, 1.0), rho[slot]))
    return s_hist, y_hist, rho, count + store.astype(count.dtype), sy_hist


def descend(chart: Chart, history: int, x0: Array, q0: Array, threshold: Array, max_iter: int,
            unrolled: bool | Unroll = False) -> Solution:
    """The one descent loop of the nonlinear solvers: L-BFGS with ``history`` pairs, or
    the plain preconditioned (PD) step with ``history=0``, in the coordinates of ``chart``.

    Each iteration takes the direction ``d = -H r`` (L-BFGS's two-loop recursion with the
    chart's preconditioner as initial inverse Hessian; ``d = -H0 r`` without history; a
    quasi-Newton direction that does not descend is replaced by the plain one) and tries
    the full step. In a chart with ``backtracks`` it halves the step up to that many times
    while Armijo's test (c = 1e-4) fails; in one without, where the plain step descends
    (the PD matrix majorises the objective), a quasi-Newton step that fails is replaced by
    the plain step.

    Arguments:
        chart: the :class:`~softbody._interfaces.Chart` of the step's coordinates.
        history: L-BFGS pairs kept (static); 0 for plain local-global PD.
        x0: ``(n, 3)`` start positions; q0: their rotations' warm start.
        threshold: stop when the chart's gradient norm is at most this.
        max_iter: most iterations (static).
        unrolled: ``False`` for a ``while_loop``, else a fixed-trip loop (:func:`iterate`)
            that reverse mode differentiates as it ran.

    Returns:
        A :class:`Solution` (``evaluations`` counts the trials of the search).
    """
    point = chart.start(x0)
    phi0, g0, q0 = chart.evaluate(point, q0)
    r0, gnorm0, data0 = chart.gradient(point, g0)
    backtracks = chart.backtracks

    def cond(c):
        gnorm, k = c[6], c[8]
        return (gnorm > threshold) & (k < max_iter)

    def body(c):
        point, q, phi, g, r, data, _, lbfgs, k, evals = c

        def precondition(v):
            return chart.precondition(point, data, v)

        if history:
            d = chart.project(data, lbfgs_direction(r, *lbfgs, precondition))
            d = jax.lax.cond(jnp.sum(r * d) < 0, lambda: d, lambda: -precondition(r))
        else:
            d = -precondition(r)
        slope = jnp.sum(r * d)

        def trial(alpha):
            step = d if alpha is None else alpha * d
            new = chart.move(point, step)
            return (new, *chart.evaluate(new, q), step)

        def rejected(alpha, phi_t):
            return ~(phi_t <= phi + 1e-4 * (1.0 if alpha is None else alpha) * slope + 1e-14 * jnp.abs(phi))

        tries, failed = jnp.asarray(0), jnp.asarray(False)
        if backtracks:
            def halve(s):
                alpha, tries, _ = s
                return alpha / 2, tries + 1, trial(alpha / 2)

            # The search runs no iterations after acceptance (they would halve the accepted step).
            _, tries, taken = iterate(lambda s: rejected(s[0], s[2][1]) & (s[1] < backtracks), halve,
                                      (jnp.asarray(1.0), tries, trial(1.0)), backtracks, unrolled is not False)
        else:
            taken = trial(None)
        if history and not backtracks:
            failed = rejected(None, taken[1])

            def plain():
                step = -precondition(r)
                new = chart.move(point, step)
                return (new, *chart.evaluate(new, q), step)

            taken = jax.lax.cond(failed, plain, lambda: taken)
        new, phi_new, g_new, q_new, step = taken
        r_new, gnorm, data_new = chart.gradient(new, g_new)
        if history:
            lbfgs = store_pair(lbfgs, *chart.pair(point, data, g, new, data_new, g_new, step))
        evals = evals + 1 + tries + failed.astype(evals.dtype)
        return new, q_new, phi_new, g_new, r_new, data_new, gnorm, lbfgs, k + 1, evals

    lbfgs = empty_history(history, r0.size, r0.dtype) if history else ()
    init = (point, q0, phi0, g0, r0, data0, gnorm0, lbfgs, jnp.asarray(0), jnp.asarray(1))
    point, q, _, _, _, _, gnorm, _, k, evals = iterate(cond, body, init, max_iter, unrolled)
    return Solution(chart.positions(point), q, k, evals, gnorm)


@dataclass(frozen=True)
class LBFGS(NonlinearSolver):
    """L-BFGS with the PD matrix as initial Hessian and an Armijo safeguard (:func:`descend`).

    Each iteration tries the full quasi-Newton step; if it does not decrease the
    objective enough (Armijo, c = 1e-4), it takes the plain PD step instead, which always
    descends in vertex coordinates. (On the shared cantilever, backtracking by halving
    first did not reduce the iteration count; the fixed pattern keeps the loop
    differentiable when unrolled.) A skeleton's chart halves instead (its joint servos are
    not in the PD matrix).

    Attributes:
        history: number of stored curvature pairs.
        volume_weight: scale of the volume term in the initial Hessian. On the shared
            DiffPD cantilever (nu = 0.45, rel. tol 1e-4) 1.0 took 213 iterations per frame,
            0.33 took 104 and 0.2 took 88 (history 5); 0.1 needed more fallbacks.
    """

    history: int = 10
    volume_weight: float = 0.2

    def run(self, chart, x0, q0, threshold, max_iter, unrolled=False):
        return descend(chart, self.history, x0, q0, threshold, max_iter, unrolled)


class _VertexChart(Chart):
    """Plain coordinates: a point is the positions ``(n, 3)``; tangents are ``(n, 3)``."""

    def __init__(self, problem: StepProblem):
        self.problem = problem

    def start(self, x0):
        return x0

    def positions(self, point):
        return point

    def evaluate(self, point, q):
        return self.problem.evaluate(point, q)

    def gradient(self, point, g):
        return g, _norm(g), ()

    def precondition(self, point, data, r):
        return self.problem.precondition(r)

    def move(self, point, step):
        return point + step

    def pair(self, point, data, g, new, data_new, g_new, step):
        return (new - point).reshape(-1), (g_new - g).reshape(-1)


@dataclass(frozen=True)
class Vertices(Coordinates):
    """Plain coordinates: every free vertex moves on its own; the solver runs as it is."""

    solvers = (LBFGS, LocalGlobal)

    def volume_weight(self, solver: NonlinearSolver) -> float:
        return solver.volume_weight

    def prepare(self, model, data, factor):
        return None

    def implicit_chart(self, prepared, x, free):
        return None

    def chart(self, problem):
        """Every free vertex moves on its own (see :class:`~softbody._interfaces.Chart`)."""
        return _VertexChart(problem)

    def contact_sweep(self, problem, p, law):
        """Every free vertex takes the per-vertex contact step; nothing else moves."""

        def place(x):
            return x, None

        def sweep(x, x_new, g, aux):
            return x_new, jnp.zeros(0, x.dtype)

        def forces(x):
            return jnp.zeros((0, 3), x.dtype)

        return ContactSweep(problem.free, place, sweep, np.zeros(0, np.int64), jnp.zeros((0, 1)), forces)


@dataclass(frozen=True)
class Step:
    """One implicit step, composed by :func:`softbody.model.build` from the scene.

    Attributes:
        coordinates: the unknowns (:class:`Vertices`, or a skeleton's
            :class:`softbody.skeleton.Reduced`).
        solver: the contact-free nonlinear iteration (:class:`LBFGS`, :class:`LocalGlobal`).
        contact: ``None`` for a scene without contact rows, else the contact constraint's
            solver (:class:`softbody.contact.Contact`), which runs the splitting iteration
            in ``coordinates`` and ``solver`` on the steps that touch nothing.

    ``build`` checks the combination (``coordinates.solvers`` lists the solvers the
    coordinates run) before anything compiles.
    """

    coordinates: Coordinates
    solver: NonlinearSolver
    contact: object = None

    @property
    def volume_weight(self) -> float:
        """The volume term's scale in the prefactored matrix: 1 with contact (its splitting
        needs the true diagonal), else as the coordinates choose for the solver."""
        return 1.0 if self.contact is not None else self.coordinates.volume_weight(self.solver)

    def prepare(self, model, data: Array, factor) -> object:
        """Per-rollout data of the coordinates (made once per rollout by
        :func:`softbody.model.prepare`, differentiable), handed to :meth:`run` as
        ``problem.prepared``."""
        return self.coordinates.prepare(model, data, factor)

    def implicit_chart(self, prepared, x: Array, free: Array):
        """Coordinates in which the step's solution ``x`` is a stationary point of ``Phi``,
        for :class:`softbody.gradients.Implicit`.

        Arguments:
            prepared: the per-rollout data (:meth:`prepare`).
            x: ``(n, 3)`` the step's solution; free: ``(n, 1)`` or ``(n, 3)`` the free mask.

        Returns:
            ``None``: the free vertices' positions themselves. Otherwise
            ``(embed, solve, size)``: ``embed(d)`` maps ``(size,)`` chart coordinates to
            positions ``(n, 3)``, with ``embed(0) = x``; ``solve(r)`` applies a symmetric
            positive definite approximation of the inverse Hessian in the chart (the
            adjoint's preconditioner).
        """
        return self.coordinates.implicit_chart(prepared, x, free)

    def run(self, problem: StepProblem, x0: Array, q0: Array, threshold: Array, max_iter: int,
            unrolled: bool | Unroll = False) -> Solution:
        """Solve the step from ``(x0, q0)`` until its residual is ``<= threshold`` or
        ``max_iter`` iterations (``unrolled``: see :meth:`NonlinearSolver.run`; a step with
        contact is never unrolled, ``build`` refuses :class:`~softbody.gradients.Unrolled`
        there)."""
        if self.contact is not None:
            return self.contact.run(problem, self.coordinates, self.solver, x0, q0, threshold, max_iter)
        return self.solver.run(self.coordinates.chart(problem), x0, q0, threshold, max_iter, unrolled)

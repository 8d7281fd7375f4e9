"""Reference integrators for accuracy studies on small meshes (up to a few thousand DOFs).

* :func:`newton_step`, :func:`newton_rollout`, :func:`newton_static`: Newton's method on the
  SAME implicit-Euler (or static) objective ``Phi`` that :mod:`softbody.simulate` minimises
  with projective dynamics: its value, gradient and convergence scale come from the
  simulator's own objective, so damping, gravity, external forces and actuator terms are
  included and the stopping test ``|grad Phi| <= tol |M s / h^2| + atol`` means the same
  thing. The Hessian is the true one, assembled sparsely from per-tet ``12 x 12`` blocks
  (forward-mode derivatives of the per-tet gradient, the rotation's derivative included)
  plus the lumped inertia and mass damping on the diagonal; vertex terms (cavity
  pressure, sheets) and dissipation terms (drag) add their Hessian densely. Each Newton
  system is solved on the host with SciPy's sparse LU over the free degrees of freedom,
  followed by a backtracking line search.
* :func:`diffrax_rollout`: the semi-discrete FEM ODE of the same model,
  ``M x'' = -dE/dx - C(x) x' + M g + f`` on the free vertices, integrated with an adaptive
  (by default stiff, implicit) diffrax solver to tight tolerances. The damping forces are
  the continuous limits of the implicit-Euler dissipation potentials: ``alpha M x'`` and
  the corotated strain-rate stress ``beta w_s V R sym(R^T F')``.

These are slow by design (host round trips, direct factorisations, dense Jacobians for
diffrax); they exist to measure the simulator's accuracy, not to replace it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import diffrax
import jax
from jax.custom_derivatives import SymbolicZero
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from softbody import rotation as rot
from softbody._interfaces import Capabilities
from softbody.elastic import deformation_gradient, shape_gradients, strain_rate_damping
from softbody.model import Model, Params, Prepared, SceneError, State, initial_state, prepare
from softbody._types import RESULTS, StepInfo
from softbody.objective import (activation_slices, dissipation_energy, has_vertex_terms, step_objective, tet_stress,
                                vertex_energy, volume_target)
from softbody.simulate import SimulationError, Trajectory, _activation, _check_controls

Array = jax.Array


# --------------------------------------------------------------------------------------
# Pieces shared by the Newton Hessian and the ODE right-hand side
# --------------------------------------------------------------------------------------

#: Warm-started Newton steps of the rotation extraction per evaluation: capped at 1 rad
#: each, then quadratically convergent, so enough to reach any rotation to round-off.
_ROTATION_STEPS = 16


def _exact_rotations(f: Array, q: Array) -> Array:
    """Quaternions ``(4, t)`` of the rotations maximising ``tr(R^T F)``, warm-started from
    ``q`` (no derivative: differentiate through :func:`softbody.rotation.rotation` at them)."""
    q = jax.lax.fori_loop(0, _ROTATION_STEPS, lambda _, q: rot.rotation(f, q, 1)[1], q)
    return jax.lax.stop_gradient(q)


def _tet_gradients(model: Model, prep: Prepared, xe: Array, q: Array, slices, target, damping=None) -> Array:
    """Per-tet gradients ``(t, 4, 3)`` of the elastic and element actuator energies.

    Each tet's gradient depends on its own vertex positions ``xe`` ``(t, 4, 3)`` only.
    ``q`` are the maximising rotations at ``xe`` (the derivative of ``R`` comes from
    :func:`softbody.rotation.rotation`'s implicit rule). ``damping(f, r) -> (energy (t,), stress (3, 3, t))``
    adds a damping stress.
    """
    g = shape_gradients(prep.dminv)  # (4, 3, t)
    f = jnp.einsum("tai,ajt->ijt", xe, g)
    r, _ = rot.rotation(f, q, 1)
    _, stress = tet_stress(model, prep, f, r, slices, target, damping)
    return jnp.einsum("ijt,ajt->tai", stress, g)


def _tet_blocks(fn, z: Array) -> Array:
    """Per-tet Jacobians ``(t, 12, 12)`` of ``fn: (t, 4, 3) -> (t, 4, 3)`` at ``z``, where
    tet ``e``'s output depends only on ``z[e]``; DOF order ``(vertex a, component i)``.

    Column ``3 a + i`` of every block is one forward derivative along the direction that
    moves local vertex ``a`` along ``i`` in all tets at once.
    """
    t = z.shape[0]
    basis = jnp.broadcast_to(jnp.eye(12).reshape(12, 1, 4, 3), (12, t, 4, 3))
    cols = jax.vmap(lambda e: jax.jvp(fn, (z,), (e,))[1])(basis)  # (12, t, 4, 3)
    return jnp.transpose(cols.reshape(12, t, 12), (1, 2, 0))


def _scatter(model: Model, per_tet: Array) -> Array:
    """Sum per-tet vertex vectors ``(t, 4, 3)`` into ``(n, 3)``."""
    return jnp.zeros((model.n_vertices, 3), per_tet.dtype).at[jnp.asarray(model.mesh.tets)].add(per_tet)


def _vertex_gradient(model: Model, prep: Prepared, x: Array, slices):
    """Sum of the vertex terms' gradients ``(n, 3)``."""
    return vertex_energy(model, prep, x, slices)[1]


def _free_dofs(model: Model) -> np.ndarray:
    """Indices of the free degrees of freedom in the flattened ``(n, 3)`` layout."""
    return np.flatnonzero(np.broadcast_to(model.free_mask, (model.n_vertices, 3)).ravel() > 0)


def _tet_dofs(model: Model) -> np.ndarray:
    """``(t, 12)`` flattened DOF indices of each tet's vertices, in block order."""
    return (3 * model.mesh.tets.astype(np.int64)[:, :, None] + np.arange(3)).reshape(-1, 12)


# --------------------------------------------------------------------------------------
# Newton's method on the implicit-Euler objective
# --------------------------------------------------------------------------------------


@functools.partial(jax.jit, static_argnames=("model",))
def _evaluate(model, prep, x_n, v_n, q_n, activation, force, x, q):
    """``(Phi, grad Phi (n, 3), exact rotations of x, convergence scale)`` at ``x``, the
    rotations warm-started from ``q``."""
    evaluate, scale = step_objective(model, prep, x_n, v_n, q_n, activation, force)
    q = _exact_rotations(deformation_gradient(model, prep.dminv, x), q)
    phi, grad, q = evaluate(x, q)
    return phi, grad, q, scale


@functools.partial(jax.jit, static_argnames=("model",))
def _element_hessians(model, prep, x_n, q_n, activation, x, q):
    """Per-tet Hessians ``(t, 12, 12)`` of the elastic, element actuator and strain-rate
    damping energies at ``x`` (exact rotations ``q``)."""
    h = prep.dt
    slices = activation_slices(model, activation)
    target = volume_target(model, prep, slices)
    damping = None
    if prep.inertia.damped(model.stiffness_damping):
        # The damping frame R_n, found as the step objective finds it.
        f_n = deformation_gradient(model, prep.dminv, x_n)
        r_n, _ = rot.rotation(f_n, q_n, model.options.rotation_iterations + 1)

        def damping(f, r):
            return strain_rate_damping(f, f_n, r_n, prep.volume, prep.w_b, h)

    xe = x[jnp.asarray(model.mesh.tets)]
    return _tet_blocks(lambda z: _tet_gradients(model, prep, z, q, slices, target, damping), xe)


@functools.partial(jax.jit, static_argnames=("model",))
def _vertex_hessian(model, prep, activation, x_n, v_n, x):
    """Dense Hessian ``(n, 3, n, 3)`` at ``x`` of the vertex terms and the dissipation terms
    (of a step from ``x_n``, ``v_n``)."""
    slices = activation_slices(model, activation)

    def gradient(y):
        return _vertex_gradient(model, prep, y, slices) + dissipation_energy(model, prep, y, x_n, v_n, slices)[1]

    return jax.jacfwd(gradient)(x)


class _Assembler:
    """Scatters per-tet ``12 x 12`` blocks into the sparse Hessian over the free DOFs."""

    def __init__(self, model: Model):
        self.free_dofs = _free_dofs(model)
        self.size = len(self.free_dofs)
        compact = np.full(3 * model.n_vertices, -1, np.int64)  # DOF -> index among the free ones
        compact[self.free_dofs] = np.arange(self.size)
        dofs = _tet_dofs(model)
        rows = compact[np.repeat(dofs, 12, axis=1)]  # (t, 144), row-major over (row, col)
        cols = compact[np.tile(dofs, (1, 12))]
        self.keep = (rows >= 0) & (cols >= 0)
        self.rows, self.cols = rows[self.keep], cols[self.keep]

    def matrix(self, blocks: np.ndarray, diagonal: np.ndarray, dense=None) -> sp.csc_matrix:
        """The free-free Hessian from blocks ``(t, 12, 12)``, a per-DOF diagonal ``(3 n,)``
        and an optional dense ``(3 n, 3 n)`` part."""
        data = blocks.reshape(len(blocks), 144)[self.keep]
        rows = np.concatenate([self.rows, np.arange(self.size)])
        cols = np.concatenate([self.cols, np.arange(self.size)])
        data = np.concatenate([data, diagonal[self.free_dofs]])
        if dense is not None:
            sub = dense[np.ix_(self.free_dofs, self.free_dofs)]
            r, c = np.nonzero(sub)
            rows, cols = np.concatenate([rows, r]), np.concatenate([cols, c])
            data = np.concatenate([data, sub[r, c]])
        return sp.coo_matrix((data, (rows, cols)), shape=(self.size, self.size)).tocsc()


def _newton(model, prep, x_n, v_n, q_n, activation, force, x0, *, tol, max_iter):
    """Newton's method with a backtracking line search.

    Returns:
        ``(x, q, iterations, evaluations, relative residual)``.

    Raises:
        ValueError: ``tol <= 0`` or ``max_iter < 1``.
        SimulationError: non-finite values, a failed line search or no convergence.
    """
    if not (tol > 0 and int(max_iter) >= 1):
        raise ValueError(f"Newton needs tol > 0 and max_iter >= 1, got tol={tol}, max_iter={max_iter}")
    assembler = _Assembler(model)
    atol = model.options.atol
    inertia = np.asarray(prep.inertia.hessian_diagonal(prep.mass, prep.mass_alpha))  # (n, 1), or 0 in statics
    diagonal = np.repeat(np.broadcast_to(inertia, (model.n_vertices, 1))[:, 0], 3)
    vertex_terms = has_vertex_terms(model)

    def evaluate(x, q):
        phi, g, q, scale = _evaluate(model, prep, x_n, v_n, q_n, activation, force, x, q)
        return float(phi), np.asarray(g).reshape(-1)[assembler.free_dofs], q, float(scale)

    x = jnp.asarray(x0)
    phi, g, q, scale = evaluate(x, q_n)
    evaluations = 1
    threshold = tol * scale + atol
    for k in range(int(max_iter) + 1):
        gnorm = float(np.linalg.norm(g))
        if not np.isfinite(phi) or not np.isfinite(gnorm):
            raise SimulationError(f"Newton iteration {k}: the objective or its gradient is not finite")
        if gnorm <= threshold:
            return x, q, k, evaluations, gnorm / (scale + atol / tol)
        if k == max_iter:
            break
        blocks = np.asarray(_element_hessians(model, prep, x_n, q_n, activation, x, q))
        dense = None
        if vertex_terms:
            dense = np.asarray(_vertex_hessian(model, prep, activation, x_n, v_n, x)).reshape(3 * model.n_vertices, -1)
        hess = assembler.matrix(blocks, diagonal, dense)
        d, slope = _descent_direction(hess, g)
        step = 1.0
        for _ in range(40):
            trial = x.reshape(-1).at[assembler.free_dofs].add(step * d).reshape(x.shape)
            phi_t, g_t, q_t, _ = evaluate(trial, q)
            evaluations += 1
            # Armijo on Phi, or (where Phi's decrease is below its rounding error near the
            # solution) a halving of the residual.
            armijo = phi_t <= phi + 1e-4 * step * slope
            rounding = phi_t <= phi + 1e-12 * abs(phi) and np.linalg.norm(g_t) <= 0.5 * gnorm
            if np.isfinite(phi_t) and (armijo or rounding):
                break
            step *= 0.5
        else:
            raise SimulationError(
                f"Newton iteration {k}: the line search found no decrease at relative residual "
                f"{gnorm / (scale + atol / tol):.3g}; the force residual is probably at its rounding "
                f"floor (tol {tol:g} is too tight for this load and stiffness)")
        x, phi, g, q = trial, phi_t, g_t, q_t
    raise SimulationError(
        f"Newton did not converge in {max_iter} iterations (relative residual "
        f"{gnorm / (scale + atol / tol):.3g} > tol {tol:g}); raise max_iter, or loosen tol if the "
        "residual has stalled at its rounding floor")


def _descent_direction(hess: sp.csc_matrix, g: np.ndarray) -> tuple[np.ndarray, float]:
    """Solve ``H d = -g``; where that is no descent direction (``H`` indefinite away from
    the minimum), shift ``H`` by growing multiples of its absolute diagonal."""
    shift_diag = np.abs(hess.diagonal())
    shift = 0.0
    for _ in range(20):
        mat = hess if shift == 0.0 else (hess + sp.diags(shift * shift_diag)).tocsc()
        try:
            d = spla.splu(mat).solve(-g)
        except RuntimeError:  # exactly singular
            d = np.full_like(g, np.nan)
        slope = float(g @ d)
        if np.all(np.isfinite(d)) and slope < 0:
            return d, slope
        shift = 1e-6 if shift == 0.0 else 10 * shift
    raise SimulationError("Newton: no descent direction even with a strongly shifted Hessian")


def newton_step(model: Model, params: Params, state: State, activation=None, force=None,
                tol: float = 1e-10, max_iter: int = 50) -> tuple[State, int]:
    """One implicit-Euler step solved with Newton's method (true Hessian, sparse LU).

    Minimises the same objective as :func:`softbody.simulate.step` (inertia, mass and
    strain-rate damping, gravity, external forces, actuators) to
    ``|grad Phi| <= tol |M s / h^2| + model.options.atol`` over the free DOFs.

    Arguments:
        model, params: from :func:`softbody.model.build`.
        state: the :class:`~softbody.model.State` at the start of the step.
        activation: ``(n_channels,)`` actuator activations, or ``None`` (zeros).
        force: ``(n, 3)`` external forces in newtons, or ``None``.
        tol: relative force-residual tolerance (same definition as ``Options.tol``).
        max_iter: Newton iteration cap.

    Returns:
        ``(next_state, iterations)``: the state after the step (positions, velocities
        ``(x - x_n) / h``, exact rotations ``(4, t)``, time) and the number of Newton
        iterations (Hessian solves).

    Raises:
        SceneError: wrong activation or force shapes.
        ValueError: ``tol <= 0`` or ``max_iter < 1``.
        SimulationError: non-finite values, a failed line search or no convergence (the
            message says which; a stalled residual means ``tol`` is below its rounding floor).
    """
    _check_step_inputs(model, activation, force)
    prep = prepare(model, params)
    return _newton_step(model, prep, state, _activation(model, activation), force, tol, max_iter)[:2]


_FREE_VERTICES = "moves every vertex freely (no reduced coordinates)"
_NO_CONTACT = "has no contact: its steps would pass through the obstacles"

#: What the Newton reference (newton_step, newton_rollout, newton_static) cannot step.
NEWTON = Capabilities(
    refuses={"contact": _NO_CONTACT, "skeleton": _FREE_VERTICES, "rigid bodies": _FREE_VERTICES,
             "motion": "keeps fixed vertices in place"},
    instead="step such a scene with softbody.simulate.rollout")

#: What diffrax_rollout cannot integrate.
DIFFRAX = Capabilities(
    refuses={**NEWTON.refuses, "partly held vertices": "integrates whole free vertices",
             "velocity forces": "integrates forces of the positions and the material's damping only"},
    instead="step such a scene with softbody.simulate.rollout (newton_rollout takes partly held vertices)")


def _check_step_inputs(model: Model, activation, force, capabilities: Capabilities = NEWTON,
                       what: str = "the Newton reference"):
    capabilities.check(model.features, what)
    if activation is not None and jnp.shape(activation) != (model.n_channels,):
        raise SceneError(f"activation must have shape ({model.n_channels},), got {jnp.shape(activation)}")
    if force is not None and jnp.shape(force) != (model.n_vertices, 3):
        raise SceneError(f"force must have shape ({model.n_vertices}, 3), got {jnp.shape(force)}")


def _newton_step(model, prep, state, activation, force, tol, max_iter):
    h = model.options.dt
    free = jnp.asarray(model.free_mask)
    x0 = jnp.where(free > 0, state.x + h * state.v, state.x)
    x, q, iters, evals, residual = _newton(model, prep, state.x, state.v, state.rot, activation, force, x0,
                                           tol=tol, max_iter=max_iter)
    return State(x=x, v=(x - state.x) / h, rot=q, t=state.t + h, contact=state.contact), iters, evals, residual


def newton_rollout(model: Model, params: Params, state0: State, n_steps: int | None = None,
                   controls=None, forces=None, tol: float = 1e-10, max_iter: int = 50) -> Trajectory:
    """``n_steps`` implicit-Euler steps, each solved with :func:`newton_step`'s method.

    Arguments:
        model, params, state0: as for :func:`softbody.simulate.rollout`.
        n_steps: number of steps (taken from controls/forces when omitted).
        controls: ``(n_steps, n_channels)`` activations, or ``None``.
        forces: ``(n_steps, n, 3)`` external forces, or ``None``.
        tol, max_iter: per-step Newton tolerance and cap.

    Returns:
        A :class:`~softbody.simulate.Trajectory`: ``x, v`` of shape ``(n_steps + 1, n, 3)``
        (the first row is ``state0``) and per-step :class:`~softbody.objective.StepInfo`
        (``iterations``: Newton iterations; ``evaluations``: objective evaluations, line
        search included; every step converged, or an error was raised; ``result`` is
        ``RESULTS.inverted`` where a step ended with more inverted tets than ``state0``,
        which is reported, not raised, else ``RESULTS.success``).

    Raises:
        SceneError: bad control or force shapes.
        ValueError: ``tol <= 0`` or ``max_iter < 1``.
        SimulationError: a step that fails (see :func:`newton_step`), naming the step.
    """
    _check_step_inputs(model, None, None)
    controls, forces, n_steps = _check_controls(model, controls, forces, n_steps, params=params, state0=state0)
    prep = prepare(model, params)
    state, xs, vs, stats = state0, [state0.x], [state0.v], []
    for k in range(n_steps):
        a = _activation(model, None if controls is None else controls[k])
        f = None if forces is None else forces[k]
        try:
            state, *step_stats = _newton_step(model, prep, state, a, f, tol, max_iter)
        except SimulationError as err:
            raise SimulationError(f"step {k}: {err}") from None
        xs.append(state.x)
        vs.append(state.v)
        stats.append(step_stats)
    iters, evals, residuals = (jnp.asarray(c) for c in zip(*stats))
    count = jax.vmap(lambda x: jnp.sum(rot.det3(deformation_gradient(model, prep.dminv, x)) <= 0))
    inverted = count(jnp.stack(xs[1:]))
    converged = jnp.ones(n_steps, bool)
    result = RESULTS.of(finite=converged, converged=converged, inverted=inverted, inverted0=count(state0.x[None])[0])
    info = StepInfo(iterations=iters, evaluations=evals, residual=residuals, converged=converged,
                    inverted=inverted, result=result, fallback=jnp.zeros(n_steps, bool),
                    overflow=jnp.zeros(n_steps, bool), tunnelled=jnp.zeros(n_steps, jnp.int32))
    return Trajectory(x=jnp.stack(xs), v=jnp.stack(vs), info=info)


def newton_static(model: Model, params: Params, force=None, activation=None, x0=None,
                  tol: float = 1e-10, max_iter: int = 50) -> tuple[Array, int]:
    """Static equilibrium ``min E(x) - f . x`` by Newton's method (see :func:`newton_step`).

    The load is gravity on the lumped masses plus ``force``, as in
    :func:`softbody.simulate.solve_static`, and the residual is relative to its norm.

    Arguments:
        model, params: from :func:`softbody.model.build` (with fixed vertices).
        force: ``(n, 3)`` external forces in newtons, or ``None``.
        activation: ``(n_channels,)`` or ``None``.
        x0: initial guess ``(n, 3)`` (default: the rest shape).
        tol, max_iter: relative force tolerance and iteration cap.

    Returns:
        ``(x, iterations)``: equilibrium positions ``(n, 3)`` and the Newton iterations.

    Raises:
        SceneError: no fixed vertices (the equilibrium is not unique), wrong shapes.
        ValueError: ``tol <= 0`` or ``max_iter < 1``.
        SimulationError: non-finite values, a failed line search or no convergence.
    """
    if len(model.fixed) == 0:
        raise SceneError("a static solve needs fixed vertices (build the model with fixed=...)")
    _check_step_inputs(model, activation, force)
    prep = prepare(model, params, static=True)
    state = initial_state(model, params, x=x0)
    x, _, iters, _, _ = _newton(model, prep, state.x, state.v, state.rot, _activation(model, activation),
                                force, state.x, tol=tol, max_iter=max_iter)
    return x, iters


# --------------------------------------------------------------------------------------
# The semi-discrete ODE, integrated with diffrax
# --------------------------------------------------------------------------------------


def diffrax_rollout(model: Model, params: Params, state0: State, t1: float, ts, rtol: float = 1e-8,
                    atol: float = 1e-10, solver=None, activation=None, force=None,
                    max_steps: int = 100_000) -> Array:
    """Integrate ``M x'' = -dE/dx - alpha M x' - f_beta(x, x') + M g + f`` with diffrax.

    The unknowns are the free vertices' displacements from ``state0.x`` and their
    velocities (so ``rtol`` is relative to the motion, not to the coordinates); fixed
    vertices stay at ``state0.x``. ``E`` is the simulator's elastic and actuator energy
    (constant activations), ``f_beta`` the nodal force of the strain-rate damping stress
    ``beta w_s V R sym(R^T F')`` (``R`` the rotation of ``F``, ``F'`` its rate): the limit
    of the implicit-Euler dissipation potential as ``h -> 0``. Step sizes come from a PI
    controller (``pcoeff = icoeff = 0.3``, diffrax's suggestion for stiff problems). For
    implicit solvers the dense Jacobian is assembled from per-tet blocks (about the cost
    of 24 evaluations of the right-hand side); keep meshes small (a dense LU of
    ``6 n_free`` unknowns per step). Where the step size is set by accuracy rather than
    stability (tight tolerances, light damping), ``solver=diffrax.Tsit5()`` needs no
    Jacobian and fewer steps: on the 99-vertex test beam over 0.04 s, 918 steps and 2 s
    against Kvaerno5's ~40 ms per step.

    Not differentiable with respect to ``params`` or ``state0`` (JAX raises if asked):
    it is a reference for accuracy, not for gradients.

    Arguments:
        model, params: from :func:`softbody.model.build`.
        state0: initial :class:`~softbody.model.State` at time ``state0.t``.
        t1: end time, s (> ``state0.t``).
        ts: ``(k,)`` increasing output times in ``[state0.t, t1]``.
        rtol, atol: the step-size controller's relative and absolute tolerances on
            displacements (m) and velocities (m/s).
        solver: a diffrax solver; ``None`` uses ``diffrax.Kvaerno5()`` (L-stable, 5th order).
        activation: constant ``(n_channels,)`` activations, or ``None``.
        force: constant ``(n, 3)`` external forces in newtons, or ``None``.
        max_steps: diffrax's cap on the number of steps.

    Returns:
        ``(k, n, 3)`` positions at ``ts``.

    Raises:
        ValueError: ``t1`` not after ``state0.t``, or ``ts`` not increasing inside the interval.
        SceneError: wrong activation or force shapes, or partly held vertices.
        RuntimeError: diffrax failed (e.g. ``max_steps`` reached).
    """
    _check_step_inputs(model, activation, force, DIFFRAX, "diffrax_rollout")
    t0 = float(state0.t)
    ts = np.asarray(ts, np.float64)
    if not t1 > t0:
        raise ValueError(f"t1 = {t1} must be after the initial time {t0}")
    if ts.ndim != 1 or len(ts) == 0 or np.any(np.diff(ts) <= 0) or ts[0] < t0 or ts[-1] > t1:
        raise ValueError(f"ts must be a non-empty increasing 1-D array inside [{t0}, {t1}]")
    solver = diffrax.Kvaerno5() if solver is None else solver
    prep = prepare(model, params)
    free = np.flatnonzero(model.free_mask[:, 0] > 0)
    slices = activation_slices(model, activation)
    load = prep.mass * jnp.asarray(model.options.gravity) + (0.0 if force is None else jnp.asarray(force))
    data = _OdeData(prep=dataclasses.replace(prep, factor=None, data=None), x0=state0.x, q0=state0.rot,
                    slices=slices, target=jnp.asarray(volume_target(model, prep, slices)), load=load)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field), solver, t0=t0, t1=float(t1), dt0=None,
        y0=(jnp.zeros((len(free), 3)), state0.v[free]), args=(model, data),
        saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol, pcoeff=0.3, icoeff=0.3),
        max_steps=max_steps)
    return jnp.broadcast_to(state0.x, (len(ts),) + state0.x.shape).at[:, free].add(sol.ys[0])


class _OdeData(NamedTuple):
    """The arrays the ODE's right-hand side reads (a pytree)."""

    prep: Prepared  # without the PD matrix and its factor
    x0: Array  # (n, 3) initial positions (the fixed vertices stay there)
    q0: Array  # (4, t) their rotations: the warm start of every rotation extraction
    slices: tuple  # per-term activations
    target: Array  # volume-term targets: () or (t,)
    load: Array  # (n, 3) gravity on the lumped masses plus external forces


def _vector_field(t, y, args):
    """``(u', v')`` for ``y = (u, v)``: the free vertices' displacements and velocities."""
    model, data = args
    u, w = y
    return w, _acceleration(model, data, u, w)


def _ode_parts(model: Model, data: _OdeData, u, w):
    """Positions and velocities ``(n, 3)``, exact rotations and the per-tet force function."""
    free = np.flatnonzero(model.free_mask[:, 0] > 0)
    prep = data.prep
    x = data.x0.at[free].add(u)
    v = jnp.zeros_like(x).at[free].set(w)
    q = _exact_rotations(deformation_gradient(model, prep.dminv, x), data.q0)
    g = shape_gradients(prep.dminv)

    def tet_forces(xe, ve):  # per-tet dE/dx plus the strain-rate damping force, (t, 4, 3)
        damping = None
        if model.stiffness_damping:
            def damping(f, r):
                # The implicit-Euler stress V w_b / h R_n sym(R_n^T (F - F_n)) with
                # F - F_n = h F' in the limit h -> 0, i.e. evaluated with h = 1 on F + F'.
                f_rate = jnp.einsum("tai,ajt->ijt", ve, g)
                return strain_rate_damping(f + f_rate, f, r, prep.volume, prep.w_b, 1.0)
        return _tet_gradients(model, prep, xe, q, data.slices, data.target, damping)

    return free, x, v, tet_forces


def _acceleration_impl(model: Model, data: _OdeData, u, w):
    """The free vertices' accelerations ``(m, 3)`` at displacements ``u`` and velocities ``w``."""
    free, x, v, tet_forces = _ode_parts(model, data, u, w)
    tets = jnp.asarray(model.mesh.tets)
    grad = _scatter(model, tet_forces(x[tets], v[tets])) + _vertex_gradient(model, data.prep, x, data.slices)
    return ((data.load - grad - data.prep.mass_alpha * v) / data.prep.mass)[free]


_acceleration = jax.custom_jvp(_acceleration_impl, nondiff_argnums=(0,))


def _dense_free_matrix(model: Model, blocks: Array) -> Array:
    """Assemble per-tet blocks ``(t, 12, 12)`` into the dense free-free matrix."""
    dofs = _tet_dofs(model)
    rows, cols = np.repeat(dofs, 12, axis=1).ravel(), np.tile(dofs, (1, 12)).ravel()
    n3 = 3 * model.n_vertices
    full = jnp.zeros((n3, n3), blocks.dtype).at[rows, cols].add(blocks.reshape(-1))
    free = _free_dofs(model)
    return full[free][:, free]


@functools.partial(_acceleration.defjvp, symbolic_zeros=True)
def _acceleration_jvp(model, primals, tangents):
    """Forward derivative through the dense Jacobians ``d a / d u`` and ``d a / d w``,
    assembled from per-tet blocks: under ``jacfwd`` (an implicit solver's Jacobian) they
    are built once and applied to all columns as one matrix product."""
    data, u, w = primals
    ddata, du, dw = tangents
    free, x, v, tet_forces = _ode_parts(model, data, u, w)
    tets = jnp.asarray(model.mesh.tets)
    xe, ve = x[tets], v[tets]
    inv_mass = 1.0 / jnp.repeat(data.prep.mass[free, 0], 3)
    tangent = jnp.zeros(u.size)
    if not isinstance(du, SymbolicZero):
        k_x = _dense_free_matrix(model, _tet_blocks(lambda z: tet_forces(z, ve), xe))
        tangent = tangent - k_x @ du.reshape(-1)
        if has_vertex_terms(model):
            dx = jnp.zeros_like(x).at[free].set(du)
            hv = jax.jvp(lambda y: _vertex_gradient(model, data.prep, y, data.slices), (x,), (dx,))[1]
            tangent = tangent - hv[free].reshape(-1)
    if not isinstance(dw, SymbolicZero):
        tangent = tangent - jnp.repeat(data.prep.mass_alpha[free, 0], 3) * dw.reshape(-1)
        if model.stiffness_damping:
            k_v = _dense_free_matrix(model, _tet_blocks(lambda z: tet_forces(xe, z), ve))
            tangent = tangent - k_v @ dw.reshape(-1)
    tangent = (inv_mass * tangent).reshape(u.shape)

    def is_zero(t):
        return isinstance(t, SymbolicZero)

    if not all(is_zero(t) for t in jax.tree.leaves(ddata, is_leaf=is_zero)):
        ddata = jax.tree.map(lambda t, p: jnp.zeros_like(p) if is_zero(t) else t, ddata, data,
                             is_leaf=is_zero)
        tangent = tangent + jax.jvp(lambda d: _acceleration_impl(model, d, u, w), (data,), (ddata,))[1]
    return _acceleration_impl(model, data, u, w), tangent

"""The objective of one implicit step, and the loop that minimises it.

See :mod:`softbody.simulate` for the equations. Both the forward solve and the implicit
adjoint (:mod:`softbody.gradients`) are built on :func:`step_objective`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from softbody import rotation as rot
from softbody._interfaces import DissipationTerm, ElementTerm, VertexTerm, VolumeTerm
from softbody.elastic import (corotated, deformation_gradient, scatter_stress, shape_gradients, strain_rate_damping,
                              stress_derivative_product)
from softbody._types import RESULTS, Model, Prepared, State, StepInfo
from softbody.inertia import Statics
from softbody.contact.obstacles import ObstacleRows
from softbody.solvers import Solution, StepProblem

Array = jax.Array




def activation_slices(model: Model, activation) -> tuple[Array, ...]:
    """Each term's slice ``(c_i,)`` of the activation vector ``(n_channels,)`` (zeros for ``None``)."""
    a = jnp.zeros(model.n_channels) if activation is None else activation
    slices, offset = [], 0
    for term in model.terms:
        slices.append(a[offset:offset + len(term.channel_names)])
        offset += len(term.channel_names)
    return tuple(slices)


def volume_target(model: Model, prep: Prepared, slices):
    """The volume term's target ``3 s`` (it aims at ``det F = s^3``): 3.0, or ``(t,)`` where
    :class:`~softbody._interfaces.VolumeTerm` terms set targets (fixed per step)."""
    target = 3.0
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if isinstance(term, VolumeTerm):
            idx, s_t = term.volume_targets(tp, a)
            target = (jnp.full(model.n_tets, 3.0) if isinstance(target, float) else target).at[idx].set(3.0 * s_t)
    return target


def tet_stress(model: Model, prep: Prepared, f, r, slices, target, damping=None):
    """The per-tet terms at deformation gradients ``f`` ``(3, 3, t)`` with rotations ``r``:
    ``(energy (), stress dE/dF (3, 3, t))`` of the elasticity, the strain-rate damping
    (``damping(f, r) -> (energy (t,), stress)``, or ``None``) and the element terms."""
    energy, stress = corotated(f, r, prep.volume, prep.w_s, prep.w_v, target)
    energy = jnp.sum(energy)
    if damping is not None:
        e_d, s_d = damping(f, r)
        energy, stress = energy + jnp.sum(e_d), stress + s_d
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if isinstance(term, ElementTerm):
            idx = jnp.asarray(tp.tets)
            e_t, s_t = term.energy_and_stress(f[:, :, idx], tp, a)
            energy = energy + jnp.sum(e_t)
            stress = stress.at[:, :, idx].add(s_t)
    return energy, stress


def vertex_energy(model: Model, prep: Prepared, x, slices):
    """``(energy (), gradient (n, 3))`` of the :class:`~softbody._interfaces.VertexTerm` terms at ``x``."""
    energy, grad = 0.0, jnp.zeros_like(x)
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if isinstance(term, VertexTerm):
            e_t, g_t = term.energy_and_gradient(x, tp, a)
            energy, grad = energy + e_t, grad + g_t
    return energy, grad


def dissipation_energy(model: Model, prep: Prepared, x, x_n, v_n, slices):
    """``(energy (), gradient (n, 3))`` of the :class:`~softbody._interfaces.DissipationTerm`
    terms in the step objective at ``x``: ``h D((x - x_n)/h)`` with the terms' geometry at
    ``x_n`` in a time step (``h = prep.dt``); in a static objective, the forces at the
    velocities ``v_n`` held as a load, ``dD/dv(v_n) . x``."""
    energy, grad = 0.0, jnp.zeros_like(x)
    static = prep.inertia.static
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if isinstance(term, DissipationTerm):
            if static:
                _, g_t = term.dissipation(v_n, x_n, tp, a)
                e_t = jnp.sum(g_t * x)
            else:
                d_t, g_t = term.dissipation((x - x_n) / prep.dt, x_n, tp, a)
                e_t = prep.dt * d_t
            energy, grad = energy + e_t, grad + g_t
    return energy, grad


def has_vertex_terms(model: Model) -> bool:
    """Whether some term is an energy of the positions (:class:`~softbody._interfaces.VertexTerm`)
    or a dissipation of the step's velocity (:class:`~softbody._interfaces.DissipationTerm`):
    the objective's part beyond the tets and the inertia."""
    return any(isinstance(term, (VertexTerm, DissipationTerm)) for term in model.terms)


class _Terms(NamedTuple):
    """The pieces of one step's objective, shared by :func:`step_objective` and
    :func:`step_hessian`."""

    tet: Callable  # (f, q) -> (energy (), stress (3, 3, t), q): every per-tet term
    vertex: Callable  # x -> (energy (), grad (n, 3)): terms of positions (cavities, joints) and dissipations
    inertia: Callable  # x -> (phi (), grad (n, 3)): inertia and mass damping, or the load
    scale: Array


def _terms(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force) -> _Terms:
    h = prep.dt
    gravity = jnp.asarray(model.options.gravity)
    free = jnp.asarray(model.free_mask)
    load = prep.mass * gravity + (0.0 if force is None else force)
    inertia, scale = prep.inertia.energy(x_n, v_n, prep.mass, prep.mass_alpha, load, free)
    iters = model.options.rotation_iterations
    damped = prep.inertia.damped(model.stiffness_damping)
    if damped:
        f_n = deformation_gradient(model, prep.dminv, x_n)
        r_n, _ = rot.rotation(f_n, q_n, iters + 1)

    slices = activation_slices(model, activation)
    target = volume_target(model, prep, slices)
    damping = (lambda f, r: strain_rate_damping(f, f_n, r_n, prep.volume, prep.w_b, h)) if damped else None

    def tet(f, q):
        r, q = rot.rotation(f, q, iters)
        return (*tet_stress(model, prep, f, r, slices, target, damping), q)

    dissipative = any(isinstance(term, DissipationTerm) for term in model.terms)

    def vertex(x):
        e_v, g_v = vertex_energy(model, prep, x, slices)
        if not dissipative:
            return e_v, g_v
        e_d, g_d = dissipation_energy(model, prep, x, x_n, v_n, slices)
        return e_v + e_d, g_v + g_d

    return _Terms(tet=tet, vertex=vertex, inertia=inertia, scale=scale)


def step_objective(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force):
    """The step objective (a time step or a static solve, as ``prep.inertia`` says):
    ``(evaluate, scale)``.

    ``evaluate(x, q) -> (phi, g, q)`` gives ``Phi(x)``, its gradient ``(n, 3)`` on the free
    vertices (zero on fixed ones, whose positions are taken from ``x_n`` whatever ``x``
    holds) and the rotations of ``x``; ``scale`` is ``|M s / h^2|`` over free vertices
    (dynamics) or ``|f|`` (statics), the denominator of the relative residual.
    """
    free = jnp.asarray(model.free_mask)
    terms = _terms(model, prep, x_n, v_n, q_n, activation, force)

    def evaluate(x, q):
        x = jnp.where(free > 0, x, x_n)
        f = deformation_gradient(model, prep.dminv, x)
        energy, stress, q = terms.tet(f, q)
        phi, grad = terms.inertia(x)
        phi, grad = phi + energy, grad + scatter_stress(model, prep.dminv, stress)
        if has_vertex_terms(model):
            e_v, g_v = terms.vertex(x)
            phi, grad = phi + e_v, grad + g_v
        return phi, grad * free, q

    return evaluate, terms.scale


def step_hessian(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force, x, q):
    """The step objective's Hessian at ``x`` as a linear map ``v (n, 3) -> H v (n, 3)``.

    It equals the linearisation of ``evaluate(., q)[1]`` of :func:`step_objective` (free
    rows and columns; zero on fixed vertices), built for repeated application: the
    per-tet stress derivative ``dP/dF`` ``(3, 3, 3, 3, t)`` is assembled once (nine
    tangents of the per-tet terms, through the rotation's exact derivative), so each
    product is a gather, a ``9 x 9`` product per tet and a scatter
    (:func:`~softbody.elastic.stress_derivative_product`, native where available), with
    none of a local step's rotation or volume iterations. Terms of positions
    (cavities, joint servos) are linearised as they are.

    Arguments:
        x: ``(n, 3)`` positions; q: ``(4, t)`` rotations of ``x`` (warm start, refined as in
            ``evaluate``); the rest as for :func:`step_objective`.
    """
    free = jnp.asarray(model.free_mask)
    terms = _terms(model, prep, x_n, v_n, q_n, activation, force)
    x = jnp.where(free > 0, x, x_n)
    f = deformation_gradient(model, prep.dminv, x)
    _, tangent = jax.linearize(lambda f: terms.tet(f, q)[1], f)
    # Nine tangents one by one (vmapped, the same took 3-4x longer on CPU), in one lax.map:
    # traced once, not nine times.
    eye = jnp.eye(9, dtype=f.dtype).reshape(9, 3, 3, 1)
    dpdf = jax.lax.map(lambda e: tangent(jnp.broadcast_to(e, f.shape)), eye)  # (kl, i, j, t)
    diagonal = prep.inertia.hessian_diagonal(prep.mass, prep.mass_alpha)
    vertex = jax.linearize(lambda x: terms.vertex(x)[1], x)[1] if has_vertex_terms(model) else None

    product = stress_derivative_product(model, prep.dminv, dpdf)

    def hvp(v):
        v = v * free
        out = product(v) + diagonal * v
        if vertex is not None:
            out = out + vertex(v)
        return out * free

    return hvp


def step_gradient_vjp(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force, x, q, lam) -> tuple:
    """Cotangents of ``(prep, x_n, v_n, q_n, activation, force)`` for the cotangent ``lam``
    of the step gradient ``g = evaluate(x, q)[1]`` of :func:`step_objective`, i.e. the
    gradient of ``lam . g`` with respect to those arguments at fixed ``x``.

    The same as ``jax.vjp`` of ``g`` with respect to them, computed differently: XLA's
    reverse pass through the per-tet stress (rotation, volume shift, cofactors) took ~25
    ms for 12k tets on CPU, against ~1 ms forward, from the fused backward kernels
    recomputing their inputs. Here that pass is replaced by a tangent: with
    ``lam . g = sum_e P_e(F_e) : D_e``, ``D_e`` the deformation-gradient increment along
    ``lam``, the derivative through ``F_e`` is ``(dP/dF)^T D_e = (dP/dF) D_e`` because
    ``P`` is the gradient of an energy (its derivative, through the rotation's exact
    derivative, is symmetric). The surrogate differentiated below,
    ``sum_e P_e(F0_e; theta) : D_e(theta) + (dP/dF D)_e : F_e(theta)`` with ``F0`` and the
    tangent held constant, has the same gradient as ``lam . g``, not the same value.

    Arguments:
        x: ``(n, 3)`` positions; q: ``(4, t)`` rotations of ``x``; lam: ``(n, 3)``; the rest
            as for :func:`step_objective`.

    Returns:
        The cotangents, a tuple like the six arguments (``float0`` for integer leaves).
    """
    free = jnp.asarray(model.free_mask)
    lam = lam * free
    sg = jax.lax.stop_gradient

    def surrogate(prep, x_n, v_n, q_n, activation, force):
        terms = _terms(model, prep, x_n, v_n, q_n, activation, force)
        held = _terms(model, *sg((prep, x_n, v_n, q_n, activation, force)))
        y = jnp.where(free > 0, x, x_n)
        f = deformation_gradient(model, prep.dminv, y)
        d = deformation_gradient(model, prep.dminv, lam)
        f0, d0 = sg(f), sg(d)
        _, kd = jax.jvp(lambda f: held.tet(f, q)[1], (f0,), (d0,))
        out = rot.dot(terms.tet(f0, q)[1], d).sum() + rot.dot(sg(kd), f).sum()
        out = out + jnp.sum(terms.inertia(y)[1] * lam)
        if has_vertex_terms(model):
            out = out + jnp.sum(terms.vertex(y)[1] * lam)
        return out

    args = (prep, x_n, v_n, q_n, activation, force)
    value, vjp = jax.vjp(surrogate, *args)
    return vjp(jnp.ones_like(value))


def contact_rows(model: Model, prep: Prepared) -> tuple:
    """The scene's contact row generators with their parameters, ``((generator, params), ...)``:
    its obstacles' (:class:`~softbody.contact.obstacles.ObstacleRows`, on ``params.obstacles``) first,
    if any, then ``build(rows=...)``'s (on ``params.rows``); ``()`` without contact."""
    obstacles = ((ObstacleRows(model.obstacles), prep.obstacles),) if model.obstacles else ()
    return obstacles + tuple(zip(model.rows, prep.rows))


def step_problem(model: Model, prep: Prepared, state: State, activation, force):
    """The :class:`~softbody.solvers.StepProblem` of one step (or static solve, as
    ``prep.inertia`` says) from ``state``.

    Returns:
        ``(problem, x0, threshold, scale)``: the problem, the start iterate ``(n, 3)``, the
        force residual to reach and the residual's scale (see :func:`step_objective`).
    """
    evaluate, scale = step_objective(model, prep, state.x, state.v, state.rot, activation, force)
    solver = model.linear_solver
    pattern = model.pattern
    opts = model.options
    free = jnp.asarray(model.free_mask)
    problem = StepProblem(
        evaluate=evaluate,
        precondition=lambda g: solver.solve(pattern, prep.factor, g),
        diagonal=prep.data[jnp.asarray(model.diag_to_data)][:, None],
        x_n=state.x, v_n=state.v, mass=prep.mass, free=free, dt=prep.dt,
        time=state.t, rows=contact_rows(model, prep), prepared=prep.step,
        blocks=model.contact_blocks,
        forces0=state.contact, bodies=model.vertex_bodies)
    x0 = prep.inertia.start(state.x, state.v, free)
    if prep.inertia.static:
        # Actuators may load a body with no external force: measure the residual against
        # the load and the initial force imbalance together.
        scale = scale + jnp.sqrt(jnp.sum(evaluate(x0, state.rot)[1] ** 2))
    return problem, x0, opts.tol * scale + opts.atol, scale


def solve_step(model: Model, prep: Prepared, state: State, activation, force, *,
               unrolled=False) -> tuple[Solution, StepInfo]:
    """Run the model's composed step (:class:`softbody.solvers.Step`) on one step (or a static
    solve, as ``prep.inertia`` says).

    ``unrolled=Unroll(extra=k)`` runs a fixed-trip loop that reverse-mode autodiff
    differentiates as it ran, with ``k`` iterations after convergence (see
    :func:`softbody.solvers.iterate` and :class:`softbody.solvers.Unroll`);
    ``False`` runs a ``while_loop`` (differentiate it with the implicit adjoint,
    :class:`softbody.gradients.Implicit`).
    """
    problem, x0, threshold, scale = step_problem(model, prep, state, activation, force)
    opts = model.options
    sol = model.step.run(problem, x0, state.rot, threshold, opts.max_iter, unrolled)
    inverted = jnp.sum(rot.det3(deformation_gradient(model, prep.dminv, sol.x)) <= 0)
    inverted0 = jnp.sum(rot.det3(deformation_gradient(model, prep.dminv, state.x)) <= 0)
    converged = sol.gnorm <= threshold
    finite = jnp.all(jnp.isfinite(sol.x)) & jnp.isfinite(sol.gnorm)
    info = StepInfo(iterations=sol.iterations, evaluations=sol.evaluations,
                    residual=sol.gnorm / (scale + opts.atol / opts.tol), converged=converged, inverted=inverted,
                    result=RESULTS.of(finite=finite, converged=converged, inverted=inverted, inverted0=inverted0,
                                      overflow=sol.overflow, tunnelled=sol.tunnelled),
                    fallback=jnp.asarray(sol.fallback), overflow=jnp.asarray(sol.overflow),
                    tunnelled=jnp.asarray(sol.tunnelled, jnp.int32))
    return sol, info


def accelerations(model: Model, prep: Prepared, state: State, activation, force) -> tuple[Array, Array]:
    """The accelerations ``M^-1 (f(x) - alpha M v - f_beta(x, v) + f_d(x, v) + M g + f_ext)``
    of the semi-discrete model at ``state`` (``f = -dE/dx`` the elastic and actuator forces,
    ``f_beta`` the strain-rate damping force ``beta w_s V R sym(R^T F')``, ``f_d = -dD/dv``
    the dissipation terms' forces, e.g. drag): what the
    explicit integrator steps with and what starts BDF2.

    Arguments:
        model, prep: the scene and its prepared data; state: positions, velocities and
            rotations (warm start of the local step).
        activation: ``(n_channels,)``; force: ``(n, 3)`` external forces or ``None``.

    Returns:
        ``(a (n, 3), rot (4, t))``: accelerations (0 on fixed vertices) and the rotations
        of the local step at ``state.x``.
    """
    x, v = state.x, state.v
    # The static objective's gradient is dE/dx - M g - f_ext: the forces without inertia.
    forces = dataclasses.replace(prep, inertia=Statics())
    evaluate, _ = step_objective(model, forces, x, v, None, activation, force)  # v: dissipations' velocity
    free = jnp.asarray(model.free_mask)
    _, grad, q = evaluate(x, state.rot)  # dE/dx - M g - f_ext on the free vertices
    total = -grad - prep.mass_alpha * v
    if model.stiffness_damping:
        f = deformation_gradient(model, prep.dminv, x)
        r = rot.rotation(f, q, 0)[0]  # the rotations of q, with the maximiser's derivative
        f_rate = jnp.einsum("tai,ajt->ijt", v[jnp.asarray(model.mesh.tets)], shape_gradients(prep.dminv))
        stress = strain_rate_damping(f + f_rate, f, r, prep.volume, prep.w_b, 1.0)[1]
        total = total - scatter_stress(model, prep.dminv, stress)
    return free * total / jnp.maximum(prep.mass, 1e-300), q

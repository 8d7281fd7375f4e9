"""The objective of one implicit step, and the loop that minimises it.

See :mod:`softbody.simulate` for the equations. Both the forward solve and the implicit
adjoint (:mod:`softbody.gradients`) are built on :func:`step_objective`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp

from softbody import rotation as rot
from softbody.elastic import corotated, deformation_gradient, scatter_stress, strain_rate_damping
from softbody.solvers import Solution, StepProblem

if TYPE_CHECKING:
    from softbody.model import Model, Prepared, State

Array = jax.Array


class StepInfo(eqx.Module):
    """Per-step solver statistics (arrays; stacked over steps in a rollout)."""

    iterations: Array
    evaluations: Array
    residual: Array  # |grad Phi| / (|M s / h^2| + atol / tol): the relative residual reached
    converged: Array
    inverted: Array  # number of inverted (det F <= 0) tets at the step's end



def step_objective(model: Model, prep: Prepared, x_n, v_n, q_n, activation, force, *, static: bool):
    """The step objective: ``(evaluate, scale)``.

    ``evaluate(x, q) -> (phi, g, q)`` gives ``Phi(x)``, its gradient ``(n, 3)`` on the free
    vertices (zero on fixed ones, whose positions are taken from ``x_n`` whatever ``x``
    holds) and the rotations of ``x``; ``scale`` is ``|M s / h^2|`` over free vertices
    (dynamics) or ``|f|`` (statics), the denominator of the relative residual.
    """
    h = model.options.dt
    gravity = jnp.asarray(model.options.gravity)
    free = jnp.asarray(model.free_mask)
    mass = prep.mass
    load = mass * gravity + (0.0 if force is None else force)
    if static:
        s = x_n
        scale = jnp.sqrt(jnp.sum((load * free) ** 2))
    else:
        s = x_n + h * v_n + h * h * load / jnp.maximum(mass, 1e-300)
        s = jnp.where(free > 0, s, x_n)
        scale = jnp.sqrt(jnp.sum((mass * s * free) ** 2)) / h**2
    iters = model.options.rotation_iterations
    damped = not static and model.stiffness_damping
    if damped:
        f_n = deformation_gradient(model, prep.dminv, x_n)
        r_n, _ = rot.rotation(f_n, q_n, iters + 1)

    # Each term's slice of the activation vector, and the volume targets (fixed per step).
    slices, offset = [], 0
    for term in model.terms:
        slices.append(activation[offset:offset + len(term.channel_names)])
        offset += len(term.channel_names)
    target = 3.0
    for term, tp, a in zip(model.terms, prep.terms, slices):
        if hasattr(term, "volume_targets"):
            idx, s_t = term.volume_targets(tp, a)
            target = (jnp.full(model.n_tets, 3.0) if isinstance(target, float) else target).at[idx].set(3.0 * s_t)

    def evaluate(x, q):
        x = jnp.where(free > 0, x, x_n)
        f = deformation_gradient(model, prep.dminv, x)
        r, q = rot.rotation(f, q, iters)
        energy, stress = corotated(f, r, prep.volume, prep.w_s, prep.w_v, target)
        energy = jnp.sum(energy)
        if damped:
            e_d, s_d = strain_rate_damping(f, f_n, r_n, prep.volume, prep.w_b, h)
            energy, stress = energy + jnp.sum(e_d), stress + s_d
        vertex_grad = 0.0
        for term, tp, a in zip(model.terms, prep.terms, slices):
            if hasattr(term, "energy_and_stress"):
                idx = jnp.asarray(tp.tets)
                e_t, s_t = term.energy_and_stress(f[:, :, idx], tp, a)
                energy = energy + jnp.sum(e_t)
                stress = stress.at[:, :, idx].add(s_t)
            if hasattr(term, "energy_and_gradient"):
                e_t, g_t = term.energy_and_gradient(x, tp, a)
                energy, vertex_grad = energy + e_t, vertex_grad + g_t
        grad = scatter_stress(model, prep.dminv, stress) + vertex_grad
        if static:
            phi = energy - jnp.sum(load * x)
            grad = grad - load
        else:
            dx, dn = (x - s) * free, (x - x_n) * free
            phi = (energy + 0.5 * jnp.sum(mass * dx * dx) / h**2
                   + 0.5 * jnp.sum(prep.mass_alpha * dn * dn) / h)
            grad = grad + mass * dx / h**2 + prep.mass_alpha * dn / h
        return phi, grad * free, q

    return evaluate, scale


def solve_step(model: Model, prep: Prepared, state: State, activation, force, *, static: bool,
               unrolled: bool | int = False) -> tuple[Solution, StepInfo]:
    """Run the model's iteration method on one step (or a static solve).

    ``unrolled=k`` runs a fixed-trip loop that reverse-mode autodiff differentiates as it
    ran, with ``k - 1`` iterations after convergence (see :func:`softbody.solvers.iterate`);
    ``False`` runs a ``while_loop`` (differentiate it with the implicit adjoint,
    :class:`softbody.gradients.Implicit`).
    """
    evaluate, scale = step_objective(model, prep, state.x, state.v, state.rot, activation, force, static=static)
    solver = model.linear_solver
    pattern = model.pattern
    opts = model.options
    free = jnp.asarray(model.free_mask)
    problem = StepProblem(
        evaluate=evaluate,
        precondition=lambda g: solver.solve(pattern, prep.factor, g),
        matvec=lambda x: pattern.matvec(prep.data, x),
        diagonal=prep.data[jnp.asarray(model.diag_to_data)][:, None],
        x_n=state.x, v_n=state.v, mass=prep.mass, free=free, dt=0.0 if static else opts.dt,
        time=state.t, obstacles=tuple(zip(model.obstacles, prep.obstacles)), prepared=prep.method)
    x0 = state.x if static else jnp.where(free > 0, state.x + opts.dt * state.v, state.x)
    if static:
        # Actuators may load a body with no external force: measure the residual against
        # the load and the initial force imbalance together.
        scale = scale + jnp.sqrt(jnp.sum(evaluate(x0, state.rot)[1] ** 2))
    threshold = opts.tol * scale + opts.atol
    sol = model.method.run(problem, x0, state.rot, threshold, opts.max_iter, unrolled)
    inverted = jnp.sum(rot.det3(deformation_gradient(model, prep.dminv, sol.x)) <= 0)
    info = StepInfo(iterations=sol.iterations, evaluations=sol.evaluations,
                    residual=sol.gnorm / (scale + opts.atol / opts.tol),
                    converged=sol.gnorm <= threshold, inverted=inverted)
    return sol, info

"""Differentiating through the simulation: the adjoint is a choice, like diffrax's.

Two modes, both exact for what they differentiate (set ``Options(adjoint=...)``):

* :class:`Implicit` (default; DiffPD's idea). Each step's output ``x*`` minimises the step
  objective ``Phi(x; theta)``, so ``grad_x Phi(x*; theta) = 0`` on the free vertices. By
  the implicit function theorem, for a cotangent ``xbar`` of ``x*``::

      H lam = xbar,     thetabar = -(d/dtheta grad_x Phi)^T lam,     H = grad_x^2 Phi(x*)

  ``H`` is the true Hessian, applied matrix-free as a Hessian-vector product (``jvp`` of
  the energy gradient, which runs through the rotation's exact derivative); the system is
  solved by conjugate gradients preconditioned with the prefactored PD matrix, the same
  factorisation the forward pass used. The forward loop itself is never taped, so memory
  per step is one state. The result is the derivative of the *exact* step solution: the
  forward tolerance must be tight for it to match finite differences of the computed
  trajectory (``tol`` <= 1e-8 gives ~1e-6 agreement in the tests; at DiffPD's 1e-4
  the forward error, not the adjoint, dominates). Where the solution is stationary only
  in other coordinates (a skeleton's bones carry joint forces), the step's coordinates
  supply a chart ``x = embed(d)`` (:meth:`~softbody.solvers.Step.implicit_chart`)
  and the same argument runs in ``d`` with the Hessian of ``Phi(embed(d))``. Per step the
  backward pass keeps the step's inputs and solution, not its rotations (the solution's
  are recomputed from positions). Contact scenes use the contact solver's own derivative.
  Reverse mode only: JAX refuses ``jax.jvp``/``jax.jacfwd`` through it ("can't apply
  forward-mode autodiff (jvp) to a custom_vjp function").
* :class:`ImplicitForward`: the same derivative in forward mode: the tangent of ``x*`` for
  a tangent ``theta_dot`` of the inputs solves ``H x_dot = -(d/dtheta grad_x Phi) theta_dot``
  with the same Hessian product, preconditioner, chart and tolerance rule. For Jacobians
  with few inputs (system identification); ``jax.grad`` through it runs but tapes each
  step's linearisation, so use :class:`Implicit` for gradients.
* :class:`Unrolled`: reverse mode through the iterations as they ran (a fixed-trip
  ``scan`` that skips finished iterations), each step and each iteration rematerialised
  (``jax.checkpoint``), and the time loop split into segments of ~sqrt(n_steps) steps
  that are themselves checkpointed, so a rollout's gradient holds O(sqrt(n_steps))
  states, not O(n_steps x iterations), plus one loop state per trip of the step being
  differentiated (``Options.max_iter`` trips: keep it near what a step needs). It
  differentiates what was computed, converged or not, and also supports forward mode
  (``jacfwd``).

:func:`check_grad` compares reverse-mode directional derivatives with (extrapolated)
central finite differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve
from softbody import rotation as rot
from softbody._interfaces import Capabilities
from softbody._types import State
from softbody.elastic import deformation_gradient
from softbody.objective import solve_step, step_gradient_vjp, step_hessian, step_objective
from softbody.solvers import Unroll


Array = jax.Array


class Adjoint:
    """Base class of the differentiation modes; :attr:`capabilities` name the scene
    features a mode cannot differentiate (``build`` refuses them)."""

    capabilities: ClassVar[Capabilities] = Capabilities()

    #: split the time loop into checkpointed segments of about sqrt(n_steps) steps
    segment_checkpoints: bool = False

    def solve(self, model, prep, state, activation, force):
        """One step (or static solve, as ``prep.inertia`` says): returns ``(Solution, StepInfo)``."""
        raise NotImplementedError

    def loop(self, body: Callable, carry, inputs, n_steps: int):
        """The time loop of a rollout, as this mode wants it kept for the backward pass:
        ``lax.scan(body, carry, inputs, length=n_steps)``, nested when
        :attr:`segment_checkpoints` is set (and ``n_steps > 3``): the outer scan keeps
        only segment-start carries, each segment of :func:`segment_length` steps is
        rematerialised in the backward pass (O(sqrt(n_steps)) carries in memory).

        Arguments:
            body: ``(carry, inputs_k) -> (carry, out_k)``, one step.
            carry: the loop's start; inputs: a pytree of ``n_steps`` rows (or ``None``).
            n_steps: the number of steps (static).

        Returns:
            ``(carry, out)`` as ``lax.scan`` returns them (``out`` with ``n_steps`` rows).
        """
        if not (self.segment_checkpoints and n_steps > 3):
            return jax.lax.scan(body, carry, inputs, length=n_steps)
        k = segment_length(n_steps)
        segments = jax.tree.map(lambda a: a.reshape((n_steps // k, k) + a.shape[1:]), inputs)

        @jax.checkpoint
        def segment(carry, seg_inputs):
            return jax.lax.scan(body, carry, seg_inputs, length=k)

        carry, out = jax.lax.scan(segment, carry, segments, length=n_steps // k)
        return carry, jax.tree.map(lambda a: a.reshape((n_steps,) + a.shape[2:]), out)


@dataclass(frozen=True)
class Unrolled(Adjoint):
    """Reverse mode through the iterations as run, with rematerialisation.

    Attributes:
        segment_checkpoints: checkpoint segments of ~sqrt(n_steps) steps (memory
            O(sqrt(n_steps)) states for ~one extra forward pass).
        remat: rematerialise each step and each iteration in the backward pass
            (``jax.checkpoint``), so the tape holds one loop state per iteration of the
            step being differentiated; ``False`` is plain autodiff (for comparison).
        extra_iterations: iterations run after each step has converged. They leave the
            converged positions (nearly) unchanged but let the derivative of the iterates
            converge too, which lags behind the iterates: on the gradient tests' cantilever
            the derivative with respect to ``nu`` was 3e-6 off at ``tol=1e-12`` without them.
    """

    segment_checkpoints: bool = True
    extra_iterations: int = 20
    remat: bool = True

    capabilities: ClassVar[Capabilities] = Capabilities(
        refuses={"contact": "differentiates the iterations as they ran, but a step with contact is "
                              "differentiated through the fixed point of its contact iteration (softbody.contact.fixed_point)"},
        instead="use the default adjoint, Implicit() (or ImplicitForward())")

    def solve(self, model, prep, state, activation, force):

        unroll = Unroll(extra=self.extra_iterations, remat=self.remat)

        def run(prep, state, activation, force):
            return solve_step(model, prep, state, activation, force, unrolled=unroll)

        if self.remat:
            run = jax.checkpoint(run, prevent_cse=False)
        return run(prep, state, activation, force)


@dataclass(frozen=True)
class Implicit(Adjoint):
    """Implicit differentiation of each converged step (see the module docstring).

    Attributes:
        tol: relative residual of the adjoint solve ``H lam = xbar``; ``None`` (default)
            follows the forward tolerance, ``Options.tol`` clipped to [1e-10, 1e-5]: the
            step solution is only that accurate, so a tighter adjoint buys little. Above
            1e-5 the adjoint's own error takes over. Measured on the shared cantilever
            against a gradient at tolerance 1e-10 (relative error of the activation / force
            gradients): forward 1e-4 with adjoint 1e-6, 1e-5, 1e-4: 1.8e-5 / 4.3e-5,
            2.4e-5 / 4.6e-5, 1.5e-4 / 2.1e-4; forward 1e-6 with adjoint 1e-6, 1e-7:
            8.1e-7 / 1.3e-6, 2.7e-7 / 6.2e-7. At forward 1e-4 the default takes ~102
            conjugate-gradient iterations per step (~113 at 1e-6, ~148 at 1e-10).
        max_iter: conjugate-gradient iteration cap.
        segment_checkpoints: as for :class:`Unrolled` (off by default: an implicit step
            keeps only its inputs and output for the backward pass).
    """

    tol: float | None = None
    max_iter: int = 2000
    segment_checkpoints: bool = False

    def solve(self, model, prep, state, activation, force):

        if model.has_contact:
            # Contact adds impulses beyond the stationarity of Phi: the contact solver
            # carries its own implicit derivative (active set held fixed).
            return solve_step(model, prep, state, activation, force)

        def forward(prep, x_n, v_n, q_n, t, activation, force):
            sol, info = solve_step(model, prep, State(x_n, v_n, q_n, t), activation, force)
            return sol, info

        @jax.custom_vjp
        def solve(prep, x_n, v_n, q_n, t, activation, force):
            return forward(prep, x_n, v_n, q_n, t, activation, force)

        def solve_fwd(prep, x_n, v_n, q_n, t, activation, force):
            sol, info = forward(prep, x_n, v_n, q_n, t, activation, force)
            # Rotations are the largest per-step arrays (4 per tet): keep the step-start
            # ones only where stiffness damping reads them, and recompute the solution's
            # in the backward pass (the maximising rotation is unique on non-inverted tets).
            q_keep = q_n if prep.inertia.damped(model.stiffness_damping) else None
            return (sol, info), (prep, x_n, v_n, q_keep, t, activation, force, sol.x)

        def solve_bwd(res, cts):
            prep, x_n, v_n, q_n, t, activation, force, xs = res
            xbar = cts[0].x
            free = jnp.asarray(model.free_mask)
            system = _StepSystem.at(model, prep, x_n, v_n, q_n, activation, force, xs)
            q_n = system.q_n
            tol = self.tol if self.tol is not None else model.options.adjoint_tol
            lam = system.push(_pcg(system.hvp, system.precondition, system.pull(xbar), tol, self.max_iter))
            ct_prep, ct_xn, ct_vn, ct_qn, ct_a, ct_f = step_gradient_vjp(
                model, prep, x_n, v_n, q_n, activation, force, xs, system.qs, -lam)
            ct_xn = ct_xn + xbar * (1.0 - free)  # fixed vertices: x* = x_n there
            return ct_prep, ct_xn, ct_vn, ct_qn, jnp.zeros_like(t), ct_a, ct_f

        solve.defvjp(solve_fwd, solve_bwd)
        return solve(prep, state.x, state.v, state.rot, state.t, activation, force)


@dataclass(frozen=True)
class ImplicitForward(Implicit):
    """The implicit derivative of :class:`Implicit` in forward mode (``jax.jvp``,
    ``jax.jacfwd``), for Jacobians with few inputs and many outputs (system
    identification's Levenberg-Marquardt).

    For a tangent ``theta_dot`` of the step inputs, the solution's tangent solves
    ``H x_dot = -(d/dtheta grad_x Phi) theta_dot`` with the same Hessian product,
    preconditioner, chart and tolerance rule (attributes as for :class:`Implicit`) as
    the reverse mode's adjoint solve. Reverse mode (``jax.grad``) also runs, by JAX
    transposing the tangent computation, but it keeps the linearisation of every step's
    per-tet terms on the tape and reverses XLA's derivative of them: use
    :class:`Implicit` there. (JAX lets one function carry a custom JVP or a custom VJP,
    not both, so the two modes are two adjoints.)
    """

    def solve(self, model, prep, state, activation, force):

        if model.has_contact:
            # The contact solver's own implicit derivative is a custom JVP already.
            return solve_step(model, prep, state, activation, force)

        @jax.custom_jvp
        def solve(prep, x_n, v_n, q_n, t, activation, force):
            return solve_step(model, prep, State(x_n, v_n, q_n, t), activation, force)

        @solve.defjvp
        def solve_jvp(primals, tangents):
            prep, x_n, v_n, q_n, t, activation, force = primals
            sol, info = solve(*primals)
            free = jnp.asarray(model.free_mask)
            system = _StepSystem.at(model, prep, x_n, v_n, q_n, activation, force, sol.x)
            args = (prep, x_n, v_n, q_n, activation, force)
            dargs = tangents[:4] + tangents[5:]
            _, dg = jax.jvp(lambda *a: system.residual(sol.x, *a), args, dargs)
            tol = self.tol if self.tol is not None else model.options.adjoint_tol
            # custom_linear_solve (H is symmetric) keeps the rule transposable for reverse mode.
            d = jax.lax.custom_linear_solve(
                system.hvp, system.pull(dg), lambda hvp, b: _pcg(hvp, system.precondition, b, tol, self.max_iter),
                symmetric=True)
            dx = -system.push(d) + tangents[1] * (1.0 - free)  # fixed vertices: x* = x_n there
            zeros = jax.tree.map(_zero_tangent, (sol, info))
            return (sol, info), (zeros[0]._replace(x=dx), zeros[1])

        return solve(prep, state.x, state.v, state.rot, state.t, activation, force)


def _zero_tangent(a):
    """A zero tangent for ``a`` (``float0`` for integer and boolean arrays)."""
    if jnp.issubdtype(jnp.result_type(a), jnp.inexact):
        return jnp.zeros_like(a)
    return np.zeros(np.shape(a), jax.dtypes.float0)


class _StepSystem(NamedTuple):
    """One step's stationarity system at its solution ``xs``, shared by both implicit modes.

    With ``g(x; theta)`` the step gradient (zero at ``xs`` on the free vertices, or, with the
    coordinates' chart ``x = embed(d)``, zero in the chart's coordinates ``d``),
    ``push(hvp^-1 pull(b))`` applies the inverse of its Hessian to ``b`` ``(n, 3)``:
    reverse mode applies it to a cotangent of ``xs``, forward mode to ``-dg/dtheta
    theta_dot``. Without a chart, ``pull`` masks the fixed vertices and ``push`` is the
    identity; ``precondition`` solves with the prefactored PD matrix (or the chart's own
    preconditioner).
    """

    qs: Array  # (4, t) rotations of xs
    q_n: Array  # the step-start rotations (xs's where the objective does not read them)
    residual: Callable  # (x, prep, x_n, v_n, q_n, activation, force) -> g (n, 3)
    hvp: Callable
    precondition: Callable
    pull: Callable  # (n, 3) -> system space
    push: Callable  # system space -> (n, 3)

    @classmethod
    def at(cls, model, prep, x_n, v_n, q_n, activation, force, xs) -> "_StepSystem":
        """The system of the step from ``(x_n, v_n, q_n)`` whose solution is ``xs``
        (``q_n`` may be ``None`` where the objective does not read it)."""

        free = jnp.asarray(model.free_mask)
        qs = rot.cold_start(deformation_gradient(model, prep.dminv, jnp.where(free > 0, xs, x_n)))
        if q_n is None:
            q_n = qs  # unread: the objective reads q_n only with stiffness damping

        def residual(x, prep, x_n, v_n, q_n, activation, force):
            evaluate, _ = step_objective(model, prep, x_n, v_n, q_n, activation, force)
            return evaluate(x, qs)[1]

        args = (prep, x_n, v_n, q_n, activation, force)
        chart = model.step.implicit_chart(jax.lax.stop_gradient(prep.step), xs, free)
        if chart is None:
            factor = jax.lax.stop_gradient(prep.factor)
            solver, pattern = model.linear_solver, model.pattern
            # The per-tet stress derivative is assembled once; each CG iteration then
            # costs gathers and a 9 x 9 product per tet (step_hessian).
            hvp = step_hessian(model, prep, x_n, v_n, q_n, activation, force, xs, qs)
            return cls(qs, q_n, residual, hvp, lambda r: solver.solve(pattern, factor, r),
                       lambda b: b * free, lambda y: y)
        # Stationary in the chart's coordinates d (x = embed(d)): the reduced gradient
        # J^T g, J = d embed/d d, vanishes; its Jacobian is the Hessian of Phi(embed(d)),
        # symmetric. Vectors of x map to the chart by J^T and back by J. That Hessian is
        # J^T H J plus the chart's curvature weighted by the gradient g (nonzero on the
        # bones: the joint forces).
        embed, precondition, size = chart
        zero = jnp.zeros(size, xs.dtype)
        _, push = jax.linearize(embed, zero)
        pull = jax.linear_transpose(push, zero)
        hessian = step_hessian(model, prep, x_n, v_n, q_n, activation, force, xs, qs)
        g = residual(xs, *args)
        _, curvature = jax.linearize(lambda d: jax.vjp(embed, d)[1](g)[0], zero)

        def hvp(d):
            return pull(hessian(push(d)))[0] + curvature(d)

        return cls(qs, q_n, residual, hvp, precondition, lambda b: pull(b)[0], push)


def _pcg(matvec, precondition, b, tol, max_iter):
    """Solve ``H x = b`` (``H`` the step Hessian in its chart, ``b`` of any shape) by
    preconditioned conjugate gradients (:func:`softbody.linsolve.conjugate_gradients`),
    from ``x0 = precondition(b)``, until ``|b - H x| <= tol |b|``."""
    return linsolve.conjugate_gradients(matvec, precondition, b, precondition(b), tol=tol, max_iter=max_iter)


def segment_length(n_steps: int) -> int:
    """Steps per checkpointed segment: about sqrt(n_steps), dividing n_steps."""
    target = max(1, int(round(math.sqrt(n_steps))))
    for k in range(target, n_steps + 1):
        if n_steps % k == 0:
            return k
    return n_steps


def central_difference(fn, args, direction, eps: float) -> float:
    """Directional derivative of ``fn`` at ``args`` along ``direction`` (a pytree like
    ``args``): central differences at ``eps`` and ``eps / 2``, Richardson-extrapolated, so
    the truncation error is O(eps^4). ``fn`` is called four times (jit it beforehand)."""

    def central(h):
        plus = jax.tree.map(lambda a, v: a + h * v, args, direction)
        minus = jax.tree.map(lambda a, v: a - h * v, args, direction)
        return (float(fn(plus)) - float(fn(minus))) / (2 * h)

    return (4 * central(eps / 2) - central(eps)) / 3


def random_directions(args, directions=None, *, seed: int = 0) -> dict:
    """Random unit directions in the space of ``args``, one per named mask.

    Arguments:
        args: a pytree of float arrays (the point).
        directions: ``None`` for one direction over all of ``args`` (named ``"all"``), or a
            mapping ``name -> mask``, each mask a pytree like ``args`` whose leaves are 0/1
            (or ``False``/``True``) arrays or scalars selecting the entries the direction
            may move.
        seed: seed of the directions (drawn in the mapping's order).

    Returns:
        ``{name: direction}``, each a pytree like ``args`` of unit Euclidean norm.

    Raises:
        ValueError: if a mask selects no entries.
    """
    leaves, tree = jax.tree.flatten(args)
    if directions is None:
        directions = {"all": jax.tree.map(lambda a: 1.0, args)}
    rng = np.random.default_rng(seed)
    out = {}
    for name, mask in directions.items():
        masks = tree.flatten_up_to(mask)
        d = [rng.standard_normal(np.shape(leaf)) * np.broadcast_to(np.asarray(m, float), np.shape(leaf))
             for leaf, m in zip(leaves, masks)]
        norm = math.sqrt(sum(float(np.sum(x * x)) for x in d))
        if norm == 0:
            raise ValueError(f"direction {name!r} selects no entries")
        out[name] = jax.tree.unflatten(tree, [jnp.asarray(x / norm) for x in d])
    return out


def directional(grad, direction) -> float:
    """The derivative ``grad . direction`` (two pytrees of the same structure)."""
    return sum(float(jnp.sum(g * v)) for g, v in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))


def check_grad(fn, args, *, directions=None, eps: float = 1e-6, seed: int = 0, verbose: bool = True) -> dict:
    """Compare reverse-mode directional derivatives of ``fn`` with central differences.

    ``fn`` and its gradient are compiled once; each direction then costs four forward
    evaluations.

    Arguments:
        fn: scalar function of the pytree ``args`` (e.g. a loss of a rollout).
        args: a pytree of float arrays (the point).
        directions: ``None`` for one random direction over all of ``args``, or a mapping
            ``name -> mask``, each mask a pytree like ``args`` whose leaves are 0/1 (or
            ``False``/``True``) arrays or scalars selecting the entries a random direction
            may move (e.g. one parameter kind).
        eps: the larger of the two finite-difference steps along each unit direction
            (central differences at ``eps`` and ``eps / 2``, Richardson-extrapolated, so the
            truncation error is O(eps^4)).
        seed: seed of the random directions.
        verbose: print one line per direction.

    Returns:
        ``{name: {"ad": dfn . d, "fd": central difference, "rel_error": |ad - fd| / |fd|}}``
        (name ``"all"`` when ``directions`` is None).

    Raises:
        ValueError: if ``fn`` is not scalar or its gradient is not finite.
    """
    value_and_grad = jax.jit(jax.value_and_grad(fn))
    forward = jax.jit(fn)
    value, grad = value_and_grad(args)
    if jnp.ndim(value) != 0:
        raise ValueError(f"check_grad needs a scalar function, got shape {jnp.shape(value)}")
    if not all(bool(jnp.all(jnp.isfinite(g))) for g in jax.tree.leaves(grad)):
        raise ValueError("the gradient is not finite")
    results = {}
    for name, d in random_directions(args, directions, seed=seed).items():
        ad = directional(grad, d)
        fd = central_difference(forward, args, d, eps)
        rel = abs(ad - fd) / max(abs(fd), 1e-300)
        results[name] = {"ad": ad, "fd": fd, "rel_error": rel}
        if verbose:
            print(f"check_grad[{name}]: {ad:.10e} (reverse mode) vs {fd:.10e} (central differences, "
                  f"eps={eps:g}): relative error {rel:.2e}")
    return results

"""The implicit derivative of a fixed point ``x* = F(x*; theta)``.

An iterative solve (the contact solver's splitting iteration) is never differentiated:
the point it returns is wrapped in :func:`fixed_point`, whose custom derivative solves
``(I - dF/dx) dx = dF/dtheta dtheta`` at ``x*`` instead. ``theta`` is everything ``F``
depends on besides ``x``, hoisted out of ``F``'s closure by :func:`closure_convert`
(for the contact solver: material and actuator parameters, the state, obstacle poses and
friction). The linear system is solved by a caller-given solver (the contact solver uses
Anderson acceleration, :func:`softbody.contact.anderson.linear_solve`, which converges where the
forward map does, its iteration matrix being ``dF/dx``) inside
:func:`jax.lax.custom_linear_solve`, so reverse mode solves the transposed system.

**Through contact** (the contact state held fixed): ``F``'s ``where`` selections
(separated, sticking or sliding, which obstacle) are those of ``x*``. The derivative is
exact for the computed contact state up to the forward tolerance; it is the derivative
of a piecewise-smooth map, so it does not see a vertex about to switch state (at the
stick/slip threshold the true derivative jumps). Norms and normalisations are guarded at
zero, so no NaN arises at rest or at zero slip. It is the implicit derivative of every step with contact, in forward and reverse mode
(:func:`softbody.model.build` refuses :class:`softbody.gradients.Unrolled` there); costs one linear fixed-point solve per step and no taped iterations.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax


def closure_convert(fun: Callable, *args):
    """``jax.closure_convert`` that hoists every traced value ``fun`` closes over.

    ``jax.closure_convert`` leaves traced values that cannot carry a tangent (integers,
    such as a host factorisation's handle inside the skeleton's condensation) in the
    closure; passed to :func:`fixed_point` as a non-differentiable argument they then
    leak out of their trace. Here they become arguments too (their tangents are float0).

    Arguments:
        fun: the function to convert, traceable at ``args``.
        args: example arguments (arrays or tracers) fixing the shapes.

    Returns:
        ``(converted, hoisted)``: ``converted(*args, *hoisted)`` computes ``fun(*args)``.
    """
    closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*args)
    traced = [isinstance(c, jax.core.Tracer) for c in closed.consts]
    hoisted = [c for c, t in zip(closed.consts, traced) if t]
    kept = [c for c, t in zip(closed.consts, traced) if not t]
    n_args = len(args)
    out_tree = jax.tree.structure(out_shape)

    def converted(*args_and_hoisted):
        given, lifted = iter(args_and_hoisted[n_args:]), iter(kept)
        consts = [next(given) if t else next(lifted) for t in traced]
        out = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree.leaves(args_and_hoisted[:n_args]))
        return jax.tree.unflatten(out_tree, out)

    return converted, hoisted


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def fixed_point(position, linear_solve, x, q, *consts):
    """``x``, a fixed point of ``position(., q, *consts)``, differentiated implicitly.

    The tangent solves ``(I - dF/dx) dx = dF/dconsts dconsts`` at ``x`` with the active set
    (contact, stick, slide choices) of ``x``; :func:`jax.lax.custom_linear_solve` makes the
    rule transposable, so reverse mode solves the transposed system.

    Arguments:
        position: ``(x, q, *consts) -> F(x)`` (static: ``x``'s shape in, ``x``'s shape
            out), from :func:`closure_convert`.
        linear_solve: ``(matvec, b) -> u`` solving ``matvec(u) = b``, ``matvec = I - dF/dx``
            (static; used for the tangent and, transposed, for the cotangent).
        x: the fixed point (computed without taping, e.g. under ``stop_gradient``).
        q: auxiliary state of the map at ``x`` (rotations), held fixed.
        consts: the values ``F`` depends on (``theta``), the hoisted values of
            :func:`closure_convert`.

    Returns:
        ``x`` itself, carrying the implicit derivative.
    """
    return x


@fixed_point.defjvp
def _fixed_point_jvp(position, linear_solve, primals, tangents):
    x, q, *consts = primals
    _, rhs = jax.jvp(lambda *c: position(x, q, *c), tuple(consts), tuple(tangents[2:]))

    def matvec(u):
        return u - jax.jvp(lambda y: position(y, q, *consts), (x,), (u,))[1]

    dx = jax.lax.custom_linear_solve(matvec, rhs, linear_solve, transpose_solve=linear_solve)
    return x, dx

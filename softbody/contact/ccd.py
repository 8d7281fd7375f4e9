"""Continuous collision detection: did a step tunnel?

Over one step every position moves on a straight line, ``x(t) = x0 + t (x1 - x0)`` for ``t``
in ``[0, 1]``. A step *tunnelled* where, at some ``t``, a surface vertex lay in a surface
triangle or a surface edge met another surface edge: a body passed through another one, or
through itself, between the start and the end of the step, where the contact rows (which
see only the positions at the step's ends) may miss it. This module finds the earliest such
time of each (vertex, triangle) and (edge, edge) pair, in static shapes (``jax.jit``,
``jax.vmap``; no host callbacks).

**Method.** Four points ``p, a, b, c`` are coplanar where ``f(t) = det[b - a, c - a,
p - a](t) = 0``; each column is linear in ``t``, so ``f`` is a cubic (for an edge pair
``(p, q)``, ``(r, s)``: ``det[q - p, s - r, r - p]``). Its real roots in ``[0, 1]`` come
from *monotone bracketing*: the roots and the extremum of the quadratic ``f'`` (by the
cancellation-free formula ``q = -(b + sign(b) sqrt(b**2 - 4 a c)) / 2``, roots ``q / a``
and ``c / q``, each clipped to ``[0, 1]``) split ``[0, 1]`` into four intervals on which
``f`` is monotone, and each interval where ``f`` changes sign holds exactly one root, found
by bisection: a fixed :data:`ITERATIONS` (56) halvings that compare only signs, locating
the root to ``2**-56`` in ``t``. Degenerate cubics need no special case: under pure
translation of the triangle the cubic and quadratic coefficients vanish (``f`` is linear,
``f'`` constant: its "roots" are clipped to the ends), and where the four points stay
coplanar ``f`` vanishes altogether. An extra split point is harmless (a monotone interval
cut in two is two monotone intervals), and a split point off by rounding can only hide a
pair of roots closer than that error, a grazing touch that the tolerance test at the split
point itself sees. Every division is guarded: nothing turns NaN for finite input.

**Candidate times.** A coplanarity root is where a crossing can happen; whether it does is
a geometric test at that time. The tested times of a pair are ``t = 0`` and ``t = 1``, the
three split points (where ``f`` may touch zero without changing sign), the four interval
roots (or interval ends), and the roots and extremum of the pair's *in-plane* functions:
quadratics that vanish where the point crosses the line of one of the triangle's edges
(``n . ((b - p) x (c - p))`` and its two rotations) or an end of one edge crosses the line
of the other, measured against the fixed unit normal ``n`` of the pair's plane at
mid-step: 18 times for a vertex-triangle pair, 21 for an edge pair. These catch a point
moving *within* the triangle's plane into it (the coplanar-throughout case, where every
time is a root of ``f``): the earliest time it is inside is 0 or a time it crosses an
edge's line. Limits: with a plane that turns during such a step the in-plane functions are
approximate (exact for a fixed plane); a triangle of zero area throughout (or two edges
collinear throughout) has no plane, and is met only at the tested times (a mesh's edge
pairs see a point crossing such a triangle's edges).

**Tolerance.** At a tested time the pair *meets* where the distance from the point to the
triangle (from one segment to the other) is at most ``eta = tol * L``, with ``L`` the
pair's size: the largest distance of any of its positions, at either end of the step, from
the first triangle vertex (first edge end) at the start. The distances are Euclidean
distances to the closed triangle (segment), robust for degenerate triangles and parallel
edges. The default ``tol`` (:data:`TOL`, ``1e-9``) is far above the rounding of ``f`` at a
root (about ``1e-16 L`` for a well-shaped triangle, more for slivers) and far below any
contact thickness. A touch within ``eta`` counts as an impact, so a pair already touching at
``t = 0`` has time of impact 0. The time reported is the earliest tested time at which the
pair meets: for a transversal crossing, the root of ``f`` (to ``2**-56``), or earlier by at
most ``eta`` over the relative speed where the pair grazes within ``eta`` first.

"No impact" is ``+inf`` throughout.

**Cost.** Per pair: 4 x 56 evaluations of a cubic, three quadratic formulas, then 18 (21)
distance tests. All of it is elementwise over the candidate buffers (no data-dependent
control flow), so the cost grows with the buffers' capacities, not with the number of
crossings: a few microseconds per slot of either buffer on 2 CPU cores.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from softbody.contact import broad_phase

__all__ = ["ITERATIONS", "TOL", "Crossings", "Tunnelled", "crossings", "edge_candidates",
           "edge_edge_toi", "surface_edges", "tunnelled", "vertex_triangle_toi"]

#: Default relative tolerance: a pair meets within ``TOL`` times its size.
TOL = 1e-9
#: Bisection halvings per root (locates a root in ``[0, 1]`` to ``2**-56``).
ITERATIONS = 56
#: A triangle (a pair of edges) counts as degenerate (parallel) where the sine of its angle
#: is below this many machine epsilons; the distance then comes from the edges (the ends).
_DEGENERATE = 1000.0


# ---------------------------------------------------------------------------------------------
# polynomials


def _dot(u, v):
    return jnp.sum(u * v, -1)


def _triple(u0, du, v0, dv, w0, dw):
    """Coefficients ``(..., 4)`` (constant first) of the cubic ``u(t) . (v(t) x w(t))`` for
    ``u(t) = u0 + t du`` etc. (each ``(..., 3)``)."""
    vw = jnp.cross(v0, w0)
    dvw = jnp.cross(dv, w0) + jnp.cross(v0, dw)
    dvdw = jnp.cross(dv, dw)
    c0 = _dot(u0, vw)
    c1 = _dot(du, vw) + _dot(u0, dvw)
    c2 = _dot(u0, dvdw) + _dot(du, dvw)
    c3 = _dot(du, dvdw)
    return jnp.stack([c0, c1, c2, c3], -1)


def _poly(c, t):
    """The polynomials ``c`` (..., 4) at the times ``t`` (..., k), by Horner's rule."""
    c = c[..., None, :]
    return ((c[..., 3] * t + c[..., 2]) * t + c[..., 1]) * t + c[..., 0]


def _bisect(c, lo, hi):
    """The root of each cubic ``c`` (..., 4) in each interval ``[lo, hi]`` (..., k) on which
    it is monotone: the first bisection point at or past the sign change; ``hi`` where the
    sign does not change."""
    f_lo, f_hi = _poly(c, lo), _poly(c, hi)
    s = jnp.sign(f_lo)
    found = s * jnp.sign(f_hi) <= 0

    def halve(_, state):
        a, b = state
        m = 0.5 * (a + b)
        right = jnp.sign(_poly(c, m)) * s > 0
        return jnp.where(right, m, a), jnp.where(right, b, m)

    _, b = jax.lax.fori_loop(0, ITERATIONS, halve, (lo, hi))
    return jnp.where(found, jnp.where(f_lo == 0, lo, b), hi)


def _ratio(num, den):
    """``num / den``, 2 where ``den`` is 0 (clipped to 1 by the callers: a time tested anyway)."""
    return jnp.where(den != 0, num / jnp.where(den != 0, den, 1.0), 2.0)


def _quadratic(a, b, c):
    """Times (..., 3) in ``[0, 1]`` of ``a t**2 + b t + c`` (each (...)): its real roots and
    its extremum, each clipped to ``[0, 1]`` (a value that is none of these, or lies outside,
    becomes 0 or 1). The roots by the cancellation-free formula ``q = -(b + sign(b) sqrt(d))
    / 2``, ``q / a`` and ``c / q``; a linear or constant polynomial is no special case."""
    d = jnp.maximum(b * b - 4 * a * c, 0.0)
    q = -0.5 * (b + jnp.where(b < 0, -1.0, 1.0) * jnp.sqrt(d))
    t = jnp.stack([_ratio(q, a), _ratio(c, q), _ratio(-0.5 * b, a)], -1)
    return jnp.clip(t, 0.0, 1.0)


def _times(c):
    """Tested times (..., 9) in ``[0, 1]`` of the cubic ``c`` (..., 4): 0, 1, the three split
    points (the roots and the extremum of ``f'``, sorted) and the root (or end) of each of
    the four intervals between them."""
    split = jnp.sort(_quadratic(3 * c[..., 3], 2 * c[..., 2], c[..., 1]), -1)
    zero, one = jnp.zeros_like(split[..., :1]), jnp.ones_like(split[..., :1])
    roots = _bisect(c, jnp.concatenate([zero, split], -1), jnp.concatenate([split, one], -1))
    return jnp.concatenate([zero, one, split, roots], -1)


def _side_times(c):
    """Tested times (..., 3 F) of the quadratics ``c`` (..., F, 4) (cubic coefficient 0)."""
    t = _quadratic(c[..., 2], c[..., 1], c[..., 0])
    return t.reshape(*t.shape[:-2], t.shape[-2] * t.shape[-1])


# ---------------------------------------------------------------------------------------------
# distances


def _point_segment2(p, a, b):
    """Squared distance (...) from ``p`` to the segment ``[a, b]`` (each (..., 3))."""
    d, w = b - a, p - a
    dd = _dot(d, d)
    s = jnp.clip(_dot(w, d) / jnp.where(dd > 0, dd, 1.0), 0.0, 1.0)
    r = w - s[..., None] * d
    return _dot(r, r)


def _point_triangle2(p, a, b, c):
    """Squared distance (...) from ``p`` to the closed triangle ``(a, b, c)``; a degenerate
    triangle (a segment or a point) by its edges."""
    n = jnp.cross(b - a, c - a)
    nn = _dot(n, n)
    eps = jnp.finfo(nn.dtype).eps
    ab, ac = b - a, c - a
    proper = nn > (_DEGENERATE * eps) ** 2 * _dot(ab, ab) * _dot(ac, ac)
    inside = (_dot(n, jnp.cross(b - p, c - p)) >= 0) & (_dot(n, jnp.cross(c - p, a - p)) >= 0) \
        & (_dot(n, jnp.cross(a - p, b - p)) >= 0)
    h = _dot(n, p - a)
    face = jnp.where(proper & inside, h * h / jnp.where(proper, nn, 1.0), jnp.inf)
    edges = jnp.minimum(jnp.minimum(_point_segment2(p, a, b), _point_segment2(p, b, c)),
                        _point_segment2(p, c, a))
    return jnp.minimum(face, edges)


def _segment_segment2(p, q, r, s):
    """Squared distance (...) between the closed segments ``[p, q]`` and ``[r, s]``."""
    d1, d2, w = q - p, s - r, p - r
    a, e, b = _dot(d1, d1), _dot(d2, d2), _dot(d1, d2)
    c, f = _dot(d1, w), _dot(d2, w)
    den = a * e - b * b
    eps = jnp.finfo(den.dtype).eps
    crossing = den > (_DEGENERATE * eps) ** 2 * a * e
    safe = jnp.where(crossing, den, 1.0)
    u, v = (b * f - c * e) / safe, (a * f - b * c) / safe
    interior = crossing & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    gap = w + u[..., None] * d1 - v[..., None] * d2
    inner = jnp.where(interior, _dot(gap, gap), jnp.inf)
    ends = jnp.minimum(jnp.minimum(_point_segment2(p, r, s), _point_segment2(q, r, s)),
                       jnp.minimum(_point_segment2(r, p, q), _point_segment2(s, p, q)))
    return jnp.minimum(inner, ends)


# ---------------------------------------------------------------------------------------------
# one pair


def _is_traced(value) -> bool:
    return isinstance(value, jax.core.Tracer)


def _check_tol(tol) -> None:
    if _is_traced(tol):
        return
    t = np.asarray(tol)
    if t.shape != () or not np.issubdtype(t.dtype, np.number) or not np.isfinite(t) or t <= 0:
        raise ValueError(f"tol must be a finite scalar > 0, got {tol!r}")


def _prepare(points, tol):
    _check_tol(tol)
    points = [jnp.asarray(x) for x in points]
    dtype = jnp.result_type(*points, float)
    points = jnp.broadcast_arrays(*(x.astype(dtype) for x in points))
    if points[0].ndim < 1 or points[0].shape[-1] != 3:
        raise ValueError(f"positions must have shape (..., 3), got {points[0].shape}")
    return points


def _unit(v):
    norm = jnp.sqrt(_dot(v, v))[..., None]
    return jnp.where(norm > 0, v / jnp.where(norm > 0, norm, 1.0), 0.0)


def _size(start, points):
    """The pair's size (...): the largest distance of ``points`` from ``start``."""
    return jnp.max(jnp.stack([jnp.sqrt(_dot(x - start, x - start)) for x in points], -1), -1)


def _earliest(t, distance2, eta):
    hit = distance2 <= (eta * eta)[..., None]
    return jnp.min(jnp.where(hit, t, jnp.inf), -1)


def _at(t, x0, dx):
    """Positions ``(..., k, 3)`` at the ``k`` times ``t`` ``(..., k)`` of a point moving from
    ``x0`` by ``dx`` ``(..., 3)``."""
    return x0[..., None, :] + t[..., None] * dx[..., None, :]


def vertex_triangle_toi(p0, p1, a0, a1, b0, b1, c0, c1, *, tol=TOL):
    """The earliest time at which a moving point lies in a moving triangle.

    Every position moves linearly over the step, ``x(t) = x0 + t (x1 - x0)``; see the
    module's method and tolerance.

    Arguments:
        p0, p1: (..., 3) the point at the step's start and end.
        a0, a1, b0, b1, c0, c1: (..., 3) the triangle's corners at the start and end. All
            eight broadcast together; finite.
        tol: scalar > 0, the relative tolerance (the point meets the triangle within
            ``tol`` times the pair's size).

    Returns:
        (...) the time of impact in ``[0, 1]``, ``+inf`` where there is none.

    Raises:
        ValueError: positions not of shape (..., 3) or not broadcastable, or a concrete
            ``tol`` not finite and > 0.
    """
    p0, p1, a0, a1, b0, b1, c0, c1 = _prepare((p0, p1, a0, a1, b0, b1, c0, c1), tol)
    dp, da, db, dc = p1 - p0, a1 - a0, b1 - b0, c1 - c0
    plane = _triple(b0 - a0, db - da, c0 - a0, dc - da, p0 - a0, dp - da)
    am, bm, cm = a0 + 0.5 * da, b0 + 0.5 * db, c0 + 0.5 * dc
    n = _unit(jnp.cross(bm - am, cm - am))
    zero = jnp.zeros_like(n)
    side = [_triple(n, zero, u0 - p0, du - dp, v0 - p0, dv - dp)
            for (u0, du), (v0, dv) in (((b0, db), (c0, dc)), ((c0, dc), (a0, da)),
                                       ((a0, da), (b0, db)))]
    t = jnp.concatenate([_times(plane), _side_times(jnp.stack(side, -2))], -1)
    d2 = _point_triangle2(_at(t, p0, dp), _at(t, a0, da), _at(t, b0, db), _at(t, c0, dc))
    eta = tol * _size(a0, (p0, p1, a1, b0, b1, c0, c1))
    return _earliest(t, d2, eta)


def edge_edge_toi(p0, p1, q0, q1, r0, r1, s0, s1, *, tol=TOL):
    """The earliest time at which two moving segments meet.

    Every position moves linearly over the step; see the module's method and tolerance.

    Arguments:
        p0, p1, q0, q1: (..., 3) the first edge's ends ``p`` and ``q`` at the step's start
            and end.
        r0, r1, s0, s1: (..., 3) the second edge's ends ``r`` and ``s``. All eight
            broadcast together; finite.
        tol: scalar > 0, the relative tolerance (the segments meet within ``tol`` times the
            pair's size).

    Returns:
        (...) the time of impact in ``[0, 1]``, ``+inf`` where there is none.

    Raises:
        ValueError: positions not of shape (..., 3) or not broadcastable, or a concrete
            ``tol`` not finite and > 0.
    """
    p0, p1, q0, q1, r0, r1, s0, s1 = _prepare((p0, p1, q0, q1, r0, r1, s0, s1), tol)
    dp, dq, dr, ds = p1 - p0, q1 - q0, r1 - r0, s1 - s0
    plane = _triple(q0 - p0, dq - dp, s0 - r0, ds - dr, r0 - p0, dr - dp)
    n = _unit(jnp.cross((q0 - p0) + 0.5 * (dq - dp), (s0 - r0) + 0.5 * (ds - dr)))
    zero = jnp.zeros_like(n)
    side = [_triple(n, zero, e0, de, x0 - o0, dx - do)
            for (o0, do), e0, de, ends in (((p0, dp), q0 - p0, dq - dp, ((r0, dr), (s0, ds))),
                                           ((r0, dr), s0 - r0, ds - dr, ((p0, dp), (q0, dq))))
            for x0, dx in ends]
    t = jnp.concatenate([_times(plane), _side_times(jnp.stack(side, -2))], -1)
    d2 = _segment_segment2(_at(t, p0, dp), _at(t, q0, dq), _at(t, r0, dr), _at(t, s0, ds))
    eta = tol * _size(p0, (p1, q0, q1, r0, r1, s0, s1))
    return _earliest(t, d2, eta)


# ---------------------------------------------------------------------------------------------
# many pairs


class Crossings(NamedTuple):
    """Times of impact of candidate pairs over one step.

    Attributes:
        vertex_triangle: (Cv,) time of impact of each (vertex, triangle) candidate, ``+inf``
            where none (or the candidate is padding or shares a vertex).
        edge_edge: (Ce,) the same for each (edge, edge) candidate.
        count: () int32 number of candidates with an impact.
        earliest: () the earliest time of impact, ``+inf`` where none.
    """

    vertex_triangle: jax.Array
    edge_edge: jax.Array
    count: jax.Array
    earliest: jax.Array


def _pairs(pairs, name):
    arr = jnp.asarray(pairs)
    if not _is_traced(pairs) and arr.size == 0:
        arr = arr.reshape(0, 2)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{name} must have shape (C, 2), got {arr.shape}")
    if not jnp.issubdtype(arr.dtype, jnp.integer):
        raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
    valid = jnp.all(arr >= 0, -1)
    return jnp.where(valid[:, None], arr, 0), valid


def crossings(x0, x1, triangles, edges, vertex_triangle, edge_edge, *, tol=TOL) -> Crossings:
    """Times of impact of candidate (vertex, triangle) and (edge, edge) pairs over one step.

    Traceable (``jax.jit``, ``jax.vmap``); the index arrays may be traced. Pairs that share
    a vertex (a vertex of its own triangle, two edges with a common end) never count.

    Arguments:
        x0, x1: (n, 3) positions at the step's start and end.
        triangles: (T, 3) int vertex indices of the surface triangles.
        edges: (E, 2) int vertex indices of the surface edges (:func:`surface_edges`).
        vertex_triangle: (Cv, 2) int candidate ``(vertex, triangle row)`` pairs; a row with
            a negative entry is padding.
        edge_edge: (Ce, 2) int candidate ``(edge row, edge row)`` pairs; likewise padded.
        tol: scalar > 0, the relative tolerance of :func:`vertex_triangle_toi`.

    Returns:
        :class:`Crossings`.

    Raises:
        ValueError: positions not of shape (n, 3), or index arrays of the wrong shape or
            not integer, or a concrete ``tol`` not finite and > 0. (Indices past the arrays
            are not checked: gathers clamp them.)
    """
    _check_tol(tol)
    x0, x1 = jnp.asarray(x0), jnp.asarray(x1)
    dtype = jnp.result_type(x0, x1, float)
    x0, x1 = x0.astype(dtype), x1.astype(dtype)
    if x0.ndim != 2 or x0.shape[1] != 3 or x0.shape != x1.shape:
        raise ValueError(f"x0 and x1 must both have shape (n, 3), got {x0.shape} and {x1.shape}")
    tri = jnp.asarray(triangles).reshape(-1, 3)
    edg = jnp.asarray(edges).reshape(-1, 2)
    # empty arrays get one dummy row to gather from (every pair is then padding or invalid)
    x0 = x0 if len(x0) else jnp.zeros((1, 3), dtype)
    x1 = x1 if len(x1) else jnp.zeros((1, 3), dtype)
    tri = tri if len(tri) else jnp.zeros((1, 3), tri.dtype)
    edg = edg if len(edg) else jnp.zeros((1, 2), edg.dtype)
    vt, vt_ok = _pairs(vertex_triangle, "vertex_triangle")
    ee, ee_ok = _pairs(edge_edge, "edge_edge")

    v, abc = vt[:, 0], tri[vt[:, 1]]
    vt_ok = vt_ok & jnp.all(abc != v[:, None], -1)
    toi = vertex_triangle_toi(x0[v], x1[v], x0[abc[:, 0]], x1[abc[:, 0]], x0[abc[:, 1]],
                              x1[abc[:, 1]], x0[abc[:, 2]], x1[abc[:, 2]], tol=tol)
    toi_vt = jnp.where(vt_ok, toi, jnp.inf)

    e, f = edg[ee[:, 0]], edg[ee[:, 1]]
    ee_ok = ee_ok & ~jnp.any(e[:, :, None] == f[:, None, :], (1, 2))
    toi = edge_edge_toi(x0[e[:, 0]], x1[e[:, 0]], x0[e[:, 1]], x1[e[:, 1]], x0[f[:, 0]],
                        x1[f[:, 0]], x0[f[:, 1]], x1[f[:, 1]], tol=tol)
    toi_ee = jnp.where(ee_ok, toi, jnp.inf)

    count = (jnp.sum(jnp.isfinite(toi_vt)) + jnp.sum(jnp.isfinite(toi_ee))).astype(jnp.int32)
    earliest = jnp.min(jnp.concatenate([toi_vt, toi_ee, jnp.full(1, jnp.inf, dtype)]))
    return Crossings(toi_vt, toi_ee, count, earliest)


# ---------------------------------------------------------------------------------------------
# a whole step


def _static(value, name: str) -> np.ndarray:
    if _is_traced(value):
        raise ValueError(f"{name} must be a static (numpy) integer array, got a traced array")
    return np.asarray(value)


def surface_edges(triangles) -> np.ndarray:
    """The distinct edges of a triangle list.

    Arguments:
        triangles: (T, 3) static int array of vertex indices.

    Returns:
        (E, 2) int64 array, each edge once as ``(low index, high index)``, sorted
        lexicographically.

    Raises:
        ValueError: ``triangles`` traced, not integer, or not of shape (T, 3).
    """
    tri = _static(triangles, "triangles")
    if tri.size == 0:
        tri = tri.reshape(0, 3)
    if tri.ndim != 2 or tri.shape[1] != 3 or (tri.size and not np.issubdtype(tri.dtype,
                                                                              np.integer)):
        raise ValueError(f"triangles must be an integer array of shape (T, 3), got {tri.dtype} "
                         f"{tri.shape}")
    e = np.sort(tri[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).astype(np.int64), 1)
    return np.unique(e, axis=0).reshape(-1, 2)


def _touching(edges: np.ndarray) -> int:
    """The number of ordered pairs of an edge list whose two edges are one edge or share an
    end (their swept boxes always overlap)."""
    degree = np.bincount(edges.reshape(-1)) if edges.size else np.zeros(0, np.int64)
    return int(len(edges) + np.sum(degree * (degree - 1)))


def edge_candidates(x0, x1, edges, margin, capacity: int, *, work: int | None = None, groups=None,
                    allowed=None):
    """The (edge, edge) pairs without a common vertex whose swept boxes overlap.

    Runs the broad phase's hashed grid (:func:`softbody.contact.broad_phase.candidates`,
    cost about linear in ``E`` for spread-out geometry): each edge's swept box (its ends at
    both times, grown by ``margin``) is queried as the box a fictitious point sweeps from the
    box's lower to its upper corner, against every edge filed as the degenerate triangle
    ``(a, b, b)``. The grid returns ordered pairs, each edge with itself and with the edges
    that share an end included (their number ``A`` is known from ``edges`` alone); its buffer
    holds ``A + 2 capacity`` of them, and the pairs ``i < j`` without a common vertex are
    compacted into ``capacity`` slots.

    Arguments:
        x0, x1: (n, 3) positions at the step's start and end (may be traced).
        edges: (E, 2) static int array of vertex indices, distinct edges.
        margin: scalar >= 0, as for the broad phase.
        capacity: static int >= 1, the number of output pairs.
        work: static int, the broad phase's budget of box tests (its default where None).
        groups, allowed: optional, as for :func:`softbody.contact.broad_phase.candidates`
            (``(n,)`` static body id per vertex, each edge within one body, and the static
            unordered ``(group_i, group_j)`` pairs that count): only edge pairs between
            allowed bodies are returned.

    Returns:
        ``(pairs, count, overflow)``: (capacity, 2) int32 ``(edge row, edge row)`` pairs with
        ``i < j``, rows past ``count`` ``-1``; () int32 the number of pairs found (at most
        ``capacity`` where ``overflow`` is unset); () bool, some pair may be missing.

    Raises:
        ValueError: as :func:`softbody.contact.broad_phase.candidates`.
    """
    edg = _static(edges, "edges").astype(np.int64).reshape(-1, 2)
    n, count_e = np.shape(x0)[0], len(edg)
    if isinstance(capacity, bool) or not isinstance(capacity, (int, np.integer)) \
            or not 1 <= capacity < 2 ** 31 - 1:
        raise ValueError(f"capacity must be a static int in [1, 2**31 - 1), got {capacity!r}")
    if count_e == 0:
        return jnp.full((capacity, 2), -1, jnp.int32), jnp.int32(0), jnp.bool_(False)
    x0, x1 = jnp.asarray(x0), jnp.asarray(x1)
    dtype = jnp.result_type(x0, x1, float)
    x0, x1 = x0.astype(dtype), x1.astype(dtype)
    ends0, ends1 = x0[edg], x1[edg]  # (E, 2, 3)
    lo = jnp.minimum(ends0.min(1), ends1.min(1))
    hi = jnp.maximum(ends0.max(1), ends1.max(1))
    boxes0, boxes1 = jnp.concatenate([x0, lo]), jnp.concatenate([x1, hi])
    if groups is not None:  # each edge's fictitious point lies in its edge's body
        groups = _static(groups, "groups").astype(np.int64).reshape(-1)
        groups = np.concatenate([groups, groups[edg[:, 0]]])
    # pairs of one edge with itself or with one sharing an end come back only within a body
    touching = _touching(edg) if groups is None or any(a == b for a, b in allowed or ()) else 0
    found = broad_phase.candidates(boxes0, boxes1, np.arange(n, n + count_e), edg[:, [0, 1, 1]],
                                   margin, touching + 2 * capacity, work=work,
                                   exclude_incident=False, groups=groups, allowed=allowed)
    i, j = found.vertex - n, found.triangle
    ei, ej = jnp.asarray(edg)[i], jnp.asarray(edg)[j]
    keep = found.valid & (i < j) & ~jnp.any(ei[:, :, None] == ej[:, None, :], (1, 2))
    dest = jnp.where(keep, jnp.cumsum(keep) - 1, capacity)
    pairs = jnp.full((capacity, 2), -1, jnp.int32).at[dest].set(
        jnp.stack([i, j], 1).astype(jnp.int32), mode="drop")
    count = jnp.sum(keep, dtype=jnp.int32)
    return pairs, count, found.overflow | (count > capacity)


class Tunnelled(NamedTuple):
    """Whether one step tunnelled.

    Attributes:
        count: () int32 number of (vertex, triangle) and (edge, edge) pairs that met
            during the step (one crossing of a surface through another is usually seen by
            several pairs).
        earliest: () the earliest time of impact in ``[0, 1]``, ``+inf`` where none.
        overflow: () bool, a broad-phase buffer overflowed: some pair may not have been
            tested, so ``count`` may be too low.
    """

    count: jax.Array
    earliest: jax.Array
    overflow: jax.Array


def tunnelled(x0, x1, triangles, *, capacity: int, margin=0.0, edge_capacity: int | None = None,
              tol=TOL, groups=None, allowed=None) -> Tunnelled:
    """Whether a surface passed through itself or another surface during one step.

    Tests every surface vertex against every triangle and every edge against every edge
    whose swept boxes overlap (self-contact and contact between bodies alike; pairs sharing
    a vertex excluded). Both candidate lists come from the broad phase's hashed grid
    (:func:`softbody.contact.broad_phase.candidates`; :func:`edge_candidates`), so the
    cost is about linear in the surface's size for spread-out geometry: the grid plus the
    exact tests of :func:`crossings` on every slot of the two fixed buffers (two spheres of
    1000 triangles in all, buffers of 128 and 512 pairs: about 12 ms on 2 CPU cores). Traceable
    (``jax.jit``, ``jax.vmap`` over ``x0``, ``x1``); ``triangles`` and the sizes are static.

    Arguments:
        x0, x1: (n, 3) positions at the step's start and end.
        triangles: (T, 3) static int array, the surface triangles.
        capacity: static int >= 1, the (vertex, triangle) candidate buffer.
        margin: scalar >= 0, grows every swept box (m).
        edge_capacity: static int >= 1, the (edge, edge) candidate buffer (see
            :func:`edge_candidates`); default ``capacity + E`` for ``E`` surface edges.
        tol: scalar > 0, the relative tolerance of :func:`vertex_triangle_toi`.
        groups, allowed: optional, as for :func:`softbody.contact.broad_phase.candidates`:
            only pairs between the allowed bodies count (e.g. ``allowed=[(0, 1)]`` for two
            bodies passing through each other, not through themselves).

    Returns:
        :class:`Tunnelled`. Where ``overflow`` is set, rerun with larger capacities
        (:func:`softbody.contact.broad_phase.required_capacity` sizes the vertex-triangle
        buffer).

    Raises:
        ValueError: as :func:`softbody.contact.broad_phase.candidates` or
            :func:`crossings`.
    """
    edges = surface_edges(triangles)
    tri = np.asarray(triangles).reshape(-1, 3)
    if edge_capacity is None:
        edge_capacity = capacity + len(edges)
    points = np.unique(tri)
    vt = broad_phase.candidates(x0, x1, points, tri, margin, capacity, groups=groups, allowed=allowed)
    vt_pairs = jnp.where(vt.valid[:, None], jnp.stack([vt.vertex, vt.triangle], 1), -1)
    ee_pairs, ee_count, ee_overflow = edge_candidates(x0, x1, edges, margin, edge_capacity, groups=groups,
                                                      allowed=allowed)

    def exact(x0, x1, vt_pairs, ee_pairs):
        found = crossings(x0, x1, tri, edges, vt_pairs, ee_pairs, tol=tol)
        return found.count, found.earliest

    def none(x0, x1, vt_pairs, ee_pairs):
        return jnp.int32(0), jnp.asarray(jnp.inf, jnp.result_type(x0, x1, float))

    # a step whose swept boxes overlap nowhere (surfaces kept apart) skips the exact tests
    count, earliest = jax.lax.cond((vt.count > 0) | (ee_count > 0), exact, none, x0, x1, vt_pairs, ee_pairs)
    return Tunnelled(count, earliest, vt.overflow | ee_overflow)

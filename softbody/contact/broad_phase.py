"""Broad phase for vertex-triangle contact: the (vertex, triangle) pairs whose swept boxes
overlap, in static shapes (usable under ``jax.jit`` and ``jax.vmap``).

**Boxes.** A candidate vertex ``p`` moving from ``x0[p]`` to ``x1[p]`` over a step sweeps the
box ``[min(x0[p], x1[p]) - margin, max(x0[p], x1[p]) + margin]``; a triangle ``(a, b, c)``
sweeps the box of its six corner positions, grown by ``margin`` the same way. Both boxes
grow, so a vertex and a triangle whose swept boxes come within ``2 margin`` of each other
pair up. A pair is a candidate where the two boxes overlap (closed intervals on every
axis), the vertex is not one of the triangle's own (``exclude_incident``), and the bodies
of the two are allowed to touch (``groups``, ``allowed``). :func:`candidates` finds them
inside a traced program; :func:`brute_force` is the exact host reference over all ``P x T``
pairs; :func:`required_capacity` sizes the fixed buffers outside ``jit``.

**Algorithm: a hashed uniform grid with a flat work list.** Each axis ``k`` gets a cell size
``h_k`` a little over half of ``e_v + e_t``, the largest vertex-box and triangle-box extents
along it. Each triangle is filed once, under the cell of its box's lower corner: the cell
is hashed into a table of ``max(2 T, 27 P)`` slots (a power of two; the second term at
most :data:`_TABLE_CAP`: a query of an empty cell rarely meets another cell's entries) and
the triangles are sorted by slot, so each slot's entries are one contiguous run. A vertex box
``[lo, hi]`` can only meet triangles whose lower corner lies in ``[lo - e_t, hi]``, an
interval shorter than ``2 h_k``: at most 3 cells per axis, the up-to-27 neighbouring cells.
Every (vertex, cell) *segment* contributes the entries of its slot, and the segments'
lengths, summed in order, lay all box tests out in one flat list (the *work list*: test
``k`` finds its segment by a running maximum over scattered segment starts, not by a
search). A test counts where the entry's own cell is the queried one (a hash collision
costs a test, never a duplicate or a false pair), the boxes overlap and the filters pass.
The hits are compacted into the first ``count`` of ``capacity`` output slots. Everything
is sorting, scatters, prefix sums and gathers over arrays of size ``T``, ``27 P`` and
``work``: for spread-out geometry (a bounded number of triangles near each vertex) the
cost grows like ``P + T`` (``T log T`` for the sort), not ``P T``. Under ``jax.vmap`` each
scene gets its own grid (cell size from its own boxes) and its own ``count``/``overflow``.

*Bodies.* With ``groups``, where every body may touch at most :data:`MAX_PARTNERS` bodies
(the usual case: a few bodies, or self-contact only), triangles are filed under (cell,
body) and a vertex looks up each partner body's slot in each cell, so it never tests a
body it may not touch (``27 P`` segments per partner). With more partners all bodies
share one grid and each test checks the pair of bodies instead: the tests then include
the forbidden neighbours (a body's own triangles near each of its vertices).

*Why this and not sort-and-sweep.* Sweeping along one axis tests every triangle in a slab
that spans the whole scene across the other two axes: about ``sqrt(T)`` per vertex for a
surface, ``P sqrt(T)`` in all, and a fixed number of neighbours per primitive along the
sweep axis overflows on any large flat scene. The grid tests only triangles near the
vertex in all three axes. *Why a flat work list rather than a fixed number of entries per
cell:* when many primitives fall into one cell (a body folded on itself, a dense patch of
small triangles, a pile of bodies) that cell's tests take what they need from a budget
shared by the whole query; a per-cell bound would have to be paid by every cell of every
query (``27 P`` times the largest occupancy) and would truncate exactly the crowded cells
where contact happens.

**Limits.** Static shapes need two fixed bounds, both static Python ints: ``capacity``
(output pairs) and ``work`` (box tests, below ``2**31``). Nothing that overflows either is
lost silently:

* more overlapping pairs than ``capacity``: the first ``capacity`` (in test order) are
  returned, ``count`` is the exact number of pairs and ``overflow`` is set;
* more box tests than ``work`` (a crowded cell, a coarse grid): the tests past the budget
  are not run, ``overflow`` is set and ``count`` adds each of them as a possible pair (an
  upper bound on the true count, so ``count > capacity`` or ``overflow`` always tells).

A caller checks ``overflow`` after the step, calls :func:`required_capacity` outside
``jit`` for the exact sizes and reruns. What makes the tests grow: the cell size follows
the *largest* box, so one large triangle or one fast vertex coarsens the grid for
everyone (more tests, the same pairs), and so do dense clusters and many primitives
crowded into one cell; hash collisions add tests too. Memory is about 100 bytes per unit
of ``work`` and per segment. To keep the cell arithmetic exact the grid has at most
``2**20`` cells per axis (``2**14`` in float32): a scene wider than that many box extents
gets larger cells. Positions must be finite. In float32 mode, counts past ``2**30`` tests
saturate (``count`` is then ``2**31 - 1``, ``overflow`` set).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

#: The largest hash table the number of queried cells asks for (slots; 1 MB of counts).
_TABLE_CAP = 2 ** 18
#: The 27 cell offsets of a vertex's query block (0..2 on each axis from its lowest cell).
_OFFSETS = np.array([(i, j, k) for i in range(3) for j in range(3) for k in range(3)], np.int32)
_INT32_MAX = np.iinfo(np.int32).max
#: Default box tests per candidate vertex when ``work`` is not given (a closed surface with
#: boxes about a third of an edge long needs 20 to 40).
WORK_PER_VERTEX = 64
#: Bodies with up to this many allowed partners file triangles by body (no tests against
#: bodies they may not touch); past it, all bodies share the grid and each test checks them.
MAX_PARTNERS = 4


class Candidates(NamedTuple):
    """The candidate pairs of one broad-phase query (capacity ``C``).

    Attributes:
        vertex: (C,) int32 vertex index (into the positions, an entry of ``points``); 0
            past ``count``.
        triangle: (C,) int32 row of ``triangles``; 0 past ``count``.
        valid: (C,) bool, the first ``min(count, C)`` entries.
        count: () int32 number of overlapping pairs found (may exceed ``C``; an upper
            bound when the work budget ran out).
        overflow: () bool, some pair may be missing: ``count > C`` or the work budget ran
            out.
    """

    vertex: jax.Array
    triangle: jax.Array
    valid: jax.Array
    count: jax.Array
    overflow: jax.Array


class _Static(NamedTuple):
    n: int
    points: np.ndarray  # (P,) int32 vertex ids
    triangles: np.ndarray  # (T, 3) int32
    tri_key: np.ndarray  # (T,) int32 key group each triangle is filed under
    partners: np.ndarray  # (P, M) int32 key groups each point looks up, -1 padding
    table: int  # hash table size (a power of two)
    allow: np.ndarray | None  # (G, G) bool bodies allowed to touch; None: every pair counts
    point_body: np.ndarray  # (P,) int32 compact body of each point
    tri_body: np.ndarray  # (T,) int32 compact body of each triangle
    per_test: bool  # bodies checked per test (not by the key groups)


def _is_traced(value) -> bool:
    return isinstance(value, jax.core.Tracer)


def _static_ints(value, name: str) -> np.ndarray:
    if _is_traced(value):
        raise ValueError(f"{name} must be a static (numpy) integer array, got a traced array")
    arr = np.asarray(value)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


def _prepare(x0, x1, points, triangles, groups, allowed) -> _Static:
    """Check the static inputs and build the per-point partner table."""
    s0, s1 = tuple(np.shape(x0)), tuple(np.shape(x1))
    if len(s0) != 2 or s0[1] != 3 or s0 != s1:
        raise ValueError(f"x0 and x1 must both have shape (n, 3), got {s0} and {s1}")
    n = s0[0]
    pts = _static_ints(points, "points")
    if pts.ndim != 1:
        raise ValueError(f"points must have shape (P,), got {pts.shape}")
    tri = _static_ints(triangles, "triangles")
    if tri.size == 0:
        tri = tri.reshape(0, 3)
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise ValueError(f"triangles must have shape (T, 3), got {tri.shape}")
    for name, arr in (("points", pts), ("triangles", tri)):
        if arr.size and (arr.min() < 0 or arr.max() >= n):
            raise ValueError(f"{name} indices must lie in [0, {n}), got [{arr.min()}, {arr.max()}]")
    if len(np.unique(pts)) != len(pts):
        raise ValueError("points must not repeat a vertex")
    if (groups is None) != (allowed is None):
        raise ValueError("groups and allowed go together: give both or neither")
    if groups is None:
        allow = None
        point_body, tri_body = np.zeros(len(pts), np.int32), np.zeros(len(tri), np.int32)
        tri_key, partners, per_test = tri_body, np.zeros((len(pts), 1), np.int32), False
    else:
        g = _static_ints(groups, "groups")
        if g.shape != (n,):
            raise ValueError(f"groups must have shape ({n},), got {g.shape}")
        ids, gid = np.unique(g, return_inverse=True)
        if isinstance(allowed, (set, frozenset)):
            allowed = list(allowed)
        pairs = _static_ints(allowed, "allowed")
        if pairs.size == 0:
            pairs = pairs.reshape(0, 2)
        if pairs.ndim != 2 or pairs.shape[1] != 2:
            raise ValueError(f"allowed must be pairs of group ids, shape (k, 2), got {pairs.shape}")
        known = np.isin(pairs, ids).all(1)
        pa, pb = np.searchsorted(ids, pairs[known, 0]), np.searchsorted(ids, pairs[known, 1])
        allow = np.zeros((len(ids), len(ids)), bool)
        allow[pa, pb] = allow[pb, pa] = True
        tg = gid[tri] if len(tri) else np.zeros((0, 3), np.int64)
        mixed = np.flatnonzero((tg != tg[:, :1]).any(1))
        if len(mixed):
            raise ValueError(f"triangle {mixed[0]} joins vertices of different groups: each "
                             "triangle must belong to one body")
        point_body, tri_body = gid[pts].astype(np.int32), tg[:, 0].astype(np.int32)
        width = int(allow.sum(1).max(initial=0))
        if width <= MAX_PARTNERS:  # file triangles by body: a vertex looks up its partners only
            table = np.full((len(ids), max(width, 1)), -1, np.int32)
            for i, row in enumerate(allow):
                table[i, : row.sum()] = np.flatnonzero(row)
            tri_key, partners, per_test = tri_body, table[point_body], False
        else:  # many partners: one key group, bodies filtered per test
            tri_key, partners = np.zeros(len(tri), np.int32), np.zeros((len(pts), 1), np.int32)
            per_test = not allow.all()
    # at least as many slots as queried cells (27 per point and partner, up to _TABLE_CAP):
    # an empty cell's query then rarely lands on an occupied slot, whose entries it would test
    segments = min(27 * len(pts) * partners.shape[1], _TABLE_CAP)
    size = 1 << max(1, int(np.ceil(np.log2(max(2 * len(tri), segments, 2)))))
    return _Static(n, pts.astype(np.int32), tri.astype(np.int32), tri_key.astype(np.int32),
                   partners.astype(np.int32), size, allow, point_body, tri_body, per_test)


def _check_margin(margin) -> None:
    if _is_traced(margin):
        return
    m = np.asarray(margin)
    if m.shape != () or not np.issubdtype(m.dtype, np.number):
        raise ValueError(f"margin must be a scalar, got {m!r}")
    if not np.isfinite(m) or m < 0:
        raise ValueError(f"margin must be finite and >= 0, got {float(m)}")


def _check_size(value, name: str) -> int:
    is_int = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if not is_int or not 1 <= value < _INT32_MAX:
        raise ValueError(f"{name} must be a static int in [1, 2**31 - 1), got {value!r}")
    return int(value)


def _hash(cell, group, mask: int):
    """Slot of (cell (..., 3) int32, group (...) int32) in a table of ``mask + 1`` slots."""
    u = jax.lax.bitcast_convert_type(cell, jnp.uint32)
    g = jax.lax.bitcast_convert_type(group, jnp.uint32)
    h = (u[..., 0] * np.uint32(73856093)) ^ (u[..., 1] * np.uint32(19349663)) \
        ^ (u[..., 2] * np.uint32(83492791)) ^ (g * np.uint32(2654435761))
    h = h ^ (h >> 16)
    h = h * np.uint32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * np.uint32(0xC2B2AE35)
    h = h ^ (h >> 16)
    return (h & np.uint32(mask)).astype(jnp.int32)


class _Layout(NamedTuple):
    v_box: jax.Array  # (P, 6) vertex boxes (lo, hi)
    t_box: jax.Array  # (T, 6) triangle boxes (lo, hi), sorted by slot
    t_int: jax.Array  # (T, 9) cell, key group, vertices, row, body; sorted by slot
    seg: jax.Array  # (S, 8) cell, key group, point, vertex, first sorted entry, first test
    total: jax.Array  # () number of box tests
    broken: jax.Array  # () bool, counts past 2**30 in float32 mode or a query block too wide


def _layout(x0, x1, st: _Static, margin, work: int) -> _Layout:
    """Boxes, the hashed grid and the segments of every query (everything but the tests);
    segments' first tests are clipped to ``work``."""
    P, T, M = len(st.points), len(st.triangles), st.partners.shape[1]
    idx = jnp.int64 if jax.config.read("jax_enable_x64") else jnp.int32
    dtype = jnp.result_type(x0, x1, float)
    x0, x1 = jnp.asarray(x0, dtype), jnp.asarray(x1, dtype)
    margin = jnp.asarray(margin, dtype)
    pts, tri = jnp.asarray(st.points), jnp.asarray(st.triangles)

    lo_v = jnp.minimum(x0[pts], x1[pts]) - margin
    hi_v = jnp.maximum(x0[pts], x1[pts]) + margin
    c0, c1 = x0[tri], x1[tri]  # (T, 3 corners, 3)
    lo_t = jnp.minimum(c0.min(1), c1.min(1)) - margin
    hi_t = jnp.maximum(c0.max(1), c1.max(1)) + margin

    # Grid, in coordinates shifted to the scene's lower corner (subtracting is monotonic,
    # so overlapping boxes still overlap there).
    origin = jnp.minimum(lo_v.min(0), lo_t.min(0))
    lv, hv, lt, ht = lo_v - origin, hi_v - origin, lo_t - origin, hi_t - origin
    span = jnp.maximum(hv.max(0), ht.max(0))
    e_t = (ht - lt).max(0)
    cells = 2 ** 20 if dtype == jnp.float64 else 2 ** 14
    h = jnp.maximum(((hv - lv).max(0) + e_t) * (0.5 * (1 + 2 ** -6)), span / cells)
    h = jnp.maximum(h, jnp.finfo(dtype).tiny)
    slack = h * 2 ** -8  # covers the rounding of the shifted coordinates
    cell_t = jnp.floor(lt / h).astype(jnp.int32)  # (T, 3)
    first_cell = jnp.floor((lv - e_t - slack) / h).astype(jnp.int32)  # (P, 3)
    last_cell = jnp.floor((hv + slack) / h).astype(jnp.int32)
    too_wide = jnp.any(last_cell - first_cell > 2)  # never by construction; flagged if it were

    # Hash table of triangles (one entry each, in its lower corner's cell).
    tg = jnp.asarray(st.tri_key)
    slot_t = _hash(cell_t, tg, st.table - 1)
    order = jnp.argsort(slot_t, stable=True)
    counts = jnp.zeros(st.table, jnp.int32).at[slot_t].add(1)
    starts = jnp.cumsum(counts) - counts
    t_box = jnp.concatenate([lo_t, hi_t], 1)[order]
    t_int = jnp.concatenate([cell_t, tg[:, None], tri, jnp.arange(T, dtype=jnp.int32)[:, None],
                             jnp.asarray(st.tri_body)[:, None]], 1)[order]

    # Segments: (point, partner key group, cell of the 27-block), each a run of one slot.
    block = first_cell[:, None, :] + jnp.asarray(_OFFSETS)  # (P, 27, 3)
    inside = jnp.all(block <= last_cell[:, None, :], -1)  # (P, 27)
    part = jnp.asarray(st.partners)  # (P, M)
    seg_cell = jnp.broadcast_to(block[:, None], (P, M, 27, 3)).reshape(-1, 3)
    seg_group = jnp.broadcast_to(part[:, :, None], (P, M, 27)).reshape(-1)
    slot = _hash(seg_cell, seg_group, st.table - 1)
    inside = jnp.broadcast_to(inside[:, None, :], (P, M, 27)).reshape(-1)
    length = jnp.where(inside & (seg_group >= 0), counts[slot], 0).astype(idx)
    offsets = jnp.cumsum(length) - length
    total = offsets[-1] + length[-1]
    offsets = jnp.where(offsets < 0, work, jnp.minimum(offsets, work)).astype(jnp.int32)
    point = jnp.broadcast_to(jnp.arange(P, dtype=jnp.int32)[:, None], (P, M * 27)).reshape(-1, 1)
    vertex = jnp.broadcast_to(pts[:, None], (P, M * 27)).reshape(-1, 1)
    seg = jnp.concatenate([seg_cell, seg_group[:, None], point, vertex, starts[slot][:, None],
                           offsets[:, None]], 1)
    broken = too_wide | (total < 0)
    if idx == jnp.int32:  # 32-bit counts: past 2**30 tests the prefix sums may wrap
        broken = broken | (jnp.sum(length.astype(dtype)) > 2 ** 30)
    return _Layout(jnp.concatenate([lo_v, hi_v], 1), t_box, t_int, seg, total, broken)


def _tests(lay: _Layout):
    """The number of box tests a query needs, saturated at int32's largest."""
    return jnp.where(lay.broken, _INT32_MAX, jnp.minimum(lay.total, _INT32_MAX)).astype(jnp.int32)


def _search(x0, x1, st: _Static, margin, capacity: int, work: int,
            exclude_incident: bool) -> Candidates:
    """The query."""
    C, B = capacity, work
    P, T = len(st.points), len(st.triangles)
    if P == 0 or T == 0:
        zero = jnp.zeros(C, jnp.int32)
        return Candidates(zero, zero, jnp.zeros(C, bool), jnp.int32(0), jnp.bool_(False))
    lay = _layout(x0, x1, st, margin, B)
    S, total = lay.seg.shape[0], lay.total

    # The work list: test k belongs to the last segment starting at or before k.
    marks = jnp.zeros(B, jnp.int32).at[lay.seg[:, 7]].max(jnp.arange(S, dtype=jnp.int32),
                                                          mode="drop")
    si = lay.seg[jax.lax.cummax(marks)]  # (B, 8)
    k = jnp.arange(B, dtype=jnp.int32)
    entry = jnp.clip(si[:, 6] + (k - si[:, 7]), 0, T - 1)
    ti, tb, vb = lay.t_int[entry], lay.t_box[entry], lay.v_box[si[:, 4]]
    vid = si[:, 5]
    hit = (k < total) & jnp.all(ti[:, :4] == si[:, :4], 1) \
        & jnp.all(tb[:, :3] <= vb[:, 3:], 1) & jnp.all(vb[:, :3] <= tb[:, 3:], 1)
    if exclude_incident:
        hit = hit & jnp.all(ti[:, 4:7] != vid[:, None], 1)
    if st.per_test:
        G = len(st.allow)
        body = jnp.asarray(st.point_body)[si[:, 4]] * G + ti[:, 8]
        hit = hit & jnp.asarray(st.allow.reshape(-1))[body]

    idx = total.dtype
    found = jnp.sum(hit, dtype=idx)
    pos = jnp.cumsum(hit, dtype=jnp.int32) - 1
    dest = jnp.where(hit & (pos < C), pos, C)
    vertex = jnp.zeros(C, jnp.int32).at[dest].set(vid, mode="drop")
    triangle = jnp.zeros(C, jnp.int32).at[dest].set(ti[:, 7], mode="drop")
    valid = jnp.arange(C) < found
    bound = found + jnp.maximum(total - B, 0)
    count = jnp.where(lay.broken | (bound < 0), _INT32_MAX, jnp.minimum(bound, _INT32_MAX))
    count = count.astype(jnp.int32)
    overflow = (count > C) | (total > B) | lay.broken
    return Candidates(vertex, triangle, valid, count, overflow)


def candidates(x0, x1, points, triangles, margin, capacity: int, *, work: int | None = None,
               exclude_incident: bool = True, groups=None, allowed=None) -> Candidates:
    """The (vertex, triangle) pairs whose swept boxes overlap, in fixed-size buffers.

    Traceable (``jax.jit``, ``jax.vmap`` over ``x0``, ``x1`` and ``margin``): the mesh data
    and sizes are static, the positions may be traced. Pairs come out in a deterministic
    order (by candidate vertex, then grid cell).

    Arguments:
        x0, x1: (n, 3) positions at the step's start and predicted end.
        points: (P,) static int array, the candidate vertices (distinct indices into x).
        triangles: (T, 3) static int array of vertex indices.
        margin: scalar >= 0 (m, may be traced); each box grows by it on every side.
        capacity: static int >= 1, the number of output slots ``C``.
        work: static int in [1, 2**31 - 1), the budget of box tests (default
            ``WORK_PER_VERTEX * P + capacity``).
        exclude_incident: drop pairs whose vertex is one of the triangle's.
        groups: optional (n,) static int body id per vertex (each triangle's vertices in one
            body); with ``allowed``, a static iterable of unordered ``(group_i, group_j)``
            pairs (``(g, g)`` allows self-contact), only pairs between allowed bodies count.

    Returns:
        :class:`Candidates`; where ``overflow`` is set some pairs may be missing (see the
        module's limits) and :func:`required_capacity` gives sizes that hold them all.

    Raises:
        ValueError: a size out of range, a negative or non-finite margin (when concrete), positions
            not of shape (n, 3), indices out of range or of the wrong shape, repeated
            points, groups without allowed (or the reverse), or a triangle across bodies.
    """
    st = _prepare(x0, x1, points, triangles, groups, allowed)
    capacity = _check_size(capacity, "capacity")
    if work is None:
        work = WORK_PER_VERTEX * len(st.points) + capacity
    work = _check_size(work, "work")
    _check_margin(margin)
    return _search(x0, x1, st, margin, capacity, work, exclude_incident)


def required_capacity(x0, x1, points, triangles, margin, *, exclude_incident: bool = True,
                      groups=None, allowed=None) -> tuple[int, int]:
    """The smallest ``(capacity, work)`` with which :func:`candidates` finds every pair.

    Host-side (runs its own compiled queries; call it outside ``jit``), e.g. after a step
    reported ``overflow``. ``x0`` and ``x1`` may carry leading batch axes ``(..., n, 3)``
    (the scenes of a ``vmap``): the sizes then hold for every scene.

    Arguments:
        x0, x1, points, triangles, margin, exclude_incident, groups, allowed: as for
            :func:`candidates` (``margin`` a concrete scalar).

    Returns:
        ``(capacity, work)``: the number of overlapping pairs and of box tests of the
        largest scene, each at least 1. (Counting the pairs runs every test: memory grows
        with ``work``.)

    Raises:
        ValueError: as :func:`candidates`, or where a scene needs more than ``2**31 - 1``
            box tests.
    """
    a, b = np.asarray(x0), np.asarray(x1)
    if a.shape != b.shape or a.ndim < 2:
        raise ValueError(f"x0 and x1 must have the same shape (..., n, 3), got {a.shape} and "
                         f"{b.shape}")
    a, b = a.reshape(-1, *a.shape[-2:]), b.reshape(-1, *b.shape[-2:])
    st = _prepare(a[0], b[0], points, triangles, groups, allowed)
    _check_margin(margin)

    if len(st.points) == 0 or len(st.triangles) == 0:
        return 1, 1
    tests = int(np.max(jax.jit(jax.vmap(lambda p, q: _tests(_layout(p, q, st, margin, 1))))(a, b)))
    if tests >= _INT32_MAX:
        raise ValueError("the query needs more than 2**31 - 1 box tests: the boxes are far too "
                         "crowded")
    query = jax.vmap(lambda p, q: _search(p, q, st, margin, 1, max(tests, 1),
                                          exclude_incident).count)
    return max(int(np.max(jax.jit(query)(a, b))), 1), max(tests, 1)


def brute_force(x0, x1, points, triangles, margin, *, exclude_incident: bool = True, groups=None,
                allowed=None) -> np.ndarray:
    """Every (vertex, triangle) pair whose swept boxes overlap, by testing all ``P x T``.

    The host reference for :func:`candidates` (same boxes, same filters), in numpy.

    Arguments:
        x0, x1, points, triangles, margin, exclude_incident, groups, allowed: as for
            :func:`candidates` (concrete arrays).

    Returns:
        (k, 2) int64 array of ``(vertex index, triangle row)``, sorted lexicographically.

    Raises:
        ValueError: as :func:`candidates`.
    """
    st = _prepare(x0, x1, points, triangles, groups, allowed)
    _check_margin(margin)
    a, b = np.asarray(x0), np.asarray(x1)
    # the query's precision (float32 where JAX's 64-bit mode is off)
    dtype = np.dtype(jax.dtypes.canonicalize_dtype(np.result_type(a, b, float)))
    a, b, m = a.astype(dtype), b.astype(dtype), dtype.type(margin)
    pts, tri = st.points, st.triangles
    lo_v, hi_v = np.minimum(a[pts], b[pts]) - m, np.maximum(a[pts], b[pts]) + m
    lo_t = np.minimum(a[tri].min(1), b[tri].min(1)) - m
    hi_t = np.maximum(a[tri].max(1), b[tri].max(1)) + m
    out = []
    chunk = max(1, 2 ** 22 // max(len(tri), 1))
    for s in range(0, len(pts), chunk):
        sl = slice(s, s + chunk)
        ok = np.all((lo_t[None] <= hi_v[sl, None]) & (lo_v[sl, None] <= hi_t[None]), -1)
        if exclude_incident:
            ok &= ~np.any(tri[None] == pts[sl, None, None], -1)
        if st.allow is not None:
            ok &= st.allow[st.point_body[sl, None], st.tri_body[None]]
        i, j = np.nonzero(ok)
        out.append(np.stack([pts[sl][i], j], 1))
    pairs = np.concatenate(out, 0).astype(np.int64) if out else np.zeros((0, 2), np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]

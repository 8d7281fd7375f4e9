"""Continuous collision detection (:mod:`softbody.contact.ccd`): analytic times of impact,
genuinely cubic motion against a dense-sampling reference, degenerate cubics, edge pairs,
shared-vertex pairs, whole steps of small meshes (with ``jit`` and ``vmap``) and a random
batch against the reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from softbody.contact import ccd

# a static triangle in the plane z = 0 (centroid at the origin)
A = np.array([-1.0, -1.0, 0.0])
B = np.array([2.0, -1.0, 0.0])
C = np.array([-1.0, 2.0, 0.0])
TRIANGLE = (A, A, B, B, C, C)


# ---------------------------------------------------------------------------------------------
# reference: dense sampling of the signed volume, bisection, then the inside test (numpy)


def _volume(x):
    """Signed volume ``det[x1 - x0, x2 - x0, x3 - x0]`` (...) of four points x (..., 4, 3)."""
    u, v, w = x[..., 1, :] - x[..., 0, :], x[..., 2, :] - x[..., 0, :], x[..., 3, :] - x[..., 0, :]
    return np.einsum("...i,...i->...", np.cross(u, v), w)


def _coplanar(x0, x1, samples=1001, iterations=80):
    """Every sign change of the signed volume of four linearly moving points (x0, x1 each
    (K, 4, 3)) found on ``samples`` times and refined by bisection: the config (R,), the
    time (R,) and the points then (R, 4, 3)."""
    t = np.linspace(0.0, 1.0, samples)
    f = np.concatenate([_volume(x0[c, None] + t[:, None, None] * (x1 - x0)[c, None])
                        for c in np.array_split(np.arange(len(x0)), max(len(x0) // 200, 1))])
    k, m = np.nonzero(np.sign(f[:, :-1]) * np.sign(f[:, 1:]) < 0)
    lo, hi, s = t[m], t[m + 1], np.sign(f[k, m])
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        right = np.sign(_volume(x0[k] + mid[:, None, None] * (x1 - x0)[k])) * s > 0
        lo, hi = np.where(right, mid, lo), np.where(right, hi, mid)
    root = 0.5 * (lo + hi)
    return k, root, x0[k] + root[:, None, None] * (x1 - x0)[k]


def _barycentric(x):
    """Barycentric coordinates (R, 3) of the projection of x[:, 3] on the triangle x[:, :3]."""
    a, b, c, p = (x[:, i] for i in range(4))
    n = np.cross(b - a, c - a)
    nn = np.einsum("ri,ri->r", n, n)
    return np.stack([np.einsum("ri,ri->r", n, np.cross(u - p, v - p)) / nn
                     for u, v in ((b, c), (c, a), (a, b))], -1)


def _segment_params(x):
    """``(u, 1 - u, v, 1 - v)`` (R, 4) of the crossing of the coplanar lines x[:, 0] x[:, 1]
    and x[:, 2] x[:, 3]."""
    p, q, r, s = (x[:, i] for i in range(4))
    d1, d2, w = q - p, s - r, p - r
    a, e, b = (np.einsum("ri,ri->r", *pair) for pair in ((d1, d1), (d2, d2), (d1, d2)))
    c, f = np.einsum("ri,ri->r", d1, w), np.einsum("ri,ri->r", d2, w)
    den = a * e - b * b
    u, v = (b * f - c * e) / den, (a * f - b * c) / den
    return np.stack([u, 1 - u, v, 1 - v], -1)


def _reference(x0, x1, inside_params):
    """Earliest coplanarity root (K,) at which ``inside_params`` of the points are all
    positive (NaN where none), and which configs lie too close to a tie for an exact
    reference (K,): a root near the step's ends, a near tangency (a complex pair of roots of
    the cubic near [0, 1], or two close roots), or a crossing near the boundary of the
    triangle (segment)."""
    k, root, x = _coplanar(x0, x1)
    params = inside_params(x)
    inside = np.all(params > 0, -1)
    first = np.full(len(x0), np.inf)
    np.minimum.at(first, k[inside], root[inside])
    near_edge = np.zeros(len(x0), bool)
    near_edge[k[np.any(np.abs(params) < 1e-3, -1)]] = True
    # the cubic through four times, solved by its companion matrix
    t = np.array([0.0, 1 / 3, 2 / 3, 1.0])
    f = _volume(x0[:, None] + t[:, None, None] * (x1 - x0)[:, None])  # (K, 4)
    coef = np.linalg.solve(np.vander(t, 4), f.T).T
    grazing = near_edge.copy()
    for i, c in enumerate(coef):
        z = np.roots(c)
        real = np.abs(z.imag) < 1e-9
        near_end = real & ((np.abs(z.real) < 0.01) | (np.abs(z.real - 1) < 0.01))
        tangent = ~real & (np.abs(z.imag) < 0.01) & (z.real > -0.01) & (z.real < 1.01)
        close = np.abs(z[:, None] - z[None, :])[~np.eye(len(z), dtype=bool)]
        grazing[i] |= bool(near_end.any() or tangent.any() or (close < 0.01).any())
    return np.where(np.isfinite(first), first, np.nan), grazing, k, root


def _vt_reference(p0, p1, a0, a1, b0, b1, c0, c1):
    x0, x1 = np.stack([a0, b0, c0, p0], 1), np.stack([a1, b1, c1, p1], 1)
    return _reference(x0, x1, _barycentric)


def _ee_reference(p0, p1, q0, q1, r0, r1, s0, s1):
    x0, x1 = np.stack([p0, q0, r0, s0], 1), np.stack([p1, q1, r1, s1], 1)
    return _reference(x0, x1, _segment_params)


# ---------------------------------------------------------------------------------------------
# vertex-triangle


@pytest.mark.parametrize("z1, expected", [(-1.0, 0.5), (-2.0, 1 / 3), (0.0, 1.0), (-0.6, 0.625)])
def test_point_through_the_centre_at_the_analytic_time(z1, expected):
    toi = ccd.vertex_triangle_toi([0.0, 0.0, 1.0], [0.0, 0.0, z1], *TRIANGLE)
    assert abs(float(toi) - expected) < 1e-12


def test_point_beside_or_short_of_the_triangle_does_not_hit():
    beside = ccd.vertex_triangle_toi([1.5, 1.5, 1.0], [1.5, 1.5, -1.0], *TRIANGLE)
    short = ccd.vertex_triangle_toi([0.0, 0.0, 1.0], [0.0, 0.0, 1e-3], *TRIANGLE)
    receding = ccd.vertex_triangle_toi([0.0, 0.0, 1.0], [0.0, 0.0, 2.0], *TRIANGLE)
    assert np.isinf(beside) and np.isinf(short) and np.isinf(receding)
    # the same triangle moving up to the point hits (the check can fail)
    up = [x + [0, 0, 2.0] for x in (A, B, C)]
    hit = ccd.vertex_triangle_toi([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], A, up[0], B, up[1], C, up[2])
    assert abs(float(hit) - 0.5) < 1e-12


def _random_cubic_configs(rng, count):
    """Triangles whose corners move with different velocities (a genuinely cubic signed
    volume) and points moving across them."""
    tri0 = rng.normal(size=(count, 3, 3))
    tri1 = tri0 + rng.normal(scale=1.0, size=(count, 3, 3))
    centre0, centre1 = tri0.mean(1), tri1.mean(1)
    p0 = centre0 + rng.normal(scale=1.0, size=(count, 3))
    p1 = centre1 - (p0 - centre0) + rng.normal(scale=0.5, size=(count, 3))
    return p0, p1, tri0[:, 0], tri1[:, 0], tri0[:, 1], tri1[:, 1], tri0[:, 2], tri1[:, 2]


def test_genuinely_cubic_motion_matches_a_bisection_reference():
    """Configurations with two or three coplanarity roots in the step, the first of them
    outside the triangle and a later one inside: the earliest inside root, to 1e-9."""
    rng = np.random.default_rng(7)
    cfg = _random_cubic_configs(rng, 1500)
    first, grazing, k, root = _vt_reference(*cfg)
    first_root = np.full(len(first), np.inf)
    np.minimum.at(first_root, k, root)
    several = np.bincount(k, minlength=len(first)) >= 2
    chosen = np.flatnonzero(several & ~grazing & (first > first_root))[:20]
    assert len(chosen) >= 5
    sub = [np.asarray(x)[chosen] for x in cfg]
    d = [x1 - x0 for x0, x1 in zip(sub[::2], sub[1::2])]
    # the cubic coefficient of the signed volume is far from zero
    cubic = np.einsum("ki,ki->k", np.cross(d[2] - d[1], d[3] - d[1]), d[0] - d[1])
    assert np.all(np.abs(cubic) > 1e-3)
    toi = np.asarray(jax.jit(ccd.vertex_triangle_toi)(*sub))
    np.testing.assert_allclose(toi, first[chosen], rtol=0, atol=1e-9)


def test_degenerate_cubics_give_no_nan():
    z = np.zeros(3)
    # pure translation of the triangle (cubic and quadratic coefficients vanish)
    up = [x + [0, 0, 3.0] for x in (A, B, C)]
    toi = ccd.vertex_triangle_toi([0, 0, 1.0], [0, 0, 1.0], A, up[0], B, up[1], C, up[2])
    assert abs(float(toi) - 1 / 3) < 1e-12
    # everything translating together: constant nonzero volume, never meets
    shift = np.array([0.3, -0.2, 0.5])
    toi = ccd.vertex_triangle_toi([0, 0, 1.0], [0, 0, 1.0] + shift, A, A + shift, B, B + shift,
                                  C, C + shift)
    assert np.isinf(toi)
    # coplanar throughout: sliding in the plane into the triangle (across the edge x = -1)
    toi = ccd.vertex_triangle_toi([-3.0, 0, 0], [0.0, 0, 0], *TRIANGLE)
    assert abs(float(toi) - 2 / 3) < 1e-9
    # coplanar throughout, staying outside; and inside from the start
    assert np.isinf(ccd.vertex_triangle_toi([-3.0, 0, 0], [-2.0, 0, 0], *TRIANGLE))
    assert float(ccd.vertex_triangle_toi([0.0, 0, 0], [0.5, 0, 0], *TRIANGLE)) == 0.0
    # coplanar throughout with a turning plane (all four points in the plane y = 0 ... moving)
    toi = ccd.vertex_triangle_toi([0.0, 0, 5.0], [0.0, 0, -5.0], z, z, [1.0, 0, 0], [1.0, 0, 0],
                                  [0, 0, 1.0], [0, 0, 1.0])
    assert np.isfinite(toi)  # the point passes through the corner region (x = 0 edge)
    # collapsed triangles and coincident points
    toi = ccd.vertex_triangle_toi(z, z, z, z, z, z, z, z)
    assert float(toi) == 0.0
    toi = ccd.vertex_triangle_toi([0, 1.0, 0], [0, -1.0, 0], [-1.0, 0, 0], [-1.0, 0, 0],
                                  [1.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.5, 0, 0])
    assert not np.isnan(toi)  # (crossing a zero-area triangle is left to its edges' tests)
    toi = ccd.vertex_triangle_toi([0, 1.0, 0], [0, 1.0, 0], [-1.0, 0, 0], [-1.0, 0, 0],
                                  [1.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.5, 0, 0])
    assert np.isinf(toi)


# ---------------------------------------------------------------------------------------------
# edge-edge


def test_perpendicular_edges_cross_at_the_analytic_time():
    # edge along x at height 1 - 2 t, edge along y fixed at z = 0.5: cross at t = 0.25
    p0, q0 = np.array([-1.0, 0, 1]), np.array([1.0, 0, 1])
    down = np.array([0, 0, -2.0])
    r, s = np.array([0, -1.0, 0.5]), np.array([0, 1.0, 0.5])
    toi = ccd.edge_edge_toi(p0, p0 + down, q0, q0 + down, r, r, s, s)
    assert abs(float(toi) - 0.25) < 1e-12
    # both moving, crossing at the mid-step
    toi = ccd.edge_edge_toi(p0, p0 + down, q0, q0 + down, r - [0, 0, 1.5], r + [0, 0, 0.5],
                            s - [0, 0, 1.5], s + [0, 0, 0.5])
    assert abs(float(toi) - 0.5) < 1e-12
    # the same motion, the second edge shifted past the first's end: no crossing
    off = np.array([1.5, 0, 0])
    toi = ccd.edge_edge_toi(p0, p0 + down, q0, q0 + down, r + off, r + off, s + off, s + off)
    assert np.isinf(toi)


def test_parallel_edges_passing_do_not_cross():
    p0, q0 = np.array([-1.0, 0, 1]), np.array([1.0, 0, 1])
    down = np.array([0, 0, -2.0])
    r, s = np.array([-1.0, 0.2, 0]), np.array([1.0, 0.2, 0])
    assert np.isinf(ccd.edge_edge_toi(p0, p0 + down, q0, q0 + down, r, r, s, s))
    # parallel and coplanar throughout (both in z = 0), sliding side by side
    r2, s2 = np.array([-1.0, 0.2, 1]), np.array([1.0, 0.2, 1])
    toi = ccd.edge_edge_toi(p0, p0 + [3.0, 0, 0], q0, q0 + [3.0, 0, 0], r2, r2, s2, s2)
    assert np.isinf(toi)
    # ... and the same parallel edges overlapping (distance 0): met at once
    toi = ccd.edge_edge_toi(p0, p0 + [3.0, 0, 0], q0, q0 + [3.0, 0, 0], r2 - [0, 0.2, 0],
                            r2 - [0, 0.2, 0], s2 - [0, 0.2, 0], s2 - [0, 0.2, 0])
    assert float(toi) == 0.0


def test_coplanar_edges_sliding_into_each_other():
    # both edges in z = 0; the first slides along x into the second: they meet when its
    # right end reaches x = 0 (t = 0.5)
    p, q = np.array([-3.0, 0, 0]), np.array([-1.0, 0, 0])
    dx = np.array([2.0, 0, 0])
    r, s = np.array([0.0, -1, 0]), np.array([0.0, 1, 0])
    toi = ccd.edge_edge_toi(p, p + dx, q, q + dx, r, r, s, s)
    assert abs(float(toi) - 0.5) < 1e-9


# ---------------------------------------------------------------------------------------------
# candidate pairs


def test_shared_vertex_pairs_are_excluded():
    x = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.0, 0, 0], [0.0, 0, 1]])
    triangles = np.array([[0, 1, 2]])
    edges = np.array([[0, 1], [1, 2], [3, 4], [0, 4]])
    vt = np.array([[0, 0], [3, 0], [-1, -1]])
    ee = np.array([[0, 1], [0, 3], [2, 0], [-1, 0]])
    out = jax.jit(ccd.crossings)(x, x, triangles, edges, vt, ee)
    vt_toi, ee_toi = np.asarray(out.vertex_triangle), np.asarray(out.edge_edge)
    # vertex 0 is a corner of its triangle: excluded; its copy 3 lies on it: met at t = 0
    assert np.isinf(vt_toi[0]) and vt_toi[1] == 0.0 and np.isinf(vt_toi[2])
    # edges 0 and 1 share vertex 1; edges 0 and 3 share vertex 0; edges 2 and 0 touch at
    # the copy of vertex 0 (distinct indices): met
    assert np.isinf(ee_toi[0]) and np.isinf(ee_toi[1]) and ee_toi[2] == 0.0
    assert np.isinf(ee_toi[3])
    assert int(out.count) == 2 and float(out.earliest) == 0.0


def test_surface_edges():
    edges = ccd.surface_edges(np.array([[0, 1, 2], [2, 1, 3]]))
    np.testing.assert_array_equal(edges, [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]])
    assert ccd.surface_edges(np.zeros((0, 3), int)).shape == (0, 2)
    with pytest.raises(ValueError):
        ccd.surface_edges(np.zeros((2, 2), int))


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="tol"):
        ccd.vertex_triangle_toi(A, A, A, A, B, B, C, C, tol=0.0)
    with pytest.raises(ValueError, match="shape"):
        ccd.edge_edge_toi(A[:2], A[:2], A[:2], A[:2], B[:2], B[:2], C[:2], C[:2])
    x = np.zeros((3, 3))
    with pytest.raises(ValueError, match="vertex_triangle"):
        ccd.crossings(x, x, [[0, 1, 2]], [[0, 1]], np.zeros((2, 3), int), np.zeros((0, 2), int))


# ---------------------------------------------------------------------------------------------
# whole steps


def _tet_and_square(z):
    """A small tetrahedron's surface centred at height ``z`` over a flat 2 x 2 square (two
    triangles) in z = 0."""
    tet = np.array([[0.0, 0, 0], [0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3]]) + [0.2, -0.3, 0]
    tet_faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    square = np.array([[-1.0, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    x = np.concatenate([tet + [0, 0, z - 0.075], square])
    return x, np.concatenate([tet_faces, np.array([[4, 5, 6], [4, 6, 7]])])


def test_tetrahedron_through_a_square():
    x0, tri = _tet_and_square(0.5)
    through, _ = _tet_and_square(-0.5)
    above, _ = _tet_and_square(0.2)
    step = jax.jit(lambda a, b: ccd.tunnelled(a, b, tri, capacity=64))
    out = step(x0, through)
    assert int(out.count) > 0 and not bool(out.overflow)
    # the lowest tet vertex (z = 0.425 at the start) reaches z = 0 at t = 0.425
    assert abs(float(out.earliest) - 0.425) < 1e-12
    out = step(x0, above)
    assert int(out.count) == 0 and np.isinf(out.earliest) and not bool(out.overflow)
    # a tilted square that one tet corner pokes through: a crossing, and none of the pair
    # tests that share a vertex (the square's diagonal) count
    x1 = above.copy()
    x1[4:, 2] = [0.5, 0.5, -0.5, -0.5]  # square tilted about its x axis: z = y / 2
    assert int(step(x0, x1).count) > 0


def test_tunnelled_under_jit_and_vmap_matches_one_at_a_time():
    x0, tri = _tet_and_square(0.5)
    heights = np.array([0.3, -0.5, 0.1, -0.2, 0.45, -1.0])
    x1 = np.stack([_tet_and_square(h)[0] for h in heights])
    x1[:, 4:] += np.random.default_rng(3).normal(0, 0.05, (len(heights), 4, 3))
    single = jax.jit(lambda b: ccd.tunnelled(x0, b, tri, capacity=64))
    one = [single(b) for b in x1]
    batch = jax.jit(jax.vmap(lambda b: ccd.tunnelled(x0, b, tri, capacity=64)))(jnp.asarray(x1))
    np.testing.assert_array_equal(batch.count, [int(o.count) for o in one])
    np.testing.assert_array_equal(batch.earliest, [float(o.earliest) for o in one])
    np.testing.assert_array_equal(batch.overflow, [bool(o.overflow) for o in one])
    assert (np.asarray(batch.count) > 0).sum() >= 2 and (np.asarray(batch.count) == 0).sum() >= 2


def _sphere(n, radius):
    z = 1 - (2 * np.arange(n) + 1) / n
    phi = np.arange(n) * np.pi * (3 - 5 ** 0.5)
    r = np.sqrt(1 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return radius * v, ConvexHull(v).simplices


def test_tunnelled_matches_all_pairs_on_two_spheres():
    """The broad phases (vertex-triangle and edge-edge) lose no pair: the counts equal those
    of every (vertex, triangle) and (edge, edge) pair tested exactly."""
    s, faces = _sphere(20, 0.5)
    n = len(s)
    tri = np.concatenate([faces, faces + n])
    edges = ccd.surface_edges(tri)
    vt_all = np.stack(np.meshgrid(np.arange(2 * n), np.arange(len(tri)), indexing="ij"),
                      -1).reshape(-1, 2)
    i, j = np.triu_indices(len(edges), 1)
    ee_all = np.stack([i, j], 1)
    step = jax.jit(lambda a, b: ccd.tunnelled(a, b, tri, capacity=2000, edge_capacity=2000))
    every = jax.jit(lambda a, b: ccd.crossings(a, b, tri, edges, vt_all, ee_all).count)
    rng = np.random.default_rng(11)
    counts = []
    for gap in (2.0, 1.2, 0.9, 0.6):
        x0 = np.concatenate([s, s + [gap, 0, 0]])
        x1 = np.concatenate([s + [0.25, 0, 0], s + [gap - 0.25, 0, 0]])
        x1 = x1 + rng.normal(0, 0.05, x1.shape)
        out = step(x0, x1)
        assert not bool(out.overflow)
        assert int(out.count) == int(every(x0, x1))
        counts.append(int(out.count))
    assert counts[0] == 0 and counts[-1] > 0


def test_groups_count_only_crossings_between_allowed_bodies():
    """Two spheres that pass into each other while one also folds through itself: with
    ``allowed=[(0, 1)]`` only the pairs across the two bodies count, as all pairs tested
    exactly with the same restriction."""
    s, faces = _sphere(20, 0.5)
    n = len(s)
    tri = np.concatenate([faces, faces + n])
    edges = ccd.surface_edges(tri)
    groups = np.repeat([0, 1], n)
    x0 = np.concatenate([s, s + [1.2, 0, 0]])
    x1 = np.concatenate([s + [0.25, 0, 0], s + [0.95, 0, 0]])
    x1[:n, 2] *= np.where(s[:, 2] > 0, -1.0, 1.0)  # the first sphere's top passes through its bottom
    x1 = x1 + np.random.default_rng(2).normal(0, 0.02, x1.shape)
    vt_all = np.stack(np.meshgrid(np.arange(2 * n), np.arange(len(tri)), indexing="ij"), -1).reshape(-1, 2)
    vt_all = vt_all[groups[vt_all[:, 0]] != groups[tri[vt_all[:, 1], 0]]]
    i, j = np.triu_indices(len(edges), 1)
    ee_all = np.stack([i, j], 1)
    ee_all = ee_all[groups[edges[ee_all[:, 0], 0]] != groups[edges[ee_all[:, 1], 0]]]
    across = ccd.tunnelled(x0, x1, tri, capacity=2000, edge_capacity=2000, groups=groups, allowed=[(0, 1)])
    every = ccd.tunnelled(x0, x1, tri, capacity=4000, edge_capacity=4000)
    assert not bool(across.overflow) and not bool(every.overflow)
    assert int(across.count) == int(ccd.crossings(x0, x1, tri, edges, vt_all, ee_all).count) > 0
    assert int(every.count) > int(across.count)  # the self-crossings count without groups


def test_edge_candidates_against_brute_force():
    s, faces = _sphere(24, 0.5)
    edges = ccd.surface_edges(faces)
    rng = np.random.default_rng(5)
    x0 = s
    x1 = s + rng.normal(0, 0.1, s.shape)
    pairs, count, overflow = jax.jit(lambda a, b: ccd.edge_candidates(a, b, edges, 0.01, 2000))(
        x0, x1)
    lo = np.minimum(x0[edges].min(1), x1[edges].min(1)) - 0.01
    hi = np.maximum(x0[edges].max(1), x1[edges].max(1)) + 0.01
    overlap = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), -1)
    shared = np.any(edges[:, None, :, None] == edges[None, :, None, :], (2, 3))
    i, j = np.nonzero(np.triu(overlap & ~shared, 1))
    got = np.asarray(pairs)[: int(count)]
    assert not bool(overflow) and np.all(np.asarray(pairs)[int(count):] == -1)
    assert sorted(map(tuple, got.tolist())) == sorted(zip(i.tolist(), j.tolist()))
    # too small a buffer is reported
    _, count, overflow = ccd.edge_candidates(x0, x1, edges, 0.01, max(len(i) // 2, 1))
    assert bool(overflow)


# ---------------------------------------------------------------------------------------------
# random batch


def _check_batch(toi, first, grazing, least):
    assert not np.any(np.isnan(toi))
    assert np.all(np.isinf(toi) | ((toi >= 0) & (toi <= 1)))
    keep = ~grazing
    assert keep.sum() > 600
    hit = np.isfinite(first)
    np.testing.assert_array_equal(np.isfinite(toi)[keep], hit[keep])
    both = keep & hit
    np.testing.assert_allclose(toi[both], first[both], rtol=0, atol=1e-9)
    assert least < both.sum() < keep.sum() - least


def test_random_vertex_triangle_batch_matches_the_reference():
    cfg = _random_cubic_configs(np.random.default_rng(2024), 1000)
    toi = np.asarray(jax.jit(ccd.vertex_triangle_toi)(*cfg))
    first, grazing, _, _ = _vt_reference(*cfg)
    _check_batch(toi, first, grazing, 100)


def test_random_edge_edge_batch_matches_the_reference():
    rng = np.random.default_rng(99)
    count = 1000
    e0 = rng.normal(size=(count, 2, 3))
    e1 = e0 + rng.normal(scale=1.0, size=(count, 2, 3))
    m0, m1 = e0.mean(1), e1.mean(1)
    f0 = m0[:, None] + rng.normal(size=(count, 2, 3))
    f1 = m1[:, None] + (m0[:, None] - f0) + rng.normal(scale=0.5, size=(count, 2, 3))
    cfg = (e0[:, 0], e1[:, 0], e0[:, 1], e1[:, 1], f0[:, 0], f1[:, 0], f0[:, 1], f1[:, 1])
    toi = np.asarray(jax.jit(ccd.edge_edge_toi)(*cfg))
    first, grazing, _, _ = _ee_reference(*cfg)
    _check_batch(toi, first, grazing, 50)


def test_empty_inputs():
    x = np.zeros((3, 3))
    none3, none2 = np.zeros((0, 3), int), np.zeros((0, 2), int)
    out = ccd.tunnelled(x, x, none3, capacity=4)
    assert int(out.count) == 0 and np.isinf(out.earliest) and not bool(out.overflow)
    out = ccd.crossings(x, x, none3, none2, -np.ones((3, 2), int), none2)
    assert out.vertex_triangle.shape == (3,) and out.edge_edge.shape == (0,)
    assert int(out.count) == 0 and np.isinf(out.earliest)

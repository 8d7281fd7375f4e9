"""The broad phase (:mod:`softbody.contact.broad_phase`) against brute force: two moving spheres
with and without body filters, a folded sheet touching itself, overflow of both fixed
bounds, ``jit`` and ``vmap`` over scenes, and the input checks."""

import jax
import numpy as np
import pytest
from scipy.spatial import ConvexHull

from softbody.contact import broad_phase as bp

MARGIN = 0.02


def _sphere(n):
    """A unit sphere's surface: the hull of ``n`` points spread on it (2 n - 4 triangles)."""
    z = 1 - (2 * np.arange(n) + 1) / n
    phi = np.arange(n) * np.pi * (3 - 5 ** 0.5)
    r = np.sqrt(1 - z * z)
    v = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return v, ConvexHull(v).simplices


SPHERE, FACES = _sphere(162)
N = len(SPHERE)
TRIANGLES = np.concatenate([FACES, FACES + N])
POINTS = np.arange(2 * N)
GROUPS = np.repeat([0, 1], N)


def _two_spheres(seed, distance):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    x0 = np.concatenate([SPHERE, SPHERE + distance * axis / np.linalg.norm(axis)])
    return x0, x0 + rng.normal(0, 0.03, x0.shape)


def _pairs(c):
    valid = np.asarray(c.valid)
    got = list(zip(np.asarray(c.vertex)[valid].tolist(), np.asarray(c.triangle)[valid].tolist()))
    assert len(set(got)) == len(got), "a pair came out twice"
    return set(got)


def _as_set(pairs):
    return set(map(tuple, pairs.tolist()))


FILTERS = [{}, {"groups": GROUPS, "allowed": {(0, 1)}},
           {"groups": GROUPS, "allowed": [(1, 0), (1, 1)]}]


@pytest.mark.parametrize("filters", FILTERS)
def test_matches_brute_force_on_two_spheres(filters):
    query = jax.jit(lambda a, b: bp.candidates(a, b, POINTS, TRIANGLES, MARGIN, 16384,
                                               **filters))
    for seed, distance in [(0, 1.5), (1, 2.05), (2, 3.0)]:  # overlapping, touching, apart
        x0, x1 = _two_spheres(seed, distance)
        ref = bp.brute_force(x0, x1, POINTS, TRIANGLES, MARGIN, **filters)
        c = query(x0, x1)
        assert not c.overflow and int(c.count) == len(ref)
        assert _pairs(c) == _as_set(ref)
        cross = (ref[:, 0] < N) != (ref[:, 1] < len(FACES))
        assert cross.any() == (distance < 2.5)


@pytest.mark.parametrize("exclude", [True, False])
def test_folded_sheet_touches_itself(exclude):
    m = 14
    u, w = np.meshgrid(np.linspace(0, 2, m), np.linspace(0, 1, m), indexing="ij")
    fold = [np.where(u < 1, u, 2 - u), w, np.where(u < 1, 0, 0.05 * (u - 1))]  # over at u = 1
    x0 = np.stack(fold, -1).reshape(-1, 3)
    idx = np.arange(m * m).reshape(m, m)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c_, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c_], 1), np.stack([a, c_, d], 1)])
    x1 = x0 + np.random.default_rng(3).normal(0, 0.01, x0.shape)
    points = np.arange(m * m)
    ref = bp.brute_force(x0, x1, points, tris, MARGIN, exclude_incident=exclude)
    query = jax.jit(lambda p, q: bp.candidates(p, q, points, tris, MARGIN, 8192,
                                               exclude_incident=exclude))
    c = query(x0, x1)
    assert not c.overflow and _pairs(c) == _as_set(ref)
    incident = {(v, t) for t, tri in enumerate(tris) for v in tri}
    assert (_as_set(ref) & incident == set()) == exclude
    assert len(_as_set(ref) - incident) > m  # the two layers meet


def _run(x0, x1, capacity, **kw):
    query = jax.jit(lambda a, b: bp.candidates(a, b, POINTS, TRIANGLES, MARGIN, capacity, **kw))
    return query(x0, x1)


def test_overflow_is_counted_never_lost():
    x0, x1 = _two_spheres(0, 1.5)
    ref = _as_set(bp.brute_force(x0, x1, POINTS, TRIANGLES, MARGIN))
    small = _run(x0, x1, 64)  # capacity short: the first 64 pairs, and how many there are
    assert small.overflow and int(small.count) == len(ref) > 64
    assert len(_pairs(small)) == 64 and _pairs(small) <= ref
    starved = _run(x0, x1, 64, work=100)  # work budget short: the untested count as pairs
    assert starved.overflow and int(starved.count) >= len(ref) and _pairs(starved) <= ref


def test_required_capacity_recovers():
    x0, x1 = _two_spheres(0, 1.5)
    ref = _as_set(bp.brute_force(x0, x1, POINTS, TRIANGLES, MARGIN))
    capacity, work = bp.required_capacity(x0, x1, POINTS, TRIANGLES, MARGIN)
    assert capacity == len(ref) and work >= capacity
    full = _run(x0, x1, capacity, work=work)
    assert not full.overflow and _pairs(full) == ref


def test_jit_and_vmap_over_scenes():
    scenes = [_two_spheres(seed, d) for seed, d in [(4, 1.2), (5, 2.0), (6, 4.0)]]
    x0, x1 = (np.stack(s) for s in zip(*scenes))
    margins = np.array([0.0, 0.02, 0.05])
    kw = {"groups": GROUPS, "allowed": {(0, 1)}}
    batch = jax.jit(jax.vmap(lambda a, b, m: bp.candidates(a, b, POINTS, TRIANGLES, m, 4096,
                                                           **kw)))
    c = batch(x0, x1, margins)
    assert c.vertex.shape == (3, 4096) and c.count.shape == (3,)
    for i, one in enumerate(zip(*c)):
        ref = bp.brute_force(x0[i], x1[i], POINTS, TRIANGLES, margins[i], **kw)
        assert not c.overflow[i] and _pairs(bp.Candidates(*one)) == _as_set(ref)
    assert bp.required_capacity(x0, x1, POINTS, TRIANGLES, 0.02, **kw)[0] == max(
        len(bp.brute_force(a, b, POINTS, TRIANGLES, 0.02, **kw)) for a, b in scenes)


def test_margin_grows_both_boxes():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 0.1]])
    pts, tri = np.array([3]), np.array([[0, 1, 2]])
    assert len(bp.brute_force(x, x, pts, tri, 0.049)) == 0
    assert bp.brute_force(x, x, pts, tri, 0.05).tolist() == [[3, 0]]
    assert int(jax.jit(lambda a: bp.candidates(a, a, pts, tri, 0.05, 1).count)(x)) == 1


def test_bad_input_is_refused():
    x = np.zeros((4, 3))
    pts, tri = np.array([3]), np.array([[0, 1, 2]])
    for kwargs, match in [({"capacity": 0}, "capacity"), ({"work": 0}, "work"),
                          ({"margin": -1.0}, "margin"), ({"x1": np.zeros((4, 2))}, "shape"),
                          ({"triangles": np.array([[0, 1, 4]])}, "triangles indices"),
                          ({"triangles": np.array([0, 1, 2])}, r"\(T, 3\)"),
                          ({"points": np.array([3, 3])}, "repeat"),
                          ({"groups": np.zeros(4, int)}, "together"),
                          ({"groups": np.array([0, 0, 1, 1]), "allowed": {(0, 1)}}, "one body")]:
        args = {"x0": x, "x1": x, "points": pts, "triangles": tri, "margin": 0.1, "capacity": 4,
                **kwargs}
        with pytest.raises(ValueError, match=match):
            bp.candidates(**args)

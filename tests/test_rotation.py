"""The rotation extraction of the corotated projection (:mod:`softbody.rotation`).

The reference is the SVD: for ``F = U diag(s) V^T`` the rotation maximising ``tr(R^T F)`` is
``U V^T`` when that is proper, else the rotation-variant ``U diag(1, 1, -1) V^T`` (flipping
the smallest singular value). The maximum is ``s1 + s2 + sign(det F) s3``; the maximiser
is unique unless the two smallest *signed* singular values sum to zero, e.g. for a pure
reflection. Where it is unique, the derivative is checked against central differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import rotation as rot

RNG = np.random.default_rng(20240611)


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _with_singular_values(signed, rng=RNG) -> np.ndarray:
    """``Q1 diag(signed) Q2^T`` with random rotations: singular values ``|signed|``,
    ``det`` of the sign of their product."""
    return _random_rotation(rng) @ np.diag(signed) @ _random_rotation(rng).T


def _svd_rotation(f: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(f)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    return u @ d @ vt


def _max_objective(f: np.ndarray) -> float:
    s = np.linalg.svd(f, compute_uv=False)
    return s[0] + s[1] + np.sign(np.linalg.det(f)) * s[2]


WIDTH = 20  # every batch is padded to this many columns, so each jitted function compiles once


def _batch(fs) -> jnp.ndarray:
    """``(3, 3, WIDTH)`` batch of the matrices ``fs``, padded with identities."""
    fs = list(fs) + [np.eye(3)] * (WIDTH - len(fs))
    return jnp.asarray(np.stack(fs, axis=-1))


# Maximiser unique: the two smallest signed singular values do not sum to zero.
UNIQUE = {
    "identity": np.eye(3),
    "distinct": _with_singular_values([1.3, 0.9, 0.7]),
    "repeated_pair": _with_singular_values([2.0, 2.0, 0.5]),
    "repeated_pair_small": _with_singular_values([2.0, 0.5, 0.5]),
    "scaled_rotation": 1.7 * _random_rotation(RNG),
    "rotation_by_pi": np.diag([1.0, -1.0, -1.0]),
    "strong_stretch": _with_singular_values([10.0, 1.0, 0.1]),
    "inverted": _with_singular_values([1.3, 0.9, -0.7]),
    "inverted_flat": _with_singular_values([2.0, 1.0, -0.05]),
    "inverted_repeated_pair": _with_singular_values([1.0, 1.0, -0.5]),
}
# Maximiser not unique (signed singular values s2 + s3 = 0): only the maximum is defined.
NON_UNIQUE = {
    "reflection": _with_singular_values([1.0, 1.0, -1.0]),
    "negated_identity": -np.eye(3),
    "inverted_scaled": -1.3 * _random_rotation(RNG),
    "inverted_repeated_small": _with_singular_values([2.0, 0.5, -0.5]),
}
ALL = {**UNIQUE, **NON_UNIQUE}


_polar = jax.jit(rot.polar)
_cold_start = jax.jit(rot.cold_start)
_newton_step = jax.jit(lambda f, q: rot.rotation(f, q, 1))  # rotation(f, q, k) is k of these
_polar_jvp = jax.jit(lambda f, df: jax.jvp(rot.polar, (f,), (df,))[1])


@pytest.fixture(scope="module")
def polar_all():
    names = list(ALL)
    r = np.asarray(_polar(_batch([ALL[n] for n in names])))
    return {n: r[:, :, k] for k, n in enumerate(names)}


@pytest.mark.parametrize("name", list(ALL))
def test_polar_is_a_proper_rotation(polar_all, name):
    r = polar_all[name]
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(r.T @ r, np.eye(3), rtol=0, atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12


@pytest.mark.parametrize("name", list(UNIQUE))
def test_polar_matches_svd(polar_all, name):
    np.testing.assert_allclose(polar_all[name], _svd_rotation(UNIQUE[name]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", list(ALL))
def test_polar_reaches_the_maximum(polar_all, name):
    f = ALL[name]
    assert np.trace(polar_all[name].T @ f) == pytest.approx(_max_objective(f), abs=1e-12)


def test_identity_is_exact(polar_all):
    np.testing.assert_array_equal(polar_all["identity"], np.eye(3))
    q = rot.identity_quaternions(WIDTH)
    r, q1 = _newton_step(_batch([np.eye(3)]), q)
    np.testing.assert_array_equal(np.asarray(r)[:, :, 0], np.eye(3))
    np.testing.assert_array_equal(np.asarray(q1), np.asarray(q))


def test_cold_start_gives_unit_quaternions_and_the_polar_factor_when_det_positive():
    names = list(ALL)
    q = np.asarray(_cold_start(_batch([ALL[n] for n in names])))
    np.testing.assert_allclose(np.sum(q * q, axis=0), 1.0, atol=1e-14)
    r = np.asarray(rot.quat_to_mat(jnp.asarray(q)))
    for k, name in enumerate(names):
        if np.linalg.det(ALL[name]) > 0:
            np.testing.assert_allclose(r[:, :, k], _svd_rotation(ALL[name]), atol=1e-12, err_msg=name)


def _axis_angle(axis, angle) -> np.ndarray:
    k = np.cross(np.eye(3), np.asarray(axis) / np.linalg.norm(axis))  # skew matrix of the unit axis
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _quaternion_of(r: np.ndarray):
    return rot.mat_to_quat(_batch([r]))  # (4, WIDTH)


def test_warm_start_converges_quadratically():
    """From a start 0.2 rad off, Newton's error roughly squares per step (0.2 -> 1e-2 ->
    1e-4 -> 1e-8 -> round-off); from the exact rotation one step changes nothing."""
    f = _with_singular_values([1.4, 1.0, 0.6])
    exact = _svd_rotation(f)
    start = exact @ _axis_angle(RNG.normal(size=3), 0.2)
    q = _quaternion_of(start)
    errors = [np.abs(start - exact).max()]
    for _ in range(5):
        r, q = _newton_step(_batch([f]), q)
        errors.append(np.abs(np.asarray(r)[:, :, 0] - exact).max())
    assert errors[-1] < 1e-14
    for e0, e1 in zip(errors, errors[1:]):
        assert e1 <= max(10 * e0**2, 1e-14), errors
    r, _ = _newton_step(_batch([f]), _quaternion_of(exact))
    np.testing.assert_allclose(np.asarray(r)[:, :, 0], exact, atol=1e-15)


def test_large_rotation_from_the_identity():
    """No warm start: capped steps (1 rad) then Newton reach a 2.8 rad rotation."""
    f = _axis_angle([1.0, 2.0, -0.5], 2.8) @ np.diag([1.2, 1.0, 0.9])
    q = rot.identity_quaternions(WIDTH)
    for _ in range(12):
        r, q = _newton_step(_batch([f]), q)
    np.testing.assert_allclose(np.asarray(r)[:, :, 0], _svd_rotation(f), atol=1e-12)


# ------------------------------------------------------------------------------------
# Derivatives (all cases in one batch: each column depends on its own F only)
# ------------------------------------------------------------------------------------

EPS = 1e-6
D_UNIQUE = {name: RNG.normal(size=(3, 3)) for name in UNIQUE}


@pytest.fixture(scope="module")
def jvps():
    names = list(UNIQUE)
    f, df = _batch([UNIQUE[n] for n in names]), _batch([D_UNIQUE[n] for n in names])
    dr = np.asarray(_polar_jvp(f, df))
    fd = (np.asarray(_polar(f + EPS * df)) - np.asarray(_polar(f - EPS * df))) / (2 * EPS)
    return {n: (dr[:, :, k], fd[:, :, k]) for k, n in enumerate(names)}


@pytest.mark.parametrize("name", list(UNIQUE))
def test_jvp_matches_central_differences(jvps, name):
    """Truncation error O(eps^2 |d3R|) ~ 1e-11 and round-off O(1e-16 / eps) ~ 1e-10 for
    eps = 1e-6 and these singular values (s2 + s3 >= 0.05): 1e-7 leaves a wide margin."""
    dr, fd = jvps[name]
    assert np.all(np.isfinite(dr))
    np.testing.assert_allclose(dr, fd, rtol=0, atol=1e-7 * max(1.0, np.abs(fd).max()))


def test_jvp_at_identity_is_the_skew_part(jvps):
    """At F = I: R(I + e A) = I + e skew(A) + O(e^2), with JAX's SVD derivative NaN there."""
    a = D_UNIQUE["identity"]
    np.testing.assert_allclose(jvps["identity"][0], 0.5 * (a - a.T), atol=1e-15)


SECOND = ["identity", "repeated_pair", "rotation_by_pi", "inverted", "inverted_repeated_pair"]


@pytest.fixture(scope="module")
def second_derivatives():
    """``grad`` of ``sum(W * R(F))`` (the transpose of the custom JVP) and its forward
    derivative (second order, as Newton's method on the energy needs), with central
    differences of the per-column losses and of the gradient."""
    w = _batch([RNG.normal(size=(3, 3)) for _ in SECOND])
    f = _batch([UNIQUE[n] for n in SECOND])
    df = _batch([RNG.normal(size=(3, 3)) for _ in SECOND])

    def losses(f):
        return np.sum(np.asarray(w) * np.asarray(_polar(f)), axis=(0, 1))

    grad = jax.grad(lambda f: jnp.sum(w * rot.polar(f)))
    grad_and_hvp = jax.jit(lambda f: jax.jvp(grad, (f,), (df,)))
    g, hv = (np.asarray(a) for a in grad_and_hvp(f))
    fd1 = (losses(f + EPS * df) - losses(f - EPS * df)) / (2 * EPS)
    fd2 = (np.asarray(grad_and_hvp(f + EPS * df)[0]) - np.asarray(grad_and_hvp(f - EPS * df)[0])) / (2 * EPS)
    directional = np.sum(g * np.asarray(df), axis=(0, 1))
    return {n: (directional[k], fd1[k], hv[:, :, k], fd2[:, :, k]) for k, n in enumerate(SECOND)}


@pytest.mark.parametrize("name", SECOND)
def test_reverse_and_second_derivatives(second_derivatives, name):
    directional, fd1, hv, fd2 = second_derivatives[name]
    assert np.isfinite(directional) and np.all(np.isfinite(hv))
    assert directional == pytest.approx(fd1, abs=1e-7 * max(1.0, abs(fd1)))
    np.testing.assert_allclose(hv, fd2, rtol=0, atol=1e-6 * max(1.0, np.abs(fd2).max()))


# ------------------------------------------------------------------------------------
# Hard cold starts: close small singular values of inverted F, flat and degenerate tets
# ------------------------------------------------------------------------------------

def test_polar_inverted_with_close_small_singular_values():
    """Unique maximisers (s2 + s3 = 0.01) in 20 random orientations."""
    fs = [_with_singular_values([1.0, 0.9, -0.89]) for _ in range(20)]
    r = np.asarray(_polar(_batch(fs)))
    for k, f in enumerate(fs):
        np.testing.assert_allclose(r[:, :, k], _svd_rotation(f), atol=1e-10)


def test_polar_of_a_flat_tet_is_finite():
    f = np.diag([2.0, 1.0, 0.0])  # a tet squashed flat onto the xy-plane
    r = np.asarray(_polar(_batch([f])))[:, :, 0]
    assert np.all(np.isfinite(r))
    np.testing.assert_allclose(r, np.eye(3), atol=1e-12)


def test_polar_of_flat_and_nearly_flat_tets_in_random_orientations():
    """det F = 0 or ~1e-14 (rank 2): the maximiser is unique (s1 + s2 > 0) and found."""
    fs = [_with_singular_values([2.0, 0.7, 0.0]) for _ in range(10)]
    fs += [_with_singular_values([1.5, 1.0, sgn * 1e-14]) for sgn in (1, -1) for _ in range(5)]
    r = np.asarray(_polar(_batch(fs)))
    for k, f in enumerate(fs):
        np.testing.assert_allclose(r[:, :, k], _svd_rotation(f), atol=1e-9)


def test_polar_inverted_with_equal_small_singular_values_reaches_the_maximum():
    """s2 = |s3|, det F < 0: the maximiser is not unique, but tr(R^T F) must be maximal."""
    fs = [_with_singular_values([1.0, 0.8, -0.8]) for _ in range(10)]
    r = np.asarray(_polar(_batch(fs)))
    for k, f in enumerate(fs):
        assert abs(np.linalg.det(r[:, :, k]) - 1.0) < 1e-12
        assert np.trace(r[:, :, k].T @ f) == pytest.approx(1.0, abs=1e-10)

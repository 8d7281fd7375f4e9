"""The collision-response QP (softbody.contact.impact_zone): the forward solution and its KKT
conditions, the two backwards against each other and against central differences, the JAX
wrapper, and the errors for bad input.

The differentiated problems are built from their solution: active rows with multipliers in
[0.5, 1.5], inactive rows slack by 0.5-1.5, so a small perturbation keeps the active set.
"""

import jax
import numpy as np
import pytest

from softbody.contact import impact_zone as iz
from softbody.bench.impact_zone import contacts


def problem(seed, n=9, m=5, active=3):
    """``(x, w, G, h, z, lam)``: a random QP and its solution, the first ``active`` rows active."""
    rng = np.random.default_rng(seed)
    G, w, z = rng.normal(size=(m, n)), rng.uniform(0.5, 2.0, n), rng.normal(size=n)
    lam = np.zeros(m)
    lam[:active] = rng.uniform(0.5, 1.5, active)
    h = -G @ z - np.where(lam > 0, 0.0, rng.uniform(0.5, 1.5, m))
    return z + G.T @ lam / w, w, G, h, z, lam


def test_one_vertex_is_pushed_onto_a_plane_along_its_weighted_projection():
    normal, d = np.array([1.0, 2.0, 2.0]) / 3, 0.5  # the plane normal . z >= d
    x, w = np.array([0.1, -0.2, 0.3]), np.array([1.0, 2.0, 4.0])
    z, lam = iz.solve(x, w, -normal[None], np.array([d]))
    expected = (d - normal @ x) / (normal @ (normal / w))
    np.testing.assert_allclose(lam, [expected], rtol=1e-13)
    np.testing.assert_allclose(z, x + expected * normal / w, rtol=1e-13)
    assert normal @ z == pytest.approx(d, rel=1e-13)
    outside = z + normal
    z, lam = iz.solve(outside, w, -normal[None], np.array([d]))
    np.testing.assert_array_equal(z, outside)
    np.testing.assert_array_equal(lam, [0.0])


@pytest.mark.parametrize("seed, n, m", [(0, 6, 4), (1, 12, 8), (2, 6, 40), (3, 30, 30)])
def test_the_solution_satisfies_the_kkt_conditions(seed, n, m):
    rng = np.random.default_rng(seed)
    G, w = rng.normal(size=(m, n)), rng.uniform(0.5, 2.0, n)
    h = -G @ rng.normal(size=n) - rng.uniform(0.0, 1.0, m)  # a strictly feasible point exists
    x = 3 * rng.normal(size=n)
    z, lam = iz.solve(x, w, G, h)
    g = G @ z + h
    assert g.max() <= 1e-9 and lam.min() >= 0
    assert np.abs(lam * g).max() <= 1e-9
    assert np.abs(w * (z - x) + G.T @ lam).max() <= 1e-9
    assert (G @ x + h).max() > 0 and lam.max() > 0  # x violated some row: the response moved it


@pytest.mark.parametrize("seed", range(4))
def test_the_constructed_solution_is_found(seed):
    x, w, G, h, z, lam = problem(seed)
    z_, lam_ = iz.solve(x, w, G, h)
    np.testing.assert_allclose(z_, z, atol=1e-12)
    np.testing.assert_allclose(lam_, lam, atol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_the_kkt_and_qr_backwards_agree(seed):
    rng = np.random.default_rng(seed)
    for x, w, G, h, z, lam in (problem(seed, n=30, m=12, active=5), contacts(8 + seed, rng)[:6]):
        dz = rng.normal(size=x.size)
        kkt, qr = (f(x, w, G, h, z, lam, dz) for f in (iz.backward_kkt, iz.backward_qr))
        for a, b in zip(kkt, qr):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-9 * np.abs(a).max())


@pytest.mark.parametrize("backward", [iz.backward_kkt, iz.backward_qr])
def test_the_backwards_match_central_differences(backward):
    x, w, G, h, z, lam = problem(5)
    c = np.random.default_rng(6).normal(size=x.size)
    grads = backward(x, w, G, h, z, lam, c)
    inputs, eps = [x, w, G, h], 1e-6
    for k, grad in enumerate(grads):
        fd = np.zeros_like(grad)
        for idx in np.ndindex(grad.shape):
            shifted = []
            for sign in (1, -1):
                moved = [a.copy() for a in inputs]
                moved[k][idx] += sign * eps
                shifted.append(c @ iz.solve(*moved)[0])
            fd[idx] = (shifted[0] - shifted[1]) / (2 * eps)
        assert np.linalg.norm(grad - fd) <= 1e-6 * np.linalg.norm(grad), grads._fields[k]
    assert not grads.dG[lam == 0].any() and not grads.dh[lam == 0].any()


def test_the_jax_wrapper_solves_and_differentiates_by_the_qr_backward():
    x, w, G, h, z, lam = problem(7)
    c = np.random.default_rng(8).normal(size=x.size)
    np.testing.assert_allclose(jax.jit(iz.qp)(x, w, G, h), z, atol=1e-12)
    grads = jax.grad(lambda *a: c @ iz.qp(*a), argnums=(0, 1, 2, 3))(x, w, G, h)
    for got, expected in zip(grads, iz.backward_qr(x, w, G, h, z, lam, c)):
        np.testing.assert_allclose(got, expected, atol=1e-12)


GOOD = {"x": np.zeros(3), "w": np.ones(3), "G": np.ones((2, 3)), "h": np.ones(2)}


@pytest.mark.parametrize("change, message", [
    ({"x": np.zeros((3, 1))}, "x must be a vector (1-D), got shape (3, 1); pass x with 1 dim"),
    ({"w": np.ones(4)}, "w has shape (4,) but x has 3 entries; pass one weight (mass) per"),
    ({"G": np.ones((2, 4))}, "G has shape (2, 4) but x has 3 entries; G must be (m, 3)"),
    ({"h": np.ones(3)}, "h has shape (3,) but G has 2 rows; pass one offset per constraint"),
    ({"w": np.array([1.0, 0.0, 1.0])}, ("w must be positive (W = diag(w) is the mass matrix), got"
                                         " min(w) = 0.0; give every coordinate a positive mass")),
    ({"x": np.array([0.0, np.nan, 0.0])}, "x has non-finite entries (nan or inf); pass finite"),
    ({"G": np.array([[1.0, 0, 0], [-1.0, 0, 0]])}, "the constraints G z + h <= 0 have no solution"),
])
def test_bad_input_is_refused_with_the_problem_and_the_fix(change, message):
    with pytest.raises(ValueError) as err:
        iz.solve(**{**GOOD, **change})
    assert message in str(err.value)
    if "shape" in message:  # the JAX wrapper checks shapes when it is traced
        with pytest.raises(ValueError) as err:
            iz.qp(**{**GOOD, **change})
        assert message in str(err.value)


@pytest.mark.parametrize("backward", [iz.backward_kkt, iz.backward_qr])
def test_dependent_active_rows_and_a_wrong_solution_shape_are_refused(backward):
    x, w, G, h = np.zeros(3), np.ones(3), np.array([[1.0, 0, 0], [1.0, 0, 0]]), np.zeros(2)
    with pytest.raises(ValueError, match="linearly dependent.*remove duplicate or redundant"):
        backward(x, w, G, h, np.zeros(3), np.ones(2), np.ones(3))
    with pytest.raises(ValueError, match=r"lam has shape \(3,\), expected \(2,\); pass the \(z, l"):
        backward(x, w, G, h, np.zeros(3), np.ones(3), np.ones(3))

"""Linear solvers of the PD global step: solutions, implicit gradients, jit/scan/vmap, errors."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse.linalg

from softbody import linsolve
from softbody.bench.solvers import pd_matrix, tet_grid
from softbody.linsolve import (
    PCG,
    DenseCholesky,
    Factor,
    SparseCholesky,
    SparseLDL,
    SparseLU,
    SparsityPattern,
    auto_solver,
)

SOLVERS = {
    "SparseLDL": SparseLDL(),
    "SparseCholesky": SparseCholesky(),
    "SparseLU": SparseLU(),
    "DenseCholesky": DenseCholesky(),
    "PCG": PCG(tol=1e-13),
}
solver_names = pytest.mark.parametrize("name", list(SOLVERS))

#: a soft material (Pa) keeps the test matrix's condition number near 1e3, so that finite
#: differences resolve the gradients to 1e-6
YOUNG = 1e4


@pytest.fixture(scope="module")
def system():
    """A 60-vertex PD matrix (3 right-hand sides): pattern, values, b, scipy's solution."""
    rows, cols, values = pd_matrix(*tet_grid((5, 4, 3)), young=YOUNG)
    pattern, index = SparsityPattern.from_coo(60, rows, cols)
    data = np.asarray(jax.ops.segment_sum(values, index, pattern.nnz))
    b = np.random.default_rng(0).standard_normal((pattern.n, 3))
    x = scipy.sparse.linalg.spsolve(pattern.to_scipy(data).tocsc(), b)
    return pattern, data, b, x


@pytest.fixture
def small_cache():
    """Shrink the host factor cache for a test, then restore it."""
    capacity = linsolve.factor_cache_info()["capacity"]
    yield
    linsolve.set_factor_cache_capacity(capacity)


def relative_error(x, reference):
    return float(np.max(np.abs(np.asarray(x) - reference)) / np.max(np.abs(reference)))


def coupling(pattern, data):
    """A weight c with |c A^-1| = 1/2, for right-hand sides that feed back the solution."""
    return 0.5 * np.linalg.eigvalsh(pattern.to_scipy(data).toarray()).min()


def material_direction(pattern, seed):
    """A perturbation of the matrix values by random per-tet stiffness and per-vertex mass
    changes: symmetric, and keeping the stiffness's null space, as material parameters do."""
    points, tets = tet_grid((5, 4, 3))
    rows, cols, values = pd_matrix(points, tets, young=YOUNG)
    factors = np.random.default_rng(seed).uniform(-1, 1, len(tets) + len(points))
    factors = np.concatenate([np.repeat(factors[: len(tets)], 16), factors[len(tets) :]])
    _, index = SparsityPattern.from_coo(pattern.n, rows, cols)
    return np.bincount(index, factors * values, minlength=pattern.nnz)


# --------------------------------------------------------------------------- pattern


def test_grid_mesh_is_a_valid_tet_mesh():
    points, tets = tet_grid((3, 4, 5), spacing=0.5)
    assert points.shape == (60, 3) and tets.shape == (6 * 2 * 3 * 4, 4)
    volumes = np.linalg.det(points[tets[:, 1:]] - points[tets[:, :1]]) / 6
    np.testing.assert_allclose(volumes, 0.5**3 / 6)  # positive, and they tile the box
    faces = np.sort(tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2  # conforming: an interior face is shared by exactly two tets
    boundary_faces = 2 * 2 * (2 * 3 + 2 * 4 + 3 * 4)
    assert np.sum(counts == 1) == boundary_faces


def test_from_coo_sums_repeated_entries_like_scipy(system):
    pattern, data, _, _ = system
    rows, cols, values = pd_matrix(*tet_grid((5, 4, 3)), young=YOUNG)
    reference = scipy.sparse.coo_matrix((values, (rows, cols)), shape=(60, 60)).toarray()
    np.testing.assert_allclose(pattern.to_scipy(data).toarray(), reference, rtol=1e-14)
    np.testing.assert_array_equal(pattern.indptr, pattern.to_scipy(data).indptr)
    np.testing.assert_array_equal(pattern.rows[pattern.diagonal_index], np.arange(60))
    np.testing.assert_array_equal(pattern.cols[pattern.transpose_index], pattern.rows)


def test_matvec_matches_scipy_and_is_differentiable(system):
    pattern, data, b, _ = system
    matrix = pattern.to_scipy(data)
    np.testing.assert_allclose(pattern.matvec(data, b), matrix @ b, rtol=1e-13)
    np.testing.assert_allclose(pattern.matvec(data, b[:, 0]), matrix @ b[:, 0], rtol=1e-13)
    np.testing.assert_allclose(pattern.to_dense(data), matrix.toarray())
    # A x is linear in data and in x: the gradients are exact
    weights = np.random.default_rng(1).standard_normal(b.shape)
    grad_data, grad_x = jax.grad(lambda d, x: jnp.sum(weights * pattern.matvec(d, x)), (0, 1))(
        data, b
    )
    np.testing.assert_allclose(grad_x, matrix.T @ weights, rtol=1e-12)
    np.testing.assert_allclose(
        grad_data, np.sum(weights[pattern.rows] * b[pattern.cols], axis=1), rtol=1e-12
    )


@pytest.mark.parametrize(
    "rows, cols, match",
    [
        ([0, 1, 2, 1], [0, 1, 3, 2], r"must lie in \[0, 3\).*square"),  # a 3 x 4 matrix
        ([0, 1, 2, 0], [0, 1, 2, 1], "not symmetric"),
        ([0, 2, 0, 2], [0, 2, 2, 0], "diagonal entries are missing"),
        ([0, 1], [0, 1, 2], "equal length"),
    ],
)
def test_bad_patterns_are_refused(rows, cols, match):
    with pytest.raises(ValueError, match=match):
        SparsityPattern.from_coo(3, np.array(rows), np.array(cols))


def test_unsorted_pattern_is_refused():
    with pytest.raises(ValueError, match="from_coo"):
        SparsityPattern(2, np.array([1, 0]), np.array([1, 0]))


# --------------------------------------------------------------------------- solutions


@solver_names
def test_solution_matches_scipy(system, name):
    pattern, data, b, x = system
    solver = SOLVERS[name]
    factor = solver.factorize(pattern, data)
    assert relative_error(solver.solve(pattern, factor, b), x) < 1e-10
    assert relative_error(solver.solve(pattern, factor, b[:, 1]), x[:, 1]) < 1e-10


@solver_names
def test_many_solves_in_jitted_scan_share_one_factorisation(system, name):
    pattern, data, b, _ = system
    solver = SOLVERS[name]
    matrix = pattern.to_scipy(data).tocsc()
    c = coupling(pattern, data)

    @jax.jit
    def rollout(data, b):
        factor = solver.factorize(pattern, data)

        def step(x, scale):
            x = solver.solve(pattern, factor, scale * b + c * x, x0=x)
            return x, x

        return jax.lax.scan(step, jnp.zeros_like(b), jnp.arange(1.0, 6.0))[1]

    xs = np.asarray(rollout(data, b))
    x = np.zeros_like(b)
    for k, scale in enumerate(range(1, 6)):
        x = scipy.sparse.linalg.spsolve(matrix, scale * b + c * x)
        assert relative_error(xs[k], x) < 1e-10


@solver_names
def test_gradients_match_central_differences(system, name):
    """d/d b and d/d data (reverse and forward mode), through a rematerialised scan of solves."""
    pattern, data, b, x = system
    solver = SOLVERS[name]
    weights = np.random.default_rng(2).standard_normal(b.shape)
    c = coupling(pattern, data)
    scale = np.abs(x).max()

    def loss(data, b):
        factor = solver.factorize(pattern, data)

        @jax.checkpoint  # as the simulator does: solves are recomputed in the backward pass
        def step(x, _):
            return solver.solve(pattern, factor, b + c * x), None

        x = jax.lax.scan(step, jnp.zeros_like(b), None, length=3)[0] / scale
        return jnp.sum(weights * x) + 0.5 * jnp.sum(x**2)

    loss_jit = jax.jit(loss)
    grad_data, grad_b = jax.jit(jax.grad(loss, (0, 1)))(data, b)

    direction = material_direction(pattern, seed=3)
    eps = 1e-4
    fd = (loss_jit(data + eps * direction, b) - loss_jit(data - eps * direction, b)) / (2 * eps)
    assert abs(jnp.vdot(grad_data, direction) - fd) <= 1e-6 * abs(fd)
    _, forward = jax.jit(lambda t: jax.jvp(lambda d: loss(d, b), (data,), (t,)))(direction)
    assert abs(forward - fd) <= 1e-6 * abs(fd)

    direction = np.random.default_rng(4).standard_normal(b.shape)
    eps = 1e-2  # the loss is quadratic in b: central differences are exact but for rounding
    fd = (loss_jit(data, b + eps * direction) - loss_jit(data, b - eps * direction)) / (2 * eps)
    assert abs(jnp.vdot(grad_b, direction) - fd) <= 1e-6 * abs(fd)


@solver_names
def test_vmap_over_two_matrices_solves_each(system, name):
    pattern, data, b, x = system
    solver = SOLVERS[name]
    # a second, different matrix: the mass part doubled (the diagonal)
    other = data.copy()
    other[pattern.diagonal_index] *= 2
    x_other = scipy.sparse.linalg.spsolve(pattern.to_scipy(other).tocsc(), b)

    @jax.jit
    @jax.vmap
    def solve_each(data):
        return solver.solve(pattern, solver.factorize(pattern, data), b)

    xs = solve_each(jnp.stack([data, other]))
    assert relative_error(xs[0], x) < 1e-10
    assert relative_error(xs[1], x_other) < 1e-10
    assert relative_error(xs[1], x) > 1e-3


@solver_names
def test_vmap_over_right_hand_sides_with_one_factor(system, name):
    pattern, data, b, x = system
    solver = SOLVERS[name]
    factor = solver.factorize(pattern, data)
    scales = jnp.array([1.0, -2.0, 3.0])
    xs = jax.jit(jax.vmap(lambda s: solver.solve(pattern, factor, s * b)))(scales)
    for s, xi in zip(scales, xs):
        assert relative_error(xi, float(s) * x) < 1e-10


def test_vmap_of_gradients_over_matrices(system):
    pattern, data, b, _ = system
    solver = SOLVERS["SparseCholesky"]

    def loss(data):
        return jnp.sum(solver.solve(pattern, solver.factorize(pattern, data), b) ** 2)

    batch = jnp.stack([data, 1.5 * data])
    grads = jax.jit(jax.vmap(jax.grad(loss)))(batch)
    np.testing.assert_allclose(grads[1], jax.grad(loss)(batch[1]), rtol=1e-10)
    np.testing.assert_allclose(grads[0], jax.grad(loss)(batch[0]), rtol=1e-10)


@pytest.mark.parametrize("name", ["SparseLDL", "DenseCholesky"])
def test_per_column_solves_each_column_with_its_matrix(system, name):
    """``PerColumn``: three matrices on one pattern, column a of b solved with matrix a, and
    the gradient of a loss with respect to every matrix's values against the same loss
    taken column by column with the plain solver."""
    pattern, data, b, x = system
    solver = SOLVERS[name]
    datas = np.stack([data, data.copy(), data.copy()])
    datas[1, pattern.diagonal_index] *= 2
    datas[2] = 0.5 * data
    per = linsolve.PerColumn(solver)
    xs = jax.jit(lambda d: per.solve(pattern, per.factorize(pattern, d), b))(datas)
    for a in range(3):
        expected = scipy.sparse.linalg.spsolve(pattern.to_scipy(datas[a]).tocsc(), b[:, a])
        assert relative_error(xs[:, a], expected) < 1e-10
    assert relative_error(xs[:, 0], x[:, 0]) < 1e-10 and relative_error(xs[:, 1], x[:, 1]) > 1e-3

    def loss(d):
        return jnp.sum(per.solve(pattern, per.factorize(pattern, d), b) ** 3)

    def loss_by_columns(d):
        return sum(jnp.sum(solver.solve(pattern, solver.factorize(pattern, d[a]), b[:, a]) ** 3) for a in range(3))

    np.testing.assert_allclose(jax.grad(loss)(datas), jax.grad(loss_by_columns)(datas), rtol=1e-9, atol=0)
    with pytest.raises(ValueError, match="one column per matrix"):
        per.solve(pattern, per.factorize(pattern, datas), b[:, :2])
    with pytest.raises(ValueError, match=r"shape \(k, "):
        per.factorize(pattern, data)


# --------------------------------------------------------------------------- host cache


@pytest.mark.parametrize("name", ["SparseCholesky", "SparseLU"])
def test_evicted_factorisation_is_rebuilt_from_the_factor(system, name, small_cache):
    pattern, data, b, x = system
    solver = SOLVERS[name]
    solve = jax.jit(lambda factor, b: solver.solve(pattern, factor, b))
    factor = jax.block_until_ready(jax.jit(solver.factorize, static_argnums=0)(pattern, data))
    linsolve.clear_factor_cache()
    before = linsolve.factor_cache_info()["refactorizations"]
    with pytest.warns(RuntimeWarning, match="evicted"):
        assert relative_error(solve(factor, b), x) < 1e-10
    assert linsolve.factor_cache_info()["refactorizations"] == before + 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # it is back in the cache: no second refactorisation
        assert relative_error(solve(factor, b), x) < 1e-10

    # least recently used goes first; under vmap each member refactorises on its own
    linsolve.set_factor_cache_capacity(1)
    other = 2 * data
    factors = jax.vmap(lambda d: solver.factorize(pattern, d))(jnp.stack([data, other]))
    jax.block_until_ready(factors)
    assert linsolve.factor_cache_info()["size"] == 1
    with pytest.warns(RuntimeWarning, match="evicted"):
        xs = jax.block_until_ready(jax.vmap(lambda f: solver.solve(pattern, f, b))(factors))
    assert relative_error(xs[0], x) < 1e-10
    assert relative_error(xs[1], x / 2) < 1e-10


def test_factorize_runs_once_per_call_and_handles_differ(system):
    pattern, data, _, _ = system
    solver = SOLVERS["SparseCholesky"]
    before = linsolve.factor_cache_info()["factorizations"]
    first = jax.block_until_ready(solver.factorize(pattern, data))
    second = jax.block_until_ready(solver.factorize(pattern, data))
    assert linsolve.factor_cache_info()["factorizations"] == before + 2
    assert int(first.aux) != int(second.aux)


def test_sparse_ldl_compiles_without_a_host_callback(system):
    """SparseLDL factorises and solves through XLA FFI calls: no Python callback in the
    program (which would keep it out of the persistent compilation cache), nothing in the
    host factor cache, and its factor is plain arrays."""
    pattern, data, b, x = system
    solver = SOLVERS["SparseLDL"]
    assert not solver.host_callback and linsolve.PerColumn(solver).host_callback is False
    program = jax.jit(lambda d, b: solver.solve(pattern, solver.factorize(pattern, d), b))
    text = program.lower(data, b).as_text()
    assert "softbody_ldl_factor" in text and "softbody_ldl_solve" in text
    assert "callback" not in text
    linsolve.clear_factor_cache()
    assert relative_error(program(data, b), x) < 1e-12
    assert linsolve.factor_cache_info()["size"] == 0
    values, rowind = solver.factorize(pattern, data).aux
    assert values.dtype == jnp.float64 and rowind.dtype == jnp.int32


def _random_spd(n: int, seed: int):
    """A random SPD matrix on a random symmetric pattern: ``(pattern, data, dense)``."""
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, n, (2, 4 * n))
    keep = i != j
    rows = np.concatenate([i[keep], j[keep], np.arange(n)])
    cols = np.concatenate([j[keep], i[keep], np.arange(n)])
    pattern, _ = SparsityPattern.from_coo(n, rows, cols)
    upper = np.where(pattern.rows < pattern.cols, rng.uniform(-1, 1, pattern.nnz), 0.0)
    off = upper + upper[pattern.transpose_index]
    dense = np.asarray(pattern.to_dense(off))
    data = off + np.where(pattern.rows == pattern.cols, np.abs(dense).sum(axis=1)[pattern.rows] + 0.1, 0.0)
    return pattern, data, np.asarray(pattern.to_dense(data))


def test_sparse_ldl_factor_matches_scipy_on_a_random_pattern():
    """The native numeric factorisation on an irregular pattern: ``L D L^T`` is the
    permuted matrix, and solves agree with scipy to rounding."""
    pattern, data, dense = _random_spd(300, seed=3)
    solver = SOLVERS["SparseLDL"]
    factor = jax.jit(solver.factorize, static_argnums=0)(pattern, data)
    analysis = linsolve._ldl_analysis(pattern)
    values, rowind = (np.asarray(a) for a in factor.aux)
    n, nnz_l = pattern.n, analysis.nnz_l
    lower = scipy.sparse.csc_matrix((values[:nnz_l], rowind, analysis.colptr), shape=(n, n)).toarray()
    unit = lower + np.eye(n)
    product = unit @ np.diag(1 / values[nnz_l:]) @ unit.T
    permuted = dense[np.ix_(analysis.perm, analysis.perm)]
    assert np.max(np.abs(product - permuted)) < 1e-12 * np.max(np.abs(dense))
    b = np.random.default_rng(4).standard_normal((n, 5))
    x = np.asarray(solver.solve(pattern, factor, b))
    assert np.max(np.abs(dense @ x - b)) < 1e-12 * np.max(np.abs(b))
    assert relative_error(x, scipy.sparse.linalg.spsolve(pattern.to_scipy(data).tocsc(), b)) < 1e-12


def test_sparse_ldl_refuses_nan_and_indefinite_matrices_with_the_fix(system):
    pattern, data, b, _ = system
    factorize = jax.jit(SOLVERS["SparseLDL"].factorize, static_argnums=0)
    indefinite = data.copy()
    indefinite[pattern.diagonal_index[7]] *= -1
    with pytest.raises(jax.errors.JaxRuntimeError,
                       match=r"SparseLDL: the matrix is not positive definite \(pivot .* <= 0 at row \d+\); "
                             r"check the material parameters and the time step"):
        jax.block_until_ready(factorize(pattern, indefinite))
    nan = data.copy()
    nan[pattern.diagonal_index[3]] = np.nan
    with pytest.raises(jax.errors.JaxRuntimeError, match=r"SparseLDL: the matrix values contain NaN or inf \(entry \(3, 3\)\)"):
        jax.block_until_ready(factorize(pattern, nan))
    # a batch refuses the member that fails, and solves the others
    batch = jax.jit(jax.vmap(lambda d: SOLVERS["SparseLDL"].solve(pattern, SOLVERS["SparseLDL"].factorize(pattern, d), b)))
    with pytest.raises(jax.errors.JaxRuntimeError, match="not positive definite"):
        jax.block_until_ready(batch(np.stack([data, indefinite])))
    assert np.all(np.isfinite(np.asarray(batch(np.stack([data, 2 * data])))))


# --------------------------------------------------------------------------- PCG specifics


def test_pcg_uses_the_warm_start_and_reports_nothing_at_max_iter(system):
    pattern, data, b, x = system
    one_step = PCG(max_iter=1)
    factor = one_step.factorize(pattern, data)
    # started at the solution it is already converged
    assert relative_error(one_step.solve(pattern, factor, b, x0=x), x) < 1e-12
    # from zero one iteration is far from it, and no error is raised: callers check residuals
    x1 = np.asarray(one_step.solve(pattern, factor, b))
    residual = np.linalg.norm(pattern.to_scipy(data) @ x1 - b) / np.linalg.norm(b)
    assert residual > 1e-3


def test_pcg_without_preconditioner_converges_too(system):
    pattern, data, b, x = system
    solver = PCG(tol=1e-13, preconditioner="none", max_iter=2000)
    assert relative_error(solver.solve(pattern, solver.factorize(pattern, data), b), x) < 1e-10


# --------------------------------------------------------------------------- errors


#: The JAX solvers refuse a matrix arithmetically (every solve NaN: no host callback, so
#: their programs can be cached); the host solvers raise from their callback, SparseLDL
#: from its native factorisation.
IN_JAX = ("DenseCholesky", "PCG")


def _refused(name, pattern, data, b, message):
    solver = SOLVERS[name]
    factorize = jax.jit(solver.factorize, static_argnums=0)
    if name in IN_JAX:
        x = jax.jit(solver.solve, static_argnums=0)(pattern, factorize(pattern, data), b)
        assert np.all(np.isnan(np.asarray(x)))
    else:
        with pytest.raises(Exception, match=message):
            jax.block_until_ready(factorize(pattern, data))


@pytest.mark.parametrize("name", ["SparseLDL", "SparseCholesky", "DenseCholesky", "PCG"])
def test_non_spd_matrix_is_refused(system, name):
    pattern, data, b, _ = system
    indefinite = data.copy()
    indefinite[pattern.diagonal_index[7]] *= -1
    _refused(name, pattern, indefinite, b, "not positive definite")


def test_jax_solvers_compile_without_host_callbacks(system):
    """A host callback keeps a program out of JAX's persistent compilation cache."""
    pattern, data, b, _ = system
    for name in IN_JAX:
        solver = SOLVERS[name]
        text = jax.jit(lambda d, r: solver.solve(pattern, solver.factorize(pattern, d), r)).lower(data, b).as_text()
        assert "callback" not in text, name


def test_singular_matrix_is_refused_by_lu(system):
    pattern, data, _, _ = system
    singular = np.where(pattern.rows == 0, 0.0, data)
    singular = np.where(pattern.cols == 0, 0.0, singular)
    with pytest.raises(Exception, match="singular"):
        jax.block_until_ready(SOLVERS["SparseLU"].factorize(pattern, singular))


@solver_names
def test_asymmetric_values_are_refused(system, name):
    pattern, data, b, _ = system
    asymmetric = data.copy()
    asymmetric[np.flatnonzero(pattern.rows < pattern.cols)[0]] *= 1.5
    _refused(name, pattern, asymmetric, b, "not symmetric")


@solver_names
def test_wrong_shapes_are_refused(system, name):
    pattern, data, b, _ = system
    solver = SOLVERS[name]
    with pytest.raises(ValueError, match=rf"data must have shape \({pattern.nnz},\)"):
        solver.factorize(pattern, data[:-1])
    factor = solver.factorize(pattern, data)
    with pytest.raises(ValueError, match=r"b must have shape \(60,\) or \(60, k\)"):
        solver.solve(pattern, factor, b[:-1])
    with pytest.raises(ValueError, match=r"b must have shape"):
        solver.solve(pattern, factor, b[:, :, None])
    with pytest.raises(ValueError, match=r"x0 must have shape \(60, 3\)"):
        solver.solve(pattern, factor, b, x0=b[:, :2])
    stranger = SOLVERS["PCG" if name != "PCG" else "DenseCholesky"]
    with pytest.raises(ValueError, match="was the factor made by"):
        solver.solve(pattern, stranger.factorize(pattern, data), b)
    with pytest.raises(TypeError, match="Factor"):
        solver.solve(pattern, (data, factor.aux), b)


def test_bad_solver_options_are_refused():
    with pytest.raises(ValueError, match="tol"):
        PCG(tol=0.0)
    with pytest.raises(ValueError, match="max_iter"):
        PCG(max_iter=0)
    with pytest.raises(ValueError, match="preconditioner"):
        PCG(preconditioner="ilu")
    with pytest.raises(ValueError, match="capacity"):
        linsolve.set_factor_cache_capacity(0)
    with pytest.raises(ValueError, match="positive"):
        auto_solver(0)


# --------------------------------------------------------------------------- interface


def test_solvers_are_static_and_factors_are_pytrees(system):
    pattern, data, _, _ = system
    assert hash(PCG()) == hash(PCG()) and PCG() == PCG() and PCG() != PCG(tol=1e-6)
    assert SparseCholesky() == SparseCholesky()
    factor = SparseCholesky().factorize(pattern, data)
    leaves = jax.tree_util.tree_leaves(factor)
    assert len(leaves) == 2 and leaves[1].dtype == jnp.int64
    assert isinstance(jax.tree_util.tree_map(lambda a: a, factor), Factor)


def test_auto_solver_picks_dense_for_small_and_sparse_for_large():
    assert isinstance(auto_solver(100), DenseCholesky)
    assert isinstance(auto_solver(linsolve.DENSE_MAX_N), DenseCholesky)
    assert isinstance(auto_solver(linsolve.DENSE_MAX_N + 1), SparseLDL)
    assert isinstance(auto_solver(linsolve.LDL_MAX_N), SparseLDL)
    assert isinstance(auto_solver(linsolve.LDL_MAX_N + 1), SparseCholesky)

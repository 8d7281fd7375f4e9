"""Linear solvers for the projective-dynamics global step.

The PD global step solves ``A X = B`` many times with one constant sparse symmetric
positive definite ``n x n`` matrix ``A`` (the scalar PD matrix ``M/h^2 + sum_i w_i G_i^T
G_i``) and ``B`` of shape ``(n, 3)``, one right-hand side per coordinate. ``A``'s values
depend on differentiable material parameters, so every solver here gives exact gradients
with respect to both the right-hand side and the matrix values by implicit
differentiation (:func:`jax.lax.custom_linear_solve`): the backward pass solves once more
with the same factorisation instead of differentiating through the solver's iterations
or callbacks.

Usage::

    pattern, index = SparsityPattern.from_coo(n, rows, cols)  # once, numpy
    data = jax.ops.segment_sum(values, index, pattern.nnz)    # differentiable values
    solver = auto_solver(pattern.n)
    factor = solver.factorize(pattern, data)                  # once per rollout
    x = solver.solve(pattern, factor, b)                      # many times, e.g. in lax.scan

The pattern and the solver are static: changing them recompiles. The :class:`Factor` is a
pytree of arrays: it may be carried through ``lax.scan``/``lax.while_loop``, returned from
``jax.jit`` and batched by ``jax.vmap`` (a batch of matrices).

=================  ====================  =====  ===  ===============================
solver             runs                  vmap   GPU  use it for
=================  ====================  =====  ===  ===============================
SparseLDL          native (XLA FFI)      yes**  no   CPU, n >~ 400 (the default there
                                                     when a C++ compiler is present)
SparseCholesky     host (cholespy)       yes*   no   CPU, n >~ 400 without a compiler
SparseLU           host (scipy splu)     yes*   no   CPU when cholespy is missing
DenseCholesky      JAX (LAPACK/cuSOLVER) yes    yes  n <~ 400; any size on a GPU that
                                                     holds the n x n matrix
PCG                JAX (lineax CG)       yes    yes  GPU, vmap over many matrices,
                                                     matrices that change every step
=================  ====================  =====  ===  ===============================

\\* Host solvers factorise each batch member separately and solve all members that share
a factorisation in one host call. \\** One member after another, natively.

Sharp bits:

- The matrix values ``data`` must be symmetric (the value at ``(i, j)`` equals the one at
  ``(j, i)``): the gradients assume it, and the Cholesky solvers read one triangle only.
  ``factorize`` checks it. Parametrise the values symmetrically (assemble them from
  symmetric element matrices) and the gradients reach your parameters exactly.
- The host solvers (:class:`SparseCholesky`, :class:`SparseLU`) keep their factorisations
  in a process-wide cache of the :func:`factor_cache_info` ``capacity`` most recent ones
  (16 by default, see :func:`set_factor_cache_capacity`); the :class:`Factor` holds a
  handle into it. A solve whose factorisation was evicted refactorises from the values
  carried in the :class:`Factor` (with a ``RuntimeWarning``) instead of failing.
- :class:`PCG` stops after ``max_iter`` iterations whether or not it reached ``tol`` and
  returns its last iterate without an error: check the residual of what you solved (the
  PD solver's force residual does) when you set ``max_iter`` low.
- ``x0`` (a warm start) is used by :class:`PCG` only; the direct solvers ignore it.
"""

from __future__ import annotations

import abc
import collections
import functools
import itertools
import threading
import warnings
import weakref
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import scipy.sparse
import scipy.sparse.linalg

try:
    import cholespy
except ImportError:  # pragma: no cover - cholespy is a declared dependency
    cholespy = None

__all__ = [
    "PCG",
    "DenseCholesky",
    "PerColumn",
    "Factor",
    "LinearSolver",
    "SparseCholesky",
    "SparseLDL",
    "SparseLU",
    "SparsityPattern",
    "auto_solver",
    "clear_factor_cache",
    "factor_cache_info",
    "set_factor_cache_capacity",
]

#: Largest ``n`` for which :func:`auto_solver` picks :class:`DenseCholesky`. Measured on a
#: 2-core CPU (``softbody bench solvers``, 3 right-hand sides): per solve, dense 0.04 ms vs
#: cholespy 0.08 ms at n = 256, 0.14 vs 0.09 ms at n = 500, 4.5 vs 0.22 ms at n = 2048.
DENSE_MAX_N = 400
#: Largest ``n`` for which :func:`auto_solver` picks :class:`SparseLDL` (see there).
LDL_MAX_N = 10_000


# --------------------------------------------------------------------------- pattern


@dataclass(frozen=True, eq=False)
class SparsityPattern:
    """The fixed sparsity pattern of a symmetric ``n x n`` matrix (static, numpy).

    Holds both triangles and the full diagonal in CSR order (sorted by row, then column,
    no duplicates). Matrix values live separately in a ``data`` array of shape ``(nnz,)``
    aligned with ``rows``/``cols``, so they may be traced and differentiated while the
    pattern stays a compile-time constant. Compared and hashed by identity.

    Build one with :meth:`from_coo` from assembled (unsorted, repeated) COO indices.

    Arguments:
        n: the matrix size.
        rows: ``(nnz,)`` row index of each stored entry.
        cols: ``(nnz,)`` column index of each stored entry.

    Raises:
        ValueError: if an index lies outside ``[0, n)``, the entries are not in sorted CSR
            order without duplicates, the pattern is not symmetric (both ``(i, j)`` and
            ``(j, i)`` stored), or a diagonal entry is missing.
    """

    n: int
    rows: np.ndarray
    cols: np.ndarray

    def __post_init__(self):
        n = int(self.n)
        rows = np.asarray(self.rows)
        cols = np.asarray(self.cols)
        if n < 1:
            raise ValueError(f"SparsityPattern: n must be positive, got {self.n}")
        if rows.ndim != 1 or cols.ndim != 1 or rows.shape != cols.shape:
            raise ValueError(
                "SparsityPattern: rows and cols must be 1-D arrays of equal length, got "
                f"shapes {rows.shape} and {cols.shape}"
            )
        if not (np.issubdtype(rows.dtype, np.integer) and np.issubdtype(cols.dtype, np.integer)):
            raise ValueError(
                f"SparsityPattern: rows and cols must be integer arrays, got {rows.dtype} "
                f"and {cols.dtype}"
            )
        _check_index_range(n, rows, cols)
        key = rows.astype(np.int64) * n + cols
        if np.any(np.diff(key) <= 0):
            raise ValueError(
                "SparsityPattern: entries must be sorted by row then column without "
                "duplicates; build the pattern with SparsityPattern.from_coo"
            )
        if not np.array_equal(np.sort(cols.astype(np.int64) * n + rows), key):
            raise ValueError(
                "SparsityPattern: the pattern is not symmetric; store both triangles "
                "(every (i, j) needs its (j, i))"
            )
        has_diagonal = np.zeros(n, bool)
        has_diagonal[rows[rows == cols]] = True
        if not has_diagonal.all():
            missing = np.flatnonzero(~has_diagonal)
            raise ValueError(
                f"SparsityPattern: {missing.size} diagonal entries are missing (first: row "
                f"{missing[0]}); an SPD matrix has a positive diagonal, so store it"
            )
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "rows", np.ascontiguousarray(rows, dtype=np.int32))
        object.__setattr__(self, "cols", np.ascontiguousarray(cols, dtype=np.int32))

    @staticmethod
    def from_coo(n: int, rows, cols) -> tuple[SparsityPattern, np.ndarray]:
        """Pattern of an assembled COO matrix (entries in any order, repeated or not).

        Arguments:
            n: the matrix size.
            rows: ``(m,)`` integer row indices, e.g. from scattering element matrices.
            cols: ``(m,)`` integer column indices.

        Returns:
            ``(pattern, index)`` where ``index`` is ``(m,)`` int32: entry ``k`` of the COO
            input lands in ``data[index[k]]``, so
            ``data = jax.ops.segment_sum(values, index, pattern.nnz)`` assembles the values.

        Raises:
            ValueError: as :class:`SparsityPattern` (indices out of range, a non-symmetric
                pattern or a missing diagonal entry), or if rows and cols differ in shape.
        """
        n = int(n)
        rows = np.asarray(rows)
        cols = np.asarray(cols)
        if rows.ndim != 1 or rows.shape != cols.shape:
            raise ValueError(
                "SparsityPattern.from_coo: rows and cols must be 1-D arrays of equal length, "
                f"got shapes {rows.shape} and {cols.shape}"
            )
        _check_index_range(n, rows, cols)
        unique, index = np.unique(rows.astype(np.int64) * n + cols, return_inverse=True)
        pattern = SparsityPattern(n, unique // n, unique % n)
        return pattern, index.astype(np.int32)

    @property
    def nnz(self) -> int:
        """Number of stored entries (both triangles)."""
        return int(self.rows.size)

    @functools.cached_property
    def indptr(self) -> np.ndarray:
        """``(n + 1,)`` int32 CSR row pointers: row ``i`` is ``cols[indptr[i]:indptr[i+1]]``."""
        counts = np.bincount(self.rows, minlength=self.n)
        return np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)

    @functools.cached_property
    def diagonal_index(self) -> np.ndarray:
        """``(n,)`` int32 position of each diagonal entry ``(i, i)`` in ``data``."""
        return np.flatnonzero(self.rows == self.cols).astype(np.int32)

    @functools.cached_property
    def transpose_index(self) -> np.ndarray:
        """``(nnz,)`` int32 position of entry ``(j, i)`` for each entry ``(i, j)``."""
        return np.argsort(self.cols.astype(np.int64) * self.n + self.rows).astype(np.int32)

    @functools.cached_property
    def _padded_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Row-padded (ELL) layout for a scatter-free matvec.

        Returns ``(cols, slots)``, both ``(n, w)`` int32 with ``w`` the largest row length:
        ``slots`` indexes ``data`` with ``nnz`` (a zero value) as padding; padded columns
        point at the row itself.
        """
        counts = np.diff(self.indptr)
        position = np.arange(counts.max())[None, :]
        valid = position < counts[:, None]
        slots = np.where(valid, self.indptr[:-1, None] + position, self.nnz)
        cols = np.where(valid, np.append(self.cols, 0)[slots], np.arange(self.n)[:, None])
        return cols.astype(np.int32), slots.astype(np.int32)

    def to_scipy(self, data) -> scipy.sparse.csr_matrix:
        """The matrix as a scipy CSR matrix.

        Arguments:
            data: ``(nnz,)`` values (numpy or a concrete JAX array).

        Returns:
            ``(n, n)`` ``scipy.sparse.csr_matrix``.

        Raises:
            ValueError: if ``data`` does not have shape ``(nnz,)``.
        """
        data = np.asarray(data)
        _check_shape("SparsityPattern.to_scipy", "data", data.shape, (self.nnz,))
        return scipy.sparse.csr_matrix((data, self.cols, self.indptr), shape=(self.n, self.n))

    def to_dense(self, data) -> jax.Array:
        """The matrix as a dense JAX array (differentiable in ``data``).

        Arguments:
            data: ``(nnz,)`` values.

        Returns:
            ``(n, n)`` array.

        Raises:
            ValueError: if ``data`` does not have shape ``(nnz,)``.
        """
        data = jnp.asarray(data)
        _check_shape("SparsityPattern.to_dense", "data", data.shape, (self.nnz,))
        return (
            jnp.zeros((self.n, self.n), data.dtype)
            .at[self.rows, self.cols]
            .set(data, indices_are_sorted=True, unique_indices=True)
        )

    def matvec(self, data, x) -> jax.Array:
        """``A @ x``, differentiable in both ``data`` and ``x``.

        Gathers each row's entries into a row-padded layout (no scatter), which is about
        twice as fast as a ``segment_sum`` on CPU.

        Arguments:
            data: ``(nnz,)`` matrix values.
            x: ``(n,)`` or ``(n, k)``.

        Returns:
            Array of ``x``'s shape.

        Raises:
            ValueError: if ``data`` or ``x`` has the wrong shape.
        """
        data = jnp.asarray(data)
        x = jnp.asarray(x)
        _check_shape("SparsityPattern.matvec", "data", data.shape, (self.nnz,))
        if x.ndim not in (1, 2) or x.shape[0] != self.n:
            raise ValueError(
                f"SparsityPattern.matvec: x must have shape ({self.n},) or ({self.n}, k), "
                f"got {x.shape}"
            )
        cols, slots = self._padded_rows
        padded = jnp.append(data, jnp.zeros((), data.dtype))
        values = padded.at[slots].get(mode="promise_in_bounds")
        neighbours = x.at[cols].get(mode="promise_in_bounds")
        return jnp.einsum("rw,rw...->r...", values, neighbours)


def _check_index_range(n: int, rows: np.ndarray, cols: np.ndarray) -> None:
    for name, index in (("rows", rows), ("cols", cols)):
        if index.size and (index.min() < 0 or index.max() >= n):
            raise ValueError(
                f"SparsityPattern: {name} indices must lie in [0, {n}) for an {n} x {n} "
                f"matrix, got the range [{index.min()}, {index.max()}] (is the matrix "
                "square, and n its size?)"
            )


def _check_shape(where: str, name: str, shape: tuple, expected: tuple) -> None:
    if tuple(shape) != tuple(expected):
        raise ValueError(f"{where}: {name} must have shape {expected}, got {tuple(shape)}")


# --------------------------------------------------------------------------- interface


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class Factor:
    """A factorised matrix: the pytree that :meth:`LinearSolver.factorize` returns.

    Attributes:
        data: ``(nnz,)`` the matrix values (differentiable; the solves' implicit gradients
            flow back to them).
        aux: what the solver precomputed, outside the gradient: an ``()`` int64 handle into
            the host factor cache (:class:`SparseCholesky`, :class:`SparseLU`), the
            ``(nnz_L + n,)`` values of ``L`` and ``D^-1`` with the ``(nnz_L,)`` int32 row
            indices of ``L`` (:class:`SparseLDL`, a pair), the ``(n, n)`` lower Cholesky
            factor (:class:`DenseCholesky`) or the ``(n,)`` inverse diagonal (:class:`PCG`).

    Under ``vmap`` every field gains the batch axis.
    """

    data: jax.Array
    aux: jax.Array | tuple[jax.Array, ...]


class LinearSolver(abc.ABC):
    """A strategy for solving ``A x = b`` with a constant SPD matrix on a fixed pattern.

    Subclasses are small frozen dataclasses (hashable, so they can be static arguments).
    Both methods work under ``jax.jit``, ``jax.grad`` and ``jax.vmap``; ``solve`` gives exact
    gradients with respect to ``b`` and to ``factor.data`` by implicit differentiation.
    """

    @property
    def host_callback(self) -> bool:
        """Whether programs that use this solver hold a host callback: JAX does not keep
        them in its persistent compilation cache, so they compile again in every process."""
        return False

    @abc.abstractmethod
    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        """Prepare repeated solves with one matrix (once per rollout, outside ``lax.scan``).

        Arguments:
            pattern: the matrix's sparsity pattern.
            data: ``(nnz,)`` matrix values, symmetric, may be traced.

        Returns:
            A :class:`Factor`.

        Raises:
            ValueError: if ``data`` has the wrong shape, or (at run time, with the
                solver's name in the message) if the values are not symmetric or the
                matrix is not positive definite where the solver can tell.
        """

    @abc.abstractmethod
    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        """Solve ``A x = b`` with a factorised matrix.

        Arguments:
            pattern: the pattern the factor was made with.
            factor: from :meth:`factorize`.
            b: ``(n,)`` or ``(n, k)`` right-hand side(s).
            x0: optional initial guess of ``b``'s shape (used by iterative solvers).

        Returns:
            ``x`` of ``b``'s shape.

        Raises:
            ValueError: if ``b``, ``x0`` or ``factor`` do not fit the pattern.
        """


def _check_data(solver: LinearSolver, pattern: SparsityPattern, data) -> jax.Array:
    if not isinstance(pattern, SparsityPattern):
        raise TypeError(
            f"{type(solver).__name__}.factorize: pattern must be a SparsityPattern, got "
            f"{type(pattern).__name__}"
        )
    data = jnp.asarray(data)
    _check_shape(f"{type(solver).__name__}.factorize", "data", data.shape, (pattern.nnz,))
    if not jnp.issubdtype(data.dtype, jnp.floating):
        data = data.astype(float)
    return data


def _check_solve_args(solver, pattern, factor, aux_shape, b, x0):
    """Validate the arguments of ``solve``; returns ``(b, x0)`` as floating arrays."""
    where = f"{type(solver).__name__}.solve"
    if not isinstance(factor, Factor):
        raise TypeError(f"{where}: factor must be a Factor from factorize, got {type(factor)}")
    _check_shape(where, "factor.data", jnp.shape(factor.data), (pattern.nnz,))
    shape = jax.tree.map(jnp.shape, factor.aux)
    if shape != aux_shape:
        raise ValueError(
            f"{where}: factor.aux has shape {shape}, expected {aux_shape}: "
            f"was the factor made by {type(solver).__name__}.factorize with this pattern?"
        )
    b = jnp.asarray(b)
    if b.ndim not in (1, 2) or b.shape[0] != pattern.n:
        raise ValueError(
            f"{where}: b must have shape ({pattern.n},) or ({pattern.n}, k), got {b.shape}"
        )
    if not jnp.issubdtype(b.dtype, jnp.floating):
        b = b.astype(float)
    if x0 is not None:
        x0 = jnp.asarray(x0, b.dtype)
        _check_shape(where, "x0", x0.shape, b.shape)
    return b, x0


def _implicit_solve(pattern, data, b, solve, transpose_solve):
    """``custom_linear_solve`` with the pattern's matvec: exact d/db and d/d data."""
    return jax.lax.custom_linear_solve(
        functools.partial(pattern.matvec, data),
        b,
        solve=solve,
        transpose_solve=transpose_solve,
        symmetric=True,
    )


def _asymmetry(pattern: SparsityPattern, data, xp=jnp):
    """Whether ``data`` is asymmetric beyond rounding (``sqrt(eps)`` of its largest value).

    ``xp`` is ``jnp`` (traced values) or ``np`` (on the host, inside a callback).
    """
    scale = xp.max(xp.abs(data))
    gap = xp.max(xp.abs(data - data[pattern.transpose_index]))
    return gap > xp.sqrt(xp.finfo(data.dtype).eps) * scale


_ASYMMETRIC = (
    "the matrix values are not symmetric (A[i, j] != A[j, i]); assemble them from "
    "symmetric element matrices"
)


# --------------------------------------------------------------------------- dense


@dataclass(frozen=True)
class DenseCholesky(LinearSolver):
    """Dense Cholesky factorisation in JAX (``jax.scipy.linalg.cho_factor``).

    Builds the ``n x n`` matrix, so memory is ``8 n^2`` bytes and factorisation
    ``n^3 / 3`` flops: the fastest choice on CPU below ``n ~ 400``, and on a GPU as long
    as the matrix fits. Works under ``vmap`` and on any backend.

    A matrix that is not symmetric positive definite, holds NaN/inf or has values that
    are not symmetric gives a factor of NaN, so every solve with it is NaN (``rollout``
    reports such a step as non-finite). The check is arithmetic, not a run-time error: a
    host callback would keep every program that factorises out of JAX's persistent
    compilation cache.
    """

    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        data = _check_data(self, pattern, data)
        values = jax.lax.stop_gradient(data)
        chol, _ = jax.scipy.linalg.cho_factor(pattern.to_dense(values), lower=True)
        bad = _asymmetry(pattern, values) | ~jnp.all(jnp.isfinite(jnp.diagonal(chol)))
        return Factor(data, jnp.where(bad, jnp.nan, chol))

    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        b, _ = _check_solve_args(self, pattern, factor, (pattern.n, pattern.n), b, x0)
        chol = jax.lax.stop_gradient(factor.aux)

        def solve(matvec, rhs):
            # Two triangular solves; jax.scipy.linalg.cho_solve also conjugates the factor,
            # an n x n copy per solve that made it 2x slower at n = 2k.
            columns = rhs.reshape(pattern.n, -1)
            y = jax.lax.linalg.triangular_solve(chol, columns, left_side=True, lower=True)
            x = jax.lax.linalg.triangular_solve(
                chol, y, left_side=True, lower=True, transpose_a=True
            )
            return x.reshape(rhs.shape)

        return _implicit_solve(pattern, factor.data, b, solve, solve)


# --------------------------------------------------------------------------- PCG


@dataclass(frozen=True)
class PCG(LinearSolver):
    """Preconditioned conjugate gradients in JAX on the sparse matvec.

    Solves all columns of ``b`` at once (each column has its own step sizes and stops
    changing once converged), warm-started from ``x0``. A fixed-shape
    ``lax.while_loop``: runs under ``vmap`` (a batch runs until its slowest member has
    converged) and on GPU. Each iteration costs one sparse matvec.

    Arguments:
        tol: stop when every column's residual satisfies ``|b - A x| <= tol |b|``.
        max_iter: iteration cap; ``None`` means ``n``. Reaching it is not an error: the
            last iterate is returned, and the caller's residual check must catch it.
        preconditioner: ``"jacobi"`` (divide by the diagonal) or ``"none"``.

    A matrix with a diagonal entry that is not positive (it cannot be SPD), NaN/inf on
    its diagonal or values that are not symmetric gives a factor whose solves are NaN
    (as :class:`DenseCholesky`, without a run-time callback).

    Raises:
        ValueError: for a non-positive ``tol`` or ``max_iter`` or an unknown
            preconditioner.
    """

    tol: float = 1e-10
    max_iter: int | None = None
    preconditioner: str = "jacobi"

    def __post_init__(self):
        if not self.tol > 0:
            raise ValueError(f"PCG: tol must be positive, got {self.tol}")
        if self.max_iter is not None and not (
            isinstance(self.max_iter, int | np.integer) and self.max_iter > 0
        ):
            raise ValueError(f"PCG: max_iter must be a positive int or None, got {self.max_iter}")
        if self.preconditioner not in ("jacobi", "none"):
            raise ValueError(
                f"PCG: unknown preconditioner {self.preconditioner!r}; use 'jacobi' or 'none'"
            )

    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        data = _check_data(self, pattern, data)
        diagonal = jax.lax.stop_gradient(data)[pattern.diagonal_index]
        bad = _asymmetry(pattern, jax.lax.stop_gradient(data)) | ~jnp.all(diagonal > 0)
        diagonal = jnp.where(bad, jnp.nan, diagonal)
        if self.preconditioner == "jacobi":
            return Factor(data, 1.0 / diagonal)
        return Factor(data, diagonal / diagonal)  # ones, or NaN for a refused matrix

    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        b, x0 = _check_solve_args(self, pattern, factor, (pattern.n,), b, x0)
        inverse_diagonal = jax.lax.stop_gradient(factor.aux)
        max_iter = pattern.n if self.max_iter is None else int(self.max_iter)
        cg = functools.partial(
            _pcg, inverse_diagonal=inverse_diagonal, tol=self.tol, max_iter=max_iter
        )

        def solve(matvec, rhs):
            start = jnp.zeros_like(rhs) if x0 is None else jax.lax.stop_gradient(x0)
            return cg(matvec, rhs, start)

        def transpose_solve(matvec, rhs):  # the adjoint's right-hand side is unrelated to x0
            return cg(matvec, rhs, jnp.zeros_like(rhs))

        return _implicit_solve(pattern, factor.data, b, solve, transpose_solve)


def _pcg(matvec, b, x0, *, inverse_diagonal, tol, max_iter):
    """Column-wise Jacobi-preconditioned CG for ``b`` of shape ``(n,)`` or ``(n, k)``: each
    column is its own :func:`conjugate_gradients` solve (``vmap``)."""

    def column(b, x0):
        return conjugate_gradients(matvec, lambda r: inverse_diagonal * r, b, x0, tol=tol, max_iter=max_iter)

    x = column(b, x0) if b.ndim == 1 else jax.vmap(column, in_axes=1, out_axes=1)(b, x0)
    # A refused matrix (NaN diagonal, see PCG) stops CG at once; its solves are NaN.
    return jnp.where(jnp.all(jnp.isfinite(inverse_diagonal)), x, jnp.nan)


def _two_norm(tree) -> jax.Array:
    """The Euclidean norm of a pytree of arrays."""
    return jnp.sqrt(sum(jnp.sum(leaf * leaf) for leaf in jax.tree.leaves(tree)))


def conjugate_gradients(matvec, precondition, b, x0, *, tol, max_iter: int):
    """Solve ``A x = b`` for a symmetric positive definite ``A`` by lineax's preconditioned
    conjugate gradients: the one CG of softbody (the PD matrix's :class:`PCG` and the
    implicit adjoints' Hessian solves).

    Arguments:
        matvec: ``x -> A x``, linear, on arrays shaped like ``b``.
        precondition: ``r -> P^-1 r``, symmetric positive definite, likewise.
        b: the right-hand side (an array of any shape, taken as one vector).
        x0: the start, shaped like ``b``.
        tol: stop when ``|b - A x| <= tol |b|`` (two-norm; lineax also asks the last update
            to be that small, in the same norm).
        max_iter: iteration cap; reaching it is not an error (the last iterate is returned).

    Returns:
        ``x``, shaped like ``b``.
    """
    structure = jax.eval_shape(lambda: b)
    spd = (lx.symmetric_tag, lx.positive_semidefinite_tag)
    solver = lx.CG(rtol=0.0, atol=tol * _two_norm(b), norm=_two_norm, stabilise_every=None, max_steps=max_iter)
    options = {"preconditioner": lx.FunctionLinearOperator(precondition, structure, tags=spd), "y0": x0}
    operator = lx.FunctionLinearOperator(matvec, structure, tags=spd)
    return lx.linear_solve(operator, b, solver, options=options, throw=False).value


# --------------------------------------------------------------------------- host solvers


class _FactorCache:
    """Process-wide LRU store of host factorisations, keyed by integer handles."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._entries: collections.OrderedDict[int, Callable] = collections.OrderedDict()
        self._handles = itertools.count(1)
        self._lock = threading.Lock()
        self.factorizations = 0
        self.refactorizations = 0

    def add(self, solve: Callable) -> int:
        with self._lock:
            handle = next(self._handles)
            self.factorizations += 1
            self._store(handle, solve)
        return handle

    def restore(self, handle: int, solve: Callable) -> None:
        with self._lock:
            self.refactorizations += 1
            self._store(handle, solve)

    def get(self, handle: int) -> Callable | None:
        with self._lock:
            solve = self._entries.get(handle)
            if solve is not None:
                self._entries.move_to_end(handle)
            return solve

    def resize(self, capacity: int) -> None:
        with self._lock:
            self.capacity = capacity
            self._evict()

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def info(self) -> dict:
        with self._lock:
            return {
                "size": len(self._entries),
                "capacity": self.capacity,
                "factorizations": self.factorizations,
                "refactorizations": self.refactorizations,
            }

    def _store(self, handle: int, solve: Callable) -> None:
        self._entries[handle] = solve
        self._entries.move_to_end(handle)
        self._evict()

    def _evict(self) -> None:
        while len(self._entries) > self.capacity:
            self._entries.popitem(last=False)


_CACHE = _FactorCache(capacity=16)


def factor_cache_info() -> dict:
    """State of the host factor cache used by :class:`SparseCholesky` and :class:`SparseLU`.

    Returns:
        ``{"size", "capacity", "factorizations", "refactorizations"}``: factorisations
        held now, the most it holds, factorisations made so far, and refactorisations of
        evicted factorisations so far (process totals).
    """
    return _CACHE.info()


def set_factor_cache_capacity(capacity: int) -> None:
    """Keep at most ``capacity`` host factorisations (evicting the least recently used).

    Raise it above the batch size when vmapping a host solver over many matrices, or
    each solve refactorises. Each factorisation holds its Cholesky/LU factor in memory.

    Raises:
        ValueError: if ``capacity`` is not a positive int.
    """
    if not (isinstance(capacity, int | np.integer) and capacity > 0):
        raise ValueError(f"factor cache capacity must be a positive int, got {capacity!r}")
    _CACHE.resize(int(capacity))


def clear_factor_cache() -> None:
    """Free every host factorisation (their :class:`Factor` s still work, by refactorising)."""
    _CACHE.clear()


class _HostSolver(LinearSolver):
    """A direct solver run on the host through ``jax.pure_callback``.

    ``factorize`` makes one callback that factorises and stores the result in the
    factor cache, returning its handle; ``solve`` makes one callback with the handle and
    the right-hand sides (the matrix is not sent again). The handle is an input of the
    solve, so the solve cannot run before its factorisation. If the handle was evicted, a
    second callback, which does receive the values, refactorises.
    """

    @property
    def host_callback(self) -> bool:
        return True

    @abc.abstractmethod
    def _factor_on_host(self, pattern: SparsityPattern, data: np.ndarray) -> Callable:
        """Factorise; returns ``solve(b)`` for C-contiguous float64 ``b`` of shape ``(n, m)``."""

    def _host_factorize(self, pattern: SparsityPattern, data: np.ndarray) -> Callable:
        name = type(self).__name__
        data = np.array(data, np.float64)  # a writable copy: the callback's input is read-only
        if not np.all(np.isfinite(data)):
            raise ValueError(f"{name}: the matrix values contain NaN or inf")
        if _asymmetry(pattern, data, np):
            raise ValueError(f"{name}: {_ASYMMETRIC}")
        solve = self._factor_on_host(pattern, data)
        lock = threading.Lock()  # XLA may run independent callbacks on several threads

        def locked_solve(b):
            with lock:
                return solve(b)

        return locked_solve

    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        data = _check_data(self, pattern, data)
        handle = jax.pure_callback(
            functools.partial(_factorize_callback, self, pattern),
            jax.ShapeDtypeStruct((), np.int64),
            jax.lax.stop_gradient(data),
            vmap_method="sequential",
        )
        return Factor(data, handle)

    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        b, _ = _check_solve_args(self, pattern, factor, (), b, x0)
        handle = factor.aux
        values = jax.lax.stop_gradient(factor.data)

        def solve(matvec, rhs):
            shapes = (jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), jax.ShapeDtypeStruct((), bool))
            x, found = self._solve_cached(handle, rhs, shapes)
            return jax.lax.cond(
                found,
                lambda: x,
                lambda: jax.pure_callback(
                    functools.partial(_refactorize_callback, self, pattern),
                    shapes[0],
                    handle,
                    values,
                    rhs,
                    found,
                    vmap_method="expand_dims",
                ),
            )

        return _implicit_solve(pattern, factor.data, b, solve, solve)

    def _solve_cached(self, handle, rhs, shapes):
        """``(x, found)``: solve with the cached factorisation ``handle``; ``found`` is
        false (and ``x`` meaningless) when it was evicted."""
        return jax.pure_callback(_solve_callback, shapes, handle, rhs, vmap_method="expand_dims")


def _factorize_callback(solver: _HostSolver, pattern: SparsityPattern, data) -> np.ndarray:
    return np.int64(_CACHE.add(solver._host_factorize(pattern, data)))


def _batched(handle, *arrays):
    """Broadcast callback arguments to a common batch shape (``vmap_method="expand_dims"``).

    ``handle`` has only batch axes; the others have the same number of leading batch axes
    followed by their own core axes. Returns the batch shape, the flat handles and each
    array reshaped to ``(members, *core)``.
    """
    handle = np.asarray(handle)
    arrays = [np.asarray(a) for a in arrays]
    depth = handle.ndim
    batch = np.broadcast_shapes(handle.shape, *(a.shape[:depth] for a in arrays))
    flat = [
        np.broadcast_to(a, batch + a.shape[depth:]).reshape((-1,) + a.shape[depth:]) for a in arrays
    ]
    return batch, np.broadcast_to(handle, batch).reshape(-1), flat


def _solve_columns(solve: Callable, rhs: np.ndarray) -> np.ndarray:
    """Solve ``(m, n, ...)`` right-hand sides sharing one factorisation in one call."""
    m, n = rhs.shape[:2]
    columns = np.require(np.moveaxis(rhs, 0, 1).reshape(n, -1), np.float64, ["C", "W"])
    x = solve(columns).reshape((n, m) + rhs.shape[2:])
    return np.moveaxis(x, 1, 0)


def _solve_callback(handle, b):
    b = np.asarray(b)
    if np.ndim(handle) == 0:  # not under vmap: one factorisation, one call
        solve = _CACHE.get(int(handle))
        if solve is None:
            return np.zeros_like(b), np.False_
        rhs = np.require(np.reshape(b, (b.shape[0], -1)), np.float64, ["C", "W"])
        return solve(rhs).reshape(b.shape).astype(b.dtype, copy=False), np.True_
    batch, handles, (rhs,) = _batched(handle, b)
    x = np.zeros(rhs.shape, rhs.dtype)
    found = np.zeros(handles.size, bool)
    for h in np.unique(handles):
        solve = _CACHE.get(int(h))
        if solve is not None:
            members = np.flatnonzero(handles == h)
            x[members] = _solve_columns(solve, rhs[members])
            found[members] = True
    return x.reshape(batch + rhs.shape[1:]), found.reshape(batch)


def _refactorize_callback(solver: _HostSolver, pattern: SparsityPattern, handle, data, b, found):
    batch, handles, (values, rhs, found) = _batched(handle, data, b, found)
    x = np.zeros(rhs.shape, rhs.dtype)
    for h in np.unique(handles[~found]):
        members = np.flatnonzero((handles == h) & ~found)
        solve = _CACHE.get(int(h))
        if solve is None:
            warnings.warn(
                f"{type(solver).__name__}: factorisation {int(h)} was evicted from the factor "
                f"cache (capacity {_CACHE.capacity}); refactorising. Raise the capacity with "
                "softbody.linsolve.set_factor_cache_capacity to avoid this.",
                RuntimeWarning,
                stacklevel=1,
            )
            solve = solver._host_factorize(pattern, values[members[0]])
            _CACHE.restore(int(h), solve)
        x[members] = _solve_columns(solve, rhs[members])
    return x.reshape(batch + rhs.shape[1:])


@dataclass(frozen=True)
class SparseCholesky(_HostSolver):
    """Prefactored sparse Cholesky on the host (cholespy, i.e. CHOLMOD), float64.

    The fastest solver on CPU from ``n ~ 400`` up. ``factorize`` costs seconds at
    ``n = 30k``; each solve is two sparse triangular solves plus a host callback
    (about 0.05-0.15 ms). Under ``vmap`` each batch member is factorised separately
    (keep the batch within :func:`set_factor_cache_capacity`), and members sharing one
    factorisation are solved together. CPU only in effect: on a GPU each solve copies
    ``b`` to the host and back.

    Raises:
        ImportError: when cholespy is not installed (use :class:`SparseLU`).
        ValueError: at run time, from ``factorize``, if the matrix is not positive definite,
            holds NaN/inf, or its values are not symmetric.
    """

    def __post_init__(self):
        if cholespy is None:
            raise ImportError(
                "SparseCholesky needs cholespy (pip install cholespy); or use SparseLU"
            )

    def _factor_on_host(self, pattern: SparsityPattern, data: np.ndarray) -> Callable:
        try:
            chol = cholespy.CholeskySolverD(
                pattern.n, pattern.indptr, pattern.cols, data, cholespy.MatrixType.CSR
            )
        except ValueError as error:
            raise ValueError(
                f"SparseCholesky: the matrix is not positive definite ({error}); check the "
                "material parameters and the time step, and that fixed vertices were "
                "eliminated"
            ) from error

        def solve(b):
            x = np.empty_like(b)
            chol.solve(b, x)
            return x

        return solve


@dataclass(frozen=True)
class SparseLU(_HostSolver):
    """Prefactored sparse LU on the host (scipy's SuperLU ``splu``), float64.

    The fallback when cholespy is unavailable: same interface and caching as
    :class:`SparseCholesky`, using SuperLU's symmetric mode (minimum degree on
    ``A + A^T``, diagonal pivots). It does not check positive definiteness.

    Raises:
        ValueError: at run time, from ``factorize``, if the matrix is singular, holds
            NaN/inf, or its values are not symmetric.
    """

    def _factor_on_host(self, pattern: SparsityPattern, data: np.ndarray) -> Callable:
        try:
            lu = scipy.sparse.linalg.splu(
                pattern.to_scipy(data).tocsc(),
                permc_spec="MMD_AT_PLUS_A",
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )
        except RuntimeError as error:
            raise ValueError(f"SparseLU: the matrix is singular ({error})") from error
        return lu.solve


@dataclass(frozen=True, eq=False)
class _LdlAnalysis:
    """The symbolic analysis of :class:`SparseLDL` for one pattern (int32 numpy arrays).

    ``perm[new] = old`` and ``pinv[old] = new`` is the fill-reducing permutation,
    ``parent`` the elimination tree of ``P A P^T`` and ``colptr`` (``n + 1``) the column
    pointers of its strictly lower factor ``L``, which has ``nnz_l`` entries.
    """

    perm: np.ndarray
    pinv: np.ndarray
    parent: np.ndarray
    colptr: np.ndarray
    nnz_l: int


_ANALYSES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_ANALYSES_LOCK = threading.Lock()


def _ldl_analysis(pattern: SparsityPattern) -> _LdlAnalysis:
    """The (cached) symbolic analysis of ``pattern`` for :class:`SparseLDL`.

    The ordering is SuperLU's minimum degree on ``A + A^T`` (``MMD_AT_PLUS_A``, with its
    elimination-tree postorder), taken from a factorisation of a diagonally dominant
    stand-in matrix on the pattern: it depends on the pattern only.
    """
    from softbody import native

    with _ANALYSES_LOCK:
        analysis = _ANALYSES.get(pattern)
    if analysis is not None:
        return analysis
    n = pattern.n
    off_diagonal = np.diff(pattern.indptr) - 1
    stand_in = np.where(pattern.rows == pattern.cols, off_diagonal[pattern.rows] + 1.0, -1.0)
    lu = scipy.sparse.linalg.splu(
        pattern.to_scipy(stand_in).tocsc(),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    pinv = np.ascontiguousarray(lu.perm_c, np.int32)
    perm = np.ascontiguousarray(np.argsort(pinv), np.int32)
    colptr = np.empty(n + 1, np.int64)
    parent = np.empty(n, np.int32)
    nnz_l = int(native.library().softbody_ldl_symbolic(n, pattern.indptr, pattern.cols, perm, pinv, colptr, parent))
    if nnz_l + n >= 2**31:
        raise ValueError(f"SparseLDL: the factor would hold {nnz_l} entries, more than its 32-bit indices "
                         "address; use SparseCholesky")
    analysis = _LdlAnalysis(perm, pinv, parent, colptr.astype(np.int32), nnz_l)
    with _ANALYSES_LOCK:
        _ANALYSES[pattern] = analysis
    return analysis


#: What to check when :class:`SparseLDL` refuses a matrix.
_LDL_ADVICE = ("check the material parameters and the time step, and that fixed vertices were "
               "eliminated")


@dataclass(frozen=True)
class SparseLDL(LinearSolver):
    """Sparse ``LDL^T`` factorised and solved natively inside XLA, without a host callback (float64).

    The symbolic analysis runs once per sparsity pattern on the host, when the first
    program using the pattern is traced: a fill-reducing ordering (SuperLU's minimum degree
    on ``A + A^T``, as :class:`SparseLU` uses), the elimination tree and the column counts
    of ``L``. The numeric factorisation ``P A P^T = L D L^T`` (up-looking, one row of ``L``
    at a time, as in T. Davis's LDL) and the triangular solves are compiled C++ registered
    as XLA FFI targets (:mod:`softbody.native`): the factor's values and row indices are
    ordinary arrays of the :class:`Factor` (``aux``), each solve inside a compiled loop costs
    what the arithmetic costs, and programs that factorise or solve hold no Python callback,
    so JAX's persistent compilation cache keeps them. On the shared DiffPD cantilever
    (n = 2673) the native solves made a 25-frame rollout 1.4-1.5x faster than
    :class:`SparseCholesky`, whose every solve is a Python callback. A jitted
    factorisation of a 546-vertex PD matrix takes 0.8 ms (7.8 ms when it was SuperLU
    behind a host callback; at n = 2673, 26 ms for both), each solve 0.07 ms as before
    (one core of a loaded 2-core machine). Under ``vmap`` batch members are factorised and
    solved one by one.

    Raises:
        ImportError: when the native library cannot be built (no C++ compiler): use
            :class:`SparseCholesky`.
        ValueError: from ``factorize`` or ``solve``, when tracing, for a pattern whose
            factor needs more than 2^31 entries.
        jax.errors.JaxRuntimeError: at run time, from the compiled program that
            factorises (``ValueError`` when ``factorize`` runs eagerly), if the matrix is not
            positive definite, holds NaN/inf, or its values are not symmetric; the message
            starts ``SparseLDL:`` and names the problem and the fix.
    """

    def __post_init__(self):
        from softbody import native

        if native.library() is None:
            raise ImportError(f"SparseLDL needs the native library, which is unavailable: "
                              f"{native.unavailable_reason()}; use SparseCholesky")

    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        from softbody import native

        data = _check_data(self, pattern, data)
        analysis = _ldl_analysis(pattern)
        values = jax.lax.stop_gradient(data).astype(jnp.float64)
        shapes = (jax.ShapeDtypeStruct((analysis.nnz_l + pattern.n,), jnp.float64),
                  jax.ShapeDtypeStruct((analysis.nnz_l,), jnp.int32))
        factor = jax.ffi.ffi_call(native.FACTOR_TARGET, shapes, vmap_method="sequential")(
            values, pattern.indptr, pattern.cols, analysis.colptr, analysis.parent, analysis.perm,
            analysis.pinv, _asymmetry(pattern, values),
            asymmetric=f"SparseLDL: {_ASYMMETRIC}", advice=_LDL_ADVICE)
        return Factor(data, tuple(factor))

    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        from softbody import native

        analysis = _ldl_analysis(pattern)
        aux_shape = ((analysis.nnz_l + pattern.n,), (analysis.nnz_l,))
        b, _ = _check_solve_args(self, pattern, factor, aux_shape, b, x0)
        values, rowind = jax.lax.stop_gradient(factor.aux)

        def solve(matvec, rhs):
            x = jax.ffi.ffi_call(native.SOLVE_TARGET, jax.ShapeDtypeStruct(rhs.shape, jnp.float64),
                                 vmap_method="sequential")(
                values, analysis.colptr, rowind, analysis.pinv, rhs.astype(jnp.float64))
            return x.astype(rhs.dtype)

        return _implicit_solve(pattern, factor.data, b, solve, solve)

# --------------------------------------------------------------------------- per column


@dataclass(frozen=True)
class PerColumn(LinearSolver):
    """One matrix per column of the right-hand side, all on one pattern: ``x[:, a] = A_a^-1 b[:, a]``.

    The PD matrix is one scalar ``n x n`` matrix applied to the three coordinates at once;
    a vertex held in some components only (a roller, a symmetry plane) needs the matrix of
    each axis without the couplings of the vertices held along it. ``factorize`` takes the
    ``(k, nnz)`` values of the ``k`` matrices and factorises each with ``solver`` (under
    ``vmap``); ``solve`` takes ``b`` of shape ``(n, k)``. Gradients flow to ``b`` and to
    every matrix's values as with ``solver``.

    Arguments:
        solver: the solver of each matrix (any :class:`LinearSolver`).

    Raises:
        ValueError: from ``factorize``/``solve``, on ``data`` not ``(k, nnz)`` or ``b`` not ``(n, k)``.
    """

    solver: LinearSolver

    @property
    def host_callback(self) -> bool:
        return self.solver.host_callback

    def factorize(self, pattern: SparsityPattern, data) -> Factor:
        data = jnp.asarray(data)
        if data.ndim != 2 or data.shape[1] != pattern.nnz:
            raise ValueError(f"PerColumn.factorize: data must have shape (k, {pattern.nnz}), got {data.shape}")
        return jax.vmap(lambda d: self.solver.factorize(pattern, d))(data)

    def solve(self, pattern: SparsityPattern, factor: Factor, b, x0=None) -> jax.Array:
        b = jnp.asarray(b)
        k = jnp.shape(factor.data)[0]
        if b.shape != (pattern.n, k):
            raise ValueError(f"PerColumn.solve: b must have shape ({pattern.n}, {k}), one column per matrix, "
                             f"got {b.shape}")
        x0 = None if x0 is None else jnp.asarray(x0)  # None: an empty pytree, nothing to map
        return jax.vmap(lambda f, c, g: self.solver.solve(pattern, f, c, g), in_axes=(0, 1, 1), out_axes=1)(
            factor, b, x0)


# --------------------------------------------------------------------------- default


def auto_solver(n: int) -> LinearSolver:
    """The default linear solver for an ``n x n`` PD matrix on CPU.

    :class:`DenseCholesky` up to ``DENSE_MAX_N`` = 400; above it :class:`SparseLDL` up to
    ``LDL_MAX_N`` = 10000 when its native library builds, else :class:`SparseCholesky`
    (:class:`SparseLU` when cholespy is missing). The dense threshold is where dense and
    sparse tie per solve on a 2-core CPU (``softbody bench solvers``); above it dense loses
    fast (20x slower at n = 2048, and its ``n^3`` factorisation takes seconds from n ~ 8k).
    Timed alone (``softbody bench pd-scaling``), SparseLDL's simplicial solve beat
    CHOLMOD's supernodal one at n = 500 and 2304 (0.03 vs 0.11 ms, 0.34 vs 0.42 ms) and
    lost at 8064 and 29160 (4.4 vs 3.3 ms, 40 vs 22 ms); inside a compiled loop CHOLMOD
    also pays 1-2 ms of host callback per solve, which decides it up to ~10k.
    Not measured on GPUs: there, choose :class:`DenseCholesky` or :class:`PCG` yourself.

    Arguments:
        n: matrix size.

    Returns:
        A :class:`LinearSolver` instance.

    Raises:
        ValueError: if ``n`` is not positive.
    """
    if n < 1:
        raise ValueError(f"auto_solver: n must be positive, got {n}")
    if n <= DENSE_MAX_N:
        return DenseCholesky()
    if n <= LDL_MAX_N:
        from softbody import native

        if native.available():
            return SparseLDL()
    if cholespy is not None:
        return SparseCholesky()
    return SparseLU()

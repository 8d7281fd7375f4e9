"""The PD matrix condensed onto a skeleton: the Schur complement on the bone block, made
once per rollout, and the reduced PD solve built on it (see :mod:`softbody.skeleton`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody.skeleton.rig import Pose, Rig

Array = jax.Array


class SchurFactor(eqx.Module):
    """The PD matrix ``A`` condensed onto the skeleton, once per rollout (:func:`schur_factor`).

    With ``A = [[Q_ff, Q_fr], [Q_rf, Q_rr]]`` (free and bone vertices; scalar ``n x n``),
    the Schur complement ``S0 = Q_rr - Q_rf Q_ff^-1 Q_fr`` and the coupling
    ``Y = Q_ff^-1 Q_fr`` enter the reduced step only through their products with the link
    features ``F = [E, E * X]`` ``(n_b, 4L)`` (``E`` the bone vertices' link indicator,
    ``X`` their rest positions): bones move rigidly, each by an affine map of its rest
    positions, so only those products are kept.

    Attributes:
        factor: the factorisation of ``A`` with the bone vertices decoupled (their rows
            and columns reduced to the diagonal): solves with it apply ``Q_ff^-1``.
        data_rf: ``(n_b, K)`` the nonzero entries of ``A`` in bone rows and free columns
            (``Q_rf``), row by row (in the bone list's order), at the vertices
            ``rf_cols`` ``(n_b, K)`` ints; rows with fewer than ``K`` entries are padded
            with zeros.
        moments: ``(4L, 4L)`` ``F^T S0 F``.
        coupling: ``(n, 4L)`` ``Y F`` on the free rows and ``-F`` on the bone rows, so that
            ``v - coupling K`` places the bones by the link motions ``K`` as it corrects
            the free rows (see :func:`_solve_reduced`).
        solver, pattern: the linear solver and sparsity pattern (static).
    """

    factor: object
    data_rf: Array
    moments: Array
    coupling: Array
    rf_cols: Array
    solver: object = eqx.field(static=True)
    pattern: object = eqx.field(static=True)

    def solve_ff(self, b: Array) -> Array:
        """``Q_ff^-1 b_f`` on the free rows (``b`` ``(n, 3)`` with zero bone rows; bone rows stay 0)."""
        return self.solver.solve(self.pattern, self.factor, b)

    def q_rf(self, v: Array) -> Array:
        """``Q_rf v_f`` ``(n_b, 3)`` for ``v`` ``(n, 3)``."""
        # Gathers summed column by column: a third of the time of a segment sum (scatter-add).
        return sum(self.data_rf[:, j, None] * v[self.rf_cols[:, j]] for j in range(self.rf_cols.shape[1]))


def _features(rig: Rig) -> np.ndarray:
    """``F = [E, E * X]`` ``(n_b, 4L)``: link indicator and rest positions per link."""
    x = rig.rest
    e = np.zeros((len(x), len(rig.links)))
    e[np.arange(len(x)), rig.vertex_link] = 1.0
    return np.concatenate([e, (e[:, :, None] * x[:, None, :]).reshape(len(x), -1)], axis=1)


def schur_factor(solver, pattern, data: Array, rig: Rig) -> SchurFactor:
    """Condense the PD matrix onto the skeleton (once per rollout; differentiable in ``data``).

    One extra factorisation (``A`` with the bone vertices decoupled, i.e. ``Q_ff``), one
    solve with ``4L`` right-hand sides for ``Y F = Q_ff^-1 (Q_fr F)``, then
    ``F^T S0 F = F^T Q_rr F - (Q_fr F)^T (Y F)``. Only the ``4L`` link features enter, not
    the ``n_b`` bone vertices one by one (a fourth of the right-hand sides, and no dense
    ``n_b x n x n_b`` product).

    Arguments:
        solver: the scene's :class:`~softbody.linsolve.LinearSolver`; pattern: its
            :class:`~softbody.linsolve.SparsityPattern`.
        data: ``(nnz,)`` the PD matrix values.
        rig: the :class:`Rig`.

    Returns:
        A :class:`SchurFactor`.
    """
    n, bone = pattern.n, np.asarray(rig.bone)
    is_bone = rig.is_bone[:, 0] > 0
    rows, cols = is_bone[pattern.rows], is_bone[pattern.cols]
    zero = jnp.zeros_like(data)
    data_ff = jnp.where((~rows & ~cols) | (pattern.rows == pattern.cols), data, zero)
    factor = solver.factorize(pattern, data_ff)
    position = np.full(n, -1)
    position[bone] = np.arange(len(bone))
    f = _features(rig)
    rf = np.flatnonzero(rows & ~cols)
    rf = rf[np.argsort(position[pattern.rows[rf]], kind="stable")]  # grouped by bone row
    row = position[pattern.rows[rf]]
    per_row = np.bincount(row, minlength=len(bone))
    table = np.full((len(bone), max(int(per_row.max()), 1)), len(rf))  # padded with the index of a zero
    table[row, np.arange(len(rf)) - np.repeat(np.cumsum(per_row) - per_row, per_row)] = np.arange(len(rf))
    q_fr_f = jnp.zeros((n, f.shape[1])).at[pattern.cols[rf]].add(data[rf, None] * f[row])
    y_f = solver.solve(pattern, factor, q_fr_f)  # Y F, zero bone rows
    rr = np.flatnonzero(rows & cols)
    q_rr = jnp.zeros((len(bone), len(bone))).at[position[pattern.rows[rr]], position[pattern.cols[rr]]].add(data[rr])
    moments = f.T @ q_rr @ f - q_fr_f.T @ y_f
    data_rf = jnp.concatenate([data[rf], jnp.zeros(1, data.dtype)])[table]
    return SchurFactor(factor, data_rf, 0.5 * (moments + moments.T), y_f.at[bone].set(-f),
                       jnp.asarray(np.append(pattern.cols[rf], 0)[table]), solver, pattern)


def _link_motions(rig: Rig, pose: Pose, move: Array) -> Array:
    """``G`` ``(4L, 3, n_dofs)``: the motion of every link per unit of each dof, in the layout
    of the features ``F`` (:class:`SchurFactor`), so that ``B d_z = F (G d_z)`` link by link.

    A dof whose twist on link ``l`` is ``(a, w)`` moves its bone vertex ``x = R_l X + p_l``
    by ``a + w x x = c + M X`` with ``c = a + w x p_l`` (row ``l``) and ``M = [w]x R_l``
    (column ``j`` of ``M`` in row ``L + 3 l + j``). Held dofs (``move = 0``) get zero columns.
    The cross products are spelled out by component (XLA's batched tiny matmuls are slower).
    """
    n_links, k = len(rig.links), rig.n_dofs
    local = pose.twists * rig.blocks(move)[rig.tree_index][:, None, :]  # (L, 6, K)
    slots = rig.tree_dofs[rig.tree_index]  # (L, K)
    twists = jnp.zeros((n_links, k + 1, 6), local.dtype).at[jnp.arange(n_links)[:, None], slots].set(
        jnp.swapaxes(local, 1, 2))
    twists = jnp.swapaxes(twists, 1, 2)[:, :, :k]  # (L, 6, k)
    a, w = twists[:, :3], twists[:, 3:]  # (L, 3, k)

    def cross(u):  # w x u for one vector u (L, 3) per link: (L, 3, k)
        u = u[:, :, None]
        return jnp.stack([w[:, 1] * u[:, 2] - w[:, 2] * u[:, 1], w[:, 2] * u[:, 0] - w[:, 0] * u[:, 2],
                          w[:, 0] * u[:, 1] - w[:, 1] * u[:, 0]], axis=1)

    m = jnp.stack([cross(pose.r[:, :, j]) for j in range(3)], axis=1)  # (L, j, 3, k)
    return jnp.concatenate([a + cross(pose.p), m.reshape(3 * n_links, 3, k)])  # explicit: k may be 0


def _held(rig: Rig, z: Array, g_z: Array) -> Array:
    """``(n_dofs,)`` 1.0 for the joints at a limit whose reduced gradient ``g_z`` pushes them
    outward (held this iteration), else 0.0."""
    value = rig.joint_values(z)
    lower, upper = jnp.asarray(rig.lower), jnp.asarray(rig.upper)
    return (((value <= lower) & (g_z > 0)) | ((value >= upper) & (g_z < 0))).astype(g_z.dtype)


def _solve_reduced(factor: SchurFactor, rig: Rig, pose: Pose, g_f: Array, g_z: Array,
                   locked: Array) -> tuple[Array, Array]:
    """Solve the reduced PD system for the right-hand side ``(g_f, g_z)`` (``g_f`` ``(n, 3)``
    with zero bone rows, ``g_z`` ``(n_dofs,)``); see :func:`schur_direction`."""
    move = 1.0 - locked
    motion = _link_motions(rig, pose, move)  # (4L, 3, k)
    v = factor.solve_ff(g_f)  # Q_ff^-1 g_f, zero bone rows
    rhs = (g_z - rig.reduce(pose, factor.q_rf(v))) * move
    rows, _, k = motion.shape  # explicit shapes: k may be 0
    columns = motion.reshape(3 * rows, k)  # (12L, k)
    small = columns.T @ (factor.moments @ motion.reshape(rows, 3 * k)).reshape(3 * rows, k)
    d_z = jnp.linalg.solve(small + jnp.diag(locked), rhs)
    # Free rows v - Y F K, bone rows F K (the bones' rigid motion), K = G d_z. Column by
    # column: three matrix-vector products took a third of the time of one (n, 4L) x (4L, 3)
    # product on CPU.
    k = motion @ d_z
    return jnp.stack([v[:, i] - factor.coupling @ k[:, i] for i in range(3)], axis=1), d_z


def schur_direction(factor: SchurFactor, rig: Rig, z: Array, g: Array, locked: Array) -> tuple[Array, Array]:
    """The reduced PD step: solve ``[[Q_ff, Q_fr B], [B^T Q_rf, B^T Q_rr B]] (d_f, d_z) = (g_f, B^T g_r)``.

    The quadratic model ``1/2 d^T A d - g . d`` is minimised over the displacements whose
    bone rows are ``B d_z``. Eliminating ``d_f = Q_ff^-1 (g_f - Q_fr B d_z)``::

        (B^T S0 B) d_z = B^T (g_r - Q_rf Q_ff^-1 g_f),    d_f = Q_ff^-1 g_f - Y B d_z,

    one sparse solve with ``Q_ff``, one sparse product with ``Q_rf``, and products with
    ``F^T S0 F`` and ``Y F`` (:class:`SchurFactor`): bones move rigidly, so ``B d_z`` is
    one affine map of the rest positions per link, ``B d_z = F G d_z``
    (:func:`_link_motions`), and ``B^T S0 B = G^T (F^T S0 F) G``. No dense
    ``n_b``-sized product is formed per iteration.

    Arguments:
        factor: from :func:`schur_factor`.
        rig: the :class:`Rig`; z: ``(n_coords,)`` its coordinates.
        g: ``(n, 3)`` gradient of the objective (all vertices).
        locked: ``(n_dofs,)`` 1 for dofs held fixed in this step (at an active limit), else 0.

    Returns:
        ``(d, d_z)``: ``(n, 3)`` displacement (bone rows ``B d_z``) and ``(n_dofs,)``; the
        step is ``x - d``, ``z - d_z``.
    """
    pose, bone = rig.pose(z), jnp.asarray(rig.bone)
    return _solve_reduced(factor, rig, pose, g.at[bone].set(0.0), rig.reduce(pose, g[bone]), locked)



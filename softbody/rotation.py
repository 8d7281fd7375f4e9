"""Per-tet rotation extraction for the corotated (ARAP) projection.

The ARAP projection of a deformation gradient ``F`` is the rotation ``R`` in SO(3) that
maximises ``tr(R^T F)``. For ``det F > 0`` it is the polar factor; for an inverted tet
(``det F < 0``) it is the rotation-variant factor ``U diag(1, 1, -1) V^T`` of the SVD, which
pushes the tet back out. Both are found here without any SVD or eigendecomposition:

* **Forward.** Newton's method on ``R <- R exp([theta])``: with ``A = R^T F`` and
  ``S = sym(A)``, the objective is ``tr(R^T F) + 2 theta . axial(A) - 1/2 theta^T H theta``
  to second order, ``H = tr(S) I - S``, so the Newton step is ``theta = 2 H^-1 axial(A)``.
  Where ``H`` is not safely positive definite (far from the maximum) the step falls back
  to the damped step ``2 axial(A) / |tr S|`` of Mueller et al. (2016, "A robust method to
  extract the rotational part of deformations"), which always makes progress. Steps are
  capped at 1 rad. The rotation is carried as a unit quaternion so that it stays exactly
  on SO(3) and can be warm-started from the previous PD iteration or time step: at rest
  (``F = I``) the answer is exact after zero steps, and near convergence each Newton step
  squares the error.
* **Derivative.** A ``custom_jvp`` by the implicit function theorem at the maximum:
  ``dR = R [omega]`` with ``(tr(S) I - S) omega = vee(R^T dF - (R^T dF)^T)``. It is finite at
  ``F = I``, with repeated singular values and for inverted tets, wherever the maximum is
  strict (the two smallest signed singular values do not sum to zero). JAX's SVD
  derivative is NaN at ``F = I``; this one is not.

Layout: structure-of-arrays. A batch of matrices is an array of shape ``(3, 3, T)``
(``F[i, j]`` is a length-``T`` vector), quaternions ``(4, T)`` as ``(w, x, y, z)``. XLA on
CPU vectorises this layout over tets far better than ``(T, 3, 3)``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

#: A batch of 3x3 matrices, shape (3, 3, T).
Mat = jax.Array
#: A batch of unit quaternions (w, x, y, z), shape (4, T).
Quat = jax.Array


def identity_quaternions(n_tets: int, dtype=jnp.float64) -> Quat:
    """Unit quaternions of the identity rotation, shape ``(4, n_tets)``."""
    return jnp.zeros((4, n_tets), dtype).at[0].set(1.0)


def quat_to_mat(q: Quat) -> Mat:
    """Rotation matrices ``(3, 3, T)`` of unit quaternions ``(4, T)``."""
    w, x, y, z = q
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]),
    ])


def matmul(a: Mat, b: Mat) -> Mat:
    """Batched ``a @ b`` for ``(3, 3, T)`` arrays.

    Written as explicit sums of elementwise products: XLA fuses these into one loop over
    tets, where an ``einsum`` becomes a slow batched dot with tiny matrices.
    """
    a, b = entries(a), entries(b)
    return jnp.stack([
        jnp.stack([a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j] for j in range(3)])
        for i in range(3)
    ])


def entries(a: jax.Array) -> list[list[jax.Array]]:
    """The entries ``(T,)`` of ``(r, c, T)`` ``a`` (a ``(3, 3, T)`` matrix) as nested lists
    ``e[i][j]``.

    One reshape and one unstack: indexing each entry where it is used (``a[i, j]``) costs a
    slice and a squeeze every time, which multiplied the programs' size and the time to
    trace them (and their derivatives). The arithmetic is the same, but XLA may fuse it
    differently, so results can differ in their last bits (``trace`` indexes its three
    entries: through this, the rounding it changed made one splitting test's landing step
    take 4304 iterations instead of 743).
    """
    rows, cols = a.shape[:2]
    e = jnp.unstack(a.reshape((rows * cols,) + a.shape[2:]))
    return [e[i * cols:(i + 1) * cols] for i in range(rows)]


def transpose(a: Mat) -> Mat:
    return jnp.swapaxes(a, 0, 1)


def vee_skew(a: Mat) -> jax.Array:
    """``(a32 - a23, a13 - a31, a21 - a12)``, shape ``(3, T)``: twice the axial vector of skew(a)."""
    return jnp.stack([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])


def _solve_sym3(h: Mat, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Solve batched symmetric 3x3 systems ``h x = b`` by cofactors.

    Returns ``(x, det)``; ``x`` is meaningless where ``det`` is ~0 (callers mask).
    """
    h = entries(h)
    c00 = h[1][1] * h[2][2] - h[1][2] * h[2][1]
    c01 = h[1][2] * h[2][0] - h[1][0] * h[2][2]
    c02 = h[1][0] * h[2][1] - h[1][1] * h[2][0]
    c11 = h[0][0] * h[2][2] - h[0][2] * h[2][0]
    c12 = h[0][1] * h[2][0] - h[0][0] * h[2][1]
    c22 = h[0][0] * h[1][1] - h[0][1] * h[1][0]
    det = h[0][0] * c00 + h[0][1] * c01 + h[0][2] * c02
    safe = jnp.where(jnp.abs(det) > 0, det, 1.0)
    x0 = (c00 * b[0] + c01 * b[1] + c02 * b[2]) / safe
    x1 = (c01 * b[0] + c11 * b[1] + c12 * b[2]) / safe
    x2 = (c02 * b[0] + c12 * b[1] + c22 * b[2]) / safe
    return jnp.stack([x0, x1, x2]), det


def _hessian(s: Mat) -> Mat:
    """``tr(S) I - S`` for symmetric ``S``, shape (3, 3, T)."""
    tr = s[0, 0] + s[1, 1] + s[2, 2]
    return jnp.eye(3, dtype=s.dtype)[:, :, None] * tr - s


def _sym(a: Mat) -> Mat:
    return 0.5 * (a + transpose(a))


def dot(a: Mat, b: Mat) -> jax.Array:
    """Frobenius inner products ``sum_ij a_ij b_ij``, shape ``(T,)`` (explicit sum: XLA's
    reductions over the leading axes of ``(3, 3, T)`` are several times slower)."""
    a, b = entries(a), entries(b)
    return sum(a[i][j] * b[i][j] for i in range(3) for j in range(3))


def trace(a: Mat) -> jax.Array:
    return a[0, 0] + a[1, 1] + a[2, 2]


def _newton_step(f: Mat, q: Quat) -> Quat:
    r = quat_to_mat(q)
    a = matmul(transpose(r), f)
    s = _sym(a)
    g = vee_skew(a)  # = 2 axial(skew A): the objective's gradient in theta
    h = _hessian(s)
    newton, det = _solve_sym3(h, g)
    # Sylvester's criterion with a margin relative to the scale of S: H safely positive definite.
    scale = jnp.sqrt(dot(s, s)) + 1e-300
    m2 = h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]
    pd = (h[0, 0] > 1e-6 * scale) & (m2 > 1e-6 * scale**2) & (det > 1e-6 * scale**3)
    tr = jnp.abs(trace(s))
    damped = g / jnp.where(tr > 1e-12 * scale, tr, scale)
    theta = jnp.where(pd, newton, damped)
    # Cap the step at 1 rad.
    norm2 = theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2
    theta = theta * jnp.minimum(1.0, jax.lax.rsqrt(jnp.maximum(norm2, 1e-300)))
    # q <- normalise(q * (1, theta / 2)): the body-frame increment, exact to O(theta^3),
    # which keeps Newton's quadratic convergence without sin/cos.
    dx, dy, dz = 0.5 * theta
    w, x, y, z = q
    out = jnp.stack([
        w - x * dx - y * dy - z * dz,
        w * dx + x + y * dz - z * dy,
        w * dy - x * dz + y + z * dx,
        w * dz + x * dy - y * dx + z,
    ])
    return out * jax.lax.rsqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2 + out[3] ** 2)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def rotation(f: Mat, q0: Quat, iterations: int = 3) -> tuple[Mat, Quat]:
    """The rotation maximising ``tr(R^T F)`` for each tet, warm-started from ``q0``.

    Arguments:
        f: deformation gradients, shape ``(3, 3, T)``.
        q0: warm-start unit quaternions, shape ``(4, T)`` (e.g. the previous iteration's).
        iterations: Newton steps (static). From a good warm start 2-3 reach machine
            precision; from the identity a large rotation needs more.

    Returns:
        ``(R, q)``: rotations ``(3, 3, T)`` and their quaternions ``(4, T)`` (to warm-start
        the next call). The derivative of ``R`` is the exact derivative of the maximiser
        (see the module docstring); ``q`` carries no derivative.
    """
    q = q0
    for _ in range(iterations):
        q = _newton_step(f, q)
    return quat_to_mat(q), q


def rotation_jvp_from(f: Mat, r: Mat, df: Mat) -> Mat:
    """Tangent of the maximising rotation: ``dR = R [omega]``, shape (3, 3, T)."""
    s = _sym(matmul(transpose(r), f))
    b = vee_skew(matmul(transpose(r), df))
    omega, _ = _solve_sym3(_hessian(s), b)
    ox, oy, oz = omega
    zero = jnp.zeros_like(ox)
    skew = jnp.stack([
        jnp.stack([zero, -oz, oy]),
        jnp.stack([oz, zero, -ox]),
        jnp.stack([-oy, ox, zero]),
    ])
    return matmul(r, skew)


@rotation.defjvp
def _rotation_jvp(iterations, primals, tangents):
    f, q0 = primals
    df = tangents[0]
    r, q = rotation(f, q0, iterations)
    dr = rotation_jvp_from(f, r, df)
    return (r, q), (dr, jnp.zeros_like(q))


def _cofactor(a: Mat) -> Mat:
    """Cofactor matrices ``cof(a) = det(a) a^-T``, shape (3, 3, T)."""
    a = entries(a)
    return jnp.stack([
        jnp.stack([a[1][1] * a[2][2] - a[1][2] * a[2][1], a[1][2] * a[2][0] - a[1][0] * a[2][2],
                   a[1][0] * a[2][1] - a[1][1] * a[2][0]]),
        jnp.stack([a[0][2] * a[2][1] - a[0][1] * a[2][2], a[0][0] * a[2][2] - a[0][2] * a[2][0],
                   a[0][1] * a[2][0] - a[0][0] * a[2][1]]),
        jnp.stack([a[0][1] * a[1][2] - a[0][2] * a[1][1], a[0][2] * a[1][0] - a[0][0] * a[1][2],
                   a[0][0] * a[1][1] - a[0][1] * a[1][0]]),
    ])


def det3(a: Mat) -> jax.Array:
    """Determinants of ``(3, 3, T)`` matrices, shape ``(T,)``."""
    a = entries(a)
    return (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))


def mat_to_quat(r: Mat) -> Quat:
    """Unit quaternions ``(4, T)`` of rotation matrices ``(3, 3, T)`` (Shepperd's method)."""
    r = entries(r)
    t = r[0][0] + r[1][1] + r[2][2]
    cands = jnp.stack([t, r[0][0], r[1][1], r[2][2]])
    k = jnp.argmax(cands, axis=0)
    s0 = jnp.sqrt(jnp.maximum(1 + t, 1e-300)) * 2
    s1 = jnp.sqrt(jnp.maximum(1 + r[0][0] - r[1][1] - r[2][2], 1e-300)) * 2
    s2 = jnp.sqrt(jnp.maximum(1 - r[0][0] + r[1][1] - r[2][2], 1e-300)) * 2
    s3 = jnp.sqrt(jnp.maximum(1 - r[0][0] - r[1][1] + r[2][2], 1e-300)) * 2
    q0 = jnp.stack([s0 / 4, (r[2][1] - r[1][2]) / s0, (r[0][2] - r[2][0]) / s0, (r[1][0] - r[0][1]) / s0])
    q1 = jnp.stack([(r[2][1] - r[1][2]) / s1, s1 / 4, (r[0][1] + r[1][0]) / s1, (r[0][2] + r[2][0]) / s1])
    q2 = jnp.stack([(r[0][2] - r[2][0]) / s2, (r[0][1] + r[1][0]) / s2, s2 / 4, (r[1][2] + r[2][1]) / s2])
    q3 = jnp.stack([(r[1][0] - r[0][1]) / s3, (r[0][2] + r[2][0]) / s3, (r[1][2] + r[2][1]) / s3, s3 / 4])
    q = jnp.select([k == 0, k == 1, k == 2], [q0, q1, q2], q3)
    return q * jax.lax.rsqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)


def _smallest_eigenvector(s: Mat) -> jax.Array:
    """Unit eigenvectors ``(3, T)`` of the smallest eigenvalue of symmetric ``(3, 3, T)`` ``s``.

    Closed form: the smallest eigenvalue by the trigonometric formula for symmetric 3x3
    matrices (Smith 1961), then the eigenvector as the largest cross product of two rows
    of ``s - lambda I`` (its null space). Accurate to ``~eps |s| / gap`` where ``gap``
    separates the two smallest eigenvalues. Where they coincide every vector of their
    plane is an eigenvector and one of them is returned; where all three coincide, the
    first axis.
    """
    q = trace(s) / 3.0
    p1 = s[0, 1] ** 2 + s[0, 2] ** 2 + s[1, 2] ** 2
    p2 = (s[0, 0] - q) ** 2 + (s[1, 1] - q) ** 2 + (s[2, 2] - q) ** 2 + 2.0 * p1
    p = jnp.sqrt(p2 / 6.0)
    safe_p = jnp.where(p > 0, p, 1.0)
    b = (s - jnp.eye(3, dtype=s.dtype)[:, :, None] * q) / safe_p
    r = jnp.clip(det3(b) / 2.0, -1.0, 1.0)
    phi = jnp.arccos(r) / 3.0
    lam = q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)
    a = s - jnp.eye(3, dtype=s.dtype)[:, :, None] * lam
    rows = [a[0], a[1], a[2]]  # each (3, T)

    def cross(u, v):
        return jnp.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                          u[0] * v[1] - u[1] * v[0]])

    cands = jnp.stack([cross(rows[0], rows[1]), cross(rows[0], rows[2]),
                       cross(rows[1], rows[2])])  # (3 candidates, 3, T)
    norms = jnp.sum(cands ** 2, axis=1)  # (3, T)
    best = jnp.take_along_axis(cands, jnp.argmax(norms, axis=0)[None, None, :], axis=0)[0]
    best_norm = jnp.max(norms, axis=0)
    # Two smallest eigenvalues (numerically) equal: a - lambda I has rank <= 1, so any
    # vector orthogonal to its largest row is an eigenvector of the smallest eigenvalue.
    row_norms = jnp.stack([jnp.sum(rw ** 2, axis=0) for rw in rows])
    big = jnp.take_along_axis(jnp.stack(rows), jnp.argmax(row_norms, axis=0)[None, None, :],
                              axis=0)[0]
    axis = jnp.eye(3, dtype=s.dtype)[jnp.argmin(jnp.abs(big), axis=0)].T  # (3, T)
    other = cross(big, axis)
    scale2 = jnp.max(row_norms, axis=0)
    degenerate = best_norm <= (1e-12 * scale2) ** 2 + 1e-300
    v = jnp.where(degenerate, other, best)
    all_equal = scale2 <= 1e-24 * (q ** 2) + 1e-300
    v = jnp.where(all_equal, jnp.eye(3, dtype=s.dtype)[:, :1], v)
    return v * jax.lax.rsqrt(jnp.sum(v ** 2, axis=0) + 1e-300)


def cold_start(f: Mat, iterations: int = 12) -> Quat:
    """Quaternions of the maximising rotation of ``F`` with no warm start, ``(4, T)``.

    Scaled Newton iteration for the orthogonal polar factor ``Q`` (Higham:
    ``X <- (g X + X^-T / g) / 2``, ``g = |det X|^(-1/3)``), then, where ``det Q < 0``, the
    reflection is turned into the rotation-variant factor ``Q (I - 2 v v^T)`` with ``v`` the
    eigenvector of ``S = Q^T F`` of smallest eigenvalue (closed form). A (nearly) flat
    ``F`` is regularised so that the iteration stays finite: ``|det X|`` is held at least
    ``1e-12 |X|^3``; the polar factor's sign along the flat direction is then arbitrary
    and the flip restores the maximiser. Use it to initialise :func:`rotation`.

    Arguments:
        f: ``(3, 3, T)`` deformation gradients.
        iterations: the most scaled Newton iterations (quadratic convergence; 12 is
            ample for condition numbers up to ~1e12); the loop stops early once converged.

    Returns:
        ``(4, T)`` unit quaternions.
    """
    if f.shape[-1] == 0:  # a scene of rigid bodies only has no tets
        return jnp.zeros((4, 0), f.dtype)

    def higham(_, x):
        c = _cofactor(x)
        d = det3(x)
        floor = 1e-12 * dot(x, x) ** 1.5 + 1e-300
        d = jnp.where(jnp.abs(d) > floor, d, jnp.where(d < 0, -floor, floor))
        g = jnp.abs(d) ** (-1.0 / 3.0)
        return 0.5 * (g * x + c / (g * d))

    # Stop once the largest relative change is below 1e-8: with quadratic convergence the
    # next step would change X by ~1e-16 (typically 5-7 steps for strains below 50 %).
    def unconverged(c):
        x, change, k = c
        return (k < iterations) & (change > 1e-8)

    def step(c):
        x, _, k = c
        y = higham(k, x)
        change = jnp.max(jnp.sqrt(dot(y - x, y - x) / (dot(y, y) + 1e-300)))
        return y, change, k + 1

    x, _, _ = jax.lax.while_loop(unconverged, step, (f, jnp.asarray(jnp.inf, f.dtype), 0))
    s = _sym(matmul(transpose(x), f))
    v = _smallest_eigenvector(s)
    xv = jnp.einsum("ijt,jt->it", x, v)
    flipped = x - 2 * xv[:, None, :] * v[None, :, :]
    r = jnp.where(det3(x) < 0, flipped, x)
    return mat_to_quat(r)


def polar(f: Mat, iterations: int = 3) -> Mat:
    """The rotation maximising ``tr(R^T F)`` with no warm start: for tests and tools.

    Arguments:
        f: ``(3, 3, T)`` deformation gradients.
        iterations: Newton polishing steps after :func:`cold_start`.

    Returns:
        ``(3, 3, T)`` rotations (det +1), differentiable as :func:`rotation`.
    """
    r, _ = rotation(f, jax.lax.stop_gradient(cold_start(f)), iterations)
    return r

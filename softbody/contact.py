"""Contact and dry friction: obstacles as signed distance functions, and the contact solver.

**Obstacles.** Each obstacle is a small frozen class (static: it fixes the code that runs)
with a parameter pytree (traced and differentiable: pose, friction, restitution) made by
``init_params()``, and::

    distance(points (n, 3), params, time) -> (phi (n,), normal (n, 3), velocity (n, 3))

the signed distance of each point to the obstacle's surface (negative inside the
obstacle), the outward unit normal and the velocity of the obstacle's material at the
point. Shapes: :class:`Plane` (any tilt), :class:`Sphere`, :class:`Box` (any rotation),
:class:`Capsule`, :class:`HeightField`; :class:`Moving` gives any of them a prescribed
rigid motion ``time -> (rotation, translation)`` (a moving plate, a gripper jaw). Every
obstacle carries a static friction coefficient ``mu_s``, a kinetic one ``mu_k <= mu_s``
and a restitution coefficient (0 by default). ``to_dict`` writes an obstacle in the
viewer's result format (:data:`softbody.io.OBSTACLE_KEYS`) and :func:`from_dict` reads it.

**The contact solver** :class:`ContactPD` solves each implicit-Euler step
``min Phi(x)`` subject to non-penetration and Coulomb friction with the design's
velocity-space splitting iteration::

    (M + h^2 D) v^{k+1} = f - h^2 (L - D) v^k + xi^k

``A = M/h^2 + L`` is the PD matrix, ``D`` a diagonal splitting (:class:`Naive`: 0,
:class:`Diagonal`: ``diag(L)``, the default :class:`ScaledDiagonal`: ``2 diag(L)``, whose
convergence is proved in its docstring) and ``xi`` the contact impulse, *added* to the
right-hand side. The right-hand side ``f`` is PD's: each iteration first runs PD's local
step at the current iterate (the projections), which gives ``grad Phi``, so that one
iteration in positions form (``x = x_n + h v``) reads::

    y = x^k - P^{-1} grad Phi(x^k),        P = M/h^2 + D           (one splitting sweep)
    x^{k+1}_i = y_i + xi_i / (h P_i)       per vertex, in its contact frame

(``b - (L - D) x = P x - grad Phi`` with ``b = A x - grad Phi`` PD's right-hand side, so
the matrix product cancels). The per-vertex contact step, for a vertex whose sweep
position ``y_i`` lies inside the nearest obstacle (``phi(y_i) < 0``), works on the impulse
``xi_i = h P_i (x_i - y_i)`` that a vertex of "mass" ``h^2 P_i`` needs:

* separating (``phi(y_i) >= 0``): no impulse;
* otherwise cancel the normal momentum: move ``y_i`` back to the surface along the normal
  (to ``phi = h e v_in`` with restitution ``e`` and incoming normal speed ``v_in``);
* stick if the tangential impulse that cancels the tangential motion relative to the
  obstacle fits the static cone (``|xi_t| <= mu_s xi_n``), else slide on the kinetic
  cone's edge (``|xi_t| = mu_k xi_n``, opposing the slip).

At a fixed point ``x^{k+1} = x^k`` the force residual ``grad Phi - r`` (``r = xi / h`` the
contact forces) vanishes, ``r`` lies in the friction cone and every contact vertex is on
the surface: the step's equilibrium. With the projections held fixed and no contact
active, the iteration matrix is ``T = P^{-1} (D - L) = (M + h^2 D)^{-1} h^2 (D - L)``, the
matrix whose spectral radius :func:`splitting_spectral_radius` measures.

Scheme, convergence criterion and costs:

* One iteration = one local step (``problem.evaluate``) + one diagonal sweep + the
  per-vertex contact step; no linear solve. The iterate with the smallest residual is
  returned after the contact step, so every vertex ends on or outside every obstacle
  (exactly for planes, spheres, boxes and capsules; to second order in the step for
  height fields; a vertex wedged between two obstacles is projected out of the deeper
  one only).
* Convergence: ``|grad Phi(x^k) - r^k| = |P (x^{k+1} - x^k)| <= threshold`` over the free
  degrees of freedom, the core's force tolerance (``Options.tol``/``atol``); at most
  ``max_iter`` iterations. ``Solution.gnorm`` is that residual.
* Anderson acceleration (``history`` > 0) of the fixed-point map, weighted by
  ``sqrt(P)``, with restarts when the residual grows tenfold over the best one; the plain
  map is contracting (see :class:`ScaledDiagonal`), the acceleration is a safeguarded
  heuristic on top. ``history=0`` runs the plain splitting iteration of the design. To a
  relative residual of 1e-6 on the first step of a resting 342-vertex gmsh cube (soft
  ``E`` = 1e4 Pa, ``h`` = 1/30 s) the plain iteration contracts by 0.9992 per iteration
  (over 10000 iterations); Anderson with history 5 took 2318, 10: 1499, 20: 458 and 30
  (the default): 261. Over the benchmark's 96 cases the default converged in all, in
  4-1384 iterations (median 150; the most for the stiff 1419-vertex quadruped at
  ``h`` = 1/30 s).
* Scenes pay for contact only when they touch: a step where no vertex of ``x_n + h v_n``
  is within ``margin`` of an obstacle runs ``free_method`` (L-BFGS with the prefactored
  PD matrix); if that result penetrates an obstacle the step is redone with contact.
  Contact masks are per-vertex booleans, so shapes are fixed under ``jit``/``vmap``.

**Gradients through contact** (implicit, with the contact state held fixed). The
solve is never differentiated. The positions it returns, a fixed point
``x* = F(x*; theta)`` of the map above, carry a custom derivative: the tangent solves
``(I - dF/dx) dx = dF/dtheta dtheta`` at ``x*``, where ``F``'s ``where`` selections
(separated, sticking or sliding, which obstacle) are those of ``x*``; the system is solved
by the same Anderson iteration (it converges where the forward map does, its iteration
matrix being ``dF/dx``), inside :func:`jax.lax.custom_linear_solve`, so reverse mode
solves the transposed system. ``theta`` is everything the step depends on: material
and actuator parameters, the state, obstacle poses and friction. The derivative is
exact for the computed contact state up to the forward tolerance; it is the derivative
of a piecewise-smooth map, so it does not see a vertex about to switch state (at the
stick/slip threshold the true derivative jumps). Norms and normalisations are guarded at
zero, so no NaN arises at rest or at zero slip. It is used when the step is
differentiated through the method (:class:`softbody.gradients.Unrolled`, forward or
reverse mode); costs one linear fixed-point solve per step and no taped iterations.
"""

# ruff: noqa: F722  (jaxtyping shape strings in annotations)
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as splinalg
from jaxtyping import Array, Float

from softbody.solvers import LBFGS, IterationMethod, Solution, StepProblem

__all__ = [
    "Box",
    "Capsule",
    "ContactPD",
    "Diagonal",
    "HeightField",
    "Moving",
    "Naive",
    "Obstacle",
    "ObstacleError",
    "Plane",
    "ScaledDiagonal",
    "Sphere",
    "Splitting",
    "from_dict",
    "splitting_spectral_radius",
]


class ObstacleError(ValueError):
    """An obstacle is invalid; the message names the problem and the fix."""


# --------------------------------------------------------------------------------------
# Guarded vector helpers (finite values and derivatives at zero length)
# --------------------------------------------------------------------------------------


def _norm(v: Array, keepdims: bool = False) -> Array:
    """Euclidean norm over the last axis, with a zero (not NaN) derivative at 0; NaN stays NaN."""
    sq = jnp.sum(v * v, axis=-1, keepdims=keepdims)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), sq)


def _unit(v: Array, fallback: Array) -> Array:
    """``v / |v|`` over the last axis, ``fallback`` where ``v`` is zero."""
    length = _norm(v, keepdims=True)
    positive = length > 0
    return jnp.where(positive, v / jnp.where(positive, length, 1.0), fallback)


_UP = np.array([0.0, 0.0, 1.0])


# --------------------------------------------------------------------------------------
# Validation of user values (eager, before anything is traced)
# --------------------------------------------------------------------------------------


def _array(owner: str, name: str, value, shape: tuple) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ObstacleError(f"{owner}.{name} = {value!r} is not numeric") from None
    if any(s != -1 and s != d for s, d in zip(shape, a.shape)) or a.ndim != len(shape):
        want = "x".join("?" if s == -1 else str(s) for s in shape) or "a scalar"
        raise ObstacleError(f"{owner}.{name} must have shape {want}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ObstacleError(f"{owner}.{name} has non-finite values ({value!r}); give a finite pose")
    return a


def _positive(owner: str, name: str, value) -> float:
    v = float(_array(owner, name, value, ()))
    if v <= 0:
        raise ObstacleError(f"{owner}.{name} must be positive, got {v}")
    return v


def _direction(owner: str, name: str, value) -> np.ndarray:
    a = _array(owner, name, value, (3,))
    length = float(np.linalg.norm(a))
    if length == 0:
        raise ObstacleError(f"{owner}.{name} must be a non-zero vector")
    return a / length


def _rotation(owner: str, name: str, value) -> np.ndarray:
    r = _array(owner, name, value, (3, 3))
    if not (np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0):
        raise ObstacleError(
            f"{owner}.{name} must be a rotation matrix (orthonormal, det +1), got {r.tolist()}"
        )
    return r


# --------------------------------------------------------------------------------------
# Obstacles
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False, kw_only=True)
class Obstacle:
    """Base class of the obstacles: friction, restitution and the common interface.

    Attributes:
        mu_s: static friction coefficient (>= 0): a sticking vertex stays put while its
            tangential contact force is at most ``mu_s`` times the normal force.
        mu_k: kinetic friction coefficient, ``0 <= mu_k <= mu_s``; ``None`` means
            ``mu_s``. A sliding vertex feels ``mu_k`` times the normal force.
        restitution: coefficient of restitution in ``[0, 1]`` (default 0: contact
            cancels the normal velocity).

    These initial values go into :meth:`init_params`, where they are traced and
    differentiable. The traced values are used as given (``mu_k`` is not re-checked
    against ``mu_s`` inside ``jit``).

    Raises:
        ObstacleError: a negative or non-finite coefficient, ``mu_k > mu_s``, a
            restitution outside ``[0, 1]``, or a bad pose (see each shape).
    """

    mu_s: float = 0.5
    mu_k: float | None = None
    restitution: float = 0.0

    kind: ClassVar[str] = ""
    #: the shape's own parameter names, in the viewer's format
    keys: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self):
        owner = type(self).__name__
        mu_s = float(_array(owner, "mu_s", self.mu_s, ()))
        mu_k = mu_s if self.mu_k is None else float(_array(owner, "mu_k", self.mu_k, ()))
        e = float(_array(owner, "restitution", self.restitution, ()))
        if mu_s < 0 or mu_k < 0:
            raise ObstacleError(
                f"{owner}: friction coefficients must be >= 0, got mu_s={mu_s}, mu_k={mu_k}"
            )
        if mu_k > mu_s:
            raise ObstacleError(
                f"{owner}: the kinetic friction coefficient mu_k={mu_k} exceeds the static "
                f"one mu_s={mu_s}; static friction is at least kinetic friction (mu_k <= mu_s)"
            )
        if not 0 <= e <= 1:
            raise ObstacleError(f"{owner}: restitution must lie in [0, 1], got {e}")
        object.__setattr__(self, "mu_s", mu_s)
        object.__setattr__(self, "mu_k", mu_k)
        object.__setattr__(self, "restitution", e)
        self._check_shape()

    def _check_shape(self):
        """Validate and normalise the shape's fields (subclasses)."""

    def _shape_params(self) -> dict:
        """The shape's own parameters as float64 arrays (subclasses)."""
        raise NotImplementedError

    def init_params(self) -> dict:
        """The obstacle's parameter pytree: a dict of float64 arrays.

        Returns:
            ``{"mu_s": (), "mu_k": (), "restitution": (), <shape keys>: ...}``, the shape
            keys as in :data:`softbody.io.OBSTACLE_KEYS` (see each shape).
        """
        p = {k: jnp.asarray(v, jnp.float64) for k, v in self._shape_params().items()}
        p.update(
            {k: jnp.asarray(getattr(self, k), jnp.float64) for k in ("mu_s", "mu_k", "restitution")}
        )
        return p

    def distance(
        self, points: Float[Array, "n 3"], params: dict, time
    ) -> tuple[Float[Array, " n"], Float[Array, "n 3"], Float[Array, "n 3"]]:
        """Signed distance, outward normal and surface velocity at each point.

        Arguments:
            points: ``(n, 3)`` query points, m.
            params: this obstacle's parameters (:meth:`init_params`, possibly traced).
            time: the time, s (scalar; used by moving obstacles).

        Returns:
            ``(phi, normal, velocity)``: ``(n,)`` signed distances (negative inside),
            ``(n, 3)`` unit normals pointing out of the obstacle, ``(n, 3)`` velocities of
            the obstacle's material (m/s; zero for fixed obstacles).
        """
        phi, normal = self._sdf(jnp.asarray(points), params)
        return phi, normal, jnp.zeros_like(normal)

    def _sdf(self, points: Array, params: dict) -> tuple[Array, Array]:
        raise NotImplementedError

    def to_dict(self, params: dict | None = None, time: float = 0.0) -> dict:
        """The obstacle in the viewer's result format, with its friction coefficients.

        Arguments:
            params: parameters to write (default :meth:`init_params`); concrete arrays.
            time: the time at which to write a moving obstacle's pose.

        Returns:
            ``{"type": kind, <keys>..., "mu_s": .., "mu_k": .., "restitution": ..}`` with
            plain lists and floats (JSON-able).
        """
        p = self.init_params() if params is None else params
        out = {"type": self.kind}
        for key in self.keys:
            out[key] = np.asarray(p[key], np.float64).tolist()
        for key in ("mu_s", "mu_k", "restitution"):
            out[key] = float(p[key])
        return out


@dataclass(frozen=True, eq=False)
class Plane(Obstacle):
    """A half-space: the obstacle fills the side of the plane opposite to ``normal``.

    Attributes:
        point: ``(3,)`` a point on the plane, m.
        normal: ``(3,)`` the outward normal (normalised here); tilt it for an incline.

    Params: ``point (3,)``, ``normal (3,)`` (normalised again inside :meth:`distance`, so it
    may be optimised freely).
    """

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)

    kind: ClassVar[str] = "plane"
    keys: ClassVar[tuple[str, ...]] = ("point", "normal")

    def _check_shape(self):
        object.__setattr__(self, "point", _array("Plane", "point", self.point, (3,)))
        object.__setattr__(self, "normal", _direction("Plane", "normal", self.normal))

    def _shape_params(self):
        return {"point": self.point, "normal": self.normal}

    def _sdf(self, points, params):
        n = _unit(params["normal"], jnp.asarray(_UP))
        phi = (points - params["point"]) @ n
        return phi, jnp.broadcast_to(n, points.shape)


@dataclass(frozen=True, eq=False)
class Sphere(Obstacle):
    """A ball of ``radius`` about ``center``.

    Params: ``center (3,)``, ``radius ()``.
    """

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0

    kind: ClassVar[str] = "sphere"
    keys: ClassVar[tuple[str, ...]] = ("center", "radius")

    def _check_shape(self):
        object.__setattr__(self, "center", _array("Sphere", "center", self.center, (3,)))
        object.__setattr__(self, "radius", _positive("Sphere", "radius", self.radius))

    def _shape_params(self):
        return {"center": self.center, "radius": self.radius}

    def _sdf(self, points, params):
        d = points - params["center"]
        return _norm(d) - params["radius"], _unit(d, jnp.asarray(_UP))


@dataclass(frozen=True, eq=False)
class Box(Obstacle):
    """An oriented box.

    Attributes:
        center: ``(3,)`` m.
        half_extents: ``(3,)`` positive half edge lengths along the box's axes, m.
        rotation: ``(3, 3)`` rotation whose columns are the box's axes in world
            coordinates (default identity).

    Params: ``center (3,)``, ``half_extents (3,)``, ``rotation (3, 3)``.
    """

    center: tuple = (0.0, 0.0, 0.0)
    half_extents: tuple = (0.5, 0.5, 0.5)
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    kind: ClassVar[str] = "box"
    keys: ClassVar[tuple[str, ...]] = ("center", "half_extents", "rotation")

    def _check_shape(self):
        object.__setattr__(self, "center", _array("Box", "center", self.center, (3,)))
        e = _array("Box", "half_extents", self.half_extents, (3,))
        if np.any(e <= 0):
            raise ObstacleError(f"Box.half_extents must be positive, got {e.tolist()}")
        object.__setattr__(self, "half_extents", e)
        object.__setattr__(self, "rotation", _rotation("Box", "rotation", self.rotation))

    def _shape_params(self):
        return {"center": self.center, "half_extents": self.half_extents, "rotation": self.rotation}

    def _sdf(self, points, params):
        rot = params["rotation"]
        local = (points - params["center"]) @ rot  # R^T (x - c) for row vectors
        sign = jnp.where(local >= 0, 1.0, -1.0)
        q = jnp.abs(local) - params["half_extents"]
        outside = jnp.maximum(q, 0.0)
        out_len = _norm(outside)
        inside = jnp.max(q, axis=-1)
        phi = out_len + jnp.minimum(inside, 0.0)
        face = jax.nn.one_hot(jnp.argmax(q, axis=-1), 3, dtype=points.dtype) * sign
        n_local = jnp.where((out_len > 0)[:, None], _unit(outside * sign, face), face)
        return phi, n_local @ rot.T


@dataclass(frozen=True, eq=False)
class Capsule(Obstacle):
    """The points within ``radius`` of the segment ``p0``-``p1``.

    Params: ``p0 (3,)``, ``p1 (3,)``, ``radius ()``.
    """

    p0: tuple = (0.0, 0.0, 0.0)
    p1: tuple = (1.0, 0.0, 0.0)
    radius: float = 0.1

    kind: ClassVar[str] = "capsule"
    keys: ClassVar[tuple[str, ...]] = ("p0", "p1", "radius")

    def _check_shape(self):
        object.__setattr__(self, "p0", _array("Capsule", "p0", self.p0, (3,)))
        object.__setattr__(self, "p1", _array("Capsule", "p1", self.p1, (3,)))
        object.__setattr__(self, "radius", _positive("Capsule", "radius", self.radius))

    def _shape_params(self):
        return {"p0": self.p0, "p1": self.p1, "radius": self.radius}

    def _sdf(self, points, params):
        p0, axis = params["p0"], params["p1"] - params["p0"]
        length2 = jnp.sum(axis * axis)
        t = jnp.clip((points - p0) @ axis / jnp.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        d = points - (p0 + t[:, None] * axis)
        return _norm(d) - params["radius"], _unit(d, jnp.asarray(_UP))


@dataclass(frozen=True, eq=False)
class HeightField(Obstacle):
    """Ground given by heights on a regular grid: the obstacle fills ``z <= H(x, y)``.

    ``heights[i][j]`` is the ground height at ``(origin[0] + i spacing[0],
    origin[1] + j spacing[1])``; ``H`` interpolates bilinearly and is extended
    constantly beyond the grid. The signed distance is the first-order estimate
    ``(z - H) / sqrt(1 + |grad H|^2)`` with normal ``(-H_x, -H_y, 1)`` normalised: exact on
    flat cells, accurate to second order in the depth elsewhere.

    Attributes:
        origin: ``(2,)`` m. spacing: ``(2,)`` positive, m. heights: ``(nx, ny)`` with
        ``nx, ny >= 2``, m.

    Params: ``origin (2,)``, ``spacing (2,)``, ``heights (nx, ny)``.
    """

    origin: tuple = (0.0, 0.0)
    spacing: tuple = (1.0, 1.0)
    heights: tuple = ((0.0, 0.0), (0.0, 0.0))

    kind: ClassVar[str] = "heightfield"
    keys: ClassVar[tuple[str, ...]] = ("origin", "spacing", "heights")

    def _check_shape(self):
        object.__setattr__(self, "origin", _array("HeightField", "origin", self.origin, (2,)))
        s = _array("HeightField", "spacing", self.spacing, (2,))
        if np.any(s <= 0):
            raise ObstacleError(f"HeightField.spacing must be positive, got {s.tolist()}")
        object.__setattr__(self, "spacing", s)
        h = _array("HeightField", "heights", self.heights, (-1, -1))
        if min(h.shape) < 2:
            raise ObstacleError(f"HeightField.heights needs at least 2 x 2 samples, got {h.shape}")
        object.__setattr__(self, "heights", h)

    def _shape_params(self):
        return {"origin": self.origin, "spacing": self.spacing, "heights": self.heights}

    def _sdf(self, points, params):
        heights = params["heights"]
        nx, ny = heights.shape
        uv = (points[:, :2] - params["origin"]) / params["spacing"]
        upper = jnp.asarray([nx - 1, ny - 1], points.dtype)
        inside = (uv > 0) & (uv < upper)  # beyond the grid H is constant along that axis
        uv = jnp.clip(uv, 0.0, upper)
        cell = jnp.clip(jnp.floor(uv), 0, upper - 1).astype(jnp.int32)
        a, b = (uv - cell).T
        i, j = cell.T
        h00, h10 = heights[i, j], heights[i + 1, j]
        h01, h11 = heights[i, j + 1], heights[i + 1, j + 1]
        height = (1 - a) * (1 - b) * h00 + a * (1 - b) * h10 + (1 - a) * b * h01 + a * b * h11
        hx = ((1 - b) * (h10 - h00) + b * (h11 - h01)) / params["spacing"][0] * inside[:, 0]
        hy = ((1 - a) * (h01 - h00) + a * (h11 - h10)) / params["spacing"][1] * inside[:, 1]
        slope = jnp.sqrt(1.0 + hx * hx + hy * hy)
        normal = jnp.stack([-hx, -hy, jnp.ones_like(hx)], axis=-1) / slope[:, None]
        return (points[:, 2] - height) / slope, normal


@dataclass(frozen=True, eq=False)
class Moving:
    """An obstacle whose pose follows a prescribed rigid motion (a moving plate, a jaw).

    The wrapped ``obstacle`` is described in its own frame; at time ``t`` that frame is
    rotated by ``R(t)`` and translated by ``p(t)``: a world point ``x`` sits at
    ``R^T (x - p)`` in the obstacle's frame. The obstacle's velocity at ``x`` is
    ``dR/dt R^T (x - p) + dp/dt``, from forward-mode differentiation of ``motion``.

    Attributes:
        obstacle: the shape, with its friction and restitution.
        motion: ``t -> (R (3, 3), p (3,))``, a JAX-traceable function of the time (s),
            differentiable in ``t``. Example (a plate pressing down at 1 cm/s)::

                Moving(Box(half_extents=(0.1, 0.1, 0.01)),
                       lambda t: (jnp.eye(3), jnp.array([0.0, 0.0, 0.1 - 0.01 * t])))

    Params: those of ``obstacle``.

    Raises:
        ObstacleError: ``obstacle`` is not an :class:`Obstacle`, or ``motion(0)`` is not a
            finite rotation and translation of the right shapes.
    """

    obstacle: Obstacle
    motion: Callable

    def __post_init__(self):
        if not isinstance(self.obstacle, Obstacle):
            raise ObstacleError(
                f"Moving.obstacle must be an Obstacle (Plane, Sphere, ...), "
                f"got {type(self.obstacle).__name__}"
            )
        if not callable(self.motion):
            raise ObstacleError(
                "Moving.motion must be a function t -> (rotation (3, 3), translation (3,))"
            )
        try:
            rot, shift = self.motion(jnp.asarray(0.0))
        except Exception as err:  # the user's function failed: say where
            raise ObstacleError(f"Moving.motion(0.0) failed: {err}") from err
        _rotation("Moving", "motion(0)[0]", rot)
        _array("Moving", "motion(0)[1]", shift, (3,))

    @property
    def kind(self) -> str:
        return self.obstacle.kind

    def init_params(self) -> dict:
        """The wrapped obstacle's parameters."""
        return self.obstacle.init_params()

    def pose(self, time) -> tuple[Array, Array]:
        """``(R (3, 3), p (3,))`` at ``time``."""
        rot, shift = self.motion(jnp.asarray(time, jnp.float64))
        return jnp.asarray(rot, jnp.float64), jnp.asarray(shift, jnp.float64)

    def distance(self, points, params, time):
        """As :meth:`Obstacle.distance`, in the moved frame, with the frame's velocity."""
        t = jnp.asarray(time, jnp.float64)
        (rot, shift), (drot, dshift) = jax.jvp(self.pose, (t,), (jnp.ones_like(t),))
        local = (jnp.asarray(points) - shift) @ rot
        phi, n_local, v_local = self.obstacle.distance(local, params, t)
        velocity = local @ drot.T + dshift + v_local @ rot.T
        return phi, n_local @ rot.T, velocity

    def to_dict(self, params: dict | None = None, time: float = 0.0) -> dict:
        """The obstacle's pose at ``time`` in the viewer's format (see :meth:`Obstacle.to_dict`).

        Raises:
            ObstacleError: a height field that is rotated at ``time`` (the format holds
                axis-aligned height fields only).
        """
        out = self.obstacle.to_dict(params, time)
        rot, shift = (np.asarray(a, np.float64) for a in self.pose(time))
        kind = self.obstacle.kind
        if kind == "plane":
            out["point"] = (rot @ out["point"] + shift).tolist()
            out["normal"] = (rot @ out["normal"]).tolist()
        elif kind == "sphere":
            out["center"] = (rot @ out["center"] + shift).tolist()
        elif kind == "box":
            out["center"] = (rot @ out["center"] + shift).tolist()
            out["rotation"] = (rot @ np.asarray(out["rotation"])).tolist()
        elif kind == "capsule":
            out["p0"] = (rot @ out["p0"] + shift).tolist()
            out["p1"] = (rot @ out["p1"] + shift).tolist()
        else:
            if not np.allclose(rot, np.eye(3), atol=1e-12):
                raise ObstacleError(
                    "a rotated height field has no representation in the result format; "
                    "move height fields by translation only"
                )
            out["origin"] = (np.asarray(out["origin"]) + shift[:2]).tolist()
            out["heights"] = (np.asarray(out["heights"]) + shift[2]).tolist()
        return out


#: type name in the result format -> obstacle class
OBSTACLE_TYPES: dict[str, type[Obstacle]] = {
    cls.kind: cls for cls in (Plane, Sphere, Box, Capsule, HeightField)
}


def from_dict(d: dict) -> Obstacle:
    """An obstacle from its result-format dict (the inverse of ``to_dict`` at a fixed time).

    Arguments:
        d: ``{"type": ..., <shape keys>..., optional "mu_s", "mu_k", "restitution"}``.
            Other keys (``"name"``, ...) are ignored.

    Returns:
        The :class:`Obstacle` (a moving obstacle comes back fixed at the written pose).

    Raises:
        ObstacleError: not a dict, an unknown ``type``, missing keys, or bad values.
    """
    if not isinstance(d, dict) or "type" not in d:
        raise ObstacleError(
            f"an obstacle dict needs a 'type' key (one of {sorted(OBSTACLE_TYPES)}), got {d!r}"
        )
    cls = OBSTACLE_TYPES.get(d["type"])
    if cls is None:
        raise ObstacleError(
            f"unknown obstacle type {d['type']!r}; use one of {sorted(OBSTACLE_TYPES)}"
        )
    missing = [k for k in cls.keys if k not in d and not (cls is Box and k == "rotation")]
    if missing:
        raise ObstacleError(f"a {d['type']} obstacle needs {list(cls.keys)}; missing {missing}")
    kwargs = {k: d[k] for k in cls.keys if k in d}
    kwargs.update({k: d[k] for k in ("mu_s", "mu_k", "restitution") if k in d})
    return cls(**kwargs)


def _check_obstacles(obstacles) -> None:
    for i, (ob, params) in enumerate(obstacles):
        if not isinstance(ob, (Obstacle, Moving)):
            raise ObstacleError(
                f"obstacle {i} is a {type(ob).__name__}, not an obstacle; use one of "
                f"{sorted(c.__name__ for c in OBSTACLE_TYPES.values())} or Moving"
            )
        if not isinstance(params, dict) or set(params) != set(ob.init_params()):
            raise ObstacleError(
                f"obstacle {i} ({ob.kind}): its parameters must be the dict made by "
                f"init_params() with keys {sorted(ob.init_params())}"
            )


# --------------------------------------------------------------------------------------
# Splittings
# --------------------------------------------------------------------------------------


class Splitting:
    """A diagonal splitting ``D`` of the PD stiffness ``L = A - M/h^2`` (a small strategy).

    The splitting iteration with projections held fixed is ``x <- P^{-1} (b + (D - L) x)``
    with ``P = M/h^2 + D``; its iteration matrix ``T = P^{-1} (D - L)`` equals the
    velocity form's ``(M + h^2 D)^{-1} h^2 (D - L)``. It converges for every right-hand
    side iff the spectral radius ``rho(T) < 1``; see :func:`splitting_spectral_radius`.
    """

    def diagonal(self, stiffness: Float[Array, "n 1"]) -> Float[Array, "n 1"]:
        """``D`` from ``diag(L)``.

        Arguments:
            stiffness: ``(n, 1)`` the diagonal of ``L`` (non-negative).

        Returns:
            ``(n, 1)`` the diagonal of ``D``.
        """
        raise NotImplementedError


@dataclass(frozen=True)
class Naive(Splitting):
    """``D = 0``: only the mass is inverted. ``rho(T) = h^2 lambda_max(M^-1 L)``, which is far
    above 1 for any stiff body and time step worth simulating (kept for the stability study)."""

    def diagonal(self, stiffness):
        return jnp.zeros_like(stiffness)


@dataclass(frozen=True)
class Diagonal(Splitting):
    """``D = diag(L)`` (Jacobi), the published choice.

    Its iteration matrix has eigenvalues in ``[-3 d/(m/h^2 + d), 1)`` in the worst case
    (``d`` a diagonal entry of ``L``): it converges when ``L <= 2 diag(L)`` (e.g. on meshes
    whose ``L`` is an M-matrix: structured grids with non-obtuse tets) or when the inertia
    dominates, and can diverge otherwise (unstructured meshes, stiff materials, long time
    steps): see :func:`splitting_spectral_radius`.
    """

    def diagonal(self, stiffness):
        return stiffness


@dataclass(frozen=True)
class ScaledDiagonal(Splitting):
    """``D = scale * diag(L)``; with ``scale >= 2`` (the default) convergence is guaranteed.

    **Theorem.** Let ``L = sum_e K_e + Lambda`` with every ``K_e`` symmetric positive
    semi-definite and nonzero only on the (at most 4) vertices of element ``e``, and
    ``Lambda >= 0`` diagonal. (The PD matrix has this form: corotated, volume, damping and
    actuator terms add ``w_e G_e G_e^T`` per tet, mass damping is diagonal; rows of fixed
    vertices are dropped.) Let ``M > 0`` be the lumped masses on the free vertices and
    ``D = 2 diag(L)``. Then every eigenvalue of ``T = (M/h^2 + D)^{-1} (D - L)`` lies in
    ``[-beta, beta]`` with ``beta = max_i 2 d_i / (m_i/h^2 + 2 d_i) < 1``, ``d = diag(L)``.

    *Proof.* (1) ``L <= 4 diag(L)``: for a PSD ``K`` on 4 indices with columns ``k_a`` of
    ``K^{1/2}``, ``u^T K u = |sum_a u_a k_a|^2 <= (sum_a |u_a| |k_a|)^2
    <= 4 sum_a u_a^2 |k_a|^2 = 4 sum_a K_aa u_a^2`` (Cauchy-Schwarz twice); sum over the
    elements, and ``Lambda`` is diagonal. (2) ``P = M/h^2 + D`` is diagonal positive, so
    ``T`` is similar to the symmetric ``P^{-1/2} (D - L) P^{-1/2}``: its eigenvalues are real
    and are Rayleigh quotients ``u^T (D - L) u / u^T P u``. (3) Since ``L >= 0``,
    ``D - L <= D``; by (1), ``D - L >= 2 diag(L) - 4 diag(L) = -D``. Hence
    ``|u^T (D - L) u| <= u^T D u`` and ``|lambda| <= max_u u^T D u / (u^T M u/h^2 + u^T D u)
    <= max_i d'_i / (m_i/h^2 + d'_i) = beta`` with ``d' = 2 d``, and ``beta < 1`` because
    every ``m_i > 0``. QED. The velocity form ``(M + h^2 D)^{-1} h^2 (D - L)`` is the same
    matrix. A larger ``scale`` keeps the bound (``beta`` grows towards 1, so convergence
    slows); for ``scale < 2`` the bound fails for some meshes. For statics (no mass) the
    bound is ``rho < 1`` iff ``L`` is definite, i.e. enough vertices are fixed.

    **The iteration that re-projects.** :class:`ContactPD` runs the local step in every
    iteration, so near a solution its map (contact state fixed) linearises to
    ``I - P^{-1} H`` on the unconstrained directions, ``H`` the step objective's true
    Hessian. PD's quadratic model with the projections of ``x`` majorises the energy and
    touches it at ``x``, so ``H <= A = P - (D - L)``, and by (3) ``P^{-1} A`` has
    eigenvalues in ``[1 - beta, 1 + beta]``. Hence ``P^{-1} H`` has eigenvalues in
    ``(0, 1 + beta]`` wherever ``H`` is positive definite (a strict minimum), and the
    linearised map's in ``[-beta, 1)``: the default converges locally at every strict
    minimum. (Terms that the PD matrix does not contain, such as cavity pressure, are
    outside this argument.) Because ``H`` is smaller than ``A`` (the volume term's PD block
    is isotropic, its Hessian rank one per tet), the published splittings can converge in
    the full iteration where the frozen-projection radius exceeds 1; the
    ``friction-stability`` benchmark measures both. Measured there (6 meshes of 125-1419
    vertices, ``E`` = 1e4-1e7 Pa, ``nu`` = 0.45, ``h`` = 1/1000-1/30 s): frozen-projection
    radius of the default 0.66 to ``1 - 1.5e-8`` (always below ``beta``), of
    :class:`Diagonal` 0.49-1.39 (above 1 on every unstructured mesh once
    ``E h^2`` is large: gmsh cube 1.03, ball 1.06, caterpillar 1.09, quadruped 1.23,
    finger 1.39), of :class:`Naive` 2 to 1.7e8; the plain full iteration diverged with
    Naive in 95 of 96 cases and never with the other two, whose contraction per iteration
    is 0.99-0.9999 for stiff bodies and long steps (hence the acceleration).

    Attributes:
        scale: the factor on ``diag(L)`` (> 0).

    Raises:
        ValueError: a non-positive or non-finite ``scale``.
    """

    scale: float = 2.0

    def __post_init__(self):
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"ScaledDiagonal.scale must be a positive number, got {self.scale!r}")

    def diagonal(self, stiffness):
        return self.scale * stiffness

    @staticmethod
    def bound(mass: np.ndarray, stiffness: np.ndarray, dt: float) -> float:
        """The theorem's ``beta`` for ``scale = 2``: ``max_i 2 d_i / (m_i/h^2 + 2 d_i)``.

        Arguments:
            mass: ``(n,)`` lumped masses of the free vertices, kg.
            stiffness: ``(n,)`` their ``diag(L)``, N/m.
            dt: the time step, s (> 0).

        Returns:
            The bound on the spectral radius, in ``[0, 1)``.
        """
        mass, d = np.asarray(mass, np.float64).ravel(), np.asarray(stiffness, np.float64).ravel()
        return float(np.max(2 * d / (mass / dt**2 + 2 * d)))


def _pd_split(model, prep):
    """Free-vertex ``(mass (f,), L (f, f) scipy CSR, dt)`` of a compiled dynamic scene and its
    prepared data (:func:`softbody.model.prepare`)."""
    h = model.options.dt
    a = model.pattern.to_scipy(np.asarray(prep.data)).tocsr()
    mass = np.asarray(prep.mass)[:, 0]
    free = np.flatnonzero(np.asarray(model.free_mask)[:, 0] > 0)
    stiffness = (a - sparse.diags(mass / h**2))[free][:, free].tocsr()
    return mass[free], stiffness, h


def splitting_spectral_radius(model, prep, splitting: Splitting) -> float:
    """Spectral radius of the splitting iteration matrix with the projections held fixed.

    ``rho((M/h^2 + D)^{-1} (D - L))`` over the free vertices, for the scene's PD matrix
    (with the volume weight of the scene's iteration method: 1 for :class:`ContactPD`).
    Computed on the host with scipy (``eigsh`` on the symmetric similar matrix
    ``P^{-1/2} (D - L) P^{-1/2}``; dense ``eigvalsh`` below 500 vertices).

    Arguments:
        model, prep: a compiled dynamic scene (:func:`softbody.model.build`) and its
            prepared data (:func:`softbody.model.prepare` of its params).
        splitting: the :class:`Splitting`.

    Returns:
        The spectral radius (< 1: the iteration converges).
    """
    mass, stiffness, h = _pd_split(model, prep)
    d = np.asarray(splitting.diagonal(jnp.asarray(stiffness.diagonal())[:, None]))[:, 0]
    return _spectral_radius(mass, stiffness, h, d)


def _spectral_radius(mass, stiffness, h: float, d) -> float:
    """``rho((M/h^2 + diag(d))^{-1} (diag(d) - L))`` for free-vertex ``mass`` (f,), ``L`` (f, f)."""
    scale = 1.0 / np.sqrt(mass / h**2 + d)
    s = sparse.diags(scale) @ (sparse.diags(d) - stiffness) @ sparse.diags(scale)
    if s.shape[0] < 500:
        return float(np.max(np.abs(np.linalg.eigvalsh(s.toarray()))))
    vals = splinalg.eigsh(s.tocsc(), k=1, which="LM", return_eigenvectors=False, tol=1e-10)
    return float(np.max(np.abs(vals)))


# --------------------------------------------------------------------------------------
# The per-vertex contact step
# --------------------------------------------------------------------------------------


def _nearest_obstacle(obstacles, points, time):
    """Per point, the geometry and coefficients of the obstacle it is deepest in (or nearest to).

    Returns ``(phi (n,), normal (n, 3), velocity (n, 3), mu_s (n,), mu_k (n,), e (n,))``.
    """
    rows = []
    for ob, p in obstacles:
        phi, normal, vel = ob.distance(points, p, time)
        ones = jnp.ones_like(phi)
        rows.append((phi, normal, vel, p["mu_s"] * ones, p["mu_k"] * ones, p["restitution"] * ones))
    if len(rows) == 1:
        return rows[0]
    pick = jax.nn.one_hot(
        jnp.argmin(jnp.stack([r[0] for r in rows]), axis=0), len(rows), axis=0
    )  # (k, n)
    return tuple(jnp.einsum("kn,kn...->n...", pick, jnp.stack(column)) for column in zip(*rows))


def _contact_step(y, x_n, v_n, h, frame, free):
    """The per-vertex contact step (positions form): returns the corrected positions.

    ``y`` ``(n, 3)`` are the sweep's positions, ``frame`` the nearest obstacle's
    ``(phi, normal, velocity, mu_s, mu_k, e)`` at ``y``, ``free`` ``(n, 1)``. The impulse on
    vertex ``i`` is ``h P_i (x_i - y_i)``; ``P_i`` scales its normal and tangential parts
    alike, so the cone test needs displacements only.
    """
    phi, normal, vel, mu_s, mu_k, e = frame
    approach = jnp.sum((v_n - vel) * normal, axis=-1)  # < 0: moving into the obstacle
    depth = h * e * jnp.maximum(-approach, 0.0) - phi  # normal correction that reaches the target
    touching = (depth > 0) & (free[:, 0] > 0)
    slip = y - x_n - h * vel  # displacement relative to the obstacle's material
    slip_t = slip - jnp.sum(slip * normal, axis=-1, keepdims=True) * normal
    slip_len = _norm(slip_t)
    stick = slip_len <= mu_s * depth
    slide = -(mu_k * depth)[:, None] * _unit(slip_t, jnp.zeros_like(slip_t))
    correction = depth[:, None] * normal + jnp.where(stick[:, None], -slip_t, slide)
    return y + jnp.where(touching[:, None], correction, 0.0)


# --------------------------------------------------------------------------------------
# The contact solver
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ContactPD(IterationMethod):
    """Implicit-Euler steps with contact and dry friction by the splitting iteration.

    See the module docstring for the scheme; in short, each iteration is PD's local step,
    one sweep of ``(M/h^2 + D) x^{k+1} = b - (L - D) x^k`` and the per-vertex contact
    step, accelerated by Anderson mixing, until ``|grad Phi - r| <= threshold``.

    Attributes:
        splitting: the :class:`Splitting` ``D`` (default :class:`ScaledDiagonal`, whose
            convergence is proved; :class:`Diagonal` and :class:`Naive` for studies).
        history: Anderson history length (0: the plain splitting iteration).
        restart: Anderson restarts when the residual exceeds ``restart`` times the best
            one so far (> 1).
        margin: a step runs ``free_method`` (no contact work) when every free vertex of
            ``x_n`` and ``x_n + h v_n`` is farther than ``margin`` (m) from every obstacle;
            if its result penetrates an obstacle the step is redone with contact.
        free_method: the contact-free iteration (default :class:`~softbody.solvers.LBFGS`).
        adjoint_tol, adjoint_max_iter: relative tolerance and iteration cap of the linear
            solve of the implicit derivative (Anderson-accelerated, like the forward solve).

    The PD matrix is prefactored with the true volume weight (``volume_weight = 1``):
    its diagonal defines ``P``.

    Raises:
        ValueError: a bad attribute (negative history, ``restart <= 1``, ...).
        ObstacleError: (in ``run``) an object in the scene's obstacles that is not an
            obstacle, or parameters that do not match it.
    """

    splitting: Splitting = field(default_factory=ScaledDiagonal)
    history: int = 30
    restart: float = 10.0
    margin: float = 1e-6
    free_method: IterationMethod = field(default_factory=LBFGS)
    adjoint_tol: float = 1e-10
    adjoint_max_iter: int = 20000

    def __post_init__(self):
        if not isinstance(self.splitting, Splitting):
            raise ValueError(
                f"ContactPD.splitting must be a Splitting (Naive(), Diagonal(), ScaledDiagonal()), "
                f"got {self.splitting!r}"
            )
        if not isinstance(self.free_method, IterationMethod) or isinstance(
            self.free_method, ContactPD
        ):
            raise ValueError(
                "ContactPD.free_method must be a contact-free IterationMethod, "
                f"got {self.free_method!r}"
            )
        if int(self.history) != self.history or self.history < 0:
            raise ValueError(f"ContactPD.history must be an integer >= 0, got {self.history!r}")
        if not self.restart > 1:
            raise ValueError(f"ContactPD.restart must exceed 1, got {self.restart!r}")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"ContactPD.margin must be a distance >= 0 (m), got {self.margin!r}")
        if not (self.adjoint_tol > 0 and int(self.adjoint_max_iter) >= 1):
            raise ValueError("ContactPD.adjoint_tol must be > 0 and adjoint_max_iter >= 1")

    def run(
        self, problem: StepProblem, x0, q0, threshold, max_iter: int, unrolled: bool = False
    ) -> Solution:
        """Solve one step with contact; see :class:`~softbody.solvers.IterationMethod`.

        The solve itself is never differentiated: the positions it returns carry the
        implicit derivative of the fixed point (see the module docstring), in forward and
        reverse mode alike, so ``unrolled`` changes nothing here.

        Returns:
            :class:`~softbody.solvers.Solution` with the positions after the last contact
            step (non-penetrating), the rotations of the local step, the iteration and
            local-step counts, and the force residual ``|grad Phi - r|``.

        Raises:
            ObstacleError: the scene's obstacles or their parameters are malformed.
            ValueError: the Naive splitting in a static solve (nothing to invert).
        """
        _check_obstacles(problem.obstacles)
        if not problem.obstacles:
            return self.free_method.run(problem, x0, q0, threshold, max_iter, unrolled)
        if problem.dt == 0 and isinstance(self.splitting, Naive):
            raise ValueError(
                "the Naive splitting has nothing to invert in a static solve (no mass): "
                "use ScaledDiagonal() or Diagonal()"
            )
        fixed_point_map, weight = self._map(problem)
        solve, consts = jax.closure_convert(
            lambda x0, q0: self._solve(
                problem, fixed_point_map, weight, x0, q0, threshold, max_iter
            ),
            x0,
            q0,
        )
        sol = solve(*jax.lax.stop_gradient((x0, q0, *consts)))
        position, consts = _closure_convert(lambda x, q: fixed_point_map(x, q)[0], sol.x, sol.q)
        linear_solve = functools.partial(
            _anderson_linear_solve,
            history=max(int(self.history), 1),
            rtol=self.adjoint_tol,
            max_iter=self.adjoint_max_iter,
        )
        return sol._replace(x=_fixed_point(position, linear_solve, sol.x, sol.q, *consts))

    def _map(self, problem: StepProblem):
        """The fixed-point map ``(x, q) -> (x_new, q_new, |grad Phi(x) - r|)`` and the Anderson
        weights ``sqrt(P)`` ``(n * 3,)`` (zero on fixed vertices)."""
        h = problem.dt
        free = problem.free
        p = self._sweep_diagonal(problem)
        t_end = problem.time + h

        def fixed_point_map(x, q):
            _, g, q = problem.evaluate(x, q)
            y = x - g / p  # one splitting sweep
            frame = _nearest_obstacle(problem.obstacles, y, t_end)
            x_new = jnp.where(
                free > 0, _contact_step(y, problem.x_n, problem.v_n, h, frame, free), x
            )
            return x_new, q, _norm((p * (x_new - x)).ravel())  # = |grad Phi(x) - r|

        return fixed_point_map, jnp.broadcast_to(jnp.sqrt(p) * free, problem.x_n.shape).ravel()

    def _sweep_diagonal(self, problem: StepProblem):
        """``P = M/h^2 + D`` ``(n, 1)`` of the splitting sweep (1 on fixed vertices, which never
        move)."""
        h = problem.dt
        inertia = problem.mass / h**2 if h > 0 else jnp.zeros_like(problem.mass)
        stiffness = jnp.maximum(problem.diagonal - inertia, 0.0)
        return jnp.where(problem.free > 0, inertia + self.splitting.diagonal(stiffness), 1.0)

    def _solve(
        self, problem: StepProblem, fixed_point_map, weight, x0, q0, threshold, max_iter: int
    ) -> Solution:
        """The forward solve: the free-step shortcut, else the splitting iteration."""

        def contact():
            return self._iterate(fixed_point_map, weight, x0, q0, threshold, max_iter)

        free = problem.free[:, 0] > 0
        t_end = problem.time + problem.dt

        def clearance(x, t):
            phi = _nearest_obstacle(problem.obstacles, x, t)[0]
            return jnp.min(jnp.where(free, phi, jnp.inf))

        near = (
            jnp.minimum(clearance(problem.x_n, problem.time), clearance(x0, t_end)) <= self.margin
        )

        def free_step():  # the free method sees no obstacles: it is contact-free by definition
            sol = self.free_method.run(problem._replace(obstacles=()), x0, q0, threshold, max_iter)

            def redo():
                again = contact()
                return again._replace(evaluations=again.evaluations + sol.evaluations)

            return jax.lax.cond(clearance(sol.x, t_end) < 0, redo, lambda: sol)

        return jax.lax.cond(near, contact, free_step)

    def _iterate(self, fixed_point_map, weight, x0, q0, threshold, max_iter: int) -> Solution:
        """Anderson-accelerated fixed-point iteration; returns the best iterate's map output."""
        zero = jnp.asarray(0)
        inf = jnp.asarray(jnp.inf, x0.dtype)

        def body(c):
            x, q, k, best_x, best_q, best_r, _, hist = c
            gx, q_new, r = fixed_point_map(x, q)
            better = r < best_r
            best_x = jnp.where(better, gx, best_x)
            best_q = jnp.where(better, q_new, best_q)
            restart = r > self.restart * best_r
            best_r = jnp.where(better, r, best_r)  # a diverging iteration (NaN) keeps the best
            x_next, hist = _anderson_mix(x, gx, weight, hist, restart, self.history)
            return x_next, q_new, k + 1, best_x, best_q, best_r, r, hist

        init = (x0, q0, zero, x0, q0, inf, inf, _anderson_init(self.history, x0.size, x0.dtype))
        out = jax.lax.while_loop(lambda c: (c[6] > threshold) & (c[2] < max_iter), body, init)
        _, _, k, best_x, best_q, best_r, _, _ = out
        return Solution(best_x, best_q, k, k, best_r)


def _anderson_init(m: int, size: int, dtype):
    """Empty Anderson history.

    ``(dR (m, N), dG (m, N), dR dR^T (m, m), r (N,), g (N,), count ())``.
    """
    return (
        jnp.zeros((m, size), dtype),
        jnp.zeros((m, size), dtype),
        jnp.zeros((m, m), dtype),
        jnp.zeros(size, dtype),
        jnp.zeros(size, dtype),
        jnp.asarray(0),
    )


def _anderson_mix(x, gx, weight, hist, restart, m: int):
    """One Anderson (type II) update from the pair ``(x, G(x))``: returns ``(x_next, hist)``.

    The last ``m`` differences of residuals ``weight * (G(x) - x)`` and of map outputs give
    the mixing coefficients by regularised least squares (their Gram matrix is updated one
    row per iteration); ``restart`` clears the history (the next iterate is then the plain
    ``G(x)``). ``m = 0`` is the plain iteration.
    """
    if m == 0:
        return gx, hist
    d_r, d_g, gram, prev_r, prev_g, count = hist
    r = weight * (gx - x).ravel()
    g = gx.ravel()
    slot = jnp.maximum(count - 1, 0) % m
    push = count >= 1
    d_r = jnp.where(push, d_r.at[slot].set(r - prev_r), d_r)
    d_g = jnp.where(push, d_g.at[slot].set(g - prev_g), d_g)
    row = d_r @ d_r[slot]
    gram = jnp.where(push, gram.at[slot, :].set(row).at[:, slot].set(row), gram)
    count = jnp.where(restart, 1, count + 1)
    valid = (jnp.arange(m) < jnp.minimum(count - 1, m)).astype(r.dtype)
    gram_valid = gram * valid[:, None] * valid[None, :]
    reg = 1e-10 * jnp.trace(gram_valid) + jnp.finfo(r.dtype).tiny
    gamma = jnp.linalg.solve(gram_valid + jnp.diag(reg + (1.0 - valid)), valid * (d_r @ r))
    x_next = (g - gamma @ d_g).reshape(x.shape)
    return x_next, (d_r, d_g, gram, r, g, count)


def _anderson_linear_solve(matvec, b, *, history: int, rtol: float, max_iter: int):
    """Solve ``matvec(u) = b``, ``matvec = I - J``, ``rho(J) < 1``: Anderson on ``u = J u + b``."""
    bnorm = _norm(b.ravel())
    threshold = rtol * bnorm

    def body(c):
        u, k, _, hist = c
        tu = u - matvec(u) + b
        residual = _norm((tu - u).ravel())
        u, hist = _anderson_mix(u, tu, jnp.ones(u.size, u.dtype), hist, jnp.asarray(False), history)
        return u, k + 1, residual, hist

    init = (
        b,
        jnp.asarray(0),
        jnp.asarray(jnp.inf, b.dtype),
        _anderson_init(history, b.size, b.dtype),
    )
    u, *_ = jax.lax.while_loop(lambda c: (c[2] > threshold) & (c[1] < max_iter), body, init)
    return u


def _closure_convert(fun: Callable, *args):
    """``jax.closure_convert`` that hoists every traced value ``fun`` closes over.

    ``jax.closure_convert`` leaves traced values that cannot carry a tangent (integers,
    such as a host factorisation's handle inside the skeleton's condensation) in the
    closure; passed to :func:`_fixed_point` as a non-differentiable argument they then
    leak out of their trace. Here they become arguments too (their tangents are float0).

    Returns:
        ``(converted, hoisted)``: ``converted(*args, *hoisted)`` computes ``fun(*args)``.
    """
    closed, out_shape = jax.make_jaxpr(fun, return_shape=True)(*args)
    traced = [isinstance(c, jax.core.Tracer) for c in closed.consts]
    hoisted = [c for c, t in zip(closed.consts, traced) if t]
    kept = [c for c, t in zip(closed.consts, traced) if not t]
    n_args = len(args)
    out_tree = jax.tree.structure(out_shape)

    def converted(*args_and_hoisted):
        given, lifted = iter(args_and_hoisted[n_args:]), iter(kept)
        consts = [next(given) if t else next(lifted) for t in traced]
        out = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree.leaves(args_and_hoisted[:n_args]))
        return jax.tree.unflatten(out_tree, out)

    return converted, hoisted


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _fixed_point(position, linear_solve, x, q, *consts):
    """``x``, a fixed point of ``position(., q, *consts)``, differentiated implicitly.

    The tangent solves ``(I - dF/dx) dx = dF/dconsts dconsts`` at ``x`` with the active set
    (contact, stick, slide choices) of ``x``; :func:`jax.lax.custom_linear_solve` makes the
    rule transposable, so reverse mode solves the transposed system.
    """
    return x


@_fixed_point.defjvp
def _fixed_point_jvp(position, linear_solve, primals, tangents):
    x, q, *consts = primals
    _, rhs = jax.jvp(lambda *c: position(x, q, *c), tuple(consts), tuple(tangents[2:]))

    def matvec(u):
        return u - jax.jvp(lambda y: position(y, q, *consts), (x,), (u,))[1]

    dx = jax.lax.custom_linear_solve(matvec, rhs, linear_solve, transpose_solve=linear_solve)
    return x, dx

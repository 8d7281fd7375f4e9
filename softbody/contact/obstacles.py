"""Obstacles as signed distance functions, with friction and restitution.

Each obstacle is a small frozen class (static: it fixes the code that runs) with a
parameter pytree (traced and differentiable: pose, friction, restitution) made by
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

**Parameters.** ``init_params()`` returns the shape's :class:`ObstacleParams` (an equinox
module: :class:`PlaneParams`, :class:`SphereParams`, :class:`BoxParams`,
:class:`CapsuleParams`, :class:`HeightFieldParams`) with the friction fields ``mu_s``,
``mu_k``, ``restitution`` and the shape's pose fields, float64 arrays. A scene's are
``params.obstacles``, one per obstacle, so ``params.obstacles[0].mu_k`` reads a
coefficient and either of::

    plane = params.obstacles[0].replace(mu_k=0.3, normal=n)
    params = eqx.tree_at(lambda p: p.obstacles[0], params, plane)
    params = eqx.tree_at(lambda p: p.obstacles[0].mu_k, params, jnp.asarray(0.3))

changes it (the contact solver, :mod:`softbody.contact`, uses them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from softbody._interfaces import Frame, Rows

__all__ = [
    "Box",
    "BoxParams",
    "Capsule",
    "CapsuleParams",
    "HeightField",
    "HeightFieldParams",
    "Moving",
    "Obstacle",
    "ObstacleError",
    "ObstacleParams",
    "ObstacleRows",
    "Plane",
    "PlaneParams",
    "Sphere",
    "SphereParams",
    "from_dict",
    "nearest_obstacle",
]

#: the parameters every obstacle has, besides its shape's
_FRICTION = ("mu_s", "mu_k", "restitution")


class ObstacleError(ValueError):
    """An obstacle is invalid; the message names the problem and the fix."""


# --------------------------------------------------------------------------------------
# Guarded vector helpers (finite values and derivatives at zero length)
# --------------------------------------------------------------------------------------


def norm(v: Array, keepdims: bool = False) -> Array:
    """Euclidean norm over the last axis, with a zero (not NaN) derivative at 0; NaN stays NaN.

    Arguments:
        v: ``(..., k)`` vectors.
        keepdims: keep the last axis (length 1).

    Returns:
        ``(...)`` (or ``(..., 1)``) lengths.
    """
    sq = jnp.sum(v * v, axis=-1, keepdims=keepdims)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), sq)


def unit(v: Array, fallback: Array) -> Array:
    """``v / |v|`` over the last axis, ``fallback`` where ``v`` is zero.

    Arguments:
        v: ``(..., k)`` vectors.
        fallback: the value where ``|v| = 0`` (broadcast against ``v``).

    Returns:
        ``(..., k)`` unit vectors (finite, with finite derivatives, at zero length).
    """
    length = norm(v, keepdims=True)
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


def check_motion(motion, owner: str, error: type[Exception] = None) -> None:
    """Check a prescribed rigid motion ``t -> (R (3, 3), p (3,))`` by calling it at ``t = 0``
    (a :class:`Moving` obstacle's, a moving clamp's in :func:`softbody.model.build`).

    Arguments:
        motion: the function; owner: what it belongs to, for the messages; error: the
            exception class to raise (default :class:`ObstacleError`).

    Raises:
        error: ``motion`` is not callable, fails at ``t = 0``, or does not return a finite
            rotation and translation of the right shapes.
    """
    error = error or ObstacleError
    if not callable(motion):
        raise error(f"{owner}: motion must be a function t -> (rotation (3, 3), translation (3,)), got "
                    f"{type(motion).__name__}")
    try:
        rot, shift = motion(jnp.asarray(0.0))
        rot, shift = np.asarray(rot, np.float64), np.asarray(shift, np.float64)
    except Exception as err:  # the user's function failed: say where
        raise error(f"{owner}: motion(0.0) failed ({err}); it must return (rotation (3, 3), translation (3,))") \
            from err
    finite = bool(np.all(np.isfinite(rot)) and np.all(np.isfinite(shift)))
    if rot.shape != (3, 3) or shift.shape != (3,) or not finite:
        raise error(f"{owner}: motion(0.0) must return a finite rotation (3, 3) and translation (3,), got shapes "
                    f"{rot.shape} and {shift.shape}{'' if finite else ' with non-finite values'}")
    if not _is_rotation(rot):
        raise error(f"{owner}: motion(0.0)[0] is not a rotation (R^T R = I, det R = 1), got {rot.tolist()}")


def _is_rotation(r: np.ndarray) -> bool:
    """``R^T R = I`` (to 1e-6) and ``det R > 0`` for a ``(3, 3)`` array."""
    return bool(np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0)


def _rotation(owner: str, name: str, value) -> np.ndarray:
    r = _array(owner, name, value, (3, 3))
    if not _is_rotation(r):
        raise ObstacleError(
            f"{owner}.{name} must be a rotation matrix (orthonormal, det +1), got {r.tolist()}"
        )
    return r


# --------------------------------------------------------------------------------------
# Parameter pytrees
# --------------------------------------------------------------------------------------


class ObstacleParams(eqx.Module):
    """An obstacle's traced parameters: friction and restitution (each shape adds its pose).

    Attributes:
        mu_s: ``()`` static friction coefficient.
        mu_k: ``()`` kinetic friction coefficient.
        restitution: ``()`` coefficient of restitution.

    Made by :meth:`Obstacle.init_params` as the shape's subclass; the values are used as
    given (not re-checked inside ``jit``).
    """

    mu_s: Array
    mu_k: Array
    restitution: Array

    def replace(self, **changes) -> ObstacleParams:
        """A copy with some fields replaced, e.g. ``params.replace(mu_k=0.3)``.

        Arguments:
            changes: field name -> new value (arrays or numbers; taken as given).

        Returns:
            The parameters of the same type with those fields changed.

        Raises:
            ObstacleError: an unknown field name.
        """
        fields = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(changes) - set(fields))
        if unknown:
            raise ObstacleError(
                f"{type(self).__name__} has no field(s) {unknown}; its fields are {fields}"
            )
        return dataclasses.replace(self, **changes)


class PlaneParams(ObstacleParams):
    """A :class:`Plane`'s parameters: ``point (3,)``, ``normal (3,)`` and the friction fields."""

    point: Array
    normal: Array


class SphereParams(ObstacleParams):
    """A :class:`Sphere`'s parameters: ``center (3,)``, ``radius ()`` and the friction fields."""

    center: Array
    radius: Array


class BoxParams(ObstacleParams):
    """A :class:`Box`'s parameters: ``center (3,)``, ``half_extents (3,)``, ``rotation (3, 3)``
    and the friction fields."""

    center: Array
    half_extents: Array
    rotation: Array


class CapsuleParams(ObstacleParams):
    """A :class:`Capsule`'s parameters: ``p0 (3,)``, ``p1 (3,)``, ``radius ()`` and the
    friction fields."""

    p0: Array
    p1: Array
    radius: Array


class HeightFieldParams(ObstacleParams):
    """A :class:`HeightField`'s parameters: ``origin (2,)``, ``spacing (2,)``,
    ``heights (nx, ny)`` and the friction fields."""

    origin: Array
    spacing: Array
    heights: Array


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
    #: the shape's parameter pytree (the friction fields and the fields ``keys``)
    params_type: ClassVar[type[ObstacleParams]] = ObstacleParams

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

    def init_params(self) -> ObstacleParams:
        """The obstacle's parameter pytree, float64 arrays.

        Returns:
            The shape's :class:`ObstacleParams` (``mu_s ()``, ``mu_k ()``,
            ``restitution ()`` and the shape fields named as in
            :data:`softbody.io.OBSTACLE_KEYS`; see each shape).
        """
        return self.params_type(
            **{k: jnp.asarray(getattr(self, k), jnp.float64) for k in _FRICTION + self.keys}
        )

    def distance(
        self, points: Float[Array, "n 3"], params: ObstacleParams, time
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

    def _sdf(self, points: Array, params: ObstacleParams) -> tuple[Array, Array]:
        raise NotImplementedError

    def to_dict(self, params: ObstacleParams | None = None, time: float = 0.0) -> dict:
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
            out[key] = np.asarray(getattr(p, key), np.float64).tolist()
        for key in _FRICTION:
            out[key] = float(getattr(p, key))
        return out


@dataclass(frozen=True, eq=False)
class Plane(Obstacle):
    """A half-space: the obstacle fills the side of the plane opposite to ``normal``.

    Attributes:
        point: ``(3,)`` a point on the plane, m.
        normal: ``(3,)`` the outward normal (normalised here); tilt it for an incline.

    Params: :class:`PlaneParams`, ``point (3,)``, ``normal (3,)`` (normalised again inside
    :meth:`distance`, so it may be optimised freely).
    """

    point: tuple = (0.0, 0.0, 0.0)
    normal: tuple = (0.0, 0.0, 1.0)

    kind: ClassVar[str] = "plane"
    params_type: ClassVar[type[ObstacleParams]] = PlaneParams
    keys: ClassVar[tuple[str, ...]] = ("point", "normal")

    def _check_shape(self):
        object.__setattr__(self, "point", _array("Plane", "point", self.point, (3,)))
        object.__setattr__(self, "normal", _direction("Plane", "normal", self.normal))


    def _sdf(self, points, params):
        n = unit(params.normal, jnp.asarray(_UP))
        phi = (points - params.point) @ n
        return phi, jnp.broadcast_to(n, points.shape)


@dataclass(frozen=True, eq=False)
class Sphere(Obstacle):
    """A ball of ``radius`` about ``center``.

    Params: :class:`SphereParams`, ``center (3,)``, ``radius ()``.
    """

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 1.0

    kind: ClassVar[str] = "sphere"
    params_type: ClassVar[type[ObstacleParams]] = SphereParams
    keys: ClassVar[tuple[str, ...]] = ("center", "radius")

    def _check_shape(self):
        object.__setattr__(self, "center", _array("Sphere", "center", self.center, (3,)))
        object.__setattr__(self, "radius", _positive("Sphere", "radius", self.radius))


    def _sdf(self, points, params):
        d = points - params.center
        return norm(d) - params.radius, unit(d, jnp.asarray(_UP))


@dataclass(frozen=True, eq=False)
class Box(Obstacle):
    """An oriented box.

    Attributes:
        center: ``(3,)`` m.
        half_extents: ``(3,)`` positive half edge lengths along the box's axes, m.
        rotation: ``(3, 3)`` rotation whose columns are the box's axes in world
            coordinates (default identity).

    Params: :class:`BoxParams`, ``center (3,)``, ``half_extents (3,)``, ``rotation (3, 3)``.
    """

    center: tuple = (0.0, 0.0, 0.0)
    half_extents: tuple = (0.5, 0.5, 0.5)
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    kind: ClassVar[str] = "box"
    params_type: ClassVar[type[ObstacleParams]] = BoxParams
    keys: ClassVar[tuple[str, ...]] = ("center", "half_extents", "rotation")

    def _check_shape(self):
        object.__setattr__(self, "center", _array("Box", "center", self.center, (3,)))
        e = _array("Box", "half_extents", self.half_extents, (3,))
        if np.any(e <= 0):
            raise ObstacleError(f"Box.half_extents must be positive, got {e.tolist()}")
        object.__setattr__(self, "half_extents", e)
        object.__setattr__(self, "rotation", _rotation("Box", "rotation", self.rotation))


    def _sdf(self, points, params):
        rot = params.rotation
        local = (points - params.center) @ rot  # R^T (x - c) for row vectors
        sign = jnp.where(local >= 0, 1.0, -1.0)
        q = jnp.abs(local) - params.half_extents
        outside = jnp.maximum(q, 0.0)
        out_len = norm(outside)
        inside = jnp.max(q, axis=-1)
        phi = out_len + jnp.minimum(inside, 0.0)
        face = jax.nn.one_hot(jnp.argmax(q, axis=-1), 3, dtype=points.dtype) * sign
        n_local = jnp.where((out_len > 0)[:, None], unit(outside * sign, face), face)
        return phi, n_local @ rot.T


@dataclass(frozen=True, eq=False)
class Capsule(Obstacle):
    """The points within ``radius`` of the segment ``p0``-``p1``.

    Params: :class:`CapsuleParams`, ``p0 (3,)``, ``p1 (3,)``, ``radius ()``.
    """

    p0: tuple = (0.0, 0.0, 0.0)
    p1: tuple = (1.0, 0.0, 0.0)
    radius: float = 0.1

    kind: ClassVar[str] = "capsule"
    params_type: ClassVar[type[ObstacleParams]] = CapsuleParams
    keys: ClassVar[tuple[str, ...]] = ("p0", "p1", "radius")

    def _check_shape(self):
        object.__setattr__(self, "p0", _array("Capsule", "p0", self.p0, (3,)))
        object.__setattr__(self, "p1", _array("Capsule", "p1", self.p1, (3,)))
        object.__setattr__(self, "radius", _positive("Capsule", "radius", self.radius))


    def _sdf(self, points, params):
        p0, axis = params.p0, params.p1 - params.p0
        length2 = jnp.sum(axis * axis)
        t = jnp.clip((points - p0) @ axis / jnp.where(length2 > 0, length2, 1.0), 0.0, 1.0)
        d = points - (p0 + t[:, None] * axis)
        return norm(d) - params.radius, unit(d, jnp.asarray(_UP))


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

    Params: :class:`HeightFieldParams`, ``origin (2,)``, ``spacing (2,)``,
    ``heights (nx, ny)``.
    """

    origin: tuple = (0.0, 0.0)
    spacing: tuple = (1.0, 1.0)
    heights: tuple = ((0.0, 0.0), (0.0, 0.0))

    kind: ClassVar[str] = "heightfield"
    params_type: ClassVar[type[ObstacleParams]] = HeightFieldParams
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


    def _sdf(self, points, params):
        heights = params.heights
        nx, ny = heights.shape
        uv = (points[:, :2] - params.origin) / params.spacing
        upper = jnp.asarray([nx - 1, ny - 1], points.dtype)
        inside = (uv > 0) & (uv < upper)  # beyond the grid H is constant along that axis
        uv = jnp.clip(uv, 0.0, upper)
        cell = jnp.clip(jnp.floor(uv), 0, upper - 1).astype(jnp.int32)
        a, b = (uv - cell).T
        i, j = cell.T
        h00, h10 = heights[i, j], heights[i + 1, j]
        h01, h11 = heights[i, j + 1], heights[i + 1, j + 1]
        height = (1 - a) * (1 - b) * h00 + a * (1 - b) * h10 + (1 - a) * b * h01 + a * b * h11
        hx = ((1 - b) * (h10 - h00) + b * (h11 - h01)) / params.spacing[0] * inside[:, 0]
        hy = ((1 - a) * (h01 - h00) + a * (h11 - h10)) / params.spacing[1] * inside[:, 1]
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
        check_motion(self.motion, "Moving")

    @property
    def kind(self) -> str:
        return self.obstacle.kind

    @property
    def params_type(self) -> type[ObstacleParams]:
        """The wrapped obstacle's parameter type."""
        return self.obstacle.params_type

    def init_params(self) -> ObstacleParams:
        """The wrapped obstacle's parameters (see :meth:`Obstacle.init_params`)."""
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

    def to_dict(self, params: ObstacleParams | None = None, time: float = 0.0) -> dict:
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
    kwargs.update({k: d[k] for k in _FRICTION if k in d})
    return cls(**kwargs)


def check_obstacles(obstacles) -> None:
    """Check a scene's ``((obstacle, params), ...)`` pairs (eagerly, before tracing a solve).

    Arguments:
        obstacles: ``((obstacle, obstacle_params), ...)`` as in
            :class:`softbody.solvers.StepProblem`.

    Raises:
        ObstacleError: an object that is not an obstacle, or parameters that are not the
            obstacle's :class:`ObstacleParams` type.
    """
    for i, (ob, params) in enumerate(obstacles):
        if not isinstance(ob, (Obstacle, Moving)):
            raise ObstacleError(
                f"obstacle {i} is a {type(ob).__name__}, not an obstacle; use one of "
                f"{sorted(c.__name__ for c in OBSTACLE_TYPES.values())} or Moving"
            )
        if not isinstance(params, ob.params_type):
            fields = [f.name for f in dataclasses.fields(ob.params_type)]
            raise ObstacleError(
                f"obstacle {i} ({ob.kind}): its parameters must be the "
                f"{ob.params_type.__name__} made by init_params() (fields {fields}), got a "
                f"{type(params).__name__}; change them with .replace(...) or eqx.tree_at"
            )



def nearest_obstacle(obstacles, points, time) -> Frame:
    """Per point, the frame of the obstacle it is deepest in (or nearest to).

    Arguments:
        obstacles: ``((obstacle, obstacle_params), ...)``, at least one.
        points: ``(m, 3)``; time: s.

    Returns:
        A :class:`~softbody._interfaces.Frame` of ``m`` rows.
    """
    frames = []
    for ob, p in obstacles:
        phi, normal, vel = ob.distance(points, p, time)
        ones = jnp.ones_like(phi)
        frames.append(Frame(phi, normal, vel, p.mu_s * ones, p.mu_k * ones, p.restitution * ones))
    return Frame.deepest(frames)


@dataclass(frozen=True)
class ObstacleRows(Rows):
    """The contact rows of a scene's obstacles: one row on every vertex, against the
    obstacle it is deepest in (or nearest to). Its parameters are ``params.obstacles``.

    Attributes:
        obstacles: the scene's obstacles (a tuple, at least one).
    """

    obstacles: tuple

    def init_params(self):
        return tuple(ob.init_params() for ob in self.obstacles)

    def check(self, params) -> None:
        """Raises :class:`ObstacleError` where an object is no obstacle or its parameters
        are not its :class:`ObstacleParams`."""
        check_obstacles(tuple(zip(self.obstacles, params)))

    def frame(self, points, index, params, time) -> Frame:
        return nearest_obstacle(tuple(zip(self.obstacles, params)), points, time)

"""Composable losses of a simulated trajectory and the controls that drove it.

Every loss is a small callable ``loss(traj, controls) -> scalar`` (a JAX float), where
``traj`` is a :class:`~softbody.simulate.Trajectory` (positions ``traj.x`` of shape
``(T + 1, n, 3)``, the first row the initial state) and ``controls`` the ``(T, C)``
activations actually applied. Losses that do not look at one of the two ignore it.
Losses combine with ``+`` and scale with ``*``::

    loss = TargetPosition(model, "tip", target=(0.08, 0, -0.03)) + 1e-3 * Effort()

Region names are resolved when a loss is made, so a typo fails at once with the list of
regions the mesh has. Centroids are volume-weighted: each vertex weighs the lumped rest
volume around it (a quarter of each adjacent tet's volume), so a region's centroid does
not depend on how finely parts of it are meshed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from softbody.model import Model
from softbody.simulate import Trajectory

from .errors import ControlError

Array = jax.Array

__all__ = [
    "Loss", "Sum", "Scaled", "TargetPosition", "ForwardDistance", "Tracking", "Effort",
    "Smoothness", "region_vertices", "centroid_weights",
]


def region_vertices(model: Model, vertices: str | Sequence[int] | None) -> np.ndarray:
    """Vertex indices of a region name, an index list, or every vertex (``None``).

    Arguments:
        model: the compiled scene.
        vertices: a region name of ``model.mesh``, a sequence of vertex indices, or ``None``.

    Returns:
        ``(k,)`` int array of vertex indices, ``k >= 1``.

    Raises:
        ControlError: an unknown region (naming the regions that exist), an empty
            selection, or indices out of range.
    """
    n = model.n_vertices
    if vertices is None:
        return np.arange(n)
    if isinstance(vertices, str):
        if vertices not in model.mesh.regions:
            raise ControlError(f"unknown region {vertices!r}; the mesh has regions {sorted(model.mesh.regions)}")
        idx = np.asarray(model.mesh.regions[vertices].vertices, np.int64)
        if idx.size == 0:
            raise ControlError(f"region {vertices!r} has no vertices")
        return idx
    idx = np.asarray(vertices, np.int64).ravel()
    if idx.size == 0:
        raise ControlError("the vertex selection is empty")
    if idx.min() < 0 or idx.max() >= n:
        raise ControlError(f"vertex indices must lie in [0, {n}), got [{idx.min()}, {idx.max()}]")
    return idx


def centroid_weights(model: Model, idx: np.ndarray) -> np.ndarray:
    """Normalised lumped rest-volume weights ``(k,)`` of the vertices ``idx`` (they sum to 1)."""
    tets = np.asarray(model.mesh.tets)
    vol = np.zeros(model.n_vertices)
    np.add.at(vol, tets, np.repeat(model.mesh.volumes()[:, None] / 4.0, 4, axis=1))
    w = vol[idx]
    if not w.sum() > 0:  # vertices that belong to no tet: fall back to the plain mean
        w = np.ones(len(idx))
    return w / w.sum()


def _centroids(x: Array, idx: np.ndarray, w: np.ndarray) -> Array:
    """Centroids ``(..., 3)`` of the vertices ``idx`` with weights ``w`` in ``x`` ``(..., n, 3)``."""
    return jnp.einsum("...ki,k->...i", x[..., idx, :], jnp.asarray(w))


def _vector3(value, what: str) -> np.ndarray:
    v = np.asarray(value, np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ControlError(f"{what} must be 3 finite numbers, got {value!r}")
    return v


class Loss:
    """Base class: ``loss(traj, controls) -> scalar``; supports ``+`` and scalar ``*``."""

    def __call__(self, traj: Trajectory, controls: Array) -> Array:
        raise NotImplementedError

    def __add__(self, other: "Loss") -> "Sum":
        if not isinstance(other, Loss):
            return NotImplemented
        return Sum((self, other))

    def __mul__(self, factor: float) -> "Scaled":
        if isinstance(factor, Loss) or not np.isscalar(factor) or not np.isfinite(factor):
            return NotImplemented
        return Scaled(self, float(factor))

    __rmul__ = __mul__


@dataclass(frozen=True, eq=False)
class Sum(Loss):
    """The sum of several losses."""

    terms: tuple[Loss, ...]

    def __add__(self, other):
        if not isinstance(other, Loss):
            return NotImplemented
        return Sum(self.terms + (other.terms if isinstance(other, Sum) else (other,)))

    def __call__(self, traj, controls):
        return sum(term(traj, controls) for term in self.terms)


@dataclass(frozen=True, eq=False)
class Scaled(Loss):
    """A loss times a constant factor."""

    term: Loss
    factor: float

    def __call__(self, traj, controls):
        return self.factor * self.term(traj, controls)


@dataclass(frozen=True, eq=False, init=False)
class TargetPosition(Loss):
    """Squared distance (m^2) of a region's centroid to a target point.

    ``over="final"``: ``|c_T - target|^2`` on the last frame; ``over="all"``: the mean of
    ``|c_k - target|^2`` over frames ``1..T``; ``over=int`` (``k > 0``): the mean over the
    last ``k`` frames (reach the target and stay there). ``axes`` restricts the distance
    to some coordinates (e.g. ``(0, 2)`` for the x-z plane).

    Arguments:
        model: the compiled scene.
        region: a region name, vertex indices, or ``None`` for the whole body.
        target: ``(3,)`` target point, m.
        over: ``"final"``, ``"all"`` or a number of final frames.
        axes: the coordinates that count.

    Raises:
        ControlError: unknown region, bad target, ``over`` or ``axes``.
    """

    idx: np.ndarray
    weights: np.ndarray
    target: np.ndarray
    over: str | int
    axes: tuple[int, ...]

    def __init__(self, model: Model, region: str | Sequence[int] | None, target, *,
                 over: str | int = "final", axes: Sequence[int] = (0, 1, 2)):
        idx = region_vertices(model, region)
        if not (over in ("final", "all") or (isinstance(over, (int, np.integer)) and not isinstance(over, bool)
                                              and over > 0)):
            raise ControlError(f"over must be 'final', 'all' or a positive number of frames, got {over!r}")
        axes = tuple(int(a) for a in axes)
        if not axes or len(set(axes)) != len(axes) or not set(axes) <= {0, 1, 2}:
            raise ControlError(f"axes must be distinct coordinates among 0, 1, 2, got {axes}")
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "weights", centroid_weights(model, idx))
        object.__setattr__(self, "target", _vector3(target, "target"))
        object.__setattr__(self, "over", over)
        object.__setattr__(self, "axes", axes)

    def centroid(self, traj: Trajectory) -> Array:
        """The region's centroid per frame, ``(T + 1, 3)``."""
        return _centroids(traj.x, self.idx, self.weights)

    def __call__(self, traj, controls):
        c = self.centroid(traj)
        if self.over == "final":
            c = c[-1:]
        elif self.over == "all":
            c = c[1:]
        else:
            if self.over > c.shape[0] - 1:
                raise ControlError(f"over={self.over} frames but the trajectory has only {c.shape[0] - 1} steps")
            c = c[-self.over:]
        d = (c - jnp.asarray(self.target))[:, jnp.asarray(self.axes)]
        return jnp.mean(jnp.sum(d * d, axis=-1))


@dataclass(frozen=True, eq=False, init=False)
class ForwardDistance(Loss):
    """Minus the distance (m) a region's centroid travels along an axis.

    The loss is ``-(c_T - c_0) . axis`` (minimising it moves the body forward);
    :meth:`travelled` gives the distance itself.

    Arguments:
        model: the compiled scene.
        axis: ``(3,)`` the forward direction (normalised here).
        region: a region name, vertex indices, or ``None`` (the whole body).

    Raises:
        ControlError: unknown region or a zero axis.
    """

    idx: np.ndarray
    weights: np.ndarray
    axis: np.ndarray

    def __init__(self, model: Model, axis=(1.0, 0.0, 0.0), region: str | Sequence[int] | None = None):
        axis = _vector3(axis, "axis")
        if not np.linalg.norm(axis) > 0:
            raise ControlError("axis must be a nonzero direction")
        idx = region_vertices(model, region)
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "weights", centroid_weights(model, idx))
        object.__setattr__(self, "axis", axis / np.linalg.norm(axis))

    def travelled(self, traj: Trajectory) -> Array:
        """Signed distance (m) of the centroid's final displacement along ``axis``."""
        c = _centroids(traj.x[jnp.asarray([0, -1])], self.idx, self.weights)
        return jnp.dot(c[1] - c[0], jnp.asarray(self.axis))

    def __call__(self, traj, controls):
        return -self.travelled(traj)


@dataclass(frozen=True, eq=False, init=False)
class Tracking(Loss):
    """Mean squared deviation (m^2) of vertices from a reference trajectory.

    ``mean over frames 1..T and the selected vertices of |x_k - x_ref,k|^2`` (frame 0 is
    the given initial state and is not compared).

    Arguments:
        model: the compiled scene.
        reference: ``(T + 1, k, 3)`` reference positions of the selected vertices.
        vertices: a region name, vertex indices (``k`` of them), or ``None`` (all ``n``).

    Raises:
        ControlError: unknown region, or a reference whose shape does not match the
            selection (at construction) or the trajectory's length (when called).
    """

    idx: np.ndarray
    reference: np.ndarray

    def __init__(self, model: Model, reference, vertices: str | Sequence[int] | None = None):
        idx = region_vertices(model, vertices)
        ref = np.asarray(reference, np.float64)
        if ref.ndim != 3 or ref.shape[1:] != (len(idx), 3) or ref.shape[0] < 2:
            raise ControlError(f"reference must have shape (T + 1, {len(idx)}, 3) with T >= 1 for the "
                               f"{len(idx)} selected vertices, got {ref.shape}")
        if not np.all(np.isfinite(ref)):
            raise ControlError("reference has non-finite values")
        object.__setattr__(self, "idx", idx)
        object.__setattr__(self, "reference", ref)

    def __call__(self, traj, controls):
        if traj.x.shape[0] != self.reference.shape[0]:
            raise ControlError(f"the trajectory has {traj.x.shape[0]} frames but the reference "
                               f"{self.reference.shape[0]}")
        d = traj.x[1:, self.idx, :] - jnp.asarray(self.reference[1:])
        return jnp.mean(jnp.sum(d * d, axis=-1))


def _check_scale(scale) -> np.ndarray:
    s = np.asarray(scale, np.float64)
    if s.ndim > 1 or not np.all(np.isfinite(s)) or not np.all(s > 0):
        raise ControlError(f"scale must be a positive number or one per channel, got {scale!r}")
    return s


@dataclass(frozen=True, eq=False, init=False)
class _ScaledControls(Loss):
    """A loss of the controls divided by a per-channel ``scale`` (> 0)."""

    scale: np.ndarray

    def __init__(self, scale=1.0):
        object.__setattr__(self, "scale", _check_scale(scale))

    def _scaled(self, controls):
        return _controls_2d(controls) / jnp.asarray(self.scale)


@dataclass(frozen=True, eq=False, init=False)
class Effort(_ScaledControls):
    """Actuation effort: ``mean over steps of sum over channels (a / scale)^2``.

    Averaged over steps so that its weight does not depend on the horizon.

    Arguments:
        scale: the activation unit, a number or one per channel (e.g. a pressure in Pa
            for cavity channels), > 0.

    Raises:
        ControlError: a non-positive scale, or controls that are not ``(T, C)`` (when called).
    """

    def __call__(self, traj, controls):
        a = self._scaled(controls)
        return jnp.mean(jnp.sum(a * a, axis=-1))


@dataclass(frozen=True, eq=False, init=False)
class Smoothness(_ScaledControls):
    """Roughness of the controls: ``mean over steps of sum over channels (da / scale)^2``,
    ``da`` the difference of consecutive steps' activations (0 for a single step).

    Arguments:
        scale: as for :class:`Effort`.

    Raises:
        ControlError: a non-positive scale, or controls that are not ``(T, C)`` (when called).
    """

    def __call__(self, traj, controls):
        a = self._scaled(controls)
        if a.shape[0] < 2:
            return jnp.zeros((), a.dtype)
        d = a[1:] - a[:-1]
        return jnp.mean(jnp.sum(d * d, axis=-1))


def _controls_2d(controls) -> Array:
    if controls is None or jnp.ndim(controls) != 2:
        raise ControlError(f"this loss needs the (T, C) controls, got "
                           f"{None if controls is None else tuple(jnp.shape(controls))}")
    return jnp.asarray(controls)

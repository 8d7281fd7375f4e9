"""Joints and links: what a skeleton is made of, checked as it is written (see :mod:`softbody.skeleton`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softbody._types import SceneError


class SkeletonError(SceneError):
    """A skeleton description is invalid; the message names the link and the fix."""


def _vector(v, what: str, unit: bool) -> np.ndarray:
    a = np.asarray(v, float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise SkeletonError(f"{what} must be 3 finite numbers, got {v!r}")
    if unit:
        norm = np.linalg.norm(a)
        if norm < 1e-12:
            raise SkeletonError(f"{what} {v!r} has zero length; give the direction of the joint axis")
        a = a / norm
    return a


def _limits(limits, what: str):
    if limits is None:
        return None
    lo, hi = (float(v) for v in limits)
    if not lo < hi:
        raise SkeletonError(f"{what} limits must satisfy lower < upper, got {limits!r}")
    return lo, hi


@dataclass(frozen=True)
class Free:
    """6-DOF root joint: position and orientation of the root bone in the world.

    Attributes:
        origin: the rotation centre in rest coordinates ``(3,)``; ``None`` (default): the
            root bone's centre of mass (uniform density), which decouples the rotational
            and translational rows of ``B^T A B`` best.
    """

    origin: tuple | None = None

    def __post_init__(self):
        if self.origin is not None:
            object.__setattr__(self, "origin", tuple(_vector(self.origin, "Free origin", unit=False)))


@dataclass(frozen=True)
class Fixed:
    """Welds a bone to its parent (or, for a root, to the world)."""


@dataclass(frozen=True)
class Revolute:
    """Hinge about ``axis`` through ``origin`` (rest coordinates); the angle in radians.

    Attributes:
        axis: ``(3,)`` direction (normalised here); the positive angle turns about it
            by the right-hand rule.
        origin: ``(3,)`` a point on the axis, m.
        limits: ``(lower, upper)`` angles in rad within ``(-pi, pi]``, or ``None``.

    Raises:
        SkeletonError: a zero-length axis, non-finite values, bad limits.
    """

    axis: tuple
    origin: tuple = (0.0, 0.0, 0.0)
    limits: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "axis", tuple(_vector(self.axis, "Revolute axis", unit=True)))
        object.__setattr__(self, "origin", tuple(_vector(self.origin, "Revolute origin", unit=False)))
        limits = _limits(self.limits, "Revolute")
        if limits is not None and not (-np.pi <= limits[0] and limits[1] <= np.pi):
            raise SkeletonError(f"Revolute limits must lie within [-pi, pi] (angles are recovered "
                                f"modulo 2 pi), got {self.limits!r}")
        object.__setattr__(self, "limits", limits)


@dataclass(frozen=True)
class Prismatic:
    """Slider along ``axis`` (rest coordinates); the slide in metres.

    Attributes:
        axis: ``(3,)`` direction (normalised here).
        limits: ``(lower, upper)`` slides in m, or ``None``.

    Raises:
        SkeletonError: a zero-length axis, non-finite values, bad limits.
    """

    axis: tuple
    limits: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "axis", tuple(_vector(self.axis, "Prismatic axis", unit=True)))
        object.__setattr__(self, "limits", _limits(self.limits, "Prismatic"))


JOINTS = (Free, Fixed, Revolute, Prismatic)
_N_COORDS = {Free: 7, Fixed: 0, Revolute: 1, Prismatic: 1}
_N_DOFS = {Free: 6, Fixed: 0, Revolute: 1, Prismatic: 1}


@dataclass(frozen=True)
class Link:
    """One bone and the joint that attaches it to its parent.

    Attributes:
        name: unique link name.
        bone: the mesh region of the bone's vertices, e.g. ``"bone:spine"``.
        parent: the parent link's name, or ``None`` for a root (attached to the world).
        joint: :class:`Free` (roots only), :class:`Fixed`, :class:`Revolute` or
            :class:`Prismatic`.
    """

    name: str
    bone: str
    parent: str | None = None
    joint: object = field(default_factory=Fixed)



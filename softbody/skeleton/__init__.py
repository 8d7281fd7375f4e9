"""Articulated skeletons: rigid bones driven by a joint tree inside a soft body.

A bone is a tagged vertex set of the mesh (a ``"bone:<name>"`` region). Its vertices do
not move freely: they follow the forward kinematics (FK) of a joint tree,

    x_v = R_l X_v + p_l        for every vertex v of link l's bone,

with ``X_v`` the rest position and ``(R_l, p_l)`` the link's world transform, the product
of the joint transforms from the root down (prefix products). Joints, with their rest
frames given in rest-world coordinates:

* :class:`Free`: 6-DOF root; position ``t`` and unit quaternion ``q`` (coordinates, 7),
  the rotation about the root's centre of mass (or a given origin) ``c``:
  ``J(X) = R(q) (X - c) + c + t``. Its tangent is ``(dt, dphi)`` (6), the rotation
  increment taken in the world frame, so that updates compose rotations and stay on SO(3).
* :class:`Revolute`: angle ``theta`` about a unit axis through an origin (1).
* :class:`Prismatic`: slide ``d`` along a unit axis (1).
* :class:`Fixed`: welded (0).

The Jacobian ``B = dx_bone/dz`` ``(n_b, 3, n_dofs)`` is taken with respect to the tangent
coordinates. Differentiating the product ``T_parent J_j(theta) T_suffix X`` in a joint's
coordinate gives ``T_parent J_j' T_suffix X``; with the world axis ``w = R_parent a`` and
origin ``o = T_parent(o_rest)`` this is ``w x (x - o)`` (revolute) or ``w`` (prismatic),
evaluated at the vertex's world position ``x``, which already holds the suffix product.
So the Jacobian needs the prefix transforms only, computed top-down in one pass.

A scene with a skeleton (``build(..., skeleton=...)``) steps in the reduced coordinates
:class:`Reduced`: the ordinary step objective ``Phi(x)`` is minimised over the free
vertices and ``z``, bones placed by ``FK(z)``; the search direction solves the PD matrix
``A`` restricted to the skeleton's motions::

    [[Q_ff,     Q_fr B  ], [d_f]   [g_f    ]
     [B^T Q_rf, B^T Q_rr B]] [d_z] = [B^T g_r]

by a Schur complement on the bone block (see :func:`schur_factor`). With obstacles, the
contact solver's splitting iteration runs with the skeleton swept in its reduced
coordinates (contact and dry friction act on the soft skin). Joint torques are
the vertex terms of :mod:`softbody.actuators.joints`: their gradient on the bone
vertices, mapped by ``B^T``, is exactly minus the torque in the joint's row.
"""

from softbody.skeleton.condense import SchurFactor, schur_direction, schur_factor
from softbody.skeleton.joints import JOINTS, Fixed, Free, Link, Prismatic, Revolute, SkeletonError
from softbody.skeleton.reduced import Reduced
from softbody.skeleton.rig import Pose, Rig, Skeleton

__all__ = [
           "JOINTS",
           "Fixed",
           "Free",
           "Link",
           "Pose",
           "Prismatic",
           "Reduced",
           "Revolute",
           "Rig",
           "SchurFactor",
           "Skeleton",
           "SkeletonError",
           "schur_direction",
           "schur_factor",
]

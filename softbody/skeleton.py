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

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody import rotation as rot
from softbody.meshing import TetMesh
from softbody._interfaces import Capabilities, ContactSweep, Coordinates
from softbody._types import SceneError
from softbody.solvers import (LBFGS, LocalGlobal, Solution, StepProblem, empty_history, iterate, lbfgs_direction,
                              store_pair)

Array = jax.Array


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


@dataclass(frozen=True)
class Skeleton:
    """A joint tree of links, stored top-down (every parent before its children).

    Attributes:
        links: the links, in any order that names existing parents.

    Raises:
        SkeletonError: no links, duplicate names, an unknown parent, a cycle, a joint of
            an unknown type, a :class:`Free` joint below the root.
    """

    links: tuple

    def __post_init__(self):
        links = tuple(self.links)
        if not links:
            raise SkeletonError("a skeleton needs at least one link")
        names = [link.name for link in links]
        for link in links:
            if not isinstance(link, Link):
                raise SkeletonError(f"skeleton links must be Link objects, got {type(link).__name__}")
            if names.count(link.name) > 1:
                raise SkeletonError(f"link name {link.name!r} is used {names.count(link.name)} times")
            if not isinstance(link.joint, JOINTS):
                raise SkeletonError(f"link {link.name!r}: joint must be Free(), Fixed(), Revolute(...) or "
                                    f"Prismatic(...), got {link.joint!r}")
            if link.parent is not None and link.parent not in names:
                raise SkeletonError(f"link {link.name!r} names an unknown parent {link.parent!r}; "
                                    f"links are {names}")
            if isinstance(link.joint, Free) and link.parent is not None:
                raise SkeletonError(f"link {link.name!r}: a Free joint attaches a root to the world; "
                                    "give it parent=None")
        by_name = {link.name: link for link in links}
        for link in links:
            seen, up = [link.name], link.parent
            while up is not None:
                if up in seen:
                    raise SkeletonError(f"the links {seen} form a cycle; a skeleton must be a tree")
                seen.append(up)
                up = by_name[up].parent
        ordered, placed = [], set()
        while len(ordered) < len(links):
            for link in links:
                if link.name not in placed and (link.parent is None or link.parent in placed):
                    ordered.append(link)
                    placed.add(link.name)
        object.__setattr__(self, "links", tuple(ordered))

    def bind(self, mesh: TetMesh) -> Rig:
        """Attach the skeleton to a mesh's bone regions.

        Arguments:
            mesh: the :class:`~softbody.meshing.TetMesh` holding the bone regions.

        Returns:
            A :class:`Rig`.

        Raises:
            SkeletonError: an unknown bone region, a bone with no vertices, a vertex in two
                bones, or a bone whose vertices are coplanar (its rotation is undefined).
        """
        return Rig(self, mesh)


def _skew(w):
    """Cross-product matrices ``[w]_x`` of vectors ``w`` ``(..., 3)``: shape ``(..., 3, 3)``."""
    zero = jnp.zeros_like(w[..., 0])
    return jnp.stack([jnp.stack([zero, -w[..., 2], w[..., 1]], -1),
                      jnp.stack([w[..., 2], zero, -w[..., 0]], -1),
                      jnp.stack([-w[..., 1], w[..., 0], zero], -1)], -2)


def _quat_mul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return jnp.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _quat_exp(phi):
    """Unit quaternion of the rotation vector ``phi`` (3,), smooth at 0."""
    half2 = 0.25 * jnp.sum(phi * phi)  # (angle / 2)^2
    small = half2 < 1e-8
    half = jnp.sqrt(jnp.where(small, 1.0, half2))
    sinc = jnp.where(small, 0.5 - half2 / 12.0, 0.5 * jnp.sin(half) / half)
    cos = jnp.where(small, 1.0 - 0.5 * half2, jnp.cos(half))
    return jnp.concatenate([cos[None], sinc * phi])


def _quat_matrix(q):
    return rot.quat_to_mat(q[:, None])[:, :, 0]


class Pose(NamedTuple):
    """The skeleton at coordinates ``z``: link transforms, bone positions and dof twists.

    Attributes:
        r: ``(L, 3, 3)`` link rotations; p: ``(L, 3)`` translations (rest ``X`` maps to
            ``r[l] X + p[l]``).
        x: ``(n_b, 3)`` bone vertex positions.
        twists: ``(L, 6, n_dofs)`` the world twist ``(u, w)`` of each dof as it moves link
            ``l`` (zero where the dof's joint is not ``l`` or an ancestor of it): a bone
            vertex ``x`` of link ``l`` moves by ``u + w x x`` per unit of the dof.
    """

    r: Array
    p: Array
    x: Array
    twists: Array


@dataclass(frozen=True, eq=False)
class Rig:
    """A :class:`Skeleton` bound to a mesh: bone vertices, rest positions, coordinate layout.

    Coordinates ``z`` ``(n_coords,)`` hold each link's joint coordinates in the skeleton's
    top-down order (Free: ``t`` then the quaternion ``(w, x, y, z)``); the tangent
    (velocity) layout ``(n_dofs,)`` is the same with 6 entries for a Free joint
    (``dt``, then the world-frame rotation increment). Static: hashed by identity.

    The kinematics are batched over links: the joint transforms of all links at once,
    then one composition per depth of the tree (prefix products, top-down).

    Attributes:
        skeleton: the skeleton.
        bone: ``(n_b,)`` mesh indices of the bone vertices, grouped by link.
        is_bone: ``(n, 1)`` 1.0 on bone vertices, 0.0 elsewhere.
        vertex_link: ``(n_b,)`` link index of each bone vertex.
        rest: ``(n_b, 3)`` rest positions of the bone vertices.
        skin: ``(c,)`` indices into :attr:`bone` of the bone vertices that touch obstacles:
            those on the mesh's surface, on links that some dof moves.
        tree: ``(L,)`` the root link of each link's tree.
        detached_dofs: ``(n_dofs,)`` 1.0 on the dofs of free bodies (a :class:`Free` root
            with no children whose vertices are in no tet: a rigid body), else 0.0.
        n_vertices: vertices of the mesh.

    Raises:
        SkeletonError: see :meth:`Skeleton.bind`.
    """

    skeleton: Skeleton
    mesh: TetMesh

    def __post_init__(self):
        mesh, links = self.mesh, self.skeleton.links
        bone, vertex_link, centres = [], [], []
        owner = {}
        for i, link in enumerate(links):
            if link.bone not in mesh.regions:
                raise SkeletonError(f"link {link.name!r}: bone region {link.bone!r} is not in the mesh; "
                                    f"it has {sorted(mesh.regions)}")
            region = mesh.regions[link.bone]
            verts = np.asarray(region.vertices, np.int64)
            if verts.size == 0:
                raise SkeletonError(f"link {link.name!r}: bone region {link.bone!r} has no vertices")
            for v in verts:
                if v in owner:
                    raise SkeletonError(f"vertex {v} belongs to the bones of links {owner[v]!r} and "
                                        f"{link.name!r}; bone regions must not overlap")
                owner[v] = link.name
            pts = mesh.points[verts]
            spread = pts - pts.mean(axis=0)
            sv = np.linalg.svd(spread, compute_uv=False) if len(verts) >= 3 else np.zeros(3)
            if len(sv) < 3 or sv[2] <= 1e-9 * max(sv[0], 1e-300):
                raise SkeletonError(f"link {link.name!r}: the vertices of bone {link.bone!r} are coplanar; a "
                                    "bone needs a volume (4 non-coplanar vertices) to define its rotation")
            bone.append(verts)
            vertex_link.append(np.full(len(verts), i))
            centres.append(_centre(link.joint, mesh, region))
        n_links = len(links)
        n_coords = [_N_COORDS[type(link.joint)] for link in links]
        n_dofs = [_N_DOFS[type(link.joint)] for link in links]
        parent = np.array([-1 if link.parent is None else [x.name for x in links].index(link.parent)
                           for link in links])
        coord_start = np.concatenate([[0], np.cumsum(n_coords)]).astype(np.int64)
        dof_start = np.concatenate([[0], np.cumsum(n_dofs)]).astype(np.int64)
        # ancestor[l, j]: joint j moves link l (j is l or one of its ancestors).
        ancestor = np.eye(n_links, dtype=bool)
        depth = np.zeros(n_links, np.int64)
        for i in range(n_links):
            if parent[i] >= 0:
                ancestor[i] |= ancestor[parent[i]]
                depth[i] = depth[parent[i]] + 1
        vertex_link = np.concatenate(vertex_link)
        dof_link = np.repeat(np.arange(n_links), n_dofs)
        lo = np.full(int(dof_start[-1]), -np.inf)
        hi = np.full(int(dof_start[-1]), np.inf)
        rot_axis, slide_axis, origin = np.zeros((n_links, 3)), np.zeros((n_links, 3)), np.zeros((n_links, 3))
        scalar = []  # links with one coordinate (Revolute, Prismatic)
        for i, link in enumerate(links):
            joint = link.joint
            if isinstance(joint, Revolute):
                rot_axis[i], origin[i] = joint.axis, joint.origin
            elif isinstance(joint, Prismatic):
                slide_axis[i] = joint.axis
            if isinstance(joint, (Revolute, Prismatic)):
                scalar.append(i)
                if joint.limits is not None:
                    lo[dof_start[i]], hi[dof_start[i]] = joint.limits
        scalar = np.asarray(scalar, np.int64)
        # The dofs of free bodies: Free roots with no children whose vertices are in no
        # tet (rigid bodies). Nothing elastic couples them, so the reduced PD matrix holds
        # their block exactly (to the rotations' second order).
        in_tets = np.isin(np.concatenate(bone), mesh.tets)
        detached = np.array([isinstance(link.joint, Free) and not np.any(parent == i)
                             and not in_tets[vertex_link == i].any() for i, link in enumerate(links)])
        # Bone vertices that can touch obstacles: on the mesh's surface, on a link some
        # dof moves (a bone welded to the world carries its contact forces in the weld).
        root = np.arange(n_links)
        for i in range(n_links):
            root[i] = i if parent[i] < 0 else root[parent[i]]
        moved_link = np.array([n_dofs[j] > 0 for j in range(n_links)]) @ ancestor.T > 0
        all_bone = np.concatenate(bone)
        skin = np.flatnonzero(np.isin(all_bone, np.asarray(mesh.surface)) & moved_link[vertex_link])
        one_hot = np.zeros((len(vertex_link), n_links))
        one_hot[np.arange(len(vertex_link)), vertex_link] = 1.0
        for name, value in dict(
                bone=np.concatenate(bone).astype(np.int32), vertex_link=vertex_link,
                rest=mesh.points[np.concatenate(bone)], centres=centres, parent=parent,
                coord_start=coord_start, dof_start=dof_start,
                moves=ancestor[:, dof_link].astype(np.float64), vertex_one_hot=one_hot,
                levels=[np.flatnonzero(depth == d) for d in range(1, int(depth.max()) + 1)],
                free_links=[i for i, link in enumerate(links) if isinstance(link.joint, Free)],
                scalar_links=scalar, scalar_coords=coord_start[scalar], scalar_dofs=dof_start[scalar],
                rot_axis=rot_axis, slide_axis=slide_axis, origin=origin,
                lower=lo, upper=hi, n_vertices=mesh.n_vertices, detached_dofs=np.repeat(detached, n_dofs).astype(float),
                skin=skin, tree=root,
                is_bone=np.isin(np.arange(mesh.n_vertices), np.concatenate(bone))[:, None].astype(float)).items():
            object.__setattr__(self, name, value)

    @property
    def n_coords(self) -> int:
        return int(self.coord_start[-1])

    @property
    def n_dofs(self) -> int:
        return int(self.dof_start[-1])

    @property
    def links(self) -> tuple:
        return self.skeleton.links

    def link_index(self, name: str) -> int:
        """Index of the link called ``name`` in the top-down order.

        Raises:
            SkeletonError: no such link.
        """
        names = [link.name for link in self.links]
        if name not in names:
            raise SkeletonError(f"no link {name!r} in the skeleton; links are {names}")
        return names.index(name)

    def rest_coordinates(self) -> Array:
        """The coordinates ``(n_coords,)`` of the rest pose (angles and slides 0, identity)."""
        z = np.zeros(self.n_coords)
        for i in self.free_links:
            z[self.coord_start[i] + 3] = 1.0
        return jnp.asarray(z)

    def _scalars(self, z: Array) -> Array:
        """Every link's angle or slide ``(L,)`` (0 for Free and Fixed joints)."""
        if len(self.scalar_links) == 0:
            return jnp.zeros(len(self.links), z.dtype)
        return jnp.zeros(len(self.links), z.dtype).at[self.scalar_links].set(z[self.scalar_coords])

    def transforms(self, z: Array) -> tuple[Array, Array]:
        """World transforms of the links by prefix products, top-down.

        Arguments:
            z: ``(n_coords,)`` coordinates.

        Returns:
            ``(R, p)``: ``(L, 3, 3)`` rotations and ``(L, 3)`` translations; link ``l``
            maps rest positions ``X`` to ``R[l] X + p[l]``.
        """
        z = jnp.asarray(z, float)
        theta = self._scalars(z)
        k = _skew(jnp.asarray(self.rot_axis))
        r = (jnp.eye(3) + jnp.sin(theta)[:, None, None] * k
             + (1.0 - jnp.cos(theta))[:, None, None] * (k @ k))  # Rodrigues; identity off revolute joints
        origin = jnp.asarray(self.origin)
        p = origin - jnp.einsum("lij,lj->li", r, origin) + theta[:, None] * jnp.asarray(self.slide_axis)
        for i in self.free_links:
            c = z[self.coord_start[i]:self.coord_start[i + 1]]
            ri = _quat_matrix(c[3:] / jnp.linalg.norm(c[3:]))
            centre = jnp.asarray(self.centres[i])
            r, p = r.at[i].set(ri), p.at[i].set(centre + c[:3] - ri @ centre)
        for idx in self.levels:
            par = self.parent[idx]
            r_par, p_par = r[par], p[par]
            p = p.at[idx].set(jnp.einsum("lij,lj->li", r_par, p[idx]) + p_par)
            r = r.at[idx].set(r_par @ r[idx])
        return r, p

    def positions(self, z: Array) -> Array:
        """Forward kinematics: bone vertex positions ``(n_b, 3)`` (in :attr:`bone` order)."""
        r, p = self.transforms(z)
        return self._place(r, p)

    def _place(self, r, p):
        link = jnp.asarray(self.vertex_link)
        return jnp.einsum("vij,vj->vi", r[link], jnp.asarray(self.rest)) + p[link]

    def pose(self, z: Array) -> Pose:
        """Transforms, bone positions and dof twists at ``z`` (see :class:`Pose`).

        The twist of a revolute dof is ``(-w x o, w)`` with the world axis ``w = R_parent a``
        through the world origin ``o`` of the joint; of a prismatic dof ``(R_parent a, 0)``;
        of a Free joint's translation ``(e_i, 0)`` and rotation (about its world centre
        ``c``) ``(-e_i x c, e_i)``. Only the prefix (parent) transforms are needed.
        """
        z = jnp.asarray(z, float)
        r, p = self.transforms(z)
        n_links, k = len(self.links), self.n_dofs
        par = np.where(self.parent >= 0, self.parent, n_links)
        r_par = jnp.concatenate([r, jnp.eye(3)[None]])[par]
        p_par = jnp.concatenate([p, jnp.zeros((1, 3))])[par]
        w = jnp.einsum("lij,lj->li", r_par, jnp.asarray(self.rot_axis))
        u = (-jnp.cross(w, jnp.einsum("lij,lj->li", r_par, jnp.asarray(self.origin)) + p_par)
             + jnp.einsum("lij,lj->li", r_par, jnp.asarray(self.slide_axis)))
        twist = jnp.zeros((k, 6))
        if len(self.scalar_links):
            twist = twist.at[self.scalar_dofs].set(jnp.concatenate([u, w], axis=1)[self.scalar_links])
        for i in self.free_links:
            c = z[self.coord_start[i]:self.coord_start[i] + 3] + jnp.asarray(self.centres[i])
            eye = jnp.eye(3)
            block = jnp.concatenate([jnp.concatenate([eye, jnp.zeros((3, 3))], axis=1),
                                     jnp.concatenate([-jnp.cross(eye, c), eye], axis=1)])
            twist = twist.at[self.dof_start[i]:self.dof_start[i] + 6].set(block)
        twists = jnp.asarray(self.moves)[:, None, :] * twist.T[None]
        return Pose(r, p, self._place(r, p), twists)

    def jacobian(self, z: Array) -> Array:
        """``B = dx_bone/dz`` in tangent coordinates, shape ``(n_b, 3, n_dofs)``.

        Column ``k`` is the world twist ``(u_k, w_k)`` of dof ``k`` applied to the vertices
        it moves: ``B[v, :, k] = u_k + w_k x x_v``.
        """
        return self._jacobian(self.pose(z))

    def _jacobian(self, pose: Pose) -> Array:
        t = pose.twists[jnp.asarray(self.vertex_link)]  # (n_b, 6, k)
        return t[:, :3] - jnp.einsum("vij,vjk->vik", _skew(pose.x), t[:, 3:])

    def reduce(self, pose: Pose, force: Array) -> Array:
        """``B^T f``: the generalised force ``(n_dofs,)`` of bone-vertex forces ``f`` ``(n_b, 3)``.

        Summed per link as a wrench (force, moment about the origin), then mapped by the
        twists; no ``(n_b, 3, n_dofs)`` Jacobian is formed.
        """
        one_hot = jnp.asarray(self.vertex_one_hot)
        moment = jnp.concatenate([force, jnp.cross(pose.x, force)], axis=1)  # (n_b, 6)
        # Column by column: matrix-vector products took half the time of one (L, n_b) x (n_b, 6) product.
        wrench = jnp.stack([one_hot.T @ m for m in moment.T], axis=1)  # (L, 6)
        return wrench.reshape(-1) @ pose.twists.reshape(wrench.size, -1)

    def retract(self, z: Array, dz: Array) -> Array:
        """Move ``z`` by the tangent step ``dz`` ``(n_dofs,)`` and stay on the manifold.

        Angles and slides add (then are clamped to their limits); a Free joint's position
        adds and its rotation composes, ``q <- exp(dphi) q``, re-normalised.
        """
        z = jnp.asarray(z, float)
        if len(self.scalar_links):
            value = jnp.clip(z[self.scalar_coords] + dz[self.scalar_dofs],
                             self.lower[self.scalar_dofs], self.upper[self.scalar_dofs])
            z = z.at[self.scalar_coords].set(value)
        for i in self.free_links:
            c, d = self.coord_start[i], dz[self.dof_start[i]:self.dof_start[i] + 6]
            q = _quat_mul(_quat_exp(d[3:]), z[c + 3:c + 7])
            z = z.at[c:c + 7].set(jnp.concatenate([z[c:c + 3] + d[:3], q / jnp.linalg.norm(q)]))
        return z

    def step_taken(self, z: Array, z_new: Array, dz: Array) -> Array:
        """The tangent step ``(n_dofs,)`` from ``z`` to ``z_new = retract(z, dz)``: ``dz``
        with the angles and slides replaced by their actual change (the limits clamp them)."""
        if not len(self.scalar_links):
            return dz
        return dz.at[self.scalar_dofs].set(z_new[self.scalar_coords] - z[self.scalar_coords])

    def coordinates(self, x_bone: Array) -> Array:
        """The coordinates ``(n_coords,)`` whose FK best fits bone positions ``(n_b, 3)``.

        Each link's rigid transform is the least-squares fit (Kabsch: the rotation of the
        covariance of positions and rest positions, by :func:`softbody.rotation.polar`,
        which is differentiable); the joint coordinates are read off the transforms of
        each link relative to its parent's. Exact (to round-off) for positions produced by
        :meth:`positions`; revolute angles come back in ``(-pi, pi]``.
        """
        one_hot = jnp.asarray(self.vertex_one_hot)
        n_links = len(self.links)
        count = self.vertex_one_hot.sum(axis=0)[:, None]
        rest = jnp.asarray(self.rest)
        xm = one_hot.T @ x_bone / count
        rm = jnp.asarray(self.vertex_one_hot.T @ self.rest / count)
        link = jnp.asarray(self.vertex_link)
        h = jnp.einsum("vl,vi,vj->lij", one_hot, x_bone - xm[link], rest - rm[link])
        r = jnp.moveaxis(rot.polar(jnp.moveaxis(h, 0, -1), iterations=3), -1, 0)
        p = xm - jnp.einsum("lij,lj->li", r, rm)
        par = np.where(self.parent >= 0, self.parent, n_links)
        r_par = jnp.concatenate([r, jnp.eye(3)[None]])[par]
        p_par = jnp.concatenate([p, jnp.zeros((1, 3))])[par]
        r_rel = jnp.einsum("lji,ljk->lik", r_par, r)
        p_rel = jnp.einsum("lji,lj->li", r_par, p - p_par)
        z = jnp.zeros(self.n_coords, x_bone.dtype)
        if len(self.scalar_links):
            axial = 0.5 * rot.vee_skew(jnp.moveaxis(r_rel, 0, -1)).T  # (L, 3): sin(theta) a
            cos = 0.5 * (jnp.trace(r_rel, axis1=1, axis2=2) - 1.0)
            angle = jnp.arctan2(jnp.sum(jnp.asarray(self.rot_axis) * axial, axis=1), cos)
            slide = jnp.sum(jnp.asarray(self.slide_axis) * p_rel, axis=1)
            is_rev = np.any(self.rot_axis != 0, axis=1)
            value = jnp.where(is_rev, angle, slide)
            z = z.at[self.scalar_coords].set(value[self.scalar_links])
        for i in self.free_links:
            centre = jnp.asarray(self.centres[i])
            c = self.coord_start[i]
            z = z.at[c:c + 3].set(p_rel[i] + r_rel[i] @ centre - centre)
            z = z.at[c + 3:c + 7].set(rot.mat_to_quat(r_rel[i][:, :, None])[:, 0])
        return z

    def joint_values(self, z: Array) -> Array:
        """Angle (rad) or slide (m) of every revolute and prismatic joint, ``(n_dofs,)``
        layout with Free rows set to 0."""
        out = jnp.zeros(self.n_dofs, jnp.asarray(z).dtype)
        if len(self.scalar_links):
            out = out.at[self.scalar_dofs].set(z[self.scalar_coords])
        return out


def _centre(joint, mesh: TetMesh, region) -> np.ndarray | None:
    """A Free joint's rotation centre: its origin, or the bone's centre of mass (the
    volume-weighted centroid of its tets; the vertex mean for a bone given by vertices only)."""
    if not isinstance(joint, Free):
        return None
    if joint.origin is not None:
        return np.asarray(joint.origin)
    if region.tets.size == 0:
        return mesh.points[region.vertices].mean(axis=0)
    corners = mesh.points[mesh.tets[region.tets]]  # (m, 4, 3)
    edges = corners[:, 1:] - corners[:, :1]
    volume = np.abs(np.linalg.det(edges))
    return (volume[:, None] * corners.mean(axis=1)).sum(axis=0) / volume.sum()


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
    e, x = rig.vertex_one_hot, rig.rest
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


def _link_motions(pose: Pose, move: Array) -> Array:
    """``G`` ``(4L, 3, n_dofs)``: the motion of every link per unit of each dof, in the layout
    of the features ``F`` (:class:`SchurFactor`), so that ``B d_z = F (G d_z)`` link by link.

    A dof whose twist on link ``l`` is ``(a, w)`` moves its bone vertex ``x = R_l X + p_l``
    by ``a + w x x = c + M X`` with ``c = a + w x p_l`` (row ``l``) and ``M = [w]x R_l``
    (column ``j`` of ``M`` in row ``L + 3 l + j``). Held dofs (``move = 0``) get zero columns.
    The cross products are spelled out by component (XLA's batched tiny matmuls are slower).
    """
    twists = pose.twists * move
    a, w = twists[:, :3], twists[:, 3:]  # (L, 3, k)

    def cross(u):  # w x u for one vector u (L, 3) per link: (L, 3, k)
        u = u[:, :, None]
        return jnp.stack([w[:, 1] * u[:, 2] - w[:, 2] * u[:, 1], w[:, 2] * u[:, 0] - w[:, 0] * u[:, 2],
                          w[:, 0] * u[:, 1] - w[:, 1] * u[:, 0]], axis=1)

    m = jnp.stack([cross(pose.r[:, :, j]) for j in range(3)], axis=1)  # (L, j, 3, k)
    n_links, _, k = twists.shape
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
    motion = _link_motions(pose, move)  # (4L, 3, k)
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


@dataclass(frozen=True)
class Reduced(Coordinates):
    """A skeleton's reduced coordinates: the soft vertices and the joint coordinates ``z``,
    bones placed by ``FK(z)`` (see the module docstring). :func:`~softbody.model.build`
    chooses them for a scene with a skeleton.

    **Without contact** (:meth:`minimize`) each iteration evaluates ``Phi`` and its gradient
    at ``x = assemble(x_free, FK(z))``, forms the reduced gradient ``(g_f, B^T g_r)``, takes
    the L-BFGS direction in the reduced coordinates (the solver's ``history`` pairs;
    :class:`~softbody.solvers.LocalGlobal` keeps none) with the reduced PD solve
    (:func:`schur_direction`) as its initial inverse Hessian, and backtracks (halving)
    until Armijo's condition holds. The PD matrix holds the elastic and inertial terms
    only; the quasi-Newton pairs add the curvature of the rest, chiefly joint servos,
    whose stiffness in joint space can exceed the condensed matrix's by orders of
    magnitude (a servo of 50 N m/rad on a soft arm: 200 plain reduced-PD iterations ended
    at a residual of 8.6e-4, the L-BFGS iteration converges). A direction that does not
    descend is replaced by the plain reduced PD direction. Updates stay on the manifold
    (:meth:`Rig.retract`); a joint at a limit whose gradient pushes it outward is held for
    that iteration. The step starts from ``z`` fitted to the inertial prediction
    ``x_n + h v_n`` of the bones (:meth:`Rig.coordinates`), so no state beyond the
    positions is needed. The condensation (:func:`schur_factor`) depends on the PD matrix
    only: it is made once per rollout (:meth:`prepare`). The PD matrix is prefactored with
    the true volume weight (``volume_weight = 1``), for which the PD model majorises the
    elastic energy.

    **With contact** (:meth:`contact_sweep`, run by :class:`~softbody.contact.Contact`)
    each iteration fits ``z`` to the iterate's bones and places them by ``FK(z)``, evaluates
    the local step, then sweeps

    * the soft vertices as in vertex coordinates: ``y = x - P^{-1} g``, followed by the
      per-vertex contact step (stick or slide, non-penetration);
    * the skeleton with its block of the same splitting:
      ``z <- retract(z, -(B^T P_b B)^{-1} B^T g_b)``, ``P_b`` the bone vertices' ``P``,
      ``B`` the FK Jacobian; a joint at a limit pushed outward is held.

    Convergence carries over from :class:`~softbody.splitting.ScaledDiagonal`'s theorem:
    with ``T = diag(I, B)`` the reduced matrices are ``T^T L T`` and ``T^T (M/h^2 + D) T``,
    the latter block diagonal (``D`` is diagonal), and ``L <= 4 diag(L)`` gives
    ``T^T L T <= 2 T^T D T``, so the frozen-projection iteration matrix again has its
    eigenvalues in ``[-beta, beta]``, ``beta < 1`` (``B^T M_b B > 0`` as every bone has a
    volume). The residual is ``|P (x_new - x)|`` over the soft vertices together with the
    reduced force ``|B^T g_b|`` of the joints free to move: zero exactly at the step's
    equilibrium with contact. Contact acts on the soft vertices: bones are meant to lie
    inside the skin.

    Gradients: both adjoints. :class:`~softbody.gradients.Implicit` (the default) uses the
    reduced coordinates as its chart (:meth:`implicit_chart`): the step's solution is
    stationary in ``(x_free, z)``, not in the bone vertices (they carry the joints'
    constraint forces), and the adjoint system is preconditioned with the same Schur
    condensation as the forward step. :class:`~softbody.gradients.Unrolled`
    differentiates the iterations as they ran. With contact the returned positions carry
    the implicit derivative of the contact fixed point (tested against central
    differences on a jointed body sliding down an incline, d slide / d mu_k).

    Attributes:
        rig: the :class:`Rig` (the scene's skeleton bound to its mesh).
        backtracks: the most halvings of a step (static).

    Raises:
        SkeletonError: a bad attribute.
    """

    solvers = (LBFGS, LocalGlobal)
    capabilities = Capabilities(
        refuses={"partly held vertices": "holds vertices in all three components only (its reduced coordinates move "
                                         "whole vertices)",
                 "pair contact": "does not carry contact rows between bodies yet (its contact sweep moves bones and "
                                 "rigid bodies by their obstacle rows alone)"},
        instead="fix them with fixed=<selection> (or a Fix with axes='xyz'), or weld a bone with a root Fixed() joint")
    rig: Rig
    backtracks: int = 8
    contact_sweeps: int = 10

    def __post_init__(self):
        if not isinstance(self.rig, Rig):
            raise SkeletonError(f"Reduced.rig must be a Rig (Skeleton.bind(mesh)), got {type(self.rig).__name__}")
        if int(self.backtracks) != self.backtracks or self.backtracks < 0:
            raise SkeletonError(f"Reduced.backtracks must be an integer >= 0, got {self.backtracks!r}")

    def volume_weight(self, solver) -> float:
        return 1.0

    def prepare(self, model, data, factor) -> SchurFactor:
        """The :class:`SchurFactor` of the scene's PD matrix."""
        return schur_factor(model.linear_solver, model.pattern, data, self.rig)

    def implicit_chart(self, prepared, x, free):
        """The reduced coordinates ``d = (d_f (n, 3) on the soft free vertices, d_z (n_dofs,))``
        about the solution ``x``: ``embed(d)`` moves the soft vertices by ``d_f`` and the
        bones to ``FK(retract(z, d_z))``; joints at a limit are held (their ``d_z`` rows
        are masked out). The preconditioner solves the reduced PD system (:func:`schur_direction`).
        See :meth:`softbody.solvers.Step.implicit_chart`."""
        rig, n, k = self.rig, x.shape[0], self.rig.n_dofs
        bone = jnp.asarray(rig.bone)
        soft = free * (1.0 - rig.is_bone)
        z = rig.coordinates(x[bone])
        pose = rig.pose(z)
        value = rig.joint_values(z)
        held = ((value <= jnp.asarray(rig.lower)) | (value >= jnp.asarray(rig.upper))).astype(x.dtype)

        def split(d):
            return d[:3 * n].reshape(n, 3) * soft, d[3 * n:] * (1.0 - held)

        def embed(d):
            d_f, d_z = split(d)
            return (x + d_f).at[bone].set(rig.positions(rig.retract(z, d_z)))

        def solve(r):
            r_f, r_z = split(r)
            d, d_z = _solve_reduced(prepared, rig, pose, r_f, r_z, held)
            return jnp.concatenate([(d * soft).ravel(), d_z * (1.0 - held)])

        return embed, solve, 3 * n + k

    def contact_sweep(self, problem, p, law):
        """The soft vertices take the per-vertex contact step; the skeleton sweeps its block
        with the contact forces on its skin (see the class docstring). See
        :meth:`softbody._interfaces.Coordinates.contact_sweep`."""
        rig = self.rig
        n, bone, skin = rig.n_vertices, jnp.asarray(rig.bone), rig.skin
        p_bone = p[bone, 0]
        owners = np.asarray(rig.bone)[skin]
        index = jnp.asarray(owners)
        tree = jnp.asarray(rig.tree[rig.vertex_link[skin]])
        valid = problem.free[index, 0] > 0

        def place(x):
            x = x if x.shape[0] == n else x[:n]
            z = rig.coordinates(x[bone])
            pose = rig.pose(z)
            return x.at[bone].set(pose.x), (z, pose)

        def inverse(jac, move):
            """``K^-1`` of the sweep's block ``K = B^T P_b B``, zero on the held dofs."""
            mask = move[:, None] * move[None, :]
            k_z = jnp.einsum("vik,v,vil->kl", jac, p_bone, jac) * mask
            return jnp.linalg.inv(k_z + jnp.diag(1.0 - move)) * mask

        def delassus_diagonal(b_skin, k_inv):
            """``(c, 3)`` the diagonal of ``W = B_C K^-1 B_C^T`` (the skin's Delassus operator)."""
            return jnp.maximum(jnp.einsum("cik,kl,cil->ci", b_skin, k_inv, b_skin), 0.0)

        def forces(x):
            return scale * x[n:]

        if not len(skin):
            def sweep(x, x_new, g, aux):
                z, pose = aux
                jac = rig._jacobian(pose)  # (n_b, 3, k)
                g_z = rig.reduce(pose, g[bone])
                move = 1.0 - _held(rig, z, g_z)
                k_z = jnp.einsum("vik,v,vil->kl", jac, p_bone, jac) * move[:, None] * move[None, :]
                d_z = jnp.linalg.solve(k_z + jnp.diag(1.0 - move), g_z * move)
                return x_new.at[bone].set(rig.positions(rig.retract(z, -d_z))), g_z * move

            scale = jnp.zeros((0, 1), p.dtype)
            return ContactSweep(problem.free * (1.0 - rig.is_bone), place, sweep, owners, scale, forces)

        # The extra rows hold the skin's contact forces over the effective mass of each skin
        # vertex at the step's start (so that they are displacements, as the other rows).
        jac_n = rig._jacobian(rig.pose(rig.coordinates(problem.x_n[bone])))
        w_n = delassus_diagonal(jac_n[skin], inverse(jac_n, jnp.ones(rig.n_dofs, p.dtype)))
        scale = (3.0 / jnp.maximum(w_n.sum(axis=1), 1e-300))[:, None]

        def sweep(x, x_new, g, aux):
            z, pose = aux
            force = forces(x)  # (c, 3) contact forces on the skin
            jac = rig._jacobian(pose)
            b_skin = jac[skin]
            g_z = rig.reduce(pose, g[bone])
            net = g_z - jnp.einsum("cik,ci->k", b_skin, force)
            move = 1.0 - _held(rig, z, net)
            k_inv = inverse(jac, move)
            # The contact forces by relaxed projected Jacobi sweeps on the Delassus operator
            # W (the body's motion linearised): each skin vertex takes the per-vertex contact
            # step, with the effective mass 1 / w_i of its diagonal block (w_i its mean
            # entry), from where the body's sweep puts it less its own force's displacement;
            # the force moves to that step's force by the fraction w_i / bound_i, with bound_i
            # >= the absolute row sums of W over the vertices pushing or about to touch (a
            # Gershgorin bound from |W_ij| <= sqrt(W_ii W_jj), per tree), so that the sweeps
            # converge for frictionless contact as the splitting does. At a fixed point the
            # body is in equilibrium with the forces, and each skin vertex satisfies the
            # contact law (on the surface, inside the cone, sliding against its slip, the
            # static cone's threshold measured with 1 / w_i as the splitting measures it with
            # P; a skin vertex sliding at the step's start meets the kinetic cone only, see
            # softbody.contact.SLIDING_SPEED): the fixed point does not depend on the bound.
            root = jnp.sqrt(delassus_diagonal(b_skin, k_inv))  # (c, 3)
            w = jnp.sum(root**2, axis=1) / 3.0

            def update(force, _):
                moved = pose.x[skin] - jnp.einsum("cik,k->ci", b_skin,
                                                  k_inv @ (g_z - jnp.einsum("cik,ci->k", b_skin, force)))
                near, _, _, _ = law(moved, index, valid)
                active = near | jnp.any(force != 0, axis=1)
                reach = jax.ops.segment_sum(jnp.where(active, root.sum(axis=1), 0.0), tree, len(rig.links))[tree]
                bound = root.max(axis=1) * (reach + jnp.where(active, 0.0, root.sum(axis=1)))
                touching, _, correction, _ = law(moved - force * w[:, None], index, valid, kinetic=True)
                target = jnp.where(touching[:, None], correction, 0.0) / jnp.where(w > 0, w, 1.0)[:, None]
                fraction = jnp.where(bound > 0, w / jnp.where(bound > 0, bound, 1.0), 0.0)
                return force + fraction[:, None] * (target - force), None

            force_new, _ = jax.lax.scan(update, force, None, length=self.contact_sweeps)
            d_z = k_inv @ (g_z - jnp.einsum("cik,ci->k", b_skin, force_new))
            placed = x_new.at[bone].set(rig.positions(rig.retract(z, -d_z)))
            residual = jnp.concatenate([net * move, (force_new - force).ravel()])
            return jnp.concatenate([placed, force_new / scale]), residual

        return ContactSweep(problem.free * (1.0 - rig.is_bone), place, sweep, owners, scale, forces)

    def minimize(self, solver, problem, x0, q0, threshold, max_iter, unrolled=False):
        """Solve one step without contact (see the class docstring); ``unrolled=False``
        runs a ``while_loop`` (forward mode only), otherwise a fixed-trip loop that reverse
        mode differentiates as it ran.

        Raises:
            SkeletonError: ``problem.prepared`` is not this rig's condensation.
        """
        if not isinstance(problem.prepared, SchurFactor):
            raise SkeletonError("reduced coordinates need their per-rollout condensation in problem.prepared; build "
                                "the step problem with softbody.model.prepare and softbody.objective.solve_step")
        history = solver.history if isinstance(solver, LBFGS) else 0
        return self._solve(problem, x0, q0, threshold, max_iter, unrolled, history)

    def _solve(self, problem, x0, q0, threshold, max_iter, unrolled, m):
        """The iterations (see the class docstring)."""
        rig, evaluate = self.rig, problem.evaluate
        factor = problem.prepared
        bone = jnp.asarray(rig.bone)
        soft = 1.0 - rig.is_bone
        n = x0.shape[0]

        def reduced(g, pose, z):
            """The reduced gradient ``B^T g_r``, the dofs held at a limit this iteration, and
            the norm of ``(g_f, B^T g_r)`` over the dofs that may move."""
            g_z = rig.reduce(pose, g[bone])
            locked = _held(rig, z, g_z)
            gnorm = jnp.sqrt(jnp.sum((g * soft) ** 2) + jnp.sum((g_z * (1.0 - locked)) ** 2))
            return g_z, locked, gnorm

        def flat(v_f, v_z):  # a reduced vector (soft rows, joint tangents) as one (3 n + k,)
            return jnp.concatenate([(v_f * soft).reshape(-1), v_z])

        def unflat(v):
            return v[:3 * n].reshape(n, 3), v[3 * n:]

        def direction(g, pose, g_z, locked, lbfgs):
            """``(d, d_z)``: the step is ``x - alpha d``, ``z - alpha d_z`` (bone rows of
            ``d`` unused: the bones are placed by ``FK``)."""
            move = 1.0 - locked

            def precondition(r):
                r_f, r_z = unflat(r)
                d, d_z = _solve_reduced(factor, rig, pose, r_f, r_z * move, locked)
                return flat(d, d_z * move)

            g_r = flat(g, g_z * move)
            if m == 0:
                return unflat(precondition(g_r))
            d_f, d_z = unflat(-lbfgs_direction(g_r, *lbfgs, precondition))
            d = flat(d_f, d_z * move)
            return unflat(jax.lax.cond(jnp.sum(g_r * d) > 0, lambda: d, lambda: precondition(g_r)))

        z0 = rig.coordinates(x0[bone])
        pose0 = rig.pose(z0)
        x0 = x0.at[bone].set(pose0.x)
        phi0, g0, q0 = evaluate(x0, q0)

        def cond(c):
            return (c[8] > threshold) & (c[10] < max_iter)

        def body(c):
            x, z, q, phi, g, pose, g_z, locked, _, evals, k, lbfgs = c
            d, d_z = direction(g, pose, g_z, locked, lbfgs)
            slope = jnp.sum((g * soft) * d) + jnp.sum(g_z * d_z)  # -dPhi/dalpha along (x - alpha d, z - alpha d_z)

            def trial(alpha):
                z_t = rig.retract(z, -alpha * d_z)
                pose_t = rig.pose(z_t)
                x_t = (x - alpha * d).at[bone].set(pose_t.x)
                phi_t, g_t, q_t = evaluate(x_t, q)
                return x_t, z_t, q_t, phi_t, g_t, pose_t

            def rejected(t):
                alpha, tries, (_, _, _, phi_t, _, _) = t
                return (~(phi_t <= phi - 1e-4 * alpha * slope + 1e-14 * jnp.abs(phi))) & (tries < self.backtracks)

            def halve(t):
                alpha, tries, _ = t
                return alpha / 2, tries + 1, trial(alpha / 2)

            # The search runs no iterations after acceptance (they would halve the accepted step).
            alpha, tries, (x_new, z_new, q, phi, g_new, pose_new) = iterate(
                rejected, halve, (jnp.asarray(1.0), jnp.asarray(0), trial(1.0)), self.backtracks,
                unrolled is not False)
            g_z_new, locked, gnorm = reduced(g_new, pose_new, z_new)
            if m:
                # The pairs leave out the free bodies' dofs, whose block the reduced PD solve
                # holds exactly (a free rigid body converges in one iteration, to 1e-17): their
                # later steps and gradient changes are round-off, which would set the quasi-
                # Newton matrix on them at random, and reverse mode through 1 / (s . y) of
                # round-off blows up (an unrolled solve beside a soft body).
                keep = 1.0 - rig.detached_dofs
                lbfgs = store_pair(lbfgs, flat(x_new - x, rig.step_taken(z, z_new, -alpha * d_z) * keep),
                                   flat(g_new - g, (g_z_new - g_z) * keep))
            return (x_new, z_new, q, phi, g_new, pose_new, g_z_new, locked, gnorm, evals + 1 + tries, k + 1,
                    lbfgs)

        lbfgs = empty_history(m, 3 * n + rig.n_dofs, x0.dtype)
        init = (x0, z0, q0, phi0, g0, pose0, *reduced(g0, pose0, z0), jnp.asarray(1), jnp.asarray(0), lbfgs)
        x, _, q, _, _, _, _, _, gnorm, evals, k, _ = iterate(cond, body, init, max_iter, unrolled)
        return Solution(x, q, k, evals, gnorm)

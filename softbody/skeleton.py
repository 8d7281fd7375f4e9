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

The reduced implicit step (:class:`SkeletonPD`) minimises the ordinary step objective
``Phi(x)`` over the free vertices and ``z``, bones placed by ``FK(z)``; its search
direction solves the PD matrix ``A`` restricted to the skeleton's motions::

    [[Q_ff,     Q_fr B  ], [d_f]   [g_f    ]
     [B^T Q_rf, B^T Q_rr B]] [d_z] = [B^T g_r]

by a Schur complement on the bone block (see :func:`schur_factor`). Joint torques are
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
from softbody.model import SceneError
from softbody.solvers import IterationMethod, Solution, StepProblem, iterate

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
    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _axis_angle(axis, theta):
    """Rotation matrix of angle ``theta`` about the unit ``axis`` (Rodrigues)."""
    k = _skew(axis)
    return jnp.eye(3) + jnp.sin(theta) * k + (1.0 - jnp.cos(theta)) * (k @ k)


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


@dataclass(frozen=True, eq=False)
class Rig:
    """A :class:`Skeleton` bound to a mesh: bone vertices, rest positions, coordinate layout.

    Coordinates ``z`` ``(n_coords,)`` hold each link's joint coordinates in the skeleton's
    top-down order (Free: ``t`` then the quaternion ``(w, x, y, z)``); the tangent
    (velocity) layout ``(n_dofs,)`` is the same with 6 entries for a Free joint
    (``dt``, then the world-frame rotation increment). Static: hashed by identity.

    Attributes:
        skeleton: the skeleton.
        bone: ``(n_b,)`` mesh indices of the bone vertices, grouped by link.
        vertex_link: ``(n_b,)`` link index of each bone vertex.
        rest: ``(n_b, 3)`` rest positions of the bone vertices.
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
        n_coords = [_N_COORDS[type(link.joint)] for link in links]
        n_dofs = [_N_DOFS[type(link.joint)] for link in links]
        parent = np.array([-1 if link.parent is None else [x.name for x in links].index(link.parent)
                           for link in links])
        dof_start = np.concatenate([[0], np.cumsum(n_dofs)])
        # ancestor[l, j]: joint j moves link l (j is l or one of its ancestors).
        ancestor = np.eye(len(links), dtype=bool)
        for i in range(len(links)):
            if parent[i] >= 0:
                ancestor[i] |= ancestor[parent[i]]
        vertex_link = np.concatenate(vertex_link)
        dof_link = np.repeat(np.arange(len(links)), n_dofs)
        lo = np.full(int(dof_start[-1]), -np.inf)
        hi = np.full(int(dof_start[-1]), np.inf)
        for i, link in enumerate(links):
            limits = getattr(link.joint, "limits", None)
            if limits is not None:
                lo[dof_start[i]], hi[dof_start[i]] = limits
        for name, value in dict(
                bone=np.concatenate(bone).astype(np.int32), vertex_link=vertex_link,
                rest=mesh.points[np.concatenate(bone)], centres=centres, parent=parent,
                coord_start=np.concatenate([[0], np.cumsum(n_coords)]), dof_start=dof_start,
                moves=ancestor[vertex_link][:, dof_link].astype(np.float64),
                lower=lo, upper=hi, n_vertices=mesh.n_vertices).items():
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
        for i, link in enumerate(self.links):
            if isinstance(link.joint, Free):
                z[self.coord_start[i] + 3] = 1.0
        return jnp.asarray(z)

    def _joint(self, i, z):
        """Joint ``i``'s local transform ``(R (3, 3), p (3,))``: ``J(X) = R X + p``."""
        joint, c = self.links[i].joint, z[self.coord_start[i]:self.coord_start[i + 1]]
        if isinstance(joint, Free):
            r = _quat_matrix(c[3:] / jnp.linalg.norm(c[3:]))
            centre = jnp.asarray(self.centres[i])
            return r, centre + c[:3] - r @ centre
        if isinstance(joint, Revolute):
            r = _axis_angle(jnp.asarray(joint.axis), c[0])
            origin = jnp.asarray(joint.origin)
            return r, origin - r @ origin
        if isinstance(joint, Prismatic):
            return jnp.eye(3), c[0] * jnp.asarray(joint.axis)
        return jnp.eye(3), jnp.zeros(3)

    def transforms(self, z: Array) -> tuple[Array, Array]:
        """World transforms of the links by prefix products, top-down.

        Arguments:
            z: ``(n_coords,)`` coordinates.

        Returns:
            ``(R, p)``: ``(L, 3, 3)`` rotations and ``(L, 3)`` translations; link ``l``
            maps rest positions ``X`` to ``R[l] X + p[l]``.
        """
        rs, ps = [], []
        for i in range(len(self.links)):
            rj, pj = self._joint(i, z)
            if self.parent[i] >= 0:
                rp, pp = rs[self.parent[i]], ps[self.parent[i]]
                rj, pj = rp @ rj, rp @ pj + pp
            rs.append(rj)
            ps.append(pj)
        return jnp.stack(rs), jnp.stack(ps)

    def positions(self, z: Array) -> Array:
        """Forward kinematics: bone vertex positions ``(n_b, 3)`` (in :attr:`bone` order)."""
        r, p = self.transforms(z)
        link = jnp.asarray(self.vertex_link)
        return jnp.einsum("vij,vj->vi", r[link], jnp.asarray(self.rest)) + p[link]

    def jacobian(self, z: Array) -> Array:
        """``B = dx_bone/dz`` in tangent coordinates, shape ``(n_b, 3, n_dofs)``.

        Column ``k`` is the world twist ``(w_k, u_k)`` of dof ``k`` applied to the vertices
        it moves: ``B[v, :, k] = w_k x x_v + u_k``.
        """
        r, p = self.transforms(z)
        ws, us = [], []
        for i, link in enumerate(self.links):
            joint = link.joint
            rp, pp = (r[self.parent[i]], p[self.parent[i]]) if self.parent[i] >= 0 else (jnp.eye(3), jnp.zeros(3))
            if isinstance(joint, Free):
                c = z[self.coord_start[i]:self.coord_start[i] + 3] + jnp.asarray(self.centres[i])
                ws += [jnp.zeros(3)] * 3 + list(jnp.eye(3))
                us += list(jnp.eye(3)) + [-jnp.cross(e, c) for e in jnp.eye(3)]
            elif isinstance(joint, Revolute):
                w = rp @ jnp.asarray(joint.axis)
                ws.append(w)
                us.append(-jnp.cross(w, rp @ jnp.asarray(joint.origin) + pp))
            elif isinstance(joint, Prismatic):
                ws.append(jnp.zeros(3))
                us.append(rp @ jnp.asarray(joint.axis))
        if not ws:
            return jnp.zeros((len(self.bone), 3, 0))
        w, u = jnp.stack(ws), jnp.stack(us)  # (k, 3)
        x = self.positions(z)
        cols = jnp.cross(w[None, :, :], x[:, None, :]) + u[None]  # (n_b, k, 3)
        return jnp.swapaxes(cols, 1, 2) * jnp.asarray(self.moves)[:, None, :]

    def retract(self, z: Array, dz: Array) -> Array:
        """Move ``z`` by the tangent step ``dz`` ``(n_dofs,)`` and stay on the manifold.

        Angles and slides add (then are clamped to their limits); a Free joint's position
        adds and its rotation composes, ``q <- exp(dphi) q``, re-normalised.
        """
        parts = []
        for i, link in enumerate(self.links):
            c, d = z[self.coord_start[i]:self.coord_start[i + 1]], dz[self.dof_start[i]:self.dof_start[i + 1]]
            if isinstance(link.joint, Free):
                q = _quat_mul(_quat_exp(d[3:]), c[3:])
                parts += [c[:3] + d[:3], q / jnp.linalg.norm(q)]
            elif isinstance(link.joint, (Revolute, Prismatic)):
                k = self.dof_start[i]
                parts.append(jnp.clip(c + d, self.lower[k], self.upper[k]))
        return jnp.concatenate(parts) if parts else z

    def coordinates(self, x_bone: Array) -> Array:
        """The coordinates ``(n_coords,)`` whose FK best fits bone positions ``(n_b, 3)``.

        Each link's rigid transform is the least-squares fit (Kabsch: the rotation of the
        covariance of positions and rest positions, by :func:`softbody.rotation.polar`,
        which is differentiable); the joint coordinates are read off the transforms of
        each link relative to its parent's. Exact (to round-off) for positions produced by
        :meth:`positions`; revolute angles come back in ``(-pi, pi]``.
        """
        link = jnp.asarray(self.vertex_link)
        n_links = len(self.links)
        count = jnp.zeros(n_links).at[link].add(1.0)[:, None]
        rest = jnp.asarray(self.rest)
        xm = jnp.zeros((n_links, 3)).at[link].add(x_bone) / count
        rm = jnp.zeros((n_links, 3)).at[link].add(rest) / count
        cov = jnp.einsum("vi,vj->vij", x_bone - xm[link], rest - rm[link])
        h = jnp.zeros((n_links, 3, 3)).at[link].add(cov)
        r = jnp.moveaxis(rot.polar(jnp.moveaxis(h, 0, -1), iterations=3), -1, 0)
        p = xm - jnp.einsum("lij,lj->li", r, rm)
        parts = []
        for i, lk in enumerate(self.links):
            joint = lk.joint
            rp, pp = (r[self.parent[i]], p[self.parent[i]]) if self.parent[i] >= 0 else (jnp.eye(3), jnp.zeros(3))
            r_rel, p_rel = rp.T @ r[i], rp.T @ (p[i] - pp)
            if isinstance(joint, Free):
                centre = jnp.asarray(self.centres[i])
                parts += [p_rel + r_rel @ centre - centre, rot.mat_to_quat(r_rel[:, :, None])[:, 0]]
            elif isinstance(joint, Revolute):
                a = jnp.asarray(joint.axis)
                axial = jnp.array([r_rel[2, 1] - r_rel[1, 2], r_rel[0, 2] - r_rel[2, 0], r_rel[1, 0] - r_rel[0, 1]])
                parts.append(jnp.arctan2(0.5 * a @ axial, 0.5 * (jnp.trace(r_rel) - 1.0))[None])
            elif isinstance(joint, Prismatic):
                parts.append((jnp.asarray(joint.axis) @ p_rel)[None])
        return jnp.concatenate(parts) if parts else jnp.zeros(0)

    def joint_values(self, z: Array) -> Array:
        """Angle (rad) or slide (m) of every revolute and prismatic joint, ``(n_dofs,)``
        layout with Free rows set to 0."""
        out = jnp.zeros(self.n_dofs)
        for i, link in enumerate(self.links):
            if isinstance(link.joint, (Revolute, Prismatic)):
                out = out.at[self.dof_start[i]].set(z[self.coord_start[i]])
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


class SchurFactor(NamedTuple):
    """The PD matrix ``A`` condensed onto the bone vertices (see :func:`schur_factor`).

    Attributes:
        schur: ``(n_b, n_b)`` the Schur complement ``S0 = Q_rr - Q_rf Q_ff^-1 Q_fr``.
        coupling: ``(n, n_b)`` ``W = A^-1 E_r S0`` (``E_r``: the bone vertices' unit vectors).
    """

    schur: Array
    coupling: Array


def schur_factor(precondition, bone: np.ndarray, n: int) -> SchurFactor:
    """Condense the PD matrix onto the bone vertices.

    With ``A = [[Q_ff, Q_fr], [Q_rf, Q_rr]]`` (free and bone vertices; scalar ``n x n``),
    the Schur complement ``S0 = Q_rr - Q_rf Q_ff^-1 Q_fr`` is the inverse of the bone block
    ``C_rr`` of ``C = A^-1 E_r``. Both come from one solve with the prefactored ``A``
    (``precondition``) for the ``n_b`` unit columns and a dense Cholesky inversion of size
    ``n_b``; no separate factorisation of ``Q_ff`` is needed, as ``Q_ff^-1`` is applied
    through ``A^-1`` in :func:`schur_direction`.

    Arguments:
        precondition: ``b (n, k) -> A^-1 b``.
        bone: ``(n_b,)`` bone vertex indices.
        n: number of vertices.

    Returns:
        A :class:`SchurFactor`.
    """
    bone = jnp.asarray(bone)
    unit = jnp.zeros((n, len(bone))).at[bone, jnp.arange(len(bone))].set(1.0)
    columns = precondition(unit)
    block = columns[bone]
    cholesky = jnp.linalg.cholesky(0.5 * (block + block.T))
    schur = jax.scipy.linalg.cho_solve((cholesky, True), jnp.eye(len(bone)))
    schur = 0.5 * (schur + schur.T)
    return SchurFactor(schur, columns @ schur)


def schur_direction(factor: SchurFactor, bone: np.ndarray, b: Array, g: Array, locked: Array,
                    precondition) -> tuple[Array, Array]:
    """The reduced PD step: solve ``[[Q_ff, Q_fr B], [B^T Q_rf, B^T Q_rr B]] (d_f, d_z) = (g_f, B^T g_r)``.

    The quadratic model ``1/2 d^T A d - g . d`` is minimised over the displacements whose
    bone rows are ``B d_z``. With ``u = A^-1 g``::

        (B^T S0 B) d_z = B^T S0 u_r,    d = u - W (u_r - B d_z),

    one solve with ``A``, products with the dense ``S0`` and ``W`` and a dense system of
    size ``n_dofs`` (the bone rows of ``d`` come out as ``B d_z``). This is the Schur
    complement on the ``z`` block written through ``A^-1``:
    ``Q_ff^-1 = (A^-1)_ff - C_f S0 C_f^T``.

    Arguments:
        factor: from :func:`schur_factor`.
        bone: ``(n_b,)`` bone vertex indices.
        b: ``(n_b, 3, n_dofs)`` Jacobian.
        g: ``(n, 3)`` gradient of the objective (all vertices).
        locked: ``(n_dofs,)`` 1 for dofs held fixed in this step (at an active limit), else 0.
        precondition: ``r (n, 3) -> A^-1 r``.

    Returns:
        ``(d, d_z)``: ``(n, 3)`` displacement (bone rows ``B d_z``) and ``(n_dofs,)``; the
        step is ``x - d``, ``z - d_z``.
    """
    n_b, _, k = b.shape
    b = b * (1.0 - locked)
    u = precondition(g)
    u_r = u[jnp.asarray(bone)]
    sb = (factor.schur @ b.reshape(n_b, 3 * k)).reshape(n_b, 3, k)
    small = jnp.einsum("vik,vil->kl", b, sb) + jnp.diag(locked)
    d_z = jnp.linalg.solve(small, jnp.einsum("vik,vi->k", sb, u_r))
    return u - factor.coupling @ (u_r - jnp.einsum("vik,k->vi", b, d_z)), d_z


@dataclass(frozen=True, eq=False)
class SkeletonPD(IterationMethod):
    """Implicit steps with rigid bones in reduced coordinates (see the module docstring).

    Each iteration evaluates ``Phi`` and its gradient at ``x = assemble(x_free, FK(z))``,
    forms the reduced gradient ``(g_f, B^T g_r)``, takes the direction of
    :func:`schur_direction`, and backtracks (halving) until Armijo's condition holds.
    Updates stay on the manifold (:meth:`Rig.retract`); a joint at a limit whose gradient
    pushes it outward is held for that iteration. The step starts from ``z`` fitted to the
    inertial prediction ``x_n + h v_n`` of the bones (:meth:`Rig.coordinates`), so no state
    beyond the positions is needed; :func:`schur_factor` is computed once per step.

    Attributes:
        rig: the :class:`Rig` (skeleton bound to the scene's mesh).
        backtracks: the most halvings of a step (static).

    The PD matrix is prefactored with the true volume weight (``volume_weight = 1``), for
    which the PD model majorises the elastic energy.

    Gradients: differentiate skeleton scenes with :class:`~softbody.gradients.Unrolled`.
    The implicit adjoint assumes ``grad Phi = 0`` at every free vertex, which does not
    hold on bone vertices (they carry the joints' constraint forces).

    Raises:
        SkeletonError: (in ``run``) the rig was bound to a mesh of another size.
        equinox.EquinoxRuntimeError: (at run time) a bone vertex is fixed.
    """

    rig: Rig
    backtracks: int = 8

    def __post_init__(self):
        if not isinstance(self.rig, Rig):
            raise SkeletonError(f"SkeletonPD.rig must be a Rig (Skeleton.bind(mesh)), got {type(self.rig).__name__}")
        if int(self.backtracks) != self.backtracks or self.backtracks < 0:
            raise SkeletonError(f"SkeletonPD.backtracks must be an integer >= 0, got {self.backtracks!r}")

    def _check(self, problem: StepProblem, x0: Array) -> Array:
        n = x0.shape[0]
        if n != self.rig.n_vertices:
            raise SkeletonError(f"the rig was bound to a mesh of {self.rig.n_vertices} vertices, the scene has {n}")
        fixed = jnp.any(problem.free[jnp.asarray(self.rig.bone)] == 0)
        return eqx.error_if(x0, fixed, "softbody: some bone vertices are fixed; bones move with their joints "
                                       "(weld a bone to the world with a root Fixed() joint instead)")

    def run(self, problem, x0, q0, threshold, max_iter, unrolled=False):
        rig, evaluate, precondition = self.rig, problem.evaluate, problem.precondition
        x0 = self._check(problem, x0)
        n = x0.shape[0]
        bone = jnp.asarray(rig.bone)
        is_bone = jnp.zeros((n, 1)).at[bone].set(1.0)
        factor = schur_factor(precondition, rig.bone, n)
        lower, upper = jnp.asarray(rig.lower), jnp.asarray(rig.upper)

        def assemble(x, z):
            return x.at[bone].set(rig.positions(z))

        def reduced(g, z):
            """``B``, the dofs held at a limit this iteration, and the norm of ``(g_f, B^T g_r)``
            over the dofs that may move."""
            b = rig.jacobian(z)
            g_z = jnp.einsum("vik,vi->k", b, g[bone])
            value = rig.joint_values(z)
            locked = (((value <= lower) & (g_z > 0)) | ((value >= upper) & (g_z < 0))).astype(g.dtype)
            gnorm = jnp.sqrt(jnp.sum((g * (1.0 - is_bone)) ** 2) + jnp.sum((g_z * (1.0 - locked)) ** 2))
            return b, locked, gnorm

        z0 = rig.coordinates(x0[bone])
        x0 = assemble(x0, z0)
        phi0, g0, q0 = evaluate(x0, q0)

        def cond(c):
            return (c[7] > threshold) & (c[9] < max_iter)

        def body(c):
            x, z, q, phi, g, b, locked, _, evals, k = c
            d, d_z = schur_direction(factor, rig.bone, b, g, locked, precondition)
            slope = jnp.sum(g * d)  # -dPhi/dalpha along (x - alpha d, z - alpha d_z)

            def trial(alpha):
                z_t = rig.retract(z, -alpha * d_z)
                x_t = assemble(x - alpha * d * (1.0 - is_bone), z_t)
                phi_t, g_t, q_t = evaluate(x_t, q)
                return x_t, z_t, q_t, phi_t, g_t

            def rejected(t):
                alpha, tries, (_, _, _, phi_t, _) = t
                return (~(phi_t <= phi - 1e-4 * alpha * slope + 1e-14 * jnp.abs(phi))) & (tries < self.backtracks)

            def halve(t):
                alpha, tries, _ = t
                return alpha / 2, tries + 1, trial(alpha / 2)

            _, tries, (x, z, q, phi, g) = iterate(rejected, halve, (jnp.asarray(1.0), jnp.asarray(0), trial(1.0)),
                                                  self.backtracks, unrolled)
            return (x, z, q, phi, g, *reduced(g, z), evals + 1 + tries, k + 1)

        init = (x0, z0, q0, phi0, g0, *reduced(g0, z0), jnp.asarray(1), jnp.asarray(0))
        x, _, q, _, _, _, _, gnorm, evals, k = iterate(cond, body, init, max_iter, unrolled)
        return Solution(x, q, k, evals, gnorm)

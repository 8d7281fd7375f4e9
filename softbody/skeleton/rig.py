"""Kinematics: a skeleton bound to a mesh's bones, its coordinates, forward kinematics and
Jacobians (see :mod:`softbody.skeleton`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from softbody import rotation as rot
from softbody.meshing import TetMesh
from softbody.skeleton.joints import _N_COORDS, _N_DOFS, JOINTS, Free, Link, Prismatic, Revolute, SkeletonError

Array = jax.Array


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
    """Products ``a b`` of quaternions ``(..., 4)`` ``(w, x, y, z)``."""
    w1, x1, y1, z1 = jnp.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = jnp.moveaxis(b, -1, 0)
    return jnp.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                      w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=-1)


def _quat_exp(phi):
    """Unit quaternions ``(..., 4)`` of the rotation vectors ``phi`` ``(..., 3)``, smooth at 0."""
    half2 = 0.25 * jnp.sum(phi * phi, axis=-1)  # (angle / 2)^2
    small = half2 < 1e-8
    half = jnp.sqrt(jnp.where(small, 1.0, half2))
    sinc = jnp.where(small, 0.5 - half2 / 12.0, 0.5 * jnp.sin(half) / half)
    cos = jnp.where(small, 1.0 - 0.5 * half2, jnp.cos(half))
    return jnp.concatenate([cos[..., None], sinc[..., None] * phi], axis=-1)


def _quat_matrix(q):
    """Rotation matrices ``(F, 3, 3)`` of unit quaternions ``(F, 4)``."""
    return jnp.moveaxis(rot.quat_to_mat(q.T), -1, 0)


class Pose(NamedTuple):
    """The skeleton at coordinates ``z``: link transforms, bone positions and dof twists.

    Attributes:
        r: ``(L, 3, 3)`` link rotations; p: ``(L, 3)`` translations (rest ``X`` maps to
            ``r[l] X + p[l]``).
        x: ``(n_b, 3)`` bone vertex positions.
        twists: ``(L, 6, K)`` the world twist ``(u, w)`` of each dof of link ``l``'s tree
            as it moves link ``l``, in the tree's slots (:attr:`Rig.tree_dofs`; zero where
            the dof's joint is not ``l`` or an ancestor of it, and on padding slots): a bone
            vertex ``x`` of link ``l`` moves by ``u + w x x`` per unit of the dof. ``K`` is
            the most dofs of one tree, so the twists grow with the number of links, not
            with the links times the dofs.
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
        tree_index: ``(L,)`` the index of each link's tree (``0 .. T - 1``, the trees in the
            order of their roots).
        tree_dofs: ``(T, K)`` each tree's dofs (tangent indices, in order), padded with
            ``n_dofs``; ``K`` is the most dofs of one tree. Nothing couples two trees'
            dofs kinematically, so blocks of this layout (:meth:`blocks`) make the skeleton's
            small solves one ``K x K`` system per tree (free rigid bodies: ``6 x 6`` each).
        vertex_tree: ``(n_b,)`` the tree index of each bone vertex.
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
        roots, tree_index = np.unique(root, return_inverse=True)
        tree_members = [np.concatenate([np.arange(dof_start[i], dof_start[i + 1]) for i in np.flatnonzero(root == r)])
                        for r in roots]
        width = max([len(d) for d in tree_members] + [0])
        tree_dofs = np.full((len(roots), width), int(dof_start[-1]), np.int64)
        for t, members in enumerate(tree_members):
            tree_dofs[t, :len(members)] = members
        # moves[l, s]: the dof in slot s of link l's tree moves link l (its joint is l or an ancestor)
        moves = np.concatenate([ancestor[:, dof_link], np.zeros((n_links, 1), bool)], axis=1)
        local_moves = np.take_along_axis(moves, tree_dofs[tree_index], axis=1).astype(np.float64)
        free = np.array([i for i, link in enumerate(links) if isinstance(link.joint, Free)], np.int64)
        all_bone = np.concatenate(bone)
        skin = np.flatnonzero(np.isin(all_bone, np.asarray(mesh.surface)) & moved_link[vertex_link])
        for name, value in dict(
                bone=np.concatenate(bone).astype(np.int32), vertex_link=vertex_link,
                rest=mesh.points[np.concatenate(bone)], parent=parent,
                coord_start=coord_start, dof_start=dof_start,
                moves=local_moves, link_count=np.bincount(vertex_link, minlength=n_links).astype(np.float64),
                rest_mean=np.stack([mesh.points[v].mean(axis=0) for v in bone]),
                levels=[np.flatnonzero(depth == d) for d in range(1, int(depth.max()) + 1)],
                free_links=free, free_coords=coord_start[free][:, None] + np.arange(7),
                free_dofs=dof_start[free][:, None] + np.arange(6),
                free_centres=np.array([centres[i] for i in free], np.float64).reshape(-1, 3),
                scalar_links=scalar, scalar_coords=coord_start[scalar], scalar_dofs=dof_start[scalar],
                rot_axis=rot_axis, slide_axis=slide_axis, origin=origin,
                lower=lo, upper=hi, n_vertices=mesh.n_vertices, detached_dofs=np.repeat(detached, n_dofs).astype(float),
                skin=skin, tree=root, tree_index=tree_index, tree_dofs=tree_dofs,
                vertex_tree=tree_index[vertex_link],
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
        if len(self.free_links):  # all Free joints at once (they are roots)
            c = z[self.free_coords]  # (F, 7)
            ri = _quat_matrix(c[:, 3:] / jnp.linalg.norm(c[:, 3:], axis=1, keepdims=True))
            centre = jnp.asarray(self.free_centres)
            r = r.at[self.free_links].set(ri)
            p = p.at[self.free_links].set(centre + c[:, :3] - jnp.einsum("fij,fj->fi", ri, centre))
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
        twist = jnp.zeros((k + 1, 6))  # a zero row for the padding slots of tree_dofs
        if len(self.scalar_links):
            twist = twist.at[self.scalar_dofs].set(jnp.concatenate([u, w], axis=1)[self.scalar_links])
        if len(self.free_links):
            c = z[self.free_coords[:, :3]] + jnp.asarray(self.free_centres)  # (F, 3) world centres
            eye = jnp.broadcast_to(jnp.eye(3), (len(c), 3, 3))
            block = jnp.concatenate([jnp.concatenate([eye, jnp.zeros_like(eye)], axis=2),
                                     jnp.concatenate([-jnp.cross(eye, c[:, None, :]), eye], axis=2)], axis=1)
            twist = twist.at[self.free_dofs].set(block)
        twists = jnp.asarray(self.moves)[:, None, :] * jnp.swapaxes(twist[self.tree_dofs[self.tree_index]], 1, 2)
        return Pose(r, p, self._place(r, p), twists)

    def jacobian(self, z: Array) -> Array:
        """``B = dx_bone/dz`` in tangent coordinates, shape ``(n_b, 3, n_dofs)``.

        Column ``k`` is the world twist ``(u_k, w_k)`` of dof ``k`` applied to the vertices
        it moves: ``B[v, :, k] = u_k + w_k x x_v``. Dense: the solves use the blocks of
        :meth:`local_jacobian` instead.
        """
        local = self.local_jacobian(self.pose(z))
        dense = jnp.zeros((len(self.bone), 3, self.n_dofs + 1), local.dtype)
        rows = jnp.arange(len(self.bone))[:, None, None]
        dense = dense.at[rows, jnp.arange(3)[None, :, None], self.tree_dofs[self.vertex_tree][:, None, :]].set(local)
        return dense[:, :, :-1]

    def local_jacobian(self, pose: Pose) -> Array:
        """``B`` by trees: ``(n_b, 3, K)``, row ``v`` over the slots of vertex ``v``'s tree
        (:attr:`tree_dofs`; zero on padding slots)."""
        t = pose.twists[jnp.asarray(self.vertex_link)]  # (n_b, 6, K)
        return t[:, :3] - jnp.einsum("vij,vjk->vik", _skew(pose.x), t[:, 3:])

    def blocks(self, v: Array) -> Array:
        """A tangent vector ``(n_dofs,)`` by trees: ``(T, K)``, zero on padding slots."""
        return jnp.concatenate([v, jnp.zeros(1, v.dtype)])[self.tree_dofs]

    def unblock(self, b: Array) -> Array:
        """The inverse of :meth:`blocks`: ``(T, K)`` to ``(n_dofs,)`` (padding slots dropped)."""
        return jnp.zeros(self.n_dofs + 1, b.dtype).at[self.tree_dofs].set(b)[:-1]

    def _per_link(self, a: Array) -> Array:
        """Sums of the per-bone-vertex rows ``a`` ``(n_b, ...)`` over each link: ``(L, ...)``."""
        return jax.ops.segment_sum(a, jnp.asarray(self.vertex_link), len(self.links), indices_are_sorted=True)

    def reduce(self, pose: Pose, force: Array) -> Array:
        """``B^T f``: the generalised force ``(n_dofs,)`` of bone-vertex forces ``f`` ``(n_b, 3)``.

        Summed per link as a wrench (force, and moment about the link's centroid ``c``, so
        that a body far from the origin loses no digits to the moment's cancellation), then
        mapped by the twists moved to ``c`` (``u + w x c``, ``w``); no ``(n_b, 3, n_dofs)``
        Jacobian is formed, and the cost is linear in the links.
        """
        link = jnp.asarray(self.vertex_link)
        centre = jnp.einsum("lij,lj->li", pose.r, jnp.asarray(self.rest_mean)) + pose.p  # (L, 3): x = R X + p
        net, moment = self._per_link(force), self._per_link(jnp.cross(pose.x - centre[link], force))
        u, w = pose.twists[:, :3], pose.twists[:, 3:]  # (L, 3, K)
        u_centre = u + jnp.cross(w, centre[:, :, None], axis=1)
        per_dof = jnp.einsum("li,lik->lk", net, u_centre) + jnp.einsum("li,lik->lk", moment, w)  # (L, K)
        slots = self.tree_dofs[self.tree_index]
        return jnp.zeros(self.n_dofs + 1, per_dof.dtype).at[slots].add(per_dof)[:-1]

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
        if len(self.free_links):
            c, d = z[self.free_coords], dz[self.free_dofs]  # (F, 7), (F, 6)
            q = _quat_mul(_quat_exp(d[:, 3:]), c[:, 3:])
            z = z.at[self.free_coords].set(
                jnp.concatenate([c[:, :3] + d[:, :3], q / jnp.linalg.norm(q, axis=1, keepdims=True)], axis=1))
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
        n_links = len(self.links)
        rest = jnp.asarray(self.rest)
        link = jnp.asarray(self.vertex_link)
        xm = self._per_link(x_bone) / self.link_count[:, None]
        rm = jnp.asarray(self.rest_mean)
        h = self._per_link(jnp.einsum("vi,vj->vij", x_bone - xm[link], rest - rm[link]))
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
        if len(self.free_links):  # roots: relative to the world
            centre, i = jnp.asarray(self.free_centres), self.free_links
            z = z.at[self.free_coords[:, :3]].set(p_rel[i] + jnp.einsum("fij,fj->fi", r_rel[i], centre) - centre)
            z = z.at[self.free_coords[:, 3:]].set(rot.mat_to_quat(jnp.moveaxis(r_rel[i], 0, -1)).T)
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


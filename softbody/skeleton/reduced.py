"""A skeleton's reduced coordinates: the step solved over the soft vertices and the joint
coordinates, with and without contact (see :mod:`softbody.skeleton`)."""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import Capabilities, Chart, ContactSweep, Coordinates, RigidParts
from softbody.skeleton.condense import SchurFactor, _held, _solve_reduced, schur_factor
from softbody.skeleton.joints import SkeletonError
from softbody.skeleton.rig import Rig
from softbody.solvers import LBFGS, LocalGlobal

Array = jax.Array


@dataclass(frozen=True)
class Reduced(Coordinates):
    """A skeleton's reduced coordinates: the soft vertices and the joint coordinates ``z``,
    bones placed by ``FK(z)`` (see the module docstring). :func:`~softbody.model.build`
    chooses them for a scene with a skeleton.

    **Without contact** (:meth:`chart`: the step's solver, L-BFGS or local-global, runs
    its one loop :func:`softbody.solvers.descend` in these coordinates) each iteration
    evaluates ``Phi`` and its gradient
    at ``x = assemble(x_free, FK(z))``, forms the reduced gradient ``(g_f, B^T g_r)``, takes
    the L-BFGS direction in the reduced coordinates (the solver's ``history`` pairs;
    :class:`~softbody.solvers.LocalGlobal` keeps none) with the reduced PD solve
    (:func:`schur_direction`) as its initial inverse Hessian, and backtracks (halving, at
    most ``backtracks`` times) until Armijo's condition holds. The PD matrix holds the elastic and inertial terms
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

    Convergence carries over from :class:`~softbody.contact.splitting.ScaledDiagonal`'s theorem:
    with ``T = diag(I, B)`` the reduced matrices are ``T^T L T`` and ``T^T (M/h^2 + D) T``,
    the latter block diagonal (``D`` is diagonal), and ``L <= 4 diag(L)`` gives
    ``T^T L T <= 2 T^T D T``, so the frozen-projection iteration matrix again has its
    eigenvalues in ``[-beta, beta]``, ``beta < 1`` (``B^T M_b B > 0`` as every bone has a
    volume). The residual is ``|P (x_new - x)|`` over the soft vertices together with the
    reduced force ``|B^T g_b|`` of the joints free to move: zero exactly at the step's
    equilibrium with contact. Obstacle contact acts on the soft vertices and the skin (a
    rigid body's surface); pair rows between bodies act on bone and rigid vertices too
    (their forces enter the bones' reduced gradient, :class:`~softbody._interfaces.RigidParts`).

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
        contact_sweeps: Jacobi sweeps of the skin's obstacle forces per contact iteration
            (static).
        pair_sweeps: Jacobi sweeps of the pair rows' forces per contact iteration where
            pair rows meet bones or rigid bodies, each followed by one update of the skin's
            obstacle forces (static; see :mod:`softbody.contact.pairs`).

    Raises:
        SkeletonError: a bad attribute.
    """

    solvers = (LBFGS, LocalGlobal)
    capabilities = Capabilities(
        refuses={"partly held vertices": "holds vertices in all three components only (its reduced coordinates move "
                                         "whole vertices)"},
        instead="fix them with fixed=<selection> (or a Fix with axes='xyz'), or weld a bone with a root Fixed() joint")
    rig: Rig
    backtracks: int = 8
    contact_sweeps: int = 10
    pair_sweeps: int = 30

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

    def contact_rows(self) -> int:
        """One extra row per skin vertex (a bone vertex that may touch an obstacle)."""
        return len(self.rig.skin)

    def contact_sweep(self, problem, p, law):
        """The soft vertices take the per-vertex contact step; the skeleton sweeps its block
        with the contact forces on its skin (see the class docstring). See
        :meth:`softbody._interfaces.Coordinates.contact_sweep`."""
        rig = self.rig
        n, bone, skin = rig.n_vertices, jnp.asarray(rig.bone), rig.skin
        p_bone = p[bone, 0]
        owners = np.asarray(rig.bone)[skin]
        index = jnp.asarray(owners)
        valid = problem.free[index, 0] > 0
        # The skeleton's small solves go tree by tree (Rig.tree_dofs): nothing couples two
        # trees' dofs in K = B^T P_b B, so each is one K x K block (6 x 6 for a free rigid
        # body) and the cost grows with the number of trees, not with its cube.
        vertex_tree, skin_tree = jnp.asarray(rig.vertex_tree), jnp.asarray(rig.vertex_tree[skin])
        n_trees = len(rig.tree_dofs)

        def place(x):
            x = x if x.shape[0] == n else x[:n]
            z = rig.coordinates(x[bone])
            pose = rig.pose(z)
            return x.at[bone].set(pose.x), (z, pose)

        def stiffness(jac):
            """The sweep's block ``K = B^T P_b B`` by trees, ``(T, K, K)``, from the
            Jacobian by trees ``jac`` ``(n_b, 3, K)`` (:meth:`Rig.local_jacobian`)."""
            if n_trees == 1:  # one tree (a jointed skeleton): one contraction, no per-vertex blocks
                return jnp.einsum("vik,v,vil->kl", jac, p_bone, jac)[None]
            return jax.ops.segment_sum(jnp.einsum("vik,v,vil->vkl", jac, p_bone, jac), vertex_tree, n_trees)

        def inverse(k_z, move):
            """``K^-1`` by trees ``(T, K, K)``, zero on the held dofs and padding slots
            (``move`` ``(T, K)``, :meth:`Rig.blocks`)."""
            mask = move[:, :, None] * move[:, None, :]
            eye = jnp.eye(k_z.shape[-1], dtype=k_z.dtype)
            return jnp.linalg.inv(k_z * mask + eye * (1.0 - move)[:, :, None]) * mask

        def times(k_inv, b):
            """``K^-1 b`` by trees: ``(T, K)``."""
            return jnp.einsum("tkl,tl->tk", k_inv, b)

        def motion(jac, d, trees):
            """``B d``: the vertices' motion ``(v, 3)`` for the tree steps ``d`` ``(T, K)``."""
            return jnp.einsum("vik,vk->vi", jac, d[trees])

        def skin_load(b_skin, force):
            """``B_C^T f`` by trees ``(T, K)``: the skin's forces ``f`` ``(c, 3)`` as generalised forces."""
            if n_trees == 1:
                return jnp.einsum("cik,ci->k", b_skin, force)[None]
            return jax.ops.segment_sum(jnp.einsum("cik,ci->ck", b_skin, force), skin_tree, n_trees)

        def delassus_diagonal(b_skin, k_inv):
            """``(c, 3)`` the diagonal of ``W = B_C K^-1 B_C^T`` (the skin's Delassus operator)."""
            return jnp.maximum(jnp.einsum("cik,ckl,cil->ci", b_skin, k_inv[skin_tree], b_skin), 0.0)

        def forces(x):
            return scale * x[n:]

        # Pair rows on bone vertices: each skin vertex's Delassus diagonal at the step's
        # start (mean over the axes), shared among the rows on its tree.
        jac_n = rig.local_jacobian(rig.pose(rig.coordinates(problem.x_n[bone])))
        w_n = delassus_diagonal(jac_n[skin], inverse(stiffness(jac_n), rig.blocks(jnp.ones(rig.n_dofs, p.dtype))))
        soft = problem.free * (1.0 - rig.is_bone)
        compliance = (soft / p).at[index].set(w_n.mean(axis=1)[:, None])
        body = np.arange(n)
        body[rig.bone] = n + rig.vertex_tree
        # The extra rows hold the skin's contact forces over the effective mass of each skin
        # vertex at the step's start (so that they are displacements, as the other rows).
        scale = (3.0 / jnp.maximum(w_n.sum(axis=1), 1e-300))[:, None]

        def skin_update(at, force, root):
            """One relaxed projected Jacobi update of the skin's contact forces ``force``
            ``(c, 3)`` with the skin vertices at ``at`` ``(c, 3)`` (where the body puts them
            under the current forces) and ``root`` ``(c, 3)`` the square roots of the
            Delassus diagonal (see ``sweep``)."""
            w = jnp.sum(root**2, axis=1) / 3.0
            near, _, _, _ = law(at, index, valid)
            active = near | jnp.any(force != 0, axis=1)
            reach = jax.ops.segment_sum(jnp.where(active, root.sum(axis=1), 0.0), skin_tree, n_trees)[skin_tree]
            bound = root.max(axis=1) * (reach + jnp.where(active, 0.0, root.sum(axis=1)))
            touching, _, correction, _ = law(at - force * w[:, None], index, valid, kinetic=True)
            target = jnp.where(touching[:, None], correction, 0.0) / jnp.where(w > 0, w, 1.0)[:, None]
            fraction = jnp.where(bound > 0, w / jnp.where(bound > 0, bound, 1.0), 0.0)
            return force + fraction[:, None] * (target - force)

        def respond(aux):
            """The soft vertices move by ``force / P``, the bones by ``B K^-1 B^T force``
            (the Jacobian at ``aux``'s pose made once for every sweep of an iteration); then
            the skin's obstacle forces take one update at the new positions and the bones
            respond to their change, so that a part's pair rows and obstacle rows relax
            together (a soft body on a rigid box on the ground)."""
            z, pose = aux
            jac = rig.local_jacobian(pose)
            k_z = stiffness(jac)
            if len(skin):
                value = rig.joint_values(z)
                free_dofs = 1.0 - ((value <= jnp.asarray(rig.lower)) | (value >= jnp.asarray(rig.upper))).astype(
                    p.dtype)
                k_free = inverse(k_z, rig.blocks(free_dofs))  # joints at a limit held while the skin relaxes
                root = jnp.sqrt(delassus_diagonal(jac[skin], k_free))

            def move_by(x, force):
                g_z = -rig.reduce(pose, force[bone])
                move = 1.0 - _held(rig, z, g_z)
                shift = motion(jac, times(inverse(k_z, rig.blocks(move)), rig.blocks(-g_z)), vertex_tree)
                x = x.at[:n].add(soft * force / p).at[bone].add(shift)
                if not len(skin):
                    return x
                old = forces(x)
                new = skin_update(x[index], old, root)
                pushed = skin_load(jac[skin], new - old)
                return x.at[bone].add(motion(jac, times(k_free, pushed), vertex_tree)).at[n:].set(new / scale)

            return move_by

        rigid = RigidParts(compliance, body, respond, self.pair_sweeps)

        if not len(skin):
            def sweep(x, x_new, g, aux):
                z, pose = aux
                jac = rig.local_jacobian(pose)  # (n_b, 3, K)
                g_z = rig.reduce(pose, g[bone])
                move = 1.0 - _held(rig, z, g_z)
                d_z = rig.unblock(times(inverse(stiffness(jac), rig.blocks(move)), rig.blocks(g_z * move)))
                return x_new.at[bone].set(rig.positions(rig.retract(z, -d_z))), g_z * move

            scale = jnp.zeros((0, 1), p.dtype)
            return ContactSweep(soft, place, sweep, owners, scale, forces, rigid)

        def sweep(x, x_new, g, aux):
            z, pose = aux
            force = forces(x)  # (c, 3) contact forces on the skin
            jac = rig.local_jacobian(pose)
            b_skin = jac[skin]
            g_z = rig.blocks(rig.reduce(pose, g[bone]))  # (T, K)
            net = rig.unblock(g_z - skin_load(b_skin, force))
            move = 1.0 - _held(rig, z, net)
            k_inv = inverse(stiffness(jac), rig.blocks(move))
            # The contact forces by relaxed projected Jacobi sweeps on the Delassus operator
            # W (the body's motion linearised): each skin vertex takes the per-vertex contact
            # step, with the effective mass 1 / w_i of its diagonal block (w_i its mean
            # entry), from where the body's sweep puts it less its own force's displacement;
            # the force moves to that step's force by the fraction w_i / bound_i, with bound_i
            # >= the absolute row sums of W over the vertices pushing or about to touch (a
            # Gershgorin bound from |W_ij| <= sqrt(W_ii W_jj), per tree), so that the sweeps
            # converge for frictionless contact as the splitting does. At a fixed point the
            # body is in equilibrium with the forces, and each skin vertex satisfies the
            # contact law (on the surface, inside the cone, sliding against its slip; one cone
            # a step, the kinetic one where the vertex slides at the step's start, see
            # softbody.contact.law.SLIDING_SPEED): the fixed point does not depend on the bound.
            root = jnp.sqrt(delassus_diagonal(b_skin, k_inv))  # (c, 3)

            def update(force, _):
                moved = pose.x[skin] - motion(b_skin, times(k_inv, g_z - skin_load(b_skin, force)), skin_tree)
                return skin_update(moved, force, root), None

            force_new, _ = jax.lax.scan(update, force, None, length=self.contact_sweeps)
            d_z = rig.unblock(times(k_inv, g_z - skin_load(b_skin, force_new)))
            placed = x_new.at[bone].set(rig.positions(rig.retract(z, -d_z)))
            residual = jnp.concatenate([net * move, (force_new - force).ravel()])
            return jnp.concatenate([placed, force_new / scale]), residual

        return ContactSweep(soft, place, sweep, owners, scale, forces, rigid)

    def chart(self, problem):
        """The reduced coordinates as a :class:`~softbody._interfaces.Chart` for the step
        without contact (see the class docstring).

        Raises:
            SkeletonError: ``problem.prepared`` is not this rig's condensation.
        """
        if not isinstance(problem.prepared, SchurFactor):
            raise SkeletonError("reduced coordinates need their per-rollout condensation in problem.prepared; build "
                                "the step problem with softbody.model.prepare and softbody.objective.solve_step")
        return _ReducedChart(self.rig, problem, self.backtracks)


class _ReducedChart(Chart):
    """A point is ``(x (n, 3), z, pose)`` with the bones at ``FK(z)``; a tangent is flat
    ``(3 n + n_dofs,)``: the soft vertices' rows (zero on bone and held vertices), then the
    joint tangents. The gradient's data is ``(g_z, locked)``: the reduced gradient ``B^T g_r``
    and the dofs held at a limit this iteration (their tangent rows are masked out)."""

    def __init__(self, rig: Rig, problem, backtracks: int):
        self.rig, self.problem, self.backtracks = rig, problem, backtracks
        self.bone = jnp.asarray(rig.bone)
        self.soft = 1.0 - rig.is_bone
        self.n = problem.x_n.shape[0]

    def _flat(self, v_f, v_z):
        return jnp.concatenate([(v_f * self.soft).reshape(-1), v_z])

    def _unflat(self, v):
        return v[:3 * self.n].reshape(self.n, 3), v[3 * self.n:]

    def start(self, x0):
        z0 = self.rig.coordinates(x0[self.bone])
        pose0 = self.rig.pose(z0)
        return x0.at[self.bone].set(pose0.x), z0, pose0

    def positions(self, point):
        return point[0]

    def evaluate(self, point, q):
        return self.problem.evaluate(point[0], q)

    def gradient(self, point, g):
        _, z, pose = point
        g_z = self.rig.reduce(pose, g[self.bone])
        locked = _held(self.rig, z, g_z)
        move = 1.0 - locked
        gnorm = jnp.sqrt(jnp.sum((g * self.soft) ** 2) + jnp.sum((g_z * move) ** 2))
        return self._flat(g, g_z * move), gnorm, (g_z, locked)

    def precondition(self, point, data, r):
        _, locked = data
        move = 1.0 - locked
        r_f, r_z = self._unflat(r)
        d, d_z = _solve_reduced(self.problem.prepared, self.rig, point[2], r_f, r_z * move, locked)
        return self._flat(d, d_z * move)

    def project(self, data, d):
        d_f, d_z = self._unflat(d)
        return self._flat(d_f, d_z * (1.0 - data[1]))

    def move(self, point, step):
        x, z, _ = point
        step_f, step_z = self._unflat(step)
        z_t = self.rig.retract(z, step_z)
        pose_t = self.rig.pose(z_t)
        return (x + step_f).at[self.bone].set(pose_t.x), z_t, pose_t

    def pair(self, point, data, g, new, data_new, g_new, step):
        # The pairs leave out the free bodies' dofs, whose block the reduced PD solve holds
        # exactly (a free rigid body converges in one iteration, to 1e-17): their later
        # steps and gradient changes are round-off, which would set the quasi-Newton
        # matrix on them at random, and reverse mode through 1 / (s . y) of round-off
        # blows up (an unrolled solve beside a soft body).
        keep = 1.0 - self.rig.detached_dofs
        (x, z, _), (x_new, z_new, _) = point, new
        return (self._flat(x_new - x, self.rig.step_taken(z, z_new, self._unflat(step)[1]) * keep),
                self._flat(g_new - g, (data_new[0] - data[0]) * keep))

"""Skeletons: forward kinematics, the reduced (Schur-complement) step, rigid bones in soft
bodies, joint torques and servos, and the errors of bad skeletons.

Small structured meshes in float64. The pendulum and the torqued hinge are rigid bodies
whose motion is known in closed form; the arm is two bones in a soft skin.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.actuators.joints import JointServo, JointTorque
from softbody.gradients import Unrolled, check_grad
from softbody.material import Material
from softbody.meshing import Region
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.contact.obstacles import Plane
from softbody.simulate import contact_forces, rollout
from softbody.solvers import NonlinearSolver
from softbody.skeleton import (Fixed, Free, Link, Prismatic, Reduced, Revolute, Skeleton, SkeletonError,
                               schur_direction, schur_factor)

from incline import G, acceleration, ramped_gravity, rot_y

SKIN = Material(E=1e4, nu=0.3, density=1000.0)  # Pa, -, kg/m^3: a soft silicone skin


def _box_region(mesh, lo, hi) -> Region:
    """The vertices in the box ``[lo, hi]`` and the tets with all four corners in it."""
    p = mesh.points
    inside = np.all((p >= np.asarray(lo) - 1e-9) & (p <= np.asarray(hi) + 1e-9), axis=1)
    return Region(np.flatnonzero(inside), np.flatnonzero(inside[mesh.tets].all(axis=1)))


@pytest.fixture(scope="module")
def bar():
    """A 0.3 m bar with three bones inside (a soft skin of one cell around them)."""
    mesh = grid_box((0.3, 0.04, 0.04), (15, 4, 4))
    bones = {f"bone:{name}": _box_region(mesh, (x0, 0.01, 0.01), (x0 + 0.06, 0.03, 0.03))
             for name, x0 in (("a", 0.02), ("b", 0.12), ("c", 0.22))}
    return mesh.with_regions(**bones)


@pytest.fixture(scope="module")
def chain(bar):
    """Free root, a revolute joint on a skew axis, a prismatic joint: 8 dofs."""
    skeleton = Skeleton([Link("c", "bone:c", "b", Prismatic((1.0, 0.2, 0.0))),
                         Link("a", "bone:a", None, Free()),
                         Link("b", "bone:b", "a", Revolute((0.0, 1.0, 1.0), (0.1, 0.02, 0.02)))])
    return skeleton.bind(bar)


def _pose(rig, seed, scale=0.5):
    dz = scale * jax.random.normal(jax.random.PRNGKey(seed), (rig.n_dofs,))
    return rig.retract(rig.rest_coordinates(), dz)


def test_links_are_ordered_top_down(chain):
    assert [link.name for link in chain.links] == ["a", "b", "c"]
    assert (chain.n_coords, chain.n_dofs) == (9, 8)


def test_fk_jacobian_matches_finite_differences(chain):
    """``B`` (tangent coordinates) against central differences of FK along the retraction;
    the truncation error is ~eps^2 |x'''| ~ 1e-12 m for eps = 1e-6."""
    for seed in range(3):
        z = _pose(chain, seed)
        b = chain.jacobian(z)
        eps = 1e-6
        fd = jnp.stack([(chain.positions(chain.retract(z, eps * e)) - chain.positions(chain.retract(z, -eps * e)))
                        / (2 * eps) for e in jnp.eye(chain.n_dofs)], axis=-1)
        assert float(jnp.abs(fd - b).max()) < 1e-8 * float(jnp.abs(b).max())


def test_two_trees_are_solved_in_blocks_of_their_own_dofs(bar):
    """Two trees (a Free root with a revolute child: 7 dofs; a second Free root: 6): the
    Jacobian by trees holds, for each bone vertex, the central differences of FK along its
    own tree's dofs (zero on padding slots), the other tree's dofs do not move it, and
    ``B^T f`` (summed per link about its centroid) equals the dense product."""
    rig = Skeleton([Link("a", "bone:a", None, Free()),
                    Link("b", "bone:b", "a", Revolute((0.0, 1.0, 1.0), (0.1, 0.02, 0.02))),
                    Link("c", "bone:c", None, Free())]).bind(bar)
    assert rig.tree_dofs.tolist() == [list(range(7)), [7, 8, 9, 10, 11, 12, 13]]  # 13 pads the second tree
    z, eps = _pose(rig, 4), 1e-6
    fd = np.asarray(jnp.stack([(rig.positions(rig.retract(z, eps * e)) - rig.positions(rig.retract(z, -eps * e)))
                               / (2 * eps) for e in jnp.eye(rig.n_dofs)], axis=-1))  # (n_b, 3, 13)
    local = np.asarray(rig.local_jacobian(rig.pose(z)))  # (n_b, 3, 7)
    slots = rig.tree_dofs[rig.vertex_tree]  # (n_b, 7)
    padded = np.concatenate([fd, np.zeros_like(fd[:, :, :1])], axis=2)
    expected = np.take_along_axis(padded, slots[:, None, :], axis=2)
    assert np.abs(local - expected).max() < 1e-8 * np.abs(fd).max()
    other = rig.tree_dofs[1 - rig.vertex_tree]
    assert np.abs(np.take_along_axis(padded, other[:, None, :], axis=2)).max() < 1e-9
    f = np.asarray(jax.random.normal(jax.random.PRNGKey(2), (len(rig.bone), 3)))
    np.testing.assert_allclose(rig.reduce(rig.pose(z), jnp.asarray(f)), np.einsum("vik,vi->k", fd, f),
                               rtol=0, atol=1e-8 * np.abs(fd).max() * np.abs(f).sum())
    v = jnp.arange(rig.n_dofs, dtype=float) + 1.0
    np.testing.assert_array_equal(rig.unblock(rig.blocks(v)), v)


def test_coordinates_invert_forward_kinematics(chain):
    for seed in range(3):
        z = _pose(chain, seed)
        back = chain.coordinates(chain.positions(z))
        # The quaternion is defined up to sign.
        back = back.at[3:7].multiply(jnp.sign(back[3] * z[3]))
        np.testing.assert_allclose(back, z, atol=1e-12)


def test_fixed_root_welds_its_bone_to_the_world(bar):
    rig = Skeleton([Link("a", "bone:a", None, Fixed())]).bind(bar)
    z = rig.rest_coordinates()
    assert z.shape == (0,) and rig.jacobian(z).shape == (len(rig.bone), 3, 0)
    np.testing.assert_array_equal(rig.positions(z), bar.points[rig.bone])


def test_free_root_rotates_about_its_centre_of_mass(chain):
    """A pure rotation of the Free root leaves the root bone's centroid in place (the
    bone is a uniform block of equal tets, so its centroid is its centre of mass)."""
    z = chain.rest_coordinates().at[3:7].set(jnp.array([np.cos(0.4), np.sin(0.4), 0.0, 0.0]))
    x = chain.positions(z)[chain.vertex_link == 0]
    np.testing.assert_allclose(x.mean(axis=0), chain.rest[chain.vertex_link == 0].mean(axis=0), atol=1e-15)


def test_schur_solve_equals_direct_reduced_solve(bar, chain):
    """The Schur-complement direction against a dense solve of the full reduced system
    ``[[Q_ff, Q_fr B], [B^T Q_rf, B^T Q_rr B]]`` (with one joint held at a limit)."""
    model, params = build(SoftBody(bar, SKIN), skeleton=chain.skeleton, options=Options(dt=0.01))
    prep = prepare(model, params)
    a = np.asarray(model.pattern.to_dense(prep.data))
    n, bone = bar.n_vertices, chain.bone
    free = np.setdiff1d(np.arange(n), bone)
    g = np.asarray(jax.random.normal(jax.random.PRNGKey(7), (n, 3)))
    z = _pose(chain, 1)
    b = np.asarray(chain.jacobian(z))
    locked = np.zeros(chain.n_dofs)
    locked[6] = 1.0
    factor = schur_factor(model.linear_solver, model.pattern, prep.data, chain)
    d, d_z = schur_direction(factor, chain, z, jnp.asarray(g), jnp.asarray(locked))

    bm = (b * (1.0 - locked)).reshape(3 * len(bone), -1)
    blocks = {k: np.kron(a[np.ix_(r, c)], np.eye(3)) for k, (r, c) in
              {"ff": (free, free), "fr": (free, bone), "rr": (bone, bone)}.items()}
    k_full = np.block([[blocks["ff"], blocks["fr"] @ bm],
                       [bm.T @ blocks["fr"].T, bm.T @ blocks["rr"] @ bm + np.diag(locked)]])
    direct = np.linalg.solve(k_full, np.concatenate([g[free].ravel(), bm.T @ g[bone].ravel()]))
    d_f, d_z_direct = direct[:3 * len(free)].reshape(-1, 3), direct[3 * len(free):]
    d = np.asarray(d)
    assert np.abs(d[free] - d_f).max() <= 1e-10 * np.abs(d_f).max()
    assert np.abs(d_z - d_z_direct).max() <= 1e-10 * np.abs(d_z_direct).max()
    assert d_z_direct[6] == 0.0
    assert np.abs(d[bone] - (bm @ d_z_direct).reshape(-1, 3)).max() <= 1e-10 * np.abs(d).max()


def _pairwise(x):
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def _max_distance_change(xs, idx):
    ref = _pairwise(xs[0][idx])
    return max(np.abs(_pairwise(x[idx]) - ref).max() for x in xs)


@pytest.mark.slow
def test_rigid_pendulum_period_and_rigidity():
    """A 2 cm cube swinging on a revolute joint 11 cm above its centre, all of it bone.

    Small-angle period ``T = 2 pi sqrt(I / (m g d))`` with ``I`` and ``m`` of the lumped
    vertex masses the simulation uses. Implicit Euler lengthens the period by a relative
    ``(h w)^2 / 3 ~ 3e-5`` at h = 1 ms and damps the swing (amplitude x ~0.97 per period),
    neither of which shifts zero crossings by 2%; a 0.05 rad amplitude adds ``theta^2/16``.
    """
    mesh = grid_box((0.02, 0.02, 0.02), (2, 2, 2))
    mesh = mesh.with_regions(**{"bone:bob": Region(np.arange(mesh.n_vertices), np.arange(mesh.n_tets))})
    pivot = np.array([0.01, 0.01, 0.12])
    rig = Skeleton([Link("bob", "bone:bob", None, Revolute((0.0, 1.0, 0.0), tuple(pivot)))]).bind(mesh)
    dt, g = 1e-3, 9.81
    model, params = build(SoftBody(mesh, SKIN), skeleton=rig.skeleton, options=Options(dt=dt, tol=1e-8))
    mass = np.asarray(prepare(model, params).mass)[:, 0]
    arm = mesh.points - pivot
    inertia = float(np.sum(mass * (arm[:, 0] ** 2 + arm[:, 2] ** 2)))
    depth = float(-np.sum(mass * arm[:, 2]) / mass.sum())
    period = 2 * np.pi * np.sqrt(inertia / (mass.sum() * g * depth))

    x0 = np.asarray(mesh.points).copy()
    x0[rig.bone] = np.asarray(rig.positions(jnp.array([0.05])))
    n_steps = int(1.2 * period / dt)
    traj = rollout(model, params, initial_state(model, params, x=x0), n_steps=n_steps)
    assert bool(jnp.all(traj.info.converged))
    xs = np.asarray(traj.x)
    theta = np.asarray(jax.jit(jax.vmap(rig.coordinates))(jnp.asarray(xs[:, rig.bone])))[:, 0]
    crossings = [k + theta[k] / (theta[k] - theta[k + 1]) for k in range(n_steps) if theta[k] * theta[k + 1] < 0]
    measured = 2 * (crossings[1] - crossings[0]) * dt
    assert abs(measured / period - 1) < 0.02, (measured, period)
    assert _max_distance_change(xs, rig.bone) < 1e-8


@pytest.fixture(scope="module")
def arm():
    """A soft arm (0.2 m) clamped at x = 0, with two bones hinged about y."""
    mesh = grid_box((0.2, 0.04, 0.04), (10, 4, 4))
    mesh = mesh.with_regions(**{"bone:upper": _box_region(mesh, (0.02, 0.01, 0.01), (0.08, 0.03, 0.03)),
                                "bone:fore": _box_region(mesh, (0.12, 0.01, 0.01), (0.18, 0.03, 0.03))})
    skeleton = Skeleton([Link("upper", "bone:upper", None, Revolute((0.0, 1.0, 0.0), (0.02, 0.02, 0.02))),
                         Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.10, 0.02, 0.02)))])
    return mesh, skeleton.bind(mesh)


@pytest.mark.slow
def test_two_link_arm_in_soft_skin_keeps_bone_lengths_and_joint_limits(arm):
    """The arm sags under gravity; the shoulder's upper limit (0.01 rad) stops it and
    holds it there, the elbow bends freely; bones stay rigid, the skin deforms."""
    mesh, _ = arm
    rig = Skeleton([Link("upper", "bone:upper", None, Revolute((0.0, 1.0, 0.0), (0.02, 0.02, 0.02), (-0.3, 0.01))),
                    Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.10, 0.02, 0.02)))]).bind(mesh)
    model, params = build(SoftBody(mesh, SKIN, fixed="xmin"), skeleton=rig.skeleton, options=Options(dt=0.01))
    traj = rollout(model, params, initial_state(model, params), n_steps=25)
    assert bool(jnp.all(traj.info.converged))
    xs = np.asarray(traj.x)
    z = np.asarray(jax.jit(jax.vmap(rig.coordinates))(jnp.asarray(xs[:, rig.bone])))
    assert z[:, 0].max() <= 0.01 + 1e-12 and z[-1, 0] == pytest.approx(0.01, abs=1e-12)
    assert z[-1, 1] > 0.02  # +y turns +x towards -z: the forearm sags
    for link in range(2):
        assert _max_distance_change(xs, rig.bone[rig.vertex_link == link]) < 1e-10
    # the shoulder stays on its hinge; the skin between the bones does deform
    upper = rig.bone[rig.vertex_link == 0]
    radius = np.linalg.norm(xs[:, upper] - np.array([0.02, 0.02, 0.02]), axis=-1)
    assert np.abs(radius - radius[0]).max() < 1e-10
    skin = np.setdiff1d(np.arange(mesh.n_vertices), np.concatenate([rig.bone, mesh.regions["xmin"].vertices]))
    assert _max_distance_change(xs, skin) > 1e-3


@pytest.mark.slow
def test_joint_torque_and_saturated_servo_spin_a_hinged_body():
    """A bone block hinged through its centre of mass, no gravity, driven by a constant
    torque ``tau`` and by a servo far from its target, which applies its torque limit
    ``tau_s``: ``theta = (tau + tau_s) t^2 / (2 I)``; implicit Euler gives
    ``(tau + tau_s) h^2 N (N + 1) / (2 I)`` after N steps (exact for this motion, to the
    step tolerance and the O(theta^2) difference between chord and arc)."""
    mesh = grid_box((0.04, 0.02, 0.02), (2, 1, 1))
    mesh = mesh.with_regions(**{"bone:body": Region(np.arange(mesh.n_vertices), np.arange(mesh.n_tets))})
    centre = np.array([0.02, 0.01, 0.01])
    rig = Skeleton([Link("body", "bone:body", None, Revolute((0.0, 0.0, 1.0), tuple(centre)))]).bind(mesh)
    tau, tau_s, dt, n_steps = 1e-4, 2e-4, 1e-3, 100
    model, params = build(SoftBody(mesh, SKIN),
                          skeleton=rig.skeleton,
                          actuators=[JointTorque(["body"]), JointServo(["body"], stiffness=1.0, torque_limit=tau_s)],
                          options=Options(dt=dt, gravity=(0.0, 0.0, 0.0), tol=1e-10))
    servo = model.terms[1]
    mass = np.asarray(prepare(model, params).mass)[:, 0]
    arm = mesh.points - centre
    inertia = float(np.sum(mass * (arm[:, 0] ** 2 + arm[:, 1] ** 2)))
    traj = rollout(model, params, initial_state(model, params), controls=jnp.tile(jnp.array([tau, 3.0]), (n_steps, 1)))
    theta = float(rig.coordinates(traj.x[-1][jnp.asarray(rig.bone)])[0])
    expected = (tau + tau_s) * dt**2 * n_steps * (n_steps + 1) / (2 * inertia)
    assert abs(theta / expected - 1) < 1e-3, (theta, expected)
    assert float(servo.torques(traj.x[-1], params.actuators[1], jnp.array([3.0]))[0]) == pytest.approx(tau_s)


@pytest.mark.slow
def test_servo_holds_a_joint_at_its_target_against_gravity(arm):
    """The shoulder servo lifts the arm to 0.1 rad above the horizontal; the soft skin and
    gravity pull back, so the servo settles where its torque balances them, slightly
    below the target (stiff gain: within 0.02 rad)."""
    mesh, rig = arm
    model, params = build(SoftBody(mesh, Material(E=1e4, nu=0.3, density=1000.0, alpha=20.0), fixed="xmin"),
                          skeleton=rig.skeleton, options=Options(dt=0.01),
                          actuators=[JointServo(["upper", "fore"], stiffness=50.0, torque_limit=5.0)])
    servo = model.terms[0]
    target = jnp.array([-0.1, 0.0])
    traj = rollout(model, params, initial_state(model, params), controls=jnp.tile(target, (60, 1)))
    z = np.asarray(rig.coordinates(traj.x[-1][jnp.asarray(rig.bone)]))
    assert np.abs(z - np.asarray(target)).max() < 0.02, z
    assert np.all(np.abs(np.asarray(servo.torques(traj.x[-1], params.actuators[0], target))) <= 5.0)


@pytest.mark.parametrize("links, message", [
    ([], "at least one link"),
    ([Link("a", "bone:a", "ghost")], "unknown parent 'ghost'"),
    ([Link("a", "bone:a", "b"), Link("b", "bone:b", "a")], "cycle"),
    ([Link("a", "bone:a"), Link("a", "bone:b", "a")], "used 2 times"),
    ([Link("a", "bone:a"), Link("b", "bone:b", "a", Free())], "parent=None"),
    ([Link("a", "bone:a", None, "hinge")], "joint must be"),
])
def test_bad_trees_are_rejected(links, message):
    with pytest.raises(SkeletonError, match=message):
        Skeleton(links)


def test_bad_joints_and_bones_are_rejected(bar):
    with pytest.raises(SkeletonError, match="zero length"):
        Revolute((0.0, 0.0, 0.0))
    with pytest.raises(SkeletonError, match="zero length"):
        Prismatic((0.0, 0.0, 1e-15))
    with pytest.raises(SkeletonError, match="lower < upper"):
        Revolute((0.0, 0.0, 1.0), limits=(0.5, -0.5))
    with pytest.raises(SkeletonError, match="not in the mesh"):
        Skeleton([Link("a", "bone:nope")]).bind(bar)
    empty = bar.with_regions(**{"bone:empty": Region(np.zeros(0, np.int32))})
    with pytest.raises(SkeletonError, match="has no vertices"):
        Skeleton([Link("a", "bone:empty")]).bind(empty)
    flat = bar.with_regions(**{"bone:flat": Region(bar.regions["xmin"].vertices)})
    with pytest.raises(SkeletonError, match="coplanar"):
        Skeleton([Link("a", "bone:flat")]).bind(flat)
    with pytest.raises(SkeletonError, match="must not overlap"):
        Skeleton([Link("a", "bone:a"), Link("b", "bone:a", "a")]).bind(bar)


def test_bad_skeleton_scenes_are_refused_before_compiling(bar, arm, no_compiling):
    """A fixed bone vertex, joint actuators without a skeleton or on joints that take no
    torque, a solver the reduced coordinates do not run: each refused by build."""
    skeleton = Skeleton([Link("a", "bone:a", None, Free())])
    rig = skeleton.bind(bar)
    with pytest.raises(SkeletonError, match="bone vertices are fixed"):
        build(SoftBody(bar, SKIN, fixed=rig.bone[:1]), skeleton=skeleton)
    with pytest.raises(SceneError, match="skeleton must be a softbody.skeleton.Skeleton"):
        build(SoftBody(bar, SKIN), skeleton=rig)
    with pytest.raises(SceneError, match="the scene has none"):
        build(SoftBody(bar, SKIN), actuators=[JointTorque(["upper"])])
    with pytest.raises(SceneError, match="only Revolute and Prismatic"):
        build(SoftBody(bar, SKIN), skeleton=skeleton, actuators=[JointTorque(["a"])])
    with pytest.raises(SkeletonError, match="no link 'nope' in the skeleton"):
        build(SoftBody(arm[0], SKIN), skeleton=arm[1].skeleton, actuators=[JointServo(["nope"])])
    with pytest.raises(SceneError, match="write \\['upper'\\]"):
        JointTorque("upper")

    class Newton(NonlinearSolver):
        pass

    with pytest.raises(SceneError, match="a scene with a skeleton runs the solvers \\['LBFGS', 'LocalGlobal'\\]"):
        build(SoftBody(bar, SKIN), skeleton=skeleton, options=Options(solver=Newton()))
    model, _ = build(SoftBody(bar, SKIN), skeleton=skeleton, obstacles=[Plane(mu_s=0.5)])
    assert isinstance(model.step.coordinates, Reduced) and model.step.contact is not None
    assert model.rig.skeleton is skeleton


@pytest.mark.slow  # ~4 min of CPU: reverse mode through 4 x 321 unrolled iterations
def test_joint_torque_gradient_matches_finite_differences_over_a_rollout(arm):
    """Reverse mode through a 4-step rollout of the soft arm driven by joint torques
    (Unrolled adjoint, float64, no contact) against Richardson-extrapolated central
    differences. The unrolled forward pass must also be the ordinary one: a line search
    that kept halving after acceptance once made it a different (non-converging) function
    whose gradient matched its own differences but not the simulation's."""
    mesh, rig = arm
    options = dict(dt=0.01, tol=1e-10, max_iter=300)
    model, params = build(SoftBody(mesh, SKIN, fixed="xmin"),
                          skeleton=rig.skeleton, actuators=[JointTorque(["upper", "fore"])],
                          options=Options(**options, adjoint=Unrolled()))
    plain, _ = build(SoftBody(mesh, SKIN, fixed="xmin"),
                     skeleton=rig.skeleton, actuators=[JointTorque(["upper", "fore"])], options=Options(**options))
    state0 = initial_state(model, params)
    controls = jnp.tile(jnp.array([2e-3, -1e-3]), (4, 1))
    traj = rollout(model, params, state0, controls=controls)
    assert bool(jnp.all(traj.info.converged))
    reference = rollout(plain, params, state0, controls=controls)
    # Both converge to |grad Phi| <= 1e-10 |M s / h^2|: positions agree far below 1e-9 m.
    assert float(jnp.abs(traj.x - reference.x).max()) < 1e-9
    tip = jnp.asarray(np.flatnonzero(mesh.points[:, 0] > 0.2 - 1e-9))

    def loss(controls):
        return jnp.mean(rollout(model, params, state0, controls=controls).x[-1][tip, 2])

    result = check_grad(loss, controls, eps=1e-4, verbose=False)["all"]
    assert abs(result["ad"]) > 1e-3  # the torques do move the tip (m per N m)
    assert result["rel_error"] <= 1e-5, result



@pytest.mark.slow
def test_implicit_gradient_of_torques_servos_and_material_matches_finite_differences(arm):
    """The default (Implicit) adjoint in the skeleton's reduced coordinates, over 3 steps of
    the soft arm with a torque on the shoulder and a servo on the elbow: the gradient of the
    tip height with respect to the torques, the servo targets, the servo gain and Young's
    modulus, each kind along its own random direction, against Richardson-extrapolated
    central differences (float64). The forward tolerance is 1e-12: at 1e-10 the
    differences along the gain and the modulus, which move the tip least, carried the
    solver's stopping noise (1e-4 relative at a step of 1e-4; the gradient itself agreed
    to 4e-7 at 1e-12)."""
    mesh, rig = arm
    model, params = build(SoftBody(mesh, SKIN, fixed="xmin"),
                          skeleton=rig.skeleton, actuators=[JointTorque(["upper"]), JointServo(["fore"], stiffness=0.05)],
                          options=Options(dt=0.01, tol=1e-12, max_iter=300))
    state0 = initial_state(model, params)
    tip = jnp.asarray(np.flatnonzero(mesh.points[:, 0] > 0.2 - 1e-9))
    theta = {"torque": jnp.full((3, 1), 2e-3), "target": jnp.full((3, 1), -0.05),
             "log_gain": jnp.log(jnp.array([0.05])), "log_E": jnp.log(params.E)}

    def loss(th):
        p = eqx.tree_at(lambda q: (q.E, q.actuators[1].stiffness), params,
                        (jnp.exp(th["log_E"]), jnp.exp(th["log_gain"])))
        controls = jnp.concatenate([th["torque"], th["target"]], axis=1)
        return jnp.mean(rollout(model, p, state0, controls=controls).x[-1][tip, 2]) * 1e3  # mm

    traj = rollout(model, params, state0, controls=jnp.concatenate([theta["torque"], theta["target"]], axis=1))
    assert bool(jnp.all(traj.info.converged))
    kinds = {k: {j: float(j == k) for j in theta} for k in theta}
    results = check_grad(loss, theta, directions=kinds, eps=1e-3, verbose=False)
    for kind, r in results.items():
        assert abs(r["ad"]) > 1e-4, (kind, r)  # each kind moves the tip
        assert r["rel_error"] <= 1e-5, (kind, r)


@pytest.mark.slow
def test_two_link_arm_joint_angles_converge_at_first_order_in_dt(arm):
    """The soft arm sagging from rest, run to t = 0.08 s with h = 0.01, 0.005, 0.0025 s:
    implicit Euler is first order, so the joint-angle differences between successive
    halvings shrink by ~2 (observed order within 0.7-1.3), and the bones stay rigid at
    every step size."""
    mesh, rig = arm
    angles = []
    for dt in (0.01, 0.005, 0.0025):
        model, params = build(SoftBody(mesh, SKIN, fixed="xmin"),
                              skeleton=rig.skeleton, options=Options(dt=dt, tol=1e-9))
        traj = rollout(model, params, initial_state(model, params), n_steps=round(0.08 / dt))
        assert bool(jnp.all(traj.info.converged))
        xs = np.asarray(traj.x)
        for link in range(2):
            assert _max_distance_change(xs, rig.bone[rig.vertex_link == link]) < 1e-10
        angles.append(np.asarray(rig.coordinates(traj.x[-1][jnp.asarray(rig.bone)])))
    coarse, fine = np.abs(angles[0] - angles[1]).max(), np.abs(angles[1] - angles[2]).max()
    assert np.abs(angles[2]).max() > 0.1  # a macroscopic swing (rad), not a rest state
    assert fine < coarse  # the dt-error shrinks
    assert 0.7 < np.log2(coarse / fine) < 1.3, (coarse, fine, angles)


def _normal_and_tangential(force, n):
    """``(normal, |tangential|)`` parts of forces ``(..., 3)`` on a plane with unit normal ``n``."""
    normal = force @ n
    return normal, np.linalg.norm(force - normal[..., None] * n, axis=-1)


@pytest.mark.slow
def test_jointed_body_sticks_on_an_incline_below_the_friction_angle_and_slides_above_it(arm):
    """The arm (free root, elbow hinge, soft skin) set down on a tilted friction plane.

    Below the friction angle (``tan theta = 0.9 mu_s``) it must come to rest: once
    settled, no contact vertex slips and the body does not creep. Above it
    (``tan theta = 1.1 mu_s``) the whole body slides with ``a = g (sin theta - mu_k
    cos theta)`` (a rigid-body result: the skin's internal forces sum to zero), without
    penetrating the plane, and the bones stay rigid throughout.
    """
    mesh, _ = arm
    rig = Skeleton([Link("upper", "bone:upper", None, Free()),
                    Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.10, 0.02, 0.02)))]).bind(mesh)
    dt, mu_s, mu_k = 0.01, 0.5, 0.4
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0, beta=0.01)),
                          skeleton=rig.skeleton, obstacles=[Plane(mu_s=mu_s, mu_k=mu_k)],
                          options=Options(dt=dt, gravity=(0.0, 0.0, 0.0), tol=1e-8, max_iter=3000))
    mass = np.asarray(prepare(model, params).mass)

    def on_incline(tan_theta, kinetic, n_steps):
        r = rot_y(np.arctan(tan_theta))
        x0 = mesh.points @ r.T
        plane = params.obstacles[0].replace(normal=jnp.asarray(r[:, 2]), mu_k=jnp.asarray(kinetic))
        p = eqx.tree_at(lambda q: q.obstacles[0], params, plane)
        traj = rollout(model, p, initial_state(model, p, x=x0), forces=ramped_gravity(mass, n_steps, dt))
        assert bool(jnp.all(traj.info.converged))
        xs = np.asarray(traj.x)
        assert (xs @ r[:, 2]).min() > -1e-12, "no vertex may end a step below the incline"
        for link in range(2):
            assert _max_distance_change(xs, rig.bone[rig.vertex_link == link]) < 1e-10
        along = (xs - x0) @ r[:, 0]
        forces = ramped_gravity(mass, n_steps, dt)
        return along.mean(axis=1), along[:, mesh.regions["zmin"].vertices], contact_forces(model, p, traj, forces=forces), xs

    com, bottom, contact, _ = on_incline(0.9 * mu_s, mu_s, 50)
    assert np.abs(bottom[40:] - bottom[40]).max() < 1e-7, "contact vertices must not slip while sticking"
    assert np.abs(com[40:] - com[40]).max() < 1e-7, "the body must not creep"
    assert np.abs(bottom).max() < 1e-4
    # Resting, the plane carries the weight through skin vertices only (bones take no contact).
    force, state = (np.asarray(a)[40:] for a in contact)
    np.testing.assert_allclose(force.sum(axis=1), np.broadcast_to([0.0, 0.0, mass.sum() * G], (10, 3)),
                               atol=1e-3 * mass.sum() * G)
    # Every contact vertex sticks, inside the static cone (some at its edge, as tan theta
    # = 0.9 mu_s is close to it).
    assert np.all(state[:, rig.bone] == 0) and np.all(np.isin(state, [0, 1]))
    normal, tangential = _normal_and_tangential(force, rot_y(np.arctan(0.9 * mu_s))[:, 2])
    assert np.all(normal[state == 1] > 0) and np.all(tangential[state == 1] <= mu_s * normal[state == 1] * (1 + 1e-6))

    com, _, contact, xs = on_incline(1.1 * mu_s, mu_k, 40)
    theta = np.arctan(1.1 * mu_s)
    expected = G * (np.sin(theta) - mu_k * np.cos(theta))
    assert acceleration(com, dt, 15) == pytest.approx(expected, rel=0.01)
    force, state = (np.asarray(a)[15:] for a in contact)
    touching = state > 0
    assert np.all(state[touching] == 2) and touching.sum(axis=1).min() >= 4  # sliding, all of them
    normal, tangential = _normal_and_tangential(force, rot_y(theta)[:, 2])
    # r = grad Phi at the solution, off by at most the residual bound tol |M s / h^2|
    bound = (1 + mu_k) * 1e-8 * np.linalg.norm(mass * xs[16:], axis=(1, 2)) / dt**2
    assert np.all((np.abs(tangential - mu_k * normal) <= bound[:, None])[touching])


@pytest.mark.slow
def test_gradient_through_skeleton_contact_matches_central_differences(arm):
    """Reverse mode through contact in a skeleton's reduced coordinates: the slide of a jointed body down an incline
    (tan theta = 1.1 mu_s) differentiated with respect to the kinetic friction coefficient,
    against central differences (eps 1e-4: truncation ~eps^2 relative; forward tol 1e-10)."""
    mesh, _ = arm
    rig = Skeleton([Link("upper", "bone:upper", None, Free()),
                    Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.10, 0.02, 0.02)))]).bind(mesh)
    dt, mu_s = 0.01, 0.5
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1000.0)),
                          skeleton=rig.skeleton, options=Options(dt=dt, gravity=(0.0, 0.0, 0.0), tol=1e-10,
                                                                 max_iter=3000), obstacles=[Plane(mu_s=mu_s, mu_k=0.4)])
    r = rot_y(np.arctan(1.1 * mu_s))
    x0 = mesh.points @ r.T
    forces = ramped_gravity(np.asarray(prepare(model, params).mass), 15, dt)

    def slide(mu_k):
        plane = params.obstacles[0].replace(normal=jnp.asarray(r[:, 2]), mu_k=mu_k)
        p = eqx.tree_at(lambda q: q.obstacles[0], params, plane)
        traj = rollout(model, p, initial_state(model, p, x=x0), forces=forces)
        return jnp.mean(traj.x[-1] @ jnp.asarray(r[:, 0]))

    grad = float(jax.jit(jax.grad(slide))(jnp.asarray(0.4)))
    f, eps = jax.jit(slide), 1e-4
    fd = float((f(jnp.asarray(0.4 + eps)) - f(jnp.asarray(0.4 - eps))) / (2 * eps))
    assert fd < 0  # more friction, less slide
    assert grad == pytest.approx(fd, rel=1e-4)

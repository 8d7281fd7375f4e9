"""Scenes of several soft bodies: the bodies' names and places in the scene's arrays, the
refusals, and physics: bodies that do not touch move in one scene exactly as each moves in
a scene of its own (materials, held vertices, a moving clamp, a muscle and contact with an
obstacle all stay with their body)."""

import jax.numpy as jnp
import numpy as np
import pytest

from softbody.contact.active_set import ActiveSet
from softbody.actuators import Muscle
from softbody.actuators.joints import JointTorque
from softbody.contact import Contact
from softbody.io import Result
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state
from softbody.contact.obstacles import Plane
from softbody.scene import SoftBody
from softbody.simulate import rollout

# An arm clamped at x = 0 with a muscle along it, its clamp rising at 5 cm/s, above a block
# that falls 2 mm onto the ground plane z = 0.
ARM = grid_box((0.06, 0.01, 0.01), (6, 1, 1), origin=(0.0, 0.0, 0.03))
BLOCK = grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(0.1, 0.0, 0.002))
MUSCLE = Muscle.from_polyline(ARM, [[0.0, 0.005, 0.035], [0.06, 0.005, 0.035]], radius=0.01, stiffness=2e4,
                              falloff="none", name="biceps")
# The active set: with the splitting alone, Anderson mixing over both bodies restarts at
# each of the block's contact changes, and the landing steps need thousands of iterations.
OPTIONS = Options(dt=0.01, tol=1e-10, max_iter=3000, contact=Contact(active_set=ActiveSet()))
# mu_s = mu_k: each step has one equilibrium (with mu_s > mu_k a landing step can have
# several, and two solves may pick different ones).
GROUND = [Plane(mu_s=0.4, mu_k=0.4)]


def _rising(t):
    return jnp.eye(3), jnp.array([0.0, 0.0, 0.05]) * t


def _arm(name=None):
    return SoftBody(ARM, Material(E=5e4, nu=0.3, density=1000.0), fixed="xmin", motion=_rising,
                    actuators=[MUSCLE], name=name)


def _block(name=None):
    return SoftBody(BLOCK, Material(E=2e5, nu=0.4, density=800.0), name=name)


def test_bodies_are_named_and_placed(no_compiling, tmp_path):
    model, params = build([_arm("arm"), _block("block")], obstacles=GROUND, options=OPTIONS)
    n_arm, t_arm = ARM.n_vertices, ARM.n_tets
    arm, block = model.bodies
    assert (arm.name, arm.vertices, arm.tets) == ("arm", (0, n_arm), (0, t_arm))
    assert (block.name, block.vertices, block.tets) == ("block", (n_arm, n_arm + BLOCK.n_vertices),
                                                        (t_arm, t_arm + BLOCK.n_tets))
    assert model.body("block") is block and arm.motion is _rising and block.motion is None
    np.testing.assert_array_equal(arm.fixed, ARM.regions["xmin"].vertices)
    assert len(block.fixed) == 0 and np.array_equal(model.fixed, arm.fixed)
    mesh = model.mesh
    np.testing.assert_array_equal(mesh.points, np.concatenate([ARM.points, BLOCK.points]))
    np.testing.assert_array_equal(mesh.regions["block/zmin"].vertices, BLOCK.regions["zmin"].vertices + n_arm)
    np.testing.assert_array_equal(mesh.regions["block"].tets, np.arange(BLOCK.n_tets) + t_arm)
    assert len(mesh.regions["arm"].faces) == len(ARM.surface) and len(mesh.surface) == len(ARM.surface) + len(
        BLOCK.surface)
    assert model.material_names == ("arm/default", "block/default")
    np.testing.assert_array_equal(model.tet_material, np.repeat([0, 1], [t_arm, BLOCK.n_tets]))
    np.testing.assert_array_equal(params.E, [5e4, 2e5])
    assert model.channel_names == ("arm/biceps",)
    np.testing.assert_array_equal(model.terms[0].tets, MUSCLE.tets)  # the arm comes first: no shift
    shifted = build([_block("block"), _arm("arm")], obstacles=GROUND, options=OPTIONS)[0]
    np.testing.assert_array_equal(shifted.terms[0].tets, MUSCLE.tets + BLOCK.n_tets)
    np.testing.assert_array_equal(shifted.body("arm").fixed, ARM.regions["xmin"].vertices + BLOCK.n_vertices)
    alone, _ = build(_arm(), obstacles=GROUND, options=OPTIONS)  # one unnamed body: its own names
    assert alone.mesh is ARM and alone.channel_names == ("biceps",) and alone.material_names == ("default",)
    with pytest.raises(SceneError, match="no body 'hand'.*'arm', 'block'"):
        model.body("hand")
    # A result file keeps which vertices are whose.
    saved = Result.from_mesh(mesh, np.stack([mesh.points] * 2), 0.01,
                             channel_names=model.channel_names, activation=np.zeros((2, 1))).save(tmp_path / "two.npz")
    loaded = Result.load(saved)
    for name in ("arm", "block", "block/zmin"):
        np.testing.assert_array_equal(loaded.regions[name].vertices, mesh.regions[name].vertices)
    assert loaded.channel_names == ("arm/biceps",)


def test_bad_scenes_are_refused(no_compiling):
    with pytest.raises(SceneError, match="not a mesh: wrap it"):
        build(ARM)
    with pytest.raises(SceneError, match="at least one body"):
        build([])
    with pytest.raises(SceneError, match="names each of them.*unnamed: bodies \\[1\\]"):
        build([_arm("arm"), _block()])
    with pytest.raises(SceneError, match="unique.*\\['twin'\\]"):
        build([_arm("twin"), _block("twin")])
    with pytest.raises(SceneError, match="without '/'"):
        _block("left/right")
    with pytest.raises(SceneError, match="bodies\\[1\\] is a TetMesh"):
        build([_arm("arm"), BLOCK])
    with pytest.raises(SceneError, match="give it to that body"):
        build(SoftBody(ARM), actuators=[MUSCLE])
    with pytest.raises(SceneError, match="acts on the scene's skeleton.*build\\(\\.\\.\\., actuators"):
        build(SoftBody(ARM, actuators=[JointTorque(["elbow"])]))
    with pytest.raises(SceneError, match="body 'block' moves its held vertices, but it has none"):
        build([_arm("arm"), SoftBody(BLOCK, motion=_rising, name="block")])
    with pytest.raises(SceneError, match="channel names must be unique"):
        build(SoftBody(ARM, actuators=[MUSCLE, MUSCLE]))


def test_bodies_that_do_not_touch_move_as_they_do_alone():
    """The arm (clamp moving, muscle on) and the block (landing on the ground with friction)
    in one scene against each in a scene of its own: the same steps to the solvers'
    tolerance (1e-10 relative residual; bound: 1e-9 m, 1e-7 of the bodies' motion)."""
    n_steps = 8
    controls = jnp.full((n_steps, 1), 0.5)
    both, params = build([_arm("arm"), _block("block")], obstacles=GROUND, options=OPTIONS)
    traj = rollout(both, params, initial_state(both, params), n_steps=n_steps, controls=controls)
    assert bool(np.all(traj.info.converged))
    arm, arm_params = build(_arm(), obstacles=GROUND, options=OPTIONS)
    arm_traj = rollout(arm, arm_params, initial_state(arm, arm_params), n_steps=n_steps, controls=controls)
    block, block_params = build(_block(), obstacles=GROUND, options=OPTIONS)
    block_traj = rollout(block, block_params, initial_state(block, block_params), n_steps=n_steps)
    split = ARM.n_vertices
    moved_arm = np.abs(np.asarray(arm_traj.x[-1]) - ARM.points).max()
    moved_block = np.abs(np.asarray(block_traj.x[-1]) - BLOCK.points).max()
    assert moved_arm > 3e-3 and moved_block > 1e-3  # both moved: the clamp rose 4 mm, the block fell 2 mm
    assert np.abs(np.asarray(block_traj.x[-1, :, 2])).min() < 1e-4  # and landed
    np.testing.assert_allclose(traj.x[:, :split], arm_traj.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(traj.x[:, split:], block_traj.x, rtol=0, atol=1e-9)


def test_the_splitting_converges_for_each_body_as_alone():
    """With the splitting alone (no active set), each body's Anderson coefficients are its
    own (``Model.contact_blocks``, one per body), so the block's landing does
    not stall the arm's convergence: every step converges within 3000 iterations at
    tol 1e-8 (measured at most 772). With one set of coefficients for both bodies a landing
    step reached the 3000-iteration cap. (The counts move by factors of 2-4 with rounding:
    the map is piecewise smooth and Anderson mixing amplifies small differences.)"""
    n_steps = 8
    options = Options(dt=0.01, tol=1e-8, max_iter=3000)
    both, params = build([_arm("arm"), _block("block")], obstacles=GROUND, options=options)
    np.testing.assert_array_equal(both.contact_blocks, np.repeat([0, 1], [ARM.n_vertices, BLOCK.n_vertices]))
    traj = rollout(both, params, initial_state(both, params), n_steps=n_steps, controls=jnp.full((n_steps, 1), 0.5))
    assert bool(np.all(traj.info.converged)), np.asarray(traj.info.iterations)
    with pytest.raises(SceneError, match="must end at the scene's"):
        build([_arm("arm"), _block("block")], obstacles=GROUND,
              options=Options(contact=Contact(blocks=((0, ARM.n_vertices),))))

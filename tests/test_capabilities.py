"""The capability table: every strategy declares the scene features it cannot step
(``Capabilities``), and each refused combination is refused before anything compiles,
naming why, what to use instead and what the strategy supports. Three of these
combinations used to run and silently drop physics: an explicit integrator chosen in the
options (contact and joints ignored), the Newton and diffrax references with obstacles
(contact ignored), and ``step`` in a scene whose integrator is not implicit Euler."""

import jax.numpy as jnp
import numpy as np
import pytest

from softbody import simulate
from softbody._interfaces import Capabilities
from softbody.aero import Drag
from softbody._types import FEATURES
from softbody.contact.active_set import ActiveSet
from softbody.contact import Contact
from softbody.explicit import SymplecticEuler, explicit_rollout
from softbody.gradients import Unrolled
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.meshing.mesh import Region
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.contact.obstacles import Plane
from softbody.contact.pairs import Touch
from softbody.reference import diffrax_rollout, newton_rollout, newton_static, newton_step
from softbody.rigid import RigidBody
from softbody.scene import Fix, SoftBody
from softbody.simulate import BDF2, step
from softbody.skeleton import Link, Skeleton

from test_rigid import box

BAR = grid_box((0.1, 0.02, 0.02), (4, 1, 1))
MATERIAL = Material(E=1e5, nu=0.3)
EXPLICIT = Options(dt=1e-4, integrator=SymplecticEuler(jnp.asarray(1e-4)))


def _scene(feature, options=Options()):
    """A small scene with exactly one feature of the table (``None``: none)."""
    if feature == "pair contact":
        block = grid_box((0.02, 0.02, 0.02), (1, 1, 1), origin=(0.0, 0.0, 0.021))
        return build([SoftBody(BAR, MATERIAL, fixed="fixed", name="bar"), SoftBody(block, MATERIAL, name="block")],
                     rows=[Touch("block", "bar")], options=options)
    if feature == "contact":
        return build(SoftBody(BAR, MATERIAL, fixed="fixed"), obstacles=[Plane(point=(0, 0, -0.01))], options=options)
    if feature == "skeleton":
        arm = Region(vertices=np.flatnonzero(BAR.points[:, 0] > 0.07).astype(np.int32))
        return build(SoftBody(BAR.with_regions(**{"bone:arm": arm}), MATERIAL, fixed="fixed"),
                     skeleton=Skeleton([Link("arm", "bone:arm")]), options=options)
    if feature == "rigid bodies":
        return build([SoftBody(BAR, MATERIAL, fixed="fixed", name="bar"),
                      RigidBody(box((0.02, 0.02, 0.02)), density=500.0, name="brick", x0=(0.2, 0.0, 0.0))],
                     options=options)
    if feature == "motion":
        return build(SoftBody(BAR, MATERIAL, fixed="fixed", motion=lambda t: (jnp.eye(3), jnp.asarray([t, 0, 0]))),
                     options=options)
    if feature == "velocity forces":
        return build(SoftBody(BAR, MATERIAL, fixed="fixed", actuators=[Drag.on(BAR, BAR.surface, wind=(1, 0, 0))]),
                     options=options)
    if feature == "partly held vertices":
        return build(SoftBody(BAR, MATERIAL, fixed=[Fix("fixed"), Fix("ymin", axes="y")]), options=options)
    return build(SoftBody(BAR, MATERIAL, fixed="fixed"), options=options)


@pytest.mark.parametrize("feature", [None, *FEATURES])
def test_a_model_knows_its_features(feature):
    model, _ = _scene(feature)
    # pair rows are contact rows: a scene with them has both features
    assert model.features == (frozenset() if feature is None else {feature} | ({"contact"} if feature == "pair contact"
                                                                              else set()))


@pytest.mark.parametrize("feature", ["pair contact", "contact", "skeleton", "rigid bodies", "motion"])
def test_an_explicit_integrator_in_the_options_refuses_what_it_would_drop(feature, no_compiling):
    """``Options(integrator=SymplecticEuler(...))`` used to pass ``build`` and step through
    contact and joints as if they were not there."""
    with pytest.raises(SceneError, match=r"Options\(integrator=SymplecticEuler\(\)\) (has no|does not).*"
                                         r"it supports: partly held vertices"):
        _scene(feature, EXPLICIT)


def test_an_explicit_integrator_in_the_options_runs_what_it_supports():
    model, params = _scene("partly held vertices", EXPLICIT)
    traj = simulate.rollout(model, params, initial_state(model, params), n_steps=2)
    reference = explicit_rollout(model, params, initial_state(model, params), n_steps=2)
    np.testing.assert_array_equal(np.asarray(traj.x), np.asarray(reference.x))


@pytest.mark.parametrize("feature", ["contact", "skeleton", "rigid bodies", "motion"])
def test_explicit_rollout_refuses_from_the_same_table(feature, monkeypatch):
    monkeypatch.setattr("softbody.explicit._explicit", lambda *a: pytest.fail("compiled before refusing"))
    model, params = _scene(feature)
    with pytest.raises(SceneError, match=f"explicit_rollout .*the scene has {feature}"):
        explicit_rollout(model, params, initial_state(model, params), n_steps=2)


@pytest.mark.parametrize("feature", ["contact", "skeleton", "rigid bodies", "motion"])
def test_the_newton_reference_refuses_what_it_would_drop(feature, no_compiling):
    """With obstacles, Newton's steps used to pass through them."""
    model, params = _scene(feature)
    state = initial_state(model, params)
    calls = [lambda: newton_step(model, params, state), lambda: newton_rollout(model, params, state, n_steps=2)]
    if feature not in ("rigid bodies",):  # a static solve of a free rigid body is refused by prepare
        calls.append(lambda: newton_static(model, params))
    for call in calls:
        with pytest.raises(SceneError, match=f"the Newton reference .*the scene has {feature}.*"
                                             "simulate.rollout"):
            call()


@pytest.mark.parametrize("feature", list(FEATURES))
def test_the_diffrax_reference_refuses_what_it_would_drop(feature, no_compiling):
    """With obstacles, the diffrax reference used to integrate through them."""
    model, params = _scene(feature)
    with pytest.raises(SceneError, match=f"diffrax_rollout .*the scene has {feature}.*it supports: none of them"):
        diffrax_rollout(model, params, initial_state(model, params), 0.01, [0.01])


def test_step_refuses_an_integrator_it_would_ignore(monkeypatch):
    """``step`` took an implicit-Euler step whatever ``Options.integrator`` said."""
    monkeypatch.setattr(simulate.ImplicitEuler, "step", lambda *a: pytest.fail("stepped before refusing"))
    model, params = _scene(None, Options(integrator=BDF2()))
    with pytest.raises(SceneError, match=r"integrator is BDF2\(\) \(Options.integrator\).*use rollout"):
        step(model, prepare(model, params), initial_state(model, params))


def test_unrolled_refuses_contact_from_the_table(no_compiling):
    with pytest.raises(SceneError, match=r"Options\(adjoint=Unrolled\(\)\) differentiates the iterations as they "
                                         r"ran.*Implicit\(\).*it supports: skeleton, rigid bodies, motion"):
        _scene("contact", Options(adjoint=Unrolled()))


def test_a_capability_names_only_known_features():
    with pytest.raises(ValueError, match="unknown scene features"):
        Capabilities(refuses={"cloth": "has no shells"})
    assert Capabilities().supported == tuple(FEATURES)


def test_reduced_coordinates_and_the_active_set_refuse_from_the_table(no_compiling):
    """Partly held vertices beside a rigid body used to pass ``build`` and fail inside the
    first step's factorisation (``PerColumn.factorize: data must have shape (k, n)``); the
    active set in a scene of rigid bodies is refused from the same table as with a
    skeleton."""
    brick = RigidBody(box((0.02, 0.02, 0.02)), density=500.0, name="brick", x0=(0.2, 0.0, 0.0))
    with pytest.raises(SceneError, match="a scene with rigid bodies holds vertices in all three components only.*"
                                         "it supports: pair contact, contact, skeleton, rigid bodies, motion"):
        build([SoftBody(BAR, MATERIAL, fixed=[Fix("fixed"), Fix("ymin", axes="y")], name="bar"), brick])
    with pytest.raises(SceneError, match=r"Contact\(active_set=ActiveSet\(\)\) works in vertex coordinates.*"
                                         r"the scene has rigid bodies.*Contact\(active_set=None\)"):
        build([SoftBody(BAR, MATERIAL, fixed="fixed", name="bar"), brick], obstacles=[Plane(point=(0, 0, -0.01))],
              options=Options(contact=Contact(active_set=ActiveSet())))

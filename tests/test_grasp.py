"""The grasp example (examples/grasp.py): two pneumatic fingers on a rising palm pick a soft
cube and a rigid box off a table through friction alone (Touch between the fingers and the object)."""

import sys
from pathlib import Path

import numpy as np
import pytest

from softbody.model import initial_state
from softbody.simulate import rollout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import grasp


@pytest.mark.slow
@pytest.mark.parametrize("obj", grasp.OBJECTS)
def test_fingers_lift_each_object_without_slip(obj):
    """At a hand-set 30 kPa the fingers close on the 3 cm object (a soft cube, or a free rigid
    box of 8 g) over 0.4 s and the palm rises 7 cm: every step converges, the object rises by
    at least 5 cm (the grasp goal) and moves by less than 1 mm relative to the fingertips
    while lifted (held by static friction). The rigid box squeezed between the soft fingers
    needs ``Contact.rigid_floor``: with its vertices swept by their inertia alone six steps
    stopped at the 6000-iteration cap."""
    model, params, obj_v, tips = grasp.scene(obj)
    traj = rollout(model, params, initial_state(model, params), grasp.pressure_ramp(3e4))  # raises unless converged
    m = grasp.grasp_metrics(traj.x, obj_v, tips)
    assert np.all(np.asarray(traj.info.result) == 0)
    assert m["lift_m"] >= grasp.LIFT_GOAL
    assert m["slip_m"] < grasp.SLIP_GOAL

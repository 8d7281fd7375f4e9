"""The grasp example (examples/grasp.py): two pneumatic fingers on a rising palm pick a soft
cube off a table through friction alone (Touch between the fingers and the cube)."""

import sys
from pathlib import Path

import numpy as np
import pytest

from softbody.model import initial_state
from softbody.simulate import rollout

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import grasp


@pytest.mark.slow
def test_fingers_lift_soft_cube_without_slip():
    """At a hand-set 30 kPa the fingers close on the 3 cm cube over 0.4 s and the palm rises
    7 cm: every step converges, the cube rises by at least 5 cm (the grasp goal) and moves by
    less than 1 mm relative to the fingertips while lifted (held by static friction)."""
    model, params, obj_v, tips = grasp.scene("soft_cube")
    traj = rollout(model, params, initial_state(model, params), grasp.pressure_ramp(3e4))  # raises unless converged
    m = grasp.grasp_metrics(traj.x, obj_v, tips)
    assert np.all(np.asarray(traj.info.result) == 0)
    assert m["lift_m"] >= grasp.LIFT_GOAL
    assert m["slip_m"] < grasp.SLIP_GOAL

"""Contact: rows that keep bodies out of obstacles and out of each other, with dry friction,
and the iteration that solves a step with them.

One job per module:

* :mod:`~softbody.contact.obstacles`: obstacles as signed distance functions, one generator
  of vertex rows (:class:`~softbody.contact.obstacles.ObstacleRows`).
* :mod:`~softbody.contact.pairs`: rows between two bodies' surfaces
  (:class:`~softbody.contact.pairs.Touch`), found by the hashed grid of
  :mod:`~softbody.contact.broad_phase`.
* :mod:`~softbody.contact.rows`: the rows one step sees (the deepest vertex row per point;
  the pair rows chosen at the step's start).
* :mod:`~softbody.contact.law`: the contact law of a row (stick, slide, separate) and the
  contact states it reports.
* :mod:`~softbody.contact.solver`: :class:`Contact`, the splitting iteration that solves a
  step with the rows.
* :mod:`~softbody.contact.report`: the contact forces and states at a step's solution.
* :mod:`~softbody.contact.splitting`: the diagonal splittings it sweeps with.
* :mod:`~softbody.contact.active_set`: the opt-in active-set iteration on the prefactored
  matrix.
* :mod:`~softbody.contact.anderson`: the one fixed-point loop (best iterate, Anderson,
  restarts) that both iterations run.
* :mod:`~softbody.contact.fixed_point`: the implicit derivative of a step's fixed point.
* :mod:`~softbody.contact.impact_zone`: the collision-response QP with its KKT and QR
  backward, the reference the pair rows' gradient tests compare with.
* :mod:`~softbody.contact.ccd`: continuous collision detection (did a step tunnel?).

The interfaces a generator implements (:class:`~softbody._interfaces.Rows`,
:class:`~softbody._interfaces.PairRows`) live in the bottom layer, so that generators need
nothing from here.
"""

from softbody.contact.law import CONTACT_STATES, SLIDING_SPEED
from softbody.contact.solver import Contact, ContactMap

__all__ = ["CONTACT_STATES", "SLIDING_SPEED", "Contact", "ContactMap"]

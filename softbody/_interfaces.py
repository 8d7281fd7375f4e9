"""The interfaces that strategies and scene parts implement (the bottom layer: it imports
no strategy and nothing else of softbody).

Actuators contribute to a step's objective in one of three ways, one base class each, so
that the step dispatches on the type of a term rather than on which methods it happens to
have:

* :class:`ElementActuator`: a PD-style element term on a set of tets
  (``energy_and_stress``; its PD matrix blocks join the prefactored matrix), e.g. muscles.
* :class:`VertexActuator`: an energy of the vertex positions (``energy_and_gradient``;
  the matrix is left alone), e.g. cavity pressure, joint torques and servos.
* :class:`VolumeActuator`: new targets for the volume term of some tets
  (``volume_targets``), e.g. pneumatic cells.

Every actuator has named control channels, each with the range of values it accepts
(:meth:`Actuator.channel_bounds`), design parameters (``init_params``) and per-rollout data
(``prepare``).
"""

from __future__ import annotations

import numpy as np


class Actuator:
    """Base class of actuator terms.

    Subclasses set ``channel_names`` (a tuple of unique names, one per control channel) and
    implement :meth:`init_params`, :meth:`prepare` and the method of their kind.
    """

    channel_names: tuple[str, ...]

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The range ``lower <= a <= upper`` of each channel's activation.

        Concrete controls outside it are refused before a simulation starts; inside a
        traced computation (an optimisation) values are clipped to it, with zero gradient
        beyond. Unbounded by default.

        Returns:
            ``(lower, upper)``, float arrays of shape ``(n_channels,)`` (``-inf``/``inf``
            where unbounded).
        """
        n = len(self.channel_names)
        return np.full(n, -np.inf), np.full(n, np.inf)

    def init_params(self):
        """The term's differentiable design parameters (a pytree; ``()`` for none)."""
        raise NotImplementedError

    def prepare(self, model, params, dminv, volume):
        """Per-rollout data from the design parameters ``params``, the rest shape's inverse
        edge matrices ``dminv`` ``(3, 3, t)`` and tet volumes ``volume`` ``(t,)``."""
        raise NotImplementedError


class ElementActuator(Actuator):
    """An element term on the tets ``prep.tets`` ``(m,)``.

    ``prepare`` returns data with ``tets`` and ``local_matrices`` ``(m, 4, 4)`` (the term's
    blocks of the PD matrix).
    """

    def energy_and_stress(self, f, prep, activation):
        """``(energy (m,), dE/dF (3, 3, m))`` for the deformation gradients ``f``
        ``(3, 3, m)`` of the term's tets and the term's activations ``(c,)``."""
        raise NotImplementedError


class VertexActuator(Actuator):
    """An energy of the positions that adds nothing to the PD matrix."""

    def energy_and_gradient(self, x, prep, activation):
        """``(energy, dE/dx (n, 3))`` at positions ``x`` ``(n, 3)``."""
        raise NotImplementedError


class VolumeActuator(Actuator):
    """New targets of the volume term on some tets."""

    def volume_targets(self, prep, activation):
        """``(tets (m,), s (m,))``: the volume term of those tets targets ``det F = s^3``."""
        raise NotImplementedError

"""softbody.actuators: muscle, pneumatic and joint actuators.

This folder (``actuators/`` in the repository) installs as ``softbody.actuators``.

* :class:`Muscle`: fibres that contract along a rest direction (element term).
* :class:`CavityPressure`: gauge pressure in pascals in a closed, tagged cavity (vertex
  term); :class:`CavityVolume`: the same cavity driven by pumped volume.
* :class:`PneumaticCells`: the cell model, tets whose volume target is the activation.
"""

from .muscle import Muscle
from .pneumatic import CavityPressure, CavityVolume, PneumaticCells

__all__ = ["CavityPressure", "CavityVolume", "Muscle", "PneumaticCells"]

"""softbody.actuators: muscle, pneumatic and joint actuators.

This folder (``actuators/`` in the repository) installs as ``softbody.actuators``.
"""

"""softbody.control: losses, trajectory optimisation, system identification, co-design.

This folder (``control/`` in the repository) installs as ``softbody.control``; there is
no top-level ``control`` package, so nothing collides with python-control.
"""

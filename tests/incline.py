"""Shared pieces of the incline scenes (a body set down on a tilted friction plane).

Gravity enters as external forces ramped up over 0.1 s so that the body is set down
gently: switched on at once it rings, and the overshoot of the shear traction makes the
edges slip, which in the band ``mu_k < tan(theta) < mu_s`` can start a slide that kinetic
friction cannot stop (physical stick-slip, not what these tests look at).
"""

import numpy as np

G = 9.81  # m/s^2


def rot_y(theta):
    """The rotation by ``theta`` (rad) about y, ``(3, 3)``."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def ramped_gravity(mass, n_steps, dt, ramp=0.1):
    """``(n_steps, n, 3)`` weights of the ``(n, 1)`` masses, ramped from 0 to full over
    ``ramp`` seconds."""
    scale = np.clip(np.arange(1, n_steps + 1) * dt / ramp, 0.0, 1.0)
    return scale[:, None, None] * mass[None] * np.array([0.0, 0.0, -G])


def acceleration(s, dt, start):
    """Twice the quadratic coefficient of a least-squares fit of ``s(t)`` over frames >= start."""
    t = np.arange(len(s)) * dt
    return 2 * np.polyfit(t[start:], s[start:], 2)[0]

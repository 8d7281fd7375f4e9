"""A sweep scene: a coarse clamped beam sagging under gravity, over Young's modulus and the
time step (``softbody sweep examples/sweep_beam.json``, and ``examples/sweep_scaling.py``).

``setup()`` builds what every point shares (the mesh); ``point(scene, E, dt)`` simulates one
point. The time step is static (each value compiles its own program), so the scene keeps
one built model per time step; Young's modulus is a traced parameter, so every modulus
reuses that model's compiled rollout. ``point`` returns JAX scalars, so it also runs
batched under ``jax.vmap`` (``vectorize=True, static=["dt"]``).
"""

from __future__ import annotations

import jax.numpy as jnp

from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout


def setup(cells=(5, 1, 1)):
    """The scene: the beam's mesh (0.1 x 0.02 x 0.02 m), its tip and a model per time step."""
    mesh = grid_box((0.1, 0.02, 0.02), cells)
    return {"mesh": mesh, "tip": mesh.region("tip").vertices, "models": {}}


def point(scene, E, dt, n_steps=8):
    """The tip's vertical displacement (m) after ``n_steps`` steps from rest, and the mean
    PD iterations per step."""
    models = scene["models"]
    if dt not in models:
        models[dt] = build(SoftBody(scene["mesh"], Material(E=1e5, nu=0.45, density=1000.0), fixed="fixed"),
                           options=Options(dt=dt, tol=1e-8, max_iter=2000))
    model, params = models[dt]
    p = params.replace(E=jnp.full_like(params.E, E))
    traj = rollout(model, p, initial_state(model, p), n_steps=n_steps)
    tip = scene["tip"]
    return {"tip_dz": traj.x[-1, tip, 2].mean() - scene["mesh"].points[tip, 2].mean(),
            "iterations": jnp.mean(traj.info.iterations)}

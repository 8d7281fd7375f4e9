"""Grasping: two pneumatic fingers pick an object off a table and lift it.

Two pneumatic fingers (:func:`softbody.meshing.finger`, 60 mm long, silicone-like
E = 200 kPa) hang downwards on either side of an object resting on a table
(:class:`softbody.contact.obstacles.Plane` with friction). Each finger's chamber lies on
its outer side, so that pressure curls its tip towards the object. Their base faces are
held by one palm (:class:`softbody.scene.SoftBody` ``motion=``, a moving clamp): still
while the fingers close (0.4 s), then rising ``RISE`` over 0.8 s (a smooth step), then
still again, 1.5 s in all at dt = 10 ms. One :class:`softbody.contact.pairs.Touch` over the
two fingers and the object carries the normal and friction forces between them (rubber
on plastic, mu_s = mu_k = ``MU``). Two objects: a free rigid box
(:class:`softbody.rigid.RigidBody`) and a soft cube (:class:`softbody.scene.SoftBody`).

The scene reports per object ``lift_m`` (the rise of the object's centre at the end) and
``slip_m`` (the largest change, while lifted, of the object's centre relative to the mean
of the fingertips) at a hand-set pressure (``--pressure``, a 0.3 s ramp). The pressures
are not optimised here yet: a gradient through this 150-step rollout with contact between
the bodies took longer than 26 minutes on the 2-core machine (see examples/README.md).

Run::

    python examples/grasp.py --out results/grasp                  # hand-set 30 kPa, both objects

Writes ``metrics.json`` (per object ``lift_m``, ``slip_m``, convergence and iteration
counts), a result file per object (``rigid_box.npz``, ``soft_cube.npz``: ``softbody view``
opens them; "colour by" ``contact_force`` or ``contact_state`` shows the contact between
the fingers, the object and the table) and a render of each one's last frame (``rigid_box.png``, ``soft_cube.png``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax.numpy as jnp
import numpy as np

from softbody import progress
from softbody.actuators import CavityPressure
from softbody.contact.obstacles import Plane
from softbody.contact.pairs import Touch
from softbody.io import Result, check_overwrite, write_metrics
from softbody.material import Material
from softbody.meshing import TetMesh, finger
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.rigid import RigidBody
from softbody.scene import SoftBody
from softbody.simulate import contact_fields, rollout

DT, DURATION = 0.01, 1.5
N_STEPS = round(DURATION / DT)
CLOSE, RISE_TIME, RISE = 0.4, 0.8, 0.07  # s, s, m
LENGTH, WIDTH, HEIGHT = 0.06, 0.02, 0.02  # finger, m
EDGE = 0.03  # the object's edge, m
GAP = 0.002  # between each finger's inner face and the object at rest, m
TIP_Z = 0.006  # fingertips' height above the table at rest, m
MU = 0.8  # fingers on the object
MU_TABLE = 0.5
THICKNESS = 1e-3
P_MAX = 6e4
CAPACITY = 16384  # broad-phase candidates per body: headroom over the default (64 per surface vertex)
OBJECTS = ("rigid_box", "soft_cube")
LIFT_GOAL, SLIP_GOAL = 0.05, 1e-3  # m: lift at least, slip below


def finger_mesh(side: int, size: float = 0.008) -> TetMesh:
    """A finger hanging down (its base up) on the ``side`` (-1 or +1) of x = 0, its chamber
    outwards: local +x (along the finger) maps to world -z, local +z (the chamber's side)
    to ``side`` times world x."""
    mesh = finger(length=LENGTH, width=WIDTH, height=HEIGHT, base=0.008, size=size)
    R = np.array([[0.0, 0.0, side], [0.0, side, 0.0], [-1.0, 0.0, 0.0]])
    offset = np.array([side * (EDGE / 2 + GAP + HEIGHT / 2), 0.0, TIP_Z + LENGTH])
    return TetMesh(mesh.points @ R.T + offset, mesh.tets, mesh.surface, mesh.regions, mesh.fields)


def palm_height(t):
    """The palm's rise (m) at time ``t`` (s): still, a smooth step of ``RISE`` over
    ``RISE_TIME`` from ``CLOSE``, then still."""
    s = jnp.clip((t - CLOSE) / RISE_TIME, 0.0, 1.0)
    return RISE * s * s * (3.0 - 2.0 * s)


def palm(t):
    """The held base faces' rigid motion ``t -> (R, p)``."""
    return jnp.eye(3), jnp.stack([0.0 * t, 0.0 * t, palm_height(t)])


def scene(obj: str, *, finger_size: float = 0.008, max_iter: int = 6000, tol: float = 1e-4,
          capacity: int | None = CAPACITY):
    """Build the grasp scene with ``obj`` (one of ``OBJECTS``) on the table; returns
    ``(model, params, object_vertices, tip_vertices)`` (scene indices)."""
    silicone = Material(E=2e5, nu=0.4, density=1100.0, alpha=10.0)
    bodies = []
    for side, name in ((-1, "left"), (1, "right")):
        mesh = finger_mesh(side, finger_size)
        chamber = CavityPressure.from_regions(mesh, ["cavity:chamber"], min_pressure=0.0, max_pressure=P_MAX)
        bodies.append(SoftBody(mesh, silicone, fixed="fixed", motion=palm, actuators=[chamber], name=name))
    # both objects on a 3 x 3 x 3 grid (the rigid box bounded by its surface, 1 cm triangles)
    cube = grid_box((EDGE,) * 3, (3, 3, 3), origin=(-EDGE / 2, -EDGE / 2, 0.0))
    if obj == "rigid_box":
        bodies.append(RigidBody(cube, density=300.0, name="object"))
    elif obj == "soft_cube":
        bodies.append(SoftBody(cube, Material(E=5e5, nu=0.4, density=300.0, alpha=10.0), name="object"))
    else:
        raise ValueError(f"unknown object {obj!r}; choose from {OBJECTS}")
    model, params = build(bodies, obstacles=[Plane(mu_s=MU_TABLE, mu_k=MU_TABLE)],
                          rows=[Touch("left", "right", "object", mu_s=MU, mu_k=MU, thickness=THICKNESS,
                                      capacity=capacity)],
                          options=Options(dt=DT, tol=tol, max_iter=max_iter))
    spans = {b.name: b for b in model.bodies}
    obj_v = np.arange(*spans["object"].vertices)
    tips = []
    for name in ("left", "right"):
        start = spans[name].vertices[0]
        tips.append(start + bodies[0].mesh.regions["tip"].vertices)
    return model, params, obj_v, np.concatenate(tips)


def pressure_ramp(p: float, ramp: float = 0.3) -> np.ndarray:
    """Both chambers' pressures ``(N_STEPS, 2)``: a linear ramp to ``p`` over ``ramp`` s, then constant."""
    t = (np.arange(N_STEPS) + 1) * DT
    return np.repeat((p * np.clip(t / ramp, 0.0, 1.0))[:, None], 2, axis=1)


def grasp_metrics(x, obj_v, tips):
    """``lift_m`` (the object's centre rise at the end) and ``slip_m`` (the largest change,
    while the palm rises and holds, of the object's centre relative to the fingertips' mean)."""
    x = np.asarray(x)
    centre = x[:, obj_v].mean(axis=1)
    rel = centre - x[:, tips].mean(axis=1)
    k0 = round(CLOSE / DT)
    slip = np.linalg.norm(rel[k0:] - rel[k0], axis=1).max()
    return {"lift_m": float(centre[-1, 2] - centre[0, 2]), "slip_m": float(slip)}


def save_result(model, params, traj, controls, path, metrics):
    """Write the trajectory as a result file for ``softbody view`` / ``softbody render``."""
    obstacles = [o.to_dict(p) for o, p in zip(model.obstacles, params.obstacles)]
    result = Result.from_mesh(model.mesh, np.asarray(traj.x), DT, obstacles=obstacles,
                              fields=contact_fields(model, params, traj, controls),
                              activation=np.concatenate([controls[:1] * 0.0, controls]),
                              channel_names=list(model.channel_names), metadata={"grasp": metrics})
    return result.save(path, force=True)


def hand_set(obj, pressure, out):
    """The rollout at a hand-set pressure ramp; returns its metrics and the built scene."""
    with progress.task(f"{obj}: building the scene"):
        model, params, obj_v, tips = scene(obj)
    controls = pressure_ramp(pressure)
    t0 = time.perf_counter()
    with progress.task(f"{obj}: simulating {N_STEPS} steps at {pressure / 1e3:.0f} kPa (compiles)"):
        traj = rollout(model, params, initial_state(model, params), controls, throw=False)
    wall = time.perf_counter() - t0
    it, res = np.asarray(traj.info.iterations), np.asarray(traj.info.result)
    m = grasp_metrics(traj.x, obj_v, tips)
    m.update(pressure_pa=pressure, all_converged=bool((res == 0).all()),
             failed_steps=np.flatnonzero(res != 0).tolist(), result_codes=sorted(set(res.tolist())),
             iterations_median=float(np.median(it)), iterations_max=int(it.max()), rollout_wall_time_s=wall,
             vertices=model.n_vertices)
    print(f"{obj}: lift {m['lift_m'] * 1e3:.1f} mm, slip {m['slip_m'] * 1e3:.3f} mm, "
          f"all steps converged: {m['all_converged']}, iterations median {m['iterations_median']:.0f} "
          f"max {m['iterations_max']}, {wall:.0f} s", flush=True)
    save_result(model, params, traj, controls, out / f"{obj}.npz", m)
    return m, (model, params, obj_v, tips)


def main(argv=None):
    """Run the hand-set grasp of each object; returns the metrics."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--pressure", type=float, default=3e4, help="hand-set chamber pressure, Pa")
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS), choices=OBJECTS)
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    metrics = {}
    for obj in args.objects:
        metrics[obj], _ = hand_set(obj, args.pressure, args.out)
        write_metrics(args.out / "metrics.json", metrics, force=True)
    _plots(args.out, metrics)
    metrics["wall_time_s"] = time.perf_counter() - start
    write_metrics(args.out / "metrics.json", metrics, force=True)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


def _plots(out, metrics):
    """A render of each object's last frame (``rigid_box.png``, ``soft_cube.png``)."""
    from softbody.render import render

    for obj in metrics:
        if (out / f"{obj}.npz").exists():
            render(out / f"{obj}.npz", out / f"{obj}.png", force=True)


if __name__ == "__main__":
    main()

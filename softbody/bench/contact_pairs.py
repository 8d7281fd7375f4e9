"""Bodies touching bodies (:class:`softbody.contact.pairs.Touch`): physics checks and costs.

Scenes (soft bodies, E = 1e6 Pa unless said, nu = 0.3, density 1e3 kg/m^3, contact
thickness 1 mm, relative tolerance 1e-8):

* ``rest``: a 2 cm soft cube (E = 1e5 Pa) on a 10 x 4 x 1 cm slab held at its base,
  dt = 0.01 s, 2 s. Reported: the deepest penetration of a row below the contact
  thickness over all steps (as a fraction of the cube's edge), the drift of the cube's
  centre over the last second, iterations per step.
* ``slide``: a 2 x 2 x 1 cm block launched at v0 = 0.3 m/s along the same slab (mu_s = 0.5,
  mu_k = 0.3) until it stops, at dt = 0.01, 0.005, 0.0025 s. Reported: the stopping
  distance against ``v0^2 / (2 g mu_k)`` and against the same block on a
  :class:`~softbody.contact.obstacles.Plane` obstacle at the slab's top (the same implicit-Euler
  discretisation: its error is ``~ v0 h / 2``), iterations per step. And once with
  mu_s = mu_k = 0.3 at dt = 0.01 s: whether every step converges (the step where the block
  comes to rest is the hard one).

* ``stack``: three 2 cm soft boxes stacked on the slab (mu_s = 0.5, mu_k = 0.4, each pair of
  neighbours a :class:`~softbody.contact.pairs.Touch`), dt = 0.01 s, 2 s: aligned, and each box
  shifted 2 mm along x from the one below. Reported: the largest displacement of a box's
  centre from its start (the issue's bar for a stack: 1 mm).

* ``rigid``: rigid bodies (:class:`~softbody.rigid.RigidBody`, density 500 kg/m^3) in pair
  rows, dt = 0.01 s, 2 s: a 2 cm rigid box set on the slab of ``rest`` (penetration, drift
  as there); three 10 cm rigid boxes stacked on a plane obstacle (largest displacement of
  a box's vertex); and the 2 cm box dropped from 2 cm above the slab (0.3 s at most 3000
  iterations a step, ``capacity=4096``: the default overflows at the impact; whether every
  step converges).

``iterations_median`` and ``iterations_max`` are over every step of the scenes above (the
mu_s = mu_k run and the rigid drop apart); ``broad_phase_share`` is the time of choosing a step's rows
(:meth:`~softbody.contact.pairs.Touch.select`: the broad phase, :mod:`softbody.contact.broad_phase`, and
the nearest of its candidates) over the time of a step of the ``rest`` scene (medians,
compile excluded).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

G, THICKNESS, V0 = 9.81, 1e-3, 0.3


def _scene(block_mesh, E_block, mu_s, mu_k, dt, plane=False):
    from softbody.material import Material
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build
    from softbody.contact.obstacles import Plane
    from softbody.contact.pairs import Touch
    from softbody.scene import SoftBody

    options = Options(dt=dt, tol=1e-8, max_iter=10000)
    if plane:
        return build(SoftBody(block_mesh, Material(E=E_block, nu=0.3, density=1000.0), name="block"),
                     obstacles=[Plane(point=(0.0, 0.0, 0.01 + THICKNESS), mu_s=mu_s, mu_k=mu_k)], options=options)
    slab = grid_box((0.1, 0.04, 0.01), (10, 4, 1), origin=(-0.03, -0.02, 0.0))
    return build([SoftBody(slab, Material(E=1e6, nu=0.3, density=1000.0), fixed="zmin", name="slab"),
                  SoftBody(block_mesh, Material(E=E_block, nu=0.3, density=1000.0), name="block")],
                 rows=[Touch("block", "slab", mu_s=mu_s, mu_k=mu_k, thickness=THICKNESS)], options=options)


def _launch(model, v0):
    import equinox as eqx

    from softbody.model import initial_state

    state = initial_state(model)
    block = model.body("block").vertices
    return eqx.tree_at(lambda s: s.v, state, state.v.at[block[0]:block[1], 0].set(v0))


def _row_gaps(model, params, x):
    import jax.numpy as jnp

    generator, p = model.rows[0], params.rows[0]
    return np.array([float(jnp.min(generator.frame(x[k], generator.select(x[k - 1], x[k], p), p).phi))
                     for k in range(1, len(x))])


def _rest(quick: bool) -> dict:
    import jax

    from softbody.bench import median_seconds
    from softbody.meshing.grid import grid_box
    from softbody.model import initial_state
    from softbody.simulate import rollout

    edge = 0.02
    cube = grid_box((edge, edge, edge), (2, 2, 2), origin=(-0.01, -0.01, 0.01 + THICKNESS))
    model, params = _scene(cube, 1e5, 0.5, 0.4, 0.01)
    n_steps = 50 if quick else 200
    state = initial_state(model)
    traj = rollout(model, params, state, n_steps=n_steps, throw=False)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(rollout(model, params, state, n_steps=n_steps, throw=False).x)
        times.append((time.perf_counter() - start) / n_steps)
    x = np.asarray(traj.x)
    gaps = _row_gaps(model, params, traj.x)
    a, b = model.body("block").vertices
    centre = x[:, a:b].mean(axis=1)
    half = n_steps // 2
    # the time of choosing one step's rows, at the last step's positions
    generator, p = model.rows[0], params.rows[0]
    select = jax.jit(lambda x0, x1: generator.select(x0, x1, p))
    select_s = median_seconds(select, traj.x[-2], traj.x[-1], repeats=20)
    info = traj.info
    return {"steps": n_steps, "converged": bool(np.all(np.asarray(info.converged))),
            "penetration_over_edge": float(max(0.0, -gaps.min()) / edge),
            "drift_last_half_m": float(np.abs(centre[half:] - centre[half]).max()),
            "iterations": np.asarray(info.iterations).tolist(),
            "step_s": float(np.median(times)), "select_s": select_s}


def _slide(dt: float, mu_s: float, mu_k: float) -> dict:
    from softbody.meshing.grid import grid_box
    from softbody.simulate import rollout

    block = grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.01 + THICKNESS))
    out = {"dt": dt, "mu_s": mu_s, "mu_k": mu_k, "expected_m": V0**2 / (2 * G * mu_k)}
    n_steps = int(round((V0 / (G * mu_k) + 0.05) / dt))
    for plane in (False, True):
        model, params = _scene(block, 1e6, mu_s, mu_k, dt, plane=plane)
        traj = rollout(model, params, _launch(model, V0), n_steps=n_steps, throw=False)
        a, b = model.body("block").vertices
        centre = np.asarray(traj.x)[:, a:b, 0].mean(axis=1)
        key = "plane" if plane else "pairs"
        out[f"{key}_distance_m"] = float(centre[-1] - centre[0])
        out[f"{key}_converged"] = bool(np.all(np.asarray(traj.info.converged)))
        out[f"{key}_iterations"] = np.asarray(traj.info.iterations).tolist()
    out["error_vs_expected"] = out["pairs_distance_m"] / out["expected_m"] - 1
    out["error_vs_plane"] = out["pairs_distance_m"] / out["plane_distance_m"] - 1
    return out


def _stack(shift: float, quick: bool) -> dict:
    from softbody.material import Material
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build, initial_state
    from softbody.contact.pairs import Touch
    from softbody.scene import SoftBody
    from softbody.simulate import rollout

    slab = grid_box((0.08, 0.08, 0.01), (4, 4, 1), origin=(-0.04, -0.04, 0.0))
    material = Material(E=1e6, nu=0.3, density=1000.0)
    bodies = [SoftBody(slab, material, fixed="zmin", name="slab")]
    rows, below = [], "slab"
    for i in range(3):
        box = grid_box((0.02, 0.02, 0.02), (2, 2, 2),
                       origin=(-0.01 + shift * i, -0.01, 0.01 + THICKNESS + i * (0.02 + THICKNESS)))
        bodies.append(SoftBody(box, material, name=f"box{i}"))
        rows.append(Touch(f"box{i}", below, mu_s=0.5, mu_k=0.4, thickness=THICKNESS))
        below = f"box{i}"
    model, params = build(bodies, rows=rows, options=Options(dt=0.01, tol=1e-8, max_iter=10000))
    n_steps = 50 if quick else 200
    traj = rollout(model, params, initial_state(model), n_steps=n_steps, throw=False)
    x = np.asarray(traj.x)
    moved = []
    for i in range(3):
        a, b = model.body(f"box{i}").vertices
        centre = x[:, a:b].mean(axis=1)
        moved.append(float(np.linalg.norm(centre - centre[0], axis=1).max()))
    return {"shift_m": shift, "steps": n_steps, "converged": bool(np.all(np.asarray(traj.info.converged))),
            "moved_max_m": moved, "iterations": np.asarray(traj.info.iterations).tolist()}


def _rigid(quick: bool) -> dict:
    import jax.numpy as jnp

    from softbody.contact.obstacles import Plane
    from softbody.contact.pairs import Touch
    from softbody.material import Material
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build, initial_state
    from softbody.rigid import RigidBody
    from softbody.scene import SoftBody
    from softbody.simulate import rollout

    def box(size, centre):
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
        quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
        triangles = np.array([t for q in quads for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])])
        return (corners - 0.5) * np.asarray(size) + np.asarray(centre), triangles

    n_steps = 50 if quick else 200
    slab = grid_box((0.1, 0.04, 0.01), (10, 4, 1), origin=(-0.03, -0.02, 0.0))
    soft = SoftBody(slab, Material(E=1e6, nu=0.3, density=1000.0), fixed="zmin", name="slab")

    def on_slab(height, steps, max_iter, capacity=None):
        rigid = RigidBody(box((0.02, 0.02, 0.02), (0.0, 0.0, 0.02 + THICKNESS + height)), density=500.0, name="box")
        touch = Touch("box", "slab", mu_s=0.5, mu_k=0.4, thickness=THICKNESS, capacity=capacity)
        model, params = build([soft, rigid], rows=[touch],
                              options=Options(dt=0.01, tol=1e-8, max_iter=max_iter))
        traj = rollout(model, params, initial_state(model), n_steps=steps, throw=False)
        return model, params, traj

    model, params, traj = on_slab(0.0, n_steps, 10000)
    gaps = _row_gaps(model, params, traj.x)
    centre = np.asarray(traj.x)[:, slab.n_vertices:].mean(axis=1)
    rest = {"converged": bool(np.all(np.asarray(traj.info.converged))),
            "penetration_over_edge": float(max(0.0, -gaps.min()) / 0.02),
            "drift_last_half_m": float(np.abs(centre[n_steps // 2:] - centre[n_steps // 2]).max()),
            "iterations": np.asarray(traj.info.iterations).tolist()}
    boxes = [RigidBody(box((0.1, 0.1, 0.1), (0.0, 0.0, 0.05 + i * (0.1 + THICKNESS))), density=500.0, name=f"b{i}")
             for i in range(3)]
    model, params = build(boxes, obstacles=[Plane(mu_s=0.5, mu_k=0.4)],
                          rows=[Touch("b1", "b0", mu_s=0.5, mu_k=0.4, thickness=THICKNESS),
                                Touch("b2", "b1", mu_s=0.5, mu_k=0.4, thickness=THICKNESS)],
                          options=Options(dt=0.01, tol=1e-8, max_iter=10000))
    traj = rollout(model, params, initial_state(model), n_steps=n_steps, throw=False)
    x = np.asarray(traj.x)
    stack = {"converged": bool(np.all(np.asarray(traj.info.converged))),
             "moved_max_m": float(np.abs(x - x[0]).max()), "iterations": np.asarray(traj.info.iterations).tolist()}
    _, _, traj = on_slab(0.02, 30, 3000, capacity=4096)
    drop = {"converged": bool(np.all(np.asarray(traj.info.converged))),
            "results": np.asarray(traj.info.result).tolist(), "iterations": np.asarray(traj.info.iterations).tolist(),
            "lowest_z_m": float(jnp.min(traj.x[:, slab.n_vertices:, 2]))}
    return {"rest": rest, "stack": stack, "drop": drop}


def run(out: Path, quick: bool) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from softbody import progress

    with progress.task("contact-pairs: cube resting on a slab"):
        rest = _rest(quick)
    slide_dts = (0.01,) if quick else (0.01, 0.005, 0.0025)
    slides = [_slide(dt, 0.5, 0.3) for dt in progress.track(slide_dts, "contact-pairs: block sliding to rest",
                                                            note=lambda dt: f"dt = {dt:g} s")]
    with progress.task("contact-pairs: block sliding, equal friction cones"):
        equal_cones = _slide(0.01, 0.3, 0.3)
    stacks = [_stack(shift, quick) for shift in progress.track((0.0, 0.002), "contact-pairs: stack of three boxes",
                                                               note=lambda s: f"shift {s:g} m")]
    with progress.task("contact-pairs: rigid boxes"):
        rigid = _rigid(quick)
    iterations = np.concatenate([rest["iterations"], *[s["pairs_iterations"] for s in slides],
                                 *[s["iterations"] for s in stacks], rigid["rest"]["iterations"],
                                 rigid["stack"]["iterations"]])

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    dts = [s["dt"] for s in slides]
    left.plot(dts, [s["pairs_distance_m"] * 100 for s in slides], "o-", label="block on slab (pair rows)")
    left.plot(dts, [s["plane_distance_m"] * 100 for s in slides], "s--", label="block on a plane obstacle")
    left.axhline(slides[0]["expected_m"] * 100, color="k", lw=0.8, label="v0^2 / (2 g mu_k)")
    left.set(xlabel="dt (s)", ylabel="stopping distance (cm)", xscale="log", title="sliding block")
    left.legend(fontsize=8)
    right.plot(rest["iterations"], label="cube resting on slab")
    right.plot(slides[0]["pairs_iterations"], label="block sliding, dt = 0.01 s")
    right.plot(rigid["rest"]["iterations"], label="rigid box resting on slab")
    right.plot(rigid["stack"]["iterations"], label="three rigid boxes stacked")
    right.set(xlabel="step", ylabel="iterations", yscale="log", title="contact iterations per step")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "contact_pairs.png", dpi=120)
    plt.close(fig)
    return {
        "iterations_median": float(np.median(iterations)),
        "iterations_max": int(iterations.max()),
        "broad_phase_share": rest["select_s"] / rest["step_s"],
        "rest_penetration_over_edge": rest["penetration_over_edge"],
        "rest_drift_m": rest["drift_last_half_m"],
        "slide_error_vs_expected": [s["error_vs_expected"] for s in slides],
        "slide_error_vs_plane": [s["error_vs_plane"] for s in slides],
        "equal_cones_converged": equal_cones["pairs_converged"],
        "stack_moved_max_m": max(stacks[0]["moved_max_m"]),
        "stack_shifted_moved_max_m": max(stacks[1]["moved_max_m"]),
        "rigid_rest_penetration_over_edge": rigid["rest"]["penetration_over_edge"],
        "rigid_rest_drift_m": rigid["rest"]["drift_last_half_m"],
        "rigid_stack_moved_max_m": rigid["stack"]["moved_max_m"],
        "rigid_drop_converged": rigid["drop"]["converged"],
        "rest": rest, "slide": slides, "slide_equal_cones": equal_cones, "stack": stacks, "rigid": rigid,
    }

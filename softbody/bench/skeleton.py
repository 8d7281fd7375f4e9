"""Cost of rigid bones in reduced coordinates against the same soft body without them.

The scene: the ``quadruped`` example robot (:func:`softbody.meshing.quadruped`, default
size: 2211 vertices, 8906 tets), its feet clamped to the ground, under gravity,
E = 1e5 Pa, nu = 0.3, density 1e3 kg/m^3, dt = 0.01 s, relative tolerance 1e-4. Its
bones are cut into 21 rigid segments (351 bone vertices in all): the spine into 9
along x, each leg bone into 3 along z. The middle spine segment is the root (a
:class:`~softbody.skeleton.Free` joint); the spine segments hang from it outwards, each
leg's top segment from the spine segment above it, and each leg segment from the one
above. With ``k`` joints the first ``k`` of the 20 non-root links, in the order hips (4),
spine (8), knees (8), are hinged (:class:`~softbody.skeleton.Revolute` about y, at the
boundary between the two segments) and the others welded
(:class:`~softbody.skeleton.Fixed`): the bone set is the same for every ``k``, only the
joints change. The baseline is the same mesh with no skeleton and plain local-global PD
(:class:`~softbody.solvers.LocalGlobal`); the skeleton's reduced coordinates
(:class:`~softbody.skeleton.Reduced`) run L-BFGS (:class:`~softbody.solvers.LBFGS`) with the
reduced PD solve, on the same prefactored matrix, as its initial inverse Hessian.

Reported per configuration: seconds per iteration and per step (medians over repeated
rollouts, compile excluded), iterations per step, and the time per iteration relative to
the baseline; ``overhead_20_joints`` is that ratio for 20 joints. The configurations are
timed in rounds (each round runs every configuration once), so that all of them see the
same machine load; the ratio of each round is taken before the median. The skeleton's
time includes its condensation (:func:`~softbody.skeleton.schur_factor`, once per
rollout), amortised over the rollout's iterations.
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

JOINTS = (0, 1, 5, 20)
SPINE_SEGMENTS, LEG_SEGMENTS = 9, 3


def _segments(mesh, region, axis: int, n: int) -> list:
    """Cut a bone region into ``n`` slabs of equal extent along ``axis``: ``[(Region, lower bound)]``."""
    from softbody.meshing import Region

    c = mesh.points[region.vertices, axis]
    edges = np.linspace(c.min(), c.max(), n + 1)
    slab = np.clip(np.searchsorted(edges, c, side="right") - 1, 0, n - 1)
    out = []
    for i in range(n):
        inside = np.zeros(mesh.n_vertices, bool)
        inside[region.vertices[slab == i]] = True
        tets = region.tets[inside[mesh.tets[region.tets]].all(axis=1)]
        out.append((Region(np.flatnonzero(inside), tets), edges[i]))
    return out


def skeleton(mesh, n_joints: int):
    """``(mesh with the bone segments as regions, Skeleton)`` with ``n_joints`` hinges (0-20)."""
    from softbody.meshing.examples import LEGS
    from softbody.skeleton import Fixed, Free, Link, Revolute, Skeleton

    if not 0 <= n_joints <= 20:
        raise ValueError(f"the quadruped's skeleton has 0 to 20 joints, got {n_joints}")
    regions, spine = {}, _segments(mesh, mesh.regions["bone:spine"], 0, SPINE_SEGMENTS)
    z_spine = float(mesh.points[mesh.regions["bone:spine"].vertices, 2].mean())
    y_axis = (0.0, 1.0, 0.0)
    root = SPINE_SEGMENTS // 2
    hips, backs, knees = [], [], []  # (name, bone, parent, origin)
    for i, (region, lower) in enumerate(spine):
        regions[f"bone:spine{i}"] = region
        if i < root:
            backs.append((f"spine{i}", f"bone:spine{i}", f"spine{i + 1}", (spine[i + 1][1], 0.0, z_spine)))
        elif i > root:
            backs.append((f"spine{i}", f"bone:spine{i}", f"spine{i - 1}", (lower, 0.0, z_spine)))
    centres = [float(mesh.points[r.vertices, 0].mean()) for r, _ in spine]
    for leg in LEGS:
        bone = mesh.regions[f"bone:leg_{leg}"]
        xy = mesh.points[bone.vertices, :2].mean(axis=0)
        parts = _segments(mesh, bone, 2, LEG_SEGMENTS)
        above = f"spine{int(np.argmin(np.abs(np.asarray(centres) - xy[0])))}"
        for j in reversed(range(LEG_SEGMENTS)):  # top segment first
            name = f"{leg}{j}"
            regions[f"bone:{name}"] = parts[j][0]
            if j == LEG_SEGMENTS - 1:
                hips.append((name, f"bone:{name}", above, (xy[0], xy[1], z_spine)))
            else:
                knees.append((name, f"bone:{name}", f"{leg}{j + 1}", (xy[0], xy[1], parts[j + 1][1])))
    links = [Link(f"spine{root}", f"bone:spine{root}", None, Free())]
    for k, (name, bone, parent, origin) in enumerate(hips + backs + knees):
        joint = Revolute(y_axis, origin) if k < n_joints else Fixed()
        links.append(Link(name, bone, parent, joint))
    return mesh.with_regions(**regions), Skeleton(links)


def scene(n_joints: int | None, mesh=None):
    """``(model, params, state0)`` of the quadruped with ``n_joints`` joints (``None``: no skeleton)."""
    from softbody.material import Material
    from softbody.meshing import quadruped
    from softbody.model import Options, build, initial_state
    from softbody.scene import SoftBody
    from softbody.solvers import LBFGS, LocalGlobal

    mesh = quadruped() if mesh is None else mesh
    skel, solver = None, LocalGlobal()
    if n_joints is not None:
        mesh, skel = skeleton(mesh, n_joints)
        solver = LBFGS()
    model, params = build(SoftBody(mesh, Material(E=1e5, nu=0.3, density=1e3), fixed="feet"),
                          skeleton=skel, options=Options(dt=0.01, max_iter=500, solver=solver))
    return model, params, initial_state(model, params)


def _timed(model, params, state0, n_steps: int):
    from softbody.simulate import rollout

    t0 = time.perf_counter()
    traj = rollout(model, params, state0, n_steps=n_steps, throw=False)  # the row reports convergence
    jax.block_until_ready(traj.x)
    return time.perf_counter() - t0, traj


def run(out: Path, quick: bool) -> dict:
    from softbody import progress
    from softbody.meshing import quadruped

    n_steps, rounds = (5, 2) if quick else (20, 5)
    with progress.task("skeleton: meshing the quadruped and building the scenes"):
        mesh = quadruped()
        configs = [None, *JOINTS]
        scenes = {k: scene(k, mesh) for k in configs}
    rows = {}
    for k, (model, params, state0) in progress.track(scenes.items(), "skeleton: first run (compiles) per joint count",
                                                     total=len(scenes), note=lambda item: f"{item[0]} joints"):
        first, traj = _timed(model, params, state0, n_steps)
        iterations = int(np.sum(traj.info.iterations))
        rows[k] = {"joints": k, "n_vertices": model.n_vertices, "n_tets": model.n_tets,
                   "bone_vertices": 0 if k is None else len(model.rig.bone),
                   "iterations_per_step": iterations / n_steps,
                   "converged": bool(np.all(traj.info.converged)), "first_run_s": first, "_times": []}
    for _ in progress.track(range(rounds), "skeleton: timed rounds", note=lambda r: f"round {r + 1}"):
        for k, (model, params, state0) in scenes.items():
            rows[k]["_times"].append(_timed(model, params, state0, n_steps)[0])
    base = np.asarray(rows[None]["_times"]) / (rows[None]["iterations_per_step"] * n_steps)
    for row in rows.values():
        times = np.asarray(row.pop("_times"))
        per_iteration = times / (row["iterations_per_step"] * n_steps)
        row.update(seconds_per_step=float(np.median(times)) / n_steps,
                   seconds_per_iteration=float(np.median(per_iteration)),
                   relative_time_per_iteration=float(np.median(per_iteration / base)))
    baseline, rows = rows[None], [rows[k] for k in JOINTS]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    labels = ["none"] + [str(k) for k in JOINTS]
    a.bar(labels, [1.0] + [r["relative_time_per_iteration"] for r in rows], color=["grey"] + ["C0"] * len(rows))
    a.axhline(1.3, color="k", ls="--", lw=0.8, label="1.3")
    a.set_xlabel("joints")
    a.set_ylabel("time per iteration / no skeleton")
    a.set_title("skeleton overhead per iteration (median of rounds)")
    a.legend()
    b.bar(labels, [baseline["iterations_per_step"]] + [r["iterations_per_step"] for r in rows],
          color=["grey"] + ["C1"] * len(rows))
    b.set_xlabel("joints")
    b.set_ylabel("iterations per step")
    b.set_title(f"quadruped, {baseline['n_vertices']} vertices, {rows[0]['bone_vertices']} on bones, dt = 0.01 s")
    fig.tight_layout()
    fig.savefig(Path(out) / "skeleton.png", dpi=120)
    plt.close(fig)
    overhead = next(r for r in rows if r["joints"] == 20)["relative_time_per_iteration"]
    return {"n_steps": n_steps, "rounds": rounds, "baseline": baseline, "skeleton": rows,
            "overhead_20_joints": overhead}

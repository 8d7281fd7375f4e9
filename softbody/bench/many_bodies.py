"""Many bodies dropped onto the ground and onto each other: cost per step against their number.

Scene: ``N`` soft 2 cm cubes (one hexahedron of 6 tets each, 8 vertices; E = 1e5 Pa,
nu = 0.3, density 1e3 kg/m^3) in two layers of ``N / 2`` columns on a square grid (one cube
for ``N = 1``), each upper cube offset by (0.3, 0.2) of an edge from the one below it so
that no corners line up, 5 mm apart and above a :class:`~softbody.contact.obstacles.Plane`
(mu_s = 0.5, mu_k = 0.4). They fall together: the lower layer lands on the ground in the
third step, the upper one on the lower layer about four steps later. One
:class:`~softbody.contact.pairs.Touch` over all the cubes (one broad phase over every
surface, contact thickness 1 mm, the same friction, edge-edge rows: without them the
offset cubes' crossed edges pass through each other, which the steps report as
``RESULTS.tunnelled``) keeps each out of the others;
dt = 0.01 s, relative tolerance 1e-6, 30 steps (0.3 s: both impacts and the start of
rest).

*Soft and rigid* (``mixed_cases``, N = 4 and 16; the quick variant N = 4): the same scene
with every other cube a :class:`~softbody.rigid.RigidBody` (density 500 kg/m^3, the same
12 triangles), rigid where the numbers of its column and layer add up odd: soft on rigid
in one column, rigid on soft in the next. The rigid bodies' small solves in each of an
iteration's 30 sweeps of the pair rows go body by body (one 6 x 6 block each,
:attr:`~softbody.skeleton.rig.Rig.tree_dofs`), so an iteration's cost grows linearly with
their number: 0.61 and 2.66 ms of CPU an iteration at N = 4 and 16 (first 5 steps; with
one dense matrix over all their degrees of freedom, before: 0.56 and 4.54 ms, and 1.27 at
N = 8). A step costs about 30 times a soft one's, mostly in iterations: at N = 4, 364 ms
of CPU against 12 ms (440 iterations a step, median, against 70). At N = 16 (eight separate
stacks of two under one Touch) the contact iteration mixed every stack with one set of
Anderson coefficients until 2026-12-07, and every step from the upper layer's landing
(step 5) on stopped at the cap: 5 of 30 steps succeeded (359 s of CPU for the 30 steps).
Each step now mixes only the bodies its rows join
(:func:`softbody.contact.solver._touching_groups`): 28 of 30 succeed (steps 5 and 15 stop
at the cap), median 578 iterations a step, 145 s of CPU (30 steps, one core); at N = 64,
21 of 30 (step 4 overflows the Touch's default capacity, 7 steps stop at the cap; before,
4 of 30: the same overflow, then every step at the cap), 702 s of CPU (1268 s before). The soft
N = 16 pile converges in every step (46-414 iterations). A soft cube resting on a rigid one
is the slow pair: 223-1061 iterations a step once it has landed (steps 4-11), against 49-186
for a rigid cube on a soft one, 68-188 for two soft ones and 12-133 for two rigid ones (two
cubes alone, the same settings), until the rigid bodies' vertices were swept no lighter than
1% of the soft ones' median (:attr:`softbody.contact.Contact.rigid_floor`, 2026-12-07): then
51-68. The N = 16 mixed pile then still succeeds in 28 of 30 steps (steps 2 and 18 at the
cap), median 360 iterations a step, 144 s of CPU. Mixed piles are not run past 16.

Reported per ``N`` (``cases``): time per step (median of the steps' mean over 3 timed
rollouts after a compiling one; compile time apart), as wall time (``step_s``) and as the
process's CPU time (``step_cpu_s``: on a machine shared with other jobs the wall time
also counts their share; run it pinned to one core, ``taskset -c 0``), iterations per step (median, max),
whether every step succeeded (``RESULTS.success``: converged, and no surface passed through
another), the deepest penetration of a pair row below the contact
thickness and of a vertex below the ground over all steps (m), the time of choosing a
step's rows (:meth:`~softbody.contact.pairs.Touch.select`, median of 20, at the last step)
over the time of a step (``broad_phase_share``), and the memory of one compiled step (the
argument, output and temporary bytes XLA reports for ``softbody.simulate.step``).

``time_exponent`` is the slope of log(CPU time per step) against log(N) fitted over the
soft cases with pair rows (``N >= 4``; ``time_exponent_wall`` the same of the wall time); 1
is linear. ``time_exponent_mixed`` is the same slope over the soft-and-rigid cases (``None``
with one case, as in the quick variant). ``all_converged`` and ``max_penetration_m`` are
over every case, soft and mixed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

EDGE, GAP, THICKNESS, DT, STEPS = 0.02, 0.005, 1e-3, 0.01, 30
#: the numbers of cubes (the quick variant stops at 16), and of soft and rigid cubes (quick: 4)
COUNTS, MIXED_COUNTS = (1, 4, 16, 64, 256), (4, 16)


def scene(n: int, cells: int = 1, rigid: bool = False):
    """``N`` cubes in two offset layers above a plane, one :class:`Touch` over all of them.

    Arguments:
        n: the number of cubes (>= 1).
        cells: hexahedra per soft cube's edge.
        rigid: every other cube rigid (see the module docstring; default all soft).

    Returns:
        ``(model, params)`` from :func:`softbody.model.build`.
    """
    from softbody.contact.obstacles import Plane
    from softbody.contact.pairs import Touch
    from softbody.material import Material
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build
    from softbody.rigid import RigidBody
    from softbody.scene import SoftBody

    columns = max(1, n // 2)
    side = int(np.ceil(np.sqrt(columns)))
    material = Material(E=1e5, nu=0.3, density=1000.0)
    pitch = EDGE + 0.015
    bodies = []
    for i in range(n):
        column, level = i % columns, i // columns
        origin = ((column % side) * pitch + level * 0.3 * EDGE, (column // side) * pitch + level * 0.2 * EDGE,
                  GAP + level * (EDGE + 2 * GAP))
        if rigid and (column + level) % 2:
            bodies.append(RigidBody(grid_box((EDGE,) * 3, (1,) * 3, origin=origin), density=500.0, name=f"cube{i}"))
        else:
            bodies.append(SoftBody(grid_box((EDGE,) * 3, (cells,) * 3, origin=origin), material, name=f"cube{i}"))
    rows = ([Touch(*[b.name for b in bodies], mu_s=0.5, mu_k=0.4, thickness=THICKNESS, edges=True)]
            if n > 1 else [])
    return build(bodies, obstacles=[Plane(mu_s=0.5, mu_k=0.4)], rows=rows,
                 options=Options(dt=DT, tol=1e-6, max_iter=3000))


def _case(n: int, rigid: bool = False) -> dict:
    import jax
    import jax.numpy as jnp

    from softbody._types import RESULTS
    from softbody.bench import median_seconds
    from softbody.model import initial_state, prepare
    from softbody.simulate import rollout, step

    model, params = scene(n, rigid=rigid)
    state = initial_state(model, params)
    start = time.perf_counter()
    traj = rollout(model, params, state, n_steps=STEPS, throw=False)
    jax.block_until_ready(traj.x)
    first = time.perf_counter() - start
    times, cpu = [], []
    for _ in range(3):
        start, start_cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(rollout(model, params, state, n_steps=STEPS, throw=False).x)
        times.append((time.perf_counter() - start) / STEPS)
        cpu.append((time.process_time() - start_cpu) / STEPS)
    step_s = float(np.median(times))
    memory = jax.jit(lambda p, s: step(model, prepare(model, p), s)).lower(params, state).compile().memory_analysis()
    step_bytes = None if memory is None else int(memory.argument_size_in_bytes + memory.output_size_in_bytes
                                                 + memory.temp_size_in_bytes)
    info = traj.info
    iterations = np.asarray(info.iterations)
    x = np.asarray(traj.x)
    out = {"n": n, "vertices": model.n_vertices, "compile_and_first_s": first - step_s * STEPS,
           "step_s": step_s, "step_cpu_s": float(np.median(cpu)), "iterations_median": float(np.median(iterations)),
           "iterations_max": int(iterations.max()), "iterations": iterations.tolist(),
           "converged": bool(np.all(np.asarray(info.result) == int(RESULTS.success))),
           "ground_penetration_m": float(max(0.0, -x[:, :, 2].min())), "step_bytes": step_bytes,
           "row_penetration_m": 0.0, "select_s": None, "broad_phase_share": None}
    if model.rows:
        generator, p = model.rows[0], params.rows[0]
        select = jax.jit(lambda x0, x1: generator.select(x0, x1, p))
        frame = jax.jit(lambda x0, x1: generator.frame(x1, generator.select(x0, x1, p), p).phi)
        out["row_penetration_m"] = float(max(0.0, -min(float(jnp.min(frame(traj.x[k - 1], traj.x[k])))
                                                       for k in range(1, STEPS + 1))))
        out["select_s"] = median_seconds(select, traj.x[-2], traj.x[-1], repeats=20)
        out["broad_phase_share"] = out["select_s"] / step_s
    return out


def run(out: Path, quick: bool) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cases = []
    for n in COUNTS[:3] if quick else COUNTS:
        cases.append(_case(n))
        print(f"many-bodies: N = {n}: {cases[-1]['step_s'] * 1e3:.1f} ms a step, "
              f"{cases[-1]['iterations_median']:.0f} iterations (median)", flush=True)
    mixed = []
    for n in MIXED_COUNTS[:1] if quick else MIXED_COUNTS:
        mixed.append(_case(n, rigid=True))
        print(f"many-bodies: N = {n} soft and rigid: {mixed[-1]['step_s'] * 1e3:.1f} ms a step, "
              f"{mixed[-1]['iterations_median']:.0f} iterations (median)", flush=True)
    paired = [c for c in cases if c["n"] >= 4]

    def slope(key, group=paired):
        group = [c for c in group if c["n"] >= 4]
        if len(group) < 2:
            return None
        return float(np.polyfit(np.log([c["n"] for c in group]), np.log([c[key] for c in group]), 1)[0])

    exponent = slope("step_cpu_s")

    ns = [c["n"] for c in cases]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.loglog(ns, [c["step_cpu_s"] * 1e3 for c in cases], "o-", label="CPU time per step")
    if paired:
        ref = paired[0]
        left.loglog([c["n"] for c in paired], [ref["step_cpu_s"] * 1e3 * c["n"] / ref["n"] for c in paired], "k--",
                    lw=0.8, label="linear in N")
    left.loglog([c["n"] for c in mixed], [c["step_cpu_s"] * 1e3 for c in mixed], "^-", label="soft and rigid")
    left.set(xlabel="cubes N", ylabel="ms per step", title=f"time per step (slope {exponent or 0:.2f}, N >= 4)")
    left.legend(fontsize=8)
    right.semilogx(ns, [c["iterations_median"] for c in cases], "o-", label="median")
    right.semilogx(ns, [c["iterations_max"] for c in cases], "s--", label="max")
    right.semilogx([c["n"] for c in mixed], [c["iterations_median"] for c in mixed], "^-", label="soft and rigid, median")
    right.set(xlabel="cubes N", ylabel="contact iterations per step", title="iterations")
    right.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "many_bodies.png", dpi=120)
    plt.close(fig)
    return {
        "time_exponent": exponent,
        "time_exponent_wall": slope("step_s"),
        "time_exponent_mixed": slope("step_cpu_s", mixed),
        "all_converged": all(c["converged"] for c in cases + mixed),
        "max_penetration_m": max(max(c["row_penetration_m"], c["ground_penetration_m"]) for c in cases + mixed),
        "thickness_m": THICKNESS,
        "cases": cases,
        "mixed_cases": mixed,
    }

"""Benchmark ``friction-stability``: where the contact splittings converge and where they fail.

For each mesh (a structured grid box and the example robots of
:mod:`softbody.meshing.examples`, each resting on a rough ground plane), Young's modulus
``E`` from 1e4 Pa (soft) to 1e7 Pa (stiff) (``nu`` = 0.45, density 1000 kg/m^3) and time
step ``dt`` from 1/1000 s to 1/30 s, and for each splitting ``D`` of
:mod:`softbody.contact.splitting` (:class:`~softbody.contact.splitting.Naive`, :class:`~softbody.contact.splitting.Diagonal`
and the default :class:`~softbody.contact.splitting.ScaledDiagonal`), it measures

- the spectral radius of the splitting's iteration matrix ``(M/h^2 + D)^{-1} (D - L)``
  with the projections held fixed (:func:`~softbody.contact.splitting.splitting_spectral_radius`;
  for the default also the proved bound and ``1 - rho``), and, for reference, that of the
  absolute-row-sum splitting ``D = diag(sum_j |L_ij|)``, which needs the matrix entries
  that an iteration method does not see;
- the full iteration on the first step of the resting body (local steps, contact and
  friction): the plain splitting iteration (``history=0``, the design's iteration) run for
  a fixed number of iterations from the step's initial guess perturbed by random
  displacements of 1e-4 of the body's size (so that an unstable mode does not hide for
  hundreds of iterations below round-off), classified ``converged`` (force residual below
  ``1e-6 |M s / h^2|``), ``diverged`` (non-finite, or the residual at the end above 10x
  its start) or ``slow`` (neither), with its empirical contraction factor per iteration;
  and the accelerated iteration as :class:`~softbody.contact.Contact` runs it
  (Anderson mixing, its default history) from the unperturbed guess: iterations to the
  same tolerance, or not converged within the cap.

And :class:`~softbody.contact.Contact` with its active-set iteration on the prefactored
matrix (``Contact(active_set=ActiveSet())``, :mod:`softbody.contact.active_set`) on the same
first steps: iterations per step (the splitting's check included), whether it converged
and whether it fell back to the splitting, and its wall time per step against the
default splitting iteration's, timed in pairs (median of ``REPEATS`` runs each, one after
the other, same process).

Writes ``out/friction-stability.png``: one panel per splitting, stiffness against time
step, each cell coloured by the plain iteration's worst outcome over the meshes and
labelled with the largest spectral radius and the number of meshes on which the
accelerated iteration converged. Returns ``max_spectral_radius`` per splitting
(over meshes, stiffnesses and time steps), the same for the plain and accelerated
iterations' outcomes, and the per-case table.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody.contact.active_set import ActiveSet
from softbody.contact import Contact
from softbody.material import Material
from softbody.meshing import TetMesh, examples
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.objective import contact_rows, solve_step, step_objective
from softbody.contact.obstacles import Plane
from softbody.solvers import LocalGlobal, StepProblem
from softbody.contact.splitting import Diagonal, Naive, ScaledDiagonal, _pd_split, _spectral_radius

#: name -> splitting, in the order of the figure's panels
SPLITTINGS = {"naive": Naive(), "diagonal": Diagonal(), "default": ScaledDiagonal()}
YOUNG = (1e4, 1e5, 1e6, 1e7)
STEPS = (1 / 1000, 1 / 300, 1 / 100, 1 / 30)
#: relative force tolerance that counts as converged
TOL = 1e-6
#: timed runs of each step (the median is kept)
REPEATS = 3
#: random displacement added to the plain iteration's initial guess, relative to the body's
#: size, so that every eigenmode is present from the start (as in a running simulation)
PERTURBATION = 1e-4


def _meshes(quick: bool) -> dict[str, TetMesh]:
    grid = grid_box((0.1, 0.1, 0.1), (4, 4, 4))
    if quick:
        return {"grid box 4^3": grid, "cube": examples.cube(size=0.0125)}
    return {
        "grid box 4^3": grid,
        "cube": examples.cube(size=0.0125),
        "ball": examples.ball(size=0.015),
        "finger": examples.finger(size=0.005),
        "caterpillar": examples.caterpillar(size=0.008),
        "quadruped": examples.quadruped(size=0.015),
    }


def _on_ground(mesh: TetMesh) -> TetMesh:
    """The mesh translated so that its lowest point touches z = 0."""
    points = mesh.points - np.array([0.0, 0.0, mesh.points[:, 2].min()])
    return TetMesh(points, mesh.tets, mesh.surface, mesh.regions, mesh.fields)


def _iterations(model, n_plain: int):
    """A jitted ``(params, perturbation (n, 3)) -> (plain residuals (n_plain,), |M s / h^2|,
    accelerated StepInfo)``; the plain iteration starts from ``x_n + h v_n + perturbation``."""
    contact = model.step.contact

    def run(params, perturbation):
        prep = prepare(model, params)
        state = initial_state(model, params)
        zero = jnp.zeros(model.n_channels)
        evaluate, scale = step_objective(
            model, prep, state.x, state.v, state.rot, zero, None
        )
        free = jnp.asarray(model.free_mask)
        problem = StepProblem(
            evaluate=evaluate,
            precondition=None,
            diagonal=prep.data[jnp.asarray(model.diag_to_data)][:, None],
            x_n=state.x,
            v_n=state.v,
            mass=prep.mass,
            free=free,
            dt=model.options.dt,
            time=state.t,
            rows=contact_rows(model, prep),
        )
        plain = Contact(splitting=contact.splitting, history=0)
        iteration = plain.map(problem, model.step.coordinates)
        x0 = iteration.lift(state.x + model.options.dt * state.v + perturbation * free)

        def body(c, _):
            x, q = c
            x, q, r = iteration.apply(x, q)
            return (x, q), r

        _, residuals = jax.lax.scan(body, (x0, state.rot), None, length=n_plain)
        _, info = solve_step(model, prep, state, zero, None)
        return residuals, scale, info

    return jax.jit(run)


def _timed_step(model):
    """A jitted ``params -> StepInfo`` of the first step from rest, and its timer
    ``(params) -> (info, median seconds over REPEATS runs)``."""
    step = jax.jit(lambda params: solve_step(model, prepare(model, params), initial_state(model, params),
                                             jnp.zeros(model.n_channels), None)[1])

    def timed(params):
        info = jax.block_until_ready(step(params))  # compiles on the first call
        seconds = []
        for _ in range(REPEATS):
            start = time.perf_counter()
            jax.block_until_ready(step(params))
            seconds.append(time.perf_counter() - start)
        return info, float(np.median(seconds))

    return timed


def _classify(residuals: np.ndarray, tol: float) -> tuple[str, float, int | None]:
    """``(status, contraction factor per iteration, iterations to tol or None)``.

    The factor is the geometric mean of the residual's ratio per iteration: up to
    convergence when it converged, else over the second half of the run.
    """
    below = np.flatnonzero(residuals <= tol)
    if below.size:
        k = int(below[0])
        rate = float((residuals[k] / residuals[0]) ** (1.0 / k)) if k > 0 else 0.0
        return "converged", rate, k + 1
    tail = residuals[len(residuals) // 2 :]
    if not np.isfinite(residuals).all() or residuals[-1] > 10 * residuals[0]:
        return (
            "diverged",
            float("inf")
            if not np.isfinite(tail).all()
            else float((tail[-1] / tail[0]) ** (1.0 / (len(tail) - 1))),
            None,
        )
    return "slow", float((tail[-1] / tail[0]) ** (1.0 / (len(tail) - 1))), None


def run(out: Path, quick: bool) -> dict:
    """Measure every splitting on every mesh, stiffness and time step; writes the figure.

    Arguments:
        out: output directory (exists).
        quick: two meshes (grid box, gmsh cube), ``E`` in {1e4, 1e7}, ``dt`` in
            {1/1000, 1/30}, 300 plain iterations (else 1000).

    Returns:
        ``{"iterations_median", "iterations_max"`` (the active-set iteration's iterations
        per step over all cases), ``"wall_ratio_vs_splitting": {"per_mesh": {mesh: ratio},
        "all": ratio}`` (the default splitting iteration's wall time over the active-set
        iteration's, summed over the cases), ``"active_set": {"converged", "fallback", "total",
        "splitting_iterations_median", "splitting_iterations_max", "cases"}``,
        ``"max_spectral_radius": {splitting: max rho}, "min_gap_default": min(1 - rho),
        "max_abs_row_sum_radius", "plain": {splitting: {status: count}},
        "accelerated": {splitting: {"converged": count, "total": count}},
        "design_claims": ..., "cases": [per-case dicts], "seconds"}``.
    """
    start = time.perf_counter()
    meshes = _meshes(quick)
    youngs = (YOUNG[0], YOUNG[-1]) if quick else YOUNG
    steps = (STEPS[0], STEPS[-1]) if quick else STEPS
    n_plain = 300 if quick else 1000
    from softbody import progress

    cases, active = [], []
    blocks = len(meshes) * len(steps)
    for mesh_name, mesh in meshes.items():
        mesh = _on_ground(mesh)
        extent = float(np.ptp(mesh.points, axis=0).max())
        perturbation = (
            PERTURBATION * extent * np.random.default_rng(0).standard_normal(mesh.points.shape)
        )
        for dt in steps:
            progress.say(f"friction-stability: case {len(cases) // (len(youngs) * len(SPLITTINGS)) + 1}/{blocks}: "
                         f"{mesh_name} ({mesh.n_vertices} vertices), dt = {dt:.4g} s, E in {list(youngs)}, "
                         f"{len(SPLITTINGS)} splittings ({time.perf_counter() - start:.0f} s so far)")
            options = Options(dt=dt, tol=TOL, max_iter=2000, solver=LocalGlobal())
            scene = dict(options=options, obstacles=[Plane(mu_s=0.5, mu_k=0.4)])
            body = SoftBody(mesh, Material(E=youngs[0], nu=0.45))
            splitting_only, base = build(body, **scene)
            fast, _ = build(body, **{**scene, "options": dataclasses.replace(
                options, contact=Contact(active_set=ActiveSet()))})
            timers = (_timed_step(fast), _timed_step(splitting_only))
            for young in youngs:
                params = eqx.tree_at(lambda p: p.E, base, jnp.full_like(base.E, young))
                (info, seconds), (info_split, seconds_split) = (timer(params) for timer in timers)
                active.append({
                    "mesh": mesh_name, "n_vertices": mesh.n_vertices, "E": young, "dt": dt,
                    "iterations": int(info.iterations), "converged": bool(info.converged),
                    "fallback": bool(info.fallback), "seconds": seconds,
                    "splitting_iterations": int(info_split.iterations), "splitting_seconds": seconds_split,
                })
            for split_name, splitting in SPLITTINGS.items():
                options = Options(dt=dt, tol=TOL, max_iter=2000, solver=LocalGlobal(),
                                  contact=Contact(splitting=splitting))
                model, params = build(SoftBody(mesh, Material(E=youngs[0], nu=0.45)),
                                      options=options, obstacles=[Plane(mu_s=0.5, mu_k=0.4)])
                iterate = _iterations(model, n_plain)
                for young in youngs:
                    params = eqx.tree_at(lambda p: p.E, params, jnp.full_like(params.E, young))
                    mass, stiffness, h = _pd_split(model, prepare(model, params))
                    d_l = stiffness.diagonal()
                    d = np.asarray(splitting.diagonal(jnp.asarray(d_l)[:, None]))[:, 0]
                    case = {
                        "mesh": mesh_name,
                        "n_vertices": mesh.n_vertices,
                        "E": young,
                        "dt": dt,
                        "splitting": split_name,
                        "spectral_radius": _spectral_radius(mass, stiffness, h, d),
                    }
                    if split_name == "default":
                        case["bound"] = ScaledDiagonal.bound(mass, d_l, h)
                        case["gap"] = 1.0 - case["spectral_radius"]
                        abs_rows = np.asarray(abs(stiffness).sum(axis=1)).ravel()
                        case["abs_row_sum_radius"] = _spectral_radius(mass, stiffness, h, abs_rows)
                    residuals, scale, info = iterate(params, perturbation)
                    residuals = np.asarray(residuals) / float(scale)  # relative force residuals
                    status, rate, needed = _classify(residuals, TOL)
                    case["plain"] = {
                        "status": status,
                        "rate": rate,
                        "iterations": needed,
                        "final_residual": float(residuals[-1]),
                    }
                    case["accelerated"] = {
                        "converged": bool(info.converged),
                        "iterations": int(info.iterations),
                        "residual": float(info.residual),
                    }
                    cases.append(case)
    _plot(out / "friction-stability.png", cases, active, youngs, steps)
    summary = {name: {} for name in SPLITTINGS}
    accelerated = {name: {"converged": 0, "total": 0} for name in SPLITTINGS}
    for c in cases:
        counts = summary[c["splitting"]]
        counts[c["plain"]["status"]] = counts.get(c["plain"]["status"], 0) + 1
        accelerated[c["splitting"]]["converged"] += c["accelerated"]["converged"]
        accelerated[c["splitting"]]["total"] += 1
    defaults = [c for c in cases if c["splitting"] == "default"]
    iterations = [c["iterations"] for c in active]
    ratio = {name: sum(c["splitting_seconds"] for c in active if c["mesh"] == name)
             / sum(c["seconds"] for c in active if c["mesh"] == name) for name in meshes}
    return {
        "iterations_median": float(np.median(iterations)),
        "iterations_max": int(max(iterations)),
        "wall_ratio_vs_splitting": {
            "per_mesh": ratio,
            "all": sum(c["splitting_seconds"] for c in active) / sum(c["seconds"] for c in active),
        },
        "active_set": {
            "converged": sum(c["converged"] for c in active),
            "fallback": sum(c["fallback"] for c in active),
            "total": len(active),
            "splitting_iterations_median": float(np.median([c["splitting_iterations"] for c in active])),
            "splitting_iterations_max": int(max(c["splitting_iterations"] for c in active)),
            "cases": active,
        },
        "max_spectral_radius": {
            name: max(c["spectral_radius"] for c in cases if c["splitting"] == name)
            for name in SPLITTINGS
        },
        "min_gap_default": min(c["gap"] for c in defaults),
        "max_abs_row_sum_radius": max(c["abs_row_sum_radius"] for c in defaults),
        "plain": summary,
        "accelerated": accelerated,
        "design_claims": {"diagonal": [1.19, 1.68], "naive": [180.0, 1.3e5]},
        "meshes": {name: m.n_vertices for name, m in meshes.items()},
        "cases": cases,
        "seconds": time.perf_counter() - start,
    }


_COLOURS = {"converged": "#4caf50", "slow": "#ffc107", "diverged": "#e53935"}
_RANK = {"converged": 0, "slow": 1, "diverged": 2}


def _plot(path: Path, cases, active, youngs, steps) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(1, len(SPLITTINGS) + 1, figsize=(4.2 * (len(SPLITTINGS) + 1), 3.8), sharey=True)
    image = np.ones((len(youngs), len(steps), 3))
    for i, young in enumerate(youngs):
        for j, dt in enumerate(steps):
            here = [c for c in active if c["E"] == young and c["dt"] == dt]
            worst = "converged" if all(c["converged"] and not c["fallback"] for c in here) else (
                "slow" if all(c["converged"] for c in here) else "diverged")
            image[i, j] = to_rgb(_COLOURS[worst])
            its = [c["iterations"] for c in here]
            split = [c["splitting_iterations"] for c in here]
            axes[-1].text(j, i, f"{int(np.median(its))} / {max(its)}\nsplitting {int(np.median(split))} / {max(split)}",
                          ha="center", va="center", fontsize=7)
    axes[-1].imshow(image, origin="lower", aspect="auto")
    axes[-1].set_xticks(range(len(steps)), [f"1/{round(1 / dt)}" for dt in steps])
    axes[-1].set(title="active set: iterations median / max", xlabel="time step (s)")
    for ax, name in zip(axes, SPLITTINGS):
        image = np.ones((len(youngs), len(steps), 3))
        for i, young in enumerate(youngs):
            for j, dt in enumerate(steps):
                here = [
                    c for c in cases if c["splitting"] == name and c["E"] == young and c["dt"] == dt
                ]
                worst = max((c["plain"]["status"] for c in here), key=_RANK.get)
                image[i, j] = to_rgb(_COLOURS[worst])
                rho = max(c["spectral_radius"] for c in here)
                label = f"{rho:.3g}" if rho < 0.999 or rho > 1 else f"1-{1 - rho:.0e}"
                accelerated = sum(c["accelerated"]["converged"] for c in here)
                label += f"\nAnderson {accelerated}/{len(here)}"
                ax.text(j, i, label, ha="center", va="center", fontsize=7)
        ax.imshow(image, origin="lower", aspect="auto")
        ax.set_xticks(range(len(steps)), [f"1/{round(1 / dt)}" for dt in steps])
        ax.set_yticks(range(len(youngs)), [f"{y:.0e}" for y in youngs])
        ax.set(title=f"{name}: frozen rho, plain iteration (colour)", xlabel="time step (s)")
    axes[0].set_ylabel("Young's modulus (Pa)")
    fig.legend(
        handles=[Patch(color=c, label=s) for s, c in _COLOURS.items()], loc="lower center", ncol=3
    )
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)

"""System identification: Young's modulus and damping of a clamped cantilever from noisy markers.

A beam (0.32 x 0.08 x 0.08 m, E = 1 MPa, nu = 0.3, 1000 kg/m^3, mass damping 1/s) is
clamped at x = 0 and released under gravity; it swings down and rings at about 4 Hz. The
"camera" sees the 27 vertices of its top face for 0.3 s (30 frames of 10 ms) with
Gaussian noise of 1 % of the peak marker displacement. Starting from E = 2 MPa and a
damping three times too high, Levenberg-Marquardt (implicit forward-mode Jacobians
through the simulation, :class:`~softbody.gradients.ImplicitForward`; log variables)
estimates E and the damping together; CMA-ES minimises the same misfit in the same
variables, and we count the simulations it needs to reach (a) the same error in E as
Levenberg-Marquardt and (b) the same misfit: a cost within 1/2 of
Levenberg-Marquardt's minimum, i.e. inside the estimate's one-standard-deviation
likelihood region (the residuals are scaled by the noise, so ``C`` is half a chi-square).
A point can cross the first threshold by chance while the damping is still off; the
second says the whole estimate is as good.

Run::

    python examples/sysid_cantilever.py --out results/sysid

Writes ``metrics.json`` (``E_rel_error``, ``iterations``, ``cmaes_simulations_to_same_error``,
``cmaes_simulations_to_same_cost``, ``lm_wall_time_s`` (compilation included),
``cmaes_wall_time_s`` (until CMA-ES met both (a) and (b)), ...; a CMA-ES count is null when the budget ran out
first), ``convergence.png`` (E error and excess misfit against simulations for both
methods) and
``fit.png`` (the tip's vertical motion: observed, initial guess, fitted).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax.numpy as jnp
import numpy as np

from softbody import control as sc
from softbody import progress
from softbody.io import check_overwrite, write_metrics
from softbody.material import Material
from softbody.meshing.grid import grid_box
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import rollout

E_TRUE, ALPHA_TRUE = 1.0e6, 1.0
E_START, ALPHA_START = 2.0e6, 3.0
N_STEPS, NOISE = 30, 0.01


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--cmaes-budget", type=int, default=600, help="CMA-ES simulation budget")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    start = time.perf_counter()

    mesh = grid_box((0.32, 0.08, 0.08), (8, 2, 2))
    options = Options(dt=0.01, tol=1e-9, max_iter=3000)
    with progress.task("building the beam and synthesising the observation (compiles a rollout)"):
        model, truth = build(SoftBody(mesh, Material(E=E_TRUE, nu=0.3, density=1000.0, alpha=ALPHA_TRUE),
                                      fixed="fixed"), options=options)
        obs = sc.synthesize(model, truth, "zmax", N_STEPS, noise=NOISE, seed=0)
    print(f"{len(obs.markers)} markers, {N_STEPS} frames, noise {obs.noise * 1e3:.3f} mm "
          f"({NOISE:.0%} of the peak displacement)")

    # Levenberg-Marquardt on (log E, log alpha).
    estimate = ("E", "alpha")
    with progress.task("Levenberg-Marquardt fit (compiles the Jacobian first)"):
        res = sc.identify(model, truth, obs, estimate, init={"E": E_START, "alpha": ALPHA_START}, n_iter=20)
    e_hist = np.array([h["E"][0] for h in res.history])
    lm_err = np.abs(e_hist / E_TRUE - 1.0)
    e_err = float(lm_err[-1])
    below = np.flatnonzero(lm_err < 0.01)
    print(f"LM: E = {res.values['E'][0]:.6g} Pa (error {e_err:.2e}, +- {res.std['E'][0]:.1e} relative), "
          f"alpha = {res.values['alpha'][0]:.4g} 1/s, {res.iterations} iterations, {res.wall_time:.1f} s")

    # CMA-ES on the same misfit and variables, from the same start.
    problem = sc.SysIdProblem(model, truth, obs, estimate)
    z0 = jnp.log(jnp.asarray([E_START, ALPHA_START]))
    start_params = problem.unpack(z0)
    same = e_err * 1.01  # the misfit's minimiser limits both methods: reach it to 1 %
    lm_cost = float(res.cost[-1])
    same_cost = lm_cost + 0.5  # one standard deviation in likelihood

    def e_error(z):
        return abs(float(np.exp(z[0])) / E_TRUE - 1.0)

    cma_start = time.perf_counter()
    # throw=False: a failed simulation costs NaN, which CMA-ES ranks last; no host callback,
    # so the compiled cost is kept between runs (as the LM fit's Jacobian program is).
    with progress.task("CMA-ES on the same misfit (compiles the cost first)"):
        cma = sc.cmaes(lambda z: problem.cost(z, throw=False), z0, sigma0=0.5, budget=args.cmaes_budget, seed=1,
                       stop=lambda z, f: e_error(z) <= same and f <= same_cost)
    cma_time = time.perf_counter() - cma_start
    cma_err = np.abs(np.exp(cma.best_x_history[:, 0]) / E_TRUE - 1.0)
    reached = np.flatnonzero(cma_err <= same)
    cma_same = int(cma.simulations[reached[0]]) if reached.size else None
    cost_reached = np.flatnonzero(cma.best_loss_history <= same_cost)
    cma_same_cost = int(cma.simulations[cost_reached[0]]) if cost_reached.size else None
    cma_1pct = np.flatnonzero(cma_err < 0.01)
    print(f"CMA-ES: E error {cma_err[-1]:.2e}, cost {cma.best_loss:.6g} (LM {lm_cost:.6g}) after "
          f"{cma.n_simulations} simulations; reached the LM error in E after {cma_same} simulations, "
          f"the LM cost + 1/2 after {cma_same_cost}")

    # Figures.
    progress.say("drawing the figures (two more rollouts)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    lm_sims = np.arange(len(lm_err)) + 1
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax.semilogy(lm_sims, lm_err, "o-", label="Levenberg-Marquardt (forward-mode Jacobian)")
    ax.semilogy(cma.simulations, cma_err, ".-", label="CMA-ES (best so far)")
    ax.axhline(0.01, color="grey", ls=":", label="1 %")
    ax.set_xscale("log")
    ax.set_xlabel("simulations")
    ax.set_ylabel("relative error in E")
    ax.set_title("Cantilever system identification (1 % marker noise)")
    ax.legend()
    floor = 1e-3  # excess misfits below this are drawn at it (log axis)
    ax2.loglog(lm_sims, np.maximum(np.asarray(res.cost) - lm_cost, floor), "o-", label="Levenberg-Marquardt")
    ax2.loglog(cma.simulations, np.maximum(cma.best_loss_history - lm_cost, floor), ".-", label="CMA-ES")
    ax2.axhline(0.5, color="grey", ls=":", label="1/2 (one standard deviation)")
    ax2.set_xlabel("simulations")
    ax2.set_ylabel("cost - Levenberg-Marquardt's minimum")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(args.out / "convergence.png", dpi=120)

    tip = mesh.regions["tip"].vertices
    marker_tip = np.flatnonzero(np.isin(obs.markers, tip))
    t = np.arange(N_STEPS + 1) * options.dt
    state0 = initial_state(model, truth)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(t, obs.positions[:, marker_tip, 2].mean(axis=1) - obs.positions[0, marker_tip, 2].mean(), "k.",
            label="observed (top tip markers)")
    for label, p, style in (("initial guess", start_params, "--"), ("fitted", res.params, "-")):
        x = np.asarray(rollout(model, p, state0, n_steps=N_STEPS).x)
        ax.plot(t, x[:, obs.markers[marker_tip], 2].mean(axis=1) - x[0, obs.markers[marker_tip], 2].mean(),
                style, label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tip vertical displacement (m)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "fit.png", dpi=120)

    metrics = {
        "E_true": E_TRUE, "E_estimate": float(res.values["E"][0]), "E_rel_error": e_err,
        "E_rel_std": float(res.std["E"][0]), "alpha_rel_std": float(res.std["alpha"][0]),
        "alpha_true": ALPHA_TRUE, "alpha_estimate": float(res.values["alpha"][0]),
        "alpha_rel_error": abs(float(res.values["alpha"][0]) / ALPHA_TRUE - 1.0),
        "iterations": res.iterations, "iterations_to_1_percent": int(below[0]) if below.size else None,
        "simulations": res.simulations, "converged": res.converged,
        "simulations_to_same_error": int(np.flatnonzero(lm_err <= same)[0]) + 1,
        "rms_residual_m": res.rms_residual, "noise_std_m": obs.noise, "markers": len(obs.markers),
        "frames": N_STEPS, "lm_wall_time_s": res.wall_time,
        "cmaes_simulations_to_same_error": cma_same, "cmaes_same_error_target": same,
        "lm_cost": lm_cost, "cmaes_simulations_to_same_cost": cma_same_cost, "cmaes_best_cost": cma.best_loss,
        "simulations_to_1_percent": int(below[0]) + 1 if below.size else None,
        "cmaes_simulations_to_1_percent": int(cma.simulations[cma_1pct[0]]) if cma_1pct.size else None,
        "cmaes_budget": args.cmaes_budget, "cmaes_simulations": cma.n_simulations,
        "cmaes_final_E_rel_error": float(cma_err[-1]), "cmaes_wall_time_s": cma_time,
        "wall_time_s": time.perf_counter() - start,
    }
    write_metrics(args.out / "metrics.json", metrics, force=args.force)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

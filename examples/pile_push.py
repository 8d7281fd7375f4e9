"""Many objects: choose the push of a striker so that a pile of cubes ends where wanted.

A heavy soft striker cube (2 cm, 4000 kg/m^3) slides on the ground towards a 2 x 2 pile
of four soft cubes (2 cm, 1000 kg/m^3, E = 100 kPa, 3 mm apart), all one hexahedron of
6 tets (8 vertices) each; Coulomb friction on the ground and between the bodies
(mu = 0.3, one :class:`~softbody.contact.pairs.Touch` over all five bodies, contact
thickness 1 mm, edge-edge rows). The striker's initial motion has three variables:
its velocity ``(vx, vy)`` and its spin about the vertical, given as the speed of its
corners (``omega_z * edge / 2``), all in m/s. It hits the pile, which scatters and slides
to rest within the horizon (0.3 s, 30 steps of 10 ms, relative tolerance 2e-6).

Loss: the sum over the four pile cubes of the squared distance (mm^2) of each final
centre of mass to its target. The targets are the final centres of a hidden push
(``TRUE``), so the optimum is zero; both methods start from ``START`` and keep to the
same box of pushes (``LOWER``, ``UPPER``). Steps that do not succeed (the iteration cap,
surfaces passing through each other in the impact) are counted, not hidden: the loss's aux
output, ``gradient_failed_steps`` per evaluation, and the final push's per-step results.

Gradient method: L-BFGS-B (scipy) on ``jax.value_and_grad`` of the loss through the
whole rollout (the contact solver's implicit adjoint); one loss-and-gradient evaluation
is counted as one simulation, and its wall time (forward and backward) is reported
apart. CMA-ES (:func:`softbody.control.cmaes`): same loss, same variables and bounds,
one simulation per candidate, up to ten times the gradient method's simulations (or
until it reaches the threshold). The threshold is ``THRESHOLD`` mm^2 (0.5 mm RMS over
the four cubes). Before optimising, the gradient at ``START`` is checked against central
differences.

Run::

    python examples/pile_push.py --out results/pile_push

Writes ``metrics.json`` (``gradient_simulations`` and ``cmaes_simulations`` to the
threshold (null if not reached), their final losses and wall times, ``fd_rel_error``, the
cost of one simulation and one gradient, per-step convergence, ...), ``loss.png`` (best
loss against simulations for both methods) and ``pile_push.npz`` (the gradient method's
push; ``softbody view`` opens it, "colour by" ``contact_force`` or ``contact_state`` shows the contact).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax
import jax.numpy as jnp
import numpy as np
from softbody.meshing.grid import grid_box

import softbody  # noqa: F401  (float64)
from softbody import control as sc
from softbody import progress
from softbody.contact.obstacles import Plane
from softbody.contact.pairs import Touch
from softbody.io import Result, check_overwrite, write_metrics
from softbody.material import Material
from softbody.model import Options, build, initial_state
from softbody.scene import SoftBody
from softbody.simulate import contact_fields, rollout

EDGE, GAP, RUN_UP = 0.02, 0.003, 0.01  # cube edge, gap in the pile, striker to pile (m)
MU, THICKNESS = 0.3, 1e-3
DT, N_STEPS, TOL, MAX_ITER = 0.01, 30, 2e-6, 20000
PILE = ("c0", "c1", "c2", "c3")
TRUE = np.array([1.1, 0.15, 0.1])  # the hidden push: vx, vy, corner speed of the spin (m/s)
START = np.array([0.7, -0.1, 0.0])
LOWER, UPPER = np.array([0.3, -0.3, -0.3]), np.array([1.4, 0.3, 0.3])
THRESHOLD = 1.0  # mm^2: 0.5 mm RMS over the four cubes
FD_EPS = 1e-4  # m/s


def scene(edges: bool = True, mu_pair: float = MU):
    """The striker and the pile on the ground; returns ``(model, params)``.

    Arguments:
        edges: edge-edge rows between the bodies (see :class:`~softbody.contact.pairs.Touch`).
        mu_pair: the friction coefficient between the bodies."""
    cube = Material(E=1e5, nu=0.3, density=1000.0)
    heavy = Material(E=1e5, nu=0.3, density=4000.0)
    bodies = [SoftBody(grid_box((EDGE,) * 3, (1, 1, 1), origin=(-EDGE - RUN_UP, -EDGE / 2, 0.0)), heavy,
                       name="striker")]
    for k, name in enumerate(PILE):
        i, j = divmod(k, 2)
        origin = (i * (EDGE + GAP), -EDGE - GAP / 2 + j * (EDGE + GAP), 0.0)
        bodies.append(SoftBody(grid_box((EDGE,) * 3, (1, 1, 1), origin=origin), cube, name=name))
    return build(bodies, obstacles=[Plane(mu_s=MU, mu_k=MU)],
                 rows=[Touch(*[b.name for b in bodies], mu_s=mu_pair, mu_k=mu_pair, thickness=THICKNESS, edges=edges,
                             capacity=4096)],
                 options=Options(dt=DT, tol=TOL, max_iter=MAX_ITER))


class PilePush:
    """The push problem: ``simulate(theta)``, ``loss(theta)`` (mm^2, with the number of
    failed steps as aux) and their compiled forms."""

    def __init__(self, n_steps: int = N_STEPS, **scene_options):
        self.model, self.params = scene(**scene_options)
        self.n_steps = n_steps
        spans = {b.name: b.vertices for b in self.model.bodies}
        self.striker = np.arange(*spans["striker"])
        self.pile = np.stack([np.arange(*spans[name]) for name in PILE])
        x0 = np.asarray(self.model.mesh.points)
        self.striker_centre = x0[self.striker].mean(axis=0)
        self.targets = None
        self.value = jax.jit(lambda theta: self.loss(theta)[0])
        self.value_and_grad = jax.jit(jax.value_and_grad(self.loss, has_aux=True))
        self.trajectory = jax.jit(self.simulate)

    def velocities(self, theta):
        """Initial vertex velocities: the striker's ``(vx, vy)`` plus its spin, zero elsewhere."""
        omega = theta[2] / (EDGE / 2)
        r = jnp.asarray(self.model.mesh.points[self.striker] - self.striker_centre)
        v = jnp.stack([theta[0] - omega * r[:, 1], theta[1] + omega * r[:, 0], 0.0 * r[:, 2]], axis=1)
        return jnp.zeros((self.model.n_vertices, 3)).at[self.striker].set(v)

    def simulate(self, theta):
        state = initial_state(self.model, self.params, v=self.velocities(theta))
        return rollout(self.model, self.params, state, n_steps=self.n_steps, throw=False)

    def centres(self, x):
        """``(4, 3)`` centres of mass of the pile's cubes (equal vertex masses on each cube)."""
        return x[self.pile].mean(axis=1)

    def aim(self, theta):
        """Set the targets to the pile's final centres under the push ``theta``; returns
        that trajectory."""
        traj = self.trajectory(jnp.asarray(theta))
        self.targets = self.centres(traj.x[-1])
        return traj

    def loss(self, theta):
        """The sum of squared distances (mm^2) of the final centres to the targets, and the
        number of steps that did not succeed."""
        traj = self.simulate(theta)
        d = (self.centres(traj.x[-1]) - self.targets) * 1e3
        failed = jnp.sum(traj.info.result != 0)
        return jnp.sum(d * d), failed


def central_differences(problem, theta, eps):
    """``(3,)`` central differences of the loss at ``theta``."""
    g = np.zeros(3)
    for i in range(3):
        e = np.zeros(3)
        e[i] = eps
        g[i] = (float(problem.value(jnp.asarray(theta + e))) - float(problem.value(jnp.asarray(theta - e)))) / (2 * eps)
    return g


def gradient_run(problem, budget):
    """L-BFGS-B on the loss and its gradient; returns the history of every evaluation."""
    from scipy.optimize import minimize

    history = {"loss": [], "theta": [], "failed": [], "seconds": []}

    def fun(theta):
        start = time.perf_counter()
        (value, failed), grad = problem.value_and_grad(jnp.asarray(theta))
        value, grad = float(value), np.asarray(grad, np.float64)
        history["seconds"].append(time.perf_counter() - start)
        history["loss"].append(value)
        history["theta"].append(np.asarray(theta).tolist())
        history["failed"].append(int(failed))
        best = min(history["loss"])
        progress.say(f"gradient: simulation {len(history['loss'])}: loss {value:.4g} mm^2 (best {best:.4g}), "
                     f"theta {np.round(theta, 4).tolist()}, {history['seconds'][-1]:.1f} s")
        if best <= THRESHOLD:
            raise _Reached
        return value, grad

    start, start_cpu = time.perf_counter(), time.process_time()
    try:
        minimize(fun, START, jac=True, method="L-BFGS-B", bounds=list(zip(LOWER, UPPER)),
                 options={"maxfun": budget, "maxiter": budget})
    except _Reached:
        pass
    history["wall_time_s"] = time.perf_counter() - start
    history["cpu_time_s"] = time.process_time() - start_cpu
    return history


class _Reached(Exception):
    """The loss fell below the threshold."""


def first_below(losses, threshold):
    """The 1-based count of simulations at which the best loss first is <= threshold, or None."""
    hits = np.flatnonzero(np.minimum.accumulate(np.asarray(losses)) <= threshold)
    return int(hits[0]) + 1 if hits.size else None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--budget", type=int, default=30, help="gradient simulation budget")
    parser.add_argument("--cmaes-factor", type=int, default=10, help="CMA-ES budget over the gradient's simulations")
    parser.add_argument("--quick", action="store_true", help="the gradient check and the gradient run only")
    parser.add_argument("--seed", type=int, default=1, help="CMA-ES seed")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with progress.task("building the scene"):
        problem = PilePush()
    model = problem.model
    progress.say(f"pile push: {len(model.bodies)} bodies, {model.n_vertices} vertices, {N_STEPS} steps of {DT} s")

    with progress.task("compiling and running the rollout"):
        t0 = time.perf_counter()
        truth = problem.aim(TRUE)
        jax.block_until_ready(truth.x)
        compile_forward = time.perf_counter() - t0
    truth_failed = int(np.sum(np.asarray(truth.info.result) != 0))

    with progress.task("compiling the loss and its gradient"):
        t0 = time.perf_counter()
        jax.block_until_ready(problem.value(jnp.asarray(START)))
        compile_value = time.perf_counter() - t0
        t0 = time.perf_counter()
        (loss0, failed0), grad0 = problem.value_and_grad(jnp.asarray(START))
        jax.block_until_ready(grad0)
        compile_grad = time.perf_counter() - t0
    timings = {"forward": [], "gradient": []}
    for _ in range(2):
        t0 = time.perf_counter()
        jax.block_until_ready(problem.value(jnp.asarray(START)))
        timings["forward"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        jax.block_until_ready(problem.value_and_grad(jnp.asarray(START)))
        timings["gradient"].append(time.perf_counter() - t0)
    forward_s, gradient_s = float(np.median(timings["forward"])), float(np.median(timings["gradient"]))
    progress.say(f"one simulation {forward_s:.2f} s, one loss and gradient {gradient_s:.2f} s "
                 f"(compiling: {compile_forward + compile_value:.0f} s forward, {compile_grad:.0f} s gradient)")

    with progress.task("central differences at the start"):
        fd = central_differences(problem, START, FD_EPS)
        fd_coarse = central_differences(problem, START, 10 * FD_EPS)
    grad0 = np.asarray(grad0)
    fd_rel = float(np.linalg.norm(grad0 - fd) / np.linalg.norm(fd))
    fd_rel_coarse = float(np.linalg.norm(grad0 - fd_coarse) / np.linalg.norm(fd_coarse))
    progress.say(f"gradient at the start {grad0.tolist()}, central differences (eps {FD_EPS}) {fd.tolist()}: "
                 f"relative error {fd_rel:.2e} ({fd_rel_coarse:.2e} against eps {10 * FD_EPS})")

    grad_hist = gradient_run(problem, args.budget)
    grad_sims = first_below(grad_hist["loss"], THRESHOLD)
    best = int(np.argmin(grad_hist["loss"]))
    grad_theta = np.asarray(grad_hist["theta"][best])
    final = problem.trajectory(jnp.asarray(grad_theta))
    info = final.info
    steps_result = np.asarray(info.result)
    metrics = {
        "gradient_simulations": grad_sims, "loss_threshold": THRESHOLD,
        "gradient_final_loss": float(grad_hist["loss"][best]), "gradient_theta": grad_theta.tolist(),
        "gradient_wall_time_s": grad_hist["wall_time_s"], "gradient_cpu_time_s": grad_hist["cpu_time_s"],
        "gradient_evaluation_s": grad_hist["seconds"],
        "gradient_evaluations": len(grad_hist["loss"]), "gradient_loss_history": grad_hist["loss"],
        "gradient_failed_steps": grad_hist["failed"], "gradient_theta_history": grad_hist["theta"],
        "fd_rel_error": fd_rel, "fd_rel_error_coarse": fd_rel_coarse, "fd_eps": FD_EPS,
        "gradient_at_start": grad0.tolist(), "fd_at_start": fd.tolist(), "fd_at_start_coarse": fd_coarse.tolist(),
        "start_loss": float(loss0), "start_failed_steps": int(failed0), "true_theta": TRUE.tolist(),
        "start_theta": START.tolist(), "true_failed_steps": truth_failed,
        "forward_s": forward_s, "gradient_s": gradient_s, "gradient_over_forward": gradient_s / forward_s,
        "compile_forward_s": compile_forward + compile_value, "compile_gradient_s": compile_grad,
        "all_steps_converged": bool((steps_result == 0).all()), "failed_steps": np.flatnonzero(steps_result).tolist(),
        "iterations_median": float(np.median(np.asarray(info.iterations))),
        "iterations_max": int(np.max(np.asarray(info.iterations))),
        "final_distances_mm": (np.linalg.norm(np.asarray(problem.centres(final.x[-1]) - problem.targets), axis=1)
                               * 1e3).tolist(),
        "pile_travel_mm": (np.linalg.norm(np.asarray(problem.targets - problem.centres(truth.x[0])), axis=1)
                           * 1e3).tolist(),
        "bodies": len(model.bodies), "vertices": model.n_vertices, "steps": N_STEPS, "dt": DT,
    }
    progress.say(f"gradient: {grad_sims} simulations to {THRESHOLD} mm^2, best {metrics['gradient_final_loss']:.3g} "
                 f"in {grad_hist['wall_time_s']:.1f} s")

    cma = None
    if not args.quick:
        budget = args.cmaes_factor * len(grad_hist["loss"])
        cma_start, cma_cpu = time.perf_counter(), time.process_time()
        cma = sc.cmaes(None, jnp.asarray(START), sigma0=0.2, budget=budget, lower=LOWER, upper=UPPER,
                       seed=args.seed, target=THRESHOLD, progress=True,
                       evaluate=lambda xs: [float(problem.value(jnp.asarray(x))) for x in xs])
        cma_time, cma_cpu = time.perf_counter() - cma_start, time.process_time() - cma_cpu
        reached = np.flatnonzero(cma.best_loss_history <= THRESHOLD)
        metrics.update({
            "cmaes_simulations": int(cma.simulations[reached[0]]) if reached.size else None,
            "cmaes_final_loss": float(cma.best_loss), "cmaes_wall_time_s": cma_time, "cmaes_cpu_time_s": cma_cpu,
            "cmaes_budget": budget, "cmaes_evaluations": cma.n_simulations, "cmaes_failed": cma.failed,
            "cmaes_theta": np.asarray(cma.best_theta).tolist(),
            "cmaes_history": {"simulations": cma.simulations.tolist(), "best_loss": cma.best_loss_history.tolist()},
        })
        progress.say(f"CMA-ES: {metrics['cmaes_simulations']} simulations to {THRESHOLD} mm^2, best "
                     f"{cma.best_loss:.3g} after {cma.n_simulations}, {cma_time:.1f} s")
    else:
        metrics.update({"cmaes_simulations": None, "cmaes_final_loss": None, "cmaes_wall_time_s": None})

    _plot(args.out, grad_hist, cma)
    obstacles = [o.to_dict(p) for o, p in zip(model.obstacles, problem.params.obstacles)]
    Result.from_mesh(model.mesh, np.asarray(final.x), DT, obstacles=obstacles,
                     fields=contact_fields(model, problem.params, final),
                     metadata={"pile_push": {"theta": grad_theta.tolist(), "loss_mm2": metrics["gradient_final_loss"]}}
                     ).save(args.out / "pile_push.npz", force=True)
    metrics["wall_time_s"] = time.perf_counter() - start
    metrics["cpu_time_s"] = time.process_time()
    write_metrics(args.out / "metrics.json", metrics, force=True)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


def _plot(out, grad_hist, cma):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    n = len(grad_hist["loss"])
    ax.semilogy(np.arange(1, n + 1), np.minimum.accumulate(grad_hist["loss"]), "o-", ms=3,
                label="L-BFGS-B, gradient through the simulation")
    if cma is not None:
        ax.semilogy(cma.simulations, cma.best_loss_history, "s-", ms=3, label="CMA-ES")
    ax.axhline(THRESHOLD, color="k", lw=0.8, ls="--", label="threshold")
    ax.set_xlabel("simulations (a loss and gradient counts as one)")
    ax.set_ylabel("best loss (mm$^2$)")
    ax.set_title("Pushing a pile of four cubes to its targets")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "loss.png", dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()

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
of the fingertips) at a hand-set pressure (``--pressure``, a 0.3 s ramp).

``--optimise`` finds the soft cube's controls instead: each finger's pressure at the times
``KNOTS`` (linear between them, 0 at t = 0; 8 variables in kPa, bounds [0, 60]), from
``START_KPA`` everywhere, a schedule that closes the fingers on the cube but lets it slip out
as the palm rises. The loss (:class:`GraspProblem`) asks the cube to follow the palm up
(mean squared height error while the palm rises and holds, per cm^2), to stay where it is
between the fingertips (mean squared drift, per 100 mm^2) and, weakly, for low pressures.
L-BFGS-B (scipy) on the gradient through the whole rollout (the contact solver's implicit
adjoint; a loss and its gradient count as one simulation) runs until the cube is lifted
(``lift_m >= 5 cm``, ``slip_m < 1 mm``, every step converged) or ``--budget``
simulations; CMA-ES (:func:`softbody.control.cmaes`) on the same loss, start, variables
and bounds (``sigma0`` 10 kPa) until it lifts the cube or ``--cmaes-budget`` simulations.

From 18 kPa the gradient method lifts the cube at its 2nd simulation and CMA-ES at its 3rd;
from 12 kPa, below the grip (the cube rests on the table and the loss sees only the fingers
sliding), the gradient method does not find it in 11 simulations and CMA-ES does at its
14th (examples/README.md).

Run::

    python examples/grasp.py --out results/grasp                  # hand-set 30 kPa, both objects
    python examples/grasp.py --out results/grasp_opt --optimise   # the soft cube's controls by gradients and CMA-ES

Writes ``metrics.json`` (per object ``lift_m``, ``slip_m``, convergence and iteration
counts; with ``--optimise`` the soft cube's entry is the optimised grasp's, with
``simulations`` (the gradient method's, to the first lift), ``cmaes_simulations_to_lift``
(``None`` where CMA-ES did not lift it within its budget), both loss histories and the
schedules), ``loss.png`` (with ``--optimise``: best loss against simulations), a result file per object (``rigid_box.npz``, ``soft_cube.npz``: ``softbody view``
opens them; "colour by" ``contact_force`` or ``contact_state`` shows the contact between
the fingers, the object and the table) and a render of each one's last frame (``rigid_box.png``, ``soft_cube.png``).
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
KNOTS = (0.1, 0.3, 0.6, 1.5)  # s: the optimised pressure schedule's knots
START_KPA = 18.0  # the optimisation's start, every knot: the cube slips out as the palm rises
UPPER_KPA = 60.0  # the schedule's bound (P_MAX)


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


def rollout_metrics(model, traj, obj_v, tips) -> dict:
    """:func:`grasp_metrics` of ``traj`` and its steps' convergence: ``all_converged``,
    ``failed_steps``, ``result_codes``, ``iterations_median``, ``iterations_max``, ``vertices``."""
    it, res = np.asarray(traj.info.iterations), np.asarray(traj.info.result)
    m = grasp_metrics(traj.x, obj_v, tips)
    m.update(all_converged=bool((res == 0).all()), failed_steps=np.flatnonzero(res != 0).tolist(),
             result_codes=sorted(set(res.tolist())), iterations_median=float(np.median(it)),
             iterations_max=int(it.max()), vertices=model.n_vertices)
    return m


def hand_set(obj, pressure, out):
    """The rollout at a hand-set pressure ramp; returns its metrics and the built scene."""
    with progress.task(f"{obj}: building the scene"):
        model, params, obj_v, tips = scene(obj)
    controls = pressure_ramp(pressure)
    t0 = time.perf_counter()
    with progress.task(f"{obj}: simulating {N_STEPS} steps at {pressure / 1e3:.0f} kPa (compiles)"):
        traj = rollout(model, params, initial_state(model, params), controls, throw=False)
    wall = time.perf_counter() - t0
    m = rollout_metrics(model, traj, obj_v, tips)
    m.update(pressure_pa=pressure, rollout_wall_time_s=wall)
    print(f"{obj}: lift {m['lift_m'] * 1e3:.1f} mm, slip {m['slip_m'] * 1e3:.3f} mm, "
          f"all steps converged: {m['all_converged']}, iterations median {m['iterations_median']:.0f} "
          f"max {m['iterations_max']}, {wall:.0f} s", flush=True)
    save_result(model, params, traj, controls, out / f"{obj}.npz", m)
    return m, (model, params, obj_v, tips)


class GraspProblem:
    """The soft cube's grasp as an optimisation over each finger's pressure at ``KNOTS``.

    ``theta`` ``(2 * len(KNOTS),)``: the left finger's pressures at the knots, then the
    right one's, in kPa. :meth:`loss` (and its compiled :attr:`value` and
    :attr:`value_and_grad`) returns the loss and, as aux, the trajectory's positions and
    the number of steps that did not succeed.
    """

    def __init__(self, obj: str = "soft_cube"):
        self.model, self.params, self.obj_v, self.tips = scene(obj)
        self.state = initial_state(self.model, self.params)
        t = (np.arange(N_STEPS) + 1) * DT
        self.basis = jnp.asarray(np.stack([np.interp(t, (0.0, *KNOTS), np.r_[0.0, e]) for e in np.eye(len(KNOTS))], 1))
        self.target = palm_height(jnp.asarray(t))
        self.value = jax.jit(self.loss)
        self.value_and_grad = jax.jit(jax.value_and_grad(self.loss, has_aux=True))

    def controls(self, theta):
        """``(N_STEPS, 2)`` chamber pressures, Pa, of the schedule ``theta`` (kPa at the knots)."""
        return self.basis @ jnp.reshape(theta, (2, -1)).T * 1e3

    def loss(self, theta):
        """Height error (per cm^2) + drift between the fingertips (per 100 mm^2) + 0.01 x mean
        squared pressure (per ``UPPER_KPA^2``), and ``(x, failed steps)``."""
        traj = rollout(self.model, self.params, self.state, self.controls(theta), throw=False)
        k0 = round(CLOSE / DT)
        centre = traj.x[:, self.obj_v].mean(axis=1)
        rel = centre - traj.x[:, self.tips].mean(axis=1)
        height = jnp.mean(((centre[1:, 2] - centre[0, 2] - self.target)[k0:] / 1e-2) ** 2)
        drift = jnp.mean(jnp.sum((rel[k0:] - rel[k0]) ** 2, axis=-1)) / 1e-2**2
        effort = 1e-2 * jnp.mean((jnp.asarray(theta) / UPPER_KPA) ** 2)
        return height + drift + effort, (traj.x, jnp.sum(traj.info.result != 0))

    def lifted(self, x, failed) -> tuple[bool, dict]:
        """Whether the rollout ``x`` lifts the object (``LIFT_GOAL``, ``SLIP_GOAL``, no failed
        step), and its :func:`grasp_metrics`."""
        m = grasp_metrics(x, self.obj_v, self.tips)
        return bool(m["lift_m"] >= LIFT_GOAL and m["slip_m"] < SLIP_GOAL and int(failed) == 0), m


class _Lifted(Exception):
    """The object was lifted."""


def gradient_run(problem: GraspProblem, budget: int, start_kpa: float = START_KPA) -> dict:
    """L-BFGS-B on the loss and its gradient from ``start_kpa`` at every knot until the object
    is lifted or ``budget`` simulations; returns the history of every evaluation."""
    from scipy.optimize import minimize

    history = {"loss": [], "theta_kpa": [], "lift_m": [], "slip_m": [], "failed": [], "seconds": [], "lifted_at": None}

    def fun(theta):
        t0 = time.perf_counter()
        with progress.task(f"gradient: simulation {len(history['loss']) + 1} (loss and gradient"
                           f"{', compiling' if not history['loss'] else ''})"):
            (value, (x, failed)), grad = jax.block_until_ready(problem.value_and_grad(jnp.asarray(theta)))
        lifted, m = problem.lifted(np.asarray(x), failed)
        for key, item in (("loss", float(value)), ("theta_kpa", np.asarray(theta).tolist()), ("lift_m", m["lift_m"]),
                          ("slip_m", m["slip_m"]), ("failed", int(failed)), ("seconds", time.perf_counter() - t0)):
            history[key].append(item)
        progress.say(f"gradient: simulation {len(history['loss'])}: loss {float(value):.4g}, lift "
                     f"{m['lift_m'] * 1e3:.1f} mm, slip {m['slip_m'] * 1e3:.2f} mm, {int(failed)} failed steps, "
                     f"pressures {np.round(theta, 1).tolist()} kPa, {history['seconds'][-1]:.0f} s")
        if lifted:
            history["lifted_at"] = len(history["loss"])
            raise _Lifted
        return float(value), np.asarray(grad, np.float64)

    start = time.perf_counter()
    theta0 = np.full(2 * len(KNOTS), start_kpa)
    try:
        minimize(fun, theta0, jac=True, method="L-BFGS-B", bounds=[(0.0, UPPER_KPA)] * theta0.size,
                 options={"maxfun": budget, "maxiter": budget})
    except _Lifted:
        pass
    history["wall_time_s"] = time.perf_counter() - start
    return history


def cmaes_run(problem: GraspProblem, budget: int, seed: int, start_kpa: float = START_KPA) -> dict:
    """CMA-ES on the same loss, start and bounds until the object is lifted or ``budget``
    simulations; returns its history."""
    from softbody.control import cmaes

    history = {"loss": [], "lift_m": [], "slip_m": [], "lifted_at": None}

    def evaluate(xs):
        values = []
        for theta in xs:
            value, (x, failed) = problem.value(jnp.asarray(theta))
            lifted, m = problem.lifted(np.asarray(x), failed)
            for key, item in (("loss", float(value)), ("lift_m", m["lift_m"]), ("slip_m", m["slip_m"])):
                history[key].append(item)
            if lifted and history["lifted_at"] is None:
                history["lifted_at"] = len(history["loss"])
            values.append(float(value))
        return values

    start = time.perf_counter()
    result = cmaes(None, jnp.full(2 * len(KNOTS), start_kpa), sigma0=10.0, budget=budget, lower=0.0,
                   upper=UPPER_KPA, seed=seed, evaluate=evaluate, stop=lambda *_: history["lifted_at"] is not None)
    history.update(wall_time_s=time.perf_counter() - start, best_theta_kpa=np.asarray(result.best_theta).tolist(),
                   best_loss=float(result.best_loss))
    return history


def optimise(out: Path, budget: int, cmaes_budget: int, seed: int, start_kpa: float = START_KPA) -> dict:
    """The soft cube's controls by gradients and by CMA-ES; returns its metrics entry."""
    with progress.task("soft_cube: building the scene"):
        problem = GraspProblem("soft_cube")
    grad = gradient_run(problem, budget, start_kpa) if budget > 0 else None
    cma = cmaes_run(problem, cmaes_budget, seed, start_kpa) if cmaes_budget > 0 else None
    for name, history in (("gradient", grad), ("CMA-ES", cma)):
        if history is not None:
            outcome = f"lifted after {history['lifted_at']}" if history["lifted_at"] else "not lifted in"
            progress.say(f"{name}: {outcome} {len(history['loss'])} simulations, {history['wall_time_s']:.0f} s")
    if grad is not None:  # the gradient method's lifting (else best) schedule
        theta = np.asarray(grad["theta_kpa"][grad["lifted_at"] - 1 if grad["lifted_at"] else int(np.argmin(grad["loss"]))])
    else:  # CMA-ES alone: its best schedule
        theta = np.asarray(cma["best_theta_kpa"])
    controls = problem.controls(jnp.asarray(theta))
    traj = rollout(problem.model, problem.params, problem.state, controls, throw=False)
    m = rollout_metrics(problem.model, traj, problem.obj_v, problem.tips)
    m.update(simulations=grad["lifted_at"] if grad else None, cmaes_simulations_to_lift=cma["lifted_at"] if cma else None,
             cmaes_budget=cmaes_budget, gradient_budget=budget, start_kpa=start_kpa, knots_s=list(KNOTS),
             theta_kpa=theta.tolist(), gradient=grad, cmaes=cma)
    save_result(problem.model, problem.params, traj, np.asarray(controls), out / "soft_cube.npz", m)
    _loss_plot(out, grad, cma, start_kpa)
    return m


def _loss_plot(out, grad, cma, start_kpa):
    """``loss.png``: best loss against simulations, gradients and CMA-ES."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for history, style, label in ((grad, "o-", "L-BFGS-B, gradient through the simulation"), (cma, "s-", "CMA-ES")):
        if history:
            ax.semilogy(np.arange(1, len(history["loss"]) + 1), np.minimum.accumulate(history["loss"]), style, ms=3,
                        label=label + (f" (lifted at {history['lifted_at']})" if history["lifted_at"] else ""))
    ax.set_xlabel("simulations (a loss and gradient counts as one)")
    ax.set_ylabel("best loss")
    ax.set_title(f"Grasping the soft cube: controls from {start_kpa:g} kPa")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "loss.png", dpi=120)
    plt.close(fig)


def main(argv=None):
    """Run the hand-set grasp of each object (or, with ``--optimise``, the soft cube's
    optimised one); returns the metrics."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--pressure", type=float, default=3e4, help="hand-set chamber pressure, Pa")
    parser.add_argument("--objects", nargs="+", default=list(OBJECTS), choices=OBJECTS)
    parser.add_argument("--optimise", action="store_true",
                        help="find the soft cube's pressure schedule by gradients and by CMA-ES (instead of --pressure)")
    parser.add_argument("--budget", type=int, default=30,
                        help="with --optimise: the gradient method's simulations (0 skips it)")
    parser.add_argument("--cmaes-budget", type=int, default=300,
                        help="with --optimise: CMA-ES's simulations (0 skips it)")
    parser.add_argument("--seed", type=int, default=1, help="with --optimise: CMA-ES's seed")
    parser.add_argument("--start-kpa", type=float, default=START_KPA,
                        help="with --optimise: the starting pressure at every knot, kPa")
    args = parser.parse_args(argv)
    if args.optimise and args.budget <= 0 and args.cmaes_budget <= 0:
        parser.error("--optimise needs --budget or --cmaes-budget above 0")
    check_overwrite(args.out / "metrics.json", args.force)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    metrics = {}
    if args.optimise:
        metrics["soft_cube"] = optimise(args.out, args.budget, args.cmaes_budget, args.seed, args.start_kpa)
        write_metrics(args.out / "metrics.json", metrics, force=True)
    for obj in args.objects if not args.optimise else ():
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

"""``softbody demo``: mesh a soft arm, simulate it, teach it to reach a point, show the result.

The robot is a soft cantilever arm (20 cm x 4 cm x 4 cm, clamped at ``x = 0``) with four
muscle bands along its length: the top, bottom, left (+y) and right (-y) halves of its
cross-section, fibres along the arm, like the four tendons of a continuum robot. Each
band is one control channel with an activation in [0, 1].

The task: starting at rest under gravity, bring the tip (the centroid of the end face)
to a target point up and to the left and keep it there. The controls are open-loop
activations on a coarse grid of knots in time (piecewise linear in between; ``sigmoid``
of free parameters keeps them in [0, 1]); the loss is::

    sum_k w_k |tip_k - target|^2 / L^2  +  effort * mean(a^2),    w_k proportional to t_k

over the frames ``k``, so reaching the target early pays and holding it at the end pays
most; the small effort term settles what the tip cannot tell apart (co-contraction).
The target is where the arm's tip rests with the top band at 0.4 and the left band at
0.3 (rounded to the millimetre), so it is reachable and a good optimiser gets close to it.

Gradients come from the simulator's implicit adjoint; Adam (optax) updates the knots.
Two functions are compiled, once each (static shapes): the loss with its gradient, and
the loss alone with its rollout (for the first and the final trajectory). Compiling is
most of a quick run's time: ``timings`` in ``metrics.json`` (the same figures as
``wall_time_s``) gives ``compile`` and its ``compile_trace`` part (tracing and lowering,
done every run; the rest is XLA, which :mod:`softbody.cache` can load on later runs), and
``compilation_cache`` how many of the programs were loaded.

Writes to ``DIR`` (default ``softbody-demo/``): ``metrics.json``, ``result.npz`` (the
optimised trajectory with its activations and the loss history; the target and the
mount are stored as obstacles for display only), ``render.png`` (last frame),
``render.mp4`` and ``loss.png``. Then serves the result in the browser viewer when stdin
is a terminal and ``--no-view`` is not given.

Command line::

    softbody demo [--out DIR] [--no-view] [--port 8080] [--force] [--quick]
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from softbody.cli import port_number

#: Arm dimensions (length along +x, width along y, height along z), m.
ARM_LENGTH, ARM_WIDTH, ARM_HEIGHT = 0.2, 0.04, 0.04
#: Muscle band name -> the (y, z) side of the cross-section it fills.
BANDS = {"top": (0, 1), "bottom": (0, -1), "left": (1, 0), "right": (-1, 0)}
#: Tip target, m: the tip's static rest point with top = 0.4, left = 0.3 (see the module docstring).
TARGET = (0.158, 0.043, 0.052)
#: Material of the arm (silicone-like) and stiffness of each muscle band.
YOUNG, POISSON, DENSITY, MASS_DAMPING = 5e5, 0.45, 1000.0, 10.0
MUSCLE_STIFFNESS = 5e5
#: Force-residual tolerance of each implicit step. Measured on this scene (full settings,
#: random controls): the implicit-adjoint gradient at 1e-6 agrees with the one at 1e-9 to
#: 3e-8 (relative), and the steps take 36 % fewer solver iterations (132 against 207).
TOLERANCE = 1e-6
#: Weight of the effort term of the loss.
EFFORT = 1e-3
#: Initial activation of every band (a near-passive arm).
INITIAL_ACTIVATION = 0.05


@dataclass(frozen=True)
class Settings:
    """The size of the demo's problem.

    Attributes:
        mesh_size: target tet edge length, m.
        dt: time step, s.
        steps: number of time steps (the horizon is ``steps * dt``).
        knots: control knots per channel, evenly spaced from t = 0 to the horizon.
        iterations: Adam iterations.
        learning_rate: Adam's initial step (on the knots' logits); it decays
            exponentially to a tenth over the iterations.
        window: render size ``(width, height)`` in pixels.
    """

    mesh_size: float
    dt: float
    steps: int
    knots: int
    iterations: int
    learning_rate: float
    window: tuple[int, int]


FULL = Settings(mesh_size=0.02, dt=0.02, steps=25, knots=5, iterations=16, learning_rate=1.0,
                window=(960, 720))
QUICK = Settings(mesh_size=0.02, dt=0.02, steps=15, knots=4, iterations=8, learning_rate=1.0,
                 window=(480, 360))

#: Shown with the result (the simulation has no obstacles): the target and the block the arm
#: is clamped to.
MARKERS = (
    {"type": "sphere", "center": list(TARGET), "radius": 0.005, "name": "target"},
    {"type": "box", "center": [-0.01, 0.0, 0.0], "half_extents": [0.01, 0.03, ARM_HEIGHT / 2],
     "name": "mount"},
)

#: The files the demo writes into its output folder.
OUTPUTS = ("metrics.json", "result.npz", "render.png", "render.mp4", "loss.png")


class Evaluation(NamedTuple):
    """What one evaluation of the objective returns besides the loss."""

    traj: object  # the Trajectory: x, v (T + 1, n, 3), info per step
    activation: object  # (T + 1, c) activations per frame
    tip: object  # (T + 1, 3) tip centroid


def arm_mesh(size: float):
    """Mesh the arm with gmsh.

    Arguments:
        size: target tet edge length, m.

    Returns:
        A :class:`~softbody.meshing.TetMesh` with regions ``"fixed"`` (x = 0), ``"tip"``
        (x = L) and ``"muscle:<band>"`` for the bands in :data:`BANDS` (each tet lies in one
        vertical and one horizontal band).
    """
    from softbody.meshing import Box, OnPlane, mesh

    body = Box((ARM_LENGTH, ARM_WIDTH, ARM_HEIGHT), center=(ARM_LENGTH / 2, 0.0, 0.0))
    for name, (side_y, side_z) in BANDS.items():
        extent = (ARM_LENGTH, ARM_WIDTH / 2 if side_y else ARM_WIDTH,
                  ARM_HEIGHT / 2 if side_z else ARM_HEIGHT)
        centre = (ARM_LENGTH / 2, side_y * ARM_WIDTH / 4, side_z * ARM_HEIGHT / 4)
        body = body.mark(f"muscle:{name}", Box(extent, center=centre))
    return mesh(body, size, select={"fixed": OnPlane("x", 0.0), "tip": OnPlane("x", ARM_LENGTH)})


def control_basis(steps: int, knots: int) -> np.ndarray:
    """Piecewise-linear interpolation from ``knots`` evenly spaced knots to every frame.

    Arguments:
        steps: number of time steps; frames are ``0 .. steps``.
        knots: number of knots (>= 2), the first at frame 0 and the last at frame ``steps``.

    Returns:
        ``(steps + 1, knots)`` hat-function weights; each row sums to 1.
    """
    s = np.arange(steps + 1) / steps * (knots - 1)
    return np.maximum(0.0, 1.0 - np.abs(s[:, None] - np.arange(knots)[None, :]))


def make_objective(model, params, state0, basis: np.ndarray, tip: np.ndarray):
    """The demo's loss as a function of the knots' logits ``z`` ``(knots, channels)``.

    Returns:
        ``evaluate(z) -> (loss, Evaluation)``: activations ``sigmoid(basis @ z)`` drive a
        rollout (frame k's activation acts during the step that ends at frame k). The
        rollout does not raise inside the compiled program (a host callback would keep it
        out of the persistent compilation cache): pass each result's trajectory to
        :func:`softbody.simulate.check_trajectory`.
    """
    import jax
    import jax.numpy as jnp

    from softbody.simulate import rollout

    frames = np.arange(basis.shape[0], dtype=np.float64)
    weights = jnp.asarray(frames / frames.sum())
    basis = jnp.asarray(basis)
    target = jnp.asarray(TARGET)

    def evaluate(z):
        activation = jax.nn.sigmoid(basis @ z)
        traj = rollout(model, params, state0, controls=activation[1:], throw=False)
        tip_x = traj.x[:, tip].mean(axis=1)
        reach = jnp.sum(weights * jnp.sum((tip_x - target) ** 2, axis=-1)) / ARM_LENGTH**2
        loss = reach + EFFORT * jnp.mean(activation**2)
        return loss, Evaluation(traj, activation, tip_x)

    return evaluate


def _checked(model, program, evaluation):
    """``program`` that raises :class:`~softbody.simulate.SimulationError` for a failed step
    of the trajectory in ``evaluation(output)`` (see :func:`make_objective`)."""
    from softbody.simulate import check_trajectory

    def run(z):
        out = program(z)
        check_trajectory(model, evaluation(out).traj)
        return out

    return run


def _progress(console):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[bold]optimising"), BarColumn(bar_width=12), MofNCompleteColumn(),
        TextColumn("loss [cyan]{task.fields[loss]}"), TextColumn("tip [magenta]{task.fields[tip]}"),
        TextColumn("{task.fields[rate]}"), TextColumn("eta"), TimeRemainingColumn(),
        console=console, disable=not console.is_terminal,
    )


def _tip_error(ev: Evaluation) -> float:
    return float(np.linalg.norm(np.asarray(ev.tip[-1]) - np.asarray(TARGET)))


def _describe_error(distance: float) -> str:
    return f"{1e3 * distance:.1f} mm ({100 * distance / ARM_LENGTH:.1f}% of L)"


def demo(out: Path, settings: Settings, *, force: bool = False, console=None) -> dict:
    """Mesh, simulate, optimise, render; write the outputs to ``out``.

    Arguments:
        out: the output folder (created).
        settings: :data:`FULL` or :data:`QUICK` (or your own).
        force: overwrite the demo's files in ``out``.
        console: a :class:`rich.console.Console` for progress output.

    Returns:
        The metrics written to ``out/metrics.json``.

    Raises:
        FileExistsError: one of the outputs exists and ``force`` is false.
    """
    import jax
    import jax.numpy as jnp
    from rich.console import Console

    from softbody import cache
    from softbody.actuators import Muscle
    from softbody.io import Result, check_overwrite, write_metrics
    from softbody.material import Material
    from softbody.model import Options, build, initial_state
    from softbody.scene import SoftBody

    console = console or Console()
    for name in OUTPUTS:
        check_overwrite(out / name, force)
    times: dict[str, float] = {}
    start = time.perf_counter()

    with console.status("meshing the arm (gmsh)"):
        mesh = arm_mesh(settings.mesh_size)
    times["mesh"] = time.perf_counter() - start
    console.print(f"meshed the arm: {mesh.n_vertices} vertices, {mesh.n_tets} tets ({times['mesh']:.1f} s)")

    channels = [f"muscle:{band}" for band in BANDS]
    material = Material(E=YOUNG, nu=POISSON, density=DENSITY, alpha=MASS_DAMPING)
    muscles = Muscle.from_regions(mesh, channels, fibre=(1.0, 0.0, 0.0), stiffness=MUSCLE_STIFFNESS)
    # Steps of this scene take up to ~200 iterations at TOLERANCE; the cap leaves room.
    options = Options(dt=settings.dt, tol=TOLERANCE, max_iter=500)
    model, params = build(SoftBody(mesh, material, fixed="fixed", actuators=[muscles]), options=options)
    state0 = initial_state(model, params)
    basis = control_basis(settings.steps, settings.knots)
    evaluate = make_objective(model, params, state0, basis, mesh.regions["tip"].vertices)
    logit = float(np.log(INITIAL_ACTIVATION / (1 - INITIAL_ACTIVATION)))
    z = jnp.full((settings.knots, len(channels)), logit)

    tick = time.perf_counter()
    kept = jax.config.jax_compilation_cache_dir
    note = f"compilation cache: {kept}" if kept else f"compilation cache {cache.reason()}"
    with console.status(f"compiling the rollout and its gradient ({note})"), cache.watch() as counts:
        if not console.is_terminal:  # no spinner: say why nothing happens for a while
            console.print(f"compiling the rollout and its gradient (tens of seconds; {note})", soft_wrap=True)
            console.file.flush()
        traced = (jax.jit(evaluate).lower(z), jax.jit(jax.value_and_grad(evaluate, has_aux=True)).lower(z))
        times["compile_trace"] = time.perf_counter() - tick
        forward, loss_and_grad = (program.compile() for program in traced)
    times["compile"] = time.perf_counter() - tick
    forward = _checked(model, forward, lambda out: out[1])
    loss_and_grad = _checked(model, loss_and_grad, lambda out: out[0][1])
    loaded = (f"{counts['hits']} of {counts['requests']} programs loaded from the compilation cache" if kept
              else "compilation cache off")
    console.print(f"compiled the rollout and its gradient ({times['compile']:.1f} s: tracing "
                  f"{times['compile_trace']:.1f} s, XLA {times['compile'] - times['compile_trace']:.1f} s; "
                  f"{loaded})", soft_wrap=True)

    tick = time.perf_counter()
    initial_loss, initial = jax.block_until_ready(forward(z))  # a program without callbacks returns at once
    times["simulate"] = time.perf_counter() - tick
    console.print(f"simulated {settings.steps * settings.dt:.2f} s ({settings.steps} steps, "
                  f"{float(np.mean(initial.traj.info.iterations)):.0f} solver iterations per step) in "
                  f"{times['simulate']:.1f} s; with the initial controls the tip ends "
                  f"{_describe_error(_tip_error(initial))} from the target", soft_wrap=True)

    tick = time.perf_counter()
    history, final = optimise(loss_and_grad, forward, z, settings, console)
    times["optimise"] = time.perf_counter() - tick

    tick = time.perf_counter()
    metrics = {
        "robot": {"length_m": ARM_LENGTH, "width_m": ARM_WIDTH, "height_m": ARM_HEIGHT,
                  "muscles": channels, "muscle_stiffness_pa": MUSCLE_STIFFNESS,
                  "material": {"E_pa": YOUNG, "nu": POISSON, "density_kg_m3": DENSITY,
                               "alpha_per_s": MASS_DAMPING}},
        "mesh": {"vertices": mesh.n_vertices, "tets": mesh.n_tets, "surface_triangles": len(mesh.surface),
                 "size_m": settings.mesh_size},
        "task": {"target_m": list(TARGET), "horizon_s": settings.steps * settings.dt, "dt_s": settings.dt,
                 "steps": settings.steps, "knots": settings.knots, "effort_weight": EFFORT,
                 "tolerance": TOLERANCE},
        "optimiser": {"name": "adam", "iterations": settings.iterations,
                      "learning_rate": settings.learning_rate},
        "quick": settings == QUICK,
        "compilation_cache": {"folder": kept, "programs": counts["requests"], "loaded": counts["hits"]},
        "initial_loss": history[0],
        "final_loss": history[-1],
        "loss_ratio": history[0] / history[-1],
        "initial_tip_distance_m": _tip_error(initial),
        "final_tip_distance_m": _tip_error(final),
        "initial_tip_distance_fraction": _tip_error(initial) / ARM_LENGTH,
        "final_tip_distance_fraction": _tip_error(final) / ARM_LENGTH,
        "final_activation": dict(zip(channels, np.asarray(final.activation)[-1].tolist())),
        "solver_iterations_per_step": {"mean": float(np.mean(final.traj.info.iterations)),
                                       "max": int(np.max(final.traj.info.iterations)),
                                       "all_converged": bool(np.all(final.traj.info.converged))},
    }
    result = Result.from_mesh(mesh, np.asarray(final.traj.x), settings.dt, activation=np.asarray(final.activation),
                              channel_names=channels, loss_history=np.asarray(history),
                              obstacles=MARKERS, metadata={"demo": metrics})
    with console.status("rendering"):
        write_outputs(out, result, settings.window, force)
    times["render"] = time.perf_counter() - tick
    times["total"] = time.perf_counter() - start
    metrics["wall_time_s"] = metrics["timings"] = times
    write_metrics(out / "metrics.json", metrics, force=force)
    return metrics


def optimise(loss_and_grad, forward, z, settings: Settings, console) -> tuple[list[float], Evaluation]:
    """Adam on the knots' logits, with a progress bar.

    Arguments:
        loss_and_grad: compiled ``z -> ((loss, Evaluation), dloss/dz)``.
        forward: compiled ``z -> (loss, Evaluation)``.
        z: initial logits ``(knots, channels)``.
        settings: iterations and learning rate.
        console: where progress goes (a bar on a terminal, one line per iteration elsewhere).

    Returns:
        ``(history, final)``: the loss before each update and after the last one
        (``iterations + 1`` values), and the evaluation of the final controls.
    """
    import optax

    # b1 = 0.5: with the default 0.9 the coherent first steps overshoot the target.
    optimizer = optax.adam(optax.exponential_decay(settings.learning_rate, settings.iterations, 0.1), b1=0.5)
    opt_state = optimizer.init(z)
    history = []
    tick = time.perf_counter()
    with _progress(console) as progress:
        task = progress.add_task("optimise", total=settings.iterations, loss="-", tip="-", rate="")
        for k in range(settings.iterations):
            (loss, ev), grad = loss_and_grad(z)
            history.append(float(loss))
            updates, opt_state = optimizer.update(grad, opt_state)
            z = optax.apply_updates(z, updates)
            error = _tip_error(ev)
            progress.update(task, advance=1, loss=f"{float(loss):.4g}", tip=f"{1e3 * error:.1f} mm",
                            rate=f"{(time.perf_counter() - tick) / (k + 1):.1f} s/it")
            if not console.is_terminal:
                console.print(f"  iteration {k + 1}/{settings.iterations}: loss {float(loss):.4g}, "
                              f"tip error {_describe_error(error)}", soft_wrap=True)
    final_loss, final = forward(z)
    history.append(float(final_loss))
    return history, final


def write_outputs(out: Path, result, window: tuple[int, int], force: bool) -> None:
    """Write ``result.npz``, ``loss.png``, ``render.png`` (last frame) and ``render.mp4``.

    Renders are coloured by activation; the video plays at 10 frames per second.
    """
    from softbody.render import plot_loss, render

    result.save(out / "result.npz", force=force)
    plot_loss(result.loss_history, out / "loss.png", title="soft arm reaching", force=force)
    with warnings.catch_warnings():
        # ffmpeg is started by fork + exec, which is safe beside JAX's threads.
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        render(result, out / "render.png", color_by="activation", window_size=window, force=force)
        render(result, out / "render.mp4", color_by="activation", fps=10, window_size=window, force=force)


def _summary(metrics: dict, out: Path) -> str:
    t = metrics["wall_time_s"]
    iters = metrics["optimiser"]["iterations"]
    return "\n".join([
        f"softbody demo: soft arm ({metrics['mesh']['vertices']} vertices, {metrics['mesh']['tets']} tets, "
        f"4 muscle bands) reaching {tuple(round(c, 3) for c in metrics['task']['target_m'])} m",
        f"  loss       {metrics['initial_loss']:.4g} -> {metrics['final_loss']:.4g} "
        f"({metrics['loss_ratio']:.0f}x lower, {iters} Adam iterations)",
        f"  tip error  {_describe_error(metrics['initial_tip_distance_m'])} -> "
        f"{_describe_error(metrics['final_tip_distance_m'])}",
        f"  wall time  mesh {t['mesh']:.1f} s, compile {t['compile']:.1f} s, simulate {t['simulate']:.1f} s, "
        f"optimise {t['optimise']:.1f} s ({t['optimise'] / iters:.1f} s per iteration), "
        f"render {t['render']:.1f} s; total {t['total']:.0f} s",
        f"  wrote      {out}/{{{', '.join(OUTPUTS)}}}",
    ])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody demo``."""
    parser.add_argument("--out", type=Path, default=Path("softbody-demo"),
                        help="output folder (default softbody-demo/); must be empty or new unless --force")
    parser.add_argument("--no-view", action="store_true", help="do not open the browser viewer at the end")
    parser.add_argument("--port", type=port_number, default=8080,
                        help="viewer port (default 8080; the next free one if taken)")
    parser.add_argument("--force", action="store_true",
                        help="overwrite the demo's files in a non-empty folder")
    parser.add_argument("--quick", action="store_true",
                        help=f"a shorter task ({QUICK.steps} steps, {QUICK.iterations} iterations) "
                             "and smaller renders")


def run(args: argparse.Namespace) -> int:
    """Run ``softbody demo``; returns the exit status (0 ok, 1 refused or failed)."""
    out: Path = args.out
    if out.exists() and not out.is_dir():
        print(f"softbody demo: {out} is a file; give --out a folder", file=sys.stderr)
        return 1
    if out.is_dir() and any(out.iterdir()) and not args.force:
        print(f"softbody demo: {out} is not empty; pass --force to overwrite the demo's files in it, "
              "or choose another folder with --out", file=sys.stderr)
        return 1
    try:
        metrics = demo(out, QUICK if args.quick else FULL, force=args.force)
    except FileExistsError as err:
        print(f"softbody demo: {err}", file=sys.stderr)
        return 1
    print(_summary(metrics, out))
    if args.no_view or not sys.stdin.isatty():
        print(f"view it in the browser: softbody view {out / 'result.npz'}")
        return 0
    from softbody.viewer import view

    # gmsh's Python API leaves Ctrl-C at SIG_DFL after meshing (it never restores the handler
    # it replaced); put Python's back so that Ctrl-C stops the viewer cleanly.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    view(out / "result.npz", port=args.port, color_by="activation", block=True)
    return 0

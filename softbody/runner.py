"""``softbody run``: simulate a mesh passively under gravity and write a result file.

Command line::

    softbody run MESH.msh|MESH.vtu|EXAMPLE [--size S] --E 1e5 --nu 0.45 --density 1000
                 [--alpha 0] --dt 0.01 --steps 100 [--fixed REGION|none] [--tol 1e-4]
                 [--gravity 0 0 -9.81] -o result.npz [--force]

``EXAMPLE`` is one of :data:`softbody.meshing.EXAMPLES` (meshed on the spot, at ``--size``
when given). The clamped vertices are those of ``--fixed``; by default the mesh's
``"fixed"`` region when it has one, else none (a free body, which falls: there is no
ground here). The result (:class:`~softbody.io.Result`) holds the trajectory, the mesh's
regions and, as metadata, the material, the options, per-step solver iterations and the
wall time; view it with ``softbody view``, render it with ``softbody render``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

def _examples():
    from softbody.meshing import EXAMPLES

    return EXAMPLES


class RunError(ValueError):
    """The command line asks for something that cannot run; the message says why and what to do."""


def load_mesh(target: str, size: float | None = None):
    """The mesh named on the command line.

    Arguments:
        target: an example name (see :data:`softbody.meshing.EXAMPLES`) or a ``.msh`` /
            ``.vtu`` file.
        size: element edge length for an example, m (default: the example's own).

    Returns:
        The :class:`~softbody.meshing.TetMesh`.

    Raises:
        RunError: the target is neither an example nor an existing mesh file, or ``size``
            is given for a file.
        MeshError: the file cannot be read or the example cannot be meshed.
    """
    from softbody.meshing import EXAMPLES, load
    from softbody.meshing.io import FORMATS

    if target in EXAMPLES:
        return EXAMPLES[target]() if size is None else EXAMPLES[target](size=size)
    path = Path(target)
    if path.suffix.lower() not in FORMATS:
        raise RunError(f"{target!r} is neither an example ({', '.join(EXAMPLES)}) nor a mesh file "
                       f"({', '.join(FORMATS)}); make one with `softbody mesh ... -o mesh.msh`")
    if not path.is_file():
        raise RunError(f"no mesh file {path}")
    if size is not None:
        raise RunError("--size applies to examples only; a mesh file is used as it is "
                       "(remesh it with `softbody mesh`)")
    return load(path)


def fixed_region(mesh, name: str | None) -> str | None:
    """The region to clamp: ``name``, or ``"fixed"`` when the mesh has it and ``name`` is ``None``.

    ``"none"`` (any case) means a free body.

    Raises:
        RunError: ``name`` is not a region of the mesh (the message lists them) or has no vertices.
    """
    if name is None:
        return "fixed" if "fixed" in mesh.regions else None
    if name.lower() == "none":
        return None
    if name not in mesh.regions:
        raise RunError(f"--fixed {name}: the mesh has no region {name!r}; it has "
                       f"{', '.join(sorted(mesh.regions)) or 'no regions'} (or use --fixed none)")
    if len(mesh.regions[name].vertices) == 0:
        raise RunError(f"--fixed {name}: the region has no vertices")
    return name


def failure_message(args: argparse.Namespace, step: int, code, max_iter: int, residual: float) -> str:
    """What ``softbody run`` says when a step fails: what failed and which options to change.

    Arguments:
        args: the command's arguments.
        step: the first failing step.
        code: its :class:`~softbody._types.RESULTS` code.
        max_iter: the solver's iteration cap.
        residual: the relative force residual the step reached.

    Returns:
        The message, which names the step, what failed and the command's options that fix it.
    """
    from softbody._types import RESULTS
    from softbody.meshing import EXAMPLES

    finer = ("a smaller --size" if args.mesh in EXAMPLES
             else "remesh it finer with `softbody mesh ... --size`")
    load = (f"lower --gravity, raise --E (now {args.E:g} Pa), refine the mesh ({finer}) "
            f"or reduce --dt (now {args.dt:g} s)")
    if code == RESULTS.max_iterations:
        what = (f"the solver stopped at its cap of {max_iter} iterations with a relative force residual of "
                f"{residual:.2g} > --tol {args.tol:g}. Loosen --tol or reduce --dt (now {args.dt:g} s)")
    elif code == RESULTS.nonfinite:
        what = f"the positions became non-finite (NaN/inf): the load is too large for the step. To fix it, {load}"
    elif code == RESULTS.inverted:
        what = f"tets inverted (det F <= 0): the body deforms more than the mesh resolves. To fix it, {load}"
    else:
        what = code.message
    return f"step {step}: {what}. Nothing was written."


def simulate(args: argparse.Namespace) -> tuple[object, dict]:
    """Mesh or load, build and simulate what ``args`` describe.

    Returns:
        ``(result, summary)``: the :class:`~softbody.io.Result` and a dict of figures
        (iterations per step, wall times) that is also its metadata.

    Raises:
        RunError, MeshError, ValueError: bad input (unknown mesh, region, material or option).
        SimulationError: a step stopped at the iteration cap, became non-finite or inverted
            tets (nothing is written then); the message names the command's options to change.
    """
    from softbody import progress
    from softbody._types import RESULTS
    from softbody.io import Result
    from softbody.material import Material
    from softbody.model import Options, build, initial_state
    from softbody.scene import SoftBody
    from softbody.simulate import SimulationError, rollout

    if args.steps < 1:
        raise RunError(f"--steps must be at least 1, got {args.steps}")
    start = time.perf_counter()
    with progress.task(f"meshing {args.mesh}" if args.mesh in _examples() else f"loading {args.mesh}"):
        mesh = load_mesh(args.mesh, args.size)
    mesh_s = time.perf_counter() - start
    fixed = fixed_region(mesh, args.fixed)
    material = Material(E=args.E, nu=args.nu, density=args.density, alpha=args.alpha)
    options = Options(dt=args.dt, tol=args.tol, gravity=tuple(args.gravity))
    with progress.task(f"building the model ({mesh.n_vertices} vertices, {mesh.n_tets} tets)"):
        model, params = build(SoftBody(mesh, material, fixed=fixed), options=options)

    # The rollout is one compiled program (a lax.scan): it cannot report per step without a
    # host callback, which would keep it out of the compilation cache; progress.compiling
    # reports around it instead (a "still ..." line every ~10 s on a pipe).
    solver = type(model.linear_solver).__name__
    tick = time.perf_counter()
    with progress.compiling(f"compiling and simulating {args.steps} steps ({solver})",
                            key=f"run/{args.mesh}/{mesh.n_vertices}/{mesh.n_tets}/{args.steps}/{args.dt:g}/{args.tol:g}",
                            cached=not model.linear_solver.host_callback):
        traj = rollout(model, params, initial_state(model, params), n_steps=args.steps, throw=False)
        traj.x.block_until_ready()  # the wait belongs inside the report
    codes = np.asarray(traj.info.result)
    if np.any(codes != RESULTS.success):
        step = int(np.argmax(codes != RESULTS.success))
        raise SimulationError(failure_message(args, step, RESULTS(int(codes[step])), model.options.max_iter,
                                              float(traj.info.residual[step])))
    x = np.asarray(traj.x)
    simulate_s = time.perf_counter() - tick
    iterations = np.asarray(traj.info.iterations)
    summary = {
        "mesh": {"source": args.mesh, "vertices": mesh.n_vertices, "tets": mesh.n_tets},
        "material": {"E": args.E, "nu": args.nu, "density": args.density, "alpha": args.alpha},
        "options": {"dt": args.dt, "steps": args.steps, "tol": args.tol, "gravity": list(args.gravity),
                    "fixed": fixed},
        "iterations_per_step": iterations.tolist(),
        "wall_time_s": {"mesh": mesh_s, "simulate_with_compile": simulate_s},
    }
    return Result.from_mesh(mesh, x, args.dt, metadata=summary), summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody run``."""
    parser.add_argument("mesh", help="a mesh file (.msh or .vtu, e.g. from `softbody mesh`) "
                                     "or an example name")
    parser.add_argument("--size", type=float, default=None, help="element edge length of an example, m")
    parser.add_argument("--E", type=float, default=1e5, help="Young's modulus, Pa (default 1e5)")
    parser.add_argument("--nu", type=float, default=0.45, help="Poisson's ratio (default 0.45)")
    parser.add_argument("--density", type=float, default=1000.0, help="density, kg/m^3 (default 1000)")
    parser.add_argument("--alpha", type=float, default=0.0, help="mass-proportional damping, 1/s (default 0)")
    parser.add_argument("--dt", type=float, default=0.01, help="time step, s (default 0.01)")
    parser.add_argument("--steps", type=int, default=100, help="number of time steps (default 100)")
    parser.add_argument("--fixed", default=None,
                        help="region whose vertices are clamped (default: 'fixed' if the mesh has it; "
                             "'none' for a free body)")
    parser.add_argument("--tol", type=float, default=1e-4,
                        help="relative force tolerance per step (default 1e-4)")
    parser.add_argument("--gravity", type=float, nargs=3, default=(0.0, 0.0, -9.81),
                        metavar=("GX", "GY", "GZ"), help="gravity, m/s^2 (default 0 0 -9.81)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="result file to write (.npz)")
    parser.add_argument("--force", action="store_true", help="overwrite the result file if it exists")


def run(args: argparse.Namespace) -> int:
    """Run ``softbody run``; returns the exit status (0 ok, 1 bad input or a failed simulation)."""
    from softbody import progress

    out: Path = args.output
    progress.say(f"softbody run {args.mesh}: {args.steps} steps of {args.dt:g} s -> {out}")
    from softbody.io import check_overwrite
    from softbody.meshing import MeshError
    from softbody.simulate import SimulationError

    try:
        if out.suffix != ".npz":
            raise RunError(f"-o {out}: result files end in .npz")
        check_overwrite(out, args.force)
        result, summary = simulate(args)
        result.save(out, force=args.force)
    except (RunError, MeshError, ValueError, FileExistsError, SimulationError) as err:
        print(f"softbody run: {err}", file=sys.stderr)
        return 1
    its = np.asarray(summary["iterations_per_step"])
    t = summary["wall_time_s"]
    opts = summary["options"]
    print(f"mesh: {summary['mesh']['vertices']} vertices, {summary['mesh']['tets']} tets; "
          f"clamped: {opts['fixed'] or 'nothing (free body)'}")
    print(f"solver iterations per step: mean {its.mean():.1f}, min {its.min()}, max {its.max()}; "
          "every step converged")
    print(f"simulated {opts['steps']} steps ({opts['steps'] * opts['dt']:.3g} s) in "
          f"{t['simulate_with_compile']:.1f} s wall time, compilation included "
          f"(meshing/loading {t['mesh']:.1f} s)")
    print(f"wrote {out}", flush=True)
    return 0

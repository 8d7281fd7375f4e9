"""Throughput of the batched environment: one ``jit(vmap(step))`` over N environments
against N single ``jit(step)`` calls in a Python loop.

Scenes: ``crawler`` is the caterpillar of ``examples/crawler.py`` (78 vertices, 144 tets,
8 muscle channels) on a friction plane, so every step runs the contact iteration;
``pendulum`` is a two-link skeleton in a soft skin (20 vertices, a joint torque and a
servo, no contact). Each environment starts from the rest shape with reset noise and
takes random actions; the same states and actions go through both paths.

Compile time (the first call, minus one run) is reported apart from run time; run times
are medians over ``--repeats`` repeats of one batched step and of ``N`` looped single
steps. Also reported: the solver iterations per step in the batch (a batched ``while``
loop runs until its slowest member converges, so the batch pays the maximum where the
loop pays the mean), the time of ``prepare`` (the PD matrix's factorisation, done once per
batch but once per call in the loop), and the shapes of the triangular solves in the
batched program (whether the batch's right-hand sides share one solve).

Run on one core of the 2-core machine::

    OPENBLAS_NUM_THREADS=1 taskset -c 1 python examples/rl_throughput.py --scene crawler

The script makes no assumption about the device: on a GPU it runs unchanged (JAX's
default device), ``--out DIR`` writes ``DIR/rl_throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import softbody  # noqa: F401  (float64)
from softbody.control import env as E
from softbody.model import prepare

sys.path.insert(0, str(Path(__file__).resolve().parent))


def crawler_env(episode_length: int):
    from crawler import caterpillar

    _, model, params = caterpillar()
    # Activations in [0, 0.5] as in examples/crawler.py; velocity noise only (position noise
    # would push bottom vertices into the ground).
    env = E.Env(model, params, observation=E.Positions(model, "xmax"), reward=E.Progress(model) + 0.01 * E.ActionPenalty(),
                action_map=E.ActionMap(model, low=0.0, high=0.5), episode_length=episode_length,
                reset_noise=E.ResetNoise(velocity=1e-3))
    return env


def pendulum_env(episode_length: int):
    from softbody.actuators.joints import JointServo, JointTorque
    from softbody.material import Material
    from softbody.meshing import Region
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build
    from softbody.scene import SoftBody
    from softbody.skeleton import Link, Revolute, Skeleton

    mesh = grid_box((0.08, 0.02, 0.02), (4, 1, 1))
    x = mesh.points[:, 0]

    def bone(lo, hi):
        inside = (x >= lo - 1e-9) & (x <= hi + 1e-9)
        return Region(np.flatnonzero(inside), np.flatnonzero(inside[mesh.tets].all(axis=1)))

    mesh = mesh.with_regions(**{"bone:upper": bone(0.0, 0.02), "bone:fore": bone(0.06, 0.08)})
    skeleton = Skeleton([Link("upper", "bone:upper", None, Revolute((0.0, 1.0, 0.0), (0.0, 0.01, 0.01))),
                         Link("fore", "bone:fore", "upper", Revolute((0.0, 1.0, 0.0), (0.05, 0.01, 0.01)))])
    model, params = build(SoftBody(mesh, Material(E=2e4, nu=0.3, density=1000.0)), skeleton=skeleton,
                          actuators=[JointTorque(["upper"]), JointServo(["fore"], stiffness=0.05)],
                          options=Options(dt=0.01, tol=1e-6, max_iter=500))
    return E.Env(model, params, observation=E.JointAngles(model), reward=E.Height(model, "xmax"),
                 action_map=E.ActionMap(model, low=[-2e-3, -0.5], high=[2e-3, 0.5]), episode_length=episode_length,
                 reset_noise=E.ResetNoise(joint=0.05))


def _block(tree):
    return jax.block_until_ready(tree)


def _timed(fn, *args):
    start = time.perf_counter()
    out = _block(fn(*args))
    return time.perf_counter() - start, out


def solve_shapes(fn, *args) -> list[str]:
    """The result shapes of the triangular solves in ``fn``'s program (its jaxpr): a batch
    that shares one factor solves ``(n, b * k)`` at once, a batched factor ``(b, n, k)``."""
    text = str(jax.make_jaxpr(fn)(*args))
    return sorted(set(re.findall(r"(f64\[[\d,]+\]) = triangular_solve", text)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", choices=("crawler", "pendulum"), default="crawler")
    parser.add_argument("--envs", type=int, default=256, help="environments in the batch (and single steps looped)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (median)")
    parser.add_argument("--out", type=Path, default=None, help="folder for rl_throughput.json")
    args = parser.parse_args(argv)
    n = args.envs

    env = (crawler_env if args.scene == "crawler" else pendulum_env)(episode_length=1000)
    model = env.model
    device = jax.devices()[0]
    print(f"{args.scene}: {model.n_vertices} vertices, {model.n_tets} tets, {env.action_size} actions, "
          f"linear solver {type(model.linear_solver).__name__}, contact {model.has_contact}; "
          f"device {device.platform} ({device.device_kind}); {n} environments")

    keys = jax.random.split(jax.random.PRNGKey(0), n)
    _, states = env.batch_reset(keys)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (n, env.action_size), minval=-1.0, maxval=1.0)
    # One warm-up step each so that the states move (the first step from rest is the easiest).
    batched = jax.jit(jax.vmap(env._step, in_axes=(0, 0, 0, None)))
    single = jax.jit(env._step)
    params = env.params

    first_batch, out = _timed(batched, keys, states, actions, params)
    run_batch, out = _timed(batched, keys, states, actions, params)
    compile_batch = first_batch - run_batch
    states = out[1]
    per_env = [jax.tree.map(lambda a, i=i: a[i], states) for i in range(n)]
    first_single, _ = _timed(single, keys[0], per_env[0], actions[0], params)
    run_one, _ = _timed(single, keys[0], per_env[0], actions[0], params)
    compile_single = first_single - run_one

    batch_times, loop_times = [], []
    for _ in range(args.repeats):
        t, out = _timed(batched, keys, states, actions, params)
        batch_times.append(t)
        start = time.perf_counter()
        results = [single(keys[i], per_env[i], actions[i], params) for i in range(n)]
        _block(results)
        loop_times.append(time.perf_counter() - start)
    iterations = np.asarray(out[4]["iterations"])
    codes = np.asarray(out[4]["result"])
    loop_iterations = np.asarray([int(r[4]["iterations"]) for r in results])
    # The batch's results equal the loop's (same states, actions, keys).
    agree = max(float(jnp.abs(out[0][i] - results[i][0]).max()) for i in range(n))

    prep = jax.jit(lambda p: prepare(model, p))
    _timed(prep, params)
    prep_times = [_timed(prep, params)[0] for _ in range(args.repeats)]
    batch, loop = statistics.median(batch_times), statistics.median(loop_times)
    shapes = solve_shapes(jax.vmap(env._step, in_axes=(0, 0, 0, None)), keys, states, actions, params)
    single_shapes = solve_shapes(env._step, keys[0], per_env[0], actions[0], params)

    metrics = {
        "scene": args.scene, "environments": n, "device": f"{device.platform} ({device.device_kind})",
        "vertices": model.n_vertices, "tets": model.n_tets, "linear_solver": type(model.linear_solver).__name__,
        "compile_batched_s": compile_batch, "compile_single_s": compile_single,
        "batched_step_s": batch, "loop_of_single_steps_s": loop, "ratio": loop / batch,
        "batched_steps_per_s": n / batch, "looped_steps_per_s": n / loop,
        "batched_times_s": batch_times, "loop_times_s": loop_times,
        "prepare_s": statistics.median(prep_times),
        "iterations_batch_max": int(iterations.max()), "iterations_mean": float(loop_iterations.mean()),
        "triangular_solve_shapes_batched": shapes, "triangular_solve_shapes_single": single_shapes,
        "max_obs_difference_batch_vs_loop": agree, "steps_not_converged_in_batch": int(np.sum(codes != 0)),
    }
    print(f"compile: batched {compile_batch:.1f} s, single {compile_single:.1f} s")
    print(f"run (median of {args.repeats}): one batched step of {n} environments {batch * 1e3:.1f} ms, "
          f"{n} single steps in a loop {loop * 1e3:.1f} ms: ratio {loop / batch:.2f}x "
          f"({n / batch:.0f} vs {n / loop:.0f} env-steps/s)")
    print(f"solver iterations per step: mean {loop_iterations.mean():.1f} (loop pays this), "
          f"max {iterations.max()} (the batched while loop runs this many)")
    print(f"prepare (factorisation) {metrics['prepare_s'] * 1e3:.2f} ms per call: once per batch, "
          f"{n} times in the loop ({n * metrics['prepare_s'] * 1e3:.0f} ms)")
    print(f"triangular solves: batched {shapes}, single {single_shapes}")
    print(f"batch vs loop observations agree to {agree:.1e}; steps of the batch that did not succeed: "
          f"{int(np.sum(codes != 0))} of {n}")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "rl_throughput.json").write_text(json.dumps(metrics, indent=2))
        print(f"wrote {args.out / 'rl_throughput.json'}")
    return metrics


if __name__ == "__main__":
    main()

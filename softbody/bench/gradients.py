"""Gradient cost, accuracy and memory on the shared DiffPD cantilever.

* ``backward_s_per_frame``: the :class:`~softbody.gradients.Implicit` adjoint's backward
  pass per frame for DiffPD's loss ``w_q . q_T + w_v . v_T`` (25 frames, forward
  tolerance 1e-4 as DiffPD's 0.35 s/frame figure), i.e. (time of value-and-gradient -
  time of the forward rollout) / frames, medians, compile excluded; ``Unrolled`` beside it.
* ``fd_rel_error``: max over parameter kinds (log E, nu, density, initial positions and
  velocities, muscle activations, external forces) of the relative error between the
  Implicit gradient's directional derivative along its own direction and central finite
  differences, at forward tolerance 1e-10, on the first 5 frames.
* Memory: peak RSS (``ru_maxrss``, measured in a child process per run) and time of a
  gradient against the horizon (50 ... 5000 steps) for ``Implicit``, ``Unrolled``
  (checkpointed steps, segments and iterations) and ``Unrolled`` without any
  checkpointing (plain autodiff through the iterations), on the same 2673-vertex mesh,
  the unrolled modes with ``max_iter`` = 150 (their tape holds ``max_iter`` trips a step); ``peak_rss_mb_1000_steps`` is Implicit's.
  A child is stopped at half the machine's memory (16 GB at most) or 30 minutes, and a
  horizon predicted (linearly from the previous one) to take longer is not started; the
  table records which and why.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softbody.bench import median_seconds
from softbody.bench.pd_cantilever import DIFFPD, load_scene, loss_of


#: iteration cap for the unrolled modes: their tape holds ``max_iter`` loop trips per step,
#: run or skipped. The scene needs at most 113 iterations per step (72 on average).
UNROLLED_MAX_ITER = 150


def _scene(adjoint: str):
    """The shared cantilever at tolerance 1e-4 with the named differentiation mode."""
    from softbody.gradients import Implicit, Unrolled

    if adjoint == "implicit":
        return load_scene(tol=1e-4, adjoint=Implicit())
    mode = {"unrolled": Unrolled(), "plain": Unrolled(segment_checkpoints=False, remat=False)}[adjoint]
    return load_scene(tol=1e-4, adjoint=mode, max_iter=UNROLLED_MAX_ITER)


def _loss_fn(model, params, state0, controls, forces, scene):
    from softbody.simulate import rollout

    def loss(controls):
        return loss_of(rollout(model, params, state0, controls=controls, forces=forces), scene)

    return loss


def backward_cost(adjoint: str, repeats: int) -> dict:
    """Forward and backward seconds per frame on the 25-frame scene at tolerance 1e-4."""
    model, params, state0, controls, forces, scene = _scene(adjoint)
    loss = _loss_fn(model, params, state0, controls, forces, scene)
    frames = controls.shape[0]
    forward = median_seconds(jax.jit(loss), controls, repeats=repeats)
    both = median_seconds(jax.jit(jax.value_and_grad(loss)), controls, repeats=repeats)
    return {"forward_s_per_frame": forward / frames, "backward_s_per_frame": max(both - forward, 0.0) / frames}


def fd_errors(frames: int = 5, eps: float = 1e-3) -> dict:
    """Relative errors of Implicit gradients vs central differences, per parameter kind.

    For each kind, the directional derivative along that kind's normalised gradient (which
    is ``|g_kind|``) against Richardson-extrapolated central differences at ``eps`` and
    ``eps / 2`` (forward tolerance 1e-10, first ``frames`` frames).
    """
    from softbody.gradients import central_difference
    from softbody.model import State
    from softbody.simulate import rollout

    model, params, state0, controls, forces, scene = load_scene(tol=1e-10, atol=0.0)
    controls, forces = controls[:frames], forces[:frames]
    theta = {"logE": jnp.log(params.E), "nu": params.nu, "density": params.density / 1000,
             "x0": state0.x, "v0": state0.v, "activation": controls, "force": forces}

    def loss(th):
        p = params.replace(E=jnp.exp(th["logE"]), nu=th["nu"], density=th["density"] * 1000)
        s0 = State(x=th["x0"], v=th["v0"], rot=state0.rot, t=state0.t)
        return loss_of(rollout(model, p, s0, controls=th["activation"], forces=th["force"]), scene)

    # Along each kind's own gradient direction the derivative is largest (|g_kind|), so the
    # forward solve's stopping noise (~1e-6 absolute in the differences at eps = 1e-3) is
    # small beside it; a random direction over thousands of entries (check_grad's) sees
    # ~|g_kind| / sqrt(entries): 1.3e-4 for v0 here, where that noise reads as 5 % error.
    value_and_grad, forward = jax.jit(jax.value_and_grad(loss)), jax.jit(loss)
    _, grad = value_and_grad(theta)
    errors = {}
    for kind in theta:
        norm = float(jnp.sqrt(jnp.sum(grad[kind] ** 2)))
        direction = {j: (grad[j] / norm if j == kind else jnp.zeros_like(theta[j])) for j in theta}
        fd = central_difference(forward, theta, direction, eps)
        errors[kind] = abs(norm - fd) / abs(fd)
    return errors


def _child(adjoint: str, horizon: int) -> None:
    """Run in a fresh process: gradient over ``horizon`` steps; print time and peak RSS."""
    import resource

    model, params, state0, controls, forces, scene = _scene(adjoint)
    controls = jnp.broadcast_to(controls[0], (horizon, controls.shape[1]))
    forces = jnp.broadcast_to(forces[0], (horizon,) + forces.shape[1:])
    loss = _loss_fn(model, params, state0, controls, forces, scene)
    t0 = time.perf_counter()
    grad = jax.jit(jax.grad(loss)).lower(controls).compile()  # compiled once, run once
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    g = jax.block_until_ready(grad(controls))
    run = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"adjoint": adjoint, "horizon": horizon, "gradient_s": run, "compile_s": compile_s,
                      "peak_rss_mb": rss, "finite": bool(np.all(np.isfinite(np.asarray(g))))}))


def _memory_cap_mb() -> float:
    """Children are stopped past half the machine's memory (16 GB at most): no swapping."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**20
    except (ValueError, OSError, AttributeError):
        total = 8192.0
    return min(0.5 * total, 16384.0)


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _watch(cmd: list[str], timeout: float, cap_mb: float) -> tuple[str | None, float, str, str]:
    """Run ``cmd``; stop it past ``timeout`` seconds or ``cap_mb`` resident MB.

    Returns ``(why_stopped or None, peak resident MB seen by polling, stdout, stderr)``.
    """
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0, why, peak = time.perf_counter(), None, 0.0
    while proc.poll() is None:
        peak = max(peak, _rss_mb(proc.pid) or 0.0)
        elapsed = time.perf_counter() - t0
        if peak > cap_mb:
            why = f"out of memory: resident set over the {cap_mb:.0f} MB cap after {elapsed:.0f} s (stopped)"
        elif elapsed > timeout:
            why = f"over {timeout:.0f} s (stopped)"
        if why:
            proc.kill()
            break
        time.sleep(0.2)
    stdout, stderr = proc.communicate()
    return why, peak, stdout, stderr


def memory_table(horizons, adjoints, timeout: float, cap_mb: float | None = None) -> list[dict]:
    """Peak RSS and gradient time per (adjoint, horizon), each in a fresh child process.

    A child is stopped past ``timeout`` seconds or ``cap_mb`` resident megabytes, and a
    horizon whose time, scaled linearly from the previous one, would exceed ``timeout`` is
    not started; either ends that adjoint's row with the reason.
    """
    from softbody import progress

    cap_mb = _memory_cap_mb() if cap_mb is None else cap_mb
    rows = []
    for adjoint in adjoints:
        previous = None
        for horizon in horizons:
            if previous is not None:
                estimate = (previous["gradient_s"] + previous["compile_s"]) * horizon / previous["horizon"]
                if estimate > timeout:
                    rows.append({"adjoint": adjoint, "horizon": horizon, "error": (
                        f"not run: ~{estimate:.0f} s scaled from {previous['horizon']} steps, "
                        f"over the {timeout:.0f} s limit")})
                    break
            cmd = [sys.executable, "-m", "softbody.bench.gradients", adjoint, str(horizon)]
            progress.say(f"gradients: memory table: {adjoint}, {horizon} steps, in a child process ...")
            why, peak, stdout, stderr = _watch(cmd, timeout, cap_mb)
            lines = [line for line in stdout.splitlines() if line.startswith("{")]
            if why is None and not lines:
                why = (stderr.strip().splitlines() or ["failed"])[-1][:200]
            row = ({"adjoint": adjoint, "horizon": horizon, "error": why, "rss_mb_when_stopped": peak}
                   if why is not None else json.loads(lines[-1]))
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)  # progress of a long table
            progress.say(f"gradients: memory table: {adjoint}, {horizon} steps: " + (
                f"stopped ({why})" if why is not None else
                f"{row.get('peak_rss_mb', float('nan')):.0f} MB peak, gradient {row.get('gradient_s', float('nan')):.2f} s"))
            if why is not None:
                break  # longer horizons will not fare better
            previous = row
    return rows


def run(out: Path, quick: bool) -> dict:
    repeats = 2 if quick else 3
    horizons = [50, 100] if quick else [50, 100, 500, 1000, 5000]
    from softbody import progress

    rows = memory_table(horizons, ["implicit", "unrolled", "plain"], timeout=600 if quick else 1800)
    with progress.task("gradients: backward cost, implicit adjoint"):
        implicit = backward_cost("implicit", repeats)
    with progress.task("gradients: backward cost, unrolled"):
        unrolled = backward_cost("unrolled", 1)  # ~12 s per frame: one timed run
    with progress.task("gradients: finite-difference check"):
        errors = fd_errors()
    rss_1000 = next((r["peak_rss_mb"] for r in rows if r.get("adjoint") == "implicit"
                     and r.get("horizon") == 1000 and "peak_rss_mb" in r), None)
    figures = {
        "backward_s_per_frame": implicit["backward_s_per_frame"],
        "forward_s_per_frame": implicit["forward_s_per_frame"],
        "unrolled_backward_s_per_frame": unrolled["backward_s_per_frame"],
        "unrolled_forward_s_per_frame": unrolled["forward_s_per_frame"],
        "fd_rel_error": max(errors.values()),
        "fd_rel_error_by_kind": errors,
        "peak_rss_mb_1000_steps": rss_1000,
        "memory_table": rows,
        "diffpd_backward_s_per_frame": DIFFPD["backward_s_per_frame"],
    }
    _plot(out / "gradients.png", rows)
    return figures


def _plot(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    labels = {"implicit": "Implicit", "unrolled": "Unrolled (checkpointed)", "plain": "Unrolled, no checkpoints"}
    for adjoint, label in labels.items():
        ok = [r for r in rows if r.get("adjoint") == adjoint and "peak_rss_mb" in r]
        if ok:
            h = [r["horizon"] for r in ok]
            a.loglog(h, [r["peak_rss_mb"] for r in ok], "o-", label=label)
            b.loglog(h, [r["gradient_s"] for r in ok], "o-", label=label)
        for r in rows:
            if r.get("adjoint") == adjoint and "out of memory" in r.get("error", "").lower():
                a.loglog([r["horizon"]], [r["rss_mb_when_stopped"]], "x", ms=10, color="k")
                a.annotate(f" {label}: out of memory", (r["horizon"], r["rss_mb_when_stopped"]), fontsize=8)
    a.set_xlabel("steps")
    a.set_ylabel("peak RSS of the process, MB")
    b.set_xlabel("steps")
    b.set_ylabel("gradient wall time, s (compile excluded)")
    a.legend()
    a.set_title("2673-vertex cantilever, tol 1e-4")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    _child(sys.argv[1], int(sys.argv[2]))

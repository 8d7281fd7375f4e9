"""Reinforcement learning on the soft crawler: PPO, SAC and SAC with the simulation's
one-step Jacobians, on the same number of simulated steps, beside trajectory optimisation.

The body, muscles and ground are ``examples/crawler.py``'s (78 vertices, 144 tets, 8
muscle channels with activations in [0, 0.5], Coulomb friction 0.8 / 0.6). The
environment (:mod:`softbody.control.env`): episodes of 50 steps (0.5 s, trajectory
optimisation's training horizon) from rest with velocity noise 1e-3 m/s; the reward is
the centroid's progress along +x in mm per step minus 0.01 times the squared action;
the observation the positions (relative to the episode's start, in cm) and velocities
(in 0.1 m/s) of the front face's vertices (``Positions(model, "xmax")``).

Agents (:mod:`softbody.control.rl`), each on ``--steps`` simulated steps (default 2000 =
trajectory optimisation's 40 simulations of 50 steps; its gradients are not counted):

* ``ppo_rejax``: rejax's PPO (one environment, rollouts of 50 steps, 4 epochs of 2
  minibatches);
* ``sac``: SAC (warm-up 200 random steps, one gradient step per sample);
* ``sac_policy_enhancement``: SAC with the actor's action gradient through the one-step
  model (one forward-mode Jacobian per sample, contact set held fixed);
* ``sac_sample_enhancement``: SAC with 2 virtual samples per real one, each checked for a
  contact switch by simulating it (discarded where the contact set changes).

Each trained deterministic policy then runs 2 s (200 steps) from rest without noise; the
figure is the centroid's distance along +x in body lengths, beside trajectory
optimisation's gait after its 40 simulations (read from ``examples/README.md``'s measured
row of ``crawler.py``).

Run::

    python examples/rl_crawler.py --out results/rl_crawler [--steps 2000] [--agents sac ppo_rejax]

``--steps 200`` is a small budget for a smoke test. Writes ``metrics.json``
(``distance_body_lengths`` per agent, ``trajectory_optimisation_body_lengths``,
``simulated_steps``, ``virtual_samples_kept``, wall times) and ``training.png`` (episode
returns during training).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax
import numpy as np
from softbody.control import env as E
from softbody.control import rl

from softbody import progress
from softbody.io import check_overwrite, write_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
from crawler import A_MAX, LENGTH, caterpillar

AGENTS = ("ppo_rejax", "sac", "sac_policy_enhancement", "sac_sample_enhancement")
EPISODE, EVAL_STEPS = 50, 200


def crawler_env(model, params, *, training: bool = True):
    """The crawler's environment: training episodes (50 steps, reset noise, reward in mm
    per step with the action penalty) or the 2 s evaluation (no noise, reward in m)."""
    common = {"observation": E.Positions(model, "xmax"), "action_map": E.ActionMap(model, low=0.0, high=A_MAX)}
    if training:
        reward = 1e3 * E.Progress(model) + 0.01 * E.ActionPenalty()
        return E.Env(model, params, reward=reward, episode_length=EPISODE, reset_noise=E.ResetNoise(velocity=1e-3),
                     **common)
    return E.Env(model, params, reward=E.Progress(model), episode_length=EVAL_STEPS, **common)


def trajectory_optimisation_figure(readme: Path) -> float | None:
    """Trajectory optimisation's body lengths after 40 simulations, from the measured
    ``crawler.py`` row of ``examples/README.md`` (``None`` where it is not found)."""
    text = readme.read_text() if readme.exists() else ""
    found = re.search(r"\| `crawler\.py` \| ([0-9.]+) body lengths in 2 s after 40 gradient simulations", text)
    return float(found.group(1)) if found else None


def train_agent(name: str, env, steps: int, seed: int):
    """Train one agent; returns ``(policy(obs) -> action, training returns, extra figures)``."""
    if name == "ppo_rejax":
        n_steps = EPISODE
        total = max(n_steps, steps // n_steps * n_steps)
        algo, train = rl.ppo(env, total, eval_every=total, num_envs=1, num_steps=n_steps, num_minibatches=2)
        ts, returns = jax.jit(train)(jax.random.PRNGKey(seed))
        return rl.ppo_policy(algo, ts), np.asarray(returns)[:, 0].tolist(), {"simulated_steps": total}
    options = {"sac": {}, "sac_policy_enhancement": {"policy_enhancement": True},
               "sac_sample_enhancement": {"virtual_samples": 2}}[name]
    agent = rl.SAC(env, rl.SACConfig(warmup=min(200, steps // 2), buffer_size=max(steps * 3, 256), **options))
    state = agent.init(seed)
    state, (rewards, dones) = agent.train(state, steps)
    r, d = np.asarray(rewards)[:, 0], np.asarray(dones)[:, 0]
    ends = np.flatnonzero(d)
    returns = [float(r[a + 1:b + 1].sum()) for a, b in zip(np.r_[-1, ends[:-1]], ends)]
    return state.actor.deterministic, returns, {"simulated_steps": steps, "virtual_samples_kept": int(state.virtual)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--steps", type=int, default=2000,
                        help="simulated steps per agent (default 2000 = trajectory optimisation's 40 x 50)")
    parser.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    parser.add_argument("--seed", type=int, default=0, help="the agents' seed")
    args = parser.parse_args(argv)
    if args.steps < EPISODE:
        parser.error(f"--steps must be at least one episode ({EPISODE})")
    check_overwrite(args.out / "metrics.json", args.force)
    start = time.perf_counter()

    with progress.task("meshing and building the caterpillar"):
        _, model, params = caterpillar()
    env, evaluation = crawler_env(model, params), crawler_env(model, params, training=False)
    distances, returns, walls, extra = {}, {}, {}, {}
    for name in args.agents:
        with progress.task(f"{name}: {args.steps} simulated steps (compiles first)"):
            t0 = time.perf_counter()
            policy, returns[name], extra[name] = train_agent(name, env, args.steps, args.seed)
            walls[name] = time.perf_counter() - t0
        with progress.task(f"{name}: the deterministic policy for {EVAL_STEPS} steps"):
            d = float(jax.jit(lambda k, p=policy: rl.evaluate_policy(evaluation, p, k, 1))(jax.random.PRNGKey(9))[0])
        distances[name] = d / LENGTH
        progress.say(f"{name}: {distances[name]:.3f} body lengths in {EVAL_STEPS * 0.01:.0f} s "
                     f"({walls[name]:.0f} s training)")
    reference = trajectory_optimisation_figure(Path(__file__).resolve().parent / "README.md")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, rs in returns.items():
        if name == "ppo_rejax":
            continue  # rejax reports its evaluations only (initial and final)
        ax.plot(np.arange(1, len(rs) + 1) * EPISODE, rs, ".-", label=name.replace("_", " "))
    ax.set_xlabel("simulated steps")
    ax.set_ylabel("training episode return (mm forward, 0.5 s)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "training.png", dpi=120)
    plt.close(fig)

    metrics = {
        "distance_body_lengths": distances, "evaluation_seconds": EVAL_STEPS * 0.01,
        "trajectory_optimisation_body_lengths": reference, "trajectory_optimisation_simulations": 40,
        "simulated_steps": {k: v["simulated_steps"] for k, v in extra.items()},
        "virtual_samples_kept": {k: v["virtual_samples_kept"] for k, v in extra.items() if "virtual_samples_kept" in v},
        "training_returns": returns, "training_wall_time_s": walls, "seed": args.seed,
        "wall_time_s": time.perf_counter() - start,
    }
    write_metrics(args.out / "metrics.json", metrics, force=args.force)
    print(f"wrote {args.out / 'metrics.json'} ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

"""Reinforcement learning with simulation gradients on an N-link pendulum (after Qiao et
al., ICML 2021): SAC, SAC + sample enhancement, SAC + policy enhancement
(:mod:`softbody.control.rl`) and rejax's PPO, best relative reward against training
samples.

The scene (:func:`pendulum_env`): a chain of ``n`` rigid 20 mm cubes (bones) joined by
20 mm soft cubes (E = 2 kPa, nu = 0.3, 1000 kg/m^3), ``2 n - 1`` cells in a row; link
``i`` hinges on its parent (the root on the world) about ``z`` at the middle of the soft
cell before it, and a joint torque drives every joint. Gravity points along ``+x``, so
the chain starts hanging (joint noise 0.05 rad); dt = 0.01 s, tolerance 1e-6, episodes
of 100 frames (1 s). Reward per frame: the tip face's height above the root pivot over
the chain's length (-1 hanging, +1 upright). Torque range ``+-tau`` per joint, ``tau``
the gravity torque of the straight chain held horizontal about the root. Observation:
the joint angles and rates.

Measured: each agent's deterministic policy (the mean action) is evaluated for one
episode after every training epoch of 100 samples (its own reset noise per seed). The
relative reward of an episode is ``(R / 100 + 1) / 2`` (0 hanging still, 1 upright the
whole episode); the curves are the best relative reward so far against training samples,
median and interquartile range over seeds. ``samples_ratio_to_sac_final[agent][n]``:
the samples at which the agent's median curve first reaches SAC's final median best
relative reward, over the samples at which SAC's does (``null`` where the agent never
reaches it within the budget; SAC's own is 1). ``cost_ms_per_sample`` is each agent's
wall time per training sample on the benchmark's machine (compile excluded; one
evaluation episode per 100 samples included, as it runs in the same compiled program;
all seeds batched by ``vmap`` and divided by their number); ``compile_s`` the first
epoch's wall time (compiling, the first epoch's training and evaluation).

Agents: SAC (2 x 64 tanh layers, Adam 1e-3, batch 128, gamma 0.99, 200 warm-up
samples of random actions, one gradient step per sample, learned temperature); sample
enhancement stores 4 virtual samples per real one (action offsets of standard deviation
0.1); policy enhancement takes the actor's action gradient through the one-step model;
PPO is rejax 0.1.3's (4 environments x 25 steps per rollout = one epoch, 4 epochs of 4
minibatches, Adam 3e-4, observation normalisation, 2 x 64 tanh layers).

What runs (it does not fit the paper's budget, 100 x n epochs for n = 1..5 links with 5
seeds, in an hour of one core; see ``docs/rl.md`` for the measured costs):

* full: n = 1 and 2 links, 5 seeds, 50 x n epochs of 100 samples (half the paper's
  budget per link count);
* ``--quick``: n = 1 link, 1 seed, 3 epochs (a smoke test: the curves mean nothing).

The JSON holds ``samples_ratio_to_sac_final``, ``curves`` (per agent and link count:
``samples``, ``median``, ``q25``, ``q75`` of the best relative reward, and every seed's
curve), ``cost_ms_per_sample``, ``compile_s``, ``final_best_relative_reward`` and
``what_ran``; ``rl_pendulum.png`` plots the curves.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

CELL = 0.02
EPISODE = 100
EPOCH = 100
AGENTS = ("sac", "sac_sample_enhancement", "sac_policy_enhancement", "ppo_rejax")
FULL = {"links": (1, 2), "seeds": 5, "epochs_per_link": 50}
QUICK = {"links": (1,), "seeds": 1, "epochs_per_link": 3}
PAPER = {"links": (1, 2, 3, 4, 5), "seeds": 5, "epochs_per_link": 100}


def pendulum_env(n_links: int, episode_length: int = EPISODE, tol: float = 1e-6):
    """The ``n_links`` pendulum of the module docstring as a :class:`~softbody.control.env.Env`.

    Arguments:
        n_links: links, >= 1.
        episode_length: frames per episode.
        tol: the step's relative tolerance.

    Returns:
        The environment (actions ``(n_links,)``, observations ``(2 n_links,)``).

    Raises:
        ValueError: ``n_links`` < 1.
    """
    from softbody.actuators.joints import JointTorque
    from softbody.control import env as E
    from softbody.material import Material
    from softbody.meshing import Region
    from softbody.meshing.grid import grid_box
    from softbody.model import Options, build
    from softbody.scene import SoftBody
    from softbody.skeleton import Link, Revolute, Skeleton

    if isinstance(n_links, bool) or not isinstance(n_links, (int, np.integer)) or n_links < 1:
        raise ValueError(f"n_links must be a whole number >= 1, got {n_links!r}")
    c = CELL
    cells = 2 * n_links - 1
    mesh = grid_box((cells * c, c, c), (cells, 1, 1))
    x = mesh.points[:, 0]
    regions = {}
    for i in range(n_links):
        inside = (x >= 2 * i * c - 1e-9) & (x <= (2 * i + 1) * c + 1e-9)
        regions[f"bone:l{i}"] = Region(np.flatnonzero(inside), np.flatnonzero(inside[mesh.tets].all(axis=1)))
    mesh = mesh.with_regions(**regions)
    links = [Link(f"l{i}", f"bone:l{i}", None if i == 0 else f"l{i - 1}",
                  Revolute((0.0, 0.0, 1.0), ((2 * i - 0.5) * c if i else 0.0, c / 2, c / 2)))
             for i in range(n_links)]
    model, params = build(SoftBody(mesh, Material(E=2e3, nu=0.3, density=1000.0)), skeleton=Skeleton(links),
                          actuators=[JointTorque([f"l{i}" for i in range(n_links)])],
                          options=Options(dt=0.01, tol=tol, max_iter=500, gravity=(9.81, 0.0, 0.0)))
    length = cells * c
    tip = np.flatnonzero(x >= length - 1e-9)
    tau = 1000.0 * c ** 3 * cells * 9.81 * length / 2
    return E.Env(model, params, observation=E.JointAngles(model),
                 reward=(1.0 / length) * E.Height(model, tip, axis=(-1.0, 0.0, 0.0)),
                 action_map=E.ActionMap(model, low=-tau, high=tau), episode_length=episode_length,
                 reset_noise=E.ResetNoise(joint=0.05))


def relative(returns):
    """Relative reward of episode returns: ``(R / episode + 1) / 2``."""
    return (np.asarray(returns, np.float64) / EPISODE + 1.0) / 2.0


def samples_to_reach(samples, curve, level) -> float | None:
    """The first sample count at which ``curve`` (non-decreasing) reaches ``level``."""
    hit = np.flatnonzero(np.asarray(curve) >= level - 1e-12)
    return float(samples[hit[0]]) if hit.size else None


def _sac_runs(env, name: str, seeds: int, epochs: int, budget: int):
    import jax

    from softbody.control import rl

    options = {"sac": {}, "sac_sample_enhancement": {"virtual_samples": 4},
               "sac_policy_enhancement": {"policy_enhancement": True}}[name]
    virtual = options.get("virtual_samples", 0)
    agent = rl.SAC(env, rl.SACConfig(buffer_size=max(budget * (1 + virtual), 256), **options))
    states = agent.init_seeds(range(seeds))
    keys = jax.random.split(jax.random.PRNGKey(1234), seeds)
    returns = []
    train_times, compile_s = [], 0.0
    for epoch in range(epochs):
        keys = jax.vmap(lambda k, e=epoch: jax.random.fold_in(k, e + 1))(keys)
        start = time.perf_counter()
        states, evaluation = agent.train_seeds(states, EPOCH, keys)  # one program: train an epoch, evaluate
        returns.append(np.asarray(evaluation)[:, 0])
        took = time.perf_counter() - start
        if epoch == 0:
            compile_s = took
        else:
            train_times.append(took)
    cost = float(np.median(train_times)) / (EPOCH * seeds) if train_times else float("nan")
    return np.stack(returns, axis=1), cost, compile_s


def _ppo_runs(env, seeds: int, epochs: int):
    import jax

    from softbody.control import rl

    budget = epochs * EPOCH
    _, train = rl.ppo(env, budget, eval_every=EPOCH, num_envs=4, num_steps=25, skip_initial_evaluation=True)
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    go = jax.jit(jax.vmap(train))
    start = time.perf_counter()
    lowered = go.lower(keys)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    _, returns = compiled(keys)
    jax.block_until_ready(returns)
    took = time.perf_counter() - start
    cost = took / (budget * seeds)
    return np.asarray(returns)[:, :, 0], cost, compile_s


def run(out: Path, quick: bool) -> dict:
    """Run the benchmark (module docstring); writes ``out/rl_pendulum.png``.

    Arguments:
        out: the output folder.
        quick: the smoke-test variant.

    Returns:
        The figures (see the module docstring).
    """
    from softbody import progress

    plan = QUICK if quick else FULL
    curves, ratios, costs, compiles, finals = {}, {}, {}, {}, {}
    cases = [(n, a) for n in plan["links"] for a in AGENTS]
    for n, name in progress.track(cases, "agents x links", note=lambda c: f"{c[1]}, {c[0]} link(s)"):
        env = pendulum_env(n)
        epochs = plan["epochs_per_link"] * n
        if name == "ppo_rejax":
            returns, cost, compile_s = _ppo_runs(env, plan["seeds"], epochs)
        else:
            returns, cost, compile_s = _sac_runs(env, name, plan["seeds"], epochs, epochs * EPOCH)
        best = np.maximum.accumulate(relative(returns), axis=1)
        samples = np.arange(1, epochs + 1) * EPOCH
        q25, median, q75 = np.percentile(best, [25, 50, 75], axis=0)
        curves.setdefault(name, {})[str(n)] = {
            "samples": samples.tolist(), "median": median.tolist(), "q25": q25.tolist(), "q75": q75.tolist(),
            "seeds": best.tolist(), "returns": np.asarray(returns).tolist()}
        costs.setdefault(name, {})[str(n)] = cost * 1e3
        compiles.setdefault(name, {})[str(n)] = compile_s
        finals.setdefault(name, {})[str(n)] = float(median[-1])
    for n in plan["links"]:
        sac = curves["sac"][str(n)]
        level = sac["median"][-1]
        sac_samples = samples_to_reach(sac["samples"], sac["median"], level)
        for name in AGENTS:
            c = curves[name][str(n)]
            reach = samples_to_reach(c["samples"], c["median"], level)
            ratio = None if reach is None else (reach / sac_samples if sac_samples else None)
            ratios.setdefault(name, {})[str(n)] = ratio
    _chart(out / "rl_pendulum.png", curves, plan)
    what = (f"links {list(plan['links'])}, {plan['seeds']} seed(s), {plan['epochs_per_link']} x n epochs of "
            f"{EPOCH} samples (the paper: links 1-5, 5 seeds, 100 x n epochs)")
    return {"samples_ratio_to_sac_final": ratios, "final_best_relative_reward": finals,
            "cost_ms_per_sample": costs, "compile_s": compiles, "what_ran": what, "links": list(plan["links"]),
            "seeds": plan["seeds"], "epochs_per_link": plan["epochs_per_link"], "samples_per_epoch": EPOCH,
            "episode_frames": EPISODE, "curves": curves}


def _chart(path: Path, curves: dict, plan: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    links = plan["links"]
    fig, axes = plt.subplots(1, len(links), figsize=(4.5 * len(links), 3.8), squeeze=False)
    for ax, n in zip(axes[0], links):
        for name in AGENTS:
            c = curves[name][str(n)]
            line, = ax.plot(c["samples"], c["median"], label=name.replace("_", " "))
            ax.fill_between(c["samples"], c["q25"], c["q75"], color=line.get_color(), alpha=0.2)
        ax.set_title(f"{n}-link pendulum ({plan['seeds']} seed(s))")
        ax.set_xlabel("training samples")
        ax.set_ylabel("best relative reward")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

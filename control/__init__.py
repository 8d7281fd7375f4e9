"""softbody.control: losses, trajectory optimisation, policies, system identification, co-design.

This folder (``control/`` in the repository) installs as ``softbody.control``; there is
no top-level ``control`` package, so nothing collides with python-control.

* :mod:`~softbody.control.losses`: composable losses of a trajectory and its controls
  (:class:`TargetPosition`, :class:`ForwardDistance`, :class:`Tracking`, :class:`Effort`,
  :class:`Smoothness`; combine with ``+`` and ``*``).
* :mod:`~softbody.control.trajopt`: open-loop activations on a control grid
  (:class:`ControlGrid`, :class:`ControlProblem`, :func:`optimize_controls`).
* :mod:`~softbody.control.policy`: closed-loop MLP policies trained through the
  simulation (:class:`MLPPolicy`, :class:`Observations`, :func:`policy_rollout`,
  :func:`train_policy`).
* :mod:`~softbody.control.sysid`: parameter estimation from marker trajectories
  (:func:`synthesize`, :class:`Observation`, :func:`identify`).
* :mod:`~softbody.control.codesign`: design and controls together (:class:`Design`,
  :class:`CoDesignProblem`, :func:`codesign`).
* :mod:`~softbody.control.baselines`: CMA-ES on the same variables (:func:`cmaes`).
* :mod:`~softbody.control.sweep`: design and parameter sweeps on Ray workers, resumable
  and fault-tolerant (:func:`run_sweep`, :func:`~softbody.control.sweep.grid`,
  :func:`~softbody.control.sweep.random_design`, :class:`SweepPool` for an optimiser's
  populations); Ray is imported only when a sweep starts (``pip install softbody[sweep]``).
* :mod:`~softbody.control.optimize`: the shared optax loop with progress and
  checkpoint/resume (:func:`minimize`).
* :mod:`~softbody.control.env`: reinforcement-learning environments in gymnax's pure style
  over any scene (:class:`Env`: ``reset``/``step``, batched by ``vmap``; :class:`ActionMap`,
  observations :class:`JointAngles`, :class:`Positions`, :class:`Concat`, rewards
  :class:`Progress`, :class:`Height`, :class:`ActionPenalty`) and exact one-step Jacobians
  by forward-mode implicit differentiation (:func:`step_jacobian`, :func:`contact_changes`).
* :mod:`~softbody.control.rl`: reinforcement learning with those Jacobians: one SAC agent
  (:class:`SAC`, :class:`SACConfig`) with sample enhancement (virtual samples from
  ``ds'/da``, ``dr/da``) and policy enhancement (the actor's action gradient through the
  one-step model) as options, and rejax's PPO as the baseline (:func:`ppo`;
  ``pip install softbody[rl]``).
"""

from .baselines import CMAResult, cmaes
from .codesign import CoDesignProblem, CoDesignResult, Design, codesign, project_capped_simplex
from .errors import ControlError
from .losses import (Effort, ForwardDistance, Loss, Scaled, Smoothness, Sum, TargetPosition, Tracking,
                     centroid_weights, region_vertices)
from .optimize import OptimizeResult, minimize
from .policy import MLPPolicy, Observations, PolicyResult, policy_rollout, train_policy
from .sysid import ESTIMABLE, Observation, SysIdProblem, SysIdResult, identify, synthesize
from . import env, rl, sweep
from .env import (ActionMap, ActionPenalty, Concat, Env, EnvState, Height, JointAngles, Positions, Progress,
                  ResetNoise, Reward, StepJacobian, Transition, contact_changes, step_jacobian)
from .rl import SAC, SACConfig, SACState, evaluate_policy, model_action_gradient, ppo, virtual_samples
from .sweep import Pool as SweepPool, SweepError, SweepResult, population_evaluator, run_sweep
from .trajopt import ControlGrid, ControlProblem, TrajOptResult, optimize_controls

__all__ = [
    "ControlError",
    "Loss", "Sum", "Scaled", "TargetPosition", "ForwardDistance", "Tracking", "Effort", "Smoothness",
    "region_vertices", "centroid_weights",
    "OptimizeResult", "minimize",
    "ControlGrid", "ControlProblem", "TrajOptResult", "optimize_controls",
    "MLPPolicy", "Observations", "PolicyResult", "policy_rollout", "train_policy",
    "ESTIMABLE", "Observation", "SysIdProblem", "SysIdResult", "identify", "synthesize",
    "Design", "CoDesignProblem", "CoDesignResult", "codesign", "project_capped_simplex",
    "CMAResult", "cmaes",
    "env", "Env", "EnvState", "ActionMap", "Transition", "Reward", "Progress", "Height", "ActionPenalty",
    "JointAngles", "Positions", "Concat", "ResetNoise", "StepJacobian", "step_jacobian", "contact_changes",
    "rl", "SAC", "SACConfig", "SACState", "ppo", "virtual_samples", "model_action_gradient", "evaluate_policy",
    "sweep", "run_sweep", "SweepPool", "SweepError", "SweepResult", "population_evaluator",
]

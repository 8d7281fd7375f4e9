"""Joint actuators of a skeleton (:mod:`softbody.skeleton`): torques and position servos.

Both are vertex terms (``energy_and_gradient(x, prep, a)``): their energy is a function of
the joint coordinates ``theta(x)`` read off the bone positions
(:meth:`softbody.skeleton.Rig.coordinates`, differentiable). They act on the skeleton of
the scene they are built into (``build(..., skeleton=..., actuators=[JointTorque(["elbow"])])``).
In the skeleton's reduced coordinates (:class:`~softbody.skeleton.Reduced`) the bones follow
``FK(z)``, so
``theta(FK(z)) = z`` and the term's bone gradient mapped by ``B^T`` is exactly
``dE/dtheta`` in the joint's row of the reduced right-hand side: a torque ``tau`` is the
energy ``-tau theta``.

Joints are revolute (torque in N m, angle in rad) or prismatic (force in N, slide in m).
Revolute angles are read in ``(-pi, pi]``; keep servo targets and torqued motions within
that range.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import VertexTerm
from softbody._types import SceneError
from softbody.skeleton import Prismatic, Revolute, Rig

Array = jax.Array


def _check_joints(joints: Sequence[str], what: str) -> tuple:
    if isinstance(joints, str):
        raise SceneError(f"{what}: joints must be a sequence of link names, got the string {joints!r}; "
                         f"write [{joints!r}]")
    joints = tuple(joints)
    if not joints:
        raise SceneError(f"{what}: name at least one joint (a link with a Revolute or Prismatic joint)")
    if len(set(joints)) != len(joints):
        raise SceneError(f"{what}: joints must be unique, got {list(joints)}")
    return joints


def _bind(term, rig, what: str):
    """A copy of the joint term ``term`` on the scene's ``rig``, with the dofs of its joints."""
    if rig is None:
        raise SceneError(f"{what} drives joints of a skeleton, but the scene has none: pass "
                         "build(..., skeleton=Skeleton([...]))")
    dofs = []
    for name in term.joints:
        i = rig.link_index(name)
        if not isinstance(rig.links[i].joint, (Revolute, Prismatic)):
            raise SceneError(f"{what}: link {name!r} has a {type(rig.links[i].joint).__name__} joint; only "
                             "Revolute and Prismatic joints take a torque or force")
        dofs.append(rig.dof_start[i])
    bound = copy.copy(term)
    object.__setattr__(bound, "rig", rig)
    object.__setattr__(bound, "dofs", np.asarray(dofs))
    return bound


def _joint_values(rig: Rig, dofs: np.ndarray, x: Array) -> Array:
    return rig.joint_values(rig.coordinates(x[jnp.asarray(rig.bone)]))[jnp.asarray(dofs)]


def _check_activation(activation: Array, names: tuple[str, ...], what: str) -> Array:
    a = jnp.asarray(activation)
    if a.shape != (len(names),):
        raise SceneError(f"{what} activation must have shape ({len(names)},) (channels {list(names)}), "
                         f"got {tuple(a.shape)}")
    return a


@dataclass(frozen=True, eq=False)
class JointTorque(VertexTerm):
    """Torque (revolute, N m) or force (prismatic, N) on joints: one channel per joint.

    The activation of channel ``j`` is the torque held over the step; the energy is
    ``-sum_j tau_j theta_j(x)``, so the joint's reduced right-hand side row gets ``tau_j``.

    Attributes:
        joints: names of the driven links (their joints) in the scene's skeleton.
        rig: the skeleton bound to the scene's mesh (set by ``build``).

    Raises:
        SceneError: duplicates, no joints; (in ``build``) an unknown link, a Free or Fixed
            joint, a scene without a skeleton.
    """

    joints: tuple
    rig: Rig | None = field(default=None, init=False)

    def __post_init__(self):
        object.__setattr__(self, "joints", _check_joints(self.joints, "JointTorque"))

    def bind(self, rig) -> "JointTorque":
        """The term on the scene's skeleton (see :meth:`softbody._interfaces.Term.bind`)."""
        return _bind(self, rig, "JointTorque")

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(f"torque:{name}" for name in self.joints)

    def init_params(self) -> tuple:
        """No design parameters."""
        return ()

    def prepare(self, model, params: tuple, dminv: Array, volume: Array) -> tuple:
        """No per-rollout data."""
        return ()

    def energy_and_gradient(self, x: Array, prep: tuple, activation: Array) -> tuple[Array, Array]:
        """``E = -tau . theta(x)`` and ``dE/dx`` ``(n, 3)``.

        Arguments:
            x: ``(n, 3)`` positions; prep: unused (``()``); activation: ``(j,)`` torques.

        Returns:
            ``(energy, gradient)`` in J and N.

        Raises:
            SceneError: ``activation`` is not of shape ``(j,)``.
        """
        tau = _check_activation(activation, self.channel_names, "joint torque")
        return jax.value_and_grad(lambda x: -jnp.sum(tau * _joint_values(self.rig, self.dofs, x)))(x)


class ServoParams(eqx.Module):
    """Design parameters of a servo term.

    Attributes:
        stiffness: ``(j,)`` proportional gains, N m/rad (N/m for prismatic joints).
        torque_limit: ``(j,)`` largest torques the servos apply, N m (N).
    """

    stiffness: Array
    torque_limit: Array


@dataclass(frozen=True, eq=False)
class JointServo(VertexTerm):
    """Position servos on joints: one channel per joint, the target angle (rad) or slide (m).

    The torque is ``clip(k (target - theta), -tau_max, tau_max)``, taken implicitly: the
    energy is the Huber function of ``theta - target`` (quadratic ``k e^2 / 2`` where the
    torque is below its limit, linear beyond), convex, so the step stays a minimisation.
    The servo's damping comes from the step's implicit integration and the material
    damping; a velocity gain needs the step-start joint angles, which vertex terms do not
    receive.

    Attributes:
        joints: names of the servoed links (their joints) in the scene's skeleton.
        stiffness: proportional gain(s), scalar or ``(j,)`` (> 0); initial design values.
        torque_limit: torque limit(s), scalar or ``(j,)`` (> 0, ``inf`` for none).
        rig: the skeleton bound to the scene's mesh (set by ``build``).

    Raises:
        SceneError: bad joints (as :class:`JointTorque`), non-positive gains or limits.
    """

    joints: tuple
    stiffness: float | Sequence[float] = 1.0
    torque_limit: float | Sequence[float] = np.inf
    rig: Rig | None = field(default=None, init=False)

    def __post_init__(self):
        object.__setattr__(self, "joints", _check_joints(self.joints, "JointServo"))
        for name in ("stiffness", "torque_limit"):
            value = np.broadcast_to(np.asarray(getattr(self, name), float), (len(self.joints),)).copy()
            if not np.all(value > 0) or np.isnan(value).any() or (name == "stiffness" and np.isinf(value).any()):
                raise SceneError(f"JointServo.{name} must be > 0{' and finite' if name == 'stiffness' else ''}, "
                                 f"got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)

    def bind(self, rig) -> "JointServo":
        """The term on the scene's skeleton (see :meth:`softbody._interfaces.Term.bind`)."""
        return _bind(self, rig, "JointServo")

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(f"target:{name}" for name in self.joints)

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Revolute targets lie in ``[-pi, pi]`` (angles are read in ``(-pi, pi]``);
        prismatic targets are unbounded."""
        revolute = np.array([isinstance(self.rig.links[self.rig.link_index(j)].joint, Revolute)
                             for j in self.joints])
        bound = np.where(revolute, np.pi, np.inf)
        return -bound, bound

    def init_params(self) -> ServoParams:
        """The gains and limits given to the term, as differentiable parameters."""
        return ServoParams(stiffness=jnp.asarray(self.stiffness), torque_limit=jnp.asarray(self.torque_limit))

    def prepare(self, model, params: ServoParams, dminv: Array, volume: Array) -> ServoParams:
        """The gains are the per-rollout data."""
        return params

    def torques(self, x: Array, prep: ServoParams, activation: Array) -> Array:
        """The servo torques ``(j,)`` at positions ``x`` ``(n, 3)`` for targets ``activation``."""
        error = _joint_values(self.rig, self.dofs, x) - activation
        return jnp.clip(-prep.stiffness * error, -prep.torque_limit, prep.torque_limit)

    def energy_and_gradient(self, x: Array, prep: ServoParams, activation: Array) -> tuple[Array, Array]:
        """The Huber servo energy and its gradient ``(n, 3)``.

        Arguments:
            x: ``(n, 3)`` positions; prep: :class:`ServoParams`; activation: ``(j,)`` targets.

        Returns:
            ``(energy, gradient)`` in J and N.

        Raises:
            SceneError: ``activation`` is not of shape ``(j,)``.
        """
        target = _check_activation(activation, self.channel_names, "joint servo")

        def energy(x):
            e = _joint_values(self.rig, self.dofs, x) - target
            k = prep.stiffness
            outside = k * jnp.abs(e) > prep.torque_limit  # the torque is at its limit
            limit = jnp.where(outside, prep.torque_limit, 0.0)
            e_in = jnp.where(outside, 0.0, e)
            return jnp.sum(0.5 * k * e_in * e_in + limit * jnp.abs(e) - 0.5 * limit * limit / k)

        return jax.value_and_grad(energy)(x)

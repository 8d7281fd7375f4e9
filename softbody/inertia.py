"""The inertia term of the step objective: what makes a solve a time step or a static one.

:func:`softbody.model.prepare` chooses one and :class:`~softbody._types.Prepared` carries it
(``prep.inertia``); the step objective, its Hessian, the adjoints and the reference
integrators read it instead of a flag passed down to each of them.

* :class:`Dynamics` (``h > 0``): implicit Euler's kinetic term with mass damping,
  ``1/(2 h^2) |x - s|_M^2 + 1/(2 h) |x - x_n|_{alpha M}^2`` with the inertial target
  ``s = x_n + h v_n + h^2 M^-1 (M g + f_ext)``: it carries the load.
* :class:`Statics`: the load's potential ``-(M g + f_ext) . x`` (no mass, no damping): the
  minimiser is an equilibrium.

Each gives its energy and gradient at positions with the residual's scale, its Hessian's
diagonal, the first iterate, and whether strain-rate damping acts (it reads the step's
start and ``h``). ``prepare`` adds the matching diagonal (``M / h^2 + alpha M / h``, or
nothing) and damping weight to the PD matrix.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

Array = jax.Array


@dataclass(frozen=True)
class Dynamics:
    """Implicit Euler's inertia term for steps of size ``h`` (s).

    Attributes:
        h: the step size the PD matrix is prefactored for (the steps read it as ``prep.dt``).
    """

    h: float
    #: whether the solve is a static one (no mass term)
    static: ClassVar[bool] = False

    @property
    def dt(self) -> float:
        """The step size ``h``."""
        return self.h

    def damped(self, stiffness_damping: bool) -> bool:
        """Whether strain-rate damping acts (it does in a time step when the scene has it)."""
        return stiffness_damping

    def start(self, x_n: Array, v_n: Array, free: Array) -> Array:
        """The first iterate: ``x_n + h v_n`` on the free vertices."""
        return jnp.where(free > 0, x_n + self.h * v_n, x_n)

    def energy(self, x_n, v_n, mass, mass_alpha, load, free) -> tuple[Callable, Array]:
        """The term at positions and the residual's scale.

        Arguments:
            x_n, v_n: ``(n, 3)`` the step's start; mass, mass_alpha: ``(n, 1)``;
            load: ``(n, 3)`` gravity plus external forces (N); free: ``(n, 1)`` 0/1.

        Returns:
            ``(fn, scale)``: ``fn(x) -> (energy (), gradient (n, 3))`` and
            ``|M s / h^2|`` over the free vertices, the denominator of the relative residual.
        """
        h = self.h
        s = x_n + h * v_n + h * h * load / jnp.maximum(mass, 1e-300)
        s = jnp.where(free > 0, s, x_n)
        scale = jnp.sqrt(jnp.sum((mass * s * free) ** 2)) / h**2

        def fn(x):
            dx, dn = (x - s) * free, (x - x_n) * free
            phi = 0.5 * jnp.sum(mass * dx * dx) / h**2 + 0.5 * jnp.sum(mass_alpha * dn * dn) / h
            return phi, mass * dx / h**2 + mass_alpha * dn / h

        return fn, scale

    def hessian_diagonal(self, mass: Array, mass_alpha: Array):
        """The term's Hessian, diagonal: ``M / h^2 + alpha M / h`` ``(n, 1)``."""
        return mass / self.h**2 + mass_alpha / self.h


@dataclass(frozen=True)
class Statics:
    """The load's potential of a static solve (no mass term, no damping)."""

    static: ClassVar[bool] = True

    @property
    def dt(self) -> float:
        """0: a static solve has no step size."""
        return 0.0

    def damped(self, stiffness_damping: bool) -> bool:
        """``False``: strain-rate damping has no rate to act on."""
        return False

    def start(self, x_n: Array, v_n: Array, free: Array) -> Array:
        """The first iterate: ``x_n``."""
        return x_n

    def energy(self, x_n, v_n, mass, mass_alpha, load, free) -> tuple[Callable, Array]:
        """``(fn, scale)`` as :meth:`Dynamics.energy`: ``fn(x) = (-load . x, -load)`` and
        the scale ``|load|`` over the free vertices."""
        scale = jnp.sqrt(jnp.sum((load * free) ** 2))

        def fn(x):
            return -jnp.sum(load * x), -load

        return fn, scale

    def hessian_diagonal(self, mass: Array, mass_alpha: Array) -> float:
        """0: the load's potential is linear."""
        return 0.0

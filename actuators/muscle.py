"""Muscle fibres: a PD term per tet that contracts along a rest fibre direction.

For a muscle tet with unit rest fibre ``m``, activation ``a`` in [0, 1], stiffness ``k``
(Pa) and design weight ``w`` (>= 0)::

    E = V k w / 2 |F m - p|^2,    p = (1 - a) F m / |F m|

i.e. the fibre's stretch ``|F m|`` is pulled toward ``1 - a``: ``a = 0`` is a passive
fibre at its rest length, ``a = 0.3`` asks for 30 % contraction. The projection ``p`` is
the closest point of ``F m`` on the sphere of radius ``1 - a`` (exact, so PD's monotone
convergence holds), and the term's PD matrix ``V k w (G m)(G m)^T`` does not depend on
``a``: activations change only the right-hand side, never the factorisation.
Each channel's range is [0, 1] (:meth:`Muscle.channel_bounds`): concrete controls outside it
are refused; inside a traced computation they are clipped (zero gradient beyond).

Design parameters (differentiable, in ``Params.actuators``): the stiffness ``k`` (one per
muscle term) and the per-tet fibre weights ``w`` (``(m,)``, 1 by default, or the
``weights`` a term is made with, e.g. the distance falloff of :meth:`Muscle.from_polyline`),
which the co-design API optimises to place muscles. Changing them changes the PD matrix, which is
refactorised once per rollout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import ElementTerm
from softbody.elastic import shape_gradients

Array = jax.Array


class MuscleParams(eqx.Module):
    stiffness: Array  # scalar, Pa
    weights: Array  # (m,) per-tet fibre weights


class MusclePrep(eqx.Module):
    """Per-rollout data of a :class:`Muscle`.

    The integer tet and channel indices stay on the term (a static field, so they are
    numpy constants under every transformation): traced integer arrays would leak out of
    ``jax.closure_convert`` in the contact solver's implicit derivative, which hoists only
    floating-point values.
    """

    local_matrices: Array  # (m, 4, 4)
    coef: Array  # (m,) V k w
    fibre: Array  # (3, m)
    term: "Muscle" = eqx.field(static=True)

    @property
    def tets(self) -> np.ndarray:
        """``(m,)`` int element indices."""
        return self.term.tets

    @property
    def channel(self) -> np.ndarray:
        """``(m,)`` int channel of each tet."""
        return self.term.channel


@dataclass(frozen=True, eq=False)
class Muscle(ElementTerm):
    """A group of muscle tets with one or more control channels.

    Attributes:
        tets: ``(m,)`` element indices.
        fibres: ``(m, 3)`` unit rest fibre directions.
        channel: ``(m,)`` index of each tet's channel in ``channel_names``.
        channel_names: the control channels this term reads, in order.
        stiffness: initial fibre stiffness ``k``, Pa.
        weights: ``(m,)`` initial fibre weights ``w`` (>= 0), or ``None`` for ones.

    Raises:
        ValueError: empty channels, zero fibre directions, mismatched shapes, negative or
            non-finite weights.
    """

    mesh_indices: ClassVar[Mapping[str, str]] = {"tets": "tets"}
    tets: np.ndarray
    fibres: np.ndarray
    channel: np.ndarray
    channel_names: tuple[str, ...]
    stiffness: float = 1e5
    weights: np.ndarray | None = None

    def __post_init__(self):
        tets = np.asarray(self.tets, np.int32).ravel()
        fibres = np.asarray(self.fibres, np.float64).reshape(-1, 3)
        channel = np.asarray(self.channel, np.int32).ravel()
        if not (len(tets) == len(fibres) == len(channel)):
            raise ValueError(f"muscle tets ({len(tets)}), fibres ({len(fibres)}) and channel ({len(channel)}) "
                             "must have one row per tet")
        norms = np.linalg.norm(fibres, axis=1)
        if np.any(norms < 1e-12):
            raise ValueError(f"{int((norms < 1e-12).sum())} muscle tets have a zero fibre direction")
        for c, name in enumerate(self.channel_names):
            if not np.any(channel == c):
                raise ValueError(f"muscle channel {name!r} maps to no tets; remove it or give it a region with tets")
        if len(tets) and (channel.min() < 0 or channel.max() >= len(self.channel_names)):
            raise ValueError("muscle channel indices out of range of channel_names")
        if not self.stiffness > 0:
            raise ValueError(f"muscle stiffness must be > 0 Pa, got {self.stiffness}")
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "fibres", fibres / norms[:, None])
        object.__setattr__(self, "channel", channel)
        object.__setattr__(self, "channel_names", tuple(self.channel_names))
        if self.weights is not None:
            weights = np.asarray(self.weights, np.float64).ravel()
            if weights.shape != tets.shape:
                raise ValueError(f"muscle weights ({weights.size}) need one value per tet ({len(tets)})")
            if not (np.all(np.isfinite(weights)) and np.all(weights >= 0)):
                raise ValueError("muscle weights must be finite and >= 0")
            object.__setattr__(self, "weights", weights)

    @classmethod
    def from_regions(cls, mesh, regions: Sequence[str], fibre=(1.0, 0.0, 0.0), stiffness: float = 1e5) -> "Muscle":
        """One channel per tet region (channel named after the region).

        Arguments:
            mesh: the :class:`~softbody.meshing.TetMesh`.
            regions: region names holding tets, e.g. ``["muscle:top", "muscle:bottom"]``.
            fibre: a direction ``(3,)`` for all tets, or the name of a per-tet mesh field
                ``(t, 3)`` (e.g. ``"fibre"``).
            stiffness: fibre stiffness, Pa.

        Raises:
            KeyError: unknown region or field (naming those that exist).
            ValueError: a region with no tets.
        """
        tets, channel = [], []
        for c, name in enumerate(regions):
            reg = mesh.region(name)
            if reg.tets.size == 0:
                raise ValueError(f"muscle region {name!r} has no tets; muscles need volume regions")
            tets.append(reg.tets)
            channel.append(np.full(len(reg.tets), c))
        tets = np.concatenate(tets)
        if isinstance(fibre, str):
            if fibre not in mesh.fields:
                raise KeyError(f"no per-tet field {fibre!r} in the mesh; it has {sorted(mesh.fields)}")
            fibres = np.asarray(mesh.fields[fibre])[tets]
        else:
            fibres = np.broadcast_to(np.asarray(fibre, float), (len(tets), 3))
        return cls(tets, fibres, np.concatenate(channel), tuple(regions), stiffness)

    @classmethod
    def from_polyline(cls, mesh, polyline, radius: float, stiffness: float = 1e5, falloff: str = "smooth",
                      name: str = "muscle") -> "Muscle":
        """A muscle along a path: one channel, fibres along the path, weights fading with distance.

        Every tet whose centroid lies within ``radius`` of the polyline joins the muscle;
        its fibre is the direction of the nearest segment and its initial weight
        ``w = phi(d / radius)`` depends on the centroid's distance ``d`` to the path:

        * ``"smooth"``: ``phi(r) = (1 - r^2)^2`` (smooth, zero at the rim);
        * ``"linear"``: ``phi(r) = 1 - r``;
        * ``"none"``: ``phi(r) = 1`` (a uniform tube).

        Arguments:
            mesh: the :class:`~softbody.meshing.TetMesh`.
            polyline: ``(k, 3)`` path points in metres, ``k >= 2``, consecutive points distinct.
            radius: the muscle's radius around the path, m (> 0).
            stiffness: fibre stiffness ``k``, Pa.
            falloff: ``"smooth"``, ``"linear"`` or ``"none"``.
            name: the channel's name.

        Returns:
            A :class:`Muscle` with one channel, ``name``.

        Raises:
            ValueError: a bad polyline, radius or falloff, or no tet within ``radius``.
        """
        profiles = {"smooth": lambda r: (1.0 - r * r) ** 2, "linear": lambda r: 1.0 - r,
                    "none": lambda r: np.ones_like(r)}
        if falloff not in profiles:
            raise ValueError(f"falloff must be one of {sorted(profiles)}, got {falloff!r}")
        path = np.asarray(polyline, np.float64)
        if path.ndim != 2 or path.shape[1] != 3 or len(path) < 2 or not np.all(np.isfinite(path)):
            raise ValueError(f"polyline must be finite points of shape (k, 3) with k >= 2, got {path.shape}")
        seg = np.diff(path, axis=0)  # (k-1, 3)
        length = np.linalg.norm(seg, axis=1)
        if np.any(length <= 1e-12 * max(1.0, float(np.abs(path).max()))):
            raise ValueError("polyline has repeated consecutive points (zero-length segments)")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"muscle radius must be a positive number of metres, got {radius}")
        centroid = np.asarray(mesh.points)[np.asarray(mesh.tets)].mean(axis=1)  # (t, 3)
        # Distance from every centroid to every segment (closest point, clamped to the ends).
        rel = centroid[:, None, :] - path[None, :-1, :]  # (t, k-1, 3)
        u = np.clip(np.einsum("tsi,si->ts", rel, seg) / length**2, 0.0, 1.0)
        dist = np.linalg.norm(rel - u[..., None] * seg[None], axis=2)  # (t, k-1)
        nearest = dist.argmin(axis=1)
        d = dist[np.arange(len(centroid)), nearest]
        tets = np.flatnonzero(d < radius)
        if len(tets) == 0:
            raise ValueError(f"no tet centroid lies within radius {radius} m of the polyline "
                             f"(the closest is {d.min():.3g} m away); widen the radius or move the path")
        fibres = seg[nearest[tets]] / length[nearest[tets], None]
        weights = profiles[falloff](d[tets] / radius)
        return cls(tets, fibres, np.zeros(len(tets)), (name,), stiffness, weights)

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Activations lie in [0, 1] (0 passive, 1 full contraction)."""
        n = len(self.channel_names)
        return np.zeros(n), np.ones(n)

    def init_params(self) -> MuscleParams:
        weights = jnp.ones(len(self.tets)) if self.weights is None else jnp.asarray(self.weights)
        return MuscleParams(stiffness=jnp.asarray(float(self.stiffness)), weights=weights)

    def prepare(self, model, p: MuscleParams, dminv: Array, volume: Array) -> MusclePrep:
        """Per-rollout data: PD matrix blocks ``(m, 4, 4)`` and coefficients."""
        idx = jnp.asarray(self.tets)
        g = shape_gradients(dminv[:, :, idx])  # (4, 3, m)
        fibre = jnp.asarray(self.fibres.T)  # (3, m)
        gm = jnp.einsum("ajm,jm->am", g, fibre)  # (4, m)
        coef = volume[idx] * p.stiffness * p.weights
        local = jnp.einsum("am,bm,m->mab", gm, gm, coef)
        return MusclePrep(local_matrices=local, coef=coef, fibre=fibre, term=self)

    def energy_and_stress(self, f: Array, prep: MusclePrep, activation: Array) -> tuple[Array, Array]:
        """Energy ``(m,)`` and ``dE/dF`` ``(3, 3, m)`` for ``f`` ``(3, 3, m)`` and activations ``(c,)``."""
        a = jnp.clip(activation, 0.0, 1.0)[jnp.asarray(prep.channel)]
        m = prep.fibre
        fm = jnp.stack([f[i, 0] * m[0] + f[i, 1] * m[1] + f[i, 2] * m[2] for i in range(3)])  # (3, m)
        length = jnp.sqrt(fm[0] ** 2 + fm[1] ** 2 + fm[2] ** 2)
        safe = jnp.where(length > 1e-12, length, 1.0)
        r = fm * (1.0 - (1.0 - a) / safe)  # F m - p
        energy = 0.5 * prep.coef * (r[0] ** 2 + r[1] ** 2 + r[2] ** 2)
        stress = prep.coef * jnp.stack([jnp.stack([r[i] * m[j] for j in range(3)]) for i in range(3)])
        return energy, stress


"""Pneumatic actuators: pressurised cavities and the cell model.

Two models, one per way a soft roboticist thinks about air:

* :class:`CavityPressure`: a gauge pressure ``p`` (pascals) in a closed cavity whose wall
  triangles are tagged in the mesh (``"cavity:<name>"`` regions, faces oriented into the
  cavity). It is the conservative potential::

      E(x) = -sum_c g_c p_c V_c(x),    V_c(x) = -1/6 sum_{f in c} x_0 . (x_1 x x_2)

  with ``V_c`` the volume the deformed cavity surface encloses (divergence theorem; the
  minus sign because the faces' normals point into the cavity, against the outward
  normal of the theorem), ``p_c`` the channel's activation in pascals (within the
  term's bounds: refused outside when concrete, clipped when traced) and ``g_c`` a design weight (1 = chamber connected). For a closed
  surface ``dV_c/dx_a = sum_{f ni a} A_f n_f / 3`` with ``A_f n_f`` the area-weighted
  normal pointing out of the cavity (into the wall), so ``-dE/dx_a = g_c p_c sum A_f n_f / 3``:
  exactly the consistent nodal load of a uniform follower pressure on the deformed wall
  (a balloon's load, not a dead load). The term adds nothing to the PD matrix.
  A volume-controlled variant (fluid pumped in by volume) is :class:`CavityVolume`.
* :class:`PneumaticCells`: the cell model of Qiao et al. (2021): the volume projection of
  the tagged tets targets ``det F = a^w`` instead of 1 (``w`` the cell's design weight;
  ``s = a^(w/3)`` below is the uniform stretch of that volume). The shape term still pulls each cell
  towards a rotation: a free body made only of cells settles at ``F = lambda I`` with
  ``lambda = (w_s + w_v s) / (w_s + w_v)`` (``w_s = 2 mu``, ``w_v = 3 lambda_Lame``), so
  ``det F`` approaches ``a`` as ``nu`` approaches 0.5. It changes only the local step,
  never the matrix.

Both kinds are differentiable in their activations and design weights
(``Params.actuators``). Channel coverage and the closedness of cavity surfaces are checked
when a term is made; the cavities' orientation when it is made from a mesh
(``from_regions``) and again when it is prepared; so a bad scene fails before anything
runs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody._interfaces import VertexTerm, VolumeTerm
from softbody._types import SceneError

Array = jax.Array

#: The lowest gauge pressure a cavity can hold: a perfect vacuum, Pa.
VACUUM = -101325.0


def _check_activation(activation: Array, channel_names: tuple[str, ...], what: str) -> Array:
    a = jnp.asarray(activation)
    if a.shape != (len(channel_names),):
        raise SceneError(f"{what} activation must have shape ({len(channel_names)},) "
                         f"(channels {list(channel_names)}), got {tuple(a.shape)}")
    return a


def _closed_surface_check(faces: np.ndarray, name: str) -> None:
    """Raise unless ``faces`` form a closed, consistently oriented surface."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = directed[:, 0].astype(np.int64) * (int(faces.max()) + 1) + directed[:, 1]
    rev = directed[:, 1].astype(np.int64) * (int(faces.max()) + 1) + directed[:, 0]
    _, counts = np.unique(key, return_counts=True)
    repeated = int((counts > 1).sum())
    unmatched = int((~np.isin(rev, key)).sum())
    if repeated or unmatched:
        raise SceneError(
            f"cavity {name!r} is not a closed, consistently oriented surface ({unmatched} edges "
            f"without an opposite twin, {repeated} repeated directed edges): its volume, and so the "
            "pressure load, is undefined. Tag the whole inner wall of a sealed chamber")


def _cavity_volumes(x: Array, faces: Array, cavity: Array, centre: Array, n_cavities: int) -> Array:
    """Volumes ``(c,)`` enclosed by each cavity's inward-facing triangles at positions ``x``."""
    p = x[faces] - centre[cavity][:, None, :]  # (f, 3, 3), shifted for round-off
    six_v = -jnp.einsum("fi,fi->f", p[:, 0], jnp.cross(p[:, 1], p[:, 2]))
    return jnp.zeros(n_cavities, x.dtype).at[cavity].add(six_v) / 6.0


def _volume_gradient(x: Array, faces: Array, weight: Array) -> Array:
    """Nodal sums ``(n, 3)`` of ``weight_f A_f n_f / 3`` over the faces: each face gives a third
    of its area-weighted normal out of the cavity (``-(x1-x0) x (x2-x0) / 2`` for faces
    oriented into it) to each of its vertices. With one weight per closed cavity this is
    ``sum_c weight_c dV_c/dx``."""
    p = x[faces]
    an = -0.5 * jnp.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # (f, 3) out of the cavity
    share = (weight[:, None] * an / 3.0)[:, None, :]
    return jnp.zeros_like(x).at[faces].add(jnp.broadcast_to(share, p.shape))


def _cavity_faces(mesh, regions: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    faces, cavity = [], []
    for c, name in enumerate(regions):
        reg = mesh.region(name)
        if len(reg.faces) == 0:
            raise SceneError(f"cavity region {name!r} has no faces; a cavity needs the triangles of its "
                             "inner wall (a 'cavity:<name>' region from softbody.meshing.Cavity)")
        faces.append(reg.faces)
        cavity.append(np.full(len(reg.faces), c))
    if not faces:
        raise SceneError("give at least one cavity region")
    return np.concatenate(faces), np.concatenate(cavity)


class CavityParams(eqx.Module):
    """Design parameters of a cavity term.

    Attributes:
        gain: ``(c,)`` one weight per cavity, 1 by default: the chamber-selection weight
            (1 = connected to its channel, 0 = sealed off, values between interpolate).
    """

    gain: Array


class CavityPrep(eqx.Module):
    """Per-rollout data of a cavity term (it adds no PD matrix blocks; the face layout
    stays on the term, which is static)."""

    centre: Array  # (c, 3) rest centroid of each cavity's vertices (a round-off shift only)
    rest_volume: Array  # (c,) volumes enclosed at the mesh's rest positions, m^3
    gain: Array  # (c,)


@dataclass(frozen=True, eq=False)
class _Cavities:
    """Layout shared by the cavity terms: wall faces, the cavity of each, one channel per cavity.

    Attributes:
        faces: ``(f, 3)`` wall triangles, oriented into their cavity.
        cavity: ``(f,)`` index of each face's cavity (= its channel) in ``channel_names``.
        channel_names: one control channel per cavity.

    Raises:
        SceneError: mismatched shapes, out-of-range indices, a channel with no faces, or a
            cavity whose faces do not form a closed, consistently oriented surface.
    """

    mesh_indices: ClassVar[Mapping[str, str]] = {"faces": "vertices"}
    faces: np.ndarray
    cavity: np.ndarray
    channel_names: tuple[str, ...]

    def __post_init__(self):
        faces = np.asarray(self.faces, np.int32).reshape(-1, 3)
        cavity = np.asarray(self.cavity, np.int32).ravel()
        names = tuple(self.channel_names)
        if len(faces) != len(cavity):
            raise SceneError(f"cavity faces ({len(faces)}) and cavity indices ({len(cavity)}) need one "
                             "row per face")
        if len(cavity) and (cavity.min() < 0 or cavity.max() >= len(names)):
            raise SceneError(f"cavity indices must lie in [0, {len(names)}), one per channel name")
        for c, name in enumerate(names):
            mine = faces[cavity == c]
            if len(mine) == 0:
                raise SceneError(f"cavity channel {name!r} maps to no cavity faces; remove the channel or "
                                 "give it the faces of a 'cavity:' region")
            _closed_surface_check(mine, name)
        object.__setattr__(self, "faces", faces)
        object.__setattr__(self, "cavity", cavity)
        object.__setattr__(self, "channel_names", names)

    @classmethod
    def from_regions(cls, mesh, regions: Sequence[str], **kwargs) -> _Cavities:
        """One cavity and one channel per ``"cavity:"`` region (channel named after the region).

        Arguments:
            mesh: the :class:`~softbody.meshing.TetMesh`.
            regions: cavity region names, e.g. ``["cavity:chamber"]``.
            **kwargs: the term's other attributes (bounds, bulk modulus).

        Raises:
            KeyError: an unknown region (naming those that exist).
            SceneError: a region without faces, an open or inconsistently oriented cavity
                surface, or faces pointing out of the cavity.
        """
        faces, cavity = _cavity_faces(mesh, regions)
        term = cls(faces, cavity, tuple(regions), **kwargs)
        term._rest_volumes(np.asarray(mesh.points))
        return term

    def _rest_volumes(self, points: np.ndarray) -> np.ndarray:
        """Enclosed volumes ``(c,)`` at ``points``; raise unless all are positive."""
        if self.faces.max() >= len(points):
            raise SceneError(f"cavity faces index vertex {int(self.faces.max())} but the mesh has "
                             f"{len(points)}; build the term from the same mesh")
        p = points[self.faces]
        six_v = -np.einsum("fi,fi->f", p[:, 0], np.cross(p[:, 1], p[:, 2]))
        volumes = np.bincount(self.cavity, six_v, minlength=len(self.channel_names)) / 6.0
        for name, v in zip(self.channel_names, volumes):
            if not v > 0:
                raise SceneError(f"cavity {name!r} encloses a volume of {v:.3g} m^3: its faces must point "
                                 "into the cavity (the orientation of 'cavity:' regions)")
        return volumes

    def init_params(self) -> CavityParams:
        """Design parameters: ``gain`` = 1 for every cavity."""
        return CavityParams(gain=jnp.ones(len(self.channel_names)))

    def prepare(self, model, p: CavityParams, dminv: Array, volume: Array) -> CavityPrep:
        """Per-rollout data: rest centroids and rest volumes of the cavities.

        Raises:
            SceneError: the faces do not belong to the model's mesh, or point out of a cavity.
        """
        points = np.asarray(model.mesh.points)
        rest = self._rest_volumes(points)
        centre = np.stack([points[np.unique(self.faces[self.cavity == c])].mean(axis=0)
                           for c in range(len(self.channel_names))])
        return CavityPrep(centre=jnp.asarray(centre), rest_volume=jnp.asarray(rest), gain=p.gain)

    def volumes(self, prep: CavityPrep, x: Array) -> Array:
        """Enclosed volume of each cavity at positions ``x`` ``(n, 3)``: ``(c,)``, m^3."""
        return _cavity_volumes(x, jnp.asarray(self.faces), jnp.asarray(self.cavity), prep.centre,
                               len(self.channel_names))


@dataclass(frozen=True, eq=False)
class CavityPressure(_Cavities, VertexTerm):
    """Gauge pressure in closed cavities: a vertex term (see the module docstring).

    The activation of each channel is the cavity's gauge pressure in pascals, clipped to
    ``[min_pressure, max_pressure]`` (outside the bounds its gradient is zero). The load
    follows the deformed wall and is scaled by the cavity's design ``gain``. Build it with
    :meth:`from_regions`.

    Attributes:
        faces: ``(f, 3)`` wall triangles, oriented into their cavity.
        cavity: ``(f,)`` index of each face's cavity (= channel) in ``channel_names``.
        channel_names: one channel per cavity.
        min_pressure: lowest gauge pressure, Pa (default: a perfect vacuum, -101325).
        max_pressure: highest gauge pressure, Pa (default: unbounded; set the pump's limit).

    Raises:
        SceneError: mismatched shapes, a channel with no faces, an open or inconsistently
            oriented cavity surface; ``min_pressure`` below vacuum or above ``max_pressure``.
    """

    min_pressure: float = VACUUM
    max_pressure: float = np.inf

    def __post_init__(self):
        super().__post_init__()
        if not (VACUUM <= self.min_pressure <= self.max_pressure):
            raise SceneError(f"pressure bounds must satisfy {VACUUM} Pa (vacuum) <= min_pressure <= "
                             f"max_pressure, got [{self.min_pressure}, {self.max_pressure}]")

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Gauge pressures lie in ``[min_pressure, max_pressure]`` Pa."""
        n = len(self.channel_names)
        return np.full(n, float(self.min_pressure)), np.full(n, float(self.max_pressure))

    def pressures(self, activation: Array) -> Array:
        """The pressures ``(c,)`` in Pa that ``activation`` ``(c,)`` asks for, after clipping."""
        a = _check_activation(activation, self.channel_names, "cavity pressure")
        return jnp.clip(a, self.min_pressure, self.max_pressure)

    def energy_and_gradient(self, x: Array, prep: CavityPrep, activation: Array) -> tuple[Array, Array]:
        """``E = -sum_c g_c p_c V_c(x)`` and ``dE/dx`` ``(n, 3)``.

        Arguments:
            x: ``(n, 3)`` positions; prep: from :meth:`prepare`; activation: ``(c,)`` in Pa.

        Returns:
            ``(energy, gradient)``: a scalar in joules and ``(n, 3)`` in newtons (minus the
            nodal pressure forces).

        Raises:
            SceneError: ``activation`` is not of shape ``(c,)``.
        """
        p = self.pressures(activation) * prep.gain
        energy = -jnp.sum(p * self.volumes(prep, x))
        return energy, -_volume_gradient(x, jnp.asarray(self.faces), p[jnp.asarray(self.cavity)])


@dataclass(frozen=True, eq=False)
class CavityVolume(_Cavities, VertexTerm):
    """Volume-controlled cavities: fluid pumped in by volume (a syringe pump), a vertex term.

    The activation ``a`` of each channel is the cavity's volume growth: the fluid's
    volume is ``V_t = V_0 (1 + g a)`` with ``V_0`` the cavity volume of the mesh as given
    (morph offsets do not move it) and ``g`` the design gain. The fluid is compressible
    with bulk modulus ``K`` (the default, 1e5 Pa, is air's isothermal bulk modulus at one
    atmosphere)::

        E = sum_c K / (2 V_0) (V_c(x) - V_t)^2,    pressure p_c = K (V_t - V_c(x)) / V_0,

    so at equilibrium the wall carries the same load as :class:`CavityPressure` at the
    pressure :meth:`pressures` reports, and volume control passes the pressure maximum
    of a ballooning wall. ``a`` lies in ``[min_growth, max_growth]`` (refused outside when
    concrete, clipped when traced).

    Limit: the fluid's stiffness ``K/V_0 |dV/dx|^2`` (a dense rank-one coupling of the
    cavity's vertices) is not in the prefactored PD matrix, so the solver's PD steps
    ignore it. On the example finger (wall E = 1e5 Pa) static solves converged for
    ``K <= E`` and diverged for ``K = 3 E``; in dynamics the mass matrix bounds the step.
    For a stiff liquid use :class:`CavityPressure` driven by the pressure instead.

    Attributes:
        faces, cavity, channel_names: as for :class:`CavityPressure`.
        bulk_modulus: ``K`` in Pa (> 0).
        min_growth: lowest growth (default -1: an emptied cavity).
        max_growth: highest growth (default unbounded).

    Raises:
        SceneError: as for :class:`CavityPressure`; a non-positive bulk modulus; bad bounds.
    """

    bulk_modulus: float = 1e5
    min_growth: float = -1.0
    max_growth: float = np.inf

    def __post_init__(self):
        super().__post_init__()
        if not (np.isfinite(self.bulk_modulus) and self.bulk_modulus > 0):
            raise SceneError(f"bulk_modulus must be a positive number of pascals, got {self.bulk_modulus}")
        if not (-1.0 <= self.min_growth <= self.max_growth):
            raise SceneError(f"growth bounds must satisfy -1 <= min_growth <= max_growth, got "
                             f"[{self.min_growth}, {self.max_growth}]")

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Growths lie in ``[min_growth, max_growth]``."""
        n = len(self.channel_names)
        return np.full(n, float(self.min_growth)), np.full(n, float(self.max_growth))

    def target_volumes(self, prep: CavityPrep, activation: Array) -> Array:
        """Fluid volumes ``V_t`` ``(c,)`` in m^3 for ``activation`` ``(c,)``."""
        a = _check_activation(activation, self.channel_names, "cavity volume")
        return prep.rest_volume * (1.0 + prep.gain * jnp.clip(a, self.min_growth, self.max_growth))

    def pressures(self, prep: CavityPrep, x: Array, activation: Array) -> Array:
        """Gauge pressures ``(c,)`` in Pa of the fluid at positions ``x`` ``(n, 3)``."""
        return self.bulk_modulus * (self.target_volumes(prep, activation) - self.volumes(prep, x)) / prep.rest_volume

    def energy_and_gradient(self, x: Array, prep: CavityPrep, activation: Array) -> tuple[Array, Array]:
        """The fluid's energy (scalar, J) and its gradient ``(n, 3)`` (N).

        Raises:
            SceneError: ``activation`` is not of shape ``(c,)``.
        """
        p = self.pressures(prep, x, activation)
        energy = jnp.sum(0.5 * p * p * prep.rest_volume / self.bulk_modulus)
        return energy, -_volume_gradient(x, jnp.asarray(self.faces), p[jnp.asarray(self.cavity)])


class CellParams(eqx.Module):
    """Design parameters of :class:`PneumaticCells`.

    Attributes:
        weights: ``(m,)`` per-cell weights, 1 by default: a cell targets ``det F = a^w``,
            so 0 removes it and 1 makes it a full cell (the design variable that places cells).
    """

    weights: Array


class CellPrep(eqx.Module):
    """Per-rollout data of :class:`PneumaticCells` (no PD matrix blocks; the tets and
    channels stay on the term, which is static)."""

    weights: Array  # (m,)


@dataclass(frozen=True, eq=False)
class PneumaticCells(VolumeTerm):
    """The cell model: tagged tets whose volume projection targets ``det F = a``.

    A volume-target term: for cell ``e`` on channel ``k`` with activation ``a_k`` (the
    target volume ratio; 1 = rest, 2 = doubled, 0.5 = halved) and design weight
    ``w_e``, the core's volume term aims at ``det F = s^3 = a_k^(w_e)`` with
    ``s = a_k^(w_e / 3)`` (reached by a free cell under a dominant volume term; see
    :func:`softbody.elastic.corotated`). ``a`` is clipped to
    ``[min_expansion, max_expansion]`` (default ``[0.2, 5]``, > 0; outside, its gradient
    is zero). Note that an activation of 0 (the default of an omitted control) asks for
    the strongest contraction, not for rest: pass ones for a neutral state.

    Attributes:
        tets: ``(m,)`` cell tets (each at most once).
        channel: ``(m,)`` index of each cell's channel in ``channel_names``.
        channel_names: the control channels.
        min_expansion, max_expansion: bounds of the target volume ratio.

    Raises:
        SceneError: mismatched shapes, repeated tets, a channel with no tets, bad bounds.
    """

    mesh_indices: ClassVar[Mapping[str, str]] = {"tets": "tets"}
    tets: np.ndarray
    channel: np.ndarray
    channel_names: tuple[str, ...]
    min_expansion: float = 0.2
    max_expansion: float = 5.0

    def __post_init__(self):
        tets = np.asarray(self.tets, np.int32).ravel()
        channel = np.asarray(self.channel, np.int32).ravel()
        names = tuple(self.channel_names)
        if len(tets) != len(channel):
            raise SceneError(f"cell tets ({len(tets)}) and channel ({len(channel)}) need one row per tet")
        if len(np.unique(tets)) != len(tets):
            raise SceneError("a tet appears in more than one cell; each cell tet has one channel")
        if len(channel) and (channel.min() < 0 or channel.max() >= len(names)):
            raise SceneError(f"cell channel indices must lie in [0, {len(names)})")
        for c, name in enumerate(names):
            if not np.any(channel == c):
                raise SceneError(f"cell channel {name!r} maps to no tets; remove the channel or give it "
                                 "a region with tets")
        if not (0 < self.min_expansion <= 1.0 <= self.max_expansion < np.inf):
            raise SceneError("cell expansion bounds must satisfy 0 < min_expansion <= 1 <= max_expansion "
                             f"< inf, got [{self.min_expansion}, {self.max_expansion}]")
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "channel", channel)
        object.__setattr__(self, "channel_names", names)

    @classmethod
    def from_regions(cls, mesh, regions: Sequence[str], **kwargs) -> PneumaticCells:
        """One channel per tet region (channel named after the region).

        Arguments:
            mesh: the :class:`~softbody.meshing.TetMesh`.
            regions: names of regions holding tets, e.g. ``["muscle:top"]``.
            **kwargs: ``min_expansion``, ``max_expansion``.

        Raises:
            KeyError: an unknown region (naming those that exist).
            SceneError: a region with no tets, or tets in two of the regions.
        """
        tets, channel = [], []
        for c, name in enumerate(regions):
            reg = mesh.region(name)
            if reg.tets.size == 0:
                raise SceneError(f"cell region {name!r} has no tets; pneumatic cells need volume regions")
            tets.append(reg.tets)
            channel.append(np.full(len(reg.tets), c))
        if not tets:
            raise SceneError("give at least one cell region")
        return cls(np.concatenate(tets), np.concatenate(channel), tuple(regions), **kwargs)

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Volume ratios lie in ``[min_expansion, max_expansion]``."""
        n = len(self.channel_names)
        return np.full(n, float(self.min_expansion)), np.full(n, float(self.max_expansion))

    def init_params(self) -> CellParams:
        """Design parameters: ``weights`` = 1 for every cell."""
        return CellParams(weights=jnp.ones(len(self.tets)))

    def prepare(self, model, p: CellParams, dminv: Array, volume: Array) -> CellPrep:
        """Per-rollout data (the cells' weights).

        Raises:
            SceneError: a cell tet the model's mesh does not have.
        """
        if self.tets.max() >= model.n_tets:
            raise SceneError(f"cell tet {int(self.tets.max())} is out of range: the mesh has {model.n_tets} tets")
        return CellPrep(weights=p.weights)

    def volume_targets(self, prep: CellPrep, activation: Array) -> tuple[np.ndarray, Array]:
        """The cells' tets ``(m,)`` and volume targets ``s = a^(w/3)`` ``(m,)``.

        Raises:
            SceneError: ``activation`` is not of shape ``(c,)``.
        """
        a = _check_activation(activation, self.channel_names, "pneumatic cell")
        a = jnp.clip(a, self.min_expansion, self.max_expansion)[jnp.asarray(self.channel)]
        return self.tets, jnp.exp(prep.weights * jnp.log(a) / 3.0)

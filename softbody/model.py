"""Scene compilation: ``TetMesh`` + materials + options -> static ``Model`` + traced ``Params``.

* :class:`Model` is static: topology, fixed vertices, the sparsity pattern of the PD
  matrix and the maps that assemble it, actuator layouts, solver choices. Changing it
  recompiles. It is hashed by identity.
* :class:`Params` is a pytree of everything differentiable: per-material Young's modulus,
  Poisson's ratio, density and damping, rest-shape morph offsets, actuator design
  parameters. Changing it does not recompile.
* :class:`State` is the pytree ``(x, v, rot)``: positions and velocities ``(n, 3)`` and the
  per-tet rotation (a unit quaternion ``(4, t)``) of ``x``, kept to warm-start the next
  local step.

Everything that depends on ``Params`` (rest-shape operators, volumes, masses, weights,
the PD matrix and its factorisation) is computed once per rollout by :func:`prepare`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve, rotation
from softbody._interfaces import Actuator, ElementActuator
from softbody.material import Material, pd_weights
from softbody.meshing import TetMesh
from softbody.gradients import Adjoint, Implicit
from softbody.solvers import LBFGS, IterationMethod

Array = jax.Array


class SceneError(ValueError):
    """A scene description is invalid; the message names the problem and the fix."""


@dataclass(frozen=True)
class Options:
    """Simulation options (static: changing them recompiles).

    Attributes:
        dt: time step, s (> 0).
        gravity: acceleration, m/s^2, shape (3,).
        tol: relative force-residual tolerance of each implicit step:
            ``|g(x)| <= tol * |M s / h^2| + atol`` over free degrees of freedom, with ``g``
            the gradient of the step's objective and ``s`` the inertial prediction (the
            definition DiffPD uses, so iteration counts compare).
        atol: absolute force tolerance, N.
        max_iter: iteration cap per step; a step that hits it reports ``converged=False``.
        method: the nonlinear iteration: :class:`~softbody.solvers.LBFGS` or
            :class:`~softbody.solvers.LocalGlobal` (plain PD); ``None`` (default) picks
            L-BFGS, or the contact solver when the scene has obstacles.
        linear_solver: a :class:`~softbody.linsolve.LinearSolver`; ``None`` picks by size.
        rotation_iterations: warm-started Newton steps of the rotation extraction per
            local step.
        adjoint: how gradients are taken: :class:`~softbody.gradients.Implicit` (default)
            or :class:`~softbody.gradients.Unrolled`.
    """

    dt: float = 0.01
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    tol: float = 1e-4
    atol: float = 1e-10
    max_iter: int = 200
    method: IterationMethod | None = None
    linear_solver: linsolve.LinearSolver | None = None
    rotation_iterations: int = 1
    adjoint: Adjoint = field(default_factory=Implicit)

    def __post_init__(self):
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise SceneError(f"Options.dt = {self.dt!r}: the time step must be a positive number of seconds")
        if self.dt > 0.1:
            raise SceneError(f"Options.dt = {self.dt} s is too large to resolve any soft-body motion; use <= 0.1 s")
        if not (self.tol > 0 and self.atol >= 0):
            raise SceneError("Options.tol must be > 0 and Options.atol >= 0")
        if int(self.max_iter) < 1:
            raise SceneError("Options.max_iter must be >= 1")
        if len(self.gravity) != 3 or not np.all(np.isfinite(self.gravity)):
            raise SceneError(f"Options.gravity must be 3 finite numbers, got {self.gravity!r}")


class Params(eqx.Module):
    """Differentiable parameters (a pytree).

    Attributes:
        E, nu, density, alpha, beta: ``(n_materials,)`` per-material values (see
            :class:`~softbody.material.Material`), in the order of ``Model.material_names``.
        morph: ``(n, 3)`` rest-shape offsets added to the mesh's rest positions.
        actuators: a tuple with one design-parameter pytree per actuator term.
        obstacles: a tuple with one parameter pytree per obstacle (pose, friction, ...).
    """

    E: Array
    nu: Array
    density: Array
    alpha: Array
    beta: Array
    morph: Array
    actuators: tuple = ()
    obstacles: tuple = ()


class State(eqx.Module):
    """Simulation state: positions ``x`` and velocities ``v`` ``(n, 3)``, rotations ``rot``
    ``(4, t)`` (warm start of the local step) and the time ``t`` (s)."""

    x: Array
    v: Array
    rot: Array
    t: Array


@dataclass(frozen=True, eq=False)
class Model:
    """Static description of a compiled scene. Build it with :func:`build`."""

    mesh: TetMesh
    options: Options
    material_names: tuple[str, ...]
    tet_material: np.ndarray  # (t,) int32 material index per tet
    fixed: np.ndarray  # (k,) int32 fixed vertex indices
    free_mask: np.ndarray  # (n, 1) float64: 1 on free vertices, 0 on fixed
    pattern: linsolve.SparsityPattern
    local_to_data: np.ndarray  # (t*16,) int32 into pattern data; nnz = dropped
    diag_to_data: np.ndarray  # (n,) int32 positions of the diagonal entries
    terms: tuple = ()  # actuator terms (see softbody.simulate for the term kinds)
    channel_names: tuple[str, ...] = ()
    obstacles: tuple = ()  # obstacle objects (see softbody.contact)
    stiffness_damping: bool = False  # some material had beta > 0 at build time

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    @property
    def n_tets(self) -> int:
        return self.mesh.n_tets

    @functools.cached_property
    def corner_incidence(self) -> np.ndarray:
        """``(n, K)`` int32: each vertex's tet corners (see :func:`softbody.elastic.corner_incidence`)."""
        from softbody.elastic import corner_incidence

        return corner_incidence(self.mesh.tets)

    @property
    def n_channels(self) -> int:
        return len(self.channel_names)

    @functools.cached_property
    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)``, each ``(n_channels,)``: the range of every control channel
        (:meth:`softbody._interfaces.Actuator.channel_bounds`), in ``channel_names`` order."""
        bounds = [term.channel_bounds() for term in self.terms]
        if not bounds:
            return np.zeros(0), np.zeros(0)
        return (np.concatenate([np.asarray(lo, np.float64) for lo, _ in bounds]),
                np.concatenate([np.asarray(hi, np.float64) for _, hi in bounds]))

    @property
    def method(self) -> IterationMethod:
        """The nonlinear iteration in use (``options.method`` or the default for the scene)."""
        if self.options.method is not None:
            return self.options.method
        if self.obstacles:
            from softbody.contact import ContactPD

            return ContactPD()
        return LBFGS()

    @property
    def linear_solver(self) -> linsolve.LinearSolver:
        return self.options.linear_solver or linsolve.auto_solver(self.pattern.n)

    def __hash__(self):
        return id(self)


def _fixed_vertices(mesh: TetMesh, fixed) -> np.ndarray:
    if fixed is None:
        return np.zeros(0, np.int32)
    if isinstance(fixed, str):
        if fixed not in mesh.regions:
            raise SceneError(f"fixed region {fixed!r} is not in the mesh; it has {sorted(mesh.regions)}")
        idx = mesh.regions[fixed].vertices
    elif callable(fixed):
        mask = np.asarray(fixed(mesh.points), bool)
        if mask.shape != (mesh.n_vertices,):
            raise SceneError(f"the fixed predicate must return a boolean mask of shape ({mesh.n_vertices},)")
        idx = np.flatnonzero(mask)
    else:
        idx = np.unique(np.asarray(fixed, np.int64))
        if idx.size and (idx.min() < 0 or idx.max() >= mesh.n_vertices):
            raise SceneError("fixed vertex indices out of range")
    if len(idx) == 0:
        raise SceneError(f"the fixed selection {fixed if isinstance(fixed, str) else ''!s} holds no vertices; "
                         "check the region or predicate, or pass fixed=None for a free body")
    return np.asarray(idx, np.int32)


def _materials(mesh: TetMesh, material) -> tuple[tuple[str, ...], list[Material], np.ndarray]:
    if isinstance(material, Material):
        return ("default",), [material], np.zeros(mesh.n_tets, np.int32)
    if not isinstance(material, Mapping):
        raise SceneError("material must be a Material or a mapping region name -> Material "
                         "(key 'default' for tets in no named region)")
    names, mats = ["default"], [material.get("default", Material())]
    tet_material = np.zeros(mesh.n_tets, np.int32)
    for name, mat in material.items():
        if name == "default":
            continue
        if not isinstance(mat, Material):
            raise SceneError(f"material[{name!r}] must be a Material, got {type(mat).__name__}")
        reg = mesh.region(name) if name in mesh.regions else None
        if reg is None:
            raise SceneError(f"material region {name!r} is not in the mesh; it has {sorted(mesh.regions)}")
        if reg.tets.size == 0:
            raise SceneError(f"material region {name!r} has no tets (is it a surface region?)")
        tet_material[reg.tets] = len(names)
        names.append(name)
        mats.append(mat)
    return tuple(names), mats, tet_material


def build(
    mesh: TetMesh,
    material: Material | Mapping[str, Material] = Material(),
    *,
    fixed: str | Sequence[int] | Callable | None = None,
    options: Options = Options(),
    actuators: Sequence = (),
    obstacles: Sequence = (),
) -> tuple[Model, Params]:
    """Compile a scene.

    Arguments:
        mesh: the tet mesh.
        material: one :class:`Material`, or a mapping from region names to materials
            (``"default"`` for the rest).
        fixed: the clamped vertices: a region name, vertex indices, a predicate
            ``points (n, 3) -> bool mask (n,)``, or ``None`` for a free body.
        options: :class:`Options`.
        actuators: actuator terms (see :mod:`softbody.actuators`).
        obstacles: obstacles for contact and friction (see :mod:`softbody.contact`).

    Returns:
        ``(model, params)``.

    Raises:
        SceneError: unknown regions, an empty fixed selection, actuators with no tets, ...
        ValueError: bad material values (from :class:`Material`).
    """
    if not isinstance(mesh, TetMesh):
        raise SceneError(f"mesh must be a softbody.meshing.TetMesh, got {type(mesh).__name__}")
    names, mats, tet_material = _materials(mesh, material)
    fixed_idx = _fixed_vertices(mesh, fixed)
    n = mesh.n_vertices
    free = np.ones(n, bool)
    free[fixed_idx] = False

    # Pattern: every tet couples its 4 vertices; rows/columns of fixed vertices keep only
    # their diagonal, so the fixed unknowns decouple (their update is always zero).
    tets = mesh.tets.astype(np.int64)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    keep = (free[rows] & free[cols]) | (rows == cols)
    diag = np.arange(n)
    pattern, index = linsolve.SparsityPattern.from_coo(
        n, np.concatenate([rows[keep], diag]), np.concatenate([cols[keep], diag]))
    nnz = len(pattern.rows)
    local_to_data = np.full(rows.shape, nnz, np.int32)
    local_to_data[keep] = index[: keep.sum()]
    diag_to_data = np.asarray(index[keep.sum():], np.int32)

    terms = tuple(actuators)
    channels: list[str] = []
    for i, term in enumerate(terms):
        if not isinstance(term, Actuator):
            raise SceneError(f"actuators[{i}] is a {type(term).__name__}, not an actuator; give terms from "
                             "softbody.actuators (Muscle, CavityPressure, CavityVolume, PneumaticCells, "
                             "JointTorque, JointServo) or subclasses of softbody._interfaces.Actuator")
        channels.extend(term.channel_names)
    if len(set(channels)) != len(channels):
        raise SceneError(f"actuator channel names must be unique, got {channels}")

    model = Model(
        mesh=mesh, options=options, material_names=names, tet_material=tet_material,
        fixed=fixed_idx, free_mask=free.astype(np.float64)[:, None], pattern=pattern,
        local_to_data=local_to_data, diag_to_data=diag_to_data, terms=terms,
        channel_names=tuple(channels), obstacles=tuple(obstacles),
        stiffness_damping=any(m.beta > 0 for m in mats),
    )
    params = Params(
        E=jnp.asarray([m.E for m in mats], jnp.float64),
        nu=jnp.asarray([m.nu for m in mats], jnp.float64),
        density=jnp.asarray([m.density for m in mats], jnp.float64),
        alpha=jnp.asarray([m.alpha for m in mats], jnp.float64),
        beta=jnp.asarray([m.beta for m in mats], jnp.float64),
        morph=jnp.zeros((n, 3), jnp.float64),
        actuators=tuple(term.init_params() for term in terms),
        obstacles=tuple(ob.init_params() for ob in obstacles),
    )
    return model, params


def initial_state(model: Model, params: Params | None = None, x=None, v=None) -> State:
    """A state at the rest shape (or at ``x``), with velocities ``v`` (default zero).

    Arguments:
        model: the compiled scene.
        params: used for the morphed rest shape when ``x`` is not given.
        x, v: optional ``(n, 3)`` positions and velocities.

    Returns:
        A :class:`State` whose rotations are those of ``x`` (cold-started).

    Raises:
        SceneError: on wrong shapes or non-finite values.
    """
    n = model.n_vertices
    rest = jnp.asarray(model.mesh.points) + (params.morph if params is not None else 0.0)
    x = rest if x is None else jnp.asarray(x, jnp.float64)
    v = jnp.zeros((n, 3)) if v is None else jnp.asarray(v, jnp.float64)
    for name, a in (("x", x), ("v", v)):
        if a.shape != (n, 3):
            raise SceneError(f"initial {name} must have shape ({n}, 3), got {a.shape}")
        if not isinstance(a, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(a))):
            raise SceneError(f"initial {name} has non-finite values")
    from softbody.elastic import deformation_gradient, rest_geometry

    dminv, _ = rest_geometry(model, params.morph if params is not None else jnp.zeros((n, 3)))
    f = deformation_gradient(model, dminv, x)
    return State(x=x, v=v, rot=rotation.cold_start(f), t=jnp.asarray(0.0))


class Prepared(eqx.Module):
    """Per-rollout quantities computed from ``Params`` by :func:`prepare` (differentiable)."""

    dminv: Array  # (3, 3, t) inverse rest edge matrices
    volume: Array  # (t,)
    mass: Array  # (n, 1) lumped masses
    mass_alpha: Array  # (n, 1) alpha-weighted lumped masses (mass damping)
    w_s: Array  # (t,) corotated weight 2 mu
    w_v: Array  # (t,) volume weight 3 lambda
    w_b: Array  # (t,) stiffness damping weight beta * 2 mu
    x_rest: Array  # (n, 3)
    terms: tuple  # per-term prepared data
    obstacles: tuple  # per-obstacle parameters (Params.obstacles)
    data: Array  # (nnz,) PD matrix values
    factor: object  # linear-solver factor
    inertia: Array  # scalar: 1/h^2 for dynamics, 0 for statics
    method: object = None  # the iteration method's per-rollout data (IterationMethod.prepare)


def prepare(model: Model, params: Params, *, static: bool = False) -> Prepared:
    """Rest-shape operators, masses, weights and the factorised PD matrix for ``params``.

    For dynamics the matrix is ``(1/h^2 + alpha/h) M + sum_e V_e (w_s + gamma w_v + beta w_s / h)
    G_e G_e^T + actuator terms``; for statics (``static=True``) the mass and damping parts
    are left out. ``gamma`` is the iteration method's ``volume_weight``: 1 for plain PD
    (its convergence proof needs the true weights), less for L-BFGS, where the matrix is
    only the initial Hessian and a softer volume weight approximates the bending
    stiffness better. Differentiable in ``params``; call it once per rollout.
    """
    from softbody.elastic import local_matrices, rest_geometry

    h = model.options.dt
    dminv, volume = rest_geometry(model, params.morph)
    mat = jnp.asarray(model.tet_material)
    w_s, w_v = pd_weights(params.E[mat], params.nu[mat])
    w_b = params.beta[mat] * w_s
    tets = jnp.asarray(model.mesh.tets)
    quarter = (params.density[mat] * volume / 4.0)[:, None].repeat(4, axis=1)
    mass = jnp.zeros(model.n_vertices).at[tets].add(quarter)
    mass_alpha = jnp.zeros(model.n_vertices).at[tets].add(quarter * params.alpha[mat][:, None])
    x_rest = jnp.asarray(model.mesh.points) + params.morph

    if static:
        inertia, weight = jnp.asarray(0.0), w_s + model.method.volume_weight * w_v
        diag_mass = jnp.zeros_like(mass)
    else:
        inertia, weight = jnp.asarray(1.0 / h**2), w_s + model.method.volume_weight * w_v + w_b / h
        diag_mass = mass / h**2 + mass_alpha / h
    local = local_matrices(dminv, volume * weight)  # (t, 4, 4)
    term_prep = tuple(term.prepare(model, p, dminv, volume) for term, p in zip(model.terms, params.actuators))
    for term, tp in zip(model.terms, term_prep):
        if isinstance(term, ElementActuator):
            local = local.at[tp.tets].add(tp.local_matrices)
    nnz = len(model.pattern.rows)
    data = jnp.zeros(nnz + 1).at[model.local_to_data].add(local.reshape(-1))[:nnz]
    data = data.at[model.diag_to_data].add(diag_mass)
    factor = model.linear_solver.factorize(model.pattern, data)
    return Prepared(dminv=dminv, volume=volume, mass=mass[:, None], mass_alpha=mass_alpha[:, None],
                    w_s=w_s, w_v=w_v, w_b=w_b, x_rest=x_rest, terms=term_prep,
                    obstacles=tuple(params.obstacles), data=data,
                    factor=factor, inertia=inertia, method=model.method.prepare(model, data, factor))

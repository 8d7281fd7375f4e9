"""The data types every layer shares: the static :class:`Model`, the differentiable
:class:`Params`, the :class:`State`, the per-rollout :class:`Prepared` data, per-step
:class:`StepInfo`, the :class:`Options` and :class:`SceneError`.

This is the bottom layer: it imports no strategy (solvers, adjoints, contact) and no
module that builds or steps a scene.

* :class:`Model` is static: topology, fixed vertices, the sparsity pattern of the PD
  matrix and the maps that assemble it, actuator layouts, the skeleton, the composed
  step (coordinates, constraint, solver) and the solver choices. Changing it
  recompiles. It is compared and hashed by content, so an identical scene built again
  reuses the compiled programs.
* :class:`Params` is a pytree of everything differentiable: per-material Young's modulus,
  Poisson's ratio, density and damping, rest-shape morph offsets, actuator design
  parameters. Changing it does not recompile.
* :class:`State` is the pytree ``(x, v, rot, t)``: positions and velocities ``(n, 3)``, the
  per-tet rotation (a unit quaternion ``(4, t)``) of ``x``, kept to warm-start the next
  local step, and the time.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
from collections.abc import Mapping
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve
from softbody.elastic import corner_incidence
from softbody.material import RULES, check_values
from softbody.meshing import TetMesh

Array = jax.Array


class SceneError(ValueError):
    """A scene description is invalid; the message names the problem and the fix."""


#: The scene features that strategies may or may not support (:attr:`Model.features`;
#: :class:`softbody._interfaces.Capabilities`), each with how a scene comes to have it.
FEATURES = {
    "pair contact": "build(rows=[Touch(...)]): bodies touching bodies",
    "contact": "build(obstacles=...) or build(rows=...)",
    "skeleton": "build(skeleton=...)",
    "rigid bodies": "RigidBody",
    "motion": "SoftBody(motion=...)",
    "partly held vertices": "Fix(..., axes=...) with fewer than three axes",
    "velocity forces": "a DissipationTerm, e.g. aero.Drag: air drag and wind",
}


def scene_features(*, contact: bool, pairs: bool, skeleton: bool, rigid: bool, motion: bool,
                   partial: bool, terms=()) -> frozenset[str]:
    """The names in :data:`FEATURES` of the features a scene has (arguments: contact rows,
    pair rows among them, a skeleton of the user's, rigid bodies, moving clamps, partly
    held vertices; and the energy terms, each bringing its ``features``)."""
    present = {"pair contact": pairs, "contact": contact, "skeleton": skeleton, "rigid bodies": rigid,
               "motion": motion, "partly held vertices": partial}
    return frozenset(name for name, has in present.items() if has).union(*(term.features for term in terms))


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
        max_iter: iteration cap per step; a step that hits it reports ``converged=False``
            and ``result == RESULTS.max_iterations``, which ``rollout`` raises unless
            called with ``throw=False``.
        solver: the contact-free nonlinear iteration: :class:`~softbody.solvers.LBFGS`
            or :class:`~softbody.solvers.LocalGlobal` (plain PD); ``None`` (default) lets
            :func:`~softbody.model.build` pick L-BFGS. It runs in the scene's coordinates
            (a skeleton's reduced coordinates where the scene has one).
        contact: the contact solver's settings (:class:`~softbody.contact.Contact`) for a
            scene with contact (obstacles or ``build(rows=...)``); ``None`` (default) lets
            ``build`` use ``Contact()``.
        linear_solver: a :class:`~softbody.linsolve.LinearSolver`; ``None`` lets ``build``
            pick by size.
        rotation_iterations: warm-started Newton steps of the rotation extraction per
            local step.
        adjoint: how gradients are taken: :class:`~softbody.gradients.Implicit` (``None``,
            the default, lets ``build`` pick it) or :class:`~softbody.gradients.Unrolled`.
        integrator: the time stepping of rollouts and policies: ``None`` (default) for
            implicit Euler (:class:`~softbody.simulate.ImplicitEuler`), or
            :class:`~softbody.simulate.BDF2` (second order).

    ``build`` stores a copy with every ``None`` but ``integrator`` resolved in
    ``Model.options`` (:func:`softbody.simulate.integrator_of` resolves that one).
    """

    dt: float = 0.01
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    tol: float = 1e-4
    atol: float = 1e-10
    max_iter: int = 200
    solver: NonlinearSolver | None = None
    contact: Contact | None = None
    linear_solver: linsolve.LinearSolver | None = None
    rotation_iterations: int = 1
    adjoint: Adjoint | None = None
    integrator: Integrator | None = None

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

    @property
    def adjoint_tol(self) -> float:
        """The default relative tolerance of a step's adjoint solve: :attr:`tol` clipped to
        [1e-10, 1e-5]. The step's solution is only ``tol`` accurate, so a tighter adjoint buys
        little; above 1e-5 the adjoint's own error takes over (measurements:
        :class:`~softbody.gradients.Implicit`, :class:`~softbody.contact.Contact`)."""
        return min(max(self.tol, 1e-10), 1e-5)


class Params(eqx.Module):
    """Differentiable parameters (a pytree).

    Attributes:
        E, nu, density, alpha, beta: ``(n_materials,)`` per-material values (see
            :class:`~softbody.material.Material`), in the order of ``Model.material_names``.
        morph: ``(n, 3)`` rest-shape offsets added to the mesh's rest positions.
        rigid_mass: ``(r,)`` the mass of each rigid body (kg), in the order of
            ``Model.bodies``; its inertia scales with it (the shape is fixed).
        actuators: a tuple with one design-parameter pytree per actuator term.
        obstacles: a tuple with one parameter pytree per obstacle (pose, friction, ...).
        rows: a tuple with one parameter pytree per contact row generator of
            ``build(rows=...)``.
    """

    E: Array
    nu: Array
    density: Array
    alpha: Array
    beta: Array
    morph: Array
    rigid_mass: Array
    actuators: tuple = ()
    obstacles: tuple = ()
    rows: tuple = ()

    def __check_init__(self):
        shape = jnp.shape(self.E)
        for name in ("nu", "density", "alpha", "beta"):
            if jnp.shape(getattr(self, name)) != shape:
                raise SceneError(f"Params.{name} has shape {jnp.shape(getattr(self, name))} but Params.E has "
                                 f"{shape}: every material value holds one entry per material")
        if jnp.ndim(self.morph) < 2 or jnp.shape(self.morph)[-1] != 3:
            raise SceneError(f"Params.morph must be (n, 3) rest-shape offsets, got shape {jnp.shape(self.morph)}")

    def replace(self, **changes) -> "Params":
        """A copy with some fields replaced, e.g. ``params.replace(E=params.E * 2)``.

        Concrete material values (``E``, ``nu``, ``density``, ``alpha``, ``beta``) are
        checked against the rules of :class:`~softbody.material.Material` before anything
        compiles; a single number for a scene with one material is taken as that
        material's value. Traced values (inside ``jax.jit``, ``jax.grad``, ``jax.vmap``)
        are used as given.

        Raises:
            SceneError: an unknown field, a material value of the wrong shape (one value
                per material, in the order of ``Model.material_names``), or shapes that do
                not fit together.
            TypeError: a material value that is not numeric.
            ValueError: a material value out of its range (e.g. ``E <= 0``, ``nu >= 0.5``).
        """
        fields = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - fields)
        if unknown:
            raise SceneError(f"Params has no field(s) {unknown}; its fields are {sorted(fields)}")
        for name in RULES.keys() & changes.keys():
            changes[name] = self._material_value(name, changes[name])
        return dataclasses.replace(self, **changes)

    def _material_value(self, name: str, value):
        """``value`` for the material field ``name``, checked and shaped when it is concrete."""
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(value)):
            return value  # traced: checking would need its value
        current = getattr(self, name)
        shape = jnp.shape(current)
        try:
            given = np.shape(value)
        except ValueError:  # ragged nesting: check_values names it
            given = shape
        if given != shape and not (given == () and shape == (1,)):
            why = ("a single number is taken for the one material; with several, give every material's value "
                   f"(e.g. jnp.full({shape[0]}, value)) or change one with params.{name}.at[i].set(value)"
                   if given == () and len(shape) == 1 else "")
            raise SceneError(f"Params.{name} has shape {given} but must have shape {shape}: one value per "
                             "material, in the order of Model.material_names" + (f"; {why}" if why else ""))
        checked = check_values(f"Params.{name}", name, value)
        if isinstance(value, jax.Array) and given == shape:
            return value
        return jnp.broadcast_to(jnp.asarray(checked, jnp.result_type(current)), shape)


class State(eqx.Module):
    """Simulation state: positions ``x`` and velocities ``v`` ``(n, 3)``, rotations ``rot``
    ``(4, t)`` (warm start of the local step), the time ``t`` (s) and, in a scene whose
    contact iteration carries forces, ``contact``: its ``(Model.n_contact_rows, 3)`` force
    rows at the end of the last step (the skin forces of bones and rigid bodies, as the
    iteration scales them, then the forces of the rows between bodies, N, on each row's
    touching vertex), from which the next step's contact iteration starts with
    ``Contact(warm_start=True)``: a warm start, which changes the iterations a step takes,
    not its solution; ``None`` starts from zero forces."""

    x: Array
    v: Array
    rot: Array
    t: Array
    contact: Array | None = None


def _update(h, obj) -> None:
    """Feed ``obj``'s content into the hash ``h``: arrays by dtype, shape and bytes,
    dataclasses by type and fields, containers item by item. Any other object counts by
    identity (a model holding it equals only models holding the same object), so that
    nothing unknown can make two different scenes compare equal."""
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif isinstance(obj, (np.ndarray, np.generic, jax.Array)) and not isinstance(obj, jax.core.Tracer):
        a = np.ascontiguousarray(np.asarray(obj))
        h.update(f"array:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    elif isinstance(obj, (tuple, list)):
        h.update(f"{type(obj).__name__}:{len(obj)}(".encode())
        for item in obj:
            _update(h, item)
        h.update(b")")
    elif isinstance(obj, Mapping):
        h.update(f"mapping:{len(obj)}(".encode())
        for key in sorted(obj, key=repr):
            _update(h, key)
            _update(h, obj[key])
        h.update(b")")
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        h.update(f"{type(obj).__module__}.{type(obj).__qualname__}(".encode())
        for f in dataclasses.fields(obj):
            h.update(f.name.encode())
            _update(h, getattr(obj, f.name))
        h.update(b")")
    else:
        h.update(f"object:{type(obj).__qualname__}:{id(obj)};".encode())


@dataclass(frozen=True, eq=False)
class Model:
    """Static description of a compiled scene. Build it with :func:`~softbody.model.build`.

    Compared and hashed by content (:attr:`digest`), so rebuilding an identical scene
    reuses the compiled programs of the first (``jax.jit`` caches on static arguments).
    """

    mesh: TetMesh
    options: Options
    material_names: tuple[str, ...]
    tet_material: np.ndarray  # (t,) int32 material index per tet
    fixed: np.ndarray  # (k,) int32 indices of the vertices with a held component
    # (n, 1) float64, 1 on free vertices, 0 on held ones; (n, 3), per component, where some
    # vertex is held in fewer than three components (see axis_keep): broadcasts against (n, 3)
    free_mask: np.ndarray
    pattern: linsolve.SparsityPattern
    local_to_data: np.ndarray  # (t*16,) int32 into pattern data; nnz = dropped
    diag_to_data: np.ndarray  # (n,) int32 positions of the diagonal entries
    # per term, (m*k*k,) int32 into pattern data of its stencil's blocks (None without one)
    block_to_data: tuple = ()
    terms: tuple = ()  # actuator terms (see softbody.simulate for the term kinds)
    channel_names: tuple[str, ...] = ()
    obstacles: tuple = ()  # obstacle objects (see softbody.contact.obstacles)
    rows: tuple = ()  # contact row generators besides the obstacles (softbody._interfaces.Rows)
    stiffness_damping: bool = False  # some material had beta > 0 at build time
    rig: object = None  # the skeleton bound to the mesh (softbody.skeleton.Rig), or None
    step: object = None  # the composed step (softbody.solvers.Step) that build resolved
    bodies: tuple = ()  # softbody.scene.BodyPart per body: its vertex and tet ranges, held vertices, motion

    @property
    def n_vertices(self) -> int:
        return self.mesh.n_vertices

    @functools.cached_property
    def features(self) -> frozenset[str]:
        """The scene's features among :data:`FEATURES`: what a strategy must support to
        step it (:class:`softbody._interfaces.Capabilities`)."""
        rigid = sum(part.rigid is not None for part in self.bodies)
        return scene_features(contact=self.has_contact, pairs=any(g.kind == "pair" for g in self.rows),
                              skeleton=self.rig is not None and len(self.rig.skeleton.links) > rigid,
                              rigid=rigid > 0, motion=self.moving, partial=self.free_mask.shape[1] > 1,
                              terms=self.terms)

    @property
    def has_contact(self) -> bool:
        """Whether the scene has contact rows: obstacles or other row generators."""
        return bool(self.obstacles or self.rows)

    @property
    def n_pair_rows(self) -> int:
        """The number of contact rows between bodies (:class:`~softbody._interfaces.PairRows`,
        over all its generators): the last rows of :attr:`State.contact`."""
        return sum(generator.size for generator in self.rows if generator.kind == "pair")

    @property
    def n_contact_rows(self) -> int:
        """The rows of :attr:`State.contact`: the contact iteration's force rows, the
        coordinates' own (:meth:`~softbody._interfaces.Coordinates.contact_rows`: forces on
        the skin of bones and rigid bodies, where they meet obstacles) then
        :attr:`n_pair_rows`; 0 without contact."""
        if not self.has_contact:
            return 0
        return self.step.coordinates.contact_rows() + self.n_pair_rows

    @functools.cached_property
    def vertex_bodies(self) -> np.ndarray | None:
        """``(n,)`` int: each vertex's body, an index into :attr:`bodies`; ``None`` for a
        scene of one body."""
        if len(self.bodies) < 2:
            return None
        return np.repeat(np.arange(len(self.bodies)), [stop - start for start, stop in
                                                        (part.vertices for part in self.bodies)])

    @functools.cached_property
    def contact_blocks(self) -> np.ndarray | None:
        """``(n,)`` int: each vertex's block of Anderson coefficients in the contact iteration
        (:func:`softbody.contact.anderson.mix`): one per body, so that bodies that do not touch
        each other converge as each would alone, and one for the bodies that rows between
        bodies (:class:`~softbody._interfaces.PairRows`) couple. ``None`` where that is one
        block for the whole scene. In a step with pair rows the forward iteration joins only
        the bodies that the step's rows join (``softbody.contact.solver._touching_groups``);
        these static blocks serve the implicit derivative's linear solve."""
        body = self.vertex_bodies
        if body is None:
            return None
        root = list(range(len(self.bodies)))

        def find(i):
            while root[i] != i:
                i = root[i]
            return i

        for generator in self.rows:
            if generator.kind == "pair":
                touched = sorted({find(int(b)) for b in np.unique(body[generator.vertices()])})
                for b in touched[1:]:
                    root[b] = touched[0]
        roots = np.array([find(i) for i in range(len(self.bodies))])
        label = np.unique(roots, return_inverse=True)[1]
        return None if label.max() == 0 else label[body]

    @property
    def n_tets(self) -> int:
        return self.mesh.n_tets

    @property
    def moving(self) -> bool:
        """Whether some body's held vertices follow a prescribed motion."""
        return any(part.motion is not None for part in self.bodies)

    def body(self, name: str | None):
        """The :class:`~softbody.scene.BodyPart` of the body called ``name``.

        Raises:
            SceneError: no such body (naming those there are).
        """
        for part in self.bodies:
            if part.name == name:
                return part
        raise SceneError(f"no body {name!r} in this scene; it has {[p.name for p in self.bodies]}")

    @functools.cached_property
    def corner_incidence(self) -> np.ndarray:
        """``(n, K)`` int32: each vertex's tet corners (see :func:`softbody.elastic.corner_incidence`)."""
        return corner_incidence(self.mesh.tets, self.n_vertices)

    @functools.cached_property
    def axis_keep(self) -> np.ndarray | None:
        """``(3, nnz)`` float64: 1 where axis ``a``'s PD matrix keeps the pattern's entry (both
        vertices free along ``a``, or a diagonal); ``None`` when no vertex is held in fewer than
        three components (``free_mask`` then has one column and one matrix serves all axes)."""
        if self.free_mask.shape[1] == 1:
            return None
        rows, cols = self.pattern.rows, self.pattern.cols
        free = self.free_mask > 0
        return ((free[rows] & free[cols]) | (rows == cols)[:, None]).T.astype(np.float64)

    @property
    def n_channels(self) -> int:
        return len(self.channel_names)

    @functools.cached_property
    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)``, each ``(n_channels,)``: the range of every control channel
        (:meth:`softbody._interfaces.Term.channel_bounds`), in ``channel_names`` order."""
        bounds = [term.channel_bounds() for term in self.terms]
        if not bounds:
            return np.zeros(0), np.zeros(0)
        return (np.concatenate([np.asarray(lo, np.float64) for lo, _ in bounds]),
                np.concatenate([np.asarray(hi, np.float64) for _, hi in bounds]))

    @property
    def linear_solver(self) -> linsolve.LinearSolver:
        """The linear solver in use (resolved by :func:`~softbody.model.build`)."""
        return self.options.linear_solver

    @functools.cached_property
    def digest(self) -> str:
        """A digest of the model's content (arrays by their bytes; see ``_update``): two
        models built from equal scenes have equal digests."""
        h = hashlib.sha256()
        for f in dataclasses.fields(self):
            _update(h, getattr(self, f.name))
        return h.hexdigest()

    def __hash__(self):
        return hash(self.digest)

    def __eq__(self, other):
        return self is other or (type(other) is type(self) and self.digest == other.digest)


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
    step: object = None  # the step's per-rollout data (Step.prepare)
    rows: tuple = ()  # per-generator parameters (Params.rows)
    # the objective's inertia term (softbody.inertia.Dynamics(h) or Statics(); static: it fixes
    # the programs): a time step of size h the matrix was prefactored for, or a static solve
    inertia: object = eqx.field(static=True, default=None)

    @property
    def dt(self) -> float:
        """The step size ``h`` the steps take (0 for a static solve)."""
        return self.inertia.dt


class RESULTS(enum.IntEnum):
    """How a step (or static solve) ended: the codes in :attr:`StepInfo.result`.

    * ``success`` (0): the step met its tolerance.
    * ``max_iterations`` (1): it stopped at the iteration cap (``Options.max_iter``)
      without meeting its tolerance (``Options.tol``); ``StepInfo.residual`` holds the
      relative residual it reached.
    * ``nonfinite`` (2): the positions, the velocities or the force residual became NaN or
      inf. In a rollout every later step carries this code too (the state is not
      advanced past it).
    * ``inverted`` (3): the step ended with more inverted tets (``det F <= 0``) than the
      initial state had (``StepInfo.inverted`` holds the count).
    * ``overflow`` (4): a contact search between bodies found more candidate pairs than
      its fixed capacity holds (``StepInfo.overflow``): contacts may be missing from the
      step. Rebuild with a larger capacity (``Touch(..., capacity=...)``).
    * ``tunnelled`` (5): surfaces kept apart by rows between bodies passed through each
      other during the step (``StepInfo.tunnelled`` counts the surface pairs that met, by
      continuous collision detection of the step's straight-line motion): the rows, chosen
      at the step's start and predicted end, missed the crossing. Reduce ``Options.dt``.

    A step with several of these reports the first in the order inverted, nonfinite,
    tunnelled, overflow, max_iterations (inverted tets usually cause the rest). Codes are plain integers:
    ``traj.info.result == RESULTS.max_iterations`` works on the arrays.
    """

    success = 0
    max_iterations = 1
    nonfinite = 2
    inverted = 3
    overflow = 4
    tunnelled = 5

    @property
    def message(self) -> str:
        """A one-line description of the code."""
        return _RESULT_MESSAGES[self]

    @staticmethod
    def of(*, finite, converged, inverted, inverted0, overflow=False, tunnelled=0) -> Array:
        """The int32 code of steps (elementwise): ``inverted`` where ``inverted > inverted0``,
        else ``nonfinite`` where not ``finite``, else ``tunnelled`` where surfaces passed
        through each other (``tunnelled > 0``: certain, where an overflow only may have lost
        contacts), else ``overflow`` where a contact search overflowed, else
        ``max_iterations`` where not ``converged``, else ``success``."""
        code = jnp.where(converged, int(RESULTS.success), int(RESULTS.max_iterations))
        code = jnp.where(overflow, int(RESULTS.overflow), code)
        code = jnp.where(tunnelled > 0, int(RESULTS.tunnelled), code)
        code = jnp.where(finite, code, int(RESULTS.nonfinite))
        return jnp.where(inverted > inverted0, int(RESULTS.inverted), code).astype(jnp.int32)


_RESULT_MESSAGES = {
    RESULTS.success: "the step met its tolerance",
    RESULTS.max_iterations: "the step stopped at the iteration cap (Options.max_iter) without meeting its tolerance",
    RESULTS.nonfinite: "the state or the force residual became non-finite (NaN/inf)",
    RESULTS.inverted: "the step ended with more inverted tets (det F <= 0) than the initial state had",
    RESULTS.overflow: "a contact search between bodies overflowed its capacity: contacts may be missing",
    RESULTS.tunnelled: "surfaces kept apart by rows between bodies passed through each other during the step",
}


class StepInfo(eqx.Module):
    """Per-step solver statistics (arrays; stacked over steps in a rollout)."""

    iterations: Array
    evaluations: Array
    residual: Array  # |grad Phi| / (|M s / h^2| + atol / tol): the relative residual reached
    converged: Array
    inverted: Array  # number of inverted (det F <= 0) tets at the step's end
    result: Array  # int32 RESULTS code: how the step ended
    fallback: Array  # bool: a contact step's fast iteration (ActiveSet) fell short and the proven
    #   splitting iteration finished the step (softbody.contact.Contact)
    overflow: Array  # bool: a contact search between bodies overflowed its capacity (RESULTS.overflow)
    tunnelled: Array  # int: surface pairs that passed through each other during the step (RESULTS.tunnelled)

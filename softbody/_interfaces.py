"""The interfaces that strategies and scene parts implement (the bottom layer, with
:mod:`softbody._types`, the only module of softbody it imports: it imports no strategy).

**Energy terms.** The objective of an implicit step is the inertia of the scene plus a sum
of energy terms (:class:`Term`): the bodies' elasticity and damping, actuators (muscles,
cavities, pneumatic cells, joint torques and servos) and whatever a user adds (a spring
between two bodies, a membrane on a surface). A term contributes in one of four ways,
one base class each, so that the step dispatches on the type of a term rather than on
which methods it happens to have:

* :class:`ElementTerm`: a PD-style element term on a set of tets
  (``energy_and_stress``; its ``4 x 4`` PD matrix blocks join the prefactored matrix),
  e.g. muscles.
* :class:`VertexTerm`: an energy of the vertex positions (``energy_and_gradient``), e.g.
  cavity pressure, joint torques and servos, springs. It may add constant ``k x k`` blocks
  on tuples of ``k <= 4`` vertices to the prefactored matrix (:meth:`VertexTerm.stencil`,
  :meth:`VertexTerm.blocks`), as ShapeOp's constraints add their triplets.
* :class:`VolumeTerm`: new targets for the volume term of some tets
  (``volume_targets``), e.g. pneumatic cells.
* :class:`DissipationTerm`: a dissipation potential of the velocities (``dissipation``),
  e.g. air drag and wind on a sheet; a step adds ``h D((x - x_n)/h)`` to its objective.
* :class:`VolumeElement`: a :class:`VertexTerm` that replaces the volume term of some tets
  (an element technology that does not lock for nearly incompressible materials).

An actuator is a term with named control channels, each with the range of values it
accepts (:meth:`Term.channel_bounds`); every term has design parameters (``init_params``,
differentiable, in ``params.actuators``) and per-rollout data (``prepare``).

**Contact rows.** Contact is made of rows (:class:`Rows` generators, each giving a
:class:`Frame` per vertex: gap, normal, surface velocity, friction, restitution). The
scene's obstacles are one generator; a test or a user adds others with
``build(rows=[...])``; the contact solver meets them all alike. Rows that couple
vertices of the scene (a vertex touching a triangle of another body) come from
:class:`PairRows` generators (:class:`PairFrame`): their forces act on both sides.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, ClassVar, Mapping, NamedTuple

import jax.numpy as jnp
import numpy as np

from softbody._types import FEATURES, SceneError


@dataclasses.dataclass(frozen=True)
class Capabilities:
    """The scene features (:data:`softbody._types.FEATURES`) a strategy cannot handle,
    each with the reason, and what to use instead: the one table from which
    :func:`softbody.model.build` (for the strategies in ``Options``) and the reference
    integrators refuse a scene before anything compiles (the pattern of MJX's
    ``put_model``). Every strategy declares its own (``capabilities``, a class attribute);
    the default supports every feature.

    Attributes:
        refuses: feature -> why the strategy cannot step a scene with it, a phrase that
            follows the strategy's name ("has no contact handling").
        instead: what to use for such a scene.
    """

    refuses: Mapping[str, str] = dataclasses.field(default_factory=dict)
    instead: str = ""

    def __post_init__(self):
        unknown = set(self.refuses) - set(FEATURES)
        if unknown:
            raise ValueError(f"unknown scene features {sorted(unknown)}; the features are {list(FEATURES)}")
        if "contact" in self.refuses and "pair contact" not in self.refuses:  # pair rows are contact rows
            object.__setattr__(self, "refuses", {"pair contact": self.refuses["contact"], **self.refuses})

    @property
    def supported(self) -> tuple[str, ...]:
        """The features this strategy supports, in :data:`~softbody._types.FEATURES` order."""
        return tuple(f for f in FEATURES if f not in self.refuses)

    def check(self, features, what: str) -> None:
        """Refuse a scene whose ``features`` this strategy does not support.

        Arguments:
            features: the scene's features (:attr:`softbody._types.Model.features`).
            what: the strategy as the user named it, e.g. ``"Options(adjoint=Unrolled())"``.

        Raises:
            SceneError: naming the first unsupported feature, why, what to use instead and
                every feature the strategy supports.
        """
        for feature in FEATURES:
            if feature in features and feature in self.refuses:
                supported = ", ".join(self.supported) or "none of them"
                raise SceneError(f"{what} {self.refuses[feature]} (the scene has {feature}: {FEATURES[feature]}); "
                                 f"{self.instead}. Of the scene features {list(FEATURES)}, it supports: {supported}")


class Term:
    """Base class of the energy terms of a step's objective.

    Subclasses set ``channel_names`` (a tuple of unique names, one per control channel;
    :class:`VertexTerm` defaults to none) and implement :meth:`init_params`,
    :meth:`prepare` and the method of their kind.
    """

    channel_names: tuple[str, ...]

    #: The scene features (:data:`softbody._types.FEATURES`) a scene with this term has.
    features: ClassVar[frozenset[str]] = frozenset()

    def channel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The range ``lower <= a <= upper`` of each channel's activation.

        Concrete controls outside it are refused before a simulation starts; inside a
        traced computation (an optimisation) values are clipped to it, with zero gradient
        beyond. Unbounded by default.

        Returns:
            ``(lower, upper)``, float arrays of shape ``(n_channels,)`` (``-inf``/``inf``
            where unbounded).
        """
        n = len(self.channel_names)
        return np.full(n, -np.inf), np.full(n, np.inf)

    def bind(self, rig) -> "Term":
        """The term as :func:`softbody.model.build` keeps it in a scene whose skeleton,
        bound to the mesh, is ``rig`` (a :class:`softbody.skeleton.Rig`, or ``None`` for a
        scene without one). The default returns the term itself.

        Raises:
            SceneError: the term needs what the scene lacks (e.g. joints without a skeleton).
        """
        return self

    #: The attributes that hold indices into the body's mesh: name -> ``"vertices"`` or ``"tets"``.
    mesh_indices: ClassVar[Mapping[str, str]] = {}

    def placed(self, prefix: str, vertices: int, tets: int) -> "Term":
        """The term of a body in a scene (:func:`softbody.scene.assemble`): the body's
        vertices start at index ``vertices`` of the scene's vertex array and its tets at
        ``tets``; its channels are named ``prefix + name``. The default shifts the
        attributes named in :attr:`mesh_indices` and prefixes ``channel_names`` (a field),
        and returns the term itself where nothing changes.

        Raises:
            SceneError: the term acts on no body's mesh (joint actuators act on the
                scene's skeleton: they go to ``build(actuators=...)``).
        """
        if not self.mesh_indices:
            raise SceneError(f"{type(self).__name__} acts on the scene's skeleton, not on one body's mesh: give "
                             "it to build(..., actuators=[...]), not to SoftBody(actuators=...)")
        if not prefix and vertices == 0 and tets == 0:
            return self  # the one unnamed body of a scene: nothing moves or is renamed
        shift = {"vertices": vertices, "tets": tets}
        changes = {key: np.asarray(getattr(self, key)) + shift[kind] for key, kind in self.mesh_indices.items()}
        if self.channel_names:
            changes["channel_names"] = tuple(prefix + c for c in self.channel_names)
        return dataclasses.replace(self, **changes)

    def init_params(self):
        """The term's differentiable design parameters (a pytree; ``()`` for none)."""
        raise NotImplementedError

    def prepare(self, model, params, dminv, volume):
        """Per-rollout data from the design parameters ``params``, the rest shape's inverse
        edge matrices ``dminv`` ``(3, 3, t)`` and tet volumes ``volume`` ``(t,)``."""
        raise NotImplementedError


class ElementTerm(Term):
    """An element term on the tets ``prep.tets`` ``(m,)``.

    ``prepare`` returns data with ``tets`` and ``local_matrices`` ``(m, 4, 4)`` (the term's
    blocks of the PD matrix).
    """

    def energy_and_stress(self, f, prep, activation):
        """``(energy (m,), dE/dF (3, 3, m))`` for the deformation gradients ``f``
        ``(3, 3, m)`` of the term's tets and the term's activations ``(c,)``."""
        raise NotImplementedError


class VertexTerm(Term):
    """An energy ``E(x)`` of the positions.

    It may add constant blocks to the prefactored PD matrix: :meth:`stencil` names the
    vertex tuples (static) and :meth:`blocks` their ``k x k`` weights (from the prepared
    data, so they may depend on design parameters). For a term in PD form,
    ``E = sum_e w_e/2 |sum_a c_ea x_a - p_e(x)|^2`` with projections ``p_e``, a tuple's block
    is ``w_e c_e c_e^T``: the matrix then majorises the term's Hessian, and local-global
    steps and the contact splitting keep their convergence. A term without blocks is
    handled by the nonlinear solver alone (L-BFGS learns its curvature).

    Without control channels by default (``channel_names = ()``); ``init_params`` and
    ``prepare`` default to none (``()``).
    """

    channel_names: tuple[str, ...] = ()

    def init_params(self):
        """No design parameters (``()``) unless a subclass has some."""
        return ()

    def prepare(self, model, params, dminv, volume):
        """No per-rollout data (``()``) unless a subclass needs some."""
        return ()

    def energy_and_gradient(self, x, prep, activation):
        """``(energy, dE/dx (n, 3))`` at positions ``x`` ``(n, 3)``."""
        raise NotImplementedError

    def stencil(self) -> np.ndarray | None:
        """``(m, k)`` ints, ``2 <= k <= 4``: the scene's vertex indices of each of the term's
        blocks of the PD matrix, or ``None`` (default) for a term that adds none. Static:
        read once by :func:`softbody.model.build`."""
        return None

    def blocks(self, prep):
        """``(m, k, k)``: the symmetric positive semi-definite weights of the blocks on
        :meth:`stencil`'s tuples, from the term's prepared data (N/m: they join the scalar
        ``n x n`` matrix, applied to each coordinate)."""
        raise NotImplementedError

    def mass(self, prep):
        """``(m, k)`` lumped masses (kg) that the vertices of :meth:`stencil`'s tuples gain
        (inertia and weight, e.g. a membrane's areal density), from the prepared data; or
        ``None`` (default) for a term without mass."""
        return None


class VolumeElement(VertexTerm):
    """A :class:`VertexTerm` that carries the volume energy of the tets ``tets`` (static
    ``(m,)`` scene tet indices) in place of their own per-tet volume term: for those tets
    :func:`softbody.model.prepare` keeps only the corotated weight ``w_s`` (their volume
    weight is 0 in the tet energy and in the PD matrix) and hands the term the volume
    weights ``w_v = 3 lambda`` ``(t,)`` of every tet (differentiable in ``E`` and ``nu``),
    e.g. a nodally averaged volume that does not lock for ``nu -> 0.5``
    (:class:`softbody.nodal.NodalVolume`). :class:`VolumeTerm` targets would not reach those
    tets: :func:`softbody.model.build` refuses a volume term whose static ``tets`` overlap them.
    """

    tets: np.ndarray

    def prepare(self, model, params, dminv, volume, w_v=None):
        """Per-rollout data; ``w_v`` ``(t,)``: the volume weights ``3 lambda`` of the scene's tets."""
        raise NotImplementedError


class DissipationTerm(Term):
    """A force of the velocities that derives from a dissipation potential ``D(v)`` (W):
    the force is ``-dD/dv``, e.g. air drag and wind on triangles
    (:class:`softbody.aero.Drag`).

    An implicit step of size ``h`` from ``x_n`` adds ``h D((x - x_n)/h)`` to its objective
    (gradient ``dD/dv``), with the term's geometry read at the step's start ``x_n``: for a
    convex ``D`` the step stays a convex problem in the term, and its stationary point
    balances the force at the step's end velocity. A static objective (a static solve, or
    the forces an explicit step takes) holds the force at the given velocities ``v_n`` as a
    constant load (a static solve has ``v_n = 0``: wind on a body at rest).

    It adds no blocks to the prefactored PD matrix (its curvature depends on the velocity):
    the nonlinear solver learns it. Without control channels; ``init_params`` and
    ``prepare`` default to none (``()``).
    """

    channel_names: tuple[str, ...] = ()
    features: ClassVar[frozenset[str]] = frozenset({"velocity forces"})

    def init_params(self):
        """No design parameters (``()``) unless a subclass has some."""
        return ()

    def prepare(self, model, params, dminv, volume):
        """No per-rollout data (``()``) unless a subclass needs some."""
        return ()

    def dissipation(self, v, x, prep, activation):
        """``(D (), dD/dv (n, 3))`` at velocities ``v`` ``(n, 3)`` (m/s), with the term's
        geometry (e.g. a triangle's normal) taken at positions ``x`` ``(n, 3)``."""
        raise NotImplementedError


class VolumeTerm(Term):
    """New targets of the volume term on some tets."""

    def volume_targets(self, prep, activation):
        """``(tets (m,), s (m,))``: the volume term of those tets targets ``det F = s^3``."""
        raise NotImplementedError


class Frame(NamedTuple):
    """The contact rows on some points: one row per point, in its contact frame.

    Attributes:
        phi: ``(m,)`` signed gap, m (< 0: the point lies inside; a point with no row has a
            gap beyond reach, e.g. ``jnp.inf``).
        normal: ``(m, 3)`` unit normals, pointing out of what the point touches.
        velocity: ``(m, 3)`` the velocity of the touched surface's material there, m/s
            (friction acts on the point's motion relative to it).
        mu_s, mu_k: ``(m,)`` static and kinetic friction coefficients (``mu_k <= mu_s``).
        restitution: ``(m,)`` coefficients of restitution in [0, 1].
    """

    phi: object
    normal: object
    velocity: object
    mu_s: object
    mu_k: object
    restitution: object

    @staticmethod
    def deepest(frames) -> "Frame":
        """Per point, the row of smallest gap among ``frames`` (each a :class:`Frame` of the
        same ``m`` points; the first on a tie). A selection, not a weighted sum: rows not
        chosen contribute nothing, not even a non-finite value."""
        if len(frames) == 1:
            return frames[0]
        pick = jnp.argmin(jnp.stack([f.phi for f in frames]), axis=0)  # (m,)

        def choose(column):
            return functools.reduce(
                lambda acc, k: jnp.where((pick == k).reshape(pick.shape + (1,) * (acc.ndim - 1)), column[k], acc),
                range(1, len(column)), column[0])

        return Frame(*(choose(column) for column in zip(*frames)))


class Rows:
    """A generator of contact rows: the constraints that keep points out of something.

    A row couples a vertex to what it must not enter (an obstacle, a moving plane that
    holds a few vertices, ...), with the gap, normal, surface velocity, friction and
    restitution of :class:`Frame`. The contact solver (:class:`softbody.contact.Contact`)
    asks every generator of a scene for its rows at trial positions and, on a vertex that
    several generators reach, keeps the deepest row; it knows nothing else about them.
    The scene's obstacles are one generator (:class:`softbody.contact.obstacles.ObstacleRows`);
    :func:`softbody.model.build` takes others as ``rows=[...]``. A row couples one vertex
    here; rows on vertex pairs and triangles (bodies touching bodies) will carry their
    vertices and barycentric weights.

    A generator is static (hashable: compare by identity or content); its design
    parameters (``init_params``, in ``params.rows``) are differentiable, and the step's
    implicit derivative reaches them through the frame.
    """

    #: rows on one vertex each (:class:`PairRows` are ``"pair"``)
    kind: ClassVar[str] = "vertex"

    def init_params(self):
        """The generator's design parameters (a pytree; ``()``: none)."""
        return ()

    def check(self, params) -> None:
        """Refuse malformed parameters before anything compiles (raises ``ValueError``)."""

    def frame(self, points, index, params, time) -> Frame:
        """The rows on some points.

        Arguments:
            points: ``(m, 3)`` trial positions of the scene's vertices ``index``.
            index: ``(m,)`` int vertex indices of ``points`` (traced: compare, gather).
            params: the generator's parameters; time: the step's end time, s.

        Returns:
            A :class:`Frame` of ``m`` rows (``phi = inf`` where the generator has none).
        """
        raise NotImplementedError


class PairFrame(NamedTuple):
    """Contact rows that couple several vertices (a vertex and a triangle of a surface):
    one row per entry, its gap a weighted sum of the vertices' positions along its normal.

    Attributes:
        vertices: ``(m, 4)`` int vertex indices of each row (the touching vertex first).
        weights: ``(m, 4)`` the row's weights on them (``1`` on the touching vertex, minus
            the barycentric coordinates of the touched point on the triangle's): the
            row's relative position is ``sum_a weights_a x_a``, and a force ``f`` on the
            row acts as ``weights_a f`` on vertex ``a``.
        phi: ``(m,)`` signed gap, m (< 0: inside; ``inf`` on a row that is not there).
        normal: ``(m, 3)`` unit normals, pointing from the touched surface to the vertex.
        mu_s, mu_k: ``(m,)`` static and kinetic friction coefficients (``mu_k <= mu_s``).
        restitution: ``(m,)`` coefficients of restitution in [0, 1].
    """

    vertices: object
    weights: object
    phi: object
    normal: object
    mu_s: object
    mu_k: object
    restitution: object


class PairRows:
    """A generator of contact rows between vertices of the scene (bodies touching bodies).

    Each row keeps a vertex out of a triangle of another surface (:class:`PairFrame`);
    the contact force of a row acts on both sides, distributed by the row's weights. The
    contact solver (:class:`softbody.contact.Contact`) asks the generator once per step
    which rows there are (:meth:`select`, at the step's start and its predicted end,
    outside differentiation: the contact set of a step is fixed), then for their frames at
    trial positions (:meth:`frame`, differentiable).

    A generator is static (hashable); :func:`softbody.model.build` binds it to the scene's
    mesh (:meth:`bind`), which resolves the names it was given into vertex and triangle
    indices; its parameters (``init_params``, in ``params.rows``) are differentiable.
    """

    kind: ClassVar[str] = "pair"
    #: the number of rows the generator puts on a step (static; set by :meth:`bind`)
    size: int = 0

    def init_params(self):
        """The generator's design parameters (a pytree)."""
        return ()

    def check(self, params) -> None:
        """Refuse malformed parameters before anything compiles (raises ``ValueError``)."""

    def bind(self, mesh, parts) -> "PairRows":
        """The generator on a scene: ``mesh`` the scene's :class:`~softbody.meshing.TetMesh`,
        ``parts`` its bodies (:class:`softbody.scene.BodyPart`). Raises ``SceneError`` on
        names that are not the scene's."""
        raise NotImplementedError

    def vertices(self):
        """The scene's vertices this generator's rows may touch, ``(k,)`` static ints (after
        :meth:`bind`). The bodies holding them share one set of Anderson coefficients in the
        contact iteration (:attr:`softbody._types.Model.contact_blocks`)."""
        raise NotImplementedError

    def select(self, x_start, x_end, params):
        """The rows of one step, chosen from the positions ``x_start`` and ``x_end``
        ``(n, 3)`` at the step's start and its predicted end (not differentiated).

        Returns:
            ``(rows, overflow)``: ``rows`` a pytree of fixed shapes (what :meth:`frame`
            reads), ``overflow`` a bool, true where the search for them overflowed a fixed
            capacity (the step then ends with ``RESULTS.overflow``).
        """
        raise NotImplementedError

    def frame(self, x, selection, params) -> PairFrame:
        """The :class:`PairFrame` of :attr:`size` rows of ``selection`` at positions ``x``
        ``(n, 3)``."""
        raise NotImplementedError

    def contact_distance(self, params):
        """The distance at which the rows hold the surfaces apart, m (a scalar): a row whose
        gap is predicted below minus this at a step's end is an impact, and the contact
        solver starts that step's iteration where the body first touches. The default is 0."""
        return jnp.asarray(0.0)

    def crossed(self, x_start, x_end, params):
        """Whether the surfaces this generator keeps apart passed through each other during
        a step that moved every vertex on a straight line from ``x_start`` to ``x_end``
        ``(n, 3)`` (not differentiated): ``(count, overflow)``, the int32 number of surface
        pairs that met and a bool, true where the search for them overflowed. The default
        checks nothing (``(0, False)``)."""
        return jnp.asarray(0, jnp.int32), jnp.asarray(False)


class Coordinates:
    """The unknowns of an implicit step: how positions are parametrised.

    :class:`softbody.solvers.Vertices` moves every free vertex; a skeleton's
    :class:`softbody.skeleton.Reduced` places its bones by forward kinematics of joint
    coordinates. A step (:class:`softbody.solvers.Step`) combines coordinates with a
    nonlinear solver and, with contact rows, a contact constraint; each method below is
    what one of those parts needs from the coordinates.
    """

    #: the scene features these coordinates cannot step (:class:`Capabilities`)
    capabilities: ClassVar[Capabilities] = Capabilities()

    def volume_weight(self, solver) -> float:
        """The scale of the volume term in the prefactored PD matrix for ``solver``."""
        raise NotImplementedError

    def prepare(self, model, data, factor):
        """Per-rollout data (a pytree or ``None``) from the PD matrix values ``data``
        ``(nnz,)`` and their factorisation; handed back as ``problem.prepared``."""
        raise NotImplementedError

    def implicit_chart(self, prepared, x, free):
        """The chart in which a step's solution is stationary (see
        :meth:`softbody.solvers.Step.implicit_chart`); ``None`` for the free vertices."""
        raise NotImplementedError

    def chart(self, problem) -> "Chart":
        """The :class:`Chart` in which a nonlinear solver minimises the step objective of
        ``problem`` (a :class:`softbody.solvers.StepProblem`) without contact."""
        raise NotImplementedError

    def contact_rows(self) -> int:
        """The number ``e`` of extra rows of :meth:`contact_sweep`'s iterate (static): the
        contact forces on vertices that the per-vertex step does not move; 0 by default."""
        return 0

    def contact_sweep(self, problem, p, law) -> "ContactSweep":
        """The parts of the contact splitting iteration that depend on the coordinates.

        Arguments:
            problem: the step's :class:`softbody.solvers.StepProblem`.
            p: ``(n, 1)`` the splitting's sweep diagonal ``M/h^2 + D``.
            law: the per-vertex contact step on some vertices, ``(y (c, 3), index (c,),
                valid (c,), kinetic=False) -> (touching (c,), stick (c,), correction (c, 3),
                normal (c, 3))`` for trial positions ``y`` of the scene's vertices ``index``
                (see :class:`softbody.contact.Contact`), for coordinates whose own unknowns
                touch obstacles; ``kinetic=True``: one cone per vertex and step, the kinetic
                one for vertices sliding at the step's start, else the static one
                (``softbody.contact.law.SLIDING_SPEED``).

        Returns:
            A :class:`ContactSweep`.
        """
        raise NotImplementedError


class Chart:
    """Coordinates in which a nonlinear solver descends on one step's objective ``Phi``.

    Made by :meth:`Coordinates.chart` for a step problem. The solvers of
    :mod:`softbody.solvers` (L-BFGS, local-global) are written once against it and run in
    any coordinates. A *point* is the chart's pytree for one iterate (it holds the
    positions); a *tangent* is an array of the chart's own shape (the free vertices'
    ``(n, 3)`` for plain coordinates; the soft vertices and joint tangents, flat, for a
    skeleton's). The solver steps from a point along a tangent ``step`` by :meth:`move`.

    Attributes:
        backtracks: how often a step that fails Armijo's test is halved before the solver
            gives up on it (static). Zero where the plain preconditioned step always
            descends (the PD matrix majorises the objective).
    """

    backtracks: ClassVar[int] = 0

    def start(self, x0):
        """The point at positions ``x0`` ``(n, 3)`` (the positions it holds may differ:
        a skeleton places its bones)."""
        raise NotImplementedError

    def positions(self, point):
        """``(n, 3)``: the positions of ``point``."""
        raise NotImplementedError

    def evaluate(self, point, q):
        """``(phi, g (n, 3), q)``: the step objective at ``point`` (rotations warm-started
        from ``q``)."""
        raise NotImplementedError

    def gradient(self, point, g):
        """``(r, gnorm, data)``: the objective's gradient ``g`` ``(n, 3)`` as a tangent
        ``r`` (zero on what may not move this iteration), its norm (the convergence
        measure) and data that :meth:`precondition` and :meth:`pair` take (a pytree)."""
        raise NotImplementedError

    def precondition(self, point, data, r):
        """``H0 r``: the initial inverse Hessian (the PD matrix's solve) on a tangent."""
        raise NotImplementedError

    def project(self, data, d):
        """A direction ``d`` with what may not move this iteration (as :meth:`gradient`
        masks it) taken out; the identity unless the chart holds some of its coordinates."""
        return d

    def move(self, point, step):
        """The point reached from ``point`` along the tangent ``step``."""
        raise NotImplementedError

    def pair(self, point, data, g, new, data_new, g_new, step):
        """``(s, y)`` flat: the curvature pair of the step ``step`` from ``point`` to ``new``
        (with gradients ``g``, ``g_new`` ``(n, 3)``), for L-BFGS's history."""
        raise NotImplementedError


class RigidParts(NamedTuple):
    """How a step's coordinates move vertices that do not move alone (bones, rigid
    bodies), for the pair rows' force updates (:attr:`ContactSweep.rigid`).

    Attributes:
        compliance: ``(n, 1)`` a vertex's compliance to a force on it, m/N: ``1 / P`` on
            the vertices that move alone; on a rigid part the diagonal of its Delassus
            operator ``B K^-1 B^T`` (mean over the three axes).
        body: ``(n,)`` static ints, the part of each vertex: its own index for a vertex
            that moves alone, one label ``>= n`` for all vertices of one rigid part. Pair
            rows split a part's compliance among the rows that touch it (mass splitting).
        respond: ``aux -> ((X_new, force (n, 3)) -> X_new)``: for an iteration's ``aux``
            (as ``place`` gave it), the iterate moved by its coordinates' response to the
            extra forces ``force`` on the vertices: ``force / P`` on the vertices that move alone, the
            linearised rigid motion ``B K^-1 B^T force`` on a rigid part; it may also relax
            the coordinates' own extra rows (a rigid part's obstacle forces), whose change the
            contact iteration counts in its residual.
        sweeps: how many Jacobi updates of the pair rows' forces each iteration runs
            (static): rows on one rigid part couple through its motion.
    """

    compliance: object
    body: np.ndarray
    respond: Callable
    sweeps: int = 1


class ContactSweep(NamedTuple):
    """What the contact iteration needs from a step's coordinates
    (:meth:`Coordinates.contact_sweep`).

    The iterate of the contact iteration is ``X`` ``(n + e, 3)``: the positions, then
    ``e`` rows of the coordinates' own (the contact forces on vertices that the per-vertex
    step does not move, each row belonging to one vertex).

    Attributes:
        touching: ``(n, 1)`` marks the vertices that the per-vertex contact step moves.
        place: ``X -> (x, aux)`` puts an iterate's positions ``(n, 3)`` on the
            coordinates' manifold.
        sweep: ``(X, x_new, g, aux) -> (X_new, r)`` moves the remaining unknowns by their
            block of the splitting (``x_new`` holds the per-vertex step's new positions)
            and returns the new iterate and the residual ``r`` (forces, N) of the
            remaining unknowns.
        owners: ``(e,)`` static ints, the vertex of each extra row.
        scale: ``(e, 1)`` the weight of each extra row (an extra row times its ``scale`` is a
            force; ``sqrt(scale)`` weighs it in Anderson's least squares, as ``sqrt(P)`` a
            position row).
        forces: ``X -> (e, 3)``: the contact forces that the extra rows hold, N.
        rigid: ``None`` where every vertex moves alone, else the :class:`RigidParts` that
            pair rows on vertices of rigid parts (bones, rigid bodies) need.
    """

    touching: object
    place: Callable
    sweep: Callable
    owners: np.ndarray
    scale: object
    forces: Callable
    rigid: tuple | None = None


class Integrator:
    """A time integrator: what one step of a rollout does (the pattern of optax's
    ``init``/``update``). :func:`softbody.simulate.rollout`, the closed-loop
    :func:`softbody.control.policy_rollout` and :func:`softbody.explicit.explicit_rollout`
    run one loop (:func:`softbody.simulate.integrate`) over an integrator: it calls
    :meth:`init` once, then :meth:`step` per step, and sets each step's result code and
    the failure handling (``throw``) the same way for all. An integrator may carry a
    memory from step to step (a multistep method's earlier states). Its
    :attr:`capabilities` name the scene features it cannot step (``build`` refuses them).
    """

    capabilities: ClassVar[Capabilities] = Capabilities()

    def init(self, model, params, state0):
        """``(prep, memory)``: the per-rollout data (the prepared scene,
        :class:`softbody._types.Prepared`) and the memory the first step gets."""
        raise NotImplementedError

    def step(self, model, prep, state, memory, activation, force):
        """Advance ``state`` (:class:`softbody._types.State`) by one step under the
        ``(n_channels,)`` ``activation`` and the ``(n, 3)`` ``force`` (or ``None``).

        Returns:
            ``(next_state, next_memory, info)``: the :class:`softbody._types.State`, the
            memory of the next step and the step's :class:`softbody._types.StepInfo` (its
            ``result`` is set by the loop).
        """
        raise NotImplementedError

    def templates(self, model, call: str) -> tuple[str, ...]:
        """The failure messages of a step (``{step}`` stands for its index), one per
        variant of :func:`softbody.simulate._first_failure`; ``call`` names the function
        a user called."""
        raise NotImplementedError

    def starts(self, model, prep, xs, vs, t0, activation0, force0):
        """For an implicit integrator, what each step of a computed trajectory solved (see
        :meth:`softbody.simulate.ImplicitEuler.starts`); the explicit one has none."""
        raise NotImplementedError

"""Scene compilation: ``TetMesh`` + materials + skeleton + obstacles + options -> static
``Model`` + traced ``Params``.

:func:`build` checks a scene and resolves its defaults once: it composes the step from the
scene (the coordinates: plain vertices, or the skeleton's reduced coordinates; the
constraint: contact where there are obstacles) and the options (the nonlinear solver, the
linear solver, the adjoint), and refuses a combination it does not support before anything
compiles; :func:`prepare` computes everything that depends on
``Params`` (rest-shape operators, volumes, masses, weights, the PD matrix and its
factorisation), once per rollout; :func:`initial_state` makes a :class:`State`. The data
types themselves live in :mod:`softbody._types`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve, rotation
from softbody._interfaces import Actuator, ElementActuator
from softbody._types import Model, Options, Params, Prepared, SceneError, State
from softbody.contact import Contact
from softbody.elastic import deformation_gradient, local_matrices, rest_geometry
from softbody.gradients import Adjoint, Implicit, Unrolled
from softbody.material import Material, pd_weights
from softbody.meshing import TetMesh
from softbody.obstacles import check_motion
from softbody.skeleton import Reduced, Rig, Skeleton, SkeletonError
from softbody.solvers import LBFGS, NonlinearSolver, Step, Vertices

Array = jax.Array


AXES = "xyz"


@dataclasses.dataclass(frozen=True)
class Fix:
    """Vertices held in chosen components of their position (a scene part for ``build(fixed=...)``).

    ``Fix("clamp")`` holds every component (a clamp, what a bare selection means);
    ``Fix(selection, axes="y")`` holds only ``y``: the vertices slide freely in ``x`` and
    ``z``, as on a roller or a symmetry plane ``y = const``; holding ``z`` on every vertex of
    a one-layer extrusion (``Fix(lambda p: np.ones(len(p), bool), axes="z")``) makes it
    plane strain.

    Arguments:
        where: a region name, vertex indices, or a predicate ``points (n, 3) -> bool mask (n,)``.
        axes: the held components, a non-empty subset of ``"xyz"`` (world axes).

    Raises:
        SceneError: axes that are not a non-empty subset of ``"xyz"``.
    """

    where: str | Sequence[int] | Callable
    axes: str = AXES

    def __post_init__(self):
        if (not isinstance(self.axes, str) or not self.axes or len(set(self.axes)) != len(self.axes)
                or not set(self.axes) <= set(AXES)):
            raise SceneError(f"Fix.axes must name held components once each from 'xyz' (e.g. 'xyz', 'y', 'xz'), "
                             f"got {self.axes!r}")


def _selection(mesh: TetMesh, where) -> np.ndarray:
    """The vertex indices a region name, index list or predicate selects (non-empty)."""
    if isinstance(where, str):
        if where not in mesh.regions:
            raise SceneError(f"fixed region {where!r} is not in the mesh; it has {sorted(mesh.regions)}")
        idx = mesh.regions[where].vertices
    elif callable(where):
        mask = np.asarray(where(mesh.points), bool)
        if mask.shape != (mesh.n_vertices,):
            raise SceneError(f"the fixed predicate must return a boolean mask of shape ({mesh.n_vertices},)")
        idx = np.flatnonzero(mask)
    else:
        idx = np.unique(np.asarray(where, np.int64))
        if idx.size and (idx.min() < 0 or idx.max() >= mesh.n_vertices):
            raise SceneError("fixed vertex indices out of range")
    if len(idx) == 0:
        raise SceneError(f"the fixed selection {where if isinstance(where, str) else ''!s} holds no vertices; "
                         "check the region or predicate, or pass fixed=None for a free body")
    return np.asarray(idx, np.int64)


def _fixed_mask(mesh: TetMesh, fixed) -> np.ndarray:
    """``(n, 3)`` bool: the held components of every vertex (see :func:`build`'s ``fixed``)."""
    held = np.zeros((mesh.n_vertices, 3), bool)
    if fixed is None:
        return held
    several = isinstance(fixed, (list, tuple)) and any(isinstance(f, Fix) for f in fixed)
    if several and not all(isinstance(f, Fix) for f in fixed):
        raise SceneError("fixed is a list mixing Fix parts with other items: give one selection, one Fix, or a "
                         "list of Fix parts (e.g. [Fix('clamp'), Fix('symmetry', axes='y')])")
    for part in fixed if several else [fixed]:
        part = part if isinstance(part, Fix) else Fix(part)
        held[np.ix_(_selection(mesh, part.where), [AXES.index(a) for a in part.axes])] = True
    return held


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


def _check_motion(motion, fixed: np.ndarray) -> None:
    """Refuse a clamp motion without fixed vertices, or one that is not ``t -> (R, p)``."""
    if motion is None:
        return
    check_motion(motion, "build", SceneError)
    if len(fixed) == 0:
        raise SceneError("motion moves the fixed vertices, but the scene has none: pass fixed=... to build")


def clamp(model: Model, x, x_rest, time):
    """``x`` with the held components of the fixed vertices where the prescribed motion puts
    them at ``time`` (the free components of a partly held vertex keep their values).

    Arguments:
        model: a scene built with ``motion``; x: ``(n, 3)`` positions; x_rest: ``(n, 3)``
        rest positions (morph included); time: the time, s.

    Returns:
        ``(n, 3)`` positions.
    """
    rot, shift = model.motion(jnp.asarray(time, jnp.float64))
    idx = jnp.asarray(model.fixed)
    target = jnp.asarray(x_rest)[idx] @ jnp.asarray(rot).T + jnp.asarray(shift)
    held = jnp.asarray(model.free_mask[model.fixed] == 0)
    return x.at[idx].set(jnp.where(held, target, x[idx]))


def _rig(mesh: TetMesh, skeleton, free: np.ndarray) -> Rig | None:
    """The skeleton bound to the mesh (``None`` without one), with no fixed bone vertex."""
    if skeleton is None:
        return None
    if not isinstance(skeleton, Skeleton):
        raise SceneError(f"skeleton must be a softbody.skeleton.Skeleton, got {type(skeleton).__name__}")
    rig = skeleton.bind(mesh)
    if not np.all(free[rig.bone]):
        raise SkeletonError("some bone vertices are fixed; bones move with their joints (weld a bone to the "
                            "world with a root Fixed() joint instead)")
    return rig


def _check_partial(skeleton, obstacles) -> None:
    """Refuse partly held vertices where the step cannot hold them yet."""
    if skeleton is not None:
        raise SceneError("a scene with a skeleton holds vertices in all three components only: fix them with "
                         "fixed=<selection> (or a Fix with axes='xyz'), or weld a bone with a root Fixed() joint")
    if obstacles:
        raise SceneError("contact holds vertices in all three components only: a scene with obstacles cannot "
                         "use Fix(..., axes=...) with fewer than three axes yet; model the support as an "
                         "obstacle (softbody.obstacles.Plane) or clamp the vertices fully")


def _compose(options: Options, rig: Rig | None, obstacles: tuple) -> Step:
    """The step of a scene: its coordinates, its contact constraint and the solver, checked
    together (every refusal here happens before anything compiles)."""
    coordinates = Vertices() if rig is None else Reduced(rig)
    solver = options.solver if options.solver is not None else LBFGS()
    if not isinstance(solver, NonlinearSolver):
        raise SceneError(f"Options.solver must be a nonlinear solver (softbody.solvers.LBFGS() or LocalGlobal()), "
                         f"got {solver!r}")
    if not isinstance(solver, coordinates.solvers):
        where = "a scene with a skeleton" if rig is not None else "this scene"
        raise SceneError(f"{where} runs the solvers {[c.__name__ for c in coordinates.solvers]}, not "
                         f"{type(solver).__name__}; pass one of them as Options(solver=...)")
    if options.contact is not None and not isinstance(options.contact, Contact):
        raise SceneError(f"Options.contact must be a softbody.contact.Contact, got {options.contact!r}")
    if options.contact is not None and not obstacles:
        raise SceneError("Options.contact sets the contact solver, but the scene has no obstacles: add "
                         "obstacles=[...] to build, or leave Options.contact at None")
    if not isinstance(options.adjoint, Adjoint):
        raise SceneError(f"Options.adjoint must be Implicit(), ImplicitForward() or Unrolled(), got "
                         f"{options.adjoint!r}")
    if obstacles and isinstance(options.adjoint, Unrolled):
        raise SceneError("Unrolled differentiates the iterations as they ran, but a step with contact is "
                         "differentiated through the fixed point of its contact iteration "
                         "(softbody.fixed_point); use the default adjoint, Implicit() (or ImplicitForward())")
    contact = (options.contact or Contact()) if obstacles else None
    if contact is not None and rig is not None and contact.active_set is not None:
        raise SceneError("Contact(active_set=...) works in vertex coordinates; a scene with a skeleton has "
                         "reduced coordinates, whose contact steps run the splitting alone: use "
                         "Contact(active_set=None)")
    return Step(coordinates, solver, contact)


def build(
    mesh: TetMesh,
    material: Material | Mapping[str, Material] = Material(),
    *,
    fixed: str | Sequence[int] | Callable | None = None,
    skeleton: Skeleton | None = None,
    motion: Callable | None = None,
    options: Options = Options(),
    actuators: Sequence = (),
    obstacles: Sequence = (),
) -> tuple[Model, Params]:
    """Compile a scene.

    Arguments:
        mesh: the tet mesh.
        material: one :class:`Material`, or a mapping from region names to materials
            (``"default"`` for the rest).
        fixed: the held vertices: a region name, vertex indices or a predicate
            ``points (n, 3) -> bool mask (n,)`` (clamped in all three components), a
            :class:`Fix` (``Fix("symmetry", axes="y")`` holds only ``y``: a roller or a
            symmetry plane), a list of :class:`Fix` parts, or ``None`` for a free body.
            Partly held vertices are refused with a skeleton or obstacles.
        skeleton: a :class:`~softbody.skeleton.Skeleton` over ``bone:`` regions of the
            mesh, or ``None``; the scene then steps in its reduced coordinates
            (``model.rig`` is the skeleton bound to the mesh).
        motion: a prescribed rigid motion of the fixed vertices (a moving clamp):
            ``t -> (R (3, 3), p (3,))``, JAX-traceable in the time ``t`` (s); at time ``t``
            a fixed vertex with rest position ``X`` (morph included) sits at ``R X + p``
            (in its held components).
            ``None`` (default): the fixed vertices stay where they start. Implicit steps
            (:func:`~softbody.simulate.step`, rollouts, policies) follow it; the explicit
            and Newton reference integrators refuse it.
        options: :class:`Options`.
        actuators: actuator terms (see :mod:`softbody.actuators`).
        obstacles: obstacles for contact and friction (see :mod:`softbody.obstacles`).

    Returns:
        ``(model, params)``.

    Raises:
        SceneError: unknown regions, an empty fixed selection, actuators with no tets, a
            combination of scene and options that the step does not support, ...
        SkeletonError: a skeleton that does not fit the mesh, or a fixed bone vertex.
        ValueError: bad material values (from :class:`Material`).
    """
    if not isinstance(mesh, TetMesh):
        raise SceneError(f"mesh must be a softbody.meshing.TetMesh, got {type(mesh).__name__}")
    names, mats, tet_material = _materials(mesh, material)
    held = _fixed_mask(mesh, fixed)
    fixed_idx = np.flatnonzero(held.any(axis=1)).astype(np.int32)
    n = mesh.n_vertices
    free = ~held.any(axis=1)  # vertices with no held component
    partial = bool(np.any(held.any(axis=1) & ~held.all(axis=1)))

    # Pattern: every tet couples its 4 vertices; rows/columns of vertices held in all three
    # components keep only their diagonal, so those unknowns decouple (their update is
    # always zero). Partly held vertices keep their couplings: the matrix of axis a drops
    # them where a vertex is held along a (Model.axis_keep), one factorisation per axis.
    tets = mesh.tets.astype(np.int64)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    moving = ~held.all(axis=1)
    keep = (moving[rows] & moving[cols]) | (rows == cols)
    diag = np.arange(n)
    pattern, index = linsolve.SparsityPattern.from_coo(
        n, np.concatenate([rows[keep], diag]), np.concatenate([cols[keep], diag]))
    nnz = len(pattern.rows)
    local_to_data = np.full(rows.shape, nnz, np.int32)
    local_to_data[keep] = index[: keep.sum()]
    diag_to_data = np.asarray(index[keep.sum():], np.int32)
    if partial:
        _check_partial(skeleton, obstacles)

    _check_motion(motion, fixed_idx)
    rig = _rig(mesh, skeleton, free)
    terms = []
    channels: list[str] = []
    for i, term in enumerate(actuators):
        if not isinstance(term, Actuator):
            raise SceneError(f"actuators[{i}] is a {type(term).__name__}, not an actuator; give terms from "
                             "softbody.actuators (Muscle, CavityPressure, CavityVolume, PneumaticCells, "
                             "JointTorque, JointServo) or subclasses of softbody._interfaces.Actuator")
        terms.append(term.bind(rig))
        channels.extend(term.channel_names)
    if len(set(channels)) != len(channels):
        raise SceneError(f"actuator channel names must be unique, got {channels}")

    adjoint = options.adjoint if options.adjoint is not None else Implicit()
    linear_solver = options.linear_solver or linsolve.auto_solver(pattern.n)
    if partial and not isinstance(linear_solver, linsolve.PerColumn):
        linear_solver = linsolve.PerColumn(linear_solver)
    options = dataclasses.replace(options, linear_solver=linear_solver, adjoint=adjoint)
    step = _compose(options, rig, tuple(obstacles))
    options = dataclasses.replace(options, solver=step.solver, contact=step.contact)
    model = Model(
        mesh=mesh, options=options, material_names=names, tet_material=tet_material,
        fixed=fixed_idx, free_mask=(~held).astype(np.float64) if partial else free.astype(np.float64)[:, None],
        pattern=pattern, local_to_data=local_to_data, diag_to_data=diag_to_data,
        terms=tuple(terms), channel_names=tuple(channels), obstacles=tuple(obstacles),
        stiffness_damping=any(m.beta > 0 for m in mats), rig=rig, step=step, motion=motion,
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
    """A state at the rest shape (or at ``x``), with velocities ``v`` (default zero). With a
    prescribed ``motion`` the fixed vertices of the rest shape start where it puts them at
    ``t = 0``.

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
    if x is None and model.motion is not None:
        rest = clamp(model, rest, rest, 0.0)
    x = rest if x is None else jnp.asarray(x, jnp.float64)
    v = jnp.zeros((n, 3)) if v is None else jnp.asarray(v, jnp.float64)
    for name, a in (("x", x), ("v", v)):
        if a.shape != (n, 3):
            raise SceneError(f"initial {name} must have shape ({n}, 3), got {a.shape}")
        if not isinstance(a, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(a))):
            raise SceneError(f"initial {name} has non-finite values")
    dminv, _ = rest_geometry(model, params.morph if params is not None else jnp.zeros((n, 3)))
    f = deformation_gradient(model, dminv, x)
    return State(x=x, v=v, rot=rotation.cold_start(f), t=jnp.asarray(0.0))


def prepare(model: Model, params: Params, *, static: bool = False) -> Prepared:
    """Rest-shape operators, masses, weights and the factorised PD matrix for ``params``.

    For dynamics the matrix is ``(1/h^2 + alpha/h) M + sum_e V_e (w_s + gamma w_v + beta w_s / h)
    G_e G_e^T + actuator terms``; for statics (``static=True``) the mass and damping parts
    are left out. ``gamma`` is the step's ``volume_weight``: 1 for plain PD
    (its convergence proof needs the true weights), less for L-BFGS, where the matrix is
    only the initial Hessian and a softer volume weight approximates the bending
    stiffness better. Differentiable in ``params``; call it once per rollout.
    """
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
        inertia, weight = jnp.asarray(0.0), w_s + model.step.volume_weight * w_v
        diag_mass = jnp.zeros_like(mass)
    else:
        inertia, weight = jnp.asarray(1.0 / h**2), w_s + model.step.volume_weight * w_v + w_b / h
        diag_mass = mass / h**2 + mass_alpha / h
    local = local_matrices(dminv, volume * weight)  # (t, 4, 4)
    term_prep = tuple(term.prepare(model, p, dminv, volume) for term, p in zip(model.terms, params.actuators))
    for term, tp in zip(model.terms, term_prep):
        if isinstance(term, ElementActuator):
            local = local.at[tp.tets].add(tp.local_matrices)
    nnz = len(model.pattern.rows)
    data = jnp.zeros(nnz + 1).at[model.local_to_data].add(local.reshape(-1))[:nnz]
    data = data.at[model.diag_to_data].add(diag_mass)
    # With partly held vertices, one matrix per axis (linsolve.PerColumn): each drops the
    # couplings of the vertices held along its axis.
    factor = model.linear_solver.factorize(
        model.pattern, data if model.axis_keep is None else data * jnp.asarray(model.axis_keep))
    return Prepared(dminv=dminv, volume=volume, mass=mass[:, None], mass_alpha=mass_alpha[:, None],
                    w_s=w_s, w_v=w_v, w_b=w_b, x_rest=x_rest, terms=term_prep,
                    obstacles=tuple(params.obstacles), data=data,
                    factor=factor, inertia=inertia, step=model.step.prepare(model, data, factor))

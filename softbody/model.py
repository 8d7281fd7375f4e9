"""Scene compilation: bodies (:mod:`softbody.scene`) + skeleton + obstacles + options -> static
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
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from softbody import linsolve, rotation
from softbody._interfaces import (Capabilities, ElementTerm, Integrator, PairRows, Rows, Term, VertexTerm,
                                  VolumeElement, VolumeTerm)
from softbody.rigid import RigidBody
from softbody.scene import SoftBody, assemble
from softbody._types import Model, Options, Params, Prepared, SceneError, State, scene_features
from softbody.contact import Contact
from softbody.elastic import deformation_gradient, local_matrices, rest_geometry
from softbody.inertia import Dynamics, Statics
from softbody.gradients import Adjoint, Implicit
from softbody.material import pd_weights
from softbody.contact.obstacles import ObstacleRows
from softbody.skeleton import Reduced, Rig, Skeleton, SkeletonError
from softbody.solvers import LBFGS, NonlinearSolver, Step, Vertices

Array = jax.Array


def clamp(model: Model, x, x_rest, time):
    """``x`` with the held components of the moving bodies' fixed vertices where their
    prescribed motions put them at ``time`` (the free components of a partly held vertex
    keep their values).

    Arguments:
        model: a scene with a body built with ``motion``; x: ``(n, 3)`` positions; x_rest:
        ``(n, 3)`` rest positions (morph included); time: the time, s.

    Returns:
        ``(n, 3)`` positions.
    """
    for part in model.bodies:
        if part.motion is None:
            continue
        rot, shift = part.motion(jnp.asarray(time, jnp.float64))
        idx = jnp.asarray(part.fixed)
        target = jnp.asarray(x_rest)[idx] @ jnp.asarray(rot).T + jnp.asarray(shift)
        held = jnp.asarray(model.free_mask[part.fixed] == 0)
        x = x.at[idx].set(jnp.where(held, target, x[idx]))
    return x


def _rig(mesh, skeleton, free: np.ndarray, scene) -> Rig | None:
    """The skeleton bound to the mesh, with a root link per rigid body (``None`` with neither),
    and no fixed bone vertex."""
    if skeleton is None and not scene.links:
        return None
    if skeleton is not None and not isinstance(skeleton, Skeleton):
        raise SceneError(f"skeleton must be a softbody.skeleton.Skeleton, got {type(skeleton).__name__}")
    links = () if skeleton is None else skeleton.links
    for link in links:
        for part in scene.parts:
            if part.rigid is None:
                continue
            if link.name == part.name:
                raise SkeletonError(f"link {link.name!r} has the name of rigid body {part.name!r}, whose own link "
                                    "it is; rename the link")
            region = mesh.regions.get(link.bone)
            if region is not None and np.any((region.vertices >= part.vertices[0])
                                             & (region.vertices < part.vertices[1])):
                raise SkeletonError(f"link {link.name!r}: bone region {link.bone!r} holds vertices of rigid body "
                                    f"{part.name!r}; a rigid body moves by its own 6 dofs and cannot be a bone: "
                                    "make the bone a region of a soft body")
    rig = (skeleton if not scene.links else Skeleton((*links, *scene.links))).bind(mesh)
    if not np.all(free[rig.bone]):
        raise SkeletonError("some bone vertices are fixed; bones move with their joints (weld a bone to the "
                            "world with a root Fixed() joint instead)")
    return rig


def _check_capabilities(features: frozenset, options: Options, reduced: bool) -> None:
    """The capability table: every strategy the step will compose (its coordinates, reduced
    with a skeleton or rigid bodies; contact and its fast iteration; the options' integrator
    and adjoint) refuses the scene features it cannot handle
    (:class:`~softbody._interfaces.Capabilities`, class attributes), before anything is
    bound or compiled."""
    scene = "a scene with a skeleton" if "skeleton" in features else "a scene with rigid bodies"
    strategies = [(scene, Reduced if reduced else Vertices)]
    if "contact" in features:
        contact = options.contact if options.contact is not None else Contact()
        strategies += [("contact", contact),
                       ("Contact(active_set=ActiveSet())", getattr(contact, "active_set", None))]
    adjoint = options.adjoint if options.adjoint is not None else Implicit()
    strategies += [(f"Options({name}={type(strategy).__name__}())", strategy)
                   for name, strategy in (("integrator", options.integrator), ("adjoint", adjoint))]
    for what, strategy in strategies:
        capabilities = getattr(strategy, "capabilities", None)  # a wrong type is refused by _compose
        if isinstance(capabilities, Capabilities):
            capabilities.check(features, what)


def _stencils(terms, n: int) -> list:
    """Each term's PD-block stencil ``(m, k)`` int64 (:meth:`VertexTerm.stencil`), or ``None``.

    Raises:
        SceneError: a stencil that is not ``(m, k)`` integers with ``2 <= k <= 4``, an index
            outside the scene's vertices, or a tuple that repeats a vertex.
    """
    out = []
    for term in terms:
        stencil = term.stencil() if isinstance(term, VertexTerm) else None
        if stencil is not None:
            name = type(term).__name__
            a = np.asarray(stencil)
            if a.ndim != 2 or not 2 <= a.shape[1] <= 4 or not np.issubdtype(a.dtype, np.integer):
                raise SceneError(f"{name}: stencil() must be (m, k) vertex indices with 2 <= k <= 4 (the contact "
                                 f"splitting's convergence proof covers blocks on at most 4 vertices), got "
                                 f"{a.dtype} of shape {a.shape}")
            if a.size and (a.min() < 0 or a.max() >= n):
                raise SceneError(f"{name}: stencil() indices must lie in [0, {n}) (the scene's vertices), got "
                                 f"[{a.min()}, {a.max()}]")
            if np.any(np.sort(a, axis=1)[:, 1:] == np.sort(a, axis=1)[:, :-1]):
                raise SceneError(f"{name}: a stencil tuple repeats a vertex; each block couples distinct vertices")
            stencil = a.astype(np.int64)
        out.append(stencil)
    return out


def _compose(options: Options, rig: Rig | None, contact_rows: bool, parts: tuple) -> Step:
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
    if options.contact is not None and not contact_rows:
        raise SceneError("Options.contact sets the contact solver, but the scene has no obstacles or contact rows: "
                         "add obstacles=[...] (or rows=[...]) to build, or leave Options.contact at None")
    if options.integrator is not None and not isinstance(options.integrator, Integrator):
        raise SceneError(f"Options.integrator must be None (implicit Euler) or an integrator such as "
                         f"softbody.simulate.BDF2(), got {options.integrator!r}")
    if not isinstance(options.adjoint, Adjoint):
        raise SceneError(f"Options.adjoint must be Implicit(), ImplicitForward() or Unrolled(), got "
                         f"{options.adjoint!r}")
    contact = (options.contact or Contact()) if contact_rows else None
    if contact is not None and contact.adjoint_tol is None:
        contact = dataclasses.replace(contact, adjoint_tol=options.adjoint_tol)
    n = parts[-1].vertices[1]
    if contact is not None and contact.blocks and contact.blocks[-1][1] != n:
        raise SceneError(f"Contact.blocks must end at the scene's {n} vertices, got {contact.blocks!r}; leave it at "
                         "() for one block per body (bodies that rows between bodies couple share one)")
    return Step(coordinates, solver, contact)


def build(
    bodies: SoftBody | RigidBody | Sequence[SoftBody | RigidBody],
    *,
    skeleton: Skeleton | None = None,
    actuators: Sequence = (),
    terms: Sequence = (),
    obstacles: Sequence = (),
    rows: Sequence = (),
    options: Options = Options(),
) -> tuple[Model, Params]:
    """Compile a scene: its bodies and what acts between them.

    Arguments:
        bodies: one :class:`~softbody.scene.SoftBody` (a tet mesh with its materials, held
            vertices, their motion and its actuators) or a list of them, each named (see
            :mod:`softbody.scene`). They are concatenated into one vertex array, in order.
            Partly held vertices are refused with a skeleton or contact; implicit steps
            (:func:`~softbody.simulate.step`, rollouts, policies) follow a body's
            ``motion``, the explicit and Newton reference integrators refuse it. A
            :class:`~softbody.rigid.RigidBody` (always named) joins as a 6-dof root link of
            the scene's reduced coordinates (see :mod:`softbody.scene`); its mass is
            ``params.rigid_mass``; it touches obstacles with its surface vertices.
        skeleton: a :class:`~softbody.skeleton.Skeleton` over ``bone:`` regions of the
            scene's mesh, or ``None``; the scene then steps in its reduced coordinates
            (``model.rig`` is the skeleton bound to the mesh).
        actuators: the terms that act on the skeleton (``JointTorque``, ``JointServo``);
            the terms on a body's elements belong to its ``SoftBody(actuators=...)``.
        terms: energy terms on the scene's vertex indices
            (:class:`~softbody._interfaces.Term` subclasses: a spring between two bodies,
            a membrane on a surface, ...). A :class:`~softbody._interfaces.VertexTerm`'s
            ``stencil()`` blocks join the PD matrix. Their channels follow the actuators'.
        obstacles: obstacles for contact and friction (see :mod:`softbody.contact.obstacles`).
        rows: other contact row generators (:class:`~softbody._interfaces.Rows`: constraints
            that keep vertices out of something, with friction); the contact solver meets
            them as it meets the obstacles' rows. Their parameters are ``params.rows``.
        options: :class:`Options`.

    Returns:
        ``(model, params)``.

    Raises:
        SceneError: no bodies, repeated or missing body names, unknown regions, an empty
            fixed selection, actuators with no tets or in the wrong place, a combination
            of scene and options that the step does not support, ...
        SkeletonError: a skeleton that does not fit the mesh, a fixed bone vertex, or a bone
            in a rigid body.
        ValueError: bad material values (from :class:`Material`).
    """
    scene = assemble(bodies)
    mesh, mats, held = scene.mesh, scene.materials, scene.held
    fixed_idx = np.flatnonzero(held.any(axis=1)).astype(np.int32)
    n = mesh.n_vertices
    free = ~held.any(axis=1)  # vertices with no held component
    partial = bool(np.any(held.any(axis=1) & ~held.all(axis=1)))

    # Pattern: every tet couples its 4 vertices; rows/columns of vertices held in all three
    # components keep only their diagonal, so those unknowns decouple (their update is
    # always zero). Partly held vertices keep their couplings: the matrix of axis a drops
    # them where a vertex is held along a (Model.axis_keep), one factorisation per axis.
    for i, term in enumerate(terms):
        if not isinstance(term, Term):
            raise SceneError(f"terms[{i}] is a {type(term).__name__}, not an energy term; subclass "
                             "softbody._interfaces.VertexTerm (or ElementTerm, VolumeTerm, DissipationTerm)")
    generators = tuple(rows)  # (the name rows is the pattern's below)
    for i, generator in enumerate(generators):
        if not isinstance(generator, (Rows, PairRows)):
            raise SceneError(f"rows[{i}] is a {type(generator).__name__}, not a contact row generator; give "
                             "softbody.contact.pairs.Touch(...) for bodies touching bodies, or subclass "
                             "softbody._interfaces.Rows (obstacles go in obstacles=[...])")
    generators = tuple(g.bind(mesh, scene.parts) if isinstance(g, PairRows) else g for g in generators)
    stencils = _stencils((*scene.terms, *actuators, *terms), n)
    tets = mesh.tets.astype(np.int64)
    blocks = [tets] + [s for s in stencils if s is not None]  # each (m, k): its k x k entries
    rows = np.concatenate([np.repeat(b, b.shape[1], axis=1).ravel() for b in blocks])
    cols = np.concatenate([np.tile(b, (1, b.shape[1])).ravel() for b in blocks])
    moving = ~held.all(axis=1)
    keep = (moving[rows] & moving[cols]) | (rows == cols)
    diag = np.arange(n)
    pattern, index = linsolve.SparsityPattern.from_coo(
        n, np.concatenate([rows[keep], diag]), np.concatenate([cols[keep], diag]))
    nnz = len(pattern.rows)
    entry_to_data = np.full(rows.shape, nnz, np.int32)  # nnz: an entry dropped with a held vertex
    entry_to_data[keep] = index[: keep.sum()]
    diag_to_data = np.asarray(index[keep.sum():], np.int32)
    local_to_data, offset = entry_to_data[: tets.size * 4], tets.size * 4
    block_to_data = []
    for s in stencils:
        block_to_data.append(None if s is None else entry_to_data[offset: offset + s.size * s.shape[1]])
        offset += 0 if s is None else s.size * s.shape[1]
    features = scene_features(
        contact=bool(obstacles or generators), pairs=any(g.kind == "pair" for g in generators),
        skeleton=isinstance(skeleton, Skeleton) and bool(skeleton.links),
        rigid=bool(scene.links), motion=any(part.motion is not None for part in scene.parts), partial=partial,
        terms=[t for t in (*scene.terms, *actuators, *terms) if isinstance(t, Term)])
    _check_capabilities(features, options, reduced=skeleton is not None or bool(scene.links))
    rig = _rig(mesh, skeleton, free, scene)
    rigid = tuple(part for part in scene.parts if part.rigid is not None)
    for i, term in enumerate(actuators):
        if not isinstance(term, Term):
            raise SceneError(f"actuators[{i}] is a {type(term).__name__}, not an actuator; give the skeleton's "
                             "terms from softbody.actuators (JointTorque, JointServo) or subclasses of "
                             "softbody._interfaces.Term")
        if term.mesh_indices:
            raise SceneError(f"actuators[{i}] ({type(term).__name__}) acts on a body's elements: give it to that "
                             "body, SoftBody(mesh, material, actuators=[...])")
    terms = [term.bind(rig) for term in (*scene.terms, *actuators, *terms)]
    covered = np.concatenate([np.asarray(t.tets).ravel() for t in terms if isinstance(t, VolumeElement)] or [[]])
    if len(np.unique(covered)) != len(covered):
        raise SceneError("two volume elements (e.g. NodalVolume) cover the same tets; give each tet's volume to one "
                         "of them")
    for term in terms:  # volume targets (pneumatic cells) act on the per-tet volume term, which those tets lack
        if isinstance(term, VolumeTerm) and np.isin(np.asarray(getattr(term, "tets", [])), covered).any():
            raise SceneError(f"{type(term).__name__} sets volume targets on tets that a volume element (e.g. "
                             "NodalVolume) covers, where they would not act; leave those tets out of the element "
                             "(NodalVolume.on(mesh, tets=...))")
    channels = [c for term in terms for c in term.channel_names]
    if len(set(channels)) != len(channels):
        raise SceneError(f"actuator channel names must be unique, got {channels}")

    adjoint = options.adjoint if options.adjoint is not None else Implicit()
    linear_solver = options.linear_solver or linsolve.auto_solver(pattern.n)
    if partial and not isinstance(linear_solver, linsolve.PerColumn):
        linear_solver = linsolve.PerColumn(linear_solver)
    options = dataclasses.replace(options, linear_solver=linear_solver, adjoint=adjoint)
    step = _compose(options, rig, bool(obstacles or generators), scene.parts)
    options = dataclasses.replace(options, solver=step.solver, contact=step.contact)
    model = Model(
        mesh=mesh, options=options, material_names=scene.material_names, tet_material=scene.tet_material,
        fixed=fixed_idx, free_mask=(~held).astype(np.float64) if partial else free.astype(np.float64)[:, None],
        pattern=pattern, local_to_data=local_to_data, diag_to_data=diag_to_data,
        block_to_data=tuple(block_to_data),
        terms=tuple(terms), channel_names=tuple(channels), obstacles=tuple(obstacles),
        rows=generators, stiffness_damping=any(m.beta > 0 for m in mats), rig=rig, step=step, bodies=scene.parts,
    )
    params = Params(
        E=jnp.asarray([m.E for m in mats], jnp.float64),
        nu=jnp.asarray([m.nu for m in mats], jnp.float64),
        density=jnp.asarray([m.density for m in mats], jnp.float64),
        alpha=jnp.asarray([m.alpha for m in mats], jnp.float64),
        beta=jnp.asarray([m.beta for m in mats], jnp.float64),
        morph=jnp.zeros((n, 3), jnp.float64),
        rigid_mass=jnp.asarray([p.rigid.mass for p in rigid], jnp.float64),
        actuators=tuple(term.init_params() for term in terms),
        obstacles=ObstacleRows(tuple(obstacles)).init_params(),
        rows=tuple(generator.init_params() for generator in generators),
    )
    return model, params


def _rigid_velocities(model: Model) -> Array:
    """``(n, 3)``: the rigid bodies' initial velocities ``v0 + omega0 x (x - x0)`` on their
    vertices (at their initial placement), zero elsewhere."""
    v = np.zeros((model.n_vertices, 3))
    for part in model.bodies:
        if part.rigid is not None:
            body, (start, stop) = part.rigid, part.vertices
            v[start:stop] = body.v0 + np.cross(body.omega0, model.mesh.points[start:stop] - body.x0)
    return jnp.asarray(v)


def initial_state(model: Model, params: Params | None = None, x=None, v=None) -> State:
    """A state at the rest shape (or at ``x``), with velocities ``v`` (default: zero on soft
    bodies, each rigid body's ``v0`` and ``omega0``). With a prescribed ``motion`` the fixed
    vertices of the rest shape start where it puts them at ``t = 0``.

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
    if x is None and model.moving:
        rest = clamp(model, rest, rest, 0.0)
    x = rest if x is None else jnp.asarray(x, jnp.float64)
    v = _rigid_velocities(model) if v is None else jnp.asarray(v, jnp.float64)
    for name, a in (("x", x), ("v", v)):
        if a.shape != (n, 3):
            raise SceneError(f"initial {name} must have shape ({n}, 3), got {a.shape}")
        if not isinstance(a, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(a))):  # numpy: no trace
            raise SceneError(f"initial {name} has non-finite values")
    dminv, _ = rest_geometry(model, params.morph if params is not None else jnp.zeros((n, 3)))
    f = deformation_gradient(model, dminv, x)
    m = model.n_contact_rows
    return State(x=x, v=v, rot=rotation.cold_start(f), t=jnp.asarray(0.0), contact=jnp.zeros((m, 3)) if m else None)


def prepare(model: Model, params: Params, *, static: bool = False, dt: float | None = None) -> Prepared:
    """Rest-shape operators, masses, weights and the factorised PD matrix for ``params``.

    For dynamics the matrix is ``(1/h^2 + alpha/h) M + sum_e V_e (w_s + gamma w_v + beta w_s / h)
    G_e G_e^T + actuator terms``; for statics (``static=True``) the mass and damping parts
    are left out. ``gamma`` is the step's ``volume_weight``: 1 for plain PD
    (its convergence proof needs the true weights), less for L-BFGS, where the matrix is
    only the initial Hessian and a softer volume weight approximates the bending
    stiffness better. Differentiable in ``params``; call it once per rollout.

    ``dt`` (default ``Options.dt``) is the step size ``h`` of the steps to take
    (``Prepared.dt``, which the steps read): an integrator whose implicit stage has another
    size (BDF2's ``2h/3``) prepares for it instead of rebuilding the model.
    """
    h = model.options.dt if dt is None else float(dt)
    dminv, volume = rest_geometry(model, params.morph)
    mat = jnp.asarray(model.tet_material)
    w_s, w_v = pd_weights(params.E[mat], params.nu[mat])
    w_v_tets = w_v  # a VolumeElement carries the volume energy of its tets instead
    for term in model.terms:
        if isinstance(term, VolumeElement):
            w_v = w_v.at[jnp.asarray(term.tets)].set(0.0)
    w_b = params.beta[mat] * w_s
    tets = jnp.asarray(model.mesh.tets)
    quarter = (params.density[mat] * volume / 4.0)[:, None].repeat(4, axis=1)
    mass = jnp.zeros(model.n_vertices).at[tets].add(quarter)
    rigid = [part for part in model.bodies if part.rigid is not None]
    if rigid and static:
        raise SceneError(f"rigid bodies {[p.name for p in rigid]} are free: a static solve has no equilibrium for "
                         "them (their stiffness is zero); simulate the scene in time instead")
    for j, part in enumerate(rigid):
        start, stop = part.vertices
        mass = mass.at[start:stop].add(params.rigid_mass[j] * jnp.asarray(part.mass_share))
    mass_alpha = jnp.zeros(model.n_vertices).at[tets].add(quarter * params.alpha[mat][:, None])
    x_rest = jnp.asarray(model.mesh.points) + params.morph

    if static:
        inertia, weight = Statics(), w_s + model.step.volume_weight * w_v
    else:
        inertia, weight = Dynamics(h), w_s + model.step.volume_weight * w_v + w_b / h
    local = local_matrices(dminv, volume * weight)  # (t, 4, 4)
    term_prep = tuple(term.prepare(model, p, dminv, volume, w_v_tets) if isinstance(term, VolumeElement)
                      else term.prepare(model, p, dminv, volume) for term, p in zip(model.terms, params.actuators))
    added = [(term.stencil(), term.mass(tp)) for term, tp in zip(model.terms, term_prep) if isinstance(term, VertexTerm)]
    added = [(jnp.asarray(s), m) for s, m in added if m is not None]
    if added:  # terms with mass of their own (a membrane's areal density)
        extra = sum(jnp.zeros(model.n_vertices).at[s].add(m) for s, m in added)
        mass = mass + extra
    for term, tp in zip(model.terms, term_prep):
        if isinstance(term, ElementTerm):
            local = local.at[tp.tets].add(tp.local_matrices)
    nnz = len(model.pattern.rows)
    data = jnp.zeros(nnz + 1).at[model.local_to_data].add(local.reshape(-1))
    for term, tp, index in zip(model.terms, term_prep, model.block_to_data):
        if index is not None:
            data = data.at[index].add(jnp.reshape(term.blocks(tp), -1))
    data = data[:nnz]
    # the inertia term's Hessian is diagonal: M / h^2 + alpha M / h, nothing in statics
    data = data.at[model.diag_to_data].add(inertia.hessian_diagonal(mass, mass_alpha))
    # With partly held vertices, one matrix per axis (linsolve.PerColumn): each drops the
    # couplings of the vertices held along its axis.
    factor = model.linear_solver.factorize(
        model.pattern, data if model.axis_keep is None else data * jnp.asarray(model.axis_keep))
    return Prepared(dminv=dminv, volume=volume, mass=mass[:, None], mass_alpha=mass_alpha[:, None],
                    w_s=w_s, w_v=w_v, w_b=w_b, x_rest=x_rest, terms=term_prep,
                    obstacles=tuple(params.obstacles), rows=tuple(params.rows), data=data,
                    factor=factor, step=model.step.prepare(model, data, factor), inertia=inertia)

"""Bodies touching bodies (softbody.contact.pairs.Touch): a soft block resting on and sliding over a
soft slab held at its base, their gradients against central differences, and the refusals."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.contact.active_set import ActiveSet
from softbody.contact.obstacles import Plane
from softbody.contact import Contact
from softbody.contact import impact_zone
from softbody.gradients import ImplicitForward
from softbody.material import Material
from softbody.meshing import self_intersections
from softbody.meshing.geometry import Box, OnPlane, mesh
from softbody.meshing.grid import grid_box
from softbody.meshing.mesh import boundary_faces
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.contact.pairs import Touch, every_pair
from softbody.rigid import RigidBody
from softbody.scene import SoftBody
from softbody.io import Result, color_options, vertex_values
from softbody.simulate import SimulationError, check_trajectory, contact_fields, contact_forces, rollout, step
from softbody._types import RESULTS

from test_rigid import box

DT, G, THICKNESS, MU = 0.01, 9.81, 1e-3, 0.3
SLAB = grid_box((0.1, 0.04, 0.01), (10, 4, 1), origin=(-0.03, -0.02, 0.0))
# the block's base starts one contact thickness above the slab's top
BLOCK = grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.01 + THICKNESS))
N_SLAB = SLAB.n_vertices


def _scene(mu_k=MU, options=Options(dt=DT, tol=1e-10, max_iter=3000), capacity=None, **bodies):
    material = Material(E=1e6, nu=0.3, density=1000.0)
    return build([bodies.get("slab", SoftBody(SLAB, material, fixed="zmin", name="slab")),
                  bodies.get("block", SoftBody(BLOCK, material, name="block"))],
                 rows=[Touch("block", "slab", mu_s=MU, mu_k=mu_k, thickness=THICKNESS, capacity=capacity)],
                 options=options)


def _launched(model, v0):
    state = initial_state(model)
    return eqx.tree_at(lambda s: s.v, state, state.v.at[N_SLAB:, 0].set(v0))


def _row_gaps(model, params, x):
    """The smallest gap of the pair rows at the end of each step (rows chosen as a step does)."""
    generator, p = model.rows[0], params.rows[0]
    return np.array([float(jnp.min(generator.frame(x[k], generator.select(x[k - 1], x[k], p), p).phi))
                     for k in range(1, len(x))])


@pytest.fixture(scope="module")
def scene():
    return _scene()


def test_bodies_that_touch_share_anderson_coefficients_and_others_keep_their_own():
    """The contact iteration's Anderson blocks come from the scene: one per body, merged
    where rows between bodies couple them (a third body that nothing touches keeps its own;
    two touching bodies alone are one block, ``None``)."""
    material = Material(E=1e6, nu=0.3, density=1000.0)
    lid = grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(0.04, -0.01, 0.012))
    model, _ = build([SoftBody(SLAB, material, fixed="zmin", name="slab"), SoftBody(BLOCK, material, name="block"),
                      SoftBody(lid, material, name="lid")],
                     rows=[Touch("block", "slab", thickness=THICKNESS)], obstacles=[Plane(point=(0, 0, -0.1))],
                     options=Options(dt=DT))
    n_block = BLOCK.n_vertices
    np.testing.assert_array_equal(model.contact_blocks, np.repeat([0, 0, 1], [N_SLAB, n_block, lid.n_vertices]))
    assert _scene()[0].contact_blocks is None


def test_a_step_mixes_the_bodies_its_rows_join_and_no_others():
    """The forward iteration's Anderson blocks in a step with pair rows: the groups of bodies
    that the step's rows join, through chains of rows (bodies 3-2-1 by two rows), and not
    not through rows that are not there (an infinite gap: a padding slot between 4, 5 and 0)
    or through a vertex of zero weight (body 4's in a row on body 0). Six bodies of two vertices, one extra row on vertex 9
    and the rows' own entries, three per row."""
    from softbody._interfaces import PairFrame
    from softbody.contact.solver import _touching_groups

    bodies = np.repeat(np.arange(6), 2)
    rows = np.array([[6, 4, 5, 5], [4, 2, 3, 3], [8, 10, 11, 0], [0, 1, 1, 8]])  # vertex 8 is body 4's
    weights = np.array([[1.0, -0.5, -0.5, 0.0], [1.0, -0.2, -0.8, 0.0], [1.0, -0.5, -0.5, 0.0], [1.0, -1.0, 0.0, 0.0]])
    frame = PairFrame(vertices=jnp.asarray(rows), weights=jnp.asarray(weights),
                      phi=jnp.array([1e-4, -1e-4, jnp.inf, 0.0]), normal=jnp.zeros((4, 3)), mu_s=None, mu_k=None,
                      restitution=None)
    labels, count = jax.jit(lambda f: _touching_groups(f, bodies, np.array([9])))(frame)
    assert count == 6
    vertex = np.repeat([0, 1, 1, 1, 4, 5], 2)
    np.testing.assert_array_equal(labels, np.repeat(np.concatenate([vertex, vertex[[9]], vertex[rows[:, 0]]]), 3))


def test_block_rests_on_slab(scene):
    model, params = scene
    traj = rollout(model, params, initial_state(model), n_steps=30)  # throws unless every step converged
    assert not np.any(np.asarray(traj.info.tunnelled))  # the continuous collision check saw no crossing
    x = np.asarray(traj.x)
    gaps = _row_gaps(model, params, traj.x)
    edge = 0.01
    assert gaps.min() > -0.01 * edge  # penetration below 1% of the block's edge
    assert abs(gaps[-1]) < 1e-8  # resting on its rows: the gap closed at the thickness
    force, state = (np.asarray(a) for a in contact_forces(model, params, traj))
    # at rest the slab holds the block's weight: the rows' forces on the block sum to m g
    mass = np.asarray(prepare(model, params).mass)[N_SLAB:].sum()
    np.testing.assert_allclose(force[-1, N_SLAB:, 2].sum(), mass * G, rtol=1e-6)
    assert (state[-1, N_SLAB:] == 1).sum() >= 4  # the base's rows stick
    # the rows act on both sides: the slab's vertices carry the opposite force
    np.testing.assert_allclose(force[-1, :N_SLAB].sum(axis=0), -force[-1, N_SLAB:].sum(axis=0), rtol=0,
                               atol=1e-6 * mass * G)
    assert (state[-1, :N_SLAB] == 1).sum() >= 4
    # a result file carries them as fields the viewer and renders colour by (frame 0: no step yet)
    result = Result.from_mesh(model.mesh, traj.x, DT, fields=contact_fields(model, params, traj))
    assert {"contact_force", "contact_state"} <= set(color_options(result))
    np.testing.assert_array_equal(vertex_values(result, "contact_force")[1:], np.linalg.norm(force, axis=-1))
    np.testing.assert_array_equal(vertex_values(result, "contact_state")[1:], state)
    assert not result.fields["contact_force"][0].any() and not result.fields["contact_state"][0].any()
    centre = x[:, N_SLAB:].mean(axis=1)
    assert np.abs(centre[20:] - centre[20]).max() < 1e-4  # drift below 0.1 mm over the last 0.1 s
    # the slab carries the block's weight: its base deflects by less than the thickness
    assert x[:, N_SLAB:, 2].min() > 0.01


def test_a_step_starts_from_the_forces_the_last_one_left():
    """The state carries the pair rows' forces (``State.contact``) and with
    ``Contact(warm_start=True)`` the next step's contact iteration starts from them: from the
    block at rest, a step started from the carried
    forces converges in a few iterations where one started from zero forces needs tens
    (measured: 1 against 90), and both reach the same positions (each to the relative
    tolerance 1e-10; measured 9e-14 m apart, 1e-9 m checked). The carried forces hold the
    block's weight."""
    model, params = _scene(options=Options(dt=DT, tol=1e-10, max_iter=3000, contact=Contact(warm_start=True)))
    prep = prepare(model, params)
    one = jax.jit(lambda s: step(model, prep, s))
    state = initial_state(model)
    assert state.contact.shape == (model.n_pair_rows, 3) and not state.contact.any()
    for _ in range(20):  # settle: the block lands on its rows and comes to rest
        state, _ = one(state)
    warm, info_warm = one(state)
    cold, info_cold = one(dataclasses.replace(state, contact=jnp.zeros_like(state.contact)))
    assert bool(info_warm.converged) and bool(info_cold.converged)
    assert int(info_warm.iterations) <= 10 and int(info_cold.iterations) >= 4 * int(info_warm.iterations)
    np.testing.assert_allclose(np.asarray(warm.x), np.asarray(cold.x), rtol=0, atol=1e-9)
    # each row's force acts on its touching vertex and, opposite, on the other side's
    # triangle: the block's own rows push it up, the slab's push it down by the reaction
    generator, p = model.rows[0], params.rows[0]
    touching = np.asarray(generator.frame(warm.x, generator.select(state.x, warm.x, p), p).vertices[:, 0])
    on_block = np.where(touching >= N_SLAB, 1.0, -1.0)
    mass = np.asarray(prep.mass)[N_SLAB:].sum()
    np.testing.assert_allclose(float(np.sum(on_block * np.asarray(warm.contact[:, 2]))), mass * G, rtol=1e-3)


def test_sliding_block_decelerates_at_mu_k_g(scene):
    model, params = scene
    v0 = 0.3  # stops after ~10 steps: the sliding steps lose mu_k g h each
    traj = rollout(model, params, _launched(model, v0), n_steps=7)
    vx = np.diff(np.asarray(traj.x)[:, N_SLAB:, 0].mean(axis=1)) / DT
    decrements = -np.diff(np.concatenate([[v0], vx]))
    # implicit Euler with Coulomb friction: each sliding step takes mu_k g h off the speed
    # (the first also settles the block on the slab's compliance)
    np.testing.assert_allclose(decrements[1:], MU * G * DT, rtol=0.01)
    assert abs(_row_gaps(model, params, traj.x)).max() < 1e-8
    force, state = (np.asarray(a) for a in contact_forces(model, params, traj))
    block = slice(N_SLAB, None)
    # the block's base slides on every step; the slab's vertices under it carry the reactions
    assert (state[:, block].max(axis=1) == 2).all() and not (state[:, block] == 1).any()
    np.testing.assert_allclose(force[:, block].sum(axis=1), -force[:, :N_SLAB].sum(axis=1), rtol=1e-6, atol=1e-9)
    # kinetic friction: the tangential force on the block is mu_k times the normal force
    # (each row's is exactly; their normals follow the slab's surface, tilted ~1e-5 rad)
    total = force[1:, block].sum(axis=1)
    np.testing.assert_allclose(-total[:, 0], MU * total[:, 2], rtol=1e-4)


@pytest.mark.slow
def test_sliding_and_sticking_gradients_match_central_differences():
    """d(block's final x)/d(mu_k, v0, E) in sliding and in sticking, reverse mode, against
    central differences; forward mode against reverse."""
    model, params = _scene(mu_k=0.25)

    def final_x(mu_k, v0, E):
        p = eqx.tree_at(lambda p: (p.rows[0]["mu_k"], p.E), params, (mu_k, params.E.at[1].set(E)))
        traj = rollout(model, p, _launched(model, v0), n_steps=3)
        return jnp.mean(traj.x[-1, N_SLAB:, 0])

    at = (jnp.asarray(0.25), jnp.asarray(0.3), jnp.asarray(1e6))
    grads = jax.grad(final_x, argnums=(0, 1, 2))(*at)
    # forward mode (ImplicitForward) gives the same derivative in mu_k
    forward_model, _ = _scene(mu_k=0.25, options=Options(dt=DT, tol=1e-10, max_iter=3000,
                                                         adjoint=ImplicitForward()))

    def forward_x(mu_k):
        p = eqx.tree_at(lambda p: p.rows[0]["mu_k"], params, mu_k)
        return jnp.mean(rollout(forward_model, p, _launched(forward_model, 0.3), n_steps=3).x[-1, N_SLAB:, 0])

    tangent = jax.jvp(forward_x, (at[0],), (jnp.asarray(1.0),))[1]
    assert abs(float(tangent) - float(grads[0])) <= 1e-6 * abs(float(grads[0]))
    # sliding (v0 = 0.3 m/s: it slides through the 3 steps), then sticking (v0 = 1 cm/s: the
    # static cone stops it in the first step; mu_k does not act, its derivative is zero)
    for at in (at, (at[0], jnp.asarray(0.01), at[2])):
        grads = jax.grad(final_x, argnums=(0, 1, 2))(*at)
        for i, (g, eps) in enumerate(zip(grads, (1e-4, 1e-4, 1e2))):
            plus = [a + eps * (j == i) for j, a in enumerate(at)]
            minus = [a - eps * (j == i) for j, a in enumerate(at)]
            fd = (final_x(*plus) - final_x(*minus)) / (2 * eps)
            assert abs(float(g) - float(fd)) <= 1e-4 * abs(float(fd)) + 1e-12, (float(at[1]), i, float(g), float(fd))


def test_an_aligned_stack_keeps_its_rows_at_the_edges():
    """Boxes stacked edge on edge: the perimeter of each box, bulging past the edges of the
    one below by its Poisson expansion, stays on it (it used to lose its rows and sink)."""
    box = grid_box((0.02, 0.02, 0.02), (2, 2, 2), origin=(-0.01, -0.01, 0.01 + THICKNESS))
    on_top = grid_box((0.02, 0.02, 0.02), (2, 2, 2), origin=(-0.01, -0.01, 0.03 + 2 * THICKNESS))
    material = Material(E=1e6, nu=0.3, density=1000.0)
    model, params = build([SoftBody(SLAB, material, fixed="zmin", name="slab"), SoftBody(box, material, name="box"),
                           SoftBody(on_top, material, name="top")],
                          rows=[Touch("box", "slab", thickness=THICKNESS), Touch("top", "box", thickness=THICKNESS)],
                          options=Options(dt=DT, tol=1e-8, max_iter=3000))
    traj = rollout(model, params, initial_state(model), n_steps=8)
    generator, p = model.rows[1], params.rows[1]
    for k in range(1, 9):
        frame = generator.frame(traj.x[k], generator.select(traj.x[k - 1], traj.x[k], p), p)
        assert float(jnp.min(frame.phi)) > -1e-8 and int(jnp.sum(frame.phi < 1e-6)) >= 9


def test_one_touch_among_three_bodies_holds_the_stack_as_the_pairs_do():
    """``Touch("top", "box", "slab")``, one search over the three surfaces, one row per
    surface vertex with the nearest other body, steps the aligned stack as the two pairwise
    generators do: every step converged, positions equal to 1e-9 m (1e-6 of the thickness;
    the two differ in redundant rows out of reach and in summation order), with fewer rows
    (each middle vertex has one, not one per pair)."""
    box = grid_box((0.02, 0.02, 0.02), (2, 2, 2), origin=(-0.01, -0.01, 0.01 + THICKNESS))
    on_top = grid_box((0.02, 0.02, 0.02), (2, 2, 2), origin=(-0.01, -0.01, 0.03 + 2 * THICKNESS))
    material = Material(E=1e6, nu=0.3, density=1000.0)
    bodies = [SoftBody(SLAB, material, fixed="zmin", name="slab"), SoftBody(box, material, name="box"),
              SoftBody(on_top, material, name="top")]
    x = {}
    for name, rows in [("pairs", [Touch("box", "slab", thickness=THICKNESS), Touch("top", "box", thickness=THICKNESS)]),
                       ("one", [Touch("top", "box", "slab", thickness=THICKNESS)])]:
        model, params = build(bodies, rows=rows, options=Options(dt=DT, tol=1e-8, max_iter=3000))
        x[name] = np.asarray(rollout(model, params, initial_state(model), n_steps=8).x)  # throws unless converged
        if name == "one":
            surfaces = sum(len(np.unique(model.mesh.regions[b].faces)) for b in ("slab", "box", "top"))
            # one vertex row per surface vertex, one edge row per surface edge of the finer bodies
            assert model.rows[0].size == surfaces + len(model.rows[0]._bound().edge_rows)
    np.testing.assert_allclose(x["one"], x["pairs"], rtol=0, atol=1e-9)
    assert x["one"][-1, N_SLAB:, 2].min() > 0.01  # above the slab's top


def test_touch_among_bodies_refuses_before_compiling():
    material = Material(E=1e5)
    slab, block = SoftBody(SLAB, material, name="slab"), SoftBody(BLOCK, material, name="block")
    with pytest.raises(SceneError, match="two or more body names"):
        Touch("block")
    with pytest.raises(SceneError, match="names one body twice"):
        Touch("block", "slab", "block")
    with pytest.raises(SceneError, match="self_contact is True, False or a tuple of the named bodies"):
        Touch("block", "slab", self_contact=("lid",))
    with pytest.raises(SceneError, match="'lid', which is not in the scene"):
        build([slab, block], rows=[Touch("block", "slab", "lid")])
    assert Touch("block", "slab", "lid").bodies == ("block", "slab", "lid")


def test_a_search_that_overflows_its_capacity_is_never_silent():
    model, params = _scene(capacity=1)
    traj = rollout(model, params, _launched(model, 0.3), n_steps=1, throw=False)
    assert int(traj.info.result[0]) == RESULTS.overflow and bool(traj.info.overflow[0])
    with pytest.raises(SimulationError, match=r"step 0: the contact search .*\.Touch\(\.\.\., capacity=\.\.\.\)"):
        rollout(model, params, _launched(model, 0.3), n_steps=1)


def test_a_block_thrown_through_the_slab_in_one_step_stops_on_it():
    """Thrown down at 3 m/s, the block would move 3 cm in one step, through the 1 cm slab:
    at the step's predicted end its vertices lie nearest the slab's bottom face. Rows meet
    the first triangle a vertex's path crosses, from the side it came from, so the block
    stops on the slab's top instead; the step's continuous collision check finds no
    crossing, and the block comes to rest on its rows. (The fast block's swept boxes need
    a larger broad-phase capacity than the default.)"""
    model, params = _scene(options=Options(dt=DT, tol=1e-8, max_iter=5000), capacity=4096)
    state = _launched(model, 0.0)
    state = eqx.tree_at(lambda s: s.v, state, state.v.at[N_SLAB:, 2].set(-3.0))
    traj = rollout(model, params, state, n_steps=6)  # throws unless every step converged, without crossings
    assert not np.any(np.asarray(traj.info.tunnelled))
    gaps = _row_gaps(model, params, traj.x)
    assert gaps.min() > -0.1 * THICKNESS and abs(gaps[-1]) < 1e-6  # stopped on the slab, resting at the thickness


def test_a_crossing_the_rows_missed_is_never_silent(scene):
    """The continuous collision check counts the surface pairs that meet during a step (the
    block moved straight through the slab: its vertices cross the slab's triangles, its edges
    the slab's edges), a step with crossings ends with ``RESULTS.tunnelled`` whatever else it
    reports, and the rollout's check says so, naming the fix."""
    model, params = scene
    generator, p = model.rows[0], params.rows[0]
    x0 = jnp.asarray(model.mesh.points)
    through = x0.at[N_SLAB:, 2].add(-0.03)
    count, _ = generator.crossed(x0, through, p)  # (its buffers overflow here: they hold 4 pairs per vertex)
    assert int(count) > 0
    assert int(generator.crossed(x0, x0.at[N_SLAB:, 0].add(0.01), p)[0]) == 0  # sliding along: none
    assert int(RESULTS.of(finite=True, converged=True, inverted=0, inverted0=0, overflow=True, tunnelled=count)) \
        == RESULTS.tunnelled
    traj = rollout(model, params, initial_state(model), n_steps=1, throw=False)
    assert int(traj.info.result[0]) == RESULTS.success and int(traj.info.tunnelled[0]) == 0
    traj = eqx.tree_at(lambda t: t.info.result, traj, jnp.full(1, int(RESULTS.tunnelled), jnp.int32))
    with pytest.raises(SimulationError, match=r"step 0: surfaces kept apart .* passed through each other.*Reduce "
                                              r"Options\.dt \(now 0\.01 s\)"):
        check_trajectory(model, traj)


def test_a_pile_falling_together_is_no_overflow_and_a_crossing_in_it_is_found():
    """Eight 2 cm cubes in a 2 x 2 x 2 pile, 1 mm apart, move 5 mm down together: their swept
    boxes overlap (192 vertex-triangle and 436 edge-edge pairs) though nothing crosses. The
    tunnelling check's default buffers (4 per vertex, 4 per edge) overflowed, and a settling
    pile's steps ended with RESULTS.overflow; its second, larger search holds them. A top
    cube moved through the one below is still counted."""
    cubes = [SoftBody(grid_box((0.02,) * 3, (1, 1, 1), origin=(0.021 * i, 0.021 * j, 0.021 * k)), Material(),
                      name=f"cube{i}{j}{k}") for i in range(2) for j in range(2) for k in range(2)]
    model, params = build(cubes, rows=[Touch(*[c.name for c in cubes], thickness=1e-3)])
    generator, p = model.rows[0], params.rows[0]
    x0 = jnp.asarray(model.mesh.points)
    count, overflow = generator.crossed(x0, x0.at[:, 2].add(-0.005), p)
    assert int(count) == 0 and not bool(overflow)
    top = np.flatnonzero(np.isin(np.arange(model.n_vertices), model.mesh.regions["cube001"].vertices))
    count, _ = generator.crossed(x0, x0.at[top, 2].add(-0.03), p)  # through cube000 below it
    assert int(count) > 0


@pytest.mark.slow
def test_frictionless_step_and_its_gradient_match_the_collision_qp():
    """With no elasticity to speak of (E = 1e-6 Pa), no gravity and a held slab, a step is the
    collision response QP ``min 1/2 |z - x_hat|_W^2 s.t. G z + h <= 0`` with ``x_hat = x_n +
    h v_n``, ``W = M / h^2`` and the rows' planes as constraints (softbody.contact.impact_zone): its
    solution and its KKT/QR derivative are the oracle of the step and of the implicit
    derivative through the pair rows."""
    material = Material(E=1e-6, nu=0.3, density=1000.0)
    block = grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.01, -0.01, 0.01 + THICKNESS + 2e-4))
    model, params = build([SoftBody(SLAB, material, fixed=lambda p: np.ones(len(p), bool), name="slab"),
                           SoftBody(block, material, name="block")],
                          rows=[Touch("block", "slab", mu_s=0.0, mu_k=0.0, thickness=THICKNESS)],
                          options=Options(dt=DT, gravity=(0.0, 0.0, 0.0), tol=1e-12, atol=1e-14, max_iter=5000))
    state = initial_state(model)
    v = np.zeros((model.n_vertices, 3))
    # the base's columns arrive 0.1, 0.5 and 0.9 mm down in the step: the first stays clear of
    # the 0.2 mm gap, the others land
    v[N_SLAB:, 2] = -0.01 - 4.0 * (np.asarray(state.x)[N_SLAB:, 0] + 0.01)
    c = np.random.default_rng(0).normal(size=(block.n_vertices, 3))

    def loss(velocity):
        traj = rollout(model, params, eqx.tree_at(lambda s: s.v, state, velocity), n_steps=1)
        return jnp.sum(traj.x[-1, N_SLAB:] * c), traj.x

    (_, x), grad_v = jax.value_and_grad(loss, has_aux=True)(jnp.asarray(v))
    generator, p = model.rows[0], params.rows[0]
    frame = generator.frame(x[1], generator.select(x[0], x[1], p), p)
    rows = [r for r in range(generator.size) if frame.phi[r] < 1e20 and frame.vertices[r, 0] >= N_SLAB]
    G, h = np.zeros((len(rows), 3 * block.n_vertices)), np.zeros(len(rows))
    for i, r in enumerate(rows):  # the plane of the slab's triangle: -(n . z_p - n . a - thickness) <= 0
        q = int(frame.vertices[r, 0]) - N_SLAB
        G[i, 3 * q:3 * q + 3] = -frame.normal[r]
        h[i] = float(frame.normal[r] @ x[1, frame.vertices[r, 1]]) + THICKNESS
    w = np.repeat(np.asarray(prepare(model, params).mass)[N_SLAB:, 0] / DT**2, 3)
    x_hat = (np.asarray(state.x)[N_SLAB:] + DT * v[N_SLAB:]).ravel()
    z, lam = impact_zone.solve(x_hat, w, G, h)
    assert len(rows) == 9 and int(np.sum(lam > 0)) == 6
    np.testing.assert_allclose(np.asarray(x[1, N_SLAB:]).ravel(), z, rtol=0, atol=1e-9)
    reference = impact_zone.backward_qr(x_hat, w, G, h, z, lam, c.ravel()).dx
    np.testing.assert_allclose(np.asarray(grad_v[N_SLAB:]).ravel() / DT, reference, rtol=0,
                               atol=1e-6 * np.abs(reference).max())


def test_rigid_box_rests_on_soft_slab():
    """A 2 cm rigid box (4 g) set one contact thickness above the soft slab: the slab's
    vertices under it hold it (pair rows on a rigid body's triangles, its motion in the
    reduced coordinates' sweep). Every step converges; it rests on the rows with the
    slab carrying its weight, no penetration beyond 1% of its edge, no drift. With
    ``Contact(warm_start=True)``, at rest each step starts from the forces the last one left
    on the rows and on the box's skin (``State.contact``) and converges within a few
    iterations (measured 1-3 from step 7; 134-400 each from zero forces)."""
    rigid = RigidBody(box((0.02, 0.02, 0.02), centre=(0.0, 0.0, 0.02 + THICKNESS)), density=500.0, name="box")
    model, params = build([SoftBody(SLAB, Material(E=1e6, nu=0.3, density=1000.0), fixed="zmin", name="slab"), rigid],
                          rows=[Touch("box", "slab", mu_s=MU, thickness=THICKNESS)],
                          options=Options(dt=DT, tol=1e-8, max_iter=3000, contact=Contact(warm_start=True)))
    traj = rollout(model, params, initial_state(model), n_steps=30)  # throws unless every step converged
    gaps = _row_gaps(model, params, traj.x)
    assert gaps.min() > -0.01 * 0.02 and abs(gaps[-1]) < 1e-8
    force, _ = (np.asarray(a) for a in contact_forces(model, params, traj))
    mass = np.asarray(prepare(model, params).mass)[N_SLAB:].sum()
    assert mass == pytest.approx(0.02**3 * 500.0, rel=1e-12)
    np.testing.assert_allclose(force[-1, N_SLAB:, 2].sum(), mass * G, rtol=1e-6)
    centre = np.asarray(traj.x)[:, N_SLAB:].mean(axis=1)
    assert np.abs(centre[15:] - centre[15]).max() < 1e-4
    assert np.asarray(traj.info.iterations)[15:].max() <= 10


@pytest.mark.slow
def test_a_soft_block_settles_on_a_light_rigid_box_in_few_iterations_and_the_floor_keeps_the_solution():
    """A soft block (4 g) set one contact thickness above a light rigid box (0.8 g) that rests
    on the ground, the block's corner off the box's. The rigid box's vertices have no
    stiffness; swept with their inertia alone, the pair rows see the box ~1000x more
    compliant than the block's vertices, and the contact iteration trades forces between
    them: the first step (the block settling onto the box) took 4365 iterations at tol
    1e-10. ``Contact.rigid_floor`` (default 0.01) sweeps them no lighter than 1% of the
    stiff vertices' median: 130. It changes the iterations only: the step ends at the same
    positions with and without it."""
    def scene(floor):
        rigid = RigidBody(box((0.02, 0.02, 0.02), centre=(0.0, 0.0, 0.01)), density=100.0, name="box")
        block = SoftBody(grid_box((0.02, 0.02, 0.01), (2, 2, 1), origin=(-0.006, -0.004, 0.02 + THICKNESS)),
                         Material(E=1e6, nu=0.3, density=1000.0), name="block")
        return build([block, rigid], obstacles=[Plane(mu_s=0.5, mu_k=0.5)],
                     rows=[Touch("block", "box", mu_s=MU, thickness=THICKNESS)],
                     options=Options(dt=DT, tol=1e-10, max_iter=20000, contact=Contact(rigid_floor=floor)))

    ends = {}
    for floor in (0.01, 0.0):
        model, params = scene(floor)
        state, info = step(model, prepare(model, params), initial_state(model))
        assert bool(info.converged)
        ends[floor] = (np.asarray(state.x), int(info.iterations))
    np.testing.assert_allclose(ends[0.01][0], ends[0.0][0], rtol=0, atol=1e-9)
    assert ends[0.01][1] <= 300 and ends[0.0][1] > 4 * ends[0.01][1]
    gaps = _row_gaps(model, params, np.stack([np.asarray(initial_state(model).x), ends[0.01][0]]))
    assert gaps.min() > -1e-9


def test_stack_of_three_rigid_boxes_stays_for_two_seconds():
    """Three 10 cm rigid boxes stacked on the ground, each resting on the one below through
    pair rows: for 2 s every step converges and no box moves by 1 mm."""
    boxes = [RigidBody(box((0.1, 0.1, 0.1), centre=(0.0, 0.0, 0.05 + i * (0.1 + THICKNESS))), density=500.0, name=f"b{i}")
             for i in range(3)]
    model, params = build(boxes, obstacles=[Plane(mu_s=0.5, mu_k=0.4)],
                          rows=[Touch("b1", "b0", mu_s=0.5, thickness=THICKNESS),
                                Touch("b2", "b1", mu_s=0.5, thickness=THICKNESS)],
                          options=Options(dt=DT, tol=1e-8, max_iter=3000))
    traj = rollout(model, params, initial_state(model), n_steps=200)
    x = np.asarray(traj.x)
    for i in range(3):
        start, end = model.body(f"b{i}").vertices
        assert np.abs(x[:, start:end] - x[0, start:end]).max() < 1e-3


def test_a_rigid_box_dropped_on_another_with_more_static_than_kinetic_friction_comes_to_rest():
    """A 2 cm rigid cube dropped 1 cm onto another resting on the ground, offset by (0.3,
    0.2) of an edge, static friction above kinetic (0.5, 0.4) on both: every step converges
    (the impact step stopped at the 3000-iteration cap while a row could test the static cone
    and slide on the kinetic one within a step) and the upper cube comes to rest on the
    lower one: its rows closed (no penetration past 1% of the edge), still, where it landed."""
    edge = 0.02
    lower = RigidBody(box((edge,) * 3, centre=(0.0, 0.0, edge / 2)), density=500.0, name="lower")
    upper = RigidBody(box((edge,) * 3, centre=(0.3 * edge, 0.2 * edge, 1.5 * edge + 0.01)), density=500.0,
                      name="upper")
    model, params = build([lower, upper], obstacles=[Plane(mu_s=0.5, mu_k=0.4)],
                          rows=[Touch("upper", "lower", mu_s=0.5, mu_k=0.4, thickness=THICKNESS, edges=True)],
                          options=Options(dt=DT, tol=1e-6, max_iter=3000))
    traj = rollout(model, params, initial_state(model), n_steps=20)  # throws unless every step converged
    gaps = _row_gaps(model, params, traj.x)
    assert gaps.min() > -0.01 * edge and abs(gaps[-1]) < 1e-8
    start, end = model.body("upper").vertices
    centre = np.asarray(traj.x)[:, start:end].mean(axis=1)
    np.testing.assert_allclose(centre[-1, :2], centre[0, :2], atol=1e-3)
    assert np.abs(np.asarray(traj.v)[-1]).max() < 1e-3


def test_crossed_edges_hold_a_box_on_a_ridge():
    """A rigid 2 cm box turned 45 degrees about y, dropped onto a held cube turned 45 degrees
    about x: only their edges meet, crossed at right angles, no vertex over a face. The
    edge-edge rows hold it, every step converged, its lowest point at half the thickness
    above the ridge; without them the edges pass through each other, and the step says so
    (``RESULTS.tunnelled``)."""
    c = np.cos(np.pi / 4)
    about_x = np.array([[1, 0, 0], [0, c, -c], [0, c, c]])
    about_y = np.array([[c, 0, c], [0, 1, 0], [-c, 0, c]])
    cube = grid_box((0.02,) * 3, (1,) * 3, origin=(-0.01, -0.01, -0.01))
    ridge = SoftBody(dataclasses.replace(cube, points=cube.points @ about_x.T), Material(E=1e6),
                     fixed=lambda p: np.ones(len(p), bool), name="ridge")
    top = 0.01 * np.sqrt(2)
    upper = RigidBody(box((0.02, 0.02, 0.02), about_y, centre=(0.0, 0.0, 2 * top + THICKNESS + 1e-3)),
                      density=500.0, name="upper")
    for edges, n_steps in ((True, 20), (False, 8)):
        model, params = build([ridge, upper], rows=[Touch("upper", "ridge", mu_s=0.5, thickness=THICKNESS,
                                                          edges=edges)],
                              options=Options(dt=DT, tol=1e-8, max_iter=3000))
        traj = rollout(model, params, initial_state(model), n_steps=n_steps, throw=False)
        start, end = model.body("upper").vertices
        lowest = np.asarray(traj.x)[:, start:end, 2].min(axis=1) - top
        result = np.asarray(traj.info.result)
        if edges:
            assert np.all(result == int(RESULTS.success)) and np.all(np.asarray(traj.info.converged))
            np.testing.assert_allclose(lowest[5:], 0.5 * THICKNESS, rtol=1e-3)
        else:
            assert int(RESULTS.tunnelled) in result.tolist() and lowest.min() < 0


@pytest.mark.slow
def test_gradients_through_edge_rows_match_central_differences():
    """A soft 2 cm cube turned 45 degrees about y, its lowest edge on a held ridge (a cube
    turned 45 degrees about x), slides across it at 0.2 m/s: only their edges meet, crossed
    (edge-edge rows, kinetic friction). d(its final mean x)/d(mu_k, v0) against central
    differences at step 1e-5 within 1e-4: the rows' weights follow the closest points of the
    solution, and so does the derivative. (Over steps 3e-6 to 3e-5 the differences move by
    1e-4 relative in mu_k and 1e-5 in v0; measured 2e-5 and 2e-6 off. With the weights held
    at the step's predicted end the derivatives were 0.36 % and 0.15 % off.)"""
    c = np.cos(np.pi / 4)
    about_x = np.array([[1, 0, 0], [0, c, -c], [0, c, c]])
    about_y = np.array([[c, 0, c], [0, 1, 0], [-c, 0, c]])
    cube = grid_box((0.02,) * 3, (1,) * 3, origin=(-0.01, -0.01, -0.01))
    top = 0.01 * np.sqrt(2)
    ridge = SoftBody(dataclasses.replace(cube, points=cube.points @ about_x.T), Material(E=1e6),
                     fixed=lambda p: np.ones(len(p), bool), name="ridge")
    upper = SoftBody(dataclasses.replace(cube, points=cube.points @ about_y.T + [0.0, 0.0, 2 * top + THICKNESS]),
                     Material(E=1e6, nu=0.3, density=500.0), name="upper")
    model, params = build([ridge, upper], rows=[Touch("upper", "ridge", mu_s=0.4, mu_k=0.3, thickness=THICKNESS,
                                                      edges=True)],
                          options=Options(dt=DT, tol=1e-11, max_iter=5000))
    start = cube.n_vertices

    def final_x(mu_k, v0):
        p = eqx.tree_at(lambda p: p.rows[0]["mu_k"], params, mu_k)
        state = initial_state(model)
        state = eqx.tree_at(lambda s: s.v, state, state.v.at[start:, 0].set(v0))
        return jnp.mean(rollout(model, p, state, n_steps=4).x[-1, start:, 0])

    at = (jnp.asarray(0.3), jnp.asarray(0.2))
    grads = jax.jit(jax.grad(final_x, argnums=(0, 1)))(*at)
    value = jax.jit(final_x)
    for i, g in enumerate(grads):
        eps = 1e-5
        plus = [a + eps * (j == i) for j, a in enumerate(at)]
        minus = [a - eps * (j == i) for j, a in enumerate(at)]
        fd = (value(*plus) - value(*minus)) / (2 * eps)
        assert abs(float(g) - float(fd)) <= 1e-4 * abs(float(fd)), (i, float(g), float(fd))


def test_self_contact_holds_a_fork_closing_on_itself():
    """A soft fork (two 1 cm arms 5 mm apart, joined and held at x = 0, the lower one on the
    ground) whose upper arm sags under gravity onto the lower one: with self-contact its
    surface never intersects itself (the meshing module's test) and every step converges;
    without it the arm passes into the other."""
    body = Box((0.06, 0.02, 0.025), center=(0.03, 0.0, 0.0135)) - Box((0.06, 0.03, 0.005),
                                                                          center=(0.04, 0.0, 0.0135))
    fork = mesh(body, size=0.006, select={"fixed": OnPlane("x", 0.0)})
    faces = boundary_faces(fork.tets)
    for contact in (True, False):
        rows = [Touch("fork", self_contact=True, mu_s=0.3, thickness=THICKNESS)] if contact else []
        model, params = build([SoftBody(fork, Material(E=5e4, nu=0.3, density=1000.0), fixed="fixed", name="fork")],
                              obstacles=[Plane(mu_s=0.3)], rows=rows, options=Options(dt=DT, tol=1e-6, max_iter=3000))
        traj = rollout(model, params, initial_state(model), n_steps=12, throw=contact)
        crossings = [len(self_intersections(x, faces)) for x in np.asarray(traj.x)]
        if contact:
            assert max(crossings) == 0 and np.all(np.asarray(traj.info.converged))
        else:
            assert max(crossings) > 0


def test_refusals_before_compiling():
    material = Material(E=1e5)
    slab, block = SoftBody(SLAB, material, name="slab"), SoftBody(BLOCK, material, name="block")
    with pytest.raises(SceneError, match="'lid', which is not in the scene"):
        build([slab, block], rows=[Touch("block", "lid")])
    with pytest.raises(SceneError, match="thickness must be a distance > 0"):
        Touch("block", "slab", thickness=0.0)
    with pytest.raises(SceneError, match="self-contact"):
        Touch("block", "block")
    pairs = every_pair("slab", "block", "lid", mu_s=0.4, thickness=2e-3)
    assert [(t.first, t.second, t.mu_s, t.thickness) for t in pairs] == [
        ("slab", "block", 0.4, 2e-3), ("slab", "lid", 0.4, 2e-3), ("block", "lid", 0.4, 2e-3)]
    with pytest.raises(SceneError, match="two or more distinct body names"):
        every_pair("slab", "slab")
    with pytest.raises(SceneError, match="capacity must be a whole number"):
        Touch("block", "slab", capacity=0)
    with pytest.raises(SceneError, match="mu_k <= mu_s"):
        Touch("block", "slab", mu_s=0.2, mu_k=0.3)
    with pytest.raises(SceneError, match="pair contact"):
        build([slab, block], rows=[Touch("block", "slab")], options=Options(contact=Contact(active_set=ActiveSet())))

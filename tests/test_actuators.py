"""Actuators: cavity pressure, volume-controlled cavities, pneumatic cells, muscles.

Physics checks on small meshes in float64: a pressurised finger against a linear-elastic
scikit-fem solve on the same tets and load, its bending and ballooning past 100 % wall
strain up to its pressure maximum (where the static solve fails with a clear error),
muscle contraction, the exact uniform expansion of pneumatic cells, and gradients against
central finite differences.
"""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.actuators import CavityPressure, CavityVolume, Muscle, PneumaticCells
from softbody.elastic import deformation_gradient
from softbody.material import Material, pd_weights
from softbody.meshing import Region, examples
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state, prepare
from softbody.scene import SoftBody
from softbody.simulate import RESULTS, SimulationError, rollout, solve_static

E_WALL, NU = 1e5, 0.45  # a soft silicone (Pa, -)
# Statics with no gravity or external force have no load scale, so the step converges on
# the absolute force residual: 1e-10 N is ~1e-7 of the pressure forces at 1 Pa and
# ~1e-11 of them at 20 kPa.
STATIC = Options(gravity=(0.0, 0.0, 0.0), tol=1e-10, atol=1e-10, max_iter=5000)
SWEEP_KPA = [0, 1, 2, 4, 6, 8, 10, 11, 12, 12.5, 13, 13.5, 14, 14.5, 15, 16, 18, 20]


def _rotation_angle_y(rest: np.ndarray, x: np.ndarray) -> float:
    """Best-fit rotation (Kabsch) of the point set ``rest -> x``: its angle about +y in
    degrees, positive when +x turns towards -z."""
    a, b = rest - rest.mean(axis=0), x - x.mean(axis=0)
    u, _, vt = np.linalg.svd(b.T @ a)
    r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    return float(np.degrees(np.arctan2(-r[2, 0], r[0, 0])))


def _stretches(model, prep, x) -> tuple[np.ndarray, np.ndarray]:
    """Principal stretches ``(t, 3)`` and ``det F`` ``(t,)`` of positions ``x``."""
    f = np.asarray(deformation_gradient(model, prep.dminv, jnp.asarray(x))).transpose(2, 0, 1)
    return np.linalg.svd(f, compute_uv=False), np.linalg.det(f)


def _pressure_forces(mesh, region: str, p: float) -> np.ndarray:
    """Nodal forces ``(n, 3)`` of pressure ``p`` on the rest cavity wall: a third of each
    face's area-weighted normal (pointing out of the cavity) to each of its vertices."""
    faces = mesh.regions[region].faces
    q = mesh.points[faces]
    an = -0.5 * np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    f = np.zeros_like(mesh.points)
    np.add.at(f, faces, np.repeat(an[:, None, :] / 3.0, 3, axis=1))
    return p * f


def _linear_elastic(mesh, E, nu, forces, fixed) -> np.ndarray:
    """Small-strain linear-elastic displacements ``(n, 3)`` (scikit-fem, P1 tets)."""
    from skfem import Basis, ElementTetP1, ElementVector, MeshTet, asm, condense, solve
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    basis = Basis(MeshTet(mesh.points.T.copy(), mesh.tets.T.copy()), ElementVector(ElementTetP1()))
    stiffness = asm(linear_elasticity(*lame_parameters(E, nu)), basis)
    dofs = basis.nodal_dofs  # (3, n): the dof of each component at each vertex
    load = np.zeros(basis.N)
    load[dofs] = forces.T
    u = solve(*condense(stiffness, load, D=dofs[:, fixed].ravel()))
    return u[dofs].T


# --- the pneumatic finger -------------------------------------------------------------------


@pytest.fixture(scope="module")
def finger():
    mesh = examples.finger(size=0.004)  # ~1000 vertices, walls one or two tets thick
    term = CavityPressure.from_regions(mesh, ["cavity:chamber"])
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(term,)),
                          options=STATIC)
    return mesh, term, model, params


@pytest.fixture(scope="module")
def sweep(finger):
    """Static states along a pressure ramp (each solve starts from the previous state),
    up to and including the first that fails (a :class:`SimulationError`, or a solve that
    does not converge)."""
    mesh, term, model, params = finger
    prep = prepare(model, params, static=True)
    cavity = mesh.regions["cavity:chamber"].vertices
    wall = np.flatnonzero(np.isin(mesh.tets, cavity).any(axis=1))
    tip = mesh.regions["tip"].vertices
    x = jnp.asarray(mesh.points)
    rows = []
    for kpa in SWEEP_KPA:
        try:
            x, info = solve_static(model, params, activation=jnp.array([kpa * 1e3]), x0=x)
        except SimulationError as error:
            rows.append({"kpa": kpa, "error": str(error), "converged": False})
            break
        xs = np.asarray(x)
        stretch, det = _stretches(model, prep, xs)
        rows.append({
            "kpa": kpa, "error": None, "converged": bool(info.converged), "min_det": float(np.min(det)),
            "inverted": int(info.inverted), "wall_strain": float(stretch[wall].max() - 1.0),
            "angle": _rotation_angle_y(mesh.points[tip], xs[tip]),
            "tip": (xs[tip] - mesh.points[tip]).mean(axis=0),
            "volume": float(term.volumes(prep.terms[0], x)[0])})
        if not rows[-1]["converged"]:
            break
    return rows


def _good(sweep):
    return [r for r in sweep if r["converged"]]


def test_zero_pressure_leaves_rest_state(finger):
    mesh = finger[0]
    x, info = solve_static(finger[2], finger[3], activation=jnp.array([0.0]), x0=jnp.asarray(mesh.points))
    assert bool(info.converged)
    np.testing.assert_allclose(np.asarray(x), mesh.points, rtol=0, atol=1e-12)


def test_finger_bends_away_from_chamber(sweep):
    """The chamber lies above the neutral axis (z > 0): the tip goes down and turns down."""
    for r in _good(sweep)[1:]:
        assert r["tip"][2] < 0, r
        assert r["angle"] > 0, r
    # At 12 kPa the bending is large (tens of degrees), not a round-off effect.
    at12 = next(r for r in sweep if r["kpa"] == 12)
    assert at12["angle"] > 10 and -at12["tip"][2] > 0.01 * 0.09


def test_bending_angle_and_volume_grow_with_pressure(sweep):
    good = [r for r in _good(sweep) if r["kpa"] <= 14]
    assert [r["kpa"] for r in good] == [k for k in SWEEP_KPA if k <= 14]
    angles = np.array([r["angle"] for r in good])
    volumes = np.array([r["volume"] for r in good])
    assert np.all(np.diff(angles) > 0), angles
    assert np.all(np.diff(volumes) > 0), volumes
    np.testing.assert_allclose(volumes[0], 0.077 * 0.014 * 0.006, rtol=1e-12)  # the chamber box


def test_small_pressure_matches_linear_elasticity(finger):
    """At small pressure the tip displacement equals a linear-elastic FEM solve on the
    same tets with the same nodal forces, and the difference (geometric nonlinearity, of
    the order of the displacement gradients) vanishes linearly with the pressure."""
    mesh, _, model, params = finger
    tip, fixed = mesh.regions["tip"].vertices, mesh.regions["fixed"].vertices
    errors = []
    for p in (10.0, 1.0):  # Pa: p / E = 1e-4 and 1e-5
        x, info = solve_static(model, params, activation=jnp.array([p]), x0=jnp.asarray(mesh.points))
        assert bool(info.converged)
        u_pd = (np.asarray(x) - mesh.points)[tip].mean(axis=0)
        u_fe = _linear_elastic(mesh, E_WALL, NU, _pressure_forces(mesh, "cavity:chamber", p), fixed)[tip].mean(axis=0)
        errors.append(np.linalg.norm(u_pd - u_fe) / np.linalg.norm(u_fe))
    assert errors[0] < 0.03
    assert errors[1] < errors[0] / 5  # first order in p: the linearisation itself agrees


def test_pressure_load_is_area_weighted_normals(finger):
    """dE/dx of the term is exactly -p x (area-weighted normals / 3) on the deformed wall,
    and it is the gradient of the energy -p V(x) (jax.grad) for a deformed, closed wall."""
    mesh, term, model, params = finger
    prep = prepare(model, params, static=True).terms[0]
    p = 2500.0
    x_rest = jnp.asarray(mesh.points)
    _, grad = term.energy_and_gradient(x_rest, prep, jnp.array([p]))
    f = _pressure_forces(mesh, "cavity:chamber", p)
    np.testing.assert_allclose(np.asarray(grad), -f, rtol=0, atol=1e-15 * np.abs(f).max())
    rng = np.random.default_rng(0)
    x = x_rest + 1e-3 * rng.standard_normal(x_rest.shape)
    energy, grad = term.energy_and_gradient(x, prep, jnp.array([p]))
    auto = jax.grad(lambda y: term.energy_and_gradient(y, prep, jnp.array([p]))[0])(x)
    np.testing.assert_allclose(np.asarray(grad), np.asarray(auto), rtol=0, atol=1e-12 * np.abs(auto).max())
    np.testing.assert_allclose(float(energy), -p * float(term.volumes(prep, x)[0]), rtol=1e-12)


def test_large_pressure_limit(sweep):
    """Ramp the pressure past 100 % chamber wall strain: every state on the way is
    converged with no inverted tet, the strain grows monotonically past 100 %, and the
    ramp ends, below 20 kPa, at the first pressure with no equilibrium, where
    :func:`solve_static` raises a :class:`SimulationError` naming the pressure (never a
    silent NaN or an inverted state). On this mesh: 100 % near 14.3 kPa, failure at 15 kPa,
    past the pressure maximum that :func:`test_pressure_maximum_under_volume_control`
    finds."""
    good = _good(sweep)
    assert all(r["inverted"] == 0 and r["min_det"] > 0 for r in good), [(r["kpa"], r["min_det"]) for r in good]
    strains = np.array([r["wall_strain"] for r in good])
    assert np.all(np.diff(strains) > 0), strains
    assert strains[-1] >= 1.0, [(r["kpa"], r["wall_strain"]) for r in sweep]
    last = sweep[-1]
    assert last["error"] is not None, f"the ramp ended without an error: {last}"
    # The message reads the same traced or not, so it names no pressure: the row does.
    # Past the limit the solution both inverts tets and overflows; inverted is reported first.
    assert re.match(r"the static (solution has more inverted tets|solve's positions became non-finite)",
                    last["error"]), last["error"]


def test_pressure_maximum_under_volume_control(finger, sweep):
    """Filled by volume, the chamber passes the pressure maximum of a ballooning wall: its
    pressure rises, peaks and falls while the wall strain grows past 100 % with no
    inverted tet. The peak lies between the highest pressure the pressure-controlled ramp
    held and the one where it failed, so that failure is the physical limit point (no
    static equilibrium exists above the peak), not a solver breakdown."""
    mesh = finger[0]
    term = CavityVolume.from_regions(mesh, ["cavity:chamber"], bulk_modulus=E_WALL)
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(term,)),
                          options=STATIC)
    prep = prepare(model, params, static=True)
    wall = np.flatnonzero(np.isin(mesh.tets, mesh.regions["cavity:chamber"].vertices).any(axis=1))
    x = jnp.asarray(mesh.points)
    pressures, strains = [], []
    # A ramp, each solve from the previous state (larger jumps, from rest to 2.5 or from
    # 3.5 to 4.5, end in inverted states, which solve_static reports). Measured (kPa):
    # 9.77, 13.59, 14.27, 14.58, 14.682, 14.679, 14.653.
    for growth in (1.0, 2.0, 2.5, 3.0, 3.5, 4.0, 4.25):
        x, info = solve_static(model, params, activation=jnp.array([growth]), x0=x)
        assert bool(info.converged) and int(info.inverted) == 0
        pressures.append(float(term.pressures(prep.terms[0], x, jnp.array([growth]))[0]))
        strains.append(float(_stretches(model, prep, np.asarray(x))[0][wall].max() - 1.0))
    peak = int(np.argmax(pressures))
    assert 0 < peak < len(pressures) - 1, pressures  # rises, then falls
    assert strains[-1] > 1.0 and np.all(np.diff(strains) > 0), strains
    held = _good(sweep)[-1]["kpa"] * 1e3
    failed = sweep[-1]["kpa"] * 1e3
    assert held < max(pressures) < failed, (held, pressures, failed)


def test_rollout_past_the_pressure_maximum_raises(finger):
    """A dynamic step to a pressure above the maximum balloons the wall until tets
    invert: the rollout stops with an error naming the step; throw=False reports the
    code and the count there."""
    mesh, term, _, _ = finger
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU, density=1100.0, alpha=20.0), fixed="fixed",
                                   actuators=(term,)),
                          options=Options(dt=0.01, gravity=(0.0, 0.0, 0.0)))
    with pytest.raises(SimulationError, match=r"step 0: more tets inverted \(det F <= 0\) than in the initial state"):
        rollout(model, params, initial_state(model, params), controls=jnp.full((3, 1), 2e4))
    traj = rollout(model, params, initial_state(model, params), controls=jnp.full((3, 1), 2e4), throw=False)
    assert int(traj.info.result[0]) == RESULTS.inverted and int(traj.info.inverted[0]) > 0


def test_volume_control_matches_pressure_control(finger):
    """A cavity filled by volume settles where the wall carries the fluid's pressure: the
    pressure-driven finger at that pressure has the same shape."""
    mesh, _, pressure_model, pressure_params = finger
    term = CavityVolume.from_regions(mesh, ["cavity:chamber"], bulk_modulus=E_WALL)
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(term,)),
                          options=STATIC)
    rest = jnp.asarray(mesh.points)
    growth = jnp.array([0.3])
    x, info = solve_static(model, params, activation=growth, x0=rest)
    assert bool(info.converged)
    prep = prepare(model, params, static=True).terms[0]
    p = term.pressures(prep, x, growth)
    ratio = float(term.volumes(prep, x)[0] / prep.rest_volume[0])
    assert 1.0 < ratio < 1.3 and float(p[0]) > 0  # the wall yields: the fluid is compressed
    np.testing.assert_allclose(float(p[0]), E_WALL * (1.3 - ratio), rtol=1e-12)
    x_p, info = solve_static(pressure_model, pressure_params, activation=p, x0=rest)
    assert bool(info.converged)
    scale = float(jnp.abs(x - rest).max())
    np.testing.assert_allclose(np.asarray(x_p), np.asarray(x), rtol=0, atol=1e-6 * scale)


# --- muscles ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def strip():
    """A 10 x 2 x 2 cm strip clamped at x = 0, a uniform muscle along its axis (the strip's
    tip also moves sideways along (0, 1, 1), by ~20 % of its axial motion: the structured
    split of every cube along the same diagonal is not mirror-symmetric, and the sideways
    motion halves when the grid is refined)."""
    mesh = grid_box((0.1, 0.02, 0.02), (10, 2, 2), origin=(0.0, -0.01, -0.01))
    muscle = Muscle.from_polyline(mesh, [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], radius=0.02,
                                  stiffness=E_WALL, falloff="none", name="axial")
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(muscle,)),
                          options=STATIC)
    return mesh, muscle, model, params


def test_muscle_contracts_along_fibre(strip):
    mesh, _, model, params = strip
    tip = mesh.regions["tip"].vertices
    rest = jnp.asarray(mesh.points)
    x, info = solve_static(model, params, activation=jnp.array([0.0]), x0=rest)
    np.testing.assert_allclose(np.asarray(x), mesh.points, rtol=0, atol=1e-12)
    strains = []
    for a in (0.1, 0.2, 0.3, 0.4):
        x, info = solve_static(model, params, activation=jnp.array([a]), x0=rest)
        assert bool(info.converged)
        u = (np.asarray(x) - mesh.points)[tip].mean(axis=0)
        strains.append(u[0] / 0.1)
    strains = np.array(strains)
    assert np.all(strains < 0) and np.all(np.diff(strains) < 0), strains
    # Bounded by the fibre's own target (1 - a): the matrix resists.
    assert np.all(-strains < np.array([0.1, 0.2, 0.3, 0.4]))


def test_muscle_from_polyline_fibres_and_falloff():
    mesh = grid_box((0.1, 0.1, 0.02), (10, 10, 2))
    r = 0.012
    path = np.array([[0.0, 0.005, 0.01], [0.05, 0.005, 0.01], [0.05, 0.1, 0.01]])  # an L in z = 0.01
    m = Muscle.from_polyline(mesh, path, radius=r, falloff="linear", name="elbow")
    # Distances of the centroids to the two axis-aligned legs.
    x, y, z = mesh.points[mesh.tets].mean(axis=1).T
    d1 = np.sqrt(np.maximum.reduce([-x, 0 * x, x - 0.05]) ** 2 + (y - 0.005) ** 2 + (z - 0.01) ** 2)
    d2 = np.sqrt((x - 0.05) ** 2 + np.maximum.reduce([0.005 - y, 0 * y, y - 0.1]) ** 2 + (z - 0.01) ** 2)
    d = np.minimum(d1, d2)
    np.testing.assert_array_equal(m.tets, np.flatnonzero(d < r))
    np.testing.assert_allclose(np.asarray(m.init_params().weights), 1.0 - d[m.tets] / r, rtol=0, atol=1e-12)
    first, second = (d1 < d2 - 1e-9)[m.tets], (d2 < d1 - 1e-9)[m.tets]
    assert first.any() and second.any()
    np.testing.assert_allclose(m.fibres[first], np.tile([1.0, 0.0, 0.0], (first.sum(), 1)))
    np.testing.assert_allclose(m.fibres[second], np.tile([0.0, 1.0, 0.0], (second.sum(), 1)))
    assert m.channel_names == ("elbow",)
    smooth = Muscle.from_polyline(mesh, path, radius=r)
    np.testing.assert_allclose(np.asarray(smooth.init_params().weights), (1.0 - (d[m.tets] / r) ** 2) ** 2,
                               rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="no tet centroid"):
        Muscle.from_polyline(mesh, [[1.0, 1.0, 1.0], [2.0, 1.0, 1.0]], radius=0.01)
    with pytest.raises(ValueError, match="zero-length"):
        Muscle.from_polyline(mesh, [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], radius=0.01)
    with pytest.raises(ValueError, match="falloff"):
        Muscle.from_polyline(mesh, path, radius=0.01, falloff="cubic")


# --- pneumatic cells ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def cells_box():
    """A box made only of cells, held at one corner vertex."""
    mesh = grid_box((0.02, 0.02, 0.02), (2, 2, 2))
    cells = PneumaticCells(np.arange(mesh.n_tets), np.zeros(mesh.n_tets), ("air",))
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed=[0], actuators=(cells,)), options=STATIC)
    return mesh, cells, model, params


def test_cells_expand_uniformly_to_the_exact_ratio(cells_box):
    """All-cell body, free but for one vertex: F = lambda I with
    lambda = (w_s + w_v a^(1/3)) / (w_s + w_v), which zeroes every tet's stress."""
    mesh, _, model, params = cells_box
    w_s, w_v = pd_weights(E_WALL, NU)
    prep = prepare(model, params, static=True)
    rest = jnp.asarray(mesh.points)
    # 10 lies above max_expansion = 5: refused when given concretely, clipped to 5 when
    # traced (inside an optimisation).
    with pytest.raises(SceneError, match=r"activation\[0\] = 10 is outside channel 'air'.s range \[0.2, 5\]"):
        solve_static(model, params, activation=jnp.array([10.0]), x0=rest)
    traced = jax.jit(lambda a: solve_static(model, params, activation=a, x0=rest))
    for a in (1.0, 0.5, 2.0, 10.0):
        x, info = traced(jnp.array([a]))
        assert bool(info.converged)
        s = min(a, 5.0) ** (1.0 / 3.0)
        lam = (w_s + w_v * s) / (w_s + w_v)
        stretch, det = _stretches(model, prep, x)
        np.testing.assert_allclose(stretch, lam, rtol=1e-8)
        np.testing.assert_allclose(det, lam**3, rtol=1e-8)


# --- bad input ----------------------------------------------------------------------------


def test_bad_actuator_input(finger, cells_box):
    mesh = finger[0]
    with pytest.raises(SceneError, match="no faces"):
        CavityPressure.from_regions(grid_box(), ["xmin"])
    with pytest.raises(SceneError, match="not a closed"):
        CavityPressure.from_regions(mesh, ["tip"])  # the tip face: an open surface
    with pytest.raises(KeyError, match="cavity:nothing"):
        CavityPressure.from_regions(mesh, ["cavity:nothing"])
    faces = mesh.regions["cavity:chamber"].faces
    with pytest.raises(SceneError, match="'spare' maps to no cavity faces"):
        CavityPressure(faces, np.zeros(len(faces)), ("chamber", "spare"))
    with pytest.raises(SceneError, match="encloses a volume of -"):
        CavityPressure.from_regions(
            mesh.with_regions(**{"cavity:flipped": Region(faces.ravel(), faces=faces[:, ::-1])}),
            ["cavity:flipped"])
    with pytest.raises(SceneError, match="vacuum"):
        CavityPressure(faces, np.zeros(len(faces)), ("chamber",), min_pressure=-2e5)
    with pytest.raises(SceneError, match="'empty' maps to no tets"):
        PneumaticCells(np.arange(4), np.zeros(4), ("air", "empty"))
    with pytest.raises(SceneError, match="has no tets"):
        PneumaticCells.from_regions(mesh, ["cavity:chamber"])
    with pytest.raises(SceneError, match="more than one cell"):
        PneumaticCells([0, 1, 1], [0, 0, 0], ("air",))
    with pytest.raises(ValueError, match="maps to no tets"):
        Muscle(np.arange(4), np.tile([1.0, 0, 0], (4, 1)), np.zeros(4), ("on", "off"))
    # Activations of the wrong shape: a short vector reaches the term, which names its channels.
    _, _, model, params = finger
    with pytest.raises(SceneError, match=r"shape \(1,\).*cavity:chamber"):
        solve_static(model, params, activation=jnp.zeros(0), x0=jnp.asarray(mesh.points))
    with pytest.raises(SceneError, match="controls must have shape"):
        rollout(model, params, initial_state(model, params), controls=jnp.zeros((3, 2)))
    _, cells, cmodel, cparams = cells_box
    with pytest.raises(SceneError, match="pneumatic cell activation"):
        cells.volume_targets(prepare(cmodel, cparams).terms[0], jnp.ones((1, 1)))


def test_activations_out_of_range_are_refused(strip, finger, no_compiling):
    """Concrete activations outside a channel's range are refused before compiling, naming
    the step, the channel and the range (a muscle at 2 and at 50 used to behave alike)."""
    mesh, _, model, params = strip
    state = initial_state(model, params)
    controls = np.full((4, 1), 0.2)
    controls[2, 0] = 2.0
    with pytest.raises(
            SceneError, match=r"controls\[2, 0\] \(step 2\) = 2 is outside channel 'axial'.s range \[0, 1\]"):
        rollout(model, params, state, controls=controls)
    with pytest.raises(SceneError, match=r"= -0.5 is outside channel 'axial'"):
        solve_static(model, params, activation=jnp.array([-0.5]))
    fmesh, _, fmodel, fparams = finger
    bounded = CavityPressure.from_regions(fmesh, ["cavity:chamber"], max_pressure=5e4)
    bmodel, bparams = build(SoftBody(fmesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(bounded,)),
                            options=STATIC)
    with pytest.raises(SceneError, match=r"= 60000 is outside channel 'cavity:chamber'.s range"):
        solve_static(bmodel, bparams, activation=jnp.array([6e4]))
    with pytest.raises(SceneError, match=r"actuators\[0\] is a dict, not an actuator"):
        build(SoftBody(fmesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=({"pressure": 1.0},)))


def test_pressure_clipped_to_bounds():
    mesh = examples.finger(size=0.004)
    term = CavityPressure.from_regions(mesh, ["cavity:chamber"], min_pressure=0.0, max_pressure=5e4)
    np.testing.assert_array_equal(np.asarray(term.pressures(jnp.array([-1e3]))), [0.0])
    np.testing.assert_array_equal(np.asarray(term.pressures(jnp.array([1e6]))), [5e4])
    np.testing.assert_array_equal(np.asarray(term.pressures(jnp.array([1.2e4]))), [1.2e4])


# --- gradients (implicit adjoint of the static solve) against central differences --------


def _central(fn, x, direction, eps):
    return (fn(x + eps * direction) - fn(x - eps * direction)) / (2 * eps)


def _check_gradients(model, params, activation, point, coordinate, design, eps_a, eps_w, rtol=1e-5):
    """``d x[point, coordinate] / d activation`` and the derivative along a random
    direction of the design array ``design(params)`` (reverse mode through the static
    solve) against central differences. The steps ``eps`` are ~1e-3 of the values: the
    forward solves' error (force residual 1e-10 N) divided by eps and the O(eps^2)
    truncation then both stay near 1e-7 relative (at 1e-4 the first reached 4e-6)."""
    rest = jnp.asarray(model.mesh.points)

    def loss(a, w):
        p = eqx.tree_at(design, params, w)
        return solve_static(model, p, activation=a, x0=rest)[0][point, coordinate].mean()

    w0 = design(params)
    ga, gw = jax.grad(loss, argnums=(0, 1))(activation, w0)
    unit = jnp.zeros_like(activation).at[0].set(1.0)
    fd_a = _central(lambda a: loss(a, w0), activation, unit, eps_a)
    direction = jnp.asarray(np.random.default_rng(1).standard_normal(w0.shape))
    direction = direction / jnp.linalg.norm(direction)
    fd_w = _central(lambda w: loss(activation, w), w0, direction, eps_w)
    np.testing.assert_allclose(float(ga[0]), float(fd_a), rtol=rtol)
    np.testing.assert_allclose(float(jnp.sum(gw * direction)), float(fd_w), rtol=rtol)


def test_muscle_gradients(strip):
    """Tip position w.r.t. the activation and the per-tet fibre weights."""
    mesh, _, model, params = strip
    _check_gradients(model, params, jnp.array([0.3]), mesh.regions["tip"].vertices, 0,
                     lambda p: p.actuators[0].weights, eps_a=3e-4, eps_w=1e-3)


def test_cavity_pressure_gradients(finger):
    """Tip height w.r.t. the pressure (Pa) and the chamber's selection weight."""
    mesh, _, model, params = finger
    _check_gradients(model, params, jnp.array([5e3]), mesh.regions["tip"].vertices, 2,
                     lambda p: p.actuators[0].gain, eps_a=10.0, eps_w=1e-3)


def test_cell_gradients():
    """A corner of a half-cell strip w.r.t. the expansion and the per-cell weights."""
    mesh = grid_box((0.04, 0.01, 0.01), (4, 1, 1))
    top = np.flatnonzero(mesh.points[mesh.tets].mean(axis=1)[:, 2] > 0.005)
    cells = PneumaticCells(top, np.zeros(len(top)), ("air",))
    model, params = build(SoftBody(mesh, Material(E=E_WALL, nu=NU), fixed="fixed", actuators=(cells,)),
                          options=STATIC)
    _check_gradients(model, params, jnp.array([1.5]), mesh.regions["tip"].vertices, 2,
                     lambda p: p.actuators[0].weights, eps_a=1e-3, eps_w=1e-3)

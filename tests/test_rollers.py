"""Vertices held in chosen components only (``Fix(where, axes=...)``): a beam on its
symmetry plane is the full beam's half, statically and in time, gradients pass through the
per-axis matrices, and what the step cannot hold yet is refused before compiling."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody import linsolve
from softbody.explicit import critical_time_step, explicit_rollout
from softbody.gradients import check_grad
from softbody.material import Material
from softbody.meshing import TetMesh
from softbody.meshing.grid import grid_box
from softbody.model import Options, SceneError, build, initial_state
from softbody.scene import Fix, SoftBody
from softbody.contact.obstacles import Plane
from softbody.reference import diffrax_rollout, newton_static
from softbody.skeleton import Link, Skeleton
from softbody.simulate import rollout, solve_static

LENGTH, HALF_WIDTH, HEIGHT = 0.2, 0.02, 0.04
MATERIAL = Material(E=2e5, nu=0.45, density=1000.0)
OPTIONS = Options(dt=0.01, tol=1e-11, max_iter=20000)
HALF = grid_box((LENGTH, HALF_WIDTH, HEIGHT), (8, 2, 2))


def _on_plane(points):
    return np.abs(points[:, 1]) < 1e-12


def _clamp(points):
    return points[:, 0] < 1e-12


def _mirror(mesh: TetMesh) -> tuple[TetMesh, np.ndarray]:
    """The mesh and its mirror image in ``y = 0`` glued on the plane; returns the full mesh
    and, for each full vertex, the half vertex it is (or mirrors)."""
    n = mesh.n_vertices
    off = np.flatnonzero(~_on_plane(mesh.points))
    image = np.arange(n)
    image[off] = n + np.arange(len(off))
    points = np.concatenate([mesh.points, mesh.points[off] * np.array([1.0, -1.0, 1.0])])
    mirrored = image[mesh.tets][:, [0, 2, 1, 3]]  # a reflection flips orientation
    source = np.concatenate([np.arange(n), off])
    return TetMesh(points, np.concatenate([mesh.tets, mirrored])), source


FULL, SOURCE = _mirror(HALF)


@pytest.fixture(scope="module")
def beams():
    half = build(SoftBody(HALF, MATERIAL, fixed=[Fix(_clamp), Fix(_on_plane, axes="y")]), options=OPTIONS)
    full = build(SoftBody(FULL, MATERIAL, fixed=_clamp), options=OPTIONS)
    return half, full


def _half_of(field_full):
    """The full beam's field on the half's vertices (the half's vertices come first)."""
    return np.asarray(field_full)[: HALF.n_vertices]


def test_the_symmetry_plane_makes_half_a_beam_the_full_beam_statically(beams):
    """Self-weight is symmetric about ``y = 0`` and the full mesh is the half and its mirror
    image, so the full equilibrium restricted to the half is the half's equilibrium with
    ``u_y = 0`` on the plane: equal to the solves' tolerance (1e-11 of the load), checked
    at 1e-6 of the deflection. Without the roller the plane's vertices would swell sideways
    (Poisson, nu = 0.45) and the field would differ by far more: checked too."""
    (half, hp), (full, fp) = beams
    x_half, info_h = solve_static(half, hp)
    x_full, info_f = solve_static(full, fp)
    assert isinstance(half.linear_solver, linsolve.PerColumn)
    u_half, u_full = np.asarray(x_half) - HALF.points, _half_of(x_full) - HALF.points
    scale = np.abs(u_full).max()
    gap = np.abs(u_half - u_full).max()
    print(f"tip deflection half {u_half[:, 2].min():.9e} m, full {u_full[:, 2].min():.9e} m; "
          f"max field gap {gap:.2e} m of {scale:.2e} m ({int(info_h.iterations)}, {int(info_f.iterations)} iters)")
    assert np.abs(u_half[_on_plane(HALF.points), 1]).max() == 0.0
    assert gap <= 1e-6 * scale

    loose, lp = build(SoftBody(HALF, MATERIAL, fixed=_clamp), options=OPTIONS)
    x_loose, _ = solve_static(loose, lp)
    assert np.abs(np.asarray(x_loose) - _half_of(x_full)).max() > 1e-3 * scale


def test_newton_reference_holds_the_same_components(beams):
    """The Newton reference's free degrees of freedom are per component: its equilibrium of
    the half beam equals the PD static solve's to the solvers' tolerances."""
    (half, hp), _ = beams
    x_pd, _ = solve_static(half, hp)
    x_nt, _ = newton_static(half, hp, tol=1e-10)
    u = np.asarray(x_pd) - HALF.points
    assert np.abs(np.asarray(x_nt) - np.asarray(x_pd)).max() <= 1e-6 * np.abs(u).max()


def test_the_half_beam_swings_like_the_full_beam(beams):
    """Released from rest under gravity, 10 implicit steps: each step is a minimisation
    whose minimiser the symmetry makes the same for both, so the trajectories agree to the
    step tolerance."""
    (half, hp), (full, fp) = beams
    th = rollout(half, hp, initial_state(half, hp), n_steps=10)
    tf = rollout(full, fp, initial_state(full, fp), n_steps=10)
    xf = np.asarray(tf.x)[:, : HALF.n_vertices]
    scale = np.abs(xf - HALF.points).max()
    gap = np.abs(np.asarray(th.x) - xf).max()
    print(f"10 steps: max gap {gap:.2e} m of {scale:.2e} m moved")
    assert gap <= 1e-6 * scale


def test_the_explicit_integrator_holds_the_same_components(beams):
    """The explicit integrator masks accelerations per component: 40 steps at half the
    critical step of the half beam and of the full beam agree to rounding."""
    (half, hp), (full, fp) = beams
    dt = 0.5 * critical_time_step(full, fp)
    th = explicit_rollout(dataclasses.replace(half, options=dataclasses.replace(half.options, dt=dt)), hp,
                          initial_state(half, hp), n_steps=40)
    tf = explicit_rollout(dataclasses.replace(full, options=dataclasses.replace(full.options, dt=dt)), fp,
                          initial_state(full, fp), n_steps=40)
    xf = np.asarray(tf.x)[:, : HALF.n_vertices]
    moved, gap = np.abs(xf - HALF.points).max(), np.abs(np.asarray(th.x) - xf).max()
    print(f"explicit, dt = {dt:.3g} s: max gap {gap:.2e} m of {moved:.2e} m moved")
    assert moved > 1e-6
    assert gap <= 1e-9 * moved


def test_gradients_pass_through_the_per_axis_matrices(beams):
    """The half beam's tip deflection after 5 steps, differentiated (implicit adjoint, whose
    linear solves run one matrix per axis) with respect to E and the density, against
    central differences."""
    (half, hp), _ = beams
    tip = jnp.asarray(np.flatnonzero(HALF.points[:, 0] > LENGTH - 1e-12))

    def deflection(theta):  # theta: E and the density relative to their values
        p = eqx.tree_at(lambda q: (q.E, q.density), hp, (hp.E * theta[:1], hp.density * theta[1:]))
        traj = rollout(half, p, initial_state(half, p), n_steps=5)
        return jnp.mean(traj.x[-1, tip, 2])

    result = check_grad(deflection, jnp.array([1.0, 1.0]), eps=1e-3,
                        directions={"E": jnp.array([1.0, 0.0]), "density": jnp.array([0.0, 1.0])})
    for name, r in result.items():
        assert r["rel_error"] < 1e-5, (name, r)


def test_held_components_follow_a_moving_clamp():
    """A roller plate that rises: vertices held in z only go up with it and stay free in x
    and y (their rest x, y keep whatever the step gives them)."""
    bar = grid_box((0.1, 0.02, 0.02), (4, 1, 1))
    model, params = build(SoftBody(bar, Material(E=1e5, nu=0.3), fixed=Fix("zmin", axes="z"),
                                   motion=lambda t: (jnp.eye(3), jnp.array([0.0, 0.0, 0.1]) * t)),
                          options=Options(dt=0.01, gravity=(0.0, 0.0, 0.0), tol=1e-10))
    traj = rollout(model, params, initial_state(model, params), n_steps=5)
    zmin = bar.regions["zmin"].vertices
    assert np.allclose(np.asarray(traj.x)[-1, zmin, 2], 0.1 * 0.05, atol=1e-15)
    # the bar is carried up as a whole (nothing holds the top): its centre rises with the plate
    assert float(jnp.mean(traj.x[-1, :, 2])) > 0.01 + 0.5 * 0.1 * 0.05


def test_partly_held_vertices_are_refused_where_the_step_cannot_hold_them(no_compiling):
    """Bad axes, a mixed list, a skeleton or obstacles with partly held vertices, and the
    diffrax reference: each a clear error before compiling."""
    with pytest.raises(SceneError, match="subset of|once each"):
        Fix("xmin", axes="xw")
    with pytest.raises(SceneError, match="once each"):
        Fix("xmin", axes="")
    with pytest.raises(SceneError, match="mixing Fix"):
        build(SoftBody(HALF, MATERIAL, fixed=[Fix("xmin"), "ymin"]))
    with pytest.raises(SceneError, match="contact holds vertices in all three"):
        build(SoftBody(HALF, MATERIAL, fixed=Fix("ymin", axes="y")), obstacles=[Plane(point=(0, 0, -0.01))])
    bone = grid_box((0.1, 0.02, 0.02), (4, 1, 1))
    with pytest.raises(SceneError, match="skeleton holds vertices in all three"):
        build(SoftBody(bone, MATERIAL, fixed=Fix("ymin", axes="y")), skeleton=Skeleton([Link("arm", "bone:arm")]))
    with pytest.raises(SceneError, match="not in the mesh"):
        build(SoftBody(HALF, MATERIAL, fixed=Fix("nowhere", axes="y")))
    model, params = build(SoftBody(HALF, MATERIAL, fixed=[Fix("xmin"), Fix("ymin", axes="y")]))
    with pytest.raises(SceneError, match="whole free vertices"):
        diffrax_rollout(model, params, initial_state(model, params), 0.01, [0.01])


# --------------------------------------------------------------------------------------
# Plane strain by extrusion: Cook's membrane
# --------------------------------------------------------------------------------------

MM = 1e-3
COOK_E, COOK_NU = 1e6, 1.0 / 3.0
COOK_SHEAR = 0.2  # N per metre of thickness, spread evenly over the right edge (16 mm)
COOK_CORNERS = np.array([[0.0, 0.0], [48.0, 44.0], [48.0, 60.0], [0.0, 44.0]]) * MM


def _cook_map(s, r):
    """The unit square onto Cook's trapezoid (bilinear; ``s``: left to right edge)."""
    a, b, c, d = COOK_CORNERS
    return ((1 - s) * (1 - r))[:, None] * a + (s * (1 - r))[:, None] * b + (s * r)[:, None] * c \
        + ((1 - s) * r)[:, None] * d


def _cook_slab(cells: int, thickness: float = 2 * MM):
    """One layer of ``cells x cells`` hexahedra (6 tets each) over Cook's section; returns
    the mesh, the model (left edge clamped, every vertex held in z: plane strain), its
    params and the right edge's consistent shear load (half on each face of the slab)."""
    box = grid_box((1.0, 1.0, thickness), (cells, cells, 1))
    unit = box.points
    points = np.column_stack([_cook_map(unit[:, 0], unit[:, 1]), unit[:, 2]])
    mesh = TetMesh(points, box.tets)
    right = np.flatnonzero(unit[:, 0] > 1 - 1e-12)
    ends = (unit[right, 1] < 1e-12) | (unit[right, 1] > 1 - 1e-12)
    force = np.zeros((mesh.n_vertices, 3))
    force[right, 1] = COOK_SHEAR * thickness / 2 * np.where(ends, 0.5, 1.0) / cells
    model, params = build(SoftBody(mesh, Material(E=COOK_E, nu=COOK_NU, density=1.0),
                                   fixed=[Fix(lambda p: p[:, 0] < 1e-12),
                                          Fix(lambda p: np.ones(len(p), bool), axes="z")]),
                          options=Options(gravity=(0.0, 0.0, 0.0), tol=1e-10, max_iter=50000))
    corner = np.flatnonzero((unit[:, 0] > 1 - 1e-12) & (unit[:, 1] > 1 - 1e-12))
    return mesh, model, params, force, corner


def _cook_tip(cells: int):
    """The top right corner's vertical displacement (mean over the two faces), m."""
    mesh, model, params, force, corner = _cook_slab(cells)
    x, info = solve_static(model, params, force=jnp.asarray(force))
    return float(np.mean(np.asarray(x)[corner, 1] - mesh.points[corner, 1])), int(info.iterations)


def _skfem_cook_2d(cells: int) -> float:
    """scikit-fem's plane-strain answer: quadratic triangles on the same section, the same
    clamp and shear traction; the top right corner's vertical displacement, m."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    unit = skfem.MeshQuad.init_tensor(np.linspace(0, 1, cells + 1), np.linspace(0, 1, cells + 1)).to_meshtri()
    mesh = skfem.MeshTri(np.ascontiguousarray(_cook_map(unit.p[0], unit.p[1]).T), unit.t)
    element = skfem.ElementVector(skfem.ElementTriP2())
    basis = skfem.Basis(mesh, element, intorder=4)
    # 3-D Lame parameters in 2-D linear elasticity are plane strain (eps_zz = 0)
    stiffness = linear_elasticity(*lame_parameters(COOK_E, COOK_NU)).assemble(basis)
    edge = skfem.FacetBasis(mesh, element, facets=mesh.facets_satisfying(lambda x: x[0] > 48 * MM - 1e-12),
                            intorder=4)

    @skfem.LinearForm
    def shear(v, w):
        return COOK_SHEAR / (16 * MM) * v[1]

    clamp = basis.get_dofs(lambda x: x[0] < 1e-12).all()
    u = skfem.solve(*skfem.condense(stiffness, shear.assemble(edge), D=clamp))
    return float((basis.probes(COOK_CORNERS[2][:, None]) @ u)[1])


def test_plane_strain_slab_is_the_3d_solution_held_in_z():
    """The extruded slab held in z everywhere against scikit-fem's linear P1 tets on the same
    mesh with the same z components removed (the plane-strain constraint applied in 3-D):
    the same discrete problem, so they agree to the geometric nonlinearity of the corotated
    model (displacements ~1e-4 of the size: ~1e-4 relative), checked at 1e-3."""
    import skfem
    from skfem.models.elasticity import lame_parameters, linear_elasticity

    mesh, model, params, force, corner = _cook_slab(6)
    assert isinstance(model.linear_solver, linsolve.PerColumn)
    x, _ = solve_static(model, params, force=jnp.asarray(force))
    u_pd = np.asarray(x) - mesh.points
    m = skfem.MeshTet(np.ascontiguousarray(mesh.points.T), np.ascontiguousarray(mesh.tets.T))
    basis = skfem.Basis(m, skfem.ElementVector(skfem.ElementTetP1()))
    stiffness = linear_elasticity(*lame_parameters(COOK_E, COOK_NU)).assemble(basis)
    held = np.concatenate([basis.nodal_dofs[:, model.free_mask[:, 0] == 0].ravel(), basis.nodal_dofs[2]])
    load = np.zeros(basis.N)
    load[basis.nodal_dofs] = force.T
    u = skfem.solve(*skfem.condense(stiffness, load, D=np.unique(held)))
    u_fem = u[basis.nodal_dofs].T
    print(f"tip: PD {u_pd[corner, 1].mean():.6e} m, scikit-fem P1 tets {u_fem[corner, 1].mean():.6e} m")
    assert np.abs(u_pd[:, 2]).max() == 0.0
    assert np.abs(u_pd - u_fem).max() <= 1e-3 * np.abs(u_fem).max()


@pytest.mark.slow
def test_plane_strain_by_extrusion_converges_to_scikit_fem_2d():
    """Cook's membrane (48 x 44/16 mm, nu = 1/3, shear on the right edge) as one layer of
    tets held in z: the top right corner's deflection converges to scikit-fem's 2-D
    plane-strain answer (P2 triangles, 64 x 64 quads, itself within ~0.2% of its
    Richardson limit), the error shrinking about 3x per halving of the cells, and is within
    1% at 128 x 128 cells."""
    reference = _skfem_cook_2d(64)
    errors = []
    for cells in (16, 32, 64, 128):
        tip, iterations = _cook_tip(cells)
        errors.append(abs(tip / reference - 1))
        print(f"{cells:4d} x {cells:<4d} cells: tip {tip:.6e} m vs {reference:.6e} m, error {errors[-1]:.2%} "
              f"({iterations} L-BFGS iterations)")
    assert all(b < a for a, b in zip(errors, errors[1:]))
    assert errors[-1] < 0.01

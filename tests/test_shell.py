"""Membranes (softbody.shell): the plane-stress patch test, finite derivatives at rest, the
PD blocks bounding the Hessian, and a fabric-reinforced pneumatic finger that bends further
and stretches less, with the fabric's stiffness as a differentiable design parameter."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softbody.actuators import CavityPressure
from softbody.gradients import check_grad
from softbody.material import Material
from softbody.meshing import examples
from softbody.model import Options, SceneError, build, prepare
from softbody.scene import SoftBody
from softbody.shell import Membrane, hinges
from softbody.simulate import solve_static

E, NU, T = 2e8, 0.3, 3e-4  # a stiff woven fabric: E t = 6e4 N/m


def _sheet(rotation, nx=6, ny=4, size=(0.3, 0.2), offset=(0.1, -0.2, 0.3)):
    """A structured triangulated ``size`` rectangle (alternating diagonals) in the plane
    spanned by the first two columns of ``rotation``, moved by ``offset``: ``(points (n, 3),
    triangles (m, 3), (a, b))`` with ``a, b`` each vertex's in-plane coordinates."""
    a, b = np.meshgrid(np.linspace(0, size[0], nx + 1), np.linspace(0, size[1], ny + 1), indexing="ij")
    a, b = a.ravel(), b.ravel()
    idx = np.arange(len(a)).reshape(nx + 1, ny + 1)
    tris = []
    for i in range(nx):
        for j in range(ny):
            p, q, r, s = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tris += [[p, q, r], [p, r, s]] if (i + j) % 2 else [[p, q, s], [q, r, s]]
    points = np.stack([a, b, np.zeros_like(a)], axis=1) @ rotation.T + np.asarray(offset)
    return points, np.asarray(tris), (a, b)


def _membrane(points, tris):
    return Membrane.on(points, tris, E=E, nu=NU, thickness=T)


ROTATION = np.linalg.qr(np.random.default_rng(1).standard_normal((3, 3)))[0]


def test_patch_test_uniform_stretch_is_plane_stress_elasticity():
    """A sheet in a tilted plane stretched uniformly by (2 %, -0.5 %) along its sides: the
    energy is the plane-stress energy ``A t E/(2(1-nu^2)) (ea^2 + eb^2 + 2 nu ea eb)``, the
    interior nodes need no load and the nodes of the side at ``a = L_a`` are pulled with
    ``t L_b E/(1-nu^2) (ea + nu eb)`` in all (likewise along ``b``), to round-off."""
    points, tris, (a, b) = _sheet(ROTATION)
    membrane = _membrane(points, tris)
    prep = membrane.prepare(None, membrane.init_params(), None, None)
    ea, eb = 0.02, -0.005
    x = (np.stack([a * (1 + ea), b * (1 + eb), np.zeros_like(a)], axis=1) @ ROTATION.T + [0.1, -0.2, 0.3])
    energy, grad = membrane.energy_and_gradient(jnp.asarray(x), prep, None)
    width, height = 0.3, 0.2
    modulus = E / (1 - NU**2)
    assert float(energy) == pytest.approx(width * height * T * modulus / 2 * (ea**2 + eb**2 + 2 * NU * ea * eb),
                                          rel=1e-12)
    force = np.asarray(grad) @ ROTATION  # the load that holds each node, in the sheet's (a, b, normal) axes
    boundary = np.isclose(a, 0) | np.isclose(a, width) | np.isclose(b, 0) | np.isclose(b, height)
    scale = T * modulus * 0.02 * width
    assert np.abs(force[~boundary]).max() < 1e-10 * scale
    assert np.abs(force[:, 2]).max() < 1e-10 * scale
    right = np.isclose(a, width)
    top = np.isclose(b, height)
    np.testing.assert_allclose(force[right, 0].sum(), T * height * modulus * (ea + NU * eb), rtol=1e-10)
    np.testing.assert_allclose(force[top, 1].sum(), T * width * modulus * (eb + NU * ea), rtol=1e-10)


def test_derivatives_are_finite_at_rest_and_the_blocks_bound_the_hessian():
    """At rest the gradient vanishes and the Hessian is finite; at rest and at a random
    deformation the PD matrix's blocks (``(2 mu + 2 lam*) A t G G^T`` per coordinate) bound
    the Hessian from above (what local-global steps and the contact splitting need)."""
    points, tris, _ = _sheet(ROTATION, nx=2, ny=2)
    membrane = _membrane(points, tris)
    prep = membrane.prepare(None, membrane.init_params(), None, None)
    n = len(points)
    blocks = np.asarray(membrane.blocks(prep))
    scalar = np.zeros((n, n))
    for tri, block in zip(tris, blocks):
        scalar[np.ix_(tri, tri)] += block
    pd = np.kron(scalar, np.eye(3))

    def energy(x):
        return membrane.energy_and_gradient(x.reshape(n, 3), prep, None)[0]

    x0 = jnp.asarray(points).ravel()
    assert np.abs(np.asarray(jax.grad(energy)(x0))).max() < 1e-9 * E * T
    rng = np.random.default_rng(0)
    for x in (x0, x0 + 0.02 * 0.1 * rng.standard_normal(x0.shape)):
        hessian = np.asarray(jax.hessian(energy)(x))
        assert np.all(np.isfinite(hessian))
        assert np.linalg.eigvalsh(pd - hessian).min() > -1e-9 * np.abs(pd).max()


def test_bad_membranes_are_refused():
    points, tris, _ = _sheet(ROTATION, nx=2, ny=2)
    mesh = examples.finger(size=0.004)
    collinear = np.array([[0, 1, 2]])  # the sheet's first column of vertices
    for message, kwargs in {"degenerate": dict(triangles=collinear),
                            "no region": dict(triangles="nowhere"),
                            "must lie in": dict(triangles=np.array([[0, 1, 10**6]])),
                            "thickness > 0": dict(triangles=tris, thickness=0.0)}.items():
        args = dict(E=E, nu=NU, thickness=T) | kwargs
        with pytest.raises(SceneError, match=message):
            Membrane.on(points if message == "degenerate" else mesh, args.pop("triangles"), **args)
    with pytest.raises(SceneError, match="names no triangles"):
        Membrane.on(mesh.with_regions(empty=mesh.regions["tip"].__class__(vertices=[0])), "empty", E=E, nu=NU,
                    thickness=T)


def test_an_empty_triangle_selection_is_refused_naming_the_fix():
    """An empty array (e.g. a face selection that matched nothing) is named as such, with
    what to give instead."""
    points, _, _ = _sheet(ROTATION, nx=2, ny=2)
    for empty in (np.zeros((0, 3), np.int64), []):
        with pytest.raises(SceneError, match="names no triangles.*surface region"):
            Membrane.on(points, empty, E=E, nu=NU, thickness=T)


def test_a_triangle_given_twice_is_refused():
    """A repeated triangle (in any vertex order) would count its stiffness twice."""
    points, tris, _ = _sheet(ROTATION, nx=2, ny=2)
    twice = np.vstack([tris, tris[3, [1, 2, 0]]])
    with pytest.raises(SceneError, match=r"given more than once, e\.g\. .* give each triangle once"):
        Membrane.on(points, twice, E=E, nu=NU, thickness=T)


def test_a_non_manifold_membrane_is_refused():
    """Three sheets meeting on one edge (a fin on a sheet) are not one membrane: refused
    with the shared edge and the fix, for a membrane alone too (without a bending term,
    whose hinges need a manifold)."""
    points, tris, _ = _sheet(ROTATION, nx=2, ny=2)
    edge = hinges(tris)[0, :2]  # an interior edge of the 2 x 2 sheet, shared by two of its triangles
    fin = np.vstack([points, points[edge].mean(axis=0) + 0.1 * ROTATION[:, 2]])
    fan = np.vstack([tris, [[edge[0], edge[1], len(points)]]])
    with pytest.raises(SceneError, match=r"not a manifold surface: 1 edges .* by 3; give each sheet"):
        Membrane.on(fin, fan, E=E, nu=NU, thickness=T)


PRESSURE = 5e3  # Pa
STATIC = Options(gravity=(0.0, 0.0, 0.0), tol=1e-10, atol=1e-10, max_iter=5000)


@pytest.fixture(scope="module")
def finger():
    """The example pneumatic finger (silicone, E 1e5 Pa) with its chamber centred on the
    neutral axis (``gap=-7 mm``), alone and with a fabric membrane bonded to its bottom face."""
    mesh = examples.finger(size=0.004, gap=-0.007)
    z = mesh.points[mesh.surface][..., 2]
    bottom = mesh.surface[np.all(np.isclose(z, mesh.points[:, 2].min()), axis=1)]
    chamber = CavityPressure.from_regions(mesh, ["cavity:chamber"])
    fabric = Membrane.on(mesh, bottom, E=E, nu=NU, thickness=T)
    silicone = Material(E=1e5, nu=0.45)
    alone = build(SoftBody(mesh, silicone, fixed="fixed", actuators=[chamber]), options=STATIC)
    bonded = build(SoftBody(mesh, silicone, fixed="fixed", actuators=[chamber, fabric]), options=STATIC)
    return mesh, alone, bonded, (chamber, bottom, silicone)


def test_a_fabric_layer_makes_the_finger_bend_further_and_stretch_less(finger):
    """At 5 kPa the finger alone elongates and hardly bends (measured: tip 2.08 mm along x,
    0.017 mm down); the fabric (``E t`` 6e4 N/m against the 3 mm silicone wall's 300 N/m)
    holds its face's strain below 1 % of the finger alone's (measured 0.003 % against
    2.5 %), so the finger curls towards it (tip 5.09 mm down, over 10 times the finger
    alone's) and its tip moves less along x (1.14 mm)."""
    mesh, alone, bonded, _ = finger
    tip = mesh.regions["tip"].vertices
    points = mesh.points
    edge = np.flatnonzero(np.isclose(points[:, 2], points[:, 2].min()) & np.isclose(points[:, 1], points[:, 1].min()))
    edge = edge[np.argsort(points[edge, 0])]  # a bottom edge of the finger, base to tip
    moved, strain = {}, {}
    for name, (model, params) in (("alone", alone), ("bonded", bonded)):
        x, _ = solve_static(model, params, activation=jnp.array([PRESSURE]), x0=jnp.asarray(points))
        x = np.asarray(x)
        moved[name] = x[tip].mean(axis=0) - points[tip].mean(axis=0)
        strain[name] = np.sum(np.linalg.norm(np.diff(x[edge], axis=0), axis=1)) / np.ptp(points[edge, 0]) - 1
    assert strain["alone"] > 0 and abs(strain["bonded"]) < 0.01 * strain["alone"]
    assert moved["bonded"][2] < 10 * moved["alone"][2] < 0  # curls towards the fabric
    assert 0 < moved["bonded"][0] < moved["alone"][0]  # elongates less


@pytest.mark.slow
def test_the_fabric_stiffness_gradient_matches_central_differences(finger):
    """d(tip height)/d(log E, log thickness of the fabric) through the static solve's
    implicit adjoint against central differences at eps 3e-3 (relative error <= 1e-6;
    measured 3e-8 and 8e-9). A softer fabric (``E t`` 1e3 N/m) than above: the stiff one
    saturates (the tip moves 2e-5 m per unit of log E), and there the differences carry the
    static solve's stopping noise (1e-5 relative at eps 1e-2, where the adjoint's result
    agrees to 1e-12 at adjoint tolerances 1e-10 and 1e-13)."""
    mesh, _, _, (chamber, bottom, silicone) = finger
    fabric = Membrane.on(mesh, bottom, E=1e3 / T, nu=NU, thickness=T)
    model, params = build(SoftBody(mesh, silicone, fixed="fixed", actuators=[chamber, fabric]),
                          options=Options(gravity=(0.0, 0.0, 0.0), tol=1e-11, atol=1e-11, max_iter=10000))
    tip = jnp.asarray(mesh.regions["tip"].vertices)

    def height(log_scales):
        fabric = params.actuators[1]
        fabric = dataclasses.replace(fabric, E=fabric.E * jnp.exp(log_scales[0]),
                                     thickness=fabric.thickness * jnp.exp(log_scales[1]))
        p = params.replace(actuators=(params.actuators[0], fabric))
        x, _ = solve_static(model, p, activation=jnp.array([PRESSURE]), x0=jnp.asarray(mesh.points))
        return jnp.mean(x[tip, 2])

    results = check_grad(height, jnp.zeros(2), directions={"log_E": jnp.array([1.0, 0.0]),
                                                             "log_t": jnp.array([0.0, 1.0])}, eps=3e-3)
    for name, r in results.items():
        assert r["rel_error"] <= 1e-6, (name, r)


def test_a_heavy_fabric_weighs_as_its_lumped_loads(finger):
    """A fabric of 0.3 kg/m^2 adds ``rho_A A`` to the scene's mass, and under gravity the
    finger sags exactly as with a massless fabric loaded by ``rho_A A_e g / 3`` on each of
    its triangles' vertices (to 1e-8 of the sag, at solve tolerance 1e-9)."""
    mesh, _, _, (_, bottom, silicone) = finger
    rho = 0.3
    heavy = Membrane.on(mesh, bottom, E=E, nu=NU, thickness=T, areal_density=rho)
    light = Membrane.on(mesh, bottom, E=E, nu=NU, thickness=T)
    options = Options(tol=1e-9, atol=1e-14, max_iter=10000)
    (m_heavy, p_heavy), (m_light, p_light) = (build(SoftBody(mesh, silicone, fixed="fixed", actuators=[f]),
                                                    options=options) for f in (heavy, light))
    added = float(np.sum(prepare(m_heavy, p_heavy).mass) - np.sum(prepare(m_light, p_light).mass))
    assert added == pytest.approx(rho * heavy.area.sum(), rel=1e-12)
    loads = np.zeros((mesh.n_vertices, 3))
    np.add.at(loads[:, 2], bottom, -9.81 * rho * heavy.area[:, None] / 3.0)
    x_heavy, _ = solve_static(m_heavy, p_heavy)
    x_light, _ = solve_static(m_light, p_light, force=jnp.asarray(loads))
    sag = np.abs(np.asarray(x_light) - mesh.points).max()
    assert np.abs(np.asarray(x_heavy) - np.asarray(x_light)).max() < 1e-8 * sag  # measured 3.6e-11 of 6.9 mm

"""Rigid bodies: exact mass properties of closed surfaces against analytic physics, and the
checks that refuse surfaces and values a rigid body cannot have."""

import meshio
import numpy as np
import pytest

from softbody import meshing
from softbody._types import SceneError
from softbody.rigid import RigidBody, mass_properties

MeshError = meshing.MeshError
RHO = 2700.0

#: unit cube corners, index 4x + 2y + z, and its faces as quads counter-clockwise from outside
_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
_QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
BOX_TRIANGLES = np.array([t for q in _QUADS for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])])


def rotation(axis, angle):
    """Rotation matrix about ``axis`` by ``angle`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def box(size, R=None, centre=(0.0, 0.0, 0.0)):
    """12-triangle surface of a box of edge lengths ``size`` centred on ``centre``, rotated by ``R``."""
    R = np.eye(3) if R is None else R
    local = (_CORNERS - 0.5) * np.asarray(size, float)
    return local @ R.T + np.asarray(centre, float), BOX_TRIANGLES.copy()


def cylinder(r, h, k):
    """Surface of a cylinder along z (radius ``r``, height ``h``, centred on the origin), faceted
    with ``k`` segments: side quads split in two, caps as fans from their centres."""
    theta = 2 * np.pi * np.arange(k) / k
    ring = np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros(k)], axis=1)
    points = np.concatenate([ring - [0, 0, h / 2], ring + [0, 0, h / 2], [[0, 0, -h / 2], [0, 0, h / 2]]])
    i, j = np.arange(k), (np.arange(k) + 1) % k
    bottom, top = np.full(k, 2 * k), np.full(k, 2 * k + 1)
    triangles = np.concatenate([
        np.stack([bottom, j, i], axis=1), np.stack([top, k + i, k + j], axis=1),
        np.stack([i, j, k + j], axis=1), np.stack([i, k + j, k + i], axis=1)])
    return points, triangles


def octahedron():
    """A closed, irregular, rotated octahedron (full inertia tensor, centre off its vertices' mean)."""
    reach = np.array([0.11, 0.05, 0.07, 0.13, 0.06, 0.09])  # along +x, -x, +y, -y, +z, -z
    points = np.zeros((6, 3))
    points[np.arange(6), np.arange(6) // 2] = reach * np.tile([1, -1], 3)
    triangles = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                          [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return points @ rotation((0.3, -1.0, 0.5), 1.1).T, triangles


def _rotated_brick(t):
    """A 0.3 x 0.2 x 0.1 box turned about (1, 2, 3) and centred at ``t``: its edges, rotation,
    mass and inertia tensor (about its centre, in world axes) from the textbook formulas."""
    a, b, c = 0.3, 0.2, 0.1
    R = rotation((1.0, 2.0, 3.0), 0.7)
    m = RHO * a * b * c
    return (a, b, c), R, m, R @ np.diag([b * b + c * c, a * a + c * c, a * a + b * b]) @ R.T * m / 12


def test_rotated_box_off_the_origin_matches_formulas():
    t = np.array([3.0, -2.0, 5.0])
    (a, b, c), R, m, expected = _rotated_brick(t)
    props = mass_properties(*box((a, b, c), R, t), RHO)
    assert props.mass == pytest.approx(m, rel=1e-8)
    assert props.volume == pytest.approx(a * b * c, rel=1e-8)
    assert np.linalg.norm(props.centre - t) <= 1e-8 * np.linalg.norm(t)
    assert np.abs(props.inertia - expected).max() <= 1e-8 * np.abs(expected).max()

    body = RigidBody(box((a, b, c), R, t), mass=m, name="brick")
    assert body.density == pytest.approx(RHO, rel=1e-12) and body.mass == m
    assert np.abs(body.inertia - expected).max() <= 1e-8 * np.abs(expected).max()
    moments, axes = body.principal
    assert moments == pytest.approx(sorted(m / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])), rel=1e-8)
    assert np.linalg.det(axes) == pytest.approx(1.0)
    # The principal axes are the box's edges (a, b, c: ascending moments): R's columns up to sign.
    assert np.abs(np.abs(axes.T @ R) - np.eye(3)).max() < 1e-8


def test_box_far_from_the_origin_keeps_its_digits():
    """Integrals about the origin would cancel ~(1e4 / 0.3)^2 ~ 1e9 times: about 1e-7 left."""
    t = np.array([1e4, -2e4, 5e3])
    edges, R, m, expected = _rotated_brick(t)
    props = mass_properties(*box(edges, R, t), RHO)
    assert props.mass == pytest.approx(m, rel=1e-8)
    assert np.abs(props.inertia - expected).max() <= 1e-8 * np.abs(expected).max()


def cylinder_errors(ks=(8, 16, 32, 64, 128), r=0.04, h=0.1):
    """Rows ``(k, relative error of I_zz, relative error of I_xx)`` of a ``k``-faceted cylinder
    against the smooth cylinder's ``m r^2 / 2`` and ``m (3 r^2 + h^2) / 12``, m = rho pi r^2 h."""
    m = RHO * np.pi * r * r * h
    izz, ixx = m * r * r / 2, m * (3 * r * r + h * h) / 12
    rows = []
    for k in ks:
        inertia = RigidBody(cylinder(r, h, k), density=RHO).inertia
        rows.append((k, abs(inertia[2, 2] / izz - 1), abs(inertia[0, 0] / ixx - 1)))
    return np.array(rows)


def test_faceted_cylinder_converges_at_second_order():
    table = cylinder_errors()
    print("\n   k   err I_zz    err I_xx")
    for k, ezz, exx in table:
        print(f"{int(k):4d}  {ezz:.4e}  {exx:.4e}")
    for column in (1, 2):
        slope = np.polyfit(np.log(table[:, 0]), np.log(table[:, column]), 1)[0]
        assert abs(slope + 2) < 0.2, (column, slope)
    assert table[-1, 1] < 1e-3 and table[-1, 2] < 1e-3


def _tet_sum(mesh: meshing.TetMesh, rho: float):
    """Mass, centre and inertia of a tet mesh summed over its tets (a decomposition independent of the surface's)."""
    v = mesh.points[mesh.tets]
    vol = mesh.volumes()
    s = v.sum(axis=1)
    centre = (vol @ s) / 4 / vol.sum()
    r = v - centre
    rs = r.sum(axis=1)
    second = np.einsum("t,tvi,tvj->ij", vol, r, r) / 20 + np.einsum("t,ti,tj->ij", vol, rs, rs) / 20
    return rho * vol.sum(), centre, rho * (np.trace(second) * np.eye(3) - second)


def test_gmsh_sphere_converges_to_two_fifths_m_r2():
    """The inscribed polyhedron's deficits are 3/8 (h/r)^2 in mass and 5/8 (h/r)^2 in moment of
    inertia for triangles of edge h (mean depth h^2 / (8 r) below the sphere)."""
    r, rho = 0.05, 1000.0
    m = rho * 4 / 3 * np.pi * r**3
    rows = []
    for size in (r / 4, r / 8):
        mesh = meshing.mesh(meshing.Sphere(r, (0.2, -0.1, 0.3)), size, curvature=0, min_quality=0.0)
        body = RigidBody(mesh, density=rho)
        mass, centre, inertia = _tet_sum(mesh, rho)
        assert body.mass == pytest.approx(mass, rel=1e-12)
        assert np.abs(body.centre - centre).max() < 1e-12
        assert np.abs(body.inertia - inertia).max() < 1e-12 * np.abs(inertia).max()
        assert len(body.points) < mesh.n_vertices  # interior vertices are dropped
        edges = body.points[body.triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)]
        h = np.linalg.norm(edges[:, 0] - edges[:, 1], axis=1).mean()
        moments = body.principal[0]
        rows.append((h, 1 - body.mass / m, 1 - moments / (0.4 * m * r * r)))
        print(f"\nsize {size:.5f}: {len(body.triangles)} triangles, mean edge {h:.5f}, mass error "
              f"{rows[-1][1]:.3e}, moment errors {np.round(rows[-1][2], 5)}")
        assert np.abs(body.centre - (0.2, -0.1, 0.3)).max() < 0.05 * h * h / r  # depth scale h^2 / r
        assert 3 / 8 * 0.85 < rows[-1][1] / (h / r) ** 2 < 3 / 8 * 1.15
        assert np.all((5 / 8 * 0.85 < rows[-1][2] / (h / r) ** 2) & (rows[-1][2] / (h / r) ** 2 < 5 / 8 * 1.15))
    (h1, _, e1), (h2, _, e2) = rows
    slope = np.log(e1.max() / e2.max()) / np.log(h1 / h2)
    assert abs(slope - 2) < 0.2, slope


def test_translation_moves_only_the_centre_and_scaling_scales_inertia_by_s5():
    points, triangles = octahedron()
    base = mass_properties(points, triangles, RHO)
    assert np.abs(base.inertia - np.diag(np.diag(base.inertia))).max() > 1e-3 * np.abs(base.inertia).max()
    # Against the same solid cut into 8 tets at an inner point (the origin), whose centre is
    # not its vertices' mean.
    fan = meshing.TetMesh(np.concatenate([points, [[0.0, 0.0, 0.0]]]), np.insert(triangles, 0, 6, axis=1))
    mass, centre, inertia = _tet_sum(fan, RHO)
    assert np.linalg.norm(centre - points.mean(axis=0)) > 0.1 * np.linalg.norm(centre)
    assert base.mass == pytest.approx(mass, rel=1e-12)
    assert np.abs(base.centre - centre).max() < 1e-15
    assert np.abs(base.inertia - inertia).max() < 1e-12 * np.abs(inertia).max()
    shift = np.array([1.5, -0.7, 2.0])
    moved = mass_properties(points + shift, triangles, RHO)
    assert moved.mass == pytest.approx(base.mass, rel=1e-12)
    assert np.abs(moved.centre - base.centre - shift).max() < 1e-12 * np.linalg.norm(shift)
    assert np.abs(moved.inertia - base.inertia).max() < 1e-10 * np.abs(base.inertia).max()
    s = 2.5
    scaled = mass_properties(points * s, triangles, RHO)
    assert scaled.mass == pytest.approx(base.mass * s**3, rel=1e-12)
    assert np.abs(scaled.centre - s * base.centre).max() < 1e-12
    assert np.abs(scaled.inertia - s**5 * base.inertia).max() < 1e-12 * s**5 * np.abs(base.inertia).max()


def test_pose_places_the_surface_and_rotates_the_inertia(tmp_path):
    a, b, c = 0.3, 0.2, 0.1
    points, triangles = box((a, b, c), centre=(0.1, 0.2, 0.3))
    path = tmp_path / "brick.stl"
    meshio.write_points_cells(path, points, [("triangle", triangles)])
    R, x0 = rotation((0.0, 1.0, 1.0), 0.4), np.array([1.0, 0.0, -2.0])
    body = RigidBody(path, density=RHO, x0=x0, R0=R, v0=(1.0, 0.0, 0.0), omega0=(0.0, 0.0, 2.0))
    assert body.mass == pytest.approx(RHO * a * b * c, rel=1e-12)
    assert np.abs(body.centre - (0.1, 0.2, 0.3)).max() < 1e-12
    placed = mass_properties(body.surface_at(), body.triangles, RHO)
    assert np.abs(placed.centre - x0).max() < 1e-12
    assert np.abs(placed.inertia - R @ body.inertia @ R.T).max() < 1e-12 * np.abs(body.inertia).max()
    assert np.abs(body.surface_at(body.centre, np.eye(3)) - body.points).max() < 1e-15
    default = RigidBody((points, triangles), density=RHO)
    assert np.array_equal(default.x0, default.centre) and np.array_equal(default.R0, np.eye(3))
    with pytest.raises(SceneError, match="R0 is not a rotation"):
        RigidBody(path, density=RHO, R0=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(SceneError, match="v0 must be 3 finite numbers"):
        RigidBody(path, density=RHO, v0=(0.0, np.nan, 0.0))


def test_open_surface_is_refused():
    points, triangles = box((0.3, 0.2, 0.1))
    with pytest.raises(MeshError, match="not watertight: 4 open edges.*close the holes"):
        RigidBody((points, triangles[2:]), density=RHO)
    with pytest.raises(MeshError, match="not closed: 4 open edges"):
        mass_properties(points, triangles[2:], RHO)


def test_inward_and_inconsistent_orientation_are_refused():
    points, triangles = box((0.3, 0.2, 0.1))
    with pytest.raises(MeshError, match=r"oriented inward.*refused rather than flipped.*triangles\[:, ::-1\]"):
        RigidBody((points, triangles[:, ::-1]), density=RHO)
    flipped = triangles.copy()
    flipped[3] = flipped[3, ::-1]
    with pytest.raises(MeshError, match="not consistently oriented: 3 edges"):
        RigidBody((points, flipped), density=RHO)


def test_bad_mass_or_density_is_refused():
    surface = box((0.3, 0.2, 0.1))
    with pytest.raises(SceneError, match="mass must be positive and finite, got -2.0"):
        RigidBody(surface, mass=-2.0)
    with pytest.raises(SceneError, match="density must be positive and finite, got nan"):
        RigidBody(surface, density=float("nan"))
    with pytest.raises(SceneError, match="density must be positive and finite, got 0.0"):
        mass_properties(*surface, 0.0)
    with pytest.raises(SceneError, match="exactly one of density.*or mass.*got both"):
        RigidBody(surface, density=RHO, mass=1.0)
    with pytest.raises(SceneError, match="exactly one of density.*or mass.*got neither"):
        RigidBody(surface)


def test_degenerate_and_self_intersecting_surfaces_are_refused():
    flat = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.3, 0.0]])
    tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    with pytest.raises(MeshError, match="encloses no volume"):
        mass_properties(flat, tet, RHO)
    p1, t1 = box((0.3, 0.2, 0.1))
    p2, t2 = box((0.3, 0.2, 0.1), centre=(0.1, 0.05, 0.0))
    with pytest.raises(MeshError, match="intersects itself"):
        RigidBody((np.concatenate([p1, p2]), np.concatenate([t1, t2 + 8])), density=RHO)
    with pytest.raises(SceneError, match="surface must be \\(points, triangles\\)"):
        RigidBody([p1, t1], density=RHO)

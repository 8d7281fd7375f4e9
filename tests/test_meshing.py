"""Geometry builder, gmsh meshing, quality checks, examples and the `softbody mesh` command."""

from __future__ import annotations

import math
import re

import gmsh
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softbody import cli
from softbody.meshing import (
    EXAMPLES,
    Box,
    Capsule,
    Cavity,
    Cylinder,
    InBox,
    MeshError,
    OnPlane,
    Sphere,
    Tag,
    TetMesh,
    check_quality,
    enclosed_volume,
    gamma,
    mesh,
    quality_report,
    signed_volumes,
)
from softbody.meshing.examples import LEGS


def region_volume(m: TetMesh, name: str) -> float:
    return float(m.volumes()[m.region(name).tets].sum())


# ---------------------------------------------------------------------------------------
# Geometry and meshing


def test_box_minus_cylinder_matches_analytic_volume():
    m = mesh(Box(0.1) - Cylinder(0.025, 0.2, axis="z"), size=0.005)
    assert np.all(signed_volumes(m.points, m.tets) > 0)
    exact = 0.1**3 - math.pi * 0.025**2 * 0.1
    assert m.volumes().sum() == pytest.approx(exact, rel=0.02)


def test_curved_primitives_volumes():
    sphere = mesh(Sphere(0.05), size=0.006)
    assert sphere.volumes().sum() == pytest.approx(4 / 3 * math.pi * 0.05**3, rel=0.02)
    capsule = mesh(Capsule(0.02, 0.1, axis=(1, 1, 0)), size=0.005)
    exact = 4 / 3 * math.pi * 0.02**3 + math.pi * 0.02**2 * 0.06
    assert capsule.volumes().sum() == pytest.approx(exact, rel=0.02)


def test_meshing_is_deterministic():
    shape = Box((0.1, 0.04, 0.03)) - Cavity(Sphere(0.01), "c") + Tag(Box(0.02, (0.04, 0, 0)), "bone:b")
    a, b = mesh(shape, size=0.006), mesh(shape, size=0.006)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.tets, b.tets)
    np.testing.assert_array_equal(a.region("cavity:c").faces, b.region("cavity:c").faces)


def test_cavity_faces_point_into_the_cavity():
    lo, hi = np.array([0.02, -0.01, -0.004]), np.array([0.08, 0.01, 0.006])
    chamber = Box(hi - lo, (lo + hi) / 2)
    m = mesh(Box((0.1, 0.03, 0.03), (0.05, 0, 0)) - Cavity(chamber, "chamber"), size=0.005)
    reg = m.region("cavity:chamber")
    tri = m.points[reg.faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    # The cavity is convex: every wall normal points towards its centre.
    to_centre = (lo + hi) / 2 - tri.mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normal, to_centre) > 0)
    # Flux: the faces enclose the chamber's volume with the into-the-cavity sign.
    assert enclosed_volume(m.points, reg.faces) == pytest.approx(np.prod(hi - lo), rel=1e-9)
    # The walls are part of the mesh boundary, with the same orientation.
    surface = {tuple(np.roll(f, -np.argmin(f))) for f in m.surface.tolist()}
    assert all(tuple(np.roll(f, -np.argmin(f))) in surface for f in reg.faces.tolist())
    np.testing.assert_array_equal(reg.vertices, np.unique(reg.faces))
    assert m.volumes().sum() == pytest.approx(0.1 * 0.03 * 0.03 - np.prod(hi - lo), rel=1e-9)


def test_open_cavity_has_walls_but_no_lid():
    # A slot through the top face: its walls face into the slot; the opening is not a wall.
    slot = Cavity(Box((0.04, 0.01, 0.03), (0, 0, 0.02)), "slot")
    m = mesh(Box(0.06) - slot, size=0.006)
    faces = m.region("cavity:slot").faces
    assert len(faces) and np.all(m.points[faces][..., 2].max(axis=1) <= 0.03 + 1e-12)
    z = m.points[faces][..., 2]
    assert not np.any(np.all(np.isclose(z, 0.03), axis=1))  # no triangle on the top plane


def test_tags_are_conforming_subvolumes():
    bone = Box((0.04, 0.01, 0.01), (0.01, 0.0, 0.0))
    m = mesh(Box(0.06) + Tag(bone, "bone:b"), size=0.006)
    reg = m.region("bone:b")
    assert region_volume(m, "bone:b") == pytest.approx(0.04 * 0.01 * 0.01, rel=1e-9)
    np.testing.assert_array_equal(reg.vertices, np.unique(m.tets[reg.tets]))
    centres = m.points[m.tets[reg.tets]].mean(axis=1)
    assert np.all(np.abs(centres - [0.01, 0, 0]) <= [0.02, 0.005, 0.005])


def test_tag_outside_the_body_adds_material_and_mark_does_not():
    body = Box((0.04, 0.04, 0.04))
    outside = Box((0.02, 0.04, 0.04), (0.02, 0, 0))  # half in, half out
    grown = mesh(body + Tag(outside, "extra"), size=0.008)
    assert grown.volumes().sum() == pytest.approx(0.05 * 0.04 * 0.04, rel=1e-9)
    assert region_volume(grown, "extra") == pytest.approx(0.02 * 0.04 * 0.04, rel=1e-9)
    marked = mesh(body.mark("right", outside), size=0.008)
    assert marked.volumes().sum() == pytest.approx(0.04**3, rel=1e-9)
    assert region_volume(marked, "right") == pytest.approx(0.01 * 0.04 * 0.04, rel=1e-9)


def test_transforms_move_tags_and_cavities():
    # The same body built along x, then rotated to lie along z and moved up.
    along_x = (Box((0.1, 0.02, 0.02), (0.05, 0, 0)) + Tag(Box(0.01, (0.09, 0, 0)), "end")
               - Cavity(Box((0.04, 0.01, 0.01), (0.04, 0, 0)), "c"))
    m = mesh(along_x.rotate(-math.pi / 2, "y").translate((0, 0, 0.2)), size=0.005)
    tip = m.points[m.tets[m.region("end").tets]].mean(axis=(0, 1))
    np.testing.assert_allclose(tip, [0, 0, 0.29], atol=1e-3)
    wall = m.points[m.region("cavity:c").vertices]
    np.testing.assert_allclose(wall.min(axis=0), [-0.005, -0.005, 0.22], atol=1e-9)
    assert enclosed_volume(m.points, m.region("cavity:c").faces) == pytest.approx(4e-6, rel=1e-9)


def test_selections_and_local_sizes():
    shape = Box((0.1, 0.02, 0.02), (0.05, 0, 0)) + Tag(Box(0.02, (0.08, 0, 0)), "bone:end")
    coarse = mesh(shape, size=0.008, select={"fixed": OnPlane("x", 0.0), "top": InBox((0, -1, 0.01), (1, 1, 1))})
    fixed = coarse.region("fixed")
    assert np.allclose(coarse.points[fixed.vertices, 0], 0.0)
    assert len(fixed.faces) and np.all(np.isin(fixed.faces, fixed.vertices))
    assert np.allclose(coarse.points[coarse.region("top").vertices, 2], 0.01)
    fine = mesh(shape, size=0.008, sizes={"bone:end": 0.002})
    assert len(fine.region("bone:end").tets) > 10 * len(coarse.region("bone:end").tets)


@pytest.mark.parametrize("build, message", [
    (lambda: Box(0.1) + Cavity(Sphere(0.01), "c"), "must be subtracted"),
    (lambda: Box(0.1) - Tag(Sphere(0.01), "t"), "Cavity(shape, name)"),
    (lambda: Box(0.1) - Cavity(Sphere(0.01, (1, 0, 0)), "c"), "does not lie inside"),
    (lambda: Box(0.1).mark("m", Sphere(0.01, (1, 0, 0))), "has no volume inside"),
    (lambda: Box(0.1) & Sphere(0.01, (1, 0, 0)), "do not overlap"),
    (lambda: Box(0.1) - Box(0.2), "removes the whole solid"),
    (lambda: Box((0.1, -0.1, 0.1)), "positive finite length"),
    (lambda: Cylinder(0.01, 0.1, axis="w"), "unknown axis"),
    (lambda: Capsule(0.05, 0.05), "shorter than its diameter"),
])
def test_bad_geometry_is_refused_with_a_reason(build, message):
    with pytest.raises(MeshError, match=re.escape(message)):
        mesh(build(), size=0.02)


def test_bad_sizes_and_selections_are_refused():
    with pytest.raises(MeshError, match=r"unknown region 'bone:x'.*\['bone:b'\]"):
        mesh(Box(0.1) + Tag(Box(0.02), "bone:b"), size=0.02, sizes={"bone:x": 0.01})
    with pytest.raises(MeshError, match="matched no vertex"):
        mesh(Box(0.1), size=0.02, select={"fixed": OnPlane("x", 1.0)})
    with pytest.raises(MeshError, match="positive"):
        mesh(Box(0.1), size=0.0)


def test_gmsh_can_be_used_again_and_alongside_a_user_session():
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("user")
        m = mesh(Box(0.05), size=0.02)
        assert gmsh.isInitialized() and gmsh.model.getCurrent() == "user"
    finally:
        gmsh.finalize()
    assert not gmsh.isInitialized()
    assert mesh(Box(0.05), size=0.02).n_tets == m.n_tets


@settings(max_examples=15, deadline=None)
@given(
    dims=st.tuples(*[st.floats(0.02, 0.1)] * 3),
    frac=st.floats(0.2, 0.4),
    offset=st.floats(-0.3, 0.3),
    axis=st.sampled_from("xyz"),
)
def test_random_boxes_and_cylinders_never_invert(dims, frac, offset, axis):
    dims = np.array(dims)
    k = "xyz".index(axis)
    across = np.delete(dims, k)
    r = frac * across.min()
    center = np.zeros(3)
    center[(k + 1) % 3] = offset * (dims[(k + 1) % 3] / 2 - r)
    hole = Cylinder(r, 2 * dims[k], center, axis)
    size = dims.min() / 3
    for shape, exact in ((Box(dims) - hole, dims.prod() - math.pi * r * r * dims[k]),
                         (Box(dims) + Tag(Cylinder(r, dims[k], center, axis), "core"), dims.prod())):
        m = mesh(shape, size=size, min_quality=0.0)  # thin walls at coarse sizes make poor tets
        assert np.all(signed_volumes(m.points, m.tets) > 0)
        assert m.volumes().sum() == pytest.approx(exact, rel=0.1)


# ---------------------------------------------------------------------------------------
# Quality


def test_slivers_near_thin_walls_are_optimised_away():
    # A 3 mm wall at a 10 mm size: gmsh's first mesh has a tet of gamma 0.086 here.
    dims = np.array([0.08960562361066403, 0.0870202846087582, 0.03])
    shape = Box(dims) - Cylinder(0.39959215342901405 * 0.03, 2 * dims[0], axis="x")
    assert quality_report(mesh(shape, size=0.01, min_quality=0.0)).min_quality < 0.1
    assert quality_report(mesh(shape, size=0.01)).min_quality >= 0.1


def test_gamma_of_known_tets():
    regular = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    corner = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-9]], float)
    q = gamma(np.concatenate([regular, corner, flat]), np.arange(12).reshape(3, 4))
    # Corner tet: inradius 1/(3+sqrt 3), circumradius sqrt(3)/2.
    assert q == pytest.approx([1.0, 3 / (3 + math.sqrt(3)) / (math.sqrt(3) / 2), 0.0], abs=1e-6)


def test_gamma_matches_gmsh():
    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addSphere(0, 0, 0, 1.0)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.4)
        gmsh.model.mesh.generate(3)
        _, tags, nodes = gmsh.model.mesh.getElements(3)
        ref = gmsh.model.mesh.getElementQualities(tags[0], "gamma")
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
    finally:
        gmsh.finalize()
    pos = np.empty(int(node_tags.max()) + 1, int)
    pos[node_tags] = np.arange(len(node_tags))
    ours = gamma(coords.reshape(-1, 3), pos[nodes[0].reshape(-1, 4)])
    np.testing.assert_allclose(ours, ref, atol=1e-12)


def test_quality_refusal_names_count_worst_and_fix():
    # A regular-ish corner tet and a flat one (its fourth vertex just off the plane z = 0).
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0.5, 0.6, 0.01]], float)
    sliver = TetMesh(points, np.array([[0, 1, 2, 3], [2, 1, 4, 5]]))
    with pytest.raises(MeshError, match=r"1 of 2 tets .* below 0\.1; the worst is 0\.0\d+ .*--min-quality"):
        check_quality(sliver, 0.1)
    check_quality(sliver, 0.0)
    with pytest.raises(MeshError, match="min_quality=...,"):
        mesh(Box(0.05), size=0.02, min_quality=0.9)


def test_quality_report():
    r = quality_report(EXAMPLES["finger"]())
    assert r.n_inverted == 0 and r.min_quality > 0.1 and 0 < r.min_dihedral < 70.53 < r.max_dihedral
    text = str(r)
    assert f"{r.n_vertices} nodes, {r.n_tets} tets" in text and "cavity:chamber" in text
    (cavity,) = [s for s in r.regions if s.name == "cavity:chamber"]
    assert cavity.cavity_volume > 0


# ---------------------------------------------------------------------------------------
# Examples


def test_cantilever_and_finger_regions():
    c = EXAMPLES["cantilever"]()
    assert np.allclose(c.points[c.region("fixed").vertices, 0], 0)
    assert np.allclose(c.points[c.region("tip").vertices, 0], 0.32)
    assert c.volumes().sum() == pytest.approx(0.32 * 0.08 * 0.08, rel=1e-9)
    f = EXAMPLES["finger"]()
    chamber = f.region("cavity:chamber")
    assert len(chamber.faces) > 0 and enclosed_volume(f.points, chamber.faces) > 0
    # The chamber lies on one side of the neutral axis (z = 0).
    assert f.points[chamber.vertices, 2].min() > 0
    assert len(f.region("fixed").vertices) and len(f.region("tip").vertices)
    assert 0.08 <= np.ptp(f.points[:, 0]) <= 0.1


def test_quadruped_bones_muscles_and_fibres():
    q = EXAMPLES["quadruped"]()
    for leg in LEGS:
        bone, muscle = q.region(f"bone:leg_{leg}"), q.region(f"muscle:leg_{leg}")
        assert len(bone.vertices) and len(bone.tets) and len(muscle.tets)
        assert not np.intersect1d(bone.tets, muscle.tets).size
        np.testing.assert_array_equal(q.fields["fibre"][muscle.tets], np.tile([0, 0, 1.0], (len(muscle.tets), 1)))
    assert len(q.region("bone:spine").tets)
    fibre = q.fields["fibre"]
    assert fibre.shape == (q.n_tets, 3) and np.allclose(np.linalg.norm(fibre, axis=1), 1)
    assert q.points[:, 2].min() == pytest.approx(0.0, abs=1e-12)


def test_ground_examples_rest_on_or_above_the_ground():
    cat = EXAMPLES["caterpillar"]()
    assert cat.points[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    top, bottom = cat.region("muscle:top"), cat.region("muscle:bottom")
    assert len(top.tets) and len(bottom.tets) and not np.intersect1d(top.tets, bottom.tets).size
    assert len(top.tets) + len(bottom.tets) == cat.n_tets
    assert np.allclose(cat.fields["fibre"], [1.0, 0, 0])
    for name in ("cube", "ball"):
        m = EXAMPLES[name]()
        assert 0 < m.points[:, 2].min() < 0.01


# ---------------------------------------------------------------------------------------
# Command line


def test_cli_meshes_an_example_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "f.msh"
    assert cli.main(["mesh", "finger", "--size", "0.004", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nodes" in text and "cavity:chamber" in text and "meshed in" in text and out.is_file()
    before = out.read_bytes()
    assert cli.main(["mesh", "finger", "--size", "0.004", "-o", str(out)]) == 1
    assert "--force" in capsys.readouterr().err and out.read_bytes() == before
    assert cli.main(["mesh", "finger", "--size", "0.006", "-o", str(out), "--force"]) == 0
    assert out.read_bytes() != before


def test_cli_unknown_target_lists_examples(capsys):
    assert cli.main(["mesh", "fingr"]) == 1
    err = capsys.readouterr().err
    assert all(name in err for name in EXAMPLES)


def test_cli_geometry_script(tmp_path, capsys):
    script = tmp_path / "robot.py"
    script.write_text(
        "from softbody.meshing import Box, Cavity, OnPlane\n"
        "def geometry():\n"
        "    return Box((0.1, 0.02, 0.02), (0.05, 0, 0)) - Cavity(Box((0.05, 0.01, 0.01), (0.05, 0, 0)), 'c')\n"
        "def selections():\n"
        "    return {'fixed': OnPlane('x', 0.0)}\n")
    out = tmp_path / "robot.vtu"
    assert cli.main(["mesh", str(script), "--size", "0.005", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "cavity:c" in text and "fixed" in text and out.is_file()
    assert cli.main(["mesh", str(script), "-o", str(tmp_path / "x.msh")]) == 1
    assert "--size is required" in capsys.readouterr().err


def test_cli_quality_threshold(capsys):
    assert cli.main(["mesh", "cube", "--min-quality", "0.9"]) == 1
    assert "--min-quality" in capsys.readouterr().err


def test_meshing_leaves_signal_handling_as_python_set_it():
    """gmsh resets SIGPIPE and SIGINT; a later write to a closed pipe must raise, not kill."""
    import os
    import signal

    from softbody.meshing import examples

    before = signal.getsignal(signal.SIGINT)
    examples.cube()
    assert signal.getsignal(signal.SIGINT) is before
    r, w = os.pipe()
    os.close(r)
    try:
        with pytest.raises(BrokenPipeError):
            os.write(w, b"x")
    finally:
        os.close(w)

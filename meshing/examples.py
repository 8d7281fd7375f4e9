"""Parametric example robots, ready to simulate.

Each function takes the robot's dimensions (metres), an element ``size`` and
``min_quality`` (see :func:`softbody.meshing.mesh`) and returns a :class:`TetMesh` with
the regions listed in its docstring. ``EXAMPLES`` maps the names the command line accepts
(``softbody mesh finger``) to these functions.

Conventions: +x is the robot's long axis (forward for walkers and crawlers), +z is up,
the ground is the plane z = 0. Fibre fields are unit vectors per tet.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .geometry import DEFAULT_MIN_QUALITY, Box, Cavity, Cylinder, OnPlane, Sphere, Tag, mesh
from .mesh import MeshError, TetMesh


def _with_fibres(m: TetMesh, fibres: np.ndarray) -> TetMesh:
    return TetMesh(m.points, m.tets, m.surface, m.regions, {**m.fields, "fibre": fibres})


def cantilever(length: float = 0.32, width: float = 0.08, height: float = 0.08, *,
               size: float = 0.02, min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A rectangular beam along +x from x = 0 to ``length``, centred on the x axis.

    Regions: ``"fixed"`` (vertices and faces at x = 0), ``"tip"`` (at x = length).
    """
    body = Box((length, width, height), center=(length / 2, 0.0, 0.0))
    return mesh(body, size, min_quality=min_quality,
                select={"fixed": OnPlane("x", 0.0), "tip": OnPlane("x", length)})


def finger(length: float = 0.09, width: float = 0.02, height: float = 0.02, *,
           wall: float = 0.003, base: float = 0.01, gap: float = 0.001,
           size: float = 0.004, min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A pneumatic finger: a beam along +x with one chamber above its neutral axis.

    The beam spans x in [0, length], y in [-width/2, width/2], z in [-height/2, height/2].
    The box chamber spans x in [base, length - wall], leaves ``wall`` to the sides and top
    and starts ``gap`` above the neutral axis (z = 0), so pressurising it lengthens the
    top layer and the finger curls towards -z.

    Regions: ``"cavity:chamber"`` (wall triangles facing into the chamber, their vertices),
    ``"fixed"`` (the base face, x = 0), ``"tip"`` (x = length).

    Raises:
        MeshError: when the walls leave no room for the chamber.
    """
    cz_lo, cz_hi = gap, height / 2 - wall
    cx_lo, cx_hi = base, length - wall
    cw = width - 2 * wall
    if cz_hi <= cz_lo or cx_hi <= cx_lo or cw <= 0:
        raise MeshError(f"finger walls (wall={wall}, base={base}, gap={gap}) leave no room for a "
                        f"chamber in a {length} x {width} x {height} beam; thin the walls")
    body = Box((length, width, height), center=(length / 2, 0.0, 0.0))
    chamber = Box((cx_hi - cx_lo, cw, cz_hi - cz_lo), center=((cx_lo + cx_hi) / 2, 0.0, (cz_lo + cz_hi) / 2))
    return mesh(body - Cavity(chamber, "chamber"), size, min_quality=min_quality,
                select={"fixed": OnPlane("x", 0.0), "tip": OnPlane("x", length)})


#: Leg names of :func:`quadruped` and the signs (x, y) of their corners: front = +x, left = +y.
LEGS = {"fl": (1, 1), "fr": (1, -1), "hl": (-1, 1), "hr": (-1, -1)}


def quadruped(body_length: float = 0.2, body_width: float = 0.1, body_height: float = 0.05,
              leg_length: float = 0.06, leg_radius: float = 0.015, bone_width: float = 0.01, *,
              size: float = 0.01, min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A soft box body on four cylindrical legs, with embedded rigid bones.

    The body spans z in [leg_length, leg_length + body_height], centred on x = y = 0; the
    legs stand on the ground (z = 0) at the body's corners. Bones are square bars of side
    ``bone_width`` inside the body (along x, 80% of its length) and inside each leg (along
    z, from a third of the leg's height into the body), so the feet and the skin stay soft.

    Regions: ``"bone:spine"``, ``"bone:leg_<l>"`` (vertices and tets), ``"muscle:leg_<l>"``
    (the leg's tets below the body, bone excluded) for l in fl, fr, hl, hr (front/hind,
    left = +y / right = -y); ``"feet"`` (vertices on the ground).
    Fields: ``"fibre"`` (t, 3): +z (the leg axis) in the leg muscles, +x elsewhere.

    Raises:
        MeshError: when the bones do not fit inside the legs and body.
    """
    if not (bone_width < np.sqrt(2) * leg_radius and bone_width < body_height / 2):
        raise MeshError(f"bone width {bone_width} must fit inside the legs (radius {leg_radius}) "
                        f"and under half the body height ({body_height / 2})")
    z_body = leg_length + body_height / 2
    shape = Box((body_length, body_width, body_height), center=(0.0, 0.0, z_body))
    shape = shape + Tag(Box((0.8 * body_length, bone_width, bone_width), (0.0, 0.0, z_body)),
                        "bone:spine")
    inset_x, inset_y = body_length / 2 - 1.5 * leg_radius, body_width / 2 - 1.5 * leg_radius
    muscles = {}
    for name, (sx, sy) in LEGS.items():
        x, y = sx * inset_x, sy * inset_y
        # The leg reaches into the body so that the fuse has no coplanar contact.
        leg = Cylinder(leg_radius, z_body, (x, y, z_body / 2), "z")
        below_body = Cylinder(leg_radius, leg_length, (x, y, leg_length / 2), "z")
        bone_lo, bone_hi = leg_length / 3, z_body - bone_width
        bone = Box((bone_width, bone_width, bone_hi - bone_lo), (x, y, (bone_lo + bone_hi) / 2))
        shape = (shape + leg + Tag(bone, f"bone:leg_{name}")).mark(f"muscle:leg_{name}", below_body - bone)
        muscles[name] = f"muscle:leg_{name}"
    m = mesh(shape, size, min_quality=min_quality, select={"feet": OnPlane("z", 0.0)})
    fibres = np.tile([1.0, 0.0, 0.0], (m.n_tets, 1))
    for region in muscles.values():
        fibres[m.regions[region].tets] = [0.0, 0.0, 1.0]
    return _with_fibres(m, fibres)


def caterpillar(n_segments: int = 5, segment_length: float = 0.03, width: float = 0.03,
                height: float = 0.025, groove: float = 0.008, *, clearance: float = 0.0,
                size: float = 0.005, min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A segmented crawler lying on the ground: a box with transverse grooves on top.

    The body spans x in [0, n_segments * segment_length], y in [-width/2, width/2],
    z in [clearance, clearance + height]; ``n_segments - 1`` half-cylinder grooves of
    radius ``groove`` (along y) cut the top between segments, leaving a continuous
    bottom layer.

    Regions: ``"muscle:top"`` (tets above mid-height), ``"muscle:bottom"`` (below it),
    ``"belly"`` (vertices on the ground face).
    Fields: ``"fibre"`` (t, 3): +x everywhere.

    Raises:
        MeshError: when the grooves would cut deeper than mid-height or wider than a segment.
    """
    if n_segments < 1:
        raise MeshError(f"n_segments must be at least 1, got {n_segments}")
    if not (groove < height / 2 and 2 * groove < segment_length):
        raise MeshError(f"groove radius {groove} must be under half the height ({height / 2}) "
                        f"and half the segment length ({segment_length / 2})")
    length = n_segments * segment_length
    z0, zmid, z1 = clearance, clearance + height / 2, clearance + height
    shape = Box((length, width, height), center=(length / 2, 0.0, (z0 + z1) / 2))
    for i in range(1, n_segments):
        shape = shape - Cylinder(groove, 2 * width, (i * segment_length, 0.0, z1), "y")
    top = Box((length, width, height / 2), center=(length / 2, 0.0, (zmid + z1) / 2))
    bottom = Box((length, width, height / 2), center=(length / 2, 0.0, (z0 + zmid) / 2))
    shape = shape.mark("muscle:top", top).mark("muscle:bottom", bottom)
    m = mesh(shape, size, min_quality=min_quality, select={"belly": OnPlane("z", z0)})
    return _with_fibres(m, np.tile([1.0, 0.0, 0.0], (m.n_tets, 1)))


def cube(edge: float = 0.05, *, clearance: float = 0.001, size: float = 0.0125,
         min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A cube of side ``edge`` centred on the z axis, its bottom ``clearance`` above z = 0.

    Regions: ``"bottom"`` (vertices and faces of the lowest face).
    """
    body = Box(edge, center=(0.0, 0.0, clearance + edge / 2))
    return mesh(body, size, min_quality=min_quality, select={"bottom": OnPlane("z", clearance)})


def ball(radius: float = 0.05, *, clearance: float = 0.001, size: float = 0.01,
         min_quality: float = DEFAULT_MIN_QUALITY) -> TetMesh:
    """A ball of ``radius`` centred on the z axis, its lowest point ``clearance`` above z = 0.

    Regions: none.
    """
    return mesh(Sphere(radius, (0.0, 0.0, clearance + radius)), size, min_quality=min_quality)


#: name -> example function, each callable as ``f(size=..., min_quality=...)``.
EXAMPLES: dict[str, Callable[..., TetMesh]] = {
    "cantilever": cantilever,
    "finger": finger,
    "quadruped": quadruped,
    "caterpillar": caterpillar,
    "cube": cube,
    "ball": ball,
}

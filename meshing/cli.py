"""``softbody mesh``: mesh an example robot, a surface or CAD file, or a geometry script.

Usage::

    softbody mesh finger --size 0.004 -o finger.msh
    softbody mesh part.stl --size 0.005 --scale 0.001 -o part.vtu
    softbody mesh part.step --size 0.005 -o part.msh
    softbody mesh robot.py --size 0.01 -o robot.msh

A geometry script is a Python file defining ``geometry()``, which returns a
:class:`softbody.meshing.Shape`, and optionally ``selections()``, which returns a dict
of region name -> selection (e.g. ``{"fixed": OnPlane("x", 0.0)}``)::

    from softbody.meshing import Box, Cavity, OnPlane

    def geometry():
        return Box((0.1, 0.02, 0.02), center=(0.05, 0, 0)) - Cavity(
            Box((0.06, 0.01, 0.005), center=(0.05, 0, 0.004)), "chamber")

    def selections():
        return {"fixed": OnPlane("x", 0.0)}

The command prints the quality report and the meshing time and writes the mesh
(``.msh`` or ``.vtu``, see :mod:`softbody.meshing.io`); it never overwrites a file
unless given ``--force``.
"""

from __future__ import annotations

import argparse
import runpy
import sys
import time
from pathlib import Path

from .examples import EXAMPLES
from .geometry import DEFAULT_MIN_QUALITY, Shape, mesh
from .io import FORMATS, save
from .mesh import MeshError, TetMesh
from .quality import quality_report
from .surface import CAD_SUFFIXES, SURFACE_SUFFIXES, mesh_file


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``softbody mesh`` arguments to ``parser``."""
    parser.add_argument("target", help=f"an example ({', '.join(EXAMPLES)}), an "
                        f"{'/'.join(s[1:] for s in SURFACE_SUFFIXES + CAD_SUFFIXES)} file, or a "
                        "Python script defining geometry()")
    parser.add_argument("--size", type=float, default=None,
                        help="element edge length in metres (default: the example's own; "
                             "required for files and scripts)")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help=f"write the mesh here ({' or '.join(FORMATS)}); without it, only report")
    parser.add_argument("--min-quality", type=float, default=DEFAULT_MIN_QUALITY,
                        help="refuse meshes whose worst tet has gamma quality below this "
                             f"(default {DEFAULT_MIN_QUALITY}; 0 accepts any non-inverted mesh)")
    parser.add_argument("--force", action="store_true", help="overwrite the output file")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="factor on STL/OBJ coordinates (0.001 for millimetres)")
    parser.add_argument("--keep-surface", action="store_true",
                        help="STL/OBJ: use the given triangles as the boundary instead of remeshing")


def _from_script(path: Path, size: float, min_quality: float) -> TetMesh:
    namespace = runpy.run_path(str(path), run_name="__softbody_geometry__")
    geometry = namespace.get("geometry")
    if not callable(geometry):
        raise MeshError(f"{path} must define a function geometry() returning a Shape "
                        "(see `softbody mesh --help`)")
    shape = geometry()
    if not isinstance(shape, Shape):
        raise MeshError(f"geometry() in {path} returned {type(shape).__name__}, not a Shape "
                        "(Box, Cylinder, ... combined with +, -, &)")
    selections = namespace.get("selections")
    select = selections() if callable(selections) else None
    return mesh(shape, size, select=select, min_quality=min_quality)


def build(args: argparse.Namespace) -> TetMesh:
    """Make the mesh the arguments describe.

    Raises:
        MeshError: for unknown targets (listing the examples), a missing ``--size`` or any
            meshing failure.
        FileNotFoundError: for a file that does not exist.
    """
    target = args.target
    if target in EXAMPLES:
        fn = EXAMPLES[target]
        kwargs = {"min_quality": args.min_quality}
        if args.size is not None:
            kwargs["size"] = args.size
        return fn(**kwargs)
    path = Path(target)
    suffix = path.suffix.lower()
    known = SURFACE_SUFFIXES + CAD_SUFFIXES + (".py",)
    if suffix not in known:
        raise MeshError(f"unknown mesh target {target!r}: give an example name ({', '.join(EXAMPLES)}) "
                        f"or a file ending in {', '.join(known)}")
    if not path.is_file():
        raise FileNotFoundError(f"no file {path}")
    if args.size is None:
        raise MeshError(f"--size is required to mesh {path} (element edge length in metres, e.g. 0.005)")
    if suffix == ".py":
        return _from_script(path, args.size, args.min_quality)
    return mesh_file(path, args.size, scale=args.scale, remesh=not args.keep_surface,
                     min_quality=args.min_quality)


def run(args: argparse.Namespace) -> int:
    """Run ``softbody mesh``; returns the exit status (0 ok, 1 refused or failed)."""
    out = args.output
    if out is not None:
        if out.suffix.lower() not in FORMATS:
            print(f"error: cannot write {out}: use a file ending in {' or '.join(FORMATS)}", file=sys.stderr)
            return 1
        if out.exists() and not args.force:
            print(f"error: {out} exists; pass --force to overwrite it", file=sys.stderr)
            return 1
    start = time.perf_counter()
    try:
        m = build(args)
    except (MeshError, FileNotFoundError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    elapsed = time.perf_counter() - start
    print(quality_report(m))
    print(f"meshed in {elapsed:.2f} s")
    if out is not None:
        save(m, out, force=args.force)
        print(f"wrote {out}")
    return 0


__all__ = ["add_arguments", "run", "build"]

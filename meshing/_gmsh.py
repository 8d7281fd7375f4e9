"""gmsh plumbing shared by the geometry and surface importers (private).

One function opens a clean, deterministic gmsh model; the others set sizes, run the 3D
mesher and read the result back as numpy arrays. gmsh is a process-wide singleton and is
not thread-safe, so every use goes through :func:`session`, which holds a lock.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator, Sequence

import gmsh
import numpy as np

from .mesh import MeshError, signed_volumes

_LOCK = threading.Lock()

#: gmsh element type codes
_TRIANGLE, _TETRA = 2, 4


@contextmanager
def session(name: str = "softbody") -> Iterator[None]:
    """Run the body with a fresh gmsh model and deterministic options.

    Initialises gmsh when it is not running (without reading the user's gmsh config files,
    which could change options) and finalises it afterwards; when it is already running
    (a user's own session), only the model made here is removed. The 3D mesher is the
    default Delaunay one on one thread, so the same input gives the same mesh every time.
    """
    with _LOCK:
        owner = not gmsh.isInitialized()
        main = threading.current_thread() is threading.main_thread()
        # gmsh replaces the Ctrl-C handler and resets SIGPIPE to its default (which kills the
        # process on a write to a closed socket, where Python expects EPIPE); gmsh.finalize()
        # restores neither, so both are restored here.
        sigint = signal.getsignal(signal.SIGINT) if main else None
        sigpipe = signal.getsignal(signal.SIGPIPE) if main else None
        if owner:
            gmsh.initialize(
                readConfigFiles=False,
                # gmsh installs a SIGINT handler, which Python allows in the main thread only.
                interruptible=main,
            )
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.option.setNumber("General.NumThreads", 1)
            gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay (HXT is not reproducible)
            gmsh.option.setNumber("Mesh.Optimize", 1)
            gmsh.option.setString("Geometry.OCCTargetUnit", "M")  # STEP/IGES imports in metres
            previous = None if owner else gmsh.model.getCurrent()
            gmsh.model.add(name)
            try:
                yield
            finally:
                gmsh.model.remove()
                if previous:
                    gmsh.model.setCurrent(previous)
        finally:
            if owner:
                gmsh.finalize()
            if main and sigint is not None:
                signal.signal(signal.SIGINT, sigint)
            if main and sigpipe is not None:
                signal.signal(signal.SIGPIPE, sigpipe)


def gmsh_error(what: str, err: Exception, fix: str) -> MeshError:
    """A :class:`MeshError` for a failed gmsh call, quoting gmsh's own message."""
    return MeshError(f"{what} failed (gmsh: {str(err).strip() or 'no message'}); {fix}")


def set_sizes(size: float, curvature: int, local: Sequence[tuple[float, str, list[int]]] = ()) -> None:
    """Set the element size: ``size`` everywhere, ``h`` on the listed entities.

    Arguments:
        size: target edge length in metres.
        curvature: minimum number of elements per 2*pi of surface curvature (0: off).
        local: ``(h, kind, tags)`` with kind ``"VolumesList"`` or ``"SurfacesList"``.
    """
    gmsh.option.setNumber("Mesh.MeshSizeMax", max([size] + [h for h, _, _ in local]))
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", curvature)
    if not local:
        return
    fields = []
    for h, kind, tags in local:
        f = gmsh.model.mesh.field.add("Constant")
        gmsh.model.mesh.field.setNumber(f, "VIn", h)
        gmsh.model.mesh.field.setNumber(f, "VOut", size)
        gmsh.model.mesh.field.setNumbers(f, kind, tags)
        fields.append(f)
    fmin = gmsh.model.mesh.field.add("Min")
    gmsh.model.mesh.field.setNumbers(fmin, "FieldsList", fields)
    gmsh.model.mesh.field.setAsBackgroundMesh(fmin)


def generate(min_quality: float) -> None:
    """Run the 3D mesher on the current model, and rescue poor meshes.

    gmsh's default optimiser leaves most meshes above gamma 0.3 but can leave a sliver near
    thin walls. When the worst tet is below ``min_quality``, the Netgen optimiser and then
    gmsh's own run once more (deterministic; about 0.1 ms per tet); the caller checks
    the result.

    Raises:
        MeshError: when gmsh fails, with its message and what to try.
    """
    try:
        gmsh.model.mesh.generate(3)
        if min_quality > 0 and _worst_gamma() < min_quality:
            gmsh.model.mesh.optimize("Netgen")
            gmsh.model.mesh.optimize("")
    except Exception as err:  # gmsh raises bare Exception with its last error
        raise gmsh_error("tetrahedral meshing", err,
                         "try a smaller --size, or simplify thin or tangent features") from None


def _worst_gamma() -> float:
    _, tags, _ = gmsh.model.mesh.getElements(3)
    tags = [t for t in tags if len(t)]
    if not tags:
        return 1.0
    return float(np.min(gmsh.model.mesh.getElementQualities(np.concatenate(tags), "gamma")))


def extract(volumes: Sequence[int]) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], dict[int, int]]:
    """Read the tets of the given volumes back from gmsh.

    Arguments:
        volumes: volume entity tags, in the order their tets are stacked.

    Returns:
        ``(points, tets, slices, node_index)``: ``points (n, 3)`` float64 holding only the
        nodes the tets use, ordered by gmsh node tag; ``tets (t, 4)`` int32, positively
        oriented; ``slices[i]`` the tet indices of ``volumes[i]``; ``node_index`` the map
        from gmsh node tag to row of ``points``.

    Raises:
        MeshError: when the volumes hold no tetrahedra.
    """
    blocks = []
    for v in volumes:
        types, _, nodes = gmsh.model.mesh.getElements(3, v)
        blocks.append(np.concatenate([n for t, n in zip(types, nodes) if t == _TETRA] or
                                     [np.zeros(0, np.uint64)]).reshape(-1, 4))
    raw = np.concatenate(blocks) if blocks else np.zeros((0, 4), np.uint64)
    if len(raw) == 0:
        raise MeshError("gmsh produced no tetrahedra; check that the geometry is a closed solid "
                        "and that --size is smaller than its features")
    tags, coords, _ = gmsh.model.mesh.getNodes()
    used = np.unique(raw)
    order = np.argsort(tags)
    rows = order[np.searchsorted(tags, used, sorter=order)]
    points = coords.reshape(-1, 3)[rows]
    tets = np.searchsorted(used, raw).astype(np.int32)
    flip = signed_volumes(points, tets) < 0
    tets[flip] = tets[flip][:, [0, 1, 3, 2]]
    bounds = np.cumsum([0] + [len(b) for b in blocks])
    slices = [np.arange(a, b, dtype=np.int32) for a, b in zip(bounds[:-1], bounds[1:])]
    node_index = {int(t): i for i, t in enumerate(used)}
    return points, tets, slices, node_index


def triangles(surfaces: Sequence[int], node_index: dict[int, int]) -> np.ndarray:
    """The mesh triangles on the given surface entities as ``(f, 3)`` rows of ``points``."""
    out = []
    for s in surfaces:
        types, _, nodes = gmsh.model.mesh.getElements(2, s)
        for t, n in zip(types, nodes):
            if t == _TRIANGLE:
                out.append(n.reshape(-1, 3))
    if not out:
        return np.zeros((0, 3), np.int32)
    raw = np.concatenate(out)
    return np.vectorize(node_index.__getitem__, otypes=[np.int32])(raw)

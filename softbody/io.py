"""Result files: the one format the simulator writes and the viewer and renderer read.

A :class:`Result` holds a mesh (rest positions, tets, surface triangles, named regions), a
trajectory of vertex positions and whatever else a run produced: actuator activations,
per-vertex fields, an optimisation's loss history, obstacles, skeleton segments and
free-form metadata. It is saved as one ``.npz`` file (metadata and obstacles as JSON
inside it) and exported for ParaView as a ``.vtu`` series with a ``.pvd`` collection, or as
one ``.xdmf`` file.

Obstacles are plain dicts with a ``"type"`` and the keys listed in :data:`OBSTACLE_KEYS`;
extra JSON-able keys (``"name"``, ``"friction"``, ...) are kept as they are::

    {"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1]}
    {"type": "sphere", "center": [0, 0, 0.1], "radius": 0.05}
    {"type": "box", "center": [0, 0, 0.1], "half_extents": [0.1, 0.1, 0.02]}  # optional "rotation": 3x3
    {"type": "capsule", "p0": [0, 0, 0], "p1": [0, 0.2, 0], "radius": 0.02}
    {"type": "heightfield", "origin": [x0, y0], "spacing": [dx, dy], "heights": [[...], ...]}

A height field's ``heights[i][j]`` is the ground height at ``(x0 + i dx, y0 + j dy)``.

Nothing a user wrote is overwritten unless asked: every writer here takes ``force`` and
raises :class:`FileExistsError` without it.
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
import xml.etree.ElementTree as ET
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np
import scipy.sparse

from softbody.meshing.mesh import MeshError, Region, boundary_faces

#: Name of the format stored in every result file, and its version.
FORMAT = "softbody.result"
FORMAT_VERSION = 1

#: Obstacle type -> required keys and their shapes (``()`` a scalar, ``-1`` any length).
OBSTACLE_KEYS: dict[str, dict[str, tuple[int, ...]]] = {
    "plane": {"point": (3,), "normal": (3,)},
    "sphere": {"center": (3,), "radius": ()},
    "box": {"center": (3,), "half_extents": (3,)},
    "capsule": {"p0": (3,), "p1": (3,), "radius": ()},
    "heightfield": {"origin": (2,), "spacing": (2,), "heights": (-1, -1)},
}

#: Colourings computed from the trajectory; per-vertex fields may not use these names.
DERIVED_QUANTITIES = ("strain", "displacement", "activation")


class ResultError(ValueError):
    """A result is malformed or a file is not a result; the message names the defect."""


def check_overwrite(path: str | os.PathLike, force: bool = False) -> Path:
    """Refuse to replace an existing file unless asked.

    Arguments:
        path: the file about to be written.
        force: allow replacing an existing file.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = Path(path)
    if path.exists() and not force:
        raise FileExistsError(
            f"{path} already exists; pass force=True (on the command line: --force) to overwrite it"
        )
    return path


@contextlib.contextmanager
def writing_to(path: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Write a file all at once: yields a temporary path beside ``path`` to write to.

    When the block finishes, the temporary file replaces ``path``; when it raises, the
    temporary file is removed and ``path`` is left as it was. Parent folders are created.

    Arguments:
        path: the file to produce.
        force: allow replacing an existing file.

    Yields:
        A temporary path with the same suffix as ``path``, in the same folder.

    Raises:
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    path = check_overwrite(path, force)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}-{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        check_overwrite(path, force)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray) or hasattr(obj, "__array__"):
        return np.asarray(obj).tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _to_json(obj: Any, what: str) -> str:
    try:
        return json.dumps(obj, default=_json_default, allow_nan=True)
    except (TypeError, ValueError) as err:
        raise ResultError(f"{what} must be JSON-serialisable (numbers, strings, lists, dicts): {err}") from None


def _obstacle(obs: Mapping[str, Any], i: int) -> dict[str, Any]:
    if not isinstance(obs, Mapping) or "type" not in obs:
        raise ResultError(f"obstacle {i} must be a dict with a 'type' key (one of {sorted(OBSTACLE_KEYS)}), got {obs!r}")
    kind = obs["type"]
    if kind not in OBSTACLE_KEYS:
        raise ResultError(f"obstacle {i} has unknown type {kind!r}; use one of {sorted(OBSTACLE_KEYS)}")
    need = dict(OBSTACLE_KEYS[kind])
    if kind == "box" and "rotation" in obs:
        need["rotation"] = (3, 3)
    missing = sorted(set(need) - set(obs))
    if missing:
        raise ResultError(f"obstacle {i} ({kind}) lacks {missing}; a {kind} needs {sorted(OBSTACLE_KEYS[kind])}")
    out = json.loads(_to_json(dict(obs), f"obstacle {i}"))
    for key, shape in need.items():
        val = np.asarray(obs[key], dtype=np.float64)
        if val.ndim != len(shape) or any(s not in (-1, d) for s, d in zip(shape, val.shape)):
            raise ResultError(f"obstacle {i} ({kind}): {key!r} must have shape {shape}, got {val.shape}")
        if not np.all(np.isfinite(val)):
            raise ResultError(f"obstacle {i} ({kind}): {key!r} is not finite")
    if kind == "plane" and np.linalg.norm(obs["normal"]) == 0:
        raise ResultError(f"obstacle {i} (plane): the normal has zero length")
    if kind in ("sphere", "capsule") and float(obs["radius"]) <= 0:
        raise ResultError(f"obstacle {i} ({kind}): radius must be positive, got {obs['radius']}")
    if kind == "box" and np.any(np.asarray(obs["half_extents"], float) <= 0):
        raise ResultError(f"obstacle {i} (box): half_extents must be positive, got {obs['half_extents']}")
    if kind == "heightfield" and (np.any(np.asarray(obs["spacing"], float) <= 0)
                                  or min(np.shape(obs["heights"])) < 2):
        raise ResultError(f"obstacle {i} (heightfield): needs positive spacing and at least 2x2 heights")
    return out


def _region(name: str, reg: Any) -> Region:
    if isinstance(reg, Region):
        return reg
    if isinstance(reg, Mapping):
        unknown = set(reg) - {"vertices", "tets", "faces"}
        if unknown:
            raise ResultError(f"region {name!r}: unknown keys {sorted(unknown)}; use vertices, tets, faces")
        if "vertices" not in reg:
            raise ResultError(f"region {name!r} has {sorted(reg)} but no vertices; give its vertex indices")
        return Region(**reg)
    return Region(np.asarray(reg))


@dataclass(frozen=True, eq=False)
class Result:
    """A simulated (or optimised) trajectory with its mesh and everything needed to show it.

    Attributes:
        points: ``(n, 3)`` float64 rest positions.
        tets: ``(t, 4)`` int32 vertex indices.
        surface: ``(f, 3)`` int32 boundary triangles with outward normals.
        x: ``(T, n, 3)`` float64 positions per frame; frame 0 is the initial state.
        dt: seconds between frames.
        activation: ``(T, c)`` control channels per frame, or ``None``.
        channel_names: ``c`` names of the activation channels. A channel named after a
            region (``"muscle:back"``, or ``"back"`` for a region ``"<kind>:back"``) colours
            that region's vertices when colouring by activation.
        fields: name -> ``(T, n)`` per-vertex scalars per frame (e.g. ``"pressure"``).
        loss_history: ``(k,)`` loss per optimisation iteration, or ``None``.
        regions: name -> :class:`~softbody.meshing.Region` (vertex indices, and tets and
            faces where present). Plain vertex index arrays are accepted and converted.
        obstacles: plain dicts, see the module docstring and :data:`OBSTACLE_KEYS`.
        skeleton: ``(T, b, 2, 3)`` bone segments (start, end) per frame, or ``None``.
        metadata: JSON-able dict (material, options, timings, ...).

    Raises:
        ResultError: on inconsistent shapes, non-finite positions, a non-positive ``dt``,
            unknown obstacle types, reserved field names or metadata that is not JSON-able.
    """

    points: np.ndarray
    tets: np.ndarray
    surface: np.ndarray
    x: np.ndarray
    dt: float
    activation: np.ndarray | None = None
    channel_names: Sequence[str] = ()
    fields: Mapping[str, np.ndarray] = field(default_factory=dict)
    loss_history: np.ndarray | None = None
    regions: Mapping[str, Region] = field(default_factory=dict)
    obstacles: Sequence[Mapping[str, Any]] = ()
    skeleton: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        def setf(name, value):
            object.__setattr__(self, name, value)

        pts = np.asarray(self.points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ResultError(f"points must have shape (n, 3), got {pts.shape}")
        n = len(pts)
        tets = np.asarray(self.tets)
        if tets.ndim != 2 or tets.shape[1] != 4:
            raise ResultError(f"tets must have shape (t, 4), got {tets.shape}")
        surface = np.asarray(self.surface)
        if surface.ndim != 2 or surface.shape[1] != 3:
            raise ResultError(f"surface must have shape (f, 3), got {surface.shape}")
        for what, idx in (("tets", tets), ("surface", surface)):
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ResultError(f"{what} indices must lie in [0, {n}), got [{idx.min()}, {idx.max()}]")
        x = np.asarray(self.x, dtype=np.float64)
        if x.ndim == 2 and x.shape == (n, 3):
            raise ResultError("x must have shape (T, n, 3): one row of positions per frame; "
                              "for a single frame pass x[None]")
        if x.ndim != 3 or x.shape[1:] != (n, 3) or len(x) == 0:
            raise ResultError(f"x must have shape (T, {n}, 3) with T >= 1, got {x.shape}")
        bad = ~np.isfinite(x).all(axis=(1, 2))
        if bad.any():
            raise ResultError(f"positions are not finite from frame {int(np.argmax(bad))} on "
                              f"({int(bad.sum())} of {len(x)} frames); the simulation diverged: "
                              "reduce the time step or check the materials")
        T = len(x)
        dt = float(self.dt)
        if not np.isfinite(dt) or dt <= 0:
            raise ResultError(f"dt must be a positive number of seconds, got {self.dt}")

        names = tuple(str(c) for c in self.channel_names)
        act = self.activation
        if act is not None:
            act = np.asarray(act, dtype=np.float64)
            if act.ndim == 1 and len(act) == T:
                act = act[:, None]
            if act.ndim != 2 or len(act) != T:
                raise ResultError(f"activation must have shape (T={T}, c), got {act.shape}")
            if not names:
                names = tuple(f"channel {i}" for i in range(act.shape[1]))
            if len(names) != act.shape[1]:
                raise ResultError(f"{len(names)} channel_names for {act.shape[1]} activation channels")
            if len(set(names)) != len(names):
                raise ResultError(f"channel_names must be unique, got {list(names)}")
        elif names:
            raise ResultError("channel_names given without activation")

        fields = {}
        for name, val in dict(self.fields).items():
            if name in DERIVED_QUANTITIES:
                raise ResultError(f"field name {name!r} is reserved (computed from the trajectory); rename the field")
            val = np.asarray(val, dtype=np.float64)
            if val.shape != (T, n):
                raise ResultError(f"field {name!r} must have shape (T, n) = {(T, n)}, got {val.shape}")
            fields[str(name)] = val

        loss = self.loss_history
        if loss is not None:
            loss = np.asarray(loss, dtype=np.float64)
            if loss.ndim != 1:
                raise ResultError(f"loss_history must be one-dimensional (k,), got {loss.shape}")

        regions = {}
        for name, reg in dict(self.regions).items():
            reg = _region(name, reg)
            for what, idx, bound in (("vertices", reg.vertices, n), ("tets", reg.tets, len(tets)),
                                     ("faces", reg.faces, n)):
                if idx.size and (idx.min() < 0 or idx.max() >= bound):
                    raise ResultError(f"region {name!r}: {what} index out of range [0, {bound})")
            regions[str(name)] = reg

        obstacles = tuple(_obstacle(o, i) for i, o in enumerate(self.obstacles))

        skel = self.skeleton
        if skel is not None:
            skel = np.asarray(skel, dtype=np.float64)
            if skel.ndim != 4 or len(skel) != T or skel.shape[2:] != (2, 3):
                raise ResultError(f"skeleton must have shape (T={T}, b, 2, 3), got {skel.shape}")

        if not isinstance(self.metadata, Mapping):
            raise ResultError(f"metadata must be a dict, got {type(self.metadata).__name__}")
        metadata = json.loads(_to_json(dict(self.metadata), "metadata"))

        setf("points", pts)
        setf("tets", tets.astype(np.int32))
        setf("surface", surface.astype(np.int32))
        setf("x", x)
        setf("dt", dt)
        setf("activation", act)
        setf("channel_names", names)
        setf("fields", MappingProxyType(fields))
        setf("loss_history", loss)
        setf("regions", MappingProxyType(regions))
        setf("obstacles", obstacles)
        setf("skeleton", skel)
        setf("metadata", metadata)

    @classmethod
    def from_mesh(cls, mesh: Any, x: Any, dt: float, **optional: Any) -> Result:
        """A result for a trajectory simulated on ``mesh``.

        Arguments:
            mesh: a :class:`~softbody.meshing.TetMesh` (anything with ``points``, ``tets``,
                ``surface`` and ``regions``).
            x: ``(T, n, 3)`` positions per frame (numpy or JAX).
            dt: seconds between frames.
            **optional: any other :class:`Result` attribute (``activation``,
                ``channel_names``, ``fields``, ``loss_history``, ``obstacles``,
                ``skeleton``, ``metadata``; ``regions`` replaces the mesh's regions).

        Returns:
            The validated :class:`Result`.

        Raises:
            ResultError: as :class:`Result`.
            TypeError: on an unknown keyword.
        """
        optional.setdefault("regions", dict(getattr(mesh, "regions", {})))
        return cls(points=mesh.points, tets=mesh.tets, surface=mesh.surface, x=x, dt=dt, **optional)

    @property
    def n_frames(self) -> int:
        """Number of frames ``T``."""
        return len(self.x)

    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``."""
        return len(self.points)

    @property
    def times(self) -> np.ndarray:
        """``(T,)`` time of each frame in seconds, starting at 0."""
        return np.arange(self.n_frames) * self.dt

    def save(self, path: str | os.PathLike, force: bool = False) -> Path:
        """Write the result to an ``.npz`` file.

        Arguments:
            path: file name ending in ``.npz``; parent folders are created.
            force: overwrite an existing file.

        Returns:
            The path written.

        Raises:
            ValueError: ``path`` does not end in ``.npz``.
            FileExistsError: the file exists and ``force`` is false.
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"result files end in .npz, got {path.name!r}")
        arrays: dict[str, np.ndarray] = {
            "format": np.array(FORMAT), "version": np.array(FORMAT_VERSION),
            "points": self.points, "tets": self.tets, "surface": self.surface, "x": self.x,
            "dt": np.array(self.dt),
            "obstacles": np.array(_to_json(list(self.obstacles), "obstacles")),
            "metadata": np.array(_to_json(self.metadata, "metadata")),
        }
        if self.activation is not None:
            arrays["activation"] = self.activation
            arrays["channel_names"] = np.array(self.channel_names, dtype=str)
        for name, val in self.fields.items():
            arrays[f"field/{name}"] = val
        if self.loss_history is not None:
            arrays["loss_history"] = self.loss_history
        for name, reg in self.regions.items():
            for part in ("vertices", "tets", "faces"):
                arrays[f"region/{name}/{part}"] = getattr(reg, part)
        if self.skeleton is not None:
            arrays["skeleton"] = self.skeleton
        with writing_to(path, force) as tmp:
            np.savez(tmp, **arrays)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Result:
        """Read a result written by :meth:`save`.

        Arguments:
            path: an ``.npz`` result file.

        Returns:
            The :class:`Result`.

        Raises:
            FileNotFoundError: no file at ``path``.
            ResultError: the file is empty, is not an ``.npz`` archive, is truncated or
                damaged, is not a softbody result, was written by a newer version, lacks
                required entries or holds entries of the wrong kind (named in the message)
                or is inconsistent.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no result file at {path}; results are written by Result.save "
                                    "(or `softbody run ... -o result.npz`)")
        with _ResultArchive(path) as archive:
            keys = archive.keys
            if "format" not in keys or str(archive.array("format", numeric=False)) != FORMAT:
                raise ResultError(f"{path} is not a softbody result file (no {FORMAT!r} format entry); "
                                  "results are written by Result.save")
            version = archive.number("version", integer=True) if "version" in keys else 0
            if version > FORMAT_VERSION:
                raise ResultError(f"{path} has format version {version}, newer than this softbody reads "
                                  f"({FORMAT_VERSION}); upgrade softbody")
            required = ["points", "tets", "surface", "x", "dt", "obstacles", "metadata"]
            missing = [k for k in required if k not in keys]
            if "activation" in keys and "channel_names" not in keys:
                missing.append("channel_names")
            if missing:
                raise ResultError(f"{path} lacks the entries {missing}; the file is truncated or was not "
                                  "written by Result.save: write it again")
            regions: dict[str, dict[str, np.ndarray]] = {}
            fields = {}
            for key in keys:
                if key.startswith("field/"):
                    fields[key[len("field/"):]] = archive.array(key)
                elif key.startswith("region/"):
                    name, _, part = key[len("region/"):].rpartition("/")
                    regions.setdefault(name, {})[part] = archive.array(key)
            optional = {k: archive.array(k) if k in keys else None
                        for k in ("activation", "loss_history", "skeleton")}
            channel_names = archive.array("channel_names", numeric=False) if "channel_names" in keys else ()
            return cls(
                points=archive.array("points"), tets=archive.array("tets"),
                surface=archive.array("surface"), x=archive.array("x"), dt=archive.number("dt"),
                channel_names=[str(c) for c in channel_names], fields=fields, regions=regions,
                obstacles=archive.json("obstacles"), metadata=archive.json("metadata"), **optional,
            )

    def __repr__(self) -> str:
        extras = [k for k in ("activation", "loss_history", "skeleton") if getattr(self, k) is not None]
        return (f"Result({self.n_frames} frames x {self.n_vertices} vertices, dt={self.dt:g} s, "
                f"{len(self.tets)} tets, fields={sorted(self.fields)}, regions={sorted(self.regions)}, "
                f"{len(self.obstacles)} obstacles, with={extras})")


#: The first bytes of a zip archive with entries, and of an empty one.
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
#: What reading a truncated or damaged zip archive raises, from its index or from an entry
#: (damaged header flags read as an unsupported compression, NotImplementedError, or as a
#: password-protected entry, RuntimeError; damaged names as bad UTF-8).
_DAMAGED_ZIP = (zipfile.BadZipFile, EOFError, OSError, zlib.error, NotImplementedError, RuntimeError,
                UnicodeDecodeError)


def _damaged_result(path: Path, detail: str = "") -> ResultError:
    return ResultError(f"{path} is not a complete softbody result file (truncated or damaged zip "
                       f"archive{detail}): re-run the simulation to write it again")


class _ResultArchive:
    """An opened result ``.npz`` whose failures (damage, foreign entries) are :class:`ResultError`.

    Arguments:
        path: an existing file.

    Raises:
        ResultError: the file is empty, a single ``.npy`` array, not a zip archive, or a
            zip archive whose index is truncated or damaged.
    """

    def __init__(self, path: Path):
        self.path = path
        with path.open("rb") as f:
            head = f.read(6)
        made_by = "results are written by Result.save (or `softbody run ... -o result.npz`)"
        if not head:
            raise ResultError(f"{path} is empty; {made_by}")
        if head.startswith(b"\x93NUMPY"):
            raise ResultError(f"{path} holds a single NumPy array (.npy), not an .npz result archive; {made_by}")
        if not head.startswith(_ZIP_MAGIC):
            raise ResultError(f"{path} is not a NumPy .npz archive (it does not start with a zip header); {made_by}")
        try:
            self.data = np.load(path, allow_pickle=False)
        except _DAMAGED_ZIP:
            raise _damaged_result(path) from None
        self.keys = set(self.data.files)

    def __enter__(self) -> _ResultArchive:
        return self

    def __exit__(self, *exc) -> None:
        self.data.close()

    def array(self, key: str, numeric: bool = True) -> np.ndarray:
        """The entry ``key``; ``numeric``: it must hold booleans, integers or floats."""
        try:
            value = self.data[key]
        except _DAMAGED_ZIP:
            raise _damaged_result(self.path, f": entry {key!r}") from None
        except ValueError:  # Python objects (pickled) or a malformed array header
            raise self._not_plain(key, numeric) from None
        if numeric and value.dtype.kind not in "biuf":
            raise self._not_plain(key, numeric)
        return value

    def _not_plain(self, key: str, numeric: bool) -> ResultError:
        return ResultError(f"{self.path}: entry {key!r} is not a plain NumPy array of "
                           f"{'numbers' if numeric else 'numbers or text'}; the file was not written by "
                           "Result.save, or is damaged: write it again")

    def number(self, key: str, integer: bool = False) -> float | int:
        """The entry ``key`` as one float (or one integer)."""
        value = self.array(key, numeric=False)
        if value.shape != () or value.dtype.kind not in ("biu" if integer else "biuf"):
            raise ResultError(f"{self.path}: entry {key!r} must be one {'integer' if integer else 'number'}, "
                              f"got shape {value.shape} of {value.dtype}; the file was not written by Result.save")
        return int(value) if integer else float(value)

    def json(self, key: str) -> Any:
        """The entry ``key`` decoded from JSON text."""
        try:
            return json.loads(str(self.array(key, numeric=False)))
        except json.JSONDecodeError as err:
            raise ResultError(f"{self.path}: entry {key!r} is not valid JSON ({err}); the file was not "
                              "written by Result.save") from None


def as_result(result: Result | str | os.PathLike) -> Result:
    """``result`` itself, or the :class:`Result` loaded from that path."""
    return result if isinstance(result, Result) else Result.load(result)


def write_metrics(path: str | os.PathLike, metrics: Mapping[str, Any], force: bool = False) -> Path:
    """Write a metrics dict as indented JSON (e.g. ``metrics.json``).

    Arguments:
        path: the JSON file to write; parent folders are created.
        metrics: str -> JSON-able values; numpy scalars and arrays are converted.
        force: overwrite an existing file.

    Returns:
        The path written.

    Raises:
        FileExistsError: the file exists and ``force`` is false.
        ResultError: a value is not JSON-serialisable.
    """
    text = _to_json(dict(metrics), "metrics")
    with writing_to(path, force) as tmp:
        tmp.write_text(json.dumps(json.loads(text), indent=2, sort_keys=True) + "\n")
    return Path(path)


# --------------------------------------------------------------------------- derived quantities


class VertexStrain:
    """Per-vertex strain: the Frobenius norm of each tet's Green strain, volume-averaged;
    on vertices in no tet (a sheet's), that of the triangles around them, area-averaged.

    ``E = (F^T F - I) / 2`` with ``F = Ds Dm^-1`` per tet; each vertex takes the
    volume-weighted mean of ``||E||_F`` over the tets around it. A triangle's ``||E||_F``
    is that of its in-plane Green strain, ``|g0^-1 g - I|_F / 2`` with ``g0``, ``g`` the
    ``2 x 2`` metrics (edge dot products) at rest and now. Zero at rest and under rigid
    motions; vertices on neither get 0.

    Arguments:
        points: ``(n, 3)`` rest positions.
        tets: ``(t, 4)`` vertex indices.
        triangles: ``(f, 3)`` vertex indices (e.g. the mesh's surface), or ``None``.
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, triangles: np.ndarray | None = None):
        points = np.asarray(points, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64)
        dm = self._edges(points[None])[0]
        vol = np.abs(np.linalg.det(dm)) / 6.0
        self.dm_inv = np.linalg.inv(dm)
        n = len(points)
        self.average = _averaging(self.tets, vol, n)
        in_tet = np.zeros(n, bool)
        in_tet[self.tets.ravel()] = True
        tri = np.zeros((0, 3), np.int64) if triangles is None else np.asarray(triangles, np.int64).reshape(-1, 3)
        self.triangles = tri[~in_tet[tri].any(axis=1)]  # those of sheets: no vertex in a tet
        g0 = self._metric(points[None])[0]
        area = 0.5 * np.sqrt(np.maximum(np.linalg.det(g0), 0.0))
        self.g0_inv = np.linalg.inv(g0) if len(self.triangles) else g0
        self.sheet_average = _averaging(self.triangles, area, n)

    def _metric(self, x: np.ndarray) -> np.ndarray:
        p = x[:, self.triangles]  # (T, f, 3, 3)
        d = np.swapaxes(p[:, :, 1:] - p[:, :, :1], -1, -2)  # (T, f, 3, 2): edge vectors
        return np.swapaxes(d, -1, -2) @ d

    def _edges(self, x: np.ndarray) -> np.ndarray:
        p = x[:, self.tets]  # (T, t, 4, 3)
        return np.swapaxes(p[:, :, 1:] - p[:, :, :1], -1, -2)  # columns are edge vectors

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Strain of each vertex in each frame.

        Arguments:
            x: ``(T, n, 3)`` positions.

        Returns:
            ``(T, n)`` float64 strain measure (dimensionless, >= 0).
        """
        x = np.asarray(x, dtype=np.float64)
        t = len(self.tets) + len(self.triangles)
        chunk = max(1, int(4_000_000 // max(t, 1)))  # about 300 MB of temporaries at most
        out = np.empty((len(x), x.shape[1]))
        for s in range(0, len(x), chunk):
            f = self._edges(x[s:s + chunk]) @ self.dm_inv
            e = 0.5 * (np.swapaxes(f, -1, -2) @ f - np.eye(3))
            per_tet = np.sqrt((e * e).sum(axis=(-1, -2)))  # (T, t)
            out[s:s + chunk] = (self.average @ per_tet.T).T
            if len(self.triangles):
                e = 0.5 * (self.g0_inv @ self._metric(x[s:s + chunk]) - np.eye(2))
                per_triangle = np.sqrt(np.maximum(np.einsum("...ij,...ji->...", e, e), 0.0))  # tr(E^2): E is similar to a symmetric one
                out[s:s + chunk] += (self.sheet_average @ per_triangle.T).T
        return out


def _averaging(cells: np.ndarray, size: np.ndarray, n: int):
    """The ``(n, c)`` sparse matrix that averages per-cell values over the cells around each
    vertex, weighted by ``size`` ``(c,)``; rows of vertices in no cell are zero."""
    k = cells.shape[1]
    w = scipy.sparse.csr_matrix((np.repeat(size, k), (cells.ravel(), np.repeat(np.arange(len(cells)), k))),
                                shape=(n, len(cells)))
    total = np.asarray(w.sum(axis=1)).ravel()
    total[total == 0] = 1.0  # vertices in no cell get 0
    return scipy.sparse.diags(1.0 / total) @ w


def vertex_strain(result: Result) -> np.ndarray:
    """Per-vertex strain of every frame, for colouring (see :class:`VertexStrain`; a sheet's
    vertices take its triangles' in-plane strain).

    Arguments:
        result: the trajectory.

    Returns:
        ``(T, n)`` float64, zero at rest and under rigid motion.
    """
    return VertexStrain(result.points, result.tets, result.surface)(result.x)


def vertex_displacement(result: Result) -> np.ndarray:
    """Distance of every vertex from its rest position, ``(T, n)`` in metres."""
    return np.linalg.norm(result.x - result.points[None], axis=-1)


def activation_regions(result: Result) -> dict[str, str]:
    """Which region each activation channel drives, matched by name.

    A channel matches a region of the same name, or a region ``"<kind>:<channel>"``.

    Returns:
        channel name -> region name, for the channels that match one.
    """
    out = {}
    for ch in result.channel_names:
        if ch in result.regions:
            out[ch] = ch
            continue
        matches = [r for r in result.regions if r.split(":", 1)[-1] == ch]
        if len(matches) == 1:
            out[ch] = matches[0]
    return out


def vertex_activation(result: Result) -> np.ndarray:
    """Activation painted onto the vertices of the region each channel drives.

    A vertex in several driven regions takes the largest activation; other vertices 0.

    Arguments:
        result: a result with ``activation``.

    Returns:
        ``(T, n)`` float64.

    Raises:
        ResultError: there is no activation, or no channel is named after a region.
    """
    if result.activation is None:
        raise ResultError("this result has no activation to colour by")
    mapping = activation_regions(result)
    if not mapping:
        raise ResultError(f"no activation channel {list(result.channel_names)} is named after a region "
                          f"{sorted(result.regions)}; name channels after the regions they drive")
    out = np.zeros((result.n_frames, result.n_vertices))
    for i, ch in enumerate(result.channel_names):
        if ch in mapping:
            v = result.regions[mapping[ch]].vertices
            out[:, v] = np.maximum(out[:, v], result.activation[:, i:i + 1])
    return out


def color_options(result: Result) -> list[str]:
    """The names :func:`vertex_values` accepts for this result, most useful first."""
    opts = ["strain", "displacement"]
    if result.activation is not None and activation_regions(result):
        opts.append("activation")
    return opts + sorted(result.fields)


def vertex_values(result: Result, name: str) -> np.ndarray:
    """Per-vertex scalars to colour by.

    Arguments:
        result: the trajectory.
        name: ``"strain"``, ``"displacement"``, ``"activation"`` or a field name.

    Returns:
        ``(T, n)`` float64.

    Raises:
        ResultError: ``name`` is not available for this result (the message lists what is).
    """
    if name == "strain":
        return vertex_strain(result)
    if name == "displacement":
        return vertex_displacement(result)
    if name == "activation":
        return vertex_activation(result)
    if name in result.fields:
        return result.fields[name]
    raise ResultError(f"cannot colour by {name!r}; this result offers {color_options(result)}")


# --------------------------------------------------------------------------- ParaView export


_SERIES_JSON = "series.json"


def _point_data(result: Result, strain: np.ndarray, act: np.ndarray | None, k: int) -> dict[str, np.ndarray]:
    data = {"displacement": result.x[k] - result.points, "strain": strain[k]}
    if act is not None:
        data["activation"] = act[k]
    if result.activation is not None:
        for i, ch in enumerate(result.channel_names):
            data[f"activation:{ch}"] = np.full(result.n_vertices, result.activation[k, i])
    for name, val in result.fields.items():
        data[name] = val[k]
    return data


def _region_masks(result: Result) -> dict[str, np.ndarray]:
    masks = {}
    for name, reg in result.regions.items():
        m = np.zeros(result.n_vertices, np.uint8)
        m[reg.vertices] = 1
        masks[f"region:{name}"] = m
    return masks


def to_vtu_series(result: Result, directory: str | os.PathLike, force: bool = False) -> Path:
    """Write one ``.vtu`` per frame and a ``.pvd`` collection that opens in ParaView.

    Each frame holds the deformed tets with point data ``displacement`` ``(n, 3)``,
    ``strain`` ``(n,)``, every per-vertex field, ``activation`` (per vertex, where channels
    are named after regions), ``activation:<channel>`` (the channel's value at every
    vertex) and ``region:<name>`` (1 on the region's vertices). ``series.json`` beside them
    keeps ``dt``, obstacles, loss history and metadata for :func:`read_vtu_series`.

    Arguments:
        result: the trajectory.
        directory: folder for ``frame_00000.vtu`` ..., ``series.pvd`` and ``series.json``
            (created if missing).
        force: overwrite files of an earlier export.

    Returns:
        Path of ``series.pvd``.

    Raises:
        FileExistsError: one of those files exists and ``force`` is false.
    """
    import meshio

    directory = Path(directory)
    names = [f"frame_{k:05d}.vtu" for k in range(result.n_frames)]
    targets = [directory / n for n in names] + [directory / "series.pvd", directory / _SERIES_JSON]
    existing = [str(p) for p in targets if p.exists()]
    if existing and not force:
        raise FileExistsError(f"{len(existing)} files of an earlier export exist (e.g. {existing[0]}); "
                              "pass force=True (on the command line: --force) to overwrite them")
    directory.mkdir(parents=True, exist_ok=True)
    strain = vertex_strain(result)
    act = vertex_activation(result) if "activation" in color_options(result) else None
    masks = _region_masks(result)
    for k, name in enumerate(names):
        mesh = meshio.Mesh(result.x[k], [("tetra", result.tets)],
                           point_data={**_point_data(result, strain, act, k), **masks})
        with writing_to(directory / name, force=True) as tmp:
            meshio.write(tmp, mesh, file_format="vtu")
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, name in zip(result.times, names):
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0", file=name)
    ET.indent(root)
    with writing_to(directory / _SERIES_JSON, force=True) as tmp:
        tmp.write_text(_to_json({
            "dt": result.dt, "obstacles": list(result.obstacles), "metadata": result.metadata,
            "loss_history": None if result.loss_history is None else result.loss_history.tolist(),
        }, "series metadata"))
    pvd = directory / "series.pvd"
    with writing_to(pvd, force=True) as tmp:
        ET.ElementTree(root).write(tmp, xml_declaration=True, encoding="utf-8")
    return pvd


def read_vtu_series(pvd: str | os.PathLike) -> Result:
    """Read a ``.pvd`` collection of ``.vtu`` frames back into a :class:`Result`.

    Reads what :func:`to_vtu_series` writes, and other tet-mesh series whose frames share
    one topology (``displacement`` point data, when present, gives the rest positions;
    otherwise frame 0 is the rest state).

    Arguments:
        pvd: the ``.pvd`` file.

    Returns:
        The :class:`Result`: positions, per-vertex fields, activation channels (from
        ``activation:<channel>``), regions (from ``region:<name>``) and, if
        ``series.json`` is beside it, ``dt``, obstacles, loss history and metadata.

    Raises:
        FileNotFoundError: the ``.pvd`` or a frame it names is missing.
        ResultError: the ``.pvd``, ``series.json`` or a frame is truncated or damaged
            (named in the message), the collection is empty, frames have no tets or
            different topologies, or frame times are not evenly spaced.
    """
    from softbody.meshing.io import read_meshio

    pvd = Path(pvd)
    if not pvd.is_file():
        raise FileNotFoundError(f"no .pvd collection at {pvd}; write one with to_vtu_series")
    rewrite = "write the series again with to_vtu_series"
    try:
        sets = ET.parse(pvd).getroot().findall("./Collection/DataSet")
    except ET.ParseError as err:
        raise ResultError(f"{pvd} is not a complete .pvd collection (not well-formed XML: {err}): {rewrite}") from None
    if not sets:
        raise ResultError(f"{pvd} lists no DataSet entries")
    times = np.array([float(s.get("timestep", k)) for k, s in enumerate(sets)])
    frames = []
    for k, s in enumerate(sets):
        f = pvd.parent / s.get("file", "")
        if not f.is_file():
            raise FileNotFoundError(f"{pvd} names {f}, which does not exist")
        if f.suffix.lower() != ".vtu":
            raise ResultError(f"{pvd} names {f}, which is not a .vtu file; the frames of a series are .vtu files")
        try:
            frames.append(read_meshio(f, remedy=rewrite))
        except MeshError as err:
            raise ResultError(f"frame {k} of {pvd}: {err}") from None
    first = frames[0]
    tets = first.cells_dict.get("tetra")
    if tets is None:
        raise ResultError(f"{sets[0].get('file')} has no tetra cells")
    for s, m in zip(sets, frames):
        if not np.array_equal(m.cells_dict.get("tetra"), tets):
            raise ResultError(f"{s.get('file')} has a different topology from the first frame")
    x = np.stack([m.points for m in frames])
    disp = first.point_data.get("displacement")
    points = x[0] - disp if disp is not None else x[0]
    side = {}
    if (pvd.parent / _SERIES_JSON).is_file():
        try:
            side = json.loads((pvd.parent / _SERIES_JSON).read_text())
        except json.JSONDecodeError as err:
            raise ResultError(f"{pvd.parent / _SERIES_JSON} is not valid JSON ({err}): {rewrite}") from None
    if "dt" in side:
        dt = float(side["dt"])
    elif len(times) > 1:
        steps = np.diff(times)
        if not np.allclose(steps, steps[0], rtol=1e-6, atol=0) or steps[0] <= 0:
            raise ResultError(f"{pvd}: frame times are not evenly spaced; resample the series")
        dt = float(steps[0])
    else:
        dt = 1.0
    channels = [k[len("activation:"):] for k in first.point_data if k.startswith("activation:")]
    activation = (np.array([[m.point_data[f"activation:{c}"][0] for c in channels] for m in frames])
                  if channels else None)
    skip = {"displacement", "strain", "activation"}
    fields = {k: np.stack([m.point_data[k] for m in frames]) for k in first.point_data
              if k not in skip and not k.startswith(("activation:", "region:"))
              and np.ndim(first.point_data[k]) == 1}
    regions = {k[len("region:"):]: np.flatnonzero(v) for k, v in first.point_data.items()
               if k.startswith("region:")}
    return Result(points=points, tets=tets, surface=boundary_faces(tets), x=x, dt=dt,
                  activation=activation, channel_names=channels, fields=fields,
                  loss_history=side.get("loss_history"), regions=regions,
                  obstacles=side.get("obstacles", ()), metadata=side.get("metadata", {}))


def to_xdmf(result: Result, path: str | os.PathLike, force: bool = False) -> Path:
    """Write the trajectory as one self-contained XDMF time series (data inline as XML).

    The mesh is the rest configuration; each time step carries point data ``position``
    and ``displacement`` ``(n, 3)`` (apply ParaView's *Warp By Vector* to
    ``displacement``), ``strain`` and every per-vertex field. Read it back with
    ``meshio.xdmf.TimeSeriesReader``. Inline XML keeps one file and needs no HDF5; for
    long trajectories of big meshes prefer :func:`to_vtu_series`.

    Arguments:
        result: the trajectory.
        path: the ``.xdmf`` file; parent folders are created.
        force: overwrite an existing file.

    Returns:
        The path written.

    Raises:
        ValueError: ``path`` does not end in ``.xdmf``.
        FileExistsError: the file exists and ``force`` is false.
    """
    import meshio

    path = Path(path)
    if path.suffix != ".xdmf":
        raise ValueError(f"XDMF files end in .xdmf, got {path.name!r}")
    strain = vertex_strain(result)
    with writing_to(path, force) as tmp, meshio.xdmf.TimeSeriesWriter(tmp, data_format="XML") as writer:
        writer.write_points_cells(result.points, [("tetra", result.tets.astype(np.int64))])
        for k, t in enumerate(result.times):
            data = {"position": result.x[k], "displacement": result.x[k] - result.points,
                    "strain": strain[k], **{n: v[k] for n, v in result.fields.items()}}
            writer.write_data(float(t), point_data=data)
    return path

"""Save and load a :class:`TetMesh` as gmsh ``.msh`` (format 4.1) or VTK ``.vtu``.

Both formats hold one block of tetrahedra; everything else is stored as data arrays that
gmsh, ParaView and pyvista show as they are:

- ``point_data["region:<name>"]``: 1 on the region's vertices, 0 elsewhere.
- ``cell_data["region:<name>"]``: 1 on the region's tets (written when it has tets).
- ``cell_data["faces:<name>"]``: the region's triangles, as a per-tet bit mask over the
  tet's 4 faces (bit k: the face opposite local vertex k with outward orientation,
  bit k + 4: the same face reversed); written when the region has faces. Region faces
  must therefore be faces of tets, which cavity walls and boundary selections are.
- ``cell_data["field:<name>"]``: a per-tet field of shape ``(t,)`` or ``(t, k)``; a field
  of shape ``(t, a, b, ...)`` is stored flattened as ``"field@axbx...:<name>"``.
- ``cell_data["surface"]``: only when the mesh's surface is not the boundary of its tets
  (it is for every mesh :func:`softbody.meshing.mesh` makes), with the same face encoding.

A round trip keeps points, tets, regions (vertices, tets, and faces up to the order of
the rows and the rotation of each triangle) and fields. ``.msh`` stores numbers as
float64: fields come back as float64.
"""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import meshio
import numpy as np

from .mesh import MeshError, Region, TetMesh, boundary_faces

FORMATS = {".msh": "gmsh", ".vtu": "vtu"}

# meshio's reader of each format, called directly: meshio.read prints a reader's ReadError
# and exits the process.
_READERS = {"gmsh": meshio.gmsh.read, "vtu": meshio.vtu.read}
# What those readers raise on a truncated or damaged file (counts that do not match the
# numbers read, vertex numbers out of range, XML that does not parse, compressed data that
# does not inflate).
_DAMAGED = (meshio.ReadError, ValueError, IndexError, KeyError, EOFError, zlib.error)
_REWRITE = "write it again with `softbody mesh` (or softbody.meshing.save)"
# A gmsh section's opening or end marker, alone on its line.
_GMSH_MARKER = re.compile(rb"^\$(End)?(MeshFormat|PhysicalNames|Entities|PartitionedEntities|Nodes|Elements|"
                          rb"Periodic|GhostElements|Parametrizations|NodeData|ElementData|ElementNodeData|"
                          rb"InterpolationScheme|Comments)\r?$", re.MULTILINE)

# Faces of a tet opposite vertices 0..3, outward for a positively oriented tet.
_LOCAL_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _format(path: Path) -> str:
    try:
        return FORMATS[path.suffix.lower()]
    except KeyError:
        raise MeshError(f"unsupported mesh file type {path.suffix!r} ({path}); "
                        f"use one of {sorted(FORMATS)}") from None


def _open_gmsh_section(path: Path) -> str | None:
    """The section a gmsh file ends inside (its end marker missing), or ``None``."""
    with path.open("rb") as f:
        f.seek(max(0, path.stat().st_size - 64))
        last = f.read().rstrip().rsplit(b"\n", 1)[-1]
    if _GMSH_MARKER.fullmatch(last) and last.startswith(b"$End"):
        return None
    markers = list(_GMSH_MARKER.finditer(path.read_bytes()))
    if markers and markers[-1].group(1) is None:
        return markers[-1].group(2).decode()
    return None


def read_meshio(path: str | Path, remedy: str = _REWRITE) -> meshio.Mesh:
    """Read a ``.msh`` or ``.vtu`` file with meshio, refusing one that is not a complete file.

    Arguments:
        path: an existing ``.msh`` or ``.vtu`` file.
        remedy: how to get a good file again; ends each error message.

    Returns:
        The :class:`meshio.Mesh` as meshio's reader returns it.

    Raises:
        MeshError: on an unknown suffix, or a file that is empty, not of its suffix's
            format, truncated or damaged (naming the gmsh section it ends inside).
    """
    path = Path(path)
    fmt = _format(path)
    with path.open("rb") as f:
        head = f.read(64).lstrip(b"\xef\xbb\xbf \t\r\n")
    if not head:
        raise MeshError(f"{path} is empty; {remedy}")
    if fmt == "gmsh" and not head.startswith(b"$MeshFormat"):
        raise MeshError(f"{path} is not a gmsh .msh file (it does not start with $MeshFormat); {remedy}")
    if fmt == "vtu" and not head.startswith(b"<"):
        raise MeshError(f"{path} is not a VTK XML .vtu file (it does not start with an XML tag); {remedy}")
    try:
        raw, error = _READERS[fmt](str(path)), None
    except _DAMAGED as err:
        raw, error = None, err
    except MemoryError as err:  # a damaged count asks for petabytes
        raise MeshError(f"{path}: reading it asked for more memory than there is ({err}); the file is "
                        f"damaged, or too big for this machine: {remedy}") from None
    # meshio reads a gmsh file that stops after a complete section, dropping the rest.
    section = _open_gmsh_section(path) if fmt == "gmsh" else None
    if section is not None:
        raise MeshError(f"{path}: the file ends inside its ${section} section (truncated or damaged): {remedy}")
    if error is not None:
        kind = {"gmsh": "gmsh .msh", "vtu": "VTK .vtu"}[fmt]
        detail = f": {error}" if str(error) else ""
        raise MeshError(f"{path} is not a complete {kind} file (truncated or damaged{detail}): {remedy}")
    return raw


def _canonical(faces: np.ndarray) -> np.ndarray:
    """Rotate each triangle so its smallest index comes first (orientation kept)."""
    faces = np.asarray(faces).reshape(-1, 3)
    shift = np.argmin(faces, axis=1)
    idx = (shift[:, None] + np.arange(3)) % 3
    return np.take_along_axis(faces, idx, axis=1)


def _face_bits(tets: np.ndarray, faces: np.ndarray, what: str) -> np.ndarray:
    """Encode triangles as a ``(t,)`` uint8 mask over each tet's outward/reversed faces."""
    local = _canonical(tets[:, _LOCAL_FACES].reshape(-1, 3))
    table = {tuple(f): i for i, f in enumerate(local.tolist())}
    bits = np.zeros(len(tets), np.uint8)
    for f in _canonical(faces).tolist():
        i = table.get(tuple(f))
        shift = 0
        if i is None:
            i, shift = table.get((f[0], f[2], f[1])), 4
        if i is None:
            raise MeshError(f"{what} has a triangle {f} that is not a face of any tet; only tet "
                            "faces can be saved")
        bits[i // 4] |= np.uint8(1 << (i % 4 + shift))
    return bits


def _faces_from_bits(tets: np.ndarray, bits: np.ndarray) -> np.ndarray:
    bits = np.asarray(bits).astype(np.uint8)
    out = []
    for k in range(4):
        face = tets[:, _LOCAL_FACES[k]]
        out.append(face[(bits >> k) & 1 == 1])
        out.append(face[(bits >> (k + 4)) & 1 == 1][:, [0, 2, 1]])
    return np.concatenate(out).astype(np.int32)


def save(mesh: TetMesh, path: str | Path, *, force: bool = False) -> Path:
    """Write a mesh to ``.msh`` (gmsh 4.1, binary) or ``.vtu``, regions and fields included.

    Arguments:
        mesh: the mesh.
        path: the file; its suffix picks the format.
        force: overwrite an existing file.

    Returns:
        The path written.

    Raises:
        FileExistsError: if the file exists and ``force`` is false.
        MeshError: on an unknown suffix, or region faces that are not tet faces.
    """
    path = Path(path)
    fmt = _format(path)
    if path.exists() and not force:
        raise FileExistsError(f"{path} exists; pass force=True (--force on the command line) "
                              "to overwrite it")
    tets = np.asarray(mesh.tets)
    point_data: dict[str, np.ndarray] = {}
    cell_data: dict[str, list[np.ndarray]] = {}
    for name, reg in mesh.regions.items():
        mask = np.zeros(mesh.n_vertices, np.uint8)
        mask[reg.vertices] = 1
        point_data[f"region:{name}"] = mask
        if len(reg.tets):
            tmask = np.zeros(mesh.n_tets, np.uint8)
            tmask[reg.tets] = 1
            cell_data[f"region:{name}"] = [tmask]
        if len(reg.faces):
            cell_data[f"faces:{name}"] = [_face_bits(tets, reg.faces, f"region {name!r}")]
    if not _same_faces(mesh.surface, boundary_faces(tets)):
        cell_data["surface"] = [_face_bits(tets, mesh.surface, "the surface")]
    for name, val in mesh.fields.items():
        val = np.asarray(val)
        key = f"field:{name}" if val.ndim <= 2 else f"field@{'x'.join(map(str, val.shape[1:]))}:{name}"
        cell_data[key] = [val.reshape(len(val), -1) if val.ndim > 2 else val]
    out = meshio.Mesh(mesh.points, [("tetra", tets)], point_data=point_data, cell_data=cell_data)
    path.parent.mkdir(parents=True, exist_ok=True)
    out.write(path, file_format=fmt)
    return path


def _same_faces(a: np.ndarray, b: np.ndarray) -> bool:
    if len(a) != len(b):
        return False
    ca, cb = _canonical(a), _canonical(b)
    return np.array_equal(ca[np.lexsort(ca.T[::-1])], cb[np.lexsort(cb.T[::-1])])


def load(path: str | Path) -> TetMesh:
    """Read a mesh written by :func:`save` (or any ``.msh``/``.vtu`` with tetrahedra).

    Arrays not following the encoding in the module docstring are ignored; a file
    without it gives a mesh without regions or fields.

    Arguments:
        path: a ``.msh`` or ``.vtu`` file.

    Returns:
        The :class:`TetMesh`, its inverted tets (if any) reoriented.

    Raises:
        FileNotFoundError: if there is no such file.
        MeshError: on an unknown suffix, a file that is empty, not of its suffix's format,
            truncated or damaged (the message names the gmsh section it ends inside), or a
            file with no tetrahedra.
    """
    path = Path(path)
    _format(path)
    if not path.is_file():
        raise FileNotFoundError(f"no mesh file at {path}")
    raw = read_meshio(path)
    blocks = [i for i, c in enumerate(raw.cells) if c.type == "tetra"]
    if not blocks:
        raise MeshError(f"{path} has no tetrahedra (cell types: {[c.type for c in raw.cells]})")
    tets = np.concatenate([raw.cells[i].data for i in blocks]).astype(np.int64)

    def cells(key: str) -> np.ndarray:
        return np.concatenate([np.asarray(raw.cell_data[key][i]) for i in blocks])

    names = sorted({k.split(":", 1)[1] for k in list(raw.point_data) + list(raw.cell_data)
                    if k.startswith(("region:", "faces:"))})
    regions = {}
    for name in names:
        key, fkey = f"region:{name}", f"faces:{name}"
        regions[name] = Region(
            np.flatnonzero(raw.point_data[key]) if key in raw.point_data else np.zeros(0, np.int64),
            tets=np.flatnonzero(cells(key)) if key in raw.cell_data else np.zeros(0, np.int64),
            faces=_faces_from_bits(tets, cells(fkey)) if fkey in raw.cell_data else np.zeros((0, 3)),
        )
    surface = _faces_from_bits(tets, cells("surface")) if "surface" in raw.cell_data else None
    fields = {}
    for key in raw.cell_data:
        if key.startswith("field:"):
            fields[key[len("field:"):]] = cells(key)
        elif key.startswith("field@"):
            shape_txt, name = key[len("field@"):].split(":", 1)
            val = cells(key)
            fields[name] = val.reshape((len(val), *map(int, shape_txt.split("x"))))
    # Files from other tools may hold negatively oriented tets: swap two vertices (after
    # decoding faces, which are explicit vertex triples from then on).
    p = raw.points[tets]
    flip = np.linalg.det(p[:, 1:] - p[:, :1]) < 0
    tets[flip] = tets[flip][:, [0, 1, 3, 2]]
    return TetMesh(raw.points, tets, surface, regions, fields)

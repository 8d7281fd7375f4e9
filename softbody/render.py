"""Offscreen renders of a result: PNG (one frame), GIF or MP4 (the trajectory), no display.

Rendering uses pyvista (VTK) through an EGL context, so it works on headless machines with
Mesa's software rasteriser; this module selects EGL before VTK is first imported
(``VTK_DEFAULT_OPENGL_WINDOW``; set that variable yourself to choose another window type,
e.g. ``vtkOSMesaRenderWindow``). Only the surface triangles are drawn. MP4 files are
encoded with the ffmpeg shipped by imageio-ffmpeg.

Command line::

    softbody render result.npz -o out.mp4 [--fps 20] [--color-by strain] [--frame -1] [--force]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from collections.abc import Sequence
from typing import Any

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402
import pyvista as pv  # noqa: E402

from softbody.io import (  # noqa: E402
    Result,
    ResultError,
    as_result,
    check_overwrite,
    vertex_values,
    writing_to,
)

pv.OFF_SCREEN = True

#: Output suffixes :func:`render` writes.
FORMATS = (".png", ".gif", ".mp4")

_BODY = "#8db4dc"
_OBSTACLE = "#b9b4ad"
_GROUND = "#f2f1ec"
_BONE = "#b2322b"
_GROUND_STYLE = {"color": _GROUND, "show_edges": True, "edge_color": "#c9c8c0", "ambient": 0.35, "diffuse": 0.65}
_LABELS = {"strain": "Green strain", "displacement": "displacement [m]", "activation": "activation"}


def vertex_normals(x: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals of a triangle surface at its vertices.

    Arguments:
        x: ``(n, 3)`` positions.
        faces: ``(f, 3)`` triangles.

    Returns:
        ``(n, 3)`` unit normals; zero for vertices on no triangle.
    """
    tri = x[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(x)
    for k in range(3):
        for c in range(3):
            vn[:, c] += np.bincount(faces[:, k], weights=fn[:, c], minlength=len(x))
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.divide(vn, norm, out=np.zeros_like(vn), where=norm > 0)


def _rotation_to_z(direction: np.ndarray) -> np.ndarray:
    """A rotation matrix taking +z to the unit vector ``direction``."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    v = np.cross([0.0, 0.0, 1.0], d)
    c = float(d[2])
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def obstacle_mesh(obstacle: dict[str, Any], lo: np.ndarray, hi: np.ndarray) -> pv.PolyData:
    """A surface for one obstacle dict (see :mod:`softbody.io`).

    Arguments:
        obstacle: a validated obstacle dict.
        lo, hi: ``(3,)`` bounding box of the body; infinite planes are drawn as squares
            three times its size around it.

    Returns:
        A :class:`pyvista.PolyData` surface.
    """
    kind = obstacle["type"]
    if kind == "plane":
        normal = np.asarray(obstacle["normal"], float)
        normal /= np.linalg.norm(normal)
        point = np.asarray(obstacle["point"], float)
        centre = (lo + hi) / 2
        centre -= np.dot(centre - point, normal) * normal
        size = 3.0 * max(float(np.max(hi - lo)), 1e-3)
        return pv.Plane(center=centre, direction=normal, i_size=size, j_size=size,
                        i_resolution=12, j_resolution=12)
    if kind == "sphere":
        return pv.Sphere(radius=float(obstacle["radius"]), center=obstacle["center"],
                         theta_resolution=48, phi_resolution=24)
    if kind == "box":
        h = np.asarray(obstacle["half_extents"], float)
        box = pv.Box(bounds=(-h[0], h[0], -h[1], h[1], -h[2], h[2])).triangulate()
        m = np.eye(4)
        m[:3, :3] = np.asarray(obstacle.get("rotation", np.eye(3)), float)
        m[:3, 3] = obstacle["center"]
        return box.transform(m, inplace=False)
    if kind == "capsule":
        p0, p1 = np.asarray(obstacle["p0"], float), np.asarray(obstacle["p1"], float)
        axis = p1 - p0
        length = float(np.linalg.norm(axis))
        if length == 0:
            return pv.Sphere(radius=float(obstacle["radius"]), center=p0)
        return pv.Capsule(center=(p0 + p1) / 2, direction=axis, radius=float(obstacle["radius"]),
                          cylinder_length=length, resolution=32)
    if kind == "heightfield":
        heights = np.asarray(obstacle["heights"], float)
        (x0, y0), (dx, dy) = obstacle["origin"], obstacle["spacing"]
        gx, gy = np.meshgrid(x0 + dx * np.arange(heights.shape[0]), y0 + dy * np.arange(heights.shape[1]),
                             indexing="ij")
        return pv.StructuredGrid(gx, gy, heights).extract_surface()
    raise ResultError(f"cannot draw obstacle type {kind!r}")


class Scene:
    """An offscreen pyvista scene of a result whose body can be moved to any frame.

    Arguments:
        result: the trajectory.
        color_by: ``"strain"``, ``"displacement"``, ``"activation"``, a field name, or
            ``None`` for one colour.
        frames: the frame indices that will be shown (they set the camera, the colour
            range and the ground).
        window_size: ``(width, height)`` in pixels.
        cmap: matplotlib colour map name.
        clim: ``(low, high)`` colour range; by default the range over the visible
            vertices of ``frames``.
        ground: draw a floor under the body's lowest point when the result has no plane
            obstacle.

    Raises:
        ResultError: ``color_by`` is not available for this result.
    """

    def __init__(self, result: Result, color_by: str | None, frames: Sequence[int],
                 window_size: tuple[int, int], cmap: str = "viridis",
                 clim: tuple[float, float] | None = None, ground: bool = True):
        self.result = result
        self.faces = result.surface
        used = np.unique(self.faces)
        shown = result.x[list(frames)]
        lo = shown[:, used].min(axis=(0, 1))
        hi = shown[:, used].max(axis=(0, 1))
        self.values = None
        if color_by is not None:
            self.values = vertex_values(result, color_by)
            if clim is None:
                vis = self.values[list(frames)][:, used]
                clim = (float(vis.min()), float(vis.max()))
                if clim[1] - clim[0] < 1e-12:
                    clim = (clim[0], clim[0] + 1.0)

        font = max(8, int(window_size[1] / 42))
        self.plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
        self.plotter.set_background("white", top="#d5dfec")
        self.plotter.enable_anti_aliasing("msaa")

        cells = np.hstack([np.full((len(self.faces), 1), 3), self.faces]).ravel()
        self.surface = pv.PolyData(result.x[frames[0]].copy(), cells)
        mesh_args: dict[str, Any] = {"specular": 0.3, "specular_power": 20, "smooth_shading": False}
        if self.values is not None:
            self.surface.point_data["value"] = self.values[frames[0]]
            label = _LABELS.get(color_by, color_by)
            mesh_args.update(scalars="value", cmap=cmap, clim=clim,
                             scalar_bar_args={"title": label, "vertical": False, "position_x": 0.55,
                                              "position_y": 0.03, "width": 0.42, "height": 0.09,
                                              "n_labels": 4, "color": "black", "fmt": "%.3g",
                                              "title_font_size": font, "label_font_size": font})
        else:
            mesh_args["color"] = _BODY
        self.surface.point_data.active_normals = vertex_normals(self.surface.points, self.faces)
        self.plotter.add_mesh(self.surface, **mesh_args)

        self.bones = None
        if result.skeleton is not None and result.skeleton.shape[1]:
            b = result.skeleton.shape[1]
            lines = np.hstack([np.full((b, 1), 2), np.arange(2 * b).reshape(b, 2)]).ravel()
            self.bones = pv.PolyData(result.skeleton[frames[0]].reshape(-1, 3).copy(), lines=lines)
            self.plotter.add_mesh(self.bones, color=_BONE, line_width=5, render_lines_as_tubes=True)

        has_plane = False
        for obstacle in result.obstacles:
            has_plane |= obstacle["type"] == "plane"
            style = _GROUND_STYLE if obstacle["type"] == "plane" else {"color": _OBSTACLE, "specular": 0.2}
            self.plotter.add_mesh(obstacle_mesh(obstacle, lo, hi), **style)
        if ground and not has_plane:
            floor = {"type": "plane", "point": [0.0, 0.0, float(lo[2])], "normal": [0.0, 0.0, 1.0]}
            self.plotter.add_mesh(obstacle_mesh(floor, lo, hi), **_GROUND_STYLE)

        self.clock = self.plotter.add_text("", position=(12, window_size[1] - 2 * font),
                                           font_size=max(8, int(0.7 * font)), color="black")
        self._aim_camera(lo, hi)

    def _aim_camera(self, lo: np.ndarray, hi: np.ndarray) -> None:
        centre = (lo + hi) / 2
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
        cam = self.plotter.camera
        direction = np.array([0.55, -1.0, 0.6])
        direction /= np.linalg.norm(direction)
        distance = 1.1 * radius / np.sin(np.radians(cam.view_angle / 2))
        cam.focal_point = centre
        cam.position = centre + distance * direction
        cam.up = (0.0, 0.0, 1.0)
        self.plotter.reset_camera_clipping_range()

    def show(self, frame: int) -> np.ndarray:
        """Move the body to ``frame``, render, and return the image.

        Arguments:
            frame: frame index.

        Returns:
            ``(height, width, 3)`` uint8 RGB image.
        """
        x = self.result.x[frame]
        self.surface.points[:] = x
        self.surface.point_data.active_normals = vertex_normals(x, self.faces)
        if self.values is not None:
            self.surface.point_data["value"][:] = self.values[frame]
        if self.bones is not None:
            self.bones.points[:] = self.result.skeleton[frame].reshape(-1, 3)
        self.clock.SetInput(f"t = {frame * self.result.dt:.3f} s   frame {frame}")
        self.plotter.render()
        return np.asarray(self.plotter.screenshot(return_img=True))

    def close(self) -> None:
        """Release the render window."""
        self.plotter.close()


def render(result: Result | str | os.PathLike, path: str | os.PathLike, *, fps: float = 20.0,
           color_by: str | None = "strain", frame: int = -1, stride: int = 1,
           window_size: tuple[int, int] = (960, 720), cmap: str = "viridis",
           clim: tuple[float, float] | None = None, ground: bool = True, progress: bool = False,
           force: bool = False) -> Path:
    """Render a result offscreen to a PNG (one frame), an animated GIF or an MP4.

    The camera frames the body's bounding box over the rendered frames and stays fixed;
    obstacles and skeleton segments are drawn; a floor is drawn under the body's lowest
    point unless the result has a plane obstacle (``ground=False`` turns it off).

    Arguments:
        result: a :class:`~softbody.io.Result` or the path of a result ``.npz``.
        path: output file ending in ``.png``, ``.gif`` or ``.mp4``; parent folders are
            created.
        fps: frames per second of a GIF or MP4.
        color_by: ``"strain"``, ``"displacement"``, ``"activation"``, a per-vertex field
            name, or ``None`` for a uniform colour.
        frame: the frame of a PNG (negative counts from the end; default the last).
        stride: for GIF and MP4, render every ``stride``-th frame (the last is always kept).
        window_size: ``(width, height)`` in pixels; MP4 rounds both up to multiples of 16.
        cmap: matplotlib colour map name.
        clim: fixed ``(low, high)`` colour range; default the range over the rendered frames.
        ground: draw a floor when there is no plane obstacle.
        progress: show a progress bar while rendering a GIF or MP4.
        force: overwrite an existing output file.

    Returns:
        The path written.

    Raises:
        ValueError: unknown suffix, ``fps`` or ``stride`` not positive.
        IndexError: ``frame`` out of range.
        FileExistsError: ``path`` exists and ``force`` is false.
        ResultError: ``color_by`` is not available for this result.
    """
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"cannot render to {path.name!r}: the file must end in one of {FORMATS}")
    if fps <= 0 or stride < 1:
        raise ValueError(f"fps must be positive and stride at least 1, got fps={fps}, stride={stride}")
    check_overwrite(path, force)
    result = as_result(result)
    T = result.n_frames
    if path.suffix.lower() == ".png":
        if not -T <= frame < T:
            raise IndexError(f"frame {frame} is out of range for {T} frames (use 0..{T - 1} or -1 for the last)")
        frames = [frame % T]
    else:
        frames = list(range(0, T, stride))
        if frames[-1] != T - 1:
            frames.append(T - 1)
    if path.suffix.lower() == ".mp4":
        window_size = tuple(-(-int(s) // 16) * 16 for s in window_size)
    scene = Scene(result, color_by, frames, window_size, cmap, clim, ground)
    try:
        with writing_to(path, force) as tmp:
            _write(scene, frames, tmp, path.suffix.lower(), fps, window_size, progress)
    finally:
        scene.close()
    return path


def _write(scene: Scene, frames: list[int], tmp: Path, suffix: str, fps: float,
           window_size: tuple[int, int], progress: bool) -> None:
    import imageio.v3 as iio
    from rich.progress import track

    if progress and suffix != ".png":
        frames = track(frames, description=f"rendering {len(frames)} frames")

    if suffix == ".png":
        iio.imwrite(tmp, scene.show(frames[0]), extension=".png")
    elif suffix == ".gif":
        with iio.imopen(tmp, "w", extension=".gif") as gif:
            for k in frames:
                gif.write(scene.show(k), duration=1000.0 / fps, loop=0, bits=8)
    else:
        import imageio_ffmpeg

        writer = imageio_ffmpeg.write_frames(str(tmp), tuple(window_size), fps=fps, codec="libx264",
                                             pix_fmt_out="yuv420p", quality=7, macro_block_size=16)
        writer.send(None)
        try:
            for k in frames:
                writer.send(np.ascontiguousarray(scene.show(k)))
        finally:
            writer.close()


def plot_loss(history: Sequence[float] | np.ndarray, path: str | os.PathLike, *,
              title: str = "optimisation", ylabel: str = "loss", log: bool | None = None,
              force: bool = False) -> Path:
    """Plot an optimisation's loss per iteration to a PNG.

    Arguments:
        history: ``(k,)`` loss values.
        path: the ``.png`` to write; parent folders are created.
        title: figure title.
        ylabel: y-axis label.
        log: logarithmic y axis; by default when all values are positive and span more
            than a factor of 10.
        force: overwrite an existing file.

    Returns:
        The path written.

    Raises:
        ValueError: ``history`` is empty or not one-dimensional, or ``path`` is not a ``.png``.
        FileExistsError: ``path`` exists and ``force`` is false.
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    history = np.asarray(history, dtype=np.float64)
    path = Path(path)
    if history.ndim != 1 or len(history) == 0:
        raise ValueError(f"history must be a non-empty (k,) array of losses, got shape {history.shape}")
    if path.suffix.lower() != ".png":
        raise ValueError(f"plot_loss writes PNG files, got {path.name!r}")
    check_overwrite(path, force)
    finite = history[np.isfinite(history)]
    if log is None:
        log = bool(len(finite)) and finite.min() > 0 and finite.max() > 10 * finite.min()
    fig = Figure(figsize=(6, 4), dpi=120, layout="constrained")
    ax = fig.add_subplot()
    ax.plot(np.arange(len(history)), history, color="#1f5fa8", lw=1.8)
    ax.set_yscale("log" if log else "linear")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title}: {history[0]:.4g} -> {history[-1]:.4g}" if len(history) > 1 else title)
    ax.grid(True, which="both", alpha=0.3)
    with writing_to(path, force) as tmp:
        fig.savefig(tmp, format="png")
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody render``."""
    parser.add_argument("result", help="result file (.npz) written by `softbody run` or Result.save")
    parser.add_argument("-o", "--output", required=True, help="output file: .png (one frame), .gif or .mp4")
    parser.add_argument("--fps", type=float, default=20.0, help="frames per second of a GIF or MP4 (default 20)")
    parser.add_argument("--color-by", default="strain",
                        help="strain (default), displacement, activation, a per-vertex field name, or none")
    parser.add_argument("--frame", type=int, default=-1, help="frame of a PNG (default -1: the last)")
    parser.add_argument("--stride", type=int, default=1, help="render every N-th frame of a GIF or MP4")
    parser.add_argument("--size", default="960x720", help="image size WIDTHxHEIGHT (default 960x720)")
    parser.add_argument("--no-ground", action="store_true", help="do not draw a floor under the body")
    parser.add_argument("--force", action="store_true", help="overwrite the output file if it exists")


def run(args: argparse.Namespace) -> int:
    """Run ``softbody render``; returns the exit status (0 on success, 1 on a user error)."""
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"softbody render: --size must look like 960x720, got {args.size!r}", file=sys.stderr)
        return 1
    color_by = None if args.color_by.lower() == "none" else args.color_by
    try:
        out = render(args.result, args.output, fps=args.fps, color_by=color_by, frame=args.frame,
                     stride=args.stride, window_size=(width, height), ground=not args.no_ground,
                     progress=True, force=args.force)
    except (FileExistsError, FileNotFoundError, IndexError, ValueError) as err:
        print(f"softbody render: {err}", file=sys.stderr)
        return 1
    print(f"wrote {out}")
    return 0

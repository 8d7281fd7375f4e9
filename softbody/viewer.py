"""Browser viewer (viser): play back a result, or drive a live simulation with sliders.

:func:`view` serves a result: the deformed surface moves along a timeline (slider,
play/pause, speed, loop), opening on the frame that moved farthest from frame 0 and
playing in a loop ("Play" pauses), coloured by strain, displacement, activation, a
per-vertex field or region, with a legend; obstacles, skeleton segments, region geometry
(chambers, muscles) and the loss curve of an optimisation are shown. :func:`view_live`
calls a step function on a timer while sliders set the actuator controls.

viser draws a mesh in one colour, so the surface is split into colour levels: every
triangle takes the level of the mean of its vertices' values (flat shading), and one mesh
per level is updated each frame. The levels of every frame are computed once when a
colouring is first chosen, so playback only slices arrays.

The server binds to 127.0.0.1 by default (this machine only); pass ``host="0.0.0.0"`` to
serve other machines on your network. Everything the page needs is served locally, so it
works offline.

Command line::

    softbody view result.npz [--port 8080] [--host 127.0.0.1] [--color-by strain]
"""

from __future__ import annotations

import argparse
import errno
import html
import os
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import viser
import viser.transforms as vtf

from softbody.cli import port_number
from softbody.io import (
    Result,
    ResultError,
    VertexStrain,
    activation_regions,
    as_result,
    color_options,
    vertex_values,
)
from softbody.meshing.mesh import boundary_faces
from softbody.meshing.surface import open_edges

#: Colour levels of continuous colourings.
LEVELS = 32
_NEUTRAL = (141, 180, 220)
_OBSTACLE = (185, 180, 173)
_BONE = (178, 50, 43)
_PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
            (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207), (127, 127, 127)]
_LABELS = {"strain": "Green strain |E|", "displacement": "displacement [m]", "activation": "activation"}


def colormap(name: str, levels: int = LEVELS) -> np.ndarray:
    """``(levels, 3)`` uint8 colours sampled from a matplotlib colour map."""
    import matplotlib

    rgba = matplotlib.colormaps[name]((np.arange(levels) + 0.5) / levels)
    return np.round(rgba[:, :3] * 255).astype(np.uint8)


def face_levels(values: np.ndarray, faces: np.ndarray, lo: float, hi: float, levels: int = LEVELS) -> np.ndarray:
    """Colour level of each triangle from per-vertex values.

    Arguments:
        values: ``(..., n)`` per-vertex values (any leading frame axes).
        faces: ``(f, 3)`` triangles.
        lo, hi: the values mapped to the first and the last level.
        levels: number of levels.

    Returns:
        ``(..., f)`` uint8 levels in ``[0, levels)``.
    """
    values = np.asarray(values)
    flat = values.reshape(-1, values.shape[-1])
    out = np.empty((len(flat), len(faces)), np.uint8)
    chunk = max(1, 2_000_000 // max(len(faces), 1))  # bounds the (frames, f, 3) temporary
    for s in range(0, len(flat), chunk):
        mean = flat[s:s + chunk, faces].mean(axis=-1)
        scaled = (mean - lo) / max(hi - lo, 1e-300) * levels
        out[s:s + chunk] = np.clip(np.floor(scaled), 0, levels - 1)
    return out.reshape(*values.shape[:-1], len(faces))


def _legend_html(title: str, colors: np.ndarray, lo: float, hi: float) -> str:
    tiny = 1e-9 * max(abs(lo), abs(hi))
    lo, hi = (0.0 if abs(v) <= tiny else v for v in (lo, hi))
    stops = ", ".join(f"rgb({r},{g},{b})" for r, g, b in colors)
    return (f'<div style="font-size:0.85em;padding:2px 0">'
            f"<div>{html.escape(title)}</div>"
            f'<div style="height:12px;border-radius:2px;background:linear-gradient(to right, {stops})"></div>'
            f'<div style="display:flex;justify-content:space-between"><span>{lo:.4g}</span>'
            f"<span>{hi:.4g}</span></div></div>")


def _swatches_html(names: Sequence[str], colors: Sequence[Sequence[int]]) -> str:
    items = "".join(f'<div><span style="display:inline-block;width:10px;height:10px;margin-right:6px;'
                    f'background:rgb({r},{g},{b})"></span>{html.escape(n)}</div>'
                    for n, (r, g, b) in zip(names, colors))
    return f'<div style="font-size:0.85em">{items}</div>'


class Coloring:
    """One way to colour the surface: levels per frame, their colours and a legend.

    Attributes:
        levels: ``(T, f)`` uint8 level of each triangle per frame (``T`` may be 1 for a
            colouring that does not change).
        colors: ``(L, 3)`` uint8 colour of each level.
        legend: HTML legend.
    """

    def __init__(self, levels: np.ndarray, colors: np.ndarray, legend: str):
        self.levels, self.colors, self.legend = levels, np.asarray(colors, np.uint8), legend

    def at(self, frame: int) -> np.ndarray:
        """``(f,)`` levels of ``frame``."""
        return self.levels[frame if len(self.levels) > 1 else 0]

    @classmethod
    def uniform(cls, n_faces: int) -> Coloring:
        """Every triangle in one colour."""
        return cls(np.zeros((1, n_faces), np.uint8), np.array([_NEUTRAL]), "")

    @classmethod
    def scalar(cls, values: np.ndarray, faces: np.ndarray, title: str, cmap: str = "viridis") -> Coloring:
        """Continuous colouring of ``(T, n)`` values over their range on the surface."""
        used = np.unique(faces)
        lo, hi = float(values[:, used].min()), float(values[:, used].max())
        if hi - lo < 1e-12:
            hi = lo + 1.0
        colors = colormap(cmap)
        return cls(face_levels(values, faces, lo, hi), colors, _legend_html(title, colors, lo, hi))

    @classmethod
    def regions(cls, regions: dict[str, Any], faces: np.ndarray, n_vertices: int) -> Coloring:
        """Each triangle whose three vertices lie in a region takes that region's colour.

        Smaller regions are painted last, so they stay visible inside larger ones.
        """
        names = sorted(regions, key=lambda r: -len(regions[r].vertices))
        colors = [_PALETTE[i % len(_PALETTE)] for i in range(len(names))] + [_NEUTRAL]
        levels = np.full(len(faces), len(names), np.uint8)
        for i, name in enumerate(names):
            inside = np.zeros(n_vertices, bool)
            inside[regions[name].vertices] = True
            levels[inside[faces].all(axis=1)] = i
        return cls(levels[None], np.array(colors), _swatches_html(names + ["other"], colors))


class Body:
    """The deformable surface in a viser scene, one mesh per colour level.

    A closed surface is drawn from its front (outer) faces; a surface with boundary edges
    (a sheet: cloth, a shell) from both sides, so that either face of it shows.

    Arguments:
        server: the viser server.
        faces: ``(f, 3)`` surface triangles.
        name: scene node name.
    """

    def __init__(self, server: viser.ViserServer, faces: np.ndarray, name: str = "/body"):
        self.server, self.faces, self.name = server, np.asarray(faces), name
        self.side = "double" if len(self.faces) and len(open_edges(self.faces)) else "front"  # a sheet
        self.handles: dict[int, Any] = {}
        self.colors: dict[int, tuple[int, int, int]] = {}
        self.opacity: float | None = None
        self.visible = True
        self.active: set[int] = set()  # levels drawn in the last show(); others hold stale geometry

    def show(self, x: np.ndarray, levels: np.ndarray, colors: np.ndarray) -> None:
        """Draw the surface at positions ``x`` ``(n, 3)`` with triangle ``levels`` ``(f,)``."""
        x = np.asarray(x, np.float32)
        order = np.argsort(levels, kind="stable")
        bounds = np.searchsorted(levels[order], np.arange(len(colors) + 1))
        self.active = {k for k in range(len(colors)) if bounds[k + 1] > bounds[k]}
        with self.server.atomic():
            for k in sorted(set(range(len(colors))) | set(self.handles)):  # levels drawn before included
                handle = self.handles.get(k)
                tris = self.faces[order[bounds[k]:bounds[k + 1]]] if k < len(colors) else self.faces[:0]
                if len(tris) == 0:
                    if handle is not None and handle.visible:
                        handle.visible = False
                    continue
                used, local = np.unique(tris, return_inverse=True)
                verts, local = x[used], local.reshape(-1, 3).astype(np.uint32)
                color = tuple(int(c) for c in colors[k])
                if handle is None:
                    self.handles[k] = self.server.scene.add_mesh_simple(
                        f"{self.name}/level{k:02d}", verts, local, color=color, flat_shading=True,
                        side=self.side, opacity=self.opacity, visible=self.visible)
                    self.colors[k] = color
                    continue
                handle.vertices = verts
                handle.faces = local
                if self.colors[k] != color:
                    handle.color = self.colors[k] = color
                if handle.visible != self.visible:
                    handle.visible = self.visible

    def set_opacity(self, opacity: float | None) -> None:
        """Opacity of the surface (``None`` or 1: opaque)."""
        self.opacity = None if opacity is None or opacity >= 1 else float(opacity)
        for handle in self.handles.values():
            handle.opacity = self.opacity

    def set_visible(self, visible: bool) -> None:
        """Show or hide the whole surface."""
        self.visible = bool(visible)
        for k, handle in self.handles.items():
            handle.visible = self.visible and k in self.active


def _nice(step: float) -> float:
    """A 1, 2 or 5 times a power of ten close to ``step``."""
    power = 10.0 ** np.floor(np.log10(step))
    return float(min((1, 2, 5, 10), key=lambda m: abs(m * power - step)) * power)


def _frame_camera(server: viser.ViserServer, lo: np.ndarray, hi: np.ndarray) -> None:
    centre = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-3)
    fov = np.radians(45.0)
    direction = np.array([0.55, -1.0, 0.6])
    direction /= np.linalg.norm(direction)
    server.scene.set_up_direction("+z")
    server.initial_camera.fov = fov
    server.initial_camera.look_at = centre
    server.initial_camera.position = centre + 1.15 * radius / np.sin(fov / 2) * direction
    server.initial_camera.up = (0.0, 0.0, 1.0)
    server.initial_camera.near = radius / 100
    server.initial_camera.far = radius * 1000


def start_frame(result: Result) -> int:
    """The frame a result opens on: the one whose surface moved farthest from frame 0.

    Frame 0 is usually the rest shape (uniform colours, nothing moved), so opening there
    looks as if nothing happened; the most displaced frame shows the motion at once.

    Arguments:
        result: the result.

    Returns:
        The index of the frame with the largest vertex displacement from frame 0 over the
        surface vertices (0 for a single frame or a body that never moves).
    """
    used = np.unique(result.surface)
    rest = result.x[0, used]
    moved = [float(np.linalg.norm(x[used] - rest, axis=1).max()) for x in result.x]  # one frame at a time
    return int(np.argmax(moved))


def _rotation_to(direction: Sequence[float]) -> np.ndarray:
    """wxyz quaternion of a rotation taking +z to ``direction``."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s, c = np.linalg.norm(axis), d[2]
    if s < 1e-12:
        return np.array([1.0, 0, 0, 0]) if c > 0 else np.array([0.0, 1, 0, 0])
    return vtf.SO3.exp(axis / s * np.arctan2(s, c)).wxyz


def _add_obstacles(server: viser.ViserServer, obstacles: Sequence[dict], lo: np.ndarray, hi: np.ndarray) -> None:
    """Draw obstacles; a grid on the floor under the body when there is no plane."""
    extent = max(float(np.max(hi - lo)), 1e-3)
    cell = _nice(extent / 5)
    size = 20 * cell
    planes = [o for o in obstacles if o["type"] == "plane"] or [
        {"type": "plane", "point": [0.0, 0.0, float(lo[2])], "normal": [0.0, 0.0, 1.0]}]
    for i, o in enumerate(planes):
        normal = np.asarray(o["normal"], float) / np.linalg.norm(o["normal"])
        centre = (lo + hi) / 2
        centre = centre - np.dot(centre - np.asarray(o["point"], float), normal) * normal
        server.scene.add_grid(f"/obstacles/plane{i}", size, size, cell_size=cell, section_size=5 * cell,
                              plane_color=(238, 236, 230), plane_opacity=1.0, shadow_opacity=0.2,
                              wxyz=_rotation_to(normal), position=centre - 1e-4 * extent * normal)
    for i, o in enumerate(obstacles):
        name = f"/obstacles/{o['type']}{i}"
        if o["type"] == "sphere":
            server.scene.add_icosphere(name, float(o["radius"]), _OBSTACLE, position=o["center"])
        elif o["type"] == "box":
            rot = vtf.SO3.from_matrix(np.asarray(o.get("rotation", np.eye(3)), float))
            server.scene.add_box(name, _OBSTACLE, 2 * np.asarray(o["half_extents"], float),
                                 wxyz=rot.wxyz, position=o["center"])
        elif o["type"] == "capsule":
            p0, p1, r = np.asarray(o["p0"], float), np.asarray(o["p1"], float), float(o["radius"])
            length = float(np.linalg.norm(p1 - p0))
            if length > 0:
                server.scene.add_cylinder(f"{name}/body", r, length, _OBSTACLE,
                                          wxyz=_rotation_to(p1 - p0), position=(p0 + p1) / 2)
            server.scene.add_icosphere(f"{name}/end0", r, _OBSTACLE, position=p0)
            server.scene.add_icosphere(f"{name}/end1", r, _OBSTACLE, position=p1)
        elif o["type"] == "heightfield":
            h = np.asarray(o["heights"], float)
            (x0, y0), (dx, dy) = o["origin"], o["spacing"]
            gx, gy = np.meshgrid(x0 + dx * np.arange(h.shape[0]), y0 + dy * np.arange(h.shape[1]), indexing="ij")
            idx = np.arange(h.size).reshape(h.shape)
            a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
            tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
            server.scene.add_mesh_simple(name, np.stack([gx, gy, h], -1).reshape(-1, 3), tris,
                                         color=_OBSTACLE, side="double")


#: How many ports, from the one asked for, a viewer tries when it is taken.
PORT_TRIES = 1000


def free_port(host: str, port: int) -> int:
    """The port a viewer asked for ``port`` on ``host`` gets: ``port`` when it is free, else
    the next free one (``0`` stays ``0``: the system picks a free port when serving).

    The server binds in a thread of its own, where a port out of range or an address that
    is not this machine's fails unseen and leaves the caller waiting; checking here
    (binding and releasing a socket per address, as the server will) turns those into
    errors before it starts.

    Arguments:
        host: interface to bind (``"127.0.0.1"``, ``"0.0.0.0"``, a host name, ...).
        port: TCP port asked for, 0 to 65535.

    Returns:
        The port to serve on.

    Raises:
        ValueError: ``port`` is not an integer from 0 to 65535, ``host`` is not an address
            of this machine, or ``port`` and the next ones (up to :data:`PORT_TRIES`) are
            all taken; the message says what to pass instead.
    """
    if isinstance(port, bool) or not isinstance(port, (int, np.integer)) or not 0 <= port <= 65535:
        raise ValueError(f"port {port!r} is not a TCP port: give an integer from 0 to 65535 (0: any free port)")
    port = int(port)
    try:
        infos = set(socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE))
    except (socket.gaierror, UnicodeError) as err:
        raise ValueError(f"cannot serve on host {host!r}: {getattr(err, 'strerror', None) or err}; use 127.0.0.1 "
                         "(this machine only) or 0.0.0.0 (every network interface)") from None

    def bind(candidate: int) -> None:
        for family, kind, proto, _, address in infos:
            try:
                sock = socket.socket(family, kind, proto)
            except OSError:
                continue  # a family this machine lacks; the server skips it too
            with sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                sock.bind((address[0], candidate, *address[2:]))
                sock.listen(1)

    last = min(port + PORT_TRIES, 65536) if port else 1
    for candidate in range(port, last):
        try:
            bind(candidate)
            return candidate
        except OSError as err:
            if err.errno == errno.EACCES:
                raise ValueError(f"cannot serve on port {candidate}: {err.strerror}; ports below 1024 need "
                                 "administrator rights: use a port from 1024 up (0: any free port)") from None
            if err.errno != errno.EADDRINUSE:
                raise ValueError(f"cannot serve on {host}:{candidate}: {err.strerror or err}; use host 127.0.0.1 "
                                 "(this machine only) or 0.0.0.0 (every network interface)") from None
    raise ValueError(f"ports {port} to {last - 1} on {host} are all in use; pass port 0 (any free port) or another port")


class _ServerViewer:
    """What playback and live viewers share: the server, its URL, the surface and colours."""

    def __init__(self, host: str, port: int, faces: np.ndarray):
        asked, port = port, free_port(host, port)
        if port != asked:
            print(f"softbody viewer: port {asked} is in use; serving on port {port}", file=sys.stderr, flush=True)
        self.server = viser.ViserServer(host=host, port=port, label="softbody", verbose=False)
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        # Docked, the panel takes its own column and the canvas shrinks to the space left of
        # it, so the initial camera frames the body in the visible part of the page (a
        # floating panel covers the canvas's right quarter, where a wide body reaches).
        self.server.gui.main_panel.dock_right()
        self.host = host
        self.port = self.server.get_port()
        shown = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
        self.url = f"http://{shown}:{self.port}"
        self.body = Body(self.server, faces)
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _start_thread(self, target: Callable[[], None]) -> None:
        self._thread = threading.Thread(target=target, name="softbody-viewer", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the timer and the server (idempotent)."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5)
        self.server.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def block(self) -> None:
        """Serve until Ctrl-C, then stop."""
        print(f"softbody viewer: open {self.url} in a browser (Ctrl-C to stop)", flush=True)
        try:
            while not self._stop.is_set():
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()


class PlaybackViewer(_ServerViewer):
    """A result served in the browser. Made by :func:`view`.

    It opens on :func:`start_frame` (the most displaced frame) and plays in a loop at real
    time; ``playing = False`` or the page's "Play" box pauses.

    Attributes:
        server: the :class:`viser.ViserServer`.
        url: address to open in a browser.
        result: the :class:`~softbody.io.Result` shown.
        gui: name -> viser GUI handle (``"frame"``, ``"play"``, ``"speed"``, ``"loop"``,
            ``"color_by"``, ``"opacity"``, ``"region:<name>"``, ...).
    """

    def __init__(self, result: Result, host: str, port: int, color_by: str | None):
        options = color_options(result) + (["regions"] if result.regions else []) + ["none"]
        if color_by is None:
            color_by = "none"
        if color_by not in options:
            raise ResultError(f"cannot colour by {color_by!r}; this result offers {options}")
        super().__init__(host, port, result.surface)
        self.result = result
        self._colorings: dict[str, Coloring] = {}
        self._overlays: dict[str, tuple[Any, np.ndarray]] = {}
        self.gui: dict[str, Any] = {}
        used = np.unique(result.surface)
        lo, hi = result.x[:, used].min(axis=(0, 1)), result.x[:, used].max(axis=(0, 1))
        _frame_camera(self.server, lo, hi)
        _add_obstacles(self.server, result.obstacles, lo, hi)
        self.bones = None
        if result.skeleton is not None and result.skeleton.shape[1]:
            self.bones = self.server.scene.add_line_segments(
                "/skeleton", result.skeleton[0].astype(np.float32), _BONE, thickness=0.012 * float(np.max(hi - lo)))
        self._build_gui(options, color_by, start_frame(result))
        self._mode = color_by
        self._show(self.frame)
        self._start_thread(self._play_loop)

    # ----------------------------------------------------------------- GUI

    def _build_gui(self, options: list[str], color_by: str, frame: int) -> None:
        r, gui = self.result, self.server.gui
        gui.add_markdown(f"**softbody** result: {r.n_vertices} vertices, {len(r.tets)} tets, "
                         f"{r.n_frames} frames of {r.dt:g} s")
        with gui.add_folder("Playback"):
            self.gui["clock"] = gui.add_markdown("")
            self.gui["frame"] = gui.add_slider("Frame", min=0, max=max(r.n_frames - 1, 1), step=1,
                                               initial_value=frame, disabled=r.n_frames == 1)
            self.gui["play"] = gui.add_checkbox("Play", initial_value=r.n_frames > 1, disabled=r.n_frames == 1)
            self.gui["speed"] = gui.add_slider("Speed (x real time)", min=0.05, max=4.0, step=0.05, initial_value=1.0)
            self.gui["loop"] = gui.add_checkbox("Loop", initial_value=True)
        with gui.add_folder("Colour"):
            self.gui["color_by"] = gui.add_dropdown("Colour by", options, initial_value=color_by)
            self.gui["legend"] = gui.add_html("")
            self.gui["opacity"] = gui.add_slider("Body opacity", min=0.1, max=1.0, step=0.05, initial_value=1.0)
        self._overlay_folder()
        if r.activation is not None:
            with gui.add_folder("Activation"):
                self.gui["activation"] = gui.add_markdown("")
                series = [{"label": "t [s]"}] + [
                    {"label": ch, "stroke": "rgb({},{},{})".format(*_PALETTE[i % len(_PALETTE)]), "width": 2}
                    for i, ch in enumerate(r.channel_names)]
                gui.add_uplot((r.times, *r.activation.T), tuple(series), title="activation",
                              scales={"x": {"time": False}}, aspect=1.6)
        if r.loss_history is not None and len(r.loss_history):
            loss = r.loss_history
            log = bool(np.all(loss[np.isfinite(loss)] > 0))
            with gui.add_folder("Optimisation"):
                gui.add_markdown(f"loss {loss[0]:.4g} -> {loss[-1]:.4g} in {len(loss)} iterations")
                gui.add_uplot((np.arange(len(loss), dtype=float), loss),
                              ({"label": "iteration"}, {"label": "loss", "stroke": "#1f5fa8", "width": 2}),
                              title="loss", aspect=1.6,
                              scales={"x": {"time": False}, **({"y": {"distr": 3, "log": 10}} if log else {})})

        self.gui["frame"].on_update(lambda _: self._show(int(self.gui["frame"].value)))
        self.gui["color_by"].on_update(lambda _: self._recolor(self.gui["color_by"].value))
        self.gui["opacity"].on_update(lambda _: self.body.set_opacity(self.gui["opacity"].value))

    def _overlay_folder(self) -> None:
        """Checkboxes that draw each region's own surface (chambers, muscles, bones)."""
        r = self.result
        drawable = {}
        for name, reg in r.regions.items():
            tris = reg.faces if len(reg.faces) else (boundary_faces(r.tets[reg.tets]) if len(reg.tets) else None)
            if tris is not None and len(tris):
                drawable[name] = tris
        if not drawable:
            return
        with self.server.gui.add_folder("Regions"):
            self.server.gui.add_markdown("Draw a region's own surface; lower the body opacity to see inside.")
            for i, (name, tris) in enumerate(sorted(drawable.items())):
                used, local = np.unique(tris, return_inverse=True)
                handle = self.server.scene.add_mesh_simple(
                    f"/regions/{i}", r.x[0, used].astype(np.float32), local.reshape(-1, 3).astype(np.uint32),
                    color=_PALETTE[i % len(_PALETTE)], opacity=0.75, side="double", visible=False)
                self._overlays[name] = (handle, used)
                box = self.server.gui.add_checkbox(name, initial_value=False)
                box.on_update(lambda _, name=name, box=box: self._toggle_overlay(name, box.value))
                self.gui[f"region:{name}"] = box

    def _toggle_overlay(self, name: str, on: bool) -> None:
        with self._lock:
            handle, used = self._overlays[name]
            handle.vertices = self.result.x[self.frame, used].astype(np.float32)
            handle.visible = on

    # ----------------------------------------------------------------- state

    @property
    def frame(self) -> int:
        """The frame shown; setting it moves the timeline (and updates every browser)."""
        return int(self.gui["frame"].value)

    @frame.setter
    def frame(self, k: int) -> None:
        T = self.result.n_frames
        if not -T <= k < T:
            raise IndexError(f"frame {k} is out of range for {T} frames")
        self.gui["frame"].value = k % T

    @property
    def playing(self) -> bool:
        """Whether the timeline plays (the "Play" box); a result opens playing when it has
        more than one frame. Setting it starts or pauses playback in every open page; once
        it is set to ``False`` the frame no longer changes by itself."""
        return bool(self.gui["play"].value)

    @playing.setter
    def playing(self, on: bool) -> None:
        with self._lock:  # the play loop advances under this lock: no step lands after a pause
            self.gui["play"].value = bool(on) and self.result.n_frames > 1

    @property
    def color_by(self) -> str:
        """The colouring shown; one of the options in the GUI's "Colour by" list."""
        return self._mode

    @color_by.setter
    def color_by(self, mode: str) -> None:
        options = list(self.gui["color_by"].options)
        if mode not in options:
            raise ResultError(f"cannot colour by {mode!r}; this result offers {options}")
        self.gui["color_by"].value = mode

    def coloring(self, mode: str) -> Coloring:
        """The colouring ``mode``, computed for every frame the first time it is asked for."""
        if mode not in self._colorings:
            r = self.result
            if mode == "none":
                self._colorings[mode] = Coloring.uniform(len(r.surface))
            elif mode == "regions":
                self._colorings[mode] = Coloring.regions(dict(r.regions), r.surface, r.n_vertices)
            else:
                cmap = "plasma" if mode == "activation" else "viridis"
                self._colorings[mode] = Coloring.scalar(vertex_values(r, mode), r.surface,
                                                        _LABELS.get(mode, mode), cmap)
        return self._colorings[mode]

    def _recolor(self, mode: str) -> None:
        with self._lock:
            self._mode = mode
            self._show(self.frame)

    def _show(self, k: int) -> None:
        r = self.result
        with self._lock:
            coloring = self.coloring(self._mode)
            self.gui["legend"].content = coloring.legend
            self.body.show(r.x[k], coloring.at(k), coloring.colors)
            if self.bones is not None:
                self.bones.points = r.skeleton[k].astype(np.float32)
            for handle, used in self._overlays.values():
                if handle.visible:
                    handle.vertices = r.x[k, used].astype(np.float32)
            self.gui["clock"].content = f"t = {k * r.dt:.4f} s · frame {k} / {r.n_frames - 1}"
            if r.activation is not None:
                driven = activation_regions(r)
                self.gui["activation"].content = "  \n".join(
                    f"{ch}: **{r.activation[k, i]:.3f}**" + (f" ({driven[ch]})" if ch in driven else "")
                    for i, ch in enumerate(r.channel_names))

    def _play_loop(self) -> None:
        """Advance the timeline in real time (times the speed) while "Play" is on."""
        dt, T = self.result.dt, self.result.n_frames
        clock, shown, last = 0.0, -1, time.perf_counter()
        while not self._stop.wait(1 / 60):
            now = time.perf_counter()
            elapsed, last = now - last, now
            with self._lock:
                if not self.gui["play"].value:
                    continue
                if self.frame != shown:  # the user moved the slider: continue from there
                    clock = self.frame * dt
                clock += elapsed * self.gui["speed"].value
                k = int(clock / dt + 1e-9)
                if k >= T:
                    if self.gui["loop"].value:
                        clock, k = clock % (T * dt), int(clock % (T * dt) / dt)
                    else:
                        self.gui["play"].value = False
                        k = T - 1
                if k != self.frame:
                    self.gui["frame"].value = k
                shown = k


class LiveViewer(_ServerViewer):
    """A live simulation in the browser, stepped on a timer. Made by :func:`view_live`.

    Attributes:
        server: the :class:`viser.ViserServer`.
        url: address to open in a browser.
        state: the latest simulation state.
        x: ``(n, 3)`` the latest positions.
        steps: steps taken since the start or the last reset.
        error: the message of the exception that stopped the stepping, or ``None``.
        gui: name -> viser GUI handle (``"control:<channel>"``, ``"run"``, ``"rate"``,
            ``"reset"``, ``"color_by"``, ...).
    """

    def __init__(self, mesh: Any, step_fn: Callable, state0: Any, channels: Sequence[str],
                 ranges: Sequence[tuple[float, float]] | None, rate: float, color_by: str | None,
                 obstacles: Sequence[dict], host: str, port: int):
        free_port(host, port)  # a bad port or host fails now, not after step_fn compiled
        points, tets, surface = (np.asarray(mesh.points, float), np.asarray(mesh.tets),
                                 np.asarray(mesh.surface))
        channels = [str(c) for c in channels]
        if not channels or len(set(channels)) != len(channels):
            raise ValueError(f"channels must be a non-empty list of unique names, got {channels}")
        ranges = [(0.0, 1.0)] * len(channels) if ranges is None else [tuple(map(float, r)) for r in ranges]
        if len(ranges) != len(channels) or any(not lo < hi for lo, hi in ranges):
            raise ValueError(f"ranges must give one (low, high) with low < high per channel, got {ranges}")
        if rate <= 0:
            raise ValueError(f"rate must be a positive number of steps per second, got {rate}")
        if color_by not in ("displacement", "strain", None, "none"):
            raise ValueError(f"live colouring is 'displacement', 'strain' or None, got {color_by!r}")
        self.points, self.faces, self.ranges = points, surface, ranges
        self.step_fn, self.state0 = step_fn, state0
        controls = np.array([lo for lo, _ in ranges])
        self.state, x = step_fn(state0, controls)  # compile and check before serving
        self.x = self._check(x, 1)
        self.steps, self.error = 1, None
        self._strain = VertexStrain(points, tets)
        self._hi = {"displacement": 0.0, "strain": 0.0}
        self._on_surface = np.unique(surface)
        self._drawn: tuple[str, np.ndarray | None] = ("", None)
        self._status_time = 0.0
        # The result wrapper validates obstacles and regions the same way result files are.
        checked = Result(points, tets, surface, points[None], 1.0, obstacles=obstacles,
                         regions=dict(getattr(mesh, "regions", {})))

        super().__init__(host, port, surface)
        extent = points.max(axis=0) - points.min(axis=0)
        lo, hi = points.min(axis=0) - 0.25 * extent, points.max(axis=0) + 0.25 * extent
        lo[2] = points[:, 2].min()
        _frame_camera(self.server, lo, hi)
        _add_obstacles(self.server, checked.obstacles, lo, hi)
        self._region_coloring = Coloring.regions(dict(checked.regions), surface, len(points)) \
            if checked.regions else None
        self.gui: dict[str, Any] = {}
        self._build_gui(channels, rate, "none" if color_by is None else color_by)
        self._draw()
        self._start_thread(self._step_loop)

    def _check(self, x: Any, step: int) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        if x.shape != self.points.shape:
            raise ValueError(f"step_fn must return (state, x) with x of shape {self.points.shape}, got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"step {step} produced non-finite positions; reduce the time step "
                                     "or the controls, then press Reset")
        return x

    def _build_gui(self, channels: list[str], rate: float, color_by: str) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**softbody** live: {len(self.points)} vertices")
        with gui.add_folder("Controls"):
            for name, (lo, hi) in zip(channels, self.ranges):
                self.gui[f"control:{name}"] = gui.add_slider(name, min=lo, max=hi, step=(hi - lo) / 100, initial_value=lo)
            self.gui["minimum"] = gui.add_button("Controls to minimum")
            self.gui["minimum"].on_click(lambda _: self.set_controls([lo for lo, _ in self.ranges]))
        with gui.add_folder("Simulation"):
            self.gui["status"] = gui.add_markdown("")
            self.gui["run"] = gui.add_checkbox("Run", initial_value=True)
            self.gui["rate"] = gui.add_slider("Steps per second", min=1.0, max=max(120.0, rate), step=1.0,
                                              initial_value=rate)
            self.gui["reset"] = gui.add_button("Reset")
            self.gui["reset"].on_click(lambda _: self.reset())
        with gui.add_folder("Colour"):
            options = ["displacement", "strain"] + (["regions"] if self._region_coloring else []) + ["none"]
            self.gui["color_by"] = gui.add_dropdown("Colour by", options, initial_value=color_by)
            self.gui["legend"] = gui.add_html("")
            self.gui["color_by"].on_update(lambda _: self._draw())
        self._channels = channels

    def controls(self) -> np.ndarray:
        """``(c,)`` the slider values, in channel order."""
        return np.array([self.gui[f"control:{c}"].value for c in self._channels], dtype=np.float64)

    def set_controls(self, values: Sequence[float]) -> None:
        """Move the sliders (in every open page) to ``values``, one per channel.

        Raises:
            ValueError: not one value per channel, or a value outside its range.
        """
        values = [float(v) for v in values]
        if len(values) != len(self._channels):
            raise ValueError(f"{len(values)} values for {len(self._channels)} channels {self._channels}")
        for name, v, (lo, hi) in zip(self._channels, values, self.ranges):
            if not lo <= v <= hi:
                raise ValueError(f"control {name!r} = {v} is outside its range [{lo}, {hi}]")
            self.gui[f"control:{name}"].value = v

    def reset(self) -> None:
        """Return to ``state0`` and the rest positions; clears an error and runs again."""
        with self._lock:
            self.state, self.x, self.steps, self.error = self.state0, self.points.copy(), 0, None
            self._hi = {"displacement": 0.0, "strain": 0.0}
            self.gui["run"].value = True
            self._draw()

    def _draw(self, force: bool = True) -> None:
        """Show the latest positions; unless ``force``, skip an unchanged body and throttle
        the status text to four updates a second."""
        with self._lock:
            now = time.monotonic()
            if force or now - self._status_time > 0.25:
                status = f"step {self.steps}"
                if self.error:
                    status += f"  \n**stopped:** {html.escape(self.error)}"
                self.gui["status"].content = status
                self._status_time = now
            mode = self.gui["color_by"].value
            if not force and mode == self._drawn[0] and np.array_equal(self.x, self._drawn[1]):
                return
            if mode == "none":
                coloring = Coloring.uniform(len(self.faces))
            elif mode == "regions":
                coloring = self._region_coloring
            else:
                values = (np.linalg.norm(self.x - self.points, axis=1) if mode == "displacement"
                          else self._strain(self.x[None])[0])
                self._hi[mode] = max(self._hi[mode], float(values[self._on_surface].max()), 1e-9)
                colors = colormap("viridis")
                coloring = Coloring(face_levels(values, self.faces, 0.0, self._hi[mode])[None], colors,
                                    _legend_html(_LABELS[mode] + " (range grows)", colors, 0.0, self._hi[mode]))
            self.gui["legend"].content = coloring.legend
            self.body.show(self.x, coloring.at(0), coloring.colors)
            self._drawn = (mode, self.x)

    def _step_loop(self) -> None:
        next_time = time.perf_counter()
        while not self._stop.is_set():
            if not self.gui["run"].value:
                self._stop.wait(0.05)
                next_time = time.perf_counter()
                continue
            try:
                with self._lock:
                    state, x = self.step_fn(self.state, self.controls())
                    self.x = self._check(x, self.steps + 1)
                    self.state, self.steps = state, self.steps + 1
                    self._draw(force=False)
            except Exception as err:  # a failing step stops the stepping, not the server
                traceback.print_exc()
                self.gui["run"].value = False
                self.error = f"{type(err).__name__}: {err}"
                self._draw()
            next_time = max(next_time + 1.0 / self.gui["rate"].value, time.perf_counter() - 0.5)
            self._stop.wait(max(0.0, next_time - time.perf_counter()))


def view(result: Result | str | os.PathLike, host: str = "127.0.0.1", port: int = 8080, block: bool = True,
         color_by: str | None = "strain") -> PlaybackViewer:
    """Serve a result in the browser viewer.

    Arguments:
        result: a :class:`~softbody.io.Result` or the path of a result ``.npz``.
        host: interface to bind; ``"127.0.0.1"`` serves this machine only.
        port: TCP port, 0 to 65535; if taken, the next free one is used (see the returned
            ``url``); 0 picks any free port.
        block: serve until Ctrl-C and stop the server before returning.
        color_by: initial colouring: ``"strain"``, ``"displacement"``, ``"activation"``, a
            field name, ``"regions"`` or ``None``.

    Returns:
        The :class:`PlaybackViewer` (its ``url``, ``server``, ``frame``, ``stop()``).

    Raises:
        FileNotFoundError, ResultError: the result cannot be read, or ``color_by`` is not
            available (the message lists what is).
        ValueError: ``port`` is not an integer from 0 to 65535, ``host`` is not an address
            of this machine, or no port from ``port`` on is free (see :func:`free_port`).
    """
    viewer = PlaybackViewer(as_result(result), host, port, color_by)
    if block:
        viewer.block()
    else:
        print(f"softbody viewer: {viewer.url}", flush=True)
    return viewer


def view_live(mesh: Any, step_fn: Callable[[Any, np.ndarray], tuple[Any, Any]], state0: Any,
              channels: Sequence[str], *, ranges: Sequence[tuple[float, float]] | None = None,
              rate: float = 30.0, color_by: str | None = "displacement", obstacles: Sequence[dict] = (),
              host: str = "127.0.0.1", port: int = 8080, block: bool = True) -> LiveViewer:
    """Run a simulation live in the browser, with one slider per control channel.

    ``step_fn(state, controls)`` is called on a timer (``rate`` times a second, adjustable
    in the page) with the sliders' values and must return ``(state, x)``. It is called
    once before the server starts, so a JAX step compiles and shape errors surface here.
    An exception or non-finite positions stop the stepping and show the message in the
    page; "Reset" starts again from ``state0``.

    Arguments:
        mesh: a :class:`~softbody.meshing.TetMesh` (anything with ``points`` ``(n, 3)``,
            ``tets``, ``surface`` and optionally ``regions``).
        step_fn: ``(state, controls (c,)) -> (state, x (n, 3))``.
        state0: the initial state.
        channels: names of the ``c`` control channels.
        ranges: ``(low, high)`` per channel; default ``(0, 1)``. Sliders start at ``low``.
        rate: steps per second.
        color_by: ``"displacement"`` (from the rest shape), ``"strain"`` or ``None``.
        obstacles: obstacle dicts to draw (see :mod:`softbody.io`).
        host: interface to bind; ``"127.0.0.1"`` serves this machine only.
        port: TCP port, 0 to 65535; if taken, the next free one is used (0: any free port).
        block: serve until Ctrl-C and stop before returning.

    Returns:
        The :class:`LiveViewer` (``url``, ``state``, ``x``, ``steps``, ``controls()``,
        ``reset()``, ``stop()``).

    Raises:
        ValueError: bad channels, ranges, rate or colouring, ``step_fn`` returned
            positions of the wrong shape, or a bad ``port`` or ``host`` (see :func:`free_port`).
        FloatingPointError: the first step produced non-finite positions.
    """
    viewer = LiveViewer(mesh, step_fn, state0, channels, ranges, rate, color_by, obstacles, host, port)
    if block:
        viewer.block()
    else:
        print(f"softbody viewer: {viewer.url}", flush=True)
    return viewer


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``softbody view``."""
    parser.add_argument("result", help="result file (.npz) written by `softbody run` or Result.save")
    parser.add_argument("--port", type=port_number, default=8080,
                        help="TCP port, 0 to 65535 (default 8080; the next free one if taken; 0: any free port)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="interface to bind (default 127.0.0.1: this machine only; 0.0.0.0: the network)")
    parser.add_argument("--color-by", default="strain",
                        help="strain (default), displacement, activation, regions, a field name, or none")


def run(args: argparse.Namespace) -> int:
    """Run ``softbody view`` until Ctrl-C; returns the exit status (1 on a user error)."""
    try:
        view(args.result, host=args.host, port=args.port, block=True,
             color_by=None if args.color_by.lower() == "none" else args.color_by)
    except (FileNotFoundError, ValueError) as err:
        print(f"softbody view: {err}", file=sys.stderr)
        return 1
    return 0

"""Speed against accuracy: every integrator's knobs on one dynamic scene, and a stability map.

The scene (:class:`Cantilever`): a clamped 0.1 x 0.02 x 0.02 m rubber beam (E = 1 MPa,
nu = 0.3, 1000 kg/m^3, no gravity, no damping) is bent by a 0.4 N tip load to its static
equilibrium (~8 mm tip deflection), the load is removed and the beam vibrates freely
(first bending period ~0.1 s) for ``duration`` seconds. ``grid_box`` meshes with
``(5k, k, k)`` cells (``k`` cells through the thickness).

Error: the relative L2 error of the tip point's displacement ``u(t)`` (the point
``(L, 0, 0)``, interpolated with the P1 shape functions of its tet, so meshes whose
vertices differ compare) over a run's own output times ``t_i``:
``sqrt(sum |u(t_i) - u_ref(t_i)|^2 / sum |u_ref(t_i)|^2)``, with ``u_ref`` diffrax's Tsit5
solution of the semi-discrete ODE on the finest mesh at rtol 1e-8 (sampled densely and
linearly interpolated). Runs on the finest mesh therefore measure the time integration
error alone; runs on coarser meshes add the spatial error.

Runs: projective dynamics (L-BFGS and plain local-global, tolerance x dt, L-BFGS on
coarser meshes, and L-BFGS with BDF2 steps, ``PD BDF2``), Newton's method on the same implicit-Euler steps (tolerance x dt),
diffrax's stiff Kvaerno5 (tolerance), explicit semi-implicit Euler (a dt ladder through
its stability limit). ``wall_s`` is the run without compilation; ``compile_s`` is
reported beside it (for Newton: the first step, which compiles its kernels).

Stability map: for E = 1e7 and 1e4 Pa (the load scaled with E, so the deflection is the
same) the largest dt of a geometric ladder at which each fixed-step method stays finite
and bounded (tip displacement never above twice the initial one: without load or
actuation the free motion can only lose energy) over ``stability_duration``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path

import numpy as np

#: Time steps of the implicit methods (s).
DTS = (1 / 30, 1 / 100, 1 / 300, 1 / 1000)
#: Geometric ladder of the stability map (s), largest first.
LADDER = (1 / 30, 1e-2, 3e-3, 1e-3, 3e-4, 1e-4, 3e-5, 1e-5, 3e-6)


@dataclasses.dataclass(frozen=True)
class Cantilever:
    """The free-vibration scene (see the module docstring).

    Attributes:
        E, nu, density: the material (Pa, -, kg/m^3).
        load: the total tip load that bends the beam before release, N (along -z).
        duration: simulated time after release, s.
        divisions: the meshes, as cells through the thickness ``k`` (``(5k, k, k)`` cells),
            coarsest first; the last is the reference mesh.
        length, width: beam dimensions, m.
    """

    E: float = 1e6
    nu: float = 0.3
    density: float = 1000.0
    load: float = 0.4
    duration: float = 0.5
    divisions: tuple[int, ...] = (2, 3, 4)
    length: float = 0.1
    width: float = 0.02

    @property
    def finest(self) -> int:
        return self.divisions[-1]

    def mesh(self, k: int):
        """The ``grid_box`` mesh with ``(5k, k, k)`` cells (regions ``fixed`` and ``tip``)."""
        return _mesh(self.length, self.width, k)

    def build(self, k: int, dt: float = 0.01, tol: float = 1e-6, solver=None, max_iter: int = 2000,
              linear_solver=None, integrator=None):
        """``(model, params)`` of the scene on mesh ``k`` with the given step options."""
        from softbody.material import Material
        from softbody.model import Options, build
        from softbody.scene import SoftBody

        options = Options(dt=dt, tol=tol, max_iter=max_iter, solver=solver, gravity=(0.0, 0.0, 0.0),
                          linear_solver=linear_solver, integrator=integrator)
        return build(SoftBody(self.mesh(k), Material(E=self.E, nu=self.nu, density=self.density), fixed="fixed"),
                     options=options)

    def initial_state(self, model, params):
        """The released state: the static equilibrium under the tip load, at rest."""
        from softbody.model import initial_state

        return initial_state(model, params, x=_deflected(self, model.n_vertices))

    def tip_displacement(self, xs) -> np.ndarray:
        """Displacements ``(T, 3)`` of the tip point ``(L, 0, 0)`` from positions ``(T, n, 3)``."""
        n = np.shape(xs)[1]
        k = _divisions_of(self, n)
        idx, w = _tip_weights(self.length, self.width, k)
        xs = np.asarray(xs)
        return np.einsum("tai,a->ti", xs[:, idx], w) - np.array([self.length, 0.0, 0.0])


@functools.lru_cache(maxsize=None)
def _mesh(length, width, k):
    from softbody.meshing.grid import grid_box

    return grid_box((length, width, width), (5 * k, k, k), origin=(0.0, -width / 2, -width / 2))


def _divisions_of(scene: Cantilever, n_vertices: int) -> int:
    for k in range(1, 64):
        if (5 * k + 1) * (k + 1) ** 2 == n_vertices:
            return k
    raise ValueError(f"no mesh of the scene has {n_vertices} vertices")


@functools.lru_cache(maxsize=None)
def _tip_weights(length, width, k):
    """Vertex indices ``(4,)`` and P1 weights ``(4,)`` of the point ``(L, 0, 0)``."""
    mesh = _mesh(length, width, k)
    p = np.array([length, 0.0, 0.0])
    xe = mesh.points[mesh.tets]  # (t, 4, 3)
    edges = np.transpose(xe[:, 1:] - xe[:, :1], (0, 2, 1))  # (t, 3, 3)
    lam = np.linalg.solve(edges, (p - xe[:, 0])[:, :, None])[:, :, 0]
    bary = np.concatenate([1 - lam.sum(1, keepdims=True), lam], axis=1)
    e = int(np.argmax(bary.min(axis=1)))  # the tet containing p (all weights >= 0)
    if bary[e].min() < -1e-9:
        raise ValueError("the tip point lies outside the mesh")
    return mesh.tets[e].astype(np.int64), np.clip(bary[e], 0.0, 1.0)


_DEFLECTED: dict = {}


def _deflected(scene: Cantilever, n_vertices: int) -> np.ndarray:
    """The static equilibrium ``(n, 3)`` under the tip load (PD, tol 1e-10), cached."""
    k = _divisions_of(scene, n_vertices)
    key = (scene.E, scene.nu, scene.load, scene.length, scene.width, k)
    if key not in _DEFLECTED:
        import jax.numpy as jnp

        from softbody.simulate import solve_static

        model, params = scene.build(k, tol=1e-10, max_iter=50000)
        tip = model.mesh.regions["tip"].vertices
        force = np.zeros((model.n_vertices, 3))
        force[tip, 2] = -scene.load / len(tip)
        x, _ = solve_static(model, params, force=jnp.asarray(force))  # raises unless it converged
        _DEFLECTED[key] = np.asarray(x)
    return _DEFLECTED[key]


# --------------------------------------------------------------------------------------
# Reference and error
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Reference:
    """The tip displacement ``u (T, 3)`` at times ``t (T,)`` of the converged solution."""

    t: np.ndarray
    u: np.ndarray
    rtol: float
    wall_s: float
    self_error: float | None  # relative L2 difference from a solve at 100 rtol, when measured

    def error(self, t, u) -> float:
        """Relative L2 error of ``u (T, 3)`` at times ``t (T,)`` (see the module docstring)."""
        t, u = np.asarray(t), np.asarray(u)
        ref = np.stack([np.interp(t, self.t, self.u[:, i]) for i in range(3)], axis=1)
        return float(np.linalg.norm(u - ref) / np.linalg.norm(ref))


def reference(scene: Cantilever, samples: int = 1000, rtol: float = 1e-8, check: bool = False) -> Reference:
    """Tsit5 on the finest mesh at ``rtol`` (atol ``1e-3 rtol``, m and m/s), sampled at
    ``samples`` times; ``check=True`` also solves at ``100 rtol`` to bound its error.

    Tsit5's step is set by the stability of the mesh's fastest mode here (its error at
    rtol 1e-7 was 1e-8 of the motion on the 99-vertex mesh), so the tolerance costs little.
    """
    import diffrax

    from softbody.reference import diffrax_rollout

    model, params = scene.build(scene.finest)
    state = scene.initial_state(model, params)
    ts = np.linspace(0.0, scene.duration, samples + 1)[1:]
    u0 = scene.tip_displacement(np.asarray(state.x)[None])

    def solve(r):
        t0 = time.perf_counter()
        xs = np.asarray(diffrax_rollout(model, params, state, scene.duration, ts, rtol=r, atol=1e-3 * r,
                                        solver=diffrax.Tsit5(), max_steps=1_000_000))
        return np.concatenate([u0, scene.tip_displacement(xs)]), time.perf_counter() - t0

    u, wall = solve(rtol)
    self_error = None
    if check:
        loose, _ = solve(100 * rtol)
        self_error = float(np.linalg.norm(loose - u) / np.linalg.norm(u))
    return Reference(t=np.concatenate([[0.0], ts]), u=u, rtol=rtol, wall_s=wall, self_error=self_error)


# --------------------------------------------------------------------------------------
# Runners: each returns (times (T,), tip displacement (T, 3), wall_s, compile_s, extra)
# --------------------------------------------------------------------------------------


def _timed(call, short: float = 2.0, repeats: int = 3):
    """``(median wall time, result)`` of a compiled call: repeated ``repeats`` times when
    the first run is shorter than ``short`` seconds (the machine is shared and noisy)."""
    import jax

    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(call())
        times.append(time.perf_counter() - t0)
        if times[0] >= short:
            break
    return float(np.median(times)), out


def _n_steps(scene: Cantilever, dt: float) -> int:
    return max(1, int(round(scene.duration / dt)))


def run_pd(scene: Cantilever, k: int, dt: float, tol: float, solver=None, duration=None, integrator=None):
    """Projective dynamics (``solver``: ``None`` = L-BFGS, or ``LocalGlobal()``; ``integrator``:
    ``None`` = implicit Euler, or ``BDF2()``)."""
    import jax

    from softbody import simulate

    scene = scene if duration is None else dataclasses.replace(scene, duration=duration)
    model, params = scene.build(k, dt=dt, tol=tol, solver=solver, integrator=integrator)
    state = scene.initial_state(model, params)
    n = _n_steps(scene, dt)
    t0 = time.perf_counter()
    # throw=False: the front records steps at the iteration cap and divergence, not raises
    compiled = jax.jit(lambda p, s: simulate.rollout(model, p, s, n_steps=n, throw=False)).lower(params, state).compile()
    compile_s = time.perf_counter() - t0
    wall, traj = _timed(lambda: compiled(params, state))
    result = np.asarray(traj.info.result)
    if np.any(result == simulate.RESULTS.nonfinite):
        return dt * np.arange(n + 1), np.full((n + 1, 3), np.nan), math.nan, compile_s, {"finite": False}
    extra = {"iterations_per_step": float(np.mean(traj.info.iterations)),
             "converged_fraction": float(np.mean(traj.info.converged)),
             "inverted_steps": int(np.sum(result == simulate.RESULTS.inverted)), "finite": True}
    return dt * np.arange(n + 1), scene.tip_displacement(traj.x), wall, compile_s, extra


def run_newton(scene: Cantilever, k: int, dt: float, tol: float, duration=None):
    """Newton's method on each implicit-Euler step (host loop, sparse LU)."""
    from softbody.reference import newton_rollout

    scene = scene if duration is None else dataclasses.replace(scene, duration=duration)
    model, params = scene.build(k, dt=dt)
    state = scene.initial_state(model, params)
    n = _n_steps(scene, dt)
    t0 = time.perf_counter()
    newton_rollout(model, params, state, n_steps=1, tol=tol)  # compiles the kernels
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    traj = newton_rollout(model, params, state, n_steps=n, tol=tol)
    wall = time.perf_counter() - t0
    extra = {"iterations_per_step": float(np.mean(traj.info.iterations)), "finite": True}
    return dt * np.arange(n + 1), scene.tip_displacement(traj.x), wall, compile_s, extra


def run_diffrax(scene: Cantilever, k: int, rtol: float, outputs: int = 100, compile_s: float | None = None):
    """diffrax's stiff Kvaerno5 with the block-assembled Jacobian at ``rtol`` (atol 1e-3 rtol).

    diffrax compiles inside the call, once per tolerance (a static argument): without
    ``compile_s`` the run is repeated and the difference is the compilation; with it (the
    same program compiled for another tolerance) the run is taken once and ``compile_s``
    subtracted.
    """
    import diffrax
    import jax

    from softbody.reference import diffrax_rollout

    model, params = scene.build(k)
    state = scene.initial_state(model, params)
    ts = np.linspace(0.0, scene.duration, outputs + 1)[1:]

    def once():
        t0 = time.perf_counter()
        xs = jax.block_until_ready(diffrax_rollout(model, params, state, scene.duration, ts, rtol=rtol,
                                                   atol=1e-3 * rtol, solver=diffrax.Kvaerno5()))
        return np.asarray(xs), time.perf_counter() - t0

    xs, first = once()
    if compile_s is None:
        xs, wall = once()
        compile_s, extra = max(first - wall, 0.0), {}
    else:
        wall, extra = max(first - compile_s, 0.0), {"compile_estimated": True}
    t = np.concatenate([[0.0], ts])
    u = np.concatenate([scene.tip_displacement(np.asarray(state.x)[None]), scene.tip_displacement(xs)])
    return t, u, wall, compile_s, {"finite": bool(np.isfinite(xs).all()), **extra}


def run_explicit(scene: Cantilever, k: int, dt: float, duration=None):
    """Semi-implicit (symplectic) Euler at ``dt``."""
    from softbody import explicit

    scene = scene if duration is None else dataclasses.replace(scene, duration=duration)
    model, params = scene.build(k, dt=dt)
    state = scene.initial_state(model, params)
    n = _n_steps(scene, dt)
    t0 = time.perf_counter()
    compiled = explicit._explicit.lower(model, params, state, None, None, n, dt).compile()
    compile_s = time.perf_counter() - t0
    wall, (traj, failed, _) = _timed(lambda: compiled(params, state, None, None, dt))
    return dt * np.arange(n + 1), scene.tip_displacement(traj.x), wall, compile_s, {"finite": not bool(failed)}


def _explicit_ladder(scene: Cantilever, k: int, ladder, n_steps: int) -> list:
    """Walk ``ladder`` (largest dt first) with ``n_steps`` explicit steps each, one compiled
    program (the step size is traced), until a dt stays finite and bounded."""
    from softbody import explicit

    model, params = scene.build(k, dt=ladder[0])
    state = scene.initial_state(model, params)
    tried = []
    for dt in ladder:
        traj, failed, _ = explicit._explicit(model, params, state, None, None, n_steps, dt)
        ok = _bounded(scene.tip_displacement(np.asarray(traj.x)), not bool(failed))
        tried.append({"dt": dt, "stable": ok, "simulated_s": n_steps * dt, **({} if ok else {"note": "unbounded"})})
        if ok:
            break
    return tried


def _bounded(u: np.ndarray, finite: bool) -> bool:
    """Finite, and the tip never moved more than twice its initial displacement."""
    if not finite or not np.isfinite(u).all():
        return False
    amplitude = np.linalg.norm(u, axis=1)
    return bool(amplitude.max() <= 2.0 * amplitude[0])


# --------------------------------------------------------------------------------------
# The bench
# --------------------------------------------------------------------------------------


def plan(quick: bool) -> dict:
    """The scene and the knob grid of the full or the quick bench."""
    if quick:
        return {"scene": Cantilever(duration=0.1, divisions=(1, 2)),
                "pd_dts": (1 / 30, 1 / 100), "pd_tols": (1e-3, 1e-6), "bdf2_dts": (1 / 30, 1 / 100),
                "local_global_dts": (1 / 100,), "coarse_dts": (1 / 100,), "coarse_tols": (1e-6,),
                "newton_dts": (1 / 100,), "newton_tols": (1e-8,), "diffrax_rtols": (1e-3,),
                "explicit_dts": (2.5e-4, 1.25e-4), "stability_divisions": 1,
                "stability_duration": 0.05, "stability_methods": ("PD L-BFGS", "PD BDF2", "explicit")}
    return {"scene": Cantilever(duration=0.3, divisions=(1, 2, 3)),
            "pd_dts": DTS + (1 / 3000, 1 / 10000, 1 / 30000), "pd_tols": (1e-6,),
            "pd_loose": ((1 / 30, 1e-3), (1 / 100, 1e-3), (1 / 1000, 1e-3)),
            "bdf2_dts": DTS + (1 / 3000,),
            "local_global_dts": (1 / 100, 1 / 300), "coarse_dts": (1 / 3000,), "coarse_tols": (1e-6,),
            "newton_dts": DTS, "newton_tols": (1e-8,),
            "diffrax_rtols": (1e-2, 1e-3, 1e-4),
            "explicit_dts": (2e-4, 1e-4, 5e-5, 2.5e-5), "stability_divisions": 2,
            "stability_duration": 0.2,
            "stability_methods": ("PD L-BFGS", "PD LocalGlobal", "PD BDF2", "Newton", "explicit")}


def _entry(method, knobs, ref: Reference, run, vertices) -> dict:
    """Run ``run()`` and make its row; a run that raises is recorded with its error.

    Says which run starts (it compiles first: a ``still ...`` line every ~10 s on a pipe,
    see :mod:`softbody.progress`) and, when it ends, its wall time, compilation and error.
    """
    from softbody import progress

    shown = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in knobs.items())
    try:
        with progress.task(f"{method} {shown} ({vertices} vertices)", done=None):
            t, u, wall, compile_s, extra = run()
    except Exception as err:  # a benchmark records failures instead of stopping
        progress.say(f"{method:16s} {knobs} FAILED: {type(err).__name__}: {err}")
        return {"method": method, **knobs, "vertices": vertices, "wall_s": math.nan, "compile_s": math.nan,
                "rel_error": math.inf, "diverged": True, "failed": f"{type(err).__name__}: {str(err)[:200]}"}
    bounded = _bounded(u, extra.pop("finite", True))
    error = ref.error(t, u) if bounded else math.inf
    row = {"method": method, **knobs, "vertices": vertices, "wall_s": wall, "compile_s": compile_s,
           "rel_error": error, "diverged": not bounded, **extra}
    progress.say(f"{method:16s} {shown:40s} wall {wall:8.3f} s  compile {compile_s:6.1f} s  error "
                 f"{error:.3e}" + ("  DIVERGED" if not bounded else ""))
    return row


def measure_front(scene: Cantilever, grid: dict, ref: Reference | None = None, methods=None) -> tuple[list, Reference]:
    """Run every method over its knobs; returns ``(rows, reference)``."""
    from softbody import progress
    from softbody.simulate import BDF2
    from softbody.solvers import LocalGlobal

    if ref is None:
        with progress.task(f"reference: Tsit5 on {scene.mesh(scene.finest).n_vertices} vertices", done=None):
            ref = reference(scene)
        progress.say(f"reference: Tsit5 rtol {ref.rtol:g} on {scene.mesh(scene.finest).n_vertices} vertices, "
                     f"{ref.wall_s:.1f} s")
    methods = methods or ("PD L-BFGS", "PD LocalGlobal", "PD BDF2", "PD mesh", "Newton", "diffrax Kvaerno5",
                          "explicit")
    rows = []
    k = scene.finest
    nv = scene.mesh(k).n_vertices
    if "PD L-BFGS" in methods:
        for dt in grid["pd_dts"]:
            for tol in grid["pd_tols"]:
                rows.append(_entry("PD L-BFGS", {"dt": dt, "tol": tol, "mesh_k": k}, ref,
                                   lambda: run_pd(scene, k, dt, tol), nv))
        for dt, tol in grid.get("pd_loose", ()):
            rows.append(_entry("PD L-BFGS", {"dt": dt, "tol": tol, "mesh_k": k}, ref,
                               lambda: run_pd(scene, k, dt, tol), nv))
    if "PD LocalGlobal" in methods:
        for dt in grid["local_global_dts"]:
            for tol in grid["pd_tols"]:
                rows.append(_entry("PD LocalGlobal", {"dt": dt, "tol": tol, "mesh_k": k}, ref,
                                   lambda: run_pd(scene, k, dt, tol, LocalGlobal()), nv))
    if "PD BDF2" in methods:
        for dt in grid["bdf2_dts"]:
            for tol in grid["pd_tols"]:
                rows.append(_entry("PD BDF2", {"dt": dt, "tol": tol, "mesh_k": k}, ref,
                                   lambda: run_pd(scene, k, dt, tol, integrator=BDF2()), nv))
    if "PD mesh" in methods:
        for kc in scene.divisions[:-1]:
            for dt in grid["coarse_dts"]:
                for tol in grid["coarse_tols"]:
                    rows.append(_entry("PD L-BFGS", {"dt": dt, "tol": tol, "mesh_k": kc}, ref,
                                       lambda: run_pd(scene, kc, dt, tol), scene.mesh(kc).n_vertices))
    if "Newton" in methods:
        for dt in grid["newton_dts"]:
            for tol in grid["newton_tols"]:
                rows.append(_entry("Newton", {"dt": dt, "tol": tol, "mesh_k": k}, ref,
                                   lambda: run_newton(scene, k, dt, tol), nv))
    if "diffrax Kvaerno5" in methods:
        compile_s = None
        for rtol in grid["diffrax_rtols"]:  # loosest first: it measures the compilation
            row = _entry("diffrax Kvaerno5", {"rtol": rtol, "mesh_k": k}, ref,
                         lambda: run_diffrax(scene, k, rtol, compile_s=compile_s), nv)
            compile_s = row["compile_s"] if math.isfinite(row["compile_s"]) else None
            rows.append(row)
    if "explicit" in methods:
        for dt in grid["explicit_dts"]:
            rows.append(_entry("explicit", {"dt": dt, "mesh_k": k}, ref, lambda: run_explicit(scene, k, dt), nv))
    return rows, ref


def stability_map(k: int, duration: float, methods, stiffnesses=(1e7, 1e4), ladder=LADDER,
                  explicit_steps: int = 400) -> dict:
    """Largest stable dt of each fixed-step method for each stiffness (see the module docstring).

    Walks ``ladder`` from the largest dt down and stops at the first dt whose run stays
    finite and bounded. Implicit runs cover ``duration``; explicit ones ``explicit_steps``
    steps: at 1.15x the limit the fastest mode grows by 2.6x per step (round-off overflows
    in ~100 steps), but a rung within a few percent above the limit could pass.
    """
    from softbody.simulate import BDF2, SimulationError
    from softbody.solvers import LocalGlobal

    table = {}
    for E in stiffnesses:
        scene = Cantilever(E=E, load=0.4 * E / 1e6, divisions=(k,))
        for method in methods:
            if method == "explicit":
                tried = _explicit_ladder(scene, k, ladder, explicit_steps)
            else:
                tried = []
                for dt in ladder:
                    try:
                        if method == "Newton":
                            result = run_newton(scene, k, dt, 1e-8, duration=max(duration, dt))
                        else:
                            result = run_pd(scene, k, dt, 1e-6, LocalGlobal() if method == "PD LocalGlobal" else None,
                                            duration=max(duration, dt),
                                            integrator=BDF2() if method == "PD BDF2" else None)
                        ok = _bounded(result[1], result[4]["finite"])
                        note = "" if ok else "unbounded"
                    except (SimulationError, ValueError) as err:
                        ok, note = False, str(err).splitlines()[0][:120]
                    tried.append({"dt": dt, "stable": ok, "simulated_s": max(duration, dt),
                                  **({"note": note} if note else {})})
                    if ok:
                        break
            stable = [t["dt"] for t in tried if t["stable"]]
            table.setdefault(method, {})[f"E={E:g}"] = {"largest_stable_dt": stable[0] if stable else None,
                                                         "tried": tried}
    table["diffrax Kvaerno5"] = {f"E={E:g}": {"largest_stable_dt": None,
                                              "note": "adaptive step size set by the error controller; "
                                                      "Kvaerno5 is L-stable"} for E in stiffnesses}
    return table


def format_stability(table: dict) -> str:
    """The stability map as a text table."""
    keys = list(next(iter(table.values())))
    lines = [f"{'method':18s}" + "".join(f"{k:>16s}" for k in keys)]
    for method, cols in table.items():
        cells = []
        for key in keys:
            dt = cols[key]["largest_stable_dt"]
            text = f"{dt:.3g} s" if dt is not None else ("adaptive" if "note" in cols[key] else "none")
            cells.append(f"{text:>16s}")
        lines.append(f"{method:18s}" + "".join(cells))
    return "\n".join(lines)


def cheapest_under(rows, error: float, method: str | None = None):
    """The fastest row with ``rel_error <= error`` (of ``method`` when given), or ``None``."""
    ok = [r for r in rows if r["rel_error"] <= error and (method is None or r["method"] == method)]
    return min(ok, key=lambda r: r["wall_s"]) if ok else None


def run(out: Path, quick: bool) -> dict:
    grid = plan(quick)
    scene = grid["scene"]
    t_start = time.perf_counter()
    rows, ref = measure_front(scene, grid)
    from softbody import progress

    with progress.task("pareto: stability map"):
        table = stability_map(grid["stability_divisions"], grid["stability_duration"], grid["stability_methods"])
    print(format_stability(table), flush=True)
    _plot(out / "pareto.png", rows, scene)
    at_1pc = {}
    for method in ("PD L-BFGS", "PD LocalGlobal", "Newton", "diffrax Kvaerno5", "explicit"):
        best = cheapest_under(rows, 1e-2, method)
        at_1pc[method] = None if best is None else {k: best[k] for k in best if k in (
            "dt", "tol", "rtol", "mesh_k", "vertices", "wall_s", "rel_error")}
    figures = {
        "scene": dataclasses.asdict(scene),
        "mesh_vertices": {str(k): scene.mesh(k).n_vertices for k in scene.divisions},
        "reference": {"solver": "diffrax Tsit5", "rtol": ref.rtol, "vertices": scene.mesh(scene.finest).n_vertices,
                      "wall_s": ref.wall_s},
        "runs": rows,
        "cheapest_at_1pc_error": at_1pc,
        "stability": table,
        "total_s": time.perf_counter() - t_start,
    }
    return figures


def _plot(path: Path, rows, scene) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    groups = {}
    for r in rows:
        name = r["method"] if r["mesh_k"] == scene.finest else f"{r['method']} ({r['vertices']} vertices)"
        groups.setdefault(name, []).append(r)
    worst = max([r["rel_error"] for r in rows if np.isfinite(r["rel_error"])] + [1.0])
    for name, group in groups.items():
        ok = sorted((r for r in group if not r["diverged"]), key=lambda r: r["wall_s"])
        front, best = [], math.inf  # the method's own Pareto front
        for r in ok:
            if r["rel_error"] < best:
                front.append(r)
                best = r["rel_error"]
        line, = ax.loglog([r["wall_s"] for r in front], [r["rel_error"] for r in front], "o-", label=name)
        others = [r for r in ok if r not in front]
        ax.loglog([r["wall_s"] for r in others], [r["rel_error"] for r in others], "o", color=line.get_color(),
                  alpha=0.35)
        bad = [r for r in group if r["diverged"]]
        if bad:
            ax.loglog([r["wall_s"] for r in bad], [2 * worst] * len(bad), "x", color=line.get_color(), ms=9)
    ax.axhline(1e-2, color="gray", lw=0.8, ls=":")
    ax.set_xlabel("wall time per run, s (compilation excluded)")
    ax.set_ylabel("relative L2 error of the tip trajectory")
    ax.set_title(f"Cantilever free vibration, {scene.duration:g} s simulated (x: diverged)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

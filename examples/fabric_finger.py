"""A fabric-reinforced pneumatic finger: a woven fabric bonded to one face of the finger.

The finger is :func:`softbody.meshing.finger` (90 x 20 x 20 mm, silicone E = 200 kPa,
nu = 0.45) with its chamber centred on the neutral axis (``gap=-7 mm``), the layout of a
fibre-reinforced bending actuator: alone, the pressurised finger only elongates. A fabric
membrane (:class:`softbody.shell.Membrane`, E t = 3e4 N/m, 0.3 mm thick) bonded to the
surface triangles of its bottom face keeps that face's length, so at the same pressure
(10 kPa, static equilibrium) the finger curls towards the fabric and elongates less. The
fabric's Young's modulus is a design parameter: the tip angle's derivative with respect
to it, through the static solve's implicit adjoint, is checked against central
differences.

On the finger as :func:`softbody.meshing.finger` makes it (chamber above the neutral
axis, ``gap=+1 mm``) the bottom face is already shortened by the pressure (the chamber's
end load acts above the section's centroid), and a fabric there holds it at its length
and so bends the finger less (measured, 20 kPa, mesh size 6 mm: 10.3 deg alone, 9.0 deg
with the fabric): a strain-limiting layer helps where its face would otherwise stretch.

Run::

    python examples/fabric_finger.py --out results/fabric_finger

Writes ``metrics.json`` (``tip_angle_deg`` and ``elongation_m`` for ``fabric`` and
``plain``, ``dangle_dE_fd_rel_error``, ...) and ``centre_lines.png`` (side view of both
deformed centre lines).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

if __name__ == "__main__":  # the first line, before the imports of JAX and softbody (seconds)
    print(f"{Path(__file__).name}: starting (importing JAX and softbody) ...", flush=True)

import jax.numpy as jnp
import numpy as np

from softbody import progress
from softbody.actuators import CavityPressure
from softbody.gradients import check_grad, random_directions
from softbody.io import check_overwrite, write_metrics
from softbody.material import Material
from softbody.meshing import finger
from softbody.model import Options, build
from softbody.scene import SoftBody
from softbody.shell import Membrane
from softbody.simulate import solve_static

LENGTH, WIDTH, HEIGHT, GAP = 0.09, 0.02, 0.02, -0.007  # m
PRESSURE = 1e4  # Pa
FABRIC_ET, FABRIC_T, FABRIC_NU = 3e4, 3e-4, 0.3  # N/m, m, -


def long_edges(points):
    """The beam's four long edges ``(y, z) = (+-w/2, +-h/2)``, each ``(k,)`` vertex indices
    from base to tip."""
    edges = []
    for y in (points[:, 1].min(), points[:, 1].max()):
        for z in (points[:, 2].min(), points[:, 2].max()):
            e = np.flatnonzero(np.isclose(points[:, 1], y) & np.isclose(points[:, 2], z))
            edges.append(e[np.argsort(points[e, 0])])
    return edges


def centre_line(points, x, edges, n=60):
    """``(n, 3)``: the mean of the four long edges, each sampled at the same ``n`` rest
    positions along the beam (under plane sections, the line through the section's
    middle)."""
    s = np.linspace(0.0, LENGTH, n)
    return np.mean([np.stack([np.interp(s, points[e, 0], x[e, k]) for k in range(3)], axis=1) for e in edges], axis=0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--force", action="store_true", help="overwrite existing results")
    parser.add_argument("--size", type=float, default=0.006, help="mesh size, m")
    args = parser.parse_args(argv)
    check_overwrite(args.out / "metrics.json", args.force)
    start = time.perf_counter()

    mesh = finger(length=LENGTH, width=WIDTH, height=HEIGHT, gap=GAP, size=args.size)
    points = mesh.points
    z = points[mesh.surface][..., 2]
    bottom = mesh.surface[np.all(np.isclose(z, points[:, 2].min()), axis=1)]
    chamber = CavityPressure.from_regions(mesh, ["cavity:chamber"])
    fabric = Membrane.on(mesh, bottom, E=FABRIC_ET / FABRIC_T, nu=FABRIC_NU, thickness=FABRIC_T)
    silicone = Material(E=2e5, nu=0.45)
    options = Options(gravity=(0.0, 0.0, 0.0), tol=1e-11, atol=1e-11, max_iter=50000)
    print(f"finger: {mesh.n_vertices} vertices, {mesh.n_tets} tets; fabric: {len(bottom)} triangles")

    tip = mesh.regions["tip"].vertices
    fit = np.stack([np.ones(len(tip)), points[tip, 1] - points[tip, 1].mean(), points[tip, 2] - points[tip, 2].mean()],
                   axis=1)
    weights = np.linalg.pinv(fit)[2]  # the tip face's rest z direction, deformed: weights @ x[tip]

    def tip_angle(x):
        """The tip face's rotation about +y, rad (positive: curled towards -z, the fabric)."""
        a = jnp.asarray(weights) @ x[jnp.asarray(tip)]
        return jnp.arctan2(a[0], a[2])

    edges = long_edges(points)
    rest = np.array([np.ptp(points[e, 0]) for e in edges])
    results, lines, models = {}, {}, {}
    for name, actuators in (("plain", [chamber]), ("fabric", [chamber, fabric])):
        with progress.task(f"static solve of the {name} finger at {PRESSURE / 1e3:.0f} kPa (compiles)"):
            model, params = build(SoftBody(mesh, silicone, fixed="fixed", actuators=actuators), options=options)
            x, info = solve_static(model, params, activation=jnp.array([PRESSURE]), x0=jnp.asarray(points))
        x = np.asarray(x)
        lengths = np.array([np.sum(np.linalg.norm(np.diff(x[e], axis=0), axis=1)) for e in edges])
        results[name] = {"tip_angle_deg": float(np.degrees(tip_angle(x))),
                         "elongation_m": float(np.mean(lengths - rest)),
                         "iterations": int(info.iterations)}
        lines[name] = centre_line(points, x, edges)
        models[name] = (model, params)
        print(f"{name}: tip angle {results[name]['tip_angle_deg']:.3f} deg, centre-line elongation "
              f"{results[name]['elongation_m'] * 1e3:.3f} mm ({results[name]['iterations']} iterations)")

    model, params = models["fabric"]

    def angle(log_scale):
        f = params.actuators[1]
        p = params.replace(actuators=(params.actuators[0], dataclasses.replace(f, E=f.E * jnp.exp(log_scale))))
        x, _ = solve_static(model, p, activation=jnp.array([PRESSURE]), x0=jnp.asarray(points))
        return tip_angle(x)

    with progress.task("d(tip angle)/dE of the fabric: implicit adjoint against central differences"):
        check = check_grad(angle, jnp.zeros(()), eps=1e-2)["all"]
    direction = float(random_directions(jnp.zeros(()), None, seed=0)["all"])
    dangle_dlog_e = check["ad"] / direction
    fabric_e = FABRIC_ET / FABRIC_T

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    args.out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    ax.plot([0, LENGTH * 1e3], [0, 0], color="grey", ls=":", label="rest")
    for name, style in (("plain", "--"), ("fabric", "-")):
        r = results[name]
        ax.plot(lines[name][:, 0] * 1e3, lines[name][:, 2] * 1e3, style,
                label=f"{name}: {r['tip_angle_deg']:.2f} deg, +{r['elongation_m'] * 1e3:.2f} mm")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_title(f"Centre lines at {PRESSURE / 1e3:.0f} kPa (fabric on the bottom face)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "centre_lines.png", dpi=120)

    metrics = {
        "tip_angle_deg": {k: v["tip_angle_deg"] for k, v in results.items()},
        "elongation_m": {k: v["elongation_m"] for k, v in results.items()},
        "static_iterations": {k: v["iterations"] for k, v in results.items()},
        "dangle_dE_rad_per_pa": dangle_dlog_e / fabric_e,
        "dangle_dE_fd_rel_error": check["rel_error"],
        "pressure_pa": PRESSURE, "fabric_E_pa": fabric_e, "fabric_thickness_m": FABRIC_T,
        "fabric_E_times_thickness_n_per_m": FABRIC_ET, "silicone_E_pa": 2e5, "chamber_gap_m": GAP,
        "mesh_size_m": args.size, "vertices": mesh.n_vertices, "tets": mesh.n_tets,
        "fabric_triangles": len(bottom), "wall_time_s": time.perf_counter() - start,
    }
    print(f"dangle/dE = {metrics['dangle_dE_rad_per_pa']:.4e} rad/Pa; relative error against central "
          f"differences {check['rel_error']:.2e}")
    write_metrics(args.out / "metrics.json", metrics, force=True)
    print(f"wrote {args.out / 'metrics.json'} and centre_lines.png ({metrics['wall_time_s']:.0f} s)", flush=True)
    return metrics


if __name__ == "__main__":
    main()

"""Volumetric locking: a silicone cantilever's static deflection against nu, per element.

Scene: a 3 x 3 x 10 cm beam along +x (gmsh, :func:`softbody.meshing.examples.cantilever`),
clamped at x = 0 (every vertex there held), E = 263,824 Pa, density 1070 kg/m^3, under two
load cases: its weight (g = 9.81 m/s^2 along -z) and a tip load of 0.1 N along -z spread
uniformly over the tip face (consistent nodal forces, a third of each tip triangle's share
on each of its corners). Elements: ``linear`` (linear tets with their own volume term,
today's default) and ``nodal`` (the same tets with the nodally averaged volume of
:class:`softbody.nodal.NodalVolume`). Static solves to a relative residual of 1e-9.

Reference: scikit-fem's small-deflection linear elasticity on a structured tet mesh of the
same beam (``cells`` along x, ``0.3 cells`` across), quadratic P2 displacements for nu < 0.49
and mixed P2-P1 (Taylor-Hood) for nu >= 0.49, where pure-displacement elements still
lock; the load cases are the same (body force, uniform traction on the tip face). The
figure compared is the tip deflection: the mean of u_z over the tip face (area-weighted,
exact for both discretisations). The gravity sag is ~7 % of the length: the corotated
model's geometric nonlinearity moves it by ~0.4 % (measured at 1 % of the load), within
the comparison's resolution but not zero.

Figures: ``max_rel_error_vs_p2[element][nu]`` is the larger of the two load cases'
``|d / d_ref - 1|`` on the finest mesh of the run (the P2 or Taylor-Hood reference, as
above); ``cases`` holds every mesh, element, nu and load case with its deflection,
L-BFGS iteration count and convergence; ``iteration_ratio[element]`` is the iterations
at nu = 0.499 over those at nu = 0.3 (gravity, finest mesh); ``reference`` the reference
deflections with the two finest reference meshes' difference (its discretisation error).
``--quick``: one mesh (641 vertices) and a coarser reference.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

LENGTH, WIDTH, HEIGHT = 0.1, 0.03, 0.03
E, DENSITY, GRAVITY, TIP_LOAD = 263824.0, 1070.0, 9.81, 0.1
NUS = (0.3, 0.45, 0.49, 0.499)
ELEMENTS = ("linear", "nodal")
LOADS = ("gravity", "tip")
#: gmsh element sizes (m): 641, 1732 and 3614 vertices
SIZES = (0.006, 0.004, 0.003)
#: reference cells along the beam (0.3 of them across)
REFERENCE_CELLS = (20, 30)
MIXED_FROM = 0.49


def reference_deflections(nu: float, cells: int) -> dict:
    """Small-deflection linear elasticity (scikit-fem) of the beam: tip deflections, m.

    Arguments:
        nu: Poisson's ratio; P2 displacements below :data:`MIXED_FROM`, Taylor-Hood P2-P1
            (pressure ``p = -lambda div u``) from it.
        cells: structured cells along the beam (``round(0.3 cells)`` across), 6 tets each.

    Returns:
        ``{"gravity": d, "tip": d}``: the mean of u_z over the tip face per load case
        (negative: downward).
    """
    import skfem
    from scipy.sparse.linalg import spsolve
    from skfem.helpers import ddot, div, sym_grad

    across = max(2, round(cells * WIDTH / LENGTH))
    mesh = skfem.MeshTet.init_tensor(np.linspace(0, LENGTH, cells + 1), np.linspace(-WIDTH / 2, WIDTH / 2, across + 1),
                                     np.linspace(-HEIGHT / 2, HEIGHT / 2, across + 1))
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    element = skfem.ElementVector(skfem.ElementTetP2())
    basis = skfem.Basis(mesh, element, intorder=4)
    tip = skfem.FacetBasis(mesh, element, facets=mesh.facets_satisfying(lambda x: x[0] > LENGTH - 1e-12), intorder=4)

    @skfem.LinearForm
    def weight(v, w):
        return -DENSITY * GRAVITY * v[2]

    @skfem.LinearForm
    def traction(v, w):
        return -TIP_LOAD / (WIDTH * HEIGHT) * v[2]

    @skfem.Functional
    def uz(w):
        return w["u"][2]

    clamp = basis.get_dofs(lambda x: x[0] < 1e-12).all()
    if nu < MIXED_FROM:
        @skfem.BilinearForm
        def stiffness(u, v, w):
            return 2 * mu * ddot(sym_grad(u), sym_grad(v)) + lam * div(u) * div(v)

        matrix, extra = stiffness.assemble(basis), 0
    else:
        pressure = skfem.Basis(mesh, skfem.ElementTetP1(), intorder=4)

        @skfem.BilinearForm
        def shear(u, v, w):
            return 2 * mu * ddot(sym_grad(u), sym_grad(v))

        @skfem.BilinearForm
        def divergence(u, q, w):
            return div(u) * q

        @skfem.BilinearForm
        def compliance(p, q, w):
            return p * q / lam

        b = divergence.assemble(basis, pressure)
        matrix = skfem.bmat([[shear.assemble(basis), -b.T], [-b, -compliance.assemble(pressure)]], "csr")
        extra = pressure.N
    # Both load cases share the condensed matrix: SuperLU factors it once and solves both
    # columns (the factorisation is most of the time; each column's figure is the one a
    # separate solve of that load gives, to the last bit).
    rhs = np.stack([np.concatenate([form.assemble(where), np.zeros(extra)])
                    for form, where in ((weight, basis), (traction, tip))], axis=1)
    condensed, _, _, inner = skfem.condense(matrix, rhs[:, 0], D=clamp)
    u = np.zeros(rhs.shape)
    u[inner] = spsolve(condensed, rhs[inner])
    return {load: float(uz.assemble(tip, u=tip.interpolate(u[:basis.N, k])) / (WIDTH * HEIGHT))
            for k, load in enumerate(LOADS)}


def beam(size: float):
    """The gmsh beam, its tip-load forces and its tip-deflection functional.

    Arguments:
        size: gmsh element size, m.

    Returns:
        ``(mesh, tip_force (n, 3), deflection)``: ``deflection(x)`` is the area-weighted
        mean of u_z over the tip face at positions ``x`` ``(n, 3)``.
    """
    from softbody.meshing.examples import cantilever

    mesh = cantilever(LENGTH, WIDTH, HEIGHT, size=size)
    faces, p = mesh.regions["tip"].faces, mesh.points
    area = 0.5 * np.linalg.norm(np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]), axis=1)
    force = np.zeros_like(p)
    for k in range(3):
        np.add.at(force[:, 2], faces[:, k], -TIP_LOAD / area.sum() * area / 3.0)

    def deflection(x):
        u = np.asarray(x)[:, 2] - p[:, 2]
        return float((area * u[faces].mean(axis=1)).sum() / area.sum())

    return mesh, force, deflection


def scene(mesh, nu: float, element: str, tol: float = 1e-9):
    """The clamped beam of one element (``"linear"`` or ``"nodal"``) at ``nu``, without
    gravity (its weight is a load case, given as forces); static solves to a relative
    residual of ``tol``.

    Returns:
        ``(model, params)`` from :func:`softbody.model.build`.
    """
    from softbody.material import Material
    from softbody.model import Options, build
    from softbody.nodal import NodalVolume
    from softbody.scene import SoftBody

    terms = [NodalVolume.on(mesh)] if element == "nodal" else []
    return build(SoftBody(mesh, Material(E=E, nu=nu, density=DENSITY), fixed="fixed", actuators=terms),
                 options=Options(tol=tol, max_iter=20000, gravity=(0.0, 0.0, 0.0)))


def _solve(mesh, force, deflection, element, nus, tol: float = 1e-9) -> list[dict]:
    """Each nu and load case of one element on one mesh (one compile: nu is a parameter),
    solved to a relative residual of ``tol``."""
    import jax.numpy as jnp

    from softbody.model import prepare
    from softbody.simulate import solve_static

    model, params = scene(mesh, nus[0], element, tol)
    out = []
    for nu in nus:
        p = params.replace(nu=jnp.asarray([nu]))
        # the weight as lumped nodal forces: P1's consistent load of a constant body force
        weight = prepare(model, p, static=True).mass * jnp.asarray([0.0, 0.0, -GRAVITY])
        for load, f in (("gravity", weight), ("tip", jnp.asarray(force))):
            start = time.perf_counter()
            x, info = solve_static(model, p, force=f, throw=False)
            out.append({"vertices": mesh.n_vertices, "element": element, "nu": nu, "load": load,
                        "deflection_m": deflection(x), "iterations": int(info.iterations),
                        "converged": bool(info.converged), "solve_s": time.perf_counter() - start})
    return out


def run(out: Path, quick: bool) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from softbody import progress

    sizes = SIZES[:1] if quick else SIZES
    cells = (10, 20) if quick else REFERENCE_CELLS
    reference = {}
    with progress.task("locking: scikit-fem references", total=len(NUS), unit="nu") as t:
        for nu in NUS:
            coarse, fine = (reference_deflections(nu, c) for c in cells)
            reference[nu] = {"element": "P2" if nu < MIXED_FROM else "P2-P1 Taylor-Hood", "cells": cells[-1],
                             **fine, "change_from_coarser": {k: abs(fine[k] / coarse[k] - 1) for k in LOADS}}
            t.advance(note=f"nu = {nu}: gravity {fine['gravity'] * 1e3:.3f} mm, tip {fine['tip'] * 1e3:.3f} mm")
    cases = []
    with progress.task("locking: softbody cases", total=len(sizes) * len(ELEMENTS), unit="cases") as t:
        for size in sizes:
            mesh, force, deflection = beam(size)
            for element in ELEMENTS:
                for case in _solve(mesh, force, deflection, element, NUS):
                    case["rel_error"] = abs(case["deflection_m"] / reference[case["nu"]][case["load"]] - 1)
                    cases.append(case)
                errors = ", ".join(f"{c['rel_error']:.3f}" for c in cases[-2 * len(NUS)::2])
                t.advance(note=f"{mesh.n_vertices} vertices, {element}: gravity errors {errors} at nu = {NUS}")
    finest = max(c["vertices"] for c in cases)
    top = [c for c in cases if c["vertices"] == finest]
    errors = {e: {str(nu): max(c["rel_error"] for c in top if c["element"] == e and c["nu"] == nu) for nu in NUS}
              for e in ELEMENTS}

    def iterations(element, nu):
        return next(c["iterations"] for c in top if c["element"] == element and c["nu"] == nu and c["load"] == "gravity")

    ratio = {e: iterations(e, 0.499) / iterations(e, 0.3) for e in ELEMENTS}

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for e, style in zip(ELEMENTS, ("s--", "o-")):
        left.plot(NUS, [100 * errors[e][str(nu)] for nu in NUS], style, label=e)
        right.plot(NUS, [iterations(e, nu) for nu in NUS], style, label=e)
    left.axhline(3.0, color="k", lw=0.8, ls=":", label="3 %")
    left.set(xlabel="Poisson's ratio", ylabel="tip deflection error, %",
             title=f"against the P2 / Taylor-Hood reference ({finest} vertices)")
    right.set(xlabel="Poisson's ratio", ylabel="L-BFGS iterations (gravity)", yscale="log",
              title="static solve, relative residual 1e-9")
    for ax in (left, right):
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "locking.png", dpi=120)
    plt.close(fig)
    return {
        "max_rel_error_vs_p2": errors,
        "iteration_ratio": ratio,
        "all_converged": all(c["converged"] for c in cases),
        "vertices": finest,
        "reference": {str(nu): r for nu, r in reference.items()},
        "cases": cases,
    }

"""Backward of the collision-response QP: the QR form against the full KKT solve.

The problems (:func:`contacts`): square cloths of ``N x N`` vertices (``N`` = 16, 32, 64;
``n = 3 N^2`` coordinates) on a unit grid in the plane, with random masses, and 3% of the
vertices (rounded, at least one) in vertex-triangle contact: each contact vertex is pressed
against a random triangle of the grid that does not hold it, along a random normal within
about 10 degrees of the plane's, at random barycentric weights. A row couples four
vertices. Each problem is built from its solution, so every contact is active with a
multiplier in [0.5, 1.5] and the timings do not depend on the forward solver: the resolved
positions ``z`` are the grid with small random offsets, ``h = -G z``, and the positions
before the response are ``x = z + W^-1 G^T lam``. Fixed seed.

Timed, each as the median of repeated calls on the same problem and upstream gradient:
:func:`softbody.contact.impact_zone.backward_kkt` (assembles and solves the dense
``(n + m) x (n + m)`` KKT system) and :func:`softbody.contact.impact_zone.backward_qr` (reduced QR of
``W^(-1/2) G^T``, ``O(n m^2)``). Reported per size: the contact count, both times, their
ratio (``speedup``), and the largest difference between the two backwards' gradients,
relative to each gradient's largest entry (``max_gradient_difference`` over all sizes).
``seed_speedup`` holds the earlier measurement's speedups for the same three sizes, kept
beside this run's for comparison (constants, not measured here). Chart: ``impact_zone.png``.

Run with ``OPENBLAS_NUM_THREADS=1`` (recorded in the figures): on the 2-core machine it was
written on, two BLAS threads made the 64x64 QR backward ten times slower (0.6 s against
0.06 s) and a dense 4000 x 4000 solve twice as slow.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

SIZES = (16, 32, 64)
CONTACT_FRACTION = 0.03
SEED_SPEEDUP = [25, 112, 64]


def contacts(N: int, rng: np.random.Generator):
    """A cloth's collision-response problem with every contact active.

    Arguments:
        N: vertices per side (``N^2`` vertices, ``n = 3 N^2`` coordinates), at least 2.
        rng: the random generator.

    Returns:
        ``(x, w, G, h, z, lam)``: the problem (``(n,)``, ``(n,)``, ``(m, n)``, ``(m,)``) and
        its solution (``(n,)``, ``(m,)``), ``m`` = 3% of the vertices.
    """
    ij = np.stack(np.meshgrid(np.arange(N), np.arange(N), indexing="ij"), -1).reshape(-1, 2)
    vertices = N * N
    quads = (ij[:, 0] < N - 1) & (ij[:, 1] < N - 1)
    corner = np.flatnonzero(quads)
    triangles = np.concatenate([np.stack([corner, corner + N, corner + 1], 1),
                                np.stack([corner + 1, corner + N, corner + N + 1], 1)])
    m = max(1, round(CONTACT_FRACTION * vertices))
    pressed = rng.choice(vertices, m, replace=False)
    G = np.zeros((m, 3 * vertices))
    for row, p in enumerate(pressed):
        candidates = triangles[~np.any(triangles == p, axis=1)]
        triangle = candidates[rng.integers(len(candidates))]
        normal = np.array([*rng.normal(scale=0.1, size=2), 1.0])
        normal /= np.linalg.norm(normal)
        G[row, 3 * p:3 * p + 3] = -normal  # thickness - normal . (z_p - sum_j beta_j z_j) <= 0
        for vertex, beta in zip(triangle, rng.dirichlet(np.ones(3))):
            G[row, 3 * vertex:3 * vertex + 3] += beta * normal
    w = np.repeat(rng.uniform(0.5, 1.5, vertices) / vertices, 3)
    z = np.concatenate([ij / (N - 1), np.zeros((vertices, 1))], 1).ravel()
    z = z + rng.normal(scale=0.01 / N, size=z.size)
    lam = rng.uniform(0.5, 1.5, m) / vertices
    return z + (G.T @ lam) / w, w, G, -G @ z, z, lam


def _median_time(function, args, repeats: int) -> tuple[float, object]:
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = function(*args)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), result


def run(out: Path, quick: bool) -> dict:
    from softbody.contact.impact_zone import backward_kkt, backward_qr

    sizes, repeats = (SIZES[:1], 3) if quick else (SIZES, 5)
    rng = np.random.default_rng(0)
    n_contacts, kkt_s, qr_s, differences = [], [], [], []
    from softbody import progress

    for N in progress.track(sizes, "impact-zone: cloth sizes", note=lambda N: f"{N}x{N}"):
        x, w, G, h, z, lam = contacts(N, rng)
        args = (x, w, G, h, z, lam, rng.normal(size=x.size))
        t_kkt, kkt = _median_time(backward_kkt, args, repeats)
        t_qr, qr = _median_time(backward_qr, args, repeats)
        n_contacts.append(len(lam))
        kkt_s.append(t_kkt)
        qr_s.append(t_qr)
        differences.append(max(float(np.abs(a - b).max() / np.abs(a).max())
                               for a, b in zip(kkt, qr)))
    speedup = [k / q for k, q in zip(kkt_s, qr_s)]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [f"{N}x{N}" for N in sizes]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    a.semilogy(labels, kkt_s, "o-", label="full KKT solve (dense)")
    a.semilogy(labels, qr_s, "s-", label="QR form")
    a.set_xlabel("cloth vertices")
    a.set_ylabel("backward time (s, median)")
    a.set_title("collision-response backward")
    a.legend()
    a.grid(True, which="both", alpha=0.3)
    at = np.arange(len(sizes))
    b.bar(at - 0.2, speedup, 0.4, label="this run")
    b.bar(at + 0.2, SEED_SPEEDUP[:len(sizes)], 0.4, label="earlier measurement", color="grey")
    b.set_xticks(at, labels)
    b.set_xlabel("cloth vertices")
    b.set_ylabel("KKT time / QR time")
    b.set_title(f"speedup ({', '.join(map(str, n_contacts))} contacts)")
    b.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(Path(out) / "impact_zone.png", dpi=120)
    plt.close(fig)
    return {"repeats": repeats, "max_gradient_difference": max(differences), "sizes": list(sizes),
            "n_contacts": n_contacts, "kkt_backward_s": kkt_s, "qr_backward_s": qr_s,
            "speedup": speedup, "seed_speedup": SEED_SPEEDUP,
            "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS")}

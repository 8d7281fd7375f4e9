"""Bodies touching bodies: contact rows between the surfaces of two bodies.

``Touch("cube", "slab", mu_s=0.5, mu_k=0.4)`` in ``build(rows=[...])`` keeps every
surface vertex of each body out of the other body's surface, with dry friction and
restitution, in the same implicit step and contact iteration as the obstacles
(:class:`softbody.contact.Contact`). Its rows are vertex-triangle rows
(:class:`~softbody._interfaces.PairFrame`): each couples a surface vertex ``p`` of one
body with a triangle ``(a, b, c)`` of the other's surface, its gap the distance of ``p``
above the triangle's plane less the contact ``thickness``::

    phi = n . (x_p - x_a) - thickness,      n the triangle's outward unit normal

and its force acts on ``p`` along ``+n`` and on the triangle's vertices along ``-n``,
distributed by the barycentric coordinates of ``p``'s projection (clamped to the
triangle): the row's weights are ``(1, -u, -v, -w)``.

**Two passes.** The vertices of the finer surface (shorter mean edge) meet the coarser
one's triangles at the thickness; the coarser one's vertices meet the finer one's
triangles at half the thickness. Both at the full thickness over-constrain flat contact
where vertices of the two surfaces coincide (the rows become redundant: a cube resting on
a slab took over 5000 iterations a step instead of 59-145); at half of it the second pass
stays idle in flat contact and catches an edge or corner of the coarser body pressing into
the finer one's face. Its cost: where only that pass supports a body (a box standing on
the edge of the one below it), the body rests half a thickness lower there.

**Which rows.** Once per step (:meth:`Touch.select`, not differentiated: a step's
contact set is fixed), each surface vertex is paired with the triangle of the other body
nearest to it at the step's predicted end (the distance to the triangle's closest point:
its interior, an edge or a corner; where several are as near, their common edge or corner
being the nearest, the one the vertex lies most squarely over, so that a vertex below a
box's bottom edge meets the bottom and not the side whose plane passes through it, and a
vertex just past a box's top edge still meets the top); a vertex whose straight path
from the step's start to its predicted end crosses a triangle from its outer side meets
the first one it crosses instead, however far beyond it the path ends (so a fast body
meets the near face of a thin one, not the far face it would end nearest). A triangle its path
does not cross counts only where the vertex lies in front of its plane, or behind it by at most
the thickness, at the step's start and at its predicted end: the row's plane, extended, would
otherwise hold the vertex where its path never meets the other body (a 2 cm cube thrown at
10 m/s at a held 5 mm plate at ``dt = 1/60`` s, predicted 8 cm beyond it: the plate's vertices
around it would meet its top and side faces, 90 of its 124 rows holding it below the plate where
it lands on it). The row is kept where that
distance is below the reach of the step's motion (the thickness plus twice the largest motion of
the vertex and the triangle's vertices from the step's start to its predicted end), so a
row exists wherever the step could bring the two together. The gap is then a smooth
function of the positions over the step: the triangle's plane, extended beyond its edges
(a vertex sliding off one triangle onto its neighbour in the same plane stays supported
for the step). The candidates come from a broad phase over the step's swept boxes
(:mod:`softbody.contact.broad_phase`: a hashed grid, cost linear in the surfaces' sizes) with a
fixed capacity; a step that overflows it ends with ``RESULTS.overflow``, never with
contacts silently lost.

**Edge-edge rows.** Two sharp edges crossing each other between their vertices (a box
standing across the edge of another, two cubes set off diagonally on each other) are
seen by no vertex-triangle row. Each surface edge of the finer bodies is paired with the
edge of a coarser body nearest to it at the step's predicted end whose closest points lie
inside both edges at the step's start and at its predicted end (nearer an end, the vertex
rows hold the contact) and that is not nearly parallel to it (squared sine of their angle
above ``_EDGE_PARALLEL``), kept where within reach as for vertex rows. The row's normal is the edges' common normal
``cross(b - a, d - c)``, on the side the edge lies at the step's start; its gap, the
distance of the two lines along it less half the thickness::

    phi = n . ((a + s (b - a)) - (c + t (d - c))) - thickness / 2

with ``s, t`` the closest points' parameters at the current positions (the gap does not
depend on them: ``n`` is normal to both edges); its weights ``(1 - s, s, t - 1, -t)``, so
the force acts at the closest points of the step's solution and the step's derivative
follows them. (Held at their values at the step's predicted end, they made
d(final position)/d(mu_k, v0) of a cube sliding across a ridge 0.36% and 0.15% off central
differences; 2e-5 and 2e-6 now.) At half the
thickness the rows stay idle in flat contact (the faces rest a full thickness apart) and
hold where only edges meet. They are opt-in, ``Touch(..., edges=True)``: where soft faces
press on each other's edges they can slow the contact iteration down (the 2 mm shifted
stack of soft cubes of ``softbody bench contact-pairs`` stopped at its 10000-iteration cap
in one step with them; its broad-phase share rose from 0.15 to 0.24).

**Self-contact.** ``Touch("fork", self_contact=True)`` keeps a body's surface out of
itself: its vertices meet its own triangles as another body's (half the thickness), with
three rules that keep a surface from meeting its own neighbourhood: a vertex never meets a
triangle nearer than half a mean surface edge at rest (``_SELF_EXCLUSION``; its own
triangles never), only one it lies in front of at the step's start (not the far wall of
its own body behind it) and only one it lies over at the predicted end (its projection
inside the triangle, so the coplanar triangles of its own face never count). The
tunnelling check searches the surface against itself too. Limits: no edge-edge rows within
a body; two folds of one surface at rest nearer than the exclusion distance never meet.

**Rigid bodies.** Either body may be a :class:`~softbody.rigid.RigidBody` (or a soft body
with bones): its vertices move with its coordinates, so a row's force on them enters the
reduced coordinates' sweep, its compliance there is the part's Delassus diagonal shared
among the rows on the part, and each iteration runs several Jacobi sweeps of the rows
(:attr:`softbody.skeleton.Reduced.pair_sweeps`), the part responding to each (rows on one
rigid part couple through its motion; on a 2 cm rigid box resting on a soft slab, 10
sweeps took a median 518 iterations a step, 30 took 175, 100 took 96, 30 the fastest).
After each sweep the part's obstacle forces (its skin's) take one update too, so that a
rigid box on the ground under a soft body relaxes both sets of rows together (a 1 cm soft
cube resting on a 2 cm rigid cube on the ground: 50-58 iterations a step, 80-115 with the
skin's forces held during the sweeps).

**Several bodies.** ``Touch("a", "b", "c", ...)`` runs one broad phase over all the named
surfaces (body groups: pairs within one body are never candidates), gives each surface
vertex one row with the nearest triangle of another body, and keeps it at the full
thickness where its body's surface is the finer of the two (the earlier named on a tie),
else at half of it: for two bodies, the two passes above. Its cost grows with the
surfaces' total size (256 cubes dropped onto each other: ``softbody bench many-bodies``).

Limits of this version (refused by :func:`softbody.model.build` or by :class:`Touch`):
one row per vertex and per edge (a vertex wedged
between two other bodies is held out of the nearer one only). **Tunnelling**:
the row choice above stops a vertex at the first triangle its path crosses (a block thrown
at 3 m/s onto a 1 cm slab at ``dt = 0.01`` s, 3 cm a step, stops on it; it passed through
before), and after each step a continuous collision check of the step's straight-line
motion (:meth:`Touch.crossed`, :mod:`softbody.contact.ccd`) counts the vertex-triangle
and edge-edge pairs of the two surfaces that met during it: a step where one did (edges
crossing between vertices, a search that overflowed) ends with ``RESULTS.tunnelled``,
never silently. **Fast impacts**: a step whose predicted end lies deep inside another body
starts its contact iteration where each body's first contact of the step closes
(:func:`softbody.contact.solver._first_touch`), not at that end. A 2 cm soft cube (27
vertices, E = 1e6 Pa) thrown at 10 m/s at a held 5 mm plate at ``dt = 1/60`` s, 16.7 cm a step,
stops on the plate's near side with every step converged (tol 1e-8; 1241 iterations in the
impact step, at most 2961 in the steps after it; it did not converge in 30000 when the
iteration started from the predicted end). Limits: thrown at 30 degrees from the normal
(friction 0.5) its impact step still stops at the cap (a relative residual of about 1e-2
after 60000 iterations), and so does a 2 cm rigid cube thrown normally at 10 m/s (no vertex
enters or passes the plate in the 3 steps measured; at 1 m/s without friction its impact
step converges in 281 iterations). Each such step
says so (``RESULTS.max_iterations``).

**Friction on rigid parts.** A row meets one friction cone a step: the kinetic one where it
slides at the step's start, else the static one (:data:`softbody.contact.law.SLIDING_SPEED`).
Tested static first and then sliding on the kinetic cone within a step, the rows on one
rigid part flipped between sticking and sliding without end: a 2 cm rigid cube dropped
1 cm onto another on the ground (mu_s = 0.5, mu_k = 0.4) stopped at the 3000-iteration cap
in its impact step, and takes 15 iterations with one cone. With mu_s = 0.5, mu_k = 0.4 and
tol 1e-8, a 1 cm soft cube dropped 5 mm onto a 2 cm rigid cube on the ground takes at
most 675 iterations a step, a 2 cm rigid cube dropped onto a 2 cm soft one 279. Limit:
a rigid body's impact on a stiff soft surface converges slowly, friction or not: the
2 cm box dropped from 2 cm onto the 10 x 4 x 1 cm slab of the tests (E = 1e6 Pa, 1 cm
elements, dt = 0.01 s, tol 1e-8) stops at the 3000 cap in its impact step, unconverged
with friction (0.5 / 0.4, or 0.5 / 0.5); without friction the step's second attempt (with
the rows of the first one's end) converges in 100 more.
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from softbody.contact import broad_phase, ccd
from softbody._interfaces import PairFrame, PairRows
from softbody._types import SceneError

__all__ = ["Touch", "every_pair"]

# the default capacity of the broad phase per pass: candidate triangles per surface vertex
_CANDIDATES_PER_VERTEX = 64
#: the tunnelling check's candidates per surface vertex and per surface edge (see Touch.crossed)
_CROSSING_CANDIDATES_PER_VERTEX = 4
#: the tunnelling check's second search, where the first overflows, is this many times larger
_CROSSING_RETRY = 16
#: edge rows need their closest points this far inside both edges (fraction of each edge):
#: nearer an end, the vertex rows hold the contact
_EDGE_END = 1e-3
#: edge rows need edges at an angle whose squared sine exceeds this (about 1.8 degrees):
#: nearly parallel edges have no well-defined common normal
_EDGE_PARALLEL = 1e-3
#: self-contact: a body's vertex never meets its own triangles nearer than this many mean
#: surface edges at rest
_SELF_EXCLUSION = 0.5
#: self-contact: a vertex meets its own body's triangle only where its projection lies
#: inside it (barycentric coordinates above minus this)
_SELF_OVER = 1e-6


def _closest(p, a, b, c):
    """Barycentric coordinates ``(..., 3)`` of the point of the triangle ``(a, b, c)`` closest
    to ``p`` (each ``(..., 3)``): its interior, an edge or a corner (Ericson's regions)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = jnp.sum(ab * ap, -1), jnp.sum(ac * ap, -1)
    bp, cp = p - b, p - c
    d3, d4 = jnp.sum(ab * bp, -1), jnp.sum(ac * bp, -1)
    d5, d6 = jnp.sum(ab * cp, -1), jnp.sum(ac * cp, -1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2

    def ratio(num, den):
        return num / jnp.where(den == 0, 1.0, den)

    one, zero = jnp.ones_like(d1), jnp.zeros_like(d1)
    inside = ratio(1.0, va + vb + vc)
    out = jnp.stack([1.0 - (vb + vc) * inside, vb * inside, vc * inside], -1)  # the interior
    t = ratio(d4 - d3, (d4 - d3) + (d5 - d6))  # edge bc
    out = jnp.where(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0))[..., None], jnp.stack([zero, 1 - t, t], -1), out)
    t = ratio(d2, d2 - d6)  # edge ac
    out = jnp.where(((vb <= 0) & (d2 >= 0) & (d6 <= 0))[..., None], jnp.stack([1 - t, zero, t], -1), out)
    t = ratio(d1, d1 - d3)  # edge ab
    out = jnp.where(((vc <= 0) & (d1 >= 0) & (d3 <= 0))[..., None], jnp.stack([1 - t, t, zero], -1), out)
    out = jnp.where(((d6 >= 0) & (d5 <= d6))[..., None], jnp.stack([zero, zero, one], -1), out)  # corner c
    out = jnp.where(((d3 >= 0) & (d4 <= d3))[..., None], jnp.stack([zero, one, zero], -1), out)  # corner b
    return jnp.where(((d1 <= 0) & (d2 <= 0))[..., None], jnp.stack([one, zero, zero], -1), out)  # corner a


def _side(p, tri):
    """The signed distance ``(...)`` of the points ``p`` ``(..., 3)`` from the planes of the
    triangles ``tri`` ``(..., 3, 3)``, positive on the side their normals point to."""
    return jnp.sum((p - tri[..., 0, :]) * _normal(*(tri[..., i, :] for i in range(3))), -1)


def _crossing(p0, p1, tri0, tri1, d0, d1):
    """Where the point moving from ``p0`` to ``p1`` ``(..., 3)`` crosses the triangle moving
    from ``tri0`` to ``tri1`` ``(..., 3, 3)`` from its outer side (the side its normal points
    to) to its inner side: the fraction ``s`` of the step ``(...)``, in ``[0, 1)``, or 1
    where it does not. The plane is taken at the step's start and end, ``d0`` and ``d1`` the
    point's signed distances from it there (:func:`_side`), interpolated linearly between
    them (exact for a triangle that translates); the crossing point must lie in the triangle
    interpolated to ``s`` (with a margin of 1e-9 in barycentric coordinates)."""
    through = (d0 >= 0) & (d1 < 0)
    s = jnp.clip(d0 / jnp.where(through, d0 - d1, 1.0), 0.0, 1.0)
    at = tri0 + s[..., None, None] * (tri1 - tri0)
    bary = _barycentric(p0 + s[..., None] * (p1 - p0), at[..., 0, :], at[..., 1, :], at[..., 2, :])
    inside = jnp.all(bary >= -1e-9, axis=-1)
    return jnp.where(through & inside, jnp.minimum(s, 1.0 - 1e-12), 1.0)


def _edge_closest(a, b, c, d):
    """The closest points of the lines through the edges ``(a, b)`` and ``(c, d)`` (each
    ``(..., 3)``): their parameters ``st`` ``(..., 2)`` along each edge (0 at ``a``, ``c``),
    the distance of the segments' points at those parameters clamped to ``[0, 1]``
    ``(...)``, and the squared sine of the edges' angle ``(...)`` (0: parallel)."""
    d1, d2, w = b - a, d - c, a - c
    aa, ee, bb = jnp.sum(d1 * d1, -1), jnp.sum(d2 * d2, -1), jnp.sum(d1 * d2, -1)
    cc, ff = jnp.sum(d1 * w, -1), jnp.sum(d2 * w, -1)
    den = aa * ee - bb**2
    sin2 = den / jnp.where(aa * ee > 0, aa * ee, 1.0)
    safe = jnp.where(den > 0, den, 1.0)
    s, t = (bb * ff - cc * ee) / safe, (aa * ff - bb * cc) / safe
    gap = w + jnp.clip(s, 0, 1)[..., None] * d1 - jnp.clip(t, 0, 1)[..., None] * d2
    return jnp.stack([s, t], -1), jnp.linalg.norm(gap, axis=-1), sin2


def _normal(a, b, c):
    """The unit normals ``(..., 3)`` of the triangles ``(a, b, c)`` (right-hand rule)."""
    normal = jnp.cross(b - a, c - a)
    return normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)


def _barycentric(p, a, b, c):
    """Barycentric coordinates ``(u, v, w)`` ``(..., 3)`` of the projection of ``p`` onto the
    plane of the triangle ``(a, b, c)`` (each ``(..., 3)``); unclamped."""
    e1, e2, d = b - a, c - a, p - a
    d00, d01, d11 = jnp.sum(e1 * e1, -1), jnp.sum(e1 * e2, -1), jnp.sum(e2 * e2, -1)
    d20, d21 = jnp.sum(d * e1, -1), jnp.sum(d * e2, -1)
    denom = d00 * d11 - d01**2
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    return jnp.stack([1.0 - v - w, v, w], axis=-1)


class Touch(PairRows):
    """Contact with dry friction between the surfaces of two or more bodies of a scene (soft
    or rigid).

    ``Touch("block", "slab")`` keeps the two apart; ``Touch("a", "b", "c", ...)`` keeps every
    named body out of every other one with one broad phase over all their surfaces, so its
    cost grows with the surfaces' total size, not with the number of pairs (where
    :func:`every_pair` makes one generator, and one search, per pair). Each surface vertex
    gets one row, with the nearest triangle of any other named body (a vertex wedged
    between two other bodies is held out of the nearer one only); a row keeps its vertex at
    the full thickness from the triangle where the vertex's body is the finer of the two
    (shorter mean surface edge; the earlier named on a tie), else at half of it (see the
    module docstring: for two bodies these are its two passes).

    Arguments:
        bodies: two or more distinct body names (``SoftBody(..., name=...)``), or one with
            ``self_contact=True``.
        mu_s: static friction coefficient (>= 0).
        mu_k: kinetic friction coefficient (``0 <= mu_k <= mu_s``; default ``mu_s``).
        restitution: coefficient of restitution in [0, 1] (0: the bodies stay together
            after an impact).
        thickness: the contact distance, m (> 0): a vertex rests this far above the
            other surface.
        self_contact: ``True`` (every named body), or a tuple of the named bodies, that
            also touch themselves (a fork closing on itself, a tube squashed until its inner
            walls meet): their vertices meet their own triangles too, away from their
            neighbours (see the module docstring). ``Touch("tube", self_contact=True)``
            names one body.
        edges: edge-edge rows besides the vertex-triangle rows (default off): each surface
            edge of a finer body against the nearest crossing edge of a coarser one (see the
            module docstring); for sharp edges that meet between vertices (rigid boxes).
        capacity: the most candidate (vertex, triangle) pairs the broad phase
            (:func:`softbody.contact.broad_phase.candidates`) holds per step for each body's
            vertices (static; the search holds ``capacity * len(bodies)``; default 64 per
            surface vertex; the box tests' budget is 4 times it; the edge rows' search holds
            as many (edge, edge) pairs per surface edge as this holds per surface vertex; the
            tunnelling check, :meth:`crossed`, holds this many of each, by default 4 per
            surface vertex and per surface edge, 64 where that overflows). A step that
            finds more ends with the result code ``RESULTS.overflow`` (a rollout raises,
            naming this fix).

    The friction coefficients, restitution and thickness are the generator's parameters
    (``params.rows[i]``, a dict with those keys): differentiable.

    Raises:
        SceneError: fewer than two names (one without self-contact), a name that is not a
            string, a body named twice, a self-contact body not among the names, bad
            coefficients.
    """

    def __init__(self, *bodies: str, mu_s: float = 0.5, mu_k: float | None = None, restitution: float = 0.0,
                 thickness: float = 1e-3, capacity: int | None = None, edges: bool = False,
                 self_contact: bool | tuple = False):
        for name in bodies:
            if not isinstance(name, str) or not name:
                raise SceneError(f"Touch takes body names (strings), got {name!r}")
        if len(set(bodies)) != len(bodies):
            raise SceneError(f"Touch{tuple(bodies)} names one body twice: for contact within a body "
                             "(self-contact) name it once with self_contact=True")
        if isinstance(self_contact, bool):
            selves = tuple(bodies) if self_contact else ()
        elif isinstance(self_contact, (tuple, list)) and all(name in bodies for name in self_contact):
            selves = tuple(self_contact)
        else:
            raise SceneError(f"Touch.self_contact is True, False or a tuple of the named bodies {list(bodies)}, got "
                             f"{self_contact!r}")
        if len(bodies) < 1 or (len(bodies) < 2 and not selves):
            raise SceneError(f"Touch takes two or more body names, got {list(bodies)}; for contact within one body "
                             "(self-contact) pass self_contact=True")
        if capacity is not None and (int(capacity) != capacity or capacity < 1):
            raise SceneError(f"Touch.capacity must be a whole number of candidate pairs >= 1 or None, got "
                             f"{capacity!r}")
        self.bodies = tuple(bodies)
        self.mu_s, self.mu_k = mu_s, mu_s if mu_k is None else mu_k
        self.restitution, self.thickness, self.capacity = restitution, thickness, capacity
        self.edges = bool(edges)
        self.self_contact = selves
        # bound to a scene by bind(): the surface vertices of the bodies, finer surfaces
        # first (_Bound)
        self._scene = None
        self.check(self.init_params())

    def __repr__(self):
        names = ", ".join(repr(b) for b in self.bodies)
        return (f"Touch({names}, mu_s={self.mu_s}, mu_k={self.mu_k}, restitution={self.restitution}, "
                f"thickness={self.thickness}, capacity={self.capacity}, edges={self.edges}, "
                f"self_contact={self.self_contact})")

    @property
    def first(self) -> str:
        """The first body's name."""
        return self.bodies[0]

    @property
    def second(self) -> str:
        """The second body's name (the first's for a body touching itself alone)."""
        return self.bodies[1] if len(self.bodies) > 1 else self.bodies[0]

    def init_params(self):
        return {"mu_s": jnp.asarray(float(self.mu_s)), "mu_k": jnp.asarray(float(self.mu_k)),
                "restitution": jnp.asarray(float(self.restitution)), "thickness": jnp.asarray(float(self.thickness))}

    def contact_distance(self, params):
        """The contact thickness (see :meth:`~softbody._interfaces.PairRows.contact_distance`)."""
        return params["thickness"]

    def check(self, params) -> None:
        try:
            values = {k: params[k] for k in ("mu_s", "mu_k", "restitution", "thickness")}
        except (KeyError, TypeError):
            raise SceneError(f"Touch parameters are a dict with keys mu_s, mu_k, restitution, thickness; got "
                             f"{params!r}") from None
        if any(isinstance(v, jax.core.Tracer) for v in values.values()):
            return
        mu_s, mu_k, e, thickness = (float(np.asarray(values[k])) for k in ("mu_s", "mu_k", "restitution",
                                                                           "thickness"))
        names = ", ".join(repr(b) for b in self.bodies)
        if not (0 <= mu_k <= mu_s):
            raise SceneError(f"Touch({names}): friction needs 0 <= mu_k <= mu_s, got mu_s={mu_s}, mu_k={mu_k}")
        if not 0 <= e <= 1:
            raise SceneError(f"Touch({names}): restitution must lie in [0, 1], got {e}")
        if not thickness > 0:
            raise SceneError(f"Touch({names}): thickness must be a distance > 0 (m), got {thickness}")

    def bind(self, mesh, parts) -> Touch:
        by_name = {part.name: part for part in parts}
        for name in self.bodies:
            if name not in by_name:
                raise SceneError(f"Touch names body {name!r}, which is not in the scene; its bodies are "
                                 f"{sorted(str(p.name) for p in parts)}")
        faces = [np.asarray(mesh.regions[name].faces, np.int64) for name in self.bodies]
        spacing = [np.mean(np.linalg.norm(mesh.points[f] - mesh.points[np.roll(f, 1, axis=1)], axis=-1))
                   for f in faces]
        order = sorted(range(len(faces)), key=lambda i: (spacing[i], i))  # finer surfaces first
        bound = copy.copy(self)
        selves = [rank for rank, i in enumerate(order) if self.bodies[i] in self.self_contact]
        bound._scene = _Bound.of([faces[i] for i in order], mesh.n_vertices, self.edges, selves,
                                 mesh.points, [_SELF_EXCLUSION * spacing[i] for i in order])
        return bound

    @property
    def size(self) -> int:
        return 0 if self._scene is None else len(self._scene.points) + len(self._scene.edge_rows)

    def vertices(self):
        """The surfaces' vertices, ``(k,)`` ints (see :meth:`PairRows.vertices`)."""
        return np.unique(self._bound().points)

    def _bound(self) -> _Bound:
        if self._scene is None:
            raise SceneError("Touch is used before build bound it to a scene: pass it in build(rows=[...])")
        return self._scene

    def select(self, x_start, x_end, params):
        """Per surface vertex, the triangle of another body nearest to it at ``x_end``
        among the broad phase's candidates, and whether it is within reach (see the module
        docstring).

        Returns:
            ``((triangles (P, 3) int, valid (P,) bool), overflow)``: ``overflow`` (bool) where
            the search found more candidates than its capacity (some rows may be missing).
        """
        scene = self._bound()
        verts, faces = scene.points, scene.faces
        motion = jnp.linalg.norm(x_end - x_start, axis=-1)
        # boxes grow by half the largest reach, so a pair within reach always overlaps
        margin = 0.5 * params["thickness"] + 2.0 * jnp.max(motion) + 1e-9
        capacity = (self.capacity * len(self.bodies) if self.capacity else  # a surface meets its own too
                    _CANDIDATES_PER_VERTEX * (4 if scene.selves else 1) * len(verts))
        found = broad_phase.candidates(x_start, x_end, verts, faces, margin, capacity, work=4 * capacity,
                                       exclude_incident=bool(scene.selves), groups=scene.rank,
                                       allowed=scene.allowed + tuple((r, r) for r in scene.selves))
        local = np.zeros(x_end.shape[0], np.int32)
        local[verts] = np.arange(len(verts))
        row = jnp.asarray(local)[found.vertex]  # (C,) each candidate's vertex, among verts
        p, tri = x_end[found.vertex], x_end[jnp.asarray(faces)[found.triangle]]  # (C, 3), (C, 3, 3)
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        normal = _normal(a, b, c)
        away = p - jnp.sum(_closest(p, a, b, c)[:, :, None] * tri, axis=1)  # from the closest point
        dist = jnp.linalg.norm(away, axis=-1)
        # where several triangles are as near (their common edge or corner is nearest), the
        # one that p lies most squarely over: a vertex just past a box's top edge meets the
        # top, not the side whose plane passes through it
        aligned = jnp.abs(jnp.sum(away * normal, -1)) / jnp.where(dist > 0, dist, 1.0)
        score = dist * (2.0 - jnp.where(dist > 0, aligned, 1.0))
        # a vertex whose straight path through the step crosses a triangle meets the
        # first one it crosses, from the side it came from, however far it ends beyond
        tri0, p0 = x_start[jnp.asarray(faces)[found.triangle]], x_start[found.vertex]
        d0, d1 = _side(p0, tri0), _side(p, tri)
        crossing = _crossing(p0, p, tri0, tri, d0, d1)
        # a triangle the path does not cross counts only where the vertex lies in front of
        # its plane (or behind it by at most the thickness) at the step's start and at its
        # predicted end: behind it at the start, the vertex faces the far side of the other
        # body; behind it at the end only, its path passes the triangle by, beyond its
        # edges. Either row, its plane extended, would hold the vertex where the path never
        # meets the body (a fast body's side and far faces, nearest where it ends beyond a
        # thin plate, pulled it through)
        ahead = (d0 >= -params["thickness"]) & (d1 >= -params["thickness"])
        valid = found.valid & (ahead | (crossing < 1.0)) & self._self_pairs(found, x_start, p, tri)
        score = jnp.where(valid, jnp.where(crossing < 1.0, crossing - 2.0, score), jnp.inf)
        best = jnp.full(len(verts), jnp.inf).at[row].min(score)
        tie = valid & (score == best[row])
        nearest = jnp.full(len(verts), len(faces)).at[row].min(jnp.where(tie, found.triangle, len(faces)))
        chosen = jnp.asarray(faces)[jnp.where(nearest < len(faces), nearest, 0)]  # (P, 3)
        reach = params["thickness"] + 2.0 * (motion[verts] + jnp.max(motion[chosen], axis=1)) + 1e-9
        crossed = best < -1.0  # the chosen triangle is one the vertex's path crosses
        valid = crossed | (jnp.full(len(verts), jnp.inf).at[row].min(jnp.where(tie, dist, jnp.inf)) <= reach)
        edge_rows, edge_overflow = self._select_edges(x_start, x_end, margin, motion, params)
        return jax.lax.stop_gradient((((chosen, valid), edge_rows), found.overflow | edge_overflow))

    def _self_pairs(self, found, x_start, p, tri):
        """``(C,)`` whether each candidate (vertex, triangle) may give a row: every pair of
        distinct bodies; a pair within one body (self-contact) only where the vertex lies
        farther than the body's exclusion distance from the triangle at rest (so its own and
        its neighbouring triangles never count), in front of the triangle at the step's
        start (not behind it, as a vertex is behind the far wall of its own body) and over
        it at the predicted end (its projection inside the triangle, so the coplanar
        triangles of the same face never count)."""
        scene = self._bound()
        if not scene.selves:
            return jnp.ones(found.vertex.shape, bool)
        faces = jnp.asarray(scene.faces)[found.triangle]
        same = jnp.asarray(scene.rank)[found.vertex] == jnp.asarray(scene.rank)[faces[:, 0]]
        rest = jnp.asarray(scene.rest)
        p0, t0 = rest[found.vertex], rest[faces]
        apart = jnp.linalg.norm(p0 - jnp.sum(_closest(p0, t0[:, 0], t0[:, 1], t0[:, 2])[:, :, None] * t0, axis=1), axis=-1)
        far = apart >= jnp.asarray(scene.exclusion)[jnp.asarray(scene.rank)[found.vertex]]
        s0 = x_start[faces]
        front = jnp.sum((x_start[found.vertex] - s0[:, 0]) * _normal(s0[:, 0], s0[:, 1], s0[:, 2]), -1) >= 0
        over = jnp.all(_barycentric(p, tri[:, 0], tri[:, 1], tri[:, 2]) >= -_SELF_OVER, axis=-1)
        return ~same | (far & front & over)

    def _select_edges(self, x_start, x_end, margin, motion, params):
        """Per surface edge, the edge of a coarser body (higher rank) nearest to it at
        ``x_end`` whose closest points lie inside both edges at ``x_start`` and ``x_end``
        (the vertex rows hold the ends), if within reach: ``((partner (E, 2) int, sign (E,)), overflow)``,
        ``sign`` the side (+1, -1; 0 where the edge has no row) that the edge lies on at the
        step's start along ``cross(edge, partner)``."""
        scene = self._bound()
        edges = scene.edges
        count = len(edges)
        if len(scene.edge_rows) == 0:
            return (jnp.zeros((0, 2), jnp.int32), jnp.zeros(0, x_end.dtype)), jnp.asarray(False)
        # as many candidates per surface edge as the vertex search holds per surface vertex
        per_element = self.capacity * len(self.bodies) / len(scene.points) if self.capacity else _CANDIDATES_PER_VERTEX
        capacity = int(np.ceil(per_element * count))
        pairs, _, overflow = ccd.edge_candidates(x_start, x_end, edges, margin, capacity, groups=scene.rank,
                                                 allowed=scene.allowed)
        live = pairs[:, 0] >= 0
        i, j = jnp.maximum(pairs[:, 0], 0), jnp.maximum(pairs[:, 1], 0)
        rank = jnp.asarray(scene.rank)[jnp.asarray(edges)[:, 0]]
        own = jnp.where(rank[i] <= rank[j], i, j)  # the row belongs to the finer body's edge
        other = jnp.where(rank[i] <= rank[j], j, i)
        e, f = jnp.asarray(edges)[own], jnp.asarray(edges)[other]
        st, dist, sin2 = _edge_closest(x_end[e[:, 0]], x_end[e[:, 1]], x_end[f[:, 0]], x_end[f[:, 1]])
        st0, _, sin2_0 = _edge_closest(x_start[e[:, 0]], x_start[e[:, 1]], x_start[f[:, 0]], x_start[f[:, 1]])
        # the closest points inside both edges at the step's start and its predicted end
        inside = jnp.all((jnp.minimum(st, st0) > _EDGE_END) & (jnp.maximum(st, st0) < 1.0 - _EDGE_END), axis=1) & (
            jnp.minimum(sin2, sin2_0) > _EDGE_PARALLEL)
        reach = params["thickness"] + 2.0 * jnp.max(motion[jnp.concatenate([e, f], 1)], axis=1) + 1e-9
        ok = live & inside & (dist <= reach)
        score = jnp.where(ok, dist, jnp.inf)
        best = jnp.full(count, jnp.inf).at[own].min(score)
        tie = ok & (score == best[own])
        nearest = jnp.full(count, count).at[own].min(jnp.where(tie, other, count))
        nearest = nearest[scene.edge_rows]
        has = nearest < count
        partner = jnp.asarray(edges)[jnp.where(has, nearest, 0)]
        mine = jnp.asarray(edges[scene.edge_rows])
        # the side at the step's start, along the normal the row uses (normal to both edges,
        # so any point of each line will do)
        a, b, c, d = (x_start[k] for k in (mine[:, 0], mine[:, 1], partner[:, 0], partner[:, 1]))
        side = jnp.sum(jnp.cross(b - a, d - c) * (a - c), -1)
        sign = jnp.where(has, jnp.sign(side), 0.0)
        return (partner.astype(jnp.int32), sign), overflow

    def frame(self, x, selection, params) -> PairFrame:
        scene = self._bound()
        vertices = scene.points
        ((triangles, valid), (partner, sign)), _ = selection
        # the full thickness where the vertex's surface is the finer, else half of it
        reach = jnp.where(scene.rank[vertices] < jnp.asarray(scene.rank)[triangles[:, 0]], 1.0, 0.5)
        p, a, b, c = x[vertices], x[triangles[:, 0]], x[triangles[:, 1]], x[triangles[:, 2]]
        normal = _normal(a, b, c)
        bary = jnp.clip(_barycentric(p, a, b, c), 0.0, 1.0)
        bary = bary / jnp.sum(bary, axis=-1, keepdims=True)
        phi = jnp.where(valid, jnp.sum((p - a) * normal, -1) - params["thickness"] * reach, jnp.inf)
        ones = jnp.ones(len(vertices) + len(partner))
        rows = jnp.concatenate([jnp.asarray(vertices)[:, None], triangles], axis=1)
        weights = jnp.concatenate([ones[:len(vertices), None], -bary], axis=1)
        if len(partner):  # edge-edge rows: the two edges' lines kept half a thickness apart
            mine = jnp.asarray(scene.edges[scene.edge_rows])
            a, b, c, d = x[mine[:, 0]], x[mine[:, 1]], x[partner[:, 0]], x[partner[:, 1]]
            cross = jnp.cross(b - a, d - c)
            length = jnp.linalg.norm(cross, axis=-1, keepdims=True)
            edge_normal = sign[:, None] * cross / jnp.where(length > 0, length, 1.0)
            gap = jnp.sum((a - c) * edge_normal, -1)  # normal to both lines: any of their points
            # the weights: the closest points' parameters at x (at the solution, where the force acts)
            st = jnp.clip(_edge_closest(a, b, c, d)[0], 0.0, 1.0)
            s_, t_ = st[:, 0], st[:, 1]
            phi = jnp.concatenate([phi, jnp.where(sign != 0, gap - 0.5 * params["thickness"], jnp.inf)])
            normal = jnp.concatenate([normal, edge_normal])
            rows = jnp.concatenate([rows, jnp.concatenate([mine, partner], axis=1)])
            weights = jnp.concatenate([weights, jnp.stack([1.0 - s_, s_, t_ - 1.0, -t_], axis=1)])
        return PairFrame(vertices=rows, weights=weights, phi=phi, normal=normal,
                         mu_s=params["mu_s"] * ones, mu_k=params["mu_k"] * ones,
                         restitution=params["restitution"] * ones)

    def crossed(self, x_start, x_end, params):
        """Whether the surfaces passed through each other during a step moving every vertex
        on a straight line from ``x_start`` to ``x_end`` (continuous collision detection
        between distinct bodies only, :func:`softbody.contact.ccd.tunnelled`): ``(count,
        overflow)`` (see :meth:`PairRows.crossed`). The search's buffers hold
        :attr:`capacity` vertex-triangle and as many edge-edge candidates, or by default four
        per surface vertex and four per surface edge. Bodies that move together a few
        millimetres a step while resting a millimetre apart (a pile falling, a stack
        settling) have overlapping swept boxes without crossing: where the default buffers
        overflow, the search runs once more with :data:`_CROSSING_RETRY` times their size
        (compiled beside the first, run only then), so that such a step is not reported as
        an overflow."""
        scene = self._bound()
        # a surface's own neighbouring elements are candidates of its self-contact check
        per_element = _CROSSING_CANDIDATES_PER_VERTEX * (8 if scene.selves else 1)
        n_edges = len(ccd.surface_edges(scene.faces))
        x_start, x_end = jax.lax.stop_gradient((x_start, x_end))

        def search(size):
            found = ccd.tunnelled(x_start, x_end, scene.faces, capacity=self.capacity or size * len(scene.points),
                                  edge_capacity=self.capacity or size * n_edges, groups=scene.rank,
                                  allowed=scene.allowed + tuple((r, r) for r in scene.selves))
            return found.count, found.overflow

        count, overflow = search(per_element)
        if self.capacity:
            return count, overflow
        return jax.lax.cond(overflow, lambda: search(_CROSSING_RETRY * per_element), lambda: (count, overflow))


@dataclasses.dataclass(frozen=True, eq=False)
class _Bound:
    """A :class:`Touch` on a scene: its bodies' surfaces, finer first.

    Attributes:
        points: (P,) the surface vertices, body by body (one row each, in this order).
        faces: (T, 3) the surface triangles, body by body.
        rank: (n,) each scene vertex's body among them (0 the finest), ``len(bodies)`` off them.
        allowed: the pairs of distinct bodies (ranks) that may touch: with ``rank`` as the
            groups, what the broad phase and the crossing check search.
        edges: (E, 2) the surface edges, body by body (none without edge rows).
        edge_rows: (R,) the edges (rows of ``edges``) that have an edge row: those of every
            body but the coarsest (whose edges are partners only).
        selves: the ranks of the bodies in contact with themselves.
        rest: (n, 3) the scene's rest positions (for self-contact's exclusion), or None.
        exclusion: per rank, the rest distance within which a body's own triangles never
            meet its vertices (and 0 for the vertices off the surfaces).
    """

    points: np.ndarray
    faces: np.ndarray
    rank: np.ndarray
    allowed: tuple
    edges: np.ndarray
    edge_rows: np.ndarray
    selves: tuple = ()
    rest: np.ndarray | None = None
    exclusion: tuple = ()

    @classmethod
    def of(cls, faces: list, n: int, edges: bool = True, selves=(), rest=None, exclusion=()) -> _Bound:
        rank = np.full(n, len(faces), np.int64)
        for i, f in enumerate(faces):
            rank[f.ravel()] = i
        allowed = tuple((i, j) for i in range(len(faces)) for j in range(i + 1, len(faces)))
        edge_list = np.concatenate([ccd.surface_edges(f) for f in faces]) if edges else np.zeros((0, 2), np.int64)
        # edge rows on every body's surface edges but the coarsest's (its edges are partners only)
        owners = np.flatnonzero(rank[edge_list[:, 0]] < len(faces) - 1)
        return cls(np.concatenate([np.unique(f) for f in faces]), np.concatenate(faces), rank, allowed, edge_list,
                   owners, tuple(selves), None if rest is None else np.asarray(rest, np.float64),
                   tuple(float(e) for e in exclusion) + (0.0,))


def every_pair(*names: str, **contact) -> list[Touch]:
    """Contact between every two of the named bodies: ``build(bodies, rows=every_pair("a",
    "b", "c", mu_s=0.5))`` is ``rows=[Touch("a", "b", ...), Touch("a", "c", ...), Touch("b",
    "c", ...)]``.

    Arguments:
        names: at least two distinct body names.
        contact: :class:`Touch`'s keyword arguments, the same for every pair.

    Returns:
        The :class:`Touch` of each unordered pair, in the order of ``names``.

    Raises:
        SceneError: fewer than two names, a repeated name, or what :class:`Touch` refuses.
    """
    if len(names) < 2 or len(set(names)) != len(names):
        raise SceneError(f"every_pair takes two or more distinct body names, got {list(names)}")
    return [Touch(a, b, **contact) for i, a in enumerate(names) for b in names[i + 1:]]


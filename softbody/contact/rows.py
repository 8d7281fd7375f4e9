"""The rows one contact step sees: the deepest vertex row per point (:func:`_frames`) and
the pair rows chosen at the step's start (:class:`_Pairs`)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from softbody._interfaces import Frame, PairFrame, PairRows, Rows
from softbody.contact.law import _FAR
from softbody.solvers import StepProblem


def _frames(rows, points, index, time) -> Frame:
    """Per point, the deepest of the rows that the scene's generators of vertex rows
    (:class:`~softbody._interfaces.Rows`) put on it.

    Arguments:
        rows: ``((generator, params), ...)`` of the step (:attr:`StepProblem.rows`); pair
            generators among them are not asked here (see :meth:`_Pairs.frame`).
        points: ``(m, 3)`` trial positions of the vertices ``index`` ``(m,)``; time: s.

    Returns:
        A :class:`~softbody._interfaces.Frame` of ``m`` rows; a point no generator reaches
        has a gap of ``_FAR``.
    """
    frames = [frame._replace(phi=jnp.minimum(frame.phi, _FAR))  # no row: far away, finite
              for frame in (generator.frame(points, index, params, time)
                            for generator, params in rows if isinstance(generator, Rows))]
    if not frames:  # pair rows alone
        m, zero = points.shape[0], jnp.zeros(points.shape[0], points.dtype)
        return Frame(jnp.full(m, _FAR, points.dtype), jnp.zeros_like(points), jnp.zeros_like(points), zero, zero,
                     zero)
    return Frame.deepest(frames)


class _Pairs(NamedTuple):
    """The pair rows of one step: ``((generator, params, selection), ...)`` (the selection
    made once at the step's start, :meth:`~softbody._interfaces.PairRows.select`)."""

    rows: tuple

    @staticmethod
    def select(problem: StepProblem, x_end) -> "_Pairs":
        """The rows that a step ending at ``x_end`` ``(n, 3)`` meets (not differentiated)."""
        x_end = jax.lax.stop_gradient(x_end)
        return _Pairs(tuple((generator, params, generator.select(problem.x_n, x_end, params))
                            for generator, params in problem.rows if isinstance(generator, PairRows)))

    @property
    def size(self) -> int:
        return sum(generator.size for generator, _, _ in self.rows)

    @property
    def selection(self) -> tuple:
        return tuple(selection for _, _, selection in self.rows)

    def chosen(self, selection) -> "_Pairs":
        """These generators with the selection ``selection`` (as :attr:`selection` gives)."""
        return _Pairs(tuple((g, p, s) for (g, p, _), s in zip(self.rows, selection)))

    def frame(self, x) -> PairFrame:
        """The rows' :class:`~softbody._interfaces.PairFrame` at positions ``x`` ``(n, 3)``
        (gaps clamped to ``_FAR``)."""
        frames = [generator.frame(x, selection, params) for generator, params, selection in self.rows]
        frame = PairFrame(*(jnp.concatenate(column) for column in zip(*frames)))
        return frame._replace(phi=jnp.minimum(frame.phi, _FAR))

    @property
    def overflow(self):
        """Whether some generator's search for its rows overflowed its capacity."""
        return functools.reduce(jnp.logical_or, (selection[1] for selection in self.selection), jnp.asarray(False))

    def crossed(self, x_start, x_end):
        """``(count, overflow)``: the surface pairs that met during a step from ``x_start`` to
        ``x_end`` over every generator (:meth:`~softbody._interfaces.PairRows.crossed`)."""
        count, overflow = jnp.asarray(0, jnp.int32), jnp.asarray(False)
        for generator, params, _ in self.rows:
            c, o = generator.crossed(x_start, x_end, params)
            count, overflow = count + c, overflow | o
        return count, overflow

    def gap(self, x):
        """The smallest gap of the rows at ``x`` (``_FAR`` without rows)."""
        return jnp.min(self.frame(x).phi) if self.rows else jnp.asarray(_FAR, x.dtype)


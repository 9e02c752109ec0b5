"""No chatter: :class:`JumpLimit`, the bound on how far a written point's offset from LBS
changes from one frame to the next."""

from __future__ import annotations

import numpy as np

from ..transforms import matrix_to_quat, quat_slerp, quat_to_matrix, rigid_fit
from .params import GuardParams, as_written

__all__ = ["JumpLimit"]


class JumpLimit:
    """No chatter: the offset from LBS of a written point, ``o = W - L``, changes by at most
    ``max_jump`` (:class:`GuardParams`) x the character's ``height`` [m] from one frame to the
    next. Where the result of a frame would move it farther (contacts that hold two parts of
    the body apart in one frame and let them through in the next), the change is cut to that
    length, so the point gets there over the next frames (a smooth path through the flicker):
    ``o(t) = o(t-1) + d min(1, r / |d|)``, ``d = o_guarded(t) - o(t-1)``. The first frame is
    taken as it is. Applied after the surface guard, to what is written only; where the cut
    would leave the mesh worse than the guard's result, :meth:`SurfaceGuard.keep` takes those
    points back to it (and :meth:`written` tells the limit what was written).

    A group (``groups[i] >= 0``: a piece written by one rigid motion, a shoe, a fist, a hair
    cap) is cut as a whole and stays rigid: a blend of two frames' offsets is not rigid, so its
    new placement ``W`` is reached from ``H`` (the last frame's placement carried by the group's
    own LBS motion, the best rigid fit of ``L(t-1) -> L(t)``) by the share ``c`` of the rigid
    motion ``H -> W`` (rotation by slerp), ``c`` the largest in [0, 1] (bisection, 12 steps)
    at which no point of the group jumps by more than the limit; ``c = 0`` where even ``H``
    does (the group then moves with its LBS).

    Attributes:
        limited: The share of the mesh's points cut in the last frame.
    """

    def __init__(self, height: float, params: GuardParams | None = None,
                 groups: np.ndarray | None = None) -> None:
        prm = params or GuardParams()
        self.step = float(prm.max_jump) * float(height) if prm.enabled else 0.0
        self._last: np.ndarray | None = None
        self._free = None if groups is None else np.asarray(groups) < 0
        self._groups = [] if groups is None else [np.nonzero(np.asarray(groups) == g)[0]
                                                  for g in np.unique(np.asarray(groups)[np.asarray(groups) >= 0])]
        self._last_lbs: np.ndarray | None = None
        self.limited = 0.0

    def apply(self, points: np.ndarray, lbs: np.ndarray) -> np.ndarray:
        """The limited points of one frame, ``[N, 3]`` (``points``: after the guard; ``lbs``:
        the mesh's LBS), rounded to float32 where a point was cut; ``points`` itself where
        none was."""
        p = np.asarray(points, dtype=np.float64)
        lb = np.asarray(lbs, dtype=np.float64)
        o = p - lb
        self.limited = 0.0
        if self._last is None or self.step <= 0.0:
            self._last, self._last_lbs = o, lb
            return points
        d = o - self._last
        length = np.linalg.norm(d, axis=1)
        cut = length > self.step
        if self._free is not None:
            cut &= self._free
        groups = [g for g in self._groups if length[g].max() > self.step]
        if not cut.any() and not groups:
            self._last, self._last_lbs = o, lb
            return points
        o = self._last + d * np.where(cut, self.step / np.maximum(length, 1e-300), 1.0)[:, None]
        for g in groups:
            o[g] = self._group(g, p[g], lb[g]) - lb[g]
            cut[g] = True
        self.limited = float(cut.mean())
        self._last, self._last_lbs = o, lb
        return as_written(lb + o)

    def written(self, points: np.ndarray, lbs: np.ndarray) -> None:
        """What was written of this frame after :meth:`apply` (``points``, ``lbs``: ``[N, 3]``
        [m]), where it differs from what :meth:`apply` returned: the next frame's limit counts
        from it."""
        self._last = np.asarray(points, dtype=np.float64) - np.asarray(lbs, dtype=np.float64)

    def _group(self, g: np.ndarray, target: np.ndarray, lbs: np.ndarray) -> np.ndarray:
        """The placement ``[n, 3]`` of group ``g`` this frame (see the class docstring):
        ``target`` its unlimited placement, ``lbs`` its LBS."""
        last_lbs = self._last_lbs[g]
        last = last_lbs + self._last[g]
        r, t = rigid_fit(last_lbs, lbs)
        hold = last @ r.T + t
        r2, t2 = rigid_fit(hold, target)
        centre = hold.mean(axis=0)
        q0, q1 = np.array([0.0, 0.0, 0.0, 1.0]), matrix_to_quat(r2)
        moved = (centre @ r2.T + t2) - centre  # where the fit takes the held centre

        def place(c: float) -> np.ndarray:
            rc = quat_to_matrix(quat_slerp(q0, q1, c))
            return (hold - centre) @ rc.T + centre + c * moved

        def jump(x: np.ndarray) -> float:
            return float(np.linalg.norm((x - lbs) - self._last[g], axis=1).max())

        lo, hi = 0.0, 1.0
        if jump(place(0.0)) > self.step:
            return place(0.0)
        for _ in range(12):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if jump(place(mid)) <= self.step else (lo, mid)
        return place(lo)

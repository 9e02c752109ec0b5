"""Worn pieces (garments wrapped over the simulated surface) repaired where they cross:
:class:`WornRepair`."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..metrics import PairQuery
from ..quality import WrittenMesh
from .params import GuardParams, as_written, pair_keys

__all__ = ["WornRepair"]


class WornRepair:
    """Worn pieces that cross themselves or each other, repaired where they cross: a garment
    layer is brought nearer the surface it is worn on there, keeping its shape elsewhere.

    A worn point (:mod:`warpskin.kernels.deform`'s wrap: trousers, a shirt, a hair cap) is
    written at ``P``, its rest offset from its carrier point ``C`` (the point of the simulated
    surface it rides on, at the written surface as it is now). Where the body folds (the back of
    a bent knee, an armpit), two layers of a garment, each at its own offset from its own part
    of the body, can pass through each other: a cloth would bunch up, a wrapped garment has no
    cloth of its own. Per frame, per mesh with worn points (on the host):

        W = C + s (P - C),     s = max(floor, E(E(r))),     E(r)_i = min(r_i, mean of r over i's ring)

    with ``r`` in [floor, 1] a raw share per worn point kept from frame to frame (``E`` eases
    the fold's edge over two rings of neighbours into the rest of the garment):

    1. ``r`` rises by ``recover`` (:class:`GuardParams`) from the last frame's, up to 1;
    2. the pairs of the worn triangles (every point worn) that intersect and did not at rest are
       found (the exact test of :class:`~warpskin.metrics.PairQuery`, on the welded mesh);
    3. where a point that rose this frame lies within two rings of a crossing pair's point, it
       goes back to the last frame's ``r`` (a crossing that stays settles where it was clear,
       instead of cycling between recovery and halving: a flicker); a crossing pair's point with
       none such nearby gets ``r x SHRINK``; only the triangles that moved are tested again; up
       to ``ROUNDS`` rounds.

    The floor keeps a garment off the body it is worn on: a point's rest clearance over its rest
    offset (:func:`~warpskin.character._clearance`), so that ``W`` stays that far above the
    carrier surface; a point at or under the surface at rest (a hair cap through a bun, a sheet
    sunk into its neighbour) has floor 1 and is never moved.

    Invariants: with no new pair ``W = P`` exactly (where ``r`` is 1 about a point); every
    written copy of a welded point gets the same ``s``; ``floor <= s <= r``; over frames of one
    pose ``r`` only rises where the result stays clear, so the written points settle. Limits:
    the repair takes the layers towards the body, it does not model the fold; a crossing that
    remains after ``ROUNDS`` rounds, or at the floor, is left (and counted by the quality
    measures). How much it took is :attr:`repaired` (mean of ``1 - s`` over the worn points)
    and :attr:`repaired_max`.

    Args:
        mesh: The written mesh (its welded topology).
        worn: ``[K]`` the mesh's own point indices that are worn (a garment's).
        floor: ``[K]`` the least ``s`` of each, in [0, 1] (``None``: 0).
        params: :class:`GuardParams` (``recover``; ``enabled`` false: no repair).
    """

    #: Rounds per frame.
    ROUNDS = 6
    #: The share of its offset a worn point of a crossing pair keeps per round.
    SHRINK = 0.5

    def __init__(self, mesh: WrittenMesh, worn: np.ndarray, floor: np.ndarray | None = None,
                 params: GuardParams | None = None) -> None:
        prm = params or GuardParams()
        self.recover = float(prm.recover)
        self.mesh = mesh
        n = mesh.first.size
        worn = np.asarray(worn, dtype=np.int64)
        self.worn = worn
        welded_worn = np.zeros(n, dtype=bool)
        welded_worn[mesh.weld[worn]] = True
        #: ``[n]`` the least ``s`` per welded point (the largest over its written copies).
        self.floor = np.ones(n)
        self.floor[mesh.weld[worn]] = 0.0
        f = np.zeros(worn.size) if floor is None else np.clip(np.asarray(floor, dtype=np.float64), 0.0, 1.0)
        np.maximum.at(self.floor, mesh.weld[worn], f)
        wt = mesh.welded_triangles
        self.triangles = wt[welded_worn[wt].all(axis=1)]
        self.enabled = bool(prm.enabled) and len(self.triangles) > 1
        self.r = np.ones(n)
        self.repaired = self.repaired_max = 0.0
        if not self.enabled:
            return
        self.query = PairQuery(self.triangles)
        # the mean over each welded point and its neighbours on the worn triangles
        e = np.concatenate([self.triangles[:, [0, 1]], self.triangles[:, [1, 2]], self.triangles[:, [2, 0]]])
        e = np.concatenate([e, e[:, ::-1], np.repeat(np.unique(self.triangles)[:, None], 2, axis=1)])
        e = np.unique(e, axis=0)
        adj = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        deg = np.asarray(adj.sum(axis=1)).ravel()
        self._adj, self._deg = adj, np.maximum(deg, 1.0)  # the mean: a sum over a count (exact for ones)
        self._has = deg > 0
        ring = (adj > 0).astype(np.int32)
        self._rings2 = ((ring @ ring) > 0).astype(np.int32).tocsr()  # within two rings
        count = len(self.triangles)
        self._count = count
        self._rest = pair_keys(self.query.pairs(mesh.welded(mesh.rest)), count)

    def _new(self, pairs: np.ndarray) -> np.ndarray:
        """The rows of ``pairs`` not crossing at rest."""
        if pairs.size == 0:
            return pairs.reshape(0, 2)
        keys = pairs[:, 0] * self._count + pairs[:, 1]
        return pairs[~np.isin(keys, self._rest)]

    def share(self, r: np.ndarray) -> np.ndarray:
        """``[n]`` the written share ``s`` of the raw shares ``r`` (welded points)."""
        for _ in range(2):
            r = np.where(self._has, np.minimum(r, (self._adj @ r) / self._deg), r)
        return np.maximum(r, self.floor)

    def apply(self, points: np.ndarray, carriers: np.ndarray) -> np.ndarray:
        """The repaired points of one frame, ``[N, 3]`` (``points``: the mesh's written points;
        ``carriers``: ``[K, 3]`` the carrier point of each of ``worn``, in its order);
        ``points`` itself where nothing was taken."""
        self.repaired = self.repaired_max = 0.0
        if not self.enabled:
            return points
        m = self.mesh
        p = np.asarray(points, dtype=np.float64)
        welded_worn = m.weld[self.worn]
        offset = p[self.worn] - np.asarray(carriers, dtype=np.float64)
        last = self.r
        r = np.minimum(last + self.recover, 1.0)
        s = self.share(r)
        out = p.copy()

        def place() -> np.ndarray:
            out[self.worn] = carriers + s[welded_worn][:, None] * offset
            return out[m.first]

        pairs = self._new(self.query.pairs(place()))
        for _ in range(self.ROUNDS):
            if pairs.size == 0:
                break
            hit = np.zeros(r.size, dtype=bool)
            hit[self.triangles[pairs.ravel()].ravel()] = True
            rose = r > last
            back = rose & ((self._rings2 @ hit.astype(np.int32)) > 0)  # rose near a crossing
            halve = hit & ((self._rings2 @ back.astype(np.int32)) == 0)  # crossing with no such
            r = np.where(back, last, np.where(halve, np.maximum(r * self.SHRINK, self.floor), r))
            before = s
            s = self.share(r)
            moved = s != before
            if not moved.any():
                break
            pairs = self._new(self.query.active(place(), moved[self.triangles].any(axis=1)))
        self.r = r
        taken = 1.0 - s[np.unique(welded_worn)]
        self.repaired = float(taken.mean()) if taken.size else 0.0
        self.repaired_max = float(taken.max()) if taken.size else 0.0
        if self.repaired_max <= 0.0:
            return points
        place()
        return as_written(out)

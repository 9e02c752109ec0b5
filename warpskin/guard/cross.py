"""Written meshes keep apart as their LBS keeps them: :class:`CrossGuard`."""

from __future__ import annotations

import numpy as np

from ..quality import CrossPairs
from ..transforms import matrix_to_quat, quat_slerp, quat_to_matrix, rigid_fit
from .params import GuardParams, as_written
from .surface import SurfaceGuard

__all__ = ["CrossGuard"]


class CrossGuard:
    """Written meshes keep apart as their LBS keeps them: where, after every mesh's own
    :class:`SurfaceGuard`, the triangles of two written meshes cross each other more than the
    same two meshes do under LBS (:class:`~warpskin.quality.CrossPairs`, beyond the pairs they
    cross in at rest: a robot's shin sits in its knee's socket), one of them gives way: the mesh
    of the deeper joint (then the smaller) is carried by the other's motion near it, as far as
    it must and with its joint points within ``joint_limit`` of their LBS (:meth:`_follow`);
    where it cannot be, it takes back part of its physical displacement around the crossing
    triangles through its guard's weight (:meth:`SurfaceGuard.take_back`: a smooth ramp over
    the surface, a rigid piece as a whole), and where it can give no more the other does if it
    is one rigid piece; ``rounds`` rounds of ``back_off``, then up to
    :attr:`SurfaceGuard.FALLBACK_ROUNDS` rounds to LBS. A pair of meshes is judged by its count:
    crossings that slide (a pair traded for its neighbour) are not taken back, only a net gain
    is; and then only the crossing pairs LBS does not have are flagged.

    Args:
        cross: The pair counter over every written mesh.
        guards: ``{mesh name: SurfaceGuard}`` of the meshes written with physics (the others
            are at their LBS and cannot help).
        params: :class:`GuardParams` (``enabled``, ``pairs``, ``rounds``, ``back_off``).
        depth: ``[M]`` per mesh, the depth in the skeleton of the joint that moves most of it
            (0: the root): of two meshes that cross, the deeper one moves (a hand off the arm,
            a shoulder pad off the torso), of equal depth the smaller (rest diagonal).
        joint_limit: How far [m] a mesh's points where it meets other pieces at rest
            (:attr:`~warpskin.quality.WrittenMesh.joint_points`) may be carried from their
            LBS (the ``joint_gap`` share of the diagonal).

    Attributes:
        rounds: The rounds the last frame took (0: nothing crossed beyond LBS).
        keys: ``(keys, keys_lbs)`` of the last frame's result and LBS
            (:meth:`~warpskin.quality.CrossPairs.keys_of_two`), for its measures.
    """

    def __init__(self, cross, guards: dict, params: GuardParams | None = None,
                 depth: np.ndarray | None = None, joint_limit: float = np.inf) -> None:
        self.cross = cross
        self.guards = guards
        self.params = params or GuardParams()
        self.rounds = 0
        self.keys: tuple[np.ndarray, np.ndarray] | None = None
        self.joint_limit = float(joint_limit)
        self._names = [mesh.name for mesh in cross.meshes]
        self._two: dict = {}  # per pair of meshes, the counter of that pair alone (:meth:`_follow`)
        size = np.array([mesh.size for mesh in cross.meshes])
        depth = np.zeros(len(size)) if depth is None else np.asarray(depth, dtype=np.float64)
        #: per mesh, its rank as a carrier: lower carries higher (nearer the skeleton's root,
        #: then larger)
        self._rank = np.lexsort((-size, depth)).argsort()
        #: per mesh, whether it is written as one rigid piece (its guard's one group)
        self._rigid = np.array([(g := guards.get(self._names[k])) is not None and g.group is not None
                                and np.unique(g.group).size == 1 for k in range(len(size))], dtype=bool)

    def _follow(self, out: dict, lbs: dict, small: int, large: int, allowed: np.ndarray) -> bool:
        """Mesh ``small`` (a row of ``cross.meshes``) placed by the share ``c`` in [0, 1] of the
        way from ``C`` (its LBS carried by ``large``'s motion away from its own LBS near it: for
        a rigid ``large`` the best rigid fit of its points within ``small``'s size of it, LBS to
        written; else the best rigid fit of its points moved as ``large``'s point nearest each
        at LBS) to where it is: for one rigid piece along the rigid motion between the two
        (rotation by slerp), else point by point. ``c`` is the largest (bisection, 10 steps) at which the two
        cross no more than ``allowed`` (per pair of meshes, beyond rest); at ``c = 0`` they sit
        as their LBS has them where ``large`` moves rigidly near ``small``. ``out`` updated;
        whether it was placed (``False``: a mesh without a guard, written at its LBS, or one that
        would still cross at the least ``c`` that keeps its joint points within ``joint_limit``
        [m] of their LBS, or no farther than they are)."""
        cross = self.cross
        ns, nl = self._names[small], self._names[large]
        guard = self.guards.get(ns)
        if guard is None:
            return False
        rigid = bool(self._rigid[small])
        ls, ll = np.asarray(lbs[ns], dtype=np.float64), np.asarray(lbs[nl], dtype=np.float64)
        written_l = np.asarray(out[nl], dtype=np.float64)
        if self._rigid[large]:
            lo_box, hi_box = ls.min(axis=0), ls.max(axis=0)
            reach = float(np.linalg.norm(hi_box - lo_box))
            near = np.all((ll >= lo_box - reach) & (ll <= hi_box + reach), axis=1)
            if np.count_nonzero(near) < 3:
                near[:] = True
            r, t = rigid_fit(ll[near], written_l[near])
            carried = ls @ r.T + t
        else:  # a carrier that deforms: the displacement of its nearest point (at LBS)
            from scipy.spatial import cKDTree

            idx = cKDTree(ll).query(ls)[1]
            # the best rigid motion onto that: a piecewise displacement would strain the mesh
            r, t = rigid_fit(ls, ls + (written_l - ll)[idx])
            carried = ls @ r.T + t
        now = np.asarray(out[ns], dtype=np.float64)
        r2, t2 = rigid_fit(carried, now)
        centre = carried.mean(axis=0)
        q0, q1 = np.array([0.0, 0.0, 0.0, 1.0]), matrix_to_quat(r2)
        shift = (centre @ r2.T + t2) - centre
        m = len(cross.meshes)
        pair = min(small, large) * m + max(small, large)
        two = self._two.get(pair)
        if two is None:  # the trials count the two meshes alone
            two = self._two[pair] = CrossPairs([cross.meshes[min(small, large)], cross.meshes[max(small, large)]])

        def place(c: float) -> np.ndarray:
            if not rigid:
                return as_written(carried + c * (now - carried))
            return as_written((carried - centre) @ quat_to_matrix(quat_slerp(q0, q1, c)).T + centre + c * shift)

        none = np.zeros(0, dtype=np.int64)

        def crosses(c: float) -> bool:
            # every pair of the two has a triangle of ``small``: its triangles alone query the
            # counter's tree (built at rest), refitted to the trial
            keys = two.keys({ns: place(c), nl: out[nl]}, [int(small > large)], none)
            return bool(two.beyond_rest(keys)[1] > allowed[pair])

        joints = cross.meshes[small].joint_points
        bound = np.inf
        if joints is not None and joints.size and np.isfinite(self.joint_limit):
            # the piece stays on at its joints: within the joint limit of their LBS there (or
            # no farther than they are)
            bound = max(self.joint_limit, float(np.linalg.norm(now[joints] - ls[joints], axis=1).max()))

        def off(c: float) -> bool:
            if not np.isfinite(bound):
                return False
            return float(np.linalg.norm(place(c)[joints] - ls[joints], axis=1).max()) > bound

        lo = 0.0
        if off(lo):  # the least share that keeps the joints on
            hi = 1.0
            for _ in range(10):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if off(mid) else (lo, mid)
            lo = hi
        if crosses(lo) or off(lo):
            return False
        hi = 1.0
        for _ in range(10):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if not (crosses(mid) or off(mid)) else (lo, mid)
        out[ns] = place(lo)
        return True

    def _take_back(self, out: dict, new: np.ndarray, mover: np.ndarray, fallback: bool) -> list[int]:
        """One round of :meth:`SurfaceGuard.take_back` on the meshes ``mover`` (``[K]``, per
        crossing pair ``new``: the mesh of it that moves), their triangles of those pairs
        flagged; ``out`` updated. The meshes (their rows) in which a point moved."""
        cross = self.cross
        t = len(cross.triangles)
        tri = np.concatenate([new // t, new % t])
        tri = tri[cross.label[tri] == np.concatenate([mover, mover])]
        moved = []
        for k in np.unique(cross.label[tri]):
            guard = self.guards.get(self._names[int(k)])
            if guard is None:
                continue
            own = tri[cross.label[tri] == k] - cross.triangle_offsets[k]
            flag = np.zeros(guard.count, dtype=bool)
            flag[guard.mesh.welded_triangles[own].ravel()] = True
            pts = guard.take_back(flag, fallback=fallback)
            if pts is not None:
                out[self._names[int(k)]] = pts
                moved.append(int(k))
        return moved

    def apply(self, written: dict, lbs: dict) -> dict:
        """``written`` (``{mesh name: [N, 3]}``, every mesh of ``cross``, each after its guard)
        with the crossings between meshes beyond LBS's taken back; ``lbs`` the same meshes'
        LBS. Returns a new dict (the meshes not changed are the same arrays)."""
        self.rounds = 0
        out = dict(written)
        cross = self.cross
        if not cross.active or not self.params.enabled or not self.params.pairs:
            self.keys = None
            return out
        keys, keys_lbs = cross.keys_of_two(out, lbs)
        allowed = cross.beyond_rest(keys_lbs)
        lbs_set = keys_lbs
        t = len(cross.triangles)
        m = len(cross.meshes)
        last = self.params.rounds + SurfaceGuard.FALLBACK_ROUNDS
        while self.rounds <= last:
            over = cross.beyond_rest(keys) > allowed
            if not over.any():
                break
            new = keys[~np.isin(keys, lbs_set)]
            a, b = cross.label[new // t], cross.label[new % t]
            pick = over[np.minimum(a, b) * m + np.maximum(a, b)]
            new, a, b = new[pick], a[pick], b[pick]
            fallback = self.rounds >= self.params.rounds
            # of each pair the mesh farther from the skeleton's root (then the smaller) moves: a
            # rigid piece is carried by its neighbour's motion (a shoulder pad on the torso it
            # sits on), as far as needed; a mesh that deforms takes back its displacement there,
            # the other where it can no longer move
            small = np.where(self._rank[a] > self._rank[b], a, b)
            large = np.where(small == a, b, a)
            moved = []
            carried = np.zeros(new.size, dtype=bool)
            for s_, l_ in {(int(u), int(v)) for u, v in zip(small, large)}:
                if self._follow(out, lbs, s_, l_, allowed):
                    moved.append(s_)
                    carried |= (small == s_) & (large == l_)
            rest = ~carried
            if rest.any():
                moved += self._take_back(out, new[rest], small[rest], fallback)
                # where that mesh can give no more, the other, if it moves as one rigid piece
                # (a mesh that deforms could cross itself where only part of it gives way)
                stuck = rest & ~np.isin(small, moved) & self._rigid[large]
                if stuck.any():
                    moved += self._take_back(out, new[stuck], large[stuck], fallback)
            if not moved:
                break
            self.rounds += 1
            keys = cross.keys(out, sorted(set(moved)), keys)  # only the moved meshes query again
        self.keys = (keys, keys_lbs)
        return out

"""Crossings repaired pair by pair: :class:`Untangle`.

The surface guard (:class:`~warpskin.guard.surface.SurfaceGuard`) takes physics back where the
written mesh crosses itself more than its LBS; where LBS itself drives one part through
another (a leg into the belly, a thigh through a skirt, a hand into the hip), the guard accepts
as many crossings as LBS has, and physics that merely matches LBS there is no better than it.
:class:`Untangle` repairs those crossings where they are: after the guard, every pair of the
written mesh's triangles that intersect (the exact test of
:func:`~warpskin.metrics.self_intersections`), other than those that cross at rest or lie
where pieces cross at rest (a tube's end in a ball joint, a bun sunk into the skull: their
crossing is the design and slides: :meth:`Untangle._seam` makes it slide as LBS slides it
where it crosses more than LBS there), is separated along the normal of the plane that
separates it least deep, or of the larger piece's triangle where one piece is more than twice
the other's size (:mod:`warpskin.kernels.untangle`). Which side each triangle
belongs on is read from the last frame written (the rest pose before the first frame), where
the pair did not cross. A point's pushes from its pairs are averaged, half of it spreads to its
unpushed neighbours (a dent, not a spike), and the rounds repeat on the pairs of the moved
triangles. The points of the edges a round would strain past
:data:`~warpskin.quality.STRAIN_LIMIT`, or of the triangles it would turn over against LBS,
where the input does not, keep still; a point is never moved farther than ``max_offset`` from
its LBS (or its input's offset, where that is farther). A round goes on where it crosses more
for now (a skirt pushed back off a hand into the thigh beneath frees itself over the next
rounds); the round with the fewest pairs beyond the rest pose's (those where pieces cross at
rest included) is written. Points of a rigid piece (a group: a shoe, a fist) do not move: the
other side gives way. A frame starts from the last frame's repair (its displacement, the same
checks made) where that leaves fewer pairs than its own input: a crossing that lasts is not
repaired from nothing every frame.

Where a closed piece (a hand, a shoe: closed but for small holes, which are capped for the
test) crosses a piece it is apart from at rest (a skirt, a shirt), the other piece gives way to
it (:meth:`Untangle._press`): its triangles' samples inside the closed piece (generalised
winding number) go out of it, each to the nearest point of its surface or, trying both and
keeping the better, all along their triangles' normals the way most of those lean (a finger
through a sheet takes the sheet past it one way, not split round it), a ramp around. This
needs no side read from the last frame: a hand swept through a skirt in one frame is often
past the point the rounds' reference says it belongs behind. It runs after the rounds, and,
where it takes pairs off the frame's start, before them too; the path with the fewest pairs
beyond the rest pose's is kept.

Invariants: with nothing to repair the input is returned itself; the result never has more
pairs beyond the rest pose's than the input, nor an edge strained or a triangle turned over
against LBS that the input does not have. Limits: a crossing deeper
than the rounds' steps (``rounds`` x ``max_step``) is only reduced; a pair whose reference
pose crossed too (a crossing carried over from a frame it could not be repaired in) has no
side there to read: it takes the sides of its closest points, which can be either, so it may be
pushed the wrong way (such a round is written only where it leaves fewer pairs); a coarse
mesh whose crossing edges are already near the strain limit (a low-poly leg driven into the
belly) has few points free to move. It changes only what is written, never the simulation.
"""

from __future__ import annotations

import numpy as np

from ..quality import STRAIN_LIMIT
from .params import as_written, pair_keys

__all__ = ["Untangle"]


class Untangle:
    """The crossing repair of one written mesh (module docstring), after its guard.

    Args:
        guard: The mesh's :class:`~warpskin.guard.surface.SurfaceGuard` (its welded topology,
            where pieces cross at rest, its rest pairs and pair counter are shared).
        groups: ``[N]`` per written point, the rigid group it moves with (-1: none); grouped
            points do not move.
        rounds: Rounds of separation per frame (0: off).
        max_step: The most [m] one pair's push may be in one round.
        max_offset: The most [m] a point repaired may lie from its LBS (the tether's cap).
        press: Closed pieces press the pieces they cross into giving way (:meth:`_press`).
    """

    #: Tries per round: the points of the edges the push strains and the triangles it turns
    #: over (that the input did not) keep still.
    ATTEMPTS = 6
    #: Where pieces cross at rest, crossings within this share of the smaller piece's diagonal
    #: of the rest crossing are left to slide (:meth:`_rest_zone`).
    REST_REACH = 0.25
    #: Tries per frame to bring the piece pairs that cross at rest to no more crossings than
    #: LBS's there (:meth:`_seam`).
    SEAM_TRIES = 3
    #: A piece is closed enough to press into another (:meth:`_closed_pieces`) where each of its
    #: holes spans at most this share of the piece's rest diagonal (a wrist, a shoe's opening).
    HOLE = 0.5
    #: The clearance a pressed point keeps from the pressing surface, x the median rest edge.
    PRESS_GAP = 0.25
    #: Rounds of the press per frame (:meth:`_press`).
    PRESS_ROUNDS = 3
    #: The press's ramp: the share of the pushed points' mean push their neighbours take, ring
    #: by ring (an edge changes by a quarter of the push at most).
    _PRESS_RAMP = (0.75, 0.5, 0.25)
    #: Where a triangle is sampled for the press: barycentric weights of its corners, centre
    #: and edge midpoints.
    _SAMPLES = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1 / 3, 1 / 3, 1 / 3],
                         [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])

    def __init__(self, guard, groups: np.ndarray | None = None, rounds: int = 8, max_step: float = np.inf,
                 max_offset: float = np.inf, press: bool = True) -> None:
        import warp as wp

        self.guard = guard
        mesh = guard.mesh
        self.mesh = mesh
        self.rounds = int(rounds)
        self.max_step = float(max_step)
        self.max_offset = float(max_offset)
        c = mesh.first.size
        self._adjacency = (guard._graph != 0).astype(np.float64)  # the welded edges, both ways
        from scipy.sparse.csgraph import connected_components

        # the welded pieces and their rest diagonals [m]
        _, self._piece = connected_components(self._adjacency, directed=False)
        rest = mesh.welded(mesh.rest)
        count = int(self._piece.max()) + 1 if c else 0
        lo = np.full((count, 3), np.inf)
        hi = np.full((count, 3), -np.inf)
        np.minimum.at(lo, self._piece, rest)
        np.maximum.at(hi, self._piece, rest)
        self._piece_size = np.linalg.norm(hi - lo, axis=1)
        mobility = np.ones(c, dtype=np.float32)
        #: ``[C]`` the rigid group of each welded point (-1: none)
        self._group = np.full(c, -1, dtype=np.int64)
        if groups is not None:
            self._group = np.asarray(groups, dtype=np.int64)[mesh.first]
            mobility[self._group >= 0] = 0.0
        #: ``[C]`` each welded point's mobility: 0 in a rigid group, else 1
        self._mobile = mobility.astype(np.float64)
        tris = guard._all_tri
        self._tri_count = len(tris)
        #: the clearance added to a pair's depth [m]: a hundredth of the median rest edge
        self.gap = 0.01 * guard.edge
        with wp.ScopedDevice("cpu"):
            self._tri = wp.array(tris.astype(np.int32), dtype=wp.vec3i)
            self._mobility = wp.array(mobility, dtype=wp.float32)
            self._size = wp.array(self._piece_size[self._piece[tris[:, 0]]].astype(np.float32) if len(tris)
                                  else np.zeros(1, np.float32), dtype=wp.float32)
            self._x = wp.zeros(c, dtype=wp.vec3)
            self._ref = wp.zeros(c, dtype=wp.vec3)
            self._push = wp.zeros(c, dtype=wp.vec3)
            self._count = wp.zeros(c, dtype=wp.float32)
            self._pairs = wp.zeros(1, dtype=wp.vec2i)
        self._zone = self._rest_zone(self.REST_REACH)
        # per piece of the mesh (WrittenMesh.piece_of_triangle): its triangles and rest diagonal [m]
        piece_of = mesh.piece_of_triangle
        order = np.argsort(piece_of, kind="stable")
        self._piece_tris = np.split(order, np.cumsum(np.bincount(piece_of, minlength=mesh.piece_count))[:-1])
        self._piece_diag = np.array([self._piece_size[self._piece[tris[t[0], 0]]] if t.size else 0.0
                                     for t in self._piece_tris])
        #: the pieces closed but for small holes (:meth:`_closed_pieces`), that press into others
        self._shells = self._closed_pieces() if press else {}
        #: the clearance [m] a pressed point keeps from the surface it was inside of
        self.press_gap = self.PRESS_GAP * guard.edge
        self._inside_at_rest: dict = {}  # (yielding, pressing piece) -> welded points inside at rest
        self._last: np.ndarray | None = None  # the last frame's result, welded
        self._repair: np.ndarray | None = None  # the last frame's repair (result - input), welded
        #: Per frame: the repairable pairs before and after, the rounds run, the pairs taken
        #: off where pieces cross at rest (:meth:`_seam`), and the pairs beyond the rest pose's
        #: the press took off the rounds' result (:meth:`_press`).
        self.stats = {"before": 0, "after": 0, "rounds": 0, "seam": 0, "press": 0}
        #: After :meth:`apply` left its input as it was: the keys of the intersecting pairs of
        #: that input and of its LBS (as :attr:`SurfaceGuard.pair_keys`, for the frame's
        #: measures); ``None`` where it repaired or counted nothing.
        self.pair_keys: tuple[np.ndarray, np.ndarray] | None = None

    def _rest_zone(self, reach: float) -> np.ndarray:
        """``[T]`` bool: the triangles within ``reach`` x the smaller piece's rest diagonal (along
        the surface) of a triangle that crosses another piece's at rest, or within the guard's
        two median edges of where pieces cross or touch at rest. A crossing there slides as the
        pieces turn (a tube's end in its ball joint); one beyond it (a thigh through a skirt's
        hem, the skirt's waist sunk into the hips at rest) is repaired."""
        from scipy.sparse.csgraph import dijkstra

        g = self.guard
        t, n = g._all_tri, self._tri_count
        zone = g._crossing.copy()
        keys = g._rest_pairs
        if not keys.size:
            return zone
        piece, size = self._piece, self._piece_size
        a, b = keys // n, keys % n
        pa, pb = piece[t[a, 0]], piece[t[b, 0]]
        radius = reach * np.minimum(size[pa], size[pb])
        near = np.zeros(len(piece), dtype=bool)
        for r in np.unique(radius):
            sel = radius == r
            src = np.unique(t[np.concatenate([a[sel], b[sel]])].ravel())
            near |= np.isfinite(dijkstra(g._graph, directed=False, indices=src, min_only=True, limit=float(r)))
        return zone | near[t].all(axis=1)

    def _closed_pieces(self) -> dict:
        """``{piece: _Shell}`` for the pieces of the welded mesh that are closed but for holes each
        spanning at most :attr:`HOLE` x the piece's rest diagonal (a hand open at the wrist, a
        shoe at its opening, a closed eye), with at least four triangles; the triangles ``(b,
        a, centre of its loop)`` over each boundary edge ``(a, b)`` (as the piece's own
        triangles run it) close it with its own orientation. Sheets (a skirt, a hair cap: a
        hole as wide as the piece) are not listed."""
        from scipy.sparse.csgraph import connected_components
        import scipy.sparse as sp

        tris, mesh = self.guard._all_tri, self.mesh
        rest = mesh.welded(mesh.rest)
        c = len(rest)
        out = {}
        for p, own in enumerate(self._piece_tris):
            t = tris[own]
            if len(t) < 4:
                continue
            directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
            und = np.sort(directed, axis=1)
            _, inv, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
            edge = directed[counts[inv.ravel()] == 1]
            size = self._piece_diag[p]
            if not edge.size:
                out[int(p)] = _Shell(t, edge, np.zeros(0, dtype=np.int64), size)
                continue
            g = sp.csr_matrix((np.ones(len(edge)), (edge[:, 0], edge[:, 1])), shape=(c, c))
            _, label = connected_components(g, directed=False)
            _, loop = np.unique(label[edge[:, 0]], return_inverse=True)
            loop = loop.ravel()
            wide = False
            for k in range(int(loop.max()) + 1):
                pts = rest[np.unique(edge[loop == k])]
                wide |= float(np.linalg.norm(np.ptp(pts, axis=0))) > self.HOLE * size
            if not wide:
                out[int(p)] = _Shell(t, edge, loop, size)
        return out

    def _press(self, x: np.ndarray, every: np.ndarray, lw: np.ndarray, harm: tuple, lbs_side: tuple, now: tuple):
        """Where a closed piece (:meth:`_closed_pieces`: a hand, a shoe) crosses a piece it is
        apart from at rest (a skirt, a shirt), the other piece gives way, in up to
        :attr:`PRESS_ROUNDS` rounds of :meth:`_press_push`, each through :meth:`_moved`'s
        checks, each trying the nearest-surface push and the one-side push and keeping the one
        that leaves fewer pairs beyond the rest pose's. Returns ``(y, every pair of y,
        measures)`` of the round with the fewest pairs beyond the rest pose's where that is
        fewer than ``x``'s, else ``None``. Unlike the
        rounds' planes, this needs no side read from the last frame: a hand swept through a
        skirt in one frame dents it from whichever side is nearer."""
        beyond = self.mesh.pairs_beyond_rest
        best, fewest = None, beyond(every)
        for _ in range(self.PRESS_ROUNDS):
            pushes = self._press_push(x, every)
            if pushes is None:
                break
            steps = [step for step in (self._moved(x, d, lw, harm, every, lbs_side, now) for d in pushes)
                     if step is not None]
            if not steps:
                break
            step = min(steps, key=lambda s: beyond(s[1]))
            x, every, now = step
            if beyond(every) < fewest:
                best, fewest = step, beyond(every)
        return best

    def _press_push(self, x: np.ndarray, every: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """One round of :meth:`_press`: two pushes ``[C, 3]`` [m] of every welded point, ``None``
        where there is none. Per pair of pieces apart at rest that cross in ``every`` (keys),
        one closed (the smaller of two closed ones presses), the other's triangles that cross
        the closed one or have a corner inside it are sampled at their corners, centre and edge
        midpoints; a sample inside the closed piece (its winding number above a half) is pushed
        out plus :attr:`press_gap`: in the first push to the nearest point of its surface, in
        the second along its triangle's normal, the way the nearest-surface pushes lean on the
        whole (their sum along the normals), to where that ray leaves the piece (one side for
        the patch: a finger through a sheet takes the sheet past it one way, not split round
        it). Each corner takes the mean of its triangles' samples' pushes weighted by their
        barycentric weight at it (a triangle whose centre alone is inside, pierced by a finger,
        moves whole). A ramp (:attr:`_PRESS_RAMP`) goes to the next rings of neighbours (a
        dent, not a spike). Rigid points, and points inside the closed piece at rest, do not
        move."""
        mesh, tris = self.mesh, self.guard._all_tri
        if not self._shells or not every.size:
            return None
        n = self._tri_count
        piece = mesh.piece_of_triangle
        ids = mesh.piece_pair_ids(every)
        apart = mesh.rest_piece_pairs[ids] == 0
        count = mesh.piece_count
        nearest, side = np.zeros_like(x), np.zeros_like(x)
        den = np.zeros(len(x))
        still = self._mobile == 0.0
        bary = self._SAMPLES
        for k in np.unique(ids[apart]):
            a, b = int(k // count), int(k % count)
            if a == b:
                continue
            if a in self._shells and (b not in self._shells or self._piece_diag[a] <= self._piece_diag[b]):
                presser, soft = a, b
            elif b in self._shells:
                presser, soft = b, a
            else:
                continue
            shell = self._shells[presser]
            own_t = self._piece_tris[soft]
            key = (soft, presser)
            if key not in self._inside_at_rest:
                rest = mesh.welded(mesh.rest)
                pts = np.unique(tris[own_t])
                self._inside_at_rest[key] = pts[shell.inside(rest[pts], rest)[0]]
            held = still.copy()
            held[self._inside_at_rest[key]] = True
            # the soft piece's points of its crossing triangles and two rings round them (a
            # patch sunk wholly inside next to them), and which of those are inside the closed one
            keys = every[ids == k]
            crossing = np.where(piece[keys // n] == soft, keys // n, keys % n)
            near = np.zeros(len(x), dtype=bool)
            near[tris[crossing].ravel()] = True
            for _ in range(2):
                near |= (self._adjacency @ near.astype(np.float64)) > 0
            cand = np.nonzero(near & ~held)[0]
            inside = np.zeros(len(x), dtype=bool)
            if cand.size:
                inside[cand[shell.inside(x[cand], x)[0]]] = True
            tri = np.union1d(crossing, own_t[inside[tris[own_t]].any(axis=1)])
            if not tri.size:
                continue
            corners = tris[tri]  # [M, 3]
            q = np.einsum("sk,mkd->msd", bary, x[corners]).reshape(-1, 3)
            inn, surface = shell.inside(q, x)
            if not inn.any():
                continue
            out = (surface - q)[inn]
            length = np.linalg.norm(out, axis=1)
            near = np.zeros_like(q)
            near[inn] = out * ((length + self.press_gap) / np.maximum(length, 1e-30))[:, None]
            normal = np.cross(x[corners[:, 1]] - x[corners[:, 0]], x[corners[:, 2]] - x[corners[:, 0]])
            normal /= np.maximum(np.linalg.norm(normal, axis=1), 1e-300)[:, None]
            normal = np.repeat(normal, len(bary), axis=0)[inn]
            ways = normal * (1.0 if np.einsum("ij,ij->i", out, normal).sum() >= 0.0 else -1.0)
            one = np.zeros_like(q)
            one[inn] = ways * (shell.exit(q[inn], ways, x) + self.press_gap)[:, None]
            weight = np.tile(bary, (len(tri), 1)) * inn[:, None]  # [M * S, 3]
            weight[held[np.repeat(corners, len(bary), axis=0)]] = 0.0
            idx = np.repeat(corners, len(bary), axis=0)  # [M * S, 3]
            for c in range(3):
                np.add.at(nearest, idx[:, c], weight[:, c, None] * near)
                np.add.at(side, idx[:, c], weight[:, c, None] * one)
                np.add.at(den, idx[:, c], weight[:, c])
        hit = den > 0.0
        if not hit.any():
            return None
        out = []
        for num in (nearest, side):
            d = np.zeros_like(x)
            d[hit] = num[hit] / den[hit, None]
            reached = hit.copy()
            last, before = hit, 1.0
            for share in self._PRESS_RAMP:  # rings of neighbours (within the piece), a falling share
                ring_near = self._adjacency @ last.astype(np.float64)
                ring = ~reached & (ring_near > 0)
                if not ring.any():
                    break
                d[ring] = (share / before) * (self._adjacency @ (d * last[:, None]))[ring] / ring_near[ring, None]
                reached |= ring
                last, before = ring, share
            d[still] = 0.0
            out.append(d)
        return out[0], out[1]

    def _pressable(self, keys: np.ndarray) -> bool:
        """Whether any pair of ``keys`` is between two pieces apart at rest, one of them closed
        (:meth:`_press` has something to act on)."""
        mesh = self.mesh
        if not self._shells or not keys.size:
            return False
        ids = mesh.piece_pair_ids(keys)
        closed = np.zeros(mesh.piece_count, dtype=bool)
        closed[list(self._shells)] = True
        lo, hi = ids // mesh.piece_count, ids % mesh.piece_count
        return bool(np.any((mesh.rest_piece_pairs[ids] == 0) & (lo != hi) & (closed[lo] | closed[hi])))

    def _repairable(self, keys: np.ndarray) -> np.ndarray:
        """The keys of ``keys`` that are repaired: not crossing at rest, not both where pieces
        cross at rest (:meth:`_rest_zone`)."""
        n = self._tri_count
        keys = np.setdiff1d(keys, self.guard._rest_pairs, assume_unique=True)
        both = self._zone[keys // n] & self._zone[keys % n]
        return keys[~both]

    def _seam(self, x: np.ndarray, every: np.ndarray, lw: np.ndarray, lbs_keys: np.ndarray, harm: tuple,
              lbs_side: tuple, now: tuple):
        """Where pieces cross at rest (the rest zone, left to slide by the rounds), the piece
        pairs that cross more than LBS's beyond the rest pose's (a soft tube's end wobbling
        through its ball joint) slide as LBS slides them: the points of their pairs that LBS
        does not have, and a ramp along the surface around them (the guard's falloff), move to
        their LBS ``lw``, or, where the other piece is rigid (a group, written moved as a
        whole), to their LBS carried by that piece's motion from its own LBS (the rigid fit);
        rigid points never move. :meth:`_moved`'s checks apply. ``every``: the keys of every
        pair of ``x`` (rest pairs included), ``lbs_keys``: LBS's. Returns :meth:`_moved`'s
        ``(y, every pair of y, measures)`` and by how much that lowers the piece pairs' excess
        over LBS (pairs), where it does, else ``None``."""
        from ..transforms import rigid_fit

        g, mesh, n, tris = self.guard, self.mesh, self._tri_count, self.guard._all_tri
        lbs = mesh.piece_pairs_beyond_rest(lbs_keys)
        mine = mesh.piece_pairs_beyond_rest(every)
        over = (mine > lbs) & (mesh.rest_piece_pairs > 0)
        if not over.any():
            return None
        zoned = self._zone[every // n] & self._zone[every % n]
        new = np.setdiff1d(every[over[mesh.piece_pair_ids(every)] & zoned], lbs_keys, assume_unique=True)
        if not new.size:
            return None
        new_pp = mesh.piece_pair_ids(new)
        moved = np.linalg.norm(x - lw, axis=1)
        mobility = self._mobile
        d = np.zeros_like(x)
        reach = np.zeros(len(x))
        for k in np.unique(new_pp):
            keys = new[new_pp == k]
            pts = tris[np.concatenate([keys // n, keys % n])].ravel()
            flag = np.zeros(len(x), dtype=bool)
            flag[pts] = True
            target = lw
            rigid = np.unique(self._group[pts[mobility[pts] == 0.0]])
            if rigid.size == 1 and rigid[0] >= 0:  # the soft side follows the rigid piece
                members = self._group == rigid[0]
                r, t = rigid_fit(lw[members], x[members])
                target = lw @ r.T + t
            ramp = g._falloff(flag, moved) * mobility
            take = ramp > reach
            d[take] = ramp[take, None] * (target[take] - x[take])
            reach = np.maximum(reach, ramp)
        step = self._moved(x, d, lw, harm, every, lbs_side, now)
        if step is None:
            return None
        then = mesh.piece_pairs_beyond_rest(step[1])
        excess, after = int(np.maximum(mine - lbs, 0).sum()), int(np.maximum(then - lbs, 0).sum())
        if after >= excess or then.sum() > mine.sum():
            return None
        return (*step, excess - after)

    def _measures(self, x: np.ndarray, lbs_side: tuple, base: tuple | None = None,
                  moved: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(strained, turned)``: the edges of ``x`` past STRAIN_LIMIT where LBS's are not, the
        judged triangles turned over against LBS's (normal against normal: where LBS folds a
        crease over, a triangle the repair turns back counts too; it stays as the guard left
        it). ``lbs_side``: :meth:`_lbs_side` of the frame;
        with ``base`` (the measures of a pose that differs from ``x`` only at the points
        ``moved``), only the edges and triangles of those points are measured again."""
        g = self.guard
        lbs_ok, n_lbs, len_lbs = lbs_side
        if base is None or moved is None:
            return (g._strain(x) > STRAIN_LIMIT) & lbs_ok, self._turned(x, n_lbs, len_lbs)
        strained, turned = base[0].copy(), base[1].copy()
        ce, ct = moved[self.mesh.edges].any(axis=1), moved[g._tri].any(axis=1)
        strained[ce] = (g._strain(x, ce) > STRAIN_LIMIT) & lbs_ok[ce]
        turned[ct] = self._turned(x, n_lbs[ct], len_lbs[ct], ct)
        return strained, turned

    def _turned(self, x: np.ndarray, n_lbs: np.ndarray, len_lbs: np.ndarray,
                which: np.ndarray | None = None) -> np.ndarray:
        """The judged triangles (or those ``which`` selects) whose normal in ``x`` points against
        LBS's (``n_lbs``, lengths ``len_lbs``, of the same triangles); never a degenerate one."""
        g = self.guard
        n = g._normals(x, which)
        ln = np.linalg.norm(n, axis=1)
        ok = (ln > g._floor) & (len_lbs > g._floor)
        return ok & (np.einsum("ij,ij->i", n, n_lbs) < 0.0)

    def _lbs_side(self, lw: np.ndarray) -> tuple:
        """What :meth:`_measures` takes from the frame's LBS ``lw`` (welded): the edges within
        STRAIN_LIMIT, the judged triangles' normals and their lengths."""
        g = self.guard
        n_lbs = g._normals(lw)
        return g._strain(lw) <= STRAIN_LIMIT, n_lbs, np.linalg.norm(n_lbs, axis=1)

    def _separate(self, x: np.ndarray, work: np.ndarray) -> None:
        """Launch the separation of the pairs ``work`` (keys) at ``x`` (welded, ``[C, 3]``) into
        the push buffers."""
        import warp as wp

        from ..kernels import untangle as k

        n = self._tri_count
        pairs = np.stack([work // n, work % n], axis=1).astype(np.int32)
        if self._pairs.shape[0] < len(pairs):
            self._pairs = wp.zeros(2 * len(pairs), dtype=wp.vec2i, device="cpu")
        self._pairs.assign(np.concatenate([pairs, np.zeros((self._pairs.shape[0] - len(pairs), 2), np.int32)]))
        self._x.assign(x.astype(np.float32))
        self._push.zero_()
        self._count.zero_()
        wp.launch(k.separate_pairs_kernel, dim=len(pairs),
                  inputs=[self._x, self._ref, self._tri, self._pairs, self._mobility, self._size, self.gap,
                          self.max_step],
                  outputs=[self._push, self._count], device="cpu")

    def _moved(self, x: np.ndarray, d: np.ndarray, lw: np.ndarray, harm: tuple, every: np.ndarray,
               lbs_side: tuple, now: tuple):
        """``x + d`` (welded, ``[C, 3]`` [m]) less what harms: a point is not moved past
        ``max_offset`` from its LBS ``lw`` (or past its offset in ``x``), and the points of the
        edges it strains and the triangles it turns over that ``harm`` (the input's
        ``(strained, turned)``) does not have keep still, up to :attr:`ATTEMPTS` times
        (``lbs_side``: :meth:`_lbs_side`; ``now``: the measures of ``x``). Returns ``(y, every
        intersecting pair of y, the measures of y)``, the pairs found from ``every`` (``x``'s)
        and the moved triangles'; ``None`` where nothing moves."""
        g, mesh, n = self.guard, self.mesh, self._tri_count
        tris, e, t = g._all_tri, mesh.edges, g._tri
        d = d.copy()
        for _ in range(self.ATTEMPTS):
            y = x + d
            off = np.linalg.norm(y - lw, axis=1)
            over = off > np.maximum(self.max_offset, np.linalg.norm(x - lw, axis=1))
            y[over] = x[over]
            y = as_written(y)
            moved = (y != x).any(axis=1)
            if not moved.any():
                return None
            strained, turned = self._measures(y, lbs_side, now, moved)
            bad = np.zeros(len(x), dtype=bool)
            bad[e[strained & ~harm[0]].ravel()] = True
            bad[t[turned & ~harm[1]].ravel()] = True
            if bad.any():  # the points of what it strains or turns over keep still
                d[bad] = 0.0
                continue
            active = moved[tris].any(axis=1)
            a, b = every // n, every % n
            kept = every[~(active[a] | active[b])]
            return y, np.union1d(kept, pair_keys(g._query.active(y, active), n)), (strained, turned)
        return None

    def _rounds(self, best: tuple, lw: np.ndarray, harm: tuple, lbs_side: tuple) -> tuple:
        """The rounds of separation (module docstring) from ``best`` = ``(x, every pair of x,
        its pairs beyond the rest pose's, its measures)``; returns the same of the round with
        the fewest pairs beyond the rest pose's (``best`` itself where none has fewer)."""
        x, every, _, now = best
        work = self._repairable(every)
        for _ in range(self.rounds):
            if not work.size:
                break
            self._separate(x, work)
            cnt = self._count.numpy().astype(np.float64)
            pushed = cnt > 0
            d = np.zeros_like(x)
            d[pushed] = self._push.numpy()[pushed] / cnt[pushed, None]
            # half of it to the unpushed neighbours: a dent, not a spike
            near = self._adjacency @ pushed.astype(np.float64)
            ring = ~pushed & (near > 0)
            d[ring] = 0.5 * (self._adjacency @ d)[ring] / near[ring, None]
            d *= self._mobile[:, None]
            step = self._moved(x, d, lw, harm, every, lbs_side, now)
            if step is None:
                break
            # the round goes on even where it crosses more for now: a crossing pushed into a
            # third surface (a skirt pushed off a hand into the thigh) frees itself over rounds
            x, every, now = step
            work = self._repairable(every)
            self.stats["rounds"] += 1
            count = self.mesh.pairs_beyond_rest(every)
            if count < best[2]:
                best = (x, every, count, now)
        return best

    def apply(self, points: np.ndarray, lbs: np.ndarray, counted: bool = False) -> np.ndarray:
        """The repaired points of one frame, ``[N, 3]`` [m] in the mesh's file order (``points``:
        the guarded result, ``lbs``: the mesh's LBS); call once per frame, in frame order.
        ``counted``: ``points`` is the guard's result of this frame as it returned it, whose
        pairs it counted (:attr:`SurfaceGuard.pair_keys`, where not ``None``): they are not
        counted again. Returns ``points`` itself where nothing is repaired, else the result
        rounded to float32 as USD stores it."""
        mesh, g = self.mesh, self.guard
        self.stats = {"before": 0, "after": 0, "rounds": 0, "seam": 0, "press": 0}
        self.pair_keys = None
        x = mesh.welded(as_written(points))
        ref = mesh.welded(mesh.rest) if self._last is None else self._last
        carried, self._repair = self._repair, None
        if self.rounds <= 0 or self._tri_count < 2 or not g.params.enabled:
            self._last = x
            return points
        lw = mesh.welded(as_written(lbs))
        # every pair but the rest pose's (judged: a push may cross where pieces cross at rest
        # too), and of them the ones repaired; counted with LBS's in one pass where the guard
        # did not count them, so that a frame left as it is needs no count of its own after
        if g.pair_keys is not None and counted:
            self.pair_keys = g.pair_keys
        else:
            self.pair_keys = g._pairs_of_two(x, lw)
        every = self.pair_keys[0]
        work = self._repairable(every)
        # piece pairs crossing at rest that cross more than LBS's beyond the rest pose's
        zoned = bool(np.any((mesh.piece_pairs_beyond_rest(every) > mesh.piece_pairs_beyond_rest(self.pair_keys[1]))
                            & (mesh.rest_piece_pairs > 0)))
        # pairs of pieces apart at rest, one of them closed: a hand in a skirt (see _press)
        pressed = self._pressable(every)
        self.stats["before"] = self.stats["after"] = int(work.size)
        if not work.size and not zoned and not pressed:
            self._last = x
            return points
        lbs_side = self._lbs_side(lw)
        harm = now = self._measures(x, lbs_side)
        self._ref.assign(ref.astype(np.float32))
        given = x
        beyond = mesh.pairs_beyond_rest
        best = (x, every, beyond(every), now)
        if carried is not None:  # the last frame's repair first, where it still helps
            step = self._moved(x, carried, lw, harm, every, lbs_side, now)
            if step is not None and beyond(step[1]) < best[2]:
                best = (step[0], step[1], beyond(step[1]), step[2])
        start = best
        best = self._rounds(best, lw, harm, lbs_side)
        if pressed:  # closed pieces in others: the other gives way, to the nearer side, after
            # the rounds, and, where that leaves such pairs and the press takes pairs off the
            # start, before them too (the rounds read a side from the last frame, which a hand
            # swept through in one frame misses)
            paths = [best]
            step = self._press(best[0], best[1], lw, harm, lbs_side, best[3])
            if step is not None:
                paths.append((step[0], step[1], beyond(step[1]), step[2]))
            left = min(paths, key=lambda b: b[2])[1]
            step = self._press(start[0], start[1], lw, harm, lbs_side, start[3]) if self._pressable(left) else None
            if step is not None:
                first = self._rounds((step[0], step[1], beyond(step[1]), step[2]), lw, harm, lbs_side)
                paths.append(first)
                step = self._press(first[0], first[1], lw, harm, lbs_side, first[3])
                if step is not None:
                    paths.append((step[0], step[1], beyond(step[1]), step[2]))
            pick = min(paths, key=lambda b: b[2])
            self.stats["press"] = best[2] - pick[2]
            best = pick
        x, every, count, now = best  # its measures too: the steps below measure from them
        if zoned:  # where pieces cross at rest: no more than LBS's, per pair of pieces
            for _ in range(self.SEAM_TRIES):
                step = self._seam(x, every, lw, self.pair_keys[1], harm, lbs_side, now)
                if step is None:
                    break
                x, every, now = step[:3]
                self.stats["seam"] += step[3]
        self.stats["after"] = int(self._repairable(every).size)
        self._last = x
        if x is given:
            return points
        self.pair_keys = None
        self._repair = x - given
        return x[mesh.weld]


class _Shell:
    """A closed piece of a written mesh (:meth:`Untangle._closed_pieces`) as two Warp meshes on
    the CPU, refitted to each pose asked about: the piece with its holes capped (fans at the
    loops' centres, with the piece's own orientation) for the inside test and the rays, and
    the piece alone for the nearest surface point.

    Args:
        triangles: ``[T, 3]`` its triangles, into the welded mesh's points.
        edges: ``[K, 2]`` its boundary edges as its triangles run them.
        loop: ``[K]`` the hole each boundary edge belongs to.
        size: Its rest diagonal [m] (the reach of the nearest-point search is twice it).
    """

    def __init__(self, triangles: np.ndarray, edges: np.ndarray, loop: np.ndarray, size: float) -> None:
        import warp as wp

        self.edges, self.loop = edges, loop
        self.points = np.unique(triangles)
        local = np.full(int(self.points.max()) + 1, -1, dtype=np.int64)
        local[self.points] = np.arange(self.points.size)
        self.loops = int(loop.max()) + 1 if loop.size else 0
        caps = np.stack([local[edges[:, 1]], local[edges[:, 0]], self.points.size + loop], axis=1) if loop.size \
            else np.zeros((0, 3), dtype=np.int64)
        self.reach = 2.0 * float(size)
        self._x = None
        with wp.ScopedDevice("cpu"):
            self.capped = wp.Mesh(points=wp.zeros(self.points.size + self.loops, dtype=wp.vec3),
                                  indices=wp.array(np.concatenate([local[triangles], caps]).astype(np.int32).ravel(),
                                                   dtype=wp.int32), support_winding_number=True)
            self.surface = wp.Mesh(points=wp.zeros(self.points.size, dtype=wp.vec3),
                                   indices=wp.array(local[triangles].astype(np.int32).ravel(), dtype=wp.int32))

    def at(self, x: np.ndarray) -> None:
        """Place both meshes at the welded points ``x`` ``[C, 3]`` [m] (refitted; nothing where
        ``x`` is the pose placed last)."""
        if self._x is x:
            return
        own = x[self.points]
        centre = np.zeros((self.loops, 3))
        if self.loops:
            np.add.at(centre, self.loop, x[self.edges[:, 0]])
            centre /= np.bincount(self.loop, minlength=self.loops)[:, None]
        self.capped.points.assign(np.concatenate([own, centre]).astype(np.float32))
        self.surface.points.assign(own.astype(np.float32))
        self.capped.refit()
        self.surface.refit()
        self._x = x

    def inside(self, queries: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """At the pose ``x``: ``([M] bool, [M, 3])`` whether each of ``queries`` [m] is inside the
        capped piece, and the nearest point of the piece's surface
        (:func:`warpskin.kernels.untangle.press_kernel`)."""
        import warp as wp

        from ..kernels import untangle as k

        self.at(x)
        with wp.ScopedDevice("cpu"):
            inside = wp.zeros(len(queries), dtype=wp.int32)
            near = wp.zeros(len(queries), dtype=wp.vec3)
            wp.launch(k.press_kernel, dim=len(queries),
                      inputs=[self.capped.id, self.surface.id, wp.array(np.asarray(queries, np.float32), dtype=wp.vec3),
                              self.reach], outputs=[inside, near])
            return inside.numpy() != 0, near.numpy().astype(np.float64)

    def exit(self, queries: np.ndarray, directions: np.ndarray, x: np.ndarray) -> np.ndarray:
        """At the pose ``x``: ``[M]`` [m] how far along the unit ``directions`` each of ``queries``
        (inside the capped piece) leaves it, the nearest crossing of its surface ahead
        (:func:`warpskin.kernels.untangle.exit_kernel`; 0 where the ray meets none)."""
        import warp as wp

        from ..kernels import untangle as k

        self.at(x)
        with wp.ScopedDevice("cpu"):
            out = wp.zeros(len(queries), dtype=wp.float32)
            wp.launch(k.exit_kernel, dim=len(queries),
                      inputs=[self.capped.id, wp.array(np.asarray(queries, np.float32), dtype=wp.vec3),
                              wp.array(np.asarray(directions, np.float32), dtype=wp.vec3), self.reach],
                      outputs=[out])
            return out.numpy().astype(np.float64)

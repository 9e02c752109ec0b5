"""The surface guard: every written mesh keeps the surface its LBS has.

A mesh written with physics is its LBS plus a physical displacement (``P = L + D``,
:mod:`warpskin.kernels.deform`). Where that displacement would make the written surface worse
than its own LBS (an edge stretched or crumpled past :data:`~warpskin.quality.STRAIN_LIMIT`
where LBS's is not, a triangle turned over against LBS, two triangles passing through each other
where LBS's do not) the guard takes part of it back there, smoothly over the surface:

    W = L + g * (P - L),      g in [0, 1] per welded point, kept from frame to frame

Every frame, per mesh (on the host, in the mesh's welded topology):

1. ``g`` rises by ``recover`` from the last frame's, up to its ceiling (1, or a directly
   simulated skin's physics weight): a point the guard held returns to its physical result over
   ``1 / recover`` frames where that is safe;
2. ``W`` is checked against ``L``. Flagged are: edges past ``strain`` x their rest length (or
   under its inverse) and past LBS's strain, where LBS's is within
   :data:`~warpskin.quality.STRAIN_LIMIT` or ``W``'s is over 1.1 x LBS's; triangles whose normal
   turns by more than ``flip_degrees`` against LBS (but for LBS's own folds that ``W`` keeps
   the right way: :func:`~warpskin.quality.own_fold_kept`); and intersecting triangle pairs
   (the exact test of :func:`~warpskin.metrics.self_intersections`) that LBS does not have, except, where
   pieces cross or touch at rest (a ball joint inside a tube's end, a seam) or where LBS passes
   through itself in the frame (a crease the physics keeps apart), those matched one
   to one with a nearby pair that LBS has and ``W`` lost (within ``match`` median edges: a
   crossing that slides trades a pair for its neighbour, and only a net gain is new). After
   the first round only the pairs of triangles whose points changed are tested again;
3. the flagged points and a smooth ramp around them, over ``spread`` x the displacement taken
   back (along the surface), first go back to the last frame's ``g`` (the rise is taken back
   where it was not safe), then lose ``back_off`` of their ``g`` per round; points that move as
   a whole (a group: a shoe, a fist) share their smallest ``g``;
4. after ``rounds`` rounds, up to :attr:`SurfaceGuard.FALLBACK_ROUNDS` more rounds set the
   points still flagged to ``g = 0`` (exactly their LBS), the ramp around them in proportion.

A skin simulated directly (or a character's own pieces) is written as its physics gives it
(``W = P``: its own collisions, volume constraints and layers act on the surface that is written)
while that physics keeps the surface: until a frame in which it turns more than
``trust_flipped`` of the triangles over against LBS, or strains ``trust_strained`` more of its
edges than LBS does (the strain a few rings around the places where LBS passes through itself
left out where the physics kept those sides apart with no crossing of its own: LBS is no
reference there, and keeping the sides apart bunches the skin between them, as in a deep
flex's crease). From that frame on (a crumpled
skin: a low-poly leg folded by its contacts) it is guarded as every captured mesh is. A skin
simulated on a refined copy is written with chords of the simulated surface, which its collisions
do not see: while trusted, its intersecting pairs that LBS does not have are still taken back, as
above, and only they (``chords``).

Invariants: with no flag ``W = P`` exactly; ``g = 0`` gives ``W = L`` exactly. A mesh the
guard converged on has no strained edge or flipped triangle that LBS does not have (within the
thresholds above, which are tighter than the measures of :mod:`warpskin.quality`), and no more
intersecting pairs than LBS. The guard changes only what is written, never the simulation.

Limits: it is a per-frame repair, not physics: where it holds a region, that region's
secondary motion is lost while held, and ``g`` can fall within one frame where the physical
result turns bad at once (it rises back over frames). How much it held is reported per frame
(:attr:`SurfaceGuard.guarded`, :attr:`SurfaceGuard.held`).
"""


from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..metrics import PairQuery
from ..quality import STRAIN_LIMIT, WrittenMesh, own_fold_kept
from .params import GuardParams, WRITTEN_FLIPPED, WRITTEN_STRAINED, as_written, blend, pair_keys

__all__ = ["SurfaceGuard"]

#: Bisection steps of :meth:`SurfaceGuard.keep`'s share of the way back to the guard's result
#: (a 256th of the way: finer is not seen).
KEEP_BISECTIONS = 8


class SurfaceGuard:
    """The guard of one written mesh (see the module docstring), holding its weight between
    frames.

    Args:
        mesh: The written mesh (:class:`~warpskin.quality.WrittenMesh`: its welded topology,
            edges and rest lengths).
        params: :class:`GuardParams`.
        groups: ``[N]`` per written point, the group of points that move as a whole (-1: none);
            a group keeps one weight (its smallest).
        ceiling: ``[N]`` per written point, the largest weight in [0, 1] it takes (default 1): a
            skin simulated directly passes its physics weight here (0 where no layer depth fits).
        direct: The mesh is a skin simulated directly: written as simulated while its physics
            keeps the surface (see the module docstring).
        intended: ``[N]`` per written point, where the physics stretches the surface on
            purpose (a muscle's belly, :meth:`~warpskin.model.SkinModelBuilder.rest_drive_support`):
            an edge wholly inside it that is longer than at rest is neither flagged nor counted
            against the trust (a pop stretches the skin over its belly by design); shortened
            edges and turned triangles there are, as everywhere.
        chords: The mesh is a skin simulated on a refined copy, written with its own triangles
            (chords of the simulated surface, whose collisions do not see them): while trusted,
            its intersecting pairs LBS does not have are still taken back (only they: its
            strain and turned triangles are its physics').
    """

    #: Rounds after the back-off that set what is still flagged to its LBS.
    FALLBACK_ROUNDS = 4

    def __init__(self, mesh: WrittenMesh, params: GuardParams | None = None, groups: np.ndarray | None = None,
                 ceiling: np.ndarray | None = None, direct: bool = False,
                 intended: np.ndarray | None = None, chords: bool = False) -> None:
        #: Whether the mesh is written as simulated (a skin simulated directly, until a frame's
        #: physical result crumples past ``trust_flipped`` or ``trust_strained``; then never again).
        self.trusted = bool(direct)
        #: The mesh is written with chords of the simulated surface (a skin simulated on a
        #: refined copy): its crossings are taken back while it is trusted too.
        self.chords = bool(chords)
        self.mesh = mesh
        self.params = params or GuardParams()
        c = mesh.first.size
        self.count = c
        e = mesh.edges
        rows, cols = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
        self._graph = sp.csr_matrix((np.concatenate([mesh.rest_length, mesh.rest_length]), (rows, cols)), shape=(c, c))
        #: The median rest edge [m]: the unit of ``match`` and of the smallest ramp.
        self.edge = float(np.median(mesh.rest_length)) if mesh.rest_length.size else 0.0
        #: Displacement [m] below which a new pair is taken for a contact LBS has to within
        #: rounding: 1e-3 of the median rest edge.
        self.noise = 1e-3 * self.edge
        t = mesh.welded_triangles
        rest = mesh.welded(mesh.rest)
        area2 = np.linalg.norm(np.cross(rest[t[:, 1]] - rest[t[:, 0]], rest[t[:, 2]] - rest[t[:, 0]]), axis=1)
        self._floor = mesh._area_floor
        self._tri = t[area2 > self._floor]  # flips are judged on triangles not degenerate at rest
        self._tri_rows = mesh.measured_triangles[area2 > self._floor]  # their file triangles
        # the frame's skinned normals of the judged triangles (:meth:`apply`'s ``skinned``), or None
        self._ref: np.ndarray | None = None
        self._all_tri = t
        self._query = PairQuery(t)  # the pair counts' tree and buffers, kept from frame to frame
        self._cos = float(np.cos(np.radians(self.params.flip_degrees)))
        # where pieces cross or touch at rest (a ball joint inside a tube's end, the seam of two
        # pieces): the triangles within two median edges of a triangle that intersects another
        # at rest, or whose box comes within 0.1 median edge of a triangle of another piece
        self._crossing = np.zeros(len(t), dtype=bool)
        #: Keys of the pairs that intersect at rest (they never mark LBS as passing through itself).
        self._rest_pairs = self._pairs(rest) if len(t) > 1 else np.zeros(0, dtype=np.int64)
        # the triangles near LBS's own crossings in the frame being guarded (:meth:`_pose_crossings`)
        self._pose_crossing = np.zeros(len(t), dtype=bool)
        if self.params.pairs and len(t) > 1:
            from scipy.sparse.csgraph import connected_components, dijkstra

            at_rest = self._rest_pairs
            src = [t[np.concatenate([at_rest // len(t), at_rest % len(t)])].ravel()]
            _, piece = connected_components(self._graph, directed=False)
            corners = rest[t]
            pad = 0.1 * self.edge
            touch = self._query.overlapping(corners.min(axis=1) - pad, corners.max(axis=1) + pad)
            touch = touch[piece[t[touch[:, 0], 0]] != piece[t[touch[:, 1], 0]]]
            src.append(t[touch.ravel()].ravel())
            src = np.unique(np.concatenate(src))
            if src.size:
                near = np.isfinite(dijkstra(self._graph, directed=False, indices=src, min_only=True, limit=2.0 * self.edge))
                self._crossing = near[t].all(axis=1)
        self.group = None
        if groups is not None:
            g = np.asarray(groups, dtype=np.int64)[mesh.first]
            if (g >= 0).any():
                _, inverse = np.unique(np.where(g >= 0, g, -1 - np.arange(c)), return_inverse=True)
                self.group = inverse.ravel()
        # the edges wholly inside the intended stretch: their stretching is neither flagged nor
        # counted against the trust
        self._intended = np.zeros(len(e), dtype=bool)
        if intended is not None:
            self._intended = np.asarray(intended, dtype=bool)[mesh.first][e].all(axis=1)
        self.ceiling = np.ones(c) if ceiling is None else np.clip(np.asarray(ceiling, dtype=np.float64)[mesh.first], 0, 1)
        #: ``[C]`` the weight of every welded point after the last frame.
        self.g = self.ceiling.copy()
        #: What the first round of the last frame flagged: ``edges``, ``flipped``, ``pairs``.
        self.flags: dict = {}
        #: Fallback rounds the last frame needed (0: the back-off sufficed).
        self.fallbacks = 0
        #: After each :meth:`apply`: the pair counts of the result and of LBS (``None`` where the
        #: result was not counted exactly: the guard off, or not converged).
        self.pair_counts: tuple[int, int] | None = None
        #: The same pairs as keys (:meth:`~warpskin.quality.WrittenMesh.pair_keys_of_two`), or ``None``.
        self.pair_keys: tuple[np.ndarray, np.ndarray] | None = None
        # the last apply's physical result and LBS, as written (:meth:`take_back` blends them)
        self._frame: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ measures
    def _strain(self, x: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
        """``max(l / l0, l0 / l)`` of every welded edge (or of the edges ``which`` selects)."""
        e, rest = self.mesh.edges, self.mesh.rest_length
        if which is not None:
            e, rest = e[which], rest[which]
        length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
        with np.errstate(divide="ignore"):
            r = length / rest
            return np.maximum(r, 1.0 / r)

    def _stretched(self, x: np.ndarray, among: np.ndarray) -> np.ndarray:
        """``[E]``: the edges of ``among`` (a mask) wholly inside the intended stretch that are
        longer in ``x`` than at rest."""
        out = among & self._intended
        if out.any():
            e, rest = self.mesh.edges[out], self.mesh.rest_length[out]
            out[out] = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) > rest
        return out

    def _normals(self, x: np.ndarray, which: np.ndarray | None = None) -> np.ndarray:
        """Area-weighted normals of the triangles judged for flips (or of those ``which``
        selects)."""
        t = self._tri if which is None else self._tri[which]
        return np.cross(x[t[:, 1]] - x[t[:, 0]], x[t[:, 2]] - x[t[:, 0]])

    def _cosines(self, x: np.ndarray, n_lbs: np.ndarray, len_lbs: np.ndarray,
                 which: np.ndarray | None = None) -> np.ndarray:
        """The cosine of every judged triangle's normal in ``x`` against its LBS normal (or of
        those ``which`` selects); 1 where either is degenerate, or where LBS turns the triangle
        over against the frame's skinned normal and ``x`` does not (:meth:`apply`'s
        ``skinned``): never a flip."""
        if which is not None:
            n_lbs, len_lbs = n_lbs[which], len_lbs[which]
        n = self._normals(x, which)
        ln = np.linalg.norm(n, axis=1)
        ok = (ln > self._floor) & (len_lbs > self._floor)
        cos = np.where(ok, np.einsum("ij,ij->i", n, n_lbs) / np.where(ok, ln * len_lbs, 1.0), 1.0)
        if self._ref is not None:  # LBS's own folds, kept the right way: no flip
            ref = self._ref if which is None else self._ref[which]
            cos = np.where(own_fold_kept(n, n_lbs, ref), 1.0, cos)
        return cos

    def _pairs(self, x: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        """Keys of the intersecting pairs of ``x`` (with ``active``: those with an active
        triangle, on the tree of the frame's :meth:`_pairs_of_two`, refitted)."""
        found = self._query.pairs(x) if active is None else self._query.active(x, active)
        return pair_keys(found, len(self._all_tri))

    def _pairs_of_two(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Keys of the intersecting pairs of ``x`` and of ``y``, in one pass."""
        n = len(self._all_tri)
        a, b = self._query.of_two(x, y)
        return pair_keys(a, n), pair_keys(b, n)

    def _min_in_groups(self, g: np.ndarray) -> np.ndarray:
        if self.group is None:
            return g
        low = np.full(int(self.group.max()) + 1, np.inf)
        np.minimum.at(low, self.group, g)
        return low[self.group]

    def _match(self, new: np.ndarray, lost: np.ndarray, lbs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Match pairs that appeared (keys ``new``) one to one with pairs that went (``lost``)
        near them: nearest first, by the pairs' centres on ``lbs``, within ``match`` median
        edges (a crossing that slid trades a pair for its neighbour). Returns the matched masks
        ``([len(new)], [len(lost)])``."""
        from scipy.spatial import cKDTree

        matched_new = np.zeros(new.size, dtype=bool)
        matched_lost = np.zeros(lost.size, dtype=bool)
        if not (new.size and lost.size and self.params.match > 0):
            return matched_new, matched_lost
        tris = self._all_tri
        tri_count = len(tris)

        def centres(keys):
            return (lbs[tris[keys // tri_count]].sum(axis=1) + lbs[tris[keys % tri_count]].sum(axis=1)) / 6.0

        k = min(8, lost.size)
        dist, j = cKDTree(centres(lost)).query(centres(new), k=k, distance_upper_bound=self.params.match * self.edge)
        dist, j = dist.reshape(new.size, k).ravel(), j.reshape(new.size, k).ravel()
        i = np.repeat(np.arange(new.size), k)
        near = np.isfinite(dist)
        i, j, dist = i[near], j[near], dist[near]
        order = np.argsort(dist, kind="stable")
        for a, b in zip(i[order].tolist(), j[order].tolist()):  # greedy, nearest first
            if not matched_new[a] and not matched_lost[b]:
                matched_new[a] = matched_lost[b] = True
        return matched_new, matched_lost

    def _new_pairs(self, pairs_w: np.ndarray, pairs_lbs: np.ndarray, lbs: np.ndarray, moved: np.ndarray) -> np.ndarray:
        """The keys of the pairs of ``pairs_w`` the guard takes back: those LBS does not have,
        less those where pieces cross or touch at rest, or where LBS passes through itself this
        frame (:meth:`_pose_crossings`), that are matched with a pair LBS has and ``pairs_w``
        lost (:meth:`_match`: a crossing that slid). While the mesh has no more pairs than LBS,
        pairs whose points moved by less than :attr:`noise` (``moved`` [m] per point) are left
        too (a contact LBS has to within rounding)."""
        new = np.setdiff1d(pairs_w, pairs_lbs, assume_unique=True)
        if not new.size:
            return new
        tri_count = len(self._all_tri)
        cr = self._crossing | self._pose_crossing
        crossing = cr[new // tri_count] & cr[new % tri_count]
        keep = np.ones(new.size, dtype=bool)
        if crossing.any():
            keep[crossing] = ~self._match(new[crossing], np.setdiff1d(pairs_lbs, pairs_w, assume_unique=True), lbs)[0]
        if pairs_w.size <= pairs_lbs.size:
            tris, tri_count = self._all_tri, len(self._all_tri)
            amount = np.maximum(moved[tris[new // tri_count]].max(axis=1), moved[tris[new % tri_count]].max(axis=1))
            keep &= amount > self.noise
        return new[keep]

    def _pose_crossings(self, pairs_lbs: np.ndarray) -> np.ndarray:
        """Mark, for this frame, where LBS passes through itself (``pairs_lbs``: the keys of its
        pairs; those of the rest pose left out): the triangles within two median edges of such
        a pair's points (:attr:`_pose_crossing`). There, as where pieces cross at rest, a new
        pair matched with one LBS has and the result lost is a crossing that slid
        (:meth:`_new_pairs`): keeping a crease apart, the physics moves where its sides meet.
        Returns those pairs' welded points, ``[K]``."""
        from scipy.sparse.csgraph import dijkstra

        own = np.setdiff1d(pairs_lbs, self._rest_pairs, assume_unique=True)
        n = len(self._all_tri)
        src = np.unique(self._all_tri[np.concatenate([own // n, own % n])].ravel())
        self._pose_crossing = np.zeros(n, dtype=bool)
        if src.size:
            near = np.isfinite(dijkstra(self._graph, directed=False, indices=src, min_only=True, limit=2.0 * self.edge))
            self._pose_crossing = near[self._all_tri].all(axis=1)
        return src

    def _kept_apart(self, pw: np.ndarray, lw: np.ndarray, s_lbs: np.ndarray) -> bool:
        """Whether a physical result that strains more edges than the trust allows
        (:meth:`_strain_excess`, up to :data:`WRITTEN_STRAINED`) only bunched the skin where LBS
        passes through itself, and kept the two sides apart (the trust is then kept).

        Where LBS passes through itself (pairs of ``lw``, the welded LBS, that the rest pose does
        not have; ``pw``: the welded physical result, ``[C, 3]`` [m]), it is no reference for
        the surface: its triangles there lie inside the body, and a result that keeps the two
        sides apart must bunch or stretch the skin between them (a deep flex's crease). The
        zone: the welded points within ``R`` along the surface (rest edges) of a point of such
        a pair's triangles, ``R`` the largest displacement from LBS of those points (how far the
        sides were moved apart: the skin bunches over about that distance), at least two median
        edges. True where the result has no intersecting pair the guard would take back
        (:meth:`_new_pairs`) and strains no more edges outside the zone than LBS does over the
        whole mesh (LBS strains its side of a crease too, the physics bunches it over a wider
        area) by ``trust_strained``."""
        from scipy.sparse.csgraph import dijkstra

        moved = np.linalg.norm(pw - lw, axis=1)
        pairs_p, pairs_lbs = self._pairs_of_two(pw, lw)
        src = self._pose_crossings(pairs_lbs)
        if not src.size or self._new_pairs(pairs_p, pairs_lbs, lw, moved).size:
            return False
        radius = max(float(moved[src].max()), 2.0 * self.edge)
        near = np.isfinite(dijkstra(self._graph, directed=False, indices=src, min_only=True, limit=radius))
        zone = near[self.mesh.edges].any(axis=1)
        return self._strain_excess(pw, s_lbs, excused=zone) <= self.params.trust_strained

    def _strain_excess(self, physical: np.ndarray, s_lbs: np.ndarray, excused: np.ndarray | None = None) -> float:
        """The share of the mesh's edges past :data:`~warpskin.quality.STRAIN_LIMIT` in the
        physical result beyond LBS's (``s_lbs``): the edges wholly inside the intended stretch
        counted only where they are shortened, the result's edges ``excused`` (``[E]``) not at
        all."""
        s = self._strain(physical)
        judged = ~self._stretched(physical, s > STRAIN_LIMIT)
        mine = (s > STRAIN_LIMIT) & judged
        if excused is not None:
            mine &= ~excused
        return (np.count_nonzero(mine) - np.count_nonzero((s_lbs > STRAIN_LIMIT) & judged)) / max(len(s), 1)

    def _turned(self, physical: np.ndarray, n_lbs: np.ndarray, len_lbs: np.ndarray) -> float:
        """The share of the judged triangles the physical result turns over against LBS (normal
        against normal, ``n_lbs`` with lengths ``len_lbs``; degenerate ones and LBS's own folds
        kept the right way never: :meth:`_cosines`)."""
        return np.count_nonzero(self._cosines(physical, n_lbs, len_lbs) < 0.0) / max(len(self._tri), 1)

    def _trusted_after(self, pw: np.ndarray, lw: np.ndarray, s_lbs: np.ndarray, n_lbs: np.ndarray,
                       len_lbs: np.ndarray) -> bool:
        """Whether a trusted mesh stays trusted with the physical result ``pw``: it turns at
        most ``trust_flipped`` of its triangles over against LBS (:meth:`_turned`) and strains
        at most ``trust_strained`` more of its edges than LBS (:meth:`_strain_excess`), or up to
        :data:`WRITTEN_STRAINED` where it bunched only around LBS's own crossings
        (:meth:`_kept_apart`)."""
        if self._turned(pw, n_lbs, len_lbs) > self.params.trust_flipped:
            return False
        excess = self._strain_excess(pw, s_lbs)
        if excess <= self.params.trust_strained:
            return True
        return excess <= WRITTEN_STRAINED and self._kept_apart(pw, lw, s_lbs)

    def _falloff(self, flagged: np.ndarray, moved: np.ndarray) -> np.ndarray:
        """``[C]`` in [0, 1]: 1 on the ``flagged`` points, falling smoothly to 0 at the distance
        ``R`` along the surface (its rest edges): ``(1 - (r / R)^2)^3``. ``R`` is ``spread`` x
        the largest displacement ``moved`` [m] of a flagged point (at least two median edges),
        so that taking back a share of the displacement strains the ramp's edges by about
        ``1 / spread`` of that share."""
        from scipy.sparse.csgraph import dijkstra

        src = np.nonzero(flagged)[0]
        radius = max(self.params.spread * float(moved[src].max()), 2.0 * self.edge)
        dist = dijkstra(self._graph, directed=False, indices=src, min_only=True, limit=radius)
        u = np.clip(dist / radius, 0.0, 1.0)
        return np.where(np.isfinite(dist), (1.0 - u * u) ** 3, 0.0)

    # ------------------------------------------------------------------ per frame
    def apply(self, points: np.ndarray, lbs: np.ndarray, skinned: np.ndarray | None = None) -> np.ndarray:
        """The guarded points of one frame, ``[N, 3]`` in the mesh's file order (``points``: the
        physical result, ``lbs``: the mesh's LBS, both ``[N, 3]`` [m]); advances the guard's
        weight. Returns ``points`` itself where nothing is held, else the blend rounded to
        float32 as USD stores it (the checks are made on those values). ``skinned``: the
        frame's :meth:`~warpskin.quality.WrittenMesh.skinned_normals` (``[T, 3]``, file
        triangles), where known: a triangle LBS turns over against it (LBS's own fold, a
        collapsed crease) is not flagged, nor counted against the trust, where the result keeps
        it the right way; it also holds for this frame's :meth:`keep`."""
        prm, mesh = self.params, self.mesh
        p = np.asarray(points, dtype=np.float64)
        lb = np.asarray(lbs, dtype=np.float64)
        self.fallbacks = 0
        self.flags = {"edges": 0, "flipped": 0, "pairs": 0}
        if not prm.enabled or self.count == 0:
            self.pair_counts = self.pair_keys = None
            if np.all(self.ceiling >= 1.0):
                return p
            return self.blend(p, lb, self.ceiling)
        # judged as it is written: USD points are float32, and a pair that touches to within
        # their rounding comes or goes with it
        given = p
        lb, p = as_written(lb), as_written(p)
        self._frame = (p, lb)
        lw = mesh.welded(lb)
        pw = mesh.welded(p)
        self._ref = None if skinned is None else np.asarray(skinned, dtype=np.float64)[self._tri_rows]
        d = pw - lw
        moving = np.linalg.norm(d, axis=1) > 0.0
        g_prev = self.g
        g = np.minimum(self.ceiling, g_prev + prm.recover)
        s_lbs = self._strain(lw)
        edge_ok_lbs = s_lbs <= STRAIN_LIMIT
        n_lbs = self._normals(lw)
        len_lbs = np.linalg.norm(n_lbs, axis=1)
        tris, tri_count = self._all_tri, len(self._all_tri)
        e, t = mesh.edges, self._tri
        if self.trusted:  # guarded from the first frame whose physics crumples on
            self.trusted = self._trusted_after(pw, lw, s_lbs, n_lbs, len_lbs)
        shape = True  # strained edges and turned triangles are flagged (not on a trusted mesh)
        pairs_lbs, pairs_w, active = np.zeros(0, dtype=np.int64), None, None
        check = self.chords and prm.pairs and len(self._all_tri) > 1
        if self.trusted:
            crossing = False
            if check:  # chords cross where the simulated surface does not: taken back where LBS does not
                pairs_w, pairs_lbs = self._pairs_of_two(as_written(blend(pw, lw, g)), lw)
                self._pose_crossings(pairs_lbs)
                crossing = self._new_pairs(pairs_w, pairs_lbs, lw, np.linalg.norm(g[:, None] * d, axis=1)).size > 0
            if not crossing:
                self.g = g
                self.pair_counts = self.pair_keys = None
                if np.all(g >= 1.0):
                    return given
                return self.blend(p, lb, g)
            shape = False
        converged = False
        last = prm.rounds + self.FALLBACK_ROUNDS
        r = 0
        changed = None  # the points whose weight the last round changed (None: every point)
        while r <= last:
            w = as_written(blend(pw, lw, g))
            flag = np.zeros(self.count, dtype=bool)
            if changed is None:
                s, cos = self._strain(w), self._cosines(w, n_lbs, len_lbs)
            else:  # only the edges and triangles of the points that moved
                ce, ct = changed[e].any(axis=1), changed[t].any(axis=1)
                s[ce] = self._strain(w, ce)
                cos[ct] = self._cosines(w, n_lbs, len_lbs, ct)
            strained = (s > prm.strain) & (s > s_lbs + 0.01) & (edge_ok_lbs | (s > 1.1 * s_lbs)) & shape
            strained &= ~self._stretched(w, strained)
            flag[e[strained].ravel()] = True
            flipped = (cos < self._cos) & shape
            flag[t[flipped].ravel()] = True
            new = np.zeros(0, dtype=np.int64)
            if prm.pairs:
                if pairs_w is None:  # both counts of the frame in one pass
                    pairs_w, pairs_lbs = self._pairs_of_two(w, lw)
                    self._pose_crossings(pairs_lbs)
                elif active is not None and active.any():  # only the pairs of moved triangles change
                    a, b = pairs_w // tri_count, pairs_w % tri_count
                    pairs_w = np.union1d(pairs_w[~(active[a] | active[b])], self._pairs(w, active))
                new = self._new_pairs(pairs_w, pairs_lbs, lw, np.linalg.norm(g[:, None] * d, axis=1))
                flag[tris[np.concatenate([new // tri_count, new % tri_count])].ravel()] = True
            if r == 0:
                self.flags = {"edges": int(strained.sum()), "flipped": int(flipped.sum()), "pairs": int(new.size)}
            flag &= moving  # a point at its LBS can be neither helped nor harmed by its weight
            if not flag.any():
                converged = True
                break
            if r == last:
                break  # still flagged: the measures will say so
            ramp = self._falloff(flag, np.linalg.norm(g[:, None] * d, axis=1))
            if r >= prm.rounds:  # the back-off did not suffice: what is flagged goes to its LBS
                g_new = g * (1.0 - ramp)
                self.fallbacks += 1
            elif r == 0 and np.any((g > g_prev) & flag):
                g_new = g - ramp * (g - np.minimum(g, g_prev))  # take back the rise where it was unsafe
            else:
                g_new = g * (1.0 - prm.back_off * ramp)
            g_new = self._min_in_groups(g_new)
            changed = g_new != g
            active = changed[tris].any(axis=1)
            g = g_new
            r += 1
        self.g = g
        self.pair_counts = (int(pairs_w.size), int(pairs_lbs.size)) if prm.pairs and converged else None
        self.pair_keys = (pairs_w, pairs_lbs) if prm.pairs and converged else None
        if np.all(g >= 1.0):
            return given
        return self.blend(p, lb, g)

    def take_back(self, flag: np.ndarray, fallback: bool = False) -> np.ndarray | None:
        """One more round of this frame's back-off, asked for from outside the mesh (its pieces
        crossing another written mesh's, :class:`CrossGuard`): the ``flag``-ged welded points
        (``[C]`` bool) and the ramp around them lose ``back_off`` of their weight (``fallback``:
        all of it, to their LBS), a group as a whole; points at their LBS are left out. Returns
        the mesh's new written points (``[N, 3]``, file order, rounded as written) after the
        last :meth:`apply`, or ``None`` where no flagged point can move."""
        frame = self._frame
        if frame is None or not self.params.enabled or self.count == 0:
            return None
        p, lb = frame
        d = self.mesh.welded(p) - self.mesh.welded(lb)
        moved = np.linalg.norm(self.g[:, None] * d, axis=1)
        flag = np.asarray(flag, dtype=bool) & (moved > 0.0)
        if not flag.any():
            return None
        ramp = self._falloff(flag, moved)
        g = self._min_in_groups(self.g * (1.0 - (1.0 if fallback else self.params.back_off) * ramp))
        if fallback:
            self.fallbacks += 1
        self.g = g
        self.pair_counts = self.pair_keys = None  # the mesh's own pairs are counted again
        return self.blend(p, lb, g)

    def keep(self, limited: np.ndarray, guarded: np.ndarray, lbs: np.ndarray) -> np.ndarray:
        """``limited`` (the guarded points after the :class:`JumpLimit`, ``[N, 3]`` [m], file
        order), unless it leaves the bounds the quality checks ask that ``guarded`` (this
        frame's :meth:`apply`) keeps better, against ``lbs``: more than :data:`WRITTEN_STRAINED`
        of its edges past :data:`~warpskin.quality.STRAIN_LIMIT` beyond LBS's, or more than
        :data:`WRITTEN_FLIPPED` of its triangles turned over against LBS, and more of them than
        ``guarded``. Then the points of the edges and triangles that make it worse go towards
        ``guarded``, and a smooth ramp around them part way (:meth:`_falloff`; a group moves as a
        whole, by its largest share), by the least share of the way (bisection,
        :data:`KEEP_BISECTIONS` steps) at which no edge is strained and no triangle turned
        over that is not in ``guarded`` (or LBS, for the edges), else all the way; they jump
        by more than the limit there. Within the bounds
        the limit's cut stands: it keeps points from jumping. ``limited`` itself where nothing
        is taken back."""
        if not self.params.enabled or self.count == 0 or limited is guarded:
            return limited
        mesh = self.mesh
        lw = mesh.welded(as_written(lbs))
        xw, gw = mesh.welded(as_written(limited)), mesh.welded(as_written(guarded))
        e, t = mesh.edges, self._tri
        lbs_over = self._strain(lw) > STRAIN_LIMIT
        x_over, g_over = self._strain(xw) > STRAIN_LIMIT, self._strain(gw) > STRAIN_LIMIT
        n_lbs = self._normals(lw)
        len_lbs = np.linalg.norm(n_lbs, axis=1)
        x_flip, g_flip = self._cosines(xw, n_lbs, len_lbs) < 0.0, self._cosines(gw, n_lbs, len_lbs) < 0.0
        over, over_g, over_lbs = np.count_nonzero(x_over), np.count_nonzero(g_over), np.count_nonzero(lbs_over)
        strained = over - over_lbs > WRITTEN_STRAINED * max(len(e), 1) and over > over_g
        flipped = (np.count_nonzero(x_flip) > WRITTEN_FLIPPED * max(len(t), 1)
                   and np.count_nonzero(x_flip) > np.count_nonzero(g_flip))
        if not (strained or flipped):
            return limited
        flag = np.zeros(self.count, dtype=bool)
        if strained:
            flag[e[x_over & ~g_over & ~lbs_over].ravel()] = True
        if flipped:
            flag[t[x_flip & ~g_flip].ravel()] = True
        if not flag.any():
            return limited
        ramp = self._falloff(flag, np.linalg.norm(xw - gw, axis=1))
        if self.group is not None:
            high = np.zeros(int(self.group.max()) + 1)
            np.maximum.at(high, self.group, ramp)
            ramp = high[self.group]

        def within(share: float) -> bool:  # no edge or triangle worse than guarded's, the ramp taken this far
            y = xw + share * ramp[:, None] * (gw - xw)
            return not (np.any((self._strain(y) > STRAIN_LIMIT) & ~g_over & ~lbs_over) or
                        np.any((self._cosines(y, n_lbs, len_lbs) < 0.0) & ~g_flip))

        # the least share of the way to ``guarded`` at which no edge or triangle is worse than
        # there (bisection): the rest of the limit's cut stands, so the points jump no farther
        # than they must
        lo, hi = 0.0, 1.0
        if within(hi):
            for _ in range(KEEP_BISECTIONS):
                mid = 0.5 * (lo + hi)
                lo, hi = (lo, mid) if within(mid) else (mid, hi)
        out = xw + hi * ramp[:, None] * (gw - xw)
        return as_written(out[mesh.weld])

    def blend(self, p: np.ndarray, lb: np.ndarray, g: np.ndarray) -> np.ndarray:
        """:func:`blend` per file point (``g`` per welded point), rounded as it is written."""
        return as_written(blend(p, lb, g[self.mesh.weld]))

    @property
    def guarded(self) -> float:
        """The share of the mesh's welded points the guard holds (``g`` under its ceiling: 1, or
        a directly simulated skin's physics weight) after the last frame."""
        return float(np.mean(self.g < self.ceiling)) if self.count else 0.0

    @property
    def held(self) -> float:
        """The mean of ``ceiling - g`` over the mesh's welded points after the last frame (0:
        nothing held, 1: all written as LBS where it would be all physical): what the guard took
        back, not what the physics weight leaves to LBS."""
        return float(np.mean(np.maximum(self.ceiling - self.g, 0.0))) if self.count else 0.0

"""What the user sees: the quality of every written mesh, frame by frame, against the same mesh
under linear blend skinning.

A bake is judged on the meshes it writes, in the file's own topology, not on the surface the
solver simulated (a cage, or a refined skin): :class:`WrittenMesh` measures one written mesh
per frame against its rest shape and its own LBS, and :class:`QualityLog` keeps the series of
every written mesh of a run, its worst frames and the range checks.

Measures of one frame (``points`` and ``lbs``, both ``[N, 3]`` in the file's vertex order):

* **strain**: the share of the mesh's edges whose length is more than :data:`STRAIN_LIMIT` x
  their rest length or less than ``1 / STRAIN_LIMIT`` of it (stretched or crumpled), beside the
  same share under LBS; and the worst ratio ``max(l / l0, l0 / l)``;
* **flips**: the share of its triangles whose normal turns by more than 90 degrees against the
  same triangle under LBS (``n . n_lbs < 0``; triangles degenerate at rest or in either pose do
  not count);
* **pairs**: intersecting triangle pairs of the mesh (the exact test of
  :func:`~warpskin.metrics.self_intersections` on the mesh welded by rest position, so that
  triangles meeting across a UV seam count as neighbours), beside LBS's; and the pairs beyond
  those the rest pose already has (pieces that cross at rest: a bun sunk into the skull, an eye
  in its socket), beside LBS's: what the animation added and the physics did or did not undo;
* **offset**: the largest distance of a vertex from its LBS position [m];
* **joint offset**: the same over the points where the mesh meets another piece at rest (a
  robot's shin at its knee and ankle): how far a gap or an overlap opens at its joints [m];
* **split**: the largest distance between two copies of one rest point (file vertices at one
  rest position: a UV seam, flat shading, a split normal) [m], beside LBS's: copies written
  apart open a crack in the surface that the measures above, made on the welded mesh, cannot see.

Seam copies are one vertex for the other measures: edges and pairs are counted once on the
welded mesh. Messages name the file's vertex numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .mesh import face_normals
from .metrics import PairQuery, self_intersections, self_intersections_of_two

__all__ = ["STRAIN_LIMIT", "WrittenMesh", "CrossPairs", "QualityLimits", "QualityLog", "mesh_measures", "own_fold_kept"]

#: An edge is strained when it is longer than this times its rest length, or shorter than its
#: inverse.
STRAIN_LIMIT = 1.5


def _weld(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)``: the first file vertex of every distinct rest position and the weld
    class of every file vertex."""
    _, first, inverse = np.unique(np.asarray(points, dtype=np.float64), axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


@dataclass
class WrittenMesh:
    """One mesh as it is written, with what its measures need, computed once at rest.

    Args:
        name: The mesh's name in the output (its prim).
        triangles: ``[T, 3]`` into the written points (the file's topology).
        rest: ``[N, 3]`` rest positions [m] (the stage-space rest pose the bake starts from).
        file_ids: ``[N]`` the file's own number of every written vertex (for messages;
            default ``0..N-1``).
    """

    name: str
    triangles: np.ndarray
    rest: np.ndarray
    file_ids: np.ndarray | None = None
    #: ``[K]`` its written points where it meets another piece at rest (a joint), whose offset
    #: from LBS is the ``joint_offset`` measure; ``None``: not measured
    joint_points: np.ndarray | None = None
    edges: np.ndarray = field(init=False)
    rest_length: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.rest = np.asarray(self.rest, dtype=np.float64)
        tri = np.asarray(self.triangles, dtype=np.int64).reshape(-1, 3)
        n = self.rest.shape[0]
        self.file_ids = np.arange(n) if self.file_ids is None else np.asarray(self.file_ids, dtype=np.int64)
        first, inverse = _weld(self.rest)
        self.first, self.weld = first, inverse
        wt = inverse[tri]
        keep = (wt[:, 0] != wt[:, 1]) & (wt[:, 1] != wt[:, 2]) & (wt[:, 0] != wt[:, 2])
        self.triangles = tri
        self.welded_triangles = wt[keep]
        self.measured_triangles = np.nonzero(keep)[0]  # file triangles that are triangles once welded
        e = np.sort(np.concatenate([wt[keep][:, [0, 1]], wt[keep][:, [1, 2]], wt[keep][:, [2, 0]]]), axis=1)
        e = np.unique(e, axis=0)
        length = np.linalg.norm(self.rest[first[e[:, 0]]] - self.rest[first[e[:, 1]]], axis=1)
        ok = length > 1e-9 * max(float(np.ptp(self.rest, axis=0).max()) if n else 0.0, 1e-30)
        self.edges, self.rest_length = e[ok], length[ok]
        a, b, c = (self.rest[tri[self.measured_triangles, k]] for k in range(3))
        area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
        scale = float(np.median(area2)) if area2.size else 0.0
        self._area_floor = 1e-8 * scale
        self._tri_ok = self.measured_triangles[area2 > self._area_floor]  # not degenerate at rest
        copy = np.nonzero(first[inverse] != np.arange(n))[0]  # every file vertex that is not its class's first
        self.copies = np.stack([copy, first[inverse[copy]]], axis=1) if copy.size else np.zeros((0, 2), np.int64)
        self.size = float(np.linalg.norm(np.ptp(self.rest, axis=0))) if n else 0.0  # rest bounding-box diagonal [m]

    @property
    def edge_count(self) -> int:
        return int(self.edges.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self._tri_ok.shape[0])

    def welded(self, points: np.ndarray) -> np.ndarray:
        """The welded mesh's points (each class's first file vertex)."""
        return np.asarray(points, dtype=np.float64)[self.first]

    def strain(self, points: np.ndarray) -> np.ndarray:
        """``[E]`` ``max(l / l0, l0 / l)`` of every welded edge (inf for an edge of length 0)."""
        w = self.welded(points)
        length = np.linalg.norm(w[self.edges[:, 0]] - w[self.edges[:, 1]], axis=1)
        with np.errstate(divide="ignore"):
            ratio = length / self.rest_length
            return np.maximum(ratio, 1.0 / ratio)

    def skinned_normals(self, blended: np.ndarray) -> np.ndarray:
        """``[T, 3]`` per file triangle, the normal its rest shape takes under the mean ``B`` of
        its points' blended skinning maps (``blended``: ``[N, 3, 3]``, the linear part of each
        written point's ``sum_k w_k M_k``): ``(B e1) x (B e2) = cof(B) (e1 x e2)``, ``e1, e2``
        its rest edges. This is the orientation LBS gives the triangle where it does not fold
        it: LBS blends the maps point by point, and where they differ much across a triangle
        (a collapsed crease) it can turn the triangle over; the mean map cannot."""
        t = self.triangles
        b = np.asarray(blended, dtype=np.float64)[t].mean(axis=1)
        r = self.rest
        e1, e2 = r[t[:, 1]] - r[t[:, 0]], r[t[:, 2]] - r[t[:, 0]]
        return np.cross(np.einsum("tij,tj->ti", b, e1), np.einsum("tij,tj->ti", b, e2))

    def flipped(self, points: np.ndarray, lbs: np.ndarray, skinned: np.ndarray | None = None) -> np.ndarray:
        """Indices of the file triangles whose normal turns by more than 90 degrees against LBS
        (among those not degenerate at rest nor in either pose). With ``skinned``
        (:meth:`skinned_normals` of the frame, ``[T, 3]``), a triangle that LBS itself turns
        over against it (LBS's own fold) is not counted where ``points`` keeps it the right
        way: there LBS is no reference, and unfolding it is the repair."""
        rows = self._tri_ok
        t = self.triangles[rows]

        def normals(x):
            return face_normals(np.asarray(x, dtype=np.float64), t)

        n, m = normals(points), normals(lbs)
        la, lb = np.linalg.norm(n, axis=1), np.linalg.norm(m, axis=1)
        ok = (la > self._area_floor) & (lb > self._area_floor)
        turned = ok & (np.einsum("ij,ij->i", n, m) < 0.0)
        if skinned is not None:
            turned &= ~own_fold_kept(n, m, np.asarray(skinned, dtype=np.float64)[rows])
        return rows[turned]

    def split(self, points: np.ndarray) -> tuple[float, int]:
        """``(gap [m], k)``: the largest distance between a file vertex and the first copy of its
        rest point (0 where no two file vertices share one), and the row of :attr:`copies`
        (``[C, 2]`` written indices ``(copy, first)``) where it is (``-1`` for none)."""
        if not self.copies.size:
            return 0.0, -1
        x = np.asarray(points, dtype=np.float64)
        gap = np.linalg.norm(x[self.copies[:, 0]] - x[self.copies[:, 1]], axis=1)
        k = int(np.argmax(gap))
        return float(gap[k]), k

    def pairs(self, points: np.ndarray) -> int:
        """Intersecting triangle pairs of the welded mesh (the exact test)."""
        return int(len(self_intersections(self.welded(points), self.welded_triangles)))

    def pairs_of_two(self, points: np.ndarray, lbs: np.ndarray) -> tuple[int, int]:
        """:meth:`pairs` of ``points`` and of ``lbs``, found in one pass."""
        a, b = self.pair_keys_of_two(points, lbs)
        return int(len(a)), int(len(b))

    def pair_keys_of_two(self, points: np.ndarray, lbs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The intersecting pairs of ``points`` and of ``lbs`` as sorted keys ``i T + j``
        (``i < j`` welded triangles, ``T`` their count), found in one pass."""
        a, b = self_intersections_of_two(self.welded(points), self.welded(lbs), self.welded_triangles)
        t = len(self.welded_triangles)
        return np.unique(a[:, 0] * t + a[:, 1]), np.unique(b[:, 0] * t + b[:, 1])

    @property
    def rest_pair_keys(self) -> np.ndarray:
        """The keys (:meth:`pair_keys_of_two`) of the pairs the rest pose has (computed once)."""
        keys = getattr(self, "_rest_keys", None)
        if keys is None:
            a = self_intersections(self.welded(self.rest), self.welded_triangles)
            keys = self._rest_keys = np.unique(a[:, 0] * len(self.welded_triangles) + a[:, 1])
        return keys

    def pairs_beyond_rest(self, keys: np.ndarray) -> int:
        """How many more intersecting pairs ``keys`` has than the rest pose, per pair of pieces
        of the mesh (connected components of the welded mesh, each with itself too): the sum
        over piece pairs of the count above that pair's count at rest."""
        return int(self.piece_pairs_beyond_rest(keys).sum())

    def piece_pairs_beyond_rest(self, keys: np.ndarray) -> np.ndarray:
        """``[P * P]`` per pair of pieces (row :meth:`piece_pair_ids`), how many more
        intersecting pairs ``keys`` has there than the rest pose (0 where it has fewer)."""
        return np.maximum(self._piece_pair_counts(keys) - self.rest_piece_pairs, 0)

    @property
    def rest_piece_pairs(self) -> np.ndarray:
        """``[P * P]`` the rest pose's intersecting pairs per pair of pieces (computed once)."""
        if getattr(self, "_rest_piece_pairs", None) is None:
            self._rest_piece_pairs = self._piece_pair_counts(self.rest_pair_keys)
        return self._rest_piece_pairs

    @property
    def piece_of_triangle(self) -> np.ndarray:
        """``[T]`` the piece (a connected part of the welded mesh, numbered ``0..P-1``) of each
        of :attr:`welded_triangles` (computed once)."""
        if getattr(self, "_piece_of_tri", None) is None:
            from scipy.sparse.csgraph import connected_components
            import scipy.sparse as sp

            t = self.welded_triangles
            c = self.first.size
            rows, cols = np.concatenate([t[:, 0], t[:, 1]]), np.concatenate([t[:, 1], t[:, 2]])
            _, label = connected_components(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(c, c)),
                                            directed=False)
            self._piece_of_tri = label[t[:, 0]]
            self._pieces = int(label.max()) + 1 if c else 0
        return self._piece_of_tri

    @property
    def piece_count(self) -> int:
        """``P``: how many pieces :attr:`piece_of_triangle` numbers (isolated points count)."""
        self.piece_of_triangle
        return self._pieces

    def piece_pair_ids(self, keys: np.ndarray) -> np.ndarray:
        """The pair of pieces of each pair of ``keys`` (:meth:`pair_keys_of_two`), as
        ``lo * P + hi`` (``lo <= hi`` the pieces of its triangles, ``P`` :attr:`piece_count`)."""
        piece = self.piece_of_triangle
        t = len(self.welded_triangles)
        k = np.asarray(keys, dtype=np.int64)
        a, b = piece[k // t], piece[k % t]
        return np.minimum(a, b) * self._pieces + np.maximum(a, b)

    def _piece_pair_counts(self, keys: np.ndarray) -> np.ndarray:
        """``[P * P]`` the pairs of ``keys`` per (lower, higher) pair of pieces."""
        ids = self.piece_pair_ids(keys)
        return np.bincount(ids, minlength=self._pieces * self._pieces)


class CrossPairs:
    """Intersecting triangle pairs between written meshes: one mesh's triangle through another's
    (a robot's shin through its foot, a sleeve through the arm when they are separate meshes),
    each mesh welded by rest position as in :class:`WrittenMesh`. Counted per pair of meshes
    beyond the pairs that pair has at rest (pieces that sit in each other's sockets in the bind
    pose), as :meth:`WrittenMesh.pairs_beyond_rest` does for the pieces of one mesh.

    Args:
        meshes: Every written mesh, in a fixed order (the keys of the dicts passed per frame are
            their names). Fewer than two: nothing to count.

    Keys of pairs are ``i T + j`` (``i < j`` rows of the meshes' welded triangles stacked in
    ``meshes`` order, ``T`` their count)."""

    def __init__(self, meshes: list[WrittenMesh]) -> None:
        self.meshes = list(meshes)
        m = len(self.meshes)
        point_offsets = np.concatenate([[0], np.cumsum([w.first.size for w in self.meshes])]).astype(np.int64)
        self.triangle_offsets = np.concatenate([[0], np.cumsum([len(w.welded_triangles) for w in self.meshes])])
        tris = [w.welded_triangles + point_offsets[k] for k, w in enumerate(self.meshes)]
        self.triangles = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
        #: ``[T]`` the mesh (its row in ``meshes``) of every stacked welded triangle.
        self.label = np.repeat(np.arange(m), np.diff(self.triangle_offsets)).astype(np.int64)
        self._query = None
        self.rest_counts = np.zeros(m * m, dtype=np.int64)
        if m > 1 and len(self.triangles) > 1:
            self._query = PairQuery(self.triangles, labels=self.label)
            rest = self._stack({w.name: w.rest for w in self.meshes})
            self.rest_counts = self.counts(self._keys(self._query.pairs(rest)))

    @property
    def active(self) -> bool:
        """Whether there are two meshes to cross."""
        return self._query is not None

    def _stack(self, points: dict) -> np.ndarray:
        return np.concatenate([w.welded(points[w.name]) for w in self.meshes])

    def _keys(self, pairs: np.ndarray) -> np.ndarray:
        return np.unique(pairs[:, 0] * len(self.triangles) + pairs[:, 1])

    def keys_of_two(self, points: dict, lbs: dict) -> tuple[np.ndarray, np.ndarray]:
        """The pairs between meshes of ``points`` and of ``lbs`` (``{name: [N, 3]}`` each, every
        mesh), as keys, found in one pass."""
        if self._query is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        a, b = self._query.of_two(self._stack(points), self._stack(lbs))
        return self._keys(a), self._keys(b)

    def keys(self, points: dict, moved: list[int] | None = None, previous: np.ndarray | None = None) -> np.ndarray:
        """The pairs between meshes of ``points`` (``{name: [N, 3]}``), as keys.

        With ``moved`` (rows of ``meshes``) and ``previous`` (the keys of this counter's last
        count): only the meshes of ``moved`` changed since that count, so the pairs of two
        other meshes are kept from ``previous`` and only the moved meshes' triangles query the
        last count's tree, refitted (:meth:`~warpskin.metrics.PairQuery.active`): the same
        keys as a whole count, found at the cost of the moved triangles."""
        if self._query is None:
            return np.zeros(0, np.int64)
        if moved is None or previous is None or not self._query.has_tree:
            return self._keys(self._query.pairs(self._stack(points)))
        act = np.isin(self.label, np.asarray(moved, dtype=np.int64))
        prev = np.asarray(previous, dtype=np.int64)
        t = len(self.triangles)
        kept = prev[~(act[prev // t] | act[prev % t])]
        found = self._query.active(self._stack(points), act)
        return np.union1d(kept, self._keys(found))

    def counts(self, keys: np.ndarray) -> np.ndarray:
        """``[M * M]`` the pairs of ``keys`` per (lower, higher) pair of meshes."""
        m = len(self.meshes)
        t = len(self.triangles)
        k = np.asarray(keys, dtype=np.int64)
        a, b = self.label[k // t], self.label[k % t]
        return np.bincount(np.minimum(a, b) * m + np.maximum(a, b), minlength=m * m)

    def beyond_rest(self, keys: np.ndarray) -> np.ndarray:
        """``[M * M]`` per pair of meshes, how many more pairs ``keys`` has than that pair at rest."""
        return np.maximum(self.counts(keys) - self.rest_counts, 0)

    def measure(self, keys: np.ndarray, keys_lbs: np.ndarray) -> dict:
        """One frame's figures from its keys (:meth:`keys_of_two`): ``pairs_across`` and
        ``pairs_across_lbs`` (all pairs between meshes), ``pairs_across_new`` and
        ``pairs_across_new_lbs`` (beyond the rest pose's, summed over pairs of meshes), and
        ``pairs_across_worst``: the two mesh names where the result's excess over LBS's (beyond
        rest) is largest, with that excess (``None`` where it has none)."""
        w, lb = self.beyond_rest(keys), self.beyond_rest(keys_lbs)
        excess = w - lb
        k = int(np.argmax(excess)) if excess.size else 0
        m = len(self.meshes)
        worst = ((self.meshes[k // m].name, self.meshes[k % m].name, int(excess[k]))
                 if excess.size and excess[k] > 0 else None)
        return {"pairs_across": int(len(keys)), "pairs_across_lbs": int(len(keys_lbs)),
                "pairs_across_new": int(w.sum()), "pairs_across_new_lbs": int(lb.sum()),
                "pairs_across_worst": worst}


def own_fold_kept(n: np.ndarray, n_lbs: np.ndarray, skinned: np.ndarray) -> np.ndarray:
    """``[T]`` bool: the triangles that LBS turns over against their skinned normal (LBS's own
    fold, :meth:`WrittenMesh.skinned_normals`) and that the result (normals ``n``) keeps the
    right way. There LBS is no reference: such a triangle is not a flip. ``n``, ``n_lbs``,
    ``skinned``: ``[T, 3]`` normals of any length."""
    return (np.einsum("ij,ij->i", n_lbs, skinned) < 0.0) & (np.einsum("ij,ij->i", n, skinned) > 0.0)


def mesh_measures(mesh: WrittenMesh, points: np.ndarray, lbs: np.ndarray, *, pairs: bool = True,
                  pair_keys: tuple[np.ndarray, np.ndarray] | None = None, skinned: np.ndarray | None = None) -> dict:
    """The measures of one frame of ``mesh`` (see the module docstring) as a dict: ``strained``,
    ``strained_lbs`` (shares of edges), ``worst_strain`` (ratio) and ``worst_strain_vertex`` (a
    file vertex of that edge), ``flipped`` (share of triangles) and ``flipped_vertex``,
    ``pairs``, ``pairs_lbs``, and ``pairs_new``, ``pairs_new_lbs`` (beyond the rest pose's;
    all ``None`` without ``pairs``; ``pair_keys`` where the caller found them with the same exact
    test on the same welded mesh, as the surface guard does: :meth:`WrittenMesh.pair_keys_of_two`),
    ``offset`` [m] and ``offset_vertex``, ``joint_offset`` [m] (the largest offset of its
    :attr:`WrittenMesh.joint_points`: a gap or overlap opening where it meets its neighbours),
    ``split`` and ``split_lbs`` [m] and ``split_vertices`` (the file vertices of the widest split,
    ``(-1, -1)`` for none). ``skinned``: the frame's :meth:`WrittenMesh.skinned_normals`, where
    LBS's own folds are not to count as flips (:meth:`WrittenMesh.flipped`)."""
    points = np.asarray(points, dtype=np.float64)
    lbs = np.asarray(lbs, dtype=np.float64)
    s, s_lbs = mesh.strain(points), mesh.strain(lbs)
    e = max(mesh.edge_count, 1)
    k = int(np.argmax(s)) if s.size else -1
    flips = mesh.flipped(points, lbs, skinned)
    d = np.linalg.norm(points - lbs, axis=1)
    j = int(np.argmax(d)) if d.size else -1
    counts = (None, None, None, None)
    if pairs:
        if pair_keys is None:
            pair_keys = mesh.pair_keys_of_two(points, lbs)
        counts = (int(pair_keys[0].size), int(pair_keys[1].size), mesh.pairs_beyond_rest(pair_keys[0]),
                  mesh.pairs_beyond_rest(pair_keys[1]))
    split, c = mesh.split(points)
    return {
        "strained": float((s > STRAIN_LIMIT).sum() / e),
        "strained_lbs": float((s_lbs > STRAIN_LIMIT).sum() / e),
        "worst_strain": float(s[k]) if k >= 0 else 1.0,
        "worst_strain_vertex": int(mesh.file_ids[mesh.first[mesh.edges[k, 0]]]) if k >= 0 else -1,
        "flipped": float(flips.size / max(mesh.triangle_count, 1)),
        "flipped_vertex": int(mesh.file_ids[mesh.triangles[flips[0], 0]]) if flips.size else -1,
        "pairs": counts[0],
        "pairs_lbs": counts[1],
        "pairs_new": counts[2],
        "pairs_new_lbs": counts[3],
        "offset": float(d[j]) if j >= 0 else 0.0,
        "offset_vertex": int(mesh.file_ids[j]) if j >= 0 else -1,
        "joint_offset": float(d[mesh.joint_points].max()) if mesh.joint_points is not None and
        mesh.joint_points.size else 0.0,
        "split": split,
        "split_lbs": mesh.split(lbs)[0],
        "split_vertices": tuple(int(v) for v in mesh.file_ids[mesh.copies[c]]) if c >= 0 else (-1, -1),
    }


@dataclass
class QualityLimits:
    """The plausible range of a written mesh; a frame past it stops the run (exit 3) unless the
    run allows unstable results.

    Attributes:
        strained: The share of edges strained past :data:`STRAIN_LIMIT` may exceed LBS's own share
            by at most this.
        flipped: At most this share of triangles may flip against LBS.
        pairs: At most ``pairs_factor x LBS's pairs + max(pairs x triangles, pairs_floor)``
            intersecting pairs.
        pairs_factor: See ``pairs``.
        split: Copies of one rest point may be written at most this share of the mesh's rest
            size (its bounding-box diagonal) farther apart than under LBS: a crack.
    """

    strained: float = 0.05
    flipped: float = 0.05
    pairs: float = 0.005
    pairs_factor: float = 2.0
    pairs_floor: int = 10
    split: float = 1e-4

    def problem(self, mesh: WrittenMesh, m: dict) -> str | None:
        """One line naming what is out of range in the measures ``m`` of ``mesh``, or ``None``."""
        if m["strained"] > m["strained_lbs"] + self.strained:
            return (f"mesh {mesh.name!r} left its plausible range: {100 * m['strained']:.1f} % of its edges are strained past {STRAIN_LIMIT:g}x of "
                    f"their rest length (LBS {100 * m['strained_lbs']:.1f} %; the worst {m['worst_strain']:.3g}x at file "
                    f"vertex {m['worst_strain_vertex']})")
        if m["flipped"] > self.flipped:
            return (f"mesh {mesh.name!r} left its plausible range: {100 * m['flipped']:.1f} % of its triangles are flipped against LBS (the first "
                    f"at file vertex {m['flipped_vertex']})")
        if m["split"] > m["split_lbs"] + self.split * mesh.size:
            a, b = m["split_vertices"]
            return (f"mesh {mesh.name!r} left its plausible range: file vertices {a} and {b}, one rest point, are written "
                    f"{1e3 * m['split']:.3g} mm apart (LBS {1e3 * m['split_lbs']:.3g} mm): a crack in the surface")
        if m["pairs"] is None:
            return None
        allowed = self.pairs_factor * m["pairs_lbs"] + max(self.pairs * mesh.triangle_count, self.pairs_floor)
        if m["pairs"] > allowed:
            return (f"mesh {mesh.name!r} left its plausible range: {m['pairs']} intersecting triangle pairs (LBS {m['pairs_lbs']}; at most "
                    f"{self.pairs_factor:g}x LBS + {100 * self.pairs:g} % of its {mesh.triangle_count} triangles, "
                    f"at least {self.pairs_floor})")
        return None


class QualityLog:
    """Per-frame measures of every written mesh of a run (:func:`mesh_measures`), their worst
    frames, and the range check (:class:`QualityLimits`).

    Args:
        meshes: The written meshes measured (those written with physics).
        limits: The plausible range, or ``None`` for no check.
        pairs: Count intersecting pairs (the costliest measure) every frame.
    """

    ACROSS_KEYS = ("pairs_across", "pairs_across_lbs", "pairs_across_new", "pairs_across_new_lbs",
                   "pairs_across_worst")
    KEYS = ("strained", "strained_lbs", "worst_strain", "flipped", "pairs", "pairs_lbs", "pairs_new", "pairs_new_lbs",
            "offset", "joint_offset", "split", "split_lbs")

    def __init__(self, meshes: list[WrittenMesh], limits: QualityLimits | None = None, *, pairs: bool = True,
                 cross: CrossPairs | None = None) -> None:
        self.meshes = list(meshes)
        self.limits = limits
        self.count_pairs = pairs
        #: The pairs between written meshes (every written mesh, :class:`CrossPairs`), or ``None``.
        self.cross = cross if cross is not None and cross.active and pairs else None
        #: Per frame, the figures of :meth:`CrossPairs.measure` (with ``cross``).
        self.across: dict[str, list] = {k: [] for k in self.ACROSS_KEYS}
        self.series: dict[str, dict[str, list]] = {m.name: {k: [] for k in self.KEYS} for m in self.meshes}
        self.frames: list[float] = []

    def measure(self, frame, points: dict, lbs: dict, *, pairs: dict | None = None,
                extra: dict | None = None, every: tuple[dict, dict] | None = None,
                skinned: dict | None = None) -> str | None:
        """Measure frame ``frame`` (``points[name]``, ``lbs[name]`` for every mesh); returns the first
        range problem (``"frame F: mesh ...``) or ``None``. The series are kept either way.
        ``pairs``: ``{name: (keys, keys_lbs)}`` found already (see :func:`mesh_measures`);
        ``extra``: ``{name: {key: value}}`` further per-frame series to keep (the guard's);
        ``every``: ``(points, lbs)`` of every written mesh (with :attr:`cross`: the pairs
        between meshes; default ``points``, ``lbs``); ``skinned``: ``{name: [T, 3]}`` the
        frame's :meth:`WrittenMesh.skinned_normals`, where known (LBS's own folds are not
        flips)."""
        self.frames.append(frame)
        if self.cross is not None:
            allp, alll = every if every is not None else (points, lbs)
            m = self.cross.measure(*self.cross.keys_of_two(allp, alll))
            for k in self.ACROSS_KEYS:
                self.across[k].append(m[k])
        problem = None
        for mesh in self.meshes:
            m = mesh_measures(mesh, points[mesh.name], lbs[mesh.name], pairs=self.count_pairs,
                              pair_keys=(pairs or {}).get(mesh.name), skinned=(skinned or {}).get(mesh.name))
            for k in self.KEYS:
                self.series[mesh.name][k].append(m[k])
            for k, v in (extra or {}).get(mesh.name, {}).items():
                self.series[mesh.name].setdefault(k, []).append(v)
            if problem is None and self.limits is not None:
                p = self.limits.problem(mesh, m)
                if p is not None:
                    problem = f"frame {frame:g}: the written {p}"
        return problem

    def summary(self) -> dict:
        """Per mesh: the worst frame's value of every measure (and the frame), and the largest
        excess over LBS of strained edges and pairs."""
        out = {}
        for mesh in self.meshes:
            s = self.series[mesh.name]
            if not self.frames:
                continue
            row: dict = {"edges": mesh.edge_count, "triangles": mesh.triangle_count}
            for k in ("strained", "strained_lbs", "worst_strain", "flipped", "offset", "joint_offset", "split"):
                a = np.asarray(s[k], dtype=np.float64)
                i = int(np.argmax(a))
                row[f"max_{k}"] = float(a[i])
                row[f"max_{k}_frame"] = self.frames[i]
            excess = np.asarray(s["strained"]) - np.asarray(s["strained_lbs"])
            row["max_strained_excess"] = float(excess.max())
            row["max_split_excess"] = float((np.asarray(s["split"]) - np.asarray(s["split_lbs"])).max())
            if self.count_pairs:
                p, pl = np.asarray(s["pairs"]), np.asarray(s["pairs_lbs"])
                row["max_pairs"], row["max_pairs_lbs"] = int(p.max()), int(pl.max())
                row["max_pairs_excess"] = int((p - pl).max())
                pn, pnl = np.asarray(s["pairs_new"]), np.asarray(s["pairs_new_lbs"])
                row["max_pairs_new"], row["max_pairs_new_lbs"] = int(pn.max()), int(pnl.max())
            for k in ("guarded", "held", "jump_limited", "worn_repaired", "untangled"):
                if s.get(k):
                    row[f"max_{k}"] = float(np.max(s[k]))
            if s.get("guard_fallbacks"):
                row["guard_fallback_frames"] = int(np.count_nonzero(s["guard_fallbacks"]))
            out[mesh.name] = row
        return out

    def across_summary(self) -> dict:
        """The pairs between written meshes over the frames (empty without :attr:`cross`):
        ``max_pairs_across_new`` and ``..._lbs`` (beyond the rest pose's), ``max_pairs_across_excess``
        (the largest excess of the first over the second in one frame) with its frame and the two
        meshes where it is largest, and ``frames_pairs_across_over``: the frames with any excess."""
        a = self.across
        if self.cross is None or not a["pairs_across_new"]:
            return {}
        new, lbs = np.asarray(a["pairs_across_new"]), np.asarray(a["pairs_across_new_lbs"])
        excess = new - lbs
        i = int(np.argmax(excess))
        worst = a["pairs_across_worst"][i]
        return {"max_pairs_across_new": int(new.max()), "max_pairs_across_new_lbs": int(lbs.max()),
                "max_pairs_across_excess": int(max(excess[i], 0)), "max_pairs_across_excess_frame": self.frames[i],
                "max_pairs_across_excess_meshes": list(worst[:2]) if worst is not None and excess[i] > 0 else None,
                "frames_pairs_across_over": int(np.count_nonzero(excess > 0)), "frames": len(self.frames)}

    def worst(self) -> dict:
        """Over every mesh: the worst strained share, flipped share, pairs excess over LBS and
        offset, each with its mesh and frame (the summary line's figures)."""
        best: dict = {}
        for mesh in self.meshes:
            s = self.series[mesh.name]
            cand = {
                "strained_excess": np.asarray(s["strained"]) - np.asarray(s["strained_lbs"]),
                "flipped": np.asarray(s["flipped"]),
                "offset": np.asarray(s["offset"]),
                "joint_offset": np.asarray(s["joint_offset"]),
                "split_excess": np.asarray(s["split"]) - np.asarray(s["split_lbs"]),
            }
            if self.count_pairs:
                cand["pairs_excess"] = np.asarray(s["pairs"]) - np.asarray(s["pairs_lbs"])
            for k, a in cand.items():
                if a.size == 0:
                    continue
                i = int(np.argmax(a))
                if k not in best or a[i] > best[k]["value"]:
                    best[k] = {"value": float(a[i]), "mesh": mesh.name, "frame": self.frames[i]}
        return best

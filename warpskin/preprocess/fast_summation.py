"""Path layout for the fast summation of region sums over a triangle mesh.

Deul & Bender 2013 (section 4.3, "Fast Summation") compute, for every oriented-particle region,
sums such as ``sum_i m_i x_i`` (the centre of mass) and ``sum_i m_i x_i x_i^T`` (the moment
matrix of equation 1). A region on one layer is an omega-ring: all vertices within ``omega`` edges
of the region's centre, so the naive sums cost ``O(omega^2 n)``. The paper adopts the fast
summation of Diziol, Bender & Bayer 2011 ("Robust real-time deformation of incompressible surface
meshes"), which needs only ``O(omega n)``:

1. **Path layout** (once per topology, shared by all layers): the vertices are covered by paths,
   each vertex on exactly one path, consecutive vertices of a path sharing a mesh edge
   (:func:`build_path_layout`). Concatenated path after path they form :attr:`PathLayout.order`.
2. **Runs** (once per set of regions): a region meets each path in a few maximal runs of
   consecutive path positions (:func:`region_runs`). Long, straight, parallel paths cut a disc of
   radius ``omega`` into about ``2 omega + 1`` runs, whatever its ``~3 omega^2`` vertices.
3. **Prefix sums** (every solver iteration, in parallel): inclusive prefix sums along every path,
   restarting at each path start (:func:`prefix_sums`).
4. **Region sums**: over the runs of a region, ``P[end] - P[start - 1]`` (``P[start - 1]`` taken
   as 0 at a path start) (:func:`run_region_sums`). The terms of sibling particles on adjacent
   layers are added elsewhere.

Layout heuristics (:data:`HEURISTICS`). Both are greedy walks over the vertices, once: start a
path at an unvisited vertex of lowest remaining (unvisited) degree, which lies on the rim of the
visited area, so that consecutive paths lie side by side; extend it forward until stuck, then
backward from its start. Both ends of a finished path are stuck, so no two path ends are ever
adjacent and joining paths afterwards gains nothing.

* ``"warnsdorff"`` (default): step to the unvisited neighbour with the fewest unvisited
  neighbours (Warnsdorff's rule, which keeps the walk hugging the visited area and so makes long,
  parallel rows); ties go to the neighbour that best continues the current direction when
  positions are given, else to the lowest index.
* ``"straight"``: step to the unvisited neighbour whose edge best continues the current direction
  (cosine), ties to fewest unvisited neighbours; a new path inherits the direction of the path
  beside its start. Needs positions.

The cost of a region sum is its number of runs: for parallel rows of vertices the ideal is
``2 omega + 1`` per region; both heuristics come close to it on skin meshes and Warnsdorff
stays closer on irregular ones (``tests/test_paths.py`` measures the mean against that bound).
Warnsdorff makes very long paths (a whole tube can be one path). ``max_path_length`` cuts them
into equal pieces for a one-thread-per-path scan at a small cost in runs.

Float32 accuracy. A prefix difference ``P[end] - P[start-1]`` carries an absolute error of about
``eps * |P|``, and ``|P|`` grows with the path length, so plain float32 prefix sums lose digits on
long paths. :func:`run_region_sums` offers three accumulations:

* ``"plain"``: the scan the paper describes;
* ``"relative"``: prefix sums of ``value - value at the path's origin``, plus
  ``run length * origin value`` per run: ``|P|`` grows with the spread of the values along the
  path rather than with their magnitude; helps only for data with a large common offset;
* ``"kahan"`` (default below float64): compensated prefix sums stored as a float pair
  ``(s, c)``, ``P[end] - P[start-1] = (s_e - s_s) - (c_e - c_s)``; as accurate as summing each
  region directly, for twice the prefix storage.

Measured float32 error, ``max over regions |fast - exact| / sum |v|`` (the scale of a direct
float32 sum's error), arm, one 2918-vertex path, worst of omega 1 and 2::

    values                      direct sum   plain        relative     kahan
    uniform [0, 1), 3 columns   2.5e-7       1.4e-4       1.2e-4       1.5e-7
    standard normal             1.4e-7       1.7e-6       8.2e-5       1.0e-7
    rest positions              8.6e-7       8.1e-4       5.9e-4       1.6e-7
    rest positions + 10 m       5.9e-7       4.5e-5       7.1e-7       1.5e-7
    x x^T (moment matrix)       7.9e-7       1.6e-2       2.4e-2       1.6e-7

With ``max_path_length=64`` plain improves about tenfold (x x^T: 1.6e-3) and kahan stays at
1.6e-7. The tests assert ``kahan`` within ``8 eps sum|v|`` (about 1e-6) and ``plain`` and
``relative`` within ``2e-3 sum|v|`` for values in [0, 1), float64 within 1e-12 relative.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..rig import RigError

__all__ = [
    "HEURISTICS",
    "ACCUMULATE",
    "PathLayout",
    "RegionRuns",
    "vertex_adjacency",
    "build_path_layout",
    "region_runs",
    "prefix_sums",
    "path_references",
    "compensated_prefix_sums",
    "run_region_sums",
]

HEURISTICS = ("warnsdorff", "straight")
ACCUMULATE = ("plain", "relative", "kahan")


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------


@dataclass
class PathLayout:
    """A cover of the vertices by vertex-disjoint paths along mesh edges.

    Attributes:
        order: Vertex indices, path after path, ``[V]`` int64 (a permutation of ``0..V-1``).
        path_offsets: ``[P + 1]`` int64; path ``p`` is ``order[path_offsets[p]:path_offsets[p+1]]``.
        path_of: Path of every vertex, ``[V]`` int64.
        position_of: Position of every vertex in :attr:`order`, ``[V]`` int64
            (``order[position_of[v]] == v``).
    """

    order: np.ndarray
    path_offsets: np.ndarray
    path_of: np.ndarray
    position_of: np.ndarray

    @property
    def vertex_count(self) -> int:
        """Number of vertices ``V``."""
        return int(self.order.shape[0])

    @property
    def path_count(self) -> int:
        """Number of paths ``P``."""
        return int(self.path_offsets.shape[0] - 1)

    @property
    def path_lengths(self) -> np.ndarray:
        """Vertices per path, ``[P]`` int64."""
        return np.diff(self.path_offsets)

    @property
    def mean_path_length(self) -> float:
        """Mean number of vertices per path (0 for an empty layout)."""
        return self.vertex_count / self.path_count if self.path_count else 0.0

    @property
    def is_path_start(self) -> np.ndarray:
        """``[V]`` bool, indexed by position: True where a path begins."""
        s = np.zeros(self.vertex_count, dtype=bool)
        s[self.path_offsets[:-1][self.path_lengths > 0]] = True
        return s

    @classmethod
    def from_paths(cls, paths: list[np.ndarray] | list[list[int]], vertex_count: int) -> PathLayout:
        """Assemble a layout from a list of vertex paths (checked: each vertex exactly once).

        Args:
            paths: Vertex indices of every path, in path order.
            vertex_count: ``V``.

        Returns:
            The layout.

        Raises:
            RigError: If a vertex is missing, repeated or out of range.
        """
        lengths = np.array([len(p) for p in paths], dtype=np.int64)
        offsets = np.zeros(lengths.size + 1, dtype=np.int64)
        np.cumsum(lengths, out=offsets[1:])
        order = (
            np.concatenate([np.asarray(p, dtype=np.int64) for p in paths])
            if paths
            else np.zeros(0, dtype=np.int64)
        )
        if order.size != vertex_count:
            raise RigError(f"path layout: paths hold {order.size} vertices, expected {vertex_count}")
        if order.size and (order.min() < 0 or order.max() >= vertex_count):
            raise RigError(f"path layout: vertex indices must be in [0, {vertex_count})")
        position_of = np.full(vertex_count, -1, dtype=np.int64)
        position_of[order] = np.arange(vertex_count, dtype=np.int64)
        if (position_of < 0).any():
            missing = np.flatnonzero(position_of < 0)
            raise RigError(f"path layout: vertices {missing[:8].tolist()} are on no path (or others on two)")
        path_of = np.empty(vertex_count, dtype=np.int64)
        path_of[order] = np.repeat(np.arange(lengths.size, dtype=np.int64), lengths)
        return cls(order=order, path_offsets=offsets, path_of=path_of, position_of=position_of)

    def paths(self) -> list[np.ndarray]:
        """The paths as a list of vertex arrays."""
        o = self.path_offsets
        return [self.order[o[p] : o[p + 1]] for p in range(self.path_count)]

    def check(self, adjacency: sp.spmatrix | None = None) -> None:
        """Verify the invariants; with ``adjacency``, also that path steps are mesh edges.

        Args:
            adjacency: ``[V, V]`` sparse vertex adjacency (see :func:`vertex_adjacency`).

        Raises:
            RigError: On the first violated invariant.
        """
        v = self.vertex_count
        if np.sort(self.order).tolist() != list(range(v)):
            raise RigError("path layout: order is not a permutation of the vertices")
        o = self.path_offsets
        if o.size < 1 or o[0] != 0 or o[-1] != v or (np.diff(o) < 0).any():
            raise RigError("path layout: path_offsets must rise from 0 to V")
        if not np.array_equal(self.order[self.position_of], np.arange(v)):
            raise RigError("path layout: position_of is not the inverse of order")
        if not np.array_equal(self.path_of[self.order], np.repeat(np.arange(self.path_count), np.diff(o))):
            raise RigError("path layout: path_of disagrees with path_offsets")
        if adjacency is not None and v > 1:
            a = sp.csr_matrix(adjacency)
            step = ~self.is_path_start[1:]
            i, j = self.order[:-1][step], self.order[1:][step]
            ok = np.asarray(a[i, j]).ravel() != 0
            if not ok.all():
                k = int(np.flatnonzero(~ok)[0])
                raise RigError(f"path layout: consecutive vertices {i[k]} and {j[k]} share no mesh edge")


@dataclass
class RegionRuns:
    """The maximal runs of every region along the paths of a :class:`PathLayout`.

    Attributes:
        run_offsets: ``[R + 1]`` int64; region ``r``'s runs are ``run_offsets[r]:run_offsets[r+1]``.
        run_start: First position (into :attr:`PathLayout.order`) of every run, ``[N]`` int64.
        run_end: Last position, inclusive, ``[N]`` int64; a run lies within one path.
    """

    run_offsets: np.ndarray
    run_start: np.ndarray
    run_end: np.ndarray

    @property
    def region_count(self) -> int:
        """Number of regions ``R``."""
        return int(self.run_offsets.shape[0] - 1)

    @property
    def run_count(self) -> int:
        """Number of runs ``N``."""
        return int(self.run_start.shape[0])

    @property
    def run_lengths(self) -> np.ndarray:
        """Vertices per run, ``[N]`` int64."""
        return self.run_end - self.run_start + 1

    @property
    def run_region(self) -> np.ndarray:
        """Region of every run, ``[N]`` int64."""
        return np.repeat(np.arange(self.region_count, dtype=np.int64), np.diff(self.run_offsets))

    @property
    def mean_runs_per_region(self) -> float:
        """Mean number of runs per region (0 when there are no regions)."""
        return self.run_count / self.region_count if self.region_count else 0.0


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _int_array(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind in "ui":
        return a.astype(np.int64, copy=False)
    if a.dtype.kind == "f" and a.size and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
        return a.astype(np.int64)
    if a.size == 0:
        return a.astype(np.int64)
    raise RigError(f"{name} must be integers, got dtype {a.dtype}")


def _check_triangles(triangles, vertex_count: int) -> np.ndarray:
    if int(vertex_count) != vertex_count or vertex_count < 0:
        raise RigError(f"path layout: vertex_count must be a non-negative integer, got {vertex_count}")
    t = _int_array(triangles, "path layout: triangles")
    if t.size == 0:
        return t.reshape(0, 3)
    if t.ndim != 2 or t.shape[1] != 3:
        raise RigError(f"path layout: triangles must have shape [T, 3], got {t.shape}")
    bad = (t < 0) | (t >= vertex_count)
    if bad.any():
        tri = np.flatnonzero(bad.any(axis=1))
        raise RigError(
            f"path layout: triangles {tri[:8].tolist()} reference vertices outside [0, {vertex_count})"
        )
    return t


def _check_csr(offsets, members, vertex_count: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    o = _int_array(offsets, f"{what}: offsets")
    m = _int_array(members, f"{what}: members")
    if o.ndim != 1 or o.size < 1:
        raise RigError(f"{what}: offsets must be a 1-D array [R + 1], got shape {o.shape}")
    if m.ndim != 1:
        raise RigError(f"{what}: members must be a 1-D array [M], got shape {m.shape}")
    if o[0] != 0:
        raise RigError(f"{what}: offsets must start at 0, got {o[0]}")
    if (np.diff(o) < 0).any():
        r = int(np.flatnonzero(np.diff(o) < 0)[0])
        raise RigError(
            f"{what}: offsets must not decrease (offsets[{r}]={o[r]} > offsets[{r + 1}]={o[r + 1]})"
        )
    if o[-1] != m.size:
        raise RigError(f"{what}: offsets end at {o[-1]} but there are {m.size} members")
    if m.size and (m.min() < 0 or m.max() >= vertex_count):
        bad = np.flatnonzero((m < 0) | (m >= vertex_count))
        raise RigError(
            f"{what}: members {m[bad[:8]].tolist()} are outside [0, {vertex_count}) "
            "(the vertices of one layer)"
        )
    return o, m


def _check_values(layout: PathLayout, values, dtype) -> tuple[np.ndarray, tuple[int, ...]]:
    """Values in path order, flattened to ``[V, K]`` in ``dtype``, and their trailing shape."""
    v = np.asarray(values)
    if v.ndim < 1 or v.shape[0] != layout.vertex_count:
        raise RigError(
            f"fast summation: values must have shape [V, ...] with V={layout.vertex_count}, got {v.shape}"
        )
    dt = np.dtype(dtype)
    if dt.kind != "f":
        raise RigError(f"fast summation: dtype must be a floating type, got {dt}")
    tail = v.shape[1:]
    x = v[layout.order].reshape(layout.vertex_count, -1).astype(dt, copy=False)
    return x, tail


# --------------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------------


def vertex_adjacency(triangles, vertex_count: int) -> sp.csr_matrix:
    """Symmetric vertex adjacency of a triangle mesh (no self loops, sorted indices).

    Args:
        triangles: ``[T, 3]`` vertex indices.
        vertex_count: ``V``; vertices in no triangle have no neighbours.

    Returns:
        ``[V, V]`` CSR matrix with ``int8`` ones where two vertices share an edge.

    Raises:
        RigError: For a malformed triangle array or indices out of range.
    """
    t = _check_triangles(triangles, vertex_count)
    n = int(vertex_count)
    i = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    j = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    keep = i != j
    a = sp.csr_matrix((np.ones(int(keep.sum()), dtype=np.int8), (i[keep], j[keep])), shape=(n, n))
    a.sum_duplicates()
    a.data[:] = 1
    a.sort_indices()
    return a


def _unit_rows(d: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.divide(d, n, out=np.zeros_like(d), where=n > 0)


def _greedy_paths(
    indptr: list[int],
    indices: list[int],
    edge_dir: list[tuple[float, float, float]] | None,
    xyz: list[list[float]] | None,
    heuristic: str,
    tol: float = 1e-3,
) -> list[list[int]]:
    """The greedy walk (one pass over the vertices). ``edge_dir[k]`` is the unit vector of CSR
    entry ``k`` (from its row vertex to ``indices[k]``); ``xyz`` the positions as lists."""
    n = len(indptr) - 1
    remdeg = [indptr[v + 1] - indptr[v] for v in range(n)]
    visited = bytearray(n)
    heap = [(remdeg[v], v) for v in range(n)]
    heapq.heapify(heap)
    tangent: list[tuple[float, float, float] | None] = [None] * n
    straight = heuristic == "straight" and edge_dir is not None
    paths: list[list[int]] = []

    def visit(v: int) -> None:
        visited[v] = 1
        for k in range(indptr[v], indptr[v + 1]):
            u = indices[k]
            if not visited[u]:
                remdeg[u] -= 1
                heapq.heappush(heap, (remdeg[u], u))

    def choose(cur: int, d, signed: bool):
        """Best unvisited neighbour of ``cur`` and its edge direction (or (-1, None))."""
        best, best_s, best_r, best_e = -1, -math.inf, 1 << 60, None
        for k in range(indptr[cur], indptr[cur + 1]):
            u = indices[k]
            if visited[u]:
                continue
            r = remdeg[u]
            if edge_dir is not None:
                e = edge_dir[k]
                s = 0.0 if d is None else e[0] * d[0] + e[1] * d[1] + e[2] * d[2]
                if not signed:
                    s = abs(s)
            else:
                e, s = None, 0.0
            if straight:
                better = s > best_s + tol or (s > best_s - tol and r < best_r)
            else:
                better = r < best_r or (r == best_r and s > best_s + tol)
            if better:
                best, best_s, best_r, best_e = u, s, r, e
        return best, best_e

    def extend(cur: int, d, path: list[int]) -> None:
        while True:
            u, e = choose(cur, d, True)
            if u < 0:
                return
            visit(u)
            path.append(u)
            d, cur = e, u

    while heap:
        r, s = heapq.heappop(heap)
        if visited[s] or r != remdeg[s]:
            continue
        visit(s)
        # inherit the direction of an adjacent, finished path (parallel paths)
        d0 = None
        if straight:
            for k in range(indptr[s], indptr[s + 1]):
                t = tangent[indices[k]]
                if t is not None:
                    d0 = t
                    break
        # forward (either sign of an inherited direction), then backward from the start
        fwd: list[int] = []
        bwd: list[int] = []
        u, e = choose(s, d0, d0 is None)
        if u >= 0:
            visit(u)
            fwd.append(u)
            extend(u, e, fwd)
            extend(s, None if e is None else (-e[0], -e[1], -e[2]), bwd)
        path = bwd[::-1] + [s] + fwd
        paths.append(path)
        if straight and len(path) > 1:
            # unit path tangent at every vertex, from its neighbours on the path
            for i, v in enumerate(path):
                a = path[i - 1] if i > 0 else v
                b = path[i + 1] if i + 1 < len(path) else v
                pa, pb = xyz[a], xyz[b]
                d = (pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2])
                ln = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
                tangent[v] = (d[0] / ln, d[1] / ln, d[2] / ln) if ln > 0 else None
    return paths


def build_path_layout(
    triangles,
    vertex_count: int,
    *,
    vertices: np.ndarray | None = None,
    heuristic: str | None = None,
    max_path_length: int | None = None,
) -> PathLayout:
    """Cover the mesh vertices by long, straight paths along mesh edges.

    Computed once per topology; all layers (same connectivity) share it.

    Args:
        triangles: ``[T, 3]`` int vertex indices.
        vertex_count: ``V``.
        vertices: Optional rest positions ``[V, 3]``: break ties by direction (``"warnsdorff"``),
            required by ``"straight"``.
        heuristic: One of :data:`HEURISTICS`; default ``"warnsdorff"`` (fewer runs on every mesh
            measured, see the module docstring).
        max_path_length: Cut longer paths into equal pieces of at most this many vertices
            (more parallelism for a one-thread-per-path scan, at the cost of a few more runs).

    Returns:
        The :class:`PathLayout`.

    Raises:
        RigError: For malformed triangles or vertices, or an unknown heuristic.
    """
    adj = vertex_adjacency(triangles, vertex_count)
    n = int(vertex_count)
    if heuristic is None:
        heuristic = "warnsdorff"
    if heuristic not in HEURISTICS:
        raise RigError(f"path layout: unknown heuristic {heuristic!r}; known: {HEURISTICS}")
    if heuristic == "straight" and vertices is None:
        raise RigError("path layout: the 'straight' heuristic needs the vertex positions")
    indptr = adj.indptr.tolist()
    indices = adj.indices.tolist()
    edge_dir = xyz = None
    if vertices is not None:
        x = np.asarray(vertices, dtype=np.float64)
        if x.shape != (n, 3):
            raise RigError(f"path layout: vertices must have shape [{n}, 3], got {x.shape}")
        if not np.isfinite(x).all():
            raise RigError("path layout: vertices must be finite")
        rows = np.repeat(np.arange(n), np.diff(adj.indptr))
        edge_dir = [tuple(r) for r in _unit_rows(x[adj.indices] - x[rows]).tolist()]
        xyz = x.tolist()
    paths = _greedy_paths(indptr, indices, edge_dir, xyz, heuristic)
    if max_path_length is not None:
        if int(max_path_length) != max_path_length or max_path_length < 1:
            raise RigError(f"path layout: max_path_length must be a positive integer, got {max_path_length}")
        paths = _split_paths(paths, int(max_path_length))
    return PathLayout.from_paths(paths, n)


def _split_paths(paths: list[list[int]], limit: int) -> list[list[int]]:
    """Cut every path longer than ``limit`` into ``ceil(len / limit)`` near-equal pieces."""
    out: list[list[int]] = []
    for p in paths:
        pieces = -(-len(p) // limit)
        if pieces <= 1:
            out.append(p)
            continue
        cuts = np.linspace(0, len(p), pieces + 1).round().astype(int).tolist()
        out.extend(p[cuts[i] : cuts[i + 1]] for i in range(pieces))
    return out


# --------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------


def region_runs(layout: PathLayout, region_offsets, region_members) -> RegionRuns:
    """The maximal runs of every region along the paths (vectorised).

    Args:
        layout: The path layout.
        region_offsets: ``[R + 1]`` CSR offsets, rising from 0 to ``M``.
        region_members: ``[M]`` vertex indices of one layer (``0 <= m < V``), no repeats within
            a region; any order.

    Returns:
        :class:`RegionRuns`; the runs of a region are sorted by position.

    Raises:
        RigError: For malformed offsets, members out of range or repeated within a region.
    """
    o, m = _check_csr(region_offsets, region_members, layout.vertex_count, "region runs")
    r_count = o.size - 1
    counts = np.diff(o)
    reg = np.repeat(np.arange(r_count, dtype=np.int64), counts)
    pos = layout.position_of[m]
    idx = np.lexsort((pos, reg))
    pos, reg = pos[idx], reg[idx]
    same_region = reg[1:] == reg[:-1]
    step = np.diff(pos)
    if (same_region & (step == 0)).any():
        k = int(np.flatnonzero(same_region & (step == 0))[0])
        raise RigError(f"region runs: region {reg[k]} lists vertex {layout.order[pos[k]]} twice")
    starts = layout.is_path_start
    new = np.ones(pos.size, dtype=bool)
    new[1:] = ~same_region | (step != 1) | starts[pos[1:]]
    last = np.ones(pos.size, dtype=bool)
    last[:-1] = new[1:]
    run_offsets = np.zeros(r_count + 1, dtype=np.int64)
    np.cumsum(np.bincount(reg[new], minlength=r_count), out=run_offsets[1:])
    return RegionRuns(run_offsets=run_offsets, run_start=pos[new].copy(), run_end=pos[last].copy())


# --------------------------------------------------------------------------------------------
# Prefix sums and region sums (host reference of the Warp kernels)
# --------------------------------------------------------------------------------------------


def _path_buckets(layout: PathLayout):
    """Group paths of similar length (within 2x) and yield ``(index [n, L], mask [n, L])``
    position matrices, padded to the bucket's longest path."""
    lengths = layout.path_lengths
    starts = layout.path_offsets[:-1]
    nonempty = lengths > 0
    key = np.zeros(lengths.size, dtype=np.int64)
    key[nonempty] = np.ceil(np.log2(lengths[nonempty])).astype(np.int64)
    for k in np.unique(key[nonempty]):
        sel = np.flatnonzero(nonempty & (key == k))
        width = int(lengths[sel].max())
        col = np.arange(width, dtype=np.int64)
        index = starts[sel, None] + col[None, :]
        mask = col[None, :] < lengths[sel, None]
        yield np.where(mask, index, 0), mask


def _segmented_cumsum(x: np.ndarray, layout: PathLayout) -> np.ndarray:
    """Sequential inclusive prefix sums of ``x`` [V, K] (path order) along every path, in
    ``x.dtype``: each path accumulated front to back, as one thread per path would."""
    out = np.empty_like(x)
    for index, mask in _path_buckets(layout):
        pad = np.where(mask[:, :, None], x[index], 0).astype(x.dtype, copy=False)
        cs = np.cumsum(pad, axis=1, dtype=x.dtype)
        out[index[mask]] = cs[mask]
    return out


def path_references(layout: PathLayout, values, dtype=np.float32) -> np.ndarray:
    """The value at every path's origin (first vertex), the reference of relative accumulation.

    Args:
        layout: The path layout.
        values: ``[V, ...]`` indexed by vertex.
        dtype: Output type.

    Returns:
        ``[P, ...]`` in ``dtype`` (zeros for empty paths).
    """
    x, tail = _check_values(layout, values, dtype)
    ref = np.zeros((layout.path_count, x.shape[1]), dtype=x.dtype)
    ne = layout.path_lengths > 0
    ref[ne] = x[layout.path_offsets[:-1][ne]]
    return ref.reshape((layout.path_count,) + tail)


def prefix_sums(
    layout: PathLayout, values, dtype=np.float64, *, reference: np.ndarray | None = None
) -> np.ndarray:
    """Inclusive prefix sums along every path, restarting at each path start.

    Host reference of the Warp scan: ``P[i] = sum(values[order[s:i+1]])`` for the path start
    ``s <= i``, accumulated sequentially in ``dtype``.

    Args:
        layout: The path layout.
        values: ``[V, ...]`` indexed by vertex.
        dtype: Accumulation and output type.
        reference: Optional ``[P, ...]`` per-path value subtracted from every value of the path
            before accumulating (relative accumulation, see :func:`path_references`).

    Returns:
        ``[V, ...]`` indexed by position in :attr:`PathLayout.order`.

    Raises:
        RigError: For values or a reference of the wrong shape.
    """
    x, tail = _check_values(layout, values, dtype)
    if reference is not None:
        ref = np.asarray(reference, dtype=x.dtype)
        if ref.shape != (layout.path_count,) + tail:
            raise RigError(
                f"fast summation: reference must have shape {(layout.path_count,) + tail}, got {ref.shape}"
            )
        x = x - np.repeat(ref.reshape(layout.path_count, -1), layout.path_lengths, axis=0)
    return _segmented_cumsum(x, layout).reshape(x.shape[:1] + tail)


def compensated_prefix_sums(layout: PathLayout, values, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """Kahan-compensated inclusive prefix sums along every path.

    Each path is accumulated front to back with Kahan's update ``y = v - c; t = s + y;
    c = (t - s) - y; s = t``; the true prefix is about ``s - c``.

    Args:
        layout: The path layout.
        values: ``[V, ...]`` indexed by vertex.
        dtype: Accumulation and output type.

    Returns:
        ``(s, c)``, each ``[V, ...]`` indexed by position.
    """
    x, tail = _check_values(layout, values, dtype)
    s_out = np.empty_like(x)
    c_out = np.empty_like(x)
    for index, mask in _path_buckets(layout):
        n, width = index.shape
        s = np.zeros((n, x.shape[1]), dtype=x.dtype)
        c = np.zeros_like(s)
        for j in range(width):
            live = mask[:, j]
            if not live.all():
                index, mask = index[live], mask[live]
                s, c = s[live], c[live]
            y = x[index[:, j]] - c
            t = s + y
            c = (t - s) - y
            s = t
            s_out[index[:, j]] = s
            c_out[index[:, j]] = c
    shape = x.shape[:1] + tail
    return s_out.reshape(shape), c_out.reshape(shape)


def run_region_sums(
    layout: PathLayout,
    runs: RegionRuns,
    values,
    dtype=np.float64,
    *,
    accumulate: str | None = None,
) -> np.ndarray:
    """Region sums from prefix differences over the runs (sibling terms not included).

    ``sum_r = sum over runs (P[end] - P[start - 1])``, with ``P[start - 1] = 0`` at a path start.

    Args:
        layout: The path layout the runs were built on.
        runs: The regions' runs (:func:`region_runs`).
        values: ``[V, ...]`` indexed by vertex.
        dtype: Accumulation and output type.
        accumulate: ``"plain"``, ``"relative"`` (prefix sums of ``value - origin value`` plus
            ``run length * origin value``) or ``"kahan"`` (compensated prefix sums); default
            ``"plain"`` for float64 and ``"kahan"`` below; see the module docstring for their
            float32 accuracy.

    Returns:
        ``[R, ...]`` region sums in ``dtype``.

    Raises:
        RigError: For bad values or an unknown accumulation.
    """
    if accumulate is None:
        accumulate = "plain" if np.dtype(dtype).itemsize >= 8 else "kahan"
    if accumulate not in ACCUMULATE:
        raise RigError(f"fast summation: unknown accumulate {accumulate!r}; known: {ACCUMULATE}")
    v = np.asarray(values)
    if v.ndim < 1 or v.shape[0] != layout.vertex_count:
        raise RigError(
            f"fast summation: values must have shape [V, ...] with V={layout.vertex_count}, got {v.shape}"
        )
    if runs.run_count and (runs.run_start.min() < 0 or runs.run_end.max() >= layout.vertex_count):
        raise RigError("fast summation: runs reach outside the layout; were they built on another one?")
    tail = v.shape[1:]
    dt = np.dtype(dtype)
    start, end = runs.run_start, runs.run_end
    at_start = layout.is_path_start[start]
    before = np.where(at_start, 0, start - 1)
    keep = (~at_start)[:, None]
    zero = np.zeros((), dtype=dt)
    if accumulate == "kahan":
        s, c = compensated_prefix_sums(layout, v, dt)
        s, c = s.reshape(layout.vertex_count, -1), c.reshape(layout.vertex_count, -1)
        ds = s[end] - np.where(keep, s[before], zero)
        dc = c[end] - np.where(keep, c[before], zero)
        diff = ds - dc
    else:
        ref = path_references(layout, v, dt) if accumulate == "relative" else None
        p = prefix_sums(layout, v, dt, reference=ref).reshape(layout.vertex_count, -1)
        diff = p[end] - np.where(keep, p[before], zero)
        if ref is not None:
            path = layout.path_of[layout.order[start]]
            cnt = runs.run_lengths.astype(dt)[:, None]
            diff = diff + cnt * ref.reshape(layout.path_count, -1)[path]
    out = np.zeros((runs.region_count, diff.shape[1]), dtype=dt)
    np.add.at(out, runs.run_region, diff.astype(dt, copy=False))
    return out.reshape((runs.region_count,) + tail)

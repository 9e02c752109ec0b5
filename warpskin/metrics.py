"""Measurements of skin quality: self-intersections and volumes.

These are independent of the solver (they share no detection code with it) so they can serve
as the exact check in reports and tests.
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangle_pairs_intersect", "self_intersections", "self_intersections_of_two", "PairQuery", "signed_volume"]


def signed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume [m^3] enclosed by a closed, outward-wound triangle mesh (divergence theorem,
    relative to the centroid for accuracy)."""
    p = np.asarray(points, dtype=np.float64)
    p = p - p.mean(axis=0)
    t = np.asarray(triangles)
    return float(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])).sum() / 6.0)


def _segments_hit_triangles(s0, s1, a, b, c, eps):
    """Do segments s0-s1 cross triangles abc (row-wise)? Moeller-Trumbore on the segment."""
    d = s1 - s0
    e1, e2 = b - a, c - a
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = s0 - a
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    return ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)


def _parallel_eps(p: np.ndarray) -> float:
    """The determinant below which a segment counts as parallel to a triangle: 1e-14 of the
    coordinates' scale squared."""
    return 1e-14 * (float(np.abs(p).max()) + 1e-30) ** 2


def triangle_pairs_intersect(points: np.ndarray, tri_a: np.ndarray, tri_b: np.ndarray) -> np.ndarray:
    """Whether triangle ``tri_a[k]`` and ``tri_b[k]`` (vertex index triples) intersect, ``[K]``.

    Two non-coplanar triangles intersect iff an edge of one crosses the other. Coplanar
    overlaps (measure zero for a deforming skin) are not reported.
    """
    p = np.asarray(points, dtype=np.float64)
    ta, tb = np.asarray(tri_a), np.asarray(tri_b)
    hit = np.zeros(ta.shape[0], dtype=bool)
    if ta.shape[0] == 0:
        return hit
    eps = _parallel_eps(p)
    for x, y in ((ta, tb), (tb, ta)):
        a, b, c = p[y[:, 0]], p[y[:, 1]], p[y[:, 2]]
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hit |= _segments_hit_triangles(p[x[:, i]], p[x[:, j]], a, b, c, eps)
    return hit


def _sorted_pairs(pairs: np.ndarray) -> np.ndarray:
    """``pairs`` ``[P, 2]`` as ``(min, max)`` rows in lexicographic order."""
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    out = np.sort(pairs, axis=1)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


def self_intersections(points: np.ndarray, triangles: np.ndarray, *, exclude_shared: bool = True) -> np.ndarray:
    """Pairs of triangles of one mesh that intersect, ``[P, 2]`` (``i < j``, sorted).

    Candidates are the pairs whose bounding boxes overlap (a BVH over the boxes, widened by
    1e-6 of the mesh's extent and coordinates past float32 rounding); each candidate gets the
    exact float64 edge/triangle test of :func:`triangle_pairs_intersect` (in the kernel). Pairs
    sharing a vertex are skipped (neighbours touch by design).
    """
    return PairQuery(triangles, exclude_shared=exclude_shared).pairs(points)


def self_intersections_of_two(points: np.ndarray, other: np.ndarray, triangles: np.ndarray, *,
                              exclude_shared: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`self_intersections` of one mesh in two poses (``points``, ``other``: ``[N, 3]``),
    found in one pass (boxes around each triangle in both): ``(pairs in points, pairs in
    other)``."""
    return PairQuery(triangles, exclude_shared=exclude_shared).of_two(points, other)


class PairQuery:
    """Exact self-intersection queries on one mesh (fixed ``triangles`` ``[T, 3]``) in changing
    poses, on a Warp BVH on the CPU: a whole count (:meth:`pairs`), a frame's count in two poses
    at once (:meth:`of_two`: the tree built over the boxes around each triangle in both), then
    rounds that move a few triangles (:meth:`active`: the tree refitted to the new boxes, queried
    by the moved triangles only), or the pairs of given boxes that overlap (:meth:`overlapping`).
    Pairs are ``i < j``, sorted; pairs sharing a vertex are skipped with ``exclude_shared``;
    with ``labels`` (``[T]`` int, a mesh per triangle) only pairs of differently labelled
    triangles are found (the crossings between meshes written as one). The device arrays are
    allocated once per mesh (and per point count)."""

    def __init__(self, triangles: np.ndarray, *, exclude_shared: bool = True, labels: np.ndarray | None = None) -> None:
        import warp as wp

        self.triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.skip_shared = int(bool(exclude_shared))
        n = len(self.triangles)
        with wp.ScopedDevice("cpu"):
            self.across = int(labels is not None)
            self._labels = wp.array(np.zeros(1, np.int32) if labels is None else np.asarray(labels, dtype=np.int32),
                                    dtype=wp.int32)
            self._tri = wp.array(self.triangles.astype(np.int32), dtype=wp.vec3i)
            self._lo = wp.empty(n, dtype=wp.vec3)
            self._hi = wp.empty(n, dtype=wp.vec3)
            self._all = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32)
            self._ones = wp.array(np.ones(n, dtype=np.int32), dtype=wp.int32)
            self._mask = wp.empty(n, dtype=wp.int32)
            self._count = wp.zeros(1, dtype=wp.int32)
            self._capacity = max(16 * n, 16)
            self._pairs = wp.empty(self._capacity, dtype=wp.vec2i)
            self._hits = wp.empty(self._capacity, dtype=wp.int32)
            self._p = self._q = wp.zeros(0, dtype=wp.vec3d)
        self._eps = (0.0, 0.0)
        self._bvh = None

    @staticmethod
    def _none() -> np.ndarray:
        return np.zeros((0, 2), dtype=np.int64)

    def _upload(self, current, x: np.ndarray):
        """``x`` ``[N, 3]`` float64 into ``current`` (reused where the point count is the same)."""
        import warp as wp

        if current.shape[0] != x.shape[0]:
            return wp.array(x, dtype=wp.vec3d, device="cpu")
        current.assign(x)
        return current

    def _boxes(self, p: np.ndarray, q: np.ndarray | None) -> None:
        """Every triangle's box in ``p`` (and ``q``), widened past the rounding to float32: by
        1e-6 of the points' extent plus their largest coordinate."""
        import warp as wp

        from .kernels import measure as k

        sets = [p] if q is None else [p, q]
        pad = 1e-6 * (max(float(np.ptp(x, axis=0).max()) for x in sets) + max(float(np.abs(x).max()) for x in sets)
                      + 1e-30)
        self._p = self._upload(self._p, p)
        if q is not None:
            self._q = self._upload(self._q, q)
        self._eps = (_parallel_eps(p), _parallel_eps(q) if q is not None else 0.0)
        wp.launch(k.triangle_boxes_kernel, dim=len(self.triangles), inputs=[self._p, self._q, int(q is not None),
                                                                         self._tri, pad],
                  outputs=[self._lo, self._hi], device="cpu")

    def _run(self, queries, active, exact: int) -> tuple[np.ndarray, np.ndarray]:
        import warp as wp

        from .kernels import measure as k

        while True:
            self._count.zero_()
            wp.launch(k.box_pairs_kernel, dim=queries.shape[0],
                      inputs=[self._bvh.id, queries, self._lo, self._hi, self._tri, active, self.skip_shared,
                              self._labels, self.across, self._p, self._q, exact, wp.float64(self._eps[0]),
                              wp.float64(self._eps[1]), self._capacity],
                      outputs=[self._count, self._pairs, self._hits], device="cpu")
            c = int(self._count.numpy()[0])
            if c <= self._capacity:
                return self._pairs.numpy()[:c].astype(np.int64), self._hits.numpy()[:c]
            self._capacity = c
            self._pairs = wp.empty(c, dtype=wp.vec2i, device="cpu")
            self._hits = wp.empty(c, dtype=wp.int32, device="cpu")

    @property
    def has_tree(self) -> bool:
        """Whether a whole count built the tree :meth:`active` refits."""
        return self._bvh is not None

    def _whole(self, exact: int) -> tuple[np.ndarray, np.ndarray]:
        import warp as wp

        self._bvh = wp.Bvh(self._lo, self._hi)
        return self._run(self._all, self._ones, exact)

    def pairs(self, points: np.ndarray) -> np.ndarray:
        """The intersecting pairs of ``points`` ``[N, 3]``."""
        if len(self.triangles) < 2:
            return self._none()
        self._boxes(np.asarray(points, dtype=np.float64), None)
        return _sorted_pairs(self._whole(1)[0])

    def of_two(self, points: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pairs in points, pairs in other)`` (``[N, 3]`` each), in one pass."""
        if len(self.triangles) < 2:
            return self._none(), self._none()
        self._boxes(np.asarray(points, dtype=np.float64), np.asarray(other, dtype=np.float64))
        pairs, where = self._whole(2)
        return _sorted_pairs(pairs[(where & 1) != 0]), _sorted_pairs(pairs[(where & 2) != 0])

    def active(self, points: np.ndarray, active: np.ndarray) -> np.ndarray:
        """The pairs in ``points`` with a triangle of ``active`` (``[T]`` bool), after
        :meth:`of_two` or :meth:`pairs` (whose tree is refitted here)."""
        import warp as wp

        if self._bvh is None:
            raise RuntimeError("PairQuery.active before a whole count")
        act = np.asarray(active, dtype=bool)
        if not act.any() or len(self.triangles) < 2:
            return self._none()
        self._boxes(np.asarray(points, dtype=np.float64), None)
        self._bvh.refit()
        self._mask.assign(act.astype(np.int32))
        queries = wp.array(np.nonzero(act)[0].astype(np.int32), dtype=wp.int32, device="cpu")
        return _sorted_pairs(self._run(queries, self._mask, 1)[0])

    def overlapping(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        """The pairs whose boxes ``lower``, ``upper`` (``[T, 3]``, given) overlap."""
        if len(self.triangles) < 2:
            return self._none()
        self._lo.assign(np.asarray(lower, dtype=np.float32))
        self._hi.assign(np.asarray(upper, dtype=np.float32))
        return _sorted_pairs(self._whole(0)[0])

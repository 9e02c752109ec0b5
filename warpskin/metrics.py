"""Measurements of skin quality: self-intersections and volumes.

These are independent of the solver (they share no detection code with it) so they can serve
as the exact check in reports and tests.
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangle_pairs_intersect", "self_intersections", "signed_volume"]


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
    scale = np.abs(p).max() + 1e-30
    eps = 1e-14 * scale**2
    for x, y in ((ta, tb), (tb, ta)):
        a, b, c = p[y[:, 0]], p[y[:, 1]], p[y[:, 2]]
        for i, j in ((0, 1), (1, 2), (2, 0)):
            hit |= _segments_hit_triangles(p[x[:, i]], p[x[:, j]], a, b, c, eps)
    return hit


def _box_pairs(lower: np.ndarray, upper: np.ndarray, triangles: np.ndarray, skip_shared: bool,
               active: np.ndarray | None = None) -> np.ndarray:
    """Pairs ``(i, j)`` of overlapping axis-aligned boxes ``[T, 3]`` (a Warp BVH on the CPU) of
    ``triangles`` (with ``skip_shared``: not sharing a vertex), in no particular order: every
    pair ``i < j``, or with ``active`` (``[T]`` bool) every pair with an active triangle, once
    (a tree over the active triangles' boxes, queried by the triangles whose boxes meet theirs)."""
    import warp as wp

    from .kernels import measure as k

    n = lower.shape[0]
    act_host = np.ones(n, dtype=np.int32) if active is None else np.asarray(active, dtype=np.int32)
    subset = np.nonzero(act_host)[0].astype(np.int32)
    if subset.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    if subset.size == n:
        queries = subset
    else:  # the triangles whose boxes meet the box around the active ones
        a_lo, a_hi = lower[subset].min(axis=0), upper[subset].max(axis=0)
        queries = np.nonzero(np.all((upper >= a_lo) & (lower <= a_hi), axis=1))[0].astype(np.int32)
    with wp.ScopedDevice("cpu"):
        lo = wp.array(lower.astype(np.float32), dtype=wp.vec3)
        hi = wp.array(upper.astype(np.float32), dtype=wp.vec3)
        bvh = wp.Bvh(lo, hi) if subset.size == n else wp.Bvh(wp.array(lower[subset].astype(np.float32), dtype=wp.vec3),
                                                            wp.array(upper[subset].astype(np.float32), dtype=wp.vec3))
        tri = wp.array(np.asarray(triangles, dtype=np.int32), dtype=wp.vec3i)
        inputs = [bvh.id, wp.array(subset, dtype=wp.int32), wp.array(queries, dtype=wp.int32), lo, hi, tri,
                  wp.array(act_host, dtype=wp.int32), int(skip_shared)]
        capacity = 16 * subset.size
        while True:
            count = wp.zeros(1, dtype=wp.int32)
            pairs = wp.zeros(capacity, dtype=wp.vec2i)
            wp.launch(k.box_pairs_kernel, dim=len(queries), inputs=[*inputs, capacity], outputs=[count, pairs])
            c = int(count.numpy()[0])
            if c <= capacity:
                break
            capacity = c
        return pairs.numpy()[:c].astype(np.int64)


def self_intersections(points: np.ndarray, triangles: np.ndarray, *, exclude_shared: bool = True,
                       active: np.ndarray | None = None) -> np.ndarray:
    """Pairs of triangles of one mesh that intersect, ``[P, 2]`` (``i < j``); with ``active``
    (``[T]`` bool) only the pairs that have an active triangle.

    Candidates are the pairs whose bounding boxes overlap (a BVH over the boxes, widened by
    1e-6 of the mesh's extent and coordinates past float32 rounding); each candidate gets the exact float64
    edge/triangle test. Pairs sharing a vertex are skipped (neighbours touch by design).
    """
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    if t.shape[0] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    # float32 boxes, widened past their rounding (relative to the coordinates and to the extent)
    pad = 1e-6 * (float(np.ptp(p, axis=0).max()) + float(np.abs(p).max()) + 1e-30)
    lower = np.minimum(np.minimum(a, b), c) - pad
    upper = np.maximum(np.maximum(a, b), c) + pad
    pairs = _box_pairs(lower, upper, t, exclude_shared, active)
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    hit = triangle_pairs_intersect(p, t[pairs[:, 0]], t[pairs[:, 1]])
    out = np.sort(pairs[hit], axis=1)
    return out[np.lexsort((out[:, 1], out[:, 0]))]

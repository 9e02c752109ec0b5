"""The exact self-intersection count (:func:`warpskin.metrics.self_intersections`): the pairs of
triangles whose bounding boxes overlap, from a BVH over the boxes, and on request the exact
float64 test of each (an edge of one crossing the other, Moeller-Trumbore on the segment, as
:func:`warpskin.metrics.triangle_pairs_intersect`). It shares no code with the solver's
collision detection, so the count stays an independent check."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def segment_hits_triangle(s0: wp.vec3d, s1: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, eps: wp.float64) -> bool:
    """Whether the segment ``s0``-``s1`` crosses triangle ``abc`` (ends and edges included); a
    segment parallel to the triangle (``|det| <= eps``) does not."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    d = s1 - s0
    e1 = b - a
    e2 = c - a
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    if wp.abs(det) <= eps:
        return False
    inv = one / det
    s = s0 - a
    u = inv * wp.dot(s, h)
    q = wp.cross(s, e1)
    v = inv * wp.dot(d, q)
    t = inv * wp.dot(e2, q)
    return u >= zero and v >= zero and u + v <= one and t >= zero and t <= one


@wp.func
def edges_cross(points: wp.array(dtype=wp.vec3d), x: wp.vec3i, y: wp.vec3i, eps: wp.float64) -> bool:
    """Whether an edge of triangle ``x`` crosses triangle ``y`` (vertex index triples)."""
    p = points[y[0]]
    q = points[y[1]]
    r = points[y[2]]
    return (segment_hits_triangle(points[x[0]], points[x[1]], p, q, r, eps)
            or segment_hits_triangle(points[x[1]], points[x[2]], p, q, r, eps)
            or segment_hits_triangle(points[x[2]], points[x[0]], p, q, r, eps))


@wp.func
def triangles_intersect(points: wp.array(dtype=wp.vec3d), a: wp.vec3i, b: wp.vec3i, eps: wp.float64) -> bool:
    """Whether triangles ``a`` and ``b`` (vertex index triples into ``points``) intersect: an
    edge of one crosses the other (coplanar overlaps are not reported)."""
    return edges_cross(points, a, b, eps) or edges_cross(points, b, a, eps)


@wp.kernel
def box_pairs_kernel(
    bvh: wp.uint64,
    queries: wp.array(dtype=wp.int32),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    active: wp.array(dtype=wp.int32),
    skip_shared: int,
    labels: wp.array(dtype=wp.int32),
    across: int,
    points: wp.array(dtype=wp.vec3d),
    points_b: wp.array(dtype=wp.vec3d),
    exact: int,
    eps: wp.float64,
    eps_b: wp.float64,
    capacity: int,
    # outputs
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
    hits: wp.array(dtype=wp.int32),
):
    """Every pair of overlapping boxes with an active triangle, once, from a BVH over every
    triangle's box: the thread of triangle ``i = queries[tid]`` (an active one) appends
    ``(i, j)`` for each ``j`` whose box overlaps its own, where ``j`` is inactive or ``i < j``
    (all active: every pair ``i < j``), with ``skip_shared`` not where the two share a vertex,
    with ``across`` only where the two have different ``labels`` (pairs between meshes).
    With ``exact`` 1 only where the two triangles intersect (:func:`triangles_intersect`) on
    ``points``, with ``exact`` 2 where they intersect on ``points`` or on ``points_b`` (the
    boxes then bound the triangle in both), ``hits`` saying where (bit 1: ``points``, bit 2:
    ``points_b``; 3 without ``exact``). Its ``count`` may pass ``capacity``: the caller grows
    the buffer and runs again."""
    i = queries[wp.tid()]
    a = triangles[i]
    q = wp.bvh_query_aabb(bvh, lower[i], upper[i])
    k = int(0)
    while wp.bvh_query_next(q, k):
        j = k
        if j == i or (active[i] != 0 and active[j] != 0 and j < i):
            continue
        if across != 0:
            if labels[i] == labels[j]:
                continue
        b = triangles[j]
        skip = False
        if skip_shared != 0:
            for u in range(3):
                for v in range(3):
                    if a[u] == b[v]:
                        skip = True
        where = int(3)
        if not skip and exact != 0:
            where = int(0)
            if triangles_intersect(points, a, b, eps):
                where = 1
            if exact == 2:
                if triangles_intersect(points_b, a, b, eps_b):
                    where += 2
            skip = where == 0
        if not skip:
            slot = wp.atomic_add(count, 0, 1)
            if slot < capacity:
                pairs[slot] = wp.vec2i(i, j)
                hits[slot] = where


@wp.kernel
def triangle_boxes_kernel(
    points: wp.array(dtype=wp.vec3d),
    points_b: wp.array(dtype=wp.vec3d),
    both: int,
    triangles: wp.array(dtype=wp.vec3i),
    pad: float,
    # outputs
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
):
    """The float32 box around triangle ``tid`` in ``points`` (with ``both``: in ``points_b``
    too), widened by ``pad`` (past the rounding to float32)."""
    t = triangles[wp.tid()]
    lo = wp.vec3d(points[t[0]])
    hi = wp.vec3d(points[t[0]])
    for k in range(3):
        lo = wp.min(lo, points[t[k]])
        hi = wp.max(hi, points[t[k]])
        if both != 0:
            lo = wp.min(lo, points_b[t[k]])
            hi = wp.max(hi, points_b[t[k]])
    w = wp.vec3(pad, pad, pad)
    lower[wp.tid()] = wp.vec3(wp.float32(lo[0]), wp.float32(lo[1]), wp.float32(lo[2])) - w
    upper[wp.tid()] = wp.vec3(wp.float32(hi[0]), wp.float32(hi[1]), wp.float32(hi[2])) + w

"""Broad phase of the exact self-intersection count (:func:`warpskin.metrics.self_intersections`):
the pairs of triangles whose bounding boxes overlap, from a BVH over the boxes. It shares no
code with the solver's collision detection, so the count stays an independent check."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def box_pairs_kernel(
    bvh: wp.uint64,
    subset: wp.array(dtype=wp.int32),
    queries: wp.array(dtype=wp.int32),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    active: wp.array(dtype=wp.int32),
    skip_shared: int,
    capacity: int,
    # outputs
    count: wp.array(dtype=wp.int32),
    pairs: wp.array(dtype=wp.vec2i),
):
    """Every pair of overlapping boxes with an active triangle, once, from a BVH over the active
    triangles' boxes (``subset``: the triangle of each of its leaves; all of them for a whole
    count): the thread of triangle ``i = queries[tid]`` (every triangle whose box may meet an
    active one) appends ``(i, j)`` for each active ``j`` whose box overlaps its own, where ``i``
    is inactive or ``i < j`` (all active: every pair ``i < j``), with ``skip_shared`` not where
    the two share a vertex; its ``count`` may pass ``capacity``: the caller grows the buffer and
    runs again."""
    i = queries[wp.tid()]
    a = triangles[i]
    q = wp.bvh_query_aabb(bvh, lower[i], upper[i])
    k = int(0)
    while wp.bvh_query_next(q, k):
        j = subset[k]
        if j == i or (active[i] != 0 and j < i):
            continue
        shared = False
        if skip_shared != 0:
            b = triangles[j]
            for u in range(3):
                for v in range(3):
                    if a[u] == b[v]:
                        shared = True
        if not shared:
            slot = wp.atomic_add(count, 0, 1)
            if slot < capacity:
                pairs[slot] = wp.vec2i(i, j)

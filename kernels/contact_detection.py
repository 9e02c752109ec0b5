"""Contact detection of the skin's self-collision (Deul & Bender 2013, section 4.5): each skin
triangle's box over the step, the vertex normals, and one BVH query per skin triangle for the
point-triangle and edge-edge candidates it owns, written into pre-sized buffers (a counter per
kind and an overflow flag: a query that would write past the capacity sets the flag and drops
nothing silently; the caller grows the buffers and runs the step again). The shared tests and
filters are :mod:`warpskin.kernels.collision`'s."""

import warp as wp

from .collision import (
    CollisionFilter, CollisionScalars, INSIDE_TOLERANCE, apart, box_gap, boxes_overlap, closest_on_triangle,
    excluded, facing, point_filtered, same_patch, segment_closest, unit_normal,
)

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Bounds of every skin triangle over the step (old and predicted positions), inflated by the
# thickness h: a contact can only involve triangles whose swept boxes overlap.
# --------------------------------------------------------------------------------------------
@wp.kernel
def triangle_bounds_kernel(
    x_old: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    pads: wp.array(dtype=wp.float32),
    vertex_tree: wp.array(dtype=wp.int32),
    # outputs
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Each triangle's box over ``x_old`` and ``x_pred``, padded by its character's pad
    (``pads[vertex_tree[its first vertex]]``) [m]."""
    t = wp.tid()
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(3):
        i = tri_indices[t, k]
        lo = wp.min(lo, wp.min(x_old[i], x_pred[i]))
        hi = wp.max(hi, wp.max(x_old[i], x_pred[i]))
    pad = wp.vec3(pads[vertex_tree[tri_indices[t, 0]]])
    lowers[t] = lo - pad
    uppers[t] = hi + pad


@wp.kernel
def vertex_normals_kernel(
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    # outputs
    normals: wp.array(dtype=wp.vec3),
):
    """Area-weighted vertex normals (not normalised), accumulated per triangle; zero first."""
    t = wp.tid()
    ia = tri_indices[t, 0]
    ib = tri_indices[t, 1]
    ic = tri_indices[t, 2]
    n = wp.cross(x[ib] - x[ia], x[ic] - x[ia])
    wp.atomic_add(normals, ia, n)
    wp.atomic_add(normals, ib, n)
    wp.atomic_add(normals, ic, n)


# --------------------------------------------------------------------------------------------
# Point-triangle detection (one thread per skin vertex). A candidate is a triangle whose swept
# box overlaps the vertex's swept box, that does not contain the vertex, and where either the
# segment x_old -> x_pred crosses the triangle from its outer side (n . (p - a) goes from >= 0
# to < 0), or the predicted point lies within the detection radius r in front of or behind it;
# in both cases the projection must fall inside the triangle. r is a few times the thickness h:
# detection runs once per step, and pairs that only come close during the constraint loop must
# already be in the list (their constraint stays inactive while C >= 0). The constraint keeps
# the point on the outer side of the skin: C(p, a, b, c) = n . (p - a) - h >= 0 (Mueller et al.
# 2007). Pairs of one surface patch (close at rest) collide only by crossing, unless the skin
# between them has folded over (the vertex normal and the triangle normal more than
# acos(fold_cos) apart, and not each behind the other): in a wrinkle or a crease they face each
# other and collide by proximity; across a convex corner they do not.
# --------------------------------------------------------------------------------------------
@wp.func
def point_triangle_candidate(
    i: int,
    t: int,
    x_old: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    filt: CollisionFilter,
    rest: wp.array(dtype=wp.vec3),
    rest_gap: float,
    vertex_normals: wp.array(dtype=wp.vec3),
    fold_cos: float,
    thickness: float,
    radius: float,
    capacity: int,
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    overflow: wp.array(dtype=wp.int32),
    colliding: wp.array(dtype=wp.int32),
):
    """Vertex ``i`` against triangle ``t`` (whose box overlaps the vertex's swept box): list the
    pair when it is a contact (see the section comment)."""
    ia = tri_indices[t, 0]
    ib = tri_indices[t, 1]
    ic = tri_indices[t, 2]
    if ia == i or ib == i or ic == i:
        return
    if point_filtered(i, ia, ib, ic, filt):
        return
    p0 = x_old[i]
    p1 = x_pred[i]
    patch = same_patch(i, ia, rest, rest_gap) or same_patch(i, ib, rest, rest_gap) or same_patch(i, ic, rest, rest_gap)
    a = x_pred[ia]
    b = x_pred[ib]
    c = x_pred[ic]
    n = unit_normal(a, b, c)
    if wp.length(n) == 0.0:
        return
    d1 = wp.dot(p1 - a, n)
    a0 = x_old[ia]
    n0 = wp.cross(x_old[ib] - a0, x_old[ic] - a0)
    d0 = wp.dot(p0 - a0, n0)
    crossing = d0 >= 0.0 and d1 < 0.0
    near = d1 < radius and d1 > -thickness  # ahead within the search radius, behind within h
    if patch and not facing(vertex_normals[i], n, (a + b + c) / 3.0 - p1, fold_cos):
        near = False
    if not (crossing or near):
        return
    bary = closest_on_triangle(p1, a, b, c)
    if wp.min(wp.min(bary[0], bary[1]), bary[2]) < -INSIDE_TOLERANCE:
        return
    slot = wp.atomic_add(pt_count, 0, 1)
    if slot < capacity:
        pt_vertex[slot] = i
        pt_triangle[slot] = t
        colliding[i] = 1
        colliding[ia] = 1
        colliding[ib] = 1
        colliding[ic] = 1
    else:
        overflow[0] = 1


@wp.kernel
def detect_point_triangle_kernel(
    bvh: wp.uint64,
    x_old: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    filt: CollisionFilter,
    rest: wp.array(dtype=wp.vec3),
    rest_gap: float,
    vertex_normals: wp.array(dtype=wp.vec3),
    fold_cos: float,
    thickness: float,
    radius: float,
    capacity: int,
    # outputs
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    overflow: wp.array(dtype=wp.int32),
    colliding: wp.array(dtype=wp.int32),
):
    """One thread per point (any point, in a triangle or not): the reference form of the
    point-triangle half of :func:`detect_kernel`, which lists the same pairs."""
    i = wp.tid()
    p0 = x_old[i]
    p1 = x_pred[i]
    # the triangle boxes are already inflated by the search radius: the query box is not
    query = wp.bvh_query_aabb(bvh, wp.min(p0, p1), wp.max(p0, p1))
    t = int(0)
    while wp.bvh_query_next(query, t):
        point_triangle_candidate(i, t, x_old, x_pred, tri_indices, filt, rest, rest_gap, vertex_normals,
                                 fold_cos, thickness, radius, capacity, pt_count, pt_vertex, pt_triangle, overflow,
                                 colliding)


# --------------------------------------------------------------------------------------------
# Edge-edge detection (one thread per skin edge): edges of overlapping triangles (no shared
# vertex) whose closest points are nearer than the thickness, or which cross each other's
# triangle during the step. Each unordered pair is kept once: from the edge with the smaller
# index, through the first of the other edge's two triangles whose box overlaps the query.
# --------------------------------------------------------------------------------------------
@wp.func
def edge_edge_candidates(
    e: int,
    t: int,
    lo: wp.vec3,
    hi: wp.vec3,
    x_old: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    edge_indices: wp.array2d(dtype=wp.int32),
    tri_edges: wp.array2d(dtype=wp.int32),
    edge_owner: wp.array(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    filt: CollisionFilter,
    rest: wp.array(dtype=wp.vec3),
    rest_gap: float,
    vertex_normals: wp.array(dtype=wp.vec3),
    fold_cos: float,
    radius: float,
    capacity: int,
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    overflow: wp.array(dtype=wp.int32),
    colliding: wp.array(dtype=wp.int32),
):
    """Edge ``e`` (swept box ``lo``-``hi``) against the edges of triangle ``t``: list the pairs
    that are contacts (see the section comment)."""
    if not boxes_overlap(lowers[t], uppers[t], lo, hi):
        return
    i1 = edge_indices[e, 0]
    i2 = edge_indices[e, 1]
    p1 = x_pred[i1]
    p2 = x_pred[i2]
    for k in range(3):
        f = tri_edges[t, k]
        if f <= e:
            continue  # each unordered pair once
        # f lies in two triangles, both returned for a near pair: take it through the first
        # (its owner) whose box overlaps the query, so the pair is listed once
        o = edge_owner[f]
        if o != t and boxes_overlap(lowers[o], uppers[o], lo, hi):
            continue
        i3 = edge_indices[f, 0]
        i4 = edge_indices[f, 1]
        if i3 == i1 or i3 == i2 or i4 == i1 or i4 == i2:
            continue
        if excluded(i1, i3, filt.rigid_bone) and excluded(i2, i4, filt.rigid_bone) and excluded(i1, i4, filt.rigid_bone):
            continue
        if apart(i1, i3, filt) or apart(i1, i4, filt) or apart(i2, i3, filt) or apart(i2, i4, filt):
            continue
        p3 = x_pred[i3]
        p4 = x_pred[i4]
        # side at the start of the step: sign of (p4 - p1) . n with n = (p2 - p1) x (p4 - p3)
        o1 = x_old[i1]
        n0 = wp.cross(x_old[i2] - o1, x_old[i4] - x_old[i3])
        c0 = wp.dot(x_old[i4] - o1, n0)
        n1 = wp.cross(p2 - p1, p4 - p3)
        c1 = wp.dot(p4 - p1, n1)
        # a pair that cannot have flipped is a contact only by proximity: most candidates are
        # rejected here by their boxes (farther apart than the radius, with a margin against
        # rounding) or as one unfolded patch, before the closest points are computed
        if not (c0 * c1 < 0.0):
            if box_gap(wp.min(p1, p2), wp.max(p1, p2), wp.min(p3, p4), wp.max(p3, p4)) > radius * (1.0 + 1.0e-4):
                continue
        patch = (same_patch(i1, i3, rest, rest_gap) or same_patch(i1, i4, rest, rest_gap)
                 or same_patch(i2, i3, rest, rest_gap) or same_patch(i2, i4, rest, rest_gap))
        if patch and facing(vertex_normals[i1] + vertex_normals[i2], vertex_normals[i3] + vertex_normals[i4],
                            (p3 + p4) * 0.5 - (p1 + p2) * 0.5, fold_cos):
            patch = False  # folded over: the two edges face each other
        if patch and not (c0 * c1 < 0.0):
            continue
        st = segment_closest(p1, p2, p3, p4)
        q1 = p1 + st[0] * (p2 - p1)
        q2 = p3 + st[1] * (p4 - p3)
        dist = wp.length(q2 - q1)
        flipped = c0 * c1 < 0.0 and st[0] > 0.0 and st[0] < 1.0 and st[1] > 0.0 and st[1] < 1.0
        if (dist >= radius or patch) and not flipped:
            continue
        if wp.abs(c0) < 1.0e-30:
            continue  # no reliable side: leave it to the point-triangle constraints
        slot = wp.atomic_add(ee_count, 0, 1)
        if slot < capacity:
            ee_a[slot] = e
            ee_b[slot] = f
            sgn = float(1.0)
            if c0 < 0.0:
                sgn = -1.0
            ee_sign[slot] = sgn
            colliding[i1] = 1
            colliding[i2] = 1
            colliding[i3] = 1
            colliding[i4] = 1
        else:
            overflow[0] = 1


# --------------------------------------------------------------------------------------------
# Both kinds in one pass, one thread per skin triangle: each vertex and each edge is owned by
# one of its triangles (the first), and a triangle queries the tree once with the box of what
# it owns, then tests each owned feature against the returned triangles whose boxes overlap
# that feature's own box: exactly the pairs of the two kernels above (one tree query per
# triangle instead of one per vertex and one per edge: the queries dominate on the CPU).
# --------------------------------------------------------------------------------------------
@wp.kernel
def detect_kernel(
    trees: wp.array(dtype=wp.uint64),
    tri_tree: wp.array(dtype=wp.int32),
    tree_start: wp.array(dtype=wp.int32),
    x_old: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    tri_owns: wp.array(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    tri_edges: wp.array2d(dtype=wp.int32),
    edge_owner: wp.array(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    filt: CollisionFilter,
    rest: wp.array(dtype=wp.vec3),
    vertex_normals: wp.array(dtype=wp.vec3),
    params: wp.array(dtype=CollisionScalars),
    capacity: int,
    # outputs
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    overflow: wp.array(dtype=wp.int32),
    colliding: wp.array(dtype=wp.int32),
    list_pairs: int,
    pair_capacity: int,
    tri_pairs: wp.array2d(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
):
    """Triangle ``t`` queries the tree ``trees[tri_tree[t]]``, over the triangles from
    ``tree_start`` of that tree on (one tree per character of a batched model: contacts stay
    within a character; one tree from 0 otherwise). ``tri_owns`` bits 0-2: the triangle owns
    its corner k; bits 3-5: its edge k (corner k to k + 1). With ``list_pairs``, every pair of triangles with no shared vertex whose boxes the
    query pairs (the tree's boxes carry the radius, the query box does not) and whose swept
    boxes are within the character's ``list_gap`` of each other goes into ``tri_pairs`` once (lower index
    first), for the fail-safe of the step (see :func:`listed_new_intersections_kernel`); ``pair_count`` counts them all, also those
    beyond ``pair_capacity``, which are not written (the fail-safe then does without the
    list)."""
    t = wp.tid()
    tree = tri_tree[t]
    rest_gap = params[tree].rest_gap
    fold_cos = params[tree].fold_cos
    thickness = params[tree].thickness
    radius = params[tree].radius
    list_gap = params[tree].list_gap
    owns = tri_owns[t]
    if owns == 0 and list_pairs == 0:
        return
    i0 = tri_indices[t, 0]
    i1 = tri_indices[t, 1]
    i2 = tri_indices[t, 2]
    # the swept box of each corner (rows)
    lo = wp.matrix_from_rows(wp.min(x_old[i0], x_pred[i0]), wp.min(x_old[i1], x_pred[i1]), wp.min(x_old[i2], x_pred[i2]))
    hi = wp.matrix_from_rows(wp.max(x_old[i0], x_pred[i0]), wp.max(x_old[i1], x_pred[i1]), wp.max(x_old[i2], x_pred[i2]))
    qlo = wp.min(wp.min(lo[0], lo[1]), lo[2])
    qhi = wp.max(wp.max(hi[0], hi[1]), hi[2])
    query = wp.bvh_query_aabb(trees[tree], qlo, qhi)
    first = tree_start[tree]
    hit = int(0)
    while wp.bvh_query_next(query, hit):
        u = first + hit
        if list_pairs != 0 and u > t and boxes_overlap(qlo - wp.vec3(list_gap), qhi + wp.vec3(list_gap),
                                                       lowers[u] + wp.vec3(radius), uppers[u] - wp.vec3(radius)):
            b0 = tri_indices[u, 0]
            b1 = tri_indices[u, 1]
            b2 = tri_indices[u, 2]
            if not (i0 == b0 or i0 == b1 or i0 == b2 or i1 == b0 or i1 == b1 or i1 == b2 or i2 == b0 or i2 == b1
                    or i2 == b2):
                slot = wp.atomic_add(pair_count, 0, 1)
                if slot < pair_capacity:  # (a list that does not fit is not used)
                    tri_pairs[slot, 0] = t
                    tri_pairs[slot, 1] = u
        if owns == 0:
            continue
        for k in range(3):
            if (owns >> k) & 1 != 0 and boxes_overlap(lowers[u], uppers[u], lo[k], hi[k]):
                point_triangle_candidate(tri_indices[t, k], u, x_old, x_pred, tri_indices, filt, rest, rest_gap,
                                         vertex_normals, fold_cos, thickness, radius, capacity, pt_count, pt_vertex,
                                         pt_triangle, overflow, colliding)
            if (owns >> (3 + k)) & 1 != 0:  # edge k: corner k to corner k + 1
                k1 = (k + 1) % 3
                edge_edge_candidates(tri_edges[t, k], u, wp.min(lo[k], lo[k1]), wp.max(hi[k], hi[k1]), x_old, x_pred,
                                     edge_indices, tri_edges, edge_owner, lowers, uppers, filt, rest, rest_gap,
                                     vertex_normals, fold_cos, radius, capacity, ee_count, ee_a, ee_b, ee_sign,
                                     overflow, colliding)


@wp.kernel
def reset_collision_kernel(
    # outputs
    colliding: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    colliding[i] = 0


@wp.kernel
def zero_counts_kernel(
    # outputs
    counts: wp.array(dtype=wp.int32),
):
    """Reset the point-triangle, edge-edge and triangle-pair counters; the overflow flag
    (counts[2]) stays until the host has seen it."""
    counts[0] = 0
    counts[1] = 0
    counts[3] = 0

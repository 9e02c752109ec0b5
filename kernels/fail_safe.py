"""The self-collision fail-safe: the written skin triangles tested exactly after the elasticity
loop, and the vertices of a pair that intersects now, did not at the step's start and does not
under LBS put back (carried by their bone layer's motion, else held); see the section comment
below."""

import warp as wp

from .collision import (
    CollisionFilter, CollisionScalars, boxes_contain, boxes_overlap, contact_range, triangle_box, triangles_filtered,
)
from .skinning import lbs_point

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# The fail-safe (after the elasticity loop and the tether): the contact constraints are found
# from a proximity and a plane-crossing test, so a vertex that slides into a neighbour's
# triangle from behind its plane, or runs past the search radius during the constraint loop
# (a fold at a crease, a fast knee), is never listed and the skin passes through itself. So
# every pair of the triangles as written (the file's, for a refined skin) is tested exactly (an
# edge of one crossing the other); the vertices of a pair that intersects now, did not at the
# start of the step, and whose LBS does not intersect either, go back to their start
# positions: first carried by the step's motion of their bone-layer particle (pinned to LBS,
# so the patch keeps up with the animation instead of freezing in place), and where that still
# intersects, held there. Later rounds look only at triangles with a vertex the last one moved
# (a put-back vertex can expose a pair with a neighbour that moved on). Pairs whose LBS
# intersects (the animation drives the two surfaces into each other: paws through legs) are
# left to the contacts: putting them back would follow the animation in and add pairs.
# Bridson et al. 2002 and Harmon et al. 2008 use fail-safes of
# this kind (impact zones moved rigidly); here a zone moves with its bones.
# --------------------------------------------------------------------------------------------
@wp.kernel
def fail_safe_bounds_kernel(
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    carry_offset: int,
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    chunk: int,
    # outputs
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Boxes of the triangles over every position the fail-safe can give a vertex: the step's,
    the start, and the start carried by the bone-layer particle (``carry_offset`` > 0), padded
    by their character's ``fail_safe_pad``; one refit serves all rounds. ``chunk`` triangles per thread (:func:`contact_range`)."""
    first, last = contact_range(wp.tid(), chunk, tri_indices.shape[0], tri_indices.shape[0])
    for t in range(first, last):
        lo = wp.vec3(1.0e30)
        hi = wp.vec3(-1.0e30)
        for k in range(3):
            i = tri_indices[t, k]
            lo = wp.min(lo, wp.min(x_old[i], x[i]))
            hi = wp.max(hi, wp.max(x_old[i], x[i]))
            if carry_offset > 0:
                c = x_old[i] + (x[i + carry_offset] - x_old[i + carry_offset])
                lo = wp.min(lo, c)
                hi = wp.max(hi, c)
        pad = params[vertex_tree[tri_indices[t, 0]]].fail_safe_pad
        lowers[t] = lo - wp.vec3(pad)
        uppers[t] = hi + wp.vec3(pad)


@wp.kernel
def escaped_kernel(
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    det_lowers: wp.array(dtype=wp.vec3),
    det_uppers: wp.array(dtype=wp.vec3),
    pair_count: wp.array(dtype=wp.int32),
    pair_capacity: int,
    chunk: int,
    # outputs
    escaped: wp.array(dtype=wp.int32),
):
    """The triangles whose box where they are now (``x``, padded by their character's
    ``fail_safe_pad`` as the fail-safe's boxes are) reaches past their detection box
    (``det_lowers``/``det_uppers``: the swept box plus the search radius) shrunk by its
    ``escape_margin`` (the radius less the reach,
    ``warpskin.collision.ESCAPE_REACH``): two triangles that did not escape and intersect now
    have swept boxes within twice the reach, and are in the detection's pair list. (Only the
    first round, which tests the pairs as they are now, reads this; the later rounds look from
    the triangles that moved, over all their positions. The box is where the triangle is now,
    not over every position the fail-safe can give it: that one would escape far more often.)
    Where that list
    did not fit (``pair_count`` above ``pair_capacity``), every triangle escapes. ``chunk``
    triangles per thread (:func:`contact_range`)."""
    fits = pair_count[0] <= pair_capacity
    first, last = contact_range(wp.tid(), chunk, tri_indices.shape[0], tri_indices.shape[0])
    for t in range(first, last):
        s = params[vertex_tree[tri_indices[t, 0]]]
        m = wp.vec3(s.escape_margin)
        lo, hi = triangle_box(x, tri_indices, t, s.fail_safe_pad)
        inside = boxes_contain(det_lowers[t] + m, det_uppers[t] - m, lo, hi)
        escaped[t] = wp.where(inside and fits, 0, 1)


@wp.kernel
def moved_farther_kernel(
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    distances: wp.array(dtype=wp.float32),
    vertex_tree: wp.array(dtype=wp.int32),
    # outputs
    moved: wp.array(dtype=wp.int32),
):
    """``moved``: 1 where a skin vertex is farther than its character's distance
    (``distances[vertex_tree[i]]``) from ``x_old``."""
    i = wp.tid()
    distance = distances[vertex_tree[i]]
    moved[i] = wp.where(wp.length_sq(x[i] - x_old[i]) > distance * distance, 1, 0)


@wp.kernel
def pin_reverted_kernel(
    reverted: wp.array(dtype=wp.int32),
    # outputs
    weight_scale: wp.array(dtype=wp.float32),
):
    """The vertices the fail-safe put back stay put in the volume iterations that follow."""
    i = wp.tid()
    if reverted[i] != 0:
        weight_scale[i] = 0.0


@wp.func
def segment_hits_triangle(s0: wp.vec3, s1: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, tol: float) -> bool:
    """Does segment s0-s1 cross triangle abc (Moeller-Trumbore)? ``tol`` widens (> 0) or
    narrows (< 0) the triangle and the segment by that fraction of their parameters."""
    d = s1 - s0
    e1 = b - a
    e2 = c - a
    h = wp.cross(d, e2)
    det = wp.dot(e1, h)
    if wp.abs(det) <= 1.0e-12 * wp.length(e1) * wp.length(e2) * wp.length(d):
        return False  # the segment is parallel to the plane (or degenerate)
    inv = 1.0 / det
    s = s0 - a
    u = inv * wp.dot(s, h)
    q = wp.cross(s, e1)
    v = inv * wp.dot(d, q)
    t = inv * wp.dot(e2, q)
    return u >= -tol and v >= -tol and u + v <= 1.0 + tol and t >= -tol and t <= 1.0 + tol


@wp.func
def triangle_points_intersect(pa0: wp.vec3, pa1: wp.vec3, pa2: wp.vec3, pb0: wp.vec3, pb1: wp.vec3, pb2: wp.vec3,
                              tol: float) -> bool:
    """Triangles (pa0, pa1, pa2) and (pb0, pb1, pb2) intersect: an edge of one crosses the
    other (``tol`` as in :func:`segment_hits_triangle`)."""
    # a triangle wholly on one side of the other's plane meets nothing of it (Moeller 1997's
    # early-out; most candidate pairs end here), widened by tol times the edge scale
    na = wp.cross(pa1 - pa0, pa2 - pa0)
    la = wp.length(na)
    eps_a = tol * la * (wp.length(pb1 - pb0) + wp.length(pb2 - pb0))
    db0 = wp.dot(na, pb0 - pa0)
    db1 = wp.dot(na, pb1 - pa0)
    db2 = wp.dot(na, pb2 - pa0)
    if (db0 > eps_a and db1 > eps_a and db2 > eps_a) or (db0 < -eps_a and db1 < -eps_a and db2 < -eps_a):
        return False
    nb = wp.cross(pb1 - pb0, pb2 - pb0)
    lb = wp.length(nb)
    eps_b = tol * lb * (wp.length(pa1 - pa0) + wp.length(pa2 - pa0))
    da0 = wp.dot(nb, pa0 - pb0)
    da1 = wp.dot(nb, pa1 - pb0)
    da2 = wp.dot(nb, pa2 - pb0)
    if (da0 > eps_b and da1 > eps_b and da2 > eps_b) or (da0 < -eps_b and da1 < -eps_b and da2 < -eps_b):
        return False
    return (segment_hits_triangle(pa0, pa1, pb0, pb1, pb2, tol) or segment_hits_triangle(pa1, pa2, pb0, pb1, pb2, tol)
            or segment_hits_triangle(pa2, pa0, pb0, pb1, pb2, tol) or segment_hits_triangle(pb0, pb1, pa0, pa1, pa2, tol)
            or segment_hits_triangle(pb1, pb2, pa0, pa1, pa2, tol) or segment_hits_triangle(pb2, pb0, pa0, pa1, pa2, tol))


@wp.func
def triangles_intersect(x: wp.array(dtype=wp.vec3), a0: int, a1: int, a2: int, b0: int, b1: int, b2: int,
                        tol: float) -> bool:
    """Two triangles (vertex indices into ``x``) intersect: an edge of one crosses the other."""
    return triangle_points_intersect(x[a0], x[a1], x[a2], x[b0], x[b1], x[b2], tol)


@wp.func
def new_intersection(
    a0: int,
    a1: int,
    a2: int,
    b0: int,
    b1: int,
    b2: int,
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tol: float,
    rest: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    filt: CollisionFilter,
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Two triangles with no shared vertex, in groups that may collide (``filt``), that
    intersect at ``x`` (widened by ``tol``), did not at ``x_old`` (narrowed by it), and whose LBS
    (``rest`` skinned by ``skin_matrices``; widened by ``tol``) does not intersect: mark their
    six vertices in ``revert`` and add the pair to ``count``."""
    if triangles_filtered(a0, a1, a2, b0, b1, b2, filt):
        return
    if triangles_intersect(x, a0, a1, a2, b0, b1, b2, tol) and not triangles_intersect(x_old, a0, a1, a2, b0, b1, b2,
                                                                                       -tol):
        # where the animation itself drives the two through each other (their LBS
        # intersects), putting them back would follow it in: that is the contacts' part
        la0 = lbs_point(rest[a0], joint_indices, joint_weights, a0, skin_matrices)
        la1 = lbs_point(rest[a1], joint_indices, joint_weights, a1, skin_matrices)
        la2 = lbs_point(rest[a2], joint_indices, joint_weights, a2, skin_matrices)
        lb0 = lbs_point(rest[b0], joint_indices, joint_weights, b0, skin_matrices)
        lb1 = lbs_point(rest[b1], joint_indices, joint_weights, b1, skin_matrices)
        lb2 = lbs_point(rest[b2], joint_indices, joint_weights, b2, skin_matrices)
        if triangle_points_intersect(la0, la1, la2, lb0, lb1, lb2, tol):
            return
        revert[a0] = 1
        revert[a1] = 1
        revert[a2] = 1
        revert[b0] = 1
        revert[b1] = 1
        revert[b2] = 1
        wp.atomic_add(count, 0, 1)


@wp.func
def new_intersections_from(
    t: int,
    trees: wp.array(dtype=wp.uint64),
    tri_tree: wp.array(dtype=wp.int32),
    tree_start: wp.array(dtype=wp.int32),
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    pad: float,
    tol: float,
    moved: wp.array(dtype=wp.int32),
    only_moved: int,
    escaped: wp.array(dtype=wp.int32),
    only_escaped: int,
    rest: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    filt: CollisionFilter,
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Triangle ``t``'s part of :func:`new_intersections_kernel` (its tree: ``trees[tri_tree[t]]``
    over the triangles from ``tree_start`` of that tree on)."""
    if only_escaped != 0 and escaped[t] == 0:
        return
    a0 = tri_indices[t, 0]
    a1 = tri_indices[t, 1]
    a2 = tri_indices[t, 2]
    moved_t = moved[a0] != 0 or moved[a1] != 0 or moved[a2] != 0
    if only_moved != 0 and only_escaped == 0 and not moved_t:
        return
    # the query box is the triangle where it is now (padded as the tree's boxes are): a pair
    # that intersects now has overlapping boxes of where both are now, and every triangle's box
    # in the tree holds every position a round can give it; the box over all of this one's
    # positions is far larger where it moved far (the triangles that escaped the pair list), and
    # finds far more
    qlo, qhi = triangle_box(x, tri_indices, t, pad)
    tree = tri_tree[t]
    query = wp.bvh_query_aabb(trees[tree], qlo, qhi)
    first = tree_start[tree]
    hit = int(0)
    while wp.bvh_query_next(query, hit):
        u = first + hit
        if u == t:
            continue
        b0 = tri_indices[u, 0]
        b1 = tri_indices[u, 1]
        b2 = tri_indices[u, 2]
        moved_u = moved[b0] != 0 or moved[b1] != 0 or moved[b2] != 0
        if only_escaped != 0:
            if escaped[u] != 0 and u < t:
                continue  # triangle u tests it
            if only_moved != 0 and not (moved_t or moved_u):
                continue
        else:
            if only_moved == 0 and u < t:
                continue
            if u < t and moved_u:
                continue  # both moved: thread u tests the pair (each pair once)
        if a0 == b0 or a0 == b1 or a0 == b2 or a1 == b0 or a1 == b1 or a1 == b2 or a2 == b0 or a2 == b1 or a2 == b2:
            continue
        new_intersection(a0, a1, a2, b0, b1, b2, x_old, x, tol, rest, joint_indices, joint_weights, skin_matrices,
                         filt, revert, count)


@wp.kernel
def new_intersections_kernel(
    trees: wp.array(dtype=wp.uint64),
    tri_tree: wp.array(dtype=wp.int32),
    tree_start: wp.array(dtype=wp.int32),
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    tol: float,
    moved: wp.array(dtype=wp.int32),
    only_moved: int,
    escaped: wp.array(dtype=wp.int32),
    only_escaped: int,
    rest: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    filt: CollisionFilter,
    reverted: wp.array(dtype=wp.int32),
    after_round: int,
    chunk: int,
    # outputs
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """``chunk`` triangles per thread (one on a GPU; see :func:`contact_range`), each: the
    pairs with another triangle (no shared vertex) whose box in the tree (over every position
    the fail-safe can give it) overlaps the box of where this one is now (padded by its
    character's ``fail_safe_pad``),
    tested by :func:`new_intersection`, each pair once. With ``only_moved``
    (the rounds after the first) only triangles with a vertex the last round ``moved`` look, at
    every other triangle (a pair of two such, from the lower-numbered one): no other pair can
    have changed. With ``only_escaped`` (the first round, where the detection's pair list has
    the pairs of every two triangles that did not escape their detection box) only the
    ``escaped`` triangles look, at the others and at the higher-numbered escaped ones; with
    ``only_moved`` as well, a pair is tested when either triangle moved. With ``after_round``
    >= 0 nothing runs unless :func:`revert_kernel` of that round put a vertex back
    (``reverted``): a round after one that found nothing has nothing to test."""
    if after_round >= 0:
        if reverted[after_round] == 0:
            return
    first, last = contact_range(wp.tid(), chunk, tri_indices.shape[0], tri_indices.shape[0])
    for t in range(first, last):
        pad = params[vertex_tree[tri_indices[t, 0]]].fail_safe_pad
        new_intersections_from(t, trees, tri_tree, tree_start, x_old, x, tri_indices, pad, tol, moved, only_moved,
                               escaped, only_escaped, rest,
                               joint_indices, joint_weights, skin_matrices, filt, revert, count)


@wp.func
def listed_pair(
    s: int,
    tri_pairs: wp.array2d(dtype=wp.int32),
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    tol: float,
    moved: wp.array(dtype=wp.int32),
    only_moved: int,
    escaped: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    filt: CollisionFilter,
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Pair ``s`` of the detection's list, tested by :func:`new_intersection` unless a triangle
    escaped, their boxes are apart or (``only_moved``) neither moved."""
    t = tri_pairs[s, 0]
    u = tri_pairs[s, 1]
    if escaped[t] != 0 or escaped[u] != 0:
        return
    if not boxes_overlap(lowers[t], uppers[t], lowers[u], uppers[u]):
        return
    a0 = tri_indices[t, 0]
    a1 = tri_indices[t, 1]
    a2 = tri_indices[t, 2]
    b0 = tri_indices[u, 0]
    b1 = tri_indices[u, 1]
    b2 = tri_indices[u, 2]
    if only_moved != 0:
        if not (moved[a0] != 0 or moved[a1] != 0 or moved[a2] != 0 or moved[b0] != 0 or moved[b1] != 0
                or moved[b2] != 0):
            return
    new_intersection(a0, a1, a2, b0, b1, b2, x_old, x, tol, rest, joint_indices, joint_weights, skin_matrices,
                     filt, revert, count)


@wp.kernel
def listed_new_intersections_kernel(
    tri_pairs: wp.array2d(dtype=wp.int32),
    pair_count: wp.array(dtype=wp.int32),
    x_old: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tri_indices: wp.array2d(dtype=wp.int32),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    tol: float,
    moved: wp.array(dtype=wp.int32),
    only_moved: int,
    escaped: wp.array(dtype=wp.int32),
    rest: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    filt: CollisionFilter,
    chunk: int,
    # outputs
    revert: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """The first round of the fail-safe from the detection's pair list, ``chunk`` slots per
    thread as the contact kernels (:func:`contact_range`; a list that did not fit is not read:
    every triangle escaped): the pairs of two triangles that did not escape, whose boxes overlap
    (with ``only_moved``: and one of which moved), tested by :func:`new_intersection`; the
    escaped triangles' pairs are :func:`new_intersections_kernel`'s (``only_escaped``)."""
    first, last = contact_range(wp.tid(), chunk, pair_count[0], tri_pairs.shape[0])
    for s in range(first, last):
        listed_pair(s, tri_pairs, x_old, x, tri_indices, lowers, uppers, tol, moved, only_moved, escaped, rest,
                    joint_indices, joint_weights, skin_matrices, filt, revert, count)


@wp.kernel
def revert_kernel(
    x_old: wp.array(dtype=wp.vec3),
    carry_offset: int,
    after_round: int,
    this_round: int,
    # outputs
    revert: wp.array(dtype=wp.int32),
    carried: wp.array(dtype=wp.int32),
    moved: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    reverted: wp.array(dtype=wp.int32),
):
    """Marked skin vertices back to their start-of-step positions: the first time in a step
    carried by the step's motion of their bone-layer particle (index + ``carry_offset``;
    pinned to LBS, so the zone keeps up with the animation), marked again (the carried patch
    still intersects) or without inner layers (``carry_offset`` 0) held there. ``moved`` says
    which vertices this round moved; ``carried`` which ones any round of the call put back
    (zeroed by the caller); clears the marks. ``reverted[this_round]`` (zeroed by the caller)
    becomes nonzero when a vertex was put back; like the round's tests, nothing runs when
    ``after_round`` >= 0 and ``reverted[after_round]`` is zero (no mark is set then, and
    ``moved`` keeps the last round's, which the later rounds, skipped too, do not read)."""
    if after_round >= 0:
        if reverted[after_round] == 0:
            return
    i = wp.tid()
    if revert[i] != 0:
        reverted[this_round] = 1
        if carry_offset > 0 and carried[i] == 0:
            j = i + carry_offset
            x[i] = x_old[i] + (x[j] - x_old[j])
        else:
            x[i] = x_old[i]
        carried[i] = 1
        revert[i] = 0
        moved[i] = 1
    else:
        moved[i] = 0

"""Self-collision of the skin layer (Deul & Bender 2013, section 4.5): BVH detection on the
predicted positions, point-triangle and edge-edge unilateral constraints projected inside the
elasticity loop, friction and restitution after it.

Detection writes into pre-sized buffers: a counter per kind and an overflow flag; a query that
would write past the capacity sets the flag and drops nothing silently (the caller grows the
buffers and runs the step again).
"""

import warp as wp

from .skinning import lbs_point

wp.set_module_options({"enable_backward": False})

#: A point counts as over a triangle while its smallest barycentric coordinate is above minus
#: this. A point over an edge two triangles share has coordinate 0 in both, and float32
#: rounding gives its sign: with a strict test both could say "outside" and the contact would
#: be lost; with the band it collides with one or both (the contact point is clamped onto the
#: triangle).
INSIDE_TOLERANCE = wp.constant(1.0e-5)


# --------------------------------------------------------------------------------------------
# Bounds of every skin triangle over the step (old and predicted positions), inflated by the
# thickness h: a contact can only involve triangles whose swept boxes overlap.
# --------------------------------------------------------------------------------------------
@wp.struct
class CollisionScalars:
    """One character's contact scalars (a model's, or each of a batch's; kernels find a
    vertex's by ``params[vertex_tree[vertex]]``): ``thickness`` h, the search ``radius``,
    ``rest_gap`` [m]; ``fold_cos``; ``friction`` and ``restitution``; ``volume_weight`` (a
    colliding particle's weight in the volume loop); the pair list's ``list_gap``, the escape
    test's ``escape_margin`` and the fail-safe boxes' ``fail_safe_pad`` [m]
    (:class:`warpskin.collision.SelfCollision`)."""

    thickness: float
    radius: float
    rest_gap: float
    fold_cos: float
    friction: float
    restitution: float
    volume_weight: float
    list_gap: float
    escape_margin: float
    fail_safe_pad: float


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


@wp.struct
class CollisionFilter:
    """What never collides: ``rigid_bone`` ``[V]`` (the bone a vertex moves rigidly with, else
    -1: two vertices of one bone's rigid neighbourhood never collide), ``group`` ``[V]`` (the
    vertex's collision group: a piece of the surface, or a piece's cap) and ``group_pairs``
    ``[G, G]`` (nonzero: those two groups never collide; pieces that overlap at rest, a cap and
    any other piece; a model of one piece has one group, and no pair); ``fail_safe_pairs``
    ``[G, G]`` (nonzero: the fail-safe leaves the pairs of triangles of those two groups alone:
    the groups of two different pieces, whose crossings the contacts alone handle)."""

    rigid_bone: wp.array(dtype=wp.int32)
    group: wp.array(dtype=wp.int32)
    group_pairs: wp.array2d(dtype=wp.int32)
    fail_safe_pairs: wp.array2d(dtype=wp.int32)


@wp.func
def excluded(a: int, b: int, rigid_bone: wp.array(dtype=wp.int32)) -> bool:
    """Two skin vertices inside one bone's rigid neighbourhood (both move rigidly with the same
    bone) can never collide with each other."""
    ra = rigid_bone[a]
    return ra >= 0 and ra == rigid_bone[b]


@wp.func
def apart(a: int, b: int, f: CollisionFilter) -> bool:
    """Vertices ``a`` and ``b`` lie in groups that never collide."""
    return f.group_pairs[f.group[a], f.group[b]] != 0


@wp.func
def point_filtered(i: int, ia: int, ib: int, ic: int, f: CollisionFilter) -> bool:
    """Point ``i`` never collides with triangle ``(ia, ib, ic)``: all three corners in its rigid
    neighbourhood, or any corner in a group it never collides with (a cap's triangle touches its
    piece's rim)."""
    rigid = excluded(i, ia, f.rigid_bone) and excluded(i, ib, f.rigid_bone) and excluded(i, ic, f.rigid_bone)
    return rigid or apart(i, ia, f) or apart(i, ib, f) or apart(i, ic, f)


@wp.func
def triangles_filtered(a0: int, a1: int, a2: int, b0: int, b1: int, b2: int, f: CollisionFilter) -> bool:
    """Two triangles the fail-safe leaves alone: corners in groups that never collide, or in
    groups whose crossings are left to the contacts (any pair of corners)."""
    if (apart(a0, b0, f) or apart(a0, b1, f) or apart(a0, b2, f) or apart(a1, b0, f) or apart(a1, b1, f)
            or apart(a1, b2, f) or apart(a2, b0, f) or apart(a2, b1, f) or apart(a2, b2, f)):
        return True
    return f.fail_safe_pairs[f.group[a0], f.group[b0]] != 0


@wp.func
def same_patch(a: int, b: int, rest: wp.array(dtype=wp.vec3), rest_gap: float) -> bool:
    """Two vertices of one surface patch (closer than ``rest_gap`` at rest). Side by side on a
    smooth surface they are legitimately closer than the thickness, so such pairs only become
    contacts when they actually cross during the step (a fold), never by proximity alone."""
    return wp.length(rest[a] - rest[b]) < rest_gap


@wp.func
def unit_normal(a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Unit normal of triangle abc (counter-clockwise: outward); zero for a degenerate one."""
    n = wp.cross(b - a, c - a)
    ln = wp.length(n)
    if ln < 1.0e-20:
        return wp.vec3(0.0)
    return n / ln


@wp.func
def clamped_bary(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric coordinates of p's projection, each clamped to [0, 1]."""
    w = closest_on_triangle(p, a, b, c)
    return wp.vec3(wp.clamp(w[0], 0.0, 1.0), wp.clamp(w[1], 0.0, 1.0), wp.clamp(w[2], 0.0, 1.0))


@wp.func
def closest_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric coordinates of the projection of p onto the plane of abc (may lie outside)."""
    e0 = b - a
    e1 = c - a
    d = p - a
    d00 = wp.dot(e0, e0)
    d01 = wp.dot(e0, e1)
    d11 = wp.dot(e1, e1)
    d20 = wp.dot(d, e0)
    d21 = wp.dot(d, e1)
    den = d00 * d11 - d01 * d01
    if den < 1.0e-30:
        return wp.vec3(-1.0, -1.0, -1.0)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return wp.vec3(1.0 - v - w, v, w)


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


@wp.func
def folded(u: wp.vec3, w: wp.vec3, fold_cos: float) -> bool:
    """Two surface directions more than acos(fold_cos) apart: the surface between two nearby
    features is folded over (a crease or a wrinkle), so they face each other."""
    return wp.dot(u, w) < fold_cos * wp.length(u) * wp.length(w)


@wp.func
def facing(u: wp.vec3, w: wp.vec3, d: wp.vec3, fold_cos: float) -> bool:
    """Two nearby features with surface directions ``u`` and ``w`` and ``d`` from the first to
    the second lie across a fold: directions more than acos(fold_cos) apart, and not each one
    behind the other (d . u < 0 and d . w > 0): that is a convex corner (a cylinder's rim, a box
    edge, low-poly geometry), where the directions are as far apart but nothing folded."""
    return folded(u, w, fold_cos) and not (wp.dot(d, u) < 0.0 and wp.dot(d, w) > 0.0)


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
def segment_closest(p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, p4: wp.vec3) -> wp.vec2:
    """Parameters (s, t) of the closest points p1 + s (p2 - p1) and p3 + t (p4 - p3)."""
    d1 = p2 - p1
    d2 = p4 - p3
    r = p1 - p3
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    if a > 1.0e-30 and e > 1.0e-30:
        c = wp.dot(d1, r)
        b = wp.dot(d1, d2)
        den = a * e - b * b
        if den > 1.0e-30:
            s = wp.clamp((b * f - c * e) / den, 0.0, 1.0)
        t = (b * s + f) / e
        if t < 0.0:
            t = 0.0
            s = wp.clamp(-c / a, 0.0, 1.0)
        elif t > 1.0:
            t = 1.0
            s = wp.clamp((b - c) / a, 0.0, 1.0)
    return wp.vec2(s, t)


@wp.func
def lines_meet_far_from_edges(p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, p4: wp.vec3, margin: float) -> bool:
    """The closest points of the two edges' infinite lines lie more than ``margin`` (a fraction
    of the edge) beyond the end of either edge; False for parallel edges."""
    d1 = p2 - p1
    d2 = p4 - p3
    r = p1 - p3
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    b = wp.dot(d1, d2)
    c = wp.dot(d1, r)
    f = wp.dot(d2, r)
    den = a * e - b * b
    if den <= 1.0e-12 * a * e:
        return False
    s = (b * f - c * e) / den
    t = (a * f - b * c) / den
    return s < -margin or s > 1.0 + margin or t < -margin or t > 1.0 + margin


@wp.func
def boxes_contain(lo_a: wp.vec3, hi_a: wp.vec3, lo_b: wp.vec3, hi_b: wp.vec3) -> bool:
    """Box a contains box b."""
    return (lo_a[0] <= lo_b[0] and lo_a[1] <= lo_b[1] and lo_a[2] <= lo_b[2] and hi_b[0] <= hi_a[0]
            and hi_b[1] <= hi_a[1] and hi_b[2] <= hi_a[2])


@wp.func
def triangle_box(x: wp.array(dtype=wp.vec3), tri_indices: wp.array2d(dtype=wp.int32), t: int, pad: float):
    """The box of triangle ``t`` at ``x``, padded by ``pad``: (lower, upper)."""
    xa = x[tri_indices[t, 0]]
    xb = x[tri_indices[t, 1]]
    xc = x[tri_indices[t, 2]]
    return wp.min(wp.min(xa, xb), xc) - wp.vec3(pad), wp.max(wp.max(xa, xb), xc) + wp.vec3(pad)


@wp.func
def box_gap(lo_a: wp.vec3, hi_a: wp.vec3, lo_b: wp.vec3, hi_b: wp.vec3) -> float:
    """Distance between two boxes (0 where they overlap): a lower bound of the distance of any
    point of one to any point of the other."""
    g = wp.max(wp.max(lo_a - hi_b, lo_b - hi_a), wp.vec3(0.0))
    return wp.length(g)


@wp.func
def boxes_overlap(lo_a: wp.vec3, hi_a: wp.vec3, lo_b: wp.vec3, hi_b: wp.vec3) -> bool:
    return (lo_a[0] <= hi_b[0] and lo_b[0] <= hi_a[0] and lo_a[1] <= hi_b[1] and lo_b[1] <= hi_a[1]
            and lo_a[2] <= hi_b[2] and lo_b[2] <= hi_a[2])


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


@wp.kernel
def detect_edge_edge_kernel(
    bvh: wp.uint64,
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
    # outputs
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    overflow: wp.array(dtype=wp.int32),
    colliding: wp.array(dtype=wp.int32),
):
    """One thread per edge: the reference form of the edge-edge half of :func:`detect_kernel`,
    which lists the same pairs."""
    e = wp.tid()
    i1 = edge_indices[e, 0]
    i2 = edge_indices[e, 1]
    lo = wp.min(wp.min(x_pred[i1], x_pred[i2]), wp.min(x_old[i1], x_old[i2]))  # triangle boxes carry the radius
    hi = wp.max(wp.max(x_pred[i1], x_pred[i2]), wp.max(x_old[i1], x_old[i2]))
    query = wp.bvh_query_aabb(bvh, lo, hi)
    t = int(0)
    while wp.bvh_query_next(query, t):
        edge_edge_candidates(e, t, lo, hi, x_old, x_pred, edge_indices, tri_edges, edge_owner, lowers, uppers,
                             filt, rest, rest_gap, vertex_normals, fold_cos, radius, capacity, ee_count, ee_a,
                             ee_b, ee_sign, overflow, colliding)


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


@wp.func
def contact_range(thread: int, chunk: int, count: int, capacity: int):
    """The items ``[first, last)`` one thread of a chunked kernel takes: ``chunk`` in a row from
    ``thread x chunk``, of the ``count`` there are (at most the buffer's ``capacity``; a
    per-triangle kernel passes the triangle count as both). With ``chunk`` 1 (CUDA) a thread per
    item; on the CPU, where the threads run one after another, a thread per ``chunk`` items
    (the same items in the same order) saves the per-thread cost of the empty slots (most of a
    contact buffer is empty) and of the triangles a fail-safe round skips."""
    first = thread * chunk
    last = wp.min(wp.min(count, capacity), first + chunk)
    return first, wp.max(first, last)


# --------------------------------------------------------------------------------------------
# Point-triangle projection, C = n . (p - a) - h >= 0, n the unit normal of abc. With the
# normal held fixed (Mueller et al. 2007): grad_p = n, grad_a = -b0 n, grad_b = -b1 n,
# grad_c = -b2 n (b the barycentric coordinates of the projection), and
#   s = C / (w_p + w_a b0^2 + w_b b1^2 + w_c b2^2),  dx_k = -s w_k grad_k.
# Corrections are accumulated (atomics) and averaged per particle by the apply kernel.
# --------------------------------------------------------------------------------------------
@wp.func
def project_point_triangle(
    k: int,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    thickness: float,
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """Contact ``k``'s point-triangle constraint, projected into ``delta``/``delta_count``."""
    i = pt_vertex[k]
    t = pt_triangle[k]
    ia = tri_indices[t, 0]
    ib = tri_indices[t, 1]
    ic = tri_indices[t, 2]
    p = x[i]
    a = x[ia]
    b = x[ib]
    c = x[ic]
    n = unit_normal(a, b, c)
    if wp.length(n) == 0.0:
        return
    cval = wp.dot(p - a, n) - thickness
    if cval >= 0.0:
        return
    bary = clamped_bary(p, a, b, c)
    wp_ = inv_mass[i]
    wa = inv_mass[ia]
    wb = inv_mass[ib]
    wc = inv_mass[ic]
    den = wp_ + wa * bary[0] * bary[0] + wb * bary[1] * bary[1] + wc * bary[2] * bary[2]
    if den < 1.0e-30:
        return
    s = cval / den
    wp.atomic_add(delta, i, -s * wp_ * n)
    wp.atomic_add(delta, ia, s * wa * bary[0] * n)
    wp.atomic_add(delta, ib, s * wb * bary[1] * n)
    wp.atomic_add(delta, ic, s * wc * bary[2] * n)
    wp.atomic_add(delta_count, i, 1)
    wp.atomic_add(delta_count, ia, 1)
    wp.atomic_add(delta_count, ib, 1)
    wp.atomic_add(delta_count, ic, 1)
    wp.atomic_add(active, 0, 1)


@wp.kernel
def project_point_triangle_kernel(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    chunk: int,
    # outputs
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """The point-triangle contacts ``chunk`` x thread ... (thread + 1) x ``chunk`` that exist
    (``pt_count``): see :func:`contact_range`; each at its character's thickness."""
    first, last = contact_range(wp.tid(), chunk, pt_count[0], pt_vertex.shape[0])
    for k in range(first, last):
        thickness = params[vertex_tree[pt_vertex[k]]].thickness
        project_point_triangle(k, x, inv_mass, tri_indices, pt_vertex, pt_triangle, thickness, delta, delta_count,
                               active)


# --------------------------------------------------------------------------------------------
# Edge-edge projection (Deul & Bender 2013, section 4.5):
#   C = sgn (p4 - p1) . n / |n| - h >= 0,   n = (p2 - p1) x (p4 - p3),
#   grad_p1 =  (e14 M e34* - n) / |n|,   grad_p2 = -(e14 M e34*) / |n|,
#   grad_p3 = -(e14 M e12*) / |n|,       grad_p4 =  (e14 M e12* + n) / |n|,
#   M = I - n n^T / |n|^2,  e_xy = p_y - p_x,  a* b = a x b   (times sgn).
# Written as row vectors: e14 M e34* = (M e14)^T e34* = -(e34 x (M e14))... evaluated below as
# (M e14) x e34 for e14^T M e34* (since u^T (v x .) = (u x v)^T), likewise for e12.
# Parallel edges (|n| ~ 0): n is the perpendicular from edge 1 to edge 2, C = sgn |d| - h
# with d the vector between the closest points, and the gradients of a point-point distance
# distributed by the closest-point parameters.
# --------------------------------------------------------------------------------------------
@wp.func
def edge_edge_constraint(p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, p4: wp.vec3, sgn: float, thickness: float,
                         violated_only: bool):
    """Returns (C, g1, g2, g3, g4) for the paper's edge-edge constraint; with ``violated_only``
    the gradients are zero (not computed) where C >= 0 (the projection skips those: on the arm
    more than half of the listed pairs in a step).

    The paper's C is the distance between the two edges' infinite lines along their common
    normal; that is the edges' distance where the lines' closest points lie on (or within one
    edge length of) both edges. Where they lie farther out (coplanar edges of a flat patch,
    edges whose lines meet far beyond their ends) the lines' distance is near zero for edges
    far apart, so there C is the unsigned distance of the edges' closest points minus the
    thickness."""
    z = wp.vec3(0.0)
    e12 = p2 - p1
    e34 = p4 - p3
    e14 = p4 - p1
    if lines_meet_far_from_edges(p1, p2, p3, p4, 1.0):
        sf = segment_closest(p1, p2, p3, p4)
        dq = (p3 + sf[1] * e34) - (p1 + sf[0] * e12)
        lq = wp.length(dq)
        if lq < 1.0e-20:
            return 0.0, z, z, z, z
        if violated_only and lq - thickness >= 0.0:
            return lq - thickness, z, z, z, z
        uq = dq / lq
        return lq - thickness, -(1.0 - sf[0]) * uq, -sf[0] * uq, (1.0 - sf[1]) * uq, sf[1] * uq
    n = wp.cross(e12, e34)
    ln2 = wp.dot(n, n)
    scale = wp.max(wp.dot(e12, e12), wp.dot(e34, e34))
    if ln2 > 1.0e-12 * scale * scale:
        ln = wp.sqrt(ln2)
        c = sgn * wp.dot(e14, n) / ln - thickness
        if violated_only and c >= 0.0:
            return c, z, z, z, z
        me14 = e14 - n * (wp.dot(n, e14) / ln2)  # M e14
        u34 = wp.cross(me14, e34)  # (e14^T M) e34*  as a vector: e14^T M (e34 x .)
        u12 = wp.cross(me14, e12)
        g1 = sgn * (u34 - n) / ln
        g2 = -sgn * u34 / ln
        g3 = -sgn * u12 / ln
        g4 = sgn * (u12 + n) / ln
        return c, g1, g2, g3, g4
    # parallel edges: the perpendicular between the closest points
    st = segment_closest(p1, p2, p3, p4)
    q1 = p1 + st[0] * e12
    q2 = p3 + st[1] * e34
    d = q2 - q1
    ld = wp.length(d)
    if ld < 1.0e-20:
        return 0.0, z, z, z, z
    c = sgn * ld - thickness
    if violated_only and c >= 0.0:
        return c, z, z, z, z
    u = d / ld
    g1 = -sgn * (1.0 - st[0]) * u
    g2 = -sgn * st[0] * u
    g3 = sgn * (1.0 - st[1]) * u
    g4 = sgn * st[1] * u
    return c, g1, g2, g3, g4


@wp.func
def project_edge_edge(
    k: int,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    edge_indices: wp.array2d(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    thickness: float,
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """Contact ``k``'s edge-edge constraint, projected into ``delta``/``delta_count``."""
    i1 = edge_indices[ee_a[k], 0]
    i2 = edge_indices[ee_a[k], 1]
    i3 = edge_indices[ee_b[k], 0]
    i4 = edge_indices[ee_b[k], 1]
    c, g1, g2, g3, g4 = edge_edge_constraint(x[i1], x[i2], x[i3], x[i4], ee_sign[k], thickness, True)
    if c >= 0.0:
        return
    w1 = inv_mass[i1]
    w2 = inv_mass[i2]
    w3 = inv_mass[i3]
    w4 = inv_mass[i4]
    den = w1 * wp.dot(g1, g1) + w2 * wp.dot(g2, g2) + w3 * wp.dot(g3, g3) + w4 * wp.dot(g4, g4)
    if den < 1.0e-30:
        return
    s = -c / den
    wp.atomic_add(delta, i1, s * w1 * g1)
    wp.atomic_add(delta, i2, s * w2 * g2)
    wp.atomic_add(delta, i3, s * w3 * g3)
    wp.atomic_add(delta, i4, s * w4 * g4)
    wp.atomic_add(delta_count, i1, 1)
    wp.atomic_add(delta_count, i2, 1)
    wp.atomic_add(delta_count, i3, 1)
    wp.atomic_add(delta_count, i4, 1)
    wp.atomic_add(active, 0, 1)


@wp.kernel
def project_edge_edge_kernel(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    edge_indices: wp.array2d(dtype=wp.int32),
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    chunk: int,
    # outputs
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """The edge-edge contacts of this thread's chunk (see :func:`contact_range`); each at its
    character's thickness."""
    first, last = contact_range(wp.tid(), chunk, ee_count[0], ee_a.shape[0])
    for k in range(first, last):
        thickness = params[vertex_tree[edge_indices[ee_a[k], 0]]].thickness
        project_edge_edge(k, x, inv_mass, edge_indices, ee_a, ee_b, ee_sign, thickness, delta, delta_count, active)


@wp.kernel
def apply_deltas_kernel(
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    # outputs
    x: wp.array(dtype=wp.vec3),
):
    """Jacobi averaging: x += sum of corrections / their count; resets the accumulators."""
    i = wp.tid()
    n = delta_count[i]
    if n > 0:
        x[i] = x[i] + delta[i] / float(n)
        delta[i] = wp.vec3(0.0)
        delta_count[i] = 0


# --------------------------------------------------------------------------------------------
# Friction and restitution (after the velocity update) for point-triangle contacts: with the
# relative velocity u = v_p - (b0 v_a + b1 v_b + b2 v_c) and the contact normal n,
#   approaching (u_n < 0):  dv_n = -(1 + e) u_n,
#   tangential: u_t = u - u_n n, reduced by min(1, mu |dv_n| / |u_t|) (Coulomb),
# the change split between the point and the triangle by inverse masses.
# --------------------------------------------------------------------------------------------
@wp.func
def friction_restitution(
    k: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    friction: float,
    restitution: float,
    dv: wp.array(dtype=wp.vec3),
    dv_count: wp.array(dtype=wp.int32),
):
    """Point-triangle contact ``k``'s velocity change, into ``dv``/``dv_count``."""
    i = pt_vertex[k]
    t = pt_triangle[k]
    ia = tri_indices[t, 0]
    ib = tri_indices[t, 1]
    ic = tri_indices[t, 2]
    a = x[ia]
    b = x[ib]
    c = x[ic]
    n = unit_normal(a, b, c)
    if wp.length(n) == 0.0:
        return
    bary = clamped_bary(x[i], a, b, c)
    u = v[i] - (bary[0] * v[ia] + bary[1] * v[ib] + bary[2] * v[ic])
    un = wp.dot(u, n)
    change = wp.vec3(0.0)
    if un < 0.0:
        change = -(1.0 + restitution) * un * n
    ut = u - un * n
    lt = wp.length(ut)
    if lt > 1.0e-12:
        change = change - wp.min(1.0, friction * wp.abs(un) / lt) * ut
    wpp = inv_mass[i]
    den = wpp + inv_mass[ia] * bary[0] * bary[0] + inv_mass[ib] * bary[1] * bary[1] + inv_mass[ic] * bary[2] * bary[2]
    if den < 1.0e-30:
        return
    s = 1.0 / den
    wp.atomic_add(dv, i, s * wpp * change)
    wp.atomic_add(dv, ia, -s * inv_mass[ia] * bary[0] * change)
    wp.atomic_add(dv, ib, -s * inv_mass[ib] * bary[1] * change)
    wp.atomic_add(dv, ic, -s * inv_mass[ic] * bary[2] * change)
    wp.atomic_add(dv_count, i, 1)
    wp.atomic_add(dv_count, ia, 1)
    wp.atomic_add(dv_count, ib, 1)
    wp.atomic_add(dv_count, ic, 1)


@wp.kernel
def friction_restitution_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    chunk: int,
    # outputs
    dv: wp.array(dtype=wp.vec3),
    dv_count: wp.array(dtype=wp.int32),
):
    """The point-triangle contacts of this thread's chunk (see :func:`contact_range`), each
    with its character's friction and restitution."""
    first, last = contact_range(wp.tid(), chunk, pt_count[0], pt_vertex.shape[0])
    for k in range(first, last):
        s = params[vertex_tree[pt_vertex[k]]]
        friction_restitution(k, x, v, inv_mass, tri_indices, pt_vertex, pt_triangle, s.friction, s.restitution, dv,
                             dv_count)


@wp.kernel
def reset_collision_kernel(
    # outputs
    colliding: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    colliding[i] = 0


@wp.kernel
def volume_weights_kernel(
    colliding: wp.array(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    vertex_count: int,
    # outputs
    weight_scale: wp.array(dtype=wp.float32),
):
    """Colliding particles (layer-major, ``vertex_count`` per layer) get their character's
    ``volume_weight`` on their inverse mass in the volume loop (Diziol et al. 2011 use 0: they
    stay put)."""
    i = wp.tid()
    if colliding[i] != 0:
        weight_scale[i] = params[vertex_tree[i % vertex_count]].volume_weight
    else:
        weight_scale[i] = 1.0


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


# --------------------------------------------------------------------------------------------
# The fail-safe (after the elasticity loop and the tether): the constraints above are found
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

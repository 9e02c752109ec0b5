"""Self-collision of the skin layer (Deul & Bender 2013, section 4.5): what its three stages
share. The stages are modules of their own: detection on the predicted positions
(:mod:`warpskin.kernels.contact_detection`), the unilateral constraints projected inside the
elasticity loop with friction and restitution after it
(:mod:`warpskin.kernels.contact_projection`), and the fail-safe
(:mod:`warpskin.kernels.fail_safe`). Here: the per-character contact scalars and filter, the
tests of which pairs may collide (pieces apart, rigid groups, one patch at rest, a fold), the
closest-point and box geometry, and a thread's slice of a contact buffer.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

#: A point counts as over a triangle while its smallest barycentric coordinate is above minus
#: this. A point over an edge two triangles share has coordinate 0 in both, and float32
#: rounding gives its sign: with a strict test both could say "outside" and the contact would
#: be lost; with the band it collides with one or both (the contact point is clamped onto the
#: triangle).
INSIDE_TOLERANCE = wp.constant(1.0e-5)


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


@wp.func
def segment_closest(p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, p4: wp.vec3) -> wp.vec2:
    """Parameters (s, t) of the closest points p1 + s (p2 - p1) and p3 + t (p4 - p3) (Ericson,
    Real-Time Collision Detection, 5.1.9); a segment of length 0 is its point (s or t = 0)."""
    d1 = p2 - p1
    d2 = p4 - p3
    r = p1 - p3
    a = wp.dot(d1, d1)
    e = wp.dot(d2, d2)
    f = wp.dot(d2, r)
    s = float(0.0)
    t = float(0.0)
    if a <= 1.0e-30 and e > 1.0e-30:  # the first a point: its projection onto the second
        t = wp.clamp(f / e, 0.0, 1.0)
    elif e <= 1.0e-30 and a > 1.0e-30:  # the second a point
        s = wp.clamp(-wp.dot(d1, r) / a, 0.0, 1.0)
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

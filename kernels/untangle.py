"""Pair-by-pair separation of crossing triangles of a written mesh
(:class:`warpskin.guard.untangle.Untangle`).

For each crossing pair (triangles ``A``, ``B``) the side each must lie on is read from a
reference pose in which they do not cross (the last frame written, or the rest pose): the
closest points ``a`` on ``A`` and ``b`` on ``B`` there, and ``A`` belongs on the side
``s_AB = sign((a - b) . n_B)`` of ``B``'s plane, ``B`` on ``s_BA = sign((b - a) . n_A)`` of
``A``'s. Now, ``A``'s depth past ``B``'s plane is ``max_v max(0, -s_AB (v - B_0) . n_B)`` over
its corners, and ``B``'s past ``A``'s likewise. The plane with the smaller depth separates
them: the two triangles are translated apart along its normal by that depth (plus ``gap``, at
most ``max_step``), shared by their mobility (0: a point that must not move, a rigid piece's).
Where one triangle's piece is more than twice the other's (a skirt before a hand), its plane
is taken instead: the larger piece is locally the flatter, and all the small piece's triangles
then push the same way. A triangle wholly on its side of the other's plane cannot cross it, so one pair alone is
resolved in one step; the caller averages the pushes a point gets from several pairs and
repeats.
"""

import warp as wp

from .collision import closest_on_triangle, segment_closest, unit_normal

wp.set_module_options({"enable_backward": False})


@wp.func
def nearer(pa: wp.vec3, pb: wp.vec3, p: wp.vec3, q: wp.vec3):
    """``(p, q)`` where they are closer to each other than ``pa`` to ``pb``, else ``(pa, pb)``."""
    if wp.length_sq(p - q) < wp.length_sq(pa - pb):
        return p, q
    return pa, pb


@wp.func
def nearer_edges(pa: wp.vec3, pb: wp.vec3, p1: wp.vec3, p2: wp.vec3, p3: wp.vec3, p4: wp.vec3):
    """:func:`nearer` with the closest points of the edges ``p1 p2`` and ``p3 p4``."""
    st = segment_closest(p1, p2, p3, p4)
    return nearer(pa, pb, p1 + st[0] * (p2 - p1), p3 + st[1] * (p4 - p3))


@wp.func
def point_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """The point of triangle ``abc`` closest to ``p`` (its projection where that is inside, else
    the closest point of its edges)."""
    w = closest_on_triangle(p, a, b, c)
    if w[0] >= 0.0 and w[1] >= 0.0 and w[2] >= 0.0:
        return w[0] * a + w[1] * b + w[2] * c
    st = segment_closest(p, p, a, b)
    q = a + st[1] * (b - a)
    _, q = nearer_edges(p, q, p, p, b, c)
    _, q = nearer_edges(p, q, p, p, c, a)
    return q


@wp.func
def from_a_to_b(a0: wp.vec3, a1: wp.vec3, a2: wp.vec3, b0: wp.vec3, b1: wp.vec3, b2: wp.vec3) -> wp.vec3:
    """``b - a`` for the closest points ``a`` on triangle ``a0 a1 a2`` and ``b`` on ``b0 b1 b2``
    (corners against the other triangle, edges against edges: the closest pair of two disjoint
    triangles is one of these)."""
    pa = a0
    pb = point_on_triangle(a0, b0, b1, b2)
    pa, pb = nearer(pa, pb, a1, point_on_triangle(a1, b0, b1, b2))
    pa, pb = nearer(pa, pb, a2, point_on_triangle(a2, b0, b1, b2))
    pa, pb = nearer(pa, pb, point_on_triangle(b0, a0, a1, a2), b0)
    pa, pb = nearer(pa, pb, point_on_triangle(b1, a0, a1, a2), b1)
    pa, pb = nearer(pa, pb, point_on_triangle(b2, a0, a1, a2), b2)
    pa, pb = nearer_edges(pa, pb, a0, a1, b0, b1)
    pa, pb = nearer_edges(pa, pb, a0, a1, b1, b2)
    pa, pb = nearer_edges(pa, pb, a0, a1, b2, b0)
    pa, pb = nearer_edges(pa, pb, a1, a2, b0, b1)
    pa, pb = nearer_edges(pa, pb, a1, a2, b1, b2)
    pa, pb = nearer_edges(pa, pb, a1, a2, b2, b0)
    pa, pb = nearer_edges(pa, pb, a2, a0, b0, b1)
    pa, pb = nearer_edges(pa, pb, a2, a0, b1, b2)
    pa, pb = nearer_edges(pa, pb, a2, a0, b2, b0)
    return pb - pa


@wp.func
def side(d: wp.vec3, n: wp.vec3, facing_sign: float) -> float:
    """The sign of ``d . n``; ``facing_sign`` where it is within rounding of 0."""
    s = wp.dot(d, n)
    if wp.abs(s) <= 1.0e-12 * wp.length(d) + 1.0e-30:
        return facing_sign
    if s > 0.0:
        return 1.0
    return -1.0


@wp.func
def depth_past(a0: wp.vec3, a1: wp.vec3, a2: wp.vec3, origin: wp.vec3, n: wp.vec3, s: float) -> float:
    """How far the farthest corner of ``a0 a1 a2`` lies on the wrong side (``-s``) of the plane
    through ``origin`` with unit normal ``n``; 0 where all lie on side ``s``."""
    d = wp.max(-s * wp.dot(a0 - origin, n), -s * wp.dot(a1 - origin, n))
    return wp.max(0.0, wp.max(d, -s * wp.dot(a2 - origin, n)))


@wp.kernel
def separate_pairs_kernel(
    x: wp.array(dtype=wp.vec3),
    ref: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    pairs: wp.array(dtype=wp.vec2i),
    mobility: wp.array(dtype=float),
    size: wp.array(dtype=float),
    gap: float,
    max_step: float,
    push: wp.array(dtype=wp.vec3),
    count: wp.array(dtype=float),
):
    """Per crossing pair (``pairs``: triangle indices): the translations that separate its two
    triangles (module docstring), added to ``push`` of their corners (``count`` + 1 each; the
    caller averages). ``x``: the points now, ``ref``: the reference pose (both ``[N]`` [m]);
    ``mobility``: ``[N]`` in [0, 1], a triangle's the least of its corners'; ``size``: ``[T]``
    the diagonal [m] of the piece of every triangle; ``gap`` [m]: the
    clearance added to the depth; ``max_step`` [m]: the most a pair's push may be."""
    k = wp.tid()
    ta = triangles[pairs[k][0]]
    tb = triangles[pairs[k][1]]
    ma = wp.min(mobility[ta[0]], wp.min(mobility[ta[1]], mobility[ta[2]]))
    mb = wp.min(mobility[tb[0]], wp.min(mobility[tb[1]], mobility[tb[2]]))
    if ma + mb <= 0.0:
        return
    ra0 = ref[ta[0]]
    ra1 = ref[ta[1]]
    ra2 = ref[ta[2]]
    rb0 = ref[tb[0]]
    rb1 = ref[tb[1]]
    rb2 = ref[tb[2]]
    ab = from_a_to_b(ra0, ra1, ra2, rb0, rb1, rb2)
    rna = unit_normal(ra0, ra1, ra2)
    rnb = unit_normal(rb0, rb1, rb2)
    # facing surfaces of one body (the default where the reference cannot tell): each in front
    s_ab = side(-ab, rnb, 1.0)
    s_ba = side(ab, rna, 1.0)
    a0 = x[ta[0]]
    a1 = x[ta[1]]
    a2 = x[ta[2]]
    b0 = x[tb[0]]
    b1 = x[tb[1]]
    b2 = x[tb[2]]
    na = unit_normal(a0, a1, a2)
    nb = unit_normal(b0, b1, b2)
    depth_a = depth_past(a0, a1, a2, b0, nb, s_ab)
    depth_b = depth_past(b0, b1, b2, a0, na, s_ba)
    axis = s_ab * nb  # the direction A moves, B the opposite
    depth = depth_a
    sa = size[pairs[k][0]]
    sb = size[pairs[k][1]]
    # a piece much larger than the other is locally the flatter: its plane separates them (a
    # skirt before a hand, a torso under a hand); between pieces of a size, the shallower plane
    if sa > 2.0 * sb or (sb <= 2.0 * sa and depth_b < depth_a):
        axis = -s_ba * na
        depth = depth_b
    step = wp.min(depth + gap, max_step)
    if wp.length_sq(axis) == 0.0:
        return
    da = axis * (step * ma / (ma + mb))
    db = -axis * (step * mb / (ma + mb))
    for i in range(3):
        wp.atomic_add(push, ta[i], da)
        wp.atomic_add(count, ta[i], 1.0)
        wp.atomic_add(push, tb[i], db)
        wp.atomic_add(count, tb[i], 1.0)


@wp.kernel
def press_kernel(
    capped: wp.uint64,
    surface: wp.uint64,
    queries: wp.array(dtype=wp.vec3),
    max_dist: float,
    # outputs
    inside: wp.array(dtype=wp.int32),
    closest: wp.array(dtype=wp.vec3),
):
    """One thread per query point ``q``: whether it is inside the closed mesh ``capped`` (a
    piece with its holes capped, built with ``support_winding_number``: its generalised
    winding number above a half, Jacobson et al. 2013, by Warp's fast winding number), and the
    point of the mesh ``surface`` (the piece itself, without its caps) nearest it, searched
    within ``max_dist`` [m] (``q`` itself where none is that near)."""
    i = wp.tid()
    q = queries[i]
    inside[i] = 0
    s = wp.mesh_query_point_sign_winding_number(capped, q, max_dist, 2.0, 0.5)
    if s.result and s.sign < 0.0:
        inside[i] = 1
    closest[i] = q
    c = wp.mesh_query_point_no_sign(surface, q, max_dist)
    if c.result:
        closest[i] = wp.mesh_eval_position(surface, c.face, c.u, c.v)


@wp.kernel
def exit_kernel(
    mesh: wp.uint64,
    queries: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    max_t: float,
    # outputs
    exit: wp.array(dtype=float),
):
    """One thread per query point ``q`` with a unit direction ``u``: the least ``t`` in
    ``(0, max_t]`` [m] at which the ray ``q + t u`` meets the mesh (both faces): for ``q``
    inside a closed mesh, where the ray leaves it; 0 where it meets none."""
    i = wp.tid()
    h = wp.mesh_query_ray(mesh, queries[i], directions[i], max_t)
    exit[i] = 0.0
    if h.result:
        exit[i] = h.t

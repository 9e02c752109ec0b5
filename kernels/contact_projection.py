"""Contact projection of the skin's self-collision (Deul & Bender 2013, section 4.5): the
point-triangle and edge-edge unilateral constraints, projected inside the elasticity loop (their
corrections averaged per particle), friction and restitution after the velocity update, and the
volume loop's weights at contacts."""

import warp as wp

from .collision import (
    CollisionScalars, clamped_bary, contact_range, lines_meet_far_from_edges, segment_closest, unit_normal,
)

wp.set_module_options({"enable_backward": False})


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
    count_active: int,
):
    """Contact ``k``'s point-triangle constraint, projected into ``delta``/``delta_count``;
    counted in ``active[0]`` where violated if ``count_active`` != 0."""
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
    if count_active != 0:
        wp.atomic_add(active, 0, 1)


@wp.func
def point_triangle_chunk(
    thread: int,
    chunk: int,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    count_active: int,
):
    """:func:`project_point_triangle` over the contacts of chunk ``thread`` that exist
    (:func:`contact_range`), each at its character's thickness."""
    first, last = contact_range(thread, chunk, pt_count[0], pt_vertex.shape[0])
    for k in range(first, last):
        thickness = params[vertex_tree[pt_vertex[k]]].thickness
        project_point_triangle(k, x, inv_mass, tri_indices, pt_vertex, pt_triangle, thickness, delta, delta_count,
                               active, count_active)


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
    count_active: int,
):
    """Contact ``k``'s edge-edge constraint, projected into ``delta``/``delta_count``; counted
    in ``active[0]`` where violated if ``count_active`` != 0."""
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
    if count_active != 0:
        wp.atomic_add(active, 0, 1)


@wp.func
def edge_edge_chunk(
    thread: int,
    chunk: int,
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    edge_indices: wp.array2d(dtype=wp.int32),
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    count_active: int,
):
    """:func:`project_edge_edge` over the contacts of chunk ``thread`` that exist
    (:func:`contact_range`), each at its character's thickness."""
    first, last = contact_range(thread, chunk, ee_count[0], ee_a.shape[0])
    for k in range(first, last):
        thickness = params[vertex_tree[edge_indices[ee_a[k], 0]]].thickness
        project_edge_edge(k, x, inv_mass, edge_indices, ee_a, ee_b, ee_sign, thickness, delta, delta_count, active,
                          count_active)


@wp.kernel
def project_contacts_kernel(
    x: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    tri_indices: wp.array2d(dtype=wp.int32),
    pt_count: wp.array(dtype=wp.int32),
    pt_vertex: wp.array(dtype=wp.int32),
    pt_triangle: wp.array(dtype=wp.int32),
    edge_indices: wp.array2d(dtype=wp.int32),
    ee_count: wp.array(dtype=wp.int32),
    ee_a: wp.array(dtype=wp.int32),
    ee_b: wp.array(dtype=wp.int32),
    ee_sign: wp.array(dtype=wp.float32),
    params: wp.array(dtype=CollisionScalars),
    vertex_tree: wp.array(dtype=wp.int32),
    chunk: int,
    pt_threads: int,
    count_active: int,
    # outputs
    delta: wp.array(dtype=wp.vec3),
    delta_count: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
):
    """One Jacobi pass's corrections of both kinds of contacts in one launch: threads
    ``[0, pt_threads)`` take the point-triangle contacts of their chunk
    (:func:`point_triangle_chunk`), the others the edge-edge contacts of chunk ``thread -
    pt_threads`` (:func:`edge_edge_chunk`). Both only read ``x`` and add into ``delta``, so the
    pass is that of each kind launched alone, one after the other (on the CPU, whose threads run
    in order, the same sums in the same order). With ``count_active`` != 0 the violated
    constraints are counted into ``active[0]`` (the caller zeroes it): only the last pass of a
    projection counts, so the passes before it take no atomic on that one address."""
    tid = wp.tid()
    if tid < pt_threads:
        point_triangle_chunk(tid, chunk, x, inv_mass, tri_indices, pt_count, pt_vertex, pt_triangle, params,
                             vertex_tree, delta, delta_count, active, count_active)
    else:
        edge_edge_chunk(tid - pt_threads, chunk, x, inv_mass, edge_indices, ee_count, ee_a, ee_b, ee_sign, params,
                        vertex_tree, delta, delta_count, active, count_active)


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

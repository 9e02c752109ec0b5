"""The written meshes' deformation: every written point is its own linear blend skinning plus
the physical deformation captured from the simulated surface, blended by its physics weight.

    d_j  = x_j - sum_k w_jk C_{c_jk} [X_j, 1]                   simulated vertex j's displacement
                                                               from its own LBS (X_j: its rest;
                                                               the LBS is the solver tether's
                                                               target, or one launch here)
    p_i' = sum_k v_ik R_{r_ik} [P_i, 1] + phi_i sum_m a_im d_{s_im}

``C`` are the simulated surface's skinning matrices, ``R`` the written meshes' (each mesh its
own inverse binds, stacked ``mesh x joint``), ``P`` the written points in their bind space,
``(s_im, a_im)`` the capture (:mod:`warpskin.capture`: a few simulated vertices per written
point, weights summing to one) and ``phi_i`` in [0, 1] the physics weight. Where the simulation
is at its LBS (``d = 0``) or ``phi = 0`` the written point is exactly its LBS; a written piece
whose points share one capture row moves by one translation on top of its LBS.

Influences and captures are flat arrays with a fixed count per point (weight 0 pads), so every
argument is one-dimensional (Warp's contiguous CPU path). One thread per point, no atomics.

A piece that moves as a whole (an eye carried by its socket, a fist, a hair bun rigid in the
file) moves by the best rigid motion of the simulated vertices that carry it
away from their LBS (:func:`group_fit_kernel`: weighted Kabsch, the polar factor of their
covariance; then :func:`group_apply_kernel`, the share ``phi`` of it on the piece's LBS): it
keeps the shape its LBS gives it and turns with what holds it.

A piece worn over the simulated pieces (a garment, a hair cap) is *wrapped* instead
(:func:`wrap_kernel`): each of its points rides on its closest point at rest of the written
surface of the simulated pieces (what shows beneath it), ``c = sum_k b_k x_{t_k}`` (barycentric
on triangle ``t``), at its rest offset ``o``
expressed as ``alpha e_1 + beta e_2 + gamma n`` in that triangle's edges ``e_1, e_2`` and the
surface's unit normal ``n`` there (the vertex normals blended by ``b``): where the surface
stretches, bends or swells the worn point follows at its own distance from it, so a garment keeps
its gap to the body and crosses it no more than the body crosses itself. A point skinned to two
joints whose skins lie apart (the web of baggy trousers between the knees) rides on a carrier on
each, blended by their skinning similarity with it, as LBS blends the two joints
(:func:`~warpskin.capture.wrap_carriers`). Then
(:func:`push_out_kernel`) a worn point that another part of the surface has come nearer than
its clearance (the thigh and the calf meeting at a bent knee, under the trousers) is put back
out to it, along the closest surface point's side: the overlap present at rest is kept (a point
inside a simulated piece at rest has no clearance and is left where it is wrapped).
"""

import warp as wp

from .rotation import polar_rotation_svd

wp.set_module_options({"enable_backward": False})


@wp.func
def lbs_flat(p: wp.vec3, row: int, influence_count: int, joint_indices: wp.array(dtype=wp.int32),
             joint_weights: wp.array(dtype=wp.float32), skin_matrices: wp.array(dtype=wp.mat44)) -> wp.vec3:
    """``sum_k w_k M_{j_k} [p, 1]`` over the ``influence_count`` influences of ``row`` (flat
    arrays, weight 0 pads)."""
    acc = wp.vec3(0.0)
    for k in range(influence_count):
        w = joint_weights[row * influence_count + k]
        if w != 0.0:
            acc += w * wp.transform_point(skin_matrices[joint_indices[row * influence_count + k]], p)
    return acc


@wp.kernel
def surface_lbs_kernel(
    rest: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    # output
    lbs: wp.array(dtype=wp.vec3),
):
    """``LBS(X_j)`` of every simulated surface vertex ``j`` (where the solver's tether targets
    are not at hand)."""
    j = wp.tid()
    lbs[j] = lbs_flat(rest[j], j, influence_count, joint_indices, joint_weights, skin_matrices)


@wp.kernel
def deform_from_targets_kernel(
    bind_points: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    capture_count: int,
    capture_indices: wp.array(dtype=wp.int32),
    capture_weights: wp.array(dtype=wp.float32),
    physics_weight: wp.array(dtype=wp.float32),
    x: wp.array(dtype=wp.vec3),
    surface_lbs: wp.array(dtype=wp.vec3),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """``p_i' = LBS(P_i) + phi_i sum_m a_im (x_{s_im} - surface_lbs_{s_im})`` (``joint_indices``
    already offset into the stacked per-mesh matrices; ``surface_lbs``: the simulated surface's
    LBS, the solver tether's targets of the step or :func:`surface_lbs_kernel`'s)."""
    i = wp.tid()
    acc = lbs_flat(bind_points[i], i, influence_count, joint_indices, joint_weights, skin_matrices)
    phi = physics_weight[i]
    if phi > 0.0:
        d = wp.vec3(0.0)
        for m in range(capture_count):
            a = capture_weights[i * capture_count + m]
            if a != 0.0:
                j = capture_indices[i * capture_count + m]
                d += a * (x[j] - surface_lbs[j])
        acc += phi * d
    out[i] = acc


@wp.kernel
def inward_rays_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    start: float,
    max_dist: float,
    tilt: float,
    # output
    hits: wp.array(dtype=wp.float32),
):
    """Distances along five rays into the surface from every point (the shape diameter there):
    one along the inward normal, four tilted by ``tilt`` radians about it, each to where it
    leaves the solid it starts in (surfaces entered and left on the way, of pieces that overlap
    this one, are counted through); each
    starts ``start`` inside the point (past its own faces) and reports ``max_dist`` where it
    leaves through nothing (an open piece)."""
    i = wp.tid()
    n = normals[i]
    helper = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        helper = wp.vec3(0.0, 1.0, 0.0)
    u = wp.normalize(wp.cross(n, helper))
    v = wp.cross(n, u)
    o = points[i] - start * n
    c = wp.cos(tilt)
    s = wp.sin(tilt)
    for r in range(5):
        d = -n
        if r == 1:
            d = -c * n + s * u
        elif r == 2:
            d = -c * n - s * u
        elif r == 3:
            d = -c * n + s * v
        elif r == 4:
            d = -c * n - s * v
        d = wp.normalize(d)
        # where the ray leaves the solid it starts in: it counts the surfaces it enters (front
        # faces) and leaves (back faces), so passing through another piece that overlaps this
        # one (a ball joint inside a tube's end) does not end the part
        travelled = float(0.0)
        result = max_dist
        depth = int(1)
        for _ in range(12):
            q = wp.mesh_query_ray(mesh, o + travelled * d, d, max_dist - travelled)
            if not q.result:
                break
            travelled += q.t
            if q.sign < 0.0:
                depth -= 1
            else:
                depth += 1
            if depth == 0:
                result = travelled + start
                break
            travelled += start
        hits[i * 5 + r] = result


@wp.kernel
def zero_vec3_kernel(
    # output
    a: wp.array(dtype=wp.vec3),
):
    a[wp.tid()] = wp.vec3(0.0)


@wp.kernel
def surface_normals_kernel(
    x: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.int32),
    # output
    normals: wp.array(dtype=wp.vec3),
):
    """Area-weighted vertex normals (not normalised) of the simulated surface ``x`` (its first
    vertices the skin layer; ``triangles`` flat, three per triangle), accumulated per triangle
    into ``normals`` (zeroed first)."""
    t = wp.tid()
    a = triangles[3 * t]
    b = triangles[3 * t + 1]
    c = triangles[3 * t + 2]
    n = wp.cross(x[b] - x[a], x[c] - x[a])
    wp.atomic_add(normals, a, n)
    wp.atomic_add(normals, b, n)
    wp.atomic_add(normals, c, n)


@wp.func
def wrapped_point(x: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), mesh: wp.uint64, i0: int, i1: int,
                  i2: int, bary: wp.vec3, coef: wp.vec3, share: float, room0: float) -> wp.vec3:
    """The point at ``coef = (alpha, beta, gamma)`` from the surface point ``bary`` of triangle
    ``(i0, i1, i2)``: ``c + alpha e_1 + beta e_2 + gamma' n`` (see the module docstring). Where
    another part of the surface (``mesh``, as it is now) lies along ``n`` within ``gamma /
    share``, the worn point keeps to its share of that room: ``gamma' = min(gamma, share x s)``
    (the back of a bent knee); where something already lay there at rest, ``room0`` away (a hair
    cap over a bun), in proportion: ``gamma' = gamma min(1, s / room0)``."""
    x0 = x[i0]
    x1 = x[i1]
    x2 = x[i2]
    c = bary[0] * x0 + bary[1] * x1 + bary[2] * x2
    n = bary[0] * normals[i0] + bary[1] * normals[i1] + bary[2] * normals[i2]
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
    g = coef[2]
    if g > 0.0 and ln > 0.0:
        start = 1.0e-3 * g
        reach = g / share
        if room0 > 0.0:
            reach = wp.max(reach, room0)
        q = wp.mesh_query_ray(mesh, c + start * n, n, reach)
        if q.result:
            room = q.t + start
            if room0 > 0.0:
                g = g * wp.min(1.0, room / room0)
            else:
                g = wp.min(g, share * room)
    return c + coef[0] * (x1 - x0) + coef[1] * (x2 - x0) + g * n


@wp.kernel
def wrap_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    share: float,
    points: wp.array(dtype=wp.int32),
    carriers: int,
    tri_vertices: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    coef: wp.array(dtype=wp.vec3),
    carrier_share: wp.array(dtype=wp.float32),
    room0: wp.array(dtype=wp.float32),
    physics_weight: wp.array(dtype=wp.float32),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Wrapped point ``k`` (written point ``points[k]``, whose ``out`` holds its LBS): ``out =
    LBS + phi (wrapped - LBS)``, ``wrapped`` the blend by ``carrier_share`` of the point as each of
    its ``carriers`` carries it (:func:`wrapped_point`; carrier ``c`` of point ``k`` at entry ``k
    carriers + c`` of ``bary``, ``coef``, ``carrier_share``, ``room0`` and, times 3, of
    ``tri_vertices``) on the written surface ``x`` with its vertex ``normals`` (``mesh``: the same
    surface, refitted; ``room0``: the room along the carrier's normal at rest, 0 where there was
    none within its reach). A carrier with share 0 is not evaluated."""
    k = wp.tid()
    i = points[k]
    w = wp.vec3(0.0, 0.0, 0.0)
    for c in range(carriers):
        e = k * carriers + c
        a = carrier_share[e]
        if a > 0.0:
            w += a * wrapped_point(x, normals, mesh, tri_vertices[3 * e], tri_vertices[3 * e + 1],
                                   tri_vertices[3 * e + 2], bary[e], coef[e], share, room0[e])
    lb = out[i]
    out[i] = lb + physics_weight[i] * (w - lb)


@wp.kernel
def room_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    mesh: wp.uint64,
    share: float,
    tri_vertices: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    coef: wp.array(dtype=wp.vec3),
    # output
    room: wp.array(dtype=wp.float32),
):
    """The room along the normal at rest of wrap entry ``k`` (a point's carrier, see
    :func:`wrapped_point`): the distance to the surface ``mesh`` within ``gamma / share`` of its
    surface point, else 0."""
    k = wp.tid()
    i0 = tri_vertices[3 * k]
    i1 = tri_vertices[3 * k + 1]
    i2 = tri_vertices[3 * k + 2]
    b = bary[k]
    c = b[0] * x[i0] + b[1] * x[i1] + b[2] * x[i2]
    n = b[0] * normals[i0] + b[1] * normals[i1] + b[2] * normals[i2]
    ln = wp.length(n)
    g = coef[k][2]
    room[k] = 0.0
    if g > 0.0 and ln > 0.0:
        n = n / ln
        start = 1.0e-3 * g
        q = wp.mesh_query_ray(mesh, c + start * n, n, g / share)
        if q.result:
            room[k] = q.t + start


@wp.func
def side_of_closest(mesh: wp.uint64, normals: wp.array(dtype=wp.vec3), tri_vertices: wp.array(dtype=wp.int32),
                    p: wp.vec3, face: int, u: float, v: float) -> float:
    """The side of ``mesh`` (over points whose vertex ``normals`` are given, its triangles
    ``tri_vertices``) that ``p`` lies on, from its closest point ``(face, u, v)``: the sign of
    ``(p - s) . n_s`` with ``s`` the closest point and ``n_s`` the vertex normals interpolated
    there (1: in front, -1: behind). Unlike the query's own sign by the closest face's normal,
    a point about as far from two parts of the surface that face each other (a shirt between
    the torso and a hanging arm) gets the side of the one it was found on."""
    s = wp.mesh_eval_position(mesh, face, u, v)
    n = (u * normals[tri_vertices[3 * face]] + v * normals[tri_vertices[3 * face + 1]]
         + (1.0 - u - v) * normals[tri_vertices[3 * face + 2]])
    if wp.dot(p - s, n) < 0.0:
        return -1.0
    return 1.0


@wp.kernel
def push_out_kernel(
    mesh: wp.uint64,
    normals: wp.array(dtype=wp.vec3),
    tri_vertices: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.int32),
    clearance: wp.array(dtype=wp.float32),
    max_dist: float,
    max_push: float,
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Worn point ``k`` (written point ``points[k]``) nearer the written surface of the simulated
    pieces (``mesh`` over the written points as they are, its triangles ``tri_vertices`` and
    their vertex ``normals``) than its ``clearance`` [m], or behind it by at most ``max_push``
    [m], goes out to that clearance from its closest surface point; a clearance of 0 or less
    leaves it, and so does a point deeper behind the surface (where two parts of the body press
    together its closest face may be the other part's: the side of an open surface is not to
    be trusted that far in). The side is :func:`side_of_closest`'s."""
    k = wp.tid()
    c = clearance[k]
    if c <= 0.0:
        return
    i = points[k]
    p = out[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    if not q.result:
        return
    s = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    sign = side_of_closest(mesh, normals, tri_vertices, p, q.face, q.u, q.v)
    d = p - s
    ld = wp.length(d)
    if sign >= 0.0 and ld >= c:
        return
    if sign < 0.0 and ld > max_push:
        return
    n = wp.mesh_eval_face_normal(mesh, q.face)
    if ld > 1.0e-9 * c:
        n = d / ld
        if sign < 0.0:
            n = -n
    out[i] = s + c * n


@wp.kernel
def signed_distance_kernel(
    mesh: wp.uint64,
    normals: wp.array(dtype=wp.vec3),
    tri_vertices: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    # output
    dist: wp.array(dtype=wp.float32),
):
    """The distance [m] of ``points[i]`` to ``mesh`` (its triangles ``tri_vertices``, their
    vertex ``normals``), negative behind it (:func:`side_of_closest`); ``max_dist`` where
    nothing is that near."""
    i = wp.tid()
    p = points[i]
    q = wp.mesh_query_point_no_sign(mesh, p, max_dist)
    dist[i] = max_dist
    if q.result:
        sign = side_of_closest(mesh, normals, tri_vertices, p, q.face, q.u, q.v)
        dist[i] = sign * wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))


@wp.kernel
def group_fit_kernel(
    x: wp.array(dtype=wp.vec3),
    lbs: wp.array(dtype=wp.vec3),
    offsets: wp.array(dtype=wp.int32),
    vertices: wp.array(dtype=wp.int32),
    weights: wp.array(dtype=wp.float32),
    # outputs
    rotation: wp.array(dtype=wp.quat),
    centre_lbs: wp.array(dtype=wp.vec3),
    centre: wp.array(dtype=wp.vec3),
):
    """Group ``g``'s rigid motion away from its LBS: its simulated vertices ``vertices[offsets[g]
    .. offsets[g + 1]]`` with ``weights`` (summing to one) at ``x`` against their ``lbs`` (the
    surface's LBS this frame): ``centre`` and ``centre_lbs`` their weighted centres, ``rotation``
    the polar factor of ``sum w (x - c)(l - c_l)^T`` (weighted Kabsch)."""
    g = wp.tid()
    c = wp.vec3(0.0)
    cl = wp.vec3(0.0)
    for k in range(offsets[g], offsets[g + 1]):
        c += weights[k] * x[vertices[k]]
        cl += weights[k] * lbs[vertices[k]]
    a = wp.mat33(0.0)
    for k in range(offsets[g], offsets[g + 1]):
        j = vertices[k]
        a += weights[k] * wp.outer(x[j] - c, lbs[j] - cl)
    rotation[g] = polar_rotation_svd(a)
    centre_lbs[g] = cl
    centre[g] = c


@wp.func
def _short_arc(q: wp.quat) -> wp.quat:
    """``q`` or ``-q``, the same rotation, whichever lies on the short arc from the identity."""
    if q[3] < 0.0:
        return -q
    return q


@wp.func
def _group_place(r: wp.quat, s: float, l: wp.vec3, cl: wp.vec3, c: wp.vec3) -> wp.vec3:
    """A grouped point at LBS ``l`` under the share ``s`` of its group's motion (``r``: that share
    of the rotation; ``cl``, ``c``: the group's centres under LBS and as simulated):
    ``R_s (l - c_l) + c_l + s (c - c_l)``."""
    return wp.quat_rotate(r, l - cl) + cl + s * (c - cl)


@wp.func
def _anchor_reach(s: float, q: wp.quat, cl: wp.vec3, c: wp.vec3, out: wp.array(dtype=wp.vec3),
                  anchors: wp.array(dtype=wp.int32), start: int, end: int) -> float:
    """The farthest any anchor (written point ``anchors[start .. end]``, ``out`` its LBS ``l``)
    moves from its LBS under the share ``s`` of a group's motion (:func:`_group_place`)."""
    r = wp.quat_slerp(wp.quat_identity(), q, s)
    far = float(0.0)
    for k in range(start, end):
        l = out[anchors[k]]
        far = wp.max(far, wp.length(_group_place(r, s, l, cl, c) - l))
    return far


@wp.kernel
def group_limit_kernel(
    out: wp.array(dtype=wp.vec3),
    rotation: wp.array(dtype=wp.quat),
    centre_lbs: wp.array(dtype=wp.vec3),
    centre: wp.array(dtype=wp.vec3),
    anchor_offsets: wp.array(dtype=wp.int32),
    anchors: wp.array(dtype=wp.int32),
    physics_weight: wp.array(dtype=wp.float32),
    limit: float,
    # output
    share: wp.array(dtype=wp.float32),
):
    """Group ``g``'s share in [0, 1] of its motion (:func:`group_fit_kernel`, after the physics
    weight of its points, uniform in a group): the largest with which no anchor (its points
    where it meets other pieces at rest, ``anchors[anchor_offsets[g] .. anchor_offsets[g + 1]]``,
    ``out`` holding their LBS) moves farther than ``limit`` [m] from its LBS (bisection, 20
    halvings; 1 where the whole motion stays within it). A piece moved as a whole so keeps its
    joints: no gap opens where it meets its neighbours, however far the simulated surface around
    it swings."""
    g = wp.tid()
    a0 = anchor_offsets[g]
    a1 = anchor_offsets[g + 1]
    share[g] = 1.0
    if a1 <= a0:
        return
    phi = physics_weight[anchors[a0]]
    q = _short_arc(rotation[g])
    cl = centre_lbs[g]
    c = centre[g]
    if _anchor_reach(phi, q, cl, c, out, anchors, a0, a1) <= limit:
        return
    lo = float(0.0)
    hi = float(1.0)
    for _it in range(20):
        mid = 0.5 * (lo + hi)
        if _anchor_reach(mid * phi, q, cl, c, out, anchors, a0, a1) <= limit:
            lo = mid
        else:
            hi = mid
    share[g] = lo


@wp.kernel
def piece_limit_kernel(
    bind_points: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    out: wp.array(dtype=wp.vec3),
    anchor_offsets: wp.array(dtype=wp.int32),
    anchors: wp.array(dtype=wp.int32),
    limit: float,
    # output
    share: wp.array(dtype=wp.float32),
):
    """Small piece ``c``'s share in [0, 1] of its written displacement from LBS (``out`` less its
    LBS, :func:`deform_from_targets_kernel`'s): ``min(1, limit / the farthest of its anchors
    anchors[anchor_offsets[c] .. anchor_offsets[c + 1]])``, so that where it meets other pieces at
    rest it stays within ``limit`` [m] of its LBS (a hand at its wrist)."""
    c = wp.tid()
    far = float(0.0)
    for k in range(anchor_offsets[c], anchor_offsets[c + 1]):
        i = anchors[k]
        l = lbs_flat(bind_points[i], i, influence_count, joint_indices, joint_weights, skin_matrices)
        far = wp.max(far, wp.length(out[i] - l))
    share[c] = 1.0
    if far > limit:
        share[c] = limit / far


@wp.kernel
def piece_scale_kernel(
    bind_points: wp.array(dtype=wp.vec3),
    influence_count: int,
    joint_indices: wp.array(dtype=wp.int32),
    joint_weights: wp.array(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    points: wp.array(dtype=wp.int32),
    piece: wp.array(dtype=wp.int32),
    share: wp.array(dtype=wp.float32),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Written point ``points[k]`` of small piece ``piece[k]``: its displacement from LBS scaled
    by the piece's ``share`` (:func:`piece_limit_kernel`): ``out = l + s (out - l)``, uniform
    over the piece (no seam within it)."""
    k = wp.tid()
    i = points[k]
    s = share[piece[k]]
    if s < 1.0:
        l = lbs_flat(bind_points[i], i, influence_count, joint_indices, joint_weights, skin_matrices)
        out[i] = l + s * (out[i] - l)


@wp.kernel
def group_apply_kernel(
    points: wp.array(dtype=wp.int32),
    group: wp.array(dtype=wp.int32),
    rotation: wp.array(dtype=wp.quat),
    centre_lbs: wp.array(dtype=wp.vec3),
    centre: wp.array(dtype=wp.vec3),
    physics_weight: wp.array(dtype=wp.float32),
    share: wp.array(dtype=wp.float32),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Grouped point ``k`` (written point ``points[k]``, whose ``out`` holds its LBS ``l``):
    ``out = R_s (l - c_l) + c_l + s (c - c_l)`` with ``s = phi x share[g]``, ``R_s`` the share
    ``s`` of its group's rotation (slerp from the identity). A piece that LBS moves rigidly stays
    rigid for every ``s`` in [0, 1]: ``s = 0`` is its LBS, ``s = 1`` the whole fitted motion."""
    k = wp.tid()
    i = points[k]
    g = group[k]
    phi = physics_weight[i] * share[g]
    q = _short_arc(rotation[g])
    r = wp.quat_slerp(wp.quat_identity(), q, phi)
    out[i] = _group_place(r, phi, out[i], centre_lbs[g], centre[g])

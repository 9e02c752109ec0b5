"""Volume constraints per sub-volume (Deul & Bender 2013, section 4.6, after Diziol, Bender &
Bayer 2011), projected with position-based dynamics (section 4.2.2).

Launch wrappers and the host layout live in :mod:`warpskin.volume`; this module holds no
Python state.

Point indices of the closed sub-volume triangles use one encoding throughout: ``k < V`` is
skin vertex ``k`` (particle ``k`` of the layer-major particle array), ``k >= V`` is fan center
``k - V`` (kinematic: read, never written).

One projection iteration is three launches, all atomic-free and deterministic:

1. :func:`volume_gradient_kernel`, one thread per (vertex, sub-volume) pair: ``grad_i V_s``,
   its surface part ``d_i`` (the correction's direction) and ``w_i grad_i V_s . d_i``;
2. :func:`volume_lambda_kernel`, one thread block per sub-volume: ``V_s`` (a block reduction
   over its closed triangles), the denominator (a block reduction over its pairs) and the
   Lagrange multiplier ``lambda_s``;
3. :func:`volume_correction_kernel`, one thread per skin vertex: ``dp_i = w_i sum_s lambda_s
   d_i`` over the sub-volumes of the vertex (Jacobi across sub-volumes).

Sums run in float64, with points taken relative to a per-sub-volume origin (a point of that
sub-volume), so float32 positions far from the world origin keep the volume: a triple product
of coordinates of size ``L`` carries terms of size ``L^3`` that cancel to the volume.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def closed_point(
    x: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    vertex_count: int,
    k: int,
) -> wp.vec3d:
    """Point ``k`` of a closed sub-volume in float64: skin vertex ``k`` or fan center ``k - V``."""
    if k < vertex_count:
        return wp.vec3d(x[k])
    return wp.vec3d(centers[k - vertex_count])


# --------------------------------------------------------------------------------------------
# Kinematic fan centers: they move rigidly with the joint whose bone carries them,
#
#   c_k(t) = M_{j_k}(t) @ [c_k^rest, 1],   M_j = G_j(t) @ inverse_bind_j
# --------------------------------------------------------------------------------------------
@wp.kernel
def subvolume_center_kernel(
    center_rest: wp.array(dtype=wp.vec3),
    center_joint: wp.array(dtype=wp.int32),
    skin_matrices: wp.array(dtype=wp.mat44),
    # outputs
    centers: wp.array(dtype=wp.vec3),
):
    k = wp.tid()
    centers[k] = wp.transform_point(skin_matrices[center_joint[k]], center_rest[k])


# --------------------------------------------------------------------------------------------
# Volume of a closed, outward-wound triangle set (divergence theorem), about an origin o:
#
#   V_s = 1/6 sum_{(a, b, c) in s} (p_a - o) . ((p_b - o) x (p_c - o))
#
# (independent of o because the set is closed). Each lane of a block sums a strided share of
# the triangles; the block then reduces the partial sums (wp.tile_sum, a fixed order).
# --------------------------------------------------------------------------------------------
@wp.func
def subvolume_partial_volume(
    x: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    vertex_count: int,
    closed_offsets: wp.array(dtype=wp.int32),
    closed_triangles: wp.array2d(dtype=wp.int32),
    origin: wp.vec3d,
    s: int,
    lane: int,
    lanes: int,
) -> wp.float64:
    """Six times the volume share of lane ``lane`` of ``lanes`` in sub-volume ``s``."""
    acc = wp.float64(0.0)
    for t in range(closed_offsets[s] + lane, closed_offsets[s + 1], lanes):
        pa = closed_point(x, centers, vertex_count, closed_triangles[t, 0]) - origin
        pb = closed_point(x, centers, vertex_count, closed_triangles[t, 1]) - origin
        pc = closed_point(x, centers, vertex_count, closed_triangles[t, 2]) - origin
        acc += wp.dot(pa, wp.cross(pb, pc))
    return acc


@wp.kernel
def subvolume_volume_kernel(
    x: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    vertex_count: int,
    closed_offsets: wp.array(dtype=wp.int32),
    closed_triangles: wp.array2d(dtype=wp.int32),
    subvolume_origin: wp.array(dtype=wp.int32),
    # outputs
    subvolume_volume: wp.array(dtype=wp.float32),
):
    s, lane = wp.tid()
    origin = closed_point(x, centers, vertex_count, subvolume_origin[s])
    acc = subvolume_partial_volume(
        x, centers, vertex_count, closed_offsets, closed_triangles, origin, s, lane, wp.block_dim()
    )
    total = wp.tile_sum(wp.tile(acc))
    if lane == 0:
        subvolume_volume[s] = wp.float32(total[0] / wp.float64(6.0))


# --------------------------------------------------------------------------------------------
# Gradient of a sub-volume's volume with respect to one of its skin vertices. V_s is linear in
# each point (a point occurs once per triangle), and the triple product is invariant under
# cyclic rotation, so for every closed triangle (a, b, c) of s containing vertex i, rotated so
# that i comes first (i, b, c):
#
#   grad_i V_s = 1/6 sum (p_b - o) x (p_c - o)
#
# The host lists these (b, c) "entries" per (vertex, sub-volume) pair; a fan triangle
# (v0, v1, center) contributes to v0 and v1 only (the center is kinematic, no entry). The sum
# over the closed one-ring is independent of o. The PBD weight of the pair is
#
#   w_i = inv_mass_i * weight_scale_i   (weight_scale 0 pins a colliding particle)
#
# With along_normals (else d_i = grad_i V_s, the paper's projection), the correction moves
# the vertex along the surface part of the gradient, d_i (the entries whose two other points
# are skin vertices): the skin inflates or deflates along its normals.
# The fans are a construction that closes the sub-volume at a plane through the bone; along
# their part of the gradient a vertex of the cut loop would slide along the bone, and most
# there: the fan's whole area is shared by the loop's few vertices. d_i is taken about p_i,
# 1/6 sum (p_b - p_i) x (p_c - p_i) over the surface entries (a third of the area-weighted
# normals of its surface triangles: independent of the origin, which the open ring of a loop
# vertex would not be otherwise), so d_i = grad_i V_s off the loops. The pair's share of the
# denominator is w_i grad_i V_s . d_i, so that to first order one projection changes V_s by
# exactly -k (V_s - V_s^rest).
# --------------------------------------------------------------------------------------------
@wp.kernel
def volume_gradient_kernel(
    x: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=wp.float32),
    weight_scale: wp.array(dtype=wp.float32),
    vertex_count: int,
    pair_vertex: wp.array(dtype=wp.int32),
    pair_subvolume: wp.array(dtype=wp.int32),
    pair_entry_offsets: wp.array(dtype=wp.int32),
    entry_points: wp.array2d(dtype=wp.int32),
    subvolume_origin: wp.array(dtype=wp.int32),
    along_normals: int,
    # outputs
    pair_gradient: wp.array(dtype=wp.vec3d),
    pair_direction: wp.array(dtype=wp.vec3d),
    pair_weighted_norm: wp.array(dtype=wp.float64),
):
    p = wp.tid()
    i = pair_vertex[p]
    origin = closed_point(x, centers, vertex_count, subvolume_origin[pair_subvolume[p]])
    pi = closed_point(x, centers, vertex_count, i) - origin
    g = wp.vec3d()
    d = wp.vec3d()
    for e in range(pair_entry_offsets[p], pair_entry_offsets[p + 1]):
        b = entry_points[e, 0]
        c = entry_points[e, 1]
        pb = closed_point(x, centers, vertex_count, b) - origin
        pc = closed_point(x, centers, vertex_count, c) - origin
        g += wp.cross(pb, pc)
        if along_normals != 0 and b < vertex_count and c < vertex_count:
            d += wp.cross(pb - pi, pc - pi)
    g = g / wp.float64(6.0)
    d = d / wp.float64(6.0)
    if along_normals == 0:
        d = g
    w = wp.float64(inv_mass[i] * weight_scale[i])
    pair_gradient[p] = g
    pair_direction[p] = d
    pair_weighted_norm[p] = w * wp.dot(g, d)


# --------------------------------------------------------------------------------------------
# PBD multiplier of the volume constraint C_s(x) = V_s(x) - V_s^rest (section 4.2.2):
#
#   lambda_s = -k (V_s - V_s^rest) / sum_{i in s} w_i grad_i V_s . d_i
#
# with stiffness k in [0, 1]. A sub-volume whose weights are all 0 (every particle pinned)
# has a zero denominator: lambda_s = 0, it is skipped. One thread block per sub-volume; the
# volume and the denominator are block reductions in a fixed order.
# --------------------------------------------------------------------------------------------
@wp.kernel
def volume_lambda_kernel(
    x: wp.array(dtype=wp.vec3),
    centers: wp.array(dtype=wp.vec3),
    vertex_count: int,
    closed_offsets: wp.array(dtype=wp.int32),
    closed_triangles: wp.array2d(dtype=wp.int32),
    subvolume_origin: wp.array(dtype=wp.int32),
    subvolume_pair_offsets: wp.array(dtype=wp.int32),
    pair_weighted_norm: wp.array(dtype=wp.float64),
    rest_volume: wp.array(dtype=wp.float64),
    stiffness: float,
    # outputs
    subvolume_volume: wp.array(dtype=wp.float64),
    subvolume_lambda: wp.array(dtype=wp.float64),
):
    s, lane = wp.tid()
    lanes = wp.block_dim()
    origin = closed_point(x, centers, vertex_count, subvolume_origin[s])
    acc = subvolume_partial_volume(x, centers, vertex_count, closed_offsets, closed_triangles, origin, s, lane, lanes)
    den = wp.float64(0.0)
    for p in range(subvolume_pair_offsets[s] + lane, subvolume_pair_offsets[s + 1], lanes):
        den += pair_weighted_norm[p]
    v6 = wp.tile_sum(wp.tile(acc))
    den_sum = wp.tile_sum(wp.tile(den))
    if lane == 0:
        v = v6[0] / wp.float64(6.0)
        d = den_sum[0]
        subvolume_volume[s] = v
        lam = wp.float64(0.0)
        if d > wp.float64(1.0e-30):
            lam = -wp.float64(stiffness) * (v - rest_volume[s]) / d
        subvolume_lambda[s] = lam


# --------------------------------------------------------------------------------------------
# Position correction of skin vertex i, summed over the sub-volumes it belongs to (a vertex on
# a cut loop belongs to two); every sub-volume uses this iteration's lambda (Jacobi):
#
#   dp_i = w_i sum_{s containing i} lambda_s d_i
#
# A pinned vertex (w_i = 0) is not written at all, so it stays bit-identical.
# --------------------------------------------------------------------------------------------
@wp.kernel
def volume_correction_kernel(
    inv_mass: wp.array(dtype=wp.float32),
    weight_scale: wp.array(dtype=wp.float32),
    vertex_pair_offsets: wp.array(dtype=wp.int32),
    vertex_pairs: wp.array(dtype=wp.int32),
    pair_subvolume: wp.array(dtype=wp.int32),
    pair_direction: wp.array(dtype=wp.vec3d),
    subvolume_lambda: wp.array(dtype=wp.float64),
    use_cap: int,
    cap_targets: wp.array(dtype=wp.vec3),
    cap_radius: wp.array(dtype=wp.float32),
    # outputs
    x: wp.array(dtype=wp.vec3),
    capped: wp.array(dtype=wp.int32),
):
    """One thread per skin vertex. With ``use_cap``, every vertex (pinned ones too) then
    ends within ``cap_radius[i]`` of ``cap_targets[i]`` (the tether's cap, counted in
    ``capped``; the same arithmetic as :func:`warpskin.kernels.constraints.tether_kernel`)."""
    i = wp.tid()
    w = inv_mass[i] * weight_scale[i]
    xi = x[i]
    if w != 0.0:
        dp = wp.vec3d()
        for k in range(vertex_pair_offsets[i], vertex_pair_offsets[i + 1]):
            p = vertex_pairs[k]
            dp += subvolume_lambda[pair_subvolume[p]] * pair_direction[p]
        xi = xi + wp.vec3(wp.float64(w) * dp)
    if use_cap != 0:
        t = cap_targets[i]
        d = xi - t
        r = cap_radius[i]
        dl = wp.length(d)
        if dl > r:
            xi = t + d * (r / dl)
            wp.atomic_add(capped, 0, 1)
    elif w == 0.0:
        return  # a pinned vertex is not written: it stays bit-identical
    x[i] = xi

"""Skinning kernels: linear blend skinning and dual-quaternion skinning, one thread per vertex.

Launch wrappers live in :mod:`warpskin.skinning`; this module holds no Python state.

Inputs are the per-vertex influences as dense ``[V, K]`` arrays (joint index, weight; weight 0
pads) and per-joint data prepared on the host once per frame (joints are few).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Linear blend skinning
#
#   p_i' = sum_k w_ik * M_{j_ik} @ [p_i, 1],   M_j = G_j(t) @ inverse_bind_j
# --------------------------------------------------------------------------------------------
@wp.func
def lbs_point(
    p: wp.vec3,
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    row: int,
    skin_matrices: wp.array(dtype=wp.mat44),
) -> wp.vec3:
    """sum_k w_k M_{j_k} p with the influences of row ``row`` (zero weights skipped)."""
    acc = wp.vec3(0.0)
    for k in range(joint_indices.shape[1]):
        w = joint_weights[row, k]
        if w != 0.0:
            acc += w * wp.transform_point(skin_matrices[joint_indices[row, k]], p)
    return acc


@wp.kernel
def lbs_kernel(
    rest_points: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    # outputs
    points: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    points[i] = lbs_point(rest_points[i], joint_indices, joint_weights, i, skin_matrices)


# --------------------------------------------------------------------------------------------
# Dual-quaternion skinning (Kavan, Collins, Zara, O'Sullivan 2008), with the two-phase scale
# extension of the same paper: the skinning matrix of joint j is split on the host into
#   M_j = [R_j S_j | t_j]   (polar decomposition, R_j a rotation, S_j symmetric),
# S_j is blended linearly and applied first, the rigid parts (R_j, t_j) are blended as unit
# dual quaternions q_j = r_j + eps * d_j with d_j = 0.5 * (t_j, 0) * r_j:
#   b = sum_k sgn_k w_k q_{j_k},  sgn_k = sign(<r_{j_k}, r_pivot>)  (shortest path),
#   p' = R(b0/|b0|) (S p) + t,  t = 2 * vec(b_e * conj(b0)) / |b0|^2.
# --------------------------------------------------------------------------------------------
@wp.func
def quat_dot(a: wp.quat, b: wp.quat):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


@wp.kernel
def dqs_kernel(
    rest_points: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    joint_real: wp.array(dtype=wp.quat),
    joint_dual: wp.array(dtype=wp.quat),
    joint_stretch: wp.array(dtype=wp.mat33),
    # outputs
    points: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    p = rest_points[i]
    # pivot: the influence with the largest weight decides the hemisphere
    kmax = int(0)
    wmax = float(-1.0)
    for k in range(joint_indices.shape[1]):
        if joint_weights[i, k] > wmax:
            wmax = joint_weights[i, k]
            kmax = k
    pivot = joint_real[joint_indices[i, kmax]]

    b0 = wp.quat(0.0, 0.0, 0.0, 0.0)
    be = wp.quat(0.0, 0.0, 0.0, 0.0)
    stretch = wp.mat33(0.0)
    for k in range(joint_indices.shape[1]):
        w = joint_weights[i, k]
        if w != 0.0:
            j = joint_indices[i, k]
            r = joint_real[j]
            s = w
            if quat_dot(r, pivot) < 0.0:
                s = -w
            b0 += s * r
            be += s * joint_dual[j]
            stretch += w * joint_stretch[j]

    n2 = quat_dot(b0, b0)
    inv_n = 1.0 / wp.sqrt(n2)
    r0 = b0 * inv_n
    # translation of the normalised dual quaternion: 2 * vec(be * conj(b0)) / |b0|^2
    # (wp.quat_inverse is the conjugate: it does not divide by |b0|^2)
    te = be * wp.quat_inverse(b0)
    t = (2.0 / n2) * wp.vec3(te[0], te[1], te[2])
    points[i] = wp.quat_rotate(r0, stretch * p) + t

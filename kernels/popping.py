"""Popping-dance kernels (Son & Han 2007, "Dynamic Skinning for Popping Dance"): example-based
skinning (pose space deformation, Lewis et al. 2000) and the skin-vibration step, one thread
per vertex.

Launch wrappers live in :mod:`warpskin.popping`; this module holds no Python state.

Both kernels work on displacements in the rest frame and skin the result with linear blend
skinning. With the blended matrix of vertex i,

    B_i = sum_k w_ik M_{j_ik}        (M_j = G_j(t) @ inverse_bind_j; B_i is affine)
    LBS(p) = B_i [p, 1]              (because LBS is linear in p for fixed weights)

so a rest-frame displacement d moves the skinned vertex by L_i d, L_i the 3x3 part of B_i.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Per-group scalars (activation, clench flag) travel by value as kernel arguments: a step
# uploads nothing and nothing can race with it.
GROUP_CAPACITY = 8
group_vector = wp.types.vector(length=GROUP_CAPACITY, dtype=wp.float32)


@wp.func
def blend_matrix(
    i: int,
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
):
    """B_i = sum_k w_ik M_{j_ik}: the affine map LBS applies to vertex i."""
    b = wp.mat44(0.0)
    for k in range(joint_indices.shape[1]):
        w = joint_weights[i, k]
        if w != 0.0:
            b += w * skin_matrices[joint_indices[i, k]]
    return b


# --------------------------------------------------------------------------------------------
# Pose space deformation (Lewis, Cordner, Fong 2000), evaluated at the current pose.
#
# The host solves the RBF system of every example set once and, per frame, turns the pose into
# cardinal weights w_e(pose) (w_e(pose_k) = delta_ek, sum_e w_e = 1). Per vertex:
#
#   n_i   = sum_{e in normal}  w_e  N_{e,i}                 rest-frame normal displacement
#   D_g,i = sum_{e in group g} w_e  (C_{e,i} - N_{e,i})     rest-frame disparity of group g
#
#   normal_points_i   = B_i [r_i + n_i, 1]                  the example-based normal mesh
#   clenched_points_i = B_i [r_i + n_i + sum_g D_g,i, 1]    every group clenched
#   disparity_max_g   = max_i |L_i D_g,i|                   dist_max of eq. 3, per group
#
# disparity_max is reduced with atomic max (order-independent, hence deterministic); the caller
# zeroes it before the launch.
# --------------------------------------------------------------------------------------------
@wp.kernel
def pose_space_kernel(
    rest_points: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    normal_examples: wp.array2d(dtype=wp.vec3),
    normal_weights: wp.array(dtype=wp.float32),
    clenched_examples: wp.array2d(dtype=wp.vec3),
    clenched_group: wp.array(dtype=wp.int32),
    clenched_weights: wp.array(dtype=wp.float32),
    # outputs
    normal_displacement: wp.array(dtype=wp.vec3),
    disparity: wp.array2d(dtype=wp.vec3),
    disparity_max: wp.array(dtype=wp.float32),
    normal_points: wp.array(dtype=wp.vec3),
    clenched_points: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    b = blend_matrix(i, joint_indices, joint_weights, skin_matrices)

    n = wp.vec3(0.0)
    for e in range(normal_examples.shape[0]):
        n += normal_weights[e] * normal_examples[e, i]

    group_count = disparity.shape[0]
    for g in range(group_count):
        disparity[g, i] = wp.vec3(0.0)
    for e in range(clenched_examples.shape[0]):
        g = clenched_group[e]
        disparity[g, i] = disparity[g, i] + clenched_weights[e] * clenched_examples[e, i]

    total = wp.vec3(0.0)
    for g in range(group_count):
        d = disparity[g, i]
        total += d
        wp.atomic_max(disparity_max, g, wp.length(wp.transform_vector(b, d)))

    p = rest_points[i] + n
    normal_displacement[i] = n
    normal_points[i] = wp.transform_point(b, p)
    clenched_points[i] = wp.transform_point(b, p + total)


# --------------------------------------------------------------------------------------------
# Skin vibration (Son & Han 2007, eqs. 1-4), on the rest-frame popping offset o of each vertex
# (the skinned vertex is B_i [r_i + n_i + o_i, 1]; with the bones still this is the paper's
# world-space update multiplied by the constant L_i, see warpskin.popping).
#
#   goal offset     o*_i = sum_g a_g D_g,i                  (a_g: activation of group g)
#   muscle group    g_i  = argmax_g |L_i D_g,i|             (the group that moves vertex i most)
#   stiffness (3)   alpha_i = (alpha_min - 1) |L_i D_{g_i},i| / disparity_max_{g_i} + 1
#
#   clenching (1-2) u <- (1 - alpha) u + alpha (o* - o) / h ;   o <- o + h u
#   relaxing  (4)   o <- o + beta h (o* - o) ;  u <- 0 ;  o <- o*  when |o* - o| < threshold
#
# In (e, h u) coordinates, e = o - o*, eqs. 1-2 are the linear map
#   [e', hu'] = [[1-alpha, 1-alpha], [-alpha, 1-alpha]] [e, hu]
# with eigenvalues 1 - alpha +- i sqrt(alpha (1 - alpha)), of modulus sqrt(1 - alpha); from
# rest (u = 0) the error is e_n = e_0 (1 - alpha)^(n/2) cos(n theta), tan(theta) = sqrt(alpha /
# (1 - alpha)): it overshoots (changes sign) for alpha < 1 and vanishes in one step for alpha = 1.
# Eq. 4 gives e' = (1 - beta h) e: monotone, no overshoot, for 0 < beta h <= 1.
# --------------------------------------------------------------------------------------------
@wp.kernel
def popping_step_kernel(
    rest_points: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    normal_displacement: wp.array(dtype=wp.vec3),
    disparity: wp.array2d(dtype=wp.vec3),
    disparity_max: wp.array(dtype=wp.float32),
    group_activation: group_vector,
    group_clenching: group_vector,
    alpha_min: float,
    beta: float,
    threshold: float,
    h: float,
    # outputs (offset and velocity are read and written)
    offset: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    goal_points: wp.array(dtype=wp.vec3),
    alpha_out: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    b = blend_matrix(i, joint_indices, joint_weights, skin_matrices)

    goal = wp.vec3(0.0)
    group = int(0)
    dist = float(-1.0)
    for g in range(disparity.shape[0]):
        d = disparity[g, i]
        goal += group_activation[g] * d
        length = wp.length(wp.transform_vector(b, d))
        if length > dist:
            dist = length
            group = g

    alpha = float(1.0)
    dmax = disparity_max[group]
    if dmax > 0.0:
        alpha = (alpha_min - 1.0) * wp.min(dist / dmax, 1.0) + 1.0

    o = offset[i]
    u = velocity[i]
    if group_clenching[group] != 0.0:
        u = (1.0 - alpha) * u + (alpha / h) * (goal - o)
        o = o + h * u
    else:
        o = o + (beta * h) * (goal - o)
        u = wp.vec3(0.0)
        if wp.length(goal - o) < threshold:
            o = goal

    p = rest_points[i] + normal_displacement[i]
    offset[i] = o
    velocity[i] = u
    points[i] = wp.transform_point(b, p + o)
    goal_points[i] = wp.transform_point(b, p + goal)
    alpha_out[i] = alpha

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
# A group's disparity rows: its inbetween shapes (UsdSkel) by weight, then its clenched shape;
# one row where it has no inbetween (see popping_step_kernel).


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
#   D_r,i = sum_{e in row r}   w_e  (C_{e,i} - N_{e,i})     rest-frame disparity of row r
#
#   normal_points_i   = B_i [r_i + n_i, 1]                  the example-based normal mesh
#   clenched_points_i = B_i [r_i + n_i + sum_g D_g,i, 1]    every group clenched (full rows)
#   disparity_max_r   = max_i |L_i D_r,i|                   dist_max of eq. 3, per row
#
# A row is one group's clenched shape (row_full 1) or one of its inbetweens (row_full 0).
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
    row_full: wp.array(dtype=wp.int32),
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
        if row_full[g] != 0:
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
# With inbetweens (popping_step_rows_kernel) the goal is sum_r c_r D_r,i over the rows, c_r a
# tent in its group's activation a: rising from the weight below the row's (lo) to its own (w),
# falling to the one above (hi); the group's clenched row (w = 1) has hi = 2, so it stays 1
# above w, and the goal runs piecewise linearly through the inbetweens. D_g,i above (the group
# and its stiffness) is the group's clenched row.
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
@wp.func
def stiffness(dist: float, dist_max: float, alpha_min: float):
    """Eq. 3: ``(alpha_min - 1) min(dist / dist_max, 1) + 1``, 1 where ``dist_max`` is 0."""
    alpha = float(1.0)
    if dist_max > 0.0:
        alpha = (alpha_min - 1.0) * wp.min(dist / dist_max, 1.0) + 1.0
    return alpha


@wp.func
def vibration_step(o: wp.vec3, u: wp.vec3, goal: wp.vec3, alpha: float, clenching: float, beta: float,
                   threshold: float, h: float):
    """One step of eqs. 1-2 (``clenching`` != 0) or eq. 4 of offset ``o`` [m] and its velocity
    ``u`` [m/s] towards ``goal`` [m]; returns the rows ``(o', u')`` of a 2 x 3 matrix."""
    if clenching != 0.0:
        u = (1.0 - alpha) * u + (alpha / h) * (goal - o)
        o = o + h * u
    else:
        o = o + (beta * h) * (goal - o)
        u = wp.vec3(0.0)
        if wp.length(goal - o) < threshold:
            o = goal
    return wp.matrix_from_rows(o, u)


def _popping_step(rows: bool) -> wp.Kernel:
    """The step kernel (eqs. 1-4 above), for one disparity row per group (``rows`` False: the
    paper's sum, the row arrays unread) or for rows with inbetweens (``rows`` True: each row's
    coefficient a tent in its group's activation, ``row_tent`` its ``(lo, 1 / (w - lo), hi,
    1 / (hi - w))``; the stiffness and the clench flag the group's, from its clenched row)."""

    def step(
        rest_points: wp.array(dtype=wp.vec3),
        joint_indices: wp.array2d(dtype=wp.int32),
        joint_weights: wp.array2d(dtype=wp.float32),
        skin_matrices: wp.array(dtype=wp.mat44),
        normal_displacement: wp.array(dtype=wp.vec3),
        disparity: wp.array2d(dtype=wp.vec3),
        disparity_max: wp.array(dtype=wp.float32),
        row_group: wp.array(dtype=wp.int32),
        row_full: wp.array(dtype=wp.int32),
        row_tent: wp.array(dtype=wp.vec4),
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
        row = int(0)
        dist = float(-1.0)
        for r in range(disparity.shape[0]):
            d = disparity[r, i]
            full = int(1)
            if wp.static(rows):
                a = group_activation[row_group[r]]
                tent = row_tent[r]
                goal += wp.min(wp.clamp((a - tent[0]) * tent[1], 0.0, 1.0),
                               wp.clamp((tent[2] - a) * tent[3], 0.0, 1.0)) * d
                full = row_full[r]
            else:
                goal += group_activation[r] * d
            if full != 0:
                length = wp.length(wp.transform_vector(b, d))
                if length > dist:
                    dist = length
                    row = r

        alpha = stiffness(dist, disparity_max[row], alpha_min)
        group = row
        if wp.static(rows):
            group = row_group[row]
        step = vibration_step(offset[i], velocity[i], goal, alpha, group_clenching[group], beta, threshold, h)
        o = wp.vec3(step[0, 0], step[0, 1], step[0, 2])

        p = rest_points[i] + normal_displacement[i]
        offset[i] = o
        velocity[i] = wp.vec3(step[1, 0], step[1, 1], step[1, 2])
        points[i] = wp.transform_point(b, p + o)
        goal_points[i] = wp.transform_point(b, p + goal)
        alpha_out[i] = alpha

    key = "popping_step_rows_kernel" if rows else "popping_step_kernel"
    step.__name__ = step.__qualname__ = key
    return wp.Kernel(step, key=key)


popping_step_kernel = _popping_step(False)
popping_step_rows_kernel = _popping_step(True)


# --------------------------------------------------------------------------------------------
# The same vibration on a written surface (warpskin.popping.surface): a muscle group's clenched
# disparity is a fixed rest-pose displacement D_g,i of the written point, the activations and
# clench flags of every step are tables uploaded once, and the point's stiffness (eq. 3) is
# measured at rest: alpha_i = (alpha_min - 1) |D_{g_i},i| / max_j |D_{g_i},j| + 1.
# --------------------------------------------------------------------------------------------
@wp.kernel
def surface_vibration_kernel(
    disparity: wp.array2d(dtype=wp.vec3),
    disparity_max: wp.array(dtype=wp.float32),
    activation: wp.array2d(dtype=wp.float32),
    clenching: wp.array2d(dtype=wp.float32),
    step: int,
    alpha_min: float,
    beta: float,
    threshold: float,
    h: float,
    # read and written
    offset: wp.array(dtype=wp.vec3),
    velocity: wp.array(dtype=wp.vec3),
):
    """Step ``step`` (a row of ``activation`` and ``clenching``, ``[S, G]``) of the rest-pose
    popping offset of every point (``disparity [G, N]`` [m], ``disparity_max [G]`` [m])."""
    i = wp.tid()
    goal = wp.vec3(0.0)
    group = int(0)
    dist = float(-1.0)
    for g in range(disparity.shape[0]):
        d = disparity[g, i]
        goal += activation[step, g] * d
        length = wp.length(d)
        if length > dist:
            dist = length
            group = g
    alpha = stiffness(dist, disparity_max[group], alpha_min)
    out = vibration_step(offset[i], velocity[i], goal, alpha, clenching[step, group], beta, threshold, h)
    offset[i] = wp.vec3(out[0, 0], out[0, 1], out[0, 2])
    velocity[i] = wp.vec3(out[1, 0], out[1, 1], out[1, 2])


@wp.kernel
def offset_clearance_kernel(
    mesh: wp.uint64,
    base: wp.array(dtype=wp.vec3),
    offset: wp.array(dtype=wp.vec3),
    start: float,
    margin: float,
    # output
    scale: wp.array(dtype=wp.float32),
):
    """How much of ``offset[i]`` [m] point ``base[i]`` [m] (on ``mesh``) may take without
    crossing the surface: ``clamp((gap / 2 - margin) / |offset|, 0, 1)``, ``gap`` the distance
    along the offset to the first surface hit (the ray starts ``start`` [m] along it, past the
    point's own faces), 1 where nothing is hit within twice the offset plus ``margin``. Half the
    gap, so two surfaces pushed towards each other both stop short of the middle."""
    i = wp.tid()
    d = offset[i]
    length = wp.length(d)
    s = float(1.0)
    if length > 0.0:
        u = d / length
        q = wp.mesh_query_ray(mesh, base[i] + u * start, u, 2.0 * (length + margin))
        if q.result:
            s = wp.clamp((0.5 * (q.t + start) - margin) / length, 0.0, 1.0)
    scale[i] = s

"""Region shape matching with oriented particles (Mueller and Chentanez 2011), the elastic
model of Deul & Bender 2013 (section 4.2.1), with both ways of computing region sums:

* **direct gather**: one thread per region loops over its members;
* **fast summation** (section 4.3): one thread per path and layer computes prefix sums along the
  path (in float64: a float32 scan of the moment sums loses 1e-2 relative), then one thread per
  region adds prefix-sum differences over its runs plus its sibling terms.

Region ``r`` (one per particle) with members ``j``, masses ``m_j``, rest offsets
``o_j = x0_j - c0_r`` (``c0_r`` the rest centre of mass), oriented-particle moments
``mu_j = m_j rho_j^2 / 5`` (spherical particle ellipsoids of radius ``rho_j``, rest orientation
the identity) and orientations ``R_j = R(q_j)``; the per-particle matrices ``mu_j R_j`` are
computed once per orientation change (by the goal-blend kernel), not once per region member:

    c_r = sum_j m_j x_j / M_r
    A_r = sum_j ( mu_j R_j + m_j (x_j - c_r) o_j^T )
        = sum_j ( mu_j R_j + m_j x_j x0_j^T ) - M_r c_r c0_r^T            (fast-summation form)
    R_r = rotational part of A_r (warm-started from q_r)
    goal of member j in region r:  g_rj = R_r o_j + c_r

Particle ``i`` then moves toward the mean of its goals over the regions containing it:
``x_i += s_i (mean_r g_ri - x_i)`` (s_i the stiffness of its layer), and its orientation is
``R_i`` (region ``i`` is particle ``i``'s region).
"""

import warp as wp

from .constraints import project_coupling, project_joint_lower_bound
from .rotation import extract_rotation

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Direct gather: sums relative to the region's own particle (keeps float32 precise)
#   A_r = sum_j mu_j R_j + sum_j m_j (x_j - x_r) o_j^T     (sum_j m_j o_j = 0 by definition)
# --------------------------------------------------------------------------------------------
@wp.kernel
def region_fit_gather_kernel(
    x: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.quat),
    particle_mass: wp.array(dtype=wp.float32),
    moment_matrix: wp.array(dtype=wp.mat33),
    region_offsets: wp.array(dtype=wp.int32),
    region_members: wp.array(dtype=wp.int32),
    region_rest_offsets: wp.array(dtype=wp.vec3),
    region_mass: wp.array(dtype=wp.float32),
    rotation_iterations: int,
    # outputs
    region_com: wp.array(dtype=wp.vec3),
    region_q: wp.array(dtype=wp.quat),
):
    r = wp.tid()
    start = region_offsets[r]
    end = region_offsets[r + 1]
    xr = x[r]
    s1 = wp.vec3(0.0)
    a = wp.mat33(0.0)
    for e in range(start, end):
        j = region_members[e]
        mj = particle_mass[j]
        d = x[j] - xr
        s1 += mj * d
        a += mj * wp.outer(d, region_rest_offsets[e]) + moment_matrix[j]
    region_com[r] = xr + s1 / region_mass[r]
    region_q[r] = extract_rotation(a, q[r], rotation_iterations)


# --------------------------------------------------------------------------------------------
# Fast summation, part 1: prefix sums along each path of each layer (one thread per path and
# layer), in float64:
#   P1[k V + p] = sum_{p' <= p on the path} m x            (vec3d)
#   P2[k V + p] = sum_{p' <= p on the path} (m x x0^T + mu R)   (mat33d)
# with p the position in the concatenated path order.
# --------------------------------------------------------------------------------------------
@wp.func
def to_vec3d(v: wp.vec3) -> wp.vec3d:
    return wp.vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))


@wp.func
def to_mat33d(m: wp.mat33) -> wp.mat33d:
    return wp.mat33d(
        wp.float64(m[0, 0]), wp.float64(m[0, 1]), wp.float64(m[0, 2]),
        wp.float64(m[1, 0]), wp.float64(m[1, 1]), wp.float64(m[1, 2]),
        wp.float64(m[2, 0]), wp.float64(m[2, 1]), wp.float64(m[2, 2]),
    )


@wp.func
def to_mat33(m: wp.mat33d) -> wp.mat33:
    return wp.mat33(
        wp.float32(m[0, 0]), wp.float32(m[0, 1]), wp.float32(m[0, 2]),
        wp.float32(m[1, 0]), wp.float32(m[1, 1]), wp.float32(m[1, 2]),
        wp.float32(m[2, 0]), wp.float32(m[2, 1]), wp.float32(m[2, 2]),
    )


@wp.func
def particle_terms(
    j: int,
    x: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=wp.float32),
    moment_matrix: wp.array(dtype=wp.mat33),
    s1: wp.vec3d,
    s2: wp.mat33d,
):
    m = wp.float64(particle_mass[j])
    xj = to_vec3d(x[j])
    s1 = s1 + m * xj
    s2 = s2 + m * wp.outer(xj, to_vec3d(x0[j])) + to_mat33d(moment_matrix[j])
    return s1, s2


@wp.kernel
def path_scan_kernel(
    x: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=wp.float32),
    moment_matrix: wp.array(dtype=wp.mat33),
    path_order: wp.array(dtype=wp.int32),
    path_offsets: wp.array(dtype=wp.int32),
    vertex_count: int,
    path_count: int,
    # outputs
    prefix_mx: wp.array(dtype=wp.vec3d),
    prefix_mxx: wp.array(dtype=wp.mat33d),
):
    tid = wp.tid()
    layer = tid / path_count
    path = tid - layer * path_count
    base = layer * vertex_count
    s1 = wp.vec3d()
    s2 = wp.mat33d()
    for pos in range(path_offsets[path], path_offsets[path + 1]):
        j = base + path_order[pos]
        s1, s2 = particle_terms(j, x, x0, particle_mass, moment_matrix, s1, s2)
        prefix_mx[base + pos] = s1
        prefix_mxx[base + pos] = s2


# --------------------------------------------------------------------------------------------
# Fast summation, part 2: region sums from run differences plus sibling terms, then the fit:
#   S1 = sum over runs (P1[end] - P1[start - 1]) + siblings,  likewise S2,
#   c = S1 / M,   A = S2 - S1 c0^T  (= S2 - M c c0^T; c0 in float64 from the float32 rest data)
# --------------------------------------------------------------------------------------------
@wp.kernel
def region_fit_runs_kernel(
    x: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.quat),
    x0: wp.array(dtype=wp.vec3),
    particle_mass: wp.array(dtype=wp.float32),
    moment_matrix: wp.array(dtype=wp.mat33),
    prefix_mx: wp.array(dtype=wp.vec3d),
    prefix_mxx: wp.array(dtype=wp.mat33d),
    position_is_path_start: wp.array(dtype=wp.int32),
    run_offsets: wp.array(dtype=wp.int32),
    run_start: wp.array(dtype=wp.int32),
    run_end: wp.array(dtype=wp.int32),
    region_offsets: wp.array(dtype=wp.int32),
    region_members: wp.array(dtype=wp.int32),
    region_sibling_count: wp.array(dtype=wp.int32),
    region_mass: wp.array(dtype=wp.float32),
    region_rest_com: wp.array(dtype=wp.vec3d),
    vertex_count: int,
    rotation_iterations: int,
    # outputs
    region_com: wp.array(dtype=wp.vec3),
    region_q: wp.array(dtype=wp.quat),
):
    r = wp.tid()
    layer = r / vertex_count
    i = r - layer * vertex_count
    base = layer * vertex_count
    s1 = wp.vec3d()
    s2 = wp.mat33d()
    for k in range(run_offsets[i], run_offsets[i + 1]):
        a = run_start[k]
        b = run_end[k]
        s1 = s1 + prefix_mx[base + b]
        s2 = s2 + prefix_mxx[base + b]
        if position_is_path_start[a] == 0:
            s1 = s1 - prefix_mx[base + a - 1]
            s2 = s2 - prefix_mxx[base + a - 1]
    end = region_offsets[r + 1]
    for e in range(end - region_sibling_count[r], end):
        s1, s2 = particle_terms(region_members[e], x, x0, particle_mass, moment_matrix, s1, s2)
    m = wp.float64(region_mass[r])
    c = s1 / m
    a_mat = s2 - wp.outer(s1, region_rest_com[r])  # = S2 - M c c0^T, without M's float32 rounding
    region_com[r] = wp.vec3(wp.float32(c[0]), wp.float32(c[1]), wp.float32(c[2]))
    region_q[r] = extract_rotation(to_mat33(a_mat), q[r], rotation_iterations)


# --------------------------------------------------------------------------------------------
# Goal blend and the position constraints of the elasticity loop, one thread per particle
# (Algorithm 1 lines 7-8): shape matching, then the kinematic coupling of the bone layer
# (zero-length distance constraint to the LBS target) and the unilateral joint constraints.
# --------------------------------------------------------------------------------------------
@wp.kernel
def blend_and_constrain_kernel(
    region_com: wp.array(dtype=wp.vec3),
    region_q: wp.array(dtype=wp.quat),
    region_rest_offsets: wp.array(dtype=wp.vec3),
    particle_region_offsets: wp.array(dtype=wp.int32),
    particle_regions: wp.array(dtype=wp.int32),
    particle_region_slots: wp.array(dtype=wp.int32),
    particle_stiffness: wp.array(dtype=wp.float32),
    coupling_first: int,
    coupling_targets: wp.array(dtype=wp.vec3),
    coupling_stiffness: float,
    joint_offsets: wp.array(dtype=wp.int32),
    joint_ids: wp.array(dtype=wp.int32),
    joint_rest_distance: wp.array(dtype=wp.float32),
    joint_centres: wp.array(dtype=wp.vec3),
    particle_moment: wp.array(dtype=wp.float32),
    iteration: int,
    # outputs
    x: wp.array(dtype=wp.vec3),
    moment_matrix: wp.array(dtype=wp.mat33),
    correction: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    # the oriented-particle moment of particle i for the next fit: mu_i R(q_i), q_i = region i's rotation
    moment_matrix[i] = particle_moment[i] * wp.quat_to_matrix(region_q[i])
    start = particle_region_offsets[i]
    end = particle_region_offsets[i + 1]
    g = wp.vec3(0.0)
    for e in range(start, end):
        r = particle_regions[e]
        g += wp.quat_rotate(region_q[r], region_rest_offsets[particle_region_slots[e]]) + region_com[r]
    x_before = x[i]
    xi = x_before
    if end > start:
        g = g / float(end - start)
        xi = xi + particle_stiffness[i] * (g - xi)
    if i >= coupling_first:
        xi = project_coupling(xi, coupling_targets[i - coupling_first], coupling_stiffness)
    for c in range(joint_offsets[i], joint_offsets[i + 1]):
        xi = project_joint_lower_bound(xi, joint_centres[joint_ids[c]], joint_rest_distance[c])
    x[i] = xi
    # the particle's squared position correction in this iteration [m^2], row ``iteration`` of
    # the flat ``[iterations x particles]`` buffer (a plain store: the iteration's residual, the
    # largest, is reduced only when read; all particles would contend for one address with an
    # atomic maximum on a GPU). The buffer is one-dimensional: a two-dimensional array argument
    # takes every thread of a CPU kernel off Warp's contiguous fast path
    correction[iteration * x.shape[0] + i] = wp.length_sq(xi - x_before)


@wp.kernel
def largest_correction_kernel(
    correction: wp.array(dtype=wp.float32),
    count: int,
    # output
    residual: wp.array(dtype=wp.float32),
):
    """Each elasticity iteration's residual [m]: the largest of its particles' corrections, from
    their squares (one thread per iteration)."""
    k = wp.tid()
    r = float(0.0)
    for i in range(k * count, (k + 1) * count):
        r = wp.max(r, correction[i])
    residual[k] = wp.sqrt(r)


@wp.kernel
def moment_matrices_kernel(
    q: wp.array(dtype=wp.quat),
    particle_moment: wp.array(dtype=wp.float32),
    # outputs
    moment_matrix: wp.array(dtype=wp.mat33),
):
    """Oriented-particle moment matrices ``mu_i R(q_i)`` (rest orientation: identity)."""
    i = wp.tid()
    moment_matrix[i] = particle_moment[i] * wp.quat_to_matrix(q[i])


# --------------------------------------------------------------------------------------------
# Rest-shape drive (muscle activation in the layered model): the region rest offsets are
#   o_e(a) = o_e + sum_g a_g d_ge
# where d_ge is entry e's offset change when group g clenches fully (precomputed on the host
# from the clenched examples: the muscle layer's rest positions move, the regions' rest centres
# follow), and a_g in [0, 1] the group's activation.
# --------------------------------------------------------------------------------------------
@wp.kernel
def rest_offsets_drive_kernel(
    base_offsets: wp.array(dtype=wp.vec3),
    delta_offsets: wp.array2d(dtype=wp.vec3),
    activation: wp.array(dtype=wp.float32),
    # outputs
    region_rest_offsets: wp.array(dtype=wp.vec3),
):
    e = wp.tid()
    o = base_offsets[e]
    for g in range(delta_offsets.shape[0]):
        o += activation[g] * delta_offsets[g, e]
    region_rest_offsets[e] = o

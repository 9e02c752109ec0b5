"""Rotation extraction: the rotational part of a 3x3 matrix, warm-started.

Mueller, Bender, Chentanez, Macklin 2016, "A robust method to extract the rotational part of
deformations": starting from a quaternion ``q`` (last step's rotation), repeat

    R     = R(q)
    omega = sum_c (R_c x A_c) / (|sum_c R_c . A_c| + 1e-9 s)     (c: columns)
    q     = quat(axis = omega / |omega|, angle = |omega|) * q

with ``s`` the largest entry of ``|A|`` (the paper's 1e-9 is for ``A`` of order one; a moment
matrix is mass x length^2, so a character of 18 cm in its file has entries near 1e-9 and an
absolute 1e-9 halved every rotation update: the regions lagged their motion), which converges to the rotation R maximising tr(R^T A), i.e. the polar factor of A (for
det A > 0), and stays well defined for flat and even singular A (it then keeps the warm start
in the degenerate directions). One or two iterations per solver iteration suffice when warm
started; ``svd3`` serves as the cold fallback.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def extract_rotation(a: wp.mat33, q: wp.quat, iterations: int) -> wp.quat:
    scale = wp.max(wp.max(wp.abs(a[0, 0]), wp.abs(a[0, 1])), wp.abs(a[0, 2]))
    scale = wp.max(scale, wp.max(wp.max(wp.abs(a[1, 0]), wp.abs(a[1, 1])), wp.abs(a[1, 2])))
    scale = wp.max(scale, wp.max(wp.max(wp.abs(a[2, 0]), wp.abs(a[2, 1])), wp.abs(a[2, 2])))
    eps = 1.0e-9 * scale + 1.0e-30
    for _ in range(iterations):
        r = wp.quat_to_matrix(q)
        r0 = wp.vec3(r[0, 0], r[1, 0], r[2, 0])
        r1 = wp.vec3(r[0, 1], r[1, 1], r[2, 1])
        r2 = wp.vec3(r[0, 2], r[1, 2], r[2, 2])
        a0 = wp.vec3(a[0, 0], a[1, 0], a[2, 0])
        a1 = wp.vec3(a[0, 1], a[1, 1], a[2, 1])
        a2 = wp.vec3(a[0, 2], a[1, 2], a[2, 2])
        denom = wp.abs(wp.dot(r0, a0) + wp.dot(r1, a1) + wp.dot(r2, a2)) + eps
        omega = (wp.cross(r0, a0) + wp.cross(r1, a1) + wp.cross(r2, a2)) / denom
        w = wp.length(omega)
        if w < 1.0e-9:
            break
        q = wp.normalize(wp.quat_from_axis_angle(omega / w, w) * q)
    return q


@wp.func
def polar_rotation_svd(a: wp.mat33) -> wp.quat:
    """Cold fallback: R = U V^T from ``svd3`` (A normalised first: in float32 ``svd3`` returns
    wrong rotations once the entries fall below about 3e-6), with det(R) = +1."""
    scale = wp.max(wp.max(wp.abs(a[0, 0]), wp.abs(a[0, 1])), wp.abs(a[0, 2]))
    scale = wp.max(scale, wp.max(wp.max(wp.abs(a[1, 0]), wp.abs(a[1, 1])), wp.abs(a[1, 2])))
    scale = wp.max(scale, wp.max(wp.max(wp.abs(a[2, 0]), wp.abs(a[2, 1])), wp.abs(a[2, 2])))
    if scale < 1.0e-30:
        return wp.quat_identity()
    u = wp.mat33()
    s = wp.vec3()
    v = wp.mat33()
    wp.svd3(a / scale, u, s, v)
    r = u * wp.transpose(v)
    if wp.determinant(r) < 0.0:
        u = wp.mat33(u[0, 0], u[0, 1], -u[0, 2], u[1, 0], u[1, 1], -u[1, 2], u[2, 0], u[2, 1], -u[2, 2])
        r = u * wp.transpose(v)
    return wp.quat_from_matrix(r)


@wp.kernel
def extract_rotations_kernel(
    a: wp.array(dtype=wp.mat33),
    q_start: wp.array(dtype=wp.quat),
    iterations: int,
    cold_start: int,
    # outputs
    q_out: wp.array(dtype=wp.quat),
):
    """Rotations of many matrices (tests and one-off use); ``cold_start`` != 0 starts from the
    ``svd3`` polar factor, otherwise from ``q_start``."""
    i = wp.tid()
    q = q_start[i]
    if cold_start != 0:
        q = polar_rotation_svd(a[i])
    q_out[i] = extract_rotation(a[i], q, iterations)

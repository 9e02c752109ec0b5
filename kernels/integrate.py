"""Time integration of the multi-layer skin (Algorithm 1 of Deul & Bender 2013, lines 1-4 and
14-18) and the kinematic drivers of a step (joint centres).

Launch wrappers live in :mod:`warpskin.solver`.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# --------------------------------------------------------------------------------------------
# Prediction (symplectic Euler) and orientation prediction of the oriented particles
#
#   v* = v + dt a,     x* = x + dt v*        (a: each particle's gravity in its file's unit)
#   q* = normalize(q + dt/2 (omega, 0) q)      (Mueller and Chentanez 2011)
# --------------------------------------------------------------------------------------------
@wp.kernel
def predict_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    q: wp.array(dtype=wp.quat),
    omega: wp.array(dtype=wp.vec3),
    gravity: wp.array(dtype=wp.vec3),
    dt: float,
    # outputs
    x_pred: wp.array(dtype=wp.vec3),
    v_pred: wp.array(dtype=wp.vec3),
    q_pred: wp.array(dtype=wp.quat),
):
    i = wp.tid()
    vi = v[i] + dt * gravity[i]
    v_pred[i] = vi
    x_pred[i] = x[i] + dt * vi
    w = omega[i]
    qi = q[i]
    dq = wp.quat(w[0], w[1], w[2], 0.0) * qi
    q_pred[i] = wp.normalize(qi + (0.5 * dt) * dq)


# --------------------------------------------------------------------------------------------
# Velocity update, damping (lines 14-17)
#
#   v = (x_new - x_old) / dt * exp(-damping dt)
#   omega = 2 vec(q_new q_old^-1) / dt        (shortest arc: flip when the scalar part < 0)
# --------------------------------------------------------------------------------------------
@wp.kernel
def update_velocity_kernel(
    x_old: wp.array(dtype=wp.vec3),
    x_new: wp.array(dtype=wp.vec3),
    q_old: wp.array(dtype=wp.quat),
    q_new: wp.array(dtype=wp.quat),
    inv_dt: float,
    damping_factor: float,
    # outputs
    v: wp.array(dtype=wp.vec3),
    omega: wp.array(dtype=wp.vec3),
):
    i = wp.tid()
    v[i] = (x_new[i] - x_old[i]) * (inv_dt * damping_factor)
    dq = q_new[i] * wp.quat_inverse(q_old[i])
    s = 2.0 * inv_dt * damping_factor
    if dq[3] < 0.0:
        s = -s
    omega[i] = wp.vec3(dq[0], dq[1], dq[2]) * s


# --------------------------------------------------------------------------------------------
# Kinematic joint centres: c_j = (G_j inverse_bind_j) [c_j^rest, 1]
# --------------------------------------------------------------------------------------------
@wp.kernel
def joint_centres_kernel(
    skin_matrices: wp.array(dtype=wp.mat44),
    joint_rest: wp.array(dtype=wp.vec3),
    # outputs
    centres: wp.array(dtype=wp.vec3),
):
    j = wp.tid()
    centres[j] = wp.transform_point(skin_matrices[j], joint_rest[j])

"""Position-based distance constraints of the multi-layer model (Deul & Bender 2013, section
4.2.2 and 4.4), as ``wp.func``s fused into the per-particle kernel of the elasticity loop.

A PBD projection moves particle i by ``dp_i = -w_i C / sum_j w_j |grad_j C|^2 grad_i C``.
Against a kinematic point (infinite mass, w = 0) the whole correction goes to the particle.
"""

import warp as wp

from .skinning import lbs_point

wp.set_module_options({"enable_backward": False})


@wp.func
def project_coupling(x: wp.vec3, target: wp.vec3, stiffness: float) -> wp.vec3:
    """Kinematic coupling: zero-length distance constraint C = |x - t| to the LBS target t
    (kinematic). The projection is x <- x + k (t - x); k = 1 pins the particle."""
    return x + stiffness * (target - x)


@wp.func
def project_joint_lower_bound(x: wp.vec3, centre: wp.vec3, rest_distance: float) -> wp.vec3:
    """Joint constraint: unilateral lower bound C = |x - c| - d0 >= 0 to the kinematic joint
    centre c; violated constraints put the particle back on the sphere of radius d0."""
    d = x - centre
    length = wp.length(d)
    if length < rest_distance and length > 1.0e-12:
        return centre + d * (rest_distance / length)
    return x


# --------------------------------------------------------------------------------------------
# Tether (a maximum-distance constraint to the animation, as PhysX's cloth "max distance"):
#   t_p = sum_k w_ik M_{j_ik} x0_p          (LBS of particle p's rest position, i = p mod V)
#   |x_p - t_p| <= r_i,  x_p <- t_p + (x_p - t_p) r_i / |x_p - t_p|   where violated.
# Applied once per step after the constraint loops and before the velocity update, so the
# velocity of a clamped particle is the clamped motion (no energy is added).
# --------------------------------------------------------------------------------------------
@wp.kernel
def tether_kernel(
    particle_q0: wp.array(dtype=wp.vec3),
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=wp.float32),
    skin_matrices: wp.array(dtype=wp.mat44),
    tether_radius: wp.array(dtype=wp.float32),
    vertex_count: int,
    reach: wp.array(dtype=wp.float32),
    # outputs
    x: wp.array(dtype=wp.vec3),
    clamped: wp.array(dtype=wp.int32),
    targets: wp.array(dtype=wp.vec3),
):
    """One thread per particle: ``x[p]`` no farther than ``tether_radius[i]`` [m] (``i`` its
    vertex) from its LBS target, a skin particle farther by its contact reach ``reach[i]`` [m]
    (``reach`` of length 1: none has one); ``clamped`` counts the particles moved. The skin's targets (``p < vertex_count``) are written
    to ``targets`` for the caps in the volume loop
    (:func:`warpskin.kernels.volume.volume_correction_kernel`)."""
    p = wp.tid()
    i = p % vertex_count
    t = lbs_point(particle_q0[p], joint_indices, joint_weights, i, skin_matrices)
    if p < vertex_count:
        targets[p] = t
    d = x[p] - t
    r = tether_radius[i]
    if p < vertex_count and reach.shape[0] > 1:
        r = r + reach[i]
    dl = wp.length(d)
    if dl > r:
        x[p] = t + d * (r / dl)
        wp.atomic_add(clamped, 0, 1)


@wp.kernel
def contact_reach_kernel(
    tether_cap: wp.array(dtype=wp.float32),
    contact_cap: wp.array(dtype=wp.float32),
    colliding: wp.array(dtype=wp.int32),
    shrink: float,
    written: wp.array(dtype=wp.int32),
    reach_in: wp.array(dtype=wp.float32),
    # outputs
    reach_out: wp.array(dtype=wp.float32),
    cap: wp.array(dtype=wp.float32),
    written_cap: wp.array(dtype=wp.float32),
):
    """One thread per skin vertex: its contact reach [m] after a step, ``e = contact_cap -
    tether_cap`` (at least 0) where the skin particle is in contact (``colliding``, ``[4V]``;
    of length 1: none is), else its reach before (``reach_in``) less ``shrink`` x ``e``, at
    least 0; the step's cap ``tether_cap + reach`` and ``written_cap`` the same where
    ``written`` is 1 (the characters with a written mesh's volume), else unbounded."""
    i = wp.tid()
    base = tether_cap[i]
    full = wp.max(contact_cap[i] - base, 0.0)
    e = wp.max(reach_in[i] - shrink * full, 0.0)
    if colliding.shape[0] > 1:
        if colliding[i] != 0:
            e = full
    reach_out[i] = e
    cap[i] = base + e
    written_cap[i] = wp.where(written[i] != 0, base + e, 1.0e30)


@wp.kernel
def split_weights_kernel(
    weight_scale: wp.array(dtype=wp.float32),
    loaded: wp.array(dtype=wp.int32),
    added: int,
    # outputs
    split: wp.array(dtype=wp.float32),
):
    """``weight_scale`` on the loaded skin vertices (``loaded`` 1; ``added`` 0) or on the
    vertices a refinement added (``loaded`` 0; ``added`` 1), 0 on the others; one thread per
    skin vertex."""
    i = wp.tid()
    keep = (loaded[i] == 0) == (added != 0)
    split[i] = wp.where(keep, weight_scale[i], 0.0)

"""Position-based distance constraints of the multi-layer model (Deul & Bender 2013, section
4.2.2 and 4.4), as ``wp.func``s fused into the per-particle kernel of the elasticity loop.

A PBD projection moves particle i by ``dp_i = -w_i C / sum_j w_j |grad_j C|^2 grad_i C``.
Against a kinematic point (infinite mass, w = 0) the whole correction goes to the particle.
"""

import warp as wp

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

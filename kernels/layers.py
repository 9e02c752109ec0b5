"""Preprocessing queries of the multi-layer model: where a projection segment leaves the body.

A skin vertex's projection segment runs from the vertex to the nearest point of its bone's
center line. Where a bone's center line lies outside the surface locally (thin parts, bones
placed near the skin), the segment passes out of the body before it reaches the bone; the
inner layers must stay short of that exit.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def segment_exit_kernel(
    mesh: wp.uint64,
    origin: wp.array(dtype=wp.vec3),
    direction: wp.array(dtype=wp.vec3),
    max_distance: wp.array(dtype=wp.float32),
    start_offset: float,
    # outputs
    exit_distance: wp.array(dtype=wp.float32),
    starts_inside: wp.array(dtype=wp.int32),
):
    """Distance [m] from ``origin[i]`` along the unit ``direction[i]`` to the first surface
    hit after ``start_offset`` (the ray starts on the surface, at its own vertex), or -1 when
    the surface is not hit within ``max_distance[i]``; and whether the ray enters the body
    there (the point ``start_offset`` along it is inside, by the winding number), 1 or 0."""
    i = wp.tid()
    d = direction[i]
    o = origin[i] + d * start_offset
    q = wp.mesh_query_ray(mesh, o, d, max_distance[i])
    if q.result:
        exit_distance[i] = q.t + start_offset
    else:
        exit_distance[i] = -1.0
    p = wp.mesh_query_point_sign_winding_number(mesh, o, 1.0e30, 2.0, 0.5)
    starts_inside[i] = 0
    if p.result and p.sign < 0.0:
        starts_inside[i] = 1

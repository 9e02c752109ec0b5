"""Rest-pose queries of a character's pieces (:mod:`warpskin.preprocess.pieces`): which pieces
lie over which (a garment over the body, a shoe over a foot)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def first_hit_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    directions: wp.array(dtype=wp.vec3),
    start: float,
    max_dist: float,
    # outputs
    dist: wp.array(dtype=wp.float32),
    face: wp.array(dtype=wp.int32),
):
    """The first face of ``mesh`` (either side) that the ray from ``points[i]`` along the unit
    ``directions[i]`` meets, starting ``start`` along it (past the point's own faces), within
    ``max_dist``: ``dist[i]`` from the point and ``face[i]``, or ``max_dist`` and -1."""
    i = wp.tid()
    d = directions[i]
    q = wp.mesh_query_ray(mesh, points[i] + start * d, d, max_dist)
    dist[i] = max_dist
    face[i] = -1
    if q.result:
        dist[i] = q.t + start
        face[i] = q.face


@wp.kernel
def near_or_inside_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    near: float,
    far: float,
    # output
    flag: wp.array(dtype=wp.int32),
):
    """``flag[i]``: 1 where ``points[i]`` lies inside the closed ``mesh`` (winding number above
    1/2) or within ``near`` of its surface, else 0 (``far``: a bound on every distance)."""
    i = wp.tid()
    p = points[i]
    flag[i] = 0
    q = wp.mesh_query_point_sign_winding_number(mesh, p, far, 2.0, 0.5)
    if q.result:
        if q.sign < 0.0:
            flag[i] = 1
        elif wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v)) < near:
            flag[i] = 1

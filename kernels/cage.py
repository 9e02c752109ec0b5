"""Inside/outside field of a character's meshes for its simulation cage (issue: any character
in): the signed distance to the surface on a regular grid, its sign from the generalised winding
number (Jacobson et al. 2013; Warp's fast dipole approximation, Barill et al. 2018), so that
holes, open cuffs and overlapping pieces still have a well-defined inside."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def winding_distance_field_kernel(
    mesh: wp.uint64,
    lower: wp.vec3,
    spacing: float,
    max_dist: float,
    # outputs
    field: wp.array3d(dtype=wp.float32),
    nearest_face: wp.array3d(dtype=wp.int32),
):
    """``field[i, j, k]``: distance from grid node ``lower + (i, j, k) spacing`` to the nearest
    surface point, negative where the winding number is above 1/2 (inside); ``max_dist`` where no
    face is that close (outside, far away). ``nearest_face``: the face of that point (-1: none)."""
    i, j, k = wp.tid()
    p = lower + wp.vec3(float(i), float(j), float(k)) * spacing
    q = wp.mesh_query_point_sign_winding_number(mesh, p, max_dist, 2.0, 0.5)
    value = max_dist
    face = int(-1)
    if q.result:
        closest = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        value = q.sign * wp.min(wp.length(p - closest), max_dist)
        face = q.face
    field[i, j, k] = value
    nearest_face[i, j, k] = face


@wp.kernel
def inside_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    # output
    inside: wp.array(dtype=wp.int32),
):
    """``inside[i]``: 1 where ``points[i]`` is inside the closed ``mesh`` (winding number above
    1/2), else 0."""
    i = wp.tid()
    q = wp.mesh_query_point_sign_winding_number(mesh, points[i], max_dist, 2.0, 0.5)
    inside[i] = 0
    if q.result and q.sign < 0.0:
        inside[i] = 1


@wp.kernel
def closest_face_kernel(
    mesh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    max_dist: float,
    # outputs
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
):
    """The closest cage triangle to each point, with the barycentric weights of its three
    vertices (Warp's (u, v) are the weights of the first two)."""
    i = wp.tid()
    q = wp.mesh_query_point_no_sign(mesh, points[i], max_dist)
    if q.result:
        face[i] = q.face
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)
    else:
        face[i] = -1

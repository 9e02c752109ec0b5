"""Embedding of a render mesh in a simulated cage (issue: any character in): every render
point is bound to its closest cage triangle by barycentric coordinates and an offset in the
local frame there (the interpolated vertex normal, and the triangle's first edge made
tangent), so that the rest pose is reproduced exactly and a rigid motion of the cage moves it
rigidly. The normal at a cage vertex is either its surface normal (area-weighted over its faces,
one launch per frame before the points: a cage on its own) or, for a cage simulated with layers,
the direction from its inner-layer particle to it (read with the points, so one launch per frame:
the tissue's own direction, which turns with the tissue and costs no gather). Evaluated every
frame on the device without atomics. (Gathering the three surface normals per point cost 5.4x
the LBS of CesiumMan's render mesh, each vertex normal computed for every point near it; the
normal pass and the points 2.6x; the tissue direction about 1.1x.)"""

import warp as wp

from .rotation import polar_rotation_svd

wp.set_module_options({"enable_backward": False})


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


@wp.func
def vertex_normal(x: wp.array(dtype=wp.vec3), offsets: wp.array(dtype=wp.int32), wedges: wp.array(dtype=wp.vec2i),
                  v: int) -> wp.vec3:
    """Area-weighted unit normal of vertex ``v``: over its faces ``(v, b, c)``, counter-clockwise,
    each given by its other two vertices (CSR ``offsets``/``wedges``), ``sum (x_b - x_v) x (x_c - x_v)``."""
    n = wp.vec3(0.0)
    xv = x[v]
    for k in range(offsets[v], offsets[v + 1]):
        w = wedges[k]
        n += wp.cross(x[w[0]] - xv, x[w[1]] - xv)
    return wp.normalize(n)


@wp.kernel
def used_vertex_normals_kernel(
    x: wp.array(dtype=wp.vec3),
    vertex_wedge_offsets: wp.array(dtype=wp.int32),
    vertex_wedges: wp.array(dtype=wp.vec2i),
    used: wp.array(dtype=wp.int32),
    # output
    normals: wp.array(dtype=wp.vec3),
):
    """Unit normals of the cage vertices ``used`` (the others are left as they are)."""
    k = wp.tid()
    v = used[k]
    normals[v] = vertex_normal(x, vertex_wedge_offsets, vertex_wedges, v)


@wp.func
def corner_normal(x: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), inner_offset: int, v: int) -> wp.vec3:
    """The normal at cage vertex ``v``: the direction from its inner particle ``x[v + inner_offset]``
    to it (``inner_offset > 0``, not normalised: the tissue depth varies smoothly), else
    ``normals[v]``."""
    if inner_offset > 0:
        return x[v] - x[v + inner_offset]
    return normals[v]


@wp.func
def surface_point(x: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), inner_offset: int, tri: wp.vec3i,
                  w: wp.vec3):
    """The barycentric point ``w`` of the triangle with vertices ``tri`` and the local frame
    there, as columns: tangent (the first edge, made orthogonal to the normal), bitangent,
    normal (the normalised interpolation of the corners' normals, :func:`corner_normal`)."""
    xa = x[tri[0]]
    xb = x[tri[1]]
    xc = x[tri[2]]
    p = w[0] * xa + w[1] * xb + w[2] * xc
    n = wp.normalize(w[0] * corner_normal(x, normals, inner_offset, tri[0])
                     + w[1] * corner_normal(x, normals, inner_offset, tri[1])
                     + w[2] * corner_normal(x, normals, inner_offset, tri[2]))
    e = xb - xa
    t = wp.normalize(e - wp.dot(e, n) * n)
    return p, wp.matrix_from_cols(t, wp.cross(n, t), n)


@wp.kernel
def embed_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    inner_offset: int,
    point_triangle: wp.array(dtype=wp.vec3i),
    bary: wp.array(dtype=wp.vec3),
    offset: wp.array(dtype=wp.vec3),
    point_group: wp.array(dtype=wp.int32),
    group_centre: wp.array(dtype=wp.vec3),
    group_rotation: wp.array(dtype=wp.mat33),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Render point ``i`` on the cage ``x``: its barycentric point plus its offset in the local
    frame there (``point_triangle[i]``: the vertices of its cage triangle); a point of a rigid
    piece (``point_group[i] >= 0``, when there are pieces) is its piece's rigid motion of its
    rest offset from the region's rest centre (:func:`rigid_regions_kernel`)."""
    i = wp.tid()
    if point_group.shape[0] > 0:
        g = point_group[i]
        if g >= 0:
            out[i] = group_centre[g] + group_rotation[g] * offset[i]
            return
    p, frame = surface_point(x, normals, inner_offset, point_triangle[i], bary[i])
    out[i] = p + frame * offset[i]


@wp.kernel
def rigid_regions_kernel(
    x: wp.array(dtype=wp.vec3),
    region_offsets: wp.array(dtype=wp.int32),
    region_members: wp.array(dtype=wp.int32),
    region_weights: wp.array(dtype=wp.float32),
    region_rest: wp.array(dtype=wp.vec3),
    # outputs
    centre: wp.array(dtype=wp.vec3),
    rotation: wp.array(dtype=wp.mat33),
):
    """The rigid motion of each rigid piece's cage region (one thread per piece): the weighted
    centre of its members ``x[region_members]`` and the rotation of the best rigid fit (the polar
    factor of ``sum_k w_k (x_k - c) r_k^T``, ``r_k`` the member's rest offset from the rest
    centre; shape matching, Mueller et al. 2005)."""
    g = wp.tid()
    start = region_offsets[g]
    end = region_offsets[g + 1]
    c = wp.vec3(0.0)
    w_sum = float(0.0)
    for k in range(start, end):
        c += region_weights[k] * x[region_members[k]]
        w_sum += region_weights[k]
    c = c / w_sum
    a = wp.mat33(0.0)
    for k in range(start, end):
        a += region_weights[k] * wp.outer(x[region_members[k]] - c, region_rest[k])
    centre[g] = c
    rotation[g] = wp.quat_to_matrix(polar_rotation_svd(a))


@wp.kernel
def rest_offsets_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    inner_offset: int,
    point_triangle: wp.array(dtype=wp.vec3i),
    bary: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    # output
    offset: wp.array(dtype=wp.vec3),
):
    """The offsets that reproduce ``points`` on the rest cage ``x``: the inverse of
    :func:`embed_kernel` (the frame is orthonormal, so its transpose)."""
    i = wp.tid()
    p, frame = surface_point(x, normals, inner_offset, point_triangle[i], bary[i])
    offset[i] = wp.transpose(frame) * (points[i] - p)

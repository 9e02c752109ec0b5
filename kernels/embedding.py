"""Embedding of a render mesh in a simulated cage (issue: any character in): every render
point is bound to its closest cage triangle by barycentric coordinates and an offset in the
local frame there (the interpolated vertex normal, and the triangle's first edge made
tangent), so that the rest pose is reproduced exactly and a rigid motion of the cage moves it
rigidly. Evaluated every frame on the device in two launches without atomics: the unit normals of
the cage vertices that some point's triangle uses (each gathered over its faces), then every
point from its triangle's three. (Gathering the three normals per point cost 5.4x the LBS of
CesiumMan's render mesh, each vertex normal computed for every point near it.)"""

import warp as wp

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
def surface_point(x: wp.array(dtype=wp.vec3), normals: wp.array(dtype=wp.vec3), tri: wp.vec3i, w: wp.vec3):
    """The barycentric point ``w`` of the triangle with vertices ``tri`` and the local frame
    there, as columns: tangent (the first edge, made orthogonal to the normal), bitangent,
    normal (the normalised interpolation of the vertex ``normals``)."""
    xa = x[tri[0]]
    xb = x[tri[1]]
    xc = x[tri[2]]
    p = w[0] * xa + w[1] * xb + w[2] * xc
    n = wp.normalize(w[0] * normals[tri[0]] + w[1] * normals[tri[1]] + w[2] * normals[tri[2]])
    e = xb - xa
    t = wp.normalize(e - wp.dot(e, n) * n)
    return p, wp.matrix_from_cols(t, wp.cross(n, t), n)


@wp.kernel
def embed_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    point_triangle: wp.array(dtype=wp.vec3i),
    bary: wp.array(dtype=wp.vec3),
    offset: wp.array(dtype=wp.vec3),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Render point ``i`` on the cage ``x``: its barycentric point plus its offset in the local
    frame there (``point_triangle[i]``: the vertices of its cage triangle)."""
    i = wp.tid()
    p, frame = surface_point(x, normals, point_triangle[i], bary[i])
    out[i] = p + frame * offset[i]


@wp.kernel
def rest_offsets_kernel(
    x: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    point_triangle: wp.array(dtype=wp.vec3i),
    bary: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    # output
    offset: wp.array(dtype=wp.vec3),
):
    """The offsets that reproduce ``points`` on the rest cage ``x``: the inverse of
    :func:`embed_kernel` (the frame is orthonormal, so its transpose)."""
    i = wp.tid()
    p, frame = surface_point(x, normals, point_triangle[i], bary[i])
    offset[i] = wp.transpose(frame) * (points[i] - p)

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
def vertex_normal(x: wp.array(dtype=wp.vec3), triangles: wp.array2d(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                  faces: wp.array(dtype=wp.int32), v: int) -> wp.vec3:
    """Area-weighted unit normal of vertex ``v``, gathered over its faces (CSR ``offsets``/``faces``)."""
    n = wp.vec3(0.0)
    for k in range(offsets[v], offsets[v + 1]):
        f = faces[k]
        a, b, c = triangles[f, 0], triangles[f, 1], triangles[f, 2]
        n += wp.cross(x[b] - x[a], x[c] - x[a])
    return wp.normalize(n)


@wp.kernel
def used_vertex_normals_kernel(
    x: wp.array(dtype=wp.vec3),
    triangles: wp.array2d(dtype=wp.int32),
    vertex_face_offsets: wp.array(dtype=wp.int32),
    vertex_faces: wp.array(dtype=wp.int32),
    used: wp.array(dtype=wp.int32),
    # output
    normals: wp.array(dtype=wp.vec3),
):
    """Unit normals of the cage vertices ``used`` (the others are left as they are)."""
    k = wp.tid()
    v = used[k]
    normals[v] = vertex_normal(x, triangles, vertex_face_offsets, vertex_faces, v)


@wp.func
def surface_point(x: wp.array(dtype=wp.vec3), triangles: wp.array2d(dtype=wp.int32), normals: wp.array(dtype=wp.vec3),
                  f: int, w: wp.vec3):
    """The barycentric point ``w`` of triangle ``f`` and the local frame there, as columns:
    tangent (the first edge, made orthogonal to the normal), bitangent, normal (the normalised
    interpolation of the vertex ``normals``)."""
    a, b, c = triangles[f, 0], triangles[f, 1], triangles[f, 2]
    p = w[0] * x[a] + w[1] * x[b] + w[2] * x[c]
    n = wp.normalize(w[0] * normals[a] + w[1] * normals[b] + w[2] * normals[c])
    e = x[b] - x[a]
    t = wp.normalize(e - wp.dot(e, n) * n)
    return p, wp.matrix_from_cols(t, wp.cross(n, t), n)


@wp.kernel
def embed_kernel(
    x: wp.array(dtype=wp.vec3),
    triangles: wp.array2d(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    offset: wp.array(dtype=wp.vec3),
    # output
    out: wp.array(dtype=wp.vec3),
):
    """Render point ``i`` on the cage ``x``: its barycentric point plus its offset in the local
    frame there."""
    i = wp.tid()
    p, frame = surface_point(x, triangles, normals, face[i], bary[i])
    out[i] = p + frame * offset[i]


@wp.kernel
def rest_offsets_kernel(
    x: wp.array(dtype=wp.vec3),
    triangles: wp.array2d(dtype=wp.int32),
    normals: wp.array(dtype=wp.vec3),
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
    points: wp.array(dtype=wp.vec3),
    # output
    offset: wp.array(dtype=wp.vec3),
):
    """The offsets that reproduce ``points`` on the rest cage ``x``: the inverse of
    :func:`embed_kernel` (the frame is orthonormal, so its transpose)."""
    i = wp.tid()
    p, frame = surface_point(x, triangles, normals, face[i], bary[i])
    offset[i] = wp.transpose(frame) * (points[i] - p)

"""Mesh helpers on the host (NumPy), each written once: welding the copies a file splits at seams,
the closedness and manifoldness of a triangle mesh, polygons fanned into triangles, triangle
normals and areas, vertex normals and mixed Voronoi areas. Indices are int64; positions float64
unless a function says it keeps the dtype it is given."""

from __future__ import annotations

import numpy as np

__all__ = ["weld_by_position", "mesh_edge_report", "triangulate_faces", "polygon_triangle_count", "vertex_normals",
           "face_normals", "summed_face_normals", "triangle_areas", "surface_area", "mixed_voronoi_areas"]


def weld_by_position(points: np.ndarray, tolerance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices that share a position (glTF splits them at UV/normal seams).

    Args:
        points: File vertex positions, ``[N, 3]``.
        tolerance: Positions closer than this (per axis, after quantisation) merge. 0 merges
            exactly equal positions only.

    Returns:
        ``(first, weld_map)``: ``first[k]`` is the file index of the first vertex of welded
        vertex ``k`` (``[V]``, in order of first appearance); ``weld_map[i]`` is the welded index
        of file vertex ``i`` (``[N]``).
    """
    p = np.asarray(points, dtype=np.float64)
    key = np.round(p / tolerance).astype(np.int64) if tolerance > 0.0 else p
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    # renumber by first appearance so a mesh without seams keeps its vertex order
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order], rank[inverse]


def mesh_edge_report(triangles: np.ndarray, vertex_count: int) -> dict:
    """Closedness and manifoldness of a triangle mesh.

    Returns a dict with ``boundary_edges`` ``[E, 2]`` (edges used by one triangle),
    ``nonmanifold_edges`` (used by more than two), ``inconsistent_edges`` (two triangles that
    traverse the edge in the same direction: flipped winding), ``nonmanifold_vertices`` (whose
    triangle fan is not a single disc), ``unused_vertices``, ``closed`` and ``manifold``.
    """
    tri = np.asarray(triangles, dtype=np.int64)
    directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    uniq, counts = np.unique(undirected, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    nonmanifold = uniq[counts > 2]
    # winding: for an edge shared by two triangles, the directed copies must be opposite
    dir_uniq, dir_counts = np.unique(directed, axis=0, return_counts=True)
    inconsistent = np.unique(np.sort(dir_uniq[dir_counts > 1], axis=1), axis=0)
    used = np.zeros(vertex_count, dtype=bool)
    used[tri.ravel()] = True
    # vertex manifoldness: around an interior vertex, #incident edges == #incident triangles
    # (a single closed fan); a boundary vertex has one more edge than triangles.
    edge_deg = np.bincount(uniq.ravel(), minlength=vertex_count)
    tri_deg = np.bincount(tri.ravel(), minlength=vertex_count)
    bnd_deg = np.bincount(boundary.ravel(), minlength=vertex_count)
    expected = tri_deg + bnd_deg // 2
    bad_vertices = np.nonzero(used & (edge_deg != expected))[0]
    return {
        "boundary_edges": boundary,
        "nonmanifold_edges": nonmanifold,
        "inconsistent_edges": inconsistent,
        "nonmanifold_vertices": bad_vertices,
        "unused_vertices": np.nonzero(~used)[0],
        "closed": boundary.shape[0] == 0 and nonmanifold.shape[0] == 0,
        "manifold": nonmanifold.shape[0] == 0 and inconsistent.shape[0] == 0 and bad_vertices.size == 0,
    }


def polygon_triangle_count(counts: np.ndarray, holes: np.ndarray) -> int:
    """How many triangles :func:`triangulate_faces` makes of polygons with ``counts`` vertices
    (``[F]``), skipping the faces ``holes`` (``[H]``) and those with fewer than three vertices."""
    keep = counts >= 3
    if holes.size:
        ok = holes[(holes >= 0) & (holes < counts.size)]
        keep[ok] = False
    return int((counts[keep] - 2).sum())


def triangulate_faces(
    counts: np.ndarray, indices: np.ndarray, holes: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Fan-triangulate polygons ``(v0, v1, ..., vn-1)`` into ``(v0, vk, vk+1)``.

    Args:
        counts: ``faceVertexCounts``, ``[F]``.
        indices: ``faceVertexIndices``, ``[sum(counts)]``.
        holes: ``holeIndices`` (faces to skip), ``[H]``.

    Returns:
        ``(triangles [T, 3], skipped)``: the triangles, in the faces' own winding, and the
        indices of faces with fewer than three vertices (dropped).
    """
    counts = np.asarray(counts, dtype=np.int64).ravel()
    indices = np.asarray(indices, dtype=np.int64).ravel()
    offsets = np.concatenate([[0], np.cumsum(counts)[:-1]]) if counts.size else counts
    keep = counts >= 3
    skipped = np.nonzero(~keep)[0]
    if holes is not None and np.size(holes):
        h = np.asarray(holes, dtype=np.int64).ravel()
        keep[h[(h >= 0) & (h < counts.size)]] = False
    faces = np.nonzero(keep)[0]
    per_face = counts[faces] - 2
    total = int(per_face.sum())
    if total == 0:
        return np.zeros((0, 3), dtype=np.int64), skipped
    face_of_tri = np.repeat(faces, per_face)
    first_tri = np.repeat(np.cumsum(per_face) - per_face, per_face)
    k = np.arange(total) - first_tri
    base = offsets[face_of_tri]
    tri = np.stack([indices[base], indices[base + k + 1], indices[base + k + 2]], axis=1)
    return tri, skipped


def face_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[T, 3]``: ``(p1 - p0) x (p2 - p0)`` of every triangle of ``points`` ``[N, 3]`` and
    ``triangles`` ``[T, 3]``, its unit normal times twice its area (outward for outward-wound
    triangles), in the dtype ``points`` has."""
    p = np.asarray(points)
    t = np.asarray(triangles)
    return np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])


def summed_face_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[N, 3]``: every point's sum of its triangles' :func:`face_normals` (area-weighted, not
    normalised; zero for a point on no triangle), in the dtype ``points`` has."""
    p = np.asarray(points)
    t = np.asarray(triangles)
    fn = face_normals(p, t)
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    return n


def triangle_areas(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[T]``: the area of every triangle [m^2], in the dtype ``points`` has."""
    return 0.5 * np.linalg.norm(face_normals(points, triangles), axis=1)


def surface_area(points: np.ndarray, triangles: np.ndarray) -> float:
    """The area [m^2] of the triangle mesh ``points`` ``[N, 3]``, ``triangles`` ``[T, 3]`` (in
    float64)."""
    return float(triangle_areas(np.asarray(points, dtype=np.float64), np.asarray(triangles, dtype=np.int64)).sum())


def vertex_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals ``[N, 3]`` of ``points`` ``[N, 3]`` and ``triangles``
    ``[T, 3]`` (outward for outward-wound triangles; zero for a point on no triangle), in float64."""
    n = summed_face_normals(np.asarray(points, dtype=np.float64), np.asarray(triangles, dtype=np.int64))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.maximum(length, 1e-300), 0.0)


def mixed_voronoi_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Mixed Voronoi area of every vertex [m^2], ``[V]`` (Meyer, Desbrun, Schroeder and Barr
    2003: the Voronoi region inside a non-obtuse triangle; half of an obtuse triangle for its
    obtuse corner, a quarter for the others); they sum to the surface area."""
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    p = v[t]  # [T, 3 corners, 3]
    # edge opposite each corner c: from corner c+1 to c+2
    e = np.stack([p[:, 2] - p[:, 1], p[:, 0] - p[:, 2], p[:, 1] - p[:, 0]], axis=1)
    len2 = np.einsum("tci,tci->tc", e, e)
    cross = np.cross(e[:, 1], e[:, 2])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    # cosine of the angle at corner c: between -e[c+2] and e[c+1]
    dots = np.stack(
        [
            -np.einsum("ti,ti->t", e[:, 2], e[:, 1]),
            -np.einsum("ti,ti->t", e[:, 0], e[:, 2]),
            -np.einsum("ti,ti->t", e[:, 1], e[:, 0]),
        ],
        axis=1,
    )
    safe = np.where(area > 0, 2.0 * area, 1.0)
    cot = dots / safe[:, None]  # cot(angle) = cos / sin = dot / |cross|
    # Voronoi corner area of corner c: (|e_{c+1}|^2 cot(c+1) + |e_{c+2}|^2 cot(c+2)) / 8, where e_k
    # is the edge opposite corner k (the edges incident to c are e_{c+1} and e_{c+2}).
    voronoi = np.empty_like(len2)
    for c in range(3):
        c1, c2 = (c + 1) % 3, (c + 2) % 3
        voronoi[:, c] = (len2[:, c1] * cot[:, c1] + len2[:, c2] * cot[:, c2]) / 8.0
    obtuse_corner = dots < 0.0
    obtuse = obtuse_corner.any(axis=1)
    corner = np.where(
        obtuse[:, None],
        np.where(obtuse_corner, area[:, None] / 2.0, area[:, None] / 4.0),
        voronoi,
    )
    out = np.zeros(v.shape[0])
    np.add.at(out, t.ravel(), corner.ravel())
    return out

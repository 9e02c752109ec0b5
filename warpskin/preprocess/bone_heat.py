"""Automatic skinning weights by bone heat.

Baran, I. and Popović, J. 2007. "Automatic Rigging and Animation of 3D Characters". ACM
Transactions on Graphics 26(3), SIGGRAPH 2007, section 4 ("Skin Attachment"). The weight of bone
``j`` is the equilibrium temperature of the surface when bone ``j`` is kept at temperature 1 and
the others at 0, heat reaching each vertex only from its nearest *visible* bone::

    (-Δ + H) w_j = H p_j

``Δ`` is the discrete surface Laplacian, ``H`` is diagonal with ``H_ii = c / d_i^2`` (``d_i`` the
distance [m] from vertex ``i`` to its nearest visible bone, ``c = 1`` in the paper) and
``p_j(i) = 1`` where bone ``j`` is that nearest visible bone (split evenly between tied bones),
0 elsewhere. A vertex sees a bone when the segment from the vertex to the nearest point of the
bone does not cross the mesh; a vertex that sees no bone gets ``H_ii = 0`` (it only receives
heat by diffusion), as in Pinocchio.

Discretisation used here (documented choices):

* ``Δ = M^-1 L`` with ``L`` the cotangent Laplacian (:func:`cotangent_laplacian`, off-diagonal
  ``0.5 (cot a + cot b)``, rows summing to zero, negative semi-definite) and ``M`` the lumped
  mixed-Voronoi vertex areas of Meyer et al. 2003 (:func:`vertex_areas`). Multiplying by ``M``
  gives the symmetric positive definite system ``(-L + M H) w_j = M H p_j``, factorised once
  (sparse LU) and solved for all bones at once.
* Visibility is tested with a vectorised segment/triangle test (Möller-Trumbore) behind a
  uniform-grid broad phase (:func:`segments_cross_mesh`). trimesh's pure-Python
  ``RayMeshIntersector`` needs the optional ``rtree`` package and queries one ray at a time, so
  it is not used. Hits on the triangles around the vertex the segment starts from, and hits
  within a small inset from its ends, are ignored.
* Only the ``visibility_candidates`` nearest bones of each vertex (plus bones tied with the
  nearest visible one) are tested for visibility; a vertex that sees none of them is treated as
  seeing no bone.
* A connected part of the mesh in which no vertex sees a bone (which would leave the system
  singular there) falls back to the nearest bone by distance, visibility ignored. Vertices in no
  (non-degenerate) triangle take their nearest bone's weight directly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from ..mesh import mixed_voronoi_areas
from ..rig import Rig, RigError
from .bones import bone_segments, closest_point_on_segments

__all__ = [
    "cotangent_laplacian",
    "vertex_areas",
    "segments_cross_mesh",
    "nearest_visible_bones",
    "bone_heat_weights",
    "with_bone_heat_weights",
]

# Relative tolerance under which two bone distances count as a tie (split the heat source).
TIE_TOLERANCE = 1e-6

# Visibility grid cell size, in mean edge lengths (larger cells test more triangles per ray,
# smaller ones walk more cells).
CELL_FACTOR = 1.0


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


def _check_mesh(
    vertices: np.ndarray, triangles: np.ndarray, where: str = "bone heat"
) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles)
    if v.ndim != 2 or v.shape[1] != 3:
        raise RigError(f"{where}: vertices must have shape [V, 3], got {v.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise RigError(f"{where}: triangles must have shape [T, 3], got {t.shape}")
    if t.shape[0] == 0:
        raise RigError(f"{where}: the mesh has no triangles")
    if not np.issubdtype(t.dtype, np.integer):
        raise RigError(f"{where}: triangles must hold integer vertex indices, got {t.dtype}")
    t = t.astype(np.int64)
    if t.min() < 0 or t.max() >= v.shape[0]:
        raise RigError(f"{where}: triangles index vertices outside [0, {v.shape[0] - 1}]")
    bad = np.nonzero(~np.all(np.isfinite(v), axis=1))[0]
    if bad.size:
        head = ", ".join(str(int(i)) for i in bad[:8])
        raise RigError(f"{where}: vertices {head}{' ...' if bad.size > 8 else ''} have NaN or inf positions")
    return v, t


def _scale(v: np.ndarray) -> float:
    """Bounding-box diagonal [m] (at least a tiny positive number)."""
    return max(float(np.linalg.norm(v.max(0) - v.min(0))), 1e-30) if v.size else 1.0


def _triangle_geometry(v: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per triangle: the cotangents of the angles at its three corners ``[T, 3]``, its area
    ``[T]`` [m^2] and a non-degenerate mask ``[T]``."""
    p = v[t]  # [T, 3 corners, 3]
    # edge opposite corner k runs between the other two corners; angle at k between them
    a = p[:, [1, 2, 0]] - p  # corner k -> next corner
    b = p[:, [2, 0, 1]] - p  # corner k -> previous corner
    cross = np.linalg.norm(np.cross(a, b), axis=2)  # [T, 3]; each equals twice the area
    area2 = cross[:, 0]
    scale = _scale(v)
    repeated = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
    ok = ~repeated & (area2 > 1e-12 * scale * scale)
    dot = np.einsum("tki,tki->tk", a, b)
    cot = np.where(ok[:, None], dot / np.where(cross > 0, cross, 1.0), 0.0)
    return cot, np.where(ok, 0.5 * area2, 0.0), ok


# --------------------------------------------------------------------------------------------
# Laplacian and areas
# --------------------------------------------------------------------------------------------


def cotangent_laplacian(vertices: np.ndarray, triangles: np.ndarray) -> sp.csr_matrix:
    """Cotangent Laplacian of a triangle mesh.

    ``L[i, j] = 0.5 (cot a_ij + cot b_ij)`` for an edge ``(i, j)`` with opposite angles
    ``a_ij, b_ij`` (one angle on a boundary edge), ``L[i, i] = -sum_j L[i, j]``. ``L`` is
    symmetric, its rows sum to zero and it is negative semi-definite (it is minus the P1 finite
    element stiffness matrix, so ``-f^T L f`` is the Dirichlet energy of ``f``). ``L f`` is the
    integrated (not area-averaged) Laplacian; divide by :func:`vertex_areas` for pointwise values.
    Degenerate (zero-area) triangles contribute nothing.

    Args:
        vertices: Positions [m], ``[V, 3]``.
        triangles: Vertex indices, ``[T, 3]``.

    Returns:
        ``[V, V]`` sparse matrix (dimensionless).

    Raises:
        RigError: NaN/inf positions, indices out of range, or no triangles.
    """
    v, t = _check_mesh(vertices, triangles, "cotangent Laplacian")
    cot, _, _ = _triangle_geometry(v, t)
    n = v.shape[0]
    # the angle at corner k is opposite the edge (k+1, k+2)
    i = t[:, [1, 2, 0]].ravel()
    j = t[:, [2, 0, 1]].ravel()
    w = 0.5 * cot.ravel()
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([j, i, i, j])
    vals = np.concatenate([w, w, -w, -w])
    return sp.coo_matrix((vals, (rows, cols)), shape=(n, n)).tocsr()


def vertex_areas(vertices: np.ndarray, triangles: np.ndarray, *, kind: str = "mixed") -> np.ndarray:
    """Lumped area [m^2] of each vertex (the diagonal of the mass matrix ``M``).

    Args:
        vertices: Positions [m], ``[V, 3]``.
        triangles: Vertex indices, ``[T, 3]``.
        kind: ``"mixed"``: the mixed Voronoi areas of Meyer, Desbrun, Schröder and Barr 2003
            (Voronoi region inside non-obtuse triangles; half / a quarter of an obtuse
            triangle for its obtuse / other corners), always positive. ``"barycentric"``: a
            third of each incident triangle. Both sum to the surface area.

    Returns:
        ``[V]`` areas; zero for a vertex in no non-degenerate triangle.
    """
    v, t = _check_mesh(vertices, triangles, "vertex areas")
    _, area, ok = _triangle_geometry(v, t)
    n = v.shape[0]
    if kind == "mixed":  # the one implementation (:func:`warpskin.mesh.mixed_voronoi_areas`)
        return mixed_voronoi_areas(v, t[ok])
    if kind != "barycentric":
        raise ValueError(f"kind must be 'mixed' or 'barycentric', got {kind!r}")
    per = np.where(ok[:, None], np.repeat(area[:, None] / 3.0, 3, axis=1), 0.0)
    return np.bincount(t.ravel(), weights=per.ravel(), minlength=n)


# --------------------------------------------------------------------------------------------
# Visibility: segments against the mesh
# --------------------------------------------------------------------------------------------


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ``counts[k]`` items per group: the group of each item and its index in the group."""
    counts = np.asarray(counts, dtype=np.int64)
    group = np.repeat(np.arange(counts.size), counts)
    starts = np.cumsum(counts) - counts
    local = np.arange(group.size, dtype=np.int64) - starts[group]
    return group, local


class _TriangleGrid:
    """Uniform grid over the triangles' bounding boxes (dilated by ``margin``), as a sorted
    cell-key -> triangle-list table."""

    def __init__(self, v: np.ndarray, t: np.ndarray, cell: float, margin: float) -> None:
        self.cell = cell
        p = v[t]
        lo = p.min(axis=(0, 1)) - cell
        hi = p.max(axis=(0, 1)) + cell
        self.lo = lo
        self.dims = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64) + 1, 1)
        cmin = np.floor((p.min(axis=1) - margin - lo) / cell).astype(np.int64)
        cmax = np.floor((p.max(axis=1) + margin - lo) / cell).astype(np.int64)
        cmin = np.clip(cmin, 0, self.dims - 1)
        cmax = np.clip(cmax, 0, self.dims - 1)
        ext = cmax - cmin + 1  # [T, 3]
        tri, local = _expand(ext.prod(axis=1))
        ex = ext[tri]
        ix = local % ex[:, 0]
        iy = (local // ex[:, 0]) % ex[:, 1]
        iz = local // (ex[:, 0] * ex[:, 1])
        c = cmin[tri] + np.stack([ix, iy, iz], axis=1)
        key = self._key(c)
        order = np.argsort(key, kind="stable")
        key, self.tri = key[order], tri[order]
        self.keys, self.starts, self.counts = np.unique(key, return_index=True, return_counts=True)

    def _key(self, c: np.ndarray) -> np.ndarray:
        d = self.dims
        return (c[:, 2] * d[1] + c[:, 1]) * d[0] + c[:, 0]

    def lookup(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start into :attr:`tri` and triangle count of the cell of each point ``[N, 3]``."""
        c = np.floor((points - self.lo) / self.cell).astype(np.int64)
        inside = np.all((c >= 0) & (c < self.dims), axis=1)
        key = self._key(np.clip(c, 0, self.dims - 1))
        k = np.clip(np.searchsorted(self.keys, key), 0, self.keys.size - 1)
        hit = inside & (self.keys[k] == key)
        return np.where(hit, self.starts[k], 0), np.where(hit, self.counts[k], 0)


def segments_cross_mesh(
    vertices: np.ndarray,
    triangles: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    *,
    start_vertex: np.ndarray | None = None,
    inset: float | None = None,
    max_pairs: int = 4_000_000,
    _grid: _TriangleGrid | None = None,
) -> np.ndarray:
    """Whether each segment ``start[k] -> end[k]`` crosses a triangle of the mesh.

    Broad phase: a uniform grid (cell of :data:`CELL_FACTOR` mean edge lengths) holding each triangle
    in the cells its bounding box, dilated by a quarter cell, overlaps; each segment is sampled
    every half cell, so every point of it lies within a quarter cell of a sample and every
    triangle it meets is listed in a sampled cell. Narrow phase: Möller-Trumbore on the candidate
    pairs, with a slightly widened (conservative) barycentric test so a segment through a
    shared edge or vertex is not missed.

    Args:
        vertices: Positions [m], ``[V, 3]``.
        triangles: Vertex indices, ``[T, 3]``.
        start: Segment starts [m], ``[S, 3]``.
        end: Segment ends [m], ``[S, 3]``.
        start_vertex: Mesh vertex each segment starts from, ``[S]`` (or -1); the triangles around
            it are ignored (the segment touches them only at its start).
        inset: Hits closer than this [m] to either end of a segment are ignored (the segment is
            shot from slightly inside its start). Default ``1e-6`` of the mesh size.
        max_pairs: Candidate (segment, triangle) pairs tested at once (memory bound).

    Returns:
        ``[S]`` bool, True where the segment crosses the mesh.
    """
    v, t = _check_mesh(vertices, triangles, "segment test")
    a = np.asarray(start, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(end, dtype=np.float64).reshape(-1, 3)
    s_count = a.shape[0]
    if b.shape[0] != s_count:
        raise ValueError(f"{s_count} segment starts but {b.shape[0]} ends")
    sv = np.full(s_count, -1, dtype=np.int64) if start_vertex is None else np.asarray(start_vertex, np.int64)
    scale = _scale(v)
    inset = 1e-6 * scale if inset is None else float(inset)
    grid = _grid if _grid is not None else _make_grid(v, t)
    out = np.zeros(s_count, dtype=bool)
    if s_count == 0:
        return out
    d = b - a
    length = np.linalg.norm(d, axis=1)
    # samples every half cell along each segment
    spacing = 0.5 * grid.cell
    n_samp = np.ceil(length / spacing).astype(np.int64) + 1
    seg, k = _expand(n_samp)
    u = k / np.maximum(n_samp[seg] - 1, 1)
    pts = a[seg] + u[:, None] * d[seg]
    first, count = grid.lookup(pts)
    # drop repeats of one cell along a segment (consecutive samples in the same cell)
    keep = count > 0
    same = np.zeros_like(keep)
    same[1:] = (seg[1:] == seg[:-1]) & (first[1:] == first[:-1])
    keep &= ~same
    seg, first, count = seg[keep], first[keep], count[keep]
    if seg.size == 0:
        return out
    tri_pts = v[t]
    e1_all = tri_pts[:, 1] - tri_pts[:, 0]
    e2_all = tri_pts[:, 2] - tri_pts[:, 0]
    plane_n = np.cross(e1_all, e2_all)
    n_len = np.linalg.norm(plane_n, axis=1)
    plane_c = np.einsum("ij,ij->i", plane_n, tri_pts[:, 0])
    # test in chunks of at most max_pairs candidate (segment, triangle) pairs
    csum = np.cumsum(count)
    lo, done = 0, 0
    while lo < seg.size:
        hi = max(int(np.searchsorted(csum, done + max_pairs, side="right")), lo + 1)
        pseg, off = _expand(count[lo:hi])
        tri = grid.tri[first[lo:hi][pseg] + off]
        sidx = seg[lo:hi][pseg]
        done, lo = int(csum[hi - 1]), hi
        # plane-side test first (cheap), then the start-vertex fan, then Möller-Trumbore
        nrm, off_c = plane_n[tri], plane_c[tri]
        s0 = np.einsum("ij,ij->i", nrm, a[sidx]) - off_c
        s1 = np.einsum("ij,ij->i", nrm, b[sidx]) - off_c
        m = (s0 * s1 <= 0.0) & ~out[sidx]
        tri, sidx = tri[m], sidx[m]
        m = ~np.any(t[tri] == sv[sidx][:, None], axis=1)
        tri, sidx = tri[m], sidx[m]
        if tri.size == 0:
            continue
        hit = _segment_triangle_hits(
            a[sidx], d[sidx], length[sidx], tri_pts[tri, 0], e1_all[tri], e2_all[tri], n_len[tri], inset
        )
        out[sidx[hit]] = True
    return out


def _make_grid(v: np.ndarray, t: np.ndarray) -> _TriangleGrid:
    p = v[t]
    edge = np.linalg.norm(p[:, [1, 2, 0]] - p, axis=2)
    scale = _scale(v)
    cell = max(CELL_FACTOR * float(edge.mean()), scale / 2000.0, 1e-12)
    return _TriangleGrid(v, t, cell, margin=0.25 * cell * (1.0 + 1e-6))


def _segment_triangle_hits(
    a: np.ndarray,
    d: np.ndarray,
    length: np.ndarray,
    p0: np.ndarray,
    e1: np.ndarray,
    e2: np.ndarray,
    n_len: np.ndarray,
    inset: float,
) -> np.ndarray:
    """Möller-Trumbore for pairs: segment ``a + s d`` (s in [0, 1]) against triangle ``p0, e1,
    e2``; True where they meet away from the segment's ends (by more than ``inset`` [m])."""
    pvec = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pvec)
    par = np.abs(det) <= 1e-12 * length * n_len  # segment parallel to the triangle's plane
    inv = 1.0 / np.where(par, 1.0, det)
    tvec = a - p0
    u = np.einsum("ij,ij->i", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    w = np.einsum("ij,ij->i", d, qvec) * inv
    s = np.einsum("ij,ij->i", e2, qvec) * inv
    eps = 1e-9
    smin = inset / np.maximum(length, 1e-300)
    return ~par & (u >= -eps) & (w >= -eps) & (u + w <= 1.0 + eps) & (s > smin) & (s < 1.0 - smin)


# --------------------------------------------------------------------------------------------
# Bone heat
# --------------------------------------------------------------------------------------------


def _check_bones(bone_start: np.ndarray, bone_end: np.ndarray, bone_mask, scale: float) -> tuple:
    a = np.asarray(bone_start, dtype=np.float64)
    b = np.asarray(bone_end, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or b.shape != a.shape:
        raise RigError(f"bone heat: bone starts {a.shape} and ends {b.shape} must both have shape [J, 3]")
    bad = np.nonzero(~np.all(np.isfinite(a) & np.isfinite(b), axis=1))[0]
    if bad.size:
        raise RigError(f"bone heat: bones {bad[:8].tolist()} have NaN or inf end points")
    mask = np.ones(a.shape[0], dtype=bool) if bone_mask is None else np.asarray(bone_mask, dtype=bool).ravel()
    if mask.shape != (a.shape[0],):
        raise RigError(f"bone heat: bone_mask has {mask.size} entries for {a.shape[0]} bones")
    length = np.linalg.norm(b - a, axis=1)
    active = mask & (length > 1e-9 * scale)
    if not active.any():
        raise RigError(
            f"bone heat: no bone with positive length among the {a.shape[0]} bones "
            f"({int(mask.sum())} not masked out); bone heat needs at least one"
        )
    return a, b, active


def nearest_visible_bones(
    vertices: np.ndarray,
    triangles: np.ndarray,
    bone_start: np.ndarray,
    bone_end: np.ndarray,
    *,
    bone_mask: np.ndarray | None = None,
    visibility_candidates: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each vertex's nearest visible bone(s) and its distance (the ``p`` and ``d`` of the paper).

    Bones are tested in order of distance; a vertex stops at its first visible bone, except
    that bones tied with it (within a relative :data:`TIE_TOLERANCE`) are tested too. At most
    the ``visibility_candidates`` nearest bones are tried for a vertex that sees none.

    Args:
        vertices: Positions [m], ``[V, 3]``.
        triangles: Vertex indices, ``[T, 3]``.
        bone_start: Bone segment starts [m], ``[J, 3]``.
        bone_end: Bone segment ends [m], ``[J, 3]``.
        bone_mask: Bones to consider, ``[J]`` bool (default: all with positive length).
        visibility_candidates: How many nearest bones to try per vertex.

    Returns:
        ``(p, distance, distance_all)``: ``p`` ``[V, J]`` heat-source shares (rows sum to 1
        where a bone is visible, 0 where none is); ``distance`` ``[V]`` [m] to the nearest
        visible bone (inf where none); ``distance_all`` ``[V, J]`` [m] to every bone (inf where
        masked or of zero length).
    """
    v, t = _check_mesh(vertices, triangles)
    scale = _scale(v)
    a, b, active = _check_bones(bone_start, bone_end, bone_mask, scale)
    n, j = v.shape[0], a.shape[0]
    dist = np.full((n, j), np.inf)
    for k in np.nonzero(active)[0]:  # bones are few; vertices are vectorised
        q, _ = closest_point_on_segments(v, np.broadcast_to(a[k], v.shape), np.broadcast_to(b[k], v.shape))
        dist[:, k] = np.linalg.norm(v - q, axis=1)
    n_active = int(active.sum())
    order = np.argsort(dist, axis=1, kind="stable")[:, :n_active]  # [V, A] nearest first
    dsort = np.take_along_axis(dist, order, axis=1)
    visible = np.zeros((n, n_active), dtype=bool)
    best = np.full(n, np.inf)  # distance of the first visible bone
    grid = _make_grid(v, t)
    rows = np.arange(n)
    kc = max(1, int(visibility_candidates))
    for r in range(n_active):
        found = np.isfinite(best)
        need = np.where(found, dsort[:, r] <= best * (1.0 + TIE_TOLERANCE), r < kc)
        idx = rows[need]
        if idx.size == 0:
            if r >= kc:
                break
            continue
        bone = order[idx, r]
        target, _ = closest_point_on_segments(v[idx], a[bone], b[bone])
        blocked = segments_cross_mesh(v, t, v[idx], target, start_vertex=idx, _grid=grid)
        visible[idx, r] = ~blocked
        newly = idx[~blocked & ~found[idx]]
        best[newly] = dsort[newly, r]
    tied = visible & (dsort <= best[:, None] * (1.0 + TIE_TOLERANCE))
    p = np.zeros((n, j))
    share = tied / np.maximum(tied.sum(axis=1, keepdims=True), 1)
    np.put_along_axis(p, order, share, axis=1)
    return p, best, dist


def _nearest_any(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heat sources from the nearest bone by distance alone (ties split), and that distance."""
    dmin = dist.min(axis=1)
    tied = dist <= dmin[:, None] * (1.0 + TIE_TOLERANCE)
    return tied / tied.sum(axis=1, keepdims=True), dmin


def bone_heat_weights(
    vertices: np.ndarray,
    triangles: np.ndarray,
    bone_start: np.ndarray,
    bone_end: np.ndarray,
    *,
    bone_mask: np.ndarray | None = None,
    max_influences: int = 4,
    heat_c: float = 1.0,
    min_weight: float = 1e-3,
    visibility_candidates: int = 3,
    area_kind: str = "mixed",
) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights by bone heat diffusion (Baran and Popović 2007, section 4).

    Solves ``(-L + M H) W = M H P`` (see the module docstring) with one sparse LU factorisation
    for all bones, then clamps negative weights to 0, keeps the ``max_influences`` largest per
    vertex, drops those below ``min_weight`` and renormalises each row to sum to one.

    Args:
        vertices: Rest positions [m], ``[V, 3]``.
        triangles: Vertex indices, ``[T, 3]`` (a closed mesh gives meaningful visibility).
        bone_start: Bone segment starts [m], ``[J, 3]``.
        bone_end: Bone segment ends [m], ``[J, 3]``.
        bone_mask: ``[J]`` bool; False skips a bone (it gets no weight). Zero-length bones are
            always skipped.
        max_influences: Columns ``K`` of the result (influences kept per vertex).
        heat_c: The paper's ``c`` (1 by default): heat-source strength relative to diffusion.
        min_weight: Weights below this are dropped before renormalising.
        visibility_candidates: Nearest bones tried per vertex in the visibility test.
        area_kind: Lumped areas for ``M``: ``"mixed"`` (Meyer et al.) or ``"barycentric"``.

    Returns:
        ``(joint_indices, joint_weights)``, both ``[V, K]`` (int64 bone indices into the ``J``
        bones, float64 weights summing to one per row, sorted by decreasing weight; unused
        columns hold weight 0 and repeat the vertex's strongest bone, so scatter them with
        addition, as :meth:`~warpskin.rig.Rig.dense_weights` does).

    Raises:
        RigError: NaN/inf positions, bad indices or shapes, no triangles, no bone with positive
            length, or a singular system.
    """
    v, t = _check_mesh(vertices, triangles)
    if int(max_influences) < 1:
        raise RigError(f"bone heat: max_influences must be >= 1, got {max_influences}")
    if not (heat_c > 0.0 and np.isfinite(heat_c)):
        raise RigError(f"bone heat: heat_c must be a positive number, got {heat_c}")
    if not (0.0 <= min_weight < 1.0):
        raise RigError(f"bone heat: min_weight must be in [0, 1), got {min_weight}")
    scale = _scale(v)
    p, dvis, dist = nearest_visible_bones(
        v, t, bone_start, bone_end, bone_mask=bone_mask, visibility_candidates=visibility_candidates
    )
    n, j = p.shape
    area = vertex_areas(v, t, kind=area_kind)
    lap = -cotangent_laplacian(v, t)  # positive semi-definite
    active = area > 0.0  # vertices in some non-degenerate triangle

    # connected parts (over non-degenerate triangles) in which no vertex sees a bone: fall back
    # to the nearest bone by distance there, or the system would be singular on that part
    _, _, ok = _triangle_geometry(v, t)
    tk = t[ok]
    adj = sp.coo_matrix(
        (np.ones(tk.size), (tk.ravel(), tk[:, [1, 2, 0]].ravel())), shape=(n, n)
    ).tocsr()
    n_comp, comp = csgraph.connected_components(adj, directed=False)
    sees = np.isfinite(dvis) & active
    lit = np.bincount(comp[sees], minlength=n_comp) > 0
    dark = ~lit[comp] | ~active
    if dark.any():
        p_any, d_any = _nearest_any(dist[dark])
        p[dark] = p_any
        dvis = dvis.copy()
        dvis[dark] = d_any
    d_eff = np.maximum(dvis, 1e-4 * scale)
    heat = np.where(np.isfinite(dvis), heat_c / d_eff**2, 0.0)

    w = p.copy()  # inactive (isolated) vertices keep their heat source as the weight
    idx = np.nonzero(active)[0]
    if idx.size:
        mh = area[idx] * heat[idx]
        a_mat = lap[idx][:, idx] + sp.diags(mh)
        bones_used = np.nonzero(p[idx].any(axis=0))[0]
        rhs = p[idx][:, bones_used] * mh[:, None]
        try:
            # COLAMD: measured faster overall than the symmetric orderings on body meshes
            lu = spla.splu(a_mat.tocsc(), permc_spec="COLAMD")
        except RuntimeError as exc:
            raise RigError(
                f"bone heat: the heat system is singular ({exc}); is the mesh degenerate?"
            ) from exc
        sol = lu.solve(rhs)
        if not np.all(np.isfinite(sol)):
            raise RigError("bone heat: the heat system gave NaN or inf weights; is the mesh degenerate?")
        w[idx] = 0.0
        w[np.ix_(idx, bones_used)] = sol
    return _prune(w, int(max_influences), float(min_weight))


def _prune(w: np.ndarray, k: int, min_weight: float) -> tuple[np.ndarray, np.ndarray]:
    """Clamp to >= 0, keep the ``k`` largest per row, drop < ``min_weight``, renormalise."""
    n, j = w.shape
    w = np.maximum(w, 0.0)
    ke = min(k, j)
    top = np.argsort(-w, axis=1, kind="stable")[:, :ke]
    tw = np.take_along_axis(w, top, axis=1)
    tw = np.where(tw >= min_weight, tw, 0.0)
    s = tw.sum(axis=1, keepdims=True)
    empty = s[:, 0] <= 0.0
    tw[empty, 0] = 1.0  # cannot happen for a solved system (rows sum to 1); keep the argmax
    s[empty] = 1.0
    tw = tw / s
    top = np.where(tw > 0.0, top, top[:, :1])
    ji = np.repeat(top[:, :1], k, axis=1)
    jw = np.zeros((n, k))
    ji[:, :ke] = top
    jw[:, :ke] = tw
    return ji.astype(np.int64), jw


def with_bone_heat_weights(rig: Rig, **kw) -> Rig:
    """A copy of ``rig`` whose skin weights come from :func:`bone_heat_weights`.

    Bones are :func:`~warpskin.preprocess.bones.bone_segments` of the rig (whose leaf-bone extension
    reads the rig's current weights); only bones of positive length get weight (a ``bone_mask``
    in ``kw`` further restricts them).

    Args:
        rig: The rig (rest mesh and skeleton are kept; its arrays are not modified).
        **kw: Keyword arguments of :func:`bone_heat_weights`.

    Returns:
        A validated :class:`~warpskin.rig.Rig` with new ``joint_indices`` / ``joint_weights``.
    """
    bones = bone_segments(rig)
    mask = bones.length > 0.0
    if kw.get("bone_mask") is not None:
        mask &= np.asarray(kw.pop("bone_mask"), dtype=bool)
    kw.pop("bone_mask", None)
    ji, jw = bone_heat_weights(
        rig.vertices, rig.triangles, bones.start, bones.end, bone_mask=mask, **kw
    )
    out = dataclasses.replace(rig, joint_indices=ji, joint_weights=jw, report=None)
    out.validate(raise_on_error=True)
    return out

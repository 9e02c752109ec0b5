"""Capture of the written meshes by the simulated surface, and their physics weights.

Every written point moves as its own LBS plus the physical deformation of the simulated
surface near it (:mod:`warpskin.kernels.deform`): the displacement of the simulated vertices
from their own LBS, blended by capture weights that are computed once, at rest, as a production
point deformer captures a render mesh by a lattice (Houdini's Point Capture and Point Deform;
Joshi et al. 2007 for harmonic captures in the same spirit). The capture respects the written
mesh's own connectivity and skinning:

1. **Candidates**: the simulated vertices within ``radius`` cage edges of the point, weighted by
   a smooth kernel of the distance, ``(1 - (r / R)^2)^3``, times the squared *skinning
   similarity* of the two (the histogram intersection ``sum_j min(w_pj, w_cj)`` of their LBS
   weights: a cage vertex driven by other joints, such as the other shoe or the torso under an
   arm, counts for nothing), times how much they face the same way (the far side of a fist
   does not capture its front).
2. **Smoothing within the piece**: the captures of the written points within ``smooth`` cage
   edges of each other *in the same piece of the same mesh* (a connected piece, or pieces of
   one mesh that touch: a segmented limb) that are skinned alike and face alike are averaged
   with the same kernel, so the carried field is smooth over the written surface and never
   bleeds between parts (fingers, the two legs, another mesh).
3. **Pieces that move as a whole**: a piece, or an assembly of pieces of one mesh that touch
   (a fist's knuckles on its palm), smaller than ``small`` cage edges (a button, a toe cap, a
   fist) and a piece LBS moves rigidly (an eye, rigidly parented armour) take one
   capture row, the mean of their points': they move by one rigid motion on top of their LBS
   (the best fit of the simulated vertices that carry them), so they never crumple.
4. The ``count`` largest weights of each point are kept and renormalised.

The **physics weight** ``phi`` in [0, 1] blends LBS (0) and the physical result (1). It is 0
where the model cannot resolve the geometry: parts thinner than ``thin`` cage edges (the
shape diameter along the inward normal: fingers, toes, ears; a sheet, whose inward rays leave
through nothing, has none), points no compatible simulated
vertex captures, and what the caller marks (vertices where no layer depth fits); 1 where the
part is ``thick`` cage edges or more and the capture is confident (its skinning similarity at
least ``confidence[1]``); a smooth ramp between, smoothed over the piece like the capture.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree
from .mesh import summed_face_normals, vertex_normals
from .preprocess.cage import closest_faces

__all__ = ["CaptureParams", "Capture", "capture_points", "identity_capture", "shape_diameter",
           "welded_pieces", "wrap_points", "wrap_carriers", "Wrap", "smoothstep"]


@dataclass
class CaptureParams:
    """Settings of :func:`capture_points`; lengths in cage edges (the simulated surface's
    resolution).

    Attributes:
        radius: Support of a point's raw capture.
        smooth: Radius of the smoothing within a piece.
        count: Simulated vertices kept per point.
        small: A piece (or an assembly of touching pieces of one mesh) whose bounding-box
            diagonal is under this moves as a whole.
        thin: Physics weight 0 for parts thinner than this.
        thick: Physics weight 1 (as far as the thickness goes) for parts at least this thick.
        confidence: Skinning similarity of the capture below which the physics weight is 0,
            and from which it is 1.
    """

    radius: float = 1.6
    smooth: float = 1.0
    count: int = 8
    small: float = 8.0
    thin: float = 1.5
    thick: float = 2.5
    confidence: tuple[float, float] = (0.5, 0.85)


@dataclass
class Capture:
    """Capture rows of the written points and their physics weights.

    Attributes:
        indices: ``[N, K]`` simulated vertices of every point (weight 0 pads).
        weights: ``[N, K]`` their weights, summing to one per row.
        physics_weight: ``[N]`` in [0, 1].
        thickness: ``[N]`` shape diameter [m] (inf where a ray found no other side).
        confidence: ``[N]`` skinning similarity of the capture, in [0, 1].
        group: ``[N]`` the group of points that move as a whole (one capture row, one weight),
            or -1.
        notes: What set weights to 0 or moved pieces as a whole, for the run's summary.
        wrap: The points wrapped onto the written surface of the simulated pieces instead (a
            worn piece, :func:`~warpskin.kernels.deform.wrap_kernel`): a :class:`Wrap`, or
            ``None``; their capture rows are empty.
    """

    indices: np.ndarray
    weights: np.ndarray
    physics_weight: np.ndarray
    thickness: np.ndarray
    confidence: np.ndarray
    group: np.ndarray | None = None
    notes: dict = field(default_factory=dict)
    wrap: "Wrap | None" = None

    def __post_init__(self) -> None:
        if self.group is None:
            self.group = np.full(self.indices.shape[0], -1, dtype=np.int64)

    def uniform_in_groups(self, phi: np.ndarray) -> np.ndarray:
        """``phi`` with every group's points at the group's mean (so the group still moves by
        one rigid motion)."""
        phi = np.asarray(phi, dtype=np.float64).copy()
        sel = self.group >= 0
        if sel.any():
            _, g = np.unique(self.group[sel], return_inverse=True)
            mean = np.bincount(g, weights=phi[sel]) / np.bincount(g)
            phi[sel] = mean[g]
        return phi


def smoothstep(x, a: float, b: float):
    """The smoothstep ``3 u^2 - 2 u^3`` of ``u = (x - a) / (b - a)`` clamped to [0, 1]: 0 up to
    ``a``, 1 from ``b`` on (``x`` any shape, float64 out)."""
    u = np.clip((np.asarray(x, dtype=np.float64) - a) / max(b - a, 1e-300), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def welded_pieces(points: np.ndarray, triangles: np.ndarray, mesh_of_point: np.ndarray):
    """Weld the points of each mesh by position (seam copies) and label connected pieces.

    Returns ``(first, cls, class_triangles, piece)``: the first point of every class ``[C]``,
    the class of every point ``[N]``, the triangles over classes (degenerate ones dropped) and
    the piece of every class ``[C]``."""
    from scipy.sparse.csgraph import connected_components

    p = np.asarray(points, dtype=np.float64)
    key = np.concatenate([np.asarray(mesh_of_point, dtype=np.float64)[:, None], p], axis=1)
    _, first, cls = np.unique(key, axis=0, return_index=True, return_inverse=True)
    cls = cls.ravel()
    t = cls[np.asarray(triangles, dtype=np.int64)]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    c = first.size
    rows, cols = np.concatenate([t[:, 0], t[:, 1], t[:, 2]]), np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    _, piece = connected_components(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(c, c)), directed=False)
    return first, cls, t, piece


def shape_diameter(points: np.ndarray, normals: np.ndarray, mesh_points: np.ndarray, mesh_triangles: np.ndarray, *,
                   device=None, tilt_degrees: float = 20.0) -> np.ndarray:
    """The shape diameter at every point [m]: the median length of five rays cast inward
    (along ``-normals`` and tilted about it) to the far side of ``mesh`` (every mesh of the
    character, so a shoe's ray stops at the shoe's sole); ``inf`` where most rays meet
    nothing (an open piece seen from its inside)."""
    import warp as wp

    from .kernels import deform as k

    p = np.asarray(points, dtype=np.float64)
    if p.shape[0] == 0:
        return np.zeros(0)
    if np.asarray(mesh_triangles).size == 0:  # no surface to cast at: no other side anywhere
        return np.full(p.shape[0], np.inf)
    mp = np.asarray(mesh_points, dtype=np.float64)
    diag = float(np.linalg.norm(np.ptp(mp, axis=0)))
    far = 2.0 * diag + 1.0
    with wp.ScopedDevice(device):
        mesh = wp.Mesh(points=wp.array(mp.astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(np.asarray(mesh_triangles, dtype=np.int32).ravel(), dtype=wp.int32))
        hits = wp.zeros(p.shape[0] * 5, dtype=wp.float32)
        wp.launch(k.inward_rays_kernel, dim=p.shape[0],
                  inputs=[mesh.id, wp.array(p.astype(np.float32), dtype=wp.vec3),
                          wp.array(np.asarray(normals, dtype=np.float32), dtype=wp.vec3), float(1e-4 * diag), float(far),
                          float(np.radians(tilt_degrees))], outputs=[hits])
        d = hits.numpy().reshape(-1, 5).astype(np.float64)
    d[d >= 0.999 * far] = np.inf
    return np.median(d, axis=1)


def _similarity(wa: np.ndarray, wb: np.ndarray, rows: np.ndarray, cols: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """``sum_j min(wa[rows, j], wb[cols, j])`` per pair, in chunks (dense weights ``[*, J]``)."""
    out = np.empty(rows.size)
    for s in range(0, rows.size, chunk):
        r, c = rows[s:s + chunk], cols[s:s + chunk]
        out[s:s + chunk] = np.minimum(wa[r], wb[c]).sum(axis=1)
    return out


def _kernel(d: np.ndarray, radius: float) -> np.ndarray:
    r2 = np.clip((d / radius) ** 2, 0.0, 1.0)
    return (1.0 - r2) ** 3


def _row_normalised(m: sp.csr_matrix) -> sp.csr_matrix:
    s = np.asarray(m.sum(axis=1)).ravel()
    return (sp.diags(1.0 / np.where(s > 0, s, 1.0)) @ m).tocsr()


def _top_k(m: sp.csr_matrix, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest entries of every row as dense ``[R, k]`` (indices, weights), rows
    renormalised; padding has weight 0 (and the row's first index)."""
    m = m.tocoo()
    order = np.lexsort((-m.data, m.row))
    row, col, val = m.row[order], m.col[order], m.data[order]
    starts = np.searchsorted(row, np.arange(m.shape[0]))
    rank = np.arange(row.size) - starts[row]
    keep = rank < k
    idx = np.zeros((m.shape[0], k), dtype=np.int64)
    w = np.zeros((m.shape[0], k))
    idx[row[keep], rank[keep]] = col[keep]
    w[row[keep], rank[keep]] = val[keep]
    first = idx[:, :1]
    idx = np.where(w > 0, idx, first)
    s = w.sum(axis=1, keepdims=True)
    return idx, w / np.where(s > 0, s, 1.0)


def _assemblies(q: np.ndarray, piece: np.ndarray, mesh: np.ndarray, gap: float) -> np.ndarray:
    """``[C]`` the assembly of every point: pieces of the same mesh whose points come within
    ``gap`` of each other (touching or overlapping parts, such as a fist's knuckles on its
    palm), joined."""
    from scipy.sparse.csgraph import connected_components

    count = int(piece.max()) + 1
    tree = cKDTree(q)
    pairs = tree.query_pairs(gap, output_type="ndarray")
    if pairs.size:
        a, b = piece[pairs[:, 0]], piece[pairs[:, 1]]
        keep = (a != b) & (mesh[pairs[:, 0]] == mesh[pairs[:, 1]])
        a, b = a[keep], b[keep]
    else:
        a = b = np.zeros(0, dtype=np.int64)
    link = sp.csr_matrix((np.ones(a.size + count), (np.concatenate([a, np.arange(count)]),
                                                      np.concatenate([b, np.arange(count)]))), shape=(count, count))
    _, label = connected_components(link, directed=False)
    return label[piece]


def _smoothing(q: np.ndarray, wq: np.ndarray, nq: np.ndarray, piece: np.ndarray, sigma: float,
               part: np.ndarray | None = None) -> sp.csr_matrix:
    """Row-normalised ``[C, C]`` averaging over the points within ``sigma`` of each other in
    the same ``piece`` (an assembly), weighted by the distance kernel, their skinning similarity
    squared and how much their normals agree (itself weight 1). Between different ``part``s of
    an assembly (a tube's end inside a ball joint, which cross each other at rest) normals up to
    90 degrees apart count fully, so where the parts overlap they carry one field and keep the
    crossing they have under LBS."""
    c = q.shape[0]
    pairs = cKDTree(q).query_pairs(sigma, output_type="ndarray") if sigma > 0 and c > 1 else np.zeros((0, 2), np.int64)
    if not pairs.size:
        return sp.identity(c, format="csr")
    a, b = pairs[:, 0], pairs[:, 1]
    same = piece[a] == piece[b]
    a, b = a[same], b[same]
    cos = np.einsum("ij,ij->i", nq[a], nq[b])
    facing = smoothstep(cos, 0.0, 0.5)
    if part is not None:
        facing = np.where(part[a] != part[b], smoothstep(cos, -0.5, 0.0), facing)
    g = _kernel(np.linalg.norm(q[a] - q[b], axis=1), sigma) * _similarity(wq, wq, a, b) ** 2 * facing
    keep = g > 0
    a, b, g = a[keep], b[keep], g[keep]
    m = sp.csr_matrix((np.concatenate([g, g, np.ones(c)]),
                       (np.concatenate([a, b, np.arange(c)]), np.concatenate([b, a, np.arange(c)]))), shape=(c, c))
    return _row_normalised(m)


def capture_points(points: np.ndarray, triangles: np.ndarray, dense_weights: np.ndarray, mesh_of_point: np.ndarray,
                   cage_vertices: np.ndarray, cage_triangles: np.ndarray, cage_dense_weights: np.ndarray, edge: float, *,
                   rigid: np.ndarray | None = None, exclude: np.ndarray | None = None,
                   cage_exclude: np.ndarray | None = None, params: CaptureParams | None = None,
                   device=None) -> Capture:
    """Capture the written points by the simulated cage (see the module docstring).

    Args:
        points: ``[N, 3]`` written points at rest [m] (every written mesh, stage space).
        triangles: ``[T, 3]`` their triangles (global indices).
        dense_weights: ``[N, J]`` their LBS weights.
        mesh_of_point: ``[N]`` which written mesh each point belongs to.
        cage_vertices: ``[V, 3]`` the simulated surface at rest [m].
        cage_triangles: ``[F, 3]``, counter-clockwise from outside.
        cage_dense_weights: ``[V, J]`` its LBS weights.
        edge: The simulated surface's edge length [m] (the unit of ``params``).
        rigid: ``[N]`` the rigid piece of each point (-1: none): such a piece moves as a whole.
        exclude: ``[N]`` bool, points whose physics weight is 0 whatever else holds.
        cage_exclude: ``[V]`` bool, simulated vertices nothing is captured by (where the
            model could not resolve the surface: no layer depth fits there).
        params: :class:`CaptureParams`.
        device: Warp device for the ray casts.
    """
    prm = params or CaptureParams()
    p = np.asarray(points, dtype=np.float64)
    cv = np.asarray(cage_vertices, dtype=np.float64)
    wp_dense = np.asarray(dense_weights, dtype=np.float64)
    wc_dense = np.asarray(cage_dense_weights, dtype=np.float64)
    h = float(edge)
    first, cls, ctri, piece = welded_pieces(p, triangles, mesh_of_point)
    c = first.size
    q = p[first]
    wq = wp_dense[first]
    nq = vertex_normals(q, ctri)
    cage_n = vertex_normals(cv, cage_triangles)
    notes: dict = {}

    # 1. raw capture: nearby simulated vertices, skinned alike and facing alike
    tree = cKDTree(cv)
    radius = prm.radius * h
    lists = tree.query_ball_point(q, radius)
    counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=c)
    none = counts == 0
    if none.any():  # far from the cage (it should not be): the nearest few
        _, near = tree.query(q[none], k=min(4, cv.shape[0]))
        near = np.atleast_2d(near)
        for i, row in zip(np.nonzero(none)[0], near):
            lists[i] = list(np.atleast_1d(row))
        counts = np.fromiter((len(x) for x in lists), dtype=np.int64, count=c)
    rows = np.repeat(np.arange(c), counts)
    cols = np.fromiter((j for x in lists for j in x), dtype=np.int64, count=int(counts.sum()))
    dist = np.linalg.norm(q[rows] - cv[cols], axis=1)
    sim = _similarity(wq, wc_dense, rows, cols)
    facing = smoothstep(np.einsum("ij,ij->i", nq[rows], cage_n[cols]), -0.3, 0.3)
    k_raw = _kernel(dist, max(radius, float(dist.max()) * 1.0001)) * sim ** 2 * facing
    if cage_exclude is not None:
        k_raw = np.where(np.asarray(cage_exclude, dtype=bool)[cols], 0.0, k_raw)
    raw = sp.csr_matrix((k_raw, (rows, cols)), shape=(c, cv.shape[0]))
    raw.eliminate_zeros()
    total = np.asarray(raw.sum(axis=1)).ravel()
    unmatched = total <= 0
    if unmatched.any():  # nothing compatible: the nearest vertex, with physics weight 0 below
        _, near = tree.query(q[unmatched], k=1)
        raw = raw + sp.csr_matrix((np.ones(int(unmatched.sum())), (np.nonzero(unmatched)[0], np.atleast_1d(near))),
                                  shape=raw.shape)
    raw = _row_normalised(raw)
    sim_m = sp.csr_matrix((sim, (rows, cols)), shape=raw.shape)
    confidence = np.asarray(raw.multiply(sim_m).sum(axis=1)).ravel()
    confidence[unmatched] = 0.0

    # 2. smoothing within each assembly (the pieces of one mesh that touch: a segmented limb),
    # between points skinned and facing alike (never across to a finger beside it)
    assembly = _assemblies(q, piece, np.asarray(mesh_of_point)[first], 0.5 * h)
    smooth = _smoothing(q, wq, nq, assembly, prm.smooth * h, part=piece)
    cap = _row_normalised(smooth @ raw)

    # physics weight: thick enough, captured confidently, not excluded
    thickness = shape_diameter(q, nq, q, ctri, device=device)
    # a part whose inward rays leave through nothing is a sheet (a flat strip, a cape): no volume
    phi = (smoothstep(np.where(np.isfinite(thickness), thickness, 0.0), prm.thin * h, prm.thick * h)
           * smoothstep(confidence, *prm.confidence))
    phi[unmatched] = 0.0
    ex = np.zeros(c, dtype=bool)
    if exclude is not None:
        np.logical_or.at(ex, cls, np.asarray(exclude, dtype=bool))
        phi[ex] = 0.0
    notes["thin_points"] = int(((thickness[cls] < prm.thin * h) | ~np.isfinite(thickness[cls])).sum())
    notes["unmatched_points"] = int(unmatched[cls].sum())
    notes["excluded_points"] = int(ex[cls].sum())
    for _ in range(2):
        phi = smooth @ phi
    phi[ex | unmatched] = 0.0

    # 3. pieces that move as a whole: small assemblies (pieces of one mesh touching each other,
    # a fist's knuckles on its palm) and rigid pieces take their mean row and weight
    group = np.full(c, -1, dtype=np.int64)
    lo = np.full((assembly.max() + 1, 3), np.inf)
    hi = np.full((assembly.max() + 1, 3), -np.inf)
    np.minimum.at(lo, assembly, q)
    np.maximum.at(hi, assembly, q)
    small = np.linalg.norm(hi - lo, axis=1) < prm.small * h
    group[small[assembly]] = assembly[small[assembly]]
    if rigid is not None:
        r = np.full(c, -1, dtype=np.int64)
        r[cls] = np.asarray(rigid, dtype=np.int64)
        sel = r >= 0
        group[sel] = assembly.max() + 1 + r[sel]
    notes["pieces_as_a_whole"] = int(np.unique(group[group >= 0]).size)
    if (group >= 0).any():
        _, g_id = np.unique(group[group >= 0], return_inverse=True)
        members = np.nonzero(group >= 0)[0]
        ind = sp.csr_matrix((np.ones(members.size), (g_id.ravel(), members)), shape=(int(g_id.max()) + 1, c))
        mean_rows = _row_normalised(ind @ cap)
        mean_phi = (ind @ phi) / np.asarray(ind.sum(axis=1)).ravel()
        other = sp.diags((group < 0).astype(np.float64)) @ cap
        assign = sp.csr_matrix((np.ones(members.size), (members, g_id.ravel())), shape=(c, mean_rows.shape[0]))
        cap = (other + assign @ mean_rows).tocsr()
        phi = np.where(group >= 0, assign @ mean_phi, phi)

    idx, w = _top_k(cap, prm.count)
    phi = np.clip(phi, 0.0, 1.0)
    return Capture(indices=idx[cls], weights=w[cls], physics_weight=phi[cls], thickness=thickness[cls],
                   confidence=confidence[cls], group=group[cls], notes=notes)


def identity_capture(count: int, physics_weight: np.ndarray | None = None) -> Capture:
    """Every written point captured by the simulated vertex of the same index (a skin simulated
    directly)."""
    phi = np.ones(count) if physics_weight is None else np.asarray(physics_weight, dtype=np.float64)
    return Capture(indices=np.arange(count)[:, None], weights=np.ones((count, 1)), physics_weight=phi,
                   thickness=np.full(count, np.inf), confidence=np.ones(count))


def _wrap_offsets(p: np.ndarray, x: np.ndarray, corners: np.ndarray, bary: np.ndarray,
                  vn: np.ndarray) -> np.ndarray:
    """``[M, 3]`` the coefficients ``(alpha, beta, gamma)`` of ``p - c`` in the basis ``(e_1, e_2,
    n)`` of each point's triangle ``corners`` at its surface point ``c`` (``bary``), ``n`` the
    vertex normals ``vn`` blended by ``bary`` and normalised."""
    c = np.einsum("mk,mkj->mj", bary, x[corners])
    n = np.einsum("mk,mkj->mj", bary, vn[corners])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    e1 = x[corners[:, 1]] - x[corners[:, 0]]
    e2 = x[corners[:, 2]] - x[corners[:, 0]]
    basis = np.stack([e1, e2, n], axis=2)  # columns
    return np.linalg.solve(basis, (p - c)[:, :, None])[:, :, 0]


def _closest(p: np.ndarray, x: np.ndarray, t: np.ndarray, device) -> tuple[np.ndarray, np.ndarray]:
    """Each point's closest triangle of ``t`` on ``x``: ``(corners [M, 3], barycentric [M, 3])``."""
    far = 2.0 * float(np.linalg.norm(np.ptp(np.concatenate([p, x]), axis=0))) + 1.0
    face, bary = closest_faces(p, x, t, far, device)
    bary = np.clip(bary, 0.0, None)
    bary /= np.maximum(bary.sum(axis=1, keepdims=True), 1e-300)
    return t[np.maximum(face, 0)], bary


def _wrap_on(p: np.ndarray, x: np.ndarray, t: np.ndarray, vn: np.ndarray,
             device) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each of ``p`` on its closest triangle of ``t`` on ``x`` (vertex normals ``vn``):
    ``(corners [M, 3], barycentric [M, 3], coefficients [M, 3], distance [M])``."""
    corners, bary = _closest(p, x, t, device)
    coef = _wrap_offsets(p, x, corners, bary, vn)
    return corners, bary, coef, np.linalg.norm(p - np.einsum("mk,mkj->mj", bary, x[corners]), axis=1)


def wrap_points(points: np.ndarray, surface: np.ndarray, triangles: np.ndarray, all_triangles: np.ndarray, *,
                device=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """How each of ``points`` ``[M, 3]`` rides on the simulated ``surface`` ``[V, 3]`` (both at
    rest) for :func:`~warpskin.kernels.deform.wrap_kernel`: its closest point on ``triangles``
    (``[T, 3]``: the surface's own, no cap), and its offset from there as ``alpha e_1 + beta e_2 +
    gamma n`` in that triangle's edges and the unit normal blended from the vertex normals of
    ``all_triangles`` (the whole closed surface, as the kernel computes them). Returns
    ``(corners [M, 3], barycentric [M, 3], coefficients [M, 3], distance [M])``."""
    x = np.asarray(surface, dtype=np.float64)
    vn = summed_face_normals(x, np.asarray(all_triangles, dtype=np.int64))
    return _wrap_on(np.asarray(points, dtype=np.float64), x, np.asarray(triangles, dtype=np.int64), vn, device)


@dataclass
class Wrap:
    """The worn points of a character and the surface points they ride on
    (:func:`~warpskin.kernels.deform.wrap_kernel`); ``K`` carriers a point.

    Attributes:
        points: ``[M]`` written points that are wrapped.
        corners: ``[M, K, 3]`` each carrier's triangle (written points of the surface).
        bary: ``[M, K, 3]`` each carrier's barycentric coordinates on it.
        coef: ``[M, K, 3]`` the point's offset from each carrier, ``(alpha, beta, gamma)``.
        share: ``[M, K]`` how much the point rides on each carrier (each row sums to 1).
        clearance: ``[M]`` the clearance [m] it keeps from the surface.
        body: ``[B, 3]`` the surface's triangles.
    """

    points: np.ndarray
    corners: np.ndarray
    bary: np.ndarray
    coef: np.ndarray
    share: np.ndarray
    clearance: np.ndarray
    body: np.ndarray

    @property
    def gamma(self) -> np.ndarray:
        """``[M]`` each point's height [m] along the normal over its closest carrier (the first)."""
        return self.coef[:, 0, 2]

    def carrier_points(self, surface: np.ndarray) -> np.ndarray:
        """``[M, 3]`` the blend of each point's carriers by ``share`` on ``surface`` ``[V, 3]``."""
        c = np.einsum("mkj,mkjc->mkc", self.bary, np.asarray(surface)[self.corners])
        return np.einsum("mk,mkc->mc", self.share, c)


def wrap_carriers(points: np.ndarray, point_weights: np.ndarray, surface: np.ndarray, surface_weights: np.ndarray,
                  triangles: np.ndarray, *, reach: float, deficit: tuple[float, float] = (0.05, 0.15),
                  device=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two carriers for each worn point of ``points`` ``[M, 3]`` on ``surface`` ``[V, 3]`` (its
    ``triangles`` ``[T, 3]``, closed or not), so that a point skinned to two joints whose skins
    lie apart (the web of baggy trousers between the knees, skinned to both thighs) rides on
    both as LBS blends them, instead of on one leg that the other then meets.

    The first carrier is the closest point (:func:`wrap_points`). Its skin weights (the corners'
    dense weights ``surface_weights`` ``[V, J]`` blended barycentrically) are compared with the
    point's own (``point_weights`` ``[M, J]``): the joint the point is skinned to most beyond its
    carrier, by ``d = max_j (w_pj - w_cj)``, has the second carrier, the closest point on the
    triangles that joint dominates (the largest summed weight of their corners). The point rides
    on the carriers in proportion to their skinning similarity with it (the histogram
    intersection ``sum_j min(w_pj, w_cj)``), the second's faded in over ``deficit`` (by ``d``) and
    out from ``reach`` to ``2 reach`` [m] of distance: a point skinned like its closest surface
    keeps one carrier. Every carrier's offset is exact at rest, so the blend is the point there.

    Returns ``(corners [M, 2, 3], barycentric [M, 2, 3], coefficients [M, 2, 3], share [M, 2],
    distance to the first [M])``; a point without a second carrier repeats its first with share 0.
    """
    p = np.asarray(points, dtype=np.float64)
    x = np.asarray(surface, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    wpt = np.asarray(point_weights, dtype=np.float64)
    wsf = np.asarray(surface_weights, dtype=np.float64)
    vn = summed_face_normals(x, t)
    c0, b0, f0, dist = _wrap_on(p, x, t, vn, device)
    m = p.shape[0]
    corners = np.repeat(c0[:, None], 2, axis=1)
    bary = np.repeat(b0[:, None], 2, axis=1)
    coef = np.repeat(f0[:, None], 2, axis=1)
    share = np.zeros((m, 2))
    share[:, 0] = 1.0
    if m == 0 or t.shape[0] == 0:
        return corners, bary, coef, share, dist
    w0 = np.einsum("mk,mkj->mj", b0, wsf[c0])
    lack = np.maximum(wpt - w0, 0.0)
    joint = np.argmax(lack, axis=1)
    need = lack[np.arange(m), joint]
    ramp = smoothstep(need, *deficit)
    dominant = np.argmax(wsf[t].sum(axis=1), axis=1)
    s1 = np.zeros(m)
    for j in np.unique(joint[ramp > 0.0]):
        sel = np.nonzero((joint == j) & (ramp > 0.0))[0]
        tj = t[dominant == j]
        if tj.shape[0] == 0:
            continue
        cj, bj, coef[sel, 1], dj = _wrap_on(p[sel], x, tj, vn, device)
        corners[sel, 1], bary[sel, 1] = cj, bj
        wj = np.einsum("mk,mkj->mj", bj, wsf[cj])
        s1[sel] = (np.minimum(wpt[sel], wj).sum(axis=1) * ramp[sel] * (1.0 - smoothstep(dj, reach, 2.0 * reach)))
    s0 = np.minimum(wpt, w0).sum(axis=1)
    total = s0 + s1
    share[:, 1] = np.where(total > 0.0, s1 / np.maximum(total, 1e-300), 0.0)
    share[:, 0] = 1.0 - share[:, 1]
    return corners, bary, coef, share, dist

"""The character's own surface, made closed, as the simulation surface.

A character from production is rarely one closed manifold: one or more meshes of many pieces
(connected components): a body open at the neck, the wrists and the ankles, a head open at the
neck and the eye sockets, clothes open at their cuffs and collars, shoes open at the top, eyes,
hair. :func:`piece_surface` makes from them a surface the layered model simulates directly:

1. **Pieces**: every written mesh welded by position (seam copies joined), split into
   connected components (:func:`~warpskin.capture.welded_pieces`).
2. **Holes capped**: every boundary loop of a piece is closed by a cap of concentric rings
   (:func:`cap_loop`), simulated but never written: its vertices are new, its rings shrink
   towards the loop's centre by about one loop edge each, so its triangles are about as large as
   the loop's edges. A loop is capped where it is simple and star-shaped about its centre in its
   own best plane (the neck, a wrist, a cuff, an eye socket, a waistband); a piece is closed
   when all its loops are capped and it then encloses a volume (a flat strip capped encloses
   none).
3. **Reduced where dense**: where the simulated pieces hold more than ``max_vertices`` points,
   each is reduced in proportion by quadric edge collapse (its boundary loops kept), then
   capped again; what is written is then captured by it.
4. **What is simulated**: every closed piece, except pieces that LBS moves rigidly (one joint)
   and that are small (under ``rigid_small`` of the character's height: an eye, a tooth, a
   button): those, and every piece that cannot be closed (a sheet: a fringe, a hair card, a
   skirt's flat panel), are *attached*: captured by the simulated surface they rest on
   (:mod:`warpskin.capture`).
5. **Which pieces collide**: pieces whose surfaces cross or touch at rest (a hair bun sunk into
   the skull, an eye in its socket, a hand's wrist tucked into a sleeve), or of which one lies
   inside the other (the body inside its trousers, a foot inside its shoe) never collide with
   each other: their overlap at rest is accepted as it is, never resolved. Caps collide with
   nothing outside their own piece. Every other pair of pieces (an arm and the torso's piece, a
   hand and a thigh) collides as the skin collides with itself.

The result (:class:`PieceSurface`) is closed, manifold and consistently wound (outward) piece
by piece; its vertices are the simulated pieces' welded points (in the order of the written
points) followed by their caps' vertices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..capture import shape_diameter, smoothstep, welded_pieces
from ..kernels import pieces as k_pieces
from ..mesh import mesh_edge_report, summed_face_normals, surface_area, vertex_normals
from ..metrics import self_intersections
from ..units import metres_per_unit
from .cage import closest_faces

__all__ = ["PieceSurface", "SurfaceGroups", "piece_surface", "cap_loop", "boundary_loops", "PieceParams"]


@dataclass
class PieceParams:
    """Settings of :func:`piece_surface`.

    Attributes:
        max_planarity: A loop whose points lie farther than this share of its mean radius
            from its best plane is not capped.
        min_fullness: A capped piece must enclose at least this share of the volume of a
            ball of its area (``V / (A^1.5 / (6 sqrt(pi)))``): a flat sheet capped encloses none.
        cap_rings: Caps of concentric rings of points of their own (:func:`cap_loop`); by
            default a strip across the loop's own points.
        max_cap_share: A piece whose caps' area is more than this share of its own is a
            sheet (a fringe, a hair cap over the scalp: capped, it would be a body of which
            half the surface is cap).
        rigid_small: A piece LBS moves rigidly whose bounding-box diagonal is under this share
            of the character's height moves with the surface it rests on (an eye).
        min_points: Pieces with fewer welded points are attached.
        max_vertices: Where the simulated pieces have more points than this, each is reduced
            in proportion (quadric edge collapse, its holes' loops kept) and what is written
            is captured by it: the layered model's cost grows with its vertices, and a few
            thousand resolve a human's joints (``None``: never).
        min_piece_points: No piece is reduced below this many points.
        garment_cover: A piece is worn over others (a garment: trousers, a shirt, a shoe
            over a foot, a hair cap over the scalp) where at least this share of its points have
            another piece beneath them (the ray along the inward normal meets another piece
            before its own other side, within ``garment_gap`` of the height): it follows the
            surface beneath it instead of being simulated with layers of its own.
        garment_gap: See ``garment_cover``.
        thin: A piece thinner than this many edges of the simulated surface (the median of
            its points' shape diameters; the edge it will have once reduced) is too thin for
            layers to resolve (a hand with its fingers as one mitten, a flat sole): it is
            attached instead.
        small_assembly: Two or more pieces of one mesh that touch and together span less than
            this many edges (a fist of palm, knuckles and thumb) are carried as a whole.
        bony_depth: The factor on the layers' projection parameters of the simulated skin
            beneath a piece LBS moves rigidly on the same joint and that is not simulated
            itself (worn or carried: a hair cap on the skull, an eye in its socket, a fringe on
            the brow), within the piece's half-diagonal of it (at most ``garment_gap`` of the
            height: a belt thins the tissue under it, not the whole pelvis) and blending back
            to 1 over as much again: such a piece moves with the best rigid motion of the
            surface beneath, which must then move with its joint as a skull does, so the
            tissue there is as thin as over a bone (0.25: the paper's bone layer at 0.2 of the
            way to the bone's line instead of 0.8). 1 leaves the layers as the scene sets them.
    """

    max_planarity: float = 1.0
    min_fullness: float = 0.15
    max_cap_share: float = 0.4
    cap_rings: bool = False
    max_vertices: int | None = 4000
    min_piece_points: int = 150
    garment_cover: float = 0.5
    garment_gap: float = 0.06
    thin: float = 2.0
    small_assembly: float = 8.0
    rigid_small: float = 0.03
    min_points: int = 12
    bony_depth: float = 0.25


@dataclass
class SurfaceGroups:
    """What the collision model needs to know of a surface of several pieces.

    Attributes:
        group: ``[V]`` the collision group of every simulated vertex: its piece, or (a cap's own
            vertices) ``P + piece``, or (a seam zone's) ``2 P + zone``.
        excluded: ``[G, G]`` bool, pairs of groups that never collide (symmetric; a group with
            itself never is).
        names: ``[P]`` a name per piece (its mesh and the joint that weighs most on it).
        owner: ``[G]`` the piece of every group.
        seams: ``[(piece, partner)]`` of every seam zone (group ``2 P + k``).
        depth_factor: ``[V]`` in (0, 1], the factor on the layers' projection parameters of
            every vertex (``PieceParams.bony_depth`` beneath a rigid piece), or ``None``.
    """

    group: np.ndarray
    excluded: np.ndarray
    names: list = field(default_factory=list)
    owner: np.ndarray | None = None
    seams: list = field(default_factory=list)
    depth_factor: np.ndarray | None = None

    @property
    def group_count(self) -> int:
        return int(self.excluded.shape[0])

    @property
    def piece(self) -> np.ndarray:
        """``[V]`` the piece of every vertex (a cap's or a seam zone's: its piece's)."""
        g = np.asarray(self.group)
        return self.owner[g] if self.owner is not None else g % max(len(self.names), 1)


@dataclass
class PieceSurface:
    """The closed simulation surface made of a character's own pieces.

    Attributes:
        vertices: ``[V, 3]`` rest positions [m] (stage space): the simulated pieces' welded
            points, then the caps' vertices.
        triangles: ``[T, 3]``: the pieces' triangles, then the caps', counter-clockwise from
            outside.
        written_triangles: ``[W, 3]`` the pieces' own triangles (no cap).
        dense_weights: ``[V, J]`` LBS weights (a cap vertex: blended from its loop's).
        origin: ``[V]`` the written point (soup index) of every vertex, -1 for a cap vertex.
        vertex_piece: ``[V]`` the piece of every vertex.
        cap: ``[V]`` bool, a cap's own vertex.
        piece_of_point: ``[N]`` the piece of every written point.
        vertex_of_point: ``[N]`` the simulated vertex of every written point (-1 on a piece
            that is not simulated, or that was decimated: captured by it instead).
        simulated: ``[P]`` bool, per piece.
        rigid: ``[P]`` bool, per piece: LBS moves it rigidly (one joint).
        closable: ``[P]`` bool, per piece: closed once capped.
        decimated: ``[P]`` bool, per piece: simulated on a reduced copy (see ``max_vertices``).
        garment: ``[P]`` bool, per piece: worn over others (see ``garment_cover``), attached to
            them.
        gap: ``[P]`` a garment's distance to what it is worn over [m] (the 90th percentile
            over its points), 0 for the others.
        carried: ``[P]`` bool, per piece: of a small assembly, carried as a whole (see
            ``small_assembly``).
        small: ``[P]`` bool, per piece: smaller than ``rigid_small`` of the height.
        groups: :class:`SurfaceGroups`.
        notes: What was capped, attached and excluded, for the run's summary.
        edge: The simulated surface's mean edge [m].
    """

    vertices: np.ndarray
    triangles: np.ndarray
    written_triangles: np.ndarray
    dense_weights: np.ndarray
    origin: np.ndarray
    vertex_piece: np.ndarray
    cap: np.ndarray
    piece_of_point: np.ndarray
    vertex_of_point: np.ndarray
    simulated: np.ndarray
    rigid: np.ndarray
    closable: np.ndarray
    decimated: np.ndarray
    garment: np.ndarray
    gap: np.ndarray
    carried: np.ndarray
    small: np.ndarray
    groups: SurfaceGroups
    notes: dict = field(default_factory=dict)
    edge: float = 0.0

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def piece_count(self) -> int:
        return int(self.simulated.shape[0])


# --------------------------------------------------------------------------------------------
# boundary loops and caps
# --------------------------------------------------------------------------------------------
def boundary_loops(triangles: np.ndarray) -> tuple[list[np.ndarray], bool]:
    """The boundary loops of a consistently wound triangle mesh, each as its vertices in the
    order the mesh's own triangles traverse its edges (``loop[i] -> loop[i + 1]``). Returns
    ``(loops, simple)``: ``simple`` is False where a boundary vertex has more than one outgoing
    boundary edge (two loops touch at a vertex) or an edge is used by more than two triangles
    or twice in the same direction (then ``loops`` is empty)."""
    t = np.asarray(triangles, dtype=np.int64)
    if t.size == 0:
        return [], True
    directed = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    und = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if (counts > 2).any():
        return [], False
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    if (dcounts > 1).any():
        return [], False
    bnd = directed[counts[inverse] == 1]
    if bnd.size == 0:
        return [], True
    starts, out_deg = np.unique(bnd[:, 0], return_counts=True)
    if (out_deg > 1).any():
        return [], False
    nxt = dict(zip(bnd[:, 0].tolist(), bnd[:, 1].tolist()))
    loops, seen = [], set()
    for s in bnd[:, 0].tolist():
        if s in seen:
            continue
        loop = [s]
        seen.add(s)
        v = nxt.get(s)
        while v is not None and v != s:
            if v in seen:
                return [], False
            loop.append(v)
            seen.add(v)
            v = nxt.get(v)
        if v is None:
            return [], False
        loops.append(np.array(loop, dtype=np.int64))
    return loops, True


def _resample(points: np.ndarray, u: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of the closed polyline ``points`` (at parameters ``u`` in [0, 1)) at parameters
    ``at``: ``(positions, index of the point before, share towards the next)``."""
    n = len(points)
    k = np.clip(np.searchsorted(u, at, side="right") - 1, 0, n - 1)
    u1 = np.where(k + 1 < n, u[np.minimum(k + 1, n - 1)], 1.0)
    s = np.clip((at - u[k]) / np.maximum(u1 - u[k], 1e-300), 0.0, 1.0)
    p = points[k] + s[:, None] * (points[(k + 1) % n] - points[k])
    return p, k, s


def cap_loop(points: np.ndarray, loop: np.ndarray, *, max_planarity: float = 0.6, rings: bool = True):
    """A cap of concentric rings closing the boundary loop ``loop`` (vertex indices into
    ``points``, in the order the piece's triangles traverse its edges).

    The loop's centre ``c`` is its length-weighted mean, its plane the best plane through it
    (Newell's normal); ring ``k`` of ``K`` is the loop resampled at ``max(3, n (1 - k / K))``
    points, scaled by ``1 - k / K`` about ``c`` (``K`` about the mean radius over the mean loop
    edge), the last ring ``c`` itself. Consecutive rings are zipped by their arc-length
    parameters.

    The new points are then relaxed (the loop held) towards the mean of their neighbours, a
    harmonic disc that irons out where a jagged loop's zigzag meets the first ring. The caller
    checks that the cap crosses neither itself nor its piece (:func:`piece_surface`).

    With ``rings`` False the cap has no point of its own: a zigzag strip of triangles across the
    loop (the cap cannot move but with its rim: no flap of its own lags behind a fast limb).

    Returns ``None`` where the loop cannot be capped (fewer than 3 points, not once around
    ``c`` in its plane or turning back by more than 90 degrees between two points, or
    farther than ``max_planarity`` x its mean radius from the plane), else ``(new_points [M, 3], triangles [F, 3], blend)`` with the triangles indexing
    ``points`` (the loop's own) and ``len(points) + j`` (new point ``j``), wound so that every
    loop edge is traversed opposite to the piece, and ``blend``: ``(index [M, 2] of the loop
    points, share [M, 2], ring scale [M])`` from which a new point's attributes are
    interpolated: ``scale x lerp(loop) + (1 - scale) x mean(loop)``.
    """
    loop = np.asarray(loop, dtype=np.int64)
    n = loop.size
    if n < 3:
        return None
    p = np.asarray(points, dtype=np.float64)[loop]
    nxt = np.roll(p, -1, axis=0)
    seg = np.linalg.norm(nxt - p, axis=1)
    perimeter = float(seg.sum())
    if not perimeter > 0:
        return None
    c = ((p + nxt) * 0.5 * seg[:, None]).sum(axis=0) / perimeter
    normal = np.cross(p - c, nxt - c).sum(axis=0)
    ln = float(np.linalg.norm(normal))
    if not ln > 0:
        return None
    normal /= ln
    r = p - c
    radius = float(np.linalg.norm(r - np.outer(r @ normal, normal), axis=1).mean())
    if not radius > 0 or float(np.abs(r @ normal).max()) > max_planarity * radius:
        return None
    # once around c in the plane (a jagged loop may turn back a little on the way)
    e1 = r[np.argmax(np.linalg.norm(r, axis=1))]
    e1 = e1 - (e1 @ normal) * normal
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    ang = np.arctan2(r @ e2, r @ e1)
    turn = np.angle(np.exp(1j * (np.roll(ang, -1) - ang)))
    if abs(turn.sum() - 2.0 * math.pi) > 1e-6 or turn.min() < -0.5 * math.pi:
        return None
    if not rings:  # the loop's own points only: a zigzag strip across it
        tris, left, right, turn = [], 0, n - 1, True
        while right - left > 1:
            if turn:
                tris.append((left, left + 1, right))
                left += 1
            else:
                tris.append((left, right - 1, right))
                right -= 1
            turn = not turn
        tris = loop[np.array(tris, dtype=np.int64)]
        e = {(int(x), int(y)) for t in tris for x, y in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
        if (int(loop[0]), int(loop[1])) in e:
            tris = tris[:, ::-1]
        empty = np.zeros((0, 2), dtype=np.int64)
        return np.zeros((0, 3)), tris, (empty, np.zeros((0, 2)), np.zeros(0))
    u = np.concatenate([[0.0], np.cumsum(seg)[:-1]]) / perimeter
    rings = max(1, int(round(radius / (perimeter / n))))
    new_pts, idx, share, scale = [], [], [], []
    ring_ids = [np.arange(n)]  # ring 0: the loop's own points (local numbering 0..n-1)
    ring_u = [u]
    base = n
    smooth = p.copy()
    for k in range(1, rings):
        s = 1.0 - k / rings
        m = max(3, int(round(n * s)))
        at = (np.arange(m) + 0.5 * (k % 2)) / m
        for _ in range(2):  # each ring rounder than the last: a jagged loop's zigzag fades inwards
            smooth = 0.5 * smooth + 0.25 * (np.roll(smooth, 1, axis=0) + np.roll(smooth, -1, axis=0))
        q, j, w = _resample(smooth, u, at)
        new_pts.append(c + s * (q - c))
        idx.append(np.stack([j, (j + 1) % n], axis=1))
        share.append(np.stack([1.0 - w, w], axis=1))
        scale.append(np.full(m, s))
        ring_ids.append(base + np.arange(m))
        ring_u.append(at)
        base += m
    new_pts.append(c[None])
    idx.append(np.zeros((1, 2), dtype=np.int64))
    share.append(np.zeros((1, 2)))
    scale.append(np.zeros(1))
    centre = base
    tris = []
    for k in range(len(ring_ids)):
        a, ua = ring_ids[k], ring_u[k]
        if k + 1 == len(ring_ids):  # the fan to the centre
            tris += [(a[i], a[(i + 1) % len(a)], centre) for i in range(len(a))]
            break
        b, ub = ring_ids[k + 1], ring_u[k + 1]
        # zip: start both rings at their points nearest parameter 0, advance the one whose
        # next point comes first
        i = j = 0
        na, nb = len(a), len(b)
        j0 = int(np.argmin(np.minimum(ub, 1.0 - ub)))
        bb = np.roll(b, -j0)
        ubb = np.mod(np.roll(ub, -j0) - ub[j0] + ua[0], 1.0)
        ubb[0] = ua[0]
        while i < na or j < nb:
            ua_next = ua[i + 1] if i + 1 < na else 1.0 + ua[0]
            ub_next = ubb[j + 1] if j + 1 < nb else 1.0 + ubb[0]
            if j >= nb or (i < na and ua_next <= ub_next):
                tris.append((a[i % na], a[(i + 1) % na], bb[j % nb]))
                i += 1
            else:
                tris.append((a[i % na], bb[(j + 1) % nb], bb[j % nb]))
                j += 1
    tris = np.array(tris, dtype=np.int64)
    # local numbering: 0..n-1 the loop, n.. the new points; to the caller's
    local = np.concatenate([loop, len(points) + np.arange(base + 1 - n)])
    tris = local[tris]
    # wound opposite to the piece along the loop: the cap must traverse loop[1] -> loop[0]
    e = {(int(x), int(y)) for t in tris for x, y in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    if (int(loop[0]), int(loop[1])) in e:
        tris = tris[:, ::-1]
    new_pts = np.concatenate(new_pts)
    # relaxed with the loop held (a few passes towards the mean of their neighbours: a harmonic
    # disc, which irons out where a jagged loop's zigzag met the first ring)
    import scipy.sparse as sp

    m = len(new_pts)
    t_loc = np.empty_like(tris)
    lookup = {int(g): i for i, g in enumerate(local)}
    for a in range(3):
        t_loc[:, a] = [lookup[int(g)] for g in tris[:, a]]
    rows = np.concatenate([t_loc[:, 0], t_loc[:, 1], t_loc[:, 2], t_loc[:, 1], t_loc[:, 2], t_loc[:, 0]])
    cols = np.concatenate([t_loc[:, 1], t_loc[:, 2], t_loc[:, 0], t_loc[:, 0], t_loc[:, 1], t_loc[:, 2]])
    adj = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n + m, n + m))
    adj.data[:] = 1.0
    avg = (sp.diags(1.0 / np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1.0)) @ adj).tocsr()[n:]
    x = np.concatenate([p, new_pts])
    for _ in range(30):
        x[n:] = 0.5 * x[n:] + 0.5 * (avg @ x)
    new_pts = x[n:]
    return new_pts, tris, (np.concatenate(idx), np.concatenate(share), np.concatenate(scale))


# --------------------------------------------------------------------------------------------
# the surface
# --------------------------------------------------------------------------------------------
def _caps_cross(points: np.ndarray, triangles: np.ndarray, own: int) -> bool:
    """Whether a cap triangle (those from ``own`` on) crosses another triangle of the piece
    (the exact test of :func:`~warpskin.metrics.self_intersections`, neighbours skipped)."""
    used = np.unique(triangles)
    remap = np.full(len(points), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    pairs = self_intersections(points[used], remap[triangles])
    return bool(pairs.size and (pairs >= own).any())


def _signed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    p = points[triangles]
    c = points[np.unique(triangles)].mean(axis=0)
    return float(np.einsum("ij,ij->i", p[:, 0] - c, np.cross(p[:, 1] - c, p[:, 2] - c)).sum() / 6.0)


def _area(points: np.ndarray, triangles: np.ndarray) -> float:
    return surface_area(points, triangles)


@dataclass
class _Local:
    """One piece as a mesh of its own: ``points [n, 3]``, open ``triangles [f, 3]``, the class
    (welded written point) of each point or -1 (a decimated piece's new points), weights
    ``[n, J]`` and its caps ``[(new points, triangles into points + new, blend, loop)]``."""

    points: np.ndarray
    triangles: np.ndarray
    cls: np.ndarray
    weights: np.ndarray
    caps: list
    flipped: bool = False


def _close(local: _Local, prm: PieceParams) -> tuple[bool, dict]:
    """Cap every boundary loop of ``local`` (in place): strips across the loops (``cap_rings``
    False), or rings where a strip would cross the piece; whether it is then a closed body, and
    what was found (loops capped or not, fullness, cap share)."""
    info = {"loops": 0, "uncapped": 0}
    loops, simple = boundary_loops(local.triangles)
    if not simple:
        info["uncapped"] = -1
        return False, info
    made = pts = tris = None
    for rings in ((prm.cap_rings,) if prm.cap_rings else (False, True)):
        made, extra = [], []
        for loop in loops:
            cap = cap_loop(np.concatenate([local.points, *extra]) if extra else local.points, loop,
                           max_planarity=prm.max_planarity, rings=rings)
            if cap is None:
                made = None
                break
            made.append((*cap, loop))
            extra.append(cap[0])
        if made is None:
            continue
        pts = np.concatenate([local.points, *extra]) if extra else local.points
        tris = np.concatenate([local.triangles, *[c[1] for c in made]]) if made else local.triangles
        if made and _caps_cross(pts, tris, len(local.triangles)):
            made = None
            continue

        rep = mesh_edge_report(tris, len(pts))
        if not (rep["closed"] and rep["manifold"]):  # a strip's diagonal that the piece has already
            made = None
            continue
        break
    if made is None:
        info["uncapped"] = len(loops)
        return False, info
    info["loops"] = len(made)
    vol = _signed_volume(pts, tris)
    area = _area(pts, local.triangles)
    full = abs(vol) / max(_area(pts, tris) ** 1.5 / (6.0 * math.sqrt(math.pi)), 1e-300)
    share = _area(pts, tris[len(local.triangles):]) / max(area, 1e-300) if made else 0.0
    info.update({"fullness": round(float(full), 3), "cap_share": round(float(share), 3)})
    if full < prm.min_fullness or share > prm.max_cap_share:
        return False, info
    local.caps = made
    local.flipped = vol < 0
    return True, info


#: A character is reduced at about this height [m] (see :func:`_decimated`).
REDUCE_AT = 1.75


def _reduction_unit(height: float) -> float:
    """The factor that takes a character of ``height`` (its file's units) to about
    :data:`REDUCE_AT`: the power of ten physics takes its unit as
    (:func:`warpskin.units.metres_per_unit`), times the power of two nearest the rest in ratio.
    A file scaled by a power of two within a decade is reduced exactly alike (multiplying by a
    power of two changes no float but its exponent); one scaled by a power of ten (a 0.1 scale on
    its root) is reduced as the same file brought to metres (``--unit-scale``) is, float for float
    where that file's points are these times the same power of ten."""
    if not (height > 0.0) or not math.isfinite(height):
        return 1.0
    unit = metres_per_unit(height)
    return unit * 2.0 ** round(math.log2(REDUCE_AT / (height * unit)))


def _decimated(local: _Local, target: int, prm: PieceParams, device, unit: float = 1.0) -> _Local | None:
    """``local`` reduced to about ``target`` points by quadric edge collapse (``fast_simplification``,
    its open boundary kept), the weights of each new point those of its closest point on the
    piece as it was, capped again; ``None`` where the result is not a closed body once capped.

    The collapse's error thresholds are absolute (squared lengths), so it runs on the points
    times ``unit`` (:func:`_reduction_unit`: the character at about human height, scaled by a
    power of two): the same character in centimetres, decimetres or metres is reduced alike, and
    exactly alike where its sizes differ by a power of two."""
    import fast_simplification


    f = local.triangles
    goal = int(round(len(f) * target / max(len(local.points), 1)))
    if goal < 8 or goal >= len(f):
        return None
    pts, tris = fast_simplification.simplify(local.points * unit, f.astype(np.int64), target_count=goal,
                                             preserve_border=True)
    tris = np.asarray(tris, dtype=np.int64)
    pts = np.asarray(pts, dtype=np.float64) / unit
    rep = mesh_edge_report(tris, len(pts))
    if not rep["manifold"] or len(rep["unused_vertices"]):
        return None
    weights = _closest_weights(pts, local.points, f, local.weights, device)
    out = _Local(points=pts, triangles=tris, cls=np.full(len(pts), -1, dtype=np.int64), weights=weights, caps=[])
    ok, _ = _close(out, prm)
    return out if ok else None


def _closest_weights(query: np.ndarray, points: np.ndarray, triangles: np.ndarray, weights: np.ndarray,
                     device) -> np.ndarray:
    """The barycentric blend of ``weights`` (per point of the mesh ``points``, ``triangles``)
    at the closest point of the mesh to each of ``query``."""
    far = 2.0 * float(np.linalg.norm(np.ptp(np.concatenate([query, points]), axis=0))) + 1.0
    face, bary = closest_faces(query, points, triangles, far, device)
    return np.einsum("vc,vcj->vj", bary, weights[triangles[np.maximum(face, 0)]])


def _garments(locals_: dict, candidates: np.ndarray, count: int, max_gap: float, cover: float,
              device) -> tuple[np.ndarray, np.ndarray]:
    """Which candidate pieces are worn over others (see :class:`PieceParams` ``garment_cover``)
    and how far they lie from them (90th percentile of the covered points' gaps [m])."""
    import warp as wp


    garment = np.zeros(count, dtype=bool)
    gap = np.zeros(count)
    ids = [k for k in np.nonzero(candidates)[0]]
    if len(ids) < 2 or not max_gap > 0:
        return garment, gap
    pts = np.concatenate([locals_[k].points for k in ids])
    offsets = np.concatenate([[0], np.cumsum([len(locals_[k].points) for k in ids])])
    tris = np.concatenate([locals_[k].triangles + offsets[i] for i, k in enumerate(ids)])
    tri_owner = np.concatenate([np.full(len(locals_[k].triangles), k) for k in ids])
    normals = summed_face_normals(pts, tris)
    flip = np.concatenate([np.full(len(locals_[k].points), -1.0 if locals_[k].flipped else 1.0) for k in ids])
    normals *= flip[:, None] / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]]])
    start = 1e-3 * float(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1).mean())
    with wp.ScopedDevice(device):
        mesh = wp.Mesh(points=wp.array(pts.astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32))
        dist = wp.zeros(len(pts), dtype=wp.float32)
        face = wp.zeros(len(pts), dtype=wp.int32)
        wp.launch(k_pieces.first_hit_kernel, dim=len(pts),
                  inputs=[mesh.id, wp.array(pts.astype(np.float32), dtype=wp.vec3),
                          wp.array((-normals).astype(np.float32), dtype=wp.vec3), start, float(max_gap)],
                  outputs=[dist, face])
        dist, face = dist.numpy().astype(np.float64), face.numpy()
    owner = np.concatenate([np.full(len(locals_[k].points), k) for k in ids])
    hit = np.where(face >= 0, tri_owner[np.maximum(face, 0)], -1)
    under = (hit >= 0) & (hit != owner)
    for i, k in enumerate(ids):
        s = slice(offsets[i], offsets[i + 1])
        if under[s].mean() < cover:
            continue
        # worn over, not through: a piece that crosses what lies beneath it at rest (a hair bun
        # sunk into the skull) is a body part of its own
        beneath = np.unique(hit[s][under[s]])
        sel = (tri_owner == k) | np.isin(tri_owner, beneath)
        pairs = self_intersections(pts, tris[sel])
        owner_sel = tri_owner[sel]
        if pairs.size and np.any((owner_sel[pairs[:, 0]] == k) != (owner_sel[pairs[:, 1]] == k)):
            continue
        garment[k] = True
        gap[k] = float(np.percentile(dist[s][under[s]], 90))
    return garment, gap


def _small_assemblies(q: np.ndarray, piece: np.ndarray, mesh: np.ndarray, count: int, h: float,
                      prm: PieceParams) -> np.ndarray:
    """``[P]`` the pieces of small assemblies: two or more pieces of one mesh that touch (come
    within half an edge ``h`` of each other: a fist's knuckles on its palm) and together span less
    than ``prm.small_assembly`` edges; they are carried as a whole, as a rigid part is."""
    from scipy.sparse.csgraph import connected_components
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    out = np.zeros(count, dtype=bool)
    if count < 2 or not h > 0:
        return out
    pairs = cKDTree(q).query_pairs(0.5 * h, output_type="ndarray")
    a, b = piece[pairs[:, 0]], piece[pairs[:, 1]]
    keep = (a != b) & (mesh[pairs[:, 0]] == mesh[pairs[:, 1]])
    link = sp.csr_matrix((np.ones(int(keep.sum()) + count), (np.concatenate([a[keep], np.arange(count)]),
                                                             np.concatenate([b[keep], np.arange(count)]))),
                         shape=(count, count))
    _, label = connected_components(link, directed=False)
    for g in np.unique(label):
        members = np.nonzero(label == g)[0]
        if members.size < 2:
            continue
        pts = q[np.isin(piece, members)]
        if float(np.linalg.norm(np.ptp(pts, axis=0))) < prm.small_assembly * h:
            out[members] = True
    return out


def _thin(locals_: dict, candidates: np.ndarray, count: int, prm: PieceParams, device) -> tuple[np.ndarray, float]:
    """``[P]`` the candidate pieces thinner than ``prm.thin`` edges of the simulated surface they
    would make (see :class:`PieceParams`): each piece's median shape diameter
    (:func:`~warpskin.capture.shape_diameter` on its own closed surface) against the mean edge of
    the candidates, grown by the square root of the reduction ``max_vertices`` asks for; and that
    edge [m]."""
    out = np.zeros(count, dtype=bool)
    ids = list(np.nonzero(candidates)[0])
    if not ids:
        return out, 0.0
    total = sum(len(locals_[k].points) for k in ids)
    edges = []
    for k in ids:
        t = locals_[k].triangles
        x = locals_[k].points
        edges.append(np.linalg.norm(x[t[:, [0, 1, 2]]] - x[t[:, [1, 2, 0]]], axis=2).ravel())
    h = float(np.concatenate(edges).mean())
    if prm.max_vertices is not None and total > prm.max_vertices:
        h *= math.sqrt(total / prm.max_vertices)
    for k in ids:
        loc = locals_[k]
        pts = np.concatenate([loc.points, *[c[0] for c in loc.caps]]) if loc.caps else loc.points
        tris = np.concatenate([loc.triangles, *[c[1] for c in loc.caps]]) if loc.caps else loc.triangles
        if loc.flipped:
            tris = tris[:, ::-1]
        n = len(loc.points)
        d = shape_diameter(loc.points, vertex_normals(pts, tris)[:n], pts, tris, device=device)
        d = d[np.isfinite(d)]
        out[k] = d.size > 0 and float(np.median(d)) < prm.thin * h
    return out, h


def piece_surface(points: np.ndarray, triangles: np.ndarray, dense_weights: np.ndarray, mesh_of_point: np.ndarray,
                  mesh_names: list[str], *, joint_names: list[str] | None = None, params: PieceParams | None = None,
                  device=None) -> PieceSurface | None:
    """The closed simulation surface of a character's own pieces (see the module docstring).

    Args:
        points: ``[N, 3]`` every written point at rest [m] (stage space).
        triangles: ``[T, 3]`` their triangles (global indices).
        dense_weights: ``[N, J]`` their LBS weights.
        mesh_of_point: ``[N]`` the written mesh of every point.
        mesh_names: The written meshes' names (for the pieces' names).
        joint_names: The joints' names: a piece is named after its mesh and the joint that
            weighs most over it (``body/chest``), numbered where several share one.
        params: :class:`PieceParams`.
        device: Warp device of the rest-pose tests (winding numbers, closest points).

    Returns:
        The :class:`PieceSurface`, or ``None`` where no piece can be simulated.
    """
    prm = params or PieceParams()
    p = np.asarray(points, dtype=np.float64)
    w = np.asarray(dense_weights, dtype=np.float64)
    mesh_of = np.asarray(mesh_of_point, dtype=np.int64)
    first, cls, ctri, piece = welded_pieces(p, triangles, mesh_of)
    q = p[first]
    wq = w[first]
    count = int(piece.max()) + 1 if piece.size else 0
    height = float(np.ptp(p, axis=0).max()) if len(p) else 0.0
    tri_piece = piece[ctri[:, 0]]
    order = np.argsort(tri_piece, kind="stable")
    tri_start = np.searchsorted(tri_piece[order], np.arange(count + 1))
    names, closable, rigid, small = [], np.zeros(count, bool), np.zeros(count, bool), np.zeros(count, bool)
    locals_: dict[int, _Local] = {}
    notes: dict = {"capped_loops": 0, "uncapped_loops": 0, "shape": {}}
    dominant = np.argmax(wq, axis=1)
    strong = wq[np.arange(len(wq)), dominant] >= 0.999
    label_count: dict[str, int] = {}
    for k in range(count):
        members = np.nonzero(piece == k)[0]
        label = mesh_names[int(mesh_of[first[members[0]]])]
        if joint_names is not None:
            label += "/" + joint_names[int(np.argmax(wq[members].sum(axis=0)))]
        no = label_count.get(label, 0)
        label_count[label] = no + 1
        names.append(label if no == 0 else f"{label}#{no + 1}")
        rigid[k] = bool(strong[members].all() and np.unique(dominant[members]).size == 1)
        small[k] = float(np.linalg.norm(np.ptp(q[members], axis=0))) < prm.rigid_small * height
        sel_t = ctri[order[tri_start[k]:tri_start[k + 1]]]
        if members.size < prm.min_points or sel_t.shape[0] < 4:
            continue
        remap = np.full(len(q), -1, dtype=np.int64)
        remap[members] = np.arange(members.size)
        local = _Local(points=q[members], triangles=remap[sel_t], cls=members, weights=wq[members], caps=[])
        ok, info = _close(local, prm)
        notes["shape"][names[k]] = info
        notes["uncapped_loops"] += max(info["uncapped"], 0)
        if ok:
            closable[k] = True
            locals_[k] = local
    simulated = closable & ~(rigid & small)
    garment, gap = _garments(locals_, simulated, count, prm.garment_gap * height, prm.garment_cover, device)
    simulated &= ~garment
    thin, h_est = _thin(locals_, simulated, count, prm, device)
    simulated &= ~thin
    notes["thin"] = [names[k] for k in np.nonzero(thin)[0]]
    carried = _small_assemblies(q, piece, mesh_of[first], count, h_est, prm)
    simulated &= ~carried
    notes["carried"] = [names[k] for k in np.nonzero(carried)[0]]
    if not simulated.any():
        return None

    # a character denser than the layered model needs: each simulated piece reduced in
    # proportion (never below min_piece_points), its boundary kept
    sizes = {k: len(locals_[k].points) for k in np.nonzero(simulated)[0]}
    total = sum(sizes.values())
    decimated = np.zeros(count, dtype=bool)
    if prm.max_vertices is not None and total > prm.max_vertices:
        factor = prm.max_vertices / total
        for k, n in sizes.items():
            target = max(prm.min_piece_points, int(round(n * factor)))
            if target < 0.9 * n:
                out = _decimated(locals_[k], target, prm, device, _reduction_unit(height))
                if out is not None:
                    locals_[k] = out
                    decimated[k] = True
    for k in np.nonzero(simulated)[0]:
        notes["capped_loops"] += len(locals_[k].caps)
    notes["rigid_small"] = [names[k] for k in np.nonzero(closable & rigid & small)[0]]
    notes["attached"] = [names[k] for k in np.nonzero(~simulated)[0]]
    notes["garments"] = [names[k] for k in np.nonzero(garment)[0]]
    notes["simulated"] = [names[k] for k in np.nonzero(simulated)[0]]
    notes["decimated"] = [names[k] for k in np.nonzero(decimated)[0]]
    notes["points_before"] = int(total)
    notes["names"] = list(names)

    # the surface: every simulated piece's points, then all caps' points
    vertices, weights, vpiece, vcap, origin_cls = [], [], [], [], []
    base = 0
    own, cap_items = [], []
    for k in np.nonzero(simulated)[0]:
        loc = locals_[k]
        vertices.append(loc.points)
        weights.append(loc.weights)
        vpiece.append(np.full(len(loc.points), k))
        vcap.append(np.zeros(len(loc.points), dtype=bool))
        origin_cls.append(loc.cls)
        t = loc.triangles + base
        own.append(t[:, ::-1] if loc.flipped else t)
        cap_items.append((k, base, loc))
        base += len(loc.points)
    cap_tris = []
    for k, start, loc in cap_items:
        n = len(loc.points)
        offset = n
        for new, tris, (bi, bs, bscale), loop in loc.caps:
            local = tris.copy()
            is_new = local >= n
            local[~is_new] += start
            local[is_new] = base + (local[is_new] - offset)
            mean_w = loc.weights[loop].mean(axis=0)
            lw = loc.weights[loop[bi[:, 0]]] * bs[:, :1] + loc.weights[loop[bi[:, 1]]] * bs[:, 1:]
            weights.append(bscale[:, None] * lw + (1.0 - bscale[:, None]) * mean_w)
            vertices.append(new)
            vpiece.append(np.full(len(new), k))
            vcap.append(np.ones(len(new), dtype=bool))
            origin_cls.append(np.full(len(new), -1, dtype=np.int64))
            cap_tris.append(local[:, ::-1] if loc.flipped else local)
            base += len(new)
            offset += len(new)
    vertices = np.concatenate(vertices)
    weights = np.concatenate(weights)
    weights = np.clip(weights, 0.0, None)
    weights /= np.maximum(weights.sum(axis=1, keepdims=True), 1e-300)
    vertex_piece = np.concatenate(vpiece)
    cap = np.concatenate(vcap)
    origin_cls = np.concatenate(origin_cls)
    written_tris = np.concatenate(own)
    tris_all = np.concatenate([written_tris, *cap_tris]) if cap_tris else written_tris
    origin = np.where(origin_cls >= 0, first[np.maximum(origin_cls, 0)], -1)
    index = np.full(len(q), -1, dtype=np.int64)
    index[origin_cls[origin_cls >= 0]] = np.nonzero(origin_cls >= 0)[0]
    e = np.concatenate([tris_all[:, [0, 1]], tris_all[:, [1, 2]], tris_all[:, [2, 0]]])
    edge = float(np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1).mean())
    groups = _groups(vertices, tris_all, written_tris, vertex_piece, cap, count, simulated, edge, names, device)
    groups.depth_factor, bony = _bony_depths(vertices, weights, vertex_piece, q, piece, dominant, rigid & ~simulated,
                                             prm.bony_depth, prm.garment_gap * height)
    notes["bony_under"] = [names[k] for k in bony]
    notes["excluded_pairs"] = [(names[a], names[b]) for a, b in sorted({tuple(sorted(p)) for p in groups.seams})]
    return PieceSurface(vertices=vertices, triangles=tris_all, written_triangles=written_tris, dense_weights=weights,
                        origin=origin, vertex_piece=vertex_piece, cap=cap, piece_of_point=piece[cls],
                        vertex_of_point=index[cls], simulated=simulated, rigid=rigid, closable=closable,
                        decimated=decimated, garment=garment, gap=gap, carried=carried, small=small, groups=groups,
                        notes=notes, edge=edge)


def _bony_depths(vertices: np.ndarray, weights: np.ndarray, vertex_piece: np.ndarray, q: np.ndarray, piece: np.ndarray,
                 dominant: np.ndarray, rigid: np.ndarray, bony: float, reach: float) -> tuple[np.ndarray, list[int]]:
    """The factor on the layers' projection parameters of every simulated vertex ``[V]`` (see
    ``PieceParams.bony_depth``): for each piece ``r`` LBS moves rigidly on joint ``j`` (``rigid``:
    the caller passes the rigid pieces that are not simulated; its welded points ``q[piece ==
    r]``, ``s`` its half-diagonal, at most ``reach``, a worn piece's largest gap [m]: a belt
    thins the tissue under it, not the whole pelvis), every vertex of another piece whose
    strongest joint is ``j``, at distance ``d`` from the nearest point of ``r``, takes
    ``bony + (1 - bony) smoothstep(d; s, 2 s)``: ``bony`` within ``s``, 1 beyond ``2 s``; the
    smallest over the rigid pieces. Returns the factors and the rigid pieces that lowered any."""
    from scipy.spatial import cKDTree

    factor = np.ones(len(vertices))
    used: list[int] = []
    if bony >= 1.0:
        return factor, used
    strongest = np.argmax(weights, axis=1)
    for r in np.nonzero(rigid)[0]:
        members = np.nonzero(piece == r)[0]
        pts = q[members]
        size = min(0.5 * float(np.linalg.norm(np.ptp(pts, axis=0))), reach)
        sel = np.nonzero((strongest == dominant[members[0]]) & (vertex_piece != r))[0]
        if sel.size == 0 or not size > 0.0:
            continue
        d, _ = cKDTree(pts).query(vertices[sel])
        f = bony + (1.0 - bony) * smoothstep(d, size, 2.0 * size)
        if (f < 1.0).any():
            used.append(int(r))
        factor[sel] = np.minimum(factor[sel], f)
    return factor, used


def _groups(vertices: np.ndarray, triangles: np.ndarray, written: np.ndarray, vertex_piece: np.ndarray, cap: np.ndarray,
            count: int, simulated: np.ndarray, edge: float, names: list, device, seam: float = 1.5) -> SurfaceGroups:
    """The collision groups and the pairs of groups that never collide (see the module
    docstring). Where two simulated pieces meet at rest (their closed surfaces cross, touch, or
    one holds part of the other: a hand's wrist at the forearm's end, the head's neck inside the
    body's, a bun sunk into the skull) the vertices of each within ``seam`` mean edges of the
    other, or inside it, form a seam zone that never collides with the other piece; the rest of
    the two collide as any two surfaces do (the hand's fingers and the thigh). A cap collides
    with nothing outside its own piece.

    Groups: ``0 .. P-1`` the pieces, ``P .. 2P-1`` their caps, then one per seam zone."""
    import warp as wp


    group = np.where(cap, count + vertex_piece, vertex_piece).astype(np.int64)
    seams: list[tuple[int, int]] = []  # (piece, partner) of each seam group
    sim = np.nonzero(simulated)[0]
    if sim.size > 1:
        with wp.ScopedDevice(device):
            pts = wp.array(vertices.astype(np.float32), dtype=wp.vec3)
            far = 2.0 * float(np.linalg.norm(np.ptp(vertices, axis=0))) + 1.0
            flag = wp.zeros(len(vertices), dtype=wp.int32)
            for k in sim:
                tris = triangles[vertex_piece[triangles[:, 0]] == k]
                mesh = wp.Mesh(points=pts, indices=wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32),
                               support_winding_number=True)
                wp.launch(k_pieces.near_or_inside_kernel, dim=len(vertices), inputs=[mesh.id, pts, seam * edge, far],
                          outputs=[flag])
                hit = flag.numpy().astype(bool) & (vertex_piece != k) & ~cap & (group < count)
                for j in np.unique(vertex_piece[hit]):
                    group[hit & (vertex_piece == j)] = 2 * count + len(seams)
                    seams.append((int(j), int(k)))
    g = 2 * count + len(seams)
    owner = np.concatenate([np.arange(count), np.arange(count), [a for a, _ in seams]]).astype(np.int64)
    excluded = np.zeros((g, g), dtype=bool)
    is_cap = np.zeros(g, dtype=bool)
    is_cap[count:2 * count] = True
    # a cap: with every group of another piece
    other = owner[:, None] != owner[None, :]
    excluded |= (is_cap[:, None] | is_cap[None, :]) & other
    # a seam zone: with every group of its partner, both ways
    for s, (a, b) in enumerate(seams):
        sg = 2 * count + s
        partner = owner == b
        excluded[sg, partner] = excluded[partner, sg] = True
    np.fill_diagonal(excluded, False)
    return SurfaceGroups(group=group, excluded=excluded, names=list(names), owner=owner, seams=seams)

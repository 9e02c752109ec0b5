"""Muscles on the written surface: ``warpskin pop``'s default for a rig without examples.

The muscles swell the **written** meshes themselves, over the physical skin. A cage is coarser
and deeper than the character it carries and the capture carries only part of its bulge, and a
pop of the multi-layer model's muscle layer moves skin far from the muscle through the volume
constraints; on the written surface the pop is where the muscle is, by the paper's method (Son &
Han 2007): each group's clenched example is its rest-pose swelling (below); the normal skin is
the physical skin (simulated directly, or carried by the cage); every written point follows its
goal, normal plus the activated swelling, with the goal-driven vibration while clenching and the
monotone relaxation afterwards (eqs. 1-4, one Warp kernel per solver step,
:func:`warpskin.kernels.popping.surface_vibration_kernel`).

The swelling of a group of bones, per written point ``x`` whose dominant joint is one of them
(``f`` the point's foot on the bone's centre line, ``t`` in [0, 1] its place along the bone,
:func:`bone_coordinates`), along the surface's normal eased over ``_EASE`` rings where it faces
away from the bone, turning to the radial direction ``x - f`` where the normal turns along the
bone or towards it (a cap), by

    b(x) = min(swell * depth, cap * length) * belly(t),
    depth = bone * min(|x - f|, thickness / 2)

(``belly``: :func:`belly_profile`, 1 over the middle of the bone, none near the joints)

(``bone``: the model's bone-layer fraction, so ``depth`` is the fat-plus-muscle depth the
layered model gives that point, but no more than half the part is thick, the shape diameter
along the inward normal, eased over the group's skin; ``length``: the bone's). Points one
mesh holds at one position (seams, flat shading) are one point of its surface. Then, in this
order:

* **clearance**: none where another piece ahead of the swelling (within 60 degrees of its
  direction) is nearer than the belly's height there at rest (a limb's end inside a ball
  joint), all of it beyond three times that height (the thinning: any piece, three times the
  belly's peak); pieces whose open borders meet (a surface cut into pieces along its seams)
  count as one;
* **volume**: a thinning takes back the swelling's flux ``sum_i A_i n_i . d_i`` (area-weighted
  normals: its volume to first order) on every connected piece, lying on the neighbourhood's
  skin away from every group's belly (the ends of the group's bones, their parents' and
  children's skin where those carry most of it,
  :func:`~warpskin.popping.muscles.thinning_reach`), at most a quarter of the belly's peak
  deep (a piece with little skin to thin keeps part of the gain);
* **stretch**: the swelling is scaled down locally until no edge is stretched or shortened by
  more than a quarter of its length (a coarse piece is not stretched across one edge) and no
  triangle keeps less than half its area facing as at rest, each group's and all groups'
  together.

The skin beyond the groups' bones, their parents and children never moves. While the skin is
written, each offset also stops at half the gap to any surface it would meet in that frame,
the offsets make no crossing the frame has not without them (but for one next to a crossing
it has: a limb through the piece over it in the source, moved by at most one ring), and the
offsets, one per point of the surface (a split corner's copies move as one), keep
every edge within the written-quality band (``STRAIN_LIMIT``) and every facet unfolded
against the frame without the pop (:meth:`SurfacePop.offsets`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import scipy.sparse as sp
import warp as wp

from ..capture import shape_diameter, welded_pieces
from ..collision import skin_edges
from ..device import resolve_device
from ..errors import SceneError
from ..kernels import popping as _k
from ..mesh import vertex_normals
from ..metrics import PairQuery, triangle_pairs_intersect
from ..preprocess.bone_heat import vertex_areas
from ..preprocess.fast_summation import vertex_adjacency
from ..quality import STRAIN_LIMIT
from .activation import clench_table
from .muscles import SWELL_CAP, Muscle, neighbourhood, thinning_reach

__all__ = ["DEFAULT_SURFACE_SWELL", "belly_profile", "surface_swelling", "bone_coordinates", "seam_points", "belly_of_groups", "SurfacePop"]

DEFAULT_SURFACE_SWELL = 0.4
"""Peak swelling of a belly on the written surface, as a share of the fat-plus-muscle depth
(over the middle of the bone; the stretch limit and the clearance may take some of it)."""
_THIN = 0.25  # the thinning is at most this share of the belly's peak
_BARE = 0.05  # a bone with less of its surface than this over its middle pops on the surface it carries
_PRESSED = 0.6  # a belly pressed on one side swells at most this much more on its free side
_EASE = 4  # passes of the ring mean that ease the depth over a group's skin
_AHEAD = 0.5  # cos of the half-angle of the cone ahead of a swelling point in which another piece holds it
_AHEAD_K = 256  # the most neighbours searched for one ahead of a point
_KEEP = 0.5  # a triangle keeps at least this share of its area along its rest normal
_STRETCH = 0.25  # the swelling stretches or shortens an edge by at most this share of its length
# what is written may ring past the rest-pose limits above (the vibration overshoots its goal),
# but no edge leaves the band that the written-quality check counts as strained (longer than
# STRAIN_LIMIT x, shorter than its inverse) and no facet folds
_WRITE_STRETCH = STRAIN_LIMIT - 1.0
_WRITE_SHORTEN = 1.0 - 1.0 / STRAIN_LIMIT
_WRITE_KEEP = 0.3
# the shares of a pair's offsets the untangle tries, the largest that keeps it apart kept: a
# pair may cross at some shares and not at larger ones (two pieces that slide past each other)
_UNTANGLE_SHARES = np.array([0.02, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95])


def belly_profile(t: np.ndarray) -> np.ndarray:
    """The belly along the bone, ``t`` in [0, 1]: 0 up to 10 % of the bone and from 90 %, 1
    over its middle (30 % to 70 %), smoothstep ramps between: a long fusiform belly, none at the
    joints, whose middle stands out as far as its peak (the stretch limit caps the peak)."""
    t = np.asarray(t, dtype=np.float64)
    return _smooth(np.clip((t - 0.1) / 0.2, 0.0, 1.0)) * _smooth(np.clip((0.9 - t) / 0.2, 0.0, 1.0))


def _area_normals(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[N, 3]`` a third of the summed (area x unit normal) of each point's triangles [m^2]."""
    p = points[triangles]
    cross = 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    out = np.zeros_like(points)
    for k in range(3):
        np.add.at(out, triangles[:, k], cross / 3.0)
    return out


def _smooth(x: np.ndarray) -> np.ndarray:
    """The smoothstep ``3 x^2 - 2 x^3`` of ``x`` in [0, 1]."""
    return x * x * (3.0 - 2.0 * x)


def _stretch_limit(points: np.ndarray, field: np.ndarray, edges: np.ndarray, lengths: np.ndarray,
                   ring: sp.csr_matrix, triangles: np.ndarray, passes: int = 8, stretch: float | None = None,
                   shorten: float | None = None, keep: float | None = None) -> np.ndarray:
    """``[N]`` factors in [0, 1] such that ``points + field * factor`` (``[N, 3]`` [m])
    stretches no edge (``edges [E, 2]``, rest ``lengths [E]`` [m]) by more than ``stretch``
    of its length nor shortens it by more than ``shorten`` (both default ``_STRETCH``; to
    within what ``passes`` passes reach), and keeps every one of ``triangles [T, 3]`` facing
    as at rest with at least ``keep`` (default ``_KEEP``) of its area along its rest normal
    (always): a bulge no steeper than the mesh can carry, so a coarse piece is not stretched
    across one edge and a sliver does not turn over.

    Each pass takes every point's factor down by what its worst edge asks (the stretch is
    nearly linear in the factor), eased over its ring (``ring``: adjacency, self included);
    then a triangle that folds gets one factor on its three points, the largest that keeps it
    (its kept area is a quadratic in a common factor, solved on a grid). Triangles that still
    fold after the passes (a corner cut again by a neighbour) are kept by their points not
    moving."""
    stretch = _STRETCH if stretch is None else stretch
    shorten = stretch if shorten is None else shorten
    keep = _KEEP if keep is None else keep
    n = len(field)
    factor = np.ones(n)
    mean = sp.diags(1.0 / np.asarray(ring.sum(axis=1)).ravel()) @ ring
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    e1, e2 = points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]]
    normal = np.cross(e1, e2)
    area2 = np.einsum("ij,ij->i", normal, normal)
    live = area2 > 0.0
    tris, e1, e2, normal, area2 = tris[live], e1[live], e2[live], normal[live], area2[live]
    grid = np.linspace(0.0, 1.0, 17)

    def kept(which: np.ndarray, moves: np.ndarray, s: np.ndarray) -> np.ndarray:
        """``[K, S]`` the area along its rest normal of each triangle ``which`` (``[K]`` bool
        or indices), as a share of its rest area, with its points moved by ``moves [K, 3, 3]``
        times each of ``s [S]``."""
        a, b, m = e1[which], e2[which], normal[which]
        f1, f2 = moves[:, 1] - moves[:, 0], moves[:, 2] - moves[:, 0]
        c1 = np.einsum("ij,ij->i", np.cross(a, f2) + np.cross(f1, b), m) / area2[which]
        c2 = np.einsum("ij,ij->i", np.cross(f1, f2), m) / area2[which]
        return 1.0 + c1[:, None] * s + c2[:, None] * s ** 2

    def folding() -> np.ndarray:
        return kept(slice(None), (field * factor[:, None])[tris], np.ones(1))[:, 0] < keep

    for _ in range(passes):
        x = points + field * factor[:, None]
        change = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / lengths - 1.0
        limit = np.where(change > 0.0, stretch, shorten)
        change = np.abs(change)
        allowed = np.where(change > limit, limit / np.maximum(change, 1e-30), np.inf)
        fold = folding()
        if allowed.min() >= 1.0 - 1e-9 and not fold.any():
            break
        cut = np.ones(n)
        np.minimum.at(cut, edges[:, 0], allowed)
        np.minimum.at(cut, edges[:, 1], allowed)
        cut = np.minimum(cut, mean @ cut)  # the neighbours of a cut point give a little too
        factor *= np.clip(cut, 0.0, 1.0)
        fold = folding()
        if fold.any():  # one common factor on a folding triangle's points
            t = tris[fold]
            common = factor[t].min(axis=1)
            ok = kept(fold, field[t] * common[:, None, None], grid) >= keep  # [F, S]
            largest = grid[np.where(ok.all(axis=1), len(grid), np.argmin(ok, axis=1)) - 1]
            for k in range(3):
                np.minimum.at(factor, t[:, k], common * largest)
    fold = folding()
    while fold.any():  # still folding: its points do not move
        factor[tris[fold].ravel()] = 0.0
        fold = folding()
    return factor


def _seams(points: np.ndarray, triangles: np.ndarray, piece: np.ndarray, *, share: float = 0.25,
           least: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Where connected pieces continue one another: two pieces whose open borders meet (at
    least ``least`` border points of one within ``share`` of the median edge of a border point
    of the other: a surface cut into pieces along its seams). Returns ``(merged [N], seam
    [N])``: the pieces with those merged, and the border points that meet another piece's."""
    from scipy.spatial import cKDTree
    from scipy.sparse.csgraph import connected_components

    seam = np.zeros(len(points), dtype=bool)
    e = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    edges, count = np.unique(e, axis=0, return_counts=True)
    border = np.unique(edges[count == 1].ravel())
    if border.size == 0 or np.unique(piece).size < 2:
        return piece, seam
    tol = share * float(np.median(np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)))
    pairs = np.array(sorted(cKDTree(points[border]).query_pairs(tol)), dtype=np.int64).reshape(-1, 2)
    a, b = piece[border[pairs[:, 0]]], piece[border[pairs[:, 1]]]
    other = a != b
    if not other.any():
        return piece, seam
    key, inverse, times = np.unique(np.sort(np.stack([a[other], b[other]], axis=1), axis=1), axis=0,
                                    return_inverse=True, return_counts=True)
    kept = times[inverse.ravel()] >= least
    seam[border[pairs[other][kept].ravel()]] = True
    key = key[times >= least]
    m = int(piece.max()) + 1
    join = sp.csr_matrix((np.ones(len(key)), (key[:, 0], key[:, 1])), shape=(m, m))
    _, merged = connected_components(join, directed=False)
    return merged[piece], seam


def _welded_surface(points: np.ndarray, triangles: np.ndarray, mesh_of_point: np.ndarray | None):
    """The written points as one surface: each mesh's points welded by position (seams, flat
    shading; :func:`~warpskin.capture.welded_pieces`). Returns ``(first [C], cls [N], triangles
    over the welded points, piece [C], seam [C])``: pieces whose borders meet merged, and the
    border points where they meet (:func:`_seams`)."""
    every = np.asarray(points, dtype=np.float64)
    mesh = np.zeros(len(every), dtype=np.int64) if mesh_of_point is None else np.asarray(mesh_of_point)
    first, cls, tris, piece = welded_pieces(every, triangles, mesh)
    piece, seam = _seams(every[first], tris, piece)
    return first, cls, tris, piece, seam


def seam_points(points: np.ndarray, triangles: np.ndarray, mesh_of_point: np.ndarray | None = None) -> np.ndarray:
    """``[N]`` bool: the points on a seam where two pieces of the surface meet (:func:`_seams`,
    after welding each mesh's points by position)."""
    _, cls, _, _, seam = _welded_surface(points, triangles, mesh_of_point)
    return seam[cls]


def _clearance(points: np.ndarray, triangles: np.ndarray, piece: np.ndarray, reach: float,
               directions: np.ndarray | None = None) -> np.ndarray:
    """``[N]`` each point's distance to the nearest other connected piece [m], ``inf`` where
    none is within ``reach`` [m]: to samples of its triangles (a barycentric grid on each, of
    4 to 64 steps a side, fine enough that samples lie at most ``reach / 12`` apart where 64
    steps allow), the distance to its surface to within half that spacing. Each piece is
    queried against the other pieces' samples in its box grown by ``reach``.

    With ``directions`` (``[N, 3]`` unit), only the samples ahead of each point count: those
    within ``acos(_AHEAD)`` of its direction, what the point moving along it could run into
    (a piece beside it, a sleeve's rim past the belly, does not hold it back)."""
    from scipy.spatial import cKDTree

    out = np.full(len(points), np.inf)
    pieces = np.unique(piece)
    if pieces.size < 2 or not reach > 0.0:
        return out
    corners = points[triangles]  # [T, 3, 3]
    longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
    steps = np.clip(np.ceil(longest / (reach / 12.0)), 4, 64).astype(np.int64)
    samples, owner = [], []
    for grid in np.unique(steps):
        which = steps == grid
        bary = np.array([(i, j, grid - i - j) for i in range(grid + 1) for j in range(grid + 1 - i)],
                        dtype=np.float64) / grid
        samples.append(np.einsum("sc,tcd->tsd", bary, corners[which]).reshape(-1, 3))
        owner.append(np.repeat(piece[triangles[which, 0]], len(bary)))
    samples, owner = np.concatenate(samples), np.concatenate(owner)
    for k in pieces:
        mine = np.flatnonzero(piece == k)
        lo, hi = points[mine].min(axis=0) - reach, points[mine].max(axis=0) + reach
        near = (owner != k) & np.all((samples >= lo) & (samples <= hi), axis=1)
        if not near.any():
            continue
        tree = cKDTree(samples[near])
        if directions is None:
            out[mine] = tree.query(points[mine], distance_upper_bound=reach)[0]
            continue
        # the nearest sample ahead: the neighbours come nearest first, so a point is done at
        # its first one ahead, or once its k nearest reach past ``reach``; else k grows, up to
        # _AHEAD_K, past which the k-th neighbour's distance stands in (a lower bound: the
        # point is held back as if a piece were there)
        others, todo, count = samples[near], mine, 16
        while todo.size:
            count = min(count, len(others))
            d, i = tree.query(points[todo], k=count, distance_upper_bound=reach)
            d, i = d.reshape(len(todo), -1), i.reshape(len(todo), -1)
            found = np.isfinite(d)
            toward = others[np.where(found, i, 0)] - points[todo][:, None]
            ahead = found & (np.einsum("pkc,pc->pk", toward, directions[todo]) >= _AHEAD * d)
            out[todo] = np.where(ahead, d, np.inf).min(axis=1)
            left = ~(ahead.any(axis=1) | ~found[:, -1] | (count >= len(others)))
            if count >= _AHEAD_K:
                out[todo[left]] = d[left, -1]
                break
            todo = todo[left]
            count *= 4
    return out


def surface_swelling(points: np.ndarray, triangles: np.ndarray, dense_weights: np.ndarray, bones, parents: np.ndarray,
                     groups: Sequence[tuple[str, Sequence[int]]], *, swell: float,
                     bone_fraction: float = 0.8, mesh_of_point: np.ndarray | None = None,
                     device=None) -> tuple[list[Muscle], np.ndarray]:
    """The muscle groups of written meshes and their rest-pose swellings (module docstring).

    Args:
        points: ``[N, 3]`` every written point at rest [m] (a
            :class:`~warpskin.preprocess.cage.CharacterSoup`'s).
        triangles: ``[T, 3]`` their triangles.
        dense_weights: ``[N, J]`` their LBS weights.
        bones: :class:`~warpskin.preprocess.bones.Bones` in the points' space.
        parents: ``[J]`` the skeleton's parents (-1: a root).
        groups: ``[(name, joint indices)]`` the muscle groups
            (:func:`~warpskin.popping.muscles.groups_of_model`).
        swell: Peak swelling as a share of the fat-plus-muscle depth, in (0, 2].
        bone_fraction: The bone layer's place from skin (0) to the bone's centre line (1).
        mesh_of_point: ``[N]`` each point's mesh: points of one mesh at one position are one
            point of its surface (seams, flat shading); default: one mesh.
        device: Warp device of the shape-diameter rays.

    Returns:
        ``(muscles, displacements [G, N, 3] [m])``: each group's rest-pose swelling of every
        point (zero outside its neighbourhood).

    Raises:
        SceneError: a bad ``swell``.
    """
    if not (isinstance(swell, (int, float)) and 0.0 < swell <= 2.0):
        raise SceneError(f"swell must be in (0, 2] (a share of the tissue depth), got {swell!r}")
    # one point per position within a mesh (a flat-shaded file splits every facet), so that
    # rings, pieces and edges are the surface's
    first, cls, tris, piece, _ = _welded_surface(points, triangles, mesh_of_point)
    points = np.asarray(points, dtype=np.float64)[first]
    w = np.asarray(dense_weights, dtype=np.float64)[first]
    n = len(points)
    names = list(bones.joint_names)
    dominant = np.argmax(w, axis=1)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    t, radial = bone_coordinates(points, dominant, bones, vertex_areas(points, tris, kind="barycentric"))
    r = np.linalg.norm(radial, axis=1)
    ok = r > 1e-9 * max(diagonal, 1e-12)
    direction = np.zeros_like(points)
    direction[ok] = radial[ok] / r[ok, None]
    normals = vertex_normals(points, tris)
    # the skin swells along its own normal where that faces away from the bone (an offset of
    # the surface: a box-like shell moves off its faces, not diagonally through them), turning
    # to the radial direction where the normal turns along the bone or towards it (a cap)
    ring = (vertex_adjacency(tris, n) + sp.identity(n, format="csr")).astype(np.float64)
    eased = normals
    for _ in range(_EASE):  # eased over a few rings: a sharp corner's two sides do not part
        eased = ring @ eased
    eased /= np.maximum(np.linalg.norm(eased, axis=1), 1e-30)[:, None]
    facing = np.einsum("ij,ij->i", eased, direction)
    s = _smooth(np.clip(facing / 0.5, 0.0, 1.0))[:, None]
    blend = s * eased + (1.0 - s) * direction
    size = np.linalg.norm(blend, axis=1)
    direction = np.where((size > 1e-9)[:, None] & ok[:, None], blend / np.maximum(size, 1e-30)[:, None], direction)
    # the tissue is no deeper than half the part is thick (a hand far from its forearm's line,
    # a stylised rig's shell), the shape diameter along the inward normal
    thick = shape_diameter(points, normals, points, tris, device=device)
    depth = bone_fraction * np.minimum(r, 0.5 * thick)
    profile = belly_profile(t)
    length = bones.length[dominant]
    flux = np.einsum("ij,ij->i", _area_normals(points, tris), direction)  # per unit radial move [m^2]
    # the fades below need the distance to three belly peaks at most: ahead of the swelling
    # for the belly (outward), any way for the thinning
    clear = _clearance(points, tris, piece, 3.0 * swell * float(depth.max(initial=0.0)))
    ahead = _clearance(points, tris, piece, 3.0 * swell * float(depth.max(initial=0.0)), directions=direction)
    edges, _ = skin_edges(tris)
    lengths = np.linalg.norm(points[edges[:, 0]] - points[edges[:, 1]], axis=1)
    edges, lengths = edges[lengths > 0.0], lengths[lengths > 0.0]
    muscles, fields = [], []
    # every group's bones: a thinning stays off all bellies, so groups that pop together do not
    # take back each other's swelling
    bellied = np.isin(dominant, [j for _, group in groups for j in group]) & ok
    for name, group in groups:
        on = np.isin(dominant, group) & ok
        # the depth eased over the group's skin: a shape diameter that jumps between
        # neighbours (a stylised rig's shell over inner parts) would make a jagged belly
        level = np.where(on, depth, 0.0)
        for _ in range(_EASE):
            level = np.where(on, (ring @ level) / np.maximum(ring @ on.astype(np.float64), 1.0), 0.0)
        amount = np.where(on, np.minimum(swell * level, SWELL_CAP * length) * profile, 0.0)
        hood = neighbourhood(group, parents)
        near = thinning_reach(w[:, hood].sum(axis=1), np.isin(dominant, hood), ring) * ok
        shape = near * np.where(bellied, 1.0 - np.clip(profile, 0.0, 1.0), 1.0)  # away from the bellies
        # none where another piece ahead of the swelling is nearer than the belly's height at
        # rest (a limb's end in a ball joint, an arm under its sleeve): moving there would cross
        # that piece's surface; full beyond three times that height. The thinning likewise,
        # with pieces in any direction
        reach = max(float(np.abs(amount).max()), 1e-12)
        local = np.maximum(np.abs(amount), 1e-3 * reach)  # the belly by its own height there
        amount = amount * _smooth(np.clip(ahead / local - 1.0, 0.0, 2.0) / 2.0)
        shape = shape * _smooth(np.clip(clear / reach - 1.0, 0.0, 2.0) / 2.0)
        amount = amount * _stretch_limit(points, amount[:, None] * direction, edges, lengths, ring, tris)
        gain = np.bincount(piece, amount * flux, minlength=piece.max() + 1)
        cost = np.bincount(piece, shape * flux, minlength=piece.max() + 1)
        # per piece, the thinning's depth m that makes the flux zero, at most a quarter of the
        # belly's peak (a piece with little skin to thin keeps part of the gain: a deeper
        # thinning there would crease it)
        m = np.where(cost > 1e-12 * diagonal ** 2, gain / np.where(cost > 0.0, cost, 1.0), 0.0)
        m = np.clip(m, 0.0, _THIN * amount.max() if amount.size else 0.0)
        field = (amount - m[piece] * shape)[:, None] * direction
        field *= _stretch_limit(points, field, edges, lengths, ring, tris)[:, None]
        moved = np.linalg.norm(field, axis=1)
        belly = on & (t > 0.3) & (t < 0.7)  # the depth there: under the belly (belly_of_groups)
        where = belly if belly.any() else on
        muscles.append(Muscle(name, [names[j] for j in group], int(np.count_nonzero(moved[cls] > 0.0)),
                              float(np.median(depth[where])) if where.any() else 0.0, float(moved.max())))
        fields.append(field)
    # groups that pop together: their sum keeps the same limit (two bones side by side, a
    # palm's metacarpals, swell towards each other)
    together = np.stack(fields)
    together *= _stretch_limit(points, together.sum(axis=0), edges, lengths, ring, tris)[None, :, None]
    return muscles, together[:, cls]


def _quantiles(x: np.ndarray, weight: np.ndarray, q) -> np.ndarray:
    """The ``q`` quantiles (in [0, 1]) of ``x`` weighted by ``weight`` (no weight: unweighted)."""
    order = np.argsort(x)
    x, wt = x[order], np.asarray(weight, dtype=np.float64)[order]
    if not wt.sum() > 0.0:
        wt = np.ones_like(x)
    cdf = np.cumsum(wt) - 0.5 * wt
    return np.interp(np.asarray(q, dtype=np.float64) * wt.sum(), cdf, x)


def bone_coordinates(points: np.ndarray, dominant: np.ndarray, bones,
                     area: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where each point lies along its dominant joint's bone.

    Returns ``(t [N], radial [N, 3])``: ``t`` in [0, 1] the place of the point's foot on the
    bone's centre line, 0 at its joint and 1 at its end (clamped); ``radial`` the point less its
    foot on the bone's (unbounded) line [m], square to the bone everywhere. A bone whose
    surface (its points weighted by ``area [N]``; default: not checked) has less than
    ``_BARE`` of its area over the bone's middle (30-70 %: a stylised rig's limb mesh bunched
    at one end, a stick to a ball) is measured along the surface it carries instead: ``t``
    piecewise linear from its 2nd percentile (0) through its median (0.5) to its 98th (1), so
    the belly sits on that surface."""
    p = np.asarray(points, dtype=np.float64)
    a, d = bones.start[dominant], bones.end[dominant] - bones.start[dominant]
    dd = np.einsum("ij,ij->i", d, d)
    raw = np.where(dd > 0.0, np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0.0, dd, 1.0), 0.0)
    t = np.clip(raw, 0.0, 1.0)
    if area is not None:
        area = np.asarray(area, dtype=np.float64)
        for k in np.unique(dominant):
            mine = dominant == k
            middle = mine & (raw > 0.3) & (raw < 0.7)
            if area[middle].sum() >= _BARE * area[mine].sum():
                continue
            lo, mid, hi = _quantiles(raw[mine], area[mine], [0.02, 0.5, 0.98])
            if lo < mid < hi:
                x = raw[mine] - mid
                t[mine] = np.clip(0.5 + 0.5 * np.where(x < 0.0, x / (mid - lo), x / (hi - mid)), 0.0, 1.0)
    return t, p - (a + raw[:, None] * d)


def belly_of_groups(points: np.ndarray, triangles: np.ndarray, dense_weights: np.ndarray, bones,
                    groups) -> np.ndarray:
    """``[G, N]`` bool: the points on the middle of each group's bones (dominant joint in the
    group, between 30 % and 70 % along the bone, :func:`bone_coordinates` with the areas of
    ``triangles``), as :func:`~warpskin.popping.report.belly_of_bones` marks a skin's."""
    dominant = np.argmax(np.asarray(dense_weights), axis=1)
    t, _ = bone_coordinates(points, dominant, bones, vertex_areas(points, triangles, kind="barycentric"))
    middle = (t > 0.3) & (t < 0.7)
    return np.array([np.isin(dominant, list(group)) & middle for _, group in groups], dtype=bool).reshape(len(groups), -1)


class SurfacePop:
    """The goal-driven popping offset of written points (module docstring), stepped with the
    physics and added to what is written.

    Args:
        displacements: ``[G, N, 3]`` each group's rest-pose swelling [m] (:func:`surface_swelling`).
        dense_weights: ``[N, J]`` the points' LBS weights.
        rest_matrices: ``[J, 4, 4]`` the skinning matrices of the rest pose the points are in.
        step_times: Clip time at the end of every solver step [s], ``[S]``.
        activation: ``activation(t) -> [G]`` in [0, 1] at clip time ``t``.
        h: Step length [s]; ``beta * h <= 1``.
        alpha_min, beta, threshold: The paper's stiffness at the largest disparity (eq. 3),
            relaxation rate [1/s] and snap distance [m] (eq. 4).
        triangles: ``[T, 3]`` the written surface's triangles: with them :meth:`offsets`
            keeps the written skin clear of itself and its facets whole.
        margin, start: The clearance's margin and its rays' start [m] (:meth:`offsets`).
        points: ``[N, 3]`` the points at rest [m]: their areas (the pressed belly) and,
            with ``triangles``, the welded surface whose facets the offsets keep.
        seams: ``[N]`` bool, the points where two pieces of the surface meet
            (:func:`seam_points`).
        mesh_of_point: ``[N]`` each point's mesh: one mesh's points at one position are one
            point of its surface (default: one mesh).
        device: Warp device.

    Every array is allocated here; a step launches one kernel with the step's index (its
    activations were uploaded once).
    """

    def __init__(self, displacements: np.ndarray, dense_weights: np.ndarray, rest_matrices: np.ndarray,
                 step_times: Sequence[float], activation: Callable[[float], np.ndarray], *, h: float,
                 alpha_min: float, beta: float, threshold: float = 1e-4, triangles: np.ndarray | None = None,
                 margin: float = 0.0, start: float = 1e-5, points: np.ndarray | None = None,
                 seams: np.ndarray | None = None, mesh_of_point: np.ndarray | None = None, device=None) -> None:
        d = np.asarray(displacements, dtype=np.float64)
        g, n = d.shape[:2]
        self.point_count = n
        self.margin, self._start = float(margin), float(start)
        self.moved = np.nonzero(np.linalg.norm(d, axis=2).max(axis=0) > 0.0)[0]  # the points it may move
        self.weights = np.asarray(dense_weights, dtype=np.float64)[self.moved]
        self._rest_inv = np.linalg.inv(self._linear(rest_matrices))  # [P, 3, 3]
        acts = np.array([np.asarray(activation(float(t)), dtype=np.float64).reshape(g) for t in step_times]) \
            if len(step_times) else np.zeros((0, g))
        if acts.size and not (np.all(acts >= 0.0) and np.all(acts <= 1.0)):
            raise SceneError(f"popping: activations must be in [0, 1], got {acts.min():.3g} to {acts.max():.3g}")
        if not (h > 0.0 and beta * h <= 1.0 + 1e-12):
            raise SceneError(f"popping: step {h!r} s needs beta * dt <= 1 (beta = {beta} /s)")
        self.steps = len(acts)
        self.h, self.alpha_min, self.beta, self.threshold = float(h), float(alpha_min), float(beta), float(threshold)
        with wp.ScopedDevice(resolve_device(device)):
            self.device = wp.get_device()
            self.disparity = wp.array(d[:, self.moved].astype(np.float32), dtype=wp.vec3)
            top = np.linalg.norm(d, axis=2).max(axis=1)
            self.disparity_max = wp.array(top.astype(np.float32), dtype=wp.float32)
            self.activation = wp.array(np.maximum(acts, 0.0).astype(np.float32).reshape(-1, g), dtype=wp.float32)
            self.clenching = wp.array(clench_table(acts).astype(np.float32).reshape(-1, g), dtype=wp.float32)
            self.offset = wp.zeros(len(self.moved), dtype=wp.vec3)
            self.velocity = wp.zeros(len(self.moved), dtype=wp.vec3)
            self._mesh = None
            # each moved point's group (the one that moves it most) and its direction at rest
            lengths = np.linalg.norm(d[:, self.moved], axis=2)  # [G, P]
            self._groups = g
            self._group = np.argmax(lengths, axis=0) if len(self.moved) else np.zeros(0, dtype=np.int64)
            top = d[self._group, self.moved]
            self._direction = top / np.maximum(np.linalg.norm(top, axis=1), 1e-30)[:, None]
            self._area = None
            if triangles is not None and points is not None:  # each point's share of the surface
                self._area = vertex_areas(points, triangles, kind="barycentric")[self.moved]
            if triangles is not None:  # the written surface, for the offsets' clearance
                tris = np.asarray(triangles, dtype=np.int64)
                self._surface = wp.zeros(n, dtype=wp.vec3)
                self._mesh = wp.Mesh(points=self._surface, indices=wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32))
                self._base = wp.zeros(len(self.moved), dtype=wp.vec3)
                self._world = wp.zeros(len(self.moved), dtype=wp.vec3)
                self._scale = wp.zeros(len(self.moved), dtype=wp.float32)
                self._facets = None
                if points is None:
                    ring = (vertex_adjacency(tris, n) + sp.identity(n, format="csr")).tocsr()
                else:  # the welded surface: its rings, and the facets the offsets keep
                    first, cls, wtris, _, _ = _welded_surface(points, tris, mesh_of_point)
                    on = np.zeros(len(first), dtype=bool)
                    on[cls[self.moved]] = True
                    wedges = skin_edges(wtris)[0]
                    wring = (vertex_adjacency(wtris, len(first)) + sp.identity(len(first), format="csr")).tocsr()
                    self._facets = (first, cls[self.moved], wedges[on[wedges].any(axis=1)],
                                    wtris[on[wtris].any(axis=1)], wring.astype(np.float64))
                    # a point's ring is its surface point's: the copies of a split corner (flat
                    # shading, seams) ease alike
                    owner = sp.csr_matrix((np.ones(n), (np.arange(n), cls)), shape=(n, len(first)))
                    ring = (owner @ wring @ owner.T).tocsr()
                self._triangles = tris
                # triangles that share a point of the surface (a seam's copies are one point):
                # a crossing the pop moves by one ring of the crossing the frame has without it
                # is that crossing, not a new one (:meth:`_untangle`)
                weld = np.arange(n) if points is None else cls  # each point's surface point
                incidence = sp.csr_matrix((np.ones(tris.size), (np.repeat(np.arange(len(tris)), 3), weld[tris].ravel())),
                                          shape=(len(tris), int(weld.max()) + 1 if n else 0))
                self._touching = ((incidence @ incidence.T) > 0).astype(np.float64).tocsr()
                on_seam = np.zeros(n, dtype=bool) if seams is None else np.asarray(seams, dtype=bool)
                self._seam_triangle = on_seam[tris].any(axis=1)
                self._pairs = PairQuery(tris)
                self._slot = np.full(n, -1, dtype=np.int64)
                self._slot[self.moved] = np.arange(len(self.moved))
                self._ring = (ring[self.moved][:, self.moved] > 0).astype(np.float64)  # among the moved points
                self._ring_mean = sp.diags(1.0 / np.asarray(self._ring.sum(axis=1)).ravel()) @ self._ring
                coo = self._ring.tocoo()
                self._ring_rows, self._ring_cols = coo.row, coo.col
        self.done = 0  # steps taken
        self.held = 0.0  # the largest share of an offset the clearance took back, over the frames

    def _linear(self, matrices: np.ndarray) -> np.ndarray:
        """``[P, 3, 3]`` the linear part of every moved point's blended skinning matrix."""
        return np.einsum("pj,jab->pab", self.weights, np.asarray(matrices, dtype=np.float64)[:, :3, :3])

    def advance(self, steps: int) -> None:
        """Take the next ``steps`` solver steps (at most the steps left)."""
        for _ in range(min(steps, self.steps - self.done)):
            wp.launch(_k.surface_vibration_kernel, dim=len(self.moved),
                      inputs=[self.disparity, self.disparity_max, self.activation, self.clenching, self.done,
                              self.alpha_min, self.beta, self.threshold, self.h],
                      outputs=[self.offset, self.velocity], device=self.device)
            self.done += 1

    def offsets(self, matrices: np.ndarray, surface: np.ndarray | None = None) -> np.ndarray:
        """``[N, 3]`` the popping offset of every point in the pose of skinning ``matrices``
        ``[J, 4, 4]`` [m]: its rest-pose offset carried by its blended skinning's linear part,
        ``L(t) L_rest^-1 o``. With ``surface`` (``[N, 3]`` the points without it, where the
        pop was made with ``triangles``), each offset is shortened so that it crosses no
        surface (:func:`~warpskin.kernels.popping.offset_clearance_kernel`: at most half the
        gap along it, less ``margin``), the shortening eased over the point's ring (its
        neighbours' smallest share, averaged over the ring), so the skin stops short of
        another part it meets (an arm swinging against the torso) without a crease; the
        offsets are shortened where they still make two triangles intersect that do not
        without them, other than a crossing the frame has without them moved by one ring
        (:meth:`_untangle`); a belly held back by either swells more where it is
        free (:meth:`_pressed`), less of that extra where it would cross another piece."""
        out = np.zeros((self.point_count, 3))
        if not len(self.moved):
            return out
        o = self.offset.numpy().astype(np.float64)
        carry = np.einsum("pab,pbc->pac", self._linear(matrices), self._rest_inv)
        world = np.einsum("pab,pb->pa", carry, o)
        if surface is not None and self._mesh is not None:
            self._surface.assign(np.asarray(surface, dtype=np.float32))
            self._mesh.refit()
            self._base.assign(np.asarray(surface, dtype=np.float32)[self.moved])
            self._world.assign(world.astype(np.float32))
            wp.launch(_k.offset_clearance_kernel, dim=len(self.moved),
                      inputs=[self._mesh.id, self._base, self._world, self._start, self.margin],
                      outputs=[self._scale], device=self.device)
            scale = self._scale.numpy().astype(np.float64)
            eased = np.minimum(scale, self._ring_mean @ self._ring_min(scale))
            held = np.asarray(surface, dtype=np.float64)
            eased *= self._untangle(held, world * eased[:, None])
            boost = self._pressed(o, world, eased)  # what is held back swells the free side
            if (boost > 1.0).any():  # where the extra would cross another piece, less of it
                eased *= 1.0 + (boost - 1.0) * self._untangle(held, world * (eased * boost)[:, None])
            if self._facets is not None:  # one factor per point of the surface (a split corner's copies)
                slot = self._facets[1]
                least = np.full(len(self._facets[0]), np.inf)
                np.minimum.at(least, slot, eased)
                eased = least[slot]
                eased *= self._keep_facets(np.asarray(surface, dtype=np.float64), world * eased[:, None])
            world *= eased[:, None]
            self.held = max(self.held, float(1.0 - eased.min()))
        out[self.moved] = world
        return out

    def _keep_facets(self, surface: np.ndarray, world: np.ndarray) -> np.ndarray:
        """``[P]`` factors in [0, 1] on the moved points' offsets ``world`` ``[P, 3]`` [m] such
        that, against the surface without them (``surface`` ``[N, 3]``) in this frame, no edge
        is longer than ``STRAIN_LIMIT`` times its length nor shorter than its inverse, and
        every triangle keeps ``_WRITE_KEEP`` of its area facing as before
        (:func:`_stretch_limit` on the welded surface): the vibration overshoots its goal
        (about 1.6x at ``alpha_min`` 0.1), and points of one triangle ring at their own
        stiffness (eq. 3), so the rest-pose limits alone do not hold the written skin."""
        if self._facets is None:
            return np.ones(len(world))
        first, slot, edges, tris, ring = self._facets
        x = surface[first]
        field = np.zeros_like(x)
        field[slot] = world
        lengths = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
        keep = lengths > 0.0
        return _stretch_limit(x, field, edges[keep], lengths[keep], ring, tris, stretch=_WRITE_STRETCH,
                              shorten=_WRITE_SHORTEN, keep=_WRITE_KEEP)[slot]

    def _pressed(self, rest: np.ndarray, world: np.ndarray, kept: np.ndarray) -> np.ndarray:
        """``[P]`` factors >= 1 on the moved points' offsets: a belly held back where it meets
        another surface (``kept [P]`` in [0, 1], the share of each offset ``world [P, 3]`` [m]
        left) swells more where it is free, as an incompressible muscle pressed on one side
        does. Per group, the outward volume held back (area x offset) is spread over its free
        points' outward offsets (outward: the rest-pose offset ``rest [P, 3]`` along the
        group's swelling), at most ``_PRESSED`` more, fading in with ``kept ** 4``."""
        out = np.ones(len(kept))
        if self._area is None or not len(kept):
            return out
        outward = np.einsum("pc,pc->p", rest, self._direction) > 0.0
        size = np.where(outward, self._area * np.linalg.norm(world, axis=1), 0.0)
        g = self._group
        lost = np.bincount(g, size * (1.0 - kept), minlength=self._groups)
        free = np.bincount(g, size * kept, minlength=self._groups)
        extra = np.where(free > 0.0, np.minimum(lost / np.where(free > 0.0, free, 1.0), _PRESSED), 0.0)
        return np.where(outward, 1.0 + extra[g] * kept ** 4, 1.0)

    def _ring_min(self, values: np.ndarray) -> np.ndarray:
        """``[P]`` the smallest of ``values`` over each moved point's ring (among the moved)."""
        low = values.copy()
        np.minimum.at(low, self._ring_rows, values[self._ring_cols])
        return low

    def _untangle(self, surface: np.ndarray, world: np.ndarray, rounds: int = 8) -> np.ndarray:
        """``[P]`` factors in [0, 1] on the moved points' offsets ``world`` ``[P, 3]`` [m] such
        that the surface with them (``surface`` ``[N, 3]`` without them) has no intersecting
        triangle pair that it has not without them (a ray misses where two surfaces meet
        between its points: fingers side by side, an arm swinging against the torso). Each
        round takes the new pairs (:func:`~warpskin.metrics.PairQuery`, exact) and, per pair,
        the largest common share of its six corners' offsets, of ``_UNTANGLE_SHARES``, that
        keeps the two triangles apart (the exact test,
        :func:`~warpskin.metrics.triangle_pairs_intersect`; none at all does, as they are
        new); each corner keeps the least of its
        pairs' shares, eased over its ring so that the held skin does not crease; at most
        ``rounds`` rounds. Two triangles that both touch a seam between pieces (a surface cut
        into pieces) are left: their borders lie on one another by design; so are two triangles
        that share a point of the surface (the copies of a flat-shaded or seam corner: they
        touch there; the written-quality check does not count them either, and
        :meth:`_keep_facets` keeps every facet unfolded). So is a pair whose
        triangles each share a point with the two triangles of a pair that intersects without
        the pop: a crossing the source already has (a limb through the piece over it, a
        stylised mesh through itself) that the pop moves by at most one ring, not a new one."""
        factor = np.ones(len(self.moved))
        x = surface.copy()
        x[self.moved] += world
        with_pop, without = self._pairs.of_two(x, surface)
        count = np.int64(len(self._triangles))
        with_pop, without = with_pop.astype(np.int64), without.astype(np.int64)
        before = without[:, 0] * count + without[:, 1]  # one key per pair
        # the source's crossings: pairs without the pop that share no point of the surface (a
        # flat-shaded mesh's neighbours touch at their corners' copies: no crossing)
        apart = without[np.asarray(self._touching[without[:, 0], without[:, 1]]).ravel() == 0.0] if len(without) \
            else without
        crossing = sp.csr_matrix((np.ones(2 * len(apart)), (np.r_[apart[:, 0], apart[:, 1]],
                                                            np.r_[apart[:, 1], apart[:, 0]])),
                                 shape=(int(count), int(count)))
        for _ in range(rounds):
            new = with_pop[~np.isin(with_pop[:, 0] * count + with_pop[:, 1], before)
                           & ~(self._seam_triangle[with_pop[:, 0]] & self._seam_triangle[with_pop[:, 1]])]  # seams
            if len(new):  # neighbours on the surface (a flat-shaded corner's copies) touch: no crossing
                new = new[np.asarray(self._touching[new[:, 0], new[:, 1]]).ravel() == 0.0]
            if len(new) and len(apart):  # a crossing of the source moved by one ring
                moved = np.asarray((self._touching[new[:, 0]] @ crossing).multiply(self._touching[new[:, 1]]).sum(axis=1)).ravel()
                new = new[moved == 0.0]
            if not len(new):
                break
            corners = self._triangles[new].reshape(-1, 6)  # [K, 6] the two triangles' points
            slots = self._slot[corners]
            on = slots >= 0
            if not on.any():
                break  # the pairs are not the pop's to undo
            base = surface[corners]  # [K, 6, 3]
            move = np.where(on[:, :, None], (world * factor[:, None])[np.maximum(slots, 0)], 0.0)
            local = np.arange(len(new) * 6).reshape(-1, 6)
            lo = np.zeros(len(new))
            for s in _UNTANGLE_SHARES[::-1]:  # the largest share of the pair's offsets that keeps it apart
                p = (base + s * move).reshape(-1, 3)
                lo = np.where((lo == 0.0) & ~triangle_pairs_intersect(p, local[:, :3], local[:, 3:]), s, lo)
            share = np.ones(len(self.moved))
            np.minimum.at(share, slots[on], np.broadcast_to(lo[:, None], slots.shape)[on])
            factor *= share
            factor = np.minimum(factor, self._ring_mean @ factor)  # eased over the ring
            x[self.moved] = surface[self.moved] + world * factor[:, None]
            with_pop = self._pairs.pairs(x).astype(np.int64)
        return factor

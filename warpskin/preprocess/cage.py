"""An automatic closed simulation cage around a character that is not one closed manifold (open
cuffs and necklines, separate pieces, overlapping parts) or is denser than the layered model
needs.

The cage is the iso-surface, slightly outside the character, of its signed distance field on a
regular grid whose sign comes from the generalised winding number (``kernels.cage``): inside and
outside stay well defined across holes and where pieces overlap. Marching cubes
(``warp.geometry.IsoSurfaceMarchingCubes``) extracts it; its vertices are welded, it is smoothed
with Taubin's lambda/mu filter (no shrinking) so that the grid's staircase does not leave long
thin triangles, and flat edges are flipped towards Delaunay.

The result is closed, manifold and consistently oriented (outward), with edges of about the
grid spacing: by default the spacing that gives about :data:`TARGET_VERTICES` vertices over the
character's surface area.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import RigWarning
from ..kernels import cage as k_cage
from ..mesh import mesh_edge_report, triangle_areas
from ..metrics import signed_volume
from ..rig import Clip, Rig, RigError
from ..run.output import rest_pose_points
from .refine import flip_flat_edges

__all__ = ["Cage", "closest_faces", "build_cage", "separable_parts", "character_parts", "default_cage_edge", "TARGET_VERTICES", "mesh_quality", "CharacterSoup", "character_soup",
           "transfer_weights", "cage_rig", "strongest_influences"]

#: Vertices of a default cage (the layered model's cost grows with them; a few thousand
#: resolve a human's joints).
TARGET_VERTICES = 3000


@dataclass
class Cage:
    """A closed simulation surface around a character.

    Attributes:
        vertices: ``[V, 3]`` [m], in the space of the points it was built from.
        triangles: ``[T, 3]``, counter-clockwise seen from outside.
        edge: Grid spacing it was built at [m] (about its edge length).
        offset: How far outside the character's surface the iso-surface lies [m].
        build_s: Seconds the build took (field, extraction, clean-up).
        timings_s: Seconds per stage.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    edge: float
    offset: float
    build_s: float = 0.0
    timings_s: dict = field(default_factory=dict)


def default_cage_edge(points: np.ndarray, triangles: np.ndarray, target_vertices: int = TARGET_VERTICES) -> float:
    """The grid spacing that puts about ``target_vertices`` vertices on a surface of the
    character's area: a closed triangle mesh has about twice as many triangles as vertices, and
    an iso-surface of spacing ``h`` has triangles of area about ``0.45 h^2``."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    area = triangle_areas(p, t).sum()
    if not (area > 0 and math.isfinite(area)):
        raise RigError("the meshes have no area: no cage can be built around them")
    return float(math.sqrt(area / (2.0 * target_vertices * 0.45)))


def build_cage(points: np.ndarray, triangles: np.ndarray, *, edge: float | None = None, offset: float = 0.6,
               smooth_iterations: int = 12, device=None, max_grid: int = 200,
               parts: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, separation: float = 2.0) -> Cage:
    """Build the cage of the triangle soup ``points`` ``[N, 3]``, ``triangles`` ``[T, 3]`` (every
    mesh of the character in one place, any topology).

    Args:
        edge: Grid spacing [m]; default :func:`default_cage_edge`.
        offset: The iso-level, in grid spacings outside the surface (the cage encloses the
            character by about this much).
        smooth_iterations: Taubin lambda/mu passes.
        device: Warp device for the field.
        max_grid: Largest number of grid nodes along an axis (a memory bound; a finer request
            is coarsened, and the cage says so in ``edge``).
        parts: ``(face_part [T], part_start [P, 3], part_end [P, 3])``: the body part of every
            triangle (its dominant joint) and each part's bone (:func:`character_parts`). Parts
            whose bones come no closer than ``separation`` grid spacings must not share a cage:
            outside the character, between two such parts (the two legs, the two shoes, an arm
            hanging beside the torso), the grid nodes where the nearest part changes are set
            outside, so the cage keeps a gap there even where the gap between the skins is
            narrower than the offset (a cage bridging the legs tears when they part).

    Raises:
        RigError: no surface, or no closed cage could be extracted (naming why).
    """
    import warp as wp
    from warp.geometry import IsoSurfaceMarchingCubes


    t_start = time.perf_counter()
    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    if p.ndim != 2 or p.shape[1] != 3 or tri.ndim != 2 or tri.shape[1] != 3 or tri.size == 0:
        raise RigError(f"a cage needs points [N, 3] and triangles [T, 3], got {p.shape} and {tri.shape}")
    if not np.isfinite(p).all():
        raise RigError("a cage needs finite points")
    h = float(edge) if edge is not None else default_cage_edge(p, tri)
    if not (h > 0 and math.isfinite(h)):
        raise RigError(f"the cage edge must be a positive length, got {edge!r}")
    lo, hi = p.min(axis=0), p.max(axis=0)
    pad = (offset + 3.0) * h
    h = max(h, float((hi - lo + 2 * pad).max()) / (max_grid - 1))  # the memory bound
    pad = (offset + 3.0) * h
    lower = lo - pad
    counts = np.ceil((hi + pad - lower) / h).astype(int) + 1
    timings = {}
    t0 = time.perf_counter()
    with wp.ScopedDevice(device):
        mesh = wp.Mesh(points=wp.array(p.astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(tri.astype(np.int32).ravel(), dtype=wp.int32), support_winding_number=True)
        grid = wp.zeros(tuple(int(c) for c in counts), dtype=wp.float32)
        faces = wp.zeros(tuple(int(c) for c in counts), dtype=wp.int32)
        far = float(np.linalg.norm(hi - lo + 2 * pad))
        wp.launch(k_cage.winding_distance_field_kernel, dim=grid.shape,
                  inputs=[mesh.id, wp.vec3(*lower.astype(np.float32)), np.float32(h), np.float32(far)],
                  outputs=[grid, faces])
        if parts is not None:
            sep = separable_parts(parts[1], parts[2], int(np.max(parts[0])) + 1 if parts[2].size == 0
                                  else max(int(np.max(parts[0])), int(np.max(parts[2]))) + 1, separation * h)
            carved = _carve(grid.numpy(), faces.numpy(), (parts[0], sep), offset * h, h)
            timings["carved_nodes"] = int(carved[1])
            grid = wp.array(carved[0], dtype=wp.float32)
        upper = lower + (counts - 1) * h
        verts, idx = IsoSurfaceMarchingCubes.extract(grid, float(offset * h), lower=tuple(map(float, lower)),
                                                     upper=tuple(map(float, upper)))
        v = verts.numpy().astype(np.float64)
        f = idx.numpy().astype(np.int64).reshape(-1, 3)
    timings["field_and_extraction"] = time.perf_counter() - t0
    if f.shape[0] == 0:
        raise RigError("no cage surface: the meshes enclose no volume (every grid node is outside them)")
    t0 = time.perf_counter()
    v, f = _weld(v, f, 1e-6 * h)
    f = _oriented_outward(v, f)
    v, f = _drop_cavities(v, f)
    v = _taubin(v, f, smooth_iterations)
    f = flip_flat_edges(v, f)
    timings["clean_up"] = time.perf_counter() - t0

    rep = mesh_edge_report(f, v.shape[0])
    if not (rep["closed"] and rep["manifold"]):
        raise RigError(f"the extracted cage is not a closed manifold ({rep}); try another edge length")
    return Cage(vertices=v, triangles=f, edge=h, offset=offset * h, build_s=time.perf_counter() - t_start,
                timings_s=timings)


def cage_from_mesh(mesh, rig, *, device=None, min_inside: float = 0.5, soup: CharacterSoup | None = None) -> Cage:
    """A user's own cage (:func:`warpskin.io.cage_file.read_cage_mesh`) for ``rig``: scaled as
    the character was (``rig.meters_per_unit``), checked to be one closed, manifold,
    consistently wound surface (an inward-wound one is turned, with one warning) that holds at
    least ``min_inside`` of the character's points at rest (the space or the units are wrong
    otherwise). Unused vertices are dropped. ``soup``: the rig's :func:`character_soup`, if
    the caller has it.

    Raises:
        RigError: one line naming the file, what is wrong and where (the file's vertex numbers).
    """
    import warnings

    import warp as wp


    t0 = time.perf_counter()
    src = mesh.source
    p = np.asarray(mesh.points, dtype=np.float64) * float(rig.meters_per_unit)
    tri = np.asarray(mesh.triangles, dtype=np.int64)
    ids = np.asarray(mesh.file_ids)
    rep = mesh_edge_report(tri, p.shape[0])

    def edge(e) -> str:
        return f"between vertices {int(ids[e[0]])} and {int(ids[e[1]])}"

    if len(rep["boundary_edges"]):
        raise RigError(f"{src}: the cage is not closed: {len(rep['boundary_edges'])} boundary edges, e.g. "
                       f"{edge(rep['boundary_edges'][0])} (the file's numbers); close its holes")
    if len(rep["nonmanifold_edges"]):
        raise RigError(f"{src}: the cage is not manifold: {len(rep['nonmanifold_edges'])} edges shared by more than two "
                       f"faces, e.g. {edge(rep['nonmanifold_edges'][0])}")
    if len(rep["nonmanifold_vertices"]):
        raise RigError(f"{src}: the cage is not manifold at {len(rep['nonmanifold_vertices'])} vertices (their faces are "
                       f"not one fan), e.g. vertex {int(ids[rep['nonmanifold_vertices'][0]])}")
    if len(rep["inconsistent_edges"]):
        raise RigError(f"{src}: the cage's faces are not wound consistently: {len(rep['inconsistent_edges'])} edges run "
                       f"the same way in both faces, e.g. {edge(rep['inconsistent_edges'][0])}; unify its normals")
    used = np.unique(tri.ravel())
    remap = np.full(p.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    p, tri = p[used], remap[tri]
    vol = signed_volume(p, tri)
    if not (vol != 0.0 and math.isfinite(vol)):
        raise RigError(f"{src}: the cage encloses no volume")
    if vol < 0:
        tri = tri[:, ::-1].copy()
        warnings.warn(f"{src}: the cage's faces point inward; turned outward", RigWarning, stacklevel=2)
    soup = soup if soup is not None else character_soup(rig)
    with wp.ScopedDevice(device):
        wm = wp.Mesh(points=wp.array(p.astype(np.float32), dtype=wp.vec3),
                     indices=wp.array(tri.astype(np.int32).ravel(), dtype=wp.int32), support_winding_number=True)
        pts = wp.array(soup.points.astype(np.float32), dtype=wp.vec3)
        inside = wp.zeros(len(soup.points), dtype=wp.int32)
        far = 2.0 * float(np.linalg.norm(np.ptp(np.concatenate([p, soup.points]), axis=0))) + 1.0
        wp.launch(k_cage.inside_kernel, dim=len(soup.points), inputs=[wm.id, pts, far], outputs=[inside])
        share = float(inside.numpy().mean())
    if share < min_inside:
        box = lambda q: "[" + ", ".join(f"{a:.3g}..{b:.3g}" for a, b in zip(q.min(0), q.max(0))) + "] m"  # noqa: E731
        raise RigError(f"{src}: the cage holds {100 * share:.0f} % of the character's points at rest (needs at least "
                       f"{100 * min_inside:.0f} %): cage {box(p)}, character {box(soup.points)}; model it around the "
                       f"character's rest pose, in the character file's units")
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    mean_edge = float(np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1).mean())
    return Cage(vertices=p, triangles=tri, edge=mean_edge, offset=0.0, build_s=time.perf_counter() - t0,
                timings_s={"read_and_check": time.perf_counter() - t0})


def _weld(v: np.ndarray, f: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices closer than ``tol`` (marching cubes emits one per cut edge and cell) and
    drop triangles that collapse."""
    key = np.round(v / max(tol, 1e-12)).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    f = inverse[f]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    used = np.unique(f)
    remap = np.full(first.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return v[first][used], remap[f]


def separable_parts(segments: np.ndarray, owner: np.ndarray, part_count: int, distance: float) -> np.ndarray:
    """``[P, P]`` bool: which body parts may not share a cage, given each part's bones as
    segments ``segments[s] = (start, end)`` (``[S, 2, 3]``, stage space) owned by part
    ``owner[s]``: those whose segments come no closer than ``distance`` (a joint's segments
    run to each of its children, so a parent and its child always may share)."""
    seg = np.asarray(segments, dtype=np.float64)
    t = np.linspace(0.0, 1.0, 9)
    samples = (seg[:, None, 0, :] + t[None, :, None] * (seg[:, 1] - seg[:, 0])[:, None, :]).reshape(-1, 3)
    who = np.repeat(np.asarray(owner, dtype=np.int64), t.size)
    d = np.linalg.norm(samples[:, None, :] - samples[None, :, :], axis=2)
    out = np.full((part_count, part_count), np.inf)
    np.minimum.at(out, (who[:, None].repeat(who.size, 1), who[None, :].repeat(who.size, 0)), d)
    return out > distance


def _carve(field: np.ndarray, faces: np.ndarray, parts: tuple[np.ndarray, np.ndarray], level: float,
           h: float) -> tuple[np.ndarray, int]:
    """Carve a gap between separable parts (see :func:`build_cage`'s ``parts``): for every pair
    of axis-neighbour grid nodes within ``1.5 h`` of the surface (inside or out) whose nearest
    parts are separable, set the one nearer to being outside (both, where both are outside
    the character) above the cage's level. Where the skins' gap is narrower than the grid, the
    nodes on either side lie inside the two parts, and the gap is cut into the one whose node
    is shallower. Returns the field and the number of nodes carved."""
    face_part, separable = parts
    label = np.where(faces >= 0, np.asarray(face_part)[np.clip(faces, 0, None)], -1)
    band = (field > -1.5 * h) & (field < level + 1.5 * h)
    carve = np.zeros(field.shape, dtype=bool)
    sep = np.asarray(separable, dtype=bool)
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        la, lb = label[lo], label[hi]
        both = band[lo] & band[hi] & (la >= 0) & (lb >= 0)
        hit = np.zeros(la.shape, dtype=bool)
        hit[both] = sep[la[both], lb[both]]
        fa, fb = field[lo], field[hi]
        outside = (fa > 0) & (fb > 0)
        carve[lo] |= hit & (outside | (fa >= fb))
        carve[hi] |= hit & (outside | (fb > fa))
    out = field.copy()
    out[carve] = np.maximum(out[carve], level + 0.5 * h)
    return out, int(carve.sum())


def _drop_cavities(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop the connected components that enclose no positive volume once the surface faces
    outward: the iso-surface of a pocket inside the character (between a fist's fingers and
    its palm, say) is a cavity, wound inward, which a simulation cage must not hold."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = v.shape[0]
    rows, cols = np.concatenate([f[:, 0], f[:, 1]]), np.concatenate([f[:, 1], f[:, 2]])
    count, label = connected_components(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n)), directed=False)
    if count == 1:
        return v, f
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    centre = v.mean(axis=0)
    vol = np.bincount(label[f[:, 0]], weights=np.einsum("ij,ij->i", p0 - centre, np.cross(p1 - centre, p2 - centre)) / 6.0,
                      minlength=count)
    keep_tri = vol[label[f[:, 0]]] > 0.0
    used = np.unique(f[keep_tri])
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return v[used], remap[f[keep_tri]]


def _oriented_outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Flip the winding if the signed volume is negative (marching cubes' convention)."""
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0
    return f if volume > 0 else f[:, [0, 2, 1]]


def _taubin(v: np.ndarray, f: np.ndarray, iterations: int, lam: float = 0.5, mu: float = -0.53) -> np.ndarray:
    """Taubin's lambda/mu smoothing with uniform weights (preprocessing; vectorised)."""
    import scipy.sparse as sp

    n = v.shape[0]
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    a = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    a.data[:] = 1.0
    deg = np.asarray(a.sum(axis=1)).ravel()
    avg = sp.diags(1.0 / np.maximum(deg, 1)) @ a
    x = v.copy()
    for _ in range(iterations):
        x = x + lam * (avg @ x - x)
        x = x + mu * (avg @ x - x)
    return x


def mesh_quality(v: np.ndarray, f: np.ndarray) -> dict:
    """Triangle shape: the aspect ratio (longest edge over the height onto it, 2/sqrt(3) for an
    equilateral triangle) per triangle, its worst and 99th percentile, and the edge lengths."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    edges = np.stack([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)], 1)
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    longest = edges.max(axis=1)
    aspect = longest ** 2 / np.maximum(area2, 1e-300)
    return {"aspect_max": float(aspect.max()), "aspect_p99": float(np.percentile(aspect, 99)),
            "edge_mean": float(edges.mean()), "edge_max": float(edges.max())}


# --------------------------------------------------------------------------------------------
# The character's meshes as one soup, weights on the cage, the cage as a rig
# --------------------------------------------------------------------------------------------
@dataclass
class CharacterSoup:
    """Every mesh of a rig at rest in stage space, as one triangle soup with LBS influences.

    Attributes:
        points: ``[N, 3]``: the skin's welded vertices first, then each attachment's.
        triangles: ``[T, 3]``.
        dense_weights: ``[N, J]`` skin weights (an attachment's own, in the rig's joints).
        pieces: ``[(name, first point, point count)]``: ``"skin"`` then the attachments.
    """

    points: np.ndarray
    triangles: np.ndarray
    dense_weights: np.ndarray
    pieces: list


def character_soup(rig) -> CharacterSoup:
    """The rig's skin (welded) and attachments at the skeleton's rest pose, in stage space."""
    j = rig.joint_count
    skin = rest_pose_points(rig)[: rig.output_count]
    pts, tris, pieces = [skin], [rig.output_triangles], [("skin", 0, len(skin))]
    dense = [rig._dense_weights(rig.joint_indices, rig.joint_weights)[: rig.output_count]]
    world = rig.joint_world_transforms(Clip("rest"), 0.0)
    start = len(skin)
    for a in getattr(rig, "attachments", []) or []:
        p = a.points(world)
        d = np.zeros((len(p), j))
        np.add.at(d, (np.repeat(np.arange(len(p)), a.joint_indices.shape[1]), a.joint_indices.ravel()), a.joint_weights.ravel())
        pts.append(p)
        tris.append(np.asarray(a.triangles) + start)
        dense.append(d)
        pieces.append((a.name, start, len(p)))
        start += len(p)
    return CharacterSoup(np.concatenate(pts), np.concatenate(tris), np.concatenate(dense), pieces)


def character_parts(rig, soup: CharacterSoup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body parts of :func:`build_cage`'s ``parts``: every soup triangle's dominant joint
    (of its corners' summed weights), and the joints' bones at rest in stage space as segments
    ``[S, 2, 3]`` with their joint ``[S]``: from each joint to each of its children (a leaf: a
    point at the joint)."""
    world = rig.joint_world_transforms(Clip("rest"), 0.0)[:, :3, 3]
    parents = np.asarray(rig.skeleton.parents)
    child = np.nonzero(parents >= 0)[0]
    leaves = np.setdiff1d(np.arange(len(world)), parents[child])
    segments = np.concatenate([np.stack([world[parents[child]], world[child]], axis=1),
                               np.stack([world[leaves], world[leaves]], axis=1)])
    owner = np.concatenate([parents[child], leaves])
    t = np.asarray(soup.triangles, dtype=np.int64)
    face_part = np.argmax(soup.dense_weights[t].sum(axis=1), axis=1)
    return face_part, segments, owner


def rigid_pieces(soup: CharacterSoup, rigid_weight: float = 0.999) -> np.ndarray:
    """The pieces of a character that LBS moves rigidly: connected components of its meshes
    (seam copies at one position joined) whose every point has one joint with weight at least
    ``rigid_weight``, the same joint for all (an eye or teeth skinned to the head, a rigidly
    parented armour plate, RobotExpressive's body parts); the components of one mesh on one joint
    are one piece (they move together: the robot's head is 29 components). Returns ``[N]``: the
    piece of each soup point, numbered from 0, or -1 (bound to the cage point by point)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(soup.points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    _, weld = np.unique(soup.points, axis=0, return_inverse=True)
    weld = weld.ravel()
    t = weld[np.asarray(soup.triangles, dtype=np.int64)]
    m = int(weld.max()) + 1
    rows, cols = np.concatenate([t[:, 0], t[:, 1]]), np.concatenate([t[:, 1], t[:, 2]])
    _, comp = connected_components(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(m, m)), directed=False)
    label = comp[weld]
    dominant = np.argmax(soup.dense_weights, axis=1)
    strong = soup.dense_weights[np.arange(n), dominant] >= rigid_weight
    count = label.max() + 1
    weak = np.bincount(label, weights=~strong, minlength=count) > 0
    lo = np.full(count, np.iinfo(np.int64).max)
    hi = np.full(count, -1)
    np.minimum.at(lo, label, dominant)
    np.maximum.at(hi, label, dominant)
    rigid = ~weak & (lo == hi)
    mesh = np.zeros(n, dtype=np.int64)
    for k, (_, start, size) in enumerate(soup.pieces):
        mesh[start:start + size] = k
    out = np.full(n, -1, dtype=np.int64)
    sel = rigid[label]
    if sel.any():  # one piece per mesh and joint
        _, out[sel] = np.unique(np.stack([mesh[sel], dominant[sel]], axis=1), axis=0, return_inverse=True)
    return out


def closest_faces(query: np.ndarray, points: np.ndarray, triangles: np.ndarray, max_distance: float,
                  device=None) -> tuple[np.ndarray, np.ndarray]:
    """The closest point of the mesh ``points`` ``[N, 3]``, ``triangles`` ``[T, 3]`` to each of
    ``query`` ``[M, 3]`` (Warp's mesh query, float32, within ``max_distance`` [m]):
    ``(face [M] int, -1 where none is that near; barycentric [M, 3] float64)``."""
    import warp as wp


    q = np.asarray(query, dtype=np.float64)
    with wp.ScopedDevice(device):
        mesh = wp.Mesh(points=wp.array(np.asarray(points).astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(np.asarray(triangles).astype(np.int32).ravel(), dtype=wp.int32))
        face = wp.zeros(len(q), dtype=wp.int32)
        bary = wp.zeros(len(q), dtype=wp.vec3)
        wp.launch(k_cage.closest_face_kernel, dim=len(q), inputs=[mesh.id, wp.array(q.astype(np.float32), dtype=wp.vec3),
                                                                 float(max_distance)], outputs=[face, bary])
        return face.numpy(), bary.numpy().astype(np.float64)


def transfer_weights(cage_vertices: np.ndarray, cage_triangles: np.ndarray, soup: CharacterSoup, *, max_distance: float,
                     device=None, influences: int = 4, smooth_passes: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Skin weights on the cage: each cage vertex takes the barycentric blend of the weights at
    its closest point on the character where that lies within ``max_distance``; the others are
    inpainted (Abdrashitov et al. 2023): the weights that are harmonic over the cage (uniform
    Laplacian) with the matched ones fixed. Then ``smooth_passes`` passes of averaging with the
    neighbours (half the vertex, half its neighbours' mean): a character of rigid parts (each
    on one joint with weight 1) would otherwise give its cage LBS weights that jump at every
    joint, so the cage's own LBS tears there (edges several times their rest length) and its
    physics fights the tear. Then the largest ``influences`` per vertex,
    normalised. Returns ``(joint_indices [V, K], joint_weights [V, K], matched [V] bool)``."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    cv = np.asarray(cage_vertices, dtype=np.float64)
    n = cv.shape[0]
    face, bary = closest_faces(cv, soup.points, soup.triangles, max_distance, device)
    matched = face >= 0
    dense = np.zeros((n, soup.dense_weights.shape[1]))
    corners = soup.triangles[face[matched]]
    dense[matched] = np.einsum("vc,vcj->vj", bary[matched], soup.dense_weights[corners])
    if not matched.any():
        raise RigError(f"no cage vertex lies within {max_distance:.3g} m of the character: no weights to transfer")
    if not matched.all():
        # harmonic inpainting: L_uu w_u = -L_um w_m with the uniform graph Laplacian L = D - A
        t = np.asarray(cage_triangles, dtype=np.int64)
        rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
        cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
        a = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
        a.data[:] = 1.0
        lap = (sp.diags(np.asarray(a.sum(axis=1)).ravel()) - a).tocsr()
        u, m = np.nonzero(~matched)[0], np.nonzero(matched)[0]
        luu = lap[u][:, u].tocsc()
        rhs = -(lap[u][:, m] @ dense[m])
        dense[u] = spla.splu(luu).solve(np.asarray(rhs))
    if smooth_passes > 0:
        t = np.asarray(cage_triangles, dtype=np.int64)
        rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
        cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
        a = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
        a.data[:] = 1.0
        avg = sp.diags(1.0 / np.maximum(np.asarray(a.sum(axis=1)).ravel(), 1.0)) @ a
        for _ in range(smooth_passes):
            dense = 0.5 * dense + 0.5 * (avg @ dense)
    return strongest_influences(dense, influences) + (matched,)


def strongest_influences(dense: np.ndarray, influences: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``influences`` largest weights of each row of ``dense`` ``[N, J]`` (negative ones taken
    as 0) and their joints: ``(joint indices [N, K], weights [N, K])``, the weights renormalised to
    sum to 1 (``K = min(influences, J)``)."""
    dense = np.clip(dense, 0.0, None)
    k = min(influences, dense.shape[1])
    idx = np.argsort(-dense, axis=1)[:, :k]
    w = np.take_along_axis(dense, idx, axis=1)
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
    return idx.astype(np.int64), w


def cage_rig(rig, cage: Cage, *, device=None, smooth_passes: int = 8) -> tuple:
    """The cage as a rig to simulate, bound at the character's rest pose: the character's
    skeleton and clips, the cage's triangles and rest points (stage space) as its bind pose, so
    its inverse binds are the inverses of the joints' rest world transforms; weights transferred
    from the character (:func:`transfer_weights`, matched within two cage edges). (Taking the
    cage into the file's bind space instead folds it where that differs from the rest pose.)
    Returns ``(rig, soup, matched)``."""
    soup = character_soup(rig)
    ji, jw, matched = transfer_weights(cage.vertices, cage.triangles, soup, max_distance=2.0 * cage.edge, device=device,
                                       smooth_passes=smooth_passes)
    rest_world = rig.joint_world_transforms(Clip("rest"), 0.0)
    caged = Rig(
        name=rig.name, vertices=cage.vertices.copy(), triangles=cage.triangles, skeleton=rig.skeleton, joint_indices=ji,
        joint_weights=jw, inverse_bind=np.linalg.inv(rest_world), clips=rig.clips,
        source=f"{rig.source} (its automatic cage)", mesh_name=f"{rig.mesh_name} (cage)", up_axis=rig.up_axis,
        meters_per_unit=rig.meters_per_unit, vertex_kind="cage",
    )
    caged.validate(raise_on_error=True)
    return caged, soup, matched


def surface_report(triangles: np.ndarray, vertex_count: int) -> dict:
    """Pieces (connected components) and boundary loops of a triangle mesh (``warpskin info``)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    t = np.asarray(triangles, dtype=np.int64)
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    graph = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(vertex_count, vertex_count))
    used = np.unique(t)
    _, labels = connected_components(graph, directed=False)
    pieces = int(np.unique(labels[used]).size)
    edges = np.sort(np.stack([rows, cols], axis=1), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = uniq[counts == 1]
    loops = 0
    if boundary.size:
        b = sp.csr_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(vertex_count, vertex_count))
        _, bl = connected_components(b, directed=False)
        loops = int(np.unique(bl[np.unique(boundary)]).size)
    return {"pieces": pieces, "boundary_loops": loops}

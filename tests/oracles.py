"""Independent references shared by the tests, in plain NumPy and Python: no warpskin kernel
or host routine under test is used here (the procedural arm generator is the only import, for
the test meshes).

* :func:`lbs` / :func:`rig_lbs`: linear blend skinning, ``sum_k w_k M_{j_k} [p, 1]``, float64.
* :func:`neighbour_sets`, :func:`omega_rings`, :func:`omega_ring`: omega-rings by
  breadth-first search over the triangle edges.
* :func:`coarse_arm`: the procedural arm at a coarse resolution (fast to build and simulate).
* :func:`flip_flat_edges_one_by_one`: Delaunay flips of coplanar triangle pairs, edge by edge.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = ["lbs", "rig_lbs", "neighbour_sets", "omega_rings", "omega_ring", "coarse_arm", "COARSE", "winding_numbers",
           "triangles_intersect_sat", "intersecting_pairs_brute_force", "strain_and_flips",
           "flip_flat_edges_one_by_one"]

#: Rings and segments of the coarse arm most solver tests use (1200 particles).
COARSE = {"rings": 30, "segments": 20}


def lbs(points: np.ndarray, joint_indices: np.ndarray, joint_weights: np.ndarray, mats: np.ndarray) -> np.ndarray:
    """Linear blend skinning ``[N, 3]``: ``sum_k w_k * (M_{j_k} @ [p, 1])`` in float64, one
    influence at a time (no blended matrix), independent of warpskin's kernels."""
    p = np.asarray(points, dtype=np.float64)
    ph = np.concatenate([p, np.ones((len(p), 1))], axis=1)
    mats = np.asarray(mats, dtype=np.float64)
    out = np.zeros((len(p), 3))
    for k in range(joint_indices.shape[1]):
        out += joint_weights[:, k, None] * np.einsum("vab,vb->va", mats[joint_indices[:, k]], ph)[:, :3]
    return out


def rig_lbs(rig, mats: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
    """:func:`lbs` of a rig's vertices (or of ``points`` with the rig's weights)."""
    return lbs(rig.vertices if points is None else points, rig.joint_indices, rig.joint_weights, mats)


def neighbour_sets(triangles: np.ndarray, vertex_count: int) -> list[set[int]]:
    """Edge neighbours of every vertex, from the triangles."""
    nb: list[set[int]] = [set() for _ in range(vertex_count)]
    for a, b, c in np.asarray(triangles).tolist():
        for u, v in ((a, b), (b, c), (c, a)):
            if u != v:
                nb[u].add(v)
                nb[v].add(u)
    return nb


def omega_ring(nb: list[set[int]], start: int, omega: int) -> dict[int, int]:
    """Every vertex within ``omega`` edges of ``start`` -> its edge distance (BFS order)."""
    dist = {start: 0}
    queue = deque([start])
    while queue:
        v = queue.popleft()
        if dist[v] == omega:
            continue
        for u in nb[v]:
            if u not in dist:
                dist[u] = dist[v] + 1
                queue.append(u)
    return dist


def omega_rings(nb: list[set[int]], omega: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR regions: every vertex and all vertices within ``omega`` edges (breadth-first)."""
    offsets, members = [0], []
    for c in range(len(nb)):
        members.extend(omega_ring(nb, c, omega))
        offsets.append(len(members))
    return np.array(offsets, dtype=np.int64), np.array(members, dtype=np.int64)


def coarse_arm(**overrides):
    """The procedural arm at :data:`COARSE` resolution (keyword overrides allowed)."""
    from warpskin.scenes.arm import make_arm

    return make_arm(**{**COARSE, **overrides})


def winding_numbers(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, block: int = 1 << 16) -> np.ndarray:
    """Generalised winding number of every point ``[P]`` with respect to a triangle mesh: the sum
    of the triangles' signed solid angles over 4 pi (Van Oosterom and Strackee 1983). About 1
    inside a closed, outward-wound surface, 0 outside. Evaluated over every point-triangle pair
    in float64, component by component, about ``block`` pairs at a time (blocks that stay in
    the cache: a few points against all triangles)."""
    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]  # [T, corner, xyz]
    corners = [[np.ascontiguousarray(tri[:, k, d]) for d in range(3)] for k in range(3)]
    chunk = max(1, int(block) // max(len(tri), 1))
    out = np.empty(len(p))
    for s in range(0, len(p), chunk):
        q = p[s:s + chunk]
        (ax, ay, az), (bx, by, bz), (cx, cy, cz) = ([v[None, :] - q[:, d, None] for d, v in enumerate(corner)]
                                                    for corner in corners)  # [C, T] each
        la = np.sqrt(ax * ax + ay * ay + az * az)
        lb = np.sqrt(bx * bx + by * by + bz * bz)
        lc = np.sqrt(cx * cx + cy * cy + cz * cz)
        det = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la \
            + (cx * ax + cy * ay + cz * az) * lb
        out[s:s + chunk] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out


def usd_skinned_world(stage, mesh_path: str, tc: float, blend_weights: dict[str, float] | None = None) -> np.ndarray:
    """World-space skinned points ``[N, 3]`` of ``mesh_path`` as usd-core's own UsdSkel
    computes them (``SkinningQuery.ComputeSkinnedPoints``, then the skeleton's local-to-world)
    at time code ``tc``; with ``blend_weights`` (``{shape name: weight}``, others 0) the mesh's
    blend shapes and their inbetweens are applied first by ``UsdSkel.BlendShapeQuery``."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    predicate = Usd.TraverseInstanceProxies()
    cache = UsdSkel.Cache()
    for prim in stage.Traverse(predicate):
        if not prim.IsA(UsdSkel.Root):
            continue
        root = UsdSkel.Root(prim)
        cache.Populate(root, predicate)
        for binding in cache.ComputeSkelBindings(root, predicate):
            for target in binding.GetSkinningTargets():
                if str(target.GetPrim().GetPath()) != mesh_path:
                    continue
                skel_query = cache.GetSkelQuery(binding.GetSkeleton())
                points = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(tc)
                if blend_weights is not None:
                    shape_binding = UsdSkel.BindingAPI(target.GetPrim())
                    names = list(shape_binding.GetBlendShapesAttr().Get())
                    query = UsdSkel.BlendShapeQuery(shape_binding)
                    sub = query.ComputeSubShapeWeights(Vt.FloatArray([blend_weights.get(n, 0.0) for n in names]))
                    assert query.ComputeDeformedPoints(*sub, query.ComputeBlendShapePointIndices(),
                                                       query.ComputeSubShapePointOffsets(), points)
                xforms = skel_query.ComputeSkinningTransforms(tc)
                assert target.ComputeSkinnedPoints(xforms, points, tc)
                l2w = np.array(UsdGeom.Xformable(skel_query.GetPrim()).ComputeLocalToWorldTransform(tc)).T
                p = np.asarray(points, dtype=np.float64)
                return p @ l2w[:3, :3].T + l2w[:3, 3]
    raise AssertionError(f"{mesh_path} is not a skinning target")


def prim(stage, relative: str):
    """The prim at ``relative`` under a bake's root (its ``defaultPrim``, named after the
    character); ``skin`` and ``lbs`` name the character's skin and its LBS guide by their role
    (the prims carry the file's mesh name, ``warpskin:role`` in their custom data)."""
    root = stage.GetDefaultPrim()
    assert root, "the stage has no defaultPrim"
    for child in root.GetChildren():
        if child.GetCustomDataByKey("warpskin:role") == relative:
            return child
    return stage.GetPrimAtPath(root.GetPath().AppendPath(relative))


def gltf_reference_points(path, t: float, animation: str | None = None) -> dict[int, np.ndarray]:
    """World-space points of every mesh node at time ``t`` [s] of ``animation`` (default the
    first), straight from the glTF spec with pygltflib and SciPy: each node's local TRS (its
    animation channels sampled linearly, rotations slerped, clamped at the ends), world = parent
    world x local for every node; a skinned mesh is the LBS of its POSITION/JOINTS_0/WEIGHTS_0
    under joint matrices world x inverse bind, any other mesh its node's world x POSITION
    (every primitive, concatenated). Keyed by node index."""
    import pygltflib
    from scipy.spatial.transform import Rotation, Slerp

    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    comp = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}

    def read(i):
        acc = g.accessors[i]
        view = g.bufferViews[acc.bufferView]
        dt = np.dtype(comp[acc.componentType])
        n, w = acc.count, width[acc.type]
        stride = view.byteStride or dt.itemsize * w
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        rows = [np.frombuffer(blob, dt, w, start + k * stride) for k in range(n)]
        return np.array(rows, dtype=np.float64)

    local = []
    for node in g.nodes:
        if node.matrix:
            local.append(np.array(node.matrix, dtype=np.float64).reshape(4, 4).T)
            continue
        local.append([np.array(node.translation or [0, 0, 0], float), np.array(node.rotation or [0, 0, 0, 1], float),
                      np.array(node.scale or [1, 1, 1], float)])
    anim = next((a for a in g.animations if a.name == animation), None) if animation else g.animations[0]
    for ch in anim.channels:
        if ch.target.path not in ("translation", "rotation", "scale"):
            continue  # morph weights do not move a mesh's base points
        smp = anim.samplers[ch.sampler]
        assert smp.interpolation in (None, "LINEAR"), "the reference samples LINEAR channels only"
        times, values = read(smp.input).ravel(), read(smp.output)
        tc = float(np.clip(t, times[0], times[-1]))
        if ch.target.path == "rotation":
            value = Slerp(times, Rotation.from_quat(values))(tc).as_quat()
        else:
            value = np.array([np.interp(tc, times, values[:, c]) for c in range(values.shape[1])])
        local[ch.target.node][["translation", "rotation", "scale"].index(ch.target.path)] = value

    def matrix(entry):
        if isinstance(entry, np.ndarray):
            return entry
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(entry[1]).as_matrix() * entry[2]
        m[:3, 3] = entry[0]
        return m

    parent = {c: i for i, node in enumerate(g.nodes) for c in (node.children or [])}
    world: dict[int, np.ndarray] = {}

    def world_of(i):
        if i not in world:
            world[i] = (world_of(parent[i]) if i in parent else np.eye(4)) @ matrix(local[i])
        return world[i]

    out = {}
    for i, node in enumerate(g.nodes):
        if node.mesh is None:
            continue
        parts = []
        for prim in g.meshes[node.mesh].primitives:
            attrs = prim.attributes
            pos = read(attrs.POSITION)
            hom = np.c_[pos, np.ones(len(pos))]
            if node.skin is None:
                parts.append((hom @ world_of(i).T)[:, :3])
                continue
            skin = g.skins[node.skin]
            ibm = read(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
            mats = np.stack([world_of(j) for j in skin.joints]) @ ibm
            ji, jw = read(attrs.JOINTS_0).astype(int), read(attrs.WEIGHTS_0)
            jw = jw / jw.sum(axis=1, keepdims=True)
            parts.append(np.einsum("vk,vkab,vb->va", jw, mats[ji], hom)[:, :3])
        out[i] = np.concatenate(parts)
    return out


def point_mesh_distance(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                        chunk: int | None = None) -> np.ndarray:
    """Brute-force unsigned distance ``[N]`` from every point to a triangle mesh (see
    :func:`closest_on_mesh`)."""
    return closest_on_mesh(points, vertices, triangles, chunk)[0]


def closest_on_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray, chunk: int | None = None) -> tuple:
    """Brute-force closest points on a triangle mesh: the closest point on each triangle by
    Ericson's region test (Real-Time Collision Detection, 5.1.5), the minimum over all
    triangles. Returns ``(distance [N], triangle [N], barycentric weights [N, 3])``. ``chunk``
    points at a time (default: about 16k point-triangle pairs a block, which stay in the cache)."""
    p = np.asarray(points, dtype=np.float64)
    a, b, c = (np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)[:, i]] for i in range(3))
    if chunk is None:
        chunk = max(1, (1 << 14) // max(len(a), 1))
    ab, ac = b - a, c - a
    out = np.empty(len(p))
    tri = np.empty(len(p), dtype=np.int64)
    bary = np.empty((len(p), 3))
    for s in range(0, len(p), chunk):
        q = p[s:s + chunk, None, :]  # [n, 1, 3] against [T, 3]
        ap, bp, cp = q - a, q - b, q - c
        d1, d2 = np.einsum("ntk,tk->nt", ap, ab), np.einsum("ntk,tk->nt", ap, ac)
        d3, d4 = np.einsum("ntk,tk->nt", bp, ab), np.einsum("ntk,tk->nt", bp, ac)
        d5, d6 = np.einsum("ntk,tk->nt", cp, ab), np.einsum("ntk,tk->nt", cp, ac)
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = va + vb + vc
            v_in, w_in = vb / denom, vc / denom
            t_ab = d1 / (d1 - d3)
            t_ac = d2 / (d2 - d6)
            t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        # barycentric (v, w) of the closest point, region by region (the last rule that applies wins)
        v = np.where(True, v_in, 0.0)
        w = np.where(True, w_in, 0.0)
        on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        v, w = np.where(on_bc, 1 - t_bc, v), np.where(on_bc, t_bc, w)
        on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        v, w = np.where(on_ac, 0.0, v), np.where(on_ac, t_ac, w)
        on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        v, w = np.where(on_ab, t_ab, v), np.where(on_ab, 0.0, w)
        at_c = (d6 >= 0) & (d5 <= d6)
        v, w = np.where(at_c, 0.0, v), np.where(at_c, 1.0, w)
        at_b = (d3 >= 0) & (d4 <= d3)
        v, w = np.where(at_b, 1.0, v), np.where(at_b, 0.0, w)
        at_a = (d1 <= 0) & (d2 <= 0)
        v, w = np.where(at_a, 0.0, v), np.where(at_a, 0.0, w)
        closest = a + v[..., None] * ab + w[..., None] * ac
        dist = np.linalg.norm(q - closest, axis=2)
        best = dist.argmin(axis=1)
        rows = np.arange(len(best))
        out[s:s + chunk] = dist[rows, best]
        tri[s:s + chunk] = best
        vb_, wb_ = v[rows, best], w[rows, best]
        bary[s:s + chunk] = np.stack([1.0 - vb_ - wb_, vb_, wb_], axis=1)
    return out, tri, bary


# --------------------------------------------------------------------------------------------
# Written-mesh measures, written independently of warpskin.metrics and warpskin.quality
# --------------------------------------------------------------------------------------------
def triangles_intersect_sat(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether triangles ``a`` and ``b`` (``[3, 3]`` each, float64) intersect, by the separating
    axis theorem: two convex polygons in 3-D are disjoint iff their projections onto one of
    the two face normals or one of the nine edge-edge cross products do not overlap. (Generic
    positions only: touching or coplanar pairs are measure zero in the tests.)"""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ea = [a[1] - a[0], a[2] - a[1], a[0] - a[2]]
    eb = [b[1] - b[0], b[2] - b[1], b[0] - b[2]]
    axes = [np.cross(ea[0], ea[1]), np.cross(eb[0], eb[1])] + [np.cross(u, v) for u in ea for v in eb]
    for ax in axes:
        if np.dot(ax, ax) < 1e-30:
            continue
        pa, pb = a @ ax, b @ ax
        if pa.max() < pb.min() or pb.max() < pa.min():
            return False
    return True


def _sat_disjoint(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`triangles_intersect_sat`'s test over many pairs at once: ``a``, ``b`` ``[N, 3, 3]``;
    True where some of the eleven axes separates the pair."""
    ea, eb = a[:, [1, 2, 0]] - a, b[:, [1, 2, 0]] - b
    axes = [np.cross(ea[:, 0], ea[:, 1]), np.cross(eb[:, 0], eb[:, 1])]
    axes += [np.cross(ea[:, u], eb[:, v]) for u in range(3) for v in range(3)]
    disjoint = np.zeros(len(a), dtype=bool)
    for ax in axes:
        pa, pb = np.einsum("nkd,nd->nk", a, ax), np.einsum("nkd,nd->nk", b, ax)
        apart = (pa.max(axis=1) < pb.min(axis=1)) | (pb.max(axis=1) < pa.min(axis=1))
        disjoint |= apart & (np.einsum("nd,nd->n", ax, ax) >= 1e-30)
    return disjoint


def intersecting_pair_list_brute_force(points: np.ndarray, triangles: np.ndarray, block: int = 256) -> np.ndarray:
    """The intersecting triangle pairs ``(i, j)``, ``i < j``, of a mesh that share no vertex,
    ``[P, 2]`` in lexicographic order, over every pair: boxes first (``block`` triangles against
    all at a time), then the separating axis test of :func:`triangles_intersect_sat` over the
    pairs whose boxes overlap, all at once."""
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    corners = p[t]
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    out = []
    for s in range(0, len(t), block):
        i = np.arange(s, min(s + block, len(t)))
        overlap = np.all((lo[None, :] <= hi[i, None]) & (hi[None, :] >= lo[i, None]), axis=2)  # [B, T]
        overlap &= np.arange(len(t))[None, :] > i[:, None]
        ii, jj = np.nonzero(overlap)
        ii = i[ii]
        shared = (t[ii][:, :, None] == t[jj][:, None, :]).any(axis=(1, 2))
        ii, jj = ii[~shared], jj[~shared]
        hit = ~_sat_disjoint(corners[ii], corners[jj])
        out.append(np.stack([ii[hit], jj[hit]], axis=1))
    if not out:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(out).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def intersecting_pairs_brute_force(points: np.ndarray, triangles: np.ndarray) -> int:
    """The number of :func:`intersecting_pair_list_brute_force`."""
    return int(len(intersecting_pair_list_brute_force(points, triangles)))


def strain_and_flips(rest: np.ndarray, points: np.ndarray, lbs: np.ndarray, triangles: np.ndarray,
                     limit: float = 1.5) -> tuple[float, float, float]:
    """``(strained share, strained share of LBS, flipped share)`` of a mesh welded by rest
    position: edges longer than ``limit`` x rest or shorter than rest / ``limit``, and
    triangles whose normal points against LBS's (the weld and the edge set by plain Python
    sets, the lengths and normals by NumPy)."""
    rest = np.asarray(rest, dtype=np.float64)
    key: dict = {}
    weld = np.array([key.setdefault(tuple(x), len(key)) for x in rest.tolist()])
    first = np.zeros(len(key), dtype=np.int64)
    first[weld[::-1]] = np.arange(len(weld))[::-1]
    edges, faces = set(), []
    for tri in np.asarray(triangles).tolist():
        w = [int(weld[v]) for v in tri]
        if len(set(w)) < 3:
            continue
        faces.append(tri)
        for u, v in ((w[0], w[1]), (w[1], w[2]), (w[2], w[0])):
            edges.add((min(u, v), max(u, v)))
    e = first[np.array(sorted(edges), dtype=np.int64)]
    l0 = np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)

    def share(x):
        x = np.asarray(x, dtype=np.float64)
        ln = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
        return float(np.mean((ln > limit * l0) | (ln < l0 / limit)))

    f = np.array(faces, dtype=np.int64)
    p, q = np.asarray(points, dtype=np.float64), np.asarray(lbs, dtype=np.float64)
    n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    m = np.cross(q[f[:, 1]] - q[f[:, 0]], q[f[:, 2]] - q[f[:, 0]])
    return share(p), share(q), float(np.mean(np.einsum("ij,ij->i", n, m) < 0.0))


def _flip_angle(x: np.ndarray, apex: int, a: int, b: int) -> float:
    u, w = x[a] - x[apex], x[b] - x[apex]
    return math.atan2(float(np.linalg.norm(np.cross(u, w))), float(np.dot(u, w)))


def flip_flat_edges_one_by_one(x: np.ndarray, triangles: np.ndarray, *, coplanar_cos: float = 1.0 - 1e-10,
                    max_passes: int = 50) -> np.ndarray:
    """Delaunay flips of coplanar triangle pairs, one edge at a time in plain Python (the
    reference for ``warpskin.preprocess.refine.flip_flat_edges``): every edge shared by two
    coplanar, equally oriented triangles whose opposite angles sum to more than pi is flipped,
    in order of the directed edges' first appearance, skipping triangles a flip of the same pass
    changed and diagonals that are edges already; passes until none flips."""
    tris = [list(t) for t in np.asarray(triangles, dtype=np.int64)]
    normals = []
    for a, b, c in tris:
        n = np.cross(x[b] - x[a], x[c] - x[a])
        ln = np.linalg.norm(n)
        normals.append(n / ln if ln > 0 else n)
    for _ in range(max_passes):
        edge_tri: dict[tuple[int, int], int] = {}  # directed edge -> its triangle
        for k, (a, b, c) in enumerate(tris):
            edge_tri[(a, b)] = k
            edge_tri[(b, c)] = k
            edge_tri[(c, a)] = k
        undirected = {tuple(sorted(e)) for e in edge_tri}
        flipped = 0
        touched: set[int] = set()
        for a, b in list(edge_tri):
            if a > b or (b, a) not in edge_tri:
                continue
            k1, k2 = edge_tri[(a, b)], edge_tri[(b, a)]
            if k1 in touched or k2 in touched:
                continue
            if float(np.dot(normals[k1], normals[k2])) < coplanar_cos:
                continue
            t1, t2 = tris[k1], tris[k2]
            c = next(v for v in t1 if v != a and v != b)
            d = next(v for v in t2 if v != a and v != b)
            if c == d or tuple(sorted((c, d))) in undirected:
                continue
            if _flip_angle(x, c, a, b) + _flip_angle(x, d, a, b) <= math.pi + 1e-9:
                continue
            # (a, b, c) and (b, a, d) become (c, a, d) and (d, b, c): both keep the orientation
            n1 = np.cross(x[a] - x[c], x[d] - x[c])
            n2 = np.cross(x[b] - x[d], x[c] - x[d])
            if np.dot(n1, normals[k1]) <= 0 or np.dot(n2, normals[k1]) <= 0:
                continue  # the quad is not convex there: a flip would fold it
            tris[k1], tris[k2] = [c, a, d], [d, b, c]
            normals[k1] = n1 / np.linalg.norm(n1)
            normals[k2] = n2 / np.linalg.norm(n2)
            undirected.discard((min(a, b), max(a, b)))
            undirected.add((min(c, d), max(c, d)))
            touched.update((k1, k2))
            flipped += 1
        if not flipped:
            break
    return np.array(tris, dtype=np.int64).reshape(-1, 3)

"""Refining a coarse skin for the simulation: long edges are split at their midpoints.

The layered model needs a skin fine enough that a shape-matching region (a vertex's one-ring)
is small against a limb. A low-poly game mesh (RiggedSimple's 96-vertex cylinder, the Fox)
has one-rings that reach from one joint past the next, so every region spans a joint and
pulls the bent limb back towards its straight bind shape. Splitting every edge longer than
``max_edge`` at its midpoint (red-green refinement, repeated until none is longer) makes the
regions small without changing the surface: the new vertices lie on the old triangles, every
file vertex stays (the first ``V`` vertices, in order), the surface stays closed, manifold and
consistently oriented, and a midpoint's skinning weights are the mean of its edge's.

The simulation then runs on the refined skin and writes back the file's own vertices.
"""

from __future__ import annotations

import math

import numpy as np

from ..mesh import surface_area

__all__ = ["RefinedSurface", "refine_long_edges", "default_max_edge", "flip_flat_edges"]

#: Vertex count the default edge length aims at for a coarse skin (near-equilateral triangles).
TARGET_VERTICES = 1000



def default_max_edge(vertices: np.ndarray, triangles: np.ndarray, target_vertices: int = TARGET_VERTICES) -> float:
    """Twice the edge length of an equilateral mesh of ``target_vertices`` vertices over the
    surface's area (a closed surface of V vertices has about 2V triangles): after splitting,
    the edges lie between this and half of it."""
    area = surface_area(vertices, triangles)
    return 2.0 * math.sqrt(2.0 * area / (math.sqrt(3.0) * max(int(target_vertices), 1)))


class RefinedSurface:
    """A refined skin.

    Attributes:
        vertices: ``[V', 3]``; the first ``original_count`` are the input's, in order.
        triangles: ``[T', 3]``, the same orientation as the input's.
        parents: The two vertices each added vertex is the midpoint of, ``[V' - V, 2]`` (either
            may itself be an added vertex, always one added earlier).
        original_count: ``V``.
    """

    def __init__(self, vertices, triangles, parents, original_count: int) -> None:
        self.vertices = vertices
        self.triangles = triangles
        self.parents = parents
        self.original_count = int(original_count)

    @property
    def added(self) -> int:
        return int(self.vertices.shape[0] - self.original_count)


def extend_midpoints(values: np.ndarray, parents: np.ndarray, *, take_first: bool = False) -> np.ndarray:
    """Per-vertex ``values`` ``[V, ...]`` extended by one row per added vertex: the mean of its
    two parents' rows (``parents`` ``[A, 2]``, each referring to earlier rows), or with
    ``take_first`` the first parent's (for labels such as a bone index)."""
    values = np.asarray(values)
    parents = np.asarray(parents, dtype=np.int64).reshape(-1, 2)
    dtype = values.dtype if take_first else np.float64
    out = np.empty((values.shape[0] + parents.shape[0],) + values.shape[1:], dtype=dtype)
    n = values.shape[0]
    out[:n] = values
    if parents.size and (parents.max(axis=1) >= n + np.arange(parents.shape[0])).any():
        raise ValueError("extend_midpoints: every added row's parents must be earlier rows")
    # one vectorised step per generation (a refinement pass): the longest run of added rows
    # whose parents are all filled already
    top = parents.max(axis=1) if parents.size else parents[:, 0]
    k = 0
    while k < parents.shape[0]:
        late = np.nonzero(top[k:] >= n + k)[0]
        stop = k + int(late[0]) if late.size else parents.shape[0]
        a, b = parents[k:stop, 0], parents[k:stop, 1]
        out[n + k:n + stop] = out[a] if take_first else 0.5 * (out[a] + out[b])
        k = stop
    return out


def refine_long_edges(vertices: np.ndarray, triangles: np.ndarray, max_edge: float, *,
                      max_vertices: int = 200_000) -> RefinedSurface:
    """Split every edge longer than ``max_edge`` at its midpoint until none is.

    Each pass marks the longest edge of every triangle that has one longer than ``max_edge``
    and splits all marked edges at once; a triangle with one, two or three split edges becomes
    two, three (the quad cut along its shorter diagonal) or four triangles, so no T-junction is
    ever left. After each pass, edges between two coplanar triangles are flipped towards
    Delaunay (:func:`flip_flat_edges`), which changes no point of the surface but keeps the
    splits of a fan (a low-poly cap) from piling up slivers at its apex.

    Raises:
        ValueError: ``max_edge`` is not positive, or refining would exceed ``max_vertices``.
    """
    if not (math.isfinite(max_edge) and max_edge > 0):
        raise ValueError(f"max_edge must be a positive length, got {max_edge!r}")
    x = np.asarray(vertices, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).copy()
    n0 = x.shape[0]
    parents: list[tuple[int, int]] = []
    while True:
        e = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1)  # [T, 3, 2]
        length = np.linalg.norm(x[e[..., 0]] - x[e[..., 1]], axis=2)  # [T, 3]
        longest = np.argmax(length, axis=1)
        rows = np.nonzero(length[np.arange(len(tris)), longest] > max_edge)[0]
        if rows.size == 0:
            break
        marked = np.sort(e[rows, longest[rows]], axis=1)
        marked = np.unique(marked, axis=0)
        if x.shape[0] + marked.shape[0] > max_vertices:
            raise ValueError(f"refining to edges of at most {max_edge:.4g} would need more than {max_vertices} vertices")
        base = x.shape[0]
        mid = {(int(a), int(b)): base + k for k, (a, b) in enumerate(marked)}
        x = np.concatenate([x, 0.5 * (x[marked[:, 0]] + x[marked[:, 1]])])
        parents.extend((int(a), int(b)) for a, b in marked)
        out = []
        for tri in tris:
            a, b, c = (int(i) for i in tri)
            m = [mid.get((min(a, b), max(a, b))), mid.get((min(b, c), max(b, c))), mid.get((min(c, a), max(c, a)))]
            k = sum(v is not None for v in m)
            if k == 0:
                out.append((a, b, c))
                continue
            # rotate so that the split edges come first: (a, b) split, then (b, c), then (c, a)
            for _ in range(3):
                if k == 3 or (k == 1 and m[0] is not None) or (k == 2 and m[2] is None):
                    break
                a, b, c = b, c, a
                m = m[1:] + m[:1]
            if k == 1:
                mab = m[0]
                out += [(a, mab, c), (mab, b, c)]
            elif k == 2:
                mab, mbc = m[0], m[1]
                out.append((mab, b, mbc))
                # the quad a, mab, mbc, c along its shorter diagonal
                if np.linalg.norm(x[a] - x[mbc]) <= np.linalg.norm(x[mab] - x[c]):
                    out += [(a, mab, mbc), (a, mbc, c)]
                else:
                    out += [(a, mab, c), (mab, mbc, c)]
            else:
                mab, mbc, mca = m
                out += [(a, mab, mca), (mab, b, mbc), (mca, mbc, c), (mab, mbc, mca)]
        tris = flip_flat_edges(x, np.array(out, dtype=np.int64))
    par = np.array(parents, dtype=np.int64).reshape(-1, 2)
    return RefinedSurface(x, tris, par, n0)


def flip_flat_edges(x: np.ndarray, triangles: np.ndarray, *, coplanar_cos: float = 1.0 - 1e-10,
                    max_passes: int = 50) -> np.ndarray:
    """Flip every edge shared by two coplanar, equally oriented triangles whose opposite angles
    sum to more than pi (the Delaunay criterion), until none is left or ``max_passes``. Only
    coplanar pairs are flipped, so the surface (every point of it) is unchanged; the
    orientation of each triangle is kept.

    Each pass tests every interior edge at once (arrays over the edges), then flips the edges
    that pass in the order of their first appearance (triangle by triangle, ``ab, bc, ca``),
    skipping an edge whose triangles a flip of this pass already changed or whose new diagonal
    is already an edge: a triangle is flipped at most once a pass.

    Args:
        x: Vertex positions ``[V, 3]``.
        triangles: ``[T, 3]`` vertex indices, consistently oriented where edges are flipped.

    Returns:
        The triangles ``[T, 3]`` (int64), same count and order, flipped edges replaced.
    """
    x = np.asarray(x, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3).copy()
    if len(tris) == 0:
        return tris
    span = int(max(x.shape[0], int(tris.max()) + 1))
    for _ in range(max_passes):
        t = len(tris)
        n = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
        ln = np.linalg.norm(n, axis=1)
        normals = n / np.where(ln > 0, ln, 1.0)[:, None]
        # directed edges a -> b of triangle k, c opposite; numbered in order of appearance
        a = tris.reshape(-1)
        b = tris[:, [1, 2, 0]].reshape(-1)
        c = tris[:, [2, 0, 1]].reshape(-1)
        owner = np.repeat(np.arange(t), 3)
        key = a * span + b
        # a directed edge met twice (a non-manifold fan) belongs to its last triangle and keeps
        # its first place in the order
        uniq, first = np.unique(key, return_index=True)
        _, last_rev = np.unique(key[::-1], return_index=True)
        last = len(key) - 1 - last_rev
        ua, ub = uniq // span, uniq % span
        rev = ub * span + ua
        pos = np.searchsorted(uniq, rev)
        pos = np.minimum(pos, len(uniq) - 1)
        has_twin = uniq[pos] == rev
        cand = np.nonzero((ua < ub) & has_twin)[0]
        if cand.size == 0:
            break
        e1, e2 = last[cand], last[pos[cand]]
        k1, k2 = owner[e1], owner[e2]
        ea, eb, ec, ed = ua[cand], ub[cand], c[e1], c[e2]
        undirected = np.unique(np.minimum(a, b) * span + np.maximum(a, b))
        cd = np.minimum(ec, ed) * span + np.maximum(ec, ed)
        j = np.minimum(np.searchsorted(undirected, cd), len(undirected) - 1)
        is_edge = undirected[j] == cd  # the new diagonal is an edge already (a flip may change that)
        ok = (np.einsum("ij,ij->i", normals[k1], normals[k2]) >= coplanar_cos) & (ec != ed)
        xa, xb, xc, xd = x[ea], x[eb], x[ec], x[ed]

        def angle(apex, p, q):
            u, w = p - apex, q - apex
            return np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w))

        ok &= angle(xc, xa, xb) + angle(xd, xa, xb) > math.pi + 1e-9
        # (a, b, c) and (b, a, d) become (c, a, d) and (d, b, c), both keeping the orientation;
        # where the quad is not convex a flip would fold it
        n1 = np.cross(xa - xc, xd - xc)
        n2 = np.cross(xb - xd, xc - xd)
        ok &= (np.einsum("ij,ij->i", n1, normals[k1]) > 0) & (np.einsum("ij,ij->i", n2, normals[k1]) > 0)
        todo = np.nonzero(ok)[0]
        todo = todo[np.argsort(first[cand[todo]], kind="stable")]
        touched: set[int] = set()
        added: set[int] = set()
        removed: set[int] = set()
        flipped = 0
        for i in todo.tolist():
            t1, t2 = int(k1[i]), int(k2[i])
            if t1 in touched or t2 in touched:
                continue
            e = int(cd[i])
            if e in added or (is_edge[i] and e not in removed):
                continue
            va, vb, vc, vd = int(ea[i]), int(eb[i]), int(ec[i]), int(ed[i])
            tris[t1] = (vc, va, vd)
            tris[t2] = (vd, vb, vc)
            removed.add(min(va, vb) * span + max(va, vb))
            added.add(e)
            touched.update((t1, t2))
            flipped += 1
        if not flipped:
            break
    return tris

"""Render meshes embedded in a simulated cage (the any-character issue, item 3).

Every render point is bound once, at rest, to its closest cage triangle: the barycentric
weights of that closest point and the point's offset from it in the local frame there (the
interpolated, normalised vertex normal; the triangle's first edge made tangent; their cross
product). The vertex normal is the cage's surface normal, or, for a cage simulated with layers
(``inner``: its fat layer), the direction from each cage vertex's inner particle to it: the
tissue's own direction, which needs no per-frame gather over the faces, so the embedding is one
launch per frame. Every frame, the same frame is built on the deformed cage and the offset
carried with it, by Warp kernels on the cage's device (``kernels.embedding``):

* at rest the render points come back exactly (to float32 rounding);
* under a rigid motion of the cage they move rigidly (every ingredient of the frame rotates);
* under a smooth deformation the offset turns with the surface but keeps its length, so the
  error grows with the strain times the offset (tested: within 15 % of the largest offset
  for a 10 % stretch).

Example:
    >>> emb = Embedding(render_points, cage_vertices, cage_triangles, device="cpu")
    >>> x = emb.evaluate(cage_positions)          # wp.array of vec3 [N], no host allocation
    >>> emb = Embedding(render_points, cage_vertices, cage_triangles, inner=fat_layer_at_rest)
    >>> x = emb.evaluate(np.concatenate([cage_positions, fat_positions]))   # one launch
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .errors import InputError

__all__ = ["Embedding"]


class Embedding:
    """Render points bound to a cage.

    Args:
        points: Render points at rest ``[N, 3]`` [m].
        cage_vertices: The cage at rest ``[V, 3]`` [m].
        cage_triangles: ``[T, 3]``, counter-clockwise from outside.
        inner: ``[V, 3]`` rest positions of an inner layer under the cage vertices (a simulated
            cage's fat layer), or ``None``. With it the normal at a cage vertex is the direction
            from its inner point to it, and :meth:`evaluate` reads the inner points from the same
            array, ``inner_offset`` entries after their cage vertices.
        inner_offset: Where :meth:`evaluate` finds vertex ``v``'s inner point: ``x[v +
            inner_offset]`` (default ``V``: the cage, then its inner layer; a simulation's
            layer-major particles: the model's vertex count).
        rigid: ``[N]`` the rigid piece of each point (``-1``: none), or ``None``. A rigid piece
            is not bound point by point: it moves as one rigid body with the best rigid fit of
            the cage region its points are closest to (the cage vertices, and their inner points,
            of its points' closest triangles, weighted by the points' barycentric weights), so
            an eye or a rigidly parented armour plate keeps its shape while it follows the cage.
        device: Warp device (the cage's simulation device).

    Attributes:
        face: ``[N]`` cage triangle of every point; ``bary`` ``[N, 3]``; ``offset`` ``[N, 3]``
            (host copies, for inspection); ``distance``: ``[N]`` rest distance to the cage [m] (a
            rigid piece's point: to its region's rest centre); ``group_count``: rigid pieces.
    """

    def __init__(self, points: np.ndarray, cage_vertices: np.ndarray, cage_triangles: np.ndarray, *,
                 inner: np.ndarray | None = None, inner_offset: int | None = None, rigid: np.ndarray | None = None,
                 device=None) -> None:
        from .kernels import embedding as k

        p = np.asarray(points, dtype=np.float64)
        cv = np.asarray(cage_vertices, dtype=np.float64)
        ct = np.asarray(cage_triangles, dtype=np.int64)
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
            raise InputError(f"embedding: render points must be finite [N, 3], got {p.shape}")
        if cv.ndim != 2 or cv.shape[1] != 3 or ct.ndim != 2 or ct.shape[1] != 3 or ct.size == 0:
            raise InputError(f"embedding: the cage must be vertices [V, 3] and triangles [T, 3], got {cv.shape}, {ct.shape}")
        if ct.min() < 0 or ct.max() >= cv.shape[0]:
            raise InputError(f"embedding: cage triangles index vertices outside [0, {cv.shape[0] - 1}]")
        rest_x = cv
        self.inner_offset = 0  # none: the surface normals
        if inner is not None:
            inner = np.asarray(inner, dtype=np.float64)
            if inner.shape != cv.shape or not np.isfinite(inner).all():
                raise InputError(f"embedding: the inner layer must be finite [{cv.shape[0]}, 3] like the cage, got {inner.shape}")
            depth = np.linalg.norm(cv - inner, axis=1)
            if depth.min() <= 1e-9 * max(float(np.ptp(cv, axis=0).max()), 1e-30):
                raise InputError(f"embedding: cage vertex {int(np.argmin(depth))} lies on its inner point (no direction)")
            offset_ = cv.shape[0] if inner_offset is None else int(inner_offset)
            if offset_ < cv.shape[0]:
                raise InputError(f"embedding: inner_offset must be at least the cage's {cv.shape[0]} vertices, got {offset_}")
            rest_x = np.zeros((offset_ + cv.shape[0], 3))
            rest_x[: cv.shape[0]] = cv
            rest_x[offset_:] = inner
            self.inner_offset = offset_
        group = np.full(p.shape[0], -1, dtype=np.int64) if rigid is None else np.asarray(rigid)
        if group.shape != (p.shape[0],) or not np.issubdtype(group.dtype, np.integer) or (group.size and group.min() < -1):
            raise InputError(f"embedding: rigid must be [{p.shape[0]}] integers (-1: no piece), got {group.shape} {group.dtype}")
        self.group_count = int(group.max()) + 1 if group.size else 0
        if self.group_count and np.setdiff1d(np.arange(self.group_count), group).size:
            raise InputError(f"embedding: rigid piece {int(np.setdiff1d(np.arange(self.group_count), group)[0])} has no point")
        self.device = wp.get_device(device)
        self.count = p.shape[0]
        self.cage_vertex_count = cv.shape[0]
        with wp.ScopedDevice(self.device):
            rest = wp.array(rest_x.astype(np.float32), dtype=wp.vec3)
            mesh = wp.Mesh(points=wp.array(cv.astype(np.float32), dtype=wp.vec3), indices=wp.array(ct.astype(np.int32).ravel(), dtype=wp.int32))
            pts = wp.array(p.astype(np.float32), dtype=wp.vec3)
            self._face = wp.zeros(self.count, dtype=wp.int32)
            self._bary = wp.zeros(self.count, dtype=wp.vec3)
            far = float(np.linalg.norm(np.ptp(np.concatenate([p, cv]), axis=0))) * 2.0 + 1.0
            wp.launch(k.closest_face_kernel, dim=self.count, inputs=[mesh.id, pts, far], outputs=[self._face, self._bary])
            face = self._face.numpy()
            if np.any(face < 0):
                raise InputError(f"embedding: render point {int(np.nonzero(face < 0)[0][0])} found no cage triangle")
            self.bary = self._bary.numpy().astype(np.float64)
            self._offset = wp.zeros(self.count, dtype=wp.vec3)
            self._out = wp.zeros(self.count, dtype=wp.vec3)
            # each point's triangle as its three vertices (one read instead of a face id and its row)
            self._point_tri = wp.array(ct[face].astype(np.int32), dtype=wp.vec3i)
            if self.inner_offset:  # the normals come from the inner layer, with the points
                self._normals = wp.zeros(1, dtype=wp.vec3)
            else:
                # vertex -> the other two vertices of each of its faces, counter-clockwise (CSR), for
                # the normals' gather: fewer reads than face ids and their three vertices each
                corner = ct.ravel()
                others = np.stack([np.roll(ct, -1, axis=1).ravel(), np.roll(ct, -2, axis=1).ravel()], axis=1)
                order = np.argsort(corner, kind="stable")
                counts = np.bincount(corner, minlength=self.cage_vertex_count)
                self._vw_offsets = wp.array(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32), dtype=wp.int32)
                self._vw_wedges = wp.array(others[order].astype(np.int32), dtype=wp.vec2i)
                # the cage vertices of the triangles some point is bound to: their normals, per frame
                self._used = wp.array(np.unique(ct[face].ravel()).astype(np.int32), dtype=wp.int32)
                self._normals = wp.zeros(self.cage_vertex_count, dtype=wp.vec3)
            self._cmd_cache: dict = {}
            self._group = wp.array(group.astype(np.int32) if self.group_count else np.zeros(0, np.int32), dtype=wp.int32)
            self._regions = self._rigid_regions(group, face, ct, cv, inner)
            # every piece's region motion of the frame (empty without pieces)
            self._motion = (wp.zeros(self.group_count, dtype=wp.vec3), wp.zeros(self.group_count, dtype=wp.mat33))
            for cmd in self._commands(rest)[:-1]:  # the rest normals (and the regions' fits)
                cmd.launch()
            wp.launch(k.rest_offsets_kernel, dim=self.count,
                      inputs=[rest, self._normals, self.inner_offset, self._point_tri, self._bary, pts],
                      outputs=[self._offset])
            if self.group_count:  # a rigid piece's points: their offsets from the region's rest centre
                off = self._offset.numpy()
                sel = group >= 0
                off[sel] = p[sel] - self._rest_centres[group[sel]]
                self._offset.assign(off.astype(np.float32))
        self.face = face
        self.offset = self._offset.numpy().astype(np.float64)
        self.distance = np.linalg.norm(self.offset, axis=1)

    def _rigid_regions(self, group: np.ndarray, face: np.ndarray, ct: np.ndarray, cv: np.ndarray, inner) -> dict | None:
        """The cage region of every rigid piece (CSR): the vertices of its points' closest
        triangles weighted by their barycentric weights (and their inner points, with the same
        weights: a flat patch then still fixes all three axes), with rest offsets from the
        region's weighted rest centre (:attr:`_rest_centres`)."""
        if not self.group_count:
            self._rest_centres = np.zeros((0, 3))
            return None
        v = cv.shape[0]
        sel = np.nonzero(group >= 0)[0]
        keys = np.repeat(group[sel], 3) * v + ct[face[sel]].ravel()
        uniq, inv = np.unique(keys, return_inverse=True)
        w = np.bincount(inv, weights=self.bary[sel].ravel())
        keep = w > 1e-9
        uniq, w = uniq[keep], w[keep]
        g, member = uniq // v, uniq % v
        rest = cv[member]
        if self.inner_offset:  # the inner points too
            g = np.concatenate([g, g])
            w = np.concatenate([w, w])
            rest = np.concatenate([rest, inner[member]])
            member = np.concatenate([member, member + self.inner_offset])
            order = np.argsort(g, kind="stable")
            g, w, rest, member = g[order], w[order], rest[order], member[order]
        counts = np.bincount(g, minlength=self.group_count)
        offsets = np.concatenate([[0], np.cumsum(counts)])
        centres = np.add.reduceat(rest * w[:, None], offsets[:-1]) / np.add.reduceat(w, offsets[:-1])[:, None]
        self._rest_centres = centres
        return {
            "offsets": wp.array(offsets.astype(np.int32), dtype=wp.int32),
            "members": wp.array(member.astype(np.int32), dtype=wp.int32),
            "weights": wp.array(w.astype(np.float32), dtype=wp.float32),
            "rest": wp.array((rest - centres[g]).astype(np.float32), dtype=wp.vec3),
        }

    def evaluate(self, cage_points) -> wp.array:
        """The render points on the cage ``cage_points`` (``wp.array`` of vec3 on the embedding's
        device, or a NumPy array, uploaded: ``[V]``, or with an inner layer at least
        ``inner_offset + V``, the inner points after the cage's): a ``wp.array`` ``[N]`` reused
        between calls (no allocation for a device array)."""
        x = cage_points
        need = self.inner_offset + self.cage_vertex_count
        if not isinstance(x, wp.array):
            arr = np.asarray(x, dtype=np.float32)
            if arr.ndim != 2 or arr.shape[1] != 3 or (arr.shape[0] < need if self.inner_offset else arr.shape[0] != need):
                what = f"at least [{need}, 3] (the cage, its inner layer from row {self.inner_offset})" \
                    if self.inner_offset else f"[{need}, 3]"
                raise InputError(f"embedding: cage points must be {what}, got {arr.shape}")
            x = wp.array(arr, dtype=wp.vec3, device=self.device)
        elif x.dtype != wp.vec3 or x.device != self.device or x.shape[0] < need:
            raise InputError(f"embedding: cage points must be a vec3 array of at least {need} points "
                             f"on {self.device}, got {x.dtype.__name__} [{x.shape[0]}] on {x.device}")
        for cmd in self._commands(x):
            cmd.launch()
        return self._out

    def _commands(self, x: wp.array) -> tuple:
        """The normals (none with an inner layer) and the points, as launches recorded for ``x``
        (a simulation alternates between two states' positions; recorded launches skip the
        per-call argument packing, most of the embedding's cost on the CPU beside the kernels
        themselves)."""
        from .kernels import embedding as k

        hit = self._cmd_cache.get(id(x))
        if hit is not None and hit[0] is x:
            return hit[1]
        if len(self._cmd_cache) >= 4:
            self._cmd_cache.clear()
        cmds = []
        r = self._regions
        if r is not None:
            cmds.append(wp.launch(k.rigid_regions_kernel, dim=self.group_count,
                                  inputs=[x, r["offsets"], r["members"], r["weights"], r["rest"]],
                                  outputs=list(self._motion), device=self.device, record_cmd=True))
        if not self.inner_offset:
            cmds.append(wp.launch(k.used_vertex_normals_kernel, dim=self._used.shape[0],
                                  inputs=[x, self._vw_offsets, self._vw_wedges, self._used], outputs=[self._normals],
                                  device=self.device, record_cmd=True))
        cmds.append(wp.launch(k.embed_kernel, dim=self.count,
                              inputs=[x, self._normals, self.inner_offset, self._point_tri, self._bary, self._offset,
                                      self._group, *self._motion],
                              outputs=[self._out], device=self.device, record_cmd=True))
        self._cmd_cache[id(x)] = (x, tuple(cmds))  # holds x, so its id stays its own
        return tuple(cmds)

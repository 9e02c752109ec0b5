"""The written meshes' deformation on the device: every written point is its LBS plus the
displacement it captured from the simulated surface (:mod:`warpskin.capture`), with the pieces
moved as a whole, the worn points wrapped on the surface, small pieces held at their joints
(:mod:`warpskin.kernels.deform`). :class:`WrittenDeformer` is the device side of
:meth:`warpskin.character.Character.points`; :func:`joint_points` finds where the written
pieces meet at rest."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from .kernels import deform as kd

if TYPE_CHECKING:
    from .capture import Capture
    from .character import Character

__all__ = ["WrittenDeformer", "joint_points", "SMALL_PIECE", "WRAP_SHARE"]


#: A written mesh moved by the capture no larger than this share of the character's diagonal is a
#: small piece (a hand, a prop) that keeps its joints by a share of its displacement
#: (:func:`~warpskin.kernels.deform.piece_limit_kernel`).
SMALL_PIECE = 0.4

#: A worn point lies at most this share of the free space along its normal from the written
#: surface it is wrapped on (:func:`~warpskin.kernels.deform.wrapped_point`).
WRAP_SHARE = 0.5


def joint_points(points: np.ndarray, triangles: np.ndarray, group: np.ndarray | None = None,
                 share: float = 0.02) -> np.ndarray:
    """``[N]`` bool: the points of a character's written meshes at rest (``points`` ``[N, 3]``,
    their ``triangles``) that lie within ``share`` of its bounding-box diagonal of a point of
    another piece (a connected part of the triangles: another mesh, or another part of one mesh;
    the points of one ``group`` >= 0, a piece moved as a whole, are one piece): where the pieces
    meet at their joints. Exact: each point's nearest neighbours are searched, twice as many
    each round, until one of another piece or the edge of the ball is reached."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    other = np.zeros(n, dtype=bool)
    if n < 2:
        return other
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    rows, cols = np.concatenate([t[:, 0], t[:, 1]]), np.concatenate([t[:, 1], t[:, 2]])
    count, label = connected_components(coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n)), directed=False)
    if group is not None:
        g = np.asarray(group, dtype=np.int64)
        label = np.where(g >= 0, count + g, label)
    reach = share * float(np.linalg.norm(np.ptp(pts, axis=0)))
    tree = cKDTree(pts)
    todo, k = np.arange(n), min(32, n)
    while todo.size:
        dist, idx = tree.query(pts[todo], k=k, distance_upper_bound=reach)
        dist, idx = dist.reshape(len(todo), -1), idx.reshape(len(todo), -1)
        found = np.isfinite(dist)
        other[todo] = (found & (label[np.where(found, idx, 0)] != label[todo][:, None])).any(axis=1)
        if k >= n:
            break
        todo = todo[found[:, -1] & ~other[todo]]  # every neighbour so far its own, the ball not exhausted
        k = min(2 * k, n)
    return other


def _group_anchors(rest: np.ndarray, joints: np.ndarray, grouped: np.ndarray, gid: np.ndarray, count: int,
                   most: int = 256, held: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per group of points moved as a whole (written points ``grouped``, group ``gid`` of each,
    ``count`` groups), its anchors: its :func:`joint_points` (``joints``, per written point at
    rest ``rest`` ``[N, 3]``), at most ``most`` of them spread over the list; a group that meets
    nothing gets its one point nearest another piece; a group whose ``held`` (per grouped point)
    is false gets none (it is not limited). Returns a CSR: ``(offsets [count + 1], written point
    indices)``, int32."""
    from scipy.spatial import cKDTree

    out: list[np.ndarray] = []
    for g in range(count):
        mine = grouped[gid == g]
        if (held is not None and not held[gid == g].any()) or not mine.size or mine.size == len(rest):
            out.append(np.zeros(0, dtype=np.int64))
            continue
        near = mine[joints[mine]]
        if not near.size:
            others = np.setdiff1d(np.arange(len(rest)), mine)
            near = mine[[int(np.argmin(cKDTree(rest[others]).query(rest[mine])[0]))]]
        if near.size > most:
            near = near[np.linspace(0, near.size - 1, most).round().astype(np.int64)]
        out.append(near)
    offsets = np.concatenate([[0], np.cumsum([a.size for a in out])]).astype(np.int32)
    return offsets, (np.concatenate(out) if out else np.zeros(0)).astype(np.int32)


class WrittenDeformer:
    """The device side of :meth:`Character.points` for a cage: the cage's displacement from its
    LBS, then every written point's LBS plus its captured displacement."""

    def __init__(self, character: Character, cap: Capture, joints: np.ndarray | None = None, *, device=None,
                 joint_gap: float = 0.01) -> None:
        import warp as wp

        from .device import resolve_device

        rig, sim = character.rig, character.sim_rig
        self.character = character
        self.device = resolve_device(device)
        j = rig.joint_count
        n = character.point_count
        parts = character.parts
        k = max(rig.joint_indices.shape[1], *[p.attachment.joint_indices.shape[1] for p in parts[1:]] or [1])
        ji = np.zeros((n, k), dtype=np.int32)
        jw = np.zeros((n, k), dtype=np.float32)
        bind = np.zeros((n, 3))
        for m, part in enumerate(parts):
            s, c = part.start, part.count
            if part.attachment is None:
                src_i, src_w, pts = rig.joint_indices[:c], rig.joint_weights[:c], rig.vertices[:c]
            else:
                a = part.attachment
                src_i, src_w, pts = a.joint_indices, a.joint_weights, a.vertices
            ji[s:s + c, :src_i.shape[1]] = m * j + src_i
            jw[s:s + c, :src_w.shape[1]] = src_w
            bind[s:s + c] = pts
        self.mesh_count = len(parts)
        self.influences = k
        # pieces that move as a whole: the best rigid motion, away from their LBS, of the
        # simulated vertices that carry them (their capture rows summed), the share phi of it
        # where the written pieces meet at rest (joint_points): kept within joint_gap x the
        # diagonal of their LBS, a rigid group by a share of its motion (group_limit_kernel), a
        # small captured mesh by a share of its displacement (piece_limit_kernel)
        rest = np.asarray(character.soup.points, dtype=np.float64)
        diagonal = float(np.linalg.norm(np.ptp(rest, axis=0)))
        self.joint_limit = joint_gap * diagonal if joint_gap > 0 else np.inf
        if joints is None:
            joints = joint_points(rest, character.soup.triangles, cap.group)
        grouped = np.nonzero(cap.group >= 0)[0]
        self.groups = None
        if grouped.size:
            gid = np.unique(cap.group[grouped], return_inverse=True)[1].ravel()
            ng = int(gid.max()) + 1
            rows = cap.indices[grouped].ravel()
            wts = (cap.weights[grouped] / np.maximum(cap.weights[grouped].sum(axis=1, keepdims=True), 1e-300)).ravel()
            owner = np.repeat(gid, cap.indices.shape[1])
            key = owner.astype(np.int64) * (sim.vertex_count + 1) + rows
            uniq, inv = np.unique(key[wts > 0], return_inverse=True)
            summed = np.bincount(inv.ravel(), weights=wts[wts > 0])
            g_of, v_of = uniq // (sim.vertex_count + 1), uniq % (sim.vertex_count + 1)
            totals = np.bincount(g_of, weights=summed, minlength=ng)
            summed = summed / totals[g_of]
            offsets = np.concatenate([[0], np.cumsum(np.bincount(g_of, minlength=ng))]).astype(np.int32)
            self.group_points = grouped
            self.groups = (offsets, v_of.astype(np.int32), summed.astype(np.float32), gid.astype(np.int32))
            # a simulated piece rigid in the file (a head on its joint, a hair bun) is one of the
            # character's own pieces, seamed to its neighbours: it moves with them, not held at LBS
            ps = character.pieces
            held = None if ps is None else ~ps.simulated[ps.piece_of_point[grouped]]
            self.anchor_offsets, self.anchors = _group_anchors(rest, joints, grouped, gid, ng, held=held)
        self.small = None  # small meshes moved by the capture (a skinned hand, a prop)
        if np.isfinite(self.joint_limit) and len(parts) > 1:
            pieces, anchors = [], []
            for part in parts:
                idx = np.arange(part.start, part.start + part.count)
                free = idx[cap.group[idx] < 0]
                size = float(np.linalg.norm(np.ptp(rest[idx], axis=0))) if idx.size else 0.0
                if free.size and size <= SMALL_PIECE * diagonal and joints[free].any():
                    pieces.append(free)
                    anchors.append(free[joints[free]])
            if pieces:
                offsets = np.concatenate([[0], np.cumsum([a.size for a in anchors])]).astype(np.int32)
                self.small = (offsets, np.concatenate(anchors).astype(np.int32),
                              np.concatenate(pieces).astype(np.int32),
                              np.concatenate([np.full(p.size, c) for c, p in enumerate(pieces)]).astype(np.int32))
        ks = sim.joint_indices.shape[1]
        v = sim.vertex_count
        with wp.ScopedDevice(self.device):
            self.bind_points = wp.array(bind.astype(np.float32), dtype=wp.vec3)
            self.ji = wp.array(ji.ravel(), dtype=wp.int32)
            self.jw = wp.array(jw.ravel(), dtype=wp.float32)
            self.cap_count = cap.indices.shape[1]
            self.cap_i = wp.array(cap.indices.astype(np.int32).ravel(), dtype=wp.int32)
            cap_w = cap.weights.astype(np.float32).copy()
            if self.groups is not None:  # a grouped point's capture is its group's motion instead
                cap_w[self.group_points] = 0.0
            self.cap_w = wp.array(cap_w.ravel(), dtype=wp.float32)
            self.phi = wp.array(cap.physics_weight.astype(np.float32), dtype=wp.float32)
            self.sim_rest = wp.array(sim.vertices.astype(np.float32), dtype=wp.vec3)
            self.sim_count = ks
            self.sim_ji = wp.array(sim.joint_indices.astype(np.int32).ravel(), dtype=wp.int32)
            self.sim_jw = wp.array(sim.joint_weights.astype(np.float32).ravel(), dtype=wp.float32)
            self.render_mats = wp.zeros(self.mesh_count * j, dtype=wp.mat44)
            self.sim_mats = wp.zeros(j, dtype=wp.mat44)
            self.sim_lbs = wp.zeros(v, dtype=wp.vec3)  # the surface's LBS where the caller has none
            self.out = wp.zeros(n, dtype=wp.vec3)
            if self.small is not None:
                offsets, anchors, points, piece = self.small
                self.small_arrays = (wp.array(offsets, dtype=wp.int32), wp.array(anchors, dtype=wp.int32),
                                     wp.array(points, dtype=wp.int32), wp.array(piece, dtype=wp.int32))
                self.small_share = wp.ones(len(offsets) - 1, dtype=wp.float32)
            if self.groups is not None:
                offsets, verts, wts, gid = self.groups
                self.group_arrays = (wp.array(offsets, dtype=wp.int32), wp.array(verts, dtype=wp.int32),
                                     wp.array(wts, dtype=wp.float32))
                ng = len(offsets) - 1
                self.group_motion = (wp.zeros(ng, dtype=wp.quat), wp.zeros(ng, dtype=wp.vec3),
                                     wp.zeros(ng, dtype=wp.vec3))
                self.group_share = wp.ones(ng, dtype=wp.float32)
                self.anchor_arrays = (wp.array(self.anchor_offsets, dtype=wp.int32),
                                      wp.array(self.anchors, dtype=wp.int32))
                self.group_apply = (wp.array(self.group_points.astype(np.int32), dtype=wp.int32),
                                    wp.array(gid, dtype=wp.int32))
            self.wrap = None
            if cap.wrap is not None:  # worn pieces: the surface's vertex normals, then each point on them
                wr = cap.wrap
                kc = wr.share.shape[1]
                self.wrap = (wp.array(wr.points.astype(np.int32), dtype=wp.int32), kc,
                             wp.array(wr.corners.astype(np.int32).ravel(), dtype=wp.int32),
                             wp.array(wr.bary.reshape(-1, 3).astype(np.float32), dtype=wp.vec3),
                             wp.array(wr.coef.reshape(-1, 3).astype(np.float32), dtype=wp.vec3),
                             wp.array(wr.share.ravel().astype(np.float32), dtype=wp.float32))
                body = wr.body
                # the written simulated pieces as they are (over the written points): their normals,
                # the free space along them, and the push-out
                self.body_triangles = wp.array(np.asarray(body, dtype=np.int32).ravel(), dtype=wp.int32)
                self.body_normals = wp.zeros(n, dtype=wp.vec3)
                self.body_mesh = wp.Mesh(points=self.out, indices=self.body_triangles)
                # the room along each worn point's normal at rest, on the rest surface
                rest_pts = wp.array(character.soup.points.astype(np.float32), dtype=wp.vec3)
                rest_mesh = wp.Mesh(points=rest_pts, indices=self.body_triangles)
                rest_normals = wp.zeros(n, dtype=wp.vec3)
                wp.launch(kd.surface_normals_kernel, dim=self.body_triangles.shape[0] // 3,
                          inputs=[rest_pts, self.body_triangles], outputs=[rest_normals])
                self.room0 = wp.zeros(wr.share.size, dtype=wp.float32)
                wp.launch(kd.room_kernel, dim=wr.share.size,
                          inputs=[rest_pts, rest_normals, rest_mesh.id, WRAP_SHARE, self.wrap[2], self.wrap[3],
                                  self.wrap[4]], outputs=[self.room0])
                self.clearance = wp.array(np.asarray(wr.clearance, dtype=np.float32), dtype=wp.float32)
                self.far = 2.0 * float(np.linalg.norm(np.ptp(sim.vertices, axis=0))) + 1.0
                self.max_push = float(character.pieces.edge)  # one edge of the simulated surface
        self.sim_vertex_count = v
        self._cmds: dict = {}

    def matrices(self, clip, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The written meshes' stacked skinning matrices ``[M * J, 4, 4]`` and the simulation
        surface's ``[J, 4, 4]`` at clip time ``t``."""
        c = self.character
        rig = c.rig
        world = rig.joint_world_transforms(clip, t)
        stack = [rig.skinning_matrices(clip, t)] + [world @ p.attachment.joint_offsets for p in c.parts[1:]]
        return np.concatenate(stack), c.sim_rig.skinning_matrices(clip, t)

    def evaluate(self, x, clip, t: float, surface_lbs=None):
        """The written points at clip time ``t`` for the simulation's positions ``x`` (device);
        ``surface_lbs``: the simulated surface's LBS at ``t`` where the caller has it on the
        device (the solver's tether targets), else computed here."""
        render, sim = self.matrices(clip, t)
        self.render_mats.assign(render.astype(np.float32))
        if surface_lbs is None:
            self.sim_mats.assign(sim.astype(np.float32))
        return self.launch(x, surface_lbs)

    def launch(self, x, surface_lbs=None):
        """The launches on the matrices last set: the written points, with the surface's
        displacement from its LBS gathered from ``surface_lbs`` (one launch) or computed here
        first (two). Recorded once per input arrays (a simulation alternates between its two
        states')."""
        import warp as wp

        from .kernels import deform as k

        key = (id(x), id(surface_lbs))
        hit = self._cmds.get(key)
        if hit is None or hit[0] is not x or hit[1] is not surface_lbs:
            if len(self._cmds) >= 4:
                self._cmds.clear()
            common = [self.bind_points, self.influences, self.ji, self.jw, self.render_mats, self.cap_count,
                      self.cap_i, self.cap_w, self.phi]
            cmds = []
            if surface_lbs is None:  # the surface's LBS first
                cmds.append(wp.launch(k.surface_lbs_kernel, dim=self.sim_vertex_count,
                                      inputs=[self.sim_rest, self.sim_count, self.sim_ji, self.sim_jw, self.sim_mats],
                                      outputs=[self.sim_lbs], device=self.device, record_cmd=True))
            cmds.append(wp.launch(k.deform_from_targets_kernel, dim=self.out.shape[0],
                                  inputs=[*common, x, self.sim_lbs if surface_lbs is None else surface_lbs],
                                  outputs=[self.out], device=self.device, record_cmd=True))
            if self.small is not None:
                offsets, anchors, points, piece = self.small_arrays
                lbs_in = [self.bind_points, self.influences, self.ji, self.jw, self.render_mats]
                cmds.append(wp.launch(k.piece_limit_kernel, dim=offsets.shape[0] - 1,
                                      inputs=[*lbs_in, self.out, offsets, anchors, float(self.joint_limit)],
                                      outputs=[self.small_share], device=self.device, record_cmd=True))
                cmds.append(wp.launch(k.piece_scale_kernel, dim=points.shape[0],
                                      inputs=[*lbs_in, points, piece, self.small_share],
                                      outputs=[self.out], device=self.device, record_cmd=True))
            if self.groups is not None:
                offsets, verts, wts = self.group_arrays
                cmds.append(wp.launch(k.group_fit_kernel, dim=offsets.shape[0] - 1,
                                      inputs=[x, self.sim_lbs if surface_lbs is None else surface_lbs, offsets,
                                              verts, wts],
                                      outputs=[*self.group_motion], device=self.device, record_cmd=True))
                if np.isfinite(self.joint_limit):
                    cmds.append(wp.launch(k.group_limit_kernel, dim=offsets.shape[0] - 1,
                                          inputs=[self.out, *self.group_motion, *self.anchor_arrays, self.phi,
                                                  float(self.joint_limit)],
                                          outputs=[self.group_share], device=self.device, record_cmd=True))
                cmds.append(wp.launch(k.group_apply_kernel, dim=self.group_apply[0].shape[0],
                                      inputs=[*self.group_apply, *self.group_motion, self.phi, self.group_share],
                                      outputs=[self.out], device=self.device, record_cmd=True))
            if self.wrap is not None:
                n = self.out.shape[0]
                after = (  # once the written pieces are in out (and the mesh over them refitted)
                    wp.launch(k.zero_vec3_kernel, dim=n, outputs=[self.body_normals], device=self.device,
                              record_cmd=True),
                    wp.launch(k.surface_normals_kernel, dim=self.body_triangles.shape[0] // 3,
                              inputs=[self.out, self.body_triangles], outputs=[self.body_normals], device=self.device,
                              record_cmd=True),
                    wp.launch(k.wrap_kernel, dim=self.wrap[0].shape[0],
                              inputs=[self.out, self.body_normals, self.body_mesh.id, WRAP_SHARE, *self.wrap, self.room0,
                                      self.phi],
                              outputs=[self.out], device=self.device, record_cmd=True),
                    wp.launch(k.push_out_kernel, dim=self.wrap[0].shape[0],
                              inputs=[self.body_mesh.id, self.body_normals, self.body_triangles, self.wrap[0],
                                      self.clearance, self.far, self.max_push],
                              outputs=[self.out], device=self.device, record_cmd=True))
            else:
                after = ()
            hit = self._cmds[key] = (x, surface_lbs, tuple(cmds), after)  # holds the arrays: their ids stay theirs
        for cmd in hit[2]:
            cmd.launch()
        if hit[3]:  # the worn points, on the written pieces as they are now
            self.body_mesh.refit()
            for cmd in hit[3]:
                cmd.launch()
        return self.out

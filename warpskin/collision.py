"""Self-collision of the skin layer: the launch wrappers of :mod:`warpskin.kernels.collision`.

Only the skin layer collides with itself, as in the paper: the inner layers follow the skin by
shape matching (their regions contain the skin particles' siblings), so they are kept apart
indirectly; at a strongly bent joint the bone layers, pinned to LBS, still interpenetrate, which
nobody sees.

Per step (Algorithm 1): :meth:`SelfCollision.detect` once on the predicted positions (BVH over
the skin triangles' swept boxes, refit every step), :meth:`project` inside every elasticity
iteration, :meth:`volume_weights` before the volume loop (colliding particles get weight 0) and
:meth:`friction_restitution` after the velocity update. Detection fills pre-sized buffers; if a
step finds more candidates than fit, :attr:`overflow` is raised and the caller calls
:meth:`grow` and repeats the step (``warpskin simulate`` does this per frame), so no contact is
ever dropped silently.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .errors import SceneError
from .kernels import collision as k

__all__ = ["CollisionParams", "SelfCollision", "skin_edges"]


@dataclass
class CollisionParams:
    """Self-collision settings.

    Attributes:
        enabled: Detect and resolve skin self-collisions.
        thickness: Contact thickness [m]; ``None``: 0.15 x the mean skin edge length.
        friction: Coulomb friction coefficient (>= 0).
        restitution: Restitution coefficient in [0, 1].
        capacity: Initial candidate buffer size per kind (grows on overflow).
        rigid_weight: A vertex whose largest weight is at least this moves rigidly with that bone;
            two such vertices of one bone never collide (their pairs are skipped).
        detection_margin: Candidates are searched within this many thicknesses (detection runs
            once per step; pairs that close in during the constraint loop must already be listed).
        rest_gap_margin: Vertices closer than this many search radii at rest belong to one
            surface patch: their pairs become contacts only when they cross during a step (a
            fold), never by proximity (side by side on a smooth surface they are closer than
            the thickness).
        fold_cos: Pairs of one surface patch whose normals are more than ``acos(fold_cos)``
            apart face each other across a fold (a crease or wrinkle) and collide by proximity
            like any other pair; default 0 (90 degrees).
        rebuild_spread: The BVH is refit every step and rebuilt (in place, between frames) once
            the skin has deformed by more than this fraction of its rest bounding-box diagonal
            since the last build (vertex displacements minus their mean); a refit keeps the
            tree's rest-pose topology, whose boxes overlap more and more as limbs swing.
        passes: Jacobi passes over the contacts per elasticity iteration (averaged corrections
            converge slowly where a particle is in several contacts).
    """

    enabled: bool = True
    thickness: float | None = None
    friction: float = 0.3
    restitution: float = 0.0
    capacity: int = 4096
    rigid_weight: float = 0.999
    detection_margin: float = 3.0
    rest_gap_margin: float = 2.0
    fold_cos: float = 0.0
    rebuild_spread: float = 0.1
    passes: int = 4

    def check(self, where: str = "collision") -> None:
        if self.thickness is not None and not (math.isfinite(self.thickness) and self.thickness > 0):
            raise SceneError(f"{where}: thickness must be a positive length [m], got {self.thickness!r}")
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise SceneError(f"{where}: friction must be >= 0, got {self.friction!r}")
        if not (0.0 <= self.restitution <= 1.0):
            raise SceneError(f"{where}: restitution must be in [0, 1], got {self.restitution!r}")
        if not (math.isfinite(self.detection_margin) and self.detection_margin >= 1.0):
            raise SceneError(f"{where}: detection_margin must be >= 1 (times the thickness), got {self.detection_margin!r}")
        if not (math.isfinite(self.rebuild_spread) and self.rebuild_spread > 0):
            raise SceneError(f"{where}: rebuild_spread must be > 0, got {self.rebuild_spread!r}")
        if not (math.isfinite(self.fold_cos) and -1.0 <= self.fold_cos <= 1.0):
            raise SceneError(f"{where}: fold_cos must be in [-1, 1], got {self.fold_cos!r}")
        if isinstance(self.passes, bool) or int(self.passes) != self.passes or self.passes < 1:
            raise SceneError(f"{where}: passes must be an integer >= 1, got {self.passes!r}")
        if isinstance(self.capacity, bool) or int(self.capacity) != self.capacity or self.capacity < 1:
            raise SceneError(f"{where}: capacity must be a positive integer, got {self.capacity!r}")


def skin_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges ``[E, 2]`` and each triangle's three edge indices ``[T, 3]``."""
    t = np.asarray(triangles, dtype=np.int64)
    directed = np.stack([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]], axis=1).reshape(-1, 2)
    und = np.sort(directed, axis=1)
    edges, inverse = np.unique(und, axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 3)


class SelfCollision:
    """Skin self-collision for one model (all buffers allocated here)."""

    def __init__(self, model, params: CollisionParams | None = None) -> None:
        self.params = params or CollisionParams()
        self.params.check()
        self.model = model
        rig = model.rig
        self.device = model.device
        tris = rig.triangles
        edges, tri_edges = skin_edges(tris)
        mean_edge = float(np.linalg.norm(rig.vertices[edges[:, 0]] - rig.vertices[edges[:, 1]], axis=1).mean())
        self.thickness = float(self.params.thickness) if self.params.thickness is not None else 0.15 * mean_edge
        self.radius = self.thickness * float(self.params.detection_margin)
        self.rest_gap = self.radius * float(self.params.rest_gap_margin)
        w = rig.joint_weights
        best = np.argmax(w, axis=1)
        rigid = np.where(w[np.arange(len(w)), best] >= self.params.rigid_weight,
                         rig.joint_indices[np.arange(len(w)), best], -1)
        v = rig.vertex_count
        dev = self.device
        with wp.ScopedDevice(dev):
            self.edge_indices = wp.array(edges.astype(np.int32), dtype=wp.int32)
            self.tri_edges = wp.array(tri_edges.astype(np.int32), dtype=wp.int32)
            owner = np.full(edges.shape[0], tris.shape[0], dtype=np.int64)  # first triangle of each edge
            np.minimum.at(owner, tri_edges.ravel(), np.repeat(np.arange(tris.shape[0]), 3))
            self.edge_owner = wp.array(owner.astype(np.int32), dtype=wp.int32)
            self.rigid_bone = wp.array(rigid.astype(np.int32), dtype=wp.int32)
            self.lowers = wp.array(rig.vertices[tris].min(axis=1).astype(np.float32), dtype=wp.vec3)
            self.uppers = wp.array(rig.vertices[tris].max(axis=1).astype(np.float32), dtype=wp.vec3)
            self.bvh = wp.Bvh(self.lowers, self.uppers)
            self.colliding = wp.zeros(4 * v, dtype=wp.int32)
            self.vertex_normals = wp.zeros(v, dtype=wp.vec3)
            self.delta = wp.zeros(v, dtype=wp.vec3)
            self.delta_count = wp.zeros(v, dtype=wp.int32)
            self.counts = wp.zeros(3, dtype=wp.int32)  # point-triangle, edge-edge, overflow flag
            # views of the counters (never reallocated), made once
            self.pt_count, self.ee_count, self.overflow_flag = self.counts[0:1], self.counts[1:2], self.counts[2:3]
            self.active = wp.zeros(1, dtype=wp.int32)  # violated constraints in the last iteration
        self._built_at = np.asarray(rig.vertices, dtype=np.float64)  # skin the tree was built for
        self._diagonal = float(np.linalg.norm(rig.vertices.max(axis=0) - rig.vertices.min(axis=0)))
        self.rebuilds = 0
        self.edge_count = int(edges.shape[0])
        self.triangle_count = int(tris.shape[0])
        self._alloc(int(self.params.capacity))

    def _alloc(self, capacity: int) -> None:
        self.capacity = capacity
        with wp.ScopedDevice(self.device):
            self.pt_vertex = wp.zeros(capacity, dtype=wp.int32)
            self.pt_triangle = wp.zeros(capacity, dtype=wp.int32)
            self.ee_a = wp.zeros(capacity, dtype=wp.int32)
            self.ee_b = wp.zeros(capacity, dtype=wp.int32)
            self.ee_sign = wp.zeros(capacity, dtype=wp.float32)

    def overflowed(self) -> bool:
        """Host check (syncs): did a detection since the last :meth:`clear_overflow` overflow?"""
        return bool(self.counts.numpy()[2])

    def clear_overflow(self) -> None:
        self.counts.zero_()

    def grow(self) -> None:
        """Double the candidate buffers until the last detection's counts fit."""
        c = self.counts.numpy()
        need = int(max(c[0], c[1]))
        cap = self.capacity
        while cap < need or cap == self.capacity:
            cap *= 2
        self._alloc(cap)
        self.counts.zero_()

    def maybe_rebuild(self, skin: np.ndarray) -> bool:
        """Host check between frames (never inside a captured graph): rebuild the BVH in place
        when the skin positions ``skin`` ``[V, 3]`` have deformed by more than
        ``rebuild_spread`` x the rest diagonal since the last build. Returns whether it did."""
        d = np.asarray(skin, dtype=np.float64) - self._built_at
        spread = float(np.linalg.norm(d - d.mean(axis=0), axis=1).max())
        if spread <= self.params.rebuild_spread * self._diagonal:
            return False
        self.bvh.rebuild()  # in place: graphs captured with this BVH stay valid
        self._built_at = np.array(skin, dtype=np.float64)
        self.rebuilds += 1
        return True

    # ------------------------------------------------------------------ per step
    def detect(self, x_old: wp.array, x_pred: wp.array) -> None:
        """Candidates on the predicted positions (swept from ``x_old``); skin layer only."""
        dev = self.device
        wp.launch(k.reset_collision_kernel, dim=self.colliding.shape[0], outputs=[self.colliding], device=dev)
        wp.launch(k.triangle_bounds_kernel, dim=self.triangle_count,
                  inputs=[x_old, x_pred, self.model.tri_indices, self.radius], outputs=[self.lowers, self.uppers], device=dev)
        self.bvh.refit()
        self.vertex_normals.zero_()
        wp.launch(k.vertex_normals_kernel, dim=self.triangle_count, inputs=[x_pred, self.model.tri_indices],
                  outputs=[self.vertex_normals], device=dev)
        fold = float(self.params.fold_cos)
        # zero the two counters, keep the overflow flag (cleared by the caller after checking)
        wp.launch(k.zero_counts_kernel, dim=1, outputs=[self.counts], device=dev)
        wp.launch(k.detect_point_triangle_kernel, dim=self.model.vertex_count,
                  inputs=[self.bvh.id, x_old, x_pred, self.model.tri_indices, self.rigid_bone, self.model.particle_q0,
                          self.rest_gap, self.vertex_normals, fold, self.thickness, self.radius, self.capacity],
                  outputs=[self.pt_count, self.pt_vertex, self.pt_triangle, self.overflow_flag, self.colliding], device=dev)
        wp.launch(k.detect_edge_edge_kernel, dim=self.edge_count,
                  inputs=[self.bvh.id, x_old, x_pred, self.edge_indices, self.tri_edges, self.edge_owner, self.lowers,
                          self.uppers, self.rigid_bone, self.model.particle_q0, self.rest_gap, self.vertex_normals, fold, self.radius,
                          self.capacity],
                  outputs=[self.ee_count, self.ee_a, self.ee_b, self.ee_sign, self.overflow_flag, self.colliding], device=dev)

    def project(self, x: wp.array, inv_mass: wp.array) -> None:
        """``params.passes`` Jacobi passes over all point-triangle and edge-edge constraints;
        :attr:`active` counts the constraints still violated in the last pass."""
        for _ in range(int(self.params.passes)):
            self._project_pass(x, inv_mass)

    def _project_pass(self, x: wp.array, inv_mass: wp.array) -> None:
        dev = self.device
        self.active.zero_()
        wp.launch(k.project_point_triangle_kernel, dim=self.capacity,
                  inputs=[x, inv_mass, self.model.tri_indices, self.pt_count, self.pt_vertex, self.pt_triangle, self.thickness],
                  outputs=[self.delta, self.delta_count, self.active], device=dev)
        wp.launch(k.project_edge_edge_kernel, dim=self.capacity,
                  inputs=[x, inv_mass, self.edge_indices, self.ee_count, self.ee_a, self.ee_b, self.ee_sign, self.thickness],
                  outputs=[self.delta, self.delta_count, self.active], device=dev)
        wp.launch(k.apply_deltas_kernel, dim=self.model.vertex_count, inputs=[self.delta, self.delta_count], outputs=[x], device=dev)

    def volume_weights(self, weight_scale: wp.array) -> None:
        wp.launch(k.volume_weights_kernel, dim=weight_scale.shape[0], inputs=[self.colliding], outputs=[weight_scale],
                  device=self.device)

    def friction_restitution(self, x: wp.array, v: wp.array, inv_mass: wp.array) -> None:
        dev = self.device
        wp.launch(k.friction_restitution_kernel, dim=self.capacity,
                  inputs=[x, v, inv_mass, self.model.tri_indices, self.pt_count, self.pt_vertex, self.pt_triangle,
                          float(self.params.friction), float(self.params.restitution)],
                  outputs=[self.delta, self.delta_count], device=dev)
        wp.launch(k.apply_deltas_kernel, dim=self.model.vertex_count, inputs=[self.delta, self.delta_count], outputs=[v], device=dev)


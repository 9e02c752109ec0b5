"""The rig: a rest mesh, a skeleton, skin weights and animation clips, all on the host.

Everything downstream (LBS/DQS baselines, the multi-layer model builder, the exporters) reads a
:class:`Rig`. Importers (:mod:`warpskin.io`) and procedural generators (:mod:`warpskin.scenes`)
produce one. A rig is in SI units (metres) once constructed; importers convert.

Skinning convention (glTF and UsdSkel agree on it)::

    p_world(t) = sum_j w_j * G_j(t) @ inverse_bind[j] @ p_rest

where ``G_j(t)`` is the world transform of joint ``j`` at time ``t`` (see
:meth:`Rig.joint_world_transforms`) and ``p_rest`` are :attr:`Rig.vertices`.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .animation import Clip, Track, key_rate
from .errors import RigError, RigWarning, index_list
from .mesh import mesh_edge_report, weld_by_position

from .transforms import compose_trs, decompose_trs, quat_normalize, quat_slerp
from .units import PLAUSIBLE, describe, extent, metres_per_unit

__all__ = [
    "RigError",
    "RigWarning",
    "Track",
    "Clip",
    "Skeleton",
    "Rig",
    "ValidationReport",
    "weld_by_position",
    "mesh_edge_report",
    "key_rate",
    "Attachment",
]


@dataclass
class Attachment:
    """Another mesh of the character that follows the skeleton by LBS: a mesh parented rigidly to
    a joint node (RobotExpressive's body parts: weight 1 to that joint, as three.js and Blender
    play it) or another skinned mesh on the same joints (its other hand). Written beside the
    skin; not simulated.

    Attributes:
        name: The mesh's name (unique in the rig).
        vertices: The file's points ``[N, 3]`` [m].
        triangles: ``[T, 3]``, counter-clockwise from outside.
        joint_indices, joint_weights: ``[N, K]`` influences (rig joint indices), weights
            summing to one.
        joint_offsets: ``[J, 4, 4]``: the transform from the file's points into each joint's
            space (the mesh's own inverse bind matrices; for a rigid mesh, its node transform
            below the joint), so that a point is ``sum_k w_k G_j(t) joint_offsets[j] p`` with
            ``G_j`` the rig's joint world transforms.
        render: Its UVs, normals and materials (:class:`~warpskin.io.render.RenderAttributes`).
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    joint_offsets: np.ndarray
    render: Any = None

    def points(self, joint_world: np.ndarray) -> np.ndarray:
        """Positions ``[N, 3]`` under the rig's joint world transforms ``[J, 4, 4]``."""
        mats = joint_world @ self.joint_offsets
        hom = np.c_[self.vertices, np.ones(len(self.vertices))]
        return np.einsum("vk,vkab,vb->va", self.joint_weights, mats[self.joint_indices], hom)[:, :3]

    def rescaled(self, factor: float) -> Attachment:
        s = np.diag([factor, factor, factor, 1.0])
        s_inv = np.diag([1.0 / factor] * 3 + [1.0])
        return dataclasses.replace(self, vertices=self.vertices * factor, joint_offsets=s @ self.joint_offsets @ s_inv)


# --------------------------------------------------------------------------------------------
# Skeleton
# --------------------------------------------------------------------------------------------


@dataclass
class Skeleton:
    """Joint hierarchy with its rest pose.

    Attributes:
        joint_names: Unique joint names, ``[J]``.
        parents: Parent joint index per joint, ``-1`` for a root, shape ``[J]``.
        rest_translation: Local rest translation [m], ``[J, 3]``.
        rest_rotation: Local rest rotation (quaternion x, y, z, w), ``[J, 4]``.
        rest_scale: Local rest scale, ``[J, 3]``.
        root_transform: World transform of the (non-joint) ancestors of each root joint,
            ``[J, 4, 4]``; only read where ``parents[j] == -1``. Identity by default.
        root_chains: For root joints whose ancestors a clip animates: the ancestor nodes top
            down, ``{joint: [(node, rest local 4x4), ...]}`` (their product is the joint's
            ``root_transform``); see :meth:`Clip.root_transforms`.
    """

    joint_names: list[str]
    parents: np.ndarray
    rest_translation: np.ndarray
    rest_rotation: np.ndarray
    rest_scale: np.ndarray
    root_transform: np.ndarray | None = None
    root_chains: dict[int, list[tuple[int, np.ndarray]]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.joint_names = [str(n) for n in self.joint_names]
        j = len(self.joint_names)
        self.parents = np.asarray(self.parents, dtype=np.int64).reshape(-1)
        self.rest_translation = np.asarray(self.rest_translation, dtype=np.float64).reshape(j, 3)
        self.rest_rotation = quat_normalize(np.asarray(self.rest_rotation, dtype=np.float64).reshape(j, 4))
        self.rest_scale = np.asarray(self.rest_scale, dtype=np.float64).reshape(j, 3)
        if self.root_transform is None:
            self.root_transform = np.tile(np.eye(4), (j, 1, 1))
        self.root_transform = np.asarray(self.root_transform, dtype=np.float64).reshape(j, 4, 4)
        if self.parents.size != j:
            raise RigError(f"skeleton has {j} joint names but {self.parents.size} parent entries")
        #: ``[J]`` every joint's number of ancestors (0: a root).
        self._order, self.depth = self._topological_order()

    @classmethod
    def from_local_matrices(
        cls,
        joint_names: list[str],
        parents: np.ndarray,
        rest_local: np.ndarray,
        root_transform: np.ndarray | None = None,
    ) -> Skeleton:
        """Build from local rest matrices ``[J, 4, 4]`` (decomposed into T, R, S)."""
        t, r, s = decompose_trs(np.asarray(rest_local, dtype=np.float64))
        return cls(list(joint_names), parents, t, r, s, root_transform)

    @property
    def joint_count(self) -> int:
        return len(self.joint_names)

    def _topological_order(self) -> tuple[np.ndarray, np.ndarray]:
        """``(order, depth)``: the joints parents first, and each joint's number of ancestors;
        raises :class:`RigError` on a parent index out of range, a repeated name or a cycle."""
        j = self.joint_count
        bad = np.nonzero((self.parents < -1) | (self.parents >= j))[0]
        if bad.size:
            k = int(bad[0])
            raise RigError(
                f"joint {k} ({self.joint_names[k]!r}) has parent index {int(self.parents[k])}, "
                f"outside [-1, {j - 1}]"
            )
        dup = {n for n in self.joint_names if self.joint_names.count(n) > 1}
        if dup:
            raise RigError(f"joint names are not unique: {sorted(dup)}")
        depth = np.full(j, -1, dtype=np.int64)
        for start in range(j):
            chain = []
            k = start
            while k != -1 and depth[k] < 0:
                if k in chain:
                    cyc = chain[chain.index(k):]
                    names = " -> ".join(self.joint_names[c] for c in cyc + [k])
                    raise RigError(f"cycle in the joint hierarchy: {names}")
                chain.append(k)
                k = int(self.parents[k])
            base = -1 if k == -1 else depth[k]
            for c in reversed(chain):
                base += 1
                depth[c] = base
        return np.argsort(depth, kind="stable"), depth

    def index(self, name: str) -> int:
        """Joint index of ``name``; raises :class:`RigError` listing the joints otherwise."""
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise RigError(f"no joint named {name!r}; joints are {self.joint_names}") from None

    def rest_local_matrices(self) -> np.ndarray:
        """Local rest transforms ``[J, 4, 4]``."""
        return compose_trs(self.rest_translation, self.rest_rotation, self.rest_scale)

    def world_from_local(self, local: np.ndarray, root: np.ndarray | None = None) -> np.ndarray:
        """Forward kinematics: world transforms ``[J, 4, 4]`` from local ones ``[J, 4, 4]``, under
        the root joints' ancestors ``root`` (default: the static :attr:`root_transform`)."""
        root = self.root_transform if root is None else root
        world = np.empty_like(local)
        for j in self._order:
            p = self.parents[j]
            world[j] = (root[j] if p < 0 else world[p]) @ local[j]
        return world

    def children(self, joint: int) -> np.ndarray:
        return np.nonzero(self.parents == joint)[0]


# --------------------------------------------------------------------------------------------
# Rig
# --------------------------------------------------------------------------------------------


@dataclass
class ValidationReport:
    """What :meth:`Rig.validate` found. ``errors`` make the rig unusable; ``warnings`` were
    repaired or only matter for the physical model."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    closed: bool = False
    manifold: bool = False
    boundary_edge_count: int = 0
    nonmanifold_edge_count: int = 0
    degenerate_triangles: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def ok(self) -> bool:
        return not self.errors


@dataclass
class Rig:
    """A skinned character: rest mesh, skeleton, weights and clips, in metres.

    Attributes:
        name: Display name (file stem or generator name).
        vertices: Rest (bind) positions [m], ``[V, 3]``, welded.
        triangles: Counter-clockwise (seen from outside) triangles into ``vertices``, ``[T, 3]``.
        skeleton: The joint hierarchy.
        joint_indices: Influencing joints per vertex, ``[V, K]`` (any ``K``; pad with weight 0).
        joint_weights: Weights per vertex, ``[V, K]``, summing to one.
        inverse_bind: Inverse bind matrices, ``[J, 4, 4]``: rest space to joint space.
        clips: Animation clips by name.
        source: File or generator the rig came from (for messages).
        mesh_name: Name of the mesh in the source file.
        weld_map: File vertex -> welded vertex, ``[N]`` (identity when nothing was welded).
        file_triangles: Triangles of the file's own (unwelded) topology, ``[T, 3]``.
        up_axis: ``"Y"`` or ``"Z"``, as the source said.
        meters_per_unit: Scale the source was converted by (informational).
        render: UVs, rest normals and materials of the file's topology
            (:class:`~warpskin.io.render.RenderAttributes`), or ``None``.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    skeleton: Skeleton
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    inverse_bind: np.ndarray
    clips: dict[str, Clip] = field(default_factory=dict)
    source: str = ""
    mesh_name: str = ""
    weld_map: np.ndarray | None = None
    file_triangles: np.ndarray | None = None
    up_axis: str = "Y"
    meters_per_unit: float = 1.0
    report: ValidationReport | None = None
    #: For a skin refined for the simulation (:meth:`refined`): the triangles of the skin as
    #: loaded (into this rig's first :attr:`output_count` vertices), and the two vertices each
    #: added vertex is the midpoint of, ``[added, 2]``. ``None`` for a rig as loaded.
    render_triangles: np.ndarray | None = None
    vertex_parents: np.ndarray | None = None
    render: Any = None
    #: Meshes parented rigidly to joints, written beside the skin (:class:`Attachment`).
    attachments: list = field(default_factory=list)
    #: What the vertices are called in messages: ``"file"`` (the file's own numbers, from
    #: :meth:`file_vertex_ids`), ``"cage"`` (an automatic or user cage: its own numbers) or
    #: ``"piece"`` (a character's own pieces made closed: :meth:`vertex_label`).
    vertex_kind: str = "file"
    #: For a surface of several pieces (:mod:`warpskin.preprocess.pieces`): their collision
    #: groups (:class:`~warpskin.preprocess.pieces.SurfaceGroups`), else ``None``.
    surface_groups: Any = None
    #: For a surface of several pieces: ``(file vertex [V] (-1: a cap's), mesh [V], mesh names,
    #: piece [V], piece names)``, what :meth:`vertex_label` says.
    surface_labels: Any = None

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.triangles = np.asarray(self.triangles, dtype=np.int64)
        self.joint_indices = np.asarray(self.joint_indices, dtype=np.int64)
        self.joint_weights = np.asarray(self.joint_weights, dtype=np.float64)
        self.inverse_bind = np.asarray(self.inverse_bind, dtype=np.float64)
        if self.joint_indices.ndim == 1:
            self.joint_indices = self.joint_indices[:, None]
        if self.joint_weights.ndim == 1:
            self.joint_weights = self.joint_weights[:, None]
        if self.weld_map is None:
            self.weld_map = np.arange(self.vertices.shape[0] if self.vertices.ndim == 2 else 0)
        if self.file_triangles is None:
            self.file_triangles = self.triangles.copy()

    # ---------------------------------------------------------------- construction helpers
    @classmethod
    def from_file_arrays(
        cls,
        *,
        name: str,
        points: np.ndarray,
        triangles: np.ndarray,
        skeleton: Skeleton,
        joint_indices: np.ndarray,
        joint_weights: np.ndarray,
        inverse_bind: np.ndarray,
        clips: dict[str, Clip] | None = None,
        source: str = "",
        mesh_name: str = "",
        weld: bool = True,
        weld_tolerance: float = 0.0,
        up_axis: str = "Y",
        meters_per_unit: float = 1.0,
        validate: bool = True,
        render: Any = None,
    ) -> Rig:
        """Build a rig from per-file-vertex arrays, welding split vertices by position.

        Weights of merged vertices come from the first file vertex of each group; a warning
        names groups whose weights disagree.
        """
        points = np.asarray(points, dtype=np.float64)
        triangles = np.asarray(triangles, dtype=np.int64)
        ji = np.asarray(joint_indices, dtype=np.int64)
        jw = np.asarray(joint_weights, dtype=np.float64)
        n = points.shape[0]
        for label, arr in (("joint indices", ji), ("joint weights", jw)):
            if arr.shape[0] != n:
                raise RigError(f"{source or name}: {n} vertices but {arr.shape[0]} rows of {label}")
        if triangles.size and (triangles.min() < 0 or triangles.max() >= n):
            bad = np.nonzero((triangles < 0).any(1) | (triangles >= n).any(1))[0]
            raise RigError(
                f"{source or name}: triangles {index_list(bad)} index vertices outside [0, {n - 1}]"
            )
        if weld and n:
            finite = np.all(np.isfinite(points), axis=1)
            if not finite.all():
                bad = np.nonzero(~finite)[0]
                raise RigError(f"{source or name}: vertices {index_list(bad)} have NaN or inf positions")
            first, wmap = weld_by_position(points, weld_tolerance)
        else:
            first, wmap = np.arange(n), np.arange(n)
        if first.size != n:
            # validate() sees the welded vertices only: a seam copy dropped by welding must not
            # hide bad weights
            dropped = np.setdiff1d(np.arange(n), first)
            w = jw[dropped]
            bad = dropped[~np.all(np.isfinite(w), axis=1) | (w < 0).any(axis=1) | ~(w.sum(axis=1) > 1e-12)]
            if bad.size:
                raise RigError(f"{source or name}: file vertices {index_list(bad)} (welded into others) have NaN, inf, "
                               "negative or all-zero joint weights")
        rig = cls(
            name=name,
            vertices=points[first],
            triangles=wmap[triangles],
            skeleton=skeleton,
            joint_indices=ji[first],
            joint_weights=jw[first],
            inverse_bind=inverse_bind,
            clips=dict(clips or {}),
            source=source,
            mesh_name=mesh_name,
            weld_map=wmap,
            file_triangles=triangles,
            up_axis=up_axis,
            meters_per_unit=meters_per_unit,
            render=render,
        )
        if render is not None:
            render.check(n, triangles.shape[0], source or name)
        rig = rig._bind_scale_normalised()
        if weld and first.size != n:
            dense = rig._dense_weights(ji, jw)
            diff = np.abs(dense - dense[first][wmap]).max(axis=1)
            split = np.nonzero(diff > 1e-4)[0]
            if split.size:
                rig._warn(
                    f"{split.size} file vertices share a position with a vertex of different "
                    f"weights (file vertices {index_list(split)}); the welded vertex keeps the "
                    "weights of the first"
                )
        if validate:
            rig.validate(raise_on_error=True)
        return rig

    def _bind_scale_normalised(self, tolerance: float = 1e-3) -> Rig:
        """The rig with its bind space scaled to match its animation, where every skinning
        matrix of the bind pose carries one uniform scale ``s`` (RobotExpressive: its armature
        node scales the 2 cm hand by 100): vertices x ``s``, inverse binds x ``1/s``, so the
        skinned points are unchanged and the skinning matrices rigid (shape matching follows
        rotations only). ``self`` otherwise; a warning says what was done."""
        j = self.skeleton.joint_count
        ib = np.asarray(self.inverse_bind)
        if ib.shape != (j, 4, 4) or self.joint_indices.shape != self.joint_weights.shape:
            return self  # validate() names what is wrong
        used = np.unique(self.joint_indices[self.joint_weights > 0])
        if used.size == 0 or used.min() < 0 or used.max() >= j or not np.isfinite(ib).all():
            return self
        mats = self.skeleton.world_from_local(self.skeleton.rest_local_matrices()) @ self.inverse_bind
        sv = np.array([np.linalg.svd(mats[j][:3, :3], compute_uv=False) for j in used])
        s = float(np.median(sv))
        if not np.isfinite(s) or s <= 0 or abs(s - 1.0) <= tolerance or np.abs(sv / s - 1.0).max() > tolerance:
            return self
        inv = np.diag([1.0 / s, 1.0 / s, 1.0 / s, 1.0])
        out = dataclasses.replace(self, vertices=self.vertices * s, inverse_bind=self.inverse_bind @ inv,
                                  report=self.report)
        out._warn(f"the skinning matrices scale the mesh by {s:.6g} (a scaled node above the skeleton); the bind "
                  "space is scaled to match (the skinned points are unchanged)")
        return out

    def _dense_weights(self, ji: np.ndarray, jw: np.ndarray) -> np.ndarray:
        j = self.skeleton.joint_count
        dense = np.zeros((ji.shape[0], j))
        ok = (ji >= 0) & (ji < j)
        rows = np.repeat(np.arange(ji.shape[0])[:, None], ji.shape[1], axis=1)
        np.add.at(dense, (rows[ok], ji[ok]), jw[ok])
        return dense

    def _warn(self, message: str) -> None:
        if self.report is None:
            self.report = ValidationReport()
        self.report.warnings.append(message)
        warnings.warn(f"{self.source or self.name}: {message}", RigWarning, stacklevel=3)

    # ---------------------------------------------------------------- properties
    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def triangle_count(self) -> int:
        return int(self.triangles.shape[0])

    @property
    def joint_count(self) -> int:
        return self.skeleton.joint_count

    @property
    def file_vertex_count(self) -> int:
        return int(self.weld_map.shape[0])

    def file_vertex_ids(self, welded) -> np.ndarray:
        """The file's own number (its first copy) of each welded vertex in ``welded``, for
        messages that the user can look up in their DCC."""
        first = np.full(self.vertex_count, -1, dtype=np.int64)
        n = self.weld_map.shape[0]
        first[self.weld_map[::-1]] = np.arange(n - 1, -1, -1)
        welded = np.asarray(welded, dtype=np.int64)
        if self.vertex_parents is not None:  # a vertex added by refining: the one it was split from
            from .preprocess.refine import extend_midpoints

            origin = extend_midpoints(np.arange(self.output_count), self.vertex_parents, take_first=True)
            welded = origin[welded]
        return first[welded]

    def vertex_label(self, k: int) -> str:
        """What messages call vertex ``k``: ``"file vertex N"`` (the file's number),
        ``"cage vertex N"``, or on a surface of pieces ``"file vertex N of mesh M"`` / ``"a cap
        vertex of piece P"`` (a cap is not in the file)."""
        k = int(k)
        if self.vertex_kind == "file":
            return f"file vertex {int(self.file_vertex_ids([k])[0])}"
        if self.vertex_kind == "piece" and self.surface_labels is not None:
            file_id, mesh, mesh_names, piece, piece_names = self.surface_labels
            if k < len(file_id) and file_id[k] >= 0:
                return f"file vertex {int(file_id[k])} of mesh {mesh_names[int(mesh[k])]!r}"
            if k < len(piece):
                return f"a cap vertex of piece {piece_names[int(piece[k])]!r}"
        return f"{self.vertex_kind} vertex {k}"

    @property
    def refined_skin(self) -> bool:
        """Whether the skin was refined for the simulation (:meth:`refined`)."""
        return self.vertex_parents is not None

    @property
    def output_count(self) -> int:
        """Vertices of the skin as loaded (what is written): the first of :attr:`vertices`."""
        return self.vertex_count - (0 if self.vertex_parents is None else int(self.vertex_parents.shape[0]))

    @property
    def output_triangles(self) -> np.ndarray:
        """Triangles of the skin as loaded, into its first :attr:`output_count` vertices."""
        return self.triangles if self.render_triangles is None else self.render_triangles

    def unrefined(self) -> Rig:
        """The rig as loaded, of a refined one (``self`` for a rig as loaded)."""
        if not self.refined_skin:
            return self
        n = self.output_count
        groups, labels = self.surface_groups, self.surface_labels
        if groups is not None:
            groups = dataclasses.replace(groups, group=np.asarray(groups.group)[:n])
        if labels is not None:
            labels = (labels[0][:n], labels[1][:n], labels[2], labels[3][:n], labels[4])
        return dataclasses.replace(
            self, vertices=self.vertices[:n].copy(), triangles=self.render_triangles.copy(),
            joint_indices=self.joint_indices[:n].copy(), joint_weights=self.joint_weights[:n].copy(),
            render_triangles=None, vertex_parents=None, report=None, surface_groups=groups, surface_labels=labels)

    def refined(self, max_edge: float) -> Rig:
        """A copy whose skin has every edge longer than ``max_edge`` [m] split at its midpoint
        (:func:`warpskin.preprocess.refine.refine_long_edges`); the loaded vertices stay the
        first ones, a midpoint's weights are the mean of its edge's. ``self`` when no edge is
        longer."""
        from .preprocess.refine import extend_midpoints, refine_long_edges

        if self.refined_skin:
            raise RigError(f"{self.source or self.name}: the skin is already refined")
        try:
            ref = refine_long_edges(self.vertices, self.triangles, max_edge)
        except ValueError as err:
            raise RigError(f"{self.source or self.name}: {err}; raise [layers] max_edge") from None
        if ref.added == 0:
            return self
        dense = extend_midpoints(self.dense_weights(), ref.parents)
        k = max(int((dense > 0).sum(axis=1).max()), 1)
        ji = np.argsort(-dense, axis=1, kind="stable")[:, :k]
        jw = np.take_along_axis(dense, ji, axis=1)
        jw /= jw.sum(axis=1, keepdims=True)
        groups, labels = self.surface_groups, self.surface_labels
        if groups is not None:  # an added vertex in its parents' group (a cap's, where one parent is)
            g = np.asarray(groups.group)
            f = groups.depth_factor
            groups = dataclasses.replace(groups, group=np.concatenate([g, g[ref.parents].max(axis=1)]),
                                         depth_factor=None if f is None else extend_midpoints(f, ref.parents))
        if labels is not None:
            f, m, mn, pc, pn = labels
            labels = (np.concatenate([f, np.full(ref.added, -1)]), np.concatenate([m, m[ref.parents[:, 0]]]), mn,
                      np.concatenate([pc, pc[ref.parents[:, 0]]]), pn)
        return dataclasses.replace(
            self,
            vertices=ref.vertices,
            triangles=ref.triangles,
            joint_indices=ji,
            joint_weights=jw,
            render_triangles=self.triangles.copy(),
            vertex_parents=ref.parents,
            report=None,
            surface_groups=groups,
            surface_labels=labels,
        )

    def size(self) -> float:
        """Diagonal of the rest mesh's bounding box [m] (the "model size" of tolerances)."""
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    def dense_weights(self) -> np.ndarray:
        """Weights as a dense ``[V, J]`` matrix."""
        return self._dense_weights(self.joint_indices, self.joint_weights)

    # ---------------------------------------------------------------- validation
    def validate(self, *, raise_on_error: bool = True) -> ValidationReport:
        """Check the rig and repair what is safe to repair.

        Errors (raised as :class:`RigError` unless ``raise_on_error=False``): NaN/inf in
        vertices, weights or matrices; a vertex without weight; negative weights; joint indices
        out of range; mismatched array sizes; cycles in the hierarchy (raised when the skeleton
        is built). Repaired with one warning: weight sums that are not one (normalised per
        vertex, as three.js and Blender do; the warning counts the vertices and names the
        worst). Reported: degenerate triangles, and whether the surface is closed and
        manifold (:meth:`require_closed` raises if not; LBS does not need it).
        """
        rep = ValidationReport(warnings=list(self.report.warnings) if self.report else [])
        errors = rep.errors
        v = self.vertices
        j = self.joint_count
        if v.ndim != 2 or v.shape[1] != 3:
            errors.append(f"vertices must have shape [V, 3], got {v.shape}")
            return self._finish(rep, raise_on_error)
        if self.triangles.ndim != 2 or self.triangles.shape[1] != 3:
            errors.append(f"triangles must have shape [T, 3], got {self.triangles.shape}")
            return self._finish(rep, raise_on_error)
        bad = np.nonzero(~np.all(np.isfinite(v), axis=1))[0]
        if bad.size:
            errors.append(f"vertices {index_list(bad)} have NaN or inf positions")
        if self.triangles.size and (self.triangles.min() < 0 or self.triangles.max() >= v.shape[0]):
            badt = np.nonzero((self.triangles < 0).any(1) | (self.triangles >= v.shape[0]).any(1))[0]
            errors.append(f"triangles {index_list(badt)} index vertices outside [0, {v.shape[0] - 1}]")
            return self._finish(rep, raise_on_error)
        if self.inverse_bind.shape != (j, 4, 4):
            errors.append(
                f"the skeleton has {j} joints but there are {self.inverse_bind.shape[0] if self.inverse_bind.ndim == 3 else '?'} "
                f"inverse bind matrices (shape {self.inverse_bind.shape})"
            )
        else:
            badj = np.nonzero(~np.all(np.isfinite(self.inverse_bind.reshape(j, 16)), axis=1))[0]
            if badj.size:
                names = [self.skeleton.joint_names[k] for k in badj[:8]]
                errors.append(f"inverse bind matrices of joints {names} hold NaN or inf")
            else:
                sing = np.nonzero(np.abs(np.linalg.det(self.inverse_bind[:, :3, :3])) < 1e-12)[0]
                if sing.size:
                    names = [self.skeleton.joint_names[k] for k in sing[:8]]
                    errors.append(f"inverse bind matrices of joints {names} are singular")
        for label, arr in (
            ("rest translation", self.skeleton.rest_translation),
            ("rest rotation", self.skeleton.rest_rotation),
            ("rest scale", self.skeleton.rest_scale),
        ):
            badj = np.nonzero(~np.all(np.isfinite(arr), axis=1))[0]
            if badj.size:
                errors.append(f"{label} of joints {[self.skeleton.joint_names[k] for k in badj[:8]]} holds NaN or inf")
        ji, jw = self.joint_indices, self.joint_weights
        if ji.shape != jw.shape or ji.shape[0] != v.shape[0]:
            errors.append(
                f"{v.shape[0]} vertices but joint indices of shape {ji.shape} and weights of shape {jw.shape}"
            )
            return self._finish(rep, raise_on_error)
        badw = np.nonzero(~np.all(np.isfinite(jw), axis=1))[0]
        if badw.size:
            errors.append(f"vertices {index_list(badw)} have NaN or inf weights")
            return self._finish(rep, raise_on_error)
        used = jw != 0.0
        oob = used & ((ji < 0) | (ji >= j))
        if oob.any():
            rows = np.nonzero(oob.any(axis=1))[0]
            vals = np.unique(ji[oob])
            errors.append(
                f"vertices {index_list(rows)} reference joint indices {index_list(vals)}, "
                f"outside [0, {j - 1}] (the skeleton has {j} joints)"
            )
        neg = np.nonzero((jw < 0.0).any(axis=1))[0]
        if neg.size:
            errors.append(f"vertices {index_list(neg)} have negative weights")
        sums = jw.sum(axis=1)
        zero = np.nonzero(sums <= 1e-12)[0]
        if zero.size:
            errors.append(f"vertices {index_list(zero)} have no weight (all weights are zero)")
        if not errors:
            off = np.abs(sums - 1.0)
            if off.max() > 1e-6:
                if off.max() <= 1e-3:
                    rep.warnings.append(
                        f"weight sums are off by rounding (up to {off.max():.2g}); normalised"
                    )
                else:
                    c = np.median(sums)
                    if np.all(np.abs(sums - c) <= 1e-3 * c):
                        rep.warnings.append(f"weights sum to {c:.6g} instead of 1 on every vertex; normalised")
                    else:  # normalised per vertex, as three.js and Blender do
                        n_off = int((off > 1e-3).sum())
                        k = int(np.argmax(off))
                        fid = int(self.file_vertex_ids([k])[0]) if self.weld_map is not None else k
                        rep.warnings.append(
                            f"the weights of {n_off} vertices do not sum to one (the worst, file vertex {fid}, sums to "
                            f"{sums[k]:.4g}); normalised per vertex"
                        )
                if not errors:
                    self.joint_weights = jw / sums[:, None]
        # scale: a body outside 5 cm - 20 m was most likely authored in other units
        if not errors and v.shape[0] and np.all(np.isfinite(v)):
            size = extent(v)
            if size > 0 and not (PLAUSIBLE[0] <= size <= PLAUSIBLE[1]):
                guess = metres_per_unit(size)
                rep.warnings.append(
                    f"the character is {size:.3g} units across, outside 5 cm - 20 m in metres: physics takes its unit "
                    f"as {describe(guess)} ([solver] units = \"file\" takes metres); --unit-scale {guess:g} (scene: "
                    f"[rig] unit_scale = {guess:g}) also writes it in metres"
                )
        # topology
        t = self.triangles
        if t.size:
            p0, p1, p2 = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
            area2 = np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
            scale = max(self.size(), 1e-30) if np.all(np.isfinite(v)) else 1.0
            repeated = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
            degenerate = np.nonzero(repeated | (area2 <= 1e-12 * scale * scale))[0]
            rep.degenerate_triangles = degenerate
            if degenerate.size:
                rep.warnings.append(f"degenerate (zero-area) triangles {index_list(degenerate)}")
            edges = mesh_edge_report(t, v.shape[0])
            rep.closed = bool(edges["closed"])
            rep.manifold = bool(edges["manifold"])
            rep.boundary_edge_count = int(edges["boundary_edges"].shape[0])
            rep.nonmanifold_edge_count = int(edges["nonmanifold_edges"].shape[0])
        else:
            errors.append("the mesh has no triangles")
        return self._finish(rep, raise_on_error)

    def _emit(self, message: str) -> None:
        warnings.warn(f"{self.source or self.name}: {message}", RigWarning, stacklevel=4)

    def _finish(self, rep: ValidationReport, raise_on_error: bool) -> ValidationReport:
        seen = set(self.report.warnings) if self.report is not None else set()
        for message in rep.warnings:
            if message not in seen:
                self._emit(message)
        self.report = rep
        if rep.errors and raise_on_error:
            where = self.source or self.name
            raise RigError(f"{where}: " + "; ".join(rep.errors))
        return rep

    def require_closed(self) -> None:
        """Raise :class:`RigError` unless the surface is closed, manifold and consistently wound
        (the physical model needs an inside). The message names offending edges/vertices."""
        # recomputed every time (cheap): the triangles may have changed since validation
        e = mesh_edge_report(self.triangles, self.vertex_count)
        where = self.source or self.name
        problems = []
        if e["boundary_edges"].shape[0]:
            problems.append(
                f"{e['boundary_edges'].shape[0]} boundary edges (open surface), e.g. between vertices "
                + ", ".join(f"{a}-{b}" for a, b in e["boundary_edges"][:4])
            )
        if e["nonmanifold_edges"].shape[0]:
            problems.append(
                f"{e['nonmanifold_edges'].shape[0]} edges shared by more than two triangles, e.g. "
                + ", ".join(f"{a}-{b}" for a, b in e["nonmanifold_edges"][:4])
            )
        if e["inconsistent_edges"].shape[0]:
            problems.append(
                f"{e['inconsistent_edges'].shape[0]} edges with inconsistent winding, e.g. "
                + ", ".join(f"{a}-{b}" for a, b in e["inconsistent_edges"][:4])
            )
        if e["nonmanifold_vertices"].size:
            problems.append(f"non-manifold vertices {index_list(e['nonmanifold_vertices'])}")
        if problems:
            raise RigError(f"{where}: mesh {self.mesh_name!r} is not a closed manifold surface: " + "; ".join(problems))

    # ---------------------------------------------------------------- animation
    def clip(self, name: str | None = None) -> Clip:
        """The clip called ``name``; the first clip when ``None``; an empty clip (rest pose)
        when the rig has none."""
        if name is None:
            if not self.clips:
                return Clip("rest")
            return next(iter(self.clips.values()))
        if name not in self.clips:
            known = ", ".join(repr(c) for c in self.clips) or "none"
            raise RigError(f"{self.source or self.name}: no clip named {name!r} (clips: {known})")
        return self.clips[name]

    def joint_world_transforms(self, clip: Clip | str | None, t: float) -> np.ndarray:
        """World transforms of every joint at time ``t`` [s], ``[J, 4, 4]``."""
        c = clip if isinstance(clip, Clip) else self.clip(clip)
        tr, rot, sc = c.sample_local_trs(self.skeleton, t)
        return self.skeleton.world_from_local(compose_trs(tr, rot, sc), c.root_transforms(self.skeleton, t))

    def skinning_matrices(self, clip: Clip | str | None, t: float) -> np.ndarray:
        """``G_j(t) @ inverse_bind[j]`` for every joint, ``[J, 4, 4]``."""
        return self.joint_world_transforms(clip, t) @ self.inverse_bind

    def skinning_matrices_from_bind(self, clip: Clip | str | None, t: float, u: float, *,
                                    keep_root: bool = True) -> np.ndarray:
        """Skinning matrices ``[J, 4, 4]`` of the pose ``u`` of the way from the bind pose
        (``u = 0``) to the clip's pose at ``t`` (``u = 1``): every joint's local translation
        and scale interpolated, its rotation slerped, then forward kinematics, so bones stay
        connected all the way (a pre-roll into a pose).

        With ``keep_root`` (the default) the root joints take their placement at ``t``
        throughout and only the joints below them move: the bind pose starts where the first
        frame puts the body (no global turn, as from CesiumMan's Z-up bind pose to its Y-up
        walk). Without it, ``u = 0`` is the mesh as modelled (identities)."""
        if not (0.0 <= u <= 1.0):
            raise RigError(f"blend factor u must be in [0, 1], got {u!r}")
        c = clip if isinstance(clip, Clip) else self.clip(clip)
        sk = self.skeleton
        bind = self.bind_world_transforms()
        parent_world = np.stack([sk.root_transform[j] if p < 0 else bind[p] for j, p in enumerate(sk.parents)])
        t0, r0, s0 = decompose_trs(np.linalg.solve(parent_world, bind))
        t1, r1, s1 = c.sample_local_trs(sk, t)
        if keep_root:
            roots = sk.parents < 0
            t0[roots], r0[roots], s0[roots] = t1[roots], r1[roots], s1[roots]
        local = compose_trs(t0 + u * (t1 - t0), quat_slerp(r0, r1, u), s0 + u * (s1 - s0))
        root = c.root_transforms(sk, t) if keep_root else None  # the roots' placement at t
        return sk.world_from_local(local, root) @ self.inverse_bind

    def bind_world_transforms(self) -> np.ndarray:
        """Joint transforms in rest space at bind time, ``inverse(inverse_bind)``, ``[J, 4, 4]``."""
        return np.linalg.inv(self.inverse_bind)

    # ---------------------------------------------------------------- hierarchy and authored keys
    def reparented(self, parents: dict[str, str], *, where: str = "") -> Rig:
        """A copy whose joints hang from the given parents (``{child: parent}``), with the rest
        pose the bind pose: for a file whose hierarchy is flat (the WebXR hand), so that a
        rotation authored on one joint carries the joints below it. Only for a rig without
        animation (its clips' local transforms would change meaning)."""
        where = where or self.source or self.name
        if any(c.tracks for c in self.clips.values()):
            raise RigError(f"{where}: [rig] parents can only be declared for a rig without animation clips")
        sk = self.skeleton
        new = sk.parents.copy()
        for child, parent in parents.items():
            c = sk.index(str(child))
            new[c] = -1 if parent in (None, "") else sk.index(str(parent))
        world = self.bind_world_transforms()
        root = sk.root_transform
        local = np.empty_like(world)
        for j in range(sk.joint_count):
            base = root[j] if new[j] < 0 else world[new[j]]
            local[j] = np.linalg.solve(base, world[j])
        skeleton = Skeleton.from_local_matrices(sk.joint_names, new, local, root.copy())  # raises on a cycle
        skeleton.root_chains = {j: chain for j, chain in sk.root_chains.items() if new[j] < 0}
        return dataclasses.replace(self, skeleton=skeleton, clips=dict(self.clips))

    def with_keys(self, name: str, keys: dict[str, list], *, interpolation: str = "LINEAR", where: str = "") -> Rig:
        """A copy with a clip ``name`` made from authored rotation keys: ``{joint: [[t, x, y, z],
        ...]}``, ``t`` in seconds, ``(x, y, z)`` in degrees about the joint's own rest axes
        (intrinsic X, then Y, then Z), added to its rest rotation; the other joints keep their
        rest pose."""
        from scipy.spatial.transform import Rotation

        where = where or self.source or self.name
        if interpolation not in ("LINEAR", "STEP"):
            raise RigError(f"{where}: key interpolation must be 'LINEAR' or 'STEP', got {interpolation!r}")
        sk = self.skeleton
        tracks = {}
        for joint, rows in keys.items():
            j = sk.index(str(joint))
            a = np.asarray(rows, dtype=np.float64) if len(rows) else np.zeros((0, 4))
            if a.ndim != 2 or a.shape[1] != 4 or not np.all(np.isfinite(a)):
                raise RigError(f"{where}: keys of joint {joint!r} must be rows [t, x_deg, y_deg, z_deg], got {rows!r}")
            if a.shape[0] > 1 and np.any(np.diff(a[:, 0]) <= 0):
                raise RigError(f"{where}: key times of joint {joint!r} must increase, got {a[:, 0].tolist()}")
            rest = Rotation.from_quat(sk.rest_rotation[j])
            q = (rest * Rotation.from_euler("XYZ", a[:, 1:], degrees=True)).as_quat()
            tracks[(j, "rotation")] = Track("rotation", a[:, 0], q, interpolation)
        clips = dict(self.clips)
        clips[name] = Clip(name, tracks)
        return dataclasses.replace(self, clips=clips)

    # ---------------------------------------------------------------- units
    def rescaled(self, factor: float) -> Rig:
        """A copy with every length multiplied by ``factor`` (e.g. 0.01 for centimetres)."""
        if not np.isfinite(factor) or factor <= 0.0:
            raise RigError(f"unit scale must be a positive number, got {factor}")
        s = np.diag([factor, factor, factor, 1.0])
        s_inv = np.diag([1.0 / factor] * 3 + [1.0])
        sk = self.skeleton
        skel = Skeleton(
            sk.joint_names,
            sk.parents.copy(),
            sk.rest_translation * factor,
            sk.rest_rotation.copy(),
            sk.rest_scale.copy(),
            s @ sk.root_transform @ s_inv,
            {j: [(node, s @ m @ s_inv) for node, m in chain] for j, chain in sk.root_chains.items()},
        )

        def scaled(tracks):
            out = {}
            for key, tr in tracks.items():
                vals = tr.values * factor if tr.path == "translation" else tr.values.copy()
                out[key] = Track(tr.path, tr.times.copy(), vals, tr.interpolation)
            return out

        clips = {cname: Clip(c.name, scaled(c.tracks), c.rate, scaled(c.ancestor_tracks))
                 for cname, c in self.clips.items()}
        return dataclasses.replace(
            self,
            vertices=self.vertices * factor,
            skeleton=skel,
            inverse_bind=s @ self.inverse_bind @ s_inv,
            clips=clips,
            meters_per_unit=self.meters_per_unit * factor,
            triangles=self.triangles.copy(),
            weld_map=self.weld_map.copy(),
            file_triangles=self.file_triangles.copy(),
            joint_indices=self.joint_indices.copy(),
            joint_weights=self.joint_weights.copy(),
            attachments=[a.rescaled(factor) for a in self.attachments],
        )

    def summary(self) -> dict:
        """Plain-data description (what ``warpskin info`` prints)."""
        rep = self.report or self.validate(raise_on_error=False)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        return {
            "name": self.name,
            "source": self.source,
            "mesh": self.mesh_name,
            "vertices": self.vertex_count,
            "file_vertices": self.file_vertex_count,
            "triangles": self.triangle_count,
            "joints": self.joint_count,
            "max_influences": int((self.joint_weights > 0).sum(axis=1).max()) if self.vertex_count else 0,
            "bbox_min": lo.tolist(),
            "bbox_max": hi.tolist(),
            "closed": rep.closed,
            "manifold": rep.manifold,
            "boundary_edges": rep.boundary_edge_count,
            "nonmanifold_edges": rep.nonmanifold_edge_count,
            "degenerate_triangles": int(rep.degenerate_triangles.size),
            "up_axis": self.up_axis,
            "meters_per_unit": self.meters_per_unit,
            "clips": {n: {"start": c.start, "end": c.end, "tracks": len(c.tracks)} for n, c in self.clips.items()},
            "warnings": list(rep.warnings),
            "errors": list(rep.errors),
        }

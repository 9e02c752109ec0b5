"""The three inner layers (fat, muscle, bone) under the skin.

Deul & Bender 2013, section 3: each skin vertex ``x_i`` and the nearest point ``f_i`` on the
center line of its bone define the projection segment; layer ``k`` vertex is
``x_i + p_k (f_i - x_i)`` with projection parameters ``0 < p_fat < p_muscle < p_bone < 1``
(per scene, optionally per bone: a fat belly uses small parameters). Every layer keeps the skin
topology; particle ``i`` of layer ``k`` is a sibling of particle ``i`` on the other layers.

Particles are numbered layer-major: global index ``k * V + i`` for layer ``k`` in
``(skin, fat, muscle, bone)`` = ``(0, 1, 2, 3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..collision import skin_edges
from ..errors import SceneError
from ..mesh import face_normals, vertex_normals
from ..metrics import self_intersections
from ..settings import check_settings, setting
from ..rig import Rig, RigError, RigWarning
from .bones import Bones, bone_segments, closest_point_on_segments, dominant_bone
from .refine import extend_midpoints

__all__ = ["LayerParams", "Layers", "build_layers", "fit_layer_depths", "fit_piece_depths", "folded_triangles", "LAYER_NAMES",
           "check_layer_folds"]

LAYER_NAMES = ("skin", "fat", "muscle", "bone")


@dataclass
class LayerParams:
    """Projection parameters of the inner layers.

    Attributes:
        fat, muscle, bone: Positions along the projection segment (0 = skin, 1 = bone center
            line); must satisfy ``0 < fat < muscle < bone < 1``. The paper's Arm: 0.15/0.45/0.8.
        per_bone: Overrides by joint name: ``{"belly": (0.05, 0.1, 0.2)}``.
        adaptive: The parameters are upper bounds: the depth is reduced locally, and
            smoothly, where the full depth would fold a layer over or leave the body
            (:func:`fit_layer_depths`). ``False``: the parameters as given, and an error where
            a layer folds.
    """

    _section = "layers"

    fat: float = setting(0.15, "number", "fat layer: position along the projection segment (0 skin, 1 bone centre "
                         "line), an upper bound with adaptive", low=0.0, high=1.0, open_low=True, open_high=True,
                         must="in (0, 1), below muscle")
    muscle: float = setting(0.45, "number", "muscle layer: as fat", low=0.0, high=1.0, open_low=True, open_high=True,
                            must="in (0, 1), between fat and bone")
    bone: float = setting(0.8, "number", "bone layer: as fat", low=0.0, high=1.0, open_low=True, open_high=True,
                          must="in (0, 1), above muscle")
    adaptive: bool = setting(True, "bool", "the projection parameters are upper bounds, reduced locally where the "
                             "full depth would fold a layer (false: as given, a fold is an error)")
    per_bone: dict[str, tuple[float, float, float]] = setting(
        {}, "table", "overrides by joint name: [layers.per_bone.JOINT] projection = [fat, muscle, bone], stiffness = "
        "[skin, fat, muscle, bone]")

    def check(self, where: str = "layers") -> None:
        for name, p in [("default", (self.fat, self.muscle, self.bone))] + list(self.per_bone.items()):
            p = tuple(float(x) for x in p)
            if len(p) != 3 or not all(np.isfinite(p)):
                raise SceneError(f"{where}: projection parameters of {name!r} must be three numbers, got {p}")
            if not (0.0 < p[0] < p[1] < p[2] < 1.0):
                raise SceneError(
                    f"{where}: projection parameters of {name!r} must satisfy 0 < fat < muscle < bone < 1, "
                    f"got fat={p[0]}, muscle={p[1]}, bone={p[2]}"
                )
        check_settings(self, where, "layers")


@dataclass
class Layers:
    """The layered rest geometry.

    Attributes:
        positions: Rest positions per layer [m], ``[4, V, 3]`` (skin, fat, muscle, bone).
        foot: Nearest point on the vertex's bone center line [m], ``[V, 3]`` (where that lies
            outside the skin, :func:`fit_layer_depths` puts it as far along the inward normal).
        bone: The vertex's bone (joint index), ``[V]``.
        bone_t: Parameter of the foot along its bone segment, ``[V]`` in [0, 1].
        params: Projection parameters used per vertex, ``[V, 3]`` (fat, muscle, bone), after
            any local reduction (:func:`fit_layer_depths`).
        bones: The bone segments.
        depth_scale: Per-vertex factor on the scene's projection parameters, ``[V]`` in (0, 1]
            (1 where the full depth fits).
        depth_notes: What :func:`fit_layer_depths` reduced, where and why (for reports).
        unresolved: ``[V]`` bool, the vertices where no positive depth fits (the skin there
            folds over or leaves the body however thin the layers are): they keep the thinnest
            depth and their folds are tolerated; what is written follows LBS there (physics
            weight 0, :mod:`warpskin.character`).
    """

    positions: np.ndarray
    foot: np.ndarray
    bone: np.ndarray
    bone_t: np.ndarray
    params: np.ndarray
    bones: Bones
    depth_scale: np.ndarray | None = None
    depth_notes: list[str] = field(default_factory=list)
    unresolved: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.depth_scale is None:
            self.depth_scale = np.ones(self.positions.shape[1])
        if self.unresolved is None:
            self.unresolved = np.zeros(self.positions.shape[1], dtype=bool)

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[1])

    @property
    def particle_count(self) -> int:
        return 4 * self.vertex_count

    def refined(self, parents: np.ndarray) -> Layers:
        """The layers of a skin refined by midpoint splits (``parents`` ``[A, 2]``, each added
        vertex's two parents, in order: :attr:`~warpskin.rig.Rig.vertex_parents`):
        every added vertex's layer positions, foot and parameters are its parents' mean, so
        each refined layer triangle lies inside a layer triangle of the coarse skin and folds
        nowhere the coarse layers do not; its bone is its first parent's."""
        return Layers(
            positions=np.stack([extend_midpoints(x, parents) for x in self.positions]),
            foot=extend_midpoints(self.foot, parents),
            bone=extend_midpoints(self.bone, parents, take_first=True),
            bone_t=extend_midpoints(self.bone_t, parents),
            params=extend_midpoints(self.params, parents),
            bones=self.bones,
            depth_scale=extend_midpoints(self.depth_scale, parents),
            depth_notes=list(self.depth_notes),
            unresolved=extend_midpoints(self.unresolved.astype(np.float64), parents) > 0,
        )

    def flat(self) -> np.ndarray:
        """All particle rest positions, layer-major, ``[4 V, 3]``."""
        return self.positions.reshape(-1, 3)


def build_layers(rig: Rig, params: LayerParams | None = None, *, bones: Bones | None = None) -> Layers:
    """Project every skin vertex toward its bone to make the fat, muscle and bone layers, at
    the scene's projection parameters (``params``, per bone where it sets them), times a surface
    of pieces' ``surface_groups.depth_factor`` elsewhere (thinner tissue beneath rigid pieces).

    Raises:
        RigError: parameters out of order, an override naming an unknown joint.
    """
    params = params or LayerParams()
    where = rig.source or rig.name
    params.check(where)
    bones = bones or bone_segments(rig)
    bone = dominant_bone(rig)
    foot, t = closest_point_on_segments(rig.vertices, bones.start[bone], bones.end[bone])
    per_joint = np.tile([params.fat, params.muscle, params.bone], (rig.joint_count, 1)).astype(np.float64)
    overridden = np.zeros(rig.joint_count, dtype=bool)
    for name, p in params.per_bone.items():
        per_joint[rig.skeleton.index(name)] = p
        overridden[rig.skeleton.index(name)] = True
    p = per_joint[bone]
    # a surface of pieces: thinner tissue beneath pieces rigid on the same joint
    # (PieceParams.bony_depth), where the scene does not set that bone's parameters itself
    factor = rig.surface_groups.depth_factor if rig.surface_groups is not None else None
    if factor is not None:
        p = p * np.where(overridden[bone], 1.0, np.asarray(factor, dtype=np.float64))[:, None]
    seg = foot - rig.vertices
    positions = np.empty((4, rig.vertex_count, 3))
    positions[0] = rig.vertices
    for k in range(3):
        positions[k + 1] = rig.vertices + p[:, k, None] * seg
    return Layers(positions=positions, foot=foot, bone=bone, bone_t=t, params=p, bones=bones)


def check_layer_folds(layers: Layers, triangles: np.ndarray, *, where: str = "layers") -> None:
    """Raise a clear error where an inner layer folds over (a triangle whose normal turned
    against the skin triangle's), which makes the layer self-intersect; triangles at
    :attr:`Layers.unresolved` vertices are tolerated.

    The message names the layer, the triangles and the bones involved, and what to change.
    """
    skin = layers.positions[0]
    tolerated = layers.unresolved[triangles].any(axis=1)
    n0 = face_normals(skin, triangles)
    for k in range(1, 4):
        n = face_normals(layers.positions[k], triangles)
        dot = np.einsum("ij,ij->i", n, n0)
        flipped = np.nonzero((dot <= 0.0) & ~tolerated)[0]
        if flipped.size:
            bones = np.unique(layers.bone[triangles[flipped].ravel()])
            names = [layers.bones.joint_names[b] for b in bones[:6]]
            raise RigError(
                f"{where}: the {LAYER_NAMES[k]} layer folds over at {flipped.size} triangles "
                f"(e.g. {', '.join(str(int(f)) for f in flipped[:6])}; bones {names}): its projection "
                "parameter is too large there; lower it (globally or for those bones)"
            )


# --------------------------------------------------------------------------------------------
# Depths that fit the body: the projection parameters as upper bounds
# --------------------------------------------------------------------------------------------
def _layer_positions(vertices: np.ndarray, seg: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """``[L, V, 3]`` positions at per-vertex depths ``[L, V]`` (fractions of the segment)."""
    return vertices[None] + depth[:, :, None] * seg[None]


def folded_triangles(skin: np.ndarray, layer: np.ndarray, triangles: np.ndarray, *, min_cos: float = 0.0) -> np.ndarray:
    """Triangles of ``layer`` (same topology as ``skin``) whose normal turned by 90 degrees or
    more against the skin triangle's (``cos <= min_cos``), or collapsed: the layer folds over
    there. Returns their indices."""
    t = triangles
    n0, n = face_normals(skin, t), face_normals(layer, t)
    dot = np.einsum("ij,ij->i", n, n0)
    norm = np.linalg.norm(n, axis=1) * np.linalg.norm(n0, axis=1)
    return np.nonzero(dot <= min_cos * np.maximum(norm, 1e-300))[0]


def _segment_exits(rig: Rig, seg: np.ndarray, reach: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each projection segment leaves the body: the distance [m] along it to the first
    surface hit past its own vertex (``inf`` where it stays inside for ``reach`` [m]), and
    whether it enters the body at its vertex at all (``False``: it points out of the skin)."""
    import warp as wp

    from ..kernels import layers as k

    length = np.linalg.norm(seg, axis=1)
    out = np.full(rig.vertex_count, np.inf)
    inside = np.ones(rig.vertex_count, dtype=bool)
    ok = length > 0
    if not ok.any():
        return out, inside
    direction = np.zeros_like(seg)
    direction[ok] = seg[ok] / length[ok, None]
    # a small step in: well above float32 rounding of the coordinates, well below an edge
    edge = np.linalg.norm(rig.vertices[rig.triangles[:, 0]] - rig.vertices[rig.triangles[:, 1]], axis=1)
    offset = 1e-2 * float(np.median(edge)) if edge.size else 1e-6
    with wp.ScopedDevice("cpu"):
        mesh = wp.Mesh(points=wp.array(rig.vertices.astype(np.float32), dtype=wp.vec3),
                       indices=wp.array(rig.triangles.astype(np.int32).ravel(), dtype=wp.int32),
                       support_winding_number=True)
        exit_d = wp.zeros(rig.vertex_count, dtype=wp.float32)
        starts = wp.zeros(rig.vertex_count, dtype=wp.int32)
        wp.launch(k.segment_exit_kernel, dim=rig.vertex_count,
                  inputs=[mesh.id, wp.array(rig.vertices.astype(np.float32), dtype=wp.vec3),
                          wp.array(direction.astype(np.float32), dtype=wp.vec3),
                          wp.array(np.where(ok, reach, 0.0).astype(np.float32), dtype=wp.float32), float(offset)],
                  outputs=[exit_d, starts])
        d = exit_d.numpy().astype(np.float64)
        inside = starts.numpy().astype(bool) | ~ok
    hit = ok & (d > 0)
    out[hit] = d[hit]
    return out, inside


def _ramp(scale: np.ndarray, edges: np.ndarray, step: float) -> np.ndarray:
    """Lower ``scale`` until neighbours differ by at most ``step`` (never raise it): a reduced
    vertex pulls its surroundings down gradually, so the depth varies smoothly."""
    s = scale.copy()
    a, b = edges[:, 0], edges[:, 1]
    for _ in range(int(np.ceil(1.0 / step)) + 1):
        before = s.copy()
        np.minimum.at(s, a, s[b] + step)
        np.minimum.at(s, b, s[a] + step)
        if np.array_equal(s, before):
            break
    return s


def fit_layer_depths(rig: Rig, layers: Layers, *, where: str = "layers", shrink: float = 0.9, ramp: float = 0.15,
                     min_scale: float = 0.02, max_rounds: int = 200, exit_margin: float = 0.9,
                     anchor_outward: bool = False) -> Layers:
    """Reduce the depth of the inner layers locally, and smoothly, wherever the full depth does
    not fit: where a layer (or the tissue between two layers) would fold over, where the layer
    would pass through itself, and where a projection segment leaves the body before the bone
    layer. The scene's projection parameters become upper bounds.

    Every vertex ``i`` gets a factor ``s_i`` in (0, 1] on its three parameters (so their order
    stays): ``s_i`` starts at the share of the segment that stays inside the body
    (``exit_margin`` of the way to the exit), lowered around such vertices until neighbours
    differ by at most ``ramp``; then, round by round, the vertices of every folded or
    self-intersecting triangle and their neighbours are scaled by ``shrink``. At ``s = 0``
    every layer is the skin itself, which does not fold, so the rounds end.

    Args:
        rig: The closed rig.
        layers: The layers of :func:`build_layers` (the full parameters).
        where: For messages.

    Returns:
        New :class:`Layers` with ``params``, ``positions`` and ``depth_scale`` fitted and
        ``depth_notes`` saying where depth was taken away and why.

    Where no positive depth fits (``s`` below ``min_scale``: the skin folds over or leaves
    the body however thin the layers are) the vertices keep ``min_scale`` and are marked
    :attr:`Layers.unresolved`, with a note that counts them and names their bones; the run
    writes LBS there.

    A vertex whose bone lies outside the skin (its segment points out of the body) goes in along
    its inward normal instead, as deep as its bone is far; with ``anchor_outward`` (a piece
    attached to a body whose bone it does not hold: a hair bun on the skull) it is anchored
    instead: the thinnest depth (``min_scale``), the piece held where it meets the body and free
    away from it (it is not marked unresolved).
    """
    v = rig.vertices
    tris = rig.triangles
    seg = layers.foot - v
    p = layers.params
    deepest = p[:, 2]
    length = np.linalg.norm(seg, axis=1)
    typical = float(np.median(length[length > 0])) if (length > 0).any() else 0.0
    on_bone = length <= 1e-6 * typical
    if on_bone.any():  # a vertex on its bone's centre line has no way in: along its inward normal
        seg[on_bone] = -vertex_normals(v, tris)[on_bone] * typical
        length = np.linalg.norm(seg, axis=1)
    exits, inward = _segment_exits(rig, seg, deepest * length / exit_margin)
    outward = ~inward
    if outward.any() and not anchor_outward:
        # the nearest point of the bone lies outside the skin here (the segment points out of
        # the body): such a vertex's layers go in along its inward normal instead, as deep as
        # its bone is far
        seg[outward] = -vertex_normals(v, tris)[outward] * length[outward, None]
        again, _ = _segment_exits(rig, seg, deepest * length / exit_margin)
        exits[outward] = again[outward]
    with np.errstate(divide="ignore", invalid="ignore"):
        cap = np.where(np.isfinite(exits), exit_margin * exits / np.maximum(deepest * length, 1e-300), 1.0)
    cap = np.clip(cap, 0.0, 1.0)
    if anchor_outward:
        cap[outward] = min_scale
    left_body = cap < 1.0
    edges, _ = skin_edges(tris)
    s = _ramp(cap, edges, ramp)
    folded_any = np.zeros(rig.vertex_count, dtype=bool)
    # pairs the skin itself has (a bind pose through itself) cannot be undone by the layers
    skin_pairs = {tuple(pq) for pq in self_intersections(v, tris).tolist()}
    # depths checked for folds: the three layers and the midpoints between them, so that no
    # layer is clean while the tissue between two layers is inverted
    fractions = np.array([p[:, 0], 0.5 * (p[:, 0] + p[:, 1]), p[:, 1], 0.5 * (p[:, 1] + p[:, 2]), p[:, 2]])
    for _ in range(max_rounds):
        pos = _layer_positions(v, seg, fractions * s[None])
        bad = np.zeros(tris.shape[0], dtype=bool)
        for x in pos:
            bad[folded_triangles(v, x, tris)] = True
        if not bad.any():  # no fold: the exact self-intersection check of the three layers
            for x in pos[[0, 2, 4]]:  # the three layers
                pairs = [pq for pq in self_intersections(x, tris).tolist() if tuple(pq) not in skin_pairs]
                bad[np.asarray(pairs, dtype=np.int64).ravel()] = True
        if not bad.any():
            break
        hit = np.zeros(rig.vertex_count, dtype=bool)
        hit[tris[bad].ravel()] = True
        ring = hit.copy()  # and their neighbours: the fold is between them
        ring[edges[:, 0]] |= hit[edges[:, 1]]
        ring[edges[:, 1]] |= hit[edges[:, 0]]
        folded_any |= ring
        s[ring] *= shrink
    else:
        hit = np.unique(tris[bad].ravel())
        s[hit] = 0.0
    if anchor_outward:  # an anchored vertex keeps the thinnest depth (never none: its particles need mass)
        s[outward] = np.maximum(s[outward], min_scale)
    weak = np.nonzero((s < min_scale) & ~(anchor_outward & outward))[0]
    unresolved = np.zeros(rig.vertex_count, dtype=bool)
    notes = []
    if weak.size:
        unresolved[weak] = True
        s[weak] = min_scale
        names = sorted({layers.bones.joint_names[b] for b in layers.bone[weak]})[:6]
        ids = _list(rig.file_vertex_ids(weak)) if rig.vertex_kind == "file" else _list(weak)
        notes.append(f"{where}: no positive layer depth fits at {weak.size} vertices ({rig.vertex_kind} vertices {ids}; "
                     f"bones {names}): the skin there folds over or leaves the body however thin the layers are; "
                     "they follow LBS")
        import warnings


        warnings.warn(notes[-1], RigWarning, stacklevel=2)
    if outward.any():
        bones = np.unique(layers.bone[outward])
        how = "are anchored (the thinnest depth)" if anchor_outward else "go in along their normal instead"
        notes.append(f"{where}: {int(outward.sum())} vertices whose bone lies outside the skin {how} (bones "
                     + ", ".join(layers.bones.joint_names[b] for b in bones[:6]) + ")")
    reduced = s < 1.0
    if reduced.any():
        for label, mask in (("the layer folded over or passed through itself", folded_any & reduced),
                            ("the projection segment left the body", left_body & reduced & ~folded_any)):
            if mask.any():
                bones = np.unique(layers.bone[mask])
                parts = []
                for b in bones[np.argsort([s[mask & (layers.bone == b)].min() for b in bones])][:6]:
                    sel = mask & (layers.bone == b)
                    parts.append(f"{layers.bones.joint_names[b]} ({int(sel.sum())} vertices, depth down to "
                                 f"{100 * s[sel].min():.0f} %)")
                notes.append(f"{where}: layer depth reduced where {label}: " + ", ".join(parts))
        ramped = reduced & ~folded_any & ~left_body
        if ramped.any():
            notes.append(f"{where}: {int(ramped.sum())} vertices around them ramp to the full depth")
    params = p * s[:, None]
    positions = np.empty_like(layers.positions)
    positions[0] = v
    for k in range(3):
        positions[k + 1] = v + params[:, k, None] * seg
    return Layers(positions=positions, foot=v + seg, bone=layers.bone, bone_t=layers.bone_t, params=params,
                  bones=layers.bones, depth_scale=s, depth_notes=notes, unresolved=unresolved)


def fit_piece_depths(rig: Rig, layers: Layers, *, where: str = "layers") -> Layers:
    """:func:`fit_layer_depths` of each piece of a surface made of several
    (``rig.surface_groups``, :mod:`warpskin.preprocess.pieces`) on its own, merged: a piece's
    layers fit its own body (its projection segments leave through its own surface, its layers
    must not cross each other), whatever other pieces lie over or inside it (the body inside
    its trousers). A rig of one surface: :func:`fit_layer_depths` itself."""
    import dataclasses

    groups = getattr(rig, "surface_groups", None)
    if groups is None:
        return fit_layer_depths(rig, layers, where=where)
    piece = groups.piece
    tri_piece = piece[rig.triangles[:, 0]]
    positions = layers.positions.copy()
    foot, params = layers.foot.copy(), layers.params.copy()
    scale = np.ones(rig.vertex_count)
    unresolved = np.zeros(rig.vertex_count, dtype=bool)
    notes: list[str] = []
    for k in np.unique(piece):
        sel = np.nonzero(piece == k)[0]
        remap = np.full(rig.vertex_count, -1, dtype=np.int64)
        remap[sel] = np.arange(sel.size)
        sub = dataclasses.replace(rig, vertices=rig.vertices[sel], triangles=remap[rig.triangles[tri_piece == k]],
                                  joint_indices=rig.joint_indices[sel], joint_weights=rig.joint_weights[sel],
                                  weld_map=np.arange(sel.size), file_triangles=None, render_triangles=None,
                                  vertex_parents=None, report=None, surface_groups=None, surface_labels=None,
                                  vertex_kind="piece")
        part = Layers(positions=layers.positions[:, sel], foot=layers.foot[sel], bone=layers.bone[sel],
                      bone_t=layers.bone_t[sel], params=layers.params[sel], bones=layers.bones)
        import warnings

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fit = fit_layer_depths(sub, part, where=f"{where}, piece {groups.names[k]!r}", anchor_outward=True)
        for w in caught:  # named again below, with the pieces' own vertex numbers
            if not issubclass(w.category, RigWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        positions[:, sel], foot[sel], params[sel] = fit.positions, fit.foot, fit.params
        scale[sel], unresolved[sel] = fit.depth_scale, fit.unresolved
        notes += fit.depth_notes
    weak = np.nonzero(unresolved)[0]
    if weak.size:
        import warnings

        names = sorted({layers.bones.joint_names[b] for b in layers.bone[weak]})[:6]
        warnings.warn(f"{where}: no positive layer depth fits at {weak.size} vertices (e.g. "
                      f"{', '.join(rig.vertex_label(i) for i in weak[:3])}; bones {names}): the skin there folds over or "
                      "leaves the body however thin the layers are; they follow LBS", RigWarning, stacklevel=2)
    return Layers(positions=positions, foot=foot, bone=layers.bone, bone_t=layers.bone_t, params=params,
                  bones=layers.bones, depth_scale=scale, depth_notes=notes, unresolved=unresolved)


def _list(idx, limit: int = 8) -> str:
    idx = [int(i) for i in idx]
    more = f", ... ({len(idx)} in all)" if len(idx) > limit else ""
    return ", ".join(str(i) for i in idx[:limit]) + more

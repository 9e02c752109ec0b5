"""Popping examples (Son & Han 2007, section 3): pairs of normal and clenched meshes at a few
skeleton poses, as rest-frame displacements; from meshes, glTF morph targets or a scene's generator."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.gltf import read_gltf_morph_targets
from ..io.usdskel import read_usd_blend_shapes, read_usd_inbetweens
from ..kernels import popping as _k
from ..rig import Clip, Rig, RigError
from ..transforms import blend_skinning_matrices, linear_blend_skin


Activation = float | Sequence[float] | Mapping[str, float] | np.ndarray
"""Muscle activations in [0, 1]: one number for every group, one per group in order, or by
group name (missing groups: 0)."""

MAX_GROUPS = _k.GROUP_CAPACITY
"""Most muscle groups one :class:`PoppingDynamics` drives (activations travel as a kernel
argument, a fixed-size vector, so a step uploads nothing)."""

EXAMPLE_GENERATORS = {"popping_arm": "warpskin.scenes.popping_arm:popping_arm_examples"}
"""Rig generators (``[rig] generator`` of a scene) that also build popping examples: name ->
``module:function(rig, **params) -> PoppingExamples``."""
_SAME_POSE = 1e-6  # relative max-abs difference of skinning matrices that counts as one pose


# --------------------------------------------------------------------------------------------
# Examples
# --------------------------------------------------------------------------------------------
@dataclass
class PoppingExamples:
    """Example pairs in the rest frame, ready for pose space deformation.

    Every example is stored as the displacement that, added to the rest mesh before linear
    blend skinning with the example's pose, reproduces the example mesh exactly:
    ``d_i = L_i^-1 (x_i - LBS(r)_i)`` with ``L_i = sum_j w_ij A_j`` the blended linear part of
    the skinning matrices (LBS is affine in the rest position for fixed weights).

    Attributes:
        vertex_count: ``V``, the rig's vertex count.
        normal_matrices: Skinning matrices of the normal examples' poses, ``[E, J, 4, 4]``.
        normal_displacements: Rest-frame displacements of the normal examples [m], ``[E, V, 3]``.
        group_names: Muscle group names, ``[G]`` (one activation signal each).
        clenched_matrices: Per group, skinning matrices of its clenched examples,
            ``[E_g, J, 4, 4]``.
        clenched_disparities: Per group, rest-frame ``clenched - normal`` displacements of its
            examples [m], ``[E_g, V, 3]`` (each clenched example minus the normal example at the
            same pose, its *partner*).
        clenched_inbetweens: Per group, its inbetween shapes (UsdSkel's): ``[(weight, [E_g, V,
            3]), ...]`` sorted by weight in (0, 1), the disparities of the group's examples at
            that activation. With them a group's goal at activation ``a`` runs piecewise
            linearly through 0 at ``a = 0``, each inbetween at its weight and
            ``clenched_disparities`` at ``a = 1``; without (an empty list, or no list at all),
            it is ``a`` times the clenched disparity, as in the paper.
    """

    vertex_count: int
    normal_matrices: np.ndarray
    normal_displacements: np.ndarray
    group_names: list[str]
    clenched_matrices: list[np.ndarray]
    clenched_disparities: list[np.ndarray]
    clenched_inbetweens: list[list[tuple[float, np.ndarray]]] = field(default_factory=list)

    def inbetweens(self, group: int) -> list[tuple[float, np.ndarray]]:
        """Group ``group``'s inbetweens (an empty list where it has none)."""
        return list(self.clenched_inbetweens[group]) if group < len(self.clenched_inbetweens) else []

    @property
    def group_count(self) -> int:
        return len(self.group_names)

    @property
    def normal_count(self) -> int:
        return int(self.normal_matrices.shape[0])


def _lbs_parts(rig: Rig, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex blended linear part ``L`` ``[V, 3, 3]`` and the skinned rest mesh ``[V, 3]``."""
    blend = blend_skinning_matrices(rig.joint_indices, rig.joint_weights, mats)  # [V, 4, 4]
    lin = blend[:, :3, :3]
    skinned = np.einsum("vij,vj->vi", lin, rig.vertices) + blend[:, :3, 3]
    return lin, skinned


def _pose_matrices(rig: Rig, pose, clip: Clip | str | None, label: str) -> np.ndarray:
    if isinstance(pose, (int, float, np.integer, np.floating)) and not isinstance(pose, bool):
        t = float(pose)
        if not math.isfinite(t):
            raise RigError(f"{label}: pose time {pose!r} is not a finite number")
        return rig.skinning_matrices(clip, t)
    m = np.asarray(pose, dtype=np.float64)
    if m.shape != (rig.joint_count, 4, 4):
        raise RigError(
            f"{label}: the pose must be a clip time [s] or skinning matrices of shape "
            f"({rig.joint_count}, 4, 4), got {type(pose).__name__} of shape {np.shape(pose)}"
        )
    if not np.all(np.isfinite(m)):
        raise RigError(f"{label}: the pose's skinning matrices hold NaN or inf")
    return m


def _rest_displacement(rig: Rig, points, mats: np.ndarray, label: str) -> np.ndarray:
    x = np.asarray(points, dtype=np.float64)
    v = rig.vertex_count
    if x.ndim != 2 or x.shape[1] != 3:
        raise RigError(f"{label}: points must have shape [V, 3], got {x.shape}")
    if x.shape[0] != v:
        raise RigError(
            f"{label}: {x.shape[0]} vertices, but the rig {rig.name!r} has {v}; an example must have "
            "the rig's topology (the same vertices in the same order)"
        )
    bad = np.nonzero(~np.all(np.isfinite(x), axis=1))[0]
    if bad.size:
        raise RigError(f"{label}: vertices {bad[:8].tolist()} have NaN or inf positions")
    lin, skinned = _lbs_parts(rig, mats)
    det = np.linalg.det(lin)
    sing = np.nonzero(np.abs(det) < 1e-12)[0]
    if sing.size:
        raise RigError(
            f"{label}: the blended skinning matrix is singular at vertices {sing[:8].tolist()}; "
            "the example pose cannot be undone there"
        )
    return np.linalg.solve(lin, (x - skinned)[:, :, None])[:, :, 0]


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    return float(np.abs(a - b).max()) <= _SAME_POSE * (1.0 + float(np.abs(a).max()))


def examples_from_meshes(
    rig: Rig,
    normal: Sequence[tuple[np.ndarray, object]],
    clenched: Sequence[tuple[np.ndarray, object]] | Mapping[str, Sequence[tuple[np.ndarray, object]]],
    *,
    clip: Clip | str | None = None,
) -> PoppingExamples:
    """Turn example meshes into rest-frame displacements (undo each example pose's skinning).

    Args:
        rig: The rig the examples belong to; every example must have its vertex count and order.
        normal: Normal examples, ``(points, pose)`` pairs: points ``[V, 3]`` [m] in the skinned
            (world) space of the pose; pose a time [s] of ``clip`` or skinning matrices
            ``[J, 4, 4]`` (``G_j @ inverse_bind_j``).
        clenched: Clenched examples, the same pairs: a list (one muscle group, ``"muscle"``) or
            a mapping from group name to its list. Each clenched example needs a normal example
            at the same pose (its partner).
        clip: Clip whose times the poses are (default: the rig's first clip).

    Returns:
        The examples, with per-group disparities ``clenched - normal`` in the rest frame.

    Raises:
        RigError: naming the example: wrong vertex count (topology), wrong shapes, NaN, a
            clenched example without a normal partner, two examples of a set at one pose, or
            no examples at all.
    """
    groups = dict(clenched) if isinstance(clenched, Mapping) else {"muscle": list(clenched)}
    if len(normal) == 0:
        raise RigError("popping examples: no normal examples; give at least one (points, pose) pair")
    if not groups or all(len(v) == 0 for v in groups.values()):
        raise RigError("popping examples: no clenched examples; give at least one (points, pose) pair")
    if len(groups) > MAX_GROUPS:
        raise RigError(f"popping examples: {len(groups)} muscle groups; at most {MAX_GROUPS} are supported")

    def unpack(item, label):
        if not isinstance(item, (tuple, list)) or len(item) != 2:
            raise RigError(f"{label}: expected a (points, pose) pair, got {type(item).__name__}")
        return item

    n_mats, n_disp = [], []
    for k, item in enumerate(normal):
        label = f"normal example {k}"
        pts, pose = unpack(item, label)
        m = _pose_matrices(rig, pose, clip, label)
        for k2, m2 in enumerate(n_mats):
            if _same_pose(m, m2):
                raise RigError(f"{label} is at the same pose as normal example {k2}; keep one example per pose")
        n_mats.append(m)
        n_disp.append(_rest_displacement(rig, pts, m, label))

    names, c_mats, c_disp = [], [], []
    for name, items in groups.items():
        if not isinstance(name, str) or not name:
            raise RigError(f"popping examples: muscle group names must be non-empty strings, got {name!r}")
        if len(items) == 0:
            raise RigError(f"popping examples: muscle group {name!r} has no clenched examples")
        gm, gd = [], []
        for k, item in enumerate(items):
            label = f"clenched example {k} of group {name!r}"
            pts, pose = unpack(item, label)
            m = _pose_matrices(rig, pose, clip, label)
            partner = next((e for e, m2 in enumerate(n_mats) if _same_pose(m, m2)), None)
            if partner is None:
                raise RigError(
                    f"{label} has no normal partner: none of the {len(n_mats)} normal examples is at its pose; "
                    "give the normal mesh at the same pose"
                )
            for k2, m2 in enumerate(gm):
                if _same_pose(m, m2):
                    raise RigError(f"{label} is at the same pose as clenched example {k2} of the same group")
            gm.append(m)
            gd.append(_rest_displacement(rig, pts, m, label) - n_disp[partner])
        names.append(name)
        c_mats.append(np.stack(gm))
        c_disp.append(np.stack(gd))
    return PoppingExamples(
        vertex_count=rig.vertex_count,
        normal_matrices=np.stack(n_mats),
        normal_displacements=np.stack(n_disp),
        group_names=names,
        clenched_matrices=c_mats,
        clenched_disparities=c_disp,
    )


CLENCH_PATTERNS = ("*clench*", "*flex*", "*pump*")
"""Names of a rig file's blend shapes (glTF morph targets) taken for clenched examples."""

BIND = "bind"
"""The pose of an example sculpted on the rig's bind mesh (``pose = "bind"`` in a scene)."""


def _group_of(target: str) -> str:
    """The muscle group a clenched target stands for: its name without the clench word
    (``biceps_clenched`` -> ``biceps``), or the name itself where nothing else is left."""
    import re

    left = re.sub(r"(clench(ed)?|flex(ed)?|pump(ed)?)", "", target, flags=re.IGNORECASE).strip(" _-.:")
    return left or target


def _read_file_shapes(path: str, mesh: str | None) -> tuple[dict, dict]:
    """A rig file's blend shapes ``{name: offsets per file vertex}`` and their inbetweens
    ``{name: [(weight, offsets)]}`` (UsdSkel only; glTF morph targets have none)."""
    suffix = Path(path).suffix.lower()
    if suffix in (".glb", ".gltf"):
        return read_gltf_morph_targets(path, mesh=mesh), {}
    return read_usd_blend_shapes(path, mesh=mesh), read_usd_inbetweens(path, mesh=mesh)


def _example_list(value, label: str, shapes: Mapping, clip_times: tuple[float, float] | None,
                  need_shape: bool) -> list[tuple]:
    """``[{shape = NAME, pose = TIME | "bind"}, ...]`` of a scene's ``[popping.examples]`` as
    ``[(shape, pose), ...]`` (pose ``"bind"`` where absent), checked against the file's shapes."""
    if isinstance(value, Mapping):
        value = [value]
    if not isinstance(value, list) or not value:
        raise RigError(f"{label} must be a list of {{shape = NAME, pose = TIME or \"bind\"}} tables")
    out = []
    for k, item in enumerate(value):
        where = f"{label}[{k}]"
        if not isinstance(item, Mapping):
            raise RigError(f"{where} must be a table {{shape = NAME, pose = TIME or \"bind\"}}, got {item!r}")
        unknown = sorted(set(item) - {"shape", "pose"})
        if unknown:
            raise RigError(f"{where}: unknown key(s) {unknown}; known: ['pose', 'shape']")
        shape = item.get("shape")
        if shape is not None and (not isinstance(shape, str) or shape not in shapes):
            raise RigError(f"{where}: no blend shape {shape!r} in the rig file; its shapes: {sorted(shapes)}")
        if need_shape and shape is None:
            raise RigError(f"{where}: a clenched example needs a shape")
        pose = item.get("pose", BIND)
        if pose != BIND:
            if isinstance(pose, bool) or not isinstance(pose, (int, float)) or not math.isfinite(pose):
                raise RigError(f"{where}: pose must be a clip time [s] or \"bind\", got {pose!r}")
            if clip_times is not None and not (clip_times[0] - 1e-9 <= pose <= clip_times[1] + 1e-9):
                raise RigError(f"{where}: pose {pose} s lies outside the clip's {clip_times[0]:.4g}-{clip_times[1]:.4g} s")
            pose = float(pose)
        out.append((shape, pose))
    return out


def examples_from_file(scene, rig: Rig | None = None) -> PoppingExamples | None:
    """Popping examples from a rig file's own blend shapes (glTF morph targets, UsdSkel blend
    shapes with their inbetweens).

    With a scene's ``[popping.examples]`` table, the examples it maps::

        [popping.examples]
        clip = "Walk"                                   # whose times the poses are (default: the scene's)
        normal = [{shape = "elbow_fix", pose = 1.25}]   # corrective shapes and where they were sculpted
        [popping.examples.clenched]
        biceps = [{shape = "biceps_clenched"}, {shape = "biceps_bent", pose = 1.25}]

    A pose is a time [s] of the clip or ``"bind"`` (the default: the skeleton's bind pose, where
    file shapes are sculpted, placed where the clip's first frame places the body's roots); a
    normal example's shape may be left out (the bind mesh at that pose).
    Shapes add, as in the DCC they were sculpted in: a clenched example is the bind mesh plus
    the normal example's shape at its pose (if any) plus its own shape (and its inbetweens),
    skinned at the pose; a clenched pose without a normal example gets the bind mesh as its
    normal partner. Without the table every shape whose name matches
    :data:`CLENCH_PATTERNS` (case-insensitive) is one muscle group's clenched shape (named by
    :func:`_group_of`) at the bind pose, with the bind mesh as the normal example.

    Returns:
        The examples, or ``None`` where the scene's rig is not a glTF or USD file, or (without
        the table) has no such shape.

    Raises:
        RigError: an unreadable shape (as :func:`~warpskin.io.gltf.read_gltf_morph_targets`), a
            table that names no shape of the file, a bad pose; naming the scene and key.
    """
    import fnmatch

    table = (scene.extra.get("popping") or {}).get("examples") if isinstance(scene.extra, dict) else None
    where = f"{scene.source or scene.name}: [popping.examples]"
    path = scene.rig_file()
    suffix = path.suffix.lower() if path is not None else ""
    if suffix not in (".glb", ".gltf", ".usd", ".usda", ".usdc", ".usdz"):
        if table is not None:
            raise RigError(f"{where} maps blend shapes of a glTF or USD rig file; this scene's rig is "
                           f"{'generated' if path is None else str(path)}")
        return None
    clip_name = scene.clip
    if table is not None:
        if not isinstance(table, Mapping):
            raise RigError(f"{where} must be a table with 'normal' and 'clenched'")
        unknown = sorted(set(table) - {"clip", "normal", "clenched"})
        if unknown:
            raise RigError(f"{where}: unknown key(s) {unknown}; known: ['clenched', 'clip', 'normal']")
        clip_name = table.get("clip", scene.clip)
        if clip_name is not None and not isinstance(clip_name, str):
            raise RigError(f"{where}: clip must be a clip name, got {clip_name!r}")
    targets, inbetweens = _read_file_shapes(str(path), scene.rig_spec.get("mesh"))
    rig = rig if rig is not None else scene.rig()
    clip = rig.clip(clip_name)
    # the bind pose where the clip's first frame places the body (its roots as there)
    bind = rig.skinning_matrices_from_bind(clip, float(clip.start), 0.0)
    if table is None:
        chosen = [n for n in targets if any(fnmatch.fnmatchcase(n.lower(), p) for p in CLENCH_PATTERNS)]
        if not chosen:
            return None
        groups: dict[str, list] = {}
        for name in chosen:
            g = _group_of(name)
            while g in groups:  # two targets for one group: each its own group
                g += "_2"
            groups[g] = [(name, bind)]
        normal: list = [(None, bind)]
    else:
        span = (float(clip.start), float(clip.end)) if clip.end > clip.start else None
        clenched = table.get("clenched")
        if not isinstance(clenched, Mapping) or not clenched:
            raise RigError(f"{where}: clenched must be a table of muscle groups, each a list of "
                           "{shape = NAME, pose = TIME or \"bind\"}")
        groups = {str(g): _example_list(v, f"{where} clenched.{g}", targets, span, True) for g, v in clenched.items()}
        normal = _example_list(table["normal"], f"{where} normal", targets, span, False) if "normal" in table else []

        def at(pose):
            return bind if pose == BIND else rig.skinning_matrices(clip, pose)

        normal = [(shape, at(pose)) for shape, pose in normal]
        for k, (_, m) in enumerate(normal):
            for k2 in range(k):
                if _same_pose(m, normal[k2][1]):
                    raise RigError(f"{where} normal[{k}] is at the same pose as normal[{k2}]; keep one normal "
                                   "example per pose")
        mapped: dict[str, list] = {}
        targets = dict(targets)
        inbetweens = dict(inbetweens)
        for g, items in groups.items():
            mapped[g] = []
            for shape, pose in items:
                m = at(pose)
                partner = next((k for k, (_, m2) in enumerate(normal) if _same_pose(m, m2)), None)
                if partner is None:  # the bind mesh partners a clenched pose no normal example has
                    normal.append((None, m))
                    partner = len(normal) - 1
                base = normal[partner][0]
                if base is not None:  # blend shapes add: the clench on top of the pose's corrective
                    name = f"{base}+{shape}"
                    targets[name] = targets[base] + targets[shape]
                    if shape in inbetweens:
                        inbetweens[name] = [(w, o + targets[base]) for w, o in inbetweens[shape]]
                    shape = name
                mapped[g].append((shape, m))
        groups = mapped
        chosen = sorted({s for s, _ in normal if s is not None} | {s for it in groups.values() for s, _ in it})
    scaled = {n: np.asarray(targets[n], dtype=np.float64) * rig.meters_per_unit for n in chosen}
    levels = {n: [(w, np.asarray(o, dtype=np.float64) * rig.meters_per_unit) for w, o in inbetweens[n]]
              for n in chosen if n in inbetweens}
    return examples_from_morph_targets(rig, scaled, normal=normal, clenched=groups, clip=clip, inbetweens=levels)


def has_examples(scene) -> bool:
    """Whether the scene's rig generator also makes popping examples (:data:`EXAMPLE_GENERATORS`)."""
    return scene.rig_spec.get("generator") in EXAMPLE_GENERATORS


def examples_for_scene(scene) -> PoppingExamples:
    """The popping examples of a scene whose rig generator makes them (:data:`EXAMPLE_GENERATORS`).

    Raises:
        RigError: the scene's rig has no examples (a file, or another generator); build them
            with :func:`examples_from_meshes` and pass them to :func:`run_popping`.
    """
    gen = scene.rig_spec.get("generator")
    if gen not in EXAMPLE_GENERATORS:
        what = f"generator {gen!r}" if gen else "a rig file"
        raise RigError(
            f"scene {scene.name!r} ({what}) has no popping examples; use a generator that makes them "
            f"({sorted(EXAMPLE_GENERATORS)}) or build them with warpskin.popping.examples_from_meshes and pass "
            "examples= to run_popping"
        )
    import importlib

    module, func = EXAMPLE_GENERATORS[gen].split(":")
    make = getattr(importlib.import_module(module), func)
    return make(scene.rig(), **scene.rig_spec.get("params", {}))


def examples_from_morph_targets(
    rig: Rig,
    targets: Mapping[str, np.ndarray],
    *,
    normal: Sequence[tuple[str | None, object]],
    clenched: Mapping[str, Sequence[tuple[str, object]]],
    clip: Clip | str | None = None,
    inbetweens: Mapping[str, Sequence[tuple[float, np.ndarray]]] | None = None,
) -> PoppingExamples:
    """Popping examples from morph targets of the rig's mesh (for instance from
    :func:`warpskin.io.gltf.read_gltf_morph_targets`).

    Each example is the rest mesh plus a target's offsets (``None``: the rest mesh itself),
    skinned at the example's pose; then :func:`examples_from_meshes` (which checks topology
    and pairing) turns them into rest-frame displacements.

    Args:
        rig: The rig whose mesh carries the targets.
        targets: ``{name: offsets}``, offsets per *file* vertex ``[N, 3]`` (or per welded
            vertex ``[V, 3]``) in the rest (bind) space.
        normal: ``[(target or None, pose), ...]``: the normal examples.
        clenched: ``{group: [(target, pose), ...]}``: the clenched examples of each muscle group,
            each at the pose of a normal example.
        clip: Clip for poses given as times.
        inbetweens: ``{target: [(weight, offsets), ...]}``: a clenched target's inbetween
            shapes (weights in (0, 1), offsets as the targets'); the target then moves its
            points piecewise linearly in the activation (:attr:`PoppingExamples.clenched_inbetweens`).
            The examples of one group may have different inbetween weights: each is taken at
            all of them (exactly, as its offsets are linear between its own weights).

    Raises:
        RigError: an unknown target (listing the known ones), offsets of the wrong size,
            inbetween weights outside (0, 1).
    """
    inbetweens = dict(inbetweens or {})

    def welded(name: str | None, label: str, d=None) -> np.ndarray:
        if name is None:
            return np.zeros_like(rig.vertices)
        if name not in targets:
            raise RigError(f"{label}: no morph target {name!r}; targets: {sorted(targets)}")
        d = np.asarray(targets[name] if d is None else d, dtype=np.float64)
        if d.shape == (rig.file_vertex_count, 3):
            first = np.zeros(rig.vertex_count, dtype=np.int64)
            first[rig.weld_map[::-1]] = np.arange(rig.file_vertex_count)[::-1]  # first file vertex of each
            return d[first]
        if d.shape == (rig.vertex_count, 3):
            return d
        raise RigError(f"{label}: morph target {name!r} has offsets of shape {d.shape}; the rig has "
                       f"{rig.file_vertex_count} file vertices ({rig.vertex_count} welded)")

    def curve(name: str, w: float, label: str) -> np.ndarray:
        """The target's offsets at weight ``w``: piecewise linear through (0, 0), its
        inbetweens and (1, the target)."""
        knots = [(0.0, np.zeros_like(rig.vertices))]
        for k, (wk, d) in enumerate(inbetweens.get(name, ())):
            if not (0.0 < float(wk) < 1.0) or float(wk) <= knots[-1][0]:
                raise RigError(f"{label}: inbetween {k} of {name!r} has weight {wk!r}; the weights must rise "
                               "strictly inside (0, 1)")
            knots.append((float(wk), welded(name, label, d)))
        knots.append((1.0, welded(name, label)))
        k = next(k for k in range(1, len(knots)) if w <= knots[k][0])
        (w0, d0), (w1, d1) = knots[k - 1], knots[k]
        u = (w - w0) / (w1 - w0)
        return (1.0 - u) * d0 + u * d1

    def mesh_at(name, pose, label, w: float = 1.0):
        mats = _pose_matrices(rig, pose, clip, label)
        pts = rig.vertices + (welded(name, label) if w == 1.0 or name is None else curve(name, w, label))
        return linear_blend_skin(pts, rig.joint_indices, rig.joint_weights, mats), mats

    normal_meshes = [mesh_at(n, pose, f"normal example {k}") for k, (n, pose) in enumerate(normal)]
    clenched_meshes = {
        group: [mesh_at(n, pose, f"clenched example {k} of {group!r}") for k, (n, pose) in enumerate(items)]
        for group, items in clenched.items()
    }
    examples = examples_from_meshes(rig, normal_meshes, clenched_meshes)
    levels = []
    for g, (group, items) in enumerate(clenched.items()):
        weights = sorted({float(w) for n, _ in items for w, _ in inbetweens.get(n, ())})
        rows = []
        for w in weights:
            d = []
            for k, (n, pose) in enumerate(items):
                label = f"clenched example {k} of {group!r} at weight {w:g}"
                pts, mats = mesh_at(n, pose, label, w)
                partner = next(e for e, m2 in enumerate(examples.normal_matrices) if _same_pose(mats, m2))
                d.append(_rest_displacement(rig, pts, mats, label) - examples.normal_displacements[partner])
            rows.append((w, np.stack(d)))
        levels.append(rows)
    if any(levels):
        examples.clenched_inbetweens = levels
    return examples

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

from ..errors import SceneError
from ..rig import Rig, RigError
from .bones import Bones, bone_segments, closest_point_on_segments, dominant_bone

__all__ = ["LayerParams", "Layers", "build_layers", "LAYER_NAMES", "check_layer_folds"]

LAYER_NAMES = ("skin", "fat", "muscle", "bone")


@dataclass
class LayerParams:
    """Projection parameters of the inner layers.

    Attributes:
        fat, muscle, bone: Positions along the projection segment (0 = skin, 1 = bone center
            line); must satisfy ``0 < fat < muscle < bone < 1``. The paper's Arm: 0.15/0.45/0.8.
        per_bone: Overrides by joint name: ``{"belly": (0.05, 0.1, 0.2)}``.
    """

    fat: float = 0.15
    muscle: float = 0.45
    bone: float = 0.8
    per_bone: dict[str, tuple[float, float, float]] = field(default_factory=dict)

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


@dataclass
class Layers:
    """The layered rest geometry.

    Attributes:
        positions: Rest positions per layer [m], ``[4, V, 3]`` (skin, fat, muscle, bone).
        foot: Nearest point on the vertex's bone center line [m], ``[V, 3]``.
        bone: The vertex's bone (joint index), ``[V]``.
        bone_t: Parameter of the foot along its bone segment, ``[V]`` in [0, 1].
        params: Projection parameters used per vertex, ``[V, 3]`` (fat, muscle, bone).
        bones: The bone segments.
    """

    positions: np.ndarray
    foot: np.ndarray
    bone: np.ndarray
    bone_t: np.ndarray
    params: np.ndarray
    bones: Bones

    @property
    def vertex_count(self) -> int:
        return int(self.positions.shape[1])

    @property
    def particle_count(self) -> int:
        return 4 * self.vertex_count

    def flat(self) -> np.ndarray:
        """All particle rest positions, layer-major, ``[4 V, 3]``."""
        return self.positions.reshape(-1, 3)


def build_layers(rig: Rig, params: LayerParams | None = None, *, bones: Bones | None = None) -> Layers:
    """Project every skin vertex toward its bone to make the fat, muscle and bone layers.

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
    for name, p in params.per_bone.items():
        per_joint[rig.skeleton.index(name)] = p
    p = per_joint[bone]
    seg = foot - rig.vertices
    positions = np.empty((4, rig.vertex_count, 3))
    positions[0] = rig.vertices
    for k in range(3):
        positions[k + 1] = rig.vertices + p[:, k, None] * seg
    return Layers(positions=positions, foot=foot, bone=bone, bone_t=t, params=p, bones=bones)


def check_layer_folds(layers: Layers, triangles: np.ndarray, *, where: str = "layers") -> None:
    """Raise a clear error where an inner layer folds over (a triangle whose normal turned
    against the skin triangle's), which makes the layer self-intersect.

    The message names the layer, the triangles and the bones involved, and what to change.
    """
    skin = layers.positions[0]
    n0 = np.cross(skin[triangles[:, 1]] - skin[triangles[:, 0]], skin[triangles[:, 2]] - skin[triangles[:, 0]])
    for k in range(1, 4):
        x = layers.positions[k]
        n = np.cross(x[triangles[:, 1]] - x[triangles[:, 0]], x[triangles[:, 2]] - x[triangles[:, 0]])
        dot = np.einsum("ij,ij->i", n, n0)
        flipped = np.nonzero(dot <= 0.0)[0]
        if flipped.size:
            bones = np.unique(layers.bone[triangles[flipped].ravel()])
            names = [layers.bones.joint_names[b] for b in bones[:6]]
            raise RigError(
                f"{where}: the {LAYER_NAMES[k]} layer folds over at {flipped.size} triangles "
                f"(e.g. {', '.join(str(int(f)) for f in flipped[:6])}; bones {names}): its projection "
                "parameter is too large there; lower it (globally or for those bones)"
            )

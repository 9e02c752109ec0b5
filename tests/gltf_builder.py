"""A small glTF 2.0 writer for the tests (pygltflib): :class:`GltfBuilder` accumulates one
binary buffer and the objects pointing into it; :func:`write_rig_glb` writes a whole rig (its
skin, its other skinned meshes, its skeleton and clips) as a character file, the way a DCC
exports one. Files go to ``tmp_path``; nothing is written to the repo."""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import numpy as np
from pygltflib import (
    GLTF2,
    Accessor,
    Animation,
    AnimationChannel,
    AnimationChannelTarget,
    AnimationSampler,
    Asset,
    Attributes,
    Buffer,
    BufferView,
    Mesh,
    Node,
    Primitive,
    Scene,
    Skin,
)

BYTE, UBYTE, SHORT, USHORT, UINT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
_NP = {BYTE: np.int8, UBYTE: np.uint8, SHORT: np.int16, USHORT: np.uint16, UINT: np.uint32, FLOAT: np.float32}
_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}


# --------------------------------------------------------------------------------------------
# A tiny glTF writer
# --------------------------------------------------------------------------------------------


class GltfBuilder:
    """Accumulates one binary buffer and the glTF objects that point into it."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.g = GLTF2(
            asset=Asset(version="2.0"),
            scene=0,
            scenes=[Scene(nodes=[])],
            buffers=[],
            bufferViews=[],
            accessors=[],
            nodes=[],
            meshes=[],
            skins=[],
            animations=[],
        )

    def view(self, raw: bytes, stride: int | None = None) -> int:
        self.blob.extend(b"\0" * (-len(self.blob) % 4))
        self.g.bufferViews.append(
            BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(raw), byteStride=stride)
        )
        self.blob.extend(raw)
        return len(self.g.bufferViews) - 1

    def accessor(self, data: Any, ctype: int = FLOAT, normalized: bool = False, atype: str | None = None) -> int:
        arr = np.asarray(data)
        arr2 = arr.reshape(arr.shape[0], -1)
        view = self.view(arr2.astype(_NP[ctype]).tobytes())
        return self.raw_accessor(view, ctype, arr2.shape[0], atype or _TYPES[arr2.shape[1]], normalized=normalized)

    def raw_accessor(
        self, view: int | None, ctype: int, count: int, atype: str, offset: int = 0, normalized: bool = False
    ) -> int:
        acc = Accessor(bufferView=view, byteOffset=offset, componentType=ctype, count=count, type=atype)
        acc.normalized = normalized
        self.g.accessors.append(acc)
        return len(self.g.accessors) - 1

    def node(self, **kw: Any) -> int:
        self.g.nodes.append(Node(**kw))
        return len(self.g.nodes) - 1

    def animation(self, name: str | None, channels: list[tuple[int, str, Any, Any, str]]) -> None:
        """``channels``: ``(node, path, times, values, interpolation)``."""
        anim = Animation(name=name, channels=[], samplers=[])
        for node, path, times, values, interp in channels:
            t = self.accessor(np.asarray(times, dtype=np.float64).reshape(-1, 1))
            v = self.accessor(np.asarray(values, dtype=np.float64).reshape(-1, {"rotation": 4}.get(path, 3)))
            anim.samplers.append(AnimationSampler(input=t, output=v, interpolation=interp))
            anim.channels.append(
                AnimationChannel(sampler=len(anim.samplers) - 1, target=AnimationChannelTarget(node=node, path=path))
            )
        self.g.animations.append(anim)

    def save(self, path: Path, kind: str = "glb") -> Path:
        """``kind``: ``"glb"``, ``"embedded"`` (data: URI) or ``"external"`` (``<stem>.bin``)."""
        data = bytes(self.blob) + b"\0" * (-len(self.blob) % 4)
        if kind == "glb":
            self.g.buffers = [Buffer(byteLength=len(data))]
            self.g.set_binary_blob(data)
            self.g.save_binary(str(path))
        elif kind == "embedded":
            uri = "data:application/octet-stream;base64," + base64.b64encode(data).decode()
            self.g.buffers = [Buffer(uri=uri, byteLength=len(data))]
            path.write_text(self.g.to_json())
        else:
            bin_path = path.with_suffix(".bin")
            bin_path.write_bytes(data)
            self.g.buffers = [Buffer(uri=bin_path.name, byteLength=len(data))]
            path.write_text(self.g.to_json())
        return path


def _top4(ji: np.ndarray, jw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The four largest influences per vertex, renormalised (glTF's JOINTS_0/WEIGHTS_0)."""
    k = np.argsort(-jw, axis=1)[:, :4]
    i = np.take_along_axis(ji, k, axis=1)
    w = np.take_along_axis(jw, k, axis=1)
    if w.shape[1] < 4:
        i = np.pad(i, ((0, 0), (0, 4 - i.shape[1])))
        w = np.pad(w, ((0, 0), (0, 4 - w.shape[1])))
    return i, w / w.sum(axis=1, keepdims=True)


def write_rig_glb(rig, path: Path, *, painted: dict[str, np.ndarray] | None = None, root_scale: float | None = None) -> Path:
    """Write ``rig`` as a binary glTF: one node per joint (rest TRS, the skeleton's hierarchy),
    one skin with the rig's inverse binds, the skin mesh (the rig's file vertices and triangles)
    and every attachment (skinned, bound with the same inverse binds) as meshes of their own
    named after them, and every clip as an animation. ``painted``: ``{mesh name: [N]}`` physics
    weights written as the custom attribute ``_PHYSICS_WEIGHT``. ``root_scale``: the skeleton
    under an ``Armature`` node of that uniform scale, as motion-capture libraries export a
    character authored in other units (the file's points and joints unchanged: the character
    stands ``root_scale`` times its size)."""
    b = GltfBuilder()
    skel = rig.skeleton
    j = skel.joint_count
    for k in range(j):
        b.node(name=skel.joint_names[k], translation=skel.rest_translation[k].tolist(),
               rotation=skel.rest_rotation[k].tolist(), scale=skel.rest_scale[k].tolist(), children=[])
    armature = None
    if root_scale is not None:
        armature = b.node(name="Armature", scale=[float(root_scale)] * 3, children=[])
        b.g.scenes[0].nodes.append(armature)
    for k in range(j):
        p = int(skel.parents[k])
        if p >= 0:
            b.g.nodes[p].children.append(k)
        elif armature is not None:
            b.g.nodes[armature].children.append(k)
        else:
            b.g.scenes[0].nodes.append(k)
    ibm = b.accessor(np.asarray(rig.inverse_bind, dtype=np.float64).transpose(0, 2, 1).reshape(j, 16))
    b.g.skins.append(Skin(joints=list(range(j)), inverseBindMatrices=ibm))
    painted = painted or {}
    file_pts = rig.vertices[rig.weld_map]
    meshes = [(rig.mesh_name or "skin", file_pts, rig.file_triangles, rig.joint_indices[rig.weld_map],
               rig.joint_weights[rig.weld_map])]
    for a in rig.attachments:
        meshes.append((a.name, a.vertices, a.triangles, a.joint_indices, a.joint_weights))
    for name, pts, tris, ji, jw in meshes:
        i4, w4 = _top4(np.asarray(ji), np.asarray(jw, dtype=np.float64))
        attrs = Attributes(POSITION=b.accessor(np.asarray(pts, dtype=np.float64)), JOINTS_0=b.accessor(i4, USHORT),
                           WEIGHTS_0=b.accessor(w4))
        if name in painted:
            setattr(attrs, "_PHYSICS_WEIGHT", b.accessor(np.asarray(painted[name], dtype=np.float64).reshape(-1, 1)))
        idx = b.accessor(np.asarray(tris, dtype=np.uint32).reshape(-1, 1), UINT)
        b.g.meshes.append(Mesh(name=name, primitives=[Primitive(attributes=attrs, indices=idx)]))
        node = b.node(name=name, mesh=len(b.g.meshes) - 1, skin=0)
        b.g.scenes[0].nodes.append(node)
    for clip in rig.clips.values():
        channels = [(joint, path, tr.times, tr.values, tr.interpolation) for (joint, path), tr in clip.tracks.items()]
        b.animation(clip.name, channels)
    return b.save(Path(path))

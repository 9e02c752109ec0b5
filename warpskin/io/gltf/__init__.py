"""glTF 2.0 importer: a skinned mesh, its skin and its animations as a :class:`~warpskin.rig.Rig`.

Reads ``.glb`` (binary container) and ``.gltf`` (JSON with ``data:`` URIs or external buffers
next to the file) through :mod:`pygltflib`; the buffer data is decoded here with NumPy
(component types, normalised integers, byte strides, matrix column padding, sparse
accessors).

glTF is in metres and Y up, so no unit or axis conversion is applied. Skinning follows the glTF
2.0 specification::

    p_world = sum_j w_j * G_j @ IBM_j @ p

where ``G_j`` is the global transform of joint node ``j`` (including any non-joint ancestors;
the transform of the mesh node itself is ignored) and ``IBM_j`` its inverse bind matrix. The
skin's joints become a :class:`~warpskin.rig.Skeleton` whose forward kinematics reproduce
``G_j``: each root joint's non-joint ancestors go into ``Skeleton.root_transform``, and static
non-joint nodes *between* two joints are folded into the child joint's rest pose and tracks.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ...rig import Attachment, Rig, RigError, RigWarning
from ..render import Material, RenderAttributes
from ..usd_export import valid_prim_name
from .document import _MALFORMED, _Document
from .mesh import _attributes, _describe, _mesh_entries, _read_mesh
from .skin import _read_clips, _SkinInfo


__all__ = ["list_gltf_meshes", "load_gltf", "read_gltf_morph_targets"]


def _wrapped(path: Path, fn: Any) -> Any:
    """Run ``fn`` converting stray parser/NumPy exceptions on malformed input into RigError."""
    try:
        return fn()
    except RigError:
        raise
    except RecursionError as e:
        raise RigError(f"{path}: malformed glTF (recursion too deep; a cycle?)") from e
    except _MALFORMED as e:
        raise RigError(f"{path}: malformed glTF ({type(e).__name__}: {e})") from e


def list_gltf_meshes(path: str | Path) -> list[dict]:
    """List the mesh instances of a glTF file.

    Args:
        path: ``.glb`` or ``.gltf`` file.

    Returns:
        One dict per node that instances a mesh (in node order), then one per mesh no node uses,
        with keys ``name`` (unique: the node name, else the mesh name, else ``mesh_<i>``;
        repeats get ``_1``, ``_2``, ...; pass it to :func:`load_gltf`), ``node`` (index or
        ``None``), ``mesh`` (index), ``skin`` (index, ``None`` when not skinned), ``skinned``,
        ``node_name``, ``mesh_name``, ``vertices`` (file vertex count over the triangle
        primitives, before welding), ``triangles`` and ``joints`` (joint count of the skin).

    Raises:
        RigError: The file is missing or is not a readable glTF 2.0 file.
    """
    p = Path(path)
    return _wrapped(p, lambda: [dict(e) for e in _mesh_entries(_Document(p))])


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


def _select(doc: _Document, entries: list[dict], mesh: str | None) -> dict:
    skinned = [e for e in entries if e["skinned"]]
    if mesh is None:
        if not skinned:
            raise doc.error(f"has no skinned mesh; meshes: {_describe(entries)}")
        return max(skinned, key=lambda e: e["vertices"])  # first of the largest
    for e in entries:
        if e["name"] == mesh:
            chosen = e
            break
    else:
        alias = [e for e in entries if mesh in (e["node_name"], e["mesh_name"])]
        alias.sort(key=lambda e: not e["skinned"])
        if not alias:
            raise doc.error(f"no mesh named {mesh!r}; meshes: {_describe(entries)}")
        chosen = alias[0]
    if not chosen["skinned"]:
        raise doc.error(
            f"mesh {mesh!r} is not skinned (no skin on its node); skinned meshes: {_describe(skinned)}"
        )
    return chosen


def _load(path: Path, mesh: str | None, weld: bool) -> Rig:
    doc = _Document(path)
    entries = _mesh_entries(doc)
    entry = _select(doc, entries, mesh)
    node_parent = doc.node_parents()
    label = entry["name"]
    points, triangles, ji, jw, attrs = _read_mesh(doc, entry["mesh"], label)
    skin_index = entry["skin"]
    info = _SkinInfo(doc, skin_index, node_parent)
    n_j = len(info.joints)
    skin = doc.skins[skin_index]
    if skin.inverseBindMatrices is not None:
        ibm = doc.accessor(skin.inverseBindMatrices, f"skin {skin_index} inverseBindMatrices")
        if ibm.shape != (n_j, 16):
            raise doc.error(
                f"skin {skin_index} inverseBindMatrices: accessor count mismatch: {ibm.shape[0]} matrices of "
                f"{ibm.shape[1]} components for {n_j} joints (expected {n_j} MAT4)"
            )
        inverse_bind = ibm.reshape(n_j, 4, 4).transpose(0, 2, 1)  # column-major storage
    else:
        inverse_bind = np.tile(np.eye(4), (n_j, 1, 1))
    clips = _read_clips(doc, info)
    rig = Rig.from_file_arrays(
        name=path.stem,
        points=points,
        triangles=triangles,
        skeleton=info.skeleton,
        joint_indices=ji,
        joint_weights=jw,
        inverse_bind=inverse_bind,
        clips=clips,
        source=str(path),
        mesh_name=label,
        weld=weld,
        up_axis="Y",
        meters_per_unit=1.0,
        render=_render_attributes(doc, triangles, attrs),
    )
    rig.attachments = _attachments(doc, entries, info, node_parent, rig)
    return rig


def _clean(name: str) -> str:
    return valid_prim_name(name)


def _attachments(doc: _Document, entries: list[dict], info, node_parent: np.ndarray, rig: Rig) -> list[Attachment]:
    """The character's other meshes, each following the rig's joints by LBS: meshes without a
    skin whose node hangs (directly or through non-joint nodes) from a joint (weight 1 to it),
    and other skinned meshes whose joints are all the rig's. One warning names them."""
    out: list[Attachment] = []
    taken = {_clean(n) for n in (rig.mesh_name, "skin", "lbs", "rest", "cage", "Looks", "layers",
                                 "layer_fat", "layer_muscle", "layer_bone")}
    n_j = rig.joint_count
    for e in entries:
        if e["name"] == rig.mesh_name or e["node"] is None:
            continue
        if e["skinned"]:
            skin = doc.skins[e["skin"]]
            nodes = list(skin.joints or [])
            if not nodes or any(n not in info.joint_of_node for n in nodes):
                continue  # another character's skeleton
            points, tris, ji, jw, attrs = _read_mesh(doc, e["mesh"], e["name"])
            ibm = (doc.accessor(skin.inverseBindMatrices, f"skin {e['skin']} inverseBindMatrices")
                   .reshape(-1, 4, 4).transpose(0, 2, 1) if skin.inverseBindMatrices is not None
                   else np.tile(np.eye(4), (len(nodes), 1, 1)))
            if ibm.shape[0] != len(nodes) or (ji.size and ji.max() >= len(nodes)):
                continue
            ours = np.array([info.joint_of_node[n] for n in nodes])
            offsets = np.tile(np.eye(4), (n_j, 1, 1))
            offsets[ours] = ibm
            ji = ours[ji]
            sums = jw.sum(axis=1, keepdims=True)
            if np.any(sums <= 0) or not np.isfinite(jw).all():
                continue
            jw = jw / sums
        else:
            if e["node"] in info.joint_of_node:  # the mesh's own node is a joint: it follows that joint
                below, p = np.eye(4), int(e["node"])
            else:
                below = doc.local_matrix(e["node"])
                p = int(node_parent[e["node"]])
            while p >= 0 and p not in info.joint_of_node:
                below = doc.local_matrix(p) @ below
                p = int(node_parent[p])
            if p < 0:
                continue  # not under the skeleton: a static prop, not part of the character
            points, tris, _, _, attrs = _read_mesh(doc, e["mesh"], e["name"], skinned=False)
            offsets = np.tile(np.eye(4), (n_j, 1, 1))
            offsets[info.joint_of_node[p]] = below
            ji = np.full((points.shape[0], 1), info.joint_of_node[p], dtype=np.int64)
            jw = np.ones((points.shape[0], 1))
        name = e["node_name"] or e["name"]
        while _clean(name) in taken:  # unique as a prim name, and not one warpskin writes
            name += "_"
        taken.add(_clean(name))
        out.append(Attachment(name=name, vertices=points, triangles=tris, joint_indices=ji, joint_weights=jw,
                              joint_offsets=offsets, render=_render_attributes(doc, tris, attrs)))
    if out:
        listed = ", ".join(a.name for a in out[:8])
        more = f" and {len(out) - 8} more" if len(out) > 8 else ""
        warnings.warn(f"{doc.where}: {len(out)} more meshes follow the skeleton ({listed}{more}): those parented "
                      "rigidly to a joint with weight 1 to it; they are written beside the skin, not simulated",
                      RigWarning, stacklevel=4)
    return out

def _render_attributes(doc: _Document, triangles: np.ndarray, attrs: dict) -> RenderAttributes:
    """UVs per triangle corner (glTF's v flipped to USD's st), rest normals and the materials of
    the mesh's primitives (base colour factor and texture image)."""
    uvs = None
    if attrs["uv"] is not None:
        uv = attrs["uv"][triangles]  # [T, 3, 2]
        uvs = np.stack([uv[..., 0], 1.0 - uv[..., 1]], axis=-1)
    used = sorted(int(m) for m in np.unique(attrs["material"]) if m >= 0)
    materials = [_material(doc, m) for m in used]
    lookup = np.full(max(used, default=-1) + 2, -1, dtype=np.int64)
    lookup[used] = np.arange(len(used))
    return RenderAttributes(uvs=uvs, normals=attrs["normal"], materials=materials,
                            triangle_material=lookup[attrs["material"]] if used else None,
                            physics_weight=attrs.get("physics_weight"))


def _material(doc: _Document, index: int) -> Material:
    mat = doc.item("materials", index, "a primitive's material")
    name = mat.name or f"material_{index}"
    pbr = mat.pbrMetallicRoughness
    factor = getattr(pbr, "baseColorFactor", None) if pbr is not None else None
    color = tuple(float(c) for c in (factor if factor and len(factor) == 4 else (1.0, 1.0, 1.0, 1.0)))
    tex_info = getattr(pbr, "baseColorTexture", None) if pbr is not None else None
    if tex_info is None or tex_info.index is None:
        return Material(name=name, base_color=color)
    texture = doc.item("textures", tex_info.index, f"material {name!r} baseColorTexture")
    if texture.source is None:
        return Material(name=name, base_color=color)
    image = doc.item("images", texture.source, f"texture {tex_info.index}")
    data = doc.image_bytes(texture.source, image)
    if data is None:
        return Material(name=name, base_color=color)
    ext = ".png" if data[:8] == b"\x89PNG\r\n\x1a\n" else ".jpg" if data[:3] == b"\xff\xd8\xff" else ""
    if not ext:  # a format a USD renderer cannot be assumed to read (KTX2, WebP): colour only
        warnings.warn(f"{doc.where}: material {name!r}: its base-colour image is neither PNG nor JPEG; written "
                      "without the texture", RigWarning, stacklevel=4)
        return Material(name=name, base_color=color)
    stem = "".join(c if c.isalnum() or c in "-_" else "_" for c in (image.name or name)) or f"image_{texture.source}"
    return Material(name=name, base_color=color, texture=data, texture_name=stem + ext)


def load_gltf(path: str | Path, *, mesh: str | None = None, weld: bool = True) -> Rig:
    """Load one skinned mesh of a glTF 2.0 file, with its skeleton and animations, as a rig.

    Args:
        path: ``.glb`` or ``.gltf`` file (buffers embedded as ``data:`` URIs or external files
            relative to it).
        mesh: Name of the mesh instance to load, as listed by :func:`list_gltf_meshes` (a node
            or mesh name also works). Default: the skinned mesh with the most vertices (the
            first of those on a tie).
        weld: Merge vertices that share a position (glTF splits them at UV/normal seams); the
            file topology stays in ``Rig.file_triangles`` and ``Rig.weld_map``.

    Returns:
        The rig in metres, Y up: vertices ``[V, 3]`` in the mesh's own space (the mesh node's
        transform is ignored, as glTF skinning prescribes), triangles ``[T, 3]`` from every
        triangle primitive, joint indices/weights ``[V, 4 * sets]`` from ``JOINTS_n``/``WEIGHTS_n``,
        the skin's joints as a skeleton (parent = nearest ancestor node in the joint list; root
        joints carry the world transform of their non-joint ancestors in ``root_transform``),
        inverse bind matrices ``[J, 4, 4]`` and one clip per animation that moves a joint
        (named after the animation, ``animation_<i>`` when unnamed). Channels on morph weights
        and on non-joint nodes are dropped (a :class:`RigWarning` names animated non-joint
        ancestors of the skeleton).

    Raises:
        RigError: Missing or unreadable file, not glTF 2.0, no skinned mesh, unknown ``mesh``,
            missing POSITION, JOINTS without WEIGHTS, accessor count mismatches, data out of
            buffer range, a cyclic node hierarchy, or a rig that fails validation (NaN
            positions, weightless vertices, joint indices out of range, ...).
    """
    p = Path(path)
    return _wrapped(p, lambda: _load(p, mesh, weld))


def read_gltf_morph_targets(path: str | Path, *, mesh: str | None = None) -> dict[str, np.ndarray]:
    """Morph targets (blend shapes) of one skinned mesh: position offsets per file vertex.

    Used for example meshes (for instance the clenched examples of the popping dance) stored as
    morph targets of the rig's own mesh, in its rest (bind) space.

    Args:
        path: ``.glb`` or ``.gltf`` file.
        mesh: The mesh instance, as for :func:`load_gltf` (default: the largest skinned mesh).

    Returns:
        ``{name: deltas [N, 3]}`` in the file's vertex order (the order of :func:`load_gltf`
        before welding; map with ``Rig.weld_map``). Names come from the mesh's
        ``extras.targetNames`` (the common exporter convention), else ``target_<i>``.

    Raises:
        RigError: primitives with different target counts, a target without POSITION, or
            an accessor whose count differs from the primitive's POSITION.
    """
    p = Path(path)

    def read() -> dict[str, np.ndarray]:
        doc = _Document(p)
        entry = _select(doc, _mesh_entries(doc), mesh)
        m = doc.meshes[entry["mesh"]]
        prims = list(m.primitives or [])
        counts = {len(pr.targets or []) for pr in prims}
        if len(counts) > 1:
            raise doc.error(f"mesh {entry['name']!r}: primitives have different numbers of morph targets {sorted(counts)}")
        n_targets = counts.pop() if counts else 0
        extras = m.extras if isinstance(m.extras, dict) else {}
        names = extras.get("targetNames") if isinstance(extras.get("targetNames"), list) else None
        if names is None or len(names) != n_targets:
            names = [f"target_{k}" for k in range(n_targets)]
        out = {str(name): [] for name in names}
        for pi, pr in enumerate(prims):
            what = f"mesh {entry['name']!r} primitive {pi}"
            n = doc.accessor_count(_attributes(pr)["POSITION"], f"{what} POSITION")
            for k, target in enumerate(pr.targets or []):
                t = target if isinstance(target, dict) else dict(target.__dict__)
                if t.get("POSITION") is None:
                    raise doc.error(f"{what} morph target {names[k]!r} has no POSITION offsets")
                d = doc.accessor(t["POSITION"], f"{what} morph target {names[k]!r} POSITION")
                if d.shape != (n, 3):
                    raise doc.error(f"{what} morph target {names[k]!r}: {d.shape[0]} offsets for {n} vertices")
                out[str(names[k])].append(d)
        return {k: np.concatenate(v).astype(np.float64) for k, v in out.items()}

    return _wrapped(p, read)

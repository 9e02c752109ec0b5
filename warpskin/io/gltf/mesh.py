"""glTF meshes: the skinned primitives of a document, their triangles and vertex attributes."""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from ...rig import RigWarning
from .document import _MODE_NAMES, _TRIANGLE_FAN, _TRIANGLE_STRIP, _TRIANGLES, _Document



def _primitive_mode(prim: Any) -> int:
    return 4 if prim.mode is None else int(prim.mode)


def _attributes(prim: Any) -> dict[str, Any]:
    """A primitive's attributes as ``{name: accessor index}`` (set ones only)."""
    raw = prim.attributes
    items = raw if isinstance(raw, dict) else (vars(raw) if raw is not None else {})
    return {str(k): v for k, v in items.items() if v is not None}


def _mesh_entries(doc: _Document) -> list[dict]:
    """One entry per mesh instance (node with a mesh), then meshes no node uses."""
    entries: list[dict] = []
    used_meshes: set[int] = set()
    for i, node in enumerate(doc.nodes):
        if node.mesh is None:
            continue
        doc.item("meshes", node.mesh, doc.node_label(i))
        skin = node.skin
        if skin is not None:
            doc.item("skins", skin, doc.node_label(i))
        used_meshes.add(int(node.mesh))
        entries.append({"node": i, "mesh": int(node.mesh), "skin": None if skin is None else int(skin)})
    for m in range(len(doc.meshes)):
        if m not in used_meshes:
            entries.append({"node": None, "mesh": m, "skin": None})
    taken: set[str] = set()
    for e in entries:
        mesh = doc.meshes[e["mesh"]]
        node_name = doc.nodes[e["node"]].name if e["node"] is not None else None
        base = node_name or mesh.name or f"mesh_{e['mesh']}"
        name, k = base, 1
        while name in taken:
            name, k = f"{base}_{k}", k + 1
        taken.add(name)
        vertices = triangles = 0
        for p, prim in enumerate(mesh.primitives or []):
            mode = _primitive_mode(prim)
            if mode not in (_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN):
                continue
            what = f"mesh {e['mesh']} primitive {p}"
            pos = _attributes(prim).get("POSITION")
            if pos is None:
                continue
            nv = doc.accessor_count(pos, f"{what} POSITION")
            ni = doc.accessor_count(prim.indices, f"{what} indices") if prim.indices is not None else nv
            vertices += nv
            triangles += ni // 3 if mode == _TRIANGLES else max(ni - 2, 0)
        joints = len(doc.skins[e["skin"]].joints or []) if e["skin"] is not None else 0
        e.update(
            name=name,
            node_name=node_name,
            mesh_name=mesh.name,
            skinned=e["skin"] is not None,
            vertices=vertices,
            triangles=triangles,
            joints=joints,
        )
    return entries


def _describe(entries: list[dict]) -> str:
    if not entries:
        return "none"
    parts = [f"{e['name']!r} ({'skin ' + str(e['skin']) if e['skinned'] else 'not skinned'})" for e in entries[:20]]
    if len(entries) > 20:
        parts.append(f"... ({len(entries)} in all)")
    return ", ".join(parts)


def _triangulate(doc: _Document, indices: np.ndarray, mode: int, what: str) -> np.ndarray:
    n = indices.size
    if mode == _TRIANGLES:
        if n % 3:
            raise doc.error(f"{what}: {n} indices is not a multiple of 3")
        return indices.reshape(-1, 3)
    if n < 3:
        return np.zeros((0, 3), dtype=np.int64)
    i = np.arange(n - 2)
    if mode == _TRIANGLE_STRIP:
        odd = i % 2
        tri = np.stack([indices[i], indices[i + 1 + odd], indices[i + 2 - odd]], axis=1)
        # strips use repeated indices to join runs; those triangles have no area
        keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
        return tri[keep]
    # fan
    return np.stack([indices[i + 1], indices[i + 2], np.full(n - 2, indices[0])], axis=1)


def _attribute_sets(doc: _Document, attrs: dict[str, Any], what: str) -> list[int]:
    sets: dict[str, set[int]] = {"JOINTS": set(), "WEIGHTS": set()}
    for key in attrs:
        for prefix in sets:
            if key.startswith(prefix + "_"):
                suffix = key[len(prefix) + 1 :]
                if suffix.isdigit():
                    sets[prefix].add(int(suffix))
    missing_w = sorted(sets["JOINTS"] - sets["WEIGHTS"])
    if missing_w:
        raise doc.error(f"{what} has JOINTS_{missing_w[0]} without WEIGHTS_{missing_w[0]}")
    missing_j = sorted(sets["WEIGHTS"] - sets["JOINTS"])
    if missing_j:
        raise doc.error(f"{what} has WEIGHTS_{missing_j[0]} without JOINTS_{missing_j[0]}")
    found = sorted(sets["JOINTS"])
    if found != list(range(len(found))):
        raise doc.error(f"{what}: joint attribute sets {found} are not numbered 0, 1, ...")
    return found


def _read_mesh(doc: _Document, mesh_index: int, label: str, *, skinned: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """Concatenated points ``[N, 3]``, triangles ``[T, 3]``, joint indices and weights ``[N, K]``,
    and the render attributes: ``{"uv": [N, 2] or None, "normal": [N, 3] or None,
    "material": [T] glTF material index (-1: none), "physics_weight": [N] or None}`` (the
    custom attribute ``_PHYSICS_WEIGHT``, SCALAR float). With ``skinned=False`` (a mesh parented
    rigidly to a joint) the joint arrays are empty ``[N, 0]``."""
    mesh = doc.meshes[mesh_index]
    prims = list(mesh.primitives or [])
    if not prims:
        raise doc.error(f"mesh {label!r} has no primitives")
    pts, tris, jis, jws = [], [], [], []
    uvs, nrms, mats, paint = [], [], [], []
    base = 0
    for p, prim in enumerate(prims):
        what = f"mesh {label!r} primitive {p}"
        mode = _primitive_mode(prim)
        if mode not in (_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN):
            raise doc.error(
                f"{what} has mode {mode} ({_MODE_NAMES.get(mode, 'unknown')}); only triangle primitives "
                "(TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN) can be skinned surfaces"
            )
        attrs = _attributes(prim)
        if "POSITION" not in attrs:
            raise doc.error(f"{what} has no POSITION attribute")
        pos = doc.accessor(attrs["POSITION"], f"{what} POSITION")
        if pos.shape[1] != 3:
            raise doc.error(f"{what} POSITION has {pos.shape[1]} components, expected 3 (VEC3)")
        n = pos.shape[0]
        sets = _attribute_sets(doc, attrs, what) if skinned else []
        if skinned and not sets:
            raise doc.error(f"{what} has no JOINTS_0/WEIGHTS_0 although the mesh is skinned")
        ji_parts, jw_parts = [], []
        rounding = 0.0  # worst-case weight-sum error from integer quantisation
        for s in sets:
            ji = doc.accessor(attrs[f"JOINTS_{s}"], f"{what} JOINTS_{s}", integer=True)
            jw = doc.accessor(attrs[f"WEIGHTS_{s}"], f"{what} WEIGHTS_{s}")
            for name, arr in ((f"JOINTS_{s}", ji), (f"WEIGHTS_{s}", jw)):
                if arr.shape[0] != n:
                    raise doc.error(
                        f"{what}: accessor count mismatch: POSITION has {n} elements but {name} has {arr.shape[0]}"
                    )
                if arr.shape[1] != 4:
                    raise doc.error(f"{what} {name} has {arr.shape[1]} components, expected 4 (VEC4)")
            ji_parts.append(ji)
            jw_parts.append(jw)
            rounding += 4 * 0.5 * doc.quantum(attrs[f"WEIGHTS_{s}"])
        jw_all = np.concatenate(jw_parts, axis=1) if jw_parts else np.zeros((n, 0))
        if rounding > 0.0:
            # normalised-integer weights are rounded one by one: 128 + 128 = 256 of 255 is still
            # "0.5 + 0.5". Renormalise sums within that rounding; leave the rest to validation.
            sums = jw_all.sum(axis=1, keepdims=True)
            fix = (sums > 0.0) & (np.abs(sums - 1.0) <= rounding + 1e-12)
            jw_all = np.where(fix, jw_all / np.where(sums > 0.0, sums, 1.0), jw_all)
        if prim.indices is not None:
            idx = doc.accessor(prim.indices, f"{what} indices", integer=True)
            if idx.shape[1] != 1:
                raise doc.error(f"{what} indices accessor is not SCALAR")
            idx = idx.ravel()
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                bad = int(idx.max()) if idx.max() >= n else int(idx.min())
                raise doc.error(f"{what} has vertex index {bad}, outside [0, {n - 1}] (POSITION has {n} elements)")
        else:
            idx = np.arange(n, dtype=np.int64)
        tri = _triangulate(doc, idx, mode, what)
        tris.append(tri + base)
        pts.append(pos)
        uvs.append(_optional(doc, attrs, "TEXCOORD_0", 2, n, what))
        nrms.append(_optional(doc, attrs, "NORMAL", 3, n, what))
        paint.append(_optional(doc, attrs, "_PHYSICS_WEIGHT", 1, n, what))
        material = prim.material
        mats.append(np.full(tri.shape[0], material if isinstance(material, int) and not isinstance(material, bool)
                            else -1, dtype=np.int64))
        jis.append(np.concatenate(ji_parts, axis=1) if ji_parts else np.zeros((n, 0), dtype=np.int64))
        jws.append(jw_all)
        base += n
    width = max(a.shape[1] for a in jis)
    jis = [np.pad(a, ((0, 0), (0, width - a.shape[1]))) for a in jis]
    jws = [np.pad(a, ((0, 0), (0, width - a.shape[1]))) for a in jws]
    if mesh.weights and np.any(np.asarray(mesh.weights, dtype=np.float64) != 0.0):
        warnings.warn(
            f"{doc.where}: mesh {label!r} has non-zero default morph target weights; morph targets are "
            "ignored (the rest mesh is the base shape)",
            RigWarning,
            stacklevel=4,
        )
    render = {
        # a primitive without UVs or normals: zeros / none for the whole mesh's normals
        "uv": np.concatenate([u if u is not None else np.zeros((q.shape[0], 2)) for u, q in zip(uvs, pts)])
        if any(u is not None for u in uvs) else None,
        "normal": np.concatenate(nrms) if all(v is not None for v in nrms) else None,
        "material": np.concatenate(mats),
        # a painted physics weight (NaN in primitives that have none)
        "physics_weight": np.concatenate([w.ravel() if w is not None else np.full(q.shape[0], np.nan)
                                          for w, q in zip(paint, pts)]) if any(w is not None for w in paint) else None,
    }
    return np.concatenate(pts), np.concatenate(tris), np.concatenate(jis), np.concatenate(jws), render


def _optional(doc: _Document, attrs: dict, name: str, width: int, n: int, what: str) -> np.ndarray | None:
    """A float vertex attribute (``TEXCOORD_0``, ``NORMAL``) of ``n`` elements, or ``None``."""
    if name not in attrs:
        return None
    arr = doc.accessor(attrs[name], f"{what} {name}")
    if arr.shape != (n, width):
        raise doc.error(f"{what} {name} has shape {arr.shape}, expected ({n}, {width})")
    if not np.isfinite(arr).all():
        bad = int(np.nonzero(~np.isfinite(arr).all(axis=1))[0][0])
        raise doc.error(f"{what} {name} of vertex {bad} is not finite")
    return arr.astype(np.float64)


# --------------------------------------------------------------------------------------------
# Skeleton and animation
# --------------------------------------------------------------------------------------------

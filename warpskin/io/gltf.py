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

import base64
import binascii
import dataclasses
import json
import struct
import urllib.parse
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pygltflib

from ..rig import PATHS, Clip, Rig, RigError, RigWarning, Skeleton, Track
from ..transforms import compose_trs, decompose_trs, quat_multiply

__all__ = ["list_gltf_meshes", "load_gltf"]

_GLB_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A
_CHUNK_BIN = 0x004E4942

_COMPONENT_DTYPES = {
    5120: np.dtype("<i1"),  # BYTE
    5121: np.dtype("<u1"),  # UNSIGNED_BYTE
    5122: np.dtype("<i2"),  # SHORT
    5123: np.dtype("<u2"),  # UNSIGNED_SHORT
    5124: np.dtype("<i4"),  # INT (not in glTF 2.0, but unambiguous)
    5125: np.dtype("<u4"),  # UNSIGNED_INT
    5126: np.dtype("<f4"),  # FLOAT
}
# (columns, rows) of each accessor type; matrices are stored column by column.
_TYPE_SHAPES = {
    "SCALAR": (1, 1),
    "VEC2": (1, 2),
    "VEC3": (1, 3),
    "VEC4": (1, 4),
    "MAT2": (2, 2),
    "MAT3": (3, 3),
    "MAT4": (4, 4),
}
_TRIANGLES, _TRIANGLE_STRIP, _TRIANGLE_FAN = 4, 5, 6
_MODE_NAMES = {
    0: "POINTS",
    1: "LINES",
    2: "LINE_LOOP",
    3: "LINE_STRIP",
    4: "TRIANGLES",
    5: "TRIANGLE_STRIP",
    6: "TRIANGLE_FAN",
}
_UNSUPPORTED_EXTENSIONS = {"KHR_draco_mesh_compression", "EXT_meshopt_compression", "KHR_meshopt_compression"}
# Python exceptions that malformed JSON content can raise deep inside pygltflib or NumPy.
_MALFORMED = (TypeError, ValueError, IndexError, KeyError, AttributeError, OverflowError, struct.error, binascii.Error)


# Nested glTF objects: {class: {field: (class of the value, is a list)}}. Used to build pygltflib's
# data classes straight from the parsed JSON: pygltflib's own decoder (dataclasses_json) needs
# seconds for files with thousands of objects (RecursiveSkeletons.glb: 12 s).
_SCHEMA: dict[str, dict[str, tuple[str, bool]]] = {
    "GLTF2": {
        "asset": ("Asset", False),
        "accessors": ("Accessor", True),
        "animations": ("Animation", True),
        "buffers": ("Buffer", True),
        "bufferViews": ("BufferView", True),
        "meshes": ("Mesh", True),
        "nodes": ("Node", True),
        "skins": ("Skin", True),
        "scenes": ("Scene", True),
    },
    "Accessor": {"sparse": ("Sparse", False)},
    "Sparse": {"indices": ("AccessorSparseIndices", False), "values": ("AccessorSparseValues", False)},
    "Animation": {"channels": ("AnimationChannel", True), "samplers": ("AnimationSampler", True)},
    "AnimationChannel": {"target": ("AnimationChannelTarget", False)},
    "Mesh": {"primitives": ("Primitive", True)},
    "Primitive": {"attributes": ("Attributes", False)},
}
# JSON types of the fields the importer reads: "int" (index/count), "ints" (list of indices),
# "nums" (list of numbers), "str", "bool". Checked up front so that a bad value is reported by
# name rather than as a stray TypeError deep inside the decoder.
_FIELD_TYPES: dict[str, dict[str, str]] = {
    "GLTF2": {"scene": "int", "extensionsRequired": "strs", "extensionsUsed": "strs"},
    "Accessor": {
        "bufferView": "int",
        "byteOffset": "int",
        "componentType": "int",
        "count": "int",
        "type": "str",
        "normalized": "bool",
        "name": "str",
    },
    "Sparse": {"count": "int"},
    "AccessorSparseIndices": {"bufferView": "int", "byteOffset": "int", "componentType": "int"},
    "AccessorSparseValues": {"bufferView": "int", "byteOffset": "int"},
    "Animation": {"name": "str"},
    "AnimationChannel": {"sampler": "int"},
    "AnimationChannelTarget": {"node": "int", "path": "str"},
    "AnimationSampler": {"input": "int", "output": "int", "interpolation": "str"},
    "Buffer": {"byteLength": "int", "uri": "str"},
    "BufferView": {"buffer": "int", "byteOffset": "int", "byteLength": "int", "byteStride": "int"},
    "Mesh": {"weights": "nums", "name": "str"},
    "Primitive": {"indices": "int", "mode": "int"},
    "Node": {
        "mesh": "int",
        "skin": "int",
        "children": "ints",
        "translation": "nums",
        "rotation": "nums",
        "scale": "nums",
        "matrix": "nums",
        "name": "str",
    },
    "Skin": {"inverseBindMatrices": "int", "skeleton": "int", "joints": "ints", "name": "str"},
    "Scene": {"nodes": "ints"},
}
_FIELDS: dict[str, tuple[type, frozenset[str]]] = {}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "int": (_is_int, "an integer"),
    "ints": (lambda v: isinstance(v, list) and all(_is_int(x) for x in v), "a list of integers"),
    "nums": (lambda v: isinstance(v, list) and all(_is_num(x) for x in v), "a list of numbers"),
    "str": (lambda v: isinstance(v, str), "a string"),
    "strs": (lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of strings"),
    "bool": (lambda v: isinstance(v, bool), "true or false"),
}


def _construct(doc: _Document, cls_name: str, value: Any, what: str) -> Any:
    """Build the pygltflib object ``cls_name`` from parsed JSON ``value`` (unknown keys dropped)."""
    if not isinstance(value, dict):
        raise doc.error(f"malformed glTF: {what} is not a JSON object")
    if cls_name == "Attributes":
        bad = [k for k in value if not k.isidentifier() or k == "self"]
        if bad:
            raise doc.error(f"malformed glTF: {what} has invalid attribute names {bad}")
        for k, v in value.items():
            if v is not None and not _is_int(v):
                raise doc.error(f"malformed glTF: {what} {k!r} must be an accessor index, got {v!r}")
        return pygltflib.Attributes(**value)
    if cls_name not in _FIELDS:
        cls = getattr(pygltflib, cls_name)
        _FIELDS[cls_name] = (cls, frozenset(f.name for f in dataclasses.fields(cls)))
    cls, fields = _FIELDS[cls_name]
    kwargs = {k: v for k, v in value.items() if k in fields}
    for key, kind in _FIELD_TYPES.get(cls_name, {}).items():
        v = kwargs.get(key)
        check, expected = _CHECKS[kind]
        if v is not None and not check(v):
            raise doc.error(f"malformed glTF: {what} {key!r} must be {expected}, got {json.dumps(v)[:60]}")
    for key, (sub, many) in _SCHEMA.get(cls_name, {}).items():
        v = kwargs.get(key)
        if v is None:
            continue
        if many:
            if not isinstance(v, list):
                raise doc.error(f"malformed glTF: {what} {key!r} is not a list")
            prefix = "" if cls_name == "GLTF2" else f"{what} "
            kwargs[key] = [_construct(doc, sub, item, f"{prefix}{key}[{i}]") for i, item in enumerate(v)]
        else:
            kwargs[key] = _construct(doc, sub, v, f"{what} {key!r}" if cls_name != "GLTF2" else key)
    return cls(**kwargs)


# --------------------------------------------------------------------------------------------
# Document: container parsing, buffers and accessors
# --------------------------------------------------------------------------------------------


class _Document:
    """A parsed glTF file with cached buffers and accessor arrays."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.where = str(path)
        self._bin_chunk: bytes | None = None
        self._buffers: dict[int, bytes] = {}
        self._accessors: dict[tuple[int, bool], np.ndarray] = {}
        self.gltf = self._parse()
        g = self.gltf
        self.nodes = list(g.nodes or [])
        self.meshes = list(g.meshes or [])
        self.skins = list(g.skins or [])
        self.animations = list(g.animations or [])

    # ------------------------------------------------------------ parsing
    def error(self, message: str) -> RigError:
        return RigError(f"{self.where}: {message}")

    def _parse(self) -> Any:
        if not self.path.exists():
            raise RigError(f"{self.where}: no such file")
        if not self.path.is_file():
            raise RigError(f"{self.where}: not a file")
        try:
            data = self.path.read_bytes()
        except OSError as e:
            raise RigError(f"{self.where}: cannot read the file ({e})") from e
        if data[:4] == _GLB_MAGIC:
            json_bytes = self._parse_glb(data)
        else:
            json_bytes = data
        try:
            doc = json.loads(json_bytes.decode("utf-8-sig"))
        except (UnicodeDecodeError, ValueError) as e:
            raise self.error(f"not a glTF file (neither a GLB container nor valid JSON: {e})") from e
        if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
            raise self.error("not a glTF file (the JSON has no 'asset' object)")
        version = str(doc["asset"].get("version", ""))
        if not version.startswith("2."):
            raise self.error(f"glTF version {version or '(missing)'} is not supported; only 2.x is")
        required = set(doc.get("extensionsRequired") or []) & _UNSUPPORTED_EXTENSIONS
        if required:
            raise self.error(f"requires the unsupported compression extension(s) {sorted(required)}")
        return _construct(self, "GLTF2", doc, "the glTF JSON")

    def _parse_glb(self, data: bytes) -> bytes:
        n = len(data)
        if n < 12:
            raise self.error(f"truncated GLB: {n} bytes, shorter than the 12-byte header")
        _, version, length = struct.unpack_from("<4sII", data, 0)
        if version != 2:
            raise self.error(f"GLB container version {version} is not supported; only 2 is")
        if length > n:
            raise self.error(f"truncated GLB: the header declares {length} bytes but the file has {n}")
        offset, chunks = 12, []
        while offset + 8 <= length:
            clen, ctype = struct.unpack_from("<II", data, offset)
            end = offset + 8 + clen
            if end > length:
                raise self.error(
                    f"truncated GLB: chunk {len(chunks)} (bytes {offset + 8}..{end}) runs past the "
                    f"declared length {length}"
                )
            chunks.append((ctype, data[offset + 8 : end]))
            offset = end
        if not chunks or chunks[0][0] != _CHUNK_JSON:
            raise self.error("malformed GLB: the first chunk is not the JSON chunk")
        if len(chunks) > 1 and chunks[1][0] == _CHUNK_BIN:
            self._bin_chunk = chunks[1][1]
        return chunks[0][1].rstrip(b" \x00")

    # ------------------------------------------------------------ indexed lookups
    def item(self, kind: str, index: Any, what: str) -> Any:
        """``gltf.<kind>[index]`` with a clear error for a bad index."""
        items = getattr(self.gltf, kind) or []
        if not isinstance(index, (int, np.integer)) or isinstance(index, bool) or not 0 <= index < len(items):
            raise self.error(f"{what} refers to {kind}[{index}], but the file has {len(items)} {kind}")
        return items[int(index)]

    def node_label(self, i: int) -> str:
        name = self.nodes[i].name
        return f"node {i} ({name!r})" if name else f"node {i}"

    # ------------------------------------------------------------ buffers
    def buffer(self, index: int, what: str) -> bytes:
        if index in self._buffers:
            return self._buffers[index]
        buf = self.item("buffers", index, what)
        uri = buf.uri
        label = f"buffer {index}"
        if uri is None:
            if self._bin_chunk is None:
                raise self.error(f"{label} has no uri and the file has no GLB binary chunk")
            data = self._bin_chunk
        elif uri.startswith("data:"):
            header, sep, payload = uri.partition(",")
            if not sep:
                raise self.error(f"{label} has a malformed data: URI (no ',')")
            try:
                if header.endswith(";base64"):
                    data = base64.b64decode(payload, validate=False)
                else:
                    data = urllib.parse.unquote_to_bytes(payload)
            except (binascii.Error, ValueError) as e:
                raise self.error(f"{label} has a data: URI that does not decode ({e})") from e
        else:
            rel = urllib.parse.unquote(uri)
            file = (self.path.parent / rel).resolve()
            if not file.is_file():
                raise self.error(f"{label} refers to the external file {uri!r} ({file}), which does not exist")
            try:
                data = file.read_bytes()
            except OSError as e:
                raise self.error(f"{label}: cannot read the external file {uri!r} ({e})") from e
        declared = buf.byteLength
        if isinstance(declared, int) and len(data) < declared:
            raise self.error(f"{label} holds {len(data)} bytes but declares byteLength {declared} (truncated?)")
        self._buffers[index] = data
        return data

    def buffer_view(self, index: int, what: str) -> tuple[bytes, int, int, int | None]:
        """``(buffer bytes, start offset, byte length, byte stride or None)`` of a buffer view."""
        bv = self.item("bufferViews", index, what)
        data = self.buffer(bv.buffer, f"buffer view {index}")
        start = int(bv.byteOffset or 0)
        length = int(bv.byteLength or 0)
        if start < 0 or length < 0 or start + length > len(data):
            raise self.error(
                f"buffer view {index} (bytes {start}..{start + length} of buffer {bv.buffer}) is out of "
                f"range: the buffer holds {len(data)} bytes"
            )
        stride = bv.byteStride
        if stride is not None and (int(stride) < 1 or int(stride) > 252):
            raise self.error(f"buffer view {index} has an invalid byteStride {stride}")
        return data, start, length, (int(stride) if stride else None)

    def _read_packed(
        self,
        view: int,
        byte_offset: int,
        ctype: int,
        shape: tuple[int, int],
        count: int,
        what: str,
        allow_stride: bool = True,
    ) -> np.ndarray:
        """Read ``count`` elements of ``shape`` (columns, rows) from a buffer view, ``[count, C]``."""
        dtype = _COMPONENT_DTYPES[ctype]
        cols, rows = shape
        col_bytes = rows * dtype.itemsize
        col_stride = (col_bytes + 3) // 4 * 4 if cols > 1 else col_bytes  # matrix columns are 4-aligned
        elem = col_stride * (cols - 1) + col_bytes
        packed = col_stride * cols
        data, start, length, stride = self.buffer_view(view, what)
        stride = stride if (stride and allow_stride) else packed
        if stride < elem:
            raise self.error(f"{what}: byteStride {stride} is smaller than one element ({elem} bytes)")
        offset = int(byte_offset or 0)
        need = offset + stride * (count - 1) + elem if count else offset
        if offset < 0 or need > length:
            raise self.error(
                f"{what} is out of range: it needs bytes {offset}..{need} of buffer view {view}, which "
                f"holds {length} bytes"
            )
        if count == 0:
            return np.zeros((0, cols * rows), dtype=dtype)
        arr = np.ndarray(
            (count, cols, rows),
            dtype=dtype,
            buffer=data,
            offset=start + offset,
            strides=(stride, col_stride, dtype.itemsize),
        )
        return np.array(arr).reshape(count, cols * rows)

    def accessor(self, index: Any, what: str, *, integer: bool = False) -> np.ndarray:
        """Decoded accessor data, ``[count, components]``.

        Args:
            index: Accessor index.
            what: What the accessor is for (used in error messages).
            integer: Return ``int64`` (requires an integer component type); otherwise
                ``float64`` with normalised integers mapped to [0, 1] / [-1, 1].
        """
        acc = self.item("accessors", index, what)
        key = (int(index), integer)
        if key in self._accessors:
            return self._accessors[key].copy()
        label = f"{what} (accessor {index})"
        ctype, atype, count = acc.componentType, acc.type, acc.count
        if ctype not in _COMPONENT_DTYPES:
            raise self.error(f"{label} has an unknown componentType {ctype}")
        if atype not in _TYPE_SHAPES:
            raise self.error(f"{label} has an unknown type {atype!r}")
        if not isinstance(count, int) or count < 0:
            raise self.error(f"{label} has an invalid count {count!r}")
        shape = _TYPE_SHAPES[atype]
        if acc.bufferView is None:
            if count * shape[0] * shape[1] > 1 << 28:
                raise self.error(f"{label} has no data and an implausibly large count {count}")
            out = np.zeros((count, shape[0] * shape[1]), dtype=_COMPONENT_DTYPES[ctype])
        else:
            out = self._read_packed(acc.bufferView, acc.byteOffset, ctype, shape, count, label)
        if acc.sparse is not None:
            out = self._apply_sparse(acc, out, ctype, shape, label)
        if integer:
            if ctype == 5126:
                raise self.error(f"{label} must hold integers but has componentType FLOAT")
            result = out.astype(np.int64)
        elif acc.normalized and ctype != 5126:
            info = np.iinfo(_COMPONENT_DTYPES[ctype])
            result = np.maximum(out.astype(np.float64) / float(info.max), -1.0)
        else:
            result = out.astype(np.float64)
        self._accessors[key] = result
        return result.copy()

    def _apply_sparse(self, acc: Any, out: np.ndarray, ctype: int, shape: tuple[int, int], label: str) -> np.ndarray:
        sp = acc.sparse
        n = sp.count
        if not isinstance(n, int) or n < 1 or sp.indices is None or sp.values is None:
            raise self.error(f"{label} has a malformed sparse section")
        ictype = sp.indices.componentType
        if ictype not in (5121, 5123, 5125):
            raise self.error(f"{label}: sparse indices have an invalid componentType {ictype}")
        idx = self._read_packed(
            sp.indices.bufferView, sp.indices.byteOffset, ictype, (1, 1), n, f"{label} sparse indices", False
        ).ravel().astype(np.int64)
        vals = self._read_packed(
            sp.values.bufferView, sp.values.byteOffset, ctype, shape, n, f"{label} sparse values", False
        )
        if idx.size and (idx.min() < 0 or idx.max() >= out.shape[0]):
            raise self.error(f"{label}: sparse indices reach {idx.max()}, outside [0, {out.shape[0] - 1}]")
        out = out.copy()
        out[idx] = vals
        return out

    def quantum(self, index: Any) -> float:
        """Quantisation step of a normalised-integer accessor (``1 / max``); 0 for floats."""
        acc = self.item("accessors", index, "accessor")
        if acc.normalized and acc.componentType in _COMPONENT_DTYPES and acc.componentType != 5126:
            return 1.0 / float(np.iinfo(_COMPONENT_DTYPES[acc.componentType]).max)
        return 0.0

    def accessor_count(self, index: Any, what: str) -> int:
        acc = self.item("accessors", index, what)
        if not isinstance(acc.count, int) or acc.count < 0:
            raise self.error(f"{what} (accessor {index}) has an invalid count {acc.count!r}")
        return acc.count

    # ------------------------------------------------------------ nodes
    def local_matrix(self, i: int) -> np.ndarray:
        """Local transform of node ``i``, ``[4, 4]``."""
        return compose_trs(*self.local_trs(i))

    def local_trs(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local translation ``[3]``, rotation ``[4]`` (x, y, z, w) and scale ``[3]`` of node ``i``
        (a ``matrix`` node is decomposed)."""
        node = self.nodes[i]
        label = self.node_label(i)
        if node.matrix is not None:
            m = self._floats(node.matrix, 16, f"{label} matrix")
            if not np.allclose(m, np.eye(4).ravel()):
                mat = m.reshape(4, 4).T  # glTF matrices are column-major
                if not np.allclose(mat[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
                    raise self.error(f"{label} has a projective matrix (last row {mat[3].tolist()})")
                t, r, s = decompose_trs(mat)
                if not np.allclose(compose_trs(t, r, s), mat, atol=1e-6 * max(1.0, np.abs(mat).max())):
                    warnings.warn(
                        f"{self.where}: {label} has a sheared matrix; the shear is dropped", RigWarning, stacklevel=4
                    )
                return t, r, s
        t, r, s = np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), np.ones(3)
        if node.translation is not None:
            t = self._floats(node.translation, 3, f"{label} translation")
        if node.rotation is not None:
            r = self._floats(node.rotation, 4, f"{label} rotation")
        if node.scale is not None:
            s = self._floats(node.scale, 3, f"{label} scale")
        return t, r, s

    def _floats(self, value: Any, n: int, what: str) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=np.float64).ravel()
        except (TypeError, ValueError) as e:
            raise self.error(f"{what} is not a list of numbers ({e})") from e
        if arr.size != n:
            raise self.error(f"{what} has {arr.size} numbers, expected {n}")
        if not np.all(np.isfinite(arr)):
            raise self.error(f"{what} holds NaN or inf")
        return arr

    def node_parents(self) -> np.ndarray:
        """Parent node of every node (``-1`` for roots), ``[N]``; raises on cycles and on nodes
        with two parents."""
        n = len(self.nodes)
        children: list[list[int]] = []
        for i, node in enumerate(self.nodes):
            kids = list(node.children or [])
            for c in kids:
                if not isinstance(c, int) or not 0 <= c < n:
                    raise self.error(f"{self.node_label(i)} lists child {c!r}, outside [0, {n - 1}]")
            children.append(kids)
        # depth-first search for a cycle (iterative: a cycle must not recurse forever)
        state = np.zeros(n, dtype=np.int8)  # 0 unseen, 1 on the current path, 2 finished
        for root in range(n):
            if state[root]:
                continue
            path, stack = [root], [iter(children[root])]
            state[root] = 1
            while stack:
                c = next(stack[-1], None)
                if c is None:
                    state[path.pop()] = 2
                    stack.pop()
                elif state[c] == 1:
                    cyc = path[path.index(c) :] + [c]
                    raise self.error(
                        "cycle in the node hierarchy: " + " -> ".join(self.node_label(k) for k in cyc)
                    )
                elif state[c] == 0:
                    state[c] = 1
                    path.append(c)
                    stack.append(iter(children[c]))
        parent = np.full(n, -1, dtype=np.int64)
        for i, kids in enumerate(children):
            for c in kids:
                if parent[c] >= 0 and parent[c] != i:
                    raise self.error(
                        f"{self.node_label(c)} is a child of both {self.node_label(int(parent[c]))} and "
                        f"{self.node_label(i)}; the node hierarchy must be a tree"
                    )
                parent[c] = i
        return parent


# --------------------------------------------------------------------------------------------
# Mesh listing
# --------------------------------------------------------------------------------------------


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


def _read_mesh(doc: _Document, mesh_index: int, label: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Concatenated points ``[N, 3]``, triangles ``[T, 3]``, joint indices and weights ``[N, K]``."""
    mesh = doc.meshes[mesh_index]
    prims = list(mesh.primitives or [])
    if not prims:
        raise doc.error(f"mesh {label!r} has no primitives")
    pts, tris, jis, jws = [], [], [], []
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
        sets = _attribute_sets(doc, attrs, what)
        if not sets:
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
        jw_all = np.concatenate(jw_parts, axis=1)
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
        tris.append(_triangulate(doc, idx, mode, what) + base)
        pts.append(pos)
        jis.append(np.concatenate(ji_parts, axis=1))
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
    return np.concatenate(pts), np.concatenate(tris), np.concatenate(jis), np.concatenate(jws)


# --------------------------------------------------------------------------------------------
# Skeleton and animation
# --------------------------------------------------------------------------------------------


class _SkinInfo:
    """The skin's joints mapped onto a :class:`Skeleton`, plus what the tracks need."""

    def __init__(self, doc: _Document, skin_index: int, node_parent: np.ndarray) -> None:
        skin = doc.skins[skin_index]
        joints = list(skin.joints or [])
        if not joints:
            raise doc.error(f"skin {skin_index} has no joints")
        for k in joints:
            doc.item("nodes", k, f"skin {skin_index} joint list")
        if len(set(joints)) != len(joints):
            dup = sorted({k for k in joints if joints.count(k) > 1})
            raise doc.error(f"skin {skin_index} lists nodes {dup} more than once")
        self.joints = joints
        self.joint_of_node = {node: j for j, node in enumerate(joints)}
        n_j = len(joints)
        self.names = _joint_names(doc, joints)
        parents = np.full(n_j, -1, dtype=np.int64)
        root_transform = np.tile(np.eye(4), (n_j, 1, 1))
        trs_t, trs_r, trs_s = np.zeros((n_j, 3)), np.zeros((n_j, 4)), np.zeros((n_j, 3))
        # joint -> static transform of the non-joint nodes between it and its parent joint
        self.pre: dict[int, tuple[np.ndarray, np.ndarray, float, bool]] = {}
        self.ancestors: set[int] = set()  # non-joint ancestors of any joint
        for j, node in enumerate(joints):
            chain = []
            p = int(node_parent[node])
            while p >= 0 and p not in self.joint_of_node:
                chain.append(p)
                p = int(node_parent[p])
            self.ancestors.update(chain)
            chain_m = np.eye(4)
            for c in reversed(chain):  # top-down product
                chain_m = chain_m @ doc.local_matrix(c)
            t, r, s = doc.local_trs(node)
            if p < 0:
                root_transform[j] = chain_m
            else:
                parents[j] = self.joint_of_node[p]
                if not np.allclose(chain_m, np.eye(4), atol=1e-12):
                    t, r, s, pre = self._fold(doc, chain_m, chain, t, r, s)
                    self.pre[j] = pre
            trs_t[j], trs_r[j], trs_s[j] = t, r, s
        self.skeleton = Skeleton(self.names, parents, trs_t, trs_r, trs_s, root_transform)

    @staticmethod
    def _fold(
        doc: _Document, chain_m: np.ndarray, chain: list[int], t: np.ndarray, r: np.ndarray, s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, float, bool]]:
        """Fold a static non-joint transform ``C`` between two joints into the child's local TRS.

        For a similarity ``C = T_c R_c (s_c I)``: ``C @ T R S = T' R' S'`` with
        ``T' = C @ t``, ``R' = R_c R``, ``S' = s_c S``; the same affine maps apply to every key.
        """
        ct, cr, cs = decompose_trs(chain_m)
        similarity = bool(
            np.allclose(cs, cs.mean(), rtol=1e-6) and np.allclose(compose_trs(ct, cr, cs), chain_m, atol=1e-9)
        )
        c3 = chain_m[:3, :3]
        if similarity:
            sc = float(cs.mean())
            return c3 @ t + chain_m[:3, 3], quat_multiply(cr, r), sc * s, (chain_m, cr, sc, True)
        t2, r2, s2 = decompose_trs(chain_m @ compose_trs(t, r, s))
        return t2, r2, s2, (chain_m, cr, float(np.cbrt(abs(np.linalg.det(c3)))), False)

    def bake(self, j: int, path: str, values: np.ndarray, cubic: bool) -> np.ndarray:
        """Map a track's values through the folded non-joint transform of joint ``j``."""
        if j not in self.pre:
            return values
        chain_m, cr, sc, _ = self.pre[j]
        if path == "translation":
            out = values @ chain_m[:3, :3].T
            if cubic:
                out[:, 1] += chain_m[:3, 3]  # tangents are directions: no offset
            else:
                out += chain_m[:3, 3]
            return out
        if path == "rotation":
            return quat_multiply(cr, values)  # linear in the key: valid for tangents too
        return values * sc


def _joint_names(doc: _Document, joints: list[int]) -> list[str]:
    names: list[str] = []
    taken: set[str] = set()
    for node in joints:
        base = doc.nodes[node].name or f"node_{node}"
        name = base if base not in taken else f"{base}_{node}"
        k = 1
        while name in taken:
            name, k = f"{base}_{node}_{k}", k + 1
        taken.add(name)
        names.append(name)
    return names


def _read_clips(doc: _Document, info: _SkinInfo) -> dict[str, Clip]:
    clips: dict[str, Clip] = {}
    names: set[str] = set()
    for a, anim in enumerate(doc.animations):
        base = anim.name or f"animation_{a}"
        name, k = base, 1
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.add(name)
        tracks: dict[tuple[int, str], Track] = {}
        ignored: set[int] = set()
        approximated: set[int] = set()
        samplers = list(anim.samplers or [])
        for c, ch in enumerate(anim.channels or []):
            target = ch.target
            node = target.node if target is not None else None
            path = target.path if target is not None else None
            if node is None or path not in PATHS:
                continue  # morph weights, KHR_animation_pointer, ...
            doc.item("nodes", node, f"animation {name!r} channel {c}")
            if node not in info.joint_of_node:
                if node in info.ancestors:
                    ignored.add(int(node))
                continue
            j = info.joint_of_node[node]
            what = f"animation {name!r} channel {c} ({info.names[j]!r} {path})"
            if not isinstance(ch.sampler, int) or not 0 <= ch.sampler < len(samplers):
                raise doc.error(f"{what} uses sampler {ch.sampler!r}, but the animation has {len(samplers)}")
            sampler = samplers[ch.sampler]
            interp = sampler.interpolation or "LINEAR"
            times = doc.accessor(sampler.input, f"{what} input")
            if times.shape[1] != 1:
                raise doc.error(f"{what}: the input (time) accessor is not SCALAR")
            values = doc.accessor(sampler.output, f"{what} output")
            cubic = interp == "CUBICSPLINE"
            width = PATHS[path]
            k_count = times.shape[0]
            expected = 3 * k_count if cubic else k_count
            if values.shape[1] != width or values.shape[0] != expected:
                raise doc.error(
                    f"{what}: accessor count mismatch: {k_count} key times need {expected} "
                    f"{'VEC' + str(width)} output values, got {values.shape[0]} of {values.shape[1]} components"
                )
            if j in info.pre:
                if not info.pre[j][3]:
                    approximated.add(j)
                values = info.bake(j, path, values.reshape((k_count, 3, width) if cubic else (k_count, width)), cubic)
            try:
                tracks[(j, path)] = Track(path, times.ravel(), values, interp)
            except RigError as e:
                raise doc.error(f"{what}: {e}") from e
        if ignored:
            warnings.warn(
                f"{doc.where}: animation {name!r} animates non-joint ancestors of the skeleton "
                f"({', '.join(doc.node_label(n) for n in sorted(ignored))}); that animation is ignored "
                "(their rest transform is used)",
                RigWarning,
                stacklevel=3,
            )
        if approximated:
            warnings.warn(
                f"{doc.where}: animation {name!r}: joints {[info.names[j] for j in sorted(approximated)]} sit "
                "below non-joint nodes with non-uniform scale or shear; their animation is approximated",
                RigWarning,
                stacklevel=3,
            )
        if tracks:
            clips[name] = Clip(name, tracks)
    return clips


# --------------------------------------------------------------------------------------------
# Loader
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
    points, triangles, ji, jw = _read_mesh(doc, entry["mesh"], label)
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
    return Rig.from_file_arrays(
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
    )


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

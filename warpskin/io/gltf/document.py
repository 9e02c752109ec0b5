"""The glTF document: JSON/GLB parsing into pygltflib objects with typed-field checks, buffers,
accessors (component types, normalised integers, strides, sparse) and node transforms."""

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

from ...rig import RigError, RigWarning
from ...transforms import compose_trs, decompose_trs



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
        "materials": ("Material", True),
        "textures": ("Texture", True),
        "images": ("Image", True),
    },
    "Material": {"pbrMetallicRoughness": ("PbrMetallicRoughness", False)},
    "PbrMetallicRoughness": {"baseColorTexture": ("TextureInfo", False)},
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
    "Primitive": {"indices": "int", "mode": "int", "material": "int"},
    "Material": {"name": "str"},
    "PbrMetallicRoughness": {"baseColorFactor": "nums"},
    "TextureInfo": {"index": "int", "texCoord": "int"},
    "Texture": {"source": "int", "name": "str"},
    "Image": {"bufferView": "int", "uri": "str", "mimeType": "str", "name": "str"},
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

    def image_bytes(self, index: int, image: Any) -> bytes | None:
        """The encoded bytes of image ``index`` (a buffer view, a ``data:`` URI or a file beside
        the glTF), or ``None`` with a warning where they cannot be read (the mesh still loads)."""
        try:
            if image.bufferView is not None:
                data, start, length, _ = self.buffer_view(image.bufferView, f"image {index}")
                return bytes(data[start : start + length])
            uri = image.uri or ""
            if uri.startswith("data:"):
                header, _, payload = uri.partition(",")
                return base64.b64decode(payload) if header.endswith(";base64") else urllib.parse.unquote_to_bytes(payload)
            return (self.path.parent / urllib.parse.unquote(uri)).read_bytes()
        except (RigError, OSError, ValueError, binascii.Error) as e:
            warnings.warn(f"{self.where}: image {index} cannot be read ({e}); written without its texture",
                          RigWarning, stacklevel=5)
            return None

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

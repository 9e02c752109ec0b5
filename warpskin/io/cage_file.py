"""A user's own simulation cage from a mesh file (``--cage FILE``; the any-character issue, item 1).

Formats: Wavefront ``.obj`` (read here: ``v`` and ``f`` records, polygons fan-triangulated, the
file's own 1-based vertex numbers kept for messages), glTF ``.glb``/``.gltf`` (trimesh, node
transforms applied) and USD ``.usd``/``.usda``/``.usdc``/``.usdz`` (usd-core: the one mesh prim,
its world transform at the default time applied). Vertices at exactly the same position (a seam
split for UVs or normals) are welded.

The cage is read in the units and the space of the character file at its rest pose, as it would
be modelled around the character in the same scene of a DCC, and scaled as the character was
(``Rig.meters_per_unit``, which includes ``--unit-scale``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import RigError
from ..mesh import triangulate_faces

__all__ = ["CAGE_EXTENSIONS", "CageMesh", "read_cage_mesh"]

CAGE_EXTENSIONS = (".obj", ".glb", ".gltf", ".usd", ".usda", ".usdc", ".usdz")


@dataclass
class CageMesh:
    """A triangle mesh as read from a cage file.

    Attributes:
        points: ``[N, 3]`` float64, in the file's units and space, seam copies welded.
        triangles: ``[T, 3]`` into ``points``, in the file's winding.
        file_ids: ``[N]`` the file's own number of each point (its first copy), for messages
            (1-based for ``.obj``, as the format counts; 0-based otherwise).
        source: The file, and the prim or mesh read.
    """

    points: np.ndarray
    triangles: np.ndarray
    file_ids: np.ndarray
    source: str


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    verts, tris = [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line_no, line in enumerate(fh, start=1):
            parts = line.split()
            if not parts:
                continue
            if parts[0] == "v":
                try:
                    verts.append([float(parts[1]), float(parts[2]), float(parts[3])])
                except (IndexError, ValueError):
                    raise RigError(f"{path}: line {line_no}: a vertex needs three numbers, got {line.strip()!r}") from None
            elif parts[0] == "f":
                ids = []
                for tok in parts[1:]:
                    try:
                        k = int(tok.split("/")[0])
                    except ValueError:
                        raise RigError(f"{path}: line {line_no}: bad face index {tok!r}") from None
                    if k == 0:
                        raise RigError(f"{path}: line {line_no}: face index 0 (OBJ counts from 1)")
                    ids.append(k - 1 if k > 0 else len(verts) + k)  # negative: relative to the end
                if len(ids) < 3:
                    raise RigError(f"{path}: line {line_no}: a face needs at least three vertices")
                bad = [i for i in ids if not 0 <= i < len(verts)]
                if bad:
                    raise RigError(f"{path}: line {line_no}: face refers to vertex {bad[0] + 1}, the file has "
                                   f"{len(verts)} so far")
                tris.extend([ids[0], ids[j], ids[j + 1]] for j in range(1, len(ids) - 1))
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), np.asarray(tris, dtype=np.int64).reshape(-1, 3), 1


def _read_gltf(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False, force="scene")
    except Exception as exc:  # trimesh raises many kinds on a broken file
        raise RigError(f"{path}: cannot read it as glTF: {exc}") from None
    geoms = [(name, g) for name, g in loaded.geometry.items() if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if len(geoms) != 1:
        names = ", ".join(repr(n) for n, _ in geoms) or "none"
        raise RigError(f"{path}: a cage file needs exactly one triangle mesh, found {len(geoms)} ({names})")
    name, g = geoms[0]
    nodes = loaded.graph.geometry_nodes.get(name, [])
    if len(nodes) != 1:
        raise RigError(f"{path}: mesh {name!r} is instanced {len(nodes)} times; a cage file needs it once")
    mat, _ = loaded.graph.get(nodes[0])
    p = np.asarray(g.vertices, dtype=np.float64)
    p = p @ np.asarray(mat, dtype=np.float64)[:3, :3].T + np.asarray(mat, dtype=np.float64)[:3, 3]
    return p, np.asarray(g.faces, dtype=np.int64), 0


def _read_usd(path: Path) -> tuple[np.ndarray, np.ndarray, int, str]:
    from pxr import Usd, UsdGeom


    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise RigError(f"{path}: cannot open it as a USD stage")
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    if len(meshes) != 1:
        names = ", ".join(str(p.GetPath()) for p in meshes[:5]) or "none"
        raise RigError(f"{path}: a cage file needs exactly one mesh prim, found {len(meshes)} ({names})")
    prim = meshes[0]
    mesh = UsdGeom.Mesh(prim)
    t = Usd.TimeCode.Default()
    pts = mesh.GetPointsAttr().Get(t)
    counts = mesh.GetFaceVertexCountsAttr().Get(t)
    idx = mesh.GetFaceVertexIndicesAttr().Get(t)
    if pts is None or counts is None or idx is None:
        raise RigError(f"{path}: mesh {prim.GetPath()} has no points or faces at the default time")
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
    world = np.asarray(UsdGeom.XformCache(t).GetLocalToWorldTransform(prim), dtype=np.float64)  # row vectors
    p = p @ world[:3, :3] + world[3, :3]
    tri, _ = triangulate_faces(np.asarray(counts), np.asarray(idx), mesh.GetHoleIndicesAttr().Get(t))
    if mesh.GetOrientationAttr().Get(t) == UsdGeom.Tokens.leftHanded:
        tri = tri[:, ::-1]
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    return p, tri, 0, f"{path} ({prim.GetPath()}, metersPerUnit {mpu:g})"


def read_cage_mesh(path: str | Path) -> CageMesh:
    """Read one closed triangle mesh for a cage (no checks of its shape: see
    :func:`warpskin.preprocess.cage.cage_from_mesh`).

    Raises:
        RigError: no such file, an unknown format, not exactly one mesh, or a malformed record
            (one line naming the file and the record).
    """
    path = Path(path)
    if not path.is_file():
        raise RigError(f"{path}: no such cage file")
    ext = path.suffix.lower()
    source = str(path)
    if ext == ".obj":
        p, tri, base = _read_obj(path)
    elif ext in (".glb", ".gltf"):
        p, tri, base = _read_gltf(path)
    elif ext in (".usd", ".usda", ".usdc", ".usdz"):
        p, tri, base, source = _read_usd(path)
    else:
        raise RigError(f"{path}: unknown cage format {ext or '(no extension)'}; expected one of {', '.join(CAGE_EXTENSIONS)}")
    if tri.shape[0] == 0:
        raise RigError(f"{path}: the cage has no faces")
    if not np.isfinite(p).all():
        k = int(np.nonzero(~np.isfinite(p).all(axis=1))[0][0])
        raise RigError(f"{path}: vertex {k + base} is not finite ({p[k].tolist()})")
    if tri.min() < 0 or tri.max() >= len(p):
        raise RigError(f"{path}: a face refers to a vertex outside 0-{len(p) - 1 + base}")
    # weld exact copies (seams split for UVs or normals); keep the first copy's number
    _, first, inverse = np.unique(p, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(first)  # welded points in the order of their first copies
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return CageMesh(points=p[first[order]], triangles=rank[inverse[tri]], file_ids=first[order] + base, source=source)

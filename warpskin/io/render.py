"""What a renderer needs of a skinned mesh besides its points: texture coordinates, shading
normals and materials, read from glTF and UsdSkel files and written back with the bake.

* UVs are kept per triangle corner of the file's own triangles (USD ``faceVarying``), in USD's
  convention (``st``, origin at the bottom left; glTF's ``v`` is flipped).
* Normals are recomputed every frame on the deformed surface: area-weighted face normals summed
  over *smoothing groups*, the file vertices at one welded position whose rest normals agree.
  A hard edge of the file (split vertices with different normals) stays hard; a UV seam (split
  vertices with the same normal) stays smooth.
* A material is a base colour and optionally its texture image (the file's bytes), written as
  a ``UsdPreviewSurface`` with the image beside the USD file.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..mesh import face_normals
from ..rig import RigError

__all__ = ["Material", "RenderAttributes", "smoothing_groups", "group_normals", "read_asset_bytes"]

#: Rest normals of two split vertices closer than this (cosine) share a smoothing group.
SAME_NORMAL_COS = 0.999


@dataclass
class Material:
    """A surface's look, as much of it as a review needs.

    Attributes:
        name: Material name (from the file).
        base_color: Linear RGBA base colour (multiplied with the texture where there is one).
        texture: The base-colour image's bytes, or ``None``.
        texture_name: File name to write the image under (``name.png`` / ``.jpg``).
    """

    name: str
    base_color: tuple[float, float, float, float] = (0.8, 0.8, 0.8, 1.0)
    texture: bytes | None = None
    texture_name: str = ""


@dataclass
class RenderAttributes:
    """Render attributes of a mesh in the file's own topology.

    Attributes:
        uvs: ``[T, 3, 2]`` texture coordinates per corner of the file's triangles (USD ``st``),
            or ``None``.
        normals: ``[N, 3]`` rest normals per file vertex (bind space), or ``None``: every split
            vertex is then smooth with its siblings.
        materials: The mesh's materials (possibly empty).
        triangle_material: ``[T]`` index into ``materials`` per file triangle (``-1``: none),
            or ``None`` when there is no material.
        physics_weight: ``[N]`` a painted physics weight per file vertex in [0, 1] (glTF
            attribute ``_PHYSICS_WEIGHT``, USD primvar ``physicsWeight``; NaN where a part of
            the mesh has none), or ``None`` (:mod:`warpskin.character`).
    """

    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    materials: list[Material] = field(default_factory=list)
    triangle_material: np.ndarray | None = None
    physics_weight: np.ndarray | None = None

    def check(self, file_vertex_count: int, triangle_count: int, where: str) -> None:
        if self.uvs is not None:
            if self.uvs.shape != (triangle_count, 3, 2) or not np.isfinite(self.uvs).all():
                raise RigError(f"{where}: texture coordinates must be finite, [{triangle_count}, 3, 2]; got {self.uvs.shape}")
        if self.normals is not None and self.normals.shape != (file_vertex_count, 3):
            raise RigError(f"{where}: normals must be [{file_vertex_count}, 3], got {self.normals.shape}")
        if self.physics_weight is not None:
            w = np.asarray(self.physics_weight, dtype=np.float64)
            if w.shape != (file_vertex_count,):
                raise RigError(f"{where}: the painted physics weight must be one per vertex ({file_vertex_count}), "
                               f"got {w.shape}")
            bad = np.nonzero(~np.isnan(w) & ((w < 0.0) | (w > 1.0) | ~np.isfinite(w)))[0]
            if bad.size:
                raise RigError(f"{where}: the painted physics weight of vertex {int(bad[0])} is {w[bad[0]]:g}, "
                               "outside [0, 1]")
        if self.triangle_material is not None:
            tm = self.triangle_material
            if tm.shape != (triangle_count,) or (tm.size and (tm.min() < -1 or tm.max() >= len(self.materials))):
                raise RigError(f"{where}: a triangle's material index is outside the {len(self.materials)} materials")

    def sliced(self, triangles: np.ndarray) -> RenderAttributes:
        """The attributes of a subset of the file's triangles (by index)."""
        return RenderAttributes(
            uvs=None if self.uvs is None else self.uvs[triangles],
            normals=self.normals,
            materials=list(self.materials),
            triangle_material=None if self.triangle_material is None else self.triangle_material[triangles],
            physics_weight=self.physics_weight,
        )


def smoothing_groups(weld_map: np.ndarray, normals: np.ndarray | None) -> np.ndarray:
    """Smoothing group of every file vertex ``[N]``: file vertices welded to one position share a
    group where their rest normals agree (cosine above :data:`SAME_NORMAL_COS`); without normals,
    every welded position is one group."""
    weld_map = np.asarray(weld_map, dtype=np.int64)
    n = weld_map.shape[0]
    if normals is None or n == 0:
        return weld_map.copy()
    nrm = np.asarray(normals, dtype=np.float64)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    order = np.argsort(weld_map, kind="stable")
    group = np.full(n, -1, dtype=np.int64)
    bounds = np.flatnonzero(np.diff(weld_map[order])) + 1
    next_id = 0
    for members in np.split(order, bounds):  # load time only; groups hold a few vertices
        for k, i in enumerate(members):
            if group[i] >= 0:
                continue
            same = members[k:][(group[members[k:]] < 0) & (nrm[members[k:]] @ nrm[i] >= SAME_NORMAL_COS)]
            group[same] = next_id
            group[i] = next_id  # itself too, whatever its normal (a zero or NaN one matches nothing)
            next_id += 1
    return group


def group_normals(points: np.ndarray, triangles: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Unit normals per vertex ``[N, 3]`` of the surface ``points`` ``[N, 3]``: area-weighted face
    normals of ``triangles`` summed over each smoothing group (``groups`` ``[N]``)."""
    p = np.asarray(points, dtype=np.float64)
    tri = np.asarray(triangles, dtype=np.int64)
    face = face_normals(p, tri)  # twice the area, outward
    count = int(groups.max()) + 1 if groups.size else 0
    acc = np.zeros((count, 3))
    for c in range(3):
        np.add.at(acc, groups[tri[:, c]], face)
    out = acc[groups]
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(length > 0, out / np.where(length > 0, length, 1.0), np.array([0.0, 1.0, 0.0]))


def read_asset_bytes(resolved: str) -> bytes | None:
    """Bytes of a resolved asset path: a plain file or a file inside a ``.usdz`` package
    (``/path/pkg.usdz[inner/file.png]``); ``None`` if it cannot be read."""
    try:
        if resolved.endswith("]") and "[" in resolved:
            package, inner = resolved[:-1].split("[", 1)
            with zipfile.ZipFile(package) as z:
                return z.read(inner)
        return Path(resolved).read_bytes()
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None

"""A small picture of a bake: its written meshes at one frame beside their LBS guides, flat
shaded and seen from the front, drawn with matplotlib (no renderer needed; ``warpskin render``
makes the full pictures with Blender). ``warpskin batch`` puts one beside every job in its index.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["write_thumbnail"]

_SKIN = np.array([0.80, 0.70, 0.62])
_LBS = np.array([0.55, 0.65, 0.80])


def _meshes(stage, code) -> tuple[list, list]:
    """``(written, lbs)``: ``[(points [N, 3], triangles [T, 3])]`` of the meshes written for
    viewing and of their LBS guides, at time code ``code``."""
    from pxr import UsdGeom

    written, lbs = [], []
    for prim in stage.GetDefaultPrim().GetChildren():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
        index = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
        points = np.asarray(mesh.GetPointsAttr().Get(code), dtype=np.float64)
        if counts.size == 0 or points.size == 0:
            continue
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        fan = [np.stack([index[s] * np.ones(c - 2, np.int64), index[s + 1:s + c - 1], index[s + 2:s + c]], axis=1)
               for s, c in zip(start, counts) if c >= 3]  # polygons as triangle fans
        tris = np.concatenate(fan) if fan else np.zeros((0, 3), np.int64)
        role = prim.GetCustomDataByKey("warpskin:role")
        guide = UsdGeom.Imageable(prim).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
        if role == "lbs" or prim.GetName().endswith("_lbs"):
            lbs.append((points, tris))
        elif not guide:
            written.append((points, tris))
    return written, lbs


def _view(points: np.ndarray, up: str) -> tuple[np.ndarray, np.ndarray]:
    """``(xy [N, 2], depth [N])`` of ``points`` seen from the front (the stage's up axis up;
    nearer points have the larger depth)."""
    if up == "Z":  # looking along +y from -y
        return points[:, [0, 2]], -points[:, 1]
    return points[:, [0, 1]], points[:, 2]  # Y up: looking along -z from +z


def write_thumbnail(bake, target, *, size: tuple[int, int] = (320, 240), code: float | None = None) -> Path:
    """Draw the bake at ``bake`` (a ``warpskin`` USD output) at time code ``code`` (default:
    its middle sample) into the PNG ``target``, ``size`` (width, height) [pixels]: the written
    meshes on the left, their LBS guides (where the bake has them) on the right, one scale and
    one frame for both; written atomically.

    Raises:
        ImportError: matplotlib is not installed.
        ValueError: the bake holds no mesh to draw.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(bake))
    mesh_prims = [p for p in stage.GetDefaultPrim().GetChildren() if p.IsA(UsdGeom.Mesh)] if stage.GetDefaultPrim() else []
    if not mesh_prims:
        raise ValueError(f"{bake}: no mesh to draw")
    if code is None:
        samples = UsdGeom.Mesh(mesh_prims[0]).GetPointsAttr().GetTimeSamples()
        code = samples[len(samples) // 2] if samples else Usd.TimeCode.Default()
    written, lbs = _meshes(stage, code)
    if not written:
        raise ValueError(f"{bake}: no mesh to draw")
    up = UsdGeom.GetStageUpAxis(stage)
    panels = [(written, _SKIN)] + ([(lbs, _LBS)] if lbs else [])
    every = np.concatenate([_view(p, up)[0] for group, _ in panels for p, _ in group])
    lo, hi = every.min(axis=0), every.max(axis=0)
    pad = 0.04 * float(max(hi - lo)) + 1e-9
    light = np.array([-0.35, 0.45, 0.82])
    light /= np.linalg.norm(light)
    width, height = size
    fig, axes = plt.subplots(1, len(panels), figsize=(width / 100.0, height / 100.0), dpi=100, squeeze=False)
    for ax, (group, colour) in zip(axes[0], panels):
        polys, shade, depth = [], [], []
        for points, tris in group:
            if not len(tris):
                continue
            xy, d = _view(points, up)
            p = points[tris]
            n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
            n /= np.maximum(np.linalg.norm(n, axis=1), 1e-30)[:, None]
            view_n = np.stack([n[:, 0], n[:, 2], -n[:, 1]], axis=1) if up == "Z" else n  # into (x, up, depth)
            polys.append(xy[tris])
            shade.append(0.35 + 0.65 * np.abs(view_n @ light))
            depth.append(d[tris].mean(axis=1))
        order = np.argsort(np.concatenate(depth))  # far first: the painter's algorithm
        faces = np.concatenate(polys)[order]
        colours = np.clip(np.concatenate(shade)[order, None] * colour[None, :], 0.0, 1.0)
        ax.add_collection(PolyCollection(faces, facecolors=colours, edgecolors="none", antialiased=False))
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        ax.axis("off")
    fig.subplots_adjust(left=0, right=1, bottom=0, top=1, wspace=0)
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}-", suffix=".png", dir=target.parent)
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=100, facecolor="white")
        os.replace(tmp, target)
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target

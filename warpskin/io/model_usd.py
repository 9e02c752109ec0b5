"""Write the built multi-layer model as USD prims so a rigger can look at it before simulating
(``warpskin layers``): every layer as a mesh, every sub-volume as a closed mesh (surface
triangles plus the fans to its bone centres), the joint-constraint particles and the bone
center lines as points."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..preprocess.layers import LAYER_NAMES
from .usd_export import UsdSkinWriter
from ..model import SkinModelBuilder

__all__ = ["write_model_usd"]

_LAYER_COLORS = [(0.85, 0.64, 0.52), (0.35, 0.5, 0.9), (0.3, 0.75, 0.35), (0.85, 0.25, 0.25)]


def _palette(k: int) -> tuple[float, float, float]:
    h = (k * 0.618034) % 1.0
    import colorsys

    return colorsys.hsv_to_rgb(h, 0.55, 0.9)


def write_model_usd(builder: SkinModelBuilder, path: str | Path, *, comment: str = "", character=None) -> Path:
    """Write layers, sub-volumes, joint-constraint particles and bones to ``path`` (rest pose);
    with a bound ``character`` (:class:`~warpskin.character.Character`), also every mesh it
    writes, at rest under ``written/``, carrying its ``physicsWeight`` (0 LBS, 1 physical) and
    ``shapeDiameter`` [m] as primvars for a DCC to colour it by."""
    b = builder.build()
    rig = b.rig
    tris = rig.triangles
    with UsdSkinWriter(path, fps=24, up_axis=rig.up_axis, comment=comment, root=rig.name or "character") as out:
        out.add_group("layers")
        depth = np.linalg.norm(b.layers.positions[3] - b.layers.positions[0], axis=1)
        for k, name in enumerate(LAYER_NAMES):
            # the skin carries where the depth was reduced (1 = the scene's full depth) and how
            # deep the tissue is [m], for a DCC to colour it by
            pv = {"depthScale": b.layers.depth_scale, "tissueDepth": depth} if k == 0 else None
            out.add_mesh(f"layers/{name}", tris, rest_points=b.layers.positions[k], animated=False, color=_LAYER_COLORS[k],
                         vertex_primvars=pv)
        sv = b.subvolumes
        if sv is not None:
            out.add_group("subvolumes")
            pts_all = np.concatenate([rig.vertices, sv.center_rest])
            for s, name in enumerate(sv.names):
                faces = sv.closed_triangles(s)
                used, inverse = np.unique(faces.ravel(), return_inverse=True)
                out.add_mesh(f"subvolumes/{name}", inverse.reshape(-1, 3), rest_points=pts_all[used], animated=False, color=_palette(s))
        jc = b.joint_constraints
        out.add_points("joint_constraint_particles", b.layers.flat()[jc.particles], width=0.002, color=(1.0, 0.8, 0.1))
        bones = b.bones
        seg = np.linspace(0.0, 1.0, 12)[None, :, None]
        line = bones.start[:, None, :] + seg * (bones.end - bones.start)[:, None, :]
        out.add_points("bones", line.reshape(-1, 3), width=0.004, color=(0.95, 0.95, 0.95))
        if character is not None and character.capture_result is not None:
            out.add_group("written")
            cap = character.capture_result
            for part in character.parts:
                s = slice(part.start, part.start + part.count)
                diameter = np.where(np.isfinite(cap.thickness[s]), cap.thickness[s], -1.0)
                out.add_mesh(f"written/{character.display_name(part.name)}", part.triangles, rest_points=part.rest, animated=False,
                             vertex_primvars={"physicsWeight": cap.physics_weight[s], "shapeDiameter": diameter})
    return Path(path)

"""What a pop did, read back from the written USD: each muscle group's bulge over time beside
its activation (``warpskin pop --report``).

A group's **bulge** at a frame is the mean, over the written skin's vertices on its belly, of how
far the skin lies outside its reference along the reference's vertex normals [m]: the
normal-only skin (goal mode: the paper's "normal" prim; layered mode: the same simulation
without the pop, its ``<skin>_normal`` guide), else LBS. The belly of a
muscle found from the skeleton is the skin on the middle of its bones (:func:`belly_of_bones`:
dominant joint in the group, foot on the bone's centre line between 30 % and 70 % of its
length); of an example group, where its clenched disparity is over half its largest
(:func:`belly_of_examples`).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

__all__ = ["belly_of_bones", "belly_of_examples", "bulge_series", "write_popping_report"]


def belly_of_bones(rig, joints: Sequence[str]) -> np.ndarray:
    """``[V]`` bool per welded vertex of ``rig``: on the middle of one of ``joints``' bones."""
    from ..preprocess.bones import bone_segments, closest_point_on_segments, dominant_bone

    names = rig.skeleton.joint_names
    idx = np.array([names.index(j) for j in joints if j in names], dtype=np.int64)
    bones = bone_segments(rig)
    dom = dominant_bone(rig)
    _, t = closest_point_on_segments(rig.vertices, bones.start[dom], bones.end[dom])
    return np.isin(dom, idx) & (t > 0.3) & (t < 0.7)


def belly_of_examples(rig, examples) -> dict[str, np.ndarray]:
    """``{group: [V] bool per welded vertex}``: where the group's clenched disparity (its
    largest over its examples) is over half its largest."""
    out = {}
    for g, name in enumerate(examples.group_names):
        d = np.linalg.norm(np.asarray(examples.clenched_disparities[g]), axis=2).max(axis=0)  # [V]
        out[name] = d > 0.5 * d.max() if d.max() > 0 else np.zeros(d.size, dtype=bool)
    return out


def bulge_series(path, bellies: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, list[float]]]:
    """``(time codes [F], {group: bulge per frame [m]})`` of the bake at ``path`` (a
    ``warpskin pop`` output) for the groups' ``bellies`` (bool per written skin vertex)."""
    from pxr import Usd, UsdGeom

    from ..preprocess.layers import _vertex_normals  # area-weighted unit normals

    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    by_role = {c.GetCustomDataByKey("warpskin:role"): UsdGeom.Mesh(c) for c in root.GetChildren() if c.IsA(UsdGeom.Mesh)}
    by_name = {c.GetName(): UsdGeom.Mesh(c) for c in root.GetChildren() if c.IsA(UsdGeom.Mesh)}
    if "popping" in by_name and "normal" in by_name:  # goal mode
        skin, ref = by_name["popping"], by_name["normal"]
    else:  # layered: against the normal-only guide where the bake has it, else LBS
        skin, ref = by_role.get("skin"), by_role.get("normal", by_role.get("lbs"))
    if skin is None or ref is None:
        raise ValueError(f"{path}: no skin beside a normal or LBS guide to measure the pop against")
    faces = np.asarray(skin.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    belly = {g: np.asarray(m, dtype=bool) for g, m in bellies.items()}
    codes = np.array(skin.GetPointsAttr().GetTimeSamples(), dtype=np.float64)
    out: dict[str, list[float]] = {g: [] for g in belly}
    for tc in codes:
        s = np.asarray(skin.GetPointsAttr().Get(tc), dtype=np.float64)
        r = np.asarray(ref.GetPointsAttr().Get(tc), dtype=np.float64)
        outward = np.einsum("ij,ij->i", s - r, _vertex_normals(r, faces))
        for g, sel in belly.items():
            out[g].append(float(outward[sel].mean()) if sel.any() else 0.0)
    return codes, out


def write_popping_report(report_dir, path, bellies: dict[str, np.ndarray], fps: float,
                         activation: Callable[[float, list[str]], np.ndarray]) -> dict:
    """Write ``popping.json`` (per group: time codes, activation, bulge [mm]) and, with
    matplotlib, ``popping.png`` (each group's bulge over time, its activation beside it) into
    ``report_dir``; returns the JSON's content. ``activation(t, groups)``: the activations at
    clip time ``t`` [s]."""
    report = Path(report_dir)
    report.mkdir(parents=True, exist_ok=True)
    codes, bulge = bulge_series(path, bellies)
    names = list(bellies)
    act = np.array([activation(tc / fps, names) for tc in codes]).reshape(len(codes), len(names))
    data = {"time_codes": codes.tolist(), "fps": fps,
            "groups": {g: {"belly_vertices": int(np.count_nonzero(bellies[g])), "activation": act[:, k].tolist(),
                           "bulge_mm": [1e3 * b for b in bulge[g]]} for k, g in enumerate(names)}}
    (report / "popping.json").write_text(json.dumps(data, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return data
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.6 * len(names) + 1), sharex=True, squeeze=False)
    for k, g in enumerate(names):
        ax = axes[k, 0]
        ax.plot(codes, data["groups"][g]["bulge_mm"], color="tab:red")
        ax.set_ylabel(f"{g}\nbulge [mm]", fontsize=7)
        ax.grid(alpha=0.3)
        twin = ax.twinx()
        twin.fill_between(codes, act[:, k], step="post", alpha=0.2, color="tab:blue")
        twin.set_ylim(0, 1.05)
        twin.set_ylabel("activation", fontsize=7)
    axes[-1, 0].set_xlabel("frame")
    fig.suptitle(f"{Path(path).name}: each muscle group's bulge (skin outside its reference, mean over its belly) "
                 "and activation", fontsize=8)
    fig.tight_layout()
    fig.savefig(report / "popping.png", dpi=100)
    plt.close(fig)
    return data

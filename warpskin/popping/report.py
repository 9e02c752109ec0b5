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
from ..mesh import vertex_normals
from ..preprocess.bones import bone_segments, closest_point_on_segments, dominant_bone

__all__ = ["belly_of_bones", "belly_of_examples", "bulge_series", "beat_summary", "write_popping_report"]

_RISE = 0.9  # a pop has risen at the first frame whose bulge reaches this share of its peak


def belly_of_bones(rig, joints: Sequence[str]) -> np.ndarray:
    """``[V]`` bool per welded vertex of ``rig``: on the middle of one of ``joints``' bones."""
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


def bulge_series(path, bellies: dict, moved: dict | None = None) -> tuple[np.ndarray, dict[str, list[float]]]:
    """``(time codes [F], {group: bulge per frame [m]})`` of the bake at ``path`` (a
    ``warpskin pop`` output) for the groups' ``bellies``: per group a bool mask per written
    skin vertex, or ``{prim name: mask per vertex of that mesh}`` for a pop that moves several
    meshes (the skin by its prim name too). Each mesh is measured outside its reference (its
    ``<name>_normal`` guide, the skin's normal-only guide, else its LBS guide) along the
    reference's vertex normals (area-weighted, over the surface with the vertices one mesh holds
    at one position joined: a flat-shaded mesh splits every corner into one vertex per facet,
    whose own normals would measure a move along the surface as none); the bulge is the mean
    over the group's belly vertices of every mesh. With ``moved`` (a dict), it also receives, per written skin vertex, ``"out"`` and
    ``"in"``, the farthest the skin got outside and inside its reference over the frames [m]
    (``[N]``, ``>= 0``), ``"rest"`` the skin's rest points ``[N, 3]`` and ``"up"`` the stage's
    up axis."""
    from pxr import Usd, UsdGeom


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
    skin_name = skin.GetPrim().GetName()
    belly = {g: ({skin_name: np.asarray(m, dtype=bool)} if not isinstance(m, dict)
                 else {k: np.asarray(v, dtype=bool) for k, v in m.items()}) for g, m in bellies.items()}
    pairs = {skin_name: (skin, ref)}
    for name in sorted({k for m in belly.values() for k in m} - {skin_name}):
        guide = by_name.get(f"{name}_normal") or by_name.get(f"{name}_lbs")
        if name not in by_name or guide is None:
            raise ValueError(f"{path}: no mesh {name!r} beside a normal or LBS guide to measure the pop against")
        pairs[name] = (by_name[name], guide)
    faces = {k: np.asarray(m.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3) for k, (m, _) in pairs.items()}
    codes = np.array(skin.GetPointsAttr().GetTimeSamples(), dtype=np.float64)
    # each mesh's vertices at one position (in its reference's first frame) are one vertex
    joined = {}
    for k, (_, guide) in pairs.items():
        first = np.asarray(guide.GetPointsAttr().Get(codes[0] if len(codes) else Usd.TimeCode.Default()),
                           dtype=np.float64)
        _, one, cls = np.unique(first, axis=0, return_index=True, return_inverse=True)
        joined[k] = (one, cls.ravel(), cls.ravel()[faces[k]])
    out: dict[str, list[float]] = {g: [] for g in belly}
    far_out = far_in = None
    for tc in codes:
        outward = {}
        for k, (mesh, guide) in pairs.items():
            s = np.asarray(mesh.GetPointsAttr().Get(tc), dtype=np.float64)
            r = np.asarray(guide.GetPointsAttr().Get(tc), dtype=np.float64)
            one, cls, tris = joined[k]
            outward[k] = np.einsum("ij,ij->i", s - r, vertex_normals(r[one], tris)[cls])
        for g, masks in belly.items():
            total = sum(float(outward[k][sel].sum()) for k, sel in masks.items())
            count = sum(int(np.count_nonzero(sel)) for sel in masks.values())
            out[g].append(total / count if count else 0.0)
        o = outward[skin_name]
        far_out = np.maximum(o, 0.0) if far_out is None else np.maximum(far_out, o)
        far_in = np.maximum(-o, 0.0) if far_in is None else np.maximum(far_in, -o)
    if moved is not None and far_out is not None:
        moved.update({"out": far_out, "in": far_in, "up": UsdGeom.GetStageUpAxis(stage),
                      "rest": np.asarray(skin.GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)})
    return codes, out


def beat_summary(codes: np.ndarray, bulge_mm: np.ndarray, onsets: np.ndarray, fps: float,
                 depth_mm: float | None = None) -> list[dict]:
    """Each pop of one group, read from its bulge: per onset time ``onsets [K]`` [s] (the
    pop's beat), over the written frames from the beat to the next onset (``codes [F]``, time
    codes; ``bulge_mm [F]``): ``beat_s``, ``beat_frame`` (the beat as a time code),
    ``peak_mm`` and ``peak_frame`` (the largest bulge and its first frame), ``rise_frame``
    (the first frame reaching 90 % of the peak: where a plateau, which the clearance or the
    stretch limit may cut the ringing down to, is reached), their lags after the beat
    ``peak_lag_frames`` and ``rise_lag_frames`` [frames], ``end_mm`` (the bulge in the last
    frame before the next pop: what is left of it), and with ``depth_mm`` the peak's
    ``share_of_depth``. Pops with fewer than two written frames are left out."""
    codes = np.asarray(codes, dtype=np.float64)
    bulge = np.asarray(bulge_mm, dtype=np.float64)
    beats = np.sort(np.asarray(onsets, dtype=np.float64)) * fps
    out = []
    for k, b in enumerate(beats):
        stop = beats[k + 1] if k + 1 < beats.size else np.inf
        sel = np.nonzero((codes >= b - 1e-6) & (codes < stop - 1e-6))[0]
        if sel.size < 2:
            continue
        w = bulge[sel]
        i = int(np.argmax(w))
        peak = float(w[i])
        r = int(np.argmax(w >= _RISE * peak)) if peak > 0.0 else i
        row = {"beat_s": float(b / fps), "beat_frame": float(b), "peak_mm": peak, "peak_frame": float(codes[sel[i]]),
               "peak_lag_frames": float(codes[sel[i]] - b), "rise_frame": float(codes[sel[r]]),
               "rise_lag_frames": float(codes[sel[r]] - b), "end_mm": float(w[-1])}
        if depth_mm:
            row["share_of_depth"] = peak / float(depth_mm)
        out.append(row)
    return out


def write_popping_report(report_dir, path, bellies: dict[str, np.ndarray], fps: float,
                         activation: Callable[[float, list[str]], np.ndarray], *,
                         onsets: dict[str, np.ndarray] | None = None,
                         depth_mm: dict[str, float] | None = None) -> dict:
    """Write ``popping.json`` (per group: time codes, activation, bulge [mm]; the farthest any
    skin vertex got outside and inside its reference, ``largest_out_mm`` / ``largest_in_mm``)
    and, with matplotlib, ``popping.png`` (each group's bulge over time, its activation beside
    it) and ``popping_map.png`` (the rest pose, front and side, each vertex coloured by how far
    the pop moved it out or in at most) into ``report_dir``; returns the JSON's content.
    ``activation(t, groups)``: the activations at clip time ``t`` [s]; with ``onsets`` (per
    group, the times its pops start [s]) each group also gets ``beats``, one
    :func:`beat_summary` row per pop (``depth_mm``: per group, the tissue depth its share is
    of)."""
    report = Path(report_dir)
    report.mkdir(parents=True, exist_ok=True)
    moved: dict = {}
    codes, bulge = bulge_series(path, bellies, moved)
    names = list(bellies)
    act = np.array([activation(tc / fps, names) for tc in codes]).reshape(len(codes), len(names))
    data = {"time_codes": codes.tolist(), "fps": fps,
            "groups": {g: {"belly_vertices": _count(bellies[g]), "activation": act[:, k].tolist(),
                           "bulge_mm": [1e3 * b for b in bulge[g]]} for k, g in enumerate(names)},
            "largest_out_mm": 1e3 * float(moved["out"].max()) if moved else 0.0,
            "largest_in_mm": 1e3 * float(moved["in"].max()) if moved else 0.0}
    for g, row in data["groups"].items():
        if onsets is not None and g in onsets:
            row["beats"] = beat_summary(codes, np.asarray(row["bulge_mm"]), onsets[g], fps,
                                        (depth_mm or {}).get(g))
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
    if moved:
        _rest_map(report / "popping_map.png", moved, Path(path).name)
    return data


def _count(mask) -> int:
    """Vertices in a belly mask, or in every mesh's mask of a ``{prim name: mask}``."""
    return sum(int(np.count_nonzero(m)) for m in mask.values()) if isinstance(mask, dict) else int(np.count_nonzero(mask))


def _rest_map(target: Path, moved: dict, name: str) -> None:
    """The rest pose seen from the front and the side (with the stage's up axis up), each skin
    vertex coloured by the farthest the pop moved it out (red) or in (blue) from its reference
    [mm], the larger of the two; the most moved drawn on top."""
    import matplotlib.pyplot as plt

    signed = np.where(moved["out"] >= moved["in"], moved["out"], -moved["in"]) * 1e3
    rest = moved["rest"]
    up = 2 if moved["up"] == "Z" else 1
    across, depth = (0, 1) if up == 2 else (0, 2)
    order = np.argsort(np.abs(signed))
    top = float(np.abs(signed).max()) or 1.0
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.5))
    for ax, (a, view) in zip(axes, [(across, "front"), (depth, "side")]):
        sc = ax.scatter(rest[order, a], rest[order, up], c=signed[order], s=5, cmap="coolwarm", vmin=-top, vmax=top)
        ax.set(title=view, aspect="equal")
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(sc, ax=axes, label="farthest out (+) or in (-) from the reference over the run [mm]", shrink=0.8)
    fig.suptitle(f"{name}: where the pop moved the skin (rest pose)", fontsize=8)
    fig.savefig(target, dpi=100)
    plt.close(fig)

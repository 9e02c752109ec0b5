"""Playing a popping scene to USD (goal mode) and its benchmark."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from ..errors import SceneError
from ..device import resolve_device
from ..scene import resolve_scene
from ..skinning import Skinner
from .activation import PoppingSettings, popping_settings
from .dynamics import PoppingDynamics
from .examples import PoppingExamples, examples_for_scene
from .layered import muscle_rest_offset_deltas
from .pose_space import PoseSpaceDeformer


@dataclass
class PoppingRun:
    """What :func:`run_popping` wrote.

    Attributes:
        path: The USD file.
        frames: Number of frames written.
        summary: Scalars: device, vertices, groups, substeps, dt [s], ``peak_overshoot_m`` (the
            farthest any vertex passed its goal, measured along its goal's disparity direction),
            ``max_goal_distance_m``, ``ms_per_frame`` (example-based skinning plus dynamics,
            without the USD writing).
    """

    path: Path
    frames: int
    summary: dict = field(default_factory=dict)


def run_popping(
    scene,
    out_path,
    *,
    examples: PoppingExamples | None = None,
    device=None,
    frames: tuple[int, int] | None = None,
    fps: float | None = None,
    alpha_min: float | None = None,
    beta: float | None = None,
    dt: float | None = None,
    progress: bool = True,
    comment: str = "",
    mode: str | None = None,
) -> PoppingRun:
    """Play a popping scene and write it to USD (the ``warpskin pop`` command).

    Prims under ``/warpskin``: ``popping`` (the dynamic skin), ``normal`` (example-based
    normal mesh, no popping), ``goal`` (the activated clenched goal, a guide) and ``lbs``
    (plain linear blend skinning, a guide), side by side for review. Every frame advances the
    dynamics by ``substeps`` steps ending at the frame's time, with the activation sampled at
    each step; the pose is the frame's.

    Args:
        scene: A :class:`~warpskin.scene.Scene`, a shipped scene name or a TOML path.
        out_path: ``.usdc`` (default format), ``.usda`` or ``.usd``; written atomically.
        examples: The examples; default :func:`examples_for_scene`.
        device: Warp device.
        frames: Inclusive frame range; default the scene's.
        fps: Output frame rate; default the scene's.
        alpha_min, beta, dt: Overrides of the scene's ``[popping]`` values.
        mode: ``"goal"`` or ``"layered"``; default the scene's ``[popping] mode``.
        progress: Progress bar on stderr.
        comment: Stage comment.

    Returns:
        A :class:`PoppingRun`.
    """
    from ..io.usd_export import UsdSkinWriter
    from ..progress import Progress

    scene = resolve_scene(scene)
    if fps is not None:
        if not (fps > 0):
            raise SceneError(f"fps must be positive, got {fps}")
        scene.fps = float(fps)
    settings = popping_settings(scene)
    where = str(scene.source or scene.name)
    for key, value in (("alpha_min", alpha_min), ("beta", beta), ("dt", dt)):
        if value is not None:
            setattr(settings, key, value)
    if mode is not None:
        settings.mode = mode
    settings.check(f"{where}: [popping]")
    if settings.mode == "layered":
        return _run_layered(scene, out_path, settings, examples=examples, device=device, frames=frames,
                            progress=progress, comment=comment)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first, last = frames if frames is not None else scene.frame_range()
    if first < 0 or last < first:
        raise SceneError(f"bad frame range {first}:{last}")
    if examples is None:
        examples = examples_for_scene(scene)
    deformer = PoseSpaceDeformer(rig, examples, device=device, joints=settings.joints, rbf_width=settings.rbf_width)
    settings.activation.check_groups(deformer.group_names, f"{where}: [popping.activation]")
    dynamics = PoppingDynamics(deformer, alpha_min=settings.alpha_min, beta=settings.beta, threshold=settings.threshold)
    frame_dt = 1.0 / scene.fps
    substeps = 1 if settings.dt is None else max(1, math.ceil(frame_dt / settings.dt - 1e-9))
    h = frame_dt / substeps
    if settings.beta * h > 1.0 + 1e-12:
        raise SceneError(f"{where}: beta * dt = {settings.beta * h:.4g} must be <= 1; lower beta or dt")
    groups = deformer.group_names
    tris = rig.triangles
    bar = Progress(last - first + 1, f"pop {scene.name} ({deformer.device}, {rig.vertex_count} vertices)", enabled=progress)
    peak_over, max_goal, compute_s = 0.0, 0.0, 0.0
    with UsdSkinWriter(out_path, fps=scene.fps, up_axis=rig.up_axis, comment=comment) as writer:
        writer.add_mesh("popping", tris, rest_points=rig.vertices, color=(0.85, 0.64, 0.52))
        writer.add_mesh("normal", tris, rest_points=rig.vertices, color=(0.55, 0.75, 0.55))
        writer.add_mesh("goal", tris, rest_points=rig.vertices, color=(0.8, 0.4, 0.4), purpose="guide")
        writer.add_mesh("lbs", tris, rest_points=rig.vertices, color=(0.4, 0.55, 0.85), purpose="guide")
        for f in range(first, last + 1):
            t = scene.frame_time(f)
            t0 = time.perf_counter()
            deformer.set_pose(rig.skinning_matrices(clip, t))
            for s in range(substeps):
                ts = t - frame_dt + (s + 1) * h
                dynamics.step(h, settings.activation.sample(ts, groups))
            lbs = deformer.lbs().numpy()
            x = dynamics.points.numpy()
            goal = dynamics.goal_points.numpy()
            normal = deformer.normal_points.numpy()
            compute_s += time.perf_counter() - t0
            writer.write_frame(f, {"popping": x, "normal": normal, "goal": goal, "lbs": lbs})
            # overshoot: how far past its goal a vertex is, along the goal's disparity direction
            d = goal - normal
            dl = np.linalg.norm(d, axis=1)
            moved = dl > 1e-6
            if moved.any():
                over = np.einsum("ij,ij->i", (x - goal)[moved], d[moved] / dl[moved, None])
                peak_over = max(peak_over, float(over.max()))
            max_goal = max(max_goal, float(np.linalg.norm(x - goal, axis=1).max()))
            bar.update()
    bar.close()
    count = last - first + 1
    return PoppingRun(
        path=Path(writer.path),
        frames=count,
        summary={
            "device": str(deformer.device),
            "vertices": rig.vertex_count,
            "groups": groups,
            "substeps": substeps,
            "dt_s": h,
            "alpha_min": settings.alpha_min,
            "beta": settings.beta,
            "peak_overshoot_m": peak_over,
            "max_goal_distance_m": max_goal,
            "ms_per_frame": 1e3 * compute_s / count,
        },
    )


# --------------------------------------------------------------------------------------------
# Benchmark
# --------------------------------------------------------------------------------------------
def bench_popping(device=None, steps: int = 200, repeat: int = 3, *, rings: int = 80, segments: int = 54) -> dict:
    """Milliseconds per frame of the popping pipeline on the arm at 4322 vertices (the paper's
    character has 4380 and runs at 60 FPS on a 3.6 GHz CPU), against plain LBS in the same run.

    Returns:
        ``vertices``; ``pose_space_ms`` (set_pose: host RBF weights, uploads and the pose space
        kernel) and ``pose_space_kernel_ms`` (the kernel alone); ``step_ms`` (one popping step:
        host activation latch plus the kernel); ``frame_ms`` (pose space + one step, the
        paper's per-frame work) and ``fps``; ``lbs_ms`` (the LBS Skinner: upload plus kernel)
        and ``lbs_kernel_ms``; ``frame_over_lbs`` and ``step_over_lbs_kernel`` ratios.
    """
    from ..bench import _best_ms
    from ..scenes.popping_arm import elbow_pose, make_popping_arm, popping_arm_examples

    if steps < 1 or repeat < 1:
        raise ValueError("steps and repeat must be >= 1")
    dev = resolve_device(device)
    rig = make_popping_arm(rings=rings, segments=segments)
    examples = popping_arm_examples(rig, rings=rings, segments=segments)
    # a slowly moving elbow, so every frame's pose (and RBF weights) differ
    mats = [elbow_pose(rig, 60.0 + 60.0 * k / max(steps - 1, 1)) for k in range(steps)]
    deformer = PoseSpaceDeformer(rig, examples, device=dev)
    dynamics = PoppingDynamics(deformer, alpha_min=0.1, beta=30.0)
    lbs = Skinner(rig, method="lbs", device=str(dev))
    h = 1.0 / 240.0
    act = np.ones(deformer.group_count)
    deformer.set_pose(mats[0])  # compile / load outside the timed regions
    dynamics.step(h, act)
    lbs.skin(mats[0])
    row = {
        "device": str(dev),
        "device_name": getattr(dev, "name", str(dev)),
        "warp": wp.config.version,
        "vertices": rig.vertex_count,
        "groups": deformer.group_count,
        "normal_examples": examples.normal_count,
        "steps": steps,
        "repeat": repeat,
    }
    row["pose_space_ms"] = _best_ms(lambda f: deformer.set_pose(mats[f]), steps, repeat, dev)
    row["pose_space_kernel_ms"] = _best_ms(lambda f: deformer.launch(), steps, repeat, dev)
    row["step_ms"] = _best_ms(lambda f: dynamics.step(h, act), steps, repeat, dev)

    def frame(f):
        deformer.set_pose(mats[f])
        dynamics.step(h, act)

    row["frame_ms"] = _best_ms(frame, steps, repeat, dev)
    row["fps"] = 1e3 / row["frame_ms"] if row["frame_ms"] > 0 else None
    row["lbs_ms"] = _best_ms(lambda f: lbs.skin(mats[f]), steps, repeat, dev)
    row["lbs_kernel_ms"] = _best_ms(lambda f: lbs.launch(), steps, repeat, dev)
    row["frame_over_lbs"] = row["frame_ms"] / row["lbs_ms"] if row["lbs_ms"] > 0 else None
    row["step_over_lbs_kernel"] = row["step_ms"] / row["lbs_kernel_ms"] if row["lbs_kernel_ms"] > 0 else None
    return row


def _run_layered(scene, out_path, settings: PoppingSettings, *, examples, device, frames, progress, comment) -> PoppingRun:
    from ..model import SkinModelBuilder
    from ..simulate import simulate

    examples = examples if examples is not None else examples_for_scene(scene)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first = (frames or scene.frame_range())[0]
    builder = SkinModelBuilder(rig, scene.model_params())
    deltas = muscle_rest_offset_deltas(builder, examples, rig.skinning_matrices(clip, scene.frame_time(first)))
    groups = list(examples.group_names)
    settings.activation.check_groups(groups, "[popping.activation]")
    result = simulate(scene, out_path, device=device, frames=frames, with_lbs=True, progress=progress, comment=comment,
                      builder=builder, rest_shape=(deltas, lambda t: settings.activation.sample(t, groups)))
    summary = dict(result.summary)
    summary["mode"] = "layered"
    summary["groups"] = groups
    return PoppingRun(path=result.path, frames=len(result.frames), summary=summary)

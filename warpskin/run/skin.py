"""``warpskin skin``: linear blend or dual-quaternion skinning of a scene to USD (the kinematic
baselines), through the frame runner."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SceneError
from ..io.usd_export import UsdSkinWriter, check_output_path
from ..options import with_overrides
from ..scene import resolve_scene
from ..skinning import Skinner
from .output import CharacterOutput
from .plan import FramePlan
from .runner import FrameRunner

__all__ = ["SkinningOptions", "SkinningStepper", "SkinRun", "skin_to_usd"]


class SkinningStepper:
    """LBS or DQS of a rig at the plan's frames (a kinematic stepper: nothing to integrate).

    Args:
        rig, clip, plan: What to skin, when.
        method: ``"lbs"`` or ``"dqs"``.
        device: Warp device.
        with_lbs: With ``method="dqs"``, also LBS as mesh ``lbs``.
        with_rest: Also the rest mesh as a static guide ``rest``.

    Points are of the welded surface; :class:`~warpskin.run.output.CharacterOutput` writes them
    in the file's topology.
    """

    def __init__(self, rig, clip, plan: FramePlan, *, method: str = "lbs", device=None, with_lbs: bool = False,
                 with_rest: bool = False, name: str = "") -> None:
        self.rig, self.clip, self.plan = rig, clip, plan
        self.skinner = Skinner(rig, method=method, device=device)
        self.lbs = Skinner(rig, method="lbs", device=device) if (with_lbs and method != "lbs") else None
        self.with_rest = with_rest
        self.variant = method
        self.label = f"skin {name or rig.name} ({method}, {self.skinner.device})"
        self._points: dict[str, np.ndarray] = {}

    def meshes(self) -> list:
        tris, rest = self.rig.triangles, self.rig.vertices
        out = [("skin", tris, rest, {"color": (0.85, 0.64, 0.52)})]
        if self.with_rest:
            out.append(("rest", tris, rest, {"animated": False, "color": (0.5, 0.5, 0.5), "purpose": "guide"}))
        if self.lbs is not None:
            out.append(("lbs", tris, rest, {"color": (0.4, 0.55, 0.85), "purpose": "guide"}))
        return out

    def advance(self, i: int) -> None:
        mats = self.rig.skinning_matrices(self.clip, self.plan.times[i])
        self._points = {"skin": self.skinner.skin(mats).numpy()}
        if self.lbs is not None:
            self._points["lbs"] = self.lbs.skin(mats).numpy()

    def frame(self, i: int) -> dict[str, np.ndarray]:
        return self._points


@dataclass
class SkinRun:
    """What :func:`skin_to_usd` wrote; unpacks as ``(path, frame_count)``.

    Attributes:
        path: The USD file.
        frames: Frames written.
        summary: Method, topology, rate, time codes, vertices written, device.
    """

    path: Path
    frames: int
    summary: dict = field(default_factory=dict)

    def __iter__(self):
        return iter((self.path, self.frames))


@dataclass(frozen=True)
class SkinningOptions:
    """How :func:`skin_to_usd` skins a scene: the Python API's options, and what ``warpskin skin``
    builds from its command line.

    Attributes:
        method: ``"lbs"`` or ``"dqs"``.
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``, ``None``: Warp's default).
        frames: Inclusive frame range; default the scene's.
        fps: Output frame rate (resampling the clip); default the scene's, else the clip's own.
        start_frame: Time code of the first frame written; default its frame number (the
            source's own time codes).
        with_rest: Also write the rest mesh as a static sibling prim ``rest``.
        with_lbs: With ``method="dqs"``, also write the LBS result as a sibling prim ``lbs``.
        topology: ``"file"`` (the file's own vertices, faces, UVs and materials, so the bake
            lines up with its source; default) or ``"welded"`` (the closed surface warpskin
            works on).
        progress: Show a progress bar on stderr.
        comment: Stage comment.
    """

    method: str = "lbs"
    device: str | None = None
    frames: tuple[int, int] | None = None
    fps: float | None = None
    start_frame: int | None = None
    with_rest: bool = False
    with_lbs: bool = False
    topology: str = "file"
    progress: bool = True
    comment: str = ""


def skin_to_usd(scene, out_path, options: SkinningOptions | None = None, **overrides) -> SkinRun:
    """Skin a scene frame by frame and write it to USD (the ``warpskin skin`` command).

    Args:
        scene: A :class:`~warpskin.scene.Scene` (or a shipped scene's name / TOML path / rig file).
        out_path: ``.usdc`` (default format), ``.usda`` or ``.usd`` file.
        options: :class:`SkinningOptions` (each field's meaning is documented there).
        overrides: Any of its fields by name (``frames=(0, 1)``, ``method="dqs"``).

    Returns:
        A :class:`SkinRun` (unpacks as ``(path, frame_count)``).

    Raises:
        InputError: an unknown option.
    """
    o = with_overrides(SkinningOptions, options, overrides, "skin")
    scene = resolve_scene(scene)
    check_output_path(out_path, inputs=scene.input_paths())  # before any work
    if o.fps is not None:
        if not (math.isfinite(o.fps) and o.fps > 0):
            raise SceneError(f"fps must be a positive number, got {o.fps}")
        scene.fps = float(o.fps)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    output = CharacterOutput(rig, o.topology, clip)
    plan = FramePlan.for_scene(scene, o.frames, start_frame=o.start_frame)
    stepper = SkinningStepper(rig, clip, plan, method=o.method, device=o.device, with_lbs=o.with_lbs,
                              with_rest=o.with_rest, name=scene.name)
    writer = UsdSkinWriter(out_path, fps=plan.fps, up_axis=rig.up_axis, comment=o.comment, root=output.root_name)
    record = FrameRunner(plan, stepper, writer=writer, progress=o.progress, steps_in_first_frame=True,
                         output=output).run()
    summary = {
        "scene": scene.name,
        "method": o.method,
        "device": str(stepper.skinner.device),
        "topology": o.topology,
        "fps": plan.fps,
        "frames": len(record.frames),
        "first_time_code": plan.time_codes[0],
        "last_time_code": plan.time_codes[-1],
        "vertices_written": rig.file_vertex_count if o.topology == "file" else rig.vertex_count,
        "mean_frame_ms": float(np.mean(record.step_ms)) if record.step_ms else 0.0,
    }
    return SkinRun(writer.path, len(record.frames), summary)

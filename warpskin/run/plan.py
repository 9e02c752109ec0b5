"""The timeline of a run: which frames, at which clip times, split into how many substeps."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import SceneError

__all__ = ["FramePlan"]


@dataclass
class FramePlan:
    """Frames of a run and the substeps between them.

    Attributes:
        frames: Frame numbers, inclusive range, ``[F]``.
        times: Clip time of every frame [s] (``frame / fps``: the source's seconds).
        fps: Frames per second of the output.
        substeps: Steps per frame, >= 1.
        dt: Step length [s] (``1 / fps / substeps``).
        time_codes: The USD time code each frame is written at: its frame number, or with a
            start frame, shifted so that the first frame is written there.
    """

    frames: list[int]
    times: list[float]
    fps: float
    substeps: int
    dt: float
    time_codes: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.time_codes:
            self.time_codes = [float(f) for f in self.frames]

    @classmethod
    def for_scene(cls, scene, frames: tuple[int, int] | None = None, *, max_dt: float | None = None,
                  start_frame: int | None = None) -> FramePlan:
        """The plan of ``scene`` over ``frames`` (default: the scene's range, which must lie in
        the clip), with substeps no longer than ``max_dt`` [s] (``None``: one step per frame),
        written from time code ``start_frame`` (default: the frame numbers themselves). The one
        place a frame range and a frame rate are checked."""
        first, last = frames if frames is not None else scene.frame_range()
        if isinstance(first, bool) or isinstance(last, bool) or int(first) != first or int(last) != last:
            raise SceneError(f"bad frame range {first}:{last}: frames are integers")
        first, last = int(first), int(last)
        if first < 0 or last < first:
            raise SceneError(f"bad frame range {first}:{last}: need 0 <= FIRST <= LAST")
        scene.check_frames(first, last)
        frame_list = list(range(first, last + 1))
        plan = cls.at_times(frame_list, [scene.frame_time(f) for f in frame_list], scene.frame_rate, max_dt=max_dt)
        if start_frame is not None:
            if isinstance(start_frame, bool) or int(start_frame) != start_frame:
                raise SceneError(f"start frame must be an integer, got {start_frame!r}")
            plan.time_codes = [float(int(start_frame) + f - first) for f in frame_list]
        return plan

    @classmethod
    def at_times(cls, frames: list[int], times: list[float], fps: float, *, max_dt: float | None = None) -> FramePlan:
        """The plan of ``frames`` at clip ``times`` [s], ``fps`` apart, with substeps no longer
        than ``max_dt`` [s] (``None``: one step per frame)."""
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise SceneError(f"fps must be a positive number, got {fps!r}")
        frame_dt = 1.0 / fps
        if max_dt is None:
            substeps = 1
        else:
            if not (math.isfinite(max_dt) and max_dt > 0):
                raise SceneError(f"dt must be a positive number of seconds, got {max_dt!r}")
            substeps = max(1, math.ceil(frame_dt / max_dt - 1e-9))
        return cls(frames=list(frames), times=list(times), fps=fps, substeps=substeps, dt=frame_dt / substeps)

    @property
    def count(self) -> int:
        return len(self.frames)

    def substep_times(self, *, leading: bool = False) -> list[float]:
        """Clip time at the end of every substep [s]: between consecutive frames (``F - 1``
        frames of substeps), or with ``leading`` also the substeps that end at the first frame
        (``F`` frames: a run that steps into every frame it writes)."""
        frame_dt = 1.0 / self.fps
        if leading:
            return [t - frame_dt + (s + 1) * self.dt for t in self.times for s in range(self.substeps)]
        return [t + (s + 1) * self.dt for t in self.times[:-1] for s in range(self.substeps)]

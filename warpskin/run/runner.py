"""The one frame loop every command runs: ``simulate``, ``pop`` (both modes), ``skin`` and the
benchmarks.

A *stepper* advances the character to each frame and hands back the points to write; the
:class:`FrameRunner` plans nothing itself but owns the loop around it: the progress bar, the
per-frame timing, the USD writer (opened, filled, closed, or aborted on an error so nothing
half-written is left) and the measurements. A :class:`~warpskin.errors.SimulationError` raised
by a stepper stops the loop and keeps every frame before it in a valid file; the error is
raised again, naming how many frames were kept and where. A stop signal
(:class:`~warpskin.errors.Stopped`, SIGTERM or SIGHUP on the command line) during a frame does
the same with the frames finished before it.

A stepper has:

* ``label``: what the progress bar says;
* ``meshes()``: ``[(name, triangles, rest_points, kwargs)]`` for
  :meth:`~warpskin.io.usd_export.UsdSkinWriter.add_mesh`;
* ``advance(i)``: step to the plan's frame ``i`` and read the result back to the host (the
  work that is timed);
* ``frame(i)``: the points of frame ``i`` to write, ``{mesh name: [N, 3]}`` (host arrays), and
  optionally ``"primvars": {mesh name: {primvar: [N]}}`` for animated primvars.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import SimulationError, Stopped
from ..progress import Progress
from .plan import FramePlan

__all__ = ["FrameRunner", "RunRecord"]


@dataclass
class RunRecord:
    """What a :meth:`FrameRunner.run` did.

    Attributes:
        frames: Frame numbers written.
        step_ms: Milliseconds per step of every frame (advance and read-back, divided by the
            substeps; 0 for a frame that needed no step).
        frame_ms: Milliseconds of every frame as a whole: its steps and read-back, then what the
            host does with the result (the stepper's ``frame``: guard, checks), writing it and
            the measures.
        failure: The error that stopped the run early, if one did (already re-raised by
            :meth:`FrameRunner.run` unless ``keep_failure``): a
            :class:`~warpskin.errors.SimulationError`, or the
            :class:`~warpskin.errors.Stopped` of a stop signal after the first frame.
    """

    frames: list[int] = field(default_factory=list)
    step_ms: list[float] = field(default_factory=list)
    frame_ms: list[float] = field(default_factory=list)
    failure: SimulationError | Stopped | None = None


class FrameRunner:
    """Runs a stepper over a :class:`FramePlan` into a writer and measurement callbacks.

    Args:
        plan: The frames and substeps.
        stepper: See the module docstring.
        writer: An open :class:`~warpskin.io.usd_export.UsdSkinWriter` (or ``None``: no file).
        measures: Callbacks ``f(i, frame, points, step_ms)`` called after a frame is written.
        progress: Show a progress bar on stderr.
        steps_in_first_frame: Whether the first frame is reached by stepping (popping) or is
            the initial state (the physical skin), for the per-step timing.
        output: A :class:`~warpskin.run.output.CharacterOutput` that declares the character's
            meshes in the file's topology (``None``: as the stepper gives them).
    """

    def __init__(self, plan: FramePlan, stepper, *, writer=None, measures: list[Callable] | None = None,
                 progress: bool = True, steps_in_first_frame: bool = False, output=None) -> None:
        self.plan = plan
        self.stepper = stepper
        self.writer = writer
        self.measures = list(measures or [])
        self.progress = progress
        self.steps_in_first_frame = steps_in_first_frame
        self.output = output

    def run(self, *, keep_failure: bool = False) -> RunRecord:
        """Run every frame. Returns the :class:`RunRecord`; a stepper's SimulationError is
        raised after the file is closed with the frames before it (or stored in the record
        with ``keep_failure``)."""
        plan, st, writer = self.plan, self.stepper, self.writer
        rec = RunRecord()
        bar = Progress(plan.count, st.label, enabled=self.progress)
        try:
            if writer is not None:
                for name, tris, rest, kw in st.meshes():
                    if self.output is not None:
                        self.output.declare(writer, name, tris, rest, kw)
                    else:
                        writer.add_mesh(name, tris, rest_points=rest, **kw)
                if self.output is not None:
                    self.output.declare_attachments(writer)
                names = [m[0] for m in st.meshes()]
                if self.output is not None and "lbs" in names and len(names) > 1:
                    # a reviewer flips between the result and LBS in any DCC (the LBS guide stays)
                    main_mesh, label = names[0], getattr(st, "variant", "physical")
                    writer.add_variant_set("deformer", {
                        label: {main_mesh: {"visibility": "inherited"}},
                        "lbs": {main_mesh: {"visibility": "invisible"}, "lbs": {"purpose": "default"}},
                    }, default=label)
            for i, f in enumerate(plan.frames):
                t0 = time.perf_counter()
                try:
                    st.advance(i)
                    stepped = i > 0 or self.steps_in_first_frame
                    step_ms = (time.perf_counter() - t0) * 1e3 / plan.substeps if stepped else 0.0
                    points = st.frame(i)
                except SimulationError as exc:
                    where = f" to {writer.path}" if writer is not None else ""
                    rec.failure = SimulationError(f"{exc} ({len(rec.frames)} frames before it were written{where})")
                    break
                except Stopped as exc:  # SIGTERM or SIGHUP: the finished frames are kept, as on a failure
                    if writer is not None and rec.frames:
                        exc.kept = (len(rec.frames), str(writer.path))
                        rec.failure = exc
                        break
                    raise
                primvars = points.pop("primvars", None) if isinstance(points, dict) else None
                if self.output is not None and self.output.attachments:
                    points = {**points, **self.output.attachment_points(plan.times[i])}
                if writer is not None:
                    writer.write_frame(plan.time_codes[i], points, primvars)
                rec.frames.append(f)
                rec.step_ms.append(step_ms)
                for measure in self.measures:
                    measure(i, f, points, step_ms)
                rec.frame_ms.append((time.perf_counter() - t0) * 1e3)
                bar.update(extra=f"{1e3 / step_ms:6.1f} steps/s" if step_ms > 0 else "")
        except BaseException:
            if writer is not None:
                writer.abort()
            raise
        finally:
            bar.close()
        if writer is not None:
            writer.close()  # on a failure the frames before it stay, in a valid file
        if rec.failure is not None and not keep_failure:
            raise rec.failure
        return rec


def first_non_finite(x: np.ndarray) -> int | None:
    """Index of the first row of ``x`` ``[N, 3]`` holding NaN or inf, else ``None``."""
    finite = np.isfinite(x).all(axis=1)
    if finite.all():
        return None
    return int(np.nonzero(~finite)[0][0])

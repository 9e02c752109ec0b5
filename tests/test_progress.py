"""The progress line's time left is measured from the units after the first (a run's first
frame is its initial state, taken without a step: timed with the others it made the first
estimate about 8x too short)."""

from __future__ import annotations

import io
import re

from warpskin.progress import Progress


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _eta(line: str) -> str:
    return re.search(r"eta\s+(\S+)", line).group(1)


def test_the_time_left_is_the_pace_after_the_first_unit():
    clock, out = _Clock(), io.StringIO()
    bar = Progress(10, "simulate", stream=out, clock=clock)
    clock.t += 0.05  # frame 0: the initial state, no step
    bar.update()
    clock.t += 1.0  # then a second a frame
    bar.update()
    lines = out.getvalue().splitlines()
    assert _eta(lines[0]) == "?"  # one cheap frame says nothing of the others' pace
    assert float(_eta(lines[1]).rstrip("s")) == 8.0  # 8 frames left at 1 s each (was 0.8 s: 10x short)
    for _ in range(8):
        clock.t += 1.0
        bar.update()
    assert _eta(out.getvalue().splitlines()[-1]) == "0.0s"


def test_a_single_unit_run_ends_at_zero():
    clock, out = _Clock(), io.StringIO()
    bar = Progress(1, "skin", stream=out, clock=clock)
    clock.t += 0.5
    bar.update()
    assert _eta(out.getvalue().splitlines()[-1]) == "0.0s"

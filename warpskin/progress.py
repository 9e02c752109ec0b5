"""A dependency-free progress bar on stderr: redraws in place on a terminal, prints a line
every 10 % otherwise (CI logs stay short)."""

from __future__ import annotations

import sys
import time


class Progress:
    """Progress of ``total`` units of work.

    Args:
        total: Number of units (frames).
        label: Text before the bar.
        unit: Name of a unit in the rate (``frames/s``).
        enabled: False silences it (``--quiet``).
        clock: Seconds, monotonic (default ``time.perf_counter``).

    The rate and the time left are measured from the first unit's end: the first unit of a run is
    unlike the others (a simulation's first frame is its initial state, taken without a step, or
    pays for compiling kernels), so until a second unit is done the time left is shown as ``?``.
    """

    def __init__(self, total: int, label: str = "", *, unit: str = "frames", enabled: bool = True, stream=None,
                 clock=time.perf_counter) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.unit = unit
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.done = 0
        self.clock = clock
        self.t0 = clock()
        self.t_first: float | None = None  # when the first update ended
        self.first_units = 0  # the units done by then
        self._last_decile = -1

    def update(self, n: int = 1, extra: str = "") -> None:
        self.done += n
        now = self.clock()
        if self.t_first is None:
            self.t_first, self.first_units = now, self.done
        if not self.enabled:
            return
        frac = min(self.done / self.total, 1.0)
        since = now - self.t_first
        measured = self.done - self.first_units
        if measured > 0 and since > 0:
            rate = measured / since
            eta = f"{(self.total - self.done) / rate:5.1f}s"
        else:  # only the first unit so far: nothing to tell the others' pace by
            rate = self.done / (now - self.t0) if now > self.t0 else 0.0
            eta = "    ?" if self.done < self.total else "  0.0s"
        text = f"{self.label} {self.done}/{self.total} {self.unit} {rate:6.1f} {self.unit}/s eta {eta} {extra}"
        if self.tty:
            width = 24
            fill = int(round(frac * width))
            self.stream.write(f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] " + text[len(self.label) + 1:])
            if self.done >= self.total:
                self.stream.write("\n")
            self.stream.flush()
        else:
            decile = int(frac * 10)
            if decile != self._last_decile or self.done >= self.total:
                if decile != self._last_decile:
                    self.stream.write(text.rstrip() + "\n")
                    self.stream.flush()
                self._last_decile = decile

    def close(self) -> None:
        if self.enabled and self.tty and self.done < self.total:
            self.stream.write("\n")
            self.stream.flush()

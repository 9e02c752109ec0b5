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
    """

    def __init__(self, total: int, label: str = "", *, unit: str = "frames", enabled: bool = True, stream=None) -> None:
        self.total = max(int(total), 1)
        self.label = label
        self.unit = unit
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.done = 0
        self.t0 = time.perf_counter()
        self._last_decile = -1

    def update(self, n: int = 1, extra: str = "") -> None:
        self.done += n
        if not self.enabled:
            return
        frac = min(self.done / self.total, 1.0)
        elapsed = time.perf_counter() - self.t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else 0.0
        text = f"{self.label} {self.done}/{self.total} {self.unit} {rate:6.1f} {self.unit}/s eta {eta:5.1f}s {extra}"
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

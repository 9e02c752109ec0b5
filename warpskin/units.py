"""The length unit physics takes a character's file in.

Everything a run sets by default is relative to the character (layer depths, the contact
thickness, the tether, the stop limits), except what has a physical unit of its own: gravity
[m/s^2] and the popping snap distance [m]. A character 1.7 mm tall in its file (a rig exported
in metres from a scene in millimetres, or with a 0.001 scale on its root) would sag a thousand
times as much, for its size, as the same rig at human scale. So physics takes the file's length
unit as the power of ten of the metre that brings the character's size nearest a human's
(:data:`HUMAN_SIZE`, in ratio): a character between about 54 cm and 5.4 m across (its bounding
box's largest side) is taken in metres, one 155 units across in centimetres, one 0.18 across
(a 0.1 scale on its root) in units of 10 m, one 0.0012 across in kilometres.
The same character at any power-of-ten scale of its file so gives the same result relative to
its size. ``[solver] units = "file"`` takes every file in metres.

This module imports no Warp kernels (the command line's parser reads it).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["HUMAN_SIZE", "PLAUSIBLE", "UNITS", "extent", "metres_per_unit", "file_unit", "describe"]

#: The size [m] (largest side of the bounding box) a character's size is brought nearest to.
HUMAN_SIZE = 1.7
#: Sizes [m] a character in metres plausibly has; outside them the rig's check warns.
PLAUSIBLE = (0.05, 20.0)


def extent(points) -> float:
    """The largest side of the axis-aligned bounding box of ``points`` ``[N, 3]``, in their unit;
    0 for no points or non-finite ones."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] == 0 or not np.all(np.isfinite(p)):
        return 0.0
    return float(np.ptp(p, axis=0).max())


def metres_per_unit(size: float) -> float:
    """The power of ten ``10^k`` (metres per file unit) for which ``size x 10^k`` is nearest
    :data:`HUMAN_SIZE` in ratio: 1 for sizes in ``[0.538, 5.38)``, 0.01 for 155, 10 for 0.18,
    1000 for 0.0012.
    1 for a size that is not a positive finite number."""
    size = float(size)
    if not (size > 0.0) or not math.isfinite(size):
        return 1.0
    return 10.0 ** round(math.log10(HUMAN_SIZE / size))


#: The ``[solver] units`` choices.
UNITS = ("auto", "file")


def file_unit(units: str, points) -> float:
    """Metres per file unit for a character at rest at ``points`` ``[N, 3]`` under ``units``
    (``[solver] units``): 1 for ``"file"``, :func:`metres_per_unit` of its :func:`extent` for
    ``"auto"``.

    Raises:
        ValueError: ``units`` is neither.
    """
    if units not in UNITS:
        raise ValueError(f"[solver] units must be 'auto' or 'file', got {units!r}")
    return 1.0 if units == "file" else metres_per_unit(extent(points))


def describe(unit: float) -> str:
    """``unit`` (metres per file unit, a power of ten) as a length name: ``"1 cm"``, ``"1 m"``."""
    names = {1e3: "1 km", 1.0: "1 m", 0.1: "1 dm", 0.01: "1 cm", 1e-3: "1 mm", 1e-6: "1 um"}
    for value, name in names.items():
        if math.isclose(unit, value, rel_tol=1e-9):
            return name
    return f"{unit:g} m"

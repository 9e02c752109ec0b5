"""Warp device selection with a clear error instead of a deep Warp exception."""

from __future__ import annotations

import warp as wp

from .errors import SceneError

# A library prints nothing on stdout of its own accord: Warp's start-up banner and its per-module
# load lines (log level INFO, Warp's default) are quieted to warnings when warpskin is imported,
# unless the caller chose a level already. Set ``wp.config.log_level = wp.LOG_INFO`` after the
# import to see them again (``warpskin --debug`` does).
if wp.config.log_level == getattr(wp, "LOG_INFO", 20):
    wp.config.log_level = getattr(wp, "LOG_WARNING", 30)

__all__ = ["resolve_device", "available_devices"]


def available_devices() -> list[str]:
    """``["cpu", "cuda:0", ...]``: every device Warp can run on here."""
    wp.init()
    return ["cpu"] + [str(d) for d in wp.get_cuda_devices()]


def resolve_device(device=None):
    """A ``wp.Device`` for ``device`` (``None``: Warp's default, ``"cpu"``, ``"cuda"``, ``"cuda:N"``).

    Raises:
        RigError: the device does not exist here (listing the ones that do).
    """
    wp.init()
    if device is None or isinstance(device, wp.Device):
        return wp.get_device(device)
    name = str(device)
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise SceneError(f"device {name!r} requested but no CUDA device is available here; devices: {available_devices()}")
    try:
        return wp.get_device(name)
    except Exception:
        raise SceneError(f"unknown device {name!r}; devices: {available_devices()}") from None

"""warpskin's exceptions: one base class, and one subclass per kind of failure, so a script (and
the CLI's exit status) can tell bad input from a failed simulation from a bug.

==========================  ====  =====================================================
class                       exit  raised when
==========================  ====  =====================================================
:class:`RigError`           2     a rig or the file it came from cannot be used (names the
                                  file, mesh, joint, vertex with the file's own numbers)
:class:`SceneError`         2     a scene file, a parameter or a command-line option is
                                  wrong (names the file and key, or the option)
:class:`OutputError`        2     the output path cannot be written (names the path)
:class:`InputError`         2     any of the three above; also an API called with arrays
                                  of the wrong shape, dtype or device
:class:`SimulationError`    3     a run failed or left its valid range; the frames before
                                  it are kept in a valid file
:class:`Stopped`            128   SIGTERM or SIGHUP reached the command (128 + the signal's
                            + n   number); the frames finished before it are kept
any other exception         1     a bug: ``warpskin --debug ...`` shows the traceback
==========================  ====  =====================================================
"""

from __future__ import annotations

import numpy as np

__all__ = ["WarpskinError", "InputError", "RigError", "SceneError", "OutputError", "SimulationError", "RigWarning",
           "Stopped", "index_list"]


class WarpskinError(Exception):
    """Base of every error warpskin raises on purpose; ``exit_code`` is the CLI's status."""

    exit_code = 1


class InputError(WarpskinError, ValueError):
    """Bad input or usage: the message names the bad part and what to do."""

    exit_code = 2


class RigError(InputError):
    """A rig (or a file it came from) cannot be used; the message names the bad part."""


class SceneError(InputError):
    """A scene file, a parameter or an option is wrong; the message names the file and key."""


class OutputError(InputError):
    """The output cannot be written where asked; nothing is left under the target name."""


class SimulationError(WarpskinError, RuntimeError):
    """A run failed (NaN, buffers that cannot hold the contacts) or left its valid range; the
    message names the frame and the particle, layer or vertex; earlier frames are kept."""

    exit_code = 3


class Stopped(BaseException):
    """A stop signal (SIGTERM, SIGHUP) reached a command; raised in its main thread, so that a
    run unwinds as an interrupt does (not an ``Exception``: no handler swallows it). The frame
    loop keeps the frames finished before it in a valid file, as a failed run does, and records
    how many in ``kept`` (``(frames, path)``; ``None``: nothing was written)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
        self.kept: tuple[int, str] | None = None


class RigWarning(UserWarning):
    """A rig problem that warpskin repaired (for example weights normalised)."""


def index_list(idx, limit: int = 8) -> str:
    """Indices for a message: the first ``limit`` of ``idx`` (any shape, flattened), comma
    separated, then ``", ... (N in all)"`` where there are more."""
    idx = np.asarray(idx).ravel()
    head = ", ".join(str(int(i)) for i in idx[:limit])
    more = f", ... ({idx.size} in all)" if idx.size > limit else ""
    return head + more

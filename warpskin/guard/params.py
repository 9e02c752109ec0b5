"""Settings of the guards of what is written, the bounds the quality checks ask, and the small
helpers the guards share (float32 rounding as written, the blend towards LBS, pair keys)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..quality import STRAIN_LIMIT
from ..settings import check_settings, setting

__all__ = ["GuardParams", "WRITTEN_STRAINED", "WRITTEN_FLIPPED", "as_written", "blend", "pair_keys"]

#: The bounds the quality checks ask of a written mesh: at most this share of its edges past
#: :data:`~warpskin.quality.STRAIN_LIMIT` beyond LBS's ...
WRITTEN_STRAINED = 0.005
#: ... and at most this share of its triangles turned over against LBS. A directly simulated
#: skin kept trusted where it bunches around LBS's own crossings
#: (:meth:`SurfaceGuard._kept_apart`) stays within the first; the jump limit's cut is taken back
#: to the guard's result only where it would leave either (:meth:`SurfaceGuard.keep`).
WRITTEN_FLIPPED = 0.01


@dataclass(frozen=True)
class GuardParams:
    """Settings of :class:`SurfaceGuard` (a scene's ``[guard]``). Each field's kind, default,
    range, unit and help are declared with it (:mod:`warpskin.settings`). Notes beyond the help:

    * ``strain`` stays below :data:`~warpskin.quality.STRAIN_LIMIT`, so the guard acts before
      the quality measure counts an edge.
    * ``trust_flipped``: a skin simulated directly is written as simulated until a frame's
      physical result turns more than this share of its triangles over against LBS (the
      :data:`WRITTEN_FLIPPED` the quality checks ask, so a trusted skin is written within it);
      from then on it is guarded.
    * ``trust_strained``: the same for the share of edges strained past the limit beyond LBS's
      (just under the 0.5 % the quality checks ask: a pop's swelling strains edges on purpose).
    * ``sway``, ``sway_frequency``, ``sway_damping``: a garment worn over the body swings as a
      damped oscillator per point driven by its LBS's acceleration, within ``sway`` x its room
      (:class:`~warpskin.guard.GarmentSway`); with the guard off (``enabled`` false) garments
      ride on the body, as written by the wrap.
    * ``swing``, ``swing_frequency``, ``swing_damping``: a loose piece
      (:func:`~warpskin.guard.swing.loose_pieces`) swings as a damped pendulum about where it
      hangs, by at most ``swing`` radians and half its room
      (:class:`~warpskin.guard.PieceSwing`); with the guard off it moves with what carries it.
    """

    _section = "guard"

    enabled: bool = setting(True, "bool", "guard the written meshes (off: written as the physics gives them)",
                            cli="--no-guard",
                            cli_help="write the meshes as the physics gives them, without the surface guard that takes "
                                     "back, smoothly, what would leave a mesh worse than its LBS (strained edges, "
                                     "flipped triangles, intersecting pairs)")
    strain: float = setting(1.45, "number", "edge strain (ratio to rest, either way) from which an edge is flagged",
                            low=1.0, open_low=True, high=STRAIN_LIMIT, must=f"in (1, {STRAIN_LIMIT:g}]")
    flip_degrees: float = setting(80.0, "number", "a triangle is flagged when its normal turns by more than this "
                                  "against LBS", unit="degrees", low=0.0, open_low=True, high=90.0, must="in (0, 90]")
    pairs: bool = setting(True, "bool", "flag intersecting triangle pairs that LBS does not have")
    match: float = setting(3.0, "number", "a new intersecting pair within this many median edges of a pair the "
                           "result lost is a crossing that slid", unit="median edges", low=0.0, high=100.0,
                           must="in [0, 100]")
    rounds: int = setting(12, "integer", "back-off rounds per frame before what is still flagged is set to its LBS",
                          low=0, high=64, must="an integer in [0, 64]")
    back_off: float = setting(0.25, "number", "share of a flagged point's weight taken away per round", low=0.0,
                              open_low=True, high=1.0, must="in (0, 1]")
    recover: float = setting(0.1, "number", "rise of the weight per frame where it is safe", low=0.0, high=1.0,
                             must="in [0, 1]")
    spread: float = setting(4.0, "number", "the weight changes over this many times the displacement it takes back "
                            "(along the surface)", low=0.0, open_low=True, high=100.0, must="in (0, 100]")
    trust_flipped: float = setting(WRITTEN_FLIPPED, "number", "a directly simulated skin is written as simulated "
                                   "until this share of its triangles turns over", low=0.0, high=1.0,
                                   must="in [0, 1]")
    trust_strained: float = setting(0.0045, "number", "... or this share of its edges strains past the limit "
                                    "beyond LBS's", low=0.0, high=1.0, must="in [0, 1]")
    joint_gap: float = setting(0.01, "number", "a piece moved as a whole (a rigid shoe, a robot's shin) moves the "
                               "points where it meets other pieces at rest by at most this share of the diagonal from "
                               "their LBS (0: no limit)", low=0.0, high=1.0, must="in [0, 1]")
    max_jump: float = setting(0.015, "number", "a written point's offset from LBS changes by at most this share of "
                              "the character's height from one frame to the next (0: no limit)", low=0.0, high=1.0,
                              must="in [0, 1]")
    untangle: int = setting(8, "integer", "rounds per frame of the pair-by-pair repair of the crossings the guard "
                            "leaves (those LBS drives too: a leg into the belly, a thigh through a skirt; 0: off)",
                            low=0, high=64, must="an integer in [0, 64]")
    untangle_step: float = setting(0.01, "number", "one round moves a crossing pair apart by at most this share of "
                                   "the character's diagonal", low=0.0, open_low=True, high=1.0, must="in (0, 1]")
    untangle_offset: float = setting(0.05, "number", "the repair moves no point farther than this share of the "
                                     "character's diagonal from its LBS", low=0.0, open_low=True, high=1.0,
                                     must="in (0, 1]")
    sway: float = setting(0.35, "number", "a loose garment's points swing after the body's motion by at most this "
                          "share of their rest gap over the body (0: garments ride on the body)", low=0.0, high=1.0,
                          must="in [0, 1]")
    sway_frequency: float = setting(2.0, "number", "natural frequency of a garment point's swing", unit="Hz", low=0.0,
                                    open_low=True, must="> 0")
    sway_damping: float = setting(0.2, "number", "damping ratio of a garment point's swing (1: critical)", low=0.0,
                                  must=">= 0")
    swing: float = setting(0.3, "number", "a loose piece (a hair bun LBS moves rigidly with the head) swings about "
                           "where it hangs by at most this angle (0: it moves with what carries it)", unit="radians",
                           low=0.0, high=1.5, must="in [0, 1.5]")
    swing_frequency: float = setting(4.0, "number", "natural frequency of a loose piece's swing", unit="Hz", low=0.0,
                                     open_low=True, must="> 0")
    swing_damping: float = setting(0.1, "number", "damping ratio of a loose piece's swing (1: critical)", low=0.0,
                                   must=">= 0")

    def check(self, where: str = "guard") -> None:
        """Every setting in its declared range (:func:`~warpskin.settings.check_settings`).

        Raises:
            SceneError: ``"<where>: [guard] <key> must be <range>, got <value>"``.
        """
        check_settings(self, where, "guard")


def as_written(x: np.ndarray) -> np.ndarray:
    """``x`` rounded to float32 (as USD stores points), in float64."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def blend(p: np.ndarray, lb: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``L + g (P - L)`` per row (``g`` per row): exactly ``P`` where ``g`` is 1, exactly ``L``
    where it is 0."""
    gw = np.asarray(g, dtype=np.float64)[:, None]
    return np.where(gw >= 1.0, p, np.where(gw <= 0.0, lb, lb + gw * (p - lb)))


def pair_keys(pairs: np.ndarray, count: int) -> np.ndarray:
    """Sorted unique int64 keys ``i * count + j`` of pairs ``[P, 2]`` with ``i < j``."""
    p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return np.unique(p[:, 0] * count + p[:, 1])

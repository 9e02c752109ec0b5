"""The guards of what is written, applied per frame after the physics (on the host):

* :class:`SurfaceGuard` (:mod:`warpskin.guard.surface`): every written mesh keeps the surface its
  LBS has;
* :class:`Untangle` (:mod:`warpskin.guard.untangle`): the crossings LBS drives too (a leg into
  the belly) are repaired pair by pair, after the surface guard;
* :class:`CrossGuard` (:mod:`warpskin.guard.cross`): written meshes keep apart as their LBS keeps
  them;
* :class:`WornRepair` (:mod:`warpskin.guard.worn`): garments worn over the simulated surface are
  repaired where they cross;
* :class:`GarmentSway` (:mod:`warpskin.guard.sway`): loose garments swing after the body's
  motion and settle after it stops;
* :class:`PieceSwing` (:mod:`warpskin.guard.swing`): loose pieces (a hair bun) swing about
  where they hang;
* :class:`PieceVolume` (:mod:`warpskin.guard.volume`): pieces written by capture keep the
  volume their simulation keeps;
* :class:`JumpLimit` (:mod:`warpskin.guard.jump`): no written point's offset from LBS jumps from
  one frame to the next;
* :class:`GuardParams` (:mod:`warpskin.guard.params`): their settings, a scene's ``[guard]``.

None of them changes the simulation, only what is written.
"""

from .cross import CrossGuard
from .jump import JumpLimit
from .params import WRITTEN_FLIPPED, WRITTEN_STRAINED, GuardParams
from .surface import SurfaceGuard
from .sway import GarmentSway
from .swing import PieceSwing
from .untangle import Untangle
from .volume import PieceVolume
from .worn import WornRepair

__all__ = ["GuardParams", "SurfaceGuard", "CrossGuard", "JumpLimit", "WornRepair", "PieceVolume", "GarmentSway", "PieceSwing",
           "Untangle",
           "WRITTEN_STRAINED",
           "WRITTEN_FLIPPED"]

"""The frame runner and its drivers: one loop for every command.

* :class:`FramePlan` (``plan``): frames, clip times and substeps; the one place frame ranges are
  checked.
* :class:`FrameRunner` (``runner``): the loop around a stepper: progress, timing, the USD
  writer (aborted on an error; a SimulationError keeps the frames before it), measurements.
* Steppers: :class:`PhysicsStepper` (``physics``: the multi-layer solver with graph capture,
  overflow retries, NaN checks and the pre-roll), :class:`PoppingStepper` (``pop``: the goal
  mode of the popping dance), :class:`SkinningStepper` (``skin``: LBS and DQS).
* Drivers: :func:`simulate` (``warpskin simulate``; its options: :class:`SimulationOptions`), :func:`run_popping` and :func:`pop`
  (``warpskin pop``, both modes), :func:`skin_to_usd` (``warpskin skin``); ``warpskin bench`` times the same steppers.
"""

from .physics import PhysicsStepper, initial_state
from .plan import FramePlan
from .pop import PoppingOptions, PoppingRun, PoppingStepper, pop, run_popping
from .runner import FrameRunner, RunRecord
from .simulate import SimulationOptions, SimulationResult, simulate
from .skin import SkinningOptions, SkinningStepper, skin_to_usd

__all__ = [
    "FramePlan",
    "FrameRunner",
    "RunRecord",
    "PhysicsStepper",
    "PoppingStepper",
    "SkinningStepper",
    "initial_state",
    "simulate",
    "SimulationOptions",
    "SimulationResult",
    "run_popping",
    "PoppingOptions",
    "pop",
    "PoppingRun",
    "skin_to_usd",
    "SkinningOptions",
]

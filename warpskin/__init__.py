"""warpskin: physically-based character skinning on NVIDIA Warp."""

from .errors import InputError, OutputError, RigError, RigWarning, SceneError, SimulationError, WarpskinError
from .rig import Clip, Rig, Skeleton, Track

#: The version, in one place: the package metadata, ``warpskin --version``, every USD file's
#: ``customLayerData["warpskin:version"]`` and the batch manifest read it; CHANGELOG.md records it.
__version__ = "0.1.0"

__all__ = [
    "Clip",
    "Rig",
    "Skeleton",
    "Track",
    "WarpskinError",
    "InputError",
    "RigError",
    "SceneError",
    "OutputError",
    "SimulationError",
    "RigWarning",
    "__version__",
]


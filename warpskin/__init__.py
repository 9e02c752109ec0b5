"""warpskin: physically-based character skinning on NVIDIA Warp."""

from .rig import Clip, Rig, RigError, RigWarning, Skeleton, Track

__version__ = "0.1.0"

__all__ = ["Clip", "Rig", "RigError", "RigWarning", "Skeleton", "Track", "__version__"]


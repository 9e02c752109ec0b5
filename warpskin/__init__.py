"""warpskin: physically-based character skinning on NVIDIA Warp."""

import os as _os

# Installed, ``warpskin.kernels`` and ``warpskin.scenes`` are the repository's top-level
# ``kernels/`` and ``scenes/`` (pyproject's package-dir). Imported from a checkout instead (any
# ``python -m`` run in it puts ``warpskin/`` first on the path), they are found there: the
# checkout's root joins the package's search path.
_root = _os.path.dirname(_os.path.dirname(_os.path.abspath(__file__)))
if not _os.path.isdir(_os.path.join(_os.path.dirname(__file__), "kernels")) and \
        _os.path.isfile(_os.path.join(_root, "kernels", "__init__.py")):
    __path__.append(_root)  # noqa: F821 (a package's own __path__)
del _root

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


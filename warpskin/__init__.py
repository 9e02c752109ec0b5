"""warpskin: physically-based character skinning on NVIDIA Warp."""


def _checkout_subpackages() -> None:
    """Installed, ``warpskin.kernels`` and ``warpskin.scenes`` are the repository's top-level
    ``kernels/`` and ``scenes/`` (pyproject's package-dir). Imported from a checkout instead (any
    ``python -m`` run in it puts ``warpskin/`` first on the path) no finder knows them: they are
    loaded from there, those two only (the checkout's root never joins the package's path)."""
    import importlib.util
    import os
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    for name in ("kernels", "scenes"):
        full = f"{__name__}.{name}"
        init = os.path.join(os.path.dirname(here), name, "__init__.py")
        if full in sys.modules or os.path.isdir(os.path.join(here, name)) or not os.path.isfile(init):
            continue
        if importlib.util.find_spec(full) is not None:  # an editable install's finder knows it
            continue
        spec = importlib.util.spec_from_file_location(full, init, submodule_search_locations=[os.path.dirname(init)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[full] = module
        spec.loader.exec_module(module)
        globals()[name] = module


_checkout_subpackages()

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


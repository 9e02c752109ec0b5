"""warpskin: physically-based character skinning on NVIDIA Warp."""

from .rig import Clip, Rig, RigError, RigWarning, Skeleton, Track

__version__ = "0.1.0"

__all__ = ["Clip", "Rig", "RigError", "RigWarning", "Skeleton", "Track", "__version__"]


def _source_tree_subpackages() -> None:
    """In a source checkout (not installed), ``kernels/`` and ``scenes/`` sit beside the
    package; make them importable as ``warpskin.kernels`` / ``warpskin.scenes`` the way the
    installed package lays them out (pyproject's package-dir), so ``python -m pytest`` from a
    checkout works too."""
    from pathlib import Path

    here = Path(__file__).resolve().parent
    root = here.parent
    if not (here / "kernels").is_dir() and (root / "kernels" / "__init__.py").is_file() and (root / "pyproject.toml").is_file():
        __path__.append(str(root))  # noqa: F821 - the package's own search path


_source_tree_subpackages()

"""Readers and writers: glTF 2.0 and UsdSkel rigs in, time-sampled USD skins out."""

from __future__ import annotations

from pathlib import Path

from ..rig import Rig, RigError

__all__ = ["load_rig", "list_meshes", "RIG_EXTENSIONS"]

GLTF_EXTENSIONS = (".glb", ".gltf")
USD_RIG_EXTENSIONS = (".usd", ".usda", ".usdc", ".usdz")
RIG_EXTENSIONS = GLTF_EXTENSIONS + USD_RIG_EXTENSIONS


def _kind(path: Path) -> str:
    if not path.exists():
        raise RigError(f"{path}: no such file")
    if not path.is_file():
        raise RigError(f"{path}: not a file")
    ext = path.suffix.lower()
    if ext in GLTF_EXTENSIONS:
        return "gltf"
    if ext in USD_RIG_EXTENSIONS:
        return "usd"
    raise RigError(f"{path}: unknown rig format {ext or '(no extension)'}; expected one of {RIG_EXTENSIONS}")


def load_rig(path: str | Path, *, mesh: str | None = None, unit_scale: float | None = None, weld: bool = True) -> Rig:
    """Load a rigged, animated character.

    Args:
        path: A ``.glb``/``.gltf`` or ``.usd``/``.usda``/``.usdc``/``.usdz`` file.
        mesh: Which skinned mesh, by name (``warpskin info`` lists them); default the largest.
        unit_scale: Multiply every length by this after the file's own unit conversion (e.g.
            0.01 for a glTF authored in centimetres).
        weld: Merge vertices that the file split at UV/normal seams (needed for a closed
            surface; the exporter can still write the file's own topology).

    Returns:
        The :class:`~warpskin.rig.Rig`, validated, in metres.
    """
    p = Path(path)
    if _kind(p) == "gltf":
        from .gltf import load_gltf

        rig = load_gltf(p, mesh=mesh, weld=weld)
    else:
        from .usdskel import load_usd

        rig = load_usd(p, mesh=mesh, weld=weld)
    if unit_scale is not None and unit_scale != 1.0:
        rig = rig.rescaled(unit_scale)
    return rig


def list_meshes(path: str | Path) -> list[dict]:
    """The meshes of a rig file (name, vertex and triangle counts, joints, skinned or not)."""
    p = Path(path)
    if _kind(p) == "gltf":
        from .gltf import list_gltf_meshes

        return list_gltf_meshes(p)
    from .usdskel import list_usd_meshes

    return list_usd_meshes(p)

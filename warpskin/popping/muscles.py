"""Muscle groups found from the skeleton, for layered popping on any closed rig (no examples).

A group is one or more bones of the multi-layer model. Clenched, it swells the fat, muscle and
skin layers of the skin vertices those bones carry (their dominant bone) outward from the bone,
as the paper's fusiform muscles: most at mid-bone, nothing at the joints,

    d_v = min(swell * h_v, cap * length_b) * sin(pi t_v)^2 * (x_v - f_v) / |x_v - f_v|

with ``x_v`` the skin vertex at rest, ``f_v`` its foot on the bone's centre line, ``t_v`` in
[0, 1] the foot's place along the bone, ``h_v`` the depth of fat and muscle there (skin to
bone layer) and ``length_b`` the bone's length. The rest-shape drive of
:func:`~warpskin.popping.layered.rest_offset_deltas` turns that into the model's clenched
rest shape; the physical skin makes the pop.

Found automatically: every bone at least ``min_length`` x the character's diagonal long that
carries at least ``min_vertices`` skin vertices (upper arms, forearms, thighs, calves, a long
chest bone), named after its joint. Or named by the user: ``name=pattern`` (the bones whose
joint names match the glob pattern, case-insensitive) or a found group's name.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import SceneError

__all__ = ["Muscle", "muscles_from_skeleton", "DEFAULT_SWELL"]

DEFAULT_SWELL = 0.4
"""Peak rest-shape swelling, as a share of the fat-plus-muscle depth (the skin rises by about
half of it once the layers around it give)."""
_CAP = 0.15  # the swelling is at most this share of its bone's length


@dataclass
class Muscle:
    """One muscle group found from the skeleton.

    Attributes:
        name: The group's name (its activation signal).
        joints: The bones it swells (joint names).
        vertices: Skin vertices it moves (refined ones included).
        depth_m: Median fat-plus-muscle depth under them [m].
        peak_m: The largest rest-shape swelling [m].
    """

    name: str
    joints: list[str]
    vertices: int
    depth_m: float
    peak_m: float


def _profile(t: np.ndarray) -> np.ndarray:
    """The swelling along the bone, ``t`` in [0, 1]: ``-sin^2(pi t) cos(2 pi t)``, 1 at mid-bone,
    0 at the joints and at the quarter points, a shallow dip (at most 0.11) between them (the
    belly gathers from the tendons, half the volume it adds taken from near the ends)."""
    return -np.sin(np.pi * t) ** 2 * np.cos(2.0 * np.pi * t)


def _field(layers, bones: np.ndarray, swell: float) -> np.ndarray:
    """``[V, 3]`` the swelling of the skin vertices whose dominant bone is in ``bones``."""
    skin, bone_layer = layers.positions[0], layers.positions[3]
    depth = np.linalg.norm(skin - bone_layer, axis=1)
    radial = skin - layers.foot
    r = np.linalg.norm(radial, axis=1)
    on = np.isin(layers.bone, bones) & (r > 1e-9) & ~layers.unresolved
    length = layers.bones.length[layers.bone]
    t = np.clip(layers.bone_t, 0.0, 1.0)
    amount = np.minimum(swell * depth, _CAP * length) * _profile(t)
    out = np.zeros_like(skin)
    out[on] = (amount[on] / r[on])[:, None] * radial[on]
    return out


def muscles_from_skeleton(builder, groups: Sequence[str] | None = None, *, swell: float = DEFAULT_SWELL,
                          min_length: float = 0.08, min_vertices: int = 12,
                          where: str = "--groups") -> tuple[list[Muscle], np.ndarray]:
    """The muscle groups of a built multi-layer model and their clenched swellings.

    Args:
        builder: A :class:`~warpskin.model.SkinModelBuilder` (built here if it is not).
        groups: ``None``: every group found (see the module docstring); else entries
            ``name=pattern`` (the bones matching the glob) or ``name`` (a found group, or a
            bone of that joint name that carries skin), in the order given.
        swell: Peak swelling as a share of the fat-plus-muscle depth, in (0, 2].
        min_length: Shortest bone found automatically, as a share of the character's diagonal.
        min_vertices: Fewest skin vertices a bone found automatically carries.

    Returns:
        ``(muscles, displacements [G, V, 3] [m])`` on the model's skin vertices.

    Raises:
        SceneError: no group found or a bad entry, naming it and listing the bones.
    """
    if not (isinstance(swell, (int, float)) and 0.0 < swell <= 2.0):
        raise SceneError(f"swell must be in (0, 2] (a share of the tissue depth), got {swell!r}")
    builder.build()
    layers = builder.layers
    names = list(layers.bones.joint_names)
    count = np.bincount(layers.bone[~layers.unresolved], minlength=len(names))
    carried = [j for j in range(len(names)) if count[j] > 0 and layers.bones.length[j] > 0.0]
    diagonal = builder.rig.size()
    found = {names[j]: [j] for j in carried
             if layers.bones.length[j] >= min_length * diagonal and count[j] >= min_vertices}
    chosen: list[tuple[str, list[int]]] = []
    if groups is None:
        if not found:
            longest = sorted(carried, key=lambda j: -layers.bones.length[j])[:6]
            raise SceneError(f"no muscle group found from the skeleton (no bone {min_length:g} of the "
                             f"{diagonal:.3g} m diagonal long that carries {min_vertices} skin vertices; longest: "
                             f"{', '.join(f'{names[j]} {layers.bones.length[j]:.3g} m' for j in longest)}): "
                             f"name them with --groups NAME=JOINT_PATTERN")
        chosen = list(found.items())
    else:
        seen = set()
        for entry in groups:
            name, eq, pattern = (str(entry).partition("="))
            name, pattern = name.strip(), pattern.strip()
            if not name or (eq and not pattern) or name in seen:
                raise SceneError(f"{where}: {entry!r}: give NAME or NAME=JOINT_PATTERN, each name once")
            seen.add(name)
            if eq:
                bones = [j for j in carried if fnmatch.fnmatchcase(names[j].lower(), pattern.lower())]
                if not bones:
                    raise SceneError(f"{where}: {entry!r}: no bone that carries skin matches {pattern!r} (bones: "
                                     f"{', '.join(names[j] for j in carried[:12])}{', ...' if len(carried) > 12 else ''})")
            elif name in found:
                bones = found[name]
            elif name in names and names.index(name) in carried:
                bones = [names.index(name)]
            else:
                raise SceneError(f"{where}: no muscle group {name!r}; found: {', '.join(found) or 'none'} (or name "
                                 f"one: {name}=JOINT_PATTERN)")
            chosen.append((name, bones))
    muscles, fields = [], []
    depth = np.linalg.norm(layers.positions[0] - layers.positions[3], axis=1)
    for name, bones in chosen:
        d = _field(layers, np.asarray(bones), swell)
        moved = np.linalg.norm(d, axis=1)
        on = np.isin(layers.bone, bones) & ~layers.unresolved
        muscles.append(Muscle(name, [names[j] for j in bones], int(np.count_nonzero(moved > 0.0)),
                              float(np.median(depth[on])) if on.any() else 0.0, float(moved.max())))
        fields.append(d)
    return muscles, np.stack(fields)

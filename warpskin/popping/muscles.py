"""Muscle groups found from the skeleton, for layered popping on any closed rig (no examples).

A group is one or more bones of the multi-layer model. Clenched, it swells the fat, muscle and
skin layers of the skin vertices those bones carry (their dominant bone) outward from the bone,
as the paper's fusiform muscles: a belly at mid-bone, nothing at the joints,

    b_v = min(swell * h_v, cap * length_b) * (-sin^2(pi t_v) cos(2 pi t_v))

along ``(x_v - f_v) / |x_v - f_v|``, with ``x_v`` the skin vertex at rest, ``f_v`` its foot on
the bone's centre line, ``t_v`` in [0, 1] the foot's place along the bone, ``h_v`` the depth of
fat and muscle there (skin to bone layer) and ``length_b`` the bone's length. The tissue keeps
its volume: a thinning around the belly (over the group's bones, their parents and children;
smooth across the sub-volumes' cut planes; fading out before the skin other bones carry) takes
back exactly what the belly adds to every sub-volume (:func:`_field`). Without that, the volume
constraints took it back over the whole sub-volume, moving skin far from the muscle. The
rest-shape drive of
:func:`~warpskin.popping.layered.rest_offset_deltas` turns the swelling into the model's clenched
rest shape; the physical skin makes the pop; :func:`belly_of_swelling` marks the skin it
stretches on purpose (which the surface guard lets stretch).

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
import scipy.sparse as sp

from ..errors import SceneError
from ..metrics import signed_volume
from ..preprocess.fast_summation import vertex_adjacency

__all__ = ["Muscle", "muscles_from_skeleton", "belly_of_swelling", "choose_groups", "groups_of_model", "DEFAULT_SWELL"]

DEFAULT_SWELL = 0.3
"""Peak rest-shape swelling of the belly, as a share of the fat-plus-muscle depth (with the
thinning around it taken off, the skin rises by most of it)."""
#: The swelling of a muscle group is at most this share of its bone's length.
SWELL_CAP = 0.15
_BUFFER = 2  # rings over which the thinning fades towards the skin the group's neighbourhood does not carry
_SMOOTH = 8  # rings over which the thinning's share passes from one sub-volume to the next


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
    """The belly along the bone, ``t`` in [0, 1]: ``-sin^2(pi t) cos(2 pi t)``, 1 at mid-bone,
    0 at the joints and at the quarter points, a shallow dip (at most 0.11) between them."""
    return -np.sin(np.pi * t) ** 2 * np.cos(2.0 * np.pi * t)


def neighbourhood(bones: Sequence[int], parents: np.ndarray) -> list[int]:
    """The joints a group's thinning may use: its ``bones``, their parents and their children."""
    return sorted(set(bones) | {int(parents[j]) for j in bones if parents[j] >= 0}
                  | {k for k in range(len(parents)) if parents[k] in bones})


def thinning_reach(share: np.ndarray, in_hood: np.ndarray, ring: sp.csr_matrix) -> np.ndarray:
    """``[V]`` in [0, 1], where a group's thinning may act: ``clip(2 share - 1)`` (none where
    the neighbourhood's joints carry at most half the vertex, ``share [V]`` their summed
    weights), faded to none over ``_BUFFER`` rings (``ring``: adjacency, self included) towards
    a vertex whose dominant joint is outside the neighbourhood (``in_hood [V]`` False), so that
    it does not reach the skin beyond."""
    near = np.clip(2.0 * share - 1.0, 0.0, 1.0)
    reached = ~np.asarray(in_hood, dtype=bool)
    level = np.where(reached, 0, _BUFFER + 1)
    for k in range(1, _BUFFER + 1):
        reached = reached | (ring @ reached.astype(np.float64) > 0.0)
        level = np.where(reached & (level > k), k, level)
    return near * np.clip(level / (_BUFFER + 1.0), 0.0, 1.0)


def _field(layers, bones: np.ndarray, swell: float, thinning: np.ndarray, volumes) -> np.ndarray:
    """``[V, 3]`` the clenched swelling of the group of ``bones``.

    The belly: ``min(swell * h_v, cap * length) * _profile(t_v)`` radially from the bone on the
    skin vertices whose dominant bone is in ``bones``. Its volume is taken back by a thinning
    ``sum_k m_k * thinning[v, k]`` radially inwards (``thinning [V, S]``: one smooth shape per
    sub-volume, :func:`muscles_from_skeleton`), ``m`` such that every sub-volume keeps its
    volume (``volumes(points) -> [S]``): Newton steps with the finite-difference Jacobian of
    the volumes by ``m`` reach 1e-6 of each (the belly's second-order gain is about ``d / R``
    of its first, a fifth at a third of a limb's radius: a first-order balance is not enough).

    A clenched muscle keeps its volume (it thickens as it shortens): a swelling that added
    volume would be taken back by the sub-volume's volume constraint, over all of that
    sub-volume's skin, far from the muscle too."""
    skin, bone_layer = layers.positions[0], layers.positions[3]
    depth = np.linalg.norm(skin - bone_layer, axis=1)
    radial = skin - layers.foot
    r = np.linalg.norm(radial, axis=1)
    ok = (r > 1e-9) & ~layers.unresolved
    on = np.isin(layers.bone, bones) & ok
    length = layers.bones.length[layers.bone]
    t = np.clip(layers.bone_t, 0.0, 1.0)
    amount = np.where(on, np.minimum(swell * depth, SWELL_CAP * length) * _profile(t), 0.0)
    shapes = np.where(ok[:, None], thinning, 0.0)
    direction = np.zeros_like(skin)
    direction[ok] = radial[ok] / r[ok][:, None]
    rest = volumes(skin)

    def excess(m: np.ndarray) -> np.ndarray:
        return volumes(skin + (amount - shapes @ m)[:, None] * direction) - rest

    used = np.nonzero(shapes.max(axis=0) > 0.0)[0]
    m = np.zeros(shapes.shape[1])
    if used.size == 0 or not amount.any():
        return amount[:, None] * direction
    step = 1e-4  # [m] the finite differences' thinning
    base = excess(m)
    jac = np.zeros((len(rest), used.size))
    for c, k in enumerate(used):
        e = np.zeros_like(m)
        e[k] = step
        jac[:, c] = (excess(e) - base) / step
    err = base
    for _ in range(8):
        if np.all(np.abs(err) <= 1e-6 * np.abs(rest)):
            break
        trial = m.copy()
        trial[used] -= np.linalg.lstsq(jac, err, rcond=None)[0]
        new = excess(trial)
        if np.abs(new).max() >= np.abs(err).max():
            break  # no longer converging: keep the best
        m, err = trial, new
    return (amount - shapes @ m)[:, None] * direction


def choose_groups(names: Sequence[str], length: np.ndarray, count: np.ndarray, diagonal: float,
                  groups: Sequence[str] | None, *, min_length: float = 0.08, min_vertices: int = 12,
                  where: str = "--groups") -> list[tuple[str, list[int]]]:
    """The muscle groups ``[(name, joint indices)]`` of a skeleton whose bones (joint ``j``:
    ``names[j]``, ``length[j]`` [m]) carry ``count[j]`` skin vertices, on a character of
    ``diagonal`` [m]: every bone ``min_length`` x the diagonal long carrying ``min_vertices``
    (``groups`` None), else the entries of ``groups`` as :func:`muscles_from_skeleton` reads them.

    Raises:
        SceneError: no group found, or a bad entry (naming it and listing the bones).
    """
    names = list(names)
    carried = [j for j in range(len(names)) if count[j] > 0 and length[j] > 0.0]
    found = {names[j]: [j] for j in carried if length[j] >= min_length * diagonal and count[j] >= min_vertices}
    chosen: list[tuple[str, list[int]]] = []
    if groups is None:
        if not found:
            longest = sorted(carried, key=lambda j: -length[j])[:6]
            raise SceneError(f"no muscle group found from the skeleton (no bone {min_length:g} of the "
                             f"{diagonal:.3g} m diagonal long that carries {min_vertices} skin vertices; longest: "
                             f"{', '.join(f'{names[j]} {length[j]:.3g} m' for j in longest)}): "
                             f"name them with --groups NAME=JOINT_PATTERN")
        return list(found.items())
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
    return chosen


def groups_of_model(builder, groups: Sequence[str] | None = None, *, min_length: float = 0.08,
                    min_vertices: int = 12, where: str = "--groups") -> list[tuple[str, list[int]]]:
    """The muscle groups ``[(name, joint indices)]`` of a multi-layer model (built here if it
    is not), by :func:`choose_groups` over the bones its skin vertices project to."""
    builder.build()
    layers = builder.layers
    count = np.bincount(layers.bone[~layers.unresolved], minlength=len(layers.bones.joint_names))
    return choose_groups(layers.bones.joint_names, layers.bones.length, count, builder.rig.size(), groups,
                         min_length=min_length, min_vertices=min_vertices, where=where)


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
    chosen = groups_of_model(builder, groups, min_length=min_length, min_vertices=min_vertices, where=where)
    layers = builder.layers
    names = list(layers.bones.joint_names)
    muscles, fields = [], []
    depth = np.linalg.norm(layers.positions[0] - layers.positions[3], axis=1)
    rig = builder.rig
    sub = builder.subvolumes
    piece = sub.triangle_labels() if sub is not None else np.zeros(len(rig.triangles), dtype=np.int64)
    count = int(piece.max()) + 1
    if sub is not None:
        def volumes(x):
            return sub.volumes(x, sub.center_rest)
    else:  # the closed skin as one
        def volumes(x):
            return np.array([signed_volume(x, rig.triangles)])
    v = rig.vertex_count
    ring = (vertex_adjacency(rig.triangles, v) + sp.identity(v, format="csr")).astype(np.float64)  # self included
    average = sp.diags(1.0 / np.asarray(ring.sum(axis=1)).ravel()) @ ring
    # each vertex's share of each sub-volume's thinning: its sub-volume (most of its triangles),
    # smoothed over a few rings, so that the thinning is continuous across the cuts
    votes = np.zeros((v, count))
    for k in range(3):
        np.add.at(votes, (rig.triangles[:, k], piece), 1.0)
    owner = np.zeros((v, count))
    owner[np.arange(v), votes.argmax(axis=1)] = 1.0
    for _ in range(_SMOOTH):
        owner = average @ owner
    parents = rig.skeleton.parents
    dominant = rig.joint_indices[np.arange(v), np.argmax(rig.joint_weights, axis=1)]
    for name, bones in chosen:
        hood = neighbourhood(bones, parents)
        share = np.where(np.isin(rig.joint_indices, hood), rig.joint_weights, 0.0).sum(axis=1)
        near = thinning_reach(share, np.isin(dominant, hood), ring)
        d = _field(layers, np.asarray(bones), swell, near[:, None] * owner, volumes)
        moved = np.linalg.norm(d, axis=1)
        on = np.isin(layers.bone, bones) & ~layers.unresolved
        muscles.append(Muscle(name, [names[j] for j in bones], int(np.count_nonzero(moved > 0.0)),
                              float(np.median(depth[on])) if on.any() else 0.0, float(moved.max())))
        fields.append(d)
    return muscles, np.stack(fields)


def belly_of_swelling(builder, displacements: np.ndarray, share: float = 0.25) -> np.ndarray:
    """``[V]`` the skin vertices that some group's clenched swelling (``displacements [G, V, 3]``
    [m], as :func:`muscles_from_skeleton` returns them) moves outward, away from its bone, by
    more than ``share`` of that group's largest outward move: the bellies, whose skin the pop
    stretches on purpose (the thinning and the joints are not)."""
    layers = builder.layers
    radial = layers.positions[0] - layers.foot
    radial /= np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None]
    out = np.einsum("gvc,vc->gv", np.asarray(displacements, dtype=np.float64), radial)
    top = np.maximum(out.max(axis=1, keepdims=True), 0.0)
    return np.any((out > share * top) & (top > 0.0), axis=0)

"""Bone segments (center lines) of a rig in rest space, and each vertex's bone.

Deul & Bender 2013, section 3: "For each vertex of the original mesh the nearest point on the
center line of the corresponding bone is computed. This bone is chosen depending on the skinning
weights of the mesh vertices."

Bone ``j`` runs from joint ``j`` to its child (to the mean of its children where it has
several). A leaf joint gets a short segment along its parent's direction: ``leaf_fraction`` of the parent
bone, but at most half way to the farthest vertex it dominates, so the segment stays inside.
A joint with neither (a root without children, as in a flat hierarchy where every joint hangs
from the scene root, or a joint at the same place as its child and its parent) gets its
segment from the geometry it drives: the principal axis of its weighted vertices, through
their weighted centre, over the middle 80 % of their extent along it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rig import Rig, RigError

__all__ = ["Bones", "bone_segments", "dominant_bone", "closest_point_on_segments", "weighted_principal_axis"]


@dataclass
class Bones:
    """Bone center lines at rest.

    Attributes:
        start: Segment start (the joint) [m], ``[J, 3]``.
        end: Segment end [m], ``[J, 3]``.
        joint_names: For messages, ``[J]``.
    """

    start: np.ndarray
    end: np.ndarray
    joint_names: list[str]

    @property
    def length(self) -> np.ndarray:
        return np.linalg.norm(self.end - self.start, axis=1)



def dominant_bone(rig: Rig) -> np.ndarray:
    """Index of the joint with the largest weight for each vertex, ``[V]``."""
    w = rig.joint_weights
    k = np.argmax(w, axis=1)
    return rig.joint_indices[np.arange(rig.vertex_count), k]


def closest_point_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on segments ``a[i] b[i]`` to points ``p[i]``; returns ``(points, t)`` with
    ``t`` in [0, 1] the segment parameter. Shapes ``[N, 3]``."""
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0)
    t = np.clip(np.where(dd > 0, t, 0.0), 0.0, 1.0)
    return a + t[:, None] * d, t


def weighted_principal_axis(rig: Rig, joint: int, *, extent: tuple[float, float] = (0.1, 0.9)):
    """The segment of a joint from the geometry it drives: the principal axis of the vertices it
    weights (weighted by its weights), through their weighted centre, from the ``extent[0]``
    to the ``extent[1]`` weighted quantile of their positions along it. ``None`` where the
    joint weights fewer than 3 vertices or they do not spread along a line."""
    w = np.zeros(rig.vertex_count)
    np.add.at(w, np.nonzero(rig.joint_indices == joint)[0], rig.joint_weights[rig.joint_indices == joint])
    sel = w > 0
    if sel.sum() < 3:
        return None
    p, ww = rig.vertices[sel], w[sel]
    c = (ww[:, None] * p).sum(axis=0) / ww.sum()
    cov = (ww[:, None, None] * np.einsum("vi,vj->vij", p - c, p - c)).sum(axis=0) / ww.sum()
    evals, evecs = np.linalg.eigh(cov)
    if evals[-1] <= 1e-12 * max(rig.size(), 1e-12) ** 2:
        return None
    a = evecs[:, -1]
    t = (p - c) @ a
    order = np.argsort(t)
    cw = np.cumsum(ww[order]) / ww.sum()
    lo = t[order][np.searchsorted(cw, extent[0])]
    hi = t[order][min(np.searchsorted(cw, extent[1]), len(t) - 1)]
    if hi - lo <= 0:
        return None
    return c + lo * a, c + hi * a


def bone_segments(rig: Rig, *, leaf_fraction: float = 0.5, min_length_fraction: float = 1e-3) -> Bones:
    """Center line of every bone in rest space (the space of ``rig.vertices``).

    Raises:
        RigError: a joint that dominates vertices has no usable bone length (it coincides with
            its child and has no parent direction to fall back on), naming the joint.
    """
    bind = rig.bind_world_transforms()
    pos = bind[:, :3, 3]
    parents = rig.skeleton.parents
    j = rig.joint_count
    names = rig.skeleton.joint_names
    start = pos.copy()
    end = pos.copy()
    scale = max(rig.size(), 1e-12)
    owner = dominant_bone(rig)
    for k in range(j):  # joints are few
        kids = np.nonzero(parents == k)[0]
        if kids.size:
            end[k] = pos[kids].mean(axis=0)
    length = np.linalg.norm(end - start, axis=1)
    for k in range(j):
        if length[k] > min_length_fraction * scale:
            continue
        # leaf (or degenerate) joint: extend along the parent direction
        p = parents[k]
        direction = None
        if p >= 0:
            d = pos[k] - pos[p]
            n = np.linalg.norm(d)
            if n > min_length_fraction * scale:
                direction, parent_len = d / n, n
        if direction is None:
            axis = weighted_principal_axis(rig, k)
            if axis is None:
                if np.any(owner == k):
                    raise RigError(
                        f"{rig.source or rig.name}: joint {names[k]!r} dominates vertices but neither the hierarchy "
                        "nor its vertices give it a bone direction (they lie at one point); move the joint or "
                        "re-weight those vertices"
                    )
                end[k] = start[k]
                continue
            start[k], end[k] = axis
            continue
        # stay inside the flesh: half way to the farthest vertex the joint dominates, so that
        # no vertex lies on its own center line (it would get a zero-height projection segment)
        mine = rig.vertices[owner == k]
        reach = float(np.max((mine - start[k]) @ direction)) if mine.size else 0.0
        length_k = leaf_fraction * parent_len
        if reach > 0.0:
            length_k = min(length_k, 0.5 * reach)
        end[k] = start[k] + direction * length_k
    return Bones(start=start, end=end, joint_names=list(names))

"""Layered popping: the activation drives the rest shape of the multi-layer model's muscle,
fat and skin layers, so the physical skin makes the pop (collisions and volume included)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..preprocess.layers import LAYER_NAMES
from ..preprocess.refine import extend_midpoints
from ..rig import RigError
from .examples import PoppingExamples
from .pose_space import PoseSpaceDeformer


# ----------------------------------------------------------------------------------------------
# Layered mode: the activation drives the muscle layer of the multi-layer model
# ----------------------------------------------------------------------------------------------
def muscle_rest_offset_deltas(builder, examples: PoppingExamples, skin_matrices: np.ndarray, *,
                              layers: Sequence[str] = ("skin", "fat", "muscle"), device=None) -> np.ndarray:
    """How every region rest offset of the multi-layer model changes when a group clenches.

    The clenched-minus-normal rest-frame displacement of group g at the pose (the examples'
    disparities interpolated with the pose space weights) moves the rest positions of the
    particles of ``layers``; each region's rest centre follows (mass weighted), so the change of
    the rest offset of entry e (member j of region r) is ``dx0_j - dc0_r``.

    By default the swelling muscle carries the tissue above it (muscle, fat and skin rest shapes
    move together; the bone layer stays): shape matching only sees shapes relative to each
    region's centre, so moving the muscle layer alone just thins the fat above it and the skin
    does not move at all. The pinned bone
    layer's regions then push the whole column out; the volume constraints keep each
    sub-volume's volume by letting the rest of it give.

    Args:
        builder: A built :class:`~warpskin.model.SkinModelBuilder` of the examples' rig.
        examples: The popping examples.
        skin_matrices: The pose, ``[J, 4, 4]`` (the popping scenes hold the bones still).
        layers: Layers whose rest shape the muscles move.

    Returns:
        ``[G, M, 3]`` [m], M the number of region entries.
    """
    builder.build()
    bad = [n for n in layers if n not in LAYER_NAMES[:3]]
    if bad:
        raise RigError(f"layered popping: layers {bad} cannot be moved by the muscles; choose from {list(LAYER_NAMES[:3])}")
    rig = builder.rig
    loaded = rig.unrefined()  # the examples are of the skin as loaded; a refined one adds midpoints
    if examples.vertex_count != loaded.vertex_count:
        raise RigError(f"layered popping: the examples have {examples.vertex_count} vertices, the rig "
                       f"{loaded.vertex_count}")
    deformer = PoseSpaceDeformer(loaded, examples, device="cpu")
    _, group_w = deformer.weights(skin_matrices)
    disp = []
    for g in range(examples.group_count):
        d = np.einsum("e,evc->vc", group_w[g], examples.clenched_disparities[g])  # [V, 3]
        disp.append(extend_midpoints(d, rig.vertex_parents) if rig.vertex_parents is not None else d)
    return rest_offset_deltas(builder, np.stack(disp), layers=layers)


def rest_offset_deltas(builder, displacements: np.ndarray, *, layers: Sequence[str] = ("skin", "fat", "muscle")) -> np.ndarray:
    """How every region rest offset of the multi-layer model changes when group ``g`` moves the
    rest positions of the particles of ``layers`` by ``displacements[g]`` (``[G, V, 3]`` [m], V
    the model's skin vertices, refined ones included): each region's rest centre follows (mass
    weighted), so entry e (member j of region r) changes by ``dx0_j - dc0_r``. Returns
    ``[G, M, 3]`` [m] for :meth:`~warpskin.model.SkinModelBuilder.set_rest_drive`."""
    builder.build()
    bad = [n for n in layers if n not in LAYER_NAMES[:3]]
    if bad:
        raise RigError(f"layered popping: layers {bad} cannot be moved by the muscles; choose from {list(LAYER_NAMES[:3])}")
    v = builder.rig.vertex_count
    disp = np.asarray(displacements, dtype=np.float64)
    if disp.ndim != 3 or disp.shape[1:] != (v, 3):
        raise RigError(f"layered popping: displacements must be [G, {v}, 3], got {disp.shape}")
    reg = builder.regions
    region_of = reg.region_of_entry()
    m = builder.masses[reg.region_members]
    out = np.zeros((disp.shape[0], reg.region_members.size, 3))
    for g in range(disp.shape[0]):
        dx0 = np.zeros((4 * v, 3))
        for name in layers:
            k = LAYER_NAMES.index(name)
            dx0[k * v:(k + 1) * v] = disp[g]
        dmember = dx0[reg.region_members]
        dcom = np.stack([np.bincount(region_of, m * dmember[:, c], minlength=reg.region_count) for c in range(3)], axis=1)
        dcom /= reg.region_mass[:, None]
        out[g] = dmember - dcom[region_of]
    return out

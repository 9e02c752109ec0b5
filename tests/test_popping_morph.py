"""Popping examples read from glTF morph targets of the rig's own mesh."""

from __future__ import annotations

import numpy as np
import pytest
from pygltflib import Attributes

from test_gltf_import import FLOAT, make_box  # the glTF test builder (tests/ is on sys.path)
from warpskin.io import load_rig
from warpskin.io.gltf import read_gltf_morph_targets
from warpskin.popping import PoseSpaceDeformer, examples_from_morph_targets
from warpskin.rig import RigError


def _bulge(pos: np.ndarray) -> np.ndarray:
    """A +x bulge of the top half (the 'clenched' shape), per file vertex."""
    d = np.zeros_like(pos)
    d[:, 0] = np.where(pos[:, 2] > 1.0, 0.1 * np.sign(pos[:, 0]), 0.0)
    return d


def _box_with_target(tmp_path):
    def add_target(b):
        prim = b.g.meshes[0].primitives[0]
        acc = b.g.accessors[prim.attributes.POSITION]
        pos = np.frombuffer(bytes(b.blob[b.g.bufferViews[acc.bufferView].byteOffset:][: acc.count * 12]),
                            dtype=np.float32).reshape(-1, 3).astype(np.float64)
        prim.targets = [Attributes(POSITION=b.accessor(_bulge(pos), FLOAT))]
        b.g.meshes[0].extras = {"targetNames": ["flex"]}

    return make_box(tmp_path, mutate=add_target)


def test_targets_read_and_turned_into_examples(tmp_path, device):
    path = _box_with_target(tmp_path)
    rig = load_rig(path)
    targets = read_gltf_morph_targets(path)
    assert list(targets) == ["flex"] and targets["flex"].shape == (rig.file_vertex_count, 3)
    pose = rig.skinning_matrices(None, 0.0)
    ex = examples_from_morph_targets(rig, targets, normal=[(None, pose)], clenched={"biceps": [("flex", pose)]})
    # the rest-frame disparity is the target's offset, welded (independent: the file positions)
    file_pos = rig.vertices[rig.weld_map]
    expected = _bulge(file_pos).astype(np.float32).astype(np.float64)  # the file stores float32
    got = ex.clenched_disparities[0][0][rig.weld_map]
    assert np.abs(got - expected).max() < 1e-9
    # at the example's own pose (here the bind pose: identity skinning), pose space deformation
    # reproduces the clenched shape: rest + offsets
    assert np.allclose(pose, np.eye(4), atol=1e-12)
    deformer = PoseSpaceDeformer(rig, ex, device=device)
    deformer.set_pose(pose)
    clenched = deformer.clenched_points.numpy()
    assert np.abs(clenched[rig.weld_map] - (file_pos + expected)).max() < 1e-5


def test_unknown_target_is_named(tmp_path):
    path = _box_with_target(tmp_path)
    rig = load_rig(path)
    with pytest.raises(RigError, match=r"no morph target 'clench'; targets: \['flex'\]"):
        examples_from_morph_targets(rig, read_gltf_morph_targets(path), normal=[(None, 0.0)],
                                    clenched={"biceps": [("clench", 0.0)]})

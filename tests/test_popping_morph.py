"""Popping examples read from glTF morph targets of the rig's own mesh."""

from __future__ import annotations

import numpy as np
import pytest
from pygltflib import Attributes

from oracles import prim
from pxr import Usd, UsdGeom
from test_gltf_import import FLOAT, make_box  # the glTF test builder (tests/ is on sys.path)
from warpskin.cli import main
from warpskin.io import load_rig
from warpskin.io.gltf import read_gltf_morph_targets
from warpskin.popping import PoseSpaceDeformer, examples_from_morph_targets
from warpskin.rig import RigError


def _bulge(pos: np.ndarray) -> np.ndarray:
    """A +x bulge of the top half (the 'clenched' shape), per file vertex."""
    d = np.zeros_like(pos)
    d[:, 0] = np.where(pos[:, 2] > 1.0, 0.1 * np.sign(pos[:, 0]), 0.0)
    return d


def _box_with_target(tmp_path, name: str = "flex"):
    def add_target(b):
        prim = b.g.meshes[0].primitives[0]
        acc = b.g.accessors[prim.attributes.POSITION]
        pos = np.frombuffer(bytes(b.blob[b.g.bufferViews[acc.bufferView].byteOffset:][: acc.count * 12]),
                            dtype=np.float32).reshape(-1, 3).astype(np.float64)
        prim.targets = [Attributes(POSITION=b.accessor(_bulge(pos), FLOAT))]
        b.g.meshes[0].extras = {"targetNames": [name]}

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


def test_a_rig_files_clenched_target_pops_by_the_papers_rules(tmp_path, capsys):
    # `warpskin pop box.glb --bpm`: the file's "biceps_clenched" morph target is the biceps'
    # clenched example (goal mode, no scene); the written skin's offset from the normal mesh
    # follows eqs. 1-4 step by step, here in NumPy: rising activation -> clench
    #   u <- (1 - alpha) u + alpha (o* - o) / h,  o <- o + h u
    # falling -> relax: o <- o + beta h (o* - o), u <- 0, snapping to o* within the threshold
    path = _box_with_target(tmp_path, "biceps_clenched")
    out = tmp_path / "pop.usdc"
    h = 1.0 / 120.0
    assert main(["pop", str(path), "-o", str(out), "--bpm", "120", "--offset", "0.1037", "--hold", "0.2513",
                 "--frames", "0:30", "--dt", str(h), "--quiet"]) == 0
    assert "groups biceps" in capsys.readouterr().out
    rig = load_rig(path)
    stage = Usd.Stage.Open(str(out))
    popping, normal = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("popping", "normal"))
    file_pos = rig.vertices[rig.weld_map]
    d = _bulge(file_pos).astype(np.float32).astype(np.float64)  # the clenched offsets (bind pose: no skinning)
    moved = np.linalg.norm(d, axis=1) > 0
    alpha = np.where(moved, 0.1, 1.0)[:, None]  # eq. 3: every moved vertex at the largest disparity
    beta, threshold = 30.0, 1e-4

    def activation(t):
        return 1.0 if any(b <= t < b + 0.2513 for b in (0.1037, 0.6037)) else 0.0

    o, u, prev, clench = np.zeros_like(d), np.zeros_like(d), 0.0, False
    fps = 30.0
    for frame in range(31):
        for s in range(4):  # the frame's steps end at its time
            t = frame / fps - 1.0 / fps + (s + 1) * h
            a = activation(t)
            clench = True if a > prev else (False if a < prev else clench)
            prev = a
            goal = a * d
            if clench:
                u = (1 - alpha) * u + alpha * (goal - o) / h
                o = o + h * u
            else:
                o = o + beta * h * (goal - o)
                u[:] = 0.0
                snap = np.linalg.norm(goal - o, axis=1) < threshold
                o[snap] = goal[snap]
        got = np.asarray(popping.Get(frame), dtype=np.float64) - np.asarray(normal.Get(frame), dtype=np.float64)
        assert np.abs(got - o).max() < 2e-5 * np.abs(d).max(), frame  # float32 kernel and file
        if frame == 17:  # 0.567 s: relaxed from the first pop and snapped, before the second beat
            assert np.abs(o).max() == 0.0 and np.abs(got).max() == 0.0
    # it vibrated: past the clenched goal during the first pop
    peak = max(float(np.max((np.asarray(popping.Get(f)) - np.asarray(normal.Get(f)))[moved, 0]
                            * np.sign(d[moved, 0]))) for f in range(4, 11))
    assert peak > 0.1 * 1.05


def test_clenched_target_names_make_the_groups(tmp_path):
    from warpskin.popping.examples import _group_of

    assert [_group_of(n) for n in ("biceps_clenched", "Flex", "quad-pump", "calf.FLEXED", "pumped")] == \
        ["biceps", "Flex", "quad", "calf", "pumped"]


def test_usd_blend_shapes_are_clenched_examples(tmp_path, capsys):
    # a UsdSkel box whose "biceps_clenched" BlendShape (sparse: the top ring) pushes 0.1 along x
    from pxr import Gf, UsdSkel, Vt
    from test_usdskel_import import build_box
    from warpskin.io.usdskel import read_usd_blend_shapes

    top = [8, 9, 10, 11]

    def add_shape(stage, binding):
        shape = UsdSkel.BlendShape.Define(stage, "/World/Char/Box/biceps_clenched")
        shape.CreateOffsetsAttr(Vt.Vec3fArray([Gf.Vec3f(0.1, 0.0, 0.0)] * len(top)))
        shape.CreatePointIndicesAttr(Vt.IntArray(top))
        binding.CreateBlendShapesAttr(Vt.TokenArray(["biceps_clenched"]))
        binding.CreateBlendShapeTargetsRel().SetTargets([shape.GetPath()])

    path = build_box(tmp_path / "box.usda", with_anim=False, mutate=add_shape)
    shapes = read_usd_blend_shapes(path)
    want = np.zeros((12, 3))
    want[top, 0] = 0.1
    assert list(shapes) == ["biceps_clenched"] and np.abs(shapes["biceps_clenched"] - want).max() < 1e-7
    out = tmp_path / "pop.usdc"
    assert main(["pop", str(path), "-o", str(out), "--bpm", "60", "--offset", "0.0513", "--frames", "0:12",
                 "--quiet"]) == 0
    assert "groups biceps" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(out))
    goal, normal = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("goal", "normal"))
    d = np.linalg.norm(np.asarray(goal.Get(6)) - np.asarray(normal.Get(6)), axis=1)  # 0.2 s: clenched
    rig = load_rig(path)
    moved = np.isin(np.arange(rig.file_vertex_count), top)  # the USD's own point numbers
    assert np.allclose(d[moved], 0.1, atol=1e-6) and np.all(d[~moved] < 1e-6)

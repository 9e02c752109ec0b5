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


def _eqs_1_to_4(goal, activation, alpha, h, *, frames, fps=30.0, beta=30.0, threshold=1e-4) -> list:
    """Son & Han's skin vibration in NumPy, as ``warpskin pop`` steps it: the offsets from the
    normal mesh at the end of each frame (``[N, 3]`` each; frame f's steps end at f / fps, the
    first frame's included). ``goal(a)``: the goal offsets at activation ``a``;
    ``activation(t)``: the activation at time ``t``; ``alpha``: ``[N, 1]`` stiffness (eq. 3).
    Rising activation -> clench: u <- (1 - alpha) u + alpha (o* - o) / h, o <- o + h u;
    falling -> relax: o <- o + beta h (o* - o), u <- 0, snapping to o* within the threshold."""
    o = u = None
    prev, clench, out = 0.0, False, []
    for frame in range(frames):
        for s in range(int(round(1.0 / (fps * h)))):
            a = activation(frame / fps - 1.0 / fps + (s + 1) * h)
            clench = True if a > prev else (False if a < prev else clench)
            prev = a
            g = goal(a)
            if o is None:
                o, u = np.zeros_like(g), np.zeros_like(g)
            if clench:
                u = (1 - alpha) * u + alpha * (g - o) / h
                o = o + h * u
            else:
                o = o + beta * h * (g - o)
                u = np.zeros_like(u)
                snap = np.linalg.norm(g - o, axis=1) < threshold
                o[snap] = g[snap]
        out.append(o.copy())
    return out


def test_a_rig_files_clenched_target_pops_by_the_papers_rules(tmp_path, capsys):
    # `warpskin pop box.glb --bpm`: the file's "biceps_clenched" morph target is the biceps'
    # clenched example (goal mode, no scene); the written skin's offset from the normal mesh
    # follows eqs. 1-4 step by step, here in NumPy (_eqs_1_to_4)
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

    def activation(t):
        return 1.0 if any(b <= t < b + 0.2513 for b in (0.1037, 0.6037)) else 0.0

    for frame, o in enumerate(_eqs_1_to_4(lambda a: a * d, activation, alpha, h, frames=31)):
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


# --------------------------------------------------------------------------------------------
# UsdSkel inbetweens and the scene's mapping of file shapes to groups and poses, against
# usd-core's own blend shapes and skinning (UsdSkel.BlendShapeQuery, SkinningQuery)
# --------------------------------------------------------------------------------------------
_TOP, _MID = [8, 9, 10, 11], [4, 5, 6, 7]
_FULL = [(0.10, 0.0, 0.0), (0.08, 0.01, 0.0), (0.12, 0.0, 0.02), (0.09, -0.02, 0.0)]
_INBETWEENS = {  # not along the full shape: the goal bends through them
    0.4: [(0.0, 0.05, 0.0), (0.02, 0.04, 0.01), (0.03, 0.0, 0.03), (-0.01, 0.05, 0.0)],
    0.75: [(0.05, 0.05, 0.01), (0.06, 0.0, 0.0), (0.02, 0.03, 0.03), (0.07, 0.01, -0.01)],
    1.3: [(0.5, 0.5, 0.5)] * 4,  # outside [0, 1]: no activation reaches it
    -0.5: [(-0.5, 0.5, 0.5)] * 4,
}


def _shaped_box(tmp_path, shapes: dict, with_anim: bool = False):
    """The UsdSkel test box with sparse blend shapes ``{name: (point indices, offsets,
    {weight: inbetween offsets})}``."""
    from pxr import Gf, UsdSkel, Vt
    from test_usdskel_import import build_box

    def add(stage, binding):
        paths = []
        for name, (idx, offsets, inbetweens) in shapes.items():
            shape = UsdSkel.BlendShape.Define(stage, f"/World/Char/Box/{name}")
            shape.CreateOffsetsAttr(Vt.Vec3fArray([Gf.Vec3f(*o) for o in offsets]))
            shape.CreatePointIndicesAttr(Vt.IntArray(idx))
            for k, (w, offs) in enumerate(inbetweens.items()):
                inb = shape.CreateInbetween(f"in{k}")
                inb.SetWeight(w)
                inb.SetOffsets(Vt.Vec3fArray([Gf.Vec3f(*o) for o in offs]))
            paths.append(shape.GetPath())
        binding.CreateBlendShapesAttr(Vt.TokenArray(list(shapes)))
        binding.CreateBlendShapeTargetsRel().SetTargets(paths)

    return build_box(tmp_path / "box.usda", with_anim=with_anim, mutate=add)


def test_usd_inbetweens_are_read_as_usdskel_defines_them(tmp_path):
    from warpskin.io.usdskel import read_usd_inbetweens

    path = _shaped_box(tmp_path, {"biceps_clenched": (_TOP, _FULL, _INBETWEENS), "plain": (_MID, _FULL, {})})
    got = read_usd_inbetweens(path)
    assert list(got) == ["biceps_clenched"] and [w for w, _ in got["biceps_clenched"]] == pytest.approx([0.4, 0.75])
    for w, offsets in got["biceps_clenched"]:
        want = np.zeros((12, 3))
        want[_TOP] = _INBETWEENS[round(w, 2)]
        assert np.abs(offsets - want).max() < 1e-7  # float32 in the file


def test_usd_inbetweens_shape_the_goal_and_the_skin_follows_the_papers_rules(tmp_path, capsys, device):
    # activations 0.2, 0.55, 0.9 and 1 on four beats: the goal mesh is the box with the blend
    # shape at that weight, as UsdSkel.BlendShapeQuery bends it through the inbetweens, and the
    # skin's offset from the normal mesh follows eqs. 1-4 towards it, in NumPy
    from oracles import usd_skinned_world

    path = _shaped_box(tmp_path, {"biceps_clenched": (_TOP, _FULL, _INBETWEENS)})
    beats = tmp_path / "beats.csv"
    levels = {0.0513: 0.2, 0.2513: 0.55, 0.4513: 0.9, 0.6513: 1.0}
    beats.write_text("time,group,activation\n" + "".join(f"{t},biceps,{a}\n" for t, a in levels.items()))
    out = tmp_path / "pop.usdc"
    h = 1.0 / 120.0
    assert main(["pop", str(path), "-o", str(out), "--beats", str(beats), "--hold", "0.1", "--frames", "0:27",
                 "--dt", str(h), "--device", str(device), "--quiet"]) == 0
    assert "groups biceps" in capsys.readouterr().out
    src, stage = Usd.Stage.Open(str(path)), Usd.Stage.Open(str(out))
    popping, normal, goal = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("popping", "normal", "goal"))
    rest = usd_skinned_world(src, "/World/Char/Box", 0.0)

    def target(a):  # the written-space offset of the shape at weight a, by usd-core
        return usd_skinned_world(src, "/World/Char/Box", 0.0, {"biceps_clenched": a}) - rest

    for frame, a in ((3, 0.2), (9, 0.55), (15, 0.9), (21, 1.0)):  # mid-hold frames
        assert np.abs(np.asarray(goal.Get(frame)) - (rest + target(a))).max() < 1e-6, (frame, a)
    full = np.linalg.norm(target(1.0), axis=1)
    alpha = ((0.1 - 1.0) * full / full.max() + 1.0)[:, None]  # eq. 3 from the clenched shape

    def activation(t):
        return next((a for b, a in levels.items() if b <= t < b + 0.1), 0.0)

    goals = {a: target(a) for a in (0.0, *levels.values())}
    for frame, o in enumerate(_eqs_1_to_4(goals.__getitem__, activation, alpha, h, frames=28)):
        got = np.asarray(popping.Get(frame), dtype=np.float64) - np.asarray(normal.Get(frame), dtype=np.float64)
        assert np.abs(got - o).max() < 2e-5 * full.max(), frame
    # the inbetween bent the path: at 0.2 the skin heads along the 0.4 inbetween (mostly +y
    # in the file), not along the clenched shape (+x)
    assert np.abs(np.asarray(goal.Get(3)) - rest - 0.2 * target(1.0)).max() > 0.01


def test_a_scene_maps_file_shapes_to_groups_and_poses(tmp_path, capsys, device):
    # a corrective "elbow_fix" is the normal example at 0.5 s, "biceps_bent" the clench sculpted
    # there (on top of the corrective) and "biceps_clenched" the clench at the bind pose: at
    # 0.5 s the written normal and goal meshes are usd-core's blend-shaped, skinned box
    from oracles import usd_skinned_world

    fix = [(0.0, 0.0, 0.03), (0.01, 0.0, 0.03), (0.0, -0.01, 0.03), (0.02, 0.0, 0.02)]
    bent = [(0.0, 0.06, 0.0), (0.01, 0.07, 0.0), (0.0, 0.05, 0.02), (-0.01, 0.06, 0.0)]
    path = _shaped_box(tmp_path, {"elbow_fix": (_MID, fix, {}), "biceps_clenched": (_TOP, _FULL, {}),
                                  "biceps_bent": (_TOP, bent, {})}, with_anim=True)
    scene = tmp_path / "pop.toml"
    scene.write_text(f'''[scene]
name = "box_pop"
[rig]
file = "{path.name}"
[popping.examples]
normal = [{{shape = "elbow_fix", pose = 0.5}}]
[popping.examples.clenched]
biceps = [{{shape = "biceps_clenched"}}, {{shape = "biceps_bent", pose = 0.5}}]
[popping.activation.biceps]
beats = [0.4513]
hold = 0.2
''')
    out = tmp_path / "pop.usdc"
    assert main(["pop", str(scene), "-o", str(out), "--frames", "0:20", "--device", str(device), "--quiet"]) == 0
    capsys.readouterr()
    src, stage = Usd.Stage.Open(str(path)), Usd.Stage.Open(str(out))
    normal, goal = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("normal", "goal"))
    box = "/World/Char/Box"
    # 0.5 s (time code 15): the examples' own pose
    assert np.abs(np.asarray(normal.Get(15)) - usd_skinned_world(src, box, 15.0, {"elbow_fix": 1.0})).max() < 1e-5
    want = usd_skinned_world(src, box, 15.0, {"elbow_fix": 1.0, "biceps_bent": 1.0})
    assert np.abs(np.asarray(goal.Get(15)) - want).max() < 1e-5
    # the bind pose (time 0): no corrective, and the bind clench
    assert np.abs(np.asarray(normal.Get(0)) - usd_skinned_world(src, box, 0.0)).max() < 1e-5
    # the bent clench differs from the bind one skinned there: the mapping, not a default, made it
    other = usd_skinned_world(src, box, 15.0, {"elbow_fix": 1.0, "biceps_clenched": 1.0})
    assert np.abs(want - other).max() > 0.05


@pytest.mark.parametrize("table, message", [
    ('normal = [{shape = "nope", pose = 0.5}]\n[popping.examples.clenched]\nbiceps = [{shape = "biceps_clenched"}]',
     r"\[popping.examples\] normal\[0\]: no blend shape 'nope' in the rig file; its shapes: \['biceps_clenched'\]"),
    ('[popping.examples.clenched]\nbiceps = [{shape = "biceps_clenched", pose = 9.5}]',
     r"clenched.biceps\[0\]: pose 9.5 s lies outside the clip's 0-0.6667 s"),
    ('[popping.examples.clenched]\nbiceps = [{pose = 0.5}]', r"clenched.biceps\[0\]: a clenched example needs a shape"),
    ('[popping.examples.clenched]\nbiceps = [{shape = "biceps_clenched", pose = "rest"}]',
     r"pose must be a clip time \[s\] or \"bind\", got 'rest'"),
    ('clenched = 3', r"clenched must be a table of muscle groups"),
    ('[popping.examples.clenched]\nbiceps = [{shape = "biceps_clenched", weight = 1}]', r"unknown key\(s\) \['weight'\]"),
])
def test_bad_example_tables_name_the_key(tmp_path, capsys, table, message):
    import re

    path = _shaped_box(tmp_path, {"biceps_clenched": (_TOP, _FULL, {})}, with_anim=True)
    scene = tmp_path / "pop.toml"
    scene.write_text(f'[scene]\nname = "box_pop"\n[rig]\nfile = "{path.name}"\n[popping.examples]\n{table}\n'
                     '[popping.activation.biceps]\nbeats = [0.2]\nhold = 0.1\n')
    assert main(["pop", str(scene), "-o", str(tmp_path / "pop.usdc"), "--quiet"]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("warpskin: error:")]
    assert len(errors) == 1 and re.search(message, errors[0]) and str(scene) in errors[0], err
    assert not (tmp_path / "pop.usdc").exists()


def test_an_example_table_needs_a_rig_file(tmp_path, capsys):
    scene = tmp_path / "arm_pop.toml"
    scene.write_text('[scene]\nname = "arm_pop"\n[rig]\ngenerator = "popping_arm"\n'
                     '[popping.examples.clenched]\nbiceps = [{shape = "biceps_clenched"}]\n'
                     '[popping.activation.biceps]\nbeats = [0.2]\nhold = 0.1\n')
    assert main(["pop", str(scene), "-o", str(tmp_path / "pop.usdc"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "[popping.examples] maps blend shapes of a glTF or USD rig file; this scene's rig is generated" in err

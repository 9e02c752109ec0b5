"""Layered popping on any closed rig: muscle groups found from the skeleton, their fusiform
swelling, and ``warpskin pop RIG --bpm`` popping them on the beat in the written USD."""

from __future__ import annotations

import dataclasses

import json

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

from oracles import prim
from warpskin.cli import main
from warpskin.errors import SceneError
from warpskin.model import SkinModelBuilder
from warpskin.popping.muscles import DEFAULT_SWELL, muscles_from_skeleton
from warpskin.popping.surface import DEFAULT_SURFACE_SWELL
from warpskin.scene import Scene, load_scene


@pytest.fixture(scope="module")
def arm_builder():
    scene = load_scene("arm")
    return SkinModelBuilder(scene.rig(), scene.model_params()).build()


def test_the_arm_has_an_upper_arm_and_a_forearm_muscle(arm_builder):
    muscles, fields = muscles_from_skeleton(arm_builder)
    layers, rig, sub = arm_builder.layers, arm_builder.rig, arm_builder.subvolumes
    names = layers.bones.joint_names
    assert [m.name for m in muscles] == ["shoulder", "elbow"]  # the two long bones; not the hand's end
    assert fields.shape == (2, rig.vertex_count, 3)
    skin, foot = layers.positions[0], layers.foot
    depth = np.linalg.norm(skin - layers.positions[3], axis=1)
    radial = (skin - foot) / np.linalg.norm(skin - foot, axis=1)[:, None]
    # each vertex's sub-volume: the one of most of its triangles
    votes = np.zeros((rig.vertex_count, sub.count))
    for k in range(3):
        np.add.at(votes, (rig.triangles[:, k], sub.triangle_labels()), 1.0)
    owner = votes.argmax(axis=1)
    rest_volumes = sub.volumes(skin, sub.center_rest)
    for m, f in zip(muscles, fields):
        j = names.index(m.joints[0])
        mine = (layers.bone == j) & ~layers.unresolved
        moved = np.linalg.norm(f, axis=1)
        along = np.einsum("ij,ij->i", f, radial)
        np.testing.assert_allclose(moved, np.abs(along), rtol=1e-9, atol=1e-15)  # nothing but radial
        # the belly in closed form, min(swell h, 0.15 length) (-sin^2(pi t) cos(2 pi t)) along the
        # bone, less a thinning: none where the bone, its parent and children carry at most half
        # of the vertex, inwards, and continuous across the cut planes of the sub-volumes (no
        # step between the two sides of a cut where one side thins and the other does not)
        t = layers.bone_t
        belly = np.where(mine, np.minimum(DEFAULT_SWELL * depth, 0.15 * layers.bones.length[j])
                         * -np.sin(np.pi * t) ** 2 * np.cos(2 * np.pi * t), 0.0)
        hood = {j, int(rig.skeleton.parents[j])} | {k for k in range(rig.joint_count) if rig.skeleton.parents[k] == j}
        share = np.where(np.isin(rig.joint_indices, sorted(hood)), rig.joint_weights, 0.0).sum(axis=1)
        thinning = belly - along
        assert np.all(thinning[share <= 0.5] == 0.0)
        # mostly a thinning (a sub-volume that only the dip towards a tendon reaches swells back
        # by its lost volume, a quarter of the thinning at most)
        assert thinning.max() > 0.1 * belly.max() and thinning.min() > -0.25 * thinning.max()
        e = np.concatenate([rig.triangles[:, [0, 1]], rig.triangles[:, [1, 2]], rig.triangles[:, [2, 0]]])
        across = owner[e[:, 0]] != owner[e[:, 1]]
        assert across.any()
        # a ramp over three rings and more, never a step (which would change by the whole thinning)
        assert np.abs(thinning[e[across, 0]] - thinning[e[across, 1]]).max() < thinning.max() / 3.0
        # the tissue keeps its volume: every sub-volume's (the divergence theorem on the closed
        # pieces) within 1e-6, and the whole skin's (trimesh)
        np.testing.assert_allclose(sub.volumes(skin + f, sub.center_rest), rest_volumes, rtol=1e-6)
        whole = trimesh.Trimesh(skin, rig.triangles, process=False).volume
        assert trimesh.Trimesh(skin + f, rig.triangles, process=False).volume == pytest.approx(whole, rel=1e-6)
        # fusiform: out at mid-bone by most of the peak, and most there; in towards the ends
        mid = mine & (t > 0.4) & (t < 0.6)
        assert np.median(along[mid]) > 0.5 * along.max() and along.max() > 0.2 * np.median(depth[mine])
        assert along.min() < 0.0 and -along.min() < along.max()
        assert np.all(belly[(t < 0.05) | (t > 0.95)] < 0.03 * belly.max())  # the belly: none at the joints
        assert m.vertices == int(np.count_nonzero(moved > 0)) and m.peak_m == pytest.approx(moved.max())


def test_the_belly_is_where_a_group_swells_out(arm_builder):
    from warpskin.popping.muscles import belly_of_swelling

    muscles, fields = muscles_from_skeleton(arm_builder)
    layers = arm_builder.layers
    radial = layers.positions[0] - layers.foot
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    out = np.einsum("gvc,vc->gv", fields, radial)
    belly = belly_of_swelling(arm_builder, fields)
    # brute force: out by more than a quarter of its group's largest outward move
    want = np.zeros(len(belly), dtype=bool)
    for g in range(len(muscles)):
        for i in range(len(belly)):
            want[i] |= bool(out[g, i] > 0.25 * out[g].max())
    np.testing.assert_array_equal(belly, want)
    assert belly.any() and not belly[np.all(out <= 0.0, axis=0)].any()  # never where it thins


def test_named_groups_and_their_errors(arm_builder):
    muscles, fields = muscles_from_skeleton(arm_builder, ["forearm=ELB*", "shoulder"], swell=0.5 * DEFAULT_SWELL)
    assert [(m.name, m.joints) for m in muscles] == [("forearm", ["elbow"]), ("shoulder", ["shoulder"])]
    auto = muscles_from_skeleton(arm_builder)[1]
    np.testing.assert_allclose(fields[0], np.where(np.linalg.norm(auto[1], axis=1)[:, None] > 0, fields[0], 0.0))
    assert np.linalg.norm(fields[0], axis=1).max() < np.linalg.norm(auto[1], axis=1).max()  # a smaller swell
    for groups, message in [
        (["quads=*thigh*"], r"'quads=\*thigh\*': no bone that carries skin matches '\*thigh\*' \(bones: "),
        (["biceps"], r"no muscle group 'biceps'; found: shoulder, elbow"),
        (["a=", "b"], r"'a=': give NAME or NAME=JOINT_PATTERN"),
        (["shoulder", "shoulder"], r"each name once"),
    ]:
        with pytest.raises(SceneError, match=message):
            muscles_from_skeleton(arm_builder, groups)
    with pytest.raises(SceneError, match="swell must be in"):
        muscles_from_skeleton(arm_builder, swell=5.0)


def _outward(path, rig, field: np.ndarray) -> np.ndarray:
    """Per frame, how far the written skin lies outside its LBS [m] along LBS's vertex normals,
    on average over the vertices a muscle's swelling moves out most (its belly: over half its
    peak along the rest normals)."""
    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in root.GetChildren() if p.IsA(UsdGeom.Mesh)}
    skin = next(m for n, m in meshes.items() if n != "lbs" and not n.endswith("_lbs"))
    lbs = meshes["lbs"] if "lbs" in meshes else meshes[skin.GetPrim().GetName() + "_lbs"]
    faces = np.asarray(skin.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    rest_normals = trimesh.Trimesh(rig.vertices, rig.triangles, process=False).vertex_normals
    out_ = np.einsum("ij,ij->i", field[: rig.vertex_count], rest_normals[: rig.vertex_count])
    welded = np.nonzero(out_ > 0.5 * out_.max())[0]
    first = np.zeros(rig.vertex_count, dtype=np.int64)
    first[rig.weld_map[::-1]] = np.arange(rig.weld_map.size)[::-1]  # a file vertex of each welded one
    sel = first[welded]
    out = []
    for tc in skin.GetPointsAttr().GetTimeSamples():
        s = np.asarray(skin.GetPointsAttr().Get(tc), dtype=np.float64)
        b = np.asarray(lbs.GetPointsAttr().Get(tc), dtype=np.float64)
        n = trimesh.Trimesh(b, faces, process=False).vertex_normals
        out.append(float(np.einsum("ij,ij->i", (s - b)[sel], n[sel]).mean()))
    return np.array(out)


@pytest.mark.parametrize("pop_on, cage", [("layers", "auto"), ("layers", "always"), ("surface", "auto")])
@pytest.mark.slow
def test_cli_pops_a_rig_without_examples_on_the_beat(tmp_path, capsys, device, arm_builder, pop_on, cage):
    # the shipped arm has no popping examples: layered mode, its two muscles found (on its own
    # skin, or on its cage whose pop the written skin takes on; or on the written skin itself),
    # popping at 0.2037 s (between frames 6 and 7 at 30 fps, off every step) for 0.25 s (to
    # frame 13.6)
    out = tmp_path / "arm_pop.usdc"
    assert main(["pop", "arm", "-o", str(out), "--bpm", "120", "--offset", "0.2037", "--frames", "0:16", "--quiet",
                 "--device", device, "--cage", cage, "--no-normal-guide", "--pop-on", pop_on]) == 0
    text = capsys.readouterr().out
    assert "driven by groups shoulder, elbow" in text and "shoulder: bones shoulder" in text
    muscles, fields = muscles_from_skeleton(arm_builder)
    depth = np.linalg.norm(arm_builder.layers.positions[0] - arm_builder.layers.positions[3], axis=1)
    for m, f in zip(muscles, fields):
        o = _outward(out, arm_builder.rig, f)
        moved = np.linalg.norm(f, axis=1)
        h = depth[moved > 0.5 * moved.max()].mean()
        assert np.abs(o[:7]).max() < 0.02 * h, m.name  # nothing before the beat
        assert o[8:10].mean() > 0.1 * h, m.name  # out by a tenth of the tissue depth and more, clenched
        assert np.abs(o[15:]).max() < 0.5 * o[8:10].mean(), m.name  # and back after the release


def test_a_rig_without_a_timeline_is_told_what_to_pass(tmp_path, capsys):
    out = tmp_path / "x.usdc"
    assert main(["pop", "arm", "-o", str(out), "--frames", "0:3", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "popping without a timeline: pass --bpm N or --beats FILE (muscle groups found: shoulder, elbow)" in err
    assert not out.exists()
    assert main(["pop", "arm", "-o", str(out), "--frames", "0:3", "--quiet", "--bpm", "60",
                 "--groups", "x=*nothing*"]) == 2
    assert "no bone that carries skin matches '*nothing*'" in capsys.readouterr().err
    assert main(["pop", "popping_arm", "-o", str(out), "--frames", "0:3", "--quiet", "--bpm", "60",
                 "--groups", "x=*elbow*"]) == 2
    assert "NAME=JOINT_PATTERN groups need --mode layered" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_cesium_man_pops_on_the_beat(tmp_path, capsys, assets):
    # a real closed rig, no scene: its long bones found (arms, legs, chest), popping at 0.2 s
    # (frame 4.8 at 24 fps) over its walk
    path = assets / "CesiumMan" / "CesiumMan.glb"
    out = tmp_path / "cesium_pop.usdc"
    assert main(["pop", str(path), "-o", str(out), "--bpm", "120", "--offset", "0.2", "--frames", "1:12",
                 "--quiet", "--no-normal-guide"]) == 0
    text = capsys.readouterr().out
    scene = Scene.from_rig_file(path)
    builder = SkinModelBuilder(scene.rig(), scene.model_params()).build()
    muscles, fields = muscles_from_skeleton(builder)
    assert len(muscles) >= 8 and all(f"{m.name}: bones" in text for m in muscles)  # arms, forearms, thighs, calves
    for m, f in zip(muscles, fields):
        o = _outward(out, builder.rig, f)  # frames 1..12: the beat falls between the 4th and 5th
        assert o[4:9].mean() - o[:4].mean() > 2e-3, m.name  # millimetres out while clenched


def test_pop_help_states_the_default_swell(capsys):
    import re

    assert main(["pop", "--help"]) == 0

    text = " ".join(capsys.readouterr().out.split())
    stated = re.search(r"--swell SWELL muscles found from the skeleton: [^(]*\(default ([0-9.]+); ([0-9.]+) with "
                       r"--pop-on layers\)", text)
    assert stated and float(stated.group(1)) == DEFAULT_SURFACE_SWELL and float(stated.group(2)) == DEFAULT_SWELL


def test_info_lists_the_muscles_pop_would_use(capsys):
    assert main(["info", "arm", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [m["name"] for m in out["muscles"]] == ["shoulder", "elbow"]
    assert all(m["vertices"] > 12 and m["peak_swell_mm"] > 0 for m in out["muscles"])
    assert main(["info", "popping_arm", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["muscles"] == "the scene's popping examples"
    assert main(["info", "arm"]) == 0
    assert "pop would use (2 muscle groups from the skeleton" in capsys.readouterr().out


def test_python_pop_takes_a_rig_or_a_scene(tmp_path, device):
    from warpskin.popping import BeatSpec
    from warpskin.run import pop

    run = pop("arm", tmp_path / "p.usdc", beats=BeatSpec(bpm=120.0, offset=0.2037, groups=["elbow"]), frames=(0, 8),
              device=device, progress=False, normal_guide=False)
    assert run.summary["mode"] == "layered" and run.summary["groups"] == ["shoulder", "elbow"] and run.frames == 9


@pytest.mark.slow
def test_pop_report_plots_each_groups_bulge_beside_its_activation(tmp_path, capsys):
    from warpskin.popping.report import belly_of_bones

    out, report = tmp_path / "arm.usdc", tmp_path / "report"
    assert main(["pop", "arm", "-o", str(out), "--bpm", "120", "--offset", "0.2037", "--frames", "0:16", "--quiet",
                 "--report", str(report), "--pop-on", "layers", "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    depth = {m["name"]: m["depth_mm"] for m in printed["muscles"]}
    # the normal-only guide is the same simulation without the pop: what simulate writes with the
    # pop's solver settings (the volume constraints along the normals), exactly
    from warpskin.run import simulate

    plain = tmp_path / "plain.usdc"
    scene = load_scene("arm")
    params = dataclasses.replace(scene.solver_params(), volume_along_normals=True)
    simulate(scene, plain, frames=(0, 16), progress=False, solver_params=params)
    capsys.readouterr()
    stages = [Usd.Stage.Open(str(out)), Usd.Stage.Open(str(plain))]  # held while their prims are read
    guide = UsdGeom.Mesh(prim(stages[0], "normal")).GetPointsAttr()
    alone = UsdGeom.Mesh(prim(stages[1], "skin")).GetPointsAttr()
    assert guide.GetTimeSamples() == alone.GetTimeSamples() == [float(f) for f in range(17)]
    for f in (0, 9, 16):
        assert np.array_equal(np.asarray(guide.Get(f)), np.asarray(alone.Get(f)))
    data = json.loads((report / "popping.json").read_text())
    assert (report / "report.json").exists()  # the simulation's own report beside it

    pytest.importorskip("matplotlib")
    assert (report / "popping.png").stat().st_size > 10_000
    rig = load_scene("arm").rig()
    stage = Usd.Stage.Open(str(out))
    skin, lbs = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("skin", "normal"))  # against the guide
    faces = np.asarray(UsdGeom.Mesh(prim(stage, "skin")).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    for group, series in data["groups"].items():
        # the activation: a pop from 0.2037 s (after frame 6 at 30 fps) held 0.25 s (to frame 13.6)
        assert series["activation"] == [1.0 if 7 <= f <= 13 else 0.0 for f in range(17)], group
        # the bulge: the skin outside the normal-only guide along its normals (trimesh's), over
        # the group's belly
        belly = belly_of_bones(rig, [group])[rig.weld_map]
        assert series["belly_vertices"] == int(belly.sum()) > 20
        for f in (3, 9, 15):
            s, b = np.asarray(skin.Get(f), dtype=np.float64), np.asarray(lbs.Get(f), dtype=np.float64)
            n = trimesh.Trimesh(b, faces, process=False).vertex_normals
            want = 1e3 * np.einsum("ij,ij->i", (s - b)[belly], n[belly]).mean()
            assert series["bulge_mm"][f] == pytest.approx(want, rel=0.03, abs=0.05), (group, f)
        # millimetres out while clenched; before the beat: the same run
        assert max(series["bulge_mm"][7:14]) > 2.0 and series["bulge_mm"][3] == 0.0
        # the pop on the beat at 0.2037 s (the time code 6.111 at 30 fps), read from the series
        (beat,) = series["beats"]
        window = series["bulge_mm"][7:]
        k = int(np.argmax(window))
        assert beat["beat_frame"] == pytest.approx(0.2037 * 30.0)
        assert (beat["peak_mm"], beat["peak_frame"]) == (window[k], 7.0 + k)
        assert beat["rise_frame"] == 7.0 + next(i for i, b in enumerate(window) if b >= 0.9 * window[k])
        assert beat["share_of_depth"] == pytest.approx(beat["peak_mm"] / depth[group])
        assert printed["beats"][group] == series["beats"]
    # the farthest out and in over the run (trimesh's normals, every frame), and their map
    far = np.zeros((17, np.asarray(skin.Get(0)).shape[0]))
    for f in range(17):
        s, b = np.asarray(skin.Get(f), dtype=np.float64), np.asarray(lbs.Get(f), dtype=np.float64)
        far[f] = np.einsum("ij,ij->i", s - b, trimesh.Trimesh(b, faces, process=False).vertex_normals)
    assert data["largest_out_mm"] == pytest.approx(1e3 * far.max(), rel=0.03)
    assert data["largest_in_mm"] == pytest.approx(-1e3 * far.min(), rel=0.03)
    assert data["largest_out_mm"] > 2.0 and data["largest_in_mm"] > 0.5  # the belly, and the thinning around it
    assert (report / "popping_map.png").stat().st_size > 10_000

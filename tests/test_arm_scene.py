"""The procedural arm and the scene files."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from warpskin.rig import RigError
from warpskin.scene import SceneError, list_scenes, load_scene
from warpskin.scenes.arm import ARM_DEFAULTS, flex_angle, make_arm


def test_arm_is_a_closed_manifold_outward_tube(arm):
    assert arm.vertex_count == 2918  # the paper's arm has 2916
    m = trimesh.Trimesh(arm.vertices, arm.triangles, process=False)
    assert m.is_watertight and m.is_winding_consistent
    assert m.volume > 0  # counter-clockwise seen from outside
    assert len(m.split(only_watertight=False)) == 1
    arm.require_closed()
    # the volume of a tube of elliptic sections, integrated from the radius profile, bounds it
    assert 0.002 < m.volume < 0.005


def test_arm_weights_partition_of_unity_and_smooth(arm):
    w = arm.dense_weights()
    assert np.allclose(w.sum(1), 1.0) and (w >= 0).all()
    x = arm.vertices[:, 0]
    b = ARM_DEFAULTS["elbow_blend"]
    assert np.allclose(w[x < 0.30 - b, 0], 1.0)
    assert np.allclose(w[(x > 0.30 + b) & (x < 0.5), 1], 1.0)
    mid = np.abs(x - 0.30) < 1e-3
    assert np.allclose(w[mid, 0], 0.5, atol=0.05)
    # smooth: the blend spans several rings, and the weight changes little from ring to ring
    elbow = (x > 0.30 - 2 * b) & (x < 0.30 + 2 * b)
    rings = np.unique(np.round(x[elbow], 6))
    w_ring = np.array([w[elbow][np.isclose(x[elbow], r, atol=1e-6), 1].mean() for r in rings])
    assert ((w_ring > 0.01) & (w_ring < 0.99)).sum() >= 5
    assert np.abs(np.diff(w_ring)).max() < 0.25


def test_arm_clip_flexes_to_150_and_back(arm):
    clip = arm.clip("flex")
    assert clip.duration == pytest.approx(5.0)
    for t, expected in [(0.0, 0.0), (1.5, 150.0), (2.0, 150.0), (4.0, 0.0), (0.75, 75.0)]:
        g = arm.joint_world_transforms(clip, t)
        upper = g[1, :3, 3] - g[0, :3, 3]
        fore = g[2, :3, 3] - g[1, :3, 3]
        cosang = upper @ fore / np.linalg.norm(upper) / np.linalg.norm(fore)
        angle = math.degrees(math.acos(np.clip(cosang, -1, 1)))
        assert angle == pytest.approx(expected, abs=0.05)
        assert math.degrees(flex_angle(t)) == pytest.approx(expected, abs=1e-9)
    # flexes toward +y (the biceps side) and the forearm presses into the upper arm
    g = arm.joint_world_transforms(clip, 1.5)
    assert g[2, 1, 3] > 0.1


def test_arm_rejects_bad_parameters():
    with pytest.raises(RigError, match="unknown parameters.*'lenght'"):
        make_arm(lenght=3)
    with pytest.raises(RigError, match="flex_degrees must be in"):
        make_arm(flex_degrees=200)
    with pytest.raises(RigError, match="wrist_radius must be a positive"):
        make_arm(wrist_radius=-0.01)
    with pytest.raises(RigError, match="rings must be an integer"):
        make_arm(rings=2.5)


def test_shipped_scenes_listed():
    names = {s["name"] for s in list_scenes()}
    assert {"arm", "cesium_man"} <= names


def test_arm_scene_frames():
    scene = load_scene("arm")
    assert scene.fps == 30
    assert scene.frame_range() == (0, 150)
    assert scene.frame_time(45) == pytest.approx(1.5)


def _write(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "text, message",
    [
        ("[rig]\ngenerator='arm'\n[animaton]\nfps=3\n", r"unknown section \[animaton\]"),
        ("[rig]\ngenerator='arm'\n[animation]\nfsp=3\n", r"unknown key\(s\) \['fsp'\] in \[animation\]"),
        ("[rig]\ngenerator='arm'\n[animation]\nfps=-3\n", "fps must be a positive number"),
        ("[rig]\ngenerator='arm'\n[animation]\nframes=[5, 2]\n", "frames must be"),
        ("[rig]\ngenerator='arm'\n[animation]\npreroll=-0.5\n", r"\[animation\] preroll must be a number of seconds >= 0"),
        ("[animation]\nfps=30\n", r"missing \[rig\]"),
        ("[rig\n", "not valid TOML"),
    ],
)
def test_scene_errors_name_the_key(tmp_path, text, message):
    with pytest.raises(SceneError, match=message):
        load_scene(_write(tmp_path, text))


def test_scene_rig_errors(tmp_path):
    with pytest.raises(SceneError, match="unknown generator 'leg'"):
        load_scene(_write(tmp_path, "[rig]\ngenerator='leg'\n")).rig()
    with pytest.raises(SceneError, match="exactly one of"):
        load_scene(_write(tmp_path, "[rig]\ngenerator='arm'\nfile='a.glb'\n")).rig()
    with pytest.raises(SceneError, match="flex_degrees must be in"):
        load_scene(_write(tmp_path, "[rig]\ngenerator='arm'\n[rig.params]\nflex_degrees=500\n")).rig()
    with pytest.raises(RigError, match="no such file"):
        load_scene(_write(tmp_path, "[rig]\nfile='missing.glb'\n")).rig()
    with pytest.raises(SceneError, match="unknown scene 'armm'.*arm"):
        load_scene("armm")


def test_scene_generator_params_apply(tmp_path):
    scene = load_scene(_write(tmp_path, "[rig]\ngenerator='arm'\n[rig.params]\nrings=20\nsegments=16\n[animation]\nfps=10\nframes=[2, 7]\n"))
    assert scene.rig().vertex_count == 20 * 16 + 2
    assert scene.frame_range() == (2, 7)


def test_scene_collision_section(tmp_path):
    base = "[rig]\ngenerator='arm'\n[collision]\n"
    p = load_scene(_write(tmp_path, base + "friction=0.5\nfold_cos=-0.2\npasses=2\n")).collision_params()
    assert (p.friction, p.fold_cos, p.passes, p.enabled) == (0.5, -0.2, 2, True)
    assert load_scene("arm").collision_params().fold_cos == 0.0  # the default: folded past 90 degrees
    with pytest.raises(SceneError, match=r"s.toml.*fold_cos must be in \[-1, 1\]"):
        load_scene(_write(tmp_path, base + "fold_cos=2.0\n")).collision_params()
    with pytest.raises(SceneError, match=r"\[collision\] fold_cos must be a number"):
        load_scene(_write(tmp_path, base + "fold_cos='x'\n")).collision_params()
    with pytest.raises(SceneError, match=r"unknown key\(s\) \['fold'\] in \[collision\]"):
        load_scene(_write(tmp_path, base + "fold=1\n"))

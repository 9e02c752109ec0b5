"""Animation authored in a scene ([animation.keys]) and a hierarchy declared for a flat rig
([rig.parents]), on the arm and on the WebXR hand (the shipped `hand` scene)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from oracles import coarse_arm
from warpskin.errors import RigError, SceneError
from warpskin.rig import Clip
from warpskin.scene import load_scene


def _flat(rig):
    """The rig with every joint a root (the same bind pose), as the WebXR hand's file has it."""
    import dataclasses

    world = rig.bind_world_transforms()
    sk = dataclasses.replace(rig.skeleton, parents=np.full(rig.joint_count, -1), rest_translation=world[:, :3, 3].copy(),
                             rest_rotation=Rotation.from_matrix(world[:, :3, :3]).as_quat(),
                             rest_scale=np.ones((rig.joint_count, 3)), root_transform=None)
    return dataclasses.replace(rig, skeleton=sk, clips={})


def test_declared_parents_keep_the_bind_pose_and_chain_the_joints():
    rig = _flat(coarse_arm())
    re = rig.reparented({"elbow": "shoulder", "wrist": "elbow"})
    assert re.skeleton.parents.tolist() == [-1, 0, 1]
    np.testing.assert_allclose(re.skinning_matrices(Clip("rest"), 0.0), np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)
    # a rotation of the elbow now carries the wrist: its world position turns about the elbow
    keyed = re.with_keys("bend", {"elbow": [[0.0, 0, 0, 0], [1.0, 0, 0, 90.0]]})
    w0, w1 = keyed.joint_world_transforms("bend", 0.0), keyed.joint_world_transforms("bend", 1.0)
    elbow = w0[1, :3, 3]
    r = Rotation.from_quat(re.skeleton.rest_rotation[1]).as_matrix()
    want = elbow + r @ Rotation.from_euler("Z", 90, degrees=True).as_matrix() @ r.T @ (w0[2, :3, 3] - elbow)
    np.testing.assert_allclose(w1[2, :3, 3], want, atol=1e-12)
    with pytest.raises(RigError, match="cycle in the joint hierarchy"):
        rig.reparented({"elbow": "wrist", "wrist": "elbow"})
    with pytest.raises(RigError, match="no joint named 'knee'"):
        rig.reparented({"knee": "shoulder"})
    with pytest.raises(RigError, match="without animation clips"):
        coarse_arm().reparented({"elbow": "shoulder"})


def test_authored_keys_rotate_about_the_joints_own_axes():
    rig = coarse_arm()
    rows = [[0.0, 0, 0, 0], [0.5, 30.0, -20.0, 45.0], [1.0, 0, 0, 90.0]]
    keyed = rig.with_keys("k", {"elbow": rows})
    rest = Rotation.from_quat(rig.skeleton.rest_rotation[1])
    keys = rest * Rotation.from_euler("XYZ", np.array(rows)[:, 1:], degrees=True)
    clip = keyed.clips["k"]
    for t in (0.0, 0.5, 1.0):  # at the keys (scipy's intrinsic XYZ as the reference)
        _, q, _ = clip.sample_local_trs(keyed.skeleton, t)
        assert (Rotation.from_quat(q[1]) * keys[[0.0, 0.5, 1.0].index(t)].inv()).magnitude() < 1e-9
    _, q, _ = clip.sample_local_trs(keyed.skeleton, 0.37)  # between keys: slerp
    assert (Rotation.from_quat(q[1]) * Slerp([0.0, 0.5, 1.0], keys)(0.37).inv()).magnitude() < 1e-9
    _, q, _ = clip.sample_local_trs(keyed.skeleton, 0.3)  # the other joints stay at rest
    np.testing.assert_allclose(q[[0, 2]], rig.skeleton.rest_rotation[[0, 2]])
    step = rig.with_keys("s", {"elbow": rows}, interpolation="STEP").clips["s"]
    _, q, _ = step.sample_local_trs(rig.skeleton, 0.49)
    assert (Rotation.from_quat(q[1]) * keys[0].inv()).magnitude() < 1e-9
    with pytest.raises(RigError, match="must increase"):
        rig.with_keys("bad", {"elbow": [[0.5, 0, 0, 0], [0.2, 0, 0, 0]]})
    with pytest.raises(RigError, match=r"rows \[t, x_deg, y_deg, z_deg\]"):
        rig.with_keys("bad", {"elbow": [[0.5, 0, 0]]})


def test_scene_keys_and_parents_are_checked(tmp_path):
    base = "[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 12\nsegments = 10\n"
    p = tmp_path / "k.toml"
    p.write_text(base + "[animation.keys.elbow]\nrotation = [[0.0, 0, 0, 0], [1.0, 0, 0, 60.0]]\n")
    scene = load_scene(p)
    assert scene.clip == "scene" and scene.frame_range() == (0, 30)
    p.write_text(base + "[animation.keys.knee]\nrotation = [[0.0, 0, 0, 0]]\n")
    with pytest.raises(SceneError, match="no joint named 'knee'"):
        load_scene(p).rig()
    p.write_text(base + "[animation]\ninterpolation = 'STEP'\n")
    with pytest.raises(SceneError, match="interpolation applies to \\[animation.keys\\] only"):
        load_scene(p)
    p.write_text(base + "[animation.keys.elbow]\nangle = [[0.0, 0, 0, 0]]\n")
    with pytest.raises(SceneError, match=r"takes rotation = \[\[t, x_deg"):
        load_scene(p)


def test_the_hand_scene_flexes_the_fingers_with_the_physical_skin(assets, tmp_path, monkeypatch):
    # the shipped hand: the WebXR hand (a flat hierarchy in the file) chained by the scene and
    # flexed by its keys; shortened to the first 0.7 s (the fingers curling) for CI time
    from warpskin.run import simulate

    monkeypatch.setenv("WARPSKIN_ASSETS", str(assets))
    scene = load_scene("hand")
    rig = scene.rig()
    assert (rig.skeleton.parents >= 0).sum() == rig.joint_count - 1  # one root: the wrist
    clip = rig.clip(scene.clip)
    world0 = rig.bind_world_transforms()
    wrist = rig.skeleton.index("wrist")
    tip = rig.skeleton.index("index-finger-tip")
    moved = rig.joint_world_transforms(clip, 0.8)[tip, :3, 3] - world0[tip, :3, 3]
    assert moved @ -world0[wrist, :3, 1] > 0.02  # toward the palm (WebXR: +Y is the back of the hand)
    result = simulate(scene, tmp_path / "hand.usdc", progress=False, frames=(0, 20), with_lbs=True, check_intersections=True)
    s = result.summary
    print({k: s[k] for k in ("max_volume_deviation", "max_volume_deviation_lbs", "max_subvolume_deviation",
                             "max_subvolume_deviation_lbs", "max_intersecting_pairs", "max_intersecting_pairs_lbs")})
    assert len(result.frames) == 21 and len(s["subvolume_names"]) > 10  # the chain gives sub-volumes per segment
    assert s["max_volume_deviation"] <= s["max_volume_deviation_lbs"]
    assert s["max_subvolume_deviation"] <= s["max_subvolume_deviation_lbs"]
    assert s["max_intersecting_pairs"] <= s["max_intersecting_pairs_lbs"]
    assert s["max_offset_from_lbs_m"] <= 0.05 * s["body_diagonal_m"]

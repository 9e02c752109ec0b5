"""Kinematic coupling and joint constraints (Deul & Bender 2013, section 4.4)."""

from __future__ import annotations

import numpy as np
import pytest

from warpskin.preprocess.joint_constraints import JointParams, build_joint_constraints
from warpskin.preprocess.kinematic_coupling import build_kinematic_coupling
from warpskin.preprocess.layers import build_layers
from warpskin.rig import RigError
from warpskin.scene import SceneError, load_scene
from warpskin.skinning import Skinner


@pytest.fixture(scope="module")
def layers(arm):
    return build_layers(arm)


def test_coupling_targets_are_lbs_of_the_bone_layer(device, arm, layers):
    kc = build_kinematic_coupling(arm, layers)
    v = arm.vertex_count
    assert np.array_equal(kc.particles, 3 * v + np.arange(v))
    mats = arm.skinning_matrices("flex", 1.5)
    # independent: the Warp LBS kernel on a rig whose rest mesh is the bone layer
    import dataclasses

    bone_rig = dataclasses.replace(arm, vertices=layers.positions[3])
    ref = Skinner(bone_rig, method="lbs", device=device).skin(mats).numpy()
    assert np.abs(kc.targets(mats) - ref).max() < 1e-5 * arm.size()
    assert np.allclose(kc.targets(np.tile(np.eye(4), (3, 1, 1))), layers.positions[3])  # bind pose: rest


def test_joint_constraints_select_exactly_the_particles_within_the_radius(arm, layers):
    jc = build_joint_constraints(arm, layers, JointParams(radius_factor=1.0, layers=("muscle", "bone")))
    v = arm.vertex_count
    centre = arm.bind_world_transforms()[:, :3, 3]
    assert set(np.unique(jc.joints)) == {1, 2}  # elbow and wrist; the root has no joint constraint
    for j in (1, 2):
        r = jc.joint_radius[j]
        assert r > 0
        for k in (2, 3):
            d = np.linalg.norm(layers.positions[k] - centre[j], axis=1)
            expected = set((k * v + np.nonzero(d < r)[0]).tolist())
            got = set(jc.particles[(jc.joints == j) & (jc.particles // v == k)].tolist())
            assert got == expected
    d = np.linalg.norm(layers.flat()[jc.particles] - centre[jc.joints], axis=1)
    assert np.allclose(jc.rest_distance, d)
    # the elbow radius is the skin's distance to the elbow where feet land on the joint: about
    # the elbow radius of the generator (0.041 m, elliptic section flattened to 0.88)
    assert 0.03 < jc.joint_radius[1] < 0.045


def test_joint_centres_follow_the_joints(arm, layers):
    jc = build_joint_constraints(arm, layers)
    mats = arm.skinning_matrices("flex", 1.5)
    world = arm.joint_world_transforms("flex", 1.5)
    assert np.allclose(jc.centres(mats), world[:, :3, 3], atol=1e-12)


def test_joint_constraint_errors(arm, layers):
    with pytest.raises(RigError, match="unknown layers \\['marrow'\\]"):
        build_joint_constraints(arm, layers, JointParams(layers=("marrow",)))
    with pytest.raises(RigError, match="radius_factor must be positive"):
        build_joint_constraints(arm, layers, JointParams(radius_factor=0))
    with pytest.raises(RigError, match="no joint named 'knee'"):
        build_joint_constraints(arm, layers, JointParams(joints=["knee"]))


def _scene(tmp_path, text):
    p = tmp_path / "s.toml"
    p.write_text("[rig]\ngenerator = 'arm'\n" + text)
    return load_scene(p)


def test_scene_model_sections(tmp_path):
    s = _scene(tmp_path, "[layers]\nfat=0.1\nmuscle=0.3\nbone=0.6\nstiffness=[1,0.5,0.5,1]\nomega=2\n"
                         "[layers.per_bone.elbow]\nprojection=[0.05,0.1,0.2]\n[joints]\nradius_factor=1.5\n"
                         "[subvolumes]\nplanes = { wrist = false }\n")
    p = s.model_params()
    assert (p.layers.fat, p.layers.muscle, p.layers.bone, p.omega) == (0.1, 0.3, 0.6, 2)
    assert p.stiffness == (1.0, 0.5, 0.5, 1.0) and p.layers.per_bone == {"elbow": (0.05, 0.1, 0.2)}
    assert p.joints.radius_factor == 1.5 and p.subvolumes.planes == {"wrist": None}


@pytest.mark.parametrize(
    "text, message",
    [
        ("[layers]\nfat=0.5\nmuscle=0.4\n", "0 < fat < muscle < bone < 1"),
        ("[layers]\nstiffness=[1, 2, 0.5, 0.5]\n", "four numbers in \\[0, 1\\]"),
        ("[layers]\nstiffness=[1, 0.5]\n", "list of 4 numbers"),
        ("[layers]\nfat='thin'\n", "fat must be a number"),
        ("[layers]\ndensity=-3\n", "density must be a positive"),
        ("[layers]\nthickness=3\n", "unknown key\\(s\\) \\['thickness'\\] in \\[layers\\]"),
        ("[subvolumes]\nplanes = { elbow = 'middle' }\n", "planes.elbow must be a number"),
    ],
)
def test_scene_model_errors(tmp_path, text, message):
    with pytest.raises(SceneError, match=message):
        _scene(tmp_path, text).model_params()

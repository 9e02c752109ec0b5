"""LBS and DQS kernels against independent NumPy/SciPy references, on every device."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from oracles import rig_lbs
from warpskin.errors import InputError, SceneError
from warpskin.scenes.arm import make_arm
from warpskin.skinning import Skinner


def _random_affine(rng, count, *, scale=True):
    m = np.tile(np.eye(4), (count, 1, 1))
    rot = Rotation.random(count, random_state=rng).as_matrix()
    s = np.diag(rng.uniform(0.7, 1.3, 3)) if scale else np.eye(3)
    m[:, :3, :3] = rot @ s
    m[:, :3, 3] = rng.normal(scale=0.3, size=(count, 3))
    return m


def _dqs_reference(rig, mats):
    """Independent DQS: SciPy quaternions, dual parts 0.5 * t * q, sign-aligned to the
    heaviest influence, normalised blend, then rotation + translation (rigid joints only)."""
    rots = Rotation.from_matrix(mats[:, :3, :3])
    q = rots.as_quat()  # x, y, z, w

    def qmul(a, b):
        ax, ay, az, aw = a.T
        bx, by, bz, bw = b.T
        return np.stack(
            [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
             aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz], axis=1)

    t = np.concatenate([mats[:, :3, 3], np.zeros((len(mats), 1))], axis=1)
    d = 0.5 * qmul(t, q)
    ji, w = rig.joint_indices, rig.joint_weights
    pivot = q[ji[np.arange(len(ji)), np.argmax(w, axis=1)]]
    b0 = np.zeros((len(ji), 4))
    be = np.zeros((len(ji), 4))
    for k in range(ji.shape[1]):
        sgn = np.sign(np.sum(q[ji[:, k]] * pivot, axis=1))
        sgn[sgn == 0] = 1.0
        b0 += (w[:, k] * sgn)[:, None] * q[ji[:, k]]
        be += (w[:, k] * sgn)[:, None] * d[ji[:, k]]
    n = np.linalg.norm(b0, axis=1, keepdims=True)
    b0, be = b0 / n, be / n
    conj = b0 * np.array([-1, -1, -1, 1])
    trans = 2.0 * qmul(be, conj)[:, :3]
    return Rotation.from_quat(b0).apply(rig.vertices) + trans


def test_lbs_matches_numpy_reference(device, arm):
    rng = np.random.default_rng(1)
    mats = _random_affine(rng, arm.joint_count)
    got = Skinner(arm, method="lbs", device=device).skin(mats).numpy()
    ref = rig_lbs(arm, mats)
    assert np.abs(got - ref).max() < 1e-5 * arm.size()


def test_dqs_matches_independent_reference(device, arm):
    # a shared random rigid motion times per-joint rotations of up to 80 degrees: joints stay
    # within 160 degrees of each other, away from DQS's antipodal sign ambiguity (a pair of
    # joints 180 degrees apart has no unique blend, and float32/float64 weight ties may then
    # pick different pivots)
    rng = np.random.default_rng(2)
    for _ in range(3):
        base = _random_affine(rng, 1, scale=False)[0]
        axes = Rotation.random(arm.joint_count, random_state=rng).as_rotvec()
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        local = np.tile(np.eye(4), (arm.joint_count, 1, 1))
        local[:, :3, :3] = Rotation.from_rotvec(axes * rng.uniform(0, np.radians(80), (arm.joint_count, 1))).as_matrix()
        local[:, :3, 3] = rng.normal(scale=0.05, size=(arm.joint_count, 3))
        mats = base @ local
        got = Skinner(arm, method="dqs", device=device).skin(mats).numpy()
        ref = _dqs_reference(arm, mats)
        assert np.abs(got - ref).max() < 1e-5 * arm.size()


def test_dqs_equals_lbs_for_one_rigid_transform(device, arm):
    rng = np.random.default_rng(3)
    m = _random_affine(rng, 1, scale=False)[0]
    mats = np.stack([m] * arm.joint_count)
    lbs = Skinner(arm, method="lbs", device=device).skin(mats).numpy()
    dqs = Skinner(arm, method="dqs", device=device).skin(mats).numpy()
    rigid = arm.vertices @ m[:3, :3].T + m[:3, 3]
    assert np.abs(lbs - rigid).max() < 1e-5 * arm.size()
    assert np.abs(dqs - lbs).max() < 1e-5 * arm.size()


def test_dqs_applies_uniform_scale_like_lbs(device, arm):
    """Two-phase DQS: a scale shared by all joints is applied exactly as LBS does."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.2, 0.5]).as_matrix() * 1.7
    m[:3, 3] = [0.1, 0.2, -0.3]
    mats = np.stack([m] * arm.joint_count)
    lbs = Skinner(arm, method="lbs", device=device).skin(mats).numpy()
    dqs = Skinner(arm, method="dqs", device=device).skin(mats).numpy()
    assert np.abs(dqs - lbs).max() < 1e-5 * arm.size() * 1.7


def _twisted(rig, degrees):
    local = rig.skeleton.rest_local_matrices()
    twist = np.eye(4)
    twist[:3, :3] = Rotation.from_euler("x", degrees, degrees=True).as_matrix()
    local[1] = local[1] @ twist  # twist the elbow about the bone axis (+x)
    return rig.skeleton.world_from_local(local) @ rig.inverse_bind


def test_candy_wrapper_dqs_keeps_volume_lbs_collapses(device, arm):
    mats = _twisted(arm, 170.0)
    rest_volume = trimesh.Trimesh(arm.vertices, arm.triangles, process=False).volume
    lbs = Skinner(arm, method="lbs", device=device).skin(mats).numpy()
    dqs = Skinner(arm, method="dqs", device=device).skin(mats).numpy()
    v_lbs = trimesh.Trimesh(lbs, arm.triangles, process=False).volume
    v_dqs = trimesh.Trimesh(dqs, arm.triangles, process=False).volume
    loss_lbs = 1.0 - v_lbs / rest_volume
    loss_dqs = 1.0 - v_dqs / rest_volume
    print(f"twist 170 deg: volume loss LBS {loss_lbs:.1%}, DQS {loss_dqs:.1%}")
    assert loss_lbs > 0.05
    assert abs(loss_dqs) < 0.01
    # the cross-section at the elbow: LBS shrinks toward the axis (candy wrapper), DQS keeps it
    at_elbow = np.abs(arm.vertices[:, 0] - 0.30) < 0.004
    r_rest = np.linalg.norm(arm.vertices[at_elbow, 1:], axis=1).mean()
    r_lbs = np.linalg.norm(lbs[at_elbow, 1:], axis=1).mean()
    r_dqs = np.linalg.norm(dqs[at_elbow, 1:], axis=1).mean()
    assert r_lbs < 0.2 * r_rest
    assert abs(r_dqs - r_rest) < 0.02 * r_rest


def test_skinner_rejects_bad_input(arm):
    with pytest.raises(SceneError, match="unknown skinning method"):
        Skinner(arm, method="cor")
    s = Skinner(arm, method="lbs", device="cpu")
    with pytest.raises(InputError, match="expected 3 skinning matrices"):
        s.skin(np.tile(np.eye(4), (2, 1, 1)))
    bad = np.tile(np.eye(4), (3, 1, 1))
    bad[1, 0, 3] = np.nan
    with pytest.raises(InputError, match="elbow"):
        s.skin(bad)


def test_skinning_matrices_from_bind_interpolate_the_joints():
    # the arm's clip at 1.5 s bends the elbow 150 degrees about z: half-way from the bind pose
    # the elbow's skinning matrix is a 75 degree rotation about the elbow's bind position
    rig = make_arm(rings=12, segments=8)
    clip = rig.clip("flex")
    np.testing.assert_allclose(rig.skinning_matrices_from_bind(clip, 1.5, 0.0), np.tile(np.eye(4), (3, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(rig.skinning_matrices_from_bind(clip, 1.5, 1.0), rig.skinning_matrices(clip, 1.5), atol=1e-12)
    half = rig.skinning_matrices_from_bind(clip, 1.5, 0.5)
    a = np.radians(75.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(half[1, :3, :3], rot, atol=1e-9)
    elbow = rig.bind_world_transforms()[1, :3, 3]
    np.testing.assert_allclose(half[1, :3, :3] @ elbow + half[1, :3, 3], elbow, atol=1e-12)  # it pivots there
    np.testing.assert_allclose(half[0], np.eye(4), atol=1e-12)  # the shoulder does not move
    with pytest.raises(Exception, match=r"u must be in \[0, 1\]"):
        rig.skinning_matrices_from_bind(clip, 1.5, 1.5)


def test_preroll_keeps_the_root_where_the_first_frame_puts_it(assets):
    # CesiumMan is bound Z-up and walks Y-up: interpolating the root too turned the whole body
    # 90 degrees during the pre-roll (its head swung 137 mm from LBS). The root joints keep the
    # first frame's placement for every u; the joints below them move from bind to pose
    from warpskin.io import load_rig

    rig = load_rig(assets / "CesiumMan" / "CesiumMan.glb")
    clip = rig.clip()
    t = clip.start
    roots = np.nonzero(rig.skeleton.parents < 0)[0]
    target = rig.skinning_matrices(clip, t)
    for u in np.linspace(0.0, 1.0, 7):
        m = rig.skinning_matrices_from_bind(clip, t, float(u))
        np.testing.assert_allclose(m[roots], target[roots], atol=1e-9)
        world = m @ rig.bind_world_transforms()  # joint world transforms
        np.testing.assert_allclose(world[roots], rig.joint_world_transforms(clip, t)[roots], atol=1e-9)
    np.testing.assert_allclose(rig.skinning_matrices_from_bind(clip, t, 1.0), target, atol=1e-9)
    # at u = 0 the body is the bind pose moved rigidly to the root's placement
    start = rig.skinning_matrices_from_bind(clip, t, 0.0)
    r = start[:, :3, :3]
    np.testing.assert_allclose(r, np.broadcast_to(r[roots[0]], r.shape), atol=1e-9)
    # (rotations to the float32 precision of the file's inverse bind matrices)
    np.testing.assert_allclose(np.einsum("jik,jil->jkl", r, r), np.broadcast_to(np.eye(3), r.shape), atol=2e-6)
    # the old interpolation (keep_root=False) starts from the mesh as modelled
    np.testing.assert_allclose(rig.skinning_matrices_from_bind(clip, t, 0.0, keep_root=False),
                               np.tile(np.eye(4), (rig.joint_count, 1, 1)), atol=1e-9)

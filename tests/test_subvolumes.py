"""Sub-volumes for volume conservation (Deul & Bender 2013, section 4.6): cutting planes, loops,
flood fill and closing fans, on the procedural arm and on CesiumMan."""

from __future__ import annotations

import dataclasses
import functools
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from oracles import rig_lbs
from warpskin.preprocess.bones import dominant_bone
from warpskin.preprocess.sub_volumes import SubVolumeParams, SubVolumes, build_subvolumes
from warpskin.rig import Rig, RigError, Skeleton
from warpskin.scenes.arm import ARM_DEFAULTS
from warpskin.skinning import Skinner

REL = 1e-6


@pytest.fixture(scope="module")
def arm_sv(arm) -> SubVolumes:
    return build_subvolumes(arm)


@functools.lru_cache(maxsize=1)
def _cesium(path: Path) -> tuple[Rig, SubVolumes]:
    from warpskin.io import load_rig

    rig = load_rig(path)
    return rig, build_subvolumes(rig)


def _mesh_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    return float(trimesh.Trimesh(points, triangles, process=False).volume)


def _closed_by_edge_count(tri: np.ndarray, n: int) -> bool:
    """Independent closedness check: every directed edge occurs once and its reverse once."""
    d = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]).astype(np.int64)
    key = d[:, 0] * n + d[:, 1]
    rkey = d[:, 1] * n + d[:, 0]
    return np.unique(key).size == key.size and np.array_equal(np.sort(key), np.sort(rkey))


def _check_closed(rig: Rig, sv: SubVolumes, points: np.ndarray, centers: np.ndarray) -> None:
    """Each sub-volume closed and consistently wound; its trimesh volume equals ``volumes``."""
    allp = np.concatenate([points, centers])
    vols = sv.volumes(points, centers)
    for s in range(sv.count):
        tri = sv.closed_triangles(s)
        assert _closed_by_edge_count(tri, allp.shape[0]), sv.names[s]
        m = trimesh.Trimesh(allp, tri, process=False)
        assert m.is_watertight and m.is_winding_consistent, sv.names[s]
        assert m.volume == pytest.approx(vols[s], rel=1e-9, abs=1e-15), sv.names[s]


def _check_partition(rig: Rig, sv: SubVolumes) -> None:
    assert np.array_equal(np.sort(sv.tri_indices), np.arange(rig.triangle_count))
    assert sv.tri_offsets[0] == 0 and sv.tri_offsets[-1] == rig.triangle_count
    assert (np.diff(sv.tri_offsets) > 0).all()
    assert sv.fan_offsets[-1] == sv.fan_triangles.shape[0]
    assert sv.center_rest.shape == (len(sv.loops), 3) and sv.center_joint.shape == (len(sv.loops),)
    assert sv.rest_volume.shape == (sv.count,) and (sv.rest_volume > 0).all()
    # each plane: one piece on either side, fans with opposite orientation
    for k in range(len(sv.loops)):
        prox, dist = sv.plane_sides[k]
        assert prox != dist
        f_prox = sv.fan_triangles[sv.fan_offsets[prox] : sv.fan_offsets[prox + 1]]
        f_dist = sv.fan_triangles[sv.fan_offsets[dist] : sv.fan_offsets[dist + 1]]
        a = {tuple(r) for r in f_prox[f_prox[:, 2] == k].tolist()}
        b = {(r[1], r[0], r[2]) for r in f_dist[f_dist[:, 2] == k].tolist()}
        assert a == b and len(a) == sv.loops[k].size


# --------------------------------------------------------------------------------------------
# arm
# --------------------------------------------------------------------------------------------


def test_arm_default_is_upper_arm_forearm_and_hand_cap(arm, arm_sv):
    sv = arm_sv
    assert sv.count == 3
    assert sv.names == ["shoulder", "elbow", "wrist"]  # upper arm, forearm, hand cap
    assert [arm.skeleton.joint_names[j] for j in sv.plane_joint] == ["elbow", "wrist"]
    np.testing.assert_allclose(sv.plane_t, [1.0, 1.0])
    np.testing.assert_allclose(sv.center_rest, [[0.30, 0, 0], [0.56, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(sv.plane_normal, [[1, 0, 0], [1, 0, 0]], atol=1e-12)
    assert sv.center_joint.tolist() == [0, 1]  # carried by the bone the center lies on
    assert sv.plane_sides.tolist() == [[0, 1], [1, 2]]
    _check_partition(arm, sv)
    # every loop: one simple cycle around the arm, within one edge length below its plane
    edge = np.linalg.norm(arm.vertices[arm.triangles[:, 0]] - arm.vertices[arm.triangles[:, 1]], axis=1).max()
    for k, loop in enumerate(sv.loops):
        assert loop.size == ARM_DEFAULTS["segments"] and np.unique(loop).size == loop.size
        s = (arm.vertices[loop] - sv.center_rest[k]) @ sv.plane_normal[k]
        assert (s <= 0).all() and (s > -edge).all()
        nxt = np.roll(loop, -1)
        edges = {tuple(sorted(e)) for e in arm.triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2).tolist()}
        assert all(tuple(sorted((a, b))) in edges for a, b in zip(loop.tolist(), nxt.tolist()))
    # pieces lie between their planes
    lab = sv.triangle_labels()
    cx = arm.vertices[arm.triangles].mean(axis=1)[:, 0]
    assert cx[lab == 0].max() < 0.30 + edge and cx[lab == 1].min() > 0.30 - edge
    assert cx[lab == 1].max() < 0.56 + edge and cx[lab == 2].min() > 0.56 - edge


def test_arm_subvolumes_closed_and_sum_to_mesh_volume_at_rest_and_flexed(arm, arm_sv):
    sv = arm_sv
    rest = _mesh_volume(arm.vertices, arm.triangles)
    assert sv.rest_volume.sum() == pytest.approx(rest, rel=REL)
    np.testing.assert_allclose(sv.volumes(arm.vertices, sv.center_rest), sv.rest_volume, rtol=1e-12)
    _check_closed(arm, sv, arm.vertices, sv.center_rest)
    for t in (0.75, 1.5, 2.0):  # flexing to 150 degrees at t = 1.5
        skin = arm.skinning_matrices(arm.clip("flex"), t)
        pts = rig_lbs(arm, skin)
        centers = sv.center_positions(skin)
        vols = sv.volumes(pts, centers)
        assert vols.sum() == pytest.approx(_mesh_volume(pts, arm.triangles), rel=REL)
        assert (vols > 0).all()
        _check_closed(arm, sv, pts, centers)
    # LBS collapses the elbow: the forearm piece loses volume at full flexion
    skin = arm.skinning_matrices(arm.clip("flex"), 1.5)
    vols = sv.volumes(rig_lbs(arm, skin), sv.center_positions(skin))
    assert vols[1] < 0.97 * sv.rest_volume[1]


def test_arm_volumes_with_warp_skinner_and_any_centers(arm, arm_sv):
    sv = arm_sv
    skinner = Skinner(arm, method="lbs", device="cpu")
    pts = skinner.skin_at(arm.clip("flex"), 1.5).numpy().astype(np.float64)
    ref = _mesh_volume(pts, arm.triangles)
    assert sv.volumes(pts, sv.center_positions(arm.skinning_matrices("flex", 1.5))).sum() == pytest.approx(ref, rel=REL)
    # the fans of a loop cancel, so the sum does not depend on where the centers are
    rng = np.random.default_rng(1)
    wild = sv.center_rest + rng.normal(scale=0.05, size=sv.center_rest.shape)
    assert sv.volumes(pts, wild).sum() == pytest.approx(ref, rel=REL)


def test_centers_move_with_their_joints(arm, arm_sv):
    sv = arm_sv
    world = arm.joint_world_transforms("flex", 1.5)
    centers = sv.center_positions(arm.skinning_matrices("flex", 1.5))
    # t = 1: the center is the joint itself (elbow, wrist), wherever the pose puts it
    np.testing.assert_allclose(centers, world[[1, 2], :3, 3], atol=1e-12)
    assert np.linalg.norm(centers[1] - sv.center_rest[1]) > 0.1  # the wrist swung up


def test_planes_can_be_moved_along_bones_or_dropped(arm):
    sv = build_subvolumes(arm, SubVolumeParams(planes={"wrist": None}))
    assert sv.count == 2 and sv.names == ["shoulder", "elbow"]
    sv = build_subvolumes(arm, SubVolumeParams(planes={"elbow": 0.5}))
    np.testing.assert_allclose(sv.center_rest[0], [0.15, 0, 0], atol=1e-12)
    assert sv.center_joint[0] == 0
    # t in (1, 2]: on the joint's own bone (elbow -> wrist), carried by the elbow
    sv = build_subvolumes(arm, SubVolumeParams(planes={"elbow": 1.5}))
    np.testing.assert_allclose(sv.center_rest[0], [0.43, 0, 0], atol=1e-12)
    assert sv.center_joint[0] == 1 and sv.count == 3
    _check_partition(arm, sv)
    skin = arm.skinning_matrices("flex", 1.5)
    pts = rig_lbs(arm, skin)
    assert sv.volumes(pts, sv.center_positions(skin)).sum() == pytest.approx(_mesh_volume(pts, arm.triangles), rel=REL)


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


def test_open_mesh_is_rejected(arm):
    hole = dataclasses.replace(arm, triangles=arm.triangles[1:], report=None)
    with pytest.raises(RigError, match="not a closed manifold surface"):
        build_subvolumes(hole)


def test_plane_outside_the_mesh_names_its_joint(arm):
    # t = 3: two leaf-bone lengths beyond the wrist, past the end of the hand cap
    with pytest.raises(RigError, match=r"plane of joint 'wrist' \(t=3\) cuts nothing"):
        build_subvolumes(arm, SubVolumeParams(planes={"wrist": 3.0}))
    with pytest.raises(RigError, match=r"joint 'elbow' \(t=-2\) cuts nothing"):
        build_subvolumes(arm, SubVolumeParams(planes={"elbow": -2.0}))


def test_bad_plane_parameters(arm):
    with pytest.raises(RigError, match="unknown joint 'knee'"):
        build_subvolumes(arm, SubVolumeParams(planes={"knee": 1.0}))
    with pytest.raises(RigError, match="root joint"):
        build_subvolumes(arm, SubVolumeParams(planes={"shoulder": 0.5}))
    with pytest.raises(RigError, match="finite"):
        build_subvolumes(arm, SubVolumeParams(planes={"wrist": math.nan}))
    # wrist at t = 0 is the elbow plane again: both loops on the same edges
    with pytest.raises(RigError, match="'wrist'.*'elbow'.*same mesh edges"):
        build_subvolumes(arm, SubVolumeParams(planes={"elbow": 1.0, "wrist": 0.0}))


def _torus_rig() -> Rig:
    """A closed torus around z with two joints along the tube at (R, 0, 0)."""
    big, small, n, m = 1.0, 0.25, 48, 16
    u = 2 * np.pi * (np.arange(n) + 0.5) / n
    v = 2 * np.pi * np.arange(m) / m
    uu, vv = np.meshgrid(u, v, indexing="ij")
    pts = np.stack(
        [(big + small * np.cos(vv)) * np.cos(uu), (big + small * np.cos(vv)) * np.sin(uu), small * np.sin(vv)], -1
    ).reshape(-1, 3)
    i, k = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b = i * m + k, ((i + 1) % n) * m + k
    c, d = ((i + 1) % n) * m + (k + 1) % m, i * m + (k + 1) % m
    tri = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    if _mesh_volume(pts, tri) < 0:
        tri = tri[:, ::-1]
    skel = Skeleton(["a", "b"], [-1, 0], [[big, -0.3, 0.0], [0.0, 0.3, 0.0]], [[0, 0, 0, 1]] * 2, np.ones((2, 3)))
    bind = skel.world_from_local(skel.rest_local_matrices())
    zeros = np.zeros((pts.shape[0], 1), dtype=np.int64)
    return Rig("torus", pts, tri, skel, zeros, np.ones((pts.shape[0], 1)), np.linalg.inv(bind))


def test_cut_that_does_not_separate_is_rejected():
    # one plane across the tube of a torus leaves the surface in one piece
    torus = _torus_rig()
    with pytest.raises(RigError, match=r"joint 'b' \(t=1\): its cut is not a closed loop separating"):
        build_subvolumes(torus, SubVolumeParams(planes={"b": 1.0}))
    # as a default plane it is left out, with a note; the whole torus is one sub-volume
    sv = build_subvolumes(torus)
    assert sv.count == 1 and len(sv.loops) == 0
    assert any("'b' left out" in n and "not a closed loop" in n for n in sv.notes)
    assert sv.rest_volume[0] == pytest.approx(_mesh_volume(torus.vertices, torus.triangles), rel=1e-12)


# --------------------------------------------------------------------------------------------
# CesiumMan
# --------------------------------------------------------------------------------------------


def test_cesium_man_subvolumes(assets):
    rig, sv = _cesium(assets / "usd" / "CesiumMan" / "CesiumMan.usdz")
    print(f"CesiumMan: {sv.count} sub-volumes: {sv.names}")
    assert sv.count == 19  # pelvis, belly, chest, neck, head, 2 x (upper arm, forearm, hand, thigh, shin, foot, toes)
    assert not [n for n in sv.notes if "left out" in n]
    _check_partition(rig, sv)
    rest = _mesh_volume(rig.vertices, rig.triangles)
    assert sv.rest_volume.sum() == pytest.approx(rest, rel=REL)
    _check_closed(rig, sv, rig.vertices, sv.center_rest)
    clip = rig.clip()
    for t in (clip.start, 0.5 * (clip.start + clip.end), 1.3):
        skin = rig.skinning_matrices(clip, t)
        pts = rig_lbs(rig, skin)
        centers = sv.center_positions(skin)
        vols = sv.volumes(pts, centers)
        assert vols.sum() == pytest.approx(_mesh_volume(pts, rig.triangles), rel=REL)
        assert (vols > 0).all()
    _check_closed(rig, sv, pts, centers)


def test_cesium_man_loops_stay_on_their_own_limb(assets):
    rig, sv = _cesium(assets / "usd" / "CesiumMan" / "CesiumMan.usdz")
    names = [n.rsplit("/", 1)[-1] for n in rig.skeleton.joint_names]
    owner = dominant_bone(rig)
    parents = rig.skeleton.parents
    for k, loop in enumerate(sv.loops):
        j = int(sv.plane_joint[k])
        near = {j, int(parents[j]), *np.nonzero(parents == j)[0].tolist()}
        near |= {int(parents[p]) for p in list(near) if parents[p] >= 0}
        assert set(owner[loop].tolist()) <= near, names[j]
        assert np.unique(loop).size == loop.size  # one simple cycle
    # the chest plane (halfway up the spine, level with the elbows) cuts the trunk only
    k = names.index("torso_joint_3")
    chest = sv.loops[list(sv.plane_joint).index(k)]
    assert np.abs(rig.vertices[chest, 1]).max() < 0.15
    # hips and shoulders: planes moved onto the limb bone, normal along the limb
    for limb in ("leg_joint_L_1", "leg_joint_R_1", "Skeleton_arm_joint_L__4_", "Skeleton_arm_joint_R"):
        j = names.index(limb)
        kk = list(sv.plane_joint).index(j)
        assert 1.0 < sv.plane_t[kk] <= 1.5 and sv.center_joint[kk] == j
        child = int(np.nonzero(parents == j)[0][0])
        bind = rig.bind_world_transforms()[:, :3, 3]
        d = bind[child] - bind[j]
        np.testing.assert_allclose(sv.plane_normal[kk], d / np.linalg.norm(d), atol=1e-12)

"""The capture of written meshes by the simulated surface, their physics weights and the
deformation kernel (warpskin.capture, warpskin.character, kernels.deform), and the cage that
keeps apart what is apart (warpskin.preprocess.cage): against closed forms and NumPy."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
import pytest
import scipy.sparse as sp
import trimesh
import warp as wp
from scipy.sparse.csgraph import connected_components

from oracles import lbs
from warpskin.capture import CaptureParams, shape_diameter
from warpskin.mesh import vertex_normals
from warpskin.character import Character
from warpskin.preprocess.cage import build_cage, character_parts, character_soup


def _components(v: np.ndarray, f: np.ndarray) -> int:
    n = len(v)
    g = sp.csr_matrix((np.ones(2 * len(f)), (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])), shape=(n, n))
    return connected_components(g, directed=False)[0]


def test_shape_diameter_of_a_sphere_and_a_box_is_their_width(device):
    s = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    v, f = np.asarray(s.vertices), np.asarray(s.faces)
    d = shape_diameter(v, vertex_normals(v, f), v, f, device=device)
    # the five rays (one along the inward normal, four tilted 20 degrees) are chords of the
    # sphere: 2 r for the first, 2 r cos 20 for the others; the median is a tilted one
    np.testing.assert_allclose(d, 2 * 0.05 * np.cos(np.radians(20.0)), rtol=0.02)
    b = trimesh.creation.box(extents=(0.3, 0.04, 0.2)).subdivide().subdivide()
    v, f = np.asarray(b.vertices), np.asarray(b.faces)
    d = shape_diameter(v, vertex_normals(v, f), v, f, device=device)
    mid_top = (np.abs(v[:, 1] - 0.02) < 1e-9) & (np.abs(v[:, 0]) < 0.1) & (np.abs(v[:, 2]) < 0.05)
    np.testing.assert_allclose(np.median(d[mid_top]), 0.04 / np.cos(np.radians(20.0)), rtol=0.02)


def test_an_overlapping_piece_does_not_end_the_ray(device):
    # a tube with a ball inside its end (a mannequin's elbow): the tube's thickness is its
    # diameter, not the distance to the ball it passes through
    from warpskin.scenes.mannequin import _tube

    tv, tf = _tube([0, 0, 0], [0, 0, 0.3], 0.05, 0.05, 32, 0.01)  # open at both ends
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.03)
    ball.apply_translation([0, 0, 0.27])
    v = np.concatenate([tv, ball.vertices])
    f = np.concatenate([tf, ball.faces + len(tv)])
    n = vertex_normals(v, f)
    side = np.abs(v[:, 2] - 0.27) < 0.006
    side[len(tv):] = False
    d = shape_diameter(v[side], n[side], v, f, device=device)
    # of a cylinder's five chords, the tilts around it are 2 r cos 20 and those along it
    # 2 r / cos 20: the median is the diameter
    np.testing.assert_allclose(d, 2 * 0.05, rtol=0.01)


def _two_blocks(gap: float, far: bool = False):
    """Two boxes side by side, each skinned to its own joint (two legs), as a rig whose skin is
    the pair (open, two pieces). ``far``: the left one's joint hangs below another joint, so the
    two are three steps apart in the skeleton (a hand beside a leg)."""
    from warpskin.rig import Rig, Skeleton

    a = trimesh.creation.box(extents=(0.1, 0.5, 0.1)).subdivide().subdivide()
    pa = np.asarray(a.vertices) + [-(0.05 + gap / 2), 0.5, 0]
    pb = np.asarray(a.vertices) + [(0.05 + gap / 2), 0.5, 0]
    pts = np.concatenate([pa, pb])
    tris = np.concatenate([a.faces, a.faces + len(pa)])
    n = len(pa)
    ji = np.concatenate([np.full((n, 1), 1), np.full((n, 1), 2)])
    jw = np.ones((2 * n, 1))
    skel = Skeleton(["root", "leg_l", "leg_r"], np.array([-1, 0, 0]),
                    np.array([[0, 0.8, 0], [-(0.05 + gap / 2), 0, 0], [0.05 + gap / 2, 0, 0]]),
                    np.tile([0, 0, 0, 1.0], (3, 1)), np.ones((3, 3)))
    if far:
        ji = np.concatenate([np.full((n, 1), 2), np.full((n, 1), 4)])
        x = 0.05 + gap / 2
        skel = Skeleton(["root", "arm", "hand", "tip", "leg", "foot"], np.array([-1, 0, 1, 2, 0, 4]),
                        np.array([[0, 0.8, 0], [-x, 0.3, 0.013], [0.007, -0.35, 0], [0, -0.5, 0], [x, -0.05, 0.011],
                                  [0, -0.5, 0]]),
                        np.tile([0, 0, 0, 1.0], (6, 1)), np.ones((6, 3)))
    inv = np.linalg.inv(skel.world_from_local(skel.rest_local_matrices()))
    return Rig.from_file_arrays(name="blocks", points=pts, triangles=tris, skeleton=skel, joint_indices=ji,
                                joint_weights=jw, inverse_bind=inv, weld=False)


def test_the_cage_keeps_a_gap_between_parts_that_must_not_share_one(device):
    rig = _two_blocks(gap=0.012)  # narrower than the cage's offset on both sides
    soup = character_soup(rig)
    edge = 0.03
    merged = build_cage(soup.points, soup.triangles, edge=edge, device=device)
    apart = build_cage(soup.points, soup.triangles, edge=edge, device=device, parts=character_parts(rig, soup))
    assert _components(merged.vertices, merged.triangles) == 1
    assert _components(apart.vertices, apart.triangles) == 2
    assert apart.timings_s["carved_nodes"] > 0
    # far apart the parts get two cages anyway, and carving changes nothing
    rig = _two_blocks(gap=0.2)
    soup = character_soup(rig)
    a = build_cage(soup.points, soup.triangles, edge=edge, device=device)
    b = build_cage(soup.points, soup.triangles, edge=edge, device=device, parts=character_parts(rig, soup))
    assert b.timings_s["carved_nodes"] == 0
    np.testing.assert_array_equal(a.vertices, b.vertices)


def test_a_pocket_inside_the_character_is_not_a_cage_component(device):
    # a thick hollow shell (an outer sphere and an inward-wound inner one): the iso-surface has
    # an outer and an inner sheet; the cage keeps only the outer, which encloses volume
    outer = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.06)
    v = np.concatenate([outer.vertices, inner.vertices])
    f = np.concatenate([outer.faces, inner.faces[:, ::-1] + len(outer.vertices)])
    cage = build_cage(v, f, edge=0.01, device=device)
    assert _components(cage.vertices, cage.triangles) == 1
    assert np.linalg.norm(cage.vertices, axis=1).min() > 0.09


def _blocks_character(device, gap=0.012):
    rig = _two_blocks(gap)
    from warpskin.rig import Clip, Track

    t = np.linspace(0, 1, 11)
    ang = np.radians(30 * np.sin(2 * np.pi * t))
    q = np.stack([np.sin(ang / 2), np.zeros_like(ang), np.zeros_like(ang), np.cos(ang / 2)], 1)
    rig.clips = {"swing": Clip("swing", {(1, "rotation"): Track("rotation", t, q), (2, "rotation"): Track("rotation", t, q[::-1])})}
    return Character(rig, cage="always", device=device)


def test_captures_sum_to_one_and_never_reach_the_other_part(device):
    ch = _blocks_character(device)
    cap = ch.bind(device=device)
    np.testing.assert_allclose(cap.weights.sum(axis=1), 1.0, atol=1e-12)
    cage_w = ch.sim_rig._dense_weights(ch.sim_rig.joint_indices, ch.sim_rig.joint_weights)
    n = len(ch.soup.points) // 2
    for part, joint in ((slice(0, n), 1), (slice(n, 2 * n), 2)):
        idx, w = cap.indices[part], cap.weights[part]
        other = 3 - joint
        # every captured cage vertex with weight carries the point's own joint, none only the other's
        used = w > 0
        assert np.all(cage_w[idx[used], joint] > 0.0)
        assert np.all(cage_w[idx[used], other] < 1.0)


def test_where_the_cage_is_at_its_lbs_the_written_meshes_are_exactly_theirs(device):
    ch = _blocks_character(device)
    ch.bind(device=device)
    clip = ch.rig.clip("swing")
    sim = ch.sim_rig
    for t in (0.2, 0.55):
        cage_lbs = lbs(sim.vertices, sim.joint_indices, sim.joint_weights, sim.skinning_matrices(clip, t))
        x = wp.array(cage_lbs.astype(np.float32), dtype=wp.vec3, device=device)
        got = ch.points(x, None, clip, t)
        want = ch.lbs(clip, t)
        np.testing.assert_allclose(got, want, atol=2e-6)


def test_the_deformation_kernel_is_lbs_plus_the_weighted_captured_displacement(device):
    # against NumPy: written = own LBS + phi * sum_m a_m (x - LBS_cage)_(s_m), for a displaced cage
    ch = _blocks_character(device)
    cap = ch.bind(device=device)
    rng = np.random.default_rng(2)
    cap.physics_weight[:] = rng.uniform(0, 1, size=cap.physics_weight.shape)  # generic weights
    ch._deformer = type(ch._deformer)(ch, cap, device=device, joint_gap=0.0)  # the formula, no joint limit
    clip = ch.rig.clip("swing")
    sim = ch.sim_rig
    t = 0.35
    cage_lbs = lbs(sim.vertices, sim.joint_indices, sim.joint_weights, sim.skinning_matrices(clip, t))
    x = cage_lbs + rng.normal(scale=0.01, size=cage_lbs.shape)
    got = ch.points(wp.array(x.astype(np.float32), dtype=wp.vec3, device=device), None, clip, t)
    d = x - cage_lbs
    own = ch.lbs(clip, t)
    phi = cap.physics_weight.astype(np.float32).astype(np.float64)
    want = own + phi[:, None] * np.einsum("nk,nkc->nc", cap.weights, d[cap.indices])
    # a block LBS moves rigidly is one group: the share phi of the rigid motion (weighted Kabsch,
    # against the cage's LBS) of the cage vertices that carry it, on top of its own LBS
    deformer = ch._deformer
    assert deformer.groups is not None
    offsets, verts, wts, gid = deformer.groups
    for g in range(len(offsets) - 1):
        v, w = verts[offsets[g]:offsets[g + 1]], wts[offsets[g]:offsets[g + 1]].astype(np.float64)
        c, cl = w @ x[v], w @ cage_lbs[v]
        u, _, vt = np.linalg.svd(((x[v] - c) * w[:, None]).T @ (cage_lbs[v] - cl))
        r = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        pts = deformer.group_points[gid == g]
        for i in pts:
            turn = Rotation.from_rotvec(Rotation.from_matrix(r).as_rotvec() * phi[i]).as_matrix()
            want[i] = turn @ (own[i] - cl) + cl + phi[i] * (c - cl)
    np.testing.assert_allclose(got, want, atol=5e-6)


def test_pieces_moved_as_a_whole_keep_their_joints(device):
    # the two blocks meet at rest (6 mm apart): a swinging cage may carry each block's rigid fit
    # far from its LBS, but where a block meets the other its points stay within joint_gap x the
    # diagonal of their LBS; the block stays rigid; a motion within the limit is left whole
    from scipy.spatial import cKDTree

    ch = _blocks_character(device, gap=0.006)
    cap = ch.bind(device=device)
    clip = ch.rig.clip("swing")
    sim, t = ch.sim_rig, 0.35
    cage_lbs = lbs(sim.vertices, sim.joint_indices, sim.joint_weights, sim.skinning_matrices(clip, t))
    rest = ch.soup.points
    diagonal = float(np.linalg.norm(np.ptp(rest, axis=0)))
    n = len(rest) // 2
    dist, _ = cKDTree(rest[n:]).query(rest[:n])
    meets = np.concatenate([dist <= 0.02 * diagonal, cKDTree(rest[:n]).query(rest[n:])[0] <= 0.02 * diagonal])
    own = ch.lbs(clip, t)
    rng = np.random.default_rng(5)
    for scale, limited in ((0.2, True), (1e-4, False)):  # a swing of 20 % of the cage's size, a tremor
        x = cage_lbs + scale * np.ptp(cage_lbs, axis=0).max() * np.stack([np.sin(cage_lbs[:, 1] * 7), np.cos(
            cage_lbs[:, 0] * 5), np.sin(cage_lbs[:, 2] * 3)], axis=1) + rng.normal(scale=1e-3 * scale, size=cage_lbs.shape)
        xs = wp.array(x.astype(np.float32), dtype=wp.vec3, device=device)
        free = type(ch._deformer)(ch, cap, device=device, joint_gap=0.0).evaluate(xs, clip, t).numpy()
        ch._deformer = type(ch._deformer)(ch, cap, device=device, joint_gap=0.01)
        got = ch.points(xs, None, clip, t)
        far = np.linalg.norm(free - own, axis=1)[meets].max()
        near = np.linalg.norm(got - own, axis=1)[meets].max()
        if limited:
            assert far > 0.02 * diagonal  # the test moves the joints well past the limit
            assert 0.0099 * diagonal <= near <= 0.01 * diagonal * (1 + 1e-4)  # at the limit, not short of it
        else:
            np.testing.assert_allclose(got, free, atol=1e-7)
        for part in (slice(0, n), slice(n, 2 * n)):  # each block rigid: its distances kept
            a, b = got[part], own[part]
            d_got = np.linalg.norm(a[:, None] - a[None], axis=2)
            d_own = np.linalg.norm(b[:, None] - b[None], axis=2)
            assert np.abs(d_got - d_own).max() < 1e-5 * diagonal


def test_a_small_assembly_moves_as_a_whole(device):
    # a "fist": a block with four knuckle spheres on it, one mesh, on the hand joint with a
    # finger joint blended in, beside a long arm: its points share one capture row and weight
    from warpskin.rig import Attachment, Rig, Skeleton

    arm = trimesh.creation.box(extents=(0.5, 0.08, 0.08)).subdivide().subdivide()
    palm = trimesh.creation.box(extents=(0.08, 0.07, 0.06)).subdivide()
    parts_v, parts_f = [np.asarray(palm.vertices) + [0.3, 0, 0]], [np.asarray(palm.faces)]
    off = len(parts_v[0])
    for k in range(4):
        s = trimesh.creation.icosphere(subdivisions=1, radius=0.013)
        parts_v.append(np.asarray(s.vertices) + [0.34, -0.027 + 0.018 * k + 0.0013, 0.021])
        parts_f.append(np.asarray(s.faces) + off)
        off += len(s.vertices)
    fv, ff = np.concatenate(parts_v), np.concatenate(parts_f)
    skel = Skeleton(["arm", "hand", "fingers"], np.array([-1, 0, 1]), np.array([[-0.25, 0, 0], [0.51, 0, 0], [0.08, 0, 0]]),
                    np.tile([0, 0, 0, 1.0], (3, 1)), np.ones((3, 3)))
    inv = np.linalg.inv(skel.world_from_local(skel.rest_local_matrices()))
    av = np.asarray(arm.vertices)
    u = np.clip((av[:, 0] + 0.25) / 0.5, 0, 1)
    rig = Rig.from_file_arrays(name="arm", points=av, triangles=arm.faces, skeleton=skel,
                               joint_indices=np.tile([0, 1], (len(av), 1)), joint_weights=np.stack([1 - 0.3 * u, 0.3 * u], 1),
                               inverse_bind=inv, weld=False)
    fw = np.clip((fv[:, 0] - 0.3) / 0.06, 0, 1) * 0.4
    rig.attachments = [Attachment("fist", fv, ff, np.tile([1, 2], (len(fv), 1)), np.stack([1 - fw, fw], 1), inv.copy())]
    ch = Character(rig, cage="always", device=device)
    fist = ch.parts[1]
    s = slice(fist.start, fist.start + fist.count)
    extent = float(np.linalg.norm(np.ptp(fist.rest, axis=0))) / ch.edge()  # in cage edges
    ch.capture = CaptureParams(small=1.5 * extent)
    cap = ch.bind(device=device)
    assert np.unique(cap.indices[s], axis=0).shape[0] == 1
    assert np.unique(cap.weights[s], axis=0).shape[0] == 1
    assert np.ptp(cap.physics_weight[s]) == 0.0
    # and with a smaller bound it is not
    ch.capture = CaptureParams(small=0.5 * extent)
    cap = ch.bind(device=device)
    assert np.unique(cap.indices[s], axis=0).shape[0] > 1


def test_cage_weights_are_smoothed_so_its_lbs_does_not_tear_at_rigid_joints(device):
    # a bar of two rigid halves (weight 1 each side of the joint), bent 45 degrees: the cage's
    # own LBS stretches its edges across the joint by far less once its weights are smoothed
    from warpskin.preprocess.cage import cage_rig
    from warpskin.rig import Clip, Rig, Skeleton, Track

    bar = trimesh.creation.box(extents=(0.6, 0.1, 0.1)).subdivide().subdivide().subdivide()
    v = np.asarray(bar.vertices)
    skel = Skeleton(["a", "b"], np.array([-1, 0]), np.array([[-0.3, 0, 0], [0.3, 0, 0]]), np.tile([0, 0, 0, 1.0], (2, 1)),
                    np.ones((2, 3)))
    inv = np.linalg.inv(skel.world_from_local(skel.rest_local_matrices()))
    right = (v[:, 0] > 0).astype(int)
    rig = Rig.from_file_arrays(name="bar", points=v, triangles=bar.faces, skeleton=skel, joint_indices=right[:, None],
                               joint_weights=np.ones((len(v), 1)), inverse_bind=inv, weld=False)
    rig.clips = {"bend": Clip("bend", {(1, "rotation"): Track("rotation", [0.0, 1.0], [[0, 0, 0, 1.0], [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)]])})}
    soup = character_soup(rig)
    cage = build_cage(soup.points, soup.triangles, edge=0.025, device=device)

    def torn(passes):
        crig, _, _ = cage_rig(rig, cage, device=device, smooth_passes=passes)
        x = lbs(crig.vertices, crig.joint_indices, crig.joint_weights, crig.skinning_matrices(rig.clip("bend"), 1.0))
        e = np.concatenate([cage.triangles[:, [0, 1]], cage.triangles[:, [1, 2]]])
        l0 = np.linalg.norm(cage.vertices[e[:, 0]] - cage.vertices[e[:, 1]], axis=1)
        ratio = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / l0
        return float(np.mean(ratio > 1.5))  # the share of torn edges

    assert torn(0) > 0.005
    assert torn(8) < 0.5 * torn(0)


def test_joint_constraints_hold_only_the_tissue_of_bones_near_the_joint():
    # a joint's sphere reaches the other block (a hand hanging beside a leg; here two blocks
    # three steps apart in the skeleton): none of that block's particles is constrained to it
    from warpskin.model import ModelParams, SkinModelBuilder
    from warpskin.preprocess.layers import LayerParams

    rig = _two_blocks(gap=0.012, far=True)  # two closed pieces: the layered model builds on them directly
    from warpskin.preprocess.joint_constraints import JointParams

    # spheres three times the joints' radius: each reaches the other block
    b = SkinModelBuilder(rig, ModelParams(layers=LayerParams(fat=0.05, muscle=0.1, bone=0.2), refine=False,
                                          joints=JointParams(radius_factor=3.0))).build()
    jc = b.joint_constraints
    v = rig.vertex_count
    bone = b.layers.bone[jc.particles % v]
    names = np.array(rig.skeleton.joint_names)
    assert jc.count > 0
    pairs = set(zip(names[jc.joints].tolist(), names[bone].tolist()))
    assert ("hand", "leg") not in pairs and ("leg", "hand") not in pairs
    assert ("hand", "hand") in pairs and ("leg", "leg") in pairs


def test_painted_weights_and_joint_patterns_override_the_automatic_map(tmp_path, device):
    # the mannequin as a file with a painted _PHYSICS_WEIGHT on its left shoe (a ramp along
    # it): the shoe's weights are the painted ones (one mean where it moves as a whole); then a
    # joint pattern blends its value in by the skinning: phi' = (1 - s) phi + s v, s the
    # point's LBS weight on the matched joints
    from gltf_builder import write_rig_glb
    from warpskin.io import load_rig
    from warpskin.scenes.mannequin import make_mannequin

    src = make_mannequin()
    shoe = next(a for a in src.attachments if a.name == "shoe_l")
    ramp = np.clip((shoe.vertices[:, 2] - shoe.vertices[:, 2].min()) / np.ptp(shoe.vertices[:, 2]), 0.0, 1.0)
    rig = load_rig(write_rig_glb(src, tmp_path / "painted.glb", painted={"shoe_l": ramp}))
    ch = Character(rig, cage="always", device=device)
    part = next(p for p in ch.parts if p.name == "shoe_l")
    s = slice(part.start, part.start + part.count)
    np.testing.assert_allclose(ch.painted()[s], ramp, atol=1e-6)
    cap = ch.bind(device=device)
    want = cap.uniform_in_groups(np.where(np.isnan(ch.painted()), cap.physics_weight, ch.painted()))
    np.testing.assert_allclose(cap.physics_weight[s], want[s], atol=1e-9)
    assert np.ptp(cap.physics_weight[s]) > 0.5  # the shoe does not move as a whole: the ramp holds
    # a joint pattern on top: the hands (fists) and feet at 0.25
    auto = cap.physics_weight.copy()
    ch2 = Character(rig, cage="always", device=device, weights={"hand_*": 0.25, "foot_?": 0.25})
    cap2 = ch2.bind(device=device)
    names = rig.skeleton.joint_names
    hit = np.array([n.startswith("hand_") or (n.startswith("foot_") and len(n) == 6) for n in names])
    share = ch2.soup.dense_weights[:, hit].sum(axis=1)
    want = cap2.uniform_in_groups((1 - share) * auto + 0.25 * share)
    np.testing.assert_allclose(cap2.physics_weight, want, atol=1e-9)
    assert share.max() > 0.99 and share.min() == 0.0
    # a pattern that names no joint is an error, naming the joints there are
    from warpskin.errors import SceneError

    with pytest.raises(SceneError, match=r"no joint matches \['\*tail\*'\]"):
        Character(rig, cage="always", device=device, weights={"*tail*": 0.0}).bind(device=device)


def test_joint_points_are_where_pieces_meet_as_brute_force_finds():
    # three dense strips (triangles of their own), two of them one rigid group: a point is a joint
    # point where a point of another piece (not its own strip, not its own group) lies within 2 %
    # of the diagonal; checked against all pairs, with pieces denser than the first search's 32
    from warpskin.deformer import joint_points

    rng = np.random.default_rng(3)
    strips, tris = [], []
    for k, x0 in enumerate((0.0, 0.0151, 0.4)):  # the first two 5 mm apart, the third far
        p = np.column_stack([x0 + rng.uniform(0, 0.01, 300), rng.uniform(0, 0.1, 300), rng.uniform(0, 0.01, 300)])
        off = sum(len(s) for s in strips)
        tris.append(np.arange(300)[:-2, None] + np.array([0, 1, 2]) + off)
        strips.append(p)
    pts, tri = np.concatenate(strips), np.concatenate(tris)
    group = np.full(len(pts), -1)
    group[300:] = 0  # strips 2 and 3 move as one
    got = joint_points(pts, tri, group)
    piece = np.repeat([0, 1, 1], 300)  # strip 1 alone; 2 and 3 one piece
    reach = 0.02 * np.linalg.norm(np.ptp(pts, axis=0))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    want = ((d <= reach) & (piece[:, None] != piece[None])).any(axis=1)
    np.testing.assert_array_equal(got, want)
    assert 0 < want.sum() < 600 and not want[600:].any()
    assert ((d <= reach) & (piece[:, None] == piece[None])).sum(axis=1).max() > 32  # past the first search

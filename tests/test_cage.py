"""The automatic simulation cage (first part of the any-character issue): a closed, manifold,
outward-oriented, near-isotropic surface around meshes of any topology. Checked with trimesh
(watertight, winding, volume), a brute-force winding number and point-to-triangle distance
(containment), a closed form (a sphere) and triangle shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from oracles import point_mesh_distance, winding_numbers
from warpskin.preprocess.cage import build_cage, default_cage_edge, mesh_quality
from warpskin.rig import RigError

ASPECT = 10.0  # longest edge^2 / (2 area): 1.15 for an equilateral triangle


def _check_cage(cage, points, tolerance):
    tm = trimesh.Trimesh(cage.vertices, cage.triangles, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    q = mesh_quality(cage.vertices, cage.triangles)
    assert q["aspect_max"] < ASPECT, q
    w = winding_numbers(points, cage.vertices, cage.triangles)
    outside = w < 0.5
    if outside.any():  # the few that the smoothing leaves outside lie within the tolerance
        assert point_mesh_distance(points[outside], cage.vertices, cage.triangles).max() < tolerance
    return tm


def test_the_cage_of_a_sphere_is_the_offset_sphere(device):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    h = 0.1
    cage = build_cage(sphere.vertices, sphere.faces, edge=h, device=device)
    tm = _check_cage(cage, np.asarray(sphere.vertices), 0.25 * h)
    r = np.linalg.norm(cage.vertices, axis=1)
    want = 1.0 + cage.offset
    assert abs(np.median(r) - want) < 0.1 * h and np.abs(r - want).max() < 0.3 * h
    assert abs(tm.volume / (4 / 3 * np.pi * want**3) - 1) < 0.02
    assert tm.body_count == 1
    assert 0.6 * h < mesh_quality(cage.vertices, cage.triangles)["edge_mean"] < 1.3 * h


def test_bad_input_names_the_problem():
    with pytest.raises(RigError, match=r"points \[N, 3\] and triangles \[T, 3\]"):
        build_cage(np.zeros((3, 2)), np.array([[0, 1, 2]]))
    with pytest.raises(RigError, match="no area"):
        default_cage_edge(np.zeros((3, 3)), np.array([[0, 1, 2]]))


def _broken_cesium_man(assets):
    """CesiumMan as a production mesh: every seam split (each triangle its own vertices), holes
    cut, the body in two pieces that overlap at the waist, and a floating eye sphere."""
    from warpskin.io import load_rig
    from warpskin.run.output import rest_pose_points

    rig = load_rig(assets / "CesiumMan" / "CesiumMan.glb")
    p, t = rest_pose_points(rig), rig.triangles
    rng = np.random.default_rng(7)
    centres = p[rng.choice(len(p), 12, replace=False)]
    near = np.linalg.norm(p[t].mean(1)[:, None, :] - centres[None], axis=2).min(1) < 0.03
    t = t[~near]  # 12 holes
    y = p[t].mean(1)[:, 1]
    waist = np.percentile(p[:, 1], 50)
    upper, lower = t[y > waist - 0.02], t[y < waist + 0.02]  # two pieces, overlapping by 4 cm
    soup = np.concatenate([p[upper].reshape(-1, 3), p[lower].reshape(-1, 3)])  # seams split everywhere
    faces = np.arange(len(soup)).reshape(-1, 3)
    head = p[np.argmax(p[:, 1])]
    eye = trimesh.creation.icosphere(subdivisions=2, radius=0.02)
    eye_v = np.asarray(eye.vertices) + head + np.array([0.0, -0.12, 0.09])
    points = np.concatenate([soup, eye_v])
    faces = np.concatenate([faces, np.asarray(eye.faces) + len(soup)])
    return points, faces, int(near.sum())


def test_a_cage_closes_holes_pieces_and_split_seams(assets, device):
    points, faces, cut = _broken_cesium_man(assets)
    assert cut > 0 and not trimesh.Trimesh(points, faces, process=True).is_watertight  # really broken
    cage = build_cage(points, faces, device=device)
    tm = _check_cage(cage, points, 0.25 * cage.edge)
    assert tm.body_count <= 2  # the body (and the eye, where it floats free of the head)
    assert 1500 < len(cage.vertices) < 8000 and cage.build_s > 0


def test_robot_expressive_gets_one_cage_around_its_14_meshes(assets, device):
    from warpskin.io import load_rig
    from warpskin.rig import Clip
    from warpskin.run.output import rest_pose_points

    rig = load_rig(assets / "RobotExpressive" / "RobotExpressive.glb")
    world = rig.joint_world_transforms(Clip("rest"), 0.0)
    parts = [(rest_pose_points(rig)[rig.weld_map], rig.file_triangles)] + [(a.points(world), a.triangles)
                                                                          for a in rig.attachments]
    assert len(parts) == 14
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    points = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    cage = build_cage(points, faces, device=device)
    tm = _check_cage(cage, points, 0.25 * cage.edge)
    assert tm.body_count == 1

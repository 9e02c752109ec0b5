"""The automatic simulation cage (first part of the any-character issue): a closed, manifold,
outward-oriented, near-isotropic surface around meshes of any topology. Checked with trimesh
(watertight, winding, volume), a brute-force winding number and point-to-triangle distance
(containment), a closed form (a sphere) and triangle shapes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from oracles import point_mesh_distance, winding_numbers, prim
from warpskin.preprocess.cage import build_cage, default_cage_edge, mesh_quality
from warpskin.rig import RigError

ASPECT = 10.0  # longest edge^2 / (2 area): 1.15 for an equilateral triangle


def _check_cage(cage, points, tolerance):
    tm = trimesh.Trimesh(cage.vertices, cage.triangles, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    q = mesh_quality(cage.vertices, cage.triangles)
    assert q["aspect_max"] < ASPECT, q
    # each distinct position once (a triangle soup repeats each about six times): the same test
    unique, inverse = np.unique(np.asarray(points), axis=0, return_inverse=True)
    w = winding_numbers(unique, cage.vertices, cage.triangles)[inverse.reshape(-1)]
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


@pytest.mark.slow
def test_a_cage_closes_holes_pieces_and_split_seams(assets, device):
    points, faces, cut = _broken_cesium_man(assets)
    assert cut > 0 and not trimesh.Trimesh(points, faces, process=True).is_watertight  # really broken
    cage = build_cage(points, faces, device=device)
    tm = _check_cage(cage, points, 0.25 * cage.edge)
    assert tm.body_count <= 2  # the body (and the eye, where it floats free of the head)
    assert 1500 < len(cage.vertices) < 8000 and cage.build_s > 0


@pytest.mark.slow
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


def test_weights_are_transferred_and_inpainted_against_numpy(device):
    # a cage (sphere) around a smaller sphere whose weights are a smooth field of two joints;
    # matched cage vertices take the barycentric blend at their closest point, the others (cut
    # off by a small max_distance on one side) the harmonic extension of the matched ones
    from warpskin.preprocess.cage import CharacterSoup, transfer_weights

    inner = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    p = np.asarray(inner.vertices)
    w0 = 0.5 + 0.4 * p[:, 0]
    dense = np.stack([w0, 1 - w0], axis=1)
    soup = CharacterSoup(p, np.asarray(inner.faces), dense, [("skin", 0, len(p))])
    cage = trimesh.creation.icosphere(subdivisions=2, radius=1.1)
    cv = np.asarray(cage.vertices) + np.array([0.06, 0.0, 0.0])  # off centre: the +x side is farther
    dist = point_mesh_distance(cv, p, np.asarray(inner.faces))
    cut = float(np.median(dist))
    ji, jw, matched = transfer_weights(cv, np.asarray(cage.faces), soup, max_distance=cut, device=device)
    assert 0 < matched.sum() < len(cv)
    got = np.zeros((len(cv), 2))
    np.put_along_axis(got, ji, jw, axis=1)
    # matched: the blend at the closest point, to the accuracy of the piecewise-linear field
    closest_w0 = 0.5 + 0.4 * (cv[matched] / np.linalg.norm(cv[matched], axis=1, keepdims=True))[:, 0]
    assert np.abs(got[matched, 0] - closest_w0).max() < 0.02
    # unmatched: harmonic (uniform Laplacian) with the matched fixed, solved densely here
    n = len(cv)
    adj = np.zeros((n, n))
    for a, b in np.asarray(cage.edges_unique):
        adj[a, b] = adj[b, a] = 1
    lap = np.diag(adj.sum(1)) - adj
    u, m = np.nonzero(~matched)[0], np.nonzero(matched)[0]
    ref = got[:, 0].copy()
    bary_field = got[m, 0]
    ref[u] = np.linalg.solve(lap[np.ix_(u, u)], -lap[np.ix_(u, m)] @ bary_field)
    np.testing.assert_allclose(got[u, 0], np.clip(ref[u], 0, 1), atol=1e-6)
    np.testing.assert_allclose(jw.sum(axis=1), 1.0, atol=1e-12)


@pytest.mark.slow
def test_a_broken_character_simulates_through_its_cage(assets, tmp_path, device):
    # CesiumMan with 8 holes cut, split in two at the waist, every seam split, and a floating eye
    # sphere skinned to the head, as a rig (its UVs kept per corner): simulate with the defaults
    # picks the cage, writes the file's own topology and UVs, embedded, the eye as one rigid
    # piece (its shape kept exactly), and the simulated cage is no worse than LBS
    from pxr import Usd, UsdGeom

    from warpskin.io import load_rig
    from warpskin.io.render import RenderAttributes
    from warpskin.rig import Rig
    from warpskin.run import simulate
    from warpskin.scene import Scene

    src = load_rig(assets / "CesiumMan" / "CesiumMan.glb")
    ft = src.file_triangles
    rng = np.random.default_rng(3)
    bind = src.vertices[src.weld_map]
    centres = bind[rng.choice(len(bind), 8, replace=False)]
    mid = bind[ft].mean(1)
    keep = np.linalg.norm(mid[:, None] - centres[None], axis=2).min(1) > 0.03
    keep &= np.abs(mid[:, 2] - 0.95) > 0.012  # a band cut at the waist (bind space is Z up): two pieces
    tris = ft[keep]
    # the eye: a sphere in front of the face (the face looks along +X in bind space), on the head joint
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.015)
    eye_tris = np.asarray(sphere.faces)
    eye_pts = (np.asarray(sphere.vertices) + np.array([0.138, 0.035, 1.42]))[eye_tris.ravel()]
    head = src.skeleton.joint_names.index("Skeleton_neck_joint_2")
    k = src.joint_indices.shape[1]
    eye_ji = np.zeros((len(eye_pts), k), dtype=src.joint_indices.dtype)
    eye_ji[:, 0] = head
    eye_jw = np.zeros((len(eye_pts), k))
    eye_jw[:, 0] = 1.0
    points = np.concatenate([bind[tris.ravel()], eye_pts])
    soup_tris = np.arange(len(points)).reshape(-1, 3)  # every seam split
    eye = np.arange(len(points)) >= 3 * len(tris)
    ji = np.concatenate([src.joint_indices[src.weld_map][tris.ravel()], eye_ji])
    jw = np.concatenate([src.joint_weights[src.weld_map][tris.ravel()], eye_jw])
    uvs = np.concatenate([src.render.uvs[keep], np.full((len(eye_tris), 3, 2), 0.5)])
    broken = Rig.from_file_arrays(
        name="BrokenMan", points=points, triangles=soup_tris, skeleton=src.skeleton, joint_indices=ji,
        joint_weights=jw, inverse_bind=src.inverse_bind, clips=src.clips, source="test", mesh_name="BrokenMan",
        weld=False, validate=False, render=RenderAttributes(uvs=uvs))
    assert not broken.validate(raise_on_error=False).closed
    scene = Scene(name="BrokenMan", source=None, rig_spec={}, fps=24.0, preroll=0.1)
    scene._rig = broken
    result = simulate(scene, tmp_path / "broken.usdc", device=device, frames=(1, 4), with_lbs=True, progress=False,
                      check_intersections=True, report_dir=tmp_path / "report")
    assert (tmp_path / "report" / "offset_map.png").is_file()  # drawn from the render skin's deviation
    s, m = result.summary, result.metrics
    assert s["cage"] is not None and s["cage"]["weights_matched"] > 0.95
    assert s["cage"]["rigid_pieces"] == 1  # the eye (the body's pieces have many joints)
    stage = Usd.Stage.Open(str(result.path))
    skin = UsdGeom.Mesh(prim(stage, "skin"))
    np.testing.assert_array_equal(np.asarray(skin.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), soup_tris)
    np.testing.assert_allclose(np.asarray(UsdGeom.PrimvarsAPI(skin).GetPrimvar("st").Get()).reshape(-1, 3, 2),
                               uvs, atol=1e-6)
    pts = np.asarray(skin.GetPointsAttr().Get(4))
    assert pts.shape == (len(points), 3) and np.isfinite(pts).all()
    assert UsdGeom.Mesh(stage.GetDefaultPrim().GetChild("cage")).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
    # the LBS guide is the broken character's own LBS (its inverse binds, not the cage's)
    from oracles import rig_lbs

    lbs = np.asarray(UsdGeom.Mesh(prim(stage, "lbs")).GetPointsAttr().Get(4), dtype=np.float64)
    want = rig_lbs(broken, broken.skinning_matrices(broken.clip(None), 4 / 24))[broken.weld_map]
    assert np.abs(lbs - want).max() < 1e-5 * broken.size()
    assert np.linalg.norm(pts - want, axis=1).max() < 0.08 * broken.size()  # the embedded skin stays near it
    # the eye keeps its shape (LBS moves it rigidly, and so does its cage region's rigid fit)
    spread = lambda p: np.linalg.norm(p[:, None] - p[None], axis=2)  # noqa: E731
    assert np.abs(spread(pts[eye]) - spread(want[eye])).max() < 1e-5 * broken.size()
    assert np.linalg.norm(pts[eye] - want[eye], axis=1).max() < 0.05 * broken.size()
    v0 = m["volume_rest"]
    assert np.all(np.abs(np.array(m["volume"]) / v0 - 1) <= np.abs(np.array(m["volume_lbs"]) / v0 - 1) + 1e-3)
    assert np.all(np.array(m["intersecting_pairs"]) <= np.array(m["intersecting_pairs_lbs"]))


def test_bench_build_reports_the_cage():
    # speed is reported, never asserted: the row carries the cage's size and its stage times
    from warpskin.bench import run_build_bench

    row = run_build_bench(["arm"])["scenes"]["arm"]
    cage = row["cage"]
    assert cage["render_points"] == 2918 and cage["vertices"] > 1000
    assert cage["build_s"] >= cage["field_and_extraction_s"] > 0
    assert cage["deformation_ms"] > 0 and cage["render_lbs_kernel_ms"] > 0 and cage["render_lbs_vertices"] == 2918
    assert cage["deformation_over_lbs"] == pytest.approx(cage["deformation_ms"] / cage["render_lbs_kernel_ms"])
    assert cage["guard_ms"] > 0 and cage["guard_acting_ms"] > 0


@pytest.mark.slow
def test_robot_expressive_walks_through_its_cage(assets, tmp_path):
    # --cage always: the 14 meshes (the skinned hands, 12 rigid parts) in one cage, simulated;
    # every mesh written with its own vertices, finite, the rigid parts rigid (the cage bound at the rest pose: in the
    # file's bind space it folded, 119 intersecting pairs, and no layer fitted)
    from pxr import Usd, UsdGeom

    from warpskin.cli import main
    from warpskin.io import load_rig

    glb = assets / "RobotExpressive" / "RobotExpressive.glb"
    out = tmp_path / "robot.usdc"
    assert main(["simulate", str(glb), "--clip", "Walking", "--frames", "0:3", "--cage", "always", "--lbs", "-o",
                 str(out), "--quiet"]) == 0
    rig = load_rig(glb)
    stage = Usd.Stage.Open(str(out))
    root = stage.GetDefaultPrim()
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in root.GetChildren() if p.IsA(UsdGeom.Mesh)}
    assert len(meshes) == 29  # 14, the cage guide and with --lbs an LBS guide beside each of the 14
    # each embedded mesh's LBS guide is what `warpskin skin` (the LBS bake) writes for it
    assert main(["skin", str(glb), "--clip", "Walking", "--frames", "0:3", "-o", str(tmp_path / "lbs.usdc")]) == 0
    lbs_stage = Usd.Stage.Open(str(tmp_path / "lbs.usdc"))
    lbs_root = lbs_stage.GetDefaultPrim()
    for a in rig.attachments:
        name = a.name.replace(".", "_")
        guide = meshes[f"{name}_lbs"]
        assert guide.GetPurposeAttr().Get() == UsdGeom.Tokens.guide
        want = np.asarray(UsdGeom.Mesh(lbs_root.GetChild(name)).GetPointsAttr().Get(3), dtype=np.float64)
        np.testing.assert_allclose(np.asarray(guide.GetPointsAttr().Get(3), dtype=np.float64), want,
                                   atol=1e-6 * rig.size())
    expected = {"Hand_R": rig.file_vertex_count, **{a.name.replace(".", "_"): len(a.vertices) for a in rig.attachments}}
    for name, count in expected.items():
        pts = np.asarray(meshes[name].GetPointsAttr().Get(3))
        assert pts.shape == (count, 3) and np.isfinite(pts).all(), name
    from pxr import UsdShade

    assert UsdShade.MaterialBindingAPI(meshes["Head"].GetPrim()).ComputeBoundMaterial()[0] or \
        UsdGeom.Subset.GetAllGeomSubsets(meshes["Head"])  # the embedded parts keep their materials
    # the 12 rigidly parented parts are rigid pieces: each moves as one rigid body with its cage
    # region (every distance within it kept), near its LBS; with --rigid-pieces joint each is its LBS

    def spread(p):
        k = np.linspace(0, len(p) - 1, min(len(p), 80)).astype(int)
        return np.linalg.norm(p[k, None] - p[None, k], axis=2)

    from warpskin.preprocess.cage import character_soup

    body = np.linalg.norm(np.ptp(character_soup(rig).points, axis=0))  # the whole robot's diagonal
    rigid = [a for a in rig.attachments if np.all(a.joint_weights.max(axis=1) >= 0.999)]
    assert len(rigid) == 12
    for a in rigid:
        name = a.name.replace(".", "_")
        got = np.asarray(meshes[name].GetPointsAttr().Get(3), dtype=np.float64)
        want = np.asarray(meshes[f"{name}_lbs"].GetPointsAttr().Get(3), dtype=np.float64)
        assert np.abs(spread(got) - spread(want)).max() < 1e-5 * rig.size(), name
        assert np.linalg.norm(got - want, axis=1).max() < 0.05 * body, name
    out2 = tmp_path / "robot_joint.usdc"
    assert main(["simulate", str(glb), "--clip", "Walking", "--frames", "0:3", "--cage", "always", "--lbs",
                 "--rigid-pieces", "joint", "--preroll", "0", "-o", str(out2), "--quiet"]) == 0  # LBS, however started
    stage2 = Usd.Stage.Open(str(out2))
    root2 = stage2.GetDefaultPrim()
    for a in rigid:
        name = a.name.replace(".", "_")
        got = np.asarray(UsdGeom.Mesh(root2.GetChild(name)).GetPointsAttr().Get(3), dtype=np.float64)
        want = np.asarray(UsdGeom.Mesh(lbs_root.GetChild(name)).GetPointsAttr().Get(3), dtype=np.float64)
        np.testing.assert_allclose(got, want, atol=1e-6 * rig.size(), err_msg=name)


def test_rigid_pieces_are_the_components_that_lbs_moves_rigidly():
    # a soup built to know the answer: in mesh "a", two eyes on joint 2 (one of them with its
    # seams split, copies at one position) and a blob whose one vertex is 0.99 on joint 2; in
    # mesh "b", a ball on joint 1 and one on joint 2; the pieces are per mesh and joint
    from warpskin.preprocess.cage import CharacterSoup, rigid_pieces

    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.1)
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    parts = [("a", v, f, 2), ("a", v[f.ravel()] + 1.0, np.arange(3 * len(f)).reshape(-1, 3), 2),
             ("a", v + 2.0, f, None), ("b", v + 3.0, f, 1), ("b", v + 4.0, f, 2)]
    pts, tris, dense, pieces, start = [], [], [], [], 0
    for k, (mesh, p, t, joint) in enumerate(parts):
        w = np.zeros((len(p), 3))
        if joint is None:
            w[:, 2] = 1.0
            w[5] = [0.0, 0.01, 0.99]
        else:
            w[:, joint] = 1.0
        pts.append(p)
        tris.append(t + start)
        dense.append(w)
        if not pieces or pieces[-1][0] != mesh:
            pieces.append([mesh, start, 0])
        pieces[-1][2] += len(p)
        start += len(p)
    soup = CharacterSoup(np.concatenate(pts), np.concatenate(tris), np.concatenate(dense), [tuple(p) for p in pieces])
    got = rigid_pieces(soup)
    sizes = [len(p[1]) for p in parts]
    part = np.repeat(np.arange(len(parts)), sizes)
    assert len(set(got[(part == 0) | (part == 1)].tolist())) == 1  # both eyes (one seam-split): one piece
    assert np.all(got[part == 2] == -1)  # one vertex at 0.99: bound point by point
    assert len({got[part == 0][0], got[part == 3][0], got[part == 4][0]}) == 3  # per mesh and joint
    assert sorted(set(got.tolist())) == [-1, 0, 1, 2]


def test_a_bad_rigid_pieces_choice_is_refused_before_any_work(tmp_path):
    from warpskin.errors import SceneError
    from warpskin.run import simulate
    from warpskin.scene import load_scene

    with pytest.raises(SceneError, match="rigid_pieces must be 'cage' or 'joint', got 'bones'"):
        simulate(load_scene("arm"), tmp_path / "x.usdc", rigid_pieces="bones", progress=False)
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_robot_pieces_cross_each_other_no_more_than_in_lbs(assets, tmp_path):
    # RobotExpressive dancing through its cage: the torso sways into its right shoulder pad
    # (frames 18-22: 24-46 pairs between the two meshes beyond the rest pose's, where LBS has none),
    # which is now carried by the torso; every piece stays within 1 % of the diagonal of its LBS
    # at its joints. Judged on the written file by the exact pair count of every pair of meshes.
    from pxr import Usd, UsdGeom

    from warpskin.character import Character
    from warpskin.cli import main
    from warpskin.io import load_rig
    from warpskin.quality import CrossPairs, WrittenMesh

    glb = assets / "RobotExpressive" / "RobotExpressive.glb"
    out = tmp_path / "dance.usdc"
    assert main(["simulate", str(glb), "--clip", "Dance", "--frames", "15:22", "--cage", "always", "--lbs", "-o",
                 str(out), "--quiet"]) == 0
    character = Character(load_rig(glb), cage="always")
    meshes = [WrittenMesh(character.display_name(p.name), p.triangles, p.rest, p.file_ids) for p in character.parts]
    cross = CrossPairs(meshes)
    stage = Usd.Stage.Open(str(out))
    root = stage.GetDefaultPrim()
    diagonal = float(np.linalg.norm(np.ptp(character.soup.points, axis=0)))

    def points(name, t):
        return np.asarray(UsdGeom.Mesh(root.GetChild(name)).GetPointsAttr().Get(t), dtype=np.float64)

    for t in range(15, 23):
        written = {m.name: points(m.name, t) for m in meshes}
        lbs = {m.name: points(f"{m.name}_lbs", t) for m in meshes}
        keys, keys_lbs = cross.keys_of_two(written, lbs)
        assert (cross.beyond_rest(keys) <= cross.beyond_rest(keys_lbs)).all(), t
        for m in meshes:
            assert np.linalg.norm(written[m.name] - lbs[m.name], axis=1).max() <= 0.01 * diagonal * (1 + 1e-4), \
                (t, m.name)


@pytest.mark.slow
def test_bench_times_what_simulate_simulates_on_an_open_character(tmp_path):
    # the shipped mannequin is open (its pieces are capped and simulated): the bench times the
    # same surface simulate steps, not the open skin (which has no closed surface to time)
    from warpskin.bench import run_solver_bench

    row = run_solver_bench(["mannequin"], device="cpu", steps=1, repeat=1, frames_timed=2)["scenes"]["mannequin"]
    assert "error" not in row, row
    # timed in a state the simulation reaches (the clip stepped from its start), not one the
    # timing loops crumpled (the bench's loops once drove a state to 15k pairs): about LBS's
    # crossings at that time (its pieces cross at rest and slide, by up to a quarter: limits)
    assert row["warmup_frames"] > 1 and row["intersecting_pairs"] <= 1.25 * row["intersecting_pairs_lbs"]
    # the bench's own simulate run there (one frame stepped) simulated as many particles
    assert row["simulate_particles"] == row["particles"] and row["simulate_frames"] == 2
    assert row["total_ms"] > 0 and row["total_graph_ms"] > 0
    # a frame is its steps and the host's work around them: more than its steps, the share in (0, 1)
    assert row["simulate_frame_ms"] > row["simulate_steps_ms"] > 0 and 0 < row["host_share"] < 1
    assert row["host_share"] == pytest.approx(1 - row["simulate_steps_ms"] / row["simulate_frame_ms"], rel=1e-9)
    # a step in plain launches launches kernels; a frame replays its graph (one launch) and reads
    # the state back at least once
    assert row["launches_per_step"] > 10 and row["launches_per_frame"] >= 1 and row["readbacks_per_frame"] >= 1
    # the bytes a step's launches take hold the elasticity loop's (the step runs that loop);
    # the rates are those bytes over the timings, against the copy's bandwidth
    assert row["step_bytes"] > row["elasticity_bytes"] > 0
    assert row["elasticity_gbs"] == pytest.approx(row["elasticity_bytes"] / row["elasticity_ms"] / 1e6, rel=1e-9)
    assert 0 < row["step_bandwidth_share"] < 10

"""Popping on the written surface (an open character through its cage): the swelling's closed
form, its first-order volume, its reach, the paper's per-point vibration against NumPy, the
clearance to another surface, and ``warpskin pop`` on an open multi-piece character."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from pxr import Usd, UsdGeom

from characters import mannequin_file
from test_characters import _assert_keeps_its_surface, written_quality
from warpskin.cli import main
from warpskin.popping.activation import clench_table
from warpskin.popping.surface import SurfacePop, belly_of_groups, surface_swelling
from warpskin.preprocess.bones import Bones

R = 0.0473  # [m] the tube's radius (generic)
L = 0.3117  # [m] every bone's length


def _tube(bones: int, segments: int = 37, rings_per_bone: int = 29, radius: float = R, lengths=None):
    """An open tube along +y over ``bones`` bones (lengths ``lengths``, default ``L`` each;
    joint k where they add up), each ring skinned wholly to the bone it lies on (rings off the
    joints: no tie)."""
    lengths = np.full(bones, L) if lengths is None else np.asarray(lengths, dtype=np.float64)
    joints = np.concatenate([[0.0], np.cumsum(lengths)])
    y = np.concatenate([joints[k] + (np.arange(rings_per_bone) + 0.5) * lengths[k] / rings_per_bone
                        for k in range(bones)])
    a = 2.0 * np.pi * (np.arange(segments) + 0.25) / segments
    pts = np.array([(radius * np.cos(u), yy, radius * np.sin(u)) for yy in y for u in a])
    tris = []
    for r in range(len(y) - 1):
        for s in range(segments):
            i, j = r * segments + s, r * segments + (s + 1) % segments
            tris += [(i, j + segments, j), (i, i + segments, j + segments)]
    weights = np.zeros((len(pts), bones + 1))
    weights[np.arange(len(pts)), np.clip(np.searchsorted(joints, pts[:, 1]) - 1, 0, bones - 1)] = 1.0
    start = np.array([(0.0, joints[k], 0.0) for k in range(bones)] + [(0.0, joints[-1], 0.0)])
    end = np.array([(0.0, joints[k + 1], 0.0) for k in range(bones)] + [(0.0, joints[-1] + L, 0.0)])
    skeleton = Bones(start=start, end=end, joint_names=[f"b{k}" for k in range(bones + 1)])
    parents = np.arange(bones + 1) - 1
    return pts, np.array(tris), weights, skeleton, parents


def _profile(t):
    """The belly along the bone, in closed form: 0 to 10 %, smoothstep up to 1 at 30 %, 1 to 70 %,
    down to 0 at 90 %."""
    t = np.asarray(t, dtype=np.float64)
    up, down = np.clip((t - 0.1) / 0.2, 0, 1), np.clip((0.9 - t) / 0.2, 0, 1)
    return (3 * up ** 2 - 2 * up ** 3) * (3 * down ** 2 - 2 * down ** 3)


def _outward_normal_flux(points, tris, field) -> float:
    """sum over the surface of (displacement . normal) dA, by trimesh's face areas and normals."""
    mesh = trimesh.Trimesh(points, tris, process=False)
    flux = 0.0
    for k in range(3):
        flux += np.sum(mesh.area_faces / 3.0 * np.einsum("ij,ij->i", field[tris[:, k]], mesh.face_normals))
    return float(flux)


def test_the_belly_is_the_closed_form_and_the_thinning_keeps_the_volume():
    # bones b0 (parent), b1 (the group), b2 (child), b3 (beyond the neighbourhood); the parent
    # and child long enough that the thinning stays well under its cap (a quarter of the peak)
    pts, tris, w, bones, parents = _tube(4, lengths=[1.6 * L, L, 1.4 * L, L], rings_per_bone=31)
    swell = 0.15  # the tube stretches by 0.15 * 0.8 < 25 % around: the stretch limit is not reached
    muscles, field = surface_swelling(pts, tris, w, bones, parents, [("biceps", [1])], swell=swell)
    (m,), f = muscles, field[0]
    # the depth: 0.8 of the way to the bone, but no deeper than half the tube is thick (the
    # 37-gon's vertex to the edge across: R (1 + cos(pi / 37)))
    half = 0.5 * R * (1.0 + np.cos(np.pi / 37))
    assert m.name == "biceps" and m.joints == ["b1"] and m.depth_m == pytest.approx(0.8 * half, rel=1e-5)
    t = (pts[:, 1] - 1.6 * L) / L
    radial = pts * np.array([1.0, 0.0, 1.0])
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    out = np.einsum("ij,ij->i", f, radial)
    # along the surface's normal, radial on the tube: to within 0.1 degree (its triangulation)
    # but near the open end, where the normal leans out of the tube (over the 4 rings that the
    # direction is eased over)
    inner = pts[:, 1] > 6 * 1.6 * L / 31
    side = np.linalg.norm(f - out[:, None] * radial, axis=1)
    assert np.all(side[inner] <= np.sin(np.radians(0.1)) * np.abs(out[inner]) + 1e-15)
    # the belly (where the profile is 1, no thinning there) is swell * depth, closed form
    on = (t > 0) & (t < 1)
    depth = np.full(len(pts), 0.8 * half)
    mid = on & (_profile(np.clip(t, 0, 1)) > 0.999)
    assert mid.any()
    assert np.allclose(out[mid], swell * depth[mid] * _profile(t[mid]), rtol=2e-3)
    # elsewhere on the bone it is the profile less one thinning depth times (1 - profile)
    p = _profile(np.clip(t, 0, 1))
    sel = on & (p > 0.05) & (p < 0.95)
    thin = (swell * depth * p - out)[sel] / (1.0 - p[sel])
    assert np.ptp(thin) < 1e-4 * thin.mean() and 0.0 < thin[0] < 0.25 * swell * 0.8 * half  # (float32 rays)
    # first-order volume: the flux through the tube is zero (the thinning is not capped here)
    gain = _outward_normal_flux(pts, tris, np.where(on[:, None], (swell * depth * p)[:, None] * radial, 0.0))
    assert gain > 0.0
    assert abs(_outward_normal_flux(pts, tris, f)) < 1e-6 * gain
    # the skin of the bone beyond the child is not the neighbourhood's: it never moves
    assert np.all(f[pts[:, 1] > 4 * L] == 0.0)


def test_a_piece_near_the_belly_keeps_it_from_moving_there():
    pts, tris, w, bones, parents = _tube(3)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.0311)
    centre = np.array([R + 0.0217, 1.5 * L, 0.0])  # beside the belly, cutting into the tube
    ball = sphere.vertices + centre
    # and a plate straight ahead of the belly's other side, nearer than its peak
    peak = 0.15 * 0.8 * R
    x = -(R + 0.71 * peak)
    plate = np.array([(x, 1.35 * L, -0.4 * R), (x, 1.65 * L, -0.4 * R), (x, 1.65 * L, 0.4 * R), (x, 1.35 * L, 0.4 * R)])
    all_pts = np.concatenate([pts, ball, plate])
    all_tris = np.concatenate([tris, sphere.faces + len(pts), np.array([(0, 1, 2), (0, 2, 3)]) + len(pts) + len(ball)])
    other_w = np.zeros((len(ball) + 4, w.shape[1]))
    other_w[:, 0] = 1.0  # carried by another bone
    muscles, field = surface_swelling(all_pts, all_tris, np.concatenate([w, other_w]), bones, parents,
                                      [("biceps", [1])], swell=0.15)
    d = field[0][: len(pts)]
    f = np.linalg.norm(d, axis=1)
    gap = np.linalg.norm(pts - centre, axis=1) - 0.0311  # to the sphere (within 0.3 % of its radius)
    after = np.linalg.norm(pts + d - centre, axis=1) - 0.0311
    # the swelling never crosses the ball's surface: the tube outside it stays out by most of
    # its gap (a point moves towards the ball by at most a third of its distance to what lies
    # ahead of it), the tube inside it stays in (0.1 mm for the search's samples, an eighth of
    # the ball's 4 mm edges apart)
    out, inside = (gap > 0.0) & (gap < 3.0 * peak), gap < 0.0
    assert out.sum() > 10 and inside.sum() > 5
    assert np.all(after[out] >= 0.5 * gap[out] - 1e-4) and np.all(after[inside] < 1e-4)
    assert np.count_nonzero(f[out] > 0.1 * peak) > 5  # the ball beside a point does not hold it
    # straight under the plate nothing moves (it is nearer than the belly is high)
    under = (np.abs(pts[:, 1] - 1.5 * L) < 0.1 * L) & (pts[:, 0] < -0.9 * R) & (np.abs(pts[:, 2]) < 0.2 * R)
    assert under.sum() > 5 and np.all(f[under] == 0.0)
    far = (gap > 3.2 * peak) & (np.abs(pts[:, 1] - 1.5 * L) < 0.05 * L) & (pts[:, 0] > -0.3 * R)
    assert far.any() and np.all(f[far] > 0.9 * peak)  # away from both, the belly is whole


def test_groups_that_pop_together_thin_off_each_others_bellies():
    # b1 and its child b2 both swell: b1's thinning may lie on b2's skin, but not on its belly
    # (else popping both would take back part of b2's swelling); b2's likewise off b1's belly;
    # each group's flux is still zero where its thinning finds room (b0 and b3 are long)
    pts, tris, w, bones, parents = _tube(4, lengths=[2.4 * L, L, L, 2.4 * L], rings_per_bone=31)
    _, field = surface_swelling(pts, tris, w, bones, parents, [("a", [1]), ("b", [2])], swell=0.15)
    y = pts[:, 1]
    t1, t2 = (y - 2.4 * L) / L, (y - 3.4 * L) / L
    belly1, belly2 = (t1 > 0.3) & (t1 < 0.7), (t2 > 0.3) & (t2 < 0.7)
    assert belly1.any() and belly2.any()
    assert np.all(field[0][belly2] == 0.0) and np.all(field[1][belly1] == 0.0)
    # what each thins lies between the bellies and beyond them, radially inward
    radial = pts * np.array([1.0, 0.0, 1.0])
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    out = [np.einsum("ij,ij->i", f, radial) for f in field]
    assert out[0][(t2 > 0.0) & (t2 < 0.1)].max() < 0.0 and out[1][(t1 > 0.9) & (t1 < 1.0)].max() < 0.0
    for o, f in zip(out, field):
        gain = _outward_normal_flux(pts, tris, np.maximum(o, 0.0)[:, None] * radial)
        assert gain > 0.0 and abs(_outward_normal_flux(pts, tris, f)) < 1e-6 * gain


def test_no_edge_stretches_more_than_a_quarter():
    pts, tris, w, bones, parents = _tube(3, segments=9, rings_per_bone=7)  # a coarse tube
    _, field = surface_swelling(pts, tris, w, bones, parents, [("biceps", [1])], swell=1.3)
    x = pts + field[0]
    e = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    ratio = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1)
    assert np.abs(ratio - 1.0).max() <= 0.25 + 1e-9
    assert np.abs(ratio - 1.0).max() > 0.2  # and it still swells as far as that allows


def _reference_vibration(disparity, activation, alpha_min, beta, h, threshold):
    """Son & Han eqs. 1-4 per point in NumPy: the offsets after every step ``[S, N, 3]``."""
    g, n = disparity.shape[:2]
    lengths = np.linalg.norm(disparity, axis=2)  # [G, N]
    group = np.argmax(lengths, axis=0)
    dist = lengths[group, np.arange(n)]
    top = lengths.max(axis=1)
    alpha = np.where(top[group] > 0, (alpha_min - 1.0) * np.minimum(dist / np.where(top[group] > 0, top[group], 1), 1)
                     + 1.0, 1.0)
    o, u = np.zeros((n, 3)), np.zeros((n, 3))
    prev, clench = np.zeros(g), np.zeros(g, dtype=bool)
    out = []
    for a in activation:
        clench = np.where(a > prev, True, np.where(a < prev, False, clench))
        prev = a
        goal = np.einsum("g,gnc->nc", a, disparity)
        for i in range(n):
            if clench[group[i]]:
                u[i] = (1.0 - alpha[i]) * u[i] + alpha[i] / h * (goal[i] - o[i])
                o[i] = o[i] + h * u[i]
            else:
                o[i] = o[i] + beta * h * (goal[i] - o[i])
                u[i] = 0.0
                if np.linalg.norm(goal[i] - o[i]) < threshold:
                    o[i] = goal[i]
        out.append(o.copy())
    return np.array(out)


def test_the_points_vibrate_by_the_papers_rules(device):
    rng = np.random.default_rng(7)
    disparity = rng.normal(size=(2, 5, 3)) * 0.004
    disparity[1, :2] = 0.0
    h, steps = 1.0 / 240.0, 80
    times = (np.arange(steps) + 1) * h
    acts = np.stack([(times > 0.021) & (times < 0.151), (times > 0.0433) & (times < 0.0917)], axis=1) * \
        np.array([1.0, 0.7])
    table = {round(t, 9): a for t, a in zip(times, acts)}
    weights = np.zeros((5, 2))
    weights[:, 0] = 1.0
    pop = SurfacePop(disparity, weights, np.tile(np.eye(4), (2, 1, 1)), times, lambda t: table[round(t, 9)], h=h,
                     alpha_min=0.13, beta=30.0, threshold=1e-5, device=device)
    ref = _reference_vibration(disparity, acts, 0.13, 30.0, h, 1e-5)
    got = []
    for _ in range(steps):
        pop.advance(1)
        got.append(pop.offsets(np.tile(np.eye(4), (2, 1, 1))))
    assert np.allclose(np.array(got), ref, atol=2e-6)
    assert np.abs(ref).max() > 1e-3 and ref[40:].std() > 0  # it moved, and it rang
    assert np.array_equal(clench_table(acts), np.where(
        np.stack([(times > 0.021) & (times < 0.151), (times > 0.0433) & (times < 0.0917)], axis=1), 1.0, 0.0))
    # posed: the rest-pose offset is carried by the point's skinning, L(t) L_rest^-1 o
    turn = np.eye(4)
    turn[:3, :3] = trimesh.transformations.rotation_matrix(0.6, [0, 0, 1])[:3, :3]
    rest = np.tile(np.eye(4), (2, 1, 1))
    rest[1, :3, :3] = trimesh.transformations.rotation_matrix(-0.2, [1, 0, 0])[:3, :3]
    weights[:, :] = [[0.7, 0.3]]
    pop = SurfacePop(disparity, weights, rest, times, lambda t: table[round(t, 9)], h=h, alpha_min=0.13, beta=30.0,
                     threshold=1e-5, device=device)
    pop.advance(30)
    posed = np.stack([turn, np.eye(4)])
    blend = lambda m: 0.7 * m[0, :3, :3] + 0.3 * m[1, :3, :3]  # noqa: E731
    want = (blend(posed) @ np.linalg.inv(blend(rest)) @ ref[29].T).T
    assert np.allclose(pop.offsets(posed), want, atol=2e-6)


def test_an_offset_stops_at_half_the_gap_to_a_surface(device):
    # a patch pushed towards a wall 13.1 mm above it keeps half the gap less the margin
    g = np.linspace(-0.01, 0.01, 4)
    patch = np.array([(x, y, 0.0) for y in g for x in g])
    ptris = np.array([(r * 4 + c, r * 4 + c + 1, r * 4 + c + 5) for r in range(3) for c in range(3)]
                     + [(r * 4 + c, r * 4 + c + 5, r * 4 + c + 4) for r in range(3) for c in range(3)])
    wall = np.array([(-0.1, -0.1, 0.0131), (0.1, -0.1, 0.0131), (0.1, 0.1, 0.0131), (-0.1, 0.1, 0.0131)])
    points = np.concatenate([patch, wall])
    tris = np.concatenate([ptris, np.array([(0, 1, 2), (0, 2, 3)]) + 16])
    disparity = np.zeros((1, 20, 3))
    disparity[0, :16, 2] = 0.0202
    weights = np.zeros((20, 1))
    weights[:, 0] = 1.0
    eye = np.eye(4)[None]
    pop = SurfacePop(disparity, weights, eye, [0.01] * 3, lambda t: np.ones(1), h=0.01, alpha_min=1.0, beta=30.0,
                     triangles=tris, margin=0.0004, start=1e-6, device=device)
    pop.advance(3)  # alpha 1: on the goal at once
    free = pop.offsets(eye)
    assert np.allclose(free[:16, 2], 0.0202, atol=1e-7)
    held = pop.offsets(eye, points)
    assert np.allclose(held[:16, 2], 0.5 * 0.0131 - 0.0004, atol=2e-6)
    assert np.all(held[16:] == 0.0) and pop.held == pytest.approx(1.0 - (0.5 * 0.0131 - 0.0004) / 0.0202, abs=1e-4)


def _child(names, parents, j: int) -> int:
    """The joint a limb bone ends at: its child with the same side suffix."""
    return int(next(k for k in np.nonzero(np.asarray(parents) == j)[0] if names[k][-2:] == names[j][-2:]))


def _meshes(stage):
    root = stage.GetDefaultPrim()
    return {p.GetName(): UsdGeom.Mesh(p) for p in root.GetChildren() if p.IsA(UsdGeom.Mesh)}


@pytest.mark.slow
def test_an_open_character_pops_on_its_written_surface(tmp_path, capsys, device):
    # the open mannequin (37 pieces, shoes and fists) on its own pieces: the beat at 0.2037 s
    # (between frames 6 and 7 at 30 fps, off every step), held 0.25 s
    from warpskin.rig import Clip
    from warpskin.scene import Scene

    glb = mannequin_file(tmp_path)
    scene = tmp_path / "mannequin.toml"  # a tenth of a second's pre-roll (the file's default: half a second)
    scene.write_text('[rig]\nfile = "mannequin.glb"\n[animation]\nclip = "walk"\npreroll = 0.1\n')
    out = tmp_path / "pop.usdc"
    assert main(["pop", str(scene), "--clip", "walk", "--frames", "0:9", "--bpm", "120", "--offset", "0.2037",
                 "--quiet", "--device", device, "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["pop_on"] == "surface" and summary["surface"]["kind"] == "pieces"
    stage = Usd.Stage.Open(str(out))
    meshes = _meshes(stage)
    assert {"body", "body_normal", "body_lbs"} <= set(meshes)
    assert meshes["body_normal"].GetPrim().GetCustomDataByKey("warpskin:role") == "normal"
    rig = Scene.from_rig_file(glb).rig()
    body, normal = meshes["body"], meshes["body_normal"]
    codes = body.GetPointsAttr().GetTimeSamples()
    x = np.array([np.asarray(body.GetPointsAttr().Get(c), dtype=np.float64) for c in codes])
    n = np.array([np.asarray(normal.GetPointsAttr().Get(c), dtype=np.float64) for c in codes])
    assert np.array_equal(x[:7], n[:7])  # nothing before the beat
    # each group's belly: the file vertices on the middle of its bone (dominant joint; foot
    # between 30 % and 70 % of it), out along the normal-only skin's normals by 20 % of the
    # depth there at least, within one frame of the beat
    faces = np.asarray(body.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    rest = np.asarray(body.GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    names = list(rig.skeleton.joint_names)
    joints = rig.joint_world_transforms(Clip("rest"), 0.0)[:, :3, 3]
    dom = rig.joint_indices[np.arange(rig.vertex_count), np.argmax(rig.joint_weights, axis=1)][rig.weld_map]
    out_by_frame = np.array([np.einsum("ij,ij->i", x[k] - n[k], trimesh.Trimesh(n[k], faces, process=False)
                                       .vertex_normals) for k in range(len(codes))])
    limbs = [m for m in summary["muscles"] if m["name"] != "chest"]  # the chest: a rounded box, no limb
    assert len(limbs) == 8
    for m in limbs:
        j = names.index(m["joints"][0])
        a, b = joints[j], joints[_child(names, rig.skeleton.parents, j)]
        axis = (b - a) / np.linalg.norm(b - a)
        t = np.einsum("ij,j->i", rest - a, axis) / np.linalg.norm(b - a)
        belly = (dom == j) & (t > 0.3) & (t < 0.7)
        depth = 0.8 * np.linalg.norm(np.cross(rest[belly] - a, axis), axis=1)
        bulge = out_by_frame[7:9, belly].mean(axis=1).max()
        assert bulge > 0.2 * np.median(depth), m["name"]
    # the skin of bones more than two away from every group never moves
    far = np.isin(dom, [names.index("head"), names.index("toe_l"), names.index("toe_r")])
    assert far.any() and np.array_equal(x[:, far], n[:, far])
    q = written_quality(out)
    _assert_keeps_its_surface({k: v for k, v in q.items() if not k.endswith("_normal")}, 10, sliding=True)
    # the guide is what `warpskin simulate` writes of the same frames (bit for bit on the CPU)
    plain = tmp_path / "plain.usdc"
    assert main(["simulate", str(scene), "--clip", "walk", "--frames", "0:9", "--quiet", "--device", device,
                 "-o", str(plain)]) == 0
    alone = Usd.Stage.Open(str(plain))
    skin = _meshes(alone)["body"].GetPointsAttr()
    for k, c in enumerate(codes):
        a = np.asarray(skin.Get(c))
        if device == "cpu":
            assert np.array_equal(a, n[k].astype(np.float32))
        else:  # atomics order the contacts differently from run to run on a GPU
            np.testing.assert_allclose(a, n[k], atol=1e-4 * rig.size())


def test_a_belly_pressed_on_one_side_swells_more_on_the_other(device):
    # a patch swelled outward (+z) by one group; a corner of it held back to 60 %: the held
    # outward volume (area x offset, trimesh's vertex areas) is spread over the rest, the free
    # points taking it whole and the held ones by their kept share to the fourth
    g = np.linspace(-0.02, 0.02, 6) + np.array([0, 0.0013, -0.0007, 0.0011, 0.0004, 0])
    points = np.array([(x, y, 0.0) for y in g for x in g])
    tris = np.array([(r * 6 + c, r * 6 + c + 1, r * 6 + c + 7) for r in range(5) for c in range(5)]
                    + [(r * 6 + c, r * 6 + c + 7, r * 6 + c + 6) for r in range(5) for c in range(5)])
    disparity = np.zeros((1, 36, 3))
    disparity[0, :, 2] = 0.004 + 0.001 * np.sin(np.arange(36))
    weights = np.ones((36, 1))
    eye = np.eye(4)[None]
    pop = SurfacePop(disparity, weights, eye, [0.01] * 2, lambda t: np.ones(1), h=0.01, alpha_min=1.0, beta=30.0,
                     triangles=tris, points=points, device=device)
    pop.advance(2)
    world = pop.offsets(eye)
    kept = np.where((points[:, 0] < -0.005) & (points[:, 1] < -0.005), 0.6, 1.0)
    area = trimesh.Trimesh(points, tris, process=False).area_faces
    vertex_area = np.zeros(36)
    for k in range(3):
        np.add.at(vertex_area, tris[:, k], area / 3.0)
    size = vertex_area * np.linalg.norm(world, axis=1)
    extra = min(np.sum(size * (1 - kept)) / np.sum(size * kept), 0.6)
    assert 0.0 < extra < 0.6  # not at the cap
    rest = pop.offset.numpy().astype(np.float64)  # the rest-pose offsets (outward: along the swelling)
    np.testing.assert_allclose(pop._pressed(rest, world, kept), 1.0 + extra * kept ** 4, rtol=1e-9)
    # pressed hard (a fifth kept on most of it), the free side takes at most 60 % more
    hard = np.where(points[:, 0] < 0.01, 0.2, 1.0)
    np.testing.assert_allclose(pop._pressed(rest, world, hard), 1.0 + 0.6 * hard ** 4, rtol=1e-9)


def test_a_limb_mesh_bunched_at_one_end_pops_where_its_surface_is():
    # a tube over 75-115 % of its bone (a stylised rig's upper arm: a ball at the elbow), and one
    # along its whole bone: the first is measured along the surface it carries, the second along
    # the bone
    from warpskin.popping.surface import bone_coordinates

    def point_areas(points, faces):  # a third of each incident triangle's area, by trimesh
        mesh = trimesh.Trimesh(points, faces, process=False)
        out = np.zeros(len(points))
        for k in range(3):
            np.add.at(out, faces[:, k], mesh.area_faces / 3.0)
        return out

    pts, tris, w, bones, parents = _tube(1, rings_per_bone=41)
    whole_t, _ = bone_coordinates(pts, np.zeros(len(pts), dtype=int), bones, point_areas(pts, tris))
    np.testing.assert_allclose(whole_t, np.clip(pts[:, 1] / L, 0, 1), rtol=1e-12, atol=1e-15)
    bunched = pts.copy()
    bunched[:, 1] = 0.75 * L + 0.4 * pts[:, 1]  # raw 0.75 .. 1.15
    t, radial = bone_coordinates(bunched, np.zeros(len(pts), dtype=int), bones, point_areas(bunched, tris))
    raw = bunched[:, 1] / L
    assert np.all(np.diff(t[np.argsort(raw)]) >= 0.0)  # still in order along the bone
    assert abs(np.median(raw[np.abs(t - 0.5) < 0.02]) - 0.95) < 0.01  # the middle: the surface's median
    assert t.min() == 0.0 and t.max() == 1.0
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), R, rtol=1e-12)  # square to the bone
    belly = belly_of_groups(bunched, tris, np.ones((len(pts), 1)), bones, [("arm", [0])])[0]
    assert np.array_equal(belly, (t > 0.3) & (t < 0.7)) and 0.3 < belly.mean() < 0.5


def test_a_surface_cut_into_pieces_pops_across_its_seams():
    # the tube cut across its belly into two pieces 0.1 mm apart (a body split by material):
    # the cut's two border rings are a seam, the pieces are one surface, and the belly runs
    # over the cut as on the whole tube
    from warpskin.popping.surface import seam_points

    pts, tris, w, bones, parents = _tube(3)
    ring_y = np.unique(pts[:, 1])
    cut_y = ring_y[np.searchsorted(ring_y, 1.5 * L)]  # a ring near mid-bone: both pieces hold it
    on_cut = np.nonzero(pts[:, 1] == cut_y)[0]
    copy = np.arange(len(pts))
    copy[on_cut] = len(pts) + np.arange(len(on_cut))  # the upper piece's own copy of that ring
    upper_tri = (pts[tris, 1] >= cut_y).all(axis=1)
    cut_tris = np.where(upper_tri[:, None], copy[tris], tris)
    cut_pts = np.concatenate([pts, pts[on_cut]])
    cut_pts[(cut_pts[:, 1] > cut_y) | (np.arange(len(cut_pts)) >= len(pts))] += [0.0, 1e-4, 0.0]
    cut_w = np.concatenate([w, w[on_cut]])
    seam = seam_points(cut_pts, cut_tris)
    assert seam.sum() == 2 * 37 and np.all(np.abs(cut_pts[seam, 1] - cut_y) < 2e-4)  # the cut's two rings
    _, whole = surface_swelling(pts, tris, w, bones, parents, [("biceps", [1])], swell=0.15)
    _, cut = surface_swelling(cut_pts, cut_tris, cut_w, bones, parents, [("biceps", [1])], swell=0.15)
    cut = cut[:, : len(pts)]
    near = np.abs(pts[:, 1] - cut_y) < 0.05 * L
    peak = 0.15 * 0.8 * R
    assert np.all(np.linalg.norm(cut[0][near], axis=1) > 0.9 * peak)
    np.testing.assert_allclose(np.linalg.norm(cut[0][near], axis=1), np.linalg.norm(whole[0][near], axis=1),
                               rtol=0.05)


def test_the_bulge_is_measured_on_the_surface_of_a_flat_shaded_mesh(tmp_path):
    # a hexagonal tube whose every triangle has its own corners (flat shading, as glTF writes
    # it), moved out radially by delta: the report's bulge is delta (the corners' own facet
    # normals lie 30 degrees off the radial and would read delta * cos 30)
    from pxr import Vt

    from warpskin.popping.report import bulge_series

    pts, tris, *_ = _tube(1, segments=6, rings_per_bone=5)
    soup = pts[tris.ravel()]  # three corners of its own per triangle
    faces = np.arange(len(soup)).reshape(-1, 3)
    radial = soup * np.array([1.0, 0.0, 1.0])
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    delta = 0.00731
    path = tmp_path / "bake.usda"
    stage = Usd.Stage.CreateNew(str(path))
    root = UsdGeom.Xform.Define(stage, "/char")
    stage.SetDefaultPrim(root.GetPrim())
    for name, role, offset in (("skin", "skin", delta), ("skin_normal", "normal", 0.0)):
        mesh = UsdGeom.Mesh.Define(stage, f"/char/{name}")
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(faces)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(faces.ravel().tolist()))
        mesh.GetPrim().SetCustomDataByKey("warpskin:role", role)
        for tc in (0.0, 1.0):
            mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy((soup + tc * offset * radial).astype(np.float32)), tc)
    stage.GetRootLayer().Save()
    middle = np.abs(soup[:, 1] - 0.5 * L) < 0.3 * L
    codes, bulge = bulge_series(path, {"biceps": middle})
    assert codes.tolist() == [0.0, 1.0]
    assert abs(bulge["biceps"][0]) < 1e-7 and bulge["biceps"][1] == pytest.approx(delta, rel=1e-4)


def _soup(pts, tris):
    """The mesh flat-shaded as glTF writes it: every triangle its own three corners."""
    return pts[tris.ravel()], np.arange(3 * len(tris)).reshape(-1, 3)


def test_the_copies_of_a_flat_shaded_corner_are_written_together(device):
    # a flat-shaded tube (six copies of most corners) whose belly swells against a plate near
    # one side: the clearance holds part of the belly back, and every copy of one corner
    # must still be written at one place, or the shading splits into cracks
    pts, tris, w, bones, parents = _tube(1, segments=11, rings_per_bone=13)
    _, field = surface_swelling(pts, tris, w, bones, parents, [("biceps", [0])], swell=0.6)
    soup, faces = _soup(pts, tris)
    x = R + 0.37 * np.abs(field).max()  # a plate beside the belly, closer than its peak
    plate = np.array([(x, 0.2 * L, -0.5 * R), (x, 0.8 * L, -0.5 * R), (x, 0.8 * L, 0.5 * R), (x, 0.2 * L, 0.5 * R)])
    points = np.concatenate([soup, plate])
    all_tris = np.concatenate([faces, np.array([(0, 1, 2), (0, 2, 3)]) + len(soup)])
    disparity = np.concatenate([field[:, tris.ravel()], np.zeros((1, 4, 3))], axis=1)
    weights = np.concatenate([w[tris.ravel()], np.tile(w[:1], (4, 1))])
    h, steps = 1.0 / 240.0, 48
    times = (np.arange(steps) + 1) * h
    eye = np.tile(np.eye(4), (2, 1, 1))
    pop = SurfacePop(disparity, weights, eye, times, lambda t: np.array([1.0 if t > 0.011 else 0.0]), h=h,
                     alpha_min=0.1, beta=30.0, triangles=all_tris, margin=1e-4, start=1e-6, points=points,
                     mesh_of_point=np.r_[np.zeros(len(soup), dtype=int), np.ones(4, dtype=int)], device=device)
    corner = tris.ravel()  # each soup point's corner on the welded tube
    gaps, held = [], []
    for _ in range(steps // 4):
        pop.advance(4)
        out = pop.offsets(eye, points)[: len(soup)]
        spread = np.zeros(len(pts))
        for axis in range(3):  # per corner, the spread of its copies' offsets (brute force)
            hi = np.full(len(pts), -np.inf)
            lo = np.full(len(pts), np.inf)
            np.maximum.at(hi, corner, out[:, axis])
            np.minimum.at(lo, corner, out[:, axis])
            spread = np.maximum(spread, hi - lo)
        gaps.append(spread.max())
        free = pop.offsets(eye)[: len(soup)]
        # under the plate (the belly's side that faces it): the offset it took back there (the
        # free side may swell more: a belly pressed on one side)
        under = (soup[:, 0] > 0.5 * R) & (soup[:, 1] > 0.2 * L) & (soup[:, 1] < 0.8 * L)
        held.append(float((np.linalg.norm(free, axis=1) - np.linalg.norm(out, axis=1))[under].max()))
    assert max(gaps) < 1e-7  # [m]: the copies move as one corner
    assert max(held) > 0.2 * np.abs(field).max()  # and the plate did hold the belly back


def test_the_written_vibration_never_folds_a_facet_nor_stretches_an_edge_past_one_and_a_half(device):
    # on a coarse tube, one point pushed out along its normal by most of an edge's length and
    # one pushed along the tube past its neighbours, ringing with the paper's stiffness: the
    # offsets as stepped fold facets and stretch edges past 1.5x; the written skin keeps every
    # facet facing as at rest (at least 0.3 of its area) and every edge within 1.5x
    pts, tris, w, bones, parents = _tube(1, segments=9, rings_per_bone=7)
    ring = L / 7
    spike, slide = 3 * 9 + 2, 4 * 9 + 6  # two points of the middle rings, generic, apart
    field = np.zeros((1, len(pts), 3))
    field[0, spike] = 0.9 * ring * pts[spike] * [1, 0, 1] / R
    field[0, slide, 1] = 1.3 * ring
    h, steps = 1.0 / 240.0, 40
    times = (np.arange(steps) + 1) * h
    eye = np.tile(np.eye(4), (2, 1, 1))
    pop = SurfacePop(field, w, eye, times, lambda t: np.array([1.0 if t > 0.006 else 0.0]), h=h, alpha_min=0.1,
                     beta=30.0, triangles=tris, margin=1e-4, start=1e-6, points=pts, device=device)
    e = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    rest_normal = np.cross(pts[tris[:, 1]] - pts[tris[:, 0]], pts[tris[:, 2]] - pts[tris[:, 0]])

    def measure(out):
        x = pts + out
        ratio = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1) / np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1)
        moved = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
        kept = np.einsum("ij,ij->i", moved, rest_normal) / np.einsum("ij,ij->i", rest_normal, rest_normal)
        return np.abs(np.log(ratio)).max(), kept.min()

    free, written = [], []
    for _ in range(steps):
        pop.advance(1)
        free.append(measure(pop.offsets(eye)))
        written.append(measure(pop.offsets(eye, pts)))
    free, written = np.array(free), np.array(written)
    assert free[:, 0].max() > np.log(1.6) and free[:, 1].min() < 0.0  # as stepped: stretched, folded
    # the guard puts the ringing edges on the band's edge (to rounding): a 1e-6 band there
    assert written[:, 0].max() < np.log(1.5) + 1e-6 and written[:, 1].min() > 0.3 - 1e-6
    assert written[:, 0].max() > np.log(1.3)  # and still moved as far as that allows


def test_a_sliver_that_would_fold_keeps_half_its_area_facing_as_at_rest():
    # two slivers back to back on one base; the first one's apex pushed across the base turns
    # it over with no edge changing length, so only the fold rule can hold it: the apex keeps
    # the largest factor on the rule's grid (sixteenths) under the closed form, where the
    # sliver's area along its rest normal, 1 - s * 0.1037 / 0.05, is half
    from scipy import sparse

    from warpskin.popping.surface import _KEEP, _stretch_limit
    from warpskin.preprocess.fast_summation import vertex_adjacency

    pts = np.array([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.5, 0.05, 0.0), (0.5, -0.05, 0.0)])
    tris = np.array([(0, 1, 2), (0, 3, 1)])
    field = np.zeros((4, 3))
    field[2, 1] = -0.1037
    edges = np.array([(0, 1), (0, 2), (1, 2), (0, 3), (1, 3)])
    lengths = np.linalg.norm(pts[edges[:, 0]] - pts[edges[:, 1]], axis=1)
    ring = (vertex_adjacency(tris, 4) + sparse.identity(4, format="csr")).astype(np.float64)
    factor = _stretch_limit(pts, field, edges, lengths, ring, tris)
    s = (1.0 - _KEEP) * 0.05 / 0.1037
    assert s - 1.0 / 16 <= factor[2] <= s
    x = pts + field * factor[:, None]
    area = lambda p, t: np.cross(p[t[1]] - p[t[0]], p[t[2]] - p[t[0]])[2]  # noqa: E731
    assert all(area(x, t) >= _KEEP * area(pts, t) for t in tris)


def _patch_under_plates(*, steep_at: float | None = None):
    """A patch swelling up to 6 mm (+z) in a bump, its rim held at 0, under a separate plate
    tilted 0.1 that starts 3.1 mm over it at x = 6.1 mm (an arm swinging against the torso);
    with ``steep_at``, also a steep plate (x = steep_at + 0.6 z) through the patch at rest (a
    limb already through the piece over it). Returns ``(points, triangles, disparity [1, N, 3],
    the tilted plate's triangles, the steep plate's)``."""
    n = 8
    g = (np.arange(n) - 3.5) * 0.005 + 0.0003 * np.sin(np.arange(n) * 1.7)
    patch = np.array([(x, y, 0.0004 * np.sin(97.0 * x) * np.cos(71.0 * y)) for y in g for x in g])  # not flat
    ptris = np.array([(r * n + c, r * n + c + 1, r * n + c + n + 1) for r in range(n - 1) for c in range(n - 1)]
                     + [(r * n + c, r * n + c + n + 1, r * n + c + n) for r in range(n - 1) for c in range(n - 1)])
    x0 = 0.0061
    plates = [np.array([(x0, -0.04, 0.0031), (0.05, -0.04, 0.0031 + 0.1 * (0.05 - x0)),
                        (0.05, 0.04, 0.0031 + 0.1 * (0.05 - x0)), (x0, 0.04, 0.0031)])]
    if steep_at is not None:
        plates.append(np.array([(steep_at + 0.6 * z, y, z) for y, z in ((-0.04, -0.004), (-0.04, 0.012),
                                                                          (0.04, 0.012), (0.04, -0.004))]))
    points = np.concatenate([patch, *plates])
    quad = np.array([(0, 1, 2), (0, 2, 3)])
    tris = np.concatenate([ptris] + [quad + n * n + 4 * k for k in range(len(plates))])
    disparity = np.zeros((1, len(points), 3))
    r = np.maximum(np.abs(patch[:, 0]), np.abs(patch[:, 1])) / 0.0175
    disparity[0, : n * n, 2] = 0.006 * np.clip(1.3 * (1.0 - r), 0.0, 1.0)  # a bump, its rim held at 0
    plate_tris = [len(ptris) + 2 * k + np.arange(2) for k in range(len(plates))]
    return points, tris, disparity, plate_tris[0], (plate_tris[1] if steep_at is not None else None)


def test_the_untangle_holds_back_only_what_would_cross_another_piece(device):
    # with the untangle's factors no triangle pair crosses that did not without the pop (brute
    # force over every pair), the skin three rings clear of the plate keeps its whole offset,
    # and the held skin keeps nearly the largest common share of every offset that keeps the
    # whole patch clear (found by bisection)
    from oracles import intersecting_pairs_brute_force
    from warpskin.metrics import self_intersections

    points, tris, disparity, _, _ = _patch_under_plates()
    x0 = 0.0061
    weights = np.ones((len(points), 1))
    eye = np.eye(4)[None]
    pop = SurfacePop(disparity, weights, eye, [0.01], lambda t: np.ones(1), h=0.01, alpha_min=1.0, beta=30.0,
                     triangles=tris, points=points, device=device)
    pop.advance(1)
    world = pop.offsets(eye)[pop.moved]
    assert np.allclose(world, disparity[0, pop.moved])
    moved = points.copy()
    moved[pop.moved] += world
    assert len(self_intersections(moved, tris)) > 0  # the whole pop would cross the plate

    factor = pop._untangle(points, world)
    kept = points.copy()
    kept[pop.moved] += world * factor[:, None]
    assert intersecting_pairs_brute_force(kept, tris) == intersecting_pairs_brute_force(points, tris) == 0
    x = points[pop.moved, 0]
    assert np.all(factor[x < x0 - 3.2 * 0.005] > 1.0 - 1e-12)  # three rings clear of the plate: untouched
    lo, hi = 0.0, 1.0
    for _ in range(30):  # the largest common share of every offset that crosses nothing
        mid = 0.5 * (lo + hi)
        trial = points.copy()
        trial[pop.moved] += mid * world
        lo, hi = (mid, hi) if intersecting_pairs_brute_force(trial, tris) == 0 else (lo, mid)
    assert 0.3 < lo < 0.9
    assert factor.min() >= lo - 0.15  # 0.6 x 0.8 here: a corner cut by its pairs' share, then by a neighbour's

def test_a_crossing_the_source_already_has_is_not_held_when_the_pop_moves_it(device):
    # a steep plate already through the patch (a limb through the piece over it, the robot's
    # thigh under its skirt): the bump moves that crossing by less than a ring, which makes new
    # pairs, each next to a pair of the crossing without the pop; the skin there keeps its whole
    # offset, while the tilted plate still holds the bump back where the pop alone would cross it
    from oracles import intersecting_pair_list_brute_force

    xs = -0.0101
    points, tris, disparity, tilted, steep = _patch_under_plates(steep_at=xs)
    eye = np.eye(4)[None]
    pop = SurfacePop(disparity, np.ones((len(points), 1)), eye, [0.01], lambda t: np.ones(1), h=0.01,
                     alpha_min=1.0, beta=30.0, triangles=tris, points=points, device=device)
    pop.advance(1)
    world = pop.offsets(eye)[pop.moved]
    assert np.allclose(world, disparity[0, pop.moved])

    def pairs(offset):
        x = points.copy()
        x[pop.moved] += offset
        return {tuple(sorted(p)) for p in intersecting_pair_list_brute_force(x, tris).tolist()}

    without = pairs(0.0)
    assert without and all(set(p) & set(steep.tolist()) for p in without)  # only the steep plate crosses
    new_whole = pairs(world) - without
    assert any(set(p) & set(steep.tolist()) for p in new_whole)  # the whole pop moves that crossing
    assert any(set(p) & set(tilted.tolist()) for p in new_whole)  # and crosses the tilted plate

    factor = pop._untangle(points, world)
    x = points[pop.moved, 0]
    assert np.all(factor[x < xs - 0.001] > 1.0 - 1e-12)  # the skin at the steep crossing keeps its offset
    assert factor.min() < 0.7  # the tilted plate still holds the bump back
    new_kept = pairs(world * factor[:, None]) - without
    assert not any(set(p) & set(tilted.tolist()) for p in new_kept)
    corners = [set(t) for t in tris.tolist()]
    touches = lambda a, b: bool(corners[a] & corners[b])  # noqa: E731  share a point (or are one)
    for a, b in new_kept:  # each new pair lies next to a crossing of the source, on both sides
        assert any((touches(a, c) and touches(b, d)) or (touches(a, d) and touches(b, c)) for c, d in without)


def test_a_mesh_too_coarse_to_show_a_belly_is_refused_in_one_line(tmp_path, capsys, assets):
    # RiggedFigure: boxes with points only at the joints (130 positions), so no group has three
    # written points over the middle of its bone: refused before anything is simulated or written
    rig = assets / "RiggedFigure" / "RiggedFigure.glb"
    out = tmp_path / "rf.usdc"
    assert main(["pop", str(rig), "--bpm", "120", "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too coarse to show a belly" in err[0] and "arm_joint_L_2" in err[0]
    assert not out.exists() and not list(tmp_path.iterdir())
    # a group named on the command line that cannot show is named
    assert main(["pop", str(rig), "--bpm", "120", "-o", str(out), "--quiet", "--groups", "fore=arm_joint_L_2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warpskin: error: --groups: fore:") and "too coarse" in err[0]


def test_info_names_the_groups_too_coarse_to_show(capsys, assets):
    # the Fox's tail bone carries skin, but its written mesh has no three points over its middle
    # that swell: info lists it as left out, and the others as pop will use them
    assert main(["info", str(assets / "Fox" / "Fox.glb"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    names = [m["name"] for m in out["muscles"]]
    assert "b_Tail02_013" not in names and len(names) >= 6
    (line,) = out["muscles_left_out"]
    assert "b_Tail02_013" in line and "too coarse" in line


def test_info_shows_the_groups_pop_uses_through_the_cage_asked_for(capsys, assets):
    robot = str(assets / "RobotExpressive" / "RobotExpressive.glb")
    assert main(["info", robot, "--cage", "always", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["simulation"] == "cage"
    assert [m["name"] for m in out["muscles"]] == ["UpperArm.L", "LowerArm.L", "UpperArm.R", "LowerArm.R",
                                                    "UpperLeg.L", "UpperLeg.R"]
    assert main(["info", robot, "--cage", "nonsense"]) == 2
    assert "--cage must be auto, always, none or a mesh file" in capsys.readouterr().err

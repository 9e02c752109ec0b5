"""Popping dance (Son & Han 2007): the skin-vibration step against its closed form, the
stiffness map, relaxation, pose space deformation against independent NumPy references, the
popping arm, bad input and the ``pop`` command; kernels on every device."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from oracles import rig_lbs, prim
from warpskin.errors import SceneError
from warpskin.cli import main
from warpskin.popping import (
    ActivationTimeline,
    PoppingDynamics,
    PoseSpaceDeformer,
    examples_for_scene,
    examples_from_meshes,
    popping_settings,
)
from warpskin.rig import Rig, RigError, Skeleton
from warpskin.scene import load_scene
from warpskin.scenes.popping_arm import _bump, elbow_pose, make_popping_arm, popping_arm_meshes
from warpskin.skinning import Skinner

H = 1.0 / 240.0  # step [s]
D = np.array([0.010, 0.004, -0.003])  # disparity of vertex 0 of the tetrahedron [m]


# ------------------------------------------------------------------------------------ fixtures
def _tetra_rig() -> Rig:
    """One joint, four vertices: the smallest closed mesh, skinned rigidly."""
    pts = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])
    tris = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    skel = Skeleton(["root"], [-1], np.zeros((1, 3)), [[0.0, 0.0, 0.0, 1.0]], np.ones((1, 3)))
    return Rig.from_file_arrays(name="tetra", points=pts, triangles=tris, skeleton=skel,
                                joint_indices=np.zeros((4, 1)), joint_weights=np.ones((4, 1)),
                                inverse_bind=np.eye(4)[None], weld=False)


@pytest.fixture(scope="module")
def tetra():
    """Vertex 0 bulges by D, vertex 1 by D / 2, vertices 2 and 3 not at all; a pose that is
    not the identity, so the rest-frame offsets are rotated into the world."""
    rig = _tetra_rig()
    pose = np.eye(4)
    c, s = math.cos(0.7), math.sin(0.7)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [0.2, -0.1, 0.3]
    mats = pose[None]
    disp = np.zeros((4, 3))
    disp[0], disp[1] = D, D / 2
    world = lambda p: p @ pose[:3, :3].T + pose[:3, 3]  # noqa: E731
    ex = examples_from_meshes(rig, normal=[(world(rig.vertices), mats)], clenched=[(world(rig.vertices + disp), mats)])
    return rig, mats, ex


@pytest.fixture(scope="module")
def arm_scene():
    scene = load_scene("popping_arm")
    return scene, scene.rig(), examples_for_scene(scene), popping_settings(scene)


def _posed(rig, ex, mats, device, **kw):
    deformer = PoseSpaceDeformer(rig, ex, device=device)
    deformer.set_pose(mats)
    return deformer, PoppingDynamics(deformer, **kw)


# --------------------------------------------------------------------------- eqs. 1-2, closed form
@pytest.mark.parametrize("alpha", [0.1, 0.35, 0.8, 1.0])
def test_clench_step_follows_the_closed_form(device, tetra, alpha):
    """Eqs. 1-2 with a fixed goal, from rest. With e = o - g and z = (e, h u):
        e' = (1 - a)(e + h u),  h u' = (1 - a) h u - a e   ->   z' = A z,
        A = [[1 - a, 1 - a], [-a, 1 - a]],  eigenvalues 1 - a +- i sqrt(a (1 - a)),
    modulus sqrt(1 - a) (det A = 1 - a; the paper says 1 - a), and from u = 0:
        e_n = e_0 (1 - a)^(n/2) cos(n theta),  tan(theta) = sqrt(a / (1 - a)),
    while the energy a e^2 + (1 - a)(h u)^2 shrinks by exactly 1 - a per step (A^T P A = (1 - a) P
    for P = diag(a, 1 - a))."""
    rig, mats, ex = tetra
    _, dyn = _posed(rig, ex, mats, device, alpha_min=alpha, beta=30.0)
    a = alpha
    mat = np.array([[1 - a, 1 - a], [-a, 1 - a]])
    eig = np.linalg.eigvals(mat)
    assert np.allclose(sorted(eig, key=lambda z: z.imag), [1 - a - 1j * math.sqrt(a * (1 - a)), 1 - a + 1j * math.sqrt(a * (1 - a))])
    assert np.allclose(np.abs(eig), math.sqrt(1 - a))
    theta = math.atan2(math.sqrt(a * (1 - a)), 1 - a)
    z0 = np.stack([-D, np.zeros(3)])  # (e, h u) per axis, starting on the normal mesh at rest
    steps = 60
    got_e, got_hu = [], []
    for _ in range(steps):
        dyn.step(H, 1.0)
        got_e.append(dyn.offset.numpy()[0] - D)
        got_hu.append(H * dyn.velocity.numpy()[0])
    got_e, got_hu = np.array(got_e), np.array(got_hu)
    n = np.arange(1, steps + 1)
    powers = np.stack([np.linalg.matrix_power(mat, k) @ z0 for k in n])  # [n, 2, 3]
    closed = -D[None] * ((1 - a) ** (n / 2) * np.cos(n * theta))[:, None]
    assert np.abs(powers[:, 0] - closed).max() < 1e-15
    tol = 2e-6 * np.linalg.norm(D)  # float32 kernel
    assert np.abs(got_e - powers[:, 0]).max() < tol
    assert np.abs(got_hu - powers[:, 1]).max() < tol
    energy = a * np.sum(got_e**2, axis=1) + (1 - a) * np.sum(got_hu**2, axis=1)
    e0 = a * np.sum(D**2)
    big = energy > 1e-9 * e0
    assert np.allclose(energy[big], e0 * (1 - a) ** n[big], rtol=1e-4)
    if a == 1.0:
        assert np.abs(got_e).max() < tol  # the goal in one step, no vibration
    else:
        sign = np.sign(got_e[:, 0][np.abs(got_e[:, 0]) > tol])
        assert np.count_nonzero(np.diff(sign)) >= 2  # passes the goal and comes back
        assert got_e[:, 0].max() > 0.0  # overshoot beyond the clenched goal (e_0 < 0)
    # vertices without disparity have alpha = 1 and never leave the normal mesh
    assert np.all(dyn.offset.numpy()[2:] == 0.0)


def test_stiffness_map(device, tetra, arm_scene):
    """Eq. 3: alpha = alpha_min at the largest disparity, 1 without disparity, linear between."""
    rig, mats, ex = tetra
    _, dyn = _posed(rig, ex, mats, device, alpha_min=0.25)
    dyn.step(H, 0.0)
    assert np.allclose(dyn.alpha.numpy(), [0.25, 0.625, 1.0, 1.0], atol=1e-6)

    scene, arm, arm_ex, _ = arm_scene
    deformer, dyn = _posed(arm, arm_ex, arm.skinning_matrices("pop", 0.0), device, alpha_min=0.2)
    dyn.step(H, 0.0)
    alpha = dyn.alpha.numpy()
    normal = deformer.normal_points.numpy()
    # the same disparity, independently: the NumPy-skinned clenched examples' interpolation is
    # tested below; here the disparity of each group at the current pose is read back
    disp = deformer.disparity.numpy()
    lin = np.einsum("vk,vkij->vij", arm.joint_weights, arm.skinning_matrices("pop", 0.0)[arm.joint_indices])[:, :3, :3]
    dist = np.linalg.norm(np.einsum("vij,gvj->gvi", lin, disp), axis=2)  # [G, V]
    group = np.argmax(dist, axis=0)
    d = dist[group, np.arange(arm.vertex_count)]
    expected = (0.2 - 1.0) * d / dist.max(axis=1)[group] + 1.0
    assert np.abs(alpha - expected).max() < 1e-5
    for g in range(dist.shape[0]):
        peak = np.argmax(dist[g])
        assert abs(alpha[peak] - 0.2) < 1e-6
    assert np.all(alpha[dist.max(axis=0) == 0.0] == 1.0)
    assert (dist.max(axis=0) == 0.0).sum() > arm.vertex_count // 3  # forearm, hand, shoulder cap
    assert np.isfinite(normal).all()


# ------------------------------------------------------------------------------------- eq. 4
def test_relaxation_is_monotone_and_ends_on_the_normal_goal(device, tetra):
    rig, mats, ex = tetra
    beta, thr = 30.0, 1e-5
    deformer, dyn = _posed(rig, ex, mats, device, alpha_min=0.3, beta=beta, threshold=thr)
    for _ in range(80):
        dyn.step(H, 1.0)
    start = dyn.offset.numpy()[0].copy()
    assert np.linalg.norm(start - D) < 1e-3 * np.linalg.norm(D)  # settled on the clenched goal
    traj = []
    for _ in range(400):
        dyn.step(H, 0.0)
        traj.append(dyn.offset.numpy()[0].copy())
        assert np.all(dyn.velocity.numpy() == 0.0)
    traj = np.array(traj)
    dist = np.linalg.norm(traj, axis=1)
    assert np.all(np.diff(dist) <= 0.0)  # monotone
    assert np.all(traj @ D >= 0.0)  # never passes the normal goal (no overshoot)
    # e_n = (1 - beta h)^n e_0 until the snap
    n = np.arange(1, len(traj) + 1)
    ref = start[None] * ((1 - beta * H) ** n)[:, None]
    before = np.linalg.norm(ref, axis=1) >= thr * 1.01
    assert np.abs(traj[before] - ref[before]).max() < 1e-6 * np.linalg.norm(D)
    snap = int(np.argmax(dist == 0.0))
    assert dist[snap] == 0.0 and np.linalg.norm(ref[snap - 1]) * (1 - beta * H) < thr * 1.01
    assert np.all(dyn.offset.numpy() == 0.0)  # exactly on the goal
    assert np.array_equal(dyn.points.numpy(), deformer.normal_points.numpy())


# ------------------------------------------------------------------- pose space deformation
def test_pose_space_deformation_reproduces_each_example(device, arm_scene):
    scene, rig, ex, _ = arm_scene
    meshes = popping_arm_meshes(rig, **scene.rig_spec["params"])
    deformer = PoseSpaceDeformer(rig, ex, device=device)
    assert deformer.joint_names == ["elbow"]
    for k, (normal, mats) in enumerate(meshes["normal"]):
        deformer.set_pose(mats)
        wn, wg = deformer.pose_weights
        assert np.allclose(wn, np.eye(3)[k], atol=1e-12)
        assert np.abs(deformer.normal_points.numpy() - normal).max() < 2e-6
        biceps, triceps = meshes["clenched"]["biceps"][k][0], meshes["clenched"]["triceps"][k][0]
        both = biceps + triceps - normal  # LBS is affine in the displacement at a fixed pose
        assert np.abs(deformer.clenched_points.numpy() - both).max() < 2e-6
        assert np.abs(deformer.lbs().numpy() - rig_lbs(rig, mats)).max() < 2e-6


def test_pose_space_deformation_is_smooth_between_examples(device, arm_scene):
    scene, rig, ex, _ = arm_scene
    deformer = PoseSpaceDeformer(rig, ex, device=device)
    step = math.radians(0.5)
    angles = np.arange(0.0, math.radians(170.0), step)
    fields = []
    for a in angles:
        deformer.set_pose(elbow_pose(rig, math.degrees(a)))
        fields.append(np.concatenate([deformer.normal_displacement.numpy()[None], deformer.disparity.numpy()]))
    f = np.array(fields)  # [A, 1 + G, V, 3] rest-frame displacements along the elbow path
    first = np.linalg.norm(np.diff(f, axis=0), axis=-1).max(axis=(1, 2)) / step
    second = np.linalg.norm(np.diff(f, n=2, axis=0), axis=-1).max(axis=(1, 2)) / step**2
    # scale: the largest displacement change between neighbouring examples over their spacing
    ex_fields = np.concatenate([ex.normal_displacements[:, None], np.stack(ex.clenched_disparities, axis=1)], axis=1)
    slope = np.linalg.norm(np.diff(ex_fields, axis=0), axis=-1).max() / math.radians(60.0)
    print(f"\nPSD along the elbow path: max |df/dangle| {first.max():.3g} m/rad, max |d2f/dangle2| "
          f"{second.max():.3g} m/rad^2; example slope {slope:.3g} m/rad")
    assert first.max() < 3.0 * slope  # bounded difference quotients: no jumps
    assert second.max() < 3.0 * slope / math.radians(60.0) + 1e-3  # and no kinks (float32 noise ~1e-4)


def test_one_example_is_lbs_plus_its_displacement(device, arm_scene):
    scene, rig, _, _ = arm_scene
    bump = _bump(rig.vertices, (0.08, 0.26), 1.0, 0.01)  # the rest-frame displacement, known
    pose = elbow_pose(rig, 60.0)
    ex = examples_from_meshes(rig, normal=[(rig_lbs(rig, pose, points=rig.vertices + bump), pose)],
                              clenched=[(rig_lbs(rig, pose, points=rig.vertices + 2 * bump), pose)])
    assert np.abs(ex.normal_displacements[0] - bump).max() < 1e-12
    deformer = PoseSpaceDeformer(rig, ex, device=device)
    lbs = Skinner(rig, method="lbs", device=device)
    for deg in (0.0, 45.0, 120.0, 160.0):
        mats = elbow_pose(rig, deg)
        deformer.set_pose(mats)
        lin = np.einsum("vk,vkij->vij", rig.joint_weights, mats[rig.joint_indices])[:, :3, :3]
        skinned = np.einsum("vij,vj->vi", lin, bump)
        base = lbs.skin(mats).numpy()
        assert np.abs(deformer.normal_points.numpy() - (base + skinned)).max() < 2e-6
        assert np.abs(deformer.clenched_points.numpy() - (base + 2 * skinned)).max() < 2e-6


# ------------------------------------------------------------------------------- popping arm
def test_popping_arm_overshoots_and_settles(device, arm_scene):
    scene, rig, ex, settings = arm_scene
    clip = rig.clip(scene.clip)
    times = np.linspace(clip.start, clip.end, 25)
    poses = np.stack([rig.skinning_matrices(clip, t) for t in times])
    assert np.array_equal(poses, np.broadcast_to(poses[0], poses.shape))  # the bones never move
    alpha_min = settings.alpha_min
    deformer, dyn = _posed(rig, ex, poses[0], device, alpha_min=alpha_min, beta=settings.beta,
                           threshold=settings.threshold)
    normal = deformer.normal_points.numpy()
    lbs0 = deformer.lbs().numpy()
    clench_steps, relax_steps = 240, 240  # 1 s clenched, 1 s relaxed
    act = {"biceps": 1.0, "triceps": 0.0}
    xs = []
    for k in range(clench_steps + relax_steps):
        if k == clench_steps:
            act = {"biceps": 0.0}
        xs.append(dyn.step(H, act).numpy().copy())
        if k == 0:
            goal = dyn.goal_points.numpy().copy()
    xs = np.array(xs)
    assert np.array_equal(deformer.lbs().numpy(), lbs0)
    d = goal - normal
    dl = np.linalg.norm(d, axis=1)
    top = int(np.argmax(dl))
    dhat = d[top] / dl[top]
    signed = (xs[:clench_steps, top] - goal[top]) @ dhat  # < 0 inside, > 0 past the clenched surface
    overshoot = signed.max()
    err = np.linalg.norm(xs[:clench_steps, top] - goal[top], axis=1)
    tol = 0.01 * dl[top]
    settle = (int(np.nonzero(err > tol)[0].max()) + 1) * H
    # the closed form's envelope |e_n| <= (1 - alpha)^(n/2) |e_0| bounds the settle time
    bound = math.ceil(math.log(0.01) / (0.5 * math.log(1 - alpha_min))) * H
    theta = math.atan2(math.sqrt(alpha_min * (1 - alpha_min)), 1 - alpha_min)
    n = np.arange(1, 200)
    closed = (-((1 - alpha_min) ** (n / 2)) * np.cos(n * theta)).max() * dl[top]
    print(f"\npopping arm ({device}, {rig.vertex_count} vertices, alpha_min {alpha_min}, dt {H * 1e3:.2f} ms): "
          f"largest disparity {dl[top] * 1e3:.2f} mm at vertex {top}; peak overshoot {overshoot * 1e3:.2f} mm "
          f"(closed form {closed * 1e3:.2f} mm) at {(np.argmax(signed) + 1) * H * 1e3:.0f} ms; settles to 1 % in "
          f"{settle * 1e3:.0f} ms (bound {bound * 1e3:.0f} ms)")
    assert alpha_min < 1.0 and overshoot > 0.0
    assert abs(overshoot - closed) < 0.02 * dl[top]
    assert settle <= bound
    # vertices that the examples do not move stay exactly on the normal mesh, always
    still = np.nonzero(np.linalg.norm(deformer.clenched_points.numpy() - normal, axis=1) == 0.0)[0]
    assert still.size > 1000 and np.array_equal(xs[:, still], np.broadcast_to(normal[still], xs[:, still].shape))
    # after relaxing, the whole skin is back exactly on the normal mesh
    assert np.array_equal(xs[-1], normal)
    relax = np.linalg.norm(xs[clench_steps:, top] - normal[top], axis=1)
    assert np.all(np.diff(relax) <= 1e-7)


# ----------------------------------------------------------------------------- bad input
def test_bad_examples_name_the_part(arm_scene):
    scene, rig, _, _ = arm_scene
    meshes = popping_arm_meshes(rig)
    normal = meshes["normal"]
    bi = meshes["clenched"]["biceps"]
    short = [(normal[0][0], normal[0][1]), (normal[1][0][:-1], normal[1][1])]
    with pytest.raises(RigError, match=r"normal example 1: 2917 vertices, but the rig 'popping_arm' has 2918"):
        examples_from_meshes(rig, normal=short, clenched=bi)
    with pytest.raises(RigError, match=r"clenched example 0 of group 'biceps': 2917 vertices"):
        examples_from_meshes(rig, normal=normal, clenched={"biceps": [(bi[0][0][:-1], bi[0][1])]})
    lonely = [(bi[0][0], elbow_pose(rig, 45.0))]
    with pytest.raises(RigError, match=r"clenched example 0 of group 'biceps' has no normal partner"):
        examples_from_meshes(rig, normal=normal, clenched={"biceps": lonely})
    with pytest.raises(RigError, match="no clenched examples"):
        examples_from_meshes(rig, normal=normal, clenched=[])
    with pytest.raises(RigError, match=r"normal example 2 is at the same pose as normal example 0"):
        examples_from_meshes(rig, normal=[normal[0], normal[1], normal[0]], clenched=bi)
    with pytest.raises(RigError, match=r"normal example 0: the pose must be a clip time"):
        examples_from_meshes(rig, normal=[(normal[0][0], np.eye(4))], clenched=bi)


def test_bad_parameters_are_clear_errors(arm_scene, tmp_path):
    scene, rig, ex, _ = arm_scene
    deformer = PoseSpaceDeformer(rig, ex, device="cpu")
    for bad in (0.0, -0.2, 1.5, float("nan")):
        with pytest.raises(SceneError, match=r"alpha_min must be in \(0, 1\]"):
            PoppingDynamics(deformer, alpha_min=bad)
    dyn = PoppingDynamics(deformer, alpha_min=0.5, beta=30.0)
    with pytest.raises(SceneError, match=r"beta \* dt <= 1"):
        dyn.step(0.05, 1.0)
    with pytest.raises(SceneError, match=r"unknown muscle group 'deltoid'"):
        dyn.step(H, {"deltoid": 1.0})
    with pytest.raises(SceneError, match=r"activations must be in \[0, 1\]"):
        dyn.step(H, [1.5, 0.0])
    with pytest.raises(SceneError, match=r"muscle groups \['calf'\] have no clenched examples"):
        ActivationTimeline({"calf": [(0.0, 1.0)]}).check_groups(deformer.group_names)
    other = make_popping_arm(rings=30)
    with pytest.raises(RigError, match=r"examples have 2918 vertices but the rig 'popping_arm' has"):
        PoseSpaceDeformer(other, ex, device="cpu")
    text = (load_scene("popping_arm").source.read_text()
            .replace('generator = "popping_arm"', 'generator = "popping_arm"\n'))
    for old, new, message in [
        ('mode = "goal"', 'mode = "dance"', "mode must be .goal. .*or .layered."),
        ("alpha_min = 0.1", "alpha_min = 0.0", r"alpha_min must be in \(0, 1\]"),
        ("beta = 30.0", "betta = 30.0", r"unknown key\(s\) \['betta'\]"),
        ("hold = 0.6", "hold = 1.2", "overlaps the beat at 1.25 s"),
    ]:
        path = tmp_path / "pop.toml"
        path.write_text(text.replace(old, new))
        with pytest.raises(SceneError, match=message):
            popping_settings(load_scene(path))
    arm = load_scene("arm")
    with pytest.raises(RigError, match=r"scene 'arm' \(generator 'arm'\) has no popping examples"):
        examples_for_scene(arm)


def test_activation_timeline():
    keys = ActivationTimeline.beats([1.0, 0.0], hold=0.4, attack=0.1, release=0.2)
    tl = ActivationTimeline({"biceps": keys, "triceps": [(0.5, 0.0), (0.5, 1.0), (0.8, 1.0), (0.8, 0.0)]})
    assert tl.groups == ["biceps", "triceps"] and tl.end == pytest.approx(1.6)
    for t, want in [(-1.0, 0.0), (0.0, 0.0), (0.05, 0.5), (0.1, 1.0), (0.4, 1.0), (0.5, 0.5), (0.6, 0.0),
                    (0.9, 0.0), (1.05, 0.5), (1.3, 1.0), (2.0, 0.0)]:
        assert tl.value("biceps", t) == pytest.approx(want), t
    assert tl.value("triceps", 0.4999) == 0.0 and tl.value("triceps", 0.5) == 1.0  # a step: right-continuous
    assert tl.value("triceps", 0.8) == 0.0 and tl.value("deltoid", 0.6) == 0.0
    assert np.allclose(tl.sample(0.6, ["triceps", "biceps"]), [1.0, 0.0])
    with pytest.raises(SceneError, match="must not decrease"):
        ActivationTimeline({"b": [(1.0, 0.0), (0.5, 1.0)]})
    with pytest.raises(SceneError, match="attack"):
        ActivationTimeline.beats([0.0], hold=0.1, attack=0.2)


# ------------------------------------------------------------------------------------- CLI
def test_cli_pop_writes_usd(tmp_path, capsys, device):
    out = tmp_path / "pop.usdc"
    assert main(["pop", "popping_arm", "-o", str(out), "--frames", "0:30", "--quiet", "--device", device]) == 0
    assert "wrote" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(out))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 30
    pts = {}
    for name in ("popping", "normal", "goal", "lbs"):
        mesh = UsdGeom.Mesh(prim(stage, f"{name}"))
        assert mesh.GetPrim().IsValid(), name
        assert mesh.GetPointsAttr().GetTimeSamples() == [float(f) for f in range(31)]
        pts[name] = np.array(mesh.GetPointsAttr().Get(30))
        assert pts[name].shape == (2918, 3)
    # frame 30 (0.5 s): the biceps popped at 0.25 s; the dynamic skin is near, not on, its goal
    assert np.abs(pts["goal"] - pts["normal"]).max() > 5e-3
    assert 0.0 < np.abs(pts["popping"] - pts["goal"]).max() < 5e-3
    assert np.abs(pts["normal"] - pts["lbs"]).max() > 1e-4  # the normal examples are not plain LBS


def test_cli_pop_bench(tmp_path, capsys, device):
    out = tmp_path / "bench.json"
    assert main(["pop", "--bench", "--steps", "3", "--repeat", "1", "--device", device, "--json", str(out)]) == 0
    row = json.loads(out.read_text())
    assert row["vertices"] == 4322 and row["device"] == device
    for key in ("pose_space_ms", "step_ms", "frame_ms", "lbs_ms", "frame_over_lbs"):
        assert row[key] > 0.0, key
    capsys.readouterr()


def test_cli_pop_without_examples_is_a_clear_error(tmp_path, capsys):
    # goal mode needs examples; without them a rig pops in layered mode (tests/test_popping_muscles.py)
    assert main(["pop", "arm", "-o", str(tmp_path / "x.usdc"), "--quiet", "--mode", "goal"]) == 2
    assert "has no popping examples" in capsys.readouterr().err
    assert not (tmp_path / "x.usdc").exists()
    assert main(["pop", "popping_arm"]) == 2
    assert "pop needs a SCENE and -o" in capsys.readouterr().err

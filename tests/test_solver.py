"""The solver (Algorithm 1): fast summation = direct gather, rigid invariance, rest stability,
volume against LBS at the 150-degree arm, damping and jiggle, determinism, bad input. Every
device."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom
from scipy.spatial.transform import Rotation

from oracles import coarse_arm, prim
from warpskin.errors import InputError, SceneError
from warpskin.model import ModelParams, SkinModelBuilder
from warpskin.scene import load_scene
from warpskin.scenes.arm import make_arm
from warpskin.run import initial_state, simulate
from warpskin.solver import SimulationError, SkinSolver, SolverParams

COARSE = "[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 30\nsegments = 20\n"


@pytest.fixture(scope="module")
def coarse_builder():
    return SkinModelBuilder(coarse_arm()).build()


def _scene(tmp_path, extra=""):
    p = tmp_path / "coarse_arm.toml"
    p.write_text(COARSE + "[animation]\nclip = 'flex'\nfps = 30\n" + extra)
    return load_scene(p)


def _at_rest(device, builder, iterations):
    """The coarse arm's model, a solver, two states (the first at the LBS rest pose of "flex") and a control."""
    model = builder.finalize(device)
    solver = SkinSolver(model, SolverParams(iterations=iterations))
    a, b, c = model.state(), model.state(), model.control()
    initial_state(model, a, builder.rig.skinning_matrices("flex", 0.0))
    return model, builder.rig, solver, a, b, c


def test_fast_summation_equals_direct_gather_in_a_running_simulation(device, coarse_builder):
    model, rig, solver, a, b, c = _at_rest(device, coarse_builder, 5)
    for k in range(12):  # a deforming, moving state
        c.set_pose(rig.skinning_matrices("flex", 0.05 * (k + 1)))
        solver.step(a, b, c, None, 0.005)
        a, b = b, a
    q_out = wp.zeros_like(a.q)
    solver.update_moments(a.q)
    solver.params = dataclasses.replace(solver.params, fast_summation=False)
    solver.region_fit(a.x, a.q, q_out)
    com_gather, q_gather = solver.region_com.numpy().copy(), q_out.numpy().copy()
    solver.params = dataclasses.replace(solver.params, fast_summation=True)
    solver.region_fit(a.x, a.q, q_out)
    com_fast, q_fast = solver.region_com.numpy(), q_out.numpy()
    size = rig.size()
    assert np.abs(com_fast - com_gather).max() < 1e-5 * size
    dot = np.abs(np.sum(q_fast * q_gather, axis=1))
    assert (1.0 - dot).max() < 1e-6  # the same rotations (up to sign)


def test_residuals_are_each_iterations_largest_correction(device, coarse_builder):
    # the elasticity loop run iteration by iteration: each iteration's residual is the largest
    # distance a particle moved in it (NumPy, from the positions before and after)
    model, rig, solver, a, b, c = _at_rest(device, coarse_builder, 4)
    c.set_pose(rig.skinning_matrices("flex", 0.3))  # far from the start pose: every iteration corrects
    solver.step(a, b, c, None, 0.005)
    want = []
    x = wp.clone(a.x)
    q_src, q_dst = wp.clone(a.q), wp.zeros_like(a.q)
    solver.update_moments(q_src)
    for it in range(4):
        before = x.numpy().astype(np.float64)
        solver.region_fit(x, q_src, q_dst)
        solver.blend_and_constrain(x, q_dst, it)
        want.append(np.linalg.norm(x.numpy() - before, axis=1).max())
        q_src, q_dst = q_dst, q_src
    got = solver.residuals.numpy()
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert want[0] > 1e-4 and want[-1] < want[0]


@pytest.mark.parametrize("fast", [False, True])
def test_rigid_motion_keeps_the_rest_shape(device, coarse_builder, fast):
    model = coarse_builder.finalize(device)
    rot = Rotation.from_euler("xyz", [0.4, -0.3, 0.7])
    m = np.eye(4)
    m[:3, :3] = rot.as_matrix()
    m[:3, 3] = [0.1, 0.2, -0.1]
    mats = np.stack([m] * model.joint_count)
    solver = SkinSolver(model, SolverParams(gravity=(0, 0, 0), fast_summation=fast))
    a, b, c = model.state(), model.state(), model.control()
    c.set_pose(mats)
    initial_state(model, a, mats)
    for _ in range(200):
        solver.step(a, b, c, None, 0.005)
        a, b = b, a
    moved = coarse_builder.layers.flat() @ m[:3, :3].T + m[:3, 3]
    assert np.abs(a.x.numpy() - moved).max() < 1e-4 * coarse_builder.rig.size()


def test_nothing_drifts_at_rest_without_gravity(device, coarse_builder):
    model = coarse_builder.finalize(device)
    solver = SkinSolver(model, SolverParams(gravity=(0, 0, 0), iterations=5))
    a, b, c = model.state(), model.state(), model.control()
    for _ in range(1000):
        solver.step(a, b, c, None, 0.005)
        a, b = b, a
    assert np.abs(a.x.numpy() - coarse_builder.layers.flat()).max() < 1e-5 * coarse_builder.rig.size()
    assert np.abs(a.v.numpy()).max() < 1e-4


def test_arm_at_150_degrees_keeps_volume_where_lbs_loses_it(device, tmp_path):
    scene = _scene(tmp_path, "[solver]\niterations = 10\nvolume_iterations = 4\n")
    out = tmp_path / "arm.usdc"
    result = simulate(scene, out, device=device, frames=(0, 48), with_lbs=True, report_dir=tmp_path / "report", progress=False)
    s = result.summary
    t = np.array(result.metrics["time"])
    assert t[-1] >= 1.5  # the elbow reached 150 degrees
    print(f"150 deg: whole volume deviation warpskin {s['max_volume_deviation']:.2e}, LBS {s['max_volume_deviation_lbs']:.2e}; "
          f"sub-volumes warpskin {s['max_subvolume_deviation']:.2e}, LBS {s['max_subvolume_deviation_lbs']:.2e}")
    assert s["max_volume_deviation_lbs"] > 0.02  # LBS deflates the elbow
    assert s["max_volume_deviation"] < 0.009  # the paper: within 0.9 %
    assert s["max_volume_deviation"] < s["max_volume_deviation_lbs"] / 10
    assert s["max_subvolume_deviation"] < s["max_subvolume_deviation_lbs"] / 10
    report = (tmp_path / "report" / "report.json").read_text()
    assert "max_volume_deviation" in report
    for name in ("volume.png", "subvolumes.png", "energy.png", "residuals.png", "offset_from_lbs.png"):
        assert (tmp_path / "report" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    residuals = result.metrics["residuals"][-1]
    assert len(residuals) == 10 and residuals[-1] < residuals[0]  # the elasticity loop converges
    stage = Usd.Stage.Open(str(out))
    assert len(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().GetTimeSamples()) == 49
    assert prim(stage, "lbs").IsValid()


def test_damping_and_jiggle_after_the_bones_stop(tmp_path, device):
    # the elbow flexes quickly (0.3 s) and holds: the skin keeps moving after the bones stop,
    # then settles
    p = tmp_path / "quick.toml"
    p.write_text(COARSE + "flex_degrees = 90.0\nflex_time = 0.3\nhold_time = 1.2\nrest_time = 0.0\n"
                 "[animation]\nclip = 'flex'\nfps = 60\nframes = [0, 90]\n[solver]\niterations = 6\ndamping = 3.0\n")
    result = simulate(load_scene(p), tmp_path / "q.usdc", device=device, progress=False)
    t = np.array(result.metrics["time"])
    ke = np.array(result.metrics["kinetic_energy"])
    off = np.array(result.metrics["max_offset_from_lbs"])
    stopped = t > 0.3 + 1e-9
    # secondary motion: during the hold the offset from LBS (the bones are still) keeps changing
    motion = np.abs(np.diff(off[stopped]))
    print(f"after the stop: offset change per frame {motion[:5]}, kinetic energy {ke[stopped][:3]} -> {ke[-1]:.2e} J")
    assert motion[:10].max() > 1e-4  # > 0.1 mm per frame right after the stop
    assert motion[-10:].max() < 0.1 * motion[:10].max()
    assert ke[-1] < 0.05 * ke[stopped][:5].max()  # damped


def test_two_cpu_runs_are_identical_with_and_without_graph_capture(tmp_path):
    scene = _scene(tmp_path, "[solver]\niterations = 4\n")
    a = simulate(scene, tmp_path / "a.usdc", device="cpu", frames=(0, 8), progress=False)
    b = simulate(_scene(tmp_path, "[solver]\niterations = 4\n"), tmp_path / "b.usdc", device="cpu", frames=(0, 8), progress=False,
                 use_graph=False)
    assert a.summary["graph_capture"] and not b.summary["graph_capture"]  # two different paths compared
    stage_a, stage_b = Usd.Stage.Open(str(a.path)), Usd.Stage.Open(str(b.path))  # keep the stages alive
    sa = UsdGeom.Mesh(prim(stage_a, "skin")).GetPointsAttr()
    sb = UsdGeom.Mesh(prim(stage_b, "skin")).GetPointsAttr()
    for f in range(9):
        assert np.array_equal(np.array(sa.Get(f)), np.array(sb.Get(f)))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"iterations": 0}, "iterations must be an integer >= 1"),
        ({"dt": 0.0}, "dt must be a positive"),
        ({"dt": -0.01}, "dt must be a positive"),
        ({"damping": -1.0}, "damping must be a rate >= 0"),
        ({"volume_stiffness": 1.5}, "volume_stiffness must be in"),
    ],
)
def test_unstable_settings_rejected(kwargs, message):
    with pytest.raises(SceneError, match=message):
        SolverParams(**kwargs).check()


def test_stiffness_outside_unit_interval_rejected(tmp_path):
    scene = _scene(tmp_path, "[layers]\nstiffness = [0.8, 0.6, 1.2, 0.8]\n")
    with pytest.raises(SceneError, match=r"four numbers in \[0, 1\]"):
        scene.model_params()
    with pytest.raises(InputError, match="step needs two different states"):
        model = SkinModelBuilder(make_arm(rings=12, segments=10), ModelParams(volume=False)).finalize("cpu")
        s = model.state()
        SkinSolver(model).step(s, s, model.control(), None, 0.005)


def test_nan_stops_the_run_naming_frame_and_particle_and_keeps_a_valid_file(tmp_path, monkeypatch):
    calls = {"n": 0}
    original = SkinSolver.step

    def poisoned(self, state_in, state_out, control, contacts, dt):
        original(self, state_in, state_out, control, contacts, dt)
        calls["n"] += 1
        if calls["n"] == 7 * 3 + 2:  # a substep of frame 4
            x = state_out.x.numpy()
            x[1234] = np.nan
            state_out.x.assign(x)

    monkeypatch.setattr(SkinSolver, "step", poisoned)
    out = tmp_path / "nan.usdc"
    with pytest.raises(SimulationError, match=r"frame 4: particle \d+ \(\w+ layer, vertex \d+\) became NaN"):
        simulate(_scene(tmp_path, "[solver]\niterations = 2\n"), out, device="cpu", frames=(0, 10), progress=False,
                 use_graph=False)  # the fault injection reads the state on the host
    stage = Usd.Stage.Open(str(out))
    samples = UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().GetTimeSamples()
    assert samples == [0.0, 1.0, 2.0, 3.0]


@pytest.mark.parametrize("fast", [False, True])
def test_region_fit_matches_a_numpy_shape_matching_reference(device, coarse_builder, fast):
    # oriented-particle shape matching (Mueller and Chentanez 2011) written out in NumPy from the
    # builder's regions: c_r = sum m x / M, A_r = sum (mu R_j + m (x_j - c_r) o_j^T), R_r its
    # rotation by scipy's polar decomposition; both the gather and the path-scan kernels agree
    # (this caught the fast path's float32 rest centres: 2e-3 rotation error in small regions)
    from scipy.linalg import polar

    b = coarse_builder
    model = b.finalize(device)
    solver = SkinSolver(model, SolverParams(fast_summation=fast, rotation_iterations=400))
    rng = np.random.default_rng(3)
    n = model.particle_count
    rot = Rotation.from_rotvec(rng.normal(size=3) * 0.3)
    x0 = b.layers.flat()
    x = rot.apply(x0) + rng.normal(scale=0.002, size=x0.shape) + [0.05, -0.02, 0.01]
    q = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.2)
    xw = wp.array(x.astype(np.float32), dtype=wp.vec3, device=model.device)
    qw = wp.array(q.as_quat().astype(np.float32), dtype=wp.quat, device=model.device)  # x, y, z, w
    q_out = wp.zeros(n, dtype=wp.quat, device=model.device)
    solver.update_moments(qw)
    solver.region_fit(xw, wp.array(np.tile([0, 0, 0, 1.0], (n, 1)).astype(np.float32), dtype=wp.quat,
                                   device=model.device), q_out)
    com = solver.region_com.numpy().astype(np.float64)
    r_got = Rotation.from_quat(q_out.numpy().astype(np.float64)).as_matrix()

    reg = b.regions
    m = b.masses
    mu = m * b.radii**2 / 5.0
    rq = q.as_matrix()
    worst_c = worst_r = 0.0
    well = 0
    fits = []
    for r in range(n):
        mem = reg.region_members[reg.region_offsets[r]:reg.region_offsets[r + 1]]
        c = (m[mem, None] * x[mem]).sum(axis=0) / m[mem].sum()
        c0 = (m[mem, None] * x0[mem]).sum(axis=0) / m[mem].sum()
        a = np.einsum("j,jk,jl->kl", m[mem], x[mem] - c, x0[mem] - c0) + (mu[mem, None, None] * rq[mem]).sum(axis=0)
        worst_c = max(worst_c, np.abs(com[r] - c).max())
        fits.append(a)
    scale = np.median([np.linalg.norm(a, 2) for a in fits])
    for r, a in enumerate(fits):
        sv = np.linalg.svd(a, compute_uv=False)
        if sv[2] < 0.05 * sv[0] or sv[0] < 1e-3 * scale:
            # a bone-layer region squeezed toward its centre line, or shrunk to a point at the
            # wrist cap (A ~ 1e-10 of the typical size, below float32 rounding): its rotation
            # is ill-conditioned; only a proper rotation is required
            assert np.linalg.det(r_got[r]) == pytest.approx(1.0, abs=1e-4)
            continue
        well += 1
        ref, _ = polar(a)
        worst_r = max(worst_r, np.abs(r_got[r] - ref).max())
    print(f"fast={fast}: centre error {worst_c:.2e} m, rotation error {worst_r:.2e} ({well} of {n} regions well conditioned)")
    assert well > 0.9 * n
    assert worst_c < 2e-6  # float32 positions of a ~0.6 m arm
    assert worst_r < 2e-5  # float32 sums; 400 warm-start iterations converge from the identity

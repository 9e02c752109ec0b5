"""The timeline of a bake: frames are the source's own time codes at its own rate (a USD stage's
timeCodesPerSecond, a glTF clip's key spacing, else 30), ``--fps`` resamples, ``--start-frame``
shifts, and a range outside the clip is refused. Checked against usd-core's own UsdSkel
skinning of the source at the same seconds."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from oracles import usd_skinned_world, prim
from warpskin.cli import main
from warpskin.errors import SceneError
from warpskin.rig import key_rate
from warpskin.run.plan import FramePlan
from warpskin.scene import Scene, load_scene

TOL = 1e-4  # of the model size (the bound for a bake against its source)


def _skin_samples(path):
    stage = Usd.Stage.Open(str(path))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.GetCustomDataByKey("warpskin:role") == "skin")
    attr = mesh.GetPointsAttr()
    return stage, {tc: np.asarray(attr.Get(tc), dtype=np.float64) for tc in attr.GetTimeSamples()}


# --------------------------------------------------------------------------------------------
# The rate of a clip's keys
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rate", [24, 25, 30, 60])
def test_key_rate_finds_the_rate_keys_were_sampled_at(rate):
    rng = np.random.default_rng(rate)
    t = (np.arange(7, 7 + 40) + rng.uniform(-2e-4, 2e-4, 40)) / rate  # jitter well inside the grid tolerance
    assert key_rate(t) == rate


@pytest.mark.parametrize("times", [
    [0.0, 1.25],  # RiggedFigure: two keys
    [0.0, 1.0, 2.0],  # RecursiveSkeletons: a key per second is not a frame rate
    [0.0, 0.03, 0.07, 0.1, 0.16],  # irregular
    [0.0, 1 / 24, 2 / 24, 3 / 24, 3.3 / 24],  # one key off the grid by 0.3 frames
])
def test_key_rate_is_none_where_no_rate_is_evident(times):
    assert key_rate(np.array(times)) is None


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------
def test_the_arm_keeps_its_scene_rate_and_frames():
    scene = load_scene("arm")
    assert scene.frame_rate == 30 and scene.frame_range()[0] == 0
    plan = FramePlan.for_scene(scene, (0, 4))
    assert plan.time_codes == [0.0, 1.0, 2.0, 3.0, 4.0] and plan.times[3] == pytest.approx(0.1)


@pytest.mark.parametrize("rel, rate, frames", [
    ("CesiumMan/CesiumMan.glb", 24, (1, 48)),  # keys 1/24 .. 2 s
    ("usd/CesiumMan/CesiumMan.usdz", 24, (1, 48)),  # stage: 24 time codes per second, 1..48
    ("RiggedSimple/RiggedSimple.glb", 24, (1, 50)),
    ("RiggedFigure/RiggedFigure.glb", 30, (0, 37)),  # two keys: no rate evident
])
def test_a_rig_file_plays_at_its_source_rate_over_its_source_frames(assets, rel, rate, frames):
    scene = Scene.from_rig_file(assets / rel)
    assert scene.frame_rate == rate
    assert scene.frame_range() == frames


def test_a_frame_range_outside_the_clip_is_refused_naming_the_clip_range(assets, tmp_path, capsys):
    scene = Scene.from_rig_file(assets / "CesiumMan" / "CesiumMan.glb")
    with pytest.raises(SceneError, match=r"outside clip 'animation_0', which spans frames 1:48 at 24 fps"):
        FramePlan.for_scene(scene, (0, 10))
    out = tmp_path / "o.usdc"
    assert main(["skin", str(assets / "CesiumMan" / "CesiumMan.glb"), "-o", str(out), "--frames", "40:60", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("warpskin: error: frames 40:60 are outside clip 'animation_0', which spans frames 1:48")
    assert not out.exists() and not list(tmp_path.iterdir())


@pytest.mark.parametrize("flag, value", [("--fps", "0"), ("--fps", "-24"), ("--fps", "nan"), ("--unit-scale", "0"),
                                         ("--unit-scale", "x")])
def test_bad_rates_and_scales_exit_2(tmp_path, capsys, flag, value):
    assert main(["skin", "arm", "-o", str(tmp_path / "o.usdc"), flag, value, "--quiet"]) == 2
    assert f"{flag} must be a positive number, got '{value}'" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Bakes against their source (usd-core's UsdSkel skinning of the usdz, the same animation as
# the glb, whose vertices are in the same order)
# --------------------------------------------------------------------------------------------
def _cesium_usdz(assets):
    p = assets / "usd" / "CesiumMan" / "CesiumMan.usdz"
    if not p.is_file():
        pytest.skip(f"{p} is absent")
    stage = Usd.Stage.Open(str(p))
    mesh = next(str(q.GetPath()) for q in stage.Traverse() if q.IsA(UsdGeom.Mesh))
    return stage, mesh


@pytest.mark.parametrize("rel", ["usd/CesiumMan/CesiumMan.usdz", "CesiumMan/CesiumMan.glb"])
def test_a_skin_bake_lines_up_with_its_source_at_every_time_code(assets, tmp_path, rel):
    src, mesh = _cesium_usdz(assets)
    out = tmp_path / "bake.usdc"
    assert main(["skin", str(assets / rel), "-o", str(out), "--topology", "file", "--quiet"]) == 0
    stage, samples = _skin_samples(out)
    assert stage.GetTimeCodesPerSecond() == 24 and stage.GetFramesPerSecond() == 24
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 48.0)
    assert sorted(samples) == [float(f) for f in range(1, 49)]
    size = float(np.linalg.norm(np.ptp(usd_skinned_world(src, mesh, 1.0), axis=0)))
    worst = max(float(np.abs(pts - usd_skinned_world(src, mesh, tc)).max()) for tc, pts in samples.items())
    assert worst < TOL * size, f"{rel}: {worst / size:.3g} of the model size"


def test_fps_resamples_and_start_frame_shifts(assets, tmp_path):
    src, mesh = _cesium_usdz(assets)
    usdz = assets / "usd" / "CesiumMan" / "CesiumMan.usdz"
    out = tmp_path / "thirty.usdc"
    assert main(["skin", str(usdz), "-o", str(out), "--topology", "file", "--fps", "30", "--quiet"]) == 0
    stage, samples = _skin_samples(out)
    assert stage.GetTimeCodesPerSecond() == 30
    assert sorted(samples) == [float(f) for f in range(2, 61)]  # 1/24 s .. 2 s at 30 fps
    for tc in (2.0, 17.0, 45.0):  # 30 fps frame k is the source's time code 24 k / 30
        ref = usd_skinned_world(src, mesh, tc * 24 / 30)
        assert np.abs(samples[tc] - ref).max() < TOL * float(np.linalg.norm(np.ptp(ref, axis=0)))
    shifted = tmp_path / "shifted.usdc"
    assert main(["skin", str(usdz), "-o", str(shifted), "--topology", "file", "--frames", "10:20", "--start-frame", "1001",
                 "--quiet"]) == 0
    stage, moved = _skin_samples(shifted)
    assert sorted(moved) == [float(f) for f in range(1001, 1012)]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1001.0, 1011.0)
    for k in (0, 5, 10):  # source frame 10 + k, written at 1001 + k
        ref = usd_skinned_world(src, mesh, 10.0 + k)
        assert np.abs(moved[1001.0 + k] - ref).max() < TOL * float(np.linalg.norm(np.ptp(ref, axis=0)))


def test_a_simulate_bake_lines_up_with_its_source(assets, tmp_path):
    # the physical skin's bake: its LBS comparison matches usd-core's skinning of the usdz at
    # every written time code, and both meshes carry the file's UVs
    src, mesh = _cesium_usdz(assets)
    out = tmp_path / "walk.usdc"
    assert main(["simulate", str(assets / "usd" / "CesiumMan" / "CesiumMan.usdz"), "-o", str(out), "--frames", "1:3",
                 "--lbs", "--preroll", "0", "--quiet"]) == 0
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == 24
    lbs = UsdGeom.Mesh(prim(stage, "lbs"))
    assert lbs.GetPointsAttr().GetTimeSamples() == [1.0, 2.0, 3.0]
    for tc in (1.0, 2.0, 3.0):
        ref = usd_skinned_world(src, mesh, tc)
        got = np.asarray(lbs.GetPointsAttr().Get(tc), dtype=np.float64)
        assert np.abs(got - ref).max() < TOL * float(np.linalg.norm(np.ptp(ref, axis=0)))
    for name in ("skin", "lbs"):
        st = UsdGeom.PrimvarsAPI(prim(stage, name)).GetPrimvar("st")
        assert st and len(st.Get()) == 3 * 4672

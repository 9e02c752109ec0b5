"""The length unit physics takes a file in (:mod:`warpskin.units`): the power of ten of the metre
nearest human size, so that a character gives the same result, relative to its size, at any
power-of-ten scale of its file; ``[solver] units = "file"`` takes metres."""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpskin.units import HUMAN_SIZE, describe, extent, file_unit, metres_per_unit


@pytest.mark.parametrize("size, unit", [(1.8, 1.0), (0.61, 1.0), (4.9, 1.0), (155.0, 0.01), (0.18, 10.0),
                                        (0.0012, 1000.0), (1700.0, 0.001), (0.021, 100.0)])
def test_the_unit_brings_the_size_nearest_a_human(size, unit):
    assert metres_per_unit(size) == pytest.approx(unit, rel=1e-12)
    # nearest in ratio: no other power of ten brings it closer
    err = abs(math.log(size * unit / HUMAN_SIZE))
    for k in range(-6, 7):
        assert err <= abs(math.log(size * 10.0 ** k / HUMAN_SIZE)) + 1e-12


def test_the_unit_changes_halfway_between_decades_in_ratio():
    # the boundaries on purpose, with a band either side (no test at the exact float tie)
    edge = HUMAN_SIZE / math.sqrt(10.0)  # 0.538 m
    assert metres_per_unit(edge * 1.01) == 1.0 and metres_per_unit(edge * 0.99) == pytest.approx(10.0)
    edge = HUMAN_SIZE * math.sqrt(10.0)  # 5.38 m
    assert metres_per_unit(edge * 0.99) == 1.0 and metres_per_unit(edge * 1.01) == pytest.approx(0.1)


@pytest.mark.parametrize("size", [0.0, -1.0, float("nan"), float("inf")])
def test_no_size_takes_metres(size):
    assert metres_per_unit(size) == 1.0


def test_the_file_unit_follows_the_setting():
    pts = np.array([[0.0, 0.0, 0.0], [1.2, 155.0, 30.0]])  # a Fox-sized character, in centimetres
    assert file_unit("auto", pts) == pytest.approx(0.01) and file_unit("file", pts) == 1.0
    with pytest.raises(ValueError, match="units must be 'auto' or 'file', got 'metres'"):
        file_unit("metres", pts)


def test_extent_and_names():
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 1.7, -0.3]])
    assert extent(pts) == pytest.approx(1.7)
    assert extent(np.zeros((0, 3))) == 0.0 and extent([[np.nan, 0, 0]]) == 0.0
    assert describe(0.01) == "1 cm" and describe(1000.0) == "1 km" and describe(10.0) == "10 m"


def _arm_scene(tmp_path, scale: float | None, units: str = "auto"):
    from warpskin.scene import load_scene

    text = "[rig]\ngenerator = 'arm'\n"
    if scale is not None:
        text += f"unit_scale = {scale!r}\n"
    text += ("[rig.params]\nrings = 30\nsegments = 20\n[animation]\nframes = [20, 30]\n"
             f"[solver]\nunits = '{units}'\n")
    path = tmp_path / f"arm_{scale}_{units}.toml"
    path.write_text(text)
    return load_scene(path)


def _skin(path) -> list[np.ndarray]:
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and not p.GetName().endswith("_lbs"))
    attr = mesh.GetPointsAttr()
    return [np.asarray(attr.Get(t), dtype=np.float64) for t in attr.GetTimeSamples()]


@pytest.fixture(scope="module")
def arm_at_human_scale(tmp_path_factory):
    from warpskin.run import simulate

    tmp = tmp_path_factory.mktemp("units")
    simulate(_arm_scene(tmp, None), tmp / "ref.usdc", device="cpu", progress=False)
    return _skin(tmp / "ref.usdc")


@pytest.mark.parametrize("scale", [1e-3, 1e3])
@pytest.mark.slow
def test_the_same_arm_at_another_scale_moves_alike(tmp_path, device, arm_at_human_scale, scale):
    # the arm 0.6 mm or 600 m long in its file (lengths times 1e-3 or 1e3; gravity acts in the
    # unit physics takes the file in): every written point, divided by the scale, where the arm
    # in metres puts it, within float32 noise; taken in metres, the file's sag differs by far more
    from warpskin.run import simulate

    ref = arm_at_human_scale
    diag = float(np.linalg.norm(np.ptp(ref[0], axis=0)))
    run = simulate(_arm_scene(tmp_path, scale), tmp_path / "scaled.usdc", device=device, progress=False)
    assert run.summary["length_unit_m"] == pytest.approx(1.0 / scale)
    got = _skin(tmp_path / "scaled.usdc")
    assert len(got) == len(ref) == 11
    worst = max(float(np.abs(g / scale - r).max()) for g, r in zip(got, ref))
    assert worst < 1e-4 * diag
    # the same file in metres: a 600 m arm barely sags, a 0.6 mm one is flattened against its tether
    if device == "cpu":
        simulate(_arm_scene(tmp_path, scale, units="file"), tmp_path / "metres.usdc", device=device, progress=False,
                 allow_unstable=True)  # the 0.6 mm arm in metres leaves its range (held at the tether's cap)
        far = max(float(np.abs(g / scale - r).max()) for g, r in zip(_skin(tmp_path / "metres.usdc"), ref))
        assert far > 1e-3 * diag > 10 * worst

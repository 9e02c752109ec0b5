"""USD exporter: round trip through usd-core, atomic writes, clear errors."""

from __future__ import annotations

import os

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpskin.io.usd_export import ExportError, UsdSkinWriter
from warpskin.scenes.arm import make_arm
from oracles import prim


@pytest.fixture(scope="module")
def arm():
    return make_arm(rings=12, segments=10)


@pytest.mark.parametrize("ext", [".usdc", ".usda", ".usd"])
def test_round_trip_every_time_sample(tmp_path, arm, ext):
    rng = np.random.default_rng(0)
    frames = {f: arm.vertices + rng.normal(scale=0.01, size=arm.vertices.shape) for f in range(3, 9)}
    target = tmp_path / f"out{ext}"
    with UsdSkinWriter(target, fps=24, up_axis="Z", meters_per_unit=1.0) as out:
        out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
        out.add_mesh("rest", arm.triangles, rest_points=arm.vertices, animated=False, purpose="guide")
        for f, pts in frames.items():
            out.write_frame(f, {"skin": pts})
    assert sorted(os.listdir(tmp_path)) == [target.name]  # no temp file left behind

    stage = Usd.Stage.Open(str(target))
    assert stage.GetTimeCodesPerSecond() == 24 and stage.GetFramesPerSecond() == 24
    assert stage.GetStartTimeCode() == 3 and stage.GetEndTimeCode() == 8
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    assert np.array_equal(np.array(mesh.GetFaceVertexCountsAttr().Get()), np.full(arm.triangle_count, 3))
    assert np.array_equal(np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), arm.triangles)
    attr = mesh.GetPointsAttr()
    assert attr.GetTimeSamples() == list(map(float, frames))
    for f, pts in frames.items():
        got = np.array(attr.Get(f))
        assert np.array_equal(got, pts.astype(np.float32))
        ext_got = np.array(mesh.GetExtentAttr().Get(f))
        assert np.allclose(ext_got, [pts.min(0), pts.max(0)], atol=1e-7)
    # topology is written once (no time samples), the static prim has none
    assert mesh.GetFaceVertexIndicesAttr().GetNumTimeSamples() == 0
    rest = UsdGeom.Mesh(prim(stage, "rest"))
    assert rest.GetPointsAttr().GetNumTimeSamples() == 0
    assert rest.GetPurposeAttr().Get() == UsdGeom.Tokens.guide


def test_failure_mid_write_leaves_no_file(tmp_path, arm):
    target = tmp_path / "out.usdc"
    with pytest.raises(RuntimeError, match="boom"):
        with UsdSkinWriter(target) as out:
            out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
            out.write_frame(0, {"skin": arm.vertices})
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []


def test_failure_keeps_previous_file_intact(tmp_path, arm):
    target = tmp_path / "out.usdc"
    with UsdSkinWriter(target) as out:
        out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
        out.write_frame(0, {"skin": arm.vertices})
    before = target.read_bytes()
    bad = arm.vertices.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ExportError, match=r"frame 1: mesh 'skin' has a NaN or inf position at vertex 5"):
        with UsdSkinWriter(target) as out:
            out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
            out.write_frame(0, {"skin": arm.vertices * 2})
            out.write_frame(1, {"skin": bad})
    assert target.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"]


def test_failure_in_final_rename_leaves_no_file(tmp_path, arm, monkeypatch):
    target = tmp_path / "out.usdc"

    def fail(*args, **kwargs):
        raise OSError("disk full")

    out = UsdSkinWriter(target)
    out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
    out.write_frame(0, {"skin": arm.vertices})
    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(ExportError, match="disk full"):
        out.close()
    assert os.listdir(tmp_path) == []


def test_bad_arguments(tmp_path, arm):
    with pytest.raises(ExportError, match="must end in one of"):
        UsdSkinWriter(tmp_path / "out.obj")
    with pytest.raises(ExportError, match="does not exist"):
        UsdSkinWriter(tmp_path / "missing" / "out.usdc")
    with pytest.raises(ExportError, match="fps must be a positive"):
        UsdSkinWriter(tmp_path / "out.usdc", fps=0)
    with UsdSkinWriter(tmp_path / "out.usdc") as out:
        out.add_mesh("skin", arm.triangles, rest_points=arm.vertices)
        with pytest.raises(ExportError, match="expects 122 points"):
            out.write_frame(0, {"skin": arm.vertices[:-1]})
        with pytest.raises(ExportError, match="no mesh 'body'"):
            out.write_frame(0, {"body": arm.vertices})
        with pytest.raises(ExportError, match="already added"):
            out.add_mesh("skin", arm.triangles)
        out.write_frame(0, {"skin": arm.vertices})


def test_materials_of_one_name_stay_apart_and_shared_ones_are_written_once(tmp_path):
    from pxr import Usd, UsdShade

    from warpskin.io.render import Material

    red, blue = Material("Body.001", (1.0, 0.0, 0.0, 1.0)), Material("Body_001", (0.0, 0.0, 1.0, 1.0))
    with UsdSkinWriter(tmp_path / "m.usda", root="M") as out:
        a, b, again = out.add_material(red), out.add_material(blue), out.add_material(Material("Body.001", red.base_color))
    assert a != b and again == a
    stage = Usd.Stage.Open(str(tmp_path / "m.usda"))
    colours = [tuple(UsdShade.Material(stage.GetPrimAtPath(p)).ComputeSurfaceSource()[0].GetInput("diffuseColor").Get())
               for p in (a, b)]
    assert colours == [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)]


def test_a_folder_that_refuses_files_is_named_before_any_work(tmp_path, monkeypatch):
    # a folder access() calls writable that refuses a file anyway (a read-only or virtual file
    # system): the up-front check and the writer each name the path; nothing is left behind
    import errno
    import tempfile

    from warpskin.io.usd_export import check_output_path

    def refuse(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(ExportError, match=r"bake\.usdc: cannot write in folder .*\(Read-only file system\)"):
        check_output_path(tmp_path / "bake.usdc")
    with pytest.raises(ExportError, match=r"bake\.usdc: cannot write in folder .*\(Read-only file system\)"):
        UsdSkinWriter(tmp_path / "bake.usdc", fps=24.0)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, a folder that refuses files")
def test_simulate_into_a_folder_that_refuses_files_exits_2(capsys):
    from warpskin.cli import main

    assert main(["simulate", "arm", "--frames", "0:1", "-o", "/proc/bake.usdc", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "/proc/bake.usdc: cannot write in folder /proc" in err and "internal error" not in err


def test_one_writer_per_output_and_a_killed_runs_leftovers_go(tmp_path):
    # a second writer of the same file while the first writes is refused, naming the path; a
    # killed run's temporary file and lock are cleared by the next writer; nothing is left
    from warpskin.io.usd_export import OutputLock, check_output_path

    out = tmp_path / "bake.usdc"
    first = UsdSkinWriter(out, fps=24.0)
    with pytest.raises(ExportError, match=r"bake\.usdc: another run is writing this file"):
        UsdSkinWriter(out, fps=24.0)
    with pytest.raises(ExportError, match=r"bake\.usdc: another run is writing this file"):
        check_output_path(out)
    first.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bake.usdc"]
    # what SIGKILL leaves: a temporary file of the stage, and a lock file nobody holds
    stale = tmp_path / ".bake.k1ll3d00.tmp.usdc"
    stale.write_bytes(b"x" * 492)
    (tmp_path / ".bake.usdc.lock").write_bytes(b"")
    other = tmp_path / ".other.k1ll3d00.tmp.usdc"  # another output's: not ours to remove
    other.write_bytes(b"x")
    check_output_path(out)
    with UsdSkinWriter(out, fps=24.0) as w:
        assert not stale.exists()
        w.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".other.k1ll3d00.tmp.usdc", "bake.usdc"]
    lock = OutputLock(out).acquire()
    assert lock.lock_path.exists()
    lock.release()
    assert not lock.lock_path.exists()

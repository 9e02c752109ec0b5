"""The ``warpskin`` command line, run in-process and once as a real console process."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpskin.cli import main
from oracles import prim


def _frames(path):
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    return stage, mesh.GetPointsAttr().GetTimeSamples()


def test_skin_arm_writes_usd_with_all_frames(tmp_path, capsys, device):
    out = tmp_path / "arm.usdc"
    assert main(["skin", "arm", "-o", str(out), "--quiet", "--device", device]) == 0
    stage, samples = _frames(out)
    assert samples == [float(f) for f in range(151)]  # 5 s at 30 fps, inclusive
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 150
    assert "wrote" in capsys.readouterr().out


def test_skin_dqs_with_lbs_and_rest_prims(tmp_path):
    out = tmp_path / "arm.usda"
    assert main(["skin", "arm", "-o", str(out), "--method", "dqs", "--with-lbs", "--with-rest",
                 "--frames", "40:49", "--quiet"]) == 0
    stage, samples = _frames(out)
    assert samples == [float(f) for f in range(40, 50)]
    for name in ("lbs", "rest"):
        assert prim(stage, f"{name}").IsValid()
    skin = np.array(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().Get(45))
    lbs = np.array(UsdGeom.Mesh(prim(stage, "lbs")).GetPointsAttr().Get(45))
    assert np.abs(skin - lbs).max() > 1e-3  # DQS and LBS differ at a bent elbow


def test_skin_cesium_man_glb(tmp_path, assets):
    out = tmp_path / "cesium.usdc"
    rig = assets / "CesiumMan" / "CesiumMan.glb"
    assert main(["skin", str(rig), "-o", str(out), "--fps", "24", "--quiet"]) == 0
    stage, samples = _frames(out)
    assert len(samples) == 48 and min(samples) == 1  # keys from 1/24 to 2 s: the source's frames 1..48
    pts = np.array(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().Get(0))
    assert pts.shape == (3273, 3)  # the file's own vertices by default
    welded = tmp_path / "welded.usdc"
    assert main(["skin", str(rig), "-o", str(welded), "--topology", "welded", "--frames", "1:2", "--quiet"]) == 0
    stage, _ = _frames(welded)
    assert np.array(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().Get(0)).shape == (2338, 3)


def test_skin_cesium_man_file_topology(tmp_path, assets):
    out = tmp_path / "cesium.usdc"
    rig = assets / "usd" / "CesiumMan" / "CesiumMan.usdz"
    assert main(["skin", str(rig), "-o", str(out), "--topology", "file", "--frames", "1:3", "--quiet"]) == 0
    stage, samples = _frames(out)
    pts = np.array(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().Get(1))
    assert pts.shape == (3273, 3) and len(samples) == 3


def test_info_and_scenes(capsys):
    assert main(["scenes"]) == 0
    assert "arm" in capsys.readouterr().out
    assert main(["info", "arm"]) == 0
    text = capsys.readouterr().out
    assert "2918 vertices" in text and "closed, manifold" in text and "elbow" in text
    # clips in frames, as --frames takes them (the arm scene: 0:150 at 30 fps), and the unit taken
    from warpskin.scene import load_scene

    scene = load_scene("arm")
    first, last = scene.clip_frames()
    assert f"frames {first}:{last} at {scene.frame_rate:g} fps" in text and (first, last) == (0, 150)
    assert "physics takes 1 unit as 1 m" in text


@pytest.mark.parametrize(
    "argv, message",
    [
        (["skin", "nosuchscene", "-o", "x.usdc"], "unknown scene 'nosuchscene'"),
        (["skin", "arm", "-o", "x.obj"], "must end in one of"),
        (["skin", "arm", "-o", "x.usdc", "--clip", "walk"], "no clip named 'walk'"),
        (["skin", "missing.glb", "-o", "x.usdc"], "missing.glb: no such file"),
        (["info", "missing.usdz"], "missing.usdz: no such file"),
    ],
)
def test_errors_are_one_line_without_traceback(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert err.strip().count("\n") == 0 or all("Warp" in line for line in err.strip().splitlines()[:-1])
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_console_process_exit_code_and_message(tmp_path):
    r = subprocess.run([sys.executable, "-m", "warpskin", "skin", "arm", "-o", str(tmp_path / "a.usdc"),
                        "--frames", "9:3"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert "--frames 9:3" in r.stderr and "Traceback" not in r.stderr


def test_warmup_loads_every_kernel_module(capsys):
    import pkgutil

    import warp as wp

    import warpskin.kernels as kernels

    names = [f"{kernels.__name__}.{m.name}" for m in pkgutil.iter_modules(kernels.__path__)]
    assert {"warpskin.kernels.collision", "warpskin.kernels.popping", "warpskin.kernels.constraints"} <= set(names)
    for n in names:  # forget what earlier tests loaded
        __import__(n)
        wp.get_module(n).unload()
    assert main(["warmup", "--device", "cpu"]) == 0
    assert "kernels ready on cpu" in capsys.readouterr().out
    for n in names:
        assert wp.get_module(n).execs, f"{n} not loaded"


def test_projection_option_sets_the_layer_depths(tmp_path, capsys):
    # a user lowers the layers' depths without writing a scene file
    import json as _json

    out = tmp_path / "l.usdc"
    assert main(["layers", "arm", "-o", str(out), "--projection", "0.1,0.3,0.6", "--json"]) == 0
    text = capsys.readouterr().out
    summary = _json.loads(text[: text.rindex("}") + 1])
    stage = Usd.Stage.Open(str(out))
    skin = np.array(UsdGeom.Mesh(prim(stage, "layers/skin")).GetPointsAttr().Get())
    bone = np.array(UsdGeom.Mesh(prim(stage, "layers/bone")).GetPointsAttr().Get())
    fat = np.array(UsdGeom.Mesh(prim(stage, "layers/fat")).GetPointsAttr().Get())
    ratio = np.linalg.norm(fat - skin, axis=1) / np.linalg.norm(bone - skin, axis=1)
    np.testing.assert_allclose(ratio, 0.1 / 0.6, rtol=1e-4)  # fat at 0.1, bone at 0.6 of each segment
    assert summary["depth_reduced_vertices"] == 0
    assert main(["layers", "arm", "-o", str(out), "--projection", "0.5,0.3,0.6"]) == 2
    assert "need 0 < FAT < MUSCLE < BONE < 1" in capsys.readouterr().err


@pytest.mark.slow
def test_warnings_are_one_plain_line_and_no_native_cuda_notice(tmp_path, assets):
    # a separate process: the "no CUDA driver" notice is printed by Warp's C library on its
    # stderr file descriptor at start-up, and Python's warnings carry file paths and source
    # lines by default; neither reaches the user of a CPU command (the Fox, 155 units across,
    # gets the unit-scale warning)
    run = subprocess.run([sys.executable, "-m", "warpskin", "simulate", str(assets / "Fox" / "Fox.glb"), "--frames",
                          "0:0", "-o", str(tmp_path / "fox.usda"), "--quiet"], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path)  # not the checkout, whose warpskin/ folder would shadow the installed package
    assert run.returncode == 0, run.stderr
    warn = [ln for ln in run.stderr.splitlines() if "outside 5 cm - 20 m" in ln]
    assert len(warn) == 1 and warn[0].startswith("warpskin: warning: "), run.stderr
    assert "Warp CUDA warning" not in run.stderr
    assert ".py:" not in run.stderr and "rig.validate" not in run.stderr


# --------------------------------------------------------------------------------------------
# CLI conventions
# --------------------------------------------------------------------------------------------
def test_version_and_global_flags_anywhere(capsys):
    import warpskin

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"warpskin {warpskin.__version__}"
    assert main(["scenes", "--debug"]) == 0  # a global flag after the command
    assert "arm" in capsys.readouterr().out


def test_output_path_is_checked_before_any_work(tmp_path, capsys):
    # the rig named is not even there: a refusal that names the output was made before any
    # loading (the missing rig would have been the error otherwise)
    glb = tmp_path / "not_there.glb"
    cases = [
        (tmp_path, "is a folder"),
        (tmp_path / "missing" / "o.usdc", "does not exist"),
        (tmp_path / ("n" * 245 + ".usdc"), "over this file system's"),
        (tmp_path / "o.obj", "output must end in one of"),
    ]
    for out, message in cases:
        assert main(["simulate", str(glb), "-o", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0] and "not_there" not in err[0], err
    assert main(["simulate", str(glb), "-o", str(tmp_path / "ok.usdc"), "--quiet"]) == 2  # the rig, once the output is fine
    assert "not_there.glb" in capsys.readouterr().err
    copy = tmp_path / "rig.usda"  # -o naming the input: refused, the input untouched
    copy.write_text("#usda 1.0\n")
    before = copy.read_bytes()
    assert main(["skin", str(copy), "-o", str(copy), "--quiet"]) == 2
    assert "is the input file" in capsys.readouterr().err and copy.read_bytes() == before


def test_json_summaries(tmp_path, capsys):
    assert main(["skin", "arm", "-o", str(tmp_path / "s.usdc"), "--frames", "0:2", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["frames"] == 3 and s["vertices_written"] == 2918 and s["fps"] == 30 and s["path"].endswith("s.usdc")
    assert main(["simulate", "arm", "-o", str(tmp_path / "p.usdc"), "--frames", "0:1", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["frames"] == 2 and s["particles"] == 11672 and "max_volume_deviation" in s
    assert main(["pop", "popping_arm", "-o", str(tmp_path / "q.usdc"), "--frames", "0:2", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["frames"] == 3 and s["groups"]


@pytest.mark.parametrize("signame, code, wait", [("SIGTERM", 143, 0.0), ("SIGHUP", 129, 0.0), ("SIGTERM", 143, 4.0)])
@pytest.mark.slow
def test_a_stopped_run_keeps_its_finished_frames_and_no_temp_file(tmp_path, signame, code, wait):
    # a stop signal as soon as the output is opened, or seconds into the run: no temporary file
    # is left, and the frames finished before the signal are kept in a valid file (as a failed
    # run keeps them), as many as the message says
    import signal
    import time

    out = tmp_path / "arm.usdc"

    def default_disposition():
        # as from a terminal: a test run under nohup hands an ignored SIGHUP down, which the
        # CLI rightly keeps ignored (it then finished and exited 0 here)
        signal.signal(getattr(signal, signame), signal.SIG_DFL)

    proc = subprocess.Popen([sys.executable, "-m", "warpskin", "simulate", "arm", "-o", str(out), "--quiet"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_disposition)
    try:
        deadline = time.monotonic() + 300  # kernels may compile first on a fresh cache
        while not [p for p in tmp_path.iterdir() if p.name.startswith(".arm.")]:
            assert proc.poll() is None and time.monotonic() < deadline, "the run never opened its output"
            time.sleep(0.2)
        time.sleep(wait)
        proc.send_signal(getattr(signal, signame))
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code
    assert f"stopped by {signame}" in err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    kept = re.search(r"the (\d+) frames finished before it were written to (\S+)", err)
    if kept is None:
        assert "nothing was written" in err and list(tmp_path.iterdir()) == []
    else:
        from pxr import Usd, UsdGeom

        assert kept.group(2) == str(out)
        stage = Usd.Stage.Open(str(out))
        mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        assert len(mesh.GetPointsAttr().GetTimeSamples()) == int(kept.group(1)) >= 1
    if wait > 0:
        assert kept is not None and int(kept.group(1)) < 151  # stopped mid-run, frames kept


@pytest.mark.slow
def test_info_reports_pieces_loops_and_the_simulation_path(assets, capsys):
    # an open strip (SimpleSkin: one piece, one boundary loop, trimesh agrees) goes through the
    # cage; the closed arm directly; RobotExpressive lists its other meshes
    import trimesh

    strip = assets / "SimpleSkin" / "SimpleSkin.gltf"
    assert main(["info", str(strip), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    from warpskin.io import load_rig

    rig = load_rig(strip)
    tm = trimesh.Trimesh(rig.vertices, rig.triangles, process=False)
    assert s["pieces"] == tm.body_count == 1
    assert s["boundary_loops"] == len(trimesh.graph.connected_components(tm.edges[trimesh.grouping.group_rows(
        tm.edges_sorted, require_count=1)])) == 1
    assert s["simulation"] == "cage"
    assert main(["info", "arm", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["pieces"], s["boundary_loops"], s["simulation"]) == (1, 0, "direct")
    assert main(["info", str(assets / "RobotExpressive" / "RobotExpressive.glb"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert len(s["other_meshes"]) == 13 and "Torso" in s["other_meshes"]
    assert s["rigid_pieces"] == 12  # the rigidly parented parts (the hands' weights vary)


def test_nohup_keeps_a_run_going(tmp_path):
    # a SIGHUP that the parent ignores (nohup) is not turned into a stop
    import signal
    import time

    out = tmp_path / "arm.usdc"
    proc = subprocess.Popen([sys.executable, "-m", "warpskin", "skin", "arm", "-o", str(out), "--quiet"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + 300
        while not [p for p in tmp_path.iterdir() if p.name.startswith(".arm.")] and proc.poll() is None:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        if proc.poll() is None:
            proc.send_signal(signal.SIGHUP)
        proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and out.is_file()


def test_the_python_api_prints_nothing_on_stdout(tmp_path):
    # a library says nothing of its own accord: no Warp banner, no module-load lines (a separate
    # process: Warp prints its banner once, at its first initialisation)
    code = ("from warpskin.run import skin_to_usd; from warpskin.scene import load_scene; "
            f"skin_to_usd(load_scene('arm'), {str(tmp_path / 'a.usdc')!r}, frames=(0, 1), progress=False)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert run.stdout == "" and (tmp_path / "a.usdc").is_file()

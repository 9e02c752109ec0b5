"""``warpskin batch``: jobs in processes of their own write what their single commands write,
a rerun does no work, a killed worker's job runs again, a bad job is recorded while the others
finish, and a bad JOBS file fails before anything runs."""

from __future__ import annotations

import json
import os
import signal
import threading
import time

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from test_gltf_import import make_box, quat_z
from warpskin.cli import main


def _points(path) -> dict:
    """``{prim path: [points per time sample]}`` of every mesh in a bake."""
    stage = Usd.Stage.Open(str(path))
    out = {}
    for p in stage.Traverse():
        if p.IsA(UsdGeom.Mesh):
            attr = UsdGeom.Mesh(p).GetPointsAttr()
            out[str(p.GetPath())] = [np.asarray(attr.Get(t)) for t in attr.GetTimeSamples()]
    return out


def _same_bake(a, b) -> None:
    pa, pb = _points(a), _points(b)
    assert pa.keys() == pb.keys() and pa
    for k in pa:
        assert len(pa[k]) == len(pb[k]) and all(np.array_equal(x, y) for x, y in zip(pa[k], pb[k])), k


def _manifest(out) -> dict:
    return json.loads((out / "manifest.json").read_text())["jobs"]


@pytest.mark.slow
def test_a_batch_bakes_what_its_commands_bake_and_a_rerun_does_no_work(tmp_path, capsys):
    bad = tmp_path / "broken.glb"
    bad.write_bytes(b"not a glTF file")
    jobs = tmp_path / "jobs.toml"
    jobs.write_text(f'''[[job]]
rig = "arm"
command = "skin"
frames = "0:3"

[[job]]
rig = "arm"
frames = "0:2"
output = "arm/sim.usdc"
args = ["--lbs"]

[[job]]
rig = "popping_arm"
command = "pop"
frames = "0:5"
args = ["--bpm", "120"]

[[job]]
rig = "{bad.name}"
''')
    out = tmp_path / "out"
    assert main(["batch", str(jobs), "-o", str(out), "--workers", "2", "--quiet"]) == 3  # one failed
    text = capsys.readouterr().out
    assert "3 ran, 0 up to date, 1 failed" in text
    m = _manifest(out)
    assert [m[k]["status"] for k in ("arm/default.usdc", "arm/sim.usdc", "popping_arm/default.usdc")] == ["ok"] * 3
    broken = m["broken/default.usdc"]
    assert broken["status"] == "failed" and broken["exit_code"] == 2 and "broken.glb" in broken["message"]
    assert not (out / "broken" / "default.usdc").exists()
    # each bake is what its single command writes, bit for bit
    for rel, argv in (("arm/default.usdc", ["skin", "arm", "--frames", "0:3"]),
                      ("arm/sim.usdc", ["simulate", "arm", "--frames", "0:2", "--lbs"]),
                      ("popping_arm/default.usdc", ["pop", "popping_arm", "--frames", "0:5", "--bpm", "120"])):
        alone = tmp_path / rel.replace("/", "_")
        assert main([*argv, "-o", str(alone), "--quiet"]) == 0
        _same_bake(out / rel, alone)
    index = (out / "index.md").read_text()
    assert "| arm/sim.usdc | simulate | ok |" in index and "| broken/default.usdc | simulate | failed |" in index
    sim = next(line for line in index.splitlines() if line.startswith("| arm/sim.usdc"))
    assert "cpu, 3 frames" in sim and "ms/step" in sim and "(LBS " in sim  # its summary's figures
    # a picture of each bake (the written skin beside its LBS guide) in the index, none for the failure
    thumb = out / "thumbs" / "arm__sim.usdc.png"
    assert f"![arm/sim.usdc](thumbs/{thumb.name})" in sim and thumb.is_file()
    assert "![" not in next(line for line in index.splitlines() if line.startswith("| broken/"))
    pytest.importorskip("matplotlib")
    from matplotlib.image import imread

    image = imread(thumb)
    assert image.shape[:2] == (240, 320)
    ink = image[:, :, :3].min(axis=2) < 0.9  # not the white background
    left, right = ink[:, :160], ink[:, 160:]
    assert 0.01 < left.mean() < 0.6 and 0.01 < right.mean() < 0.6  # the arm, and its LBS beside it
    # the two drawn at one scale: the same size on the page within two pixels (frame 1: near LBS)
    for axis in (0, 1):
        spans = [np.nonzero(half.any(axis=axis))[0] for half in (left, right)]
        assert abs((spans[0][-1] - spans[0][0]) - (spans[1][-1] - spans[1][0])) <= 2
    drawn = thumb.stat().st_mtime_ns
    # a rerun does no work: the finished jobs are up to date (their files untouched), the
    # failed one runs again
    stamps = {k: (out / k).stat().st_mtime_ns for k in ("arm/default.usdc", "arm/sim.usdc")}
    capsys.readouterr()
    assert main(["batch", str(jobs), "-o", str(out), "--quiet"]) == 3
    assert "0 ran, 3 up to date, 1 failed" in capsys.readouterr().out
    assert {k: (out / k).stat().st_mtime_ns for k in stamps} == stamps
    assert thumb.stat().st_mtime_ns == drawn  # not drawn again
    again = _manifest(out)
    assert again["arm/sim.usdc"]["attempts"] == 1 and again["broken/default.usdc"]["attempts"] == 1
    # a changed input is not up to date
    jobs.write_text(jobs.read_text().replace('frames = "0:2"', 'frames = "0:1"'))
    assert main(["batch", str(jobs), "-o", str(out), "--quiet"]) == 3
    assert "1 ran, 2 up to date, 1 failed" in capsys.readouterr().out


@pytest.mark.slow
def test_a_killed_worker_is_run_again(tmp_path, capsys):
    jobs = tmp_path / "jobs.toml"
    jobs.write_text('[[job]]\nrig = "arm"\nframes = "0:24"\n')
    out = tmp_path / "out"
    done: list[int] = []
    batch = threading.Thread(target=lambda: done.append(main(["batch", str(jobs), "-o", str(out), "--quiet"])))
    batch.start()
    pid = None
    deadline = time.monotonic() + 60.0
    while pid is None and time.monotonic() < deadline:  # its worker, as the manifest names it
        time.sleep(0.05)
        try:
            pid = _manifest(out)["arm/default.usdc"].get("pid")
        except (OSError, json.JSONDecodeError, KeyError):
            pass
    assert pid is not None
    time.sleep(1.0)  # mid-run (the bake takes several seconds)
    os.kill(pid, signal.SIGKILL)
    batch.join(timeout=300)
    assert done == [0]
    entry = _manifest(out)["arm/default.usdc"]
    assert entry["status"] == "ok" and entry["attempts"] == 2 and "pid" not in entry
    frames = _points(out / "arm" / "default.usdc")
    assert all(len(v) == 25 for v in frames.values())  # every frame written by the second run
    assert not [p for p in (out / "arm").iterdir() if p.name.startswith(".")]  # no temporary file left


@pytest.mark.parametrize("job, message", [
    ('rig = "arm"\ncolour = "red"', r"job 1 \(arm\): unknown key\(s\) \['colour'\]"),
    ('rig = "arm"\ncommand = "render"', r"job 1 \(arm\): command must be one of simulate, skin, pop, got 'render'"),
    ('rig = "arm"\nargs = ["--bogus"]', r"job 1 \(arm\): args: unrecognized arguments: --bogus"),
    ('rig = "arm"\nargs = ["-o", "x.usdc"]', r"job 1 \(arm\): args: -o is the batch's to set \(use the job's output key\)"),
    ('rig = "arm"\noutput = "../x.usdc"', r"output '../x.usdc' must stay inside OUTDIR"),
    ('rig = "nope.glb"', r"job 1 \(nope.glb\): rig '.*nope.glb' is neither a file nor a shipped scene"),
    ('rig = "arm"\nframes = "3"', r"frames must be \"A:B\" \(inclusive\), got '3'"),
    ('rig = "arm"\n[[job]]\nrig = "arm"', r"job 2 \(arm\): output 'arm/default.usdc' is also .*job 1 \(arm\)'s"),
])
def test_a_bad_jobs_file_names_the_job_and_runs_nothing(tmp_path, capsys, job, message):
    import re

    jobs = tmp_path / "jobs.toml"
    jobs.write_text(f"[[job]]\n{job}\n")
    out = tmp_path / "out"
    assert main(["batch", str(jobs), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(message, err[0]) and str(jobs) in err[0], err
    assert not out.exists()


def test_rig_files_with_every_clip(tmp_path, capsys):
    # a glTF box with two clips: one job per clip, each what `skin --clip NAME` writes
    hop = [(2, "translation", [0.0, 0.5, 1.0], np.array([[0.0, 0.0, 1.0], [0.0, 0.7, 1.0], [0.0, 0.0, 1.0]]), "LINEAR")]
    turn = [(2, "rotation", [0.0, 1.0], np.stack([quat_z(0.0), quat_z(90.0)]), "LINEAR")]
    rig = make_box(tmp_path, animations=[("hop", hop), ("turn", turn)])
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "*.glb"), "--clips", "all", "--command", "skin", "-o", str(out),
                 "--quiet"]) == 0
    assert "2 ran, 0 up to date, 0 failed" in capsys.readouterr().out
    for clip in ("hop", "turn"):
        alone = tmp_path / f"{clip}.usdc"
        assert main(["skin", str(rig), "--clip", clip, "-o", str(alone), "--quiet"]) == 0
        _same_bake(out / "box" / f"{clip}.usdc", alone)


@pytest.mark.slow
def test_the_same_bakes_through_a_ray_cluster(tmp_path, capsys, monkeypatch):
    # a local Ray cluster started here (`ray start --head`, without token authentication: a
    # test cluster of one machine), the batch connecting to its address: every job a Ray
    # task, every bake bit for bit what the local batch writes
    import shutil
    import socket
    import subprocess
    import sys
    from pathlib import Path

    pytest.importorskip("ray", reason="Ray is the test extra's (pip install '.[test]')")
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    jobs = tmp_path / "jobs.toml"
    jobs.write_text('[[job]]\nrig = "arm"\ncommand = "skin"\nframes = "0:3"\n\n'
                    '[[job]]\nrig = "popping_arm"\ncommand = "pop"\nframes = "0:5"\nargs = ["--bpm", "120"]\n')
    ray_cli = shutil.which("ray", path=str(Path(sys.executable).parent)) or "ray"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    import tempfile

    temp = tempfile.mkdtemp(prefix="wsray-", dir="/tmp")  # Ray's sockets need a short path
    start = subprocess.run([ray_cli, "start", "--head", f"--port={port}", "--num-cpus=2", "--include-dashboard=false",
                            "--node-ip-address=127.0.0.1", f"--temp-dir={temp}", "--disable-usage-stats"],
                           capture_output=True, text=True, timeout=180)
    assert start.returncode == 0, start.stderr[-2000:]
    try:
        assert main(["batch", str(jobs), "-o", str(tmp_path / "ray_out"), "--ray", f"127.0.0.1:{port}",
                     "--quiet"]) == 0
    finally:
        subprocess.run([ray_cli, "stop", "--force"], capture_output=True, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)
    assert main(["batch", str(jobs), "-o", str(tmp_path / "local_out"), "--quiet"]) == 0
    for rel in ("arm/default.usdc", "popping_arm/default.usdc"):
        _same_bake(tmp_path / "ray_out" / rel, tmp_path / "local_out" / rel)
    assert _manifest(tmp_path / "ray_out")["arm/default.usdc"]["status"] == "ok"


def test_cuda_jobs_get_a_gpu_each(tmp_path):
    # three jobs on --device cuda and two GPUs (given; the scheduling is the same with Warp's
    # count): each job runs with CUDA_VISIBLE_DEVICES one of its own, so at most two at a time
    # whatever --workers says; where no CUDA driver exists each job fails with its one line
    from warpskin.batch import jobs_for_rigs, run_batch

    jobs = jobs_for_rigs(["arm", "popping_arm", "mannequin"], tmp_path / "out", command="skin",
                         frames="0:1", args=["--device", "cuda"])
    result = run_batch(jobs, tmp_path / "out", workers=3, progress=False, gpus=2)
    gpus = [result.entries[j.id].get("gpu") for j in jobs]
    assert sorted(set(gpus)) == [0, 1] and len(gpus) == 3
    for j in jobs:
        e = result.entries[j.id]
        assert e["status"] == "ok" or (e["exit_code"] == 2 and "cuda" in e["message"].lower()), e


def _alive(pid: int) -> bool:
    """Whether process ``pid`` still runs (a zombie nobody reaped has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except OSError:
        return False


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="the parent-death signal is Linux's (prctl)")
def test_a_batch_killed_with_sigkill_takes_its_workers_with_it(tmp_path):
    # a farm's SIGKILL cannot be caught by the batch; its workers get SIGTERM from the kernel as it
    # dies, and end (keeping the frames they finished) instead of baking on for nothing
    import subprocess
    import sys

    jobs = tmp_path / "jobs.toml"
    jobs.write_text('[[job]]\nrig = "arm"\n')  # the whole clip: a minute of work
    out = tmp_path / "out"
    batch = subprocess.Popen([sys.executable, "-m", "warpskin", "batch", str(jobs), "-o", str(out), "--quiet"],
                             cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    pid = None
    deadline = time.monotonic() + 120.0
    try:
        while pid is None and time.monotonic() < deadline:
            time.sleep(0.1)
            try:
                pid = _manifest(out)["arm/default.usdc"].get("pid")
            except (OSError, json.JSONDecodeError, KeyError):
                pass
        assert pid is not None and _alive(pid)
        time.sleep(1.0)
        batch.kill()
        batch.wait(timeout=30)
        deadline = time.monotonic() + 30.0
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(pid), "the worker outlived its batch"
    finally:
        if batch.poll() is None:
            batch.kill()
        if pid is not None and _alive(pid):
            os.kill(pid, signal.SIGKILL)


def test_the_example_jobs_file_is_a_batch(tmp_path, capsys):
    # the jobs file the docs show reads as jobs of every command, and its skin job bakes
    from pathlib import Path

    from warpskin.batch import read_jobs, run_batch

    example = Path(__file__).resolve().parent.parent / "docs" / "examples" / "jobs.toml"
    jobs = read_jobs(example, tmp_path)
    assert [j.command for j in jobs] == ["simulate", "skin", "pop", "simulate"]
    assert len({j.output for j in jobs}) == len(jobs)
    skin = [j for j in jobs if j.command == "skin"]
    result = run_batch(skin, tmp_path, progress=False)
    assert result.failed == [] and (tmp_path / "arm" / "dqs.usdc").is_file()
    docs = (example.parent.parent / "batches.md").read_text()
    assert "{literalinclude} examples/jobs.toml" in docs

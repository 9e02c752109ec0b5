"""Pops on the beat: a tempo (``--bpm``) or a file of times (``--beats``) turned into each muscle
group's activation, and the popping arm's bulge following those beats in the written USD."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from oracles import prim
from warpskin.cli import main
from warpskin.errors import SceneError
from warpskin.popping import Beat, BeatSpec, beat_times, read_beats


def test_beat_times_are_the_tempo_grid_within_the_range():
    # 100 bpm, every other beat from 0.31 s: 0.31 + 1.2 k (closed form), inside [0.2, 4.0]
    got = beat_times(100.0, start=0.2, end=4.0, offset=0.31, every=2)
    np.testing.assert_allclose(got, [0.31, 1.51, 2.71, 3.91], rtol=0, atol=1e-12)
    # a grid that starts before the range: only the beats inside it
    np.testing.assert_allclose(beat_times(120.0, start=1.13, end=2.4, offset=0.07), [1.57, 2.07], rtol=0, atol=1e-12)
    # the range's ends are kept within a tolerance band (a beat on the last frame pops)
    assert beat_times(60.0, start=0.0, end=2.0 - 1e-12, offset=0.0).tolist()[-1] == pytest.approx(2.0)
    assert beat_times(60.0, start=0.0, end=1.9, offset=0.0).size == 2
    for bad in (dict(bpm=0.0), dict(bpm=float("nan")), dict(bpm=120.0, every=0), dict(bpm=120.0, offset=float("inf"))):
        kw = {"start": 0.0, "end": 1.0, **bad}
        with pytest.raises(SceneError):
            beat_times(kw.pop("bpm"), **kw)


def test_groups_pop_together_or_in_turn():
    names = ["biceps", "triceps", "deltoid"]
    together = BeatSpec(bpm=60.0, offset=0.5, hold=0.3, groups=["triceps", "biceps"]).timeline(names, 0.0, 3.0)
    assert sorted(together.groups) == ["biceps", "triceps"]  # deltoid not asked for
    for g in ("biceps", "triceps"):
        for beat in (0.5, 1.5, 2.5):
            assert together.value(g, beat + 0.01) == 1.0 and together.value(g, beat + 0.31) == 0.0
            assert together.value(g, beat - 0.01) == 0.0
    turn = BeatSpec(bpm=60.0, offset=0.5, hold=0.3, groups=["triceps", "biceps"], in_turn=True).timeline(names, 0.0, 3.0)
    owner = {0.5: "triceps", 1.5: "biceps", 2.5: "triceps"}  # the --groups order
    for beat, g in owner.items():
        other = "biceps" if g == "triceps" else "triceps"
        assert turn.value(g, beat + 0.1) == 1.0 and turn.value(other, beat + 0.1) == 0.0


def test_default_hold_is_half_the_gap_at_most_a_quarter_second():
    tl = BeatSpec(bpm=240.0).timeline(["biceps"], 0.0, 1.0)  # beats 0.25 s apart: hold 0.125 s
    assert tl.value("biceps", 0.1) == 1.0 and tl.value("biceps", 0.2) == 0.0
    tl = BeatSpec(bpm=30.0).timeline(["biceps"], 0.0, 4.0)  # 2 s apart: hold 0.25 s
    assert tl.value("biceps", 0.24) == 1.0 and tl.value("biceps", 0.26) == 0.0


def test_beats_from_a_file(tmp_path):
    path = tmp_path / "song.csv"
    path.write_text("time,group,activation\n# the chorus\n0.5\n1.25, biceps, 0.5\n\n2.0,triceps # a comment\n")
    beats = read_beats(path)
    assert beats == [Beat(0.5), Beat(1.25, "biceps", 0.5), Beat(2.0, "triceps")]
    tl = BeatSpec(beats=beats, hold=0.2).timeline(["biceps", "triceps"], 0.0, 3.0)
    assert tl.value("biceps", 0.6) == 1.0 and tl.value("triceps", 0.6) == 1.0  # a plain time: every group
    assert tl.value("biceps", 1.3) == 0.5 and tl.value("triceps", 1.3) == 0.0
    assert tl.value("triceps", 2.1) == 1.0 and tl.value("biceps", 2.1) == 0.0


@pytest.mark.parametrize("text, message", [
    ("0.5\nsoon\n", r"line 2: the first column must be a time in seconds, got 'soon'"),
    ("0.5,biceps,2\n", r"line 1: the activation must be in \[0, 1\], got '2'"),
    ("0.5,biceps,1,x\n", r"line 1: expected time\[,group\[,activation\]\], got 4 columns"),
    ("# nothing\n\n", r"no beats"),
])
def test_bad_beat_files_name_the_line(tmp_path, text, message):
    path = tmp_path / "beats.txt"
    path.write_text(text)
    with pytest.raises(SceneError, match=message):
        read_beats(path)


def test_bad_beats_for_the_groups_are_clear():
    with pytest.raises(SceneError, match=r"unknown muscle group\(s\) \['quads'\]; groups are \['biceps'\]"):
        BeatSpec(bpm=60.0, groups=["quads"]).timeline(["biceps"], 0.0, 2.0)
    with pytest.raises(SceneError, match=r"unknown muscle group\(s\) \['quads'\]"):
        BeatSpec(beats=[Beat(0.5, "quads")]).timeline(["biceps"], 0.0, 2.0)
    with pytest.raises(SceneError, match="no beat between 0.5 s and 0.9 s"):
        BeatSpec(bpm=60.0, offset=1.0).timeline(["biceps"], 0.5, 0.9)
    with pytest.raises(SceneError, match=r"the pop on the beat at 0.5 s \(hold 0.6 s \+ release 0.0 s\) overlaps the beat at 1.0 s"):
        BeatSpec(bpm=120.0, offset=0.5, hold=0.6).timeline(["biceps"], 0.0, 2.0)
    with pytest.raises(SceneError, match="exactly one of --bpm or --beats"):
        BeatSpec()


def _bulge(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip times [s] of the frames, how far the dynamic skin lies from the normal-only skin at
    most in each [m], and the per-vertex distances ``[F, V]``, read from the written USD."""
    stage = Usd.Stage.Open(str(path))
    fps = stage.GetTimeCodesPerSecond()
    popping, normal = (UsdGeom.Mesh(prim(stage, n)).GetPointsAttr() for n in ("popping", "normal"))
    codes = popping.GetTimeSamples()
    d = np.array([np.linalg.norm(np.asarray(popping.Get(tc)) - np.asarray(normal.Get(tc)), axis=1) for tc in codes])
    return np.array(codes) / fps, d.max(axis=1), d


def test_cli_bpm_pops_land_on_the_beat(tmp_path, capsys, device):
    # 100 bpm, every other beat from 0.31 s (generic times, off the 60 fps frames), the biceps
    # and the triceps in turn: each pop starts at its beat and peaks within one 24 fps frame of it
    out = tmp_path / "beat.usdc"
    assert main(["pop", "popping_arm", "-o", str(out), "--frames", "0:180", "--quiet", "--device", device,
                 "--bpm", "100", "--offset", "0.31", "--every", "2", "--groups", "biceps,triceps", "--in-turn"]) == 0
    capsys.readouterr()
    times, bulge, per_vertex = _bulge(out)
    beats = [0.31, 1.51, 2.71]
    assert bulge[times < beats[0]].max() < 1e-6  # nothing before the first beat
    where = []
    for k, beat in enumerate(beats):
        end = beats[k + 1] if k + 1 < len(beats) else times[-1] + 1.0
        window = (times >= beat - 1e-9) & (times < end)
        first = np.nonzero(window)[0][0]
        assert bulge[first - 1] < 0.1 * bulge[window].max()  # still at rest in the frame before the beat
        rise = bulge[window]
        peak = int(np.nonzero((rise[1:-1] >= rise[:-2]) & (rise[1:-1] > rise[2:]))[0][0]) + 1  # the first local peak
        assert times[first + peak] - beat <= 1.0 / 24.0 + 1e-9
        assert rise[peak] > 2e-3  # a visible pop
        where.append(int(per_vertex[first + peak].argmax()))
    # in turn: the first and third pops are the biceps', the second the triceps' (elsewhere on the arm)
    stage = Usd.Stage.Open(str(out))
    rest = np.asarray(UsdGeom.Mesh(prim(stage, "normal")).GetPointsAttr().Get(0.0))
    assert np.linalg.norm(rest[where[0]] - rest[where[2]]) < np.linalg.norm(rest[where[0]] - rest[where[1]])


def test_cli_beat_flags_are_checked(tmp_path, capsys):
    out = tmp_path / "x.usdc"
    for argv, message in [
        (["--offset", "0.5"], "--offset need --bpm or --beats"),
        (["--bpm", "120", "--beats", str(tmp_path / "b.txt")], "give one of --bpm or --beats, not both"),
        (["--bpm", "120", "--groups", "biceps,quads"], "unknown muscle group(s) ['quads']"),
        (["--bpm", "120", "--groups", "biceps,,triceps"], "--groups must name distinct muscle groups"),
        (["--beats", str(tmp_path / "missing.txt")], "cannot read the beats"),
    ]:
        assert main(["pop", "popping_arm", "-o", str(out), "--quiet", "--frames", "0:10", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
        assert not out.exists()


@pytest.mark.parametrize("alpha", [0.1, 0.4, 1.0])
def test_the_layered_drive_rings_while_clenched_and_relaxes_monotonely(alpha):
    # warpskin.popping.activation.vibrating: from rest a step to 1 at t = 0.0123 s, released at
    # 0.3123 s; the response's error e = a - 1 while clenched follows the paper's linear map
    # [e, h u]' = [[1-a, 1-a], [-a, 1-a]] [e, h u] (eqs. 1-2), then falls by (1 - beta h) a step
    from warpskin.popping.activation import vibrating

    h, beta = 0.005, 30.0
    on, off = 0.0123, 0.3123

    def goal(t):
        return np.array([1.0 if on <= t < off else 0.0])

    f = vibrating(goal, 0.0, 0.6, h=h, alpha=alpha, beta=beta)
    times = h * np.arange(121)
    got = np.array([f(t)[0] for t in times])
    first = int(np.ceil(on / h))  # the first step that sees the clench (on is off the grid)
    assert np.all(got[:first] == 0.0)
    mat = np.array([[1 - alpha, 1 - alpha], [-alpha, 1 - alpha]])
    z = np.array([-1.0, 0.0])  # e = a - 1 from rest, h u = 0
    last = int(np.floor(off / h))
    for k in range(first, last + 1):
        z = mat @ z
        assert got[k] - 1.0 == pytest.approx(z[0], abs=1e-12), k
    if alpha < 1.0:
        assert got[first:last + 1].max() > 1.0 + 0.1 * (1 - alpha)  # overshoot: it rings
    relax = got[last + 1:]
    assert np.all(np.diff(relax) <= 0.0) and np.all(relax >= 0.0)  # monotone, never below the goal
    a = got[last]
    for k, value in enumerate(relax[:20], start=1):
        a = a + beta * h * (0.0 - a)
        assert value == pytest.approx(a, abs=1e-12) or value == 0.0
    with pytest.raises(SceneError, match="beta"):
        vibrating(goal, 0.0, 1.0, h=0.1, alpha=0.1, beta=30.0)


def test_onsets_are_where_each_pop_leaves_zero():
    from warpskin.popping import ActivationTimeline

    tl = ActivationTimeline({
        "biceps": ActivationTimeline.beats([1.37, 0.41, 2.9], hold=0.3, attack=0.05, release=0.1),
        "triceps": [(0.0, 0.0), (0.2, 1.0), (0.5, 1.0), (0.6, 0.0), (1.0, 0.0), (1.1, 0.5), (1.3, 0.2), (1.4, 0.0)],
        "calf": [(0.0, 0.7), (0.4, 0.7), (0.5, 0.0)],  # clenched from its first key
    })
    assert tl.onsets("biceps").tolist() == pytest.approx([0.41, 1.37, 2.9], abs=1e-15)
    assert tl.onsets("triceps").tolist() == pytest.approx([0.0, 1.0], abs=1e-15)
    assert tl.onsets("calf").tolist() == [0.0]
    assert tl.onsets("deltoid").size == 0


def test_beat_summary_reads_each_pop_from_its_bulge():
    from warpskin.popping.report import beat_summary

    fps = 24.0
    codes = np.arange(0.0, 60.0)
    bulge = np.zeros(codes.size)
    # beat 1 at 0.31 s (frame 7.44): rises over frames 8-10, rings, its largest at frame 13
    bulge[8:20] = [3.0, 8.6, 9.2, 8.8, 9.1, 9.7, 9.4, 6.0, 3.0, 1.0, 0.4, 0.2]
    # beat 2 at 1.2 s (frame 28.8): a plateau cut flat at 5.0 from frame 30, its first frame the peak
    bulge[29:40] = [4.4, 5.0, 5.0, 5.0, 5.0, 5.0, 2.0, 0.8, 0.3, 0.1, 0.05]
    rows = beat_summary(codes, bulge, np.array([1.2, 0.31]), fps, depth_mm=25.0)
    assert len(rows) == 2
    a, b = rows
    assert a["beat_frame"] == pytest.approx(7.44) and b["beat_frame"] == pytest.approx(28.8)
    assert (a["peak_mm"], a["peak_frame"], a["rise_frame"]) == (9.7, 13.0, 10.0)  # frame 9: 8.6 < 0.9 * 9.7 <= 9.2
    assert a["peak_lag_frames"] == pytest.approx(13.0 - 7.44) and a["rise_lag_frames"] == pytest.approx(10.0 - 7.44)
    assert a["end_mm"] == 0.0 and a["share_of_depth"] == pytest.approx(9.7 / 25.0)
    assert (b["peak_mm"], b["peak_frame"], b["rise_frame"]) == (5.0, 30.0, 30.0)  # 4.4 < 4.5
    assert b["end_mm"] == 0.0
    # a pop with under two written frames after it is left out; no depth, no share
    rows = beat_summary(codes, bulge, np.array([0.31, 59.5 / fps]), fps)
    assert len(rows) == 1 and "share_of_depth" not in rows[0]

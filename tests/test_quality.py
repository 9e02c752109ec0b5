"""What is written is measured: strained edges, flipped triangles and intersecting pairs of every
written mesh against its LBS (warpskin.quality), checked against references written separately
(a separating-axis triangle test over every pair, plain loops over edges and faces), on
meshes and on the USD a run writes; and the range checks stop runs whose written meshes or
tether cap show an explosion."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from oracles import intersecting_pairs_brute_force, prim, strain_and_flips
from warpskin.metrics import self_intersections
from warpskin.quality import QualityLimits, WrittenMesh, mesh_measures


def _crumpled_sheet(seed: int, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """A grid sheet folded with random bumps large enough to pass through itself (generic
    positions: no vertex on another's face)."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    z = 0.6 * np.sin(3.1 * u + rng.uniform(0, 6)) * np.cos(2.7 * v + rng.uniform(0, 6))
    p = np.stack([u + 0.35 * np.sin(5 * v + rng.uniform(0, 6)), v, z], axis=-1).reshape(-1, 3)
    p += rng.normal(scale=1e-3, size=p.shape)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return p, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_pair_count_matches_a_separating_axis_test_over_every_pair(seed):
    p, t = _crumpled_sheet(seed)
    # two copies, one shifted through the other: many crossings between the two sheets
    q = p + np.array([0.05, 0.03, 0.02]) + np.random.default_rng(seed + 10).normal(scale=1e-3, size=p.shape)
    pts = np.concatenate([p, q])
    tris = np.concatenate([t, t + len(p)])
    want = intersecting_pairs_brute_force(pts, tris)
    assert want > 20  # the test meets real intersections
    assert len(self_intersections(pts, tris)) == want


def test_written_mesh_welds_seams_and_counts_like_the_welded_mesh():
    # the same crossing sheets with every triangle's corners split (a file's UV seams):
    # measured on the written (split) mesh, the count is the welded mesh's
    p, t = _crumpled_sheet(4)
    q = p + np.array([0.04, -0.02, 0.03])
    pts = np.concatenate([p, q])
    tris = np.concatenate([t, t + len(p)])
    split = pts[tris.ravel()]
    split_tris = np.arange(len(split)).reshape(-1, 3)
    mesh = WrittenMesh("sheet", split_tris, split)
    assert mesh.pairs(split) == intersecting_pairs_brute_force(pts, tris)
    # split, the brute force sees neighbours as strangers: the weld is what makes them neighbours
    assert intersecting_pairs_brute_force(split, split_tris) > mesh.pairs(split)


def test_strain_and_flips_against_plain_loops():
    rng = np.random.default_rng(7)
    rest, tris = _crumpled_sheet(5, n=12)
    lbs = rest + rng.normal(scale=0.01, size=rest.shape)
    points = lbs.copy()
    # crumple a patch: stretch some edges past 1.5x, squash others, fold a few triangles over
    patch = np.linalg.norm(rest[:, :2] - [0.5, 0.5], axis=1) < 0.2
    points[patch] += rng.normal(scale=0.08, size=(int(patch.sum()), 3))
    split = tris.ravel()
    mesh = WrittenMesh("sheet", np.arange(split.size).reshape(-1, 3), rest[split])
    m = mesh_measures(mesh, points[split], lbs[split], pairs=False)
    s, s_lbs, f = strain_and_flips(rest[split], points[split], lbs[split], np.arange(split.size).reshape(-1, 3))
    assert s > 0.02 and f > 0.005  # the measures see the crumpling
    assert m["strained"] == pytest.approx(s, abs=1e-12)
    assert m["strained_lbs"] == pytest.approx(s_lbs, abs=1e-12)
    assert m["flipped"] == pytest.approx(f, abs=1e-12)


def test_limits_name_the_mesh_and_the_files_vertex():
    rest, tris = _crumpled_sheet(6)
    mesh = WrittenMesh("shoe_l", tris, rest, file_ids=np.arange(len(rest)) + 100)
    bad = rest.copy()
    bad[40] += [0.0, 0.0, 2.0]  # one spike: its edges strained far past 1.5x
    m = mesh_measures(mesh, bad, rest)
    limits = QualityLimits(strained=0.01, flipped=0.5)
    line = limits.problem(mesh, m)
    assert line is not None and "mesh 'shoe_l'" in line and "file vertex 1" in line
    assert m["worst_strain_vertex"] in {140} | {100 + int(j) for j in tris[(tris == 40).any(1)].ravel()}
    assert limits.problem(mesh, mesh_measures(mesh, rest, rest)) is None


def _widest_split_by_loops(rest: np.ndarray, points: np.ndarray) -> float:
    """The farthest two written vertices with one rest position lie apart: every pair of copies
    of each rest position (grouped by exact equality, -0.0 as 0.0), by scipy's pdist."""
    from scipy.spatial.distance import pdist

    _, group = np.unique(np.asarray(rest, dtype=np.float64) + 0.0, axis=0, return_inverse=True)
    group = group.reshape(-1)
    worst = 0.0
    for g in np.nonzero(np.bincount(group) > 1)[0]:
        worst = max(worst, float(pdist(np.asarray(points, dtype=np.float64)[group == g]).max()))
    return worst


def test_copies_written_apart_are_a_crack_the_limits_name():
    # a sheet with every triangle's corners split (flat shading): LBS moves the copies as one;
    # the written mesh moves some corners of one rest point apart by a small, uneven amount
    rng = np.random.default_rng(11)
    rest, tris = _crumpled_sheet(8)
    split_ids = tris.ravel()
    flat = rest[split_ids]
    lbs = flat + rng.normal(scale=0.01, size=(1, 3))
    points = lbs.copy()
    points[::7] += rng.normal(scale=2e-3, size=points[::7].shape)
    mesh = WrittenMesh("fist_r", np.arange(split_ids.size).reshape(-1, 3), flat, file_ids=np.arange(split_ids.size) + 500)
    m = mesh_measures(mesh, points, lbs, pairs=False)
    want = _widest_split_by_loops(flat, points)
    assert want > 1e-3
    assert m["split"] == pytest.approx(want, rel=1e-12)
    assert m["split_lbs"] == pytest.approx(_widest_split_by_loops(flat, lbs), abs=1e-12)
    a, b = m["split_vertices"]
    assert flat[a - 500].tolist() == flat[b - 500].tolist() and a != b
    assert np.linalg.norm(points[a - 500] - points[b - 500]) == pytest.approx(want, rel=1e-12)
    # the welded measures do not see it (one edge per welded pair, strained by a hair at most)
    assert m["strained"] == 0.0 and m["flipped"] == 0.0
    line = QualityLimits().problem(mesh, m)
    assert line is not None and "mesh 'fist_r'" in line and f"file vertices {a} and {b}" in line and "crack" in line
    # a split within the band (a tenth of the limit, 1e-4 of the mesh's size) passes
    tiny = lbs.copy()
    tiny[::7] += 1e-6 * mesh.size * rng.normal(size=tiny[::7].shape) / np.sqrt(3)
    assert 0.0 < mesh_measures(mesh, tiny, lbs, pairs=False)["split"] < 1e-5 * mesh.size
    assert QualityLimits().problem(mesh, mesh_measures(mesh, tiny, lbs, pairs=False)) is None


@pytest.mark.slow
def test_a_run_reports_what_it_wrote_and_the_usd_agrees(tmp_path):
    # the coarse arm: the summary's per-mesh figures are the worst over the frames of the
    # written USD, measured there with the plain-loop reference and the brute-force pair count
    from warpskin.cli import main

    scene = tmp_path / "arm.toml"
    scene.write_text("[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 30\nsegments = 20\n"
                     "[animation]\nclip = 'flex'\nfps = 30\nframes = [30, 40]\n[solver]\niterations = 8\ntether_max = 0.08\n")
    out = tmp_path / "arm.usdc"
    report = tmp_path / "report"
    assert main(["simulate", str(scene), "-o", str(out), "--lbs", "--quiet", "--report", str(report)]) == 0
    data = json.loads((report / "report.json").read_text())
    stage = Usd.Stage.Open(str(out))
    skin, ref = UsdGeom.Mesh(prim(stage, "skin")), UsdGeom.Mesh(prim(stage, "lbs"))
    name = skin.GetPrim().GetName()  # the arm's mesh name: what the summary calls it
    assert name == "arm" and ref.GetPrim().GetName() == "arm_lbs"
    row = data["summary"]["written"][name]
    tris = np.asarray(skin.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    rest = np.asarray(skin.GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64)
    worst = [0.0, 0.0, 0.0]
    pairs = []
    for tc in skin.GetPointsAttr().GetTimeSamples():
        x = np.asarray(skin.GetPointsAttr().Get(tc), dtype=np.float64)
        lb = np.asarray(ref.GetPointsAttr().Get(tc), dtype=np.float64)
        worst = [max(a, b) for a, b in zip(worst, strain_and_flips(rest, x, lb, tris))]
        pairs.append((intersecting_pairs_brute_force(x, _welded(rest, tris)), intersecting_pairs_brute_force(lb, _welded(rest, tris))))
    # the file holds float32 points: the shares agree to a band of one edge
    assert row["max_strained"] == pytest.approx(worst[0], abs=1.5 / row["edges"])
    assert row["max_strained_lbs"] == pytest.approx(worst[1], abs=1.5 / row["edges"])
    assert row["max_flipped"] == pytest.approx(worst[2], abs=1.5 / row["triangles"])
    # the skin's written points are the simulated float32 ones exactly; the LBS guide is float64
    # rounded to float32 in the file, so its count may differ where two triangles graze
    assert row["max_pairs"] == max(p for p, _ in pairs)
    assert abs(row["max_pairs_lbs"] - max(q for _, q in pairs)) <= 1 + 0.01 * row["max_pairs_lbs"]
    assert len(data["written"][name]["strained"]) == 11
    splits = [_widest_split_by_loops(rest, np.asarray(skin.GetPointsAttr().Get(tc), dtype=np.float64))
              for tc in skin.GetPointsAttr().GetTimeSamples()]
    assert row["max_split"] == pytest.approx(max(splits), abs=1e-7)
    assert len(data["metrics"]["tether_clamped"]) == 11 and "max_capped_share" in data["summary"]
    assert len(data["metrics"]["capped_share"]) == 11 and max(data["metrics"]["capped_share"]) == pytest.approx(
        data["summary"]["max_capped_share"])
    # every per-frame metric is named in the docs' description of report.json
    from pathlib import Path

    described = (Path(__file__).resolve().parent.parent / "docs" / "model.md").read_text()
    for key in data["metrics"]:
        assert f"`{key}`" in described, key


def _welded(rest: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Triangles re-indexed onto the first vertex of each rest position (the brute force's own
    weld, for pairs across seams)."""
    key: dict = {}
    first = np.array([key.setdefault(tuple(x), i) for i, x in enumerate(rest.tolist())])
    return first[tris]

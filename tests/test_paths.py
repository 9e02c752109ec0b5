"""Fast-summation path layout (Deul & Bender 2013, section 4.3; Diziol, Bender & Bayer 2011).

The omega-rings are built here with a plain breadth-first search over the triangle edges,
independently of :mod:`warpskin.preprocess.fast_summation`, and every fast region sum is compared with the
direct sum. Float32 bounds (errors relative to ``sum |v|`` over the region, values in [0, 1)):
``kahan`` (the float32 default) within ``8 eps``; ``plain`` and ``relative`` within ``1e-3``
(measured up to 1.4e-4 on the arm's single 2918-vertex path). Float64: ``1e-12`` relative.
"""

from __future__ import annotations


import numpy as np
import pytest
from scipy.spatial import Delaunay

from oracles import neighbour_sets, omega_rings
from warpskin.preprocess.fast_summation import (
    ACCUMULATE,
    HEURISTICS,
    PathLayout,
    RegionRuns,
    build_path_layout,
    compensated_prefix_sums,
    path_references,
    prefix_sums,
    region_runs,
    run_region_sums,
    vertex_adjacency,
)
from warpskin.rig import RigError
from warpskin.scenes.arm import make_arm

EPS32 = float(np.finfo(np.float32).eps)
KAHAN_BOUND = 8 * EPS32  # x sum|v| per region
PLAIN_BOUND = 1e-3  # x sum|v| per region, values in [0, 1)


# --------------------------------------------------------------------------------------------
# Independent helpers: edges and omega-rings straight from the triangles
# --------------------------------------------------------------------------------------------


def direct_sums(offsets: np.ndarray, members: np.ndarray, values: np.ndarray, dtype=np.float64) -> np.ndarray:
    reg = np.repeat(np.arange(offsets.size - 1), np.diff(offsets))
    out = np.zeros((offsets.size - 1,) + values.shape[1:], dtype=dtype)
    np.add.at(out, reg, values[members].astype(dtype))
    return out


def check_layout(layout: PathLayout, triangles: np.ndarray, vertex_count: int) -> None:
    order = layout.order
    assert order.dtype == np.int64 and order.shape == (vertex_count,)
    assert np.array_equal(np.sort(order), np.arange(vertex_count))  # each vertex exactly once
    assert np.array_equal(order[layout.position_of], np.arange(vertex_count))
    assert np.array_equal(layout.position_of[order], np.arange(vertex_count))
    o = layout.path_offsets
    assert o[0] == 0 and o[-1] == vertex_count and (np.diff(o) >= 1).all()
    assert layout.path_count == o.size - 1
    for p in range(layout.path_count):
        assert (layout.path_of[order[o[p] : o[p + 1]]] == p).all()
    nb = neighbour_sets(triangles, vertex_count)
    edges = {(min(u, v), max(u, v)) for u, nbs in enumerate(nb) for v in nbs}
    for p in range(layout.path_count):
        path = order[o[p] : o[p + 1]].tolist()
        for u, v in zip(path[:-1], path[1:]):
            assert (min(u, v), max(u, v)) in edges, f"path {p}: {u} -> {v} is not a mesh edge"
    assert layout.mean_path_length == pytest.approx(vertex_count / layout.path_count)


def check_runs(layout: PathLayout, runs: RegionRuns, offsets: np.ndarray, members: np.ndarray) -> None:
    assert runs.run_offsets.shape == offsets.shape and runs.run_offsets[0] == 0
    assert runs.run_offsets[-1] == runs.run_count
    start, end = runs.run_start, runs.run_end
    assert (end >= start).all()
    # each run within one path
    assert np.array_equal(layout.path_of[layout.order[start]], layout.path_of[layout.order[end]])
    # every member covered by exactly one run of its region
    lengths = end - start + 1
    within = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    covered_pos = np.repeat(start, lengths) + within
    covered_reg = np.repeat(runs.run_region, lengths)
    got = np.lexsort((layout.order[covered_pos], covered_reg))
    reg = np.repeat(np.arange(offsets.size - 1), np.diff(offsets))
    want = np.lexsort((members, reg))
    assert np.array_equal(covered_reg[got], reg[want])
    assert np.array_equal(layout.order[covered_pos][got], members[want])
    # maximal: consecutive runs of a region are neither touching nor overlapping on one path
    same = runs.run_region[1:] == runs.run_region[:-1]
    nxt, prev_end = start[1:][same], end[:-1][same]
    assert (nxt > prev_end).all()  # sorted, disjoint
    touching = (nxt == prev_end + 1) & ~layout.is_path_start[nxt]
    assert not touching.any()


# --------------------------------------------------------------------------------------------
# Fixtures
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def arm_rings(arm):
    """The arm and its omega-rings (BFS reference) for omega 1 and 2."""
    nb = neighbour_sets(arm.triangles, arm.vertex_count)
    return arm, {w: omega_rings(nb, w) for w in (1, 2)}


_CESIUM: dict = {}


@pytest.fixture
def cesium(assets):
    """CesiumMan (welded UsdSkel import) and its omega-rings, loaded once per module."""
    if "rig" not in _CESIUM:
        from warpskin.io import load_rig

        rig = load_rig(assets / "usd/CesiumMan/CesiumMan.usdz")
        nb = neighbour_sets(rig.triangles, rig.vertex_count)
        _CESIUM["rig"] = rig, {w: omega_rings(nb, w) for w in (1, 2)}
    return _CESIUM["rig"]


def delaunay_mesh(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = rng.random((n, 2))
    return np.c_[p, 0.1 * np.sin(6 * p[:, 0])], Delaunay(p).simplices.astype(np.int64)


def soup_mesh(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random triangles over random vertices: non-manifold, several components, isolated
    vertices and a degenerate triangle."""
    rng = np.random.default_rng(seed)
    tris = rng.integers(0, n - 5, size=(n, 3))
    tris[0] = (1, 1, 2)
    return rng.random((n, 3)), tris


# --------------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("heuristic", HEURISTICS)
def test_arm_layout_is_valid(arm_rings, heuristic):
    rig, _ = arm_rings
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices, heuristic=heuristic)
    check_layout(layout, rig.triangles, rig.vertex_count)


@pytest.mark.parametrize("mesh", ["delaunay", "soup"])
@pytest.mark.parametrize("heuristic", HEURISTICS + ("warnsdorff-no-positions",))
@pytest.mark.parametrize("seed", [0, 1])
def test_random_mesh_layout_is_valid(mesh, heuristic, seed):
    x, tris = (delaunay_mesh if mesh == "delaunay" else soup_mesh)(400, seed)
    if heuristic == "warnsdorff-no-positions":
        layout = build_path_layout(tris, len(x))
    else:
        layout = build_path_layout(tris, len(x), vertices=x, heuristic=heuristic)
    check_layout(layout, tris, len(x))
    split = build_path_layout(tris, len(x), vertices=x, max_path_length=7)
    check_layout(split, tris, len(x))
    assert split.path_lengths.max() <= 7


def test_layout_check_detects_broken_layouts(arm_rings):
    rig, _ = arm_rings
    adj = vertex_adjacency(rig.triangles, rig.vertex_count)
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices)
    layout.check(adj)
    order = layout.order.copy()
    order[[5, 900]] = order[[900, 5]]  # a jump across the arm: not a mesh edge
    broken = PathLayout.from_paths([order], rig.vertex_count)
    broken.check()  # still a permutation
    with pytest.raises(RigError, match="share no mesh edge"):
        broken.check(adj)
    bad = PathLayout(layout.order, layout.path_offsets, layout.path_of, np.roll(layout.position_of, 1))
    with pytest.raises(RigError, match="inverse"):
        bad.check()


def test_layout_edge_cases():
    empty = build_path_layout(np.zeros((0, 3), dtype=np.int64), 3)
    check_layout(empty, np.zeros((0, 3), dtype=np.int64), 3)
    assert empty.path_count == 3  # isolated vertices: one path each
    none = build_path_layout(np.zeros((0, 3), dtype=np.int64), 0)
    assert none.path_count == 0 and none.mean_path_length == 0.0
    tri = build_path_layout([[0, 1, 2]], 3)
    assert tri.path_count == 1


def test_large_mesh_layout_is_valid():
    # build speed is recorded by `warpskin bench --build`, never asserted in a test
    rig = make_arm(rings=190, segments=190)  # 36k vertices
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices)
    check_layout(layout, rig.triangles, rig.vertex_count)


# --------------------------------------------------------------------------------------------
# Runs and sums
# --------------------------------------------------------------------------------------------


def _check_sums(rig, rings, layout, seed):
    rng = np.random.default_rng(seed)
    v = rig.vertex_count
    for omega, (o, m) in rings.items():
        runs = region_runs(layout, o, m)
        check_runs(layout, runs, o, m)
        values = rng.random((v, 3))
        exact = direct_sums(o, m, values)
        scale = direct_sums(o, m, np.abs(values))
        fast = run_region_sums(layout, runs, values)
        assert fast.dtype == np.float64 and fast.shape == exact.shape
        np.testing.assert_allclose(fast, exact, rtol=1e-12, atol=0)
        v32 = values.astype(np.float32)
        exact32 = direct_sums(o, m, v32)
        errors = {}
        for acc in ACCUMULATE:
            f = run_region_sums(layout, runs, v32, np.float32, accumulate=acc)
            assert f.dtype == np.float32
            errors[acc] = float(np.max(np.abs(f - exact32) / scale))
        default = run_region_sums(layout, runs, v32, np.float32)
        assert np.array_equal(default, run_region_sums(layout, runs, v32, np.float32, accumulate="kahan"))
        report = ", ".join(f"{k} {e:.1e}" for k, e in errors.items())
        print(f"\nomega={omega}: float32 error / sum|v|: {report}")
        assert errors["kahan"] <= KAHAN_BOUND
        assert errors["plain"] <= PLAIN_BOUND and errors["relative"] <= PLAIN_BOUND
        # matrices (the moment sums x x^T) keep their shape
        mat = rng.standard_normal((v, 3, 3))
        np.testing.assert_allclose(
            run_region_sums(layout, runs, mat), direct_sums(o, m, mat), rtol=1e-12, atol=1e-12 * m.size
        )


def test_arm_region_sums_match_direct(arm_rings):
    rig, rings = arm_rings
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices)
    _check_sums(rig, rings, layout, 0)
    split = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices, max_path_length=64)
    _check_sums(rig, rings, split, 1)


def test_cesium_man_region_sums_match_direct(cesium):
    rig, rings = cesium
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices)
    check_layout(layout, rig.triangles, rig.vertex_count)
    _check_sums(rig, rings, layout, 2)


def test_random_mesh_region_sums_match_direct():
    x, tris = soup_mesh(300, 3)
    nb = neighbour_sets(tris, len(x))
    layout = build_path_layout(tris, len(x), vertices=x)
    rng = np.random.default_rng(4)
    for omega in (1, 2):
        o, m = omega_rings(nb, omega)
        # shuffle the members of every region: any order is accepted
        m = np.concatenate([rng.permutation(m[o[r] : o[r + 1]]) for r in range(o.size - 1)])
        runs = region_runs(layout, o, m)
        check_runs(layout, runs, o, m)
        vals = rng.random(len(x))
        np.testing.assert_allclose(run_region_sums(layout, runs, vals), direct_sums(o, m, vals), rtol=1e-12)


def test_empty_regions_and_single_vertex_regions(arm_rings):
    rig, _ = arm_rings
    layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices)
    o = np.array([0, 0, 1, 1, 3])
    m = np.array([5, layout.order[10], layout.order[11]])
    runs = region_runs(layout, o, m)
    assert runs.run_offsets.tolist() == [0, 0, 1, 1, 2]
    vals = np.arange(rig.vertex_count, dtype=np.float64)
    s = run_region_sums(layout, runs, vals)
    assert s.tolist() == [0.0, 5.0, 0.0, float(layout.order[10] + layout.order[11])]


def test_prefix_sums_restart_at_every_path():
    x, tris = delaunay_mesh(300, 5)
    layout = build_path_layout(tris, len(x), vertices=x, max_path_length=20)
    rng = np.random.default_rng(6)
    vals = rng.random((len(x), 2))
    p = prefix_sums(layout, vals)
    assert p.shape == vals.shape
    for q, path in enumerate(layout.paths()):
        s, e = layout.path_offsets[q], layout.path_offsets[q + 1]
        np.testing.assert_allclose(p[s:e], np.cumsum(vals[path], axis=0), rtol=1e-14)
    # float32: sequential accumulation along each path, as the scan kernel does
    p32 = prefix_sums(layout, vals, np.float32)
    for q, path in enumerate(layout.paths()):
        s, e = layout.path_offsets[q], layout.path_offsets[q + 1]
        assert np.array_equal(p32[s:e], np.cumsum(vals[path].astype(np.float32), axis=0, dtype=np.float32))
    # relative: prefix sums of value - value at the path origin
    ref = path_references(layout, vals, np.float64)
    assert np.array_equal(ref, vals[layout.order[layout.path_offsets[:-1]]])
    pr = prefix_sums(layout, vals, reference=ref)
    k = np.arange(len(x)) - np.repeat(layout.path_offsets[:-1], layout.path_lengths) + 1
    np.testing.assert_allclose(pr + k[:, None] * np.repeat(ref, layout.path_lengths, axis=0), p, atol=1e-12)
    # compensated: s - c is the prefix to about float32 precision of the prefix itself
    s32, c32 = compensated_prefix_sums(layout, vals, np.float32)
    exact = prefix_sums(layout, vals.astype(np.float32).astype(np.float64))
    assert np.max(np.abs((s32.astype(np.float64) - c32) - exact) / exact) < 2 * EPS32


# --------------------------------------------------------------------------------------------
# Quality: runs per region, heuristics compared
# --------------------------------------------------------------------------------------------


def _report(name, rig, rings):
    means = {}
    for h in HEURISTICS:
        layout = build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices, heuristic=h)
        for omega, (o, m) in rings.items():
            runs = region_runs(layout, o, m)
            means[h, omega] = runs.mean_runs_per_region
            print(
                f"\n{name} {h:10s} omega={omega}: {layout.path_count} paths (mean length "
                f"{layout.mean_path_length:.0f}), mean runs per region {runs.mean_runs_per_region:.3f}, "
                f"mean region size {np.diff(o).mean():.2f}"
            )
    return means


def test_arm_runs_per_region(arm_rings):
    rig, rings = arm_rings
    means = _report("arm", rig, rings)
    size1 = np.diff(rings[1][0]).mean()
    size2 = np.diff(rings[2][0]).mean()
    # the arm is a regular grid: parallel paths cut a 7-vertex 1-ring into 3 runs, a 2-ring into 5
    assert means["warnsdorff", 1] < size1 / 2
    assert means["warnsdorff", 2] < size2 / 3
    assert means["warnsdorff", 1] < 3.1 and means["warnsdorff", 2] < 5.3
    # the default heuristic is the better one on the arm
    assert means["warnsdorff", 2] <= means["straight", 2]


def test_cesium_man_runs_per_region(cesium):
    rig, rings = cesium
    means = _report("CesiumMan", rig, rings)
    assert means["warnsdorff", 1] < np.diff(rings[1][0]).mean() / 2
    assert means["warnsdorff", 2] < np.diff(rings[2][0]).mean() / 3


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


def test_bad_input_raises_rig_error():
    x, tris = delaunay_mesh(50, 7)
    with pytest.raises(RigError, match="outside"):
        build_path_layout(np.array([[0, 1, 60]]), 50)
    with pytest.raises(RigError, match=r"\[T, 3\]"):
        build_path_layout(np.array([[0, 1, 2, 3]]), 50)
    with pytest.raises(RigError, match="integers"):
        build_path_layout(np.array([[0.5, 1, 2]]), 50)
    with pytest.raises(RigError, match="heuristic"):
        build_path_layout(tris, 50, vertices=x, heuristic="zigzag")
    with pytest.raises(RigError, match="positions"):
        build_path_layout(tris, 50, heuristic="straight")
    with pytest.raises(RigError, match="vertices must have shape"):
        build_path_layout(tris, 50, vertices=x[:10])
    with pytest.raises(RigError, match="max_path_length"):
        build_path_layout(tris, 50, max_path_length=0)
    layout = build_path_layout(tris, 50, vertices=x)
    with pytest.raises(RigError, match="not decrease"):
        region_runs(layout, [0, 3, 2, 4], [0, 1, 2, 3])
    with pytest.raises(RigError, match="start at 0"):
        region_runs(layout, [1, 2], [0, 1])
    with pytest.raises(RigError, match="members"):
        region_runs(layout, [0, 2], [0, 1, 2])
    with pytest.raises(RigError, match="outside"):
        region_runs(layout, [0, 2], [0, 50])
    with pytest.raises(RigError, match="outside"):
        region_runs(layout, [0, 2], [-1, 3])
    with pytest.raises(RigError, match="twice"):
        region_runs(layout, [0, 3], [4, 5, 4])
    runs = region_runs(layout, [0, 2], [4, 5])
    with pytest.raises(RigError, match="values"):
        run_region_sums(layout, runs, np.zeros(49))
    with pytest.raises(RigError, match="accumulate"):
        run_region_sums(layout, runs, np.zeros(50), accumulate="pairwise")
    with pytest.raises(RigError, match="floating"):
        prefix_sums(layout, np.zeros(50), np.int32)
    with pytest.raises(RigError, match="reference"):
        prefix_sums(layout, np.zeros(50), reference=np.zeros(layout.path_count + 1))
    with pytest.raises(RigError, match="no path"):
        PathLayout.from_paths([[0, 1], [1]], 3)

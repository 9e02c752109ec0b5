"""The surface guard (warpskin.guard): what it writes is never worse than LBS, it leaves a good
physical result untouched, acts locally and smoothly, recovers over frames, keeps groups rigid.
Judged by the independent references of oracles.py (plain-loop strain and flips, separating-axis
pair counts over every pair), on spheres in generic positions (a random rotation and jitter)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from characters import generic_sphere, random_rotation
from oracles import intersecting_pairs_brute_force, strain_and_flips
from warpskin.errors import SceneError
from warpskin.guard import GuardParams, SurfaceGuard
from warpskin.metrics import PairQuery, self_intersections
from warpskin.quality import WrittenMesh


def _f32(x: np.ndarray) -> np.ndarray:
    """``x`` as USD stores points: rounded to float32."""
    return np.asarray(x, dtype=np.float32).astype(np.float64)


_rotation = random_rotation
_sphere = generic_sphere  # generic: no symmetry, no ties


def _pose(points: np.ndarray, seed: int) -> np.ndarray:
    """A rigid motion standing in for the frame's LBS."""
    return points @ _rotation(seed + 100).T + np.array([0.31, -0.17, 0.05])


def _dent(rest: np.ndarray, lbs: np.ndarray, centre: np.ndarray, radius: float, depth: float, seed: int = 0) -> np.ndarray:
    """LBS crumpled within ``radius`` of ``centre`` on the rest shape: every point there thrown
    by up to ``depth`` in a random direction (strained edges, triangles turned over)."""
    d = np.linalg.norm(rest - centre, axis=1)
    w = np.clip(1.0 - d / radius, 0.0, 1.0) ** 0.3
    return lbs + depth * w[:, None] * np.random.default_rng(seed).normal(size=lbs.shape)


def test_a_good_physical_result_is_written_untouched():
    rest, tris = _sphere((0, 0, 0), 0.1, 1)
    guard = SurfaceGuard(WrittenMesh("s", tris, rest))
    lbs = _pose(rest, 1)
    physical = lbs + 0.002 * np.sin(17.0 * lbs)  # a smooth bulge: nothing strained, flipped or crossing
    for _ in range(3):
        out = guard.apply(physical, lbs)
        assert np.array_equal(out, physical)
        assert guard.held == 0.0 and guard.guarded == 0.0
    assert guard.pair_counts == (0, 0)


def test_what_the_jump_limit_would_crumple_goes_back_to_the_guarded_surface():
    # the guard's result this frame is smooth; the jump limit, keeping points near their last
    # frame, leaves a crumpled dent in it (0.8 % of the edges strained): the dent's points and a
    # ramp around them go back towards the guarded points, as far as it takes for no edge or
    # triangle to be worse than there, far points stay as the limit left them;
    # nothing to keep, or a dent within the quality bounds, no change
    rest, tris = _sphere((0, 0, 0), 1.0, 2, subdivisions=4)
    guard = SurfaceGuard(WrittenMesh("s", tris, rest))
    lbs = _pose(rest, 2)
    guarded = lbs + 0.01 * np.sin(3.0 * lbs)
    assert strain_and_flips(rest, guarded, lbs, tris)[0] == 0.0
    limited = _dent(rest, guarded, rest[17], 0.25, 0.05)
    s, s_lbs, f = strain_and_flips(rest, limited, lbs, tris)
    assert s - s_lbs > 0.007 and f > 0.002
    out = guard.keep(limited, guarded, lbs)
    s, s_lbs, f = strain_and_flips(rest, out, lbs, tris)
    assert f == 0.0 and s <= s_lbs
    # the least share of the way back (the points jump no farther than they must): half of it
    # leaves the dent worse than the guarded surface, and it is less than all of it
    half = limited + 0.5 * (out - limited)
    s_half, _, f_half = strain_and_flips(rest, half, lbs, tris)
    assert f_half > 0.0 or s_half > s_lbs
    assert np.linalg.norm(out - limited, axis=1).max() < 0.99 * np.linalg.norm(guarded - limited, axis=1).max()
    far = np.linalg.norm(rest - rest[17], axis=1) > 1.0
    assert np.array_equal(out[far], np.asarray(limited[far], dtype=np.float32).astype(np.float64))
    assert guard.keep(guarded, guarded, lbs) is guarded
    clean = guarded + 0.001
    assert guard.keep(clean, guarded, lbs) is clean
    # a smaller dent, within the bounds the quality checks ask (0.5 % of the edges strained
    # beyond LBS, 1 % of the triangles turned): the limit's cut stands
    small = _dent(rest, guarded, rest[17], 0.12, 0.05)
    s, s_lbs, f = strain_and_flips(rest, small, lbs, tris)
    assert 0.0 < s - s_lbs < 0.004 and 0.0 < f < 0.008
    assert guard.keep(small, guarded, lbs) is small
    # a group (a piece moved as a whole) that the ramp reaches moves by one share
    group = np.where(np.linalg.norm(rest - rest[17], axis=1) < 0.6, 0, -1)
    grouped = SurfaceGuard(WrittenMesh("s", tris, rest), groups=group).keep(limited, guarded, lbs)
    inside = group == 0
    moved, full = (grouped - limited)[inside].ravel(), (guarded - limited)[inside].ravel()
    share = float(moved @ full / (full @ full))
    assert 0.0 < share <= 1.0 + 1e-6 and np.abs(moved - share * full).max() < 1e-6


def test_a_crumpled_dent_is_taken_back_locally_and_smoothly():
    rest, tris = _sphere((0, 0, 0), 1.0, 2, subdivisions=4)  # edges of about 0.095
    mesh = WrittenMesh("s", tris, rest)
    guard = SurfaceGuard(mesh)
    lbs = _pose(rest, 2)
    centre = rest[17]
    physical = _dent(rest, lbs, centre, 0.25, 0.05)
    s, s_lbs, f = strain_and_flips(rest, physical, lbs, tris)
    assert f > 0.002 and s > s_lbs + 0.002  # the physical result is crumpled there
    out = guard.apply(physical, lbs)
    s, s_lbs, f = strain_and_flips(rest, out, lbs, tris)
    assert f == 0.0
    assert s <= s_lbs
    # every point lies between its LBS and its physical result, on the segment
    # (to within the float32 rounding the points are written with: 6e-8 at 1 m)
    moved, taken = np.linalg.norm(physical - lbs, axis=1), out - lbs
    g = np.einsum("ij,ij->i", taken, physical - lbs) / np.maximum(moved**2, 1e-30)
    sure = moved > 1e-3
    assert np.all((g[sure] > -1e-4) & (g[sure] < 1 + 1e-4))
    np.testing.assert_allclose(taken[sure], g[sure, None] * (physical - lbs)[sure], rtol=0, atol=2e-7)
    # local: farther than the ramp (spread x the largest displacement) from the dent along the
    # surface (no nearer than straight), every point is exactly its physical result
    ramp = guard.params.spread * moved.max() + 2 * guard.edge
    far = np.linalg.norm(rest - centre, axis=1) > 0.25 + ramp
    assert far.sum() > 0.2 * len(rest)
    assert np.array_equal(out[far], _f32(physical[far]))


def test_a_piece_pushed_into_another_is_taken_back_to_no_more_pairs_than_lbs():
    a, ta = _sphere((0, 0, 0), 0.1, 3, subdivisions=2)
    b, tb = _sphere((0.215, 0.0, 0.0), 0.1, 4, subdivisions=2)
    rest = np.concatenate([a, b])
    tris = np.concatenate([ta, tb + len(a)])
    lbs = _pose(rest, 3)
    assert intersecting_pairs_brute_force(lbs, tris) == 0
    # the second sphere's near side bulges into the first (smoothly: nothing strained or flipped)
    towards = lbs[: len(a)].mean(axis=0) - lbs[len(a):].mean(axis=0)
    towards /= np.linalg.norm(towards)
    near = np.clip((lbs[len(a):] - lbs[len(a):].mean(axis=0)) @ towards / 0.1, 0.0, 1.0) ** 2
    physical = lbs.copy()
    physical[len(a):] += 0.04 * near[:, None] * towards
    assert intersecting_pairs_brute_force(physical, tris) > 10
    guard = SurfaceGuard(WrittenMesh("two", tris, rest))
    out = guard.apply(physical, lbs)
    assert intersecting_pairs_brute_force(out, tris) == 0
    assert guard.pair_counts == (0, 0)
    np.testing.assert_array_equal(out[: len(a)], _f32(physical[: len(a)]))  # the first sphere did not move


def test_a_crossing_that_slides_with_fewer_pairs_is_not_taken_back():
    # two pieces that cross at rest (a ball in a tube's end); the physics draws one out a little:
    # the crossing slides (pairs come and go near each other), the count falls, nothing is new
    a, ta = _sphere((0, 0, 0), 0.1, 5)
    b, tb = _sphere((0.17, 0.013, -0.007), 0.1, 6)
    rest = np.concatenate([a, b])
    tris = np.concatenate([ta, tb + len(a)])
    lbs = _pose(rest, 5)
    away = lbs[len(a):].mean(axis=0) - lbs[: len(a)].mean(axis=0)
    physical = lbs.copy()
    physical[len(a):] += 0.012 * away / np.linalg.norm(away)
    before, after = intersecting_pairs_brute_force(lbs, tris), intersecting_pairs_brute_force(physical, tris)
    assert before > 50 and after < before
    new = {tuple(p) for p in self_intersections(physical, tris).tolist()} - {tuple(p) for p in self_intersections(lbs, tris).tolist()}
    assert new  # pairs LBS does not have: the crossing slid
    guard = SurfaceGuard(WrittenMesh("two", tris, rest))
    out = guard.apply(physical, lbs)
    assert np.array_equal(out, physical)


def test_the_weight_recovers_by_its_rate_where_it_is_safe():
    rest, tris = _sphere((0, 0, 0), 0.1, 7)
    guard = SurfaceGuard(WrittenMesh("s", tris, rest), GuardParams(recover=0.1))
    lbs = _pose(rest, 7)
    guard.apply(_dent(rest, lbs, rest[5], 0.035, 0.03), lbs)
    g = guard.g.copy()
    assert g.min() < 0.5
    bulge = lbs + 0.002 * np.sin(17.0 * lbs)  # a harmless result: the weight may rise again
    for _ in range(12):
        out = guard.apply(bulge, lbs)
        g = np.minimum(1.0, g + 0.1)
        np.testing.assert_allclose(guard.g, g, atol=1e-12)
        # the blend of the float32 points as they are written, itself written as float32
        gw = guard.g[guard.mesh.weld][:, None]
        lw, bw = _f32(lbs), _f32(bulge)
        expected = bulge if np.all(gw >= 1.0) else _f32(np.where(gw >= 1.0, bw, lw + gw * (bw - lw)))
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-8)
    assert guard.held == 0.0 and np.array_equal(out, bulge)


def test_a_group_keeps_one_weight_and_stays_rigid():
    a, ta = _sphere((0, 0, 0), 0.1, 8)
    b, tb = _sphere((0.5, 0, 0), 0.05, 9, subdivisions=2)
    rest = np.concatenate([a, b])
    tris = np.concatenate([ta, tb + len(a)])
    groups = np.r_[np.full(len(a), -1), np.zeros(len(b), dtype=np.int64)]
    lbs = _pose(rest, 8)
    physical = lbs.copy()
    physical[len(a):] += np.array([0.01, 0.02, -0.01])  # the small piece moves as a whole
    # ... and one of its points is thrown out: that edge strains, the whole piece is held alike
    physical[len(a) + 3] += 0.06 * (lbs[len(a) + 3] - lbs[len(a):].mean(axis=0)) / 0.05
    guard = SurfaceGuard(WrittenMesh("two", tris, rest), groups=groups)
    out = guard.apply(physical, lbs)
    g = guard.g[guard.mesh.weld]
    assert np.ptp(g[len(a):]) == 0.0 and g[len(a)] < 1.0
    s, s_lbs, f = strain_and_flips(rest, out, lbs, tris)
    assert s <= s_lbs and f == 0.0


def test_the_guard_off_writes_the_physical_result():
    rest, tris = _sphere((0, 0, 0), 0.1, 10)
    lbs = _pose(rest, 10)
    physical = _dent(rest, lbs, rest[3], 0.035, 0.03)
    guard = SurfaceGuard(WrittenMesh("s", tris, rest), GuardParams(enabled=False))
    assert np.array_equal(guard.apply(physical, lbs), physical)


@pytest.mark.parametrize("share", [0.02, 0.3, 0.9])
def test_pairs_of_active_triangles_are_those_of_the_whole_count(share):
    # the guard's active-only query (the whole count's tree, refitted, asked by the active
    # triangles) gives exactly the pairs of the full count that have an active triangle
    a, ta = _sphere((0, 0, 0), 0.1, 11)
    b, tb = _sphere((0.16, 0.02, 0.01), 0.1, 12)
    p = np.concatenate([a, b])
    t = np.concatenate([ta, tb + len(a)])
    full = self_intersections(p, t)
    assert len(full) > 50
    active = np.random.default_rng(13).uniform(size=len(t)) < share
    query = PairQuery(t)
    np.testing.assert_array_equal(query.pairs(p), full)
    got = query.active(p, active)
    want = full[active[full[:, 0]] | active[full[:, 1]]]
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("key, value", [("strain", 1.6), ("flip_degrees", 0), ("rounds", 2.5), ("back_off", 0),
                                        ("recover", -0.1), ("spread", 0), ("enabled", 1), ("match", -1)])
def test_guard_settings_out_of_range_fail_with_one_line_naming_the_key(tmp_path, key, value):
    from warpskin.scene import load_scene

    p = tmp_path / "s.toml"
    v = str(value).lower() if isinstance(value, bool) else repr(value)
    p.write_text(f"[rig]\ngenerator = 'arm'\n[guard]\n{key} = {v}\n")
    with pytest.raises(SceneError) as e:
        load_scene(p).guard_params()
    msg = str(e.value)
    assert "\n" not in msg and f"[guard] {key}" in msg and "s.toml" in msg


def test_scene_guard_and_physics_weights_sections_are_read(tmp_path):
    from warpskin.scene import load_scene

    p = tmp_path / "s.toml"
    p.write_text("[rig]\ngenerator = 'arm'\n[guard]\nenabled = false\nrecover = 0.25\n"
                 "[physics.weights]\n\"*hand*\" = 0.0\n\"upper*\" = 0.5\n")
    scene = load_scene(p)
    g = scene.guard_params()
    assert g.enabled is False and g.recover == 0.25
    assert scene.physics_weights() == {"*hand*": 0.0, "upper*": 0.5}



def _pushed_out(seed: int, swell: float):
    """Two spheres apart at rest; under "LBS" the second sinks into the first (a pose-made
    intersection); the "physics" pushes it back out and swells it (``swell`` x across: edges
    stretched by up to that, no crossing): taken back towards LBS, it would sink in again."""
    a, ta = _sphere((0, 0, 0), 1.0, seed, subdivisions=3)
    b, tb = _sphere((2.05, 0.0, 0.0), 1.0, seed + 1, subdivisions=3)  # about 0.05 apart
    rest = np.concatenate([a, b])
    tris = np.concatenate([ta, tb + len(a)])
    lbs = rest.copy()
    lbs[len(a):] -= np.array([0.8, 0.0, 0.0])  # sunk into the first by about 0.75
    physical = rest.copy()  # pushed back out, clear of the first
    physical[len(a):, 1:] *= swell
    return rest, tris, lbs, physical


def test_a_skin_simulated_directly_is_written_as_simulated_while_its_physics_keeps_the_surface():
    # swollen by 1.49: past the guard's 1.45, within the measure's 1.5; its contact resolved
    rest, tris, lbs, physical = _pushed_out(20, 1.49)
    assert intersecting_pairs_brute_force(lbs, tris) > 20 and intersecting_pairs_brute_force(physical, tris) == 0
    guard = SurfaceGuard(WrittenMesh("two", tris, rest), direct=True)
    for _ in range(2):
        assert np.array_equal(guard.apply(physical, lbs), physical)
        assert guard.trusted and guard.held == 0.0
    # a captured mesh with the same result is held to its LBS: taken back towards it, it sinks in
    plain = SurfaceGuard(WrittenMesh("two", tris, rest)).apply(physical, lbs)
    assert plain is not physical and intersecting_pairs_brute_force(plain, tris) > 0


def test_a_skin_whose_physics_crumples_is_guarded_from_then_on():
    # swollen by 2.2: its edges strained past 1.5 where LBS's are not, on most of a sphere
    rest, tris, lbs, physical = _pushed_out(21, 2.2)
    guard = SurfaceGuard(WrittenMesh("two", tris, rest), direct=True)
    out = guard.apply(physical, lbs)
    assert not guard.trusted
    s, s_lbs, f = strain_and_flips(rest, out, lbs, tris)
    assert f == 0.0 and s <= s_lbs
    assert 0 < intersecting_pairs_brute_force(out, tris) <= intersecting_pairs_brute_force(lbs, tris)
    mild = lbs + 0.3 * (physical - lbs)  # a frame it would pass: still guarded
    guard.apply(mild, lbs)
    assert not guard.trusted


def test_skin_bunched_where_lbs_passes_through_itself_keeps_the_trust_and_elsewhere_loses_it():
    # LBS sinks the second sphere into the first; the physics keeps it clear and lifts three
    # points of it (not neighbours, six edges each) by two median edges: 18 of the 3840 edges
    # strained past 1.5x (0.47 %: past the trust's 0.45 %, within the 0.5 % the quality checks
    # ask), no triangle turned. Near the circle where LBS's spheres cross (a crease's bunching)
    # the skin stays trusted; the same points on the far side of the sphere crumple the trust,
    # and so do the points near the circle where the physics lets the spheres cross itself
    rest, tris, lbs, _ = _pushed_out(23, 1.0)
    half = len(rest) // 2
    assert intersecting_pairs_brute_force(lbs, tris) > 20
    edges = np.unique(np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]]), axis=1), axis=0)
    assert len(edges) == 3840
    degree = np.bincount(edges.ravel(), minlength=len(rest))
    step = 2.0 * float(np.median(np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)))
    along = rest[:, 0] - 2.05  # from the second sphere's centre, along the axis of the two

    def lifted(offset, shift):
        picked = []
        for i in np.argsort(np.abs(along - offset)):
            if i >= half and degree[i] == 6 and not any(((edges == [min(i, j), max(i, j)]).all(axis=1)).any()
                                                        for j in picked):
                picked.append(int(i))
            if len(picked) == 3:
                break
        x = rest.copy()
        radial = x[picked] - np.array([2.05, 0.0, 0.0])
        x[picked] += step * radial / np.linalg.norm(radial, axis=1)[:, None]
        x[half:, 0] += shift
        return x, np.abs(along[picked] - offset).max()

    # (the points' offset, the second sphere moved along the axis, trusted): LBS's crossing
    # circle, its mirror, LBS's crossing circle with the spheres passing 0.07 into each other
    for offset, shift, trusted in ((-0.625, 0.0, True), (0.625, 0.0, False), (-0.625, -0.12, False)):
        physical, spread = lifted(offset, shift)
        assert spread < 0.1
        assert (intersecting_pairs_brute_force(physical, tris) == 0) == (shift == 0.0)
        s, s_lbs, flipped = strain_and_flips(rest, physical, lbs, tris)
        assert s - s_lbs == pytest.approx(18 / 3840) and flipped == 0.0
        guard = SurfaceGuard(WrittenMesh("two", tris, rest), direct=True)
        out = guard.apply(physical, lbs)
        assert guard.trusted == trusted
        if trusted:
            assert np.array_equal(out, physical) and guard.held == 0.0
        else:
            assert guard.held > 0.0


def test_a_crossing_lbs_makes_that_slides_is_left_and_only_its_net_gain_taken_back():
    # LBS sinks the second sphere into the first (pairs the rest pose does not have); the result
    # sinks it as deep, slid sideways: the crossing moves by about a ring, trading each pair LBS
    # has for a neighbour, and nothing is taken back. Slid further, it gains 2 pairs over LBS's:
    # only those are flagged
    rest, tris, lbs, _ = _pushed_out(23, 1.0)
    half = len(rest) // 2
    for slide, gained in ((0.02, 0), (0.04, 2)):
        physical = lbs.copy()
        physical[half:, 1] += slide
        with_lbs = {tuple(p) for p in self_intersections(lbs, tris)}
        ours = {tuple(p) for p in self_intersections(physical, tris)}
        assert len(ours - with_lbs) > 20
        assert intersecting_pairs_brute_force(physical, tris) - intersecting_pairs_brute_force(lbs, tris) == gained
        guard = SurfaceGuard(WrittenMesh("two", tris, rest))
        out = guard.apply(physical, lbs)
        assert guard.flags["pairs"] == gained
        if gained == 0:
            assert np.array_equal(out, physical) and guard.held == 0.0
        else:
            assert 0.0 < guard.held < 0.02


def test_a_stretch_made_on_purpose_is_written_and_a_squeeze_there_is_not():
    # the second sphere swollen by 2.2 (its edges stretched past 1.5) where the physics stretches
    # the skin on purpose (a muscle's belly): still trusted, and not flagged once guarded either
    rest, tris, lbs, physical = _pushed_out(22, 2.2)
    intended = np.zeros(len(rest), dtype=bool)
    intended[len(rest) // 2:] = True
    for direct in (True, False):
        guard = SurfaceGuard(WrittenMesh("two", tris, rest), direct=direct, intended=intended)
        assert np.array_equal(guard.apply(physical, lbs), physical)
        assert guard.held == 0.0 and guard.trusted == direct
    # the same stretch outside the intended points crumples the trust (as above)
    elsewhere = SurfaceGuard(WrittenMesh("two", tris, rest), direct=True, intended=~intended)
    elsewhere.apply(physical, lbs)
    assert not elsewhere.trusted
    # squeezed there instead (edges shortened past 1 / 1.5): not on purpose, guarded
    squeezed = rest.copy()
    squeezed[len(rest) // 2:, 1:] *= 0.45
    guard = SurfaceGuard(WrittenMesh("two", tris, rest), direct=True, intended=intended)
    out = guard.apply(squeezed, lbs)
    assert not guard.trusted and guard.held > 0.0
    assert strain_and_flips(rest, out, lbs, tris)[0] < strain_and_flips(rest, squeezed, lbs, tris)[0]


def test_a_captured_mesh_is_held_to_its_lbs():
    rest, tris, lbs, physical = _pushed_out(22, 2.2)
    out = SurfaceGuard(WrittenMesh("two", tris, rest)).apply(physical, lbs)
    s, s_lbs, f = strain_and_flips(rest, out, lbs, tris)
    assert f == 0.0 and s <= s_lbs
    # taken back towards LBS, it sinks in again: no more than LBS's pairs, but some
    assert 0 < intersecting_pairs_brute_force(out, tris) <= intersecting_pairs_brute_force(lbs, tris)


def test_a_direct_skin_is_written_as_its_lbs_where_its_ceiling_is_zero():
    # vertices where no layer depth fits have physics weight 0: the guard's ceiling
    rest, tris = _sphere((0, 0, 0), 0.1, 30)
    lbs = _pose(rest, 30)
    physical = lbs + 0.002 * np.sin(17.0 * lbs)
    ceiling = np.ones(len(rest))
    ceiling[:40] = 0.0
    out = SurfaceGuard(WrittenMesh("s", tris, rest), ceiling=ceiling, direct=True).apply(physical, lbs)
    np.testing.assert_array_equal(out[:40], _f32(lbs[:40]))
    np.testing.assert_array_equal(out[40:], _f32(physical[40:]))


# ---------------------------------------------------------------- pieces written as separate meshes
def _cross_pairs_brute_force(meshes: list, points: dict) -> set:
    """Every intersecting pair of triangles from two different meshes (each welded by rest
    position), by the separating-axis oracle over all pairs of the two meshes stacked."""
    from oracles import intersecting_pair_list_brute_force

    stacked, tris, label, offset = [], [], [], 0
    for k, m in enumerate(meshes):
        w = m.welded(points[m.name])
        stacked.append(w)
        tris.append(m.welded_triangles + offset)
        label.append(np.full(len(m.welded_triangles), k))
        offset += len(w)
    tris, label = np.concatenate(tris), np.concatenate(label)
    pairs = intersecting_pair_list_brute_force(np.concatenate(stacked), tris)
    return {(int(i), int(j)) for i, j in pairs if label[i] != label[j]}


def test_pairs_between_meshes_are_every_crossing_of_two_meshes_and_no_other():
    from warpskin.quality import CrossPairs

    # two spheres sunk into each other, and a third crossing itself (its own pairs are not between meshes)
    va, ta = _sphere([0.0, 0.0, 0.0], 1.0, 1, 2)
    vb, tb = _sphere([1.63, 0.21, -0.12], 0.8, 2, 2)
    vc, tc = _sphere([-2.9, 0.07, 0.13], 0.7, 3, 2)
    vc2, tc2 = _sphere([-2.4, 0.11, -0.05], 0.6, 4, 2)  # a second shell in mesh c, through the first
    a = WrittenMesh("a", ta, va)
    b = WrittenMesh("b", tb, vb)
    c = WrittenMesh("c", np.concatenate([tc, tc2 + len(vc)]), np.concatenate([vc, vc2]))
    cross = CrossPairs([a, b, c])
    rest = {m.name: m.rest for m in (a, b, c)}
    t = len(cross.triangles)
    want_rest = _cross_pairs_brute_force([a, b, c], rest)
    assert want_rest  # a and b cross at rest; c crosses only itself
    assert {(int(k // t), int(k % t)) for k in cross.keys(rest)} == want_rest
    assert cross.rest_counts[0 * 3 + 1] == len(want_rest) and cross.rest_counts.sum() == len(want_rest)
    # a pose: b pushed deeper into a, c moved onto b's far side
    pose = dict(rest)
    pose["b"] = vb + np.array([-0.23, 0.04, 0.02])
    pose["c"] = np.concatenate([vc, vc2]) + np.array([5.05, 0.16, 0.09])
    lbs = dict(rest)
    keys, keys_lbs = cross.keys_of_two(pose, lbs)
    want = _cross_pairs_brute_force([a, b, c], pose)
    assert {(int(k // t), int(k % t)) for k in keys} == want
    assert set(keys_lbs.tolist()) == set(cross.keys(rest).tolist())
    beyond = cross.beyond_rest(keys)
    lab = cross.label
    ab = sum(1 for i, j in want if {lab[i], lab[j]} == {0, 1})
    bc = sum(1 for i, j in want if {lab[i], lab[j]} == {1, 2})
    assert bc > 0 and beyond[1 * 3 + 2] == bc and beyond[0 * 3 + 1] == max(ab - len(want_rest), 0)
    m = cross.measure(keys, keys_lbs)
    assert m["pairs_across"] == len(want) and m["pairs_across_lbs"] == len(want_rest)
    assert m["pairs_across_new"] == int(beyond.sum()) and m["pairs_across_new_lbs"] == 0
    assert m["pairs_across_worst"][:2] in (("a", "b"), ("b", "c"))
    # then c alone moves again (onto a's other side, off b): only its triangles query the
    # refitted tree, the pairs of a and b kept from the last count, the same as brute force
    later = dict(pose)
    later["c"] = np.concatenate([vc, vc2]) + np.array([1.77, 0.93, 0.05])
    moved = cross.keys(later, [2], keys)
    want_later = _cross_pairs_brute_force([a, b, c], later)
    assert {(int(k // t), int(k % t)) for k in moved} == want_later
    assert any(2 in (lab[i], lab[j]) for i, j in want_later) and want_later != want


def _box(centre, size, seed: int):
    """A generic closed box: subdivided, rotated slightly, jittered."""
    s = trimesh.creation.box(extents=size)
    s = s.subdivide().subdivide()
    rng = np.random.default_rng(seed)
    v = np.asarray(s.vertices, dtype=np.float64)
    ang = 0.03
    rz = np.array([[np.cos(ang), -np.sin(ang), 0.0], [np.sin(ang), np.cos(ang), 0.0], [0.0, 0.0, 1.0]])
    v = v @ rz.T + 1e-3 * rng.uniform(-1, 1, size=v.shape)
    return v + np.asarray(centre, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


@pytest.mark.parametrize("rigid", [True, False])
@pytest.mark.parametrize("carrier_rigid", [True, False])
def test_a_piece_pushed_into_by_its_carrier_is_carried_not_held(rigid, carrier_rigid):
    """A torso (root joint; rigid, or bulging where the pad sits) sways into a shoulder pad (a
    child joint; rigid or not) that LBS keeps apart from it: the pad is carried by the torso's motion, as far as needed to cross no more than LBS
    does; the torso keeps all of its physics; the pad stays within the joint limit where it meets
    the torso."""
    from warpskin.guard import CrossGuard
    from warpskin.quality import CrossPairs

    vt, tt = _box([0.0, 0.0, 0.0], [1.0, 2.0, 0.6], 5)
    vs, ts = _sphere([0.0, 1.31, 0.02], 0.35, 6, 2)  # sunk into the torso's top at rest
    torso = WrittenMesh("torso", tt, vt)
    pad_joints = np.nonzero(vs[:, 1] < 1.1)[0]  # where it meets the torso at rest
    pad = WrittenMesh("pad", ts, vs, joint_points=pad_joints)
    prm = GuardParams()
    guards = {"torso": SurfaceGuard(torso, prm, groups=np.zeros(len(vt), np.int64) if carrier_rigid else None),
              "pad": SurfaceGuard(pad, prm, groups=np.zeros(len(vs), np.int64) if rigid else None)}
    cross = CrossPairs([torso, pad])
    limit = 0.2
    guard = CrossGuard(cross, guards, prm, depth=np.array([0, 3]), joint_limit=limit)
    lbs = {"torso": vt, "pad": vs}
    sway = np.array([0.013, 0.147, -0.008])  # the torso's physics: up into the pad
    bulge = np.zeros(len(vt)) if carrier_rigid else 0.02 * np.exp(-np.linalg.norm(vt - [0.0, 1.0, 0.0], axis=1) ** 2 / 0.1)
    physical = {"torso": vt + sway + bulge[..., None] * np.array([0.0, 1.0, 0.0]), "pad": vs}
    guarded = {name: guards[name].apply(physical[name], lbs[name]) for name in guards}
    before = cross.beyond_rest(cross.keys(guarded))[1]
    assert before > 0  # the sway sinks the pad in
    out = guard.apply(guarded, lbs)
    after = _cross_pairs_brute_force([torso, pad], out)
    assert len(after) <= cross.rest_counts[1]  # no more than at rest (LBS is the rest here)
    np.testing.assert_array_equal(out["torso"], guarded["torso"])  # the carrier keeps its physics
    moved = out["pad"] - vs
    assert np.linalg.norm(moved, axis=1).max() <= limit * (1 + 1e-6)
    # carried, not held: the pad rose with the torso by a good share of the sway
    assert moved.mean(axis=0) @ sway / (sway @ sway) > 0.3
    if rigid:  # a rigid piece stays rigid
        d0 = np.linalg.norm(vs[:, None] - vs[None], axis=2)
        d1 = np.linalg.norm(out["pad"][:, None] - out["pad"][None], axis=2)
        assert np.abs(d1 - d0).max() < 1e-5
    assert guard.keys is not None and guard.rounds >= 1


def test_crossings_between_meshes_that_only_slide_are_left_alone():
    """Two meshes that cross at rest and, in the pose, trade crossing pairs one for another as
    they slide (no more in number than LBS's) are written as the physics gives them."""
    from warpskin.guard import CrossGuard
    from warpskin.quality import CrossPairs

    va, ta = _sphere([0.0, 0.0, 0.0], 1.0, 7, 2)
    vb, tb = _sphere([1.71, 0.13, 0.05], 0.8, 8, 2)
    a, b = WrittenMesh("a", ta, va), WrittenMesh("b", tb, vb)
    prm = GuardParams()
    guards = {"a": SurfaceGuard(a, prm), "b": SurfaceGuard(b, prm)}
    cross = CrossPairs([a, b])
    guard = CrossGuard(cross, guards, prm, depth=np.array([0, 1]))
    lbs = {"a": va, "b": vb}
    physical = {"a": va, "b": vb + np.array([0.015, -0.03, 0.04])}  # slides along the crossing
    guarded = {n: guards[n].apply(physical[n], lbs[n]) for n in guards}
    keys, keys_lbs = cross.keys_of_two(guarded, lbs)
    assert not np.array_equal(keys, keys_lbs)  # pairs traded ...
    assert cross.beyond_rest(keys)[1] <= cross.beyond_rest(keys_lbs)[1]  # ... none gained
    out = guard.apply(guarded, lbs)
    assert out["b"] is guarded["b"] and out["a"] is guarded["a"] and guard.rounds == 0


def _folded(rest: np.ndarray, tris: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``rest`` with ``count`` triangles far apart each folded over: its first point taken
    across the line of the other two, in the triangle's plane, to a fifth of its distance from
    that line (the triangle turns over; its neighbours about that point are only bent)."""
    rng = np.random.default_rng(seed)
    out = rest.copy()
    chosen = []
    for t in rng.permutation(len(tris)):
        c = rest[tris[t]].mean(axis=0)
        if all(np.linalg.norm(c - rest[tris[k]].mean(axis=0)) > 0.5 for k in chosen):
            chosen.append(t)
        if len(chosen) == count:
            break
    for t in chosen:
        v, a, b = tris[t]
        u = (rest[b] - rest[a]) / np.linalg.norm(rest[b] - rest[a])
        foot = rest[a] + ((rest[v] - rest[a]) @ u) * u
        out[v] = foot - 0.2 * (rest[v] - foot)
    return out


@pytest.mark.parametrize("folds, trusted", [(5, True), (16, False)])
def test_a_direct_skin_is_trusted_only_while_it_turns_over_no_more_than_the_written_bound(folds, trusted):
    # a sphere of 1280 triangles kept at rest by its physics where "LBS" folds triangles over
    # (no skinned normals given: LBS is the reference): 5 turned against LBS (0.4 %, under the
    # 1 % the written meshes are held to) keep the trust, 16 (1.25 %, over it) lose it; the
    # boundary is tested with margins on both sides
    rest, tris = _sphere((0.0, 0.0, 0.0), 1.0, 31)
    lbs = _folded(rest, tris, folds, 32)
    physical = rest.copy()
    assert strain_and_flips(rest, physical, lbs, tris)[2] == pytest.approx(folds / len(tris))
    guard = SurfaceGuard(WrittenMesh("sphere", tris, rest), direct=True)
    out = guard.apply(physical, lbs)
    assert guard.trusted is trusted
    if trusted:
        assert np.array_equal(out, physical)
    else:
        assert strain_and_flips(rest, out, lbs, tris)[2] <= 0.01


def test_lbs_own_folds_unfolded_by_the_physics_are_neither_flags_nor_flips():
    # "LBS" folds 24 triangles of 1280 over (1.9 %, past the trust's 1 %); the frame's skinned
    # normals (its points' blended maps, here one rotation for all: the rest normals turned)
    # say they point the other way. A result that keeps them the right way is counted
    # unflipped and keeps the trust; judged against LBS alone it would lose it. A result that
    # turns other triangles over is still judged against LBS
    rest, tris = _sphere((0.0, 0.0, 0.0), 1.0, 33)
    r = _rotation(34)
    posed = rest @ r.T
    lbs = _folded(rest, tris, 24, 35) @ r.T
    mesh = WrittenMesh("sphere", tris, rest)
    skinned = mesh.skinned_normals(np.tile(r, (len(rest), 1, 1)))
    # the cross-product form against the cofactor itself: cof(R) = R for a rotation
    e1, e2 = rest[tris[:, 1]] - rest[tris[:, 0]], rest[tris[:, 2]] - rest[tris[:, 0]]
    assert np.allclose(skinned, np.cross(e1, e2) @ r.T, atol=1e-12)
    assert mesh.flipped(posed, lbs).size == 24 and mesh.flipped(posed, lbs, skinned).size == 0
    assert strain_and_flips(rest, posed, lbs, tris)[2] == pytest.approx(24 / len(tris))  # the oracle agrees
    guard = SurfaceGuard(mesh, direct=True)
    assert np.array_equal(guard.apply(posed, lbs, skinned), posed) and guard.trusted
    plain = SurfaceGuard(mesh, direct=True)
    plain.apply(posed, lbs)
    assert not plain.trusted
    # the physics turning 32 other triangles over (2.5 %) loses the trust
    turned = _folded(rest, tris, 32, 36) @ r.T
    assert mesh.flipped(turned, lbs, skinned).size > 24
    guard = SurfaceGuard(mesh, direct=True)
    guard.apply(turned, lbs, skinned)
    assert not guard.trusted


def test_skinned_normals_are_the_cofactor_of_the_mean_blended_map():
    # a generic (non-orthogonal) map per point: the triangle's mean map B gives
    # cof(B) (e1 x e2) = det(B) B^-T (e1 x e2), computed here by inversion
    rest, tris = _sphere((0.0, 0.0, 0.0), 1.0, 37, subdivisions=1)
    rng = np.random.default_rng(38)
    blended = np.eye(3) + 0.3 * rng.normal(size=(len(rest), 3, 3))
    mesh = WrittenMesh("sphere", tris, rest)
    got = mesh.skinned_normals(blended)
    b = blended[tris].mean(axis=1)
    n0 = np.cross(rest[tris[:, 1]] - rest[tris[:, 0]], rest[tris[:, 2]] - rest[tris[:, 0]])
    want = np.einsum("t,tji,tj->ti", np.linalg.det(b), np.linalg.inv(b), n0)
    assert np.allclose(got, want, rtol=1e-9, atol=1e-12)

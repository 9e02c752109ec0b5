"""Self-collision: constraint gradients against finite differences, single-projection
separation, detection against brute force, buffer overflow and growth (every device)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import warp as wp
from pxr import Usd, UsdGeom

from characters import pressed_arm
from oracles import coarse_arm, prim
from warpskin.kernels import collision as k
from warpskin.kernels import contact_detection as kd
from warpskin.kernels import contact_projection as kp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _edge_edge_eval(p: wp.array(dtype=wp.vec3), sgn: float, h: float, violated_only: int, out_c: wp.array(dtype=float),
                    out_g: wp.array(dtype=wp.vec3)):
    c, g1, g2, g3, g4 = kp.edge_edge_constraint(p[0], p[1], p[2], p[3], sgn, h, violated_only != 0)
    out_c[0] = c
    out_g[0] = g1
    out_g[1] = g2
    out_g[2] = g3
    out_g[3] = g4


def _ee(points, sgn, h, device, violated_only=False):
    p = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
    c = wp.zeros(1, dtype=float, device=device)
    g = wp.zeros(4, dtype=wp.vec3, device=device)
    wp.launch(_edge_edge_eval, dim=1, inputs=[p, sgn, h, int(violated_only), c, g], device=device)
    return float(c.numpy()[0]), g.numpy().astype(np.float64)


def _ee_reference(p, sgn, h):
    n = np.cross(p[1] - p[0], p[3] - p[2])
    return sgn * (p[3] - p[0]) @ n / np.linalg.norm(n) - h


def _line_params(p):
    """Unclamped parameters (s, t) of the closest points of the two edges' infinite lines."""
    d1, d2, r = p[1] - p[0], p[3] - p[2], p[0] - p[2]
    a, b, e, c, f = d1 @ d1, d1 @ d2, d2 @ d2, d1 @ r, d2 @ r
    den = a * e - b * b
    return (b * f - c * e) / den, (a * f - b * c) / den


def _edges_whose_lines_meet(rng, inside):
    """Random edges whose lines' closest points lie within [-0.5, 1.5] of both (``inside``) or
    beyond [-2, 3] of one: generic, well away from the branch boundary at [-1, 2]."""
    while True:
        p = rng.normal(size=(4, 3))
        s, t = _line_params(p)
        if inside and -0.5 < s < 1.5 and -0.5 < t < 1.5:
            return p
        if not inside and (min(s, t) < -2.0 or max(s, t) > 3.0):
            return p


@pytest.mark.parametrize("seed", range(6))
def test_edge_edge_gradient_equals_finite_differences(device, seed):
    rng = np.random.default_rng(seed)
    p = _edges_whose_lines_meet(rng, inside=True)
    sgn, h = (1.0 if seed % 2 else -1.0), 0.01
    c, g = _ee(p, sgn, h, device)
    assert c == pytest.approx(_ee_reference(p, sgn, h), abs=1e-5)
    eps = 1e-5
    for i in range(4):
        for d in range(3):
            dp = np.zeros((4, 3))
            dp[i, d] = eps
            fd = (_ee_reference(p + dp, sgn, h) - _ee_reference(p - dp, sgn, h)) / (2 * eps)
            assert g[i, d] == pytest.approx(fd, abs=2e-3 * max(1.0, abs(fd)))


def _segment_distance(p, samples=2001):
    """Brute force: the distance of the two edges by dense sampling of the first."""
    s = np.linspace(0.0, 1.0, samples)[:, None]
    q = p[0] + s * (p[1] - p[0])
    d = p[3] - p[2]
    t = np.clip((q - p[2]) @ d / (d @ d), 0.0, 1.0)[:, None]
    return float(np.linalg.norm(q - (p[2] + t * d), axis=1).min())


@pytest.mark.parametrize("seed", range(4))
def test_edge_edge_far_lines_use_the_edges_distance(device, seed):
    """Edges whose lines meet far beyond their ends: C is the edges' own distance minus h (the
    lines' distance, the paper's C, would be near zero for coplanar edges however far apart)."""
    rng = np.random.default_rng(100 + seed)
    p = _edges_whose_lines_meet(rng, inside=False)
    h = 0.01
    c, g = _ee(p, 1.0 if seed % 2 else -1.0, h, device)
    assert c == pytest.approx(_segment_distance(p) - h, abs=1e-5)
    eps = 1e-5
    for i in range(4):
        for d in range(3):
            dp = np.zeros((4, 3))
            dp[i, d] = eps
            fd = (_segment_distance(p + dp, 20001) - _segment_distance(p - dp, 20001)) / (2 * eps)
            assert g[i, d] == pytest.approx(fd, abs=2e-2 * max(1.0, abs(fd)))


def test_edge_edge_coplanar_edges_far_apart_are_inactive(device):
    """Two edges in one plane (a flat cap of a low-poly mesh), 0.5 apart, whose lines cross
    3 edge lengths away: no constraint although the lines' distance is 0."""
    p = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.2, 0.5, 0.0], [0.8, 0.52, 0.0]])
    s, t = _line_params(p)
    assert max(abs(s), abs(t)) > 3.0
    c, _ = _ee(p, 1.0, 0.05, device)
    assert c == pytest.approx(_segment_distance(p) - 0.05, abs=1e-5) and c > 0.4


def test_edge_edge_parallel_branch(device):
    # two parallel edges 0.02 apart along z: C = sgn |d| - h, gradient along the perpendicular
    p = np.array([[0, 0, 0], [1, 0, 0], [0.2, 0, 0.02], [0.8, 0, 0.02]], dtype=float)
    c, g = _ee(p, 1.0, 0.005, device)
    assert c == pytest.approx(0.02 - 0.005, abs=1e-6)
    # moving the second edge up by e changes C by e: finite differences of the distance
    assert g[2, 2] + g[3, 2] == pytest.approx(1.0, abs=1e-5)
    assert g[0, 2] + g[1, 2] == pytest.approx(-1.0, abs=1e-5)
    assert np.abs(g[:, :2]).max() < 1e-6


def test_edge_edge_violated_only_skips_only_the_gradients_of_satisfied_pairs(device):
    # the projection's form: the same C everywhere; where C < 0 the same gradients, bit for
    # bit; where C >= 0 zero gradients. Lines meeting near and far, and parallel edges, each
    # with a thin thickness and one 0.05 past their distance (both signs)
    rng = np.random.default_rng(11)
    configs = [_edges_whose_lines_meet(rng, inside=True) for _ in range(3)]
    configs += [_edges_whose_lines_meet(rng, inside=False) for _ in range(3)]
    configs.append(np.array([[0, 0, 0], [1, 0, 0], [0.2, 0, 0.02], [0.8, 0, 0.02]], dtype=float))
    seen = set()
    for p in configs:
        for sgn in (1.0, -1.0):
            c0, _ = _ee(p, sgn, 0.0, device)
            for h in (0.004, abs(c0) + 0.05):
                c, g = _ee(p, sgn, h, device)
                c_lazy, g_lazy = _ee(p, sgn, h, device, violated_only=True)
                assert c_lazy == c
                if c < 0.0:
                    np.testing.assert_array_equal(g_lazy, g)
                    assert np.abs(g).max() > 0.1
                else:
                    assert not g_lazy.any()
                seen.add(c < 0.0)
    assert seen == {True, False}


def _contact_scalars(device, n: int, *, thickness=0.0, radius=0.0, friction=0.0, restitution=0.0):
    """One character's :class:`CollisionScalars` (the rest zero) and a vertex-to-character map
    of ``n`` zeros: what the contact kernels read in place of scalars."""
    s = k.CollisionScalars()
    s.thickness, s.radius, s.friction, s.restitution = thickness, radius, friction, restitution
    return wp.array([s], dtype=k.CollisionScalars, device=device), wp.zeros(n, dtype=wp.int32, device=device)


def _project_launch(device, x, w, tri, delta, count, active, pt=None, ee=None, edges=None, h=0.01, chunk=1,
                    counted=None, count_active=True):
    """One launch of the solver's contact pass (:func:`~warpskin.kernels.contact_projection.
    project_contacts_kernel`) over the given contacts into ``delta``, ``count`` and ``active``
    (not applied): ``counted`` of each kind counted (default all), a thread per ``chunk``
    contacts, both buffers five slots longer than the longer list (slots past the counts
    unused); the violated constraints counted into ``active`` only with ``count_active``."""
    pt, ee = list(pt or ()), list(ee or ())
    capacity = max(len(pt), len(ee)) + 5
    params, tree = _contact_scalars(device, len(w), thickness=h)

    def buffer(values, dtype):
        return wp.array(list(values) + [0] * (capacity - len(values)), dtype=dtype, device=device)

    def counts(values):
        return wp.array([len(values) if counted is None or not values else counted], dtype=wp.int32, device=device)

    e = np.asarray(edges if edges is not None else [[0, 1]], dtype=np.int32)
    threads = -(-capacity // chunk)
    wp.launch(kp.project_contacts_kernel, dim=2 * threads,
              inputs=[x, w, wp.array(np.asarray(tri, dtype=np.int32).reshape(-1, 3), dtype=wp.int32, device=device),
                      counts(pt), buffer([v for v, _ in pt], wp.int32), buffer([t for _, t in pt], wp.int32),
                      wp.array(e, dtype=wp.int32, device=device), counts(ee), buffer([a for a, _, _ in ee], wp.int32),
                      buffer([b for _, b, _ in ee], wp.int32), buffer([sg for _, _, sg in ee], wp.float32), params,
                      tree, chunk, threads, int(count_active)],
              outputs=[delta, count, active], device=device)


def _project_once(device, points, inv_mass, tri, pt=None, ee=None, edges=None, h=0.01, chunk=1, counted=None):
    """One Jacobi pass over the given contacts as the solver makes it (one launch of both kinds,
    then the averaged corrections applied): ``(positions [N, 3], constraints active)``."""
    x = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
    w = wp.array(inv_mass.astype(np.float32), dtype=wp.float32, device=device)
    n = len(points)
    delta = wp.zeros(n, dtype=wp.vec3, device=device)
    count = wp.zeros(n, dtype=wp.int32, device=device)
    active = wp.zeros(1, dtype=wp.int32, device=device)
    _project_launch(device, x, w, tri, delta, count, active, pt, ee, edges, h, chunk, counted)
    wp.launch(kp.apply_deltas_kernel, dim=n, inputs=[delta, count], outputs=[x], device=device)
    return x.numpy().astype(np.float64), int(active.numpy()[0])


@pytest.mark.parametrize("chunk", [1, 3])
def test_one_launch_projects_both_kinds_of_contacts_as_one_launch_each_does(device, chunk):
    # the solver's pass launches both kinds of contacts at once: its first threads take the
    # point-triangle chunks, the rest the edge-edge ones. The same corrections as the point-
    # triangle contacts launched alone, then the edge-edge ones alone, into the same sums, on a
    # generic cloud of contacts, the last buffer slots beyond the counts left out
    rng = np.random.default_rng(7)
    n = 40
    points = rng.normal(size=(n, 3)) * 0.05
    inv_mass = rng.uniform(0.5, 2.0, size=n)
    tri = np.array([rng.choice(n, size=3, replace=False) for _ in range(12)])
    edges = np.array([rng.choice(n, size=2, replace=False) for _ in range(20)])
    pt = [(int(v), int(t)) for v, t in zip(rng.integers(0, n, 30), rng.integers(0, 12, 30)) if v not in tri[t]]
    ee = [(int(a), int(b), float(rng.choice([-1.0, 1.0]))) for a, b in zip(rng.integers(0, 20, 30), rng.integers(0, 20, 30))
          if not set(edges[a]) & set(edges[b])]
    h = 0.03

    def run(*kinds, count_active=True):
        x = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
        w = wp.array(inv_mass.astype(np.float32), dtype=wp.float32, device=device)
        delta = wp.zeros(n, dtype=wp.vec3, device=device)
        count = wp.zeros(n, dtype=wp.int32, device=device)
        active = wp.zeros(1, dtype=wp.int32, device=device)
        for p, e in kinds:
            _project_launch(device, x, w, tri, delta, count, active, p, e, edges, h, chunk, count_active=count_active)
        wp.launch(kp.apply_deltas_kernel, dim=n, inputs=[delta, count], outputs=[x], device=device)
        return x.numpy().astype(np.float64), int(active.numpy()[0])

    want, want_active = run((pt, None), (None, ee))
    got, got_active = run((pt, ee))
    assert want_active > 0 and got_active == want_active
    # a pass that does not count (every pass of a projection but its last) moves the points alike
    quiet, quiet_active = run((pt, ee), count_active=False)
    assert quiet_active == 0
    if wp.get_device(device).is_cpu:
        assert np.array_equal(quiet, got)
    else:
        np.testing.assert_allclose(quiet, got, atol=1e-6)
    assert np.abs(want - points).max() > 1e-3  # the contacts moved the points
    if wp.get_device(device).is_cpu:  # threads in order: the same sums in the same order
        assert np.array_equal(got, want)
    else:  # a GPU's atomics add in any order
        np.testing.assert_allclose(got, want, atol=1e-6)


def test_point_pushed_through_a_triangle_is_separated_by_one_projection(device):
    tri = [0, 1, 2]  # in the plane z = 0, normal +z (counter-clockwise from above)
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.25, 0.25, -0.03]], dtype=float)
    inv_mass = np.array([1.0, 2.0, 0.5, 1.0])
    h = 0.01
    x, active = _project_once(device, points, inv_mass, tri, pt=[(3, 0)], h=h)
    assert active == 1
    n = np.cross(x[1] - x[0], x[2] - x[0])
    n /= np.linalg.norm(n)
    assert (x[3] - x[0]) @ n == pytest.approx(h, abs=1e-3 * h)  # exactly at the thickness, first order
    # momentum is conserved: sum of m dx = 0
    m = 1.0 / inv_mass
    assert np.abs((m[:, None] * (x - points)).sum(0)).max() < 1e-6


def test_crossing_edges_are_separated_by_one_projection(device):
    # edge 1 along x at z = 0; edge 2 along y, pushed from z = +0.02 (its side at the start) to
    # z = -0.01: one projection restores C = h on the original side
    points = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, -0.01], [0, 1, -0.01]], dtype=float)
    edges = [[0, 1], [2, 3]]
    start = points.copy()
    start[2:, 2] = 0.02
    n0 = np.cross(start[1] - start[0], start[3] - start[2])
    sgn = float(np.sign((start[3] - start[0]) @ n0))
    h = 0.005
    x, active = _project_once(device, points, np.ones(4), [0, 1, 2], ee=[(0, 1, sgn)], edges=edges, h=h)
    assert active == 1
    assert _ee_reference(x, sgn, 0.0) == pytest.approx(h, rel=1e-3)
    assert x[2, 2] > x[0, 2]  # edge 2 is back above edge 1


def test_contact_kernels_take_the_counted_contacts_in_chunks(device):
    # a crumpled sheet: 40 point-triangle and 40 edge-edge contacts of random (generic) points,
    # the buffers holding 13 more garbage entries past the count; a thread per 1, 4 or 64
    # slots projects the same contacts (bit for bit on the CPU, whose threads run in order),
    # and the same as buffers holding only the counted ones
    rng = np.random.default_rng(7)
    n = 30
    points = rng.uniform(-0.1, 0.1, (n, 3))
    inv_mass = rng.uniform(0.5, 2.0, n)
    tri = rng.choice(n, (12, 3), replace=True)
    tri = tri[[len(set(t)) == 3 for t in tri]]
    edges = [[a, b] for a, b in rng.choice(n, (20, 2)) if a != b]
    pt_all = [(int(rng.integers(n)), int(rng.integers(len(tri)))) for _ in range(53)]
    pt_all = [(v, t) for v, t in pt_all if v not in tri[t]]
    ee_all = [(int(a), int(b), float(s)) for a, b, s in
              zip(rng.integers(len(edges), size=53), rng.integers(len(edges), size=53), rng.choice([-1.0, 1.0], 53))]
    ee_all = [(a, b, s) for a, b, s in ee_all if not set(edges[a]) & set(edges[b])]
    count = min(len(pt_all), len(ee_all)) - 13
    h = 0.02
    ref, active_ref = _project_once(device, points, inv_mass, tri, pt=pt_all[:count], ee=ee_all[:count], edges=edges,
                                    h=h)
    assert active_ref > count // 2  # most of them are violated: the projection moves points
    assert np.abs(ref - points).max() > 1e-3
    for chunk in (1, 4, 64):
        x, active = _project_once(device, points, inv_mass, tri, pt=pt_all, ee=ee_all, edges=edges, h=h, chunk=chunk,
                                  counted=count)
        assert active == active_ref
        if wp.get_device(device).is_cpu:
            np.testing.assert_array_equal(x, ref)
        else:  # the atomics' order differs between runs on a GPU
            np.testing.assert_allclose(x, ref, atol=1e-6)
    # friction and restitution over the same point-triangle contacts, random velocities
    v0 = rng.normal(size=(n, 3))

    def velocities(pt, counted, chunk):
        arr = lambda a, dt: wp.array(np.asarray(a), dtype=dt, device=device)  # noqa: E731
        v, dv = arr(v0.astype(np.float32), wp.vec3), wp.zeros(n, dtype=wp.vec3, device=device)
        dv_count = wp.zeros(n, dtype=wp.int32, device=device)
        wp.launch(kp.friction_restitution_kernel, dim=-(-len(pt) // chunk),
                  inputs=[arr(points.astype(np.float32), wp.vec3), v, arr(inv_mass.astype(np.float32), wp.float32),
                          arr(np.asarray(tri, dtype=np.int32), wp.int32), arr([counted], wp.int32),
                          arr([p for p, _ in pt], wp.int32), arr([t for _, t in pt], wp.int32),
                          *_contact_scalars(device, n, friction=0.4, restitution=0.3), chunk],
                  outputs=[dv, dv_count], device=device)
        wp.launch(kp.apply_deltas_kernel, dim=n, inputs=[dv, dv_count], outputs=[v], device=device)
        return v.numpy()

    ref_v = velocities(pt_all[:count], count, 1)
    assert np.abs(ref_v - v0).max() > 1e-2
    for chunk in (4, 64):
        got = velocities(pt_all, count, chunk)
        if wp.get_device(device).is_cpu:
            np.testing.assert_array_equal(got, ref_v)
        else:
            np.testing.assert_allclose(got, ref_v, atol=1e-5)


# ---------------------------------------------------------------- detection and the whole solver
from warpskin.collision import CollisionParams  # noqa: E402
from warpskin.metrics import self_intersections  # noqa: E402
from warpskin.model import ModelParams, SkinModelBuilder  # noqa: E402
from warpskin.scene import load_scene  # noqa: E402
from warpskin.run import simulate  # noqa: E402

COARSE = "[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 30\nsegments = 20\n[animation]\nclip = 'flex'\nfps = 30\n"


def _pairs(col):
    """The detected pairs as sets; every pair is listed once."""
    c = col.counts.numpy()
    pt = list(zip(col.pt_vertex.numpy()[: c[0]].tolist(), col.pt_triangle.numpy()[: c[0]].tolist()))
    ee = list(zip(col.ee_a.numpy()[: c[1]].tolist(), col.ee_b.numpy()[: c[1]].tolist()))
    assert len(set(pt)) == len(pt) and len(set(ee)) == len(ee), "a contact pair listed twice"
    return set(pt), set(ee)


def _triangle_pairs(contacts):
    n = int(contacts.counts.numpy()[3])
    pairs = [tuple(p) for p in contacts.tri_pairs.numpy()[:n].tolist()]
    assert len(set(pairs)) == len(pairs), "a triangle pair listed twice"
    return set(pairs)


def test_overflow_grows_and_finds_the_same_pairs(device):
    rig, _, big, a, b = pressed_arm(device, 1 << 15, 1 << 20)
    assert not big.overflowed()
    ref = _pairs(big)
    ref_tri = _triangle_pairs(big)
    assert len(ref[0]) > 10 and len(ref[1]) > 10 and len(ref_tri) > 1000
    _, col, small, a2, b2 = pressed_arm(device, 8, 1 << 20)
    assert small.overflowed()  # the flag, never a silent drop
    while small.overflowed():
        small.grow()
        col.detect(a2.x, b2.x, small)
    assert small.capacity > 8
    assert _pairs(small) == ref
    assert _triangle_pairs(small) == ref_tri
    # the fail-safe's pair list is no contact: one that does not fit raises no flag (the
    # fail-safe does without it), and grows between frames to what the last step listed
    _, col, short, a3, b3 = pressed_arm(device, 1 << 15, 64)
    assert not short.overflowed() and int(short.counts.numpy()[3]) == len(ref_tri)
    assert not short.grow_pairs(64)  # at its limit
    assert short.grow_pairs(1 << 20) and short.pair_capacity >= len(ref_tri)
    col.detect(a3.x, b3.x, short)
    assert _triangle_pairs(short) == ref_tri and _pairs(short) == ref


def test_contact_capacities_must_be_positive_integers(device):
    from warpskin.errors import InputError

    model = SkinModelBuilder(coarse_arm(), ModelParams(volume=False)).finalize(device)
    for bad in ("64", 2.5, True, 0):
        with pytest.raises(InputError, match=re.escape(f"contact capacity must be a positive integer, got {bad!r}")):
            model.contacts(bad)
    for bad in (2.0, -1):
        with pytest.raises(InputError, match=re.escape(f"pair capacity must be a positive integer, got {bad!r}")):
            model.contacts(64, bad)
    c = model.contacts(np.int64(64), 128)
    assert c.capacity == 64 and c.pair_capacity == 128


def test_triangle_pair_list_matches_brute_force(device):
    # the fail-safe's list: every two skin triangles with no shared vertex whose swept boxes
    # are within twice the escape reach of each other on every axis, once, lower index first
    from warpskin.collision import ESCAPE_REACH

    rig, col, contacts, a, b = pressed_arm(device, 1 << 15, 1 << 20)
    tris = rig.triangles
    x0 = a.x.numpy()[: rig.vertex_count].astype(np.float64)[tris]
    x1 = b.x.numpy()[: rig.vertex_count].astype(np.float64)[tris]
    lo = np.minimum(x0.min(axis=1), x1.min(axis=1))
    hi = np.maximum(x0.max(axis=1), x1.max(axis=1))
    r = 2.0 * ESCAPE_REACH * col.radius
    assert 0.0 < r <= col.radius  # (the tree's boxes carry the radius: it returns all of them)
    gap = np.maximum(lo[:, None, :] - hi[None, :, :], lo[None, :, :] - hi[:, None, :]).max(axis=2)  # [T, T]
    shared = (tris[:, None, :, None] == tris[None, :, None, :]).any(axis=(2, 3))
    # the regular procedural mesh repeats its gaps: pairs within a band of the radius (float32
    # boxes against float64 ones) may go either way, every other pair must be decided exactly
    band = 1e-4 * r
    def pairs(mask):
        t, u = np.nonzero(mask & ~shared)
        return {(int(i), int(j)) for i, j in zip(t, u) if i < j}
    must, may = pairs(gap < r - band), pairs(np.abs(gap - r) <= band)
    assert len(must) > 1000
    got = _triangle_pairs(contacts)
    assert must <= got and got <= must | may


def test_detected_point_triangle_pairs_match_brute_force(device):
    # every (vertex, triangle) pair whose predicted point lies within the thickness in front of
    # or behind the triangle, projecting inside it, and from different patches, is found
    rig, col, contacts, a, b = pressed_arm(device, 1 << 15)
    pt, _ = _pairs(contacts)
    x = b.x.numpy()[: rig.vertex_count].astype(np.float64)
    rest = rig.vertices
    tris = rig.triangles
    h, gap = col.thickness, col.rest_gap
    p0, p1, p2 = x[tris[:, 0]], x[tris[:, 1]], x[tris[:, 2]]
    n = np.cross(p1 - p0, p2 - p0)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    def bary(i, t):
        e0, e1, dd = p1[t] - p0[t], p2[t] - p0[t], x[i] - p0[t]
        m = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
        v, w = np.linalg.solve(m, [dd @ e0, dd @ e1])
        return min(v, w, 1 - v - w)

    expected = set()
    for i in range(rig.vertex_count):
        d = np.einsum("tj,tj->t", x[i] - p0, n)
        cand = np.nonzero((d < h * 0.99) & (d > -h * 0.99))[0]
        for t in cand:
            if i in tris[t] or np.linalg.norm(rest[tris[t]] - rest[i], axis=1).min() < gap:
                continue
            if bary(i, t) > 1e-3:  # projects inside
                expected.add((i, int(t)))
    assert len(expected) > 10 and expected <= pt
    # and nothing listed that cannot be a contact: every pair projects inside its triangle and
    # lies in front of it within the search radius, or behind it (crossed or pressed in)
    for i, t in pt:
        assert i not in tris[t] and bary(i, t) > -1e-4
        assert (x[i] - p0[t]) @ n[t] < col.radius * 1.001


@pytest.mark.slow
def test_arm_at_150_degrees_has_no_intersections_where_lbs_has_many(tmp_path, device):
    # the shipped arm scene at its full resolution (2918 vertices, the paper's 2916), with its
    # own solver settings: flexed to 150 degrees (frame 45) and held (to frame 60); every frame
    result = simulate(load_scene("arm"), tmp_path / "arm.usdc", device=device, frames=(0, 60), with_lbs=True,
                      check_intersections=True, progress=False)
    assert result.summary["vertices"] == 2918 and len(result.frames) == 61
    m, s = result.metrics, result.summary
    print(f"intersecting skin triangle pairs per frame: warpskin max {max(m['intersecting_pairs'])}, "
          f"LBS max {max(m['intersecting_pairs_lbs'])}; volume deviation {s['max_volume_deviation']:.2e} "
          f"(LBS {s['max_volume_deviation_lbs']:.2e}); sub-volumes {s['max_subvolume_deviation']:.2e}")
    assert max(m["intersecting_pairs_lbs"]) > 20
    assert max(m["intersecting_pairs"]) == 0  # every exported frame
    assert s["max_volume_deviation"] < 0.009 and s["max_subvolume_deviation"] < s["max_subvolume_deviation_lbs"] / 10
    assert max(m["contacts_point_triangle"]) > 0 and max(m["contacts_edge_edge"]) > 0
    # an independent recount from the written file
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(result.path))
    skin = UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr()
    lbs = UsdGeom.Mesh(prim(stage, "lbs")).GetPointsAttr()
    rig = load_scene("arm").rig()
    for f in range(0, 61, 15):
        assert len(self_intersections(np.array(skin.Get(f), dtype=np.float64), rig.triangles)) == 0
    last = np.array(skin.Get(60), dtype=np.float64)
    # the contact region bulges: around the contact, the upper arm's skin moves out from the
    # upper-arm bone further than LBS puts it (volume pushed out of the pressed patch)
    lbs_last = np.array(lbs.Get(60), dtype=np.float64)
    g = rig.joint_world_transforms("flex", rig.clip("flex").start + 60 / 30)
    axis0, axis1 = g[0, :3, 3], g[1, :3, 3]
    u = (axis1 - axis0) / np.linalg.norm(axis1 - axis0)

    def radius(points):
        d = points - axis0
        return np.linalg.norm(d - np.outer(d @ u, u), axis=1)

    upper = (rig.vertices[:, 0] > 0.12) & (rig.vertices[:, 0] < 0.26)
    gain = radius(last)[upper] - radius(lbs_last)[upper]
    print(f"upper arm: largest outward bulge against LBS {1e3 * gain.max():.1f} mm, largest inward (contact) {1e3 * gain.min():.1f} mm")
    assert gain.min() < -1e-3  # the pressed patch is flattened
    assert gain.max() > 1e-3  # and the flesh around it bulges out


def test_simulate_grows_overflowing_contact_buffers_and_repeats_the_frame(tmp_path, device):
    # the coarse arm pressing to 150 degrees with buffers for 8 candidates: every overflow grows
    # them and repeats the frame from its start (re-capturing the graphs), so the run equals one
    # whose buffers never overflowed (bit for bit on the CPU, where the contact order is fixed)
    text = COARSE + "frames = [36, 46]\n[solver]\niterations = 4\n[collision]\ncapacity = {}\n"
    runs = []
    for cap in (8, 1 << 16):
        p = tmp_path / f"cap{cap}.toml"
        p.write_text(text.format(cap))
        runs.append(simulate(load_scene(p), tmp_path / f"cap{cap}.usdc", device=device, progress=False))
    small, big = runs
    assert small.summary["overflow_retries"] >= 2 and big.summary["overflow_retries"] == 0
    assert small.summary["collision_capacity"] >= 256 and small.summary["graph_capture"]
    stages = [Usd.Stage.Open(str(r.path)) for r in runs]
    pts = [UsdGeom.Mesh(prim(s, "skin")).GetPointsAttr() for s in stages]
    for t in range(11):
        a, b = np.array(pts[0].Get(t)), np.array(pts[1].Get(t))
        if device == "cpu":
            np.testing.assert_array_equal(a, b)
        else:  # atomics order the contacts differently from run to run on a GPU
            np.testing.assert_allclose(a, b, atol=1e-4 * coarse_arm().size())


def test_collision_params_rejected():
    with pytest.raises(Exception, match="thickness must be a positive"):
        CollisionParams(thickness=-1.0).check()
    with pytest.raises(Exception, match="restitution must be in"):
        CollisionParams(restitution=2.0).check()
    with pytest.raises(Exception, match=r"fold_cos must be in \[-1, 1\]"):
        CollisionParams(fold_cos=1.5).check()
    for bad in (-1, 1.5, "4", True):
        with pytest.raises(Exception, match="fail_safe_rounds must be an integer >= 0"):
            CollisionParams(fail_safe_rounds=bad).check()


def _folded_strip(angle_deg: float, *, jitter: float = 0.02, row_shift: float = 0.41):
    """A strip (3 rows of 6 vertices, about unit spacing) folded about its middle row by
    ``angle_deg``. Generic positions: the turned-over row is shifted along the strip by
    ``row_shift`` and every vertex jittered (seeded), so that no vertex projects onto a
    triangle edge or vertex (an exact boundary, decided by float rounding)."""
    rng = np.random.default_rng(7)
    xs = np.arange(6, dtype=np.float64)
    a = np.radians(angle_deg)
    rows = [np.stack([xs, np.full(6, y), np.zeros(6)], 1) for y in (-1.0, 0.0)]
    rows.append(np.stack([xs + row_shift, np.full(6, np.cos(a)), np.full(6, np.sin(a))], 1))  # row 2 turned about y = 0
    x = np.concatenate(rows)
    x[:, :2] += rng.uniform(-jitter, jitter, size=(len(x), 2)) * (np.arange(len(x)) >= 6)[:, None]  # rows 1, 2
    tris = []
    for r in range(2):
        for c in range(5):
            v00, v01, v10, v11 = r * 6 + c, r * 6 + c + 1, (r + 1) * 6 + c, (r + 1) * 6 + c + 1
            tris += [[v00, v01, v11], [v00, v11, v10]]
    return x, np.array(tris)


def _no_filter(n: int):
    """A collision filter that filters nothing (no rigid bone, one group), on the scoped device."""
    f = k.CollisionFilter()
    f.rigid_bone = wp.full(n, -1, dtype=wp.int32)
    f.group = wp.zeros(n, dtype=wp.int32)
    f.group_pairs = wp.zeros((1, 1), dtype=wp.int32)
    f.fail_safe_pairs = wp.zeros((1, 1), dtype=wp.int32)
    return f


def _detect_pt(x, tris, fold_cos, h, radius, device):
    n = len(x)
    rest = np.stack([x[:, 0], np.repeat([-1.0, 0.0, 1.0], 6), np.zeros(n)], 1)  # the flat strip
    with wp.ScopedDevice(device):
        xw = wp.array(x.astype(np.float32), dtype=wp.vec3)
        tw = wp.array(tris.astype(np.int32), dtype=wp.int32)
        lo = wp.zeros(len(tris), dtype=wp.vec3)
        hi = wp.zeros(len(tris), dtype=wp.vec3)
        wp.launch(kd.triangle_bounds_kernel, dim=len(tris), inputs=[xw, xw, tw, wp.array([radius], dtype=wp.float32),
                                                                  wp.zeros(n, dtype=wp.int32)], outputs=[lo, hi])
        bvh = wp.Bvh(lo, hi)
        vn = wp.zeros(n, dtype=wp.vec3)
        wp.launch(kd.vertex_normals_kernel, dim=len(tris), inputs=[xw, tw], outputs=[vn])
        count = wp.zeros(1, dtype=wp.int32)
        pv = wp.zeros(256, dtype=wp.int32)
        pt = wp.zeros(256, dtype=wp.int32)
        wp.launch(kd.detect_point_triangle_kernel, dim=n,
                  inputs=[bvh.id, xw, xw, tw, _no_filter(n), wp.array(rest.astype(np.float32), dtype=wp.vec3),
                          100.0, vn, fold_cos, h, radius, 256],
                  outputs=[count, pv, pt, wp.zeros(1, dtype=wp.int32), wp.zeros(n, dtype=wp.int32)])
        c = int(count.numpy()[0])
        return set(zip(pv.numpy()[:c].tolist(), pt.numpy()[:c].tolist()))


def _fold_reference(x, tris, fold_cos, h, radius):
    """Brute force: (vertex, triangle) pairs of a patch that face each other across a fold, and
    the smallest relative margin of any tested quantity to its threshold (barycentric
    coordinates to 0, the distance to -h and to the search radius, the normals' cosine to
    ``fold_cos``), so a test can check that no pair sits on a boundary."""
    tn = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
    vn = np.zeros_like(x)
    for t, f in enumerate(tris):
        vn[f] += tn[t]
    out = set()
    margin = np.inf
    for i in range(len(x)):
        for t, f in enumerate(tris):
            if i in f:
                continue
            n = tn[t] / np.linalg.norm(tn[t])
            d = (x[i] - x[f[0]]) @ n
            cos = vn[i] @ n / np.linalg.norm(vn[i])
            e0, e1, dd = x[f[1]] - x[f[0]], x[f[2]] - x[f[0]], x[i] - x[f[0]]
            m = np.array([[e0 @ e0, e0 @ e1], [e0 @ e1, e1 @ e1]])
            v, w = np.linalg.solve(m, [dd @ e0, dd @ e1])
            bary = min(v, w, 1 - v - w)
            near = -h < d < radius
            if near and cos < fold_cos:
                margin = min(margin, abs(bary))
            if bary >= 0 and cos < fold_cos:
                margin = min(margin, abs(d + h) / h, abs(d - radius) / radius)
            if near and bary >= 0:
                margin = min(margin, abs(cos - fold_cos))
            if near and cos < fold_cos and bary >= 0:
                out.add((i, t))
    return out, margin


def _edge_pairs_detected(points, tris, x_tri, device, h=0.1, radius=0.3):
    """Point-triangle detection of ``points`` [P, 3] against the triangles ``x_tri`` [3T, 3]
    (``tris`` into them), all in different patches: the detected (point, triangle) pairs."""
    x = np.vstack([x_tri, points]).astype(np.float32)
    n, n_tri = len(x), len(x_tri)
    with wp.ScopedDevice(device):
        xw = wp.array(x, dtype=wp.vec3)
        tw = wp.array(tris.astype(np.int32), dtype=wp.int32)
        lo, hi = wp.zeros(len(tris), dtype=wp.vec3), wp.zeros(len(tris), dtype=wp.vec3)
        wp.launch(kd.triangle_bounds_kernel, dim=len(tris), inputs=[xw, xw, tw, wp.array([radius], dtype=wp.float32),
                                                                  wp.zeros(n, dtype=wp.int32)], outputs=[lo, hi])
        bvh = wp.Bvh(lo, hi)
        cap = 4 * len(points) * len(tris)
        count, pv, pt = wp.zeros(1, dtype=wp.int32), wp.zeros(cap, dtype=wp.int32), wp.zeros(cap, dtype=wp.int32)
        wp.launch(kd.detect_point_triangle_kernel, dim=n,
                  inputs=[bvh.id, xw, xw, tw, _no_filter(n), xw, 0.0, wp.zeros(n, dtype=wp.vec3), 0.0, h,
                          radius, cap],
                  outputs=[count, pv, pt, wp.zeros(1, dtype=wp.int32), wp.zeros(n, dtype=wp.int32)])
        c = int(count.numpy()[0])
    return {(int(i) - n_tri, int(t)) for i, t in zip(pv.numpy()[:c], pt.numpy()[:c]) if i >= n_tri}


def test_point_over_a_shared_edge_collides_with_one_of_its_triangles(device):
    # an exact boundary on purpose: a point straight above the edge two triangles share has
    # barycentric coordinate 0 in both, and float32 rounding decides the sign; it must collide
    # with at least one of them (it used to be missed by both in 1 case of 9), while points
    # clearly inside one triangle (1e-3 of its size from the edge) collide with that one only
    rng = np.random.default_rng(11)
    for trial in range(60):
        a, b, c = rng.normal(size=(3, 3))
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n)
        m = 0.5 * (a + b)
        d = m - (c - m) + 0.2 * (b - a)  # the other side of edge ab, in the plane
        x_tri = np.stack([a, b, c, d]).astype(np.float32).astype(np.float64)
        tris = np.array([[0, 1, 2], [1, 0, 3]])  # both facing n
        s = rng.uniform(0.2, 0.8, size=8)
        lift = rng.uniform(0.01, 0.08, size=8)[:, None] * n
        on_edge = x_tri[0] + s[:, None] * (x_tri[1] - x_tri[0]) + lift
        toward = (x_tri[2] - m) / np.linalg.norm(x_tri[2] - m)  # into triangle 0
        size = np.linalg.norm(x_tri[1] - x_tri[0])
        inside0 = on_edge + 1e-3 * size * toward
        inside1 = on_edge - 1e-3 * size * toward
        got = _edge_pairs_detected(np.vstack([on_edge, inside0, inside1]), tris, x_tri, device)
        for i in range(8):
            assert {t for p, t in got if p == i}, f"trial {trial}: a point over the shared edge collided with neither triangle"
            assert {t for p, t in got if p == 8 + i} == {0}
            assert {t for p, t in got if p == 16 + i} == {1}


def test_folded_patch_pairs_collide_by_proximity(device):
    # one surface patch (every vertex within the rest gap of every other) folded over by 170
    # degrees: the turned-over row faces the first band 0.17 above it; those pairs must become
    # contacts (brute-force reference), while the flat strip and the switched-off rule give none
    h, radius = 0.2, 0.6
    x, tris = _folded_strip(170.0)
    got = _detect_pt(x, tris, 0.0, h, radius, device)
    ref, margin = _fold_reference(x, tris, 0.0, h, radius)
    assert margin > 1e-3, "a reference pair sits on a boundary: the test would depend on rounding"
    assert len(ref) >= 5 and got == ref
    # the turned-over row against the first band, and the first row against the turned-over band
    assert all((i >= 12 and tris[t].max() < 12) or (i < 6 and tris[t].min() >= 6) for i, t in got)
    assert _detect_pt(x, tris, -1.0, h, radius, device) == set()  # fold rule off: patch pairs only by crossing
    flat, _ = _folded_strip(0.0)
    assert _detect_pt(flat, tris, 0.0, h, radius, device) == set()
    # a gentle bend (60 degrees) is not a fold
    bent, _ = _folded_strip(60.0)
    assert _detect_pt(bent, tris, 0.0, h, radius, device) == set()


def test_bvh_rebuilt_once_the_skin_has_deformed_and_finds_the_same_pairs(device):
    # the tree is built on the straight arm; at 150 degrees the forearm has swung ~0.25 m (more
    # than 10 % of the arm's diagonal): maybe_rebuild rebuilds it, detection finds the same pairs
    rig, col, contacts, a, b = pressed_arm(device, 1 << 15)
    before = _pairs(contacts)
    skin = b.x.numpy()[: rig.vertex_count]
    assert col.maybe_rebuild(skin) and col.rebuilds == 1
    col.detect(a.x, b.x, contacts)
    assert _pairs(contacts) == before and len(before[0]) > 10
    assert not col.maybe_rebuild(skin + 0.01)  # a translation is no deformation
    assert col.rebuilds == 1


def test_preroll_reaches_a_self_intersecting_first_pose_by_collision(tmp_path, device):
    # the coarse arm's LBS at 150 degrees passes through itself; started there, the skin keeps
    # part of it; a pre-roll from the bind pose (straight, clean) reaches the pose by collision
    p = tmp_path / "arm.toml"
    # the arm scene's cap (8 %): the crease skin kept out of the collapse lies farther than the
    # default 5 % from LBS
    p.write_text(COARSE + "frames = [45, 46]\n[solver]\niterations = 10\ntether_max = 0.08\n")
    scene = load_scene(p)
    kw = dict(device=device, with_lbs=True, check_intersections=True, progress=False)
    cold = simulate(scene, tmp_path / "cold.usdc", **kw)
    warm = simulate(scene, tmp_path / "warm.usdc", preroll=0.5, **kw)
    assert cold.metrics["intersecting_pairs_lbs"][0] > 20
    assert cold.metrics["intersecting_pairs"][-1] > 0  # started there, it keeps part of them
    assert warm.summary["preroll_steps"] == 100
    assert max(warm.metrics["intersecting_pairs"]) == 0
    with pytest.raises(Exception, match="preroll must be"):
        simulate(scene, tmp_path / "bad.usdc", preroll=-1.0, **kw)


@pytest.mark.slow
def test_cesium_man_walk_starts_clean_after_the_preroll(tmp_path, assets, device):
    # CesiumMan's first walk pose passes the skin through itself under LBS; the scene's 0.5 s
    # pre-roll from the (clean) bind pose reaches it by collision. Frames 7-12 bend the knees:
    # the contact constraints alone kept 8 pairs there (at the back of the knees), which the
    # fail-safe removes, carrying the skin along (the skin stays within 5 % of the diagonal
    # of LBS, and no sub-volume worse than LBS's)
    scene = load_scene("cesium_man")
    rig = scene.rig()
    assert scene.preroll == 0.5 and len(self_intersections(rig.vertices, rig.triangles)) == 0
    result = simulate(scene, tmp_path / "walk.usdc", device=device, frames=(1, 13), with_lbs=True,
                      check_intersections=True, progress=False)
    m, s = result.metrics, result.summary
    print(f"CesiumMan frames 1-13: intersecting pairs {m['intersecting_pairs']}, LBS {m['intersecting_pairs_lbs']}, "
          f"fail-safe pairs per frame {m['fail_safe_pairs']}, offset {max(m['max_offset_from_lbs']) / s['body_diagonal_m']:.3f}")
    assert min(m["intersecting_pairs_lbs"]) > 40
    assert max(m["intersecting_pairs"]) == 0
    assert sum(m["fail_safe_pairs"]) > 0  # it acted in the written frames (the knee bend)
    assert max(m["max_offset_from_lbs"]) <= 0.05 * s["body_diagonal_m"]
    rest = np.array(m["subvolume_rest"])
    sub = np.abs(np.array(m["subvolume"]) / rest - 1).max(axis=1)
    sub_lbs = np.abs(np.array(m["subvolume_lbs"]) / rest - 1).max(axis=1)
    assert np.all(sub <= sub_lbs + 1e-3)


def test_preroll_from_a_self_intersecting_bind_pose_warns(tmp_path):
    # a bind pose that passes through itself cannot be cleaned by a pre-roll that starts there:
    # the coarse arm modelled in its LBS pose at 0.8 s (the elbow folded through itself)
    from dataclasses import replace

    from warpskin.transforms import linear_blend_skin

    arm = coarse_arm()
    folded = linear_blend_skin(arm.vertices, arm.joint_indices, arm.joint_weights, arm.skinning_matrices("flex", 0.8))
    assert len(self_intersections(folded, arm.triangles)) > 0
    p = tmp_path / "thin.toml"  # thin layers, so that they do not fold over in the folded pose
    p.write_text(COARSE + "[layers]\nfat = 0.02\nmuscle = 0.05\nbone = 0.1\n")
    scene = load_scene(p)
    scene._rig = replace(arm, vertices=folded)
    with pytest.warns(UserWarning, match=r"bind pose itself has \d+ intersecting"):
        simulate(scene, tmp_path / "w.usdc", device="cpu", frames=(0, 0), preroll=0.01, progress=False)


@pytest.mark.slow
def test_detected_edge_edge_pairs_match_brute_force(device):
    # every pair of skin edges (no shared vertex, from different patches, not all four vertices
    # rigid on one bone, not coplanar at the start) whose predicted segments come nearer than the
    # search radius is listed, once. The distance by sampling both segments (independent of the
    # kernel's closed form; sampling only overestimates it, so every expected pair is real)
    from scipy.spatial import cKDTree

    from warpskin.collision import skin_edges

    rig, col, contacts, a, b = pressed_arm(device, 1 << 15)
    _, ee = _pairs(contacts)
    edges, _ = skin_edges(rig.triangles)
    x = b.x.numpy()[: rig.vertex_count].astype(np.float64)
    x_old = a.x.numpy()[: rig.vertex_count].astype(np.float64)
    rest = rig.vertices
    w = rig.joint_weights
    best = np.argmax(w, axis=1)
    rigid = np.where(w[np.arange(len(w)), best] >= 0.999, rig.joint_indices[np.arange(len(w)), best], -1)
    s = np.linspace(0.0, 1.0, 21)
    p, q = x[edges[:, 0]], x[edges[:, 1]]
    half = 0.5 * np.linalg.norm(q - p, axis=1)
    cand = np.sort(cKDTree(0.5 * (p + q)).query_pairs(2 * half.max() + col.radius, output_type="ndarray"), axis=1)
    e, f = cand[:, 0], cand[:, 1]
    i1, i2, i3, i4 = edges[e, 0], edges[e, 1], edges[f, 0], edges[f, 1]
    keep = (i1 != i3) & (i1 != i4) & (i2 != i3) & (i2 != i4)
    # one patch: by crossing or fold only, not by distance
    gap = np.min([np.linalg.norm(rest[m] - rest[n], axis=1) for m, n in ((i1, i3), (i1, i4), (i2, i3), (i2, i4))], axis=0)
    keep &= gap >= col.rest_gap
    keep &= ~((rigid[i1] >= 0) & (rigid[i1] == rigid[i2]) & (rigid[i2] == rigid[i3]) & (rigid[i3] == rigid[i4]))
    # coplanar at the start of the step (no side): left to the point-triangle contacts
    d1, d2, d3 = x_old[i2] - x_old[i1], x_old[i4] - x_old[i3], x_old[i4] - x_old[i1]
    vol = np.abs(np.einsum("ij,ij->i", d3, np.cross(d1, d2)))
    keep &= vol >= 1e-9 * np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1) * np.linalg.norm(d3, axis=1)
    e, f = e[keep], f[keep]
    dist = np.empty(len(e))
    for at in range(0, len(e), 256):  # blocks of pairs that stay in the cache
        eb, fb = e[at:at + 256], f[at:at + 256]
        u = p[eb][:, None] + s[None, :, None] * (q[eb] - p[eb])[:, None]  # [B, S, 3]
        v = p[fb][:, None] + s[None, :, None] * (q[fb] - p[fb])[:, None]
        dist[at:at + 256] = np.sqrt(((u[:, :, None] - v[:, None]) ** 2).sum(axis=3)).min(axis=(1, 2))
    expected = set(zip(e[dist < 0.98 * col.radius].tolist(), f[dist < 0.98 * col.radius].tolist()))
    assert len(expected) > 50
    assert expected <= ee


def test_groups_that_never_collide_are_filtered_and_the_others_are_not(device):
    # a point 0.05 in front of a triangle (within the search radius, inside it in projection):
    # a contact candidate, unless its group and the triangle's never collide; a triangle with one
    # corner in such a group (a cap's triangle at its piece's rim) is filtered too
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.0], [0.37, 0.33, 0.05]])
    tris = np.array([[0, 1, 2]])
    radius, h = 0.3, 0.1
    with wp.ScopedDevice(device):
        xw = wp.array(x.astype(np.float32), dtype=wp.vec3)
        tw = wp.array(tris.astype(np.int32), dtype=wp.int32)
        lo, hi = wp.zeros(1, dtype=wp.vec3), wp.zeros(1, dtype=wp.vec3)
        wp.launch(kd.triangle_bounds_kernel, dim=1, inputs=[xw, xw, tw, wp.array([radius], dtype=wp.float32),
                                                           wp.zeros(4, dtype=wp.int32)], outputs=[lo, hi])
        bvh = wp.Bvh(lo, hi)

        def found(group, pairs):
            f = k.CollisionFilter()
            f.rigid_bone = wp.full(4, -1, dtype=wp.int32)
            f.group = wp.array(np.asarray(group, dtype=np.int32), dtype=wp.int32)
            f.group_pairs = wp.array(np.asarray(pairs, dtype=np.int32), dtype=wp.int32)
            f.fail_safe_pairs = wp.zeros((1, 1), dtype=wp.int32)
            count = wp.zeros(1, dtype=wp.int32)
            pv, pt = wp.zeros(8, dtype=wp.int32), wp.zeros(8, dtype=wp.int32)
            wp.launch(kd.detect_point_triangle_kernel, dim=4,
                      inputs=[bvh.id, xw, xw, tw, f, xw, 0.0, wp.zeros(4, dtype=wp.vec3), 0.0, h, radius, 8],
                      outputs=[count, pv, pt, wp.zeros(1, dtype=wp.int32), wp.zeros(4, dtype=wp.int32)])
            return int(count.numpy()[0])

        apart = [[0, 1, 0], [1, 0, 1], [0, 1, 0]]
        assert found([0, 0, 0, 0], [[0]]) == 1  # one group: a contact
        assert found([0, 0, 0, 2], apart) == 1  # groups 0 and 2 may collide
        assert found([0, 0, 0, 1], apart) == 0  # groups 0 and 1 never do
        assert found([0, 1, 0, 2], apart) == 0  # one corner in a group the point's never meets
        assert found([2, 2, 2, 2], apart) == 1  # a group with itself always may

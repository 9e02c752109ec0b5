"""The pair-by-pair crossing repair (warpskin.guard.Untangle, warpskin.kernels.untangle): what LBS
drives through itself is separated, each side where the reference pose had it, by about the
depth of the crossing and only near it, rigid pieces kept still, crossings present at rest left.
Judged by the independent references of oracles.py (separating-axis pair counts over every pair,
plain-loop strain and flips) and closed forms, on spheres in generic positions."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from characters import generic_sphere, random_rotation
from oracles import intersecting_pair_list_brute_force, intersecting_pairs_brute_force, strain_and_flips
from warpskin.guard import GuardParams, SurfaceGuard, Untangle
from warpskin.kernels import untangle as k
from warpskin.quality import WrittenMesh


_rotation = random_rotation


def _sphere(centre, radius: float, seed: int):
    return generic_sphere(centre, radius, seed, jitter=0.005)  # generic: no symmetry, no ties


def _two(a, b):
    (pa, ta), (pb, tb) = a, b
    return np.concatenate([pa, pb]), np.concatenate([ta, tb + len(pa)]), len(pa)


def _untangle(rest, tris, groups=None, **kw):
    mesh = WrittenMesh("m", tris, rest)
    return Untangle(SurfaceGuard(mesh, GuardParams()), groups, **kw)


def _distance_to_points(p: np.ndarray, points: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    return cKDTree(points).query(p)[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_a_sphere_driven_into_another_is_pushed_out_by_about_the_depth_and_only_there(seed):
    r = 0.1
    rest, tris, n = _two(_sphere((0, 0, 0), r, seed), _sphere((0.26, 0.0, 0.0), r, seed + 10))
    # LBS drives the second into the first by 0.012 along x (what the guard leaves: LBS has it too)
    depth = 0.012
    lbs = rest.copy()
    lbs[n:, 0] -= 0.26 - (2 * r - depth)
    assert intersecting_pairs_brute_force(lbs, tris) > 0
    u = _untangle(rest, tris, rounds=16, max_step=0.005)
    out = u.apply(lbs, lbs)
    assert intersecting_pairs_brute_force(out, tris) == 0
    assert u.stats["before"] > 0 and u.stats["after"] == 0
    strained, _, flipped = strain_and_flips(rest, out, lbs, tris)
    assert strained == 0.0 and flipped == 0.0
    move = out - lbs
    # apart along x: the first sphere back, the second forward, each by part of the depth
    assert move[:n, 0].min() < -0.2 * depth and move[n:, 0].max() > 0.2 * depth
    assert move[:n, 0].max() <= 1e-7 and move[n:, 0].min() >= -1e-7
    # by about the depth, not more: no point moves farther than twice it
    assert np.linalg.norm(move, axis=1).max() < 2.0 * depth
    # only near the contact: points farther than 4 depths and an edge from the other sphere stay
    edge = np.linalg.norm(rest[tris[:, 0]] - rest[tris[:, 1]], axis=1).max()
    far = np.concatenate([_distance_to_points(lbs[:n], lbs[n:]), _distance_to_points(lbs[n:], lbs[:n])]) > 4 * depth + edge
    assert far.sum() > 0.5 * len(lbs)  # most of both spheres
    assert np.array_equal(out[far], np.asarray(lbs[far], np.float32).astype(np.float64))


def test_a_rigid_piece_keeps_still_and_the_other_gives_way():
    r = 0.1
    rest, tris, n = _two(_sphere((0, 0, 0), r, 3), _sphere((0.25, 0.02, 0.0), r, 4))
    lbs = rest.copy()
    lbs[n:, 0] -= 0.25 - (2 * r - 0.01)
    groups = np.full(len(rest), -1)
    groups[n:] = 0  # the second sphere moves as a whole (a fist)
    u = _untangle(rest, tris, groups, rounds=16, max_step=0.005)
    out = u.apply(lbs, lbs)
    assert intersecting_pairs_brute_force(out, tris) == 0
    assert np.array_equal(out[n:], np.asarray(lbs[n:], np.float32).astype(np.float64))
    assert (out[:n, 0] - lbs[:n, 0]).min() < -0.005


def test_each_side_is_where_the_reference_pose_had_it():
    # a sheet hanging in front of a ball (a skirt before a thigh): the same outward direction,
    # not facing each other; the ball moves forward through it
    ball, bt = _sphere((0, 0, 0), 0.1, 5)
    m = 17
    y, z = np.meshgrid(np.linspace(-0.15, 0.15, m), np.linspace(-0.15, 0.15, m), indexing="ij")
    sv = np.stack([np.full(y.size, 0.125), y.ravel(), z.ravel()], axis=1)
    sv += np.random.default_rng(6).uniform(-2e-4, 2e-4, size=sv.shape) + np.array([0.0, 0.003, -0.002])
    q = (np.arange(m - 1)[:, None] * m + np.arange(m - 1)[None, :]).ravel()
    st = np.concatenate([np.stack([q, q + m, q + m + 1], 1), np.stack([q, q + m + 1, q + 1], 1)])
    st = st if np.cross(sv[st[0, 1]] - sv[st[0, 0]], sv[st[0, 2]] - sv[st[0, 0]])[0] > 0 else st[:, ::-1]
    rest, tris, n = _two((ball, bt), (sv, st))
    lbs = rest.copy()
    lbs[:n, 0] += 0.032  # the ball's front at about 0.132: through the sheet at 0.125
    before = intersecting_pairs_brute_force(lbs, tris)
    assert before > 0
    u = _untangle(rest, tris, rounds=24, max_step=0.004)
    out = u.apply(lbs, lbs)
    after = intersecting_pairs_brute_force(out, tris)
    assert after < 0.25 * before
    move = out - lbs
    # the sheet goes forward, in front of the ball as at rest, the ball back: never the sheet behind
    assert move[n:, 0].max() > 0.002 and move[n:, 0].min() >= -1e-7
    assert move[:n, 0].max() <= 1e-7
    front = out[:n, 0].max()
    hit = np.abs(out[n:, 1]) + np.abs(out[n:, 2]) < 0.03  # the sheet's points before the ball's front
    assert out[n:][hit, 0].min() > front - 0.004


def test_nothing_crossing_is_returned_itself():
    rest, tris, n = _two(_sphere((0, 0, 0), 0.1, 7), _sphere((0.3, 0, 0), 0.1, 8))
    lbs = rest + np.array([0.01, 0.02, -0.03])
    u = _untangle(rest, tris)
    assert u.apply(lbs, lbs) is lbs
    assert u.stats == {"before": 0, "after": 0, "rounds": 0, "seam": 0, "press": 0}


@pytest.mark.parametrize("degrees", [20.0, 35.0])
def test_pieces_that_cross_at_rest_are_left_to_slide(degrees):
    # a ball joint in a socket's end, crossing by design at rest; the ball turns about its centre
    # (a generic axis) and its crossing slides over it
    rest, tris, n = _two(_sphere((0, 0, 0), 0.1, 9), _sphere((0.15, 0.01, 0), 0.08, 10))
    assert intersecting_pairs_brute_force(rest, tris) > 0
    axis = np.array([0.3, 0.8, 0.52])
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
    lbs = rest.copy()
    c = np.array([0.15, 0.01, 0])
    lbs[n:] = (rest[n:] - c) @ turn.T + c
    assert intersecting_pairs_brute_force(lbs, tris) > 0
    u = _untangle(rest, tris)
    assert u.apply(lbs, lbs) is lbs
    assert u.stats["before"] == 0


def _turn(axis, degrees: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    a = np.radians(degrees)
    kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def _beyond_rest(x, rest, tris, n_tris) -> int:
    """Pairs beyond the rest pose's per pair of pieces (the report's measure), by brute force:
    two pieces, the first ``n_tris`` triangles the first's."""
    def counts(p):
        pairs = intersecting_pair_list_brute_force(p, tris)
        a, b = pairs[:, 0] >= n_tris, pairs[:, 1] >= n_tris
        return np.bincount(a.astype(int) + b.astype(int), minlength=3)  # (0, 0), (0, 1), (1, 1)

    return int(np.maximum(counts(x) - counts(rest), 0).sum())


@pytest.mark.parametrize("rigid", [False, True])
def test_a_joint_crossing_at_rest_that_wobbles_slides_as_lbs_slides_it(rigid):
    # a ball in a socket's end, crossing by design at rest; LBS turns the socket 25 degrees about
    # its centre. The written socket ripples where it passes through the ball (a soft tube's
    # end wobbling in its joint), crossing it more than LBS does. Rigid: the ball is a rigid
    # group written moved 4 degrees off its LBS, and the socket's ripple follows it there.
    ball, bt = _sphere((0, 0, 0), 0.1, 9)
    rest, tris, n = _two((ball, bt), _sphere((0.15, 0.01, 0), 0.08, 10))
    c = np.array([0.15, 0.01, 0])
    lbs = rest.copy()
    lbs[n:] = (rest[n:] - c) @ _turn((0.3, 0.8, 0.52), 25.0).T + c
    x = lbs.copy()
    groups = None
    if rigid:
        groups = np.full(len(rest), -1)
        groups[:n] = 0
        m = _turn((0.7, -0.2, 0.4), 4.0)
        x[:n] = lbs[:n] @ m.T
    reference = x[:n]  # the ball as written
    u_dir = x[n:] - c
    u_dir /= np.linalg.norm(u_dir, axis=1)[:, None]
    gap = np.linalg.norm(x[n:], axis=1) - np.linalg.norm(reference, axis=1).mean()
    band = np.abs(gap) < 0.03
    angle = np.arctan2(u_dir[:, 2], u_dir[:, 1])
    ripple = np.where(band, 0.012 * np.sin(7 * angle) * (1 - np.abs(gap) / 0.03), 0.0)
    x[n:] += ripple[:, None] * u_dir
    if rigid:  # where the socket would be, carried with the ball
        lbs_carried = lbs @ m.T
        lbs_reference = np.concatenate([x[:n], lbs_carried[n:]])
    else:
        lbs_reference = lbs
    nt = len(bt)
    limit = _beyond_rest(lbs_reference, rest, tris, nt)
    assert _beyond_rest(x, rest, tris, nt) > limit + 5  # the ripple crosses more
    u = _untangle(rest, tris, groups)
    out = u.apply(x, lbs)
    assert _beyond_rest(out, rest, tris, nt) <= max(limit, _beyond_rest(lbs, rest, tris, nt))
    assert u.stats["seam"] > 0 and u.stats["before"] == 0  # nothing repaired by the rounds
    # the ball as it was (at its LBS, or rigid); away from the seam the socket as it was
    as_input = np.asarray(x, np.float32).astype(np.float64)
    assert np.array_equal(out[:n], as_input[:n])
    far = np.abs(gap) > 0.09
    assert far.sum() > 0.25 * (len(rest) - n)
    assert np.array_equal(out[n:][far], as_input[n:][far])
    # where it moved, toward where LBS slides it (carried with the ball where that is rigid)
    moved = np.linalg.norm(out - as_input, axis=1) > 1e-6
    assert moved.any()
    target = lbs_carried if rigid else lbs
    before = np.linalg.norm(x[moved] - target[moved], axis=1)
    after = np.linalg.norm(out[moved] - target[moved], axis=1)
    assert np.all(after <= before + 1e-6) and after.sum() < 0.5 * before.sum()
    # and nothing strained or turned over that the input was not
    s_in, _, f_in = strain_and_flips(rest, x, lbs, tris)
    s_out, _, f_out = strain_and_flips(rest, out, lbs, tris)
    assert s_out <= s_in and f_out <= f_in


def test_the_repair_off_with_no_rounds():
    rest, tris, n = _two(_sphere((0, 0, 0), 0.1, 0), _sphere((0.26, 0.0, 0.0), 0.1, 10))
    lbs = rest.copy()
    lbs[n:, 0] -= 0.07
    u = _untangle(rest, tris, rounds=0)
    assert u.apply(lbs, lbs) is lbs


@wp.kernel
def _closest_kernel(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = k.from_a_to_b(a[3 * i], a[3 * i + 1], a[3 * i + 2], b[3 * i], b[3 * i + 1], b[3 * i + 2])


def test_closest_points_of_two_triangles_match_dense_sampling(device):
    rng = np.random.default_rng(12)
    count = 40
    a = rng.normal(size=(count, 3, 3)) * 0.5
    b = rng.normal(size=(count, 3, 3)) * 0.5 + rng.normal(size=(count, 1, 3)) * 1.5
    out = wp.zeros(count, dtype=wp.vec3, device=device)
    wp.launch(_closest_kernel, dim=count, inputs=[wp.array(a.reshape(-1, 3), dtype=wp.vec3, device=device),
                                                  wp.array(b.reshape(-1, 3), dtype=wp.vec3, device=device)],
              outputs=[out], device=device)
    d = np.linalg.norm(out.numpy(), axis=1)
    # the reference: the least distance between dense barycentric samples of the two
    m = 60
    u, v = np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m))
    keep = u + v <= 1.0
    bary = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], axis=1)
    from scipy.spatial import cKDTree

    for i in range(count):
        pa, pb = bary @ a[i], bary @ b[i]
        ref = cKDTree(pb).query(pa)[0].min()
        spacing = max(np.ptp(a[i], axis=0).max(), np.ptp(b[i], axis=0).max()) / (m - 1)
        if ref < 2 * spacing:
            continue  # crossing or nearly: the samples cannot tell the distance
        assert d[i] <= ref + 1e-5
        assert d[i] >= ref - 2 * spacing


@pytest.mark.parametrize("mobile_a, size_b", [(1.0, 1.0), (0.0, 1.0), (1.0, 5.0)])
def test_one_crossing_pair_is_pushed_apart_by_the_depth_past_the_separating_plane(device, mobile_a, size_b):
    # A in the plane z = 0 (normal +z); B a small tilted triangle through it, above A in the
    # reference pose: B belongs in front of A, A behind B
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.03, 0.0], [0.02, 1.0, 0.0]])
    b = np.array([[0.2, 0.2, -0.03], [0.45, 0.25, 0.05], [0.25, 0.43, 0.06]])
    x = np.concatenate([a, b])
    ref = x + np.array([[0, 0, 0]] * 3 + [[0, 0, 0.3]] * 3)
    gap, max_step = 1e-3, 1.0
    tris = np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int32)
    arrays = dict(x=wp.array(x, dtype=wp.vec3, device=device), ref=wp.array(ref, dtype=wp.vec3, device=device),
                  tri=wp.array(tris, dtype=wp.vec3i, device=device),
                  pairs=wp.array(np.array([[0, 1]], np.int32), dtype=wp.vec2i, device=device),
                  mobility=wp.array(np.array([mobile_a] * 3 + [1.0] * 3, np.float32), dtype=float, device=device),
                  size=wp.array(np.array([1.0, size_b], np.float32), dtype=float, device=device))
    push = wp.zeros(6, dtype=wp.vec3, device=device)
    count = wp.zeros(6, dtype=float, device=device)
    wp.launch(k.separate_pairs_kernel, dim=1, inputs=[*arrays.values(), gap, max_step], outputs=[push, count],
              device=device)
    p = push.numpy()
    assert np.array_equal(count.numpy(), np.ones(6))
    nb = np.cross(b[1] - b[0], b[2] - b[0])
    nb /= np.linalg.norm(nb)
    depth_b = 0.03  # B's lowest corner below A's plane
    depth_a = max(0.0, np.max(((a - b[0]) @ nb)))  # A belongs behind B's plane: its corners in front
    share_a = mobile_a / (mobile_a + 1.0)
    if size_b > 2.0:  # B's piece is the larger: its plane separates them, A goes behind it
        step = depth_a + gap
        np.testing.assert_allclose(p[:3], np.tile(-nb * step * share_a, (3, 1)), atol=1e-6)
        np.testing.assert_allclose(p[3:], np.tile(nb * step * (1 - share_a), (3, 1)), atol=1e-6)
    else:  # the shallower plane, A's: B goes up out of it, A down
        assert depth_b < depth_a
        step = depth_b + gap
        np.testing.assert_allclose(p[:3], np.tile([0, 0, -step * share_a], (3, 1)), atol=1e-6)
        np.testing.assert_allclose(p[3:], np.tile([0, 0, step * (1 - share_a)], (3, 1)), atol=1e-6)


def _hull(seed: int, count: int = 60):
    """A generic convex polyhedron (the hull of random points on an ellipsoid: every one a
    vertex), outward-wound: ``(points, triangles, equations)``, ``equations`` its facets'
    planes ``n . x + d <= 0`` inside."""
    from scipy.spatial import ConvexHull

    rng = np.random.default_rng(seed)
    p = rng.normal(size=(count, 3))
    p = p / np.linalg.norm(p, axis=1)[:, None] * np.array([0.1, 0.07, 0.05])
    h = ConvexHull(p)
    used = np.unique(h.simplices)
    remap = np.full(count, -1)
    remap[used] = np.arange(used.size)
    tris = remap[h.simplices]
    pts = p[used]
    centre = pts.mean(axis=0)
    for i, t in enumerate(tris):  # outward winding
        if np.dot(np.cross(pts[t[1]] - pts[t[0]], pts[t[2]] - pts[t[0]]), pts[t[0]] - centre) < 0:
            tris[i] = t[::-1]
    return pts, tris, h.equations


def _mesh(pts, tris, device, winding=False):
    return wp.Mesh(points=wp.array(pts, dtype=wp.vec3, device=device),
                   indices=wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32, device=device),
                   support_winding_number=winding)


def test_the_inside_test_and_nearest_point_of_a_closed_piece(device):
    # press_kernel against the hull's own planes (inside: every facet's n . x + d < 0, kept a
    # generic margin from them) and the nearest point against dense samples of every facet
    pts, tris, eq = _hull(21)
    rng = np.random.default_rng(22)
    q = rng.normal(size=(400, 3)) * 0.08
    signed = (q @ eq[:, :3].T + eq[:, 3]).max(axis=1)  # > 0 outside, < 0 inside (convex)
    q = q[np.abs(signed) > 2e-3]
    inside = wp.zeros(len(q), dtype=wp.int32, device=device)
    near = wp.zeros(len(q), dtype=wp.vec3, device=device)
    capped, surface = _mesh(pts, tris, device, winding=True), _mesh(pts, tris, device)
    wp.launch(k.press_kernel, dim=len(q), inputs=[capped.id, surface.id, wp.array(q, dtype=wp.vec3, device=device), 1.0],
              outputs=[inside, near], device=device)
    ref = (q @ eq[:, :3].T + eq[:, 3]).max(axis=1) < 0.0
    assert ref.sum() > 50 and (~ref).sum() > 50
    np.testing.assert_array_equal(inside.numpy() != 0, ref)
    m = 40
    u, v = np.meshgrid(np.linspace(0, 1, m), np.linspace(0, 1, m))
    keep = u + v <= 1.0
    bary = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], axis=1)
    from scipy.spatial import cKDTree

    samples = np.einsum("sk,tkd->tsd", bary, pts[tris]).reshape(-1, 3)
    dense = cKDTree(samples).query(q)[0]
    d = np.linalg.norm(near.numpy() - q, axis=1)
    spacing = np.linalg.norm(pts[tris[:, 1]] - pts[tris[:, 0]], axis=1).max() / (m - 1)
    assert np.all(d <= dense + 1e-6)
    assert np.all(d >= dense - spacing)
    # and the point lies on the surface: on a facet's plane, within float32 rounding
    on = np.abs(near.numpy() @ eq[:, :3].T + eq[:, 3]).min(axis=1)
    assert on.max() < 1e-6


def test_a_ray_from_inside_leaves_a_closed_piece_where_its_planes_say(device):
    # exit_kernel against the closed form for a convex polyhedron: from an inside point q along
    # u, the least (-d - n . q) / (n . u) over the facets the ray heads out of (n . u > 0)
    pts, tris, eq = _hull(23)
    rng = np.random.default_rng(24)
    q = rng.normal(size=(300, 3)) * 0.03
    q = q[(q @ eq[:, :3].T + eq[:, 3]).max(axis=1) < -2e-3]
    u = rng.normal(size=(len(q), 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    out = wp.zeros(len(q), dtype=float, device=device)
    mesh = _mesh(pts, tris, device)
    wp.launch(k.exit_kernel, dim=len(q), inputs=[mesh.id, wp.array(q, dtype=wp.vec3, device=device),
                                                  wp.array(u, dtype=wp.vec3, device=device), 1.0],
              outputs=[out], device=device)
    nu = u @ eq[:, :3].T
    t = np.where(nu > 0, (-eq[:, 3][None, :] - q @ eq[:, :3].T) / np.where(nu > 0, nu, 1.0), np.inf).min(axis=1)
    assert len(q) > 50
    np.testing.assert_allclose(out.numpy(), t, rtol=1e-4, atol=1e-6)


def test_a_closed_piece_with_a_small_hole_is_closed_by_its_caps_and_a_sheet_is_not():
    # the hull without one vertex's fan (a wrist's opening): a closed piece, its cap over the
    # hole; the winding number with the cap is the hull's inside test away from the hole. A
    # sheet (a strip as wide as itself) is not a closed piece
    pts, tris, eq = _hull(25, count=300)
    cut = int(np.argmax(pts[:, 0]))
    open_tris = tris[~(tris == cut).any(axis=1)]
    m = 9
    y, z = np.meshgrid(np.linspace(0, 0.2, m), np.linspace(0, 0.05, 3), indexing="ij")
    sheet = np.stack([np.full(y.size, 0.5), y.ravel(), z.ravel()], axis=1)
    sheet += np.random.default_rng(26).uniform(-1e-4, 1e-4, size=sheet.shape)
    qd = (np.arange(m - 1)[:, None] * 3 + np.arange(2)[None, :]).ravel()
    sheet_tris = np.concatenate([np.stack([qd, qd + 3, qd + 4], 1), np.stack([qd, qd + 4, qd + 1], 1)])
    rest, all_tris, n = _two((pts, open_tris), (sheet, sheet_tris))
    u = _untangle(rest, all_tris)
    mesh = u.mesh
    piece_of = {int(mesh.piece_of_triangle[i]) for i in range(len(open_tris))}
    assert len(piece_of) == 1
    hull_piece = piece_of.pop()
    assert set(u._shells) == {hull_piece}
    rng = np.random.default_rng(27)
    q = rng.uniform(-1.2, 1.2, size=(1500, 3)) * np.array([0.1, 0.07, 0.05])
    signed = (q @ eq[:, :3].T + eq[:, 3]).max(axis=1)
    away = np.linalg.norm(q - pts[cut], axis=1) > 0.3 * np.linalg.norm(np.ptp(pts, axis=0))
    q = q[(np.abs(signed) > 2e-3) & away]
    got, _ = u._shells[hull_piece].inside(q, mesh.welded(rest))
    inside = (q @ eq[:, :3].T + eq[:, 3]).max(axis=1) < 0.0
    assert inside.sum() > 20 and (~inside).sum() > 20
    np.testing.assert_array_equal(got, inside)
    # its one hole found and capped: a loop round the vertex cut out, every edge of its fan
    shell = u._shells[hull_piece]
    assert shell.loops == 1 and len(shell.edges) == (tris == cut).any(axis=1).sum()


def _sheet(x0: float, half: float, m: int, seed: int):
    """A generic square sheet in the plane x = ``x0`` (jittered), its normal +x."""
    y, z = np.meshgrid(np.linspace(-half, half, m), np.linspace(-half, half, m), indexing="ij")
    sv = np.stack([np.full(y.size, x0), y.ravel(), z.ravel()], axis=1)
    sv += np.random.default_rng(seed).uniform(-2e-4, 2e-4, size=sv.shape) + np.array([0.0, 0.003, -0.002])
    q = (np.arange(m - 1)[:, None] * m + np.arange(m - 1)[None, :]).ravel()
    st = np.concatenate([np.stack([q, q + m, q + m + 1], 1), np.stack([q, q + m + 1, q + 1], 1)])
    return sv, (st if np.cross(sv[st[0, 1]] - sv[st[0, 0]], sv[st[0, 2]] - sv[st[0, 0]])[0] > 0 else st[:, ::-1])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_hand_swept_through_a_skirt_in_one_frame_dents_it_to_the_nearer_side(seed):
    # a closed ball (a hand) behind a sheet (a skirt) at rest, the last frame written; this frame
    # LBS has swept it through, its centre now 0.6 r in front: the sheet crosses the ball's back
    # cap, 0.4 r deep. The rounds read from the last frame that the ball belongs behind, which
    # would take pushing the sheet 1.6 r; the press takes the sheet over the nearer cap instead
    r = 0.08
    ball, bt = _sphere((0, 0, 0), r, 30 + seed)
    sv, st = _sheet(0.2, 0.2, 25, 40 + seed)
    rest, tris, n = _two((ball, bt), (sv, st))
    lbs = rest.copy()
    lbs[:n, 0] += 0.2 + 0.6 * r
    before = intersecting_pairs_brute_force(lbs, tris)
    assert before > 0
    groups = np.full(len(rest), -1)
    groups[:n] = 0  # the hand moves as a whole

    def run(press: bool):
        u = _untangle(rest, tris, groups, rounds=8, max_step=0.01 * 0.5, max_offset=0.05 * 0.5 * 4, press=press)
        return u, u.apply(lbs, lbs)

    u, out = run(True)
    _, plain = run(False)
    after, after_plain = intersecting_pairs_brute_force(out, tris), intersecting_pairs_brute_force(plain, tris)
    assert after <= 0.1 * before < after_plain
    assert u.stats["press"] > 0
    move = out - lbs
    assert np.array_equal(out[:n], np.asarray(lbs[:n], np.float32).astype(np.float64))  # the hand as driven
    # the sheet went back over the cap (-x), not forward through the ball, by about the cap's depth
    assert move[n:, 0].min() < -0.3 * r and move[n:, 0].max() <= 1e-7
    assert np.linalg.norm(move[n:], axis=1).max() < 0.4 * r + 0.05 * r + 0.25 * 0.02
    # none of it left inside the ball (a margin under its jittered radius)
    centre = lbs[:n].mean(axis=0)
    assert np.linalg.norm(out[n:] - centre, axis=1).min() > 0.99 * r
    # only near it: sheet points farther than 2 r from the ball's axis stay
    far = np.linalg.norm(lbs[n:, 1:] - centre[1:], axis=1) > 2.0 * r
    assert far.sum() > 0.4 * (len(lbs) - n)
    assert np.array_equal(out[n:][far], np.asarray(lbs[n:][far], np.float32).astype(np.float64))
    strained, _, flipped = strain_and_flips(rest, out, lbs, tris)
    assert strained == 0.0 and flipped == 0.0

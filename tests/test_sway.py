"""GarmentSway: a worn garment point's damped swing, against scipy's ODE integrator and the
damped oscillator's closed-form decay."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from warpskin.errors import SceneError
from warpskin.guard import GarmentSway, GuardParams
from warpskin.guard.sway import soft_limit


def _reference(u0, v0, accel, dt, omega, zeta):
    """``u(dt), u'(dt)`` of u'' + 2 zeta omega u' + omega^2 u = -accel by scipy's RK45."""
    def f(_, y):
        u, v = y[:3], y[3:]
        return np.concatenate([v, -accel - 2.0 * zeta * omega * v - omega * omega * u])
    sol = solve_ivp(f, (0.0, dt), np.concatenate([u0, v0]), rtol=1e-10, atol=1e-13)
    return sol.y[:3, -1], sol.y[3:, -1]


@pytest.mark.parametrize("zeta", [0.0, 0.2, 1.0, 2.5])
def test_one_frame_is_the_exact_solution(zeta):
    rng = np.random.default_rng(3)
    sway = GarmentSway(np.arange(4), np.full(4, 0.05), np.ones(4), frequency=1.7, damping=zeta, share=0.5)
    u0, v0, a = rng.normal(0, 0.01, (4, 3)), rng.normal(0, 0.1, (4, 3)), rng.normal(0, 3.0, (4, 3))
    u, v = sway.step(u0, v0, a, 0.037)
    for i in range(4):
        ru, rv = _reference(u0[i], v0[i], a[i], 0.037, 2.0 * np.pi * 1.7, zeta)
        np.testing.assert_allclose(u[i], ru, atol=1e-9)
        np.testing.assert_allclose(v[i], rv, atol=1e-8)


def _drive(sway, lbs_frames, fps):
    """The swing ``[F, K, 3]`` written per frame for LBS positions ``[F, K, 3]`` (the wrap's
    points at their LBS, so the written offset is the swing itself)."""
    out = []
    for f, lbs in enumerate(lbs_frames):
        out.append(sway.apply(lbs, lbs, f / fps) - lbs)
    return np.array(out)


def test_a_stop_rings_down_at_the_damping_rate():
    """A point moving at constant speed stops dead: it swings on past the stop and decays; the
    ratio of successive peaks is the damped oscillator's exp(-2 pi zeta / sqrt(1 - zeta^2)),
    and the swing up to the stop agrees with scipy integrating the same frame-constant forcing."""
    fps, f0, zeta = 120.0, 2.0, 0.1
    t = np.arange(360) / fps
    x = np.where(t < 0.5, 2.0 * t, 1.0)  # 2 m/s, stopping at 0.5 s
    lbs = np.zeros((len(t), 1, 3))
    lbs[:, 0, 0] = x + 0.3
    lbs[:, 0, 1] = 0.9
    sway = GarmentSway(np.array([0]), np.array([1000.0]), np.array([1.0]), frequency=f0, damping=zeta, share=1.0)
    swing = _drive(sway, lbs, fps)[:, 0, 0]
    assert np.all(swing[:2] == 0.0)  # the first two frames restart the oscillator
    assert abs(swing[2]) < 1e-9  # a constant speed: no acceleration (second differences round off)
    # the reference: the same second differences, constant over each frame, from frame 2 on
    u, v, ref = np.zeros(3), np.zeros(3), [0.0, 0.0]
    for f in range(2, len(t)):
        a = np.array([(lbs[f, 0, 0] - 2 * lbs[f - 1, 0, 0] + lbs[f - 2, 0, 0]) * fps * fps, 0.0, 0.0])
        u, v = _reference(u, v, a, 1.0 / fps, 2.0 * np.pi * f0, zeta)
        ref.append(u[0])
    np.testing.assert_allclose(swing, ref, atol=1e-4 * np.abs(ref).max())  # the limit (1 km) scales by < 1e-5
    after = swing[t > 0.52]
    peaks = [abs(after[i]) for i in range(1, len(after) - 1)
             if abs(after[i]) >= abs(after[i - 1]) and abs(after[i]) > abs(after[i + 1])]
    assert len(peaks) >= 3 and peaks[0] > 0.05  # it swings on, by centimetres, after the stop
    ratio = np.array(peaks[1:4]) / np.array(peaks[:3])  # half periods apart
    expected = np.exp(-np.pi * zeta / np.sqrt(1.0 - zeta * zeta))
    np.testing.assert_allclose(ratio, expected, rtol=0.03)


def test_the_swing_stays_within_its_share_of_the_gap():
    """A violent shake: every written swing is within share x gap (and near it), a point with no
    gap or no physics weight is never moved, bit for bit."""
    rng = np.random.default_rng(7)
    fps, k = 30.0, 5
    lbs = np.cumsum(rng.normal(0.0, 0.3, (40, k, 3)), axis=0)
    gap = np.array([0.04, 0.01, 0.0, -0.02, 0.03])
    weight = np.array([1.0, 0.5, 1.0, 1.0, 0.0])
    sway = GarmentSway(np.arange(k), gap, weight, frequency=2.0, damping=0.2, share=0.5)
    swing = np.linalg.norm(_drive(sway, lbs, fps), axis=2)
    tol = 1.0 + 1e-12  # at the limit, as far as tanh's rounding takes it
    assert np.all(swing[:, 0] <= 0.5 * 0.04 * tol) and swing[:, 0].max() > 0.9 * 0.5 * 0.04
    assert np.all(swing[:, 1] <= 0.5 * 0.5 * 0.01 * tol) and swing[:, 1].max() > 0.9 * 0.25 * 0.01
    assert np.all(swing[:, 2:] == 0.0)


def test_a_held_pose_is_written_as_given_and_time_going_back_restarts():
    lbs = np.tile(np.array([[0.1, 1.2, 0.3], [0.2, 1.1, 0.35]]), (6, 1, 1))
    sway = GarmentSway(np.array([0, 1]), np.array([0.03, 0.03]), np.ones(2), frequency=2.0, damping=0.2, share=0.5)
    pts = lbs[0] + 0.01
    for f in range(6):
        assert sway.apply(pts, lbs[f], f / 30.0) is pts
    moving = GarmentSway(np.array([0]), np.array([0.03]), np.ones(1), frequency=2.0, damping=0.2, share=0.5)
    one = pts[:1].copy()
    for f in range(4):
        moving.apply(one, one + np.array([0.1 * f * f, 0.0, 0.0]), f / 30.0)
    assert moving.largest > 0.0
    assert moving.apply(one, one, 0.0) is one  # time went back: restarted, written as given
    assert moving.largest == 0.0


def test_sway_settings_are_checked():
    GuardParams(sway=0.0, sway_frequency=0.5, sway_damping=0.0).check()
    for bad in (dict(sway=1.5), dict(sway_frequency=0.0), dict(sway_damping=-0.1)):
        with pytest.raises(SceneError, match=f"\\[guard\\] {next(iter(bad))} must be"):
            GuardParams(**bad).check()


def _grid(nx=9, ny=7, h=0.023):
    from warpskin.quality import WrittenMesh

    xy = np.stack(np.meshgrid(np.arange(nx) * h, np.arange(ny) * h, indexing="ij"), axis=-1).reshape(-1, 2)
    rest = np.column_stack([xy, 0.01 * np.sin(7.0 * xy[:, 0])])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return WrittenMesh("garment", tris, rest), rest


def test_the_limit_changes_gently_along_the_garment():
    """On a grid garment whose gap jumps from 0 (a tight band) to 4 cm, the sloped limit is the
    largest under share x gap that changes by at most SLOPE per metre along the edges: the
    brute force min_j (share gap_j + SLOPE d(i, j)), d by scipy's Dijkstra over the rest edges;
    points of the mesh not worn count as a limit of 0."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    h = 0.023
    mesh, rest = _grid(h=h)
    xy = rest[:, :2]
    worn = np.nonzero(xy[:, 0] > 0.5 * h)[0]  # the first column is not worn (the body)
    gap = np.where(xy[worn, 1] > 2.5 * h, 0.04, 0.0)
    sway = GarmentSway(worn, gap, np.ones(worn.size), frequency=2.0, damping=0.2, share=0.5, mesh=mesh)
    e = mesh.edges
    graph = sp.csr_matrix((np.concatenate([mesh.rest_length] * 2), (np.concatenate([e[:, 0], e[:, 1]]),
                                                                   np.concatenate([e[:, 1], e[:, 0]]))),
                          shape=(len(rest), len(rest)))
    dist = dijkstra(graph, directed=False)
    base = np.zeros(len(rest))
    base[worn] = 0.5 * gap
    expected = (base[None, :] + GarmentSway.SLOPE * dist).min(axis=1)[worn]
    np.testing.assert_allclose(sway.limit, expected, rtol=1e-12, atol=1e-15)
    assert sway.limit.max() > 0.0 and np.all(sway.limit <= 0.5 * gap + 1e-15)


def test_neighbours_swing_alike_within_their_limits():
    """Each point of a grid garment shaken on its own: with the mesh, the swing written is the
    ring mean of the points' swings (neighbours differ far less than the points' own swings
    do), still within every point's limit, and 0 where the limit is."""
    mesh, rest = _grid()
    k = len(rest)
    worn = np.arange(k)
    gap = np.where(rest[:, 0] > 0.03, 0.04, 0.0)
    rng = np.random.default_rng(11)
    lbs = rest[None] + np.cumsum(rng.normal(0.0, 0.004, (12, k, 3)), axis=0)
    apart = GarmentSway(worn, gap, np.ones(k), frequency=2.0, damping=0.2, share=0.5)
    alike = GarmentSway(worn, gap, np.ones(k), frequency=2.0, damping=0.2, share=0.5, mesh=mesh)
    e = mesh.edges
    for f in range(12):
        a = apart.apply(lbs[f], lbs[f], f / 30.0) - lbs[f]
        b = alike.apply(lbs[f], lbs[f], f / 30.0) - lbs[f]
        if f < 2:
            assert not a.any() and not b.any()
            continue
        assert np.all(np.linalg.norm(b, axis=1) <= alike.limit * (1.0 + 1e-12))
        assert np.all(b[gap == 0.0] == 0.0)
        inner = (gap[e] > 0.0).all(axis=1)  # edges away from the tight band
        spread_a = np.linalg.norm(a[e[inner, 0]] - a[e[inner, 1]], axis=1).mean()
        spread_b = np.linalg.norm(b[e[inner, 0]] - b[e[inner, 1]], axis=1).mean()
        assert spread_b < 0.5 * spread_a


def test_the_swing_slides_along_the_body_and_keeps_off_other_pieces():
    """With carriers, the swing lies across each point's offset from its carrier (it slides
    along the body) and is at most share x that offset (the room the wrap leaves this frame);
    a point that another piece comes near this frame swings by at most share x the distance."""
    rng = np.random.default_rng(5)
    fps, k = 30.0, 6
    lbs = np.cumsum(rng.normal(0.0, 0.05, (10, k + 1, 3)), axis=0)  # the last row: another piece's point
    offset = rng.normal(0.0, 1.0, (k, 3))
    offset *= (np.array([0.03, 0.03, 0.03, 0.03, 0.004, 0.03]) / np.linalg.norm(offset, axis=1))[:, None]
    pieces = np.array([0, 0, 0, 0, 0, 0, 1])
    sway = GarmentSway(np.arange(k), np.full(k, 0.04), np.ones(k), frequency=2.0, damping=0.2, share=0.5,
                       pieces=pieces)
    for f in range(10):
        carriers = lbs[f, :k] - offset
        pts = lbs[f].copy()
        pts[k] = pts[5] + np.array([0.006, 0.0, 0.0])  # 6 mm from point 5 this frame
        swing = (sway.apply(pts, lbs[f], f / fps, carriers) - pts)[:k]
        if f < 2:
            assert not swing.any()
            continue
        n = offset / np.linalg.norm(offset, axis=1, keepdims=True)
        np.testing.assert_allclose(np.einsum("ij,ij->i", swing, n), 0.0, atol=1e-12)
        size = np.linalg.norm(swing, axis=1)
        tol = 1.0 + 1e-12
        assert np.all(size[:4] <= 0.5 * 0.03 * tol) and size[:4].max() > 0.0
        assert size[4] <= 0.5 * 0.004 * tol  # the wrap left it 4 mm of its 4 cm
        assert size[5] <= 0.5 * 0.006 * tol  # the other piece 6 mm away


def test_under_half_its_limit_the_swing_is_the_oscillator_s_own():
    """The limit leaves a swing under half of it alone, so its decay is the oscillator's: the
    same stop with a limit four times the swing's peak and with none gives the same swing; with
    a limit under the peak, the swing is compressed and stays within it."""
    fps = 60.0
    t = np.arange(120) / fps
    lbs = np.zeros((len(t), 1, 3))
    lbs[:, 0, 0] = np.where(t < 0.3, 1.5 * t, 0.45)
    runs = {}
    for lim in (1e6, 4.0 * 0.12, 0.05):
        sway = GarmentSway(np.array([0]), np.array([lim]), np.ones(1), frequency=2.0, damping=0.2, share=1.0)
        runs[lim] = _drive(sway, lbs, fps)[:, 0, 0]
    peak = np.abs(runs[1e6]).max()
    assert 0.08 < peak < 0.12  # the peak under a quarter of the second limit
    np.testing.assert_array_equal(runs[4.0 * 0.12], runs[1e6])
    assert np.abs(runs[0.05]).max() <= 0.05 * (1.0 + 1e-12) and np.abs(runs[0.05]).max() > 0.025


def test_soft_limit():
    size = np.array([0.0, 0.2, 0.5, 0.6, 1.0, 5.0, 1e3, 0.3])
    lim = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0])
    f = soft_limit(size, lim)
    np.testing.assert_array_equal(f[:3], 1.0)  # up to half the limit: untouched
    assert f[-1] == 0.0
    out = f * size
    assert np.all(out[:7] <= 1.0 + 1e-12) and np.all(np.diff(out[:7]) > 0.0)  # rising, within the limit
    # slope 1 at the knee (finite differences), and the closed form beyond it
    h = 1e-6
    slope = (soft_limit(np.array([0.5 + h]), np.array([1.0]))[0] * (0.5 + h) - 0.5) / h
    assert slope == pytest.approx(1.0, abs=1e-5)
    assert out[4] == pytest.approx(0.5 + 0.5 * np.tanh(1.0), rel=1e-12)


def test_carriers_and_pieces_each_alone():
    """Carriers without pieces still slide the swing along the body; pieces without carriers
    still keep it off the other piece."""
    rng = np.random.default_rng(9)
    k = 5
    lbs = np.cumsum(rng.normal(0.0, 0.05, (8, k + 1, 3)), axis=0)
    offset = rng.normal(0.0, 0.02, (k, 3))
    n = offset / np.linalg.norm(offset, axis=1, keepdims=True)
    slide = GarmentSway(np.arange(k), np.full(k, 0.05), np.ones(k), frequency=2.0, damping=0.2, share=0.5)
    apart = GarmentSway(np.arange(k), np.full(k, 0.05), np.ones(k), frequency=2.0, damping=0.2, share=0.5,
                        pieces=np.array([0] * k + [1]))
    for f in range(8):
        a = (slide.apply(lbs[f, :k], lbs[f, :k], f / 30.0, lbs[f, :k] - offset) - lbs[f, :k])
        pts = lbs[f].copy()
        pts[k] = pts[0] + np.array([0.0, 0.004, 0.0])
        b = (apart.apply(pts, lbs[f], f / 30.0) - pts)[:k]
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, n), 0.0, atol=1e-12)
        assert np.linalg.norm(b[0]) <= 0.5 * 0.004 * (1.0 + 1e-12)
    assert np.abs(a).max() > 0.0 and np.abs(b[1:]).max() > 0.0

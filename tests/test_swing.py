"""PieceSwing and loose_pieces: which pieces hang loose (geometry built here, generic positions),
the pendulum against scipy's ODE integrator and its closed-form static deflection, and the
winding numbers against the sphere's inside and outside."""

import numpy as np
import pytest
import trimesh
from scipy.integrate import solve_ivp

from warpskin.guard.swing import LoosePiece, PieceSwing, curvature_centre, loose_pieces, winding_numbers
from warpskin.transforms import rigid_fit


def _sphere(center, radius, subdivisions=3):
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices) + np.asarray(center, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)


def test_winding_numbers_inside_and_outside_a_sphere():
    v, t = _sphere((0.1, -0.2, 0.3), 1.0)
    rng = np.random.default_rng(5)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    inside = (0.1, -0.2, 0.3) + d * rng.uniform(0.0, 0.85, (40, 1))
    outside = (0.1, -0.2, 0.3) + d * rng.uniform(1.2, 4.0, (40, 1))
    np.testing.assert_allclose(winding_numbers(inside, v, t), 1.0, atol=1e-9)
    np.testing.assert_allclose(winding_numbers(outside, v, t), 0.0, atol=1e-9)
    np.testing.assert_allclose(winding_numbers(inside, v, t[:, ::-1]), -1.0, atol=1e-9)  # wound inward


def _head_scene():
    """A head (radius 1, closed, joint 0) with, all rigid: a bun half sunk into its crown (joint
    0), an eye mostly inside its front (joint 0), a ponytail ball at its back on joint 1, and a
    second closed ball beside the head joined to it by a small ball touching both (joint 0)."""
    parts = [
        (_sphere((0.0, 0.0, 0.0), 1.0), 0),  # 0 head
        (_sphere((0.04, 1.03, 0.02), 0.3), 0),  # 1 bun: its centre just outside the crown
        (_sphere((0.31, 0.12, 0.84), 0.2), 0),  # 2 eye: a cap shows
        (_sphere((0.03, -0.15, -1.05), 0.3), 1),  # 3 on another joint
        (_sphere((2.62, 0.01, 0.02), 1.0), 0),  # 4 a second head
        (_sphere((1.31, 0.02, -0.01), 0.36), 0),  # 5 between the two
    ]
    points, tris, piece, joint = [], [], [], []
    base = 0
    for k, ((v, t), j) in enumerate(parts):
        points.append(v)
        tris.append(t + base)
        piece.append(np.full(len(v), k))
        joint.append(np.full(len(v), j))
        base += len(v)
    points, piece, joint = np.concatenate(points), np.concatenate(piece), np.concatenate(joint)
    closed = {k: parts[k][0] for k in range(len(parts))}
    return points, np.concatenate(tris), piece, joint, closed


def test_only_a_piece_hanging_off_one_place_of_its_own_joint_is_loose():
    points, _, piece, joint, closed = _head_scene()
    loose = loose_pieces(points, piece, joint, np.ones(6, dtype=bool), closed, touch=0.08)
    assert [p.piece for p in loose] == [1]  # not the eye, the other joint's ball, the joint ball
    bun = loose[0]
    assert bun.carrier == 0 and 0 in bun.touching
    np.testing.assert_array_equal(bun.points, np.nonzero(piece == 1)[0])
    # the pivot lies on the head (within the icosphere's chord error) under the part that shows
    assert abs(np.linalg.norm(bun.pivot) - 1.0) < 0.01
    shown = points[bun.points[bun.visible]].mean(axis=0)
    assert np.all(np.linalg.norm(points[bun.points[bun.visible]], axis=1) > 1.0 - 0.01)
    cos = shown @ bun.pivot / (np.linalg.norm(shown) * np.linalg.norm(bun.pivot))
    assert cos > 0.999
    # it turns about the head's centre (the sphere fitted to the head about the pivot)
    assert np.linalg.norm(bun.centre) < 0.01
    # nothing is loose where no piece is rigid, or where the carrier is not closed
    assert loose_pieces(points, piece, joint, np.zeros(6, dtype=bool), closed, touch=0.08) == []
    assert loose_pieces(points, piece, joint, np.ones(6, dtype=bool), {1: closed[1]}, touch=0.08) == []


def _bun_swing(frequency, damping, angle):
    points, _, piece, joint, closed = _head_scene()
    mine = np.isin(piece, (0, 1))
    loose = loose_pieces(points, piece, joint, np.ones(6, dtype=bool), closed, touch=0.08)
    keep = np.nonzero(mine)[0]
    remap = np.full(len(points), -1)
    remap[keep] = np.arange(keep.size)
    bun = LoosePiece(loose[0].piece, remap[loose[0].points], loose[0].visible, loose[0].pivot, 0, loose[0].touching)
    swing = PieceSwing([bun], points[keep], piece[keep], np.ones(keep.size), frequency, damping, angle)
    return swing, bun, points[keep]


def test_the_curvature_centre_of_a_cap_and_none_of_a_flat_or_a_saddle():
    rng = np.random.default_rng(11)
    centre, radius = np.array([0.3, -0.1, 0.2]), 0.7
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    sphere = centre + radius * d
    pivot = sphere[np.argmax(d[:, 1])]  # the top of the sphere
    up = (pivot - centre) / radius
    np.testing.assert_allclose(curvature_centre(pivot, up, sphere, 0.4, 2.0), centre, atol=1e-9)
    assert curvature_centre(pivot, -up, sphere, 0.4, 2.0) is None  # seen from inside: concave
    assert curvature_centre(pivot, up, sphere, 0.4, 0.5) is None  # rounder than allowed
    assert curvature_centre(pivot, up, sphere, 0.02, 2.0) is None  # too few vertices near
    u, v = rng.uniform(-0.3, 0.3, (2, 300))
    flat = np.stack([u, np.full_like(u, 0.2), v], axis=1)
    saddle = np.stack([u, 0.2 + 0.5 * (u * u - v * v), v], axis=1)
    top = np.array([0.0, 0.2, 0.0])
    for surface in (flat, saddle):
        assert curvature_centre(top, np.array([0.0, 1.0, 0.0]), surface, 0.25, 2.0) is None


def test_a_sunk_piece_slides_over_its_round_carrier_keeping_its_depth():
    """The bun on its head scene, swung about the head's centre: every point keeps its distance
    from that centre (its depth in the head is the rest depth), and its centroid moves as far
    as the same swing about the pivot on the head's surface would move it."""
    points, _, piece, joint, closed = _head_scene()
    loose = loose_pieces(points, piece, joint, np.ones(6, dtype=bool), closed, touch=0.08)
    keep = np.nonzero(np.isin(piece, (0, 1)))[0]
    remap = np.full(len(points), -1)
    remap[keep] = np.arange(keep.size)
    lp = loose[0]
    rest = points[keep]
    make = lambda centre: PieceSwing([LoosePiece(lp.piece, remap[lp.points], lp.visible, lp.pivot, 0, lp.touching,
                                                 centre)], rest, piece[keep], np.ones(keep.size), 4.0, 1.0, 1.5)
    about_centre, about_pivot = make(lp.centre), make(None)
    a = np.array([20.0, 0.0, 7.0])
    for f in range(40):
        t = f / 30.0
        lbs = rest + 0.5 * a * t * t
        slid, tilted = about_centre.apply(lbs, lbs, t), about_pivot.apply(lbs, lbs, t)
    bun = remap[lp.points]
    moved = slid[bun] - lbs[bun]
    assert np.linalg.norm(moved, axis=1).max() > 0.005  # it swings
    shift = 0.5 * a * t * t
    np.testing.assert_allclose(np.linalg.norm(slid[bun] - shift - lp.centre, axis=1),
                               np.linalg.norm(rest[bun] - lp.centre, axis=1), atol=1e-12)
    vis = bun[lp.visible]
    c_slid, c_tilted = slid[vis].mean(axis=0) - lbs[vis].mean(axis=0), tilted[vis].mean(axis=0) - lbs[vis].mean(axis=0)
    np.testing.assert_allclose(np.linalg.norm(c_slid), np.linalg.norm(c_tilted), rtol=0.02)
    assert c_slid @ c_tilted > 0.99 * np.linalg.norm(c_slid) * np.linalg.norm(c_tilted)


def _rotation(before, after):
    """``[3, 3]`` the rotation of the best rigid fit of ``before`` onto ``after``."""
    return rigid_fit(before, after)[0]


def test_a_constant_acceleration_deflects_the_piece_by_the_static_angle():
    fps, a = 30.0, np.array([2.0, 0.0, 0.0])
    swing, bun, rest = _bun_swing(4.0, 1.0, 1.5)
    vis = rest[bun.points[bun.visible]]
    c = vis.mean(axis=0)
    arm = c - bun.pivot
    g2 = np.mean(np.sum((vis - c) ** 2, axis=1))
    w = 2.0 * np.pi * 4.0
    expected = -np.cross(arm, a) / ((arm @ arm + g2) * w * w)  # the rotation vector at rest
    for f in range(90):
        t = f / fps
        lbs = rest + 0.5 * a * t * t
        out = swing.apply(lbs, lbs, t)
    r = _rotation(lbs[bun.points], out[bun.points])
    got = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0  # sin(angle) x axis
    np.testing.assert_allclose(got, np.sin(np.linalg.norm(expected)) * expected / np.linalg.norm(expected),
                               atol=2e-4)
    # rigid: every distance within the piece kept; its centroid lags behind the acceleration
    moved = out[bun.points]
    i, j = np.triu_indices(len(moved), 1)
    np.testing.assert_allclose(np.linalg.norm(moved[i] - moved[j], axis=1),
                               np.linalg.norm(lbs[bun.points][i] - lbs[bun.points][j], axis=1), atol=1e-12)
    assert (moved.mean(axis=0) - lbs[bun.points].mean(axis=0)) @ a < 0.0
    # the head is not moved
    head = np.setdiff1d(np.arange(len(rest)), bun.points)
    np.testing.assert_array_equal(out[head], lbs[head])


def test_the_swing_after_a_stop_is_the_pendulum_integrated_by_scipy():
    fps, zeta, freq = 30.0, 0.1, 4.0
    swing, bun, rest = _bun_swing(freq, zeta, 1.5)
    w = 2.0 * np.pi * freq
    vis = rest[bun.points[bun.visible]]
    c = vis.mean(axis=0)
    arm = c - bun.pivot
    inertia = arm @ arm + np.mean(np.sum((vis - c) ** 2, axis=1))
    # a push along x for a third of a second, then held still: the centroid's LBS path
    times = np.arange(40) / fps
    x = np.where(times < 1.0 / 3.0, 0.5 * 3.0 * times ** 2, 0.5 * 3.0 / 9.0)
    written = []
    for f, t in enumerate(times):
        lbs = rest + np.array([x[f], 0.0, 0.0])
        out = swing.apply(lbs, lbs, t)
        r = _rotation(lbs[bun.points], out[bun.points])
        written.append(np.arctan2(r[1, 0] - r[0, 1], r[0, 0] + r[1, 1]))  # about z
    # the reference: the same forcing (the LBS's second differences, constant over each frame)
    theta, rate, ref = 0.0, 0.0, [0.0, 0.0]
    for f in range(2, len(times)):
        h = 1.0 / fps
        accel = (x[f] - 2.0 * x[f - 1] + x[f - 2]) / (h * h)
        force = -(arm[0] * 0.0 - arm[1] * accel) / inertia  # z of -(arm x a)
        sol = solve_ivp(lambda _, y: [y[1], force - 2.0 * zeta * w * y[1] - w * w * y[0]], (0.0, h), [theta, rate],
                        rtol=1e-10, atol=1e-13)
        theta, rate = sol.y[0, -1], sol.y[1, -1]
        ref.append(theta)
    np.testing.assert_allclose(written, ref, atol=1e-6)
    after = np.abs(np.array(written)[12:])
    assert after.max() > 0.02  # it still swings after the stop, ringing down
    assert after[-8:].max() < after[:8].max()


def test_no_acceleration_leaves_the_points_as_they_are():
    swing, bun, rest = _bun_swing(4.0, 0.1, 0.3)
    lbs = rest + np.array([0.3, -0.2, 0.1])
    for f in range(6):  # a pose held: exactly no acceleration
        assert swing.apply(lbs, lbs, f / 30.0) is lbs
    assert swing.largest == 0.0
    swing.reset()
    for f in range(6):  # a constant velocity: no acceleration but the positions' rounding
        lbs = rest + np.array([0.01 * f, 0.0, 0.0])
        np.testing.assert_allclose(swing.apply(lbs, lbs, f / 30.0), lbs, atol=1e-12)
    assert swing.largest < 1e-12


def test_the_swing_is_limited_to_its_angle():
    swing, bun, rest = _bun_swing(1.0, 0.0, 0.2)
    largest = 0.0
    for f in range(60):
        t = f / 30.0
        lbs = rest + 0.5 * np.array([50.0, 0.0, 0.0]) * t * t  # far past the limit's static angle
        swing.apply(lbs, lbs, t)
        largest = max(largest, swing.largest)
    assert 0.1 < largest <= 0.2 + 1e-12


def test_guard_settings_of_the_swing_are_checked():
    from warpskin.errors import SceneError
    from warpskin.guard import GuardParams

    GuardParams(swing=0.0, swing_frequency=0.5, swing_damping=0.0).check()
    for bad in (dict(swing=2.0), dict(swing_frequency=0.0), dict(swing_damping=-0.1)):
        with pytest.raises(SceneError, match="swing"):
            GuardParams(**bad).check()

"""The chord constraints of a refined skin's written triangles (:mod:`warpskin.kernels.chords`)
against closed forms, and their effect on a low-poly character (the Fox's run)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from warpskin.kernels import chords as kc


def _strain(x, rest_length, lbs, inv_mass, limit, device):
    xs = wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device=device)
    wp.launch(kc.chord_strain_kernel, dim=1,
              inputs=[wp.array(np.array([[0, 1]], np.int32), dtype=wp.int32, device=device),
                      wp.array(np.array([rest_length], np.float32), dtype=wp.float32, device=device),
                      wp.array(np.asarray(lbs, np.float32), dtype=wp.vec3, device=device),
                      wp.array(np.asarray(inv_mass, np.float32), dtype=wp.float32, device=device), limit],
              outputs=[xs], device=device)
    return xs.numpy().astype(np.float64)


@pytest.mark.parametrize("length, lbs_length, expect", [
    (2.0, 1.0, 1.4),         # stretched: to the limit x rest
    (0.5, 1.0, 1.0 / 1.4),   # shortened: to rest / limit
    (2.0, 1.83, 1.83),       # LBS stretches it more than the limit: to LBS's length
    (0.3, 0.55, 0.55),       # LBS shortens it more: to LBS's length
])
def test_an_edge_goes_to_its_bound_about_its_mass_weighted_centre(device, length, lbs_length, expect):
    x = np.array([[0.1, 0.2, 0.3], [0.1, 0.2, 0.3]]) + np.array([[0.0, 0.0, 0.0], [0.6, 0.8, 0.0]]) * length
    lbs = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, lbs_length]])
    out = _strain(x, 1.0, lbs, [1.0, 3.0], 1.4, device)
    assert np.linalg.norm(out[1] - out[0]) == pytest.approx(expect, rel=1e-5)
    # along the edge, about the centre weighted by mass (1 : 1/3)
    centre = lambda p: (p[0] / 1.0 + p[1] / 3.0) / (1.0 + 1.0 / 3.0)  # noqa: E731
    np.testing.assert_allclose(centre(out), centre(x), atol=1e-6)
    np.testing.assert_allclose(np.cross(out[1] - out[0], [0.6, 0.8, 0.0]), 0.0, atol=1e-6)


def test_an_edge_within_its_bounds_or_between_pinned_points_is_left_alone(device):
    x = np.array([[0.0, 0.0, 0.0], [1.23, 0.0, 0.0]])
    np.testing.assert_array_equal(_strain(x, 1.0, x, [1.0, 1.0], 1.4, device), x.astype(np.float32))
    far = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    np.testing.assert_array_equal(_strain(far, 1.0, x, [0.0, 0.0], 1.4, device), far.astype(np.float32))
    # one end pinned: the other takes the whole correction
    out = _strain(far, 1.0, x, [0.0, 1.0], 1.4, device)
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.0], [1.4, 0.0, 0.0]], atol=1e-6)


def _orient(x, lbs, inv_mass, share, device, launches=1):
    xs = wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device=device)
    tri = wp.array(np.array([[0, 1, 2]], np.int32), dtype=wp.int32, device=device)
    lb = wp.array(np.asarray(lbs, np.float32), dtype=wp.vec3, device=device)
    w = wp.array(np.asarray(inv_mass, np.float32), dtype=wp.float32, device=device)
    for _ in range(launches):
        wp.launch(kc.chord_orientation_kernel, dim=1, inputs=[tri, lb, w, share], outputs=[xs], device=device)
    return xs.numpy().astype(np.float64)


def _normal(p):
    return np.cross(p[1] - p[0], p[2] - p[0])


REST = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.3, 0.9, 0.0]])  # in the xy plane, normal +z


def test_a_turned_over_triangle_is_turned_back_keeping_its_centre(device):
    # its third corner pushed through the first edge: the triangle faces -z
    x = REST + np.array([[0.0, 0.0, 0.05], [0.0, 0.0, -0.02], [0.2, -1.2, 0.1]])
    assert _normal(x)[2] < 0
    masses = [1.0, 2.0, 0.5]
    out = _orient(x, REST, masses, 0.1, device, launches=30)
    floor = 0.1 * np.linalg.norm(_normal(REST))
    assert _normal(out)[2] >= floor * (1 - 1e-3)   # converged onto the bound (a band for float32)
    assert _normal(out)[2] <= floor * 1.05         # and not beyond it: a bound, not a spring
    w = np.array(masses)[:, None]
    np.testing.assert_allclose((out / w).sum(axis=0), (x / w).sum(axis=0), atol=1e-5)  # momentum kept


def test_a_triangle_facing_the_right_way_is_left_alone(device):
    x = REST * 1.1 + np.array([0.3, -0.2, 0.05])
    np.testing.assert_array_equal(_orient(x, REST, [1.0, 1.0, 1.0], 0.1, device), x.astype(np.float32))


def test_the_reference_is_lbs_as_it_faces_this_frame(device):
    # LBS turned by 90 degrees about x (the rest normal +z goes to -y): a triangle facing +y is
    # turned to face -y, by at least the share of LBS's area
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    lbs = REST @ rot.T
    x = lbs.copy()
    x[2] = x[0] + (x[0] - x[2])  # folded through its first corner: faces +y
    assert _normal(x)[1] > 0 > _normal(lbs)[1]
    out = _orient(x, lbs, [1.0, 1.0, 1.0], 0.1, device, launches=30)
    assert -_normal(out)[1] >= 0.1 * np.linalg.norm(_normal(lbs)) * (1 - 1e-3)
    # a triangle LBS collapses to a point constrains nothing
    point = np.repeat(lbs[:1], 3, axis=0)
    np.testing.assert_array_equal(_orient(x, point, [1.0, 1.0, 1.0], 0.1, device), x.astype(np.float32))


def test_the_chords_lbs_reference_is_the_blend_of_the_joint_matrices(device):
    # the solver launches the skinning module's LBS kernel on the skin particles for it
    from warpskin.kernels.skinning import lbs_kernel

    rng = np.random.default_rng(3)
    rest = rng.normal(size=(5, 3))
    mats = np.stack([np.eye(4), np.eye(4)])
    mats[1, :3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    mats[1, :3, 3] = [0.5, -0.2, 0.1]
    w = rng.random((5, 2))
    w /= w.sum(axis=1, keepdims=True)
    expect = sum(w[:, k, None] * (rest @ mats[k, :3, :3].T + mats[k, :3, 3]) for k in range(2))
    out = wp.zeros(5, dtype=wp.vec3, device=device)
    wp.launch(lbs_kernel, dim=5, inputs=[
        wp.array(rest.astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(np.tile(np.arange(2, dtype=np.int32), (5, 1)), dtype=wp.int32, device=device),
        wp.array(w.astype(np.float32), dtype=wp.float32, device=device),
        wp.array(mats.astype(np.float32), dtype=wp.mat44, device=device)], outputs=[out], device=device)
    np.testing.assert_allclose(out.numpy(), expect, atol=1e-5)


def test_chord_strain_between_zero_and_one_is_refused():
    from warpskin.errors import SceneError
    from warpskin.params import SolverParams

    with pytest.raises(SceneError, match=r"^x: \[solver\] chord_strain must be 0 \(off\) or > 1, got 0\.9$"):
        SolverParams(chord_strain=0.9).check("x")
    SolverParams(chord_strain=0.0).check("x")
    SolverParams(chord_strain=1.2).check("x")

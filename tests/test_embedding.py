"""The embedding of a render mesh in a cage, against NumPy references: the rest pose is
reproduced, a rigid motion of the cage moves the render points rigidly, a smooth stretch stays
within a stated bound, on every device; with the cage's surface normals and with an inner layer's
directions (a simulated cage's fat layer), whose per-frame result is also checked against a NumPy
evaluation of the same frame."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.spatial.transform import Rotation

from oracles import closest_on_mesh
from warpskin.embedding import Embedding
from warpskin.errors import InputError


def _scene():
    """A bumpy render mesh (points inside and outside the cage) and a coarser cage around it."""
    render = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v = np.asarray(render.vertices)
    bumps = 1.0 + 0.06 * np.sin(5 * v[:, 0]) * np.cos(4 * v[:, 1])
    points = v * bumps[:, None] * np.array([1.0, 1.3, 0.9])
    cage = trimesh.creation.icosphere(subdivisions=2, radius=1.05)
    cage_v = np.asarray(cage.vertices) * np.array([1.0, 1.3, 0.9])
    return points, cage_v, np.asarray(cage.faces)


def _inner(cv):
    """An inner layer under the cage, as a fat layer sits: each vertex moved 15 % of the way to
    an axis (not along the surface normal), with a smooth, uneven depth."""
    axis_point = np.stack([np.zeros(len(cv)), cv[:, 1] * 0.5, np.zeros(len(cv))], axis=1)
    share = 0.15 * (1.0 + 0.3 * np.sin(3.0 * cv[:, 1]))
    return cv + share[:, None] * (axis_point - cv)


def _embed(points, cv, ct, layered, device=None):
    return Embedding(points, cv, ct, inner=_inner(cv) if layered else None, device=device)


def _cage_input(cv, layered, fn=lambda p: p):
    """The evaluate input of the cage ``cv`` moved by ``fn``: the cage, then its inner layer."""
    return (np.concatenate([fn(cv), fn(_inner(cv))]) if layered else fn(cv)).astype(np.float32)


def _numpy_frame(emb, x, ct, layered):
    """Float64 NumPy evaluation of the embedding on ``x`` (the module's definition, written out:
    the point's barycentric point plus its offset in the frame of the interpolated normal and
    its triangle's first edge)."""
    v = emb.cage_vertex_count
    tri = ct[emb.face]
    w = emb.bary
    xs = x[:v].astype(np.float64)
    if layered:
        nrm = xs - x[emb.inner_offset:emb.inner_offset + v].astype(np.float64)
    else:
        nrm = np.zeros_like(xs)
        fn = np.cross(xs[ct[:, 1]] - xs[ct[:, 0]], xs[ct[:, 2]] - xs[ct[:, 0]])  # twice the area x the unit normal
        for k in range(3):
            np.add.at(nrm, ct[:, k], fn)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True).clip(1e-30)
    p = np.einsum("nk,nkd->nd", w, xs[tri])
    n = np.einsum("nk,nkd->nd", w, nrm[tri])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    e = xs[tri[:, 1]] - xs[tri[:, 0]]
    t = e - np.einsum("nd,nd->n", e, n)[:, None] * n
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(n, t)
    o = emb.offset
    return p + o[:, :1] * t + o[:, 1:2] * b + o[:, 2:] * n


@pytest.mark.parametrize("layered", [False, True], ids=["surface_normals", "inner_layer"])
def test_the_rest_pose_is_reproduced(device, layered):
    points, cv, ct = _scene()
    emb = _embed(points, cv, ct, layered, device)
    got = emb.evaluate(wp.array(_cage_input(cv, layered), dtype=wp.vec3, device=device)).numpy()
    size = np.linalg.norm(np.ptp(points, axis=0))
    assert np.abs(got - points).max() < 1e-6 * size
    assert emb.distance.max() > 0.05  # the points really sit off the cage, on both sides


@pytest.mark.parametrize("layered", [False, True], ids=["surface_normals", "inner_layer"])
def test_a_rigid_motion_of_the_cage_moves_the_points_rigidly(device, layered):
    points, cv, ct = _scene()
    emb = _embed(points, cv, ct, layered, device)
    rot = Rotation.from_rotvec([0.7, -1.1, 0.4]).as_matrix()
    shift = np.array([0.3, -2.0, 5.0])
    got = emb.evaluate(_cage_input(cv, layered, lambda p: p @ rot.T + shift)).numpy()
    want = points @ rot.T + shift
    assert np.abs(got - want).max() < 1e-5 * np.linalg.norm(np.ptp(points, axis=0))


@pytest.mark.parametrize("layered", [False, True], ids=["surface_normals", "inner_layer"])
def test_a_smooth_stretch_stays_within_the_stated_bound(device, layered):
    # the offsets turn with the surface (or the tissue) but keep their length: the error is at
    # most about the strain times the offset (10 % stretch: within 15 % of the largest offset)
    points, cv, ct = _scene()
    emb = _embed(points, cv, ct, layered, device)
    stretch = np.diag([1.10, 0.95, 1.0])
    got = emb.evaluate(_cage_input(cv, layered, lambda p: p @ stretch.T)).numpy()
    err = np.linalg.norm(got - points @ stretch.T, axis=1)
    assert err.max() <= 0.15 * emb.distance.max()
    assert err.max() > 1e-4  # a stretch is not a rigid motion: the bound is exercised


@pytest.mark.parametrize("layered", [False, True], ids=["surface_normals", "inner_layer"])
def test_a_deformed_frame_matches_numpy(device, layered):
    # a non-rigid, non-linear deformation of both layers (the inner one moved on its own too):
    # the kernel's frame is the NumPy one of the same definition, to float32 rounding
    points, cv, ct = _scene()
    emb = _embed(points, cv, ct, layered, device)
    rng = np.random.default_rng(7)
    x = _cage_input(cv, layered, lambda p: p + 0.08 * np.sin(2.0 * p[:, [1, 2, 0]]))
    x = x + rng.normal(scale=0.01, size=x.shape).astype(np.float32)
    got = emb.evaluate(x).numpy()
    want = _numpy_frame(emb, x, ct, layered)
    assert np.abs(got - want).max() < 2e-5 * np.linalg.norm(np.ptp(points, axis=0))
    assert np.abs(want - points).max() > 0.02  # the deformation moved the points


def test_bad_input_names_the_problem():
    points, cv, ct = _scene()
    with pytest.raises(InputError, match="render points must be finite"):
        Embedding(np.full((3, 3), np.nan), cv, ct)
    with pytest.raises(InputError, match="index vertices outside"):
        Embedding(points, cv, ct + len(cv))
    emb = Embedding(points, cv, ct)
    with pytest.raises(InputError, match=r"cage points must be \[162, 3\]"):
        emb.evaluate(np.zeros((5, 3)))
    with pytest.raises(InputError, match=r"inner layer must be finite \[162, 3\]"):
        Embedding(points, cv, ct, inner=cv[:10])
    flat = _inner(cv)
    flat[17] = cv[17]
    with pytest.raises(InputError, match="cage vertex 17 lies on its inner point"):
        Embedding(points, cv, ct, inner=flat)
    with pytest.raises(InputError, match="inner_offset must be at least the cage's 162"):
        Embedding(points, cv, ct, inner=_inner(cv), inner_offset=100)
    layered = Embedding(points, cv, ct, inner=_inner(cv))
    with pytest.raises(InputError, match=r"at least \[324, 3\] \(the cage, its inner layer from row 162\)"):
        layered.evaluate(cv)


def _eye_scene():
    """The bumpy scene plus a small sphere (an eye) inside the cage near its surface: a rigid piece."""
    points, cv, ct = _scene()
    eye = np.asarray(trimesh.creation.icosphere(subdivisions=2, radius=0.12).vertices) + np.array([0.55, 0.6, 0.35])
    group = np.concatenate([np.full(len(points), -1), np.zeros(len(eye), dtype=np.int64)])
    return np.concatenate([points, eye]), group, cv, ct


def _kabsch(rest, now, w):
    """Weighted best rigid fit (NumPy SVD): rotation and the two weighted centres."""
    c0 = (w[:, None] * rest).sum(0) / w.sum()
    c = (w[:, None] * now).sum(0) / w.sum()
    u, _, vt = np.linalg.svd(((now - c) * w[:, None]).T @ (rest - c0))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt, c0, c


@pytest.mark.parametrize("layered", [False, True], ids=["surface_normals", "inner_layer"])
def test_a_rigid_piece_moves_as_its_regions_best_rigid_fit(device, layered):
    # an eye bound as one piece: exact at rest; under a non-rigid deformation of the cage it keeps
    # its shape (every distance within it) and moves as the NumPy weighted best rigid fit of its
    # region (the cage vertices of its points' closest triangles, weighted by their barycentric
    # weights, and their inner points); bound point by point, the same eye is distorted
    points, group, cv, ct = _eye_scene()
    eye = group == 0
    emb = Embedding(points, cv, ct, inner=_inner(cv) if layered else None, rigid=group, device=device)
    assert emb.group_count == 1
    size = np.linalg.norm(np.ptp(points, axis=0))
    rest = emb.evaluate(_cage_input(cv, layered)).numpy()
    assert np.abs(rest - points).max() < 1e-6 * size

    def warp_(p):
        return p + 0.15 * np.sin(2.5 * p[:, [1, 2, 0]]) * np.array([1.0, 0.5, 0.8])

    x = _cage_input(cv, layered, warp_)
    got = emb.evaluate(x).numpy()
    # the reference: region and weights rebuilt from the brute-force closest triangles in NumPy
    _, tri, bary = closest_on_mesh(points[eye], cv, ct)
    w = np.zeros(len(cv))
    np.add.at(w, ct[tri].ravel(), bary.ravel())
    region = np.nonzero(w > 1e-9)[0]
    rest_r, now_r, wr = cv[region], x[region].astype(np.float64), w[region]
    if layered:
        rest_r = np.concatenate([rest_r, _inner(cv)[region]])
        now_r = np.concatenate([now_r, x[len(cv) + region].astype(np.float64)])
        wr = np.concatenate([wr, wr])
    rot, c0, c = _kabsch(rest_r, now_r, wr)
    want = c + (points[eye] - c0) @ rot.T
    assert np.abs(got[eye] - want).max() < 2e-5 * size
    assert np.abs(got[eye] - points[eye]).max() > 0.05  # it moved

    def spread(p):
        return np.linalg.norm(p[:, None] - p[None], axis=2)

    assert np.abs(spread(got[eye]) - spread(points[eye])).max() < 1e-5 * size  # rigid
    loose = Embedding(points, cv, ct, inner=_inner(cv) if layered else None, device=device).evaluate(x).numpy()
    assert np.abs(spread(loose[eye]) - spread(points[eye])).max() > 1e-3 * size  # point by point: distorted
    np.testing.assert_allclose(got[~eye], loose[~eye], atol=1e-6 * size)  # the rest bound as before


def test_bad_rigid_pieces_are_named():
    points, group, cv, ct = _eye_scene()
    with pytest.raises(InputError, match=r"rigid must be \[2724\] integers"):
        Embedding(points, cv, ct, rigid=group[:10])
    skipped = group.copy()
    skipped[skipped == 0] = 1
    with pytest.raises(InputError, match="rigid piece 0 has no point"):
        Embedding(points, cv, ct, rigid=skipped)

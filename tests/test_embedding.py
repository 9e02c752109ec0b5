"""The embedding of a render mesh in a cage, against NumPy references: the rest pose is
reproduced, a rigid motion of the cage moves the render points rigidly, a smooth stretch stays
within a stated bound, on every device."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.spatial.transform import Rotation

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


def test_the_rest_pose_is_reproduced(device):
    points, cv, ct = _scene()
    emb = Embedding(points, cv, ct, device=device)
    got = emb.evaluate(wp.array(cv.astype(np.float32), dtype=wp.vec3, device=device)).numpy()
    size = np.linalg.norm(np.ptp(points, axis=0))
    assert np.abs(got - points).max() < 1e-6 * size
    assert emb.distance.max() > 0.05  # the points really sit off the cage, on both sides


def test_a_rigid_motion_of_the_cage_moves_the_points_rigidly(device):
    points, cv, ct = _scene()
    emb = Embedding(points, cv, ct, device=device)
    rot = Rotation.from_rotvec([0.7, -1.1, 0.4]).as_matrix()
    shift = np.array([0.3, -2.0, 5.0])
    got = emb.evaluate((cv @ rot.T + shift).astype(np.float32)).numpy()
    want = points @ rot.T + shift
    assert np.abs(got - want).max() < 1e-5 * np.linalg.norm(np.ptp(points, axis=0))


def test_a_smooth_stretch_stays_within_the_stated_bound(device):
    # the offsets turn with the surface but keep their length: the error is at most about the
    # strain times the offset (10 % stretch: within 15 % of the largest offset)
    points, cv, ct = _scene()
    emb = Embedding(points, cv, ct, device=device)
    stretch = np.diag([1.10, 0.95, 1.0])
    got = emb.evaluate((cv @ stretch.T).astype(np.float32)).numpy()
    err = np.linalg.norm(got - points @ stretch.T, axis=1)
    assert err.max() <= 0.15 * emb.distance.max()
    assert err.max() > 1e-4  # a stretch is not a rigid motion: the bound is exercised


def test_bad_input_names_the_problem():
    points, cv, ct = _scene()
    with pytest.raises(InputError, match="render points must be finite"):
        Embedding(np.full((3, 3), np.nan), cv, ct)
    with pytest.raises(InputError, match="index vertices outside"):
        Embedding(points, cv, ct + len(cv))
    emb = Embedding(points, cv, ct)
    with pytest.raises(InputError, match=r"cage points must be \[162, 3\]"):
        emb.evaluate(np.zeros((5, 3)))

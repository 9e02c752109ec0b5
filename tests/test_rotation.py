"""Rotation extraction (Mueller et al. 2016) against scipy.linalg.polar, on every device."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

from warpskin.kernels.rotation import extract_rotations_kernel


def _run(a, q0, iterations, device, cold=0):
    a_wp = wp.array(a.astype(np.float32), dtype=wp.mat33, device=device)
    q_wp = wp.array(q0.astype(np.float32), dtype=wp.quat, device=device)
    out = wp.zeros(len(a), dtype=wp.quat, device=device)
    wp.launch(extract_rotations_kernel, dim=len(a), inputs=[a_wp, q_wp, iterations, cold], outputs=[out], device=device)
    return Rotation.from_quat(out.numpy()).as_matrix()


def _matrices(rng, n):
    """Random matrices with det > 0: generic, near-singular (one tiny singular value) and flat
    (rank 2, as a planar region gives), each times a random rotation."""
    mats = []
    for kind in ("generic", "near_singular", "flat"):
        for _ in range(n):
            u = Rotation.random(random_state=rng).as_matrix()
            v = Rotation.random(random_state=rng).as_matrix()
            s = rng.uniform(0.3, 3.0, 3)
            if kind == "near_singular":
                s[2] = 1e-4
            elif kind == "flat":
                s[2] = 0.0
            mats.append(u @ np.diag(s) @ v.T)
    return np.array(mats)


def test_equals_scipy_polar_cold_start(device):
    rng = np.random.default_rng(0)
    a = _matrices(rng, 40)
    identity = np.tile([0.0, 0.0, 0.0, 1.0], (len(a), 1))
    r = _run(a, identity, 60, device, cold=1)
    for k in range(len(a)):
        ref, _ = polar(a[k])
        if np.linalg.det(ref) < 0:
            # flat matrices: scipy returns the nearest orthogonal matrix, a reflection here; the
            # nearest rotation (unique: two singular values are non-zero) flips the null direction
            u, _, vt = np.linalg.svd(a[k])
            ref = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        assert np.abs(r[k] - ref).max() < 1e-5, k
        assert np.linalg.det(r[k]) == pytest.approx(1.0, abs=1e-5)


def test_equals_scipy_polar_from_identity_warm_start(device):
    # without svd: from the identity, iterations alone converge (generic matrices within 180 deg)
    rng = np.random.default_rng(1)
    a = []
    for _ in range(60):
        rot = Rotation.from_rotvec(rng.normal(size=3) * 0.6).as_matrix()  # |angle| mostly < 120 deg
        s = rng.uniform(0.5, 2.0, 3)
        v = Rotation.random(random_state=rng).as_matrix()
        a.append(rot @ v @ np.diag(s) @ v.T)  # rotation times a symmetric positive stretch
    a = np.array(a)
    r = _run(a, np.tile([0.0, 0.0, 0.0, 1.0], (len(a), 1)), 100, device)
    for k in range(len(a)):
        ref, _ = polar(a[k])
        assert np.abs(r[k] - ref).max() < 1e-5


def test_warm_start_converges_geometrically(device):
    # a slightly perturbed warm start (last step's rotation): every iteration cuts the error
    # by a factor (measured ~3 for stretches of +-10 %); the solver runs one per iteration, so
    # 20 elasticity iterations converge far below float32 noise
    rng = np.random.default_rng(2)
    rots = Rotation.random(50, random_state=rng)
    stretch = np.array([np.diag(rng.uniform(0.9, 1.1, 3)) for _ in range(50)])
    a = rots.as_matrix() @ stretch
    near = (rots * Rotation.from_rotvec(rng.normal(scale=0.02, size=(50, 3)))).as_quat()
    errors = [np.abs(_run(a, near, it, device) - rots.as_matrix()).max() for it in (0, 2, 4, 8, 16)]
    assert all(b < a_ / 2.5 for a_, b in zip(errors[:-1], errors[1:]))
    assert errors[-1] < 1e-6


@pytest.mark.parametrize("scale", [1e-12, 1e-6, 1e6])
def test_the_rotation_does_not_depend_on_the_matrix_scale(device, scale):
    # a moment matrix is mass x length^2: a character 18 cm tall in its file (a 0.1 scale on its
    # root) has entries near 1e-9. Each iteration's step must be the same for A and s A (the
    # polar factor of s A is A's): the warm start from a perturbed rotation, a few iterations
    rng = np.random.default_rng(3)
    rots = Rotation.random(30, random_state=rng)
    stretch = np.array([np.diag(rng.uniform(0.8, 1.2, 3)) for _ in range(30)])
    a = rots.as_matrix() @ stretch
    near = (rots * Rotation.from_rotvec(rng.normal(scale=0.2, size=(30, 3)))).as_quat()
    for iterations in (1, 3):
        unit = _run(a, near, iterations, device)
        scaled = _run(a * scale, near, iterations, device)
        assert np.abs(scaled - unit).max() < 1e-5, iterations
    assert np.abs(_run(a * scale, near, 30, device) - rots.as_matrix()).max() < 1e-5

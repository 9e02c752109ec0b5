"""Kinematic skinning baselines on Warp: linear blend skinning (LBS) and dual-quaternion
skinning (DQS).

These are the references the physical skin is compared against, and the bone-layer driver of
the multi-layer model (kinematic coupling).

Example:
    >>> from warpskin.scenes.arm import make_arm
    >>> from warpskin.skinning import Skinner
    >>> rig = make_arm()
    >>> skinner = Skinner(rig, method="dqs", device="cpu")
    >>> points = skinner.skin_at(rig.clip(), 1.0)   # wp.array of vec3, [V]
    >>> points.numpy().shape
    (2918, 3)
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .errors import InputError, SceneError
from .kernels import skinning as _k
from .device import resolve_device
from .rig import Clip, Rig
from .transforms import matrix_to_quat, quat_multiply

__all__ = ["Skinner", "SKINNING_METHODS", "dual_quaternions"]

SKINNING_METHODS = ("lbs", "dqs")


def dual_quaternions(skin_matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split skinning matrices ``[J, 4, 4]`` into DQS inputs.

    Returns:
        ``(real, dual, stretch)``: unit quaternions ``[J, 4]`` (x, y, z, w) of the rotation
        part, dual parts ``[J, 4]`` carrying the translation, and the symmetric stretch
        ``[J, 3, 3]`` left after taking the rotation out (``A = R S``, polar decomposition).
    """
    m = np.asarray(skin_matrices, dtype=np.float64)
    a = m[:, :3, :3]
    u, sig, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt))
    # proper rotation: flip the smallest singular direction when A reflects
    u[:, :, 2] *= d[:, None]
    sig[:, 2] *= d
    rot = u @ vt
    stretch = np.einsum("jki,jk,jkl->jil", vt, sig, vt)  # V^T diag(sig) V
    real = matrix_to_quat(rot)
    t = np.concatenate([m[:, :3, 3], np.zeros((m.shape[0], 1))], axis=1)
    dual = 0.5 * quat_multiply(t, real)
    return real, dual, stretch


class Skinner:
    """Skins one rig on one Warp device, frame after frame, into a preallocated output.

    Args:
        rig: The rig to skin.
        method: ``"lbs"`` or ``"dqs"``.
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:0"``); default: Warp's default.

    The per-frame host work is O(joints): sampling the clip and forward kinematics. The
    per-vertex work runs in one kernel launch.
    """

    def __init__(self, rig: Rig, *, method: str = "lbs", device: str | None = None) -> None:
        if method not in SKINNING_METHODS:
            raise SceneError(f"unknown skinning method {method!r}; choose one of {SKINNING_METHODS}")
        self.rig = rig
        self.method = method
        self.device = resolve_device(device)
        v = rig.vertex_count
        j = rig.joint_count
        with wp.ScopedDevice(self.device):
            self.rest_points = wp.array(rig.vertices.astype(np.float32), dtype=wp.vec3)
            self.joint_indices = wp.array(np.clip(rig.joint_indices, 0, max(j - 1, 0)).astype(np.int32))
            weights = np.where((rig.joint_indices >= 0) & (rig.joint_indices < j), rig.joint_weights, 0.0)
            self.joint_weights = wp.array(weights.astype(np.float32))
            self.skin_matrices = wp.zeros(j, dtype=wp.mat44)
            self.joint_real = wp.zeros(j, dtype=wp.quat)
            self.joint_dual = wp.zeros(j, dtype=wp.quat)
            self.joint_stretch = wp.zeros(j, dtype=wp.mat33)
            self.points = wp.zeros(v, dtype=wp.vec3)
        # host staging buffers, reused every frame
        self._h_mats = np.zeros((j, 4, 4), dtype=np.float32)

    def set_skin_matrices(self, skin_matrices: np.ndarray) -> None:
        """Upload per-joint skinning matrices ``G_j @ inverse_bind_j``, ``[J, 4, 4]``."""
        m = np.asarray(skin_matrices)
        if m.shape != (self.rig.joint_count, 4, 4):
            raise InputError(
                f"expected {self.rig.joint_count} skinning matrices of shape 4x4, got array of shape {m.shape}"
            )
        if not np.all(np.isfinite(m)):
            bad = np.nonzero(~np.all(np.isfinite(m.reshape(m.shape[0], -1)), axis=1))[0]
            names = [self.rig.skeleton.joint_names[k] for k in bad[:8]]
            raise InputError(f"skinning matrices of joints {names} hold NaN or inf")
        if self.method == "lbs":
            self._h_mats[:] = m
            self.skin_matrices.assign(self._h_mats)
        else:
            real, dual, stretch = dual_quaternions(m)
            self.joint_real.assign(real.astype(np.float32))
            self.joint_dual.assign(dual.astype(np.float32))
            self.joint_stretch.assign(stretch.astype(np.float32))

    def launch(self) -> wp.array:
        """Skin the rest points with the uploaded joint data into :attr:`points`."""
        if self.method == "lbs":
            wp.launch(
                _k.lbs_kernel,
                dim=self.rig.vertex_count,
                inputs=[self.rest_points, self.joint_indices, self.joint_weights, self.skin_matrices],
                outputs=[self.points],
                device=self.device,
            )
        else:
            wp.launch(
                _k.dqs_kernel,
                dim=self.rig.vertex_count,
                inputs=[
                    self.rest_points,
                    self.joint_indices,
                    self.joint_weights,
                    self.joint_real,
                    self.joint_dual,
                    self.joint_stretch,
                ],
                outputs=[self.points],
                device=self.device,
            )
        return self.points

    def skin(self, skin_matrices: np.ndarray) -> wp.array:
        """Skin with explicit skinning matrices ``[J, 4, 4]``; returns :attr:`points` ``[V]`` vec3 [m]."""
        self.set_skin_matrices(skin_matrices)
        return self.launch()

    def skin_at(self, clip: Clip | str | None, t: float) -> wp.array:
        """Skin at time ``t`` [s] of ``clip``; returns :attr:`points` ``[V]`` vec3 [m]."""
        return self.skin(self.rig.skinning_matrices(clip, t))

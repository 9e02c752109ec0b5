"""Example-based skinning: pose space deformation (Lewis, Cordner & Fong 2000) of the popping
examples over joint rotations with radial basis functions, skinned on Warp."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import warp as wp

from ..kernels import popping as _k
from ..rig import Clip, Rig, RigError
from ..skinning import Skinner
from .examples import MAX_GROUPS, PoppingExamples


# --------------------------------------------------------------------------------------------
# Pose space
# --------------------------------------------------------------------------------------------
def pose_rotations(rig: Rig, skin_matrices: np.ndarray, joints: Sequence[int] | None = None) -> np.ndarray:
    """Local joint rotations of a pose given by its skinning matrices.

    Args:
        rig: The rig (for the bind pose and the hierarchy).
        skin_matrices: ``G_j @ inverse_bind_j``, ``[..., J, 4, 4]``.
        joints: Joint indices to return (default: all).

    Returns:
        Unit quaternions (x, y, z, w) of each joint's rotation relative to its parent,
        ``[..., K, 4]`` (the polar rotation factor when the joint also scales).
    """
    idx = np.arange(rig.joint_count) if joints is None else np.asarray(joints, dtype=np.int64)
    return _local_rotations(np.asarray(skin_matrices, dtype=np.float64), np.linalg.inv(rig.inverse_bind),
                            rig.skeleton.parents, rig.skeleton.root_transform, idx)


def _local_rotations(m: np.ndarray, bind: np.ndarray, parents: np.ndarray, root: np.ndarray, idx: np.ndarray) -> np.ndarray:
    world = m[..., idx, :, :] @ bind[idx]  # G_j = M_j @ bind_j
    p = parents[idx]
    pp = np.maximum(p, 0)
    parent_world = np.where((p >= 0)[:, None, None], m[..., pp, :, :] @ bind[pp], root[idx])
    local = np.linalg.solve(parent_world, world)[..., :3, :3]
    u, _, vt = np.linalg.svd(local)
    d = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= d[..., None]
    rot = u @ vt
    flat = rot.reshape(-1, 3, 3)
    quats = np.empty((flat.shape[0], 4))
    for k, r in enumerate(flat.tolist()):  # joints are few: scalar Shepperd beats NumPy here
        quats[k] = _shepperd(r)
    return quats.reshape(rot.shape[:-2] + (4,))


def _shepperd(r: list) -> tuple[float, float, float, float]:
    """Unit quaternion (x, y, z, w), up to sign, of a 3x3 rotation given as nested lists."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
    tr = r00 + r11 + r22
    if tr >= max(r00, r11, r22):
        q = (r21 - r12, r02 - r20, r10 - r01, 1.0 + tr)
    elif r00 >= r11 and r00 >= r22:
        q = (1.0 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12)
    elif r11 >= r22:
        q = (r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21, r02 - r20)
    else:
        q = (r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22, r10 - r01)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _rotation_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose distance [rad]: sqrt of the summed squared rotation angles between joint rotations
    ``a`` ``[..., K, 4]`` and ``b`` (broadcast); ``2 atan2(|vec(conj(a) b)|, |w|)`` is accurate
    near zero, unlike ``acos``."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    # conj(a) * b
    x = aw * bx - ax * bw - ay * bz + az * by
    y = aw * by + ax * bz - ay * bw - az * bx
    z = aw * bz - ax * by + ay * bx - az * bw
    w = aw * bw + ax * bx + ay * by + az * bz
    angle = 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), np.abs(w))
    return np.sqrt(np.sum(angle * angle, axis=-1))


def _conj_left_matrices(q: np.ndarray) -> np.ndarray:
    """``L [..., 4, 4]`` with ``L @ b = conj(q) * b`` (Hamilton product, x, y, z, w order)."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [w, z, -y, -x],
        [-z, w, x, -y],
        [y, -x, w, -z],
        [x, y, z, w],
    ]
    return np.stack([np.stack(row, -1) for row in rows], -2)


def _radial_basis(poses: np.ndarray, width: float | None, label: str) -> tuple[float, np.ndarray, np.ndarray]:
    """Solve the Gaussian RBF system of one example set once (Lewis et al. 2000).

    ``f(p) = c + sum_k lambda_k phi(|p - p_k|)``, ``sum_k lambda_k = 0``, ``phi(r) = exp(-(r /
    sigma)^2)``, solved for the identity right-hand side: that gives *cardinal* weights
    ``w(p) = phi(|p - p_.|) @ lam + const`` with ``f(p) = sum_e w_e(p) f_e``, ``w_e(p_k) =
    delta_ek`` and ``sum_e w_e(p) = 1`` everywhere (the constant term reproduces constants), so
    one example gives its value everywhere. The Gaussian is positive definite, so the system is
    regular for distinct poses.

    Args:
        poses: Joint rotations of the examples, ``[E, K, 4]``.
        width: sigma [rad]; ``None``: the mean distance from each example to its nearest one.
        label: Names the example set in errors.

    Returns:
        ``(sigma, lam [E, E], const [E])``.
    """
    e = poses.shape[0]
    dist = _rotation_distance(poses[:, None], poses[None, :])
    if e > 1:
        off = dist + np.diag(np.full(e, np.inf))
        if off.min() < 1e-9:
            i, j = np.unravel_index(np.argmin(off), off.shape)
            raise RigError(f"{label}: examples {i} and {j} are at the same pose of the interpolated joints")
        width = float(np.mean(off.min(axis=1))) if width is None else width
    width = 1.0 if width is None else float(width)
    if not (math.isfinite(width) and width > 0.0):
        raise RigError(f"rbf_width must be a positive number of radians, got {width}")
    a = np.zeros((e + 1, e + 1))
    a[:e, :e] = np.exp(-((dist / width) ** 2))
    a[:e, e] = 1.0
    a[e, :e] = 1.0
    rhs = np.zeros((e + 1, e))
    rhs[:e] = np.eye(e)
    x = np.linalg.solve(a, rhs)
    return width, x[:e], x[e]


def _tents(row_group: np.ndarray, row_weight: np.ndarray) -> np.ndarray:
    """``[R, 4]`` each disparity row's ``(lo, 1 / (w - lo), hi, 1 / (hi - w))``: ``lo`` and
    ``hi`` the weights of the rows below and above it in its group (0 below the first; 2
    above the clenched row, ``w = 1``), so its goal coefficient ``min((a - lo) / (w - lo),
    (hi - a) / (hi - w))`` clamped to [0, 1] is a tent in the group's activation ``a``."""
    lo = np.zeros(len(row_group))
    hi = np.full(len(row_group), 2.0)
    for r in range(len(row_group)):
        if r > 0 and row_group[r - 1] == row_group[r]:
            lo[r] = row_weight[r - 1]
        if r + 1 < len(row_group) and row_group[r + 1] == row_group[r]:
            hi[r] = row_weight[r + 1]
    return np.stack([lo, 1.0 / (row_weight - lo), hi, 1.0 / (hi - row_weight)], axis=1)


class PoseSpaceDeformer:
    """Example-based skinning: pose space deformation of the normal and clenched examples,
    then linear blend skinning, on one Warp device.

    Per frame, :meth:`set_pose` turns the pose into RBF weights on the host (O(joints +
    examples)) and launches one kernel that writes, per vertex: the interpolated rest-frame
    normal displacement, the per-group disparities, the normal mesh (:attr:`normal_points`),
    the fully clenched mesh (:attr:`clenched_points`) and the per-group ``dist_max`` of eq. 3.

    Args:
        rig: The rig.
        examples: Its examples (:func:`examples_from_meshes`).
        device: Warp device.
        joints: Names of the joints whose local rotations span pose space. Default: the joints
            whose rotation differs between examples (all joints if none does).
        rbf_width: Gaussian width sigma [rad]; default: the mean distance from each example to
            its nearest neighbour in pose space (per example set).

    Attributes:
        normal_points: Example-based normal mesh [m], ``[V]`` vec3.
        clenched_points: Example-based mesh with every group clenched [m], ``[V]`` vec3.
        normal_displacement: Interpolated rest-frame normal displacement [m], ``[V]`` vec3.
        disparity: Interpolated rest-frame ``clenched - normal`` per row [m], ``[R, V]`` vec3:
            per group its inbetweens by weight (:attr:`PoppingExamples.clenched_inbetweens`),
            then its clenched shape; one row per group (``R = G``) where none has inbetweens.
        disparity_max: ``max_i |L_i D_r,i|`` per row [m], ``[R]``.
        row_group: The group of each row, ``[R]`` int.
        row_weight: The activation at which each row is the group's goal, ``[R]`` (1: its
            clenched shape).
        row_full: Whether each row is its group's clenched shape, ``[R]`` bool.
        row_tent: Each row's goal coefficient as a tent in its group's activation: 0 at ``lo``
            rising to 1 at its weight ``w`` and falling to 0 at ``hi`` (2 for a clenched row:
            it stays 1), as ``(lo, 1 / (w - lo), hi, 1 / (hi - w))``, ``[R]`` vec4
            (:func:`_tents`, :func:`warpskin.kernels.popping.popping_step_kernel`).
    """

    def __init__(
        self,
        rig: Rig,
        examples: PoppingExamples,
        *,
        device=None,
        joints: Sequence[str] | None = None,
        rbf_width: float | None = None,
    ) -> None:
        if examples.vertex_count != rig.vertex_count:
            raise RigError(
                f"popping examples have {examples.vertex_count} vertices but the rig {rig.name!r} has "
                f"{rig.vertex_count}; build them with examples_from_meshes(rig, ...)"
            )
        if examples.group_count == 0:
            raise RigError("popping examples hold no clenched group")
        if examples.group_count > MAX_GROUPS:
            raise RigError(f"{examples.group_count} muscle groups; at most {MAX_GROUPS} are supported")
        self.rig = rig
        self.examples = examples
        self.skinner = Skinner(rig, method="lbs", device=device)
        self.device = self.skinner.device
        self.group_names = list(examples.group_names)
        self._bind = np.linalg.inv(rig.inverse_bind)
        sk = rig.skeleton
        all_mats = np.concatenate([examples.normal_matrices, *examples.clenched_matrices])
        all_rot = _local_rotations(all_mats, self._bind, sk.parents, sk.root_transform, np.arange(rig.joint_count))
        if joints is None:
            spread = _rotation_distance(all_rot[:, None, :, None], all_rot[None, :, :, None]).max(axis=(0, 1))
            idx = np.nonzero(spread > 1e-6)[0]
            if idx.size == 0:
                idx = np.arange(rig.joint_count)
        else:
            if len(joints) == 0:
                raise RigError("popping: joints must name at least one joint")
            idx = np.array([sk.index(n) for n in joints])
        self.joints = idx
        self.joint_names = [sk.joint_names[j] for j in idx]
        # the disparity rows: per group its inbetweens by weight, then its clenched shape
        rows = []  # (group, weight, disparities [E_g, V, 3])
        for g in range(examples.group_count):
            rows += [(g, float(w), d) for w, d in examples.inbetweens(g)]
            rows.append((g, 1.0, examples.clenched_disparities[g]))
        self.row_group = np.array([g for g, _, _ in rows], dtype=np.int32)
        self.row_weight = np.array([w for _, w, _ in rows])
        self.row_full = self.row_weight == 1.0
        self._full_rows = np.nonzero(self.row_full)[0]
        # one RBF per example set (normal, then each row), solved once; per frame all sets'
        # cardinal weights come from one distance evaluation and one block-diagonal product
        en = examples.normal_count
        sizes = [en] + [len(examples.clenched_matrices[g]) for g, _, _ in rows]
        labels = ["normal examples"] + [f"clenched examples of group {examples.group_names[g]!r}" for g, _, _ in rows]
        e_all = sum(sizes)
        first = np.cumsum([en] + [len(m) for m in examples.clenched_matrices])  # group g's first example
        order = np.concatenate([np.arange(en)] + [first[g] + np.arange(len(examples.clenched_matrices[g]))
                                                  for g, _, _ in rows])
        self._poses = all_rot[order][:, idx]
        self._conj_left = _conj_left_matrices(self._poses)  # [E_all, K, 4, 4]
        self._width = np.zeros(e_all)
        self._lam = np.zeros((e_all, e_all))
        self._const = np.zeros(e_all)
        self._slices = []
        start = 0
        for size, label in zip(sizes, labels):
            sl = slice(start, start + size)
            self._width[sl], self._lam[sl, sl], self._const[sl] = _radial_basis(self._poses[sl], rbf_width, label)
            self._slices.append(sl)
            start += size
        self.rbf_width = float(self._width[0])

        v, r = rig.vertex_count, len(rows)
        c_disp = np.concatenate([d for _, _, d in rows])
        c_group = np.concatenate([np.full(len(d), k, dtype=np.int32) for k, (_, _, d) in enumerate(rows)])
        with wp.ScopedDevice(self.device):
            self.normal_examples = wp.array(examples.normal_displacements.astype(np.float32), dtype=wp.vec3)
            self.clenched_examples = wp.array(c_disp.astype(np.float32), dtype=wp.vec3)
            self.clenched_group = wp.array(c_group, dtype=wp.int32)  # the row of each clenched example
            self.row_group_device = wp.array(self.row_group, dtype=wp.int32)
            self.row_full_device = wp.array(self.row_full.astype(np.int32), dtype=wp.int32)
            self.row_tent = wp.array(_tents(self.row_group, self.row_weight).astype(np.float32), dtype=wp.vec4)
            self.example_weights = wp.zeros(e_all, dtype=wp.float32)  # normal, then clenched
            self.normal_displacement = wp.zeros(v, dtype=wp.vec3)
            self.disparity = wp.zeros((r, v), dtype=wp.vec3)
            self.disparity_max = wp.zeros(r, dtype=wp.float32)
            self.normal_points = wp.zeros(v, dtype=wp.vec3)
            self.clenched_points = wp.zeros(v, dtype=wp.vec3)
        self.normal_weights = self.example_weights[:en]  # views, made once
        self.clenched_weights = self.example_weights[en:]
        # host side of the weights: on the CPU the device array itself, else a staging copy
        self._h_weights = self.example_weights.numpy() if self.device.is_cpu else np.zeros(e_all, dtype=np.float32)
        self.pose_weights: tuple[np.ndarray, list[np.ndarray]] | None = None
        s = self.skinner
        self._launch = wp.launch(
            _k.pose_space_kernel,
            dim=rig.vertex_count,
            inputs=[s.rest_points, s.joint_indices, s.joint_weights, s.skin_matrices, self.normal_examples,
                    self.normal_weights, self.clenched_examples, self.clenched_group, self.clenched_weights,
                    self.row_full_device],
            outputs=[self.normal_displacement, self.disparity, self.disparity_max, self.normal_points,
                     self.clenched_points],
            device=self.device,
            record_cmd=True,
        )

    @property
    def group_count(self) -> int:
        return len(self.group_names)

    def weights(self, skin_matrices: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """Cardinal RBF weights of the pose: normal ``[E]`` and per group ``[E_g]``."""
        w = self._weights(np.asarray(skin_matrices, dtype=np.float64))
        return w[self._slices[0]], [w[self._slices[1 + r]] for r in self._full_rows]

    def _weights(self, skin_matrices: np.ndarray) -> np.ndarray:
        sk = self.rig.skeleton
        rot = _local_rotations(skin_matrices, self._bind, sk.parents, sk.root_transform, self.joints)
        rel = np.einsum("ekij,kj->eki", self._conj_left, rot)  # conj(example) * pose
        angle = 2.0 * np.arctan2(np.linalg.norm(rel[..., :3], axis=-1), np.abs(rel[..., 3]))
        r = np.sqrt(np.sum(angle * angle, axis=-1))
        return np.exp(-((r / self._width) ** 2)) @ self._lam + self._const

    def set_pose(self, skin_matrices: np.ndarray) -> wp.array:
        """Interpolate the examples at a pose and skin them.

        Args:
            skin_matrices: ``G_j @ inverse_bind_j`` of the pose, ``[J, 4, 4]``.

        Returns:
            :attr:`normal_points` (``[V]`` vec3 [m]); :attr:`clenched_points` and the
            disparities are updated too.
        """
        self.skinner.set_skin_matrices(skin_matrices)
        w = self._weights(np.asarray(skin_matrices, dtype=np.float64))
        self.pose_weights = (w[self._slices[0]], [w[self._slices[1 + r]] for r in self._full_rows])
        self._h_weights[:] = w
        if not self.device.is_cpu:
            self.example_weights.assign(self._h_weights)
        return self.launch()

    def set_pose_at(self, clip: Clip | str | None, t: float) -> wp.array:
        """:meth:`set_pose` at time ``t`` [s] of ``clip``."""
        return self.set_pose(self.rig.skinning_matrices(clip, t))

    def launch(self) -> wp.array:
        """Run the pose space kernel with the uploaded pose and weights; returns :attr:`normal_points`."""
        self.disparity_max.zero_()
        self._launch.launch()
        return self.normal_points

    def lbs(self) -> wp.array:
        """Plain linear blend skinning of the rest mesh at the current pose (the baseline),
        ``[V]`` vec3 [m]."""
        return self.skinner.launch()

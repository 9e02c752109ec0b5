"""Dynamic skinning for popping dance (Son & Han 2007) on Warp.

The paper takes a *normal* mesh and a *clenched* mesh (isometric contraction: the muscles bulge,
the bones stay put) and makes the skin vibrate toward the clenched surface when the dancer pops,
and slide back without vibration when the dancer relaxes:

* **Example-based skinning** (the paper's section 3, Fig. 7): example pairs (normal, clenched) at
  a few skeleton poses, interpolated over pose space with radial basis functions and skinned:
  pose space deformation (Lewis, Cordner & Fong 2000). :class:`PoppingExamples`,
  :func:`examples_from_meshes`, :class:`PoseSpaceDeformer`.
* **Skin vibration** (eqs. 1-4): per-vertex stiffness from the normal/clenched disparity (eq. 3),
  a damped goal-seeking step while clenched (eqs. 1-2), a monotone slide back to the normal
  mesh while relaxing (eq. 4). :class:`PoppingDynamics`, one Warp kernel per step.
* **Activation**: a clench/relax signal per muscle group over time, keyed to music beats.
  :class:`ActivationTimeline`.
* :func:`run_popping` plays a scene to USD (``warpskin pop``), :func:`bench_popping` times it.

Where this differs from the paper, and why:

* The dynamic state is the **popping offset in the rest frame** (a displacement added to the
  example-based normal displacement before skinning), not the world position. With the bones
  still (isometric contraction, the paper's case) the world-space update of eqs. 1-4 is the
  rest-frame update multiplied by the constant 3x3 blend matrix ``L_i`` (the update is linear),
  so the two are identical. With moving bones, the skeletal motion stays kinematic: a relaxing
  vertex (eq. 4 is a first-order lag) does not trail behind a moving bone.
* Several **muscle groups** (biceps, triceps), each with its own clenched examples and its own
  activation. The goal offset is ``sum_g a_g D_g`` (``D_g``: clenched minus normal of group g);
  a vertex takes its stiffness and its clench/relax mode from the group that moves it most, and
  ``dist_max`` of eq. 3 is taken per group, so the belly of every muscle gets ``alpha_min``.
  With one group and a 0/1 activation this is the paper's model.
* Activations in [0, 1] (ramps), not just 0/1: a group is *clenching* (eqs. 1-2) from the step
  its activation rises until it falls, then *relaxing* (eq. 4) until it rises again; the goal
  moves with the activation.
* The paper states that the eigenvalues of eqs. 1-2, ``1 - alpha +- i sqrt(alpha (1 - alpha))``,
  have magnitude ``1 - alpha``; their modulus is ``sqrt(1 - alpha)`` (the determinant of the
  system matrix is ``1 - alpha``). From rest the error after n steps is exactly
  ``e_n = e_0 (1 - alpha)^(n/2) cos(n theta)``, ``tan(theta) = sqrt(alpha / (1 - alpha))``;
  ``tests/test_popping.py`` checks the kernel against it.
* ``alpha`` is a per-step quantity, as in the paper: the vibration period is ``2 pi / theta``
  steps, so the scene fixes the step ``dt``. ``beta`` is a rate [1/s] and needs
  ``0 < beta * dt <= 1`` (the paper's "beta between 0 and 1" with h = one step).

References:
    H. Son, J. Han. Dynamic Skinning for Popping Dance. Technologies for E-Learning and Digital
    Entertainment (Edutainment) 2007, LNCS 4469.
    J. P. Lewis, M. Cordner, N. Fong. Pose Space Deformation: A Unified Approach to Shape
    Interpolation and Skeleton-Driven Deformation. SIGGRAPH 2000.

Example:
    >>> from warpskin.scenes.popping_arm import make_popping_arm, popping_arm_examples
    >>> rig = make_popping_arm()
    >>> deformer = PoseSpaceDeformer(rig, popping_arm_examples(rig), device="cpu")
    >>> dynamics = PoppingDynamics(deformer, alpha_min=0.1, beta=30.0)
    >>> deformer.set_pose(rig.skinning_matrices("pop", 0.0))
    >>> for _ in range(100):
    ...     points = dynamics.step(1.0 / 240.0, {"biceps": 1.0})   # wp.array of vec3 [V]
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from .device import resolve_device
from .kernels import popping as _k
from .rig import Clip, Rig, RigError
from .scene import resolve_scene
from .skinning import Skinner
from .transforms import blend_skinning_matrices, linear_blend_skin

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "PoppingExamples",
    "examples_from_meshes",
    "pose_rotations",
    "PoseSpaceDeformer",
    "PoppingDynamics",
    "ActivationTimeline",
    "PoppingSettings",
    "PoppingRun",
    "popping_settings",
    "examples_for_scene",
    "run_popping",
    "bench_popping",
    "Activation",
    "MAX_GROUPS",
    "EXAMPLE_GENERATORS",
]

Activation = float | Sequence[float] | Mapping[str, float] | np.ndarray
"""Muscle activations in [0, 1]: one number for every group, one per group in order, or by
group name (missing groups: 0)."""

MAX_GROUPS = _k.GROUP_CAPACITY
"""Most muscle groups one :class:`PoppingDynamics` drives (activations travel as a kernel
argument, a fixed-size vector, so a step uploads nothing)."""

EXAMPLE_GENERATORS = {"popping_arm": "warpskin.scenes.popping_arm:popping_arm_examples"}
"""Rig generators (``[rig] generator`` of a scene) that also build popping examples: name ->
``module:function(rig, **params) -> PoppingExamples``."""

_SAME_POSE = 1e-6  # relative max-abs difference of skinning matrices that counts as one pose


# --------------------------------------------------------------------------------------------
# Examples
# --------------------------------------------------------------------------------------------
@dataclass
class PoppingExamples:
    """Example pairs in the rest frame, ready for pose space deformation.

    Every example is stored as the displacement that, added to the rest mesh before linear
    blend skinning with the example's pose, reproduces the example mesh exactly:
    ``d_i = L_i^-1 (x_i - LBS(r)_i)`` with ``L_i = sum_j w_ij A_j`` the blended linear part of
    the skinning matrices (LBS is affine in the rest position for fixed weights).

    Attributes:
        vertex_count: ``V``, the rig's vertex count.
        normal_matrices: Skinning matrices of the normal examples' poses, ``[E, J, 4, 4]``.
        normal_displacements: Rest-frame displacements of the normal examples [m], ``[E, V, 3]``.
        group_names: Muscle group names, ``[G]`` (one activation signal each).
        clenched_matrices: Per group, skinning matrices of its clenched examples,
            ``[E_g, J, 4, 4]``.
        clenched_disparities: Per group, rest-frame ``clenched - normal`` displacements of its
            examples [m], ``[E_g, V, 3]`` (each clenched example minus the normal example at the
            same pose, its *partner*).
    """

    vertex_count: int
    normal_matrices: np.ndarray
    normal_displacements: np.ndarray
    group_names: list[str]
    clenched_matrices: list[np.ndarray]
    clenched_disparities: list[np.ndarray]

    @property
    def group_count(self) -> int:
        return len(self.group_names)

    @property
    def normal_count(self) -> int:
        return int(self.normal_matrices.shape[0])


def _lbs_parts(rig: Rig, mats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex blended linear part ``L`` ``[V, 3, 3]`` and the skinned rest mesh ``[V, 3]``."""
    blend = blend_skinning_matrices(rig.joint_indices, rig.joint_weights, mats)  # [V, 4, 4]
    lin = blend[:, :3, :3]
    skinned = np.einsum("vij,vj->vi", lin, rig.vertices) + blend[:, :3, 3]
    return lin, skinned


def _pose_matrices(rig: Rig, pose, clip: Clip | str | None, label: str) -> np.ndarray:
    if isinstance(pose, (int, float, np.integer, np.floating)) and not isinstance(pose, bool):
        t = float(pose)
        if not math.isfinite(t):
            raise RigError(f"{label}: pose time {pose!r} is not a finite number")
        return rig.skinning_matrices(clip, t)
    m = np.asarray(pose, dtype=np.float64)
    if m.shape != (rig.joint_count, 4, 4):
        raise RigError(
            f"{label}: the pose must be a clip time [s] or skinning matrices of shape "
            f"({rig.joint_count}, 4, 4), got {type(pose).__name__} of shape {np.shape(pose)}"
        )
    if not np.all(np.isfinite(m)):
        raise RigError(f"{label}: the pose's skinning matrices hold NaN or inf")
    return m


def _rest_displacement(rig: Rig, points, mats: np.ndarray, label: str) -> np.ndarray:
    x = np.asarray(points, dtype=np.float64)
    v = rig.vertex_count
    if x.ndim != 2 or x.shape[1] != 3:
        raise RigError(f"{label}: points must have shape [V, 3], got {x.shape}")
    if x.shape[0] != v:
        raise RigError(
            f"{label}: {x.shape[0]} vertices, but the rig {rig.name!r} has {v}; an example must have "
            "the rig's topology (the same vertices in the same order)"
        )
    bad = np.nonzero(~np.all(np.isfinite(x), axis=1))[0]
    if bad.size:
        raise RigError(f"{label}: vertices {bad[:8].tolist()} have NaN or inf positions")
    lin, skinned = _lbs_parts(rig, mats)
    det = np.linalg.det(lin)
    sing = np.nonzero(np.abs(det) < 1e-12)[0]
    if sing.size:
        raise RigError(
            f"{label}: the blended skinning matrix is singular at vertices {sing[:8].tolist()}; "
            "the example pose cannot be undone there"
        )
    return np.linalg.solve(lin, (x - skinned)[:, :, None])[:, :, 0]


def _same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    return float(np.abs(a - b).max()) <= _SAME_POSE * (1.0 + float(np.abs(a).max()))


def examples_from_meshes(
    rig: Rig,
    normal: Sequence[tuple[np.ndarray, object]],
    clenched: Sequence[tuple[np.ndarray, object]] | Mapping[str, Sequence[tuple[np.ndarray, object]]],
    *,
    clip: Clip | str | None = None,
) -> PoppingExamples:
    """Turn example meshes into rest-frame displacements (undo each example pose's skinning).

    Args:
        rig: The rig the examples belong to; every example must have its vertex count and order.
        normal: Normal examples, ``(points, pose)`` pairs: points ``[V, 3]`` [m] in the skinned
            (world) space of the pose; pose a time [s] of ``clip`` or skinning matrices
            ``[J, 4, 4]`` (``G_j @ inverse_bind_j``).
        clenched: Clenched examples, the same pairs: a list (one muscle group, ``"muscle"``) or
            a mapping from group name to its list. Each clenched example needs a normal example
            at the same pose (its partner).
        clip: Clip whose times the poses are (default: the rig's first clip).

    Returns:
        The examples, with per-group disparities ``clenched - normal`` in the rest frame.

    Raises:
        RigError: naming the example: wrong vertex count (topology), wrong shapes, NaN, a
            clenched example without a normal partner, two examples of a set at one pose, or
            no examples at all.
    """
    groups = dict(clenched) if isinstance(clenched, Mapping) else {"muscle": list(clenched)}
    if len(normal) == 0:
        raise RigError("popping examples: no normal examples; give at least one (points, pose) pair")
    if not groups or all(len(v) == 0 for v in groups.values()):
        raise RigError("popping examples: no clenched examples; give at least one (points, pose) pair")
    if len(groups) > MAX_GROUPS:
        raise RigError(f"popping examples: {len(groups)} muscle groups; at most {MAX_GROUPS} are supported")

    def unpack(item, label):
        if not isinstance(item, (tuple, list)) or len(item) != 2:
            raise RigError(f"{label}: expected a (points, pose) pair, got {type(item).__name__}")
        return item

    n_mats, n_disp = [], []
    for k, item in enumerate(normal):
        label = f"normal example {k}"
        pts, pose = unpack(item, label)
        m = _pose_matrices(rig, pose, clip, label)
        for k2, m2 in enumerate(n_mats):
            if _same_pose(m, m2):
                raise RigError(f"{label} is at the same pose as normal example {k2}; keep one example per pose")
        n_mats.append(m)
        n_disp.append(_rest_displacement(rig, pts, m, label))

    names, c_mats, c_disp = [], [], []
    for name, items in groups.items():
        if not isinstance(name, str) or not name:
            raise RigError(f"popping examples: muscle group names must be non-empty strings, got {name!r}")
        if len(items) == 0:
            raise RigError(f"popping examples: muscle group {name!r} has no clenched examples")
        gm, gd = [], []
        for k, item in enumerate(items):
            label = f"clenched example {k} of group {name!r}"
            pts, pose = unpack(item, label)
            m = _pose_matrices(rig, pose, clip, label)
            partner = next((e for e, m2 in enumerate(n_mats) if _same_pose(m, m2)), None)
            if partner is None:
                raise RigError(
                    f"{label} has no normal partner: none of the {len(n_mats)} normal examples is at its pose; "
                    "give the normal mesh at the same pose"
                )
            for k2, m2 in enumerate(gm):
                if _same_pose(m, m2):
                    raise RigError(f"{label} is at the same pose as clenched example {k2} of the same group")
            gm.append(m)
            gd.append(_rest_displacement(rig, pts, m, label) - n_disp[partner])
        names.append(name)
        c_mats.append(np.stack(gm))
        c_disp.append(np.stack(gd))
    return PoppingExamples(
        vertex_count=rig.vertex_count,
        normal_matrices=np.stack(n_mats),
        normal_displacements=np.stack(n_disp),
        group_names=names,
        clenched_matrices=c_mats,
        clenched_disparities=c_disp,
    )


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
        disparity: Interpolated rest-frame ``clenched - normal`` per group [m], ``[G, V]`` vec3.
        disparity_max: ``max_i |L_i D_g,i|`` per group [m], ``[G]``.
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
        # one RBF per example set (normal, then each group), solved once; per frame all sets'
        # cardinal weights come from one distance evaluation and one block-diagonal product
        en = examples.normal_count
        sizes = [en] + [len(m) for m in examples.clenched_matrices]
        labels = ["normal examples"] + [f"clenched examples of group {n!r}" for n in examples.group_names]
        e_all = sum(sizes)
        self._poses = all_rot[:, idx]
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

        v, g = rig.vertex_count, examples.group_count
        c_disp = np.concatenate(examples.clenched_disparities)
        c_group = np.concatenate([np.full(len(d), k, dtype=np.int32) for k, d in enumerate(examples.clenched_disparities)])
        with wp.ScopedDevice(self.device):
            self.normal_examples = wp.array(examples.normal_displacements.astype(np.float32), dtype=wp.vec3)
            self.clenched_examples = wp.array(c_disp.astype(np.float32), dtype=wp.vec3)
            self.clenched_group = wp.array(c_group, dtype=wp.int32)
            self.example_weights = wp.zeros(e_all, dtype=wp.float32)  # normal, then clenched
            self.normal_displacement = wp.zeros(v, dtype=wp.vec3)
            self.disparity = wp.zeros((g, v), dtype=wp.vec3)
            self.disparity_max = wp.zeros(g, dtype=wp.float32)
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
                    self.normal_weights, self.clenched_examples, self.clenched_group, self.clenched_weights],
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
        return w[self._slices[0]], [w[sl] for sl in self._slices[1:]]

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
        self.pose_weights = (w[self._slices[0]], [w[sl] for sl in self._slices[1:]])
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


# --------------------------------------------------------------------------------------------
# Dynamics
# --------------------------------------------------------------------------------------------
def _check_dynamics(alpha_min: float, beta: float, threshold: float, where: str = "popping") -> None:
    if isinstance(alpha_min, bool) or not isinstance(alpha_min, (int, float)) or not (0.0 < alpha_min <= 1.0):
        raise RigError(f"{where}: alpha_min must be in (0, 1] (the stiffness at the largest disparity), got {alpha_min!r}")
    if isinstance(beta, bool) or not isinstance(beta, (int, float)) or not (math.isfinite(beta) and beta > 0.0):
        raise RigError(f"{where}: beta must be a positive relaxation rate [1/s], got {beta!r}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not (math.isfinite(threshold) and threshold >= 0.0):
        raise RigError(f"{where}: threshold must be a distance >= 0 [m], got {threshold!r}")


class PoppingDynamics:
    """Skin vibration of the popping dance (Son & Han 2007, eqs. 1-4), one kernel per step.

    The state is the rest-frame popping offset ``o`` and its velocity ``u`` per vertex; the
    skinned vertex is ``LBS(r + n + o)`` with ``n`` the example-based normal displacement of
    the deformer's current pose. Every array is allocated here; :meth:`step` allocates nothing
    and uploads nothing (the activations travel as kernel arguments).

    Args:
        deformer: The example-based skinning, posed by :meth:`PoseSpaceDeformer.set_pose`
            before the first step and whenever the pose changes.
        alpha_min: Stiffness at the largest disparity, in (0, 1] (eq. 3); 1 means no vibration.
        beta: Relaxation rate [1/s] (eq. 4); each step needs ``0 < beta * dt <= 1``.
        threshold: Relaxing vertices closer than this to their goal snap onto it [m].

    Attributes:
        points: Skinned dynamic skin [m], ``[V]`` vec3 (written by :meth:`step`).
        goal_points: Skinned goal of the step (normal mesh plus the activated disparities) [m].
        offset: Rest-frame popping offset [m], ``[V]`` vec3.
        velocity: Rest-frame offset velocity [m/s], ``[V]`` vec3.
        alpha: Per-vertex stiffness of the last step (eq. 3), ``[V]``.

    Limitations:
        ``alpha`` acts per step: the vibration's period and decay are counted in steps, so keep
        ``dt`` fixed for a scene. The pose is constant over the steps between two
        :meth:`PoseSpaceDeformer.set_pose` calls.
    """

    def __init__(self, deformer: PoseSpaceDeformer, *, alpha_min: float = 0.1, beta: float = 30.0,
                 threshold: float = 1e-4) -> None:
        _check_dynamics(alpha_min, beta, threshold)
        self.deformer = deformer
        self.alpha_min = float(alpha_min)
        self.beta = float(beta)
        self.threshold = float(threshold)
        self.device = deformer.device
        v = deformer.rig.vertex_count
        with wp.ScopedDevice(self.device):
            self.offset = wp.zeros(v, dtype=wp.vec3)
            self.velocity = wp.zeros(v, dtype=wp.vec3)
            self.points = wp.zeros(v, dtype=wp.vec3)
            self.goal_points = wp.zeros(v, dtype=wp.vec3)
            self.alpha = wp.ones(v, dtype=wp.float32)
        g = deformer.group_count
        self._index = {n: k for k, n in enumerate(deformer.group_names)}
        self._act = np.zeros(_k.GROUP_CAPACITY, dtype=np.float32)
        self._prev = np.zeros(_k.GROUP_CAPACITY, dtype=np.float32)
        self._clench = np.zeros(_k.GROUP_CAPACITY, dtype=np.float32)
        self._g = g
        self.steps = 0
        d, sk = deformer, deformer.skinner
        # recorded once; a step only re-packs the activations and h (cheaper than wp.launch)
        self._launch = wp.launch(
            _k.popping_step_kernel,
            dim=d.rig.vertex_count,
            inputs=[sk.rest_points, sk.joint_indices, sk.joint_weights, sk.skin_matrices, d.normal_displacement,
                    d.disparity, d.disparity_max, _k.group_vector(), _k.group_vector(), self.alpha_min, self.beta,
                    self.threshold, 1.0],
            outputs=[self.offset, self.velocity, self.points, self.goal_points, self.alpha],
            device=self.device,
            record_cmd=True,
        )
        names = [a.label for a in _k.popping_step_kernel.adj.args]
        self._i_act, self._i_clench, self._i_h = (names.index(n) for n in ("group_activation", "group_clenching", "h"))

    @property
    def clenching(self) -> np.ndarray:
        """Per group: True while clenching (eqs. 1-2), False while relaxing (eq. 4), ``[G]``."""
        return self._clench[: self._g] != 0.0

    def reset(self) -> None:
        """Back to the normal mesh, at rest, every group relaxed."""
        self.offset.zero_()
        self.velocity.zero_()
        self._prev[:] = 0.0
        self._clench[:] = 0.0
        self.steps = 0

    def _set_activation(self, activation: Activation) -> None:
        act, g = self._act, self._g
        if isinstance(activation, Mapping):
            act[:] = 0.0
            for name, value in activation.items():
                if name not in self._index:
                    raise RigError(f"popping: unknown muscle group {name!r}; groups are {list(self._index)}")
                act[self._index[name]] = value
        elif np.ndim(activation) == 0:
            act[:g] = activation
            act[g:] = 0.0
        else:
            values = np.asarray(activation, dtype=np.float32).ravel()
            if values.size != g:
                raise RigError(f"popping: {values.size} activations given for {g} muscle groups {list(self._index)}")
            act[:g] = values
            act[g:] = 0.0
        if not (np.all(act >= 0.0) and np.all(act <= 1.0)):  # also rejects NaN
            raise RigError(f"popping: activations must be in [0, 1], got {act[:g].tolist()}")
        # clench/relax latch per group: rising -> clench (eqs. 1-2), falling -> relax (eq. 4)
        self._clench[act > self._prev] = 1.0
        self._clench[act < self._prev] = 0.0
        self._prev[:] = act

    def step(self, dt: float, activation: Activation) -> wp.array:
        """Advance the skin by one step.

        Args:
            dt: Step length h [s]; needs ``0 < beta * dt <= 1``.
            activation: Muscle activations in [0, 1]: one number for every group, a sequence
                in :attr:`PoseSpaceDeformer.group_names` order, or a mapping group name ->
                activation (missing groups: 0).

        Returns:
            :attr:`points`, the skinned dynamic skin, ``[V]`` vec3 [m].
        """
        if not (dt > 0.0 and self.beta * dt <= 1.0 + 1e-12):
            raise RigError(
                f"popping: step dt={dt!r} s must be positive with beta * dt <= 1 (beta = {self.beta} /s); "
                f"use dt <= {1.0 / self.beta:.6g} s"
            )
        self._set_activation(activation)
        cmd = self._launch
        cmd.set_param_at_index(self._i_act, _k.group_vector(*self._act))
        cmd.set_param_at_index(self._i_clench, _k.group_vector(*self._clench))
        cmd.set_param_at_index(self._i_h, float(dt))
        cmd.launch()
        self.steps += 1
        return self.points


# --------------------------------------------------------------------------------------------
# Activation timeline
# --------------------------------------------------------------------------------------------
class ActivationTimeline:
    """Muscle activation per group over time: piecewise-linear keys, steps where two keys share
    a time (the later one holds from that instant on).

    Args:
        keys: Group name -> ``[(time [s], activation in [0, 1]), ...]`` with non-decreasing
            times. Before the first key the first value holds, after the last the last.

    Example:
        >>> tl = ActivationTimeline({"biceps": ActivationTimeline.beats([0.5, 1.5], hold=0.4)})
        >>> tl.sample(0.6, ["biceps"])
        array([1.])
    """

    def __init__(self, keys: Mapping[str, Sequence[tuple[float, float]]] | None = None, *, where: str = "activation") -> None:
        self.times: dict[str, np.ndarray] = {}
        self.values: dict[str, np.ndarray] = {}
        for name, pairs in (keys or {}).items():
            arr = np.asarray(pairs, dtype=np.float64)
            if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
                raise RigError(f"{where}: group {name!r}: keys must be a non-empty list of [time, activation] pairs")
            t, a = arr[:, 0], arr[:, 1]
            if not np.all(np.isfinite(arr)):
                raise RigError(f"{where}: group {name!r}: keys hold NaN or inf")
            if np.any(np.diff(t) < 0.0):
                k = int(np.nonzero(np.diff(t) < 0.0)[0][0])
                raise RigError(f"{where}: group {name!r}: key times must not decrease (key {k + 1} at {t[k + 1]} s "
                               f"comes after {t[k]} s)")
            if np.any((a < 0.0) | (a > 1.0)):
                raise RigError(f"{where}: group {name!r}: activations must be in [0, 1], got {a[(a < 0) | (a > 1)][:4].tolist()}")
            self.times[str(name)] = t
            self.values[str(name)] = a

    @staticmethod
    def beats(beats: Sequence[float], *, hold: float, attack: float = 0.0, release: float = 0.0,
              where: str = "activation") -> list[tuple[float, float]]:
        """Keys of one pop per beat: rise 0 -> 1 over ``attack`` [s] from the beat, stay
        clenched until ``hold`` [s] after it, fall to 0 over ``release`` [s].

        Raises:
            RigError: negative durations, ``attack > hold``, or pops that overlap the next beat.
        """
        b = np.sort(np.asarray(beats, dtype=np.float64).ravel())
        if b.size == 0 or not np.all(np.isfinite(b)):
            raise RigError(f"{where}: beats must be a non-empty list of times [s]")
        for label, value in (("hold", hold), ("attack", attack), ("release", release)):
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0.0):
                raise RigError(f"{where}: {label} must be a duration >= 0 [s], got {value!r}")
        if hold <= 0.0:
            raise RigError(f"{where}: hold must be positive [s], got {hold!r}")
        if attack > hold:
            raise RigError(f"{where}: attack ({attack} s) must not exceed hold ({hold} s)")
        gaps = np.diff(b)
        if gaps.size and gaps.min() < hold + release - 1e-12:
            k = int(np.argmin(gaps))
            raise RigError(f"{where}: the pop on the beat at {b[k]} s (hold {hold} s + release {release} s) overlaps "
                           f"the beat at {b[k + 1]} s")
        keys = []
        for t in b:
            keys += [(t, 0.0), (t + attack, 1.0), (t + hold, 1.0), (t + hold + release, 0.0)]
        return keys

    @classmethod
    def from_table(cls, table: Mapping, *, where: str = "[popping.activation]") -> ActivationTimeline:
        """From a scene's ``[popping.activation]`` table: per group either ``keys = [[t, a], ...]``
        or ``beats = [t, ...]`` with ``hold`` (and optional ``attack``, ``release``) [s]."""
        if not isinstance(table, Mapping):
            raise RigError(f"{where} must be a table of muscle groups")
        keys = {}
        for name, spec in table.items():
            w = f"{where} {name}"
            if not isinstance(spec, Mapping):
                raise RigError(f"{w}: must be a table with 'keys' or 'beats'")
            unknown = sorted(set(spec) - {"keys", "beats", "hold", "attack", "release"})
            if unknown:
                raise RigError(f"{w}: unknown key(s) {unknown}; known: ['attack', 'beats', 'hold', 'keys', 'release']")
            if ("keys" in spec) == ("beats" in spec):
                raise RigError(f"{w}: give exactly one of 'keys' or 'beats'")
            if "keys" in spec:
                if set(spec) - {"keys"}:
                    raise RigError(f"{w}: hold, attack and release only apply to 'beats'")
                keys[name] = spec["keys"]
            else:
                if "hold" not in spec:
                    raise RigError(f"{w}: 'beats' needs 'hold' (how long each pop stays clenched [s])")
                keys[name] = cls.beats(spec["beats"], hold=spec["hold"], attack=spec.get("attack", 0.0),
                                       release=spec.get("release", 0.0), where=w)
        return cls(keys, where=where)

    @property
    def groups(self) -> list[str]:
        return list(self.times)

    @property
    def end(self) -> float:
        """Time of the last key over all groups [s] (0 when empty)."""
        return max((float(t[-1]) for t in self.times.values()), default=0.0)

    def check_groups(self, names: Sequence[str], where: str = "activation") -> None:
        """Raise :class:`RigError` if the timeline drives a group that ``names`` lacks."""
        unknown = [g for g in self.times if g not in names]
        if unknown:
            raise RigError(f"{where}: muscle groups {unknown} have no clenched examples; groups are {list(names)}")

    def value(self, group: str, t: float) -> float:
        """Activation of ``group`` at time ``t`` [s] (0 for a group without keys)."""
        times = self.times.get(group)
        if times is None:
            return 0.0
        vals = self.values[group]
        k = int(np.searchsorted(times, t, side="right")) - 1
        if k < 0:
            return float(vals[0])
        if k >= times.size - 1:
            return float(vals[-1])
        u = (t - times[k]) / (times[k + 1] - times[k])
        return float(vals[k] + u * (vals[k + 1] - vals[k]))

    def sample(self, t: float, groups: Sequence[str]) -> np.ndarray:
        """Activations of ``groups`` at time ``t`` [s], ``[G]``."""
        return np.array([self.value(g, t) for g in groups])


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------
@dataclass
class PoppingSettings:
    """The ``[popping]`` section of a scene.

    Attributes:
        mode: ``"goal"``: the paper's goal-seeking skin; ``"layered"``: the activation moves the
            muscle layer's rest shape of the multi-layer model toward the clenched example and
            the physical skin (shape matching, volume, collisions) makes the pop.
        alpha_min: Stiffness at the largest disparity, in (0, 1] (eq. 3).
        beta: Relaxation rate [1/s] (eq. 4).
        threshold: Snap distance of relaxing vertices [m].
        dt: Step length [s]; ``None``: one step per frame.
        rbf_width: Gaussian width in pose space [rad]; ``None``: automatic.
        joints: Joints spanning pose space; ``None``: the joints the examples vary.
        activation: Activation per muscle group over clip time.
    """

    mode: str = "goal"
    alpha_min: float = 0.1
    beta: float = 30.0
    threshold: float = 1e-4
    dt: float | None = None
    rbf_width: float | None = None
    joints: list[str] | None = None
    activation: ActivationTimeline = field(default_factory=ActivationTimeline)

    def check(self, where: str = "[popping]") -> None:
        if self.mode not in ("goal", "layered"):
            raise RigError(f"{where}: mode must be 'goal' (the paper's goal-driven skin) or 'layered' (the activation "
                           f"drives the muscle layer of the multi-layer model), got {self.mode!r}")
        _check_dynamics(self.alpha_min, self.beta, self.threshold, where)
        if self.dt is not None and not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            raise RigError(f"{where}: dt must be a positive step length [s], got {self.dt!r}")
        if self.dt is not None and self.beta * self.dt > 1.0 + 1e-12:
            raise RigError(f"{where}: beta * dt = {self.beta * self.dt:.4g} must be <= 1 (no overshoot on relax); "
                           f"lower beta or dt")
        if self.rbf_width is not None and not (isinstance(self.rbf_width, (int, float)) and self.rbf_width > 0):
            raise RigError(f"{where}: rbf_width must be a positive angle [rad], got {self.rbf_width!r}")


_SETTING_KEYS = {"mode", "alpha_min", "beta", "threshold", "dt", "rbf_width", "joints", "activation"}


def popping_settings(scene) -> PoppingSettings:
    """Parse a scene's ``[popping]`` section (defaults where absent).

    Raises:
        RigError: a value of the wrong kind or range, naming the file and key.
    """
    where = str(scene.source) if getattr(scene, "source", None) else "scene"
    table = scene.extra.get("popping") if isinstance(getattr(scene, "extra", None), dict) else None
    if table is None and getattr(scene, "source", None) is not None and str(scene.source).endswith(".toml"):
        try:
            table = tomllib.loads(Path(scene.source).read_text()).get("popping")
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise RigError(f"{where}: cannot read the [popping] section: {exc}") from None
    table = dict(table or {})
    unknown = sorted(set(table) - _SETTING_KEYS)
    if unknown:
        raise RigError(f"{where}: unknown key(s) {unknown} in [popping]; known: {sorted(_SETTING_KEYS)}")
    for key in ("alpha_min", "beta", "threshold", "dt", "rbf_width"):
        if key in table and (isinstance(table[key], bool) or not isinstance(table[key], (int, float))):
            raise RigError(f"{where}: [popping] {key} must be a number, got {table[key]!r}")
    if "mode" in table and not isinstance(table["mode"], str):
        raise RigError(f"{where}: [popping] mode must be a string")
    joints = table.get("joints")
    if joints is not None and (not isinstance(joints, list) or not all(isinstance(j, str) for j in joints)):
        raise RigError(f"{where}: [popping] joints must be a list of joint names")
    settings = PoppingSettings(
        mode=table.get("mode", "goal"),
        alpha_min=table.get("alpha_min", PoppingSettings.alpha_min),
        beta=table.get("beta", PoppingSettings.beta),
        threshold=table.get("threshold", PoppingSettings.threshold),
        dt=table.get("dt"),
        rbf_width=table.get("rbf_width"),
        joints=joints,
        activation=ActivationTimeline.from_table(table.get("activation", {}), where=f"{where}: [popping.activation]"),
    )
    settings.check(f"{where}: [popping]")
    return settings


def examples_for_scene(scene) -> PoppingExamples:
    """The popping examples of a scene whose rig generator makes them (:data:`EXAMPLE_GENERATORS`).

    Raises:
        RigError: the scene's rig has no examples (a file, or another generator); build them
            with :func:`examples_from_meshes` and pass them to :func:`run_popping`.
    """
    gen = scene.rig_spec.get("generator")
    if gen not in EXAMPLE_GENERATORS:
        what = f"generator {gen!r}" if gen else "a rig file"
        raise RigError(
            f"scene {scene.name!r} ({what}) has no popping examples; use a generator that makes them "
            f"({sorted(EXAMPLE_GENERATORS)}) or build them with warpskin.popping.examples_from_meshes and pass "
            "examples= to run_popping"
        )
    import importlib

    module, func = EXAMPLE_GENERATORS[gen].split(":")
    make = getattr(importlib.import_module(module), func)
    return make(scene.rig(), **scene.rig_spec.get("params", {}))


@dataclass
class PoppingRun:
    """What :func:`run_popping` wrote.

    Attributes:
        path: The USD file.
        frames: Number of frames written.
        summary: Scalars: device, vertices, groups, substeps, dt [s], ``peak_overshoot_m`` (the
            farthest any vertex passed its goal, measured along its goal's disparity direction),
            ``max_goal_distance_m``, ``ms_per_frame`` (example-based skinning plus dynamics,
            without the USD writing).
    """

    path: Path
    frames: int
    summary: dict = field(default_factory=dict)


def run_popping(
    scene,
    out_path,
    *,
    examples: PoppingExamples | None = None,
    device=None,
    frames: tuple[int, int] | None = None,
    fps: float | None = None,
    alpha_min: float | None = None,
    beta: float | None = None,
    dt: float | None = None,
    progress: bool = True,
    comment: str = "",
    mode: str | None = None,
) -> PoppingRun:
    """Play a popping scene and write it to USD (the ``warpskin pop`` command).

    Prims under ``/warpskin``: ``popping`` (the dynamic skin), ``normal`` (example-based
    normal mesh, no popping), ``goal`` (the activated clenched goal, a guide) and ``lbs``
    (plain linear blend skinning, a guide), side by side for review. Every frame advances the
    dynamics by ``substeps`` steps ending at the frame's time, with the activation sampled at
    each step; the pose is the frame's.

    Args:
        scene: A :class:`~warpskin.scene.Scene`, a shipped scene name or a TOML path.
        out_path: ``.usdc`` (default format), ``.usda`` or ``.usd``; written atomically.
        examples: The examples; default :func:`examples_for_scene`.
        device: Warp device.
        frames: Inclusive frame range; default the scene's.
        fps: Output frame rate; default the scene's.
        alpha_min, beta, dt: Overrides of the scene's ``[popping]`` values.
        mode: ``"goal"`` or ``"layered"``; default the scene's ``[popping] mode``.
        progress: Progress bar on stderr.
        comment: Stage comment.

    Returns:
        A :class:`PoppingRun`.
    """
    from .io.usd_export import UsdSkinWriter
    from .progress import Progress

    scene = resolve_scene(scene)
    if fps is not None:
        if not (fps > 0):
            raise RigError(f"fps must be positive, got {fps}")
        scene.fps = float(fps)
    settings = popping_settings(scene)
    where = str(scene.source or scene.name)
    for key, value in (("alpha_min", alpha_min), ("beta", beta), ("dt", dt)):
        if value is not None:
            setattr(settings, key, value)
    if mode is not None:
        settings.mode = mode
    settings.check(f"{where}: [popping]")
    if settings.mode == "layered":
        return _run_layered(scene, out_path, settings, examples=examples, device=device, frames=frames,
                            progress=progress, comment=comment)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first, last = frames if frames is not None else scene.frame_range()
    if first < 0 or last < first:
        raise RigError(f"bad frame range {first}:{last}")
    if examples is None:
        examples = examples_for_scene(scene)
    deformer = PoseSpaceDeformer(rig, examples, device=device, joints=settings.joints, rbf_width=settings.rbf_width)
    settings.activation.check_groups(deformer.group_names, f"{where}: [popping.activation]")
    dynamics = PoppingDynamics(deformer, alpha_min=settings.alpha_min, beta=settings.beta, threshold=settings.threshold)
    frame_dt = 1.0 / scene.fps
    substeps = 1 if settings.dt is None else max(1, math.ceil(frame_dt / settings.dt - 1e-9))
    h = frame_dt / substeps
    if settings.beta * h > 1.0 + 1e-12:
        raise RigError(f"{where}: beta * dt = {settings.beta * h:.4g} must be <= 1; lower beta or dt")
    groups = deformer.group_names
    tris = rig.triangles
    bar = Progress(last - first + 1, f"pop {scene.name} ({deformer.device}, {rig.vertex_count} vertices)", enabled=progress)
    peak_over, max_goal, compute_s = 0.0, 0.0, 0.0
    with UsdSkinWriter(out_path, fps=scene.fps, up_axis=rig.up_axis, comment=comment) as writer:
        writer.add_mesh("popping", tris, rest_points=rig.vertices, color=(0.85, 0.64, 0.52))
        writer.add_mesh("normal", tris, rest_points=rig.vertices, color=(0.55, 0.75, 0.55))
        writer.add_mesh("goal", tris, rest_points=rig.vertices, color=(0.8, 0.4, 0.4), purpose="guide")
        writer.add_mesh("lbs", tris, rest_points=rig.vertices, color=(0.4, 0.55, 0.85), purpose="guide")
        for f in range(first, last + 1):
            t = scene.frame_time(f)
            t0 = time.perf_counter()
            deformer.set_pose(rig.skinning_matrices(clip, t))
            for s in range(substeps):
                ts = t - frame_dt + (s + 1) * h
                dynamics.step(h, settings.activation.sample(ts, groups))
            lbs = deformer.lbs().numpy()
            x = dynamics.points.numpy()
            goal = dynamics.goal_points.numpy()
            normal = deformer.normal_points.numpy()
            compute_s += time.perf_counter() - t0
            writer.write_frame(f, {"popping": x, "normal": normal, "goal": goal, "lbs": lbs})
            # overshoot: how far past its goal a vertex is, along the goal's disparity direction
            d = goal - normal
            dl = np.linalg.norm(d, axis=1)
            moved = dl > 1e-6
            if moved.any():
                over = np.einsum("ij,ij->i", (x - goal)[moved], d[moved] / dl[moved, None])
                peak_over = max(peak_over, float(over.max()))
            max_goal = max(max_goal, float(np.linalg.norm(x - goal, axis=1).max()))
            bar.update()
    bar.close()
    count = last - first + 1
    return PoppingRun(
        path=Path(writer.path),
        frames=count,
        summary={
            "device": str(deformer.device),
            "vertices": rig.vertex_count,
            "groups": groups,
            "substeps": substeps,
            "dt_s": h,
            "alpha_min": settings.alpha_min,
            "beta": settings.beta,
            "peak_overshoot_m": peak_over,
            "max_goal_distance_m": max_goal,
            "ms_per_frame": 1e3 * compute_s / count,
        },
    )


# --------------------------------------------------------------------------------------------
# Benchmark
# --------------------------------------------------------------------------------------------
def bench_popping(device=None, steps: int = 200, repeat: int = 3, *, rings: int = 80, segments: int = 54) -> dict:
    """Milliseconds per frame of the popping pipeline on the arm at 4322 vertices (the paper's
    character has 4380 and runs at 60 FPS on a 3.6 GHz CPU), against plain LBS in the same run.

    Returns:
        ``vertices``; ``pose_space_ms`` (set_pose: host RBF weights, uploads and the pose space
        kernel) and ``pose_space_kernel_ms`` (the kernel alone); ``step_ms`` (one popping step:
        host activation latch plus the kernel); ``frame_ms`` (pose space + one step, the
        paper's per-frame work) and ``fps``; ``lbs_ms`` (the LBS Skinner: upload plus kernel)
        and ``lbs_kernel_ms``; ``frame_over_lbs`` and ``step_over_lbs_kernel`` ratios.
    """
    from .bench import _best_ms
    from .scenes.popping_arm import elbow_pose, make_popping_arm, popping_arm_examples

    if steps < 1 or repeat < 1:
        raise ValueError("steps and repeat must be >= 1")
    dev = resolve_device(device)
    rig = make_popping_arm(rings=rings, segments=segments)
    examples = popping_arm_examples(rig, rings=rings, segments=segments)
    # a slowly moving elbow, so every frame's pose (and RBF weights) differ
    mats = [elbow_pose(rig, 60.0 + 60.0 * k / max(steps - 1, 1)) for k in range(steps)]
    deformer = PoseSpaceDeformer(rig, examples, device=dev)
    dynamics = PoppingDynamics(deformer, alpha_min=0.1, beta=30.0)
    lbs = Skinner(rig, method="lbs", device=str(dev))
    h = 1.0 / 240.0
    act = np.ones(deformer.group_count)
    deformer.set_pose(mats[0])  # compile / load outside the timed regions
    dynamics.step(h, act)
    lbs.skin(mats[0])
    row = {
        "device": str(dev),
        "device_name": getattr(dev, "name", str(dev)),
        "warp": wp.config.version,
        "vertices": rig.vertex_count,
        "groups": deformer.group_count,
        "normal_examples": examples.normal_count,
        "steps": steps,
        "repeat": repeat,
    }
    row["pose_space_ms"] = _best_ms(lambda f: deformer.set_pose(mats[f]), steps, repeat, dev)
    row["pose_space_kernel_ms"] = _best_ms(lambda f: deformer.launch(), steps, repeat, dev)
    row["step_ms"] = _best_ms(lambda f: dynamics.step(h, act), steps, repeat, dev)

    def frame(f):
        deformer.set_pose(mats[f])
        dynamics.step(h, act)

    row["frame_ms"] = _best_ms(frame, steps, repeat, dev)
    row["fps"] = 1e3 / row["frame_ms"] if row["frame_ms"] > 0 else None
    row["lbs_ms"] = _best_ms(lambda f: lbs.skin(mats[f]), steps, repeat, dev)
    row["lbs_kernel_ms"] = _best_ms(lambda f: lbs.launch(), steps, repeat, dev)
    row["frame_over_lbs"] = row["frame_ms"] / row["lbs_ms"] if row["lbs_ms"] > 0 else None
    row["step_over_lbs_kernel"] = row["step_ms"] / row["lbs_kernel_ms"] if row["lbs_kernel_ms"] > 0 else None
    return row


# ----------------------------------------------------------------------------------------------
# Layered mode: the activation drives the muscle layer of the multi-layer model
# ----------------------------------------------------------------------------------------------
def muscle_rest_offset_deltas(builder, examples: PoppingExamples, skin_matrices: np.ndarray, *,
                              layers: Sequence[str] = ("skin", "fat", "muscle"), device=None) -> np.ndarray:
    """How every region rest offset of the multi-layer model changes when a group clenches.

    The clenched-minus-normal rest-frame displacement of group g at the pose (the examples'
    disparities interpolated with the pose space weights) moves the rest positions of the
    particles of ``layers``; each region's rest centre follows (mass weighted), so the change of
    the rest offset of entry e (member j of region r) is ``dx0_j - dc0_r``.

    By default the swelling muscle carries the tissue above it (muscle, fat and skin rest shapes
    move together; the bone layer stays): shape matching only sees shapes relative to each
    region's centre, so moving the muscle layer alone just thins the fat above it and the skin
    does not move (measured: 0.0 mm against 4.4 mm on the popping arm's biceps). The pinned bone
    layer's regions then push the whole column out; the volume constraints keep each
    sub-volume's volume by letting the rest of it give.

    Args:
        builder: A built :class:`~warpskin.model.SkinModelBuilder` of the examples' rig.
        examples: The popping examples.
        skin_matrices: The pose, ``[J, 4, 4]`` (the popping scenes hold the bones still).
        layers: Layers whose rest shape the muscles move.

    Returns:
        ``[G, M, 3]`` [m], M the number of region entries.
    """
    from .build.layers import LAYER_NAMES

    builder.build()
    bad = [n for n in layers if n not in LAYER_NAMES[:3]]
    if bad:
        raise RigError(f"layered popping: layers {bad} cannot be moved by the muscles; choose from {list(LAYER_NAMES[:3])}")
    v = builder.rig.vertex_count
    if examples.vertex_count != v:
        raise RigError(f"layered popping: the examples have {examples.vertex_count} vertices, the model {v}")
    deformer = PoseSpaceDeformer(builder.rig, examples, device="cpu")
    _, group_w = deformer.weights(skin_matrices)
    reg = builder.regions
    region_of = reg.region_of_entry()
    m = builder.masses[reg.region_members]
    out = np.zeros((examples.group_count, reg.region_members.size, 3))
    for g in range(examples.group_count):
        disp = np.einsum("e,evc->vc", group_w[g], examples.clenched_disparities[g])  # [V, 3]
        dx0 = np.zeros((4 * v, 3))
        for name in layers:
            k = LAYER_NAMES.index(name)
            dx0[k * v:(k + 1) * v] = disp
        dmember = dx0[reg.region_members]
        dcom = np.stack([np.bincount(region_of, m * dmember[:, c], minlength=reg.region_count) for c in range(3)], axis=1)
        dcom /= reg.region_mass[:, None]
        out[g] = dmember - dcom[region_of]
    return out


def _run_layered(scene, out_path, settings: PoppingSettings, *, examples, device, frames, progress, comment) -> PoppingRun:
    from .model import SkinModelBuilder
    from .simulate import simulate

    examples = examples if examples is not None else examples_for_scene(scene)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first = (frames or scene.frame_range())[0]
    builder = SkinModelBuilder(rig, scene.model_params())
    deltas = muscle_rest_offset_deltas(builder, examples, rig.skinning_matrices(clip, scene.frame_time(first)))
    groups = list(examples.group_names)
    settings.activation.check_groups(groups, "[popping.activation]")
    result = simulate(scene, out_path, device=device, frames=frames, with_lbs=True, progress=progress, comment=comment,
                      builder=builder, rest_shape=(deltas, lambda t: settings.activation.sample(t, groups)))
    summary = dict(result.summary)
    summary["mode"] = "layered"
    summary["groups"] = groups
    return PoppingRun(path=result.path, frames=len(result.frames), summary=summary)


def examples_from_morph_targets(
    rig: Rig,
    targets: Mapping[str, np.ndarray],
    *,
    normal: Sequence[tuple[str | None, object]],
    clenched: Mapping[str, Sequence[tuple[str, object]]],
    clip: Clip | str | None = None,
) -> PoppingExamples:
    """Popping examples from morph targets of the rig's mesh (for instance from
    :func:`warpskin.io.gltf.read_gltf_morph_targets`).

    Each example is the rest mesh plus a target's offsets (``None``: the rest mesh itself),
    skinned at the example's pose; then :func:`examples_from_meshes` (which checks topology
    and pairing) turns them into rest-frame displacements.

    Args:
        rig: The rig whose mesh carries the targets.
        targets: ``{name: offsets}``, offsets per *file* vertex ``[N, 3]`` (or per welded
            vertex ``[V, 3]``) in the rest (bind) space.
        normal: ``[(target or None, pose), ...]``: the normal examples.
        clenched: ``{group: [(target, pose), ...]}``: the clenched examples of each muscle group,
            each at the pose of a normal example.
        clip: Clip for poses given as times.

    Raises:
        RigError: an unknown target (listing the known ones), offsets of the wrong size.
    """
    def welded(name: str | None, label: str) -> np.ndarray:
        if name is None:
            return np.zeros_like(rig.vertices)
        if name not in targets:
            raise RigError(f"{label}: no morph target {name!r}; targets: {sorted(targets)}")
        d = np.asarray(targets[name], dtype=np.float64)
        if d.shape == (rig.file_vertex_count, 3):
            first = np.zeros(rig.vertex_count, dtype=np.int64)
            first[rig.weld_map[::-1]] = np.arange(rig.file_vertex_count)[::-1]  # first file vertex of each
            return d[first]
        if d.shape == (rig.vertex_count, 3):
            return d
        raise RigError(f"{label}: morph target {name!r} has offsets of shape {d.shape}; the rig has "
                       f"{rig.file_vertex_count} file vertices ({rig.vertex_count} welded)")

    def mesh_at(name, pose, label):
        mats = _pose_matrices(rig, pose, clip, label)
        pts = rig.vertices + welded(name, label)
        return linear_blend_skin(pts, rig.joint_indices, rig.joint_weights, mats), mats

    normal_meshes = [mesh_at(n, pose, f"normal example {k}") for k, (n, pose) in enumerate(normal)]
    clenched_meshes = {
        group: [mesh_at(n, pose, f"clenched example {k} of {group!r}") for k, (n, pose) in enumerate(items)]
        for group, items in clenched.items()
    }
    return examples_from_meshes(rig, normal_meshes, clenched_meshes)


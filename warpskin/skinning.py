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


def skin_to_usd(
    scene,
    out_path,
    *,
    method: str = "lbs",
    device: str | None = None,
    frames: tuple[int, int] | None = None,
    fps: float | None = None,
    with_rest: bool = False,
    with_lbs: bool = False,
    topology: str = "welded",
    progress: bool = True,
    comment: str = "",
):
    """Skin a scene frame by frame and write it to USD (the ``warpskin skin`` command).

    Args:
        scene: A :class:`~warpskin.scene.Scene` (or a shipped scene's name / TOML path / rig file).
        out_path: ``.usdc`` (default format), ``.usda`` or ``.usd`` file.
        method: ``"lbs"`` or ``"dqs"``.
        device: Warp device.
        frames: Inclusive frame range; default the scene's.
        fps: Output frame rate; default the scene's.
        with_rest: Also write the rest mesh as a static sibling prim ``rest``.
        with_lbs: With ``method="dqs"``, also write the LBS result as a sibling prim ``lbs``.
        topology: ``"welded"`` (the closed surface warpskin works on) or ``"file"`` (the
            file's own vertices, split at seams, so UVs in the source still line up).
        progress: Show a progress bar on stderr.
        comment: Stage comment.

    Returns:
        ``(path, frame_count)``.
    """
    from .io.usd_export import UsdSkinWriter
    from .progress import Progress
    from .scene import resolve_scene

    scene = resolve_scene(scene)
    if fps is not None:
        if not (fps > 0):
            raise SceneError(f"fps must be positive, got {fps}")
        scene.fps = float(fps)
    if topology not in ("welded", "file"):
        raise SceneError(f"topology must be 'welded' or 'file', got {topology!r}")
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    first, last = frames if frames is not None else scene.frame_range()
    if first < 0 or last < first:
        raise SceneError(f"bad frame range {first}:{last}")
    skinner = Skinner(rig, method=method, device=device)
    lbs = Skinner(rig, method="lbs", device=device) if (with_lbs and method != "lbs") else None
    if topology == "file":
        tris, remap = rig.file_triangles, rig.weld_map
    else:
        tris, remap = rig.triangles, None

    def pick(points: np.ndarray) -> np.ndarray:
        return points[remap] if remap is not None else points

    bar = Progress(last - first + 1, f"skin {scene.name} ({method}, {skinner.device})", enabled=progress)
    with UsdSkinWriter(out_path, fps=scene.fps, up_axis=rig.up_axis, comment=comment) as writer:
        writer.add_mesh("skin", tris, rest_points=pick(rig.vertices), color=(0.85, 0.64, 0.52))
        if with_rest:
            writer.add_mesh("rest", tris, rest_points=pick(rig.vertices), animated=False, color=(0.5, 0.5, 0.5), purpose="guide")
        if lbs is not None:
            writer.add_mesh("lbs", tris, rest_points=pick(rig.vertices), color=(0.4, 0.55, 0.85), purpose="guide")
        for f in range(first, last + 1):
            mats = rig.skinning_matrices(clip, scene.frame_time(f))
            frame = {"skin": pick(skinner.skin(mats).numpy())}
            if lbs is not None:
                frame["lbs"] = pick(lbs.skin(mats).numpy())
            writer.write_frame(f, frame)
            bar.update()
    bar.close()
    return writer.path, last - first + 1

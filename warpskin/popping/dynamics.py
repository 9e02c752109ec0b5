"""Skin vibration (Son & Han 2007, eqs. 1-4): per-vertex stiffness from the normal/clenched
disparity, the goal-driven step while clenching and the monotone relaxation afterwards."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..errors import SceneError
from ..kernels import popping as _k
from ..params import PoppingSettings
from ..settings import check_value, setting_named
from .examples import Activation

if TYPE_CHECKING:
    from .pose_space import PoseSpaceDeformer


# --------------------------------------------------------------------------------------------
# Dynamics
# --------------------------------------------------------------------------------------------
def _check_dynamics(alpha_min: float, beta: float, threshold: float, where: str = "popping") -> None:
    """``alpha_min``, ``beta`` and ``threshold`` in their ranges as ``[popping]`` declares them
    (:class:`~warpskin.params.PoppingSettings`), else a one-line SceneError."""
    for name, value in (("alpha_min", alpha_min), ("beta", beta), ("threshold", threshold)):
        check_value(setting_named(PoppingSettings, name), value, f"{where}: ")


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
        # recorded once; a step only re-packs the activations and h (cheaper than wp.launch);
        # inbetweens (disparity rows beyond one per group) take the rows' kernel
        kernel = _k.popping_step_kernel if d.row_full.all() else _k.popping_step_rows_kernel
        self._launch = wp.launch(
            kernel,
            dim=d.rig.vertex_count,
            inputs=[sk.rest_points, sk.joint_indices, sk.joint_weights, sk.skin_matrices, d.normal_displacement,
                    d.disparity, d.disparity_max, d.row_group_device, d.row_full_device, d.row_tent,
                    _k.group_vector(), _k.group_vector(), self.alpha_min, self.beta, self.threshold, 1.0],
            outputs=[self.offset, self.velocity, self.points, self.goal_points, self.alpha],
            device=self.device,
            record_cmd=True,
        )
        names = [a.label for a in kernel.adj.args]
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
                    raise SceneError(f"popping: unknown muscle group {name!r}; groups are {list(self._index)}")
                act[self._index[name]] = value
        elif np.ndim(activation) == 0:
            act[:g] = activation
            act[g:] = 0.0
        else:
            values = np.asarray(activation, dtype=np.float32).ravel()
            if values.size != g:
                raise SceneError(f"popping: {values.size} activations given for {g} muscle groups {list(self._index)}")
            act[:g] = values
            act[g:] = 0.0
        if not (np.all(act >= 0.0) and np.all(act <= 1.0)):  # also rejects NaN
            raise SceneError(f"popping: activations must be in [0, 1], got {act[:g].tolist()}")
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
            raise SceneError(
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

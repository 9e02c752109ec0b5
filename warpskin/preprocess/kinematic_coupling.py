"""Kinematic coupling (Deul & Bender 2013, section 4.4): every bone-layer particle is pulled to
its LBS position by a zero-length distance constraint; its LBS target uses the weights of its
skin vertex."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rig import Rig, RigError
from ..transforms import linear_blend_skin
from .layers import Layers

__all__ = ["KinematicCoupling", "build_kinematic_coupling"]


@dataclass
class KinematicCoupling:
    """Bone-layer particles and their LBS targets.

    Attributes:
        particles: Global indices of the coupled particles, ``[V]`` (the bone layer).
        rest: Their rest positions [m], ``[V, 3]``.
        joint_indices, joint_weights: LBS influences, ``[V, K]``.
        stiffness: Constraint stiffness in [0, 1] (the paper uses 1).
    """

    particles: np.ndarray
    rest: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    stiffness: float = 1.0

    def targets(self, skin_matrices: np.ndarray) -> np.ndarray:
        """LBS targets [m], ``[V, 3]``, for skinning matrices ``[J, 4, 4]`` (host reference)."""
        return linear_blend_skin(self.rest, self.joint_indices, self.joint_weights, skin_matrices)


def build_kinematic_coupling(rig: Rig, layers: Layers, *, stiffness: float = 1.0) -> KinematicCoupling:
    """Couple every bone-layer particle to its LBS position."""
    if not (0.0 <= stiffness <= 1.0):
        raise RigError(f"coupling stiffness must be in [0, 1], got {stiffness}")
    v = layers.vertex_count
    return KinematicCoupling(
        particles=3 * v + np.arange(v),
        rest=layers.positions[3].copy(),
        joint_indices=rig.joint_indices.copy(),
        joint_weights=rig.joint_weights.copy(),
        stiffness=float(stiffness),
    )

"""Joint constraints (Deul & Bender 2013, section 4.4): particles near a joint keep at least
their rest distance to the joint centre (a unilateral, lower-bound distance constraint), so
tissue does not sink into the bones at a bent joint while it may still move away from it.

Joint centres are kinematic: the centre of joint ``j`` at time ``t`` is
``(G_j(t) @ inverse_bind_j) @ bind_position_j``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..rig import Rig, RigError
from ..settings import setting
from .layers import LAYER_NAMES, Layers

__all__ = ["JointParams", "JointConstraints", "build_joint_constraints"]


@dataclass
class JointParams:
    """Which particles get joint constraints.

    Attributes:
        radius_factor: A particle is constrained to joint ``j`` when its vertex's bone is at
            most two steps from ``j`` in the skeleton and its rest distance to the joint centre is below
            ``radius_factor`` times the joint's radius (the median distance of the skin
            vertices whose bone foot is at that joint).
        layers: Layers whose particles may be constrained.
        joints: Joint names to constrain; ``None``: every joint between two bones.
    """

    _section = "joints"

    radius_factor: float = setting(1.0, "number", "a particle is constrained to a joint within this many times the "
                                   "joint's radius", low=0.0, open_low=True, must="a positive number")
    layers: tuple[str, ...] = setting(("fat", "muscle", "bone"), "strings", "the layers whose particles may be "
                                      "constrained", choices=LAYER_NAMES)
    joints: list[str] | None = setting(None, "strings", "the joints to constrain (default: every joint between two "
                                       "bones)", optional=True)


@dataclass
class JointConstraints:
    """Unilateral lower-bound distance constraints to joint centres.

    Attributes:
        particles: Constrained particle per constraint, ``[C]``.
        joints: Joint index per constraint, ``[C]``.
        rest_distance: Lower bound (the rest distance) [m], ``[C]``.
        joint_rest: Rest (bind) position of every joint centre [m], ``[J, 3]``.
        joint_radius: Radius used per joint [m], ``[J]`` (0 for joints without constraints).
    """

    particles: np.ndarray
    joints: np.ndarray
    rest_distance: np.ndarray
    joint_rest: np.ndarray
    joint_radius: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def count(self) -> int:
        return int(self.particles.size)

    def centres(self, skin_matrices: np.ndarray) -> np.ndarray:
        """Joint centres [m], ``[J, 3]``, for skinning matrices ``[J, 4, 4]``."""
        return np.einsum("jab,jb->ja", skin_matrices[:, :3, :3], self.joint_rest) + skin_matrices[:, :3, 3]


def _within_two_steps(parents: np.ndarray) -> list[np.ndarray]:
    """For every joint, the joints at most two steps from it in the skeleton (itself, its
    parent and grandparent, its children and grandchildren, its siblings)."""
    n = len(parents)
    adj = [set() for _ in range(n)]
    for c, p in enumerate(parents):
        if p >= 0:
            adj[c].add(int(p))
            adj[int(p)].add(c)
    out = []
    for j in range(n):
        one = adj[j] | {j}
        two = set(one)
        for k in adj[j]:
            two |= adj[k]
        out.append(np.array(sorted(two), dtype=np.int64))
    return out


def build_joint_constraints(rig: Rig, layers: Layers, params: JointParams | None = None) -> JointConstraints:
    """Select the particles near each joint and record their rest distances."""
    params = params or JointParams()
    where = rig.source or rig.name
    if not (params.radius_factor > 0 and np.isfinite(params.radius_factor)):
        raise RigError(f"{where}: joint radius_factor must be positive, got {params.radius_factor}")
    bad = [name for name in params.layers if name not in LAYER_NAMES]
    if bad:
        raise RigError(f"{where}: unknown layers {bad} for joint constraints; layers are {list(LAYER_NAMES)}")
    parents = rig.skeleton.parents
    names = rig.skeleton.joint_names
    joint_rest = rig.bind_world_transforms()[:, :3, 3]
    if params.joints is None:
        # joints between two bones: they have a parent and carry a bone (children or vertices)
        chosen = [j for j in range(rig.joint_count) if parents[j] >= 0 and np.any(layers.bone == j)]
    else:
        chosen = [rig.skeleton.index(n) for n in params.joints]
    skin = layers.positions[0]
    layer_ids = [LAYER_NAMES.index(n) for n in params.layers]
    v = layers.vertex_count
    radius = np.zeros(rig.joint_count)
    around = _within_two_steps(parents)
    parts, joints, dists = [], [], []
    for j in chosen:  # joints are few
        # skin vertices whose projection foot is at this joint: the start of bone j, or the
        # end of the parent's bone
        at_joint = ((layers.bone == j) & (layers.bone_t < 1e-6)) | ((layers.bone == parents[j]) & (layers.bone_t > 1 - 1e-6))
        d_skin = np.linalg.norm(skin - joint_rest[j], axis=1)
        if at_joint.any():
            radius[j] = float(np.median(d_skin[at_joint]))
        else:
            near = np.isin(layers.bone, [j, parents[j]])
            if not near.any():
                continue
            radius[j] = float(np.quantile(d_skin[near], 0.05))
        r = params.radius_factor * radius[j]
        # only the tissue of the bones around the joint (within two steps of it in the
        # skeleton): a hand that hangs beside a leg at rest must not keep the leg's particles
        # away from its wrist
        own = np.isin(layers.bone, around[j])
        for k in layer_ids:
            d = np.linalg.norm(layers.positions[k] - joint_rest[j], axis=1)
            sel = np.nonzero((d < r) & (d > 1e-9 * max(rig.size(), 1e-12)) & own)[0]
            parts.append(k * v + sel)
            joints.append(np.full(sel.size, j))
            dists.append(d[sel])
    if params.joints is not None:
        empty = [names[j] for j in chosen if radius[j] == 0.0]
        if empty:
            raise RigError(f"{where}: joints {empty} have no nearby vertices for joint constraints")
    cat = (lambda xs, dt: np.concatenate(xs).astype(dt) if xs else np.zeros(0, dt))
    return JointConstraints(
        particles=cat(parts, np.int64), joints=cat(joints, np.int64), rest_distance=cat(dists, np.float64),
        joint_rest=joint_rest, joint_radius=radius,
    )

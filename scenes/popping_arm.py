"""Procedural popping arm (Son & Han 2007, Figs. 4, 6 and 7): the procedural arm
(:func:`warpskin.scenes.arm.make_arm`) with its elbow held still, plus example pairs (normal,
clenched) at three elbow angles for two muscle groups, biceps and triceps.

* **Normal examples**: the plain skinned arm plus a small pose-dependent fullness of the
  relaxed biceps (it bunches up as the elbow flexes: ``normal_height * angle / 150 deg``), so
  the normal group is a real pose space deformation, not only LBS.
* **Clenched examples**: the normal example plus a smooth bump of the muscle belly along the
  outward radial direction of the upper arm: the biceps on the +y side (the side the forearm
  folds to), the triceps on the -y side. The bump is ``height * sin^2(pi u) * max(0, +-cos
  phi)^2`` with ``u`` the position along the muscle (its tendon ends give 0) and ``phi`` the
  angle around the arm from +y: a fusiform muscle, largest at its centre (the paper's Fig. 6).
  The biceps bulges more when the elbow is flexed (``biceps_flex_gain``).

Every example is made in the world space of its pose (skinned) and goes through
:func:`warpskin.popping.examples_from_meshes`, the same path file-based examples take.

Coordinates and joints as :mod:`warpskin.scenes.arm`: the arm along +x, shoulder at the origin,
the elbow flexes about +z toward +y. The clip ``pop`` holds the elbow at ``hold_degrees``
(the bones never move: isometric contraction).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from warpskin.rig import Clip, Rig, RigError, Track
from warpskin.transforms import linear_blend_skin
from warpskin.scenes.arm import ARM_DEFAULTS, make_arm

__all__ = ["make_popping_arm", "popping_arm_examples", "popping_arm_meshes", "POPPING_ARM_DEFAULTS", "elbow_pose"]

POPPING_ARM_DEFAULTS: dict = {
    "hold_degrees": 100.0,  # elbow flexion held by the clip [deg]
    "duration": 4.0,  # clip length [s]
    "example_degrees": [30.0, 90.0, 150.0],  # elbow angles of the three example pairs [deg]
    "biceps_height": 0.010,  # biceps bulge at 90 degrees [m]
    "biceps_flex_gain": 0.4,  # extra biceps bulge per 150 degrees of flexion, as a fraction
    "biceps_span": [0.08, 0.26],  # biceps belly along x, tendon to tendon [m]
    "triceps_height": 0.006,  # triceps bulge [m]
    "triceps_span": [0.05, 0.24],  # triceps belly along x [m]
    "normal_height": 0.002,  # relaxed biceps fullness at 150 degrees (normal examples) [m]
}

# arm parameters that only shape the arm's own flex clip, which the popping arm replaces
_CLIP_KEYS = {"flex_degrees", "flex_time", "hold_time", "rest_time", "key_rate"}


def _split(params: dict) -> tuple[dict, dict]:
    unknown = sorted(set(params) - set(POPPING_ARM_DEFAULTS) - set(ARM_DEFAULTS))
    if unknown:
        known = sorted(set(POPPING_ARM_DEFAULTS) | (set(ARM_DEFAULTS) - _CLIP_KEYS))
        raise RigError(f"popping_arm generator: unknown parameters {unknown}; known: {known}")
    arm = {k: v for k, v in params.items() if k in ARM_DEFAULTS}
    pop = {**POPPING_ARM_DEFAULTS, **{k: v for k, v in params.items() if k in POPPING_ARM_DEFAULTS}}
    for key in ("hold_degrees",):
        if not (isinstance(pop[key], (int, float)) and 0.0 <= pop[key] <= 175.0):
            raise RigError(f"popping_arm generator: {key} must be in [0, 175] degrees, got {pop[key]!r}")
    for key in ("duration", "biceps_height", "triceps_height"):
        if not (isinstance(pop[key], (int, float)) and math.isfinite(pop[key]) and pop[key] > 0.0):
            raise RigError(f"popping_arm generator: {key} must be a positive number, got {pop[key]!r}")
    for key in ("biceps_flex_gain", "normal_height"):
        if not (isinstance(pop[key], (int, float)) and math.isfinite(pop[key]) and pop[key] >= 0.0):
            raise RigError(f"popping_arm generator: {key} must be a number >= 0, got {pop[key]!r}")
    ex = pop["example_degrees"]
    if not isinstance(ex, (list, tuple)) or len(ex) == 0 or not all(
        isinstance(a, (int, float)) and 0.0 <= a <= 175.0 for a in ex
    ):
        raise RigError(f"popping_arm generator: example_degrees must be a list of angles in [0, 175], got {ex!r}")
    for key in ("biceps_span", "triceps_span"):
        span = pop[key]
        if not isinstance(span, (list, tuple)) or len(span) != 2 or not (0.0 <= span[0] < span[1]):
            raise RigError(f"popping_arm generator: {key} must be [start, end] with 0 <= start < end [m], got {span!r}")
    return arm, pop


def elbow_pose(rig: Rig, degrees: float) -> np.ndarray:
    """Skinning matrices ``[J, 4, 4]`` of the arm with the elbow flexed by ``degrees`` about +z
    (shoulder and wrist at rest)."""
    local = rig.skeleton.rest_local_matrices()
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    e = rig.skeleton.index("elbow")
    local[e, :3, :3] = local[e, :3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rig.skeleton.world_from_local(local) @ rig.inverse_bind


def make_popping_arm(**params) -> Rig:
    """Build the popping arm rig: :func:`~warpskin.scenes.arm.make_arm` with a clip ``pop``
    that holds the elbow at ``hold_degrees`` for ``duration`` seconds.

    Args:
        **params: Overrides of :data:`POPPING_ARM_DEFAULTS` and of the arm's shape parameters
            (:data:`~warpskin.scenes.arm.ARM_DEFAULTS`; lengths in metres, angles in degrees).

    Returns:
        The rig (joints ``shoulder``, ``elbow``, ``wrist``; clip ``pop``). Its examples:
        :func:`popping_arm_examples` with the same parameters.
    """
    arm_params, pop = _split(params)
    rig = make_arm(**arm_params)
    a = math.radians(pop["hold_degrees"])
    q = [0.0, 0.0, math.sin(a / 2), math.cos(a / 2)]
    track = Track("rotation", [0.0, float(pop["duration"])], [q, q], "STEP")  # exactly still
    clip = Clip("pop", {(rig.skeleton.index("elbow"), "rotation"): track})
    return dataclasses.replace(rig, name="popping_arm", source="generator:popping_arm", clips={"pop": clip})


def _bump(rest: np.ndarray, span, side: float, height: float) -> np.ndarray:
    """Rest-frame muscle bulge ``[V, 3]``: radial, ``height * sin^2(pi u) * max(0, side *
    cos phi)^2``."""
    x, y, z = rest[:, 0], rest[:, 1], rest[:, 2]
    radial = np.stack([np.zeros_like(y), y, z], axis=1)
    r = np.linalg.norm(radial, axis=1)
    safe = np.where(r > 1e-12, r, 1.0)
    u = np.clip((x - span[0]) / (span[1] - span[0]), 0.0, 1.0)
    along = np.sin(np.pi * u) ** 2
    around = np.maximum(side * y / safe, 0.0) ** 2
    amount = np.where(r > 1e-12, height * along * around, 0.0)
    return radial / safe[:, None] * amount[:, None]


def _skin(rig: Rig, points: np.ndarray, mats: np.ndarray) -> np.ndarray:
    return linear_blend_skin(points, rig.joint_indices, rig.joint_weights, mats)


def popping_arm_meshes(rig: Rig, **params) -> dict:
    """The example meshes in world space: ``{"normal": [(points, matrices), ...], "clenched":
    {"biceps": [...], "triceps": [...]}}`` (input of
    :func:`warpskin.popping.examples_from_meshes`)."""
    _, pop = _split(params)
    rest = rig.vertices
    normal, biceps, triceps = [], [], []
    for deg in pop["example_degrees"]:
        mats = elbow_pose(rig, deg)
        flex = deg / 150.0
        n_disp = _bump(rest, pop["biceps_span"], +1.0, pop["normal_height"] * flex) if pop["normal_height"] > 0 else 0.0 * rest
        b_disp = _bump(rest, pop["biceps_span"], +1.0, pop["biceps_height"] * (1.0 + pop["biceps_flex_gain"] * (flex - 0.6)))
        t_disp = _bump(rest, pop["triceps_span"], -1.0, pop["triceps_height"])
        normal.append((_skin(rig, rest + n_disp, mats), mats))
        biceps.append((_skin(rig, rest + n_disp + b_disp, mats), mats))
        triceps.append((_skin(rig, rest + n_disp + t_disp, mats), mats))
    return {"normal": normal, "clenched": {"biceps": biceps, "triceps": triceps}}


def popping_arm_examples(rig: Rig, **params):
    """The popping arm's examples (:class:`~warpskin.popping.PoppingExamples`): three pairs at
    ``example_degrees``, groups ``biceps`` and ``triceps``.

    Args:
        rig: The rig from :func:`make_popping_arm` (or :func:`~warpskin.scenes.arm.make_arm`).
        **params: The same parameters as :func:`make_popping_arm` (arm shape keys are ignored
            here; the rig already has its shape).
    """
    from warpskin.popping import examples_from_meshes

    meshes = popping_arm_meshes(rig, **params)
    return examples_from_meshes(rig, normal=meshes["normal"], clenched=meshes["clenched"])

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
* **Muscles without examples**: groups found from the skeleton; their clenched shape a fusiform
  swelling of the multi-layer model's muscle layer (:mod:`warpskin.popping.muscles`, the
  physical skin makes the pop) or of the written meshes themselves, each written point
  vibrating by eqs. 1-4 over the physical normal skin (:mod:`warpskin.popping.surface`, the
  default through a cage).
* :func:`warpskin.run.run_popping` plays a scene to USD (``warpskin pop``) through the frame
  runner, :func:`warpskin.bench.run_popping_bench` times it.

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


from ..params import PoppingSettings
from .activation import ActivationTimeline, Beat, BeatSpec, beat_times, popping_settings, read_beats
from .dynamics import PoppingDynamics
from .examples import EXAMPLE_GENERATORS, MAX_GROUPS, Activation, PoppingExamples, examples_for_scene, examples_from_meshes, examples_from_morph_targets
from .layered import muscle_rest_offset_deltas
from .pose_space import PoseSpaceDeformer, pose_rotations

__all__ = [
    "PoppingExamples",
    "examples_from_meshes",
    "examples_from_morph_targets",
    "pose_rotations",
    "PoseSpaceDeformer",
    "PoppingDynamics",
    "ActivationTimeline",
    "Beat",
    "BeatSpec",
    "beat_times",
    "read_beats",
    "PoppingSettings",
    "popping_settings",
    "examples_for_scene",
    "muscle_rest_offset_deltas",
    "Activation",
    "MAX_GROUPS",
    "EXAMPLE_GENERATORS",
]

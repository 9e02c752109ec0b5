"""The physical skin as a stepper of the frame runner: the solver, its two states, the control
and the contacts; every pose uploaded once; one captured graph per frame; overflow retries;
NaN checks; the pre-roll from the bind pose.

Poses for every substep are computed on the host once, before the loop, and uploaded as one
array; a frame copies its substeps' poses into a staging buffer on the device, and each
substep copies its pose into the control and calls ``solver.step``. A frame's substeps are
recorded once as a Warp graph (CPU and CUDA) and replayed; with an odd substep count the two
state parities get a graph each. Per frame the skin comes back to the host once.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import numpy as np
import warp as wp

from ..errors import InputError, SceneError, SimulationError
from ..metrics import self_intersections
from ..preprocess.layers import LAYER_NAMES
from ..solver import SkinSolver
from .plan import FramePlan
from .runner import first_non_finite

__all__ = ["PhysicsStepper", "initial_state"]

#: Times a frame (or the pre-roll) is run again with doubled contact buffers before giving up.
MAX_GROWTHS = 8
#: The fail-safe's list of nearby triangle pairs grows (between frames) up to this many per skin
#: triangle; a step that lists more (a violent motion) does without it.
PAIR_LIMIT = 64


def initial_state(model, state, skin_matrices: np.ndarray) -> None:
    """Put ``state`` (of ``model``) at the pose ``skin_matrices`` ``[J, 4, 4]`` (the model's
    joints; a batch's, character after character): every particle skinned with its vertex's
    weights (LBS on the host in float64 from the model's layers at rest,
    :meth:`~warpskin.model.RestLayers.skin`), at rest (zero velocities), oriented like its
    dominant bone. A batch's characters come out as each does alone.

    Raises:
        InputError: ``skin_matrices`` is not ``[J, 4, 4]``.
    """
    m = np.asarray(skin_matrices)
    if m.shape != (model.joint_count, 4, 4):
        raise InputError(f"expected skinning matrices of shape {(model.joint_count, 4, 4)}, got {m.shape}")
    if len(model.rest) == 1:
        x, q = model.rest[0].skin(m)
    else:
        total = model.vertex_count
        x = np.zeros((4 * total, 3), dtype=np.float32)
        q = np.zeros((4 * total, 4), dtype=np.float32)
        for rest, r in zip(model.rest, model.characters):
            at = r.particles(total)
            x[at], q[at] = rest.skin(m[rest.joint_start:rest.joint_start + rest.joint_count])
    state.x.assign(x)
    state.q.assign(q)
    state.v.zero_()
    state.omega.zero_()
    state.contact_reach.zero_()


class PhysicsStepper:
    """Advances the multi-layer model through a :class:`FramePlan`.

    Args:
        rig: The simulated rig (its clips give the poses).
        solver: The :class:`~warpskin.solver.SkinSolver` of its model (``builder.finalize(device)``)
            and settings (``dt`` is the plan's substep).
        plan: The frames.
        clip: The clip the poses come from.
        use_graph: Record each frame once as a graph and replay it (bit-identical to plain
            launches).
        preroll: Seconds simulated from the bind pose into the first frame's pose before the
            first frame (nothing of it is written); 0 for none.
        activation: ``activation(t) -> [G]`` for a model with a rest-shape drive.
        label: Progress-bar label prefix: the command and what is simulated (default
            ``"simulate <rig name>"``).
    """

    def __init__(self, rig, solver: SkinSolver, plan: FramePlan, clip, *, use_graph: bool = True,
                 preroll: float = 0.0, activation: Callable | None = None, label: str | None = None) -> None:
        model, params = solver.model, solver.params
        self.model, self.plan, self.clip = model, plan, clip
        self.rig = rig
        self.solver = solver
        self.collision = solver.collision
        self.contacts = model.contacts()  # None when the model has no collision data
        self.use_graph = use_graph
        self.dev = dev = model.device
        self.label = f"{label or 'simulate ' + rig.name} ({dev}, {model.particle_count} particles)"
        self.substeps = substeps = plan.substeps
        self.dt = plan.dt
        j = self.joint_count = rig.joint_count
        step_times = plan.substep_times()
        poses = np.stack([rig.skinning_matrices(clip, t) for t in step_times]) if step_times else np.zeros((0, j, 4, 4))
        self.frame_poses = np.stack([rig.skinning_matrices(clip, t) for t in plan.times])
        self.poses_dev = wp.array(poses.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=dev)
        self.staging = wp.zeros(substeps * j, dtype=wp.mat44, device=dev)  # this frame's substep poses
        self.state_a, self.state_b, self.control = model.state(), model.state(), model.control()
        g = self.group_count = model.rest_drive_group_count
        self.act_dev = self.act_staging = None
        if g:
            if activation is None:
                raise SceneError("the model has a rest-shape drive: give the activation over time")
            acts = np.array([np.asarray(activation(t), dtype=np.float32).reshape(g) for t in step_times]) \
                if step_times else np.zeros((0, g), np.float32)
            self.act_dev = wp.array(acts.reshape(-1), dtype=wp.float32, device=dev)
            self.act_staging = wp.zeros(max(substeps * g, 1), dtype=wp.float32, device=dev)
            self.control.set_activation(np.asarray(activation(plan.times[0]), np.float32).reshape(g))
        initial_state(model, self.state_a, self.frame_poses[0])
        if not (math.isfinite(preroll) and preroll >= 0):
            raise SceneError(f"preroll must be a number of seconds >= 0, got {preroll!r}")
        self.preroll = float(preroll)
        self.preroll_steps = math.ceil(preroll / params.dt - 1e-9) if preroll > 0 else 0
        self.overflow_retries = 0
        if self.preroll_steps:
            self._preroll()
        self.graphs = self._capture_graphs()
        self.backup = model.state() if self.contacts is not None else None
        self._skin: np.ndarray | None = None  # the last frame's skin (host copy)
        self._x: np.ndarray | None = None

    # ------------------------------------------------------------------ pieces
    def _run_frame(self, sa, sb):
        """All substeps of one frame from ``sa``; returns ``(result, other)``."""
        j, g = self.joint_count, self.group_count
        for s in range(self.substeps):
            wp.copy(self.control.skin_matrices, self.staging, dest_offset=0, src_offset=s * j, count=j)
            if self.act_staging is not None:
                wp.copy(self.control.muscle_activation, self.act_staging, dest_offset=0, src_offset=s * g, count=g)
            self.solver.step(sa, sb, self.control, self.contacts, self.dt)
            sa, sb = sb, sa
        return sa, sb

    def _capture_graphs(self) -> dict:
        """One graph per state parity (Warp captures on CPU too); ``{}`` where capture is not
        supported or not worth it."""
        out = {}
        if self.use_graph and self.plan.count > 2:
            a, b = self.state_a, self.state_b
            try:
                for start in ((a, b), (b, a)) if self.substeps % 2 else ((a, b),):
                    with wp.ScopedCapture(device=self.dev) as cap:  # records; runs nothing yet
                        self._run_frame(*start)
                    out[id(start[0])] = cap.graph
            except Exception:  # capture unsupported here: plain launches
                out = {}
        return out

    def _preroll_graphs(self, h: float) -> dict:
        """One solver step of ``h`` [s] recorded per state parity (``{id(source state): graph}``;
        ``{}`` where capture is off or not supported): the pre-roll's poses change every step,
        so it replays steps, not frames."""
        out = {}
        if self.use_graph:
            a, b = self.state_a, self.state_b
            try:
                for sa, sb in ((a, b), (b, a)):
                    with wp.ScopedCapture(device=self.dev) as cap:  # records; runs nothing yet
                        self.solver.step(sa, sb, self.control, self.contacts, h)
                    out[id(sa)] = cap.graph
            except Exception:  # capture unsupported here: plain launches
                out = {}
        return out

    def _preroll(self) -> None:
        rig = self.rig
        bind_pairs = len(self_intersections(rig.vertices, rig.triangles))
        if bind_pairs:
            warnings.warn(f"{rig.name}: the bind pose itself has {bind_pairs} intersecting skin triangle pairs; the "
                          "pre-roll starts from them and cannot undo them", stacklevel=3)
        n = self.preroll_steps
        u = np.arange(1, n + 1) / n
        u = u * u * (3.0 - 2.0 * u)  # ease in and out
        t0 = self.plan.times[0]
        pre = np.stack([rig.skinning_matrices_from_bind(self.clip, t0, float(x)) for x in u])
        start = rig.skinning_matrices_from_bind(self.clip, t0, 0.0)  # the bind pose, where frame 0 puts the root
        pre_dev = wp.array(pre.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=self.dev)
        j = self.joint_count
        a = self.state_a
        h = self.preroll / n
        for attempt in range(MAX_GROWTHS + 1):
            # from the bind pose into the first frame's pose: one step recorded per state parity
            # and replayed (bit-identical to plain launches), the pose copied in before each
            steps = self._preroll_graphs(h) if n > 4 else {}
            initial_state(self.model, a, start)
            sa, sb = a, self.state_b
            for s in range(n):
                wp.copy(self.control.skin_matrices, pre_dev, dest_offset=0, src_offset=s * j, count=j)
                graph = steps.get(id(sa))
                if graph is not None:
                    wp.capture_launch(graph)
                else:
                    self.solver.step(sa, sb, self.control, self.contacts, h)
                sa, sb = sb, sa
            if sa is not a:
                for name in ("x", "q", "contact_reach"):
                    wp.copy(getattr(a, name), getattr(sa, name))
            a.v.zero_()
            a.omega.zero_()
            if self.contacts is None or not self.contacts.overflowed():
                break
            if attempt == MAX_GROWTHS:
                raise SimulationError(f"pre-roll: more than {self.contacts.capacity} contact candidates even after growing "
                                      f"the buffers {MAX_GROWTHS} times; lower [collision] detection_margin or thickness")
            self.contacts.grow()
        if not np.isfinite(a.x.numpy()).all():
            raise SimulationError("pre-roll: a particle became NaN or inf; lower dt or shorten the pre-roll's motion")

    # ------------------------------------------------------------------ the stepper protocol
    def meshes(self) -> list:
        return []  # the driver decides what is written

    def advance(self, i: int) -> None:
        """Step from frame ``i - 1`` to frame ``i`` (nothing for the first frame)."""
        if i > 0:
            self._step_frame(i)
        self._read()
        bad = first_non_finite(self._x)
        if bad is not None:
            layer, vert = divmod(bad, self.model.vertex_count)
            raise SimulationError(
                f"frame {self.plan.frames[i]}: particle {bad} ({LAYER_NAMES[layer]} layer, vertex {vert}) became NaN or "
                "inf; lower dt or raise damping/iterations"
            )

    def _step_frame(self, i: int) -> None:
        j, g, substeps = self.joint_count, self.group_count, self.substeps
        wp.copy(self.staging, self.poses_dev, dest_offset=0, src_offset=(i - 1) * substeps * j, count=substeps * j)
        if self.act_staging is not None:
            wp.copy(self.act_staging, self.act_dev, dest_offset=0, src_offset=(i - 1) * substeps * g, count=substeps * g)
        contacts = self.contacts
        if contacts is not None:
            self.backup.assign(self.state_a)
            self.collision.maybe_rebuild(self._skin)  # the previous frame's skin (host copy)
        growths = 0
        while True:
            graph = self.graphs.get(id(self.state_a))
            if graph is not None:
                wp.capture_launch(graph)
                if substeps % 2:
                    self.state_a, self.state_b = self.state_b, self.state_a
            else:
                self.state_a, self.state_b = self._run_frame(self.state_a, self.state_b)
            if contacts is None or not contacts.overflowed():
                break
            if not np.isfinite(self.state_a.x.numpy()).all():
                contacts.clear_overflow()  # NaN boxes overlap everything: report the NaN below
                break
            if growths >= MAX_GROWTHS:
                raise SimulationError(
                    f"frame {self.plan.frames[i]}: more than {contacts.capacity} contact candidates even after growing "
                    f"the buffers {MAX_GROWTHS} times; lower [collision] detection_margin or thickness"
                )
            # more contact candidates than the buffers hold: grow them and redo the frame
            if substeps % 2:
                self.state_a, self.state_b = self.state_b, self.state_a
            self.state_a.assign(self.backup)
            contacts.grow()
            self.overflow_retries += 1
            growths += 1
            self.graphs = self._capture_graphs()
        # the fail-safe's pair list, short in the last step: larger from the next frame on (a
        # short list only costs time: the fail-safe then queries the tree from every triangle)
        if contacts is not None and contacts.grow_pairs(PAIR_LIMIT * self.model.collision.triangle_count):
            self.graphs = self._capture_graphs()

    def _read(self) -> None:
        self._x = self.state_a.x.numpy()
        self._skin = self._x[: self.model.vertex_count]

    def frame(self, i: int) -> dict[str, np.ndarray]:
        """``{"skin": [V, 3]}`` plus ``layer_fat``, ``layer_muscle``, ``layer_bone``."""
        v = self.model.vertex_count
        x = self._x
        out = {"skin": self._skin}
        for k in range(1, 4):
            out[f"layer_{LAYER_NAMES[k]}"] = x[k * v:(k + 1) * v]
        return out

    # ------------------------------------------------------------------ measurements
    @property
    def positions(self) -> np.ndarray:
        """All particle positions of the last frame [m], ``[4V, 3]`` (host)."""
        return self._x

    def velocities(self) -> np.ndarray:
        """Particle velocities of the current state [m/s], ``[4V, 3]`` (syncs)."""
        return self.state_a.v.numpy()

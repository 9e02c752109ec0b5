"""The multi-layer skin model: built once on the host, uploaded once to a Warp device.

``SkinModelBuilder(rig, params).finalize(device)`` runs every preprocessing stage of Deul &
Bender 2013 (layers, masses, regions, fast-summation paths and runs, sub-volumes, joint
constraints, kinematic coupling) and returns a :class:`SkinModel` of static ``wp.array``s.
``model.state()`` and ``model.control()`` make the time-varying arrays the solver advances.

Particles are numbered layer-major: ``k * V + i`` for vertex ``i`` on layer ``k`` in
(skin, fat, muscle, bone).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .errors import SceneError
from .preprocess.bones import Bones, bone_segments
from .preprocess.joint_constraints import JointConstraints, JointParams, build_joint_constraints
from .preprocess.kinematic_coupling import KinematicCoupling, build_kinematic_coupling
from .preprocess.layers import LAYER_NAMES, LayerParams, Layers, build_layers, check_layer_folds
from .preprocess.masses import particle_masses
from .preprocess.regions import Regions, build_regions, particle_radii
from .device import resolve_device
from .rig import Rig, RigError

__all__ = ["ModelParams", "SkinModelBuilder", "SkinModel", "State", "Control"]


@dataclass
class ModelParams:
    """Everything an artist sets for the model (Table 1 of the paper, plus the rest).

    Attributes:
        layers: Projection parameters (fat, muscle, bone), with per-bone overrides.
        stiffness: Shape-matching stiffness per layer (skin, fat, muscle, bone), each in [0, 1].
            The paper's Arm: 0.8/0.6/0.7/0.8.
        stiffness_per_bone: Overrides by joint name, four values each.
        density: Tissue density [kg/m^3].
        omega: Region size (omega-ring).
        coupling_stiffness: Bone layer to LBS distance-constraint stiffness in [0, 1].
        joints: Joint-constraint selection.
        subvolumes: Sub-volume cutting planes (``warpskin.preprocess.sub_volumes.SubVolumeParams``);
            ``None`` for the defaults.
        volume: False skips the sub-volumes (no volume constraints).
    """

    layers: LayerParams = field(default_factory=LayerParams)
    stiffness: tuple[float, float, float, float] = (0.8, 0.6, 0.7, 0.8)
    stiffness_per_bone: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    density: float = 1000.0
    omega: int = 1
    coupling_stiffness: float = 1.0
    joints: JointParams = field(default_factory=JointParams)
    subvolumes: object | None = None
    volume: bool = True

    def check(self, where: str = "model") -> None:
        self.layers.check(where)
        for name, s in [("default", self.stiffness)] + list(self.stiffness_per_bone.items()):
            s = tuple(s)
            if len(s) != 4 or not all(0.0 <= float(x) <= 1.0 for x in s):
                raise SceneError(f"{where}: stiffness of {name!r} must be four numbers in [0, 1] (skin, fat, muscle, bone), got {s}")
        if not (np.isfinite(self.density) and self.density > 0):
            raise SceneError(f"{where}: density must be a positive number [kg/m^3], got {self.density}")
        if int(self.omega) != self.omega or self.omega < 1:
            raise SceneError(f"{where}: omega must be an integer >= 1, got {self.omega}")
        if not (0.0 <= self.coupling_stiffness <= 1.0):
            raise SceneError(f"{where}: coupling stiffness must be in [0, 1], got {self.coupling_stiffness}")


class SkinModelBuilder:
    """Builds the multi-layer model of a closed rig on the host.

    Args:
        rig: A rig with a closed, manifold, consistently wound surface.
        params: Model parameters; defaults are the paper's Arm values.

    Attributes (after :meth:`build`): ``bones``, ``layers``, ``masses``, ``radii``, ``regions``,
    ``paths``, ``runs``, ``subvolumes``, ``coupling``, ``joint_constraints``, ``timings`` (seconds
    per stage).
    """

    def __init__(self, rig: Rig, params: ModelParams | None = None) -> None:
        self.rig = rig
        self.params = params or ModelParams()
        self.where = rig.source or rig.name
        self.timings: dict[str, float] = {}
        self._built = False

    def _stage(self, name: str, fn):
        t0 = time.perf_counter()
        out = fn()
        self.timings[name] = time.perf_counter() - t0
        return out

    def build(self) -> SkinModelBuilder:
        """Run every preprocessing stage (idempotent)."""
        if self._built:
            return self
        rig, p = self.rig, self.params
        p.check(self.where)
        rig.require_closed()
        self.bones: Bones = self._stage("bones", lambda: bone_segments(rig))
        self.layers: Layers = self._stage("layers", lambda: build_layers(rig, p.layers, bones=self.bones))
        self._stage("layer_check", lambda: check_layer_folds(self.layers, rig.triangles, where=self.where))
        self.masses = self._stage("masses", lambda: particle_masses(self.layers, rig.triangles, density=p.density, where=self.where))
        self.radii = self._stage("radii", lambda: particle_radii(self.layers, rig.triangles))
        self.regions: Regions = self._stage("regions", lambda: build_regions(self.layers, rig.triangles, self.masses, omega=p.omega))

        from .preprocess.fast_summation import build_path_layout, region_runs

        # paths of at most 32 vertices: the scan runs one thread per path and layer, and the
        # unbounded layout is one path per layer on a tube (4 threads; 36 ms on an H100 against
        # 1.6 ms for the direct gather). Runs per region rise only slightly.
        self.paths = self._stage(
            "paths",
            lambda: build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices, max_path_length=32),
        )
        self.runs = self._stage("runs", lambda: region_runs(self.paths, self.regions.ring_offsets, self.regions.ring_members))
        if p.volume:
            from .preprocess.sub_volumes import build_subvolumes

            self.subvolumes = self._stage("subvolumes", lambda: build_subvolumes(rig, p.subvolumes, bones=self.bones))
        else:
            self.subvolumes = None
        self.coupling: KinematicCoupling = self._stage(
            "coupling", lambda: build_kinematic_coupling(rig, self.layers, stiffness=p.coupling_stiffness)
        )
        self.joint_constraints: JointConstraints = self._stage(
            "joint_constraints", lambda: build_joint_constraints(rig, self.layers, p.joints)
        )
        self.stiffness = self._particle_stiffness()
        self._built = True
        return self

    def _particle_stiffness(self) -> np.ndarray:
        per_joint = np.tile(np.asarray(self.params.stiffness, dtype=np.float64), (self.rig.joint_count, 1))
        for name, s in self.params.stiffness_per_bone.items():
            per_joint[self.rig.skeleton.index(name)] = s
        return per_joint[self.layers.bone].T.reshape(-1)  # [4, V] -> layer-major [4V]

    def summary(self) -> dict:
        """Counts and statistics of the built model (what ``warpskin layers`` prints)."""
        self.build()
        out = {
            "vertices": self.rig.vertex_count,
            "particles": 4 * self.rig.vertex_count,
            "total_mass_kg": float(self.masses.sum()),
            "omega": self.regions.omega,
            "mean_region_size": self.regions.mean_region_size,
            "paths": int(self.paths.path_count),
            "mean_runs_per_region": float(self.runs.mean_runs_per_region),
            "joint_constraints": self.joint_constraints.count,
            "subvolumes": len(self.subvolumes.names) if self.subvolumes is not None else 0,
            "timings_s": dict(self.timings),
        }
        return out

    def finalize(self, device=None) -> SkinModel:
        """Build (if needed) and upload everything once. Returns the :class:`SkinModel`."""
        self.build()
        return SkinModel(self, resolve_device(device))


def _i32(a) -> np.ndarray:
    a = np.asarray(a)
    if a.size and (a.max() > np.iinfo(np.int32).max):
        raise RigError("model too large for 32-bit indices")
    return a.astype(np.int32)


class SkinModel:
    """Static simulation data on one device (``wp.array``s), plus the host builder for
    inspection.

    Array names follow the entity they index: ``particle_*`` ``[4V]``, ``region_*`` (CSR over
    regions, ``[4V+1]`` offsets), ``path_*``, ``run_*``, ``coupling_*`` ``[V]``; only what the
    kernels read is uploaded.
    """

    def __init__(self, builder: SkinModelBuilder, device) -> None:
        b = builder
        self.builder = b
        self.device = device
        self.rig = b.rig
        self.vertex_count = b.rig.vertex_count
        self.particle_count = 4 * self.vertex_count
        self.joint_count = b.rig.joint_count
        reg = b.regions
        v3 = lambda a: wp.array(np.asarray(a, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=device)
        f32 = lambda a: wp.array(np.asarray(a, dtype=np.float32), dtype=wp.float32, device=device)
        i32 = lambda a: wp.array(_i32(a), dtype=wp.int32, device=device)
        with wp.ScopedDevice(device):
            self.tri_indices = wp.array(_i32(b.rig.triangles), dtype=wp.int32, device=device)
            self.particle_q0 = v3(b.layers.flat())
            self.particle_mass = f32(b.masses)
            self.particle_inv_mass = f32(1.0 / b.masses)
            self.particle_stiffness = f32(b.stiffness)
            self.region_offsets = i32(reg.region_offsets)
            self.region_members = i32(reg.region_members)
            self.region_sibling_count = i32(reg.sibling_count)
            self.region_rest_offsets = v3(reg.rest_offsets)
            # rest centres for the fast summation, in float64 from the float32 rest positions
            # and masses the kernels read: A = S2 - S1 c0^T cancels large terms, and a float32
            # c0 (or one from unrounded data) left up to 2e-3 rotation error in small regions
            q0 = np.asarray(b.layers.flat(), dtype=np.float32).astype(np.float64)
            m32 = np.asarray(b.masses, dtype=np.float32).astype(np.float64)
            seg = reg.region_offsets
            mem = reg.region_members
            mx0 = np.add.reduceat(m32[mem, None] * q0[mem], seg[:-1], axis=0)
            msum = np.add.reduceat(m32[mem], seg[:-1])
            self.region_rest_com = wp.array(mx0 / msum[:, None], dtype=wp.vec3d, device=device)
            self.region_mass = f32(reg.region_mass)
            self.particle_region_offsets = i32(reg.particle_offsets)
            self.particle_regions = i32(reg.particle_regions)
            self.particle_region_slots = i32(reg.particle_slots)
            self.path_order = i32(b.paths.order)
            self.path_offsets = i32(b.paths.path_offsets)
            self.run_offsets = i32(b.runs.run_offsets)
            self.run_start = i32(b.runs.run_start)
            self.run_end = i32(b.runs.run_end)
            c = b.coupling
            self.coupling_rest = v3(c.rest)
            self.coupling_joint_indices = i32(np.clip(c.joint_indices, 0, self.joint_count - 1))
            self.coupling_joint_weights = f32(c.joint_weights)
            self.coupling_stiffness = float(c.stiffness)
            jc = b.joint_constraints
            self.joint_rest = v3(jc.joint_rest)
            # the joint constraints' and sub-volumes' device data live with the solver and
            # VolumeConstraints, which build their own layouts from the builder
            self.subvolume_count = len(b.subvolumes.names) if b.subvolumes is not None else 0

    def state(self) -> State:
        """A rest state: positions at rest, zero velocities, identity orientations."""
        return State(self)

    def control(self) -> Control:
        """Per-frame drive: skinning matrices of the joints (identity = bind pose)."""
        return Control(self)


class State:
    """What the solver advances: particle positions ``x`` [m], velocities ``v`` [m/s],
    orientations ``q`` and angular velocities ``omega`` [rad/s], all ``[4V]``."""

    def __init__(self, model: SkinModel) -> None:
        n = model.particle_count
        with wp.ScopedDevice(model.device):
            self.x = wp.clone(model.particle_q0)
            self.v = wp.zeros(n, dtype=wp.vec3)
            self.q = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), dtype=wp.quat)
            self.omega = wp.zeros(n, dtype=wp.vec3)


class Control:
    """What drives a frame: the joints' skinning matrices ``G_j(t) inverse_bind_j``, ``[J]``."""

    def __init__(self, model: SkinModel) -> None:
        self.model = model
        self.skin_matrices = wp.array(np.tile(np.eye(4, dtype=np.float32), (model.joint_count, 1, 1)), dtype=wp.mat44, device=model.device)
        self._host = np.zeros((model.joint_count, 4, 4), dtype=np.float32)

    def set_pose(self, skin_matrices: np.ndarray) -> None:
        """Upload skinning matrices ``[J, 4, 4]`` (from ``rig.skinning_matrices(clip, t)``)."""
        m = np.asarray(skin_matrices)
        if m.shape != self._host.shape:
            raise RigError(f"expected skinning matrices of shape {self._host.shape}, got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise RigError("skinning matrices hold NaN or inf")
        self._host[:] = m
        self.skin_matrices.assign(self._host)


__all__ += ["LAYER_NAMES"]

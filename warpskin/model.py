"""The multi-layer skin model: built once on the host, uploaded once to a Warp device.

``SkinModelBuilder(rig, params).finalize(device)`` runs every preprocessing stage of Deul &
Bender 2013 (layers, masses, regions, fast-summation paths and runs, sub-volumes, joint
constraints, kinematic coupling) and returns a :class:`SkinModel` of static ``wp.array``s.
``model.state()``, ``model.control()`` and ``model.contacts()`` make the time-varying arrays:
what the solver advances, what drives a frame and the collision buffers (Newton's pattern).

Particles are numbered layer-major: ``k * V + i`` for vertex ``i`` on layer ``k`` in
(skin, fat, muscle, bone).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import warp as wp

from .errors import InputError, SceneError
from .collision import CollisionParams, collision_topology, mean_edge, upload_collision
from .metrics import signed_volume
from .preprocess.bones import Bones, bone_segments
from .preprocess.fast_summation import build_path_layout, region_runs
from .preprocess.joint_constraints import JointConstraints, JointParams, build_joint_constraints
from .preprocess.kinematic_coupling import KinematicCoupling, build_kinematic_coupling
from .preprocess.layers import LAYER_NAMES, LayerParams, Layers, build_layers, check_layer_folds, fit_piece_depths
from .preprocess.masses import particle_masses
from .preprocess.refine import default_max_edge
from .preprocess.regions import Regions, build_regions, particle_radii
from .device import resolve_device
from .preprocess.sub_volumes import SubVolumes, build_subvolumes
from .settings import check_settings, setting
from .rig import Rig
from .skinning import dual_quaternions
from .transforms import linear_blend_skin
from .units import extent
from .volume import upload_volume_layout, volume_layout

__all__ = ["ModelParams", "SkinModelBuilder", "SkinModel", "State", "Control", "Contacts", "RestLayers",
           "model_host_arrays"]


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
        collision: The skin self-collision model (thickness, friction, margins); with
            ``enabled = False`` the model has no contact data and ``model.contacts()`` is
            ``None``.
        refine: Simulate a coarse skin on a refined copy
            (:func:`warpskin.preprocess.refine.refine_long_edges`: every edge longer than
            ``max_edge`` split at its midpoint, the surface unchanged; the file's vertices are
            what is written). With ``max_edge`` unset, a skin is coarse when its mean edge is
            longer than :data:`COARSE_EDGE` x :func:`~warpskin.preprocess.refine.default_max_edge`
            (edges of about 1000 vertices over its area): a low-poly mesh's one-ring regions
            span its joints and hold bent limbs straight.
        max_edge: Longest simulated edge [m]; ``None`` for the default (coarse skins only).
    """

    _section = "layers"

    layers: LayerParams = field(default_factory=LayerParams)
    stiffness: tuple[float, float, float, float] = setting(
        (0.8, 0.6, 0.7, 0.8), "numbers", "shape-matching stiffness per layer: skin, fat, muscle, bone", length=4,
        low=0.0, high=1.0, must="four numbers in [0, 1] (skin, fat, muscle, bone)")
    stiffness_per_bone: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)
    density: float = setting(1000.0, "number", "tissue density", unit="kg/m^3", low=0.0, open_low=True,
                             must="a positive number")
    omega: int = setting(1, "integer", "region size: the omega-ring of a particle", low=1)
    coupling_stiffness: float = setting(1.0, "number", "stiffness of the bone layer's coupling to LBS", low=0.0,
                                        high=1.0, must="in [0, 1]")
    joints: JointParams = field(default_factory=JointParams)
    subvolumes: object | None = None
    volume: bool = setting(True, "bool", "per-joint sub-volume volume constraints (false: none)", section="subvolumes",
                           key="enabled")
    collision: CollisionParams = field(default_factory=CollisionParams)
    refine: bool = setting(True, "bool", "simulate a coarse skin on a refined copy (the file's vertices are what is "
                           "written)")
    max_edge: float | None = setting(None, "number", "refine any skin to edges of at most this (default: coarse "
                                     "skins only, to about 1000 vertices over its area)", unit="m", low=0.0,
                                     open_low=True, optional=True, must="a positive length [m]")

    def check(self, where: str = "model") -> None:
        """Every setting in its declared range, the projection parameters ordered, the per-bone
        stiffness four numbers in [0, 1] each.

        Raises:
            SceneError: one line naming the setting, the value and what is allowed.
        """
        self.layers.check(where)
        for name, s in [("default", self.stiffness)] + list(self.stiffness_per_bone.items()):
            s = tuple(s)
            if len(s) != 4 or not all(0.0 <= float(x) <= 1.0 for x in s):
                raise SceneError(f"{where}: stiffness of {name!r} must be four numbers in [0, 1] (skin, fat, muscle, bone), got {s}")
        check_settings(self, where, "layers")
        check_settings(self, where, "subvolumes")
        self.collision.check(where)


#: A skin is coarse (refined by default) when its mean edge is longer than this share of
#: :func:`~warpskin.preprocess.refine.default_max_edge` (about 1000 vertices over its area): a
#: game mesh of a few hundred vertices is, a skin of a few thousand is not.
COARSE_EDGE = 0.9


def written_surface(rig: Rig):
    """The loaded mesh of a refined ``rig`` as one closed "sub-volume" without fans
    (:class:`~warpskin.preprocess.sub_volumes.SubVolumes`), for a volume constraint on what is
    written."""
    tris = np.asarray(rig.output_triangles, dtype=np.int64)
    n = rig.output_count
    return SubVolumes(
        names=["written mesh"], triangles=tris, tri_offsets=np.array([0, len(tris)]), tri_indices=np.arange(len(tris)),
        fan_offsets=np.array([0, 0]), fan_triangles=np.zeros((0, 3), dtype=np.int64), center_rest=np.zeros((0, 3)),
        center_joint=np.zeros(0, dtype=np.int64), loops=[], rest_volume=np.array([signed_volume(rig.vertices[:n], tris)]),
        plane_joint=np.zeros(0, dtype=np.int64), plane_t=np.zeros(0), plane_normal=np.zeros((0, 3)),
        plane_sides=np.zeros((0, 2), dtype=np.int64), vertex_count=rig.vertex_count)


def refine_coarse(rig: Rig, max_edge: float | None = None) -> Rig:
    """``rig`` refined for the simulation (:meth:`Rig.refined`) where its skin is coarse, or
    everywhere an edge is longer than an explicit ``max_edge``; ``rig`` itself otherwise."""
    if max_edge is None:
        max_edge = default_max_edge(rig.vertices, rig.triangles)
        if mean_edge(rig.vertices, rig.triangles) <= COARSE_EDGE * max_edge:
            return rig
    return rig.refined(float(max_edge))


class SkinModelBuilder:
    """Builds the multi-layer model of a closed rig on the host.

    Args:
        rig: A rig with a closed, manifold, consistently wound surface.
        params: Model parameters; defaults are the paper's Arm values.

    Attributes (after :meth:`build`): ``bones``, ``layers``, ``masses``, ``radii``, ``regions``,
    ``paths``, ``runs``, ``subvolumes``, ``coupling``, ``joint_constraints``, and the solver's
    host layouts ``solver_layout`` (joint-constraint CSR, fast-summation path starts,
    oriented-particle moments, float64 region rest centres), ``volume_layout``
    (:class:`~warpskin.volume.VolumeLayout` or ``None``), ``collision_topology``
    (:class:`~warpskin.collision.CollisionTopology`); ``rest_drive`` (rest-offset deltas of the
    muscle drive, ``[G, M, 3]``, or ``None``); ``timings`` (seconds per stage).

    Every host array the solver, the volume constraints and the self-collision read is made
    here; :meth:`finalize` is the only upload.
    """

    def __init__(self, rig: Rig, params: ModelParams | None = None) -> None:
        self.rig = rig
        self.params = params or ModelParams()
        self.where = rig.source or rig.name
        self.timings: dict[str, float] = {}
        self.rest_drive: np.ndarray | None = None
        self.rest_drive_swelling: np.ndarray | None = None
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
        if p.refine and not rig.refined_skin:
            rig = self.rig = self._stage("refine", lambda: refine_coarse(rig, p.max_edge))
        # the bones and the layers of the skin as loaded; a refined skin's added vertices get
        # their parents' mean (each refined layer triangle lies in a coarse one)
        loaded = rig.unrefined()
        self.bones: Bones = self._stage("bones", lambda: bone_segments(loaded))
        self.layers: Layers = self._stage("layers", lambda: build_layers(loaded, p.layers, bones=self.bones))
        if p.layers.adaptive:
            self.layers = self._stage("layer_depths", lambda: fit_piece_depths(loaded, self.layers, where=self.where))
        if loaded is not rig:
            self.layers = self.layers.refined(rig.vertex_parents)
        self._stage("layer_check", lambda: check_layer_folds(self.layers, rig.triangles, where=self.where))
        self.masses = self._stage("masses", lambda: particle_masses(self.layers, rig.triangles, density=p.density, where=self.where))
        self.radii = self._stage("radii", lambda: particle_radii(self.layers, rig.triangles))
        self.regions: Regions = self._stage("regions", lambda: build_regions(self.layers, rig.triangles, self.masses, omega=p.omega))


        # paths of at most 32 vertices: the scan runs one thread per path and layer, and the
        # unbounded layout can be one path per layer on a tube (four threads for the whole
        # scan, far slower than the direct gather on a GPU); runs per region rise only slightly
        self.paths = self._stage(
            "paths",
            lambda: build_path_layout(rig.triangles, rig.vertex_count, vertices=rig.vertices, max_path_length=32),
        )
        self.runs = self._stage("runs", lambda: region_runs(self.paths, self.regions.ring_offsets, self.regions.ring_members))
        if p.volume:
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
        self.solver_layout = self._stage("solver_layout", self._solver_layout)
        if self.subvolumes is not None:
            self.volume_layout = self._stage("volume_layout", lambda: volume_layout(self.subvolumes))
        else:
            self.volume_layout = None
        self.collision_topology = self._stage("collision_topology", lambda: collision_topology(rig))
        self._built = True
        return self

    def _solver_layout(self) -> dict[str, np.ndarray]:
        """Host arrays of :class:`~warpskin.solver.SkinSolver` (see :class:`SkinModel`)."""
        n = 4 * self.rig.vertex_count
        v = self.rig.vertex_count
        out: dict[str, np.ndarray] = {}
        out["particle_moment"] = (self.masses * self.radii**2 / 5.0).astype(np.float32)
        # joint constraints as a per-particle CSR (a particle near two joints has two)
        jc = self.joint_constraints
        order = np.argsort(jc.particles, kind="stable")
        offsets = np.zeros(n + 1, dtype=np.int32)
        np.cumsum(np.bincount(jc.particles, minlength=n), out=offsets[1:])
        out["joint_offsets"] = offsets
        out["joint_ids"] = jc.joints[order].astype(np.int32)
        out["joint_rest_distance"] = jc.rest_distance[order].astype(np.float32)
        # fast summation: first position of every non-empty path
        starts = np.zeros(v, dtype=np.int32)
        starts[self.paths.path_offsets[:-1][np.diff(self.paths.path_offsets) > 0]] = 1
        out["position_is_path_start"] = starts
        # rest centres for the fast summation, in float64 from the float32 rest positions
        # and masses the kernels read: A = S2 - S1 c0^T cancels large terms, and a float32
        # c0 (or one from unrounded data) left up to 2e-3 rotation error in small regions
        reg = self.regions
        q0 = np.asarray(self.layers.flat(), dtype=np.float32).astype(np.float64)
        m32 = np.asarray(self.masses, dtype=np.float32).astype(np.float64)
        seg, mem = reg.region_offsets, reg.region_members
        mx0 = np.add.reduceat(m32[mem, None] * q0[mem], seg[:-1], axis=0)
        msum = np.add.reduceat(m32[mem], seg[:-1])
        out["region_rest_com"] = mx0 / msum[:, None]
        return out

    def set_rest_drive(self, delta_offsets: np.ndarray, swelling: np.ndarray | None = None) -> SkinModelBuilder:
        """Let activations move the rest shape (muscle activation in the layered model).

        Args:
            delta_offsets: Change of every region rest offset when group g is fully active,
                ``[G, M, 3]`` [m] (M = region entries; see
                :func:`warpskin.popping.muscle_rest_offset_deltas`). ``Control.muscle_activation``
                ``[G]`` then drives it every step; the model's rest offsets stay as built.
            swelling: ``[V]`` per skin vertex, where the drive stretches the skin on purpose (a
                muscle's belly; :meth:`rest_drive_support`); default every vertex it can move.

        Returns:
            The builder (call before :meth:`finalize`).
        """
        self.build()
        d = np.asarray(delta_offsets, dtype=np.float32)
        m = self.regions.region_members.shape[0]
        if d.ndim != 3 or d.shape[1:] != (m, 3) or d.shape[0] < 1:
            raise InputError(f"rest-shape deltas must have shape [G, {m}, 3] with G >= 1, got {d.shape}")
        if not np.isfinite(d).all():
            raise InputError("rest-shape deltas hold NaN or inf")
        self.rest_drive = d
        if swelling is not None:
            sw = np.asarray(swelling, dtype=bool)
            if sw.shape != (self.rig.vertex_count,):
                raise InputError(f"swelling must have shape [{self.rig.vertex_count}], got {sw.shape}")
        self.rest_drive_swelling = None if swelling is None else sw
        return self

    def rest_drive_support(self) -> np.ndarray:
        """``[V]`` per skin vertex: where the rest-shape drive (:meth:`set_rest_drive`) stretches
        the skin on purpose: its ``swelling`` where given, else whether it can move the vertex at
        all (a particle of its column, any layer, belongs to a region whose rest offsets some
        group changes). All ``False`` without a drive."""
        self.build()
        v = self.rig.vertex_count
        if self.rest_drive is None:
            return np.zeros(v, dtype=bool)
        if self.rest_drive_swelling is not None:
            return self.rest_drive_swelling.copy()
        reg = self.regions
        changed = np.zeros(reg.region_count, dtype=bool)
        changed[reg.region_of_entry()[np.any(self.rest_drive != 0.0, axis=(0, 2))]] = True
        moved = np.zeros(4 * v, dtype=bool)
        moved[reg.region_members[changed[reg.region_of_entry()]]] = True
        return moved.reshape(4, v).any(axis=0)

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
            "depth_reduced_vertices": int((self.layers.depth_scale < 1.0).sum()),
            "min_depth_scale": float(self.layers.depth_scale.min()),
            "depth_notes": list(self.layers.depth_notes),
            "timings_s": dict(self.timings),
        }
        return out

    def finalize(self, device=None) -> SkinModel:
        """Build (if needed) and upload everything once. Returns the :class:`SkinModel`.

        The same path as a batch of characters (:func:`warpskin.batch_model.batch_model`):
        :func:`model_host_arrays`, then one :class:`SkinModel` upload."""
        self.build()
        return SkinModel(model_host_arrays(self), resolve_device(device))


@dataclass(frozen=True)
class RestLayers:
    """One character's layers at rest and its skin weights on the host (float64, as built):
    what puts a state at a pose (:meth:`skin`, :func:`warpskin.run.physics.initial_state`).

    Attributes:
        points: ``[4 V_c, 3]`` the particles at rest, layer-major.
        joint_indices, joint_weights: ``[V_c, K]`` the skin's influences (the rig's).
        bone: ``[V_c]`` the joint each vertex's column is oriented by (its dominant bone).
        joint_start: Its first joint in the model's joints (0 for one character).
        joint_count: Its joints.
    """

    points: np.ndarray
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    bone: np.ndarray
    joint_start: int = 0
    joint_count: int = 0

    def skin(self, skin_matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(x [4 V_c, 3], q [4 V_c, 4])`` float32: every particle skinned with its vertex's
        weights at its own joints' ``skin_matrices`` ``[joint_count, 4, 4]`` (LBS in float64),
        and oriented like its vertex's bone."""
        ji = np.tile(self.joint_indices, (4, 1))
        jw = np.tile(self.joint_weights, (4, 1))
        x = linear_blend_skin(self.points, ji, jw, skin_matrices)
        q_joint, _, _ = dual_quaternions(skin_matrices)  # rotation part of every joint
        q = np.tile(q_joint[self.bone], (4, 1))
        return x.astype(np.float32), q.astype(np.float32)


def _i32(a) -> np.ndarray:
    a = np.asarray(a)
    if a.size and (a.max() > np.iinfo(np.int32).max):
        raise InputError("model too large for 32-bit indices")
    return a.astype(np.int32)


def model_host_arrays(b: SkinModelBuilder) -> dict:
    """The host arrays :class:`SkinModel` uploads for one built character (NumPy; the keys are
    the model's attribute names, see there), and the sizes and scalars beside them:
    ``vertex_count``, ``joint_count``, ``coupling_stiffness``, ``vertex_diagonal`` ``[V]``
    (the body's diagonal [m] at every vertex), ``output_count`` and ``vertex_loaded`` ``[V]``
    (1 on the loaded mesh's vertices, 0 on those a refinement added), ``written_surface`` (the
    loaded mesh of a refined skin with volume, else ``None``) and ``vertex_written_volume``
    ``[V]`` (1 where it applies), ``rest_drive`` (``[G, M, 3]``
    or ``None``), ``subvolume_count``, ``volume_layout`` and ``volume_centres`` (the
    :class:`~warpskin.preprocess.sub_volumes.SubVolumes`, or ``None``), and per character (one
    here; a batch's in order) ``rest`` (its :class:`RestLayers`), ``mean_edges`` (its simulated
    skin's mean rest edge) and ``character_diagonals`` (its rest diagonal) ; ``collision``: the
    self-collision's host form (``topology``, ``params``, ``vertices``, ``triangles``,
    ``output_triangles``; a batch adds ``rigid_bone`` and ``characters``), ``None`` with it off,
    and ``collision_params`` (its :class:`~warpskin.params.CollisionParams`, on or off)."""
    rig = b.rig
    reg = b.regions
    lay = b.solver_layout
    c = b.coupling
    v = rig.vertex_count
    joints = rig.joint_count
    # the volume constraints' weights along the normals (SolverParams.volume_along_normals):
    # a skin particle lighter than the median (thin tissue, near its bone) takes no larger
    # share of a sub-volume's correction
    skin_mass = b.masses[:v]
    return {
        "vertex_count": v,
        "joint_count": joints,
        "tri_indices": np.asarray(rig.triangles),
        "particle_q0": np.asarray(b.layers.flat(), dtype=np.float32),
        "particle_mass": np.asarray(b.masses),
        "volume_inv_mass": 1.0 / np.maximum(b.masses, np.median(skin_mass)),
        "particle_stiffness": np.asarray(b.stiffness),
        "particle_moment": lay["particle_moment"],
        "region_offsets": reg.region_offsets,
        "region_members": reg.region_members,
        "region_sibling_count": reg.sibling_count,
        "region_rest_offsets": np.asarray(reg.rest_offsets, dtype=np.float32).reshape(-1, 3),
        "region_rest_com": lay["region_rest_com"],
        "region_mass": np.asarray(reg.region_mass),
        "particle_region_offsets": reg.particle_offsets,
        "particle_regions": reg.particle_regions,
        "particle_region_slots": reg.particle_slots,
        "path_order": b.paths.order,
        "path_offsets": b.paths.path_offsets,
        "position_is_path_start": lay["position_is_path_start"],
        "run_offsets": b.runs.run_offsets,
        "run_start": b.runs.run_start,
        "run_end": b.runs.run_end,
        "coupling_rest": np.asarray(c.rest, dtype=np.float32).reshape(-1, 3),
        "coupling_joint_indices": np.clip(c.joint_indices, 0, joints - 1),
        "coupling_joint_weights": np.asarray(c.joint_weights),
        "coupling_stiffness": float(c.stiffness),
        "joint_rest": np.asarray(b.joint_constraints.joint_rest, dtype=np.float32).reshape(-1, 3),
        "vertex_tissue_depth": np.linalg.norm(b.layers.positions[3] - b.layers.positions[0], axis=1),
        "vertex_diagonal": np.full(v, rig.size(), dtype=np.float64),
        "extent": extent(rig.vertices),
        "joint_offsets": lay["joint_offsets"],
        "joint_ids": lay["joint_ids"],
        "joint_rest_distance": lay["joint_rest_distance"],
        "rest_drive": b.rest_drive,
        "subvolume_count": len(b.subvolumes.names) if b.subvolumes is not None else 0,
        "volume_layout": b.volume_layout if b.subvolumes is not None else None,
        "volume_centres": b.subvolumes,
        "output_count": int(rig.output_count),
        "vertex_loaded": (np.arange(v) < rig.output_count).astype(np.int32),
        "written_surface": written_surface(rig) if (rig.refined_skin and b.subvolumes is not None) else None,
        "vertex_written_volume": np.full(v, int(rig.refined_skin and b.subvolumes is not None), dtype=np.int32),
        "rest": [RestLayers(np.asarray(b.layers.flat(), dtype=np.float64), np.asarray(rig.joint_indices),
                            np.asarray(rig.joint_weights), np.asarray(b.layers.bone), 0, joints)],
        "mean_edges": [b.collision_topology.mean_edge],
        "character_diagonals": [rig.size()],
        "collision_params": b.params.collision,
        "collision": {"topology": b.collision_topology, "params": b.params.collision, "vertices": rig.vertices,
                      "triangles": rig.triangles, "output_triangles": rig.output_triangles}
        if b.params.collision.enabled else None,
    }


class SkinModel:
    """Static simulation data on one device: ``wp.array`` objects, sizes and scalars, no host arrays.

    Array names follow the entity they index: ``particle_*`` ``[4V]``, ``region_*`` (CSR over
    regions, ``[4V+1]`` offsets), ``path_*``, ``run_*``, ``coupling_*`` ``[V]``, ``joint_*``
    (per-particle CSR of the joint constraints), ``subvolume_*``/``volume_*`` (the volume
    projection's layout, see :class:`~warpskin.volume.VolumeLayout`), ``edge_*``/``tri_*``
    (collision topology); ``rest_drive_offsets`` ``[G, M]`` for a muscle-driven rest shape.
    Built by :meth:`SkinModelBuilder.finalize` (the builder stays the host view) or, for
    several characters, by :func:`warpskin.batch_model.batch_model`: both upload host arrays of
    :func:`model_host_arrays`' layout here, once. Beside the device arrays the model keeps, on
    the host, only what puts a state at a pose (``rest``: each character's :class:`RestLayers`)
    and the written surface's definition (``written_surface``).
    """

    def __init__(self, host: dict, device) -> None:
        """Upload ``host`` (:func:`model_host_arrays`' layout: one character's, or a batch's,
        :func:`warpskin.batch_model.batch_host_arrays`) to ``device``."""
        h = host
        self.device = device
        self.vertex_count = int(h["vertex_count"])
        self.particle_count = 4 * self.vertex_count
        self.joint_count = int(h["joint_count"])
        self.triangle_count = int(h["tri_indices"].shape[0])
        v3 = lambda a: wp.array(np.asarray(a, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=device)
        f32 = lambda a: wp.array(np.asarray(a, dtype=np.float32), dtype=wp.float32, device=device)
        i32 = lambda a: wp.array(_i32(a), dtype=wp.int32, device=device)
        with wp.ScopedDevice(device):
            self.tri_indices = wp.array(_i32(h["tri_indices"]), dtype=wp.int32, device=device)
            self.particle_q0 = v3(h["particle_q0"])
            self.particle_mass = f32(h["particle_mass"])
            self.particle_inv_mass = f32(1.0 / h["particle_mass"])
            self.volume_inv_mass = f32(h["volume_inv_mass"])
            self.particle_stiffness = f32(h["particle_stiffness"])
            self.particle_moment = f32(h["particle_moment"])
            self.region_offsets = i32(h["region_offsets"])
            self.region_members = i32(h["region_members"])
            self.region_entry_count = int(h["region_members"].shape[0])
            self.region_sibling_count = i32(h["region_sibling_count"])
            self.region_rest_offsets = v3(h["region_rest_offsets"])
            self.region_rest_com = wp.array(h["region_rest_com"], dtype=wp.vec3d, device=device)
            self.region_mass = f32(h["region_mass"])
            self.particle_region_offsets = i32(h["particle_region_offsets"])
            self.particle_regions = i32(h["particle_regions"])
            self.particle_region_slots = i32(h["particle_region_slots"])
            self.path_order = i32(h["path_order"])
            self.path_offsets = i32(h["path_offsets"])
            self.path_count = int(h["path_offsets"].shape[0] - 1)
            self.position_is_path_start = i32(h["position_is_path_start"])
            self.run_offsets = i32(h["run_offsets"])
            self.run_start = i32(h["run_start"])
            self.run_end = i32(h["run_end"])
            self.coupling_rest = v3(h["coupling_rest"])
            self.coupling_joint_indices = i32(h["coupling_joint_indices"])
            self.coupling_joint_weights = f32(h["coupling_joint_weights"])
            self.coupling_stiffness = float(h["coupling_stiffness"])
            self.joint_rest = v3(h["joint_rest"])
            # tissue depth of every vertex at rest (skin to bone layer) [m], and the body's size
            self.vertex_tissue_depth = f32(h["vertex_tissue_depth"])
            self.diagonal = float(np.max(h["vertex_diagonal"], initial=0.0))
            #: the rest skin's largest bounding-box side [m] (a batch's: its characters', in order)
            self.extents = [float(e) for e in np.atleast_1d(h.get("extent", 0.0))]
            #: ``[V]`` float64: each vertex's body diagonal [m] (one value per character)
            self.vertex_diagonal = wp.array(np.asarray(h["vertex_diagonal"], dtype=np.float64), dtype=wp.float64,
                                            device=device)
            self.joint_offsets = i32(h["joint_offsets"])
            self.joint_ids = i32(h["joint_ids"])
            self.joint_rest_distance = f32(h["joint_rest_distance"])
            # muscle-driven rest shape (layered popping)
            drive = h["rest_drive"]
            self.rest_drive_group_count = 0 if drive is None else int(drive.shape[0])
            self.rest_drive_offsets = wp.array(drive, dtype=wp.vec3) if drive is not None else None
        self.subvolume_count = int(h["subvolume_count"])
        self.volume = upload_volume_layout(h["volume_layout"], h["volume_centres"], device) \
            if self.subvolume_count else None
        # a refined skin is written with the loaded mesh's triangles, chords of the simulated
        # surface: its volume is one more constraint, on the loaded vertices (host form, see
        # SkinSolver); vertex_loaded says which vertices those are (1: loaded, 0: added)
        self.output_count = int(h["output_count"])
        self.vertex_loaded = wp.array(np.asarray(h["vertex_loaded"], dtype=np.int32), dtype=wp.int32, device=device)
        self.written_surface = h.get("written_surface")
        #: ``[V]`` 1 where the vertex's character has the written mesh's volume constraint
        self.vertex_written_volume = wp.array(np.asarray(h["vertex_written_volume"], dtype=np.int32), dtype=wp.int32,
                                              device=device)
        self.collision_params = h.get("collision_params") or CollisionParams(enabled=False)
        self.collision = _upload_collision(h["collision"], device) if h.get("collision") is not None else None
        #: the characters of a batch (:func:`warpskin.batch_model.batch_model`); empty for one
        self.characters = list(h.get("characters", []))
        #: per character (one, or a batch's in order): its body diagonal [m], its simulated
        #: skin's mean rest edge, and its layers at rest (:class:`RestLayers`, on the host)
        self.character_diagonals = [float(d) for d in h["character_diagonals"]]
        self.mean_edges = [float(e) for e in h["mean_edges"]]
        self.rest: list[RestLayers] = list(h["rest"])

    def state(self) -> State:
        """A rest state: positions at rest, zero velocities, identity orientations."""
        return State(self)

    def control(self) -> Control:
        """Per-frame drive: skinning matrices of the joints (identity = bind pose) and the
        muscle activation of a rest-shape drive (zero)."""
        return Control(self)

    def contacts(self, capacity: int | None = None, pair_capacity: int | None = None) -> Contacts | None:
        """Collision buffers (``None`` when the model has self-collision switched off).

        Args:
            capacity: Candidate pairs per kind (default ``[collision] capacity``); they grow
                on overflow with :meth:`Contacts.grow`.
            pair_capacity: Nearby triangle pairs the detection lists for the fail-safe
                (default 8 per skin triangle); grown the same way.
        """
        if self.collision is None:
            return None
        return Contacts(self, capacity if capacity is not None else int(self.collision_params.capacity), pair_capacity)


def _upload_collision(c: dict, device):
    """The self-collision's device data from its host form (:func:`model_host_arrays`'
    ``collision``); a batch's ``rigid_bone`` and per-character ``characters`` replace the first
    character's."""
    surface = SimpleNamespace(vertices=c["vertices"], triangles=c["triangles"], output_triangles=c["output_triangles"])
    data = upload_collision(c["topology"], surface, c["params"], device)
    if c.get("rigid_bone") is not None:
        data.rigid_bone = wp.array(np.asarray(c["rigid_bone"], dtype=np.int32), dtype=wp.int32, device=device)
    if c.get("characters") is not None:
        data.characters = list(c["characters"])
    return data


class State:
    """What the solver advances: particle positions ``x`` [m], velocities ``v`` [m/s],
    orientations ``q`` and angular velocities ``omega`` [rad/s], all ``[4V]``, and each skin
    vertex's contact reach ``contact_reach`` ``[V]`` [m] (how much farther than the tether's
    cap recent contacts let it be from LBS: ``SolverParams.tether_contact``; 0 at rest)."""

    def __init__(self, model: SkinModel) -> None:
        n = model.particle_count
        with wp.ScopedDevice(model.device):
            self.x = wp.clone(model.particle_q0)
            self.v = wp.zeros(n, dtype=wp.vec3)
            self.q = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), dtype=wp.quat)
            self.omega = wp.zeros(n, dtype=wp.vec3)
            self.contact_reach = wp.zeros(model.vertex_count, dtype=wp.float32)

    def assign(self, other: State) -> None:
        """Copy ``other`` into this state (device copies, no allocation)."""
        for name in ("x", "v", "q", "omega", "contact_reach"):
            wp.copy(getattr(self, name), getattr(other, name))


class Control:
    """What drives a frame: the joints' skinning matrices ``G_j(t) inverse_bind_j`` ``[J]`` and,
    for a model with a rest-shape drive, the muscle activation ``[G]`` in [0, 1]."""

    def __init__(self, model: SkinModel) -> None:
        dev = model.device
        self.skin_matrices = wp.array(np.tile(np.eye(4, dtype=np.float32), (model.joint_count, 1, 1)), dtype=wp.mat44, device=dev)
        self.muscle_activation = wp.zeros(model.rest_drive_group_count, dtype=wp.float32, device=dev)
        self._host = np.zeros((model.joint_count, 4, 4), dtype=np.float32)

    def set_pose(self, skin_matrices: np.ndarray) -> None:
        """Upload skinning matrices ``[J, 4, 4]`` (from ``rig.skinning_matrices(clip, t)``)."""
        m = np.asarray(skin_matrices)
        if m.shape != self._host.shape:
            raise InputError(f"expected skinning matrices of shape {self._host.shape}, got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InputError("skinning matrices hold NaN or inf")
        self._host[:] = m
        self.skin_matrices.assign(self._host)

    def set_activation(self, activation) -> None:
        """Upload muscle activations ``[G]`` (the rest-shape drive's groups, in [0, 1])."""
        a = np.asarray(activation, dtype=np.float32).reshape(-1)
        g = self.muscle_activation.shape[0]
        if a.shape[0] != g:
            raise InputError(f"expected {g} muscle activations, got {a.shape[0]}")
        self.muscle_activation.assign(a)


class Contacts:
    """Skin self-collision buffers: candidate point-triangle and edge-edge pairs found by the
    detection of a step, their counts, the overflow flag and the per-particle colliding flags.

    ``counts`` is ``[point-triangle, edge-edge, overflow, triangle pairs]``; detection never
    writes past :attr:`capacity` but raises the flag, and the caller (the frame runner) checks
    :meth:`overflowed`, calls :meth:`grow` and repeats the frame, so no contact is dropped
    silently. Growing reallocates the pair buffers: graphs captured with the old ones must be
    captured again.
    """

    def __init__(self, model: SkinModel, capacity: int, pair_capacity: int | None = None) -> None:
        def positive(name, value):
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
                raise InputError(f"{name} must be a positive integer, got {value!r}")

        positive("contact capacity", capacity)
        if pair_capacity is not None:
            positive("pair capacity", pair_capacity)
        self.device = model.device
        with wp.ScopedDevice(self.device):
            # point-triangle, edge-edge, overflow flag, triangle pairs
            self.counts = wp.zeros(4, dtype=wp.int32)
            # views of the counters (never reallocated), made once
            self.pt_count, self.ee_count, self.overflow_flag = self.counts[0:1], self.counts[1:2], self.counts[2:3]
            self.pair_count = self.counts[3:4]
            self.colliding = wp.zeros(model.particle_count, dtype=wp.int32)
            self.active = wp.zeros(1, dtype=wp.int32)  # violated constraints in the last pass
        self._alloc(int(capacity))
        # the detection's list of nearby triangle pairs, for the fail-safe (see
        # SelfCollision.fail_safe): about 3 per triangle in a step; see grow_pairs
        if pair_capacity is None:
            pair_capacity = 8 * model.collision.triangle_count if model.collision is not None else 1
        self._alloc_pairs(int(pair_capacity))

    def _alloc(self, capacity: int) -> None:
        self.capacity = capacity
        with wp.ScopedDevice(self.device):
            self.pt_vertex = wp.zeros(capacity, dtype=wp.int32)
            self.pt_triangle = wp.zeros(capacity, dtype=wp.int32)
            self.ee_a = wp.zeros(capacity, dtype=wp.int32)
            self.ee_b = wp.zeros(capacity, dtype=wp.int32)
            self.ee_sign = wp.zeros(capacity, dtype=wp.float32)

    def _alloc_pairs(self, capacity: int) -> None:
        self.pair_capacity = capacity
        self.tri_pairs = wp.zeros((capacity, 2), dtype=wp.int32, device=self.device)

    def overflowed(self) -> bool:
        """Host check (syncs): did a detection since the last :meth:`clear_overflow` overflow?"""
        return bool(self.counts.numpy()[2])

    def clear_overflow(self) -> None:
        self.counts.zero_()

    def grow(self) -> None:
        """Double the candidate buffers until the last detection's counts fit."""
        c = self.counts.numpy()
        need = int(max(c[0], c[1]))
        cap = self.capacity
        while cap < need or cap == self.capacity:
            cap *= 2
        self._alloc(cap)
        self.counts.zero_()

    def grow_pairs(self, limit: int) -> bool:
        """Host check (syncs), between frames: when the last detection listed more triangle
        pairs than :attr:`pair_capacity`, double it until they fit, up to ``limit``; returns
        whether it grew (graphs captured with the old buffer must be captured again). A list
        that does not fit is never an error: the fail-safe then queries the tree from every
        triangle, as it would without a list."""
        n = int(self.counts.numpy()[3])
        if n <= self.pair_capacity or self.pair_capacity >= limit:
            return False
        cap = self.pair_capacity
        while cap < n and cap < limit:
            cap *= 2
        self._alloc_pairs(min(cap, limit))
        return True


__all__ += ["LAYER_NAMES"]

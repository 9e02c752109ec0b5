"""The physically-based skin solver: Algorithm 1 of Deul & Bender 2013 as Warp kernels.

Example:
    >>> model = SkinModelBuilder(rig, params).finalize("cpu")
    >>> solver = SkinSolver(model, SolverParams(iterations=20))
    >>> state_in, state_out, control, contacts = model.state(), model.state(), model.control(), model.contacts()
    >>> control.set_pose(rig.skinning_matrices(clip, t))
    >>> solver.step(state_in, state_out, control, contacts, 0.005)
    >>> state_in, state_out = state_out, state_in
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .collision import SelfCollision, skin_edges
from .errors import InputError, SceneError, SimulationError
from .params import SolverParams
from .kernels import chords as k_chord
from .kernels import constraints as k_con
from .kernels import integrate as k_int
from .kernels import shape_matching as k_sm
from .kernels import skinning as k_skin
from .metrics import self_intersections
from .model import Contacts, Control, SkinModel, State
from .units import UNITS, metres_per_unit
from .volume import VolumeConstraints

__all__ = ["SolverParams", "SkinSolver", "largest_step", "clean_at_rest", "SimulationError", "length_units", "particle_gravity", "GRAVITY_STEP",
           "gravity_step_limit", "skin_step_limit"]

#: The most a step may let gravity move a free particle (``g dt^2``), as a share of the skin's
#: mean rest edge: :func:`gravity_step_limit`.
GRAVITY_STEP = 0.05


def length_units(model: SkinModel, units: str = "auto") -> list[float]:
    """Metres per length unit of the file of each character of ``model`` (one for a single
    character; a batch's in order): 1 for ``units`` ``"file"``; for ``"auto"`` the power of ten
    that brings its rest skin nearest human size (:func:`warpskin.units.metres_per_unit` of its
    largest bounding-box side, ``model.extents``).

    Raises:
        SceneError: ``units`` is neither.
    """
    if units not in UNITS:
        raise SceneError(f"[solver] units must be 'auto' or 'file', got {units!r}")
    extents = list(getattr(model, "extents", None) or [0.0])
    return [1.0 if units == "file" else metres_per_unit(e) for e in extents]


def gravity_step_limit(mean_edge: float, gravity, unit: float) -> float:
    """The longest step [s] in which gravity alone moves a free particle by at most
    :data:`GRAVITY_STEP` x ``mean_edge`` (the skin's mean rest edge, in the file's unit):
    ``sqrt(GRAVITY_STEP mean_edge / g)``, ``g = |gravity| / unit`` (``gravity`` [m/s^2], ``unit``
    metres per file unit, :func:`length_units`). ``inf`` where gravity or the edge is zero.

    A longer step drops the tissue by more per step than the elasticity iterations take back
    (their corrections spread over the regions a ring at a time), and the surface crumples
    whatever the contacts do; the share is set so that the finest shipped skin keeps within the
    strain the quality checks ask (docs: limits). Drivers split a frame into steps no longer
    than this, whatever the ``dt`` asked (which stays the longest step)."""
    g = float(np.linalg.norm(np.asarray(gravity, dtype=np.float64))) / float(unit)
    if not (g > 0.0 and mean_edge > 0.0 and math.isfinite(g)):
        return math.inf
    return math.sqrt(GRAVITY_STEP * float(mean_edge) / g)


#: Passes of the chord constraints after the tether and the fail-safe (before the volume loop,
#: which keeps the volume they move), besides one per elasticity iteration.
CHORD_PASSES = 4


def skin_step_limit(model: SkinModel, params: SolverParams) -> float:
    """The longest step [s] :func:`gravity_step_limit` allows ``model`` (one character or a
    batch): the smallest over its characters, each from its own simulated skin's mean rest edge
    (``model.mean_edges``) and file unit (:func:`length_units` with ``params.units``); ``inf``
    without gravity. Every driver that steps a model (``simulate``, ``bench``) splits its steps
    to this."""
    units = length_units(model, params.units)
    limits = [gravity_step_limit(e, params.gravity, u) for e, u in zip(model.mean_edges, units)]
    return min(limits, default=math.inf)


def largest_step(model: SkinModel, params: SolverParams) -> tuple[float, float]:
    """``(dt, limit)`` [s]: the longest step a run of ``model`` takes, ``params.dt`` or, where it
    is shorter, the limit gravity allows (:func:`skin_step_limit`, ``inf`` without gravity), and
    that limit. The one place the step is resolved: ``simulate`` splits its frames into steps no
    longer than ``dt`` (and pre-rolls with it), ``bench`` times steps of ``dt``."""
    limit = skin_step_limit(model, params)
    return min(params.dt, limit), limit


def clean_at_rest(model: SkinModel) -> np.ndarray:
    """``[V]`` bool: the vertices of the characters whose simulated skin has no intersecting
    triangle pair at rest (:func:`~warpskin.metrics.self_intersections` of each one's rest skin,
    ``model.rest``). Only there do contacts push the skin past the tether's cap
    (``tether_contact``): where pieces cross at rest (a hand sunk into a sleeve, a tube's end in
    a ball joint) the contacts start inside what they should keep apart, and reaching farther
    pushed the cut CesiumMan's pieces through each other (189 pairs where LBS has 67)."""
    tris = model.tri_indices.numpy().reshape(-1, 3)
    ranges = [(r.vertex_start, r.vertex_count, r.triangle_start, r.triangle_count) for r in model.characters] or \
        [(0, model.vertex_count, 0, len(tris))]
    clean = np.zeros(model.vertex_count, dtype=bool)
    for rest, (v0, vc, t0, tc) in zip(model.rest, ranges):
        mine = tris[t0:t0 + tc] - v0
        clean[v0:v0 + vc] = len(self_intersections(rest.points[:vc], mine)) == 0
    return clean


def particle_gravity(model: SkinModel, gravity, units: list[float]) -> np.ndarray:
    """``gravity`` [m/s^2] in each particle's file unit, ``[particle_count, 3]`` float32: divided
    by its character's ``units`` (metres per file unit). A batch's character ``c`` owns the
    vertices of ``model.characters[c]``; a single character, all of them."""
    g = np.asarray(gravity, dtype=np.float64).reshape(1, 3)
    per_vertex = np.full(model.vertex_count, units[0], dtype=np.float64)
    for r, unit in zip(getattr(model, "characters", None) or [], units):
        per_vertex[r.vertex_start:r.vertex_start + r.vertex_count] = unit
    per_particle = np.tile(per_vertex, model.particle_count // max(model.vertex_count, 1))
    return (g / per_particle[:, None]).astype(np.float32)


class SkinSolver:
    """Position-based multi-layer skin: oriented-particle shape matching, kinematic coupling,
    joint constraints, sub-volume volume constraints.

    Every buffer is allocated here; :meth:`step` only launches kernels (no host allocation, no
    host-device copy), so it can be recorded or captured.

    References:
        Deul, Bender 2013, "Physically-Based Character Skinning"; Mueller, Chentanez 2011,
        "Solid simulation with oriented particles"; Mueller et al. 2016, "A robust method to
        extract the rotational part of deformations"; Diziol, Bender, Bayer 2011.

    Limitations:
        Only the skin layer collides with itself (the paper's choice); detection is discrete,
        once per step, so contacts that appear during the constraint loop wait for the next
        step; a fail-safe after the elasticity loop puts back the vertices of a pair that
        newly intersects (:meth:`~warpskin.collision.SelfCollision.fail_safe`).
    """

    def __init__(self, model: SkinModel, params: SolverParams | None = None) -> None:
        """Args:
            model: The uploaded model. Self-collision runs when the model has collision data
                (``ModelParams.collision.enabled``) and :meth:`step` is given contacts.
            params: Solver settings.
        """
        self.model = model
        self.params = params or SolverParams()
        self.params.check()
        # iterations is fixed at construction (buffers are sized by it)
        self._iterations = int(self.params.iterations)
        n = model.particle_count
        v = model.vertex_count
        dev = model.device
        self.device = dev
        with wp.ScopedDevice(dev):
            self.region_com = wp.zeros(n, dtype=wp.vec3)
            self.q_scratch = wp.zeros(n, dtype=wp.quat)
            self.coupling_targets = wp.zeros(v, dtype=wp.vec3)
            self.joint_centres = wp.zeros(model.joint_count, dtype=wp.vec3)
            self.moment_matrix = wp.zeros(n, dtype=wp.mat33)
            # every particle's squared position correction in each elasticity iteration of the
            # last step [m^2], flat (iteration-major); :attr:`residuals` reduces them when read
            self.corrections = wp.zeros(self.params.iterations * n, dtype=wp.float32)
            self._residuals = wp.zeros(self.params.iterations, dtype=wp.float32)
            # the tether: radius per vertex [m], and a running count of the particles it clamped
            p = self.params
            self.tether_radius = None
            if p.tether > 0:
                depth = model.vertex_tissue_depth.numpy().astype(np.float64)
                diagonal = model.vertex_diagonal.numpy()  # [V]: each character's own
                radius = np.minimum(p.tether * depth + p.tether_floor * diagonal, p.tether_max * diagonal)
                self.tether_radius = wp.array(radius.astype(np.float32), dtype=wp.float32)
                # the hard bound after the volume loop: the cap alone (see tether_max)
                self.tether_cap = wp.array((p.tether_max * diagonal).astype(np.float32), dtype=wp.float32)
            self.tether_clamped = wp.zeros(1, dtype=wp.int32)
            self._no_contacts = wp.zeros(1, dtype=wp.int32)
            self._no_reach = wp.zeros(1, dtype=wp.float32)
            self.contact_cap = self.contact_written_cap = None
            # the skin's LBS targets of the step (written by the tether, read by the volume loop's caps)
            self.tether_targets = wp.zeros(v, dtype=wp.vec3)
            # fast summation buffers
            self.prefix_mx = wp.zeros(n, dtype=wp.vec3d)
            self.prefix_mxx = wp.zeros(n, dtype=wp.mat33d)
            # the rest offsets the shape matching reads: the model's, or a muscle-driven copy
            self.region_rest_offsets = model.region_rest_offsets
            if model.rest_drive_group_count:
                if self.params.fast_summation:
                    raise SceneError("the rest-shape drive (layered popping) needs the direct gather: set fast_summation = false")
                self.region_rest_offsets = wp.clone(model.region_rest_offsets)
            # volume constraints, and the inverse masses of their weights
            self.volume_inv_mass = model.volume_inv_mass if self.params.volume_along_normals else model.particle_inv_mass
            self.volume = None
            self.volume_weight_scale = wp.ones(n, dtype=wp.float32)
            if model.subvolume_count and self.params.volume_iterations > 0:
                self.volume = VolumeConstraints(model, along_normals=self.params.volume_along_normals)
                self.volume_centres = self.volume.centers  # its fan centres, posed every step
            # a refined skin: the written mesh's volume on the loaded vertices, then the
            # sub-volumes again on the added ones (see step)
            self.written_volume = None
            if self.volume is not None and model.written_surface is not None:
                self.written_volume = VolumeConstraints(model.written_surface, device=dev,
                                                        along_normals=self.params.volume_along_normals)
                self.split_weight_scale = wp.zeros(v, dtype=wp.float32)
                # the cap of the pass on the added vertices: only on the characters that have a
                # written mesh's volume (a batch's others are not capped again: they are not moved)
                self.split_cap = None
                if self.tether_radius is not None:
                    mine = model.vertex_written_volume.numpy() != 0
                    self.split_cap = self.tether_cap if mine.all() else wp.array(
                        np.where(mine, self.tether_cap.numpy(), np.inf).astype(np.float32), dtype=wp.float32)
            self._chords_setup(model)
            self.collision = None
            if model.collision is not None:
                self.collision = SelfCollision(model)
                # the caps of a step with contacts (tether_contact): the skin in contact may be
                # pushed farther from LBS than the tether's cap
                if self.tether_radius is not None:
                    diagonal = model.vertex_diagonal.numpy()
                    reach = np.where(clean_at_rest(model), p.tether_contact, p.tether_max) * diagonal
                    self.contact_max = wp.array(reach.astype(np.float32), dtype=wp.float32)
                    self.contact_cap = wp.clone(self.tether_cap)
                    self.contact_written_cap = wp.clone(self.tether_cap)
                # the skin between the fail-safe and the volume loop: what the pass after the
                # volume loop puts a pair's vertices back to
                self.x_before_volume = wp.zeros(v, dtype=wp.vec3) if self.volume is not None else None
        #: metres per file length unit of each character (``[solver] units``; a batch's in
        #: order): gravity acts in each one's unit, per particle
        self.length_units = length_units(model, self.params.units)
        self.length_unit = self.length_units[0]
        self._gravity = wp.array(particle_gravity(model, self.params.gravity, self.length_units), dtype=wp.vec3,
                                 device=dev)

    @property
    def residuals(self) -> wp.array:
        """The largest position correction [m] of each elasticity iteration of the last step,
        ``[iterations]`` (reduced from :attr:`corrections` by one launch when read; never read
        inside a step)."""
        wp.launch(k_sm.largest_correction_kernel, dim=self._iterations, inputs=[self.corrections, self.model.particle_count],
                  outputs=[self._residuals], device=self.device)
        return self._residuals

    # ------------------------------------------------------------------ pieces of a step
    def update_moments(self, q: wp.array) -> None:
        """Oriented-particle moment matrices of orientations ``q`` (before a fit that follows
        anything but the goal blend, which updates them itself)."""
        wp.launch(k_sm.moment_matrices_kernel, dim=self.model.particle_count, inputs=[q, self.model.particle_moment],
                  outputs=[self.moment_matrix], device=self.device)

    def region_fit(self, x: wp.array, q_in: wp.array, q_out: wp.array) -> None:
        """Region centres into :attr:`region_com` and rotations into ``q_out`` (warm-started from
        ``q_in``; the oriented-particle moments are :attr:`moment_matrix`, which must belong to
        ``q_in``: see :meth:`update_moments`), by fast summation or direct gather
        (``params.fast_summation``)."""
        m = self.model
        it = self.params.rotation_iterations
        if self.params.fast_summation:
            wp.launch(
                k_sm.path_scan_kernel,
                dim=4 * m.path_count,
                inputs=[x, m.particle_q0, m.particle_mass, self.moment_matrix, m.path_order, m.path_offsets,
                        m.vertex_count, m.path_count],
                outputs=[self.prefix_mx, self.prefix_mxx],
                device=self.device,
            )
            wp.launch(
                k_sm.region_fit_runs_kernel,
                dim=m.particle_count,
                inputs=[x, q_in, m.particle_q0, m.particle_mass, self.moment_matrix, self.prefix_mx, self.prefix_mxx,
                        m.position_is_path_start, m.run_offsets, m.run_start, m.run_end, m.region_offsets,
                        m.region_members, m.region_sibling_count, m.region_mass, m.region_rest_com, m.vertex_count, it],
                outputs=[self.region_com, q_out],
                device=self.device,
            )
        else:
            wp.launch(
                k_sm.region_fit_gather_kernel,
                dim=m.particle_count,
                inputs=[x, q_in, m.particle_mass, self.moment_matrix, m.region_offsets, m.region_members,
                        self.region_rest_offsets, m.region_mass, it],
                outputs=[self.region_com, q_out],
                device=self.device,
            )

    def blend_and_constrain(self, x: wp.array, q_regions: wp.array, iteration: int = 0) -> None:
        """One elasticity iteration's per-particle goal blend of the region fits (into ``x``),
        with the kinematic coupling and the joint constraints; updates the moment matrices and
        row ``iteration`` of :attr:`corrections`."""
        m = self.model
        wp.launch(
            k_sm.blend_and_constrain_kernel,
            dim=m.particle_count,
            inputs=[self.region_com, q_regions, self.region_rest_offsets, m.particle_region_offsets, m.particle_regions,
                    m.particle_region_slots, m.particle_stiffness, 3 * m.vertex_count, self.coupling_targets,
                    m.coupling_stiffness, m.joint_offsets, m.joint_ids, m.joint_rest_distance,
                    self.joint_centres, m.particle_moment, iteration],
            outputs=[x, self.moment_matrix, self.corrections],
            device=self.device,
        )

    def _kinematics(self, control: Control) -> None:
        m = self.model
        wp.launch(
            k_skin.lbs_kernel,
            dim=m.vertex_count,
            inputs=[m.coupling_rest, m.coupling_joint_indices, m.coupling_joint_weights, control.skin_matrices],
            outputs=[self.coupling_targets],
            device=self.device,
        )
        wp.launch(k_int.joint_centres_kernel, dim=m.joint_count, inputs=[control.skin_matrices, m.joint_rest],
                  outputs=[self.joint_centres], device=self.device)
        if self.volume is not None:
            self.volume.center_positions(control.skin_matrices, self.volume_centres)

    def _volume_loop(self, x: wp.array, weight_scale: wp.array | None = None, cap_radius: wp.array | None = None) -> None:
        """``volume_iterations`` of the sub-volume constraints on ``x`` (weights
        :attr:`volume_weight_scale` unless given), each followed by the tether's cap where
        there is a tether (against the targets :meth:`_tether` wrote earlier in the step; radii
        ``cap_radius`` ``[V]`` [m] where given, else :attr:`tether_cap`)."""
        p = self.params
        w = self.volume_weight_scale if weight_scale is None else weight_scale
        # the cap is fused into each iteration's correction launch, against the targets the
        # step's tether wrote (the skinning matrices do not change within a step)
        cap = None if self.tether_radius is None else (
            self.tether_targets, self.tether_cap if cap_radius is None else cap_radius, self.tether_clamped)
        self.volume.project(x, self.volume_inv_mass, w, self.volume_centres, p.volume_iterations,
                            p.volume_stiffness, cap=cap)

    def _written_volume(self, x: wp.array, control: Control, collide: bool = False,
                        cap_radius: wp.array | None = None) -> None:
        """A refined skin is written with the loaded mesh's triangles, chords of the simulated
        surface, which lose volume where the added vertices bulge between them while the
        refined surface keeps its own. One projection of the written mesh's volume on the
        loaded vertices, then the sub-volume iterations on the added ones alone (the loaded
        ones pinned), which restore the sub-volumes without changing what is written. (One
        more constraint in the volume loop itself would take volume from small sub-volumes
        such as paws.) The volume loop's own weights (contacts, the fail-safe's pins)
        apply in both; with ``collide``, the fail-safe holds what the projection pushes through."""
        m = self.model
        dev = self.device
        wp.launch(k_con.split_weights_kernel, dim=m.vertex_count, inputs=[self.volume_weight_scale, m.vertex_loaded, 0],
                  outputs=[self.split_weight_scale], device=dev)
        col = self.collision if collide and self.collision.data.fail_safe_rounds > 0 else None
        if col is not None:
            wp.copy(self.x_before_volume, x, count=m.vertex_count)
        self.written_volume.project(x, self.volume_inv_mass, self.split_weight_scale, self.written_volume.centers, 1,
                                    self.params.volume_stiffness)
        if col is not None:
            # what the projection pushed through goes back (it can make pairs where LBS has
            # none); the added vertices do not change the written mesh
            col.fail_safe(self.x_before_volume, x, control.skin_matrices, carry=False,
                          min_move=col.default_min_move)
        wp.launch(k_con.split_weights_kernel, dim=m.vertex_count, inputs=[self.volume_weight_scale, m.vertex_loaded, 1],
                  outputs=[self.split_weight_scale], device=dev)
        self._volume_loop(x, self.split_weight_scale, self.split_cap if cap_radius is None else cap_radius)

    def _tether(self, x: wp.array, control: Control, cap_only: bool = False, reach: wp.array | None = None) -> None:
        """The tether on every particle, or with ``cap_only`` its cap (``tether_max`` x the
        diagonal) on the skin particles; with ``reach`` ``[V]`` [m] (``State.contact_reach``),
        each skin particle's radius is longer by its reach (``tether_contact``).
        Writes the skin's LBS targets of ``control`` that the volume loop's caps use (so it
        runs first in a step)."""
        m = self.model
        radius, dim = (self.tether_cap, m.vertex_count) if cap_only else (self.tether_radius, m.particle_count)
        wp.launch(k_con.tether_kernel, dim=dim,
                  inputs=[m.particle_q0, m.coupling_joint_indices, m.coupling_joint_weights, control.skin_matrices,
                          radius, m.vertex_count, self._no_reach if reach is None else reach],
                  outputs=[x, self.tether_clamped, self.tether_targets], device=self.device)

    def _chords_setup(self, model: SkinModel) -> None:
        """The written triangles and edges of a refined skin with volume (``model.written_surface``)
        that :meth:`_chords` keeps (``chord_strain``, ``chord_area``); ``None`` where there are none
        or both are off."""
        p = self.params
        self.chords = None
        surface = model.written_surface
        if surface is None or not (p.chord_strain > 0.0 or p.chord_area > 0.0):
            return
        dev = self.device
        tris = np.asarray(surface.triangles, dtype=np.int64)
        edges, _ = skin_edges(tris)
        rest = model.particle_q0.numpy()[: model.vertex_count].astype(np.float64)
        self.chords = {
            "triangles": wp.array(tris.astype(np.int32), dtype=wp.int32, device=dev),
            "edges": wp.array(edges.astype(np.int32), dtype=wp.int32, device=dev),
            "rest_length": wp.array(np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1).astype(np.float32),
                                    dtype=wp.float32, device=dev),
            "lbs": wp.zeros(model.vertex_count, dtype=wp.vec3, device=dev),  # the step's LBS of the skin
        }

    def _chords(self, x: wp.array) -> None:
        """One pass of the chord constraints (:mod:`warpskin.kernels.chords`): the written edges'
        strain, then the written triangles' orientation, against the step's LBS."""
        m, c, p, dev = self.model, self.chords, self.params, self.device
        if p.chord_strain > 0.0:
            wp.launch(k_chord.chord_strain_kernel, dim=c["edges"].shape[0],
                      inputs=[c["edges"], c["rest_length"], c["lbs"], m.particle_inv_mass, p.chord_strain],
                      outputs=[x], device=dev)
        if p.chord_area > 0.0:
            wp.launch(k_chord.chord_orientation_kernel, dim=c["triangles"].shape[0],
                      inputs=[c["triangles"], c["lbs"], m.particle_inv_mass, p.chord_area], outputs=[x], device=dev)

    # ------------------------------------------------------------------ the step
    def step(self, state_in: State, state_out: State, control: Control, contacts: Contacts | None, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` [s] into ``state_out`` (Algorithm 1). The caller swaps
        the two states.

        Args:
            state_in: The state at the start of the step (read only).
            state_out: The state at its end.
            control: Skinning matrices (and muscle activation) of this step.
            contacts: Collision buffers from ``model.contacts()``; ``None`` switches
                self-collision off for the step.
            dt: Step length [s].
        """
        if state_in is state_out:
            raise InputError("step needs two different states (state_in, state_out); swap them after each step")
        if not (dt > 0.0):
            raise SceneError(f"dt must be positive, got {dt}")
        p = self.params
        if p.iterations != self._iterations:
            raise InputError(f"iterations changed from {self._iterations} to {p.iterations} after the solver was built; build a new SkinSolver")
        m = self.model
        dev = self.device
        n = m.particle_count
        col = self.collision if contacts is not None else None
        if contacts is not None and self.collision is None:
            raise InputError("contacts given, but the model was built with [collision] enabled = false")
        if m.rest_drive_group_count:
            wp.launch(k_sm.rest_offsets_drive_kernel, dim=m.region_entry_count,
                      inputs=[m.region_rest_offsets, m.rest_drive_offsets, control.muscle_activation],
                      outputs=[self.region_rest_offsets], device=dev)
        # 1-4: prediction
        wp.launch(k_int.predict_kernel, dim=n, inputs=[state_in.x, state_in.v, state_in.q, state_in.omega, self._gravity, dt],
                  outputs=[state_out.x, state_out.v, state_out.q], device=dev)
        self._kinematics(control)
        self.update_moments(state_out.q)
        # 5: collision detection, once, on the predicted positions
        if col is not None:
            col.detect(state_in.x, state_out.x, contacts)
        # 6-10: elasticity loop (shape matching, coupling, joint constraints)
        q_src, q_dst = state_out.q, self.q_scratch
        if self.chords is not None:  # the step's LBS of the skin, the chords' reference
            wp.launch(k_skin.lbs_kernel, dim=m.vertex_count, inputs=[m.particle_q0, m.coupling_joint_indices,
                      m.coupling_joint_weights, control.skin_matrices], outputs=[self.chords["lbs"]], device=dev)
        for it in range(p.iterations):
            self.region_fit(state_out.x, q_src, q_dst)
            self.blend_and_constrain(state_out.x, q_dst, it)
            if self.chords is not None:
                self._chords(state_out.x)
            if col is not None:
                col.project(state_out.x, m.particle_inv_mass, contacts)
            q_src, q_dst = q_dst, q_src
        if q_src is not state_out.q:
            wp.copy(state_out.q, q_src)
        # the tether: no particle farther from its LBS target than its radius (before the volume
        # loop, which restores what the clamp took from a sub-volume)
        # the skin in contact reaches farther (tether_contact), and back over tether_release
        reach = cap = written_cap = None
        if self.contact_cap is not None:
            shrink = min(dt / p.tether_release, 1.0)
            wp.launch(k_con.contact_reach_kernel, dim=m.vertex_count,
                      inputs=[self.tether_cap, self.contact_max,
                              contacts.colliding if col is not None else self._no_contacts, shrink,
                              m.vertex_written_volume, state_in.contact_reach],
                      outputs=[state_out.contact_reach, self.contact_cap, self.contact_written_cap], device=dev)
            reach, cap, written_cap = state_out.contact_reach, self.contact_cap, self.contact_written_cap
        if self.tether_radius is not None:
            self._tether(state_out.x, control, reach=reach)
        # the fail-safe: a skin triangle pair the constraints let through is put back where the
        # step's start was free of it (before the volume loop, which restores the volume around
        # what it put back: after it, held parts would lose their volume; what the volume loop
        # pushes through is the second pass's, below)
        if col is not None:
            col.fail_safe(state_in.x, state_out.x, control.skin_matrices, contacts=contacts)
        if self.chords is not None:  # what the tether and the fail-safe left of the chords' shape
            for _ in range(CHORD_PASSES):
                self._chords(state_out.x)
        # 11-13: volume loop; with the tether, each volume iteration is followed by the cap
        # (the volume loop moves skin particles only): a sub-volume squeezed by contacts
        # corrects through its few free particles and can throw one past it (a paw's vertex far
        # beyond the cap); interleaved, what the cap takes back is restored by the particles
        # that still have room
        if self.volume is not None:
            fail_safe = col is not None and col.data.fail_safe_rounds > 0
            if col is not None:
                col.volume_weights(contacts, self.volume_weight_scale)
            if fail_safe:
                wp.copy(self.x_before_volume, state_out.x, count=m.vertex_count)
            self._volume_loop(state_out.x, cap_radius=cap)
            # the volume loop can push a pair through (which then stays): a second fail-safe
            # pass puts those vertices back where the loop found them, pinned, and the loop runs
            # again so that the others restore what they gave up
            if fail_safe:
                col.fail_safe(self.x_before_volume, state_out.x, control.skin_matrices, carry=False,
                              min_move=col.default_min_move, contacts=contacts)
                col.pin_reverted(self.volume_weight_scale)
                self._volume_loop(state_out.x, cap_radius=cap)
        if self.written_volume is not None:
            self._written_volume(state_out.x, control, col is not None, written_cap)
        if self.tether_radius is not None and col is not None and self.volume is None:
            self._tether(state_out.x, control, cap_only=True, reach=reach)  # what the fail-safe held back stays within the cap
        # 14-17: velocities, angular velocities, damping
        wp.launch(k_int.update_velocity_kernel, dim=n,
                  inputs=[state_in.x, state_out.x, state_in.q, state_out.q, 1.0 / dt, math.exp(-p.damping * dt)],
                  outputs=[state_out.v, state_out.omega], device=dev)
        # 18: friction and restitution of the colliding particles
        if col is not None:
            col.friction_restitution(state_out.x, state_out.v, m.particle_inv_mass, contacts)

"""``warpskin simulate``: the physical skin over a scene's frames to USD, with per-frame
measurements (volumes, sub-volumes, energy, offset from LBS, contacts, intersections) and an
optional report."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import SimulationError
from ..io.usd_export import UsdSkinWriter, valid_prim_name, check_output_path
from ..metrics import self_intersections_of_two, signed_volume
from ..model import SkinModelBuilder
from ..params import RunLimits
from ..options import with_overrides
from ..preprocess.layers import LAYER_NAMES
from ..quality import QualityLimits, QualityLog
from ..report import write_plots
from ..scene import Scene, resolve_scene
from ..solver import GRAVITY_STEP, SkinSolver, SolverParams, largest_step
from ..transforms import linear_blend_skin
from .physics import PhysicsStepper
from .output import CharacterOutput, attachment_kwargs
from .plan import FramePlan
from .runner import FrameRunner

__all__ = ["SimulationOptions", "SimulationResult", "simulate"]

_SKIN_COLOR = (0.85, 0.64, 0.52)
_LBS_COLOR = (0.4, 0.55, 0.85)
_NORMAL_COLOR = (0.55, 0.75, 0.55)


@dataclass
class SimulationResult:
    """What a run produced.

    Attributes:
        path: The USD file.
        frames: Frame numbers written.
        metrics: Per-frame series (``time``, ``volume``, ``volume_lbs``, ``subvolume``,
            ``subvolume_lbs``, ``kinetic_energy``, ``max_offset_from_lbs``, ``step_ms``).
        summary: Scalars: particle count, substeps, dt, volume deviations, timing.
    """

    path: Path
    frames: list[int]
    metrics: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)


def _vertex(rig, k: int) -> str:
    """``"file vertex N"`` (the file's number), ``"cage vertex N"`` or a piece's vertex
    (:meth:`~warpskin.rig.Rig.vertex_label`), for messages."""
    return rig.vertex_label(k)


class _Measurements:
    """Per-frame measurements of the physical skin against LBS (host, after the frame)."""

    def __init__(self, builder, stepper: PhysicsStepper, plan: FramePlan, check_intersections: bool,
                 limits: RunLimits, allow_unstable: bool = False) -> None:
        self.b, self.st, self.plan = builder, stepper, plan
        self.check_intersections = check_intersections
        self.limits, self.allow_unstable, self.warned = limits, allow_unstable, False
        self.diagonal = builder.rig.size()
        self._pending: dict = {}
        self._clamped = int(stepper.solver.tether_clamped.numpy()[0])  # the pre-roll's
        col = stepper.collision
        self._fail_safe = int(col.fail_safe_pairs.numpy()[0]) if col is not None else 0
        rig = builder.rig
        subs = builder.subvolumes
        self.m: dict = {k: [] for k in ("time", "frame", "volume", "volume_lbs", "subvolume", "subvolume_lbs", "kinetic_energy",
                                         "max_offset_from_lbs", "relative_speed_rms", "animation_speed_change_rms",
                                         "step_ms", "residuals",
                                         "contacts_point_triangle", "contacts_edge_edge", "constraints_active", "intersecting_pairs",
                                         "intersecting_pairs_lbs", "tether_clamped", "fail_safe_pairs", "capped_share")}
        self.m["volume_rest"] = signed_volume(rig.vertices[: rig.output_count], rig.output_triangles)
        self.m["subvolume_rest"] = subs.rest_volume.tolist() if subs is not None else []
        self.lbs: np.ndarray | None = None
        self._prev_lbs: np.ndarray | None = None
        self._prev_lbs_velocity: np.ndarray | None = None
        self._prev_speed = 0.0
        self._skin_mass = np.asarray(builder.masses[: rig.vertex_count], dtype=np.float64)
        # LBS's worst volume error so far, whole and per sub-volume (what the animation itself
        # does to the volume: a frame within it is in range)
        self._worst_lbs = 0.0
        self._worst_lbs_sub = np.zeros(len(self.m["subvolume_rest"]))

    def lbs_points(self, i: int) -> np.ndarray:
        """LBS of every simulated skin vertex (the file's first, then any added by refining)."""
        rig = self.b.rig
        return linear_blend_skin(rig.vertices, rig.joint_indices, rig.joint_weights, self.st.frame_poses[i])

    def evaluate(self, i: int, skin: np.ndarray) -> np.ndarray:
        """Volumes and offset of frame ``i`` against LBS, kept for :meth:`__call__`; raises
        :class:`SimulationError` where the skin left its plausible range (unless
        ``allow_unstable``, then one warning). ``skin`` is every simulated skin vertex; the
        volume, offset and intersections are those of the file's own mesh (its vertices are
        the first ones), the sub-volumes those of the simulated surface. Returns the LBS of
        the file's mesh."""
        b, st = self.b, self.st
        subs = b.subvolumes
        n, tris = b.rig.output_count, b.rig.output_triangles
        lbs_all = self.lbs_points(i)
        lbs, out = lbs_all[:n], skin[:n]
        e = {"lbs": lbs, "lbs_all": lbs_all, "skin": out, "volume": signed_volume(out, tris),
             "volume_lbs": signed_volume(lbs, tris)}
        if subs is not None:
            centres = subs.center_positions(st.frame_poses[i])
            e["subvolume"] = subs.volumes(skin.astype(np.float64), centres)
            e["subvolume_lbs"] = subs.volumes(lbs_all, centres)
        d = np.linalg.norm(out - lbs, axis=1)
        e["offset"] = float(d.max())
        # the skin's motion relative to the animation: its velocities minus LBS's over the frame
        e["velocities"] = vel = st.velocities()  # one host copy per frame, for __call__ too
        vs = vel[: b.rig.vertex_count].astype(np.float64)
        # and the animation's own change of velocity over the frame (what it put in: a skin that
        # lags a sudden start or stop is faster relative to it by up to that much)
        w = self._skin_mass

        def rms(x: np.ndarray) -> float:  # mass-weighted RMS of per-vertex vectors [m/s]
            return float(np.sqrt(np.sum(w * np.einsum("ij,ij->i", x, x)) / w.sum()))

        velocity_lbs = None
        if self._prev_lbs is not None and i > 0:
            frame_dt = self.plan.times[i] - self.plan.times[i - 1]
            velocity_lbs = (lbs_all - self._prev_lbs) / frame_dt
            rel = vs - velocity_lbs
            change = velocity_lbs - (self._prev_lbs_velocity if self._prev_lbs_velocity is not None else 0.0)
            e["animation_speed_change_rms"] = rms(change)
        else:
            rel = np.zeros_like(vs)
            e["animation_speed_change_rms"] = 0.0
        e["relative_speed_rms"] = rms(rel)
        e["relative_speed"] = rel
        e["relative_speed_before"] = self._prev_speed
        self._prev_lbs_velocity = velocity_lbs
        self._prev_lbs, self._prev_speed = lbs_all, e["relative_speed_rms"]
        self._pending = e
        problem = self._out_of_range(i, skin, e, d)
        if problem is not None:
            if not self.allow_unstable:
                raise SimulationError(problem + "; lower dt, raise stiffness or iterations, or pass --allow-unstable")
            if not self.warned:
                warnings.warn(problem + "; continuing (--allow-unstable)", RuntimeWarning, stacklevel=2)
                self.warned = True
        return lbs

    def _out_of_range(self, i: int, skin: np.ndarray, e: dict, d: np.ndarray) -> str | None:
        p, b = self.limits, self.b
        f = self.plan.frames[i]
        diag = self.diagonal
        if e["offset"] > p.max_offset * diag:
            k = int(np.argmax(d))
            bone = b.layers.bones.joint_names[b.layers.bone[k]]
            return (f"frame {f}: the skin left its plausible range: {_vertex(b.rig, k)} "
                    f"(bone {bone!r}) is {e['offset']:.3g} m from LBS, {100 * e['offset'] / diag:.1f} % of the body's "
                    f"{diag:.3g} m diagonal (max_offset {p.max_offset:g})")
        speed, before, given = e["relative_speed_rms"], e["relative_speed_before"], e["animation_speed_change_rms"]
        if speed > p.max_speed * diag and speed - before > given:
            rel = np.linalg.norm(e["relative_speed"], axis=1)
            k = int(np.argmax(rel))
            bone = b.layers.bones.joint_names[b.layers.bone[k]]
            return (f"frame {f}: the skin left its plausible range: its motion relative to the animation keeps "
                    f"growing without input (RMS {speed:.3g} m/s, {speed / diag:.2g} body diagonals per second, "
                    f"max_speed {p.max_speed:g}; up {speed - before:.3g} m/s in the frame, where the animation's "
                    f"own velocity changed by {given:.3g} m/s; fastest near {_vertex(b.rig, k)}, bone {bone!r})")
        v0 = self.m["volume_rest"]
        err, err_lbs = abs(e["volume"] / v0 - 1.0), abs(e["volume_lbs"] / v0 - 1.0)
        self._worst_lbs = max(self._worst_lbs, err_lbs)
        if err > max(p.max_volume_error, 2.0 * err_lbs, self._worst_lbs):
            return (f"frame {f}: the skin left its plausible range: its volume is off by {100 * err:.1f} % (LBS "
                    f"{100 * err_lbs:.1f} %, at worst {100 * self._worst_lbs:.1f} %; max_volume_error "
                    f"{100 * p.max_volume_error:g} %)")
        if "subvolume" in e:
            subs = b.subvolumes
            err_s, err_s_lbs = subs.volume_errors(e["subvolume"]), subs.volume_errors(e["subvolume_lbs"])
            self._worst_lbs_sub = np.maximum(self._worst_lbs_sub, err_s_lbs)
            over = err_s > np.maximum(np.maximum(p.max_volume_error, 2.0 * err_s_lbs), self._worst_lbs_sub)
            if over.any():
                k = int(np.argmax(np.where(over, err_s, -1.0)))
                of = "" if subs.error_scale[k] <= abs(subs.rest_volume[k]) else (
                    f" of {100 * subs.SMALL_SHARE:g} % of the body's volume, which it is smaller than")
                return (f"frame {f}: the skin left its plausible range: sub-volume {subs.names[k]!r} is off by "
                        f"{100 * err_s[k]:.1f} %{of} (LBS {100 * err_s_lbs[k]:.1f} %, at worst "
                        f"{100 * self._worst_lbs_sub[k]:.1f} %; max_volume_error {100 * p.max_volume_error:g} %)")
        return None

    def __call__(self, i: int, f: int, points: dict, step_ms: float) -> None:
        m, b, st = self.m, self.b, self.st
        tris = b.rig.output_triangles
        e = self._pending
        # the simulated surface (the file's vertices as simulated, or the cage), not what is
        # written (which the surface guard may have taken back towards LBS)
        skin = points.get("cage", e["skin"])
        lbs = e["lbs"]
        vel = e["velocities"]
        m["time"].append(self.plan.times[i])
        m["frame"].append(self.plan.time_codes[i])
        m["volume"].append(e["volume"])
        m["volume_lbs"].append(e["volume_lbs"])
        if "subvolume" in e:
            m["subvolume"].append(e["subvolume"].tolist())
            m["subvolume_lbs"].append(e["subvolume_lbs"].tolist())
        m["kinetic_energy"].append(float(0.5 * np.sum(b.masses * np.einsum("ij,ij->i", vel, vel))))
        m["max_offset_from_lbs"].append(e["offset"])
        m["relative_speed_rms"].append(e["relative_speed_rms"])
        m["animation_speed_change_rms"].append(e["animation_speed_change_rms"])
        m["step_ms"].append(step_ms)
        m["residuals"].append(st.solver.residuals.numpy().tolist() if i > 0 else [])
        clamped = int(st.solver.tether_clamped.numpy()[0])  # a running count: this frame's share
        m["tether_clamped"].append(clamped - self._clamped)
        self._clamped = clamped
        if st.collision is not None:  # pairs the fail-safe put back in this frame (running count)
            fs = int(st.collision.fail_safe_pairs.numpy()[0])
            m["fail_safe_pairs"].append(fs - self._fail_safe)
            self._fail_safe = fs
        c = st.contacts
        if c is not None:
            counts = c.counts.numpy()
            m["contacts_point_triangle"].append(int(counts[0]) if i > 0 else 0)
            m["contacts_edge_edge"].append(int(counts[1]) if i > 0 else 0)
            m["constraints_active"].append(int(c.active.numpy()[0]) if i > 0 else 0)
        if self.check_intersections:
            pairs, pairs_lbs = self_intersections_of_two(skin, lbs, tris)
            m["intersecting_pairs"].append(int(len(pairs)))
            m["intersecting_pairs_lbs"].append(int(len(pairs_lbs)))


class _WrittenQuality:
    """The measures of every mesh written with physics, per frame (:class:`~warpskin.quality.QualityLog`),
    and the share of the simulated skin held at the tether's cap; either out of its range stops
    the run (:class:`SimulationError`) unless ``allow_unstable`` (one warning)."""

    def __init__(self, character, plan: FramePlan, limits: RunLimits, allow_unstable: bool, stepper,
                 measures: _Measurements, skin_prim: str = "skin") -> None:
        params = stepper.solver.params  # the tether's cap
        self.plan, self.run_limits, self.allow_unstable, self.stepper = plan, limits, allow_unstable, stepper
        self.tether_max = params.tether_max
        # measured and reported under the names they are written with (the skin: its file's)
        self.names = {p.name: (skin_prim if p.name == "skin" else valid_prim_name(p.name)) for p in character.parts}
        self.meshes = [character.meshes[p.name] for p in character.parts if p.physics]
        self.guards = {self.names[name]: g for name, g in character.guards.items()}
        self.limits = {self.names[name]: lim for name, lim in character.limits.items()}
        self.repairs = {self.names[name]: r for name, r in getattr(character, "repairs", {}).items()}
        self.untangles = {self.names[name]: u for name, u in getattr(character, "untangles", {}).items()}
        self.log = QualityLog(self.meshes, QualityLimits(limits.max_strained, limits.max_flipped),
                              cross=None if character.cross is None else character.cross.cross)
        from ..delivery import DeliveryLog

        self.character = character
        #: what the physics delivered to each written mesh (:mod:`warpskin.delivery`)
        self.delivery = DeliveryLog({m.name: m for m in self.meshes}, float(np.ptp(character.soup.points, axis=0).max()),
                                    weights={self.names[p.name]: character.soup.dense_weights[p.start:p.start + p.count]
                                             for p in character.parts if p.physics})
        self.capped: list[float] = []
        self._capped_since: float | None = None  # clip time the share went above max_capped
        self.measures = measures  # one warning per run, shared with the simulated surface's checks
        self.cap = params.tether_max * stepper.model.diagonal if params.tether > 0 else None
        # the simulated vertices that show in what is written (a thin part written as LBS may
        # rest at the cap without harm)
        self.shown = character.sim_vertex_weight(stepper.model.vertex_count) > 0.5

    def check(self, i: int, written: dict, lbs: dict) -> None:
        f = self.plan.frames[i]
        guards = self.guards
        physical = getattr(self.character, "last_physical", None) or {}
        self.delivery.measure({self.names[k]: v for k, v in written.items() if self.names[k] in self.delivery.meshes},
                              {self.names[k]: v for k, v in lbs.items() if self.names[k] in self.delivery.meshes},
                              {self.names[k]: v for k, v in physical.items() if self.names[k] in self.delivery.meshes})
        problem = self.log.measure(f, {self.names[k]: v for k, v in written.items()},
                                   {self.names[k]: v for k, v in lbs.items()},
                                   pairs={k: g.pair_keys for k, g in guards.items() if g.pair_keys is not None},
                                   extra={k: {"guarded": g.guarded, "held": g.held, "guard_fallbacks": g.fallbacks,
                                              "jump_limited": self.limits[k].limited,
                                              **({"untangled": self.untangles[k].stats["before"]
                                                  - self.untangles[k].stats["after"] + self.untangles[k].stats["seam"]}
                                                 if k in self.untangles else {}),
                                              **({"worn_repaired": self.repairs[k][0].repaired}
                                                 if k in self.repairs else {})}
                                          for k, g in guards.items()},
                                   every=({self.character.display_name(k): v for k, v in written.items()},
                                          {self.character.display_name(k): v for k, v in lbs.items()}),
                                   skinned={self.names[k]: v
                                            for k, v in getattr(self.character, "last_skinned", {}).items()})
        if self.cap is not None:
            st = self.stepper
            v = st.model.vertex_count
            target = self.measures._pending["lbs_all"]  # the simulated skin's LBS of this frame
            d = np.linalg.norm(st.positions[:v] - target, axis=1)
            share = float(np.mean((d >= 0.99 * self.cap) & self.shown))
            self.capped.append(share)
            self.measures.m["capped_share"].append(share)
            # how long the share has stayed above the bound, frame after frame (a lag clears
            # within a frame or two; an explosion the cap holds stays)
            t = float(self.plan.times[i])
            if share > self.run_limits.max_capped:
                self._capped_since = t if self._capped_since is None else self._capped_since
            else:
                self._capped_since = None
            held = None if self._capped_since is None else t - self._capped_since
            if problem is None and held is not None and held >= self.run_limits.capped_time - 1e-6:
                problem = (f"frame {f}: the skin left its plausible range: {100 * share:.1f} % of the simulated skin "
                           f"(where it shows in the written meshes) is held at the tether's cap "
                           f"({self.cap:.3g} m from LBS, tether_max {self.tether_max:g}; max_capped "
                           f"{100 * self.run_limits.max_capped:g} %), above that for {held:.3g} s (capped_time "
                           f"{self.run_limits.capped_time:g} s): an explosion the cap hides")
        if problem is None:
            return
        if not self.allow_unstable:
            raise SimulationError(f"{problem}; lower dt, raise stiffness or iterations, or pass --allow-unstable")
        if not self.measures.warned:
            warnings.warn(problem + "; continuing (--allow-unstable)", RuntimeWarning, stacklevel=2)
            self.measures.warned = True


def _surface_summary(character) -> dict:
    """What was simulated: ``kind`` (``skin``, ``pieces`` or ``cage``) and, for the character's
    own pieces, which were simulated and which attached, the holes capped, the pairs of pieces
    kept from colliding, the loose pieces that swing (:class:`~warpskin.guard.PieceSwing`) and the
    rigid pieces whose joint's tissue beneath them is thinned (``bony_under``:
    ``PieceParams.bony_depth``)."""
    out = {"kind": character.surface, "vertices": int(character.sim_rig.vertex_count)}
    ps = character.pieces
    if ps is not None:
        n = ps.notes
        out.update({"pieces": int(ps.piece_count), "simulated": list(n["simulated"]), "attached": list(n["attached"]),
                    "capped_holes": int(n["capped_loops"]), "cap_vertices": int(ps.cap.sum()),
                    "apart": [list(p) for p in n["excluded_pairs"]], "edge_m": float(ps.edge),
                    "swinging": [n["names"][p.piece] for s in character.swings.values() for p in s.pieces],
                    "bony_under": list(n.get("bony_under", []))})
    return out


def _meshes_to_write(character, builder, render, with_lbs: bool, with_layers: bool) -> list:
    """``[(name, triangles, rest points, writer kwargs)]`` of a simulation's output: the skin
    (carrying its distance from LBS per vertex and frame, for a DCC to colour it by) and, with
    ``with_lbs``, its LBS as a guide; through a cage the render meshes deformed through it,
    each with its LBS guide, and the cage as a guide; with ``with_layers`` the inner layers as
    simulated (guides)."""
    sim = builder.rig
    tris = sim.output_triangles
    n_out = sim.output_count
    if not character.captured:
        meshes = [("skin", tris, sim.vertices[:n_out], {"color": _SKIN_COLOR, "animated_primvars": ("deviationFromLbs",)})]
        if with_lbs:
            meshes.append(("lbs", tris, sim.vertices[:n_out], {"color": _LBS_COLOR, "purpose": "guide"}))
    else:
        rt = render.output_triangles
        meshes = [("skin", rt, render.vertices[: render.output_count],
                   {"color": _SKIN_COLOR, "animated_primvars": ("deviationFromLbs",)})]
        if with_lbs:
            meshes.append(("lbs", rt, render.vertices[: render.output_count], {"color": _LBS_COLOR, "purpose": "guide"}))
        others = [(p.name, p.triangles, p.rest, attachment_kwargs(p.attachment)) for p in character.parts[1:]]
        meshes += others
        if with_lbs:  # each mesh's own LBS beside it, as for the skin
            meshes += [(f"{name}_lbs", t, p, {"color": _LBS_COLOR, "purpose": "guide"}) for name, t, p, _ in others]
        if character.caged:
            meshes.append(("cage", sim.output_triangles, character.cage_surface.vertices,
                           {"color": (0.6, 0.6, 0.6), "purpose": "guide", "as_is": True}))
        elif with_layers:  # the character's own pieces as simulated, caps included (a guide)
            meshes.append(("surface", sim.triangles, character.pieces.vertices,
                           {"color": (0.6, 0.6, 0.6), "purpose": "guide", "as_is": True}))
    if with_layers:
        for k in range(1, 4):
            meshes.append((f"layer_{LAYER_NAMES[k]}", sim.triangles, builder.layers.positions[k],
                           {"purpose": "guide", "as_is": True}))
    return meshes


def _steps_gravity_allows(scene, model, params: SolverParams, plan: FramePlan, frames, start_frame):
    """``(params, plan, limit)``: the solver settings and frame plan with steps no longer than
    :func:`~warpskin.solver.gravity_step_limit` of the simulated skin (``limit`` [s], ``inf``
    without gravity), with one warning where that splits the frames into more steps than
    ``params.dt`` asked; unchanged where it does not."""
    from dataclasses import replace

    dt, limit = largest_step(model, params)
    if not dt < params.dt:
        return params, plan, limit
    asked = plan
    params = replace(params, dt=dt)
    plan = FramePlan.for_scene(scene, frames, max_dt=dt, start_frame=start_frame)
    if plan.substeps > asked.substeps:
        warnings.warn(f"{scene.source or scene.name}: steps of {1e3 * asked.dt:.3g} ms let gravity move the skin by "
                      f"{GRAVITY_STEP * (asked.dt / limit) ** 2:.2g} of its mean "
                      f"edge per step, more than the elasticity iterations take back (the tissue would sag and "
                      f"crumple): each frame is split into {plan.substeps} steps of {1e3 * plan.dt:.3g} ms instead "
                      f"(dt is the longest step; at most {1e3 * limit:.3g} ms for this skin)", RuntimeWarning,
                      stacklevel=3)
    return params, plan, limit


@dataclass(frozen=True)
class SimulationOptions:
    """How :func:`simulate` runs a scene: the Python API's options, and what ``warpskin simulate``
    builds from its command line (:func:`warpskin.cli.cmd_simulate`). Every field has the
    default a scene needs nothing else for.

    * ``device``: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``None`` (Warp's default), resolved
      once, by the model (:meth:`~warpskin.model.SkinModelBuilder.finalize`).
    * ``frames``: ``(first, last)`` of the source's time codes (``frame / fps`` seconds, at the
      clip's own rate unless the scene sets ``fps``), default all; ``start_frame`` writes the
      first frame at that time code instead.
    * ``solver_params`` and ``limits`` (:class:`~warpskin.params.RunLimits`: where the run stops;
      both default to the scene's ``[solver]``), ``collision``
      (:class:`~warpskin.collision.CollisionParams`, default: the scene's ``[collision]``, on
      unless disabled), ``guard`` (:class:`~warpskin.guard.GuardParams`, default: the scene's
      ``[guard]``, on: it takes back, frame by frame and smoothly, the part of the physical
      displacement that would leave a mesh written with physics worse than its own LBS; how
      much it held is in the summary's ``written`` and ``delivered`` and in report.json).
    * ``with_lbs``, ``with_layers``: also write LBS, and the inner layers, as guides;
      ``topology`` ``"file"`` (default) writes the skin (and LBS) with the file's own vertices,
      faces, UVs and materials, ``"welded"`` the closed surface as loaded.
    * ``report_dir``: write report.json and PNG plots there; ``check_intersections`` counts
      intersecting skin triangle pairs per frame with the exact, solver-independent check
      (:func:`warpskin.metrics.self_intersections`), default only with a report.
    * ``progress``: a progress bar on stderr; ``comment``: the USD layer's comment.
    * ``use_graph`` records each frame's substeps once as a Warp graph (CPU and CUDA) and
      replays it, which removes the per-launch overhead; the results are bit-identical.
    * ``preroll`` [s] (default: the scene's ``[animation] preroll``) simulates that long before
      the first frame, from the bind pose into the first frame's pose (the root joints at the
      first frame's placement throughout, the joints below them interpolated, eased in and
      out); velocities are zeroed after it. A first pose whose LBS skin already passes through
      itself is then reached by collision instead of started from; nothing of the pre-roll is
      written.
    * ``allow_unstable`` turns a frame out of its plausible range into one warning and goes on.
    * ``cage``: ``"auto"`` (default) simulates, where the skin is not one closed manifold, the
      character's own pieces or an automatic closed cage around it
      (:func:`~warpskin.preprocess.cage.build_cage`, weights transferred) and writes every mesh
      as its own LBS plus the physical deformation captured near it
      (:class:`~warpskin.character.Character`, :mod:`warpskin.capture`); a closed skin is
      simulated directly, its other meshes (attachments) following their joints by LBS.
      ``"always"`` cages any character (its attachments too); ``"none"`` never (the skin must
      then be closed). A mesh file (:data:`~warpskin.io.cage_file.CAGE_EXTENSIONS`) is the
      user's own cage, used as the automatic one would be
      (:func:`~warpskin.preprocess.cage.cage_from_mesh`: closed, manifold, around the rest
      pose, in the character file's units).
    * ``rigid_pieces``: through a cage, the pieces that LBS moves rigidly (eyes or teeth skinned
      to one joint, rigidly parented parts) move by one rigid motion with the cage around them
      (``"cage"``, default) or follow their joints (``"joint"``).
    * ``physics_weights``: ``{joint-name pattern: weight}`` overrides of the physics weight (0:
      LBS, 1: physical), before the scene's ``[physics.weights]``.
    * ``builder``: a model builder to use instead of the scene's (for example one with a
      rest-shape drive, :meth:`~warpskin.model.SkinModelBuilder.set_rest_drive`); then
      ``activation(t) -> [G]`` gives the muscle activation at clip time ``t`` (every substep's
      is precomputed and uploaded once, like the poses).
    * ``prepare(builder)``, where given, is called on the model builder of the simulated
      surface (the skin, or the character's cage) before the model is finalised, for example to
      set the rest-shape drive that ``activation`` drives (layered popping on any character).
    * ``overlay(character, builder, plan)``, where given, is called once the character is bound
      and returns an offset of what is written, stepped with the physics
      (:class:`~warpskin.popping.surface.SurfacePop`: its ``advance(steps)`` takes a frame's
      solver steps, its ``offsets(skinning matrices, points) -> [N, 3]`` [m] is added to every
      written point, before the written meshes are measured; its ``moved`` lists the points it
      may move); with its ``normal_guide`` true, every mesh it moves is also written without
      it, as the guide ``<mesh>_normal`` (the skin's: ``<skin>_normal``).
    """

    device: object = None
    frames: tuple[int, int] | None = None
    solver_params: SolverParams | None = None
    limits: RunLimits | None = None
    with_lbs: bool = False
    with_layers: bool = False
    report_dir: object = None
    progress: bool = True
    comment: str = ""
    use_graph: bool = True
    collision: object = None
    check_intersections: bool | None = None
    builder: SkinModelBuilder | None = None
    activation: Callable | None = None
    preroll: float | None = None
    allow_unstable: bool = False
    start_frame: int | None = None
    topology: str = "file"
    cage: object = "auto"
    rigid_pieces: str = "cage"
    physics_weights: dict | None = None
    guard: object = None
    prepare: Callable | None = None
    overlay: Callable | None = None


def simulate(scene: Scene | str, out_path, options: SimulationOptions | None = None, **overrides) -> SimulationResult:
    """Simulate a scene (a :class:`~warpskin.scene.Scene`, a shipped scene's name, a TOML path or a
    rig file) and write the skin (and on request LBS and the inner layers) to USD.

    ``options`` (:class:`SimulationOptions`, each field's meaning is documented there) with
    ``overrides`` (any of its fields by name, e.g. ``simulate(scene, path, frames=(0, 24),
    with_lbs=True)``), applied by :func:`~warpskin.options.with_overrides`.

    Every frame is checked against its plausible range before it is written: the simulated skin
    within ``max_offset`` x the body's diagonal of LBS, the whole and every sub-volume within
    ``max_volume_error`` of the rest volume (or twice LBS's own error, where LBS is worse), at
    most ``max_capped`` of it held at the tether's cap; and every mesh written with physics
    (:mod:`warpskin.quality`): at most ``max_strained`` more of its edges strained past 1.5x
    than its LBS, at most ``max_flipped`` of its triangles flipped against LBS, and not many
    more intersecting pairs than LBS. ``allow_unstable`` turns a violation into one warning and
    goes on. The summary's ``written`` holds each written mesh's worst figures, report.json
    their series. If a frame finds more contact candidates than the buffers hold, the frame is
    run again with larger buffers.

    Raises:
        InputError: an unknown option.
        SimulationError: a particle became NaN, or the skin left its plausible range; the
            message names the frame and the particle, vertex (the file's number), bone or
            sub-volume; the USD file keeps the frames before it (valid, closed).
    """
    options = with_overrides(SimulationOptions, options, overrides, "simulate")
    run = _Simulation(resolve_scene(scene), out_path, options)
    record = FrameRunner(run.plan, run, writer=run.writer, measures=[run.measures], progress=run.o.progress,
                         output=run.output).run(keep_failure=True)
    summary = _summary(run, record.frames)
    summary.update(_frame_timing(record, run.plan.substeps))
    result = SimulationResult(path=Path(run.writer.path), frames=record.frames, metrics=run.measures.m, summary=summary)
    if run.o.report_dir is not None:
        _write_report(run, summary)
    if record.failure is not None:
        raise record.failure
    return result


class _Simulation:
    """One run of :func:`simulate`: the character bound to its model, the stepper, the checks and
    the writer (its frames are what :class:`FrameRunner` writes: ``label``, :meth:`meshes`,
    :meth:`advance`, :meth:`frame`)."""

    def __init__(self, scene: Scene, out_path, o: SimulationOptions) -> None:
        from ..character import check_choices

        self.scene, self.o = scene, o
        self.cage_file = check_choices(o.cage, o.rigid_pieces)  # before any work
        check_output_path(out_path, inputs=[*scene.input_paths(), *([self.cage_file] if self.cage_file else [])])
        params = o.solver_params or scene.solver_params()
        params.check(str(scene.source or scene.name))
        self.limits = o.limits or scene.run_limits()
        self.limits.check(str(scene.source or scene.name))
        rig = scene.rig()
        self.clip = rig.clip(scene.clip)
        plan = FramePlan.for_scene(scene, o.frames, max_dt=params.dt, start_frame=o.start_frame)
        t_build = time.perf_counter()
        self.render = rig  # what is written
        self._bind(scene, rig)
        builder, model = self.builder, self.model
        self.params, self.plan, self.gravity_limit = _steps_gravity_allows(scene, model, params, plan,
                                                                           o.frames, o.start_frame)
        self.pop = o.overlay(self.character, builder, self.plan) if o.overlay is not None else None
        self.build_s = time.perf_counter() - t_build
        self._checks()
        self.writer = UsdSkinWriter(out_path, fps=self.plan.fps, up_axis=self.character.sim_rig.up_axis, comment=o.comment,
                                    root=self.output.root_name)

    def _bind(self, scene: Scene, rig) -> None:
        """The character (:class:`~warpskin.character.Character`), its simulated surface's model
        builder and model, bound."""
        from ..character import Character

        o = self.o
        weights = {**(o.physics_weights or {}), **{k: v for k, v in scene.physics_weights().items()
                                                   if k not in (o.physics_weights or {})}}
        guard = scene.guard_params() if o.guard is None else o.guard
        guard.check()
        character = Character(rig, cage="none" if o.builder is not None else (self.cage_file or o.cage),
                              rigid_pieces=o.rigid_pieces, weights=weights or None, device=o.device, guard=guard)
        self.character = character
        self.caged = character if character.caged else None
        self.captured = character if character.captured else None
        builder = o.builder or SkinModelBuilder(character.sim_rig, scene.model_params())  # [collision] included
        if o.prepare is not None:
            o.prepare(builder)
        if o.collision is not None:
            builder.params.collision = o.collision
        self.builder = builder
        self.model = builder.finalize(o.device)
        character.bind(builder, device=self.model.device)

    def _checks(self) -> None:
        """The stepper, the measures of the simulated surface and of the written meshes, and what
        is written."""
        o, character, plan = self.o, self.character, self.plan
        check_intersections = o.report_dir is not None if o.check_intersections is None else o.check_intersections
        self.stepper = PhysicsStepper(self.builder.rig, SkinSolver(self.model, self.params), plan, self.clip,
                                      use_graph=o.use_graph,
                                      preroll=self.scene.preroll if o.preroll is None else float(o.preroll),
                                      activation=o.activation,
                                      label=f"simulate {self.scene.name or self.builder.rig.name}")
        self.label = self.stepper.label
        self.measures = _Measurements(self.builder, self.stepper, plan, check_intersections, self.limits,
                                      o.allow_unstable)
        self.sim = self.builder.rig  # the simulated skin: the file's vertices first, then any added by refining
        self.output = (CharacterOutput(self.sim, o.topology, self.clip) if self.captured is None
                       else CharacterOutput(self.render, o.topology))
        self.quality = _WrittenQuality(character, plan, self.limits, o.allow_unstable, self.stepper, self.measures,
                                       self.output.skin_prim)
        self._meshes = _meshes_to_write(character, self.builder, self.render, o.with_lbs, o.with_layers)
        self.guided = []  # the meshes the overlay moves, each written without it beside it as a guide
        if self.pop is not None and self.pop.normal_guide:
            self.guided = [p for p in character.parts
                           if np.any((self.pop.moved >= p.start) & (self.pop.moved < p.start + p.count))]
            _add_normal_guides(self._meshes, self.guided, self.output.skin_prim)
        self.render_deviation = np.zeros(self.render.output_count)  # the written skin's, per vertex, over the frames

    # ------------------------------------------------------------------ what FrameRunner writes
    def meshes(self):
        return self._meshes

    def advance(self, i):
        self.stepper.advance(i)

    def frame(self, i):
        """The points written at frame ``i`` (after the checks, which stop the run where a mesh
        left its range)."""
        character, plan, params, o = self.character, self.plan, self.params, self.o
        pts = self.stepper.frame(i)
        self.measures.evaluate(i, pts["skin"])  # stops here if the simulated surface left its range
        t = plan.times[i]
        lbs_all = character.lbs(self.clip, t)
        # the surface's LBS of the frame: the tether's targets of its last step, where it stepped
        targets = self.stepper.solver.tether_targets if (i > 0 and params.tether > 0) else None
        written = character.written(self.stepper.state_a.x, pts["skin"], self.clip, t, lbs=lbs_all,
                                    surface_lbs=targets)
        normal = written
        if self.pop is not None:  # the overlay's offsets, stepped with the physics
            if i > 0:
                self.pop.advance(plan.substeps)
            every = np.concatenate([written[p.name] for p in character.parts])
            offsets = character.split(self.pop.offsets(self.render.skinning_matrices(self.clip, t), every))
            written = {k: v + offsets[k] for k, v in written.items()}
        lbs_by = character.split(lbs_all)
        self.quality.check(i, written, lbs_by)  # stops here if a written mesh left its range
        out = dict(written) if self.captured is not None else {"skin": written["skin"]}
        lbs = lbs_by["skin"]
        if self.caged is not None:
            out["cage"] = pts["skin"][: self.sim.output_count]
        elif self.captured is not None and o.with_layers:
            out["surface"] = pts["skin"][: character.pieces.vertex_count]
        deviation = np.linalg.norm(out["skin"] - lbs, axis=1)
        self.render_deviation[:] = np.maximum(self.render_deviation, deviation)
        out["primvars"] = {"skin": {"deviationFromLbs": deviation}}
        for p in self.guided:
            out["normal" if p.name == "skin" else f"{p.name}_normal"] = normal[p.name]
        if o.with_lbs:
            out["lbs"] = lbs
            if self.captured is not None:
                out.update({f"{name}_lbs": v for name, v in lbs_by.items() if name != "skin"})
        if o.with_layers:
            for k in range(1, 4):
                out[f"layer_{LAYER_NAMES[k]}"] = pts[f"layer_{LAYER_NAMES[k]}"]
        return out


def _add_normal_guides(meshes: list, guided: list, skin_prim: str) -> None:
    """Add to ``meshes`` (:func:`_meshes_to_write`) a guide ``<mesh>_normal`` for every part in
    ``guided`` (the meshes an overlay moves, written without it beside it)."""
    for p in guided:
        if p.name == "skin":
            meshes.insert(1, ("normal", meshes[0][1], meshes[0][2], {"color": _NORMAL_COLOR, "purpose": "guide",
                                                                    "prim_name": f"{skin_prim}_normal"}))
        else:
            meshes.append((f"{p.name}_normal", p.triangles, p.rest, {"color": _NORMAL_COLOR, "purpose": "guide"}))


def _summary(run: _Simulation, written: list[int]) -> dict:
    """The run's summary (:attr:`SimulationResult.summary`) after the frames ``written``."""
    metrics, plan, params, model = run.measures.m, run.plan, run.params, run.model
    character, caged, stepper, quality = run.character, run.caged, run.stepper, run.quality
    col = stepper.collision
    # frame 0 is the LBS pose by construction (the simulation starts there): measure after it
    vol, vol_lbs, v0 = np.array(metrics["volume"][1:]), np.array(metrics["volume_lbs"][1:]), metrics["volume_rest"]
    summary = {
        "scene": run.scene.name, "device": str(model.device), "particles": model.particle_count,
        "vertices": model.vertex_count, "topology": run.o.topology,
        "file_vertices_written": run.render.file_vertex_count if run.o.topology == "file" else run.render.output_count,
        "surface": _surface_summary(character),
        "cage": None if caged is None else _cage_summary(caged, run.o.rigid_pieces, run.cage_file),
        "physics_weight": character.weight_summary(),
        "written": quality.log.summary(),
        "written_worst": quality.log.worst(),
        "written_across": quality.log.across_summary(),
        "delivered": quality.delivery.summary(),
        "max_capped_share": float(max(quality.capped)) if quality.capped else 0.0,
        "refined_vertices_added": model.vertex_count - run.sim.output_count,
        "frames": len(written),
        "substeps_per_frame": plan.substeps,
        "dt_s": plan.dt,
        "gravity_step_limit_s": run.gravity_limit if np.isfinite(run.gravity_limit) else None,
        "iterations": params.iterations,
        "volume_iterations": params.volume_iterations,
        "fast_summation": params.fast_summation,
        "graph_capture": bool(stepper.graphs),  # frames replayed from captured graphs (else plain launches)
        "build_s": run.build_s,
        "mean_step_ms": float(np.mean(metrics["step_ms"][1:])) if len(written) > 1 else 0.0,
        "max_volume_deviation": float(np.abs(vol / v0 - 1).max()) if vol.size else 0.0,
        "max_volume_deviation_lbs": float(np.abs(vol_lbs / v0 - 1).max()) if vol.size else 0.0,
        "collisions": col is not None,
        "collision_thickness_m": col.thickness if col is not None else None,
        "collision_capacity": stepper.contacts.capacity if col is not None else None,
        "overflow_retries": stepper.overflow_retries,
        "preroll_s": stepper.preroll,
        "preroll_steps": stepper.preroll_steps,
        "bvh_rebuilds": col.rebuilds if col is not None else 0,
        "fail_safe_pairs": int(col.fail_safe_pairs.numpy()[0]) if col is not None else 0,
        "tether": params.tether,
        "tether_clamped_particle_steps": int(stepper.solver.tether_clamped.numpy()[0]),
        "max_offset_from_lbs_m": float(max(metrics["max_offset_from_lbs"])) if metrics["max_offset_from_lbs"] else 0.0,
        "body_diagonal_m": run.measures.diagonal,
        # the written meshes' rest diagonal, all of them together (the joint limit's reference)
        "written_diagonal_m": float(np.linalg.norm(np.ptp(character.soup.points, axis=0))),
        "length_unit_m": stepper.solver.length_unit,  # metres per file unit, as gravity takes it
        "depth_reduced_vertices": int((run.builder.layers.depth_scale < 1.0).sum()),
        "depth_notes": list(run.builder.layers.depth_notes),
    }
    if run.measures.check_intersections and metrics["intersecting_pairs"]:
        summary["max_intersecting_pairs"] = max(metrics["intersecting_pairs"])
        summary["max_intersecting_pairs_lbs"] = max(metrics["intersecting_pairs_lbs"])
        summary["intersecting_pairs_first_frame"] = metrics["intersecting_pairs"][0]
    subs = run.builder.subvolumes
    if subs is not None and metrics["subvolume"]:
        if len(metrics["subvolume"]) > 1:
            for key, name in (("subvolume", "max_subvolume_deviation"), ("subvolume_lbs", "max_subvolume_deviation_lbs")):
                summary[name] = float(subs.volume_errors(np.array(metrics[key][1:])).max())
        summary["subvolume_names"] = list(subs.names)
    return summary


def _frame_timing(record, substeps: int) -> dict:
    """``mean_frame_ms``: the wall time of a frame after the first (its steps and read-back,
    the guard and checks, writing, measures), and ``host_share``: the share of that not spent
    stepping (the per-frame work around the steps; on the CPU the steps are host time too)."""
    frame = np.asarray(record.frame_ms[1:], dtype=np.float64)
    steps = np.asarray(record.step_ms[1:len(record.frame_ms)], dtype=np.float64) * substeps
    if not frame.size or frame.sum() <= 0.0:
        return {"mean_frame_ms": 0.0, "host_share": 0.0}
    return {"mean_frame_ms": float(frame.mean()), "host_share": float(max(1.0 - steps.sum() / frame.sum(), 0.0))}


def _cage_summary(caged, rigid_pieces: str, cage_file) -> dict:
    """The summary's ``cage``: what was simulated around a caged character."""
    return {
        "vertices": int(caged.sim_rig.vertex_count), "edge_m": caged.cage_surface.edge, "build_s": caged.build_s,
        "weights_matched": float(caged.matched.mean()), "captured_points": int(caged.point_count),
        "rigid_pieces": caged.rigid_piece_count, "rigid_pieces_follow": rigid_pieces,
        "meshes": [p.name for p in caged.parts],
        "source": str(cage_file) if cage_file is not None else "automatic",
    }


def _write_report(run: _Simulation, summary: dict) -> None:
    """``report.json`` and the PNG plots into the run's ``report_dir``; adds ``plots`` to
    ``summary``."""
    report = Path(run.o.report_dir)
    report.mkdir(parents=True, exist_ok=True)
    model, plan, params, metrics = run.model, run.plan, run.params, run.measures.m
    subs = run.builder.subvolumes
    col = run.stepper.collision
    title = (f"{run.scene.name}: {model.particle_count} particles, {plan.substeps} x {plan.dt * 1e3:.2f} ms steps per "
             f"frame at {plan.fps:g} fps, {params.iterations} + {params.volume_iterations} iterations, collisions "
             f"{'on' if col is not None else 'off'}, {model.device}")
    plots = write_plots(report, metrics, list(subs.names) if subs is not None else [], title=title,
                        where=(run.output.rest, run.render_deviation),
                        weights=(run.character.soup.points, run.character.capture_result.physics_weight),
                        quality=run.quality.log.series)
    if not plots:
        warnings.warn(f"{report}: no PNG plots (matplotlib cannot be imported: reinstall warpskin); report.json "
                      f"has the figures", RuntimeWarning, stacklevel=3)
    summary["plots"] = plots or "matplotlib cannot be imported: no PNG plots"
    (report / "report.json").write_text(json.dumps({"summary": summary, "metrics": run.measures.m,
                                                    "written": run.quality.log.series}, indent=1))

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
from ..io.usd_export import UsdSkinWriter, check_output_path
from ..metrics import self_intersections, signed_volume
from ..model import SkinModelBuilder
from ..preprocess.layers import LAYER_NAMES
from ..scene import Scene
from ..solver import SolverParams
from ..transforms import linear_blend_skin
from .physics import PhysicsStepper
from .output import CharacterOutput, attachment_kwargs
from .plan import FramePlan
from .runner import FrameRunner

__all__ = ["SimulationResult", "simulate"]

_SKIN_COLOR = (0.85, 0.64, 0.52)
_LBS_COLOR = (0.4, 0.55, 0.85)


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


class _Measurements:
    """Per-frame measurements of the physical skin against LBS (host, after the frame)."""

    def __init__(self, builder, stepper: PhysicsStepper, plan: FramePlan, check_intersections: bool,
                 params: SolverParams, allow_unstable: bool = False) -> None:
        self.b, self.st, self.plan = builder, stepper, plan
        self.check_intersections = check_intersections
        self.params, self.allow_unstable, self.warned = params, allow_unstable, False
        self.diagonal = builder.rig.size()
        self._pending: dict = {}
        self._clamped = int(stepper.solver.tether_clamped.numpy()[0])  # the pre-roll's
        col = stepper.collision
        self._fail_safe = int(col.fail_safe_pairs.numpy()[0]) if col is not None else 0
        rig = builder.rig
        subs = builder.subvolumes
        self.m: dict = {k: [] for k in ("time", "frame", "volume", "volume_lbs", "subvolume", "subvolume_lbs", "kinetic_energy",
                                         "max_offset_from_lbs", "relative_speed_rms", "step_ms", "residuals",
                                         "contacts_point_triangle", "contacts_edge_edge", "constraints_active", "intersecting_pairs",
                                         "intersecting_pairs_lbs", "tether_clamped", "fail_safe_pairs")}
        self.m["volume_rest"] = signed_volume(rig.vertices[: rig.output_count], rig.output_triangles)
        self.m["subvolume_rest"] = subs.rest_volume.tolist() if subs is not None else []
        self.lbs: np.ndarray | None = None
        self._prev_lbs: np.ndarray | None = None
        self._prev_speed = 0.0
        self._skin_mass = np.asarray(builder.masses[: rig.vertex_count], dtype=np.float64)
        self.max_deviation = np.zeros(rig.output_count)  # per file vertex, over the frames written

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
        e = {"lbs": lbs, "volume": signed_volume(out, tris), "volume_lbs": signed_volume(lbs, tris)}
        if subs is not None:
            centres = subs.center_positions(st.frame_poses[i])
            e["subvolume"] = subs.volumes(skin.astype(np.float64), centres)
            e["subvolume_lbs"] = subs.volumes(lbs_all, centres)
        d = np.linalg.norm(out - lbs, axis=1)
        e["offset"] = float(d.max())
        e["deviation"] = d
        # the skin's motion relative to the animation: its velocities minus LBS's over the frame
        e["velocities"] = vel = st.velocities()  # one host copy per frame, for __call__ too
        vs = vel[: b.rig.vertex_count].astype(np.float64)
        if self._prev_lbs is not None and i > 0:
            frame_dt = self.plan.times[i] - self.plan.times[i - 1]
            rel = vs - (lbs_all - self._prev_lbs) / frame_dt
        else:
            rel = np.zeros_like(vs)
        w = self._skin_mass
        e["relative_speed_rms"] = float(np.sqrt(np.sum(w * np.einsum("ij,ij->i", rel, rel)) / w.sum()))
        e["relative_speed"] = rel
        e["relative_speed_before"] = self._prev_speed
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
        p, b = self.params, self.b
        f = self.plan.frames[i]
        diag = self.diagonal
        if e["offset"] > p.max_offset * diag:
            k = int(np.argmax(d))
            bone = b.layers.bones.joint_names[b.layers.bone[k]]
            return (f"frame {f}: the skin left its plausible range: file vertex {int(b.rig.file_vertex_ids([k])[0])} "
                    f"(bone {bone!r}) is {e['offset']:.3g} m from LBS, {100 * e['offset'] / diag:.1f} % of the body's "
                    f"{diag:.3g} m diagonal (max_offset {p.max_offset:g})")
        speed, before = e["relative_speed_rms"], e["relative_speed_before"]
        if speed > p.max_speed * diag and speed > before:
            rel = np.linalg.norm(e["relative_speed"], axis=1)
            k = int(np.argmax(rel))
            bone = b.layers.bones.joint_names[b.layers.bone[k]]
            return (f"frame {f}: the skin left its plausible range: its motion relative to the animation keeps "
                    f"growing without input (RMS {speed:.3g} m/s, {speed / diag:.2g} body diagonals per second, "
                    f"max_speed {p.max_speed:g}; fastest near file vertex {int(b.rig.file_vertex_ids([k])[0])}, "
                    f"bone {bone!r})")
        v0 = self.m["volume_rest"]
        err, err_lbs = abs(e["volume"] / v0 - 1.0), abs(e["volume_lbs"] / v0 - 1.0)
        if err > max(p.max_volume_error, 2.0 * err_lbs):
            return (f"frame {f}: the skin left its plausible range: its volume is off by {100 * err:.1f} % (LBS "
                    f"{100 * err_lbs:.1f} %, max_volume_error {100 * p.max_volume_error:g} %)")
        if "subvolume" in e:
            rest = b.subvolumes.rest_volume
            err_s = np.abs(e["subvolume"] / rest - 1.0)
            err_s_lbs = np.abs(e["subvolume_lbs"] / rest - 1.0)
            over = err_s > np.maximum(p.max_volume_error, 2.0 * err_s_lbs)
            if over.any():
                k = int(np.argmax(np.where(over, err_s, -1.0)))
                return (f"frame {f}: the skin left its plausible range: sub-volume {b.subvolumes.names[k]!r} is off by "
                        f"{100 * err_s[k]:.1f} % (LBS {100 * err_s_lbs[k]:.1f} %, max_volume_error "
                        f"{100 * p.max_volume_error:g} %)")
        return None

    def __call__(self, i: int, f: int, points: dict, step_ms: float) -> None:
        m, b, st = self.m, self.b, self.st
        tris = b.rig.output_triangles
        self.max_deviation = np.maximum(self.max_deviation, self._pending["deviation"])
        skin = points.get("cage", points["skin"])  # the simulated surface: the file's vertices, or the cage
        e = self._pending
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
            m["intersecting_pairs"].append(int(len(self_intersections(skin, tris))))
            m["intersecting_pairs_lbs"].append(int(len(self_intersections(lbs, tris))))


class _CagedCharacter:
    """A character simulated through a cage (automatic, or the user's ``cage_file``): the cage
    rig, and (:meth:`bind`) every render mesh embedded in the cage at rest (stage space)."""

    def __init__(self, rig, device, cage_file=None) -> None:
        from ..preprocess.cage import build_cage, cage_from_mesh, cage_rig, character_soup

        t0 = time.perf_counter()
        soup = character_soup(rig)
        if cage_file is not None:  # the user's own
            from ..io.cage_file import read_cage_mesh

            self.cage = cage_from_mesh(read_cage_mesh(cage_file), rig, device=device, soup=soup)
        else:
            self.cage = build_cage(soup.points, soup.triangles, device=device)
        self.rig, self.soup, self.matched = cage_rig(rig, self.cage, device=device)
        self.source = rig
        self.device = device
        self.embedding = None
        self.build_s = time.perf_counter() - t0

    def bind(self, builder, rigid_pieces: str = "cage") -> None:
        """Embed every render mesh in the cage's model: the normal at a cage vertex is the
        direction from its fat-layer particle to it (one launch per frame, no normal pass).
        The pieces that LBS moves rigidly (:func:`~warpskin.preprocess.cage.rigid_pieces`: eyes,
        teeth, rigidly parented parts) move as rigid bodies with the cage region they lie in
        (``rigid_pieces="cage"``) or follow their joints by LBS (``"joint"``)."""
        from ..embedding import Embedding
        from ..preprocess.cage import rigid_pieces as find_rigid

        t0 = time.perf_counter()
        self.rigid = find_rigid(self.soup)
        self.rigid_mode = rigid_pieces
        n = len(self.cage.vertices)  # the cage's own vertices come first (a refined cage adds more after)
        self.embedding = Embedding(self.soup.points, self.cage.vertices, self.cage.triangles,
                                   inner=builder.layers.positions[1][:n],
                                   rigid=self.rigid if rigid_pieces == "cage" else None, device=self.device)
        self.build_s += time.perf_counter() - t0

    @property
    def rigid_piece_count(self) -> int:
        return int(self.rigid.max()) + 1 if self.rigid.size else 0

    def attachment_meshes(self) -> list:
        out = []
        for a in self.source.attachments:
            _, start, count = next(p for p in self.soup.pieces if p[0] == a.name)
            out.append((a.name, a.triangles, self.soup.points[start:start + count], attachment_kwargs(a)))
        return out

    def render_points(self, cage_points: np.ndarray, fat_points: np.ndarray, lbs) -> dict:
        """Every render mesh's points on the cage's skin and fat layers (their first ``V`` rows);
        with rigid pieces following their joints, theirs from ``lbs()`` (the soup's LBS)."""
        n = self.embedding.cage_vertex_count
        x = np.concatenate([cage_points[:n], fat_points[:n]]).astype(np.float32)
        pts = self.embedding.evaluate(x).numpy().astype(np.float64)
        if self.rigid_mode == "joint" and self.rigid_piece_count:
            sel = self.rigid >= 0
            pts[sel] = lbs()[sel]
        return {name: pts[start:start + count] for name, start, count in self.soup.pieces}


def simulate(
    scene: Scene,
    out_path,
    *,
    device=None,
    frames: tuple[int, int] | None = None,
    solver_params: SolverParams | None = None,
    with_lbs: bool = False,
    with_layers: bool = False,
    report_dir=None,
    progress: bool = True,
    comment: str = "",
    use_graph: bool = True,
    collision=None,
    check_intersections: bool | None = None,
    builder: SkinModelBuilder | None = None,
    activation: Callable | None = None,
    preroll: float | None = None,
    allow_unstable: bool = False,
    start_frame: int | None = None,
    topology: str = "file",
    cage: str | Path = "auto",
    rigid_pieces: str = "cage",
) -> SimulationResult:
    """Simulate a scene and write the skin (and on request LBS and the inner layers) to USD.

    ``use_graph`` records each frame's substeps once as a Warp graph (CPU and CUDA) and
    replays it, which removes the per-launch overhead; the results are bit-identical.
    ``builder`` is a model builder to use instead of the scene's (for example one with a
    rest-shape drive, :meth:`~warpskin.model.SkinModelBuilder.set_rest_drive`); then
    ``activation(t) -> [G]`` gives the muscle activation at clip time ``t`` (every substep's is
    precomputed and uploaded once, like the poses). ``collision``
    (:class:`~warpskin.collision.CollisionParams`) defaults to the scene's ``[collision]``
    section (on unless disabled). If a frame finds more contact candidates than the buffers
    hold, the frame is run again with larger buffers. ``check_intersections`` counts
    intersecting skin triangle pairs per frame with the exact, solver-independent check
    (:func:`warpskin.metrics.self_intersections`); default: only when writing a report.
    ``preroll`` [s] (default: the scene's ``[animation] preroll``) simulates that long before
    the first frame, from the bind pose into the first frame's pose (the root joints at the
    first frame's placement throughout, the joints below them interpolated, eased in and out);
    velocities are zeroed after it.
    A first pose whose LBS skin already passes through itself is then reached by collision
    instead of started from; nothing of the pre-roll is written.

    Every frame is checked against its plausible range before it is written: the skin within
    ``max_offset`` x the body's diagonal of LBS, the whole and every sub-volume within
    ``max_volume_error`` of the rest volume (or twice LBS's own error, where LBS is worse).
    ``allow_unstable`` turns a violation into one warning and goes on.

    Frames are the source's time codes (``frame / fps`` seconds, at the clip's own rate unless
    the scene sets ``fps``); ``start_frame`` writes the first frame at that time code instead.
    ``topology`` ``"file"`` (default) writes the skin (and LBS) with the file's own vertices,
    faces, UVs and materials, ``"welded"`` the closed surface as loaded.

    ``cage``: ``"auto"`` (default) simulates an automatic closed cage around the character
    (:func:`~warpskin.preprocess.cage.build_cage`, weights transferred) where its skin is not
    one closed manifold, and writes every mesh embedded in it
    (:class:`~warpskin.embedding.Embedding`) with the cage as a guide; a closed skin is
    simulated directly, its other meshes (attachments) following their joints by LBS.
    ``"always"`` cages any character (its attachments too); ``"none"`` never (the skin must
    then be closed). A mesh file (:data:`~warpskin.io.cage_file.CAGE_EXTENSIONS`) is the user's
    own cage, used as the automatic one would be
    (:func:`~warpskin.preprocess.cage.cage_from_mesh`: closed, manifold, around the rest pose,
    in the character file's units). ``rigid_pieces``: through a cage, the pieces that LBS moves
    rigidly (eyes or teeth skinned to one joint, rigidly parented parts) move as rigid bodies with
    the cage region they lie in (``"cage"``, default) or follow their joints (``"joint"``).

    Raises:
        SimulationError: a particle became NaN, or the skin left its plausible range; the
            message names the frame and the particle, vertex (the file's number), bone or
            sub-volume; the USD file keeps the frames before it (valid, closed).
    """
    import time

    cage_file = None
    if rigid_pieces not in ("cage", "joint"):
        from ..errors import SceneError

        raise SceneError(f"rigid_pieces must be 'cage' or 'joint', got {rigid_pieces!r}")
    if isinstance(cage, Path) or cage not in ("auto", "always", "none"):
        from ..errors import SceneError
        from ..io.cage_file import CAGE_EXTENSIONS

        if not isinstance(cage, (str, Path)) or Path(cage).suffix.lower() not in CAGE_EXTENSIONS:
            raise SceneError(f"cage must be 'auto', 'always', 'none' or a mesh file ({', '.join(CAGE_EXTENSIONS)}), "
                             f"got {cage!r}")
        cage_file = Path(cage)
    check_output_path(out_path, inputs=[*scene.input_paths(), *([cage_file] if cage_file else [])])  # before any work
    params = solver_params or scene.solver_params()
    params.check(str(scene.source or scene.name))
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    plan = FramePlan.for_scene(scene, frames, max_dt=params.dt, start_frame=start_frame)
    preroll = scene.preroll if preroll is None else float(preroll)
    t_build = time.perf_counter()
    render = rig  # what is written
    caged = None
    report = rig.report or rig.validate(raise_on_error=False)
    closed_skin = report.closed and report.manifold
    if builder is None and (cage_file is not None or cage == "always" or (cage == "auto" and not closed_skin)):
        caged = _CagedCharacter(rig, device, cage_file)
        rig = caged.rig
    builder = builder or SkinModelBuilder(rig, scene.model_params())  # the scene's [collision] included
    if collision is not None:
        builder.params.collision = collision
    model = builder.finalize(device)
    if caged is not None:
        caged.bind(builder, rigid_pieces)
    build_s = time.perf_counter() - t_build
    if check_intersections is None:
        check_intersections = report_dir is not None
    stepper = PhysicsStepper(builder, model, params, plan, clip, use_graph=use_graph, preroll=preroll,
                             activation=activation, label="simulate", name=scene.name)
    measures = _Measurements(builder, stepper, plan, check_intersections, params, allow_unstable)
    sim = builder.rig  # the simulated skin: the file's vertices first, then any added by refining
    n_out = sim.output_count
    tris = sim.output_triangles
    # the skin carries its distance from LBS per vertex and frame, for a DCC to colour it by
    if caged is None:
        meshes = [("skin", tris, sim.vertices[:n_out], {"color": _SKIN_COLOR, "animated_primvars": ("deviationFromLbs",)})]
        if with_lbs:
            meshes.append(("lbs", tris, sim.vertices[:n_out], {"color": _LBS_COLOR, "purpose": "guide"}))
    else:  # the render meshes, embedded in the simulated cage; the cage as a guide
        rt = render.output_triangles
        meshes = [("skin", rt, render.vertices[: render.output_count],
                   {"color": _SKIN_COLOR, "animated_primvars": ("deviationFromLbs",)})]
        if with_lbs:
            meshes.append(("lbs", rt, render.vertices[: render.output_count], {"color": _LBS_COLOR, "purpose": "guide"}))
        meshes += caged.attachment_meshes()
        if with_lbs:  # each embedded mesh's own LBS beside it, as for the skin
            meshes += [(f"{name}_lbs", t, p, {"color": _LBS_COLOR, "purpose": "guide"})
                       for name, t, p, _ in caged.attachment_meshes()]
        meshes.append(("cage", sim.output_triangles, caged.cage.vertices,
                       {"color": (0.6, 0.6, 0.6), "purpose": "guide", "as_is": True}))
    if with_layers:  # the inner layers as simulated (guides)
        for k in range(1, 4):
            meshes.append((f"layer_{LAYER_NAMES[k]}", sim.triangles, builder.layers.positions[k],
                           {"purpose": "guide", "as_is": True}))

    render_deviation = np.zeros(render.output_count)  # caged: per render vertex, over the frames

    class _Writes:
        """What ``simulate`` writes of a physics frame."""

        label = stepper.label

        def meshes(self):
            return meshes

        def advance(self, i):
            stepper.advance(i)

        def frame(self, i):
            pts = stepper.frame(i)
            out = {"skin": pts["skin"][:n_out]}
            lbs = measures.evaluate(i, pts["skin"])  # stops here if the skin left its range
            if caged is not None:  # the cage's own vertices come first (a refined cage adds more after)
                # the render skin's own LBS (its inverse binds, not the cage's, which is bound at rest)
                lbs = linear_blend_skin(render.vertices[: render.output_count], render.joint_indices[: render.output_count],
                                        render.joint_weights[: render.output_count],
                                        render.skinning_matrices(clip, plan.times[i]))

                def soup_lbs(skin_lbs=lbs, t=plan.times[i]):
                    world = render.joint_world_transforms(clip, t)
                    return np.concatenate([skin_lbs, *[a.points(world) for a in render.attachments]])

                out = caged.render_points(pts["skin"], pts["layer_fat"], soup_lbs)
                out["cage"] = pts["skin"][: sim.output_count]
            deviation = np.linalg.norm(out["skin"] - lbs, axis=1)
            if caged is not None:
                render_deviation[:] = np.maximum(render_deviation, deviation)
            out["primvars"] = {"skin": {"deviationFromLbs": deviation}}
            if with_lbs:
                out["lbs"] = lbs
                if caged is not None and render.attachments:
                    world = render.joint_world_transforms(clip, plan.times[i])
                    for a in render.attachments:
                        out[f"{a.name}_lbs"] = a.points(world)
            if with_layers:
                for k in range(1, 4):
                    out[f"layer_{LAYER_NAMES[k]}"] = pts[f"layer_{LAYER_NAMES[k]}"]
            return out

    output = CharacterOutput(sim, topology, clip) if caged is None else CharacterOutput(render, topology)
    writer = UsdSkinWriter(out_path, fps=plan.fps, up_axis=rig.up_axis, comment=comment, root=output.root_name)
    record = FrameRunner(plan, _Writes(), writer=writer, measures=[measures], progress=progress,
                         output=output).run(keep_failure=True)
    metrics = measures.m
    written = record.frames
    subs = builder.subvolumes
    col = stepper.collision
    # frame 0 is the LBS pose by construction (the simulation starts there): measure after it
    vol = np.array(metrics["volume"][1:])
    vol_lbs = np.array(metrics["volume_lbs"][1:])
    v0 = metrics["volume_rest"]
    summary = {
        "scene": scene.name,
        "device": str(model.device),
        "particles": model.particle_count,
        "vertices": model.vertex_count,
        "topology": topology,
        "file_vertices_written": render.file_vertex_count if topology == "file" else render.output_count,
        "cage": None if caged is None else {
            "vertices": int(caged.rig.vertex_count), "edge_m": caged.cage.edge, "build_s": caged.build_s,
            "weights_matched": float(caged.matched.mean()), "embedded_points": int(caged.embedding.count),
            "rigid_pieces": caged.rigid_piece_count, "rigid_pieces_follow": rigid_pieces,
            "meshes": [p[0] for p in caged.soup.pieces],
            "source": str(cage_file) if cage_file is not None else "automatic",
        },
        "refined_vertices_added": model.vertex_count - n_out,
        "frames": len(written),
        "substeps_per_frame": plan.substeps,
        "dt_s": plan.dt,
        "iterations": params.iterations,
        "volume_iterations": params.volume_iterations,
        "fast_summation": params.fast_summation,
        "graph_capture": bool(stepper.graphs),  # frames replayed from captured graphs (else plain launches)
        "build_s": build_s,
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
        "body_diagonal_m": measures.diagonal,
        "depth_reduced_vertices": int((builder.layers.depth_scale < 1.0).sum()),
        "depth_notes": list(builder.layers.depth_notes),
    }
    if check_intersections and metrics["intersecting_pairs"]:
        summary["max_intersecting_pairs"] = max(metrics["intersecting_pairs"])
        summary["max_intersecting_pairs_lbs"] = max(metrics["intersecting_pairs_lbs"])
        summary["intersecting_pairs_first_frame"] = metrics["intersecting_pairs"][0]
    if subs is not None and metrics["subvolume"]:
        rest = np.array(metrics["subvolume_rest"])
        if len(metrics["subvolume"]) > 1:
            summary["max_subvolume_deviation"] = float(np.abs(np.array(metrics["subvolume"][1:]) / rest - 1).max())
            summary["max_subvolume_deviation_lbs"] = float(np.abs(np.array(metrics["subvolume_lbs"][1:]) / rest - 1).max())
        summary["subvolume_names"] = list(subs.names)
    result = SimulationResult(path=Path(writer.path), frames=written, metrics=metrics, summary=summary)
    if report_dir is not None:
        from ..report import write_plots

        report = Path(report_dir)
        report.mkdir(parents=True, exist_ok=True)
        title = (f"{scene.name}: {model.particle_count} particles, {plan.substeps} x {plan.dt * 1e3:.2f} ms steps per frame "
                 f"at {plan.fps:g} fps, {params.iterations} + {params.volume_iterations} iterations, collisions "
                 f"{'on' if col is not None else 'off'}, {model.device}")
        plots = write_plots(report, metrics, list(subs.names) if subs is not None else [], title=title,
                            where=(output.rest, measures.max_deviation if caged is None else render_deviation))
        summary["plots"] = plots or "matplotlib not installed: pip install 'warpskin[report]' for PNG plots"
        (report / "report.json").write_text(json.dumps({"summary": summary, "metrics": metrics}, indent=1))
    if record.failure is not None:
        raise record.failure
    return result

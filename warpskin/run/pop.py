"""``warpskin pop``: a popping scene to USD through the frame runner, in the paper's goal mode
(example-based skinning plus the goal-driven skin vibration) or the layered mode (the
activation drives the multi-layer model's rest shape; the physical skin makes the pop)."""

from __future__ import annotations

import math

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import RigWarning, SceneError
from ..io.usd_export import UsdSkinWriter, valid_prim_name, check_output_path
from ..model import SkinModelBuilder
from ..options import with_overrides
from ..params import PoppingSettings
from ..popping.activation import BeatSpec, popping_settings, vibrating
from ..popping.dynamics import PoppingDynamics
from ..popping.examples import PoppingExamples, examples_for_scene, examples_from_file, has_examples
from ..popping.layered import muscle_rest_offset_deltas, rest_offset_deltas
from ..popping.muscles import DEFAULT_SWELL, belly_of_swelling, groups_of_model, muscles_from_skeleton
from ..popping.pose_space import PoseSpaceDeformer
from ..popping.report import belly_of_bones, belly_of_examples, write_popping_report
from ..preprocess.bones import Bones
from ..rig import Clip
from ..scene import resolve_scene
from ..units import file_unit
from .output import CharacterOutput
from .plan import FramePlan
from .runner import FrameRunner

__all__ = ["PoppingOptions", "PoppingRun", "PoppingStepper", "pop", "run_popping", "surface_muscles",
           "POP_ON"]

POP_ON = ("surface", "layers")
"""Where muscles found from the skeleton swell (:func:`run_popping`'s ``pop_on``)."""
_CLEAR = 2.5e-4  # the gap a surface pop keeps to a surface it meets, in body diagonals


@dataclass
class PoppingRun:
    """What :func:`run_popping` wrote.

    Attributes:
        path: The USD file.
        frames: Number of frames written.
        summary: Scalars: device, vertices, groups, substeps, dt [s], ``peak_overshoot_m`` (the
            farthest any vertex passed its goal, measured along its goal's disparity direction),
            ``max_goal_distance_m``, ``ms_per_frame`` (example-based skinning plus dynamics,
            without the USD writing).
    """

    path: Path
    frames: int
    summary: dict = field(default_factory=dict)


class PoppingStepper:
    """The goal mode as a stepper: every frame poses the example-based skinning at the frame's
    pose and advances the dynamics by the plan's substeps ending at the frame's time, with the
    activation sampled at each step."""

    def __init__(self, rig, clip, plan: FramePlan, deformer: PoseSpaceDeformer, dynamics: PoppingDynamics,
                 settings: PoppingSettings, *, name: str = "") -> None:
        self.rig, self.clip, self.plan = rig, clip, plan
        self.deformer, self.dynamics, self.settings = deformer, dynamics, settings
        self.groups = deformer.group_names
        self.step_times = plan.substep_times(leading=True)
        self.label = f"pop {name or rig.name} ({deformer.device}, {rig.vertex_count} vertices)"
        self.variant = "popping"
        self._points: dict[str, np.ndarray] = {}

    def meshes(self) -> list:
        tris, rest = self.rig.triangles, self.rig.vertices
        return [
            ("popping", tris, rest, {"color": (0.85, 0.64, 0.52)}),
            ("normal", tris, rest, {"color": (0.55, 0.75, 0.55)}),
            ("goal", tris, rest, {"color": (0.8, 0.4, 0.4), "purpose": "guide"}),
            ("lbs", tris, rest, {"color": (0.4, 0.55, 0.85), "purpose": "guide"}),
        ]

    def advance(self, i: int) -> None:
        p = self.plan
        self.deformer.set_pose(self.rig.skinning_matrices(self.clip, p.times[i]))
        for s in range(p.substeps):
            self.dynamics.step(p.dt, self.settings.activation.sample(self.step_times[i * p.substeps + s], self.groups))
        self._points = {
            "popping": self.dynamics.points.numpy(),
            "normal": self.deformer.normal_points.numpy(),
            "goal": self.dynamics.goal_points.numpy(),
            "lbs": self.deformer.lbs().numpy(),
        }

    def frame(self, i: int) -> dict[str, np.ndarray]:
        return self._points


class _Overshoot:
    """How far past its goal a vertex gets, along the goal's disparity direction."""

    def __init__(self) -> None:
        self.peak_over = 0.0
        self.max_goal = 0.0

    def __call__(self, i, f, pts, step_ms) -> None:
        x, goal, normal = pts["popping"], pts["goal"], pts["normal"]
        d = goal - normal
        dl = np.linalg.norm(d, axis=1)
        moved = dl > 1e-6
        if moved.any():
            over = np.einsum("ij,ij->i", (x - goal)[moved], d[moved] / dl[moved, None])
            self.peak_over = max(self.peak_over, float(over.max()))
        self.max_goal = max(self.max_goal, float(np.linalg.norm(x - goal, axis=1).max()))


@dataclass(frozen=True)
class PoppingOptions:
    """How :func:`run_popping` plays a scene: the Python API's options, and what ``warpskin pop``
    builds from its command line. Every field has the default a scene needs nothing else for.

    Attributes:
        examples: The examples; default :func:`~warpskin.popping.examples_for_scene`.
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:N"``, ``None``: Warp's default).
        frames: Inclusive frame range; default the scene's.
        fps: Output frame rate; default the scene's.
        start_frame: Time code of the first frame written; default its frame number.
        topology: ``"file"`` (the file's own vertices, faces, UVs; default) or ``"welded"``.
        alpha_min, beta, dt: Overrides of the scene's ``[popping]`` values.
        progress: Progress bar on stderr.
        comment: Stage comment.
        mode: ``"goal"`` or ``"layered"``; default the scene's ``[popping] mode``.
        beats: Pops on a tempo or a list of beats (:class:`~warpskin.popping.BeatSpec`) over
            the frames written, in place of the scene's ``[popping.activation]``.
        muscles: Layered mode without examples (any closed rig): the muscle groups, as
            :func:`~warpskin.popping.muscles_from_skeleton` takes them (``name=pattern`` or a
            found group's name); default every group found from the skeleton.
        swell: Their peak swelling as a share of the fat-plus-muscle depth (default
            :data:`~warpskin.popping.muscles.DEFAULT_SWELL` in the layers,
            :data:`~warpskin.popping.surface.DEFAULT_SURFACE_SWELL` on the surface).
        cage: Layered mode without examples: ``"auto"`` (an open character simulates through
            an automatic cage, whose muscles pop and carry the written meshes), ``"always"``,
            ``"none"`` or a cage mesh file, as :func:`~warpskin.run.simulate` takes it.
        report_dir: Also write the report there: each muscle group's bulge against its
            activation over time (``popping.json``, ``popping.png``; :mod:`warpskin.popping.report`),
            in layered mode beside the simulation's own report.
        normal_guide: Layered mode: also simulate the same frames without the pop and write
            that skin beside the result as the guide ``<skin>_normal`` (the paper's normal-only
            skin; the pop's bulge is measured against it). Doubles the cost. Both run with the
            volume constraints along the normals (``[solver] volume_along_normals``) unless the
            scene sets it.
        vibrate: Layered mode: the rest-shape drive follows each group's activation as the
            paper's skin follows its goal (:func:`~warpskin.popping.activation.vibrating`: ringing
            about it while clenched, with ``alpha_min`` per solver step, relaxing monotonely
            with ``beta``); ``False``: it follows the activation as it is.
        pop_on: Layered mode without examples: where the muscles swell. ``"surface"``
            (default): the written meshes, by the paper's goal-driven skin over the physical
            normal skin (:mod:`warpskin.popping.surface`; one simulation, the guide free);
            ``"layers"``: the multi-layer model's rest shape (the skin's, or its cage's), the
            physical skin making the pop.
    """

    examples: PoppingExamples | None = None
    device: object = None
    frames: tuple[int, int] | None = None
    fps: float | None = None
    start_frame: int | None = None
    topology: str = "file"
    alpha_min: float | None = None
    beta: float | None = None
    dt: float | None = None
    progress: bool = True
    comment: str = ""
    mode: str | None = None
    beats: BeatSpec | None = None
    muscles: list[str] | None = None
    swell: float | None = None
    cage: object = "auto"
    report_dir: object = None
    normal_guide: bool = True
    vibrate: bool = True
    pop_on: str = "surface"


def run_popping(scene, out_path, options: PoppingOptions | None = None, **overrides) -> PoppingRun:
    """Play a popping scene and write it to USD (the ``warpskin pop`` command).

    Prims under ``/warpskin``: ``popping`` (the dynamic skin), ``normal`` (example-based
    normal mesh, no popping), ``goal`` (the activated clenched goal, a guide) and ``lbs``
    (plain linear blend skinning, a guide), side by side for review. Every frame advances the
    dynamics by ``substeps`` steps ending at the frame's time, with the activation sampled at
    each step; the pose is the frame's. In layered mode the file holds the physical skin and
    LBS, as ``warpskin simulate --lbs`` writes them. Without examples (a rig file, or a scene
    whose rig makes none) the mode is layered, with muscle groups found from the skeleton.

    Args:
        scene: A :class:`~warpskin.scene.Scene`, a shipped scene name or a TOML path.
        out_path: ``.usdc`` (default format), ``.usda`` or ``.usd``; written atomically.
        options: :class:`PoppingOptions` (each field's meaning is documented there).
        overrides: Any of its fields by name (``frames=(0, 26)``, ``beats=BeatSpec(bpm=120)``).

    Returns:
        A :class:`PoppingRun`.
    """
    o = with_overrides(PoppingOptions, options, overrides, "pop")
    scene = resolve_scene(scene)
    check_output_path(out_path, inputs=scene.input_paths())  # before any work
    if o.fps is not None:
        if not (math.isfinite(o.fps) and o.fps > 0):
            raise SceneError(f"fps must be a positive number, got {o.fps}")
        scene.fps = float(o.fps)
    settings = popping_settings(scene)
    where = str(scene.source or scene.name)
    for key in ("alpha_min", "beta", "dt"):
        if getattr(o, key) is not None:
            setattr(settings, key, getattr(o, key))
    if o.mode is not None:
        settings.mode = o.mode
    settings.check(where)
    if o.pop_on not in POP_ON:
        raise SceneError(f"pop_on must be one of {', '.join(POP_ON)}, got {o.pop_on!r}")
    examples = o.examples
    mapped = "examples" in (scene.extra.get("popping") or {})
    if examples is None and (mapped or not has_examples(scene)):
        examples = examples_from_file(scene)  # the file's blend shapes: mapped, or those named *clench* ...
    if settings.mode is None:
        settings.mode = "goal" if examples is not None or has_examples(scene) else "layered"
    if settings.mode == "layered":
        return _LayeredPop(scene, settings, o, examples).run(out_path)
    if o.muscles is not None and any("=" in str(m) for m in o.muscles):
        raise SceneError(f"{where}: goal mode pops the examples' groups ({'--groups'} takes their names); "
                         "NAME=JOINT_PATTERN groups need --mode layered")
    return _run_goal(scene, out_path, settings, o, examples)


def _run_goal(scene, out_path, settings: PoppingSettings, o: PoppingOptions, examples) -> PoppingRun:
    """The goal mode (:func:`run_popping`): example-based skinning and the goal-driven skin."""
    where = str(scene.source or scene.name)
    rig = scene.rig()
    clip = rig.clip(scene.clip)
    plan = FramePlan.for_scene(scene, o.frames, max_dt=settings.dt, start_frame=o.start_frame)
    if examples is None:
        examples = examples_for_scene(scene)
    deformer = PoseSpaceDeformer(rig, examples, device=o.device, joints=settings.joints, rbf_width=settings.rbf_width)
    if o.beats is not None:
        settings.activation = o.beats.timeline(deformer.group_names, float(plan.times[0]), float(plan.times[-1]))
    settings.activation.check_groups(deformer.group_names, f"{where}: [popping.activation]")
    dynamics = PoppingDynamics(deformer, alpha_min=settings.alpha_min, beta=settings.beta,
                               threshold=settings.threshold / file_unit(scene.solver_params().units, rig.vertices))
    h = plan.dt
    if settings.beta * h > 1.0 + 1e-12:
        raise SceneError(f"{where}: beta * dt = {settings.beta * h:.4g} must be <= 1; lower beta or dt")
    stepper = PoppingStepper(rig, clip, plan, deformer, dynamics, settings, name=scene.name)
    over = _Overshoot()
    output = CharacterOutput(rig, o.topology, clip)
    writer = UsdSkinWriter(out_path, fps=plan.fps, up_axis=rig.up_axis, comment=o.comment, root=output.root_name)
    record = FrameRunner(plan, stepper, writer=writer, measures=[over], progress=o.progress,
                         steps_in_first_frame=True, output=output).run()
    count = len(record.frames)
    summary = {
        "device": str(deformer.device),
        "vertices": rig.vertex_count,
        "groups": deformer.group_names,
        "substeps": plan.substeps,
        "dt_s": h,
        "alpha_min": settings.alpha_min,
        "beta": settings.beta,
        "peak_overshoot_m": over.peak_over,
        "max_goal_distance_m": over.max_goal,
        "ms_per_frame": float(np.sum(record.step_ms)) * plan.substeps / count,
    }
    if o.report_dir is not None:
        rep = _report(o.report_dir, writer.path, belly_of_examples(rig, examples), rig, o.topology, plan.fps, settings)
        summary["popping_report"], summary["beats"] = rep["dir"], rep["beats"]
    return PoppingRun(path=Path(writer.path), frames=count, summary=summary)


def _report(report_dir, path, bellies: dict, rig, topology: str, fps: float, settings,
            depth_mm: dict[str, float] | None = None) -> dict:
    """The popping report (:func:`~warpskin.popping.report.write_popping_report`) of a bake whose
    skin is ``rig``'s (``bellies``: per group a mask per welded skin vertex, or ``{prim name:
    mask per written point of that mesh}`` as written); returns its folder (``dir``) and each
    group's pops (``beats``: :func:`~warpskin.popping.report.beat_summary`)."""
    masks = {g: (m[rig.weld_map] if topology == "file" and not isinstance(m, dict) else m) for g, m in bellies.items()}
    tl = settings.activation
    data = write_popping_report(report_dir, path, masks, fps, lambda t, names: tl.sample(t, names),
                                onsets={g: tl.onsets(g) for g in masks}, depth_mm=depth_mm)
    return {"dir": str(report_dir), "beats": {g: row.get("beats", []) for g, row in data["groups"].items()}}


class _LayeredPop:
    """The layered mode (:func:`run_popping`): the activation drives the multi-layer model's rest
    shape (examples' muscles, or muscles found from the skeleton of what is simulated), or the
    written meshes' goal-driven offset (``pop_on="surface"``); one :func:`simulate` run, and
    with ``normal_guide`` (but on the surface) a second without the pop beside it."""

    def __init__(self, scene, settings: PoppingSettings, o: PoppingOptions, examples) -> None:
        if examples is None and has_examples(scene):
            examples = examples_for_scene(scene)
        self.scene, self.settings, self.o, self.examples = scene, settings, o, examples
        self.rig = scene.rig()
        self.clip = self.rig.clip(scene.clip)
        self.solver = _pop_solver_params(scene)
        self.plan = FramePlan.for_scene(scene, o.frames, max_dt=self.solver.dt, start_frame=o.start_frame)
        self.start, self.end = float(self.plan.times[0]), float(self.plan.times[-1])
        self.found: list = []  # the muscles found from the skeleton
        self.groups: list[str] = []
        self.surface = False
        self.surface_bellies: list = []  # per group, {written mesh: belly mask} (on the written surface)
        self.drive: list = []  # the rest drive's activation over clip time, once the groups are known
        self.made: list = []  # the surface pop, once made

    def timeline(self, names: list[str], respond: bool = True) -> None:
        """The groups ``names`` and their activation: the rest drive follows each group's
        activation as the paper's skin follows its goal, ringing about it while clenched
        (``alpha_min`` per solver step) and relaxing monotonely (``beta``); ``respond`` false
        (or ``vibrate`` off): as it is."""
        settings, plan = self.settings, self.plan
        self.groups[:] = names
        if self.o.beats is None and not settings.activation.groups:
            raise SceneError(f"{self.scene.source or self.scene.name}: popping without a timeline: pass --bpm N or "
                             f"--beats FILE (muscle groups found: {', '.join(names)})")
        if self.o.beats is not None:
            settings.activation = self.o.beats.timeline(names, self.start, self.end)
        settings.activation.check_groups(names, "[popping.activation]")

        def raw(t: float) -> np.ndarray:
            return settings.activation.sample(t, names)

        self.drive[:] = [vibrating(raw, self.start - 1.0 / plan.fps, self.end + plan.dt, h=plan.dt,
                                   alpha=settings.alpha_min, beta=settings.beta)
                         if self.o.vibrate and respond else raw]

    def activation(self, t: float) -> np.ndarray:
        return self.drive[0](t)

    def overlay(self, character, builder, frames_plan):
        """The surface pop (:func:`_surface_pop`) over what ``character`` writes."""
        unit = file_unit(self.scene.solver_params().units, character.soup.points)  # metres per file unit
        pop = _surface_pop(character, builder, frames_plan, self, unit=unit)
        pop.normal_guide = bool(self.o.normal_guide)
        self.made.append(pop)
        return pop

    def prepare(self, builder) -> None:
        """Muscles from the skeleton of what is simulated (the skin, or its cage) as its rest drive."""
        swell = DEFAULT_SWELL if self.o.swell is None else self.o.swell
        self.found[:], swelling = muscles_from_skeleton(builder, self.o.muscles, swell=swell)
        self.timeline([m.name for m in self.found])
        builder.set_rest_drive(rest_offset_deltas(builder, swelling), swelling=belly_of_swelling(builder, swelling))

    def run(self, out_path) -> PoppingRun:
        from .simulate import SimulationOptions, simulate

        o, examples = self.o, self.examples
        base = SimulationOptions(device=o.device, frames=o.frames, with_lbs=True, progress=o.progress,
                                 comment=o.comment, start_frame=o.start_frame, topology=o.topology,
                                 report_dir=o.report_dir)
        if examples is not None:
            if o.muscles is not None and any("=" in str(m) for m in o.muscles):
                raise SceneError("this scene's examples name its muscle groups: --groups takes their names "
                                 f"({', '.join(examples.group_names)})")
            builder = SkinModelBuilder(self.rig, self.scene.model_params())
            builder.set_rest_drive(muscle_rest_offset_deltas(builder, examples,
                                                             self.rig.skinning_matrices(self.clip, self.start)))
            self.timeline(list(examples.group_names))
            result = simulate(self.scene, out_path, base, solver_params=self.solver, builder=builder,
                              activation=self.activation)
        elif o.pop_on == "surface":  # on the written meshes
            self.surface = True
            result = simulate(self.scene, out_path, base, cage=o.cage, overlay=self.overlay)
        else:  # any rig: muscles from the skeleton of what is simulated (the skin, or its cage)
            result = simulate(self.scene, out_path, base, solver_params=self.solver, cage=o.cage,
                              prepare=self.prepare, activation=self.activation)
        if o.normal_guide and not self.surface:  # the same run without the pop, beside it (twice the cost)
            _add_normal_guide(self.scene, result.path, SimulationOptions(
                device=o.device, frames=o.frames, start_frame=o.start_frame, topology=o.topology, cage=o.cage,
                solver_params=self.solver, progress=o.progress, comment="normal-only guide"))
        return PoppingRun(path=result.path, frames=len(result.frames), summary=self.summary(result))

    def summary(self, result) -> dict:
        """The simulation's summary with the pop's: mode, groups, muscles found, the report."""
        o, found = self.o, self.found
        summary = dict(result.summary)
        summary["mode"] = "layered"
        summary["pop_on"] = "surface" if self.surface else "layers"
        if self.surface and self.made:  # the largest share of an offset the clearance to another surface took back
            summary["clearance_held"] = self.made[0].held
        summary["groups"] = self.groups
        summary["normal_guide"] = bool(o.normal_guide)
        if found:
            summary["muscles"] = [{"name": m.name, "joints": m.joints, "vertices": m.vertices,
                                   "depth_mm": 1e3 * m.depth_m, "peak_swell_mm": 1e3 * m.peak_m} for m in found]
        if o.report_dir is not None:
            render = self.scene.rig()
            rep = _report(o.report_dir, result.path, self._bellies(render), render, o.topology, self.scene.frame_rate,
                          self.settings, depth_mm={m.name: 1e3 * m.depth_m for m in found})
            summary["popping_report"], summary["beats"] = rep["dir"], rep["beats"]
        return summary

    def _bellies(self, render) -> dict:
        """Per group, its belly for the report: ``{prim name: mask per written point}`` on the
        surface, else a mask per skin vertex."""
        if not self.surface:
            return (belly_of_examples(render, self.examples) if self.examples is not None
                    else {m.name: belly_of_bones(render, m.joints) for m in self.found})
        skin_prim = CharacterOutput(render, self.o.topology).skin_prim
        weld = self.o.topology == "file"
        return {g: {(skin_prim if name == "skin" else valid_prim_name(name)):
                    (m[render.weld_map] if name == "skin" and weld else m)
                    for name, m in masks.items() if m.any()}
                for g, masks in zip(self.groups, self.surface_bellies)}


_SHOWN_POINTS = 3  # the fewest written positions on a belly that swell visibly for a group to pop
LEFT_OUT = "muscle groups left out"  # how the warning naming the groups too coarse to show starts


def surface_muscles(character, builder, muscles=None, swell: float | None = None, device=None):
    """The muscle groups of a character's written meshes and their rest-pose swellings, as
    ``warpskin pop`` (``--pop-on surface``) uses them: the groups of ``builder``'s model
    (:func:`~warpskin.popping.muscles.groups_of_model`, the skin's or its cage's) on the
    character's written points (:func:`~warpskin.popping.surface.surface_swelling`).

    A group shows on the written surface only where its belly (the middle of its bones,
    :func:`~warpskin.popping.surface.belly_of_groups`) has at least ``_SHOWN_POINTS`` written
    positions that swell by a quarter of its peak swelling share of the depth there (a coarse
    mesh, a box limb with points only at its joints, has none): groups found from the skeleton
    that do not are left out with a warning (a :class:`~warpskin.errors.SceneError` when none
    is left), and a group named in ``muscles`` that does not is an error.

    Returns ``(muscles, displacements [G, N, 3] [m], groups [(name, joints)], bones in the
    written points' space, mesh of every written point [N], bellies [G, N] bool)``."""
    import warnings

    from ..capture import welded_pieces
    from ..popping.surface import DEFAULT_SURFACE_SWELL, belly_of_groups, surface_swelling

    soup = character.soup
    chosen = groups_of_model(builder, muscles)  # builds the model
    bones = builder.layers.bones
    # the simulated skin's bones into the soup's space (its skinning at the rest pose)
    rest = builder.rig.skinning_matrices(Clip("rest"), 0.0)

    def moved(p):
        return np.einsum("jab,jb->ja", rest[:, :3, :3], p) + rest[:, :3, 3]

    stage = Bones(start=moved(bones.start), end=moved(bones.end), joint_names=list(bones.joint_names))
    mesh = character.mesh_of_point
    share = DEFAULT_SURFACE_SWELL if swell is None else swell
    found, swelling = surface_swelling(soup.points, soup.triangles, soup.dense_weights, stage,
                                       character.rig.skeleton.parents, chosen, swell=share,
                                       bone_fraction=builder.params.layers.bone, mesh_of_point=mesh, device=device)
    bellies = belly_of_groups(soup.points, soup.triangles, soup.dense_weights, stage, chosen)
    # a written position: one mesh's points at one place (seam and flat-shading copies)
    position = welded_pieces(soup.points, soup.triangles,
                             np.zeros(len(soup.points), dtype=np.int64) if mesh is None else mesh)[1]
    shown = []
    for g, m in enumerate(found):
        swells = bellies[g] & (np.linalg.norm(swelling[g], axis=1) >= 0.25 * share * m.depth_m)
        shown.append(m.depth_m > 0.0 and np.unique(position[swells]).size >= _SHOWN_POINTS)
    hidden = [m.name for m, ok in zip(found, shown) if not ok]
    if hidden and muscles is not None:
        raise SceneError(f"--groups: {', '.join(hidden)}: fewer than {_SHOWN_POINTS} written points over the middle of "
                         "the bone swell by a quarter of the peak (the mesh is too coarse there to show a belly)")
    if hidden:
        if len(hidden) == len(found):
            raise SceneError(f"no muscle group found from the skeleton shows on the written meshes: none has "
                             f"{_SHOWN_POINTS} written points over the middle of its bone that swell by a quarter of the "
                             f"peak ({', '.join(hidden)}); the meshes are too coarse to show a belly: subdivide them")
        warnings.warn(f"{LEFT_OUT}, too coarse to show a belly on the written meshes (fewer than "
                      f"{_SHOWN_POINTS} written points over the middle of the bone swell by a quarter of the peak): "
                      f"{', '.join(hidden)}", RigWarning, stacklevel=2)
        keep = np.array(shown)
        found = [m for m, ok in zip(found, shown) if ok]
        chosen = [c for c, ok in zip(chosen, shown) if ok]
        swelling, bellies = swelling[keep], bellies[keep]
    return found, swelling, chosen, stage, mesh, bellies



def _surface_pop(character, builder, plan, run: _LayeredPop, unit: float = 1.0):
    """The written meshes' muscles (:func:`surface_muscles`, with ``run``'s muscles, swell and
    device) and their goal-driven offset (:class:`~warpskin.popping.surface.SurfacePop`),
    stepped with the solver's steps of ``plan``; fills ``run.found`` and ``run.surface_bellies``
    (per group, ``{written mesh: belly mask per point}``) and sets its activation
    (:meth:`_LayeredPop.timeline`). ``unit``: metres per file unit (the snap distance
    ``settings.threshold`` is in metres)."""
    from ..popping.surface import SurfacePop, seam_points

    soup, rig, settings, o = character.soup, character.rig, run.settings, run.o
    run.found[:], swelling, chosen, stage, mesh, belly = surface_muscles(character, builder, o.muscles, o.swell,
                                                                         o.device)
    names = [m.name for m in run.found]
    run.surface_bellies[:] = [character.split(mask) for mask in belly]
    run.timeline(names, respond=False)  # the points themselves vibrate
    diagonal = character.rig.size()
    return SurfacePop(swelling, soup.dense_weights, rig.skinning_matrices(Clip("rest"), 0.0), plan.substep_times(),
                      lambda t: settings.activation.sample(t, names), h=plan.dt,
                      alpha_min=settings.alpha_min if o.vibrate else 1.0, beta=settings.beta,
                      threshold=settings.threshold / unit, triangles=soup.triangles, margin=_CLEAR * diagonal,
                      start=1e-5 * diagonal, points=soup.points,
                      seams=seam_points(soup.points, soup.triangles, mesh), mesh_of_point=mesh, device=o.device)


def _pop_solver_params(scene):
    """The scene's solver settings for a layered pop and its normal-only guide: the volume
    constraints along the normals (``volume_along_normals``) unless the scene sets it."""
    from dataclasses import replace

    params = scene.solver_params()
    if "volume_along_normals" not in scene.extra.get("solver", {}):
        params = replace(params, volume_along_normals=True)
    return params


def _add_normal_guide(scene, path, options) -> None:
    """Simulate ``scene`` without the pop with ``options`` (:class:`~warpskin.run.SimulationOptions`:
    the same frames, cage, topology and solver settings as the bake) and add its skin to the bake
    at ``path`` as the guide ``<skin>_normal`` (``warpskin:role`` ``normal``); the file is
    replaced atomically."""
    import os
    import tempfile

    from pxr import Usd, UsdGeom, Vt

    from .simulate import simulate

    out = Path(path)
    with tempfile.TemporaryDirectory(prefix="warpskin-normal-") as tmp:
        normal = Path(tmp) / "normal.usdc"
        simulate(scene, normal, options)
        src, dst = Usd.Stage.Open(str(normal)), Usd.Stage.Open(str(out))

        def skin(stage):
            return next(UsdGeom.Mesh(c) for c in stage.GetDefaultPrim().GetChildren()
                        if c.GetCustomDataByKey("warpskin:role") == "skin")

        a, b = skin(src), skin(dst)
        guide = UsdGeom.Mesh.Define(dst, b.GetPath().GetParentPath().AppendChild(b.GetPrim().GetName() + "_normal"))
        for name in ("faceVertexCounts", "faceVertexIndices", "orientation", "subdivisionScheme"):
            value = b.GetPrim().GetAttribute(name).Get()
            if value is not None:
                guide.GetPrim().GetAttribute(name).Set(value)
        for tc in a.GetPointsAttr().GetTimeSamples():
            guide.GetPointsAttr().Set(a.GetPointsAttr().Get(tc), tc)
        guide.CreatePurposeAttr(UsdGeom.Tokens.guide)
        guide.CreateDisplayColorAttr(Vt.Vec3fArray([(0.55, 0.75, 0.55)]))
        guide.GetPrim().SetCustomDataByKey("warpskin:role", "normal")
        staged = out.with_name(f".{out.stem}.normal{out.suffix}")
        try:
            dst.GetRootLayer().Export(str(staged))
            os.replace(staged, out)
        finally:
            staged.unlink(missing_ok=True)


def pop(rig_or_scene, out_path, *, clip: str | None = None, **options) -> PoppingRun:
    """``warpskin pop`` in Python: a rig file (``.glb``, ``.gltf``, ``.usd*``), a shipped scene
    name, a TOML scene path or a :class:`~warpskin.scene.Scene`, played to ``out_path``;
    ``clip`` picks the rig file's animation; every other option as :func:`run_popping` takes
    it (``beats=BeatSpec(bpm=120)``, ``muscles=["biceps_l=*upperarm*l*"]``, ``cage``, ...)."""
    scene = resolve_scene(rig_or_scene)
    if clip is not None:
        scene.clip = clip
    return run_popping(scene, out_path, **options)

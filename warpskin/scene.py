"""Scenes: a rig (file, shipped asset or procedural generator), its clip, frame rate and frame
range, in a TOML file.

A shipped scene is named by its file stem (``warpskin skin arm``); any other TOML file is named
by its path. Example::

    [scene]
    description = "Elbow flexed to 150 degrees and back"

    [rig]
    generator = "arm"          # or: file = "character.glb" (relative to this TOML file)
    # weights = "bone_heat"    # automatic weights (Baran & Popovic 2007) instead of the file's
                               # or: asset = "CesiumMan/CesiumMan.glb" (in the assets folder)
    # mesh = "Body"            # which skinned mesh, when the file has several
    # unit_scale = 0.01        # for files authored in centimetres

    [rig.params]               # generator parameters (see warpskin.scenes.<generator>)
    flex_degrees = 150

    [animation]
    clip = "flex"
    fps = 30
    frames = [0, 135]          # inclusive; default: the whole clip

Unknown sections or keys are errors (a typo must not be silently ignored).
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from .errors import SceneError
from .rig import Rig, RigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Scene", "SceneError", "load_scene", "resolve_scene", "is_rig_file", "list_scenes", "find_assets_dir",
           "GENERATORS"]


#: Output frame rate where neither the scene nor the clip gives one [frames/s].
DEFAULT_FPS = 30.0

#: Name of the clip made from a scene's ``[animation.keys]``.
SCENE_CLIP = "scene"

#: Seconds of pre-roll from the bind pose for a rig from a file (a procedural rig starts at rest
#: in its first pose): the first frame's LBS pose often passes the skin through itself.
FILE_RIG_PREROLL = 0.5

GENERATORS = {
    "arm": "warpskin.scenes.arm:make_arm",
    "popping_arm": "warpskin.scenes.popping_arm:make_popping_arm",
    "mannequin": "warpskin.scenes.mannequin:make_mannequin",
}

_SCHEMA: dict[str, set[str]] = {
    "scene": {"name", "description"},
    "rig": {"generator", "file", "asset", "mesh", "unit_scale", "params", "weights", "parents"},
    "animation": {"clip", "fps", "frames", "preroll", "keys", "interpolation"},
    # the multi-layer model (Deul & Bender 2013, Table 1 columns and the preprocessing)
    "layers": {"fat", "muscle", "bone", "adaptive", "stiffness", "density", "omega", "coupling_stiffness", "per_bone",
               "refine", "max_edge"},
    "joints": {"radius_factor", "layers", "joints"},
    "subvolumes": {"enabled", "planes"},
    # Algorithm 1 settings
    "solver": {"iterations", "volume_iterations", "rotation_iterations", "dt", "gravity", "damping",
               "fast_summation", "volume_along_normals", "volume_stiffness", "tether", "tether_floor", "tether_max", "max_offset",
               "max_volume_error", "max_speed", "max_strained", "max_flipped", "max_capped"},
    # skin self-collision (section 4.5): its keys are CollisionParams' declared settings
    "collision": None,
    # what is written: the physics weight (0 LBS, 1 physical) by joint-name pattern
    "physics": {"weights"},
    # what is written: the surface guard (warpskin.guard): GuardParams' declared settings
    "guard": None,
    # popping dance (Son & Han 2007), read by warpskin.popping.popping_settings
    "popping": {"mode", "alpha_min", "beta", "threshold", "dt", "rbf_width", "joints", "activation", "examples"},
}


def find_assets_dir() -> Path | None:
    """The third-party assets folder: ``$WARPSKIN_ASSETS``, else ``shared/assets`` next to the
    current folder or next to the source checkout; ``None`` when absent."""
    env = os.environ.get("WARPSKIN_ASSETS")
    candidates = [Path(env)] if env else []
    here = Path.cwd()
    candidates += [here / "shared" / "assets", here.parent / "shared" / "assets"]
    candidates.append(Path(__file__).resolve().parents[2] / "shared" / "assets")
    for c in candidates:
        if c.is_dir():
            return c
    return None


@dataclass
class Scene:
    """A rig plus what to play of it.

    Attributes:
        name: Scene name (file stem).
        source: The TOML file (or the rig file for a bare rig).
        rig_spec: The ``[rig]`` table.
        clip: Clip name (``None``: the rig's first clip).
        fps: Frames per second of the output; ``None``: the clip's own rate (a USD stage's
            timeCodesPerSecond, a glTF clip's key spacing), else 30 (see :attr:`frame_rate`).
        frames: Inclusive frame range ``(first, last)`` or ``None`` for the whole clip. Frame
            ``f`` is at clip time ``f / frame_rate`` seconds: the source's own time codes, so a
            bake lines up with its source (CesiumMan's walk is frames 1-48 at 24 fps).
        preroll: Seconds of simulation before the first frame, moving from the bind pose into
            the first frame's pose (0: start at the first frame's LBS pose).
        description: Free text.
        extra: Sections for later stages (layers, solver), kept verbatim.
    """

    name: str
    source: Path | None
    rig_spec: dict
    clip: str | None = None
    fps: float | None = None
    frames: tuple[int, int] | None = None
    preroll: float = 0.0
    description: str = ""
    extra: dict = field(default_factory=dict)
    _rig: Rig | None = None

    @classmethod
    def from_rig_file(
        cls, path: str | Path, *, clip: str | None = None, fps: float | None = None, mesh: str | None = None,
        unit_scale: float | None = None,
    ) -> Scene:
        """A scene that plays a rig file as it is."""
        p = Path(path)
        spec = {"file": str(p.resolve())}
        if mesh:
            spec["mesh"] = mesh
        if unit_scale:
            spec["unit_scale"] = unit_scale
        return cls(name=p.stem, source=p, rig_spec=spec, clip=clip, fps=float(fps) if fps else None, preroll=FILE_RIG_PREROLL)

    def rig(self) -> Rig:
        """Load (once) and return the rig."""
        if self._rig is None:
            self._rig = _build_rig(self)
        return self._rig

    @property
    def frame_rate(self) -> float:
        """Frames per second of the output: :attr:`fps` if set, else the clip's own rate, else
        :data:`DEFAULT_FPS`."""
        if self.fps is not None:
            return float(self.fps)
        rate = self.rig().clip(self.clip).rate
        return float(rate) if rate else DEFAULT_FPS

    def clip_frames(self) -> tuple[int, int]:
        """The frames the clip spans at :attr:`frame_rate`: the first at or after its first
        key, the last at or before its last key."""
        clip = self.rig().clip(self.clip)
        r = self.frame_rate
        eps = 1e-3  # frames: key times are often float32 (RiggedSimple's last key is 49.99999 frames)
        first = int(math.ceil(clip.start * r - eps))
        return first, max(first, int(math.floor(clip.end * r + eps)))

    def frame_range(self) -> tuple[int, int]:
        """Inclusive frame range to play (the scene's, else the whole clip)."""
        return self.frames if self.frames is not None else self.clip_frames()

    def check_frames(self, first: int, last: int) -> None:
        """Raise :class:`SceneError` unless ``first:last`` lies inside the clip; a clip of one
        pose (a rig without animation: its rest pose) holds it over any frames from 0."""
        lo, hi = self.clip_frames()
        clip = self.rig().clip(self.clip)
        if clip.end <= clip.start and first >= 0:
            return
        if first < lo or last > hi:
            raise SceneError(
                f"frames {first}:{last} are outside clip {clip.name!r}, which spans frames {lo}:{hi} at "
                f"{self.frame_rate:g} fps ({clip.start:.4g}-{clip.end:.4g} s)"
            )

    def model_params(self):
        """The :class:`~warpskin.model.ModelParams` of the ``[layers]``, ``[joints]``,
        ``[subvolumes]`` and ``[collision]`` sections (defaults: the paper's Arm values)."""
        params = _model_params(self.extra, _where(self.source))
        params.collision = self.collision_params()
        return params

    def solver_params(self):
        """The :class:`~warpskin.solver.SolverParams` of the ``[solver]`` section."""
        from .solver import SolverParams

        table = dict(self.extra.get("solver", {}))
        where = _where(self.source)
        for key in ("iterations", "volume_iterations", "rotation_iterations"):
            if key in table and (isinstance(table[key], bool) or not isinstance(table[key], int)):
                raise SceneError(f"{where}: [solver] {key} must be an integer, got {table[key]!r}")
        for key in ("dt", "damping", "volume_stiffness", "tether", "tether_floor", "tether_max", "max_offset",
                    "max_volume_error", "max_speed", "max_strained", "max_flipped", "max_capped"):
            if key in table and (isinstance(table[key], bool) or not isinstance(table[key], (int, float))):
                raise SceneError(f"{where}: [solver] {key} must be a number, got {table[key]!r}")
        for key in ("fast_summation", "volume_along_normals"):
            if key in table and not isinstance(table[key], bool):
                raise SceneError(f"{where}: [solver] {key} must be true or false")
        if "gravity" in table:
            table["gravity"] = _numbers(where, "[solver] gravity", table["gravity"], 3)
        params = SolverParams(**table)
        params.check(where)
        return params

    def collision_params(self):
        """The :class:`~warpskin.collision.CollisionParams` of the ``[collision]`` section
        (self-collision is on by default)."""
        from .collision import CollisionParams
        from .settings import from_section

        return from_section(CollisionParams, dict(self.extra.get("collision", {})), _where(self.source), "collision")

    def guard_params(self):
        """The :class:`~warpskin.guard.GuardParams` of the ``[guard]`` section (the surface guard
        of the written meshes; on by default)."""
        from .guard import GuardParams
        from .settings import from_section

        return from_section(GuardParams, dict(self.extra.get("guard", {})), _where(self.source), "guard")

    def physics_weights(self) -> dict[str, float]:
        """``[physics.weights]``: joint-name patterns (shell-style, case-insensitive: ``"*hand*"``)
        and the physics weight in [0, 1] of the skin their joints drive
        (:class:`~warpskin.character.Character`), in the file's order."""
        table = self.extra.get("physics", {}).get("weights", {})
        where = _where(self.source)
        if not isinstance(table, dict):
            raise SceneError(f"{where}: [physics.weights] must be a table of joint-name patterns and weights")
        for key, value in table.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0.0 <= value <= 1.0):
                raise SceneError(f"{where}: [physics.weights] {key!r} must be a weight in [0, 1] (0: LBS, 1: physical), "
                                 f"got {value!r}")
        return {str(k): float(v) for k, v in table.items()}

    def rig_file(self) -> Path | None:
        """The rig file this scene reads: ``[rig] file`` (relative to the scene's TOML) or the
        shared ``asset``; ``None`` for a generated rig or an asset without an assets folder."""
        spec = self.rig_spec
        if "file" in spec:
            path = Path(spec["file"])
            if not path.is_absolute() and self.source is not None and self.source.suffix == ".toml":
                path = self.source.parent / path
            return path
        if "asset" in spec:
            assets = find_assets_dir()
            if assets is not None:
                return assets / spec["asset"]
        return None

    def input_paths(self) -> list[Path]:
        """The files this scene reads: its TOML (or rig) file and the rig file it names."""
        out = [self.source] if self.source is not None else []
        path = self.rig_file()
        return out + ([path] if path is not None else [])

    def frame_time(self, frame: int) -> float:
        """Clip time [s] of a frame: ``frame / frame_rate``."""
        return frame / self.frame_rate


def _where(scene_path: Path | None) -> str:
    return str(scene_path) if scene_path else "scene"


def _build_rig(scene: Scene) -> Rig:
    rig = _load_rig_of(scene)
    where = _where(scene.source)
    parents = scene.rig_spec.get("parents")
    if parents is not None:
        if not isinstance(parents, dict) or not all(isinstance(v, str) for v in parents.values()):
            raise SceneError(f"{where}: [rig] parents must be a table of joint = \"parent joint\" (\"\" for a root)")
        try:
            rig = rig.reparented(parents, where=where)
        except RigError as exc:
            raise SceneError(f"{where}: [rig] parents: {exc}") from None
    keys = scene.extra.get("keys")
    if keys:
        try:
            rig = rig.with_keys(SCENE_CLIP, keys, interpolation=scene.extra.get("interpolation", "LINEAR"), where=where)
        except RigError as exc:
            raise SceneError(f"{where}: [animation.keys] {exc}") from None
    weights = scene.rig_spec.get("weights", "file")
    if weights == "bone_heat":
        from .preprocess.bone_heat import with_bone_heat_weights

        rig = with_bone_heat_weights(rig)
    elif weights != "file":
        raise SceneError(f"{_where(scene.source)}: [rig] weights must be 'file' or 'bone_heat', got {weights!r}")
    return rig


def _load_rig_of(scene: Scene) -> Rig:
    spec = scene.rig_spec
    where = _where(scene.source)
    given = [k for k in ("generator", "file", "asset") if k in spec]
    if len(given) != 1:
        raise SceneError(f"{where}: [rig] needs exactly one of 'generator', 'file' or 'asset' (got {given or 'none'})")
    unit_scale = spec.get("unit_scale")
    if "generator" in spec:
        gen = spec["generator"]
        if gen not in GENERATORS:
            raise SceneError(f"{where}: unknown generator {gen!r}; known: {sorted(GENERATORS)}")
        module, func = GENERATORS[gen].split(":")
        import importlib

        make = getattr(importlib.import_module(module), func)
        params = spec.get("params", {})
        if not isinstance(params, dict):
            raise SceneError(f"{where}: [rig.params] must be a table")
        try:
            rig = make(**params)
        except (RigError, SceneError) as exc:
            raise SceneError(f"{where}: {exc}") from None
        return rig.rescaled(unit_scale) if unit_scale else rig
    if "params" in spec:
        raise SceneError(f"{where}: [rig.params] only applies to a generator")
    from .io import load_rig

    if "file" in spec:
        path = Path(spec["file"])
        if not path.is_absolute() and scene.source is not None:
            path = scene.source.parent / path
    else:
        assets = find_assets_dir()
        if assets is None:
            raise SceneError(
                f"{where}: the rig is the shared asset {spec['asset']!r}, but no assets folder was found; "
                "set WARPSKIN_ASSETS to the folder that holds it"
            )
        path = assets / spec["asset"]
    return load_rig(path, mesh=spec.get("mesh"), unit_scale=unit_scale)


def _section_keys(section: str) -> set[str]:
    """The keys a scene's ``[section]`` may hold: the declared settings of its parameter class
    (:mod:`warpskin.settings`) where it has one, else the schema's list."""
    declared = _declared_sections()
    if section in declared:
        from .settings import settings_of

        return {s.name for s in settings_of(declared[section])}
    return _SCHEMA[section]


def _declared_sections() -> dict:
    """``{section: parameter class}`` of the scene sections made from declared settings."""
    from .collision import CollisionParams
    from .guard import GuardParams

    return {"collision": CollisionParams, "guard": GuardParams}


def _scenes_dir():
    return resources.files("warpskin.scenes")


def list_scenes() -> list[dict]:
    """Shipped scenes: name, description, rig kind."""
    out = []
    for entry in sorted(_scenes_dir().iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text())
            rig = data.get("rig", {})
            kind = next((f"{k}: {rig[k]}" for k in ("generator", "asset", "file") if k in rig), "?")
            out.append(
                {"name": entry.name[:-5], "description": data.get("scene", {}).get("description", ""), "rig": kind}
            )
    return out


def _positive(where: str, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise SceneError(f"{where}: {key} must be a positive number, got {value!r}")
    return float(value)


def is_rig_file(target: str | Path) -> bool:
    """Is ``target`` a rig file (glTF or USD, by its extension) rather than a scene?"""
    from .io import RIG_EXTENSIONS

    return str(target).lower().endswith(RIG_EXTENSIONS)


def resolve_scene(target: Scene | str | Path) -> Scene:
    """A :class:`Scene` as it is; a rig file played as it is; otherwise a scene name or TOML path."""
    if isinstance(target, Scene):
        return target
    return Scene.from_rig_file(target) if is_rig_file(target) else load_scene(target)


def load_scene(name_or_path: str | Path) -> Scene:
    """Load a shipped scene by name, or a TOML scene file by path.

    Raises:
        SceneError: unknown scene name (listing the shipped ones), unreadable TOML, unknown
            sections or keys, or values of the wrong kind.
    """
    text_path: Path | None = None
    candidate = Path(name_or_path)
    if is_rig_file(candidate):
        raise SceneError(f"{candidate}: a rig file, not a scene: use resolve_scene() or Scene.from_rig_file() for it")
    if candidate.suffix.lower() == ".toml" or candidate.exists():
        if not candidate.is_file():
            raise SceneError(f"{candidate}: no such scene file")
        text_path = candidate.resolve()
        try:
            text = candidate.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            raise SceneError(f"{candidate}: not a TOML scene file (not UTF-8 text)") from None
        name = candidate.stem
    else:
        name = str(name_or_path)
        entry = _scenes_dir() / f"{name}.toml"
        if not entry.is_file():
            known = ", ".join(s["name"] for s in list_scenes())
            raise SceneError(f"unknown scene {name!r}; shipped scenes: {known} (or give a path to a .toml file)")
        text = entry.read_text()
        text_path = Path(str(entry))
    where = _where(text_path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{where}: not valid TOML: {exc}") from None

    extra = {k: data[k] for k in ("layers", "joints", "subvolumes", "solver", "collision", "physics", "guard", "popping")
             if k in data}
    for section, table in data.items():
        if section not in _SCHEMA:
            raise SceneError(f"{where}: unknown section [{section}]; known: {sorted(_SCHEMA)}")
        if not isinstance(table, dict):
            raise SceneError(f"{where}: {section} must be a table")
        keys = _section_keys(section)
        unknown = sorted(set(table) - keys)
        if unknown:
            raise SceneError(f"{where}: unknown key(s) {unknown} in [{section}]; known: {sorted(keys)}")
    meta = data.get("scene", {})
    anim = data.get("animation", {})
    if "rig" not in data:
        raise SceneError(f"{where}: missing [rig] section")
    fps = _positive(where, "[animation] fps", anim["fps"]) if "fps" in anim else None
    frames = anim.get("frames")
    if frames is not None:
        if (
            not isinstance(frames, list)
            or len(frames) != 2
            or not all(isinstance(f, int) and not isinstance(f, bool) for f in frames)
            or frames[0] < 0
            or frames[1] < frames[0]
        ):
            raise SceneError(f"{where}: [animation] frames must be [first, last] integers with 0 <= first <= last, got {frames!r}")
        frames = (frames[0], frames[1])
    clip = anim.get("clip")
    if clip is not None and not isinstance(clip, str):
        raise SceneError(f"{where}: [animation] clip must be a string")
    keys = anim.get("keys")
    if keys is not None:
        if not isinstance(keys, dict) or not all(isinstance(v, dict) and set(v) == {"rotation"} for v in keys.values()):
            raise SceneError(f"{where}: [animation.keys.JOINT] takes rotation = [[t, x_deg, y_deg, z_deg], ...]")
        extra["keys"] = {j: v["rotation"] for j, v in keys.items()}
        extra["interpolation"] = anim.get("interpolation", "LINEAR")
        clip = clip or SCENE_CLIP
    elif "interpolation" in anim:
        raise SceneError(f"{where}: [animation] interpolation applies to [animation.keys] only")
    is_file_rig = "file" in data["rig"] or "asset" in data["rig"]
    preroll = anim.get("preroll", FILE_RIG_PREROLL if is_file_rig else 0.0)
    if isinstance(preroll, bool) or not isinstance(preroll, (int, float)) or not math.isfinite(preroll) or preroll < 0:
        raise SceneError(f"{where}: [animation] preroll must be a number of seconds >= 0, got {preroll!r}")
    return Scene(
        name=str(meta.get("name", name)),
        source=text_path,
        rig_spec=dict(data["rig"]),
        clip=clip,
        fps=fps,
        frames=frames,
        preroll=float(preroll),
        description=str(meta.get("description", "")),
        extra=extra,
    )


def _numbers(where: str, key: str, value, count: int) -> tuple[float, ...]:
    if (
        not isinstance(value, list)
        or len(value) != count
        or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)
    ):
        raise SceneError(f"{where}: {key} must be a list of {count} numbers, got {value!r}")
    return tuple(float(x) for x in value)


def _model_params(extra: dict, where: str):
    from .preprocess.joint_constraints import JointParams
    from .preprocess.layers import LayerParams
    from .model import ModelParams

    lay = extra.get("layers", {})
    defaults = LayerParams()
    per_bone_proj, per_bone_stiff = {}, {}
    for bone, table in lay.get("per_bone", {}).items():
        if not isinstance(table, dict) or set(table) - {"projection", "stiffness"}:
            raise SceneError(f"{where}: [layers.per_bone.{bone}] takes 'projection' and/or 'stiffness'")
        if "projection" in table:
            per_bone_proj[bone] = _numbers(where, f"[layers.per_bone.{bone}] projection", table["projection"], 3)
        if "stiffness" in table:
            per_bone_stiff[bone] = _numbers(where, f"[layers.per_bone.{bone}] stiffness", table["stiffness"], 4)
    for key in ("fat", "muscle", "bone", "density", "coupling_stiffness"):
        if key in lay and (isinstance(lay[key], bool) or not isinstance(lay[key], (int, float))):
            raise SceneError(f"{where}: [layers] {key} must be a number, got {lay[key]!r}")
    omega = lay.get("omega", 1)
    if isinstance(omega, bool) or not isinstance(omega, int):
        raise SceneError(f"{where}: [layers] omega must be an integer, got {omega!r}")
    adaptive = lay.get("adaptive", defaults.adaptive)
    if not isinstance(adaptive, bool):
        raise SceneError(f"{where}: [layers] adaptive must be true or false, got {adaptive!r}")
    layer_params = LayerParams(
        fat=float(lay.get("fat", defaults.fat)),
        muscle=float(lay.get("muscle", defaults.muscle)),
        bone=float(lay.get("bone", defaults.bone)),
        per_bone=per_bone_proj,
        adaptive=adaptive,
    )
    jt = extra.get("joints", {})
    jp = JointParams()
    joint_params = JointParams(
        radius_factor=float(jt.get("radius_factor", jp.radius_factor)),
        layers=tuple(jt.get("layers", jp.layers)),
        joints=list(jt["joints"]) if "joints" in jt else None,
    )
    sv = extra.get("subvolumes", {})
    sub_params = None
    if "planes" in sv:
        from .preprocess.sub_volumes import SubVolumeParams

        planes = {}
        for joint, value in sv["planes"].items():
            if value is False or value == "off":
                planes[joint] = None
            elif isinstance(value, (int, float)) and not isinstance(value, bool):
                planes[joint] = float(value)
            else:
                raise SceneError(f"{where}: [subvolumes] planes.{joint} must be a number in [0, 1] or false, got {value!r}")
        sub_params = SubVolumeParams(planes=planes)
    refine = lay.get("refine", True)
    if not isinstance(refine, bool):
        raise SceneError(f"{where}: [layers] refine must be true or false, got {refine!r}")
    max_edge = lay.get("max_edge")
    if max_edge is not None and (isinstance(max_edge, bool) or not isinstance(max_edge, (int, float))):
        raise SceneError(f"{where}: [layers] max_edge must be a length [m], got {max_edge!r}")
    enabled = sv.get("enabled", True)
    if not isinstance(enabled, bool):
        raise SceneError(f"{where}: [subvolumes] enabled must be true or false")
    params = ModelParams(
        layers=layer_params,
        stiffness=_numbers(where, "[layers] stiffness", lay["stiffness"], 4) if "stiffness" in lay else ModelParams().stiffness,
        stiffness_per_bone=per_bone_stiff,
        density=float(lay.get("density", 1000.0)),
        omega=omega,
        coupling_stiffness=float(lay.get("coupling_stiffness", 1.0)),
        joints=joint_params,
        subvolumes=sub_params,
        volume=enabled,
        refine=refine,
        max_edge=None if max_edge is None else float(max_edge),
    )
    params.check(where)
    return params

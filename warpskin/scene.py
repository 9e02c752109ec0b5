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
from .io import RIG_EXTENSIONS, load_rig
from .params import CollisionParams, PoppingSettings
from .rig import Rig, RigError
from .settings import check_value, from_section, read_section, setting, setting_named, settings_of

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["Scene", "SceneError", "load_scene", "resolve_scene", "is_rig_file", "list_scenes", "find_assets_dir",
           "GENERATORS", "SceneInfo", "RigSpec", "AnimationSpec", "PhysicsSettings", "scene_sections"]


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
    "dancer": "warpskin.scenes.dancer:make_dancer",
}

def _frames_arg(text: str) -> tuple[int, int]:
    """``--frames FIRST:LAST`` (inclusive integers, ``0 <= FIRST <= LAST``)."""
    import argparse

    try:
        a, b = text.split(":")
        first, last = int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames must be FIRST:LAST (inclusive integers), got {text!r}") from None
    if first < 0 or last < first:
        raise argparse.ArgumentTypeError(f"--frames {text}: need 0 <= FIRST <= LAST")
    return first, last


@dataclass
class SceneInfo:
    """A scene's ``[scene]`` section (declared settings, :mod:`warpskin.settings`)."""

    _section = "scene"

    name: str | None = setting(None, "string", "the scene's name (default: the file's stem)", optional=True)
    description: str = setting("", "string", "free text, listed by warpskin scenes")


@dataclass
class RigSpec:
    """A scene's ``[rig]`` section: which rig, and how it is read."""

    _section = "rig"

    generator: str | None = setting(None, "string", "a procedural rig: " + ", ".join(sorted(GENERATORS)),
                                    optional=True)
    file: str | None = setting(None, "string", "a rig file (.glb, .gltf, .usd, .usda, .usdc, .usdz), relative to "
                               "the scene file", optional=True)
    asset: str | None = setting(None, "string", "a rig file in the shared assets folder ($WARPSKIN_ASSETS)",
                                optional=True)
    mesh: str | None = setting(None, "string", "the skinned mesh to use when the file has several (default: the "
                               "largest)", optional=True, cli="--mesh")
    unit_scale: float | None = setting(None, "number", "multiply lengths by this (0.01 for a file in centimetres)",
                                       low=0.0, open_low=True, optional=True, must="a positive number",
                                       cli="--unit-scale")
    params: dict = setting({}, "table", "a generator's parameters (see its module, warpskin.scenes.GENERATOR)")
    weights: str = setting("file", "string", "skin weights: the file's or bone heat (Baran & Popovic 2007)",
                           choices=("file", "bone_heat"), cli="--weights")
    parents: dict = setting({}, "table", "joint = \"parent joint\" (\"\" for a root): a hierarchy for a file whose "
                            "joints are all roots")


@dataclass
class AnimationSpec:
    """A scene's ``[animation]`` section: what to play of the rig, and at which rate."""

    _section = "animation"

    clip: str | None = setting(None, "string", "clip name (default: the first)", optional=True, cli="--clip")
    fps: float | None = setting(None, "number", "output frame rate, resampling the clip (default: the source's: a "
                                "USD stage's timeCodesPerSecond, a glTF clip's key spacing, else 30)", unit="frames/s",
                                low=0.0, open_low=True, optional=True, must="a positive number", cli="--fps")
    frames: list | None = setting(None, "integers", "inclusive frame range, the source's time codes (frame f is at f "
                                  "/ fps s; default: the whole clip)", length=2, optional=True,
                                  valid=lambda v: 0 <= v[0] <= v[1],
                                  must="[first, last] integers with 0 <= first <= last", cli="--frames",
                                  metavar="FIRST:LAST", parse=_frames_arg)
    preroll: float | None = setting(None, "number", "simulated from the bind pose into the first frame's pose before "
                                    "writing (default: 0.5 for a rig file, 0 for a generator)", unit="s", low=0.0,
                                    optional=True, must="a number of seconds >= 0", cli="--preroll", metavar="SECONDS")
    keys: dict = setting({}, "table", "keys authored here for a rig without clips (clip \"scene\"): "
                         "[animation.keys.JOINT] rotation = [[t, x, y, z], ...] (s, degrees about the joint's axes)")
    interpolation: str = setting("LINEAR", "string", "interpolation of [animation.keys]", choices=("LINEAR", "STEP"))


@dataclass
class PhysicsSettings:
    """A scene's ``[physics]`` section: what is written, per joint."""

    _section = "physics"

    weights: dict = setting({}, "table", "joint-name pattern (shell-style, case-insensitive) = physics weight of the "
                            "skin its joints drive, in [0, 1] (0: LBS, 1: physical)")


def scene_sections() -> dict[str, list]:
    """``{section: [Setting, ...]}``: every section a scene file may hold and its declared keys
    (:mod:`warpskin.settings`), in the order of the docs' reference."""
    from .guard import GuardParams
    from .model import ModelParams
    from .params import CollisionParams, PoppingSettings, RunLimits, SolverParams
    from .preprocess.joint_constraints import JointParams
    from .preprocess.layers import LayerParams
    from .preprocess.sub_volumes import SubVolumeParams

    return {
        "scene": settings_of(SceneInfo),
        "rig": settings_of(RigSpec),
        "animation": settings_of(AnimationSpec),
        "layers": settings_of(LayerParams) + settings_of(ModelParams, "layers"),
        "joints": settings_of(JointParams),
        "subvolumes": settings_of(ModelParams, "subvolumes") + settings_of(SubVolumeParams),
        "solver": settings_of(SolverParams) + settings_of(RunLimits),
        "collision": settings_of(CollisionParams),
        "physics": settings_of(PhysicsSettings),
        "guard": settings_of(GuardParams),
        "popping": settings_of(PoppingSettings),
    }


def _read(scene_or_extra, section: str, where: str) -> dict:
    """A section's table read against its declared keys (:func:`~warpskin.settings.read_section`):
    ``{field name: value}`` of the keys given."""
    table = scene_or_extra.get(section, {})
    return read_section(scene_sections()[section], table, where, section)


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
        return clip_frame_span(self.rig().clip(self.clip), self.frame_rate)

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
        """The :class:`~warpskin.solver.SolverParams` of the ``[solver]`` section (what the solver
        reads, and ``dt``)."""
        from .params import SolverParams

        return self._solver_section(SolverParams)

    def run_limits(self):
        """The :class:`~warpskin.params.RunLimits` of the ``[solver]`` section (where a run stops)."""
        from .params import RunLimits

        return self._solver_section(RunLimits)

    def _solver_section(self, cls):
        """``cls`` (:class:`~warpskin.params.SolverParams` or :class:`~warpskin.params.RunLimits`)
        from its keys of the ``[solver]`` section, the whole section checked."""
        from dataclasses import fields

        where = _where(self.source)
        table = _read(self.extra, "solver", where)
        if "gravity" in table:
            table["gravity"] = tuple(float(g) for g in table["gravity"])
        names = {f.name for f in fields(cls)}
        params = cls(**{k: v for k, v in table.items() if k in names})
        params.check(where)
        return params

    def collision_params(self):
        """The :class:`~warpskin.collision.CollisionParams` of the ``[collision]`` section
        (self-collision is on by default)."""
        return from_section(CollisionParams, self.extra.get("collision", {}), _where(self.source), "collision")

    def guard_params(self):
        """The :class:`~warpskin.guard.GuardParams` of the ``[guard]`` section (the surface guard
        of the written meshes; on by default)."""
        from .guard import GuardParams

        return from_section(GuardParams, self.extra.get("guard", {}), _where(self.source), "guard")

    def popping_settings(self):
        """The :class:`~warpskin.params.PoppingSettings` of the ``[popping]`` section (defaults
        where absent), its activation table parsed into an
        :class:`~warpskin.popping.activation.ActivationTimeline`.

        Raises:
            SceneError: a value of the wrong kind or range, naming the file and key.
        """
        from .popping.activation import ActivationTimeline  # the popping package loads Warp: only when asked

        where = str(self.source) if self.source else "scene"
        values = read_section(scene_sections()["popping"], dict(self.extra.get("popping") or {}), where, "popping")
        values["activation"] = ActivationTimeline.from_table(values.get("activation", {}),
                                                             where=f"{where}: [popping.activation]")
        settings = PoppingSettings(**values)
        settings.check(where)
        return settings

    def physics_weights(self) -> dict[str, float]:
        """``[physics.weights]``: joint-name patterns (shell-style, case-insensitive: ``"*hand*"``)
        and the physics weight in [0, 1] of the skin their joints drive
        (:class:`~warpskin.character.Character`), in the file's order."""
        where = _where(self.source)
        physics = self.extra.get("physics", {})
        if isinstance(physics, dict) and "weights" in physics and not isinstance(physics["weights"], dict):
            raise SceneError(f"{where}: [physics.weights] must be a table of joint-name patterns and weights")
        table = _read(self.extra, "physics", where).get("weights", {})
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
    check_value(setting_named(RigSpec, "weights"), weights, f"{where}: [rig] ")
    if weights == "bone_heat":
        from .preprocess.bone_heat import with_bone_heat_weights

        rig = with_bone_heat_weights(rig)
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


def is_rig_file(target: str | Path) -> bool:
    """Is ``target`` a rig file (glTF or USD, by its extension) rather than a scene?"""
    return str(target).lower().endswith(RIG_EXTENSIONS)


def resolve_scene(target: Scene | str | Path) -> Scene:
    """A :class:`Scene` as it is; a rig file played as it is; otherwise a scene name or TOML path."""
    if isinstance(target, Scene):
        return target
    return Scene.from_rig_file(target) if is_rig_file(target) else load_scene(target)


def clip_frame_span(clip, rate: float) -> tuple[int, int]:
    """The inclusive frames ``clip`` spans at ``rate`` [fps]: the first at or after its first key,
    the last at or before its last key (within a thousandth of a frame: key times are often
    float32, RiggedSimple's last key is 49.99999 frames)."""
    eps = 1e-3
    first = int(math.ceil(clip.start * rate - eps))
    return first, max(first, int(math.floor(clip.end * rate + eps)))


def _format_hint(path: Path) -> str:
    """What a file that is not a scene looks like, by its first bytes, and the extensions a rig
    file is taken by: ``"; it looks like binary glTF: rename it to .glb (...)"``."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        head = b""
    kinds = {b"glTF": ("binary glTF", ".glb"), b"PXR-USDC": ("USD crate", ".usdc"), b"PK\x03\x04": ("a zip (USDZ?)", ".usdz"),
             b"#usda": ("USD text", ".usda")}
    seen = next((kind for magic, kind in kinds.items() if head.startswith(magic)), None)
    known = f"rig files end in {', '.join(RIG_EXTENSIONS)}; scenes in .toml"
    return f"; it looks like {seen[0]}: rename it to {seen[1]} ({known})" if seen else f" ({known})"


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
            raise SceneError(f"{candidate}: not a TOML scene file (not UTF-8 text){_format_hint(candidate)}") from None
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
        hint = _format_hint(text_path) if text_path is not None and text_path.suffix.lower() != ".toml" else ""
        raise SceneError(f"{where}: not valid TOML: {exc}{hint}") from None

    extra = {k: data[k] for k in ("layers", "joints", "subvolumes", "solver", "collision", "physics", "guard", "popping")
             if k in data}
    sections = scene_sections()
    for section, table in data.items():
        if section not in sections:
            raise SceneError(f"{where}: unknown section [{section}]; known: {sorted(sections)}")
        if not isinstance(table, dict):
            raise SceneError(f"{where}: {section} must be a table")
        keys = {s.scene_key for s in sections[section]}
        unknown = sorted(set(table) - keys)
        if unknown:
            raise SceneError(f"{where}: unknown key(s) {unknown} in [{section}]; known: {sorted(keys)}")
    # the sections read here; the others are read, with their values checked, by their readers
    # (Scene.model_params, solver_params, ...)
    meta = _read(data, "scene", where)
    _read(data, "rig", where)
    anim = _read(data, "animation", where)
    if "rig" not in data:
        raise SceneError(f"{where}: missing [rig] section")
    fps = float(anim["fps"]) if anim.get("fps") is not None else None
    frames = tuple(anim["frames"]) if anim.get("frames") is not None else None
    clip = anim.get("clip")
    keys = anim.get("keys")
    if keys is not None:
        if not all(isinstance(v, dict) and set(v) == {"rotation"} for v in keys.values()):
            raise SceneError(f"{where}: [animation.keys.JOINT] takes rotation = [[t, x_deg, y_deg, z_deg], ...]")
        extra["keys"] = {j: v["rotation"] for j, v in keys.items()}
        extra["interpolation"] = anim.get("interpolation", "LINEAR")
        clip = clip or SCENE_CLIP
    elif "interpolation" in anim:
        raise SceneError(f"{where}: [animation] interpolation applies to [animation.keys] only")
    is_file_rig = "file" in data["rig"] or "asset" in data["rig"]
    preroll = anim.get("preroll")
    if preroll is None:
        preroll = FILE_RIG_PREROLL if is_file_rig else 0.0
    return Scene(
        name=str(meta.get("name") or name),
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
    """The :class:`~warpskin.model.ModelParams` of ``[layers]``, ``[joints]`` and ``[subvolumes]``
    (each key's kind and range from its declaration; the per-bone and per-plane tables here)."""
    from .preprocess.joint_constraints import JointParams
    from .preprocess.layers import LayerParams
    from .model import ModelParams

    lay = _read(extra, "layers", where)
    per_bone_proj, per_bone_stiff = {}, {}
    for bone, table in lay.pop("per_bone", {}).items():
        if not isinstance(table, dict) or set(table) - {"projection", "stiffness"}:
            raise SceneError(f"{where}: [layers.per_bone.{bone}] takes 'projection' and/or 'stiffness'")
        if "projection" in table:
            per_bone_proj[bone] = _numbers(where, f"[layers.per_bone.{bone}] projection", table["projection"], 3)
        if "stiffness" in table:
            per_bone_stiff[bone] = _numbers(where, f"[layers.per_bone.{bone}] stiffness", table["stiffness"], 4)
    layer_keys = {s.name for s in settings_of(LayerParams)}
    layer_params = LayerParams(per_bone=per_bone_proj, **{k: v for k, v in lay.items() if k in layer_keys})
    model = {k: v for k, v in lay.items() if k not in layer_keys}
    if "stiffness" in model:
        model["stiffness"] = tuple(float(x) for x in model["stiffness"])
    jt = _read(extra, "joints", where)
    if "layers" in jt:
        jt["layers"] = tuple(jt["layers"])
    joint_params = JointParams(**jt)
    sv = _read(extra, "subvolumes", where)
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
    params = ModelParams(
        layers=layer_params,
        stiffness_per_bone=per_bone_stiff,
        joints=joint_params,
        subvolumes=sub_params,
        **{k: v for k, v in sv.items() if k != "planes"},
        **model,
    )
    params.check(where)
    return params

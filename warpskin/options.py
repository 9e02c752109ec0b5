"""The command line's own options, declared once (:mod:`warpskin.settings`): what a command writes,
where it runs, how it reports. The options that stand for a scene key (``--iterations``,
``--clip``, ``--no-guard``, ...) are declared on their parameter class's field (``SolverParams``,
``AnimationSpec``, ``GuardParams``, ...); :func:`warpskin.settings.add_option` makes every option of
the parser from one of the two.

Each command's options are a dataclass (its options' names are the parsed arguments' names);
:class:`CommonOptions` holds those several commands share with one meaning.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

from .settings import setting

__all__ = ["with_overrides", "GlobalOptions", "CommonOptions", "InfoOptions", "SkinOptions", "SimulateOptions", "LayersOptions",
           "BenchOptions", "PopOptions", "RenderOptions"]


# ------------------------------------------------------------------------------ option texts
def projection_arg(text: str) -> tuple[float, float, float]:
    """``--projection FAT,MUSCLE,BONE`` with ``0 < FAT < MUSCLE < BONE < 1``."""
    try:
        fat, muscle, bone = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--projection must be FAT,MUSCLE,BONE (three numbers), got {text!r}") from None
    if not (0.0 < fat < muscle < bone < 1.0):
        raise argparse.ArgumentTypeError(f"--projection {text}: need 0 < FAT < MUSCLE < BONE < 1")
    return fat, muscle, bone


def weight_arg(text: str) -> tuple[str, float]:
    """``--physics-weight PATTERN=W`` with ``W`` in [0, 1]."""
    pattern, eq, value = text.rpartition("=")
    try:
        w = float(value)
    except ValueError:
        w = math.nan
    if not eq or not pattern or not (0.0 <= w <= 1.0):
        raise argparse.ArgumentTypeError(f"--physics-weight must be PATTERN=W with W in [0, 1], got {text!r}")
    return pattern, w


def cage_arg(text: str):
    """``--cage``: ``auto``, ``always``, ``none``, or an existing cage mesh file (a Path)."""
    from .io.cage_file import CAGE_EXTENSIONS

    if text in ("auto", "always", "none"):
        return text
    path = Path(text)
    if path.suffix.lower() not in CAGE_EXTENSIONS:
        raise argparse.ArgumentTypeError(f"--cage must be auto, always, none or a mesh file "
                                         f"({', '.join(CAGE_EXTENSIONS)}), got {text!r}")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"--cage {text}: no such file")
    return path


def frame_list_arg(text: str) -> list[float]:
    """``render --frames``: comma-separated time codes."""
    try:
        out = [float(x) for x in text.split(",")]
    except ValueError:
        out = []
    if not out or not all(math.isfinite(x) for x in out):
        raise argparse.ArgumentTypeError(f"--frames must be comma-separated time codes, got {text!r}")
    return out


def resolution_arg(text: str) -> tuple[int, int]:
    """``--resolution WxH`` in pixels, each in 16..8192."""
    w, _, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        size = (0, 0)
    if min(size) < 16 or max(size) > 8192:
        raise argparse.ArgumentTypeError(f"--resolution must be WxH in pixels (16..8192), got {text!r}")
    return size


_CAGE = "auto|always|none|FILE"


def with_overrides(kind: type, options, overrides: dict, command: str):
    """A Python API's options in one place: ``options`` (an instance of the frozen dataclass
    ``kind``, or ``None`` for its defaults) with the fields named in ``overrides`` replaced
    (:func:`dataclasses.replace`).

    Raises:
        InputError: ``"<command>: unknown option 'NAME' (options: ...)"``, or ``options`` not a
            ``kind``.
    """
    from dataclasses import fields, replace

    from .errors import InputError

    if options is None:
        options = kind()
    elif not isinstance(options, kind):
        raise InputError(f"{command}: options must be a {kind.__name__}, got {type(options).__name__}")
    known = {f.name for f in fields(kind)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise InputError(f"{command}: unknown option {unknown[0]!r} (options: {', '.join(sorted(known))})")
    return replace(options, **overrides) if overrides else options


# ------------------------------------------------------------------------------ declarations
@dataclass
class GlobalOptions:
    """Options of ``warpskin`` itself (also taken after the command)."""

    debug: bool = setting(False, "bool", "print tracebacks on errors", cli="--debug")


@dataclass
class CommonOptions:
    """Options several commands share, with one meaning."""

    target: str = setting("", "string", "a .glb/.gltf/.usd/.usda/.usdc/.usdz file, a scene name or a .toml file",
                          cli="target", metavar="RIG|SCENE")
    output: str | None = setting(None, "string", "output .usdc (default format), .usda or .usd", optional=True,
                                 cli=("-o", "--output"))
    device: str | None = setting(None, "string", "cpu, cuda or cuda:N (default: Warp's default)", optional=True,
                                 cli="--device")
    start_frame: int | None = setting(None, "integer", "write the first frame at time code N (default: the source's "
                                      "own frame numbers)", optional=True, cli="--start-frame", metavar="N")
    topology: str = setting("file", "string", "the file's own vertices, faces, UVs and materials (default) or the "
                            "welded closed surface", choices=("file", "welded"), cli="--topology")
    projection: tuple | None = setting(None, "numbers", "layer projection parameters, upper bounds ([layers] fat, "
                                       "muscle, bone; default 0.15,0.45,0.8)", length=3, optional=True,
                                       cli="--projection", metavar="FAT,MUSCLE,BONE", parse=projection_arg)
    json: bool = setting(False, "bool", "print the run's summary as JSON instead of the text line", cli="--json")
    quiet: bool = setting(False, "bool", "no progress bar", cli="--quiet")


@dataclass
class InfoOptions:
    """``warpskin info``."""

    cage: object = setting("auto", "string", "the physics weights and muscle groups as simulate and pop see them "
                           "with this --cage", cli="--cage", metavar=_CAGE, parse=cage_arg)
    json: bool = setting(False, "bool", "print JSON", cli="--json")


@dataclass
class SkinOptions:
    """``warpskin skin``."""

    method: str = setting("lbs", "string", "linear blend or dual quaternion skinning", choices=("lbs", "dqs"),
                          cli="--method")
    with_rest: bool = setting(False, "bool", "also write the rest mesh as a sibling prim", cli="--with-rest")
    with_lbs: bool = setting(False, "bool", "with --method dqs, also write the LBS result", cli="--with-lbs")


@dataclass
class SimulateOptions:
    """``warpskin simulate``."""

    lbs: bool = setting(False, "bool", "also write the LBS result as a sibling prim", cli="--lbs")
    layers: bool = setting(False, "bool", "also write the fat, muscle and bone layers", cli="--layers")
    cage: object = setting("auto", "string", "where the skin is not one closed manifold, auto (the default) "
                           "simulates the character's own pieces, holes capped and clothes worn over them, or an "
                           "automatic closed cage where fewer than half its points lie on pieces that close; always: "
                           "a cage around every mesh, each written as its LBS plus the cage's physical deformation "
                           "captured near it; none: never a cage (the skin or its own pieces); or FILE, your own "
                           "closed cage (.obj, .glb, .gltf, .usd, .usda, .usdc, .usdz) around the character's rest "
                           "pose, in the character file's units", cli="--cage", metavar=_CAGE, parse=cage_arg)
    rigid_pieces: str = setting("cage", "string", "through a cage, the pieces LBS moves rigidly (eyes or teeth "
                                "skinned to one joint, rigidly parented parts): moved by one rigid motion with the cage "
                                "around them (cage, the default) or following their joints exactly (joint)",
                                choices=("cage", "joint"), cli="--rigid-pieces")
    physics_weight: list | None = setting(None, "string", "the physics weight (0: LBS, 1: physical) of the skin the "
                                          "joints matching PATTERN drive, e.g. '*hand*=0' (repeatable; scene: "
                                          "[physics.weights])", optional=True, cli="--physics-weight",
                                          metavar="PATTERN=W", parse=weight_arg)
    report: str | None = setting(None, "string", "write report.json and PNG plots (volume, energy) to DIR",
                                 optional=True, cli="--report", metavar="DIR")
    no_gravity: bool = setting(False, "bool", "switch gravity off ([solver] gravity = [0, 0, 0])", cli="--no-gravity")
    allow_unstable: bool = setting(False, "bool", "go on (with one warning) when the skin leaves its plausible range "
                                   "instead of stopping with exit 3 ([solver] max_offset, max_volume_error)",
                                   cli="--allow-unstable")


@dataclass
class LayersOptions:
    """``warpskin layers``."""

    json: bool = setting(False, "bool", "print the model summary as JSON", cli="--json")


@dataclass
class BenchOptions:
    """``warpskin bench``."""

    scenes: list = setting([], "strings", "scenes or rig files (default: arm, cesium_man)", cli="scenes",
                           metavar="SCENE")
    frames: int = setting(60, "integer", "skinning frames per measurement", low=1, cli="--frames")
    steps: int = setting(10, "integer", "solver steps per measurement", low=1, cli="--steps")
    repeat: int = setting(3, "integer", "measurements; the best is reported", low=1, cli="--repeat")
    json: str | None = setting(None, "string", "also write the JSON to FILE", optional=True, cli="--json",
                               metavar="FILE")
    build: bool = setting(False, "bool", "time the model build (layers ... sub-volumes) instead; default scenes: arm, "
                          "cesium_man, arm35k", cli="--build")
    batch: int | None = setting(None, "integer", "instead: N instances of each scene (default: arm) in one batched "
                                "model against N separate models, character-steps per second", optional=True,
                                cli="--batch", metavar="N")


@dataclass
class PopOptions:
    """``warpskin pop``."""

    target: str | None = setting(None, "string", "a closed rig file (.glb, .gltf, .usd*: muscles found from its "
                                 "skeleton, layered mode), a scene with popping examples (popping_arm) or a .toml "
                                 "scene", optional=True, cli="target", metavar="SCENE")
    no_vibrate: bool = setting(False, "bool", "layered mode: the muscles follow the activation as it is, without the "
                               "paper's ringing while clenched", cli="--no-vibrate")
    no_normal_guide: bool = setting(False, "bool", "layered mode: do not also simulate the frames without the pop for "
                                    "the <skin>_normal guide (half the cost)", cli="--no-normal-guide")
    report: str | None = setting(None, "string", "write each muscle group's bulge against its activation over time "
                                 "(popping.json, popping.png; in layered mode beside the simulation's report)",
                                 optional=True, cli="--report", metavar="DIR")
    cage: object = setting("auto", "string", "muscles found from the skeleton: simulate (and pop) an automatic closed "
                           "cage where the skin is not one closed manifold (auto), always, never, or your own cage "
                           "FILE, as simulate does", cli="--cage", metavar=_CAGE, parse=cage_arg)
    # the defaults stated are warpskin.popping's DEFAULT_SURFACE_SWELL and DEFAULT_SWELL (a test
    # compares them)
    swell: float | None = setting(None, "number", "muscles found from the skeleton: peak swelling as a share of the "
                                  "fat-plus-muscle depth (default 0.4; 0.3 with --pop-on layers)", low=0.0,
                                  open_low=True, optional=True, must="a positive number", cli="--swell")
    pop_on: str = setting("surface", "string", "muscles found from the skeleton: swell the written meshes over the "
                          "physical skin (surface, the default: the paper's goal-driven skin, one simulation) or the "
                          "multi-layer model's rest shape (layers: the physical skin, or its cage, makes the pop)",
                          choices=("surface", "layers"), cli="--pop-on")
    bpm: float | None = setting(None, "number", "pop on every beat at this tempo [beats per minute]", low=0.0,
                                open_low=True, optional=True, must="a positive number", cli="--bpm")
    offset: float = setting(0.0, "number", "with --bpm: clip time of the first beat (default 0)", unit="s",
                            cli="--offset", metavar="SECONDS")
    every: int = setting(1, "integer", "with --bpm: pop on every K-th beat (default 1)", low=1, cli="--every",
                         metavar="K")
    beats: str | None = setting(None, "string", "pop at the times in FILE: one time in seconds a line, or "
                                "time,group[,activation] (CSV)", optional=True, cli="--beats", metavar="FILE")
    hold: float | None = setting(None, "number", "how long each pop stays clenched (default: half the time to the "
                                 "group's next pop, at most 0.25 s)", low=0.0, open_low=True, optional=True,
                                 must="a positive number", cli="--hold", metavar="SECONDS")
    groups: str | None = setting(None, "string", "the muscle groups that pop, in this order (default: every group); "
                                 "on a rig file also NAME=JOINT_PATTERN (glob) to make one, e.g. biceps_l=*arm*L*",
                                 optional=True, cli="--groups", metavar="A,B,...")
    in_turn: bool = setting(False, "bool", "give each beat to the next group in --groups order instead of popping "
                            "them together", cli="--in-turn")
    bench: bool = setting(False, "bool", "instead: time example-based skinning and the popping step per frame at 4322 "
                          "vertices vs LBS (JSON)", cli="--bench")
    steps: int = setting(200, "integer", "with --bench: frames per measurement", low=1, cli="--steps")
    repeat: int = setting(3, "integer", "with --bench: measurements; the best is reported", low=1, cli="--repeat")
    json: str | None = setting(None, "string", "print the run's summary as JSON (with --bench: also write the JSON "
                               "to FILE)", optional=True, cli="--json", metavar="FILE")


@dataclass
class RenderOptions:
    """``warpskin render``."""

    bake: str = setting("", "string", "a USD file written with --lbs", cli="bake", metavar="BAKE")
    output: str = setting("", "string", "folder for the PNG pictures", cli=("-o", "--output"), metavar="DIR")
    frames: list | None = setting(None, "numbers", "comma-separated time codes to render (default: the worst frame "
                                  "and --extra others)", optional=True, cli="--frames", parse=frame_list_arg)
    extra: int = setting(2, "integer", "frames besides the worst one (default 2)", low=0, cli="--extra")
    no_close_up: bool = setting(False, "bool", "leave out the close-up of the worst mesh", cli="--no-close-up")
    resolution: tuple = setting((800, 900), "integers", "size of each panel in pixels (default 800x900)", length=2,
                                low=16, high=8192, cli="--resolution", metavar="WxH", parse=resolution_arg)
    yaw: float = setting(20.0, "number", "the camera's turn about the vertical from the front (180: from behind)",
                         unit="degrees", low=-360.0, high=360.0, must="in [-360, 360]", cli="--yaw")
    python: str | None = setting(None, "string", "a Python with Blender's bpy (default: $WARPSKIN_BPY_PYTHON or "
                                 ".venv-bpy/bin/python)", optional=True, cli="--python", metavar="EXE")
    color: str = setting("plain", "string", "colour the physical meshes by their offset from LBS, or by their "
                         "motion against LBS since the previous frame (what moves on its own: jiggle, a garment "
                         "still swinging after a stop), white to red", choices=("plain", "offset", "motion"),
                         cli="--color")
    quiet: bool = setting(False, "bool", "do not list the pictures written", cli="--quiet")

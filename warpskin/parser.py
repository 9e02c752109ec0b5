"""The ``warpskin`` command line's parser: every command and its options, made from their
declarations (:mod:`warpskin.settings`, :mod:`warpskin.options`). It imports no command: the
command line (:mod:`warpskin.cli`) hands each command's function in, and a batch parses its
jobs' arguments with it (:mod:`warpskin.batch`)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping

from .options import (
    BenchOptions, CommonOptions, GlobalOptions, InfoOptions, LayersOptions, PopOptions, RenderOptions,
    SimulateOptions, SkinOptions,
)
from .params import CollisionParams, PoppingSettings, SolverParams
from .scene import AnimationSpec, RigSpec
from .settings import add_option as opt

__all__ = ["Parser", "build_parser"]


class Parser(argparse.ArgumentParser):
    """argparse's parser whose usage error is one line naming the option, then where the help
    is (argparse prints the whole usage first: 15 lines before the one that matters)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n(options: {self.prog} --help)\n")


def build_parser(handlers: Mapping[str, Callable] | None = None,
                 extra: Callable[[argparse._SubParsersAction], None] | None = None) -> argparse.ArgumentParser:
    """The parser of every command but ``batch``. Each option is made from its declaration
    (:func:`warpskin.settings.add_option`): a scene setting's field (``SolverParams.iterations``
    is ``--iterations``) or a command's own (:mod:`warpskin.options`).

    Args:
        handlers: ``{command: function}``: each command's ``func`` default (the command line's;
            none: the parser only parses, as a batch does to check a job's arguments).
        extra: Called with the subcommands before the last one (``warmup``), to add more
            (the command line adds ``batch`` there).
    """
    from . import __version__
    from .guard import GuardParams

    def handled(s, command: str) -> None:
        if handlers and command in handlers:
            s.set_defaults(func=handlers[command])

    C = CommonOptions
    p = Parser(prog="warpskin", description="Physically-based character skinning on NVIDIA Warp.")
    p.add_argument("--version", action="version", version=f"warpskin {__version__}")
    opt(p, GlobalOptions, "debug")
    # global flags are accepted after the command too (SUPPRESS: not given there, the value
    # before the command stands)
    common = Parser(add_help=False)
    opt(common, GlobalOptions, "debug", default=argparse.SUPPRESS)
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    add_parser = sub.add_parser

    def with_common(*a, **kw):
        return add_parser(*a, parents=[common], **kw)

    sub.add_parser = with_common

    def rig_input(s, *names):
        for name in names:
            opt(s, RigSpec if name in ("mesh", "unit_scale", "weights") else AnimationSpec, name)

    s = sub.add_parser("scenes", help="list the shipped scenes")
    handled(s, "scenes")

    s = sub.add_parser("info", help="describe a rig file or scene")
    opt(s, C, "target")
    rig_input(s, "mesh", "unit_scale")
    opt(s, InfoOptions, "cage")
    opt(s, InfoOptions, "json")
    handled(s, "info")

    s = sub.add_parser("skin", help="skin a rig or scene with LBS or DQS and write USD")
    opt(s, C, "target")
    opt(s, C, "output", required=True)
    opt(s, SkinOptions, "method")
    rig_input(s, "clip", "frames", "fps")
    opt(s, C, "start_frame")
    opt(s, C, "device")
    rig_input(s, "mesh", "unit_scale", "weights")
    for name in ("with_rest", "with_lbs"):
        opt(s, SkinOptions, name)
    opt(s, C, "json")
    opt(s, C, "topology")
    opt(s, C, "quiet")
    handled(s, "skin")

    s = sub.add_parser("simulate", help="simulate the physical skin and write it to USD")
    opt(s, C, "target")
    opt(s, C, "projection")
    opt(s, C, "output", required=True)
    rig_input(s, "frames", "fps")
    opt(s, C, "start_frame")
    rig_input(s, "clip")
    opt(s, C, "device")
    rig_input(s, "mesh", "unit_scale", "weights")
    opt(s, SimulateOptions, "lbs")
    opt(s, C, "topology")
    for name in ("layers", "cage", "rigid_pieces"):
        opt(s, SimulateOptions, name)
    opt(s, SimulateOptions, "physics_weight", action="append")
    opt(s, SimulateOptions, "report")
    for name in ("iterations", "volume_iterations", "dt", "damping", "fast_summation"):
        opt(s, SolverParams, name)
    opt(s, SimulateOptions, "no_gravity")
    opt(s, CollisionParams, "enabled")
    opt(s, GuardParams, "enabled")
    opt(s, SimulateOptions, "allow_unstable")
    rig_input(s, "preroll")
    opt(s, C, "json")
    opt(s, C, "quiet")
    handled(s, "simulate")

    s = sub.add_parser("layers", help="build the multi-layer model and write it to USD for inspection")
    opt(s, C, "target")
    opt(s, C, "output", required=True)
    rig_input(s, "mesh", "unit_scale", "weights")
    opt(s, C, "projection")
    opt(s, LayersOptions, "json")
    handled(s, "layers")

    s = sub.add_parser("bench", help="time skinning per frame (or the model build with --build); JSON out")
    opt(s, BenchOptions, "scenes", nargs="*")
    opt(s, C, "device")
    for name in ("frames", "steps", "repeat", "json", "build", "batch"):
        opt(s, BenchOptions, name)
    handled(s, "bench")

    s = sub.add_parser("pop", help="popping dance (Son & Han 2007): example-based skinning plus skin vibration to USD")
    opt(s, PopOptions, "target", nargs="?")
    rig_input(s, "clip")
    for name in ("no_vibrate", "no_normal_guide", "report", "cage", "swell", "pop_on"):
        opt(s, PopOptions, name)
    opt(s, C, "output")
    rig_input(s, "frames", "fps")
    opt(s, C, "start_frame")
    opt(s, C, "device")
    for name in ("alpha_min", "beta", "dt"):
        opt(s, PoppingSettings, name)
    opt(s, C, "quiet")
    opt(s, C, "topology")
    opt(s, PoppingSettings, "mode")
    beat = s.add_argument_group("pops on the beat (in place of the scene's [popping.activation])")
    for name in ("bpm", "offset", "every", "beats", "hold", "groups", "in_turn"):
        opt(beat, PopOptions, name)
    for name in ("bench", "steps", "repeat"):
        opt(s, PopOptions, name)
    opt(s, PopOptions, "json", nargs="?", const="-")
    handled(s, "pop")

    s = sub.add_parser("render", help="pictures of a bake in Blender: the physical result beside LBS, at its worst frame")
    opt(s, RenderOptions, "bake")
    opt(s, RenderOptions, "output", required=True)
    for name in ("frames", "extra", "no_close_up", "resolution", "yaw", "color", "python", "quiet"):
        opt(s, RenderOptions, name)
    handled(s, "render")

    if extra is not None:
        extra(sub)

    s = sub.add_parser("warmup", help="compile and cache the Warp kernels")
    opt(s, C, "device")
    handled(s, "warmup")
    return p

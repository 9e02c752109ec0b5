"""Every setting declared once (warpskin.settings): every key a scene file takes and every option
of every command comes from a declaration, each declared scene key is read with its value, an
undeclared one is refused, and the checks (scene and command line) refuse what the declared range
does not allow, with the declared words."""

from __future__ import annotations

import argparse
import math
import re

import pytest

from warpskin.errors import SceneError
from warpskin.scene import load_scene, scene_sections
from warpskin.settings import Setting, read_section, setting, settings_of

# values a generic choice of the declared range would not satisfy together
_TOGETHER = {
    ("layers", "fat"): 0.1, ("layers", "muscle"): 0.4, ("layers", "bone"): 0.7,  # fat < muscle < bone
    ("popping", "dt"): 0.01,  # beta * dt <= 1
    ("animation", "frames"): [2, 7],
    ("joints", "layers"): ["muscle", "bone"], ("joints", "joints"): ["elbow"],
    ("popping", "joints"): ["elbow"], ("popping", "mode"): "layered",
}


def _toml(value) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{}"
    return repr(value)


def _number_inside(s: Setting, k: int = 0):
    """A generic value inside the declared range of a number or integer setting."""
    lo = s.low if s.low is not None else 0.0
    hi = s.high if s.high is not None else lo + 10.0
    if s.kind in ("integer", "integers"):
        return int(math.ceil(lo)) + 1 + k if s.high is None or hi - lo >= 2 + k else int(math.ceil(lo))
    return lo + (0.37 + 0.1 * k) * (hi - lo)


def _valid(section: str, s: Setting):
    """A value of the declared kind inside the declared range, away from its bounds."""
    if (section, s.scene_key) in _TOGETHER:
        return _TOGETHER[(section, s.scene_key)]
    if s.kind == "bool":
        return not s.default if isinstance(s.default, bool) else False
    if s.kind == "string":
        return s.choices[-1] if s.choices else f"x_{s.name}"
    if s.kind == "strings":
        return [f"x_{s.name}"]
    if s.kind == "table":
        return {}
    if s.kind in ("numbers", "integers"):
        return [_number_inside(s, k) for k in range(s.length or 2)]
    return _number_inside(s)


def _read_back(scene, section: str) -> dict:
    """What the scene's reader of ``section`` made of it, by scene key."""
    from warpskin.popping import popping_settings

    if section == "scene":
        return {"name": scene.name, "description": scene.description}
    if section == "rig":
        return dict(scene.rig_spec)
    if section == "animation":
        return {"clip": scene.clip, "fps": scene.fps, "frames": list(scene.frames), "preroll": scene.preroll,
                "interpolation": scene.extra.get("interpolation"), "keys": scene.extra.get("keys")}
    if section in ("layers", "joints", "subvolumes"):
        m = scene.model_params()
        out = {"stiffness": list(m.stiffness), "density": m.density, "omega": m.omega,
               "coupling_stiffness": m.coupling_stiffness, "refine": m.refine, "max_edge": m.max_edge,
               "fat": m.layers.fat, "muscle": m.layers.muscle, "bone": m.layers.bone, "adaptive": m.layers.adaptive,
               "per_bone": m.layers.per_bone}
        out.update({"radius_factor": m.joints.radius_factor, "layers": list(m.joints.layers), "joints": m.joints.joints,
                    "enabled": m.volume, "planes": {} if m.subvolumes is None else m.subvolumes.planes})
        return out
    if section == "solver":  # the solver's settings and the run's limits
        return {s.scene_key: list(getattr(p, s.name)) if s.kind == "numbers" else getattr(p, s.name)
                for p in (scene.solver_params(), scene.run_limits()) for s in settings_of(p)}
    if section == "physics":
        return {"weights": scene.physics_weights()}
    obj = {"collision": scene.collision_params, "guard": scene.guard_params,
           "popping": lambda: popping_settings(scene)}[section]()
    out = {s.scene_key: getattr(obj, s.name) for s in settings_of(obj)}
    if section == "popping":  # read into the activation timeline: its groups
        out["activation"] = obj.activation.times
    return out


@pytest.mark.parametrize("section", sorted(scene_sections()))
def test_a_scene_section_takes_exactly_its_declared_keys(section, tmp_path):
    # every declared key of the section, set to a value inside its declared range, is read by
    # the section's reader with that value; a key not declared is refused naming the known ones
    declared = scene_sections()[section]
    assert declared, section
    values = {s.scene_key: _valid(section, s) for s in declared}
    lines = [f"{k} = {_toml(v)}" for k, v in values.items()]
    base = {"scene": '[scene]\nname = "t"\n', "rig": '[rig]\ngenerator = "arm"\n'}
    text = "".join(v for k, v in base.items() if k != section) + f"[{section}]\n" + "\n".join(lines) + "\n"
    if section == "rig":  # exactly one source of the rig is read, the others are refused there
        text = text.replace('file = "x_file"\n', "").replace('asset = "x_asset"\n', "")
        values = {k: v for k, v in values.items() if k not in ("file", "asset")}
        values["generator"] = "arm"
        text = text.replace('generator = "x_generator"', 'generator = "arm"')
    path = tmp_path / "t.toml"
    path.write_text(text)
    got = _read_back(load_scene(path), section)
    for key, value in values.items():
        read = got[key]
        if isinstance(value, float):
            assert read == pytest.approx(value, rel=1e-12), key
        elif isinstance(value, dict):
            assert not read, key  # an empty table reads as an empty one
        else:
            assert read == value, key
    path.write_text(text + "not_a_key = 0.01\n")
    known = sorted(s.scene_key for s in declared)
    with pytest.raises(SceneError, match=rf"unknown key\(s\) \['not_a_key'\] in \[{section}\]; known: "
                       + re.escape(str(known))):
        load_scene(path)


def test_a_scene_takes_only_the_declared_sections(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text('[rig]\ngenerator = "arm"\n[solvr]\niterations = 3\n')
    with pytest.raises(SceneError, match=r"unknown section \[solvr\]; known: \['animation', 'collision', 'guard', "
                       r"'joints', 'layers', 'physics', 'popping', 'rig', 'scene', 'solver', 'subvolumes'\]"):
        load_scene(path)


def _outside(s: Setting):
    """A number outside the declared range, by a margin (``None`` when unbounded)."""
    if s.low is not None:
        return s.low - max(1.0, abs(s.low))
    if s.high is not None:
        return s.high + max(1.0, abs(s.high))
    return None


@pytest.mark.parametrize("section", sorted(scene_sections()))
def test_a_value_outside_its_declared_range_is_refused_naming_the_key(section, tmp_path):
    # each bounded number of the section, set outside its range, is refused by load or by the
    # section's reader in one line naming the file, the section, the key and the declared range
    bounded = [s for s in scene_sections()[section] if s.kind in ("number", "integer") and _outside(s) is not None]
    base = '[scene]\nname = "t"\n' + ('[rig]\ngenerator = "arm"\n' if section != "rig" else "")
    path = tmp_path / "t.toml"
    for s in bounded:
        bad = _outside(s)
        bad = int(bad) if s.kind == "integer" else bad
        extra = 'generator = "arm"\n' if section == "rig" else ""
        path.write_text(base + f"[{section}]\n{extra}{s.scene_key} = {bad!r}\n")
        with pytest.raises(SceneError) as info:
            _read_back(load_scene(path), section)
        line = str(info.value)
        assert line.startswith(f"{path}: [{section}] {s.scene_key} must be {s.range_text()}"), line
        assert "\n" not in line


@pytest.mark.parametrize("section,text,message", [
    ("collision", "restitution = 1.7", r"t.toml: \[collision\] restitution must be in \[0, 1\], got 1.7$"),
    ("guard", "strain = 1.7", r"t.toml: \[guard\] strain must be in \(1, 1.5\], got 1.7$"),
    ("solver", "dt = 0", r"t.toml: \[solver\] dt must be a positive number \[s\], got 0$"),
    ("layers", "density = -3", r"t.toml: \[layers\] density must be a positive number \[kg/m\^3\], got -3$"),
    ("popping", 'mode = "dance"', r"t.toml: \[popping\] mode must be 'goal' or 'layered', got 'dance'$"),
    ("animation", "frames = [5, 2]", r"t.toml: \[animation\] frames must be \[first, last\] integers with 0 <= first "
                                     r"<= last, got \[5, 2\]$"),
])
def test_the_messages_name_the_file_the_key_the_range_and_the_value(section, text, message, tmp_path):
    path = tmp_path / "t.toml"
    path.write_text(f'[rig]\ngenerator = "arm"\n[{section}]\n{text}\n')
    with pytest.raises(SceneError, match=message):
        _read_back(load_scene(path), section)


def test_a_value_of_the_wrong_kind_is_refused():
    s = Setting(name="fps", kind="number", default=None, help="", section="animation", optional=True)
    with pytest.raises(SceneError, match=r"^f.toml: \[animation\] fps must be a number, got 'fast'$"):
        read_section([s], {"fps": "fast"}, "f.toml", "animation")
    b = Setting(name="enabled", kind="bool", default=True, help="", section="guard")
    with pytest.raises(SceneError, match=r"^f.toml: \[guard\] enabled must be true or false, got 1$"):
        read_section([b], {"enabled": 1}, "f.toml", "guard")
    n = Setting(name="gravity", kind="numbers", default=(0, 0, 0), help="", length=3, section="solver")
    with pytest.raises(SceneError, match=r"gravity must be a list of 3 numbers, got \[0, 1\]"):
        read_section([n], {"gravity": [0, 1]}, "f.toml", "solver")
    i = Setting(name="omega", kind="integer", default=1, help="", low=1, section="layers")
    with pytest.raises(SceneError, match=r"omega must be an integer >= 1, got 2.0"):  # no float of integer value
        read_section([i], {"omega": 2.0}, "f.toml", "layers")


@pytest.mark.parametrize("low,open_low,inside,outside", [
    (0.0, False, 1e-6, -1e-6), (0.0, True, 1e-6, -1e-6), (1.0, False, 1.000001, 0.999999)])
def test_bounds_allow_inside_and_refuse_outside_by_a_margin(low, open_low, inside, outside):
    s = Setting(name="x", kind="number", default=None, help="", low=low, open_low=open_low, high=low + 1.0)
    assert s.allows(inside) and not s.allows(outside)
    assert not s.allows(math.nan) and not s.allows(True) and not s.allows("1")
    assert s.range_text() == f"a number {'>' if open_low else '>='} {low:g} and <= {low + 1:g}"


def test_numpy_values_are_numbers_and_lists():
    # the Python API takes NumPy scalars and arrays where the declaration asks for numbers and
    # lists; a float of integer value is not an integer; an int too large for a float is refused
    import numpy as np

    from warpskin.solver import SolverParams

    SolverParams(iterations=np.int64(20), dt=np.float32(0.005), gravity=np.array([0.0, -9.81, 0.0])).check()
    with pytest.raises(SceneError, match=r"\[solver\] dt must be a positive number \[s\], got 0.0$"):
        SolverParams(dt=np.float32(0.0)).check()
    with pytest.raises(SceneError, match=r"\[solver\] iterations must be an integer >= 1, got 20.0$"):
        SolverParams(iterations=20.0).check()
    with pytest.raises(SceneError, match=r"gravity must be three finite numbers \[m/s\^2\], got \[0.0, 1.0\]$"):
        SolverParams(gravity=np.array([0.0, 1.0])).check()
    big = 10 ** 400
    assert not Setting(name="n", kind="integer", default=1, help="", low=1).allows(big)


def test_a_list_of_choices_takes_only_them(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text('[rig]\ngenerator = "arm"\n[joints]\nlayers = ["muscle", "marrow"]\n')
    with pytest.raises(SceneError, match=r"\[joints\] layers must be a list of 'skin', 'fat', 'muscle', 'bone', got "
                                         r"\['muscle', 'marrow'\]$"):
        load_scene(path).model_params()


def test_a_declared_field_copies_its_list_default():
    from dataclasses import dataclass

    @dataclass
    class P:
        names: list = setting(["a"], "strings", "names")

    one, two = P(), P()
    one.names.append("b")
    assert two.names == ["a"] and settings_of(P)[0].default == ["a"]


# ------------------------------------------------------------------------------ command line
def _actions():
    """Every (command, action) of the parser but help and version."""
    from warpskin.cli import build_parser

    parser = build_parser()
    out = [("warpskin", a) for a in parser._actions]
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        out += [(name, a) for a in p._actions]
    return [(c, a) for c, a in out if not isinstance(a, (argparse._HelpAction, argparse._VersionAction,
                                                        argparse._SubParsersAction))]


def test_every_command_line_option_comes_from_a_declaration():
    # each option (and positional) of every command is made from a declared setting: its
    # option strings, help and choices; one that stands for a scene key names it, and that key
    # is the scene section's declared one
    sections = scene_sections()
    actions = _actions()
    assert len(actions) > 100
    for command, a in actions:
        s = getattr(a, "setting", None)
        assert isinstance(s, Setting), (command, a.option_strings or a.dest)
        if a.option_strings:
            assert a.option_strings == list(s.cli), (command, a.option_strings)
        else:
            assert [a.dest] == list(s.cli), (command, a.dest)
        assert a.help.startswith((s.cli_help or s.help)[:40]), (command, a.option_strings)
        if s.choices:
            assert list(a.choices) == list(s.choices)
        if s.section:
            assert f"(scene: [{s.section}] {s.scene_key})" in a.help
            assert s in sections[s.section], (command, a.option_strings)  # the section's own declaration
            assert a.default is None or a.default == argparse.SUPPRESS or s.kind == "bool"


def test_command_line_numbers_refuse_what_the_declaration_does_not_allow():
    # an option made from a bounded number refuses a value outside the range, with the
    # declared words, and takes one inside
    checked = 0
    for command, a in _actions():
        s = a.setting
        if s.kind not in ("number", "integer") or s.parse is not None or _outside(s) is None:
            continue
        bad = _outside(s)
        with pytest.raises(argparse.ArgumentTypeError, match=rf"^{a.option_strings[-1]} must be "
                           + re.escape(s.range_text(unit=False)) + ", got "):
            a.type(str(int(bad) if s.kind == "integer" else bad))
        good = _number_inside(s)
        assert a.type(str(good)) == pytest.approx(good)
        checked += 1
    assert checked >= 15


def test_a_scene_option_sets_what_its_key_sets(tmp_path):
    # --iterations 7 and [solver] iterations = 7 give the same solver settings; --no-guard and
    # [guard] enabled = false the same guard
    from warpskin.cli import build_parser

    args = build_parser().parse_args(["simulate", "arm", "-o", "x.usdc", "--iterations", "7", "--dt", "0.004",
                                      "--no-guard", "--clip", "flex", "--frames", "2:9"])
    assert (args.iterations, args.dt, args.no_guard, args.clip, args.frames) == (7, 0.004, True, "flex", (2, 9))
    path = tmp_path / "t.toml"
    path.write_text('[rig]\ngenerator = "arm"\n[animation]\nclip = "flex"\nframes = [2, 9]\n'
                    '[solver]\niterations = 7\ndt = 0.004\n[guard]\nenabled = false\n')
    scene = load_scene(path)
    assert (scene.solver_params().iterations, scene.solver_params().dt) == (args.iterations, args.dt)
    assert scene.guard_params().enabled is (not args.no_guard)
    assert (scene.clip, scene.frames) == (args.clip, args.frames)

"""The exception hierarchy and the CLI's exit status: 2 for bad input or usage (one line naming
the file, key or option), 3 for a run that failed (the frames before it kept), 1 only for a bug
(with the hint to rerun with --debug)."""

from __future__ import annotations

import importlib

import pytest
from pxr import Usd, UsdGeom

import warpskin
from warpskin.cli import main
from warpskin.errors import InputError, OutputError, RigError, SceneError, SimulationError, WarpskinError
from oracles import prim

COARSE = "[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 16\nsegments = 12\n[animation]\nclip = 'flex'\nfps = 30\n"


def test_hierarchy_tells_input_from_failure():
    for cls in (RigError, SceneError, OutputError):
        assert issubclass(cls, InputError) and issubclass(cls, WarpskinError) and cls.exit_code == 2
    assert issubclass(SimulationError, WarpskinError) and not issubclass(SimulationError, InputError)
    assert SimulationError.exit_code == 3
    assert not issubclass(SceneError, RigError) and not issubclass(RigError, SceneError)
    assert warpskin.WarpskinError is WarpskinError and warpskin.SimulationError is SimulationError
    from warpskin.io.usd_export import ExportError
    from warpskin.solver import SimulationError as from_solver

    assert issubclass(ExportError, OutputError) and from_solver is SimulationError


def test_the_package_is_importable_once():
    # a checkout's root must not be on warpskin's own search path: no second copy as warpskin.warpskin
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("warpskin.warpskin")
    from warpskin import kernels

    assert kernels.__name__ == "warpskin.kernels"


def _one_line(err: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("warpskin:")]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def test_bad_scene_key_exits_2_naming_file_and_key(tmp_path, capsys):
    p = tmp_path / "bad.toml"
    p.write_text(COARSE + "[solver]\ndt = -0.01\n")
    assert main(["simulate", str(p), "-o", str(tmp_path / "o.usdc"), "--quiet"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(p) in line and "dt must be a positive" in line


def test_missing_rig_file_exits_2(tmp_path, capsys):
    assert main(["skin", str(tmp_path / "nope.glb"), "-o", str(tmp_path / "o.usdc"), "--quiet"]) == 2
    assert "nope.glb" in _one_line(capsys.readouterr().err)


def test_bad_frames_option_exits_2(tmp_path, capsys):
    # a usage error: one error line naming the option, then where the options are listed (not
    # argparse's whole usage first)
    assert main(["skin", "arm", "-o", str(tmp_path / "o.usdc"), "--frames", "5:2", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "usage:" not in err
    assert err.strip().splitlines() == ["warpskin skin: error: argument --frames: --frames 5:2: need 0 <= FIRST <= LAST",
                                        "(options: warpskin skin --help)"]


def test_failed_run_exits_3_and_keeps_the_frames_before_it(tmp_path, capsys, monkeypatch):
    from warpskin.run import physics

    original = physics.PhysicsStepper.advance

    def failing(self, i):
        if i == 3:
            raise SimulationError("frame 3: particle 7 (skin layer, vertex 7) became NaN or inf; lower dt")
        original(self, i)

    monkeypatch.setattr(physics.PhysicsStepper, "advance", failing)
    p = tmp_path / "arm.toml"
    p.write_text(COARSE)
    out = tmp_path / "o.usdc"
    assert main(["simulate", str(p), "-o", str(out), "--frames", "0:6", "--quiet"]) == 3
    line = _one_line(capsys.readouterr().err)
    assert "simulation failed: frame 3" in line and "3 frames before it were written" in line
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]


def test_a_bug_exits_1_with_the_debug_hint(tmp_path, capsys, monkeypatch):
    from warpskin import skinning

    def broken(*args, **kwargs):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(skinning.Skinner, "skin", broken)
    assert main(["skin", "arm", "-o", str(tmp_path / "o.usdc"), "--quiet"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "internal error: ZeroDivisionError" in line and "--debug" in line
    assert not list(tmp_path.iterdir())  # nothing half-written, no temp file
    with pytest.raises(ZeroDivisionError):
        main(["--debug", "skin", "arm", "-o", str(tmp_path / "o.usdc"), "--quiet"])


def test_every_subpackage_is_installed():
    # pyproject lists the packages explicitly (kernels/ and scenes/ are mapped into warpskin):
    # a subpackage missing there imports from a checkout but not from `pip install .`
    import sys
    from pathlib import Path

    if sys.version_info >= (3, 11):
        import tomllib
    else:  # pragma: no cover
        import tomli as tomllib

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(root).parts) for p in (root / "warpskin").rglob("__init__.py")}
    found |= {"warpskin.kernels", "warpskin.scenes"}
    assert found == listed


def test_load_scene_refuses_a_rig_file_or_binary_with_one_line(tmp_path):
    from warpskin.scene import load_scene

    (tmp_path / "fox.glb").write_bytes(b"glTF\x02\x00\x00\x00\xec")
    with pytest.raises(SceneError, match="a rig file, not a scene"):
        load_scene(tmp_path / "fox.glb")
    p = tmp_path / "scene.toml"
    p.write_bytes(b"\xec\xff\x00 not text")
    with pytest.raises(SceneError, match="not a TOML scene file"):
        load_scene(p)


def test_a_rig_under_another_extension_is_told_what_it_looks_like(tmp_path, capsys):
    # a binary glTF named .txt: one line saying what it looks like and the extensions taken
    from gltf_builder import write_rig_glb
    from warpskin.scenes.arm import make_arm

    glb = write_rig_glb(make_arm(rings=8, segments=8), tmp_path / "arm.glb")
    wrong = tmp_path / "arm.txt"
    wrong.write_bytes(glb.read_bytes())
    assert main(["info", str(wrong)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert "arm.txt: not a TOML scene file" in err and "looks like binary glTF: rename it to .glb" in err
    assert ".usdz" in err

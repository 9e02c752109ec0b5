"""Bakes in a real DCC and under usd-core's validators.

* Every kind of output passes every validator usd-core registers (``UsdValidation``).
* Blender (its Python module ``bpy``, in its own virtual environment: ``.venv-bpy``, which the
  README's test command and ``.ci/run`` create) imports a CesiumMan bake and an arm bake with
  ``bpy.ops.wm.usd_import``; the mesh evaluated through the depsgraph at several frames has the
  file's points, UVs, frame range and rate.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdValidation

from oracles import prim
from warpskin.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _validate(path: Path) -> list[str]:
    reg = UsdValidation.ValidationRegistry()
    validators = [reg.GetOrLoadValidatorByName(m.name) for m in reg.GetAllValidatorMetadata()]
    stage = Usd.Stage.Open(str(path))
    errors = UsdValidation.ValidationContext([v for v in validators if v]).Validate(stage)
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors if e.GetType() == UsdValidation.ValidationErrorType.Error]


OUTPUTS = {
    "skin_arm": ["skin", "arm", "--frames", "0:2", "--with-rest"],
    "skin_dqs_cesium": ["skin", "{assets}/CesiumMan/CesiumMan.glb", "--method", "dqs", "--with-lbs", "--frames", "1:3"],
    "skin_two_materials": ["skin", "{assets}/RobotExpressive/RobotExpressive.glb", "--frames", "0:2"],
    "simulate_arm": ["simulate", "arm", "--frames", "0:2", "--lbs", "--layers"],
    "simulate_fox": ["simulate", "{assets}/Fox/Fox.glb", "--frames", "0:1", "--lbs"],
    "pop": ["pop", "popping_arm", "--frames", "0:2"],
    "layers": ["layers", "arm"],
}


@pytest.mark.parametrize("name", sorted(OUTPUTS))
def test_every_kind_of_output_passes_usd_validation(name, tmp_path, request):
    args = OUTPUTS[name]
    if any("{assets}" in a for a in args):
        assets = request.getfixturevalue("assets")
        args = [a.format(assets=assets) for a in args]
    out = tmp_path / f"{name}.usdc"
    quiet = [] if name == "layers" else ["--quiet"]
    assert main([*args, "-o", str(out), *quiet]) == 0
    assert _validate(out) == []


# --------------------------------------------------------------------------------------------
# Blender
# --------------------------------------------------------------------------------------------
BLENDER_SCRIPT = r"""
import bpy, json, sys
path, frames, guides = sys.argv[1], [int(f) for f in sys.argv[2].split(",")], sys.argv[3] == "guides"
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=path, import_guide=guides)
scene = bpy.context.scene
out = {"fps": scene.render.fps / scene.render.fps_base, "frame_start": scene.frame_start,
       "frame_end": scene.frame_end, "objects": {}}
for frame in frames:
    scene.frame_set(frame)
    graph = bpy.context.evaluated_depsgraph_get()
    for obj in scene.objects:
        if obj.type != "MESH":
            continue
        ev = obj.evaluated_get(graph)
        mesh = ev.to_mesh()
        entry = out["objects"].setdefault(obj.name, {"points": {}})
        entry["points"][str(frame)] = [list(ev.matrix_world @ v.co) for v in mesh.vertices]
        if "loops" not in entry:
            layer = mesh.uv_layers.active
            entry["uv"] = [list(d.uv) for d in layer.data] if layer else None
            entry["loops"] = [loop.vertex_index for loop in mesh.loops]
            entry["materials"] = [s.material.name for s in obj.material_slots if s.material]
        ev.to_mesh_clear()
print("JSON:" + json.dumps(out))
"""


def _blender_python() -> Path:
    given = os.environ.get("WARPSKIN_BPY_PYTHON")
    path = Path(given) if given else ROOT / ".venv-bpy" / "bin" / "python"
    if not path.is_file():
        pytest.skip(f"Blender's bpy is not installed at {path}: the README's test command creates it "
                    "(python3 -m venv .venv-bpy && .venv-bpy/bin/pip install bpy)")
    return path


def _import_in_blender(tmp_path: Path, usd: Path, frames: list[int], *, guides: bool = False) -> dict:
    script = tmp_path / "import_usd.py"
    script.write_text(BLENDER_SCRIPT)
    run = subprocess.run([str(_blender_python()), str(script), str(usd), ",".join(map(str, frames)),
                          "guides" if guides else "no-guides"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    line = next(ln for ln in run.stdout.splitlines() if ln.startswith("JSON:"))
    out = json.loads(line[5:])
    out["log"] = run.stdout + run.stderr
    return out


def _usd_y_up(blender_points) -> np.ndarray:
    """Blender's Z-up world back to the bake's Y-up stage (its importer turns the root +90
    degrees about X)."""
    b = np.asarray(blender_points, dtype=np.float64)
    return np.stack([b[:, 0], b[:, 2], -b[:, 1]], axis=1)


@pytest.mark.parametrize("kind", ["cesium_skin", "arm_simulate"])
@pytest.mark.slow
def test_blender_imports_a_bake_as_written(kind, tmp_path, request):
    if kind == "cesium_skin":
        assets = request.getfixturevalue("assets")
        args, frames, first_last = ["skin", str(assets / "CesiumMan" / "CesiumMan.glb")], [1, 17, 48], (1, 48)
    else:
        args, frames, first_last = ["simulate", "arm", "--frames", "0:12"], [0, 6, 12], (0, 12)
    out = tmp_path / f"{kind}.usdc"
    assert main([*args, "-o", str(out), "--quiet"]) == 0
    got = _import_in_blender(tmp_path, out, frames)
    assert (got["frame_start"], got["frame_end"]) == first_last  # Blender's timeline is the bake's
    # Blender reads frame f at time code f; its importer (5.0) keeps the scene's own rate (24 fps),
    # which is CesiumMan's: a 30 fps bake (the arm) plays right once the scene's rate is set to
    # the stage's (the README says so), or baked with --fps 24
    rate = Usd.Stage.Open(str(out)).GetFramesPerSecond()
    if kind == "cesium_skin":
        assert got["fps"] == rate == 24.0
    else:
        assert rate == 30.0
    stage = Usd.Stage.Open(str(out))
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    obj = got["objects"][mesh.GetPrim().GetName()]  # the skin keeps its file's mesh name
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    assert obj["loops"] == faces.tolist()
    size = float(np.linalg.norm(np.ptp(np.asarray(mesh.GetPointsAttr().Get(frames[0])), axis=0)))
    for f in frames:
        want = np.asarray(mesh.GetPointsAttr().Get(f), dtype=np.float64)
        assert np.abs(_usd_y_up(obj["points"][str(f)]) - want).max() < 1e-6 * size, f"frame {f}"
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    if kind == "cesium_skin":
        np.testing.assert_allclose(np.asarray(obj["uv"]), np.asarray(st.Get()), atol=1e-6)
        assert obj["materials"] == ["Cesium_Man_effect"]
    else:
        assert not st  # a procedural arm has no UVs


@pytest.mark.slow
def test_a_caged_bake_with_its_guides_imports_into_blender(tmp_path, assets):
    # RobotExpressive through its cage with every mesh's LBS guide and the cage: Blender imports
    # it with guides on (a segfault was reported here), reports no invalid face data (the file's
    # Foot.L and Foot.R hold a triangle that repeats a vertex: not written), and every mesh,
    # guides included, has the file's points
    out = tmp_path / "robot.usdc"
    assert main(["simulate", str(assets / "RobotExpressive" / "RobotExpressive.glb"), "--cage", "always", "--lbs",
                 "--clip", "Walking", "--frames", "0:2", "--preroll", "0", "-o", str(out), "--quiet"]) == 0
    got = _import_in_blender(tmp_path, out, [0, 2], guides=True)  # (no pre-roll: the file, not the motion, is tested)
    assert "Invalid face data" not in got["log"]
    stage = Usd.Stage.Open(str(out))
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.GetDefaultPrim().GetChildren() if p.IsA(UsdGeom.Mesh)}
    assert len(meshes) == 14 + 14 + 1  # the meshes, their LBS guides, the cage
    assert set(meshes) <= set(got["objects"])
    for name, mesh in meshes.items():
        want = np.asarray(mesh.GetPointsAttr().Get(2), dtype=np.float64)
        size = float(np.linalg.norm(np.ptp(want, axis=0)))
        assert np.abs(_usd_y_up(got["objects"][name]["points"]["2"]) - want).max() < 1e-5 * size, name
        faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])), name


def test_render_captions_give_the_offset_as_a_share_of_the_height(tmp_path):
    # the caption's offset is a share of the character's height, so a file in centimetres (the
    # Fox: 155 units tall, offsets of a few units) reads as one in metres does; the height is
    # the largest extent of the physical meshes' rest points, found from the bake itself
    from warpskin.render import _captions, _height, bake_pairs

    series = {"fox": {"strained": [0.0, 0.01], "strained_lbs": [0.0, 0.02], "flipped": [0.0, 0.003],
                      "offset": [0.0, 5.479]}}
    caps = _captions("fox", 1.0, 1, series, True, 155.0)
    assert caps[0][1].endswith(f"offset {100 * 5.479 / 155.0:.1f} % of the height")
    small = {"fox": dict(series["fox"], offset=[0.0, 0.05479])}
    assert _captions("fox", 1.0, 1, small, True, 1.55) == caps

    bake = tmp_path / "arm.usdc"
    assert main(["simulate", "arm", "-o", str(bake), "--frames", "0:1", "--lbs", "--quiet"]) == 0
    stage = Usd.Stage.Open(str(bake))
    (pair,) = bake_pairs(stage)
    rest = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath(pair.physical)).GetPointsAttr().Get(), dtype=np.float64)
    assert _height(stage, [pair]) == pytest.approx(float((rest.max(axis=0) - rest.min(axis=0)).max()))


@pytest.fixture(scope="module")
def arm_bake(tmp_path_factory):
    """A short bake of the coarse arm, with its LBS: frames 40-46 of its flex."""
    tmp = tmp_path_factory.mktemp("arm")
    scene = tmp / "arm.toml"
    scene.write_text("[rig]\ngenerator = 'arm'\n[rig.params]\nrings = 30\nsegments = 20\n"
                     "[animation]\nclip = 'flex'\nfps = 30\nframes = [40, 46]\n[solver]\niterations = 8\ntether_max = 0.08\n")
    bake = tmp / "arm.usdc"
    assert main(["simulate", str(scene), "-o", str(bake), "--lbs", "--quiet"]) == 0
    return bake


def test_the_render_script_draws_physical_beside_lbs(tmp_path, arm_bake):
    # the short bake of the coarse arm, rendered by warpskin render in Blender: the worst frame
    # and one more, and a close-up; each picture has two panels of the same size that differ
    # (the physical skin and LBS) on a white page with something drawn on it
    from PIL import Image

    from warpskin.render import render_bake

    paths = render_bake(arm_bake, tmp_path / "pictures", extra=1, resolution=(320, 240),
                        python=str(_blender_python()), progress=False)
    assert len(paths) == 3 and all(p.is_file() for p in paths)
    for p in paths:
        img = np.asarray(Image.open(p).convert("RGB"), dtype=np.float64) / 255.0
        assert img.shape == (240, 640, 3)
        left, right = img[:, :320], img[:, 320:]
        assert np.median(img) > 0.9  # a white page
        for panel in (left, right):
            assert (panel.min(axis=2) < 0.8).mean() > 0.01  # a mesh is drawn
        assert np.abs(left - right).mean() > 1e-3  # two different colours, two different shapes


def test_the_render_colours_what_moves_against_lbs(tmp_path, arm_bake):
    # --color motion: the physical skin drawn white where it moves with LBS and orange to red
    # where it moves against it since the previous frame (the arm's jiggle as it flexes),
    # against the USD samples themselves: the reddest pixels are where the motion is largest;
    # the LBS panel keeps its plain blue; the caption gives the scale
    from PIL import Image

    from warpskin.errors import InputError
    from warpskin.render import bake_pairs, render_bake

    stage = Usd.Stage.Open(str(arm_bake))
    pair = bake_pairs(stage)[0]
    phys, lbs = (UsdGeom.Mesh(stage.GetPrimAtPath(p)).GetPointsAttr() for p in (pair.physical, pair.lbs))
    moved = [np.linalg.norm((np.asarray(phys.Get(t)) - np.asarray(lbs.Get(t)))
                            - (np.asarray(phys.Get(t - 1)) - np.asarray(lbs.Get(t - 1))), axis=1).max()
             for t in range(41, 47)]
    frame = 41 + int(np.argmax(moved))
    assert max(moved) > 0.0
    path, = render_bake(arm_bake, tmp_path / "pictures", frames=[frame], close_up=False, resolution=(320, 240),
                        python=str(_blender_python()), progress=False, color="motion")
    img = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64) / 255.0
    left, right = img[:, :320], img[:, 320:]
    warm = left[..., 0] - left[..., 2] > 0.4  # orange to red (the plain skin tan: at most 0.37, lit)
    assert warm.mean() > 1e-3
    assert (right[..., 2] - right[..., 0] > 0.1).mean() > 0.01 and (right[..., 0] - right[..., 2] > 0.25).mean() == 0.0
    assert (left.max(axis=2) < 0.3).mean() > 1e-4  # dark caption text
    with pytest.raises(InputError, match="color must be one of plain, offset, motion"):
        render_bake(arm_bake, tmp_path / "pictures", color="speed", python=str(_blender_python()))

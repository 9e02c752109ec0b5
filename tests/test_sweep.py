"""A sweep of the settings a user changes first (the step, the tissue's stiffness, the clip)
over shared characters at sizes of 1e-3 to 1e3 in their file: every run ends with exit 0, or
with a deliberate exit 3 that names its frame and keeps the frames before it; a run that ends
is never written worse than LBS on volume, intersecting pairs beyond the rest pose's or strained
edges, and stays within the tether's cap of it. One combination per row (not the full product:
each run is a few frames, the rows cover every value of every axis), and the procedural arm's
150-degree flex at 0.02 s steps (split into the steps gravity allows)."""

from __future__ import annotations

import dataclasses

import re
import warnings

import pytest

pytestmark = pytest.mark.slow

# (asset, clip, frames, unit scale, largest substep [s] or None, fat stiffness or None)
ROWS = [
    ("CesiumMan/CesiumMan.glb", None, (1, 8), 1e-3, None, None),
    ("CesiumMan/CesiumMan.glb", None, (1, 8), 1e3, 0.02, None),
    ("Fox/Fox.glb", "Walk", (0, 8), None, 0.02, None),
    ("Fox/Fox.glb", "Run", (0, 8), 1e-3, None, 0.1),
    ("RiggedFigure/RiggedFigure.glb", None, (0, 8), 1e3, None, 0.1),
    ("RiggedFigure/RiggedFigure.glb", None, (0, 8), None, 0.02, None),
    ("arm", None, (0, 60), None, 0.02, None),  # the shipped scene: its flex to 150 degrees
]


@pytest.mark.parametrize("asset, clip, frames, scale, dt, fat", ROWS)
def test_a_sweep_ends_well_or_stops_on_purpose(tmp_path, request, asset, clip, frames, scale, dt, fat):
    from warpskin.errors import SimulationError
    from warpskin.run import simulate
    from warpskin.scene import Scene, load_scene
    from warpskin.units import HUMAN_SIZE, extent

    if asset == "arm":  # shipped: no assets needed
        scene = load_scene(asset)
    else:
        scene = Scene.from_rig_file(request.getfixturevalue("assets") / asset, clip=clip, unit_scale=scale)
    params = scene.solver_params()
    if dt is not None:
        params = dataclasses.replace(params, dt=dt)
    if fat is not None:  # softer fat than the default: [layers] stiffness = [skin, fat, muscle, bone]
        stiffness = list(scene.model_params().stiffness)
        stiffness[1] = fat
        scene.extra.setdefault("layers", {})["stiffness"] = stiffness
        assert scene.model_params().stiffness[1] == fat
    out = tmp_path / "sweep.usdc"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            run = simulate(scene, out, device="cpu", progress=False, frames=frames, solver_params=params)
        except SimulationError as exc:  # a deliberate stop: the frame named, the frames before it kept
            kept = re.search(r"^frame (\d+): .*\((\d+) frames before it were written to ", str(exc))
            assert kept is not None, str(exc)
            assert int(kept.group(2)) == int(kept.group(1)) - frames[0] and out.is_file()
            return
    s = run.summary
    assert s["frames"] == frames[1] - frames[0] + 1
    for mesh, d in s["delivered"].items():
        w = s["written"][mesh]
        print(mesh, {k: round(v, 4) for k, v in d.items() if isinstance(v, float)}, w.get("max_pairs_new"),
              w.get("max_pairs_new_lbs"))
        assert d["volume"] <= d["volume_lbs"] + 1e-3
        assert w["max_pairs_new"] <= w["max_pairs_new_lbs"]
        assert w["max_strained_excess"] <= 0.005
        cap = max(params.tether_max, params.tether_contact)  # the skin in contact reaches farther
        assert w["max_offset"] <= cap * s["body_diagonal_m"] * (1 + 1e-4) + 1e-12
    # the unit physics takes the file in brings it nearest human size, within a factor of sqrt(10)
    size = extent(scene.rig().vertices) * s["length_unit_m"]
    assert HUMAN_SIZE / 10 ** 0.5 <= size <= HUMAN_SIZE * 10 ** 0.5

"""Layered popping: the activation drives the multi-layer model's rest shape; the skin pops,
the bones stay, the volume holds."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpskin.popping import BeatSpec
from warpskin.run import run_popping
from warpskin.rig import RigError
from warpskin.scene import load_scene
from oracles import prim

SCENE = """[rig]
generator = "popping_arm"
[rig.params]
hold_degrees = 100.0
duration = 1.2
rings = 30
segments = 20
[animation]
clip = "pop"
fps = 30
[solver]
iterations = 10
[popping]
mode = "layered"
[popping.activation.biceps]
keys = [[0.3, 0.0], [0.35, 1.0], [0.9, 1.0], [0.95, 0.0]]
"""


@pytest.mark.slow
def test_layered_mode_pops_the_skin_and_keeps_the_volume(tmp_path, device):
    path = tmp_path / "pop.toml"
    path.write_text(SCENE)
    run = run_popping(load_scene(path), tmp_path / "pop.usdc", device=device, progress=False)
    s = run.summary
    assert s["mode"] == "layered" and run.frames == 37
    assert s["max_volume_deviation"] < 0.009  # the solver issue's bound (the paper: 0.9 %)
    scene = load_scene(path)
    rig = scene.rig()
    stage = Usd.Stage.Open(str(run.path))
    skin = UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr()
    lbs = UsdGeom.Mesh(prim(stage, "lbs")).GetPointsAttr()
    assert np.array_equal(np.array(lbs.Get(5)), np.array(lbs.Get(30)))  # the bones never move
    g = rig.joint_world_transforms("pop", scene.frame_time(5))
    a0, a1 = g[0, :3, 3], g[1, :3, 3]
    u = (a1 - a0) / np.linalg.norm(a1 - a0)

    def radius(points):
        d = np.asarray(points, dtype=np.float64) - a0
        return np.linalg.norm(d - np.outer(d @ u, u), axis=1)

    biceps = (rig.vertices[:, 0] > 0.1) & (rig.vertices[:, 0] < 0.24) & (rig.vertices[:, 1] > 0.02)
    relaxed = radius(skin.Get(8))[biceps].mean()  # t = 0.27 s: before the pop, settled
    clenched = radius(skin.Get(26))[biceps].mean()  # t = 0.87 s: clenched for half a second
    after = radius(skin.Get(36))[biceps].mean()  # t = 1.2 s: relaxed again
    print(f"biceps skin radius: relaxed {1e3 * relaxed:.2f} mm, clenched {1e3 * clenched:.2f} mm, after {1e3 * after:.2f} mm")
    assert clenched - relaxed > 2e-3  # the activation changes the skin: a bulge of millimetres
    assert abs(after - relaxed) < 0.5 * (clenched - relaxed)  # and it goes back


def test_layered_mode_pops_on_the_beat(tmp_path, device):
    # the scene's keys replaced by a tempo: one pop at 0.31 s held 0.6 s (30 bpm, the next beat
    # past the frames), the skin over the biceps out while clenched and not before
    path = tmp_path / "pop.toml"
    path.write_text(SCENE)
    run = run_popping(load_scene(path), tmp_path / "beat.usdc", device=device, progress=False, frames=(0, 26),
                      normal_guide=False,
                      beats=BeatSpec(bpm=30.0, offset=0.31, hold=0.6, groups=["biceps"]))
    assert run.summary["mode"] == "layered" and run.frames == 27
    scene = load_scene(path)
    rig = scene.rig()
    stage = Usd.Stage.Open(str(run.path))
    skin = UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr()
    g = rig.joint_world_transforms("pop", scene.frame_time(5))
    a0, a1 = g[0, :3, 3], g[1, :3, 3]
    u = (a1 - a0) / np.linalg.norm(a1 - a0)
    biceps = (rig.vertices[:, 0] > 0.1) & (rig.vertices[:, 0] < 0.24) & (rig.vertices[:, 1] > 0.02)

    def radius(frame):  # the biceps skin's mean distance from the upper arm's axis [m]
        d = np.asarray(skin.Get(frame), dtype=np.float64) - a0
        return np.linalg.norm(d - np.outer(d @ u, u), axis=1)[biceps].mean()

    bulge = radius(26) - radius(8)
    assert bulge > 2e-3  # clenched since 0.31 s (frame 9.3): millimetres out
    assert abs(radius(8) - radius(5)) < 0.2 * bulge  # before the beat only the physics settling


def test_layered_mode_rejects_unknown_layers(tmp_path):
    from warpskin.model import SkinModelBuilder
    from warpskin.popping import examples_for_scene, muscle_rest_offset_deltas

    path = tmp_path / "pop.toml"
    path.write_text(SCENE)
    scene = load_scene(path)
    with pytest.raises(RigError, match="cannot be moved by the muscles"):
        muscle_rest_offset_deltas(SkinModelBuilder(scene.rig()), examples_for_scene(scene),
                                  scene.rig().skinning_matrices("pop", 0.5), layers=("bone",))


def test_layered_deltas_of_a_refined_skin_carry_the_examples_to_the_midpoints(tmp_path):
    # a skin refined for the simulation (every edge longer than its mean split): the examples
    # are of the file's vertices; each added vertex's clenched displacement is its parents'
    # mean (a loop as the reference), and the region offsets change by the formula
    from warpskin.model import ModelParams, SkinModelBuilder
    from warpskin.popping import examples_for_scene, muscle_rest_offset_deltas
    from warpskin.popping.pose_space import PoseSpaceDeformer

    path = tmp_path / "pop.toml"
    path.write_text(SCENE)
    scene = load_scene(path)
    rig = scene.rig()
    e = np.sort(np.concatenate([rig.triangles[:, [0, 1]], rig.triangles[:, [1, 2]], rig.triangles[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    mean_edge = float(np.linalg.norm(rig.vertices[e[:, 0]] - rig.vertices[e[:, 1]], axis=1).mean())
    builder = SkinModelBuilder(rig, ModelParams(max_edge=mean_edge)).build()
    assert builder.rig.vertex_count > rig.vertex_count
    examples = examples_for_scene(scene)
    mats = rig.skinning_matrices("pop", 0.5)
    got = muscle_rest_offset_deltas(builder, examples, mats)
    _, group_w = PoseSpaceDeformer(rig, examples, device="cpu").weights(mats)
    v = builder.rig.vertex_count
    reg = builder.regions
    region_of = reg.region_of_entry()
    m = builder.masses[reg.region_members]
    for g in range(examples.group_count):
        disp = list(np.einsum("e,evc->vc", group_w[g], examples.clenched_disparities[g]))
        for a, b in builder.rig.vertex_parents:
            disp.append(0.5 * (disp[a] + disp[b]))
        dx0 = np.concatenate([np.array(disp)] * 3 + [np.zeros((v, 3))])  # skin, fat, muscle move; bone stays
        dm = dx0[reg.region_members]
        dcom = np.zeros((reg.region_count, 3))
        np.add.at(dcom, region_of, m[:, None] * dm)
        dcom /= reg.region_mass[:, None]
        np.testing.assert_allclose(got[g], dm - dcom[region_of], atol=1e-12)
    assert np.abs(got).max() > 1e-4  # the clenched biceps moves something

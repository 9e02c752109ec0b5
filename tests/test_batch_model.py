"""Several characters in one model (:func:`warpskin.batch_model.batch_model`): one launch per
kernel steps them all, and on the CPU each character's particles are bit for bit what it gets
simulated alone (the reference: the same builder's model, stepped by itself)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oracles import coarse_arm
from warpskin.batch_model import batch_model
from warpskin.collision import CollisionParams
from warpskin.errors import InputError
from warpskin.model import ModelParams, SkinModelBuilder
from warpskin.run.physics import initial_state
from warpskin.solver import SkinSolver, SolverParams

STEPS = 12
DT = 1.0 / 200.0


def _builders(collision: CollisionParams | None = None, other: CollisionParams | None = None, refine: bool = False):
    """Three characters nobody made alike: the coarse arm, a thicker and longer arm of other
    resolution with other stiffnesses and tissue density (and collision ``other``; with
    ``refine``, simulated on a refined copy of its coarse mesh), and the first again (an
    instance)."""
    col = collision or CollisionParams(enabled=False)
    a = SkinModelBuilder(coarse_arm(), ModelParams(collision=col, refine=False))
    b = SkinModelBuilder(coarse_arm(rings=23, segments=13, biceps_radius=0.061, upper_length=0.337),
                         ModelParams(collision=other or col, refine=refine, stiffness=(0.7, 0.5, 0.6, 0.9),
                                     density=1070.0))
    c = SkinModelBuilder(coarse_arm(), ModelParams(collision=col, refine=False))
    return [a, b, c]


def _clip_poses(rig, steps: int, phase: float) -> list[np.ndarray]:
    clip = next(iter(rig.clips.values()))
    return [rig.skinning_matrices(clip, phase + (s + 1) * DT * 20.0) for s in range(steps)]


def _run(model, poses: list[np.ndarray], contacted: list | None = None, start=None) -> tuple[np.ndarray, np.ndarray]:
    """``(x, v)`` after stepping ``model`` from rest (or from ``start(state)``) through
    ``poses``, one step each; with ``contacted``, each step's point-triangle contact count is
    appended to it."""
    solver = SkinSolver(model, SolverParams(iterations=6))
    a, b, control = model.state(), model.state(), model.control()
    if start is not None:
        start(a)
    contacts = model.contacts(capacity=1 << 15)  # the same buffers alone and batched, none overflows
    for m in poses:
        control.set_pose(m)
        solver.step(a, b, control, contacts, DT)
        if contacts is not None:
            assert not contacts.overflowed()
            if contacted is not None:
                contacted.append(int(contacts.counts.numpy()[0]))
        a, b = b, a
    return a.x.numpy(), a.v.numpy()


def test_each_character_of_a_batch_steps_bit_for_bit_as_alone(device):
    # on the CPU bit for bit; on CUDA the atomic sums' order is free: to float rounding
    builders = _builders()
    phases = [0.4, 0.9, 1.7]  # each its own moment of its clip
    poses = [_clip_poses(b.build().rig, STEPS, ph) for b, ph in zip(builders, phases)]
    batch = batch_model(builders, device)
    assert [r.vertex_count for r in batch.characters] == [b.rig.vertex_count for b in builders]
    assert batch.vertex_count == sum(b.rig.vertex_count for b in builders)
    x, v = _run(batch, [np.concatenate([p[s] for p in poses]) for s in range(STEPS)])
    for b, p, r in zip(builders, poses, batch.characters):
        alone_x, alone_v = _run(b.finalize(device), p)
        mine = r.particles(batch.vertex_count)
        assert np.abs(alone_x - b.layers.flat()).max() > 0.05  # it moved [m]
        if str(device) == "cpu":
            assert np.array_equal(x[mine], alone_x)
            assert np.array_equal(v[mine], alone_v)
        else:
            assert np.allclose(x[mine], alone_x, atol=1e-5)


def test_contacts_stay_within_each_character_and_each_steps_as_alone(device):
    # the arms flexed past 100 degrees press the forearm on the biceps (point-triangle contacts
    # every step); two of them overlap in space (instances at one place), so a contact between
    # characters would be found if the trees were shared; the second arm has its own contact
    # thickness (its mesh's: 0.15 x its mean edge), friction and restitution, and is simulated
    # on a refined copy of its coarse mesh (the written mesh's volume and fail-safe are its
    # own): each character's particles are still bit for bit its own run's (CPU)
    col = CollisionParams(thickness=0.0031)
    builders = _builders(col, CollisionParams(friction=0.37, restitution=0.21), refine=True)
    assert builders[1].build().rig.refined_skin  # its written mesh is the coarse one: its own fail-safe and volume
    phases = [1.45, 1.6, 1.52]  # near the peak flexion (1.5 s)
    poses = [_clip_poses(b.build().rig, STEPS, ph) for b, ph in zip(builders, phases)]
    batch = batch_model(builders, device)
    assert batch.collision is not None
    thick = [c["thickness"] for c in batch.collision.characters]
    assert thick[0] == thick[2] == 0.0031 and abs(thick[1] - 0.0031) > 1e-4
    contacted: list = []
    x, v = _run(batch, [np.concatenate([p[s] for p in poses]) for s in range(STEPS)], contacted)
    assert np.count_nonzero(contacted) >= STEPS - 1  # contacts in (nearly) every step
    for b, p, r in zip(builders, poses, batch.characters):
        alone: list = []
        alone_x, alone_v = _run(b.finalize(device), p, alone)
        assert np.count_nonzero(alone) >= STEPS - 1
        mine = r.particles(batch.vertex_count)
        if str(device) == "cpu":
            assert np.array_equal(x[mine], alone_x)
            assert np.array_equal(v[mine], alone_v)
        else:
            assert np.allclose(x[mine], alone_x, atol=1e-5)


def test_a_batch_refuses_what_it_does_not_lay_out_in_one_line():
    mixed = [SkinModelBuilder(coarse_arm(), ModelParams(refine=False)),
             SkinModelBuilder(coarse_arm(rings=23), ModelParams(refine=False, collision=CollisionParams(passes=2)))]
    with pytest.raises(InputError, match=r"one \[collision\] passes: character 0 \(.*\) has 4, character 1 \(.*\) 2"):
        batch_model(mixed, "cpu")
    off = CollisionParams(enabled=False)
    mixed = [SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False)),
             SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False, volume=False))]
    with pytest.raises(InputError, match="all need sub-volumes or none; character 1"):
        batch_model(mixed, "cpu")
    with pytest.raises(InputError, match="one coupling stiffness"):
        batch_model([SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False)),
                     SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False, coupling_stiffness=0.5))],
                    "cpu")
    with pytest.raises(InputError, match="at least one character"):
        batch_model([], "cpu")
    with pytest.raises(InputError, match="character 1: expected a SkinModelBuilder .*, got Rig"):
        batch_model([SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False)), coarse_arm()], "cpu")
    driven = SkinModelBuilder(coarse_arm(), ModelParams(collision=off, refine=False))
    driven.set_rest_drive(np.zeros((1, driven.build().regions.region_members.shape[0], 3)))
    with pytest.raises(InputError, match=r"character 0 \(.*\): a rest-shape drive \(layered popping\) is not batched"):
        batch_model([driven], "cpu")


def test_initial_state_skins_each_character_of_a_batch_with_its_own_joints():
    # one path for one model and a batch: the batch's state at its characters' poses is each
    # one's own LBS (NumPy, from its rig's weights), and matrices for another joint count are
    # refused in one line
    from warpskin.transforms import linear_blend_skin

    off = CollisionParams(enabled=False)
    rigs = [coarse_arm(), coarse_arm(rings=23)]
    builders = [SkinModelBuilder(r, ModelParams(collision=off, refine=False)) for r in rigs]
    batch = batch_model(builders, "cpu")
    assert [r.joint_start for r in batch.rest] == [0, rigs[0].joint_count]
    poses = [rigs[0].skinning_matrices("flex", 0.7), rigs[1].skinning_matrices("flex", 1.3)]
    state = batch.state()
    initial_state(batch, state, np.concatenate(poses))
    x = state.x.numpy()
    for rig, b, pose, r in zip(rigs, builders, poses, batch.characters):
        expect = linear_blend_skin(b.layers.flat(), np.tile(rig.joint_indices, (4, 1)), np.tile(rig.joint_weights, (4, 1)),
                                   pose)
        assert np.allclose(x[r.particles(batch.vertex_count)], expect, atol=1e-6 * rig.size())
    with pytest.raises(InputError, match=r"skinning matrices of shape \(%d, 4, 4\), got \(%d, 4, 4\)"
                       % (batch.joint_count, rigs[0].joint_count)):
        initial_state(batch, state, poses[0])


def test_bench_batch_reports_character_steps_per_second(tmp_path, capsys, device):
    # the JSON record (no timing is asserted: the figures are the performance page's): N
    # instances in one model against N separate models, on the device asked for. The shipped
    # arm with dt 0.02: the batch steps as simulate would, no longer than gravity allows its
    # edges (the limit's closed form, the mean edge from trimesh)
    import json

    import trimesh

    from warpskin.cli import main
    from warpskin.scene import resolve_scene
    from warpskin.solver import GRAVITY_STEP

    text = (Path(__file__).parents[1] / "scenes" / "arm.toml").read_text()
    assert text.count("\ndt = 0.005\n") == 1
    scene = tmp_path / "arm.toml"
    scene.write_text(text.replace("\ndt = 0.005\n", "\ndt = 0.02\n"))
    out = tmp_path / "batch.json"
    assert main(["bench", str(scene), "--batch", "2", "--steps", "1", "--repeat", "1", "--device", str(device),
                 "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["device"] == str(device) and report["characters"] == 2
    row = report["scenes"]["arm"]
    rig = resolve_scene("arm").rig()
    edge = float(trimesh.Trimesh(rig.vertices, rig.triangles, process=False).edges_unique_length.mean())
    limit = (GRAVITY_STEP * edge / 9.81) ** 0.5
    assert row["gravity_step_limit_s"] == pytest.approx(limit, rel=1e-6)
    assert row["dt_s"] == pytest.approx(limit, rel=1e-6) and limit < 0.01
    assert row["characters"] == 2 and row["particles"] == 2 * 4 * rig.vertex_count
    assert row["separate_step_ms"] > 0 and row["batch_step_ms"] > 0
    assert row["speedup"] == pytest.approx(row["separate_step_ms"] / row["batch_step_ms"])
    assert row["batch_character_steps_per_s"] == pytest.approx(2e3 / row["batch_step_ms"])
    assert main(["bench", "--batch", "0"]) == 2
    assert "--batch needs a positive number of characters, got 0" in capsys.readouterr().err


def test_eight_cesium_men_step_bit_for_bit_as_each_alone(assets):
    # eight instances of one real rig, each at its own moment of the walk, contacts on: each
    # one's particles after the steps are its own run's (CPU)
    from warpskin.scene import resolve_scene

    scene = resolve_scene("cesium_man")
    rig = scene.rig()
    builder = SkinModelBuilder(rig, scene.model_params())
    builder.params.collision = scene.collision_params()
    batch = batch_model([builder] * 8, "cpu")
    clip = rig.clip(scene.clip)
    steps = 4
    poses = [[rig.skinning_matrices(clip, clip.start + 0.09 * c + s * DT) for s in range(steps + 1)] for c in range(8)]
    x, v = _run(batch, [np.concatenate([p[s] for p in poses]) for s in range(1, steps + 1)],
                start=lambda st: initial_state(batch, st, np.concatenate([p[0] for p in poses])))
    alone = builder.finalize("cpu")
    for p, r in zip(poses, batch.characters):
        ax, av = _run(alone, p[1:], start=lambda st: initial_state(alone, st, p[0]))
        mine = r.particles(batch.vertex_count)
        assert np.array_equal(x[mine], ax) and np.array_equal(v[mine], av)


def test_a_mixed_batch_of_real_rigs_steps_bit_for_bit_as_each_alone(assets):
    # CesiumMan (closed), the Fox (a coarse mesh simulated on a refined copy, in centimetres)
    # and the procedural arm, each with its own parameters, contacts on: each one's particles
    # after the steps are its own run's (CPU)
    from warpskin.io import load_rig
    from warpskin.scene import resolve_scene

    builders, clips = [], []
    for scene in (resolve_scene("cesium_man"), resolve_scene("arm")):
        rig = scene.rig()
        b = SkinModelBuilder(rig, scene.model_params())
        b.params.collision = scene.collision_params()
        builders.append(b)
        clips.append((rig, rig.clip(scene.clip), 0.3))
    fox = load_rig(assets / "Fox" / "Fox.glb")
    builders.insert(1, SkinModelBuilder(fox))
    clips.insert(1, (fox, fox.clip("Walk"), 0.2))
    batch = batch_model(builders, "cpu")
    assert builders[1].rig.refined_skin and batch.written_surface is not None
    steps = 4
    poses = [[rig.skinning_matrices(clip, clip.start + t0 + s * DT) for s in range(steps + 1)] for rig, clip, t0 in clips]
    x, v = _run(batch, [np.concatenate([p[s] for p in poses]) for s in range(1, steps + 1)],
                start=lambda st: initial_state(batch, st, np.concatenate([p[0] for p in poses])))
    for b, p, r in zip(builders, poses, batch.characters):
        alone = b.finalize("cpu")
        ax, av = _run(alone, p[1:], start=lambda st: initial_state(alone, st, p[0]))
        mine = r.particles(batch.vertex_count)
        assert np.array_equal(x[mine], ax) and np.array_equal(v[mine], av), r.name


def test_each_characters_control_sets_its_own_matrices():
    # a character's control writes its part of the batch's matrices and nothing else; a wrong
    # shape names the character
    builders = _builders()
    batch = batch_model(builders, "cpu")
    from warpskin.batch_model import character_controls

    control = batch.control()
    controls = character_controls(batch, control)
    poses = [b.rig.skinning_matrices(next(iter(b.rig.clips.values())), 0.37 * (k + 1)) for k, b in enumerate(builders)]
    controls[1].set_pose(poses[1])
    got = control.skin_matrices.numpy()
    r = batch.characters[1]
    assert np.allclose(got[r.joint_start:r.joint_start + r.joint_count], poses[1], atol=0)
    eye = np.eye(4, dtype=np.float32)
    others = np.r_[0:r.joint_start, r.joint_start + r.joint_count:len(got)]
    assert np.array_equal(got[others], np.broadcast_to(eye, (len(others), 4, 4)))
    j0 = batch.characters[0].joint_count
    with pytest.raises(InputError, match=rf"character 0 \(.*\): expected skinning matrices of shape \({j0}, 4, 4\)"):
        controls[0].set_pose(np.zeros((j0 + 1, 4, 4)))
    with pytest.raises(InputError, match="not a batched model"):
        character_controls(builders[0].finalize("cpu"), control)

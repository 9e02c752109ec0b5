"""Rig validation: every problem gives a clear error (or a named warning), checked on small
hand-made rigs; mesh checks against trimesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from warpskin.rig import Clip, Rig, RigError, Track, RigWarning, Skeleton, mesh_edge_report, weld_by_position
from warpskin.transforms import compose_trs


def _skeleton(parents=(-1, 0)):
    j = len(parents)
    t = np.zeros((j, 3))
    t[1:, 0] = 1.0
    return Skeleton([f"j{k}" for k in range(j)], np.array(parents), t, np.tile([0, 0, 0, 1.0], (j, 1)), np.ones((j, 3)))


def _box():
    m = trimesh.creation.box()
    return np.asarray(m.vertices), np.asarray(m.faces)


def _rig(**over):
    v, f = _box()
    sk = _skeleton()
    ji = np.tile([0, 1], (len(v), 1))
    jw = np.tile([0.75, 0.25], (len(v), 1))
    args = dict(name="box", points=v, triangles=f, skeleton=sk, joint_indices=ji, joint_weights=jw,
                inverse_bind=np.linalg.inv(sk.world_from_local(sk.rest_local_matrices())), source="box.test")
    args.update(over)
    return Rig.from_file_arrays(**args)


def test_valid_rig_is_closed_manifold():
    rig = _rig()
    assert rig.report.ok and rig.report.closed and rig.report.manifold
    rig.require_closed()


def test_nan_vertex_named():
    v, _ = _box()
    v[3, 0] = np.nan
    with pytest.raises(RigError, match=r"box.test: vertices 3 have NaN"):
        _rig(points=v)


def test_vertex_without_weight_named():
    jw = np.tile([0.75, 0.25], (8, 1))
    jw[6] = 0.0
    with pytest.raises(RigError, match=r"vertices 6 have no weight"):
        _rig(joint_weights=jw)


def test_weights_off_by_constant_factor_are_normalised_with_warning():
    with pytest.warns(RigWarning, match="sum to 100"):
        rig = _rig(joint_weights=np.tile([75.0, 25.0], (8, 1)))
    assert np.allclose(rig.joint_weights.sum(1), 1.0)
    assert np.allclose(rig.joint_weights[:, 0], 0.75)


def test_weights_off_by_rounding_are_normalised_with_warning():
    jw = np.tile([0.75, 0.25], (8, 1))
    jw[2] = [0.7504, 0.25]
    with pytest.warns(RigWarning, match="rounding"):
        rig = _rig(joint_weights=jw)
    assert np.allclose(rig.joint_weights.sum(1), 1.0)


def test_weights_with_varying_sums_are_normalised_per_vertex_with_one_warning():
    # as three.js and Blender do: each vertex's weights divided by their sum; one warning that
    # counts the vertices and names the worst (RobotExpressive's hands sum to up to 1.755)
    jw = np.tile([0.75, 0.25], (8, 1))
    jw[4] = [0.3, 0.2]
    jw[6] = [1.2, 0.555]
    with pytest.warns(RigWarning) as record:
        rig = _rig(joint_weights=jw)
    messages = [str(w.message) for w in record if "normalised per vertex" in str(w.message)]
    assert len(messages) == 1 and "weights of 2 vertices do not sum to one" in messages[0]
    assert "file vertex 6, sums to 1.755" in messages[0]  # the farthest from one
    np.testing.assert_allclose(rig.joint_weights, jw / jw.sum(axis=1, keepdims=True))


def test_negative_weight_is_an_error():
    jw = np.tile([1.25, -0.25], (8, 1))
    with pytest.raises(RigError, match="negative weights"):
        _rig(joint_weights=jw)


def test_joint_index_out_of_range_named():
    ji = np.tile([0, 1], (8, 1))
    ji[5, 1] = 7
    with pytest.raises(RigError, match=r"vertices 5 reference joint indices 7, outside \[0, 1\]"):
        _rig(joint_indices=ji)


def test_mismatched_inverse_bind_count():
    with pytest.raises(RigError, match="2 joints but there are 3 inverse bind"):
        _rig(inverse_bind=np.tile(np.eye(4), (3, 1, 1)))


def test_cycle_in_hierarchy_named():
    with pytest.raises(RigError, match="cycle in the joint hierarchy"):
        _skeleton(parents=(1, 2, 0))


def test_parent_out_of_range_named():
    with pytest.raises(RigError, match=r"joint 1 \('j1'\) has parent index 5"):
        _skeleton(parents=(-1, 5))


def test_degenerate_triangle_reported():
    v, f = _box()
    f = np.concatenate([f, [[0, 0, 1]]])
    with pytest.warns(RigWarning, match=r"degenerate \(zero-area\) triangles 12"):
        rig = _rig(triangles=f)
    assert list(rig.report.degenerate_triangles) == [12]


def test_open_mesh_is_reported_and_rejected_by_require_closed():
    v, f = _box()
    rig = _rig(triangles=f[:-1])
    assert not rig.report.closed
    with pytest.raises(RigError, match=r"not a closed manifold surface: 3 boundary edges"):
        rig.require_closed()


def test_flipped_triangle_is_inconsistent_winding():
    v, f = _box()
    f = f.copy()
    f[0] = f[0, ::-1]
    rig = _rig(triangles=f)
    assert rig.report.closed and not rig.report.manifold
    with pytest.raises(RigError, match="inconsistent winding"):
        rig.require_closed()


def test_nonmanifold_edge_reported():
    v, f = _box()
    extra = np.array([[0.0, 0.0, 2.0]])
    e = f[0]
    f2 = np.concatenate([f, [[e[0], e[1], 8]]])
    rig = _rig(points=np.concatenate([v, extra]), triangles=f2,
               joint_indices=np.tile([0, 1], (9, 1)), joint_weights=np.tile([0.5, 0.5], (9, 1)))
    assert not rig.report.manifold and rig.report.nonmanifold_edge_count == 1
    with pytest.raises(RigError, match="shared by more than two triangles"):
        rig.require_closed()


@pytest.mark.parametrize("seed", range(3))
def test_edge_report_agrees_with_trimesh(seed):
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=2)
    f = np.asarray(m.faces)
    f = f[rng.random(len(f)) > 0.05]  # punch holes
    rep = mesh_edge_report(f, len(m.vertices))
    t = trimesh.Trimesh(m.vertices, f, process=False)
    assert rep["closed"] == t.is_watertight
    edges = np.sort(t.edges, axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    assert rep["boundary_edges"].shape[0] == int((counts == 1).sum())


def test_weld_by_position_keeps_order_and_maps_back():
    v, f = _box()
    split = np.concatenate([v, v[[0, 3]]])  # two seam duplicates at the end
    first, wmap = weld_by_position(split)
    assert np.array_equal(first, np.arange(8))
    assert np.array_equal(wmap, np.concatenate([np.arange(8), [0, 3]]))
    assert np.array_equal(split[first][wmap], split)


def test_bad_weights_on_a_welded_seam_copy_are_named():
    # file vertices 8 and 9 duplicate vertices 0 and 3 (a seam); welding keeps 0 and 3, so
    # validate() never sees the copies: their NaN / negative weights must still be rejected
    v, f = _box()
    pts = np.concatenate([v, v[[0, 3]]])
    ji = np.tile([0, 1], (10, 1))
    jw = np.tile([0.75, 0.25], (10, 1))
    jw[8] = [np.nan, 1.0]
    jw[9] = [1.5, -0.5]
    with pytest.raises(RigError, match=r"box\.test: file vertices 8, 9 \(welded into others\) have NaN"):
        _rig(points=pts, joint_indices=ji, joint_weights=jw)
    jw[8] = jw[9] = [0.75, 0.25]
    assert _rig(points=pts, joint_indices=ji, joint_weights=jw).vertex_count == 8


def test_rescaled_scales_skinned_positions():
    move = Clip("move", {
        (1, "rotation"): Track("rotation", [0.0, 1.0], [[0, 0, 0, 1.0], [0, 0, 0.6, 0.8]]),
        (0, "translation"): Track("translation", [0.0, 1.0], [[0, 0, 0.0], [1.0, 2.0, 3.0]]),
    })
    rig = _rig(clips={"move": move})
    small = rig.rescaled(0.01)
    assert np.allclose(small.vertices, rig.vertices * 0.01)
    p = np.concatenate([rig.vertices, np.ones((8, 1))], 1)
    p_s = np.concatenate([small.vertices, np.ones((8, 1))], 1)
    for j in range(2):
        big = np.einsum("ij,vj->vi", rig.skinning_matrices("move", 0.5)[j], p)[:, :3]
        sm = np.einsum("ij,vj->vi", small.skinning_matrices("move", 0.5)[j], p_s)[:, :3]
        assert np.abs(big - rig.vertices).max() > 0.1  # a real pose, not the identity
        assert np.allclose(sm, big * 0.01)
    assert small.meters_per_unit == pytest.approx(0.01)
    with pytest.raises(RigError, match="positive"):
        rig.rescaled(-1.0)


def test_unknown_clip_lists_clips():
    rig = _rig()
    with pytest.raises(RigError, match=r"no clip named 'walk' \(clips: none\)"):
        rig.clip("walk")


@pytest.mark.parametrize("factor, guess", [(100.0, "0.01"), (0.01, "100"), (1.0, None)])
def test_a_body_outside_5_cm_to_20_m_warns_with_the_likely_unit_scale(factor, guess):
    import warnings as _w

    base = _rig()
    extent = float((base.vertices.max(axis=0) - base.vertices.min(axis=0)).max())
    scale = factor * 1.7 / extent  # a 1.7 m body, then in centimetres or hectometres
    with _w.catch_warnings(record=True) as record:
        _w.simplefilter("always")
        _rig(points=_box()[0] * scale)
    hits = [str(w.message) for w in record if "outside 5 cm - 20 m" in str(w.message)]
    if guess is None:
        assert hits == []
    else:
        assert len(hits) == 1 and f"--unit-scale {guess}" in hits[0]


def test_a_scaled_node_above_the_skeleton_is_moved_into_the_bind_space():
    """A 100x scaled, rotated armature node above the joints (RobotExpressive): the bind space
    is scaled to match, the skinned points of every pose are unchanged (NumPy LBS of the file's
    arrays as the reference) and every skinning matrix becomes rigid."""
    from scipy.spatial.transform import Rotation

    v, f = _box()
    v = v * 0.02 + np.array([0.003, -0.001, 0.002])  # a 2 cm box
    root = np.eye(4)
    root[:3, :3] = 100.0 * Rotation.from_euler("x", -90, degrees=True).as_matrix()
    sk = _skeleton()
    sk = Skeleton(sk.joint_names, sk.parents, sk.rest_translation * 0.02, sk.rest_rotation, sk.rest_scale,
                  np.stack([root, np.eye(4)]))
    inverse_bind = np.linalg.inv(sk.world_from_local(sk.rest_local_matrices())) @ root  # binds at the mesh's scale
    ji = np.tile([0, 1], (len(v), 1))
    rng = np.random.default_rng(0)
    w0 = rng.uniform(0.2, 0.8, len(v))
    jw = np.stack([w0, 1 - w0], axis=1)
    clip = Clip("bend", {(1, "rotation"): Track("rotation", np.array([0.0, 1.0]),
                                                np.array([[0, 0, 0, 1.0], Rotation.from_euler("z", 40, degrees=True).as_quat()]))})
    with pytest.warns(RigWarning, match="scale the mesh by 100"):
        rig = _rig(points=v, triangles=f, skeleton=sk, joint_indices=ji, joint_weights=jw, inverse_bind=inverse_bind,
                   clips={"bend": clip}, validate=False)
    np.testing.assert_allclose(rig.vertices, v * 100.0, rtol=1e-12)
    for t in (0.0, 0.6, 1.0):
        world = sk.world_from_local(compose_trs(*clip.sample_local_trs(sk, t)))
        want = np.einsum("vk,vkij,vj->vi", jw, (world @ inverse_bind)[ji], np.c_[v, np.ones(len(v))])[:, :3]
        mats = rig.skinning_matrices("bend", t)
        got = np.einsum("vk,vkij,vj->vi", jw, mats[ji], np.c_[rig.vertices, np.ones(len(v))])[:, :3]
        np.testing.assert_allclose(got, want, atol=1e-9)
        for m in mats:
            np.testing.assert_allclose(np.linalg.svd(m[:3, :3], compute_uv=False), 1.0, atol=1e-9)


def test_an_unscaled_or_unevenly_scaled_rig_is_left_alone():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RigWarning)  # no warning either
        rig = _rig()
    np.testing.assert_array_equal(rig.vertices, _box()[0])
    # a non-uniform scale cannot be moved into a rigid bind: left as it is
    sk = _skeleton()
    root = np.diag([100.0, 50.0, 100.0, 1.0])
    sk = Skeleton(sk.joint_names, sk.parents, sk.rest_translation, sk.rest_rotation, sk.rest_scale,
                  np.stack([root, np.eye(4)]))
    ib = np.linalg.inv(sk.world_from_local(sk.rest_local_matrices())) @ root
    rig = _rig(skeleton=sk, inverse_bind=ib, validate=False)
    np.testing.assert_array_equal(rig.vertices, _box()[0])

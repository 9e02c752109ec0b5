"""Bone-heat skinning weights (Baran and Popović 2007) and the cotangent Laplacian under them."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.spatial
import trimesh

from warpskin.preprocess.bones import bone_segments, dominant_bone
from warpskin.preprocess.bone_heat import (
    _segment_triangle_hits,
    bone_heat_weights,
    cotangent_laplacian,
    nearest_visible_bones,
    segments_cross_mesh,
    vertex_areas,
    with_bone_heat_weights,
)
from warpskin.rig import RigError
from warpskin.scenes.arm import make_arm

# the weight profiles below were measured on this layout (54 rings of 54 vertices, 2918 vertices);
# the shipped arm's default is 81 x 36 (isotropic triangles for the contact), where the same
# heat leaks a little further in x per ring
SEGMENTS = 54


@pytest.fixture(scope="module")
def arm():
    return make_arm(rings=54, segments=SEGMENTS)


@pytest.fixture(scope="module")
def arm_heat(arm):
    return with_bone_heat_weights(arm)


def _jittered_sphere(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    rng = np.random.default_rng(seed)
    v = m.vertices * rng.uniform(0.8, 1.2, (len(m.vertices), 1))
    return v, np.asarray(m.faces)


def _ring_means(rig, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ring x [m] and the ring-mean weights ``[rings, J]`` (the two poles left out)."""
    x = rig.vertices[:-2, 0].reshape(-1, SEGMENTS)[:, 0]
    return x, w[:-2].reshape(-1, SEGMENTS, w.shape[1]).mean(axis=1)


def _crossing(x: np.ndarray, w: np.ndarray) -> float:
    """First x where the decreasing ring weight ``w`` passes 0.5, linearly interpolated."""
    i = int(np.nonzero((w[:-1] >= 0.5) & (w[1:] < 0.5))[0][0])
    return float(x[i] + (w[i] - 0.5) / (w[i] - w[i + 1]) * (x[i + 1] - x[i]))


# --------------------------------------------------------------------------------------------
# Cotangent Laplacian and areas
# --------------------------------------------------------------------------------------------


def test_laplacian_symmetric_rows_sum_to_zero_and_semidefinite():
    v, t = _jittered_sphere()
    lap = cotangent_laplacian(v, t)
    assert lap.shape == (len(v), len(v))
    assert abs(lap - lap.T).max() < 1e-12
    assert np.abs(np.asarray(lap.sum(axis=1))).max() < 1e-12
    eig = np.linalg.eigvalsh(lap.toarray())
    assert eig.max() < 1e-9 * abs(eig.min())  # negative semi-definite, one zero eigenvalue


def test_laplacian_matches_brute_force_angles():
    v, t = _jittered_sphere(seed=3)
    n = len(v)
    ref = np.zeros((n, n))
    for tri in t:
        for k in range(3):
            c, i, j = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]  # angle at c opposite edge (i, j)
            e1, e2 = v[i] - v[c], v[j] - v[c]
            ang = np.arccos(np.dot(e1, e2) / (np.linalg.norm(e1) * np.linalg.norm(e2)))
            w = 0.5 / np.tan(ang)
            ref[i, j] += w
            ref[j, i] += w
            ref[i, i] -= w
            ref[j, j] -= w
    assert np.allclose(cotangent_laplacian(v, t).toarray(), ref, atol=1e-10)


@pytest.mark.parametrize("kind", ["regular", "delaunay"])
def test_laplacian_of_a_linear_function_vanishes_on_a_flat_mesh(kind):
    if kind == "regular":
        g = np.linspace(0.0, 1.0, 9)
        xy = np.stack(np.meshgrid(g, g * 0.7), axis=-1).reshape(-1, 2)
    else:
        rng = np.random.default_rng(1)
        xy = np.concatenate([rng.uniform(0.0, 1.0, (200, 2)), [[0, 0], [0, 1], [1, 0], [1, 1]]])
    t = scipy.spatial.Delaunay(xy).simplices
    v = np.column_stack([xy, np.zeros(len(xy))])
    f = 2.0 * v[:, 0] - 3.0 * v[:, 1] + 0.5
    lf = cotangent_laplacian(v, t) @ f
    m = trimesh.Trimesh(v, t, process=False)
    boundary = np.unique(m.edges[trimesh.grouping.group_rows(m.edges_sorted, require_count=1)])
    interior = np.setdiff1d(np.arange(len(v)), boundary)
    assert interior.size > 10
    assert np.abs(lf[interior]).max() < 1e-10
    assert np.abs(lf[boundary]).max() > 1e-3  # boundary rows are not a Laplacian: the test bites


@pytest.mark.parametrize("kind", ["mixed", "barycentric"])
def test_vertex_areas_sum_to_the_surface_area(kind):
    v, t = _jittered_sphere(seed=2)
    a = vertex_areas(v, t, kind=kind)
    assert (a > 0).all()
    assert np.isclose(a.sum(), trimesh.Trimesh(v, t, process=False).area, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------------------------


def test_segments_cross_mesh_matches_brute_force(arm):
    v, t = arm.vertices, arm.triangles
    rng = np.random.default_rng(0)
    s = 400
    a = v[rng.integers(0, len(v), s)]
    b = a + rng.normal(0.0, 0.06, (s, 3))
    got = segments_cross_mesh(v, t, a, b)
    tp = v[t]
    e1, e2 = tp[:, 1] - tp[:, 0], tp[:, 2] - tp[:, 0]
    nl = np.linalg.norm(np.cross(e1, e2), axis=1)
    d = b - a
    ln = np.linalg.norm(d, axis=1)
    inset = 1e-6 * arm.size()
    ref = np.array(
        [
            _segment_triangle_hits(
                np.broadcast_to(a[k], tp[:, 0].shape), np.broadcast_to(d[k], tp[:, 0].shape),
                np.full(len(t), ln[k]), tp[:, 0], e1, e2, nl, inset,
            ).any()
            for k in range(s)
        ]
    )
    assert 0.1 < ref.mean() < 0.9
    assert np.array_equal(got, ref)
    # a segment through the whole arm crosses it; one along the axis inside does not
    axis = segments_cross_mesh(v, t, [[0.1, 0, 0], [0.1, -1, 0]], [[0.4, 0, 0], [0.1, 1, 0]])
    assert axis.tolist() == [False, True]


def test_every_arm_vertex_sees_a_bone(arm):
    bones = bone_segments(arm)
    p, d, _ = nearest_visible_bones(arm.vertices, arm.triangles, bones.start, bones.end)
    assert np.isfinite(d).all()
    assert np.allclose(p.sum(axis=1), 1.0)
    # ties: only the wrist ring (x = 0.56 exactly, where the forearm bone ends and the wrist
    # bone starts) is equidistant from two bones; no ring lies exactly on the elbow plane
    tied = (p > 0).sum(axis=1) > 1
    assert tied.sum() == SEGMENTS and np.allclose(arm.vertices[tied, 0], 0.56)
    assert np.allclose(p[tied, 1:], 0.5)


def test_tied_bones_share_the_heat_source():
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    start = np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.0]])
    end = np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    p, d, _ = nearest_visible_bones(m.vertices, m.faces, start, end)
    mid = np.abs(m.vertices[:, 0]) < 1e-12  # equidistant from both bones
    assert mid.sum() >= 4
    assert np.allclose(p[mid], 0.5) and np.allclose(p[~mid].max(axis=1), 1.0)
    ji, jw = bone_heat_weights(m.vertices, m.faces, start, end)
    w = np.zeros((len(m.vertices), 2))
    np.add.at(w, (np.repeat(np.arange(len(w)), ji.shape[1]), ji.ravel()), jw.ravel())  # padded columns
    assert np.allclose(w[mid], 0.5, atol=1e-6)  # symmetric mesh: half and half on the mid-plane


# --------------------------------------------------------------------------------------------
# Bone heat on the arm
# --------------------------------------------------------------------------------------------


def test_arm_bone_heat_is_a_partition_of_unity(arm, arm_heat):
    ji, jw = arm_heat.joint_indices, arm_heat.joint_weights
    assert ji.shape == jw.shape == (arm.vertex_count, 4)
    assert (jw >= 0).all() and np.allclose(jw.sum(axis=1), 1.0)
    assert ((ji >= 0) & (ji < 3)).all()
    assert ((jw == 0) | (jw >= 1e-3)).all()  # min_weight dropped
    assert np.all(np.diff(jw, axis=1) <= 0)  # sorted by decreasing weight
    assert np.array_equal(arm_heat.vertices, arm.vertices)
    assert not np.array_equal(arm_heat.joint_weights[:, :3], arm.joint_weights)  # a copy, re-weighted


def test_arm_bone_heat_dominates_far_from_the_joints_and_decays(arm, arm_heat):
    w = arm_heat.dense_weights()
    x = arm.vertices[:, 0]
    # heat leaks about two limb radii (~0.09 m) past a joint with c = 1, so "far" means that far
    assert w[x < 0.20, 0].min() > 0.95
    assert w[(x > 0.39) & (x < 0.49), 1].min() > 0.95
    assert w[x > 0.575, 2].min() > 0.5  # the wrist cap
    xr, wr = _ring_means(arm, w)
    band = (xr > 0.15) & (xr < 0.45)
    assert np.all(np.diff(wr[band, 0]) < 0)  # shoulder weight falls across the elbow
    assert np.all(np.diff(wr[(xr > 0.30) & (xr < 0.42), 1]) > 0)  # elbow weight rises
    # rings are rotationally symmetric (the cross-section is an ellipse; spread is small)
    per_ring = w[:-2].reshape(-1, SEGMENTS, 3)
    assert np.ptp(per_ring, axis=1).max() < 0.03


def test_arm_bone_heat_crosses_one_half_at_the_elbow_like_the_procedural_weights(arm, arm_heat):
    xr, heat = _ring_means(arm, arm_heat.dense_weights())
    _, proc = _ring_means(arm, arm.dense_weights())
    spacing = float(np.median(np.diff(xr[(xr > 0.0) & (xr < 0.56)])))
    x_heat, x_proc = _crossing(xr, heat[:, 0]), _crossing(xr, proc[:, 0])
    print(
        f"shoulder weight = 0.5 at x = {x_heat:.4f} (bone heat), {x_proc:.4f} (procedural); "
        f"ring spacing {spacing:.4f}"
    )
    assert abs(x_proc - 0.30) < 1e-3
    # the heat source switches bone between the two rings around x = 0.30, so the discrete
    # crossing sits midway between them: within half a ring spacing (+ margin) of the elbow
    assert abs(x_heat - x_proc) < 0.6 * spacing
    near = np.argsort(np.abs(xr - 0.30))[:2]  # the two rings around the elbow
    assert np.all(np.abs(heat[near, 0] - 0.5) < 0.1) and np.all(np.abs(proc[near, 0] - 0.5) < 0.25)


def test_prune_to_max_influences_and_renormalise(arm):
    bones = bone_segments(arm)
    ji, jw = bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.end, max_influences=1)
    assert ji.shape == (arm.vertex_count, 1) and np.allclose(jw, 1.0)
    ji, jw = bone_heat_weights(
        arm.vertices, arm.triangles, bones.start, bones.end, max_influences=6, min_weight=0.2
    )
    assert ji.shape == (arm.vertex_count, 6)
    assert np.allclose(jw.sum(axis=1), 1.0) and ((jw == 0) | (jw >= 0.2)).all()
    assert (jw[:, 3:] == 0).all()  # only 3 bones
    # a masked bone gets no weight: the shoulder then carries the forearm's heat too
    ji, jw = bone_heat_weights(
        arm.vertices, arm.triangles, bones.start, bones.end, bone_mask=[True, False, True]
    )
    assert not np.any((ji == 1) & (jw > 0))


# --------------------------------------------------------------------------------------------
# Fall-backs and bad input
# --------------------------------------------------------------------------------------------


def test_a_part_that_sees_no_bone_falls_back_to_the_nearest_bone():
    outer = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    v = np.concatenate([outer.vertices, inner.vertices, [[5.0, 0.0, 0.0]]])  # + an unused vertex
    t = np.concatenate([outer.faces, inner.faces + len(outer.vertices)])
    # two bones outside both spheres: the inner sphere is hidden behind the outer one
    start = np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    end = np.array([[3.0, 0.0, 0.0], [-3.0, 0.0, 0.0]])
    _, d, _ = nearest_visible_bones(v, t, start, end)
    inner_idx = np.arange(len(outer.vertices), len(outer.vertices) + len(inner.vertices))
    assert np.isinf(d[inner_idx]).all()
    ji, jw = bone_heat_weights(v, t, start, end)
    assert np.allclose(jw.sum(axis=1), 1.0) and (jw >= 0).all()
    xi = v[inner_idx, 0]
    dom = ji[inner_idx, 0]
    assert np.all(dom[xi > 0.05] == 0) and np.all(dom[xi < -0.05] == 1)
    assert ji[-1, 0] == 0 and jw[-1, 0] == 1.0  # the unused vertex: its nearest bone


def test_degenerate_triangles_are_ignored(arm):
    bones = bone_segments(arm)
    ref = bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.end)
    extra = np.concatenate([arm.triangles, [[0, 0, 1], [5, 6, 5]]])  # repeated corners
    got = bone_heat_weights(arm.vertices, extra, bones.start, bones.end)
    assert np.array_equal(got[0], ref[0]) and np.allclose(got[1], ref[1], atol=1e-12)
    lap = cotangent_laplacian(arm.vertices, extra)
    assert np.isfinite(lap.data).all()


def test_bad_input_raises_rig_error(arm):
    bones = bone_segments(arm)
    v = arm.vertices.copy()
    v[7] = np.nan
    with pytest.raises(RigError, match="NaN"):
        bone_heat_weights(v, arm.triangles, bones.start, bones.end)
    with pytest.raises(RigError, match="NaN"):
        cotangent_laplacian(v, arm.triangles)
    with pytest.raises(RigError, match="positive length"):
        bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.start)
    with pytest.raises(RigError, match="positive length"):
        bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.end, bone_mask=[False] * 3)
    with pytest.raises(RigError, match="outside"):
        bone_heat_weights(arm.vertices, arm.triangles + len(v), bones.start, bones.end)
    with pytest.raises(RigError, match="no triangles"):
        bone_heat_weights(arm.vertices, np.zeros((0, 3), int), bones.start, bones.end)
    with pytest.raises(RigError, match="shape"):
        bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.end[:2])
    with pytest.raises(RigError, match="max_influences"):
        bone_heat_weights(arm.vertices, arm.triangles, bones.start, bones.end, max_influences=0)


# --------------------------------------------------------------------------------------------
# CesiumMan
# --------------------------------------------------------------------------------------------


def test_cesium_man_dominant_bone_agrees_with_the_file(assets):
    from warpskin.io import load_rig

    rig = load_rig(assets / "usd/CesiumMan/CesiumMan.usdz")
    bones = bone_segments(rig)
    heat = with_bone_heat_weights(rig)
    assert np.allclose(heat.joint_weights.sum(axis=1), 1.0) and (heat.joint_weights >= 0).all()
    file_dom, heat_dom = dominant_bone(rig), dominant_bone(heat)
    # bone_segments gives every CesiumMan joint a positive length (leaves are extended along
    # their parent), so every vertex is compared
    positive = bones.length[file_dom] > 0
    assert positive.all()
    agree = float(np.mean(file_dom[positive] == heat_dom[positive]))
    listed = (rig.joint_indices == heat_dom[:, None]) & (rig.joint_weights > 0)
    in_file = float(np.mean(listed.any(axis=1)))
    print(f"CesiumMan: bone-heat dominant bone == file dominant bone on {agree:.3f} of vertices; "
          f"among the file's influences on {in_file:.3f}")
    assert agree > 0.85  # measured 0.900; the misses are the 2 cm hip and chest bones
    assert in_file > 0.95

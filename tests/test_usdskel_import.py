"""UsdSkel importer: the imported rig reproduces usd-core's own skinning
(``UsdSkel.SkinningQuery.ComputeSkinnedPoints``) on the shared assets and on small stages
built here, and malformed input raises :class:`RigError` naming the file and prim."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt  # noqa: E402

from oracles import rig_lbs, usd_skinned_world
from warpskin.io import usdskel  # noqa: E402
from warpskin.io.usdskel import list_usd_meshes, load_usd  # noqa: E402
from warpskin.mesh import triangulate_faces  # noqa: E402
from warpskin.rig import Rig, RigError, RigWarning  # noqa: E402

ASSET_TIMES = (1.0, 10.5, 24.0, 37.25, 48.0)
TOL = 1e-5  # relative to the model size (bbox diagonal)


# --------------------------------------------------------------------------------------------
# Reference and helpers
# --------------------------------------------------------------------------------------------


def rig_skinned_file_points(rig: Rig, t: float, clip: str | None = None) -> np.ndarray:
    """LBS of the rig at ``t`` [s], mapped back to the file's points ``[N, 3]``."""
    m = rig.skinning_matrices(rig.clip(clip), t)  # [J, 4, 4]
    return rig_lbs(rig, m)[rig.weld_map]


def max_rel_error(rig: Rig, stage: Usd.Stage, tcs, scale: float = 1.0) -> float:
    tcps = stage.GetTimeCodesPerSecond()
    worst = 0.0
    for tc in tcs:
        ref = usd_skinned_world(stage, rig.mesh_name, tc) * scale
        got = rig_skinned_file_points(rig, tc / tcps)
        worst = max(worst, float(np.abs(got - ref).max()) / rig.size())
    return worst


def signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    p0, p1, p2 = (vertices[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() / 6.0)


# --------------------------------------------------------------------------------------------
# Shared assets (usd-wg conversions of the Cesium glTF samples)
# --------------------------------------------------------------------------------------------


def _asset(assets: Path, name: str) -> Path:
    p = assets / "usd" / name / f"{name}.usdz"
    if not p.is_file():
        pytest.skip(f"{p} is absent")
    return p


@pytest.mark.parametrize("name", ["CesiumMan", "RiggedFigure", "RiggedSimple"])
def test_asset_matches_usd_skinning(assets: Path, name: str) -> None:
    path = _asset(assets, name)
    rig = load_usd(path)
    stage = Usd.Stage.Open(str(path))
    err = max_rel_error(rig, stage, ASSET_TIMES)
    assert err < TOL, f"{name}: max |rig LBS - ComputeSkinnedPoints| = {err:.3g} x model size"


def test_cesium_man_counts(assets: Path) -> None:
    rig = load_usd(_asset(assets, "CesiumMan"))
    assert rig.file_vertex_count == 3273
    assert rig.vertex_count == 2338
    assert rig.triangle_count == 4672
    assert rig.joint_count == 19
    assert rig.report.closed and rig.report.manifold
    rig.require_closed()
    assert signed_volume(rig.vertices, rig.triangles) > 0.0
    assert rig.up_axis == "Y" and rig.meters_per_unit == 1.0
    assert rig.mesh_name.endswith("/Cesium_Man_2")
    assert list(rig.clips) == ["skelAnim_0"]
    clip = rig.clip()
    assert clip.start == pytest.approx(1 / 24)
    assert clip.end == pytest.approx(48 / 24)
    assert all(tr.interpolation == "LINEAR" for tr in clip.tracks.values())
    assert rig.skeleton.joint_names[0] == "Skeleton_torso_joint_1"
    assert rig.skeleton.parents[0] == -1
    unwelded = load_usd(_asset(assets, "CesiumMan"), weld=False)
    assert unwelded.vertex_count == 3273 and unwelded.triangle_count == 4672


def test_cesium_man_listing_and_selection(assets: Path) -> None:
    path = _asset(assets, "CesiumMan")
    meshes = list_usd_meshes(path)
    skinned = [m for m in meshes if m["skinned"]]
    assert len(skinned) == 1
    m = skinned[0]
    assert m["name"] == "/CesiumMan/Geom/Z_UP/Armature/Skeleton_torso_joint_1_3/Cesium_Man_2"
    assert (m["vertices"], m["triangles"], m["joints"]) == (3273, 4672, 19)
    assert m["skeleton"].endswith("/Skeleton")
    assert m["animation"] == "/CesiumMan/Animations/skelAnim_0"
    by_name = load_usd(path, mesh="Cesium_Man_2")
    by_path = load_usd(path, mesh=m["name"])
    assert by_name.mesh_name == by_path.mesh_name == m["name"]
    with pytest.raises(RigError, match="Cesium_Man_2") as exc:
        load_usd(path, mesh="Body")
    assert "'Body'" in str(exc.value) and str(path) in str(exc.value)


# --------------------------------------------------------------------------------------------
# Hand-built stages: a closed box (3 rings of 4 points) skinned to a 2-joint chain
# --------------------------------------------------------------------------------------------

RING = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]  # CCW seen from +z


def _box_faces() -> tuple[list[int], list[int]]:
    faces = [[0, 3, 2, 1], [8, 9, 10, 11]]  # caps
    for r in range(2):
        for i in range(4):
            j = (i + 1) % 4
            faces.append([4 * r + i, 4 * r + j, 4 * (r + 1) + j, 4 * (r + 1) + i])
    return [len(f) for f in faces], [v for f in faces for v in f]


def _quat(axis, degrees) -> Gf.Quatf:
    q = Gf.Rotation(Gf.Vec3d(*axis), degrees).GetQuat()
    return Gf.Quatf(q.GetReal(), Gf.Vec3f(q.GetImaginary()))


def build_box(
    path: Path,
    *,
    mpu: float = 1.0,
    left_handed: bool = False,
    constant_weights: bool = False,
    sparse_anim: bool = False,
    with_anim: bool = True,
    skel_binding: bool = True,
    mesh_joints: list[str] | None = None,
    mutate=None,
) -> Path:
    """Write the test box stage to ``path`` and return it. ``mutate(stage, mesh_binding)`` may
    corrupt it before saving."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(30.0)
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(20.0)

    world = UsdGeom.Xform.Define(stage, "/World")
    world.AddTranslateOp().Set(Gf.Vec3d(1.0, 2.0, 3.0))
    world.AddRotateXOp().Set(90.0)
    root = UsdSkel.Root.Define(stage, "/World/Char")
    skel = UsdSkel.Skeleton.Define(stage, "/World/Char/Skel")
    joints = ["root", "root/tip"]
    skel.CreateJointsAttr(Vt.TokenArray(joints))
    tip = Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0.0, 0.0, 1.0))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0), tip]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0), tip]))

    mesh = UsdGeom.Mesh.Define(stage, "/World/Char/Box")
    # authored 0.25 below the bind pose; geomBindTransform lifts it back
    pts = [(x, y, z - 0.25) for z in (0.0, 1.0, 2.0) for x, y in RING]
    mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*p) for p in pts]))
    counts, indices = _box_faces()
    if left_handed:
        indices = [v for k in range(len(counts)) for v in reversed(indices[4 * k : 4 * k + 4])]
        mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray(counts))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray(indices))

    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    if skel_binding:
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(0.0, 0.0, 0.25)))
    if mesh_joints is not None:
        binding.CreateJointsAttr(Vt.TokenArray(mesh_joints))
    if constant_weights:
        binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([1]))
        binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    else:
        # ring 0 on the root, ring 1 shared, ring 2 on the tip (skeleton joint indices)
        ji = [[0, 1]] * 4 + [[0, 1]] * 4 + [[1, 0]] * 4
        jw = [[1.0, 0.0]] * 4 + [[0.5, 0.5]] * 4 + [[1.0, 0.0]] * 4
        if mesh_joints is not None:  # indices refer to the mesh's own joint order
            remap = [mesh_joints.index(n) for n in joints]
            ji = [[remap[a], remap[b]] for a, b in ji]
        binding.CreateJointIndicesPrimvar(False, 2).Set(Vt.IntArray([i for row in ji for i in row]))
        binding.CreateJointWeightsPrimvar(False, 2).Set(Vt.FloatArray([w for row in jw for w in row]))

    if with_anim:
        anim = UsdSkel.Animation.Define(stage, "/World/Char/Walk")
        anim_joints = ["root/tip"] if sparse_anim else joints
        anim.CreateJointsAttr(Vt.TokenArray(anim_joints))
        rot_root = [_quat((0, 0, 1), a) for a in (0.0, 30.0, 45.0)]
        rot_tip = [_quat((1, 0, 0), a) for a in (0.0, 60.0, 170.0)]
        tr_root = [(0.0, 0.0, 0.0), (0.3, 0.0, 0.0), (0.3, 0.2, 0.0)]
        for k, tc in enumerate((0.0, 10.0, 20.0)):
            rots = [rot_tip[k]] if sparse_anim else [rot_root[k], rot_tip[k]]
            anim.GetRotationsAttr().Set(Vt.QuatfArray(rots), tc)
            if not sparse_anim:
                anim.GetTranslationsAttr().Set(
                    Vt.Vec3fArray([Gf.Vec3f(*tr_root[k]), Gf.Vec3f(0.0, 0.0, 1.0)]), tc
                )
        if sparse_anim:  # a single default value: a constant track
            anim.GetTranslationsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(0.0, 0.1, 1.0)]))
        n = len(anim_joints)
        # scales: tip grows 1 -> 1.5 in x over tc 0..20 (half precision; test times keep it exact)
        for tc, sx in ((0.0, 1.0), (20.0, 1.5)):
            vals = [Gf.Vec3h(1.0, 1.0, 1.0)] * (n - 1) + [Gf.Vec3h(sx, 1.0, 1.0)]
            anim.GetScalesAttr().Set(Vt.Vec3hArray(vals), tc)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    if mutate is not None:
        mutate(stage, binding)
    del root
    stage.GetRootLayer().Save()
    return path


BOX_TIMES = (0.0, 2.5, 5.0, 12.5, 20.0, 25.0)
BOX_MESH = "/World/Char/Box"


def _check_box(path: Path, rig: Rig, scale: float = 1.0) -> None:
    stage = Usd.Stage.Open(str(path))
    err = max_rel_error(rig, stage, BOX_TIMES, scale)
    assert err < TOL, f"max |rig LBS - ComputeSkinnedPoints| = {err:.3g} x model size"


def test_box_matches_usd(tmp_path: Path) -> None:
    path = build_box(tmp_path / "box.usda", mesh_joints=["root/tip", "root"])
    rig = load_usd(path)
    _check_box(path, rig)
    assert rig.mesh_name == BOX_MESH and rig.name == "box"
    assert rig.vertex_count == 12 and rig.triangle_count == 20  # 10 quads
    assert rig.up_axis == "Z"
    rig.require_closed()
    assert signed_volume(rig.vertices, rig.triangles) == pytest.approx(2.0)
    # rest vertices are in skeleton space: geomBindTransform applied
    assert rig.vertices[:, 2].min() == pytest.approx(0.0) and rig.vertices[:, 2].max() == pytest.approx(2.0)
    # root joints hang below the /World transform
    stage = Usd.Stage.Open(str(path))
    world = np.array(UsdGeom.Xformable(stage.GetPrimAtPath("/World")).ComputeLocalToWorldTransform(0)).T
    np.testing.assert_allclose(rig.skeleton.root_transform[0], world, atol=1e-12)
    clip = rig.clips["Walk"]
    assert clip.start == 0.0 and clip.end == pytest.approx(20.0 / 30.0)
    assert set(clip.tracks) == {(j, p) for j in (0, 1) for p in ("translation", "rotation", "scale")}


def test_box_centimetres_become_metres(tmp_path: Path) -> None:
    path_m = build_box(tmp_path / "box_m.usda")
    path_cm = build_box(tmp_path / "box_cm.usda", mpu=0.01)
    rig_m, rig_cm = load_usd(path_m), load_usd(path_cm)
    assert rig_cm.meters_per_unit == pytest.approx(0.01)
    np.testing.assert_allclose(rig_cm.vertices, rig_m.vertices * 0.01, atol=1e-12)
    _check_box(path_cm, rig_cm, scale=0.01)
    for t in (0.1, 0.5):
        np.testing.assert_allclose(
            rig_skinned_file_points(rig_cm, t), rig_skinned_file_points(rig_m, t) * 0.01, atol=1e-9
        )


def test_box_left_handed_winding_is_flipped(tmp_path: Path) -> None:
    path = build_box(tmp_path / "box_lh.usda", left_handed=True)
    rig = load_usd(path)
    assert signed_volume(rig.vertices, rig.triangles) == pytest.approx(2.0)
    rig.require_closed()
    _check_box(path, rig)


def test_box_constant_weights(tmp_path: Path) -> None:
    path = build_box(tmp_path / "box_const.usda", constant_weights=True)
    rig = load_usd(path)
    assert rig.joint_indices.shape == (12, 1)
    assert np.all(rig.joint_indices == 1) and np.all(rig.joint_weights == 1.0)
    _check_box(path, rig)


def test_box_sparse_animation_keeps_rest(tmp_path: Path) -> None:
    path = build_box(tmp_path / "box_sparse.usda", sparse_anim=True)
    rig = load_usd(path)
    clip = rig.clip()
    assert {j for j, _ in clip.tracks} == {1}
    tr = clip.tracks[(1, "translation")]
    assert tr.times.size == 1  # default-only value: one constant key
    np.testing.assert_allclose(tr.values[0], [0.0, 0.1, 1.0], atol=1e-7)
    assert clip.start == 0.0 and clip.end == pytest.approx(20.0 / 30.0)
    local = rig.skeleton.rest_local_matrices()
    np.testing.assert_allclose(local[0], np.eye(4), atol=1e-12)
    _check_box(path, rig)


def test_box_without_animation_and_without_rest_transforms(tmp_path: Path) -> None:
    def drop_rest(stage, _binding):
        stage.GetPrimAtPath("/World/Char/Skel").RemoveProperty("restTransforms")

    path = build_box(tmp_path / "box_still.usda", with_anim=False, mutate=drop_rest)
    rig = load_usd(path)
    assert rig.clips == {}
    # rest pose from bindTransforms: the tip sits 1 unit up
    np.testing.assert_allclose(rig.skeleton.rest_translation[1], [0.0, 0.0, 1.0], atol=1e-12)
    world = rig.joint_world_transforms(None, 0.0)
    np.testing.assert_allclose(world @ rig.inverse_bind, np.tile(rig.skeleton.root_transform[0], (2, 1, 1)), atol=1e-12)


def test_box_held_interpolation_steps(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Held interpolation is a runtime stage setting (not stored in files): set it on open.
    path = build_box(tmp_path / "box_held.usda")
    real_open = usdskel._open_stage

    def held_open(p):
        pxr_ns, stage, pp = real_open(p)
        stage.SetInterpolationType(Usd.InterpolationTypeHeld)
        return pxr_ns, stage, pp

    monkeypatch.setattr(usdskel, "_open_stage", held_open)
    rig = load_usd(path)
    assert all(tr.interpolation == "STEP" for tr in rig.clip().tracks.values())
    stage = Usd.Stage.Open(str(path))
    stage.SetInterpolationType(Usd.InterpolationTypeHeld)
    assert max_rel_error(rig, stage, (0.0, 4.0, 10.0, 13.7, 20.0)) < TOL


def test_triangulate_faces_fans_holes_and_degenerate() -> None:
    counts = np.array([5, 2, 3, 4])
    indices = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13])
    tri, skipped = triangulate_faces(counts, indices, holes=np.array([3]))
    np.testing.assert_array_equal(tri, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [7, 8, 9]])
    np.testing.assert_array_equal(skipped, [1])


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="no such file"):
        load_usd(tmp_path / "nope.usda")


def test_not_a_usd_file(tmp_path: Path) -> None:
    p = tmp_path / "junk.usda"
    p.write_text("this is not a USD layer\n{ [ }\n")
    with pytest.raises(RigError, match="junk.usda.*cannot be opened as a USD stage"):
        load_usd(p)
    b = tmp_path / "junk.usdc"
    b.write_bytes(b"\x00\x01binary nonsense" * 10)
    with pytest.raises(RigError, match="cannot be opened"):
        list_usd_meshes(b)


def test_no_skinned_mesh(tmp_path: Path) -> None:
    p = tmp_path / "plain.usda"
    stage = Usd.Stage.CreateNew(str(p))
    cube = UsdGeom.Mesh.Define(stage, "/Cube")
    cube.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(0, 1, 0)]))
    cube.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    cube.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    stage.GetRootLayer().Save()
    with pytest.raises(RigError, match=r"no skinned mesh.*</Cube>"):
        load_usd(p)
    listing = list_usd_meshes(p)
    assert listing == [
        {
            "name": "/Cube",
            "skinned": False,
            "vertices": 3,
            "triangles": 1,
            "joints": 0,
            "skeleton": None,
            "animation": None,
            "problem": None,
        }
    ]
    with pytest.raises(RigError, match="not skinned"):
        load_usd(p, mesh="Cube")


def test_missing_skeleton_binding(tmp_path: Path) -> None:
    path = build_box(tmp_path / "unbound.usda", skel_binding=False)
    with pytest.raises(RigError, match="no skinned mesh.*no skel:skeleton binding"):
        load_usd(path)
    [entry] = list_usd_meshes(path)
    assert not entry["skinned"] and "skel:skeleton" in entry["problem"]


def _set_weights(values):
    def mutate(_stage, binding):
        binding.GetJointWeightsPrimvar().Set(Vt.FloatArray(values))

    return mutate


def test_vertex_without_weight(tmp_path: Path) -> None:
    jw = [1.0, 0.0] * 4 + [0.5, 0.5] * 4 + [1.0, 0.0] * 4
    jw[6:8] = [0.0, 0.0]  # vertex 3
    path = build_box(tmp_path / "zero.usda", mutate=_set_weights(jw))
    with pytest.raises(RigError, match=r"zero\.usda: mesh </World/Char/Box>: vertices 3 have no joint weight"):
        load_usd(path)


def test_joint_index_out_of_range(tmp_path: Path) -> None:
    def mutate(_stage, binding):
        ji = list(binding.GetJointIndicesPrimvar().Get())
        ji[10] = 7  # vertex 5, weight 0.5
        binding.GetJointIndicesPrimvar().Set(Vt.IntArray(ji))

    path = build_box(tmp_path / "oob.usda", mutate=mutate)
    with pytest.raises(RigError, match=r"</World/Char/Box>: vertices 5 use joint indices 7, outside \[0, 1\]"):
        load_usd(path)


def test_nan_point(tmp_path: Path) -> None:
    def mutate(stage, _binding):
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(BOX_MESH)).GetPointsAttr()
        pts = list(attr.Get())
        pts[4] = Gf.Vec3f(float("nan"), 0.0, 0.0)
        attr.Set(Vt.Vec3fArray(pts))

    path = build_box(tmp_path / "nan.usda", mutate=mutate)
    with pytest.raises(RigError, match=r"</World/Char/Box>: points 4 are NaN or inf"):
        load_usd(path)


def test_mesh_without_points(tmp_path: Path) -> None:
    def mutate(stage, _binding):
        UsdGeom.Mesh(stage.GetPrimAtPath(BOX_MESH)).GetPointsAttr().Set(Vt.Vec3fArray())

    path = build_box(tmp_path / "empty.usda", mutate=mutate)
    with pytest.raises(RigError, match=r"empty\.usda: mesh </World/Char/Box>: has no points"):
        load_usd(path, mesh=BOX_MESH)


def test_mesh_joint_unknown_to_skeleton(tmp_path: Path) -> None:
    def mutate(_stage, binding):
        binding.GetJointsAttr().Set(Vt.TokenArray(["root/tip", "root/elbow"]))

    path = build_box(tmp_path / "joints.usda", mesh_joints=["root/tip", "root"], mutate=mutate)
    with pytest.raises(RigError, match=r"skel:joints names 1 joint\(s\) .*lacks: \['root/elbow'\]"):
        load_usd(path)


def test_bind_transform_count_mismatch(tmp_path: Path) -> None:
    def mutate(stage, _binding):
        UsdSkel.Skeleton(stage.GetPrimAtPath("/World/Char/Skel")).GetBindTransformsAttr().Set(
            Vt.Matrix4dArray([Gf.Matrix4d(1.0)])
        )

    path = build_box(tmp_path / "bind.usda", mutate=mutate)
    with pytest.raises(RigError, match=r"has 1 bindTransforms for 2 joints"):
        load_usd(path)


def test_bad_face_indices_and_influence_sizes(tmp_path: Path) -> None:
    def bad_faces(stage, _binding):
        attr = UsdGeom.Mesh(stage.GetPrimAtPath(BOX_MESH)).GetFaceVertexIndicesAttr()
        idx = list(attr.Get())
        idx[0] = 40
        attr.Set(Vt.IntArray(idx))

    path = build_box(tmp_path / "faces.usda", mutate=bad_faces)
    with pytest.raises(RigError, match=r"faceVertexIndices entries 0 are outside \[0, 11\]"):
        load_usd(path)
    path = build_box(tmp_path / "short.usda", mutate=_set_weights([1.0, 0.0] * 5))
    with pytest.raises(RigError, match="jointIndices has 24 entries but primvars:skel:jointWeights has 10"):
        load_usd(path)


def test_animation_size_mismatch(tmp_path: Path) -> None:
    def mutate(stage, _binding):
        anim = UsdSkel.Animation(stage.GetPrimAtPath("/World/Char/Walk"))
        anim.GetRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1.0)]), 10.0)

    path = build_box(tmp_path / "anim.usda", mutate=mutate)
    with pytest.raises(RigError, match=r"</World/Char/Walk> rotations has 1 entries at time code 10 .* 2 joints"):
        load_usd(path)


def test_animation_missing_component_is_ignored_like_usd(tmp_path: Path) -> None:
    def mutate(stage, _binding):
        stage.GetPrimAtPath("/World/Char/Walk").RemoveProperty("scales")

    path = build_box(tmp_path / "noscale.usda", mutate=mutate)
    with pytest.warns(RigWarning, match="does not author scale"):
        rig = load_usd(path)
    assert rig.clips == {}
    _check_box(path, rig)  # USD also falls back to the rest pose


def test_quaternion_slerp_matches_usd_interpolation(tmp_path: Path) -> None:
    # USD interpolates quaternion time samples by slerp on the shorter arc; a Track must agree
    # even when consecutive keys lie in opposite hemispheres.
    stage = Usd.Stage.CreateInMemory()
    attr = stage.DefinePrim("/p").CreateAttribute("q", Sdf.ValueTypeNames.QuatfArray)
    q0 = Gf.Quatf(0.9, Gf.Vec3f(0.1, 0.3, 0.2)).GetNormalized()
    q1 = Gf.Quatf(-0.5, Gf.Vec3f(0.5, -0.4, 0.3)).GetNormalized()
    attr.Set(Vt.QuatfArray([q0]), 0.0)
    attr.Set(Vt.QuatfArray([q1]), 10.0)
    from warpskin.rig import Track

    def xyzw(q):
        return [*q.GetImaginary(), q.GetReal()]

    track = Track("rotation", [0.0, 10.0], [xyzw(q0), xyzw(q1)])
    for tc in (1.0, 2.5, 5.0, 7.3, 9.9):
        got = track.sample(tc)
        ref = np.array(xyzw(attr.Get(tc)[0]))
        assert math.isclose(abs(float(np.dot(got, ref))), 1.0, abs_tol=1e-6)
        np.testing.assert_allclose(got, ref, atol=1e-6)


def test_a_painted_physics_weight_primvar_is_read_and_checked(tmp_path: Path) -> None:
    # primvars:physicsWeight (vertex) lands per file vertex on the rig; a value outside [0, 1]
    # is refused with the vertex named
    paint = np.linspace(0.0, 1.0, 12)

    def painted(values):
        def mutate(stage, binding):
            pv = UsdGeom.PrimvarsAPI(binding.GetPrim()).CreatePrimvar("physicsWeight", Sdf.ValueTypeNames.FloatArray,
                                                                      UsdGeom.Tokens.vertex)
            pv.Set(Vt.FloatArray([float(v) for v in values]))
        return mutate

    rig = load_usd(build_box(tmp_path / "paint.usda", mutate=painted(paint)))
    got = rig.render.physics_weight
    assert got is not None and got.shape == (rig.file_vertex_count,)
    np.testing.assert_allclose(np.sort(got), np.sort(paint), atol=1e-6)
    bad = paint.copy()
    bad[5] = 1.5
    with pytest.raises(RigError, match=r"painted physics weight of vertex 5 is 1.5, outside \[0, 1\]"):
        load_usd(build_box(tmp_path / "bad.usda", mutate=painted(bad)))

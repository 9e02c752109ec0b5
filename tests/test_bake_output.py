"""What a bake carries for a DCC besides its points: the file's own topology and UVs, normals
that keep the file's hard edges, a UsdPreviewSurface material with the file's texture, the rest
pose in stage space, a root prim named after the character (kind component, defaultPrim), and
a variant set that flips between the physical skin and LBS. References: trimesh's reading of
the glTF files, usd-core's reading of the usdz, the packaged image bytes."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import trimesh
from pxr import Kind, Sdf, Usd, UsdGeom, UsdShade

from oracles import prim
from warpskin.cli import main


def _bake(tmp_path, *args, name="bake.usdc"):
    out = tmp_path / name
    assert main([*args, "-o", str(out), "--quiet"]) == 0
    return out, Usd.Stage.Open(str(out))


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation R that best maps the centred points ``a`` onto ``b`` (b ~ R a + t)."""
    ca, cb = a - a.mean(0), b - b.mean(0)
    u, _, vt = np.linalg.svd(cb.T @ ca)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def test_cesium_man_bake_has_the_files_topology_uvs_and_texture(assets, tmp_path):
    glb = assets / "CesiumMan" / "CesiumMan.glb"
    out, stage = _bake(tmp_path, "skin", str(glb), "--frames", "1:3")
    ref = trimesh.load(glb, process=False, force="mesh")  # trimesh's own glTF reader
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    np.testing.assert_array_equal(faces, ref.faces)
    assert len(mesh.GetPointsAttr().Get(1)) == len(ref.vertices) == 3273
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    assert st.GetTypeName() == Sdf.ValueTypeNames.TexCoord2fArray
    # trimesh flips glTF's v to the bottom-left origin, as USD's st has it
    np.testing.assert_allclose(np.asarray(st.Get()).reshape(-1, 3, 2), ref.visual.uv[ref.faces], atol=1e-6)
    # the material: a UsdPreviewSurface whose diffuse colour reads the file's image through st
    material = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()[0]
    assert material and material.GetPrim().GetParent().GetName() == "Looks"
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    texture = UsdShade.Shader(surface.GetInput("diffuseColor").GetConnectedSource()[0].GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    image = texture.GetInput("file").Get()
    written = (out.parent / image.path).read_bytes()
    with zipfile.ZipFile(assets / "usd" / "CesiumMan" / "CesiumMan.usdz") as z:  # the same image, packaged
        assert written == z.read("0/CesiumMan_img0.jpg")
    reader = UsdShade.Shader(texture.GetInput("st").GetConnectedSource()[0].GetPrim())
    assert reader.GetInput("varname").Get() == "st"
    assert not [p for p in out.parent.rglob("*") if p.name.startswith(".")]  # no temp files left


def test_usdz_bake_carries_the_sources_st(assets, tmp_path):
    usdz = assets / "usd" / "CesiumMan" / "CesiumMan.usdz"
    _, stage = _bake(tmp_path, "skin", str(usdz), "--frames", "1:2")
    src = Usd.Stage.Open(str(usdz))
    src_mesh = next(UsdGeom.Mesh(p) for p in src.Traverse() if p.IsA(UsdGeom.Mesh))
    src_st = np.asarray(UsdGeom.PrimvarsAPI(src_mesh).GetPrimvar("st").Get())  # vertex interpolated there
    faces = np.asarray(src_mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    st = np.asarray(UsdGeom.PrimvarsAPI(UsdGeom.Mesh(prim(stage, "skin"))).GetPrimvar("st").Get()).reshape(-1, 3, 2)
    np.testing.assert_allclose(st, src_st[faces], atol=1e-7)


def test_normals_keep_the_files_hard_edges(assets, tmp_path):
    # RiggedSimple: a cylinder whose cap and side vertices are split (160 file vertices at 96
    # positions) with different normals. At rest the written normals are the file's normals
    # (trimesh) carried into stage space; split copies share a normal only where the file's do.
    glb = assets / "RiggedSimple" / "RiggedSimple.glb"
    _, stage = _bake(tmp_path, "skin", str(glb), "--frames", "1:2")
    ref = list(trimesh.load(glb, process=False).geometry.values())[0]
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    rest = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    normals = np.asarray(mesh.GetNormalsAttr().Get(), dtype=np.float64)
    rot = _kabsch(np.asarray(ref.vertices), rest)
    file_normals = np.asarray(ref.vertex_normals) @ rot.T
    cos = np.einsum("ij,ij->i", normals, file_normals)
    assert cos.min() > 0.9, f"worst normal {np.degrees(np.arccos(cos.min())):.1f} degrees off the file's"
    _, pos_id = np.unique(np.round(rest, 5), axis=0, return_inverse=True)
    i, j = np.nonzero((pos_id[:, None] == pos_id[None, :]) & ~np.eye(len(rest), dtype=bool))
    same_in_file = np.einsum("ij,ij->i", file_normals[i], file_normals[j]) > 0.999
    same_written = np.einsum("ij,ij->i", normals[i], normals[j]) > 0.999999
    assert i.size > 0 and np.array_equal(same_in_file, same_written)
    # animated normals are time-sampled with the points
    assert len(mesh.GetNormalsAttr().GetTimeSamples()) == 2


def test_the_rest_pose_stands_in_stage_space(assets, tmp_path):
    # CesiumMan's bind space is Z-up under a Y-up stage: the default-time points stand where its
    # frames stand
    _, stage = _bake(tmp_path, "skin", str(assets / "CesiumMan" / "CesiumMan.glb"), "--frames", "1:1")
    attr = UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr()
    rest, first = np.asarray(attr.Get()), np.asarray(attr.Get(1))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    for pts in (rest, first):
        size = np.ptp(pts, axis=0)
        assert size.argmax() == 1  # tallest along Y (lying in bind space it was tallest along Z)
    assert abs(np.ptp(rest[:, 1]) / np.ptp(first[:, 1]) - 1) < 0.1
    assert np.linalg.norm(rest.mean(0) - first.mean(0)) < 0.2 * np.ptp(first[:, 1])


def test_stages_are_named_after_their_character_and_compose(assets, tmp_path):
    a, sa = _bake(tmp_path, "skin", str(assets / "CesiumMan" / "CesiumMan.glb"), "--frames", "1:2", name="cesium.usdc")
    b, sb = _bake(tmp_path, "skin", "arm", "--frames", "0:1", name="arm.usdc")
    for stage, name in ((sa, "CesiumMan"), (sb, "arm")):
        root = stage.GetDefaultPrim()
        assert root.GetName() == name and Usd.ModelAPI(root).GetKind() == Kind.Tokens.component
    shot = Usd.Stage.CreateInMemory()
    shot.GetRootLayer().subLayerPaths = [str(a), str(b)]
    assert {p.GetName() for p in shot.GetPseudoRoot().GetChildren()} == {"CesiumMan", "arm"}


def test_lbs_is_a_variant_of_the_bake(tmp_path):
    _, stage = _bake(tmp_path, "simulate", "arm", "--frames", "0:2", "--lbs")
    root = stage.GetDefaultPrim()
    vset = root.GetVariantSets().GetVariantSet("deformer")
    assert set(vset.GetVariantNames()) == {"physical", "lbs"} and vset.GetVariantSelection() == "physical"
    skin, lbs = UsdGeom.Imageable(prim(stage, "skin")), UsdGeom.Imageable(prim(stage, "lbs"))
    assert skin.ComputeVisibility() == UsdGeom.Tokens.inherited and lbs.ComputePurpose() == UsdGeom.Tokens.guide
    vset.SetVariantSelection("lbs")
    assert skin.ComputeVisibility() == UsdGeom.Tokens.invisible
    assert lbs.ComputeVisibility() == UsdGeom.Tokens.inherited and lbs.ComputePurpose() == UsdGeom.Tokens.default_


@pytest.mark.parametrize("command", ["skin", "simulate"])
def test_welded_topology_on_request(assets, tmp_path, command):
    extra = ["--no-collisions", "--preroll", "0"] if command == "simulate" else []
    _, stage = _bake(tmp_path, command, str(assets / "CesiumMan" / "CesiumMan.glb"), "--frames", "1:2",
                     "--topology", "welded", *extra)
    mesh = UsdGeom.Mesh(prim(stage, "skin"))
    assert len(mesh.GetPointsAttr().Get(1)) == 2338 and not UsdGeom.PrimvarsAPI(mesh).HasPrimvar("st")


def test_the_report_and_the_bake_show_where_the_physics_acts(tmp_path):
    import json

    report = tmp_path / "report"
    out, stage = _bake(tmp_path, "simulate", "arm", "--frames", "0:4", "--lbs", "--report", str(report))
    data = json.loads((report / "report.json").read_text())
    assert data["metrics"]["frame"] == [0.0, 1.0, 2.0, 3.0, 4.0]
    for name in ("volume.png", "intersections.png", "contacts.png", "step_time.png", "offset_map.png",
                 "offset_from_lbs.png"):
        assert (report / name).stat().st_size > 1000, name
    # the skin's per-vertex distance from LBS, time-sampled: |skin - lbs| from the file's own points
    skin = UsdGeom.Mesh(prim(stage, "skin"))
    lbs = UsdGeom.Mesh(prim(stage, "lbs"))
    pv = UsdGeom.PrimvarsAPI(skin).GetPrimvar("deviationFromLbs")
    assert pv.GetInterpolation() == UsdGeom.Tokens.vertex and pv.GetAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
    for tc in (1.0, 4.0):
        want = np.linalg.norm(np.asarray(skin.GetPointsAttr().Get(tc), dtype=np.float64)
                              - np.asarray(lbs.GetPointsAttr().Get(tc), dtype=np.float64), axis=1)
        np.testing.assert_allclose(np.asarray(pv.Get(tc)), want, atol=2e-7)
    assert np.asarray(pv.Get(4.0)).max() > 1e-4  # the physics acts


def test_every_mesh_of_robot_expressive_is_written_following_its_joints(assets, tmp_path):
    # 14 meshes: the skinned right hand (the skin), the other skinned hand and 12 body parts
    # parented rigidly to joints; each written with its own vertices and faces, and matching
    # the glTF spec's own evaluation (pygltflib: node world x points, LBS for the skinned ones)
    from oracles import gltf_reference_points

    glb = assets / "RobotExpressive" / "RobotExpressive.glb"
    out, stage = _bake(tmp_path, "skin", str(glb), "--clip", "Walking", "--frames", "0:6")
    import pygltflib

    g = pygltflib.GLTF2().load(str(glb))
    mesh_nodes = {n.name.replace(".", "_"): i for i, n in enumerate(g.nodes) if n.mesh is not None}  # prim names
    assert len(mesh_nodes) == 14
    root = stage.GetDefaultPrim()
    written = {p.GetName(): UsdGeom.Mesh(p) for p in root.GetChildren() if p.IsA(UsdGeom.Mesh)}
    assert len(written) == 14 and "Hand_R" in written  # the skin keeps its file's name
    fps = stage.GetTimeCodesPerSecond()
    for tc in (0.0, 3.0, 6.0):
        ref = gltf_reference_points(glb, tc / fps, animation="Walking")
        size = float(np.linalg.norm(np.ptp(np.concatenate(list(ref.values())), axis=0)))
        for name, mesh in written.items():
            node = mesh_nodes[name]
            got = np.asarray(mesh.GetPointsAttr().Get(tc), dtype=np.float64)
            assert got.shape == ref[node].shape, name
            assert np.abs(got - ref[node]).max() < 1e-5 * size, f"{name} at {tc}"
    assert _validate_ok(out)


def _validate_ok(path) -> bool:
    from pxr import UsdValidation

    reg = UsdValidation.ValidationRegistry()
    ctx = UsdValidation.ValidationContext([reg.GetOrLoadValidatorByName(m.name) for m in reg.GetAllValidatorMetadata()])
    errors = [e for e in ctx.Validate(Usd.Stage.Open(str(path))) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]
    return True


def test_smoothing_groups_keep_a_vertex_with_a_zero_normal_to_itself():
    from warpskin.io.render import group_normals, smoothing_groups

    weld = np.array([0, 0, 1, 2])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    groups = smoothing_groups(weld, normals)
    assert groups.min() >= 0 and len(set(groups.tolist())) == 4
    pts = np.array([[0.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]])
    n = group_normals(pts, np.array([[0, 2, 3]]), groups)
    np.testing.assert_allclose(n[[0, 2, 3]], np.tile([0.0, 0.0, 1.0], (3, 1)))


def test_inner_layers_are_written_as_simulated(tmp_path):
    _, stage = _bake(tmp_path, "simulate", "arm", "--frames", "0:1", "--layers")
    skin = np.asarray(UsdGeom.Mesh(prim(stage, "skin")).GetPointsAttr().Get())
    bone = UsdGeom.Mesh(prim(stage, "layer_bone"))
    assert np.abs(np.asarray(bone.GetPointsAttr().Get()) - skin).max() > 1e-3  # the bone layer, not the skin
    assert bone.GetPurposeAttr().Get() == UsdGeom.Tokens.guide

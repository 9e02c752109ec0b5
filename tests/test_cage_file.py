"""A user's own cage from a mesh file (``--cage FILE``): read back from .obj, .usda and .glb
against the arrays written (with the file's transform applied), every malformed cage refused
with one line naming the file's vertices, and a simulation through it."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from oracles import prim
from warpskin.errors import RigError
from warpskin.io.cage_file import read_cage_mesh

# a generic rigid placement (no axis-aligned ties)
ROT = trimesh.transformations.rotation_matrix(0.7, [0.3, 1.0, -0.2])[:3, :3]
SHIFT = np.array([0.13, -0.41, 0.27])


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.9)
    return np.asarray(s.vertices, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


def _write_obj(path, v, f, *, split=False):
    with open(path, "w") as fh:
        fh.write("# a cage\n")
        if split:  # every corner its own vertex (a seam everywhere), welded on read
            for t in f:
                for k in t:
                    fh.write("v %.17g %.17g %.17g\n" % tuple(v[k]))
            for i in range(len(f)):
                fh.write(f"f {3 * i + 1}/{3 * i + 1} {3 * i + 2}/{3 * i + 2} {3 * i + 3}/{3 * i + 3}\n")
            return
        for p in v:
            fh.write("v %.17g %.17g %.17g\n" % tuple(p))
        fh.write("f %d %d %d\n" % tuple(f[0] + 1))
        for t in f[1:]:
            fh.write("f %d %d %d\n" % tuple(t - len(v)))  # relative (negative) indices: -1 is the last


def _same_mesh(got, v, f, atol):
    """The read mesh equals (v, f) up to the order of its points."""
    assert got.points.shape == v.shape and got.triangles.shape == f.shape
    d = np.linalg.norm(got.points[:, None] - v[None], axis=2)
    match = d.argmin(axis=1)
    assert d.min(axis=1).max() < atol and len(set(match.tolist())) == len(v)
    assert sorted(map(tuple, match[got.triangles].tolist())) == sorted(map(tuple, f.tolist()))


def test_obj_reads_back_welded_with_the_files_numbers(tmp_path):
    v, f = _sphere()
    _write_obj(tmp_path / "a.obj", v, f)
    got = read_cage_mesh(tmp_path / "a.obj")
    np.testing.assert_array_equal(got.points, v)
    np.testing.assert_array_equal(got.triangles, f)
    np.testing.assert_array_equal(got.file_ids, np.arange(1, len(v) + 1))  # OBJ counts from 1
    _write_obj(tmp_path / "b.obj", v, f, split=True)
    got = read_cage_mesh(tmp_path / "b.obj")
    _same_mesh(got, v, f, 1e-12)
    first = {}
    for i, t in enumerate(f):  # the first copy of each vertex in the split file
        for c, k in enumerate(t):
            first.setdefault(int(k), 3 * i + c + 1)
    match = np.linalg.norm(got.points[:, None] - v[None], axis=2).argmin(axis=1)
    assert got.file_ids.tolist() == [first[int(k)] for k in match]


def test_usda_and_glb_apply_their_transforms(tmp_path):
    from pxr import Gf, Usd, UsdGeom

    v, f = _sphere()
    want = v @ ROT.T + SHIFT
    stage = Usd.Stage.CreateNew(str(tmp_path / "c.usda"))
    xf = UsdGeom.Xform.Define(stage, "/Cage")
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = ROT, SHIFT
    xf.AddTransformOp().Set(Gf.Matrix4d(m.T.tolist()))  # USD: row vectors
    mesh = UsdGeom.Mesh.Define(stage, "/Cage/mesh")
    mesh.GetPointsAttr().Set(v.tolist())
    mesh.GetFaceVertexCountsAttr().Set([3] * len(f))
    mesh.GetFaceVertexIndicesAttr().Set(f.ravel().tolist())
    stage.Save()
    got = read_cage_mesh(tmp_path / "c.usda")
    np.testing.assert_allclose(got.points, want, atol=1e-6)
    np.testing.assert_array_equal(got.triangles, f)
    scene = trimesh.Scene()
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = ROT, SHIFT
    scene.add_geometry(trimesh.Trimesh(v, f, process=False), transform=t)
    scene.export(str(tmp_path / "d.glb"))
    got = read_cage_mesh(tmp_path / "d.glb")
    _same_mesh(got, want, f, 1e-5)


def test_a_bad_cage_file_is_refused_naming_the_record(tmp_path):
    v, f = _sphere()
    with pytest.raises(RigError, match="no such cage file"):
        read_cage_mesh(tmp_path / "none.obj")
    (tmp_path / "x.ply").write_text("ply\n")
    with pytest.raises(RigError, match="unknown cage format .ply"):
        read_cage_mesh(tmp_path / "x.ply")
    (tmp_path / "bad.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")
    with pytest.raises(RigError, match=r"bad.obj: line 4: face refers to vertex 7, the file has 3"):
        read_cage_mesh(tmp_path / "bad.obj")
    (tmp_path / "short.obj").write_text("v 0 0\n")
    with pytest.raises(RigError, match="line 1: a vertex needs three numbers"):
        read_cage_mesh(tmp_path / "short.obj")
    two = trimesh.Scene([trimesh.Trimesh(v, f), trimesh.Trimesh(v + 3.0, f)])
    two.export(str(tmp_path / "two.glb"))
    with pytest.raises(RigError, match="exactly one triangle mesh, found 2"):
        read_cage_mesh(tmp_path / "two.glb")


# --------------------------------------------------------------------------------------------
# checks against the character: CesiumMan and its automatic cage, written as a file
# --------------------------------------------------------------------------------------------
_CESIUM = {}


@pytest.fixture
def cesium(assets):
    """CesiumMan's rig and its automatic cage (built once)."""
    from warpskin.preprocess.cage import build_cage, character_soup
    from warpskin.scene import resolve_scene

    if not _CESIUM:
        rig = resolve_scene(assets / "CesiumMan" / "CesiumMan.glb").rig()
        soup = character_soup(rig)
        _CESIUM["v"] = rig, build_cage(soup.points, soup.triangles)
    return _CESIUM["v"]


def test_a_malformed_cage_is_refused_with_the_files_vertex_numbers(cesium, tmp_path, device):
    from warpskin.errors import RigWarning
    from warpskin.metrics import signed_volume
    from warpskin.preprocess.cage import cage_from_mesh

    rig, cage = cesium
    v, f = cage.vertices / rig.meters_per_unit, cage.triangles

    def load(name, vv, ff):
        _write_obj(tmp_path / name, vv, ff)
        return read_cage_mesh(tmp_path / name)

    ok = cage_from_mesh(load("ok.obj", v, f), rig, device=device)
    np.testing.assert_allclose(ok.vertices, cage.vertices, atol=1e-12)
    assert signed_volume(ok.vertices, ok.triangles) > 0
    # a hole: the three edges of the dropped face, one named by its OBJ numbers
    a, b, c = sorted(int(k) + 1 for k in f[0])
    with pytest.raises(RigError, match=r"open.obj: the cage is not closed: 3 boundary edges, e.g. between vertices "
                                       rf"({a} and {b}|{a} and {c}|{b} and {c}) \(the file's numbers\)"):
        cage_from_mesh(load("open.obj", v, f[1:]), rig, device=device)
    # one face turned: its edges run the same way as their neighbours'
    g = f.copy()
    g[5] = g[5][::-1]
    with pytest.raises(RigError, match="not wound consistently: 3 edges"):
        cage_from_mesh(load("turned.obj", v, g), rig, device=device)
    # a face repeated: three edges in three faces
    with pytest.raises(RigError, match="not manifold: 3 edges shared by more than two faces"):
        cage_from_mesh(load("twice.obj", v, np.concatenate([f, f[:1]])), rig, device=device)
    # every face turned: turned back, with one warning
    with pytest.warns(RigWarning, match="point inward; turned outward"):
        inward = cage_from_mesh(load("inward.obj", v, f[:, ::-1]), rig, device=device)
    assert signed_volume(inward.vertices, inward.triangles) == pytest.approx(signed_volume(ok.vertices, ok.triangles))
    # the cage in centimetres around a character in metres: it holds none of it
    with pytest.raises(RigError, match=r"the cage holds 0 % of the character's points at rest"):
        cage_from_mesh(load("cm.obj", 100.0 * v, f), rig, device=device)


@pytest.mark.slow
def test_cesium_man_simulates_through_a_cage_file(cesium, tmp_path, device):
    from pxr import Usd, UsdGeom

    from warpskin.run import simulate
    from warpskin.scene import resolve_scene

    rig, cage = cesium
    _write_obj(tmp_path / "cage.obj", cage.vertices / rig.meters_per_unit, cage.triangles)
    scene = resolve_scene(rig.source)
    # frames 1-14: without the fail-safe the cage's legs passed through each other from frame 13
    # (30 pairs, 44 at frame 14, where its LBS has 263 and 240); with it, and its pass after
    # the volume loop, none
    result = simulate(scene, tmp_path / "out.usdc", device=device, frames=(1, 14), with_lbs=True, progress=False,
                      check_intersections=True, cage=tmp_path / "cage.obj")
    s, m = result.summary, result.metrics
    print(f"fail-safe pairs per frame {m['fail_safe_pairs']}; pairs {m['intersecting_pairs']}, "
          f"LBS {m['intersecting_pairs_lbs']}")
    assert s["cage"]["source"] == str(tmp_path / "cage.obj") and s["cage"]["vertices"] == len(cage.vertices)
    stage = Usd.Stage.Open(str(result.path))
    root = stage.GetDefaultPrim()
    guide = UsdGeom.Mesh(root.GetChild("cage"))
    np.testing.assert_array_equal(np.asarray(guide.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3), cage.triangles)
    np.testing.assert_allclose(np.asarray(guide.GetPointsAttr().Get(Usd.TimeCode.Default()), dtype=np.float64),
                               cage.vertices, atol=1e-6 * rig.size())
    skin = UsdGeom.Mesh(prim(stage, "skin"))
    assert np.asarray(skin.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3).tolist() == rig.file_triangles.tolist()
    pts = np.asarray(skin.GetPointsAttr().Get(14))
    assert pts.shape == (rig.file_vertex_count, 3) and np.isfinite(pts).all()
    assert min(m["intersecting_pairs_lbs"]) > 80 and max(m["intersecting_pairs"]) == 0
    assert s["fail_safe_pairs"] > 0
    v0 = m["volume_rest"]
    assert np.all(np.abs(np.array(m["volume"]) / v0 - 1) <= np.abs(np.array(m["volume_lbs"]) / v0 - 1) + 1e-3)


def test_cli_cage_file_errors_exit_2(tmp_path):
    import subprocess
    import sys

    (tmp_path / "c.txt").write_text("")
    for arg, want in (("c.txt", "--cage must be auto, always, none or a mesh file"), ("none.obj", "no such file")):
        r = subprocess.run([sys.executable, "-m", "warpskin", "simulate", "arm", "--cage", str(tmp_path / arg), "-o",
                            str(tmp_path / "o.usdc")], capture_output=True, text=True)
        assert r.returncode == 2 and want in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "o.usdc").exists()

"""glTF 2.0 importer: sampling against hand-computed values, accessor decoding, welding, the
third-party assets against an independent NumPy/SciPy skinning reference, and broken files.

Small glTF files are generated in ``tmp_path`` with pygltflib; nothing is written to the repo.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
from pygltflib import (
    GLTF2,
    AccessorSparseIndices,
    AccessorSparseValues,
    Attributes,
    Mesh,
    Node,
    Primitive,
    Skin,
    Sparse,
)
from scipy.spatial.transform import Rotation, Slerp

from gltf_builder import _NP, FLOAT, UBYTE, UINT, USHORT, GltfBuilder
from oracles import gltf_reference_points, lbs, rig_lbs
from warpskin.io.gltf import list_gltf_meshes, load_gltf
from warpskin.rig import RigError, RigWarning



# box: x, y in [-0.5, 0.5], z in [0, 2]; corner index = 4 * zi + 2 * yi + xi
CORNERS = np.array([[x, y, z] for z in (0.0, 2.0) for y in (-0.5, 0.5) for x in (-0.5, 0.5)])
QUADS = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
ROOT_T = np.array([1.0, 2.0, 3.0])
J1_T = np.array([0.0, 0.0, 1.0])


def box_geometry(split: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Box positions and outward-wound triangles; ``split`` gives every face its own 4 vertices
    (24 vertices, like a glTF exporter splitting at normal seams)."""
    if split:
        pos = CORNERS[QUADS.ravel()]
        quads = np.arange(24).reshape(6, 4)
    else:
        pos, quads = CORNERS, QUADS
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return pos, tris


def box_skin(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bottom vertices follow joint 0; top vertices 0.75 joint 1 + 0.25 joint 0."""
    top = pos[:, 2] > 1.0
    joints = np.zeros((len(pos), 4), dtype=np.int64)
    weights = np.zeros((len(pos), 4))
    joints[top, 0], joints[top, 1] = 1, 0
    weights[:, 0] = np.where(top, 0.75, 1.0)
    weights[top, 1] = 0.25
    return joints, weights


def make_box(
    tmp_path: Path,
    *,
    name: str = "box",
    split: bool = True,
    positions: np.ndarray | None = None,
    joints: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    weight_ctype: int = FLOAT,
    animations: list[tuple[str | None, list]] = (),
    kind: str = "glb",
    mutate: Callable[[GltfBuilder], None] | None = None,
) -> Path:
    """A 2-joint skinned box: ``root`` (non-joint, T(1,2,3)) -> ``j0`` -> ``j1`` (T(0,0,1));
    mesh node ``box`` (its own transform, T(100,0,0), must be ignored)."""
    b = GltfBuilder()
    pos, tris = box_geometry(split)
    pos = pos if positions is None else positions
    ji, jw = box_skin(pos)
    ji = ji if joints is None else joints
    jw = jw if weights is None else weights
    if weight_ctype != FLOAT:
        jw = np.round(jw * np.iinfo(_NP[weight_ctype]).max)
    attrs = Attributes(
        POSITION=b.accessor(pos),
        JOINTS_0=b.accessor(ji, USHORT),
        WEIGHTS_0=b.accessor(jw, weight_ctype, normalized=weight_ctype != FLOAT),
    )
    prim = Primitive(attributes=attrs, indices=b.accessor(tris.reshape(-1, 1), USHORT, atype="SCALAR"), mode=4)
    b.g.meshes.append(Mesh(name="boxmesh", primitives=[prim]))
    b.node(name="root", translation=ROOT_T.tolist(), children=[1])
    b.node(name="j0", children=[2])
    b.node(name="j1", translation=J1_T.tolist())
    b.node(name="box", mesh=0, skin=0, translation=[100.0, 0.0, 0.0])
    b.g.scenes[0].nodes = [0, 3]
    bind = np.stack([np.eye(4), np.eye(4)])
    bind[0, :3, 3] = ROOT_T
    bind[1, :3, 3] = ROOT_T + J1_T
    ibm = np.linalg.inv(bind).transpose(0, 2, 1).reshape(2, 16)  # column-major
    b.g.skins.append(Skin(joints=[1, 2], inverseBindMatrices=b.accessor(ibm)))
    for anim_name, channels in animations:
        b.animation(anim_name, channels)
    if mutate is not None:
        mutate(b)
    return b.save(tmp_path / f"{name}.{'glb' if kind == 'glb' else 'gltf'}", kind)


def rot_z(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_matrix()


def quat_z(deg: float) -> np.ndarray:
    return Rotation.from_euler("z", deg, degrees=True).as_quat()  # x, y, z, w


# --------------------------------------------------------------------------------------------
# Sampling against hand-computed values
# --------------------------------------------------------------------------------------------


def test_rest_pose_structure(tmp_path: Path) -> None:
    rig = load_gltf(make_box(tmp_path))
    sk = rig.skeleton
    assert sk.joint_names == ["j0", "j1"]
    assert sk.parents.tolist() == [-1, 0]
    np.testing.assert_allclose(sk.root_transform[0][:3, 3], ROOT_T)
    np.testing.assert_allclose(sk.rest_translation[1], J1_T)
    assert rig.clips == {}
    # bind pose: the rest mesh skins onto itself (the mesh node's T(100,0,0) is ignored)
    mats = rig.skinning_matrices(None, 0.0)
    np.testing.assert_allclose(lbs(rig.vertices, rig.joint_indices, rig.joint_weights, mats), rig.vertices, atol=1e-12)
    world = rig.joint_world_transforms(None, 0.0)
    np.testing.assert_allclose(world[1][:3, 3], ROOT_T + J1_T)


def test_step_sampling(tmp_path: Path) -> None:
    vals = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 1.0], [2.0, 1.0, 1.0]])
    rig = load_gltf(make_box(tmp_path, animations=[("hop", [(2, "translation", [0.0, 1.0, 2.0], vals, "STEP")])]))
    track = rig.clip("hop").tracks[(1, "translation")]
    assert track.interpolation == "STEP"
    np.testing.assert_allclose(track.sample(0.5), vals[0])
    np.testing.assert_allclose(track.sample(0.999), vals[0])
    np.testing.assert_allclose(track.sample(1.0), vals[1])
    np.testing.assert_allclose(track.sample(1.5), vals[1])
    np.testing.assert_allclose(track.sample(9.0), vals[2])
    world = rig.joint_world_transforms("hop", 1.5)
    np.testing.assert_allclose(world[1][:3, 3], ROOT_T + vals[1])


def test_linear_translation_lerp_and_rotation_slerp(tmp_path: Path) -> None:
    tvals = np.array([[0.0, 0.0, 1.0], [4.0, 0.0, 1.0]])
    rvals = np.stack([quat_z(0.0), quat_z(90.0)])
    anim = [
        (2, "translation", [0.0, 1.0], tvals, "LINEAR"),
        (2, "rotation", [0.0, 1.0], rvals, "LINEAR"),
    ]
    rig = load_gltf(make_box(tmp_path, animations=[("turn", anim)]))
    clip = rig.clip("turn")
    assert clip.start == 0.0 and clip.end == 1.0
    np.testing.assert_allclose(clip.tracks[(1, "translation")].sample(0.25), [1.0, 0.0, 1.0], atol=1e-12)
    # slerp half-way between 0 and 90 degrees about z is a 45 degree turn: (0, 0, sin 22.5, cos 22.5)
    q = clip.tracks[(1, "rotation")].sample(0.5)
    np.testing.assert_allclose(q, [0.0, 0.0, math.sin(math.radians(22.5)), math.cos(math.radians(22.5))], atol=1e-7)
    world = rig.joint_world_transforms(clip, 0.5)
    np.testing.assert_allclose(world[1][:3, :3], rot_z(45.0), atol=1e-7)
    np.testing.assert_allclose(world[1][:3, 3], ROOT_T + [2.0, 0.0, 1.0], atol=1e-7)
    # a third of the way: 30 degrees (slerp is uniform in angle, lerp would not be)
    np.testing.assert_allclose(rig.joint_world_transforms(clip, 1.0 / 3.0)[1][:3, :3], rot_z(30.0), atol=1e-7)
    # the top of the box follows: a top vertex at t = 0.5
    mats = rig.skinning_matrices(clip, 0.5)
    p = np.array([[0.5, 0.5, 2.0]])
    k = int(np.nonzero(np.all(rig.vertices == p, axis=1))[0][0])
    got = lbs(rig.vertices[k : k + 1], rig.joint_indices[k : k + 1], rig.joint_weights[k : k + 1], mats)
    p_j1 = rot_z(45.0) @ (p[0] - ROOT_T - J1_T) + ROOT_T + [2.0, 0.0, 1.0]  # G_1 @ IBM_1 @ p
    expected = 0.75 * p_j1 + 0.25 * p[0]
    np.testing.assert_allclose(got[0], expected, atol=1e-7)


def test_cubicspline_hermite(tmp_path: Path) -> None:
    t0, t1 = 1.0, 3.0
    p0, p1 = np.array([0.0, 0.0, 1.0]), np.array([2.0, 1.0, 1.0])
    a0, b0 = np.array([9.0, 9.0, 9.0]), np.array([1.0, 0.0, 0.5])  # in/out tangents of key 0
    a1, b1 = np.array([0.0, 2.0, -0.5]), np.array([7.0, 7.0, 7.0])  # of key 1
    vals = np.stack([a0, p0, b0, a1, p1, b1])  # glTF order: in-tangent, value, out-tangent
    rig = load_gltf(make_box(tmp_path, animations=[("curve", [(2, "translation", [t0, t1], vals, "CUBICSPLINE")])]))
    track = rig.clip("curve").tracks[(1, "translation")]
    assert track.interpolation == "CUBICSPLINE" and track.values.shape == (2, 3, 3)
    dt = t1 - t0
    for t in (1.5, 2.0, 2.7):
        s = (t - t0) / dt
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        expected = h00 * p0 + h10 * dt * b0 + h01 * p1 + h11 * dt * a1
        np.testing.assert_allclose(track.sample(t), expected, atol=1e-12)
    # at the mid-point by hand: 0.5 p0 + 0.125*2*b0 + 0.5 p1 - 0.125*2*a1
    mid = 0.5 * p0 + 0.25 * b0 + 0.5 * p1 - 0.25 * a1
    np.testing.assert_allclose(rig.joint_world_transforms("curve", 2.0)[1][:3, 3], ROOT_T + mid, atol=1e-7)
    np.testing.assert_allclose(track.sample(t1), p1)


def test_clip_names_unnamed_and_duplicates(tmp_path: Path) -> None:
    ch = [(2, "translation", [0.0, 1.0], [[0, 0, 1], [0, 0, 2]], "LINEAR")]
    anims = [(None, ch), ("walk", ch), ("walk", ch), (None, [(1, "rotation", [0.0], [quat_z(10)], "LINEAR")])]
    rig = load_gltf(make_box(tmp_path, animations=anims))
    assert list(rig.clips) == ["animation_0", "walk", "walk_1", "animation_3"]
    assert list(rig.clip("animation_3").tracks) == [(0, "rotation")]


def test_matrix_nodes_and_non_joint_nodes_between_joints(tmp_path: Path) -> None:
    """j0 given as a column-major matrix; a static non-joint node (rotation, uniform scale,
    translation) sits between j0 and j1; j1 has LINEAR rotation and CUBICSPLINE translation.
    The skeleton's forward kinematics must equal the product of the node transforms."""
    m_j0 = np.eye(4)
    m_j0[:3, :3] = Rotation.from_euler("x", 30, degrees=True).as_matrix()
    m_j0[:3, 3] = [0.1, 0.2, 0.3]
    mid_q = Rotation.from_euler("y", 40, degrees=True).as_quat()
    rq = np.stack([quat_z(0), quat_z(120)])
    cubic = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1], [0, 0, 0]], dtype=float)

    def mutate(b: GltfBuilder) -> None:
        b.g.nodes[1] = Node(name="j0", matrix=m_j0.T.ravel().tolist(), children=[4])
        b.node(name="offset", translation=[0.5, 0, 0], rotation=mid_q.tolist(), scale=[2, 2, 2], children=[2])

    anims = [("a", [(2, "rotation", [0.0, 2.0], rq, "LINEAR"), (2, "translation", [0.0, 2.0], cubic, "CUBICSPLINE")])]
    rig = load_gltf(make_box(tmp_path, animations=anims, mutate=mutate))
    assert rig.skeleton.parents.tolist() == [-1, 0]

    def trs(t: Any, q: Any, s: Any) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(q).as_matrix() * np.asarray(s, dtype=float)
        m[:3, 3] = t
        return m

    root = trs(ROOT_T, [0, 0, 0, 1], [1, 1, 1])
    offset = trs([0.5, 0, 0], mid_q, [2, 2, 2])
    for t in (0.0, 0.5, 1.3, 2.0):
        s = t / 2.0
        h = np.array([2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2])
        tr = h[0] * cubic[1] + h[1] * 2.0 * cubic[2] + h[2] * cubic[4] + h[3] * 2.0 * cubic[3]
        rot = Slerp([0.0, 2.0], Rotation.from_quat(rq))([t]).as_quat()[0]
        g1 = root @ m_j0 @ offset @ trs(tr, rot, [1, 1, 1])
        world = rig.joint_world_transforms("a", t)
        np.testing.assert_allclose(world[0], root @ m_j0, atol=1e-9)
        np.testing.assert_allclose(world[1], g1, atol=1e-9)


def test_an_animated_non_joint_ancestor_moves_the_skeleton(tmp_path: Path) -> None:
    # the non-joint root node's translation is kept (glTF: a joint's world transform includes
    # every ancestor's), not dropped with a warning
    channels = [
        (0, "translation", [0.0, 1.0], [[0, 0, 0], [1, 0, 0]], "LINEAR"),  # the non-joint root
        (2, "scale", [0.0], [[1, 1, 2]], "STEP"),
    ]
    anims = [("a", channels)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigWarning)
        rig = load_gltf(make_box(tmp_path, animations=anims))
    clip = rig.clip("a")
    assert list(clip.tracks) == [(1, "scale")] and list(clip.ancestor_tracks) == [(0, "translation")]
    w0, w1, half = (rig.joint_world_transforms(clip, t) for t in (0.0, 1.0, 0.5))
    np.testing.assert_allclose(w1[:, :3, 3] - w0[:, :3, 3], np.tile([1.0, 0.0, 0.0], (rig.joint_count, 1)), atol=1e-12)
    np.testing.assert_allclose(half[:, :3, 3] - w0[:, :3, 3], np.tile([0.5, 0.0, 0.0], (rig.joint_count, 1)), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Accessor decoding
# --------------------------------------------------------------------------------------------


def test_weld_box(tmp_path: Path) -> None:
    rig = load_gltf(make_box(tmp_path, split=True))
    pos, tris = box_geometry(split=True)
    assert rig.file_vertex_count == 24 and rig.vertex_count == 8
    np.testing.assert_array_equal(rig.vertices[rig.weld_map], pos)
    np.testing.assert_array_equal(rig.file_triangles, tris)
    np.testing.assert_array_equal(rig.triangles, rig.weld_map[tris])
    assert rig.report.closed and rig.report.manifold
    rig.require_closed()
    raw = load_gltf(make_box(tmp_path, split=True), weld=False)
    assert raw.vertex_count == 24 and not raw.report.closed
    np.testing.assert_array_equal(raw.weld_map, np.arange(24))


@pytest.mark.parametrize("ctype", [UBYTE, USHORT])
def test_normalized_integer_weights(tmp_path: Path, ctype: int) -> None:
    rig = load_gltf(make_box(tmp_path, weight_ctype=ctype))
    top = rig.vertices[:, 2] > 1
    # 0.75 / 0.25 quantised: exact for 16 bits up to 1/65535; ubyte rounds (191, 64) -> renormalised
    tol = 2.0 / np.iinfo(_NP[ctype]).max
    np.testing.assert_allclose(rig.joint_weights[top, 0], 0.75, atol=tol)
    np.testing.assert_allclose(rig.joint_weights.sum(1), 1.0, atol=1e-6)


def test_quantised_weight_rounding_is_renormalised(tmp_path: Path) -> None:
    """0.5/0.5 as UNSIGNED_BYTE rounds to 128 + 128 = 256/255: within quantisation, so it is
    silently renormalised instead of failing validation."""
    pos, _ = box_geometry(split=False)
    _, jw = box_skin(pos)
    top = pos[:, 2] > 1
    jw[top, :2] = 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error", RigWarning)
        rig = load_gltf(make_box(tmp_path, split=False, weights=jw, weight_ctype=UBYTE))
    np.testing.assert_allclose(rig.joint_weights[top, :2], 0.5)
    np.testing.assert_allclose(rig.joint_weights.sum(1), 1.0)


def test_interleaved_strided_accessors_two_weight_sets_and_byte_offsets(tmp_path: Path) -> None:
    """POSITION and WEIGHTS_0 interleaved in one strided buffer view (accessor byteOffsets),
    plus a second JOINTS_1/WEIGHTS_1 set."""
    pos, tris = box_geometry(split=False)
    ji, jw = box_skin(pos)
    jw2 = jw.copy()
    jw *= 0.5  # half the weight in set 0, half in set 1 (on joint 1 at the top, joint 0 below)
    jw2 *= 0.5
    j2 = ji.copy()

    def mutate(b: GltfBuilder) -> None:
        rec = np.zeros(8, dtype=[("p", "<f4", 3), ("w", "<f4", 4), ("pad", "<u1", 4)])  # 32-byte stride
        rec["p"], rec["w"] = pos, jw
        view = b.view(rec.tobytes(), stride=32)
        p_acc = b.raw_accessor(view, FLOAT, 8, "VEC3", offset=0)
        w_acc = b.raw_accessor(view, FLOAT, 8, "VEC4", offset=12)
        attrs = Attributes(
            POSITION=p_acc,
            JOINTS_0=b.accessor(ji, UBYTE),
            WEIGHTS_0=w_acc,
            JOINTS_1=b.accessor(j2, USHORT),
            WEIGHTS_1=b.accessor(jw2),
        )
        idx = b.accessor(tris.reshape(-1, 1), UINT, atype="SCALAR")
        b.g.meshes[0].primitives = [Primitive(attributes=attrs, indices=idx)]

    rig = load_gltf(make_box(tmp_path, mutate=mutate))
    assert rig.joint_indices.shape == (8, 8)
    np.testing.assert_allclose(rig.vertices, pos)
    ref = load_gltf(make_box(tmp_path, name="ref", split=False))
    np.testing.assert_allclose(rig.dense_weights(), ref.dense_weights(), atol=1e-7)


def test_multiple_primitives_non_indexed_strip_and_fan(tmp_path: Path) -> None:
    """Four primitives: indexed TRIANGLES, non-indexed TRIANGLES, TRIANGLE_STRIP, TRIANGLE_FAN."""
    pos, tris = box_geometry(split=False)
    ji, jw = box_skin(pos)

    def mutate(b: GltfBuilder) -> None:
        def prim(p: np.ndarray, mode: int, idx: np.ndarray | None) -> Primitive:
            j, w = box_skin(p)
            attrs = Attributes(POSITION=b.accessor(p), JOINTS_0=b.accessor(j, UBYTE), WEIGHTS_0=b.accessor(w))
            i = None if idx is None else b.accessor(idx.reshape(-1, 1), UBYTE, atype="SCALAR")
            return Primitive(attributes=attrs, indices=i, mode=mode)

        b.g.meshes[0].primitives = [
            prim(pos, 4, tris[:4].ravel()),  # 4 triangles, indexed
            prim(pos[tris[4:6].ravel()], 4, None),  # 2 triangles, non-indexed (6 vertices)
            prim(pos, 5, np.array([0, 1, 2, 3])),  # strip (glTF rule): (0,1,2), (1,3,2)
            prim(pos, 6, np.array([4, 5, 7, 6])),  # fan: (5,7,4), (7,6,4)
        ]

    rig = load_gltf(make_box(tmp_path, mutate=mutate), weld=False)
    assert rig.file_vertex_count == 8 + 6 + 8 + 8
    strip = np.array([[0, 1, 2], [1, 3, 2]])
    fan = np.array([[5, 7, 4], [7, 6, 4]])
    expected = np.concatenate([tris[:4], np.arange(6).reshape(2, 3) + 8, strip + 14, fan + 22])
    np.testing.assert_array_equal(rig.triangles, expected)
    meshes = list_gltf_meshes(tmp_path / "box.glb")
    assert meshes[0]["vertices"] == 30 and meshes[0]["triangles"] == 10
    welded = load_gltf(tmp_path / "box.glb")
    assert welded.vertex_count == 8


def test_sparse_accessor(tmp_path: Path) -> None:
    """POSITION as a sparse accessor over an all-zero base (no bufferView)."""
    pos, _ = box_geometry(split=True)

    def mutate(b: GltfBuilder) -> None:
        nz = np.nonzero(np.any(pos != 0.0, axis=1))[0]
        iv = b.view(nz.astype(np.uint16).tobytes())
        vv = b.view(pos[nz].astype(np.float32).tobytes())
        acc = b.raw_accessor(None, FLOAT, len(pos), "VEC3")
        b.g.accessors[acc].sparse = Sparse(
            count=len(nz),
            indices=AccessorSparseIndices(bufferView=iv, componentType=USHORT),
            values=AccessorSparseValues(bufferView=vv),
        )
        b.g.meshes[0].primitives[0].attributes.POSITION = acc

    rig = load_gltf(make_box(tmp_path, mutate=mutate))
    np.testing.assert_array_equal(rig.vertices[rig.weld_map], pos)


@pytest.mark.parametrize("kind", ["embedded", "external"])
def test_gltf_json_variants(tmp_path: Path, kind: str) -> None:
    ref = load_gltf(make_box(tmp_path, name="ref"))
    rig = load_gltf(make_box(tmp_path, kind=kind))
    np.testing.assert_array_equal(rig.vertices, ref.vertices)
    np.testing.assert_array_equal(rig.triangles, ref.triangles)
    np.testing.assert_allclose(rig.inverse_bind, ref.inverse_bind)


def test_list_meshes_and_selection(tmp_path: Path) -> None:
    def mutate(b: GltfBuilder) -> None:
        b.node(name="box", mesh=0, skin=0)  # same name again: made unique
        b.node(name="prop", mesh=0)  # not skinned
        b.g.scenes[0].nodes += [4, 5]

    path = make_box(tmp_path, mutate=mutate)
    meshes = list_gltf_meshes(path)
    assert [m["name"] for m in meshes] == ["box", "box_1", "prop"]
    assert [m["skin"] for m in meshes] == [0, 0, None]
    assert [m["skinned"] for m in meshes] == [True, True, False]
    assert meshes[0]["vertices"] == 24 and meshes[0]["triangles"] == 12 and meshes[0]["joints"] == 2
    assert load_gltf(path, mesh="box_1").mesh_name == "box_1"
    assert load_gltf(path).mesh_name == "box"
    with pytest.raises(RigError, match=r"no mesh named 'nope'.*'box'.*'box_1'.*'prop'"):
        load_gltf(path, mesh="nope")
    with pytest.raises(RigError, match=r"'prop' is not skinned"):
        load_gltf(path, mesh="prop")


# --------------------------------------------------------------------------------------------
# Third-party assets against an independent reference
# --------------------------------------------------------------------------------------------


def _ref_accessor(g: GLTF2, blob: bytes, index: int) -> np.ndarray:
    """Independent accessor reader: gather bytes by (start + i*stride + k)."""
    a = g.accessors[index]
    bv = g.bufferViews[a.bufferView]
    dt = np.dtype(_NP[a.componentType])
    n = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[a.type]
    stride = bv.byteStride or n * dt.itemsize
    start = (bv.byteOffset or 0) + (a.byteOffset or 0)
    raw = np.frombuffer(blob, np.uint8)
    idx = start + np.arange(a.count)[:, None] * stride + np.arange(n * dt.itemsize)[None, :]
    out = raw[idx].copy().view(dt).reshape(a.count, n).astype(np.float64)
    if a.normalized:
        out /= np.iinfo(dt).max
    return out


def _ref_skin(path: Path, anim_index: int, t: float) -> tuple[np.ndarray, int]:
    """LBS of the first skinned mesh straight from the node tree, with SciPy slerp."""
    g = GLTF2().load(str(path))
    blob = g.binary_blob()
    trs = {}
    for i, n in enumerate(g.nodes):
        trs[i] = [
            np.array(n.translation if n.translation is not None else [0.0, 0.0, 0.0]),
            np.array(n.rotation if n.rotation is not None else [0.0, 0.0, 0.0, 1.0]),
            np.array(n.scale if n.scale is not None else [1.0, 1.0, 1.0]),
        ]
    anim = g.animations[anim_index]
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        assert s.interpolation in (None, "LINEAR")
        times = _ref_accessor(g, blob, s.input).ravel()
        vals = _ref_accessor(g, blob, s.output)
        tc = min(max(t, times[0]), times[-1])
        slot = {"translation": 0, "rotation": 1, "scale": 2}[ch.target.path]
        if slot == 1:
            trs[ch.target.node][1] = Slerp(times, Rotation.from_quat(vals))([tc]).as_quat()[0]
        else:
            trs[ch.target.node][slot] = np.array([np.interp(tc, times, vals[:, c]) for c in range(3)])

    def local(i: int) -> np.ndarray:
        n = g.nodes[i]
        if n.matrix is not None:
            return np.array(n.matrix, dtype=np.float64).reshape(4, 4).T
        tt, q, sc = trs[i]
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(q).as_matrix() * sc
        m[:3, 3] = tt
        return m

    glob: dict[int, np.ndarray] = {}

    def visit(i: int, parent: np.ndarray) -> None:
        glob[i] = parent @ local(i)
        for c in g.nodes[i].children or []:
            visit(c, glob[i])

    for root in g.scenes[g.scene or 0].nodes:
        visit(root, np.eye(4))
    mesh_node = next(n for n in g.nodes if n.skin is not None)
    skin = g.skins[mesh_node.skin]
    prim = g.meshes[mesh_node.mesh].primitives[0]
    assert len(g.meshes[mesh_node.mesh].primitives) == 1
    p = _ref_accessor(g, blob, prim.attributes.POSITION)
    j = _ref_accessor(g, blob, prim.attributes.JOINTS_0).astype(np.int64)
    w = _ref_accessor(g, blob, prim.attributes.WEIGHTS_0)
    ibm = _ref_accessor(g, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    mats = np.stack([glob[n] for n in skin.joints]) @ ibm
    return lbs(p, j, w, mats), len(skin.joints)


def test_cesium_man_counts(assets: Path) -> None:
    path = assets / "CesiumMan" / "CesiumMan.glb"
    rig = load_gltf(path)
    assert rig.vertex_count == 2338 and rig.file_vertex_count == 3273
    assert rig.triangle_count == 4672 and rig.joint_count == 19
    assert rig.report.closed
    assert rig.name == "CesiumMan" and rig.source == str(path) and rig.up_axis == "Y"
    clip = rig.clip()
    assert clip.start == pytest.approx(0.0417, abs=1e-4)
    assert clip.duration == pytest.approx(1.9583, abs=1e-4)
    assert list_gltf_meshes(path)[0]["vertices"] == 3273


@pytest.mark.parametrize(
    "rel, anim",
    [
        ("CesiumMan/CesiumMan.glb", 0),
        ("RiggedFigure/RiggedFigure.glb", 0),
        ("RiggedSimple/RiggedSimple.glb", 0),
        ("Fox/Fox.glb", 2),
    ],
)
@pytest.mark.parametrize("t", [0.5, 1.0])
def test_lbs_matches_independent_reference(assets: Path, rel: str, anim: int, t: float) -> None:
    path = assets / rel
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RigWarning)
        rig = load_gltf(path)
    ref, n_joints = _ref_skin(path, anim, t)
    assert rig.joint_count == n_joints
    clip = list(rig.clips.values())[anim]
    got = lbs(rig.vertices, rig.joint_indices, rig.joint_weights, rig.skinning_matrices(clip, t))
    err = np.abs(got[rig.weld_map] - ref).max()
    assert err <= 1e-5 * rig.size(), err


def test_other_assets_load(assets: Path) -> None:
    fig = load_gltf(assets / "RiggedFigure" / "RiggedFigure.glb")
    assert (fig.vertex_count, fig.triangle_count, fig.joint_count) == (130, 256, 19) and fig.report.closed
    simple = load_gltf(assets / "RiggedSimple" / "RiggedSimple.glb")
    assert (simple.vertex_count, simple.triangle_count, simple.joint_count) == (96, 188, 2) and simple.report.closed
    fox = load_gltf(assets / "Fox" / "Fox.glb")
    assert list(fox.clips) == ["Survey", "Walk", "Run"]
    assert (fox.vertex_count, fox.file_vertex_count, fox.joint_count) == (290, 1728, 24)
    assert fox.clip("Walk").duration == pytest.approx(0.7083, abs=1e-3)
    skin = load_gltf(assets / "SimpleSkin" / "SimpleSkin.gltf")
    assert (skin.vertex_count, skin.triangle_count, skin.joint_count) == (10, 8, 2)
    assert skin.report.closed is False
    with pytest.raises(RigError, match="not a closed manifold"):
        skin.require_closed()
    hand = load_gltf(assets / "WebXRGenericHand" / "left.glb")
    assert hand.clips == {} and hand.joint_count == 25 and hand.vertex_count == 1159
    assert hand.clip().name == "rest"


def test_recursive_skeletons(assets: Path) -> None:
    path = assets / "RecursiveSkeletons" / "RecursiveSkeletons.glb"
    meshes = list_gltf_meshes(path)
    assert len(meshes) == 84 and len({m["name"] for m in meshes}) == 84
    assert {m["mesh"] for m in meshes} == {0} and sorted(m["skin"] for m in meshes) == list(range(84))
    assert all(m["vertices"] == 40 and m["triangles"] == 76 and m["joints"] == 10 for m in meshes)
    # default: the first of the (equally large) skinned meshes, its own 10-joint chain
    rig = load_gltf(path)
    assert rig.mesh_name == meshes[0]["name"] and rig.joint_count == 10 and rig.vertex_count == 40
    assert rig.skeleton.parents.tolist() == [-1] + list(range(9))
    assert list(rig.clips) == ["Track0"] and len(rig.clip("Track0").tracks) == 10
    # a nested skeleton: its chain hangs off joints of another skin, which are animated; that
    # animation is kept (the root's ancestors move with the clip), nothing is dropped
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        nested = load_gltf(path, mesh=meshes[1]["name"])
    assert not [w for w in caught if "non-joint" in str(w.message)]
    assert nested.joint_count == 10 and list(nested.skeleton.root_chains) == [0]
    clip = nested.clip("Track0")
    assert clip.ancestor_tracks
    a, b = clip.root_transforms(nested.skeleton, 0.3)[0], clip.root_transforms(nested.skeleton, 1.3)[0]
    assert not np.allclose(a, b)


# --------------------------------------------------------------------------------------------
# Broken input
# --------------------------------------------------------------------------------------------


def test_missing_and_garbage_files(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="nothere.glb: no such file"):
        load_gltf(tmp_path / "nothere.glb")
    junk = tmp_path / "junk.gltf"
    junk.write_bytes(b"\x00\x01 definitely not json")
    with pytest.raises(RigError, match="junk.gltf: not a glTF file"):
        load_gltf(junk)
    other = tmp_path / "other.gltf"
    other.write_text(json.dumps({"hello": 1}))
    with pytest.raises(RigError, match="other.gltf: not a glTF file"):
        list_gltf_meshes(other)
    bad_types = tmp_path / "types.gltf"
    bad_types.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": [{"children": "abc"}], "meshes": 3}))
    with pytest.raises(RigError, match="types.gltf: malformed glTF"):
        load_gltf(bad_types)


def test_truncated_glb(tmp_path: Path) -> None:
    path = make_box(tmp_path)
    data = path.read_bytes()
    for cut in (8, len(data) // 2, len(data) - 4):
        (tmp_path / "cut.glb").write_bytes(data[:cut])
        with pytest.raises(RigError, match="cut.glb: truncated GLB"):
            load_gltf(tmp_path / "cut.glb")


def test_no_skin(tmp_path: Path) -> None:
    def mutate(b: GltfBuilder) -> None:
        b.g.nodes[3].skin = None
        b.g.skins = []

    path = make_box(tmp_path, kind="embedded", mutate=mutate)
    with pytest.raises(RigError, match=r"box.gltf: has no skinned mesh; meshes: 'box' \(not skinned\)"):
        load_gltf(path)
    assert list_gltf_meshes(path)[0]["skin"] is None


def test_weights_count_mismatch(tmp_path: Path) -> None:
    pos, _ = box_geometry()
    _, jw = box_skin(pos)
    msg = r"box.glb: .*primitive 0: accessor count mismatch: POSITION has 24 .* WEIGHTS_0 has 20"
    with pytest.raises(RigError, match=msg):
        load_gltf(make_box(tmp_path, weights=jw[:20]))


def test_joint_index_out_of_range(tmp_path: Path) -> None:
    pos, _ = box_geometry(split=False)
    ji, _ = box_skin(pos)
    ji[5, 0] = 7
    msg = r"vertices 5 reference joint indices 7, outside \[0, 1\] \(the skeleton has 2 joints\)"
    with pytest.raises(RigError, match=msg):
        load_gltf(make_box(tmp_path, split=False, joints=ji))


def test_nan_position(tmp_path: Path) -> None:
    pos, _ = box_geometry()
    pos = pos.copy()
    pos[3, 1] = np.nan
    with pytest.raises(RigError, match=r"vertices 3 have NaN or inf positions"):
        load_gltf(make_box(tmp_path, positions=pos))


def test_vertex_without_weight(tmp_path: Path) -> None:
    pos, _ = box_geometry(split=False)
    _, jw = box_skin(pos)
    jw[2] = 0.0
    with pytest.raises(RigError, match=r"vertices 2 have no weight"):
        load_gltf(make_box(tmp_path, split=False, weights=jw))


def test_weights_sum_to_100_are_normalised(tmp_path: Path) -> None:
    pos, _ = box_geometry()
    _, jw = box_skin(pos)
    with pytest.warns(RigWarning, match="weights sum to 100 instead of 1"):
        rig = load_gltf(make_box(tmp_path, weights=jw * 100.0))
    np.testing.assert_allclose(rig.joint_weights.sum(1), 1.0)
    np.testing.assert_allclose(rig.joint_weights.max(), 1.0)


def test_hierarchy_cycle(tmp_path: Path) -> None:
    def mutate(b: GltfBuilder) -> None:
        b.g.nodes[2].children = [0]  # root -> j0 -> j1 -> root

    with pytest.raises(RigError, match=r"box.glb: cycle in the node hierarchy: .*'root'.*'j0'.*'j1'"):
        load_gltf(make_box(tmp_path, mutate=mutate))

    def mutate_self(b: GltfBuilder) -> None:
        b.g.nodes[1].children = [1, 2]

    with pytest.raises(RigError, match="cycle"):
        load_gltf(make_box(tmp_path, name="self", mutate=mutate_self))


def test_missing_external_bin(tmp_path: Path) -> None:
    path = make_box(tmp_path, kind="external")
    path.with_suffix(".bin").unlink()
    with pytest.raises(RigError, match=r"box.gltf: buffer 0 refers to the external file 'box.bin'.*does not exist"):
        load_gltf(path)


def test_missing_position_and_unpaired_joints(tmp_path: Path) -> None:
    def no_pos(b: GltfBuilder) -> None:
        b.g.meshes[0].primitives[0].attributes.POSITION = None

    with pytest.raises(RigError, match=r"mesh 'box' primitive 0 has no POSITION"):
        load_gltf(make_box(tmp_path, name="a", mutate=no_pos))

    def no_weights(b: GltfBuilder) -> None:
        b.g.meshes[0].primitives[0].attributes.WEIGHTS_0 = None

    with pytest.raises(RigError, match=r"primitive 0 has JOINTS_0 without WEIGHTS_0"):
        load_gltf(make_box(tmp_path, name="b", mutate=no_weights))

    def lines(b: GltfBuilder) -> None:
        b.g.meshes[0].primitives[0].mode = 1

    with pytest.raises(RigError, match=r"primitive 0 has mode 1 \(LINES\)"):
        load_gltf(make_box(tmp_path, name="c", mutate=lines))


def test_out_of_range_data(tmp_path: Path) -> None:
    def view_past_end(b: GltfBuilder) -> None:
        b.g.bufferViews[0].byteLength += 4096

    with pytest.raises(RigError, match=r"buffer view 0 .* is out of range"):
        load_gltf(make_box(tmp_path, name="a", mutate=view_past_end))

    def accessor_past_view(b: GltfBuilder) -> None:
        b.g.accessors[0].byteOffset = 16

    with pytest.raises(RigError, match=r"POSITION \(accessor 0\) is out of range"):
        load_gltf(make_box(tmp_path, name="b", mutate=accessor_past_view))

    def bad_index(b: GltfBuilder) -> None:
        b.g.meshes[0].primitives[0].attributes.JOINTS_0 = 99

    with pytest.raises(RigError, match=r"refers to accessors\[99\]"):
        load_gltf(make_box(tmp_path, name="c", mutate=bad_index))

    def short_ibm(b: GltfBuilder) -> None:
        b.g.accessors[b.g.skins[0].inverseBindMatrices].count = 1

    with pytest.raises(RigError, match=r"inverseBindMatrices: accessor count mismatch"):
        load_gltf(make_box(tmp_path, name="d", mutate=short_ibm))

    def bad_vertex_index(b: GltfBuilder) -> None:
        b.g.meshes[0].primitives[0].indices = b.accessor(np.array([[0], [1], [30]]), USHORT, atype="SCALAR")

    with pytest.raises(RigError, match=r"vertex index 30, outside \[0, 23\]"):
        load_gltf(make_box(tmp_path, name="e", mutate=bad_vertex_index))


def test_bad_animation_keys(tmp_path: Path) -> None:
    anims = [("bad", [(2, "translation", [0.0, 1.0, 1.0], np.zeros((3, 3)), "LINEAR")])]
    with pytest.raises(RigError, match=r"animation 'bad' channel 0 \('j1' translation\).*not strictly increasing"):
        load_gltf(make_box(tmp_path, animations=anims))
    anims = [("short", [(2, "translation", [0.0, 1.0], np.zeros((2, 3)), "CUBICSPLINE")])]
    with pytest.raises(RigError, match=r"2 key times need 6 VEC3 output values"):
        load_gltf(make_box(tmp_path, name="c", animations=anims))



# --------------------------------------------------------------------------------------------
# Nested skeletons: a joint's world transform includes every animated ancestor (glTF spec)
# --------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_every_nested_skeleton_follows_its_animated_ancestors(assets: Path) -> None:
    # RecursiveSkeletons: 84 skins whose chains hang off joints of other skins, which are
    # animated; each instance's LBS against the spec's own evaluation at generic times
    path = assets / "RecursiveSkeletons" / "RecursiveSkeletons.glb"
    meshes = list_gltf_meshes(path)
    times = (0.37, 1.21, 1.93)
    refs = {t: gltf_reference_points(path, t) for t in times}
    worst = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RigWarning)  # unit-size hints, bind-space scale
        for k, entry in enumerate(meshes):
            rig = load_gltf(path, mesh=entry["name"])
            for t in times:
                got = rig_lbs(rig, rig.skinning_matrices(rig.clip(None), t))[rig.weld_map]
                ref = refs[t][entry["node"]]
                worst = max(worst, float(np.abs(got - ref).max() / np.linalg.norm(np.ptp(ref, axis=0))))
    assert worst < 1e-6, f"worst instance off by {worst:.3g} of its size"

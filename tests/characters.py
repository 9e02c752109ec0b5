"""Open, multi-piece test characters with shoes and fists, made by the tests from what they
have (nothing is written to the repo):

* :func:`dancer_file`: the shipped production-style dancer written as a glTF file with a scaled
  root (one mesh of open, overlapping pieces: what a motion-capture library hands over);
* :func:`mannequin_file`: the shipped procedural mannequin written as a glTF file, so it goes
  through the importer as a user's file does (its shoes and fists other skinned meshes);
* :func:`cut_cesium_man`: CesiumMan cut into open pieces along its joints (every triangle on
  its dominant joint's piece, each piece's vertices its own, shrunk by 0.2 % about its centre so
  that no importer welds them back), with a rounded shoe around each
  foot (a mesh of its own, bending at the toe) and a fist block on each hand (a mesh of its own
  on the hand joint).
* :func:`pressed_arm`: the coarse procedural arm's skin at LBS 150 degrees, the forearm pressed
  into the upper arm, with one detection run on it (the contacts and fail-safe tests' scene);
* :func:`generic_sphere`, :func:`random_rotation`: an icosphere in a generic position (turned
  and jittered: no symmetry, no ties), the guards' test pieces.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gltf_builder import write_rig_glb


def random_rotation(seed: int) -> np.ndarray:
    """A proper rotation ``[3, 3]`` drawn from ``seed``."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def generic_sphere(centre, radius: float, seed: int, subdivisions: int = 3, jitter: float = 0.01):
    """An icosphere of ``radius`` about ``centre``, turned by :func:`random_rotation` and each
    vertex's radius jittered by up to ``jitter`` of it: ``(points [N, 3], triangles [T, 3])``."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    rng = np.random.default_rng(seed)
    v = s.vertices @ random_rotation(seed).T
    v = v * (1.0 + jitter * rng.uniform(-1, 1, size=(len(v), 1)))
    return v + np.asarray(centre, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


def dancer_file(tmp_path: Path, root_scale: float | None = 0.1, **params) -> Path:
    """The procedural dancer (:mod:`warpskin.scenes.dancer`: one skinned mesh of open and
    overlapping pieces, clothes, hair, eyes) as ``dancer.glb``, its skeleton under a root node
    scaled by ``root_scale`` (the character stands 0.18 m tall in its file at 0.1), as a
    motion-capture library exports one."""
    from warpskin.scenes.dancer import make_dancer

    rig = make_dancer(**params)
    return write_rig_glb(rig, Path(tmp_path) / "dancer.glb", root_scale=root_scale)


def mannequin_file(tmp_path: Path, **params) -> Path:
    """The procedural mannequin (:mod:`warpskin.scenes.mannequin`) as ``mannequin.glb``."""
    from warpskin.scenes.mannequin import make_mannequin

    rig = make_mannequin(**params)
    return write_rig_glb(rig, Path(tmp_path) / "mannequin.glb")


def _rounded_box(center, radii, res: int = 8, power: float = 4.0):
    from warpskin.scenes.mannequin import _shell

    return _shell(center, radii, power, res)


def cut_cesium_man(assets: Path):
    """CesiumMan in pieces, with shoes and fists, as a rig (bind space is CesiumMan's, Z up)."""
    from warpskin.io import load_rig
    from warpskin.rig import Attachment, Rig

    src = load_rig(Path(assets) / "CesiumMan" / "CesiumMan.glb")
    names = src.skeleton.joint_names
    ft = src.file_triangles
    ji_f, jw_f = src.joint_indices[src.weld_map], src.joint_weights[src.weld_map]
    bind_f = src.vertices[src.weld_map]
    dom = ji_f[np.arange(len(ji_f)), np.argmax(jw_f, axis=1)]
    tri_piece = np.array([np.bincount(dom[t], minlength=len(names)).argmax() for t in ft])
    pts, tris, ji, jw, uvs = [], [], [], [], []
    base = 0
    for piece in np.unique(tri_piece):
        sel = ft[tri_piece == piece]
        used, inv = np.unique(sel.ravel(), return_inverse=True)
        piece_pts = bind_f[used]
        centre = piece_pts.mean(axis=0)
        pts.append(centre + (1.0 - 2e-3) * (piece_pts - centre))  # shrunk a little: pieces do not weld
        ji.append(ji_f[used])
        jw.append(jw_f[used])
        tris.append(inv.reshape(-1, 3) + base)
        uvs.append(src.render.uvs[tri_piece == piece])
        base += used.size
    from warpskin.io.render import RenderAttributes

    order = np.concatenate([np.nonzero(tri_piece == p)[0] for p in np.unique(tri_piece)])
    render = RenderAttributes(uvs=np.concatenate(uvs), normals=None, materials=list(src.render.materials),
                              triangle_material=None if src.render.triangle_material is None
                              else src.render.triangle_material[order])
    rig = Rig.from_file_arrays(name="cut_cesium_man", points=np.concatenate(pts), triangles=np.concatenate(tris),
                               skeleton=src.skeleton, joint_indices=np.concatenate(ji), joint_weights=np.concatenate(jw),
                               inverse_bind=src.inverse_bind, clips=src.clips, source="test:cut_cesium_man",
                               mesh_name="body", weld=False, up_axis=src.up_axis, render=render)
    # shoes around the feet and fists on the hands, in bind space (CesiumMan's is Z up)
    bind_world = src.bind_world_transforms()
    attachments = []
    for side in ("L", "R"):
        foot = next(j for j, n in enumerate(names) if n == f"leg_joint_{side}_5")
        toe = [j for j, n in enumerate(names) if src.skeleton.parents[j] == foot]
        hand = next(j for j, n in enumerate(names) if n in (f"Skeleton_arm_joint_{side}__2_", f"Skeleton_arm_joint_{side}__3_")
                    and not any(src.skeleton.parents == j))
        fv = bind_f[dom == foot]
        lo, hi = fv.min(axis=0), fv.max(axis=0)
        c = 0.5 * (lo + hi)
        shoe_v, shoe_t = _rounded_box(c, 0.5 * (hi - lo) + 0.012, res=12)
        w_toe = np.zeros(len(shoe_v))
        if toe:
            t0 = bind_world[toe[0], :3, 3]
            d = shoe_v - bind_world[foot, :3, 3]
            axis = (t0 - bind_world[foot, :3, 3]) / np.linalg.norm(t0 - bind_world[foot, :3, 3])
            s = d @ axis
            s0 = (t0 - bind_world[foot, :3, 3]) @ axis
            w_toe = np.clip((s - (s0 - 0.02)) / 0.04, 0.0, 1.0)
        sj = np.stack([np.full(len(shoe_v), foot), np.full(len(shoe_v), toe[0] if toe else foot)], axis=1)
        attachments.append(Attachment(f"shoe_{side}", shoe_v, shoe_t, sj, np.stack([1 - w_toe, w_toe], 1),
                                      np.asarray(src.inverse_bind).copy()))
        hv = bind_f[dom == hand]
        lo, hi = hv.min(axis=0), hv.max(axis=0)
        fist_v, fist_t = _rounded_box(0.5 * (lo + hi), 0.5 * (hi - lo) + 0.01, res=8)
        attachments.append(Attachment(f"fist_{side}", fist_v, fist_t, np.full((len(fist_v), 1), hand),
                                      np.ones((len(fist_v), 1)), np.asarray(src.inverse_bind).copy()))
    rig.attachments = attachments
    return rig


def pressed_arm(device, capacity: int, pair_capacity: int | None = None):
    """The coarse arm's skin at LBS 150 degrees (forearm pressed into the upper arm): the
    rig, the detection, its contacts and the two states it ran on."""
    from oracles import coarse_arm

    from warpskin.collision import SelfCollision
    from warpskin.model import ModelParams, SkinModelBuilder
    from warpskin.run import initial_state

    rig = coarse_arm()
    builder = SkinModelBuilder(rig, ModelParams(volume=False))
    model = builder.finalize(device)
    col = SelfCollision(model)
    contacts = model.contacts(capacity, pair_capacity)
    a, b = model.state(), model.state()
    initial_state(model, a, rig.skinning_matrices("flex", 1.2))
    initial_state(model, b, rig.skinning_matrices("flex", 1.5))
    col.detect(a.x, b.x, contacts)
    return rig, col, contacts, a, b

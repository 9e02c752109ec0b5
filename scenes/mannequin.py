"""Procedural mannequin: an open, multi-piece character with shoes and fists, the kind of rig
a production hands over without a closed skin.

The body mesh is many separate pieces, as a jointed mannequin is built: closed shells (pelvis,
chest, head, ball joints) and open tubes (the limb segments and the neck, their ends hidden in
the neighbouring pieces). A limb segment is skinned to its bone and blends into its neighbour
over ``blend`` at each end, so LBS stretches it a little where it bends, as a real rig does. The
shoes and fists are meshes of their own: each shoe a rounded box on its foot that bends at the
toe joint, each fist a rounded block with four knuckles and a thumb (five pieces, all on the
hand joint: LBS moves them rigidly).

The rest pose is a T-pose (arms along the x axis, the character faces +z, Y up, metres, about
1.8 m tall); the clips bring the arms down. Clips (keys at ``key_rate``):

* ``walk``: two strides, arms swinging against the legs;
* ``run``: two faster strides, knees and elbows deeply bent;
* ``kick``: the right leg kicks forward to the height of the hips and returns.

Coordinates of a joint's local frame: the rest orientation is the identity for every joint, so
a key rotates about the world axes at rest (x: flexion, forward is negative for a leg; z: the
arms down).
"""

from __future__ import annotations

import math

import numpy as np

from warpskin.rig import Attachment, Clip, Rig, RigError, Skeleton, Track
from warpskin.transforms import quat_axis_angle, quat_multiply

__all__ = ["make_mannequin", "MANNEQUIN_DEFAULTS", "JOINTS"]

MANNEQUIN_DEFAULTS: dict = {
    "segments": 24,  # vertices around a limb tube
    "tube_ring": 0.02,  # [m] between rings along a tube
    "shell": 8,  # grid cells along a cube face of a shell (head, balls, shoes, fists)
    "blend": 0.04,  # [m] half-width of a segment's weight blend into its neighbour
    "key_rate": 30.0,  # keys per second
    "cycle": 1.0,  # [s] one walking stride pair (the run takes 0.7 of it)
    "arm_angle": 72.0,  # [degrees] the arms' rest pose below the horizontal (0: a T-pose)
    "stance": 0.08,  # [m] half the distance between the feet at rest
}

#: (name, parent) of every joint, parents first.
JOINTS = [
    ("hips", None), ("spine", "hips"), ("chest", "spine"), ("neck", "chest"), ("head", "neck"),
    *[(f"{j}_{s}", p if p in ("chest", "hips") else f"{p}_{s}") for s in ("l", "r") for j, p in (
        ("upperarm", "chest"), ("forearm", "upperarm"), ("hand", "forearm"), ("fingers", "hand"), ("thumb", "hand"),
        ("thigh", "hips"), ("shin", "thigh"), ("foot", "shin"), ("toe", "foot"))],
]

SHOULDER = 0.20  # [m] from the middle
UPPER, FORE = 0.27, 0.24  # [m] bone lengths of the arm


def arm_frame(sign: float, arm_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The shoulder ``[3]`` and the rotation ``[3, 3]`` whose columns are the arm's direction
    (shoulder to hand), its up (in the frontal plane) and the character's forward (+z), for the
    left (``sign`` 1) or right (-1) arm hanging ``arm_angle`` degrees below the horizontal."""
    a = math.radians(arm_angle)
    d = np.array([sign * math.cos(a), -math.sin(a), 0.0])
    up = np.cross(np.array([0.0, 0.0, 1.0]), d) * sign
    return np.array([sign * SHOULDER, 1.43, 0.0]), np.stack([d, up, [0.0, 0.0, 1.0]], axis=1)


def joint_positions(arm_angle: float, stance: float) -> dict[str, np.ndarray]:
    """Rest positions of every joint in the world [m]."""
    out = {"hips": (0.0, 0.95, 0.0), "spine": (0.0, 1.08, 0.0), "chest": (0.0, 1.24, 0.0), "neck": (0.0, 1.47, 0.0),
           "head": (0.0, 1.58, 0.0)}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        s, r = arm_frame(sign, arm_angle)
        d = r[:, 0]
        out[f"upperarm_{side}"] = s
        out[f"forearm_{side}"] = s + UPPER * d
        out[f"hand_{side}"] = s + (UPPER + FORE) * d
        out[f"fingers_{side}"] = s + (UPPER + FORE + 0.075) * d
        out[f"thumb_{side}"] = s + (UPPER + FORE + 0.03) * d + 0.03 * r[:, 2]
        x = sign * stance
        out[f"thigh_{side}"] = (x, 0.90, 0.0)
        out[f"shin_{side}"] = (x, 0.50, 0.0)
        out[f"foot_{side}"] = (x, 0.09, 0.0)
        out[f"toe_{side}"] = (x, 0.03, 0.11)
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


# --------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------
def _smoothstep(x, a: float, b: float):
    u = np.clip((np.asarray(x, dtype=np.float64) - a) / (b - a), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _shell(center, radii, power: float, res: int, rotation=None) -> tuple[np.ndarray, np.ndarray]:
    """A closed superellipsoid ``sum |x_i / r_i|^power = 1`` around ``center``, its axes the
    columns of ``rotation`` (default: the world's): a cube's faces gridded ``res x res``,
    welded, each point pushed out along its direction; triangles counter-clockwise from
    outside."""
    g = np.linspace(-1.0, 1.0, res + 1)
    u, v = np.meshgrid(g, g, indexing="ij")
    pts, tris = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            p = np.zeros((res + 1, res + 1, 3))
            p[..., axis] = sign
            p[..., (axis + 1) % 3] = u
            p[..., (axis + 2) % 3] = v
            base = sum(len(q) for q in pts)
            idx = base + np.arange((res + 1) ** 2).reshape(res + 1, res + 1)
            a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
            t = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
            if sign < 0:
                t = t[:, ::-1]
            pts.append(p.reshape(-1, 3))
            tris.append(t)
    p = np.concatenate(pts)
    t = np.concatenate(tris)
    key = np.round(p * res * 4).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    p, t = p[first], inv.ravel()[t]
    d = p / np.linalg.norm(p, axis=1, keepdims=True)
    r = d / (np.abs(d) ** power).sum(axis=1, keepdims=True) ** (1.0 / power) * np.asarray(radii)
    rot = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    if np.linalg.det(rot) < 0:  # a mirrored frame: keep the faces wound outward
        t = t[:, ::-1]
    return np.asarray(center) + r @ rot.T, t


def _tube(p0, p1, r0: float, r1: float, segments: int, ring: float, flatten: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """An open tube from ``p0`` to ``p1`` whose radius goes smoothly from ``r0`` to ``r1``;
    triangles counter-clockwise seen from outside."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    a = axis / length
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    rings = max(3, int(math.ceil(length / ring)) + 1)
    s = np.linspace(0.0, 1.0, rings)
    radius = r0 + (r1 - r0) * _smoothstep(s, 0.0, 1.0)
    th = np.arange(segments) / segments * 2.0 * math.pi
    pts = (p0[None, None] + s[:, None, None] * axis[None, None]
           + radius[:, None, None] * (np.cos(th)[None, :, None] * e1 + flatten * np.sin(th)[None, :, None] * e2))
    k = np.arange(rings - 1)[:, None]
    j = np.arange(segments)[None, :]
    v00, v01 = (k * segments + j).ravel(), (k * segments + (j + 1) % segments).ravel()
    v10, v11 = ((k + 1) * segments + j).ravel(), ((k + 1) * segments + (j + 1) % segments).ravel()
    tris = np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)])
    # outward: (e1 x e2) = a, so a ring walked e1 -> e2 is counter-clockwise about +a
    x = pts.reshape(-1, 3)
    n = np.cross(x[tris[:, 1]] - x[tris[:, 0]], x[tris[:, 2]] - x[tris[:, 0]])
    c = x[tris].mean(axis=1) - p0
    radial = c - np.outer(c @ a, a)
    if np.einsum("ij,ij->i", n, radial).sum() < 0:
        tris = tris[:, ::-1]
    return x, tris


class _Mesh:
    """Pieces appended into one mesh with per-vertex influences (two per vertex)."""

    def __init__(self) -> None:
        self.points, self.tris, self.ji, self.jw = [], [], [], []
        self.count = 0

    def add(self, pts: np.ndarray, tris: np.ndarray, ji: np.ndarray, jw: np.ndarray) -> None:
        self.points.append(pts)
        self.tris.append(tris + self.count)
        self.ji.append(ji)
        self.jw.append(jw)
        self.count += len(pts)

    def arrays(self):
        return (np.concatenate(self.points), np.concatenate(self.tris), np.concatenate(self.ji),
                np.concatenate(self.jw))


# --------------------------------------------------------------------------------------------
# the character
# --------------------------------------------------------------------------------------------
def _rot(*parts) -> np.ndarray:
    """The product of ``(axis, degrees)`` rotations, applied right to left."""
    q = np.array([0.0, 0.0, 0.0, 1.0])
    for axis, deg in parts:
        q = quat_multiply(q, quat_axis_angle(axis, deg))
    return q


X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)


def _pose(name: str, u: np.ndarray, arm_angle: float, hips: np.ndarray) -> dict[str, list]:
    """Local rotations (and the hips' translation) of clip ``name`` at normalised times ``u``
    in [0, 1]: ``{joint: [per-key quaternion]}``, ``"hips_t"``: per-key translation."""
    keys: dict[str, list] = {}

    def put(joint, q):
        keys.setdefault(joint, []).append(q)

    rest_hips = hips
    for x in u:
        if name in ("walk", "run"):
            run = name == "run"
            ph = 2.0 * math.pi * 2.0 * x  # two strides
            thigh_amp, knee_amp, arm_amp, elbow = (42.0, 95.0, 45.0, 85.0) if run else (26.0, 45.0, 22.0, 20.0)
            for side, sgn in (("l", 1.0), ("r", -1.0)):
                s = math.sin(ph if side == "l" else ph + math.pi)
                c = math.cos(ph if side == "l" else ph + math.pi)
                put(f"thigh_{side}", _rot((X, -thigh_amp * s - (10.0 if run else 0.0))))
                put(f"shin_{side}", _rot((X, knee_amp * max(0.0, c) + 5.0)))
                put(f"foot_{side}", _rot((X, -12.0 * s)))
                put(f"toe_{side}", _rot((X, 25.0 * max(0.0, -s))))
                # the arm down (about z), swinging against its leg (about x), the elbow bent forward
                put(f"upperarm_{side}", _rot((X, arm_amp * s), (Z, -sgn * (78.0 - arm_angle))))
                put(f"forearm_{side}", _rot((Y, -sgn * (elbow + 10.0 * s))))
                put(f"hand_{side}", _rot((X, 8.0 * s)))
                put(f"fingers_{side}", _rot((Z, sgn * 6.0 * (1.0 + s))))  # the grip tightens
                put(f"thumb_{side}", _rot((Y, 5.0 * s)))
            put("spine", _rot((Y, 6.0 * math.sin(ph)), (X, 8.0 if run else 2.0)))
            put("chest", _rot((Y, -6.0 * math.sin(ph))))
            put("neck", _rot((Y, 3.0 * math.sin(ph))))
            put("head", _rot((X, -4.0 if run else 0.0)))
            put("hips", _rot((Y, -5.0 * math.sin(ph))))
            keys.setdefault("hips_t", []).append(rest_hips + [0.0, (0.035 if run else 0.02) * math.cos(2 * ph) - 0.02, 0.0])
        elif name == "kick":
            k = math.sin(math.pi * min(1.0, max(0.0, (x - 0.15) / 0.6)))  # 0 -> 1 -> 0
            w = math.sin(math.pi * min(1.0, max(0.0, (x - 0.25) / 0.3)))  # the snap of the knee
            put("thigh_r", _rot((X, -85.0 * k)))
            put("shin_r", _rot((X, 70.0 * k * (1.0 - w) + 10.0 * k)))
            put("foot_r", _rot((X, 25.0 * k)))
            put("toe_r", _rot((X, 0.0)))
            put("thigh_l", _rot((X, -8.0 * k), (Z, 4.0 * k)))
            put("shin_l", _rot((X, 15.0 * k)))
            put("foot_l", _rot((X, -8.0 * k)))
            put("toe_l", _rot((X, 0.0)))
            for side, sgn in (("l", 1.0), ("r", -1.0)):
                put(f"upperarm_{side}", _rot((X, 30.0 * k * sgn), (Z, -sgn * (78.0 - arm_angle - 45.0 * k))))
                put(f"forearm_{side}", _rot((Y, -sgn * (25.0 + 40.0 * k))))
                put(f"hand_{side}", _rot((X, 0.0)))
                put(f"fingers_{side}", _rot((Z, sgn * 12.0 * k)))
                put(f"thumb_{side}", _rot((Y, 8.0 * k)))
            put("spine", _rot((X, 12.0 * k)))
            put("chest", _rot((X, 6.0 * k)))
            put("neck", _rot((X, -8.0 * k)))
            put("head", _rot((X, -6.0 * k)))
            put("hips", _rot((X, 10.0 * k)))
            keys.setdefault("hips_t", []).append(rest_hips + [0.0, -0.03 * k, -0.03 * k])
        else:  # pragma: no cover - names are fixed below
            raise RigError(f"mannequin: unknown clip {name!r}")
    return keys


def make_mannequin(**overrides) -> Rig:
    """The mannequin rig: the multi-piece ``body`` as the skin, the shoes and fists as meshes of
    their own (:class:`~warpskin.rig.Attachment`), clips ``walk``, ``run`` and ``kick``.

    Keyword arguments override :data:`MANNEQUIN_DEFAULTS`.

    Raises:
        RigError: an unknown parameter or a value out of range.
    """
    p = dict(MANNEQUIN_DEFAULTS)
    unknown = sorted(set(overrides) - set(p))
    if unknown:
        raise RigError(f"mannequin: unknown parameter(s) {unknown}; known: {sorted(p)}")
    p.update(overrides)
    seg, ring, res, blend = int(p["segments"]), float(p["tube_ring"]), int(p["shell"]), float(p["blend"])
    if seg < 6 or res < 2 or not (ring > 0 and blend > 0 and p["key_rate"] > 0 and p["cycle"] > 0):
        raise RigError(f"mannequin: need segments >= 6, shell >= 2 and positive lengths and rates, got {p}")
    names = [j[0] for j in JOINTS]
    index = {n: i for i, n in enumerate(names)}
    pos = joint_positions(float(p["arm_angle"]), float(p["stance"]))
    world = np.array([pos[n] for n in names])

    def blended(pts, own: str, prox: str | None = None, dist: str | None = None, share: float = 0.5):
        """Weights of a segment from joint ``own`` to its child ``dist``: its own bone, blending
        into ``prox`` (the parent) at its start and into ``dist`` at its end, ``share`` of each
        at the joint."""
        a = world[index[own]]
        b = world[index[dist]] if dist else a
        axis = b - a
        length = float(np.linalg.norm(axis))
        t = (pts - a) @ (axis / length) if length > 0 else np.zeros(len(pts))
        w_prox = share * (1.0 - _smoothstep(t, -blend, blend)) if prox else np.zeros(len(pts))
        w_dist = share * _smoothstep(t, length - blend, length + blend) if dist else np.zeros(len(pts))
        ji = np.stack([np.full(len(pts), index[own]), np.full(len(pts), index[prox or own]),
                       np.full(len(pts), index[dist or own])], axis=1)
        jw = np.stack([1.0 - w_prox - w_dist, w_prox, w_dist], axis=1)
        return ji, jw

    def rigid(pts, joint: str):
        n = len(pts)
        return (np.stack([np.full(n, index[joint])] * 3, axis=1), np.stack([np.ones(n), np.zeros(n), np.zeros(n)], 1))

    body = _Mesh()

    def tube(own, prox, dist, p0, p1, r0, r1, flatten=1.0):
        pts, tris = _tube(p0, p1, r0, r1, seg, ring, flatten)
        body.add(pts, tris, *blended(pts, own, prox, dist))

    def shell(joint, center, radii, power=2.0, prox=None, dist=None, rotation=None, mesh=None):
        pts, tris = _shell(center, radii, power, res, rotation)
        (mesh or body).add(pts, tris, *(blended(pts, joint, prox, dist) if (prox or dist) else rigid(pts, joint)))

    # torso: pelvis and chest shells, the abdomen and neck as open tubes between them
    shell("hips", (0.0, 0.96, 0.0), (0.16, 0.10, 0.11), 2.5)
    tube("spine", "hips", "chest", (0.0, 1.00, 0.0), (0.0, 1.22, 0.0), 0.125, 0.14, flatten=0.78)
    shell("chest", (0.0, 1.33, 0.0), (0.19, 0.15, 0.115), 2.5)
    tube("neck", "chest", "head", (0.0, 1.43, 0.0), (0.0, 1.60, 0.0), 0.05, 0.045)
    shell("head", (0.0, 1.69, 0.015), (0.095, 0.115, 0.105), 2.2)
    fists = {}
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        ua, fa, hd, fg, tb = (f"{j}_{side}" for j in ("upperarm", "forearm", "hand", "fingers", "thumb"))
        th, sh, ft = f"thigh_{side}", f"shin_{side}", f"foot_{side}"
        s0, rot = arm_frame(sgn, float(p["arm_angle"]))
        d = rot[:, 0]
        shell(ua, s0, (0.062, 0.062, 0.062))
        tube(ua, "chest", fa, s0 + 0.02 * d, s0 + (UPPER - 0.01) * d, 0.05, 0.041)
        shell(fa, s0 + UPPER * d, (0.04, 0.04, 0.04))
        tube(fa, ua, hd, s0 + (UPPER + 0.01) * d, s0 + (UPPER + FORE - 0.01) * d, 0.039, 0.03, flatten=0.85)
        x = sgn * float(p["stance"])
        shell(th, (x, 0.89, 0.0), (0.075, 0.075, 0.075))
        tube(th, "hips", sh, (x, 0.88, 0.0), (x, 0.52, 0.0), 0.072, 0.052)
        shell(sh, (x, 0.50, 0.0), (0.052, 0.052, 0.052))
        tube(sh, th, ft, (x, 0.49, 0.0), (x, 0.12, 0.0), 0.05, 0.034)
        shell(ft, (x, 0.09, 0.0), (0.036, 0.036, 0.036))
        # a fist: the palm on the hand, blending into the curled fingers (four knuckle rolls
        # side by side, a few millimetres apart) and the thumb across them
        fist = _Mesh()
        h0 = world[index[hd]]
        pts, tris = _shell(h0 + 0.045 * d, (0.045, 0.045, 0.036), 4.0, res, rot)
        fist.add(pts, tris, *blended(pts, hd, None, fg, share=0.4))
        for k in range(4):
            c = h0 + 0.088 * d + (0.033 - 0.022 * k) * rot[:, 1] + 0.012 * rot[:, 2]
            pts, tris = _shell(c, (0.016, 0.0095, 0.026), 2.5, max(3, res // 2), rot)
            fist.add(pts, tris, *blended(pts, fg, hd, None, share=0.3))
        c = h0 + 0.05 * d - 0.034 * rot[:, 1] + 0.036 * rot[:, 2]
        pts, tris = _shell(c, (0.032, 0.013, 0.015), 2.5, max(3, res // 2), rot)
        fist.add(pts, tris, *blended(pts, tb, hd, None, share=0.3))
        fists[side] = fist.arrays()
    b_pts, b_tris, b_ji, b_jw = body.arrays()

    parents = np.array([index[j[1]] if j[1] else -1 for j in JOINTS])
    skel = Skeleton(names, parents, np.array([world[i] - (world[parents[i]] if parents[i] >= 0 else 0.0)
                                              for i in range(len(names))]),
                    np.tile([0.0, 0.0, 0.0, 1.0], (len(names), 1)), np.ones((len(names), 3)))
    inverse_bind = np.linalg.inv(skel.world_from_local(skel.rest_local_matrices()))

    attachments = []
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        # a shoe: a rounded box around the foot, bending at the toe joint
        x = sgn * float(p["stance"])
        pts, tris = _shell((x, 0.05, 0.045), (0.055, 0.052, 0.135), 4.0, res + 4)
        zt = world[index[f"toe_{side}"]][2]
        w_toe = _smoothstep(pts[:, 2], zt - 0.03, zt + 0.03)
        ji = np.stack([np.full(len(pts), index[f"foot_{side}"]), np.full(len(pts), index[f"toe_{side}"])], 1)
        jw = np.stack([1.0 - w_toe, w_toe], 1)
        attachments.append(Attachment(name=f"shoe_{side}", vertices=pts, triangles=tris, joint_indices=ji,
                                      joint_weights=jw, joint_offsets=inverse_bind.copy()))
        f_pts, f_tris, f_ji, f_jw = fists[side]
        attachments.append(Attachment(name=f"fist_{side}", vertices=f_pts, triangles=f_tris, joint_indices=f_ji,
                                      joint_weights=f_jw, joint_offsets=inverse_bind.copy()))

    clips = {}
    rate = float(p["key_rate"])
    for name, length in (("walk", 2.0 * p["cycle"]), ("run", 1.4 * p["cycle"]), ("kick", 1.5 * p["cycle"])):
        n = int(round(length * rate)) + 1
        times = np.arange(n) / rate
        keys = _pose(name, times / times[-1], float(p["arm_angle"]), world[index["hips"]])
        tracks = {(index["hips"], "translation"): Track("translation", times, np.array(keys.pop("hips_t")))}
        for joint, qs in keys.items():
            tracks[(index[joint], "rotation")] = Track("rotation", times, np.array(qs))
        clips[name] = Clip(name, tracks, rate=rate)

    rig = Rig.from_file_arrays(name="mannequin", points=b_pts, triangles=b_tris, skeleton=skel, joint_indices=b_ji,
                               joint_weights=b_jw, inverse_bind=inverse_bind, clips=clips, source="generator:mannequin",
                               mesh_name="body", weld=False)
    rig.attachments = attachments
    return rig

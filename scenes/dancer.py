"""Procedural dancer: a production-style character, the kind a motion-capture library hands over.

One skinned mesh of many separate pieces, none of them a closed body on its own:

* ``body``: torso, arms and legs as one smooth surface, **open** at the neck, the wrists and the
  ankles (its boundary loops sit inside the pieces that meet it there);
* ``head``: skull, jaw and neck, open at the neck (tucked into the body's neck) and at two eye
  sockets;
* two ``eye`` balls in the sockets (crossing the head's surface at rest, skinned rigidly to the
  head), two hair ``bun`` s sunk into the skull (rigid to the head), a ``hair`` cap (an open
  sheet over the scalp) and a ``fringe`` (an open strip over the forehead);
* two ``hand`` s (mittens with a thumb, bending at the fingers), open at the wrist and tucked
  into the forearms;
* two ``shoe`` s, open at the top, the ankles inside them;
* baggy ``trousers`` (open at the waist and at both cuffs) and a short-sleeved ``shirt`` (open
  at the collar, the hem and both sleeves), each lying outside the body at rest; with ``skirt``
  the trousers' piece is a flared skirt instead (one tube over both thighs, open at the waist
  and at its hem above the knees, skinned to the hips and both thighs).

Smooth surfaces (body, head, hands, trousers, shirt) are iso-surfaces of smooth unions of round
cones (marching cubes on a grid of spacing ``cell``), cut open by planes, smoothed (Taubin) and
flipped towards Delaunay; their skin weights are a soft minimum over the round cones, each
tagged with its bone, so that they blend where the shapes blend. The rest pose is an A-pose
(arms ``arm_angle`` degrees below the horizontal), facing +z, Y up, metres, 1.80 m tall.

Clips (keys at ``key_rate``): ``dance``: bounces with pumping arms, a sway with the arms
overhead, a crouch, a jump and a landing, a fast twist and a stop held still for the last
second (loose parts keep moving after it). ``walk``: two strides.

Every piece's file vertex numbers are contiguous, in the order listed by :data:`PIECES`.
"""

from __future__ import annotations

import math

import numpy as np

from warpskin.rig import Clip, Rig, RigError, Skeleton, Track
from warpskin.transforms import quat_axis_angle, quat_multiply

__all__ = ["make_dancer", "DANCER_DEFAULTS", "JOINTS", "PIECES"]

DANCER_DEFAULTS: dict = {
    "cell": 0.02,  # [m] marching-cubes grid spacing of the smooth pieces
    "shell": 10,  # grid cells along a cube face of the shells (eyes, buns, shoes, hair)
    "arm_angle": 45.0,  # [degrees] the arms' rest pose below the horizontal
    "key_rate": 30.0,  # keys per second
    "clothes": True,  # trousers and shirt
    "skirt": False,  # with clothes: a flared skirt to above the knees in the trousers' place
    "hair": True,  # buns, hair cap and fringe
}

#: The pieces in file order (each one or two connected components: ``_l``/``_r`` pairs).
PIECES = ("body", "head", "eye_l", "eye_r", "bun_l", "bun_r", "hair", "fringe", "hand_l", "hand_r", "shoe_l",
          "shoe_r", "trousers", "shirt")

#: (name, parent) of every joint, parents first.
JOINTS = [
    ("hips", None), ("spine", "hips"), ("chest", "spine"), ("neck", "chest"), ("head", "neck"),
    *[(f"{j}_{s}", p if p in ("chest", "hips") else f"{p}_{s}") for s in ("l", "r") for j, p in (
        ("upperarm", "chest"), ("forearm", "upperarm"), ("hand", "forearm"), ("fingers", "hand"),
        ("thigh", "hips"), ("shin", "thigh"), ("foot", "shin"), ("toe", "foot"))],
]

UPPER, FORE = 0.28, 0.25  # [m] arm bone lengths
STANCE = 0.10  # [m] half the distance between the hip joints


def _smoothstep(x, a: float, b: float):
    u = np.clip((np.asarray(x, dtype=np.float64) - a) / (b - a), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def arm_direction(sign: float, arm_angle: float) -> np.ndarray:
    a = math.radians(arm_angle)
    return np.array([sign * math.cos(a), -math.sin(a), 0.0])


def joint_positions(arm_angle: float) -> dict[str, np.ndarray]:
    """Rest positions of every joint in the world [m]."""
    out = {"hips": (0.0, 0.95, 0.0), "spine": (0.0, 1.06, 0.0), "chest": (0.0, 1.22, 0.0), "neck": (0.0, 1.45, 0.0),
           "head": (0.0, 1.58, 0.0)}
    for side, sign in (("l", 1.0), ("r", -1.0)):
        d = arm_direction(sign, arm_angle)
        s = np.array([sign * 0.17, 1.40, 0.0])
        out[f"upperarm_{side}"] = s
        out[f"forearm_{side}"] = s + UPPER * d
        out[f"hand_{side}"] = s + (UPPER + FORE) * d
        out[f"fingers_{side}"] = s + (UPPER + FORE + 0.09) * d
        x = sign * STANCE
        out[f"thigh_{side}"] = (x, 0.92, 0.0)
        out[f"shin_{side}"] = (x, 0.50, 0.0)
        out[f"foot_{side}"] = (x, 0.08, 0.0)
        out[f"toe_{side}"] = (x, 0.025, 0.11)
    return {k: np.asarray(v, dtype=np.float64) for k, v in out.items()}


# --------------------------------------------------------------------------------------------
# signed distances
# --------------------------------------------------------------------------------------------
class _Cone:
    """A round cone from ``a`` (radius ``r1``) to ``b`` (radius ``r2``) tagged with its joint,
    squashed across its axis by ``flat`` along ``across`` (an elliptic section)."""

    def __init__(self, joint: str, a, b, r1: float, r2: float, flat: float = 1.0, across=(0.0, 0.0, 1.0)) -> None:
        self.joint, self.a, self.b = joint, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        self.r1, self.r2, self.flat = float(r1), float(r2), float(flat)
        self.across = np.asarray(across, dtype=np.float64) / np.linalg.norm(across)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        q = p - self.a
        if self.flat != 1.0:  # stretch the squashed direction: its section becomes an ellipse
            q = q + (1.0 / self.flat - 1.0) * np.outer(q @ self.across, self.across)
        ba = self.b - self.a
        l2 = float(ba @ ba)
        rr = self.r1 - self.r2
        a2 = l2 - rr * rr
        il2 = 1.0 / l2
        y = q @ ba
        z = y - l2
        x = q * l2 - np.outer(y, ba)
        x2 = np.einsum("ij,ij->i", x, x)
        y2 = y * y * l2
        z2 = z * z * l2
        k = math.copysign(1.0, rr) * rr * rr * x2
        d_mid = (np.sqrt(np.maximum(x2 * a2 * il2, 0.0)) + y * rr) * il2 - self.r1
        d_top = np.sqrt(x2 + z2) * il2 - self.r2
        d_bot = np.sqrt(x2 + y2) * il2 - self.r1
        d = np.where(np.sign(y) * a2 * y2 < k, d_bot, d_mid)
        return np.where(np.sign(z) * a2 * z2 > k, d_top, d) * (self.flat if self.flat < 1.0 else 1.0)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


class _Shape:
    """Round cones joined by a smooth union of blend radius ``blend``, cut by planes ``(point,
    normal, radius)`` (the side the normal points to is kept; the cut acts within ``radius`` of
    the line through the point along the normal, ``None``: everywhere); ``over``: ``(shape,
    gap)`` pairs, shapes it is worn over by at least ``gap``."""

    def __init__(self, cones: list[_Cone], blend: float, cuts: list[tuple] = (), over: list[tuple] = ()) -> None:
        self.cones, self.blend, self.cuts = cones, float(blend), list(cuts)
        self.over = list(over)

    def sdf(self, p: np.ndarray, cut: bool = True) -> np.ndarray:
        """The signed distance (approximately: the squashed cones' is scaled), cut by the
        planes; a shape worn ``over`` another encloses it by ``gap`` at least."""
        d = self.cones[0](p)
        for c in self.cones[1:]:
            d = _smin(d, c(p), self.blend)
        for shape, gap in self.over:
            d = np.minimum(d, shape.sdf(p, cut=False) - gap)
        if cut:
            for point, normal, radius in self.cuts:
                n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
                q = p - np.asarray(point)
                h = q @ n
                within = True if radius is None else np.linalg.norm(q - np.outer(h, n), axis=1) < radius
                d = np.where(within, np.maximum(d, -h), d)
        return d

    def weights(self, p: np.ndarray, names: list[str], softness: float) -> tuple[np.ndarray, np.ndarray]:
        """Skin weights: a soft minimum over the cones' distances (``exp(-(d - d_min) / s)``),
        summed per joint, the four largest kept."""
        cones = self.cones + [c for shape, _ in self.over for c in shape.cones]
        d = np.stack([c(p) for c in cones], axis=1)
        w = np.exp(-(d - d.min(axis=1, keepdims=True)) / softness)
        dense = np.zeros((len(p), len(names)))
        for k, c in enumerate(cones):
            dense[:, names.index(c.joint)] += w[:, k]
        idx = np.argsort(-dense, axis=1)[:, :4]
        jw = np.take_along_axis(dense, idx, axis=1)
        jw[jw < 1e-3 * jw[:, :1]] = 0.0
        return idx, jw / jw.sum(axis=1, keepdims=True)


def _taubin(v: np.ndarray, f: np.ndarray, fixed: np.ndarray, iterations: int, lam=0.5, mu=-0.53) -> np.ndarray:
    import scipy.sparse as sp

    n = len(v)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    a = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    a.data[:] = 1.0
    avg = sp.diags(1.0 / np.maximum(np.asarray(a.sum(axis=1)).ravel(), 1.0)) @ a
    move = (~fixed)[:, None].astype(np.float64)
    x = v.copy()
    for _ in range(iterations):
        x = x + lam * move * (avg @ x - x)
        x = x + mu * move * (avg @ x - x)
    return x


def _boundary_vertices(f: np.ndarray, n: int) -> np.ndarray:
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    out = np.zeros(n, dtype=bool)
    out[u[c == 1].ravel()] = True
    return out


def _surface(shape: _Shape, cell: float, drop=None) -> tuple[np.ndarray, np.ndarray]:
    """The open surface of ``shape``: marching cubes of its cut distance, the faces on the cut
    planes (and those ``drop(centroids)`` selects) removed, smoothed with its boundary held,
    flipped towards Delaunay. Triangles counter-clockwise from outside."""
    import warp as wp
    from warp.geometry import IsoSurfaceMarchingCubes

    from warpskin.preprocess.cage import _weld
    from warpskin.preprocess.refine import flip_flat_edges

    cones = shape.cones + [c for s, _ in shape.over for c in s.cones]
    pts = np.concatenate([np.concatenate([c.a, c.b])[None].reshape(2, 3) for c in cones])
    pad = max(max(c.r1, c.r2) for c in cones) + max([g for _, g in shape.over] or [0.0]) + 3 * cell
    lo, hi = pts.min(axis=0) - pad, pts.max(axis=0) + pad
    counts = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[k] + cell * np.arange(counts[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    field = shape.sdf(grid).reshape(*counts).astype(np.float32)
    upper = lo + (counts - 1) * cell
    with wp.ScopedDevice("cpu"):
        verts, idx = IsoSurfaceMarchingCubes.extract(wp.array(field, dtype=wp.float32), 0.0, lower=tuple(map(float, lo)),
                                                     upper=tuple(map(float, upper)))
        v = verts.numpy().astype(np.float64)
        f = idx.numpy().astype(np.int64).reshape(-1, 3)
    v, f = _weld(v, f, 1e-6 * cell)
    p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    if np.einsum("ij,ij->i", p0, np.cross(p1, p2)).sum() < 0:
        f = f[:, ::-1]
    centre = v[f].mean(axis=1)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    keep = np.ones(len(f), dtype=bool)
    for point, normal, radius in shape.cuts:  # the cut faces and the chamfer marching cubes leaves at their rim
        nn = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
        q = centre - np.asarray(point)
        near = np.ones(len(f), dtype=bool) if radius is None else \
            np.linalg.norm(q - np.outer(q @ nn, nn), axis=1) < radius + cell
        keep &= ~(near & (((v[f] - np.asarray(point)) @ nn).min(axis=1) < 0.5 * cell))
    if drop is not None:
        keep &= ~drop(centre)
    f = f[keep]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(used.size)
    v, f = v[used], remap[f]
    # drop crumbs the cuts left (components of a few faces)
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    m = len(v)
    _, lab = connected_components(sp.csr_matrix((np.ones(2 * len(f)), (np.r_[f[:, 0], f[:, 1]], np.r_[f[:, 1], f[:, 2]])),
                                                shape=(m, m)), directed=False)
    size = np.bincount(lab[f[:, 0]], minlength=lab.max() + 1)
    f = f[size[lab[f[:, 0]]] >= 50]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(used.size)
    v, f = v[used], remap[f]
    v = _taubin(v, f, _boundary_vertices(f, len(v)), 10)
    f = flip_flat_edges(v, f)
    return v, f


def _shell(center, radii, power: float, res: int) -> tuple[np.ndarray, np.ndarray]:
    from warpskin.scenes.mannequin import _shell as shell

    return shell(center, radii, power, res)


def _kept(v: np.ndarray, f: np.ndarray, keep_face: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    f = f[keep_face]
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(used.size)
    return v[used], remap[f]


# --------------------------------------------------------------------------------------------
# the animation
# --------------------------------------------------------------------------------------------
#: The dance's key poses: (time [s], {joint or "hips_t": values}). A joint's values are degrees
#: about (x, y, z) at rest, applied x first; an arm's ``y`` is its elbow's flexion about its own
#: axis (see :func:`_pose_quaternions`); ``_s`` joints are both sides, their z and y mirrored.
_NEUTRAL = {"upperarm_s": (0.0, 0.0, -25.0), "forearm_s": (0.0, 20.0, 0.0)}
_DANCE = [
    (0.00, {}),
    (0.25, {"hips_t": (0.0, -0.07, 0.0), "thigh_s": (-32.0, 0, 0), "shin_s": (64.0, 0, 0), "foot_s": (-32.0, 0, 0),
            "spine": (10.0, 0, 0), "upperarm_s": (-20.0, 0, 15.0), "forearm_s": (0, 95.0, 0)}),
    (0.50, {"upperarm_s": (0.0, 0.0, -30.0), "forearm_s": (0, 30.0, 0)}),
    (0.75, {"hips_t": (0.0, -0.07, 0.0), "thigh_s": (-32.0, 0, 0), "shin_s": (64.0, 0, 0), "foot_s": (-32.0, 0, 0),
            "spine": (10.0, 0, 0), "upperarm_s": (-30.0, 0, 35.0), "forearm_s": (0, 100.0, 0), "head": (12, 0, 0)}),
    (1.00, {"upperarm_s": (0.0, 0.0, -30.0), "forearm_s": (0, 30.0, 0)}),
    (1.35, {"hips_t": (0.07, -0.02, 0.0), "hips": (0, 0, 10.0), "spine": (0, 0, -14.0), "chest": (0, 0, -6.0),
            "head": (0, 0, 10.0), "upperarm_l": (0, 0, 95.0), "forearm_l": (0, 25.0, 0), "upperarm_r": (0, 0, -30.0),
            "thigh_r": (0, 0, -8.0), "thigh_l": (0, 0, 4.0)}),
    (1.75, {"hips_t": (-0.07, -0.02, 0.0), "hips": (0, 0, -10.0), "spine": (0, 0, 14.0), "chest": (0, 0, 6.0),
            "head": (0, 0, -10.0), "upperarm_r": (0, 0, 95.0), "forearm_r": (0, 25.0, 0), "upperarm_l": (0, 0, -30.0),
            "thigh_l": (0, 0, 8.0), "thigh_r": (0, 0, -4.0)}),
    (2.15, {"hips_t": (0.07, -0.02, 0.0), "hips": (0, 0, 10.0), "spine": (0, 0, -14.0), "chest": (0, 0, -6.0),
            "head": (0, 0, 10.0), "upperarm_l": (0, 0, 95.0), "forearm_l": (0, 25.0, 0), "upperarm_r": (0, 0, -30.0)}),
    (2.45, {}),
    (2.65, {"hips_t": (0.0, -0.16, 0.02), "thigh_s": (-70.0, 0, 0), "shin_s": (120.0, 0, 0), "foot_s": (-50.0, 0, 0),
            "spine": (28.0, 0, 0), "upperarm_s": (45.0, 0, -25.0), "forearm_s": (0, 30.0, 0)}),
    (2.90, {"hips_t": (0.0, 0.16, 0.0), "thigh_s": (-50.0, 0, 0), "shin_s": (90.0, 0, 0), "foot_s": (35.0, 0, 0),
            "spine": (-5.0, 0, 0), "upperarm_s": (0, 0, 120.0), "forearm_s": (0, 10.0, 0), "head": (-15, 0, 0)}),
    (3.10, {"hips_t": (0.0, -0.14, 0.02), "thigh_s": (-65.0, 0, 0), "shin_s": (110.0, 0, 0), "foot_s": (-45.0, 0, 0),
            "spine": (25.0, 0, 0), "upperarm_s": (-60.0, 0, -10.0), "forearm_s": (0, 40.0, 0)}),
    (3.35, {}),
    (3.55, {"spine": (0, 45.0, 0), "chest": (0, 35.0, 0), "head": (0, -30.0, 0), "upperarm_s": (0, 0, 45.0),
            "forearm_s": (0, 5.0, 0), "hips": (0, 10.0, 0)}),
    (3.72, {"spine": (0, -25.0, 0), "chest": (0, -20.0, 0), "head": (0, 15.0, 0), "upperarm_s": (0, 0, 10.0),
            "hips": (0, -6.0, 0)}),
    (3.90, {}),
    (4.90, {}),
]


def _catmull_rom(times: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Centripetal-free (uniform) Catmull-Rom through ``values [K, D]`` at ``times [K]``,
    sampled at ``t``; flat tangents at both ends."""
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[k], times[k + 1]
    u = ((t - t0) / (t1 - t0))[:, None]
    p0, p1, p2, p3 = values[np.maximum(k - 1, 0)], values[k], values[k + 1], values[np.minimum(k + 2, len(times) - 1)]
    m1 = np.where((k > 0)[:, None], (p2 - p0) * 0.5, 0.0)
    m2 = np.where((k + 2 < len(times))[:, None], (p3 - p1) * 0.5, 0.0)
    u2, u3 = u * u, u * u * u
    return (2 * u3 - 3 * u2 + 1) * p1 + (u3 - 2 * u2 + u) * m1 + (-2 * u3 + 3 * u2) * p2 + (u3 - u2) * m2


def _pose_values(pose: dict, joint: str, side: str | None) -> np.ndarray:
    """The (x, y, z) degrees of ``joint`` (its side's) in a key pose, over the neutral pose."""
    base = joint if side is None else joint[:-2] + "_s"
    sgn = 1.0 if side in (None, "l") else -1.0
    v = np.zeros(3)
    for src in (_NEUTRAL, pose):
        if base in src:
            x, y, z = src[base]
            v = np.array([x, sgn * y if base.startswith(("upperarm", "forearm")) else y, sgn * z], dtype=np.float64)
        if joint in src and side is not None:
            x, y, z = src[joint]
            v = np.array([x, sgn * y if joint.startswith(("upperarm", "forearm")) else y, sgn * z], dtype=np.float64)
    return v


def _clip(name: str, keys: list, rate: float, world: dict, arm_angle: float) -> Clip:
    names = [j[0] for j in JOINTS]
    index = {n: i for i, n in enumerate(names)}
    times = np.array([k[0] for k in keys])
    n = int(round(times[-1] * rate)) + 1
    t = np.arange(n) / rate
    tracks = {}
    for joint in names:
        side = joint[-1] if joint[-2:] in ("_l", "_r") else None
        vals = np.array([_pose_values(pose, joint, side) for _, pose in keys])
        if not np.any(vals) and joint not in ("hips",):
            continue
        ang = _catmull_rom(times, vals, t)
        qs = []
        for x, y, z in ang:
            if joint.startswith("forearm"):  # the elbow bends forward about the arm's own axis
                sgn = 1.0 if side == "l" else -1.0
                d = arm_direction(sgn, arm_angle)
                q = quat_axis_angle(np.cross([0.0, 0.0, 1.0], d), -sgn * y)
            else:
                q = quat_multiply(quat_axis_angle((0, 0, 1), z), quat_multiply(quat_axis_angle((0, 1, 0), y), quat_axis_angle((1, 0, 0), x)))
            qs.append(q)
        tracks[(index[joint], "rotation")] = Track("rotation", t, np.array(qs))
    trans = np.array([np.asarray(pose.get("hips_t", (0.0, 0.0, 0.0)), dtype=np.float64) for _, pose in keys])
    tracks[(index["hips"], "translation")] = Track("translation", t, world["hips"] + _catmull_rom(times, trans, t))
    return Clip(name, tracks, rate=rate)


def _walk_keys() -> list:
    keys = []
    for k in range(9):
        s = math.sin(math.pi * k / 2.0)
        c = math.cos(math.pi * k / 2.0)
        keys.append((k * 0.25, {"thigh_l": (-26.0 * s, 0, 0), "thigh_r": (26.0 * s, 0, 0),
                                "shin_l": (45.0 * max(0.0, c) + 5.0, 0, 0), "shin_r": (45.0 * max(0.0, -c) + 5.0, 0, 0),
                                "upperarm_l": (22.0 * s, 0, -25.0), "upperarm_r": (-22.0 * s, 0, -25.0),
                                "hips_t": (0.0, 0.02 * abs(c) - 0.02, 0.0), "spine": (0, 6.0 * s, 0)}))
    return keys


# --------------------------------------------------------------------------------------------
# the character
# --------------------------------------------------------------------------------------------
def make_dancer(**overrides) -> Rig:
    """The dancer rig: one skinned mesh ``dancer`` of the pieces in :data:`PIECES`, clips
    ``dance`` (4.9 s) and ``walk`` (2 s).

    Keyword arguments override :data:`DANCER_DEFAULTS`.

    Raises:
        RigError: an unknown parameter or a value out of range.
    """
    p = dict(DANCER_DEFAULTS)
    unknown = sorted(set(overrides) - set(p))
    if unknown:
        raise RigError(f"dancer: unknown parameter(s) {unknown}; known: {sorted(p)}")
    p.update(overrides)
    cell, res, rate = float(p["cell"]), int(p["shell"]), float(p["key_rate"])
    if not (0.004 <= cell <= 0.05) or res < 3 or not rate > 0 or not 0.0 <= float(p["arm_angle"]) <= 80.0:
        raise RigError(f"dancer: need cell in [0.004, 0.05] m, shell >= 3, key_rate > 0 and arm_angle in [0, 80], got {p}")
    arm_angle = float(p["arm_angle"])
    names = [j[0] for j in JOINTS]
    pos = joint_positions(arm_angle)
    soft = 0.35 * 0.04  # [m] softness of the weights' soft minimum

    pieces: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def add(name, v, f, ji, jw):
        pieces.append((name, v, f, np.asarray(ji), np.asarray(jw)))

    def rigid(n, joint):
        ji = np.zeros((n, 4), dtype=np.int64)
        jw = np.zeros((n, 4))
        ji[:, 0] = names.index(joint)
        jw[:, 0] = 1.0
        return ji, jw

    arms = {}
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        d = arm_direction(sgn, arm_angle)
        arms[side] = (d, np.cross([0.0, 0.0, 1.0], d) * sgn)  # the arm's direction and its "up" in the frontal plane

    # ---- body: open at the neck, the wrists and the ankles
    cones = [_Cone("hips", (0, 0.90, 0), (0, 1.02, 0), 0.150, 0.136, 0.72),
             _Cone("spine", (0, 1.02, 0), (0, 1.20, 0), 0.132, 0.142, 0.70),
             _Cone("chest", (0, 1.20, 0), (0, 1.37, 0), 0.150, 0.140, 0.68),
             _Cone("neck", (0, 1.37, 0), (0, 1.57, 0), 0.058, 0.050)]
    cuts = [((0, 1.52, 0), (0, -1, 0), 0.12)]
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        d, _ = arms[side]
        s, e, w = pos[f"upperarm_{side}"], pos[f"forearm_{side}"], pos[f"hand_{side}"]
        cones += [_Cone(f"upperarm_{side}", s - 0.02 * d, e, 0.054, 0.040),
                  _Cone(f"forearm_{side}", e, w, 0.040, 0.031, 0.8, arms[side][1]),
                  _Cone(f"thigh_{side}", pos[f"thigh_{side}"], pos[f"shin_{side}"], 0.080, 0.052),
                  _Cone(f"shin_{side}", pos[f"shin_{side}"], pos[f"foot_{side}"], 0.050, 0.032)]
        cuts += [(w - 0.012 * d, -d, 0.08), ((sgn * STANCE, 0.13, 0), (0, 1, 0), 0.12)]
    body = _Shape(cones, 0.045, cuts)
    legs = _Shape([c for c in cones if c.joint[:-2] not in ("upperarm", "forearm")], 0.045)
    top = _Shape([c for c in cones if c.joint[:-2] != "forearm"], 0.045)
    v, f = _surface(body, cell)
    add("body", v, f, *body.weights(v, names, soft))

    # ---- head: open at the neck and at two eye sockets
    eye_r = 0.0135
    head = _Shape([_Cone("neck", (0, 1.47, 0), (0, 1.62, 0), 0.046, 0.044),
                   _Cone("head", (0, 1.64, 0.005), (0, 1.73, 0.005), 0.092, 0.088, 0.95, (1, 0, 0)),
                   _Cone("head", (0, 1.63, 0.04), (0, 1.595, 0.065), 0.050, 0.030)], 0.035, [((0, 1.475, 0), (0, 1, 0), 0.12)])
    eyes = []
    for sgn in (1.0, -1.0):  # the front of the head along +z at the eye's height, then a little inside
        probe = np.array([[sgn * 0.032, 1.69, z] for z in np.linspace(0.0, 0.2, 2001)])
        front = probe[np.argmax(head.sdf(probe, cut=False) > 0.0)]
        eyes.append(front - np.array([0.0, 0.0, 0.004]))
    socket = 0.0115

    def sockets(c):
        return np.min([np.linalg.norm(c - (e + [0, 0, 0.004]), axis=1) for e in eyes], axis=0) < socket

    v, f = _surface(head, cell * 0.8, drop=sockets)
    add("head", v, f, *head.weights(v, names, soft))
    for side, e in zip(("l", "r"), eyes):
        v, f = _shell(e, (eye_r,) * 3, 2.0, max(3, res // 2))
        add(f"eye_{side}", v, f, *rigid(len(v), "head"))

    # ---- hair: two buns sunk into the skull, a cap over the scalp (open), a fringe strip (open)
    if p["hair"]:
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            v, f = _shell((sgn * 0.060, 1.775, -0.050), (0.042, 0.042, 0.042), 2.0, res)
            add(f"bun_{side}", v, f, *rigid(len(v), "head"))
        hair = _Shape([_Cone("head", (0, 1.62, 0), (0, 1.63, 0), 0.01, 0.01)], 0.01, over=[(head, 0.006)])
        v, f = _surface(hair, cell * 0.8, drop=lambda c: c[:, 1] < 1.745 - 0.10 * _smoothstep(-c[:, 2], -0.02, 0.08))
        add("hair", v, f, *rigid(len(v), "head"))
        u, w = np.meshgrid(np.linspace(-0.055, 0.055, 13), np.linspace(0.0, 0.045, 6), indexing="ij")
        probe_z = np.array([head.sdf(np.array([[x, 1.745, z] for z in np.linspace(0.0, 0.2, 801)]), cut=False)
                            for x in u[:, 0]])
        zf = np.linspace(0.0, 0.2, 801)[np.argmax(probe_z > 0.0, axis=1)]
        v = np.stack([u, 1.765 - w, np.repeat(zf[:, None], w.shape[1], 1) + 0.009 + 0.2 * w * w], axis=-1).reshape(-1, 3)
        nu, nw = u.shape
        idx = np.arange(nu * nw).reshape(nu, nw)
        a, b, c2, d2 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        f = np.concatenate([np.stack([a, c2, b], 1), np.stack([a, d2, c2], 1)])
        add("fringe", v, f, *rigid(len(v), "head"))

    # ---- hands: mittens with a thumb, open at the wrist, tucked into the forearms
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        d, up = arms[side]
        h = pos[f"hand_{side}"]
        fwd = np.array([0.0, 0.0, 1.0])
        hand = _Shape([_Cone(f"hand_{side}", h - 0.03 * d, h + 0.085 * d, 0.022, 0.030, 0.55, up),
                       _Cone(f"fingers_{side}", h + 0.085 * d, h + 0.17 * d, 0.028, 0.018, 0.5, up),
                       _Cone(f"hand_{side}", h + 0.02 * d + 0.015 * fwd, h + 0.07 * d + 0.05 * fwd, 0.014, 0.011)],
                      0.02, [(h - 0.026 * d, d, 0.08)])
        v, f = _surface(hand, cell * 0.6)
        add(f"hand_{side}", v, f, *hand.weights(v, names, soft * 0.6))

    # ---- shoes: rounded boxes open at the top, the ankles inside
    for side, sgn in (("l", 1.0), ("r", -1.0)):
        x = sgn * STANCE
        v, f = _shell((x, 0.07, 0.04), (0.055, 0.07, 0.135), 4.0, res + 2)
        c = v[f].mean(axis=1)
        opening = (c[:, 1] > 0.10) & (((c[:, 0] - x) / 0.047) ** 2 + ((c[:, 2] + 0.005) / 0.05) ** 2 < 1.0)
        v, f = _kept(v, f, ~opening)
        zt = pos[f"toe_{side}"][2]
        w_toe = _smoothstep(v[:, 2], zt - 0.03, zt + 0.03)
        ji = np.zeros((len(v), 4), dtype=np.int64)
        jw = np.zeros((len(v), 4))
        ji[:, 0], ji[:, 1] = names.index(f"foot_{side}"), names.index(f"toe_{side}")
        jw[:, 0], jw[:, 1] = 1.0 - w_toe, w_toe
        add(f"shoe_{side}", v, f, ji, jw)

    # ---- clothes: baggy trousers (open at the waist and the cuffs), a short-sleeved shirt
    if p["clothes"]:
        cones = [_Cone("hips", (0, 0.92, 0), (0, 1.04, 0), 0.160, 0.146, 0.74)]
        cuts = [((0, 1.035, 0), (0, -1, 0), 0.3)]
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            cones += [_Cone(f"thigh_{side}", pos[f"thigh_{side}"], pos[f"shin_{side}"], 0.098, 0.082),
                      _Cone(f"shin_{side}", pos[f"shin_{side}"], pos[f"foot_{side}"] + [0, 0.05, 0], 0.082, 0.075)]
        cuts += [((sgn * STANCE, 0.17, 0), (0, 1, 0), 0.15) for sgn in (1.0, -1.0)]
        trousers = _Shape(cones, 0.05, cuts, over=[(legs, 0.007)])
        if p["skirt"]:  # one tube over both thighs, flaring to its hem, skinned to the hips and thighs
            cones = [_Cone("hips", (0, 0.92, 0), (0, 1.04, 0), 0.165, 0.150, 0.74)]
            for side, sgn in (("l", 1.0), ("r", -1.0)):
                hip, knee = pos[f"thigh_{side}"], pos[f"shin_{side}"]
                cones.append(_Cone(f"thigh_{side}", hip, hip + 0.75 * (knee - hip) + [sgn * 0.04, 0, 0], 0.125, 0.165))
            cuts = [((0, 1.035, 0), (0, -1, 0), 0.3), ((0, 0.60, 0), (0, 1, 0), None)]
            trousers = _Shape(cones, 0.12, cuts, over=[(legs, 0.007)])
        v, f = _surface(trousers, cell)
        add("trousers", v, f, *trousers.weights(v, names, soft))
        cones = [_Cone("spine", (0, 0.97, 0), (0, 1.20, 0), 0.168, 0.158, 0.72),
                 _Cone("chest", (0, 1.20, 0), (0, 1.37, 0), 0.166, 0.154, 0.70),
                 _Cone("neck", (0, 1.36, 0), (0, 1.48, 0), 0.078, 0.068)]
        cuts = [((0, 1.465, 0), (0, -1, 0), 0.15), ((0, 0.985, 0), (0, 1, 0), None)]
        for side, sgn in (("l", 1.0), ("r", -1.0)):
            d, _ = arms[side]
            s = pos[f"upperarm_{side}"]
            cones.append(_Cone(f"upperarm_{side}", s - 0.03 * d, s + 0.16 * d, 0.068, 0.058))
            cuts.append((s + 0.13 * d, -d, 0.074))
        shirt = _Shape(cones, 0.05, cuts, over=[(top, 0.008), (trousers, 0.006)])
        v, f = _surface(shirt, cell)
        add("shirt", v, f, *shirt.weights(v, names, soft))

    order = {name: k for k, name in enumerate(PIECES)}
    pieces.sort(key=lambda x: order[x[0]])
    pts, tris, ji, jw = [], [], [], []
    base = 0
    for _, v, f, i, w in pieces:
        pts.append(v)
        tris.append(f + base)
        ji.append(i)
        jw.append(w)
        base += len(v)

    world = np.array([pos[n] for n in names])
    parents = np.array([names.index(j[1]) if j[1] else -1 for j in JOINTS])
    skel = Skeleton(names, parents, np.array([world[i] - (world[parents[i]] if parents[i] >= 0 else 0.0)
                                              for i in range(len(names))]),
                    np.tile([0.0, 0.0, 0.0, 1.0], (len(names), 1)), np.ones((len(names), 3)))
    inverse_bind = np.linalg.inv(skel.world_from_local(skel.rest_local_matrices()))
    clips = {"dance": _clip("dance", _DANCE, rate, pos, arm_angle), "walk": _clip("walk", _walk_keys(), rate, pos, arm_angle)}
    return Rig.from_file_arrays(name="dancer", points=np.concatenate(pts), triangles=np.concatenate(tris), skeleton=skel,
                                joint_indices=np.concatenate(ji), joint_weights=np.concatenate(jw),
                                inverse_bind=inverse_bind, clips=clips, source="generator:dancer", mesh_name="dancer",
                                weld=False)

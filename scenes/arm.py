"""Procedural arm rig: a closed, manifold tube with an upper arm, an elbow, a forearm and a
wrist, three joints (shoulder, elbow, wrist), smooth weights around the elbow and a clip that
flexes the elbow from 0 to 150 degrees and back, so that the forearm presses into the upper arm.

The default resolution (81 rings of 36 vertices plus two poles, 2918 vertices) matches the
2916-vertex arm of Deul & Bender 2013, Table 1. The triangles are close to isotropic (about 9 mm
along the arm, 7 mm around the elbow): with long thin triangles the elbow crease folds within
one triangle's width, and triangles one edge apart cross each other before any contact can
separate them.

Coordinates: the arm lies along +x (shoulder at the origin), the elbow flexes about +z so the
forearm folds toward +y (the biceps side). Y is up in the exported stage; the arm is horizontal.
"""

from __future__ import annotations

import math

import numpy as np

from warpskin.rig import Clip, Rig, RigError, Skeleton, Track

__all__ = ["make_arm", "ARM_DEFAULTS", "flex_angle"]

ARM_DEFAULTS: dict = {
    "upper_length": 0.30,  # shoulder -> elbow [m]
    "forearm_length": 0.26,  # elbow -> wrist [m]
    "shoulder_radius": 0.055,  # [m]
    "biceps_radius": 0.05,  # bulge of the upper arm [m]
    "elbow_radius": 0.041,  # [m]
    "forearm_radius": 0.044,  # bulge of the forearm [m]
    "wrist_radius": 0.027,  # [m]
    "flatten": 0.88,  # cross-section: z half-axis / y half-axis
    "rings": 81,  # rings along the arm (plus two poles)
    "segments": 36,  # vertices around each ring
    "elbow_blend": 0.045,  # half-width of the shoulder/elbow weight blend [m]
    "flex_degrees": 150.0,  # peak elbow flexion
    "flex_time": 1.5,  # seconds to flex, and to extend again
    "hold_time": 1.0,  # seconds held at the peak
    "rest_time": 1.0,  # seconds held straight at the end (the skin settles)
    "key_rate": 30.0,  # keys per second of the elbow track
}


def _smoothstep(x: np.ndarray, a: float, b: float) -> np.ndarray:
    u = np.clip((x - a) / (b - a), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _profile(x: np.ndarray, p: dict) -> np.ndarray:
    """Radius [m] of the arm along its axis: piecewise smooth through the named radii."""
    l1, l2 = p["upper_length"], p["forearm_length"]
    xs = np.array([0.0, 0.45 * l1, l1, l1 + 0.3 * l2, l1 + l2])
    rs = np.array(
        [p["shoulder_radius"], p["biceps_radius"], p["elbow_radius"], p["forearm_radius"], p["wrist_radius"]]
    )
    # monotone cubic (smoothstep) blend between consecutive control radii
    x = np.clip(np.asarray(x, dtype=np.float64), xs[0], xs[-1])
    k = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, xs.size - 2)
    return rs[k] + (rs[k + 1] - rs[k]) * _smoothstep(x, xs[k], xs[k + 1])


def flex_angle(t: np.ndarray | float, p: dict | None = None) -> np.ndarray:
    """Elbow flexion [rad] of the default clip at times ``t`` [s]: ease in to the peak, hold,
    ease out, hold straight."""
    p = {**ARM_DEFAULTS, **(p or {})}
    t = np.asarray(t, dtype=np.float64)
    peak = math.radians(p["flex_degrees"])
    ft, ht = p["flex_time"], p["hold_time"]
    up = _smoothstep(t, 0.0, ft)
    down = _smoothstep(t, ft + ht, 2 * ft + ht)
    return peak * (up - down)


def _check(p: dict) -> None:
    unknown = sorted(set(p) - set(ARM_DEFAULTS))
    if unknown:
        raise RigError(f"arm generator: unknown parameters {unknown}; known: {sorted(ARM_DEFAULTS)}")
    for key in ARM_DEFAULTS:
        v = p[key]
        if key in ("rings", "segments"):
            if int(v) != v or v < 3:
                raise RigError(f"arm generator: {key} must be an integer >= 3, got {v}")
        elif key == "flex_degrees":
            if not (0.0 <= v <= 175.0):
                raise RigError(f"arm generator: flex_degrees must be in [0, 175], got {v}")
        elif key in ("hold_time", "rest_time"):
            if not (v >= 0.0):
                raise RigError(f"arm generator: {key} must be >= 0, got {v}")
        elif not (v > 0.0 and math.isfinite(v)):
            raise RigError(f"arm generator: {key} must be a positive number, got {v}")
    if p["flatten"] > 1.5:
        raise RigError(f"arm generator: flatten must be in (0, 1.5], got {p['flatten']}")
    if p["elbow_blend"] >= min(p["upper_length"], p["forearm_length"]) / 2:
        raise RigError("arm generator: elbow_blend must be less than half of each bone length")


def make_arm(**params) -> Rig:
    """Build the procedural arm rig.

    Args:
        **params: Overrides of :data:`ARM_DEFAULTS` (lengths and radii in metres, times in
            seconds, angles in degrees).

    Returns:
        A closed, manifold, consistently wound :class:`~warpskin.rig.Rig` with joints
        ``shoulder``, ``elbow``, ``wrist`` and one clip, ``flex``.
    """
    p = {**ARM_DEFAULTS, **params}
    _check(p)
    rings, seg = int(p["rings"]), int(p["segments"])
    l1, l2 = p["upper_length"], p["forearm_length"]
    x_sh, x_wr = 0.0, l1 + l2

    # ring stations: rounded caps at both ends (quarter ellipses), uniform spacing between
    cap = max(2, rings // 9)
    body = rings - 2 * cap
    if body < 2:
        raise RigError("arm generator: rings too few for the caps; use rings >= 9")
    r_sh = _profile(np.array([x_sh]), p)[0]
    r_wr = _profile(np.array([x_wr]), p)[0]
    cap_len_sh, cap_len_wr = 0.6 * r_sh, 0.6 * r_wr
    phi = np.arange(1, cap + 1) / (cap + 1) * (0.5 * math.pi)  # from the pole toward the body
    xs_cap0 = x_sh - cap_len_sh * np.cos(phi)
    f_cap0 = np.sin(phi)
    xs_body = np.linspace(x_sh, x_wr, body)
    xs_cap1 = x_wr + cap_len_wr * np.cos(phi[::-1])
    f_cap1 = np.sin(phi[::-1])
    ring_x = np.concatenate([xs_cap0, xs_body, xs_cap1])
    ring_f = np.concatenate([f_cap0, np.ones(body), f_cap1])
    ring_r = _profile(np.clip(ring_x, x_sh, x_wr), p) * ring_f

    theta = np.arange(seg) / seg * 2.0 * math.pi
    # ring vertices: (x, r cos theta, flatten * r sin theta)
    rx = np.repeat(ring_x, seg)
    rr = np.repeat(ring_r, seg)
    th = np.tile(theta, rings)
    ring_pts = np.stack([rx, rr * np.cos(th), p["flatten"] * rr * np.sin(th)], axis=1)
    pole0 = np.array([[x_sh - cap_len_sh, 0.0, 0.0]])
    pole1 = np.array([[x_wr + cap_len_wr, 0.0, 0.0]])
    verts = np.concatenate([ring_pts, pole0, pole1])
    i_pole0, i_pole1 = rings * seg, rings * seg + 1

    # triangles, counter-clockwise seen from outside (normals point away from the x axis)
    k = np.arange(rings - 1)[:, None]
    a = np.arange(seg)[None, :]
    v00 = (k * seg + a).ravel()
    v01 = (k * seg + (a + 1) % seg).ravel()
    v10 = ((k + 1) * seg + a).ravel()
    v11 = ((k + 1) * seg + (a + 1) % seg).ravel()
    quads = np.concatenate([np.stack([v00, v01, v11], 1), np.stack([v00, v11, v10], 1)])
    a1 = np.arange(seg)
    fan0 = np.stack([np.full(seg, i_pole0), (a1 + 1) % seg, a1], 1)
    last = (rings - 1) * seg
    fan1 = np.stack([np.full(seg, i_pole1), last + a1, last + (a1 + 1) % seg], 1)
    tris = np.concatenate([fan0, quads, fan1])

    # weights: shoulder -> elbow blend around the elbow, elbow -> wrist blend at the wrist
    x = verts[:, 0]
    b = p["elbow_blend"]
    s1 = _smoothstep(x, l1 - b, l1 + b)
    s2 = _smoothstep(x, x_wr - 0.6 * b, x_wr + 0.2 * b)
    w = np.stack([1.0 - s1, s1 * (1.0 - s2), s1 * s2], axis=1)
    ji = np.tile(np.arange(3), (verts.shape[0], 1))

    names = ["shoulder", "elbow", "wrist"]
    parents = np.array([-1, 0, 1])
    rest_t = np.array([[0.0, 0.0, 0.0], [l1, 0.0, 0.0], [l2, 0.0, 0.0]])
    rest_r = np.tile([0.0, 0.0, 0.0, 1.0], (3, 1))
    skel = Skeleton(names, parents, rest_t, rest_r, np.ones((3, 3)))
    bind_world = skel.world_from_local(skel.rest_local_matrices())
    inverse_bind = np.linalg.inv(bind_world)

    total = 2 * p["flex_time"] + p["hold_time"] + p["rest_time"]
    key_count = max(2, int(round(total * p["key_rate"])) + 1)
    times = np.linspace(0.0, total, key_count)
    ang = flex_angle(times, p)
    quats = np.stack([np.zeros_like(ang), np.zeros_like(ang), np.sin(ang / 2), np.cos(ang / 2)], axis=1)
    clip = Clip("flex", {(1, "rotation"): Track("rotation", times, quats, "LINEAR")})

    return Rig.from_file_arrays(
        name="arm",
        points=verts,
        triangles=tris,
        skeleton=skel,
        joint_indices=ji,
        joint_weights=w,
        inverse_bind=inverse_bind,
        clips={"flex": clip},
        source="generator:arm",
        mesh_name="arm",
        weld=False,
    )

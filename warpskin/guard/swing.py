"""Loose pieces swing: :class:`PieceSwing`, the follow-through of a piece hung on the body whole.

A piece that LBS moves rigidly and that hangs off the piece it is attached to (a hair bun on
the skull, a ponytail or an earring on the head joint: :func:`loose_pieces` says which) is
written by one rigid motion, so it keeps its shape; left at that it moves exactly as what
carries it and stops in the same frame. A loose piece swings about where it is attached, as a
damped pendulum driven by the inertial force of its LBS's motion (on the host, per frame,
before the surface guard, which judges the result):

    theta'' + 2 zeta w theta' + w^2 theta = -(r x a) / (|r|^2 + g^2),      w = 2 pi f

* ``theta`` the swing, a rotation vector [rad] in the world frame, kept across the arm ``r``;
* ``r = c - q`` the arm from the pivot ``q`` to the piece's centroid ``c``: ``q`` is the point
  of the carrier's closed surface nearest ``c`` at rest, carried with the piece (the best rigid
  fit of its rest points onto its points this frame);
* ``g^2`` the mean squared distance of the piece's points from ``c`` (the moment of inertia
  about ``q`` is ``m (|r|^2 + g^2)`` for a body whose inertia is the same about every axis);
* ``a`` the acceleration of the centroid of its LBS (second differences over the last three
  frames, constant over a frame: the pendulum is integrated exactly over it,
  :func:`~warpskin.guard.sway.damped_step`).

The swing is limited smoothly (:func:`~warpskin.guard.sway.soft_limit`) to the least of
``angle`` and :attr:`PieceSwing.ROOM` x the room of the piece over its reach: the room is the distance this
frame from the piece to the nearest point of a piece it does not touch at rest, the reach the
distance of its farthest point from ``q``. What is written is ``o + R(phi k theta) (x - o)``
(``phi`` the piece's physics weight in [0, 1]): exactly rigid. It turns about ``o``, the centre
of the carrier's curvature beneath ``q`` (:func:`curvature_centre`: the sphere fitted to the
carrier's surface about ``q`` at rest, carried as ``q`` is), by the angle that moves ``c`` as far
as ``theta`` about ``q`` would, ``k = |c - q| / |c - o|`` at rest: a piece sunk into a round
carrier (a bun into the skull) slides over it and keeps its depth in it and in what lies
parallel to it (a hair cap), so its crossing with them moves with it instead of growing as it
tilts. Where the surface there is not round and convex, ``o = q`` and ``k = 1``.

Invariants: with no LBS acceleration (a pose held from the start) the points are written as
given; the first two frames, and any frame whose time does not advance, are written as given
and restart the pendulum. Limits: the pendulum has no gravity of its own (the rest pose is its
balance in any orientation) and does not collide: a swing that would cross another piece within
its limit is the surface guard's to take back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..transforms import rigid_fit
from .sway import LbsAcceleration, damped_step, soft_limit

__all__ = ["LoosePiece", "PieceSwing", "curvature_centre", "loose_pieces", "winding_numbers"]


@dataclass(frozen=True)
class LoosePiece:
    """A piece that swings (:func:`loose_pieces`).

    Attributes:
        piece: Its piece number.
        points: ``[K]`` its point indices (into the points :func:`loose_pieces` was given).
        visible: The rows of ``points`` outside its carrier at rest (a bun sunk into the skull:
            the part that shows), whose centroid the swing's arm reaches and whose LBS drives it.
        pivot: ``[3]`` where it is attached at rest [m]: the point of its carrier's closed
            surface nearest its centroid (the pendulum's pivot).
        centre: ``[3]`` what it turns about [m]: the centre of its carrier's curvature
            beneath ``pivot`` (:func:`curvature_centre`), or ``pivot`` (``None``: ``pivot``).
        carrier: The piece it hangs from (the largest closed piece it touches at rest).
        touching: The pieces it touches or crosses at rest (its carrier among them): they do
            not limit its swing.
    """

    piece: int
    points: np.ndarray
    visible: np.ndarray
    pivot: np.ndarray
    carrier: int
    touching: tuple[int, ...]
    centre: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.centre is None:
            object.__setattr__(self, "centre", np.asarray(self.pivot, dtype=np.float64))


def winding_numbers(query: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[Q]`` the winding number of the closed, outward-wound surface ``(vertices [V, 3],
    triangles [T, 3])`` about each row of ``query`` ``[Q, 3]``: the sum of the triangles' signed
    solid angles (Van Oosterom and Strackee 1983) over 4 pi; 1 inside, 0 outside, in between on
    an open surface. Exact in floating point away from the surface; O(Q T) memory per block of
    queries."""
    q = np.asarray(query, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles, dtype=np.int64)]
    out = np.zeros(len(q))
    for s in range(0, len(q), 64):
        a, b, c = (v[None, :, i, :] - q[s:s + 64, None, :] for i in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
        det = np.einsum("qti,qti->qt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("qti,qti->qt", a, b) * lc + np.einsum("qti,qti->qt", a, c) * lb
               + np.einsum("qti,qti->qt", b, c) * la)
        out[s:s + 64] = 2.0 * np.arctan2(det, den).sum(axis=1) / (4.0 * np.pi)
    return out


def _closest_on_triangles(p: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``[3]`` the point of the triangles ``(vertices, triangles)`` nearest ``p`` ``[3]`` (Warp's
    mesh query on the CPU, float32)."""
    from ..preprocess.cage import closest_faces

    v = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    reach = 2.0 * float(np.linalg.norm(np.ptp(np.vstack([v, np.reshape(p, (1, 3))]), axis=0))) + 1.0
    face, bary = closest_faces(np.reshape(p, (1, 3)), v, t, reach, device="cpu")
    return bary[0] @ v[t[face[0]]]


def curvature_centre(pivot: np.ndarray, outward: np.ndarray, vertices: np.ndarray, radius: float,
                     largest: float) -> np.ndarray | None:
    """``[3]`` the centre of the sphere fitted (algebraically, by least squares) to ``vertices``
    ``[V, 3]`` within ``radius`` [m] of ``pivot`` ``[3]``, a point of that surface whose outward
    direction is ``outward`` ``[3]``; ``None`` where the surface there is not a convex cap of a
    sphere of radius at most ``largest`` [m]: fewer than 10 vertices, the centre not behind the
    pivot, the pivot off the sphere or the vertices off it by more than a tenth of its radius
    (RMS), a saddle or a flat."""
    v = np.asarray(vertices, dtype=np.float64)
    p = np.asarray(pivot, dtype=np.float64)
    near = v[np.linalg.norm(v - p, axis=1) <= radius]
    if len(near) < 10:
        return None
    a = np.hstack([2.0 * (near - p), np.ones((len(near), 1))])  # about the pivot: well conditioned
    b = np.sum((near - p) ** 2, axis=1)
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    o = sol[:3]
    r2 = float(sol[3] + o @ o)
    if not np.isfinite(r2) or r2 <= 0.0:
        return None
    r = np.sqrt(r2)
    if r > largest or o @ np.asarray(outward, dtype=np.float64) >= 0.0:
        return None
    if abs(np.linalg.norm(o) - r) > 0.1 * r:
        return None
    if np.sqrt(np.mean((np.linalg.norm(near - p - o, axis=1) - r) ** 2)) > 0.1 * r:
        return None
    return p + o


def loose_pieces(points: np.ndarray, piece: np.ndarray, joint: np.ndarray, rigid: np.ndarray,
                 closed: dict[int, tuple[np.ndarray, np.ndarray]], touch: float) -> list[LoosePiece]:
    """The pieces that hang loose off what carries them, at rest.

    Args:
        points: ``[N, 3]`` every written point at rest [m].
        piece: ``[N]`` the piece of every point.
        joint: ``[N]`` the joint that moves each point most (its largest skin weight).
        rigid: ``[P]`` per piece, whether LBS moves it rigidly (one joint).
        closed: ``{piece: (vertices [V, 3], triangles [T, 3])}`` the pieces that are closed (their
            holes capped), outward wound: the carriers a piece can hang from.
        touch: Points of two pieces within this distance [m] touch.

    Returns:
        The loose pieces, each one that:

        * LBS moves rigidly on a joint ``j``, and touches at rest only points moved most by
          ``j`` (a bun on the skull; not a ball joint between two limbs);
        * hangs from the largest closed piece it touches (its carrier), at least twice its own
          size (bounding-box diagonals: a head on a neck is not loose);
        * shows at least 40 % of its points outside the carrier, and the centroid ``c`` of
          those lies outside it (an eye is inside its head) at a distance ``d`` from the
          carrier's nearest point ``q`` (the pivot) of at least a quarter of their radius of
          gyration (a sheet lying on the skull has no arm);
        * touches what it touches in one place: no point of contact farther than ``d`` above
          ``c`` along ``c - q`` nor farther from ``q`` than 1.5 x its largest distance from ``c`` (not glasses on
          the nose and the ears, not a ball between two tubes).
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    piece = np.asarray(piece, dtype=np.int64)
    joint = np.asarray(joint, dtype=np.int64)
    count = int(piece.max()) + 1 if piece.size else 0
    members = [np.nonzero(piece == k)[0] for k in range(count)]
    size = np.array([float(np.linalg.norm(np.ptp(points[m], axis=0))) if m.size else 0.0 for m in members])
    out: list[LoosePiece] = []
    if count < 2:
        return out
    tree = cKDTree(points)
    for k in np.nonzero(np.asarray(rigid, dtype=bool))[0]:
        mine = members[k]
        if mine.size < 4:
            continue
        near = tree.query_ball_point(points[mine], touch)
        other = np.unique(np.concatenate([np.asarray(n, dtype=np.int64) for n in near]))
        other = other[piece[other] != k]
        if other.size == 0:
            continue
        own = np.bincount(joint[mine]).argmax()
        if (joint[other] != own).any():
            continue
        touching = np.unique(piece[other])
        carriers = [int(m) for m in touching if int(m) in closed]
        if not carriers:
            continue
        carrier = max(carriers, key=lambda m: members[m].size)
        if size[k] > 0.5 * size[carrier]:
            continue
        verts, tris = closed[carrier]
        rows = np.nonzero(winding_numbers(points[mine], verts, tris) < 0.5)[0]
        if rows.size < 0.4 * mine.size:
            continue
        visible = mine[rows]
        c = points[visible].mean(axis=0)
        if winding_numbers(c, verts, tris)[0] >= 0.5:
            continue
        q = _closest_on_triangles(c, verts, tris)
        arm = c - q
        d = float(np.linalg.norm(arm))
        if d < 0.25 * float(np.sqrt(np.mean(np.sum((points[visible] - c) ** 2, axis=1)))):
            continue
        attached = np.array([i for i, n in zip(mine, near) if (piece[np.asarray(n, dtype=np.int64)] != k).any()])
        below = (points[attached] - c) @ (arm / d) <= d
        close = np.linalg.norm(points[attached] - q, axis=1) <= 1.5 * float(np.linalg.norm(points[mine] - c, axis=1).max())
        if not (below.all() and close.all()):
            continue
        reach = 1.5 * float(np.linalg.norm(points[mine] - c, axis=1).max())
        centre = curvature_centre(q, arm / d, verts, reach, 0.5 * float(np.linalg.norm(np.ptp(verts, axis=0))))
        out.append(LoosePiece(int(k), mine, rows, q, carrier, tuple(int(m) for m in touching), centre))
    return out


class PieceSwing:
    """The swing of one written mesh's loose pieces (see the module docstring).

    Args:
        pieces: The mesh's loose pieces, their ``points`` and ``touching`` in the mesh's own
            point and piece numbers.
        rest: ``[N, 3]`` the mesh's points at rest [m].
        piece_of_point: ``[N]`` the piece of each of the mesh's points.
        weight: ``[N]`` each point's physics weight in [0, 1] (a piece swings by its mean).
        frequency: ``f`` [Hz], > 0.
        damping: ``zeta``, >= 0.
        angle: The largest swing [rad] (0: none).
    """

    #: The share of its room (see the module docstring) a piece's farthest point swings into.
    ROOM = 0.5

    def __init__(self, pieces: list[LoosePiece], rest: np.ndarray, piece_of_point: np.ndarray, weight: np.ndarray,
                 frequency: float, damping: float, angle: float) -> None:
        self.rest = np.asarray(rest, dtype=np.float64)
        self.piece_of_point = np.asarray(piece_of_point, dtype=np.int64)
        self.pieces = [p for p in pieces if p.points.size]
        w = np.clip(np.asarray(weight, dtype=np.float64), 0.0, 1.0)
        self.weight = np.array([float(w[p.points].mean()) for p in self.pieces])
        shown = [self.rest[p.points[p.visible]] for p in self.pieces]
        self.gyration = np.array([float(np.mean(np.sum((v - v.mean(axis=0)) ** 2, axis=1))) for v in shown])
        # the angle about the centre that moves the centroid as far as the swing about the pivot
        self.ratio = np.array([float(np.linalg.norm(v.mean(axis=0) - p.pivot))
                               / max(float(np.linalg.norm(v.mean(axis=0) - p.centre)), 1e-300)
                               for v, p in zip(shown, self.pieces)])
        self.omega = 2.0 * np.pi * float(frequency)
        self.zeta = float(damping)
        self.angle = float(angle)
        self.enabled = bool(self.pieces) and self.omega > 0.0 and self.angle > 0.0 and bool((self.weight > 0.0).any())
        k = len(self.pieces)
        self._theta = np.zeros((k, 3))
        self._rate = np.zeros((k, 3))
        self._lbs = LbsAcceleration()  # of the shown parts' LBS centroids
        #: The largest written swing [rad] of the last frame (0 where none).
        self.largest = 0.0

    def reset(self) -> None:
        """At rest, with no history: the next two frames are written as given."""
        self._theta[:] = 0.0
        self._rate[:] = 0.0
        self._lbs.reset()

    def _room(self, points: np.ndarray, p: LoosePiece) -> float:
        """The distance [m] from ``p`` to the nearest point of a piece it does not touch at rest
        (inf where there is none), in ``points`` ``[N, 3]``."""
        from scipy.spatial import cKDTree

        others = ~np.isin(self.piece_of_point, (p.piece, *p.touching))
        if not others.any():
            return np.inf
        return float(cKDTree(points[others]).query(points[p.points])[0].min())

    def apply(self, points: np.ndarray, lbs: np.ndarray, t: float) -> np.ndarray:
        """The mesh's points with its loose pieces swung, ``[N, 3]`` (``points``: as written so
        far, ``lbs``: the mesh's LBS, both ``[N, 3]`` [m]; ``t``: the frame's clip time [s],
        rising from frame to frame). ``points`` itself where nothing swings."""
        self.largest = 0.0
        if not self.enabled:
            return points
        lbs = np.asarray(lbs, dtype=np.float64)
        if self._lbs.stale(t):
            self.reset()
        pushed = self._lbs.push(t, np.array([lbs[p.points[p.visible]].mean(axis=0) for p in self.pieces]))
        if pushed is None:
            return points
        accel, h1 = pushed
        x = np.asarray(points, dtype=np.float64)
        out = None
        for i, p in enumerate(self.pieces):
            cur = x[p.points]
            r, tr = rigid_fit(self.rest[p.points], cur)
            q = r @ p.pivot + tr
            arm = cur[p.visible].mean(axis=0) - q
            d2 = float(arm @ arm)
            if d2 <= 0.0:
                continue
            n = arm / np.sqrt(d2)
            force = -np.cross(arm, accel[i]) / (d2 + self.gyration[i])
            theta, rate = damped_step(self._theta[i], self._rate[i], force, h1, self.omega, self.zeta)
            theta, rate = theta - (theta @ n) * n, rate - (rate @ n) * n  # across the arm: a swing, no twist
            reach = float(np.linalg.norm(cur - q, axis=1).max())
            limit = min(self.angle, self.ROOM * self._room(x, p) / max(reach, 1e-300))
            scale = float(soft_limit(np.array([np.linalg.norm(theta)]), np.array([limit]))[0])
            self._theta[i], self._rate[i] = theta * scale, rate * scale
            swing = self._theta[i]
            size = float(np.linalg.norm(swing)) if self.weight[i] > 0.0 else 0.0
            if size == 0.0:
                continue
            self.largest = max(self.largest, size)
            rot = _rotation(self.ratio[i] * swing)
            o = r @ p.centre + tr
            if out is None:
                out = x.copy()
            out[p.points] = o + (cur - o) @ rot.T
        return points if out is None else out


def _rotation(v: np.ndarray) -> np.ndarray:
    """``[3, 3]`` the rotation by the rotation vector ``v`` ``[3]`` [rad] (Rodrigues)."""
    a = float(np.linalg.norm(v))
    if a == 0.0:
        return np.eye(3)
    k = v / a
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)

"""Loose garments swing: :class:`GarmentSway`, the follow-through of a garment's worn points.

A garment worn over the simulated surface (trousers, a shirt: :mod:`warpskin.kernels.deform`'s
wrap) rides on the body at its rest offset, so it moves exactly as the body under it does: it
never swings, and where the body stops it stops in the same frame. A loose garment hangs with
room between it and the body; it lags behind, swings past and settles. Per worn point ``i`` (on
the host, per frame, before the worn repair and the surface guard), a damped oscillator of
natural frequency ``f`` [Hz] and damping ratio ``zeta`` is driven by the inertial force of its
LBS's motion, along the body:

    u'' + 2 zeta w u' + w^2 u = -T_i a_i(t),      w = 2 pi f,      W_i = P_i + phi_i (S u)_i

* ``a_i`` the acceleration of the point's LBS (second differences over the last three frames,
  constant over a frame: the oscillator is integrated exactly over it); ``T_i`` the projection
  onto the plane across the point's offset from its carrier ``P_i - C_i`` (the swing slides
  along the body, it does not press into it); ``P_i`` the worn point as the wrap gives it,
  ``phi_i`` its physics weight;
* the state is limited, smoothly, to ``s_i`` (:func:`soft_limit`: untouched up to half of it,
  so the oscillator's own decay holds there; beyond, compressed towards ``s_i``; its velocity
  scaled alike), with ``s_i = share x`` the least of
  the point's rest gap over the surface it is worn on (0 where it lies on or in it), its rest
  distance to another piece, its offset ``|P_i - C_i|`` this frame (the wrap shrinks it where
  the body folds under it: the back of a bent knee) and its distance this frame to another
  piece of its mesh (a shoe, the other leg); the rest part of ``s`` changes by at most
  :attr:`GarmentSway.SLOPE` per metre along the mesh (a tight cuff beside a loose leg);
* ``S`` is :attr:`GarmentSway.ROUNDS` rounds of the mean over each point's ring of the mesh's
  worn points (neighbours swing alike, so the swing strains the garment little), its result
  projected onto each point's plane again and cut to ``s_i``.

So a tight waistband does not move, a baggy leg swings by up to ``share`` of its room, and no
point comes nearer the body or another piece than ``1 - share`` of the room it has. After a stop
the swing decays as ``exp(-zeta w t)``: with 2 Hz and 0.2, to a third in 0.45 s and a tenth in
0.9 s.

Invariants: with no LBS acceleration (a pose held from the start) ``W = P`` exactly; the first
two frames (and any frame whose time does not advance) are written as the wrap gives them and
restart the oscillator; seam copies of a point swing alike. Limits: ``u`` is an offset in the
world frame, driven by each point's own acceleration; it does not model cloth (no folds, no
drape). The worn repair and the surface guard judge the result, so a swing that would cross
the garment's other layer or another piece is taken back there.
"""

from __future__ import annotations

import numpy as np

__all__ = ["GarmentSway", "LbsAcceleration", "damped_step", "piece_room", "soft_limit"]


def piece_room(points: np.ndarray, piece: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``[K]`` the distance [m] from each of ``points[rows]`` to the nearest of ``points``
    ``[N, 3]`` on another piece (``piece``: ``[N]`` per point; inf where there is none): the
    room a garment point has before it meets the body, another garment or a shoe."""
    from scipy.spatial import cKDTree

    rows = np.asarray(rows, dtype=np.int64)
    own = piece[rows]
    out = np.full(rows.size, np.inf)
    for k in np.unique(own):
        others = piece != k
        if others.any():
            mine = own == k
            out[mine] = cKDTree(points[others]).query(points[rows[mine]])[0]
    return out


def soft_limit(size: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """``[K]`` the factor that takes a length ``size`` to at most ``limit`` (both ``[K]``,
    >= 0), smoothly: 1 up to half the limit (the oscillator's own motion, its decay untouched),
    beyond it ``L/2 + L/2 tanh((|u| - L/2) / (L/2))`` over ``|u|`` (slope 1 at the knee, at most
    ``L``: below it but where tanh rounds to 1); 0 where the limit is 0."""
    size = np.asarray(size, dtype=np.float64)
    lim = np.asarray(limit, dtype=np.float64)
    knee = 0.5 * lim
    over = size > knee
    out = np.where(lim > 0.0, 1.0, 0.0)
    k = knee[over]
    out[over] = np.where(k > 0.0, (k + k * np.tanh((size[over] - k) / np.maximum(k, 1e-300)))
                         / np.maximum(size[over], 1e-300), 0.0)
    return out


def damped_step(u: np.ndarray, v: np.ndarray, force: np.ndarray, dt: float, omega: float,
                zeta: float) -> tuple[np.ndarray, np.ndarray]:
    """The state ``(u, v)`` after ``dt`` [s] of ``u'' + 2 zeta omega u' + omega^2 u = force``
    with ``force`` constant over the step (arrays of one shape, any unit of ``u``; ``omega``
    [rad/s] > 0, ``zeta`` >= 0): the exact solution about the static offset ``force / omega^2``,
    under-, critically or over-damped alike."""
    w, z = float(omega), float(zeta)
    rest = np.asarray(force, dtype=np.float64) / (w * w)
    x0, v0 = u - rest, v
    if z < 1.0:
        wd = w * np.sqrt(1.0 - z * z)
        e, c, s = np.exp(-z * w * dt), np.cos(wd * dt), np.sin(wd * dt)
        x = e * (x0 * c + (v0 + z * w * x0) / wd * s)
        xv = e * (v0 * c - (w * x0 + z * v0) / np.sqrt(1.0 - z * z) * s)
    elif z == 1.0:
        e = np.exp(-w * dt)
        x = e * (x0 + (v0 + w * x0) * dt)
        xv = e * (v0 - w * (v0 + w * x0) * dt)
    else:
        r = np.sqrt(z * z - 1.0)
        l1, l2 = -w * (z - r), -w * (z + r)
        c2 = (v0 - l1 * x0) / (l2 - l1)
        c1 = x0 - c2
        x = c1 * np.exp(l1 * dt) + c2 * np.exp(l2 * dt)
        xv = c1 * l1 * np.exp(l1 * dt) + c2 * l2 * np.exp(l2 * dt)
    return rest + x, xv


class LbsAcceleration:
    """The acceleration of tracked LBS positions from their last three frames: second
    differences over unequal frame spans, ``2 ((L2 - L1) / h1 - (L1 - L0) / h0) / (h1 + h0)``,
    taken as constant over the latest span ``h1`` (the swing integrates it exactly there)."""

    def __init__(self) -> None:
        self._frames: list[tuple[float, np.ndarray]] = []  # the last two frames' (time, positions)

    def reset(self) -> None:
        """No history: the next two frames give no acceleration."""
        self._frames = []

    def stale(self, t: float) -> bool:
        """Whether clip time ``t`` [s] does not advance past the last frame's (a restart)."""
        return bool(self._frames) and not t > self._frames[-1][0]

    def push(self, t: float, now: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Record positions ``now`` (any shape, [m]) at ``t`` [s], later than the last frame's;
        ``(acceleration [m/s^2] shaped as now, h1 [s])``, or None on the first two frames."""
        if len(self._frames) < 2:
            self._frames.append((float(t), now))
            return None
        (t0, l0), (t1, l1) = self._frames
        h1, h0 = float(t) - t1, t1 - t0
        accel = 2.0 * ((now - l1) / h1 - (l1 - l0) / h0) / (h1 + h0)
        self._frames = [(t1, l1), (float(t), now)]
        return accel, h1


def _across(x: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rows of ``x`` ``[K, 3]`` less their part along the unit rows of ``n``."""
    return x - np.einsum("ij,ij->i", x, n)[:, None] * n


class GarmentSway:
    """The swing of one written mesh's garment points (see the module docstring).

    Args:
        worn: ``[K]`` the mesh's own point indices that are worn garment points.
        gap: ``[K]`` each point's rest gap [m] over the surface it is worn on (negative or 0:
            none; it does not swing).
        weight: ``[K]`` each point's physics weight in [0, 1].
        frequency: ``f`` [Hz], > 0.
        damping: ``zeta``, >= 0.
        share: The swing's limit as a share of the gap, in [0, 1] (0: no swing).
        mesh: The written mesh (:class:`~warpskin.quality.WrittenMesh`) whose points ``worn``
            index: where given, the limit changes by at most :attr:`SLOPE` per unit length along
            its edges (0 on the points not worn), and the swing is the ring mean ``S``.
        pieces: ``[N]`` the piece of every point of the mesh: where given, a point swings by at
            most ``share`` of its distance this frame to a point of another piece.
    """

    #: Rounds of the ring mean over the written swing (see ``mesh``).
    ROUNDS = 4
    #: The most a swing's limit changes per unit length along the mesh's edges (see ``mesh``).
    SLOPE = 0.2

    def __init__(self, worn: np.ndarray, gap: np.ndarray, weight: np.ndarray, frequency: float, damping: float,
                 share: float, mesh=None, pieces: np.ndarray | None = None) -> None:
        self.worn = np.asarray(worn, dtype=np.int64)
        self.pieces = None if pieces is None else np.asarray(pieces)
        k = self.worn.size
        self.share = float(share)
        self.limit = self.share * np.maximum(np.asarray(gap, dtype=np.float64).reshape(k), 0.0)
        self._smooth = None
        if mesh is not None and k:
            self.limit = self._sloped(mesh, self.limit)
            self._smooth = self._ring_mean(mesh)
        self.weight = np.clip(np.asarray(weight, dtype=np.float64).reshape(k), 0.0, 1.0)
        self.omega = 2.0 * np.pi * float(frequency)
        self.zeta = float(damping)
        self.enabled = bool(k) and self.omega > 0.0 and bool((self.limit * self.weight > 0.0).any())
        self._u = np.zeros((k, 3))
        self._v = np.zeros((k, 3))
        self._lbs = LbsAcceleration()
        #: The largest written swing [m] of the last frame (0 where none).
        self.largest = 0.0

    def _sloped(self, mesh, limit: np.ndarray) -> np.ndarray:
        """``limit`` ``[K]`` made to change by at most :attr:`SLOPE` per metre along ``mesh``'s
        rest edges (:class:`~warpskin.quality.WrittenMesh`; points not worn: 0), the largest
        such limit under it: neighbours whose limits differ swing apart by at most that share of
        their edge, so the swing strains the garment by at most about :attr:`SLOPE` (a tight
        cuff beside a loose leg)."""
        welded = mesh.weld[self.worn]
        lim = np.zeros(mesh.first.size)
        lim[welded] = np.inf
        np.minimum.at(lim, welded, limit)
        e, step = mesh.edges, self.SLOPE * mesh.rest_length
        for _ in range(mesh.first.size):
            new = lim.copy()
            np.minimum.at(new, e[:, 0], lim[e[:, 1]] + step)
            np.minimum.at(new, e[:, 1], lim[e[:, 0]] + step)
            if np.array_equal(new, lim):
                break
            lim = new
        return lim[welded]

    def _ring_mean(self, mesh):
        """``(M, ids)``: ``M`` the ``[W, W]`` sparse mean over each welded worn point and its
        neighbours along ``mesh``'s edges among the worn points, ``ids`` ``[K]`` each worn
        point's row (seam copies share one)."""
        import scipy.sparse as sp

        from ..preprocess.fast_summation import vertex_adjacency

        uniq, ids = np.unique(mesh.weld[self.worn], return_inverse=True)
        ring = vertex_adjacency(mesh.welded_triangles, mesh.first.size)[uniq][:, uniq].astype(np.float64)
        ring = (ring + sp.identity(uniq.size, format="csr")).tocsr()
        deg = np.asarray(ring.sum(axis=1)).ravel()
        return sp.diags(1.0 / deg) @ ring, ids.ravel()

    def reset(self) -> None:
        """At rest, with no history: the next two frames are written as given."""
        self._u[:] = 0.0
        self._v[:] = 0.0
        self._lbs.reset()

    def step(self, u: np.ndarray, v: np.ndarray, a: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The oscillator's state ``(u, v)`` (``[K, 3]`` [m], [m/s]) after ``dt`` [s] under the
        constant acceleration ``a`` ``[K, 3]`` [m/s^2] (:func:`damped_step`)."""
        return damped_step(u, v, -a, dt, self.omega, self.zeta)

    def apply(self, points: np.ndarray, lbs: np.ndarray, t: float, carriers: np.ndarray | None = None) -> np.ndarray:
        """The mesh's points with its garment points swung, ``[N, 3]`` (``points``: as the wrap
        gives them, ``lbs``: the mesh's LBS, both ``[N, 3]`` [m]; ``t``: the frame's clip time
        [s], rising from frame to frame). ``points`` itself where nothing swings."""
        self.largest = 0.0
        if not self.enabled:
            return points
        if self._lbs.stale(t):
            self.reset()
        pushed = self._lbs.push(t, np.asarray(lbs, dtype=np.float64)[self.worn])
        if pushed is None:
            return points
        a, h1 = pushed
        lim = self.limit
        n = None
        if carriers is not None:  # along the body: the swing in the plane across the point's offset
            n = np.asarray(points, dtype=np.float64)[self.worn] - np.asarray(carriers, dtype=np.float64)
            gap = np.linalg.norm(n, axis=1)
            lim = np.minimum(lim, self.share * gap)  # where the body folds under it, the room it has now
            n /= np.maximum(gap, 1e-300)[:, None]
            a = _across(a, n)
        if self.pieces is not None:  # and where another piece comes near in this pose
            lim = np.minimum(lim, self.share * piece_room(np.asarray(points, dtype=np.float64), self.pieces, self.worn))
        u, v = self.step(self._u, self._v, a, h1)
        if n is not None:
            u, v = _across(u, n), _across(v, n)
        scale = soft_limit(np.linalg.norm(u, axis=1), lim)
        self._u, self._v = u * scale[:, None], v * scale[:, None]
        swing = self._u
        if self._smooth is not None:  # neighbours swing alike: a few rounds of the ring mean
            m, ids = self._smooth
            w = np.zeros((m.shape[0], 3))
            np.add.at(w, ids, swing)
            w /= np.bincount(ids, minlength=m.shape[0])[:, None]
            for _ in range(self.ROUNDS):
                w = m @ w
            swing = w[ids]
            if n is not None:  # the mean of neighbours' slides leans off the plane: back onto it
                swing = _across(swing, n)
            size = np.linalg.norm(swing, axis=1)  # still within each point's limit
            swing = swing * np.minimum(1.0, lim / np.maximum(size, 1e-300))[:, None]
        swing = self.weight[:, None] * swing
        self.largest = float(np.linalg.norm(swing, axis=1).max())
        if self.largest == 0.0:
            return points
        out = np.array(points, dtype=np.float64, copy=True)
        out[self.worn] += swing
        return out

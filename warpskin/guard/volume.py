"""Pieces written by capture keep the volume their simulation keeps: :class:`PieceVolume`.

A character simulated on its own pieces is written by capture where they are dense or worn
(:mod:`warpskin.capture`): its written points follow the simulated surface, whose sub-volumes
the volume constraints hold, but the written surface between them is interpolated and the
volume of a written piece drifts where its simulated one does not. Per frame, per mesh written
by capture (on the host, in the mesh's welded topology), before the worn repair and the surface
guard, and once more after the worn repair, the points it moved held (weight 0):

    C_k = V_k(W) - V0_k,    W_i <- W_i - w_i g_i C_k / sum_{j in k} w_j |g_j|^2

for every closed piece ``k`` (a connected component of the welded mesh, its holes closed by fans
to each loop's centre, as :func:`~warpskin.delivery.piece_volumes` measures it) that holds a
point with weight: ``V`` its signed volume [m^3], ``V0`` at rest, ``g_i = dV / dW_i`` (the fans'
centres moving with their loops) and ``w_i`` in [0, 1] the point's weight (its physics weight;
0 on a piece moved as a whole, which keeps its LBS shape). This is the
position-based projection of a volume constraint per piece (Mueller et al. 2007, as the
sub-volumes' in :mod:`warpskin.kernels.volume`), repeated ``ROUNDS`` times: the gradient moves
with the points, so one projection leaves an error of second order in the correction.

Invariants: a point of weight 0 is never moved; every written copy of a welded point moves
alike; a piece whose boundary is not a set of simple loops, or whose rest volume is below a
thousandth of the largest piece's, is left as it is. The surface guard judges the result, so a
correction that would cross or fold is taken back with the rest. Limits: an open piece's volume
depends on how its holes are closed; this is the volume the quality measures report, not that
of the caps the simulation uses.
"""

from __future__ import annotations

import numpy as np

from ..delivery import hole_fans, piece_components, piece_volumes
from ..mesh import mesh_edge_report
from ..quality import WrittenMesh

__all__ = ["PieceVolume"]


class PieceVolume:
    """The volume repair of one mesh written by capture (see the module docstring).

    Args:
        mesh: The written mesh (its welded topology).
        weight: ``[N]`` per written point (file order), its weight in the correction in [0, 1].
    """

    #: Projections per frame.
    ROUNDS = 2

    def __init__(self, mesh: WrittenMesh, weight: np.ndarray) -> None:
        self.mesh = mesh
        c = mesh.first.size
        t = mesh.welded_triangles
        self._tri = t
        self.piece = piece_components(c, t) if c else np.zeros(0, dtype=np.int64)
        self.count = int(self.piece.max()) + 1 if c else 0
        self.fans = hole_fans(t) if c else (np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64))
        w = np.clip(np.asarray(weight, dtype=np.float64), 0.0, 1.0)[mesh.first] if c else np.zeros(0)
        rest = mesh.welded(mesh.rest)
        self.rest_volumes = piece_volumes(rest, t, self.piece, self.count, self.fans) if c else np.zeros(0)
        # a piece is closed when each of its boundary edges is one of the fans' (hole_fans is
        # empty where the boundary is not simple loops: then only pieces without a boundary)
        open_edge = np.zeros(self.count, dtype=bool)
        if c and not len(self.fans[0]):
            boundary = mesh_edge_report(t, c)["boundary_edges"]
            open_edge[self.piece[boundary[:, 0]]] = True
        big = np.abs(self.rest_volumes) > 1e-3 * (np.abs(self.rest_volumes).max() if self.count else 0.0)
        active = big & ~open_edge
        if c:
            active &= np.bincount(self.piece, weights=w, minlength=self.count) > 0
        #: ``[K]`` the pieces that are repaired.
        self.active = active
        self.weight = np.where(active[self.piece], w, 0.0) if c else w
        #: The largest relative volume change of a repaired piece before the last call's
        #: repair (0 where none is repaired).
        self.error = 0.0

    def gradients(self, x: np.ndarray) -> np.ndarray:
        """``[C, 3]`` ``dV_k / dx_i`` of every welded point's piece volume at ``x`` ``[C, 3]``
        (:func:`~warpskin.delivery.piece_volumes`, its fans' centres the means of their loops)."""
        t = self._tri
        # about each piece's centroid (the gradient of a closed piece does not depend on the
        # origin; a far one would cost digits)
        n = np.maximum(np.bincount(self.piece, minlength=self.count), 1)
        centre = np.stack([np.bincount(self.piece, weights=x[:, j], minlength=self.count) for j in range(3)], axis=1)
        x = x - (centre / n[:, None])[self.piece]
        c = len(x)
        a, b, d = x[t[:, 0]], x[t[:, 1]], x[t[:, 2]]
        # V = sum a . (b x d) / 6 about any origin for a closed piece: dV/da = (b x d) / 6, ...
        rows = [t[:, 0], t[:, 1], t[:, 2]]
        parts = [np.cross(b, d), np.cross(d, a), np.cross(a, b)]
        e, loop = self.fans
        if len(e):
            m = np.stack([np.bincount(loop, weights=x[e[:, 1], j]) for j in range(3)], axis=1)
            m /= np.bincount(loop)[:, None]
            mc = m[loop]  # fan triangle (e0, e1, m) of the boundary edge (e0, e1)
            rows += [e[:, 0], e[:, 1]]
            parts += [np.cross(x[e[:, 1]], mc), np.cross(mc, x[e[:, 0]])]
            # the centre is the mean of the loop's points (each is the e1 of one fan edge)
            gm = np.stack([np.bincount(loop, weights=v, minlength=len(m)) for v in np.cross(x[e[:, 0]], x[e[:, 1]]).T],
                          axis=1)
            rows.append(e[:, 1])
            parts.append(gm[loop] / np.bincount(loop)[loop][:, None])
        r, p = np.concatenate(rows), np.concatenate(parts)
        return np.stack([np.bincount(r, weights=p[:, j], minlength=c) for j in range(3)], axis=1) / 6.0

    def apply(self, points: np.ndarray, hold: np.ndarray | None = None) -> np.ndarray:
        """The repaired points ``[N, 3]`` (file order) of ``points`` ``[N, 3]`` [m]; ``points``
        itself where no piece is repaired. ``hold``: ``[N]`` bool per point (file order), points
        that keep where they are (weight 0: where the worn repair has just taken a garment's
        layers apart); only the pieces that hold one are repaired then. None: every piece."""
        if not self.active.any():
            self.error = 0.0
            return points
        mesh = self.mesh
        x = mesh.welded(np.asarray(points, dtype=np.float64))
        x0 = x.copy()
        w, active = self.weight, self.active
        if hold is not None:
            held = np.zeros(x.shape[0], dtype=bool)
            held[mesh.weld[np.asarray(hold, dtype=bool)]] = True
            w = np.where(held, 0.0, w)
            active = active & (np.bincount(self.piece, weights=held, minlength=self.count) > 0)
            if not active.any():
                return points
        for r in range(self.ROUNDS):
            v = piece_volumes(x, self._tri, self.piece, self.count, self.fans)
            c = np.where(active, v - self.rest_volumes, 0.0)
            if r == 0:
                self.error = float(np.max(np.abs(c[active] / self.rest_volumes[active])))
            g = self.gradients(x)
            denom = np.bincount(self.piece, weights=w * np.einsum("ij,ij->i", g, g), minlength=self.count)
            s = np.where(denom > 0.0, c / np.where(denom > 0.0, denom, 1.0), 0.0)
            x -= (s[self.piece] * w)[:, None] * g
        return np.asarray(points, dtype=np.float64) + (x - x0)[mesh.weld]

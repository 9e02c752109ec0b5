"""What the physics delivered to the written meshes, frame by frame, against their own LBS.

:mod:`warpskin.quality` checks that a written mesh is no worse than its LBS; this module says how
much of the physics reaches it, on the meshes as written (the file's topology), whatever surface
was simulated. Per written mesh, with ``W`` the written points, ``L`` their LBS and ``P`` the
physical result before the surface guard (all ``[N, 3]`` [m]) and ``o = W - L`` the offset:

* **held**: ``sum min(|P - W|, |P - L|) / sum |P - L|`` over the points and frames, the share
  of the physical displacement the guard took back (0: all of it written; 1: all held at LBS; a
  point written farther from its physical result than its whole displacement, a piece carried
  by its neighbour, counts that displacement, no more), and the same share in the worst frame;
* **secondary motion**: ``mean |o(t) - o(t-1)|`` over ``mean |L(t) - L(t-1)|``, summed over the
  frames: how much the skin moves against the animation, as a share of the animation's own
  motion (the jiggle, the lag and the settling after a stop);
* **chatter**: the largest ``|o(t) - o(t-1)|`` of any point between two frames, as a share of
  the character's height (a point that jumps between frames);
* **volume**: the signed volume of every piece of the mesh (connected component, welded), each
  hole closed by a fan to the centre of its boundary loop (the volume of a closed piece; an open
  body closed at its neck, wrists and ankles; a cone volume about the piece's own centroid where
  a boundary is not a set of simple loops), summed, its change against rest beside LBS's, and
  the worst piece's (among those holding at least 1 % of the mesh's rest volume);
* **rigid pieces**: the pieces LBS moves rigidly (every point on one joint with weight
  :data:`RIGID_WEIGHT` or more): the RMS distance [m] of their points from the best rigid motion
  of their rest shape (Kabsch): how much a piece that is rigid in the file was deformed.

The first frame is the start of the simulation (at LBS by construction): motion is measured
from the second frame on.
"""

from __future__ import annotations

import numpy as np

from .preprocess.pieces import boundary_loops
from .quality import WrittenMesh
from .transforms import rigid_fit

__all__ = ["DeliveryLog", "RIGID_WEIGHT", "hole_fans", "piece_components", "piece_volumes", "rigid_rms"]

#: A point is on one joint when that joint's weight is at least this.
RIGID_WEIGHT = 0.999


def piece_components(count: int, triangles: np.ndarray) -> np.ndarray:
    """``[count]`` the connected component of every point of ``triangles`` ``[T, 3]`` (a point on
    no triangle is a component of its own)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    t = np.asarray(triangles, dtype=np.int64)
    rows, cols = np.concatenate([t[:, 0], t[:, 1]]), np.concatenate([t[:, 1], t[:, 2]])
    _, label = connected_components(sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(count, count)),
                                    directed=False)
    return label


def hole_fans(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fans that close the holes of a mesh: ``(edges [F, 2], loop [F])``, every boundary
    edge ``(b, a)`` (opposite to the way its triangle runs it) and its loop's number; empty where
    the boundary is not a set of simple loops (:func:`~warpskin.preprocess.pieces.boundary_loops`)."""
    loops, simple = boundary_loops(triangles)
    if not simple or not loops:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64)
    edges = np.concatenate([np.stack([np.roll(lp, -1), lp], axis=1) for lp in loops])
    return edges, np.concatenate([np.full(len(lp), k) for k, lp in enumerate(loops)])


def piece_volumes(points: np.ndarray, triangles: np.ndarray, piece: np.ndarray, count: int,
                  fans: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``[K]`` the signed volume [m^3] of each of ``count`` pieces (``piece`` ``[V]``, the piece of
    every point): ``sum (a - c) . ((b - c) x (d - c)) / 6`` over its triangles ``(a, b, d)`` about
    ``c``, the mean of its points, and over the fan triangles ``(b, a, m)`` that close its holes
    (``fans``: :func:`hole_fans`; ``m`` the centre of the edge's loop)."""
    x = np.asarray(points, dtype=np.float64)
    n = np.bincount(piece, minlength=count).astype(np.float64)
    c = np.stack([np.bincount(piece, weights=x[:, k], minlength=count) for k in range(3)], axis=1)
    c /= np.maximum(n, 1.0)[:, None]
    t = np.asarray(triangles, dtype=np.int64)
    tp = piece[t[:, 0]]
    a, b, d = (x[t[:, k]] - c[tp] for k in range(3))
    out = np.bincount(tp, weights=np.einsum("ij,ij->i", a, np.cross(b, d)) / 6.0, minlength=count)
    if fans is not None and len(fans[0]):
        e, loop = fans
        k = int(loop.max()) + 1
        m = np.stack([np.bincount(loop, weights=x[e[:, 1], j], minlength=k) for j in range(3)], axis=1)
        m /= np.bincount(loop, minlength=k)[:, None]
        ep = piece[e[:, 0]]
        a, b, d = x[e[:, 0]] - c[ep], x[e[:, 1]] - c[ep], m[loop] - c[ep]
        out += np.bincount(ep, weights=np.einsum("ij,ij->i", a, np.cross(b, d)) / 6.0, minlength=count)
    return out


def rigid_rms(points: np.ndarray, rest: np.ndarray) -> float:
    """The RMS distance [m] of ``points`` ``[N, 3]`` from the best rigid motion of ``rest`` onto
    them (Kabsch, without scaling)."""
    p = np.asarray(points, dtype=np.float64)
    r, t = rigid_fit(rest, p)
    return float(np.sqrt(np.mean(np.sum((np.asarray(rest, dtype=np.float64) @ r.T + t - p) ** 2, axis=1))))


class _Mesh:
    """What the measures of one written mesh need, made once at rest."""

    def __init__(self, mesh: WrittenMesh, dense_weights: np.ndarray | None) -> None:
        self.mesh = mesh
        c = mesh.first.size
        self.piece = piece_components(c, mesh.welded_triangles) if c else np.zeros(0, dtype=np.int64)
        self.count = int(self.piece.max()) + 1 if c else 0
        rest = mesh.welded(mesh.rest)
        self.fans = hole_fans(mesh.welded_triangles) if c else None
        self.rest_volumes = piece_volumes(rest, mesh.welded_triangles, self.piece, self.count, self.fans)
        total = float(np.abs(self.rest_volumes).sum())
        self.significant = np.abs(self.rest_volumes) >= 0.01 * total if total > 0 else np.zeros(self.count, bool)
        self.rigid: list[np.ndarray] = []
        if dense_weights is not None and c:
            w = np.asarray(dense_weights, dtype=np.float64)[mesh.first]
            joint = np.argmax(w, axis=1)
            strong = w[np.arange(c), joint] >= RIGID_WEIGHT
            for k in range(self.count):
                members = np.nonzero(self.piece == k)[0]
                if members.size >= 4 and strong[members].all() and np.unique(joint[members]).size == 1:
                    self.rigid.append(members)
        self.rest = rest


class DeliveryLog:
    """The delivery measures (see the module docstring) of every written mesh of a run.

    Args:
        meshes: ``{name: WrittenMesh}`` the meshes written with physics.
        height: The character's height [m] (the largest extent of its rest pose): the unit of
            chatter.
        weights: ``{name: [N, J]}`` each mesh's LBS weights (for its rigid pieces); a mesh
            without has none.
    """

    KEYS = ("held", "held_sum", "physical_sum", "motion", "lbs_motion", "chatter", "volume", "volume_lbs",
            "piece_volume", "piece_volume_lbs", "rigid_rms")

    def __init__(self, meshes: dict[str, WrittenMesh], height: float, weights: dict | None = None) -> None:
        self.height = float(height)
        self.meshes = {name: _Mesh(m, (weights or {}).get(name)) for name, m in meshes.items()}
        self.series: dict[str, dict[str, list]] = {name: {k: [] for k in self.KEYS} for name in self.meshes}
        self._last: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def measure(self, written: dict, lbs: dict, physical: dict | None = None) -> None:
        """One frame: ``written``, ``lbs`` and (where the caller has it) ``physical``, each
        ``{name: [N, 3]}``."""
        for name, m in self.meshes.items():
            s = self.series[name]
            mesh = m.mesh
            w = mesh.welded(written[name])
            lb = mesh.welded(lbs[name])
            o = w - lb
            if physical is not None and name in physical:
                p = mesh.welded(physical[name])
                d = np.linalg.norm(p - lb, axis=1)
                total = float(d.sum())
                held = float(np.minimum(np.linalg.norm(p - w, axis=1), d).sum())
                s["held"].append(held / total if total > 0 else 0.0)
                s["held_sum"].append(held)
                s["physical_sum"].append(total)
            else:
                s["held"].append(0.0)
                s["held_sum"].append(0.0)
                s["physical_sum"].append(0.0)
            last = self._last.get(name)
            if last is None:
                s["motion"].append(0.0)
                s["lbs_motion"].append(0.0)
                s["chatter"].append(0.0)
            else:
                step = np.linalg.norm(o - last[0], axis=1)
                s["motion"].append(float(step.mean()) if step.size else 0.0)
                s["lbs_motion"].append(float(np.linalg.norm(lb - last[1], axis=1).mean()) if step.size else 0.0)
                s["chatter"].append(float(step.max()) / self.height if step.size and self.height > 0 else 0.0)
            self._last[name] = (o, lb)
            for key, x in (("", w), ("_lbs", lb)):
                v = piece_volumes(x, mesh.welded_triangles, m.piece, m.count, m.fans)
                total0 = float(m.rest_volumes.sum())
                s["volume" + key].append(abs(float(v.sum()) / total0 - 1.0) if total0 != 0 else 0.0)
                sig = m.significant
                s["piece_volume" + key].append(float(np.max(np.abs(v[sig] / m.rest_volumes[sig] - 1.0))) if sig.any()
                                               else 0.0)
            s["rigid_rms"].append(max((rigid_rms(w[idx], m.rest[idx]) for idx in m.rigid), default=0.0))

    def summary(self) -> dict:
        """Per mesh: ``held`` (over the frames after the first) and ``held_max`` (the worst
        frame's), ``secondary_motion`` (the ratio),
        ``chatter`` (worst, share of the height), ``volume`` and ``volume_lbs`` (worst change
        after the first frame), ``piece_volume`` and ``piece_volume_lbs`` (the worst piece's),
        ``rigid_pieces`` and ``rigid_rms_m`` (worst)."""
        out = {}
        for name, s in self.series.items():
            n = len(s["held"])
            if n == 0:
                continue
            after = slice(1, None) if n > 1 else slice(0, None)
            lbs_motion = float(np.sum(s["lbs_motion"]))
            physical = float(np.sum(s["physical_sum"][after]))
            out[name] = {
                "held": float(np.sum(s["held_sum"][after])) / physical if physical > 0 else 0.0,
                "held_max": float(np.max(s["held"][after])),
                "secondary_motion": float(np.sum(s["motion"])) / lbs_motion if lbs_motion > 0 else 0.0,
                "chatter": float(np.max(s["chatter"])),
                "volume": float(np.max(s["volume"][after])),
                "volume_lbs": float(np.max(s["volume_lbs"][after])),
                "piece_volume": float(np.max(s["piece_volume"][after])),
                "piece_volume_lbs": float(np.max(s["piece_volume_lbs"][after])),
                "rigid_pieces": len(self.meshes[name].rigid),
                "rigid_rms_m": float(np.max(s["rigid_rms"])),
            }
        return out

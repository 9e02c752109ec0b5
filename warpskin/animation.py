"""Animation clips of a rig: :class:`Track` (one property of one joint, keyed) and :class:`Clip`
(a named set of tracks), sampled at any time; :func:`key_rate`, the frame rate a clip's keys were
sampled at. Times in seconds; translations in the rig's units (metres once a rig is
constructed), rotations as unit quaternions ``(x, y, z, w)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .errors import RigError
from .transforms import compose_trs, decompose_trs, quat_normalize, quat_slerp

if TYPE_CHECKING:
    from .rig import Skeleton

__all__ = ["Track", "Clip", "key_rate", "INTERPOLATIONS", "PATHS"]

INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
PATHS = {"translation": 3, "rotation": 4, "scale": 3}


@dataclass
class Track:
    """One animated property of one joint: keyframes and how to interpolate between them.

    Attributes:
        path: ``"translation"`` [m], ``"rotation"`` (quaternion x, y, z, w) or ``"scale"``.
        times: Key times [s], shape ``[key_count]``, strictly increasing.
        values: Key values, shape ``[key_count, C]`` for ``LINEAR``/``STEP`` and
            ``[key_count, 3, C]`` (in-tangent, value, out-tangent) for ``CUBICSPLINE``;
            ``C`` is 3 or 4.
        interpolation: ``"LINEAR"`` (rotations slerped), ``"STEP"`` or ``"CUBICSPLINE"``
            (cubic Hermite, the glTF 2.0 rule; rotations renormalised).
    """

    path: str
    times: np.ndarray
    values: np.ndarray
    interpolation: str = "LINEAR"

    def __post_init__(self) -> None:
        if self.path not in PATHS:
            raise RigError(f"track path {self.path!r} is not one of {sorted(PATHS)}")
        if self.interpolation not in INTERPOLATIONS:
            raise RigError(f"interpolation {self.interpolation!r} is not one of {INTERPOLATIONS}")
        self.times = np.asarray(self.times, dtype=np.float64).ravel()
        c = PATHS[self.path]
        values = np.asarray(self.values, dtype=np.float64)
        k = self.times.size
        if k == 0:
            raise RigError(f"{self.path} track has no keys")
        shape = (k, 3, c) if self.interpolation == "CUBICSPLINE" else (k, c)
        if values.size != int(np.prod(shape)):
            raise RigError(
                f"{self.path} track: {k} key times but {values.size} values; expected shape {shape}"
            )
        self.values = values.reshape(shape)
        if not np.all(np.isfinite(self.times)) or not np.all(np.isfinite(self.values)):
            raise RigError(f"{self.path} track holds NaN or inf keys")
        if k > 1 and np.any(np.diff(self.times) <= 0.0):
            raise RigError(f"{self.path} track key times are not strictly increasing")

    @property
    def start(self) -> float:
        return float(self.times[0])

    @property
    def end(self) -> float:
        return float(self.times[-1])

    def sample(self, t: float) -> np.ndarray:
        """Value at time ``t`` [s]; clamped to the first/last key outside the key range."""
        times, cubic = self.times, self.interpolation == "CUBICSPLINE"
        vals = self.values[:, 1] if cubic else self.values
        if t <= times[0] or times.size == 1:
            out = vals[0].copy()
        elif t >= times[-1]:
            out = vals[-1].copy()
        else:
            k = int(np.searchsorted(times, t, side="right")) - 1
            t0, t1 = times[k], times[k + 1]
            dt = t1 - t0
            u = (t - t0) / dt
            if self.interpolation == "STEP":
                out = vals[k].copy()
            elif self.interpolation == "LINEAR":
                if self.path == "rotation":
                    out = quat_slerp(vals[k], vals[k + 1], u)
                else:
                    out = (1.0 - u) * vals[k] + u * vals[k + 1]
            else:
                # glTF 2.0 Appendix C: Hermite with tangents scaled by the key interval.
                p0, m0 = self.values[k, 1], dt * self.values[k, 2]
                p1, m1 = self.values[k + 1, 1], dt * self.values[k + 1, 0]
                u2, u3 = u * u, u * u * u
                out = (
                    (2 * u3 - 3 * u2 + 1) * p0
                    + (u3 - 2 * u2 + u) * m0
                    + (-2 * u3 + 3 * u2) * p1
                    + (u3 - u2) * m1
                )
        if self.path == "rotation":
            out = quat_normalize(out)
        return out


@dataclass
class Clip:
    """A named animation: tracks keyed by ``(joint index, path)``.

    Joints or properties without a track keep the skeleton's rest value.
    """

    name: str
    tracks: dict[tuple[int, str], Track] = field(default_factory=dict)
    #: The source's frame rate [frames/s]: a USD stage's timeCodesPerSecond, the spacing of a
    #: glTF clip's keys where it is a frame rate (:func:`key_rate`), else ``None``.
    rate: float | None = None
    #: Tracks of non-joint nodes above root joints (:attr:`Skeleton.root_chains`), keyed by
    #: ``(node, path)``: a skeleton nested under animated nodes (RecursiveSkeletons).
    ancestor_tracks: dict[tuple[int, str], Track] = field(default_factory=dict)

    @property
    def start(self) -> float:
        """First key time over all tracks [s] (0 for an empty clip)."""
        return min((tr.start for tr in self._all_tracks()), default=0.0)

    @property
    def end(self) -> float:
        """Last key time over all tracks [s] (0 for an empty clip)."""
        return max((tr.end for tr in self._all_tracks()), default=0.0)

    def _all_tracks(self):
        return list(self.tracks.values()) + list(self.ancestor_tracks.values())

    def root_transforms(self, skeleton: Skeleton, t: float) -> np.ndarray:
        """World transform of every root joint's non-joint ancestors at time ``t``, ``[J, 4, 4]``:
        the skeleton's static :attr:`~Skeleton.root_transform`, with every chain that holds an
        animated node evaluated node by node at ``t`` (glTF: a node's world transform is its
        parent's times its own local one)."""
        root = skeleton.root_transform
        if not self.ancestor_tracks or not skeleton.root_chains:
            return root
        root = root.copy()
        for j, chain in skeleton.root_chains.items():
            if not any((node, p) in self.ancestor_tracks for node, _ in chain for p in PATHS):
                continue
            m = np.eye(4)
            for node, rest in chain:
                keyed = [p for p in PATHS if (node, p) in self.ancestor_tracks]
                if keyed:
                    trs = list(decompose_trs(rest))
                    for p in keyed:
                        trs[list(PATHS).index(p)] = self.ancestor_tracks[(node, p)].sample(t)
                    rest = compose_trs(*trs)
                m = m @ rest
            root[j] = m
        return root

    @property
    def duration(self) -> float:
        return self.end - self.start

    def sample_local_trs(self, skeleton: Skeleton, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local translation ``[J, 3]``, rotation ``[J, 4]`` and scale ``[J, 3]`` at time ``t``."""
        tr = skeleton.rest_translation.copy()
        rot = skeleton.rest_rotation.copy()
        sc = skeleton.rest_scale.copy()
        for (j, path), track in self.tracks.items():
            value = track.sample(t)
            if path == "translation":
                tr[j] = value
            elif path == "rotation":
                rot[j] = value
            else:
                sc[j] = value
        return tr, rot, sc


def key_rate(times: np.ndarray, *, lowest: float = 12.0, highest: float = 240.0, tolerance: float = 1e-3) -> float | None:
    """The frame rate a clip's key times were sampled at, where one is evident: the inverse
    of the median spacing, rounded to a whole rate in ``[lowest, highest]`` frames/s, with
    every key within ``tolerance`` frames of that grid. ``None`` for sparse or irregular keys
    (RiggedFigure's two keys 1.25 s apart), so that the caller falls back to a default."""
    t = np.unique(np.asarray(times, dtype=np.float64))
    if t.size < 3:
        return None
    spacing = float(np.median(np.diff(t)))
    if spacing <= 0:
        return None
    rate = round(1.0 / spacing)
    if not (lowest <= rate <= highest) or abs(rate * spacing - 1.0) > 1e-2:
        return None
    off_grid = np.abs(t * rate - np.round(t * rate))
    return float(rate) if float(off_grid.max()) <= tolerance else None

"""Muscle activation over time (clench/relax per group, keyed to beats) and a scene's
``[popping]`` settings."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import SceneError

if TYPE_CHECKING:
    from ..params import PoppingSettings


# --------------------------------------------------------------------------------------------
# Activation timeline
# --------------------------------------------------------------------------------------------
class ActivationTimeline:
    """Muscle activation per group over time: piecewise-linear keys, steps where two keys share
    a time (the later one holds from that instant on).

    Args:
        keys: Group name -> ``[(time [s], activation in [0, 1]), ...]`` with non-decreasing
            times. Before the first key the first value holds, after the last the last.

    Example:
        >>> tl = ActivationTimeline({"biceps": ActivationTimeline.beats([0.5, 1.5], hold=0.4)})
        >>> tl.sample(0.6, ["biceps"])
        array([1.])
    """

    def __init__(self, keys: Mapping[str, Sequence[tuple[float, float]]] | None = None, *, where: str = "activation") -> None:
        self.times: dict[str, np.ndarray] = {}
        self.values: dict[str, np.ndarray] = {}
        for name, pairs in (keys or {}).items():
            arr = np.asarray(pairs, dtype=np.float64)
            if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
                raise SceneError(f"{where}: group {name!r}: keys must be a non-empty list of [time, activation] pairs")
            t, a = arr[:, 0], arr[:, 1]
            if not np.all(np.isfinite(arr)):
                raise SceneError(f"{where}: group {name!r}: keys hold NaN or inf")
            if np.any(np.diff(t) < 0.0):
                k = int(np.nonzero(np.diff(t) < 0.0)[0][0])
                raise SceneError(f"{where}: group {name!r}: key times must not decrease (key {k + 1} at {t[k + 1]} s "
                               f"comes after {t[k]} s)")
            if np.any((a < 0.0) | (a > 1.0)):
                raise SceneError(f"{where}: group {name!r}: activations must be in [0, 1], got {a[(a < 0) | (a > 1)][:4].tolist()}")
            self.times[str(name)] = t
            self.values[str(name)] = a

    @staticmethod
    def beats(beats: Sequence[float], *, hold: float, attack: float = 0.0, release: float = 0.0,
              where: str = "activation", levels: Sequence[float] | None = None) -> list[tuple[float, float]]:
        """Keys of one pop per beat: rise 0 -> 1 (or the beat's ``levels`` entry, in [0, 1]) over
        ``attack`` [s] from the beat, stay clenched until ``hold`` [s] after it, fall to 0 over
        ``release`` [s].

        Raises:
            SceneError: negative durations, ``attack > hold``, levels outside [0, 1], or pops
                that overlap the next beat.
        """
        raw = np.asarray(beats, dtype=np.float64).ravel()
        order = np.argsort(raw, kind="stable")
        b = raw[order]
        if b.size == 0 or not np.all(np.isfinite(b)):
            raise SceneError(f"{where}: beats must be a non-empty list of times [s]")
        lv = np.ones(b.size) if levels is None else np.asarray(levels, dtype=np.float64).ravel()
        if lv.shape != raw.shape or not np.all((lv >= 0.0) & (lv <= 1.0)):
            raise SceneError(f"{where}: one activation in [0, 1] per beat, got {np.asarray(levels).tolist()[:6]}")
        lv = lv[order]
        for label, value in (("hold", hold), ("attack", attack), ("release", release)):
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0.0):
                raise SceneError(f"{where}: {label} must be a duration >= 0 [s], got {value!r}")
        if hold <= 0.0:
            raise SceneError(f"{where}: hold must be positive [s], got {hold!r}")
        if attack > hold:
            raise SceneError(f"{where}: attack ({attack} s) must not exceed hold ({hold} s)")
        gaps = np.diff(b)
        if gaps.size and gaps.min() < hold + release - 1e-12:
            k = int(np.argmin(gaps))
            raise SceneError(f"{where}: the pop on the beat at {b[k]} s (hold {hold} s + release {release} s) overlaps "
                           f"the beat at {b[k + 1]} s")
        keys = []
        for t, a in zip(b.tolist(), lv.tolist()):
            keys += [(t, 0.0), (t + attack, a), (t + hold, a), (t + hold + release, 0.0)]
        return keys

    @classmethod
    def from_table(cls, table: Mapping, *, where: str = "[popping.activation]") -> ActivationTimeline:
        """From a scene's ``[popping.activation]`` table: per group either ``keys = [[t, a], ...]``
        or ``beats = [t, ...]`` with ``hold`` (and optional ``attack``, ``release``) [s]."""
        if not isinstance(table, Mapping):
            raise SceneError(f"{where} must be a table of muscle groups")
        keys = {}
        for name, spec in table.items():
            w = f"{where} {name}"
            if not isinstance(spec, Mapping):
                raise SceneError(f"{w}: must be a table with 'keys' or 'beats'")
            unknown = sorted(set(spec) - {"keys", "beats", "hold", "attack", "release"})
            if unknown:
                raise SceneError(f"{w}: unknown key(s) {unknown}; known: ['attack', 'beats', 'hold', 'keys', 'release']")
            if ("keys" in spec) == ("beats" in spec):
                raise SceneError(f"{w}: give exactly one of 'keys' or 'beats'")
            if "keys" in spec:
                if set(spec) - {"keys"}:
                    raise SceneError(f"{w}: hold, attack and release only apply to 'beats'")
                keys[name] = spec["keys"]
            else:
                if "hold" not in spec:
                    raise SceneError(f"{w}: 'beats' needs 'hold' (how long each pop stays clenched [s])")
                keys[name] = cls.beats(spec["beats"], hold=spec["hold"], attack=spec.get("attack", 0.0),
                                       release=spec.get("release", 0.0), where=w)
        return cls(keys, where=where)

    @property
    def groups(self) -> list[str]:
        return list(self.times)

    @property
    def end(self) -> float:
        """Time of the last key over all groups [s] (0 when empty)."""
        return max((float(t[-1]) for t in self.times.values()), default=0.0)

    def check_groups(self, names: Sequence[str], where: str = "activation") -> None:
        """Raise :class:`RigError` if the timeline drives a group that ``names`` lacks."""
        unknown = [g for g in self.times if g not in names]
        if unknown:
            raise SceneError(f"{where}: muscle groups {unknown} have no clenched examples; groups are {list(names)}")

    def value(self, group: str, t: float) -> float:
        """Activation of ``group`` at time ``t`` [s] (0 for a group without keys)."""
        times = self.times.get(group)
        if times is None:
            return 0.0
        vals = self.values[group]
        k = int(np.searchsorted(times, t, side="right")) - 1
        if k < 0:
            return float(vals[0])
        if k >= times.size - 1:
            return float(vals[-1])
        u = (t - times[k]) / (times[k + 1] - times[k])
        return float(vals[k] + u * (vals[k + 1] - vals[k]))

    def onsets(self, group: str) -> np.ndarray:
        """``[K]`` the times [s] at which ``group``'s activation leaves 0 upwards (each pop's
        start: a key at 0 followed by one above it), ascending; a group clenched from its first
        key starts a pop there."""
        times = self.times.get(group)
        if times is None:
            return np.zeros(0)
        v = self.values[group]
        rise = np.nonzero((v[:-1] == 0.0) & (v[1:] > 0.0))[0]
        out = times[rise]
        if v[0] > 0.0:
            out = np.concatenate([[times[0]], out])
        return np.unique(out)

    def sample(self, t: float, groups: Sequence[str]) -> np.ndarray:
        """Activations of ``groups`` at time ``t`` [s], ``[G]``."""
        return np.array([self.value(g, t) for g in groups])


# --------------------------------------------------------------------------------------------
# Beats: a tempo or a file of times
# --------------------------------------------------------------------------------------------
def beat_times(bpm: float, *, start: float, end: float, offset: float = 0.0, every: int = 1) -> np.ndarray:
    """The times [s] of every ``every``-th beat at ``bpm`` beats per minute, the first at
    ``offset`` [s] (clip time), that fall in ``[start, end]``: ``offset + k * every * 60 / bpm``
    for ``k = 0, 1, ...``."""
    if isinstance(bpm, bool) or not isinstance(bpm, (int, float)) or not (math.isfinite(bpm) and 0.0 < bpm <= 2000.0):
        raise SceneError(f"--bpm must be a tempo in (0, 2000] beats per minute, got {bpm!r}")
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise SceneError(f"--every must be a whole number of beats >= 1, got {every!r}")
    if not (isinstance(offset, (int, float)) and math.isfinite(offset)):
        raise SceneError(f"--offset must be a time [s], got {offset!r}")
    period = every * 60.0 / bpm
    k0 = max(0, math.ceil((start - offset) / period - 1e-9))
    k1 = math.floor((end - offset) / period + 1e-9)
    return offset + period * np.arange(k0, max(k0, k1 + 1), dtype=np.float64)


@dataclass
class Beat:
    """One pop: at ``time`` [s] (clip time), of ``group`` (``None``: the groups that pop on
    every beat, together or in turn), clenched to ``activation`` in [0, 1]."""

    time: float
    group: str | None = None
    activation: float = 1.0


def read_beats(path) -> list[Beat]:
    """Beats from a text file: one per line, ``time`` (seconds) or ``time,group[,activation]``
    (CSV); blank lines and ``#`` comments are skipped, and so is a first line of column names
    (``time,group,activation``).

    Raises:
        SceneError: an unreadable file or a bad line, naming the file and the line number.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{p}: cannot read the beats: {exc}") from None
    out: list[Beat] = []
    for n, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        cells = [c.strip() for c in body.split(",")]
        if n == 1 and cells[0].lower() in ("time", "t", "seconds", "time_s"):
            continue  # a header
        try:
            t = float(cells[0])
        except ValueError:
            t = float("nan")
        if not math.isfinite(t):
            raise SceneError(f"{p}: line {n}: the first column must be a time in seconds, got {cells[0]!r}")
        if len(cells) > 3:
            raise SceneError(f"{p}: line {n}: expected time[,group[,activation]], got {len(cells)} columns")
        group = cells[1] if len(cells) > 1 and cells[1] else None
        a = 1.0
        if len(cells) > 2:
            try:
                a = float(cells[2])
            except ValueError:
                a = float("nan")
            if not 0.0 <= a <= 1.0:
                raise SceneError(f"{p}: line {n}: the activation must be in [0, 1], got {cells[2]!r}")
        out.append(Beat(t, group, a))
    if not out:
        raise SceneError(f"{p}: no beats (one time in seconds a line, or time,group[,activation])")
    return out


@dataclass
class BeatSpec:
    """Pops on a beat, from the command line (``warpskin pop --bpm/--beats``): a tempo
    (``bpm``, ``offset`` [s], ``every``) or a list of :class:`Beat`, and how each pop is shaped
    (``hold``, ``attack``, ``release`` [s]; ``hold`` ``None``: half the shortest time between
    two pops of one group, at most 0.25 s). ``groups`` picks the groups that pop and their
    order (``None``: every group); ``in_turn`` gives each beat without a group to the next
    group in that order instead of to all of them."""

    bpm: float | None = None
    offset: float = 0.0
    every: int = 1
    beats: list[Beat] | None = None
    hold: float | None = None
    attack: float = 0.0
    release: float = 0.0
    groups: list[str] | None = None
    in_turn: bool = False

    def __post_init__(self) -> None:
        if (self.bpm is None) == (self.beats is None):
            raise SceneError("give exactly one of --bpm or --beats")

    def timeline(self, names: Sequence[str], start: float, end: float, where: str = "beats") -> ActivationTimeline:
        """The activation over clip time ``[start, end]`` [s] of the groups ``names`` (those the
        examples or the rig define).

        Raises:
            SceneError: a group that does not exist, no beat in the range, overlapping pops.
        """
        names = list(names)
        order = list(names) if self.groups is None else list(self.groups)
        unknown = [g for g in order if g not in names]
        if unknown:
            raise SceneError(f"{where}: unknown muscle group(s) {unknown}; groups are {names}")
        if not order:
            raise SceneError(f"{where}: no muscle group to pop")
        if self.bpm is not None:
            beats = [Beat(float(t)) for t in beat_times(self.bpm, start=start, end=end, offset=self.offset,
                                                        every=self.every)]
        else:
            beats = sorted(self.beats, key=lambda b: b.time)
            unknown = sorted({b.group for b in beats if b.group is not None and b.group not in names})
            if unknown:
                raise SceneError(f"{where}: unknown muscle group(s) {unknown}; groups are {names}")
        if not beats:
            raise SceneError(f"{where}: no beat between {start:g} s and {end:g} s (clip time)")
        per: dict[str, list[Beat]] = {g: [] for g in order}
        turn = 0
        for b in beats:
            if b.group is not None:
                per.setdefault(b.group, []).append(b)
            elif self.in_turn:
                per[order[turn % len(order)]].append(b)
                turn += 1
            else:
                for g in order:
                    per[g].append(b)
        gaps = [np.diff([b.time for b in bs]) for bs in per.values() if len(bs) > 1]
        shortest = min((float(g.min()) for g in gaps), default=float("inf"))
        hold = self.hold if self.hold is not None else min(0.25, 0.5 * shortest)
        keys = {g: ActivationTimeline.beats([b.time for b in bs], hold=hold, attack=self.attack, release=self.release,
                                            levels=[b.activation for b in bs], where=f"{where}: group {g!r}")
                for g, bs in per.items() if bs}
        return ActivationTimeline(keys, where=where)


def clench_table(activation: np.ndarray) -> np.ndarray:
    """``[S, G]`` 1 while each group clenches, 0 while it relaxes, from its activations over
    the steps ``[S, G]``: rising starts a clench, falling a relaxation, otherwise it goes on
    (from relaxed before the first step)."""
    a = np.asarray(activation, dtype=np.float64)
    out = np.zeros_like(a)
    prev = np.zeros(a.shape[1])
    state = np.zeros(a.shape[1])
    for s in range(a.shape[0]):
        state = np.where(a[s] > prev, 1.0, np.where(a[s] < prev, 0.0, state))
        out[s] = state
        prev = a[s]
    return out


def vibrating(sample: Callable[[float], np.ndarray], start: float, end: float, *, h: float, alpha: float,
              beta: float, threshold: float = 1e-6) -> Callable[[float], np.ndarray]:
    """The paper's skin response (Son & Han, eqs. 1, 2 and 4) applied to each group's activation,
    for the layered mode's rest-shape drive: ``sample(t) -> [G]`` the activations in [0, 1];
    returns ``f(t) -> [G]``, the responding activation at clip time ``t`` in ``[start, end]``
    [s] (linear between steps of ``h`` [s] from ``start``).

    Per group, with ``a*`` the activation and ``a`` the response: while clenching (``a*`` rose
    last) ``u <- (1 - alpha) u + alpha (a* - a) / h, a <- a + h u`` (it overshoots and rings
    about ``a*``, its amplitude shrinking by ``sqrt(1 - alpha)`` a step); while relaxing (``a*``
    fell last) ``a <- a + beta h (a* - a), u <- 0``, monotone, snapping to ``a*`` within
    ``threshold``. ``alpha`` 1: ``a = a*`` (no vibration)."""
    if not (0.0 < alpha <= 1.0 and h > 0.0 and 0.0 < beta * h <= 1.0 + 1e-12):
        raise SceneError(f"vibration: need 0 < alpha <= 1 and 0 < beta * h <= 1, got alpha {alpha}, beta {beta}, h {h}")
    count = max(2, int(math.ceil((end - start) / h - 1e-9)) + 1)
    times = start + h * np.arange(count)
    goal = np.array([np.asarray(sample(float(t)), dtype=np.float64).ravel() for t in times])  # [n, G]
    a = np.zeros(goal.shape[1])
    u = np.zeros_like(a)
    clenching = clench_table(goal) > 0.0
    out = np.empty_like(goal)
    for k in range(count):
        g = goal[k]
        c, r = clenching[k], ~clenching[k]
        u[c] = (1.0 - alpha) * u[c] + alpha * (g[c] - a[c]) / h
        a[c] += h * u[c]
        a[r] += beta * h * (g[r] - a[r])
        u[r] = 0.0
        snap = r & (np.abs(g - a) < threshold)
        a[snap] = g[snap]
        out[k] = a
    return lambda t: np.array([np.interp(t, times, out[:, j]) for j in range(out.shape[1])])


# --------------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------------
def popping_settings(scene) -> PoppingSettings:
    """A scene's ``[popping]`` section, parsed: :meth:`warpskin.scene.Scene.popping_settings`.

    Raises:
        SceneError: a value of the wrong kind or range, naming the file and key.
    """
    return scene.popping_settings()

"""Settings declared once: each parameter class's fields carry their type, range, unit and one line
of help (dataclass field metadata), and the checks, their messages, a scene section's key list and
type checks, and the docs' scene-file reference are all made from that declaration.

Why dataclass metadata and not a validation library such as pydantic: the parameter classes are
plain dataclasses the solver and the kernels' hosts read every step, the messages must stay the
project's one-line form (the file, the key, the value, what is allowed), and the declaration needs
no dependency.

Use::

    @dataclass
    class CollisionParams:
        friction: float = setting(0.3, "number", "Coulomb friction coefficient", low=0.0, must=">= 0")

    check_settings(params, where)              # every declared field in its range, else SceneError
    params = from_section(CollisionParams, table, where, "collision")   # a scene's [collision]
    reference_markdown(CollisionParams, "collision")                    # the docs' table
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from .errors import SceneError

__all__ = ["Setting", "setting", "settings_of", "check_settings", "from_section", "reference_markdown"]

_KINDS = ("bool", "number", "integer")


@dataclass(frozen=True)
class Setting:
    """One declared setting.

    Attributes:
        name: The field's name, which is also its scene key.
        kind: ``"bool"``, ``"number"`` (a finite float; an int is taken) or ``"integer"`` (an
            int, not a float of integer value).
        default: Its default (``None`` where ``optional``).
        help: One line: what it does.
        unit: Its unit (``"m"``, ``"1/s"``, ...; empty for a plain number).
        low, high: Its range's bounds (``None``: unbounded); ``open_low``/``open_high`` exclude them.
        optional: ``None`` is allowed (and means the documented automatic value).
        must: What the range is, in words, for the message ``"<name> must be <must>, got <value>"``.
    """

    name: str
    kind: str
    default: object
    help: str
    unit: str = ""
    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False
    optional: bool = False
    must: str = ""

    def allows(self, value) -> bool:
        """Whether ``value`` is of this setting's kind and in its range."""
        if value is None:
            return self.optional
        if self.kind == "bool":
            return isinstance(value, bool)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.kind == "integer" and not isinstance(value, int):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return False
        if self.high is not None and (value >= self.high if self.open_high else value > self.high):
            return False
        return True

    def range_text(self) -> str:
        """The range in words (``must``, else made from the bounds)."""
        if self.must:
            return self.must
        if self.kind == "bool":
            return "true or false"
        lo = "" if self.low is None else f"{'>' if self.open_low else '>='} {self.low:g}"
        hi = "" if self.high is None else f"{'<' if self.open_high else '<='} {self.high:g}"
        what = "an integer" if self.kind == "integer" else "a number"
        return " and ".join(x for x in (f"{what} {lo}".strip(), hi) if x)


def setting(default, kind: str, help: str, **options) -> dataclasses.Field:
    """A dataclass field declaring a setting (:class:`Setting`'s attributes as keywords)."""
    if kind not in _KINDS:
        raise ValueError(f"unknown setting kind {kind!r}; known: {_KINDS}")
    return dataclasses.field(default=default, metadata={"setting": {"kind": kind, "help": help, **options}})


def settings_of(cls) -> list[Setting]:
    """The declared settings of a dataclass ``cls`` (instance or class), in field order."""
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get("setting")
        if meta is not None:
            out.append(Setting(name=f.name, default=f.default, **meta))
    return out


def check_settings(obj, where: str, section: str | None = None) -> None:
    """Every declared setting of ``obj`` allowed (:meth:`Setting.allows`).

    Raises:
        SceneError: ``"<where>: [<section>] <name> must be <range>, got <value>"`` (without
            the section where none is given) for the first that is not.
    """
    prefix = f"{where}: [{section}] " if section else f"{where}: "
    for s in settings_of(obj):
        value = getattr(obj, s.name)
        if not s.allows(value):
            raise SceneError(f"{prefix}{s.name} must be {s.range_text()}, got {value!r}")


def from_section(cls, table: dict, where: str, section: str):
    """An instance of ``cls`` from a scene's ``[section]`` table: unknown keys, values of the
    wrong type (``"[section] key must be a number"``, ``"... true or false"``, ``"... an
    integer"``) and values out of range are :class:`~warpskin.errors.SceneError` s naming the
    file, the key and the value."""
    declared = {s.name: s for s in settings_of(cls)}
    unknown = sorted(set(table) - set(declared))
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown} in [{section}]; known: {sorted(declared)}")
    for key, value in table.items():
        s = declared[key]
        if value is None and s.optional:
            continue
        if s.kind == "bool" and not isinstance(value, bool):
            raise SceneError(f"{where}: [{section}] {key} must be true or false")
        if s.kind != "bool" and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise SceneError(f"{where}: [{section}] {key} must be a number, got {value!r}")
    obj = cls(**table)
    check_settings(obj, where, section)
    return obj


def reference_markdown(cls, section: str) -> str:
    """The docs' reference of a scene section: one row per declared setting (key, kind, default,
    range, unit, help)."""
    rows = [f"### `[{section}]`", "", "| key | kind | default | allowed | unit | what it does |", "|---|---|---|---|---|---|"]
    for s in settings_of(cls):
        default = "automatic" if s.default is None else (str(s.default).lower() if s.kind == "bool" else f"{s.default!r}")
        rows.append(f"| `{s.name}` | {s.kind} | {default} | {s.range_text()} | {s.unit or '-'} | {s.help} |")
    return "\n".join(rows) + "\n"

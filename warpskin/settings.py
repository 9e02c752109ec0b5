"""Settings declared once: each setting is a dataclass field carrying its kind, default, range, unit,
one line of help, the scene section and key it is read from and the command-line option that sets
it (dataclass field metadata). The checks and their messages, a scene section's key list and type
checks, the command-line options (:func:`add_option`: type, choices, help) and the docs' references
are all made from that declaration.

Why dataclass metadata and not a validation library such as pydantic: the parameter classes are
plain dataclasses the solver and the kernels' hosts read every step, the messages must stay the
project's one-line form (the file, the key, the value, what is allowed), and the declaration needs
no dependency.

Use::

    @dataclass
    class CollisionParams:
        _section = "collision"       # the scene section of its settings (a field may name another)
        friction: float = setting(0.3, "number", "Coulomb friction coefficient", low=0.0, must=">= 0")

    check_settings(params, where)              # every declared field in its range, else SceneError
    values = read_section(settings_of(CollisionParams), table, where, "collision")   # a scene's [collision]
    add_option(parser, SolverParams, "iterations")        # --iterations, from SolverParams.iterations
    reference_markdown(settings_of(CollisionParams), "collision")                    # the docs' table

Kinds: ``bool``; ``number`` (a finite float; an int is taken); ``integer`` (an int, not a float of
integer value); ``string`` (with ``choices``: one of them); ``numbers`` and ``integers`` (a list of
``length`` of them, each in the range); ``strings`` (a list of strings); ``table`` (a TOML table whose
contents the reader checks: its help says what it holds).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Callable

from .errors import SceneError

__all__ = ["Setting", "setting", "settings_of", "setting_named", "check_settings", "check_value", "read_section",
           "from_section", "add_option", "reference_markdown"]

_KINDS = ("bool", "number", "integer", "string", "numbers", "integers", "strings", "table")


@dataclass(frozen=True)
class Setting:
    """One declared setting.

    Attributes:
        name: The field's name.
        kind: One of the kinds of the module docstring.
        default: Its default (``None`` where ``optional``).
        help: One line: what it does.
        unit: Its unit (``"m"``, ``"1/s"``, ...; empty for a plain number).
        low, high: Its range's bounds (``None``: unbounded; per element for a list kind);
            ``open_low``/``open_high`` exclude them.
        optional: ``None`` is allowed (and means the documented automatic value).
        must: What the range is, in words, for the message ``"<name> must be <must>, got <value>"``.
        choices: The strings a ``string`` setting may be (empty: any).
        length: How many elements a list kind holds (0: any).
        valid: A further test of a value of the right kind and range (e.g. ``first <= last``),
            stated in ``must``.
        section: The scene section it is read from (empty: not a scene key; a command-line option).
        key: Its key in that section (default: ``name``).
        cli: Its command-line option strings (``("-o", "--output")``; a positional's name); empty:
            not on the command line.
        cli_help: The option's help where it differs from ``help`` (a ``--no-...`` switch).
        metavar: The option's metavar.
        parse: Reads the option's text (raising :class:`argparse.ArgumentTypeError` in one line);
            default: made from the kind and range.
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
    choices: tuple = ()
    length: int = 0
    valid: Callable | None = None
    section: str = ""
    key: str = ""
    cli: tuple = ()
    cli_help: str = ""
    metavar: str = ""
    parse: Callable | None = None

    @property
    def scene_key(self) -> str:
        """Its key in its scene section."""
        return self.key or self.name

    def _in_range(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            return False
        if self.kind in ("integer", "integers") and not isinstance(value, numbers.Integral):
            return False
        try:
            if not math.isfinite(value):
                return False
        except OverflowError:  # an int too large for a float
            return False
        if self.low is not None and (value <= self.low if self.open_low else value < self.low):
            return False
        if self.high is not None and (value >= self.high if self.open_high else value > self.high):
            return False
        return True

    def allows(self, value) -> bool:
        """Whether ``value`` is of this setting's kind (:meth:`type_ok`) and in its range."""
        if value is None:
            return self.optional
        if not self.type_ok(value):
            return False
        if self.kind in ("number", "integer"):
            ok = self._in_range(value)
        elif self.kind in ("numbers", "integers"):
            ok = all(self._in_range(x) for x in value)
        elif self.kind in ("string", "strings") and self.choices:
            ok = all(x in self.choices for x in ([value] if self.kind == "string" else value))
        else:
            ok = True
        return ok and (self.valid is None or bool(self.valid(value)))

    def kind_text(self) -> str:
        """The kind in words (``"a number"``, ``"a list of 3 numbers"``, ...)."""
        n = f"{self.length} " if self.length else ""
        return {"bool": "true or false", "number": "a number", "integer": "an integer", "string": "a string",
                "numbers": f"a list of {n}numbers", "integers": f"a list of {n}integers",
                "strings": "a list of strings", "table": "a table"}[self.kind]

    def range_text(self, unit: bool = True) -> str:
        """The range in words (``must``, else made from the kind, the bounds and the choices),
        with the unit where the words do not already give one (``unit=False``: without)."""
        text = self._range_words()
        if unit and self.unit and "[" not in text and "second" not in text:
            text += f" [{self.unit}]"
        return text

    def _range_words(self) -> str:
        if self.must:
            return self.must
        if self.choices:
            names = [repr(c) for c in self.choices]
            if self.kind == "strings":
                return "a list of " + ", ".join(names)
            return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " or " + names[-1]
        if self.kind not in ("number", "integer", "numbers", "integers"):
            return self.kind_text()
        lo = "" if self.low is None else f"{'>' if self.open_low else '>='} {self.low:g}"
        hi = "" if self.high is None else f"{'<' if self.open_high else '<='} {self.high:g}"
        what = self.kind_text()
        if self.kind in ("numbers", "integers") and (lo or hi):
            what += " each"
        return " and ".join(x for x in (f"{what} {lo}".strip(), hi) if x)

    def type_ok(self, value) -> bool:
        """Whether ``value`` is of this setting's kind (range aside)."""
        if value is None:
            return self.optional
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind in ("number", "integer"):
            return not isinstance(value, bool) and isinstance(value, numbers.Real)
        if self.kind == "string":
            return isinstance(value, str)
        if self.kind == "table":
            return isinstance(value, dict)
        if not _is_list(value) or (self.length and len(value) != self.length):
            return False
        if self.kind == "strings":
            return all(isinstance(x, str) for x in value)
        return all(not isinstance(x, bool) and isinstance(x, numbers.Real) for x in value)


def _is_list(value) -> bool:
    """A list, a tuple or a one-dimensional array (anything sized and iterable but a string or
    a mapping)."""
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__") or not hasattr(value, "__iter__"):
        return False
    return getattr(value, "ndim", 1) == 1


def setting(default, kind: str, help: str, **options) -> dataclasses.Field:
    """A dataclass field declaring a setting (:class:`Setting`'s attributes as keywords; a list or
    dict default is copied for each instance; ``cli`` may be one string)."""
    if kind not in _KINDS:
        raise ValueError(f"unknown setting kind {kind!r}; known: {_KINDS}")
    if isinstance(options.get("cli"), str):
        options["cli"] = (options["cli"],)
    if "choices" in options:
        options["choices"] = tuple(options["choices"])
    meta = {"setting": {"kind": kind, "help": help, **options}}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=meta)
    if callable(default) and kind == "table":  # a factory (a table read into an object)
        return dataclasses.field(default_factory=default, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def settings_of(cls, section: str | None = None) -> list[Setting]:
    """The declared settings of a dataclass ``cls`` (instance or class), in field order; with
    ``section``, those of that scene section only. A setting's section is its field's own, else
    the class's ``_section``."""
    out = []
    for f in dataclasses.fields(cls):
        meta = f.metadata.get("setting")
        if meta is None:
            continue
        meta = dict(meta)
        meta.setdefault("section", getattr(cls, "_section", ""))
        if section is not None and meta["section"] != section:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif meta["kind"] == "table":  # an empty table (its factory may build an object, lazily)
            default = {}
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None
        out.append(Setting(name=f.name, default=default, **meta))
    return out


def setting_named(cls, name: str) -> Setting:
    """The declared setting ``name`` of ``cls``."""
    for s in settings_of(cls):
        if s.name == name:
            return s
    raise KeyError(f"{cls.__name__} declares no setting {name!r}")


def _value_text(value) -> str:
    """A value as the user wrote it: a list for a tuple or an array, a plain number for a
    NumPy scalar."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool) and type(value).__module__ == "numpy":
        value = value.item()
    if not isinstance(value, (str, bytes, dict, list)) and _is_list(value):
        value = [x.item() if type(x).__module__ == "numpy" else x for x in value]
    return repr(value)


def check_value(s: Setting, value, prefix: str) -> None:
    """``value`` of the right kind and range for ``s``, else a :class:`SceneError`
    ``"<prefix><key> must be <kind or range>, got <value>"``."""
    key = s.scene_key if s.section else s.name
    if not s.type_ok(value):
        raise SceneError(f"{prefix}{key} must be {s.kind_text()}, got {_value_text(value)}")
    if not s.allows(value):
        raise SceneError(f"{prefix}{key} must be {s.range_text()}, got {_value_text(value)}")


def check_settings(obj, where: str, section: str | None = None) -> None:
    """Every declared setting of ``obj`` allowed (:meth:`Setting.allows`).

    With ``section``, the settings of that scene section only.

    Raises:
        SceneError: ``"<where>: [<section>] <key> must be <range>, got <value>"`` (without
            the section where none is given) for the first that is not.
    """
    prefix = f"{where}: [{section}] " if section else f"{where}: "
    for s in settings_of(obj, section):
        value = getattr(obj, s.name)
        if s.kind != "table" and not s.allows(value):  # a table is read (and checked) into an object
            raise SceneError(f"{prefix}{s.scene_key} must be {s.range_text()}, got {_value_text(value)}")


def read_section(settings: list[Setting], table: dict, where: str, section: str) -> dict:
    """A scene's ``[section]`` table checked against its declared ``settings``: unknown keys,
    values of the wrong kind and values out of range are :class:`~warpskin.errors.SceneError` s
    naming the file, the key and the value. Returns ``{field name: value}`` of the keys given,
    a ``number`` as a float (a table's contents are its reader's to check)."""
    declared = {s.scene_key: s for s in settings}
    if not isinstance(table, dict):
        raise SceneError(f"{where}: {section} must be a table")
    unknown = sorted(set(table) - set(declared))
    if unknown:
        raise SceneError(f"{where}: unknown key(s) {unknown} in [{section}]; known: {sorted(declared)}")
    out = {}
    for key, value in table.items():
        s = declared[key]
        check_value(s, value, f"{where}: [{section}] ")
        out[s.name] = float(value) if s.kind == "number" and value is not None else value
    return out


def from_section(cls, table: dict, where: str, section: str):
    """An instance of ``cls`` from a scene's ``[section]`` table (:func:`read_section` over
    ``cls``'s settings of that section), then :func:`check_settings`."""
    obj = cls(**read_section(settings_of(cls, section), table, where, section))
    check_settings(obj, where, section)
    return obj


# ---------------------------------------------------------------------------- command line
def _cli_type(s: Setting, flag: str):
    """An argparse type for a number or integer setting: its kind and range, else one line
    ``"<flag> must be <range>, got '<text>'"`` (the unit is in the option's help)."""

    def parse(text: str):
        try:
            value = int(text) if s.kind == "integer" else float(text)
        except ValueError:
            value = None
        if value is None or not s.allows(value):
            raise argparse.ArgumentTypeError(f"{flag} must be {s.range_text(unit=False)}, got {text!r}")
        return value

    return parse


def cli_help(s: Setting) -> str:
    """The option's help: its ``cli_help``, or its ``help`` and unit; and the scene key it stands for."""
    text = s.cli_help or s.help
    if s.unit and not s.cli_help and "[" not in text:
        text += f" [{s.unit}]"
    if s.section:
        text += f" (scene: [{s.section}] {s.scene_key})"
    return text


def add_option(parser, cls, name: str, **overrides):
    """Add the command-line option of ``cls``'s declared setting ``name`` to ``parser`` (an
    :class:`argparse.ArgumentParser` or group): its option strings, type (:attr:`Setting.parse`,
    else made from the kind and range), choices, metavar and help from the declaration; a
    ``bool`` is a switch. A scene setting's option defaults to ``None`` (the scene's value
    stands); a command's own option to its declared default. ``overrides`` are argparse's
    (``required``, ``nargs``, ``action``, ``default``). The action keeps its setting as
    ``action.setting``."""
    s = setting_named(cls, name)
    if not s.cli:
        raise KeyError(f"{cls.__name__}.{name} has no command-line option")
    positional = not s.cli[0].startswith("-")
    if s.kind in ("numbers", "integers", "strings", "table") and s.parse is None and not positional:
        raise TypeError(f"{cls.__name__}.{name}: a {s.kind} option needs a parse function in its declaration")
    kw: dict = {"help": cli_help(s)}
    if s.kind == "bool":
        kw["action"] = "store_true"
    else:
        if s.parse is not None:
            kw["type"] = s.parse
        elif s.kind in ("number", "integer"):
            kw["type"] = _cli_type(s, s.cli[-1])
        if s.choices:
            kw["choices"] = list(s.choices)
        if s.metavar:
            kw["metavar"] = s.metavar
        if not positional:
            kw["default"] = None if s.section else s.default
    kw.update(overrides)
    action = parser.add_argument(*s.cli, **kw)
    action.setting = s
    return action


# ---------------------------------------------------------------------------- docs
def _default_text(s: Setting) -> str:
    if s.default is None:
        return "automatic"
    if s.kind == "bool":
        return str(s.default).lower()
    if s.kind == "table":
        return "empty" if not s.default or not isinstance(s.default, dict) else repr(s.default)
    if isinstance(s.default, tuple):
        return repr(list(s.default))
    return repr(s.default)


def reference_markdown(settings: list[Setting], section: str) -> str:
    """The docs' reference of a scene section: one row per declared setting (key, kind, default,
    range, unit, help, command-line option)."""
    rows = [f"### `[{section}]`", "", "| key | kind | default | allowed | unit | what it does | option |",
            "|---|---|---|---|---|---|---|"]
    for s in settings:
        option = ", ".join(f"`{c}`" for c in s.cli) or "-"
        allowed, text = (x.replace("|", "\\|") for x in (s.range_text(unit=False), s.help))
        rows.append(f"| `{s.scene_key}` | {s.kind} | {_default_text(s)} | {allowed} | {s.unit or '-'} | {text} | {option} |")
    return "\n".join(rows) + "\n"

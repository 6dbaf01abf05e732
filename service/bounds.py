"""Every setting declared once: its type and a physically sensible range.

A setting is a dataclass field made with `setting(...)`; `check_fields` (called from the
dataclass's `__post_init__`) checks and normalizes every such field, so a TOML file, a
command-line option and a run-time `configure` all pass through the same test. Types are
strict: `"false"` is not a bool, `1.5` is not an int, `true` is not a number, and a
number must be finite and inside its range. Errors are `ConfigError`s that name the
setting, what it takes and what it got.
"""

from __future__ import annotations

import dataclasses
import difflib
import inspect
import math
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from service.errors import ConfigError

UNITS = {"m": "metres", "s": "seconds", "Hz": "Hz", "rad": "radians", "": ""}
MAX_TEXT = 4096
"""Longest string any setting takes (a path, a map spec, an endpoint)."""
MAX_ITEMS = 64
"""Most strings a list setting takes."""


@dataclass(frozen=True)
class Bound:
    """What one setting accepts."""

    kind: str
    """'int', 'float', 'bool', 'str', 'strs' (a list of strings, kept as a tuple), 'vec3'
    (three finite floats) or 'options' (a table of keyword options: identifiers to numbers,
    bools or strings)."""
    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    choices: tuple[str, ...] | Callable[[], list[str]] = ()
    """Allowed strings (or a function listing them, for registries loaded lazily)."""
    optional: bool = False
    """None is allowed (and means 'not set')."""

    def describe(self) -> str:
        unit = UNITS.get(self.unit, self.unit)
        what = {"int": "an integer", "float": "a number", "bool": "true or false",
                "str": "a string", "strs": f"a list of at most {MAX_ITEMS} strings",
                "vec3": "three numbers",
                "options": "a table of names to numbers, true/false or strings (at most 64)"
                }[self.kind]
        if self.kind in ("int", "float", "vec3") and self.lo is not None:
            number = "{:d}" if self.kind == "int" else "{:g}"
            what += f" in [{number.format(self.lo)}, {number.format(self.hi)}]"
        if unit:
            what += f" ({unit})"
        choices = self._choices()
        if choices:
            what = "one of " + ", ".join(choices)
        return what + (" or nothing" if self.optional else "")

    def _choices(self) -> list[str]:
        return list(self.choices()) if callable(self.choices) else list(self.choices)

    def check(self, name: str, value: Any) -> Any:
        """`value` normalized (an int where a float is wanted becomes a float), or ConfigError."""
        if value is None and self.optional:
            return None
        ok, normal = _CHECKS[self.kind](self, value)
        if ok and self.kind == "str":
            choices = self._choices()
            ok = not choices or normal in choices
        if not ok:
            raise ConfigError(f"{name} must be {self.describe()}, got {_show(value)}"
                              f"{self._millimetres_hint(value)}")
        return normal

    def _millimetres_hint(self, value: Any) -> str:
        """A length given in millimetres by mistake: what it is in metres, when that fits."""
        if self.unit != "m" or self.kind != "float" or not _is_number(value) or value < 1:
            return ""
        metres = float(value) / 1000
        return (f"; lengths are metres: for {value:g} mm give {metres:g}"
                if _in_range(self, metres) else "")


def _in_range(bound: Bound, x: float) -> bool:
    return math.isfinite(x) and (bound.lo is None or bound.lo <= x) and (
        bound.hi is None or x <= bound.hi)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _int(bound: Bound, value: Any) -> tuple[bool, Any]:
    ok = isinstance(value, int) and not isinstance(value, bool) and _in_range(bound, value)
    return ok, value


def _float(bound: Bound, value: Any) -> tuple[bool, Any]:
    if not _is_number(value):
        return False, value
    try:
        x = float(value)
    except OverflowError:  # an int beyond float's range
        return False, value
    return _in_range(bound, x), x


def _bool(bound: Bound, value: Any) -> tuple[bool, Any]:
    return isinstance(value, bool), value


def _str(bound: Bound, value: Any) -> tuple[bool, Any]:
    return isinstance(value, str) and len(value) <= MAX_TEXT and "\0" not in value, value


def _strs(bound: Bound, value: Any) -> tuple[bool, Any]:
    if not isinstance(value, (list, tuple)) or len(value) > MAX_ITEMS:
        return False, value
    return all(_str(bound, v)[0] for v in value), tuple(value)


def _vec3(bound: Bound, value: Any) -> tuple[bool, Any]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        return False, value
    parts = [_float(bound, v) for v in value]
    return all(ok for ok, _ in parts), tuple(v for _, v in parts)


def _options(bound: Bound, value: Any) -> tuple[bool, Any]:
    if not isinstance(value, dict) or len(value) > 64:
        return False, value
    for key, v in value.items():
        if not (isinstance(key, str) and key.isidentifier()):
            return False, value
        if not (isinstance(v, (bool, str)) or (_is_number(v) and _float(Bound("float"), v)[0])):
            return False, value
    return True, dict(value)


_CHECKS: dict[str, Callable[[Bound, Any], tuple[bool, Any]]] = {
    "int": _int, "float": _float, "bool": _bool, "str": _str, "strs": _strs, "vec3": _vec3,
    "options": _options}


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def setting(default: Any, kind: str, *, lo: float | None = None, hi: float | None = None,
            unit: str = "", choices: tuple[str, ...] | Callable[[], list[str]] = (),
            optional: bool = False) -> Any:
    """A dataclass field with its bound (mutable defaults are copied per instance)."""
    bound = Bound(kind, lo, hi, unit, choices, optional)
    meta = {"bound": bound}
    if isinstance(default, (dict, list)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def same_as(cls: type, name: str) -> Any:
    """A field declared like `cls.name` (same default, same bound): declared once, used twice."""
    source = next(f for f in dataclasses.fields(cls) if f.name == name)
    bound: Bound = source.metadata["bound"]
    default = (source.default_factory() if source.default is dataclasses.MISSING
               else source.default)
    return setting(default, bound.kind, lo=bound.lo, hi=bound.hi, unit=bound.unit,
                   choices=bound.choices, optional=bound.optional)


def bound_of(cls: type, name: str) -> Bound:
    return next(f for f in dataclasses.fields(cls) if f.name == name).metadata["bound"]


def check_fields(obj: Any, prefix: str = "", *, flags: bool = False) -> None:
    """Check and normalize every `setting` field of a (frozen) dataclass instance; errors
    name a field `prefix + name`, or as its command-line flag (`--max-steps`) with `flags`."""
    for f in dataclasses.fields(obj):
        bound = f.metadata.get("bound")
        if bound is not None:
            name = "--" + f.name.replace("_", "-") if flags else prefix + f.name
            value = bound.check(name, getattr(obj, f.name))
            object.__setattr__(obj, f.name, value)


def keyword_params(target: Callable[..., Any]) -> dict[str, tuple[Any, Any]]:
    """`target`'s keyword-only parameters (a class: those of its `__init__` and, through
    `**options`, its bases'), each as (type hint, default)."""
    params: dict[str, tuple[Any, Any]] = {}
    inits = [c.__init__ for c in inspect.getmro(target)] if inspect.isclass(target) \
        else [target]
    for init in inits:
        try:
            signature = inspect.signature(init)
        except (TypeError, ValueError):
            break
        try:
            hints = typing.get_type_hints(init, include_extras=True)
        except Exception:  # annotations we cannot resolve: names are still checked
            hints = {}
        for name, p in signature.parameters.items():
            if p.kind is inspect.Parameter.KEYWORD_ONLY:
                params.setdefault(name, (hints.get(name), p.default))
        if not any(p.kind is inspect.Parameter.VAR_KEYWORD
                   for p in signature.parameters.values()):
            break
    return params


def settable(hint: Any) -> bool:
    """Whether a configuration can give a parameter of this type hint (a plain scalar)."""
    return _kinds(_unwrapped(hint)[0]) is not None


def check_keywords(target: Callable[..., Any], options: dict[str, Any], what: str) -> None:
    """Check keyword `options` against `target`'s keyword-only parameters
    (`keyword_params`): known names, values of the type each parameter's annotation names
    (int, float, bool, str or None), and inside the `Bound` an `Annotated` one carries
    (`Count`, ...): checked here, when a client sets them, not when an episode starts with
    them and faults (`initial = -1` latched a fault, torque off, at every later start)."""
    params = keyword_params(target)
    for name, value in options.items():
        if name not in params:
            known = [n for n, (h, _) in params.items() if settable(h)]
            close = difflib.get_close_matches(name, known, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise ConfigError(f"{what} has no option '{name}'; {hint}its options: "
                              f"{', '.join(known) or 'none'}")
        hint, bounds = _unwrapped(params[name][0])
        kinds = _kinds(hint)
        if kinds is None:
            raise ConfigError(f"{what} option '{name}' cannot be set from a configuration")
        if not any(_matches(kind, value) for kind in kinds):
            raise ConfigError(f"{what} option '{name}' must be "
                              f"{' or '.join(sorted(kinds))}, got {_show(value)}")
        for bound in bounds:
            bound.check(f"{what} option '{name}'", value)


def _unwrapped(hint: Any) -> tuple[Any, list[Bound]]:
    """A type hint without its `Annotated` wrapper, and the `Bound`s that wrapper carried."""
    if typing.get_origin(hint) is typing.Annotated:
        hint, *extras = typing.get_args(hint)
        return hint, [b for b in extras if isinstance(b, Bound)]
    return hint, []


def _kinds(hint: Any) -> set[str] | None:
    """The plain kinds a type hint admits ({'int'}, {'float', 'none'}, ...), or None."""
    args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, _UnionType) \
        else (hint,)
    names = {int: "int", float: "float", bool: "bool", str: "str", type(None): "none"}
    kinds = {names[a] for a in args if a in names}
    return kinds if kinds and len(kinds) == len(args) else None


_UnionType = type(int | None)

Count = typing.Annotated[int, Bound("int", lo=1, hi=1_000_000)]
"""A localizer option that counts what it holds or tries: at least one, at most a million
(a pool of a billion poses is a MemoryError at the first update, under a fault)."""
Headings = typing.Annotated[int, Bound("int", lo=1, hi=720)]
"""Headings a table or grid holds per position (half a degree apart at most)."""
Pitch = typing.Annotated[float | None, Bound("float", lo=1e-5, hi=1.0, unit="m",
                                             optional=True)]
"""A cell's width, or None for the localizer's own choice."""
Share = typing.Annotated[float, Bound("float", lo=0.0, hi=1.0)]
Contraction = typing.Annotated[float, Bound("float", lo=0.01, hi=1.0)]
Gate = typing.Annotated[float, Bound("float", lo=0.1, hi=1000.0)]
"""A threshold in sigmas or nats."""


def _matches(kind: str, value: Any) -> bool:
    if kind == "none":
        return value is None
    if kind == "float":
        return _float(Bound("float"), value)[0]
    if kind == "int":
        return isinstance(value, int) and not isinstance(value, bool)
    if kind == "bool":
        return isinstance(value, bool)
    return isinstance(value, str)

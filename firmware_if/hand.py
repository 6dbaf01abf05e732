"""Hand descriptions: fingers as serial chains of revolute joints on Dynamixel servos.

Loaded from TOML (a preset name from `firmware_if/hands/` or a file path), validated once in
`__post_init__` with errors that name the field to fix. Lengths in metres, angles in radians.
"""

from __future__ import annotations

import difflib
import itertools
import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from firmware_if.errors import HandConfigError
from firmware_if.registers import (
    BAUD_RATES,
    EXTENDED_RANGE,
    MODELS,
    POSITION_CENTRE,
    RAD_S_PER_VEL,
    REG,
    rad_to_ticks,
)

PRESET_DIR = Path(__file__).with_name("hands")
MAX_TIP_RADIUS = 0.1
MAX_REACH = 3.0
"""Metres beyond which a fingertip's radius, and a finger's links together, are taken for
millimetres (a hand file in millimetres was blamed on the object it could not hold)."""
TURN = 2 * math.pi
"""Radians: the most a finger joint's limit may lie from its zero (a limit in degrees,
-97 for -1.69 rad, was taken, and the servo sent to -2928 degrees)."""


def joint_ticks(joints: Sequence[Joint], q: Sequence[float]) -> dict[int, int]:
    """Position register values {servo id: ticks} of a chain's joints at angles `q`: goals
    for the backend, present positions for the emulator."""
    return {j.id: rad_to_ticks(float(a), j.zero_ticks, j.direction)
            for j, a in zip(joints, q, strict=True)}


def _vec3(value: Any, where: str) -> tuple[float, float, float]:
    try:
        v = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise HandConfigError(f"{where} must be a list of three numbers, got {value!r}") from None
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise HandConfigError(f"{where} must be three finite numbers, got {value!r}")
    return v  # type: ignore[return-value]


@dataclass(frozen=True)
class Joint:
    """One revolute joint: rotation about `axis` after translating by `origin` (parent frame)."""

    name: str
    id: int
    axis: tuple[float, float, float]
    origin: tuple[float, float, float]
    limits: tuple[float, float]
    zero_ticks: int = POSITION_CENTRE
    """Register value at joint angle 0."""
    direction: int = 1
    """+1 or -1: sign between joint angle and servo ticks."""
    model: str = "XM430-W350"

    def __post_init__(self) -> None:
        where = f"joint '{self.name}'"
        if not 0 <= self.id <= 252:
            raise HandConfigError(f"{where}: id must be 0..252, got {self.id}")
        axis = np.asarray(_vec3(self.axis, f"{where}: axis"))
        norm = float(np.linalg.norm(axis))
        if norm < 1e-9:
            raise HandConfigError(f"{where}: axis must not be zero")
        object.__setattr__(self, "axis", tuple(float(a) for a in axis / norm))
        object.__setattr__(self, "origin", _vec3(self.origin, f"{where}: origin"))
        lo, hi = (float(v) for v in self.limits)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise HandConfigError(f"{where}: limits must be [low, high] radians with low < high, "
                                  f"got {list(self.limits)}")
        if max(abs(lo), abs(hi)) > TURN:  # a finger's joint turns less than a turn
            raise HandConfigError(
                f"{where}: limits {list(self.limits)} reach beyond a whole turn: joint angles "
                f"are radians ({lo:g} degrees would be {math.radians(lo):.3g} rad, {hi:g} "
                f"degrees {math.radians(hi):.3g} rad)")
        object.__setattr__(self, "limits", (lo, hi))
        if self.direction not in (1, -1):
            raise HandConfigError(f"{where}: direction must be 1 or -1, got {self.direction}")
        _check_zero_ticks(self.zero_ticks, where)
        if self.model not in MODELS:
            raise HandConfigError(f"{where}: unknown servo model '{self.model}'; known: "
                                  f"{', '.join(MODELS)}")


@dataclass(frozen=True)
class TipRoll:
    """A continuously rolling tip joint: reported, not part of the centre's kinematics."""

    id: int
    zero_ticks: int = POSITION_CENTRE
    direction: int = 1

    def __post_init__(self) -> None:
        if not 0 <= self.id <= 252:
            raise HandConfigError(f"tip_roll: id must be 0..252, got {self.id}")
        if self.direction not in (1, -1):
            raise HandConfigError(f"tip_roll: direction must be 1 or -1, got {self.direction}")
        _check_zero_ticks(self.zero_ticks, "tip_roll")


def _check_zero_ticks(value: int, where: str) -> None:
    if not -EXTENDED_RANGE <= value <= EXTENDED_RANGE:
        raise HandConfigError(f"{where}: zero_ticks must be a position register value in "
                              f"[{-EXTENDED_RANGE}, {EXTENDED_RANGE}], got {value}")


@dataclass(frozen=True)
class Finger:
    """One finger: joints from base to tip and the fingertip sphere that rolls on the object."""

    name: str
    joints: tuple[Joint, ...]
    tip: tuple[float, float, float]
    """Offset from the last joint frame to the fingertip centre."""
    radius: float
    home: tuple[float, ...]
    """Joint angles of the start posture (the tip is then lowered onto the surface)."""
    tip_roll: TipRoll | None = None
    base: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Where the chain starts in the hand plane: (x, z) metres and the angle (radians, from
    hand x towards hand z) its own x axis points at. A lone finger's is (0, 0, 0)."""
    planar: bool = field(default=False)
    """All joint axes parallel: the centre moves in a vertical plane (explores a profile)."""

    def __post_init__(self) -> None:
        where = f"finger '{self.name}'"
        if not self.joints:
            raise HandConfigError(f"{where}: needs at least one [[joints]] entry")
        object.__setattr__(self, "tip", _vec3(self.tip, f"{where}: tip"))
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise HandConfigError(f"{where}: radius must be > 0 metres, got {self.radius}")
        reach = sum(float(np.linalg.norm(j.origin)) for j in self.joints) + float(
            np.linalg.norm(self.tip))
        if self.radius > MAX_TIP_RADIUS or reach > MAX_REACH:
            raise HandConfigError(
                f"{where}: a fingertip radius of {self.radius:g} m and links {reach:g} m long "
                "in all are a hand's size in millimetres: a hand file's lengths are metres")
        if len(self.home) != len(self.joints):
            raise HandConfigError(f"{where}: home needs {len(self.joints)} angles, "
                                  f"got {len(self.home)}")
        for j, q in zip(self.joints, self.home, strict=True):
            if not j.limits[0] <= q <= j.limits[1]:
                raise HandConfigError(f"{where}: home angle {q} of joint '{j.name}' "
                                      f"is outside its limits {list(j.limits)}")
        try:
            base = tuple(float(v) for v in self.base)
        except (TypeError, ValueError):
            base = ()
        if len(base) != 3 or not all(math.isfinite(v) for v in base):
            raise HandConfigError(f"{where}: base must be [x, z, angle] (metres, metres, "
                                  f"radians), got {list(self.base)}")
        object.__setattr__(self, "base", base)
        axes = np.array([j.axis for j in self.joints])
        object.__setattr__(self, "planar", bool(np.all(np.abs(axes @ axes[0]) > 1 - 1e-9)))

    @property
    def ids(self) -> tuple[int, ...]:
        """Servo ids of the chain, then the tip roll joint's if any."""
        return tuple(j.id for j in self.joints) + ((self.tip_roll.id,) if self.tip_roll else ())

    @property
    def lower(self) -> np.ndarray:
        return np.array([j.limits[0] for j in self.joints])

    @property
    def upper(self) -> np.ndarray:
        return np.array([j.limits[1] for j in self.joints])


@dataclass(frozen=True)
class Hand:
    """Fingers on one servo bus, and the bus settings. A single finger is a hand of one:
    `joints`, `tip`, `radius`, `home`, `tip_roll`, `planar`, `lower` and `upper` are its."""

    name: str
    fingers: tuple[Finger, ...]
    baud: int = 1_000_000
    return_delay_us: int = 0
    goal_current_a: float = 0.4
    """Current bound in current-based position mode: how hard the tip presses."""
    profile_velocity_rad_s: float = 0.0
    """Profile velocity of every joint (0: as fast as the servo can)."""
    grasp_centre: tuple[float, float] = (0.0, 0.0)
    """Where in the hand plane (x, z metres) a hand of several fingers holds an object."""

    def __post_init__(self) -> None:
        if not self.fingers:
            raise HandConfigError(f"hand '{self.name}': needs at least one finger")
        names = list(self.finger_names)
        if len(set(names)) != len(names):
            raise HandConfigError(f"hand '{self.name}': finger names must be unique, "
                                  f"got {names}")
        ids = list(self.ids)
        if len(set(ids)) != len(ids):
            users: dict[int, list[str]] = {}
            for f in self.fingers:
                for j in f.joints:
                    users.setdefault(j.id, []).append(f"joint '{j.name}'")
                if f.tip_roll is not None:
                    users.setdefault(f.tip_roll.id, []).append(f"the tip roll of finger '{f.name}'")
            shared = "; ".join(f"id {i}: {' and '.join(who)}" for i, who in users.items()
                               if len(who) > 1)
            raise HandConfigError(f"hand '{self.name}': servo ids must be unique, got {ids} "
                                  f"({shared})")
        for a, b in itertools.combinations(self.fingers, 2):
            apart = math.hypot(a.base[0] - b.base[0], a.base[1] - b.base[1])
            if apart < a.radius + b.radius:
                raise HandConfigError(
                    f"hand '{self.name}': fingers '{a.name}' and '{b.name}' have bases "
                    f"{apart * 1e3:.1f} mm apart, less than their tips are wide together: "
                    "give each finger its own base")
        if len(self.fingers) > 1:
            for f in self.fingers:
                if not (f.planar and abs(abs(f.joints[0].axis[1]) - 1) < 1e-9):
                    raise HandConfigError(
                        f"hand '{self.name}': finger '{f.name}': the fingers of a hand work "
                        "in its x-z plane, so every joint axis must be [0, 1, 0] or [0, -1, 0]")
        if self.baud not in BAUD_RATES.values():
            raise HandConfigError(f"hand '{self.name}': baud must be one of "
                                  f"{sorted(BAUD_RATES.values())}, got {self.baud}")
        if not 0 <= self.return_delay_us <= 508:
            raise HandConfigError(f"hand '{self.name}': return_delay_us must be 0..508")
        if not 0 < self.goal_current_a <= 3.2:
            raise HandConfigError(f"hand '{self.name}': goal_current_a must be in (0, 3.2] A")
        top = REG["profile_velocity"].hi * RAD_S_PER_VEL
        if not 0 <= self.profile_velocity_rad_s <= top:
            raise HandConfigError(f"hand '{self.name}': profile_velocity_rad_s must be in "
                                  f"[0, {top:.0f}] rad/s (0: as fast as the servo goes)")
        try:
            centre = tuple(float(v) for v in self.grasp_centre)
        except (TypeError, ValueError):
            centre = ()
        if len(centre) != 2 or not all(math.isfinite(v) for v in centre):
            raise HandConfigError(f"hand '{self.name}': grasp_centre must be [x, z] metres")
        object.__setattr__(self, "grasp_centre", centre)

    @property
    def ids(self) -> tuple[int, ...]:
        """Every servo id on the bus, finger by finger."""
        return tuple(i for f in self.fingers for i in f.ids)

    @property
    def finger_names(self) -> tuple[str, ...]:
        """Every finger's name, in order (the backends' `finger_names`)."""
        return tuple(f.name for f in self.fingers)

    @property
    def finger(self) -> Finger:
        """The one finger of a single-finger hand."""
        if len(self.fingers) != 1:
            raise HandConfigError(f"hand '{self.name}' has {len(self.fingers)} fingers; this "
                                  "needs a single finger (e.g. the planar or spatial preset)")
        return self.fingers[0]

    joints = property(lambda self: self.finger.joints)
    tip = property(lambda self: self.finger.tip)
    radius = property(lambda self: self.finger.radius)
    home = property(lambda self: self.finger.home)
    tip_roll = property(lambda self: self.finger.tip_roll)
    base = property(lambda self: self.finger.base)
    planar = property(lambda self: self.finger.planar)
    lower = property(lambda self: self.finger.lower)
    upper = property(lambda self: self.finger.upper)


def _whole(value: Any, where: str) -> int:
    """An integer from TOML: `1.5`, `true` or `"3"` are errors, not 1, 1 or 3."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise HandConfigError(f"{where} must be a whole number, got {value!r}")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise HandConfigError(f"{where} must be a number, got {value!r}")
    return float(value)


def _table(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise HandConfigError(f"{where} must be a table, got {value!r}")
    return value


def _list(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise HandConfigError(f"{where} must be a list, got {value!r}")
    return value


HAND_KEYS = ("name", "model", "fingers", "baud", "return_delay_us", "goal_current_a",
             "profile_velocity_rad_s", "grasp_centre")
FINGER_KEYS = ("name", "model", "joints", "tip", "radius", "home", "base", "tip_roll")
JOINT_KEYS = ("name", "id", "axis", "origin", "limits", "zero_ticks", "direction", "model")
TIP_ROLL_KEYS = ("id", "zero_ticks", "direction")


def _known(table: dict[str, Any], keys: tuple[str, ...], where: str) -> dict[str, Any]:
    """`table`, refused if it has a key not in `keys`: a misspelt `goal_current` (for
    `goal_current_a`) was ignored, and the servos ran at the default current."""
    for key in table:
        if key not in keys:
            close = difflib.get_close_matches(key, keys, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise HandConfigError(f"{where}: unknown field '{key}'; {hint}fields: "
                                  f"{', '.join(keys)}")
    return table


def _field(table: dict[str, Any], key: str, where: str) -> Any:
    if key not in table:
        raise HandConfigError(f"{where}: missing field '{key}'")
    return table[key]


def _finger_from_dict(data: dict[str, Any], name: str, model: str, *, based: bool = False
                      ) -> Finger:
    """One finger; `based`: it must say where its base is (one of several fingers: a
    default base would put two of them on the same spot without a word)."""
    name = str(data.get("name", name))
    where = f"finger '{name}'"
    joints = []
    for i, entry in enumerate(_list(data.get("joints", []), f"{where}: joints")):
        w = f"{where}: joints[{i}]"
        j = _known(_table(entry, w), JOINT_KEYS, w)
        joints.append(Joint(
            name=str(j.get("name", f"joint{i}")), id=_whole(_field(j, "id", w), f"{w}: id"),
            axis=_field(j, "axis", w), origin=j.get("origin", (0.0, 0.0, 0.0)),
            limits=tuple(_number(v, f"{w}: limits")
                         for v in _list(_field(j, "limits", w), f"{w}: limits")),
            zero_ticks=_whole(j.get("zero_ticks", POSITION_CENTRE), f"{w}: zero_ticks"),
            direction=_whole(j.get("direction", 1), f"{w}: direction"),
            model=str(j.get("model", data.get("model", model)))))
    roll = data.get("tip_roll")
    if roll is not None:
        roll = _known(_table(roll, f"{where}: tip_roll"), TIP_ROLL_KEYS, f"{where}: tip_roll")
    tip_roll = None if roll is None else TipRoll(
        id=_whole(_field(roll, "id", f"{where}: tip_roll"), f"{where}: tip_roll: id"),
        zero_ticks=_whole(roll.get("zero_ticks", POSITION_CENTRE),
                          f"{where}: tip_roll: zero_ticks"),
        direction=_whole(roll.get("direction", 1), f"{where}: tip_roll: direction"))
    base = _field(data, "base", where) if based else data.get("base", (0.0, 0.0, 0.0))
    return Finger(name=name, joints=tuple(joints),
                  tip=_field(data, "tip", where),
                  radius=_number(_field(data, "radius", where), f"{where}: radius"),
                  home=tuple(_number(q, f"{where}: home")
                             for q in _list(_field(data, "home", where), f"{where}: home")),
                  tip_roll=tip_roll, base=tuple(base))


def hand_from_dict(data: dict[str, Any], name: str = "hand") -> Hand:
    """Build a hand from parsed TOML, turning missing or mistyped fields into clear errors.

    Either a `[[fingers]]` list (each with its own joints, tip, radius, home, base and
    optional tip_roll) or, for a single finger, those fields at the top level.
    """
    hand_name = str(data.get("name", name))
    where = f"hand '{hand_name}'"
    try:
        model = str(data.get("model", "XM430-W350"))
        if "fingers" in data:
            if "joints" in data:
                raise HandConfigError(f"hand '{hand_name}': give [[fingers]] or top-level "
                                      "[[joints]], not both")
            _known(data, HAND_KEYS, where)
            listed = _list(data["fingers"], f"{where}: fingers")
            fingers = tuple(_finger_from_dict(
                _known(_table(f, f"{where}: fingers[{i}]"), FINGER_KEYS,
                       f"{where}: fingers[{i}]"), f"finger{i}", model, based=len(listed) > 1)
                for i, f in enumerate(listed))
        else:  # one finger, its fields at the top level
            _known(data, tuple(dict.fromkeys(HAND_KEYS + FINGER_KEYS)), where)
            if "tip" not in data and "joints" not in data:
                raise HandConfigError(f"{where}: no fingers; list them as [[fingers]], each "
                                      "with joints, tip, radius and home (or give one "
                                      "finger's at the top level)")
            fingers = (_finger_from_dict(data, hand_name, model),)
        return Hand(name=hand_name, fingers=fingers,
                    baud=_whole(data.get("baud", 1_000_000), f"{where}: baud"),
                    return_delay_us=_whole(data.get("return_delay_us", 0),
                                           f"{where}: return_delay_us"),
                    goal_current_a=_number(data.get("goal_current_a", 0.4),
                                           f"{where}: goal_current_a"),
                    profile_velocity_rad_s=_number(data.get("profile_velocity_rad_s", 0.0),
                                                   f"{where}: profile_velocity_rad_s"),
                    grasp_centre=tuple(data.get("grasp_centre", (0.0, 0.0))))
    except KeyError as exc:
        raise HandConfigError(f"hand '{name}': missing field {exc.args[0]!r}") from None
    except (TypeError, ValueError, AttributeError) as exc:
        if isinstance(exc, HandConfigError):
            raise
        raise HandConfigError(f"hand '{name}': {exc}") from None


def presets(holding: bool = False) -> list[str]:
    """The hand presets' names; `holding`: only hands of several fingers, which can hold an
    object (a lab told of `planar` for its object was then refused it: one finger)."""
    names = sorted(p.stem for p in PRESET_DIR.glob("*.toml"))
    return [n for n in names if len(load_hand(n).fingers) > 1] if holding else names


def load_hand(spec: str, holding: bool = False) -> Hand:
    """A preset name ('planar', 'spatial', 'two-finger', ...) or a path to a TOML file;
    `holding`: for an object, so an error lists the presets that can hold one."""
    path = PRESET_DIR / f"{spec}.toml"
    if not path.is_file():
        path = Path(spec)
        if not path.is_file():
            raise HandConfigError(f"no hand preset or file '{spec}'; presets: "
                                  f"{', '.join(presets(holding))}")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise HandConfigError(f"{path}: not valid TOML ({exc})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise HandConfigError(f"hand file '{path}' could not be read: {exc}") from None
    return hand_from_dict(data, name=path.stem)

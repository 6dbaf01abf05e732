"""Seeded fuzzing of configuration: TOML files, hand files and run-time `configure`.

Whatever the values, the outcome is a valid configuration or one ConfigError (hand files:
HandConfigError) naming the problem; over the wire, an `ok` reply or `bad_config`, and a
refused change leaves the running config as it was.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_if.errors import HandConfigError
from firmware_if.hand import hand_from_dict
from service.daemon.config import RUNTIME_SECTIONS, SECTIONS, DaemonConfig, load_config
from service.daemon.harness import loopback_config, running_node
from service.errors import ConfigError
from service.wire.client import Client, CommandFailed

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = {name: [f.name for f in dataclasses.fields(type(getattr(DaemonConfig(), name)))]
          for name in SECTIONS if name != "auto_configure"}

NASTY = st.sampled_from([
    True, False, 0, -1, 1, 2, 3, 0.5, 1.5, -0.0, 1e-300, 1e300, math.inf, -math.inf,
    math.nan, 2**63 - 1, -(2**63), "", "x", "false", "1", "peaks", "bumps:20:nan",
    "bumps:30:1", "/etc/passwd", "sim", "dynamixel", "particles", "skip", "process",
    [1, 2], [1.0, 2.0, 3.0], ["a", "b", "c"], [], {"work": 10}, {"work": "x"},
    {"port": "/dev/null", "hand": "planar"}, {"a": {"b": 1}},
])
VALUES = NASTY | st.integers(-(2**63), 2**63 - 1) | st.floats() | st.text(max_size=12)


@st.composite
def config_tables(draw: st.DrawFn, sections: tuple[str, ...] = tuple(SCHEMA)
                  ) -> dict[str, Any]:
    """Random {section: {key: value}} over the real keys (and an occasional typo)."""
    out: dict[str, Any] = {}
    for section in draw(st.lists(st.sampled_from(sections), max_size=3, unique=True)):
        keys = draw(st.lists(st.sampled_from([*SCHEMA[section], "typo"]), min_size=1,
                             max_size=3, unique=True))
        out[section] = {k: draw(VALUES) for k in keys}
    return out


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value == math.inf else
                                                "-inf" if value == -math.inf else repr(value))
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + "}"


def toml_text(tables: dict[str, Any]) -> str:
    return "\n".join(f"[{name}]\n" + "\n".join(f"{k} = {toml_value(v)}" for k, v in t.items())
                     for name, t in tables.items()) + "\n"


@settings(max_examples=150, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(config_tables())
def test_fuzzed_config_files_load_or_name_the_problem(tmp_path_factory, tables) -> None:
    path = tmp_path_factory.mktemp("cfg") / "hapticd.toml"
    path.write_text(toml_text(tables))
    try:
        config = load_config(path)
    except ConfigError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    config.run_settings()  # an accepted config builds its settings
    assert 1.0 / config.loop.cloud_hz < 100 and config.lease.ttl_s <= 10.0


@settings(max_examples=100, derandomize=True, deadline=None)
@given(st.binary(max_size=200) | st.text(max_size=200).map(str.encode))
def test_garbage_config_files_are_config_errors(tmp_path_factory, data: bytes) -> None:
    path = tmp_path_factory.mktemp("cfg") / "hapticd.toml"
    path.write_bytes(data)
    with contextlib.suppress(ConfigError):  # anything else fails the test
        load_config(path)


PLANAR = tomllib.loads((ROOT / "firmware_if/hands/planar.toml").read_text())
HAND_KEYS = ["name", "radius", "tip", "home", "baud", "return_delay_us", "goal_current_a",
             "profile_velocity_rad_s", "tip_roll", "joints"]
JOINT_KEYS = ["name", "id", "axis", "origin", "limits", "zero_ticks", "direction", "model"]


@settings(max_examples=300, derandomize=True, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(HAND_KEYS + [f"j.{k}" for k in JOINT_KEYS]),
                          VALUES), min_size=1, max_size=3))
def test_fuzzed_hand_files_build_or_name_the_problem(changes) -> None:
    data = json.loads(json.dumps(PLANAR))
    for key, value in sorted(changes, key=lambda c: not c[0].startswith("j.")):
        if key.startswith("j."):  # joint fields first: `joints` itself may be replaced after
            data["joints"][0][key[2:]] = value
        else:
            data[key] = value
    try:
        hand_from_dict(data, "fuzzed")
    except HandConfigError as exc:
        assert str(exc)


@pytest.fixture(scope="module")
def ctl():
    with running_node(loopback_config({"backend": {"step_duration_s": 0.0}})) as node, \
            Client(node.endpoints["cmd"], timeout_s=20.0, retries=0) as client:
        yield client


@settings(max_examples=60, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(config_tables(RUNTIME_SECTIONS))
def test_fuzzed_configure_is_ok_or_bad_config_and_refusals_change_nothing(ctl, tables):
    before = ctl.call("get_config")
    try:
        ctl.call("configure", changes=tables)
    except CommandFailed as exc:
        assert exc.code in ("bad_config", "hardware"), exc
        assert ctl.call("get_config") == before
    else:
        ctl.call("configure", changes={s: dataclasses.asdict(getattr(DaemonConfig(), s))
                                       for s in ("backend", "scenario", "lease")}
                 | {"loop": {"rate_hz": 200.0, "cloud_hz": 4.0, "state_every": 1}})
    assert ctl.call("ping") == {"pong": True}
    assert ctl.status()["state"] == "inactive"

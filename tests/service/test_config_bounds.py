"""Issue 12, finding 1 and 5: every setting has a type and a range; bad values are errors
that name the setting, never a crash, a traceback or a silently changed daemon."""

from __future__ import annotations

import math
from pathlib import Path

import msgpack
import numpy as np
import pytest

from firmware_if.errors import HandConfigError
from firmware_if.hand import hand_from_dict, load_hand
from service.bounds import check_keywords, keyword_params, settable
from service.daemon.config import DaemonConfig, from_dict
from service.daemon.harness import loopback_config, running_node
from service.episode.scenario import RunSettings
from service.errors import ConfigError
from service.registry import LOCALIZERS
from service.wire import envelope as wire
from service.wire.client import Client, CommandFailed

ROOT = Path(__file__).resolve().parents[2]

# (section, key, value): each was accepted before and crashed, stalled, disabled the lease
# watchdog or changed the daemon while being refused (issue 12's reproductions).
REPRODUCTIONS = [
    ("loop", "cloud_hz", 1e-300),       # OverflowError in the next tick: hapticd exited
    ("lease", "hold_s", math.inf),      # hapticd exited when the lease expired
    ("lease", "hold_s", 1e9),           # watchdog off: torque stayed on
    ("lease", "ttl_s", 2**63),          # watchdog off
    ("loop", "rate_hz", 1e-5),          # no state for good, could not be undone
    ("loop", "rate_hz", 1e-300),        # answered `internal` but applied
    ("lease", "ttl_s", 1e308),          # answered `internal` but applied
    ("loop", "state_every", 2**63),     # stream stopped
    ("scenario", "noise", "false"),     # turned noise on
    ("scenario", "seed", 1.5),
    ("scenario", "start", ["a", "b", "c"]),
    ("scenario", "map", 5),
    ("scenario", "spacing", 1e-300),
    ("scenario", "radius", 20.0),
    ("scenario", "localizer_options", {"work": "abc"}),
    ("scenario", "localizer_options", {"wrok": 10}),
    ("scenario", "localizer_options", {"initial": -1}),   # accepted; every start faulted
    ("scenario", "localizer_options", {"children": -1}),  # faulted mid-episode
    ("scenario", "localizer_options", {"capacity": 10**9}),
    ("scenario", "localizer_options", {"contraction": 0.0}),
    ("backend", "options", {"port": "/dev/null"}),
    ("loop", "stats_window", 10**9),
    ("endpoints", "sndhwm", 0),
    ("loop", "realtime_priority", 99),  # above what an ordinary RT task should take
    ("loop", "realtime_priority", -1),
]


# A held-out lab's (2026-12-05): a port out of range was bound modulo 65536 (556000 put the
# stream on 31712); a preset's typo and a hand file that is not there, given to the
# Dynamixel backend, started a daemon that could never configure.
HELD_OUT = [
    ("endpoints", "pub", "tcp://127.0.0.1:556000"),
    ("endpoints", "cmd", "tcp://127.0.0.1:99999"),
    ("endpoints", "pub", "tcp://127.0.0.1:0"),
    ("endpoints", "cmd", "tcp://127.0.0.1"),
    ("scenario", "map", "peeks"),
    ("scenario", "map", "bumps:20:x"),
]


@pytest.mark.parametrize("section, key, value", REPRODUCTIONS + HELD_OUT)
def test_out_of_range_or_mistyped_values_are_config_errors(section: str, key: str,
                                                           value: object) -> None:
    with pytest.raises(ConfigError, match=f"{section}.*{key}|{key}"):
        from_dict({section: {key: value}})


def test_a_dynamixel_hand_file_that_is_not_there_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="backend.options.hand: hand file "
                                          "'no-such-hand.toml' cannot be used"):
        from_dict({"backend": {"name": "dynamixel",
                               "options": {"port": "/dev/null", "hand": "no-such-hand.toml"}}})


@pytest.mark.parametrize("endpoint", ["tcp://127.0.0.1:65535", "tcp://127.0.0.1:*",
                                      "tcp://[::1]:5560", "ipc:///tmp/hapticd-pub"])
def test_ports_in_range_and_other_transports_are_taken(endpoint: str) -> None:
    assert from_dict({"endpoints": {"pub": endpoint}}).endpoints.pub == endpoint


def test_the_stream_and_the_commands_need_an_endpoint_each() -> None:
    """A held-out check gave both one endpoint: "Address already in use; is another hapticd
    running there?"."""
    with pytest.raises(ConfigError, match="endpoints.pub and endpoints.cmd are one endpoint"):
        from_dict({"endpoints": {"pub": "tcp://127.0.0.1:5561"}})
    both = from_dict({"endpoints": {"pub": "tcp://127.0.0.1:*", "cmd": "tcp://127.0.0.1:*"}})
    assert both.endpoints.pub == both.endpoints.cmd  # any free port, one each


def test_the_lease_watchdog_cannot_be_configured_away() -> None:
    for ttl, hold in ((10.0, 5.0), (0.1, 0.0)):  # the extremes allowed
        lease = from_dict({"lease": {"ttl_s": ttl, "hold_s": hold}}).lease
        assert lease.ttl_s + lease.hold_s <= 15.0
    for bad in ({"ttl_s": 10.5}, {"hold_s": 5.5}, {"ttl_s": -1}, {"ttl_s": True}):
        with pytest.raises(ConfigError, match="lease"):
            from_dict({"lease": bad})


def test_values_are_normalized_not_coerced() -> None:
    config = from_dict({"loop": {"rate_hz": 250}, "scenario": {"start": [0.1, 0.1, 1]}})
    assert config.loop.rate_hz == 250.0 and isinstance(config.loop.rate_hz, float)
    assert config.scenario.start == (0.1, 0.1, 1.0)
    for bad in ("true", 1, None):
        with pytest.raises(ConfigError, match="noise"):
            from_dict({"scenario": {"noise": bad}})


def test_run_settings_share_the_bounds_haptic_run_uses() -> None:
    with pytest.raises(ConfigError, match="--radius must be a number in"):
        RunSettings(radius=1e-300)
    with pytest.raises(ConfigError, match="option 'work' must be int"):
        RunSettings(localizer_options={"work": "abc"})
    with pytest.raises(ConfigError, match="no option 'wrok'; did you mean 'work'"):
        RunSettings(localizer_options={"wrok": 1})


def test_refused_configure_changes_nothing_and_is_bad_config() -> None:
    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        before = ctl.call("get_config")
        for section, key, value in REPRODUCTIONS:
            if section == "endpoints":
                continue  # not changeable at run time: also bad_config
            with pytest.raises(CommandFailed) as err:
                ctl.call("configure", changes={section: {key: value}})
            assert err.value.code == "bad_config", (section, key, err.value)
        for spec in ("bumps:20:nan", "peaks:1e-300", "no-such-preset"):  # load-time errors
            with pytest.raises(CommandFailed, match="bad_config"):
                ctl.call("configure", changes={"scenario": {"map": spec}})
        # a change is validated whole: one bad key leaves the good one unapplied too
        with pytest.raises(CommandFailed, match="bad_config"):
            ctl.call("configure", changes={"loop": {"rate_hz": 100.0},
                                           "lease": {"ttl_s": 1e9}})
        assert ctl.call("get_config") == before
        assert ctl.status()["state"] == "inactive"


@pytest.mark.parametrize("v", [True, 2.0, "2", None, 1, 3])
def test_only_the_integer_2_is_version_2(v: object) -> None:
    with pytest.raises(wire.WireError) as err:
        wire.check_envelope({"v": v, "type": "request"}, need_seq=False)
    assert err.value.code == "bad_version"


def test_configure_request_with_v_true_is_refused() -> None:
    from service.wire.commands import CommandServer, Lease

    class Nothing:
        def __getattr__(self, name: str):  # any control: must not be reached
            raise AssertionError(f"{name} ran")

    import zmq
    server = CommandServer(zmq.Context.instance(), "inproc://v-true", Nothing(), Lease(1.0))
    try:
        for v in (True, 2.0):
            reply = msgpack.unpackb(server.handle(msgpack.packb(
                {"v": v, "type": "request", "id": 1, "cmd": "estop"})))
            assert reply["error"]["code"] == "bad_version"
    finally:
        server.close()


TOML_CASES = [
    "[scenario]\nseed = 1.5\n",
    '[scenario]\nstart = ["a", "b", "c"]\n',
    "[scenario]\nmap = 5\n",
    '[scenario]\nmap = "peaks"\nspacing = 1e-300\n',
    '[scenario]\nnoise = "false"\n',
    "[loop]\ncloud_hz = 1e-300\n",
    "[lease]\nhold_s = inf\n",
    "[loop]\nstate_every = 9223372036854775807\n",
    "auto_configure = 1\n",
    '[backend]\nname = "dynamixel"\noptions = { port = 3, hand = "planar" }\n',
    '[scenario]\nmap = "peeks"\n',  # ran on unconfigured (a held-out lab's typo)
]


@pytest.mark.parametrize("text", TOML_CASES)
def test_hapticd_bad_toml_is_one_line_and_status_2(tmp_path: Path, text: str, capsys) -> None:
    import threading

    from service.daemon.main import main

    cfg = tmp_path / "hapticd.toml"
    cfg.write_text(f'[endpoints]\npub = "ipc://{tmp_path}/p"\ncmd = "ipc://{tmp_path}/c"\n'
                   + text)
    status: list[int] = []
    runner = threading.Thread(target=lambda: status.append(main(["--config", str(cfg)])),
                              daemon=True)
    runner.start()
    runner.join(30)  # an accepted config would serve for ever
    assert status == [2]
    err = capsys.readouterr().err
    assert err.startswith("hapticd: error:") and err.count("\n") == 1, err


@pytest.mark.parametrize("field, value, words", [
    ("joints", [1, 2], "must be a table"),
    ("zero_ticks", 1_000_000_000_000, "zero_ticks"),
    ("baud", 1.5, "whole number"),
    ("tip_roll", 5, "tip_roll"),
    ("profile_velocity_rad_s", 1e300, "profile_velocity"),
    ("direction", 0.5, "direction"),
])
def test_bad_hand_files_are_hand_config_errors(field: str, value: object, words: str) -> None:
    import tomllib

    data = tomllib.loads((ROOT / "firmware_if/hands/planar.toml").read_text())
    if field in ("zero_ticks", "direction"):
        data["joints"][0][field] = value
    else:
        data[field] = value
    with pytest.raises(HandConfigError, match=words):
        hand_from_dict(data, "planar")


def test_an_unreadable_hand_file_is_a_hand_config_error(tmp_path: Path) -> None:
    binary = tmp_path / "hand.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(HandConfigError, match="could not be read"):
        load_hand(str(binary))


@pytest.mark.parametrize("argv", [
    ["run", "--localizer-option", "work=abc"],
    ["run", "--radius", "20"],
    ["run", "--spacing", "1e-300", "--map", "x.npy"],
    ["run", "--max-steps", "0"],
    ["ctl", "--cmd", "garbage", "status"],
    ["watch", "--pub", "garbage", "--duration", "0.1"],
])
def test_cli_user_errors_are_one_line_and_status_2(argv: list[str], capsys) -> None:
    from tools.cli import main

    assert main(argv) == 2  # an exception here would be the traceback a user sees
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err, err


def test_replay_of_a_message_without_its_fields_is_one_line(tmp_path: Path, capsys) -> None:
    from tools.cli import main

    bad = tmp_path / "bad.hrec"
    with bad.open("wb") as f:
        f.write(msgpack.packb({"format": "haptic-record", "v": 1, "config": None}))
        f.write(msgpack.packb({"topic": "state", "t_ns": 1,
                               "payload": wire.encode("state", 1, {"fault": None})}))
    assert main(["replay", str(bad)]) == 2
    assert "message 1" in capsys.readouterr().err


def test_defaults_are_inside_their_own_bounds() -> None:
    assert from_dict({}) == DaemonConfig()
    for name in LOCALIZERS.names():  # every localizer's option defaults pass their bounds
        target = LOCALIZERS.load(name)
        defaults = {option: default for option, (hint, default)
                    in keyword_params(target).items() if settable(hint) and default is not None}
        check_keywords(target, defaults, name)


def test_a_finger_backends_hand_file_tells_a_client_nothing_and_a_missing_hand_is_named(
        tmp_path: Path) -> None:
    """A hand file named in backend.options answered with its TOML parser's line and column
    (of /etc/shadow, say): it is quieted as scenario.hand's is. Options without a hand
    answered with a Python TypeError; they name what is missing and how to give it."""
    hand = tmp_path / "hand.toml"
    hand.write_text('name = "x"\nhunter2 = \n')
    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        before = ctl.call("get_config")
        for options, words in (({"port": "/dev/null", "hand": str(hand)}, "cannot be used"),
                               ({"port": "/dev/null", "hand": str(tmp_path / "no.toml")},
                                "cannot be used"),
                               ({"port": "/dev/null"}, "need hand beside what they give")):
            with pytest.raises(CommandFailed) as err:
                ctl.call("configure", changes={"backend": {"name": "dynamixel",
                                                           "options": options}})
            message = str(err.value)
            assert err.value.code == "bad_config" and words in message, message
            for leak in ("hunter2", "line", "column", "exist", "TypeError", "keyword"):
                assert leak not in message, message
        assert ctl.call("get_config") == before
        # a hand's options without a port: "DynamixelHand.from_cli() missing 1 required
        # keyword-only argument: 'port'" (a fault campaign's finding)
        with pytest.raises(CommandFailed) as err:
            ctl.call("configure", changes={
                "backend": {"name": "dynamixel", "options": {}},
                "scenario": {"object": "blob", "hand": "three-finger"}})
        message = str(err.value)
        assert "backend.options for 'dynamixel' need port beside what they give " \
               "(nothing)" in message and "keyword" not in message, message
        assert ctl.call("get_config") == before


def test_backend_options_missing_a_key_are_refused_before_anything_is_prepared(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A held-out lab waited 1.3-9 s for this refusal, behind the preparation of a map it
    had not changed: options that lack a key are refused with the rest of the check."""
    from service.daemon import controls

    def prepared(*args, **kwargs):
        raise AssertionError("the configure was prepared before its options were checked")

    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        before = ctl.call("get_config")
        monkeypatch.setattr(controls, "Reconfiguration", prepared)
        for changes, missing in (
                ({"backend": {"name": "dynamixel", "options": {"port": "/dev/null"}}}, "hand"),
                ({"backend": {"name": "dynamixel", "options": {}},
                  "scenario": {"object": "blob", "hand": "three-finger"}}, "port")):
            with pytest.raises(CommandFailed) as err:
                ctl.call("configure", changes=changes)
            assert err.value.code == "bad_config"
            assert f"need {missing} beside what they give" in str(err.value)
        assert ctl.call("get_config") == before


def test_a_map_in_millimetres_is_accepted_with_a_warning_the_client_sees(tmp_path: Path) -> None:
    """Under hapticd a map whose heights were in millimetres was taken without a word, where
    `haptic run` warns: the configure's reply and `status` carry the map check's warnings."""
    rng = np.random.default_rng(0)
    path = tmp_path / "mm.npy"
    np.save(path, rng.normal(size=(201, 201)).cumsum(0).cumsum(1) * 0.01)
    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        reply = ctl.call("configure", changes={"scenario": {"map": str(path), "spacing": 0.001}})
        assert any("look like millimetres" in w for w in reply["warnings"])
        assert ctl.call("status")["map_warnings"] == reply["warnings"]
        reply = ctl.call("set_map", map="bumps:20:1")
        assert not any("millimetres" in w for w in reply["warnings"])


def test_a_map_files_own_mistakes_are_told_in_full(tmp_path: Path) -> None:
    """A map file named without its spacing, or in a format that is no map's, is the client's
    own mistake and says nothing of the daemon's files: it is told as `haptic run` tells it,
    not hidden behind "cannot be used" (the spacing's message reached only the log)."""
    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        before = ctl.call("get_config")
        for changes, words in (({"map": str(tmp_path / "a.npy")}, "scenario.spacing"),
                               ({"map": str(tmp_path / "a.npz")}, ".csv, .npy, .txt")):
            with pytest.raises(CommandFailed) as err:
                ctl.call("configure", changes={"scenario": changes})
            assert err.value.code == "bad_config" and words in str(err.value)
            assert "cannot be used" not in str(err.value) and "exist" not in str(err.value)
        assert ctl.call("get_config") == before


def test_a_radius_a_map_file_cannot_take_is_told_in_full(tmp_path: Path) -> None:
    """The map file loads, the fingertip does not fit on it: the client is told about the
    radius, as on a preset (it was told the file "cannot be used", the cause only logged)."""
    path = tmp_path / "small.npy"
    np.save(path, np.zeros((50, 50)))
    with running_node(loopback_config()) as node, Client(node.endpoints["cmd"]) as ctl:
        ctl.call("configure", changes={"scenario": {"map": str(path), "spacing": 0.001}})
        before = ctl.call("get_config")
        with pytest.raises(CommandFailed) as err:
            ctl.call("configure", changes={"scenario": {"radius": 0.3}})
        assert err.value.code == "bad_config" and "does not fit on map" in str(err.value)
        assert "cannot be used" not in str(err.value)
        assert ctl.call("get_config") == before


def test_a_message_without_a_version_is_told_so() -> None:
    """A fault campaign's finding: a request with no `v` was answered "schema version
    None is not supported"."""
    with pytest.raises(wire.WireError, match="carries no schema version"):
        wire.check_envelope({"type": "request"}, need_seq=False)


def test_a_bad_option_table_says_what_a_table_holds() -> None:
    """A fault campaign's finding: {"work": [1]} was refused as "must be a table", which
    it is; the list inside is what no option takes."""
    from service.bounds import Bound

    with pytest.raises(ConfigError, match="must be a table of names to numbers, true/false "
                       r"or strings \(at most 64\), got"):
        Bound("options").check("scenario.localizer_options", {"work": [1]})


def test_a_length_in_millimetres_is_told_in_metres() -> None:
    """A researcher's finding: `--radius 8` said "for 8 mm give 0.008", `--spacing 1` only
    its range."""
    from service.bounds import Bound

    with pytest.raises(ConfigError, match="for 1 mm give 0.001"):
        Bound("float", 1e-6, 0.1, unit="m").check("--spacing", 1)
    with pytest.raises(ConfigError) as err:
        Bound("float", 1e-6, 0.1, unit="m").check("--spacing", 500)  # 0.5 m: still too big
    assert "mm give" not in str(err.value)


def test_an_object_preset_the_daemon_does_not_know_is_a_config_error() -> None:
    """A held-out check: `object = "teapot"` (or a seed that is no number, or a plane for a
    CSV outline) started a daemon that could never configure, where `map = "teapot"` was
    one line and exit 2; and on a finger's Dynamixel backend `configure
    scenario.object=teapot` was told about `backend.options.hand`, never about teapot."""
    for scenario, words in (({"object": "teapot"}, "unknown object 'teapot'"),
                            ({"object": "keyed:x"}, "seed must be a whole number"),
                            ({"object": "outline.csv", "plane": "z=0.01"}, "not a CSV"),
                            ({"object": "blob", "object_units": "mm"}, "not presets")):
        with pytest.raises(ConfigError, match=f"scenario.object: .*{words}"):
            from_dict({"scenario": scenario})
    with pytest.raises(ConfigError, match="unknown object 'teapot'"):
        from_dict({"backend": {"name": "dynamixel",
                               "options": {"port": "/dev/null", "hand": "spatial"}},
                   "scenario": {"object": "teapot"}})


def test_a_bus_cycle_budget_out_of_range_is_refused_at_once() -> None:
    """A held-out check: `configure backend.options={..., "cycle_budget_s": 99}` was
    answered `bad_config` only once the compute process had set the scenario up (1-2 s);
    a bad value is refused before anything is built."""
    for budget in (99, -1, 0.001):
        with pytest.raises(ConfigError, match="backend.options.cycle_budget_s must be "
                                              "0.002 .. 0.5 s"):
            from_dict({"backend": {"name": "dynamixel", "options": {
                "port": "/dev/null", "hand": "spatial", "cycle_budget_s": budget}}})
    assert from_dict({"backend": {"name": "dynamixel", "options": {
        "port": "/dev/null", "hand": "spatial", "cycle_budget_s": 0.02}}})

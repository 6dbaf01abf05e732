"""The daemon config validator and the lifecycle table."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.daemon.config import DaemonConfig, from_dict, load_config
from service.daemon.harness import loopback_config
from service.daemon.lifecycle import Lifecycle, State
from service.errors import ConfigError, StateError

SAMPLE = Path(__file__).resolve().parents[2] / "config" / "hapticd.toml"


def test_sample_config_is_valid_and_equals_the_defaults() -> None:
    assert load_config(SAMPLE) == DaemonConfig()


@pytest.mark.parametrize("data, words", [
    ({"loop": {"rate_hz": 0}}, "rate_hz"),
    ({"loop": {"rate_hz": True}}, "rate_hz"),
    ({"loop": {"overrun": "later"}}, "overrun"),
    ({"loop": {"work_fraction": 0.5}}, "work_fraction is gone"),
    ({"loop": {"typo": 1}}, "unknown key"),
    ({"loop": {"localizer_mode": "sliced"}}, "localizer_mode is gone"),
    ({"nonsense": {}}, "unknown config section"),
    ({"backend": {"name": "warp"}}, "backend.name"),
    ({"scenario": {"localizer": "magic"}}, "localizer"),
    ({"scenario": {"step": -1}}, "step"),
    ({"scenario": {"start": [1, 2]}}, "start"),
    ({"backend": {"name": "dynamixel", "options": {"port": "/dev/ttyUSB0", "hand": "planar"}},
      "scenario": {"start": [0.1, 0.1, 0.0]}},  # was accepted, and unused
     "scenario.start hides the simulator's start pose.*remove scenario.start"),
    ({"endpoints": {"pub": "localhost"}}, "endpoint"),
    ({"security": {"curve": True}}, "server_secret_key"),
    ({"lease": {"ttl_s": 0}}, "ttl_s"),
    ({"auto_configure": "yes"}, "auto_configure"),
])
def test_bad_values_are_rejected_with_a_useful_message(data: dict, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        from_dict(data)


def test_changes_are_validated_the_same_way() -> None:
    config = DaemonConfig()
    changed = config.updated({"scenario": {"map": "bumps:20:3", "start": [0.1, 0.1, 0.0]}})
    assert changed.scenario.map == "bumps:20:3" and changed.scenario.start == (0.1, 0.1, 0.0)
    assert config.scenario.map == "peaks"  # frozen: the old one is untouched
    with pytest.raises(ConfigError, match="rate_hz"):
        config.updated({"loop": {"rate_hz": -5}})
    with pytest.raises(ConfigError, match="cannot be changed"):
        config.updated({"endpoints": {"pub": "tcp://0.0.0.0:1"}})


@pytest.mark.parametrize("change", [{"map": "nope.npy"}, {"policy": "random"},
                                    {"radius": 0.005}, {"object": "keyed", "spacing": 0.001}])
def test_a_hand_refuses_what_only_a_finger_uses(change: dict) -> None:
    """Stored unchecked on a hand, a map file that does not load was accepted, and then
    refused the switch back to a finger (a client written from the docs alone)."""
    hand = DaemonConfig().updated({"scenario": {"object": "blob", "hand": "three-finger"}})
    with pytest.raises(ConfigError, match="applies to a finger on a map.*object"):
        hand.updated({"scenario": change})
    finger = hand.updated({"scenario": {"object": None, "hand": None, "map": "bumps:20:3"}})
    assert finger.scenario.object is None and finger.scenario.map == "bumps:20:3"


@pytest.mark.parametrize(("earlier", "clear"), [
    ({"localizer_options": {"work": 1000000}}, {"localizer_options": {}}),
    ({"start": [0.1, 0.1, 0.0]}, {"start": None}),
])
def test_a_fingers_setting_left_from_earlier_says_how_to_clear_it(earlier, clear) -> None:
    """A held-out client set localizer options, and long after was refused a hand for them
    ("apply to a finger on a map"), with no word of how to go on: changes merge."""
    finger = DaemonConfig().updated({"scenario": earlier})
    hand = {"object": "keyed", "hand": "two-finger"}
    with pytest.raises(ConfigError, match=f"set {next(iter(clear))} to .* in the same change"):
        finger.updated({"scenario": hand})
    assert finger.updated({"scenario": {**hand, **clear}}).scenario.object == "keyed"


def test_load_reports_missing_and_broken_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[loop\nrate_hz = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    typo = tmp_path / "typo.toml"  # a lab's typo named its key, not its file
    typo.write_text("[scenario]\nradious = 0.008\n")
    with pytest.raises(ConfigError) as err:
        load_config(typo)
    assert str(err.value).startswith(f"{typo}: [scenario] has unknown key(s) radious")


def test_lifecycle_table() -> None:
    lc = Lifecycle()
    with pytest.raises(StateError, match="allowed in: inactive"):
        lc.check("activate")
    lc.apply("configure")
    assert lc.state is State.INACTIVE
    with pytest.raises(StateError, match="no valid reading"):
        lc.require_valid_read()
    lc.mark_read()
    lc.apply("activate")
    lc.apply("fault", "servo 3 overload")
    assert (lc.state, lc.fault) == (State.FAULT, "servo 3 overload")
    for event in ("activate", "deactivate"):
        assert not lc.allowed(event)
    # a held-out lab's client was refused "while fault" and not told the way out
    with pytest.raises(StateError, match=r"while fault; allowed in: inactive \(reset clears"):
        lc.check("activate")
    assert lc.allowed("configure")  # a new backend, perhaps on a new port, clears it too
    lc.apply("reset")
    assert lc.state is State.INACTIVE and lc.fault is None and not lc.valid_read
    # a held-out client was told "(activate first)", which never allows a reset
    with pytest.raises(StateError) as refused:
        lc.check("reset")
    assert str(refused.value) == ("cannot reset while inactive; allowed in: fault (no fault "
                                  "is latched: nothing to reset)")
    # a held-out lab's daemon started without its port: reset named no way out
    with pytest.raises(StateError, match=r"while unconfigured.*send configure, \{\} to try"):
        Lifecycle().check("reset")


def test_hardware_backends_assume_encoder_noise_unless_told() -> None:
    from service.daemon.config import BackendConfig, DaemonConfig, ScenarioConfig
    from service.localization.models import HARDWARE_SENSOR_SIGMA

    assert DaemonConfig().run_settings().sensor_sigma is None
    hw = DaemonConfig(backend=BackendConfig(name="dynamixel"))
    assert hw.run_settings().sensor_sigma == HARDWARE_SENSOR_SIGMA
    told = DaemonConfig(backend=BackendConfig(name="dynamixel"),
                        scenario=ScenarioConfig(sensor_sigma=0.0005))
    assert told.run_settings().sensor_sigma == 0.0005


def test_the_daemon_and_haptic_run_share_their_defaults():
    """ScenarioConfig mirrors RunSettings field by field: its defaults must not drift."""
    from service.daemon.config import ScenarioConfig
    from service.episode.scenario import RunSettings

    assert ScenarioConfig().run_settings() == RunSettings()


@pytest.mark.parametrize(("hand", "said"), [
    ("four-finger", "no hand preset 'four-finger': the presets are"),
    ("three-fingers", "no hand preset 'three-fingers' (did you mean 'three-finger'?)"),
])
def test_a_hand_name_that_is_no_preset_is_told_so(hand, said):
    """A client from the docs alone: `scenario.hand = "four-finger"` was "hand file
    'four-finger' cannot be used: it is missing, unreadable or not a hand description": a
    name shaped like no file is a preset's, and the presets are listed."""
    with pytest.raises(ConfigError) as refused:
        loopback_config({"scenario": {"object": "blob", "hand": hand}})
    assert said in str(refused.value) and "two-finger" in str(refused.value)
    assert "cannot be used" not in str(refused.value)
    assert "planar" not in str(refused.value)  # one finger holds nothing


def test_a_preset_after_a_map_file_needs_no_spacing_undone() -> None:
    """A new user's daemon, left unconfigured by a map file that would not load, refused
    `configure scenario.map=peaks`: "a spacing ... applies to map files, not presets" (the
    file's spacing stayed); the way out, `scenario.spacing=null` beside it, was written
    nowhere."""
    on_file = DaemonConfig().updated({"scenario": {"map": "nosuch.npy", "spacing": 0.001}})
    back = on_file.updated({"scenario": {"map": "peaks"}})
    assert (back.scenario.map, back.scenario.spacing) == ("peaks", None)
    with pytest.raises(ConfigError, match="applies to map files, not presets"):
        on_file.updated({"scenario": {"map": "peaks", "spacing": 0.001}})  # given: refused

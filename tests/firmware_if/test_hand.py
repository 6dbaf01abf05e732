"""Hand descriptions: presets load, and the validator names the field to fix."""

from __future__ import annotations

import copy
import tomllib

import pytest

from firmware_if.errors import HandConfigError
from firmware_if.hand import PRESET_DIR, hand_from_dict, load_hand, presets


def spatial_dict() -> dict:
    return tomllib.loads((PRESET_DIR / "spatial.toml").read_text())


def test_presets_load_and_classify():
    assert set(presets()) >= {"planar", "spatial"}
    spatial, planar = load_hand("spatial"), load_hand("planar")
    assert not spatial.planar and planar.planar
    assert spatial.ids == (1, 2, 3, 4) and spatial.tip_roll is not None
    assert planar.ids == (1, 2)


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d["joints"][0].update(id=300), "joint 'yaw': id must be 0..252"),
    (lambda d: d["joints"][1].update(limits=[1.0, -1.0]), "joint 'shoulder': limits"),
    # a held-out lab's limits in degrees, taken and sent to the servo as -2928 degrees
    (lambda d: d["joints"][1].update(limits=[-97.0, 40.0]),
     "limits \\[-97.0, 40.0\\] reach beyond a whole turn: joint angles are radians"),
    (lambda d: d["joints"][2].update(axis=[0, 0, 0]), "joint 'elbow': axis must not be zero"),
    (lambda d: d["joints"][2].update(axis=[0, 1]), "joint 'elbow': axis must be three"),
    (lambda d: d["joints"][0].update(direction=2), "direction must be 1 or -1"),
    (lambda d: d["joints"][0].update(model="XL320"), "unknown servo model 'XL320'"),
    (lambda d: d["joints"][1].update(id=1),
     "servo ids must be unique, got .*id 1: joint 'yaw' and joint 'shoulder'"),
    (lambda d: d.update(home=[0.0, 5.0, 1.1]), "home angle 5.0 of joint 'shoulder'"),
    (lambda d: d.update(home=[0.0]), "home needs 3 angles"),
    (lambda d: d.update(radius=-1), "radius must be > 0"),
    (lambda d: d.update(baud=12345), "baud must be one of"),
    (lambda d: d.pop("tip"), "missing field 'tip'"),
    (lambda d: d["joints"][0].pop("axis"), "missing field 'axis'"),
    (lambda d: d.update(goal_current_a=0), "goal_current_a"),
    # misspelt safety settings were ignored: the servos ran at the default current, full speed
    (lambda d: d.update(goal_current=0.1), "unknown field 'goal_current'; did you mean "
     "'goal_current_a'?"),
    (lambda d: d.update(profile_velocity=2.0), "unknown field 'profile_velocity'; did you "
     "mean 'profile_velocity_rad_s'?"),
    (lambda d: d.update(wrist=1), "unknown field 'wrist'"),
    (lambda d: d["joints"][1].update(gear=3), "joints\\[1\\]: unknown field 'gear'"),
    (lambda d: d["joints"][1].pop("id"), "joints\\[1\\]: missing field 'id'"),
    (lambda d: d["tip_roll"].update(speed=1), "tip_roll: unknown field 'speed'"),
    (lambda d: [d.pop(k) for k in ("joints", "tip", "radius", "home", "tip_roll")],
     "no fingers; list them as"),
])
def test_validator_names_the_field(edit, message):
    data = copy.deepcopy(spatial_dict())
    edit(data)
    with pytest.raises(HandConfigError, match=message.replace("(", r"\(")):
        hand_from_dict(data, "test")


def test_unknown_preset_and_bad_toml(tmp_path):
    with pytest.raises(HandConfigError, match="no hand preset or file 'nope'"):
        load_hand("nope")
    bad = tmp_path / "bad.toml"
    bad.write_text("radius = [")
    with pytest.raises(HandConfigError, match="not valid TOML"):
        load_hand(str(bad))


def test_file_path_loads(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text((PRESET_DIR / "planar.toml").read_text())
    assert load_hand(str(path)).planar


def test_hand_presets_of_several_fingers():
    two, three = load_hand("two-finger"), load_hand("three-finger")
    assert [f.name for f in two.fingers] == ["left", "right"]
    assert len(three.fingers) == 3
    assert two.ids == (1, 2, 3, 4, 5, 6)
    assert all(f.planar and f.tip_roll is not None for f in two.fingers + three.fingers)
    with pytest.raises(HandConfigError, match="has 2 fingers; this needs a single finger"):
        _ = two.joints
    single = load_hand("planar")
    assert single.fingers[0].joints == single.joints  # a finger is a hand of one


def two_finger_dict() -> dict:
    return tomllib.loads((PRESET_DIR / "two-finger.toml").read_text())


@pytest.mark.parametrize(("edit", "message"), [
    (lambda d: d["fingers"][1]["joints"][0].update(id=1), "servo ids must be unique"),
    (lambda d: d["fingers"][1].update(name="left"), "finger names must be unique"),
    (lambda d: d["fingers"][0]["joints"][0].update(axis=[0, 0, 1]),
     "every joint axis must be \\[0, 1, 0\\]"),
    (lambda d: d["fingers"][0].update(base=[0, 0]), "base must be \\[x, z, angle\\]"),
    (lambda d: d["fingers"][1].pop("radius"), "finger 'right': missing field 'radius'"),
    # a fault campaign's finding: without it the finger sat at the hand's origin, silently
    (lambda d: d["fingers"][1].pop("base"), "finger 'right': missing field 'base'"),
    (lambda d: d["fingers"][1].update(goal_current_a=0.1), "fingers\\[1\\]: unknown field "
     "'goal_current_a'"),  # a hand's setting, not a finger's
    (lambda d: d.update(grasp_centre=[0, "a"]), "grasp_centre"),
    (lambda d: d.update(joints=[]), "not both"),
    # a researcher's hand file: two fingers on one base ran, their tips overlapping
    (lambda d: d["fingers"][1].update(base=d["fingers"][0]["base"]),
     "fingers 'left' and 'right' have bases 0.0 mm apart, less than their tips are wide "
     "together: give each finger its own base"),
    # in millimetres, it was blamed on the object ("narrower than the fingertip radius")
    (lambda d: d["fingers"][0].update(radius=8), "finger 'left': a fingertip radius of 8 m "
     "and links .* long in all are a hand's size in millimetres: a hand file's lengths are "
     "metres"),
])
def test_several_fingers_validator_names_the_field(edit, message):
    data = copy.deepcopy(two_finger_dict())
    edit(data)
    with pytest.raises(HandConfigError, match=message):
        hand_from_dict(data, "test")

"""Issue 12, findings 2 and 4, through hapticd: a lost bus latches a fault (never a crash),
`reset` re-opens it (the emulator restarted at the same path) and `configure` can move to a
new port; after any reset every servo holds what `open` wrote."""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from firmware_if.hand import load_hand
from firmware_if.registers import BAUD_REGISTER
from service.daemon.config import SecurityConfig
from service.daemon.harness import loopback_config, running_node
from service.localization.maps import load_map
from service.wire.client import Client, CommandFailed, Controller, Subscriber
from sim_backend.emulator import ServoBus
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos
from sim_backend.emulator.servo import EmulatedServo

HAND = load_hand("spatial")
MAP = load_map("peaks")
TRUTH = (0.10, 0.10, 2 * 3.141592653589793 * 3 / 11)


def emulator(link: Path | None = None) -> ServoBus:
    plant = FingerPlant(HAND, MAP, TRUTH)
    return ServoBus(hand_bus_servos(HAND, plant), plant=plant,
                    link=None if link is None else str(link)).start()


def options(port: str) -> dict:
    return {"port": port, "hand": "spatial", "cycle_budget_s": 0.05}


@pytest.fixture()
def rig(tmp_path: Path) -> Iterator[tuple]:
    link = tmp_path / "ttyDXL"
    buses = [emulator(link)]
    config = loopback_config({"backend": {"name": "dynamixel", "options": options(str(link))},
                              "scenario": {"noise": True, "max_steps": 60}})
    # a lab rehearsing on the emulator lets clients move to its pseudo-terminals
    config = dataclasses.replace(config, security=SecurityConfig(serial_ports=("/dev/pts/*",)))
    try:
        with running_node(config) as node, \
                Subscriber(node.endpoints["pub"], ["state", "event"]) as sub, \
                Controller(node.endpoints["cmd"], timeout_s=10.0) as ctl:
            yield node, sub, ctl, buses, link
    finally:
        for bus in buses:
            bus.stop()


def explore_until_moving(sub: Subscriber, ctl: Controller) -> None:
    assert sub.wait_for(lambda m: m.topic == "state" and m["state"] == "inactive"
                        and m["fingers"], 10.0)
    ctl.call("activate")
    ctl.call("start_exploration", repeat=True)
    assert sub.wait_for(lambda m: m.topic == "state" and m["moving"], 20.0)


def wait_fault(sub: Subscriber) -> dict:
    """The fault event of a fault mid-episode, after checking what follows it: the episode
    cut short ends with `episode_done` (reason `fault`), then torque is off."""
    fault = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "fault", 10.0)
    assert fault is not None, "no fault event"
    done = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "episode_done", 5.0)
    assert done is not None and done["reason"] == "fault" and not done["converged"]
    # the estimate as of the cut; the step under way when the fault came is not counted
    # (it has no `step` event: episode_done said 5 where the stream held 4)
    assert done["steps"] >= 0 and done["candidates"] >= 1
    state = sub.wait_for(lambda m: m.topic == "state", 5.0)
    assert state["state"] == "fault" and not state["torque_on"] and not state["exploring"]
    return fault.body


def test_killing_the_emulator_mid_exploration_faults_and_reset_recovers(rig) -> None:
    node, sub, ctl, buses, link = rig
    for _round in range(3):  # `haptic bench faults` does this 20 times with processes
        explore_until_moving(sub, ctl)
        buses[-1].stop()  # the emulator dies mid-exploration
        assert "serial port" in wait_fault(sub)["reason"]
        assert ctl.call("ping") == {"pong": True}  # the daemon stays up
        buses.append(emulator(link))  # a new emulator at the same path
        assert ctl.call("reset")["state"] == "inactive"
        assert all(s.get("goal_current") == 149 for s in buses[-1].servos.values())
    explore_until_moving(sub, ctl)  # and it explores again


def test_reset_with_no_bus_keeps_the_fault_and_configure_moves_to_a_new_port(rig) -> None:
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].stop()
    wait_fault(sub)
    with pytest.raises(Exception) as err:
        ctl.call("reset")  # nothing at the port: refused, still faulted
    assert err.value.code == "hardware" and "cannot open" in str(err.value)
    faulted = ctl.status()
    assert faulted["state"] == "fault" and faulted["estimate"] is not None
    buses.append(emulator())  # somewhere else: /dev/pts/N
    result = ctl.call("configure", changes={"backend": {"options": options(buses[-1].port)}})
    assert result["state"] == "inactive"
    assert ctl.call("get_config")["backend"]["options"]["port"] == buses[-1].port
    # a fault campaign's finding: the recovery had dropped the estimate
    assert ctl.status()["estimate"] == faulted["estimate"]
    explore_until_moving(sub, ctl)


def test_new_backend_options_on_the_same_port_reopen_it(rig) -> None:
    """A serial port opens once (`sdk_fixes`, defect 5): the new backend of a configure on
    the same port takes it over from the old one; a new one that fails gives it back."""
    node, sub, ctl, buses, link = rig
    changed = {**options(str(link)), "cycle_budget_s": 0.04}
    assert ctl.call("configure", changes={"backend": {"options": changed}})["state"] == "inactive"
    with pytest.raises(Exception) as err:
        ctl.call("configure", changes={"backend": {"options": {**changed, "hand": "nope"}}})
    assert err.value.code == "bad_config"
    assert ctl.call("get_config")["backend"]["options"]["cycle_budget_s"] == 0.04
    explore_until_moving(sub, ctl)  # the old backend has its port again


def test_configure_moves_to_another_name_of_the_port_it_holds(rig) -> None:
    """A held-out lab moved a running daemon from its port to another name of the same
    device (a link, as /dev/serial/by-id/... is): refused, "another process has it open",
    though only the daemon itself did. The old backend lets the device go first now, under
    either name, and it explores on the new one."""
    node, sub, ctl, buses, link = rig
    device = os.path.realpath(link)
    assert device != str(link)
    for port in (device, str(link)):
        reply = ctl.call("configure", changes={"backend": {"options": options(port)}})
        assert reply["state"] == "inactive"
        assert ctl.call("get_config")["backend"]["options"]["port"] == port
    explore_until_moving(sub, ctl)


def test_a_hardware_error_fault_then_reset_restores_goal_current_and_touch_down(rig) -> None:
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].inject_hardware_error(2, 0x04)  # overheating: servo 2 turns its torque off
    assert "servo 2" in wait_fault(sub)["reason"]
    assert ctl.call("reset")["state"] == "inactive"
    for servo in buses[-1].servos.values():
        assert servo.get("goal_current") == 149 and servo.get("operating_mode") == 5
    explore_until_moving(sub, ctl)  # activate touched down again: no "no surface found"


def test_a_configure_in_fault_clears_a_hardware_error_as_reset_does(rig) -> None:
    """A fault campaign's finding: protocol.md says a configure in fault clears the fault
    as `reset` does, but with a servo's overload latched it answered `hardware` and the
    daemon stayed in fault; only `reset` rebooted the servo."""
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].inject_hardware_error(2, 0x20)  # overload
    assert "servo 2" in wait_fault(sub)["reason"]
    reply = ctl.call("configure", changes={})
    assert reply["state"] == "inactive"
    assert reply["rebooted"] == ["servo 2 reported overload error: rebooted it (find out why "
                                 "before you activate)"]
    assert buses[-1].servos[2].get("hardware_error_status") == 0
    assert buses[-1].servos[2].get("goal_current") == 149
    explore_until_moving(sub, ctl)


def test_a_daemon_started_before_its_bus_says_why_and_configures_later(tmp_path: Path) -> None:
    """A held-out fault check started hapticd before the emulator: `status` said only
    `unconfigured` and `activate` only "cannot activate while unconfigured"; the reason was
    in the log alone."""
    link = tmp_path / "ttyDXL"
    config = loopback_config({"backend": {"name": "dynamixel", "options": options(str(link))}})
    bus = None
    try:
        with running_node(config) as node, Controller(node.endpoints["cmd"]) as ctl:
            status = ctl.status()
            assert status["state"] == "unconfigured" and str(link) in status["configure_error"]
            with pytest.raises(Exception) as err:
                ctl.call("activate")
            assert err.value.code == "bad_state" and str(link) in str(err.value)
            before = ctl.status()["configure_error"]
            with pytest.raises(Exception) as err:  # refused: it changes nothing
                ctl.call("configure", changes={"scenario": {"map": str(tmp_path / "nope.npy")}})
            assert err.value.code == "bad_config"
            assert ctl.status()["configure_error"] == before
            bus = emulator(link)
            assert ctl.call("configure", changes={})["state"] == "inactive"
            assert ctl.status()["configure_error"] is None
            with pytest.raises(Exception) as err:  # a helper's client saw this one set it
                ctl.call("configure", changes={"scenario": {"map": str(tmp_path / "nope.npy")}})
            assert err.value.code == "bad_config"
            assert ctl.status()["configure_error"] is None
    finally:
        if bus is not None:
            bus.stop()


def test_a_bus_that_does_not_open_again_after_a_failed_configure_is_a_named_fault(
        rig, monkeypatch) -> None:
    """A fault campaign's finding: a configure whose new backend failed to open, its servo
    going quiet, released the port and could not open the old backend again either; the
    daemon then latched "read failed: Dynamixel finger is not open: call open() first",
    which names neither the bus nor what to do."""
    from firmware_if.errors import FirmwareError
    from service.daemon import reconfigure

    node, sub, ctl, buses, link = rig
    assert sub.wait_for(lambda m: m.topic == "state" and m["state"] == "inactive", 10.0)

    class Quiet:
        def open(self) -> None:
            raise FirmwareError("servo 5 does not answer a ping")

        def close(self) -> None:
            pass

    def quiet(*_args) -> None:
        raise FirmwareError("servo 5 does not answer a ping")

    monkeypatch.setattr(reconfigure, "make_backend", lambda *args: Quiet())
    monkeypatch.setattr(node.backend, "open", quiet)  # the released old one, too
    with pytest.raises(Exception) as err:
        ctl.call("configure", changes={"backend": {"options": {**options(str(link)),
                                                               "cycle_budget_s": 0.04}}})
    assert "servo 5 does not answer" in str(err.value)
    fault = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "fault", 10.0)
    assert fault is not None
    assert fault["reason"].startswith("the bus did not open again after the configure "
                                      "failed: servo 5 does not answer a ping; once the bus "
                                      "answers, send reset or configure")
    assert ctl.status()["fault"] == fault["reason"]


def test_a_fault_is_logged_as_an_error(rig, caplog) -> None:
    """A lab that keeps the steps out of its log (`--log-level warning`) still finds its
    faults there: the `fault` event and the lifecycle entering it are errors."""
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].stop()
    wait_fault(sub)
    records = [r for r in caplog.records if r.name == "hapticd"
               and (r.getMessage() == "fault"
                    or getattr(r, "fields", {}).get("state") == "fault")]
    assert {r.getMessage() for r in records} == {"fault", "lifecycle"}
    assert all(r.levelno == logging.ERROR for r in records)


def test_a_reset_onto_another_bus_warns_of_servos_the_hand_does_not_use(rig) -> None:
    """A held-out check killed the emulator and started another hand's at the same link:
    `reset` said nothing of servos 5-9 answering beside the hand's, though `configure` would
    have. Once the port itself was lost, what answers when it opens again is looked at."""
    node, sub, ctl, buses, link = rig
    assert sub.wait_for(lambda m: m.topic == "state" and m["fingers"], 10.0)
    assert ctl.call("status")["backend_warnings"] == []
    buses[-1].stop()  # the port vanishes, between episodes
    assert "serial port" in sub.wait_for(
        lambda m: m.topic == "event" and m["event"] == "fault", 10.0)["reason"]
    plant = FingerPlant(HAND, MAP, TRUTH)
    stranger = EmulatedServo(9, position=2048)
    stranger.set("baud_rate", BAUD_REGISTER[HAND.baud])  # as the hand's, so it answers
    buses.append(ServoBus([*hand_bus_servos(HAND, plant), stranger], plant=plant,
                          link=str(link)).start())
    reply = ctl.call("reset")
    assert reply["state"] == "inactive"
    assert len(reply["warnings"]) == 1 and "servo 9 also answers" in reply["warnings"][0]
    assert ctl.call("status")["backend_warnings"] == reply["warnings"]


def test_a_reset_after_a_servo_fault_keeps_the_bus_as_it_was(rig) -> None:
    """A fault that is not the port's (a servo's hardware error) leaves the bus the same:
    reset does not look at it again (0.8 s without a published state) and says nothing."""
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].inject_hardware_error(2, 0x20)  # overload
    assert "servo 2" in wait_fault(sub)["reason"]
    reply = ctl.call("reset")
    assert reply["state"] == "inactive" and reply["warnings"] == []


def test_the_loop_keeps_its_rate_while_a_silent_servo_is_asked_why(rig) -> None:
    """A held-out client: when the servos fell silent, state and replies stopped for
    0.7-1 s (the fault's diagnosis pinged each servo in the tick that latched it, waiting
    0.6 s for late answers). It asks on a thread of its own now: the state stream and
    the replies go on between the lifecycle's turn to fault and the fault event, which
    still names the servo and comes before the episode's end."""
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].fault(2).mute = True  # servo 2 unplugged: every cycle's read fails
    turned = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "lifecycle"
                          and m["state"] == "fault", 10.0)
    assert turned is not None
    assert ctl.call("ping") == {"pong": True}  # answered while the servos are asked
    between = []
    fault = None
    while fault is None:
        msg = sub.recv(5.0)
        assert msg is not None, "no fault event"
        assert not (msg.topic == "event" and msg["event"] == "episode_done"), \
            "the episode's end came before its fault"
        if msg.topic == "event" and msg["event"] == "fault":
            fault = msg.body
        elif msg.topic == "state":
            between.append(msg)
    assert between and all(m["state"] == "fault" for m in between)
    assert "servo 2 does not answer a ping" in fault["reason"], fault["reason"]
    done = sub.wait_for(lambda m: m.topic == "event" and m["event"] == "episode_done", 5.0)
    assert done is not None and done["reason"] == "fault"
    assert "servo 2 does not answer a ping" in ctl.status()["fault"]
    buses[-1].fault(2).mute = False
    assert ctl.call("reset")["state"] == "inactive"
    explore_until_moving(sub, ctl)


def test_the_loop_keeps_its_rate_while_a_reset_asks_a_silent_servo(rig) -> None:
    """A held-out client's `reset` took up to 1.54 s while a servo was silent, and ran in
    the loop's tick: no state and no reply meanwhile. It runs beside the loop now
    (`reset_job`): `status` says it is under way, state and replies go on, and the reply
    still says why it failed; then a reset with the servo back clears the fault."""
    node, sub, ctl, buses, link = rig
    explore_until_moving(sub, ctl)
    buses[-1].fault(2).mute = True
    wait_fault(sub)
    with Client(node.endpoints["cmd"], timeout_s=10.0) as other, \
            ThreadPoolExecutor(1) as asker:
        asking = asker.submit(ctl.call, "reset")
        seen = False
        while not asking.done() and not seen:
            seen = other.status()["resetting"]
        assert seen, "the reset was answered before status ever saw it at work"
        assert sub.wait_for(lambda m: m.topic == "state" and m["state"] == "fault", 1.0)
        assert other.call("ping") == {"pong": True}
        assert other.status()["resetting"], "over before the state and the ping came"
        with pytest.raises(CommandFailed) as refused:
            asking.result()
    assert refused.value.code == "hardware"
    assert "servo 2" in str(refused.value) and ctl.status()["state"] == "fault"
    buses[-1].fault(2).mute = False
    assert ctl.call("reset")["state"] == "inactive"
    assert not ctl.status()["resetting"]

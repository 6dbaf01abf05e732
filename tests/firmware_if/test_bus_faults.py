"""Fault injection on the servo-bus emulator: a lost port, a mute servo, corrupt and late
replies, hardware errors; each latches a fault with torque off, and `clear_fault` recovers
with every servo configured as `open` left it (issue 12, findings 2 and 4)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from firmware_if.backend import StepCommand
from firmware_if.dxl_bus import TORQUE_CHECK_CYCLES
from firmware_if.dynamixel_backend import DynamixelBackend, StepSettings
from firmware_if.errors import FirmwareError, HardwareFault, PortLost
from firmware_if.hand import Hand, load_hand
from firmware_if.registers import REG
from service.episode.runner import execute_step
from service.localization.maps import load_map
from sim_backend.emulator import ServoBus
from sim_backend.emulator.plant import FingerPlant, hand_bus_servos

MAP = load_map("peaks")
HAND = load_hand("spatial")
SETTINGS = StepSettings(cycle_budget_s=0.1)  # generous: these tests run on a busy machine
RAM = [r.name for r in REG.values() if not r.eeprom and r.access == "RW"
       and r.name != "goal_position"]  # the goal follows the joint while torque is off


def emulator(hand: Hand = HAND, link: Path | None = None) -> ServoBus:
    plant = FingerPlant(hand, MAP, (0.1, 0.1, 0.3))
    return ServoBus(hand_bus_servos(hand, plant), plant=plant,
                    link=None if link is None else str(link)).start()


def ram(bus: ServoBus, ids: tuple[int, ...] = HAND.ids) -> dict[tuple[int, str], int]:
    """Every RW RAM register of every servo, as the servos hold them (the backend's own
    read-back is `configure(verify=True)`)."""
    return {(sid, name): bus.servos[sid].get(name) for sid in ids for name in RAM}


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[DynamixelBackend, ServoBus, Path]]:
    link = tmp_path / "ttyDXL"
    bus = emulator(link=link)
    backend = DynamixelBackend(HAND, str(link), SETTINGS)
    backend.open()
    try:
        yield backend, bus, link
    finally:
        backend.close()
        bus.stop()


def test_open_writes_its_settings_to_every_servo(rig) -> None:
    backend, bus, _ = rig
    for servo in bus.servos.values():
        for name, value in backend.servo_settings().items():
            assert servo.get(name) == value, (servo.id, name)
    assert backend.servo_settings()["goal_current"] == 149  # 0.4 A


def test_a_lost_port_latches_a_fault_and_nothing_escapes(rig) -> None:
    backend, bus, _ = rig
    backend.set_torque(True)
    backend.command_step(StepCommand(0.01, 0.0))
    bus.stop()  # the emulator dies: EIO / termios.error on the host side
    state = backend.read_state()
    assert state.fault and "serial port" in state.fault and not state.torque_on
    assert not state.moving  # the step under way ended (blocked)
    assert backend.read_state().fault == state.fault  # the first cause stays
    backend.set_torque(False)  # best effort on a dead port: no exception
    with pytest.raises(HardwareFault) as refused:
        backend.command_step(StepCommand(0.01, 0.0))
    # the fault says how to recover once ("reset ... to recover; reset first" before)
    assert str(refused.value).count("reset") == 1, str(refused.value)


def test_reset_reopens_the_port_on_a_new_emulator_and_reconfigures_it(rig) -> None:
    backend, bus, link = rig
    opened = ram(bus)
    bus.stop()
    assert backend.read_state().fault
    with pytest.raises(PortLost):  # nothing at the port yet: the fault stays
        backend.clear_fault()
    assert backend.read_state().fault
    fresh = emulator(link=link)  # servos at power-on defaults
    try:
        assert fresh.servos[1].get("goal_current") != 149
        backend.clear_fault()
        assert ram(fresh) == opened
        state = backend.read_state()
        assert state.fault is None
        backend.set_torque(True)
        assert not execute_step(backend, StepCommand(0.01, 0.0)).blocked
    finally:
        backend.close()
        fresh.stop()


def test_a_hardware_error_reboot_restores_every_ram_register(rig) -> None:
    """The finding: after the reboot Goal Current read 0 instead of 149, and the finger
    could no longer touch down."""
    backend, bus, _ = rig
    opened = ram(bus)
    backend.set_torque(True)
    bus.inject_hardware_error(2, 0x04)  # overheating: torque off, alert bit set
    state = backend.read_state()
    assert state.fault and "servo 2" in state.fault and "find out why before you reset" in \
        state.fault
    # reboots servo 2: its RAM returns to defaults, then is rewritten
    assert backend.clear_fault() == ["servo 2 reported overheating error: rebooted it (find "
                                     "out why before you activate)"]
    assert bus.servos[2].get("hardware_error_status") == 0
    assert ram(bus) == opened
    backend.set_torque(True)  # touches down again
    assert not execute_step(backend, StepCommand(0.01, 0.0)).blocked


def test_a_servo_id_the_bus_does_not_have_says_what_to_do(tmp_path: Path) -> None:
    """A fault campaign's finding: a wrong id gave only the SDK's "There is no status
    packet!"."""
    link = tmp_path / "ttyDXL"
    bus = emulator(load_hand("planar"), link=link)  # servos 1 and 2; the spatial hand has 1-4
    try:
        backend = DynamixelBackend(HAND, str(link), SETTINGS)
        with pytest.raises(FirmwareError, match=r"servo 3.*haptic bus scan --port .*ids belong "
                           "in the hand file"):
            backend.open()
    finally:
        bus.stop()


def test_a_hardware_error_behind_another_fault_is_named_by_the_reset(rig) -> None:
    """A held-out fault campaign's finding: servo 2 overloaded while a mute servo's fault
    was latched; nothing reported it, and the reset rebooted it without a word."""
    backend, bus, _ = rig
    backend.set_torque(True)
    plan = bus.fault(1)
    plan.mute = True
    for _ in range(SETTINGS.failure_tolerance):
        state = backend.read_state()
    assert state.fault and "servo 1" in state.fault
    bus.inject_hardware_error(2, 0x20)  # overload, behind the latched fault
    plan.mute = False
    assert backend.clear_fault() == ["servo 2 reported overload error: rebooted it (find out "
                                     "why before you activate)"]
    assert bus.servos[2].get("hardware_error_status") == 0


def test_a_servo_that_restarts_by_itself_faults_the_bus(rig) -> None:
    """A held-out fault campaign's finding: a servo rebooted by a brown-out answers as before
    with its torque off, and the finger explored on with a limp joint, every step blocked."""
    backend, bus, _ = rig
    opened = ram(bus)
    backend.set_torque(True)
    bus.servos[2].reboot()
    for _ in range(TORQUE_CHECK_CYCLES + 1):
        state = backend.read_state()
        if state.fault:
            break
    assert state.fault and "servo 2 lost torque" in state.fault and not state.torque_on
    backend.clear_fault()
    assert ram(bus) == opened
    backend.set_torque(True)
    assert not execute_step(backend, StepCommand(0.01, 0.0)).blocked


def test_a_servo_that_restarts_while_torque_is_off_is_set_up_before_torque_on(rig) -> None:
    """A fault campaign's finding: `reboot 2` while the daemon was inactive went unseen (the
    torque check runs while torque should be on), and activating put torque on a servo
    whose goal current and profile were back at their defaults."""
    backend, bus, _ = rig
    opened = ram(bus)
    bus.servos[2].reboot()
    assert ram(bus) != opened  # RAM at defaults
    backend.set_torque(True)
    on = {key: 1 if key[1] == "torque_enable" else value for key, value in opened.items()}
    assert ram(bus) == on
    assert not execute_step(backend, StepCommand(0.01, 0.0)).blocked


@pytest.mark.parametrize("inject", ["mute", "corrupt", "late"])
def test_a_misbehaving_servo_faults_the_bus_and_reset_recovers(rig, inject: str) -> None:
    backend, bus, _ = rig
    opened = ram(bus)
    plan = bus.fault(3)
    if inject == "mute":
        plan.mute = True
    elif inject == "corrupt":
        plan.corrupt = 1000
    else:
        plan.late_s = 0.2  # past every timeout
    for _ in range(SETTINGS.failure_tolerance):
        state = backend.read_state()
    assert state.fault and "consecutive failed cycles" in state.fault
    assert bus.wait_until(lambda: not any(s.torque_on for s in bus.servos.values()))
    if inject == "mute":  # (a late servo would pile up a backlog of stale replies)
        with pytest.raises(FirmwareError, match="check the bus power and every servo's "
                           "cable, then reset again"):
            backend.clear_fault()  # still misbehaving: the fault stays, and what to do
        assert backend.read_state().fault
    plan.mute, plan.corrupt, plan.late_s = False, 0, 0.0
    backend.clear_fault()
    assert backend.read_state().fault is None
    assert ram(bus) == opened


def test_a_reset_with_a_servo_still_answering_late_stays_in_fault(tmp_path: Path) -> None:
    """A held-out fault campaign: with a servo answering after 10 ms (past a cycle's read,
    within the setup's timeout), `reset` answered ok and the bus faulted again 0.2 s
    later. The reset now times every servo's answer and keeps the fault, naming it."""
    settings = StepSettings(cycle_budget_s=0.03)  # a cycle's read waits 15 ms
    with emulator(link=tmp_path / "ttyDXL") as bus, \
            DynamixelBackend(HAND, str(tmp_path / "ttyDXL"), settings) as backend:
        plan = bus.fault(3)
        plan.mute = True
        for _ in range(settings.failure_tolerance):
            state = backend.read_state()
        assert state.fault
        plan.mute, plan.late_s = False, 0.025  # past a cycle's read, within the setup's
        with pytest.raises(HardwareFault, match="reset failed: servo 3 answers a ping "
                           "only after .* reset again once they answer in time"):
            backend.clear_fault()
        assert backend.read_state().fault
        plan.late_s = 0.0
        backend.clear_fault()
        assert backend.read_state().fault is None


def test_one_corrupt_reply_is_forgiven(rig) -> None:
    backend, bus, _ = rig
    bus.fault(1).corrupt = 1
    assert backend.read_state().fault is None
    assert backend.read_state().fault is None
    assert backend.bus.stats.failures >= 1 and bus.stats["corrupted"] == 1


def test_configure_on_a_new_port_is_a_new_bus(rig) -> None:
    backend, bus, _ = rig
    other = emulator()
    try:
        moved = DynamixelBackend(HAND, other.port, SETTINGS)
        moved.open()
        assert moved.read_state().fault is None
        moved.close()
    finally:
        other.stop()


def test_a_hand_file_that_is_not_the_bus_s_is_named(tmp_path: Path) -> None:
    """`--hand planar` on a spatial finger's bus said only "no surface found"."""
    bus = emulator(link=tmp_path / "ttyDXL")
    backend = DynamixelBackend(load_hand("planar"), str(tmp_path / "ttyDXL"), SETTINGS)
    try:
        backend.open()
        with pytest.raises(HardwareFault, match=r"no surface found.*servos 3, 4 also answer "
                           r"on this bus, which hand 'planar' does not use \(ids 1, 2\)"):
            backend.set_torque(True)
    finally:
        backend.close()
        bus.stop()


def test_a_port_lost_while_reset_checks_the_servos_is_a_fault_not_an_os_error(
        rig, monkeypatch) -> None:
    """A held-out client killed the emulator 20-60 ms into a `reset`: the reply was
    `internal` ("SerialException: write failed: [Errno 5]"), the check's pings having gone
    past the bus's guard on port errors."""
    import firmware_if.dynamixel_backend as backend_module

    backend, bus, link = rig
    bus.stop()
    assert backend.read_state().fault
    fresh = emulator(link=link)
    real = backend_module.late_words

    def port_dies_first(dxl_bus):
        fresh.stop()  # the emulator dies just as the reset pings its servos
        return real(dxl_bus)

    monkeypatch.setattr(backend_module, "late_words", port_dies_first)
    with pytest.raises(PortLost, match="serial port"):
        backend.clear_fault()
    assert backend.read_state().fault  # still faulted, and says so
    monkeypatch.setattr(backend_module, "late_words", real)
    again = emulator(link=link)
    try:
        backend.clear_fault()  # a reset onto a new emulator recovers
        assert backend.read_state().fault is None
    finally:
        backend.close()
        again.stop()


def test_a_servo_whose_every_reply_comes_damaged_is_told_from_a_silent_one(rig) -> None:
    """A held-out fault campaign's `corrupt 2 100000` was told "servo 2 does not answer a
    ping: check its cable and power", though its replies were arriving, damaged."""
    backend, bus, _ = rig
    bus.fault(3).corrupt = 100_000
    for _ in range(SETTINGS.failure_tolerance):
        state = backend.read_state()
    assert "servo 3 answers a ping only with damaged replies (bad checksums" in state.fault
    assert "does not answer" not in state.fault
    with pytest.raises(FirmwareError, match="reset failed: a servo's reply came damaged "
                       r"\(servo 3: .*a garbled reply"):
        backend.clear_fault()  # still damaged: the reset names the servo and the garbling
    bus.fault(3).corrupt = 0
    backend.clear_fault()
    assert backend.read_state().fault is None

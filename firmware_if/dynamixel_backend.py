"""The Backend contract on Dynamixel servos: encoders -> kinematics -> fingertip centre.

A step is a compliant Cartesian move: inverse kinematics of (centre + step, a little below
the surface) gives goal positions in current-based position mode, so the tip presses with a
bounded current and rides the surface. Every `read_state` is one bus cycle (sync read, plus a
sync write when the step's state machine has new goals) and advances that state machine:

    move --settled, reached, pressing--> done
    move --settled, reached, not touching--> move deeper (up to `max_press`)
    move --settled, short of the target (a wall) or timed out--> retreat --settled--> done (blocked)

A blocked step leaves the finger where it started, as the simulated finger does.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from firmware_if import kinematics as kin
from firmware_if.backend import FingerState, HandOfOne, StepCommand, check_can_step
from firmware_if.bus_diagnosis import late_words
from firmware_if.dxl_bus import DxlBus, ServoReading
from firmware_if.errors import (
    BusTimeoutError,
    CommunicationError,
    FirmwareError,
    HandConfigError,
    HardwareFault,
    NotReadyError,
    PortLost,
)
from firmware_if.hand import Hand, joint_ticks, load_hand
from firmware_if.registers import (
    CURRENT_BASED_POSITION,
    RAD_PER_TICK,
    amp_to_current,
    rad_s_to_velocity,
    ticks_to_rad,
)

log = logging.getLogger("haptic.servos")


@dataclass(frozen=True)
class StepSettings:
    """How a compliant step is made. Metres and seconds."""

    press: float = 0.004
    """How far below the last contact height each move aims, so the tip keeps pressing."""
    max_press: float = 0.03
    """Give up (blocked) when no surface is found this far below the start height."""
    reach_tolerance: float = 0.001
    """A move counts as reached when the centre is this close to the target in x-y."""
    contact_margin: float = 0.0005
    """In contact when the centre rests this far above where the goal would put it."""
    timeout_s: float = 3.0
    cycle_budget_s: float = 0.01
    failure_tolerance: int = 3

    def __post_init__(self) -> None:
        for name in ("press", "max_press", "reach_tolerance", "contact_margin", "timeout_s",
                     "cycle_budget_s"):
            if not getattr(self, name) > 0:
                raise HandConfigError(f"step setting {name} must be > 0")
        if self.failure_tolerance < 1:
            raise HandConfigError("failure_tolerance must be at least 1")


def check_cycle_budget(cycle_budget_s: object) -> None:
    """HandConfigError unless `cycle_budget_s` is a bus cycle's budget the loop can keep:
    checked where a config names it, before any bus is built (hapticd answered a bad one
    only after its compute process had set the scenario up, 1-2 s on)."""
    if isinstance(cycle_budget_s, bool) or not isinstance(cycle_budget_s, (int, float)) \
            or not 0.002 <= cycle_budget_s <= 0.5:
        raise HandConfigError(f"cycle_budget_s must be 0.002 .. 0.5 s, got {cycle_budget_s!r}")


class DynamixelBackend(HandOfOne):
    """A finger of Dynamixel servos on one bus, implementing `firmware_if.backend.Backend`."""

    def __init__(self, hand: Hand, port: str, settings: StepSettings | None = None) -> None:
        self.hand = hand
        self.port = port
        self.settings = settings or StepSettings()
        self.bus = DxlBus(port, hand.ids, baud=hand.baud,
                          cycle_budget_s=self.settings.cycle_budget_s,
                          failure_tolerance=self.settings.failure_tolerance)
        self._state: FingerState | None = None
        self._q = np.asarray(hand.fingers[0].home, dtype=np.float64)
        self._torque = False
        self._fault: str | None = None
        self._diagnosed: tuple[str, str] | None = None
        """The latest background diagnosis: (the fault's message, with its words)."""
        self._port_lost = False
        """The port itself failed since the bus last opened: what answers when it opens
        again may be another bus (a restarted emulator of another hand, an adapter moved)."""
        self._steps_done = 0
        self._blocked = False
        self._pending_goals: dict[int, int] | None = None
        self._step: _Step | None = None
        self._joints_moving = False
        self._nominal_xy: np.ndarray | None = None
        self.warnings: list[str] = []
        """What the last `open` found worth a word but no refusal (servos on the bus that
        the hand does not use: another device, or the wrong hand file)."""

    @classmethod
    def from_cli(cls, *, port: str, hand: str, radius: float, step: float,
                 cycle_budget_s: float = StepSettings.cycle_budget_s) -> DynamixelBackend:
        """Build from `haptic run` options or hapticd's `[backend] options` (no I/O: that
        happens in `open`). `cycle_budget_s` bounds one bus cycle (a read's timeout is half)."""
        h = load_hand(hand)
        if abs(h.radius - radius) > 1e-9:
            raise HandConfigError(f"--radius {radius} m does not match the hand's fingertip "
                                  f"radius {h.radius} m; pass --radius {h.radius}")
        check_cycle_budget(cycle_budget_s)
        return cls(h, port, StepSettings(cycle_budget_s=cycle_budget_s))

    @property
    def home_centre(self) -> tuple[float, float, float]:
        """Where the hand's home posture puts the fingertip centre (hand frame): the servos'
        power-up posture, under which a fresh `haptic emulate` puts its seed's start."""
        c = kin.forward(self.hand, np.asarray(self.hand.home, dtype=np.float64))
        return (float(c[0]), float(c[1]), float(c[2]))

    def centre_sigma(self) -> np.ndarray:
        """1-sigma error (metres, per hand axis) of the centre from encoder rounding at the
        present posture: half a tick each way per joint, through the Jacobian.

        A localizer fed by this backend needs a sensor tolerance at least a few times this
        (about 0.1 mm for the presets), not the noise-free 0.5 um of the simulator.
        """
        jac = kin.jacobian(self.hand, self._q)
        return RAD_PER_TICK / np.sqrt(12.0) * np.sqrt(np.sum(jac**2, axis=1))

    # -- lifecycle -------------------------------------------------------------------------
    def servo_settings(self) -> dict[str, int]:
        """Every register `open` sets on every servo, in the order written (EEPROM first,
        which needs torque off). A reboot after a hardware error returns RAM to defaults,
        so `clear_fault` writes all of them again."""
        return {"return_delay_time": self.hand.return_delay_us // 2,
                "status_return_level": 2,
                "operating_mode": CURRENT_BASED_POSITION,
                "goal_current": amp_to_current(self.hand.goal_current_a),
                "profile_velocity": rad_s_to_velocity(self.hand.profile_velocity_rad_s)}

    def open(self) -> None:
        self.bus.open()
        try:
            self._set_up()
        except BusTimeoutError as exc:
            self.bus.close()
            raise BusTimeoutError(  # "no reply in time" says only that none answered
                f"{exc}; is every servo of the hand on {self.bus.port_name} at "
                f"{self.bus.baud} baud? `haptic bus scan --port {self.bus.port_name}` lists "
                "those that answer: their ids belong in the hand file", exc.servo_ids) from None
        except BaseException:
            self.bus.close()
            raise

    def _set_up(self, *, look_for_strangers: bool = True) -> None:
        """Torque off, every servo configured and checked, fast reads detected, first read;
        servos on the bus that the hand does not use are a warning (`warnings`). A reset
        keeps the warning its opening gave unless the port itself was lost (what answers
        now may be another hand's bus): the look pings 32 ids and waits a timeout for
        each that is not there, 0.8 s during which `hapticd`'s loop published nothing."""
        self.bus.torque(False)
        self._settings_hold()
        self.bus.detect_fast_read()
        self._state = self._tolerant_read()
        if not look_for_strangers:
            return
        strangers = self._strangers()
        self.warnings = [strangers] if strangers else []
        for warning in self.warnings:  # `haptic run` shows it on stderr, hapticd in its log
            log.warning("warning: %s", warning)

    def _settings_hold(self) -> None:
        """Every servo's settings read back, and written again where one differs, before
        torque goes on: a servo that restarted while torque was off (a brown-out) answers as
        before with its RAM at defaults (goal current, profile), and the torque check
        (`TORQUE_CHECK_CYCLES`) cannot tell while torque is meant to be off."""
        self.bus.configure(self.servo_settings(), verify=True)

    def _tolerant_read(self) -> FingerState:
        """A reading outside the control cycle (the first, the one torque on starts from),
        allowing the bus's usual tolerance of missed cycles."""
        for attempt in range(self.settings.failure_tolerance):
            try:
                return self._read()
            except CommunicationError:
                if attempt == self.settings.failure_tolerance - 1:
                    raise
        raise AssertionError("unreachable")

    def close(self) -> None:
        self._torque = False
        self._step = None
        self.bus.close()
        self._state = None

    def __enter__(self) -> DynamixelBackend:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_torque(self, on: bool) -> None:
        """Torque on holds the present posture, then lowers the tip onto the surface."""
        self._require_open()
        if not on:
            self.bus.torque(False, best_effort=True)
            self._torque = False
            if self._step is not None:
                self._finish(blocked=True)  # a step cut short counts as blocked
            return
        if self._fault:
            raise HardwareFault(f"cannot enable torque while faulted: {self._fault}; reset first")
        self._settings_hold()
        state = self._tolerant_read()  # one missed reply (a loaded host) fails nothing else
        self.bus.write_goals(self._goal_ticks(np.asarray(state.joints)))
        self.bus.torque(True)
        self._torque = True
        self._nominal_xy = None
        self._touch_down()

    def clear_fault(self) -> list[str]:
        """Recover from any fault: open the port afresh (an unplugged adapter or a restarted
        emulator at the same path), reboot servos that report a hardware error (each named
        in the lines returned), and write every setting of `open` to every servo again. If
        that fails the fault stays."""
        self._torque = False
        self._step = None
        self._pending_goals = None
        rebooted: list[str] = []
        words = ""
        for attempt in range(2):  # once more: a late reply still in flight can spoil one
            try:
                self.bus.reopen()
                rebooted += self.bus.reset()
                self._set_up(look_for_strangers=self._port_lost)
                words = late_words(self.bus)  # servos that would fail the next cycles
                break
            except FirmwareError as exc:
                self.bus.close()
                self._fault = f"reset failed: {exc}"
                self._port_lost = self._port_lost or isinstance(exc, PortLost)
                if isinstance(exc, CommunicationError) and attempt == 1:
                    raise CommunicationError(  # what to do, not only what the SDK said
                        f"reset failed: {_what_failed(exc)}, then reset again (`haptic bus "
                        "scan` lists the servos on the port: another hand's bus?)",
                        exc.servo_ids) from exc
                if attempt == 1 or isinstance(exc, PortLost):
                    raise
        if words:
            self._fault = f"reset failed: {words}"
            raise HardwareFault(f"{self._fault}; reset again once they answer in time")
        self._fault, self._port_lost = None, False
        return rebooted

    # -- I/O -------------------------------------------------------------------------------
    def finger_names(self) -> tuple[str, ...]:
        """The hand file's name of its finger."""
        return self.hand.finger_names

    def read_state(self) -> FingerState:
        state = self._poll()
        if state is None:
            return self._stale()
        if self._step is not None:
            self._advance_step(state)
            state = self._stamp(state)
        self._state = state
        return state

    @property
    def diagnosing(self) -> bool:
        """The bus is asking its servos why its cycles failed, on a thread of its own
        (`DxlBus.diagnose_in_background`): the fault's words are not all in yet."""
        return self.bus.diagnosing

    def with_diagnosis(self, text: str) -> str:
        """`text` (a fault's words that quote this backend's) with the diagnosis's words
        added where it quotes the latched message, waiting for a diagnosis under way."""
        self.bus.wait_for_diagnosis()
        self._take_diagnosis()
        return text if self._diagnosed is None else text.replace(*self._diagnosed)

    def _take_diagnosis(self) -> None:
        """A background diagnosis that has ended adds its words to the fault they explain."""
        told = self.bus.take_diagnosis()
        if told is not None:
            self._diagnosed = told
            if self._fault is not None:
                self._fault = self._fault.replace(*told)

    def _poll(self):
        """One bus cycle, sending any goals waiting: the new reading, or None when there is
        none (a fault latched now or before: torque off and a step under way ends blocked;
        or a missed cycle, whose goals go with the next). Shared by every hand of servos."""
        self._take_diagnosis()
        if self._fault and not self.bus.is_open:  # a reset could not reopen the port
            return None
        self._require_open()
        goals, self._pending_goals = self._pending_goals, None
        try:
            return self._read(goals)
        except HardwareFault as exc:
            self._fault = self._fault or str(exc)  # the first cause, not "reset first"
            self._port_lost = self._port_lost or isinstance(exc, PortLost)
            self._torque = False
            if self._step is not None:
                self._finish(blocked=True)  # whoever waits for the step sees it end
            return None
        except CommunicationError:
            if goals:
                self._pending_goals = goals  # resend with the next cycle
            return None

    def command_step(self, step: StepCommand) -> None:
        self._require_open()
        check_can_step(fault=self._fault, torque_on=self._torque, busy=self._step is not None)
        state = self._state or self._read()
        q = np.asarray(state.joints)
        centre = np.asarray(state.centre)
        if self._nominal_xy is None:
            self._nominal_xy = centre[:2].copy()
        # Aim from where the previous step was aimed, not from the quantized reading, so
        # encoder rounding does not accumulate into a drift over many steps.
        xy = self._nominal_xy + np.array([step.dx, step.dy])
        target = np.array([xy[0], xy[1], centre[2] - self.settings.press])
        self._step = _Step(start_q=q, target=target, depth=0.0, t0=time.monotonic(),
                           phase="move")
        self._aim(target, q)

    # -- internals -------------------------------------------------------------------------
    def _aim(self, target: np.ndarray, q0: np.ndarray) -> None:
        ik = kin.inverse(self.hand, target, q0, tolerance=2e-5)
        step = self._step
        assert step is not None
        if not bool(ik.reachable):
            self._retreat(step)
            return
        self._pending_goals = self._goal_ticks(ik.q)
        step.goal_q, step.last, step.cycles = ik.q, None, 0

    def _retreat(self, step: _Step) -> None:
        """Head back to where the step began: it is blocked (unreachable or no contact)."""
        step.phase = "retreat"
        self._pending_goals = self._goal_ticks(step.start_q)
        step.goal_q, step.last, step.cycles = step.start_q, None, 0

    def _advance_step(self, state: FingerState) -> None:
        step = self._step
        assert step is not None
        positions = tuple(state.joints)
        step.cycles += 1
        settled = step.last == positions and not self._joints_moving and step.cycles > 2
        step.last = positions
        timed_out = time.monotonic() - step.t0 > self.settings.timeout_s
        if not settled and not timed_out:
            return
        centre = np.asarray(state.centre)
        if step.phase == "retreat":  # back where the step began (or out of time)
            self._finish(blocked=True)
            return
        reached = np.hypot(*(centre[:2] - step.target[:2])) <= self.settings.reach_tolerance
        goal_z = kin.forward(self.hand, step.goal_q)[2]
        touching = centre[2] > goal_z + self.settings.contact_margin
        if reached and touching:
            self._finish(blocked=False)
        elif reached and not timed_out and step.depth + self.settings.press \
                <= self.settings.max_press:
            step.depth += self.settings.press
            step.target = step.target - np.array([0.0, 0.0, self.settings.press])
            self._aim(step.target, np.asarray(state.joints))
        else:
            step.t0 = time.monotonic()
            self._retreat(step)

    def _finish(self, blocked: bool) -> None:
        step = self._step
        if not blocked and step is not None:
            self._nominal_xy = step.target[:2].copy()
        self._steps_done += 1
        self._blocked = blocked
        self._step = None

    def _touch_down(self) -> None:
        """Press straight down until the tip rests on the surface (blocking, bounded)."""
        self.command_step(StepCommand(0.0, 0.0))
        deadline = time.monotonic() + self.settings.timeout_s * 4
        done = self._steps_done
        while self._steps_done == done and time.monotonic() < deadline and not self._fault:
            self.read_state()
        self._steps_done = done  # touching down is not a step
        no_surface, self._blocked = self._blocked, False
        if self._fault:
            raise HardwareFault(self._fault)
        if no_surface:  # what `open` found on the bus may say why (`warnings`)
            raise HardwareFault(f"no surface found within {self.settings.max_press} m below "
                                "the fingertip; move the hand closer and retry"
                                + "".join(f"; {w}" for w in self.warnings))

    def _strangers(self) -> str:
        """Words for servos that answer on this bus but are not the hand's: a hand file
        that is not this bus's (`--hand planar` on a spatial finger, a two-finger hand on
        a three-finger bus) moves joints whose tip never reaches the surface, and said only
        "no surface found", or ran on the wrong kinematics without a word."""
        try:
            others = sorted(set(self.bus.scan(range(32))) - set(self.hand.ids))
        except FirmwareError:
            return ""
        if not others:
            return ""
        return (f"servo{'s' if len(others) > 1 else ''} {', '.join(map(str, others))} "
                f"also answer{'' if len(others) > 1 else 's'} on this bus, which hand "
                f"'{self.hand.name}' does not use (ids {', '.join(map(str, self.hand.ids))}): "
                "is it the right hand?")

    def _goal_ticks(self, q: np.ndarray) -> dict[int, int]:
        return joint_ticks(self.hand.joints, q)

    def _read(self, goals: dict[int, int] | None = None) -> FingerState:
        readings = self.bus.cycle(goals)
        return self._state_from(readings)

    def _state_from(self, readings: dict[int, ServoReading]) -> FingerState:
        q = np.array([ticks_to_rad(readings[j.id].position, j.zero_ticks, j.direction)
                      for j in self.hand.joints])
        self._q = q
        self._joints_moving = any(readings[j.id].velocity for j in self.hand.joints)
        centre = kin.forward(self.hand, q)
        roll = self.hand.tip_roll
        tip_roll = None if roll is None else ticks_to_rad(readings[roll.id].position,
                                                          roll.zero_ticks, roll.direction)
        return self._stamp(FingerState(t_ns=time.monotonic_ns(),
                                       centre=(float(centre[0]), float(centre[1]),
                                               float(centre[2])),
                                       joints=tuple(float(a) for a in q), tip_roll=tip_roll))

    def _stamp(self, state: FingerState) -> FingerState:
        return FingerState(t_ns=state.t_ns, centre=state.centre, moving=self._step is not None,
                           blocked=self._blocked, steps_done=self._steps_done,
                           joints=state.joints, tip_roll=state.tip_roll,
                           torque_on=self._torque, fault=self._fault)

    def _stale(self) -> FingerState:
        """The last good reading, restamped: a missed cycle does not move the finger."""
        if self._state is None:
            raise NotReadyError("no valid reading from the bus yet")
        return self._stamp(self._state)

    def _require_open(self) -> None:
        if not self.bus.is_open:
            raise NotReadyError("Dynamixel finger is not open: call open() first")




@dataclass
class _Step:
    start_q: np.ndarray
    target: np.ndarray
    depth: float
    t0: float
    phase: str
    goal_q: np.ndarray | None = None
    last: tuple[float, ...] | None = None
    cycles: int = 0
    """Bus cycles since the last goals were sent."""


def _what_failed(exc: CommunicationError) -> str:
    """A reset's words for a servo it could not set up: silent, or answering garbled (a
    held-out check's servo whose every reply came damaged was told it "does not
    answer")."""
    if isinstance(exc, BusTimeoutError):
        return f"a servo does not answer ({exc}); check the bus power and every servo's cable"
    return (f"a servo's reply came damaged ({exc}); check every servo's cable and connectors "
            "(noise, a loose contact) and that the servos use the bus's baud")

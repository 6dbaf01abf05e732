"""Poses, beliefs and outcomes as a person reads them: millimetres, degrees, percentages.

`haptic run`, `haptic explore` and `haptic watch` print through these, so one episode
reads the same whichever way it ran. Only the standard library is imported.
"""

from __future__ import annotations

import math
import re
import signal
from collections.abc import Sequence
from typing import Any

NO_SAFE_MOVE = ("no safe move left (under a pose the readings still allow, every roll "
                "and turn in reach would weaken the grasp below its threshold)")
"""Why a hand's episode stopped undecided (`stuck`): an honest "not yet", not a fault."""

EXIT_FAULT = 3
"""`haptic run`'s exit status when the servos faulted mid-run (2 is a bad option or file,
1 a wrong pose or a drop): a script can tell the hardware from its own mistakes."""


DAEMON_WAY_OUT = re.compile(r"(,? then|[;,]) reset\b(?! failed)[^;.?]*")
"""A fault's advice to reset (`hapticd`'s way out: `reset` again, `reset first`, `reset (or
configure another port) to recover`), which a command that has ended cannot take."""


def fault_cause(fault: str) -> str:
    """A latched fault in a command's words: its own cause, without the advice for a
    daemon (`reset`, `configure`) that a command that has ended cannot take."""
    return "; ".join(part for part in DAEMON_WAY_OUT.sub("", fault).split("; ")
                     if part and not part.startswith(("torque off", "torque is off")))


def command_record(report: Any) -> dict[str, Any]:
    """An episode's JSON as a command writes it (`--json`): its fault in the command's
    words (a held-out campaign read "reset to recover" in a `haptic run` file)."""
    data = report.to_json()
    if data.get("fault"):
        data["fault"] = fault_cause(data["fault"])
    return data


def fault_result(fault: str, steps: int) -> str:
    """The result line of a run a latched fault cut, in a command's words (`fault_cause`)."""
    cause = fault_cause(fault)
    return (f"stopped by a hardware fault during step {steps + 1}, torque off: {cause}. "
            f"Fix what it names (the servo's cable and power, the port) and run again; "
            f"the {steps_text(steps)} before it stand")


def interrupted_result(signal_name: str, steps: int) -> str:
    """The result line of a run a signal cut (`runner.kept_on_interrupt`)."""
    if steps == 0:
        return f"interrupted by {signal_name} before its first step"
    return f"interrupted by {signal_name} after {steps_text(steps)}; what they found stands"


def interrupted_status(signal_name: str) -> int:
    """The exit status of a command a signal cut: 128 + its number, as a shell's."""
    return 128 + int(signal.Signals[signal_name])


def steps_text(count: int) -> str:
    """'1 step', '8 steps'."""
    return f"{count} step{'' if count == 1 else 's'}"


def mm(value: float | None, spec: str = ".1f") -> str:
    return "?" if value is None or not math.isfinite(value) else f"{value * 1e3:{spec}} mm"


def degrees(radians: float) -> float:
    """A heading in [0, 360) degrees, rounded to 0.1 so that -1e-9 reads 0.0, never 360.0."""
    return round(math.degrees(radians), 1) % 360


def pose_text(pose: Sequence[float] | None, second: str = "y") -> str:
    """(x, y, heading) in m, m, rad as 'x  120.00 mm  y   80.00 mm  heading  30.0 deg'; an
    object in a hand's plane is (x, z, heading): `second` 'z'."""
    if pose is None:
        return "none"
    x, y, heading = (float(v) for v in pose)
    return (f"x {x * 1e3:7.2f} mm  {second} {y * 1e3:7.2f} mm  "
            f"heading {degrees(heading):6.1f} deg")


def quality_text(predicted: float | None, true: float | None) -> str:
    """A hand's grasp quality: the policy's prediction and, in simulation, the truth."""
    if predicted is None and true is None:
        return "quality ?"
    text = "quality" if predicted is None else f"quality predicted {predicted:5.2f} N"
    return text if true is None else f"{text} (true {true:5.2f} N)"


def belief_text(position_sd: float | None, heading_sd: float | None,
                mode_mass: float | None) -> str:
    """How sure the localizer is: the spread of its hypotheses and its leading mode's
    probability (comparable across localizers, unlike a count of hypotheses)."""
    if position_sd is None or not math.isfinite(position_sd):
        spread = "spread unbounded"  # the fit may slide: its readings lie on a plain
    else:  # a direction the readings do not see yet has a spread of no meaning in numbers
        # (a helper read "spread 514850229.0 mm / 74956147.2 deg")
        spread = ("spread over 1 m" if position_sd > 1.0 else f"spread {mm(position_sd)}")
        if heading_sd is not None and math.isfinite(heading_sd):
            spread += (" / over 180 deg" if heading_sd > math.pi
                       else f" / {math.degrees(heading_sd):.1f} deg")
    if mode_mass is None or not math.isfinite(mode_mass):
        return spread
    return f"{spread}, leading mode {percent(mode_mass)} %"


def percent(share: float) -> str:
    """A share as a whole percentage, but never rounded up to 100 when short of it: a
    held-out check read "(100 %)" beside "its share 99.6 % ... of the 99.9 % needed"."""
    p = 100 * share
    if 99.5 <= p < 100:
        return f"{math.floor(p * 100) / 100:.2f}".rstrip("0").rstrip(".")
    return f"{p:.0f}"


OTHERS_NAMED = 0.05
"""Least share left beyond the two poses named that an ambiguity names too, as "other
poses"."""


def why_not_converged(*, candidates: int, steps: int, max_steps: int,
                      pose: Sequence[float] | None, mode_mass: float | None,
                      runner_up: Sequence[float] | None,
                      runner_up_mass: float | None, second: str = "y",
                      where: str = "on this map", held_back: str = "") -> str:
    """One sentence on why an episode ended without declaring a pose (`second`: the name
    of a pose's second coordinate, `z` for an object in a hand's plane; `where` the poses
    lie; `held_back`: the localizer's own words for what held the declaration back, if it
    gave them)."""
    if candidates == 0 or pose is None:
        return f"every hypothesis was eliminated: the readings fit no pose {where}"
    parts = []
    if steps >= max_steps:
        parts.append(f"out of steps ({steps} of at most {max_steps})")
    lead = "" if mode_mass is None else f" ({percent(mode_mass)} %)"
    if held_back and (runner_up is None or runner_up_mass is None or runner_up_mass < 0.005):
        parts.append(f"the leading pose {pose_text(pose, second=second)}{lead} is not yet "
                     f"confirmed: {held_back}")
    elif runner_up is not None and runner_up_mass is not None and runner_up_mass < 0.005:
        parts.append(f"the leading pose {pose_text(pose, second=second)}{lead} is not yet "
                     "confirmed: its fit to every reading, its spread, or another pose "
                     f"{where} that fits nearly as well holds it back")
    elif runner_up is not None:
        share = "" if runner_up_mass is None else f" ({percent(runner_up_mass)} %)"
        poses = [f"{pose_text(pose, second=second)}{lead}",
                 f"{pose_text(runner_up, second=second)}{share}"]
        if (runner_up_mass or 0.0) > (mode_mass or 0.0):  # the likelier first: a leader
            poses.reverse()  # whose rival fits better once both are fitted weighs 0 %
        rest = 1.0 - (mode_mass or 0.0) - (runner_up_mass or 0.0)
        if mode_mass is not None and runner_up_mass is not None and rest >= OTHERS_NAMED:
            poses.append(f"other poses ({percent(rest)} %)")  # a held-out check read "between
            # A (8 %) and B (8 %)", as if two poses shared what 84 % said was anywhere
        parts.append(f"still ambiguous between {', '.join(poses[:-1])} and {poses[-1]}")
    else:
        parts.append(f"the leading pose {pose_text(pose, second=second)}{lead} is not yet "
                     "clear of the rest")
    return "; ".join(parts)


def hand_step_text(step: dict) -> str:
    """One step of a hand as `haptic run --object --json` records it (and `hapticd` streams
    it): which finger rolled or whether all turned the object, how sure the estimate is (as
    a finger's step says it; a recording made before steps carried it: the hypotheses
    left), the grasp quality the policy predicted and (simulation) the true one, the least
    true quality during the step where it dipped below where it ended, the update's
    time."""
    what = (f"finger {step['finger']} rolls" if step["kind"] == "explore"
            else "all turn the object")
    if step["blocked"]:
        what += " (blocked)"
    predicted, quality = step.get("predicted_quality"), step.get("quality")
    least = step.get("least_quality")
    dipped = quality is not None and least is not None and least < quality - 0.005
    belief = (belief_text(step["position_sd"], step["heading_sd"], step["mode_mass"])
              if "mode_mass" in step else f"candidates {step['candidates']:5d}")
    return (f"step {step['index']:3d}  {what:<26}  {belief:<44}  "
            f"{'' if predicted is None else f'predicted {_newtons(predicted)}  '}"
            f"{'' if quality is None else f'quality {_newtons(quality)}  '}"
            f"{f'(least {_newtons(least)})  ' if dipped else ''}"
            f"{step['compute_ms']:6.2f} ms")


def _newtons(value: float | None) -> str:
    return "  ?   N" if value is None or not math.isfinite(value) else f"{value:5.2f} N"

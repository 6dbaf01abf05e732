"""How beliefs read: a spread no reading bounds is said in words, not in nine digits."""

import math

import pytest

from tools.words import belief_text, fault_result, percent


def test_a_spread_no_reading_bounds_reads_in_words():
    """A helper read "spread 514850229.0 mm / 74956147.2 deg" while a raised text's plain
    left a direction unseen, and "476.2 deg" at another step."""
    assert belief_text(514850.229, 1.3e6, 0.2) == \
        "spread over 1 m / over 180 deg, leading mode 20 %"
    assert belief_text(0.00046, math.radians(0.43), 1.0) == \
        "spread 0.5 mm / 0.4 deg, leading mode 100 %"
    assert belief_text(0.2505, math.radians(476.2), None) == "spread 250.5 mm / over 180 deg"
    assert belief_text(float("inf"), None, None) == "spread unbounded"


def test_a_rival_of_no_weight_is_not_called_an_ambiguity():
    """'still ambiguous between X (100 %) and Y (0 %)' named no ambiguity: the leader was
    held back by its fit, its spread or a pose found on the whole map."""
    from tools.words import why_not_converged

    text = why_not_converged(candidates=10, steps=40, max_steps=40, pose=(0.1, 0.2, 0.3),
                             mode_mass=0.9999, runner_up=(0.0, 0.0, 0.0),
                             runner_up_mass=0.0001)
    assert "ambiguous" not in text and "not yet confirmed" in text
    text = why_not_converged(candidates=10, steps=40, max_steps=40, pose=(0.1, 0.2, 0.3),
                             mode_mass=0.7, runner_up=(0.0, 0.0, 0.0), runner_up_mass=0.3)
    assert "still ambiguous between" in text and "(30 %)" in text


def test_an_ambiguity_names_the_likelier_pose_first():
    """A held-out check read 'still ambiguous between X (0 %) and Y (48 %)' on a map with
    an exact half turn: the leader's rival fitted better once both were fitted."""
    from tools.words import why_not_converged

    text = why_not_converged(candidates=10, steps=60, max_steps=60, pose=(0.131, 0.048, 4.05),
                             mode_mass=0.0, runner_up=(0.068, 0.151, 0.91),
                             runner_up_mass=0.48)
    first, second = text.split("still ambiguous between ")[1].split(", ")
    assert "x   68.00 mm" in first and first.endswith("(48 %)")
    assert second.endswith("(0 %) and other poses (52 %)")


def test_an_ambiguity_says_how_much_lies_beyond_the_two_poses_it_names():
    """A held-out check read "still ambiguous between A (8 %) and B (8 %)": the other 84 %
    was on poses it did not name."""
    from tools.words import why_not_converged

    spread = why_not_converged(candidates=10, steps=60, max_steps=60, pose=(0.1, 0.0, 0.0),
                               mode_mass=0.08, runner_up=(0.0, 0.1, 1.0),
                               runner_up_mass=0.08)
    assert spread.endswith("(8 %) and other poses (84 %)")
    two = why_not_converged(candidates=10, steps=60, max_steps=60, pose=(0.1, 0.0, 0.0),
                            mode_mass=0.6, runner_up=(0.0, 0.1, 1.0), runner_up_mass=0.38)
    assert "other poses" not in two and two.endswith("(38 %)")


def test_a_localizer_that_says_what_held_it_back_is_quoted():
    from tools.words import why_not_converged

    text = why_not_converged(candidates=10, steps=60, max_steps=60, pose=(0.1, 0.0, 0.0),
                             mode_mass=1.0, runner_up=None, runner_up_mass=0.0,
                             held_back="its spread: position sd 0.90 mm, of at most 0.80 mm")
    assert text.endswith("is not yet confirmed: its spread: position sd 0.90 mm, of at most "
                         "0.80 mm")


@pytest.mark.parametrize(("fault", "cause"), [
    ("hand is faulted: bus on /dev/pts/3: serial port /dev/pts/3 failed (fast sync read: "
     "[Errno 5] Input/output error); torque is off as far as the bus allows; reset (or "
     "configure another port) to recover", "serial port /dev/pts/3 failed"),
    ("the finger faulted during a step: bus on /dev/pts/3: 3 consecutive failed cycles; then "
     "the serial port itself failed (x): its adapter unplugged, or the emulator stopped? "
     "Reconnect it, then reset (or configure another port); torque off sent to every servo, "
     "reset to recover", "or the emulator stopped? Reconnect it."),
    ("finger is faulted: servo 5 does not answer a ping: check its cable and power; reset "
     "first", "servo 5 does not answer a ping: check its cable and power."),
])
def test_a_run_cut_by_a_fault_names_its_cause_without_the_daemons_way_out(fault, cause):
    """`haptic run` has ended when it says so: a `reset` is `hapticd`'s (a held-out check
    was told to reset a run that no longer existed)."""
    words = fault_result(fault, 4)
    assert cause in words and "reset" not in words and "recover" not in words
    assert "during step 5" in words and "the 4 steps before it stand" in words


def test_one_step_is_one_step():
    """A held-out hand localized "in 1 steps"."""
    from tools.words import steps_text

    assert (steps_text(1), steps_text(0), steps_text(8)) == ("1 step", "0 steps", "8 steps")


@pytest.mark.parametrize("share, said", [(0.996, "99.6"), (0.99999, "99.99"), (1.0, "100"),
                                         (0.5, "50"), (0.994, "99")])
def test_a_share_short_of_all_is_never_said_to_be_100_percent(share, said):
    """A held-out check read "(100 %)" beside "its share 99.6 % ... of the 99.9 % needed"."""
    assert percent(share) == said


def test_a_hand_step_says_how_sure_the_estimate_is_as_a_finger_step_does():
    """A hand's step lines gave a count of hypotheses, where a finger's give the spread and
    the leading mode's share; a recording made before steps carried them still reads."""
    from tools.words import hand_step_text

    step = {"index": 4, "kind": "explore", "finger": 1, "blocked": False,
            "predicted_quality": 1.2, "quality": 1.5, "least_quality": 1.5,
            "candidates": 230, "compute_ms": 1.5}
    old = hand_step_text(step)
    assert "candidates   230" in old and "leading mode" not in old
    new = hand_step_text({**step, "position_sd": 0.0004, "heading_sd": math.radians(0.5),
                          "mode_mass": 0.92})
    assert "spread 0.4 mm / 0.5 deg, leading mode 92 %" in new and "candidates" not in new

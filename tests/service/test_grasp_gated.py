"""The grasp-gated policy: the gate is what keeps the object in the hand."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_if.hand import load_hand
from service.episode.hand_episode import simulate_hand
from service.episode.hand_scenario import HandSettings
from service.errors import ConfigError
from service.localization.grasp import GraspSpec, joint_torque
from service.localization.localizers.base import Hypotheses
from service.localization.objects.field import contact_field
from service.localization.objects.presets import preset_object
from service.localization.policies import grasp_gated
from service.localization.policies.grasp_gated import GraspGatedPolicy, HandView
from service.localization.policies.guarded_poses import (
    COVER,
    COVER_LENGTH,
    FLOOR_SDS,
    SPREAD_CAP,
    spread_floor,
    with_cover,
    with_spread,
)
from service.localization.policies.hand_view import best_allowed
from sim_backend.hand import HandSimConfig, SimulatedHand

DATA = Path(__file__).parent / "data"
HAND = load_hand("two-finger")
OBJECT = preset_object("blob:2")
SPEC = GraspSpec()


def explore_knowing_the_pose(gate: bool, steps: int = 25) -> SimulatedHand:
    """Let the policy drive the simulated hand with the true pose as its only hypothesis."""
    sim = SimulatedHand(HAND, OBJECT, HandSimConfig(pose=(0.001, -0.001, 0.7)),
                        np.random.default_rng(0))
    sim.open()
    sim.set_torque(True)
    policy = GraspGatedPolicy(gate=gate)
    field = contact_field(OBJECT)
    for _ in range(steps):
        state = sim.read_hand()
        view = HandView(hypotheses=Hypotheses(np.array([sim.pose]), np.ones(1)),
                        centres=np.array([[f.centre[0], f.centre[2]] for f in state.fingers]),
                        joints=tuple(np.asarray(f.joints) for f in state.fingers),
                        field=field, fingers=HAND.fingers,
                        torque=joint_torque(HAND.goal_current_a, "XM430-W350"), grasp=SPEC,
                        step_length=0.003, sigma=2e-4)
        decision = policy.decide(view)
        if decision.command is None:
            break
        if gate:
            assert decision.predicted_quality >= SPEC.threshold_n
        sim.command_hand(decision.command)
        if sim.read_hand().dropped:
            break
    return sim


def test_the_gate_holds_the_object_and_without_it_the_object_drops():
    gated = explore_knowing_the_pose(gate=True)
    assert not gated.read_hand().dropped
    assert gated.min_quality >= SPEC.margin_n
    assert explore_knowing_the_pose(gate=False).read_hand().dropped


@pytest.mark.parametrize(("quality", "weights", "safe"), [
    ([0.5, 0.6], [0.5, 0.5], True),           # above the threshold everywhere
    ([0.35, 0.6], [0.5, 0.5], False),         # a likely pose goes below it
    ([0.39, 0.6], [0.01, 0.99], True),        # an unlikely one may, within the risk
    ([0.24, 0.6], [0.01, 0.99], False),       # but hardly ever near the margin
])
def test_the_gate_weighs_the_plausible_poses(quality, weights, safe):
    policy = GraspGatedPolicy()
    policy._now = np.array([0.45, 0.7])  # the grasp as it is, under each pose
    view = HandView(hypotheses=Hypotheses(np.zeros((2, 3)), np.array(weights)),
                    centres=np.zeros((2, 2)), joints=(), field=None, fingers=(), torque=0.5,
                    grasp=GraspSpec(threshold_n=0.4), step_length=0.003, sigma=2e-4)
    assert policy._safe(view, np.array(quality), np.array(weights)) is safe


@pytest.mark.parametrize(("mode_of", "safe"), [([0, 0, 1], False), ([0, 1, 1], True),
                                               ([-1, -1, -1], True)])
def test_a_pose_near_the_margin_puts_its_whole_mode_at_risk(mode_of, safe):
    """Three fingers on a held-out five-pointed star (seed 37): the two poses beside the
    truth predicted 0.24 and 0.19 N at 0.15 % of the weight between them, their mode held
    17 %, and the object dropped at 0.18 N. A mode's poses sample one uncertainty; one of
    them near the margin puts the whole mode's weight at risk."""
    policy = GraspGatedPolicy()
    weights = np.array([0.001, 0.2, 0.799])
    policy._now = np.array([0.7, 0.7, 0.7])
    policy._mode_of = np.array(mode_of)
    view = HandView(hypotheses=Hypotheses(np.zeros((3, 3)), weights),
                    centres=np.zeros((3, 2)), joints=(), field=None, fingers=(), torque=0.5,
                    grasp=GraspSpec(threshold_n=0.4), step_length=0.003, sigma=2e-4)
    # the light pose 0 comes near the margin (0.2 + 0.25 * 0.2 = 0.25 N); the rest hold
    assert policy._safe(view, np.array([0.22, 0.6, 0.6]), weights) is safe


def test_three_fingers_hold_a_five_pointed_star_where_the_quality_falls_steeply():
    """A helper's held-out outline (r = 21 + 4 cos(5t + 0.3) mm, `data/five_pointed_star.csv`),
    seed 37: a roll after a turn took the grasp from 0.88 to 0.18 N (the test above)."""
    star = Path(__file__).parent / "data" / "five_pointed_star.csv"
    report = simulate_hand(HandSettings(object=str(star), hand="three-finger", seed=37,
                                        noise=True, max_steps=12))
    assert not report.result.dropped and report.min_quality > SPEC.margin_n


@pytest.mark.parametrize(("outline", "seed", "steps"), [
    ("notched_disc.csv", 0, 6), ("notched_disc.csv", 19, 12),
    ("rounded_rectangle_3_to_1.csv", 27, 4)])
def test_two_fingers_fear_the_worlds_worst_near_the_margin(outline, seed, steps):
    """Two fingers on a helper's held-out outlines (a 48 mm disc with a 4 mm notch; a 54 x 18
    mm rectangle with 4 mm corners, `data/`): the model's quality held under every plausible
    pose, the world's fell below the margin. A tip rested on the notch's edge where the model
    bridged it (the disc, seed 19: 3.72 N in the model under the truth itself), or the world's
    outline turned a contact's normal by about one sd of its slope (the rectangle, seed 27:
    0.21 N in the model under the truth, -0.07 N with one normal turned 0.8 degrees; the
    disc, seed 0, is held only with the normals turned too). Near the margin the gate now
    judges each move at the world's worst (`WORLD_TILT`, and a tip beside a kink resting
    where it holds least); each of these dropped the object before."""
    path = Path(__file__).parent / "data" / outline
    report = simulate_hand(HandSettings(object=str(path), hand="two-finger", seed=seed,
                                        noise=True, max_steps=steps))
    assert not report.result.dropped and report.min_quality > SPEC.margin_n


@pytest.mark.parametrize(("guard", "safe"), [([False, True, False], False),
                                             ([False, False, True], True)])
def test_the_gate_holds_for_the_leaders_spread(guard, safe):
    """A weightless neighbour that stands for the leader's own spread is guarded as a
    likely pose; another weightless pose is not."""
    policy = GraspGatedPolicy()
    policy._now = np.array([0.45, 0.7, 0.7])
    policy._guard = np.array(guard)
    view = HandView(hypotheses=Hypotheses(np.zeros((3, 3)), np.array([1.0, 0.0, 0.0])),
                    centres=np.zeros((2, 2)), joints=(), field=None, fingers=(), torque=0.5,
                    grasp=GraspSpec(threshold_n=0.4), step_length=0.003, sigma=2e-4)
    quality = np.array([0.5, 0.35, 0.5])  # the second pose loses the threshold
    assert policy._safe(view, quality, np.array([1.0, 0.0, 0.0])) is safe


@pytest.mark.parametrize(("guard_quality", "likely_quality", "safe"), [
    (0.8, 1.1, True),    # a guard below the threshold, above the margin's buffer
    (0.35, 1.1, False),  # a guard within the buffer (0.2 + 0.25 x 0.8 = 0.4 N)
    (0.8, 0.9, False),   # a likely pose below the threshold, as ever
])
def test_as_a_last_resort_the_guards_are_kept_only_off_the_margin(guard_quality,
                                                                   likely_quality, safe):
    policy = GraspGatedPolicy()
    policy._now = np.array([1.5, 1.2])
    policy._guard = np.array([False, True])
    weights = np.array([1.0, 0.0])
    view = HandView(hypotheses=Hypotheses(np.zeros((2, 3)), weights),
                    centres=np.zeros((2, 2)), joints=(), field=None, fingers=(), torque=0.5,
                    grasp=GraspSpec(margin_n=0.2, threshold_n=1.0), step_length=0.003,
                    sigma=2e-4)
    quality = np.array([likely_quality, guard_quality])
    assert policy._safe(view, quality, weights, last_resort=True) is safe
    assert not policy._safe(view, quality, weights)  # the guard below the threshold


def test_three_fingers_leave_a_start_whose_edge_poses_forbade_every_move():
    """rounded:23, seed 23, three fingers: the true grasp held 11.6 N, but the gate's guards
    at the edge of what the start allows (1.06-1.4 N) forbade every roll and every turn,
    and the episode ended where it began."""
    report = simulate_hand(HandSettings(object="rounded:23", hand="three-finger", seed=23,
                                        noise=True, max_steps=3))
    assert len(report.result.steps) == 3 and not report.result.dropped


def test_each_modes_neighbours_lie_two_spreads_away_at_most_the_cap():
    poses = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 2.0], [0.001, 0.0, 1.02]])
    weights = np.array([0.7, 0.2, 0.1])  # the third is in the leader's mode
    out, w, guard = with_spread(poses, weights, (0.0005, np.deg2rad(10.0)))
    assert len(out) == 15 and guard.tolist() == [False] + [True] * 12 + [False, False]
    assert w.tolist() == [0.7] + [0.0] * 12 + [0.2, 0.1]
    for mode, around in ((poses[0], out[1:7]), (poses[1], out[7:13])):
        assert np.allclose(np.abs(around[:2, 2] - mode[2]), 2 * SPREAD_CAP[1])
        assert np.allclose(np.abs(around[2:, :2] - mode[:2]).max(axis=1), 0.001)
    assert len(with_spread(poses, weights, (float("nan"), 0.1))[0]) == 3


def test_a_mode_too_light_to_matter_gets_no_neighbours():
    poses = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 2.0]])
    out, _, guard = with_spread(poses, np.array([0.999, 0.001]), (0.0005, 0.01))
    assert len(out) == 8 and guard.sum() == 6


def test_a_leader_a_few_degrees_off_does_not_drop_the_object():
    """rounded:9, seed 9, three fingers: the estimate 2.7 degrees off near a rounded corner
    predicted a sound grasp where the truth's was at the margin; the object dropped."""
    report = simulate_hand(HandSettings(object="rounded:9", hand="three-finger", seed=9,
                                        noise=True, max_steps=30))
    assert not report.result.dropped and not report.score.wrong_declaration


def test_the_cover_fills_the_gaps_where_the_readings_allow():
    """Cover poses lie beside the heaviest plausible poses, along the way the readings
    leave loose: the fingertips stay on the contour there, as under the pose itself."""
    sim = SimulatedHand(HAND, OBJECT, HandSimConfig(pose=(0.001, -0.001, 0.7)),
                        np.random.default_rng(0))
    sim.open()
    centres = np.array([[f.centre[0], f.centre[2]] for f in sim.read_hand().fingers])
    field = contact_field(OBJECT)
    rng = np.random.default_rng(3)
    poses = np.array(sim.pose) + rng.normal(0, [0.002, 0.002, 0.03], (40, 3))
    view = HandView(hypotheses=Hypotheses(poses, np.full(40, 1 / 40)), centres=centres,
                    joints=(), field=field, fingers=HAND.fingers, torque=0.5, grasp=SPEC,
                    step_length=0.003, sigma=2e-4)
    cover = with_cover(view, poses)
    assert len(cover) == 6 * min(COVER, len(poses))
    anchors = np.tile(poses[:COVER], (6, 1))
    scale = np.array([1.0, 1.0, COVER_LENGTH])
    moved = np.linalg.norm((cover - anchors) * scale, axis=1)
    assert np.all(moved > 0) and np.all(moved <= 0.004 + 1e-12)

    def off_contour(p: np.ndarray) -> np.ndarray:
        c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
        w = centres[None] - p[:, None, :2]
        d, _, _ = field.distance(c[:, None] * w[..., 0] + s[:, None] * w[..., 1],
                                 -s[:, None] * w[..., 0] + c[:, None] * w[..., 1])
        return d

    change = np.abs(off_contour(cover) - off_contour(anchors)).max(axis=1)
    loose = slice(0, 4 * min(COVER, len(poses)))  # along the null direction
    assert np.median(change[loose] / moved[loose]) < 0.1  # a random way moves it ~0.5
    assert np.all(change[loose.stop:] <= 2 * 2e-4 + 2e-4)  # across: within the noise


@pytest.mark.parametrize(("name", "seed"), [("rounded:7", 7), ("ellipse:7", 7),
                                            ("blob:8", 8), ("rounded:8", 8), ("blob:6", 6)])
def test_two_fingers_hold_where_the_hypotheses_left_gaps(name, seed):
    """Two fingers dropped these (B6, `--noise --max-steps 60`): the truth lay between the
    plausible hypotheses, where the grasp was far weaker than under any of them (rounded:7,
    seed 7: the nearest 1.5 mm and 1.4 degrees off, 1.0 N predicted, 0.10 N felt)."""
    report = simulate_hand(HandSettings(object=name, hand="two-finger", seed=seed,
                                        noise=True, max_steps=60))
    assert not report.result.dropped and not report.score.wrong_declaration


def test_three_fingers_hold_where_the_truth_lies_beside_light_poses():
    """Found under a gate I did not keep, which guarded the cover only beside poses that
    were likely by weight (`haptic bench grasp --first-seed 100`): three fingers on blob:116,
    seed 116, dropped the object on the first roll (0.17 N). Two fingers dropped blob:169
    and keyed:193 the same way, later on. The gaps beside poses of a percent or less hold
    the truth often enough that every gap is guarded."""
    report = simulate_hand(HandSettings(object="blob:116", hand="three-finger", seed=116,
                                        noise=True, max_steps=2))
    assert not report.result.dropped and report.min_quality >= GraspSpec().threshold_n


def test_two_fingers_hold_when_the_truth_lies_in_a_light_mode():
    """B6 at 50 runs per cell dropped this one at step 5 (`--noise`): the truth's mode
    held 1.7-4.5 % of the plausible weight, its nearest members 1.8-3.2 mm and 2-3.6 degrees off,
    and every move looked safe under them while the true quality fell to 0.15 N. The gate
    now guards every mode's spread, not only the leader's."""
    report = simulate_hand(HandSettings(object="rounded:39", hand="two-finger", seed=39,
                                        noise=True, max_steps=6))
    assert not report.result.dropped


@given(scores=st.lists(st.sampled_from([0.0, -0.0, 0.5, 1.0, 1.0, -np.inf, np.inf, np.nan])
                       | st.floats(-2, 2), max_size=12),
       allowed=st.lists(st.booleans(), min_size=12, max_size=12))
def test_the_best_allowed_option_is_argmax_over_the_allowed(scores, allowed):
    """Asking best first gives the option `np.argmax` picks among all the allowed ones (NaN
    first, ties to the lower index), and asks nothing after the one it returns."""
    score = np.array(scores, dtype=float)
    asked: list[int] = []

    def check(k: int) -> bool:
        asked.append(k)
        return allowed[k]

    best = best_allowed(score, check)
    ok = [k for k in range(len(score)) if allowed[k]]
    assert best == (ok[int(np.argmax(score[ok]))] if ok else None)
    assert len(set(asked)) == len(asked) and (best is None or asked[-1] == best)


def test_two_fingers_move_from_a_start_firmer_than_the_threshold():
    """rounded:2, seed 2: the poses that explain two opposed fingers' first readings run
    on until the grasp under them would be as weak as the start is known to be. Known only
    to keep the threshold (the default), every move took one of them below it and the hand
    never moved; known to keep twice the threshold, it explores. Same object, same pose."""
    firm = HandSettings(object="rounded:2", hand="two-finger", seed=2, noise=True,
                        max_steps=2, start_n=2.0)
    report = simulate_hand(firm)
    assert report.result.steps and not report.result.dropped
    default = simulate_hand(HandSettings(**{**firm.to_json(), "start": report.start,
                                            "start_n": None}))
    assert default.settings.grasp.start_quality_n == default.settings.threshold_n
    assert default.result.stuck and not default.result.steps


ON_THE_MODEL = (0.0006199451520301556, 8.784545560781539e-05, -2.3434347309434607)
"""rounded:192's start for seed 192 as drawn on the model's outline, before starts were
drawn in the simulated world (`94c259a`)."""


def test_the_start_keeps_its_promised_quality_in_the_simulated_world():
    """rounded:192, seed 192, three fingers: the first step dropped the object, the estimate
    3.5 mm and 41 degrees off (`haptic bench grasp --first-seed 100`). The start had been
    drawn with quality at least 1 N on the model's outline; in the simulated world, its
    outline perturbed, it was 0.37 N, so the truth was not among the poses the gate guards
    (those under which the start kept the threshold). The start is now drawn in the world."""
    settings = HandSettings(object="rounded:192", hand="three-finger", seed=192, noise=True,
                            max_steps=2)
    with pytest.raises(ConfigError, match="cannot hold"):
        simulate_hand(dataclasses.replace(settings, start=ON_THE_MODEL))
    report = simulate_hand(settings)
    assert report.start != ON_THE_MODEL
    assert report.start_quality >= settings.grasp.start_quality_n
    assert not report.result.dropped


def test_the_start_promise_allows_for_the_model_outline_being_off(monkeypatch,
                                                                  weigh_without_offset):
    """keyed:1, seed 1, two fingers: the start held 1.03 N in the simulated world and 0.73 N
    on the model's outline. Cut at the promise on the model alone (and the pool weighed
    without the readings' shared offset, as it was found), the truth was not among the
    poses the gate guards, and the second roll dropped the object (0.11 N)."""
    settings = HandSettings(object="keyed:1", hand="two-finger", seed=1, noise=True,
                            max_steps=3)
    assert not simulate_hand(settings).result.dropped
    monkeypatch.setattr(grasp_gated, "TILT", 0.0)
    weigh_without_offset()
    assert simulate_hand(settings).result.dropped


@pytest.mark.xfail(strict=True, reason="found on B6's members 100-199, not fixed: the model's "
                   "outline puts this start far weaker than the world's, beyond what the "
                   "gate allows for (TILT)")
def test_two_fingers_hold_ellipse_137_at_the_first_step():
    """ellipse:137, seed 137, two fingers (`haptic bench grasp --first-seed 100`): the start
    held 1.05 N in the simulated world, 0.17 N on the model's outline and at most 0.90 N
    with the normals turned by three sds of the world's slope, so the truth was not among
    the poses the gate guards; the first move, a turn, dropped the object."""
    report = simulate_hand(HandSettings(object="ellipse:137", hand="two-finger", seed=137,
                                        noise=True, max_steps=2))
    assert not report.result.dropped


def test_two_fingers_hold_a_disc_with_three_notches_through_a_turn():
    """A helper's held-out 40 mm disc with three sharp-edged notches
    (`data/disc_with_three_notches.csv`), seed 14: the turn at step 17 dropped the object;
    under the true pose the model itself predicts -0.13 N for it. The heading was unknown
    over the whole disc and the truth's mode held too little weight for `DROP_RISK`. Since
    the pool's weights allow the readings' shared offset, the hand holds it and stops at
    step 3 with no safe move (least quality 7.5 N)."""
    report = simulate_hand(HandSettings(object=str(DATA / "disc_with_three_notches.csv"),
                                        hand="two-finger", seed=14, noise=True, max_steps=17))
    assert not report.result.dropped


def test_three_fingers_hold_a_kidney_at_step_40():
    """A helper's held-out kidney, an ellipse with a 7 mm dent (`data/kidney_with_a_dent.csv`),
    seed 7: every weighted plausible pose kept the grasp above the threshold, and the roll
    at step 40 dropped the object (a strict xfail: the leading modes lay 4.5 degrees from
    the truth, their spread too narrow). Since a roll comes before a second turn of one mode
    (`object_judge.FRESH`) its route differs: it holds and localizes in 36 steps (seeds 0-19
    all hold). Why the old route's modes lay that far off was not traced: such a tail can
    recur elsewhere."""
    report = simulate_hand(HandSettings(object=str(DATA / "kidney_with_a_dent.csv"),
                                        hand="three-finger", seed=7, noise=True, max_steps=40))
    assert not report.result.dropped and report.score.success


def test_two_fingers_with_12_mm_tips_hold_a_triangle_from_a_firm_start():
    """A helper's own two-finger hand with 12 mm tips (`data/two_finger_hand_12mm_tips.toml`)
    on its rounded triangle with one corner flattened
    (`data/triangle_with_a_flat_corner.csv`), seed 301, `--start-quality 2`: the true
    quality went 2.91, 2.04, then 0.19 N at step 3 (the margin is 0.2 N), the policy
    having predicted 1.46, 0.05 and -0.40 N at least over its plausible poses. Since the
    pool's weights allow the readings' shared offset, it holds through 60 steps (least
    1.43 N), undeclared."""
    report = simulate_hand(HandSettings(
        object=str(DATA / "triangle_with_a_flat_corner.csv"),
        hand=str(DATA / "two_finger_hand_12mm_tips.toml"), seed=301, noise=True,
        max_steps=3, start_n=2.0))
    assert not report.result.dropped


@pytest.mark.xfail(strict=True, reason="found by a helper's held-out hunt, not fixed: the "
                   "pool never held the truth's region, so no plausible pose stood for it")
def test_two_fingers_hold_a_long_rectangle_with_a_dent_noise_free():
    """A helper's 40 x 16 mm rectangle with a 0.6 mm dent
    (`data/long_rectangle_with_a_dent.csv`), seed 2, no noise, two fingers: the second
    roll dropped the object (true quality -0.35 N). The truth fits the readings exactly,
    but the pool's members nearest it (0.4-1 mm, 2 degrees) fit them hundreds of nats
    worse than a mode 3 mm and 43 degrees off, and weighed at the pool's own widened sd
    instead the hand dropped it a step later: the poses the gate guards never came near
    the truth."""
    report = simulate_hand(HandSettings(object=str(DATA / "long_rectangle_with_a_dent.csv"),
                                        hand="two-finger", seed=2, max_steps=3))
    assert not report.result.dropped


def test_three_fingers_hold_an_exact_lens_with_noise():
    """A helper's lens (`data/lens.csv`: two 25 mm arcs, exactly symmetric under a half
    turn), seed 8, B2's noise: the true quality fell 0.44, 0.35, 0.25, then 0.20 N from
    step 51 while the policy predicted 1.85, 1.53, 1.32 and 1.03 N; the leader lay 1.65 mm
    and 6.2 degrees from the truth's image, and the object dropped at step 54. Since the
    mode tracks weigh the readings' shared offset (`ObjectTracks`), as the judge does, the
    hand holds it (through 120 steps, undeclared, 0.3 mm from the truth at the end)."""
    report = simulate_hand(HandSettings(object=str(DATA / "lens.csv"), hand="three-finger",
                                        seed=8, noise=True, max_steps=54))
    assert not report.result.dropped


def test_a_hand_without_tip_roll_servos_explores_but_never_turns(tmp_path):
    """A held-out hand with no `[fingers.tip_roll]` turned the object in simulation, where
    the tips rolled as told; on the servos nothing rolled them, the object went where the
    motion model did not follow, and the estimate was lost (before that, the first turn
    raised "no tip-roll servo"). Such a hand now only rolls its fingers along the object."""
    import re

    text = (Path(__file__).resolve().parents[2] / "firmware_if" / "hands"
            / "three-finger.toml").read_text()
    free = re.sub(r"\[fingers\.tip_roll\]\nid = \d+\n", "", text)
    assert "tip_roll" not in free
    (tmp_path / "free.toml").write_text(free)
    settings = HandSettings(object="blob:4", seed=4, noise=True, max_steps=8)
    turned = simulate_hand(dataclasses.replace(settings, hand="three-finger"))
    assert any(s.kind == "manipulate" for s in turned.result.steps)  # as a roll servo lets
    rolled = simulate_hand(dataclasses.replace(settings, hand=str(tmp_path / "free.toml")))
    assert rolled.result.steps and not any(s.kind == "manipulate"
                                           for s in rolled.result.steps)
    assert not rolled.result.dropped


def test_the_gates_neighbours_stand_for_the_worlds_mismatch_at_least():
    """The floor under the spread the gate guards: the world's outline mismatch, in
    position and over the object's lever in heading; none where the model is the world."""
    assert spread_floor(0.0, 0.03) == (0.0, 0.0)
    position, heading = spread_floor(0.0002, 0.025)
    assert position == pytest.approx(FLOOR_SDS * 0.0002)
    assert heading == pytest.approx(FLOOR_SDS * 0.0002 / 0.025)
    poses, weights = np.array([[0.0, 0.0, 0.0]]), np.array([1.0])
    tight = with_spread(poses, weights, (1e-5, 1e-4), (position, heading))[0]
    assert np.max(np.abs(tight[1:, :2])) == pytest.approx(2 * position)
    assert np.max(np.abs(tight[1:, 2])) == pytest.approx(2 * heading)


def test_three_fingers_hold_five_alike_lobes_through_a_turn():
    """A held-out researcher's outline with five alike lobes (`data/five_lobes.csv`), seed
    3: the pool claimed a spread of 0.14 degrees while its leader lay 2.1 degrees and 1 mm
    from the truth (its nearest image), the world's mismatch having led the fit there
    after a turn; the next turn, predicted at 1.10 N under every plausible pose, dropped
    the object at step 31 (0.12 N). The gate's neighbours stand for the mismatch now."""
    report = simulate_hand(HandSettings(object=str(DATA / "five_lobes.csv"),
                                        hand="three-finger", seed=3, noise=True, max_steps=32))
    assert not report.result.dropped


def test_three_fingers_roll_before_they_turn_a_known_object_again():
    """A held-out lab's kidney outline (`data/kidney.csv`), seed 0, noise-free: the leader
    held the truth at 100 % from step 2, but the policy turned the object at every one of
    100 steps (its heading alternating between two values from step 79). Each turn left the
    judge three readings since it, too few to weigh (`object_judge.FRESH`), so nothing was
    ever declared. With one mode left, a roll now comes before the next turn."""
    report = simulate_hand(HandSettings(object=str(DATA / "kidney.csv"), hand="three-finger",
                                        seed=0, max_steps=30))
    assert report.score.success
    kinds = [step.kind for step in report.result.steps]
    assert "manipulate" in kinds and kinds != ["manipulate"] * len(kinds)


@pytest.mark.parametrize(("logits", "stalled"), [
    ([2.6] * 7, True),  # six rolls at 93 %
    ([2.6] * 6, False),  # five: not yet
    ([2.5, 2.6, 2.55, 2.7, 2.65, 2.6, 2.75], True),  # wobbling within 0.3
    ([1.9, 2.0, 2.2, 2.3, 2.5, 2.7, 2.9], False),  # climbing: the rolls tell
    ([9.0, 2.6, 2.6, 2.6, 2.6, 2.6, 2.6, 2.6], True),  # only the last six rolls count
    ([2.6, 2.6, 2.6, float("nan"), 2.6, 2.6, 2.6], False),  # no share to judge by
    ([-2.9] * 7, False),  # a leader of 5 % among many: rolls strike the many out
])
def test_rolls_stall_when_the_leading_share_stays_put(logits, stalled):
    assert grasp_gated.stalled(logits) is stalled


def test_three_fingers_turn_once_their_rolls_stop_telling_the_modes_apart():
    """rounded:5, seed 5, three fingers: the rolls promised 0.04-0.29 nats each but re-read
    felt contour, and the leader sat at 93 % from step 25 to step 60, undecided, while a
    safe turn was on offer throughout."""
    report = simulate_hand(HandSettings(object="rounded:5", hand="three-finger", seed=5,
                                        noise=True, max_steps=60))
    turns = sum(step.kind == "manipulate" for step in report.result.steps)
    assert report.score.success and not report.result.dropped and turns >= 2


@pytest.mark.xfail(strict=True, reason="a turn's quality falls off a cliff between the "
                   "gate's guards: not yet guarded")
def test_three_fingers_hold_a_circle_with_a_small_bump_through_a_turn():
    """A held-out fault campaign's circle of 30 mm radius with one 1.5 mm bump, seed 108:
    at step 27 the hand turned the object with the leader at 86 %, 1.7 degrees and 0.2 mm
    from the truth. The model predicted 3.18 N under the leader and every guard of its
    spread held, but -0.20 N at the truth itself, and the object dropped (-0.04 N)."""
    report = simulate_hand(HandSettings(object=str(DATA / "circle_with_a_small_bump.csv"),
                                        hand="three-finger", seed=108, noise=True,
                                        max_steps=30))
    assert not report.result.dropped

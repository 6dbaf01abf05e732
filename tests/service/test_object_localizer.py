"""Localizing a held object (Algorithm IV on (x, z, theta)): it finds the pose, says "not
yet" on a symmetric object, and follows the object when the fingers carry it."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from firmware_if.backend import FingerMove, HandCommand
from service.episode import hand_episode
from service.episode.hand_episode import simulate_hand
from service.episode.hand_scenario import (
    UNIT,
    HandSettings,
    build_localizer,
    draw_truth,
    load_parts,
    score,
    streams,
)
from service.episode.hand_step import step_json
from service.localization.localizers import (
    contour_fit,
    object_judge,
    object_tracks,
    shared_error,
)
from service.localization.localizers.base import Estimate, update, wrap_angle
from service.localization.localizers.contour_fit import assess, refine
from service.localization.localizers.object_base import HandMeasurement
from service.localization.objects import rolling
from service.localization.policies import grasp_gated
from service.localization.policies.grasp_gated import GraspGatedPolicy
from sim_backend.hand import HandSimConfig, SimulatedHand

DATA = Path(__file__).parent / "data"


@pytest.fixture
def one_step_policy(monkeypatch):
    """The policy these episodes were found under: moves weighed by what they tell the
    plausible poses alone, a turn only when no roll tells anything
    (`GraspGatedPolicy(precision=False)`). The tests that use it reproduce a judgement
    the episode came to then; the policy of today takes other paths."""
    monkeypatch.setattr(hand_episode, "build_policy",
                        lambda settings: GraspGatedPolicy(gate=settings.gate, precision=False))


THREE = HandSettings(object="blob:3", hand="three-finger", noise=True, max_steps=30)


def pose_error(a, b) -> tuple[float, float]:
    return float(np.hypot(a[0] - b[0], a[1] - b[1])), float(abs(wrap_angle(a[2] - b[2])))


@pytest.mark.parametrize("algorithm", ["particles", "elimination"])
def test_three_fingers_localize_a_held_object_under_noise(algorithm):
    report = simulate_hand(dataclasses.replace(THREE, algorithm=algorithm))
    assert report.result.converged and not report.result.dropped
    assert report.score.success and not report.score.wrong_declaration
    position, heading = pose_error(report.result.estimate.pose, report.truth)
    assert position < 1e-3 and heading < np.deg2rad(2)
    again = simulate_hand(dataclasses.replace(THREE, algorithm=algorithm))  # same seed
    assert [s.centres for s in again.result.steps] == [s.centres for s in report.result.steps]


@pytest.mark.parametrize(("heading_deg", "success", "wrong"), [(2.0, True, False),
                                                               (8.0, False, True)])
def test_a_score_is_plain_json(heading_deg, success, wrong):
    """A wrong declaration's score was numpy's bool, which bench grasp --json and haptic
    run --json could not write."""
    declared = Estimate(pose=(0.001, 0.0, np.deg2rad(heading_deg)), candidates=1,
                        converged=True)
    s = score(declared, (0.0, 0.0, 0.0), dropped=False)
    assert (s.success, s.wrong_declaration) == (success, wrong)
    assert json.loads(json.dumps(dataclasses.asdict(s)))["success"] is success


def test_a_symmetric_object_stays_not_yet():
    report = simulate_hand(dataclasses.replace(THREE, object="ellipse:1", max_steps=20))
    assert not report.result.converged and not report.score.wrong_declaration
    assert not report.result.dropped


@pytest.mark.usefixtures("one_step_policy")
def test_an_undecided_pose_and_its_mirror_are_given_the_masses_they_were_weighed_at():
    """A mirror that fitted a hair better left the estimate at "0 %" beside its "50 %"
    (`haptic run --object ellipse:2 --hand three-finger --max-steps 5`)."""
    est = simulate_hand(HandSettings(object="ellipse:2", hand="three-finger", seed=0,
                                     max_steps=5)).result.estimate
    assert not est.converged and est.runner_up is not None
    assert est.mode_mass > 0.3 and est.runner_up_mass > 0.3
    assert est.mode_mass + est.runner_up_mass <= 1.0 + 1e-9
    turned = abs(wrap_angle(est.runner_up[2] - est.pose[2]))
    assert turned > np.deg2rad(170)  # the mirror, half a turn away


@pytest.mark.parametrize("max_steps", [3, 5, 8])
def test_right_after_a_turn_an_exact_mirror_keeps_its_half(max_steps):
    """A held-out check: three fingers on an ellipse (seed 0, no noise) ended, a step or
    two after a turn, at "100 %" on a pose half a turn from the truth; at 3, 5 and 8 steps
    main said 82 %, 88 % and 97 %. With under four readings since the turn the tracks were
    weighed without the leader's images: the exact mirror, never a track, went unweighed."""
    est = simulate_hand(HandSettings(object="ellipse", hand="three-finger", seed=0,
                                     max_steps=max_steps)).result.estimate
    assert not est.converged and est.runner_up is not None
    assert 0.4 < est.mode_mass < 0.6 and 0.4 < est.runner_up_mass < 0.6
    assert abs(wrap_angle(est.runner_up[2] - est.pose[2])) > np.deg2rad(170)


def test_an_ellipse_is_not_declared_against_its_exact_mirror():
    """ellipse:316, seed 316, three fingers: the half-turned mirror held 0.4988 of the
    tracks' probability, yet the final comparison declared the leader at 0.9999 at step
    18. The mirror had been polished on the latest readings alone and then judged on what
    the leader felt before; in the final comparison, refined from 5 readings, it had slid
    onto a poorer fit. Each of the two mends (`object_judge._images`,
    `object_judge._rivals_beside`) alone keeps this episode undeclared; main declared it."""
    report = simulate_hand(HandSettings(object="ellipse:316", hand="three-finger", seed=316,
                                        noise=True, max_steps=20))
    assert not report.result.converged and not report.result.dropped


def test_refine_recovers_a_pose_from_exact_readings():
    parts = load_parts(THREE)
    pose = np.array([0.001, -0.002, 0.6])
    outline, normals = parts.contour.resampled(0.004)
    local = outline + 0.008 * normals
    c, s = np.cos(pose[2]), np.sin(pose[2])
    points = local @ np.array([[c, s], [-s, c]]) + pose[:2]
    fit = refine(parts.field, points[::3], np.full(len(points[::3]), 0.008),
                 pose + [0.0005, -0.0003, 0.02], 1e-5)
    assert pose_error(fit.pose, pose)[0] < 2e-5 and fit.rms < 1.0


def _readings_around(ctx_or_parts, pose, count, tip=0.008, bulge=None):
    """Fingertip centres of radius `tip` touching the outline under `pose` at `count`
    places spread around it (each pushed out by `bulge`, metres, if given)."""
    contour = ctx_or_parts.field.contour if hasattr(ctx_or_parts, "field") else \
        ctx_or_parts.contour
    outline, normals = contour.resampled(0.0005)
    idx = np.linspace(0, len(outline), count, endpoint=False).astype(int)
    out = tip + (np.zeros(count) if bulge is None else bulge)
    return object_tracks.from_object(outline[idx] + out[:, None] * normals[idx], pose)


def test_a_whitened_fit_is_generalized_least_squares():
    """`contour_fit.whitened_fit` with readings whose errors are correlated lands where a
    general least-squares solver on the whitened residuals does, and its chi-square is
    r^T C^-1 r there."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import least_squares

    from service.localization.localizers.refine import shared_error

    parts = load_parts(THREE)
    pose = np.array([0.001, -0.002, 0.6])
    bumps = np.random.default_rng(5).normal(0.0, 2e-4, 24)
    points = _readings_around(parts, pose, 24, bulge=bumps)
    radii = np.full(len(points), 0.008)
    cov = np.diag(np.full(len(points), 2e-4) ** 2) + shared_error(points, 3e-4, 0.01) + 1e-8
    chol = cholesky(cov, lower=True)
    start = pose + [0.0005, -0.0003, 0.02]
    fitted, chi2 = contour_fit.whitened_fit(parts.field, start, points, radii, chol, 12, 0.01)

    def whitened(p):
        r = contour_fit.residuals(parts.field, p[None], points, radii)[0]
        return solve_triangular(chol, r, lower=True)

    solved = least_squares(whitened, start, xtol=1e-12, ftol=1e-12).x
    assert np.hypot(*(fitted[:2] - solved[:2])) < 1e-6
    assert abs(wrap_angle(fitted[2] - solved[2])) < 1e-6
    r = contour_fit.residuals(parts.field, fitted[None], points, radii)[0]
    assert chi2 == pytest.approx(r @ np.linalg.solve(cov, r))


def test_a_refined_contour_fit_says_which_readings_it_kept():
    """`contour_fit.refine` sets an outlier aside, and says so (`Fit.kept`, as the finger's
    refine does): the judge weighs only the kept readings again."""
    parts = load_parts(THREE)
    pose = np.array([0.001, -0.002, 0.6])
    off = np.zeros(24)
    off[7] = 0.003  # 3 mm outside the outline
    points = _readings_around(parts, pose, 24, bulge=off)
    fit = refine(parts.field, points, np.full(len(points), 0.008), pose, 2e-4, max_outliers=2)
    assert fit.kept is not None and 7 not in fit.kept and len(fit.kept) == 23


def test_errors_shared_over_a_patch_count_as_one_error():
    """`shared_error.correlated_fits`: a world whose outline bulges 0.4 mm over one patch
    pushes every reading there outward alike. Counted independent, the truth misfits them
    by many times the noise; weighed as the world makes them (shared over the patch, and
    one offset shared by all) it costs about what one such error does. At the truth itself
    (no steps): fitted, a pose absorbs the bulge either way."""
    settings = HandSettings(object="keyed:3", hand="three-finger", noise=True)
    ctx = build_localizer(settings, load_parts(settings), np.random.default_rng(0)).ctx
    tip = 0.008
    arc = np.linspace(-1.5, 1.5, 8) * 1e-3
    bulge = _on_outline(ctx, np.zeros(3), arc, tip + 0.0004)
    elsewhere = _on_outline(ctx, np.zeros(3), arc + 0.03, tip)
    points = np.vstack([bulge, elsewhere])
    radii, sd = np.full(len(points), tip), np.full(len(points), ctx.sigma)
    r = contour_fit.residuals(ctx.field, np.zeros((1, 3)), points, radii)[0]
    assert np.sum((r / sd) ** 2) > 8 * (0.0004 / ctx.sigma) ** 2 * 0.9
    _, chi2 = shared_error.correlated_fits(ctx, np.zeros((1, 3)), points, radii, sd,
                                           iterations=0)
    assert chi2[0] < 2 * (0.0004 / ctx.mismatch_sd) ** 2


def test_the_shared_weighing_tells_two_lobes_from_their_half_turn():
    """`object_judge._correlated_mass` on readings all around two lobes 0.5 mm apart in
    radius, the world bulging by B2's mismatch: the truth holds nearly all the weight
    beside its half-turned image, and the image, as the leader, nearly none."""
    from service.localization.objects.symmetry import images, near_symmetries

    settings = HandSettings(object=str(DATA / "two_lobes_half_mm_apart.csv"),
                            hand="three-finger", noise=True)
    ctx = build_localizer(settings, load_parts(settings), np.random.default_rng(0)).ctx
    truth = np.array([0.001, -0.002, 0.3])
    (image,) = images(truth, near_symmetries(ctx.field))
    bulge = np.random.default_rng(3).normal(0.0, ctx.mismatch_sd, 40)
    points = _readings_around(ctx, truth, 40, bulge=bulge)
    radii, sd = np.full(len(points), 0.008), np.full(len(points), ctx.sigma)

    def mass(lead, other):
        fit = assess(ctx.field, points, radii, lead, sd)
        return object_judge._correlated_mass(ctx, fit, other[None], points, radii, sd)

    assert mass(truth, image) > 0.999
    assert mass(image, truth) < 0.001


def test_the_localizer_follows_a_carried_object():
    settings = dataclasses.replace(THREE, noise=False)
    parts = load_parts(settings)
    truth_rng, world_rng, loc_rng, _ = streams(3)
    start = draw_truth(settings, parts, truth_rng, parts.contour)  # noise-free: the model
    sim = SimulatedHand(parts.hand, parts.contour, HandSimConfig(pose=start), world_rng)
    sim.open()
    sim.set_torque(True)

    def centres():
        return np.array([[f.centre[0], f.centre[2]] for f in sim.read_hand().fingers])

    localizer = build_localizer(settings, parts, loc_rng)
    localizer.start(HandMeasurement(0, centres(), (0, 1, 2)))
    radii = np.full(3, 0.008)
    for step in range(1, 7):  # explore a little, each finger in turn
        f = step % 3
        _, normals = rolling.contacts(parts.field, np.array([sim.pose]), centres()[None], radii)
        move = [None, None, None]
        dx, dz = 0.002 * np.array([-normals[0, f, 1], normals[0, f, 0]])
        move[f] = FingerMove(dx=dx, dz=dz)
        sim.command_hand(HandCommand(tuple(move)))
        update(localizer, HandMeasurement(step, centres(), (f,)))
    before = localizer.estimate().pose
    assert pose_error(before, sim.pose)[0] < 5e-4
    moves, rolls = rolling.plan_turn(parts.field, np.array(before), centres(), radii, 0.3)
    sim.command_hand(HandCommand(tuple(FingerMove(dx=m[0], dz=m[1], roll=r)
                                       for m, r in zip(moves, rolls, strict=True))))
    assert not sim.read_hand().dropped
    update(localizer, HandMeasurement(7, centres(), (0, 1, 2), carried=(moves, rolls)))
    after = localizer.hypotheses(limit=1).poses[0]
    position, heading = pose_error(after, sim.pose)
    assert abs(wrap_angle(sim.pose[2] - start[2])) > 0.25  # the object did turn
    assert position < 1e-3 and heading < np.deg2rad(2)


def test_unknown_algorithm_for_objects_is_a_clear_error():
    with pytest.raises(Exception, match="unknown algorithm 'grid'; choose one of: particles, "
                                        "elimination"):
        HandSettings(algorithm="grid")


def test_readings_that_share_the_outlines_error_count_once():
    """Readings within the world's mismatch length share its error: as evidence they count
    as the distinct patches they were taken on, and the spread widens to match."""
    from service.localization.localizers.refine import Fit
    from service.localization.localizers.shared_error import patch_temper as _temper
    from service.localization.localizers.shared_error import widened as _widened

    ctx = dataclasses.replace(build_localizer(THREE, load_parts(THREE),
                                              np.random.default_rng(0)).ctx,
                              mismatch_length=0.01)
    patch = np.array([[0.0, 0.0], [0.001, 0.0], [0.002, 0.0], [0.05, 0.0]])
    assert _temper(ctx, patch) == pytest.approx(0.5)  # two patches in four readings
    assert _temper(dataclasses.replace(ctx, mismatch_length=0.0), patch) == 1.0
    fit = Fit(pose=(0.0, 0.0, 0.0), position_sd=1e-4, heading_sd=0.01, rms=0.0,
              max_abs=0.0, readings=4)
    wide = _widened(fit, 0.25)
    assert (wide.position_sd, wide.heading_sd) == pytest.approx((2e-4, 0.02))


def test_three_small_arcs_do_not_declare_a_half_turn_image():
    """rounded:14, seed 14, three fingers: 11 readings from three small arcs fitted a pose
    136 degrees off better than the truth (by 7 nats, counted as independent) and it was
    declared."""
    report = simulate_hand(HandSettings(object="rounded:14", hand="three-finger", seed=14,
                                        noise=True, max_steps=30))
    assert not report.score.wrong_declaration and not report.result.dropped


@pytest.mark.parametrize("carried_sd, localizes", [(object_tracks.CARRIED_SD, True), (0.0, False)])
def test_readings_carried_without_noise_keep_a_floor(monkeypatch, carried_sd, localizes):
    """Without noise the motion model adds no spread to the readings a turn carries, yet
    they moved with the track's pose as fitted then, not with the truth: three fingers on
    keyed:0 (seed 0) kept turning the object and never declared. With the floor they
    localize it, and without it they still do not."""
    monkeypatch.setattr(object_tracks, "CARRIED_SD", carried_sd)
    report = simulate_hand(HandSettings(object="keyed:0", hand="three-finger", seed=0,
                                        noise=False, max_steps=20))
    assert report.score.success == localizes
    assert not report.score.wrong_declaration
    assert not report.result.dropped


def test_exact_readings_since_a_turn_hold_back_a_fit_the_carried_ones_pulled_off():
    """blob:37, seed 7, three fingers, no noise: the track carried through the turn at step 2
    had been 3.9 degrees off the truth, and the readings it carried moved with that error.
    The fit on them and the four exact readings since the turn lay 1.7 degrees off, missing
    those four by up to 2.8 sds, and was declared claiming an sd of 0.27 degrees. Now the
    readings since the turn must fit it nearly as well as a pose of their own
    (`object_judge.SPLIT_CHI2`)."""
    report = simulate_hand(HandSettings(object="blob:37", hand="three-finger", seed=7,
                                        noise=False, max_steps=20))
    assert report.score.success and not report.result.dropped
    assert np.rad2deg(report.score.heading_error) < 0.5


def test_no_half_turned_image_of_a_slender_outline_is_declared():
    """A helper's 44 x 11 mm outline whose ends differ by 15 % in thickness
    (`data/slender_with_unequal_ends.csv`), three fingers, B2's noise, seed 8: the leader
    was the half-turned image from step 1 and was declared at step 53, 1.9 mm and 177.8
    degrees off, claiming 0.22 mm and 0.52 degrees. The nine readings since the last turn
    fit the image better than the truth (14 nats at the judge's sd), yet with their shared
    offset counted the two lay 0.7 nats apart: the truth's track had lost 19 nats before
    the turn, weighed without the offset the judge allows (`ObjectTracks.update`)."""
    report = simulate_hand(HandSettings(object=str(DATA / "slender_with_unequal_ends.csv"),
                                        hand="three-finger", seed=8, noise=True,
                                        max_steps=53))
    assert not report.score.wrong_declaration


FOUND_START = (0.0007284762401801974, -0.0024788270824965463, 0.30938507388240977)
"""rounded:8's start for seed 8 from a 2 N start, as drawn on the model's outline before
starts were drawn in the simulated world (`94c259a`)."""


def _no_offset(ctx, poses, points, radii, sd, temper):
    return temper * object_judge.fit_log_likelihood(ctx.field, poses, points, radii, sd,
                                                    ctx.outlier_probability,
                                                    ctx.outlier_range)


def _unchecked(*args):
    """The whole-object check switched off: no pose beyond the leader's tolerance."""
    return 1.0, None, 0.0, np.empty((0, 3))


@pytest.mark.parametrize("checked", [True, False])
@pytest.mark.usefixtures("one_step_policy")
def test_a_pose_the_pool_lost_is_weighed_before_a_declaration(monkeypatch, checked,
                                                              weigh_without_offset):
    """blob:12, seed 12, one finger on the clamped object: the pool kept a pose 177
    degrees off and lost the truth, which fitted the readings 2.7 nats better; the pose
    was declared at 0.9997 at step 12. The whole-object check finds the truth through the
    first reading, refuses, and hands it to the tracks and the pool: the finger localizes
    it. Without the check (and the readings' shared offset, as it was found), the wrong
    pose."""
    if not checked:
        monkeypatch.setattr(object_judge, "_whole_object", _unchecked)
        weigh_without_offset()
    report = simulate_hand(HandSettings(object="blob:12", hand="two-finger", seed=12,
                                        noise=True, max_steps=20, single_finger=True))
    assert report.score.wrong_declaration != checked
    assert report.score.success == checked


def test_the_whole_object_check_waits_between_the_update_and_the_next_move(monkeypatch):
    """The check costs a few milliseconds: it runs as the finger's certificate does, after
    the update and before the next move (`HandStepper.settle`), so the update stays
    bounded; a declaration it allows costs no move."""
    calls = []
    check = object_judge._whole_object

    def counted(*args):
        calls.append(len(args[1]))
        return check(*args)

    monkeypatch.setattr(object_judge, "_whole_object", counted)
    report = simulate_hand(THREE)
    assert report.result.converged and report.score.success and calls
    settled = [s for s in report.result.steps if s.settle_ms > 0]
    assert len(settled) == len(calls) and settled[-1] is report.result.steps[-1]


def test_the_whole_object_check_finds_every_pose_that_fits():
    """Readings taken at a known pose: the best pose beyond the tolerance of a wrong
    leader is the truth, found anywhere on the object (a leader a half turn away)."""
    from service.localization.localizers.object_certificate import rivals_beyond

    parts = load_parts(THREE)
    truth = np.array([0.001, -0.002, 0.7])
    outline, normals = parts.contour.resampled(0.004)
    local = (outline + 0.008 * normals)[::7][:9]  # tip centres on the outline, object frame
    c, s = np.cos(truth[2]), np.sin(truth[2])
    points = np.column_stack([c * local[:, 0] - s * local[:, 1] + truth[0],
                              s * local[:, 0] + c * local[:, 1] + truth[1]])
    leader = truth + np.array([0.0, 0.0, np.pi])
    found = rivals_beyond(parts.field, points, np.full(len(points), 0.008), leader, sd=2e-4,
                          outlier_probability=0.02, outlier_range=0.05,
                          position_tol=0.0025, heading_tol=np.deg2rad(5.0))
    assert len(found)
    position, heading = pose_error(found[0], truth)
    assert position < 2e-4 and heading < np.deg2rad(0.5)
    others = rivals_beyond(parts.field, points, np.full(len(points), 0.008), truth, sd=2e-4,
                           outlier_probability=0.02, outlier_range=0.05,
                           position_tol=0.0025, heading_tol=np.deg2rad(5.0))
    fit = object_judge.fit_log_likelihood(parts.field, np.vstack([truth, others]), points,
                                          np.full(len(points), 0.008), 2e-4, 0.02, 0.05)
    assert np.all(fit[1:] < fit[0] - 20)  # asked of the truth, it finds nothing comparable


@pytest.mark.parametrize("offset", [True, False])
@pytest.mark.usefixtures("one_step_policy")
def test_readings_off_the_truth_alike_are_not_read_as_another_pose(monkeypatch, offset,
                                                                  weigh_without_offset):
    """rounded:8, seed 8, three fingers from a 2 N start: the world's outline lies outside
    the model's under every reading (0.25-0.75 mm on average per finger's arc), and a pose
    125 degrees off fitted them better than the truth; it was declared at step 23. Allowed
    one offset of the whole outline, the judge finds the truth comparable and declares
    nothing; without it, the wrong pose. The episode as it was found: the start the seed
    drew on the model's outline then (`FOUND_START`), the gate without its allowance for
    the world's slope (`grasp_gated.TILT`)."""
    monkeypatch.setattr(grasp_gated, "TILT", 0.0)
    if not offset:  # neither in the comparison nor in the fit (nor the whole-object check)
        monkeypatch.setattr(object_judge, "offset_log_likelihood", _no_offset)
        monkeypatch.setattr(object_judge, "offset_refit", lambda *args: args[4])
        monkeypatch.setattr(object_judge, "_whole_object", _unchecked)
        weigh_without_offset()  # nor in the pool's and the tracks' weights
    report = simulate_hand(HandSettings(object="rounded:8", hand="three-finger", seed=8,
                                        noise=True, max_steps=23, start_n=2.0,
                                        start=FOUND_START))
    assert report.score.wrong_declaration != offset
    assert not report.result.dropped


@pytest.mark.parametrize("refit", [True, False])
@pytest.mark.usefixtures("one_step_policy")
def test_a_world_off_the_model_alike_does_not_keep_the_declaration_back(monkeypatch, refit,
                                                                        weigh_without_offset):
    """blob:27, seed 27, three fingers from a 2 N start: the world's outline lay off the
    model's alike under the fingertips, and the fit's largest residual stayed just beyond
    the rule's limit (4.5 sd against 3.6) to step 60, the pose 0.25 degrees off. Judged
    with the offset fitted, the hand localizes it; without (nor in the pool's and the
    tracks' weights, as it was found), it does not."""
    if not refit:
        monkeypatch.setattr(object_judge, "offset_refit", lambda *args: args[4])
        weigh_without_offset()
    report = simulate_hand(HandSettings(object="blob:27", hand="three-finger", seed=27,
                                        noise=True, max_steps=20, start_n=2.0))
    assert report.score.success == refit
    assert not report.score.wrong_declaration


def test_no_wrong_declaration_on_an_outline_near_its_120_degree_turn():
    """A helper's own hand (three fingers at 30/150/270 degrees, 50/45 mm links, 10 mm
    tips) and outline (a rounded triangle matching its 120-degree turn within 0.73 mm):
    seed 1 was declared 0.1 mm and 120.2 degrees off after 40 steps, at a mode mass of
    0.9998: the evidence from before the object's last turn counted 12.2 nats against the
    truth, where before the turn, tempered by the patches it came from, it had counted 5.5
    (`ObjectTracks`)."""
    data = Path(__file__).parent / "data"
    report = simulate_hand(HandSettings(
        object=str(data / "rounded_triangle_near_120.csv"),
        hand=str(data / "wide_three_finger_hand.toml"), seed=1, noise=True, max_steps=60))
    assert not report.score.wrong_declaration


def test_a_carry_keeps_the_evidence_as_tempered_as_it_was():
    """Readings from one patch of the outline share the world's error: the evidence they
    give one track over another is tempered by the patches felt (`shared_error.patch_temper`),
    and a carry keeps it so; counted afresh after the turn, it counted in full."""
    settings = HandSettings(object="blob:3", hand="three-finger", noise=True)
    parts = load_parts(settings)
    ctx = build_localizer(settings, parts, np.random.default_rng(0)).ctx
    truth = np.zeros(3)
    off = np.array([0.001, 0.0, 0.0])  # outward where the readings are (the right)
    # six readings within a millimetre of one another: one patch of the outline
    arc = np.linspace(-0.5, 0.5, 6) * 1e-3
    tip = parts.hand.fingers[0].radius
    points, radii = _on_outline(ctx, truth, arc, tip), np.full(len(arc), tip)
    tracks = object_tracks.ObjectTracks()
    tracks.update(ctx, points, radii, np.vstack([truth, off]), np.zeros(2), sd=ctx.sigma,
                  position_tol=1e-9, heading_tol=1e-9)
    temper = object_judge.patch_temper(ctx, points)
    assert len(tracks.centres) == 2 and temper <= 0.5
    kept = temper * (tracks.ll[0] - tracks.ll[1])
    assert kept > 1.0  # the readings do tell the two apart
    tracks.carry(ctx, points[:3], np.zeros((3, 2)), np.zeros(3), points, radii)
    assert tracks.prior[0] - tracks.prior[1] == pytest.approx(kept)


def _on_outline(ctx, pose, arc, tip) -> np.ndarray:
    """Fingertip centres touching the outline under `pose`, along `arc` (metres) from its
    rightmost point in the object's frame."""
    contour = ctx.field.contour
    points, normals = contour.resampled(0.0001)
    start = int(np.argmax(points[:, 0]))
    idx = (start + np.round(arc / 0.0001).astype(int)) % len(points)
    local = points[idx] + tip * normals[idx]
    return object_tracks.from_object(local, pose)


def test_a_declared_heading_lies_within_three_of_its_spreads():
    """keyed:124, seed 124, three fingers: declared 3.6 degrees off at a heading spread of
    0.75 degrees (4.8 spreads): readings in a few patches, on an ellipse near its round,
    erred together, and the spread counted only the patches felt."""
    report = simulate_hand(HandSettings(object="keyed:124", hand="three-finger", seed=124,
                                        noise=True, max_steps=30))
    estimate = report.result.estimate
    if report.result.converged:
        assert report.score.heading_error <= 3 * estimate.heading_sd
    assert not report.score.wrong_declaration


def test_readings_that_err_together_pin_the_pose_less():
    """The sandwich spread (`contour_fit.correlated_spread`): without a shared error it is
    the fit's own; the more error the readings share, the wider."""
    settings = HandSettings(object="keyed:3", hand="three-finger", noise=True)
    ctx = build_localizer(settings, load_parts(settings), np.random.default_rng(0)).ctx
    points, normals = ctx.field.contour.resampled(0.0001)
    idx = np.linspace(0, len(points), 12, endpoint=False).astype(int)
    tip = 0.008
    centres, radii = points[idx] + tip * normals[idx], np.full(len(idx), tip)
    sd = np.full(len(idx), ctx.sigma)
    own = assess(ctx.field, centres, radii, np.zeros(3), sd)
    spreads = [contour_fit.correlated_spread(ctx.field, centres, radii, np.zeros(3), sd,
                                             error_sd, 0.014)
               for error_sd in (0.0, 1e-4, 2e-4, 4e-4)]
    assert spreads[0] == pytest.approx((own.position_sd, own.heading_sd))
    assert all(b[0] > a[0] and b[1] > a[1] for a, b in zip(spreads, spreads[1:], strict=False))


def test_each_step_says_the_least_quality_during_it():
    """A held-out check: a run's least quality (0.48 N) was far below every step's shown
    quality (at least 1.63 N): the dip came inside a turn, where no step said so."""
    report = simulate_hand(HandSettings(object="blob:4", hand="three-finger", seed=4,
                                        noise=True, max_steps=8))
    steps = report.result.steps
    assert any(s.kind == "manipulate" for s in steps)
    assert all(s.least_quality <= s.quality for s in steps)
    assert min([report.start_quality] + [s.least_quality for s in steps]) == pytest.approx(
        report.min_quality)
    assert step_json(steps[0])["least_quality"] == steps[0].least_quality


@pytest.mark.usefixtures("one_step_policy")
def test_poses_refined_onto_the_leader_do_not_split_its_mass():
    """A helper's near-circle with a 2.5 mm bump: its images under the many turns that
    nearly match, polished onto the readings, landed on the leader (0.04 mm and 0.3 degrees
    apart) and were weighed as its rivals: "still ambiguous between" two right poses at 25 %
    and 29 %, after 60 steps."""
    report = simulate_hand(HandSettings(
        object=str(Path(__file__).parent / "data" / "near_circle_with_a_bump.csv"),
        hand="three-finger", seed=0, noise=True, max_steps=60))
    estimate = report.result.estimate
    assert estimate.mode_mass > 0.99
    assert estimate.runner_up is None or not object_tracks.near(
        np.asarray([estimate.runner_up]), np.asarray([estimate.pose]), 0.25 * UNIT,
        np.deg2rad(5.0))[0, 0]


@pytest.fixture
def estimates(monkeypatch) -> list[Estimate]:
    """Every estimate the object particle filter gives, in order, as it gives them."""
    from service.localization.localizers.object_particles import ObjectParticles

    seen: list[Estimate] = []
    estimate = ObjectParticles.estimate

    def recorded(self):
        seen.append(estimate(self))
        return seen[-1]

    monkeypatch.setattr(ObjectParticles, "estimate", recorded)
    return seen


def test_the_estimate_is_never_shown_beside_itself_as_its_rival(estimates):
    """A held-out 12-tooth gear (a mesh's section; three fingers, seed 2): a few readings
    after a turn, the estimate was the pool's heaviest member while its rival was the
    tracks' second mode, the same pose: "still ambiguous between x 2.54 mm z -2.28 mm
    heading 17.6 deg (25 %) and x 2.54 mm z -2.28 mm heading 17.6 deg". The estimate is
    now the pose the share and the rival are reckoned beside, every step."""
    simulate_hand(HandSettings(object=str(Path(__file__).parent / "data"
                                          / "gear_twelve_teeth.csv"),
                               hand="three-finger", seed=2, max_steps=10))
    rivals = [(e.pose, e.runner_up) for e in estimates if e.runner_up is not None]
    assert len(rivals) > 5
    assert not any(object_tracks.near(np.asarray([runner]), np.asarray([pose]), 0.25 * UNIT,
                                     np.deg2rad(5.0))[0, 0] for pose, runner in rivals)


def test_the_reported_pose_is_never_outweighed_by_its_runner_up(estimates):
    """Three fingers on an ellipse (seed 1, noise): the judge chose its leader among the
    tracks, then weighed it with the readings' shared offset, where its mirror image often
    weighed more (20 of 40 updates; on the emulated servos 306 of 349, a held-out client's
    count), and the estimate showed the lighter pose at 7 % beside its runner-up at 93 %.
    The heavier is now the estimate."""
    simulate_hand(HandSettings(object="ellipse", hand="three-finger", seed=1, noise=True,
                               max_steps=25))
    weighed = [(e.mode_mass, e.runner_up_mass) for e in estimates
               if e.mode_mass is not None and e.runner_up is not None]
    assert len(weighed) > 10
    assert all(runner <= mass for mass, runner in weighed), weighed


def test_the_rival_is_named_while_the_readings_since_a_turn_are_few() -> None:
    """A client from the docs alone: after each turn of two fingers on keyed (seed 2, no
    noise) the estimate gave its leader at 49 % and `runner_up` nil; the rival holding the
    other half is named now, as before the turn."""
    from service.episode.hand_episode import simulate_hand
    from service.episode.hand_scenario import HandSettings

    report = simulate_hand(HandSettings(object="keyed", hand="two-finger", seed=2,
                                        noise=False, max_steps=8))
    assert report.result.steps[-1].kind == "manipulate"  # the last step was a turn
    est = report.result.estimate
    assert est.mode_mass < 0.6 and est.runner_up is not None
    assert 0.3 < est.runner_up_mass <= 1.0 - est.mode_mass + 1e-9


def test_the_policy_weighs_a_pose_under_an_outline_off_alike_as_the_judge_does():
    """The world's outline may lie off the model's alike under every reading (B2's
    mismatch): the truth then misses each reading by the same amount, and a pose shifted by
    it fits them all. Weighed without the readings' shared offset, the members nearest the
    truth held at most 7e-5 of the weight the gate guards by, and two fingers dropped
    ellipse:66 (seed 66, with the tracks alone weighing the offset); with it the two are
    alike within a few nats (`ObjectParticles.hypotheses`)."""
    settings = HandSettings(object="blob:3", hand="three-finger", noise=True)
    parts = load_parts(settings)
    loc = build_localizer(settings, parts, np.random.default_rng(0))
    ctx = loc.ctx
    truth = np.zeros(3)
    shifted = np.array([0.0004, 0.0, 0.0])  # outward where the readings are (the right)
    tip = parts.hand.fingers[0].radius
    arc = np.linspace(-1.5, 1.5, 6) * 1e-3
    points = _on_outline(ctx, truth, arc, tip + 0.0004)  # the world 0.4 mm larger there
    loc.poses, loc.prior = np.vstack([truth, shifted]), np.zeros(2)
    loc.points, loc.radii = points, np.full(len(arc), tip)
    loc.resid = contour_fit.residuals(ctx.field, loc.poses, loc.points, loc.radii)
    plain = contour_fit.fit_log_likelihood(ctx.field, loc.poses, loc.points, loc.radii,
                                           ctx.sigma, ctx.outlier_probability,
                                           ctx.outlier_range)
    assert plain[1] - plain[0] > 8.0  # without the offset the truth is all but ruled out
    weights = dict(zip(map(tuple, loc.hypotheses().poses), loc.hypotheses().weights,
                       strict=True))
    assert weights[tuple(truth)] > grasp_gated.LIKELY


@pytest.mark.parametrize(("seed", "steps"), [(19, 55), (37, 49)])
def test_no_half_turned_image_of_two_lobes_half_a_millimetre_apart_is_declared(seed, steps):
    """A helper's outline of two lobes, radii 15 and 15.5 mm
    (`data/two_lobes_half_mm_apart.csv`), three fingers, B2's noise: the half-turned image
    was declared, 0.4 mm and 179.2 degrees off claiming 0.22 mm and 0.5 degrees (seed 19, at
    step 55; seed 37 alike, at step 49). The tracks and the final weighing count the
    readings of a patch as one whatever they say. Weighed with their errors shared over
    each patch, each pose fitted so, the image fitted seed 19's 64 readings at step 55
    better than the declared pose by 5.3 in chi-square (`object_judge._correlated_mass`)."""
    report = simulate_hand(HandSettings(object=str(DATA / "two_lobes_half_mm_apart.csv"),
                                        hand="three-finger", seed=seed, noise=True,
                                        max_steps=steps))
    assert not report.score.wrong_declaration
    # and says why, with the share the shared weighing gives (a few %, not 99.9)
    assert "once the readings' errors are weighed as shared" in report.result.estimate.held_back

"""Honest declarations for a held object: the judgement every object localizer's leader must
pass, over its mode tracks (`object_tracks`).

As for a finger (`convergence.py`): the leader's images under the object's near symmetries
join the tracks, since a bounded pool may never have sampled the rotated pose that explains
everything equally.

A pose is declared only when it leads with almost all the probability among the tracks, its
least-squares refinement explains every reading since the last manipulation at about the
sensor's noise and pins the pose tightly, there is enough evidence (distinct places felt),
and it agrees with the previous update's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from service.localization.localizers.base import Budget
from service.localization.localizers.contour_fit import (
    assess,
    distinct_places,
    fit_log_likelihood,
    gauss_newton,
    refine,
    residuals,
)
from service.localization.localizers.convergence import ConvergenceRule, distinct, share_text
from service.localization.localizers.object_base import ObjectContext
from service.localization.localizers.object_certificate import rivals_beyond
from service.localization.localizers.object_tracks import ObjectTracks, near, tolerance
from service.localization.localizers.refine import Fit
from service.localization.localizers.shared_error import (
    correlated_fits,
    offset_log_likelihood,
    offset_refit,
    patch_temper,
    widened,
    with_shared_error,
)
from service.localization.objects.symmetry import images

REFINED_RIVALS = 2
FRESH = 4
"""Readings since the last manipulation (or the first grasp) the tracks are weighed on
afresh; with fewer, the tracks stand as they are and no pose is declared (`_as_tracked`).
A policy that turns the object before this many learns nothing the judge can confirm."""
ADOPT = 1e-5
"""Least weight, relative to the leader's, at which a pose the whole-object check found
(`object_certificate`) joins the tracks: the localizer had lost it, and the next updates
must weigh it. Low enough that rivals which hold a declaration back only together join
too: else the check refuses at every step while the tracks never learn why."""
FOUND_WEIGHED = 4
"""Most poses the whole-object check found, heaviest first, that `confirm` weighs again
with the readings' errors shared (`_correlated_mass`: a fit of each), beside the rivals."""


@dataclass(frozen=True)
class ObjectVerdict:
    fit: Fit | None
    mode_mass: float
    runner_up: tuple[float, float, float] | None
    runner_up_mass: float
    converged: bool
    found: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    """Poses the whole-object check found that the tracks did not hold (`_whole_object`):
    a localizer that lost them should weigh them again."""
    awaiting: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """Every other check passed: the leader's readings, radii and sds the whole-object
    check (`confirm`) is still to be run on before the pose is declared."""
    rivals: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    """With `awaiting`: the rivals and images the final weighing set beside the fit, which
    `confirm` weighs again with the readings' errors shared."""
    leader: tuple[float, float, float] | None = None
    """With no `fit`, the pose `mode_mass` and `runner_up` are reckoned beside (the tracks'
    heaviest): the estimate shows it, so it is never shown beside itself as its own rival."""
    held_back: str = ""
    """What holds the declaration back, in words, as a finger's judge says it (a held-out
    lab's "not yet" named three possible causes and not which)."""

    @property
    def pose(self) -> tuple[float, float, float] | None:
        """The pose the verdict leads with: the fit's, else the tracks' leader."""
        return self.fit.pose if self.fit is not None else self.leader


def judge(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray, tracks: ObjectTracks, *,
          rule: ConvergenceRule, noisy: bool, places_before: int, epoch: int,
          previous: tuple[float, float, float] | None, motions: np.ndarray) -> ObjectVerdict:
    """Weigh the tracks (and the leader's near-symmetric images), refine the leader on its
    readings (those since the last manipulation, and those its motions carried) and ask
    `rule` whether to declare it.

    `places_before` counts the distinct places felt before the last manipulation: their
    evidence lives on in the priors, and counts towards enough readings. After `epoch`
    manipulations only a track carried through all of them may be declared: a pose found
    since has never been asked to explain the readings from before."""
    if len(tracks.centres) == 0:
        return ObjectVerdict(None, 0.0, None, 0.0, False, held_back="no pose fits the readings")
    if len(points) < FRESH:
        return _as_tracked(ctx, tracks, motions, points, radii)
    scale = ctx.scale
    sigma = ctx.sigma
    sd = max(sigma, 0.01 * scale)
    tol_pos, tol_head = tolerance(ctx)
    total = tracks.total
    lead = int(np.argmax(total))
    mirrored, image_prior = _images(ctx, tracks, lead, tracks.centres[lead], motions, points,
                                    radii)
    centres = np.vstack([tracks.centres, mirrored])
    prior = np.concatenate([tracks.prior, image_prior])
    temper = patch_temper(ctx, points)
    score = prior + temper * fit_log_likelihood(ctx.field, centres, points, radii, sd,
                                                ctx.outlier_probability, ctx.outlier_range)
    order = distinct(centres, score, tol_pos, tol_head)
    share = np.exp(score[order] - score[order[0]])
    share /= share.sum()
    runner = tuple(float(v) for v in centres[order[1]]) if len(order) > 1 else None
    runner_mass = float(share[1]) if len(order) > 1 else 0.0
    mass = float(share[0])
    best = centres[order[0]]
    # the leader's fit uses every reading it has: what its motions carried, and the latest
    lead_points, lead_radii, lead_sd = points, radii, np.full(len(points), sigma)
    if order[0] < len(tracks.centres):
        lead_points, lead_radii, lead_sd = tracks.history(int(order[0]), points, radii, sigma)
    places = places_before + distinct_places(points, 0.25 * scale)
    fit = _floored(ctx, lead_points, lead_radii, assess(ctx.field, lead_points, lead_radii,
                                                        best, lead_sd))
    enough_here = distinct_places(points, 0.25 * scale) >= 2
    converged = False
    held = ("" if enough_here else "the readings since the last turn lie in one place") or \
        rule.loosened().unmet(readings=places - 1, noisy=noisy, mode_mass=mass, fit=fit,
                              step_length=scale)
    if not held:
        outliers = len(points) // 8 if noisy else 0
        fit = offset_refit(ctx, lead_points, lead_radii, lead_sd, refine(
            ctx.field, lead_points, lead_radii, best, lead_sd, max_outliers=outliers), outliers)
        rivals = [i for i, w in zip(order[1:1 + REFINED_RIVALS], share[1:1 + REFINED_RIVALS],
                                    strict=False) if w > 1e-6]
        fits = [fit] + [refine(ctx.field, points, radii, centres[i], sigma,
                               max_outliers=outliers) for i in rivals]
        ll = prior[[order[0]] + rivals] + offset_log_likelihood(
            ctx, np.array([f.pose for f in fits]), points, radii, max(sigma, 0.002 * scale),
            temper)
        rivals_ll, images, images_ll = _rivals_beside(
            ctx, tracks, order[0], fit, centres[rivals], ll[1:], prior[rivals],
            motions, points, radii, temper)
        ll = np.concatenate([ll[:1], rivals_ll, images_ll])
        others = np.vstack([np.array([f.pose for f in fits[1:]]).reshape(-1, 3), images])
        # one refined or polished onto the leader's pose is the leader, not its rival: a
        # near-circle's images split the mass between poses 0.04 mm and 0.3 degrees apart,
        # 25 % and 29 %, and no hand ever localized it (a helper's outline, seeds 0-29)
        same = near(others, np.asarray([fit.pose]), tol_pos, tol_head)[:, 0]
        ll[0] = max(ll[0], ll[1:][same].max(initial=-np.inf))
        ll, others = np.concatenate([ll[:1], ll[1:][~same]]), others[~same]
        rest = share[1 + len(rivals):].sum()
        w = np.exp(ll - ll.max())
        w = w / w.sum() * (1.0 - rest)
        # the leader's mass and the heaviest other's, as they were weighed (a mirror that
        # fits better was "0 %" beside its "50 %")
        mass = float(w[0])
        if len(others):
            j = int(np.argmax(w[1:]))
            runner, runner_mass = tuple(float(v) for v in others[j]), float(w[1 + j])
            if runner_mass > mass:  # this weighing prefers another pose: it is the estimate
                return _reported_instead(ctx, points, radii, runner, runner_mass, fit.pose,
                                         mass)
        fit = with_shared_error(ctx, lead_points, lead_radii, lead_sd, widened(
            _floored(ctx, lead_points, lead_radii, fit), patch_temper(ctx, lead_points)))
        held = rule.unmet(readings=places - 1, noisy=noisy, mode_mass=mass, fit=fit,
                          step_length=scale)
        if not held and not (order[0] < len(tracks.centres)
                             and tracks.carries[int(order[0])] >= epoch):
            held = "it was found since the last turn: the readings before it are not its own"
        if not held and noisy and not (previous is not None and bool(near(
                np.asarray([fit.pose]), np.asarray([previous]), rule.max_position_sd * scale,
                rule.max_heading_sd)[0, 0])):
            held = "it moved since the last reading: not settled yet"
        if not held and not noisy and len(lead_points) > len(points) and not _carried_agree(
                ctx, points, radii, fit):
            held = ("the readings since the last turn fit a pose of their own better than the "
                    "readings carried through it allow")
        converged = not held
    # the whole-object check, which costs most, is left to `confirm`
    return ObjectVerdict(fit, mass, runner, runner_mass, False,
                         awaiting=(lead_points, lead_radii, lead_sd) if converged else None,
                         rivals=others if converged else np.empty((0, 3)), held_back=held)


def _correlated_mass(ctx: ObjectContext, fit: Fit, others: np.ndarray, points: np.ndarray,
                     radii: np.ndarray, sd: np.ndarray) -> float:
    """The share of `fit`'s pose beside `others` (rivals, images, poses found anywhere) on
    the readings it kept, each pose fitted with the readings' errors weighed as shared
    (`shared_error.correlated_fits`), one per place they end (the best), those ending
    within the tolerance of the fit's pose counting as it. 0 if the fit's own pose,
    so fitted, slides beyond the tolerance: a pose nearby fits better."""
    kept = np.arange(len(points)) if fit.kept is None else fit.kept
    ends, chi2 = correlated_fits(ctx, np.vstack([[fit.pose], others]), points[kept],
                                 radii[kept], sd[kept])
    tol = tolerance(ctx)
    same = near(ends, np.asarray([fit.pose]), *tol)[:, 0]
    if not same[0]:
        return 0.0
    order = distinct(ends, -chi2, *tol)
    w = np.exp(-0.5 * (chi2[order] - chi2[order].min()))
    return float(w[same[order]].sum() / w.sum())


SPLIT_CHI2 = 11.34
"""The chi-square (3 degrees of freedom, 1 % beyond it) by which the readings since the last
manipulation may fit the leader worse than they fit a pose of their own (`_carried_agree`)."""


def _carried_agree(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray, fit: Fit
                   ) -> bool:
    """Without noise, whether the readings carried through a manipulation agree with those
    since: the latter, exact, may fit the leader (fitted on both) worse than they fit a
    pose refined on them alone by at most `SPLIT_CHI2`. Readings carried on a track that
    was off when it was carried moved with its error, which their sd (`CARRIED_SD`) does
    not hold, and a fit that splits the difference claims the spread of both: three fingers
    on blob:37 (seed 7) declared a pose 1.7 degrees off claiming an sd of 0.27, missing the
    four exact readings since the turn by up to 2.8 sds."""
    own = refine(ctx.field, points, radii, np.asarray(fit.pose), ctx.sigma, max_outliers=0)
    chi2 = np.sum((residuals(ctx.field, np.array([fit.pose, own.pose]), points, radii)
                   / ctx.sigma) ** 2, axis=1)
    return bool(chi2[0] - chi2[1] <= SPLIT_CHI2)


def _as_tracked(ctx: ObjectContext, tracks: ObjectTracks, motions: np.ndarray,
                points: np.ndarray, radii: np.ndarray) -> ObjectVerdict:
    """The verdict with too few readings since the last manipulation to weigh afresh (under
    `FRESH`): no fit and no declaration, the tracks' modes as they stand, with the leader's
    near-symmetric images (`_images`) among them as `judge` weighs them - the leader's share
    and the heaviest other's. (A client saw `runner_up` nil beside a leader at 49 % after
    each turn of two fingers on keyed, seed 2: the mass was one track's, the rival unsaid.
    A held-out check saw three fingers end on an ellipse, after a turn, at "100 %" half a
    turn from the truth: the mirror, never a track, went unweighed.)"""
    tol_pos, tol_head = tolerance(ctx)
    lead = int(np.argmax(tracks.total))
    mirrored, image_prior = _images(ctx, tracks, lead, tracks.centres[lead], motions, points,
                                    radii)
    # an image explains the readings since the turn as the leader does: its own prior, and
    # the leader's evidence since
    since = tracks.total[lead] - tracks.prior[lead]
    centres = np.vstack([tracks.centres, mirrored])
    total = np.concatenate([tracks.total, image_prior + since])
    order = distinct(centres, total, tol_pos, tol_head)
    share = np.exp(total[order] - total[order[0]])
    share /= share.sum()
    leader = tuple(float(v) for v in centres[order[0]])
    held = (f"{len(points)} readings since the last turn, of the {FRESH} needed to weigh the "
            "poses afresh")
    if len(order) < 2:
        return ObjectVerdict(None, float(share[0]), None, 0.0, False, leader=leader,
                             held_back=held)
    return ObjectVerdict(None, float(share[0]), tuple(float(v) for v in centres[order[1]]),
                         float(share[1]), False, leader=leader, held_back=held)


def _reported_instead(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray,
                      heavier: tuple[float, float, float], heavier_mass: float,
                      leader: tuple[float, float, float], leader_mass: float,
                      found: np.ndarray | None = None) -> ObjectVerdict:
    """The verdict when the final weighing (the readings' shared offset counted) puts a rival
    or image above the leader the tracks chose, or the whole-object check finds a pose that
    outweighs it: the heavier is reported, the leader is its runner-up, and nothing is
    declared until they agree. An ellipse on the emulated servos (three fingers, seed 2, no
    noise): the estimate was shown at 7 % beside its mirror image at 93 %, which the
    encoders' rounding favoured."""
    fit = _floored(ctx, points, radii, assess(ctx.field, points, radii, np.asarray(heavier),
                                              ctx.sigma))
    return ObjectVerdict(fit, heavier_mass, leader, leader_mass, False,
                         np.empty((0, 3)) if found is None else found,
                         held_back="another pose weighs more once the readings' shared "
                                   "error is counted")


def confirm(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray, tracks: ObjectTracks,
            verdict: ObjectVerdict, rule: ConvergenceRule) -> ObjectVerdict:
    """The verdict once the whole-object check (`_whole_object`) has weighed the poses the
    tracks may have lost: converged if none fits comparably; else not, with the heaviest as
    the runner-up, and those found joining the tracks."""
    if verdict.awaiting is None or verdict.fit is None:
        return verdict
    lead_points, lead_radii, lead_sd = verdict.awaiting
    tol_pos, tol_head = tolerance(ctx)
    share, heaviest, ratio, found = _whole_object(ctx, lead_points, lead_radii, lead_sd,
                                                  verdict.fit, tracks.centres)
    # the tracked rivals' weight is in the verdict's mass, the rest in `share`
    mass, runner, runner_mass = verdict.mode_mass * share, verdict.runner_up, \
        verdict.runner_up_mass
    converged = mass >= rule.mode_mass
    if heaviest is not None and mass * ratio > runner_mass:  # its own weight, not the rest's
        runner, runner_mass = heaviest, mass * ratio
    tracks.adopt(ctx, found, points, radii, sd=max(ctx.sigma, 0.002 * ctx.scale),
                 position_tol=tol_pos, heading_tol=tol_head)
    if heaviest is not None and ratio > 1.0:  # a pose it found weighs more than the leader
        return _reported_instead(ctx, points, radii, heaviest, mass * ratio, verdict.fit.pose,
                                 mass, found)
    held = "" if converged else (
        f"its share {share_text(mass)} beside the poses the whole-object check found, of the "
        f"{share_text(rule.mode_mass)} needed")
    # and beside every rival, with the readings' errors weighed as the world makes them
    others = np.vstack([verdict.rivals, found[:FOUND_WEIGHED]])
    if converged and ctx.mismatch_length > 0 and ctx.mismatch_sd > 0 and len(others):
        shared = _correlated_mass(ctx, verdict.fit, others, lead_points, lead_radii, lead_sd)
        if shared < rule.mode_mass:  # the share said, as every other check says its own
            converged, held = False, (
                f"its share {share_text(shared)} once the readings' errors are weighed as "
                f"shared over each patch, of the {share_text(rule.mode_mass)} needed")
    return ObjectVerdict(verdict.fit, mass, runner, runner_mass, converged, found,
                         held_back=held)


def _whole_object(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray,
                  sd: np.ndarray, fit: Fit, tracked: np.ndarray
                  ) -> tuple[float, tuple[float, float, float] | None, float, np.ndarray]:
    """The leader's share against the poses beyond its tolerance, and beside no `tracked`
    pose (the judge weighed those), that explain its readings best anywhere on the object
    (`object_certificate.rivals_beyond`), weighed as the final comparison weighs its
    rivals; the heaviest of them and its weight against the leader's; and those that keep
    at least `ADOPT` of the leader's weight, heaviest first.

    The readings are the leader's whole history (`ObjectTracks.history`: what its motions
    carried, with their noise, and the latest), as its images are judged: asked only of
    the readings since the last turn, a pose the pool had lost fitted those few as well as
    the leader, and three fingers on keyed and rounded, once they had turned the object,
    declared 16 and 14 fewer of members 0-99 (B6)."""
    sd = np.maximum(sd, 0.002 * ctx.scale)
    tol_pos, tol_head = tolerance(ctx)
    found = rivals_beyond(ctx.field, points, radii, np.asarray(fit.pose), sd=sd,
                          outlier_probability=ctx.outlier_probability,
                          outlier_range=ctx.outlier_range, position_tol=tol_pos,
                          heading_tol=tol_head)
    found = found[~np.any(near(found, tracked, tol_pos, tol_head), axis=1)]
    if len(found) == 0:
        return 1.0, None, 0.0, found
    ll = offset_log_likelihood(ctx, np.vstack([np.asarray(fit.pose), found]), points, radii,
                                sd, patch_temper(ctx, points))
    w = np.exp(ll[1:] - ll[0])
    order = np.argsort(-w, kind="stable")
    heaviest = tuple(float(v) for v in found[order[0]])
    return (float(1.0 / (1.0 + w.sum())), heaviest, float(w[order[0]]),
            found[order[w[order] >= ADOPT]])


def _rivals_beside(ctx: ObjectContext, tracks: ObjectTracks, leader: int, fit: Fit,
                   rivals: np.ndarray, refined_ll: np.ndarray, rivals_prior: np.ndarray,
                   motions: np.ndarray, points: np.ndarray, radii: np.ndarray,
                   temper: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The final comparison's rivals judged fairly: each refined rival (`refined_ll`) at no
    worse than where it started, and the refined leader's own images, which fit as well as
    it does except where the one feature tells them apart. Returns the rivals' log
    likelihoods, raised by any image beside them, and the other images with theirs.

    From 5 readings of three fingers, a refinement took an ellipse's half-turned image 6
    degrees off onto a poorer fit, and the leader was declared at 0.9997 against its exact
    mirror (ellipse:14, seed 14, three fingers)."""
    sd = max(ctx.sigma, 0.002 * ctx.scale)
    rivals_ll = refined_ll.copy()
    if len(rivals):
        rivals_ll = np.maximum(rivals_ll, rivals_prior + offset_log_likelihood(
            ctx, rivals, points, radii, sd, temper))
    if leader >= len(tracks.centres):
        return rivals_ll, np.empty((0, 3)), np.empty(0)
    mirrored, prior = _images(ctx, tracks, leader, np.asarray(fit.pose), motions, points,
                              radii)
    if len(mirrored) == 0:
        return rivals_ll, np.empty((0, 3)), np.empty(0)
    ll = prior + offset_log_likelihood(ctx, mirrored, points, radii, sd, temper)
    beside = near(mirrored, rivals, *tolerance(ctx))
    for i, row in enumerate(beside):
        if row.any():
            j = int(np.argmax(row))
            rivals_ll[j] = max(rivals_ll[j], ll[i])
    alone = ~beside.any(axis=1)
    return rivals_ll, mirrored[alone], ll[alone]


def _images(ctx: ObjectContext, tracks: ObjectTracks, lead: int, pose: np.ndarray,
            motions: np.ndarray, points: np.ndarray, radii: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """`pose`'s images under the object's near symmetries, and their prior: track `lead`'s,
    plus how much better or worse they explain what it felt before (where the one feature
    tells them apart). The images and `pose` are polished alike, on everything the track
    has: polished on the latest readings alone, an ellipse's exact mirror slid where those
    few did not hold it, then explained what the leader felt 85 nats worse, and the leader
    was declared against it (ellipse:14, seed 14, three fingers)."""
    mirrored = images(pose, motions)
    prior = np.full(len(mirrored), tracks.prior[lead])
    if len(mirrored) == 0:
        return mirrored.reshape(0, 3), prior
    every, every_radii, every_sd = tracks.history(lead, points, radii, ctx.sigma)
    polished = gauss_newton(ctx.field, np.vstack([pose[np.newaxis], mirrored]), every,
                            every_radii, 1.0 / np.maximum(every_sd, 1e-9) ** 2,
                            iterations=10, max_move=0.25 * ctx.scale)
    felt = tracks.felt[lead]
    if len(felt):
        ll = fit_log_likelihood(ctx.field, polished, felt[:, :2], felt[:, 2],
                                np.sqrt(max(ctx.sigma, 0.002 * ctx.scale) ** 2 + felt[:, 3]),
                                ctx.outlier_probability, ctx.outlier_range)
        prior += patch_temper(ctx, felt[:, :2]) * (ll[1:] - ll[0])
    return polished[1:], prior


def _floored(ctx: ObjectContext, points: np.ndarray, radii: np.ndarray, fit: Fit) -> Fit:
    """`fit` with its spread recomputed at a reading sd of at least 0.05 % of the scale,
    so a noise-free run's spread says how well the shape of the readings fixes the pose
    (as `convergence._with_floored_spread`)."""
    floor = max(ctx.sigma, 0.0005 * ctx.scale)
    if floor <= ctx.sigma:
        return fit
    spread = assess(ctx.field, points, radii, np.asarray(fit.pose), floor)
    return dataclasses.replace(fit, position_sd=spread.position_sd,
                               heading_sd=spread.heading_sd)


class TrackJudged:
    """The judgement both object localizers end an update with: their leading poses feed
    the mode tracks, and the tracks are judged (`judge`). Expects the localizer's context,
    readings (`points`, `radii`), `tracks`, `rule`, `sigma`, `noisy`, `places_before`,
    `epoch` and `motions`."""

    _awaiting: ObjectVerdict | None = None
    """The latest verdict, when only the whole-object check stands between it and a
    declaration: `background` runs the check (the estimate is `pending` meanwhile)."""

    def _judge_leaders(self, poses: np.ndarray, prior: np.ndarray, previous: Fit | None
                       ) -> ObjectVerdict:
        """Track `poses` (with their `prior`), judge against the `previous` update's fit,
        and keep the verdict's fit and modes."""
        tol_pos, tol_head = tolerance(self.ctx)
        self.tracks.update(self.ctx, self.points, self.radii, poses, prior,
                           sd=max(self.sigma, 0.002 * self.ctx.scale), position_tol=tol_pos,
                           heading_tol=tol_head)
        v = judge(self.ctx, self.points, self.radii, self.tracks, rule=self.rule,
                  noisy=self.noisy, places_before=self.places_before, epoch=self.epoch,
                  previous=None if previous is None else previous.pose, motions=self.motions)
        self._keep_verdict(v)
        self._awaiting = v if v.awaiting is not None else None
        return v

    leader: tuple[float, float, float] | None = None
    """The pose the latest verdict leads with (`ObjectVerdict.pose`)."""

    held_back = ""
    """What the latest verdict says holds the declaration back (`ObjectVerdict.held_back`)."""

    def _keep_verdict(self, v: ObjectVerdict) -> None:
        self.fit, self.converged, self.mode_mass = v.fit, v.converged, v.mode_mass
        self.held_back = v.held_back
        self.leader = v.pose
        self.runner_up, self.runner_up_mass = v.runner_up, v.runner_up_mass

    @property
    def pending(self) -> bool:
        """Only the whole-object check stands between the estimate and a declaration."""
        return self._awaiting is not None

    def background(self, budget: Budget) -> bool:
        """The whole-object check a declaration waits on (`confirm`), between updates: the
        update itself stays bounded, and a declaration it allows costs no move (`settle`).
        One piece of work: it runs whole whatever the budget."""
        if self._awaiting is None:
            return True
        v = confirm(self.ctx, self.points, self.radii, self.tracks, self._awaiting, self.rule)
        self._awaiting = None
        self._keep_verdict(v)
        if len(v.found):
            self._found(v.found)
        return True

    def _found(self, poses: np.ndarray) -> None:
        """Poses the whole-object check found that the localizer had lost (its pool takes
        them in, if it has one)."""

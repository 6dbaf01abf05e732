"""Honest convergence: no wrong declarations on an ambiguous surface, and the rule itself."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from service.episode.scenario import RunSettings
from service.episode.simulate import simulate
from service.localization.localizers.convergence import (
    ConvergenceRule,
    distinct,
    group_modes,
    share_text,
)
from service.localization.localizers.refine import Fit
from service.localization.localizers.sweep import turns_to_check
from service.localization.localizers.symmetry import (
    _convolve,
    images,
    revolution_centre,
    symmetries,
)
from service.localization.maps import bumps, eggcrate, load_map, peaks
from service.localization.surface import contact_surface


@pytest.mark.parametrize("name", ["particles", "grid"])
@pytest.mark.parametrize("noise", [False, True])
def test_egg_crate_gets_no_wrong_declaration(name, noise):
    crate = eggcrate()
    for seed in (1, 2, 3):  # seed 2, noise-free: particles once declared a half-turn image
        report = simulate(RunSettings(map="eggcrate", algorithm=name, policy="info-gain",
                                      seed=seed, noise=noise, max_steps=25), crate)
        assert not report.score.wrong_declaration, f"{name} seed {seed} declared wrongly"


def test_a_chance_fit_of_a_few_noisy_readings_is_not_declared():
    """bumps:20:1, seed 8: at 7 readings a pose 27 mm and 87 degrees off fitted all of
    them at 0.96 sigma RMS and was declared, when the pool had never held the truth."""
    report = simulate(RunSettings(map="bumps:20:1", seed=8, noise=True, max_steps=60),
                      bumps(20, seed=1))
    assert not report.score.wrong_declaration
    assert report.score.success


def test_egg_crate_symmetries_read_the_same_heights():
    surface = contact_surface(eggcrate(), 0.008)
    motions = symmetries(surface)
    assert len(motions) > 10 and set(motions[:, 0]) == {0.0, 1.0, 2.0, 3.0}
    pose = np.array([0.07, 0.11, 0.4])
    rivals = images(surface, pose, motions)
    x_max, _ = surface.map.extent
    on_map = np.all((rivals[:, :2] > 0.02) & (rivals[:, :2] < x_max - 0.02), axis=1)
    here = surface.height(0.07, 0.11)
    for x, y, _ in rivals[on_map]:
        assert surface.height(x, y) == pytest.approx(here, abs=1e-6)
    assert len(symmetries(contact_surface(bumps(20, seed=1), 0.008))) == 0


@given(st.integers(1, 40), st.integers(1, 40), st.integers(1, 40), st.integers(1, 40),
       st.integers(0, 2**32 - 1))
@settings(max_examples=40, deadline=None)
def test_the_symmetry_finders_convolution_is_scipys(h1, w1, h2, w2, seed) -> None:
    rng = np.random.default_rng(seed)
    a, b = rng.normal(size=(h1, w1)), rng.normal(size=(h2, w2))
    np.testing.assert_allclose(_convolve(a, b), signal.fftconvolve(a, b), atol=1e-9)


def _fit(**kw) -> Fit:
    base = dict(pose=(0.1, 0.1, 0.0), position_sd=1e-4, heading_sd=0.005, rms=1.0,
                max_abs=2.0, readings=8)
    base.update(kw)
    return Fit(**base)


def test_rule_needs_readings_mass_fit_and_tightness():
    rule = ConvergenceRule()
    ok = dict(readings=8, noisy=True, mode_mass=0.9999, fit=_fit(), step_length=0.01)
    assert rule.holds(**ok)
    assert not rule.holds(**{**ok, "readings": 3})
    assert not rule.holds(**{**ok, "mode_mass": 0.9})
    assert not rule.holds(**{**ok, "fit": _fit(rms=5.0)})
    assert not rule.holds(**{**ok, "fit": _fit(position_sd=2e-3)})
    assert not rule.holds(**{**ok, "fit": None})
    assert rule.loosened().holds(**{**ok, "fit": _fit(position_sd=1e-3)})


def test_only_a_spread_that_counts_the_shared_error_may_be_looser():
    """With noise the spread is the sandwich that counts the map's shared error, and 0.07
    steps passes; without noise it is the fit's own at a floored sd, held to 0.06."""
    rule = ConvergenceRule()
    fit = _fit(position_sd=0.07 * 0.01, max_abs=1.0)
    assert rule.holds(readings=8, noisy=True, mode_mass=0.9999, fit=fit, step_length=0.01)
    assert not rule.holds(readings=8, noisy=False, mode_mass=0.9999, fit=fit,
                          step_length=0.01)


def test_a_larger_map_asks_one_more_reading_per_doubling_of_its_area():
    step = 0.01
    assert ConvergenceRule.for_map((0.2, 0.2), step) == ConvergenceRule()  # B1's map
    assert ConvergenceRule.for_map((0.1, 0.1), step) == ConvergenceRule()
    assert ConvergenceRule.for_map((1.0, 0.0), step) == ConvergenceRule()  # a profile
    for extent, extra in [((0.4, 0.2), 1), ((0.4, 0.4), 2), ((0.8, 0.8), 4)]:
        rule = ConvergenceRule.for_map(extent, step)
        assert rule.min_readings_noisy == ConvergenceRule.min_readings_noisy + extra
        assert rule.min_readings == ConvergenceRule.min_readings + extra
        ok = dict(readings=rule.min_readings_noisy, noisy=True, mode_mass=0.9999, fit=_fit(),
                  step_length=step)
        assert rule.holds(**ok)
        assert not rule.holds(**{**ok, "readings": rule.min_readings_noisy - 1})


def test_modes_group_and_merge():
    poses = np.array([[0.1, 0.1, 0.0], [0.1005, 0.1, 0.01], [0.15, 0.1, 0.0]])
    modes = group_modes(poses, np.array([3.0, 2.0, 1.0]), 0.0025, np.deg2rad(5))
    assert modes.masses.tolist() == pytest.approx([5 / 6, 1 / 6])
    assert modes.labels.tolist() == [0, 0, 1]
    assert distinct(poses, np.array([1.0, 2.0, 0.5]), 0.0025, np.deg2rad(5)).tolist() == [1, 2]


@pytest.mark.parametrize("surface, seed, why", [
    ("plate:20:1", 0, "23 mm off along a rib: the readings never saw that direction, and "
                      "a singular fit's pseudo-inverse called it certain"),
    ("terrain:20:0", 7, "3.8 mm and 4.3 degrees off: a better fit a few millimetres away "
                        "had been merged into the leader's mode"),
    ("plate:20:1", 7, "a half turn: the plate's near symmetry (0.85 correlation) went "
                      "unnoticed, its image untested"),
    ("pattern:20:1", 4, "a quarter turn of four holes, before any reading touched the "
                        "feature that breaks the pattern"),
    ("profile:plate:20:2", 0, "3.1 mm off: one plate edge in a flat valley of misfit"),
    ("profile:shell:20:1", 2, "3.6 mm off: a valley 5 mm wide, its curvature claimed 0.46"),
    ("profile:terrain:20:2", 1, "3.0 mm off: errors of the map that correlate over a step"),
    ("profile:terrain:20:2", 17, "3 mm off (`haptic bench profile`'s near miss): the "
                                 "valley's misfit weighed the readings as independent"),
    ("plate:20:2", 5, "a half turn about a pocket: the sweep judged cells on the flat "
                      "readings round the start, and the truth's cell never made its hand"),
    ("plate:20:1", 16, "a half turn, 111 mm off, at a leading-mode mass of 1"),
    ("plate:20:1", 2, "a quarter turn about a square pocket: the truth's cells were handed "
                      "over but three Gauss-Newton steps left them short of it"),
    ("pattern:20:7", 1, "a quarter turn, 21 mm off, on a surface no benchmark uses: the "
                        "truth's refined fit (chi-square 5.6 on 15 readings) beat the "
                        "declared one's (5.9), but the sweep never handed its cell over"),
    ("plate:20:5", 5, "a quarter turn, 60 mm off, on a surface no benchmark uses: the "
                      "truth's cell ranked 109th of the turned poses, and at one sd for "
                      "every reading a wall made it 17 nats worse than the declared pose"),
    ("plate:20:16", 1, "a quarter turn, 86 mm off, on a surface no benchmark uses"),
    ("plate:20:10", 12, "a half turn, 43 mm off, on a surface no benchmark uses"),
    ("pattern:20:16", 7, "a quarter turn, 45 mm off, on a surface no benchmark uses"),
    ("shell:20:5", 2, "4.2 mm off with a claimed sd of 0.6 mm: the map's error, shared by "
                      "nearby readings, moved the fit, and the spread assumed it did not"),
    ("shell:20:17", 13, "3.1 mm and 1.5 degrees off: a near miss, as shell:20:5"),
    ("plate:20:6", 13, "2.5 mm off with a claimed sd of 0.56 mm, as shell:20:5"),
    ("terrain:20:2", 16, "2.6 mm and 1.7 degrees off: a second local fit 1.3 mm away marked "
                         "a valley of misfit that reached the truth between the axes the "
                         "valley check scanned"),
    ("plate:20:3", 13, "a quarter turn, 47 mm off, under a turned check (not kept) that went "
                       "on through the leader's flips even once complete: the truth's cell "
                       "had been screened on the first 9 readings only"),
    # surfaces no benchmark uses (map seeds 3-17): strict xfails until the valley was
    # scanned toward the local fits nearby (`_valley_within`); since then both localize
    # on another route, and why the earlier routes declared wrongly was not traced further
    ("plate:20:10", 17, "a half turn, 31 mm off"),
    ("pattern:20:3", 10, "3.0 mm off at 11 claimed sds: the readings fit it, and a "
                         "least-squares fit started from the truth ran off the map"),
    # the second held-out check (map seeds 27-35), fixed by weighing the readings' shared
    # error when the leader must beat its rivals (`shared_error_mass`)
    ("terrain:20:33", 11, "2.1 mm and 5.3 degrees off at 0.45 mm / 0.7 degrees claimed"),
    ("shell:20:30", 0, "2.5 mm and 2.6 degrees off at 0.8 mm / 1.0 degrees claimed"),
    # the third (map seeds 40-43), fixed by the deep turned check between steps (`DEEP`)
    ("plate:20:40", 11, "a half turn, 113 mm off: the turned screen, whose misfit forgives "
                        "readings near a pocket's walls, ranked the truth's cells 1,272nd "
                        "and 1,842nd of 31,423, and each share of 8,192 polished its best 128"),
])
def test_no_wrong_declaration_where_one_was_found(surface, seed, why):
    assert not _declares_wrongly(surface, seed), why


@pytest.mark.parametrize("surface, seed, why", [
    ("pattern:20:22", 5, "a quarter turn, 34 mm off: the truth fits as well, but its turned "
                         "cell ranked 132nd-180th of its slice, behind cells crowding a few "
                         "flat places, and only the best 128 were screened and 16 polished"),
])
def test_no_wrong_declaration_on_surfaces_no_benchmark_uses(surface, seed, why):
    """Map seeds 18-26, which no benchmark runs and no change was tuned on (`haptic bench
    objects --map-seeds 18,...,26`): 2 wrong declarations in 720 runs on `b6c53f0`, 1 since
    the valley scan toward the local fits (shell:20:22, seed 17, a near miss, is no longer
    declared), none since the turned check polishes every turned pose that may still fit
    (`f697e28`)."""
    assert not _declares_wrongly(surface, seed), why


def test_no_near_miss_on_map_seeds_27_to_35():
    """A second held-out check (`haptic bench objects --map-seeds 27,...,35`, 720 runs):
    557 localized and 3 declared just past the tolerance, each at 4-8 of its claimed sds.
    Weighing the readings' shared error among the rivals fixed two (cases of
    `test_no_wrong_declaration_where_one_was_found`); shell:20:27 seed 1 was still declared
    2.5 mm and 0.5 degrees off at a claimed 0.5 mm, the readings pointing there (refined
    from the truth, the fit landed on the declared pose). Since the plan counts the error
    nearby readings share (`precision.Spread`) its walk reads other places and it
    localizes (41 steps, 1.1 mm off). The judge is as it was: such a tail can recur."""
    assert not _declares_wrongly("shell:20:27", 1)


def _declares_wrongly(surface: str, seed: int) -> bool:
    """Whether B2's noisy episode of `seed` on the preset `surface` declares a wrong pose."""
    report = simulate(RunSettings(map=surface, seed=seed, noise=True, max_steps=60),
                      load_map(surface))
    return report.score.wrong_declaration


def _valley_case(name: str, surface_name: str):
    """A recorded declaration's readings (tests/service/data/NAME.json) on the preset
    `surface_name`, ready for `_valley_within`: a callable taking its keyword options."""
    import json
    from pathlib import Path

    from service.episode.scenario import surface_for
    from service.localization.localizers.convergence import (
        FLOOR,
        _local_fits,
        _valley_within,
    )
    from service.localization.localizers.refine import assess, reading_sigmas

    case = json.loads((Path(__file__).parent / "data" / f"{name}.json").read_text())
    surface = surface_for(RunSettings(map=surface_name, noise=True), None)
    history, pose = np.array(case["history"]), np.array(case["pose"])
    step = case["step"]
    tol_pos, tol_head = 0.25 * step, np.deg2rad(5.0)
    assert np.hypot(*(np.array(case["truth"][:2]) - pose[:2])) > tol_pos  # it was wrong
    sds = reading_sigmas(surface, history, pose, case["sigma"], case["position_sigma"])
    fit = assess(surface, history, pose, sds)
    floored = np.maximum(sds, FLOOR * step)
    nearby = _local_fits(surface, history, pose, sds, tol_pos, tol_head)

    def valley_within(toward: bool, shared: bool = False) -> bool:
        return _valley_within(surface, history, fit, floored, tol_pos, tol_head,
                              case["margin"], toward=nearby if toward else None,
                              shared=(case["sigma"], step) if shared else None)

    return valley_within


def test_the_valley_is_scanned_toward_the_local_fits_nearby():
    """Readings under which a pose 2.6 mm and 1.7 degrees off the truth was declared
    (terrain:20:2, seed 16, step 26, by a version of the turned check that was not kept;
    BENCHMARKS.md): along its principal axes the misfit rises past the tolerance, but a
    second local fit 1.3 mm away marks a valley that reaches the truth between them, and
    the scan toward it finds a pose beyond the tolerance the readings allow. (The readings
    weighed as independent, as without noise; with noise their shared error shows the
    valley along the axes too.)"""
    valley_within = _valley_case("terrain_20_2_seed16_step26", "terrain:20:2")
    assert valley_within(toward=False)
    assert not valley_within(toward=True)
    assert not valley_within(toward=False, shared=True)


def test_the_valley_weighs_readings_that_err_together_as_one_error():
    """Readings under which a pose 3.3 mm and 0.5 degrees off the truth was declared
    (shell:20:42, seed 14, step 27): weighed as independent, every pose the scan reaches
    beyond the tolerance misfits by more than three sigmas, and the valley looked narrow;
    weighed with the error they share where the world differs from the map (as the spread
    is), the smooth shell allows poses beyond the tolerance, and nothing is declared."""
    valley_within = _valley_case("shell_20_42_seed14_step27", "shell:20:42")
    assert valley_within(toward=True)
    assert not valley_within(toward=True, shared=True)


def test_readings_that_err_together_are_weighed_as_one_error(texture_map):
    """Readings under which a pose 107 mm and a quarter turn off the truth was declared
    (`conftest.texture_with_a_bowl_and_a_bump`, B2's noise, seed 10, step 37): weighed as
    independent, they prefer it to the truth by 16.5 in chi-square, a share of 0.9997;
    weighed with the error they share where the world differs from the map (as the spread
    is), the truth keeps a share the declaration must not ignore."""
    import json
    from pathlib import Path

    from service.episode.scenario import surface_for
    from service.localization.localizers.convergence import FLOOR, shared_error_mass
    from service.localization.localizers.fitting import offset_residuals
    from service.localization.localizers.refine import reading_sigmas

    case = json.loads((Path(__file__).parent / "data" / "texture_bowl_bump_seed10.json")
                      .read_text())
    surface = surface_for(RunSettings(map=str(texture_map), spacing=0.001, noise=True), None)
    history, step = np.array(case["history"]), case["step"]
    poses = np.array([case["pose"], case["truth"]])
    assert np.hypot(*(poses[0, :2] - poses[1, :2])) > 0.1  # the declared pose was wrong
    sds = np.maximum(reading_sigmas(surface, history, poses[0], case["sigma"],
                                    case["position_sigma"]), FLOOR * step)
    resid, _ = offset_residuals(surface, poses, history, case["margin"])
    independent = np.sum((resid / sds) ** 2, axis=1)
    assert independent[1] - independent[0] > 2 * np.log(1 / (1 - 0.999))  # it would pass
    share = shared_error_mass(surface, history, poses, sds, case["sigma"], step,
                              case["margin"], 0.25 * step, np.deg2rad(5.0))
    assert 0.5 < share < ConvergenceRule.mode_mass


def test_no_wrong_declaration_on_the_texture_with_a_bowl_and_a_bump(texture_map):
    """The episode itself (B2's noise, seed 10): declared a quarter turn 107 mm off at step
    37 when the readings were weighed as independent; now it is not declared wrongly."""
    report = simulate(RunSettings(map=str(texture_map), spacing=0.001, noise=True, seed=10,
                                  max_steps=40))
    assert not report.score.wrong_declaration


def test_no_wrong_declaration_on_a_helpers_machined_plate(plate_map):
    """Declared 126 mm and 79 degrees off at step 28 (B2's noise, seed 148) when the readings
    were weighed as independent (`conftest.machined_plate`, which has no symmetry). It
    localizes now."""
    report = simulate(RunSettings(map=str(plate_map), spacing=0.001, noise=True, seed=148,
                                  max_steps=50))
    assert not report.score.wrong_declaration


def test_a_leader_is_not_given_the_share_of_an_image_that_fits_as_well(holes_map):
    """A held-out plate of 16 holes, one larger (`conftest.holes_grid`; B2's noise, seed 0):
    from step 45 the leader, a quarter turn and 107 mm from the truth, held 100 %. The truth
    is its image and fitted as well, but the image the map's symmetry made of the leader lay
    2.6 mm off it, beside the holes' walls, and polished to 3,000 nats worse. Only its
    spread (4.9 mm) kept it from being declared."""
    report = simulate(RunSettings(map=str(holes_map), spacing=0.001, noise=True, seed=0,
                                  max_steps=60))
    truth = np.array([report.truth.x, report.truth.y])
    for step in report.result.steps:
        off = np.hypot(*(np.asarray(step.estimate[:2]) - truth))
        assert step.mode_mass < 0.9 or off < 0.01, (step.index, step.mode_mass, off)
    assert not report.score.wrong_declaration


def test_a_reading_is_judged_against_all_the_error_it_is_expected_to_have():
    """The spread counts the map's error that nearby readings share; the rule's largest
    residual now does too (`Fit.max_abs_shared`): each reading over its own sd and that
    error together. Over its own sd alone, one reading 4.3 sds off kept plate:20:27, seed
    12, undeclared for 60 steps at 0.1 mm and 0.1 degrees from the truth."""
    rule = ConvergenceRule()
    fit = Fit(pose=(0.1, 0.1, 0.0), position_sd=0.0002, heading_sd=0.002, rms=1.1,
              max_abs=4.3, readings=40)

    def holds(f, noisy=True):
        return rule.holds(readings=40, noisy=noisy, mode_mass=1.0, fit=f, step_length=0.01)
    assert not holds(fit)  # the whole error not modelled: its own sd is all there is
    assert holds(dataclasses.replace(fit, max_abs_shared=4.3 / np.sqrt(2)))
    assert not holds(dataclasses.replace(fit, max_abs_shared=4.3))
    assert not holds(dataclasses.replace(fit, max_abs=6.5, max_abs_shared=2.0), noisy=False)
    report = simulate(RunSettings(map="plate:20:27", seed=12, noise=True, max_steps=60),
                      load_map("plate:20:27"))
    assert report.score.success


def test_a_noise_free_reading_is_judged_at_what_a_sampled_map_knows():
    """Without noise the sensor sd is 0.1 um, but the map is known between its samples only
    to about `FLOOR` steps (the spread is floored there already). Judged at 0.1 um, one
    reading beside a pocket's wall lay 23.65 sds off a fit on the truth, and plate:20:1,
    seed 0, held it at 100 % for 100 steps without a declaration."""
    report = simulate(RunSettings(map="plate:20:1", seed=0, noise=False, max_steps=60),
                      load_map("plate:20:1"))
    assert report.score.success, report.result.ended


@pytest.mark.parametrize("surface, seed", [("shell:20:11", 30), ("shell:20:17", 31)])
def test_a_noise_free_residual_is_not_judged_at_the_spreads_floor(surface, seed):
    """Judged at `FLOOR` (20 um at a 10 mm step), a held-out check found shell:20:11, seed
    30, declared 4.8 mm and 1.9 degrees off at a claimed 0.24 mm, and shell:20:17, seed 31,
    1.6 mm and 3.0 degrees off (a success, but far outside its claimed spread); each was
    exact before. Residuals have their own floor (`RESIDUAL_FLOOR`)."""
    report = simulate(RunSettings(map=surface, seed=seed, noise=False, max_steps=60),
                      load_map(surface))
    assert report.score.success and report.score.position_error < 1e-4


def test_turns_other_than_quarter_turns_are_found_and_their_images_read_alike(hex_map):
    """A hexagonal lattice repeats under turns of 60 degrees, which the quarter-turn search
    never tried: a helper's held-out check found five poses declared 29-86 mm and 60
    degrees off on one. Such turns are now found, and a pose's image under one lands within
    a polish (a millimetre, half a degree) of the pose turned about a bump, which reads the
    same heights."""
    surface = contact_surface(load_map(str(hex_map), 0.001), 0.008)
    motions = symmetries(surface)
    other = motions[np.abs(motions[:, 0] - np.round(motions[:, 0])) > 1e-9]
    assert {60, 120, 240, 300} <= set(np.round(other[:, 0] * 90).astype(int))
    pose = np.array([0.0877, 0.081, 1.29])
    centre = np.array([0.1, 0.1])  # a bump of the lattice, at the map's centre
    for turn in np.deg2rad([60.0, 120.0, -60.0, -120.0]):
        c, s = np.cos(turn), np.sin(turn)
        at = centre + np.array([[c, -s], [s, c]]) @ (pose[:2] - centre)
        image = images(surface, pose, other)
        off = np.hypot(*(image[:, :2] - at).T)
        turned = np.abs((image[:, 2] - pose[2] - turn + np.pi) % (2 * np.pi) - np.pi)
        assert np.min(np.where(turned < np.deg2rad(0.5), off, np.inf)) < 0.001
    assert not np.any(np.abs(symmetries(contact_surface(peaks(), 0.008))[:, 0] % 1) > 0)


NOT_YET = {("knurl12_map", 298), ("knurl12_map", 270), ("knurl12_map", 155),
           ("knurl_map", 237), ("knurl_map", 55)}
"""Episodes that end "not yet" with the leader on the truth. 155: since the turned check
runs between steps its path differs, and at 60 readings the refined fit's rms is 1.306
sensor sds against the rule's 1.3 (0.33 mm and 0.1 degrees from the truth). knurl_map 237
and 55 (0.6 and 0.4 mm from the truth): the certificate of the whole map runs out of room
on the knurl's lattice, and a declaration now waits for one that does not (the other checks
alone let a held-out worn knurl's wrong poses through)."""


@pytest.mark.parametrize("surface, seed, was", [
    ("hex_map", 234, "80 mm and 60 degrees off at step 15: turned about a bump"),
    ("gear_map", 151, "73 mm and two teeth (55 degrees) off"),
    ("knurl12_map", 155, "72 mm and 121 degrees off"),
    ("knurl12_map", 298, "74.9 mm and 60.6 degrees off: the knurl correlates with its "
     "60-degree turn at 0.75 only, and the images of its motions missed the lattice shift "
     "the truth lay at"),
    ("knurl_map", 237, "66 mm and 60 degrees off: the turn was found, but no image landed "
     "on the truth"),
    ("knurl12_map", 270, "155 mm and a half turn off: the turned check polished the best 16 "
     "of the turned poses that fit, and on a lattice dozens fit alike"),
    ("knurl_map", 55, "15.9 mm off, a lattice shift, once the turned check screened the "
     "knurl's own turns (the same cause)"),
    ("twins_map", 17, "105 mm and a half turn off: the finger read only the pocket and the "
     "gap between the blocks, which the half turn maps onto themselves"),
])
def test_no_wrong_declaration_where_a_turn_of_a_pattern_was_declared(request, surface, seed,
                                                                     was):
    """A helper's held-out check: these were declared the truth turned by the pattern's
    pitch (a hexagonal lattice's or a knurl's 60 degrees, a gear's teeth), an image no
    check had tried. With those turns' images judged, and the turned check screening the
    leader turned by them anywhere on the map (`sweep.turns_to_check`), they localize, or
    (knurl12 298 and 270, where a polish may not carry a reading past the map's edge) end
    "not yet" with the leader on the truth."""
    score = _held_out_episode(request, surface, seed).score
    assert score.success or (surface, seed) in NOT_YET and not score.wrong_declaration, was


def test_a_surface_of_revolution_repeats_under_every_turn_about_its_axis(rings_map):
    """Rings about a point off the map's centre read the same under any turn about it: the
    turns found are every one tried, and they share that point as their fixed point. The
    turned check leaves them to the images (a turn every 2 degrees would make its grid too
    coarse to find anything)."""
    surface = contact_surface(load_map(str(rings_map), 0.001), 0.008)
    motions = symmetries(surface)
    turns = np.round(motions[motions[:, 0] % 1 != 0, 0] * 90).astype(int)
    assert len(set(turns)) >= 170
    axis = revolution_centre(motions, surface.map.extent)
    assert axis is not None and np.hypot(axis[0] - 0.110, axis[1] - 0.095) < 0.002
    assert np.allclose(np.rad2deg(turns_to_check(surface)), np.arange(45.0, 360.0, 45.0))
    assert revolution_centre(symmetries(contact_surface(peaks(), 0.008)), (0.2, 0.2)) is None


@pytest.mark.parametrize("seed, was", [(12, "34.2 mm and 84.0 degrees off"),
                                       (24, "79.5 mm and 78.4 degrees off")])
def test_no_wrong_declaration_on_a_surface_of_revolution(rings_map, seed, was):
    """A helper's held-out rings: every turn about their axis reads alike, and poses turned
    by 66-173 degrees were declared in 23 of 680 runs, since no check tried those turns. Each
    turn every 2 degrees is now an image the judge weighs."""
    report = simulate(RunSettings(map=str(rings_map), spacing=0.001, noise=True, seed=seed,
                                  max_steps=60))
    assert not report.score.wrong_declaration, was


@pytest.mark.parametrize("surface, seed, was", [
    ("knurl12_map", 250, "172 mm and a half turn off"),
    ("knurl_map", 184, "192 mm and a half turn off"),
])
def test_no_wrong_declaration_where_the_truth_was_refitted_past_the_edge(request, surface,
                                                                           seed, was):
    """The truth, refitted by least squares, put a far reading a millimetre past the map's
    edge (the finger's dead reckoning drifts about 0.1 mm a step), and every check that
    weighs rivals ruled it out as off the map. A polish no longer carries a reading further
    past the edge (`kernels.gauss_newton`)."""
    assert not _held_out_episode(request, surface, seed).score.wrong_declaration, was


@pytest.mark.parametrize("surface, seed, was", [
    ("pattern:20:28", 2, "a quarter turn, 162 mm off: no cell the turned check screened lay "
     "within 3 mm of the truth"),
    ("pattern:20:33", 8, "a quarter turn, 102 mm off: the truth's turned cell ranked 2,064th "
     "of 31,423"),
    ("knurl12_map", 15, "a half turn, 64.5 mm off: the leader was 3.9 degrees off the "
     "truth's exact image"),
    ("knurl12_map", 34, "a half turn, 62.8 mm off: the turned check weighed the readings as "
     "independent"),
    ("knurl12_map", 38, "a half turn, 75.0 mm off: the same"),
    ("knurl12_map", 75, "a half turn, 49.8 mm off"),
    ("plate_map", 60, "a quarter turn, 154 mm off"),
    ("plate_map", 3, "19.6 mm and 10.5 degrees off"),
    ("plate:20:43", 16, "2.9 mm off, four turned shares a step: a spread of 0.66 mm"),
    ("shell:20:42", 17, "2.7 mm and 1.6 degrees off, the same: 0.74 mm"),
    ("terrain:20:34", 3, "2.8 mm and 1.5 degrees off, the same: 0.58 mm"),
])
def test_no_wrong_declaration_where_the_checks_between_steps_once_went_wrong(
        request, surface, seed, was):
    """Declared wrong by versions that ran the turned check, or the sweep on every map,
    between steps (BENCHMARKS.md, "The sweep between steps on a large map"; not kept): the
    checks' weaknesses they exposed are still there, so these stay hard cases."""
    if surface.endswith("_map"):
        score = _held_out_episode(request, surface, seed).score
    else:
        score = simulate(RunSettings(map=surface, noise=True, seed=seed, max_steps=60)).score
    assert not score.wrong_declaration, was


@pytest.mark.xfail(strict=False, reason="a near miss inside the leader's basin: the "
                   "spread claimed 0.75 mm and the pose was 2.86 mm off (3.8 sds), on this "
                   "session's CPU; not strict, as another CPU's arithmetic takes another path")
def test_no_near_miss_on_terrain_48_seed_12():
    """Map seeds no benchmark had used (`haptic bench objects --map-seeds 48,49,50,51`):
    terrain:20:48, seed 12, was declared 2.86 mm and 1.3 degrees off at step 33, on main
    and with the certificate alike (within twice the same-pose tolerance, the certificate
    leaves the leader's basin to the spread)."""
    report = simulate(RunSettings(map="terrain:20:48", noise=True, seed=12, max_steps=60))
    assert not report.score.wrong_declaration


def test_no_wrong_declaration_on_the_machined_plate_seed_77(request):
    """Declared 123 mm and 79 degrees off at step 53 on one machine (the turn no multiple of
    45 degrees, so no turned check tries it), while the truth fitted the readings 42 nats
    better: it never joined the pool, as the sweep's screen ranked the truth's cells 6,154th
    and below of 27,744. On another machine's arithmetic the same seed never declares. The
    certificate's search of the whole map now stands between either and a declaration."""
    assert not _held_out_episode(request, "plate_map", 77).score.wrong_declaration


def _held_out_episode(request: pytest.FixtureRequest, surface: str, seed: int):
    """B2's noisy episode of `seed` on the map file fixture `surface` (1 mm samples)."""
    path = request.getfixturevalue(surface)
    return simulate(RunSettings(map=str(path), spacing=0.001, noise=True, seed=seed,
                                max_steps=60))


def test_no_near_miss_on_the_fine_knurl_seed_59(request):
    """The tests' held-out knurl_12 (`haptic bench realistic --map F --spacing 0.001
    --runs 100`), seed 59: declared 3.7 mm and 2.7 degrees off at step 25 once the pool
    kept room beside its modes' leaders. The readings' own best fit was that far off (the
    spread claimed 0.73 mm): the valley scan weighed the readings as independent, and the
    truth looked 21.5 worse in chi-square; counted shared, 0.2."""
    assert not _held_out_episode(request, "knurl12_map", 59).score.wrong_declaration


def test_no_near_miss_on_shell_42_seed_14():
    """`haptic bench objects --map-seeds 40,41,42,43`: shell:20:42 seed 14 was declared
    3.3 mm and 0.5 degrees off at step 27 once the pool kept room beside its modes' leaders
    (`test_the_valley_weighs_readings_that_err_together_as_one_error` has its readings)."""
    report = simulate(RunSettings(map="shell:20:42", noise=True, seed=14, max_steps=60))
    assert not report.score.wrong_declaration


@pytest.mark.parametrize(("mass", "said"), [(0.998999, "99.89 %"), (0.997199, "99.71 %"),
                                          (0.97, "97 %"), (0.5, "50 %"), (1.0, "100 %"),
                                          (0.000123456, "0.01234 %"), (0.0, "0 %")])
def test_a_share_in_words_is_cut_never_rounded_up_to_its_bar(mass, said):
    """A share of 0.998999 read "99.9 %" beside a bar of 99.9 %; a held-out check read
    "(99.71 %)" in the estimate and "its share 99.72 %" in the words after it."""
    assert share_text(mass) == said


@pytest.mark.parametrize(("change", "words"), [
    ({"readings": 3}, "3 distinct places read beyond the first, of the 6 needed"),
    ({"mode_mass": 0.97}, "its share 97 % beside the other poses that fit, of the 99.9 %"),
    ({"rms": 1.5}, "its fit: the readings' rms residual is 1.50 sds, of at most 1.3"),
    ({"max_abs_shared": 4.0}, "its fit: a reading lies 4.00 sds off it"),
    ({"position_sd": 0.0011}, "its spread: position sd 1.10 mm, of at most 0.80 mm"),
    ({"heading_sd": np.deg2rad(2.0)}, "its spread: heading sd 2.00 deg, of at most 1.50 deg"),
    # as the estimate line says it (a held-out cliff map: "spread over 1 m" above
    # "position sd 18473.21 mm", and "inf mm" under "unbounded")
    ({"position_sd": 18.47321}, "its spread: position sd over 1 m, of at most 0.80 mm"),
    ({"position_sd": np.inf}, "position sd unbounded (the readings lie on a plain)"),
])
def test_a_rule_that_does_not_hold_names_the_first_condition_it_misses(change, words):
    """A held-out check: "not yet confirmed: its fit to every reading, its spread, or
    another pose that fits nearly as well holds it back" left a user guessing which."""
    rule = ConvergenceRule()
    evidence = {"readings": 8, "mode_mass": 0.9999}
    fit = _fit(position_sd=0.0002, heading_sd=0.002, max_abs_shared=2.0)
    assert rule.unmet(noisy=True, fit=fit, step_length=0.01, **evidence) == ""
    evidence.update({k: v for k, v in change.items() if k in evidence})
    fit = dataclasses.replace(fit, **{k: v for k, v in change.items() if k not in evidence})
    assert words in rule.unmet(noisy=True, fit=fit, step_length=0.01, **evidence)
    assert not rule.holds(noisy=True, fit=fit, step_length=0.01, **evidence)


def test_a_noise_free_fit_stopped_short_beside_a_wall_is_restarted(pockets_map):
    """A helper's plate with four sharp-walled pockets (`conftest.four_pockets_and_a_dimple`),
    seed 0, no noise: the leader lay within 0.02 mm of the truth for 64 steps, undeclared
    ("a reading lies 9.13 sds off it"): least squares stopped 16 um short where the walls
    kink the misfit. Restarted a little way off each way (`convergence.RESTART`), it
    settles on the truth, exactly."""
    report = simulate(RunSettings(map=str(pockets_map), spacing=0.001, seed=0, max_steps=40))
    assert report.score.success and report.score.position_error < 1e-5


def test_a_restarted_exact_fit_of_a_quarter_turn_is_not_declared():
    """pattern:20:2, seed 0, no noise: restarted, the leader's fit of a pose 162 mm and a
    quarter turn off the truth became exact at step 31 and was declared, the certificate
    having missed the truth beside the pattern's walls. With the certificate's boxes
    polished again from inside (`certificate.AGAIN`), the truth is declared, in 34 steps."""
    report = simulate(RunSettings(map="pattern:20:2", seed=0, max_steps=40))
    assert not report.score.wrong_declaration and report.score.success

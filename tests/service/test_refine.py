"""Continuous refinement: least squares of the start pose to every reading."""

from __future__ import annotations

import numpy as np
import pytest

from service.localization.localizers.fitting import gauss_newton, sample
from service.localization.localizers.refine import (
    _inverse,
    assess,
    correlated_spread,
    reading_sigmas,
    refine,
)
from service.localization.maps import peaks
from service.localization.models import rotate
from service.localization.surface import contact_surface

TRUTH = np.array([0.15, 0.17, 0.3])


@pytest.fixture(scope="module")
def surface():
    return contact_surface(peaks(), 0.008)


def _history(surface, truth=TRUTH, steps=8, noise=0.0, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    spiral = [(1, 0), (0, 1), (-1, 0), (-1, 0), (0, -1), (0, -1), (1, 0), (1, 0), (1, 0),
              (0, 1), (0, 1), (0, 1), (-1, 0), (-1, 0)]  # a square spiral: turns every side
    d = np.vstack([np.zeros(2), np.cumsum(np.array(spiral[:steps]) * 0.01, axis=0)])
    dx, dy = rotate(truth[2], d[:, 0], d[:, 1])
    z, _, _ = sample(surface, truth[0] + dx, truth[1] + dy)
    h = np.column_stack([d, z - z[0]])
    return h + noise * rng.standard_normal(h.shape) * (np.arange(len(h)) > 0)[:, None]


@pytest.mark.parametrize("offset", [(0.001, -0.002, -0.04), (0.004, 0.002, 0.1)])
def test_noise_free_fit_recovers_the_pose_exactly(surface, offset):
    fit = refine(surface, _history(surface), TRUTH + np.array(offset), 1e-7)
    np.testing.assert_allclose(fit.pose, TRUTH, atol=1e-9)
    assert fit.max_abs < 1e-3


def test_noisy_fit_is_close_and_its_uncertainty_honest(surface):
    errors = []
    for seed in range(8):
        h = _history(surface, steps=10, noise=1e-4, seed=seed)
        fit = refine(surface, h, TRUTH + np.array([0.002, 0.001, 0.05]), 2e-4)
        error = np.hypot(fit.pose[0] - TRUTH[0], fit.pose[1] - TRUTH[1])
        errors.append(error)
        assert fit.rms < 3
        assert error < 4 * fit.position_sd  # the reported uncertainty covers the error
    assert np.median(errors) < 1.5e-3


def test_more_readings_tighten_the_fit(surface):
    short = assess(surface, _history(surface, steps=4), TRUTH, 2e-4)
    long = assess(surface, _history(surface, steps=12), TRUTH, 2e-4)
    assert long.position_sd < short.position_sd
    assert long.heading_sd < short.heading_sd


def test_one_bad_reading_is_dropped(surface):
    h = _history(surface, steps=12)
    h[5, 2] += 0.005  # a 5 mm slip
    fit = refine(surface, h, TRUTH + np.array([0.001, 0.001, 0.02]), 1e-4)
    assert fit.readings == len(h) - 1
    assert fit.kept is not None and 5 not in fit.kept and len(fit.kept) == len(h) - 1
    np.testing.assert_allclose(fit.pose[:2], TRUTH[:2], atol=2e-4)


def test_a_reading_a_few_sigmas_off_is_kept_not_explained_away(surface):
    """Dropping 5-sigma readings let a wrong pose fit the rest and be declared (B3)."""
    h = _history(surface, steps=12)
    h[5, 2] += 7.5e-4  # 4.7 sigmas after the fit (sigma = 0.1 mm): a misfit, not a slip
    fit = refine(surface, h, TRUTH + np.array([0.001, 0.001, 0.02]), 1e-4)
    assert fit.readings == len(h)
    assert fit.max_abs > 4.0  # the convergence rule (at most 3 with noise) sees the misfit


def test_steep_readings_get_larger_sigmas(surface):
    s = reading_sigmas(surface, _history(surface), TRUTH, 2e-4, 1e-4)
    assert np.all(s >= 2e-4) and s.max() > s.min()
    np.testing.assert_allclose(reading_sigmas(surface, _history(surface), TRUTH, 2e-4, 0.0),
                               2e-4)


def test_gauss_newton_polishes_many_poses_at_once(surface):
    h = _history(surface, steps=8)
    starts = TRUTH + np.array([[0.001, 0.0, 0.02], [-0.001, 0.001, -0.03], [0.0, -0.001, 0.0]])
    moved = gauss_newton(surface, starts, h, np.ones(len(h)), iterations=10, max_move=0.003)
    before = np.hypot(*(starts[:, :2] - TRUTH[:2]).T)
    after = np.hypot(*(moved[:, :2] - TRUTH[:2]).T)
    assert np.all(after < before)


def _shared_error(h: np.ndarray, error_sd: float, length: float, noise: float,
                  rng: np.random.Generator) -> np.ndarray:
    """`h` with heights off by a smooth error that readings `length` apart share (Gaussian
    correlation, sd `error_sd`) plus independent noise: a world that is not its map."""
    d2 = np.sum((h[:, None, :2] - h[None, :, :2]) ** 2, axis=-1)
    cov = error_sd**2 * np.exp(-0.5 * d2 / length**2) + noise**2 * np.eye(len(h))
    out = h.copy()
    out[:, 2] += rng.multivariate_normal(np.zeros(len(h)), cov)
    return out


def test_without_a_shared_error_the_spread_is_the_fits_own(surface):
    h = _history(surface, steps=10)
    fit = assess(surface, h, TRUTH, 2e-4)
    position, heading = correlated_spread(surface, h, TRUTH, 2e-4, 0.0, 0.0, 0.01)
    assert position == pytest.approx(fit.position_sd, rel=1e-9)
    assert heading == pytest.approx(fit.heading_sd, rel=1e-9)


def test_a_shared_error_is_not_averaged_away_by_reading_one_place_again(surface):
    """Four readings of each place shrink the fit's own spread by half; an error the map
    shares with nearby readings stays, so the spread that counts it hardly shrinks."""
    once = _history(surface, steps=10)
    four = np.vstack([once] * 4)
    own = [assess(surface, h, TRUTH, 2e-4).position_sd for h in (once, four)]
    shared = [correlated_spread(surface, h, TRUTH, 2e-4, 0.0, 2e-4, 0.01)[0]
              for h in (once, four)]
    assert own[1] == pytest.approx(own[0] / 2, rel=1e-6)
    assert shared[0] > own[0]
    assert shared[1] > 0.75 * shared[0]


def test_the_spread_covers_the_error_of_a_world_that_is_not_its_map(surface):
    """100 seeded worlds off their map by a shared 0.2 mm error over a step: the error of
    the fit lies beyond twice the claimed (total) spread about as often as a Gaussian says
    (2 %), where the fit's own spread, which takes each reading's error as its own, is
    beaten four times as often (shell:20:5, seed 2, was declared 4.2 mm off at 0.6)."""
    own, shared = [], []
    for seed in range(100):
        h = _shared_error(_history(surface, steps=12), 2e-4, 0.01, 1e-4,
                          np.random.default_rng(seed))
        fit = refine(surface, h, TRUTH + np.array([0.002, 0.001, 0.05]), 2e-4)
        error = np.hypot(fit.pose[0] - TRUTH[0], fit.pose[1] - TRUTH[1])
        own.append(error / fit.position_sd)
        shared.append(error / correlated_spread(surface, h, np.asarray(fit.pose), 2e-4, 0.0,
                                                2e-4, 0.01)[0])
    assert np.mean(np.array(shared) > 2) <= 0.03
    assert np.mean(np.array(own) > 2) >= 0.06


def test_a_spread_the_readings_cannot_bound_is_unbounded(surface):
    """Every reading at one place: the sandwich has no inverse, and the spread is infinite,
    never quietly the fit's own."""
    h = np.zeros((6, 3))
    position, heading = correlated_spread(surface, h, TRUTH, 2e-4, 0.0, 2e-4, 0.01)
    assert position == np.inf and heading == np.inf


def test_a_spread_the_readings_barely_bound_is_unbounded():
    """Normal equations a hair from singular (on a plain with two small holes, a helper's
    held-out surface, the x and heading columns of one step's Jacobian): their inverse is
    round-off, with variances below zero or in the billions, and the spread read 0.0 mm at
    one step and 640 m at the one before. It is unbounded, as for equations that are
    singular outright; well-conditioned ones invert as before."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=8)
    jac = np.column_stack([x, 3.0 * x + 1e-9 * rng.normal(size=8), np.ones(8)])
    seen = jac.T @ jac
    assert np.linalg.cond(seen) > 1e12  # np.linalg.inv still returns numbers here
    assert np.all(np.isinf(_inverse(seen)))
    well = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 0.5], [0.0, 0.5, 2.0]])
    assert np.allclose(_inverse(well) @ well, np.eye(3))

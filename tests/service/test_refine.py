"""Continuous refinement: least squares of the start pose to every reading."""

from __future__ import annotations

import numpy as np
import pytest

from service.localization.localizers.fitting import gauss_newton, sample
from service.localization.localizers.refine import assess, reading_sigmas, refine
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

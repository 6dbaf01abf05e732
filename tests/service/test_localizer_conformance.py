"""One conformance suite for every registered localizer (STYLE.md item 4).

Each algorithm must: give the same answer however its updates (and the work between them)
are sliced; give the same
answer for the same seed, bit for bit; find (and, if discrete, never drop) a noise-free
true pose on `peaks`; hand out normalized hypotheses; report a sane estimate.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.episode.scenario import RunSettings
from service.episode.simulate import simulate
from service.localization.localizers.base import (
    Budget,
    LocalizerContext,
    Measurement,
    background,
    update,
)
from service.localization.maps import peaks
from service.localization.models import NoiseSpec, models_for, rotate
from service.localization.surface import contact_surface
from service.registry import LOCALIZERS

NAMES = LOCALIZERS.names()
STEP = 0.01
PATH = [(1, 0), (0, 1), (1, 0), (0, 1), (-1, 0), (0, 1)]
"""Moves (in steps) of a fixed noise-free path, so localizers are compared on equal data."""


@pytest.fixture(scope="module")
def surface():
    return contact_surface(peaks(), 0.008)


def _measurements(surface, start=(0.07, 0.12, 0.6)) -> list[Measurement]:
    """Noise-free readings of the fixed path from `start`."""
    x0, y0, heading = start
    z0 = surface.height(x0, y0)
    d = np.zeros(2)
    out = []
    for i, move in enumerate(PATH, start=1):
        d = d + np.array(move, dtype=float) * STEP
        dx, dy = rotate(np.asarray(heading), d[0], d[1])
        z = surface.height(x0 + float(dx), y0 + float(dy)) - z0
        out.append(Measurement(step=i, displacement=np.array([d[0], d[1], z])))
    return out


def _localizer(name: str, surface, seed: int = 0):
    motion, sensor = models_for(NoiseSpec())
    ctx = LocalizerContext(surface=surface, motion=motion, sensor=sensor, step_length=STEP,
                           rng=np.random.default_rng(seed))
    return LOCALIZERS.load(name)(ctx)


def _run(localizer, measurements, budget: Budget | None = None) -> None:
    localizer.start(Measurement(step=0, displacement=np.zeros(3)))
    for m in measurements:
        if budget is None:
            update(localizer, m)
            background(localizer)
        else:
            localizer.begin_update(m)
            calls = 0
            while not localizer.work(budget):
                calls += 1
                assert calls < 100_000, "work() never finishes"
            while not localizer.background(budget):
                calls += 1
                assert calls < 100_000, "background() never finishes"


@pytest.mark.parametrize("name", NAMES)
def test_tiny_budget_gives_the_same_result_as_unlimited(name, surface):
    data = _measurements(surface)
    whole, sliced = _localizer(name, surface), _localizer(name, surface)
    _run(whole, data)
    _run(sliced, data, Budget(max_items=64))
    assert whole.estimate() == sliced.estimate()
    a, b = whole.hypotheses(limit=50), sliced.hypotheses(limit=50)
    np.testing.assert_array_equal(a.poses, b.poses)
    np.testing.assert_array_equal(a.weights, b.weights)


@pytest.mark.parametrize("name", NAMES)
def test_same_seed_same_episode_bit_for_bit(name):
    settings = RunSettings(algorithm=name, policy="info-gain", seed=5, noise=True, max_steps=8)
    first, second = (_untimed(simulate(settings).to_json()) for _ in range(2))
    assert first == second


def _untimed(report: dict) -> dict:
    """An episode's JSON without its wall-clock timings (which no seed fixes)."""
    for step in report["steps"]:
        step.pop("compute_ms")
        step.pop("policy_ms")
        step.pop("background_ms")
        step.pop("settle_ms")  # the checks a declaration waited on (grid: `whole_map`)
    return report


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("seed", [1, 2])
def test_noise_free_truth_is_found_on_peaks(name, seed):
    policy = "paper" if name == "elimination" else "info-gain"
    report = simulate(RunSettings(algorithm=name, policy=policy, seed=seed, max_steps=60))
    assert report.score.success, f"{name} did not localize seed {seed}"
    assert report.true_pose_eliminated in (None, False)


@pytest.mark.parametrize("name", NAMES)
def test_hypotheses_are_normalized_and_limited(name, surface):
    loc = _localizer(name, surface)
    _run(loc, _measurements(surface)[:3])
    for limit in (None, 1, 10):
        h = loc.hypotheses(limit=limit)
        assert h.poses.ndim == 2 and h.poses.shape[1] == 3
        assert len(h.poses) == len(h.weights) > 0
        if limit is not None:
            assert len(h.poses) <= limit
        assert np.all(h.weights >= 0)
        assert h.weights.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("name", NAMES)
def test_estimate_fields_are_sane(name, surface):
    loc = _localizer(name, surface)
    loc.start(Measurement(step=0, displacement=np.zeros(3)))
    before = loc.estimate()
    assert before.candidates > 0 and not before.converged
    _run(loc, _measurements(surface))
    est = loc.estimate()
    assert est.pose is not None and np.all(np.isfinite(est.pose))
    assert est.candidates >= 1
    assert 0.0 <= est.mode_mass <= 1.0 or np.isnan(est.mode_mass)
    assert 0.0 <= est.runner_up_mass <= 1.0
    for sd in (est.position_sd, est.heading_sd):
        assert np.isnan(sd) or sd >= 0
    if est.converged:  # a declaration is a pose near the truth
        assert np.hypot(est.pose[0] - 0.07, est.pose[1] - 0.12) < 0.25 * STEP


@pytest.fixture(scope="module")
def profile():
    """A 40 cm profile cut from a seeded bumps map: a planar finger's whole world."""
    from service.localization.maps import bumps
    from service.localization.surface import HeightMap

    row = bumps(40.0, seed=3).heights[200]
    return HeightMap(row, 0.001, name="bumps-profile")


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("noise", [False, True])
def test_a_profile_is_localized_or_refused_naming_one_that_does(name, noise, profile):
    """Noise-free every algorithm that takes a profile localizes it; with noise none
    declares a wrong pose and the default localizes it."""
    from service.errors import ConfigError

    settings = RunSettings(map="profile", algorithm=name, seed=2, noise=noise, max_steps=40)
    try:
        report = simulate(settings, profile)
    except ConfigError as exc:
        named = [other for other in NAMES if other != name and other in str(exc)]
        assert named, f"{name} refused a profile without naming one that takes it: {exc}"
        return
    assert not report.score.wrong_declaration
    if not noise or name == RunSettings().algorithm:  # the pose table of Algorithm III
        # has no entry near a continuous start, so with noise it may answer "none"
        assert report.score.success, f"{name} did not localize the profile (noise={noise})"
        est = report.result.estimate.pose
        assert est[1] == 0.0 and est[2] in (0.0, np.pi, -np.pi)


@pytest.mark.parametrize("name", NAMES)
def test_a_step_blocked_by_the_edge_rules_out_poses_that_put_its_target_inside(name, surface):
    """Start 5 mm from the left edge facing +x: the first step back (-x) is blocked. With
    walls, the hypotheses left must (nearly all) put that step's target off the map."""
    start = (0.005, 0.1, 0.0)
    motion, sensor = models_for(NoiseSpec())
    ctx = LocalizerContext(surface=surface, motion=motion, sensor=sensor, step_length=STEP,
                           rng=np.random.default_rng(0), walls=True)
    loc = LOCALIZERS.load(name)(ctx)
    loc.start(Measurement(step=0, displacement=np.zeros(3)))
    update(loc, Measurement(step=1, displacement=np.zeros(3), blocked=True,
                            command=(-STEP, 0.0)))
    for m in _measurements(surface, start)[:4]:
        update(loc, Measurement(step=m.step + 1, displacement=m.displacement))
    h = loc.hypotheses(limit=200)
    tx, ty = motion.positions(h.poses, np.array([-STEP, 0.0]))
    inside = surface.map.inside(tx, ty, -0.002)
    assert h.weights[inside].sum() < 0.05


def test_a_blocked_step_is_evidence_only_where_the_edge_blocks():
    from service.localization.localizers.base import reading_row

    m = Measurement(step=3, displacement=np.array([0.01, 0.0, 0.002]), blocked=True,
                    command=(0.01, 0.0))
    np.testing.assert_array_equal(reading_row(m, walls=True), [0.01, 0.0, 0.002, 0.01, 0.0])
    np.testing.assert_array_equal(reading_row(m, walls=False), [0.01, 0.0, 0.002, 0.0, 0.0])

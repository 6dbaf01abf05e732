"""The certificate (`localizers/certificate.py`): bounds that never rule out a pose that fits,
and a search that finds a rival no pool held."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.localization import bound_kernels
from service.localization.localizers.certificate import KEPT, SLACK, Certificate, certify
from service.localization.localizers.fitting import offset_residuals
from service.localization.localizers.refine import reading_sigmas_each
from service.localization.localizers.turned import Weighing, rivals_clear
from service.localization.surface import HeightMap, contact_surface

SD, POSITION_SD = 1e-4, 1e-4
_X, _Y = np.meshgrid(np.arange(201) * 0.001, np.arange(201) * 0.001)


def _feature(cx: float, cy: float, turn: float) -> np.ndarray:
    """A lopsided bump (a big round one and a small one beside it) at (cx, cy), turned."""
    c, s = math.cos(turn), math.sin(turn)
    z = np.zeros_like(_X)
    for (u, v), height, width in (((0.0, 0.0), 0.003, 0.006), ((0.010, 0.004), 0.0025, 0.004)):
        x, y = cx + c * u - s * v, cy + s * u + c * v
        z += height * np.exp(-((_X - x) ** 2 + (_Y - y) ** 2) / (2 * width**2))
    return z


def _weighing(heights: np.ndarray):
    surface = contact_surface(HeightMap(heights, 0.001, "twins"), 0.008)
    return Weighing(surface, SD, SD, POSITION_SD, 5 * POSITION_SD, 0.0, 1.0, 0.01,
                    (0.0025, np.deg2rad(5.0)), 0.999)


def _readings(weighing: Weighing, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A walk of 5 x 5 places 5 mm apart round the first contact, read under `pose` with
    the sensor's noise: (K, 5) history rows."""
    u, v = np.meshgrid(np.arange(5) * 0.005, np.arange(5) * 0.005)
    rows = np.zeros((25, 5))
    rows[:, 0], rows[:, 1] = u.ravel(), v.ravel()
    resid, _ = offset_residuals(weighing.surface, pose[np.newaxis], rows, 1.0)
    heights = resid[0] - resid[0, 0]  # the map's heights relative to the first contact
    rows[:, 2] = heights + rng.normal(0.0, SD, 25)
    rows[0, 2] = 0.0
    return rows


def _certified(weighing: Weighing, history: np.ndarray, pose: np.ndarray) -> Certificate:
    cert = Certificate(pose=pose, readings=len(history))
    for _ in certify(weighing, history, pose, cert):
        pass
    return cert


def test_the_certificate_finds_a_twin_feature_at_a_turn_no_check_screens():
    """Two alike features 70 degrees apart (no multiple of 45): a walk over one reads what
    a walk over the other does, and the certificate of one pose names the other."""
    first, second, turn = np.array([0.06, 0.06]), np.array([0.14, 0.13]), np.deg2rad(70.0)
    weighing = _weighing(_feature(*first, 0.0) + _feature(*second, turn))
    pose = np.array([0.052, 0.05, 0.3])
    history = _readings(weighing, pose, np.random.default_rng(0))
    c, s = math.cos(turn), math.sin(turn)
    offset = pose[:2] - first
    twin = np.array([second[0] + c * offset[0] - s * offset[1],
                     second[1] + s * offset[0] + c * offset[1], pose[2] + turn])
    cert = _certified(weighing, history, pose)
    assert cert.complete and not cert.overflowed
    near = np.hypot(*(cert.rivals[:, :2] - twin[:2]).T) < 0.001
    assert near.any(), cert.rivals
    assert not rivals_clear(weighing, history, pose, cert.rivals)


def test_the_certificate_clears_a_feature_the_map_holds_once():
    weighing = _weighing(_feature(0.06, 0.06, 0.0))
    pose = np.array([0.052, 0.05, 0.3])
    history = _readings(weighing, pose, np.random.default_rng(1))
    cert = _certified(weighing, history, pose)
    assert cert.complete and not cert.overflowed and cert.boxes > 0
    assert rivals_clear(weighing, history, pose, cert.rivals)


def test_a_certificate_stands_for_its_pose_while_the_readings_since_keep_its_margin():
    """A certificate made on 20 readings stands for its pose on 25 that the pose fits (each
    costs the margin only the pose's shortfall from a perfect fit), not for a pose 5 mm
    away, not on fewer readings than it was made on, and not once a reading since misfits
    the pose by 7 sds (25 nats: `SLACK` - `KEPT` is 10)."""
    weighing = _weighing(_feature(0.06, 0.06, 0.0))
    pose = np.array([0.052, 0.05, 0.3])
    history = _readings(weighing, pose, np.random.default_rng(2))
    cert = _certified(weighing, history[:20], pose)
    assert cert.margin(weighing, history[:20], pose) == pytest.approx(SLACK)
    assert cert.covers(weighing, history, pose)
    assert SLACK - 10.0 < cert.margin(weighing, history, pose) < SLACK
    assert not cert.covers(weighing, history, pose + [0.005, 0.0, 0.0])
    assert not cert.covers(weighing, history[:19], pose)
    misfit = history.copy()
    misfit[22, 2] += 7 * SD
    assert not cert.covers(weighing, misfit, pose)
    assert SLACK - KEPT < 0.5 * 7**2


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), half=st.floats(1e-4, 0.01),
       half_turn=st.floats(1e-3, 0.5))
def test_a_box_bound_never_exceeds_the_misfit_of_a_pose_in_the_box(seed, half, half_turn):
    """The bound is a lower bound for every pose in the box, however the box lies round it."""
    rng = np.random.default_rng(seed)
    heights = np.zeros_like(_X)
    for _ in range(6):
        x, y = rng.uniform(0.0, 0.2, 2)
        heights += rng.uniform(-0.004, 0.004) * np.exp(
            -((_X - x) ** 2 + (_Y - y) ** 2) / (2 * rng.uniform(0.003, 0.02) ** 2))
    weighing = _weighing(heights)
    surface = weighing.surface
    pose = np.array([*rng.uniform(0.04, 0.16, 2), rng.uniform(-np.pi, np.pi)])
    history = _readings(weighing, pose, rng)
    history[:, :2] += rng.uniform(-0.02, 0.02, (len(history), 2))  # not on a grid
    history[0, :2] = 0.0
    anchor = history[:, :2].mean(axis=0)
    readings = np.ascontiguousarray(history[:, :3])
    readings[:, :2] -= anchor
    reach = np.hypot(readings[:, 0], readings[:, 1])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    at = pose[:2] + [c * anchor[0] - s * anchor[1], s * anchor[0] + c * anchor[1]]
    centre = np.array([*(at + rng.uniform(-half, half, 2)),
                       pose[2] + rng.uniform(-half_turn, half_turn)])
    lo, hi, steep, index = bound_kernels.pyramid(surface.centre_heights, surface.map.spacing)
    bound = bound_kernels.box_bound(surface.centre_heights, lo, hi, steep, index,
                                    surface.map.spacing,
                                    surface.map.extent, 1.0, readings, reach, *centre, half,
                                    half_turn, SD, POSITION_SD)
    resid, _ = offset_residuals(surface, pose[np.newaxis], history, 1.0)
    sds = reading_sigmas_each(surface, history, pose[np.newaxis], SD, POSITION_SD)[0]
    assert bound <= np.sum((resid[0] / sds) ** 2) * (1 + 1e-9) + 1e-9


def test_a_box_whose_readings_all_land_off_the_map_is_ruled_out():
    weighing = _weighing(_feature(0.06, 0.06, 0.0))
    surface = weighing.surface
    readings = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0]])
    lo, hi, steep, index = bound_kernels.pyramid(surface.centre_heights, surface.map.spacing)
    bound = bound_kernels.box_bound(surface.centre_heights, lo, hi, steep, index,
                                    surface.map.spacing,
                                    surface.map.extent, 0.0005, readings, np.array([0.0, 0.01]),
                                    0.5, 0.5, 0.0, 0.001, 0.01, SD, POSITION_SD)
    assert bound == np.inf


@pytest.mark.parametrize("shape", [(201, 201), (57, 130), (2, 9)])
def test_the_pyramid_holds_every_block_s_range(shape):
    rng = np.random.default_rng(3)
    grid = rng.normal(size=shape)
    lo, hi, steep, index = bound_kernels.pyramid(grid, 0.001)
    for level, (base, rows, cols) in enumerate(index):
        b = 1 << level
        i, j = rng.integers(0, rows), rng.integers(0, cols)
        block = grid[i * b:(i + 1) * b + 1, j * b:(j + 1) * b + 1]
        assert lo[base + i * cols + j] <= block.min()
        assert hi[base + i * cols + j] >= block.max()
    assert index[-1, 1] == index[-1, 2] == 1


def _worn_knurl(path) -> str:
    """A held-out surface: a 200 mm diamond knurl (8 mm pitch, 0.8 mm deep) with one worn
    patch (20 mm round (140, 60) mm, flattened to 0.3 mm), at 1 mm."""
    x, y = np.meshgrid(np.arange(200.0), np.arange(200.0))
    z = 0.4 * (np.abs(np.sin(np.pi * (x + y) / 8)) + np.abs(np.sin(np.pi * (x - y) / 8)))
    worn = (x - 140) ** 2 + (y - 60) ** 2 < 20**2
    z[worn] = np.minimum(z[worn], 0.3)
    np.save(path, z * 1e-3)
    return str(path)


@pytest.mark.parametrize("seed, radius", [(22, 0.008), (17, 0.003)])
def test_a_map_too_alike_to_check_whole_declares_nothing(tmp_path, seed, radius):
    """On the worn knurl the certificate ran out of room (more fine boxes survived the
    bound than it keeps), which let the other checks declare alone: a pose 26 mm and 27
    degrees off (seed 22), and with a 3 mm tip one 57 mm and 100 degrees off (seed 17),
    where the truth fitted the readings 5 nats better. Now such a declaration waits."""
    from service.episode.scenario import RunSettings
    from service.episode.simulate import simulate

    report = simulate(RunSettings(map=_worn_knurl(tmp_path / "knurl.npy"), spacing=0.001,
                                  radius=radius, noise=True, seed=seed, max_steps=60))
    assert not report.score.wrong_declaration


def test_the_certificate_finds_an_exact_rival_beside_walls():
    """Readings of `haptic run --map pattern:20:2 --seed 0` (noise-free) at step 31
    (`data/pattern_20_2_seed0_step31.json`): a pose 162 mm and a quarter turn from the
    truth fits them exactly, and so does the truth. A version of the judge that restarted
    the leader's least squares (not kept) reached that exact fit, and the certificate for
    it found no rival at all: the pose was declared, wrong (on main the leader's own fit
    stops short of exact there and nothing is declared, which hid the gap). The 26 fine
    boxes round the truth were polished from their centres only, and beside the walls
    least squares stopped at least 63 nats short. Now the best of a slice's boxes whose
    centres fell short are polished again from inside (`certificate.AGAIN`). (All of them
    so, the extra work held 31 of B1's 103 declarations back, mean steps 5.83 to 6.15.)"""
    import json
    from pathlib import Path

    from service.episode.scenario import RunSettings, surface_for
    from service.localization.localizers.convergence import within
    from service.localization.localizers.turned import slope_weighed

    case = json.loads((Path(__file__).parent / "data" / "pattern_20_2_seed0_step31.json")
                      .read_text())
    surface = surface_for(RunSettings(map="pattern:20:2"), None)
    w = case["weighing"]
    weighing = Weighing(surface, w["sigma"], w["fit_sd"], w["position_sigma"], w["margin"],
                        w["outlier_probability"], w["outlier_range"], w["step_length"],
                        tuple(w["same_pose"]), w["mode_mass"])
    history, pose, truth = (np.array(case[k]) for k in ("history", "pose", "truth"))
    ll = slope_weighed(weighing, history, np.vstack([pose, truth]), weighing.fit_sd)
    assert abs(ll[0] - ll[1]) < 1.0  # both explain every reading exactly
    cert = Certificate(pose, len(history))
    for _ in certify(weighing, history, pose, cert):
        pass
    assert cert.complete and not cert.overflowed
    assert np.any(within(cert.rivals, truth, *weighing.same_pose)), "the truth was missed"

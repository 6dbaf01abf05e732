"""Information-gain exploration: informative moves, never a known-blocked one, vectorized."""

from __future__ import annotations

import numpy as np
import pytest

from service.episode.scenario import RunSettings
from service.episode.simulate import simulate
from service.localization.localizers.base import Hypotheses
from service.localization.maps import peaks
from service.localization.policies.base import PolicyInput, predicted_heights
from service.localization.policies.info_gain import InfoGainPolicy, information
from service.localization.surface import contact_surface


@pytest.fixture(scope="module")
def surface():
    return contact_surface(peaks(), 0.008)


def _view(surface, poses, blocked=frozenset(), displacement=(0.0, 0.0)):
    w = np.full(len(poses), 1.0 / len(poses))
    return PolicyInput(hypotheses=Hypotheses(np.asarray(poses, dtype=float), w),
                       displacement=np.array(displacement), blocked=frozenset(blocked),
                       surface=surface, step_length=0.01, rng=np.random.default_rng(0))


def test_information_is_zero_when_all_agree_and_log_n_when_all_differ():
    w = np.full(4, 0.25)
    same = np.zeros((1, 4, 1))
    apart = np.arange(4.0).reshape(1, 4, 1)
    assert information(same, w, 0.01)[0] == pytest.approx(0.0, abs=1e-12)
    assert information(apart, w, 0.01)[0] == pytest.approx(np.log(4), rel=1e-6)


def test_chooses_the_move_that_tells_the_hypotheses_apart(surface):
    rng = np.random.default_rng(3)
    poses = np.column_stack([rng.uniform(0.05, 0.15, 40), rng.uniform(0.05, 0.15, 40),
                             rng.uniform(-np.pi, np.pi, 40)])
    view = _view(surface, poses)
    move = InfoGainPolicy(reach=1).next_move(view)
    z, inside = predicted_heights(view, poses)
    spread = [np.std(z[m][inside[m]]) for m in range(4)]
    assert spread[move] >= 0.5 * max(spread)


def test_never_takes_a_move_known_blocked(surface):
    poses = np.array([[0.1, 0.1, 0.0], [0.12, 0.08, 1.0], [0.05, 0.15, 2.0]])
    policy = InfoGainPolicy()
    for blocked in ({0}, {0, 1}, {0, 1, 2}):
        assert policy.next_move(_view(surface, poses, blocked)) not in blocked


def test_remembers_walls_found_earlier(surface):
    poses = np.array([[0.1, 0.1, 0.0], [0.12, 0.08, 1.0], [0.05, 0.15, 2.0]])
    policy = InfoGainPolicy()
    policy.next_move(_view(surface, poses, {3}, displacement=(0.01, 0.0)))
    # back at the same spot later, with the runner's blocked set long cleared
    assert policy.next_move(_view(surface, poses, set(), displacement=(0.01, 0.0))) != 3


@pytest.mark.parametrize("lookahead", [1, 2])
def test_deterministic_and_beats_random_on_average(lookahead):
    def steps(policy: str, seed: int) -> int:
        s = RunSettings(algorithm="grid", policy=policy, seed=seed, max_steps=30)
        return len(simulate(s).result.steps)

    ours = [steps("info-gain", s) for s in (3, 4)]
    assert ours == [steps("info-gain", s) for s in (3, 4)]
    assert np.mean(ours) <= np.mean([steps("random", s) for s in (3, 4)])
    policy = InfoGainPolicy(lookahead=lookahead)
    surface = contact_surface(peaks(), 0.008)
    poses = np.array([[0.1, 0.1, 0.0], [0.12, 0.08, 1.0], [0.05, 0.15, 2.0]])
    assert policy.next_move(_view(surface, poses)) in range(4)


def test_paper_policy_samples_only_candidates_with_weight():
    """Fewer nonzero weights than the 10 samples must not crash the paper's heuristic."""
    from service.localization.localizers.base import Hypotheses
    from service.localization.maps import peaks
    from service.localization.policies.base import PolicyInput
    from service.localization.policies.paper import PaperPolicy
    from service.localization.surface import contact_surface

    poses = np.array([[0.05, 0.05, 0.0], [0.1, 0.1, 1.0], [0.15, 0.1, 2.0]] * 5)
    weights = np.zeros(len(poses))
    weights[:3] = 1 / 3
    view = PolicyInput(hypotheses=Hypotheses(poses, weights), displacement=np.zeros(2),
                       blocked=frozenset(), surface=contact_surface(peaks(), 0.008),
                       step_length=0.01, rng=np.random.default_rng(0))
    assert PaperPolicy().next_move(view) in range(4)

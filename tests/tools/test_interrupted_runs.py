"""A run cut by Ctrl-C or a stop signal keeps what it found: a held-out fault campaign's
`haptic run --backend dynamixel --json` lost the 11-14 steps it had taken."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from service.episode.hand_episode import simulate_hand
from service.episode.hand_scenario import HandSettings
from tools import hand_cli, run_cli
from tools.cli import main
from tools.signals import Interrupted


def cut_at(step: int, signum: int):
    """An `on_step` printer that lands `signum` as step `step` is printed."""
    def on_step(record) -> None:
        if record.index == step:
            raise Interrupted(signum)
    return on_step


def test_an_interrupted_run_writes_what_it_found_and_exits_with_the_signal(
        monkeypatch, tmp_path: Path, capsys) -> None:
    monkeypatch.setattr(run_cli, "StepPrinter", lambda: cut_at(3, signal.SIGTERM))
    out = tmp_path / "run.json"
    status = main(["run", "--noise", "--seed", "1", "--json", str(out), "--plot",
                   str(tmp_path / "run.png")])
    assert status == 128 + signal.SIGTERM
    episode = json.loads(out.read_text())
    assert episode["ended"] == "interrupted" and episode["interrupted"] == "SIGTERM"
    assert [s["index"] for s in episode["steps"]] == [1, 2, 3]
    assert episode["estimate"] is not None and not episode["converged"]
    printed = capsys.readouterr().out
    assert "interrupted by SIGTERM after 3 steps; what they found stands" in printed
    assert not (tmp_path / "run.png").exists() and "no figure" in printed


def test_an_interrupted_hand_run_writes_what_it_found(monkeypatch, tmp_path: Path,
                                                      capsys) -> None:
    monkeypatch.setattr(hand_cli, "_print_step", cut_at(2, signal.SIGHUP))
    out = tmp_path / "hand.json"
    status = main(["run", "--object", "blob", "--hand", "three-finger", "--seed", "2",
                   "--json", str(out)])
    assert status == 128 + signal.SIGHUP
    episode = json.loads(out.read_text())
    assert episode["interrupted"] == "SIGHUP" and len(episode["steps"]) == 2
    assert "interrupted by SIGHUP after 2 steps" in capsys.readouterr().out


def test_without_being_asked_an_episode_unwinds_on_ctrl_c() -> None:
    """Benches and campaigns stop on Ctrl-C: only a command that writes one episode keeps it."""
    with pytest.raises(KeyboardInterrupt):
        simulate_hand(HandSettings(object="blob", hand="three-finger", seed=2),
                      on_step=cut_at(1, signal.SIGINT))


def test_a_second_signal_waits_for_a_backend_to_close(monkeypatch) -> None:
    """The first signal ends a run on servos and the runner closes the backend (torque off,
    then the port); a second landing inside that exchange could leave the servos on."""
    from tools import signals
    from tools.signals import _on_signal, closed_whole

    # the signal seen stays seen for this process: put it back for the tests after
    monkeypatch.setitem(signals._seen, "signum", None)

    class Servos:
        torque_off = False

        def close(self) -> None:
            _on_signal(signal.SIGINT, None)  # the second Ctrl-C lands here
            self.torque_off = True

    servos = closed_whole(Servos())
    with pytest.raises(Interrupted):  # it still ends the command, once torque is off
        servos.close()
    assert servos.torque_off


def test_a_run_cut_while_a_step_is_recorded_keeps_the_belief_of_the_steps_it_holds(
        monkeypatch) -> None:
    """A review: a signal landing after step 4's update but before its record left step 4's
    belief beside steps 1-3 (the JSON's estimate and score disagreed with its steps)."""
    from service.episode import runner
    from service.episode.scenario import RunSettings
    from service.episode.simulate import simulate

    record = runner.StepRecord

    def cut_while_recording(**fields):
        if fields["index"] == 4:
            raise Interrupted(signal.SIGTERM)
        return record(**fields)

    monkeypatch.setattr(runner, "StepRecord", cut_while_recording)
    report = simulate(RunSettings(noise=True, seed=1), keep_on_interrupt=True)
    steps, estimate = report.result.steps, report.result.estimate
    assert len(steps) == 3 and report.result.interrupted == "SIGTERM"
    assert estimate.pose == steps[-1].estimate and estimate.candidates == steps[-1].candidates
    assert report.true_pose_eliminated is None  # a localizer cut mid-update cannot say

"""Outputs are checked before any work (`tools.outputs`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.errors import ConfigError
from tools.cli import main
from tools.outputs import check_outputs


def test_a_writable_path_passes_and_leaves_nothing_behind(tmp_path: Path) -> None:
    check_outputs(tmp_path / "r.json", None, "-", figures=(tmp_path / "f.png", None))
    assert list(tmp_path.iterdir()) == []
    kept = tmp_path / "old.json"
    kept.write_text("{}")
    check_outputs(kept)
    assert kept.read_text() == "{}"  # checked, not truncated


@pytest.mark.parametrize("where, words", [
    ("missing/r.json", "folder missing does not exist"),
    (".", "it is a folder"),
    ("/proc/haptic-check.json", "cannot write /proc/haptic-check.json: "),
])
def test_an_unwritable_path_is_named(tmp_path: Path, monkeypatch, where, words) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=words):
        check_outputs(Path(where))


def test_a_figure_in_a_format_matplotlib_does_not_write_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cannot draw .*x\.txt: a figure is one of .*\.png"):
        check_outputs(figures=(tmp_path / "x.txt",))
    assert not (tmp_path / "x.txt").exists()


def test_a_bench_refuses_an_unwritable_output_before_any_episode(tmp_path, capsys,
                                                                  monkeypatch) -> None:
    """A held-out check: `haptic bench paper --json /sys/x.json` ran every episode, then
    failed with a traceback; `--plot x.txt` wrote the JSON first, then failed."""
    from tools import bench_common

    monkeypatch.setattr(bench_common, "run_episodes", lambda *a, **k: pytest.fail("ran"))
    assert main(["bench", "paper", "--runs", "1", "--workers", "1", "--json",
                 "/proc/haptic-check.json"]) == 2
    assert "cannot write /proc/haptic-check.json" in capsys.readouterr().err
    assert main(["bench", "realistic", "--runs", "1", "--workers", "1", "--json",
                 str(tmp_path / "ok.json"), "--plot", str(tmp_path / "x.txt")]) == 2
    assert "a figure is one of" in capsys.readouterr().err
    assert not (tmp_path / "ok.json").exists()

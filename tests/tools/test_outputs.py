"""Outputs are checked before any work (`tools.outputs`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.errors import ConfigError
from tools.cli import main
from tools.outputs import check_outputs


def test_a_writable_path_passes_and_leaves_nothing_behind(tmp_path: Path) -> None:
    check_outputs(tmp_path / "r.json", None, "-", figures=(tmp_path / "f.png", None),
                  stdout=True)
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


def test_an_output_that_is_an_input_or_another_output_is_refused(tmp_path: Path) -> None:
    """A held-out check: `export run.mcap --json run.mcap` overwrote the recording, `run
    --map in.npy --json in.npy` the map, and `--json same.png --plot same.png` kept one."""
    source = tmp_path / "in.npy"
    source.write_bytes(b"map")
    with pytest.raises(ConfigError, match="it is an input of this command"):
        check_outputs(source, inputs=(str(source),))
    (tmp_path / "link.npy").symlink_to(source)
    with pytest.raises(ConfigError, match="it is an input"):
        check_outputs(tmp_path / "link.npy", inputs=(source,))
    with pytest.raises(ConfigError, match="twice"):
        check_outputs(tmp_path / "same.png", figures=(tmp_path / "same.png",))
    assert source.read_bytes() == b"map"


def test_standard_output_only_where_the_command_writes_there(tmp_path: Path) -> None:
    """A held-out check's `run --json -` wrote a file named '-'; `export --json -` writes
    to standard output."""
    check_outputs("-", stdout=True)
    with pytest.raises(ConfigError, match="'-' is not a file"):
        check_outputs("-")


def test_a_figure_format_that_needs_tex_is_refused_before_the_work() -> None:
    """`--plot x.pgf` passed the check, then failed after the run: PGF needs xelatex."""
    with pytest.raises(ConfigError, match="a figure is one of"):
        check_outputs(figures=("x.pgf",))

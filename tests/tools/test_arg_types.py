"""Bounded numbers on the command line: a held-out check of bad values gave tracebacks
(`--cycles -1`, `--interval inf`, `--budget-ms nan`, `map check --step inf`), "too many open
files" (`--subscribers 100000`) and commands that never ended (`--duration inf`, `bus read
--count 0`, a daemon's bad `--step-s` waited for its reply). Each is now one line naming
the option, exit status 2, before anything starts."""

from __future__ import annotations

import argparse

import pytest

from service.daemon.config import LoopConfig
from tools.arg_types import integer, number, setting
from tools.cli import main


@pytest.mark.parametrize("argv, option", [
    ("bench bus --cycles -1", "--cycles"),
    ("bench bus --servos 300", "--servos"),
    ("bench hand-bus --ticks -1", "--ticks"),
    ("bench anytime --runs -1", "--runs"),
    ("bench anytime --budget-ms nan", "--budget-ms"),
    ("bench service --subscribers 100000", "--subscribers"),
    ("bench service --duration inf", "--duration"),
    ("bench service --step-s -1", "--step-s"),
    ("bench service --seed -1", "--seed"),
    ("bench soak --reconnect-s nan", "--reconnect-s"),
    ("bench faults --rate nan", "--rate"),
    ("bus read --port /dev/null --hand planar --interval inf", "--interval"),
    ("bus read --port /dev/null --hand planar --count 0", "--count"),
    ("watch --duration -1", "--duration"),
    ("watch --count 0", "--count"),
    ("view --duration nan", "--duration"),
    ("bench paper --runs 1 --workers 100000", "--workers"),
    ("map check peaks --step 1e9", "--step"),
    ("map check peaks --step inf", "--step"),
    ("map check peaks --radius 1e-300", "--radius"),
    ("record x.mcap --state-hz nan", "--state-hz"),
    ("replay x.mcap --delay -5", "--delay"),
    ("replay x.mcap --speed 0", "--speed"),
    ("explore --wait nan", "--wait"),
    ("ctl status --timeout -1", "--timeout"),
    ("bus scan --port /dev/null --baud 0", "--baud"),  # 0 was taken as "the default"
    # a second held-out check's: tracebacks, or errors that named no option
    ("map from-mesh x.stl -o y.npy --spacing 1e308", "--spacing"),
    ("map from-mesh x.stl -o y.npy --spacing 0.001 --scale 1e308", "--scale"),
    ("run --object blob --mu 1e308", "--mu"),
    ("run --object blob --mu 0", "--mu"),
    ("run --object blob --mass inf", "--mass"),
    ("run --object blob --threshold nan", "--threshold"),
    ("bench grasp --start-quality 1e308", "--start-quality"),
    ("bench objects --size nan", "--size"),
    ("bench scale --map-seed -1", "--map-seed"),
])
def test_a_bad_number_is_one_line_naming_its_option(argv, option, capsys):
    with pytest.raises(SystemExit) as stopped:  # argparse's own exit, before any work
        main(argv.split())
    assert stopped.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"argument {option}: " in err
    assert "must be" in err or "invalid choice" in err


def test_the_types_take_what_their_range_allows():
    assert integer(1, 3)("3") == 3 and number(0.5, 2.0)("0.5") == 0.5
    assert setting(LoopConfig, "rate_hz")("200") == 200.0
    for parse, text in ((integer(1, 3), "4"), (integer(1, 3), "2.0"), (number(0, 1), "inf"),
                        (number(0, 1), "x"), (setting(LoopConfig, "rate_hz"), "5")):
        with pytest.raises(argparse.ArgumentTypeError):
            parse(text)


@pytest.mark.parametrize("argv, said", [
    ("bench paper --first-seed 9223372036854775807", "--first-seed 9223372036854775807 with "
                                                     "--runs 103 gives seeds outside"),
    ("bench grasp --first-seed -1", "--first-seed -1 with --runs 100"),
    ("bench hand-bus --first-seed -1", "--first-seed -1 with --seeds 4"),
])
def test_first_seeds_are_named_as_given(argv, said, capsys):
    """A held-out check was told of `--seed` (and 9223372036854775808) for `--first-seed`."""
    assert main(argv.split()) == 2
    assert said in capsys.readouterr().err

"""`haptic bench anytime`: it replays episodes under a budget and reports the slices."""

import json

from tools.cli import main


def test_anytime_bench_reports_slices(tmp_path):
    out = tmp_path / "a.json"
    assert main(["bench", "anytime", "--runs", "1", "--algorithms", "elimination,particles",
                 "--budget-ms", "0.5", "--json", str(out)]) == 0
    rows = {r["algorithm"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"elimination", "particles"}
    # particles splits each update across several budgeted calls
    assert rows["particles"]["slices_per_update_median"] > 1
    assert rows["elimination"]["slice_ms_max"] >= rows["elimination"]["slice_ms_median"] > 0

"""tools/stability_chart.py: the failure interval of each experiment and the chart files."""

from __future__ import annotations

import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

from stability_chart import failure_interval, main, read  # noqa: E402


def test_failure_interval_is_between_the_last_good_and_the_first_failed_run():
    runs = [(0.2, "stable"), (0.7, "caught"), (0.4, "drift"), (0.5, "silent")]
    assert failure_interval(runs) == (0.4, 0.5)
    lo, hi = failure_interval([(0.2, "stable")])
    assert lo == 0.2 and math.isnan(hi)


def test_chart_from_csv(tmp_path, capsys):
    csv = tmp_path / "s.csv"
    csv.write_text(
        "experiment,dt_over_TR,outcome,quantity,value,bound_over_TR,source\n"
        "a,0.2,stable,q,1,0.25,x\na,0.5,silent,q,3,,x\nb,1.0,stable,q,1,2.0,x\nb,3.0,caught,q,,,x\n"
    )
    assert read(csv)["a"]["bound"] == 0.25
    out = tmp_path / "c.png"
    assert main([str(csv), str(out)]) == 0
    assert out.stat().st_size > 1000 and out.with_suffix(".svg").exists()
    text = capsys.readouterr().out
    assert "(0.80, 2.00]" in text and "(0.50, 1.50]" in text

"""``pdem study``'s crossover chart (wall time against a stiffness knob, DEM-P's runs fitted by a
power law, DEM-C as one line) and zipped series (several keys varied as one)."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_study import _spec  # noqa: E402

from pdem.errors import InputError  # noqa: E402
from pdem.study import Study, load_spec, plan_runs  # noqa: E402
from pdem.study.charts import crossover_fit, write_charts  # noqa: E402

E = "materials.glass.youngs_modulus"
BODY = f"""
[quantities.q]
path = "results.x"
reference = {{ finest = "p", by = "{E}", largest = true }}
tolerance = 0.05
[[series]]
name = "p"
zip = true
vary = {{ "{E}" = [1.0e6, 4.0e6, 1.6e7], "run.seed" = [1, 2, 3] }}
[[series]]
name = "c"
set = {{ "contact.law" = "complementarity" }}
vary = {{ "run.seed" = [1, 2, 3] }}
[crossover]
x = "{E}"
penalty = ["p"]
rigid = ["c"]
extend_to = 7.0e10
marks = {{ glass = 6.3e10 }}
"""


def test_zipped_series_take_the_lists_together(tmp_path):
    plans = plan_runs(load_spec(_spec(tmp_path, BODY)))
    p = [pl for pl in plans if pl.series == "p"]
    assert [(pl.knobs[E], pl.knobs["run.seed"]) for pl in p] == [(1.0e6, 1), (4.0e6, 2), (1.6e7, 3)]
    unzipped = BODY.replace("zip = true\n", "")
    assert len([pl for pl in plan_runs(load_spec(_spec(tmp_path, unzipped))) if pl.series == "p"]) == 9
    with pytest.raises(InputError, match="one length"):
        load_spec(_spec(tmp_path, BODY.replace('"run.seed" = [1, 2, 3] }\n[[series]]\nname = "c"',
                                               '"run.seed" = [1, 2] }\n[[series]]\nname = "c"')))


@pytest.mark.parametrize(
    "change, message",
    [
        (('penalty = ["p"]', 'penalty = ["nope"]'), "'nope'"),
        (('rigid = ["c"]', 'rigid = ["x"]'), "'x'"),
        ((f'x = "{E}"', 'x = "run.seed"'), None),  # varied in p: valid
        ((f'x = "{E}"', 'x = "run.dt"'), "is not varied in penalty series"),
        (("[crossover]", '[crossover]\nquantity = "w"'), "'w'"),
        (("marks = { glass = 6.3e10 }", "marks = { glass = -6.3e10 }"), "marks must be stiffnesses > 0"),
    ],
)
def test_crossover_spec_errors_name_the_key(tmp_path, change, message):
    body = BODY.replace(*change)
    if message is None:
        assert load_spec(_spec(tmp_path, body)).crossovers[0].x == "run.seed"
        return
    with pytest.raises(InputError, match=message):
        load_spec(_spec(tmp_path, body))


def _rows(a: float, b: float, rigid: list[float], errors: list[float]) -> list[dict]:
    rows = []
    for k, (x, err) in enumerate(zip([1.0e6, 4.0e6, 1.6e7], errors, strict=True)):
        rows.append({"series": "p", "run": f"p{k}", "method": "DEM-P", E: x, "run.seed": k + 1,
                     "wall_s": a * x**b, "status": "ok", "q_error": err, "q": 1.0})  # fmt: skip
    for k, t in enumerate(rigid):
        rows.append({"series": "c", "run": f"c{k}", "method": "DEM-C", E: "", "run.seed": k + 1,
                     "wall_s": t, "status": "ok", "q_error": 0.02, "q": 1.0})  # fmt: skip
    return rows


def test_fit_and_crossover_against_the_closed_form(tmp_path):
    study = Study.from_file(_spec(tmp_path, BODY))
    cx = study.spec.crossovers[0]
    a, b = 3.0e-3, 0.5
    fit = crossover_fit(study, cx, _rows(a, b, [40.0, 30.0, 35.0], [0.06, 0.01, 0.0]))
    assert fit["b"] == pytest.approx(b, rel=1e-12) and fit["a"] == pytest.approx(a, rel=1e-10)
    assert fit["t_rigid"] == 35.0 and fit["t_rigid_range"] == (30.0, 40.0)
    assert fit["x_cross"] == pytest.approx((35.0 / a) ** (1 / b), rel=1e-10)
    glass = fit["marks"]["glass"]
    assert glass["t_penalty"] == pytest.approx(a * 6.3e10**b, rel=1e-10)
    assert glass["penalty_over_rigid"] == pytest.approx(a * 6.3e10**b / 35.0, rel=1e-10)
    accurate = [u["accurate"] for u in fit["runs"] if u["role"] == "penalty"]
    assert accurate == [False, True, True]  # 0.06 > 0.05
    # a failed penalty run stays out of the fit; a flat line has no crossover
    rows = _rows(a, 0.0, [35.0], [0.0, 0.0, 0.0])
    rows[0]["status"], rows[0]["wall_s"] = "failed", 1e9
    fit = crossover_fit(study, cx, rows)
    assert fit["b"] == pytest.approx(0.0, abs=1e-12) and fit["x_cross"] is None


def test_report_writes_the_crossover_chart_table_and_numbers(tmp_path):
    study = Study.from_file(_spec(tmp_path, BODY))
    rows = _rows(3.0e-3, 0.5, [35.0], [0.06, 0.01, 0.0])
    out = tmp_path / "report"
    out.mkdir()
    paths = write_charts(study, rows, out)
    assert paths["crossover_table"].is_file() and (out / "crossover.png").stat().st_size > 0
    with open(paths["crossover_table"]) as fh:
        table = list(csv.DictReader(fh))
    assert [t["role"] for t in table] == ["penalty"] * 3 + ["rigid"]
    assert [t["within_tolerance"] for t in table] == ["False", "True", "True", "True"]
    numbers = json.loads(paths["crossover_numbers"].read_text())
    assert math.isclose(numbers["x_cross"], (35.0 / 3.0e-3) ** 2, rel_tol=1e-10)
    text = "\n".join(study._crossover_reading(study.spec.crossovers[0], rows))
    assert "cross at x = 1.36e+08" in text and "glass" in text

"""Each contact law's own time step: ``dt`` / ``dt_fraction`` in a ``[contact.<law>]`` table step
that law only, so that ``contact.law`` alone switches a deck between DEM-P's step and DEM-C's."""

from __future__ import annotations

import json
import sys
import tomllib
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from decks import TINY_LATTICE  # noqa: E402

from pdem.deck import validate_deck  # noqa: E402
from pdem.errors import DeckError  # noqa: E402

DEM_P_DT, DEM_C_DT = 2e-6, 5e-5


def _deck(run_dt: float | None = None, **tables) -> dict:
    data = tomllib.loads(TINY_LATTICE)
    if run_dt is None:
        del data["run"]["dt"]
    else:
        data["run"]["dt"] = run_dt
    data["contact"] = {"law": "hertz_mindlin", "hertz_mindlin": {"dt": DEM_P_DT},
                       "complementarity": {"dt": DEM_C_DT, "solver": "apgd"}}  # fmt: skip
    for name, table in tables.items():
        data["contact"][name] = table
    return data


def _resolve(data: dict, *sets: str):
    return validate_deck(data, overrides=list(sets))


def test_each_law_runs_at_its_own_step():
    p = _resolve(_deck())
    assert p.deck.run.dt == DEM_P_DT and p.step_key == "contact.hertz_mindlin.dt"
    c = _resolve(_deck(), "contact.law=complementarity")
    assert c.deck.run.dt == DEM_C_DT and c.step_key == "contact.complementarity.dt"
    assert c.law_params.solver == "apgd"  # the rest of the table is the law's, as before
    assert "dt" not in c.law_params.model_dump()


def test_a_law_table_without_a_step_leaves_the_law_its_default():
    data = _deck(hertz_mindlin={})
    r = _resolve(data)
    assert r.deck.run.dt is None and r.deck.run.dt_fraction is None and r.step_key == "run.dt"
    r = _resolve(_deck(hertz_mindlin={"dt_fraction": 0.1}))
    assert r.deck.run.dt is None and r.deck.run.dt_fraction == 0.1


def test_a_step_in_run_and_in_the_selected_law_table_is_an_error():
    with pytest.raises(DeckError) as err:
        _resolve(_deck(run_dt=1e-6))
    text = str(err.value)
    assert "contact.hertz_mindlin.dt" in text and "run.dt" in text and "one place" in text
    # the other law's table does not clash: it is not used
    r = _resolve(_deck(run_dt=1e-6, hertz_mindlin={}))
    assert r.deck.run.dt == 1e-6


def test_a_set_step_wins_over_the_deck_files_other_step():
    r = _resolve(_deck(), "run.dt=3e-6")  # the law's table gives one, --set run.dt another
    assert r.deck.run.dt == 3e-6 and r.step_key == "run.dt"
    r = _resolve(_deck(), "run.dt_fraction=0.1")
    assert r.deck.run.dt is None and r.deck.run.dt_fraction == 0.1
    r = _resolve(_deck(run_dt=1e-6, hertz_mindlin={}), "contact.hertz_mindlin.dt=4e-6")
    assert r.deck.run.dt == 4e-6 and r.step_key == "contact.hertz_mindlin.dt"
    with pytest.raises(DeckError, match="one place"):  # both set: no winner
        _resolve(_deck(), "run.dt=3e-6", "contact.hertz_mindlin.dt=4e-6")


@pytest.mark.parametrize("value", [-1.0, 0.0, "1e-5", True, float("inf"), [1e-5]])
@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_bad_steps_are_named_in_either_table(value, law):
    data = _deck()
    data["contact"][law]["dt"] = value
    with pytest.raises(DeckError) as err:
        _resolve(data)
    text = str(err.value)
    assert f"contact.{law}.dt" in text and "must be a number > 0" in text
    if law == "complementarity":  # not selected: the message says when it would be used
        assert "used when contact.law = 'complementarity'" in text


def test_dt_and_dt_fraction_in_one_law_table_is_an_error():
    with pytest.raises(DeckError, match="give one"):
        _resolve(_deck(hertz_mindlin={"dt": 1e-6, "dt_fraction": 0.1}))


def test_the_step_is_checked_against_the_stability_estimate_under_its_own_key(run_pdem, tmp_path):
    """A law's own step above its stability estimate: the error names the key that gave it."""
    data = _deck(hertz_mindlin={"dt": 1e-3})
    from pdem.deck.toml_writer import dumps

    deck = tmp_path / "deck.toml"
    deck.write_text(dumps(data, "test"))
    code, _, err = run_pdem([deck, "--output", tmp_path / "out", "--quiet"])
    assert code != 0
    assert "contact.hertz_mindlin.dt: dt = 0.001 s" in err and "stability estimate" in err


def test_runs_record_the_law_step_as_run_dt(run_pdem, tmp_path):
    """Both methods run the deck at their own step; the resolved deck gives it as run.dt."""
    from pdem.deck.toml_writer import dumps

    deck = tmp_path / "deck.toml"
    deck.write_text(dumps(_deck(), "test"))
    for law, dt in (("hertz_mindlin", DEM_P_DT), ("complementarity", DEM_C_DT)):
        out = tmp_path / law
        code, _, err = run_pdem([deck, "--output", out, "--quiet", "--set", f"contact.law={law}"])
        assert code == 0, err
        summary = json.loads((out / "summary.json").read_text())
        assert summary["dt"] == dt and summary["steps"] == 20
        resolved = tomllib.loads((out / "deck.resolved.toml").read_text())
        assert resolved["run"]["dt"] == dt
        assert "dt" not in resolved["contact"]


def test_advise_costs_dem_c_at_its_own_step(tmp_path):
    """pdem advise's method estimate uses [contact.complementarity] dt for DEM-C's steps."""
    from pdem.advise import advise
    from pdem.deck.toml_writer import dumps

    deck = tmp_path / "deck.toml"
    deck.write_text(dumps(_deck(), "test"))
    method = [f for f in advise(deck, probe=False).findings if f.topic == "method"][0]
    assert method.numbers["DEM-C h [s]"] == DEM_C_DT
    assert "[contact.complementarity] dt" in method.reason
    # a DEM-P step 8x finer than needed: the change is made to the key that gives it
    deck.write_text(dumps(_deck(hertz_mindlin={"dt": DEM_P_DT / 8}), "test"))
    changes = advise(deck, probe=False).changes
    assert "contact.hertz_mindlin.dt" in changes and "run.dt" not in changes, changes
    assert changes["contact.hertz_mindlin.dt"] > DEM_P_DT / 8

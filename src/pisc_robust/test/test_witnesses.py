"""The witness table (pisc_analysis.witnesses): what pisc_feasibility --csv writes is read
back with its rules, seed, draws and digest, and a file that is not a complete table is
refused with what is wrong."""

from __future__ import annotations

import math

import pytest

from pisc_analysis.witnesses import (FORMAT, WitnessFileError, read_witness_csv,
                                     write_witness_csv)

META = {"catch_by_s": 8.0, "hold_from_s": 9.0, "run_s": 12.0, "seed": 1, "draws": 300,
        "searched": 2, "distribution": "thesis-rig", "distribution_digest": "0123456789abcdef",
        "config": "default", "set": "", "current_limit_a": 0.9, "multiple_shooting": False}
ROWS = [
    {"draw": 7, "feasible": True, "how": "feedback", "caught_at_s": 2.35, "reason": "",
     "bound": False, "transcribed_s": math.nan, "motor.resistance_ohm": 12.5},
    {"draw": 41, "feasible": False, "how": "not found", "caught_at_s": math.inf,
     "reason": "never in the catch region for good; |x| up to 0.030 m in the hold",
     "bound": False, "transcribed_s": math.nan, "motor.resistance_ohm": 17.25},
]


def test_a_table_is_read_back_with_its_header_typed(tmp_path):
    path = tmp_path / "w.csv"
    write_witness_csv(path, META, ROWS)
    text = path.read_text()
    # the documented layout: '# key: value' lines, the format first, then the CSV header
    assert text.startswith(f"# format: {FORMAT}\n# catch_by_s: 8.0\n# hold_from_s: 9.0\n"
                           "# run_s: 12.0\n# seed: 1\n# draws: 300\n")
    assert "\ndraw,feasible,how,caught_at_s,reason,bound,transcribed_s,motor.resistance_ohm\n" \
        in text
    meta, rows = read_witness_csv(path)
    assert meta["catch_by_s"] == 8.0 and meta["hold_from_s"] == 9.0 and meta["run_s"] == 12.0
    assert meta["seed"] == 1 and meta["draws"] == 300 and meta["searched"] == 2
    assert meta["distribution_digest"] == "0123456789abcdef"
    assert meta["current_limit_a"] == "0.9" and meta["multiple_shooting"] == "false"
    assert [r["draw"] for r in rows] == [7, 41]
    assert [r["feasible"] for r in rows] == [True, False]
    assert rows[0]["caught_at_s"] == 2.35 and math.isinf(rows[1]["caught_at_s"])
    assert math.isnan(rows[0]["transcribed_s"]) and rows[1]["bound"] is False
    assert rows[1]["reason"] == ROWS[1]["reason"] and rows[1]["how"] == "not found"
    assert rows[1]["motor.resistance_ohm"] == 17.25
    assert not list(tmp_path.glob(".*partial"))  # written beside it, then renamed


def _refused(tmp_path, text: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(WitnessFileError, match=message):
        read_witness_csv(path)


def _header(**changes) -> str:
    meta = {"format": FORMAT, **META, **changes}
    return "".join(f"# {k}: {v}\n" for k, v in meta.items() if v is not None)


def test_a_plain_csv_without_the_header_lines_is_refused(tmp_path):
    _refused(tmp_path, "draw,feasible\n0,True\n",
             r"bad.csv: no '# key: value' header lines: not a witness table of "
             r"pisc_feasibility \(format pisc-witnesses/1\)")


def test_a_header_without_the_rules_or_the_seed_is_refused(tmp_path):
    _refused(tmp_path, _header(catch_by_s=None, seed=None) + "draw,feasible\n7,True\n41,False\n",
             r"bad.csv: the header lacks catch_by_s, seed")
    _refused(tmp_path, _header(draws="many") + "draw,feasible\n7,True\n41,False\n",
             r"bad.csv: draws = 'many': an integer expected")
    _refused(tmp_path, _header(format="pisc-witnesses/2") + "draw,feasible\n",
             r"format 'pisc-witnesses/2', this reader reads 'pisc-witnesses/1'")
    _refused(tmp_path, "# a comment\ndraw,feasible\n", r"line 1: '# a comment': '# key: value'")


def test_a_table_without_the_draw_or_feasible_column_is_refused(tmp_path):
    _refused(tmp_path, _header() + "draw,how\n7,feedback\n41,not found\n",
             r"bad.csv: no column feasible \(columns: draw, how\)")
    _refused(tmp_path, _header(), r"no column draw, feasible \(columns: none\)")


def test_rows_that_do_not_fit_the_header_are_refused(tmp_path):
    _refused(tmp_path, _header() + "draw,feasible\n7,True\n",
             r"1 rows, the header says 2 draws searched \(an interrupted run\?\)")
    _refused(tmp_path, _header() + "draw,feasible\n7,True\n300,False\n",
             r"row 2: draw 300 is not among the 300 draws \(0 .. 299\)")
    _refused(tmp_path, _header() + "draw,feasible\n7,True\n7,False\n", r"row 2: draw 7 again")
    _refused(tmp_path, _header() + "draw,feasible\n7,yes\n41,False\n",
             r"row 1: feasible = 'yes': True or False expected")
    _refused(tmp_path, _header() + "draw,feasible\n7,True,extra\n41,False\n",
             r"row 1: 2 columns expected")


def test_the_writer_refuses_a_header_a_reader_could_not_use(tmp_path):
    with pytest.raises(ValueError, match=r"header lacks distribution_digest"):
        write_witness_csv(tmp_path / "w.csv", {k: v for k, v in META.items()
                                               if k != "distribution_digest"}, ROWS)
    with pytest.raises(ValueError, match=r"one line"):
        write_witness_csv(tmp_path / "w.csv", {**META, "set": "a\nb"}, ROWS)
    with pytest.raises(ValueError, match=r"rows lack the column 'feasible'"):
        write_witness_csv(tmp_path / "w.csv", META, [{"draw": 1}])
    assert not (tmp_path / "w.csv").exists()


@pytest.mark.parametrize("name, rules", [
    ("thesis-rig-300-seed1-3s.csv", (3.0, 6.0, 10.0)),
    ("thesis-rig-300-seed1-8s.csv", (8.0, 9.0, 12.0)),
])
def test_the_shipped_tables_are_the_draws_of_the_distribution_they_name(name, rules):
    """The tables under distributions/witnesses/ read back complete, with their rules,
    and each row's drawn values are the values pisc_robustness draws today for that
    draw (same digest, seed and N): a table left behind by a change of the distribution
    fails here. A witness is caught by the deadline; a draw without one says why (unless
    the bound proved it infeasible)."""
    from pisc_robust.robustness import load_benchmark
    from pisc_robust.uncertainty import DISTRIBUTION_DIR

    meta, rows = read_witness_csv(DISTRIBUTION_DIR / "witnesses" / name)
    assert (meta["catch_by_s"], meta["hold_from_s"], meta["run_s"]) == rules
    assert (meta["seed"], meta["draws"], meta["searched"]) == (1, 300, 300)
    _, distribution, draws, _ = load_benchmark("default", [], meta["distribution"],
                                               meta["draws"], meta["seed"])
    assert meta["distribution_digest"] == distribution.digest
    assert [r["draw"] for r in rows] == list(range(300))
    for row in rows:
        assert {k: row[k] for k in draws.one(row["draw"])} == draws.one(row["draw"])
        if row["feasible"]:
            assert row["caught_at_s"] <= rules[0] and row["reason"] == ""
        elif row["how"] != "bound":  # proved infeasible: no candidate to say why
            assert row["reason"] and not math.isnan(row["caught_at_s"])

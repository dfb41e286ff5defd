"""One rule for "caught": the graph's run summary judges a run by the robustness
benchmark's tiers (safe; caught: caught for good by 8 s, held from 9 s; fast: by 3 s,
held from 6 s), says each tier's verdict with its rule, and its result line follows one
tier; an experiment run reports the experiment, not a swing-up verdict."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pisc_robust.robustness import evaluate
from pisc_runs.verdict import Criteria
from pisc_runs.summary import RunTables, Table, summarise_bag, summarise_tables
from pisc_robust.uncertainty import Draws
from pisc_msgs_py.types import Mode
from pisc_sim.configuration import load_graph_config

PERIOD = 0.005
SWINGUP = Path(__file__).resolve().parents[3] / "bags" / "default-swingup"


def run(duration_s: float, catch_at_s: float, x=None, theta=None) -> RunTables:
    """A run's tables: the cart at 0 and the pendulum upright from ``catch_at_s`` (the
    supervisor catching there for good), hanging before; ``x``, ``theta``: functions of
    time that replace them."""
    n = int(round(duration_s / PERIOD)) + 1
    t = np.arange(n) * PERIOD
    stamps = np.arange(n, dtype=np.int64) * 5_000_000 + 10**12
    xs = np.zeros(n) if x is None else x(t)
    ths = np.where(t < catch_at_s, math.pi, 0.0) if theta is None else theta(t)

    def table(values: np.ndarray) -> Table:
        return Table(stamps, stamps + 1000, values.reshape(n, -1))

    empty = Table(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)))
    k = int(round(catch_at_s / PERIOD))
    modes = [(int(stamps[0]), Mode.SWING_UP, ""), (int(stamps[k]), Mode.CATCH, "")]
    return RunTables(table(np.column_stack([xs, ths])), table(np.zeros((n, 2))),
                     table(np.zeros(n)), table(np.zeros(n)), table(np.zeros(n)), empty, modes)


RANGE = (-0.225, 0.125)


def test_a_catch_for_good_at_3_010_s_is_caught_not_fast_and_says_which_rule():
    s = summarise_tables(run(10.0, 3.010), PERIOD, Criteria(), RANGE)
    assert s.passed == {"safe": True, "caught": True, "fast": False} and s.caught
    assert s.why["fast"] == "caught for good only at 3.01 s"
    lines = s.format().splitlines()
    assert lines[-4:] == [
        "safe                   yes: no fault, inside the safe range -0.225 .. +0.125 m",
        "caught                 yes: caught for good by 8 s, held (|theta| < 0.05 rad, |x| < "
        "0.02 m) from 9 s to the end (10 s)",
        "fast                   NO: caught for good by 3 s, held (|theta| < 0.05 rad, |x| < "
        "0.02 m) from 6 s to the end (10 s) (caught for good only at 3.01 s)",
        "result                 CAUGHT (the caught tier: caught for good by 8 s, held "
        "(|theta| < 0.05 rad, |x| < 0.02 m) from 9 s to the end (10 s))"]
    fast = summarise_tables(run(10.0, 3.010), PERIOD, Criteria(), RANGE, tier="fast")
    assert not fast.caught
    assert fast.format().splitlines()[-1].startswith("result                 NOT CAUGHT (the "
                                                     "fast tier: caught for good by 3 s")
    assert summarise_tables(run(10.0, 2.995), PERIOD, Criteria(), RANGE, "fast").caught


def test_a_run_that_leaves_the_safe_range_is_neither_safe_nor_caught():
    def x(t):  # out to -0.23 m at 2 s, back by the catch
        return np.where((t > 1.9) & (t < 2.1), -0.23, 0.0)

    s = summarise_tables(run(10.0, 2.5, x=x), PERIOD, Criteria(), RANGE)
    assert s.passed == {"safe": False, "caught": False, "fast": False}
    assert s.why["caught"] == "cart left the safe range (|x| up to 0.230 m)"
    assert s.format().splitlines()[-1].startswith("result                 NOT CAUGHT")


def test_a_hold_box_left_late_or_a_run_shorter_than_the_window_does_not_pass():
    def theta(t):  # caught at 1 s, knocked out of the box at 7 s for a moment
        return np.where(t < 1.0, math.pi, np.where(np.abs(t - 7.0) < 0.031, 0.08, 0.0))

    s = summarise_tables(run(10.0, 1.0, theta=theta), PERIOD, Criteria(), RANGE)
    assert s.passed == {"safe": True, "caught": True, "fast": False}
    assert s.why["fast"] == "not held: outside the hold box until 7.03 s"
    short = summarise_tables(run(5.0, 1.0), PERIOD, Criteria(), RANGE)
    assert short.passed == {"safe": True, "caught": False, "fast": False}
    assert short.why["fast"] == "the run ended at 5.00 s, before the hold window from 6 s"


def test_the_graphs_summary_agrees_with_the_benchmark_on_the_same_run():
    """The reference bag (the default configuration through the lockstep graph) and the
    pure closed loop of its configuration: the same catch, the same last sample outside the
    hold box, the same verdicts."""
    s = summarise_bag(SWINGUP, PERIOD)
    config, _ = load_graph_config(str(SWINGUP / "pisc_params.yaml"))
    o = evaluate(config, config.plant, Draws({"initial.x_m": np.array([config.initial.x_m])},
                                             1), Criteria(run_s=10.0), 0)
    assert s.state_source == "true" and s.safe_range_m == (-0.225, 0.125)
    assert s.caught_at_s == pytest.approx(o.caught_at_s[0], abs=1e-9)
    assert s.unheld_at_s == pytest.approx(o.unheld_at_s[0], abs=1e-9)
    assert s.max_abs_x_m == pytest.approx(o.largest_x_m[0], abs=1e-9)
    assert s.passed == {t: bool(o.passed(t)[0]) for t in ("safe", "caught", "fast")}


def test_an_experiment_run_reports_the_experiment_and_no_verdict():
    s = summarise_tables(run(10.0, 3.0), PERIOD, Criteria(), RANGE)
    text = s.format(experiment="excitation")
    assert "result " not in text and "caught                 " not in text
    assert text.splitlines()[-1] == ("experiment             excitation: completed without "
                                     "a fault; cart within +0.0000 .. +0.0000 m")

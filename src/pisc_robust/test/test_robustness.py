"""pisc_robustness and the scoring behind it: what a success is, how failures are told
apart, and the same numbers from the same seed."""

from __future__ import annotations

import math
import shlex

import numpy as np
import pytest

from pisc_sim.configuration import load_graph_config
from pisc_robust.robustness import binomial_interval, prepare, rerun_command, success_by_value
from pisc_runs.verdict import FAILURES, Criteria, Outcomes
from pisc_robust.robustness_cli import PLOT
from pisc_robust.robustness_cli import main as robustness_main
from pisc_robust.uncertainty import load_distribution


def outcomes(**columns) -> Outcomes:
    n = len(next(iter(columns.values())))
    base = dict(safe=np.ones(n, bool), caught=np.zeros(n, bool), fast=np.zeros(n, bool),
                caught_at_s=np.full(n, 1.0), first_catch_s=np.full(n, 1.0),
                largest_x_m=np.full(n, 0.05), unheld_at_s=np.full(n, 1.5),
                hold_theta_rad=np.full(n, 0.01), hold_x_m=np.full(n, 0.005),
                hold_setpoint_rms_a=np.full(n, 0.02), faulted=np.zeros(n, bool),
                left_range=np.zeros(n, bool))
    base.update({k: np.asarray(v) for k, v in columns.items()})
    return Outcomes(**base)


def test_failures_are_told_apart_and_ranked_worst_first():
    c = Criteria()
    o = outcomes(
        safe=[True, False, False, True, True, True, True, True],
        caught=[True, False, False, False, False, False, False, True],
        fast=[True, False, False, False, False, False, False, False],
        left_range=[False, True, False, False, False, False, False, False],
        faulted=[False, True, True, False, False, False, False, False],
        caught_at_s=[1.0, math.inf, math.inf, math.inf, math.inf, 8.5, 1.0, 4.0],
        first_catch_s=[1.0, math.inf, math.inf, math.inf, 2.0, 8.5, 1.0, 4.0],
        unheld_at_s=[1.5, 12.0, 12.0, 12.0, 12.0, 9.0, 10.0, 4.5])
    assert list(o.kinds(c, "safe")) == [-1, 0, 1, -1, -1, -1, -1, -1]
    assert list(o.kinds(c, "caught")) == [-1, 0, 1, 2, 3, 4, 5, -1]
    assert list(o.kinds(c, "fast")) == [-1, 0, 1, 2, 3, 4, 5, 4]
    assert o.why(0, c) == ""
    assert o.why(1, c, "safe") == "cart left the safe range (|x| up to 0.050 m)"
    assert o.why(2, c, "safe") == FAILURES[1]
    assert o.why(4, c, "caught") == "caught at 2.00 s, lost"
    assert o.why(5, c, "caught") == "caught for good only at 8.50 s"
    assert o.why(6, c, "caught") == "not held: outside the hold box until 10.00 s"
    assert o.why(7, c, "caught") == ""
    assert o.why(7, c, "fast") == "caught for good only at 4.00 s"
    badness = o.badness(c, "caught")
    assert badness[0] == badness[7] == 0
    assert np.argmax(badness) in (1, 2)  # faults first
    assert badness[3] > badness[5] > 0  # never caught before caught late
    assert o.badness(c, "fast")[7] > 0
    assert o.rates() == {"safe": 6 / 8, "caught": 2 / 8, "fast": 1 / 8}


def test_the_score_puts_safe_first_then_counts_the_catches():
    """One safe draw more outweighs every catch; then a caught draw counts one, a fast draw
    (caught too) two."""
    n = 10

    def score(safe: int, caught: int, fast: int) -> float:
        return outcomes(safe=np.arange(n) < safe, caught=np.arange(n) < caught,
                        fast=np.arange(n) < fast).score()

    assert score(10, 10, 10) == 1.0
    assert score(6, 0, 0) > score(5, 5, 5)
    assert score(5, 3, 0) > score(5, 2, 0)
    assert score(5, 3, 1) > score(5, 3, 0)
    assert score(5, 2, 2) > score(5, 3, 0)  # two fast catches count more than three late
    assert score(5, 3, 1) == score(5, 2, 2)
    # with a target, safety beyond it no longer decides
    n = 2000

    def targeted(safe: int, caught: int) -> float:
        return outcomes(safe=np.arange(n) < safe, caught=np.arange(n) < caught,
                        fast=np.zeros(n, bool)).score(safe_target=0.999)

    # 99.9 % of 2000 draws: 1998 safe meet the target
    assert targeted(1998, 1500) == targeted(2000, 1500) < targeted(1998, 1501)
    assert targeted(1997, 1999) < targeted(1998, 1)
    assert score(0, 0, 0) == 0.0


@pytest.mark.parametrize("kwargs, match", [
    (dict(catch_by_s=13.0), r"--catch-by 13 s is past --run-s 12 s"),
    (dict(hold_from_s=12.0), r"--hold-from 12 s is not inside the run"),
    (dict(hold_from_s=7.0), r"--hold-from 7 s is before --catch-by 8 s"),
    (dict(fast_by_s=9.0, fast_hold_from_s=9.5, hold_from_s=10.0),
     r"the fast tier .* must be within the caught tier"),
    (dict(run_s=-1.0), r"--run-s -1: a positive number of s"),
    (dict(catch_by_s=math.nan), r"--catch-by nan: a positive number of s"),
])
def test_rules_that_make_no_sense_are_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Criteria(**kwargs)


def test_the_binomial_interval_holds_the_rate_and_reaches_the_ends():
    low, high = binomial_interval(950, 1000)
    assert low < 0.95 < high
    assert (low, high) == pytest.approx((0.9346, 0.9627), abs=5e-4)
    assert binomial_interval(0, 10)[0] == 0.0
    assert binomial_interval(10, 10)[1] == 1.0


def test_success_by_value_bins_the_draws():
    values = np.arange(100.0)
    success = values < 50
    edges, rate, count = success_by_value(values, success, bins=10)
    assert len(edges) == 11 and count.sum() == 100
    np.testing.assert_array_equal(rate, [1] * 5 + [0] * 5)
    edges, rate, count = success_by_value(np.geomspace(1, 100, 50), np.ones(50, bool),
                                          bins=5, log=True)
    np.testing.assert_allclose(edges, np.geomspace(1, 100, 6))
    assert np.all(count == 10)


def test_a_fixed_initial_state_in_the_distribution_starts_every_draw(tmp_path):
    config = load_graph_config("default")[0]
    path = tmp_path / "d.yaml"
    path.write_text("distribution: {plant: {initial: {x_m: 0.05}, motor: {resistance_ohm: "
                    "15.0}}, parameters: {initial.theta_rad: {offset: 0.1}}}")
    distribution = load_distribution(str(path), config)
    started, plant = prepare(config, distribution)
    assert started.initial.x_m == 0.05
    assert plant.motor.resistance_ohm == 15.0
    assert config.plant.motor.resistance_ohm == 14.0  # the controllers' model stays


def test_the_rerun_command_sets_the_controllers_and_the_plant():
    command = rerun_command("default", {"swing_up.k_x": 5.0}, {"models.friction": "coulomb"},
                            {"motor.resistance_ohm": 12.5, "initial.theta_rad": 3.0})
    assert shlex.split(command) == [
        "./pisc", "run", "--config", "default", "--set", "swing_up.k_x=5.0",
        "--plant-set", "models.friction=coulomb", "--plant-set", "motor.resistance_ohm=12.5",
        "--plant-set", "initial.theta_rad=3.0"]


def run(tmp_path, capsys, *extra: str) -> str:
    assert robustness_main(["default", "--draws", "120", "--seed", "3", "--worst", "3",
                            "--out", str(tmp_path), *extra]) == 0
    return capsys.readouterr().out


def test_pisc_robustness_prints_the_same_numbers_for_the_same_seed(tmp_path, capsys):
    first = run(tmp_path / "a", capsys)
    again = run(tmp_path / "b", capsys)
    other = run(tmp_path / "c", capsys, "--seed", "4")

    def numbers(out: str) -> list[str]:
        return [line for line in out.splitlines() if not line.startswith(("wall time", "plot:"))]

    assert numbers(first) == numbers(again)
    assert numbers(first) != numbers(other)
    for expected in ("distribution thesis-rig (digest ", "motor.resistance_ohm in [9.8, 18.2]",
                     "draws 120, seed 3", "safe   ", "caught ", "fast   ", "95 % interval",
                     "failures: ", "catch time (", "largest |x| (all draws): p5 ",
                     "hold's current set-point RMS from 9 s (caught): ",
                     "simulated s per wall s",
                     f"plot: {tmp_path / 'a' / PLOT}"):
        assert expected in first, expected
    assert (tmp_path / "a" / PLOT).stat().st_size > 10_000
    worst = [line.strip() for line in first.splitlines()
             if line.strip().startswith("./pisc run")]
    assert 0 < len(worst) <= 9 or first.count("no failure") == 3
    for command in worst:
        args = shlex.split(command)
        assert args[:4] == ["./pisc", "run", "--config", "default"]
        assert "models.friction=coulomb" in args
        assert any(a.startswith("motor.resistance_ohm=") for a in args)


def wall_time(draws: int, workers: int, tmp_path, **env: str) -> tuple[float, str]:
    """Run pisc_robustness as a user does; its printed wall time and success line."""
    import os
    import re
    import subprocess
    import sys

    completed = subprocess.run(
        [sys.executable, "-m", "pisc_robust.robustness_cli", "default", "--draws",
         str(draws), "--seed", "1", "--workers", str(workers), "--worst", "0", "--out",
         str(tmp_path)], capture_output=True, text=True, timeout=1800,
        env={**os.environ, **env})
    assert completed.returncode == 0, completed.stderr
    wall = re.search(r"^wall time ([0-9.]+) s", completed.stdout, re.M)
    success = re.search(r"^safe .*$", completed.stdout, re.M)
    return float(wall[1]), success[0]


@pytest.mark.bench
def test_bench_wall_time_by_draws_and_workers(tmp_path):
    """How the wall time of ``pisc_robustness default`` (cluster start-up included) grows
    with the draws and the workers; prints the table of docs/robustness.md, "Scaling"."""
    import os

    wall_time(10, 0, tmp_path)  # the kernel compiled into its cache
    table = {}
    for n in (1000, 3000, 10000):
        for workers in (0, 1, 2):
            wall, success = wall_time(n, workers, tmp_path)
            table[n, workers] = wall
            print(f"{n:6d} draws, --workers {workers}: {wall:6.1f} s wall, "
                  f"{n * 12.0 / wall:6.0f} simulated s per wall s; {success}", flush=True)
    active, _ = wall_time(1000, 0, tmp_path, OMP_WAIT_POLICY="ACTIVE")
    print(f"  1000 draws, --workers 0, OMP_WAIT_POLICY=ACTIVE: {active:.1f} s wall")
    print(f"\n{os.cpu_count()} cores; load average {os.getloadavg()}")
    print("| draws | --workers 0 (in process) | --workers 1 | --workers 2 |")
    print("|---:|---:|---:|---:|")
    for n in (1000, 3000, 10000):
        print(f"| {n} | " + " | ".join(f"{table[n, w]:.1f} s" for w in (0, 1, 2)) + " |")

"""The learning example and the benchmark, as commands (bench marker: minutes, the wall
clock): ./pisc test -m bench src/pisc_gym/test/test_learn.py"""

from __future__ import annotations

import pytest

from pisc_gym import bench_cli, learn_cli

pytestmark = pytest.mark.bench


def test_the_learnt_catch_policy_catches_95_percent_of_new_randomised_starts(capsys):
    code = learn_cli.main([])
    out = capsys.readouterr().out
    assert "caught" in out
    assert code == 0, out  # 0: at least 95 % caught


def test_the_benchmark_prints_every_size_and_both_errors(capsys):
    assert bench_cli.main(["--sizes", "1", "100", "--seconds", "0.5"]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") >= 6 and "CartPole" in out and "error against solve_ivp" in out

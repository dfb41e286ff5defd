"""pisc_integrators: the speed-against-error table and plot, on a short run."""

import re

import pytest

from pisc_bench.integrators_cli import main


def _rows(text):
    rows = {}
    for line in text.splitlines():
        m = re.match(r"^(\S.*?)\s{2,}(\d+ steps/period|rtol \S+|DOP853 rtol \S+)\s+([\d.]+)\s+"
                     r"(\S+)\s+(\S+)\s+(\d+)$", line)
        if m:
            rows[(m[1].strip(), m[2])] = (float(m[3]), float(m[4]), m[5], int(m[6]))
    return rows


def test_table_plot_and_comparison_on_a_short_playback(tmp_path, capsys):
    png = tmp_path / "wp.png"
    assert main(["--duration", "0.5", "--conservative-duration", "5", "--quick",
                 "--png", str(png)]) == 0
    out = capsys.readouterr().out
    playback, conservative = out.split("\nconservative:")
    rows = _rows(playback)
    # every integrator of the plant and every solve_ivp method is in the playback table
    for method in ("RK45", "DOP853", "LSODA", "Radau"):
        assert any(k[0] == f"solve_ivp {method}" for k in rows), method
    assert ("exprk4", "1 steps/period") in rows and ("rk4", "20 steps/period") in rows
    # rk4 below its stability limit is not offered: 13 steps (h R/L = 2.69) is the
    # smallest stable count
    assert ("rk4", "13 steps/period") in rows and ("rk4", "12 steps/period") not in rows
    # the default setting reaches 1e-6 against the reference; its rhs count is exact
    _, error, _, evals = rows[("exprk4", "2 steps/period")]
    assert error < 1e-6 and evals == 100 * 2 * 5
    # and so does rk4 at 20 steps (4 right-hand sides per step)
    _, error, _, evals = rows[("rk4", "20 steps/period")]
    assert error < 1e-6 and evals == 100 * 20 * 4
    # the reference is checked against an independent integrator
    check = float(re.search(r"exprk4 at 64 steps/period differs from it by (\S+)", out)[1])
    assert check < 1e-9
    assert "fastest solve_ivp as accurate:" in out
    # conservative table: energy drift column filled in, python-control present
    assert "control input_output_response" in conservative
    assert float(_rows(conservative)[("rk4", "8 steps/period")][2]) < 1e-9
    drift = float(re.search(r"scene integrator rk4, 8 steps/period: energy drift (\S+)",
                            conservative)[1])
    assert drift < 1e-9
    assert png.stat().st_size > 20_000


def test_refuses_an_unknown_scene(capsys):
    assert main(["--scene", "nope", "--conservative", "none"]) == 2
    assert "no such scene" in capsys.readouterr().err


def test_refuses_a_duration_shorter_than_a_period(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--duration", "-1", "--conservative", "none"])
    assert exit_info.value.code == 2
    assert "--duration -1.0: must be at least one period" in capsys.readouterr().err

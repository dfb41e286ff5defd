"""Issue 15: bad input to a run, crashed nodes and visitors on the command topic.

Each case was found by a hostile test on the landed code; each test here failed there.
"""

from __future__ import annotations

import pytest

from pisc_bringup.graph import main

pytestmark = pytest.mark.integration


# -- bad input to pisc_graph: refused before anything is made --------------------------

@pytest.mark.parametrize("args,message", [
    (["--x0", "0.5", "--duration", "1"],
     "initial.x_m = 0.5 lies outside the track (track.min_m .. track.max_m = -0.23 .. 0.13 m)"),
    (["--x0", "-0.3", "--duration", "1"], "initial.x_m = -0.3 lies outside the track"),
    (["--duration", "-1"], "--duration -1.0: must be a finite number of seconds > 0"),
    (["--duration", "0"], "--duration 0.0: must be a finite number of seconds > 0"),
    (["--duration", "nan"], "--duration nan: must be a finite number of seconds > 0"),
    (["--duration", "inf"], "--duration inf: must be a finite number of seconds > 0"),
    (["--driver", "/dev/nonexistent"], "driver.port = /dev/nonexistent: no such device"),
])
def test_a_run_refuses_bad_input_with_one_line_and_makes_no_bag(tmp_path, domain_id, capsys,
                                                                args, message):
    bag = tmp_path / "refused"
    status = main([*args, "--bag", str(bag), "--domain-id", str(domain_id)])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith(f"pisc_graph: invalid configuration: {message}")
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not bag.exists()

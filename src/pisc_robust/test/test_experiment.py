"""The thesis's experiment as data: the shipped file says what Section 6.6 says, bad files
are refused naming the event, and each event is measured as the thesis's figures read."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from pisc_robust.experiment import EVENTS, Traces, judge, load_experiment, measure
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.types import Mode

PERIOD = 0.005


def test_the_shipped_file_holds_section_6_6():
    """The numbers of Section 6.6 and the start it describes."""
    e = load_experiment("thesis-6.6")
    assert e.configuration == "thesis"
    events = {ev.name: (ev.value, ev.tolerance) for ev in e.events}
    assert events == {"oscillations": (3.0, 0.5), "hand_over_s": (2.34, 0.2),
                      "upright_s": (3.25, 0.3), "catch_exits": (0.0, 0.5),
                      "saturation_overlap": (1.0, 0.25)}
    assert e.start == {"x_dot_mps": 0.0, "theta_rad": math.pi, "theta_dot_radps": 0.0}
    assert e.x_range_m == (-0.225, 0.125)
    assert e.duration_s == 10.0
    # the thesis's own arithmetic: 3.25 s - 2.34 s = the linear controller's 0.91 s
    assert events["upright_s"][0] - events["hand_over_s"][0] == pytest.approx(0.91)


GOOD = """\
experiment:
  configuration: thesis
  duration_s: 10.0
  start: {theta_rad: 3.14, theta_dot_radps: 0.0, x_dot_mps: 0.0, x_m: [-0.1, 0.1]}
  events:
    hand_over_s: {value: 2.34, tolerance: 0.2}
"""


def write(tmp_path, text):
    path = tmp_path / "experiment.yaml"
    path.write_text(textwrap.dedent(text))
    return path


@pytest.mark.parametrize(("old", "new", "says"), [
    ("hand_over_s: {value: 2.34, tolerance: 0.2}", "swings: {value: 3, tolerance: 1}",
     ["experiment.events.swings", "unknown event", "oscillations"]),
    ("tolerance: 0.2", "tolerance: 0", ["experiment.events.hand_over_s.tolerance", "above 0"]),
    ("tolerance: 0.2", "tolerance: -0.1", ["experiment.events.hand_over_s.tolerance",
                                           "above 0"]),
    ("tolerance: 0.2", "tolerance: .nan", ["hand_over_s.tolerance", "finite number"]),
    ("tolerance: 0.2", "tolerance: yes", ["hand_over_s.tolerance", "finite number"]),
    ("value: 2.34, tolerance: 0.2", "value: 2.34", ["hand_over_s", "tolerance"]),
    ("x_m: [-0.1, 0.1]", "x_m: [0.1, -0.1]", ["experiment.start.x_m", "empty"]),
    ("duration_s: 10.0", "duration_s: 0", ["experiment.duration_s", "above 0"]),
    ("theta_rad: 3.14, ", "", ["experiment.start", "theta_rad"]),
    ("  configuration: thesis\n", "  configuration: thesis\n  colour: red\n",
     ["experiment.colour", "unknown key"]),
])
def test_a_bad_file_is_refused_naming_what_is_wrong(tmp_path, old, new, says):
    assert old in GOOD
    path = write(tmp_path, GOOD.replace(old, new))
    with pytest.raises(ConfigError) as info:
        load_experiment(str(path))
    for word in says:
        assert word in str(info.value)
    assert str(path) in str(info.value)


def test_a_good_file_loads(tmp_path):
    e = load_experiment(str(write(tmp_path, GOOD)))
    assert [ev.name for ev in e.events] == ["hand_over_s"]
    with pytest.raises(ConfigError, match="nosuch: no such experiment"):
        load_experiment("nosuch")


def run(theta, mode, voltage=None, setpoint=None):
    """Traces of one or more columns."""
    theta = np.asarray(theta, dtype=float).reshape(len(theta), -1)
    shape = theta.shape
    return Traces(PERIOD, theta, np.asarray(mode).reshape(shape),
                  np.zeros(shape) if voltage is None else np.asarray(voltage).reshape(shape),
                  np.zeros(shape) if setpoint is None else np.asarray(setpoint).reshape(shape),
                  11.47, 0.9)


def swing_then_catch(passes: int, catch_at: int, settle_at: int, cycles: int = 2001,
                     kick: float = 0.0):
    """A pendulum that swings through hanging ``passes`` times (0.3 rad each side, a
    quarter period at rest first), goes up (theta -> 2 pi) and is caught at row
    ``catch_at``, is 0.2 rad from upright until row ``settle_at`` and 0.01 rad after."""
    theta = np.full(cycles, math.pi)
    k = np.arange(catch_at)
    # sin starts at the bottom: passes through pi at every half period, the last half
    # swing (the one up) cut at the catch
    half = catch_at / (passes + 0.5)
    theta[:catch_at] = math.pi + 0.3 * np.sin(np.pi * k / half)
    theta[catch_at:settle_at] = 2 * math.pi - 0.2 + kick
    theta[settle_at:] = 2 * math.pi - 0.01
    mode = np.where(np.arange(cycles) >= catch_at, Mode.CATCH.code, Mode.SWING_UP.code)
    return theta, mode


def test_the_events_of_a_run_built_to_have_them():
    theta, mode = swing_then_catch(passes=6, catch_at=468, settle_at=650)
    m = measure(run(theta, mode))
    assert m["oscillations"][0] == 3.0  # six passes through hanging
    assert m["hand_over_s"][0] == pytest.approx(468 * PERIOD)
    assert m["upright_s"][0] == pytest.approx(650 * PERIOD)
    assert m["catch_exits"][0] == 0.0


def test_going_over_the_top_is_not_a_pass_through_hanging():
    """Through hanging twice, then over the top (pi -> 3 pi ... the far side), then back
    down through hanging once more: three passes, not four."""
    up = np.linspace(math.pi + 0.3, 3 * math.pi - 0.3, 80)  # over the top at 2 pi
    theta = np.concatenate([math.pi + 0.3 * np.sin(np.linspace(0, 2 * np.pi, 100)),
                            up, 3 * math.pi - 0.3 * np.sin(np.linspace(0, np.pi, 50)),
                            np.full(20, 3 * math.pi)])
    mode = np.zeros(len(theta), dtype=int)
    assert measure(run(theta, mode))["oscillations"][0] == 1.0  # two passes: 1 oscillation
    back = np.concatenate([theta[:-20], 3 * math.pi + 0.3 * np.sin(np.linspace(0, 3, 60))])
    assert measure(run(back, np.zeros(len(back), dtype=int)))["oscillations"][0] == 1.5


def test_a_catch_that_is_lost_counts_its_exits_and_never_settles():
    theta, mode = swing_then_catch(passes=6, catch_at=468, settle_at=650)
    mode[700:720] = Mode.SWING_UP.code
    mode[900:905] = Mode.SWING_UP.code
    theta[-1] = 2 * math.pi - 0.06  # off upright at the very end
    m = measure(run(theta, mode))
    assert m["catch_exits"][0] == 2.0
    assert m["upright_s"][0] == math.inf
    never = measure(run(np.full(100, math.pi), np.zeros(100, dtype=int)))
    assert never["hand_over_s"][0] == math.inf and never["upright_s"][0] == math.inf


def test_saturation_overlap_counts_the_cycles_with_both_at_the_limit():
    """Ten cycles with the set-point at +0.9 A: the voltage at 11.47 V in four, at
    0.95 x 11.47 = 10.8965 V in four (the anti-windup's level: counted), at 10 V in two;
    then five cycles with only the voltage saturated, and five of the opposite signs."""
    n = 40
    i_d = np.zeros(n)
    u = np.zeros(n)
    i_d[:10] = 0.9
    u[:4], u[4:8], u[8:10] = 11.47, 0.95 * 11.47, 10.0
    u[10:15] = -11.47
    i_d[20:25], u[20:25] = -0.9, 11.47  # both at a limit, opposite signs: not "together"
    m = measure(run(np.full(n, math.pi), np.zeros(n, dtype=int), u, i_d))
    assert m["saturation_overlap"][0] == pytest.approx(8 / 20)
    none = measure(run(np.full(n, math.pi), np.zeros(n, dtype=int)))
    assert none["saturation_overlap"][0] == 0.0


def test_judge_needs_every_event_within_its_tolerance():
    e = load_experiment("thesis-6.6")
    good = {"oscillations": np.array([3.0, 2.5, 3.0, 3.0]),
            "hand_over_s": np.array([2.34, 2.53, 2.55, 2.30]),
            "upright_s": np.array([3.25, 2.95, 3.25, math.inf]),
            "catch_exits": np.zeros(4),
            "saturation_overlap": np.array([1.0, 0.75, 0.9, 0.9])}
    assert judge(e, good).tolist() == [True, True, False, False]
    assert set(EVENTS) == {ev.name for ev in e.events}

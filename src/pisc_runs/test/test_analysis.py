"""Analysis of the reference swing-up: metrics equal to its recorded summary, plots, CSV."""

from __future__ import annotations

import csv
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pisc_runs.analysis import CSV_COLUMNS, PLOTS, UPRIGHT_RAD, analyse_bag
from pisc_bag.bag import read_bag
from pisc_msgs_py.convert import motor_sample_from_msg
from pisc_msgs_py.topics import VOLTAGE
from pisc_model.dynamics import wrap_to_upright

pytestmark = pytest.mark.bag

BAGS = Path(__file__).resolve().parents[3] / "bags"
SWINGUP = BAGS / "lyapunov-swingup"  # the times below are of this recording
THESIS = BAGS / "thesis-gains"


def pisc_bag(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", *map(str, args)],
                          capture_output=True, text=True, timeout=180)


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR", path
    return struct.unpack(">II", data[16:24])


@pytest.fixture(scope="module")
def analysed(tmp_path_factory):
    out = tmp_path_factory.mktemp("analysis")
    return pisc_bag("analyse", SWINGUP, "--out", out), out


def test_metrics_match_the_summary_printed_when_the_bag_was_recorded(analysed):
    completed, _ = analysed
    assert completed.returncode == 0, completed.stderr
    recorded = (SWINGUP / "summary.txt").read_text().splitlines()
    metrics = recorded[recorded.index(next(x for x in recorded if x.startswith("cycles"))):]
    assert len(metrics) == 10 and metrics[-1] == "result                 CAUGHT"
    printed = completed.stdout.splitlines()
    for line in metrics[:-1]:  # first catch, largest |x|, RMS, latency, deadline misses, ...
        assert line in printed, line
    # the verdict now says which rule it is: the benchmark's caught tier, and the others
    assert ("result                 CAUGHT (the caught tier: caught for good by 8 s, held "
            "(|theta| < 0.05 rad, |x| < 0.02 m) from 9 s to the end (10 s))") in printed
    assert any(line.startswith("fast                   yes: caught for good by 3 s")
               for line in printed)


def test_the_added_metrics_agree_with_the_recorded_states():
    a = analyse_bag(SWINGUP)
    tr = a.trace
    assert a.summary.first_catch_s == pytest.approx(1.47, abs=1e-12)
    assert a.mode_changes[1][0] == a.summary.first_catch_s
    assert [m.value for _, m in a.mode_changes] == ["swing_up", "catch"]
    # time to upright: the first cycle from the catch on within UPRIGHT_RAD of upright
    th = np.abs(wrap_to_upright(tr.true_theta))
    k = int(round(a.time_to_upright_s / 0.005))
    assert th[k] <= UPRIGHT_RAD and np.all(th[294:k] > UPRIGHT_RAD)
    assert 1.47 < a.time_to_upright_s < 3.25  # the thesis's rig: 3.25 s
    # settle time: inside 0.05 rad and 0.02 m from then on, outside just before
    s = int(round(a.settle_time_s / 0.005))
    inside = (th <= 0.05) & (np.abs(tr.true_x) <= 0.02)
    assert inside[s:].all() and not inside[s - 1]
    error = tr.i_d - tr.i
    assert a.current_peak_error_a == np.max(np.abs(error))
    assert a.voltage_saturated_s == pytest.approx(0.005 * np.sum(np.abs(tr.u) == 11.47))
    assert a.current_saturated_s == pytest.approx(0.005 * np.sum(np.abs(tr.i_d) == 0.9))
    assert a.voltage_saturated_s == pytest.approx(0.8) and a.current_saturated_s == 1.565


def test_plots_are_written_one_per_thesis_figure(analysed):
    completed, out = analysed
    assert "wrote 6 plots and 1 CSV log(s)" in completed.stdout
    for name, *_ in PLOTS:
        path = out / name
        assert png_size(path) == (800, 360)
        assert path.stat().st_size > 20_000, path  # a plotted trace, not an empty frame
    assert sorted(p.name for p in out.glob("*.png")) == sorted(p[0] for p in PLOTS)


def test_csv_has_the_thesis_columns_and_every_value_exactly(analysed):
    _, out = analysed
    with (out / "log.csv").open() as stream:
        rows = list(csv.reader(stream))
    assert tuple(rows[0]) == CSV_COLUMNS == ("t", "x", "theta", "x_dot", "theta_dot", "i",
                                             "i_d", "u")
    assert len(rows) == 1 + 2001
    voltages = [motor_sample_from_msg(m.message).value
                for m in read_bag(SWINGUP, [VOLTAGE.name])]
    assert [float(r[7]) for r in rows[1:]] == voltages
    assert float(rows[1][0]) == 0.0 and float(rows[-1][0]) == 10.0


def test_two_bags_overlaid(tmp_path):
    completed = pisc_bag("analyse", SWINGUP, "--overlay", THESIS, "--out", tmp_path)
    assert completed.returncode == 0, completed.stderr
    assert "lyapunov-swingup:" in completed.stdout and "thesis-gains:" in completed.stdout
    assert "modes                  swing_up at 0.000 s, catch at 1.445 s, swing_up at 1.715 s" \
        in completed.stdout
    assert (tmp_path / "log_overlay_thesis-gains.csv").is_file()
    single = pisc_bag("analyse", SWINGUP, "--out", tmp_path / "single")
    assert single.returncode == 0
    for name, *_ in PLOTS:
        assert (tmp_path / name).read_bytes() != (tmp_path / "single" / name).read_bytes()


def test_a_message_of_the_wrong_layout_is_named(tmp_path):
    from pisc_bag.bag import TYPESTORE, BagWriter
    from pisc_msgs_py.topics import GRAPH_TOPICS, JOINT_STATES

    JointState = TYPESTORE.types["sensor_msgs/msg/JointState"]
    Header = TYPESTORE.types["std_msgs/msg/Header"]
    Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
    msg = JointState(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=""),
                     name=["wheel"], position=np.array([0.1]),
                     velocity=np.array([], dtype=float), effort=np.array([], dtype=float))
    writer = BagWriter(tmp_path / "odd", GRAPH_TOPICS)
    writer.write(JOINT_STATES.name,
                 bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/JointState")), 1, 1)
    writer.close()
    completed = pisc_bag("analyse", tmp_path / "odd")
    assert completed.returncode == 2 and "Traceback" not in completed.stderr
    assert completed.stderr == (f"pisc_bag analyse: {tmp_path / 'odd'}: /pisc/joint_states: "
                                "joint_states: expected joints ['cart', 'pendulum'], got "
                                "['wheel']\n")
    replay = pisc_bag("replay", tmp_path / "odd", "--config", "default")
    assert replay.returncode == 2 and "Traceback" not in replay.stderr
    assert "/pisc/joint_states: joint_states: expected joints" in replay.stderr


def test_malformed_bags_give_a_clear_error_and_no_traceback(tmp_path):
    missing = pisc_bag("analyse", tmp_path / "nowhere")
    assert missing.returncode == 2
    assert missing.stderr == f"pisc_bag analyse: {tmp_path / 'nowhere'}: no such bag directory\n"
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: [oops\n")
    completed = pisc_bag("analyse", bad)
    assert completed.returncode == 2 and "Traceback" not in completed.stderr
    assert completed.stderr.startswith(f"pisc_bag analyse: {bad / 'metadata.yaml'}: malformed "
                                       "rosbag2 metadata")

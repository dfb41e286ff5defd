"""Regression replay of every reference bag, and what a changed gain looks like."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pisc_bag.bag import BagError, BagWriter, header_stamp_ns, read_bag, read_bag_raw
from pisc_bag.bag_repair import index_problems, repair_bag
from pisc_bag.bag_readers import READERS, read_every_way
from pisc_runs.replay import (
    COMPARED_TOPICS,
    RecordedRun,
    StampTable,
    bag_config,
    compare,
    load_recorded,
    load_recorded_bag,
    load_recorded_columns,
    replay_bag,
    replay_cores,
)
from pisc_msgs_py.convert import stamp_from_msg
from pisc_msgs_py.topics import (
    CART_FORCE,
    CURRENT_SETPOINT,
    GRAPH_TOPICS,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    STATE,
    VOLTAGE,
)
from pisc_msgs_py.types import Mode

pytestmark = pytest.mark.bag

BAGS = Path(__file__).resolve().parent.parent / "bags"
# the committed bags; runs of ``./pisc run`` land beside them as bags/run-* (not in git)
REFERENCE_BAGS = sorted(p for p in BAGS.iterdir()
                        if (p / "metadata.yaml").is_file() and not p.name.startswith("run-"))
SWINGUP = BAGS / "lyapunov-swingup"  # the previous default of its day, whose times the
# tests below name; default-swingup, of today's default, replays as every reference bag


def test_the_reference_bags_are_there():
    assert {p.name for p in REFERENCE_BAGS} >= {"default-swingup", "thesis-gains",
                                                 "driver-swingup"}


@pytest.mark.parametrize("bag", REFERENCE_BAGS, ids=lambda p: p.name)
def test_every_reader_reads_every_message_of_every_reference_bag(bag):
    """Found by a hostile test: rosbags' AnyReader refused every committed bag ("Unindexed
    MCAP messages are not in timestamp order") and an indexed reader found none of their
    messages. Now each is indexed and in log-time order, and rosbags, mcap in log-time
    order and the indexed reader read every message that metadata.yaml counts, the same
    ones."""
    read = read_every_way(bag)
    import yaml

    count = yaml.safe_load((bag / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]["message_count"]
    assert len(read["mcap"]) == count
    for reader in READERS:
        assert read[reader] == read["mcap"], reader
    times = [t for _, t, _ in read["mcap"]]
    assert times == sorted(times)
    (path,) = bag.glob("*.mcap")
    assert index_problems(path) == []


def summary_cycles(bag: Path) -> int:
    line = next(x for x in (bag / "summary.txt").read_text().splitlines()
                if x.startswith("cycles"))
    return int(line.split()[1])


@pytest.mark.parametrize("bag", REFERENCE_BAGS, ids=lambda p: p.name)
def test_every_reference_bag_replays_bit_for_bit_through_the_cores(bag):
    report = replay_bag(bag)
    assert report.reproduced, report.format()
    assert report.cycles == summary_cycles(bag)
    for t in report.topics:
        assert t.differ == 0 and t.largest == 0.0 and t.first is None
        expected = report.cycles if t.topic != MODE.name else t.compared
        assert t.compared == expected and t.compared >= 2
    assert "result: REPRODUCED (tolerance 0)" in report.format()


def assert_columns_give_the_messages_run(bag: Path) -> RecordedRun:
    """Replay's bounded-memory path (the bag read as columns, the run held as numpy
    columns) gives the run the message path gives, value for value, and the same report
    through the cores."""
    by_messages = load_recorded(read_bag(bag), str(bag))
    by_columns = load_recorded_columns(bag, str(bag))
    assert list(by_columns.samples) == list(by_messages.samples)
    assert all(type(v) is float for s in by_columns.samples[:3] for v in s[1:])
    for topic in COMPARED_TOPICS:
        assert dict(by_columns.outputs[topic]) == dict(by_messages.outputs[topic]), topic
    assert isinstance(by_columns.outputs[VOLTAGE.name], StampTable)
    assert by_columns.notes == by_messages.notes
    cfg, _ = bag_config(bag)
    recomputed = replay_cores(by_columns, cfg)
    as_dicts = {topic: dict(table) for topic, table in recomputed.items()}
    assert compare(by_columns, recomputed) == compare(by_messages, as_dicts)
    return by_columns


@pytest.mark.parametrize("bag", REFERENCE_BAGS, ids=lambda p: p.name)
def test_replay_reads_the_columns_into_the_run_the_messages_give(bag):
    assert_columns_give_the_messages_run(bag)


def test_a_resent_sample_keeps_its_first_message_and_bad_messages_are_named(tmp_path):
    """A stamp recorded twice keeps its first message on both paths, and a topic without
    messages is empty on both; a message the columns cannot read (joints replay does not
    know) goes to the message path, whose error names it."""
    import numpy as np

    from pisc_bag.bag import TYPESTORE

    def joint_state(stamp: int, names: list[str], position: list[float]) -> bytes:
        t = TYPESTORE.types
        msg = t["sensor_msgs/msg/JointState"](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
                sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id=""),
            name=names, position=np.array(position), velocity=np.array([], dtype=float),
            effort=np.array([], dtype=float))
        return bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/JointState"))

    raw = list(read_bag_raw(SWINGUP))
    resent = joint_state(10_000_000, ["cart", "pendulum"], [9.0, 9.0])
    for name, extra in (("resent", (JOINT_STATES.name, resent)),
                        ("strange", (STATE.name, joint_state(0, ["a", "b"], [0.0, 0.0]))),
                        ("no-force", None)):
        writer = BagWriter(tmp_path / name, GRAPH_TOPICS)
        for k, m in enumerate(raw):
            if extra is None and m.topic == CART_FORCE.name:
                continue  # a topic with no message (a run that did not record it)
            writer.write(m.topic, m.data, m.log_time_ns, m.publish_time_ns or 0)
            if k == len(raw) // 2 and extra is not None:
                writer.write(*extra, m.log_time_ns, m.log_time_ns)
        writer.close()
        shutil.copy(SWINGUP / "pisc_params.yaml", tmp_path / name)
    assert not assert_columns_give_the_messages_run(tmp_path / "no-force").outputs[
        CART_FORCE.name]
    run = assert_columns_give_the_messages_run(tmp_path / "resent")
    assert run.samples[2][1:3] != (9.0, 9.0) and run.samples[2][0] == 10_000_000
    with pytest.raises(BagError, match="/pisc/state: state: expected joints "
                                       r"\['cart', 'pendulum'\], got \['a', 'b'\]"):
        load_recorded_bag(tmp_path / "strange")


def test_a_changed_swing_up_gain_diverges_at_the_first_sample():
    report = replay_bag(SWINGUP, overrides={"swing_up.k_x": 6.3})
    assert not report.reproduced
    by_topic = {t.topic: t for t in report.topics}
    assert by_topic[STATE.name].differ == 0  # the estimator does not see gains
    first = by_topic[CART_FORCE.name].first
    assert first.stamp_ns == 0 and first.field == "force"
    recorded_force = next(m.message.wrench.force.x for m in read_bag(SWINGUP, [CART_FORCE.name]))
    assert first.recorded == recorded_force and first.recomputed != recorded_force
    assert by_topic[CART_FORCE.name].largest > 0


def test_a_changed_catch_pole_diverges_exactly_at_the_first_catch():
    """Catch gains act from the first catch (1.470 s in summary.txt) on, never before."""
    report = replay_bag(SWINGUP, overrides={"catch.poles": [-15.0, -11.0, -3.0, -2.4]})
    by_topic = {t.topic: t for t in report.topics}
    assert by_topic[CART_FORCE.name].first.stamp_ns == 1_470_000_000
    assert by_topic[MODE.name].differ == 0
    assert "first divergence on /pisc/cart_force: t = 1.470 s" in report.format()


def test_a_changed_switching_threshold_moves_the_mode_change():
    report = replay_bag(SWINGUP, overrides={"switching.delta_s": 0.1})
    first = {t.topic: t for t in report.topics}[MODE.name].first
    assert first is not None and first.field == "mode"
    assert first.stamp_ns == 1_470_000_000 and first.recorded is Mode.CATCH


def test_replay_command_exit_status_and_report():
    ok = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "replay", str(SWINGUP)],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "2001 cycles through the estimator, supervisor and current loop cores" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "replay", str(SWINGUP),
                          "--set", "current_loop.k_pi=2.91"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 1, bad.stderr
    assert "first divergence on /pisc/motor/voltage: t = 0.000 s (stamp 0) voltage" in bad.stdout
    assert "result: MISMATCH (tolerance 0)" in bad.stdout
    # a tolerance above the largest difference accepts it
    loose = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "replay", str(SWINGUP),
                            "--set", "current_loop.k_pi=2.91", "--tolerance", "0.1"],
                           capture_output=True, text=True, timeout=120)
    assert loose.returncode == 0 and "REPRODUCED (tolerance 0.1)" in loose.stdout


def test_replay_runs_the_cores_without_the_plant_kernel():
    """Replay's memory (<= 200 MB for a 10-minute bag) leaves no room
    for numba (75 MB imported): the configuration and the cores come without the plant's
    kernel (pisc_plant.layout), and the batch controllers are imported only by a batch.
    (python-control and scipy are: the catch gain is designed again, and the recorded K
    kept when it is the same design.)"""
    code = ("import sys\nfrom pisc_runs.replay import replay_bag\n"
            f"report = replay_bag({str(SWINGUP)!r})\nassert report.reproduced\n"
            "print(sorted(m for m in ('numba', 'pisc_plant.kernel', "
            "'pisc_sim.batch_controllers') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.integration
def test_replay_through_the_nodes_over_topics(domain_id):
    from pisc_bringup.replay_node import replay_nodes

    report = replay_nodes(SWINGUP, domain_id=domain_id)
    assert report.reproduced, report.format()
    assert report.cycles == 2001 and report.how == "nodes"
    changed = replay_nodes(SWINGUP, overrides={"catch.poles": [-15.0, -11.0, -3.0, -2.4]},
                           domain_id=domain_id)
    first = {t.topic: t for t in changed.topics}[CART_FORCE.name].first
    assert first.stamp_ns == 1_470_000_000


def test_compare_reports_missing_outputs_and_respects_the_tolerance():
    samples = [(k * 5_000_000, 0.0, 3.0, 0.0) for k in range(4)]
    outputs = {name: {} for name in COMPARED_TOPICS}
    for stamp, *_ in samples:
        outputs[STATE.name][stamp] = (0.0, 0.0)
        outputs[CART_FORCE.name][stamp] = (1.0,)
        outputs[CURRENT_SETPOINT.name][stamp] = (0.5,)
        outputs[VOLTAGE.name][stamp] = (2.0,)
    outputs[MODE.name][0] = (Mode.SWING_UP,)
    run = RecordedRun(samples, outputs)
    same = {k: dict(v) for k, v in outputs.items()}
    assert compare(run, same).reproduced
    lost = {k: dict(v) for k, v in outputs.items()}
    del lost[VOLTAGE.name][10_000_000]
    report = compare(run, lost)
    voltage = {t.topic: t for t in report.topics}[VOLTAGE.name]
    assert voltage.differ == 1 and voltage.compared == 3
    assert voltage.first.stamp_ns == 10_000_000 and voltage.first.recomputed is None
    near = {k: dict(v) for k, v in outputs.items()}
    near[VOLTAGE.name][5_000_000] = (2.0 + 1e-9,)
    assert not compare(run, near).reproduced
    assert compare(run, near, tolerance=1e-8).reproduced
    nan = {k: dict(v) for k, v in outputs.items()}
    nan[VOLTAGE.name][5_000_000] = (float("nan"),)
    assert not compare(run, nan, tolerance=1e9).reproduced


def test_a_repaired_bag_whose_recording_ended_inside_a_cycle_replays_without_that_cycle(
        tmp_path):
    """Found by a hostile test: replay of a repaired bag failed ("/pisc/joint_states at
    stamp ... has no /pisc/motor/current of the same stamp"): the recorder died inside the
    last cycle. The incomplete last cycle is dropped, and the report says so."""
    cut = 1_000_000_000  # the recorder dies after this cycle's joint_states
    live = BagWriter(tmp_path / "live", GRAPH_TOPICS)
    for m in read_bag_raw(SWINGUP):
        stamp = header_stamp_ns(m.data)
        if stamp is not None and (stamp > cut or (stamp == cut and
                                                  m.topic != JOINT_STATES.name)):
            continue
        live.write(m.topic, m.data, m.log_time_ns, m.publish_time_ns or 0)
    bag = tmp_path / "killed"
    bag.mkdir()
    (bag / "killed_0.mcap").write_bytes(live.path.read_bytes())  # as SIGKILL leaves it
    live.close()
    shutil.copy(SWINGUP / "pisc_params.yaml", bag)
    repair_bag(bag)
    assert_columns_give_the_messages_run(bag)
    report = replay_bag(bag)
    note = ("dropped the incomplete last cycle, the recording ended inside it: stamp "
            f"1000000000 (t = 1.000 s) has no {MOTOR_CURRENT.name}")
    assert report.reproduced, report.format()
    assert report.cycles == 200 and note in report.notes
    completed = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "replay", str(bag)],
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr
    assert note in completed.stdout and "result: REPRODUCED" in completed.stdout
    # a sample missing before the end is still an error
    run = load_recorded(read_bag(SWINGUP))
    assert not run.notes
    messages = [m for m in read_bag(SWINGUP)
                if not (m.topic == MOTOR_CURRENT.name
                        and stamp_from_msg(m.message.header.stamp) == 5_000_000)]
    with pytest.raises(BagError, match="at stamp 5000000 has no /pisc/motor/current"):
        load_recorded(iter(messages))


def test_a_truncated_bag_is_refused_with_its_name_and_no_traceback(tmp_path):
    bag = tmp_path / "cut"
    shutil.copytree(SWINGUP, bag)
    mcap = bag / f"{SWINGUP.name}_0.mcap"
    mcap.write_bytes(mcap.read_bytes()[:100_000])
    completed = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "replay", str(bag)],
                               capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert completed.stderr.startswith(f"pisc_bag replay: {mcap}: truncated, it ends without "
                                       "the MCAP footer")
    assert "Traceback" not in completed.stderr
    with pytest.raises(BagError, match="no /pisc/joint_states message"):
        load_recorded(iter(()), "empty")


@pytest.mark.integration
def test_a_run_that_faults_replays_exactly_through_cores_and_nodes(tmp_path, domain_id):
    """The fault path: the supervisor latches fault, the current loop commands 0 V."""
    from pisc_bringup.graph import RunOptions, run_graph
    from pisc_bringup.replay_node import replay_nodes

    # the previous default: the default's track guard keeps the cart inside this range
    result = run_graph(RunOptions(
        config="lyapunov-tuned",
        overrides={"initial.x_m": 0.05, "safety.x_min_m": -0.03}, duration_s=2.0,
        bag_dir=tmp_path / "fault", domain_id=domain_id))
    assert result.summary.faults
    cores = replay_bag(result.bag_dir)
    assert cores.reproduced, cores.format()
    modes = load_recorded(read_bag(result.bag_dir)).outputs[MODE.name]
    assert [v[0] for _, v in sorted(modes.items())][-1] is Mode.FAULT
    nodes = replay_nodes(result.bag_dir, domain_id=domain_id)
    assert nodes.reproduced, nodes.format()
    # the replay sees the fault too: a wider safe range changes the outcome from there on
    wider = replay_bag(result.bag_dir, overrides={"safety.x_min_m": -0.225})
    first = {t.topic: t for t in wider.topics}[MODE.name].first
    assert first is not None and first.recorded is Mode.FAULT

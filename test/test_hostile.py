"""Hostile nodes, clocks, signals and devices: each case failed on the code before the
graph's topics were pinned and every end made a clean one (docs/safety.md).

* a visitor on each input topic of the graph, answering every sample one period ahead
  (lockstep), is named on /diagnostics with its topic, and none of its messages is used;
* a negative or backwards /clock, and a measurement whose stamp is not the next, are
  refused and said, never a crash;
* pisc_graph with a visitor stops at once (exit 3), names it, the bag marks it, and the
  summary and replay call nothing CAUGHT or REPRODUCED;
* SIGINT and SIGTERM to pisc_graph end it cleanly (130, 143) in one process and in
  separate processes, with the summary and a whole bag;
* a serial port that goes away ends the run within --port-retry (realtime).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
import rclpy.node
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from conftest import spin_until
from pisc_bag.bag_repair import index_problems
from pisc_runs.replay import replay_bag
from pisc_runs.summary import foreign_in_bag, summarise_bag
from pisc_control.current_loop_node import CurrentLoopNode
from pisc_control.estimator_node import EstimatorNode
from pisc_control.supervisor_node import SupervisorNode
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.convert import (
    cart_force_to_msg,
    joint_sample_from_msg,
    joint_sample_to_msg,
    mode_to_msg,
    motor_sample_to_msg,
    state_to_msg,
    stamp_to_msg,
    true_state_to_msg,
)
from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    DIAGNOSTICS,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    SIM_STATE,
    STATE,
    VOLTAGE,
)
from pisc_msgs_py.types import (
    CartForce,
    JointSample,
    Mode,
    ModeReport,
    MotorSample,
    StateEstimate,
    TrueState,
)
from pisc_plant.plant_node import PlantNode

ERROR = DiagnosticStatus.ERROR
PERIOD_NS = 5_000_000

pytestmark = pytest.mark.integration


def spoof(topic: str, stamp_ns: int):
    """A message of ``topic`` stamped ``stamp_ns``, with values no controller would make."""
    if topic == JOINT_STATES.name:
        return joint_sample_to_msg(JointSample(stamp_ns, 0.03, 0.5))
    if topic == STATE.name:
        return state_to_msg(StateEstimate(stamp_ns, 0.03, 0.0, 0.5, 0.0))
    if topic == CART_FORCE.name:
        return cart_force_to_msg(CartForce(stamp_ns, -20.0))
    if topic == MODE.name:
        return mode_to_msg(ModeReport(stamp_ns, Mode.CATCH))
    if topic == SIM_STATE.name:
        return true_state_to_msg(TrueState(stamp_ns, 0.03, 0.0, 0.5, 0.0, 0.0))
    if topic == CLOCK.name:
        return Clock(clock=stamp_to_msg(stamp_ns))
    if topic == DIAGNOSTICS.name:
        msg = DiagnosticArray()
        msg.header.stamp = stamp_to_msg(stamp_ns)
        return msg
    return motor_sample_to_msg(MotorSample(stamp_ns, -0.9))  # current, set-point, voltage


class Visitor:
    """A node named ``visitor`` that answers every sample on ``topic``, stamped one period
    ahead (in lockstep with the plant, as the hostile test of the issue did)."""

    def __init__(self, context, topic) -> None:
        self.node = rclpy.node.Node("visitor", context=context)
        self.sent: list[int] = []
        self.publisher = self.node.create_publisher(message_class(topic.type), topic.name,
                                                    qos_profile(topic.qos))

        mine: set[int] = set()

        def answer(msg) -> None:
            stamp = joint_sample_from_msg(msg).stamp_ns
            if stamp in mine:  # its own (on /pisc/joint_states), or answered already
                return
            mine.update((stamp, stamp + PERIOD_NS))
            self.sent.append(stamp + PERIOD_NS)
            self.publisher.publish(spoof(topic.name, stamp + PERIOD_NS))

        self.node.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                      answer, qos_profile(JOINT_STATES.qos))


class LockstepBench:
    """The plant and the three controllers in this process in lockstep (the controllers
    on simulated time, as the launch file runs them), what the plant applies, and every
    status on /diagnostics."""

    def __init__(self, context, clock: str = "lockstep") -> None:
        sim_time = [Parameter("use_sim_time", value=clock == "lockstep")]
        self.controllers = {"estimator": EstimatorNode(context=context,
                                                       parameter_overrides=sim_time),
                            "supervisor": SupervisorNode(context=context,
                                                         parameter_overrides=sim_time),
                            "current_loop": CurrentLoopNode(context=context,
                                                            parameter_overrides=sim_time)}
        self.plant = PlantNode(context=context, parameter_overrides=[
            Parameter("simulation.clock", value=clock),
            Parameter("simulation.clock_every", value=1),
            Parameter("simulation.start_settle_s", value=0.1),
            Parameter("simulation.resend_after_s", value=0.1),
            Parameter("initial.x_m", value=0.05)])
        self.applied: list[tuple[int, float]] = []  # (sample index, voltage)
        command = self.plant._sim.command

        def spy(voltage: float, delay_s: float = 0.0) -> None:
            self.applied.append((self.plant._sim.index, voltage))
            command(voltage, delay_s)

        self.plant._sim.command = spy
        self.probe = rclpy.node.Node("probe", context=context)
        self.statuses: list = []
        self.probe.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                                       lambda m: self.statuses.extend(m.status),
                                       qos_profile(DIAGNOSTICS.qos))
        self.executor = SingleThreadedExecutor(context=context)
        self.nodes = [*self.controllers.values(), self.plant, self.probe]
        for node in self.nodes:
            self.executor.add_node(node)

    def spin_until(self, predicate, timeout_s: float = 20.0) -> bool:
        return spin_until(self.executor, predicate, timeout_s)

    def errors(self, text: str) -> list:
        return [s for s in self.statuses if s.level == ERROR and text in s.message]

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()


def _values(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


# each input of the controllers and who reads it
READERS = [(JOINT_STATES, "estimator"), (MOTOR_CURRENT, "current_loop"),
           (STATE, "supervisor"), (CART_FORCE, "current_loop"), (MODE, "current_loop"),
           (CLOCK, "estimator")]


@pytest.mark.parametrize("topic,reader", READERS, ids=[t.name for t, _ in READERS])
def test_a_visitor_on_an_input_is_named_and_none_of_its_messages_is_used(ros_context,
                                                                         topic, reader):
    bench = LockstepBench(ros_context)
    visitor = None
    try:
        assert bench.spin_until(lambda: bench.plant._sim.index >= 40)
        assert any(v != 0.0 for _, v in bench.applied)
        visitor = Visitor(ros_context, topic)
        bench.executor.add_node(visitor.node)
        text = f"another publisher on {topic.name}: /visitor"
        assert bench.spin_until(lambda: bench.errors(text) and len(visitor.sent) >= 1)
        fault = next(s for s in bench.errors(text) if s.name == f"pisc/{reader}")
        assert _values(fault)["topic"] == topic.name
        assert _values(fault)["intruders"] == "/visitor"
        assert fault.message.startswith(f"{text}; the {reader} uses none of its messages "
                                         "while it is there")
        # the chain answers nothing while the visitor is there: simulated time stands
        # still, and no voltage is applied over any of it
        index = bench.plant._sim.index
        applied = len(bench.applied)
        bench.spin_until(lambda: False, 1.0)
        assert bench.plant._sim.index <= index + 1
        assert all(v == 0.0 for _, v in bench.applied[applied + 1:])
        assert bench.spin_until(lambda: bench.errors("command watchdog: no command answered"))
        # its stamps (one period ahead) never reached an output of the chain
        assert not bench.errors("Traceback")
    finally:
        if visitor is not None:
            bench.executor.remove_node(visitor.node)
            visitor.node.destroy_node()
        bench.close()


@pytest.mark.realtime
@pytest.mark.parametrize("topic", [JOINT_STATES, STATE, CART_FORCE, MODE],
                         ids=lambda t: t.name)
def test_on_the_wall_clock_a_visitor_gets_zero_volts_within_20_ms(ros_context, topic):
    """The issue, on the wall clock: a fake angle of +0.5 rad gave 95 mode flips and 54
    cycles at +-11.47 V. Now the chain answers nothing from the visitor's first message
    on, and the plant's watchdog applies 0 V three periods later."""
    bench = LockstepBench(ros_context, "wall")
    visitor = None
    try:
        assert bench.spin_until(lambda: bench.plant._sim.index >= 100)
        visitor = Visitor(ros_context, topic)
        bench.executor.add_node(visitor.node)
        first = {}
        record = visitor.publisher.publish

        def noted(msg) -> None:
            first.setdefault("sample", bench.plant._sim.index)
            record(msg)

        visitor.publisher.publish = noted
        text = f"another publisher on {topic.name}: "
        assert bench.spin_until(lambda: bench.errors(text) and len(visitor.sent) >= 20)
        zero_from = first["sample"] + 4  # 20 ms of 5 ms periods
        late = [(k, v) for k, v in bench.applied if k >= zero_from and v != 0.0]
        assert late == [], late
    finally:
        if visitor is not None:
            bench.executor.remove_node(visitor.node)
            visitor.node.destroy_node()
        bench.close()


def _clock_node(ros_context):
    node = EstimatorNode(context=ros_context,
                         parameter_overrides=[Parameter("use_sim_time", value=True)])
    plant = rclpy.node.Node("plant", context=ros_context)  # the pinned /clock publisher
    clock = plant.create_publisher(message_class(CLOCK.type), CLOCK.name,
                                   qos_profile(CLOCK.qos))
    statuses: list = []
    plant.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                              lambda m: statuses.extend(m.status), qos_profile(DIAGNOSTICS.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(plant)
    return node, plant, clock, statuses, executor


def test_a_negative_or_backwards_clock_is_refused_and_said_not_a_crash(ros_context):
    node, plant, clock, statuses, executor = _clock_node(ros_context)
    try:
        assert spin_until(executor, lambda: clock.get_subscription_count() >= 1
                          and node._diagnostics.get_subscription_count() >= 1, 10.0)
        clock.publish(Clock(clock=stamp_to_msg(2_000_000_000)))
        assert spin_until(executor, lambda: node.get_clock().now().nanoseconds
                          == 2_000_000_000, 10.0)
        negative = Clock()
        negative.clock.sec, negative.clock.nanosec = -3, 0
        clock.publish(negative)  # rclpy's own subscription raised: "must not be negative"
        assert spin_until(executor, lambda: any("rejected /clock" in s.message
                                                for s in statuses), 10.0)
        clock.publish(Clock(clock=stamp_to_msg(1_000_000_000)))  # back in time
        assert spin_until(executor, lambda: any("goes back" in s.message
                                                for s in statuses), 10.0)
        messages = [s.message for s in statuses if "/clock" in s.message]
        assert messages == [
            "rejected /clock: stamp -3.000000000 s is before 0",
            "rejected /clock: 1.000000000 s goes back from 2.000000000 s; the clock stays "
            "there"], messages
        assert node.get_clock().now().nanoseconds == 2_000_000_000
        clock.publish(Clock(clock=stamp_to_msg(2_005_000_000)))  # forward again: taken
        assert spin_until(executor, lambda: node.get_clock().now().nanoseconds
                          == 2_005_000_000, 10.0)
    finally:
        node.destroy_node()
        plant.destroy_node()


@pytest.mark.parametrize("sim_time", [True, False], ids=["lockstep", "wall"])
def test_a_measurement_whose_stamp_is_not_the_next_is_refused(ros_context, sim_time):
    """(4.7), (4.9) difference over one period: a measurement 3 periods on (lockstep) or
    one from before the last (any clock) is not differentiated, and the node says so."""
    node = EstimatorNode(context=ros_context,
                         parameter_overrides=[Parameter("use_sim_time", value=sim_time)])
    plant = rclpy.node.Node("plant", context=ros_context)
    joints = plant.create_publisher(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                    qos_profile(JOINT_STATES.qos))
    states, statuses = [], []
    plant.create_subscription(message_class(STATE.type), STATE.name,
                              lambda m: states.append(joint_sample_from_msg(m).stamp_ns),
                              qos_profile(STATE.qos))
    plant.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                              lambda m: statuses.extend(s.message for s in m.status),
                              qos_profile(DIAGNOSTICS.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(plant)
    try:
        assert spin_until(executor, lambda: joints.get_subscription_count() >= 1
                          and node._state_pub.get_subscription_count() >= 1
                          and node._diagnostics.get_subscription_count() >= 1, 10.0)
        sent = [10_000_000, 15_000_000, 30_000_000, 12_000_000]
        for stamp in sent:
            joints.publish(joint_sample_to_msg(JointSample(stamp, 0.0, 3.0)))
            spin_until(executor, lambda: False, 0.2)
        rejected = [m for m in statuses if m.startswith("rejected joint_states")]
        if sim_time:  # 30 ms is three periods on, 12 ms before the last
            assert states == [10_000_000, 15_000_000]
            assert rejected == [
                "rejected joint_states: stamp 0.030000 s is not the next period's "
                "(0.015000 s + 5 ms); not used",
                "rejected joint_states: stamp 0.012000 s is not the next period's "
                "(0.015000 s + 5 ms); not used"], rejected
        else:
            assert states == [10_000_000, 15_000_000, 30_000_000]
            assert rejected == [
                "rejected joint_states: stamp 0.012000 s is not the next period's "
                "(later than 0.030000 s); not used"], rejected
    finally:
        node.destroy_node()
        plant.destroy_node()


# -- pisc_graph: a visitor stops the run, the bag marks it ---------------------------------

def _graph(args: list[str], bag: Path, domain_id: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--bag", str(bag), "--domain-id",
         str(domain_id), "--x0", "0.05", *args], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)


def _started(graph: subprocess.Popen, bag: Path, timeout_s: float = 60.0) -> None:
    """Until the run's graph is running: its bag holds 200 kB (a few hundred cycles)."""
    deadline = time.monotonic() + timeout_s

    def size() -> int:
        files = list(bag.glob("*.mcap"))
        return files[0].stat().st_size if files else 0

    while size() < 200_000:
        assert graph.poll() is None and time.monotonic() < deadline, graph.communicate()
        time.sleep(0.01)


@pytest.mark.parametrize("topic,layout", [(JOINT_STATES, []), (SIM_STATE, ["--processes"])],
                         ids=["joint_states-one-process", "true_state-processes"])
def test_a_visitor_on_a_graph_topic_stops_the_run_named_and_the_bag_says_so(
        tmp_path, domain_id, topic, layout):
    """A visitor in lockstep with the plant (the issue's: 538 of 1,325 samples replaced,
    the cart driven into the end stop, a run reported CAUGHT and REPRODUCED): pisc_graph
    names it and stops (exit 3), its bag marks the topic, and neither the summary nor
    replay calls the run caught or reproduced. On the true state only the recorder and
    the runner read, in separate processes. (A 60 s run: with 30 s the run ended on a
    loaded machine before the visitor had been discovered, 2 of about 10 runs.)"""
    bag = tmp_path / "bag"
    graph = _graph(["--duration", "60", *layout], bag, domain_id)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    visitor = None
    try:
        _started(graph, bag)
        visitor = Visitor(context, topic)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(visitor.node)
        spin_until(executor, lambda: graph.poll() is not None, 120.0)
        out, err = graph.communicate(timeout=60)
    finally:
        if graph.poll() is None:
            graph.kill()
        if visitor is not None:
            visitor.node.destroy_node()
        context.try_shutdown()
    assert graph.returncode == 3, (out, err)
    assert f"another publisher on {topic.name}: /visitor" in err, err
    assert "Traceback" not in err and "FATAL" not in err, err
    assert "FOREIGN PUBLISHER" in out and "result                 NOT CAUGHT" in out, out
    assert f"{topic.name}: /visitor" in foreign_in_bag(bag), foreign_in_bag(bag)
    assert index_problems(next(bag.glob("*.mcap"))) == []
    summary = summarise_bag(bag, 0.005)
    assert not summary.caught and f"{topic.name}: /visitor" in summary.foreign
    report = replay_bag(bag)
    assert not report.reproduced and "result: CONTESTED" in report.format()


# -- signals: every end a clean end -----------------------------------------------------

@pytest.mark.parametrize("signum,layout", [(signal.SIGINT, []),
                                           (signal.SIGTERM, ["--processes"])],
                         ids=["SIGINT-one-process", "SIGTERM-processes"])
def test_a_signal_to_pisc_graph_ends_the_run_cleanly_with_its_summary(tmp_path, domain_id,
                                                                    signum, layout):
    """The issue: no handler; pisc_graph died with -15 (or a KeyboardInterrupt traceback),
    no summary, and pisc_record exited 1 with a BrokenPipeError. Now: the source stopped
    first, the bag finished and summarised, "interrupted at t = ...", 128 + the signal."""
    bag = tmp_path / "bag"
    graph = _graph(["--duration", "60", *layout], bag, domain_id)
    try:
        _started(graph, bag)
        graph.send_signal(signum)
        out, err = graph.communicate(timeout=120)
    finally:
        if graph.poll() is None:
            graph.kill()
    assert graph.returncode == 128 + signum, (out, err)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    name = signal.Signals(signum).name
    assert f"stopped                interrupted at t = " in out and f"by {name}" in out, out
    assert "result                 NOT CAUGHT" in out or "result                 CAUGHT" in out
    assert (bag / "metadata.yaml").is_file()
    assert index_problems(next(bag.glob("*.mcap"))) == []
    assert summarise_bag(bag, 0.005).cycles > 100
    report = replay_bag(bag)
    assert report.reproduced, report.format()


def test_the_recorder_outlives_its_runner_without_a_traceback(tmp_path, domain_id):
    """pisc_record whose runner is gone (its standard output a closed pipe) finishes the
    bag and exits 0, without a BrokenPipeError."""
    bag = tmp_path / "bag"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    read, write = os.pipe()
    recorder = subprocess.Popen([sys.executable, "-m", "pisc_bag.record_cli", "--bag", str(bag),
                                 "--topic", VOLTAGE.name], env=env, stdout=write,
                                stderr=subprocess.PIPE, text=True)
    os.close(write)
    try:
        deadline = time.monotonic() + 30.0
        while not list(bag.glob("*.mcap")):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        time.sleep(0.5)
        os.close(read)  # the reader of its counts is gone
        recorder.send_signal(signal.SIGTERM)
        _, err = recorder.communicate(timeout=60)
    finally:
        if recorder.poll() is None:
            recorder.kill()
    assert recorder.returncode == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert (bag / "metadata.yaml").is_file()


# -- through the driver and the virtual rig (the wall clock: realtime) -------------------

def _driver_graph(tmp_path, domain_id, *args: str):
    from test_driver import start_rig

    rig = start_rig(tmp_path)
    bag = tmp_path / "bag"
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    graph = subprocess.Popen(
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--driver", rig.device, "--bag", str(bag),
         "--realtime", "40", *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    return rig, bag, graph


@pytest.mark.realtime
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_a_driver_run_zeroes_the_rig_and_ends_cleanly(tmp_path, domain_id,
                                                                  signum):
    rig, bag, graph = _driver_graph(tmp_path, domain_id, "--duration", "30")
    try:
        _started(graph, bag)
        graph.send_signal(signum)
        out, err = graph.communicate(timeout=120)
        status = rig.status()
    finally:
        if graph.poll() is None:
            graph.kill()
        rig.stop()
    assert graph.returncode == 128 + signum, (out, err)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    assert "interrupted at t = " in out, out
    assert status["last_byte"] == 0 and status["applied_v"] == 0.0, status  # 0 V last
    assert index_problems(next(bag.glob("*.mcap"))) == []
    assert summarise_bag(bag, 0.005).cycles > 50


@pytest.mark.realtime
def test_a_port_that_goes_away_ends_the_run_within_its_retry_naming_it(tmp_path, domain_id):
    """The issue: the virtual rig killed mid-run (--duration 30): pisc_graph ran on past
    120 s, printing nothing. Now it says so at once, waits --port-retry, names the port,
    keeps the bag, exit status 4."""
    rig, bag, graph = _driver_graph(tmp_path, domain_id, "--duration", "30",
                                    "--port-retry", "2")
    try:
        _started(graph, bag)
        device = rig.device
        rig.process.kill()
        killed = time.monotonic()
        out, err = graph.communicate(timeout=60)
        took = time.monotonic() - killed
    finally:
        if graph.poll() is None:
            graph.kill()
        rig.stop()
    assert graph.returncode == 4, (out, err)
    assert f"{device} went away" in err and f"{device} did not come back" in err, err
    assert took < 2.0 + 10.0, took  # the retry, then the stop and the bag's finish
    assert "Traceback" not in err, err
    assert index_problems(next(bag.glob("*.mcap"))) == []
    assert summarise_bag(bag, 0.005).cycles > 50


# -- the smaller cases: each refused with a message naming it ----------------------------

def test_a_domain_id_fast_dds_cannot_map_is_refused_before_anything_starts(tmp_path, capsys):
    from pisc_bringup.graph_cli import main

    bag = tmp_path / "refused"
    assert main(["--domain-id", "300", "--bag", str(bag), "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err == ("pisc_graph: invalid configuration: --domain-id 300: must be 0 .. 232 "
                   "(Fast DDS's ports for a larger id are past 65535)\n")
    assert not bag.exists()


@pytest.mark.parametrize("args,message", [
    (["--seed", "-1"], "--seed -1: must be an integer 0 .. 9223372036854775807"),
    (["--draws", "1000000000000000"],
     "--draws 1000000000000000: at most 10,000,000 (each draw is held in memory; run more "
     "as several seeds)"),
])
def test_robustness_refuses_a_seed_or_a_draw_count_it_cannot_take(capsys, args, message):
    from pisc_robust.robustness_cli import main

    with pytest.raises(SystemExit) as exit_:
        main(["default", *args])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.rstrip().endswith(message), err
    assert "Traceback" not in err


def test_a_number_in_e_notation_is_a_number_as_ros_reads_it():
    from pisc_msgs_py.config import parse_overrides
    from pisc_sim.configuration import load_run_config

    assert parse_overrides(["rig.cart_mass_kg=5e-1", "a=-2E+2", "b=.5e1", "c=5",
                            "d=e5"]) == {"rig.cart_mass_kg": 0.5, "a": -200.0, "b": 5.0,
                                         "c": 5, "d": "e5"}
    config, flat, _ = load_run_config("default", parse_overrides(["rig.cart_mass_kg=5e-1"]))
    assert flat["rig.cart_mass_kg"] == 0.5


def test_the_virtual_rig_refuses_a_silence_longer_than_an_hour():
    from pisc_plant.rig_faults import RequestError, check_request

    assert check_request({"silence_s": 3600})["silence_s"] == 3600.0
    with pytest.raises(RequestError, match=r"silence_s = 1e\+308 is too long \(seconds "
                                           r"without frames, 0 \.\. 3600\)"):
        check_request({"silence_s": 1e308})


def test_the_summary_flags_a_voltage_before_its_sample_and_a_foreign_publisher():
    """The issue: a summary printed a negative sample-to-voltage median (-0.904 ms) and
    nothing flagged it; a bag with a foreign publisher was CAUGHT."""
    import numpy as np

    from pisc_runs.verdict import Criteria
    from pisc_runs.summary import RunTables, Table, summarise_tables

    n = 10
    stamps = np.arange(n, dtype=np.int64) * PERIOD_NS
    published = stamps + 10**12

    def table(publish, values) -> Table:
        return Table(stamps.copy(), publish, np.asarray(values, dtype=np.float64))

    tables = RunTables(
        joints=table(published, np.zeros((n, 2))),
        state=table(published, np.zeros((n, 2))),
        current=table(published, np.zeros((n, 1))),
        setpoint=table(published, np.zeros((n, 1))),
        # three voltages published 0.9 ms before their sample
        voltage=table(published + np.array([-900_000] * 3 + [200_000] * (n - 3)),
                      np.zeros((n, 1))),
        true=table(published, np.zeros((n, 2))),
        modes=[(0, Mode.CATCH, "")])
    # caught at once and held from the second sample to the end of this 45 ms run
    hold = Criteria(run_s=0.045, catch_by_s=0.005, hold_from_s=0.005, fast_by_s=0.005,
                    fast_hold_from_s=0.005)
    summary = summarise_tables(tables, 0.005, hold)
    assert summary.negative_latencies == 3 and summary.caught
    assert ("TIMES                  3 cycles whose voltage was published before their "
            "sample: not the graph's own timing (another publisher, or a clock that "
            "stepped back)") in summary.format().splitlines()
    tables.foreign.append("/pisc/motor/current_setpoint: /visitor")
    summary = summarise_tables(tables, 0.005, hold)
    assert not summary.caught
    lines = summary.format().splitlines()
    assert "FOREIGN PUBLISHER      /pisc/motor/current_setpoint: /visitor" in lines
    assert lines[-1].startswith("result                 NOT CAUGHT (the caught tier")
    assert summary.why["caught"] == "a foreign publisher on the graph's topics"


@pytest.mark.parametrize("kind", [k for k in __import__("pisc_bringup.launch_graph", fromlist=["x"])
                                  .NODE_KINDS if k != ("pisc_driver", "driver_node")],
                         ids=lambda k: k[1])
def test_every_topic_a_node_publishes_is_declared_for_the_runner(ros_context, kind):
    """pisc_graph pins the publishers of every topic of the graph by what NODE_KINDS
    declares: a node publishing a topic not declared there would be taken for a foreign
    publisher and stop every run. (The driver needs a port; its topics are declared with
    the plant's, test_driver.)"""
    import importlib

    from pisc_bringup.launch_graph import NODE_KINDS

    spec = NODE_KINDS[kind]
    cls = getattr(importlib.import_module(spec.module), spec.cls)
    node = cls(context=ros_context, parameter_overrides=[
        Parameter("simulation.clock", value="lockstep")] if kind[1] == "plant_node" else [])
    try:
        published = {p.topic_name for p in node.publishers} - {"/rosout", "/parameter_events"}
        assert published <= {t.name for t in spec.publishes}, published
    finally:
        node.destroy_node()

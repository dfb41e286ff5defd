"""Bad input to a run, crashed nodes and visitors on the command topic.

Each case was found by a hostile test on the landed code; each test here failed there.
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
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from conftest import spin_until
from pisc_bringup.graph_cli import main
from pisc_control.current_loop_node import CurrentLoopNode
from pisc_control.estimator_node import EstimatorNode
from pisc_control.supervisor_node import SupervisorNode
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.convert import (
    joint_sample_from_msg,
    mode_from_msg,
    motor_sample_to_msg,
    stamp_from_msg,
)
from pisc_msgs_py.topics import DIAGNOSTICS, JOINT_STATES, MODE, SIM_STATE, VOLTAGE
from pisc_msgs_py.types import Mode, MotorSample
from pisc_plant.plant_node import PlantNode

OK = DiagnosticStatus.OK
ERROR = DiagnosticStatus.ERROR

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


# -- visitors on the command topic and silent controllers, launch-free --------------------

VISITOR_V = 11.47


class _Bench:
    """The plant and the three controllers in this process, a spy on what the plant
    applies, and a probe of the plant's diagnostics."""

    def __init__(self, context, clock: str) -> None:
        plant_params = [Parameter("simulation.clock", value=clock),
                        Parameter("simulation.start_settle_s", value=0.1),
                        Parameter("simulation.resend_after_s", value=0.2),
                        Parameter("initial.x_m", value=0.05)]
        self.controllers = {"estimator": EstimatorNode(context=context),
                            "supervisor": SupervisorNode(context=context),
                            "current_loop": CurrentLoopNode(context=context)}
        self.plant = PlantNode(context=context, parameter_overrides=plant_params)
        self.applied: list[tuple[int, float]] = []  # (sample index, voltage) per command
        command = self.plant._sim.command

        def spy(voltage: float, delay_s: float = 0.0) -> None:
            self.applied.append((self.plant._sim.index, voltage))
            command(voltage, delay_s)

        self.plant._sim.command = spy
        self.sample_of: dict[int, int] = {}  # stamp -> index of every sample published
        record = self.plant._watchdog.sample

        def recorded(index: int, stamp_ns: int) -> None:
            self.sample_of[stamp_ns] = index
            record(index, stamp_ns)

        self.plant._watchdog.sample = recorded
        self.probe = rclpy.node.Node("probe", context=context)
        self.diagnostics: list = []
        self.probe.create_subscription(
            message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
            lambda m: self.diagnostics.extend(s for s in m.status if s.name == "pisc/plant"),
            qos_profile(DIAGNOSTICS.qos))
        self.executor = SingleThreadedExecutor(context=context)
        for node in [*self.controllers.values(), self.plant, self.probe]:
            self.executor.add_node(node)

    def spin_until(self, predicate, timeout_s: float = 20.0) -> bool:
        return spin_until(self.executor, predicate, timeout_s)

    def errors(self, text: str) -> list:
        return [s for s in self.diagnostics if s.level == ERROR and text in s.message]

    def close(self) -> None:
        for node in [*self.controllers.values(), self.plant, self.probe]:
            node.destroy_node()


def _values(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


@pytest.mark.parametrize("clock", ["lockstep", pytest.param("wall", marks=pytest.mark.realtime)])
def test_a_visitor_answering_every_sample_drives_nothing_and_is_named(ros_context, clock):
    bench = _Bench(ros_context, clock)
    visitor = rclpy.node.Node("visitor", context=ros_context)
    sent: list[int] = []  # sample stamps the visitor answered
    try:
        assert bench.spin_until(lambda: bench.plant._sim.index >= 40)
        applied_before = len(bench.applied)
        assert any(v != 0.0 for _, v in bench.applied)  # the current loop drives the motor
        publisher = visitor.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                             qos_profile(VOLTAGE.qos))

        def answer(msg) -> None:
            sample = joint_sample_from_msg(msg)
            sent.append(sample.stamp_ns)
            publisher.publish(motor_sample_to_msg(MotorSample(sample.stamp_ns, VISITOR_V)))

        visitor.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                    answer, qos_profile(JOINT_STATES.qos))
        bench.executor.add_node(visitor)
        start = bench.plant._sim.index
        assert bench.spin_until(lambda: len(sent) >= 40 and bench.errors("/visitor"))
        fault = bench.errors("/visitor")[0]
        assert fault.message.startswith(f"another publisher on {VOLTAGE.name}: /visitor; the "
                                         "plant applies 0 V while it is there")
        assert _values(fault)["intruders"] == "/visitor"
        # none of its commands applied; 0 V from the sample its first answer came for
        after = bench.applied[applied_before:]
        assert VISITOR_V not in {v for _, v in bench.applied}
        faulted_at = int(_values(fault)["sample"])
        assert start <= faulted_at
        assert all(v == 0.0 for k, v in after if k >= faulted_at), after
        assert faulted_at <= bench.sample_of[sent[0]]  # at the latest its first message's
        # the visitor leaves: the current loop's commands apply again
        bench.executor.remove_node(visitor)
        visitor.destroy_node()
        gone = len(bench.applied)
        assert bench.spin_until(lambda: any(
            s.level == OK and "/visitor left" in s.message for s in bench.diagnostics))
        assert bench.spin_until(lambda: any(v != 0.0 for _, v in bench.applied[gone:]))
    finally:
        bench.close()


@pytest.mark.parametrize("stage", ["estimator", "supervisor", "current_loop"])
def test_in_lockstep_a_silent_stage_holds_no_voltage_and_is_named(ros_context, stage):
    """Lockstep: time advances only on a command carrying the awaited sample's stamp, so a
    controller that stops holds no voltage over any simulated time; the plant names it."""
    bench = _Bench(ros_context, "lockstep")
    try:
        assert bench.spin_until(lambda: bench.plant._sim.index >= 40)
        node = bench.controllers.pop(stage)
        bench.executor.remove_node(node)  # it stops answering; its publishers stay
        index = bench.plant._sim.index
        assert bench.spin_until(lambda: bench.errors("command watchdog"), 10.0)
        assert bench.plant._sim.index == index  # simulated time stood still
        error = bench.errors("command watchdog")[0]
        assert f"the {stage} (/{stage}) stopped" in error.message, error.message
        assert _values(error)["silent"] == f"/{stage}"
        node.destroy_node()
    finally:
        bench.close()


@pytest.mark.realtime
@pytest.mark.parametrize("stage", ["estimator", "supervisor", "current_loop"])
def test_on_the_wall_clock_a_silent_stage_gets_zero_volts_at_once_and_its_name_later(
        ros_context, stage):
    """Wall clock: 0 V from the third sample left unanswered, said at once;
    the stage is named when it has fallen 8 samples behind the one before it
    (StopWitness), which only a stage that stopped does."""
    bench = _Bench(ros_context, "wall")
    try:
        assert bench.spin_until(lambda: bench.plant._sim.index >= 40)
        node = bench.controllers.pop(stage)
        bench.executor.remove_node(node)  # it stops answering; its publishers stay
        assert bench.spin_until(lambda: len(bench.errors("command watchdog")) >= 2, 10.0)
        trip, named = bench.errors("command watchdog")[:2]
        values = _values(named)
        assert trip.message.endswith("(the stage that stopped is named when it has fallen "
                                     "behind)"), trip.message
        assert f"the {stage} (/{stage}) stopped" in named.message, named.message
        assert values["silent"] == f"/{stage}" and values["sure"] == "True"
        assert values["sample"] == _values(trip)["sample"]
        tripped = int(values["sample"])
        assert tripped - int(values["last_answered_sample"]) == 3
        assert int(values["behind"]) >= 8 and int(values["named_at_sample"]) > tripped
        assert all(v == 0.0 for k, v in bench.applied if k >= tripped)
        node.destroy_node()
    finally:
        bench.close()


# -- crash matrix: SIGKILL of a controller process in a wall-clock graph -------------------

def _child_pid(parent: int, executable: str) -> int | None:
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue
        ppid = int(stat.rpartition(")")[2].split()[1])
        if ppid == parent and executable in cmdline:
            return int(entry.name)
    return None


@pytest.mark.realtime
@pytest.mark.parametrize("stage", ["estimator", "supervisor", "current_loop"])
def test_sigkill_of_a_controller_while_balancing_zeroes_the_motor_and_fails_the_run(
        tmp_path, domain_id, monkeypatch, stage):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # as pisc_graph's
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain_id))
    graph = subprocess.Popen(
        # started 0.05 rad from upright: caught at once. (From hanging, the swing-up of
        # the default passes within 11 mm of the safe range's end, and with --processes on
        # this 2-core machine its latency faulted it before the catch in 2 of 9 runs.) At
        # the middle of the safe range [-0.225, 0.125] m: from x0 = +0.05 m the catch
        # carried the cart 80 mm, out of the range, under load (2026-12-03, p99 10 ms)
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--processes", "--clock", "wall",
         "--x0", "-0.05", "--set", "initial.theta_rad=0.05", "--duration", "60",
         "--bag", str(tmp_path / "bag"), "--domain-id", str(domain_id)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    probe = rclpy.node.Node("crash_probe", context=context)
    modes: list = []
    plant: list = []
    probe.create_subscription(message_class(MODE.type), MODE.name,
                              lambda m: modes.append(mode_from_msg(m).mode),
                              qos_profile(MODE.qos))
    probe.create_subscription(
        message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
        lambda m: plant.extend((m.header.stamp, s) for s in m.status if s.name == "pisc/plant"),
        qos_profile(DIAGNOSTICS.qos))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(probe)
    try:
        spin_until(executor, lambda: Mode.CATCH in modes or graph.poll() is not None, 120.0)
        if Mode.CATCH not in modes:
            if graph.poll() is None:
                graph.kill()
            out, err = graph.communicate()
            raise AssertionError(f"no catch seen in 120 s or before pisc_graph exited "
                                 f"({graph.returncode}): modes seen "
                                 f"{sorted(set(modes))[:5]}, {len(plant)} plant statuses; "
                                 f"pisc_graph said:\n{out[-1500:]}\n{err[-3000:]}")
        assert graph.poll() is None, graph.communicate()
        spin_until(executor, lambda: False, 3.0)  # balancing for 3 s
        pid = _child_pid(graph.pid, f"{stage}_node")
        assert pid is not None
        killed_ns = time.time_ns()
        os.kill(pid, signal.SIGKILL)

        _, err = graph.communicate(timeout=120)
        spin_until(executor, lambda: False, 0.5)  # the last diagnostics
        # the watchdog trip in force at the end: none resumed after it
        last = max((k for k, (_, s) in enumerate(plant)
                    if s.message.startswith("command watchdog")), default=None)
        assert last is not None and plant[last][1].level == ERROR, (
            [s.message for _, s in plant], err)
        stamp, error = plant[last]
        values = _values(error)
        zero_ns = stamp.sec * 1_000_000_000 + stamp.nanosec
        print(f"SIGKILL {stage}: 0 V from {(zero_ns - killed_ns) * 1e-6:.1f} ms after the kill "
              f"(plant clock), sample {values['sample']}, last answered "
              f"{values['last_answered_sample']}; named at sample "
              f"{values.get('named_at_sample')}, {values.get('behind')} behind, sure "
              f"{values.get('sure')}")
        assert values["applied_v"] == "0.0"
        # 0 V from the third sample after the last one answered: 15 ms at 5 ms
        assert int(values["sample"]) - int(values["last_answered_sample"]) == 3
        # the stage that died is named once it has fallen behind the one before it (on
        # this shared 2-core machine the chain also stalls past 3 periods now and then: a
        # trip of a stall in force at the kill is named by the stage that then died).
        # Or a stage before it that stopped with it: killed, the supervisor took the
        # estimator's /pisc/state with it, 8 samples and more, 1 of about 21 kills
        # (2026-12-03; cause not seen). pisc_graph names the process that died.
        chain = ["estimator", "supervisor", "current_loop"]
        named = values["silent"].removeprefix("/")
        assert named in chain[:chain.index(stage) + 1], error.message
        assert f"the {named} (/{named}) stopped" in error.message, error.message
        if named != stage:
            print(f"named the {named}, before the {stage} in the chain: {error.message}")
        assert graph.returncode == 2
        assert f"{stage}_node exited with status -9" in err, err
    finally:
        if graph.poll() is None:
            graph.kill()
            graph.communicate()
        probe.destroy_node()
        context.try_shutdown()


# -- a clean stop: SIGTERM inside a cycle finishes the cycle, and a run ends at its duration -

# plant_node, with SIGTERM arriving inside _publish_sample 40 samples after the probe has
# matched its joint and true states (after its joint_states, before its true state) and the rest of
# the cycle published 50 ms later, when the signal has been handled: the hostile tests' race, made
# certain. (On the wall clock the plant does not wait for subscribers: counted from its
# start, the 40 samples were over before discovery under the parallel suite's load.)
_SIGTERM_INSIDE_A_CYCLE = """
import os, signal, sys, time
from pisc_plant import plant_node
publish_sample = plant_node.PlantNode._publish_sample
matched = []
def cut(self):
    if not matched and min(self._joint_pub.get_subscription_count(),
                           self._true_pub.get_subscription_count()) > 0:
        matched.append(self._sim.index)
    if matched and self._sim.index == matched[0] + 40:
        publish = self._joint_pub.publish
        def then_sigterm(msg):
            publish(msg)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        self._joint_pub.publish = then_sigterm
    elif matched and self._sim.index == matched[0] + 41:
        self._joint_pub.publish = type(self._joint_pub).publish.__get__(self._joint_pub)
    publish_sample(self)
plant_node.PlantNode._publish_sample = cut
sys.exit(plant_node.main())
"""


def test_sigterm_inside_a_cycle_finishes_the_cycle_and_stops_cleanly(ros_context, domain_id):
    """Found by a hostile test: SIGTERM inside _publish_sample made the rest of the cycle
    fail ("Failed to publish: publisher's context is invalid", a FATAL log, exit 0): the
    bag lacked the last sample's true state. Now the plant finishes the cycle and stops
    before the next."""
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    probe = rclpy.node.Node("stop_probe", context=ros_context)
    seen: dict[str, list[int]] = {JOINT_STATES.name: [], SIM_STATE.name: []}
    for topic in (JOINT_STATES, SIM_STATE):
        probe.create_subscription(
            message_class(topic.type), topic.name,
            lambda m, name=topic.name: seen[name].append(stamp_from_msg(m.header.stamp)),
            qos_profile(topic.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(probe)
    plant = subprocess.Popen(
        [sys.executable, "-c", _SIGTERM_INSIDE_A_CYCLE, "--ros-args", "-p",
         "simulation.clock:=wall"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        assert spin_until(executor, lambda: plant.poll() is not None, 60.0)
        spin_until(executor, lambda: False, 0.3)
        _, err = plant.communicate(timeout=20)
    finally:
        if plant.poll() is None:
            plant.kill()
        probe.destroy_node()
    assert plant.returncode == 0, err
    assert "Exception" not in err and "FATAL" not in err, err
    joints, true = seen[JOINT_STATES.name], seen[SIM_STATE.name]
    assert len(joints) > 10, (len(joints), err)
    # the cycle the signal cut is whole, and it is the last one
    assert joints[-1] == true[-1], (joints[-3:], true[-3:])
    assert set(joints[-30:]) <= set(true)


def test_a_run_in_separate_processes_ends_at_its_duration_exactly(tmp_path, domain_id):
    """Found by a hostile test: `--processes` runs went on 1-4 cycles past --duration (the
    plant ran on until its SIGTERM). The plant now stops at the duration itself: 1 s at 5
    ms is the 201 samples 0 .. 1 s, each answered, and no sample after them."""
    from pisc_bag.bag import read_bag
    from pisc_bringup.graph import RunOptions, run_graph

    bag = tmp_path / "bag"
    result = run_graph(RunOptions(duration_s=1.0, processes=True, bag_dir=bag,
                                  domain_id=domain_id, overrides={"initial.x_m": 0.05}))
    stamps = {topic.name: {stamp_from_msg(m.message.header.stamp)
                           for m in read_bag(bag, [topic.name])}
              for topic in (JOINT_STATES, SIM_STATE, VOLTAGE)}
    assert result.summary.cycles == 201, result.summary.format()
    assert len(stamps[VOLTAGE.name]) == 201
    assert stamps[JOINT_STATES.name] == stamps[SIM_STATE.name] == stamps[VOLTAGE.name]
    assert max(stamps[VOLTAGE.name]) - min(stamps[VOLTAGE.name]) == 1_000_000_000
    assert result.summary.state_source == "true"


def test_another_subscriber_on_the_domain_does_not_pass_for_the_recorder(tmp_path, domain_id):
    """Found by a hostile test: any subscriber of the graph's topics on the same ROS domain
    (a `ros2 topic echo`) fooled the recorder readiness check, and the run then failed with
    a FileNotFoundError traceback on the bag's pisc_params.yaml. The run now waits for its
    own recorder, by node name."""
    from pisc_bringup.graph import RunOptions, run_graph
    from pisc_msgs_py.topics import GRAPH_TOPICS

    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    echo = rclpy.node.Node("echo", context=context)
    for topic in GRAPH_TOPICS:
        echo.create_subscription(message_class(topic.type), topic.name, lambda m: None,
                                 qos_profile(topic.qos))
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(echo)
    try:
        executor.spin_once(timeout_sec=0.5)  # discovered before the run starts
        bag = tmp_path / "bag"
        result = run_graph(RunOptions(duration_s=0.5, bag_dir=bag, domain_id=domain_id))
        assert result.summary.cycles == 101, result.summary.format()
        assert (bag / "pisc_params.yaml").is_file()
    finally:
        echo.destroy_node()
        rclpy.try_shutdown(context=context)


def test_an_experiment_run_exits_0_without_a_fault_and_says_so(tmp_path, domain_id, capfd):
    """An identification run has nothing to catch: it reports the experiment, not a
    swing-up's verdict (once NOT CAUGHT with exit 1, then NOT CAUGHT with exit 0), and
    exits 0 when the run did not fault."""
    status = main(["--scene", "excitation", "--duration", "1", "--bag", str(tmp_path / "bag"),
                   "--domain-id", str(domain_id)])
    out = capfd.readouterr().out
    assert status == 0, out
    assert "experiment             excitation: completed without a fault; cart within " in out
    assert "CAUGHT" not in out and "result " not in out

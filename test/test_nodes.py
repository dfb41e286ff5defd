"""Nodes without launch files: refusing bad parameters, answering one cycle, live changes."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
import rclpy.node
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.time import Time

from conftest import spin_until
from pisc_control.current_loop_node import CurrentLoopNode
from pisc_control.estimator_node import EstimatorNode
from pisc_control.supervisor_node import SupervisorNode
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.node_params import PISC_SECTIONS, StartError, parse_ros_arguments
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.convert import (
    cart_force_to_cdr,
    joint_sample_to_cdr,
    joint_sample_to_msg,
    mode_to_msg,
    motor_sample_from_msg,
    motor_sample_to_msg,
    stamp_from_msg,
    state_to_cdr,
)
from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    DIAGNOSTICS,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
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
)
from pisc_plant.plant_node import PlantNode

pytestmark = pytest.mark.integration

NODES = {"plant": PlantNode, "estimator": EstimatorNode, "supervisor": SupervisorNode,
         "current_loop": CurrentLoopNode}


@pytest.mark.parametrize("node,overrides,message", [
    ("plant", {"rig.cart_mass_kg": -0.4735}, r"rig.cart_mass_kg = -0.4735 must be positive"),
    ("supervisor", {"rig.pendulum_mass_kg": 0.0}, r"rig.pendulum_mass_kg = 0.0 must be positive"),
    ("supervisor", {"swing_up.k_v": 0.05}, r"swing_up.k_v / swing_up.k_e .* \(3.29\)"),
    ("supervisor", {"rig.gravity_mps2": 0.0}, r"not controllable .* rig.gravity_mps2"),
    ("supervisor", {"catch.poles": [-1.0, -2.0, 0.5, -3.0]}, r"catch.poles .* negative real"),
    ("estimator", {"loop.period_s": math.nan}, r"loop.period_s = nan must be finite"),
    ("current_loop", {"current_loop.k_ii": math.inf}, r"current_loop.k_ii = inf must be finite"),
    ("current_loop", {"motor.wheel_radius_m": -0.032}, r"motor.wheel_radius_m .* positive"),
    ("plant", {"integrator.method": "rk4", "integrator.substeps": 2},
     r"integrator.substeps = 2 is too few for rk4"),
    ("estimator", {"estimator.velocity_filter_hz": "fast"}, r"expected a number, got 'fast'"),
    ("supervisor", {"swing_up.k_vv": 0.1}, r"swing_up.k_vv: unknown parameter"),
    ("plant", {"simulation.clock_every": 0},
     r"simulation.clock_every = 0 must lie in \[1, 1000\]"),
    ("estimator", {"start.await_subscribers": "pisc/state=2"},
     r"start.await_subscribers = 'pisc/state=2' must list TOPIC=N \(an absolute topic "
     r"name, a count >= 0\): 'pisc/state=2' is not"),
    ("current_loop", {"start.await_subscribers": "/pisc/motor/voltage=1, /pisc/motor/voltage=2"},
     r"start.await_subscribers = .* names /pisc/motor/voltage twice"),
    ("supervisor", {"start.await_subscribers": "/pisc/state=1"},
     r"start.await_subscribers: /pisc/state is not published by node 'supervisor' \(it "
     r"publishes /diagnostics, /parameter_events, /pisc/cart_force, /pisc/mode, "
     r"/pisc/pendulum_estimate\)"),
    ("plant", {"start.await_timeout_s": 0.0},
     r"start.await_timeout_s = 0.0 must lie in \[0.01, 600"),
    ("plant", {"friction.pivot_viscous_nms": 4e-5},
     r"friction.pivot_viscous_nms = 4e-05 is not used: models.friction is 'none'"),
])
def test_node_refuses_to_start_on_an_invalid_parameter(ros_context, node, overrides, message):
    params = [Parameter(k, value=v) for k, v in overrides.items()]
    with pytest.raises(ConfigError, match=message):
        NODES[node](context=ros_context, parameter_overrides=params)


def test_entry_point_refuses_and_says_why(env_for_domain, tmp_path):
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_control.supervisor_node", "--ros-args",
         "-p", "swing_up.k_e:=20.0"],
        env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert "refusing to start: invalid parameter: swing_up.k_v / swing_up.k_e" in completed.stderr
    assert "(3.29)" in completed.stderr


def test_a_node_subscribes_once_its_publishers_have_matched_the_readers_it_awaits(
        ros_context, monkeypatch):
    """start.await_subscribers (pisc_graph gives it to node processes): the estimator
    creates no subscription before /pisc/state has matched the reader it was told of, so
    nothing it answers is lost to a reader that matches it late."""
    counts_at_subscribing = []
    create = rclpy.node.Node.create_subscription

    def create_subscription(self, *args, **kwargs):
        counts_at_subscribing.append(self._state_pub.get_subscription_count())
        return create(self, *args, **kwargs)

    monkeypatch.setattr(EstimatorNode, "create_subscription", create_subscription)
    made = []
    starting = threading.Thread(target=lambda: made.append(EstimatorNode(
        context=ros_context, parameter_overrides=[
            Parameter("start.await_subscribers", value="/pisc/state=1")])))
    starting.start()
    probe = rclpy.node.Node("probe", context=ros_context)
    try:
        starting.join(1.0)  # no reader of /pisc/state exists: it cannot have started
        assert starting.is_alive() and counts_at_subscribing == []
        probe.create_subscription(message_class(STATE.type), STATE.name, lambda msg: None,
                                  qos_profile(STATE.qos))
        starting.join(30.0)
        assert not starting.is_alive() and made
        assert counts_at_subscribing == [1]  # /pisc/joint_states, after the match
    finally:
        starting.join(30.0)
        for node in made:
            node.destroy_node()
        probe.destroy_node()


def test_a_node_whose_readers_do_not_come_does_not_start_and_names_them(ros_context,
                                                                          env_for_domain):
    with pytest.raises(StartError, match=(
            r"^node 'current_loop': within 0.2 s \(start.await_timeout_s\) "
            r"/pisc/motor/voltage matched 0 of the 2 subscribers of "
            r"start.await_subscribers$")):
        CurrentLoopNode(context=ros_context, parameter_overrides=[
            Parameter("start.await_subscribers",
                      value="/pisc/motor/current_setpoint=0,/pisc/motor/voltage=2"),
            Parameter("start.await_timeout_s", value=0.2)])
    # its entry point: exit status 1 (not started), said on standard error
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_control.estimator_node", "--ros-args",
         "-p", "start.await_subscribers:=/pisc/state=1", "-p", "start.await_timeout_s:=0.5"],
        env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 1
    assert ("not started: node 'estimator': within 0.5 s (start.await_timeout_s) "
            "/pisc/state matched 0 of the 1 subscribers") in completed.stderr


def test_the_lockstep_plant_waits_for_every_clock_subscriber_it_was_told_of(ros_context):
    """A runner holds the plant back by the count of /clock subscribers it asks for."""
    plant = PlantNode(context=ros_context, parameter_overrides=[
        Parameter("simulation.clock", value="lockstep"),
        Parameter("simulation.min_clock_subscribers", value=2),
        Parameter("simulation.start_settle_s", value=0.05)])
    probe = rclpy.node.Node("probe", context=ros_context)
    samples = []
    probe.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name,
                              samples.append, qos_profile(JOINT_STATES.qos))
    probe.create_subscription(message_class(MOTOR_CURRENT.type), MOTOR_CURRENT.name,
                              lambda msg: None, qos_profile(MOTOR_CURRENT.qos))
    probe.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name, qos_profile(VOLTAGE.qos))

    def clock_subscriber():
        probe.create_subscription(message_class(CLOCK.type), CLOCK.name, lambda msg: None,
                                  qos_profile(CLOCK.qos))

    clock_subscriber()
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(plant)
    executor.add_node(probe)
    try:
        # every other edge is there; one /clock subscriber of two: no sample
        assert not spin_until(executor, lambda: samples, 1.5)
        clock_subscriber()
        assert spin_until(executor, lambda: samples, 10.0)
    finally:
        plant.destroy_node()
        probe.destroy_node()


def test_the_wall_clock_plant_reads_the_node_clock_and_a_clock_override(ros_context):
    """The wall-clock plant stamps with its node's clock: the system's realtime clock
    (read without an rclpy Time), or /clock's time once ROS time overrides it."""
    plant = PlantNode(context=ros_context)
    try:
        before = time.time_ns()
        assert before <= plant._wall_ns() <= time.time_ns()
        clock = plant.get_clock()
        clock._set_ros_time_is_active(True)  # what use_sim_time's TimeSource does
        clock.set_ros_time_override(Time(seconds=12, nanoseconds=345))
        assert plant._wall_ns() == 12_000_000_345
    finally:
        plant.destroy_node()


def test_the_lockstep_plant_publishes_clock_with_every_clock_every_th_sample(ros_context):
    """/clock carries the stamps of samples 0, N, 2N, ... (simulation.clock_every = N),
    and the nodes on simulated time see it from the first sample on."""
    plant = PlantNode(context=ros_context, parameter_overrides=[
        Parameter("simulation.clock", value="lockstep"),
        Parameter("simulation.clock_every", value=3),
        Parameter("simulation.min_clock_subscribers", value=1),
        Parameter("simulation.command_node", value="probe"),
        Parameter("simulation.start_settle_s", value=0.05)])
    probe = rclpy.node.Node("probe", context=ros_context)
    samples: list[int] = []
    clocks: list[int] = []
    voltage = probe.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                     qos_profile(VOLTAGE.qos))

    def answer(msg) -> None:  # each sample answered with 0 V of its stamp: time goes on
        samples.append(stamp_from_msg(msg.header.stamp))
        voltage.publish(motor_sample_to_msg(MotorSample(samples[-1], 0.0)))

    probe.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name, answer,
                              qos_profile(JOINT_STATES.qos))
    probe.create_subscription(message_class(MOTOR_CURRENT.type), MOTOR_CURRENT.name,
                              lambda msg: None, qos_profile(MOTOR_CURRENT.qos))
    probe.create_subscription(message_class(CLOCK.type), CLOCK.name,
                              lambda msg: clocks.append(stamp_from_msg(msg.clock)),
                              qos_profile(CLOCK.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(plant)
    executor.add_node(probe)
    try:
        assert spin_until(executor, lambda: len(samples) >= 10, 20.0)
        spin_until(executor, lambda: len(clocks) >= 4, 2.0)
    finally:
        plant.destroy_node()
        probe.destroy_node()
    assert samples[:10] == [k * 5_000_000 for k in range(10)]
    assert clocks[:4] == [0, 15_000_000, 30_000_000, 45_000_000]


def test_newest_stamps_are_taken_when_read_and_wake_no_executor(ros_context):
    """The plant's and the driver's view of the chain (which stage stopped): the stamp
    of the newest message on each topic when read, a malformed one ignored, and no
    subscription an executor would call back for each message."""
    node = EstimatorNode(context=ros_context)  # any PiscNode
    callbacks = len(list(node.subscriptions))
    stamps = node.newest_stamps([("estimator", STATE), ("supervisor", CART_FORCE)])
    probe = rclpy.node.Node("probe", context=ros_context)
    state = probe.create_publisher(message_class(STATE.type), STATE.name,
                                   qos_profile(STATE.qos))
    force = probe.create_publisher(message_class(CART_FORCE.type), CART_FORCE.name,
                                   qos_profile(CART_FORCE.qos))
    seen: list[bytes] = []  # what the probe's own reader of the force got, raw
    probe.create_subscription(message_class(CART_FORCE.type), CART_FORCE.name, seen.append,
                              qos_profile(CART_FORCE.qos), raw=True)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(probe)
    try:
        assert len(list(node.subscriptions)) == callbacks
        assert spin_until(executor, lambda: state.get_subscription_count() >= 1
                          and force.get_subscription_count() >= 1, 10.0)
        assert stamps.read() == {}
        for k in (1, 2, 3):
            state.publish(state_to_cdr(StateEstimate(k * 5_000_000, 0.0, 0.0, 0.0, 0.0)))
        force.publish(cart_force_to_cdr(CartForce(5_000_000, 1.0)))
        assert spin_until(executor, lambda: stamps.read() == {
            "estimator": 15_000_000, "supervisor": 5_000_000}, 10.0), stamps.read()
        malformed = b"\x00\x01\x00\x00\x07"  # CDR, then no header
        force.publish(malformed)
        # delivered in this process (the probe's reader has it): the node's reader too
        assert spin_until(executor, lambda: seen[-1:] == [malformed], 10.0)
        assert stamps.read() == {"estimator": 15_000_000, "supervisor": 5_000_000}
    finally:
        probe.destroy_node()
        node.destroy_node()


def test_a_running_node_refuses_a_bad_change_and_takes_a_good_one(ros_context):
    node = SupervisorNode(context=ros_context)
    try:
        bad = node.set_parameters([Parameter("swing_up.k_e", value=50.0)])[0]
        assert not bad.successful and "(3.29)" in bad.reason
        assert node.config.config.swing_up.k_e == 8.1  # unchanged (no file: thesis defaults)
        good = node.set_parameters([Parameter("catch.poles", value=[-10.0, -8.0, -2.0, -1.5])])[0]
        assert good.successful
        assert node.config.config.catch.poles == (-10.0, -8.0, -2.0, -1.5)
    finally:
        node.destroy_node()


def test_controllers_answer_a_sample_with_a_voltage_of_the_same_stamp(ros_context):
    nodes = [EstimatorNode(context=ros_context), SupervisorNode(context=ros_context),
             CurrentLoopNode(context=ros_context)]
    probe = nodes[0].__class__.__mro__[-2]  # rclpy Node
    # in the plant's place: the controllers' inputs answer to the plant alone
    probe = probe("plant", context=ros_context)
    joints = probe.create_publisher(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                    qos_profile(JOINT_STATES.qos))
    current = probe.create_publisher(message_class(MOTOR_CURRENT.type), MOTOR_CURRENT.name,
                                     qos_profile(MOTOR_CURRENT.qos))
    answers = []
    probe.create_subscription(message_class(VOLTAGE.type), VOLTAGE.name,
                              lambda m: answers.append(motor_sample_from_msg(m)),
                              qos_profile(VOLTAGE.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    for n in [*nodes, probe]:
        executor.add_node(n)
    try:
        assert spin_until(executor, lambda: joints.get_subscription_count() >= 1
                          and current.get_subscription_count() >= 1
                          and nodes[2]._voltage_pub.get_subscription_count() >= 1, 10.0)
        assert spin_until(executor, lambda: nodes[1]._force_pub.get_subscription_count() >= 1
                          and nodes[0]._state_pub.get_subscription_count() >= 1, 10.0)
        for k, stamp in enumerate((5_000_000, 10_000_000)):
            joints.publish(joint_sample_to_msg(JointSample(stamp, 0.05, math.pi)))
            current.publish(motor_sample_to_msg(MotorSample(stamp, 0.0)))
            assert spin_until(executor, lambda k=k: len(answers) > k, 10.0)
        assert [a.stamp_ns for a in answers] == [5_000_000, 10_000_000]
        # the default start-up pulls the cart towards the middle of the track: negative force
        assert answers[0].value < 0.0
    finally:
        for n in [*nodes, probe]:
            n.destroy_node()


def _diagnostics_probe(ros_context, node, name: str):
    """A probe node named ``name`` (the node whose topics it publishes: the inputs answer
    to it alone) whose subscription gathers every status message on /diagnostics, and
    an executor spinning it with ``node``: (probe, the messages, executor)."""
    probe = rclpy.node.Node(name, context=ros_context)
    statuses: list[str] = []
    probe.create_subscription(message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
                              lambda m: statuses.extend(s.message for s in m.status),
                              qos_profile(DIAGNOSTICS.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (node, probe):
        executor.add_node(n)
    return probe, statuses, executor


def test_bytes_that_are_no_joint_state_are_refused_on_diagnostics_and_the_node_answers_on(
        ros_context):
    """The nodes read their cycle's topics raw: a sample whose bytes are no
    JointState is refused on /diagnostics, naming the topic and what is wrong, and the
    next good sample is answered (rclpy's own deserialisation raised in the executor)."""
    estimator = EstimatorNode(context=ros_context)
    probe, statuses, executor = _diagnostics_probe(ros_context, estimator, "plant")
    joints = probe.create_publisher(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                    qos_profile(JOINT_STATES.qos))
    states = []
    probe.create_subscription(message_class(STATE.type), STATE.name, states.append,
                              qos_profile(STATE.qos))
    try:
        assert spin_until(executor, lambda: joints.get_subscription_count() >= 1
                          and estimator._state_pub.get_subscription_count() >= 1
                          and estimator._diagnostics.get_subscription_count() >= 1, 10.0)
        good = joint_sample_to_cdr(JointSample(5_000_000, 0.05, math.pi))
        joints.publish(good[:30])  # ends before its two joint names
        assert spin_until(executor, lambda: any("rejected" in m for m in statuses), 10.0)
        assert [m for m in statuses if "rejected" in m] == [
            "rejected /pisc/joint_states: JointState: malformed CDR (2 joint names do not "
            "fit in the message)"]
        joints.publish(good)
        assert spin_until(executor, lambda: len(states) == 1, 10.0)
        assert tuple(states[0].position) == (0.05, math.pi)
    finally:
        for n in (estimator, probe):
            n.destroy_node()


def test_the_current_loop_takes_the_mode_as_a_value_and_refuses_an_unknown_one(ros_context):
    """A topic without a raw reader (/pisc/mode, a DiagnosticArray) hands the callback the
    converter's value too; a mode it does not know is refused on /diagnostics as parse
    says it, and a fault after it is taken."""
    loop = CurrentLoopNode(context=ros_context)
    probe, statuses, executor = _diagnostics_probe(ros_context, loop, "supervisor")
    modes = probe.create_publisher(message_class(MODE.type), MODE.name, qos_profile(MODE.qos))
    try:
        assert spin_until(executor, lambda: modes.get_subscription_count() >= 1
                          and loop._diagnostics.get_subscription_count() >= 1, 10.0)
        unknown = mode_to_msg(ModeReport(5_000_000, Mode.CATCH))
        unknown.status[0].message = "dancing"
        modes.publish(unknown)
        assert spin_until(executor, lambda: any("rejected" in m for m in statuses), 10.0)
        assert [m for m in statuses if "rejected" in m] == [
            "rejected mode: mode: unknown mode 'dancing'"]
        modes.publish(mode_to_msg(ModeReport(10_000_000, Mode.FAULT, "x below x_min")))
        assert spin_until(executor, lambda: loop._fault == "x below x_min", 10.0)
    finally:
        for n in (loop, probe):
            n.destroy_node()


# -- names no node reads, command lines rcl cannot read, array values -----------

def _node_from_command_line(cls, domain_id, ros_args):
    """Construct ``cls`` as its entry point would with ``--ros-args *ros_args``."""
    args = ["node", "--ros-args", *ros_args]
    context = Context()
    rclpy.init(args=args, context=context, domain_id=domain_id)
    try:
        node = cls(context=context, command_line=parse_ros_arguments(args))
        node.destroy_node()
    finally:
        context.try_shutdown()


@pytest.mark.parametrize("node,ros_args,message", [
    ("plant", ["-p", "nosuch.x:=1"],
     r"^nosuch.x \(-p nosuch.x:=1\): not a parameter of node 'plant' \(it reads rig, "),
    ("plant", ["-p", "rigg.cart_mass_kg:=-1"],
     r"^rigg.cart_mass_kg .*: not a parameter of node 'plant'; did you mean rig.cart_mass_kg\?"),
    ("supervisor", ["-p", "swingup.k_v:=0.05"],
     r"^swingup.k_v .*'supervisor'; did you mean swing_up.k_v\?"),
    # a section another node reads, aimed at this one: still refused
    ("estimator", ["-p", "swing_up.k_v:=0.05"],
     r"^swing_up.k_v .*not a parameter of node 'estimator' \(it reads loop, estimator, start\)"),
    # -p NODE:NAME:=VALUE aims at that node only
    ("current_loop", ["-p", "current_loop:loop.period:=0.005", "-p", "plant:nosuch.x:=1"],
     r"^loop.period \(-p current_loop:loop.period:=0.005\): not a parameter of node "
     r"'current_loop'; did you mean loop.period_s\?"),
])
def test_a_name_aimed_at_a_node_that_it_does_not_declare_is_refused(domain_id, node, ros_args,
                                                                     message):
    with pytest.raises(ConfigError, match=message):
        _node_from_command_line(NODES[node], domain_id, ros_args)


def test_a_shared_file_may_hold_other_nodes_sections_but_no_unknown_section(domain_id,
                                                                            tmp_path):
    shipped = str(Path(__file__).resolve().parent.parent
                  / "src/pisc_sim/config/default.yaml")
    for cls in NODES.values():  # every node reads its sections of the one file
        _node_from_command_line(cls, domain_id, ["--params-file", shipped])
    typo = tmp_path / "typo.yaml"
    typo.write_text("/**:\n  ros__parameters:\n    swingup:\n      k_v: 0.05\n")
    for cls in NODES.values():  # and every node refuses a section no node reads
        with pytest.raises(ConfigError, match=r"^swingup.k_v: unknown parameter; did you mean "
                           r"swing_up.k_v\? .*'swingup' is no section of a PISC node"):
            _node_from_command_line(cls, domain_id, ["--params-file", str(typo)])


def test_the_known_sections_are_those_the_nodes_read():
    from pisc_runs.markers_node import SECTIONS as MARKERS_SECTIONS
    from pisc_control.supervisor_node import SECTIONS as SUPERVISOR_SECTIONS
    from pisc_driver.driver_node import SECTIONS as DRIVER_SECTIONS
    from pisc_plant.plant_node import SECTIONS as PLANT_SECTIONS

    read = {*PLANT_SECTIONS, *SUPERVISOR_SECTIONS, *DRIVER_SECTIONS, *MARKERS_SECTIONS,
            "loop", "estimator", "motor", "current_loop", "start"}  # start: every PiscNode
    assert PISC_SECTIONS == read


@pytest.mark.parametrize("ros_args,message", [
    (["--params-file", "/nonexistent.yaml"],
     "refusing to start: --params-file /nonexistent.yaml: cannot read it (No such file or "
     "directory)"),
    (["--params-file", "BROKEN"],
     "refusing to start: --params-file BROKEN: not valid YAML (line 4, column 1: "),
    (["-p", "rig.cart_mass_kg"],
     "refusing to start: -p rig.cart_mass_kg: expected NAME:=VALUE"),
    (["-p", "rig.cart_mass_kg:=[1,"],
     "refusing to start: -p rig.cart_mass_kg:=[1,: the value is not valid YAML"),
    (["-p", "nosuch.x:=1"],
     "refusing to start: invalid parameter: nosuch.x (-p nosuch.x:=1): not a parameter of "
     "node 'plant'"),
])
def test_a_command_line_rcl_cannot_read_is_one_line_and_no_traceback(env_for_domain, tmp_path,
                                                                     ros_args, message):
    broken = tmp_path / "broken.yaml"
    broken.write_text("/**:\n  ros__parameters:\n    rig: {cart_mass_kg: [1,\n")
    ros_args = [str(broken) if a == "BROKEN" else a for a in ros_args]
    message = message.replace("BROKEN", str(broken))
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_plant.plant_node", "--ros-args", *ros_args],
        env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert completed.stderr.startswith(message), completed.stderr
    assert completed.stderr.count("\n") == 1 and "Traceback" not in completed.stderr


def test_an_array_parameter_changes_through_the_set_parameters_service(ros_context):
    """ros2 param set and rqt send a DOUBLE_ARRAY, which rclpy hands over as array('d')."""
    from rcl_interfaces.srv import SetParameters

    node = SupervisorNode(context=ros_context)
    client_node = rclpy.node.Node("client", context=ros_context)
    client = client_node.create_client(SetParameters, "/supervisor/set_parameters")
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(client_node)
    try:
        assert spin_until(executor, client.service_is_ready, 10.0)
        results = []
        for poles in ([-15.0, -11.0, -3.0, -2.4], [-15.0, -11.0, -3.0, 2.4]):
            request = SetParameters.Request(
                parameters=[Parameter("catch.poles", value=poles).to_parameter_msg()])
            future = client.call_async(request)
            assert spin_until(executor, future.done, 10.0)
            results.append(future.result().results[0])
        assert results[0].successful, results[0].reason
        assert node.config.config.catch.poles == (-15.0, -11.0, -3.0, -2.4)
        assert not results[1].successful and "negative real" in results[1].reason
        assert node.config.config.catch.poles == (-15.0, -11.0, -3.0, -2.4)  # unchanged
    finally:
        node.destroy_node()
        client_node.destroy_node()


_LEAVES_REALTIME = """
import os, threading
import rclpy
from pisc_control.estimator_node import EstimatorNode
from pisc_msgs_py.base_node import run_node
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
seen = {}

class Probe(EstimatorNode):
    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.create_timer(0.3, lambda: rclpy.try_shutdown())
        self.other = threading.Thread(target=threading.Event().wait, args=(30.0,),
                                      daemon=True)
        self.other.start()  # started at SCHED_FIFO: keeps it

    def destroy_node(self):
        seen["main"] = os.sched_getscheduler(0)
        seen["other"] = os.sched_getscheduler(self.other.native_id)
        super().destroy_node()

status = run_node(Probe, [])
print(status, seen["main"], seen["other"])
"""


def test_a_stopping_node_gives_up_sched_fifo_before_it_destroys_its_node(env_for_domain):
    """run_node (and pisc_graph) leave SCHED_FIFO in the thread that destroys the node:
    Fast DDS's wait there takes no turns and starved the threads it waits for
    (base_node.leave_realtime). Other threads keep the policy."""
    from pisc_bench.soak_options import check_realtime

    refused = check_realtime(10)  # this container allows it; a machine without
    if refused is not None:  # CAP_SYS_NICE has no SCHED_FIFO to leave
        pytest.skip(f"SCHED_FIFO is not allowed here ({refused}); it needs CAP_SYS_NICE")
    done = subprocess.run([sys.executable, "-c", _LEAVES_REALTIME], env=env_for_domain,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["0", str(os.SCHED_OTHER), str(os.SCHED_FIFO)], done.stdout

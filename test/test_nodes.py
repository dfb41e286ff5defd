"""Nodes without launch files: refusing bad parameters, answering one cycle, live changes."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
import rclpy.node
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from conftest import spin_until
from pisc_control.current_loop_node import CurrentLoopNode
from pisc_control.estimator_node import EstimatorNode
from pisc_control.supervisor_node import SupervisorNode
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.convert import (
    joint_sample_to_msg,
    motor_sample_from_msg,
    motor_sample_to_msg,
)
from pisc_msgs_py.topics import CLOCK, JOINT_STATES, MOTOR_CURRENT, VOLTAGE
from pisc_msgs_py.types import JointSample, MotorSample
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
    probe = probe("probe", context=ros_context)
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

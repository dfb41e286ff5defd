"""The names a node refuses and the --ros-args it reads, without rclpy (node_params)."""

from dataclasses import dataclass

import pytest

from pisc_msgs_py.config import ConfigError, in_range, param
from pisc_msgs_py.node_params import (
    Override,
    StartParams,
    check_overrides,
    parse_ros_arguments,
)

DECLARED = ["start.await_subscribers", "start.await_timeout_s", "start.publishers",
            "loop.period_s"]


@dataclass(frozen=True)
class Loop:
    period_s: float = param(0.005, "the control period", "s", in_range(1e-4, 1.0))


def _loop_section():
    return {"loop": Loop, "start": StartParams}


def test_parse_ros_arguments_reads_each_p_with_its_target_and_origin():
    got = parse_ros_arguments(["node", "--ros-args", "-p", "loop.period_s:=0.005", "-r",
                               "a:=b", "-p", "estimator:loop.period_s:=0.01", "--", "-p",
                               "ignored:=1"])
    assert got == (Override(None, "loop.period_s", "-p loop.period_s:=0.005"),
                   Override("estimator", "loop.period_s", "-p estimator:loop.period_s:=0.01"))


@pytest.mark.parametrize("args, message", [
    (["--ros-args", "-p"], "-p: expected NAME:=VALUE after it"),
    (["--ros-args", "-p", "loop.period_s=1"], "-p loop.period_s=1: expected NAME:=VALUE"),
    (["--ros-args", "--params-file", "/nonexistent.yaml"],
     "--params-file /nonexistent.yaml: cannot read it"),
])
def test_parse_ros_arguments_refuses_what_rcl_could_not_read(args, message):
    with pytest.raises(ConfigError, match=message):
        parse_ros_arguments(args)


def test_a_name_aimed_at_the_node_must_be_declared_and_the_closest_is_named():
    wrong = Override(None, "loop.period", "-p loop.period:=0.005")
    with pytest.raises(ConfigError, match=(
            r"loop.period \(-p loop.period:=0.005\): not a parameter of node 'estimator'; "
            r"did you mean loop.period_s\? \(it reads loop, start\)")):
        check_overrides("estimator", "/estimator", DECLARED, _loop_section(), [wrong], {})


def test_a_name_aimed_at_another_node_or_shared_is_left_to_that_node():
    other = Override("supervisor", "swing_up.gain", "-p supervisor:swing_up.gain:=1")
    shared = Override("/**", "swing_up.gain", "--params-file f.yaml")
    check_overrides("estimator", "/estimator", DECLARED, _loop_section(), [other, shared],
                    {"swing_up.gain": 1.0})


def test_a_shared_name_in_no_pisc_section_is_refused_with_the_section_it_resembles():
    with pytest.raises(ConfigError, match=(
            r"swingup.gain: unknown parameter; did you mean swing_up.gain\? \(not a parameter "
            r"of node 'estimator', and 'swingup' is no section of a PISC node\)")):
        check_overrides("estimator", "/estimator", DECLARED, _loop_section(), [],
                        {"swingup.gain": 1.0})


def test_a_shared_name_in_one_of_the_nodes_sections_must_be_one_of_its_fields():
    with pytest.raises(ConfigError, match="loop.period"):
        check_overrides("estimator", "/estimator", DECLARED, _loop_section(), [],
                        {"loop.period": 0.005})

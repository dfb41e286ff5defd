"""Every topic of the PISC graph: name, message type, QoS and meaning, in one place.

Only standard messages from ROS 2 common_interfaces are used, so a recorded bag opens in
any ROS tool. The plant simulator and the serial driver publish and subscribe exactly
the same topics, so either is a drop-in for the other.

One control cycle, all messages stamped with the stamp of the sample that started it::

    plant | driver --JOINT_STATES, MOTOR_CURRENT-->  (sample k, stamp t_k)
    estimator      --STATE------------------------>  (t_k)
    supervisor     --CART_FORCE, MODE (on change)->  (t_k)
    current loop   --CURRENT_SETPOINT, VOLTAGE---->  (t_k)
    plant | driver applies VOLTAGE until sample k+1

There is no stamped scalar in common_interfaces, and ROS's policy is to carry a quantity
in the message that names its meaning. The armature quantities therefore travel as a
``sensor_msgs/JointState`` of the single joint ``motor`` with the value in ``effort``,
the way ros2_control's joint_state_broadcaster maps a motor's current interface onto
``effort``; the unit is fixed per topic (A or V). The supervisor's mode travels as a
``diagnostic_msgs/DiagnosticArray`` with one status (a stamped, named state with a
level and a reason), published when it changes and latched for late joiners.

QoS is described here as plain data (the recorder stores it in ``metadata.yaml``);
nodes turn it into rclpy profiles in :mod:`pisc_msgs_py.base_node`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from pisc_msgs_py.config import ConfigError

__all__ = [
    "CART_FORCE",
    "CLOCK",
    "CONTROL_QOS",
    "CURRENT_SETPOINT",
    "DIAGNOSTICS",
    "FOREIGN",
    "GRAPH_TOPICS",
    "graph_topics_named",
    "JOINT_NAMES",
    "JOINT_STATES",
    "LATCHED_QOS",
    "MARKERS",
    "MODE",
    "MOTOR_CURRENT",
    "MOTOR_JOINT",
    "OPTIONAL_TOPICS",
    "PENDULUM_ESTIMATE",
    "PENDULUM_ESTIMATE_JOINTS",
    "QosSpec",
    "RECORDER_PROGRESS",
    "SIM_STATE",
    "STATE",
    "Topic",
    "VOLTAGE",
    "VOLTAGE_SENT",
]


@dataclass(frozen=True)
class QosSpec:
    """A QoS profile as data: history depth, reliability and durability."""

    depth: int
    reliable: bool = True
    transient_local: bool = False


@dataclass(frozen=True)
class Topic:
    name: str
    type: str  # ROS 2 type name, e.g. 'sensor_msgs/msg/JointState'
    qos: QosSpec
    description: str


# Every sample matters (lockstep simulation waits for each answer, the recorder must
# lose nothing): reliable, with a history deep enough to ride out a slow subscriber.
CONTROL_QOS = QosSpec(depth=100, reliable=True, transient_local=False)
# The last value is what counts and late joiners need it.
LATCHED_QOS = QosSpec(depth=1, reliable=True, transient_local=True)

#: Joint order of every JointState on the mechanical topics.
JOINT_NAMES = ("cart", "pendulum")
#: The single joint of the armature topics.
MOTOR_JOINT = "motor"

JOINT_STATES = Topic(
    "/pisc/joint_states", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "measured cart position [m] and pendulum angle [rad] (position), joints cart, pendulum",
)
MOTOR_CURRENT = Topic(
    "/pisc/motor/current", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "measured armature current [A] (effort of joint motor)",
)
STATE = Topic(
    "/pisc/state", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "estimated state: positions as measured, velocities by differences (4.7), (4.9)",
)
CART_FORCE = Topic(
    "/pisc/cart_force", "geometry_msgs/msg/WrenchStamped", CONTROL_QOS,
    "force the supervisor asks of the cart [N] (force.x, frame cart)",
)
MODE = Topic(
    "/pisc/mode", "diagnostic_msgs/msg/DiagnosticArray", LATCHED_QOS,
    "supervisor mode (status message: swing_up, catch or fault) and why, on change",
)
CURRENT_SETPOINT = Topic(
    "/pisc/motor/current_setpoint", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "desired armature current i_d [A] (effort of joint motor), (4.2) saturated",
)
VOLTAGE = Topic(
    "/pisc/motor/voltage", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "armature voltage command u [V] (effort of joint motor), PI output (3.47)",
)
# What went out on the wire, for analysis and identification: the controllers' voltage is
# what they asked for; the driver may send 0 V instead (a stale command, a silent device, a
# second publisher) or repeat the last byte for a frame left unanswered, and only it knows
# when the byte left. Published right after each write, so its publish time, which a bag
# keeps, is the write time.
VOLTAGE_SENT = Topic(
    "/pisc/motor/voltage_sent", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "driver only: the voltage of each command byte written to the rig [V] (effort of joint "
    "motor, as the byte encodes it), published as it is written; stamp: the sample it "
    "answers, or for a byte of the driver's own the newest sample; frame_id: answer, hold "
    "or zero",
)
#: The joints of the supervisor's online estimates (PENDULUM_ESTIMATE).
PENDULUM_ESTIMATE_JOINTS = ("omega0_sq", "pivot_loss")
PENDULUM_ESTIMATE = Topic(
    "/pisc/pendulum_estimate", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "supervisor with adaptation.enabled: what it believes of the pendulum, joints omega0_sq "
    "(omega_0^2 = m g l / J [1/s^2]) and pivot_loss (b / J [1/s]), the estimate in position "
    "and its standard deviation in velocity; in every cycle the estimate changed",
)
SIM_STATE = Topic(
    "/pisc/sim/true_state", "sensor_msgs/msg/JointState", CONTROL_QOS,
    "simulator only: true state (cart, pendulum, motor: position, velocity; motor effort "
    "= current [A]) at each sample, for analysis",
)
DIAGNOSTICS = Topic(
    "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", QosSpec(depth=100),
    "health of every node; faults say why",
)
# Reliable, so that a recorder loses no tick (a best-effort /clock lost ticks under load);
# the best-effort subscriptions of use_sim_time clocks still match a reliable publisher.
CLOCK = Topic(
    "/clock", "rosgraph_msgs/msg/Clock", QosSpec(depth=100, reliable=True),
    "simulated time, published by the plant in lockstep mode",
)

#: The topics a run records by default.
GRAPH_TOPICS = (
    JOINT_STATES, MOTOR_CURRENT, STATE, CART_FORCE, MODE, CURRENT_SETPOINT, VOLTAGE,
    VOLTAGE_SENT, PENDULUM_ESTIMATE, SIM_STATE, DIAGNOSTICS, CLOCK,
)
# The rig drawn for RViz and Foxglove (pisc_bringup markers_node), on request only
# (``pisc_graph --markers``). Each array holds the whole picture; the last few are kept
# for a viewer that joins late, or after the run has stopped.
MARKERS = Topic(
    "/pisc/markers", "visualization_msgs/msg/MarkerArray",
    QosSpec(depth=10, reliable=True, transient_local=True),
    "the rig as markers (track, end stops, safe range, cart, pendulum coloured by mode, "
    "force arrow, mode and time), frame world, at most markers.rate_hz per second of stamps",
)
# The run's recorder says how far it has written (``pisc_record --progress``): the stamp
# of the newest sample whose every message is in the bag. The lockstep plant waits on it
# when it would run more than ``simulation.recorder_lag_samples`` ahead (a publisher
# keeps only CONTROL_QOS's 100 messages for a recorder that trails). Latched: a plant that
# matches late gets the last word. Not a graph topic: it says nothing about the rig and is
# not recorded.
RECORDER_PROGRESS = Topic(
    "/pisc/recorder/progress", "rosgraph_msgs/msg/Clock", LATCHED_QOS,
    "the run's recorder: stamp of the newest sample it has written whole to the bag",
)
# The run's recorder marks in its bag the topics on which a publisher other than the
# graph's was matched while it recorded (pisc_record --expect): one status when such a
# publisher appears (ERROR, naming the topic and the publishers) and one when the topic
# has only the graph's again (OK), at the log times it saw it. Written into the bag, not
# published; the summary and replay refuse to call such a run CAUGHT or REPRODUCED.
FOREIGN = Topic(
    "/pisc/recorder/foreign", "diagnostic_msgs/msg/DiagnosticArray", QosSpec(depth=100),
    "the recorder: another publisher than the graph's on a recorded topic, and its end "
    "(status values: topic, publishers, contested messages); in the bag only",
)
#: Topics of nodes the graph runs only on request: recordable, not recorded by default.
OPTIONAL_TOPICS = (MARKERS,)


def graph_topics_named(names: Iterable[str]) -> tuple[Topic, ...]:
    """The graph's topics of these names, in the graph's order, then the optional ones
    (:data:`OPTIONAL_TOPICS`); :class:`ConfigError` for a name that is not one of them (it
    names the graph's topics)."""
    known = {t.name: t for t in (*GRAPH_TOPICS, *OPTIONAL_TOPICS)}
    names = list(names)
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(f"{unknown[0]} is not a topic of the graph (topics: "
                          f"{', '.join(t.name for t in GRAPH_TOPICS)})")
    return tuple(t for t in (*GRAPH_TOPICS, *OPTIONAL_TOPICS) if t.name in names)

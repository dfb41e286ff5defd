"""The rig as markers: the geometry against the state, the throttle on
the samples' stamps, the node over ROS topics, and a lockstep graph run's bag."""

from __future__ import annotations

import math
import subprocess
import sys
from fractions import Fraction

import numpy as np
import pytest

from pisc_runs.rig_drawing import MODE_COLOURS
from pisc_runs.markers import (
    MARKER_IDS,
    MarkerFeed,
    MarkerScene,
    MarkersParams,
    RigFrame,
    rig_markers,
)
from pisc_control.supervisor import SafetyParams
from pisc_msgs_py.config import ConfigError, from_flat
from pisc_msgs_py.types import Mode
from pisc_model.params import RigParams, TrackParams

L = 0.0865  # Table 6.1's l (RigParams' default); the drawn rod is 2 l long
SCENE = MarkerScene.of(RigParams(), TrackParams(), SafetyParams())


def frame(x=0.0, theta=0.0, mode=Mode.SWING_UP, force=0.0, stamp=0, true_state=True):
    return RigFrame(stamp, x, theta, mode, force, true_state, stamp * 1e-9)


def by_id(markers):
    return {(m.ns, m.id): m for m in markers}


@pytest.mark.parametrize("x,theta", [(0.05, 0.3), (-0.12, -1.0), (0.0, math.pi),
                                     (0.1, math.pi / 2)])
def test_the_cart_and_the_pendulum_are_where_the_state_puts_them(x, theta):
    m = by_id(rig_markers(frame(x, theta), SCENE))
    cart = m["cart", 0]
    assert cart.kind == "cube" and cart.position == (x, 0.0, 0.0)
    rod = m["pendulum", 0]
    assert rod.kind == "line_strip" and len(rod.points) == 2
    (px, py, pz), (ex, ey, ez) = rod.points
    assert (px, pz) == (x, 0.0) and py == ey  # the pivot on the cart, in one x-z plane
    # SPEC section 4: theta = 0 upright, positive towards +x; the tip of the 2 l rod
    assert ex == pytest.approx(x + 2 * L * math.sin(theta), abs=1e-12)
    assert ez == pytest.approx(2 * L * math.cos(theta), abs=1e-12)
    # measured back from the drawing: the angle from the vertical and the length
    assert math.atan2(ex - px, ez - pz) == pytest.approx(
        math.atan2(math.sin(theta), math.cos(theta)), abs=1e-12)
    assert math.hypot(ex - px, ez - pz) == pytest.approx(2 * L, abs=1e-12)


def test_hanging_puts_the_tip_below_the_pivot_and_upright_above():
    hanging = by_id(rig_markers(frame(0.0, math.pi), SCENE))["pendulum", 0].points[1]
    upright = by_id(rig_markers(frame(0.0, 0.0), SCENE))["pendulum", 0].points[1]
    assert hanging[2] == pytest.approx(-0.173) and upright[2] == pytest.approx(0.173)


@pytest.mark.parametrize("mode", list(Mode))
def test_the_pendulum_and_the_text_have_the_mode_colour(mode):
    m = by_id(rig_markers(frame(mode=mode), SCENE))
    expected = tuple(c / 255 for c in MODE_COLOURS[mode]) + (1.0,)
    assert m["pendulum", 0].colour == expected
    assert m["status", 0].colour == expected
    assert m["status", 0].text.startswith(mode.value)


def test_no_mode_yet_is_grey_and_says_so():
    m = by_id(rig_markers(frame(mode=None), SCENE))
    r, g, b, _ = m["pendulum", 0].colour
    assert r == g == b
    assert m["status", 0].text.startswith("mode ?")


@pytest.mark.parametrize("force,length", [(2.0, 0.05), (-1.0, -0.025), (10.0, 0.1),
                                          (-50.0, -0.1)])
def test_the_force_arrow_points_along_the_force(force, length):
    """animate's scale, 0.025 m per newton, cut at 0.1 m."""
    arrow = by_id(rig_markers(frame(x=0.03, force=force), SCENE))["force", 0]
    assert arrow.kind == "arrow" and arrow.action == "add"
    (sx, _, sz), (ex, _, ez) = arrow.points
    assert sx == 0.03 and sz == ez
    assert ex - sx == pytest.approx(length, abs=1e-12)


@pytest.mark.parametrize("force", [math.nan, 0.0, 0.1])
def test_no_force_or_a_tiny_one_deletes_the_arrow_under_its_own_id(force):
    arrow = by_id(rig_markers(frame(force=force), SCENE))["force", 0]
    assert arrow.action == "delete"


def test_every_array_has_the_same_namespaces_and_ids():
    arrays = [rig_markers(frame(x, th, mode, f), SCENE) for x, th, mode, f in
              [(0.0, 0.0, Mode.SWING_UP, 1.0), (0.1, 3.0, Mode.CATCH, math.nan),
               (-0.2, -2.0, Mode.FAULT, -3.0), (0.05, 1.0, None, 0.0)]]
    for markers in arrays:
        assert [(m.ns, m.id) for m in markers] == list(MARKER_IDS)
    assert len(set(MARKER_IDS)) == len(MARKER_IDS)


def test_the_static_parts_show_the_end_stops_and_the_safe_range():
    track, safety = TrackParams(min_m=-0.3, max_m=0.2), SafetyParams(x_min_m=-0.25, x_max_m=0.15)
    m = by_id(rig_markers(frame(), MarkerScene.of(RigParams(), track, safety)))
    assert [m["end_stops", k].position[0] for k in (0, 1)] == [-0.3, 0.2]
    rail = m["track", 0]
    assert rail.position[0] - rail.scale[0] / 2 == pytest.approx(-0.3)
    assert rail.position[0] + rail.scale[0] / 2 == pytest.approx(0.2)
    limits = m["safe_range", 0]
    assert limits.kind == "line_list"
    assert sorted({p[0] for p in limits.points}) == [-0.25, 0.15]
    # each limit a vertical line reaching above the upright tip and below the hanging one
    assert min(p[2] for p in limits.points) < -2 * L and max(p[2] for p in limits.points) > 2 * L


# -- the feed: which samples, with which force and mode ------------------------------------

PERIOD_NS = 5_000_000


def first_of_each_slot(stamps, rate_hz):
    """By hand: the first stamp at or after each k / rate_hz."""
    out, k = [], 0
    for s in stamps:
        if Fraction(s, 10**9) >= Fraction(k, 1) / Fraction(rate_hz):
            out.append(s)
            k = math.floor(Fraction(s, 10**9) * Fraction(rate_hz)) + 1
    return out


def run_feed(feed, stamps, force_of=lambda s: s * 1e-9, true_state=True):
    frames = []
    for s in stamps:
        frames += feed.on_state(s, s * 1e-10, -s * 1e-10, true_state)
        frames += feed.on_force(s, force_of(s))
    return frames


@pytest.mark.parametrize("rate_hz", [30.0, 50.0, 7.0])
def test_the_feed_draws_at_most_rate_hz_per_second_of_stamps(rate_hz):
    stamps = [k * PERIOD_NS for k in range(400)]  # 2 s of a 5 ms loop
    frames = run_feed(MarkerFeed(MarkersParams(rate_hz=rate_hz)), stamps)
    assert [f.stamp_ns for f in frames] == first_of_each_slot(stamps, rate_hz)
    assert len(frames) == math.ceil(2.0 * rate_hz)
    for f in frames:  # each with its own sample's state and force
        assert (f.x_m, f.theta_rad, f.force_n) == (f.stamp_ns * 1e-10, -f.stamp_ns * 1e-10,
                                                   f.stamp_ns * 1e-9)


def test_the_same_samples_are_drawn_whatever_the_first_stamp_heard():
    """A viewer started late, or a bag played from the middle, draws the same samples."""
    stamps = [k * PERIOD_NS for k in range(400)]
    whole = [f.stamp_ns for f in run_feed(MarkerFeed(MarkersParams()), stamps)]
    late = [f.stamp_ns for f in run_feed(MarkerFeed(MarkersParams()), stamps[123:])]
    assert late[1:] == [s for s in whole if s > late[0]]


def test_a_force_that_came_first_or_never_and_the_mode_of_each_stamp():
    feed = MarkerFeed(MarkersParams(rate_hz=100.0))  # a slot per 10 ms: every other sample
    feed.on_mode(0, Mode.SWING_UP)
    assert feed.on_force(0, 1.5) == []  # the force before the state: drawn at once
    (first,) = feed.on_state(0, 0.01, 3.0, True)
    assert (first.force_n, first.mode) == (1.5, Mode.SWING_UP)
    assert feed.on_state(10_000_000, 0.02, 2.0, True) == []  # waits for its force
    feed.on_mode(15_000_000, Mode.CATCH)
    # the next sample came before the force: drawn without one
    (second,) = feed.on_state(15_000_000, 0.03, 1.0, True)
    assert second.stamp_ns == 10_000_000 and math.isnan(second.force_n)
    assert second.mode is Mode.SWING_UP  # the change at 15 ms is not yet its mode
    assert feed.on_state(20_000_000, 0.04, 0.5, True) == []
    (third,) = feed.on_force(20_000_000, -2.0)
    assert (third.x_m, third.force_n, third.mode) == (0.04, -2.0, Mode.CATCH)
    assert third.run_time_s == pytest.approx(0.02)


def test_a_stamp_older_than_the_last_starts_over():
    feed = MarkerFeed(MarkersParams())
    run_feed(feed, [k * PERIOD_NS for k in range(100)])
    frames = run_feed(feed, [k * PERIOD_NS for k in range(3)])  # a new run from 0
    assert [f.stamp_ns for f in frames] == [0]
    assert frames[0].run_time_s == 0.0


def test_auto_takes_the_true_state_when_it_is_published_else_the_measured_one():
    feed = MarkerFeed(MarkersParams(source="auto"))
    # nothing publishes a true state (the rig): the measured samples are drawn
    (f,) = feed.on_state(0, 0.1, 0.0, False, lambda: False) + feed.on_force(0, 0.0)
    assert not f.true_state
    # a simulator publishes one: measured samples are not drawn
    assert feed.on_state(40_000_000, 0.2, 0.0, False, lambda: True) == []
    (g,) = feed.on_state(80_000_000, 0.3, 0.0, True) + feed.on_force(80_000_000, 0.0)
    assert g.true_state and g.x_m == 0.3
    # once a true state arrived, measured samples are ignored even if it seems unpublished
    assert feed.on_state(120_000_000, 0.4, 0.0, False, lambda: False) == []
    measured = MarkerFeed(MarkersParams(source="measured"))
    assert measured.on_state(0, 0.1, 0.0, True) == []
    only_true = MarkerFeed(MarkersParams(source="true"))
    assert only_true.on_state(0, 0.1, 0.0, False) == []


@pytest.mark.parametrize("name,value,message", [
    ("markers.source", "both", r"markers.source = 'both' must be one of 'auto', 'true', "
                               r"'measured'"),
    ("markers.rate_hz", 0.0, r"markers.rate_hz = 0.0 must be positive \(> 0\)"),
    ("markers.rate_hz", math.inf, r"markers.rate_hz = inf must be finite"),
    ("markers.frame_id", "/world", r"markers.frame_id = '/world' must be a frame name"),
    ("markers.frame_id", "", r"markers.frame_id = '' must be a frame name"),
    ("markers.rate", 30.0, r"markers.rate: unknown parameter; did you mean markers.rate_hz\?"),
])
def test_invalid_markers_parameters_are_refused_with_the_rule(name, value, message):
    with pytest.raises(ConfigError, match=message):
        from_flat(MarkersParams, {name: value}, "markers")


# -- the node over ROS topics ----------------------------------------------------------------

@pytest.mark.integration
def test_the_node_publishes_the_throttled_samples_with_their_stamps(ros_context):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from conftest import spin_until
    from pisc_runs.markers_node import MarkersNode
    from pisc_msgs_py.base_node import message_class, qos_profile
    from pisc_msgs_py.convert import cart_force_to_msg, mode_to_msg, true_state_to_msg
    from pisc_msgs_py.topics import CART_FORCE, JOINT_STATES, MARKERS, MODE, SIM_STATE
    from pisc_msgs_py.types import CartForce, ModeReport, TrueState

    from rclpy.parameter import Parameter

    # the probe stands in for the graph: the node's inputs answer to it alone
    fed = ",".join(f"{t.name}=probe" for t in (SIM_STATE, JOINT_STATES, CART_FORCE, MODE))
    node = MarkersNode(context=ros_context,
                       parameter_overrides=[Parameter("start.publishers", value=fed)])
    probe = Node("probe", context=ros_context)
    pubs = {t.name: probe.create_publisher(message_class(t.type), t.name, qos_profile(t.qos))
            for t in (SIM_STATE, CART_FORCE, MODE)}
    arrays = []
    probe.create_subscription(message_class(MARKERS.type), MARKERS.name, arrays.append,
                              qos_profile(MARKERS.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(probe)
    stamps = [1_000_000_000 + k * PERIOD_NS for k in range(100)]  # 0.5 s from t = 1 s
    expected = first_of_each_slot(stamps, 30.0)
    try:
        assert spin_until(executor, lambda: all(p.get_subscription_count() >= 1
                                                for p in pubs.values())
                          and node._pub.get_subscription_count() >= 1, 10.0)
        pubs[MODE.name].publish(mode_to_msg(ModeReport(stamps[0], Mode.CATCH)))
        assert spin_until(executor, lambda: node._feed.mode_at(stamps[0]) is Mode.CATCH, 10.0)
        for k, s in enumerate(stamps):
            pubs[SIM_STATE.name].publish(true_state_to_msg(
                TrueState(s, 0.001 * k, 0.0, 0.01 * k, 0.0, 0.0)))
            pubs[CART_FORCE.name].publish(cart_force_to_msg(CartForce(s, 1.0)))
            # one cycle at a time, as the graph sends them
            assert spin_until(executor, lambda s=s: node._feed.last_stamp_ns == s
                              and node._feed.force_heard(s), 10.0)
        assert spin_until(executor, lambda: len(arrays) >= len(expected), 20.0), len(arrays)
        assert not spin_until(executor, lambda: len(arrays) > len(expected), 0.3)
    finally:
        node.destroy_node()
        probe.destroy_node()
    assert len(expected) == 15  # 30 per second of stamps, over 0.5 s
    got = []
    for array in arrays:
        stamp = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in array.markers}
        assert len(stamp) == 1 and {m.header.frame_id for m in array.markers} == {"world"}
        got.append(stamp.pop())
        k = stamps.index(got[-1])
        markers = {(m.ns, m.id): m for m in array.markers}
        assert list(markers) == list(MARKER_IDS)
        assert markers["cart", 0].pose.position.x == pytest.approx(0.001 * k)
        tip = markers["pendulum", 0].points[1]
        assert tip.x == pytest.approx(0.001 * k + 2 * L * math.sin(0.01 * k))
        colour = markers["pendulum", 0].color
        assert (colour.r, colour.g, colour.b) == pytest.approx(
            tuple(c / 255 for c in MODE_COLOURS[Mode.CATCH]))
    assert got == expected


@pytest.mark.integration
def test_the_node_refuses_an_invalid_parameter_at_start_and_when_running(ros_context):
    from rclpy.parameter import Parameter

    from pisc_runs.markers_node import MarkersNode

    with pytest.raises(ConfigError, match=r"markers.rate_hz = -30.0 must be positive"):
        MarkersNode(context=ros_context,
                    parameter_overrides=[Parameter("markers.rate_hz", value=-30.0)])
    node = MarkersNode(context=ros_context)
    try:
        bad = node.set_parameters([Parameter("markers.source", value="both")])[0]
        assert not bad.successful and "must be one of 'auto', 'true', 'measured'" in bad.reason
        good = node.set_parameters([Parameter("markers.rate_hz", value=10.0)])[0]
        assert good.successful and node._feed.params.rate_hz == 10.0
    finally:
        node.destroy_node()


@pytest.mark.integration
def test_the_entry_point_refuses_and_says_why(env_for_domain):
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_runs.markers_node", "--ros-args",
         "-p", "markers.frame_id:=/world"],
        env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert completed.stderr.startswith(
        "refusing to start: invalid parameter: markers.frame_id = '/world' must be a frame "
        "name"), completed.stderr
    assert "Traceback" not in completed.stderr


# -- pisc_graph --markers ------------------------------------------------------------------

@pytest.mark.integration
def test_a_lockstep_run_with_markers_records_the_true_state_drawn(tmp_path, domain_id):
    from pisc_bag.bag import read_bag
    from pisc_bringup.graph import RunOptions, run_graph
    from pisc_msgs_py.convert import true_state_from_msg
    from pisc_msgs_py.topics import MARKERS, SIM_STATE

    result = run_graph(RunOptions(duration_s=2.0, clock="lockstep", markers=True,
                                  bag_dir=tmp_path / "bag", domain_id=domain_id))
    truth, drawn = {}, {}
    for m in read_bag(result.bag_dir, [SIM_STATE.name, MARKERS.name]):
        if m.topic == SIM_STATE.name:
            s = true_state_from_msg(m.message)
            truth[s.stamp_ns] = (s.position_m, s.angle_rad)
        else:
            markers = {(mk.ns, mk.id): mk for mk in m.message.markers}
            stamp = m.message.markers[0].header.stamp
            drawn[stamp.sec * 10**9 + stamp.nanosec] = markers
    assert result.recorded[MARKERS.name] == len(drawn)
    stamps = sorted(truth)
    expected = first_of_each_slot(stamps, 30.0)
    # every slot of 1/30 s drawn once, at its first sample (the node may miss the first
    # samples while it matches the plant, and the last drawn sample waits for a force
    # the run may stop before sending)
    first, last = min(drawn), max(drawn)
    assert sorted(drawn)[1:] == [s for s in expected if first < s <= last]
    assert first <= expected[1] and last >= expected[-2] and len(drawn) >= 59
    for stamp, markers in drawn.items():
        x, theta = truth[stamp]
        assert markers["cart", 0].pose.position.x == x  # the true state of the same stamp
        tip = markers["pendulum", 0].points[1]
        np.testing.assert_allclose([tip.x, tip.z], [x + 2 * L * math.sin(theta),
                                                    2 * L * math.cos(theta)], atol=1e-12)

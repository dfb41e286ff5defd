"""Markers node: the rig as a MarkerArray on /pisc/markers, for RViz and Foxglove.

Subscribes to the true state (``/pisc/sim/true_state``) and the measured joint states
(``/pisc/joint_states``), the mode and the cart force; ``markers.source`` chooses the
state drawn (``auto``: the true state whenever something publishes it, else the measured
one). Publishes at most ``markers.rate_hz`` arrays per second of the samples' own stamps,
each stamped with its sample's stamp (:class:`pisc_runs.markers.MarkerFeed`), so it
draws the same samples in lockstep, on the wall clock and under ``pisc_bag play``.
Optional: ``pisc_graph --markers`` runs it with the graph and records its topic.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Point
from visualization_msgs.msg import Marker, MarkerArray

from pisc_runs.markers import MarkerFeed, MarkerScene, MarkersParams, RigFrame, rig_markers
from pisc_control.supervisor import SafetyParams
from pisc_msgs_py.base_node import WARN, PiscNode, run_node
from pisc_msgs_py.convert import (
    cart_force_from_msg,
    joint_sample_from_msg,
    mode_from_msg,
    stamp_to_msg,
    true_state_from_msg,
)
from pisc_msgs_py.topics import CART_FORCE, JOINT_STATES, MARKERS, MODE, SIM_STATE
from pisc_model.params import RigParams, TrackParams

SECTIONS = {"markers": MarkersParams, "rig": RigParams, "track": TrackParams,
            "safety": SafetyParams}

KINDS = {"cube": Marker.CUBE, "line_strip": Marker.LINE_STRIP, "line_list": Marker.LINE_LIST,
         "arrow": Marker.ARROW, "text": Marker.TEXT_VIEW_FACING}
ACTIONS = {"add": Marker.ADD, "delete": Marker.DELETE}


@dataclass(frozen=True)
class MarkersConfig:
    params: MarkersParams
    scene: MarkerScene


class MarkersNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("markers", SECTIONS, **kwargs)
        self._feed = MarkerFeed(self.config.params)
        self._pub = self.publisher(MARKERS)
        self._subs = [self.subscription(SIM_STATE, self._on_true_state),
                      self.subscription(JOINT_STATES, self._on_joint_states),
                      self.subscription(CART_FORCE, self._on_force),
                      self.subscription(MODE, self._on_mode)]

    def build(self, flat: dict[str, Any]) -> MarkersConfig:
        params = self.section(flat, "markers")
        scene = MarkerScene.of(self.section(flat, "rig"), self.section(flat, "track"),
                               self.section(flat, "safety"), params.frame_id)
        return MarkersConfig(params, scene)

    def on_config(self, config: MarkersConfig) -> None:
        self.config = config
        self._feed.params = config.params

    def _true_state_published(self) -> bool:
        return self.count_publishers(SIM_STATE.name) > 0

    def _on_true_state(self, msg: Any) -> None:
        self._sample(msg, true_state_from_msg, True)

    def _on_joint_states(self, msg: Any) -> None:
        self._sample(msg, joint_sample_from_msg, False)

    def _sample(self, msg: Any, convert: Any, true_state: bool) -> None:
        s = self.parse(msg, convert, "state sample", WARN)
        if s is None:
            return
        self._publish(self._feed.on_state(s.stamp_ns, s.position_m, s.angle_rad, true_state,
                                          self._true_state_published))

    def _on_force(self, msg: Any) -> None:
        f = self.parse(msg, cart_force_from_msg, "cart force", WARN)
        if f is None:
            return
        self._publish(self._feed.on_force(f.stamp_ns, f.force_n))

    def _on_mode(self, msg: Any) -> None:
        report = self.parse(msg, mode_from_msg, "mode", WARN)
        if report is None:
            return
        self._feed.on_mode(report.stamp_ns, report.mode)

    def _publish(self, frames: list[RigFrame]) -> None:
        for frame in frames:
            self._pub.publish(to_msg(frame, self.config.scene))


def to_msg(frame: RigFrame, scene: MarkerScene) -> MarkerArray:
    """The frame's markers as a MarkerArray, each stamped with the frame's sample stamp."""
    stamp = stamp_to_msg(frame.stamp_ns)
    out = MarkerArray()
    for spec in rig_markers(frame, scene):
        m = Marker()
        m.header.stamp = stamp
        m.header.frame_id = scene.frame_id
        m.ns, m.id = spec.ns, spec.id
        m.type, m.action = KINDS[spec.kind], ACTIONS[spec.action]
        m.pose.position.x, m.pose.position.y, m.pose.position.z = spec.position
        (m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z,
         m.pose.orientation.w) = spec.orientation
        m.scale.x, m.scale.y, m.scale.z = spec.scale
        m.color.r, m.color.g, m.color.b, m.color.a = spec.colour
        m.points = [Point(x=p[0], y=p[1], z=p[2]) for p in spec.points]
        m.text = spec.text
        out.markers.append(m)
    return out


def main(args: list[str] | None = None) -> int:
    return run_node(MarkersNode, args)


if __name__ == "__main__":
    raise SystemExit(main())

"""The graph live in Foxglove: a WebSocket server (foxglove-sdk) on this machine serving
the run's topics and the rig as a 3D scene. No rclpy here (the node is foxglove_node).

:class:`LiveServer` serves, on ``ws://127.0.0.1:PORT`` with Foxglove's WebSocket
protocol v1 (subprotocol ``foxglove.sdk.v1``, the name foxglove-sdk gives it):

* every topic of :data:`LIVE_TOPICS`, its CDR bytes unchanged (message encoding
  ``cdr``) with its ROS 2 message definition as the schema (encoding ``ros2msg``, the
  definition the bags embed), so Foxglove plots ``/pisc/joint_states.position[1]`` as it
  does from a bag; the latched mode is sent again to each new subscriber;
* ``/pisc/scene``, ``foxglove.SceneUpdate`` (protobuf): the rig of
  :func:`pisc_runs.markers.rig_markers` (track, end stops, safe range, cart,
  pendulum in its mode's colour, force arrow, status text) in frame ``world``, at most
  30 frames a second of the samples' stamps (:class:`pisc_runs.markers.MarkerFeed`).

``pisc_graph --foxglove [PORT]`` runs it in a process of its own (foxglove_node) beside
the graph; ``pisc_bag play --foxglove [PORT]`` feeds it the bag's messages as it plays
them. :func:`check_port` refuses a port in use, naming it, before a run starts.
docs/foxglove.md says how to open the shipped layout (``foxglove/pisc.json``).
"""

from __future__ import annotations

import errno
import math
import socket
from collections.abc import Callable
from typing import Any

from pisc_bag.bag import TYPESTORE, header_stamp_ns
from pisc_runs.markers import MarkerFeed, MarkerScene, MarkersParams, MarkerSpec, RigFrame, \
    rig_markers
from pisc_msgs_py import cdr
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.convert import MODE_STATUS_NAME
from pisc_msgs_py.topics import (
    CART_FORCE,
    CURRENT_SETPOINT,
    DIAGNOSTICS,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    SIM_STATE,
    STATE,
    VOLTAGE,
    Topic,
)
from pisc_msgs_py.types import Mode

__all__ = ["DEFAULT_PORT", "LIVE_TOPICS", "SCENE_TOPIC", "LiveServer", "check_port",
           "scene_update"]

DEFAULT_PORT = 8765  # Foxglove's own default
LIVE_TOPICS: tuple[Topic, ...] = (JOINT_STATES, MOTOR_CURRENT, STATE, CART_FORCE, MODE,
                                  CURRENT_SETPOINT, VOLTAGE, SIM_STATE, DIAGNOSTICS)
SCENE_TOPIC = "/pisc/scene"
LATCHED = (MODE.name,)
HOST = "127.0.0.1"


def check_port(port: Any) -> int:
    """``port`` if a server may listen on it on this machine; :class:`ConfigError` naming
    the port otherwise (not a port number, or in use)."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ConfigError(f"--foxglove {port!r}: a port number in 1 .. 65535")
    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        probe.bind((HOST, port))
    except OSError as exc:
        why = "in use" if exc.errno == errno.EADDRINUSE else exc.strerror
        raise ConfigError(f"--foxglove {port}: port {port} on {HOST} is {why}") from None
    finally:
        probe.close()
    return port


def _schema(topic: Topic) -> Any:
    import foxglove

    text, _ = TYPESTORE.generate_msgdef(topic.type, ros_version=2)
    return foxglove.Schema(name=topic.type, encoding="ros2msg", data=text.encode())


def scene_update(frame: RigFrame, scene: MarkerScene) -> Any:
    """The rig of one frame as a ``foxglove.SceneUpdate``: one entity per marker of
    :func:`pisc_runs.markers.rig_markers` (namespace and id as its id), or a deletion
    for a marker the frame removes (the force arrow without a force)."""
    from foxglove import messages as m

    stamp = m.Timestamp(sec=frame.stamp_ns // 1_000_000_000,
                        nsec=frame.stamp_ns % 1_000_000_000)
    entities, deletions = [], []
    for spec in rig_markers(frame, scene):
        ident = f"{spec.ns}/{spec.id}"
        if spec.action == "delete":
            deletions.append(m.SceneEntityDeletion(timestamp=stamp, id=ident))
            continue
        entities.append(m.SceneEntity(timestamp=stamp, frame_id=scene.frame_id, id=ident,
                                      **_primitive(m, spec)))
    return m.SceneUpdate(deletions=deletions, entities=entities)


def _primitive(m: Any, spec: MarkerSpec) -> dict[str, list[Any]]:
    px, py, pz = spec.position
    ox, oy, oz, ow = spec.orientation
    pose = m.Pose(position=m.Vector3(x=px, y=py, z=pz),
                  orientation=m.Quaternion(x=ox, y=oy, z=oz, w=ow))
    colour = m.Color(r=spec.colour[0], g=spec.colour[1], b=spec.colour[2], a=spec.colour[3])
    sx, sy, sz = spec.scale
    if spec.kind == "cube":
        return {"cubes": [m.CubePrimitive(pose=pose, size=m.Vector3(x=sx, y=sy, z=sz),
                                          color=colour)]}
    if spec.kind in ("line_strip", "line_list"):
        kind = (m.LinePrimitiveLineType.LineStrip if spec.kind == "line_strip"
                else m.LinePrimitiveLineType.LineList)
        return {"lines": [m.LinePrimitive(type=kind, pose=pose, thickness=sx, color=colour,
                                          points=[m.Point3(x=a, y=b, z=c)
                                                  for a, b, c in spec.points])]}
    if spec.kind == "arrow":  # the Marker's start and end points as a pose and a length
        (ax, ay, az), (bx, by, bz) = spec.points
        length = math.hypot(bx - ax, by - ay, bz - az)
        yaw = 0.0 if bx >= ax else math.pi  # along the track, +x or -x
        pose = m.Pose(position=m.Vector3(x=ax, y=ay, z=az),
                      orientation=m.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                               w=math.cos(yaw / 2)))
        head = min(sz, length)
        return {"arrows": [m.ArrowPrimitive(pose=pose, shaft_length=length - head,
                                            shaft_diameter=sx, head_length=head,
                                            head_diameter=sy, color=colour)]}
    return {"texts": [m.TextPrimitive(pose=pose, billboard=True, font_size=sz,
                                      color=colour, text=spec.text)]}


class LiveServer:
    """A Foxglove WebSocket server of one run; :meth:`publish` each message as it goes."""

    def __init__(self, port: int, scene: MarkerScene, rate_hz: float = 30.0) -> None:
        import foxglove
        from foxglove.channel import Channel
        from foxglove.channels import SceneUpdateChannel

        check_port(port)
        self._context = foxglove.Context()
        self._last: dict[str, bytes] = {}
        self._channels = {t.name: Channel(t.name, schema=_schema(t), message_encoding="cdr",
                                          context=self._context) for t in LIVE_TOPICS}
        self._scene_channel = SceneUpdateChannel(SCENE_TOPIC, context=self._context)
        self._scene = scene
        self._feed = MarkerFeed(MarkersParams(rate_hz=rate_hz, frame_id=scene.frame_id))
        self._true_state = False
        try:
            self._server = foxglove.start_server(name="pisc", host=HOST, port=port,
                                                 context=self._context,
                                                 server_listener=self)
        except Exception as exc:  # noqa: BLE001 (the SDK's error for a port it cannot take)
            raise ConfigError(f"--foxglove {port}: cannot serve on {HOST}:{port} ({exc})") \
                from None
        self.port = self._server.port

    # ServerListener: a new subscriber of a latched topic gets its last message
    def on_subscribe(self, client: Any, channel: Any) -> None:
        data = self._last.get(channel.topic)
        if data is not None:
            self._channels[channel.topic].log(data)

    def publish(self, topic: str, data: bytes) -> None:
        """One message of ``topic`` as it was published (CDR); others are not served."""
        channel = self._channels.get(topic)
        if channel is None:
            return
        stamp = header_stamp_ns(data)
        channel.log(data, log_time=stamp)
        if topic in LATCHED:
            self._last[topic] = data
        for frame in self._frames(topic, data, stamp):
            self._scene_channel.log(scene_update(frame, self._scene), log_time=frame.stamp_ns)

    def _frames(self, topic: str, data: bytes, stamp: int | None) -> list[RigFrame]:
        if stamp is None:
            return []
        if topic in (SIM_STATE.name, JOINT_STATES.name):
            true_state = topic == SIM_STATE.name
            self._true_state |= true_state
            position = cdr.decode_joint_state(data).position
            published: Callable[[], bool] = lambda: self._true_state  # noqa: E731
            return self._feed.on_state(stamp, position[0], position[1], true_state, published)
        if topic == CART_FORCE.name:
            return self._feed.on_force(stamp, cdr.decode_wrench_stamped(data).wrench.force.x)
        if topic == MODE.name:
            msg = TYPESTORE.deserialize_cdr(data, MODE.type)
            for status in msg.status:
                if status.name == MODE_STATUS_NAME and status.message in Mode._value2member_map_:
                    self._feed.on_mode(stamp, Mode(status.message))
        return []

    def close(self) -> None:
        self._server.stop()

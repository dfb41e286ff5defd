"""pisc_foxglove: the run's topics live in Foxglove, in a process of its own.

    pisc_foxglove --port PORT --params FILE [--ros-args ...]

Subscribes to :data:`pisc_runs.foxglove_live.LIVE_TOPICS` (their raw CDR bytes; best
effort but the latched mode, so a slow viewer never holds a publisher back) and hands
each message to a :class:`~pisc_runs.foxglove_live.LiveServer` on 127.0.0.1:PORT,
which draws the rig from the parameter file's ``rig``, ``track`` and ``safety``. Prints
``serving ws://127.0.0.1:PORT`` once it listens; exits 2 naming the port when it is in
use. ``pisc_graph --foxglove`` starts it before the run and stops it after.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["START_TIMEOUT_S", "command", "main", "scene_of", "wait_serving"]

START_TIMEOUT_S = 30.0


def command(port: int, params: Path) -> list[str]:
    """The command line of the bridge for ``port`` and the run's parameter file."""
    from pisc_msgs_py.processes import console_command

    return [*console_command("pisc_foxglove", "pisc_runs.foxglove_node"), "--port",
            str(port), "--params", str(params)]


def wait_serving(child: Any, port: int, stderr: Any = None) -> Any:
    """``child`` (started with :func:`command`, standard output a pipe) once it says it
    serves; :class:`~pisc_msgs_py.config.ConfigError` with its reason (a port in use:
    its number) when it exits instead or does not say so in :data:`START_TIMEOUT_S`.
    ``stderr()``: what the child wrote on its standard error, once it has exited."""
    import os
    import select
    import time

    from pisc_msgs_py.config import ConfigError

    # the pipe's bytes as they come, not readline(): a line not yet ended blocked a run
    # for good past the deadline (a lockstep run of the test suite, 2026-12-06)
    fd, pending = child.stdout.fileno(), b""
    deadline = time.monotonic() + START_TIMEOUT_S
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([fd], [], [], min(left, 0.5))
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:  # it exited
                break
            *lines, pending = (pending + chunk).split(b"\n")
            if any(line.startswith(b"serving ") for line in lines):
                return child
    if child.poll() is None:
        child.kill()
    child.wait()
    said = (stderr() if stderr is not None else b"").decode(errors="replace").strip()
    reason = said.splitlines()[-1].removeprefix("pisc_foxglove: ") if said else (
        f"it did not serve within {START_TIMEOUT_S:.0f} s")
    raise ConfigError(reason if reason.startswith("--foxglove") else
                      f"--foxglove {port}: pisc_foxglove did not start: {reason}")


def scene_of(params: Path) -> Any:
    """The rig to draw (:class:`pisc_runs.markers.MarkerScene`) of a parameter file."""
    from pisc_runs.markers import MarkerScene
    from pisc_control.supervisor import SafetyParams
    from pisc_model.params import RigParams, TrackParams
    from pisc_msgs_py.config import from_flat, load_params_file

    flat = load_params_file(params)
    return MarkerScene.of(from_flat(RigParams, flat, "rig"), from_flat(TrackParams, flat, "track"),
                          from_flat(SafetyParams, flat, "safety"), "world")


def main(argv: Sequence[str] | None = None) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import ReliabilityPolicy

    from pisc_runs.foxglove_live import LIVE_TOPICS, LiveServer
    from pisc_msgs_py.base_node import message_class, qos_profile
    from pisc_msgs_py.config import ConfigError
    from pisc_msgs_py.topics import MODE

    args_in = list(sys.argv[1:] if argv is None else argv)
    ros_args = args_in[args_in.index("--ros-args"):] if "--ros-args" in args_in else []
    mine = args_in[:len(args_in) - len(ros_args)]
    parser = argparse.ArgumentParser(prog="pisc_foxglove", description=__doc__.split("\n\n")[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--params", type=Path, required=True,
                        help="the run's parameter file (the rig drawn in the 3D scene)")
    args = parser.parse_args(mine)
    try:
        server = LiveServer(args.port, scene_of(args.params))
    except ConfigError as exc:
        print(f"pisc_foxglove: {exc}", file=sys.stderr)
        return 2
    rclpy.init(args=["pisc_foxglove", *ros_args])
    node = Node("pisc_foxglove")
    for topic in LIVE_TOPICS:
        qos = qos_profile(topic.qos)
        if topic is not MODE:
            qos.reliability = ReliabilityPolicy.BEST_EFFORT
        node.create_subscription(message_class(topic.type), topic.name,
                                 lambda data, name=topic.name: server.publish(name, data),
                                 qos, raw=True)
    print(f"serving ws://127.0.0.1:{server.port}", flush=True)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        server.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

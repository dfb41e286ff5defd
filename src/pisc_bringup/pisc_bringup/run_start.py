"""Before a run of the graph and at its start: the options and their checks, the
parameter files and the launch file's arguments, the recorder's command line, and the
waits until the recorder and the nodes are connected (see :mod:`pisc_bringup.graph`).
"""

from __future__ import annotations

import math
import os
import subprocess
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node

import yaml

from pisc_bag.bag_repair import RepairReport
from pisc_bag.run_files import PARAMS_FILE, PLANT_PARAMS_FILE
from pisc_bringup.children import spawn, stderr_of, stop
from pisc_bringup.dds import dds_environment
from pisc_bringup.launch_graph import (
    Graph,
    GraphNode,
    expected_publishers,
    expected_subscribers,
    read_graph,
    recorded_topics,
)
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.processes import console_command
from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    CURRENT_SETPOINT,
    DIAGNOSTICS,
    GRAPH_TOPICS,
    JOINT_STATES,
    MOTOR_CURRENT,
    SIM_STATE,
    STATE,
    VOLTAGE,
    Topic,
)
from pisc_runs.summary import RunSummary
from pisc_sim.configuration import load_run_config, write_params_file

__all__ = ["EXECUTORS", "MAX_DOMAIN_ID", "RECORDER_GATHER_S", "RECORDER_LAG_SAMPLES", "SAMPLE_TOPICS", "GraphError",
           "RecorderDied", "RunOptions", "RunPlan", "awaiting", "check_recorder",
           "checked_config", "clock_subscribers", "controllers_matched", "default_bag_dir",
           "expected_messages", "launch_args", "plan_run", "plant_description", "read_again",
           "recorder_args", "recorder_matched", "recorder_ready", "run_args",
           "start_processes", "wait_for", "write_params"]


LAUNCH_FILES = {False: "sim", True: "rig"}

# Lockstep: how many samples the plant may run ahead of the newest sample the recorder
# has written whole (simulation.recorder_lag_samples). With what the recorder reports
# every 5 samples (pisc_record --progress), at most 25 samples' messages (7-8 a sample)
# are on their way to it: well inside each publisher's history of 100 (CONTROL_QOS) and Fast
# DDS's shared-memory port of 512 messages. With 50, a recorder stopped for 1 s froze
# the whole --processes graph in 2 of 13 runs (the plant's timer did not run either):
# most likely a writer waiting for a reader whose port was full (docs/recording.md).
RECORDER_LAG_SAMPLES = 20
# Lockstep: the recorder lets messages gather this long after writing a batch (pisc_record
# --gather), so that it wakes about once a cycle, not for each of a cycle's 7-8 messages
# (docs/figures.md, "Fewer wake-ups a cycle"). Well inside what the plant lets it trail
# (RECORDER_LAG_SAMPLES).
RECORDER_GATHER_S = 0.001
# what a lockstep graph publishes once every sample: the recorder's progress is the
# oldest of the newest it has written of each (a topic whose message DDS sends again
# lags the others). Not /clock: it goes out with every simulation.clock_every-th sample
# only, and as a progress topic it held the plant back once clock_every neared the lag.
SAMPLE_TOPICS = (JOINT_STATES, MOTOR_CURRENT, SIM_STATE, STATE, CART_FORCE,
                 CURRENT_SETPOINT, VOLTAGE)

# Fast DDS maps a domain to UDP ports 7400 + 250 * id + ...: past 232 they exceed 65535
MAX_DOMAIN_ID = 232


EXECUTORS = {"events": EventsExecutor, "single": SingleThreadedExecutor,
             "multi": MultiThreadedExecutor}


class GraphError(RuntimeError):
    """The graph did not run to the end; the message says what happened."""


class RecorderDied(GraphError):
    """pisc_record died during the run: the run stopped there, and the bag was finished
    with what had been recorded (``repair``, None if that failed; ``summary`` of the
    recorded part, None if there is none)."""

    def __init__(self, message: str, bag_dir: Path, summary: RunSummary | None,
                 repair: RepairReport | None) -> None:
        super().__init__(message)
        self.bag_dir = bag_dir
        self.summary = summary
        self.repair = repair


@dataclass(frozen=True)
class RunOptions:
    config: str = "default"
    overrides: dict[str, Any] = field(default_factory=dict)
    duration_s: float = 10.0
    clock: str = "lockstep"
    processes: bool = False
    executor: str = "events"  # in one process: 'events', 'single' or 'multi'
    bag_dir: Path | None = None
    domain_id: int | None = None
    timeout_s: float | None = None  # wall-clock limit; default scales with duration
    driver_port: str | None = None  # run the serial driver on this port instead of the plant
    record: tuple[str, ...] | None = None  # topics to record (with RUN_TOPICS); None: all
    # model error: the plant's own configuration (None: the controllers') and overrides
    # applied to the plant only, after ``overrides`` (sections the plant reads)
    plant_config: str | None = None
    plant_overrides: dict[str, Any] = field(default_factory=dict)
    markers: bool = False  # also run the markers node and record /pisc/markers
    foxglove_port: int | None = None  # serve the run live to Foxglove on this port
    # the launch file declaring the graph (a path); None: sim.launch.xml, or
    # rig.launch.xml with driver_port
    launch: str | None = None
    # with driver_port: how long a port that went away may take to come back [s]
    port_retry_s: float = 3.0

    @property
    def initial_x_m(self) -> Any:
        """The plant's initial cart position as set on the command line, else 'file'."""
        return self.plant_overrides.get("initial.x_m", self.overrides.get("initial.x_m", "file"))


def checked_config(options: RunOptions) -> tuple[Any, dict[str, Any], dict[str, Any]]:
    """The run's configuration, flat parameters (with the catch gains this machine
    computes) and the plant's flat parameters, or :class:`ConfigError` naming the option
    that is wrong: all of it before the recorder makes the bag directory."""
    if options.driver_port is not None and (
            options.plant_config is not None or options.plant_overrides):
        raise ConfigError(
            f"--driver {options.driver_port} with --plant-config/--plant-set "
            f"({plant_description(options)}): the plant is the device: start "
            "pisc_virtual_rig with its own parameter file")
    if not math.isfinite(options.duration_s) or options.duration_s <= 0.0:
        raise ConfigError(f"--duration {options.duration_s}: must be a finite number of "
                          "seconds > 0")
    if options.timeout_s is not None and not (math.isfinite(options.timeout_s)
                                              and options.timeout_s > 0.0):
        raise ConfigError(f"timeout_s = {options.timeout_s}: must be a finite number of "
                          "seconds > 0 (None: by the duration)")
    config, flat, plant_params = load_run_config(
        options.config, options.overrides, options.plant_config, options.plant_overrides)
    supervisor = Supervisor(config.supervisor)  # refuses (3.29), an uncontrollable model
    # the K this machine computes goes into the bag's parameter file, so that a replay on
    # a machine whose LAPACK rounds differently uses the same bits (catch.recorded_gain)
    flat = {**flat, "catch.recorded_gain": [float(k) for k in supervisor.gain]}
    if config.supervisor.catch.hold_poles:
        flat["catch.recorded_hold_gain"] = [float(k) for k in supervisor.hold_gain]
    track = config.simulated_plant.track
    if options.driver_port is None and not track.min_m <= config.initial.x_m <= track.max_m:
        raise ConfigError(f"initial.x_m = {config.initial.x_m} lies outside the track "
                          f"(track.min_m .. track.max_m = {track.min_m} .. {track.max_m} m)")
    _check_run_options(options)
    return config, flat, plant_params


def _check_run_options(options: RunOptions) -> None:
    """The options that are not the configuration's: the port, domain, clock, executor."""
    port = options.driver_port
    if port is not None and not os.access(port, os.R_OK | os.W_OK):
        # refused here, before the recorder makes the bag directory
        problem = "not readable and writable" if os.path.exists(port) else "no such device"
        raise ConfigError(f"driver.port = {port}: {problem}")
    if options.domain_id is not None and not 0 <= options.domain_id <= MAX_DOMAIN_ID:
        raise ConfigError(f"--domain-id {options.domain_id}: must be 0 .. {MAX_DOMAIN_ID} "
                          "(Fast DDS's ports for a larger id are past 65535)")
    if not (math.isfinite(options.port_retry_s) and 0.0 < options.port_retry_s <= 3600.0):
        raise ConfigError(f"--port-retry {options.port_retry_s}: must be a number of seconds "
                          "> 0 and <= 3600")
    if options.clock not in ("lockstep", "wall"):
        raise ConfigError(f"--clock {options.clock!r}: expected 'lockstep' or 'wall'")
    if options.executor not in EXECUTORS:
        raise ConfigError(
            f"--executor {options.executor!r}: expected one of {', '.join(EXECUTORS)}")
    if options.driver_port is not None and options.clock == "lockstep":
        raise ConfigError("--driver runs against the wall clock (the device paces the "
                          "samples): use --clock wall")


def default_bag_dir(options: RunOptions) -> Path:
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-%f")
    x0 = options.initial_x_m
    name = Path(options.config).stem
    return Path("bags") / f"run-{name}-{options.clock}-x0_{x0}-{stamp}"


def plant_description(options: RunOptions) -> str | None:
    """What the plant runs when it differs from the controllers' model, else None.

    E.g. ``default with motor.resistance_ohm=18.2`` or ``thesis``.
    """
    if options.plant_config is None and not options.plant_overrides:
        return None
    name = options.plant_config if options.plant_config is not None else options.config
    if not options.plant_overrides:
        return name
    return f"{name} with " + ", ".join(f"{k}={v}" for k, v in options.plant_overrides.items())


@dataclass(frozen=True)
class RunPlan:
    """What a run starts, read before anything starts: the launch file's graph, what its
    source waits for, the topics recorded, the wall-clock limit and the environment of
    the processes."""
    graph: Graph
    run_args: dict[str, str]
    recorded: tuple[Topic, ...]
    timeout_s: float
    env: dict[str, str]


def plan_run(options: RunOptions, flat: dict[str, Any],
             plant_params: dict[str, Any]) -> RunPlan:
    """Which nodes run is the launch file's to say. It is read now, with the run's
    parameter files in a scratch directory (a file it refuses leaves no bag), and again
    once they are in the bag (:func:`read_again`), with what the run computes from the
    graph (what the plant or the driver waits for)."""
    driver = options.driver_port is not None
    with tempfile.TemporaryDirectory(prefix="pisc_graph-launch-") as scratch:
        files = write_params(Path(scratch), flat, None if driver else plant_params)
        graph = read_graph(options.launch or LAUNCH_FILES[driver],
                           launch_args(options, files), driver)
    recorded = recorded_topics(options.record) + tuple(
        t for n in graph.observers for t in n.publishes if t is not DIAGNOSTICS)
    timeout = options.timeout_s if options.timeout_s is not None else (
        60.0 + 20.0 * options.duration_s)
    # discovery stays on this machine unless the user asked for more (docs/safety.md);
    # PISC's Fast DDS profile unless the user gives one
    env = dds_environment(dict(os.environ))
    if options.domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(options.domain_id)
    return RunPlan(graph, run_args(options, graph), recorded, timeout, env)


def recorder_args(options: RunOptions, plan: RunPlan, bag_dir: Path, ready: Path,
                  marks: Path, name: str) -> list[str]:
    """pisc_record's command line for the run: its bag, the topics, in lockstep the
    progress it reports to the plant (:data:`RECORDER_LAG_SAMPLES`), the graph's own
    nodes, the file it marks foreign publishers in (``marks``, run_guard), the file it
    writes once it has matched every publisher of the run (``ready``) and its node name
    (another subscriber on the domain, a ``ros2 topic echo`` or another run's recorder,
    must not pass for it)."""
    graph, recorded = plan.graph, plan.recorded
    lockstep = options.clock == "lockstep"
    args = [*console_command("pisc_record", "pisc_bag.record_cli"), "--bag", str(bag_dir)]
    if options.record is not None or graph.observers:
        args += [arg for t in recorded for arg in ("--topic", t.name)]
    publishers = list(graph.nodes)
    if lockstep and options.driver_port is None:  # the plant waits on its progress
        args += [arg for t in recorded if t in SAMPLE_TOPICS
                 and expected_publishers(t, publishers, lockstep)
                 for arg in ("--progress", t.name)]
        args += ["--gather", str(RECORDER_GATHER_S)]
    args += [*(arg for n in graph.nodes for arg in ("--own", n.name)),
             "--marks-file", str(marks)]
    args += ["--ready-file", str(ready), *(
        arg for t in recorded
        for arg in ("--expect", f"{t.name}={expected_publishers(t, publishers, lockstep)}"))]
    return [*args, "--ros-args", "-r", f"__node:={name}"]


def write_params(directory: Path, flat: dict[str, Any],
                 plant_flat: dict[str, Any] | None) -> dict[str, Path]:
    """The run's parameter files in ``directory``: the controllers' and, for the simulated
    plant, the plant's (:data:`PARAMS_FILE`, :data:`PLANT_PARAMS_FILE`)."""
    files = {"params": directory / PARAMS_FILE}
    write_params_file(files["params"], flat)
    if plant_flat is not None:
        files["plant_params"] = directory / PLANT_PARAMS_FILE
        write_params_file(files["plant_params"], plant_flat)
    return files


def launch_args(options: RunOptions, files: dict[str, Path],
                run: dict[str, str] | None = None) -> dict[str, str]:
    """The arguments pisc_graph gives the launch file, as ``ros2 launch FILE name:=value``
    would: its parameter files, the clock, markers on request, and ``run`` (what the plant
    or the driver waits for, computed from the graph: :func:`run_args`; placeholders
    before the graph is known)."""
    args = {name: str(path) for name, path in files.items()}
    args["markers"] = "true" if options.markers else "false"
    if options.driver_port is not None:
        args["port"] = options.driver_port
        args["min_subscribers"] = "0"
    else:
        args["clock"] = options.clock
        args["use_sim_time"] = "true" if options.clock == "lockstep" else "false"
        # the plant stops at the duration itself: a node process is stopped later
        args["duration"] = yaml.safe_dump(float(options.duration_s)).splitlines()[0]
        args.update(min_subscribers="1", min_true_state_subscribers="0",
                    min_clock_subscribers="0")
    args.update(run or {})
    return args


def run_args(options: RunOptions, graph: Graph) -> dict[str, str]:
    """What the source waits for before its first sample, from the graph's nodes."""
    loop = [*graph.controllers, graph.source]
    if options.driver_port is not None:
        # the driver publishes no sample before the graph's readers, the recorder among
        # them, have matched both sample topics: the bag then holds every sample
        return {"min_subscribers": str(min(expected_subscribers(JOINT_STATES, True, loop),
                                           expected_subscribers(MOTOR_CURRENT, True, loop)))}
    run = {"min_subscribers": str(expected_subscribers(JOINT_STATES, True, loop)),
           "min_true_state_subscribers": "1",
           "min_clock_subscribers": str(clock_subscribers(graph, options.processes)),
           "recorder_lag_samples": str(RECORDER_LAG_SAMPLES
                                       if options.clock == "lockstep" else 0)}
    if not options.processes:
        # before the plant's first sample run_graph has seen both ends of every match:
        # the controllers' readers are matched where they are created (one participant),
        # the recorder's when it writes its ready file; no settling time is needed
        run["start_settle"] = "0.0"
    return run


def read_again(first: Graph, options: RunOptions, files: dict[str, Path],
               run: dict[str, str]) -> Graph:
    """The launch file read with the bag's parameter files and the run's arguments; it
    must start the nodes it started on the first reading."""
    graph = read_graph(first.path, launch_args(options, files, run),
                       options.driver_port is not None)
    if [(n.name, n.executable) for n in graph.nodes] != [
            (n.name, n.executable) for n in first.nodes]:
        raise GraphError(f"{first.path}: starts other nodes with the run's arguments "
                         f"({', '.join(n.name for n in graph.nodes)}) than without "
                         f"({', '.join(n.name for n in first.nodes)})")
    return graph


def clock_subscribers(graph: Graph, processes: bool) -> int:
    """Subscribers of /clock the lockstep plant waits for: each controller's clock (rclpy
    subscribes a node with use_sim_time to /clock), the recorder, and, with separate
    processes, this runner, which subscribes once the recorder has matched every
    publisher (in one process nothing runs before the runner spins, after that)."""
    return len(graph.controllers) + 1 + (1 if processes else 0)


def expected_messages(duration_s: float, period_s: float,
                      recorded: Sequence[Topic]) -> dict[str, int]:
    """What a lockstep run of ``duration_s`` publishes on the recorded topics that go
    out with every sample (:data:`SAMPLE_TOPICS`): a message for each of the samples
    0 .. duration_s / period_s (a sample sent again is recorded twice, so a bag may hold
    more)."""
    samples = round(duration_s / period_s) + 1
    return {t.name: samples for t in SAMPLE_TOPICS if t in recorded}


def wait_for(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise GraphError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.01)


def check_recorder(recorder: subprocess.Popen) -> None:
    if recorder.poll() is not None:
        recorder.communicate()
        raise GraphError(f"pisc_record exited: "
                         f"{stderr_of(recorder).decode(errors='replace').strip()}")


def recorder_ready(watcher: Node, recorder: subprocess.Popen, recorded: Sequence[Topic],
                   name: str) -> bool:
    """The recorder runs and its own subscriptions (node ``name``) are seen on every
    recorded topic (before any node of the graph exists)."""
    check_recorder(recorder)
    return all(any(info.node_name == name
                   for info in watcher.get_subscriptions_info_by_topic(t.name))
               for t in recorded)


def recorder_matched(recorder: subprocess.Popen, ready: Path) -> bool:
    """The recorder has matched every publisher of the run (its ``--ready-file``)."""
    check_recorder(recorder)
    return ready.exists()


def controllers_matched(nodes: Sequence[Node], recorded: Sequence[Topic],
                        controllers: Sequence[GraphNode]) -> bool:
    """Every controller publisher sees its subscribers among the controllers and recorder.

    The plant comes later and waits for its own edges (``simulation.min_subscribers``).
    """
    for node in nodes:
        for publisher in node.publishers:
            topic = next((t for t in GRAPH_TOPICS if t.name == publisher.topic_name), None)
            if topic is None or topic in (DIAGNOSTICS, CLOCK):
                continue
            expected = expected_subscribers(topic, topic in recorded, controllers)
            if publisher.get_subscription_count() < expected:
                return False
    return True


def awaiting(node: GraphNode, counted: Sequence[GraphNode],
             recorded: Sequence[Topic]) -> GraphNode:
    """``node`` with ``start.await_subscribers`` (:class:`pisc_msgs_py.node_params.StartParams`)
    for a process of its own: each of its publications but /diagnostics and /clock waits
    for its subscribers among ``counted``, the recorder when the topic is recorded, and,
    for the voltage, the runner's tap (:class:`VoltageTap`)."""
    wanted = ",".join(
        f"{t.name}={expected_subscribers(t, t in recorded, counted) + (t is VOLTAGE)}"
        for t in node.publishes if t not in (DIAGNOSTICS, CLOCK))
    if not wanted:
        return node
    return replace(node, parameters={**node.parameters, "start.await_subscribers": wanted})


def start_processes(graph: Graph, watcher: Node, env: dict[str, str],
                    recorded: Sequence[Topic] = GRAPH_TOPICS,
                    source_waits: bool = False) -> list[subprocess.Popen]:
    """Start the launch file's controllers, each as its own process, and wait until they
    are connected; then start its source (the plant or the driver), last in the list.

    With ``source_waits`` (the lockstep plant, which samples nothing until the runner
    subscribes to /clock, the last subscriber it waits for) the source starts with the
    controllers, so that it loads while they do (from the controllers' connection to the
    recorder's last match took 0.6-3.4 s before, 0.5-0.8 s after, two runs each here on
    2026-12-03); its own subscriptions are not counted as the controllers'."""
    # each waits, before it subscribes, until its publishers have matched the readers
    # counted here: the recorder's too, which DDS may match long after the recorder
    # matched them (docs/recording.md, "Late matches")
    counted = [*graph.controllers, *([graph.source] if source_waits else [])]
    children = [spawn(awaiting(node, counted, recorded).command(), env, subprocess.DEVNULL)
                for node in graph.controllers]
    if source_waits:
        children.append(spawn(graph.source.command(), env, subprocess.DEVNULL))

    def subscribers(topic: Topic) -> int:
        return sum(1 for info in watcher.get_subscriptions_info_by_topic(topic.name)
                   if info.node_name != graph.source.name)

    def connected() -> bool:
        for child in children:
            if child.poll() is not None:
                raise GraphError(stop(child)[0] or f"{child.args[0]} exited")
        for node in graph.controllers:
            for topic in node.publishes:
                if topic is DIAGNOSTICS:
                    continue
                expected = (expected_subscribers(topic, topic in recorded, graph.controllers)
                            + (topic is VOLTAGE))
                if subscribers(topic) < expected:
                    return False
            if watcher.count_publishers(node.publishes[0].name) < 1:
                return False
        return True

    wait_for(connected, 60.0, "the node processes to connect")
    if not source_waits:
        children.append(spawn(graph.source.command(), env, subprocess.DEVNULL))
    return children

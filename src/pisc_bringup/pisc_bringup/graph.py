"""Run the PISC graph against the simulator (or the rig), record it, and summarise the
run: :func:`run_graph`, which ``pisc_graph`` (:mod:`pisc_bringup.graph_cli`) runs. The
graph is read from the launch file (:mod:`pisc_bringup.launch_graph`), the run's checks,
parameter files and start-up waits are :mod:`pisc_bringup.run_start`, its child processes
:mod:`pisc_bringup.children` and what it watches while it runs
:mod:`pisc_bringup.run_watch`.

**The graph is the launch file's.** Which nodes run, with which executable, node name,
parameter files and parameters, is read from ``pisc_bringup/launch/sim.launch.xml``
(``rig.launch.xml`` with ``--driver``; ``--launch FILE`` names another) by
:mod:`pisc_bringup.launch_file`, with the arguments ``ros2 launch`` would take: the bag's
parameter files (``params``, ``plant_params``), ``clock``, ``use_sim_time``, ``duration``,
what the plant or the driver waits for (``min_subscribers``...: the run's recorder) and
``markers``. What a launch file does not say, the class of each executable and the topics
it reads and writes, is
:data:`pisc_bringup.launch_graph.NODE_KINDS`. A file whose graph cannot run (an unknown
executable, no plant or two, a topic the loop reads that no node publishes) is refused,
naming the file and the node, before anything starts.

The recorder (``pisc_record``) always runs as a process of its own. By default the
plant, estimator, supervisor and current loop run in this process on one
``EventsExecutor`` (the measured choice, see README), each named and parametrised as
the launch file says; ``--processes`` starts each node as its own process through its
console entry point, with the file's parameter files and parameters, as ``ros2 launch``
would. ``--driver PORT`` puts the serial driver (``pisc_driver driver_node``) in the
plant's place, on the rig's port or on the pseudo-terminal of ``pisc_virtual_rig``,
against the wall clock, always in a process of its own (a crash of the controllers'
process leaves it to zero the motor). ``--realtime PRIORITY`` runs this
process and the processes it starts under SCHED_FIFO, as a control computer runs its loop: a
real device does not wait for a loaded machine (README, "Serial driver"). ``--scene``
takes a scene's configuration, overrides, duration and the topics it records
(:mod:`pisc_sim.scene`; ``--record`` replaces that list, and
:data:`pisc_bringup.launch_graph.RUN_TOPICS` are
recorded whatever it says). ``--markers`` also runs the markers node (the rig drawn on
``/pisc/markers`` for RViz and Foxglove, docs/markers.md) and records its topic.

**Model error.** ``--plant-config`` and ``--plant-set`` (and a scene's ``plant:`` block)
give the simulated plant other physical parameters than the controllers assume
(:func:`pisc_sim.configuration.load_run_config`): the plant node gets the plant's
flat parameters, the controllers keep theirs. The bag holds both: ``pisc_params.yaml``
(the controllers', which replay and analysis read) and ``plant_params.yaml`` (what the
plant node got; written for every simulated run). With ``--driver`` the plant is the
device and the plant options are refused.

The plant starts publishing once its subscribers are matched (in one process, once
every controller's are too) and the recorder has matched every publisher (a recorder
that matches late gets only the last 100 messages); a lockstep sample that is lost
anyway is sent again; in lockstep the plant runs at most
:data:`pisc_bringup.run_start.RECORDER_LAG_SAMPLES` samples ahead of the newest sample
the recorder has written, so a recorder short of the CPU pauses the run instead of
losing messages (docs/recording.md). With ``--processes
--clock wall`` the plant does not wait for the recorder. The run ends when the voltage
answering the sample at ``--duration`` has been received; the bag is closed, read back
and summarised, and judged by the robustness benchmark's rule (:mod:`pisc_runs.summary`:
each tier, safe, caught and fast, with its rule), whose verdict is ``pisc_graph``'s exit
status (:mod:`pisc_bringup.graph_cli`). An experiment run (``experiment.kind``) gets no
swing-up verdict: the summary says what the experiment did.

**Other ends** (:mod:`pisc_bringup.run_guard`): every node answers to the graph's own
publishers alone, and a publisher of any other node on a topic of the graph stops the
run; SIGINT or SIGTERM stop it, a serial port that went away and did not come back
within ``--port-retry`` seconds too. Each time the source is stopped first (0 V), then
the other nodes, the bag is finished and its summary printed with what ended the run.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from pisc_bag.bag import BagError
from pisc_bag.bag_repair import repair_bag
from pisc_bringup.children import ExitAlarm, exit_description, spawn, stderr_of, stop, stop_all
from pisc_bringup.launch_graph import Graph
from pisc_bringup.run_guard import (
    EXIT_FOREIGN,
    EXIT_PORT_LOST,
    Interrupt,
    RunGuard,
    RunStopped,
    pin_publishers,
)
from pisc_bringup.run_start import (
    EXECUTORS,
    GraphError,
    RecorderDied,
    RunOptions,
    RunPlan,
    awaiting,
    checked_config,
    controllers_matched,
    default_bag_dir,
    expected_messages,
    plan_run,
    read_again,
    recorder_args,
    recorder_matched,
    recorder_ready,
    start_processes,
    wait_for,
    write_params,
)
from pisc_bringup.run_watch import (
    DeathWatch,
    Progress,
    RecorderWatch,
    VoltageTap,
    count_publications,
    wait_acknowledged,
)
from pisc_msgs_py.base_node import (
    freeze_startup_objects,
    leave_realtime,
    message_class,
    qos_profile,
)
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.topics import CLOCK, VOLTAGE
from pisc_runs.summary import RunSummary, summarise_bag
from pisc_sim.configuration import write_params_file

__all__ = ["GraphError", "RecorderDied", "RunOptions", "RunResult", "not_finished",
           "recorded_counts", "run_graph"]


@dataclass(frozen=True)
class RunResult:
    bag_dir: Path
    summary: RunSummary
    recorded: dict[str, int]  # messages per topic, as pisc_record reported on closing
    wall_s: float
    processes: list[str]  # executables started with --processes
    # messages per topic the nodes of this process published (empty with --processes);
    # with --processes in lockstep, what the samples of the run make (expected_messages)
    published: dict[str, int] = field(default_factory=dict)
    experiment: str = "none"  # experiment.kind: an identification run, not a swing-up
    # wall time from the first voltage this runner saw (its nodes published it, or with
    # --processes it received it) to the one ending the run:
    # the loop itself, without start-up and finishing the bag (lockstep: its speed), and
    # the CPU time this process used meanwhile (all its threads; the nodes in one process)
    loop_s: float | None = None
    loop_cpu_s: float | None = None

    @property
    def missing(self) -> dict[str, int]:
        """Messages per recorded topic that were published and the bag does not hold:
        this process's nodes' own count against the recorder's, or with --processes in
        lockstep a message of each sample topic per sample (:func:`expected_messages`);
        empty for a --processes run on the wall clock, which nothing here counts."""
        return {topic: sent - self.recorded[topic] for topic, sent in self.published.items()
                if topic in self.recorded and self.recorded[topic] < sent}


def run_graph(options: RunOptions) -> RunResult:
    """Run, record and summarise; raises ConfigError, BagError or GraphError.

    Every configuration error is raised before the recorder starts, so a refused run
    leaves no bag directory behind.
    """
    config, flat, plant_params = checked_config(options)
    bag_dir = options.bag_dir or default_bag_dir(options)
    if bag_dir.exists() and any(bag_dir.iterdir()):
        raise BagError(f"{bag_dir}: exists and is not empty; not overwriting a bag")
    run = _Run(options, config, flat, plant_params, bag_dir, plan_run(options, flat, plant_params))
    run.start_recorder()
    run.start_watching()
    run.interrupt.install()
    try:
        run.interrupt.armed = True  # a signal from now until the spin raises KeyboardInterrupt
        if run.interrupt.signum is not None:
            raise KeyboardInterrupt
        run.start_graph()
        run.spin()
    except KeyboardInterrupt:  # a signal while the run started (Interrupt): a clean end
        pass
    finally:
        run.stop()
    return run.result()


class _Run:
    """One run of :func:`run_graph`, step by step: the recorder (and the Foxglove bridge),
    the runner's own node and what it watches, the graph's nodes (in this process or as
    processes), the spin to the end, the stop, and the verdict."""

    def __init__(self, options: RunOptions, config: Any, flat: dict[str, Any],
                 plant_params: dict[str, Any], bag_dir: Path, plan: RunPlan) -> None:
        self.options, self.config, self.bag_dir, self.plan = options, config, bag_dir, plan
        self.flat, self.plant_params = flat, plant_params
        self.lockstep = options.clock == "lockstep"
        self.driver = options.driver_port is not None
        self.period_s = config.loop.period_s
        self.children: list[subprocess.Popen] = []
        self.nodes: list[Node] = []
        self.alarms: list[ExitAlarm] = []  # started once the executor is there
        self.executor: Any = None
        self.tap: VoltageTap | None = None
        self.bridge: subprocess.Popen | None = None
        self.published: dict[str, int] = {}
        self.finished = False
        self.interrupt = Interrupt()  # SIGINT, SIGTERM: a clean end (run_guard)

    def start_recorder(self) -> None:
        """The Foxglove bridge on request (refused, a port in use, before the bag exists),
        then the recorder, which never runs under --realtime: it must not take the CPU
        from the loop."""
        self.started = time.monotonic()
        # the recorder announces in this file that it has matched every publisher of the
        # run; ``foreign`` is the runner's word to the recorder (run_guard)
        self.ready_dir = tempfile.TemporaryDirectory(prefix="pisc_graph-")
        scratch = Path(self.ready_dir.name)
        self.ready, self.marks = scratch / "recorder-ready", scratch / "foreign"
        port = self.options.foxglove_port
        if port is not None:
            from pisc_runs import foxglove_node

            write_params_file(scratch / "foxglove.yaml", self.flat)
            bridge = self.bridge = spawn(foxglove_node.command(port, scratch / "foxglove.yaml"),
                                         self.plan.env, subprocess.PIPE)
            try:
                foxglove_node.wait_serving(bridge, port, lambda: stderr_of(bridge))
            except ConfigError:
                self.ready_dir.cleanup()
                raise
        self.recorder_name = f"pisc_record_{os.getpid()}"
        self.recorder = spawn(
            recorder_args(self.options, self.plan, self.bag_dir, self.ready, self.marks,
                          self.recorder_name),
            self.plan.env, subprocess.PIPE, batch_scheduling=True)

    def start_watching(self) -> None:
        """The runner's node, how it follows the run's voltages and sees the recorder die,
        and the guard against other publishers, a lost port and signals (run_guard)."""
        options = self.options
        self.context = Context()
        rclpy.init(context=self.context, domain_id=options.domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        progress = self.progress = Progress(options.duration_s)
        watch = self.watch = RecorderWatch(self.recorder, progress)
        watcher = self.watcher = Node("pisc_graph", context=self.context)
        self.guard = RunGuard(watcher, self.plan.graph, self.plan.recorded, self.lockstep,
                              self.interrupt, progress.end, self.run_time,
                              options.port_retry_s, options.duration_s,
                              lambda: progress.first_wall if not options.processes else None)
        if not options.processes:
            # The current loop is in this process: its voltages are followed as it
            # publishes them (count_publications), not through a subscription of the
            # runner's, which was one more delivery and callback each cycle; the
            # recorder's exit is seen as it happens, not looked for (a timer each period
            # cost the process 2-4 % of a core on the wall clock, docs/soak.md)
            self.alarms.append(ExitAlarm(watcher, [self.recorder], watch.check))
            return
        tap = self.tap = VoltageTap(watcher, progress)

        def on_period() -> None:
            tap.drain()
            watch.check()

        watcher.create_timer(self.period_s, on_period)

    def run_time(self) -> str:
        return self.progress.run_time(self.progress.last_ns)

    def start_graph(self) -> None:
        """The graph's nodes, once the recorder has subscribed: the bag's parameter files
        written (a bag says what was simulated, model error or not: plant_params.yaml),
        the launch file read again with them, each node's inputs pinned to the graph's
        publishers (run_guard); then the nodes, in processes or in this one."""
        wait_for(lambda: recorder_ready(self.watcher, self.recorder, self.plan.recorded,
                                        self.recorder_name), 30.0, "pisc_record to subscribe")
        files = write_params(self.bag_dir, self.flat,
                             None if self.driver else self.plant_params)
        graph = read_again(self.plan.graph, self.options, files, self.plan.run_args)
        graph = pin_publishers(graph, self.recorder_name, self.lockstep)
        if self.options.processes:
            self._start_processes(graph)
        else:
            self._start_in_process(graph)
        if not self.options.processes:
            def on_voltage(data: bytes) -> None:
                self.progress(VOLTAGE.name, data)

            self.published = count_publications(self.nodes, on_voltage)
        elif self.lockstep and not self.driver:
            self.published = expected_messages(self.options.duration_s, self.period_s,
                                               self.plan.recorded)

    def _start_processes(self, graph: Graph) -> None:
        env, recorded = self.plan.env, self.plan.recorded
        self.children = start_processes(graph, self.watcher, env, recorded,
                                        source_waits=self.lockstep)
        for node in graph.observers:  # the lockstep plant starts once the recorder matched it
            self.children.insert(0, spawn(awaiting(node, (), recorded).command(), env,
                                          subprocess.DEVNULL))
        # a node process that dies ends the run at once; the plant's watchdog has zeroed
        # the motor, and stop() names the process
        self.alarms.append(DeathWatch(self.watcher, self.children, self.progress).alarm)
        wait_for(lambda: recorder_matched(self.recorder, self.ready), 30.0,
                 "pisc_record to match every publisher")
        if self.lockstep:  # the plant's last awaited subscriber: it may start now
            self.watcher.create_subscription(message_class(CLOCK.type), CLOCK.name,
                                             lambda data: None, qos_profile(CLOCK.qos),
                                             raw=True)
        # the runner only watches here, but a SingleThreadedExecutor took 37 % of a core
        # doing it (two messages a cycle) from the nodes' two cores; the EventsExecutor
        # 11 % (docs/figures.md)
        self.executor = EXECUTORS[self.options.executor](context=self.context)

    def _start_in_process(self, graph: Graph) -> None:
        nodes, context = self.nodes, self.context
        for node in graph.controllers:
            nodes.append(node.instantiate(context))
        for node in graph.observers:  # before the plant, which stays last: it is stopped
            nodes.append(node.instantiate(context))  # first
        # DDS matches in its own threads: no spinning is needed to wait for it.
        wait_for(lambda: controllers_matched(nodes, self.plan.recorded, graph.controllers),
                 30.0, "the graph to connect")
        if self.driver:
            # the driver in a process of its own: a crash of this one (the controllers')
            # leaves it to zero the motor (docs/safety.md)
            self.children = [spawn(graph.source.command(), self.plan.env, subprocess.DEVNULL)]
            self.alarms.append(DeathWatch(self.watcher, self.children, self.progress).alarm)
        else:
            nodes.append(graph.source.instantiate(context))
        # nothing is sent before the executor spins: by then the recorder takes it all
        wait_for(lambda: recorder_matched(self.recorder, self.ready), 30.0,
                 "pisc_record to match every publisher")
        # The executor spins in the main thread: an EventsExecutor spun from another
        # thread holds the interpreter lock and starves the rest of the process.
        self.executor = EXECUTORS[self.options.executor](context=context)

    def spin(self) -> None:
        """Spin until the voltage answering the sample at the duration, the wall-clock
        limit, or an end the guard or a watch calls; then wait for the recorder to
        acknowledge what is still in flight (the plant stops with the last sample)."""
        progress, timeout = self.progress, self.plan.timeout_s
        # An EventsExecutor kept busy (a lockstep run in this process) does not return at
        # its timeout (test_graph.py): a timer ends the wait at the limit.
        deadline = time.monotonic() + timeout

        def at_the_limit() -> None:
            if time.monotonic() > deadline:
                progress.end()

        self.watcher.create_timer(min(1.0, timeout / 4), at_the_limit)
        for node in [*self.nodes, self.watcher]:
            self.executor.add_node(node)
        for alarm in self.alarms:
            alarm.start(self.executor)
        freeze_startup_objects()
        self.interrupt.armed = False  # while spinning, the guard's timer looks at the signal
        if self.interrupt.signum is None:
            self.executor.spin_until_future_complete(progress.future, timeout)
        self.finished = progress.done.is_set() and not self.guard.ended
        limit = 30.0 + self.options.duration_s
        if self.watch.returncode is None and not wait_acknowledged(self.nodes, limit):
            print("pisc_graph: the recorder did not acknowledge every message within "
                  f"{limit:.0f} s; the bag may miss the last ones", file=sys.stderr)

    def stop(self) -> None:
        """The source first (0 V), then the other nodes, the runner's own, the recorder
        (which finishes the bag) and the bridge."""
        self.interrupt.armed = False
        # what was frozen is garbage again once the run is over (a process that runs
        # graphs one after another, as the tests do, would otherwise keep every frozen
        # object, nodes left undestroyed in reference cycles with their DDS endpoints)
        gc.unfreeze()
        for alarm in self.alarms:  # (the children's exits below are the run's end, not news)
            alarm.close()
        # the plant first, so the controllers see no sample after their peers stopped
        self.failures = stop_all(self.children)
        leave_realtime()  # before any node or participant is destroyed (base_node)
        if self.tap is not None:
            self.tap.destroy()
        # the executor lets go of the nodes' entities while they live (a RecorderDied's
        # traceback kept it alive past the context's shutdown, and freeing it then
        # crashed pisc_graph, SIGSEGV in EventHandler.__exit__, once on 2026-12-04)
        if self.executor is not None:
            self.executor.shutdown()
        for node in [*reversed(self.nodes), self.watcher]:  # the plant or driver first: 0 V
            node.destroy_node()
        self.context.try_shutdown()
        self.guard.tell(self.marks)  # before the recorder finishes the bag
        self.recorder_problem, self.recorder_output = stop(self.recorder)
        if self.bridge is not None:
            stop(self.bridge, hang_is_failure=False)
        self.ready_dir.cleanup()
        self.interrupt.restore()

    def result(self) -> RunResult:
        """The run's result, or the exception that says how it ended otherwise."""
        bag_dir, period_s, problem = self.bag_dir, self.period_s, self.recorder_problem
        failed = [f for f in self.failures if f]
        said = "; ".join(x for x in [*failed, problem.partition(": ")[2].strip()] if x)
        if self.watch.returncode is not None:
            raise _recorder_died(
                f"pisc_record {exit_description(self.watch.returncode)} "
                f"{self.watch.run_time()} of the run; the run was stopped there"
                f"{' and the rig left at 0 V' if self.driver else ''}", bag_dir, period_s, said)
        stopped = _stopped_by(self.guard, self.interrupt, self.run_time(), bag_dir, period_s,
                              problem)
        if stopped is not None:
            raise stopped
        if problem and self.finished and not failed:  # it died finishing the bag
            raise _recorder_died(
                f"pisc_record {exit_description(self.recorder.returncode)} after the run, "
                "while finishing the bag", bag_dir, period_s, said)
        if failed:
            raise GraphError("; ".join(failed))
        if problem:
            raise GraphError(f"pisc_record failed: {problem}")
        recorded = recorded_counts(self.recorder_output)
        if not self.finished:
            raise GraphError(not_finished(self.options.duration_s, self.plan.timeout_s,
                                          self.progress.last_ns, recorded))
        wall = time.monotonic() - self.started
        summary = summarise_bag(bag_dir, period_s)
        started_as = [Path(c.args[0]).name for c in self.children]
        result = RunResult(bag_dir, summary, recorded, wall, started_as, dict(self.published),
                           self.config.supervisor.experiment.kind, self.progress.loop_s,
                           self.progress.loop_cpu_s)
        for topic, lost in result.missing.items():
            print(f"pisc_graph: the bag misses {lost} of the {self.published[topic]} "
                  f"messages published on {topic}", file=sys.stderr)
        return result


def _recorder_died(what: str, bag_dir: Path, period_s: float,
                   recorder_error: str) -> RecorderDied:
    """Finish the bag of a run whose recorder died, as ``pisc_bag repair`` does."""
    lines = [what]
    if recorder_error:
        lines.append(f"pisc_record said: {recorder_error}")
    repair, summary = None, None
    try:
        repair = repair_bag(bag_dir)
    except BagError as exc:
        lines.append(f"`pisc_bag repair {bag_dir}` could not finish the bag: {exc}")
    else:
        lines.append(f"the bag was finished with what was recorded, as `pisc_bag repair "
                     f"{bag_dir}` does: {repair.recovered} messages"
                     + (f"; the recorder's file as found is kept as {repair.backup.name}"
                        if repair.backup is not None else ""))
        try:
            summary = summarise_bag(bag_dir, period_s)
        except BagError as exc:
            lines.append(f"no summary: {exc}")
    return RecorderDied("\n".join(lines), bag_dir, summary, repair)


def _stopped_by(guard: RunGuard, interrupt: Interrupt, run_time: str, bag_dir: Path,
                period_s: float, recorder_problem: str) -> RunStopped | None:
    """What ended a run before its duration (:mod:`pisc_bringup.run_guard`), as the
    exception pisc_graph reports, with the summary of the bag (None: nothing ended it)."""
    if interrupt.signum is not None:
        what, status = (f"interrupted {run_time} by {interrupt.name}",
                        128 + interrupt.signum)
    elif guard.foreign:
        what, status = (f"another publisher than the graph's {run_time}: "
                        + "; ".join(guard.foreign), EXIT_FOREIGN)
    elif guard.port_lost is not None:
        what, status = (f"{guard.port_lost} went away and did not come back; the run "
                        f"ended {run_time}", EXIT_PORT_LOST)
    else:
        return None
    summary = None
    lines = [what]
    if recorder_problem:
        lines.append(f"pisc_record: {recorder_problem}")
    try:
        summary = summarise_bag(bag_dir, period_s)
        if guard.foreign:
            summary = replace(summary, foreign=[*summary.foreign, *(
                f for f in guard.foreign if f not in summary.foreign)])
    except BagError as exc:
        lines.append(f"no summary: {exc}")
    return RunStopped("\n".join(lines), status, bag_dir, summary)


def not_finished(duration_s: float, timeout_s: float, last_ns: int | None,
                 recorded: dict[str, int]) -> str:
    """Why a run ended without its last voltage: the newest voltage it saw and what the
    recorder wrote of each topic (a run that stood still waiting for the recorder shows
    the topic it lacked)."""
    wrote = (f"the recorder wrote {', '.join(f'{t} {n}' for t, n in recorded.items())}"
             if recorded else "the recorder said nothing of what it wrote")
    return (f"the run did not reach {duration_s} s within {timeout_s:g} s of wall time "
            f"(last voltage stamp: {last_ns}); {wrote}")


def recorded_counts(output: str) -> dict[str, int]:
    """What pisc_record said it wrote, from its standard output: one line ``TOPIC COUNT``
    for each topic. Other lines are Fast DDS's log, which writes there too (a profile it cannot
    read, say); before 2026-12-03 such a line ended the run with a ValueError."""
    counts = {}
    for line in output.splitlines():
        topic, _, count = line.rpartition(" ")
        if topic.startswith("/") and " " not in topic and count.isdigit():
            counts[topic] = int(count)
    return counts

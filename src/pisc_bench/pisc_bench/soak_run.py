"""The soak's run: the load, the virtual rig, the outside observer, the machine probes and
``pisc_graph`` started, sampled once a second, the faults sent, all stopped
(:func:`run`); what happened is a :class:`RunRecord` for :mod:`pisc_bench.soak_report`."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pisc_bench.machine_probe import ProbeRun, Probes
from pisc_bench.soak_faults import DROP_RATE, fault_schedule
from pisc_bench.soak_figures import PERIOD_S, Sample
from pisc_bench.soak_options import SoakOptions, start_load, stop_load
from pisc_bench.soak_proc import Monitor, read_proc
from pisc_msgs_py.processes import console_command, stop_child

__all__ = ["RunRecord", "run"]

PROBE_MARGIN_S = 120.0  # a machine probe stops by itself this long after the run's end


@dataclass
class RunRecord:
    """What happened while the graph ran, for the report."""

    graph_status: int
    graph_output: str
    monitor: Monitor
    sent: list[tuple[float, dict[str, Any]]] = field(default_factory=list)  # unix, request
    first_command_unix: float | None = None
    rig_final: dict[str, Any] = field(default_factory=dict)
    observed: dict[str, list[int]] | None = None
    observer_samples: list[Sample] = field(default_factory=list)
    probes: list[ProbeRun] | str = field(default_factory=list)  # or why there are none


def run(options: SoakOptions, out: Path, domain_id: int,
        say: Callable[[str], None]) -> RunRecord:
    """Start the rig (and observer), run pisc_graph, sample, inject faults; stop all."""
    from pisc_sim.configuration import config_path
    from pisc_plant.rig_process import RigProcess

    from pisc_bringup.dds import dds_environment

    env = dds_environment(dict(os.environ))  # what pisc_graph gives its processes
    env["ROS_DOMAIN_ID"] = str(domain_id)
    schedule = fault_schedule(options.seed, options.duration_s) if options.faults else None
    rig = observer = graph = probes = None
    graph_log = (out / "graph.log").open("w")
    load: list[subprocess.Popen] = []
    try:
        if options.load:
            load = start_load(options.load)
            say(f"load: {len(load)} busy loops, one per CPU")
        if options.faults:
            observer = subprocess.Popen(
                [sys.executable, "-m", "pisc_bench.soak_observer_node",
                 str(out / "observer.json"), "--domain-id", str(domain_id)],
                env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            if observer.stdout.readline().strip() != "loaded":
                raise RuntimeError("the outside observer did not start")
        command = [*console_command("pisc_graph", "pisc_bringup.graph_cli"), "--clock", "wall",
                   "--duration", f"{options.duration_s:g}", "--bag", str(out / "bag"),
                   "--domain-id", str(domain_id)]
        if options.driver:
            rig_args = ["--params-file", str(config_path("default")), "--x0", "0.0",
                        "--seed", str(options.seed)]
            if options.faults:
                rig_args += ["--drop-rate", f"{DROP_RATE:g}"]
            if options.realtime:
                rig_args += ["--realtime", str(options.realtime + 10)]
            rig = RigProcess(rig_args, env=env)
            command += ["--driver", rig.device]
        if options.realtime:
            command += ["--realtime", str(options.realtime)]
        # the machine's own latency beside the run, one bare timer loop per CPU, just above
        # the graph's priority (machine_probe; started before the graph, stopped after)
        probes = Probes(out, options.realtime + 1 if options.realtime else 0, PERIOD_S,
                        options.duration_s + PROBE_MARGIN_S)
        say("running: " + " ".join(command))
        graph = subprocess.Popen(command, env=env, stdout=graph_log,
                                 stderr=subprocess.STDOUT)
        monitor = Monitor(graph.pid)
        record = RunRecord(0, "", monitor)
        if rig is not None:
            monitor.add("virtual rig", rig.process.pid)
        pending = schedule.requests() if schedule is not None else []
        next_sample = time.monotonic()
        next_look = time.monotonic()
        while graph.poll() is None:
            now = time.monotonic()
            if now >= next_sample:
                monitor.sample()
                if observer is not None:
                    seen = read_proc(observer.pid)
                    if seen is not None:
                        record.observer_samples.append(Sample(time.time(), *seen))
                next_sample += 1.0
            if rig is not None and pending and record.first_command_unix is None \
                    and now >= next_look:
                next_look = now + 0.05
                if rig.status()["bytes_received"] > 0:
                    record.first_command_unix = time.time()
                    if observer is not None:  # the driver has published: it may look
                        observer.stdin.write("subscribe\n")
                        observer.stdin.flush()
                        if observer.stdout.readline().strip() != "ready":
                            raise RuntimeError("the outside observer did not subscribe")
            if record.first_command_unix is not None and pending:
                due = record.first_command_unix + pending[0][0]
                if time.time() >= due:
                    _, request = pending.pop(0)
                    rig.request(**request)
                    record.sent.append((time.time(), request))
            time.sleep(0.005 if pending else 0.05)  # a fault due, else only the samples
        record.graph_status = graph.returncode
        if observer is not None:
            time.sleep(1.0)  # what is still in flight reaches the observer
    except BaseException:
        if graph is not None and graph.poll() is None:
            graph.send_signal(signal.SIGINT)
            try:
                graph.wait(timeout=60)
            except subprocess.TimeoutExpired:
                graph.kill()
        raise
    finally:
        stop_load(load)
        if probes is not None:
            try:
                probe_runs: list[ProbeRun] | str = probes.stop()
            except ValueError as exc:
                probe_runs = str(exc)
        if observer is not None:
            stop_child(observer, signal.SIGTERM)
        if rig is not None:
            final = rig.stop()
        graph_log.close()
    record.graph_output = (out / "graph.log").read_text()
    record.probes = probe_runs or "no machine probe finished"
    if rig is not None:
        record.rig_final = final
    if observer is not None and (out / "observer.json").exists():
        record.observed = json.loads((out / "observer.json").read_text())
    return record

"""How fast the lockstep graph runs, beside a bare rclpy ping-pong measured in the same run.

    python -m pisc_bench.lockstep_bench_cli [--duration S] [--repeat N] [--hops N]
                                              [--no-processes] [--no-anchors]
                                              [--no-graph] [--json FILE]

**Anchors.** Two nodes in one process on an ``EventsExecutor`` pass a ``JointState``
back and forth on two topics (publish, spin until the other's callback ran): the cost of
one hop, once with rclpy message objects and once as bytes (:mod:`pisc_msgs_py.cdr`,
taken raw), each alone and with a KEEP_ALL reliable reader of both topics in another
process (what the recorder is to the graph). The figures are wall and CPU time (this
process, all its threads) per hop.

**The graph.** ``pisc_graph --duration S`` in one process and with ``--processes``
(:func:`pisc_bringup.graph.run_graph`, recorder included, a bag in a scratch directory),
``--repeat`` times each: the loop's wall time (first voltage to the one ending the run),
its CPU time in the graph's process (one process only), the whole run's wall time
(start-up, the recorder's matching and the bag's finish included), and whether the bag
holds every message the nodes published. Each line says how many anchor hops a cycle
costs. The machine is shared: run it with ``uptime`` beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from pisc_msgs_py.topics import CLOCK, JOINT_STATES

__all__ = ["main", "ping_pong"]

PING, PONG = "/pisc_bench/ping", "/pisc_bench/pong"


def _reader(ready: Path) -> int:
    """The other process's KEEP_ALL reliable reader of both topics (raw), until stopped."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from pisc_msgs_py.base_node import message_class

    rclpy.init()
    node = Node("pisc_bench_reader")
    qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    for topic in (PING, PONG):
        node.create_subscription(message_class(JOINT_STATES.type), topic, lambda _: None,
                                 qos, raw=True)
    ready.touch()
    executor = EventsExecutor()
    executor.add_node(node)
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    return 0


def ping_pong(hops: int, as_bytes: bool, reader: bool, domain_id: int) -> tuple[float, float]:
    """(wall, CPU) seconds per hop of a ping-pong between two nodes of this process."""
    import rclpy
    from rclpy.context import Context
    from rclpy.experimental import EventsExecutor
    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from pisc_msgs_py.base_node import message_class
    from pisc_msgs_py.convert import joint_sample_from_msg, joint_sample_to_cdr, \
        joint_sample_to_msg
    from pisc_msgs_py.cdr import decode_joint_state
    from pisc_msgs_py.types import JointSample

    child = None
    scratch = tempfile.TemporaryDirectory(prefix="pisc_bench-")
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    if reader:
        ready = Path(scratch.name) / "ready"
        child = subprocess.Popen([sys.executable, "-m", "pisc_bench.lockstep_bench_cli",
                                  "--reader", str(ready)], env=env)
        while not ready.exists():
            if child.poll() is not None:
                raise RuntimeError("the reader process exited")
            time.sleep(0.01)
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        a, b = Node("pisc_bench_a", context=context), Node("pisc_bench_b", context=context)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE)
        joint_state = message_class(JOINT_STATES.type)
        ping, pong = (a.create_publisher(joint_state, PING, qos),
                      b.create_publisher(joint_state, PONG, qos))
        encode: Callable[[JointSample], object] = (joint_sample_to_cdr if as_bytes
                                                   else joint_sample_to_msg)

        def decode(msg: object) -> JointSample:
            return joint_sample_from_msg(decode_joint_state(msg) if as_bytes else msg)

        got = [0]

        def on_ping(msg: object) -> None:
            pong.publish(encode(decode(msg)))

        def on_pong(msg: object) -> None:
            decode(msg)
            got[0] += 1

        b.create_subscription(joint_state, PING, on_ping, qos, raw=as_bytes)
        a.create_subscription(joint_state, PONG, on_pong, qos, raw=as_bytes)
        executor = EventsExecutor(context=context)
        executor.add_node(a)
        executor.add_node(b)
        want = 1 + reader
        deadline = time.monotonic() + 30.0
        while min(ping.get_subscription_count(), pong.get_subscription_count()) < want:
            if time.monotonic() > deadline:
                raise RuntimeError("the ping-pong's readers did not match within 30 s")
            time.sleep(0.01)
        time.sleep(0.5)  # a reader matches its writers a little after they match it

        def rounds(n: int) -> None:
            for k in range(n):
                ping.publish(encode(JointSample(k * 5_000_000, 0.1, 3.0)))
                target = got[0] + 1
                while got[0] < target:
                    executor.spin_once(timeout_sec=1.0)

        rounds(100)
        wall, cpu = time.perf_counter(), time.process_time()
        rounds(hops // 2)
        n = 2 * (hops // 2)
        return (time.perf_counter() - wall) / n, (time.process_time() - cpu) / n
    finally:
        context.try_shutdown()
        if child is not None:
            child.terminate()
            child.wait(timeout=10)
        scratch.cleanup()


def _graph(duration_s: float, processes: bool, domain_id: int) -> dict[str, float | bool]:
    from pisc_bringup.graph import RunOptions, run_graph
    from pisc_plant.plant_node import SimulationParams

    with tempfile.TemporaryDirectory(prefix="pisc_bench-") as scratch:
        result = run_graph(RunOptions(duration_s=duration_s, processes=processes,
                                      bag_dir=Path(scratch) / "bag", domain_id=domain_id))
    # one process: what its nodes published, topic by topic; processes: a message of each
    # sample topic per sample (graph.expected_messages), and /clock every clock_every
    complete = (not result.missing and (not processes or result.recorded.get(CLOCK.name, 0)
                                        >= -(-result.summary.cycles
                                             // SimulationParams().clock_every)))
    return {"loop": result.loop_s or float("nan"),
            "cpu": result.loop_cpu_s if not processes else float("nan"),
            "wall": result.wall_s, "messages": float(sum(result.recorded.values())),
            "complete": complete, "cycles": float(result.summary.cycles)}


def _median(values: list[float]) -> float:
    return statistics.median(values)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lockstep_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=10.0, help="simulated s per run")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each layout")
    parser.add_argument("--hops", type=int, default=4000, help="hops per anchor")
    parser.add_argument("--no-processes", action="store_true", help="skip --processes")
    parser.add_argument("--no-anchors", action="store_true", help="skip the ping-pongs")
    parser.add_argument("--no-graph", action="store_true", help="the ping-pongs only")
    parser.add_argument("--json", type=Path, metavar="FILE",
                        help="also write the figures to FILE (for pisc_bench)")
    parser.add_argument("--reader", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.reader is not None:
        return _reader(args.reader)
    if args.repeat < 1 or args.hops < 2 or not args.duration > 0:
        parser.error("--repeat >= 1, --hops >= 2 and --duration > 0")
    from pisc_bringup.dds import dds_environment
    from pisc_msgs_py.processes import DomainClaim

    # the graph's own DDS environment (Fast DDS profile), as pisc_graph gives it to its
    # nodes, before this process's first participant
    dds_environment(os.environ)

    def claimed(run: Callable[[int], object]) -> object:
        claim = DomainClaim()
        try:
            return run(claim.domain_id)
        finally:
            claim.release()

    print(f"lockstep_bench {time.strftime('%Y-%m-%d %H:%M:%S %Z')}, load "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    hop = float("nan")
    figures: dict[str, object] = {"duration_s": args.duration, "anchors": {}, "graph": {}}
    if not args.no_anchors:
        for as_bytes in (False, True):
            for reader in (False, True):
                wall, cpu = claimed(lambda d: ping_pong(args.hops, as_bytes, reader, d))
                if as_bytes and reader:
                    hop = wall
                figures["anchors"][f"{'bytes' if as_bytes else 'objects'}"
                                   f"{'_reader' if reader else ''}"] = {"wall_s": wall,
                                                                         "cpu_s": cpu}
                print(f"anchor: ping-pong, {'bytes (raw)' if as_bytes else 'message objects'}"
                      f"{', KEEP_ALL reader in another process' if reader else ''}: "
                      f"{wall * 1e6:6.1f} us per hop wall, {cpu * 1e6:6.1f} us CPU", flush=True)
    for processes in (False, True):
        if args.no_graph or (processes and args.no_processes):
            continue
        runs = [claimed(lambda d: _graph(args.duration, processes, d))
                for _ in range(args.repeat)]
        loops = [r["loop"] for r in runs]
        cycles = runs[0]["cycles"]
        loop = _median(loops)
        layout = "--processes" if processes else "one process"
        cpu = "" if processes else f", CPU {_median([r['cpu'] for r in runs]):.2f} s"
        per_hop = (f", a cycle = {loop / cycles / hop:.1f} anchor hops" if hop == hop else "")
        print(f"graph, {layout}: {args.duration:g} s simulated, loop {loop:.2f} s wall "
              f"(median of {len(runs)}: {', '.join(f'{x:.2f}' for x in loops)}; "
              f"{loop / cycles * 1e6:.0f} us per cycle, {args.duration / loop:.1f}x real "
              f"time{cpu}{per_hop}); whole run {_median([r['wall'] for r in runs]):.1f} s; "
              f"{int(runs[0]['messages'])} messages recorded, "
              f"{'every one published' if all(r['complete'] for r in runs) else 'SOME MISSING'}",
              flush=True)
        figures["graph"]["processes" if processes else "one_process"] = {
            "loop_s": loop, "loops_s": loops, "cycles": cycles,
            "cpu_s": None if processes else _median([r["cpu"] for r in runs]),
            "wall_s": _median([r["wall"] for r in runs]),
            "messages": int(runs[0]["messages"]),
            "complete": all(bool(r["complete"]) for r in runs)}
    if args.json is not None:
        args.json.write_text(json.dumps(figures) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

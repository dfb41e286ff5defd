"""pisc_record: record graph topics to a rosbag2 MCAP bag until SIGINT or SIGTERM.

    pisc_record --bag DIR [--topic NAME ...] [--ready-file PATH [--expect NAME=N ...]]
                [--progress NAME] [--gather S]

A process of its own, so recording competes with the control loop for nothing but a
CPU core. Every message is written as soon as it is taken (:mod:`pisc_bag.
recorder_node`), unchunked, and handed to the operating system at once. On SIGINT or
SIGTERM it first takes what DDS still holds for it (until nothing has arrived for
``--drain`` seconds), then finishes the bag: the file rewritten indexed and in
log-time order, then ``metadata.yaml`` (:mod:`pisc_bag.bag`), and prints the
message count of every topic and how long the finish took. Killed, even with SIGKILL,
the bag keeps every message written so far, all but those of about the last wake-up,
and ``pisc_bag repair`` finishes it.

``--ready-file PATH`` creates PATH once every subscription has matched its publishers
(at least one each, or the N of ``--expect NAME=N``). A publisher sees the recorder
before the recorder sees the publisher; what it sends in between reaches the recorder
only while it is still in the publisher's history (100 messages), so a runner that
must lose nothing starts its graph after this file exists.

``--progress NAME`` (repeatable: the recorded topics published every sample) publishes
on ``/pisc/recorder/progress`` the oldest of the newest stamps written to the bag of each
of them, after every 5 samples' worth: a lockstep plant with
``simulation.recorder_lag_samples`` waits on it (pisc_graph passes each sample topic of
the run; :mod:`pisc_bag.recorder_node`).

``--gather S``: after writing what it took, the recorder lets messages gather for S
seconds before it waits for more, so it wakes once for several of them, not for each
(default 0: it takes each as it comes). Killed, it then also loses what arrived in those
S seconds. pisc_graph passes 1 ms in lockstep, where the plant waits for the recorder's
progress and a recorder woken for every message took 40 % of a core of the two a
``--processes`` run shares (docs/figures.md); on the wall clock it passes nothing.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

import rclpy
from rclpy.signals import SignalHandlerOptions

from pisc_bag.bag import BagError, BagWriter
from pisc_bag.recorder_node import RecorderNode
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.topics import GRAPH_TOPICS, graph_topics_named

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="pisc_record", description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", type=Path, required=True, help="new bag directory")
    parser.add_argument("--topic", action="append", default=[],
                        help="topic to record (default: every topic of the graph)")
    parser.add_argument("--drain", type=float, default=0.2,
                        help="on SIGINT/SIGTERM, keep taking messages until none arrived for "
                             "this long [s] (default 0.2)")
    parser.add_argument("--ready-file", type=Path,
                        help="create this file once every subscription has matched its "
                             "publishers (see --expect)")
    parser.add_argument("--expect", action="append", default=[], metavar="NAME=N",
                        help="with --ready-file: publishers topic NAME must have matched "
                             "(default 1 per topic; 0 for a topic nothing publishes yet)")
    parser.add_argument("--own", metavar="NODE", action="append", default=[],
                        help="with --expect: a node of the run (repeatable); once ready, a "
                        "topic with more publishers than --expect says is marked in the bag "
                        "(/pisc/recorder/foreign), naming those of other nodes")
    parser.add_argument("--marks-file", type=Path, metavar="PATH",
                        help="with --expect: before finishing the bag, mark in it each "
                        "'TOPIC<tab>publishers' line of this file, if it exists (the "
                        "runner's own word on foreign publishers)")
    parser.add_argument("--progress", metavar="NAME", action="append", default=[],
                        help="a recorded topic published every sample (repeatable): publish "
                             "the oldest of the newest stamps written of each on "
                             "/pisc/recorder/progress (a lockstep plant waits on it)")
    parser.add_argument("--gather", type=float, default=0.0, metavar="S",
                        help="after writing what it took, let messages gather for S seconds "
                             "before taking more (fewer wake-ups; a kill also loses what "
                             "arrived in them); default 0")
    return parser


def main(argv: list[str] | None = None) -> int:
    args, ros_args = _parser().parse_known_args(argv)
    try:
        if not 0.0 <= args.gather < 1.0:  # also refuses nan
            raise ValueError(f"--gather {args.gather}: must be a number of seconds >= 0 "
                             "and < 1")
        topics = list(graph_topics_named(args.topic) if args.topic else GRAPH_TOPICS)
        expected = _expected_publishers(args.expect, [t.name for t in topics], args.ready_file)
        for name in args.progress:
            if name not in {t.name for t in topics}:
                raise ValueError(f"--progress {name}: not a recorded topic (recorded: "
                                 f"{', '.join(t.name for t in topics)})")
    except (ConfigError, ValueError) as exc:
        print(f"pisc_record: {exc}", file=sys.stderr)
        return 2
    try:
        writer = BagWriter(args.bag, topics)
    except BagError as exc:
        print(f"pisc_record: {exc}", file=sys.stderr)
        return 2
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, frame: stop.append(signum))
    # rclpy's own handlers would shut the context down at once, dropping what DDS holds
    rclpy.init(args=[sys.argv[0], *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = RecorderNode(writer, topics, progress=args.progress)
    try:
        while not stop:
            if node.take(0.1 if expected is None else 0.01) and args.gather:
                time.sleep(args.gather)
            if expected is not None and all(
                    node.publisher_count(name) >= n for name, n in expected.items()):
                args.ready_file.touch()
                if args.expect:  # the run's publishers: more are marked in the bag
                    node.expect_publishers(expected, args.own)
                expected = None
        # drain: take what has arrived but not been taken, until the graph is quiet
        quiet_since = time.monotonic()
        while time.monotonic() - quiet_since < args.drain:
            if node.take(0.01):
                quiet_since = time.monotonic()
    finally:
        node.close_marks(_told(args.marks_file))
        node.destroy_node()
        rclpy.try_shutdown()
        failed = None
        try:
            node.close()  # finish the bag: seconds for a long one, after DDS is done
        except BagError as exc:
            failed = exc
    try:
        if failed is not None:
            print(f"pisc_record: {failed}", file=sys.stderr)
            return 1
        for name, count in writer.counts.items():
            print(f"{name} {count}")
        sys.stdout.flush()
        for foreign in node.foreign:
            print(f"pisc_record: marked in the bag: another publisher on {foreign}",
                  file=sys.stderr)
        print(f"pisc_record: finished {args.bag} in {writer.finish_s:.2f} s (indexed, in "
              "log-time order)", file=sys.stderr)
    except BrokenPipeError:
        # the runner that reads this is gone (killed): the bag is whole all the same, and
        # Python would raise again flushing at exit: what is left goes nowhere
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.dup2(devnull, sys.stderr.fileno())
    return 0 if failed is None else 1


def _told(path: Path | None) -> list[tuple[str, str]]:
    """The ``TOPIC<tab>publishers`` lines of ``--marks-file`` (none if it is missing)."""
    if path is None or not path.is_file():
        return []
    lines = path.read_text(errors="replace").splitlines()
    return [(topic, who) for topic, sep, who in (line.partition("\t") for line in lines)
            if sep and topic.startswith("/") and who]


def _expected_publishers(expect: list[str], recorded: list[str],
                         ready_file: Path | None) -> dict[str, int] | None:
    """Publishers per recorded topic to wait for before creating ``ready_file`` (None:
    nothing to wait for); ValueError naming a malformed or unrecorded ``--expect`` or a
    ready file that exists already or cannot be created."""
    if ready_file is None:
        if expect:
            raise ValueError("--expect needs --ready-file (the file it announces readiness in)")
        return None
    if ready_file.exists():
        raise ValueError(f"--ready-file {ready_file}: exists already (a runner would take "
                         "the recorder as ready at once)")
    if not ready_file.parent.is_dir():
        raise ValueError(f"--ready-file {ready_file}: {ready_file.parent} is not a directory")
    counts = dict.fromkeys(recorded, 1)
    for item in expect:
        name, sep, value = item.partition("=")
        if not sep or not value.strip().isdigit():
            raise ValueError(f"--expect {item!r}: expected NAME=N with N a count (0, 1, ...)")
        if name not in counts:
            raise ValueError(f"--expect {item!r}: {name} is not recorded "
                             f"(recorded: {', '.join(recorded)})")
        counts[name] = int(value)
    return counts


if __name__ == "__main__":
    raise SystemExit(main())

"""pisc_soak: a wall-clock soak of the graph, its figures against its targets.

    pisc_soak [--duration 600] [--driver] [--faults] [--realtime P] [--load N] [--seed S]
              [--out DIR]

Runs ``pisc_graph --clock wall`` for ``--duration`` seconds against the simulated plant,
or with ``--driver`` against ``pisc_virtual_rig`` on a pseudo-terminal through the
serial driver (which ``pisc_graph`` runs in a process of its own), recorded as usual,
in a ROS domain of its own. While it runs it samples, once a second, the CPU time and
resident memory of every process of the run from ``/proc`` (the graph's process, each
node process, the recorder, the virtual rig). Then it reads the bag and prints:

* sample-to-voltage latency median, p99, p99.9, max and cycles over the 5 ms period,
  per cycle as :mod:`pisc_runs.summary` computes it (the voltage's publish time minus
  its sample's, both from the bag);
* cycles completed against those expected over the run's span (its periods + 1, from the
  stamps, robust to a late first or last sample: :func:`expected_cycles`);
* CPU seconds and % of one core per process, over the window from 10 s after the first
  cycle to the last one (start-up and the final read of the bag are outside it);
* resident memory per process at 10 s and at the end, and the growth;
* the machine's anchor: the hypervisor's steal time, and a bare timer loop per CPU at
  the graph's scheduling, one SCHED_FIFO priority above it with ``--realtime``
  (:mod:`pisc_bench.machine_probe`): how late it woke (p99, max, wake-ups over the
  period) and how many of the cycles over 5 ms fell near its stalls;
* whether the pendulum was held (the run summary's criteria).

``--faults`` (with ``--driver``): byte drops at 1e-3 from the start, a 0.2 s silence of
the device once a minute and garbage bursts at random times (:func:`fault_schedule`,
from ``--seed``), sent to the rig as JSON requests on its standard input. It then also
reports each silence's recovery (from the first frame after the silence until |theta|
< 0.05 rad for a whole second, or "lost") and checks, with an outside observer (a
separate rclpy process with KEEP_ALL reliable subscriptions on the driver's topics,
made once the rig has had its first command), that the bag holds every message the
driver published that the observer received.

``--load N``: N busy loops (``while True: pass``, normal scheduling, each held to one
CPU of those this process may use), started before the machine probe and the graph and
stopped after them: a loaded computer beside the rig. The bare timer measures the same
loaded machine, so a run under load compares the graph's cycles over the period with the
bare timer's wake-ups over it (the target: no more) instead of asking for none.

Exit status: 0 when every target is met (:class:`pisc_bench.soak_figures.Targets`:
sample-to-voltage p99 <= 1.0 ms, <= 2.0 ms with ``--driver``; 0 cycles over 5 ms; every
expected cycle completed, without ``--faults``; the four nodes' CPU <= 15 % of one core;
resident memory growth <= 2 MB per process; the pendulum held; with ``--faults`` every
silence recovered and nothing the observer saw missing from the bag), 1 otherwise,
naming each target missed; 2 on bad arguments.
The report is also written to ``DIR/report.json`` (``DIR``: ``--out``, default
``bags/soak-<time>``; the bag is ``DIR/bag``). docs/soak.md has the figures.
"""

from __future__ import annotations

import json
import sys
from datetime import UTC, datetime
from pathlib import Path

from pisc_bench.soak_figures import Targets, missed_targets
from pisc_bench.soak_options import ArgumentError, check_realtime, parse_args
from pisc_bench.soak_report import analyse, format_report
from pisc_bench.soak_run import run
from pisc_msgs_py.processes import DomainClaim

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        options = parse_args(argv)
    except ArgumentError as exc:
        print(f"pisc_soak: {exc}", file=sys.stderr)
        return 2
    problem = check_realtime(options.realtime)
    if problem is not None:
        print(f"pisc_soak: --realtime {options.realtime}: cannot use SCHED_FIFO here "
              f"({problem}); it needs CAP_SYS_NICE", file=sys.stderr)
        return 2
    out = options.out or Path("bags") / (
        "soak-" + datetime.now(UTC).strftime("%Y%m%d-%H%M%S"))
    out.mkdir(parents=True, exist_ok=True)
    claim = DomainClaim()
    try:
        record = run(options, out, claim.domain_id, lambda s: print(s, flush=True))
    except KeyboardInterrupt:
        print("pisc_soak: interrupted", file=sys.stderr)
        return 1
    except RuntimeError as exc:  # a helper process that did not start: said, not traced
        print(f"pisc_soak: {exc}", file=sys.stderr)
        return 1
    finally:
        claim.release()
    if record.graph_status not in (0, 1):
        print(record.graph_output, end="")
        print(f"pisc_soak: pisc_graph exited with status {record.graph_status}; no figures "
              f"(its output: {out / 'graph.log'})", file=sys.stderr)
        return 1
    report = analyse(options, out, record)
    missed = missed_targets(report, Targets.for_run(options.driver))
    report["missed_targets"] = missed
    (out / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    print(format_report(report))
    for line in missed:
        print(f"target missed          {line}")
    print(f"result                 {'every target met' if not missed else 'FAILED'} "
          f"(report: {out / 'report.json'})")
    return 0 if not missed else 1


if __name__ == "__main__":
    raise SystemExit(main())

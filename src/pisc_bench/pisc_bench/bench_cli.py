"""pisc_bench: every speed and real-time figure of the project in one run, each beside its
target and an anchor measured in the same run.

    .venv/bin/pisc_bench [--only STEP ...] [--skip STEP ...] [--out DIR]
                         [--soak-seconds 600] [--bag-seconds 600] [--repeat 3]
                         [--rigs 10000]

Each step runs the project's own benchmark command in processes of its own, one after
another (run it on an otherwise idle machine; the load average is printed at the start
and the end):

* ``anchors``: a bare rclpy ping-pong between two nodes on an ``EventsExecutor``, one
  hop with message objects and one as bytes with a KEEP_ALL reader in another process
  (``lockstep_bench --no-graph``); the single-rig kernel and ``solve_ivp`` restarted at
  each sample (LSODA at rtol 1e-9, the fastest setting as accurate as the kernel's
  default, ``pisc_integrators``), each over 2 s of the ``thesis-gains`` playback, per
  5 ms sample;
* ``first-run``: ``git clone`` of this checkout's HEAD into a scratch directory, then
  ``./pisc run --duration 10`` there, set-up included (pip's cache as this machine has
  it);
* ``lockstep``: ``lockstep_bench --no-anchors`` (10 s simulated, one process and
  ``--processes``, ``--repeat`` runs each, every message recorded);
* ``batch``: ``pisc_batch_bench`` (``--rigs`` rigs, 2 s);
* ``bag``: ``bag_bench --seconds`` (finish, repair, analyse, replay of a 10-minute bag);
* ``soak``, ``soak-driver``: ``pisc_soak --duration`` on the wall clock, in one process
  and through the driver and the virtual rig with the driver in a process of its own.

The table gives each figure, its target (the constants below, the soak's from
:mod:`pisc_bench.soak_figures`) and whether it is met, and its
ratio to an anchor of the same run: a lockstep cycle and a latency in rclpy hops, a
batch rig-period and the kernel against the single-rig kernel's sample, ``solve_ivp``
against the kernel, a soak's cycles over 5 ms against a bare timer loop's wake-ups
over 5 ms late in the same run (:mod:`pisc_bench.machine_probe`). Everything each
step printed is in ``DIR/STEP.log`` and the figures in ``DIR/bench.json`` (``--out``;
default a scratch directory, removed at the end unless given). A step that fails is reported with its log's end; the others still run. Exit
status 0 when every step ran (targets met or not), 1 when one failed.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pisc_bench.soak_figures import (
    GROWTH_MB,
    NODES_CPU_PERCENT,
    OVER_PERIOD,
    P99_DRIVER_MS,
    P99_MS,
)

__all__ = ["STEPS", "Row", "kernel_anchors", "main", "rows"]

STEPS = ("anchors", "first-run", "lockstep", "batch", "bag", "soak", "soak-driver")
REPO = Path(__file__).resolve().parents[3]
ANCHOR_SCENE = "thesis-gains"  # pisc_integrators' playback
ANCHOR_SECONDS = 2.0
ANCHOR_SCIPY = ("LSODA", 1e-9)  # the fastest solve_ivp as accurate as the default (figures)

#: The first ``./pisc run`` of a fresh clone, set-up included [s]: a newcomer's first try
FIRST_RUN_S = 120.0
#: The lockstep graph's loop over 10 s simulated [s], one process and ``--processes``
#: (ten and five times the rig's own pace)
LOCKSTEP_S_PER_10_S = {"one_process": 1.0, "processes": 2.0}
#: The batch closed loop [simulated s per wall s] (10,000 draws of a 12 s run: 4 s)
BATCH_SIM_S_PER_S = 30000.0
#: Each bag tool on a 10-minute bag: its wall time [s] and peak resident memory [MB]
#: (streamed, whatever the bag's length)
BAG_TOOL_S = 10.0
BAG_TOOL_MB = 200.0


@dataclass(frozen=True)
class Row:
    """One figure: what, its value shown, its target, met or not, its anchor."""

    figure: str
    value: str
    target: str = ""
    met: bool | None = None  # None: no target
    anchor: str = ""


def kernel_anchors(seconds: float = ANCHOR_SECONDS) -> dict[str, float]:
    """Wall seconds per sample of the single-rig kernel (the scene's own integrator) and of
    ``solve_ivp`` restarted at each sample, over ``seconds`` of the playback of
    ``pisc_integrators`` (its scene's closed-loop voltages, each held a period)."""
    from pisc_plant import work_precision as wp
    from pisc_plant.plant import Plant
    from pisc_sim.closed_loop import simulate
    from pisc_sim.scene import load_scene

    scene = load_scene(ANCHOR_SCENE)
    cfg = scene.config
    period = cfg.loop.period_s
    n = int(round(seconds / period))
    commands = simulate(cfg, seconds)["u"][:n]
    plant = Plant(cfg.plant)
    i0 = cfg.initial
    y0 = plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad, i0.theta_dot_radps)
    own = min((wp.playback(plant, y0, commands, period) for _ in range(3)),
              key=lambda r: r.wall_s)  # the best of three: the kernel's call is short
    method, rtol = ANCHOR_SCIPY
    scipy = wp.playback_scipy(plant, y0, commands, period, method, rtol, rtol * 1e-3)
    reference = wp.playback_scipy(plant, y0, commands, period, "DOP853", 1e-13, 1e-16)
    return {"samples": n, "kernel_s": own.wall_s / n, "solve_ivp_s": scipy.wall_s / n,
            "kernel_error": own.error(reference.states),
            "solve_ivp_error": scipy.error(reference.states)}


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else format(value, spec)


def rows(results: dict[str, Any]) -> list[Row]:
    """The table of one run's results (the steps' figures, by step name)."""
    out: list[Row] = []
    hops = results.get("anchors", {}).get("hops", {})
    hop = hops.get("objects", {}).get("wall_s")
    kernel = results.get("anchors", {}).get("kernel", {})
    kernel_s = kernel.get("kernel_s")

    def in_hops(seconds: float | None) -> str:
        return f"{seconds / hop:.1f} hops" if seconds is not None and hop else ""

    if hops:
        out.append(Row("anchor: rclpy hop, message objects", f"{hop * 1e6:.1f} us"))
        if "bytes_reader" in hops:
            out.append(Row("anchor: rclpy hop, bytes, KEEP_ALL reader elsewhere",
                           f"{hops['bytes_reader']['wall_s'] * 1e6:.1f} us",
                           anchor=in_hops(hops["bytes_reader"]["wall_s"])))
    if kernel:
        out.append(Row("anchor: single-rig kernel, a 5 ms sample",
                       f"{kernel_s * 1e6:.1f} us",
                       anchor=f"error {kernel['kernel_error']:.1e}"))
        method, rtol = ANCHOR_SCIPY
        out.append(Row(f"anchor: solve_ivp {method} rtol {rtol:.0e}, a sample",
                       f"{kernel['solve_ivp_s'] * 1e6:.0f} us",
                       anchor=f"{kernel['solve_ivp_s'] / kernel_s:.0f}x the kernel, error "
                              f"{kernel['solve_ivp_error']:.1e}"))
    first = results.get("first-run")
    if first:
        out.append(Row("first ./pisc run, fresh clone, set-up included",
                       f"{first['wall_s']:.1f} s" + ("" if first["rc"] == 0
                                                     else f" (exit {first['rc']})"),
                       f"<= {FIRST_RUN_S:g} s",
                       first["rc"] == 0 and first["wall_s"] <= FIRST_RUN_S))
    graph = results.get("lockstep", {}).get("graph", {})
    for key, label in (("one_process", "one process"), ("processes", "--processes")):
        target = LOCKSTEP_S_PER_10_S[key]
        g = graph.get(key)
        if g is None:
            continue
        duration = results["lockstep"]["duration_s"]
        per_cycle = g["loop_s"] / g["cycles"]
        out.append(Row(f"lockstep loop, {label}, {duration:g} s simulated",
                       f"{g['loop_s']:.2f} s", f"<= {target * duration / 10.0:g} s",
                       g["loop_s"] <= target * duration / 10.0,
                       f"a cycle {in_hops(per_cycle)}" if hop else ""))
        out.append(Row(f"lockstep, {label}: every message recorded",
                       f"{g['messages']} messages, "
                       + ("all" if g["complete"] else "SOME MISSING"),
                       "all", g["complete"]))
    batch = results.get("batch")
    if batch:
        ratio = (f"a rig-period {batch['ns_per_rig_period'] * 1e-9 / kernel_s:.3f} of a "
                 "single-rig sample" if kernel_s else "")
        out.append(Row(f"batch closed loop, {batch['rigs']} rigs",
                       f"{batch['sim_s_per_s']:,.0f} sim s/s", f">= {BATCH_SIM_S_PER_S:,.0f}",
                       batch["sim_s_per_s"] >= BATCH_SIM_S_PER_S, ratio))
        out.append(Row("batch: numpy controller cores instead",
                       f"{batch['numpy_sim_s_per_s']:,.0f} sim s/s"))
        out.append(Row("batch: the plant alone", f"{batch['plant_sim_s_per_s']:,.0f} sim s/s",
                       anchor=f"{batch['plant_ns_per_rig_period']:.0f} ns a rig-period"))
    bag = results.get("bag")
    if bag:
        for step, r in bag.get("tools", {}).items():
            ok = r["rc"] == 0 or (step == "replay" and r["rc"] == 1)
            out.append(Row(f"bag {step}, {bag['messages']:,} messages",
                           f"{r['wall_s']:.2f} s, {r['rss_mb']:.0f} MB",
                           f"<= {BAG_TOOL_S:g} s, <= {BAG_TOOL_MB:g} MB",
                           ok and r["wall_s"] <= BAG_TOOL_S and r["rss_mb"] <= BAG_TOOL_MB,
                           f"{r['messages'] / r['wall_s']:,.0f} messages/s"))
    for step, label, p99_target in (("soak", "wall clock, one process", P99_MS),
                                    ("soak-driver", "through the driver", P99_DRIVER_MS)):
        report = results.get(step)
        if not report:
            continue
        lat = report["latency"]
        what = f"{label}, {report['duration_s']:g} s"
        out.append(Row(f"{what}: sample-to-voltage p99",
                       f"{lat['p99_ms']:.3f} ms (median {lat['median_ms']:.3f}, p99.9 "
                       f"{lat['p999_ms']:.3f}, max {lat['max_ms']:.3f})",
                       f"<= {p99_target:g} ms", lat["p99_ms"] <= p99_target,
                       in_hops(lat["p99_ms"] * 1e-3)))
        machine = report.get("machine", {})
        out.append(Row(f"{what}: cycles over 5 ms",
                       f"{lat['over_period']} of {report['cycles']['completed']}",
                       f"{OVER_PERIOD}", lat["over_period"] <= OVER_PERIOD,
                       "" if "over_period" not in machine else
                       f"a bare timer: {machine['over_period']} wake-ups over 5 ms of "
                       f"{machine['wakeups']}, max {machine['max_ms']:.1f} ms late"))
        nodes = report.get("nodes_cpu_percent")
        out.append(Row(f"{what}: the nodes' CPU", f"{_fmt(nodes, '.1f')} % of a core",
                       f"<= {NODES_CPU_PERCENT:g} %",
                       nodes is not None and nodes <= NODES_CPU_PERCENT))
        growth = [u.get("growth_mb") for u in report["processes"].values()]
        worst = max((g for g in growth if g is not None), default=None)
        out.append(Row(f"{what}: resident memory growth (most of any process)",
                       f"{_fmt(worst, '.2f')} MB", f"<= {GROWTH_MB:g} MB",
                       worst is not None and worst <= GROWTH_MB))
        out.append(Row(f"{what}: held", "yes" if report["held"] else "NO", "yes",
                       bool(report["held"])))
    return out


def format_rows(table: list[Row]) -> str:
    widths = [max(len(getattr(r, f)) for r in table) for f in ("figure", "value", "target")]
    lines = [f"{'figure':<{widths[0]}}  {'value':<{widths[1]}}  {'target':<{widths[2]}}  "
             "met  anchor"]
    for r in table:
        met = "" if r.met is None else ("yes" if r.met else "NO")
        lines.append(f"{r.figure:<{widths[0]}}  {r.value:<{widths[1]}}  "
                     f"{r.target:<{widths[2]}}  {met:<3}  {r.anchor}".rstrip())
    return "\n".join(lines)


def _run_step(name: str, command: list[str], log: Path, cwd: Path | None = None,
              env: dict[str, str] | None = None) -> tuple[int, float]:
    """Run one step's command, its output to ``log``; (exit status, wall seconds)."""
    print(f"pisc_bench: {name}: {' '.join(command)}", flush=True)
    start = time.perf_counter()
    with log.open("w") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, cwd=cwd, env=env,
                              check=False)
    wall = time.perf_counter() - start
    print(f"pisc_bench: {name}: exit {done.returncode} after {wall:.1f} s", flush=True)
    return done.returncode, wall


def _tail(log: Path, lines: int = 15) -> str:
    return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=STEPS, default=list(STEPS),
                        metavar="STEP", help=f"run these steps only ({', '.join(STEPS)})")
    parser.add_argument("--skip", nargs="+", choices=STEPS, default=[], metavar="STEP",
                        help="leave these steps out")
    parser.add_argument("--out", type=Path, help="directory for the logs, bags and "
                        "bench.json (default: a scratch directory, removed at the end)")
    parser.add_argument("--soak-seconds", type=float, default=600.0,
                        help="wall-clock run length of each soak (default 600)")
    parser.add_argument("--bag-seconds", type=float, default=600.0,
                        help="length of the bag tools' bag (default 600)")
    parser.add_argument("--repeat", type=int, default=3, help="lockstep runs of each layout")
    parser.add_argument("--rigs", type=int, default=10000, help="rigs of the batch")
    parser.add_argument("--kernel-anchors", type=Path, help=argparse.SUPPRESS)  # a child
    args = parser.parse_args(argv)
    if args.kernel_anchors is not None:
        args.kernel_anchors.write_text(json.dumps(kernel_anchors()) + "\n")
        return 0
    if args.soak_seconds < 15 or args.bag_seconds <= 0 or args.repeat < 1 or args.rigs < 1:
        parser.error("--soak-seconds >= 15, --bag-seconds > 0, --repeat >= 1, --rigs >= 1")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out}: exists and is not a directory")
    steps = [s for s in STEPS if s in args.only and s not in args.skip]
    if not steps:
        parser.error("--only and --skip leave no step to run")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        out = args.out
    else:
        out = Path(tempfile.mkdtemp(prefix="pisc_bench-"))
    python = sys.executable
    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True, check=False).stdout.strip()
    started = datetime.datetime.now(datetime.UTC)
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    header = (f"pisc_bench {started:%Y-%m-%d %H:%M} UTC, commit {commit or '?'}, "
              f"{os.cpu_count()} CPUs, load average {load}")
    print(header, flush=True)
    results: dict[str, Any] = {"date": f"{started:%Y-%m-%d %H:%M} UTC", "commit": commit,
                               "load_start": load, "steps": steps}
    failed: list[str] = []

    def step(name: str, command: list[str], read: Callable[[int, float], Any],
             ok: tuple[int, ...] = (0,), **kwargs: Any) -> Any:
        """Run a step; its figures (``read(exit status, wall s)``), None if it failed."""
        log = out / f"{name}.log"
        rc, wall = _run_step(name, command, log, **kwargs)
        try:
            value = read(rc, wall)
            why = "" if rc in ok else f"exit {rc}"
        except (OSError, ValueError, KeyError) as exc:
            value, why = None, f"no figures ({exc})"
        if why:
            failed.append(name)
            print(f"pisc_bench: {name} failed: {why}; the end of {log}:\n{_tail(log)}",
                  file=sys.stderr, flush=True)
        return value

    def load_json(path: Path) -> Callable[[int, float], Any]:
        return lambda rc, wall: json.loads(path.read_text())

    if "anchors" in steps:
        hops, kernel = out / "anchors-hops.json", out / "anchors-kernel.json"
        hop_figures = step("anchors", [python, "-m", "pisc_bench.lockstep_bench_cli",
                                       "--no-graph", "--json", str(hops)], load_json(hops))
        kernel_figures = step("anchors-kernel", [python, "-m", "pisc_bench.bench_cli",
                                                 "--kernel-anchors", str(kernel)],
                              load_json(kernel))
        results["anchors"] = {"hops": (hop_figures or {}).get("anchors", {}),
                              "kernel": kernel_figures or {}}
    if "first-run" in steps:
        clone = out / "first-run-clone"
        shutil.rmtree(clone, ignore_errors=True)
        cloned = subprocess.run(["git", "clone", "-q", str(REPO), str(clone)],
                                capture_output=True, text=True, check=False)
        if cloned.returncode != 0:
            failed.append("first-run")
            print(f"pisc_bench: first-run: cannot clone {REPO} (a git checkout is needed): "
                  f"{cloned.stderr.strip()}", file=sys.stderr, flush=True)
        else:
            # the clone's own ./pisc and .venv, not this one's
            env = {k: v for k, v in os.environ.items()
                   if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
            env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep)
                                          if not p.startswith(str(REPO)))
            results["first-run"] = step("first-run", ["./pisc", "run", "--duration", "10"],
                                        lambda rc, wall: {"rc": rc, "wall_s": wall},
                                        cwd=clone, env=env)
            shutil.rmtree(clone, ignore_errors=True)
    if "lockstep" in steps:
        path = out / "lockstep.json"
        results["lockstep"] = step("lockstep", [
            python, "-m", "pisc_bench.lockstep_bench_cli", "--no-anchors", "--repeat",
            str(args.repeat), "--json", str(path)], load_json(path))
    if "batch" in steps:
        path = out / "batch.json"
        results["batch"] = step("batch", [
            python, "-m", "pisc_bench.batch_bench_cli", "--rigs", str(args.rigs), "--json",
            str(path)], load_json(path))
    if "bag" in steps:
        path = out / "bag.json"

        def read_bag(rc: int, wall: float) -> dict[str, Any]:
            tools = json.loads(path.read_text())
            return {"tools": tools, "seconds": args.bag_seconds,
                    "messages": max(r["messages"] for r in tools.values())}

        results["bag"] = step("bag", [
            python, "-m", "pisc_bench.bag_bench_cli", "--seconds", f"{args.bag_seconds:g}",
            "--dir", str(out / "bag"), "--json", str(path)], read_bag)
        shutil.rmtree(out / "bag", ignore_errors=True)  # 100 MB a bag
    for name, extra in (("soak", []), ("soak-driver", ["--driver"])):
        if name in steps:
            directory = out / name
            shutil.rmtree(directory, ignore_errors=True)
            results[name] = step(name, [
                python, "-m", "pisc_bench.soak_cli", "--duration", f"{args.soak_seconds:g}",
                "--out", str(directory), *extra], load_json(directory / "report.json"),
                ok=(0, 1))  # 1: a target missed
    results = {k: v for k, v in results.items() if v is not None}  # a failed step's
    results["load_end"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    results["failed"] = failed
    table = rows(results)
    results["rows"] = [r.__dict__ for r in table]
    (out / "bench.json").write_text(json.dumps(results, indent=1) + "\n")
    print()
    print(header)
    print(format_rows(table))
    print(f"load average at the end {results['load_end']}"
          + (f"; failed: {', '.join(failed)}" if failed else ""))
    if args.out is None:
        shutil.rmtree(out, ignore_errors=True)
    else:
        print(f"logs and bench.json in {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())

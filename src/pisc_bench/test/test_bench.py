"""pisc_bench: the project's speed and real-time figures in one table, each against its
target and its anchor."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from pisc_bench.bench_cli import Row, format_rows, rows

HOP = 40e-6
KERNEL = 5e-6


def _results() -> dict:
    return {
        "anchors": {"hops": {"objects": {"wall_s": HOP, "cpu_s": HOP},
                             "bytes_reader": {"wall_s": 2.5 * HOP, "cpu_s": HOP}},
                    "kernel": {"samples": 400, "kernel_s": KERNEL, "solve_ivp_s": 1e-3,
                               "kernel_error": 1e-8, "solve_ivp_error": 2e-9}},
        "first-run": {"rc": 0, "wall_s": 121.5},
        "lockstep": {"duration_s": 10.0, "graph": {
            "one_process": {"loop_s": 0.9, "cycles": 2001, "messages": 20000,
                            "complete": True},
            "processes": {"loop_s": 3.6, "cycles": 2001, "messages": 20000,
                          "complete": False}}},
        "batch": {"rigs": 10000, "sim_s_per_s": 20000.0, "ns_per_rig_period": 250.0,
                  "numpy_sim_s_per_s": 17000.0, "plant_sim_s_per_s": 33000.0,
                  "plant_ns_per_rig_period": 150.0},
        "bag": {"messages": 962700, "tools": {
            "analyse": {"rc": 0, "wall_s": 4.0, "rss_mb": 155.0, "messages": 962700},
            "replay": {"rc": 1, "wall_s": 6.6, "rss_mb": 201.0, "messages": 962700}}},
        "soak": {"duration_s": 600.0, "held": True,
                 "latency": {"median_ms": 0.5, "p99_ms": 0.8, "p999_ms": 1.5, "max_ms": 6.0,
                             "over_period": 1},
                 "cycles": {"completed": 120000}, "nodes_cpu_percent": 14.0,
                 "machine": {"over_period": 40, "wakeups": 239950, "max_ms": 17.494},
                 "processes": {"graph": {"growth_mb": 0.5}, "recorder": {"growth_mb": 3.0}}},
    }


def _row(table: list[Row], start: str) -> Row:
    return next(r for r in table if r.figure.startswith(start))


def test_each_figure_is_judged_against_its_target_and_set_beside_its_anchor():
    table = rows(_results())
    assert _row(table, "first ./pisc run").met is False  # 121.5 s > 120 s
    one = _row(table, "lockstep loop, one process, 10 s")
    assert one.value == "0.90 s" and one.met is True
    # a cycle in hops: 0.9 s / 2001 cycles / 40 us
    assert one.anchor == f"a cycle {0.9 / 2001 / HOP:.1f} hops" == "a cycle 11.2 hops"
    assert _row(table, "lockstep loop, --processes").met is False  # 3.6 s > 2.0 s
    assert _row(table, "lockstep, --processes: every message").met is False
    batch = _row(table, "batch closed loop")
    assert batch.met is False and batch.value == "20,000 sim s/s"
    assert batch.anchor == "a rig-period 0.050 of a single-rig sample"  # 250 ns / 5 us
    assert _row(table, "anchor: solve_ivp").anchor.startswith("200x the kernel")
    assert _row(table, "anchor: rclpy hop, bytes").anchor == "2.5 hops"
    assert _row(table, "bag analyse").met is True
    replay = _row(table, "bag replay")  # exit 1 is a mismatch, not a failure; 201 MB is
    assert replay.met is False and replay.anchor == f"{962700 / 6.6:,.0f} messages/s"
    p99 = _row(table, "wall clock, one process, 600 s: sample-to-voltage p99")
    assert p99.met is True and p99.anchor == "20.0 hops"  # 0.8 ms / 40 us
    overs = _row(table, "wall clock, one process, 600 s: cycles over 5 ms")
    assert overs.met is False and overs.value == "1 of 120000"
    assert overs.anchor == "a bare timer: 40 wake-ups over 5 ms of 239950, max 17.5 ms late"
    assert _row(table, "wall clock, one process, 600 s: the nodes' CPU").met is True
    growth = _row(table, "wall clock, one process, 600 s: resident memory")
    assert growth.value == "3.00 MB" and growth.met is False  # the worst process
    text = format_rows(table)
    assert text.splitlines()[0].split() == ["figure", "value", "target", "met", "anchor"]
    assert len(text.splitlines()) == len(table) + 1


def test_steps_not_run_leave_no_rows_and_no_anchor_leaves_no_ratio():
    results = _results()
    del results["anchors"], results["soak"], results["first-run"]
    table = rows(results)
    assert not any(r.figure.startswith(("anchor", "wall clock", "first")) for r in table)
    assert _row(table, "lockstep loop, one process").anchor == ""
    assert rows({}) == []


def test_bad_options_are_refused_with_their_names():
    bad = subprocess.run([sys.executable, "-m", "pisc_bench.bench_cli", "--soak-seconds", "5"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--soak-seconds >= 15" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "pisc_bench.bench_cli", "--only", "lunch"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice: 'lunch'" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "pisc_bench.bench_cli", "--only", "batch",
                          "--skip", "batch"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "leave no step to run" in bad.stderr
    bad = subprocess.run([sys.executable, "-m", "pisc_bench.bench_cli", "--out", __file__],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "exists and is not a directory" in bad.stderr


@pytest.mark.bench
@pytest.mark.integration
def test_a_short_run_measures_its_anchors_and_the_batch(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pisc_bench.bench_cli", "--only", "anchors",
                           "batch", "--rigs", "200", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    print(done.stdout)
    assert done.returncode == 0, done.stderr
    results = json.loads((tmp_path / "bench.json").read_text())
    assert results["steps"] == ["anchors", "batch"] and results["failed"] == []
    kernel = results["anchors"]["kernel"]
    assert 0 < kernel["kernel_s"] < kernel["solve_ivp_s"]
    assert kernel["kernel_error"] < 1e-6 and kernel["solve_ivp_error"] < 1e-6
    assert set(results["anchors"]["hops"]) == {"objects", "objects_reader", "bytes",
                                               "bytes_reader"}
    figures = [r["figure"] for r in results["rows"]]
    assert "batch closed loop, 200 rigs" in figures
    assert "batch closed loop, 200 rigs" in done.stdout
    assert (tmp_path / "batch.log").read_text().startswith("scene thesis-rig, 200 rigs")

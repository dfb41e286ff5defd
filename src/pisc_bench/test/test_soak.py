"""pisc_soak: its pure parts in the default suite,
the command itself behind ``bench`` (``pytest src/pisc_bench/test/test_soak.py -m bench -s``)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pisc_bench.machine_probe import ProbeRun, Probes, load, probe_figures
from pisc_bench.soak_cli import main
from pisc_bench.soak_faults import DROP_RATE, SILENCE_S, fault_schedule, recoveries
from pisc_bench.soak_figures import (
    Sample,
    Targets,
    expected_cycles,
    latency_figures,
    missed_targets,
    observer_check,
    usage_over,
)
from pisc_bench.soak_options import start_load, stop_load
from pisc_bench.soak_proc import children_of, read_proc, read_steal, steal_figures
from pisc_bench.soak_report import format_report
from pisc_plant.rig_faults import check_request

# -- statistics --------------------------------------------------------------------------


def test_latency_figures_are_numpys_linear_percentiles_and_count_cycles_over_the_period():
    latencies = [0.5] * 997 + [5.0, 6.0, 10.0]
    figures = latency_figures(latencies, 0.005)
    assert figures["median_ms"] == 0.5
    assert figures["p99_ms"] == 0.5  # position 0.99 * 999 = 989.01: both neighbours 0.5
    # position 0.999 * 999 = 998.001, between 6.0 and 10.0
    assert figures["p999_ms"] == pytest.approx(6.0 + 0.001 * 4.0)
    assert figures["max_ms"] == 10.0
    assert figures["over_period"] == 2  # 5.0 ms is on time, as in the run summary
    assert figures["cycles"] == 1000


def test_latency_figures_refuse_an_empty_run():
    with pytest.raises(ValueError, match="no complete cycle"):
        latency_figures([], 0.005)


# -- cycles expected over the span ------------------------------------------------------

P_NS = 5_000_000


def arrivals(frames: int, seed: int = 1, lost: tuple[int, ...] = ()) -> np.ndarray:
    """Arrival stamps of a driver run: each frame on the 5 ms grid plus a lateness of
    0.5-1.0 ms (the reader's usual delay), the frames ``lost`` missing."""
    rng = np.random.default_rng(seed)
    grid = 1_000_000_000 + np.arange(frames, dtype=np.int64) * P_NS
    stamps = grid + rng.integers(500_000, 1_000_000, frames)
    return np.delete(stamps, list(lost))


def test_grid_stamps_count_the_span_in_periods_whatever_periods_were_skipped():
    # the simulated plant: stamps on the grid; its wall timer skipped 40 periods
    stamps = np.concatenate([np.arange(1000), np.arange(1040, 4001)]) * P_NS
    assert expected_cycles(stamps, 0.005) == 4001


def test_a_first_sample_that_arrived_late_does_not_shorten_the_span():
    # 4001 frames, every one received; the first read came 8 ms late (as in a 20 s
    # driver run counted 4003 cycles against 4002 expected)
    stamps = arrivals(4001)
    stamps[0] += 8_000_000
    stamps[1] = stamps[0] + 1000  # the same read completed the second frame
    assert round((stamps[-1] - stamps[0]) / P_NS) + 1 == 3999  # the old rule
    assert expected_cycles(stamps, 0.005) == 4001


def test_a_backlog_at_the_start_and_a_late_last_sample_are_counted_right():
    stamps = arrivals(4001)
    stamps[:6] = stamps[5] + 20_000_000 + np.arange(6) * 1000  # one read, 20 ms late
    stamps[-1] += 2_000_000  # the last one 2 ms later than usual
    assert expected_cycles(stamps, 0.005) == 4001


def test_frames_lost_are_expected_cycles_that_did_not_complete():
    stamps = arrivals(4001, lost=(7, 2000, 3998))  # one at each end and one inside
    assert len(stamps) == 3998
    assert expected_cycles(stamps, 0.005) == 4001


def test_never_fewer_cycles_expected_than_samples_and_none_without_samples():
    stamps = np.arange(10, dtype=np.int64) * 1000  # ten samples in 9 us: all of them
    assert expected_cycles(stamps, 0.005) == 10
    with pytest.raises(ValueError, match="no samples"):
        expected_cycles([], 0.005)


# -- the fault schedule ------------------------------------------------------------------


def test_the_fault_schedule_is_the_seeds_and_has_one_silence_a_minute():
    schedule = fault_schedule(7, 600.0)
    assert schedule == fault_schedule(7, 600.0)
    assert schedule != fault_schedule(8, 600.0)
    assert schedule.drop_rate == DROP_RATE == 1e-3
    assert len(schedule.silences_s) == 10
    for minute, t in enumerate(schedule.silences_s):
        assert 12.0 + 60.0 * minute <= t < 16.0 + 60.0 * minute
    times = [t for t, _ in schedule.garbage]
    assert times == sorted(times) and 5.0 < times[0] and times[-1] < 600.0
    assert all(1 <= n <= 64 for _, n in schedule.garbage)
    assert len({n for _, n in schedule.garbage}) > 5  # sizes vary


def test_a_silence_is_left_out_when_its_recovery_could_not_be_seen():
    assert len(fault_schedule(0, 20.0).silences_s) == 1  # 12-16 s, 3.8 s or more to recover
    assert fault_schedule(0, 15.0).silences_s == ()  # 12 s + 0.2 s + 3 s > 15 s
    for seed in range(20):
        for t in fault_schedule(seed, 75.0).silences_s:
            assert t + SILENCE_S + 3.0 <= 75.0


def test_every_request_of_the_schedule_is_one_the_virtual_rig_accepts():
    requests = fault_schedule(3, 600.0).requests()
    assert [t for t, _ in requests] == sorted(t for t, _ in requests)
    assert sum("silence_s" in r for _, r in requests) == 10
    for _, request in requests:
        assert check_request(json.loads(json.dumps(request))) == request


# -- recoveries --------------------------------------------------------------------------


def trace(theta_after, gap=(10.0, 10.2), end_s=14.0, period=0.005):
    """Samples every 5 ms but none strictly inside ``gap``; theta 0.01 before the gap and
    ``theta_after(t)`` from its end."""
    t = np.arange(0.0, end_s + period / 2, period)
    t = t[(t <= gap[0] + 1e-9) | (t >= gap[1] - 1e-9)]
    theta = np.where(t <= gap[0] + 1e-9, 0.01, [theta_after(x) for x in t])
    return t, theta


def test_a_pendulum_that_stays_in_the_band_recovers_at_once():
    t, theta = trace(lambda x: 0.02)
    (r,) = recoveries(t, theta, [9.99])
    assert r.silent_s == pytest.approx(0.2)
    assert r.ended_s == pytest.approx(10.2)
    assert r.recovery_s == 0.0 and r.peak_theta_rad == pytest.approx(0.02)
    assert not r.lost


def test_recovery_is_the_first_sample_back_in_the_band_for_a_second():
    # 0.2 rad at the end of the silence, linearly to 0 at 10.71 s: |theta| < 0.05 from
    # 10.5825 s on, so from the sample of 10.585 s
    t, theta = trace(lambda x: max(0.0, 0.2 * (1.0 - (x - 10.2) / 0.51)))
    (r,) = recoveries(t, theta, [9.99])
    assert r.recovery_s == pytest.approx(0.385, abs=1e-6)
    assert r.peak_theta_rad == pytest.approx(0.2)


def test_swinging_through_the_band_is_not_a_recovery():
    # a 2 Hz swing of 0.2 rad for a second after the silence, then still: each pass
    # through upright is < 0.05 rad for 40 ms; it stays only from the last one, 20 ms
    # before 11.2 s (arcsin(0.25) / (4 pi) = 20.1 ms)
    def swing(x):
        return 0.2 * math.sin(4.0 * math.pi * (x - 10.2)) if x < 11.2 else 0.001

    t, theta = trace(swing)
    (r,) = recoveries(t, theta, [9.99])
    assert r.recovery_s == pytest.approx(1.0 - 0.0201, abs=0.006)


def test_a_pendulum_that_never_comes_back_is_lost_and_a_missing_gap_is_said():
    t, theta = trace(lambda x: 0.3)
    (r,) = recoveries(t, theta, [9.99])
    assert r.lost and r.peak_theta_rad == pytest.approx(0.3)
    assert "lost (peak |theta| 0.300 rad)" in r.format()
    (none,) = recoveries(t, theta, [5.0])  # nothing was silent near 5 s
    assert none.silent_s is None and none.lost
    assert none.format() == "silence asked at 5.000 s: no gap between frames seen"


def test_a_recovery_must_come_before_the_next_silence():
    # back in the band only at 12.5 s: lost if the next silence is asked at 13.0 s (no
    # whole second before it), recovered when it is asked at 14.0 s
    t, theta = trace(lambda x: 0.3 if x < 12.5 else 0.0, end_s=16.0)
    first, _ = recoveries(t, theta, [9.99, 13.0])
    assert first.lost
    first, _ = recoveries(t, theta, [9.99, 14.0])
    assert first.recovery_s == pytest.approx(2.3)


# -- processes and the observer ----------------------------------------------------------


def test_usage_over_takes_the_first_and_last_samples_inside_the_window():
    samples = [Sample(100.0 + k, 0.5 * k, 100_000_000 + 10_000 * k) for k in range(21)]
    usage = usage_over(samples, 104.5, 115.2)  # samples 105 .. 115
    assert usage["window_s"] == 10.0
    assert usage["cpu_s"] == 5.0 and usage["cpu_percent"] == 50.0
    assert usage["rss_start_mb"] == pytest.approx(100.05)
    assert usage["growth_mb"] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="1 sample"):
        usage_over(samples, 104.5, 105.5)


def test_read_proc_gives_this_process_cpu_and_resident_memory_and_none_once_gone():
    cpu, rss = read_proc(os.getpid())
    assert cpu > 0.0
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    assert abs(rss - pages * os.sysconf("SC_PAGE_SIZE")) < 5_000_000
    child = subprocess.Popen(["sleep", "30"])
    try:
        # Popen may return (vfork) before exec has set the new command line: empty until
        # then (1 of 3 suite runs on 2026-12-05 read it so)
        deadline = time.monotonic() + 10.0
        while not Path(f"/proc/{child.pid}/cmdline").read_bytes():
            assert time.monotonic() < deadline
            time.sleep(0.001)
        assert "sleep 30" in children_of(os.getpid())[child.pid]
    finally:
        child.kill()
        child.wait()
    assert read_proc(child.pid) is None


def test_steal_figures_count_the_cycles_over_the_period_near_a_second_with_steal():
    # steal grew over 105-106, 106-107 (0.03 s) and 115-116 (0.02 s)
    steal = {106: 0.01, 107: 0.03, 116: 0.05}
    samples, so_far = [], 0.0
    for k in range(100, 121):
        so_far = steal.get(k, so_far)
        samples.append((float(k), so_far))
    # widened by 1 s: 104-108 and 114-117, 7 s of the 20 s window
    overs = [103.9, 104.2, 107.9, 110.0, 116.5, 125.0]  # the last is after the window
    figures = steal_figures(samples, 99.0, 121.0, overs)
    assert figures["steal_s"] == pytest.approx(0.05)
    assert figures["intervals_with_steal"] == 3 and figures["near_s"] == 1.0
    assert figures["near_share"] == pytest.approx(7.0 / 20.0)
    assert (figures["overs"], figures["overs_near"]) == (5, 3)
    assert steal_figures(samples, 99.0, 121.0, overs, near_s=0.0)["overs_near"] == 0
    with pytest.raises(ValueError, match="1 steal sample"):
        steal_figures(samples, 104.5, 105.5, overs)


def probe_run(cpu, late_ms, start_s=100.0, period_s=0.005):
    return ProbeRun(cpu, 41, round(period_s * 1e9), round(start_s * 1e9),
                    np.round(np.asarray(late_ms) * 1e6).astype(np.int64))


def test_probe_figures_count_wakeups_over_the_period_and_the_cycles_near_a_stall():
    # CPU 0 wakes 0.02 ms late but for a 12 ms stall at deadline 1000 (105.0 s): the
    # deadlines it covered are 12, 7 and 2 ms late; CPU 1 is 1.5 ms late at 110.0 s
    late0 = np.full(4000, 0.02)
    late0[1000:1003] = [12.0, 7.0, 2.0]
    late1 = np.full(4000, 0.01)
    late1[2000] = 1.5
    runs = [probe_run(0, late0), probe_run(1, late1)]
    overs = [105.05, 109.95, 112.0, 130.0]  # the last is after the window
    figures = probe_figures(runs, 99.999, 119.002, overs)
    assert [(c["cpu"], c["wakeups"], c["over_period"]) for c in figures["cpus"]] == [
        (0, 3801, 2), (1, 3801, 0)]
    assert figures["cpus"][0]["max_ms"] == pytest.approx(12.0)
    assert figures["cpus"][1]["p99_ms"] == pytest.approx(0.01)
    assert figures["wakeups"] == 7602 and figures["over_period"] == 2
    assert figures["max_ms"] == pytest.approx(12.0)
    # stalls (over 1 ms late) at 105.000, 105.005, 105.010 and 110.000 s, widened by 0.1 s:
    # 104.9-105.11 and 109.9-110.1, 0.41 s of the 19.003 s window
    assert figures["stalls"] == 4
    assert figures["near_share"] == pytest.approx(0.41 / 19.003)
    assert (figures["overs"], figures["overs_near"]) == (3, 2)
    with pytest.raises(ValueError, match="no probe wake-up between 200.0 and 300.0"):
        probe_figures(runs, 200.0, 300.0, overs)


def test_a_stopped_machine_probe_wakes_late_by_the_stop_and_counts_each_deadline(tmp_path):
    probes = Probes(tmp_path, 0, 0.005, 30.0)
    try:
        time.sleep(0.3)
        victim = probes.processes[0]
        victim.send_signal(signal.SIGSTOP)
        time.sleep(0.06)
        victim.send_signal(signal.SIGCONT)
        time.sleep(0.2)
    finally:
        runs = probes.stop()
    assert [r.cpu for r in runs] == sorted(os.sched_getaffinity(0))
    stopped = runs[0]
    late_ms = stopped.lateness_ns * 1e-6
    assert late_ms.size >= 80 and (late_ms >= 0).all()
    # no wake-up during the 60 ms stop: the first deadline in it is >= 55 ms late, and
    # each of the ten or more after it, 5 ms less each, is counted
    assert late_ms.max() >= 55.0
    assert (late_ms > 5.0).sum() >= 10
    assert stopped.period_ns == 5_000_000 and stopped.priority == 0
    assert abs(stopped.deadlines_unix_s()[0] - (time.time() - late_ms.size * 0.005)) < 1.0


def test_probes_that_cannot_start_say_why_and_leave_none_running(tmp_path):
    with pytest.raises(RuntimeError, match=r"the machine probe on CPU \d+ did not start: "
                       r"machine_probe: CPU \d+, priority 100: "):
        Probes(tmp_path, 100, 0.005, 30.0)  # SCHED_FIFO priorities end at 99
    assert not list(tmp_path.iterdir())


def test_a_machine_probe_that_died_is_named_when_the_probes_stop(tmp_path):
    probes = Probes(tmp_path, 0, 0.005, 30.0)
    probes.processes[-1].kill()
    probes.processes[-1].wait()
    name = f"probe-cpu{max(os.sched_getaffinity(0))}.npz"
    with pytest.raises(ValueError, match=f"machine probe {name} exited with status -9"):
        probes.stop()
    assert all(p.poll() is not None for p in probes.processes)


def test_a_machine_probe_on_a_cpu_that_does_not_exist_says_so(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pisc_bench.machine_probe_cli", "--cpu",
                           "4096", "--out", str(tmp_path / "p.npz")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.startswith("machine_probe: CPU 4096, priority 0: ")
    assert not (tmp_path / "p.npz").exists()
    with pytest.raises(ValueError, match="machine probe .*p.npz"):
        load(tmp_path / "p.npz")


def test_a_machine_probe_refuses_an_output_it_could_not_write_before_it_runs(tmp_path):
    done = subprocess.run([sys.executable, "-m", "pisc_bench.machine_probe_cli", "--cpu", "0",
                           "--out", str(tmp_path / "nowhere" / "p.npz")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""  # never said ready
    assert f"--out {tmp_path / 'nowhere' / 'p.npz'}: {tmp_path / 'nowhere'} is not a " \
        "directory" in done.stderr


def test_a_soak_whose_machine_probe_cannot_start_says_so_without_a_traceback(
        tmp_path, capsys, monkeypatch):
    import pisc_bench.soak_run as soak_module

    def refuse(*args, **kwargs):
        raise RuntimeError("the machine probe on CPU 0 did not start: refused")

    monkeypatch.setattr(soak_module, "Probes", refuse)
    assert main(["--duration", "15", "--out", str(tmp_path / "soak")]) == 1
    err = capsys.readouterr().err
    assert err == "pisc_soak: the machine probe on CPU 0 did not start: refused\n"


def test_read_steal_is_the_eighth_value_of_proc_stats_cpu_line_in_seconds():
    before = int(Path("/proc/stat").read_text().split("\n")[0].split()[8])
    steal = read_steal()
    after = int(Path("/proc/stat").read_text().split("\n")[0].split()[8])
    tick = 1.0 / os.sysconf("SC_CLK_TCK")
    assert before * tick <= steal <= after * tick


def test_the_observer_check_counts_what_the_bag_misses_repeats_included():
    checked = observer_check({"/a": [1, 2, 2, 3], "/b": [5]},
                             {"/a": [1, 2, 3, 4], "/b": [5, 6], "/c": [7]})
    assert checked == {"/a": {"observed": 4, "in_bag": 4, "missing_from_bag": 1},
                       "/b": {"observed": 1, "in_bag": 2, "missing_from_bag": 0},
                       "/c": {"observed": 0, "in_bag": 1, "missing_from_bag": 0}}


# -- targets -----------------------------------------------------------------------------


def good_report(**changes):
    usage = {"cpu_s": 1.0, "cpu_percent": 10.0, "rss_start_mb": 100.0, "rss_end_mb": 101.0,
             "growth_mb": 1.0, "window_s": 590.0}
    report = {"latency": {"median_ms": 0.5, "p99_ms": 0.9, "p999_ms": 1.5, "max_ms": 3.0,
                          "over_period": 0, "cycles": 120001},
              "period_s": 0.005, "faults": False,
              "cycles": {"completed": 120001, "expected": 120001},
              "nodes_cpu_percent": 12.0,
              "processes": {"graph": dict(usage), "recorder": dict(usage)},
              "held": True}
    report.update(changes)
    return report


def test_the_report_prints_the_steal_beside_the_cycles_over_the_period_or_why_not():
    report = good_report(
        duration_s=600.0, driver=False, realtime=None, date="2026-12-05 02:59 UTC",
        bag="/tmp/bag", seed=0, nodes_processes=["graph"], caught_at_s=1.995,
        hold_theta_rad=0.0019, hold_x_m=0.0034, state_source="true", faults_seen=[],
        cycles={"completed": 120001, "expected": 120001, "nominal": 120001, "unanswered": 0},
        steal={"steal_s": 0.48, "intervals_with_steal": 14, "near_s": 1.0,
               "near_share": 0.07, "overs": 21, "overs_near": 4})
    assert ("steal (hypervisor)     0.48 s in 14 seconds; 4 of the 21 cycles over 5 ms "
            "within 1 s of one (7.0 % of the window is)") in format_report(report).splitlines()
    report["steal"] = {"error": "1 steal sample(s) between 10.0 and 20.0"}
    assert "steal (hypervisor)     1 steal sample(s) between 10.0 and 20.0" \
        in format_report(report).splitlines()
    assert "machine (bare timer)   not measured" in format_report(report).splitlines()
    report["machine"] = {"cpus": [{}, {}], "p99_ms": 0.061, "max_ms": 17.494,
                         "over_period": 40, "wakeups": 239950, "overs_near": 19,
                         "overs": 21, "near_s": 0.1, "stall_ms": 1.0, "stalls": 142,
                         "near_share": 0.0484}
    lines = format_report(report).splitlines()
    at = lines.index("machine (bare timer)   2 loops, one per CPU: p99 0.061 ms, max 17.494 "
                     "ms late, 40 wake-ups over 5 ms of 239950")
    assert lines[at + 1] == ("                       19 of the 21 cycles over 5 ms within "
                             "0.1 s of a wake-up over 1 ms late (142 such; 4.8 % of the "
                             "window is)")
    report["load"] = 2
    assert format_report(report).splitlines()[0] == (
        "PISC soak: 600 s wall clock, simulated plant, under load (2 busy loops, one per "
        "CPU); 2026-12-05 02:59 UTC")


def test_a_run_that_meets_every_target_misses_none():
    assert missed_targets(good_report(), Targets()) == []


def test_each_missed_target_is_named_with_its_figure():
    report = good_report(nodes_cpu_percent=36.2, held=False,
                         cycles={"completed": 2775, "expected": 3002})
    report["latency"].update(p99_ms=1.2, over_period=3)
    report["processes"]["recorder"]["growth_mb"] = 2.5
    assert missed_targets(report, Targets()) == [
        "sample-to-voltage p99 1.200 ms > 1.0 ms",
        "3 cycles over the 5 ms period (target 0)",
        "2775 cycles completed of 3002 expected",
        "the four nodes' CPU 36.2 % of one core > 15 %",
        "recorder: resident memory grew 2.50 MB > 2 MB",
        "the pendulum was not held"]
    # the cycles over the period beside the machine's own stalls, when measured
    report["machine"] = {"overs_near": 2, "near_s": 0.1}
    assert missed_targets(report, Targets())[1] == (
        "3 cycles over the 5 ms period (target 0; 2 within 0.1 s of the bare timer's "
        "stalls)")
    # through the driver p99 may reach 2.0 ms
    report = good_report()
    report["latency"]["p99_ms"] = 1.2
    assert missed_targets(report, Targets.for_run(driver=True)) == []


def test_under_load_the_cycles_over_the_period_may_be_the_bare_timers_and_no_more():
    """A loaded machine (pisc_soak --load): the bare timer measured beside the run is the
    machine's own limit; the graph may have as many cycles over the period, not more."""
    report = good_report(load=2)
    report["machine"] = {"over_period": 3, "overs_near": 3, "near_s": 0.1}
    report["latency"].update(over_period=3)
    assert missed_targets(report, Targets.for_run(driver=True)) == []
    report["latency"].update(over_period=4)
    assert missed_targets(report, Targets.for_run(driver=True)) == [
        "4 cycles over the 5 ms period (target 3 (the bare timer's wake-ups over it); 3 "
        "within 0.1 s of the bare timer's stalls)"]


def _cpu_ticks(pid: int) -> int:
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return int(fields[11]) + int(fields[12])


def test_the_load_is_one_busy_loop_per_cpu_held_there_and_stopped():
    cpus = sorted(os.sched_getaffinity(0))
    loops = start_load(len(cpus))
    try:
        assert [sorted(os.sched_getaffinity(p.pid)) for p in loops] == [[c] for c in cpus]
        before = [_cpu_ticks(p.pid) for p in loops]
        time.sleep(0.5)
        assert all(_cpu_ticks(p.pid) > b for p, b in zip(loops, before))  # busy
        assert all(os.sched_getscheduler(p.pid) == os.SCHED_OTHER for p in loops)
    finally:
        stop_load(loops)
    assert all(p.poll() is not None for p in loops)


def test_a_faults_run_misses_a_lost_silence_and_a_message_the_bag_lacks():
    report = good_report(faults=True, cycles={"completed": 100, "expected": 120001},
                         recoveries=[{"requested_s": 13.2, "recovery_s": 0.4},
                                     {"requested_s": 74.0, "recovery_s": None}],
                         observer={"/pisc/joint_states": {"observed": 10, "in_bag": 9,
                                                          "missing_from_bag": 1},
                                   "/diagnostics": {"observed": 0, "in_bag": 3,
                                                    "missing_from_bag": 0}})
    assert missed_targets(report, Targets.for_run(driver=True)) == [
        "1 of 2 silences not recovered (74.0 s)",
        "/pisc/joint_states: 1 messages the observer received are not in the bag",
        "/diagnostics: the observer received nothing"]


# -- arguments ---------------------------------------------------------------------------


@pytest.mark.parametrize("args, message", [
    (["--duration", "nan"], "--duration nan: must be a finite number of seconds >= 15"),
    (["--duration", "14"], "--duration 14: must be a finite number of seconds >= 15"),
    (["--faults"], "--faults needs --driver"),
    (["--driver", "--realtime", "95"], "--realtime 95: must be a SCHED_FIFO priority from 1 "
                                       "to 89"),
    (["--seed", "-1"], "--seed -1: must be >= 0"),
    (["--load", "-1"], "--load -1: must be 0 .. "),
    (["--load", "999"], "--load 999: must be 0 .. "),
])
def test_bad_arguments_exit_2_naming_the_rule_and_write_nothing(tmp_path, capsys, args,
                                                                 message):
    out = tmp_path / "soak"
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pisc_soak: ") and message in err and "Traceback" not in err
    assert not out.exists()


def test_an_output_directory_that_holds_something_is_refused(tmp_path, capsys):
    (tmp_path / "report.json").write_text("{}")
    assert main(["--out", str(tmp_path)]) == 2
    assert "exists and is not an empty directory; not overwriting" in capsys.readouterr().err
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_a_value_that_is_not_a_number_is_argparses_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--duration", "ten"])
    assert exc.value.code == 2
    assert "argument --duration: invalid float value: 'ten'" in capsys.readouterr().err


# -- the command (bench) -----------------------------------------------------------------


def soak(tmp_path, *args: str) -> tuple[int, str, dict]:
    beside = Path(sys.executable).parent / "pisc_soak"
    command = [str(beside)] if beside.exists() else [sys.executable, "-m", "pisc_bench.soak_cli"]
    out = tmp_path / "soak"
    started = time.monotonic()
    done = subprocess.run([*command, *args, "--out", str(out)], capture_output=True,
                          text=True, timeout=600)
    print(done.stdout, done.stderr, f"({time.monotonic() - started:.0f} s)")
    assert done.returncode in (0, 1), done.stderr
    report = json.loads((out / "report.json").read_text())
    assert (done.returncode == 0) == (report["missed_targets"] == [])
    for line in report["missed_targets"]:
        assert f"target missed          {line}" in done.stdout
    return done.returncode, done.stdout, report


def check_common(report: dict, duration_s: float, processes: set[str]) -> None:
    lat = report["latency"]
    assert 0 < lat["median_ms"] <= lat["p99_ms"] <= lat["p999_ms"] <= lat["max_ms"]
    assert lat["cycles"] == report["cycles"]["completed"]
    assert report["cycles"]["completed"] <= report["cycles"]["expected"]
    # the span is the run: --duration of 5 ms cycles, one more for both ends
    assert abs(report["cycles"]["expected"] - (duration_s / 0.005 + 1)) < 40
    assert set(report["processes"]) == processes
    for usage in report["processes"].values():
        assert usage["window_s"] == pytest.approx(duration_s - 10.0, abs=2.5)
        assert 0.0 < usage["cpu_percent"] < 200.0 and usage["rss_start_mb"] > 10.0
    assert report["caught_at_s"] is not None


@pytest.mark.bench
def test_soak_of_the_simulated_plant_prints_its_figures(tmp_path):
    rc, output, report = soak(tmp_path, "--duration", "20")
    check_common(report, 20.0, {"graph", "recorder"})
    assert report["nodes_cpu_percent"] == report["processes"]["graph"]["cpu_percent"]
    assert "sample-to-voltage      median" in output and "p99.9" in output


@pytest.mark.bench
def test_soak_under_load_through_the_driver_measures_the_bare_timer_beside_it(tmp_path):
    """The command docs/soak.md's figures under load come from (10 minutes there)."""
    realtime = ["--realtime", "40"] if _fifo_allowed() else []
    rc, output, report = soak(tmp_path, "--driver", "--load", "2", "--duration", "20",
                              *realtime)
    assert report["load"] == 2 and "under load (2 busy loops, one per CPU)" in output
    assert "machine (bare timer)" in output and "error" not in report["machine"]


@pytest.mark.bench
def test_soak_through_the_driver_with_faults_loses_nothing_the_observer_saw(tmp_path):
    realtime = ["--realtime", "40"] if _fifo_allowed() else []
    rc, output, report = soak(tmp_path, "--driver", "--faults", "--duration", "20",
                              *realtime)
    check_common(report, 20.0, {"graph", "recorder", "driver", "virtual rig"})
    observer = report["observer"]
    samples = observer["/pisc/joint_states"]
    # the observer received (nearly) every sample of the run, and the bag holds each
    assert samples["observed"] >= 0.9 * report["cycles"]["expected"]
    assert all(seen["missing_from_bag"] == 0 for seen in observer.values()), observer
    # the driver publishes both for each frame: from the time the observer's two
    # subscriptions had both matched (one may match a message before the other), the
    # observer received the same stamps on both
    seen = json.loads((tmp_path / "soak" / "observer.json").read_text())
    joints, currents = seen["/pisc/joint_states"], seen["/pisc/motor/current"]
    both = max(joints[0], currents[0])
    assert [s for s in joints if s >= both] == [s for s in currents if s >= both]
    assert observer["/diagnostics"]["observed"] >= 10  # the driver's, at least 1 per second
    (silence,) = report["recoveries"]  # one minute's silence, 12-16 s into the run
    assert 12.0 <= silence["requested_s"] < 16.0
    assert 0.19 <= silence["silent_s"] <= 0.30
    assert report["rig"]["dropped"] > 0 and report["garbage_bursts"]


def _fifo_allowed() -> bool:
    try:
        done = subprocess.run([sys.executable, "-c", "import os; os.sched_setscheduler(0, "
                               "os.SCHED_FIFO, os.sched_param(40))"], capture_output=True)
    except OSError:
        return False
    return done.returncode == 0


# -- why the 600 s driver soak lost the swing-up (bench) -----------------------------------


def _swing_up(drop_seed: int | None = None, stall: tuple[int, int] | None = None,
              duration_s: float = 3.0) -> tuple[str, float, float]:
    """The closed loop of the default configuration from rest as the driver sees it:
    each frame lost with the probability of a 1e-3 byte drop among its 7 bytes (the
    controllers never see it; the rig holds the last byte), or the host stalled for
    ``stall = (first frame, frames)`` (no byte reaches the rig: it holds the last one
    for its 50 ms watchdog, then 0 V; the controllers see the frames afterwards).
    Returns (outcome, time of the catch or fault [s], lowest measured x [m])."""
    from pisc_msgs_py.types import Mode
    from pisc_plant.plant import Plant
    from pisc_plant.sampled import SampledPlant
    from pisc_sim.closed_loop import Controllers
    from pisc_sim.configuration import load_graph_config

    config, _ = load_graph_config("default")
    plant = Plant(config.simulated_plant)
    assert not plant.config.models.force_input
    i0 = config.initial
    sampled = SampledPlant(plant, plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad,
                                                      i0.theta_dot_radps))
    controllers = Controllers(config)
    rng = np.random.default_rng(drop_seed)
    p_frame = 1.0 - (1.0 - DROP_RATE) ** 7
    silent, lowest, caught = 0, 0.0, None
    for k in range(round(duration_s / 0.005)):
        sample = sampled.sample()
        lowest = min(lowest, sample.position_m)
        if drop_seed is not None and rng.random() < p_frame:
            continue  # lost: no answer, the rig holds the byte
        out = controllers.step(sample.position_m, sample.angle_rad, sample.current_a)
        if out.mode is Mode.FAULT:
            return "fault", k * 0.005, lowest
        if out.mode is Mode.CATCH and caught is None:
            caught = k * 0.005
        if stall is not None and stall[0] <= k < stall[0] + stall[1]:
            silent += 1
            if silent > 10:  # the rig's watchdog: 50 ms
                sampled.command(0.0)
        else:
            silent = 0
            sampled.command(out.voltage, 0.0008)  # (the rig's plant takes voltage)
        sampled.advance()
    return ("caught" if caught is not None else "not caught"), caught or 0.0, lowest


@pytest.mark.bench
def test_the_swing_up_survives_byte_drops_but_not_a_host_stall_of_180_ms():
    """Figures behind docs/soak.md ("Why the swing-up was lost"): .venv/bin/python -m
    pytest src/pisc_bench/test/test_soak.py -m bench -k host_stall -s"""
    nominal = _swing_up()
    print(f"no faults: {nominal}")
    assert nominal[0] == "caught" and -0.225 < nominal[2] < -0.205  # 12-20 mm to spare
    for seed in range(10):
        outcome = _swing_up(drop_seed=seed)
        print(f"1e-3 byte drops, seed {seed}: {outcome}")
        assert outcome[0] == "caught" and abs(outcome[2] - nominal[2]) < 0.003
    # the soak's stall: 178 ms of no reads from 0.486 s, the cart running left at 0.6 m/s
    for frames in (10, 36):
        outcome = _swing_up(stall=(97, frames))
        print(f"host stall of {frames * 5} ms at 0.486 s: {outcome}")
    assert _swing_up(stall=(97, 10))[0] == "caught"
    assert _swing_up(stall=(97, 36))[:1] == ("fault",)

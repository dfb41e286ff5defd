"""The real driver node against the virtual rig on a pseudo-terminal.

The rig (``pisc_virtual_rig``) runs the plant in real time, paced by its own clock like
the PIC, under SCHED_FIFO so that a loaded machine delays its frames no more than the
PIC's timer would; the graph (``pisc_graph --driver``) runs the control nodes and the
driver in one process, also under SCHED_FIFO, as a control computer runs its loop.
Acceptance is the simulation-only graph's (test_graph.py), judged on the measured
state of the bag and on the rig's true state, which its log gives per frame with the
Unix time the frame was sent (the driver stamps samples with that clock on arrival).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from conftest import spin_until
from pisc_bag.bag import read_bag
from pisc_sim.configuration import config_path
from pisc_runs.summary import summarise_bag
from pisc_driver.driver_node import DriverNode
from pisc_driver.link import SerialLink
from pisc_driver.protocol import command_voltage, encode_command
from pisc_msgs_py.base_node import message_class, qos_profile
from pisc_msgs_py.convert import (
    joint_sample_from_msg,
    mode_from_msg,
    motor_sample_to_msg,
    stamp_from_msg,
)
from pisc_msgs_py.topics import (
    DIAGNOSTICS,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    VOLTAGE,
    VOLTAGE_SENT,
)
from pisc_msgs_py.types import Mode, MotorSample
from pisc_plant.rig_process import RigProcess

pytestmark = pytest.mark.integration

RT_RIG = "50"  # SCHED_FIFO priority of the rig: above the graph, like hardware
RT_GRAPH = "40"


def start_rig(tmp_path, *args: str) -> RigProcess:
    return RigProcess(["--realtime", RT_RIG, "--params-file", str(config_path("default")),
                       "--log", str(tmp_path / "rig.csv"), *args])


def start_graph(env, port: str, bag, duration_s: float) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--driver", port, "--duration",
         str(duration_s), "--bag", str(bag), "--realtime", RT_GRAPH],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(graph: subprocess.Popen, timeout_s: float = 120.0) -> tuple[int, str]:
    out, err = graph.communicate(timeout=timeout_s)
    return graph.returncode, out + err


def wait_cycles(rig: RigProcess, commands: int, timeout_s: float = 120.0) -> dict:
    """Wait until the rig has received ``commands`` command bytes (about 5 ms each)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = rig.status()
        if status["bytes_received"] >= commands:
            return status
        time.sleep(0.05)
    raise TimeoutError(f"the rig received fewer than {commands} commands in {timeout_s} s")


def run_window(bag) -> tuple[float, float]:
    """Unix times of the first and last complete cycle of the bag."""
    stamps = [m.message.header.stamp for m in read_bag(bag, [VOLTAGE.name])]
    ns = sorted(s.sec * 1_000_000_000 + s.nanosec for s in stamps)
    return ns[0] * 1e-9, ns[-1] * 1e-9


def true_log(tmp_path) -> np.ndarray:
    return np.genfromtxt(tmp_path / "rig.csv", delimiter=",", names=True)


def assert_acceptance_measured(summary) -> None:
    """test_graph.assert_acceptance on the measured state (no simulator topic here)."""
    assert summary.caught_at_s is not None and summary.caught_at_s <= 3.0, summary.format()
    assert summary.held and summary.hold_theta_rad < 0.05 and summary.hold_x_m < 0.02, (
        summary.format())
    assert summary.state_source == "measured"
    assert -0.22 <= summary.x_range_m[0] and summary.x_range_m[1] <= 0.12, summary.format()
    assert summary.duration_s >= 10.0 and not summary.faults, summary.format()


def assert_acceptance_true(log: np.ndarray, start: float, end: float) -> None:
    """The same limits on the rig's true state: held from 6 s, inside the IR range."""
    run = log[(log["unix_s"] >= start - 0.005) & (log["unix_s"] <= end)]
    assert run["unix_s"][0] - start < 0.05 and end - run["unix_s"][-1] < 0.05  # covers the run
    late = run[run["unix_s"] >= start + 6.0]
    theta_up = np.abs((late["theta"] + math.pi) % (2 * math.pi) - math.pi)
    assert theta_up.max() < 0.05 and np.abs(late["x"]).max() < 0.02, (
        theta_up.max(), np.abs(late["x"]).max())
    assert run["x"].min() >= -0.22 and run["x"].max() <= 0.12


def driver_statuses(bag) -> list:
    return [s for m in read_bag(bag, [DIAGNOSTICS.name]) for s in m.message.status
            if s.name == "pisc/driver"]


def late_cycles(bag, until_s: float, period_s: float = 0.005) -> list[tuple[float, str]]:
    """Cycles from 50 ms (after the first cycle's start-up) to ``until_s`` of a run that
    missed the real-time deadline: a voltage sent more than a period after its sample,
    or a sample arriving more than two periods after the one before.

    Returns (run time, what) for each, from the publish times the bag keeps.
    """
    sent: dict[str, dict[int, int]] = {JOINT_STATES.name: {}, VOLTAGE.name: {}}
    for m in read_bag(bag, list(sent)):
        sent[m.topic].setdefault(stamp_from_msg(m.message.header.stamp), m.publish_time_ns)
    samples, voltages = sent[JOINT_STATES.name], sent[VOLTAGE.name]
    t0 = min(voltages)
    late = [((s - t0) * 1e-9, f"voltage {(v - samples[s]) * 1e-6:.1f} ms after its sample")
            for s, v in voltages.items()
            if s in samples and v - samples[s] > period_s * 1e9]
    stamps = sorted(s for s in samples if s >= t0)
    late += [((b - t0) * 1e-9, f"sample {(b - a) * 1e-6:.1f} ms after the one before")
             for a, b in zip(stamps, stamps[1:], strict=False) if b - a > 2 * period_s * 1e9]
    return sorted(x for x in late if 0.05 <= x[0] <= until_s)


def run_swing_up(tmp_path, env, *rig_args: str, during=None) -> tuple[int, str, Path, dict]:
    """Swing up from x0 = 0 through the driver and the virtual rig for 10 s; ``during(rig)``
    acts on the rig while the graph runs. Returns (exit status, output, bag, the rig's
    final status) of the first run that catches by 3 s, or of the last.

    Up to eight runs: a run that does not catch by 3 s counts only when this machine met
    every deadline of its swing-up (50 ms to 3 s); then it fails the test at once. The
    one-swing swing-up tolerates little (README), and the driver sends 0 V once the
    newest command is 10 ms old: a vCPU stalled by its host for 10-60 ms (vmstat shows
    up to 16 % steal on these machines under load, which SCHED_FIFO cannot prevent) can
    cost the first catch. On a noisy day three runs in a row have missed it.
    """
    attempts = 8
    for attempt in range(1, attempts + 1):
        bag = tmp_path / f"bag{attempt}"
        rig = start_rig(tmp_path, "--x0", "0.0", *rig_args)
        graph = None
        try:
            graph = start_graph(env, rig.device, bag, 10.0)
            if during is not None:
                during(rig)
            rc, output = finish(graph)
        finally:
            if graph is not None and graph.poll() is None:  # ``during`` raised
                graph.kill()
                graph.communicate()
            final = rig.stop()
        print(output)
        caught_at = summarise_bag(bag, 0.005).caught_at_s if rc in (0, 1) else None
        if (rc == 0 and caught_at is not None and caught_at <= 3.0) or attempt == attempts:
            break
        late = late_cycles(bag, 3.0)
        assert late, f"not caught by 3 s with every deadline of the swing-up met:\n{output}"
        print(f"attempt {attempt}: not caught by 3 s after {len(late)} late cycles before "
              f"3 s (first at {late[0][0]:.3f} s: {late[0][1]}); running again")
    return rc, output, bag, final


@pytest.mark.realtime
def test_swing_up_and_catch_through_the_driver_and_the_virtual_rig(tmp_path, env_for_domain):
    rc, output, bag, final = run_swing_up(tmp_path, env_for_domain)
    summary = summarise_bag(bag, 0.005)
    assert rc == 0, output
    assert_acceptance_measured(summary)
    assert_acceptance_true(true_log(tmp_path), *run_window(bag))
    assert "serial driver on /dev/pts/" in output and "result                 CAUGHT" in output
    # nothing lost on the way: every byte the rig sent made an accepted frame, and every
    # sample the driver published was answered and recorded
    # (the driver publishes from the first frame to its shutdown; the run is the span the
    # controllers answered, so count the samples inside it)
    stamps = {topic: [stamp_from_msg(m.message.header.stamp)
                      for m in read_bag(bag, [topic])]
              for topic in (JOINT_STATES.name, VOLTAGE.name)}
    first, last = min(stamps[VOLTAGE.name]), max(stamps[VOLTAGE.name])
    inside = sum(first <= s <= last for s in stamps[JOINT_STATES.name])
    assert len(stamps[VOLTAGE.name]) == inside and summary.cycles in (inside, inside - 1)
    values = {kv.key: kv.value for kv in driver_statuses(bag)[-1].values}
    assert (values["rehunts"], values["bytes_discarded"]) == ("0", "0"), values
    statuses = driver_statuses(bag)
    # the driver's own process may have said "opened" before the recorder matched it
    assert any(s.message in (f"opened {final['device']}", f"link up on {final['device']}")
               for s in statuses), [s.message for s in statuses[:3]]
    assert final["last_byte"] == 0  # the graph's end: the driver sent 0 V last


@pytest.mark.realtime
def test_device_silence_is_a_fault_and_zero_volts_within_20_ms(tmp_path, env_for_domain):
    rig = start_rig(tmp_path, "--x0", "0.0")
    try:
        graph = start_graph(env_for_domain, rig.device, tmp_path / "bag", 4.0)
        wait_cycles(rig, 500)  # 2.5 s into the run: swinging up or balancing
        rig.request(silence_s=0.2)
        time.sleep(0.3)
        status = rig.status()
        rc, output = finish(graph)
    finally:
        rig.stop()
    assert rc in (0, 1), output
    assert status["silence_start"] is not None
    print(f"zero voltage {status['zero_after_silence_s'] * 1e3:.1f} ms after the last frame")
    assert 0.0 < status["zero_after_silence_s"] <= 0.020
    faults = [s for s in driver_statuses(tmp_path / "bag") if s.level == 2]
    assert any(s.message.startswith("device silent: no frame for") for s in faults), faults


@pytest.mark.realtime
def test_byte_drops_at_1e_2_during_balance_do_not_drop_the_pendulum(tmp_path, env_for_domain):
    def drop_bytes(rig: RigProcess) -> None:
        wait_cycles(rig, 700)  # 3.5 s: caught at about 1.5 s
        rig.request(drop_rate=0.01)

    rc, output, bag, final = run_swing_up(tmp_path, env_for_domain, "--seed", "3",
                                          during=drop_bytes)
    assert rc == 0, output
    assert final["dropped"] > 100
    summary = summarise_bag(bag, 0.005)
    print(summary.format())
    assert summary.cycles < 2000 * 0.97  # frames were lost ...
    assert_acceptance_measured(summary)  # ... and the pendulum was held
    assert_acceptance_true(true_log(tmp_path), *run_window(bag))
    last = driver_statuses(bag)[-1]
    values = {kv.key: kv.value for kv in last.values}
    assert int(values["rehunts"]) > 50 and int(values["bytes_discarded"]) > 50, values


@pytest.mark.realtime
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_killing_the_driver_leaves_zero_volts_as_the_last_byte(tmp_path, env_for_domain,
                                                                ros_context, signum):
    rig = start_rig(tmp_path)
    driver = subprocess.Popen(
        [sys.executable, "-m", "pisc_driver.driver_node", "--ros-args", "-p",
         f"driver.port:={rig.device}"], env=env_for_domain, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    node = Node("current_loop", context=ros_context)  # the publisher the driver pins
    publisher = node.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                      qos_profile(VOLTAGE.qos))

    def answer(msg) -> None:  # every sample answered with 3 V, as the current loop would
        sample = joint_sample_from_msg(msg)
        publisher.publish(motor_sample_to_msg(MotorSample(sample.stamp_ns, 3.0)))

    node.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name, answer,
                             qos_profile(JOINT_STATES.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    try:
        assert spin_until(executor, lambda: rig.status()["last_byte"] == encode_command(3.0),
                          30.0), rig.status()
        driver.send_signal(signum)
        spin_until(executor, lambda: driver.poll() is not None, 20.0)
        out, err = driver.communicate(timeout=20)
        assert driver.returncode == 0, err
        time.sleep(0.05)
        status = rig.status()
        assert status["last_byte"] == 0x00, status
        assert status["applied_v"] == 0.0
    finally:
        if driver.poll() is None:
            driver.kill()
        node.destroy_node()
        rig.stop()


class Answerer:
    """A stand-in for the current loop (the node the driver pins, ``current_loop``), or,
    named otherwise, a visitor: answers every sample with ``volts`` while ``answering``
    is true; ``sent`` holds the stamps of the samples it answered."""

    def __init__(self, ros_context, volts: float, name: str = "current_loop",
                 executor=None) -> None:
        self.node = Node(name, context=ros_context)
        self.answering = True
        self.sent: list[int] = []
        publisher = self.node.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                               qos_profile(VOLTAGE.qos))

        def answer(msg) -> None:
            if self.answering:
                sample = joint_sample_from_msg(msg)
                self.sent.append(sample.stamp_ns)
                publisher.publish(motor_sample_to_msg(MotorSample(sample.stamp_ns, volts)))

        self.node.create_subscription(message_class(JOINT_STATES.type), JOINT_STATES.name,
                                      answer, qos_profile(JOINT_STATES.qos))
        self.executor = executor or SingleThreadedExecutor(context=ros_context)
        self.executor.add_node(self.node)

    def spin_until(self, predicate, timeout_s: float) -> bool:
        return spin_until(self.executor, predicate, timeout_s)


def start_driver(env, port: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pisc_driver.driver_node", "--ros-args", "-p",
         f"driver.port:={port}"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)


@pytest.mark.realtime
def test_sigkill_of_the_driver_while_driving_leaves_zero_volts_by_the_rig_watchdog(
        tmp_path, env_for_domain, ros_context):
    """Found by a hostile test: SIGKILL of the process holding the driver left the last
    byte's voltage applied for ever (the thesis's firmware); the rig's watchdog now zeroes
    it 50-55 ms after the last byte."""
    rig = start_rig(tmp_path)
    driver = start_driver(env_for_domain, rig.device)
    answerer = Answerer(ros_context, 3.0)
    try:
        assert answerer.spin_until(lambda: rig.status()["applied_v"] == pytest.approx(
            command_voltage(encode_command(3.0))), 30.0), rig.status()
        driver.kill()  # the host crashes: nothing more is sent
        driver.communicate(timeout=20)

        def zeroed(status: dict) -> bool:  # a trip in force, after the last byte
            return (status["watchdog_tripped"]
                    and status["watchdog_trip_time"] > status["last_byte_time"])

        status = rig.status()
        deadline = time.monotonic() + 2.0
        while not zeroed(status) and time.monotonic() < deadline:
            time.sleep(0.01)
            status = rig.status()
        # (a trip before the kill, the driver stalled past 50 ms on this loaded machine,
        # ended at its next byte: only the trip in force at the end counts)
        shown = {k: status[k] for k in ("frames", "overruns", "applied_v", "last_byte",
                                        "watchdog_trips", "watchdog_tripped")}
        assert status["last_byte"] == encode_command(3.0), shown  # the driver never sent 0 V
        assert zeroed(status) and status["applied_v"] == 0.0, shown  # ... yet 0 V applies
        assert 0.050 < status["watchdog_delay_s"] <= 0.055 + 1e-9  # by the rig's clock
        delay = status["watchdog_trip_time"] - status["last_byte_time"]
        print(f"0 V {delay * 1e3:.1f} ms after the last byte of the killed driver "
              "(monotonic clock)")
    finally:
        if driver.poll() is None:
            driver.kill()
        answerer.node.destroy_node()
        rig.stop()


@pytest.mark.realtime
def test_the_driver_answers_every_frame_while_the_controllers_are_silent_until_it_stops(
        tmp_path, env_for_domain, ros_context):
    """While the driver lives the rig's watchdog never trips, the controllers silent or
    not: it answers each frame (0 V once the commands are stale). When it stops it
    sends 0 V and then nothing, and the watchdog trips."""
    rig = start_rig(tmp_path)
    driver = start_driver(env_for_domain, rig.device)
    answerer = Answerer(ros_context, 3.0)
    try:
        assert answerer.spin_until(lambda: rig.status()["bytes_received"] > 20, 30.0)
        answerer.answering = False  # the controllers die
        answerer.spin_until(lambda: False, 0.1)
        before = rig.status()
        answerer.spin_until(lambda: False, 1.0)
        after = rig.status()
        frames = after["frames"] - before["frames"]
        received = after["bytes_received"] - before["bytes_received"]
        print(f"{received} bytes for {frames} frames while the controllers were silent; "
              f"watchdog trips {after['watchdog_trips']}")
        # one byte per frame read (a driver that falls behind reads several frames at once
        # and answers the last; stalled for 50 ms, it lets the watchdog trip: this
        # machine's load decides how often, so only the sure part is asserted here; the
        # rule itself is test_driver_core's)
        assert frames > 0 and received >= 0.5 * frames
        assert after["last_byte"] == 0x00 and after["applied_v"] == 0.0
        driver.send_signal(signal.SIGTERM)
        driver.communicate(timeout=20)
        assert driver.returncode == 0
        time.sleep(0.05)  # (the rig reads what the driver wrote before it exited)
        stopped = rig.status()
        time.sleep(0.2)
        final = rig.status()
        assert final["bytes_received"] == stopped["bytes_received"]  # nothing more sent
        assert final["watchdog_trips"] > after["watchdog_trips"] and final["applied_v"] == 0.0
    finally:
        if driver.poll() is None:
            driver.kill()
        answerer.node.destroy_node()
        rig.stop()


@pytest.mark.realtime
def test_every_byte_the_driver_writes_is_published_as_written(tmp_path, env_for_domain,
                                                             ros_context):
    """/pisc/motor/voltage_sent: one message per byte written, which the rig (an outside
    observer) counts as received. An answer carries the stamp of the sample it answers
    and the voltage its byte encodes; once the controllers fall silent the driver's own
    bytes say so (held, then 0 V once the command is stale). Counted with the driver
    running and quiet (the rig silent: no frame, no byte), not across its stop."""
    rig = start_rig(tmp_path)
    driver = start_driver(env_for_domain, rig.device)
    answerer = Answerer(ros_context, 3.0)
    answerer.answering = False  # until the observer hears the driver's publisher
    observer = Node("voltage_sent_observer", context=ros_context)
    sent: list[tuple[int, str, float]] = []
    sub = observer.create_subscription(
        message_class(VOLTAGE_SENT.type), VOLTAGE_SENT.name,
        lambda m: sent.append((stamp_from_msg(m.header.stamp), m.header.frame_id,
                               m.effort[0])), qos_profile(VOLTAGE_SENT.qos))
    answerer.executor.add_node(observer)
    try:
        assert answerer.spin_until(lambda: sub.get_publisher_count() > 0, 30.0)
        # (and the driver's writer ours: discovery matches the two ends one at a time,
        # and a message published before its writer has matched a reader is not its)
        answerer.spin_until(lambda: False, 2.0)
        # Counted from here: a byte written before (a 0 V while the answering node was
        # not yet named, an intruder until then) may have been published before the
        # driver's writer matched this reader: 6 of 61 runs failed so on 2026-12-05, and
        # in the two with the driver's own log of what it published, that "zero" came
        # first, about 2 s before the first answer, and the observer never got it.
        received_before, sent_before = rig.status()["bytes_received"], len(sent)
        answerer.answering = True
        assert answerer.spin_until(lambda: len(sent) > 250, 30.0), len(sent)
        answerer.answering = False  # the controllers die
        answerer.spin_until(lambda: False, 0.5)
        rig.request(silence_s=30.0)  # no frames: the driver has nothing more to answer
        answerer.spin_until(lambda: False, 1.0)  # (its silence fault: 0 V, if not sent)
        received = rig.status()["bytes_received"]
        answerer.spin_until(lambda: False, 0.5)  # the last messages
        assert rig.status()["bytes_received"] == received  # quiet
    finally:
        if driver.poll() is None:
            driver.kill()
        answerer.node.destroy_node()
        observer.destroy_node()
        rig.stop()
    answers = [m for m in sent if m[1] == "answer"]
    own = [m for m in sent if m[1] != "answer"]
    print(f"{received} bytes received by the rig; {len(answers)} answers and {len(own)} of "
          f"the driver's own published; {received_before} and {sent_before} before counting")
    assert received - received_before == len(sent) - sent_before
    assert {m[1] for m in sent} <= {"answer", "hold", "zero"}
    volts = command_voltage(encode_command(3.0))
    # 0 V until the driver has pinned the answering node as the command's one publisher
    # (docs/safety.md), then the answers' 3 V as the byte encodes it
    volts_sent = [v for _, _, v in answers]
    pinned = next(k for k, v in enumerate(volts_sent) if v != 0.0)
    print(f"answers sent as 0 V before the pin: {pinned}")
    assert volts_sent[pinned:] == pytest.approx([volts] * (len(answers) - pinned), abs=1e-12)
    assert len(answers) - pinned > 150 and {m[0] for m in answers} <= set(answerer.sent)
    stamps = [m[0] for m in answers]
    assert stamps == sorted(set(stamps))  # one answer per sample, in order
    assert own[-1][1:] == ("zero", 0.0) and sent[-1] == own[-1]


def test_missing_or_busy_port_or_bad_parameter_refuses_to_start_and_says_why(tmp_path, env_for_domain):
    command = [sys.executable, "-m", "pisc_driver.driver_node", "--ros-args", "-p"]
    missing = subprocess.run(command + ["driver.port:=/dev/pisc-no-such-port"],
                             env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert missing.returncode == 2
    assert ("refusing to start: invalid parameter: driver.port = '/dev/pisc-no-such-port': "
            "no such device") in missing.stderr
    bad = subprocess.run(command + ["driver.port:=/dev/null", "-p",
                                    "driver.silence_timeout_s:=0.0"],
                         env=env_for_domain, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2
    assert "driver.silence_timeout_s = 0.0 must lie in [0.001, 10.0]" in bad.stderr
    rig = start_rig(tmp_path)
    holder = SerialLink(rig.device)
    holder.open()
    try:
        busy = subprocess.run(command + [f"driver.port:={rig.device}"], env=env_for_domain,
                              capture_output=True, text=True, timeout=60)
    finally:
        holder.close()
        rig.stop()
    assert busy.returncode == 2
    assert "the port is busy, another program has it open" in busy.stderr


def test_parameter_change_sends_zero_and_a_vanished_port_is_reported_and_retried(
        tmp_path, ros_context):
    rig = start_rig(tmp_path)
    node = DriverNode(context=ros_context, parameter_overrides=[
        Parameter("driver.port", value=rig.device),
        Parameter("driver.reopen_interval_s", value=0.05),
        Parameter("driver.command_node", value="probe")])  # the probe's commands drive
    probe = Node("probe", context=ros_context)
    errors = _driver_statuses(probe, b"\x02")
    voltage = probe.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                     qos_profile(VOLTAGE.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(probe)
    try:
        assert spin_until(executor, lambda: node._core.parser.frames > 20, 10.0)
        assert spin_until(executor, lambda: voltage.get_subscription_count() > 0, 10.0)

        def answered() -> bool:  # a command answering the newest frame, as a current
            # loop sends: one alone can be refused, older than 10 ms when it arrives under
            # load, or not newer than a frame at which the pin saw the graph name the probe
            voltage.publish(motor_sample_to_msg(MotorSample(node._core.last_frame_ns, -11.47)))
            executor.spin_once(timeout_sec=0.005)
            return rig.status()["last_byte"] == 0xFF

        assert spin_until(executor, answered, 10.0)
        result = node.set_parameters([Parameter("driver.silence_timeout_s", value=0.02)])[0]
        assert result.successful
        assert node._core.params.silence_timeout_s == 0.02
        assert rig.status()["last_byte"] == 0x00  # zero before the port was reopened
        assert spin_until(executor, lambda: node._core.parser.frames > 20, 10.0)
        rig.stop()  # the device goes away mid-run
        assert spin_until(executor, lambda: any("the device went away" in e for e in errors),
                          10.0), errors
        assert spin_until(executor, lambda: any("no such device" in e and "retrying" in e
                                                for e in errors), 10.0), errors
        assert node._reader is not None and node._reader.is_alive()
        assert rclpy.ok(context=ros_context)
    finally:
        node.destroy_node()
        probe.destroy_node()
        rig.stop()


def _driver_statuses(node: Node, level: bytes) -> list[str]:
    """The messages of the driver's /diagnostics statuses at ``level`` (a byte in
    rclpy: b"\\x01" WARN, b"\\x02" ERROR), as ``node``'s subscription receives them."""
    said: list[str] = []
    node.create_subscription(
        message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
        lambda m: said.extend(s.message for s in m.status
                              if s.name == "pisc/driver" and s.level == level),
        qos_profile(DIAGNOSTICS.qos))
    return said


def _raw_pty() -> tuple[int, int, str]:
    """A pseudo-terminal in raw mode: (master, non-blocking; slave; the slave's path)."""
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def _written(master: int) -> bytes:
    """What the driver wrote to the pseudo-terminal since the last call."""
    try:
        return os.read(master, 4096)
    except BlockingIOError:
        return b""


def test_the_reader_looks_for_another_command_publisher_at_every_frame(ros_context):
    """Who publishes commands is looked at on every command, at every frame by the reader
    and every 0.1 s besides; a timer each period cost the driver's process 200 wake-ups a
    second of two threads. Here the driver's executor never spins: a visitor
    that joins while no command comes is found by the frames alone, and 0 V is written
    at once."""
    import struct

    master, slave, path = _raw_pty()
    count = [0]

    def frames(n: int = 1) -> None:  # a frame every 5 ms, the count still
        for _ in range(n):
            os.write(master, struct.pack(">BHHh", 0xAA, 400, 780, count[0]))
            time.sleep(0.005)

    def written() -> bytes:
        return _written(master)

    node = DriverNode(context=ros_context, parameter_overrides=[
        Parameter("driver.port", value=path)])
    loop = Node("current_loop", context=ros_context)
    visitor = None
    errors = _driver_statuses(loop, b"\x02")
    listen = SingleThreadedExecutor(context=ros_context)
    listen.add_node(loop)  # (the probe's subscription only: the driver is not spun)
    try:
        loop.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name, qos_profile(VOLTAGE.qos))
        deadline = time.monotonic() + 20.0
        while node._pin.pinned is None and time.monotonic() < deadline:
            frames(2)  # (the first two lock the parser on)
        assert node._pin.pinned is not None and not node._pin.intruders  # pinned by frames
        frames(3)
        written()  # (what came before: 0 V if the graph listed the loop late)
        visitor = Node("visitor", context=ros_context)
        visitor.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                 qos_profile(VOLTAGE.qos))
        while node._sub.get_publisher_count() < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        frames_before = node._core.parser.frames
        while not node._pin.intruders and time.monotonic() < deadline:
            frames()
        assert node._pin.intruders == ("/visitor",)
        assert node._core.parser.frames > frames_before  # a frame it read found it
        out = written()  # 0 V at once, with no command to answer (the reader writes it
        while not out and time.monotonic() < deadline:  # right after the look)
            time.sleep(0.005)
            out = written()
        assert out[:1] == bytes([0x00]), out
        assert spin_until(listen, lambda: any(e.startswith(
            f"another publisher on {VOLTAGE.name}: /visitor") for e in errors), 10.0), errors
    finally:
        node.destroy_node()
        loop.destroy_node()
        if visitor is not None:
            visitor.destroy_node()
        for fd in (master, slave):
            os.close(fd)


def test_a_command_the_driver_cannot_read_is_refused_with_its_reason_and_writes_nothing(
        ros_context):
    """A voltage command goes from its bytes to a value on the subscription's fast path
    and is checked there as the controllers' inputs are: a command with a NaN
    voltage or without the motor joint is refused on /diagnostics, at WARN, naming what
    is wrong, and no byte is written for it; the next good command is written at once."""
    import struct

    master, slave, path = _raw_pty()
    node = DriverNode(context=ros_context, parameter_overrides=[
        Parameter("driver.port", value=path),
        Parameter("driver.command_max_age_periods", value=100.0),
        Parameter("driver.silence_timeout_s", value=10.0)])
    loop = Node("current_loop", context=ros_context)
    warnings = _driver_statuses(loop, b"\x01")
    pub = loop.create_publisher(message_class(VOLTAGE.type), VOLTAGE.name,
                                qos_profile(VOLTAGE.qos))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(loop)

    def written() -> bytes:
        return _written(master)

    def command(volts: float, joint: str = "motor") -> None:
        msg = motor_sample_to_msg(MotorSample(node._core.newest_stamp_ns, volts))
        msg.name = [joint]
        pub.publish(msg)

    try:
        deadline = time.monotonic() + 20.0
        while node._core.newest_stamp_ns < 0 and time.monotonic() < deadline:
            os.write(master, struct.pack(">BHHh", 0xAA, 400, 780, 0))
            executor.spin_once(timeout_sec=0.005)
        assert node._core.newest_stamp_ns >= 0
        # both ends matched: a volatile writer that has not yet matched the driver's
        # reader drops what it is given (seen under load)
        while (node._sub.get_publisher_count() < 1 or pub.get_subscription_count() < 1) \
                and time.monotonic() < deadline:
            time.sleep(0.01)
        written()
        command(math.nan)
        assert spin_until(executor, lambda: any(
            w == "rejected voltage command: motor: non-finite value in [nan]"
            for w in warnings), 10.0), warnings
        command(2.0, joint="cart")
        assert spin_until(executor, lambda: any(
            w == "rejected voltage command: motor: expected joints ['motor'], got ['cart']"
            for w in warnings), 10.0), warnings
        assert written() == b"" and node._core.commands == 0
        # a fresh sample to answer: the first one is older than the commands' age limit by
        # now (the two refusals take tens of ms, more on a loaded machine; the good command
        # was dropped as stale); the limit is the longest the driver allows, 0.5 s, and the
        # device is not called silent while the test takes its time
        first = node._core.newest_stamp_ns
        os.write(master, struct.pack(">BHHh", 0xAA, 400, 780, 0))
        assert spin_until(executor, lambda: node._core.newest_stamp_ns > first, 10.0)
        command(2.0)
        assert spin_until(executor, lambda: node._core.commands == 1, 10.0), (
            f"{node._core.stale_commands} stale")
        out = written()
        deadline = time.monotonic() + 10.0
        while not out and time.monotonic() < deadline:
            time.sleep(0.005)
            out = written()
        assert out == bytes([encode_command(2.0)]), out
    finally:
        node.destroy_node()
        loop.destroy_node()
        for fd in (master, slave):
            os.close(fd)


def test_the_driver_runs_on_the_wall_clock_only(tmp_path):
    completed = subprocess.run(
        # a port that opens: the clock is what is refused, not the port
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--driver", "/dev/null",
         "--clock", "lockstep", "--bag", str(tmp_path / "bag")],
        capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert "--driver runs against the wall clock (the device paces the samples)" in (
        completed.stderr)


# -- at the driver: only the graph drives the motor; the crash matrix -----------------------

VISITOR_V = 11.47


def _level(status) -> int:
    return status.level if isinstance(status.level, int) else status.level[0]


def _values(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


class DriverWatch:
    """The driver's statuses on /diagnostics, each with its stamp (ns), and the modes."""

    def __init__(self, node: Node) -> None:
        self.statuses: list[tuple[int, object]] = []
        self.modes: list = []
        node.create_subscription(
            message_class(DIAGNOSTICS.type), DIAGNOSTICS.name,
            lambda m: self.statuses.extend((stamp_from_msg(m.header.stamp), s)
                                           for s in m.status if s.name == "pisc/driver"),
            qos_profile(DIAGNOSTICS.qos))
        node.create_subscription(message_class(MODE.type), MODE.name,
                                 lambda m: self.modes.append(mode_from_msg(m).mode),
                                 qos_profile(MODE.qos))

    def errors(self, text: str) -> list[tuple[int, object]]:
        return [(t, s) for t, s in self.statuses if _level(s) == 2 and text in s.message]


@pytest.mark.realtime
def test_a_visitor_answering_every_sample_drives_nothing_through_the_driver(
        tmp_path, env_for_domain, ros_context):
    """Found by a hostile test: the driver took commands from anyone on
    /pisc/motor/voltage. Now none of a visitor's commands reaches the rig: 0 V from its
    arrival, a fault naming it, and the current loop's commands apply again once it has
    gone."""
    rig = start_rig(tmp_path)
    driver = start_driver(env_for_domain, rig.device)
    loop = Answerer(ros_context, 3.0)
    watch = DriverWatch(loop.node)
    three_v = command_voltage(encode_command(3.0))
    visitor = None
    try:
        assert loop.spin_until(lambda: rig.status()["applied_v"] == pytest.approx(three_v),
                               30.0), rig.status()
        loop.spin_until(lambda: False, 0.2)
        visitor = Answerer(ros_context, VISITOR_V, "visitor", loop.executor)
        assert loop.spin_until(lambda: len(visitor.sent) >= 40 and watch.errors("/visitor"),
                               30.0), watch.statuses[-3:]
        fault_ns, fault = watch.errors("/visitor")[0]
        assert fault.message.startswith(f"another publisher on {VOLTAGE.name}: /visitor; "
                                        "the driver sends 0 V while it is there")
        assert _values(fault)["intruders"] == "/visitor"
        first_ns = visitor.sent[0]
        print(f"fault {(fault_ns - first_ns) * 1e-6:.1f} ms after the sample the visitor's "
              "first command answered (driver clock)")
        # the fault is raised at the latest when its first command arrives
        assert fault_ns <= first_ns + 20_000_000
        during_until = time.time()
        visitor.answering = False
        loop.executor.remove_node(visitor.node)
        visitor.node.destroy_node()
        visitor = None
        # the driver learns of the departure through discovery, slower under load
        assert loop.spin_until(lambda: any(
            _level(s) == 0 and "/visitor left" in s.message for _, s in watch.statuses), 60.0), [
            (t, _level(s), s.message) for t, s in watch.statuses[-5:]]
        assert loop.spin_until(lambda: rig.status()["applied_v"] == pytest.approx(three_v),
                               20.0), rig.status()
    finally:
        if visitor is not None:
            visitor.node.destroy_node()
        driver.send_signal(signal.SIGTERM)
        driver.communicate(timeout=20)
        loop.node.destroy_node()
        rig.stop()
    log = true_log(tmp_path)
    # by the rig's own log (the voltage applied at each tick, with its clock): the visitor's
    # 11.47 V never; 0 V from a period after the fault until the visitor had gone
    assert not np.any(np.isclose(log["applied_v"], VISITOR_V, atol=0.05))
    held = log[(log["unix_s"] > fault_ns * 1e-9 + 0.005) & (log["unix_s"] < during_until)]
    assert len(held) >= 30 and np.all(held["applied_v"] == 0.0), held["applied_v"]
    assert np.any(np.isclose(log["applied_v"][log["unix_s"] > during_until], three_v))


def _start_balancing(tmp_path, env, ros_context, processes: bool):
    # the rig starts 0.05 rad from upright at the middle of the safe range: caught at once.
    # From hanging at x0 = 0 the swing-up passes within 11 mm of the range's end, and a
    # late cycle faulted it before any catch (modes swing_up, fault; the rig at 0 V): the
    # CI run of 138efbd and 2 of about 40 runs here on 2026-12-03, as test_faults.py's
    # kills through the plant had before they started so. Held there (--hold) until the
    # controllers' first voltage: the rig simulates from its own start, and in the 5-8 s
    # the graph takes to come up the pendulum had fallen and swung, so the run began
    # from wherever it was; 2 of 10 such starts faulted (cart at x = -0.2251 m),
    # 2026-12-05
    rig = start_rig(tmp_path, "--x0", "-0.05", "--set", "initial.theta_rad=0.05", "--hold")
    graph = None
    try:  # a failure here stops the rig and the graph (a rig left at SCHED_FIFO loads
        # every later test of the run)
        graph = subprocess.Popen(
            [sys.executable, "-m", "pisc_bringup.graph_cli", "--driver", rig.device, "--duration",
             "60", "--bag", str(tmp_path / "bag"), "--realtime", RT_GRAPH,
             *(["--processes"] if processes else [])],
            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        probe = Node("crash_probe", context=ros_context)
        watch = DriverWatch(probe)
        executor = SingleThreadedExecutor(context=ros_context)
        executor.add_node(probe)
        # balancing (or, on a slow day, still swinging up: the chain answers every sample
        # either way, which is what the crash cuts)
        caught = spin_until(executor,
                            lambda: Mode.CATCH in watch.modes or graph.poll() is not None, 30.0)
        assert graph.poll() is None, graph.communicate()
        spin_until(executor, lambda: False, 1.0)
        if not (rig.status()["applied_v"] != 0.0 or caught):  # said in full on failure
            print("rig:", rig.status(), "\nmodes:", watch.modes, "\ndriver's last statuses:",
                  *[(t, _level(s), s.message) for t, s in watch.statuses[-8:]], sep="\n")
        assert rig.status()["applied_v"] != 0.0 or caught
    except BaseException:
        if graph is not None and graph.poll() is None:
            graph.kill()
            _, err = graph.communicate()
            print("pisc_graph's standard error:", err[-4000:], sep="\n")  # shown on failure
        rig.stop()
        raise
    return rig, graph, probe, watch, executor, caught


@pytest.mark.realtime
@pytest.mark.parametrize("stage", ["estimator", "supervisor", "current_loop"])
def test_sigkill_of_a_controller_through_the_driver_zeroes_the_rig_and_names_it(
        tmp_path, env_for_domain, ros_context, stage):
    """The hostile tests' crash matrix through the driver and the virtual rig (``--driver
    --processes``): the driver sends 0 V at the latest 3 frames after the last answered
    one (its age rule sooner), and /diagnostics names the stage that died."""
    from test_faults import _child_pid

    rig, graph, probe, watch, executor, caught = _start_balancing(
        tmp_path, env_for_domain, ros_context, processes=True)
    try:
        pid = _child_pid(graph.pid, f"{stage}_node")
        assert pid is not None
        killed_ns = time.time_ns()
        os.kill(pid, signal.SIGKILL)
        _, err = graph.communicate(timeout=120)
        spin_until(executor, lambda: False, 0.3)
    finally:
        if graph.poll() is None:
            graph.kill()
            graph.communicate()
        probe.destroy_node()
        rig.stop()
    assert graph.returncode == 2 and f"{stage}_node exited with status -9" in err, err
    for _, s in watch.errors("another publisher"):
        print(f"(before the kill) {s.message}")
    trips = watch.errors("command watchdog")
    assert trips, [s.message for _, s in watch.statuses]
    trip_ns, trip = trips[-1]
    values = _values(trip)
    assert values["applied_v"] == "0.0"
    assert int(values["sample"]) - int(values["last_answered_sample"]) == 3
    answered_ns = int(values["last_answered_stamp_ns"])
    print(f"SIGKILL {stage} ({'balancing' if caught else 'swinging up'}): watchdog trip "
          f"{(trip_ns - killed_ns) * 1e-6:.1f} ms after the kill (driver clock), last answered "
          f"sample {(killed_ns - answered_ns) * 1e-6:.1f} ms before it")
    print(f"named {values.get('behind')} samples behind, sure {values.get('sure')}")
    # named once it has fallen behind (a trip of a stall in force at the kill too)
    assert f"the {stage} (/{stage}) stopped" in trip.message, trip.message
    assert values["silent"] == f"/{stage}"
    # the rig's own log: 0 V from 20 ms after the last answered sample, to the end
    log = true_log(tmp_path)
    after = log[log["unix_s"] >= answered_ns * 1e-9 + 0.020]
    assert len(after) > 20 and np.all(after["applied_v"] == 0.0), after["applied_v"][:10]
    late = log[log["unix_s"] > killed_ns * 1e-9]
    zero = late["unix_s"][np.flatnonzero(late["applied_v"] == 0.0)[0]]
    print(f"0 V at the rig's tick {(zero - killed_ns * 1e-9) * 1e3:.1f} ms after the kill")


@pytest.mark.realtime
def test_sigkill_of_the_controllers_process_leaves_the_driver_to_zero_the_rig(
        tmp_path, env_for_domain, ros_context):
    """Found by a hostile test: SIGKILL of ``pisc_graph --driver`` left the last byte's
    voltage applied. The driver runs in a process of its own: the rig gets 0 V from it,
    before its own firmware watchdog would trip (50 ms after the last byte)."""
    from test_faults import _child_pid

    rig, graph, probe, watch, executor, caught = _start_balancing(
        tmp_path, env_for_domain, ros_context, processes=False)
    driver = _child_pid(graph.pid, "driver_node")
    try:
        assert driver is not None  # its own process
        driving = rig.status()
        killed = time.monotonic()
        graph.kill()
        graph.communicate(timeout=20)
        deadline = time.monotonic() + 20.0
        while Path(f"/proc/{driver}").exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not Path(f"/proc/{driver}").exists()  # it stopped with its parent
        time.sleep(0.1)
        status = rig.status()
    finally:
        if driver is not None and Path(f"/proc/{driver}").exists():
            os.kill(driver, signal.SIGKILL)
        probe.destroy_node()
        rig.stop()
    print(f"driving {driving['applied_v']:.2f} V; last byte {status['last_byte']:#04x}, "
          f"{(status['last_byte_time'] - killed) * 1e3:.1f} ms after the kill")
    assert status["last_byte"] == 0x00 and status["applied_v"] == 0.0  # the driver's 0 V
    log = true_log(tmp_path)
    after = log[log["monotonic_s"] > killed]
    zero = after["monotonic_s"][np.flatnonzero(after["applied_v"] == 0.0)[0]]
    # the zero came from a byte, not from the rig's watchdog, which trips only after it
    trip = status["watchdog_trip_time"]
    assert trip is None or zero < trip, (zero, trip)
    assert np.all(log["applied_v"][log["monotonic_s"] >= zero] == 0.0)
    print(f"0 V at the rig {(zero - killed) * 1e3:.1f} ms after the kill (rig's clock)")


def test_the_driver_publishes_no_sample_before_the_graphs_subscribers_are_there(
        tmp_path, env_for_domain, ros_context):
    """Found by a hostile test: in its own process the driver
    published the rig's first samples before the run's recorder had matched it, so the
    bag lacked them. With driver.min_subscribers = N it publishes nothing until both
    sample topics have N subscribers."""
    rig = start_rig(tmp_path)
    driver = subprocess.Popen(
        [sys.executable, "-m", "pisc_driver.driver_node", "--ros-args", "-p",
         f"driver.port:={rig.device}", "-p", "driver.min_subscribers:=2"],
        env=env_for_domain, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    observer = Node("observer", context=ros_context)
    second = Node("second_reader", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(observer)
    seen: list[int] = []
    observer.create_subscription(
        message_class(JOINT_STATES.type), JOINT_STATES.name,
        lambda m: seen.append(joint_sample_from_msg(m).stamp_ns), qos_profile(JOINT_STATES.qos))
    observer.create_subscription(message_class(MOTOR_CURRENT.type), MOTOR_CURRENT.name,
                                 lambda m: None, qos_profile(MOTOR_CURRENT.qos))
    try:
        # the rig streams 200 frames a second; with one subscriber nothing is published
        assert spin_until(executor, lambda: rig.status()["frames"] > 400, 60.0)
        assert seen == []
        for topic in (JOINT_STATES, MOTOR_CURRENT):
            second.create_subscription(message_class(topic.type), topic.name, lambda m: None,
                                       qos_profile(topic.qos))
        executor.add_node(second)
        assert spin_until(executor, lambda: len(seen) > 20, 30.0), len(seen)
        assert seen == sorted(seen)
    finally:
        driver.send_signal(signal.SIGINT)
        try:
            driver.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            driver.kill()
        observer.destroy_node()
        second.destroy_node()
        rig.stop()

"""Hooks and launch-free ROS 2 fixtures for every test of the project (src/*/test and
test/): a domain per test, a context, spin_until, and the graph helpers the graph tests
share (``from conftest import spin_until``)."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from pisc_bringup.dds import FASTDDS_PROFILE, FASTDDS_PROFILES
from pisc_msgs_py.processes import DomainClaim

__all__ = ["DomainClaim", "VoltageWatch", "recorder_pid", "spin_until",
           "start_graph_with_watch"]

# The tests' own nodes and the graphs they run in this process use the Fast DDS profile
# pisc_graph gives its nodes; set before the process's first DDS participant reads it.
os.environ.setdefault(FASTDDS_PROFILES, str(FASTDDS_PROFILE))
# ... and let idle OpenMP threads (the plant kernel's) sleep, as every command does
# (robustness_cli.quiet_threads): with the default active wait a 60-draw tuning trial of
# the commissioning took 20-35 s in a test worker under load 10, instead of about 2 s
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def pytest_runtest_setup(item: pytest.Item) -> None:
    """A realtime test fails at once, saying why, when other tests run beside it: its
    outcome depends on the machine keeping the wall clock, which a second worker of the
    suite takes from it (``./pisc test`` runs on both cores and leaves them out)."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1 and item.get_closest_marker("realtime") is not None:
        pytest.fail(f"a realtime test with {workers} test workers beside each other: it "
                    "needs the machine to itself; run it alone: ./pisc test -m realtime "
                    "(pytest -n 0)", pytrace=False)


@pytest.fixture(autouse=True)
def _no_virtual_rig_outlives_its_test() -> Iterator[None]:
    """Stop every pisc_virtual_rig a test started and left running (one whose test failed
    before its own clean-up): at SCHED_FIFO it would load every later test of the run."""
    yield
    module = sys.modules.get("pisc_plant.rig_process")
    if module is not None:
        for rig in list(module.RigProcess.running):
            rig.stop()


_FAILED = pytest.StashKey[bool]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """After a failed test's teardown: destroy every node whose context is down. Pytest
    keeps a failed test's traceback, and with it the nodes its frames held, to the end of
    the session; a node never destroyed keeps its publishers in its domain after its
    context's shutdown (a later test given that domain id saw them as intruders)."""
    outcome = yield
    report = outcome.get_result()
    if report.failed:
        item.stash[_FAILED] = True
    if call.when == "teardown" and item.stash.get(_FAILED, False):
        gc.collect()
        for node in [o for o in gc.get_objects() if isinstance(o, Node)]:
            try:
                if not node.context.ok():
                    node.destroy_node()
            except Exception:  # destroyed already, or its context is
                pass


@pytest.fixture
def claim_domain() -> Iterator[Callable[[], int]]:
    """Claim as many domain ids as a test needs; all are released after it."""
    claims: list[DomainClaim] = []

    def claim() -> int:
        claims.append(DomainClaim())
        return claims[-1].domain_id

    yield claim
    for c in claims:
        c.release()


@pytest.fixture
def domain_id(claim_domain: Callable[[], int]) -> int:
    return claim_domain()


@pytest.fixture
def ros_context(domain_id: int) -> Iterator[Context]:
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        yield context
    finally:
        context.try_shutdown()


def spin_until(executor, predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Spin until ``predicate()`` holds or the timeout passes; returns the predicate."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


@pytest.fixture
def env_for_domain(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    return env


def recorder_pid(bag: Path) -> int | None:
    """The pid of the pisc_record process writing ``bag`` (from /proc), if it runs."""
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if str(bag).encode() in cmdline and any(c.endswith(b"pisc_record") or
                                                c == b"pisc_bag.record_cli" for c in cmdline):
            return int(proc.name)
    return None


class VoltageWatch:
    """An outside subscriber of the voltage: each one's DDS reception time (wall clock).

    Subscribes once the graph has found its recorder (the bag's parameter file exists):
    a subscriber there before would be taken for the recorder."""

    def __init__(self, ros_context) -> None:
        from pisc_bag.bag import header_stamp_ns
        from pisc_bag.recorder_node import recording_qos
        from pisc_msgs_py.base_node import message_class
        from pisc_msgs_py.topics import VOLTAGE

        self.node = Node("voltage_watch", context=ros_context)
        self.executor = SingleThreadedExecutor(context=ros_context)
        self.executor.add_node(self.node)
        self.received: list[tuple[int, int]] = []  # (reception ns, stamp)
        self.sub = self.node.create_subscription(
            message_class(VOLTAGE.type), VOLTAGE.name,
            lambda data, info: self.received.append(
                (info["received_timestamp"], header_stamp_ns(data))),
            recording_qos(VOLTAGE), raw=True)

    def spin_until(self, predicate, timeout_s: float) -> bool:
        return spin_until(self.executor, predicate, timeout_s)

    def close(self) -> None:
        if self.sub is not None:
            self.sub = None
            self.node.destroy_node()


def start_graph_with_watch(args: list[str], bag: Path, env, ros_context):
    """``python -m pisc_bringup.graph_cli --bag BAG ARGS`` and, once it has found its
    recorder, a :class:`VoltageWatch` of it."""
    graph = subprocess.Popen([sys.executable, "-m", "pisc_bringup.graph_cli", "--bag",
                              str(bag), *args], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60.0
    while not (bag / "pisc_params.yaml").exists():
        assert graph.poll() is None and time.monotonic() < deadline, graph.communicate()
        time.sleep(0.002)
    return graph, VoltageWatch(ros_context)

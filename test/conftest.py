"""Launch-free ROS 2 test fixtures: a domain per test, a context, spin_until."""

from __future__ import annotations

import gc
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node

from pisc_msgs_py.processes import DomainClaim

__all__ = ["DomainClaim", "recorder_pid", "spin_until"]

@pytest.fixture(autouse=True)
def _no_virtual_rig_outlives_its_test() -> Iterator[None]:
    """Stop every pisc_virtual_rig a test started and left running (one whose test failed
    before its own clean-up): at SCHED_FIFO it would load every later test of the run."""
    yield
    module = sys.modules.get("pisc_plant.virtual_rig")
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
                                                c == b"pisc_bringup.record" for c in cmdline):
            return int(proc.name)
    return None

"""Launch-free ROS 2 test fixtures: a domain per test, a context, spin_until."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable, Iterator

import pytest
import rclpy
from rclpy.context import Context

# Domains 1..99 are free for tests; each test process takes a different block so parallel
# runs on one machine do not hear each other.
_domains = itertools.count(1 + (os.getpid() % 9) * 10)


@pytest.fixture
def domain_id() -> int:
    return next(_domains) % 100 or 1


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

"""Launch-free ROS 2 test fixtures: a domain per test, a context, spin_until."""

from __future__ import annotations

import fcntl
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context

_LOCK_DIR = Path(tempfile.gettempdir()) / "pisc-ros-domains"


class DomainClaim:
    """A ROS domain id no other process on this machine uses while the claim is held.

    Each id 1..100 has a lock file; a claim holds an exclusive lock on one, so test runs
    in parallel (several checkouts, CI and a developer) never hear each other's graphs.
    """

    def __init__(self) -> None:
        _LOCK_DIR.mkdir(exist_ok=True)
        for domain in range(1, 101):
            handle = (_LOCK_DIR / f"{domain}.lock").open("w")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.close()
                continue
            self.domain_id = domain
            self._handle = handle
            return
        raise RuntimeError(f"no free ROS domain id: all of 1..100 are claimed in {_LOCK_DIR}")

    def release(self) -> None:
        self._handle.close()


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

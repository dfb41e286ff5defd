"""Hooks for every test of the project (src/*/test and test/)."""

from __future__ import annotations

import os

import pytest

from pisc_bringup.dds import FASTDDS_PROFILE, FASTDDS_PROFILES

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

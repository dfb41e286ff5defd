"""The lockstep benchmark runs its anchors and both layouts and says what it measured."""

from __future__ import annotations

import re

import pytest

from pisc_bench.lockstep_bench_cli import main

pytestmark = [pytest.mark.bench, pytest.mark.integration]


def test_the_benchmark_prints_anchors_and_both_layouts_with_every_message_recorded(capfd):
    assert main(["--duration", "2", "--repeat", "1", "--hops", "200"]) == 0
    out = capfd.readouterr().out
    print(out)
    anchors = re.findall(r"^anchor: ping-pong, .*: +([\d.]+) us per hop wall, +([\d.]+) us CPU$",
                         out, re.MULTILINE)
    assert len(anchors) == 4 and all(float(wall) > 0 for wall, _ in anchors), out
    for layout in ("one process", "--processes"):
        line = next(l for l in out.splitlines() if l.startswith(f"graph, {layout}:"))
        assert "2 s simulated, loop " in line and "anchor hops" in line, line
        assert line.endswith("every one published"), line

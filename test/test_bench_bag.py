"""Benchmarks of recording and replay; run with `./pisc test -m bench -s test/test_bench_bag.py`.

They print figures (the README quotes them) and assert only what holds on any load:
that each measured run did its work.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from pisc_bringup.bag import TYPESTORE, BagWriter, read_bag
from pisc_bringup.replay import bag_config, load_recorded, replay_bag, replay_cores
from pisc_msgs_py.topics import GRAPH_TOPICS, JOINT_STATES

pytestmark = pytest.mark.bench

SWINGUP = Path(__file__).resolve().parent.parent / "bags" / "default-swingup"
N = 20_000


def joint_states_cdr(k: int) -> bytes:
    import numpy as np

    JointState = TYPESTORE.types["sensor_msgs/msg/JointState"]
    Header = TYPESTORE.types["std_msgs/msg/Header"]
    Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
    msg = JointState(header=Header(stamp=Time(sec=k // 200, nanosec=(k % 200) * 5_000_000),
                                   frame_id=""),
                     name=["cart", "pendulum"], position=np.array([0.001 * k, 3.0]),
                     velocity=np.array([], dtype=float), effort=np.array([], dtype=float))
    return bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


def test_bench_message_write_cost_unchunked_flushed_vs_chunked(tmp_path):
    data = [joint_states_cdr(k) for k in range(N)]
    writer = BagWriter(tmp_path / "unchunked", GRAPH_TOPICS)
    started = time.perf_counter()
    for k, d in enumerate(data):
        writer.write(JOINT_STATES.name, d, k, k)
    unchunked = (time.perf_counter() - started) / N
    writer.close()
    with (tmp_path / "chunked.mcap").open("wb") as stream:
        chunked_writer = Writer(stream, compression=CompressionType.NONE)  # 1 MiB chunks
        chunked_writer.start(profile="ros2", library="bench")
        schema = chunked_writer.register_schema("sensor_msgs/msg/JointState", "ros2msg", b"")
        channel = chunked_writer.register_channel(JOINT_STATES.name, "cdr", schema)
        started = time.perf_counter()
        for k, d in enumerate(data):
            chunked_writer.add_message(channel, k, d, k, sequence=k)
        chunked = (time.perf_counter() - started) / N
        chunked_writer.finish()
    assert sum(1 for _ in read_bag(tmp_path / "unchunked")) == N
    print(f"\nmessage write cost ({N} joint_states of {len(data[0])} bytes): unchunked and "
          f"flushed (BagWriter) {unchunked * 1e6:.1f} us/msg, mcap default 1 MiB chunks "
          f"{chunked * 1e6:.1f} us/msg")


def test_bench_replay_cost_per_cycle():
    cfg, _ = bag_config(SWINGUP)
    started = time.perf_counter()
    run = load_recorded(read_bag(SWINGUP))
    read_s = time.perf_counter() - started
    started = time.perf_counter()
    outputs = replay_cores(run, cfg)
    cores_s = time.perf_counter() - started
    started = time.perf_counter()
    report = replay_bag(SWINGUP)
    total_s = time.perf_counter() - started
    assert report.reproduced and len(outputs["/pisc/motor/voltage"]) == 2001
    cycles = len(run.samples)
    print(f"\nreplay of {SWINGUP.name} ({cycles} cycles): reading and decoding the bag "
          f"{read_s:.2f} s, controller cores {cores_s / cycles * 1e6:.0f} us/cycle, whole "
          f"replay with comparison {total_s:.2f} s ({total_s / cycles * 1e6:.0f} us/cycle)")


@pytest.mark.integration
def test_bench_replay_through_the_nodes(domain_id):
    from pisc_bringup.replay_node import replay_nodes

    started = time.perf_counter()
    report = replay_nodes(SWINGUP, domain_id=domain_id)
    wall = time.perf_counter() - started
    assert report.reproduced
    print(f"\nreplay of {SWINGUP.name} through the nodes over topics: {wall:.1f} s "
          f"({wall / report.cycles * 1e3:.2f} ms/cycle)")

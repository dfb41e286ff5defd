"""The columnar bag reader: the same numbers as the message path, read in
blocks; anything it would have to guess at goes back to the message path, whose errors name
the message."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from pisc_runs.analysis import _limits, analyse_bag, analyse_messages, decimate, write_csv
from pisc_bag.bag import TYPESTORE, BagError, BagWriter, read_bag, read_bag_raw
from pisc_bag.bag_columns import FastPathRefused, read_columns
from pisc_runs.summary import TABLE_TOPICS, summarise, summarise_bag, tables_of_bag
from pisc_msgs_py.topics import CART_FORCE, GRAPH_TOPICS, JOINT_STATES, MODE, VOLTAGE

pytestmark = pytest.mark.bag

BAGS = Path(__file__).resolve().parents[3] / "bags"
SWINGUP = BAGS / "default-swingup"
DRIVER = BAGS / "driver-swingup"


_DECODED: dict[Path, list] = {}


def _messages(bag: Path) -> list:
    """The bag's decoded messages (read once per bag and session: the slow path)."""
    if bag not in _DECODED:
        _DECODED[bag] = list(read_bag(bag))
    return _DECODED[bag]


def _same_columns_as_messages(bag: Path, messages: list | None = None, **kwargs) -> None:
    columns, modes = read_columns(bag, list(TABLE_TOPICS), [MODE.name], **kwargs)
    messages = _messages(bag) if messages is None else messages
    for topic in TABLE_TOPICS:
        ours = [m for m in messages if m.topic == topic]
        got = columns[topic]
        assert len(got) == len(ours), topic
        assert got.stamp_ns.tolist() == [
            m.message.header.stamp.sec * 10**9 + m.message.header.stamp.nanosec for m in ours]
        assert got.log_ns.tolist() == [m.log_time_ns for m in ours]
        assert got.publish_ns.tolist() == [m.publish_time_ns for m in ours]
        for field, values in got.values.items():
            assert np.array_equal(values, [list(getattr(m.message, field)) for m in ours])
    assert [(t, lt) for t, lt, _, _ in modes] == [
        (m.topic, m.log_time_ns) for m in messages if m.topic == MODE.name]


@pytest.mark.parametrize("bag", [SWINGUP, DRIVER], ids=["lockstep", "driver"])
def test_the_columns_are_the_messages_numbers_in_any_block_size(bag):
    for block in (8 * 1024 * 1024, 4096, 100):  # blocks smaller than a chunk, a record
        _same_columns_as_messages(bag, block_bytes=block)


def _copy(bag: Path, out: Path, change=None, compression=None) -> Path:
    """``bag``'s messages written again (through ``change(topic, k, data)`` -> data or
    None to drop), as PISC writes a bag, or with compressed chunks by mcap's Writer."""
    kept = []
    count: dict[str, int] = {}
    for raw in read_bag_raw(bag):
        k = count[raw.topic] = count.get(raw.topic, -1) + 1
        data = raw.data if change is None else change(raw.topic, k, raw.data)
        if data is not None:
            kept.append((raw, data))
    writer = BagWriter(out, GRAPH_TOPICS)
    for raw, data in kept:
        writer.write(raw.topic, data, raw.log_time_ns, raw.publish_time_ns, flush=False)
    writer.close()
    if compression is not None:  # the same file, chunks compressed (as rosbag2 may write)
        path = next(out.glob("*.mcap"))
        from mcap.reader import make_reader
        with path.open("rb") as stream:
            records = list(make_reader(stream).iter_messages(log_time_order=False))
        with path.open("wb") as stream:
            w = Writer(stream, compression=compression, chunk_size=64 * 1024)
            w.start(profile="ros2", library="test")
            schemas, channels = {}, {}
            for schema, channel, message in records:
                if schema.id not in schemas:
                    schemas[schema.id] = w.register_schema(schema.name, schema.encoding,
                                                           schema.data)
                if channel.id not in channels:
                    channels[channel.id] = w.register_channel(
                        channel.topic, channel.message_encoding, schemas[schema.id],
                        channel.metadata)
                w.add_message(channels[channel.id], message.log_time, message.data,
                              message.publish_time, sequence=message.sequence)
            w.finish()
    return out


def test_compressed_chunks_give_the_same_columns(tmp_path):
    bag = _copy(SWINGUP, tmp_path / "zstd", compression=CompressionType.ZSTD)
    _same_columns_as_messages(bag, _messages(SWINGUP))
    bag = _copy(SWINGUP, tmp_path / "lz4", compression=CompressionType.LZ4)
    _same_columns_as_messages(bag, _messages(SWINGUP), block_bytes=4096)


def test_a_chunk_whose_crc_is_wrong_is_refused_by_the_shared_walk(tmp_path):
    """One byte changed in a chunk's records: the walk the column reader and the indexer
    share (pisc_bag.mcap_scan) stops there, so the columns go to the message path and
    repair's check of the file says it cannot be read through."""
    import shutil

    from mcap.reader import make_reader

    from pisc_bag.bag_repair import index_problems

    bag = tmp_path / "crc"
    shutil.copytree(SWINGUP, bag)
    path = next(bag.glob("*.mcap"))
    with path.open("rb") as stream:
        chunk = make_reader(stream).get_summary().chunk_indexes[1]
    data = bytearray(path.read_bytes())
    at = chunk.chunk_start_offset + chunk.chunk_length - 1000  # in a message of the chunk
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(FastPathRefused, match="a chunk that does not parse"):
        read_columns(bag, list(TABLE_TOPICS))
    problems = index_problems(path)
    assert len(problems) == 1 and problems[0].startswith(
        "it cannot be read through (CRCValidationError"), problems


def _joint_message(data: bytes):
    return TYPESTORE.deserialize_cdr(data, "sensor_msgs/msg/JointState")


def _serialise(msg) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


def test_a_value_that_is_not_finite_goes_to_the_message_path_which_names_it(tmp_path):
    def nan_voltage(topic, k, data):
        if topic == VOLTAGE.name and k == 700:
            msg = _joint_message(data)
            msg.effort = np.array([float("nan")])
            return _serialise(msg)
        return data

    bag = _copy(SWINGUP, tmp_path / "nan", nan_voltage)
    with pytest.raises(FastPathRefused, match="not finite"):
        read_columns(bag, list(TABLE_TOPICS))
    with pytest.raises(BagError, match=r"/pisc/motor/voltage: motor.*not finite|finite"):
        summarise_bag(bag, 0.005)
    with pytest.raises(BagError) as message_path:
        analyse_messages(list(read_bag(bag)), "nan", *_limits(bag))
    with pytest.raises(BagError) as ours:
        analyse_bag(bag)
    assert str(ours.value) == f"{bag}: {message_path.value}"


@pytest.mark.parametrize("bag", [SWINGUP, DRIVER], ids=["lockstep", "driver"])
def test_the_cart_force_wrenches_read_as_columns_as_the_messages(bag, tmp_path):
    """geometry_msgs/WrenchStamped (replay reads /pisc/cart_force this way): force and
    torque as values of x, y, z; a value that is not finite goes to the message path."""
    columns, _ = read_columns(bag, [CART_FORCE.name], block_bytes=64 * 1024)
    got = columns[CART_FORCE.name]
    ours = [m for m in _messages(bag) if m.topic == CART_FORCE.name]
    assert got.names == ("x", "y", "z") and len(got) == len(ours) > 2000
    assert got.stamp_ns.tolist() == [
        m.message.header.stamp.sec * 10**9 + m.message.header.stamp.nanosec for m in ours]
    for field in ("force", "torque"):
        assert np.array_equal(got.values[field], [
            [getattr(getattr(m.message.wrench, field), a) for a in "xyz"] for m in ours])

    def nan_force(topic, k, data):
        if topic == CART_FORCE.name and k == 700:
            msg = TYPESTORE.deserialize_cdr(data, CART_FORCE.type)
            msg.wrench.force.x = float("nan")
            return bytes(TYPESTORE.serialize_cdr(msg, CART_FORCE.type))
        return data

    with pytest.raises(FastPathRefused, match="not finite"):
        read_columns(_copy(bag, tmp_path / "nan", nan_force), [CART_FORCE.name])


def test_joint_names_the_bag_does_not_agree_on_are_named_by_the_message_path(tmp_path):
    def renamed(topic, k, data):
        if topic == JOINT_STATES.name and k == 3:
            msg = _joint_message(data)
            msg.name = ["wagon", "pendulum"]  # same length: only the bytes differ
            return _serialise(msg)
        return data

    bag = _copy(SWINGUP, tmp_path / "renamed", renamed)
    with pytest.raises(FastPathRefused, match="differ in layout"):
        read_columns(bag, list(TABLE_TOPICS))
    with pytest.raises(BagError, match=r"joint_states: expected joints \['cart', 'pendulum'\], "
                                       r"got \['wagon', 'pendulum'\]"):
        analyse_bag(bag)


def test_messages_of_other_lengths_and_repeated_stamps_read_as_the_message_path(tmp_path):
    """A frame_id on some set-points (another length: the message path reads that topic)
    and a sample recorded twice with another publish time (a lockstep resend): the
    summary keeps the last of a stamp, the trace the first, on both paths."""
    def odd(topic, k, data):
        if topic == "/pisc/motor/current_setpoint" and k % 3 == 0:
            msg = _joint_message(data)
            msg.header.frame_id = "motor_frame"
            return _serialise(msg)
        return data

    bag = _copy(SWINGUP, tmp_path / "odd", odd)
    with pytest.raises(FastPathRefused, match="several lengths"):
        read_columns(bag, list(TABLE_TOPICS))
    # the message path reads it (frame_id changes no number): what the columns read of
    # the bag it was made from
    assert analyse_bag(bag).format() == analyse_bag(SWINGUP).format()

    raws = list(read_bag_raw(SWINGUP))
    again = tmp_path / "again"
    writer = BagWriter(again, GRAPH_TOPICS)
    for n, raw in enumerate(raws):
        writer.write(raw.topic, raw.data, raw.log_time_ns, raw.publish_time_ns, flush=False)
        if raw.topic == JOINT_STATES.name and n % 50 == 0:  # resent 3 ms later
            writer.write(raw.topic, raw.data, raw.log_time_ns + 1,
                         raw.publish_time_ns + 3_000_000, flush=False)
    writer.close()
    columns, _ = read_columns(again, list(TABLE_TOPICS))
    assert len(columns[JOINT_STATES.name]) > len(set(columns[JOINT_STATES.name].stamp_ns))
    messages = list(read_bag(again))
    fast, slow = summarise_bag(again, 0.005), summarise(messages, 0.005)
    assert dataclasses.asdict(fast) == dataclasses.asdict(slow)
    assert fast.latency_ms != summarise(_messages(SWINGUP), 0.005).latency_ms  # resends count
    a, b = analyse_bag(again), analyse_messages(messages, again.name, *_limits(again))
    for field in dataclasses.fields(a.trace):
        x, y = getattr(a.trace, field.name), getattr(b.trace, field.name)
        assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y, field.name


def test_the_reference_bags_analyse_as_before(tmp_path):
    """The columns give what the message path gives, CSV byte for byte."""
    for bag in (SWINGUP, DRIVER):
        tables = tables_of_bag(bag)
        assert len(tables.joints.stamp_ns) > 2000
        fast = analyse_bag(bag)
        slow = analyse_messages(_messages(bag), bag.name, *_limits(bag))
        assert fast.format() == slow.format()
        write_csv(fast.trace, tmp_path / "fast.csv")
        write_csv(slow.trace, tmp_path / "slow.csv")
        assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "slow.csv").read_bytes()


def test_decimation_keeps_every_peak_and_leaves_short_runs_alone():
    t = np.arange(120_001) * 0.005
    y = np.sin(t) + 0.01 * np.cos(37 * t)
    y[55_555], y[90_001] = 5.0, -4.0
    td, yd = decimate(t, y)
    assert len(td) <= 4000 and np.all(np.diff(td) > 0)
    assert yd.max() == 5.0 and td[np.argmax(yd)] == t[55_555]
    assert yd.min() == -4.0 and td[np.argmin(yd)] == t[90_001]
    # every run's extremes: the envelope of any window of 1/2000 of the run is kept
    for a in range(0, 120_000, 6_000):
        window = slice(a, a + 60)
        inside = (td >= t[window][0]) & (td <= t[window][-1])
        assert yd[inside].max() <= y[window].max() + 1e-12
    short_t, short_y = t[:2001], y[:2001]
    assert decimate(short_t, short_y)[0] is short_t


def test_pisc_bag_analyse_loads_neither_rclpy_nor_the_graph(tmp_path):
    code = ("import sys; from pisc_bringup.bag_cli import main; "
            f"rc = main(['analyse', {str(SWINGUP)!r}, '--out', {str(tmp_path)!r}]); "
            "print(rc, 'rclpy' in sys.modules, 'pisc_bringup.run_start' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.strip().splitlines()[-1] == "0 False False", out.stderr

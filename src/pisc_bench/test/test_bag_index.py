"""Finishing and repairing a bag in bounded memory: the stream is read in
blocks and written indexed in log-time order through a reorder window, or by an external
merge when a message comes too late for the window; the file is the one the mcap
library's writer gave when the whole stream was read into memory, byte for byte."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import pytest
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from pisc_bag import bag_index, mcap_scan
from pisc_bag.bag import BagWriter
from pisc_bag.bag_index import CHUNK_SIZE
from pisc_bag.bag_repair import index_problems, repair_bag
from pisc_bench.bag_bench import recorded_messages
from pisc_bag.bag_readers import read_every_way
from pisc_msgs_py.topics import GRAPH_TOPICS

pytestmark = pytest.mark.bag

SWINGUP = Path(__file__).resolve().parents[3] / "bags" / "lyapunov-swingup"


def recorded_order(seconds: int = 10) -> list[tuple[str, bytes, int, int]]:
    """The reference bag's messages as a recorder takes them: in log-time order but for
    local inversions (each message taken up to 6 ms late, as the reference bags were
    recorded: up to 5.6 ms, 10 messages), repeated with later times for longer
    recordings (what ``bag_bench`` makes)."""
    return list(recorded_messages(SWINGUP, seconds))


def write_stream(directory: Path, messages) -> BagWriter:
    """A bag written as the recorder writes it, not finished."""
    writer = BagWriter(directory, GRAPH_TOPICS)
    for topic, data, log_time, publish_time in messages:
        writer.write(topic, data, log_time, publish_time, flush=False)
    writer.flush()
    return writer


def indexed_in_memory(stream: bytes, library: str = "pisc",
                      compression: CompressionType = CompressionType.NONE) -> bytes:
    """What finishing did before: every record read, the messages sorted by log time
    (stable), written by the mcap library's writer."""
    import io

    from mcap.exceptions import EndOfFile

    schemas, channels, messages = {}, {}, []
    try:
        for record in StreamReader(io.BytesIO(stream)).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                messages.append(record)
    except EndOfFile:  # a stream: no footer
        pass
    out = io.BytesIO()
    writer = Writer(out, chunk_size=CHUNK_SIZE, compression=compression, enable_crcs=True)
    writer.start(profile="ros2", library=library)
    for s in schemas.values():
        writer.register_schema(s.name, s.encoding, s.data)
    for c in channels.values():
        writer.register_channel(c.topic, c.message_encoding, c.schema_id, c.metadata)
    for m in sorted(messages, key=lambda m: m.log_time):
        writer.add_message(m.channel_id, m.log_time, m.data, m.publish_time,
                           sequence=m.sequence)
    writer.finish()
    return out.getvalue()


@pytest.mark.parametrize(("hold", "block"), [(None, None), (50, 64 * 1024), (0, 4096),
                                             (1, 1 << 20)],
                         ids=["default", "small-window", "no-window", "one-held"])
def test_a_finished_bag_is_what_sorting_in_memory_gave_byte_for_byte(tmp_path, monkeypatch,
                                                                     hold, block):
    messages = recorded_order()
    writer = write_stream(tmp_path / "bag", messages)
    stream = writer.path.read_bytes()
    assert sum(b[2] < a[2] for a, b in zip(messages, messages[1:])) > 1000  # inversions
    if hold is not None:
        monkeypatch.setattr(bag_index, "HOLD_MESSAGES", hold)
        monkeypatch.setattr(mcap_scan, "BLOCK_BYTES", block)
    writer.close()
    assert writer.path.read_bytes() == indexed_in_memory(stream)
    assert index_problems(writer.path) == []
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag_0.mcap",
                                                                     "metadata.yaml"]


def test_a_message_older_than_the_window_is_merged_into_its_place(tmp_path, monkeypatch):
    """The window cannot place a message older than what it has written: the file is
    sorted again by an external merge of sorted runs beside the bag, every message in
    its place, the runs removed."""
    messages = recorded_order()
    first = min(m[2] for m in messages)
    late = (messages[0][0], messages[0][1], first + 1, first)  # taken at the very end
    messages = [*messages[:-1], late, messages[-1]]
    writer = write_stream(tmp_path / "bag", messages)
    stream = writer.path.read_bytes()
    monkeypatch.setattr(mcap_scan, "BLOCK_BYTES", 256 * 1024)  # several runs
    out = tmp_path / "out.mcap"
    with out.open("wb") as f:
        written = bag_index.write_sorted(writer.path, f, "pisc")
    assert written.merged and written.messages == len(messages)
    assert out.read_bytes() == indexed_in_memory(stream)
    assert not list(tmp_path.glob("**/.pisc-sort-*"))
    writer.close()
    assert writer.path.read_bytes() == indexed_in_memory(stream)
    got = read_every_way(tmp_path / "bag")
    expected = sorted(((t, lt, d) for t, d, lt, _ in messages), key=lambda m: m[1])
    for reader, read in got.items():
        assert read == expected, reader


def test_repair_of_a_cut_stream_gives_what_sorting_in_memory_gave(tmp_path, monkeypatch):
    messages = recorded_order()
    writer = write_stream(tmp_path / "live", messages)
    stream = writer.path.read_bytes()
    monkeypatch.setattr(bag_index, "HOLD_MESSAGES", 20)
    monkeypatch.setattr(mcap_scan, "BLOCK_BYTES", 32 * 1024)
    for cut in (len(stream) // 3, len(stream) - 5):
        bag = tmp_path / f"cut{cut}"
        bag.mkdir()
        (bag / f"cut{cut}_0.mcap").write_bytes(stream[:cut])
        report = repair_bag(bag)
        whole = report.backup.stat().st_size - report.dropped_bytes
        assert (bag / f"cut{cut}_0.mcap").read_bytes() == indexed_in_memory(
            stream[:whole], "pisc repair")
        assert 0 < report.dropped_bytes < 200 and report.recovered < len(messages)


def test_finishing_holds_a_block_not_the_bag(tmp_path, monkeypatch):
    """The memory a finish takes (Python and numpy allocations, traced) does not grow
    with the bag but with the block, the window and the chunk: a 60 s stream (10 MB)
    takes no more than a 10 s one plus a little, under 4 MB (a 128 KiB block, 1000
    messages held, the 768 KiB chunk and the buffers it is joined from). Reading the
    whole stream took about 0.5 kB a message, 4 times the stream."""
    monkeypatch.setattr(mcap_scan, "BLOCK_BYTES", 128 * 1024)
    monkeypatch.setattr(bag_index, "HOLD_MESSAGES", 1000)
    write_stream(tmp_path / "first", recorded_order(10)[:100]).close()  # imports done
    peaks, sizes = {}, {}
    for seconds in (10, 60):
        writer = write_stream(tmp_path / f"bag{seconds}", recorded_order(seconds))
        sizes[seconds] = writer.path.stat().st_size
        tracemalloc.start()
        writer.close()
        peaks[seconds] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert index_problems(writer.path) == []
    assert peaks[60] < peaks[10] + 1_000_000, peaks
    assert peaks[60] < 4_000_000 < sizes[60], (peaks, sizes)


def test_the_index_check_walks_in_blocks_and_counts_what_the_mcap_reader_counts(tmp_path):
    """index_problems (repair's check of a finished file) counts by the record framing,
    as the mcap reader reading the file through counts; where the walk is not sure (a
    file cut short) the reader decides, and names what it cannot read."""
    from pisc_bag.bag_repair import _index_counts_by_reader

    writer = write_stream(tmp_path / "bag", recorded_order())
    stream = writer.path.read_bytes()
    # as bags were finished before the recorder wrote them indexed and in order
    unindexed = tmp_path / "unindexed.mcap"
    unindexed.write_bytes(stream)
    with unindexed.open("ab") as out:
        out.write(bytes.fromhex("0f0400000000000000") + b"\0\0\0\0")  # data end, no CRC
        out.write(bytes.fromhex("021400000000000000") + bytes(20) + mcap_scan.MCAP_MAGIC)
    writer.close()
    zstd = tmp_path / "zstd.mcap"  # chunks compressed, as other writers may write them
    zstd.write_bytes(indexed_in_memory(stream, compression=CompressionType.ZSTD))
    for path in (writer.path, unindexed, zstd):
        counts = bag_index.index_counts(path)
        assert counts is not None and counts == _index_counts_by_reader(path), path
    assert index_problems(writer.path) == index_problems(zstd) == []
    assert index_problems(unindexed) == [
        "no statistics in its summary",
        "16045 of its 16045 messages are not in chunks (no index finds them)",
        f"{bag_index.index_counts(unindexed).backwards} messages out of log-time order"]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(writer.path.read_bytes()[:100_000])
    assert bag_index.index_counts(cut) is None
    assert index_problems(cut) == ["it cannot be read through (EndOfFile: )"]


def test_repair_removes_what_a_merge_killed_midway_left(tmp_path):
    """A finish killed during the external merge leaves its runs in a temporary
    directory beside the bag: repair removes them with the ``.tmp`` file, and says so,
    for a stream as for a finished bag."""
    writer = write_stream(tmp_path / "live", recorded_order())
    bag = tmp_path / "cut"
    bag.mkdir()
    (bag / "cut_0.mcap").write_bytes(writer.path.read_bytes())
    writer.close()
    for name in (".pisc-sort-abc", ".pisc-sort-def"):
        (bag / name).mkdir()
        (bag / name / "run000000").write_bytes(b"\x05" * 100)
    (bag / "cut_0.mcap.tmp").write_bytes(b"\x89MCAP0")
    report = repair_bag(bag)
    assert report.removed == (bag / "cut_0.mcap.tmp", bag / ".pisc-sort-abc",
                              bag / ".pisc-sort-def")
    assert "removed .pisc-sort-abc (an interrupted finish)" in report.format()
    assert sorted(p.name for p in bag.iterdir()) == ["cut_0.mcap", "cut_0.mcap.unfinished",
                                                      "metadata.yaml"]
    (bag / ".pisc-sort-ghi").mkdir()
    again = repair_bag(bag)  # finished: only the leftover to remove
    assert again.removed == (bag / ".pisc-sort-ghi",) and again.backup is None

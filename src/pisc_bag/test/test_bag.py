"""Bags: written then read back with the mcap and the rosbags readers and as a viewer
opens a file (its indexes); repair of what a dead recorder or a broken metadata.yaml
leaves."""

import subprocess
import sys

import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pisc_bag.bag import BagError, BagWriter, read_bag, read_bag_raw
from pisc_bag.bag_index import CHUNK_SIZE
from pisc_bag.bag_repair import index_problems, repair_bag
from pisc_bag.bag_readers import READERS, read_every_way
from pisc_msgs_py.convert import stamp_from_msg
from pisc_msgs_py.topics import GRAPH_TOPICS, JOINT_STATES, MODE, STATE

TS = get_typestore(Stores.ROS2_JAZZY)


def joint_states_cdr(stamp_ns: int, x: float) -> bytes:
    JointState = TS.types["sensor_msgs/msg/JointState"]
    Header = TS.types["std_msgs/msg/Header"]
    Time = TS.types["builtin_interfaces/msg/Time"]
    import numpy as np
    msg = JointState(header=Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
                                   frame_id=""),
                     name=["cart", "pendulum"], position=np.array([x, 3.0]),
                     velocity=np.array([], dtype=float), effort=np.array([], dtype=float))
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/JointState"))


def test_round_trip_counts_times_and_metadata(tmp_path):
    bag = tmp_path / "run"
    writer = BagWriter(bag, GRAPH_TOPICS)
    for k in range(50):
        data = joint_states_cdr(k * 5_000_000, 0.001 * k)
        writer.write(JOINT_STATES.name, data, 1000 + k, 900 + k)
    writer.close()
    messages = list(read_bag(bag))
    assert len(messages) == 50
    assert [stamp_from_msg(m.message.header.stamp) for m in messages] == [
        k * 5_000_000 for k in range(50)]
    assert messages[7].log_time_ns == 1007 and messages[7].publish_time_ns == 907
    info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap" and info["message_count"] == 50
    counts = {t["topic_metadata"]["name"]: t["message_count"]
              for t in info["topics_with_message_count"]}
    assert counts[JOINT_STATES.name] == 50 and counts[MODE.name] == 0
    mode_qos = next(t for t in info["topics_with_message_count"]
                    if t["topic_metadata"]["name"] == MODE.name)["topic_metadata"]
    assert mode_qos["offered_qos_profiles"][0]["durability"] == "transient_local"
    with AnyReader([bag], default_typestore=TS) as reader:  # what other ROS tools use
        assert reader.message_count == 50
        conn = next(c for c in reader.connections if c.topic == JOINT_STATES.name)
        first = next(reader.messages(connections=[conn]))
        assert list(reader.deserialize(first[2], conn.msgtype).name) == ["cart", "pendulum"]


def test_refuses_to_overwrite_and_names_unreadable_bags(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(BagError, match="exists and is not empty"):
        BagWriter(tmp_path / "full", GRAPH_TOPICS)
    with pytest.raises(BagError, match="empty: no such bag directory"):
        list(read_bag(tmp_path / "empty"))
    (tmp_path / "nometa").mkdir()
    with pytest.raises(BagError, match=r"nometa: not a rosbag2 directory \(no metadata.yaml\)$"):
        list(read_bag(tmp_path / "nometa"))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(BagError, match=r"bad/metadata.yaml: malformed rosbag2 metadata \(KeyError"):
        list(read_bag(bad))
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    with pytest.raises(BagError, match="malformed rosbag2 metadata"):
        list(read_bag(bad))
    (bad / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": {
        "relative_file_paths": ["bad_0.mcap"], "storage_identifier": "mcap"}}))
    with pytest.raises(BagError, match="bad_0.mcap: listed in metadata.yaml but missing"):
        list(read_bag(bad))
    (bad / "bad_0.mcap").write_bytes(b"PK\x03\x04" + b"\x00" * 40)
    with pytest.raises(BagError, match="bad_0.mcap: not an MCAP file"):
        list(read_bag(bad))
    (bad / "bad_0.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 7)
    with pytest.raises(BagError, match=r"bad_0.mcap: truncated, .* `pisc_bag repair .*bad`"):
        list(read_bag(bad))
    # the footer magic but garbage between: the reader's complaint, with the file named
    (bad / "bad_0.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x07" * 40 + b"\x89MCAP0\r\n")
    with pytest.raises(BagError, match="bad_0.mcap: cannot read"):
        list(read_bag(bad))


def write_unfinished(tmp_path, n: int) -> tuple[bytes, list[int]]:
    """The bytes a recorder killed after ``n`` joint_states leaves, and each message's end."""
    bag = tmp_path / "live"
    writer = BagWriter(bag, GRAPH_TOPICS)
    ends = []
    for k in range(n):
        writer.write(JOINT_STATES.name, joint_states_cdr(k * 5_000_000, 0.001 * k), 1000 + k,
                     900 + k)
        ends.append(writer.path.stat().st_size)  # flushed after every message
    data = writer.path.read_bytes()
    return data, ends


def test_repair_recovers_every_whole_message_wherever_the_file_was_cut(tmp_path):
    data, ends = write_unfinished(tmp_path, 8)
    header_end = ends[0] - (ends[1] - ends[0])  # schemas and channels, then messages
    cuts = sorted({header_end, *ends, *(e - 1 for e in ends), *(e + 7 for e in ends[:-1]),
                   len(data)})
    for cut in cuts:
        bag = tmp_path / f"cut{cut}"
        bag.mkdir()
        (bag / f"cut{cut}_0.mcap").write_bytes(data[:cut])
        with pytest.raises(BagError, match="no metadata.yaml.*pisc_bag repair"):
            list(read_bag(bag))
        report = repair_bag(bag)
        whole = sum(1 for e in ends if e <= cut)
        assert report.counts[JOINT_STATES.name] == whole, cut
        assert report.dropped_bytes == cut - (ends[whole - 1] if whole else header_end), cut
        assert report.backup.read_bytes() == data[:cut]
        messages = list(read_bag(bag))
        assert [stamp_from_msg(m.message.header.stamp) for m in messages] == [
            k * 5_000_000 for k in range(whole)]
        if whole:
            assert messages[-1].log_time_ns == 1000 + whole - 1
        info = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        assert info["message_count"] == whole
        mode_qos = next(t for t in info["topics_with_message_count"]
                        if t["topic_metadata"]["name"] == MODE.name)["topic_metadata"]
        assert mode_qos["offered_qos_profiles"][0]["durability"] == "transient_local"
        assert mode_qos["type"] == "diagnostic_msgs/msg/DiagnosticArray"
        with AnyReader([bag], default_typestore=TS) as reader:
            assert reader.message_count == whole


def test_repair_refuses_finished_and_hopeless_files(tmp_path):
    bag = tmp_path / "done"
    writer = BagWriter(bag, GRAPH_TOPICS)
    writer.close()
    with pytest.raises(BagError, match="done_0.mcap: already finished; nothing to repair"):
        repair_bag(bag)
    (tmp_path / "stub").mkdir()
    (tmp_path / "stub" / "stub_0.mcap").write_bytes(b"\x89MCAP0\r\n\x01\x02")
    with pytest.raises(BagError, match="stub_0.mcap: no channel record survived"):
        repair_bag(tmp_path / "stub")
    (tmp_path / "none").mkdir()
    with pytest.raises(BagError, match="expected one .mcap file to repair, found 0"):
        repair_bag(tmp_path / "none")


def assert_every_reader_reads(bag, expected):
    """rosbags, mcap in log-time order and the indexed reader all read ``expected``
    ((topic, log time, data) in log-time order), and the file is indexed and ordered."""
    read = read_every_way(bag)
    for reader in READERS:
        assert read[reader] == expected, reader
    (path,) = bag.glob("*.mcap")
    assert index_problems(path) == []


def out_of_order_messages(n: int) -> list[tuple[str, int, bytes]]:
    """What a recorder takes: two topics, each in order, interleaved out of log-time
    order (a message received earlier on one topic is taken after a later one)."""
    messages = []
    for k in range(n):
        messages.append((STATE.name, 2000 + 10 * k + 7, joint_states_cdr(k * 5_000_000, 0.5)))
        messages.append((JOINT_STATES.name, 2000 + 10 * k,
                         joint_states_cdr(k * 5_000_000, 0.001 * k)))
    return messages


def test_a_finished_bag_is_indexed_in_log_time_order_and_every_reader_reads_it(tmp_path):
    """Found by a hostile test: AnyReader refused PISC bags ("Unindexed MCAP messages are not in
    timestamp order"), and an indexed reader found no message in them (no chunks)."""
    bag = tmp_path / "bag"
    writer = BagWriter(bag, GRAPH_TOPICS)
    taken = out_of_order_messages(5000)  # 1.2 MB: more than one chunk
    for topic, log_time, data in taken:
        writer.write(topic, data, log_time, log_time - 5)
    writer.close()
    expected = sorted(taken, key=lambda m: m[1])
    assert_every_reader_reads(bag, expected)
    from mcap.reader import make_reader

    with (bag / "bag_0.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    stats = summary.statistics
    assert stats.message_count == 10000 and stats.chunk_count == len(summary.chunk_indexes) >= 2
    assert stats.message_start_time == 2000 and stats.message_end_time == expected[-1][1]
    for chunk in summary.chunk_indexes:  # each chunk: up to CHUNK_SIZE, message indexes
        assert chunk.uncompressed_size <= CHUNK_SIZE + 200
        assert set(chunk.message_index_offsets) == {
            cid for cid, c in summary.channels.items()
            if c.topic in (STATE.name, JOINT_STATES.name)}
    assert [m.log_time_ns for m in read_bag_raw(bag)] == [m[1] for m in expected]
    assert not list(tmp_path.glob("bag/*.tmp"))  # written beside, renamed over the stream


def test_a_repaired_bag_is_indexed_in_log_time_order_and_every_reader_reads_it(tmp_path):
    writer = BagWriter(tmp_path / "live", GRAPH_TOPICS)
    taken = out_of_order_messages(500)
    for topic, log_time, data in taken:
        writer.write(topic, data, log_time, log_time - 5)
    bag = tmp_path / "killed"
    bag.mkdir()
    (bag / "killed_0.mcap").write_bytes(writer.path.read_bytes()[:-30])  # cut inside one
    writer.close()
    report = repair_bag(bag)
    assert report.recovered == 999 and report.backup.name == "killed_0.mcap.unfinished"
    expected = sorted(taken[:-1], key=lambda m: m[1])
    assert_every_reader_reads(bag, expected)


def finished_bag(tmp_path, name="done", n=40):
    bag = tmp_path / name
    writer = BagWriter(bag, GRAPH_TOPICS)
    for k in range(n):
        writer.write(JOINT_STATES.name, joint_states_cdr(k * 5_000_000, 0.001 * k), 1000 + k,
                     900 + k)
    writer.close()
    return bag


MALFORMED = r"metadata.yaml: malformed rosbag2 metadata \(.*\); `pisc_bag repair .*done` rebuilds"


@pytest.mark.parametrize(("garbage", "refusal"), [
    ("", MALFORMED),
    ("rosbag2_bagfile_information: [\n", MALFORMED),
    ("\x00\x07 not yaml: [\n", MALFORMED),
    ("just a string\n", MALFORMED),
    ("rosbag2_bagfile_information: {}\n", MALFORMED),
    ("rosbag2_bagfile_information:\n  relative_file_paths: [other.mcap]\n"
     "  storage_identifier: mcap\n  message_count: 40\n  topics_with_message_count: []\n",
     "other.mcap: listed in metadata.yaml but missing"),
], ids=["empty", "broken-yaml", "binary", "string", "no-keys", "wrong-file"])
def test_repair_rebuilds_a_broken_metadata_yaml_from_the_mcap_file(tmp_path, garbage, refusal):
    """Found by a hostile test: `pisc_bag repair` said "already finished; nothing to
    repair" and the bag stayed unreadable although its MCAP file was whole."""
    bag = finished_bag(tmp_path)
    good = (bag / "metadata.yaml").read_text()
    mcap_bytes = (bag / "done_0.mcap").read_bytes()
    (bag / "metadata.yaml").write_text(garbage)
    with pytest.raises(BagError, match=refusal):
        list(read_bag(bag))
    completed = subprocess.run([sys.executable, "-m", "pisc_bringup.bag_cli", "repair", str(bag)],
                               capture_output=True, text=True, timeout=120)
    assert completed.returncode == 0, completed.stderr
    assert "metadata.yaml rebuilt from the MCAP file (the one found is kept as " \
           "metadata.yaml.broken)" in completed.stdout
    assert "left as it was" in completed.stdout
    assert (bag / "metadata.yaml").read_text() == good
    assert (bag / "metadata.yaml.broken").read_text() == garbage
    assert (bag / "done_0.mcap").read_bytes() == mcap_bytes  # whole and indexed: untouched
    assert len(list(read_bag(bag))) == 40
    with pytest.raises(BagError, match="already finished; nothing to repair"):
        repair_bag(bag)


def test_repair_writes_a_missing_metadata_yaml_of_an_indexed_file(tmp_path):
    """A finish interrupted between the indexed file's rename and metadata.yaml."""
    bag = finished_bag(tmp_path)
    good = (bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").unlink()
    report = repair_bag(bag)
    assert report.backup is None and report.metadata_backup is None
    assert report.found == ("no metadata.yaml",)
    assert (bag / "metadata.yaml").read_text() == good


def test_repair_finishes_a_stream_whose_finish_was_interrupted(tmp_path):
    """Killed while writing the indexed file: the stream is whole, a partial .tmp lies
    beside it; repair removes it and finishes the stream."""
    writer = BagWriter(tmp_path / "live", GRAPH_TOPICS)
    for k in range(30):
        writer.write(JOINT_STATES.name, joint_states_cdr(k * 5_000_000, 0.0), 1000 + k, 900 + k)
    bag = tmp_path / "cut"
    bag.mkdir()
    (bag / "cut_0.mcap").write_bytes(writer.path.read_bytes())
    writer.close()
    (bag / "cut_0.mcap.tmp").write_bytes(writer.path.read_bytes()[:500])
    report = repair_bag(bag)
    assert report.recovered == 30 and report.removed == (bag / "cut_0.mcap.tmp",)
    assert not (bag / "cut_0.mcap.tmp").exists()
    assert "removed cut_0.mcap.tmp (an interrupted finish)" in report.format()
    assert len(list(read_bag(bag))) == 30


def test_repair_indexes_a_finished_bag_written_unindexed(tmp_path):
    """Bags finished before the finish indexed them (unchunked, out of log-time order):
    repair writes them indexed and in order, keeping the file as found; the metadata is
    the same."""
    from mcap.writer import CompressionType, Writer

    bag = finished_bag(tmp_path)
    good = (bag / "metadata.yaml").read_text()
    path = bag / "done_0.mcap"
    records = list(read_bag_raw(bag))
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    with path.open("wb") as out:  # as the recorder finished a bag before
        writer = Writer(out, compression=CompressionType.NONE, use_chunking=False)
        writer.start(profile="ros2", library="pisc")
        for sid, schema in summary.schemas.items():
            assert writer.register_schema(schema.name, schema.encoding, schema.data) == sid
        for cid, c in summary.channels.items():
            assert writer.register_channel(c.topic, c.message_encoding, c.schema_id,
                                           c.metadata) == cid
        channel = next(c for c, ch in summary.channels.items() if ch.topic == JOINT_STATES.name)
        for m in reversed(records):
            writer.add_message(channel, m.log_time_ns, m.data, m.publish_time_ns)
        writer.finish()
    found = index_problems(path)
    assert found == ["40 of its 40 messages are not in chunks (no index finds them)",
                     "39 messages out of log-time order"]
    from rosbags.rosbag2.errors import ReaderError

    with pytest.raises(ReaderError, match="Unindexed MCAP messages are not in timestamp order"):
        read_every_way(bag)
    report = repair_bag(bag)
    assert report.backup.name == "done_0.mcap.unindexed" and report.found == tuple(found)
    assert_every_reader_reads(bag, [(m.topic, m.log_time_ns, m.data) for m in records])
    assert (bag / "metadata.yaml").read_text() == good


def test_a_recorder_killed_before_its_first_message_leaves_a_bag_repair_finishes(tmp_path):
    """The schemas and channels reach the file when the bag is created: a recorder
    killed before its first message left only the MCAP magic, and repair found "no
    channel record" (pisc_graph could not finish such a bag)."""
    from pisc_bag.bag import bag_topics

    writer = BagWriter(tmp_path / "live", GRAPH_TOPICS)
    bag = tmp_path / "empty"
    bag.mkdir()
    (bag / "empty_0.mcap").write_bytes(writer.path.read_bytes())
    writer.close()
    report = repair_bag(bag)
    assert report.recovered == 0 and list(report.counts) == [t.name for t in GRAPH_TOPICS]
    assert list(read_bag(bag)) == [] and bag_topics(bag) == [t.name for t in GRAPH_TOPICS]
    assert_every_reader_reads(bag, [])

"""Bags: written then read back with both the mcap and the rosbags readers."""

import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pisc_bringup.bag import BagError, BagWriter, read_bag, repair_bag
from pisc_msgs_py.convert import stamp_from_msg
from pisc_msgs_py.topics import GRAPH_TOPICS, JOINT_STATES, MODE

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

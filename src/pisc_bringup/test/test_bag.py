"""Bags: written then read back with both the mcap and the rosbags readers."""

import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pisc_bringup.bag import BagError, BagWriter, read_bag
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
    with pytest.raises(BagError, match="no metadata.yaml"):
        list(read_bag(tmp_path / "empty"))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bad / "bad_0.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 7)
    with pytest.raises(BagError, match="bad_0.mcap: cannot read"):
        list(read_bag(bad))

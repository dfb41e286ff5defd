"""rosbag2 directories with MCAP storage: writing raw CDR messages, reading them back.

A bag is a directory holding ``metadata.yaml`` and ``<name>_0.mcap``, the layout
``ros2 bag`` writes on Jazzy, so a PISC bag opens with ``ros2 bag info``, rosbags,
mcap-ros2-support, Foxglove and PlotJuggler. Message definitions come from the
rosbags type store (the Jazzy definitions), embedded as ``ros2msg`` schemas; each
channel carries its offered QoS profile and type hash as rosbag2 does.

The MCAP file is written without chunks and flushed after each message, so a recorder
that dies loses at most what the operating system had not yet been handed; a bag
closed normally gets its summary, footer and ``metadata.yaml``.

Times: ``log_time`` is when the recorder received a message and ``publish_time`` when
it was sent (DDS source timestamp), both wall-clock nanoseconds; the control cycle's
own time is in each message's header stamp.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2.metadata import dump_qos_v8, dump_qos_v9
from rosbags.typesys import Stores, get_typestore

from pisc_msgs_py.topics import QosSpec, Topic

__all__ = ["BagError", "BagMessage", "BagWriter", "read_bag"]

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ROSBAG2_VERSION = 9
_NEVER = QosTime(0x7FFFFFFF, 0xFFFFFFFF)  # rmw's "infinite" duration as rosbag2 dumps it


class BagError(RuntimeError):
    """A bag cannot be written or read; the message names the path and the problem."""


def _qos(spec: QosSpec) -> Qos:
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=spec.depth,
        reliability=QosReliability.RELIABLE if spec.reliable else QosReliability.BEST_EFFORT,
        durability=(QosDurability.TRANSIENT_LOCAL if spec.transient_local
                    else QosDurability.VOLATILE),
        deadline=_NEVER,
        lifespan=_NEVER,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=_NEVER,
        avoid_ros_namespace_conventions=False,
    )


@dataclass
class _Channel:
    topic: Topic
    channel_id: int
    type_hash: str
    count: int = 0


class BagWriter:
    """Write raw (CDR) messages of known topics into a new rosbag2 MCAP bag."""

    def __init__(self, directory: str | Path, topics: Sequence[Topic]) -> None:
        self.directory = Path(directory)
        if self.directory.exists() and any(self.directory.iterdir()):
            raise BagError(f"{self.directory}: exists and is not empty; not overwriting a bag")
        self.directory.mkdir(parents=True, exist_ok=True)
        self.path = self.directory / f"{self.directory.name}_0.mcap"
        self._file = self.path.open("wb")
        self._writer = Writer(
            self._file, compression=CompressionType.NONE, use_chunking=False, enable_crcs=True)
        self._writer.start(profile="ros2", library="pisc")
        self._channels: dict[str, _Channel] = {}
        self._schemas: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns = 0
        self._closed = False
        for topic in topics:
            self._add(topic)
        self._file.flush()

    def _add(self, topic: Topic) -> None:
        schema_id = self._schemas.get(topic.type)
        if schema_id is None:
            text, _ = TYPESTORE.generate_msgdef(topic.type, ros_version=2)
            schema_id = self._writer.register_schema(topic.type, "ros2msg", text.encode())
            self._schemas[topic.type] = schema_id
        type_hash = TYPESTORE.hash_rihs01(topic.type)
        channel_id = self._writer.register_channel(
            topic.name, "cdr", schema_id,
            {"offered_qos_profiles": dump_qos_v8([_qos(topic.qos)]),
             "topic_type_hash": type_hash},
        )
        self._channels[topic.name] = _Channel(topic, channel_id, type_hash)

    def write(self, topic_name: str, data: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        channel = self._channels[topic_name]
        channel.count += 1
        self._writer.add_message(channel.channel_id, log_time_ns, data, publish_time_ns,
                                 sequence=channel.count)
        self._file.flush()
        if self._first_ns is None:
            self._first_ns = log_time_ns
        self._first_ns = min(self._first_ns, log_time_ns)
        self._last_ns = max(self._last_ns, log_time_ns)

    @property
    def counts(self) -> dict[str, int]:
        return {name: c.count for name, c in self._channels.items()}

    def close(self) -> None:
        """Finish the MCAP file (summary, footer) and write ``metadata.yaml``."""
        if self._closed:
            return
        self._closed = True
        self._writer.finish()
        self._file.close()
        start = self._first_ns or 0
        duration = max(0, self._last_ns - start)
        total = sum(c.count for c in self._channels.values())
        info = {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "relative_file_paths": [self.path.name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": total,
            "topics_with_message_count": [
                {
                    "topic_metadata": {
                        "name": c.topic.name,
                        "type": c.topic.type,
                        "serialization_format": "cdr",
                        "offered_qos_profiles": dump_qos_v9([_qos(c.topic.qos)]),
                        "type_description_hash": c.type_hash,
                    },
                    "message_count": c.count,
                }
                for c in self._channels.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [{
                "path": self.path.name,
                "starting_time": {"nanoseconds_since_epoch": start},
                "duration": {"nanoseconds": duration},
                "message_count": total,
            }],
            "custom_data": None,
            "ros_distro": "jazzy",
        }
        text = yaml.safe_dump({"rosbag2_bagfile_information": info}, default_flow_style=False,
                              sort_keys=False)
        tmp = self.directory / "metadata.yaml.tmp"
        tmp.write_text(text)
        tmp.replace(self.directory / "metadata.yaml")


@dataclass(frozen=True)
class BagMessage:
    topic: str
    log_time_ns: int
    publish_time_ns: int | None
    message: Any  # decoded by rosbags; attribute access like an rclpy message


def read_bag(directory: str | Path, topics: Sequence[str] | None = None) -> Iterator[BagMessage]:
    """Decoded messages of a PISC bag in file order, or :class:`BagError` saying why not.

    Uses the mcap reader (which exposes both log and publish times) and decodes CDR with
    the rosbags type store.
    """
    directory = Path(directory)
    if not (directory / "metadata.yaml").exists():
        raise BagError(f"{directory}: not a rosbag2 directory (no metadata.yaml)")
    files = sorted(directory.glob("*.mcap"))
    if not files:
        raise BagError(f"{directory}: no .mcap file")
    for path in files:
        try:
            with path.open("rb") as stream:
                reader = make_reader(stream)
                for schema, channel, message in reader.iter_messages(topics=topics):
                    if schema is None:
                        raise BagError(f"{path}: channel {channel.topic} has no schema")
                    yield BagMessage(
                        channel.topic, message.log_time, message.publish_time,
                        TYPESTORE.deserialize_cdr(message.data, schema.name))
        except BagError:
            raise
        except Exception as exc:  # the readers raise several unrelated types for bad files
            raise BagError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from exc

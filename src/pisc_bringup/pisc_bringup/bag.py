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

import io
import struct
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

__all__ = ["BagError", "BagMessage", "BagWriter", "RawMessage", "RepairReport", "bag_files",
           "header_stamp_ns", "read_bag", "read_bag_raw", "repair_bag"]

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
        _write_metadata(self.directory, self.path.name, [
            _TopicRecord(c.topic.name, c.topic.type, _qos(c.topic.qos), c.type_hash, c.count)
            for c in self._channels.values()
        ], self._first_ns or 0, self._last_ns)


@dataclass(frozen=True)
class _TopicRecord:
    name: str
    type: str
    qos: Qos
    type_hash: str
    count: int


def _write_metadata(directory: Path, file_name: str, topics: Sequence[_TopicRecord],
                    first_ns: int, last_ns: int) -> None:
    """rosbag2 ``metadata.yaml`` (version 9) for one MCAP file, written atomically."""
    duration = max(0, last_ns - first_ns)
    total = sum(t.count for t in topics)
    info = {
        "version": ROSBAG2_VERSION,
        "storage_identifier": "mcap",
        "relative_file_paths": [file_name],
        "duration": {"nanoseconds": duration},
        "starting_time": {"nanoseconds_since_epoch": first_ns},
        "message_count": total,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.type,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": dump_qos_v9([t.qos]),
                    "type_description_hash": t.type_hash,
                },
                "message_count": t.count,
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [{
            "path": file_name,
            "starting_time": {"nanoseconds_since_epoch": first_ns},
            "duration": {"nanoseconds": duration},
            "message_count": total,
        }],
        "custom_data": None,
        "ros_distro": "jazzy",
    }
    text = yaml.safe_dump({"rosbag2_bagfile_information": info}, default_flow_style=False,
                          sort_keys=False)
    tmp = directory / "metadata.yaml.tmp"
    tmp.write_text(text)
    tmp.replace(directory / "metadata.yaml")


@dataclass(frozen=True)
class BagMessage:
    topic: str
    log_time_ns: int
    publish_time_ns: int | None
    message: Any  # decoded by rosbags; attribute access like an rclpy message


def header_stamp_ns(data: bytes) -> int | None:
    """Stamp of a little-endian CDR message that starts with std_msgs/Header, else None."""
    if len(data) < 12 or data[1] not in (0x01, 0x03):  # CDR_LE or PL_CDR_LE
        return None
    sec, nanosec = struct.unpack_from("<iI", data, 4)
    return sec * 1_000_000_000 + nanosec


MCAP_MAGIC = b"\x89MCAP0\r\n"


def bag_files(directory: str | Path) -> list[Path]:
    """The MCAP files of a rosbag2 directory, checked; :class:`BagError` says what is wrong.

    The files are those ``metadata.yaml`` lists. A file that does not end with the MCAP
    magic was not finished (its recorder was killed): :func:`repair_bag` recovers it.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f"{directory}: no such bag directory")
    meta = directory / "metadata.yaml"
    if not meta.exists():
        hint = (f"; if its recorder was killed, `pisc_bag repair {directory}` rebuilds it"
                if any(directory.glob("*.mcap")) else "")
        raise BagError(f"{directory}: not a rosbag2 directory (no metadata.yaml){hint}")
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        names = info["relative_file_paths"]
        storage = info["storage_identifier"]
    except (yaml.YAMLError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise BagError(f"{meta}: malformed rosbag2 metadata ({type(exc).__name__}: {exc})") \
            from None
    if storage != "mcap":
        raise BagError(f"{meta}: storage {storage!r}, only 'mcap' bags are read")
    if not names:
        raise BagError(f"{meta}: lists no bag file")
    files = [directory / n for n in names]
    for path in files:
        if not path.is_file():
            raise BagError(f"{path}: listed in metadata.yaml but missing")
        size = path.stat().st_size
        with path.open("rb") as stream:
            head = stream.read(8)
            stream.seek(max(0, size - 8))
            tail = stream.read(8)
        if head != MCAP_MAGIC:
            raise BagError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        if size < 16 or tail != MCAP_MAGIC:
            raise BagError(
                f"{path}: truncated, it ends without the MCAP footer (the recording was not "
                f"finished); `pisc_bag repair {directory}` recovers its messages")
    return files


def bag_topics(directory: str | Path) -> list[str]:
    """The topics a bag recorded (its ``metadata.yaml``), with or without messages."""
    bag_files(directory)  # checks the directory and its metadata
    info = yaml.safe_load((Path(directory) / "metadata.yaml").read_text())
    try:
        return [t["topic_metadata"]["name"]
                for t in info["rosbag2_bagfile_information"]["topics_with_message_count"]]
    except (KeyError, TypeError) as exc:
        raise BagError(f"{directory}/metadata.yaml: malformed topic list "
                       f"({type(exc).__name__}: {exc})") from None


def read_bag(directory: str | Path, topics: Sequence[str] | None = None) -> Iterator[BagMessage]:
    """Decoded messages of a PISC bag in file order, or :class:`BagError` saying why not.

    :func:`read_bag_raw`'s messages (the mcap reader exposes both log and publish times),
    the CDR decoded with the rosbags type store.
    """
    for raw in read_bag_raw(directory, topics):
        try:
            message = TYPESTORE.deserialize_cdr(raw.data, raw.type)
        except Exception as exc:  # rosbags raises several unrelated types for bad data
            raise BagError(f"{directory}: {raw.topic}: cannot decode a {raw.type} "
                           f"({type(exc).__name__}: {exc})") from exc
        yield BagMessage(raw.topic, raw.log_time_ns, raw.publish_time_ns, message)


@dataclass(frozen=True)
class RawMessage:
    topic: str
    type: str  # ROS 2 type name, from the channel's schema
    log_time_ns: int
    data: bytes  # CDR, as recorded
    publish_time_ns: int | None = None


def read_bag_raw(directory: str | Path,
                 topics: Sequence[str] | None = None) -> Iterator[RawMessage]:
    """The recorded CDR bytes of a PISC bag in file order, undecoded (for playback)."""
    for path in bag_files(directory):
        try:
            with path.open("rb") as stream:
                for schema, channel, message in make_reader(stream).iter_messages(topics=topics):
                    if schema is None:
                        raise BagError(f"{path}: channel {channel.topic} has no schema")
                    yield RawMessage(channel.topic, schema.name, message.log_time, message.data,
                                     message.publish_time)
        except BagError:
            raise
        except Exception as exc:  # the readers raise several unrelated types for bad files
            raise BagError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from exc


@dataclass(frozen=True)
class RepairReport:
    """What :func:`repair_bag` did."""

    path: Path  # the repaired MCAP file
    backup: Path  # the unfinished file as it was found
    counts: dict[str, int]  # messages recovered per topic
    dropped_bytes: int  # the incomplete record at the end, discarded

    @property
    def recovered(self) -> int:
        return sum(self.counts.values())

    def format(self) -> str:
        lines = [f"repaired {self.path}: recovered {self.recovered} messages "
                 f"({self.dropped_bytes} bytes of an incomplete last record dropped); "
                 f"the file as found is kept as {self.backup.name}"]
        lines += [f"  {name} {count}" for name, count in self.counts.items()]
        return "\n".join(lines)


def repair_bag(directory: str | Path) -> RepairReport:
    """Finish a bag whose recorder died: rebuild its MCAP summary and ``metadata.yaml``.

    Reads the unfinished file record by record up to the first incomplete or corrupt
    record, writes the schemas, channels and messages found into a finished MCAP file
    (same ids, times and sequence numbers) and writes ``metadata.yaml``. The file as
    found is kept beside it with the suffix ``.unfinished``. A bag that is already
    finished is left alone (:class:`BagError`).
    """
    from mcap.records import Channel, DataEnd, Footer, Message, Schema
    from mcap.stream_reader import StreamReader

    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f"{directory}: no such bag directory")
    candidates = sorted(directory.glob("*.mcap"))
    if len(candidates) != 1:
        raise BagError(f"{directory}: expected one .mcap file to repair, found "
                       f"{len(candidates)}")
    path = candidates[0]
    raw = path.read_bytes()
    if not raw.startswith(MCAP_MAGIC):
        raise BagError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    if len(raw) >= 16 and raw.endswith(MCAP_MAGIC) and (directory / "metadata.yaml").exists():
        raise BagError(f"{path}: already finished; nothing to repair")

    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    messages: list[Message] = []
    complete = _whole_records_end(raw)
    try:
        for record in StreamReader(io.BytesIO(raw[:complete]), validate_crcs=True).records:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
            elif isinstance(record, Message):
                messages.append(record)
            elif isinstance(record, (DataEnd, Footer)):
                break
    except Exception:  # noqa: BLE001, S110 - whole records that do not parse end the data
        pass
    if not channels:
        raise BagError(f"{path}: no channel record survived; nothing to recover")

    backup = path.with_name(path.name + ".unfinished")
    path.replace(backup)
    with path.open("wb") as out:
        writer = Writer(out, compression=CompressionType.NONE, use_chunking=False,
                        enable_crcs=True)
        writer.start(profile="ros2", library="pisc repair")
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data)
                      for sid, s in schemas.items()}
        channel_ids = {cid: writer.register_channel(c.topic, c.message_encoding,
                                                    schema_ids.get(c.schema_id, 0), c.metadata)
                       for cid, c in channels.items()}
        counts = {c.topic: 0 for c in channels.values()}
        known = [m for m in messages if m.channel_id in channel_ids]
        for m in known:
            writer.add_message(channel_ids[m.channel_id], m.log_time, m.data, m.publish_time,
                               sequence=m.sequence)
            counts[channels[m.channel_id].topic] += 1
        writer.finish()
    records = []
    for cid, c in channels.items():
        schema = schemas.get(c.schema_id)
        qos = _parse_offered_qos(c.metadata.get("offered_qos_profiles", ""))
        records.append(_TopicRecord(c.topic, schema.name if schema else "", qos,
                                    c.metadata.get("topic_type_hash", ""), counts[c.topic]))
    times = [m.log_time for m in known]
    _write_metadata(directory, path.name, records, min(times, default=0), max(times, default=0))
    return RepairReport(path, backup, counts, len(raw) - complete)


def _whole_records_end(raw: bytes) -> int:
    """Offset after the last whole record: each is opcode (1 byte), length (8 bytes LE), body.

    The reader does not notice a record cut short (it reads what is left), so the framing
    is walked here first and the incomplete tail is never handed to it.
    """
    offset = len(MCAP_MAGIC)
    while offset + 9 <= len(raw):
        (length,) = struct.unpack_from("<Q", raw, offset + 1)
        end = offset + 9 + length
        if end > len(raw):
            break
        offset = end
    return offset


def _parse_offered_qos(text: str) -> Qos:
    from rosbags.rosbag2.metadata import parse_qos

    try:
        parsed = parse_qos(text)
    except Exception:  # noqa: BLE001 - an unreadable profile is recorded as the default
        parsed = []
    return parsed[0] if parsed else _qos(QosSpec(depth=100))

"""rosbag2 directories with MCAP storage: writing raw CDR messages, reading them back.

A bag is a directory holding ``metadata.yaml`` and ``<name>_0.mcap``, the layout
``ros2 bag`` writes on Jazzy, so a PISC bag opens with ``ros2 bag info``, rosbags,
mcap-ros2-support, Foxglove and PlotJuggler. Message definitions come from the
rosbags type store (the Jazzy definitions), embedded as ``ros2msg`` schemas; each
channel carries its offered QoS profile and type hash as rosbag2 does.

**While recording** the MCAP file is a stream: every message is written unchunked, in
the order the recorder took it, and handed to the operating system at once, so a
recorder that dies, even by SIGKILL, loses only what it had not yet taken.

**Finishing** (:meth:`BagWriter.close`, and :func:`pisc_bag.bag_repair.repair_bag` for a
recorder that
died) rewrites the stream as an indexed file, the way rosbag2 writes MCAP: the messages
in log-time order (stable: a tie keeps the recorded order) in chunks of up to 768 KiB
(libmcap's default, which rosbag2 uses), each followed by its message indexes, and a
summary with the schemas, channels, statistics, one chunk index per chunk and the
summary offsets, as the ``mcap`` library's writer lays them out. The stream is read and
written a block at a time, in bounded memory (:mod:`pisc_bag.bag_index`: a reorder
window, and an external merge beside the bag if a message comes too late for it). The
indexed file is written
beside the stream (``<name>_0.mcap.tmp``), synced, and renamed over it, and
``metadata.yaml`` is written last (also through a rename): a finish that is
interrupted leaves either the whole stream or the whole indexed file, and
``pisc_bag repair`` completes it.

Times: ``log_time`` is when the recorder received a message and ``publish_time`` when
it was sent (DDS source timestamp), both wall-clock nanoseconds; the control cycle's
own time is in each message's header stamp.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable, Iterator, Sequence
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

from pisc_bag.bag_index import Written, write_sorted
from pisc_bag.mcap_scan import MCAP_MAGIC, NotMcap
from pisc_msgs_py.topics import QosSpec, Topic

__all__ = ["BagError", "BagMessage", "BagWriter", "RawMessage", "bag_files", "bag_topics",
           "header_stamp_ns", "read_bag", "read_bag_raw", "topic_counts", "topic_records",
           "write_indexed", "write_metadata"]

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
ROSBAG2_VERSION = 9
TEMP_SUFFIX = ".tmp"  # the indexed file while it is written, beside the stream
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
    """Write raw (CDR) messages of known topics into a new rosbag2 MCAP bag.

    Messages are streamed unchunked as they come (:meth:`write`); :meth:`close` finishes
    the bag: indexed, in log-time order, with ``metadata.yaml`` (see the module).
    """

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
        self._closed = False
        self.finish_s: float | None = None  # how long close() took to index the file
        for topic in topics:
            self._add(topic)
        self._writer.flush()  # the schemas and channels: a bag killed now is still whole

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

    def add_topic(self, topic: Topic) -> None:
        """A topic not given at the start (a channel of the stream from here on)."""
        if topic.name not in self._channels:
            self._add(topic)

    def write(self, topic_name: str, data: bytes, log_time_ns: int, publish_time_ns: int,
              flush: bool = True) -> None:
        """Append one message to the stream; ``flush`` hands it to the operating system
        now (else :meth:`flush` does, e.g. once for the messages taken together)."""
        channel = self._channels[topic_name]
        channel.count += 1
        self._writer.add_message(channel.channel_id, log_time_ns, data, publish_time_ns,
                                 sequence=channel.count)
        if flush:
            self._file.flush()

    def flush(self) -> None:
        self._file.flush()

    @property
    def counts(self) -> dict[str, int]:
        return {name: c.count for name, c in self._channels.items()}

    def close(self) -> None:
        """Finish the bag: the stream rewritten indexed and in log-time order, then
        ``metadata.yaml``. :class:`BagError` if that fails (the stream is then left for
        ``pisc_bag repair``)."""
        if self._closed:
            return
        self._closed = True
        import time

        self._file.close()  # the stream: whole records, no summary
        started = time.perf_counter()
        try:
            _finish_stream(self.directory, self.path)
        except (OSError, BagError) as exc:
            raise BagError(f"{self.path}: could not finish the bag ({exc}); `pisc_bag repair "
                           f"{self.directory}` finishes it from the recorded stream") from exc
        self.finish_s = time.perf_counter() - started


def _finish_stream(directory: Path, path: Path) -> Written:
    """What :meth:`BagWriter.close` does once the stream is closed: ``path`` rewritten
    indexed and in log-time order, then ``metadata.yaml``."""
    written = write_indexed(path, "pisc")
    write_metadata(directory, path.name,
                   topic_records(written.schemas, written.channels, topic_counts(written)),
                   written.first_ns, written.last_ns)
    return written


@dataclass(frozen=True)
class _TopicRecord:
    name: str
    type: str
    qos: Qos
    type_hash: str
    count: int


def write_metadata(directory: Path, file_name: str, topics: Sequence[_TopicRecord],
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


def bag_files(directory: str | Path) -> list[Path]:
    """The MCAP files of a rosbag2 directory, checked; :class:`BagError` says what is wrong.

    The files are those ``metadata.yaml`` lists. A file that does not end with the MCAP
    magic was not finished (its recorder was killed):
    :func:`pisc_bag.bag_repair.repair_bag` recovers it.
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
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
        hint = (f"; `pisc_bag repair {directory}` rebuilds it from the MCAP file"
                if any(directory.glob("*.mcap")) else "")
        raise BagError(f"{meta}: malformed rosbag2 metadata ({type(exc).__name__}: "
                       f"{' '.join(str(exc).split())}){hint}") from None
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


def write_indexed(path: Path, library: str,
                  before_replace: Callable[[Written], None] | None = None) -> Written:
    """Rewrite ``path`` (an MCAP file: a stream, finished or not, or an indexed file) as
    an indexed MCAP file in log-time order, in bounded memory
    (:func:`pisc_bag.bag_index.write_sorted`: the whole records up to the first
    incomplete or corrupt one).

    Written to ``path`` + :data:`TEMP_SUFFIX`, synced, then renamed over ``path`` (an
    interruption leaves ``path`` as it was); ``before_replace`` is called with what was
    written before the rename (an exception from it removes the new file and leaves
    ``path`` alone). Messages of a channel that has no channel record before them are
    dropped: they cannot be read.
    """
    tmp = path.with_name(path.name + TEMP_SUFFIX)
    with tmp.open("wb") as out:
        try:
            written = write_sorted(path, out, library)
        except NotMcap as exc:
            raise BagError(str(exc)) from None
        out.flush()
        os.fsync(out.fileno())
    if before_replace is not None:
        try:
            before_replace(written)
        except BaseException:
            tmp.unlink()
            raise
    tmp.replace(path)
    return written


def topic_records(schemas: dict[int, Any], channels: dict[int, Any],
                  counts: dict[str, int]) -> list[_TopicRecord]:
    topics = []
    for c in channels.values():
        schema = schemas.get(c.schema_id)
        qos = _parse_offered_qos(c.metadata.get("offered_qos_profiles", ""))
        topics.append(_TopicRecord(c.topic, schema.name if schema else "", qos,
                                   c.metadata.get("topic_type_hash", ""), counts[c.topic]))
    return topics


def topic_counts(written: Written) -> dict[str, int]:
    counts: dict[str, int] = {}
    for cid, c in written.channels.items():
        counts[c.topic] = counts.get(c.topic, 0) + written.counts.get(cid, 0)
    return counts


def _parse_offered_qos(text: str) -> Qos:
    from rosbags.rosbag2.metadata import parse_qos

    try:
        parsed = parse_qos(text)
    except Exception:  # noqa: BLE001 - an unreadable profile is recorded as the default
        parsed = []
    return parsed[0] if parsed else _qos(QosSpec(depth=100))

"""rosbag2 directories with MCAP storage: writing raw CDR messages, reading them back.

A bag is a directory holding ``metadata.yaml`` and ``<name>_0.mcap``, the layout
``ros2 bag`` writes on Jazzy, so a PISC bag opens with ``ros2 bag info``, rosbags,
mcap-ros2-support, Foxglove and PlotJuggler. Message definitions come from the
rosbags type store (the Jazzy definitions), embedded as ``ros2msg`` schemas; each
channel carries its offered QoS profile and type hash as rosbag2 does.

**While recording** the MCAP file is a stream: every message is written unchunked, in
the order the recorder took it, and handed to the operating system at once, so a
recorder that dies, even by SIGKILL, loses only what it had not yet taken.

**Finishing** (:meth:`BagWriter.close`, and :func:`repair_bag` for a recorder that
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

import io
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

from pisc_bag.bag_index import (
    CHUNK_SIZE,
    MCAP_MAGIC,
    SCRATCH_PREFIX,
    IndexCounts,
    NotMcap,
    Written,
    index_counts,
    write_sorted,
)
from pisc_msgs_py.topics import QosSpec, Topic

__all__ = ["BagError", "BagMessage", "BagWriter", "RawMessage", "RepairReport", "bag_files",
           "header_stamp_ns", "index_problems", "read_bag", "read_bag_raw", "repair_bag"]

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
    written = _write_indexed(path, "pisc")
    _write_metadata(directory, path.name,
                    _topic_records(written.schemas, written.channels, _topic_counts(written)),
                    written.first_ns, written.last_ns)
    return written


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


def _write_indexed(path: Path, library: str,
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


def _topic_records(schemas: dict[int, Any], channels: dict[int, Any],
                   counts: dict[str, int]) -> list[_TopicRecord]:
    topics = []
    for c in channels.values():
        schema = schemas.get(c.schema_id)
        qos = _parse_offered_qos(c.metadata.get("offered_qos_profiles", ""))
        topics.append(_TopicRecord(c.topic, schema.name if schema else "", qos,
                                   c.metadata.get("topic_type_hash", ""), counts[c.topic]))
    return topics


def _topic_counts(written: Written) -> dict[str, int]:
    counts: dict[str, int] = {}
    for cid, c in written.channels.items():
        counts[c.topic] = counts.get(c.topic, 0) + written.counts.get(cid, 0)
    return counts


def index_problems(path: str | Path) -> list[str]:
    """What keeps a finished MCAP file from being indexed and in log-time order, as
    :class:`BagWriter` and :func:`repair_bag` write it: ``[]`` when nothing does.

    Checked: a summary with statistics; every message in a chunk with a chunk index in
    the summary; every message listed by a message index; the statistics' message count;
    log times that never decrease in file order. The file is walked in blocks
    (:func:`pisc_bag.bag_index.index_counts`); where that walk is not sure, the mcap
    reader reads it through and names what it cannot read.
    """
    counts = index_counts(Path(path)) or _index_counts_by_reader(Path(path))
    if isinstance(counts, str):
        return [counts]
    messages, in_chunks, indexed = counts.messages, counts.in_chunks, counts.indexed
    chunks, chunk_indexes, backwards = counts.chunks, counts.chunk_indexes, counts.backwards
    statistics = counts.statistics
    problems = []
    if statistics is None:
        problems.append("no statistics in its summary")
    elif statistics != messages:
        problems.append(f"its statistics count {statistics} messages, the file holds "
                        f"{messages}")
    if in_chunks != messages:
        problems.append(f"{messages - in_chunks} of its {messages} messages are not in chunks "
                        "(no index finds them)")
    if chunk_indexes != chunks:
        problems.append(f"{chunk_indexes} chunk indexes in its summary for {chunks} chunks")
    if indexed != in_chunks:
        problems.append(f"its message indexes list {indexed} of the {in_chunks} messages in "
                        "chunks")
    if backwards:
        problems.append(f"{backwards} messages out of log-time order")
    return problems


def _index_counts_by_reader(path: Path) -> IndexCounts | str:
    """:class:`IndexCounts` as the mcap reader reads the file through (chunk and data
    section CRCs checked), or what it cannot read."""
    from mcap.records import Chunk, ChunkIndex, Message, MessageIndex, Statistics
    from mcap.stream_reader import StreamReader, breakup_chunk

    messages = in_chunks = indexed = backwards = chunks = chunk_indexes = 0
    statistics = None
    last: int | None = None
    try:
        with path.open("rb") as stream:
            for record in StreamReader(stream, validate_crcs=True, emit_chunks=True).records:
                inner: list[Any] = [record]
                if isinstance(record, Chunk):
                    chunks += 1
                    inner = breakup_chunk(record, validate_crc=True)
                    in_chunks += sum(isinstance(r, Message) for r in inner)
                elif isinstance(record, MessageIndex):
                    indexed += len(record.records)
                elif isinstance(record, ChunkIndex):
                    chunk_indexes += 1
                elif isinstance(record, Statistics):
                    statistics = record.message_count
                for r in inner:
                    if isinstance(r, Message):
                        messages += 1
                        backwards += last is not None and r.log_time < last
                        last = r.log_time
    except Exception as exc:  # noqa: BLE001 - the readers raise several unrelated types
        return f"it cannot be read through ({type(exc).__name__}: {exc})"
    return IndexCounts(messages, in_chunks, indexed, backwards, chunks, chunk_indexes,
                       statistics)


def _metadata_problem(directory: Path, file_name: str, counts: dict[str, int]) -> str | None:
    """What is wrong with a bag's ``metadata.yaml`` for an MCAP file holding ``counts``
    messages per topic, or None."""
    meta = directory / "metadata.yaml"
    if not meta.exists():
        return "no metadata.yaml"
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        names = info["relative_file_paths"]
        storage = info["storage_identifier"]
        total = info["message_count"]
        listed = {t["topic_metadata"]["name"]: t["message_count"]
                  for t in info["topics_with_message_count"]}
    except (yaml.YAMLError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
        return f"metadata.yaml is malformed ({type(exc).__name__}: {' '.join(str(exc).split())})"
    if storage != "mcap" or names != [file_name]:
        return (f"metadata.yaml lists {names!r} in storage {storage!r}, not the MCAP file "
                f"{file_name}")
    if total != sum(counts.values()) or listed != counts:
        return (f"metadata.yaml disagrees with {file_name} ({total} messages listed, "
                f"{sum(counts.values())} in the file)")
    return None


@dataclass(frozen=True)
class RepairReport:
    """What :func:`repair_bag` did."""

    path: Path  # the repaired MCAP file
    backup: Path | None  # the MCAP file as it was found, when it was rewritten
    counts: dict[str, int]  # messages recovered per topic
    dropped_bytes: int  # the incomplete or unreadable end of the file, discarded
    found: tuple[str, ...] = ()  # what was wrong
    metadata_backup: Path | None = None  # a metadata.yaml that was wrong, as found
    removed: tuple[Path, ...] = ()  # an interrupted finish's temporary file

    @property
    def recovered(self) -> int:
        return sum(self.counts.values())

    def format(self) -> str:
        first = f"repaired {self.path}: recovered {self.recovered} messages"
        if self.backup is not None and self.backup.suffix == ".unfinished":
            first += f" ({self.dropped_bytes} bytes of an incomplete last record dropped)"
        if self.backup is not None:
            first += f"; the file as found is kept as {self.backup.name}"
        lines = [first, f"  found: {'; '.join(self.found)}"]
        if self.backup is not None:
            lines.append("  rewritten indexed, in log-time order")
        else:
            lines.append("  the MCAP file was whole, indexed and in order: left as it was")
        lines.append("  metadata.yaml rebuilt from the MCAP file" + (
            f" (the one found is kept as {self.metadata_backup.name})"
            if self.metadata_backup is not None else ""))
        lines += [f"  removed {p.name} (an interrupted finish)" for p in self.removed]
        lines += [f"  {name} {count}" for name, count in self.counts.items()]
        return "\n".join(lines)


def repair_bag(directory: str | Path) -> RepairReport:
    """Finish a bag whose recorder died, or whose finish was interrupted, and rebuild a
    missing or broken ``metadata.yaml`` from its MCAP file.

    An MCAP file that is not finished, not indexed or not in log-time order is read
    record by record up to the first incomplete or corrupt record, and its schemas,
    channels and messages (same times and sequence numbers) are written as a finished,
    indexed file in log-time order (as :meth:`BagWriter.close` does); the file as found
    is kept beside it with the suffix ``.unfinished`` (or ``.unindexed``). A
    ``metadata.yaml`` that is missing, malformed or disagrees with the MCAP file is
    written anew from it; a wrong one is kept as ``metadata.yaml.broken``. A bag with
    nothing to repair is left alone (:class:`BagError`).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise BagError(f"{directory}: no such bag directory")
    candidates = sorted(directory.glob("*.mcap"))
    if len(candidates) != 1:
        raise BagError(f"{directory}: expected one .mcap file to repair, found "
                       f"{len(candidates)}")
    path = candidates[0]
    leftover = path.with_name(path.name + TEMP_SUFFIX)
    with path.open("rb") as stream:
        if stream.read(8) != MCAP_MAGIC:
            raise BagError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        stream.seek(0, io.SEEK_END)
        size = stream.tell()
        stream.seek(max(0, size - 8))
        finished = size >= 16 and stream.read(8) == MCAP_MAGIC
    found = [] if finished else ["the file ends without the MCAP footer (its recording "
                                 "was not finished)"]
    if finished:
        found += index_problems(path)

    if not found:  # a whole, indexed file: the metadata alone may be wrong
        with path.open("rb") as stream:
            reader = make_reader(stream)
            summary = reader.get_summary()
        stats = summary.statistics
        counts = {c.topic: stats.channel_message_counts.get(cid, 0)
                  for cid, c in summary.channels.items()}
        problem = _metadata_problem(directory, path.name, counts)
        if problem is None:
            removed = _remove(leftover)
            if removed:
                return RepairReport(path, None, counts, 0, ("an interrupted finish's "
                                    "temporary file",), None, removed)
            raise BagError(f"{path}: already finished; nothing to repair")
        meta_backup = _keep_broken_metadata(directory)
        times = ((stats.message_start_time, stats.message_end_time) if stats.message_count
                 else (0, 0))
        _write_metadata(directory, path.name,
                        _topic_records(summary.schemas, summary.channels, counts), *times)
        removed = _remove(leftover)
        return RepairReport(path, None, counts, 0, (problem,), meta_backup, removed)

    removed = _remove(leftover)
    backup = path.with_name(path.name + (".unindexed" if finished else ".unfinished"))

    def keep_as_found(written: Written) -> None:
        if not written.channels:
            raise BagError(f"{path}: no channel record survived; nothing to recover")
        _link_or_copy(path, backup)

    written = _write_indexed(path, "pisc repair", keep_as_found)
    counts = _topic_counts(written)
    problem = _metadata_problem(directory, path.name, counts)
    meta_backup = None
    if problem is not None and problem != "no metadata.yaml":
        found.append(problem)
        meta_backup = _keep_broken_metadata(directory)
    _write_metadata(directory, path.name,
                    _topic_records(written.schemas, written.channels, counts),
                    written.first_ns, written.last_ns)
    dropped = written.size - written.whole_bytes if not finished else 0
    return RepairReport(path, backup, counts, dropped, tuple(found), meta_backup, removed)


def _remove(leftover: Path) -> tuple[Path, ...]:
    """An interrupted finish's leftovers: its ``.tmp`` file, and the temporary
    directories of an external merge beside it."""
    import shutil

    removed = []
    if leftover.exists():
        leftover.unlink()
        removed.append(leftover)
    for scratch in sorted(leftover.parent.glob(SCRATCH_PREFIX + "*")):
        if scratch.is_dir():
            shutil.rmtree(scratch)
            removed.append(scratch)
    return tuple(removed)


def _keep_broken_metadata(directory: Path) -> Path | None:
    meta = directory / "metadata.yaml"
    if not meta.exists():
        return None
    backup = directory / "metadata.yaml.broken"
    meta.replace(backup)
    return backup


def _link_or_copy(path: Path, backup: Path) -> None:
    """``backup``: the bytes of ``path`` as they are now (a hard link, else a copy)."""
    import shutil

    if backup.exists():
        backup.unlink()
    try:
        os.link(path, backup)
    except OSError:
        shutil.copyfile(path, backup)


def _parse_offered_qos(text: str) -> Qos:
    from rosbags.rosbag2.metadata import parse_qos

    try:
        parsed = parse_qos(text)
    except Exception:  # noqa: BLE001 - an unreadable profile is recorded as the default
        parsed = []
    return parsed[0] if parsed else _qos(QosSpec(depth=100))

"""Repairing a bag: finishing one whose recorder died or whose finish was interrupted,
and rebuilding a missing or broken ``metadata.yaml`` (``pisc_bag repair``); and
:func:`index_problems`, what keeps a finished MCAP file from being indexed and in
log-time order as :class:`pisc_bag.bag.BagWriter` writes it.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader

from pisc_bag.bag import (
    TEMP_SUFFIX,
    BagError,
    topic_counts,
    topic_records,
    write_indexed,
    write_metadata,
)
from pisc_bag.bag_index import SCRATCH_PREFIX, IndexCounts, Written, index_counts
from pisc_bag.mcap_scan import MCAP_MAGIC

__all__ = ["RepairReport", "index_problems", "repair_bag"]


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
        write_metadata(directory, path.name,
                       topic_records(summary.schemas, summary.channels, counts), *times)
        removed = _remove(leftover)
        return RepairReport(path, None, counts, 0, (problem,), meta_backup, removed)

    removed = _remove(leftover)
    backup = path.with_name(path.name + (".unindexed" if finished else ".unfinished"))

    def keep_as_found(written: Written) -> None:
        if not written.channels:
            raise BagError(f"{path}: no channel record survived; nothing to recover")
        _link_or_copy(path, backup)

    written = write_indexed(path, "pisc repair", keep_as_found)
    counts = topic_counts(written)
    problem = _metadata_problem(directory, path.name, counts)
    meta_backup = None
    if problem is not None and problem != "no metadata.yaml":
        found.append(problem)
        meta_backup = _keep_broken_metadata(directory)
    write_metadata(directory, path.name,
                   topic_records(written.schemas, written.channels, counts),
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

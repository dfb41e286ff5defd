"""A bag read by each reader the project promises it opens with, message by message.

* ``rosbags``: rosbags' ``AnyReader`` (what ROS tools written in Python use), which
  refuses an unindexed MCAP file whose messages are not in log-time order;
* ``mcap``: the mcap library's reader in log-time order
  (``iter_messages(log_time_order=True)``);
* ``indexed``: the way a viewer opens a file that has a summary (MCAP's TypeScript
  ``McapIndexedReader`` in Foxglove and the web viewers): only through the summary's
  chunk indexes and each chunk's message indexes. A file without them yields nothing
  here, as it does there.

:func:`read_every_way` gives each reader's messages as (topic, log time, CDR bytes);
the tests compare them with what was written.
"""

from __future__ import annotations

import io
from pathlib import Path

from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message, MessageIndex
from mcap.stream_reader import get_chunk_data_stream
from rosbags.highlevel import AnyReader

from pisc_bag.bag import TYPESTORE, bag_files

__all__ = ["READERS", "indexed_messages", "read_every_way"]

READERS = ("rosbags", "mcap", "indexed")

Read = list[tuple[str, int, bytes]]  # (topic, log time, data) in the order read


def read_every_way(bag: str | Path) -> dict[str, Read]:
    """Every message of ``bag`` (a rosbag2 directory) as each of :data:`READERS` reads it."""
    bag = Path(bag)
    (path,) = bag_files(bag)
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        by_rosbags = [(c.topic, t, bytes(d)) for c, t, d in reader.messages()]
    with path.open("rb") as stream:
        by_mcap = [(c.topic, m.log_time, m.data)
                   for _, c, m in make_reader(stream).iter_messages(log_time_order=True)]
    return {"rosbags": by_rosbags, "mcap": by_mcap, "indexed": indexed_messages(path)}


def indexed_messages(path: str | Path) -> Read:
    """The messages of an MCAP file found through its summary's chunk indexes and each
    chunk's message indexes, in log-time order (ties in file order), as an indexed
    reader finds them; a file with no chunk index yields none."""
    out: list[tuple[int, int, int, str, int, bytes]] = []
    with Path(path).open("rb") as stream:
        summary = make_reader(stream).get_summary()
        if summary is None:
            return []
        for chunk_index in summary.chunk_indexes:
            stream.seek(chunk_index.chunk_start_offset + 1 + 8)
            chunk = Chunk.read(ReadDataStream(stream))
            data, _ = get_chunk_data_stream(chunk, validate_crc=True)
            records = io.BytesIO(data.read(chunk.uncompressed_size))
            for channel_id, offset in chunk_index.message_index_offsets.items():
                stream.seek(offset + 1 + 8)
                index = MessageIndex.read(ReadDataStream(stream))
                assert index.channel_id == channel_id
                for log_time, at in index.records:
                    records.seek(at)
                    record = ReadDataStream(records)
                    record.read1()  # opcode
                    message = Message.read(record, record.read8())
                    out.append((log_time, chunk_index.chunk_start_offset, at,
                                summary.channels[message.channel_id].topic, message.log_time,
                                message.data))
    out.sort(key=lambda m: m[:3])
    return [(topic, log_time, data) for _, _, _, topic, log_time, data in out]

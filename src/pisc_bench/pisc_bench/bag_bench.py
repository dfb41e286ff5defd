"""A long bag for the bag tools' benchmark (:mod:`pisc_bench.bag_bench_cli`).

The bag is made as the recorder makes one: an unfinished stream written by
:class:`~pisc_bag.bag.BagWriter`, the messages of ``--from`` (default the reference
bag ``bags/default-swingup``, 10 s) repeated until the stream is ``--seconds`` long, each
repetition with its log, publish and header times moved on by the source's length, and
taken in the order a recorder takes them: each message up to 6 ms late, so the log
times have local inversions as recorded bags had (up to 5.6 ms). Replaying such a bag
runs every cycle through the controllers, but they do not give the recorded outputs
after the first repetition (the run starts again from where it ended): the figure is
the time and memory of reading, replaying and comparing, not a verdict. ``--from`` a
recording at least ``--seconds`` long (``pisc_graph --duration 600 --bag BAG``) is used
as it is, its messages re-recorded in the same way.
"""

from __future__ import annotations

import shutil
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

__all__ = ["make_stream", "recorded_messages"]

REPO = Path(__file__).resolve().parents[3]
DEFAULT_SOURCE = REPO / "bags" / "default-swingup"
LATE_NS = 6_000_000  # each message taken up to this late (uniform), a recorder's order


def _shifted(data: bytes, by_ns: int) -> bytes:
    """A CDR message whose first field is a time (every PISC topic's header stamp, or
    ``/clock``'s clock) with that time moved on by ``by_ns``."""
    from pisc_bag.bag import header_stamp_ns

    stamp = header_stamp_ns(data)
    if stamp is None or not by_ns:
        return data
    out = bytearray(data)
    struct.pack_into("<iI", out, 4, *divmod(stamp + by_ns, 1_000_000_000))
    return bytes(out)


def recorded_messages(source: Path, seconds: float, seed: int = 16) -> Iterator[tuple[str, bytes, int, int]]:
    """(topic, data, log time, publish time) of the stream, in a recorder's order, made
    one repetition of ``source`` at a time."""
    from pisc_bag.bag import header_stamp_ns, read_bag_raw

    raw = list(read_bag_raw(source))
    logs = np.array([m.log_time_ns for m in raw], dtype=np.int64)
    stamps = [header_stamp_ns(m.data) for m in raw]
    known = [s for s in stamps if s is not None]
    period = 5_000_000
    log_span = int(logs.max() - logs.min()) + period
    stamp_span = (max(known) - min(known) + period) if known else 0
    # a run's length is its simulated time, the header stamps' (lockstep runs faster
    # than the wall clock the log times follow)
    repeats = max(1, round(seconds * 1e9 / (stamp_span or log_span)))
    rng = np.random.default_rng(seed)
    for k in range(repeats):
        order = np.argsort(logs + rng.integers(0, LATE_NS, len(raw)), kind="stable")
        for i in order.tolist():
            m = raw[i]
            yield (m.topic, _shifted(m.data, k * stamp_span), m.log_time_ns + k * log_span,
                   (m.publish_time_ns or m.log_time_ns) + k * log_span)


def make_stream(directory: Path, source: Path, seconds: float, seed: int = 16) -> int:
    """An unfinished bag (the stream a recorder leaves before finishing) in
    ``directory``, with the source's parameter files; returns its message count."""
    from pisc_bag.bag import BagWriter, bag_topics
    from pisc_msgs_py.topics import GRAPH_TOPICS

    names = set(bag_topics(source))
    writer = BagWriter(directory, [t for t in GRAPH_TOPICS if t.name in names])
    n = 0
    for topic, data, log_time, publish_time in recorded_messages(source, seconds, seed):
        writer.write(topic, data, log_time, publish_time, flush=False)
        n += 1
    writer.flush()
    writer._file.close()  # noqa: SLF001 - left unfinished, as a recorder leaves it
    writer._closed = True  # noqa: SLF001
    for params in ("pisc_params.yaml", "plant_params.yaml"):
        if (source / params).exists():
            shutil.copyfile(source / params, directory / params)
    return n

"""The frame parser against lost bytes and flipped bits (``pisc_parser_bench``,
:mod:`pisc_bench.parser_bench_cli`).

    pisc_parser_bench [--frames 200000] [--adversarial-frames 100000]
                      [--adversarial-counts 0xAAAA 0xAA01 0x00AA 0]
                      [--rates 1e-4 1e-3 1e-2] [--seed 1]

Frames come from the rig's own physics: a batch of simulated rigs (pisc_plant) driven by
random sinusoidal voltages, swinging the pendulum through every encoder value and the
cart from stop to stop, encoded through the sensors' inverse calibrations. Each rig's
stream is cut as the link would cut it (bursts of 7 bytes every 5 ms at 115200 baud),
then damaged byte by byte: a byte is lost with probability p ("drop") or has one bit
flipped ("flip").

A second, adversarial stream (:func:`adversarial_frames`) puts the header value 0xAA in
every data byte where the sensors can put it at once: every IR and current code has the
low byte 0xAA, and the encoder rests or swings by up to 400 counts about a count that
makes its bytes look like a header (0xAAAA: both bytes 0xAA; 0xAA01: 0xAA followed by a
byte that passes as an ADC high byte) or like ADC high bytes (0x00AA and 0x0000: the
pendulum hanging at rest). It is damaged by drops only (a flipped bit is a false frame
whatever the stream).

Three parsers read the same damaged stream, burst by burst:

* naive: wait for 0xAA, take the next six bytes;
* FrameParser fed bytes only (no arrival times);
* FrameParser fed bytes with the arrival time of each burst (what the driver does).

For each it prints frames delivered, **false frames** (delivered but not a frame the
device sent: misframed, or with a flipped bit that no check can see without a
checksum), of them those whose **values were never sent** (a misframed frame whose six
data bytes are nevertheless one sent frame's, with a 0xAA from elsewhere as its header,
delivers true values), intact frames lost, and frames to resynchronise after an isolated
damaged frame (1 = the next frame is delivered again). A frame "delivered late" came out
of the parser only when a later burst arrived (while hunting, confirmed by the next
header).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pisc_driver.protocol import (
    FRAME_LENGTH,
    Frame,
    FrameParser,
    NaiveParser,
    encode_frame,
    wrap_count,
)
from pisc_model.params import LoopParams
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig

__all__ = ["ADVERSARIAL_COUNTS", "ParserScore", "adversarial_frames", "damage",
           "rig_frames", "score"]

BYTE_S = 10 / 115200  # 8N1: ten bits per byte
PERIOD_S = 0.005

# encoder counts (as the 16-bit register holds them) about which the adversarial rigs rest
ADVERSARIAL_COUNTS = (0xAAAA, 0xAA01, 0x00AA, 0x0000)


def rig_frames(n_frames: int, rigs: int = 100, seed: int = 1) -> list[list[bytes]]:
    """Frames of ``rigs`` simulated rigs, ``n_frames`` in all, as the PIC encodes them."""
    rng = np.random.default_rng(seed)
    config = PlantConfig(loop=LoopParams())
    plant = Plant(config)
    per_rig = -(-n_frames // rigs)
    x0 = rng.uniform(-0.15, 0.08, rigs)
    state = plant.initial_state(x0, 0.0, np.pi + rng.uniform(-0.3, 0.3, rigs), 0.0)
    amplitude = rng.uniform(4.0, 11.47, rigs)
    frequency = rng.uniform(0.7, 4.0, rigs)
    phase = rng.uniform(0.0, 2 * np.pi, rigs)
    period = config.loop.period_s
    out: list[list[bytes]] = [[] for _ in range(rigs)]
    for k in range(per_rig):
        ir, cur, count = plant.raw_measurement(state)
        for r in range(rigs):
            out[r].append(encode_frame(Frame(int(ir[r]), int(cur[r]), wrap_count(int(count[r])))))
        voltage = amplitude * np.sin(2 * np.pi * frequency * k * period + phase)
        state = plant.advance(state, voltage, period)
    total = 0
    for r in range(rigs):  # trim to exactly n_frames
        keep = min(per_rig, n_frames - total)
        out[r] = out[r][:keep]
        total += keep
    return [frames for frames in out if frames]


def adversarial_frames(n_frames: int, rigs: int = 100, seed: int = 1,
                       counts: tuple[int, ...] = ADVERSARIAL_COUNTS,
                       swing_counts: float = 400.0) -> list[list[bytes]]:
    """Frames of ``rigs`` rigs, ``n_frames`` in all, with 0xAA in as many data bytes as
    the sensors allow: every IR and current code ends in 0xAA (the high byte, 0..3, is
    drawn per rig), and the encoder count stays near one of ``counts`` (rig ``r`` near
    ``counts[r % len(counts)]``): one in three of each count's rigs rests there (the
    count jitters by one), the others swing about it by up to ``swing_counts`` at 0.3-2 Hz
    (at most about 25 counts per period, well inside the parser's rate bound).
    """
    rng = np.random.default_rng(seed)
    per_rig = -(-n_frames // rigs)
    out: list[list[bytes]] = []
    total = 0
    for r in range(rigs):
        keep = min(per_rig, n_frames - total)
        if keep <= 0:
            break
        total += keep
        k = np.arange(keep)
        resting = (r // len(counts)) % 3 == 0
        amplitude = 0.0 if resting else rng.uniform(0.0, swing_counts)
        frequency = rng.uniform(0.3, 2.0)
        phase = rng.uniform(0.0, 2 * np.pi)
        offset = np.round(amplitude * np.sin(2 * np.pi * frequency * k * PERIOD_S + phase))
        offset += rng.integers(-1, 2, keep)
        ir = (int(rng.integers(0, 4)) << 8) | 0xAA
        current = (int(rng.integers(0, 4)) << 8) | 0xAA
        centre = counts[r % len(counts)]
        out.append([encode_frame(Frame(ir, current, wrap_count(centre + int(d))))
                    for d in offset])
    return out


@dataclass
class Damaged:
    """A damaged stream: bursts as received, and for each received byte its origin."""

    bursts: list[bytes]
    frame_of: np.ndarray  # transmitted frame index of each received byte
    position: np.ndarray  # position 0..6 inside that frame
    flipped: np.ndarray  # bool: a bit of this byte was flipped
    damaged_frames: np.ndarray  # bool per transmitted frame


def damage(frames: list[bytes], kind: str, rate: float, rng: np.random.Generator) -> Damaged:
    n = len(frames)
    data = np.frombuffer(b"".join(frames), dtype=np.uint8).copy()
    frame_of = np.repeat(np.arange(n), FRAME_LENGTH)
    position = np.tile(np.arange(FRAME_LENGTH), n)
    hit = rng.random(len(data)) < rate
    damaged = np.zeros(n, dtype=bool)
    damaged[frame_of[hit]] = True
    flipped = np.zeros(len(data), dtype=bool)
    if kind == "drop":
        keep = ~hit
    elif kind == "flip":
        bits = rng.integers(0, 8, len(data)).astype(np.uint8)
        data[hit] ^= (np.uint8(1) << bits[hit])
        flipped = hit
        keep = np.ones(len(data), dtype=bool)
    else:
        raise ValueError(f"damage kind {kind!r}: expected 'drop' or 'flip'")
    data, frame_of, position, flipped = data[keep], frame_of[keep], position[keep], flipped[keep]
    bursts = []
    bounds = np.searchsorted(frame_of, np.arange(n + 1))
    for k in range(n):
        bursts.append(data[bounds[k]:bounds[k + 1]].tobytes())
    return Damaged(bursts, frame_of, position, flipped, damaged)


@dataclass
class ParserScore:
    delivered: int = 0
    false_frames: int = 0
    misframed: int = 0
    wrong_values: int = 0  # false frames whose values no sent frame had
    intact_lost: int = 0
    late: int = 0  # delivered after a later burst arrived (hunting)
    resync: list[int] | None = None

    def add(self, other: ParserScore) -> None:
        self.delivered += other.delivered
        self.false_frames += other.false_frames
        self.misframed += other.misframed
        self.wrong_values += other.wrong_values
        self.intact_lost += other.intact_lost
        self.late += other.late
        self.resync = (self.resync or []) + (other.resync or [])


def score(parser, stream: Damaged, timed: bool) -> ParserScore:
    """Feed the bursts (with their arrival times if ``timed``) and judge every frame."""
    result = ParserScore(resync=[])
    n = len(stream.bursts)
    good = np.zeros(n, dtype=bool)  # transmitted frames delivered correctly
    for k, burst in enumerate(stream.bursts):
        if not burst:
            continue
        arrival = k * PERIOD_S + len(burst) * BYTE_S if timed else None
        for frame in parser.feed(burst, arrival):
            result.delivered += 1
            o = frame.offset
            origin = stream.frame_of[o:o + FRAME_LENGTH]
            aligned = (len(origin) == FRAME_LENGTH and np.all(origin == origin[0])
                       and np.array_equal(stream.position[o:o + FRAME_LENGTH],
                                          np.arange(FRAME_LENGTH)))
            if not aligned:
                result.misframed += 1
                result.false_frames += 1
                data = origin[1:]  # the data bytes: one sent frame's, unflipped?
                if not (len(data) == FRAME_LENGTH - 1 and np.all(data == data[0])
                        and np.array_equal(stream.position[o + 1:o + FRAME_LENGTH],
                                           np.arange(1, FRAME_LENGTH))
                        and not np.any(stream.flipped[o + 1:o + FRAME_LENGTH])):
                    result.wrong_values += 1
                continue
            if np.any(stream.flipped[o:o + FRAME_LENGTH]):
                result.false_frames += 1
                result.wrong_values += int(np.any(stream.flipped[o + 1:o + FRAME_LENGTH]))
                continue
            good[origin[0]] = True
            if origin[0] < k:
                result.late += 1
    result.intact_lost = int(np.sum(~stream.damaged_frames & ~good))
    # frames to resynchronise after an isolated damaged frame d: the first correctly
    # delivered frame after d, counted from d (1 = the very next frame)
    delivered_idx = np.flatnonzero(good)
    for d in np.flatnonzero(stream.damaged_frames):
        if d == 0 or d + 1 >= n or not good[d - 1]:
            continue
        nxt = np.searchsorted(delivered_idx, d + 1)
        if nxt == len(delivered_idx):
            continue
        first = delivered_idx[nxt]
        if np.any(stream.damaged_frames[d + 1:first + 1]):
            continue  # another fault before resynchronising: not isolated
        result.resync.append(int(first - d))
    return result


PARSERS = (("naive (0xAA + 6 bytes)", NaiveParser, False),
           ("FrameParser, bytes only", FrameParser, False),
           ("FrameParser, bytes + arrival times", FrameParser, True))


def run(n_frames: int, rates: list[float], seed: int, adversarial: int = 100_000,
        counts: tuple[int, ...] = ADVERSARIAL_COUNTS,
        progress: Callable[[int], None] | None = None) -> list[dict]:
    """Rows of the table: the simulated rigs' stream (drops and flips), then
    ``adversarial`` frames of the adversarial stream about ``counts`` (drops; none if 0).
    ``progress(1)`` is called after each row."""
    sources = [("rigs", rig_frames(n_frames, seed=seed), ("drop", "flip"), n_frames, ())]
    if adversarial:
        sources.append(("adversarial", adversarial_frames(adversarial, seed=seed,
                                                          counts=counts),
                        ("drop",), adversarial, (2,)))
    rows = []
    for source, rigs, kinds, frames, salt in sources:
        for kind in kinds:
            for rate in rates:
                rng = np.random.default_rng([seed, int(rate * 1e6), kind == "drop", *salt])
                streams = [damage(f, kind, rate, rng) for f in rigs]
                for name, cls, timed in PARSERS:
                    total = ParserScore(resync=[])
                    for stream in streams:
                        total.add(score(cls(), stream, timed))
                    damaged = int(sum(s.damaged_frames.sum() for s in streams))
                    rows.append(dict(stream=source, kind=kind, rate=rate, parser=name,
                                     frames=frames, damaged=damaged, score=total))
                    if progress is not None:
                        progress(1)
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| stream | damage | rate/byte | parser | delivered | false frames (misframed) "
             "| values never sent | intact lost | delivered late | resync frames max (mean) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s: ParserScore = r["score"]
        if r["parser"].startswith("naive"):
            resync = "-"
        elif s.resync:
            resync = f"{max(s.resync)} ({np.mean(s.resync):.2f})"
        else:
            resync = "-"
        lines.append(f"| {r.get('stream', 'rigs')} | {r['kind']} | {r['rate']:g} | "
                     f"{r['parser']} | {s.delivered} | {s.false_frames} ({s.misframed}) | "
                     f"{s.wrong_values} | {s.intact_lost} | {s.late} | {resync} |")
    return "\n".join(lines)


def format_adversarial(rows: list[dict]) -> str:
    """One line per FrameParser feeding on the adversarial stream's drops: false frames per
    100 000 frames at each rate, and the longest resynchronisation."""
    lines = []
    for name, _, _ in PARSERS[1:]:
        mine = [r for r in rows if r.get("stream") == "adversarial" and r["parser"] == name
                and r["kind"] == "drop"]
        if not mine:
            continue
        parts = []
        for r in mine:
            s: ParserScore = r["score"]
            per = 100_000 / r["frames"]
            resync = max(s.resync) if s.resync else "-"
            parts.append(f"drops {r['rate']:g}: {s.false_frames * per:g} false frames "
                         f"({s.wrong_values * per:g} with values never sent), resync <= {resync}")
        lines.append(f"adversarial stream, {name}, per 100000 frames: " + "; ".join(parts))
    return "\n".join(lines)

"""``pisc_parser_bench``: the frame parser against lost bytes and flipped bits.

    pisc_parser_bench [--frames 200000] [--rates 1e-4 1e-3 1e-2] [--seed 1]

Frames come from the rig's own physics: a batch of simulated rigs (pisc_plant) driven by
random sinusoidal voltages, swinging the pendulum through every encoder value and the
cart from stop to stop, encoded through the sensors' inverse calibrations. Each rig's
stream is cut as the link would cut it (bursts of 7 bytes every 5 ms at 115200 baud),
then damaged byte by byte: a byte is lost with probability p ("drop") or has one bit
flipped ("flip"). Three parsers read the same damaged stream, burst by burst:

* naive: wait for 0xAA, take the next six bytes;
* FrameParser fed bytes only (no arrival times);
* FrameParser fed bytes with the arrival time of each burst (what the driver does).

For each it prints frames delivered, **false frames** (delivered but not a frame the
device sent: misframed, or with a flipped bit that no check can see without a
checksum), intact frames lost, and frames to resynchronise after an isolated damaged
frame (1 = the next frame is delivered again). A frame "delivered late" came out of the
parser only when a later burst arrived (while hunting, confirmed by the next header).
"""

from __future__ import annotations

import argparse
import time
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
from pisc_plant.params import LoopParams
from pisc_plant.plant import Plant, PlantConfig

__all__ = ["ParserScore", "damage", "main", "rig_frames", "score"]

BYTE_S = 10 / 115200  # 8N1: ten bits per byte


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
    intact_lost: int = 0
    late: int = 0  # delivered after a later burst arrived (hunting)
    resync: list[int] | None = None

    def add(self, other: ParserScore) -> None:
        self.delivered += other.delivered
        self.false_frames += other.false_frames
        self.misframed += other.misframed
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
        arrival = k * 0.005 + len(burst) * BYTE_S if timed else None
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
                continue
            if np.any(stream.flipped[o:o + FRAME_LENGTH]):
                result.false_frames += 1
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


def run(n_frames: int, rates: list[float], seed: int) -> list[dict]:
    rigs = rig_frames(n_frames, seed=seed)
    rows = []
    for kind in ("drop", "flip"):
        for rate in rates:
            rng = np.random.default_rng([seed, int(rate * 1e6), kind == "drop"])
            streams = [damage(frames, kind, rate, rng) for frames in rigs]
            for name, cls, timed in PARSERS:
                total = ParserScore(resync=[])
                for stream in streams:
                    total.add(score(cls(), stream, timed))
                damaged = int(sum(s.damaged_frames.sum() for s in streams))
                rows.append(dict(kind=kind, rate=rate, parser=name, frames=n_frames,
                                 damaged=damaged, score=total))
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| damage | rate/byte | parser | delivered | false frames (misframed) "
             "| intact lost | delivered late | resync frames max (mean) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s: ParserScore = r["score"]
        if r["parser"].startswith("naive"):
            resync = "-"
        elif s.resync:
            resync = f"{max(s.resync)} ({np.mean(s.resync):.2f})"
        else:
            resync = "-"
        lines.append(f"| {r['kind']} | {r['rate']:g} | {r['parser']} | {s.delivered} | "
                     f"{s.false_frames} ({s.misframed}) | {s.intact_lost} | {s.late} | {resync} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_parser_bench",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200_000)
    parser.add_argument("--rates", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2])
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    started = time.monotonic()
    rows = run(args.frames, args.rates, args.seed)
    print(f"{args.frames} frames per condition (100 simulated rigs), seed {args.seed}")
    print(format_rows(rows))
    print(f"({time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""pisc_parser_bench: the frame parser against lost bytes and flipped bits, on the
simulated rigs' frames and on an adversarial stream (:mod:`pisc_bench.parser_bench`)."""

from __future__ import annotations

import argparse
import time

from pisc_bench.parser_bench import (
    ADVERSARIAL_COUNTS,
    PARSERS,
    format_adversarial,
    format_rows,
    run,
)

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_parser_bench",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=200_000,
                        help="frames of the simulated rigs per condition")
    parser.add_argument("--adversarial-frames", type=int, default=100_000,
                        help="frames of the adversarial stream per condition (0 = none)")
    parser.add_argument("--adversarial-counts", type=lambda text: int(text, 0), nargs="+",
                        default=list(ADVERSARIAL_COUNTS), metavar="COUNT",
                        help="encoder counts the adversarial rigs rest or swing about, as "
                        "the 16-bit register holds them (default 0xAAAA 0xAA01 0x00AA 0)")
    parser.add_argument("--rates", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2])
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    if args.frames < 1 or args.adversarial_frames < 0:
        parser.error("--frames must be at least 1 and --adversarial-frames at least 0")
    if not all(0.0 <= r <= 1.0 for r in args.rates):
        parser.error("--rates are probabilities per byte, in [0, 1]")
    if not all(0 <= c <= 0xFFFF for c in args.adversarial_counts):
        parser.error("--adversarial-counts are 16-bit register values, 0 to 0xFFFF")
    started = time.monotonic()
    counts = tuple(args.adversarial_counts)
    from pisc_msgs_py.progress import progress_bar

    total = len(PARSERS) * len(args.rates) * (2 + (1 if args.adversarial_frames else 0))
    with progress_bar(total, "row", "parser bench") as bar:
        rows = run(args.frames, args.rates, args.seed, args.adversarial_frames, counts, bar)
    print(f"{args.frames} frames per condition (100 simulated rigs), "
          f"{args.adversarial_frames} of the adversarial stream (100 rigs about counts "
          f"{', '.join(f'0x{c:04X}' for c in counts)}), seed {args.seed}")
    print(format_rows(rows))
    summary = format_adversarial(rows)
    if summary:
        print(summary)
    print(f"({time.monotonic() - started:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``pisc_bag animate BAG``: the run drawn as the rig to a GIF or an MP4
(:mod:`pisc_runs.animate`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from pisc_bag.bag import BagError
from pisc_runs.animate import frame_cycles, load_run, write_animation

__all__ = ["add_arguments", "run"]


def add_arguments(parser: Any) -> None:
    """``pisc_bag animate`` options."""
    parser.add_argument("bag", type=Path, help="bag directory")
    parser.add_argument("--out", type=Path,
                        help="the animation, .gif or .mp4 (default: BAG/animation.gif)")
    parser.add_argument("--overlay", type=Path, help="a second bag drawn behind, in grey")
    parser.add_argument("--fps", type=float, default=25.0, help="frames per second "
                        "(default: %(default)s)")
    parser.add_argument("--speed", type=float, default=1.0,
                        help="run seconds per second of animation (default: %(default)s; "
                        "0.25 is slow motion)")
    parser.add_argument("--start", type=float, default=0.0, metavar="T",
                        help="first frame at this run time [s] (default: 0)")
    parser.add_argument("--end", type=float, metavar="T",
                        help="last frame at this run time [s] (default: the end)")


def run(args: Any) -> int:
    """Write the animation; 0 on success."""
    from pisc_msgs_py.progress import progress_bar

    out = args.out or args.bag / "animation.gif"
    if out.suffix.lower() not in (".gif", ".mp4"):
        raise BagError(f"{out}: the animation must be a .gif or an .mp4 file")
    if not out.parent.is_dir():
        raise BagError(f"{out.parent}: no such directory for the animation")
    first = load_run(args.bag)
    overlay = load_run(args.overlay) if args.overlay is not None else None
    try:
        cycles = frame_cycles(first.t, args.fps, args.speed, args.start, args.end)
    except ValueError as exc:
        raise BagError(str(exc)) from None
    began = time.perf_counter()
    with progress_bar(len(cycles), "frame", "animate") as bar:
        n = write_animation(first, out, overlay, args.fps, args.speed, args.start, args.end,
                            bar)
    wall = time.perf_counter() - began
    shown = float(first.t[cycles[-1]] - first.t[cycles[0]])
    print(f"wrote {out}: {n} frames at {args.fps:g} fps, {shown:.2f} s of the run"
          f"{'' if args.speed == 1 else f' at {args.speed:g}x'}, "
          f"{'true' if first.true_state else 'measured'} state, in {wall:.1f} s",
          file=sys.stdout)
    return 0


"""``pisc_bag analyse BAG``: the metrics of a run, plots like the thesis's Figs. 6.3-6.8
and its CSV log (:mod:`pisc_runs.analysis`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pisc_bag.bag import BagError
from pisc_runs.analysis import analyse_bag, write_csv, write_plots

__all__ = ["add_arguments", "run"]


def add_arguments(parser: Any) -> None:
    """``pisc_bag analyse`` options."""
    parser.add_argument("bag", type=Path, help="bag directory")
    parser.add_argument("--out", type=Path,
                        help="directory for the plots and the CSV (default: BAG/analysis)")
    parser.add_argument("--overlay", type=Path, help="a second bag drawn over the first")


def run(args: Any) -> int:
    """Print the metrics, write the plots and the CSV; 0 on success."""
    first = analyse_bag(args.bag)
    analyses = [first]
    if args.overlay is not None:
        analyses.append(analyse_bag(args.overlay))
    out = args.out or args.bag / "analysis"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BagError(f"{out}: cannot create the output directory ({exc.strerror})") from None
    period = first.summary.period_s
    for n, analysis in enumerate(analyses):
        if n:
            print()
        print(f"{analysis.trace.label}:")
        print(analysis.format())
        suffix = "" if n == 0 else f"_overlay_{analysis.trace.label}"
        write_csv(analysis.trace, out / f"log{suffix}.csv")
    paths = write_plots([a.trace for a in analyses], out, period)
    print(f"wrote {len(paths)} plots and {len(analyses)} CSV log(s) to {out}")
    return 0

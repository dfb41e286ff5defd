"""The command: ``pisc_analysis``: the seeds' analysis of a configuration, as a printed
report and plots (:mod:`pisc_analysis.report`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pisc_msgs_py.config import ConfigError, parse_overrides
from pisc_analysis import report as analysis_report
from pisc_analysis.report import build_report

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="pisc_analysis",
                                     description=analysis_report.__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="default",
                        help="named configuration (default, thesis) or a parameter file")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override a parameter, e.g. --set motor.resistance_ohm=6")
    parser.add_argument("--out", type=Path, default=Path("analysis"),
                        help="directory for the PNG plots (default ./analysis)")
    parser.add_argument("--grid", type=int, default=100,
                        help="region of attraction: N x N starts (default 100)")
    parser.add_argument("--roa-duration", type=float, default=1.5,
                        help="region of attraction: seconds per start (default 1.5)")
    parser.add_argument("--roa-x0", type=float, nargs="+", default=[0.0],
                        help="region of attraction: initial cart positions [m], one map "
                        "each (default 0)")
    parser.add_argument("--compare", nargs="*", default=None,
                        help="configurations whose region of attraction is drawn beside "
                        "(default: thesis, or default for --config thesis)")
    parser.add_argument("--no-roa", action="store_true", help="skip the region of attraction")
    args = parser.parse_args(argv)
    try:
        overrides = parse_overrides(args.set)
    except ConfigError as exc:
        parser.error(str(exc))
    if args.grid < 0:
        parser.error(f"--grid {args.grid}: must be positive")
    compare = args.compare
    if compare is None:
        compare = ["default"] if args.config == "thesis" else ["thesis"]
    try:
        report = build_report(args.config, overrides, args.out,
                              grid=0 if args.no_roa else args.grid,
                              roa_duration_s=args.roa_duration, roa_x0_m=args.roa_x0,
                              compare=compare, progress=sys.stderr)
    except ConfigError as exc:
        print(f"pisc_analysis: invalid configuration: {exc}", file=sys.stderr)
        return 2
    print(report.text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

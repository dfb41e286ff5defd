"""pisc_identify: the rig's parameters from recorded runs (docs/identification.md).

    pisc_identify BAG [BAG ...] [--fit R,J_m,cart_coulomb,...] [--config BASE]
                  [--out FILE] [--plot FILE] [--segment S] [--max-evaluations N]

Fits the parameters named by ``--fit`` (default: what the bags' experiments excite:
R, L, J_m, cart_coulomb, cart_viscous, pivot_viscous, current_offset for an excitation,
I and pivot_viscous for a free swing with l from the base, and delay for a run on the wall
clock) so that the plant, driven by the
recorded voltages, predicts what the sensors measured (:mod:`pisc_robust.identify`).
Prints each estimate with its 95 % interval, the residual against the sensors'
resolution and the pairs of parameters the data cannot separate; writes a parameter
file (``--out``, default ``identified.yaml``) that ``./pisc run --plant-config``,
``pisc_robustness`` and ``pisc_tune`` take, and the overlay plot of measured against
simulated signals (``--plot``, default the file's name with ``.png``).

Exit status: 0 identified; 1 the fit failed (did not converge, diverged); 2 the input
cannot serve (a bag that cannot be read or lacks the measured topics, no voltage to
excite what is asked, an unknown parameter). Nothing is written unless it succeeds.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

PROG = "pisc_identify"


def main(argv: list[str] | None = None) -> int:
    from pisc_robust.robustness_args import quiet_threads

    quiet_threads()
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("bags", nargs="+", metavar="BAG", help="bag directories of runs")
    parser.add_argument("--fit", metavar="NAMES",
                        help="comma-separated parameters to fit, short or dotted names (R, L, "
                        "J_m, b_m, cart_coulomb, cart_viscous, pivot_viscous, M, m, l, I, "
                        "delay); default: what the bags' experiments excite")
    parser.add_argument("--config", metavar="BASE",
                        help="the base configuration (a name or a parameter file): the values "
                        "not fitted and the fit's start (default: the first bag's "
                        "pisc_params.yaml, else default)")
    parser.add_argument("--out", type=Path, default=Path("identified.yaml"), metavar="FILE",
                        help="parameter file to write (default: %(default)s)")
    parser.add_argument("--plot", type=Path, metavar="FILE",
                        help="overlay plot (PNG; default: --out with .png)")
    parser.add_argument("--segment", type=float, default=1.0, metavar="S",
                        help="segment length [s] (default: %(default)s)")
    parser.add_argument("--max-evaluations", type=int, default=100, metavar="N",
                        help="largest number of evaluations of each fit (default: %(default)s)")
    args = parser.parse_args(argv)
    if args.segment <= 0.0:
        parser.error(f"--segment {args.segment}: must be positive")
    if args.max_evaluations < 1:
        parser.error(f"--max-evaluations {args.max_evaluations}: at least 1")

    from pisc_robust.identify import TIMING_ROUNDS, identify
    from pisc_robust.identify_data import (
        DEFAULT_FIT,
        FitError,
        IdentifyError,
        parse_fit,
        read_recording,
    )
    from pisc_robust.identify_report import format_report, load_base, plot_overlay, write_result

    def fail(status: int, text: str) -> int:
        print(f"{PROG}: {text}", file=sys.stderr)
        print(f"{PROG}: nothing written", file=sys.stderr)
        return status

    try:
        fit = parse_fit(args.fit) if args.fit is not None else None
        recordings = [read_recording(bag) for bag in args.bags]
        base, flat, base_name = load_base(args.config, recordings)
        if fit is None:
            keys: list[str] = []
            for r in recordings:
                keys += [k for k in DEFAULT_FIT.get(r.experiment, DEFAULT_FIT["none"])
                         if k not in keys]
            if any(r.wall_clock for r in recordings) and "delay" not in keys:
                keys.append("delay")
            fit = parse_fit(keys)
    except IdentifyError as exc:
        return fail(2, str(exc))
    plot = args.plot or args.out.with_suffix(".png")
    print(f"{PROG}: {len(recordings)} recording(s), base {base_name}; fitting "
          f"{', '.join(u.key for u in fit)}", flush=True)
    from pisc_msgs_py.progress import progress_bar

    passes = 2 + (TIMING_ROUNDS if any(r.wall_clock for r in recordings) else 0)
    try:
        # a bar over the fit's passes, labelled with the pass's evaluations (stderr, only
        # on a terminal); the passes' lines go to stdout as before
        with progress_bar(passes, "pass", "fit") as bar:

            def evaluated(done: int, total: int, evaluations: int) -> None:
                bar.to(done)
                bar.describe(f"pass {done + 1}/{total}: {evaluations} evaluations")

            result = identify(recordings, fit, base, segment_s=args.segment,
                              max_evaluations=args.max_evaluations,
                              progress=lambda text: print(f"  {text}", flush=True),
                              on_evaluation=evaluated)
    except FitError as exc:
        return fail(1, str(exc))
    except IdentifyError as exc:
        return fail(2, str(exc))
    print(format_report(result))
    if not result.estimates:
        return fail(1, "no parameter could be identified from these data")
    # both files or neither: write beside the targets, then move them in place
    try:
        for target in (args.out, plot):
            target.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=args.out.parent, prefix=".pisc_identify-") as tmp:
            params = Path(tmp) / "params.yaml"
            image = Path(tmp) / "plot.png"
            write_result(result, flat, base_name, params, " ".join(
                [PROG, *(argv if argv is not None else sys.argv[1:])]))
            plot_overlay(result, image)
            os.replace(params, args.out)
            os.replace(image, plot)
    except OSError as exc:
        return fail(2, f"cannot write {args.out} or {plot}: {exc}")
    print(f"wrote {args.out} (./pisc run --plant-config {args.out}; pisc_robustness "
          f"{args.out}; pisc_tune {args.out}) and {plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

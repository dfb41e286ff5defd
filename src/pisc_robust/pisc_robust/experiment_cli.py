"""pisc_experiment: judge a recorded run against the thesis's experiment and draw it in the
layout of the thesis's Figures 6.3-6.8, the thesis's events marked
(docs/thesis-experiment.md).

    ./pisc run --config thesis --plant-config thesis-calibrated-plant --bag bags/calibrated
    .venv/bin/pisc_experiment bags/calibrated --out docs/images

Prints each event: the thesis's value and tolerance, the run's value, whether it meets it;
writes ``DIR/<experiment>.png`` (default DIR: BAG/analysis). Exit status 0 when the run
meets every event, 1 when it misses one, 2 on a bag or experiment file it cannot read.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

PROG = "pisc_experiment"

# the thesis's figure, the column, its label and colour (the thesis: desired current red,
# measured blue, Fig. 6.7)
PANELS = (
    ("Fig. 6.3 cart position", "x [m]", (("x", "x measured", "C0"),)),
    ("Fig. 6.4 cart velocity", "x_dot [m/s]", (("x_dot", "x_dot (4.9)", "C0"),)),
    ("Fig. 6.5 pendulum angle", "theta [rad]", (("theta", "theta measured", "C0"),)),
    ("Fig. 6.6 pendulum velocity", "theta_dot [rad/s]",
     (("theta_dot", "theta_dot (4.7)", "C0"),)),
    ("Fig. 6.7 current", "current [A]", (("i_d", "i_d desired (4.2)", "C3"),
                                          ("i", "i measured", "C0"))),
    ("Fig. 6.8 voltage", "u [V]", (("u", "u (3.47)", "C0"),)),
)
THESIS_RUN_S = 6.0  # "La prueba ... dura aproximadamente 6[s]"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("bag", type=Path, help="a run's bag directory")
    parser.add_argument("--experiment", default="thesis-6.6", metavar="NAME|FILE",
                        help="a shipped experiment or an experiment file (default: "
                        "%(default)s)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="directory of the figure (default: BAG/analysis)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from pisc_runs.analysis import analyse_bag
    from pisc_bag.bag import BagError
    from pisc_robust.experiment import format_score, load_experiment
    from pisc_msgs_py.config import ConfigError

    try:
        experiment = load_experiment(args.experiment)
        analysis = analyse_bag(args.bag)
        out = args.out or args.bag / "analysis"
        out.mkdir(parents=True, exist_ok=True)
    except (ConfigError, BagError, OSError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 2
    measured, ok = score_run(experiment, analysis)
    print(f"{args.bag} against {experiment.name} ({experiment.description}):")
    print(*format_score(experiment, measured), sep="\n")
    path = out / f"{experiment.name}.png"
    draw(path, experiment, analysis, measured)
    print(f"{'meets every event' if ok else 'misses an event'}; wrote {path}")
    return 0 if ok else 1


def score_run(experiment: Any, analysis: Any) -> tuple[dict[str, np.ndarray], bool]:
    """The experiment's events measured on a recorded run, and whether it meets them."""
    from pisc_robust.experiment import judge, measure, traces_from_run

    traces = traces_from_run(analysis.trace, analysis.voltage_limit_v,
                             analysis.current_limit_a, analysis.summary.period_s)
    measured = measure(traces)
    return measured, bool(judge(experiment, measured)[0])


def draw(path: Path, experiment: Any, analysis: Any, measured: dict[str, np.ndarray]) -> None:
    """Six panels in the thesis's order (Figs. 6.3-6.8): the run's measured values, the
    thesis's hand-over and time to 0 rad with their tolerances shaded (orange, green), the
    run's as dashed lines, the end of the thesis's 6 s run dotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    trace = analysis.trace
    fig, axes = plt.subplots(3, 2, figsize=(12, 8.4), sharex=True)
    marks = [(experiment.event("hand_over_s"), "C1", "hand-over"),
             (experiment.event("upright_s"), "C2", "at 0 rad")]
    for ax, (title, unit, columns) in zip(axes.flat, PANELS, strict=True):
        for column, label, colour in columns:
            ax.plot(trace.t, getattr(trace, column), color=colour, lw=0.8, label=label)
        for event, colour, what in marks:
            if event is None:
                continue
            ax.axvspan(event.value - event.tolerance, event.value + event.tolerance,
                       color=colour, alpha=0.15, lw=0,
                       label=f"thesis {what} {event.value:g} +- {event.tolerance:g} s")
            ax.axvline(event.value, color=colour, lw=1.0)
            run = float(measured[event.name][0])
            if np.isfinite(run):
                ax.axvline(run, color=colour, lw=1.0, ls="--", label=f"run {what} {run:.2f} s")
        ax.axvline(THESIS_RUN_S, color="0.4", lw=0.8, ls=":", label="end of the thesis's run")
        if column == "u":
            for sign in (-1, 1):
                ax.axhline(sign * analysis.voltage_limit_v, color="0.5", lw=0.6)
        if title.startswith("Fig. 6.7"):
            for sign in (-1, 1):
                ax.axhline(sign * analysis.current_limit_a, color="0.5", lw=0.6)
        ax.set_title(title, fontsize=9)
        ax.set_ylabel(unit, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    handles, labels = axes[2, 0].get_legend_handles_labels()
    more, more_labels = axes[1, 0].get_legend_handles_labels()
    fig.legend(handles + more[:1], labels + more_labels[:1], loc="lower center", ncol=4,
               fontsize=8)
    for ax in axes[2]:
        ax.set_xlabel("t [s]", fontsize=8)
    osc = float(measured["oscillations"][0])
    fig.suptitle(f"{analysis.trace.label} against {experiment.name}: {2 * osc:g} passes "
                 f"through hanging before the hand-over ({osc:g} oscillations; thesis: "
                 "three)", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())

"""Analysis of a recorded run: metrics, plots like the thesis's Figs. 6.3-6.8, the CSV log.

    pisc_bag analyse BAG [--out DIR] [--overlay BAG2] [--label NAME ...]

Everything is computed from the bag, keyed by the header stamp of each cycle (a cycle
is complete when its voltage was recorded), with run time ``t`` = stamp minus the
first sample's stamp. The run's summary (:mod:`pisc_runs.summary`, the lines
``pisc_graph`` prints when it records) is printed first, then:

* time to upright: the first time at or after the first catch that the pendulum is
  within ``UPRIGHT_RAD`` of upright; the thesis's rig took 3.25 s (2.34 s of swing-up,
  then 0.91 s of the linear controller; Fig. 6.5);
* settle time: from when on |theta| and |x| stay within the hold limits (0.05 rad,
  0.02 m) to the end of the run;
* current tracking RMS and peak of i_d - i (the same cycle, Fig. 6.7);
* time in saturation: cycles whose voltage is at the limit (+-11.47 V, Fig. 6.8) and
  whose current setpoint is at its limit (+-0.9 A, (4.2));
* mode changes with their times.

Plots (PNG, one per figure, the mode shaded): cart position (Fig. 6.3), cart velocity
(6.4), pendulum angle (6.5), pendulum velocity (6.6), desired and measured current
(6.7), motor voltage (6.8); measured values as the thesis logged them, the simulator's
true state dashed where the bag has it. With ``--overlay`` a second run is drawn over
the first in every plot. The CSV has the thesis's log columns in its order: t, x,
theta, x_dot, theta_dot, i, i_d, u (SPEC section 4), every value written exactly
(``repr``), one row per cycle.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bag.bag import BagError, BagMessage
from pisc_bag.run_files import recorded_params, recorded_section
from pisc_runs.verdict import Criteria
from pisc_runs.summary import (
    RunSummary,
    RunTables,
    member,
    safe_range_of,
    summarise_tables,
    tables_of,
    tables_of_bag,
)
from pisc_control.current_loop import CurrentLoopParams
from pisc_msgs_py.types import Mode
from pisc_model.dynamics import wrap_to_upright
from pisc_model.params import LoopParams

__all__ = [
    "CSV_COLUMNS",
    "PLOTS",
    "RunAnalysis",
    "RunTrace",
    "UPRIGHT_RAD",
    "analyse_bag",
    "write_csv",
    "write_plots",
]

UPRIGHT_RAD = 0.01  # "reaches 0 rad": within 0.01 rad (6 encoder counts) of upright
CSV_COLUMNS = ("t", "x", "theta", "x_dot", "theta_dot", "i", "i_d", "u")
MODE_COLOURS = {Mode.SWING_UP: "#fff2cc", Mode.CATCH: "#d9ead3", Mode.FAULT: "#f4cccc"}


@dataclass(frozen=True)
class RunTrace:
    """One row per complete cycle: the thesis's log columns, the mode, the true state."""

    label: str
    t: np.ndarray
    x: np.ndarray
    theta: np.ndarray
    x_dot: np.ndarray
    theta_dot: np.ndarray
    i: np.ndarray
    i_d: np.ndarray
    u: np.ndarray
    mode: list[Mode]  # in force at each cycle
    true_x: np.ndarray | None  # None: the bag has no simulator state
    true_theta: np.ndarray | None
    start_ns: int = 0  # header stamp of the first cycle (t = 0)

    def column(self, name: str) -> np.ndarray:
        return getattr(self, name)


def trace_from_messages(messages: Iterable[BagMessage], label: str) -> RunTrace:
    """Cycles of a run; :class:`BagError` if the bag has none or a message is malformed
    (the caller names the bag)."""
    return trace_from_tables(tables_of(messages), label)


def trace_from_tables(tables: RunTables, label: str) -> RunTrace:
    """Cycles of a run, the first message of each stamp counting (:class:`BagError` if
    there is none): a cycle is complete when its sample, estimate, current, set-point and
    voltage were all recorded."""
    picked = {name: getattr(tables, name).pick("first")
              for name in ("joints", "state", "current", "setpoint", "voltage", "true")}
    stamps = picked["voltage"][0]
    for name in ("joints", "state", "current", "setpoint"):
        stamps = stamps[member(stamps, picked[name][0])]
    if not len(stamps):
        raise BagError("no complete control cycle (joint_states, state, current, "
                       "setpoint and voltage of one stamp)")

    def col(name: str, index: int = 0) -> np.ndarray:
        unique, rows = picked[name]
        return getattr(tables, name).values[rows[np.searchsorted(unique, stamps)], index]

    # the mode in force at each cycle: the newest report at or before its stamp (the
    # first report before any)
    modes = sorted(tables.modes, key=lambda r: r[0])
    if modes:
        newest = np.searchsorted(np.array([r[0] for r in modes]), stamps, side="right") - 1
        kinds = [mode for _, mode, _ in modes]
        in_force = [kinds[k] for k in np.maximum(newest, 0).tolist()]
    else:
        in_force = [Mode.SWING_UP] * len(stamps)
    t0 = int(stamps[0])
    has_true = bool(np.all(member(stamps, picked["true"][0])))
    return RunTrace(
        label=label,
        t=(stamps - t0) * 1e-9,
        x=col("joints", 0), theta=col("joints", 1),
        x_dot=col("state", 0), theta_dot=col("state", 1),
        i=col("current"), i_d=col("setpoint"), u=col("voltage"),
        mode=in_force,
        true_x=col("true", 0) if has_true else None,
        true_theta=col("true", 1) if has_true else None,
        start_ns=t0,
    )


@dataclass(frozen=True)
class RunAnalysis:
    summary: RunSummary
    trace: RunTrace
    time_to_upright_s: float | None
    settle_time_s: float | None
    current_peak_error_a: float
    voltage_saturated_s: float
    current_saturated_s: float
    mode_changes: list[tuple[float, Mode]]  # (t, new mode), the first report included
    voltage_limit_v: float
    current_limit_a: float

    def format(self) -> str:
        def t(v: float | None) -> str:
            return "never" if v is None else f"{v:.3f} s"

        s = self.summary
        lines = [s.format().rsplit("\n", 1)[0]]  # the recording's summary, verdict last
        lines += [
            f"time to upright        {t(self.time_to_upright_s)} "
            f"(|theta| <= {UPRIGHT_RAD} rad after the first catch)",
            f"settle time            {t(self.settle_time_s)} (|theta| <= "
            f"{Criteria().theta_rad} rad and |x| <= {Criteria().x_m} m to the end)",
            f"current tracking peak  {self.current_peak_error_a:.4f} A (|i_d - i|)",
            f"voltage saturated      {self.voltage_saturated_s:.3f} s "
            f"(|u| at {self.voltage_limit_v} V)",
            f"current setpoint sat.  {self.current_saturated_s:.3f} s "
            f"(|i_d| at {self.current_limit_a} A)",
            "modes                  " + ", ".join(
                f"{m.value} at {tt:.3f} s" for tt, m in self.mode_changes),
            s.format().rsplit("\n", 1)[1],
        ]
        return "\n".join(lines)


def _limits(bag: Path) -> tuple[float, float, float]:
    """Period, voltage limit and current limit of the run (its parameter file or defaults)."""
    flat = recorded_params(bag)
    loop = recorded_section(bag, LoopParams, "loop", flat)
    cl = recorded_section(bag, CurrentLoopParams, "current_loop", flat)
    return loop.period_s, cl.voltage_limit_v, cl.current_limit_a


def analyse_messages(messages: Sequence[BagMessage], label: str, period_s: float,
                     voltage_limit_v: float, current_limit_a: float,
                     hold: Criteria = Criteria()) -> RunAnalysis:
    return analyse_tables(tables_of(messages), label, period_s, voltage_limit_v,
                          current_limit_a, hold)


def analyse_tables(tables: RunTables, label: str, period_s: float, voltage_limit_v: float,
                   current_limit_a: float, hold: Criteria = Criteria(),
                   safe_range_m: tuple[float, float] | None = None) -> RunAnalysis:
    trace = trace_from_tables(tables, label)
    summary = summarise_tables(tables, period_s, hold, safe_range_m)
    # the state the summary judged by: the simulator's where recorded, else measured
    x = trace.true_x if summary.state_source == "true" else trace.x
    theta = trace.true_theta if summary.state_source == "true" else trace.theta
    th_up = np.abs(wrap_to_upright(theta))
    upright = None
    if summary.first_catch_s is not None:
        after = (trace.t >= summary.first_catch_s - 1e-9) & (th_up <= UPRIGHT_RAD)
        upright = float(trace.t[np.argmax(after)]) if after.any() else None
    inside = (th_up <= hold.theta_rad) & (np.abs(x) <= hold.x_m)
    settle = None
    if inside[-1]:
        outside = np.flatnonzero(~inside)
        settle = float(trace.t[outside[-1] + 1]) if len(outside) else float(trace.t[0])
    error = np.abs(trace.i_d - trace.i)
    changes, previous = [], None
    for tt, m in zip(trace.t, trace.mode, strict=True):
        if m is not previous:
            changes.append((float(tt), m))
            previous = m
    return RunAnalysis(
        summary=summary,
        trace=trace,
        time_to_upright_s=upright,
        settle_time_s=settle,
        current_peak_error_a=float(error.max()),
        voltage_saturated_s=float(np.sum(np.abs(trace.u) >= voltage_limit_v) * period_s),
        current_saturated_s=float(np.sum(np.abs(trace.i_d) >= current_limit_a) * period_s),
        mode_changes=changes,
        voltage_limit_v=voltage_limit_v,
        current_limit_a=current_limit_a,
    )


def analyse_bag(bag: str | Path, label: str | None = None) -> RunAnalysis:
    """Read a bag and compute its metrics; :class:`BagError` names what is wrong."""
    bag = Path(bag)
    period, vm, im = _limits(bag)
    tables = tables_of_bag(bag)  # its errors name the bag
    try:
        return analyse_tables(tables, label or bag.name, period, vm, im,
                              safe_range_m=safe_range_of(bag))
    except BagError as exc:
        raise BagError(f"{bag}: {exc}") from None


def write_csv(trace: RunTrace, path: Path) -> None:
    """The thesis's log columns, one row per cycle, each value exactly (``repr``)."""
    with path.open("w", newline="") as stream:
        csv.writer(stream).writerow(CSV_COLUMNS)
        # what csv.writer writes for these rows (no value needs quoting), column by column
        columns = [map(repr, trace.column(c).tolist()) for c in CSV_COLUMNS]
        stream.writelines(",".join(row) + "\r\n" for row in zip(*columns, strict=True))


# file name, title, unit, measured column(s), true-state column (if any)
PLOTS = (
    ("fig6_3_cart_position.png", "Cart position (thesis Fig. 6.3)", "x [m]", ("x",), "true_x"),
    ("fig6_4_cart_velocity.png", "Cart velocity (Fig. 6.4)", "x_dot [m/s]", ("x_dot",), None),
    ("fig6_5_pendulum_angle.png", "Pendulum angle (Fig. 6.5)", "theta [rad]", ("theta",),
     "true_theta"),
    ("fig6_6_pendulum_velocity.png", "Pendulum velocity (Fig. 6.6)", "theta_dot [rad/s]",
     ("theta_dot",), None),
    ("fig6_7_current.png", "Desired and measured current (Fig. 6.7)", "current [A]",
     ("i_d", "i"), None),
    ("fig6_8_voltage.png", "Motor voltage (Fig. 6.8)", "u [V]", ("u",), None),
)
_STYLES = {"x": "C0", "x_dot": "C0", "theta": "C0", "theta_dot": "C0", "i_d": "C3", "i": "C0",
           "u": "C0"}
_LABELS = {"x": "x measured", "x_dot": "x_dot estimated (4.7)", "theta": "theta measured",
           "theta_dot": "theta_dot estimated (4.9)", "i": "i measured",
           "i_d": "i_d desired (4.2)", "u": "u commanded (3.47)"}


PLOT_POINTS = 4000  # a line of more points is drawn decimated (about 5 per pixel column)


def decimate(t: np.ndarray, y: np.ndarray,
             points: int = PLOT_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """(t, y) for drawing: unchanged up to ``points`` samples, else the smallest and the
    largest sample of each of ``points // 2`` equal runs, in time order, so every peak
    stays on the plot (min-max decimation) while matplotlib draws a bounded number."""
    n = len(t)
    if n <= points:
        return t, y
    runs = points // 2
    k = -(-n // runs)  # samples per run (the last one padded with the last sample)
    padded = np.concatenate([y, np.full(runs * k - n, y[-1])]).reshape(runs, k)
    first = np.arange(runs) * k
    picked = np.unique(np.minimum(np.concatenate(
        [first + padded.argmin(axis=1), first + padded.argmax(axis=1)]), n - 1))
    return t[picked], y[picked]


def _shade_modes(axes: Any, trace: RunTrace, period_s: float) -> None:
    start = 0
    for k in range(1, len(trace.mode) + 1):
        if k == len(trace.mode) or trace.mode[k] is not trace.mode[start]:
            axes.axvspan(trace.t[start], trace.t[k - 1] + period_s,
                         color=MODE_COLOURS[trace.mode[start]], linewidth=0, zorder=0)
            start = k


def write_plots(traces: Sequence[RunTrace], out_dir: Path, period_s: float = 0.005) -> list[Path]:
    """One PNG per thesis figure; the first run's modes shaded, later runs overlaid."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    paths = []
    for name, title, unit, columns, true_column in PLOTS:
        figure = Figure(figsize=(8, 3.6), dpi=100)
        FigureCanvasAgg(figure)
        axes = figure.add_subplot()
        _shade_modes(axes, traces[0], period_s)
        for n, trace in enumerate(traces):
            dash = "-" if n == 0 else "--"
            suffix = f" ({trace.label})" if len(traces) > 1 else ""
            for column in columns:
                colour = _STYLES[column] if n == 0 else ("C1" if column != "i_d" else "C4")
                axes.plot(*decimate(trace.t, trace.column(column)), dash, color=colour,
                          linewidth=0.9, label=_LABELS[column] + suffix)
            if true_column and len(traces) == 1 and trace.column(true_column) is not None:
                axes.plot(*decimate(trace.t, trace.column(true_column)), ":", color="k",
                          linewidth=0.8, label=f"{columns[0]} true (simulator)")
        handles, _ = axes.get_legend_handles_labels()
        handles += [Patch(color=MODE_COLOURS[m], label=f"mode {m.value}")
                    for m in Mode if m in traces[0].mode]
        axes.legend(handles=handles, fontsize=7, loc="upper right")
        axes.set_title(title + (f": {traces[0].label}" if len(traces) == 1 else
                                f": {' vs '.join(t.label for t in traces)}"))
        axes.set_xlabel("t [s]")
        axes.set_ylabel(unit)
        axes.grid(True, linewidth=0.3)
        figure.tight_layout()
        path = out_dir / name
        figure.savefig(path)
        paths.append(path)
    return paths

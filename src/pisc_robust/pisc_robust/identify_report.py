"""Identification's output: the base configuration, the parameter file written with the
estimates (:func:`write_result`), the printed report (:func:`format_report`) and the plot
of the measured against the simulated (:func:`plot_overlay`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pisc_model import sensors
from pisc_msgs_py.config import ConfigError
from pisc_plant.plant_config import PlantConfig
from pisc_robust.identify import Result
from pisc_robust.identify_data import NOT_PLANT, QUANTISATION_RMS, IdentifyError, Recording
from pisc_sim.configuration import load_graph_config, params_file_text

__all__ = ["format_report", "load_base", "plot_overlay", "result_flat", "write_result"]


def load_base(config: str | None, recordings: Sequence[Recording]
              ) -> tuple[PlantConfig, dict[str, Any], str]:
    """The base configuration: ``config`` (a name or file), else the first bag's
    controllers' parameter file, else ``default``: (plant, flat parameters, its name)."""
    source = config
    if source is None:
        source = next((str(r.params_file) for r in recordings if r.params_file), "default")
    try:
        graph, flat = load_graph_config(source)
    except ConfigError as exc:
        raise IdentifyError(f"--config {source}: {exc}") from None
    return graph.plant, flat, source


def result_flat(result: Result, base_flat: dict[str, Any]) -> dict[str, Any]:
    """The parameter file to write: the base's parameters with the estimates, without the
    experiment (a configuration that swings up), friction on when friction was fitted."""
    flat = {k: v for k, v in base_flat.items() if not k.startswith("experiment.")}
    for e in result.estimates:
        if e.unknown.key in NOT_PLANT:
            continue  # (the delay below; a sensor's error is the rig's, not its model's)
        flat[e.unknown.name] = float(f"{e.value:.6g}")
    if any(e.unknown.name.startswith("friction.") for e in result.estimates):
        flat["models.friction"] = "coulomb"
    delay = next((e for e in result.estimates if e.unknown.key == "delay"), None)
    if delay is not None:
        latency = np.concatenate([r.latency_s for r in result.recordings])
        flat["actuator.command_delay_s"] = float(f"{delay.value + np.median(latency):.6g}")
    return flat


def _fmt(value: float) -> str:
    return f"{value:.5g}"


def format_report(result: Result) -> str:
    seg = result.segments
    lines = []
    recs = result.recordings
    seconds = sum(r.duration_s for r in recs)
    written = any(r.read_delay_s is not None for r in recs)
    clock = ("wall clock: each voltage from its recorded latency "
             f"(median {np.median(np.concatenate([r.latency_s for r in recs])) * 1e3:.2f} ms"
             f"{', the reads estimated from the stamps' if written else ''}) plus delay"
             if any(r.wall_clock for r in recs) else "lockstep: delay only")
    lines.append(f"recordings      {len(recs)} ({result.cycles} samples, {seconds:.1f} s); "
                 f"{clock}")
    used = seg.size.sum() * result.base.loop.period_s
    lines.append(f"segments        {seg.count} fitted ({used:.1f} s), each from its own "
                 "estimated initial state")
    if seg.left_out:
        by_reason: dict[str, list[tuple[str, float, float]]] = {}
        for name, a, b, reason in seg.left_out:
            by_reason.setdefault(reason, []).append((name, a, b))
        for reason, spans in by_reason.items():
            total = sum(b - a for _, a, b in spans)
            where = ", ".join(f"{a:.2f}-{b:.2f} s" + (f" of {Path(n).name}" if len(recs) > 1
                                                       else "") for n, a, b in spans[:4])
            more = f" and {len(spans) - 4} more" if len(spans) > 4 else ""
            lines.append(f"left out        {len(spans)} ({total:.2f} s): {reason}: "
                         f"{where}{more}")
    lines.append(f"fit             {result.iterations} evaluations, {result.wall_s:.1f} s")
    if result.timing_spread_s is not None:
        lines.append(f"timing          each cycle's voltage timed by the current sensor: "
                     f"{result.timing_spread_s * 1e3:.2f} ms spread about the recorded latency "
                     f"plus delay")
    lines.append(f"{'parameter':<16}{'estimate':>14}   {'95 % interval':<27}{'base':>12}")
    for e in result.estimates:
        u = e.unknown
        lines.append(f"{u.key:<16}{_fmt(e.value):>14}   "
                     f"{_fmt(e.low) + ' .. ' + _fmt(e.high):<27}{_fmt(e.base):>12}  "
                     f"{u.unit}  ({u.name})")
    for e in result.not_identifiable:
        u = e.unknown
        if e.reason:
            lines.append(f"{u.key:<16}{'not identifiable':>14}   {e.reason}; the file keeps the "
                         f"base value {_fmt(e.base)} {u.unit}")
            continue
        lines.append(f"{u.key:<16}{'not identifiable':>14}   from these data at "
                     f"{result.base.loop.period_s * 1e3:g} ms sampling (estimate "
                     f"{_fmt(e.value)}, 95 % interval {_fmt(e.low)} .. {_fmt(e.high)} "
                     f"{u.unit}); the file keeps the base value {_fmt(e.base)}")
    steps = (result.base.sensors.adc_lsb_v, result.base.sensors.encoder_rad_per_count,
             result.base.sensors.adc_lsb_v)
    rms = result.residual_rms
    lines.append(
        f"residual RMS    IR {rms[0]:.3f} codes, encoder {rms[1]:.3f} counts, current "
        f"{rms[2]:.3f} codes ({rms[2] * steps[2] * result.base.sensors.current_scale_a_per_v * 1e3:.1f} mA); "
        f"quantisation alone gives {QUANTISATION_RMS:.3f}")
    worst = float(np.max(rms))
    if worst > 3.0:
        lines.append(f"warning: the residual ({worst:.1f} steps) is far above the sensors' "
                     "resolution: the model does not follow these data (look at the plot)")
    for w in result.warnings:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def write_result(result: Result, base_flat: dict[str, Any], base_name: str, out: Path,
                 command: str = "") -> None:
    """Write the parameter file (with what was identified in its header)."""
    flat = result_flat(result, base_flat)
    header = [f"# Identified by pisc_identify from {len(result.recordings)} recording(s): "
              + ", ".join(Path(r.name).name for r in result.recordings),
              f"# base: {base_name}" + (f"; command: {command}" if command else "")]
    for e in result.estimates:
        header.append(f"#   {e.unknown.name} = {_fmt(e.value)} {e.unknown.unit} "
                      f"(95 %: {_fmt(e.low)} .. {_fmt(e.high)})")
    for e in result.not_identifiable:
        header.append(f"#   {e.unknown.name}: not identifiable, base value kept")
    header.append("# Use: ./pisc run --plant-config FILE; pisc_robustness FILE; pisc_tune FILE")
    out.write_text("\n".join(header) + "\n" + params_file_text(flat))


def plot_overlay(result: Result, path: Path) -> None:
    """Measured against simulated position, angle and current, the voltage, and the
    residuals in sensor steps: each recording whole, and two seconds of the first."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result.base.sensors
    period = result.base.loop.period_s
    seg = result.segments
    recs = result.recordings[:3]
    columns = len(recs) + 1
    fig, axes = plt.subplots(5, columns, figsize=(6.5 * columns, 12), squeeze=False,
                             sharex="col")
    labels = ("cart position [m]", "pendulum angle [rad]", "current [A]", "voltage [V]",
              "residual [sensor steps]")
    steps = np.array([s.adc_lsb_v, s.encoder_rad_per_count, s.adc_lsb_v])
    first = int(np.argmax(seg.owner == 0))  # the first recording's first segment
    for col in range(columns):
        k = col if col < len(recs) else 0
        r = result.recordings[k]
        t = (r.stamps_ns - r.stamps_ns[0]) * 1e-9
        window = (-np.inf, np.inf)
        if col == len(recs):
            t0 = t[seg.first[first]] + min(1.0, 0.25 * seg.size[first] * period)
            window = (t0, t0 + 2.0)
        inside = (t >= window[0]) & (t <= window[1])
        zoom = col == len(recs)
        for row, values in enumerate((r.x, r.theta, r.current, r.voltage)):
            axes[row, col].plot(t[inside], values[inside], color="0.6",
                                lw=0 if zoom and row < 3 else 0.9,
                                marker="." if zoom and row < 3 else None, ms=3,
                                label="measured")
        mine = np.flatnonzero(seg.owner == k)
        for n in mine:
            tt = t[seg.first[n]:seg.first[n] + seg.size[n]]
            p = result.predicted[n, :seg.size[n]]
            keep = (tt >= window[0]) & (tt <= window[1])
            if not keep.any():
                continue
            sim = (sensors.ir_position(s, p[:, 0]), p[:, 1],
                   sensors.current_from_voltage(s, p[:, 2]))
            for row in range(3):
                axes[row, col].plot(tt[keep], sim[row][keep], color="C3", lw=0.8,
                                    label="simulated" if n == mine[0] else None)
            residual = (p - seg.measured[n, :seg.size[n]]) / steps
            for c, name in enumerate(("IR", "encoder", "current")):
                axes[4, col].plot(tt[keep], residual[keep, c], lw=0.5, color=f"C{c}",
                                  label=name if n == mine[0] else None)
        for name, a, b, _ in seg.left_out:
            if name == r.name and b >= window[0] and a <= window[1]:
                for row in range(5):
                    axes[row, col].axvspan(max(a, window[0]), min(b, window[1]),
                                           color="0.88", zorder=0)
        title = Path(r.name).name
        axes[0, col].set_title(title if not zoom else f"{title}: 2 s in detail")
        axes[4, col].set_xlabel("time [s]")
        for row in range(5):
            axes[row, col].set_ylabel(labels[row])
            axes[row, col].grid(True, lw=0.3)
    axes[0, 0].legend(loc="upper right")
    axes[4, 0].legend(loc="upper right", ncol=3)
    rms = result.residual_rms
    fig.suptitle("pisc_identify: measured (grey) and the identified model driven by the "
                 "recorded voltages (red), segment by segment; grey bands: left out\n"
                 f"residual RMS: IR {rms[0]:.2f} codes, encoder {rms[1]:.2f} counts, current "
                 f"{rms[2]:.2f} codes (quantisation alone: {QUANTISATION_RMS:.2f})")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)

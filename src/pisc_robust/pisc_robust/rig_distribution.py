"""What a commissioning knows about its rig, and the distribution that says it.

:func:`merge` joins the two identifications (the excitation's motor, friction and delay;
the free swing's I and pivot friction) into one record: every estimate of both with its
95 % interval and the fit it came from, which of them the rig's file keeps (of a
parameter both fitted, the narrower interval), what was not identifiable, the sensors'
noise and the latency as measured. :func:`rig_file_text` writes the file, its header
naming every estimate; :func:`distribution_text` writes the rig's distribution:

* every identified plant parameter uniform over its interval widened by ``widen`` about
  the estimate (each side by the factor);
* the sensors' noise as measured, times (1 -+ ``noise_span``): the standard deviation
  of each channel's fit residual above what quantisation alone gives,
  ``step sqrt(r^2 - 1/12)`` (``r`` in sensor steps, the step at the recording's median
  cart position for the IR sensor; an upper bound, as what the model does not follow
  counts as noise too: the smaller of the two fits');
* the latency as measured: from the 1st to the 99th percentile of the recorded
  sample-to-voltage times (none in lockstep) plus the identified delay's widened
  interval;
* M and m within ``mass_tolerance``, l within ``length_tolerance`` (relative) of the
  values the configuration has (``--set`` them as measured on the rig);
* the starts the rig will meet: x0 within ``start_x_m`` of the configuration's, theta
  within ``start_theta_rad`` of hanging, at rest;
* what neither pins down (L with the delay fitted, a J_m not identifiable, ...) over the
  prior distribution's range; the rotor's b_m is held, as the cart's viscous friction
  identified includes b_m / r^2.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["distribution_text", "describe", "measured_noise", "merge", "rig_file_text"]

NOISE = ("noise.x_std_m", "noise.theta_std_rad", "noise.current_std_a")
LATENCY = "actuator.command_delay_s"
MEASURED = {"rig.cart_mass_kg": "mass", "rig.pendulum_mass_kg": "mass",
            "rig.pendulum_com_m": "length"}
#: Held, with the reason: a distribution that varied it would count its effect twice
HELD = {"motor.viscous_friction_nms": "b_m / r^2 is in the cart's viscous friction "
        "as identified"}


def measured_noise(result: Any) -> dict[str, float]:
    """Each sensor's noise standard deviation (SI) from a fit's residual RMS in steps."""
    from pisc_model import sensors

    s = result.base.sensors
    x = np.concatenate([r.x for r in result.recordings])
    v = float(sensors.ir_voltage(s, float(np.median(x))))
    ir_step = abs(float(sensors.ir_position(s, v + s.adc_lsb_v) - sensors.ir_position(s, v)))
    steps = (ir_step, s.encoder_rad_per_count, s.adc_lsb_v * s.current_scale_a_per_v)
    return {name: float(step * math.sqrt(max(r * r - 1.0 / 12.0, 0.0)))
            for name, step, r in zip(NOISE, steps, result.residual_rms, strict=True)}


def _estimate(e: Any, source: str) -> dict[str, Any]:
    u = e.unknown
    return {"name": u.name, "key": u.key, "unit": u.unit, "value": float(e.value),
            "low": float(e.low), "high": float(e.high), "std": float(e.std),
            "source": source, "reason": e.reason}


def merge(results: Mapping[str, Any], flat: Mapping[str, Any]) -> dict[str, Any]:
    """The record of both identifications (``results`` by stage: 'excitation',
    'free-swing'); ``flat``: the free swing's file (the excitation's values beneath)."""
    from pisc_robust.identify_data import NOT_PLANT

    estimates, unidentified = [], []
    for stage, result in results.items():
        estimates += [_estimate(e, stage) for e in result.estimates]
        unidentified += [_estimate(e, stage) for e in result.not_identifiable]
    chosen: dict[str, dict[str, Any]] = {}
    for e in estimates:
        if e["key"] in NOT_PLANT and e["key"] != "delay":
            continue
        width = e["high"] - e["low"]
        if e["name"] not in chosen or width < chosen[e["name"]]["high"] - chosen[e["name"]]["low"]:
            chosen[e["name"]] = e
    merged = dict(flat)
    for name, e in chosen.items():
        if name != LATENCY:  # (the file's delay: the estimate plus the recorded latency)
            merged[name] = float(f"{e['value']:.6g}")
    for e in estimates:
        e["in_file"] = chosen.get(e["name"]) is e
    excitation = results["excitation"]
    latency = np.concatenate([r.latency_s for r in excitation.recordings])
    return {
        "estimates": estimates,
        "not_identifiable": [e for e in unidentified if e["name"] not in chosen],
        "residual_rms": {stage: [float(v) for v in r.residual_rms]
                         for stage, r in results.items()},
        # each fit's residual bounds the noise from above: the tighter bound of the two
        "noise": {name: min(measured_noise(r)[name] for r in results.values())
                  for name in NOISE},
        "latency_s": {"p1": float(np.percentile(latency, 1)),
                      "p50": float(np.median(latency)),
                      "p99": float(np.percentile(latency, 99))},
        "wall_clock": any(r.wall_clock for r in excitation.recordings),
        "flat": {k: (list(v) if isinstance(v, tuple) else v) for k, v in merged.items()},
    }


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def rig_file_text(identified: Mapping[str, Any]) -> str:
    """The rig's parameter file: every estimate and interval in its header."""
    from pisc_sim.configuration import params_file_text

    head = ["pisc_commission: the rig as identified (the excitation, then the free swing on "
            "top); every estimate, its 95 % interval and the fit it came from:"]
    for e in identified["estimates"]:
        head.append(f"  {e['name']} = {_fmt(e['value'])} {e['unit']} (95 %: "
                    f"{_fmt(e['low'])} .. {_fmt(e['high'])}), {e['source']}"
                    + ("" if e["in_file"] else ", not in the file (the other fit's "
                       "interval is narrower)" if e["name"].count(".") else ", not a plant "
                       "parameter"))
    for e in identified["not_identifiable"]:
        head.append(f"  {e['name']}: not identifiable ({e['source']}), the base value kept")
    noise = identified["noise"]
    head.append("  measured noise (above quantisation): " + ", ".join(
        f"{k} {_fmt(v)}" for k, v in noise.items()))
    lat = identified["latency_s"]
    head.append(f"  recorded sample-to-voltage latency: p1 {lat['p1'] * 1e3:.3f}, median "
                f"{lat['p50'] * 1e3:.3f}, p99 {lat['p99'] * 1e3:.3f} ms")
    return "".join(f"# {line}\n" for line in head) + params_file_text(identified["flat"])


def describe(identified: Mapping[str, Any]) -> list[str]:
    lines = [f"{e['key']:<15}{_fmt(e['value']):>12} {e['unit']:<10} 95 % {_fmt(e['low'])} .. "
             f"{_fmt(e['high'])} ({e['source']}{'' if e['in_file'] else ', not kept'})"
             for e in identified["estimates"]]
    lines += [f"{e['key']:<15}not identifiable ({e['source']})"
              for e in identified["not_identifiable"]]
    lines.append("noise (measured): " + ", ".join(
        f"{k.split('.')[1]} {_fmt(v)}" for k, v in identified["noise"].items()))
    return lines


def _rule(name: str) -> Any:
    from pisc_robust.uncertainty import _field

    return _field(name)[1].metadata["rule"]


def _range(name: str, value: float, low: float, high: float, widen: float
           ) -> tuple[float, float]:
    """[value - widen (value - low), value + widen (high - value)], its low end moved in
    to what the parameter's rule allows (0, or a fraction of the value)."""
    lo, hi = value - widen * (value - low), value + widen * (high - value)
    rule = _rule(name)
    if rule(lo):
        lo = max(lo, 0.0)
    if rule(lo):
        lo = value / (1.0 + widen)
    return lo, hi


def distribution_text(identified: Mapping[str, Any], plan: Any, prior: Any) -> str:
    """The distribution file of the rig (module docstring); ``plan``: its options
    (:class:`pisc_robust.commission.Plan`), ``prior``: the distribution whose ranges the
    parameters nothing pins down keep."""
    flat = identified["flat"]
    entries: dict[str, tuple[float, float, str]] = {}
    delay = None
    for e in identified["estimates"]:
        if not e["in_file"]:
            continue
        if e["name"] == LATENCY:
            delay = e
            continue
        if e["name"].count(".") != 1:  # (a sensor's own error, not the plant's)
            continue
        lo, hi = _range(e["name"], e["value"], e["low"], e["high"], plan.widen)
        entries[e["name"]] = (lo, hi, f"identified {_fmt(e['value'])} (95 %: "
                              f"{_fmt(e['low'])} .. {_fmt(e['high'])}, {e['source']}), "
                              f"x{plan.widen:g}")
    lat = identified["latency_s"]
    if delay is not None:
        d_lo, d_hi = _range(LATENCY, delay["value"], delay["low"], delay["high"], plan.widen)
        lo, hi = max(0.0, lat["p1"] + d_lo), lat["p99"] + d_hi
        period = float(flat["loop.period_s"])
        if hi >= period:
            # (the batch simulation models a command that comes within its period)
            raise ValueError(
                f"the latency reaches {hi * 1e3:.3f} ms (the recorded sample-to-voltage p99 "
                f"{lat['p99'] * 1e3:.3f} ms plus the identified delay, widened): past the "
                f"{period * 1e3:g} ms period, commands came late in these runs (a machine "
                "busy with other work, or runs without --realtime); make the runs again on "
                "a quiet machine (remove 1-excitation and the stages after it)")
        entries[LATENCY] = (lo, hi, f"recorded p1 {lat['p1'] * 1e3:.3f} .. p99 "
                            f"{lat['p99'] * 1e3:.3f} ms, plus the delay "
                            f"{_fmt(delay['value'])} s (95 %: {_fmt(delay['low'])} .. "
                            f"{_fmt(delay['high'])}), x{plan.widen:g}")
    for name, value in identified["noise"].items():
        entries[name] = (value * (1.0 - plan.noise_span), value * (1.0 + plan.noise_span),
                         f"measured {_fmt(value)}, x(1 -+ {plan.noise_span:g})")
    for name, what in MEASURED.items():
        tol = plan.mass_tolerance if what == "mass" else plan.length_tolerance
        value = float(flat[name])
        if tol > 0:
            entries[name] = (value * (1.0 - tol), value * (1.0 + tol),
                             f"as measured, {value:g} +-{100 * tol:g} %")
    starts = (("initial.x_m", plan.start_x_m, "m"), ("initial.theta_rad",
                                                     plan.start_theta_rad, "rad"))
    for name, width, unit in starts:
        value = float(flat[name])
        if width > 0:
            entries[name] = (value - width, value + width,
                             f"the starts: {value:g} +-{width:g} {unit}, at rest")
    unknown = {e["name"]: e for e in identified["not_identifiable"]}
    for r in prior.ranges:
        if r.name in entries or r.name in HELD or r.name.startswith("initial.") \
                or r.name in NOISE or r.name == LATENCY:
            continue
        lo, hi = r.value_range
        why = ("not identifiable from these runs" if r.name in unknown
               else "not identified")
        entries[r.name] = (lo, hi, f"{why}: {prior.name}'s range")
    lines = [
        "# The distribution of a commissioned rig, written by pisc_commission from its",
        "# identification (docs/commissioning.md): identified values over their 95 %",
        f"# intervals widened x{plan.widen:g}, the noise and latency as measured, the masses and",
        "# lengths within their measuring tolerance, the starts the rig will meet.",
        *(f"# held: {name}: {why}" for name, why in HELD.items()),
        "distribution:",
        "  description: the commissioned rig as identified, measured and started",
    ]
    if flat.get("models.friction", "none") != "none":
        lines.append(f"  plant: {{models: {{friction: {flat['models.friction']}}}}}")
    lines.append("  parameters:")
    for name in sorted(entries):
        lo, hi, why = entries[name]
        lines.append(f"    {name}: {{uniform: [{lo!r}, {hi!r}]}}  # {why}")
    return "\n".join(lines) + "\n"

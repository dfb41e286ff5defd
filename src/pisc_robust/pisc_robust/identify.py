"""System identification from recorded runs: the rig's parameters, with their uncertainty.

The plant of :mod:`pisc_plant.plant` (the rig's full-fidelity layout: armature current,
RC-filtered sensors) is driven by the voltages a run recorded, and the parameters asked
for are fitted by ``scipy.optimize.least_squares`` so that what it predicts matches
what the sensors measured: the IR position and the current through their 10-bit ADC,
the angle through the encoder. Residuals are taken where the sensors quantise, in
their own steps (ADC codes, encoder counts; a measured code stands for the middle of
its step), so the fit's residual reads directly against the sensors' resolution:
quantisation alone gives 1/sqrt(12) = 0.29 of a step.

**Segments (multiple shooting).** The recording is cut into segments (1 s by default),
each simulated from an initial state of its own that the fit estimates with the
parameters (cart position and velocity, angle and rate, the two sensor filters'
voltages; the armature current starts at its quasi-static value). Model error and
drift then cannot accumulate over a run, and an unstable upright would not dominate.
A segment is left out, and the report says so, when in it the cart was at an end
stop (the IR reading saturates there: the stops lie beyond the sensor's range), the
current sensor saturated, a sample was missing, or a voltage arrived two periods late.

**Timing.** Each voltage acts from the time it reached the rig: in a run on the wall
clock (the driver and a rig, or its virtual rig) that is the cycle's own latency from
the rig's tick, plus a constant the fit can estimate (``delay``). The bag gives the
latency from the sample's stamp to the voltage: to the driver's write of the byte
(``/pisc/motor/voltage_sent``; bags before 2026-12-03 have only the controllers'
publication of ``/pisc/motor/voltage``, earlier than the write by the callback's wait),
and from the rig's tick to the stamp, the read's delay, which :func:`rig_ticks`
estimates from the stamps. The voltage is the byte's: a sample the driver did not answer
(its answer came too late) or in whose period it wrote 0 V of its own is left out; one
that reached the rig after the next tick acts from there, in the next period. Measured
against the virtual rig's own record of each byte's arrival (a 60 s run, 2026-12-03):
the voltages' publication explained the arrival times with a correlation of 0.45-0.57
(another run), the writes 0.81 (0.27 ms robust spread), the writes with the reads'
delays 0.93 (0.13 ms), and 0.95 (0.11 ms) once the virtual rig timed its periods from
its timer's ticks (docs/identification.md, "Timing"). In a lockstep simulation the
latency is ``delay`` alone (the plant's ``actuator.command_delay_s``).

**The Jacobian** is one batched call of the compiled kernel: a plant set
(:func:`pisc_plant.plant.plant_set`) with one rig per segment and per perturbation
(each parameter, each component of a segment's initial state), forward differences.

**Stopping.** Each pass of ``least_squares`` ends as usual (on the cost, the step or
the gradient), once the next Gauss-Newton step would move every unknown by less than
a hundredth of its standard error (:func:`_within_standard_error`), or once five
iterations together gained less than a move of a quarter standard error would
(:func:`_stalled`): along the R-J_m valley the cost keeps falling by parts in 10^9 an
evaluation, which the data cannot tell from nothing, and such fits used to run out of
evaluations.

**Uncertainty.** The 95 % intervals come from the Jacobian at the optimum, with a
cluster-robust (sandwich) covariance over segments: the quantisation error of a slowly
moving signal is far from white, and the sandwich does not assume it is; the t
quantile has one degree of freedom less than there are segments. Channels are weighted
by their residual RMS (a second pass after a first fit weighted by the sensors'
resolution). A parameter whose interval is wider than its own value (or its typical
size) is reported as not identifiable from these data and held at its base value; a
pair whose estimates correlate beyond 0.95 is named.

Some parameters cannot be told apart by any data from this model: J_m / r^2 adds to
the cart's mass M + m (fit J_m with M known, or M with J_m known), b_m / r^2 to the
cart's viscous friction, and L acts only within 0.14 ms of a voltage step, as a delay
would. The correlation warning names such pairs when both are fitted.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from pisc_bag.bag import BagError, bag_topics, read_bag
from pisc_sim.configuration import load_graph_config, params_file_text
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.convert import MessageError, joint_sample_from_msg, motor_sample_from_msg
from pisc_msgs_py.topics import JOINT_STATES, MOTOR_CURRENT, VOLTAGE, VOLTAGE_SENT
from pisc_model import sensors
from pisc_model.params import ModelParams, NoiseParams, SensorParams
from pisc_plant import kernel_batch as kernel
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig, plant_set

__all__ = ["DEFAULT_FIT", "UNKNOWNS", "FitError", "IdentifyError", "Recording", "Result", "Unknown",
           "format_report", "identify", "load_base", "parse_fit", "plot_overlay",
           "read_recording", "recording_from_arrays", "result_flat", "write_result"]

CONTROLLERS_PARAMS = "pisc_params.yaml"  # the bag's controllers' file (pisc_bringup.run_start)
MEASURED = (JOINT_STATES.name, MOTOR_CURRENT.name, VOLTAGE.name)
QUANTISATION_RMS = 1.0 / math.sqrt(12.0)  # of a step, for a uniform error
STATE_SCALE = np.array([0.002, 0.02, 0.002, 0.05, 0.005, 0.005])  # x, x', th, th', v_ir, v_cur
STATE_NAMES = ("x", "x_dot", "theta", "theta_dot", "v_ir", "v_cur")
CHANNELS = ("IR position", "encoder angle", "current")
STEP = 1e-6  # forward-difference step, in units of each unknown's scale
#: A voltage reaching the rig later than this many periods after its sample is left out;
#: one after the next tick acts from its arrival in the next period (make_segments)
LATE_PERIODS = 1.9
#: An estimate is reported as identified when its 95 % interval's half-width is at most
#: this fraction of it (or a tenth of the parameter's typical size, for a value near 0)
IDENTIFIABLE = 0.25


class IdentifyError(RuntimeError):
    """The input cannot be identified from; the message says why."""


class FitError(IdentifyError):
    """The fit failed (did not converge, or the model diverged)."""


@dataclass(frozen=True)
class Unknown:
    """A parameter the fit can estimate."""

    key: str  # short name on the command line
    name: str  # the parameter it sets (dotted name)
    unit: str
    scale: float  # typical size (scales the fit, and decides what is identifiable)
    low: float
    high: float
    needs_voltage: bool  # seen only through the motor: needs a voltage that is not zero
    meaning: str


UNKNOWNS = (
    Unknown("R", "motor.resistance_ohm", "ohm", 10.0, 0.5, 500.0, True, "armature resistance"),
    Unknown("L", "motor.inductance_h", "H", 2e-3, 1e-6, 1.0, True, "armature inductance"),
    Unknown("J_m", "motor.rotor_inertia_kgm2", "kg m^2", 2e-6, 0.0, 1e-3, True,
            "rotor inertia (with M + m known)"),
    Unknown("b_m", "motor.viscous_friction_nms", "N m s/rad", 1e-5, 0.0, 1e-2, True,
            "rotor viscous friction (adds to the cart's as b_m / r^2)"),
    Unknown("cart_coulomb", "friction.cart_coulomb_n", "N", 0.05, 0.0, 5.0, True,
            "cart Coulomb friction"),
    Unknown("cart_viscous", "friction.cart_viscous_ns_per_m", "N s/m", 0.25, 0.0, 20.0, True,
            "cart viscous friction"),
    Unknown("pivot_viscous", "friction.pivot_viscous_nms", "N m s/rad", 5e-5, 0.0, 1e-2, False,
            "pivot viscous friction"),
    Unknown("M", "rig.cart_mass_kg", "kg", 0.5, 0.01, 20.0, True, "cart mass"),
    Unknown("m", "rig.pendulum_mass_kg", "kg", 0.01, 1e-4, 5.0, False, "pendulum mass"),
    Unknown("l", "rig.pendulum_com_m", "m", 0.1, 1e-3, 2.0, False,
            "pivot to the pendulum's centre of mass"),
    Unknown("I", "rig.pendulum_inertia_kgm2", "kg m^2", 3e-5, 0.0, 1.0, False,
            "pendulum inertia about its centre of mass"),
    Unknown("delay", "actuator.command_delay_s", "s", 1e-3, 0.0, 1.0, True,
            "sample to voltage, the part the bag does not record"),
    Unknown("current_offset", "current_offset", "A", 0.01, -0.5, 0.5, False,
            "error of the current sensor's zero (measured minus true current)"),
)
#: Unknowns that are not plant parameters: timing and the sensors' own errors
NOT_PLANT = ("delay", "current_offset")
BY_KEY = {u.key: u for u in UNKNOWNS}
BY_NAME = {u.name: u for u in UNKNOWNS}

#: What each experiment identifies by default (``--fit`` replaces it).
DEFAULT_FIT = {
    "excitation": ("R", "L", "J_m", "cart_coulomb", "cart_viscous", "pivot_viscous",
                   "current_offset"),
    # the swing fixes (I + m l^2) / (m l) and c / (m l) only (l and I apart need the
    # cart's reaction, which its friction holds still): l from the base, as measured
    "free_swing": ("I", "pivot_viscous"),
    "none": ("R", "L", "J_m", "cart_coulomb", "cart_viscous", "pivot_viscous",
             "current_offset"),
}


def parse_fit(spec: str | Sequence[str]) -> list[Unknown]:
    """``R,J_m,cart_coulomb`` (short or dotted names) -> the unknowns, in that order."""
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    out: list[Unknown] = []
    for item in (i.strip() for i in items):
        if not item:
            continue
        unknown = BY_KEY.get(item) or BY_NAME.get(item)
        if unknown is None:
            raise IdentifyError(
                f"--fit {item}: no such parameter (known: "
                + ", ".join(f"{u.key} ({u.name})" for u in UNKNOWNS) + ")")
        if unknown not in out:
            out.append(unknown)
    if not out:
        raise IdentifyError("--fit: no parameter named")
    return out


# -- recordings ------------------------------------------------------------------------


@dataclass(frozen=True)
class Recording:
    """The measured samples of one run, with the voltage that answered each."""

    name: str
    stamps_ns: np.ndarray  # (N,) int64, the cycles' header stamps
    x: np.ndarray  # measured cart position, m
    theta: np.ndarray  # measured angle, rad
    current: np.ndarray  # measured current, A
    voltage: np.ndarray  # the voltage answering each sample, V
    latency_s: np.ndarray  # the rig's sample to its voltage (wall clock), 0 in lockstep
    wall_clock: bool
    experiment: str = "none"
    params_file: Path | None = None  # the run's controllers' parameter file, if any
    # wall clock: each sample's tick of the rig's timer (a frame lost skips one) and its
    # time from that tick to its stamp (included in latency_s), estimated from the stamps
    # (:func:`rig_ticks`); None when not estimated
    ticks: np.ndarray | None = None
    read_delay_s: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return float(self.stamps_ns[-1] - self.stamps_ns[0]) * 1e-9


def recording_from_arrays(name: str, period_s: float, x: Any, theta: Any, current: Any,
                          voltage: Any, latency_s: Any = 0.0, experiment: str = "none",
                          wall_clock: bool = False) -> Recording:
    """A recording of samples every ``period_s`` (a pure simulation's log, for instance)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    stamps = np.arange(n, dtype=np.int64) * round(period_s * 1e9)
    return Recording(name, stamps, x, np.asarray(theta, dtype=float),
                     np.asarray(current, dtype=float), np.asarray(voltage, dtype=float),
                     np.broadcast_to(np.asarray(latency_s, dtype=float), (n,)).copy(),
                     wall_clock, experiment)


def _experiment_of(params_file: Path) -> str:
    from pisc_msgs_py.config import load_params_file

    try:
        return str(load_params_file(params_file).get("experiment.kind", "none"))
    except ConfigError:
        return "none"


def rig_ticks(stamps_ns: np.ndarray, period_s: float, window: int = 200
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """(each sample's tick of the rig's timer, its time from that tick to its stamp in s,
    the earliest 0), or None when the stamps do not show the ticks.

    The rig samples on its own timer, every period; the driver stamps a frame when it
    has read it, so a late read makes a late stamp, not a late sample. With sample k
    taken at tick n_k, stamp_k - n_k T is the read's delay plus a constant and the two
    clocks' drift, and its least value over the next ``window`` samples (a read that met
    no delay) is the constant and drift alone. A frame lost (the parser refuses one whose
    bytes came apart, a byte dropped) raises that least value by a period for good from
    the next sample on: n_k = k + the lost frames before k. A line through each window's
    earliest stamp is then the ticks' time, and each stamp's distance above it its read's
    delay (reads late by half a period or more just before a lost frame would put the
    loss early: a sample just after a skipped tick and a tenth of a period or more below
    the line goes to the tick before). None when the result is not one line (some
    window's earliest half a period or more off it: a stall longer than the window, say)
    or the run is shorter than two windows."""
    n = len(stamps_ns)
    if n < 2 * window:
        return None
    k = np.arange(n)
    t = (stamps_ns - stamps_ns[0]) * 1e-9
    offset = t - k * period_s
    padded = np.concatenate([offset, np.full(window - 1, np.inf)])
    ahead = np.lib.stride_tricks.sliding_window_view(padded, window).min(axis=1)
    # lost frames: a rise of half a period or more over the level, which follows the
    # least value down and up by less than a quarter period (the clocks' drift)
    ticks = k.copy()
    level, count = ahead[0], 0
    for j in range(n):
        x = (ahead[j] - level) / period_s - count
        if x >= 0.5:
            count += int(np.rint(x))
        elif x < 0.25:
            level = ahead[j] - count * period_s
        ticks[j] += count

    def fit() -> tuple[np.ndarray, np.ndarray]:
        offset = t - ticks * period_s
        earliest = np.array([i + int(np.argmin(offset[i:i + window]))
                             for i in range(0, n, window)])
        slope, intercept = np.polyfit(ticks[earliest], offset[earliest], 1)
        return offset - (intercept + slope * ticks), earliest

    delay, earliest = fit()
    # reads late by half a period or more just before a lost frame put the loss early:
    # such a sample then sits a period before its tick; it belongs to the tick before
    early = np.flatnonzero(delay < -0.1 * period_s)
    for j in early:
        if j == 0 or ticks[j - 1] < ticks[j] - 1:
            ticks[j] -= 1
    if early.size:
        delay, earliest = fit()
    if np.ptp(delay[earliest]) >= 0.5 * period_s:
        return None
    return ticks, delay - delay.min()


def read_recording(bag: str | Path) -> Recording:
    """The measured samples of a bag; :class:`IdentifyError` when it cannot serve."""
    bag = Path(bag)
    try:
        topics = bag_topics(bag)
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    missing = [t for t in MEASURED if t not in topics]
    if missing:
        raise IdentifyError(
            f"{bag}: the bag has no {' and no '.join(missing)}: identification needs the "
            f"measured position and angle ({JOINT_STATES.name}), current "
            f"({MOTOR_CURRENT.name}) and the voltage answering each sample ({VOLTAGE.name})")
    joints: dict[int, tuple[float, float, int | None]] = {}
    current: dict[int, float] = {}
    voltage: dict[int, tuple[float, int | None]] = {}
    # through the driver: what each byte written asked for, and when it was written
    written: dict[int, tuple[float, int | None]] = {}
    own: set[int] = set()  # samples in whose period the driver wrote 0 V of its own
    try:
        for m in read_bag(bag, [*MEASURED, *([VOLTAGE_SENT.name] if VOLTAGE_SENT.name in
                                             topics else [])]):
            if m.topic == JOINT_STATES.name:
                s = joint_sample_from_msg(m.message)
                joints[s.stamp_ns] = (s.position_m, s.angle_rad, m.publish_time_ns)
            elif m.topic == MOTOR_CURRENT.name:
                c = motor_sample_from_msg(m.message)
                current[c.stamp_ns] = c.value
            elif m.topic == VOLTAGE.name:
                v = motor_sample_from_msg(m.message)
                voltage[v.stamp_ns] = (v.value, m.publish_time_ns)
            else:
                v = motor_sample_from_msg(m.message)
                if m.message.header.frame_id == "answer":
                    written.setdefault(v.stamp_ns, (v.value, m.publish_time_ns))
                elif m.message.header.frame_id == "zero":  # (a hold repeats the last byte)
                    own.add(v.stamp_ns)
    except BagError as exc:
        raise IdentifyError(str(exc)) from None
    except MessageError as exc:
        raise IdentifyError(f"{bag}: {exc}") from None
    empty = [name for name, d in zip(MEASURED, (joints, current, voltage), strict=True) if not d]
    if empty:
        raise IdentifyError(f"{bag}: no messages on {', '.join(empty)}: nothing was measured")
    if written:
        # the bytes as written: a sample the driver did not answer (its answer came too
        # late) or in whose period it wrote 0 V of its own gets no voltage, and the model
        # leaves its period out
        voltage = {k: written.get(k, (math.nan, None)) if k not in own else (math.nan, None)
                   for k in voltage}
    stamps = np.array(sorted(set(joints) & set(current) & set(voltage)), dtype=np.int64)
    if len(stamps) < 20:
        raise IdentifyError(f"{bag}: only {len(stamps)} complete samples (position, angle, "
                            "current and the voltage answering them)")
    x = np.array([joints[s][0] for s in stamps])
    theta = np.array([joints[s][1] for s in stamps])
    i = np.array([current[s] for s in stamps])
    u = np.array([voltage[s][0] for s in stamps])
    sent = [(voltage[s][1], joints[s][2]) for s in stamps]
    known = [(v, j) for v, j in sent if v is not None and j is not None]
    # a run on the wall clock stamps its samples with the time they were sent; a lockstep
    # run with simulated time, unrelated to the publish times
    wall = bool(known) and float(np.median([abs(j - s) for (_, j), s in zip(
        sent, stamps, strict=True) if j is not None])) < 1e9
    latency = np.array([(v - j) * 1e-9 if wall and v is not None and j is not None else 0.0
                        for v, j in sent])
    params_file = bag / CONTROLLERS_PARAMS
    params = params_file if params_file.is_file() else None
    ticks = read = None
    if wall:
        period = float(np.median(np.diff(stamps))) * 1e-9
        found = rig_ticks(stamps, period)
        if found is not None:
            ticks, read = found
            latency = latency + read
    return Recording(str(bag), stamps, x, theta, i, u, latency, wall,
                     _experiment_of(params) if params else "none", params, ticks, read)


# -- segments --------------------------------------------------------------------------


@dataclass
class Segments:
    """The samples the fit uses, cut into segments of at most ``length`` samples."""

    length: int
    owner: np.ndarray  # (n,) the recording of each segment
    first: np.ndarray  # (n,) index of each segment's first sample in its recording
    size: np.ndarray  # (n,) samples in each segment
    u: np.ndarray  # (n, length) voltage answering sample j (padded)
    u_before: np.ndarray  # (n,) the voltage answering the sample before the first
    latency: np.ndarray  # (n, length) s
    measured: np.ndarray  # (n, length, 3): IR and current ADC voltages, angle (step middles)
    mask: np.ndarray  # (n, length, 3) bool: residuals that count
    guess: np.ndarray  # (n, 6) initial state guesses
    left_out: list[tuple[str, float, float, str]] = field(default_factory=list)
    # the voltage before u_before and u_before's latency: the one acting at the start when
    # u_before arrives in the segment's first period (None: every voltage on time)
    u_before2: np.ndarray | None = None
    latency_before: np.ndarray | None = None

    @property
    def count(self) -> int:
        return len(self.owner)

    def subset(self, keep: np.ndarray, reason: str,
               recordings: Sequence[Recording]) -> Segments:
        """The segments ``keep`` (bool, one per segment); the others left out for
        ``reason``."""
        left = list(self.left_out)
        for n in np.flatnonzero(~keep):
            r = recordings[self.owner[n]]
            t = (r.stamps_ns - r.stamps_ns[0]) * 1e-9
            left.append((r.name, float(t[self.first[n]]),
                         float(t[self.first[n] + self.size[n] - 1]), reason))
        size = int(self.size[keep].max())
        return Segments(size, self.owner[keep], self.first[keep], self.size[keep],
                        self.u[keep, :size], self.u_before[keep], self.latency[keep, :size],
                        self.measured[keep, :size], self.mask[keep, :size],
                        self.guess[keep], left,
                        None if self.u_before2 is None else self.u_before2[keep],
                        None if self.latency_before is None else self.latency_before[keep])


def _codes(s: SensorParams, r: Recording) -> tuple[np.ndarray, ...]:
    """(IR code, current code, encoder count) of each sample, as floats, and whether each
    channel is on its sensor's grid (quantised measurements)."""
    ir = (sensors.ir_voltage(s, r.x) - s.adc_ref_low_v) / s.adc_lsb_v
    cur = (sensors.current_sensor_voltage(s, r.current) - s.adc_ref_low_v) / s.adc_lsb_v
    count = (r.theta - s.encoder_zero_rad) / s.encoder_rad_per_count
    return ir, cur, count


def _on_grid(values: np.ndarray) -> bool:
    return bool(np.all(np.abs(values - np.rint(values)) < 1e-3))


def make_segments(recordings: Sequence[Recording], s: SensorParams, period_s: float,
                  segment_s: float = 1.0, min_segment_s: float = 0.25) -> Segments:
    """Cut the recordings into segments, leaving out what the model cannot follow."""
    length = max(4, int(round(segment_s / period_s)))
    shortest = max(4, int(round(min_segment_s / period_s)))
    pieces: list[tuple[int, int, int]] = []  # (recording, first, size)
    left_out: list[tuple[str, float, float, str]] = []
    top = s.adc_levels - 1
    for k, r in enumerate(recordings):
        n = len(r.stamps_ns)
        t = (r.stamps_ns - r.stamps_ns[0]) * 1e-9
        ir, cur, _ = _codes(s, r)
        gaps = np.diff(r.stamps_ns) * 1e-9 / period_s
        # a transition k -> k + 1 the model can follow: the next sample one period on, the
        # voltage answering k applied within the period
        if r.ticks is not None:  # (rig_ticks) a late read is a late stamp, and only a
            steady = np.diff(r.ticks) == 1  # frame lost is a sample missing
        elif r.wall_clock:
            steady = (gaps > 0.5) & (gaps < 1.5)
        else:
            steady = np.abs(gaps - 1.0) < 1e-3
        # the voltage answering k reaches the rig before tick k + 2 (LATE_PERIODS: with
        # a margin for the fitted delay); one that comes after tick k + 1 acts in the
        # next period, as the model simulates it
        timely = r.latency_s[:-1] < LATE_PERIODS * period_s
        finite = np.isfinite(r.x) & np.isfinite(r.theta) & np.isfinite(r.current)
        answered = np.isfinite(r.voltage[:-1])  # (through the driver: as it wrote it)
        good = steady & timely & finite[:-1] & finite[1:] & answered
        stop = (np.rint(ir) <= 0) | (np.rint(ir) >= top)
        saturated = (np.rint(cur) <= 0) | (np.rint(cur) >= top)
        reasons = {}
        for j in np.flatnonzero(~good):
            reasons[j] = ("a sample missing or out of time" if not steady[j] else
                          "the voltage arrived two periods late" if not timely[j] else
                          "a value that is not finite" if not (finite[j] and finite[j + 1])
                          else "no answer written to the rig, or 0 V of the driver's own")
        # runs of good transitions; a segment starts one sample after its run begins (the
        # voltage acting at its start is then known)
        start = 0
        while start < n - 1:
            if not good[start]:
                start += 1
                continue
            end = start
            while end < n - 1 and good[end]:
                end += 1
            # samples start + 1 .. end form the run (transition start -> start + 1 known)
            a, b = start + 1, end  # inclusive
            count = b - a + 1
            bounds = []
            if count >= shortest:
                parts = max(1, int(round(count / length)))
                edges = np.linspace(a, b + 1, parts + 1).round().astype(int)
                bounds = [(lo, hi - lo) for lo, hi in zip(edges[:-1], edges[1:], strict=True)
                          if hi - lo >= shortest]
            elif count > 0:
                left_out.append((r.name, t[a], t[b], "too short between breaks in timing"))
            for lo, size in bounds:
                hi = lo + size
                if stop[lo:hi].any():
                    left_out.append((r.name, t[lo], t[hi - 1],
                                     "the cart at an end stop (IR reading saturated)"))
                elif saturated[lo:hi].any():
                    left_out.append((r.name, t[lo], t[hi - 1], "current sensor saturated"))
                else:
                    pieces.append((k, lo, size))
            if end < n - 1:
                left_out.append((r.name, t[end], t[min(end + 1, n - 1)], reasons[end]))
            start = end + 1
    if not pieces:
        raise IdentifyError("no segment left to fit: " + (
            "; ".join(sorted({reason for *_, reason in left_out})) or "the recordings are "
            "too short"))
    size = max(p[2] for p in pieces)
    n = len(pieces)
    u = np.zeros((n, size))
    before = np.zeros(n)
    before2 = np.zeros(n)
    latency_before = np.zeros(n)
    latency = np.zeros((n, size))
    measured = np.zeros((n, size, 3))
    mask = np.zeros((n, size, 3), dtype=bool)
    guess = np.zeros((n, 6))
    grids = [_on_grid(c) for r in recordings for c in _codes(s, r)]  # IR, current, count
    tau_ir = 1.0 / (2.0 * math.pi * s.ir_filter_hz)
    for row, (k, lo, count) in enumerate(pieces):
        r = recordings[k]
        ir, cur, cnt = _codes(s, r)
        on = grids[3 * k:3 * k + 3]
        sl = slice(lo, lo + count)
        # (the last sample's voltage acts after the segment: NaN there when the driver
        # wrote no answer to it)
        u[row, :count] = np.nan_to_num(r.voltage[sl])
        u[row, count:] = u[row, count - 1]
        before[row] = r.voltage[lo - 1]
        # (the one before it, if known: else a late u_before is taken as acting from the
        # start)
        two = r.voltage[lo - 2] if lo >= 2 else math.nan
        before2[row] = two if math.isfinite(two) else before[row]
        latency_before[row] = r.latency_s[lo - 1]
        latency[row, :count] = r.latency_s[sl]
        half = 0.5  # a code stands for the middle of its step (the ADC truncates)
        measured[row, :count, 0] = s.adc_ref_low_v + (
            (np.rint(ir[sl]) + half) if on[0] else ir[sl]) * s.adc_lsb_v
        measured[row, :count, 1] = s.encoder_zero_rad + (
            np.rint(cnt[sl]) if on[2] else cnt[sl]) * s.encoder_rad_per_count
        measured[row, :count, 2] = s.adc_ref_low_v + (
            (np.rint(cur[sl]) + half) if on[1] else cur[sl]) * s.adc_lsb_v
        mask[row, :count] = True
        # initial state: differences around the first sample, the IR reading corrected
        # for its filter's lag
        j0, j1 = max(lo - 3, 0), min(lo + 3, len(r.x) - 1)
        dt = (j1 - j0) * period_s
        x_dot = (r.x[j1] - r.x[j0]) / dt
        theta_dot = (r.theta[j1] - r.theta[j0]) / dt
        guess[row] = (r.x[lo] + x_dot * tau_ir, x_dot, r.theta[lo], theta_dot,
                      measured[row, 0, 0], measured[row, 0, 2])
    owner, first, sizes = (np.array(v) for v in zip(*pieces, strict=True))
    return Segments(size, owner, first, sizes, u, before, latency, measured, mask, guess,
                    left_out, before2, latency_before)


# -- the model -------------------------------------------------------------------------


def model_plant(base: PlantConfig) -> PlantConfig:
    """The model the fit simulates: ``base``'s values in the rig's full layout (armature
    current, quantised sensors and their filters, Coulomb and viscous friction), without
    noise and without end stops (segments at a stop are left out)."""
    from dataclasses import replace

    return replace(base, models=ModelParams(armature="full", current_loop="sampled_pi",
                                            sensors="quantised", sensor_filters=True,
                                            friction="coulomb", end_stops=False),
                   noise=NoiseParams())


def _with_values(config: PlantConfig, values: dict[str, float]) -> PlantConfig:
    """``config`` with the dotted parameters ``values`` set (one rig)."""
    sections: dict[str, dict[str, float]] = {}
    for name, value in values.items():
        section, _, leaf = name.partition(".")
        sections.setdefault(section, {})[leaf] = float(value)
    return dataclasses.replace(config, **{
        section: dataclasses.replace(getattr(config, section), **changes)
        for section, changes in sections.items()})


def _value(config: PlantConfig, name: str) -> float:
    section, _, leaf = name.partition(".")
    return float(getattr(getattr(config, section), leaf))


class Problem:
    """The least-squares problem over the parameters, the segments' initial states
    eliminated (variable projection).

    For parameters theta, each segment's initial state is fitted on its own (a damped
    Gauss-Newton iteration on six unknowns, every segment and perturbation a rig of one
    batched simulation); :meth:`residuals` is the weighted residual at those states, and
    :meth:`jacobian` its derivative with the states' response taken into account
    (Kaufman's projection: each segment's parameter columns minus their part along its
    own state columns). ``least_squares`` then works on the few parameters only.
    """

    def __init__(self, segments: Segments, base: PlantConfig, fit: Sequence[Unknown],
                 start: dict[str, float]) -> None:
        self.seg = segments
        self.base_config = base
        self.base = model_plant(base)
        self.fit = list(fit)
        self.period = base.loop.period_s
        self.sensors = base.sensors
        self.p = len(self.fit)
        self.start = start
        self.weights = np.full(3, 1.0 / QUANTISATION_RMS)  # 1 / (sigma in steps)
        s = self.sensors
        self.steps = np.array([s.adc_lsb_v, s.encoder_rad_per_count, s.adc_lsb_v])
        self.flat_mask = segments.mask.reshape(segments.count, -1)
        self.rows = np.flatnonzero(segments.mask.reshape(-1))
        per_segment = self.flat_mask.sum(axis=1)
        self.row_edges = np.concatenate([[0], np.cumsum(per_segment)])
        self.scale = np.array([u.scale for u in self.fit])
        self.offsets = np.zeros((segments.count, 6))  # the states, scaled, from the guess
        self._solved: tuple[bytes, np.ndarray] | None = None
        self.simulations = 0

    # unknowns <-> values
    def initial(self) -> np.ndarray:
        return np.array([self.start[u.key] / u.scale for u in self.fit])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low = np.array([u.low / u.scale for u in self.fit])
        high = np.array([(min(u.high, 0.95 * self.period) if u.key == "delay" else u.high)
                         / u.scale for u in self.fit])
        return low, high

    def values(self, z: np.ndarray) -> dict[str, float]:
        out = dict(self.start)
        for k, u in enumerate(self.fit):
            out[u.key] = float(z[k] * u.scale)
        return out

    def states(self, offsets: np.ndarray | None = None) -> np.ndarray:
        """Initial states (n, 6): x, x_dot, theta, theta_dot, v_ir, v_cur."""
        return self.seg.guess + (self.offsets if offsets is None else offsets) * STATE_SCALE

    # simulation
    def simulate(self, values: dict[str, np.ndarray], y0: np.ndarray,
                 rows: np.ndarray) -> np.ndarray:
        """Predicted (IR voltage, angle, current sensor voltage) (rigs, length, 3) of the
        segments ``rows`` (one per rig), rig k with ``values[key][k]`` and state ``y0[k]``.

        Groups of at most ``kernel.CHUNK`` rigs, which the kernel steps on one thread:
        its threads gain nothing at this size and, spinning, cost milliseconds a call."""
        out = np.empty((len(rows), self.seg.length, 3))
        for lo in range(0, len(rows), kernel.CHUNK):
            group = slice(lo, lo + kernel.CHUNK)
            out[group] = self._simulate({k: np.asarray(v)[group] for k, v in values.items()},
                                        y0[group], rows[group])
        return out

    def _simulate(self, values: dict[str, np.ndarray], y0: np.ndarray,
                  rows: np.ndarray, states: np.ndarray | None = None) -> np.ndarray:
        self.simulations += 1
        seg = self.seg
        rigs = len(rows)
        plant_values = {BY_KEY[key].name: v for key, v in values.items()
                        if key not in NOT_PLANT}
        try:
            plant = Plant(plant_set(self.base, plant_values))
        except ConfigError as exc:
            raise FitError(f"the fit reached an invalid model: {exc}") from None
        idx = plant.index
        motor = plant.config.motor
        resistance = np.broadcast_to(np.asarray(motor.resistance_ohm, dtype=float), (rigs,))
        ker = (np.asarray(motor.back_emf_v_s_per_rad, dtype=float)
               / np.asarray(motor.wheel_radius_m, dtype=float))
        delay = np.broadcast_to(values["delay"], (rigs,))
        # the current sensor's zero error, as the voltage it adds at the ADC
        offset = np.broadcast_to(values["current_offset"], (rigs,)) / (
            self.sensors.current_scale_a_per_v)
        u = seg.u[rows]
        latency = seg.latency[rows]
        period = self.period
        # the voltage acting at the first sample; one arriving after it (late) is pending
        acting = seg.u_before[rows]
        pending = np.full(rigs, np.nan)  # arrival of a late voltage in this period, s
        pending_u = acting.copy()
        if seg.latency_before is not None:
            d = seg.latency_before[rows] + delay
            late = d >= period
            acting = np.where(late, seg.u_before2[rows], acting)
            pending = np.where(late, np.minimum(d - period, 0.999 * period), np.nan)
        y = np.empty((rigs, plant.size))
        y[:, idx["x"]] = y0[:, 0]
        y[:, idx["x_dot"]] = y0[:, 1]
        y[:, idx["theta"]] = y0[:, 2]
        y[:, idx["theta_dot"]] = y0[:, 3]
        y[:, idx["i"]] = (plant.applied(acting) - ker * y0[:, 1]) / resistance
        y[:, idx["v_ir"]] = y0[:, 4]
        y[:, idx["v_cur"]] = y0[:, 5]
        length = seg.length
        out = np.empty((rigs, length, 3))
        for j in range(length):
            out[:, j, 0] = y[:, idx["v_ir"]]
            out[:, j, 1] = y[:, idx["theta"]]
            out[:, j, 2] = y[:, idx["v_cur"]] + offset
            if states is not None:
                states[:, j] = y
            if j == length - 1:
                break
            # in this period: the late voltage of the sample before arrives at ``pending``
            # (if any), then this sample's at d, unless it is late too (d >= period);
            # bytes reach the rig in the order they were written
            t = np.zeros(rigs)
            if not np.all(np.isnan(pending)):
                has = ~np.isnan(pending)
                t = np.where(has, pending, 0.0)
                if np.any(t > 0.0):
                    y = plant.advance(y, acting, t)
                acting = np.where(has, pending_u, acting)
            arrival = np.clip(latency[:, j] + delay, 0.0, 1.999 * period)
            late = arrival >= period
            d = np.where(late, period, np.maximum(arrival, t))
            if np.any(d > t):
                y = plant.advance(y, acting, d - t)
            acting = np.where(late, acting, u[:, j])
            if np.any(d < period):
                y = plant.advance(y, acting, period - d)
            pending = np.where(late, arrival - period, np.nan)
            pending_u = u[:, j]
        if not np.all(np.isfinite(out)):
            raise FitError("the model diverged (a value that is not finite) at " + ", ".join(
                f"{k} = {np.asarray(v).ravel()[0]:.4g}" for k, v in values.items()
                if BY_KEY[k] in self.fit))
        return out

    def _weighted(self, predicted: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(rigs, length * 3) weighted residuals in sensor steps, 0 where masked."""
        r = (predicted - self.seg.measured[rows]) / self.steps * self.weights
        return np.where(self.seg.mask[rows], r, 0.0).reshape(len(rows), -1)

    def _batch(self, z: np.ndarray, offsets: np.ndarray, parameters: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Residuals (n, length*3) at the states, their derivatives by the states
        (6, n, length*3) and, with ``parameters``, by the parameters (p, n, length*3):
        one batched simulation, forward differences."""
        n_seg, p = self.seg.count, self.p
        extra = p if parameters else 0
        blocks = 1 + extra + 6
        # segment-major: a segment's rigs side by side share their steps (its latencies),
        # and the kernel computes the exponential scheme's tables once for such a run
        rows = np.repeat(np.arange(n_seg), blocks)
        which = np.tile(np.arange(blocks), n_seg)  # 0 base, then parameters, then states
        values = {k: np.full(len(rows), v) for k, v in self.values(z).items()}
        for k in range(extra):
            u = self.fit[k]
            values[u.key][which == 1 + k] += STEP * u.scale
        y0 = np.repeat(self.states(offsets), blocks, axis=0)
        for c in range(6):
            y0[which == 1 + extra + c, c] += STEP * STATE_SCALE[c]
        r = self._weighted(self.simulate(values, y0, rows), rows).reshape(n_seg, blocks, -1)
        r = r.transpose(1, 0, 2)
        diff = (r[1:] - r[0]) / STEP  # per unit of the scaled unknowns
        return r[0], diff[extra:], (diff[:extra] if parameters else None)

    def solve_states(self, z: np.ndarray, iterations: int = 8) -> np.ndarray:
        """Fit every segment's initial state for parameters ``z``; the residuals (n, L*3).

        Damped Gauss-Newton on each segment's six unknowns, the derivatives by forward
        differences in the same batched simulation as the residuals (the calls cost
        about what a simulation of the segments alone costs); a segment whose cost a
        step raised goes back and is damped more."""
        key = np.asarray(z, dtype=float).tobytes()
        if self._solved is not None and self._solved[0] == key:
            return self._solved[1]
        offsets = self.offsets.copy()
        damping = np.full(self.seg.count, 1e-6)
        kept: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # r, ds, cost
        step = np.zeros_like(offsets)
        for _ in range(iterations):
            r, ds, _ = self._batch(z, offsets, parameters=False)
            cost = np.einsum("ij,ij->i", r, r)
            if kept is not None:
                worse = cost > kept[2]
                if worse.any():
                    offsets[worse] -= step[worse]
                    r[worse], ds[:, worse], cost[worse] = (kept[0][worse], kept[1][:, worse],
                                                          kept[2][worse])
                damping = np.where(worse, damping * 100.0, np.maximum(damping * 0.1, 1e-9))
            kept = (r, ds, cost)
            a = np.einsum("cnk,dnk->ncd", ds, ds)
            diagonal = np.maximum(np.einsum("ncc->nc", a), 1e-12)
            a += damping[:, None, None] * np.eye(6) * diagonal[:, :, None]
            g = np.einsum("cnk,nk->nc", ds, r)
            step = -np.linalg.solve(a, g[:, :, None])[:, :, 0]
            promised = -np.einsum("nc,nc->n", g, step)
            if promised.sum() < 1e-10 * max(cost.sum(), 1.0):
                break
            offsets = offsets + step
        else:
            r, _, _ = self._batch(z, offsets, parameters=False)
            worse = np.einsum("ij,ij->i", r, r) > kept[2]
            offsets[worse] -= step[worse]
            r[worse] = kept[0][worse]
        self.offsets = offsets
        self._solved = (key, r)
        return r

    def residuals(self, z: np.ndarray) -> np.ndarray:
        r = self.solve_states(z)
        return r.reshape(-1)[self.rows]

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """d residuals / d parameters with the states following (Kaufman's projection)."""
        self.solve_states(z)
        _, ds, dp = self._batch(z, self.offsets, parameters=True)
        # per segment: J_p - J_s (J_s^T J_s)^-1 J_s^T J_p
        a = np.einsum("cnk,dnk->ncd", ds, ds)
        b = np.einsum("cnk,pnk->ncp", ds, dp)
        solved = np.linalg.solve(a + 1e-12 * np.eye(6), b)  # (n, 6, p)
        projected = dp - np.einsum("cnk,ncp->pnk", ds, solved)
        return projected.reshape(self.p, -1)[:, self.rows].T

    def timing(self, z: np.ndarray) -> tuple[np.ndarray, float]:
        """Each cycle's voltage timing as the current sensor tells it: (the change of
        each cycle's delay, (n, length), 0 where the data say nothing; the spread of
        the delays about the recorded latency plus ``delay``, s).

        The voltage answering sample k reaches the rig some time after the latency the
        bag records (the way from the controllers' publication to the rig is not
        recorded), and a current step a fraction of a millisecond early or late moves
        the filtered current at sample k + 1 by several ADC codes (and the cart's
        impulse with it). From the model's state at each sample, one period is
        simulated at the current delay and a little later: the slope s of the
        predicted current sensor voltage against the delay and the residual r at
        k + 1 give the correction -s r / (s^2 + sigma_q^2 / sigma_e^2), the mean of the
        delay given r when the delays scatter by sigma_e about their mean and the sensor
        reads with sigma_q (both by moments: r^2 = sigma_q^2 + s^2 sigma_e^2 over the
        cycles). A cycle whose current barely changes keeps its delay.
        """
        seg = self.seg
        n_seg, length = seg.count, seg.length
        values = self.values(z)
        rows = np.arange(n_seg)
        states = np.empty((n_seg, length, Plant(self.base).size))
        predicted = self._simulate({k: np.full(n_seg, v) for k, v in values.items()},
                                   self.states(), rows, states)
        single = Plant(_with_values(self.base, {BY_KEY[k].name: v for k, v in values.items()
                                                if k not in NOT_PLANT}))
        index = single.index["v_cur"]
        period = self.period
        # cycles whose voltage and the one before came on time (the late ones keep theirs)
        before = (np.zeros(n_seg) if seg.latency_before is None else seg.latency_before)
        previous = np.concatenate([before[:, None], seg.latency[:, :-2]], axis=1)
        on_time = ((seg.latency[:, :-1] + values["delay"] < 0.999 * period)
                   & (previous + values["delay"] < period))
        cycle = (np.arange(length - 1)[None, :] < (seg.size - 1)[:, None]) & on_time
        y = states[:, :-1][cycle]
        acting = np.concatenate([seg.u_before[:, None], seg.u[:, :-1]], axis=1)[:, :-1][cycle]
        new = seg.u[:, :-1][cycle]
        d0 = np.clip(seg.latency[:, :-1][cycle] + values["delay"], 0.0, 0.999 * period)
        shift = np.where(d0 + 1e-4 < 0.999 * period, 1e-4, -1e-4)

        def current_after(d: np.ndarray) -> np.ndarray:
            out = np.empty(len(d))
            for lo in range(0, len(d), 4096):
                g = slice(lo, lo + 4096)
                y1 = single.advance(y[g], acting[g], d[g])
                out[g] = single.advance(y1, new[g], period - d[g])[:, index]
            return out

        at = current_after(d0)
        slope = (current_after(d0 + shift) - at) / shift
        r = (predicted[:, 1:, 2][cycle] - seg.measured[:, 1:, 2][cycle])
        r = np.where(seg.mask[:, 1:, 2][cycle], r, 0.0)
        # moments: r^2 = sigma_q^2 + sigma_e^2 s^2
        design = np.column_stack([np.ones_like(slope), slope * slope])
        (q2, e2), *_ = np.linalg.lstsq(design, r * r, rcond=None)
        q2 = max(q2, (QUANTISATION_RMS * self.steps[2]) ** 2)
        if not e2 > 0.0:
            return np.zeros((n_seg, length)), 0.0
        change = -slope * r / (slope * slope + q2 / e2)
        change = np.clip(d0 + change, 0.0, 0.999 * period) - d0
        out = np.zeros((n_seg, length))
        out[:, :-1][cycle] = change
        return out, math.sqrt(e2)

    def row_codes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the measured code, the channel, whether it is held) of every residual row:
        ADC codes of the IR and current readings, encoder counts of the angle (each
        rounded: noisy or off-grid readings are taken at their nearest code); a row is
        held when its channel reads the same code for at least :data:`HELD_SAMPLES`
        samples in a row (a level, not a signal passing through the code). Counting
        every current reading as held (the PI loop (3.47) acts on the code it reads)
        made R's intervals cover through the driver but widened J_m's past
        :data:`IDENTIFIABLE` (docs/identification.md, "The quantisation floor")."""
        s = self.sensors
        m = self.seg.measured
        codes = np.rint(np.stack([(m[..., 0] - s.adc_ref_low_v) / s.adc_lsb_v - 0.5,
                                  (m[..., 1] - s.encoder_zero_rad) / s.encoder_rad_per_count,
                                  (m[..., 2] - s.adc_ref_low_v) / s.adc_lsb_v - 0.5],
                                 axis=-1)).astype(np.int64)
        mask = self.seg.mask
        # runs of one code along each segment's samples, per channel: (n, 3, length)
        c, v = codes.transpose(0, 2, 1), mask.transpose(0, 2, 1)
        start = np.ones(c.shape, dtype=bool)
        start[..., 1:] = (c[..., 1:] != c[..., :-1]) | (v[..., 1:] != v[..., :-1])
        run = np.cumsum(start.reshape(-1)) - 1
        held = (np.bincount(run)[run] >= HELD_SAMPLES).reshape(c.shape).transpose(0, 2, 1)
        channel = np.broadcast_to(np.arange(3), m.shape)
        return (codes.reshape(-1)[self.rows], channel.reshape(-1)[self.rows],
                held.reshape(-1)[self.rows])

    def segment_rows(self, s: int) -> slice:
        return slice(self.row_edges[s], self.row_edges[s + 1])

    def channel_rms(self, z: np.ndarray) -> np.ndarray:
        """RMS residual of each channel, in the sensor's steps (unweighted)."""
        r = self.residuals(z)
        channel = np.tile(np.arange(3), self.seg.count * self.seg.length)[self.rows]
        return np.array([math.sqrt(np.mean((r[channel == c] / self.weights[c]) ** 2))
                         for c in range(3)])

    def predictions(self, z: np.ndarray) -> np.ndarray:
        """Predicted (IR voltage, angle, current sensor voltage) of every segment."""
        self.solve_states(z)
        rows = np.arange(self.seg.count)
        values = {k: np.full(len(rows), v) for k, v in self.values(z).items()}
        return self.simulate(values, self.states(), rows)


# -- the fit ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Estimate:
    unknown: Unknown
    value: float
    low: float  # 95 % interval
    high: float
    std: float
    base: float
    identifiable: bool = True
    reason: str = ""  # why it is not identifiable, when it is not fitted at all

    @property
    def half_width(self) -> float:
        return 0.5 * (self.high - self.low)


@dataclass
class Result:
    estimates: list[Estimate]
    not_identifiable: list[Estimate]
    correlation: np.ndarray  # of every fitted parameter (``fitted``)
    warnings: list[str]
    residual_rms: np.ndarray  # per channel, in sensor steps
    segments: Segments
    recordings: list[Recording]
    predicted: np.ndarray  # (n, length, 3)
    base: PlantConfig
    iterations: int
    wall_s: float
    cycles: int
    delay_s: float  # the constant part of the sample-to-voltage time used
    timing_spread_s: float | None = None  # each cycle's delay about it (wall clock)
    fitted: list[Estimate] = field(default_factory=list)  # every parameter fitted, in order

    def value(self, key: str) -> float | None:
        return next((e.value for e in self.estimates if e.unknown.key == key), None)


#: A channel reading one code for at least this many samples in a row holds a level (50 ms:
#: the excitation's bit), whose quantisation error every such sample shares
HELD_SAMPLES = 10

#: Passes of the per-cycle timing for a run on the wall clock (each a fit of its own)
TIMING_ROUNDS = 2
#: A fit stops when its next Gauss-Newton step is under this fraction of every unknown's
#: standard error (:func:`_within_standard_error`)
STOP_FRACTION = 0.01
#: ... or when its last STALL_ITERATIONS iterations gained less than a move of
#: STALL_FRACTION of a standard error would (:func:`_stalled`)
STALL_ITERATIONS = 5
STALL_FRACTION = 0.25

#: A segment whose residual RMS exceeds this many times the median segment's is left out
OUTLIER = 4.0


def _drop_outliers(problem: Problem, segments: Segments, z: np.ndarray,
                   recordings: Sequence[Recording], say: Callable[[str], None]
                   ) -> tuple[Problem, Segments]:
    """Leave out the segments the fitted model cannot follow at all (a voltage that was
    recorded but never reached the motor: a driver holding 0 V at the start of a run,
    or after a watchdog; a knock on the cart): their residual RMS is more than
    :data:`OUTLIER` times the median segment's."""
    r = problem.solve_states(z)
    counts = np.maximum(segments.mask.reshape(segments.count, -1).sum(axis=1), 1)
    rms = np.sqrt(np.einsum("ij,ij->i", r, r) / counts)
    keep = rms <= OUTLIER * max(float(np.median(rms)), 1.0)
    if keep.all() or keep.sum() < 2:
        return problem, segments
    say(f"leaving out {int((~keep).sum())} segment(s) the model cannot follow")
    offsets = problem.offsets[keep]
    weights = problem.weights
    segments = segments.subset(
        keep, "the model cannot follow it (residual over "
        f"{OUTLIER:g} times the median segment's): was the recorded voltage applied?",
        recordings)
    new = Problem(segments, problem.base_config, problem.fit, problem.start)
    new.offsets = offsets
    new.weights = weights
    new.simulations = problem.simulations
    return new, segments


def _covariance(problem: Problem, jac: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, int]:
    """Cluster-robust covariance of the fitted parameters (scaled), over segments, and
    the degrees of freedom of its t quantile.

    ``jac`` is the projected Jacobian at the optimum (the states eliminated), so
    ``(J^T J)^-1`` is the parameters' block of the full problem's inverse, and each
    segment's score ``g_s = J_s^T r_s`` is its parameters' score (its own states' scores
    vanish at their optimum). The sandwich ``(J^T J)^-1 (sum_s h_s h_s^T) (J^T J)^-1``
    takes the scores as the jackknife over segments does (CR3): ``h_s = (I - H_ss)^-1``
    applied to the segment's residuals, ``H_ss`` its leverage, which is
    ``h_s = B (B - J_s^T J_s)^-1 g_s`` with ``B = J^T J`` (Woodbury), times
    ``(n - 1) / n``: with a few dozen segments, the plain sandwich is too narrow.
    """
    bread = jac.T @ jac
    inverse = np.linalg.pinv(bread, rcond=1e-14, hermitian=True)
    n_seg = problem.seg.count
    scores = []
    for s in range(n_seg):
        rows = problem.segment_rows(s)
        js = jac[rows]
        g = js.T @ r[rows]
        try:
            h = bread @ np.linalg.solve(bread - js.T @ js, g)
        except np.linalg.LinAlgError:
            h = g
        scores.append(h)
    scores = np.array(scores)
    meat = scores.T @ scores * ((n_seg - 1) / max(n_seg, 1))
    return inverse @ (meat + quantisation_meat(problem, jac)) @ inverse, max(n_seg - 1, 1)


def quantisation_meat(problem: Problem, jac: np.ndarray) -> np.ndarray:
    """The quantisation floor of the covariance's meat: ``sigma_q^2 sum_c s_c s_c^T``.

    A quantised sensor's error is a function of the true value: every sample a channel
    reads at one code shares (nearly) the same error ``e_c``, uniform over the step
    (``sigma_q^2 = 1/12`` of a step squared). A signal held at one level (the current at
    its limit, the pendulum hanging still) is at the same code in every segment, so its
    error is the same in all of them: the estimate moves by ``-B^-1 J^T dr`` and the
    sandwich over segments, which sees only what differs between segments, never sees
    it. Taking each (channel, code) as one such error, independent of the others,
    adds ``B^-1 (sigma_q^2 sum_c s_c s_c^T) B^-1`` to the covariance, where
    ``s_c = sum over the held rows read at code c of w J_row`` (``w`` the channel's
    weight: the rows are weighted residuals, so an error of ``e`` steps moves a row by
    ``w e``). Only held rows count (:meth:`Problem.row_codes`: the code read for at
    least :data:`HELD_SAMPLES` samples in a row): a signal passing through a code, or
    swinging about it, reads it at true values spread over the step, whose errors are
    not shared (the sandwich sees them), and counting them as one error would swamp
    what depends on them (J_m, through the swinging pendulum's encoder)."""
    codes, channel, held = problem.row_codes()
    if not held.any():
        return np.zeros((jac.shape[1], jac.shape[1]))
    weight = problem.weights[channel[held]]
    group = np.unique(np.column_stack([channel[held], codes[held]]), axis=0,
                      return_inverse=True)[1]
    group = np.asarray(group).reshape(-1)
    sums = np.zeros((int(group.max()) + 1, jac.shape[1]))
    np.add.at(sums, group, jac[held] * weight[:, None])
    return QUANTISATION_RMS ** 2 * (sums.T @ sums)


def identify(recordings: Sequence[Recording], fit: Sequence[Unknown], base: PlantConfig,
             segment_s: float = 1.0, max_evaluations: int = 100,
             progress: Callable[[str], None] | None = None,
             timing_rounds: int = TIMING_ROUNDS,
             on_evaluation: Callable[[int, int, int], None] | None = None) -> Result:
    """Fit ``fit`` to the recordings, from ``base``'s values; see the module's notes.

    ``progress`` receives a line of text per pass; ``on_evaluation(pass, passes,
    evaluations)`` is called after every evaluation of the residuals (``pass`` counts
    from 0, ``evaluations`` within the pass): a progress bar's hook.

    Raises :class:`IdentifyError` for input that cannot serve (no voltage to excite what
    is asked, no usable segment) and :class:`FitError` when the fit fails.
    """
    started = time.perf_counter()
    say = progress or (lambda text: None)
    period = base.loop.period_s
    if not recordings:
        raise IdentifyError("no recording to identify from")
    step_v = base.actuator.step_v or 1e-3
    needs = [u for u in fit if u.needs_voltage and u.key not in NOT_PLANT]
    if needs and all(np.all(np.abs(r.voltage) < 0.5 * step_v) for r in recordings):
        raise IdentifyError(
            "the recorded voltage is zero throughout: nothing excites the motor and the cart, "
            f"so {', '.join(u.key for u in needs)} cannot be identified (record an "
            "excitation experiment: experiment.kind: excitation)")
    segments = make_segments(recordings, base.sensors, period, segment_s)
    model = model_plant(base)
    start = {u.key: _value(model, u.name) for u in UNKNOWNS if u.key not in NOT_PLANT}
    start["delay"] = base.actuator.command_delay_s
    start["current_offset"] = 0.0
    for u in fit:
        if u.key == "current_offset":
            continue
        if start[u.key] <= u.low or (u.key != "delay" and start[u.key] == 0.0):
            start[u.key] = u.low + 0.2 * u.scale  # inside the bounds: the fit can move it
    fitted = list(fit)
    unfitted: list[Estimate] = []
    keys = [u.key for u in fitted]
    if "L" in keys and "delay" in keys:
        # L shapes the current only within a few L / R of each voltage step, as a delay
        # of L / R would: with each command's delay unknown to that precision (fitted),
        # no sampling at 5 ms tells the two apart (the fit would trade them freely)
        L = BY_KEY["L"]
        b = _base_value(base, L)
        unfitted.append(Estimate(
            L, b, math.nan, math.nan, math.nan, b, False,
            f"at {period * 1e3:g} ms sampling L acts only as a delay of L / R "
            f"({b / base.motor.resistance_ohm * 1e3:.2f} ms at the base values) would, and the "
            "delay of the commands is not known to that precision: fitted with it, the two "
            "cannot be told apart"))
        fitted = [u for u in fitted if u.key != "L"]
    evaluations = 0
    timing_spread: float | None = None
    problem = Problem(segments, base, fitted, start)
    low, high = problem.bounds()
    z = np.clip(problem.initial(), low, high)

    passes = 2 + (timing_rounds if any(r.wall_clock for r in recordings) else 0)
    done_passes = 0

    def solve(z: np.ndarray, what: str) -> np.ndarray:
        nonlocal evaluations, done_passes
        say(f"fitting {', '.join(u.key for u in fitted)} over {segments.count} segments "
            f"({what})")
        count = 0

        def residuals(z: np.ndarray) -> np.ndarray:
            nonlocal count
            out = problem.residuals(z)
            count += 1
            if on_evaluation is not None:
                on_evaluation(done_passes, passes, count)
            return out

        last_jacobian: list[tuple[bytes, np.ndarray]] = []

        def jacobian(z: np.ndarray) -> np.ndarray:
            j = problem.jacobian(z)
            last_jacobian[:] = [(np.asarray(z, dtype=float).tobytes(), j)]
            return j

        costs: list[float] = []
        stalled = False

        def close_enough(intermediate_result: Any) -> None:
            # (least_squares passes its OptimizeResult to a parameter of this name only)
            nonlocal stalled
            x = np.asarray(intermediate_result.x, dtype=float)
            r = intermediate_result.fun
            costs.append(float(r @ r))
            if _stalled(costs, len(r) - len(x)):
                stalled = True
                raise StopIteration
            # the iterate least_squares just accepted has its Jacobian computed
            if not last_jacobian or last_jacobian[0][0] != x.tobytes():
                return
            if _within_standard_error(last_jacobian[0][1], r, x, low, high):
                raise StopIteration

        try:
            solution = least_squares(
                residuals, z, jac=jacobian, bounds=(low, high),
                method="trf", x_scale="jac", ftol=1e-9, xtol=1e-9, gtol=1e-9,
                max_nfev=max_evaluations, callback=close_enough)
        except IdentifyError:
            raise
        except (ValueError, np.linalg.LinAlgError) as exc:
            raise FitError(f"the fit failed: {exc}") from None
        evaluations += solution.nfev
        why = {-2: (f"{STALL_ITERATIONS} iterations gained less than a move of "
                    f"{STALL_FRACTION:g} of a standard error" if stalled else
                    f"the next step under {STOP_FRACTION:g} of a standard error"),
               1: "gradient", 2: "cost", 3: "step", 4: "cost and step"}.get(solution.status)
        say(f"  {solution.nfev} evaluations, {solution.njev} Jacobians, "
            f"{problem.simulations} simulations, {time.perf_counter() - started:.1f} s"
            + (f"; converged ({why})" if why else ""))
        if solution.status == 0 or solution.status == -1:
            raise FitError(
                f"the fit did not converge within {max_evaluations} evaluations "
                f"({solution.message.rstrip('.')})" + _inseparable(problem, solution.x))
        done_passes += 1
        return solution.x

    def reweight(z: np.ndarray) -> None:
        problem.weights = 1.0 / np.maximum(problem.channel_rms(z), QUANTISATION_RMS)
        problem._solved = None

    z = solve(z, "weights: the sensors' resolution")
    problem, segments = _drop_outliers(problem, segments, z, recordings, say)
    low, high = problem.bounds()
    reweight(z)
    z = solve(z, "weights: the residuals")
    for _ in range(timing_rounds if any(r.wall_clock for r in recordings) else 0):
        change, spread = problem.timing(z)
        segments.latency += change
        timing_spread = spread
        problem._solved = None
        reweight(z)
        z = solve(z, f"each cycle's delay from the current: spread {spread * 1e3:.2f} ms")
    r = problem.residuals(z)
    jac = problem.jacobian(z)
    cov, dof = _covariance(problem, jac, r)
    t = float(stats.t.ppf(0.975, dof))
    values = problem.values(z)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0)) * problem.scale
    estimates = []
    for k, u in enumerate(fitted):
        v = values[u.key]
        half = t * std[k]
        estimates.append(Estimate(u, v, max(v - half, u.low), min(v + half, u.high),
                                  float(std[k]), _base_value(base, u),
                                  half <= max(IDENTIFIABLE * abs(v), 0.1 * u.scale)))
    scale = problem.scale
    cov_phys = cov * np.outer(scale, scale)
    d = np.sqrt(np.maximum(np.diag(cov_phys), 1e-300))
    correlation = cov_phys / np.outer(d, d)
    warnings = []
    for a in range(len(estimates)):
        for b in range(a + 1, len(estimates)):
            c = correlation[a, b]
            if abs(c) > 0.95:
                warnings.append(
                    f"{estimates[a].unknown.key} and {estimates[b].unknown.key}: correlation "
                    f"{c:+.3f}: these data cannot tell them apart (fix one of them)")
    rms = problem.channel_rms(z)
    cycles = sum(len(rec.stamps_ns) for rec in recordings)
    return Result([e for e in estimates if e.identifiable],
                  unfitted + [e for e in estimates if not e.identifiable], correlation,
                  warnings, rms,
                  segments, list(recordings), problem.predictions(z), base, evaluations,
                  time.perf_counter() - started, cycles, float(values["delay"]),
                  timing_spread_s=timing_spread, fitted=estimates)


def _within_standard_error(jac: np.ndarray, r: np.ndarray, z: np.ndarray,
                           low: np.ndarray, high: np.ndarray,
                           fraction: float | None = None) -> bool:
    """Whether the Gauss-Newton step from ``z`` (kept inside the bounds) moves every
    unknown by less than ``fraction`` (default :data:`STOP_FRACTION`) of its standard
    error: the statistical stopping rule of a least-squares fit (after Bates and Watts,
    *Technometrics* 23 (1981), the relative offset), which an ``ftol`` on the cost is
    not. Along a valley (R and J_m, docs/identification.md) each step lowers a cost of
    some 10^4 by 10^-4 or so: far below what the data can tell, and an ``ftol`` of 1e-9
    kept such fits going until they ran out of evaluations. The standard errors here are
    Gauss-Newton's, ``s^2 (J^T J)^-1`` with ``s^2`` the residuals' mean square (cheap at
    every step; the reported intervals use the sandwich)."""
    fraction = STOP_FRACTION if fraction is None else fraction
    n, p = jac.shape
    if n <= p:
        return False
    try:
        step, *_ = np.linalg.lstsq(jac, -r, rcond=None)
        # an unknown on a bound that the step would take past it stays there, and the
        # step is that of the others alone (the bound's active set)
        held = ((z <= low) & (step < 0.0)) | ((z >= high) & (step > 0.0))
        if held.any():
            step = np.zeros(p)
            if not held.all():
                step[~held], *_ = np.linalg.lstsq(jac[:, ~held], -r, rcond=None)
        inverse = np.linalg.pinv(jac.T @ jac, rcond=1e-14, hermitian=True)
    except np.linalg.LinAlgError:
        return False
    step = np.clip(z + step, low, high) - z
    s2 = float(r @ r) / (n - p)
    std = np.sqrt(np.maximum(np.diag(inverse), 0.0) * s2)
    return bool(np.all(np.abs(step) <= fraction * std))


def _stalled(costs: Sequence[float], dof: int) -> bool:
    """Whether the last :data:`STALL_ITERATIONS` iterations of a fit (``costs``: the sum
    of squared residuals after each) together lowered it by less than a move of
    :data:`STALL_FRACTION` of a standard error does: in the Gauss-Newton model a move of
    ``f`` standard errors (the Mahalanobis distance in ``s^2 (J^T J)^-1``) changes the
    cost by ``f^2 s^2``, ``s^2`` the residuals' mean square (``dof`` degrees of freedom).
    A fit whose Gauss-Newton steps promise more than they deliver, step after step, is
    at the resolution of its own residuals (each segment's initial state is solved
    anew at every evaluation, to a tolerance): through the driver, a draw whose last
    pass went on for 100 evaluations gained 0.01-0.2 of a cost of 26,071 an iteration
    while its Gauss-Newton step stayed 0.16-0.92 of the delay's standard error."""
    if len(costs) <= STALL_ITERATIONS or dof <= 0:
        return False
    s2 = costs[-1] / dof
    return costs[-1 - STALL_ITERATIONS] - costs[-1] < STALL_FRACTION ** 2 * s2


def _inseparable(problem: Problem, z: np.ndarray) -> str:
    """For a fit that did not converge: the pairs of parameters whose estimates correlate
    beyond 0.95 at its last point (Gauss-Newton's (J^T J)^-1), the usual reason (a valley
    along which the cost barely changes), as text to add to the error."""
    try:
        jac = problem.jacobian(z)
        cov = np.linalg.pinv(jac.T @ jac, rcond=1e-14, hermitian=True)
    except (IdentifyError, np.linalg.LinAlgError, ValueError):
        return ""
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    corr = cov / np.outer(d, d)
    pairs = [f"{problem.fit[a].key} and {problem.fit[b].key} (correlation {corr[a, b]:+.3f})"
             for a in range(problem.p) for b in range(a + 1, problem.p)
             if abs(corr[a, b]) > 0.95]
    if not pairs:
        return ""
    return ("; these data cannot tell apart " + ", ".join(pairs)
            + ": fit one of each pair, the other known (--fit, --config)")


def _base_value(base: PlantConfig, u: Unknown) -> float:
    return 0.0 if u.key == "current_offset" else _value(base, u.name)


# -- output ----------------------------------------------------------------------------


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

"""The recordings cut into the segments the fit simulates, each from an initial state of
its own (:func:`make_segments`).

**Segments (multiple shooting).** The recording is cut into segments (1 s by default),
each simulated from an initial state of its own that the fit estimates with the
parameters (cart position and velocity, angle and rate, the two sensor filters'
voltages; the armature current starts at its quasi-static value). Model error and
drift then cannot accumulate over a run, and an unstable upright would not dominate.
A segment is left out, and the report says so, when in it the cart was at an end
stop (the IR reading saturates there: the stops lie beyond the sensor's range), the
current sensor saturated, a sample was missing, or a voltage arrived two periods late.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from pisc_model import sensors
from pisc_model.params import SensorParams
from pisc_robust.identify_data import IdentifyError, Recording

__all__ = ["LATE_PERIODS", "Segments", "make_segments"]

#: A voltage reaching the rig later than this many periods after its sample is left out;
#: one after the next tick acts from its arrival in the next period (make_segments)
LATE_PERIODS = 1.9


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


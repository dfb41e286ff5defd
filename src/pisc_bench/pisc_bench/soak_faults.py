"""The soak's faults (``pisc_soak --driver --faults``): the seeded schedule of what the
virtual rig is asked to do (byte drops, silences of the device, garbage bursts) and each
silence's recovery, measured from the recorded samples.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["DROP_RATE", "SILENCE_S", "FaultSchedule", "Recovery", "fault_schedule",
           "recoveries"]

DROP_RATE = 1e-3  # per byte, from the start of a --faults run
SILENCE_S = 0.2  # one silence of the device each minute
SILENCE_EVERY_S = 60.0
SILENCE_FIRST_S = 12.0  # the first minute's silence falls in 12-16 s (after the catch)
SILENCE_JITTER_S = 4.0
SILENCE_MARGIN_S = 3.0  # no silence closer than this to the end: its recovery is measured
GARBAGE_EVERY_S = 10.0  # mean interval of the garbage bursts (Poisson), from 5 s on
GARBAGE_FROM_S = 5.0
GARBAGE_BYTES = (1, 64)  # bytes per burst, uniform, inclusive
RECOVERY_BAND_RAD = 0.05  # |theta| from upright, the run summary's hold criterion
RECOVERY_SETTLE_S = 1.0  # ... held for this long counts as recovered
#: The samples judged for the hold start this long after the first cycle (the run
#: summary's, :attr:`pisc_runs.verdict.Criteria.fast_hold_from_s`)
HELD_FROM_S = 6.0


@dataclass(frozen=True)
class FaultSchedule:
    """What ``--faults`` does to the rig, in seconds from the first cycle."""

    drop_rate: float
    silences_s: tuple[float, ...]  # each SILENCE_S long
    garbage: tuple[tuple[float, int], ...]  # (time, bytes)

    def requests(self) -> list[tuple[float, dict[str, Any]]]:
        """The rig's JSON requests in time order (the drop rate is set at its start)."""
        out = [(t, {"silence_s": SILENCE_S}) for t in self.silences_s]
        out += [(t, {"garbage": n}) for t, n in self.garbage]
        return sorted(out, key=lambda r: r[0])


def fault_schedule(seed: int, duration_s: float) -> FaultSchedule:
    """The seeded faults of a run of ``duration_s``: one silence in each minute, at
    12-16 s into it, none within 3 s of the end (its recovery must be seen); garbage
    bursts of 1-64 random bytes at Poisson times (mean 10 s apart) from 5 s to the end.
    """
    rng = np.random.default_rng(seed)
    silences = []
    minute = 0
    while True:
        t = SILENCE_FIRST_S + minute * SILENCE_EVERY_S + rng.uniform(0.0, SILENCE_JITTER_S)
        if t + SILENCE_S + SILENCE_MARGIN_S > duration_s:
            break
        silences.append(round(float(t), 3))
        minute += 1
    garbage = []
    t = GARBAGE_FROM_S
    while True:
        t += rng.exponential(GARBAGE_EVERY_S)
        if t >= duration_s:
            break
        garbage.append((round(float(t), 3),
                        int(rng.integers(GARBAGE_BYTES[0], GARBAGE_BYTES[1] + 1))))
    return FaultSchedule(DROP_RATE, tuple(silences), tuple(garbage))


@dataclass(frozen=True)
class Recovery:
    requested_s: float  # run time the silence was asked for
    silent_s: float | None  # the gap between frames around it (None: no gap seen)
    ended_s: float | None  # run time of the first frame after it
    recovery_s: float | None  # from ended_s until |theta| < band for RECOVERY_SETTLE_S
    peak_theta_rad: float | None  # largest |theta| from ended_s to the recovery

    @property
    def lost(self) -> bool:
        return self.recovery_s is None

    def format(self) -> str:
        if self.silent_s is None:
            return f"silence asked at {self.requested_s:.3f} s: no gap between frames seen"
        what = ("lost" if self.recovery_s is None
                else f"recovered {self.recovery_s:.3f} s after it")
        return (f"silence at {self.requested_s:.3f} s: {self.silent_s * 1e3:.0f} ms without "
                f"frames, ended {self.ended_s:.3f} s; {what} (peak |theta| "
                f"{self.peak_theta_rad:.3f} rad)")


def recoveries(t_s: np.ndarray, theta_rad: np.ndarray, requested_s: Sequence[float],
               end_s: float | None = None, band_rad: float = RECOVERY_BAND_RAD,
               settle_s: float = RECOVERY_SETTLE_S, min_gap_s: float = 0.1,
               search_s: float = 1.0) -> list[Recovery]:
    """Each silence's recovery from the samples' run times ``t_s`` and ``theta_rad``
    (from upright).

    The silence is the largest gap between samples from 50 ms before its request to
    ``search_s`` after (at least ``min_gap_s``); it ends at the first sample after the
    gap. It is recovered at the first sample from there on at which |theta| < band and
    stays so for ``settle_s`` (0 when the pendulum never left the band), found before
    the next silence's request (or ``end_s``, default the last sample); else lost.
    """
    t = np.asarray(t_s, dtype=float)
    th = np.abs(np.asarray(theta_rad, dtype=float))
    end = float(t[-1]) if end_s is None else end_s
    out = []
    for k, asked in enumerate(requested_s):
        limit = requested_s[k + 1] if k + 1 < len(requested_s) else end
        i0 = max(int(np.searchsorted(t, asked - 0.05)) - 1, 0)
        i1 = int(np.searchsorted(t, asked + search_s))
        gaps = np.diff(t[i0:i1 + 1])
        if gaps.size == 0 or gaps.max() < min_gap_s:
            out.append(Recovery(asked, None, None, None, None))
            continue
        g = i0 + int(np.argmax(gaps)) + 1  # the first sample after the gap
        silent, ended = float(gaps.max()), float(t[g])
        recovered = None
        out_of_band = g + np.nonzero(th[g:] >= band_rad)[0]
        # where the pendulum may come back: the first sample after the silence and each
        # sample in the band that follows one out of it
        back = ([g] if th[g] < band_rad else []) + [
            i + 1 for i in out_of_band if i + 1 < len(t) and th[i + 1] < band_rad]
        for j in back:
            if t[j] + settle_s > limit:
                break
            k = int(np.searchsorted(out_of_band, j, side="right"))
            if k == len(out_of_band) or t[out_of_band[k]] > t[j] + settle_s:
                recovered = j
                break
        if recovered is None:
            peak = float(th[g:int(np.searchsorted(t, limit, side="right"))].max(initial=0.0))
            out.append(Recovery(asked, silent, ended, None, peak))
        else:
            out.append(Recovery(asked, silent, ended, float(t[recovered]) - ended,
                                float(th[g:recovered + 1].max())))
    return out


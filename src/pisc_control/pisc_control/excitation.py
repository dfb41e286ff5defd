"""Identification experiments: what the supervisor asks of the cart instead of a swing-up.

Section ``experiment`` (the supervisor reads it). With ``experiment.kind`` other than
``none`` the supervisor neither swings up nor catches; every sample it asks for the
force of :func:`experiment_force`, and its fault rules (a state that is not finite,
the cart outside ``safety.x_min_m .. safety.x_max_m``) stay active: a fault still
latches, commands no force, and the current loop then commands 0 V.

* ``excitation``: an open-loop sequence with the pendulum hanging, chosen by
  ``experiment.signal``: ``prbs`` (a maximum-length pseudo-random binary sequence of
  order 9, +-amplitude, one bit every ``bit_s``; with ``level_spread`` each bit's
  magnitude varies, seeded, between ``(1 - level_spread)`` and 1 times the amplitude, so
  that the current loop holds its set-point at many levels, not two), ``chirp`` (a sine
  sweeping from ``chirp_start_hz`` to ``chirp_end_hz`` over ``chirp_sweep_s``, repeated)
  or ``steps`` (levels of +-amplitude and +-amplitude/2 in a seeded order, each held
  ``bit_s``). It starts ``start_s`` after the first sample. A slow position loop (an acceleration
  ``-position_k_x (x - center_m) - position_k_v x_dot``) keeps the cart near the centre,
  and a guard recentres it: where the cart, braked at the excitation's own
  acceleration, would stop within ``margin_m`` of the safe range, the excitation
  brakes it instead.
* ``free_swing``: no excitation; the same position loop holds the cart where the run
  began (both gains 0: no current, a free cart) while the pendulum, released from an
  angle, swings freely: for l, I and the pivot's friction.

The sequence is a pure function of the sample's time, so a run and its replay ask for
the same forces. The recorded voltages are what an identification
(:mod:`pisc_robust.identify`) drives its model with: the current loop in between,
the voltages are whatever it took to follow the requested force.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, finite, in_range, nonnegative, one_of, param, positive
from pisc_model.params import RigParams

__all__ = ["KINDS", "SIGNALS", "ExperimentParams", "excitation_signal", "experiment_force",
           "prbs_bits"]

KINDS = ("none", "excitation", "free_swing")
SIGNALS = ("prbs", "chirp", "steps")

PRBS_ORDER = 9  # x^9 + x^5 + 1: a maximum-length sequence of 511 bits
PRBS_TAPS = (9, 5)


@dataclass(frozen=True)
class ExperimentParams:
    """An identification experiment instead of the swing-up (docs/identification.md)."""

    kind: str = param("none", "'none' (swing up and catch), 'excitation' (an open-loop "
                      "sequence on the cart, pendulum hanging) or 'free_swing' (the cart held, "
                      "the pendulum swinging freely)", "", one_of(*KINDS))
    signal: str = param("prbs", "excitation: 'prbs', 'chirp' or 'steps'", "", one_of(*SIGNALS))
    amplitude_n: float = param(1.5, "excitation: force amplitude asked of the current loop",
                               "N", positive)
    bit_s: float = param(0.05, "prbs: length of one bit; steps: how long each level is held",
                         "s", in_range(1e-3, 60.0))
    chirp_start_hz: float = param(0.2, "chirp: frequency at the start of each sweep", "Hz",
                                  positive)
    chirp_end_hz: float = param(8.0, "chirp: frequency at the end of each sweep", "Hz",
                                positive)
    chirp_sweep_s: float = param(10.0, "chirp: length of one sweep (then it starts again)",
                                 "s", positive)
    level_spread: float = param(0.0, "prbs: each bit's magnitude is the amplitude times 1 "
                                "minus this fraction of a seeded uniform draw, so the held "
                                "current levels spread over the current sensor's codes",
                                "", in_range(0.0, 0.9))
    seed: int = param(1, "prbs and steps: seed of the sequence", "", in_range(0, 2**31 - 1))
    start_s: float = param(0.5, "the excitation starts this long after the first sample",
                           "s", nonnegative)
    center_m: float = param(-0.05, "excitation: where the position loop pulls the cart (the "
                            "middle of the safe range)", "m", finite)
    position_k_x: float = param(4.0, "position loop: acceleration per metre from the centre "
                                "(free_swing: from where the run began)", "1/s^2", nonnegative)
    position_k_v: float = param(2.0, "position loop: acceleration per m/s of the cart", "1/s",
                                nonnegative)
    margin_m: float = param(0.05, "excitation: the guard brakes the cart when it would stop "
                            "closer than this to the safe range's limits", "m", nonnegative)

    def __post_init__(self) -> None:
        if self.signal == "chirp" and not self.chirp_end_hz > self.chirp_start_hz:
            raise ConfigError(
                f"experiment.chirp_end_hz = {self.chirp_end_hz} must exceed "
                f"experiment.chirp_start_hz = {self.chirp_start_hz}")


@lru_cache(maxsize=16)
def prbs_bits(seed: int) -> np.ndarray:
    """The 511 bits (0 or 1) of the order-9 maximum-length sequence whose shift register
    starts at ``seed mod 511 + 1`` (never the all-zero register)."""
    register = seed % ((1 << PRBS_ORDER) - 1) + 1
    bits = np.empty((1 << PRBS_ORDER) - 1, dtype=np.int8)
    for k in range(len(bits)):
        bit = ((register >> (PRBS_TAPS[0] - 1)) ^ (register >> (PRBS_TAPS[1] - 1))) & 1
        register = ((register << 1) | bit) & ((1 << PRBS_ORDER) - 1)
        bits[k] = bit
    bits.setflags(write=False)
    return bits


def _hash(seed: int, n: np.ndarray) -> np.ndarray:
    """SplitMix64's output for (seed, n): 64 well-mixed bits per index, as uint64."""
    with np.errstate(over="ignore"):
        z = np.asarray(n, dtype=np.uint64) + np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))


def _step_levels(seed: int, n: np.ndarray) -> np.ndarray:
    """Level of step ``n``: +-1 or +-1/2, from a hash of (seed, n) (SplitMix64)."""
    choice = (_hash(seed, n) & np.uint64(3)).astype(np.int64)
    return np.array([1.0, -1.0, 0.5, -0.5])[choice]


def _bit_scale(seed: int, spread: float, n: np.ndarray) -> np.ndarray:
    """The magnitude of bit ``n`` (counted from the start, not within the sequence's
    period) as a fraction of the amplitude: ``1 - spread u`` with ``u`` uniform in
    [0, 1) from the top 53 bits of a hash of (seed, n); 1 with no spread."""
    if spread == 0.0:
        return np.ones(np.shape(n))
    # (the seed altered by a constant: these draws are not those of _step_levels)
    u = (_hash(seed ^ 0x5bd1e995, n) >> np.uint64(11)).astype(np.float64) * 2.0 ** -53
    return 1.0 - spread * u


def excitation_signal(params: ExperimentParams, t: ArrayLike) -> np.ndarray:
    """The excitation's force [N] at run time ``t`` [s] (0 before ``start_s``, and for a
    ``free_swing`` or no experiment)."""
    t = np.asarray(t, dtype=float)
    if params.kind != "excitation":
        return np.zeros_like(t)
    tau = t - params.start_s
    running = tau >= 0.0
    tau = np.where(running, tau, 0.0)
    a = params.amplitude_n
    if params.signal == "prbs":
        bits = prbs_bits(params.seed)
        n = np.floor(tau / params.bit_s + 1e-9).astype(np.int64)
        value = a * _bit_scale(params.seed, params.level_spread, n) * (
            2.0 * bits[n % len(bits)] - 1.0)
    elif params.signal == "steps":
        n = np.floor(tau / params.bit_s + 1e-9).astype(np.int64)
        value = a * _step_levels(params.seed, n)
    else:
        sweep = params.chirp_sweep_s
        s = np.mod(tau, sweep)
        f0, f1 = params.chirp_start_hz, params.chirp_end_hz
        value = a * np.sin(2.0 * np.pi * (f0 * s + 0.5 * (f1 - f0) * s * s / sweep))
    return np.where(running, value, 0.0)


def experiment_force(
    params: ExperimentParams,
    rig: RigParams,
    limits_m: tuple[float, float],
    t: ArrayLike,
    x: ArrayLike,
    x_dot: ArrayLike,
    origin_m: ArrayLike,
) -> np.ndarray:
    """The cart force [N] an experiment asks for at run time ``t``.

    ``excitation``: :func:`excitation_signal` plus the position loop's
    ``-(M + m) (k_x (x - center) + k_v x_dot)``; where the cart, braked at half the
    excitation's acceleration ``amplitude / (M + m)``, would stop beyond ``limits_m``
    narrowed by ``margin_m``, the excitation brakes it (``-amplitude sign(x_dot)``)
    instead. ``free_swing``: the position loop about ``origin_m`` (where the run began).
    """
    x = np.asarray(x, dtype=float)
    x_dot = np.asarray(x_dot, dtype=float)
    mass = rig.a2
    if params.kind == "free_swing":
        return -mass * (params.position_k_x * (x - np.asarray(origin_m, dtype=float))
                        + params.position_k_v * x_dot)
    hold = -mass * (params.position_k_x * (x - params.center_m) + params.position_k_v * x_dot)
    excite = excitation_signal(params, t)
    # judged at half the excitation's acceleration: the position loop and the pendulum's
    # reaction take some of it, and a late command (a loaded control computer) more
    brake = 0.5 * params.amplitude_n / mass
    stop = x + x_dot * np.abs(x_dot) / (2.0 * brake)
    low, high = limits_m[0] + params.margin_m, limits_m[1] - params.margin_m
    excite = np.where((stop > high) & (x_dot > 0.0), -params.amplitude_n,
                      np.where((stop < low) & (x_dot < 0.0), params.amplitude_n, excite))
    # a cart already outside the narrowed range and at rest is pushed back in
    excite = np.where((x > high) & (x_dot <= 0.0) & (excite > 0.0), -excite,
                      np.where((x < low) & (x_dot >= 0.0) & (excite < 0.0), -excite, excite))
    return hold + excite

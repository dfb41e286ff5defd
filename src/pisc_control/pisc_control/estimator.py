"""Velocity estimation by backward differences of the measured positions.

The thesis computes ``v(k) = (p(k) - p(k-1)) / Ts`` for the cart (4.9) and the
pendulum (4.7). Differentiation amplifies quantisation: one IR code (about 0.4 mm near
x = 0) becomes 0.09 m/s and one encoder count (1.57 mrad) 0.31 rad/s, which the catch
gain turns into a chattering current. Two options trade that noise for lag: a
difference over N periods, ``(p(k) - p(k-N)) / (N Ts)``, which divides the quantisation
step's effect by N for a lag of (N - 1) Ts / 2, and a first-order low-pass on the
differences. With N = 1 and no low-pass (the defaults) the estimator is exactly the
thesis's.

The law is :func:`estimator_step`, on floats (or on arrays: it has no branch on the
values): the estimator node runs it through :class:`OneRigEstimator`, the compiled
batch (:mod:`pisc_sim.batch_controllers`) and the environments compile it, and
:func:`estimator_update` applies it to arrays of rigs with an immutable state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import in_range, nonnegative, param

__all__ = ["EstimatorParams", "EstimatorState", "OneRigEstimator", "estimator_constants",
           "estimator_step", "estimator_update"]


@dataclass(frozen=True)
class EstimatorParams:
    velocity_filter_hz: float = param(
        0.0,
        "corner of a first-order low-pass on the differences; 0 = plain backward "
        "difference (4.7), (4.9)",
        "Hz",
        nonnegative,
    )
    difference_periods: int = param(
        1, "N: velocity as the difference over N periods, (p(k) - p(k-N)) / (N Ts); 1 = the "
        "thesis's backward difference (4.7), (4.9)", "", in_range(1, 100))


def estimator_constants(params: EstimatorParams, period_s: float) -> tuple[float, float]:
    """(a, 1 - a) of the low-pass, a = exp(-2 pi fc Ts); (0, 0) without one."""
    if params.velocity_filter_hz > 0.0:
        a = math.exp(-2.0 * math.pi * params.velocity_filter_hz * period_s)
        return a, 1.0 - a
    return 0.0, 0.0


def estimator_step(a: float, b: float, span: float, x: float, theta: float,
                   oldest_x: float, oldest_theta: float, v_x: float, v_theta: float
                   ) -> tuple[float, float]:
    """(x_dot, theta_dot) from this sample and the window's oldest, ``span`` seconds
    before; low-passed with the previous estimates (v_x, v_theta) when a > 0 (a, b from
    :func:`estimator_constants`). The first sample, which has no window, gives 0, 0
    without calling this.

    Notes
    -----
    Implements (4.7) and (4.9), over N = ``difference_periods`` periods:
    ``d(k) = (p(k) - p(k-N)) / (N Ts)`` (over the k periods there are during the first N
    samples); with ``velocity_filter_hz = fc > 0`` the difference ``d`` is filtered as
    ``v(k) = a v(k-1) + (1 - a) d(k)``, ``a = exp(-2 pi fc Ts)``.
    """
    x_dot = (x - oldest_x) / span
    theta_dot = (theta - oldest_theta) / span
    if a > 0.0:
        x_dot = a * v_x + b * x_dot
        theta_dot = a * v_theta + b * theta_dot
    return x_dot, theta_dot


@dataclass(frozen=True)
class EstimatorState:
    """Previous sample and previous velocity estimate; ``None`` before the first sample."""

    x_m: np.ndarray | None = None
    theta_rad: np.ndarray | None = None
    x_dot_mps: np.ndarray | None = None
    theta_dot_radps: np.ndarray | None = None
    # the samples before the previous one, oldest first (N - 1 of them at most)
    x_past: tuple[np.ndarray, ...] = ()
    theta_past: tuple[np.ndarray, ...] = ()


def estimator_update(
    params: EstimatorParams,
    period_s: float,
    state: EstimatorState,
    x_m: ArrayLike,
    theta_rad: ArrayLike,
) -> tuple[EstimatorState, np.ndarray, np.ndarray]:
    """:func:`estimator_step` over arrays of rigs (any shape), with its window.

    Returns the new state and ``(x_dot, theta_dot)``. The first sample has no
    predecessor and gives zero velocity (the thesis program differenced against its
    initial zeros, a spike of x / Ts on the first sample).
    """
    x = np.asarray(x_m, dtype=float)
    theta = np.asarray(theta_rad, dtype=float)
    if state.x_m is None or state.theta_rad is None:
        x_dot = np.zeros_like(x)
        theta_dot = np.zeros_like(theta)
        return EstimatorState(x, theta, x_dot, theta_dot), x_dot, theta_dot
    x_window = (*state.x_past, state.x_m)  # the previous samples, oldest first
    theta_window = (*state.theta_past, state.theta_rad)
    n = len(x_window)  # N, or fewer during the first N samples
    span = period_s if n == 1 else n * period_s
    a, b = estimator_constants(params, period_s)
    x_dot, theta_dot = estimator_step(a, b, span, x, theta, x_window[0], theta_window[0],
                                      state.x_dot_mps, state.theta_dot_radps)
    x_dot, theta_dot = np.asarray(x_dot, dtype=float), np.asarray(theta_dot, dtype=float)
    keep = params.difference_periods - 1  # samples kept besides the newest
    x_past = (*x_window, x)[-1 - keep:-1] if keep else ()
    theta_past = (*theta_window, theta)[-1 - keep:-1] if keep else ()
    return (EstimatorState(x, theta, x_dot, theta_dot, x_past, theta_past), x_dot,
            theta_dot)


class OneRigEstimator:
    """The estimator of one rig, as its node runs it: the window of previous samples,
    the previous estimates, and :func:`estimator_step`."""

    def __init__(self, params: EstimatorParams, period_s: float) -> None:
        self._window: list[tuple[float, float]] = []  # previous samples, oldest first
        self._previous = (0.0, 0.0)
        self.configure(params, period_s)

    def configure(self, params: EstimatorParams, period_s: float) -> None:
        """New parameters; the window shrinks or grows to the new N over the next samples,
        as :func:`estimator_update`'s does."""
        self._a, self._b = estimator_constants(params, period_s)
        self._period = period_s
        self._n = params.difference_periods

    def step(self, x: float, theta: float) -> tuple[float, float]:
        """(x_dot, theta_dot) at this sample; (0, 0) at the first."""
        window = self._window
        if window:
            n = len(window)
            span = self._period if n == 1 else n * self._period
            oldest_x, oldest_theta = window[0]
            x_dot, theta_dot = estimator_step(self._a, self._b, span, x, theta, oldest_x,
                                              oldest_theta, *self._previous)
        else:
            x_dot = theta_dot = 0.0
        window.append((x, theta))
        del window[:-self._n]
        self._previous = (x_dot, theta_dot)
        return x_dot, theta_dot

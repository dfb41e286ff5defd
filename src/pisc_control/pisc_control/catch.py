"""Linear state feedback that catches and balances the pendulum upright, thesis 3.3."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, finite, nonnegative, one_of, param, positive
from pisc_model.dynamics import linearise_upright, wrap_to_upright
from pisc_model.params import RigParams

__all__ = ["CatchParams", "GOVERNOR_STRIDE", "SAME_DESIGN_RTOL", "catch_force", "catch_gain",
           "governor_rows", "recorded_or_designed"]

#: the governor checks its prediction every this many periods (and at the first)
GOVERNOR_STRIDE = 3


@dataclass(frozen=True)
class CatchParams:
    """How the catch gain K is designed from the linearisation (3.41)-(3.42).

    K is always computed from the model, never typed in: by pole placement (the
    thesis's method, Table 6.3) or by LQR.
    """

    design: str = param("poles", "gain design: 'poles' (placement) or 'lqr'", "",
                        one_of("poles", "lqr"))
    poles: tuple[float, ...] = param(
        [-15.0, -11.0, -2.0, -1.5],
        "real parts of the closed-loop poles for design 'poles' (thesis: -15, -11, -2, -1.5)",
        "1/s",
    )
    poles_imag: tuple[float, ...] = param(
        [0.0, 0.0, 0.0, 0.0], "imaginary parts of the poles, in conjugate pairs", "rad/s")
    lqr_q: tuple[float, ...] = param(
        [1.0, 1.0, 1.0, 1.0], "diagonal of Q on [x, x_dot, theta, theta_dot] for design 'lqr'",
        "", nonnegative)
    lqr_r: float = param(1.0, "R, weight of f^2 for design 'lqr'", "1/N^2", positive)
    target_m: float = param(0.0, "x*, where the catch balances the cart", "m", finite)
    settle_rate_mps: float = param(
        0.0, "the catch's cart reference starts where the cart is when the catch begins and "
        "moves to x* at this speed (0 = x* at once, the thesis's law)", "m/s", nonnegative)
    governor: bool = param(
        False, "a reference governor keeps the catch inside the track and the current limit: "
        "the catch starts only where the linear closed loop's prediction from the state "
        "stays inside both with its cart reference somewhere, and the reference is kept "
        "where it does (false: the thesis's catch, which starts wherever (4.1) says)", "")
    governor_horizon_s: float = param(1.5, "governor: how far ahead it predicts", "s",
                                      positive)
    governor_margin_m: float = param(
        0.02, "governor: the predicted cart stays this far inside the safe range "
        "(safety.x_min_m, safety.x_max_m)", "m", nonnegative)
    governor_current_a: float = param(
        0.8, "governor: the predicted current set-point stays within +- this", "A", positive)
    guard: bool = param(
        False, "the swing-up's track guard (swing_up.guard_accel_mps2, guard_margin_m) also "
        "watches the catch: where the cart, braked at the guard's rate, would stop beyond the "
        "guard's limits, the catch lets go (or does not start) and the guard brakes", "")
    recorded_gain: tuple[float, ...] = param(
        [], "K as a recorded run computed it (pisc_graph writes it into the bag's parameter "
        "file); used instead of the designed K only when the design gives the same K within "
        "1e-9 relative, so that a replay on another machine, whose LAPACK rounds the last "
        "bits differently, reproduces the run bit for bit, and a changed design still changes "
        "K; empty: the designed K", "N/m, N s/m, N/rad, N s/rad")

    @property
    def pole_set(self) -> np.ndarray:
        """The poles as complex numbers."""
        return np.array(self.poles) + 1j * np.array(self.poles_imag)

    def __post_init__(self) -> None:
        if self.design == "poles":
            if len(self.poles) != 4 or len(self.poles_imag) != 4:
                raise ConfigError(
                    f"catch.poles, catch.poles_imag: expected 4 values each, got "
                    f"{len(self.poles)} and {len(self.poles_imag)}")
            if not all(p < 0.0 for p in self.poles):
                raise ConfigError(
                    f"catch.poles = {list(self.poles)}: every pole must have a negative real "
                    "part (a stable closed loop)")
            pairs = sorted(zip(self.poles, self.poles_imag, strict=True))
            if pairs != sorted(zip(self.poles, (-i for i in self.poles_imag), strict=True)):
                raise ConfigError(
                    f"catch.poles_imag = {list(self.poles_imag)}: complex poles must come in "
                    "conjugate pairs (same real part, opposite imaginary parts)")
        if len(self.lqr_q) != 4:
            raise ConfigError(f"catch.lqr_q: expected 4 weights, got {len(self.lqr_q)}")
        if self.recorded_gain and (len(self.recorded_gain) != 4
                                   or not all(math.isfinite(k) for k in self.recorded_gain)):
            raise ConfigError(f"catch.recorded_gain = {list(self.recorded_gain)}: expected "
                              "4 finite gains, or none")


def catch_gain(rig: RigParams, params: CatchParams) -> np.ndarray:
    """K (shape (4,)) such that ``f = -K z`` places the poles or minimises the LQR cost.

    Raises :class:`ConfigError` if the linearisation is not controllable.

    Notes
    -----
    Controllability by the rank of [B AB A^2B A^3B] (its determinant is (3.45));
    pole placement by python-control's ``place`` (Ackermann's ``acker`` when a pole is
    repeated, which ``place`` cannot do with one input); LQR by ``control.lqr``.
    """
    # imported here: python-control (with scipy.signal and matplotlib) takes 1.3 s to
    # import, which only the node that designs K should pay, not every node that imports
    # the supervisor's module for its constants (the estimator, the current loop)
    import control

    a, b = linearise_upright(rig)
    ctrb = control.ctrb(a, b)
    rank = np.linalg.matrix_rank(ctrb)
    if rank < 4:
        raise ConfigError(
            f"rig: the linearisation about upright is not controllable (rank of the "
            f"controllability matrix (3.45) is {rank} < 4); check rig.gravity_mps2 and the "
            "masses"
        )
    if params.design == "poles":
        poles = params.pole_set
        if len(np.unique(poles)) < len(poles):
            k = control.acker(a, b, poles)
        else:
            k = control.place(a, b, poles)
    else:
        k, _, _ = control.lqr(a, b, np.diag(params.lqr_q), np.array([[params.lqr_r]]))
    k = np.asarray(k, dtype=float).reshape(4)
    if not np.all(np.isfinite(k)):
        raise ConfigError(f"catch: the gain design produced non-finite gains {k}")
    return recorded_or_designed(k, params.recorded_gain)


#: how far a recorded K may be from the designed one and still be "the same design": the
#: LAPACK kernels of two machines differ by a few ulps (5e-15 relative on the default's LQR
#: between OpenBLAS's SkylakeX and Zen kernels), a changed design by far more
SAME_DESIGN_RTOL = 1e-9


def recorded_or_designed(designed: np.ndarray, recorded: tuple[float, ...]) -> np.ndarray:
    """The recorded K when it is the designed K up to rounding, else the designed K."""
    if recorded and np.allclose(designed, recorded, rtol=SAME_DESIGN_RTOL, atol=0.0):
        return np.array(recorded, dtype=float)
    return designed


def catch_force(
    gain: np.ndarray,
    x: ArrayLike,
    x_dot: ArrayLike,
    theta: ArrayLike,
    theta_dot: ArrayLike,
    target_m: ArrayLike = 0.0,
) -> np.ndarray:
    """``f = -K z``, z relative to the upright equilibrium at ``target_m``.

    Notes
    -----
    Implements (3.46) with theta wrapped to the nearest upright (2 pi n), as the C++
    program does with ``thetad``.
    """
    k1, k2, k3, k4 = gain
    return -(
        k1 * (np.asarray(x, dtype=float) - target_m)
        + k2 * np.asarray(x_dot, dtype=float)
        + k3 * wrap_to_upright(theta)
        + k4 * np.asarray(theta_dot, dtype=float)
    )


def governor_rows(rig: RigParams, gain: np.ndarray, period_s: float, horizon_s: float,
                  force_per_amp: float) -> np.ndarray:
    """The catch's linear closed-loop prediction, one row per checked sample.

    Row j is ``(P_j, Q_j)`` (8 values): with ``w = [x - r, x_dot, theta, theta_dot]`` now
    (theta from upright, r the catch's cart reference held constant), the cart after
    ``k_j`` periods is ``r + P_j . w`` and the current set-point ``Q_j . w``, for
    ``k_j = 0, GOVERNOR_STRIDE, 2 GOVERNOR_STRIDE, ...`` up to ``horizon_s``.

    Notes
    -----
    The linearisation (3.41)-(3.42) held over each period (zero-order hold, the
    discrete model ``Phi = e^{A Ts}``, ``Gamma = int_0^Ts e^{A s} ds B``), under the catch
    ``f = -K w`` (3.46), and the set-point (4.2) ``i_d = f / (k_m / r)`` before its
    saturation: ``w_{k+1} = (Phi - Gamma K) w_k``, ``P_j = e_1^T (Phi - Gamma K)^{k_j}``,
    ``Q_j = -K (Phi - Gamma K)^{k_j} / (k_m / r)``.
    """
    from scipy.linalg import expm

    a, b = linearise_upright(rig)
    block = np.zeros((5, 5))
    block[:4, :4] = a * period_s
    block[:4, 4:] = b * period_s
    e = expm(block)
    phi, gamma = e[:4, :4], e[:4, 4:]
    k = np.asarray(gain, dtype=float).reshape(1, 4)
    closed = phi - gamma @ k
    steps = int(round(horizon_s / period_s))
    rows = []
    power = np.eye(4)
    for step in range(steps + 1):
        if step % GOVERNOR_STRIDE == 0:
            rows.append(np.concatenate([power[0], -(k @ power)[0] / force_per_amp]))
        power = closed @ power
    return np.ascontiguousarray(rows, dtype=float)

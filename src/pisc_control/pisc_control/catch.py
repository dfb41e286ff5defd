"""Linear state feedback that catches and balances the pendulum upright, thesis 3.3.

The gain K is designed from the model (:func:`catch_gain`). The laws of a sample are
written on floats, one rig at a time, with the constants of :func:`catch_constants`:
the catch (3.46) (:func:`catch_force`, with the hold's gain blended in,
:func:`held_catch_force`, :func:`hold_blend`), its cart reference
(:func:`catch_reference`), the reference governor (:func:`governor_interval` over the
prediction of :func:`governor_rows`) and the catch's track guard
(:func:`guard_lets_go`); the supervisor (:func:`pisc_control.supervisor.
supervisor_step`) calls them in the node and in the compiled batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_control.floatmath import clip
from pisc_msgs_py.config import ConfigError, finite, nonnegative, one_of, param, positive
from pisc_model.dynamics import linearise_upright
from pisc_model.params import RigParams

__all__ = ["CatchParams", "GOVERNOR_STRIDE", "SAME_DESIGN_RTOL", "catch_constants",
           "catch_force", "catch_gain", "catch_reference", "governor_interval", "governor_rows",
           "guard_lets_go", "held_catch_force", "hold_blend", "narrow_interval",
           "recorded_or_designed"]

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
    hold_poles: tuple[float, ...] = param(
        [], "real poles of the gain that balances once the catch has held for hold_after_s "
        "(design 'poles'; softer poles chatter less on the sensors' steps); empty: the "
        "catch's gain throughout", "1/s")
    hold_after_s: float = param(1.0, "hold_poles: the catch's gain gives way to the hold's "
                                "after this long in the catch", "s", nonnegative)
    hold_blend_s: float = param(0.5, "hold_poles: over this long, linearly", "s", positive)
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
        False, "a track guard watches the catch: where the cart, moving on for "
        "catch.guard_lead_s and then braked at catch.guard_accel_mps2, would stop beyond the "
        "safe range less catch.guard_margin_m, "
        "the catch lets go (or does not start) and the swing-up's guard brakes", "")
    guard_accel_mps2: float = param(2.5, "guard: the braking acceleration it counts on",
                                    "m/s^2", positive)
    guard_margin_m: float = param(0.02, "guard: how far inside the safe range the cart must "
                                  "stop", "m", nonnegative)
    guard_lead_s: float = param(
        0.04, "guard: the cart is taken to move on at its estimated velocity for this long "
        "before it brakes (what the IR's low-pass and the estimator's differences lag)", "s",
        nonnegative)
    recorded_hold_gain: tuple[float, ...] = param(
        [], "the hold's gain (hold_poles) as a recorded run computed it, used as "
        "recorded_gain is", "N/m, N s/m, N/rad, N s/rad")
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
        if self.hold_poles and (len(self.hold_poles) != 4
                                or not all(p < 0.0 for p in self.hold_poles)):
            raise ConfigError(f"catch.hold_poles = {list(self.hold_poles)}: expected 4 real "
                              "poles with negative real parts, or none")
        if self.hold_poles and self.design != "poles":
            raise ConfigError("catch.hold_poles: the hold's gain is placed like the catch's "
                              "(catch.design: poles)")
        if len(self.lqr_q) != 4:
            raise ConfigError(f"catch.lqr_q: expected 4 weights, got {len(self.lqr_q)}")
        for name in ("recorded_gain", "recorded_hold_gain"):
            gain = getattr(self, name)
            if gain and (len(gain) != 4 or not all(math.isfinite(k) for k in gain)):
                raise ConfigError(f"catch.{name} = {list(gain)}: expected 4 finite gains, "
                                  "or none")


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


def governor_rows(rig: RigParams, gain: np.ndarray, period_s: float, horizon_s: float,
                  force_per_amp: float, difference_periods: int = 1,
                  velocity_filter_hz: float = 0.0, ir_filter_hz: float = 0.0) -> np.ndarray:
    """The catch's linear closed-loop prediction, one row per checked sample.

    Row j is ``(P_j, Q_j)`` (8 values): with ``w = [x - r, x_dot, theta, theta_dot]`` now
    (as the supervisor sees them: positions as measured, velocities as estimated; theta
    from upright; r the catch's cart reference held constant), the cart after ``k_j``
    periods is ``r + P_j . w`` and the current set-point ``Q_j . w``, for
    ``k_j = 0, GOVERNOR_STRIDE, 2 GOVERNOR_STRIDE, ...`` up to ``horizon_s``.

    Notes
    -----
    The plant is the linearisation (3.41)-(3.42) held over each period (zero-order hold,
    ``Phi = e^{A Ts}``, ``Gamma = int_0^Ts e^{A s} ds B``) under the catch (3.46) and the
    set-point (4.2) before its saturation, ``i_d = f / (k_m / r)``. The catch acts on
    what the supervisor is given, so the prediction carries what lies between: the IR
    reading of the cart through its RC low-pass (corner ``ir_filter_hz``, 0 = none,
    sampled as ``x_ir(k+1) = c x_ir(k) + (1 - c) x(k)``, ``c = e^{-2 pi f Ts}``) and the
    estimator's velocities, differences over N = ``difference_periods`` periods (4.7),
    (4.9) low-passed at ``velocity_filter_hz`` (:func:`pisc_control.estimator.
    estimator_update`). Its state is the plant's four, the IR reading, the N previous
    readings of the cart and of the angle and the two velocity estimates; it starts as
    if the rig had been moving at the estimated velocities: the reading where the cart
    is, the previous readings ``p - i Ts v``, the estimates ``v``. Without filters and
    with N = 1 the IR reading and the difference's lag are those of the model alone.
    Every product is summed in a fixed order (:func:`_matmul`, :func:`_expm`): the rows
    are the same bits on every CPU, as a replay on another machine needs.
    """
    a, b = linearise_upright(rig)
    block = np.zeros((5, 5))
    block[:4, :4] = a * period_s
    block[:4, 4:] = b * period_s
    e = _expm(block)
    phi, gamma = e[:4, :4], e[:4, 4]
    k = np.asarray(gain, dtype=float).reshape(4)
    n = difference_periods
    c_ir = math.exp(-2.0 * math.pi * ir_filter_hz * period_s) if ir_filter_hz > 0 else 0.0
    c_v = (math.exp(-2.0 * math.pi * velocity_filter_hz * period_s)
           if velocity_filter_hz > 0 else 0.0)
    # state: x, x_dot, th, th_dot | x_ir | x history (1..n) | th history (1..n) | vx, vth
    size = 4 + 1 + 2 * n + 2
    X_IR, HX, HTH, VX, VTH = 4, 5, 5 + n, 5 + 2 * n, 6 + 2 * n

    def step(s: np.ndarray) -> tuple[np.ndarray, float]:
        """One period from state ``s``: (next state, set-point)."""
        reading, angle = (s[X_IR] if c_ir > 0 else s[0]), s[2]
        vx = c_v * s[VX] + (1.0 - c_v) * (reading - s[HX + n - 1]) / (n * period_s)
        vth = c_v * s[VTH] + (1.0 - c_v) * (angle - s[HTH + n - 1]) / (n * period_s)
        force = -(k[0] * reading + k[1] * vx + k[2] * angle + k[3] * vth)
        out = np.zeros(size)
        out[:4] = _matmul(phi, s[:4, None])[:, 0] + gamma * force
        out[X_IR] = c_ir * s[X_IR] + (1.0 - c_ir) * s[0]
        out[HX] = reading
        out[HX + 1:HX + n] = s[HX:HX + n - 1]
        out[HTH] = angle
        out[HTH + 1:HTH + n] = s[HTH:HTH + n - 1]
        out[VX], out[VTH] = vx, vth
        return out, force / force_per_amp

    # the step is linear: its matrix and its set-point's row, column by column
    closed = np.zeros((size, size))
    setpoint = np.zeros(size)
    for column in range(size):
        unit = np.zeros(size)
        unit[column] = 1.0
        closed[:, column], setpoint[column] = step(unit)
    # the start from what the supervisor sees, w = [x - r, x_dot, th, th_dot]
    embed = np.zeros((size, 4))
    embed[:4, :4] = np.eye(4)
    embed[X_IR, 0] = 1.0
    for i in range(n):
        embed[HX + i, 0], embed[HX + i, 1] = 1.0, -(i + 1) * period_s
        embed[HTH + i, 2], embed[HTH + i, 3] = 1.0, -(i + 1) * period_s
    embed[VX, 1] = embed[VTH, 3] = 1.0
    steps = int(round(horizon_s / period_s))
    rows = []
    power = embed
    for index in range(steps + 1):
        if index % GOVERNOR_STRIDE == 0:
            rows.append(np.concatenate([power[0], _matmul(setpoint[None, :], power)[0]]))
        power = _matmul(closed, power)
    return np.ascontiguousarray(rows, dtype=float)


def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b by elementwise products summed in a fixed order: the same bits on every CPU
    (a BLAS's kernels round differently from one CPU to another, and a replay on another
    machine must give the recorded run's governor back exactly)."""
    return np.add.reduce(a[:, :, None] * b[None, :, :], axis=1)


def _expm(m: np.ndarray) -> np.ndarray:
    """e^m by scaling and squaring of its Taylor series (:func:`_matmul` only, so the same
    bits on every CPU); for the small norms of a period's linearisation."""
    norm = float(np.max(np.sum(np.abs(m), axis=0)))
    squarings = max(0, int(math.ceil(math.log2(norm / 0.25)))) if norm > 0.25 else 0
    scaled = m / (2.0 ** squarings)
    result = np.eye(len(m))
    term = np.eye(len(m))
    for order in range(1, 20):
        term = _matmul(term, scaled) / order
        result = result + term
    for _ in range(squarings):
        result = _matmul(result, result)
    return result


# places in the catch's constants (catch_constants)
(K_K1, K_K2, K_K3, K_K4, K_H1, K_H2, K_H3, K_H4, K_TARGET, K_SETTLE, K_SETTLE_STEP,
 K_HOLD_AFTER, K_HOLD_BLEND, K_GOV, K_GOV_X_LO, K_GOV_X_HI, K_GOV_I, K_GUARD, K_TWO_BRAKE,
 K_LOW, K_HIGH, K_LEAD, N_K) = range(23)


def catch_constants(gain: np.ndarray, hold_gain: np.ndarray, params: CatchParams,
                    limits_m: tuple[float, float], period_s: float, pump_guard: bool
                    ) -> tuple[float, ...]:
    """The constants of the laws below (places ``K_*``): the catch's gain K and the
    hold's, the reference's settling, the governor's bounds in the safe range
    ``limits_m``, and the catch's guard (``pump_guard``: the swing-up's track guard is
    there to brake when the catch lets go)."""
    c = params
    k = [0.0] * N_K
    k[K_K1], k[K_K2], k[K_K3], k[K_K4] = (float(v) for v in gain)
    k[K_H1], k[K_H2], k[K_H3], k[K_H4] = (float(v) for v in hold_gain)
    k[K_TARGET] = c.target_m
    k[K_SETTLE] = 1.0 if c.settle_rate_mps != 0.0 else 0.0
    k[K_SETTLE_STEP] = c.settle_rate_mps * period_s
    k[K_HOLD_AFTER] = c.hold_after_s / period_s if c.hold_poles else -1.0
    k[K_HOLD_BLEND] = c.hold_blend_s / period_s
    k[K_GOV] = 1.0 if c.governor else 0.0
    k[K_GOV_X_LO] = limits_m[0] + c.governor_margin_m
    k[K_GOV_X_HI] = limits_m[1] - c.governor_margin_m
    k[K_GOV_I] = c.governor_current_a
    k[K_GUARD] = 1.0 if c.guard and pump_guard else 0.0
    k[K_TWO_BRAKE] = 2.0 * c.guard_accel_mps2
    k[K_LOW] = limits_m[0] + c.guard_margin_m
    k[K_HIGH] = limits_m[1] - c.guard_margin_m
    k[K_LEAD] = c.guard_lead_s
    return tuple(k)


def catch_force(k1: float, k2: float, k3: float, k4: float, x: float, x_dot: float,
                th: float, theta_dot: float, reference: float) -> float:
    """``f = -K z``, z the state relative to the upright equilibrium with the cart at
    ``reference``; ``th``: the angle from the nearest upright (2 pi n), as the C++
    program takes ``thetad``. No branch: it also runs on arrays.

    Notes
    -----
    Implements (3.46), ``f = -(k1 (x - x*) + k2 x_dot + k3 theta + k4 theta_dot)``.
    """
    return -(k1 * (x - reference) + k2 * x_dot + k3 * th + k4 * theta_dot)


def held_catch_force(k: tuple[float, ...], blend: float, x: float, x_dot: float, th: float,
                     theta_dot: float, reference: float) -> float:
    """:func:`catch_force` with the catch's gain K, or with ``blend`` > 0 the gain blended
    linearly towards the hold's, K + blend (K_hold - K) (:func:`hold_blend`)."""
    if blend > 0.0:
        return catch_force(k[K_K1] + blend * (k[K_H1] - k[K_K1]),
                           k[K_K2] + blend * (k[K_H2] - k[K_K2]),
                           k[K_K3] + blend * (k[K_H3] - k[K_K3]),
                           k[K_K4] + blend * (k[K_H4] - k[K_K4]),
                           x, x_dot, th, theta_dot, reference)
    return catch_force(k[K_K1], k[K_K2], k[K_K3], k[K_K4], x, x_dot, th, theta_dot,
                       reference)


def hold_blend(k: tuple[float, ...], held: float) -> float:
    """How far the hold's gain has replaced the catch's (0 .. 1) after ``held`` periods in
    the catch: from ``catch.hold_after_s`` on, linearly over ``catch.hold_blend_s``
    (always 0 without ``catch.hold_poles``)."""
    if k[K_HOLD_AFTER] >= 0.0:
        return clip((held - k[K_HOLD_AFTER]) / k[K_HOLD_BLEND], 0.0, 1.0)
    return 0.0


def guard_lets_go(k: tuple[float, ...], x: float, x_dot: float) -> bool:
    """The catch's track guard (``catch.guard``): whether the cart, moving on at x_dot
    for ``guard_lead_s`` and then braked at ``guard_accel_mps2``, would stop beyond the
    safe range less ``guard_margin_m``, moving towards that end."""
    if k[K_GUARD] > 0.0:
        stop = x + x_dot * (k[K_LEAD] + abs(x_dot) / k[K_TWO_BRAKE])
        return (stop > k[K_HIGH] and x_dot > 0.0) or (stop < k[K_LOW] and x_dot < 0.0)
    return False


def narrow_interval(lo: float, hi: float, a: float, b: float, low: float, high: float
                    ) -> tuple[float, float]:
    """[lo, hi] narrowed to the r with low <= a + b r <= high (empty: lo > hi)."""
    if b > 1e-12:
        lo = max(lo, (low - a) / b)
        hi = min(hi, (high - a) / b)
    elif b < -1e-12:
        lo = max(lo, (high - a) / b)
        hi = min(hi, (low - a) / b)
    elif not (a >= low and a <= high):
        lo, hi = math.inf, -math.inf
    return lo, hi


def governor_interval(k: tuple[float, ...], rows, x: float, x_dot: float, th: float,
                      theta_dot: float) -> tuple[float, float]:
    """(lo, hi): the catch's cart references r for which the linear closed loop's
    prediction from this state (:func:`governor_rows`: row j gives the cart ``r + P_j .
    w`` and the set-point ``Q_j . w``, ``w = [x - r, x_dot, th, theta_dot]``) keeps the
    cart in the safe range less ``governor_margin_m`` and the set-point within
    +-``governor_current_a`` at every row; lo > hi when no reference does."""
    lo, hi = -math.inf, math.inf
    x_lo, x_hi, i_max = k[K_GOV_X_LO], k[K_GOV_X_HI], k[K_GOV_I]
    for j in range(len(rows)):
        row = rows[j]
        moved = row[0] * x + row[1] * x_dot + row[2] * th + row[3] * theta_dot
        lo, hi = narrow_interval(lo, hi, moved, 1.0 - row[0], x_lo, x_hi)
        current = row[4] * x + row[5] * x_dot + row[6] * th + row[7] * theta_dot
        lo, hi = narrow_interval(lo, hi, current, -row[4], -i_max, i_max)
    return lo, hi


def catch_reference(k: tuple[float, ...], entering: bool, catching: bool, x: float,
                    previous: float, lo: float, hi: float) -> float:
    """The catch's cart reference this sample: ``catch.target_m``, or with
    ``settle_rate_mps`` > 0 the cart's position when the catch began (``entering``),
    moved towards the target by rate x Ts a sample while ``catching``; then kept in the
    governor's interval [lo, hi] (:func:`governor_interval`; none: lo > hi)."""
    if k[K_SETTLE] > 0.0:
        ref = x if entering else previous
        if catching:
            ref = ref + clip(k[K_TARGET] - ref, -k[K_SETTLE_STEP], k[K_SETTLE_STEP])
    else:
        ref = k[K_TARGET]
    if lo <= hi:
        ref = clip(ref, lo, hi)
    return ref

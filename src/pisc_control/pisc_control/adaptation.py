"""Online estimates of the pendulum the controller is swinging: omega_0^2 and its pivot loss.

The swing-up and the switching rule read the pendulum's energy, which depends on its
natural frequency omega_0 = sqrt(m g l / J) (J = I + m l^2), and the energy the pendulum
loses on its way to the top depends on the pivot's friction. Over the rigs PISC must
serve, omega_0^2 varies by about +-15 % and the pivot's loss from nothing to a third of
what the cart can put in; neither is measured on the thesis's rig. This core estimates
both from the pendulum's own motion, sample by sample, while it swings.

The pendulum row of the cart-pole with pivot friction b, in the cart's frame (2.26):

    J theta_ddot = m g l sin(theta) - m l a cos(theta) - b theta_dot,

a the cart's acceleration. Divided by J, with m l / J = omega_0^2 / g:

    theta_ddot = omega_0^2 (sin(theta) - a cos(theta) / g) - beta theta_dot,   beta = b / J,

linear in the unknowns (omega_0^2, beta). Each sample gives one equation, from central
differences over ``h`` periods (the second difference of a sampled signal is its second
derivative averaged by a triangle of half-width h Ts, exactly), of the encoder's angle
and of the IR sensor's position. The IR reading is the cart's position through an RC
low-pass (SPEC section 4), about ``d`` periods late, so the angle's terms are taken ``d``
periods earlier than the position's. Recursive least squares (a Gaussian prior around
the configuration's model, no forgetting: the rig does not change during a run) turns
the equations into estimates with their standard deviations.

Everything is a function of floats and of a mutable sequence of floats (a list in the
nodes, an array row in the compiled batch), so the same source runs in both
(:mod:`pisc_sim.batch_controllers` compiles it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from pisc_model.params import RigParams
from pisc_msgs_py.config import ConfigError, in_range, nonnegative, param, positive

__all__ = ["AdaptationParams", "adaptation_constants", "adaptation_estimates",
           "adaptation_init", "adaptation_size", "adaptation_std", "adaptation_step"]


@dataclass(frozen=True)
class AdaptationParams:
    """How the controller estimates its pendulum online (``enabled: false``: it uses the
    configuration's m, l, I and no pivot loss, as the thesis does)."""

    enabled: bool = param(False, "estimate omega_0^2 and the pivot's loss online and use "
                          "them in the swing-up and the switching rule", "")
    spacing_periods: int = param(
        8, "h: the differences' spacing; longer averages the sensors' steps more, shorter "
        "follows the cart's changes of acceleration more closely", "", in_range(1, 40))
    ir_lag_periods: int = param(
        2, "d: how many periods the IR reading lags the cart (its RC low-pass: 1 / (2 pi "
        "10.26 Hz) = 15.5 ms; 2 gave the estimates closest to the truth over 30 drawn "
        "rigs)", "", in_range(0, 40))
    omega_sq_std: float = param(
        0.15, "prior standard deviation of omega_0^2, relative to the model's", "",
        positive)
    damping_prior_per_s: float = param(
        0.45, "prior mean of beta = b / J, the pivot's loss", "1/s", nonnegative)
    damping_std_per_s: float = param(0.3, "prior standard deviation of beta", "1/s",
                                     positive)
    noise_radps2: float = param(
        3.0, "standard deviation of one equation's error (the sensors' steps through the "
        "differences)", "rad/s^2", positive)
    omega_sq_bounds: float = param(
        0.4, "omega_0^2 stays within this fraction of the model's value", "",
        in_range(0.0, 0.95))
    damping_max_per_s: float = param(3.0, "beta stays within [0, this]", "1/s", positive)
    stall_s: float = param(
        0.0, "the swing-up gives up when the pendulum's energy has not risen by stall_rise_j "
        "for this long while it stays more than stall_below_j below upright's (a rig too "
        "weak or too lossy to be swung up): it stops pumping and says so (0 = never)", "s",
        nonnegative)
    stall_rise_j: float = param(0.0003, "what counts as a rise of the energy, for stall_s",
                                "J", positive)
    stall_below_j: float = param(0.002, "a plateau this far below upright's energy or more "
                                 "counts as a stall, for stall_s", "J", positive)

    def __post_init__(self) -> None:
        if not self.omega_sq_bounds > 0.0:
            raise ConfigError(f"adaptation.omega_sq_bounds = {self.omega_sq_bounds}: must be "
                              "positive")


# places in the constants
(A_H, A_D, A_HT2, A_2HT, A_G, A_NOISE2, A_W2_LO, A_W2_HI, A_B_MAX, A_ON, A_2T, A_STALL_N,
 A_STALL_RISE, A_STALL_FLOOR, N_A) = range(15)
# places in the state after the two histories of 2 h + d + 1 samples each
(ADAPT_SAMPLES, ADAPT_W2, ADAPT_BETA, ADAPT_P00, ADAPT_P01, ADAPT_P11, ADAPT_BEST_E,
 ADAPT_BEST_K, ADAPT_STALLED, ADAPT_HELD, ADAPT_TAIL) = range(11)


def _window(params: AdaptationParams) -> int:
    return 2 * params.spacing_periods + params.ir_lag_periods + 1


def adaptation_size(params: AdaptationParams) -> int:
    """How many floats one rig's state holds."""
    return 2 * _window(params) + ADAPT_TAIL


def adaptation_constants(params: AdaptationParams, rig: RigParams, period_s: float
                         ) -> tuple[float, ...]:
    """The estimator's constants for a rig modelled by ``rig``."""
    c = [0.0] * N_A
    h = params.spacing_periods
    c[A_H] = float(h)
    c[A_D] = float(params.ir_lag_periods)
    c[A_HT2] = (h * period_s) * (h * period_s)
    c[A_2HT] = 2.0 * h * period_s
    c[A_2T] = 2.0 * period_s
    c[A_STALL_N] = round(params.stall_s / period_s)
    c[A_STALL_RISE] = params.stall_rise_j / rig.mgl  # energies in units of m g l
    c[A_STALL_FLOOR] = -params.stall_below_j / rig.mgl
    c[A_G] = rig.gravity_mps2
    c[A_NOISE2] = params.noise_radps2 * params.noise_radps2
    w2 = rig.mgl / (rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m)
    c[A_W2_LO] = w2 * (1.0 - params.omega_sq_bounds)
    c[A_W2_HI] = w2 * (1.0 + params.omega_sq_bounds)
    c[A_B_MAX] = params.damping_max_per_s
    c[A_ON] = 1.0 if params.enabled else 0.0
    return tuple(c)


def adaptation_init(params: AdaptationParams, rig: RigParams, state) -> None:
    """Set ``state`` (a mutable sequence of :func:`adaptation_size` floats) to the prior."""
    n = 2 * _window(params)
    for k in range(n):
        state[k] = 0.0
    w2 = rig.mgl / (rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m)
    state[n + ADAPT_SAMPLES] = 0.0
    state[n + ADAPT_W2] = w2
    state[n + ADAPT_BETA] = params.damping_prior_per_s
    state[n + ADAPT_P00] = (params.omega_sq_std * w2) ** 2
    state[n + ADAPT_P01] = 0.0
    state[n + ADAPT_P11] = params.damping_std_per_s ** 2
    state[n + ADAPT_BEST_E] = -math.inf
    state[n + ADAPT_BEST_K] = 0.0
    state[n + ADAPT_STALLED] = 0.0
    state[n + ADAPT_HELD] = 0.0


def adaptation_step(a: tuple[float, ...], state, x: float, theta: float, learn: bool
                    ) -> tuple[float, float, float, float, bool, float]:
    """Take one sample (the measured cart position and angle); (omega_0^2, beta) now, and
    the pendulum's angle one period ago with its rate by the central difference over the
    two periods around it, (theta_{k-1}, (theta_k - theta_{k-2}) / (2 Ts)) (the angle and a
    rate at 0 before three samples).

    The pair is what the swing-up reads the pendulum's energy from: a rate with one
    period's lag and the angle of the same instant, where the estimator's velocity (a
    difference over N periods, low-passed, to balance without chatter) lags 25 ms and
    made the energy it read swing by +-2 mJ within each swing (of 2 m g l = 18 mJ).

    ``state`` is updated in place: the newest sample replaces the oldest of each history
    (``state[n + ADAPT_SAMPLES]`` counts the samples), and once the histories are full
    and while ``learn``, the sample's equation updates the estimates and their
    covariance. The supervisor learns while it swings the pendulum up, not while it
    balances it: near upright the equation's terms are small and the IR reading's lag,
    which the d periods only approximate, dominates them.
    """
    h = int(a[A_H])
    d = int(a[A_D])
    window = 2 * h + d + 1
    n = 2 * window
    count = int(state[n + ADAPT_SAMPLES])
    slot = count % window
    state[slot] = theta
    state[window + slot] = x
    count += 1
    state[n + ADAPT_SAMPLES] = float(count)
    w2 = state[n + ADAPT_W2]
    beta = state[n + ADAPT_BETA]
    if count >= 3:
        middle = state[(count - 2) % window]
        rate = (theta - state[(count - 3) % window]) / a[A_2T]
    else:
        middle, rate = theta, 0.0
    stalled = state[n + ADAPT_STALLED] > 0.0
    held = 0.0 if learn else state[n + ADAPT_HELD] + 1.0
    state[n + ADAPT_HELD] = held
    if (learn and a[A_STALL_N] > 0.0 and count >= 3 and not stalled
            and math.isfinite(middle) and math.isfinite(rate)):
        energy = rate * rate / (2.0 * w2) + (math.cos(middle) - 1.0)
        if energy > state[n + ADAPT_BEST_E] + a[A_STALL_RISE]:
            state[n + ADAPT_BEST_E] = energy
            state[n + ADAPT_BEST_K] = float(count)
        elif (count - state[n + ADAPT_BEST_K] >= a[A_STALL_N]
              and state[n + ADAPT_BEST_E] < a[A_STALL_FLOOR]):
            stalled = True
            state[n + ADAPT_STALLED] = 1.0
    if a[A_ON] == 0.0 or count < window or not learn:
        return w2, beta, middle, rate, stalled, held

    th0 = state[(count - 1 - d) % window]
    th1 = state[(count - 1 - h - d) % window]
    th2 = state[(count - 1 - 2 * h - d) % window]
    x0 = state[window + (count - 1) % window]
    x1 = state[window + (count - 1 - h) % window]
    x2 = state[window + (count - 1 - 2 * h) % window]
    if not (math.isfinite(th0) and math.isfinite(th1) and math.isfinite(th2)):
        return w2, beta, middle, rate, stalled, held  # (math.sin raises on infinities)
    theta_ddot = (th0 - 2.0 * th1 + th2) / a[A_HT2]
    accel = (x0 - 2.0 * x1 + x2) / a[A_HT2]
    # the triangle's average of sin(theta) to second order, (f(-h) + 10 f(0) + f(h)) / 12
    sn = (math.sin(th0) + 10.0 * math.sin(th1) + math.sin(th2)) / 12.0
    phi0 = sn - accel * math.cos(th1) / a[A_G]
    phi1 = -(th0 - th2) / a[A_2HT]
    if not (math.isfinite(theta_ddot) and math.isfinite(phi0) and math.isfinite(phi1)):
        return w2, beta, middle, rate, stalled, held  # not finite: nothing learnt
    p00, p01, p11 = state[n + ADAPT_P00], state[n + ADAPT_P01], state[n + ADAPT_P11]
    # recursive least squares: gain k = P phi / (noise^2 + phi' P phi)
    pp0 = p00 * phi0 + p01 * phi1
    pp1 = p01 * phi0 + p11 * phi1
    s = a[A_NOISE2] + phi0 * pp0 + phi1 * pp1
    k0, k1 = pp0 / s, pp1 / s
    error = theta_ddot - (w2 * phi0 + beta * phi1)
    w2 = w2 + k0 * error
    beta = beta + k1 * error
    state[n + ADAPT_P00] = p00 - k0 * pp0
    state[n + ADAPT_P01] = p01 - k0 * pp1
    state[n + ADAPT_P11] = p11 - k1 * pp1
    w2 = min(max(w2, a[A_W2_LO]), a[A_W2_HI])
    beta = min(max(beta, 0.0), a[A_B_MAX])
    state[n + ADAPT_W2] = w2
    state[n + ADAPT_BETA] = beta
    return w2, beta, middle, rate, stalled, held


def adaptation_estimates(state) -> tuple[float, float]:
    """The estimates in ``state``: (omega_0^2, beta)."""
    n = len(state) - ADAPT_TAIL
    return state[n + ADAPT_W2], state[n + ADAPT_BETA]


def adaptation_std(state) -> tuple[float, float]:
    """The estimates' standard deviations (from the covariance in ``state``)."""
    n = len(state) - ADAPT_TAIL
    return math.sqrt(max(state[n + ADAPT_P00], 0.0)), math.sqrt(max(state[n + ADAPT_P11], 0.0))

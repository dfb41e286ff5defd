"""The online estimates of omega_0^2 and the pivot's loss (pisc_control.adaptation), on
motions integrated here independently of the project's plant."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from pisc_control.adaptation import (
    AdaptationParams,
    adaptation_constants,
    adaptation_estimates,
    adaptation_init,
    adaptation_size,
    adaptation_std,
    adaptation_step,
)
from pisc_model.params import RigParams
from pisc_msgs_py.config import ConfigError

PERIOD = 0.005
G = 9.81


def _swing(omega_sq: float, beta: float, cart, duration: float = 2.0,
           theta0: float = math.pi - 0.6) -> tuple[np.ndarray, np.ndarray]:
    """The pendulum of theta_ddot = omega^2 (sin theta - a cos theta / g) - beta theta_dot
    under the cart's motion ``cart(t) -> (x, a)``, sampled every period (no sensors)."""

    def rhs(t, y):
        _, a = cart(t)
        theta, rate = y
        return [rate, omega_sq * (math.sin(theta) - a * math.cos(theta) / G) - beta * rate]

    times = np.arange(0.0, duration, PERIOD)
    sol = solve_ivp(rhs, (0.0, duration), [theta0, 0.0], t_eval=times, rtol=1e-10,
                    atol=1e-12, method="DOP853")
    x = np.array([cart(t)[0] for t in times])
    return x, sol.y[0]


def _shaking(amplitude: float, omega: float):
    return lambda t: (amplitude * math.sin(omega * t),
                      -amplitude * omega * omega * math.sin(omega * t))


def _run(params: AdaptationParams, rig: RigParams, x, theta, learn=True):
    state = [0.0] * adaptation_size(params)
    adaptation_init(params, rig, state)
    a = adaptation_constants(params, rig, PERIOD)
    out = [adaptation_step(a, state, float(xk), float(tk), learn)[:2]
           for xk, tk in zip(x, theta)]
    return np.array(out), state


# the thesis rig's pendulum (Table 6.1): m g l = 0.01055 x 9.81 x 0.0865 = 8.95234e-3 N m,
# J = I + m l^2 = 2.631524e-5 + 7.89370e-5 = 1.052522e-4 kg m^2, omega_0^2 = 85.0555 1/s^2
RIG = RigParams()
NOMINAL = RIG.mgl / (RIG.pendulum_inertia_kgm2 + RIG.ml * RIG.pendulum_com_m)
# no sensor lag in these motions (the IR's RC low-pass is the plant's, tested through it)
EXACT = AdaptationParams(enabled=True, ir_lag_periods=0)


def test_nominal_omega_sq():
    assert NOMINAL == pytest.approx(85.0555, abs=1e-3)


@pytest.mark.parametrize("truth, loss", [(0.85 * NOMINAL, 0.0), (1.15 * NOMINAL, 0.9),
                                         (NOMINAL, 0.4)])
def test_converges_on_a_shaken_pendulum(truth, loss):
    """A pendulum shaken by the cart at 1.5 Hz, 3 cm: after 2 s both estimates are within
    1 % of omega_0^2 and 0.03 1/s of the loss, from the prior's nominal values."""
    x, theta = _swing(truth, loss, _shaking(0.03, 2 * math.pi * 1.5))
    out, state = _run(EXACT, RIG, x, theta)
    w2, beta = out[-1]
    assert w2 == pytest.approx(truth, rel=0.01)
    assert beta == pytest.approx(loss, abs=0.03)
    assert adaptation_estimates(state) == (w2, beta)
    w2_std, beta_std = adaptation_std(state)
    assert 0.0 < w2_std < 0.15 * NOMINAL and 0.0 < beta_std < EXACT.damping_std_per_s


def test_prior_until_the_window_is_full_and_while_not_learning():
    """Before 2 h + d + 1 samples, and whenever it is told not to learn, the estimates stay
    where they were (the prior: the model's omega_0^2 and the prior loss)."""
    x, theta = _swing(1.1 * NOMINAL, 0.5, _shaking(0.03, 9.0))
    window = 2 * EXACT.spacing_periods + EXACT.ir_lag_periods + 1
    out, _ = _run(EXACT, RIG, x[:window - 1], theta[:window - 1])
    assert np.all(out == (NOMINAL, EXACT.damping_prior_per_s))
    out, _ = _run(EXACT, RIG, x, theta, learn=False)
    assert np.all(out == (NOMINAL, EXACT.damping_prior_per_s))


def test_disabled_gives_the_model():
    x, theta = _swing(1.1 * NOMINAL, 0.5, _shaking(0.03, 9.0))
    out, _ = _run(AdaptationParams(enabled=False), RIG, x, theta)
    assert np.all(out == (NOMINAL, AdaptationParams().damping_prior_per_s))


def test_bounded():
    """A measurement that makes no sense (the angle jumps) cannot carry the estimates past
    their bounds."""
    x = np.zeros(400)
    theta = np.where(np.arange(400) % 2 == 0, 3.0, 3.4)
    out, _ = _run(EXACT, RIG, x, theta)
    assert np.all(out[:, 0] >= NOMINAL * (1 - EXACT.omega_sq_bounds) - 1e-9)
    assert np.all(out[:, 0] <= NOMINAL * (1 + EXACT.omega_sq_bounds) + 1e-9)
    assert np.all((out[:, 1] >= 0.0) & (out[:, 1] <= EXACT.damping_max_per_s))


def test_non_finite_sample_is_skipped():
    x, theta = _swing(NOMINAL, 0.3, _shaking(0.03, 9.0))
    theta = theta.copy()
    theta[200] = math.nan
    out, _ = _run(EXACT, RIG, x, theta)
    assert np.all(np.isfinite(out))


def test_refuses_bounds_of_zero():
    with pytest.raises(ConfigError, match="adaptation.omega_sq_bounds"):
        dataclasses.replace(EXACT, omega_sq_bounds=0.0)


def test_the_energy_rate_is_the_central_difference_one_period_late():
    params = AdaptationParams(enabled=False)
    state = [0.0] * adaptation_size(params)
    adaptation_init(params, RIG, state)
    a = adaptation_constants(params, RIG, PERIOD)
    angles = [3.0, 3.01, 3.03, 3.06]
    got = [adaptation_step(a, state, 0.0, th, True)[2:4] for th in angles]
    assert got[0] == (3.0, 0.0) and got[1] == (3.01, 0.0)
    assert got[2] == (3.01, pytest.approx(0.03 / (2 * PERIOD)))
    assert got[3] == (3.03, pytest.approx(0.05 / (2 * PERIOD)))


def test_a_swing_up_that_stalls_gives_up_and_one_that_rises_does_not():
    """A pendulum that keeps swinging 1 rad about hanging (energy far below upright's, not
    rising) stalls after stall_s; one shaken into larger swings does not."""
    params = dataclasses.replace(EXACT, stall_s=1.0)
    x, theta = _swing(NOMINAL, 0.0, lambda t: (0.0, 0.0), duration=1.6, theta0=math.pi - 1.0)
    state = [0.0] * adaptation_size(params)
    adaptation_init(params, RIG, state)
    a = adaptation_constants(params, RIG, PERIOD)
    stalled = [adaptation_step(a, state, float(xk), float(tk), True)[4]
               for xk, tk in zip(x, theta)]
    first = stalled.index(True)
    assert 1.0 <= first * PERIOD <= 1.0 + 0.7  # a second after the best energy, once seen
    assert all(stalled[first:])
    # resonant shaking: after 1.2 s out of phase the swings grow
    params = dataclasses.replace(EXACT, stall_s=1.5)
    a = adaptation_constants(params, RIG, PERIOD)
    x, theta = _swing(NOMINAL, 0.0, _shaking(0.03, math.sqrt(NOMINAL)), duration=3.0)
    state = [0.0] * adaptation_size(params)
    adaptation_init(params, RIG, state)
    assert not any(adaptation_step(a, state, float(xk), float(tk), True)[4]
                   for xk, tk in zip(x, theta))

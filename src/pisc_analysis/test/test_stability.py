"""Krasovskii, Routh and the sampled PI current loop."""

import math
from dataclasses import replace

import numpy as np
import pytest

from pisc_analysis.linear import linearise, place_gain
from pisc_analysis.stability import (
    closed_loop_jacobian,
    krasovskii,
    krasovskii_radius,
    lyapunov_matrix,
    pi_characteristic_polynomial,
    quasi_static_pi_poles,
    routh_table,
    sampled_pi_check,
    sampled_pi_poles,
    sampled_pi_resistance_limit,
)
from pisc_analysis.symbolic import cart_pole
from pisc_control.current_loop import CurrentLoopParams, CurrentLoopState, current_loop_update
from pisc_model.params import MotorParams
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig

MOTOR = MotorParams()
THESIS_PI = CurrentLoopParams()  # k_pi = 2.9, k_ii = 1800 (Table 6.2)
TS = 0.005


# -- the sampled PI loop (acceptance: thesis gains unstable at 6 ohm, stable at 14 ohm) --


def test_quasi_static_check_reports_thesis_gains_unstable_at_6_ohm_stable_at_default():
    at6 = sampled_pi_check(replace(MOTOR, resistance_ohm=6.0), THESIS_PI, TS,
                           model="quasi-static")
    assert not at6.stable
    # 6 z^2 + 5.9 z - 2.9 = 0
    assert at6.worst_pole.real == pytest.approx((-5.9 - math.sqrt(5.9**2 + 4 * 6 * 2.9)) / 12)
    assert round(at6.worst_pole.real, 3) == -1.343
    default = sampled_pi_check(MOTOR, THESIS_PI, TS, model="quasi-static")
    assert MOTOR.resistance_ohm == 14.0
    assert default.stable
    np.testing.assert_allclose(np.sort(default.poles.real),
                               np.sort(np.roots([14.0, 2.9 + 9.0 - 14.0, -2.9])), rtol=1e-12)


def test_exact_armature_model_agrees_with_the_quasi_static_one_when_l_over_r_is_small():
    for r in (6.0, 14.0):
        motor = replace(MOTOR, resistance_ohm=r)
        exact = np.sort_complex(sampled_pi_poles(motor, THESIS_PI, TS))
        quasi = np.sort_complex(quasi_static_pi_poles(r, 2.9, 1800.0, TS))
        # exp(-R Ts / L) = exp(-15) at 6 ohm: the armature pole is gone within a period
        np.testing.assert_allclose(exact[np.abs(exact) > 1e-5], quasi, atol=1e-5)


def test_quasi_static_boundary_is_k_pi_plus_half_k_ii_ts():
    limit = sampled_pi_resistance_limit(MOTOR, THESIS_PI, TS, model="quasi-static")
    assert limit == pytest.approx(2.9 + 1800.0 * TS / 2.0, abs=2e-4)


def test_the_72_hz_sensor_filter_moves_the_boundary_below_6_ohm():
    limit = sampled_pi_resistance_limit(MOTOR, THESIS_PI, TS, model="filter")
    assert 5.70 < limit < 5.78
    at6 = sampled_pi_check(replace(MOTOR, resistance_ohm=6.0), THESIS_PI, TS, model="filter")
    assert at6.stable and at6.spectral_radius == pytest.approx(0.930, abs=1e-3)
    at55 = sampled_pi_check(replace(MOTOR, resistance_ohm=5.5), THESIS_PI, TS, model="filter")
    assert not at55.stable


def _simulated_voltage_swing(resistance_ohm: float) -> float:
    """Largest sample-to-sample voltage change over the last 0.25 s of a 1 s run."""
    plant = Plant(PlantConfig(motor=replace(MOTOR, resistance_ohm=resistance_ohm)))
    y = plant.initial_state(0.0, 0.0, math.pi, 0.0)
    state = CurrentLoopState()
    voltages = []
    for _ in range(200):
        _, _, current = plant.measurement(y)
        state, u = current_loop_update(THESIS_PI, TS, state, 0.1, current)
        voltages.append(float(u))
        y = plant.advance(y, u, TS)
    return float(np.max(np.abs(np.diff(voltages[-50:]))))


def test_the_simulated_plant_agrees_with_the_filter_model_on_both_sides_of_the_boundary():
    # 5.5 ohm: filter model unstable -> the voltage alternates between the rails
    assert _simulated_voltage_swing(5.5) > 20.0
    # 6 ohm: SPEC's quasi-static model says unstable, the filter model and the plant agree
    # it is stable (what is left is the ADC's 12 mA quantisation times k_pi)
    assert _simulated_voltage_swing(6.0) < 1.0


def test_unknown_model_is_refused():
    with pytest.raises(ValueError, match="model = 'jury'"):
        sampled_pi_check(MOTOR, THESIS_PI, TS, model="jury")
    with pytest.raises(ValueError, match="no stability boundary between 20.0 and 1000.0 ohm"):
        sampled_pi_resistance_limit(MOTOR, THESIS_PI, TS, low_ohm=20.0)


# -- Routh ------------------------------------------------------------------------------


def test_routh_table_of_thesis_3_51_has_no_sign_change():
    c = pi_characteristic_polynomial(MOTOR, THESIS_PI)
    ell, j, b, r = 0.002, 2e-6, 1e-6, 14.0
    np.testing.assert_allclose(
        c, [ell * j, j * (r + 2.9) + b * ell, b * (r + 2.9) + 0.0637**2 + 1800 * j, 1800 * b])
    table, changes = routh_table(c)
    assert changes == 0
    # Table 3.1, row s^1: (c2 c1 - c3 c0) / c2
    assert table[2, 0] == pytest.approx((c[1] * c[2] - c[0] * c[3]) / c[1])
    assert np.all(np.roots(c).real < 0)


def test_routh_counts_right_half_plane_roots():
    # (s - 1)(s - 2)(s + 3) = s^3 - 7 s + 6: two roots on the right
    assert routh_table([1.0, 0.0, -7.0, 6.0])[1] == 2
    assert routh_table([1.0, 6.0, 11.0, 6.0])[1] == 0
    with pytest.raises(ValueError, match="row of zeros"):
        routh_table([1.0, 0.0, 1.0])


# -- Krasovskii -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def thesis_closed_loop():
    system, s = cart_pole()
    values = {s.M: 0.4735, s.m: 0.01055, s.l: 0.0865, s.I: 2.631524e-5, s.g: 9.81}
    a, b = linearise(system, values)
    k = place_gain(a, b, [-15.0, -11.0, -2.0, -1.5])
    return closed_loop_jacobian(system, values, k), a - b @ k.reshape(1, 4)


def test_closed_loop_jacobian_at_the_origin_is_a_minus_bk(thesis_closed_loop):
    jac, a_cl = thesis_closed_loop
    np.testing.assert_allclose(jac(np.zeros((1, 4)))[0], a_cl, rtol=1e-10, atol=1e-10)


def test_krasovskii_with_p_identity_fails_as_it_must_for_q_q_dot_coordinates(
        thesis_closed_loop):
    jac, _ = thesis_closed_loop
    result = krasovskii(jac, np.zeros((1, 4)))
    # F[0, 0] = 2 d(x_dot)/dx = 0 and F is indefinite: seed 001's form cannot pass
    assert not result.negative_definite
    assert result.max_eigenvalue > 0.0


def test_generalised_krasovskii_passes_near_the_origin_and_fails_far_away(thesis_closed_loop):
    jac, a_cl = thesis_closed_loop
    p = lyapunov_matrix(a_cl)
    at_origin = krasovskii(jac, np.zeros((1, 4)), p)
    assert at_origin.negative_definite
    assert at_origin.max_eigenvalue == pytest.approx(-1.0)  # P A + A^T P = -I there
    scale = [0.1, 0.5, 0.1, 1.0]
    r = krasovskii_radius(jac, p, scale, samples=2000)
    assert 0.1 < r < 2.0
    assert krasovskii(jac, np.array(scale) * r * 0.99 * np.array([0, 0, 1, 0]), p).negative_definite
    assert not krasovskii(jac, np.array([0.0, 0.0, 1.2, 0.0]), p).negative_definite

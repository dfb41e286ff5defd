"""The compiled kernel: phi-functions, the structured operators against matrix functions
computed independently, the right-hand side against dynamics.py, and the exponential
scheme's order on the stiff rig."""

import dataclasses
import math
from fractions import Fraction

import numpy as np
import pytest
from scipy.linalg import expm

from pisc_plant import kernel
from pisc_plant.dynamics import accelerations
from pisc_plant.params import FrictionParams, ModelParams
from pisc_plant.plant import IntegratorParams, Plant, PlantConfig


@pytest.mark.parametrize("z", [-60.0, -7.0, -4.0001, -3.9999, -2.0, -0.3, -1e-5, 0.0, 0.5, 3.0])
def test_phi_matches_its_series_and_closed_form(z):
    exact_z = Fraction(z)
    for k in range(8):
        # the series in exact rational arithmetic (no cancellation at any z)
        terms = int(3 * abs(z)) + 60
        series = float(sum(exact_z**j / math.factorial(j + k) for j in range(terms)))
        assert kernel.phi(k, z) == pytest.approx(series, rel=1e-12, abs=1e-300)
        out = np.empty(8)
        kernel._phis(z, out)
        assert out[k] == pytest.approx(series, rel=1e-11, abs=1e-300)
    if abs(z) >= 1.0:  # where the closed form itself is accurate
        assert kernel.phi(2, z) == pytest.approx((math.exp(z) - 1 - z) / z**2, rel=1e-9)


def _phi_matrix(k, a):
    """phi_k(A) from the exponential of an augmented block matrix (Saad's identity)."""
    n = a.shape[0]
    if k == 0:
        return expm(a)
    m = np.zeros((n * (k + 1), n * (k + 1)))
    m[:n, :n] = a
    for j in range(k):
        m[j * n:(j + 1) * n, (j + 1) * n:(j + 2) * n] = np.eye(n)
    return expm(m)[:n, k * n:(k + 1) * n]


def test_structured_operators_equal_the_matrix_phi_functions():
    """Every operator of the scheme applied through its divided differences equals the
    same combination of phi_k(s h L) computed with scipy's expm of L as a dense matrix."""
    lam, w_ir, w_cur, c_v, h = -6990.0, 64.5, 452.4, 90.5, 0.0025
    c = np.array([4.1, -30.0, 0.7, -2.5, lam])  # c_x, c_theta, c_x1, c_theta1, lam
    # state order of a full-fidelity plant plus r: x, x_dot, theta, theta_dot, q, v_ir, v_cur, r
    a = np.zeros((8, 8))
    a[0, 1] = a[2, 3] = 1.0
    a[1, 4], a[3, 4], a[1, 7], a[3, 7] = c[0], c[1], c[2], c[3]
    a[4, 4] = a[7, 7] = lam
    a[7, 4] = 1.0
    a[5, 5], a[6, 6], a[6, 4] = -w_ir, -w_cur, c_v
    table = kernel.exp_coefficients(w_ir, w_cur, c_v, h)
    ph = np.empty((2, 8))
    kernel._armature_operators(lam, table, ph)
    lay = kernel.Layout(kernel.ARM_FULL, True, True).array()
    for op in range(kernel.N_OPERATORS):
        expected = np.zeros((8, 8))
        for si, s in enumerate(kernel.STAGE_FRACTIONS):
            for k in range(4):
                w = kernel.OP_WEIGHTS[op, si, k]
                if w:
                    expected += w * _phi_matrix(k, s * h * a)
        expected *= 1.0 if op < 2 else h
        got = np.zeros((8, 8))
        for j in range(8):
            v = np.zeros(8)
            v[j] = 1.0
            kernel._apply_add(table[op], v, c, lay, got[:, j])
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-13 * np.abs(expected).max())


def test_right_hand_side_agrees_with_the_reference_dynamics():
    friction = FrictionParams(cart_viscous_ns_per_m=0.3, pivot_viscous_nms=2e-5,
                              cart_coulomb_n=0.05)
    plant = Plant(PlantConfig(models=ModelParams(friction="coulomb"), friction=friction))
    rng = np.random.default_rng(3)
    cfg = plant.config
    for _ in range(20):
        x, xd, th, thd, i = rng.uniform([-0.2, -1, -7, -20, -1], [0.1, 1, 7, 20, 1])
        y = plant.initial_state(x, xd, th, thd, i)
        f = plant.derivative(y, 0.0)  # zero command: 0 V applied
        force = (cfg.motor.force_per_amp * i - cfg.motor.reflected_damping_ns_per_m * xd
                 - 0.3 * xd - 0.05 * math.tanh(xd / 1e-3))
        # the pivot torque enters through the pendulum row: compare without it separately
        xdd, thdd = accelerations(cfg.rig, th, thd, force, cfg.motor.reflected_mass_kg)
        a1, ml = cfg.rig.a1, cfg.rig.ml
        den = cfg.rig.a2 + cfg.motor.reflected_mass_kg - a1 * math.cos(th) ** 2
        tau = -2e-5 * thd
        xdd += -a1 * math.cos(th) * tau / ml / den
        thdd += a1 * (cfg.rig.a2 + cfg.motor.reflected_mass_kg) * tau / ml / (ml * den)
        assert f[1] == pytest.approx(xdd, rel=1e-12, abs=1e-12)
        assert f[3] == pytest.approx(thdd, rel=1e-12, abs=1e-12)
        back_emf = cfg.motor.back_emf_v_s_per_rad * xd / cfg.motor.wheel_radius_m
        assert f[4] == pytest.approx((0.0 - cfg.motor.resistance_ohm * i - back_emf)
                                     / cfg.motor.inductance_h, rel=1e-12)


def _playback_errors(config, counts, y0, commands):
    reference = Plant(dataclasses.replace(config, integrator=IntegratorParams("rk4", 800)))
    yr = y0
    ref_states = []
    for u in commands:
        yr = reference.advance(yr, u, 0.005)
        ref_states.append(yr)
    errors = []
    for n in counts:
        plant = Plant(dataclasses.replace(config, integrator=IntegratorParams("exprk4", n)))
        y = y0
        worst = 0.0
        for u, r in zip(commands, ref_states, strict=True):
            y = plant.advance(y, u, 0.005)
            worst = max(worst, float(np.max(np.abs(y[:4] - r[:4]))))
        errors.append(worst)
    return errors


def test_exponential_scheme_stays_accurate_through_voltage_steps():
    """The hard part of the rig: a voltage step every period starts a 0.14 ms armature
    transient while the pendulum swings at 15 rad/s. Measured: 2.4e-7, 1.6e-8, 3.5e-9,
    1.7e-9, 5.0e-10 rad/s at 1, 2, 4, 8, 16 steps per period: fourth order from 1 to 2
    steps, then slower (what L leaves out, the angle's second-order change during the
    transient, sets a floor near 1e-9)."""
    config = PlantConfig(models=ModelParams(sensors="ideal", sensor_filters=False,
                                            end_stops=False))
    y0 = Plant(config).initial_state(0.0, 0.3, 2.0, 15.0, 0.0)
    commands = [6.0, -6.0, 9.0, -3.0] * 5
    errors = _playback_errors(config, (1, 2, 4, 8, 16), y0, commands)
    assert errors[0] < 5e-7 and errors[1] < 3e-8 and errors[4] < 1e-9, errors
    assert errors[0] / errors[1] > 10, errors
    assert all(a > b for a, b in zip(errors, errors[1:], strict=False)), errors


def test_batch_and_single_rig_are_bit_identical():
    plant = Plant(PlantConfig(integrator=IntegratorParams("exprk4", 2)))
    starts = np.linspace(-0.1, 0.1, 130)  # more than two of the kernel's chunks
    batch = plant.initial_state(starts, 0.1, 3.0, 1.0)
    commands = np.linspace(-11, 11, 130)
    out = plant.advance(batch, commands, 0.005)
    for k in (0, 63, 64, 129):
        single = plant.advance(plant.initial_state(starts[k], 0.1, 3.0, 1.0), commands[k], 0.005)
        np.testing.assert_array_equal(out[k], single)

"""The compiled kernel: phi-functions, the structured operators against matrix functions
computed independently, the right-hand side against dynamics.py, and the exponential
scheme's order on the stiff rig."""

import dataclasses
import math
from fractions import Fraction

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from pisc_plant import kernel
from pisc_plant import kernel_batch
from pisc_plant import kernel_operators
from pisc_plant import kernel_steps
from pisc_model.dynamics import accelerations
from pisc_model.params import FrictionParams, ModelParams
from pisc_plant.layout import (
    ARM_FORCE, ARM_FULL, ARM_QUASI_STATIC, P_A1, P_A2, P_KER, P_KF, P_L, P_R, Layout,
)
from pisc_plant.plant import Plant
from pisc_plant.plant_config import IntegratorParams, PlantConfig, pack_constants


@pytest.mark.parametrize("z", [-60.0, -7.0, -4.0001, -3.9999, -2.0, -0.3, -1e-5, 0.0, 0.5, 3.0])
def test_phi_matches_its_series_and_closed_form(z):
    exact_z = Fraction(z)
    for k in range(8):
        # the series in exact rational arithmetic (no cancellation at any z)
        terms = int(3 * abs(z)) + 60
        series = float(sum(exact_z**j / math.factorial(j + k) for j in range(terms)))
        assert kernel_operators.phi(k, z) == pytest.approx(series, rel=1e-12, abs=1e-300)
        out = np.empty(8)
        kernel_operators._phis(z, out)
        assert out[k] == pytest.approx(series, rel=1e-11, abs=1e-300)
    if abs(z) >= 1.0:  # where the closed form itself is accurate
        assert kernel_operators.phi(2, z) == pytest.approx((math.exp(z) - 1 - z) / z**2, rel=1e-9)


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
    # c_x, c_theta, c_x1, c_theta1, lam, the current sensor's share of q, (two unused),
    # c_x2, c_theta2
    c = np.array([4.1, -30.0, 0.7, -2.5, lam, 0.97, 0.0, 0.0, 3.3, -41.0, 0.0, 0.0])
    # a full-fidelity plant plus r and s: x, x_dot, theta, theta_dot, q, v_ir, v_cur, r, s
    a = np.zeros((9, 9))
    a[0, 1] = a[2, 3] = 1.0
    a[1, 4], a[3, 4], a[1, 7], a[3, 7], a[1, 8], a[3, 8] = c[0], c[1], c[2], c[3], c[8], c[9]
    a[4, 4] = a[7, 7] = a[8, 8] = lam
    a[7, 4] = a[8, 7] = 1.0
    a[5, 5], a[6, 6], a[6, 4] = -w_ir, -w_cur, c_v * c[5]
    table = kernel_operators.exp_coefficients(w_ir, w_cur, c_v, lam, h)
    for op in range(kernel_operators.N_OPERATORS):
        expected = np.zeros((9, 9))
        for si, s in enumerate(kernel_operators.STAGE_FRACTIONS):
            for k in range(4):
                w = kernel_operators.OP_WEIGHTS[op, si, k]
                if w:
                    expected += w * _phi_matrix(k, s * h * a)
        expected *= 1.0 if op < 2 else h
        got = np.zeros((9, 9))
        for j in range(9):
            v = np.zeros(9)
            v[j] = 1.0
            out = np.zeros(9)
            kernel_steps.apply_add(table[op], v, c, out)
            got[:, j] = out
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-13 * np.abs(expected).max())
        # the form for the nonlinear part's vectors (zero x, theta, r, s) agrees
        for j in (1, 3, 4, 5, 6):
            v = np.zeros(9)
            v[j] = 1.0
            out = np.zeros(9)
            kernel_steps.apply_add_n(table[op], v, c, out)
            np.testing.assert_allclose(out, got[:, j], rtol=1e-12, atol=1e-300)


def _exp_coefficients_one_by_one(w_ir, w_cur, c_v, lam, h):
    """kernel_operators.exp_coefficients as it was first written, in Python: every term a Python
    float, added one at a time in the order s = 1/2, 1, k = 0..3, skipping alpha = 0."""
    table = np.zeros((15, kernel_operators.OP_WIDTH))
    phi_cur = np.array([[kernel_operators.phi(k, -s * h * w_cur) for k in range(4)]
                        for s in kernel_operators.STAGE_FRACTIONS])
    for op, weights in enumerate(kernel_operators.OP_WEIGHTS):
        scale = 1.0 if op < 2 else h
        for si, s in enumerate(kernel_operators.STAGE_FRACTIONS):
            sh = s * h
            for k in range(4):
                alpha = scale * weights[si, k]
                if alpha == 0.0:
                    continue
                table[op, kernel_operators.OP_D0] += alpha / math.factorial(k)
                table[op, kernel_operators.OP_D1] += alpha * sh / math.factorial(k + 1)
                table[op, kernel_operators.OP_DIR] += alpha * kernel_operators.phi(k, -sh * w_ir)
                table[op, kernel_operators.OP_DCUR] += alpha * phi_cur[si, k]
    table[kernel_operators.ROW_PHI_CUR, 0:4] = phi_cur[0]
    table[kernel_operators.ROW_PHI_CUR, 4:8] = phi_cur[1]
    table[kernel_operators.ROW_CONST, 0:3] = (c_v, w_cur, h)
    if lam != 0.0:
        kernel_operators.armature_operators(lam, table, np.empty((2, 8)))
    return table


def test_operator_tables_are_the_one_by_one_sums_bit_for_bit():
    """The compiled exp_coefficients (two tables a cycle on the wall clock) gives the bits
    of the Python sums, over step sizes and rates on both sides of phi's switch from the
    series to the exponential (|z| = 2), with and without filters and armature."""
    rng = np.random.default_rng(16)
    cases = [(64.5, 452.4, 90.5, -6990.0, 0.0025), (0.0, 0.0, 0.0, 0.0, 0.0025),
             (64.5, 800.0, 90.5, -6990.0, 0.0025)]  # |w_cur h| = 2 exactly
    for _ in range(400):
        w_cur = rng.choice([0.0, 10 ** rng.uniform(0, 4.5)])
        w_ir = rng.choice([0.0, 10 ** rng.uniform(0, 4)])
        lam = rng.choice([0.0, -10 ** rng.uniform(1, 5)])
        cases.append((w_ir, w_cur, w_cur / 5.0, lam, 10 ** rng.uniform(-8, -1.5)))
    switched = 0
    for case in cases:
        got = kernel_operators.exp_coefficients(*case)
        expected = _exp_coefficients_one_by_one(*case)
        assert got.tobytes() == expected.tobytes(), (case, np.argwhere(got != expected))
        switched += max(case[0], case[1]) * case[4] >= 2.0
    assert 50 < switched < len(cases) - 50  # both of phi's branches taken, often


def test_armature_rate_is_the_middle_of_the_rates_the_angle_gives():
    """lam = -R/L + d k_f / (a2 - a1/2); the state's own rate -R/L + d k_f / den(theta)
    stays within d k_f a1 / (2 den^2) of it: 0.0049 1/s on the thesis rig, 7e-7 of R/L
    (computed here from the parameters)."""
    plant = Plant(PlantConfig())
    p = pack_constants(plant.config)
    d = p[P_KER] / p[P_R]
    rates = [-p[P_R] / p[P_L] + d * p[P_KF] / (p[P_A2] - p[P_A1]
                                                                   * math.cos(t) ** 2)
             for t in np.linspace(0, math.pi, 181)]
    lam = kernel_operators.armature_rate(p)
    assert lam == pytest.approx(-14.0 / 0.002 + d * p[P_KF]
                                / (p[P_A2] - 0.5 * p[P_A1]), rel=1e-15)
    assert min(rates) < lam < max(rates)
    assert max(abs(r - lam) for r in rates) < 0.005  # 1/s, against R/L = 7000 1/s


def test_each_layout_has_its_own_kernels():
    """A layout's indices are constants of its compiled kernels: each of the six layouts
    (armature x filters) has its own entry points, and each steps its own state size
    (the end stops are a run-time flag); each has a second set with the Coulomb term
    (those of plant sets have it always)."""
    seen = set()
    for arm in (ARM_FULL, ARM_QUASI_STATIC, ARM_FORCE):
        for filters in (True, False):
            layout = Layout(arm, filters, True)
            k = kernel.for_layout(layout)
            assert kernel.for_layout(Layout(arm, filters, False)).advance is k.advance
            seen.add(k.advance)
            coulomb = kernel.for_layout(Layout(arm, filters, True, True))
            assert coulomb.advance is not k.advance
            assert coulomb.advance_many is not k.advance_many
            assert coulomb.advance_set is k.advance_set
            seen.add(coulomb.advance)
            models = ModelParams(
                armature={ARM_FULL: "full", ARM_QUASI_STATIC: "quasi_static",
                          ARM_FORCE: "ideal_force"}[arm],
                current_loop="sampled_pi" if arm != ARM_FORCE else "ideal",
                sensors="quantised" if filters else "ideal", sensor_filters=filters)
            plant = Plant(PlantConfig(models=models))
            assert plant.size == layout.size == 4 + (arm == ARM_FULL) + 2 * filters
            # the right-hand side's indices: at rest with the filters settled on the
            # state, the filters do not move and the positions move with the rates
            rest = plant.initial_state(0.02, 0.0, 3.0, 1.5)
            f = plant.derivative(rest, 0.0)
            assert f[0] == 0.0 and f[2] == 1.5
            np.testing.assert_allclose(f[4 + (arm == ARM_FULL):], 0.0, atol=1e-9)
            # the step's indices: one period against solve_ivp on that right-hand side
            u = 0.5 if arm == ARM_FORCE else 3.0
            y0 = plant.initial_state(0.02, 0.1, 3.0, 1.5)
            fine = Plant(PlantConfig(models=models, integrator=IntegratorParams("exprk4", 64)))
            reference = solve_ivp(lambda t, y: plant.applied_derivative(y, plant.applied(u)),
                                  (0.0, 0.005), y0, method="DOP853", rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(fine.advance(y0, u, 0.005), reference.y[:, -1],
                                       rtol=1e-9, atol=1e-11)
    assert len(seen) == 12


@pytest.mark.parametrize("rigs", [1, 600])  # one chunk; the parallel entry point
def test_the_layout_without_coulomb_friction_gives_its_bits_at_zero_coulomb_force(rigs):
    """The default layout leaves the Coulomb term out; with Coulomb friction modelled at
    F_c = 0 the term is an exact zero: both give the same bits, over states that reach
    the end stops, both signs of the cart's velocity, and 0 m/s exactly."""
    rng = np.random.default_rng(11)
    viscous = FrictionParams(cart_viscous_ns_per_m=0.3, pivot_viscous_nms=2e-5,
                             cart_coulomb_n=0.0)
    plants = [Plant(PlantConfig(models=ModelParams(friction=model), friction=viscous))
              for model in ("viscous", "coulomb")]
    assert [p.layout.coulomb for p in plants] == [False, True]
    y = plants[0].initial_state(rng.uniform(-0.25, 0.15, rigs), rng.uniform(-1, 1, rigs),
                                rng.uniform(-7, 7, rigs), rng.uniform(-20, 20, rigs),
                                rng.uniform(-1, 1, rigs))
    y[: max(1, rigs // 10), 1] = 0.0
    u = rng.uniform(-12, 12, rigs)
    a, b = (p.advance(y, u, 0.005) for p in plants)
    np.testing.assert_array_equal(a.view(np.int64), b.view(np.int64))
    # and the term acts where it is modelled
    coulomb = Plant(PlantConfig(models=ModelParams(friction="coulomb"),
                                friction=dataclasses.replace(viscous, cart_coulomb_n=0.05)))
    assert not np.array_equal(coulomb.advance(y, u, 0.005), a)


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


def test_exponential_scheme_is_fourth_order_and_keeps_it_through_voltage_steps():
    """The hard part of the rig: a voltage step every period starts a 0.14 ms armature
    transient while the pendulum swings at 15 rad/s. Held voltage, measured: 2.9e-7,
    1.8e-8, 1.2e-9, 1.1e-10, 1.0e-11 rad/s at 1, 2, 4, 8, 16 steps per period (fourth
    order: 16 times less per halving, 11 near the reference's own error). A step every
    period: 2.5e-7, 1.6e-8, 2.4e-9, 1.4e-9, 3.3e-10: the same at 1 and 2 steps; from 4
    steps on, what L leaves out (the fast angle's own share, e^(2 lam t)) shows near
    1e-9."""
    config = PlantConfig(models=ModelParams(sensors="ideal", sensor_filters=False,
                                            end_stops=False))
    y0 = Plant(config).initial_state(0.0, 0.3, 2.0, 15.0, 0.0)
    held = _playback_errors(config, (1, 2, 4, 8, 16), y0, [6.0] * 20)
    assert all(a / b > 10 for a, b in zip(held, held[1:], strict=False)), held
    stepped = _playback_errors(config, (1, 2, 4, 8, 16), y0, [6.0, -6.0, 9.0, -3.0] * 5)
    assert stepped[0] < 3.5e-7 and stepped[1] < 2.5e-8 and stepped[4] < 1e-9, stepped
    assert stepped[0] < 1.2 * held[0] and stepped[1] < 1.2 * held[1], (stepped, held)
    assert all(a > b for a, b in zip(stepped, stepped[1:], strict=False)), stepped


@pytest.mark.parametrize("theta_dot", [0.0, 4.0, 8.0])
def test_a_voltage_step_adds_no_error_of_its_own(theta_dot):
    """One period from a settled current with and without a 10 V step, against rk4 at
    1280 steps: the step's 0.14 ms transient adds nothing measurable at 1 and 2 steps
    per period. (Measured while the scheme was built: 4e-9 to 1e-8 rad/s with the step
    against 1e-10 to 2e-9 without; first without s and the transient's push on the
    angle, then with L's constant armature rate but without q + delta r.)"""
    config = PlantConfig(models=ModelParams(end_stops=False))
    truth = Plant(dataclasses.replace(config, integrator=IntegratorParams("rk4", 1280)))
    y = truth.advance(truth.initial_state(0.0, 0.1, math.pi + 0.3, theta_dot), 2.0, 0.005)
    for n in (1, 2):
        plant = Plant(dataclasses.replace(config, integrator=IntegratorParams("exprk4", n)))
        errors = [abs(plant.advance(y, u, 0.005)[3] - truth.advance(y, u, 0.005)[3])
                  for u in (2.0, 12.0)]
        assert errors[1] < 1.5 * errors[0] + 1e-10, (n, errors)


def test_batch_and_single_rig_are_bit_identical():
    """A rig gets the same bits alone, in a vectorised loop body (four rigs a register)
    and in a loop's remainder, in the parallel path (more than two chunks) and the
    serial one."""
    plant = Plant(PlantConfig(integrator=IntegratorParams("exprk4", 2)))
    rigs = 2 * kernel_batch.CHUNK + 87
    starts = np.linspace(-0.1, 0.1, rigs)
    commands = np.linspace(-11, 11, rigs)
    batch = plant.initial_state(starts, 0.1, 3.0, 1.0)
    out = plant.advance(batch, commands, 0.005)
    few = plant.advance(batch[:7], commands[:7], 0.005)  # the serial path
    np.testing.assert_array_equal(few, out[:7])
    for k in (0, 3, 4, 6, kernel_batch.CHUNK - 1, kernel_batch.CHUNK, rigs - 2, rigs - 1):
        single = plant.advance(plant.initial_state(starts[k], 0.1, 3.0, 1.0), commands[k], 0.005)
        np.testing.assert_array_equal(out[k], single)

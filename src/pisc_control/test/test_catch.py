"""Catch gains: thesis Table 6.3, seed 001, LQR against the Riccati equation."""

import math

import numpy as np
import pytest
from scipy.linalg import solve_continuous_are

from pisc_control.catch import CatchParams, catch_force, catch_gain
from pisc_control.floatmath import wrap
from pisc_msgs_py.config import ConfigError
from pisc_model.dynamics import linearise_upright
from pisc_model.params import RigParams

RIG = RigParams()


def test_thesis_table_6_3_to_four_significant_digits():
    k = catch_gain(RIG, CatchParams())
    assert [float(f"{v:.4g}") for v in k] == [-2.771, -3.669, -19.29, -2.043]
    # Table 6.3 prints 5 digits: -2.7711, -3.6696, -19.291, -2.0432
    np.testing.assert_allclose(k, [-2.7711, -3.6696, -19.291, -2.0432], rtol=5e-5)


def test_seed001_feedback_with_a_repeated_pole():
    """Seed 001: F = 74.698 th + 16.587 th_d + 10.194 x + 9.1743 x_d for -1 +- sqrt(3) j, -5, -5."""
    rig = RigParams(cart_mass_kg=2.0, pendulum_mass_kg=0.1, pendulum_com_m=0.5,
                    pendulum_inertia_kgm2=0.0, gravity_mps2=9.81)
    params = CatchParams(poles=(-1.0, -1.0, -5.0, -5.0),
                         poles_imag=(math.sqrt(3), -math.sqrt(3), 0.0, 0.0))
    f_gains = -catch_gain(rig, params)  # f = -K z = F z
    np.testing.assert_allclose(f_gains, [10.194, 9.1743, 74.698, 16.587], rtol=5e-5)


def test_placed_poles_are_the_closed_loop_eigenvalues():
    a, b = linearise_upright(RIG)
    for poles in ([-15.0, -11.0, -2.0, -1.5], [-4.0, -4.0, -3.0, -2.0]):
        k = catch_gain(RIG, CatchParams(poles=tuple(poles)))
        eig = np.sort(np.linalg.eigvals(a - b @ k.reshape(1, 4)).real)
        np.testing.assert_allclose(eig, np.sort(poles), rtol=1e-6)


def test_lqr_gain_solves_the_riccati_equation():
    q, r = (100.0, 1.0, 10.0, 1.0), 0.5
    k = catch_gain(RIG, CatchParams(design="lqr", lqr_q=q, lqr_r=r))
    a, b = linearise_upright(RIG)
    p = solve_continuous_are(a, b, np.diag(q), np.array([[r]]))
    np.testing.assert_allclose(k, (b.T @ p / r).ravel(), rtol=1e-6)


def test_uncontrollable_linearisation_is_refused():
    with pytest.raises(ConfigError, match="not controllable"):
        catch_gain(RigParams(gravity_mps2=0.0), CatchParams())


@pytest.mark.parametrize("kwargs,match", [
    (dict(poles=(-1.0, -2.0, 3.0, -4.0)), "negative real part"),
    (dict(poles=(-1.0, -2.0, -3.0)), "expected 4 values"),
    (dict(poles=(-1.0, -1.0, -5.0, -5.0), poles_imag=(1.0, 1.0, 0.0, 0.0)), "conjugate pairs"),
])
def test_bad_pole_sets_are_refused(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        CatchParams(**kwargs)


def test_force_sign_and_wrap():
    k = catch_gain(RIG, CatchParams())
    # pendulum leaning towards +x: push the cart towards +x (SPEC section 1)
    assert catch_force(*k, 0.0, 0.0, 0.05, 0.0, 0.0) > 0
    # the angle from the nearest upright, as the supervisor gives it
    assert catch_force(*k, 0.0, 0.0, wrap(0.05 + 4 * math.pi), 0.0, 0.0) == pytest.approx(
        catch_force(*k, 0.0, 0.0, 0.05, 0.0, 0.0), rel=1e-12)
    assert catch_force(*k, 0.02, 0.0, 0.0, 0.0, 0.02) == 0.0


def test_a_recorded_gain_is_used_only_when_the_design_gives_it_up_to_rounding():
    """A bag's K (another machine's LAPACK: a few ulps off) replaces the designed K; a K
    of another design does not."""
    designed = catch_gain(RIG, CatchParams())
    ulps = tuple(float(np.nextafter(np.nextafter(k, 0.0), 0.0)) for k in designed)  # 2 ulps
    assert tuple(catch_gain(RIG, CatchParams(recorded_gain=ulps))) == ulps
    assert not np.array_equal(designed, ulps)
    other = tuple(float(k) * (1.0 + 1e-6) for k in designed)  # not this design's
    np.testing.assert_array_equal(catch_gain(RIG, CatchParams(recorded_gain=other)), designed)
    # changed poles with the old recording's K: the new design's K
    moved = catch_gain(RIG, CatchParams(poles=(-15.0, -11.0, -3.0, -2.4), recorded_gain=ulps))
    np.testing.assert_array_equal(
        moved, catch_gain(RIG, CatchParams(poles=(-15.0, -11.0, -3.0, -2.4))))


@pytest.mark.parametrize("gain", [(1.0, 2.0, 3.0), (1.0, 2.0, math.nan, 4.0)])
def test_a_malformed_recorded_gain_is_refused(gain):
    with pytest.raises(ConfigError, match=r"catch.recorded_gain = .*expected 4 finite gains"):
        CatchParams(recorded_gain=gain)


def test_governor_rows_against_a_simulation_of_the_sampled_loop():
    """Row j gives the cart and the set-point after 3 j periods of a loop simulated here
    period by period: the zero-order hold of the linearisation (scipy.signal.
    cont2discrete), the IR reading through its RC low-pass, the estimator over arrays
    (differences over 7 periods, low-passed) and the catch f = -K z on what it gives; the
    rig moving at the estimated velocities before the start."""
    from scipy.signal import cont2discrete

    from pisc_control.catch import GOVERNOR_STRIDE, governor_rows
    from pisc_control.estimator import EstimatorParams, EstimatorState, estimator_update
    from pisc_model.params import MotorParams

    k = catch_gain(RIG, CatchParams(poles=(-14.0, -4.8, -4.0, -3.5)))
    a, b = linearise_upright(RIG)
    ts = 0.005
    phi, gamma, *_ = cont2discrete((a, b, np.eye(4), np.zeros((4, 1))), ts, "zoh")
    fpa = MotorParams().force_per_amp
    assert fpa == pytest.approx(0.0637 / 0.032)
    est = EstimatorParams(difference_periods=7, velocity_filter_hz=15.8)
    ir_hz = 10.26
    rows = governor_rows(RIG, k, ts, 1.5, fpa, 7, 15.8, ir_hz)
    assert rows.shape == (1 + 300 // GOVERNOR_STRIDE, 8)
    np.testing.assert_array_equal(rows[0, :4], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(rows[0, 4:], -k / fpa, rtol=1e-12)

    r = 0.03  # the catch's reference
    w = np.array([0.02, 0.1, 0.05, -0.3])  # x - r, x_dot, theta, theta_dot as seen
    z = w + np.array([r, 0.0, 0.0, 0.0])  # the true state, as the rows assume at the start
    c_ir = math.exp(-2 * math.pi * ir_hz * ts)
    reading = z[0]
    past_x = tuple(z[0] - i * ts * z[1] for i in range(7, 0, -1))
    past_th = tuple(z[2] - i * ts * z[3] for i in range(7, 0, -1))
    state = EstimatorState(past_x[-1], past_th[-1], z[1], z[3], past_x[:-1], past_th[:-1])
    for step in range(301):
        state, v_x, v_th = estimator_update(est, ts, state, reading, z[2])
        force = -(k[0] * (reading - r) + k[1] * v_x + k[2] * z[2] + k[3] * v_th)
        if step % GOVERNOR_STRIDE == 0:
            row = rows[step // GOVERNOR_STRIDE]
            assert r + row[:4] @ w == pytest.approx(z[0], abs=1e-12)
            assert row[4:] @ w == pytest.approx(force / fpa, abs=1e-12)
        reading = c_ir * reading + (1 - c_ir) * z[0]
        z = phi @ z + gamma[:, 0] * float(force)


def test_the_governors_exponential_is_scipys():
    """The fixed-order exponential the governor uses (the same bits on every CPU) agrees
    with scipy's Pade approximant to the last digits, on the period's block of the thesis
    rig and on a block 40 times larger (which needs squaring)."""
    from scipy.linalg import expm

    from pisc_control.catch import _expm

    a, b = linearise_upright(RIG)
    for period in (0.005, 0.2):
        block = np.zeros((5, 5))
        block[:4, :4], block[:4, 4:] = a * period, b * period
        np.testing.assert_allclose(_expm(block), expm(block), rtol=1e-13, atol=1e-14)

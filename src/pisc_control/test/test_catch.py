"""Catch gains: thesis Table 6.3, seed 001, LQR against the Riccati equation."""

import math

import numpy as np
import pytest
from scipy.linalg import solve_continuous_are

from pisc_control.catch import CatchParams, catch_force, catch_gain
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
    assert catch_force(k, 0.0, 0.0, 0.05, 0.0) > 0
    assert catch_force(k, 0.0, 0.0, 0.05 + 4 * math.pi, 0.0) == pytest.approx(
        catch_force(k, 0.0, 0.0, 0.05, 0.0), rel=1e-12)
    assert catch_force(k, 0.02, 0.0, 0.0, 0.0, target_m=0.02) == 0.0


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


def test_governor_rows_against_an_independent_discretisation():
    """Row j is e_1 and -K / (k_m / r) times (Phi - Gamma K)^(3 j), with Phi, Gamma the
    zero-order hold of the linearisation, here from scipy.signal.cont2discrete."""
    from scipy.signal import cont2discrete

    from pisc_control.catch import GOVERNOR_STRIDE, governor_rows
    from pisc_model.params import MotorParams

    k = catch_gain(RIG, CatchParams())
    a, b = linearise_upright(RIG)
    phi, gamma, *_ = cont2discrete((a, b, np.eye(4), np.zeros((4, 1))), 0.005, "zoh")
    closed = phi - gamma @ k.reshape(1, 4)
    fpa = MotorParams().force_per_amp
    assert fpa == pytest.approx(0.0637 / 0.032)
    rows = governor_rows(RIG, k, 0.005, 1.5, fpa)
    assert rows.shape == (1 + 300 // GOVERNOR_STRIDE, 8)
    np.testing.assert_array_equal(rows[0, :4], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(rows[0, 4:], -k / fpa, rtol=1e-12)
    for j in (1, 10, 100):
        power = np.linalg.matrix_power(closed, GOVERNOR_STRIDE * j)
        np.testing.assert_allclose(rows[j, :4], power[0], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rows[j, 4:], -(k @ power) / fpa, rtol=1e-9, atol=1e-12)

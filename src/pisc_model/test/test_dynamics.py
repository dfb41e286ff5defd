"""Cart-pole model: SPEC section 6 numbers and independent checks of (3.3)-(3.6), (2.54)."""

import math

import numpy as np
import pytest

from pisc_model.dynamics import accelerations, energy, linearise_upright, wrap_to_upright
from pisc_model.params import RigParams

RIG = RigParams()
SEED001 = RigParams(cart_mass_kg=2.0, pendulum_mass_kg=0.1, pendulum_com_m=0.5,
                    pendulum_inertia_kgm2=0.0, gravity_mps2=9.81)


def sig4(value: float) -> float:
    return float(f"{value:.4g}")


def test_linearisation_reproduces_thesis_6_3():
    a, b = linearise_upright(RIG)
    assert sig4(a[1, 2]) == -0.1630
    assert sig4(a[3, 2]) == 86.47
    assert sig4(b[1, 0]) == 2.100
    assert sig4(b[3, 0]) == -18.21
    # The thesis prints 5 significant digits: 0.16302, 86.469, 2.1002, -18.210.
    np.testing.assert_allclose([a[1, 2], a[3, 2], b[1, 0], b[3, 0]],
                               [-0.16302, 86.469, 2.1002, -18.210], rtol=5e-5, atol=0)


def test_open_loop_poles_thesis_and_seed001():
    for rig, pole in ((RIG, 9.2989), (SEED001, 4.539)):
        a, _ = linearise_upright(rig)
        eig = np.sort(np.linalg.eigvals(a).real)
        np.testing.assert_allclose(eig, [-pole, 0.0, 0.0, pole], atol=5e-4)


def mass_matrix_accelerations(rig, theta, theta_dot, force):
    """(2.26)-(2.29) solved directly: M(q) q_dd = tau - C q_d - G."""
    m, l, mm = rig.pendulum_mass_kg, rig.pendulum_com_m, rig.cart_mass_kg
    c, s = math.cos(theta), math.sin(theta)
    mq = np.array([[mm + m, m * l * c], [m * l * c, m * l * l + rig.pendulum_inertia_kgm2]])
    rhs = np.array([force + m * l * theta_dot**2 * s, m * rig.gravity_mps2 * l * s])
    return np.linalg.solve(mq, rhs)


@pytest.mark.parametrize("rig", [RIG, SEED001])
def test_accelerations_match_the_mass_matrix_form(rig):
    rng = np.random.default_rng(1)
    for _ in range(50):
        theta, theta_dot, force = rng.uniform(-7, 7), rng.uniform(-15, 15), rng.uniform(-3, 3)
        x_dd, th_dd = accelerations(rig, theta, theta_dot, force)
        np.testing.assert_allclose([x_dd, th_dd],
                                   mass_matrix_accelerations(rig, theta, theta_dot, force),
                                   rtol=1e-12, atol=1e-12)


def test_energy_rate_is_x_dot_times_force():
    """(2.57): dE/dt = x_dot f along the motion given by (3.3), (3.5)."""
    rng = np.random.default_rng(2)
    m, l, i = RIG.pendulum_mass_kg, RIG.pendulum_com_m, RIG.pendulum_inertia_kgm2
    for _ in range(50):
        x_d, th, th_d, f = (rng.uniform(-1, 1), rng.uniform(-7, 7), rng.uniform(-15, 15),
                            rng.uniform(-3, 3))
        x_dd, th_dd = accelerations(RIG, th, th_d, f)
        c, s = math.cos(th), math.sin(th)
        de_dt = (RIG.a2 * x_d * x_dd + m * l * (x_dd * th_d * c + x_d * th_dd * c
                                                 - x_d * th_d**2 * s)
                 + (i + m * l * l) * th_d * th_dd - RIG.mgl * s * th_d)
        assert de_dt == pytest.approx(x_d * f, rel=1e-9, abs=1e-12)


def test_energy_reference_points():
    assert energy(RIG, 0.0, 0.0, 0.0) == 0.0
    assert energy(RIG, 0.0, math.pi, 0.0) == pytest.approx(-2 * RIG.mgl, rel=1e-15)
    assert -2 * RIG.mgl == pytest.approx(-0.017905, rel=1e-4)


def test_linearisation_is_the_jacobian_of_the_model():
    a, b = linearise_upright(RIG)
    h = 1e-6
    x_dd_th = (accelerations(RIG, h, 0.0, 0.0)[0] - accelerations(RIG, -h, 0.0, 0.0)[0]) / (2 * h)
    th_dd_th = (accelerations(RIG, h, 0.0, 0.0)[1] - accelerations(RIG, -h, 0.0, 0.0)[1]) / (2 * h)
    x_dd_f, th_dd_f = accelerations(RIG, 0.0, 0.0, 1.0)
    np.testing.assert_allclose([a[1, 2], a[3, 2], b[1, 0], b[3, 0]],
                               [x_dd_th, th_dd_th, x_dd_f, th_dd_f], rtol=1e-7)


def test_extra_cart_mass_enters_the_cart_row_only():
    extra = 0.01
    x_dd, th_dd = accelerations(RIG, 0.3, 2.0, 1.0, extra)
    heavier = RigParams(cart_mass_kg=RIG.cart_mass_kg + extra)
    np.testing.assert_allclose((x_dd, th_dd), accelerations(heavier, 0.3, 2.0, 1.0), rtol=1e-14)


def test_accelerations_broadcast_over_a_batch():
    theta = np.linspace(-3, 3, 7).reshape(7, 1)
    force = np.array([-1.0, 0.0, 1.0])
    x_dd, th_dd = accelerations(RIG, theta, 0.5, force)
    assert x_dd.shape == (7, 3)
    assert th_dd[2, 0] == accelerations(RIG, float(theta[2, 0]), 0.5, -1.0)[1]


@pytest.mark.parametrize("theta,expected", [
    (0.0, 0.0), (0.1, 0.1), (2 * math.pi - 0.1, -0.1), (4 * math.pi + 0.2, 0.2),
    (-2 * math.pi + 0.3, 0.3), (math.pi - 1e-9, math.pi - 1e-9)])
def test_wrap_to_upright(theta, expected):
    assert wrap_to_upright(theta) == pytest.approx(expected, abs=1e-12)

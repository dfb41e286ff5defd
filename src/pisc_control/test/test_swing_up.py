"""Swing-up laws: (3.30) and its gain condition (3.29), and the energy pump."""

import math

import numpy as np
import pytest

from pisc_control.swing_up import (
    SwingUpParams,
    check_gain_condition,
    gain_condition,
    rig_pendulum_energy,
    swing_up_force,
)
from pisc_msgs_py.config import ConfigError
from pisc_model.dynamics import accelerations, energy
from pisc_model.params import RigParams

RIG = RigParams()
THESIS = SwingUpParams()


def test_thesis_gains_satisfy_3_29_with_the_published_numbers():
    ratio, bound = gain_condition(RIG, THESIS)
    assert round(ratio, 5) == 0.01235
    assert round(bound, 5) == 0.00867
    check_gain_condition(RIG, THESIS)


def test_gains_breaking_3_29_are_refused_with_the_condition_named():
    with pytest.raises(ConfigError, match=r"swing_up.k_v / swing_up.k_e .* \(3.29\)"):
        check_gain_condition(RIG, SwingUpParams(k_v=0.05, k_e=8.1))


def test_energy_target_raises_the_bound():
    ratio, bound = gain_condition(RIG, SwingUpParams(energy_target_j=0.002))
    assert bound == pytest.approx(RIG.a2 * (2 * RIG.mgl + 0.002))


def test_law_at_a_worked_state():
    x, x_d, th, th_d = 0.03, -0.2, 2.5, 4.0
    m, l, i, g = RIG.pendulum_mass_kg, RIG.pendulum_com_m, RIG.pendulum_inertia_kgm2, 9.81
    a1 = m * m * l * l / (m * l * l + i)
    a2 = RIG.cart_mass_kg + m
    e = (0.5 * a2 * x_d**2 + m * l * x_d * th_d * math.cos(th)
         + 0.5 * (i + m * l * l) * th_d**2 + m * g * l * (math.cos(th) - 1))
    den = a2 - a1 * math.cos(th) ** 2
    expected = ((0.1 * math.sin(th) * (a1 * g * math.cos(th) - m * l * th_d**2)
                 - den * (55.5 * x + 1.55 * x_d)) / (0.1 + den * 8.1 * e))
    assert swing_up_force(RIG, THESIS, x, x_d, th, th_d) == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("gains", [THESIS, SwingUpParams(k_v=0.008, k_x=6.3, k_delta=0.087,
                                                         k_e=0.47, energy_target_j=0.0012,
                                                         target_m=-0.04)])
def test_lyapunov_derivative_is_minus_k_delta_x_dot_squared(gains):
    """(3.31): with f from (3.30) and the dynamics (3.3), V_dot = -k_delta x_dot^2."""
    rng = np.random.default_rng(3)
    for _ in range(100):
        x, x_d, th, th_d = (rng.uniform(-0.2, 0.1), rng.uniform(-1, 1), rng.uniform(-7, 7),
                            rng.uniform(-12, 12))
        f = swing_up_force(RIG, gains, x, x_d, th, th_d)
        x_dd, _ = accelerations(RIG, th, th_d, f)
        e = energy(RIG, x_d, th, th_d) - gains.energy_target_j
        v_dot = (gains.k_e * e * x_d * f + gains.k_v * x_d * x_dd
                 + gains.k_x * (x - gains.target_m) * x_d)
        assert v_dot == pytest.approx(-gains.k_delta * x_d**2, rel=1e-7, abs=1e-12)


def test_denominator_stays_positive_at_the_boundary_of_3_29():
    """Just inside (3.29) the force is finite for every state, including hanging at rest."""
    bound = 2 * RIG.mgl * RIG.a2
    gains = SwingUpParams(k_v=0.1, k_e=0.1 / (bound * (1 + 1e-9)))
    rng = np.random.default_rng(4)
    states = rng.uniform([-0.2, -2, -10, -30], [0.2, 2, 10, 30], size=(20000, 4))
    forces = swing_up_force(RIG, gains, *states.T)
    assert np.all(np.isfinite(forces))
    assert np.isfinite(swing_up_force(RIG, gains, 0.01, 0.0, math.pi, 0.0))


PUMP = SwingUpParams(law="energy_pump", pump_gain=3.0, pump_accel_mps2=2.5, track_k_x=6.0,
                     track_k_v=2.5, energy_target_j=0.0005, target_m=0.02)


def test_energy_pump_at_a_worked_state():
    """The law written out by hand from its docstring, with the thesis rig's numbers."""
    x, x_d, th, th_d = 0.03, -0.2, 2.5, 4.0
    m, l, i, g = RIG.pendulum_mass_kg, RIG.pendulum_com_m, RIG.pendulum_inertia_kgm2, 9.81
    j = i + m * l * l
    e_p = 0.5 * j * th_d**2 + m * g * l * (math.cos(th) - 1)
    error = (0.0005 - e_p) / (2 * m * g * l)
    u = 3.0 * error * th_d * math.cos(th) / math.sqrt(m * g * l / j)
    a = -2.5 * max(-1.0, min(1.0, u)) - 6.0 * (x - 0.02) - 2.5 * x_d
    a1 = m * m * l * l / j
    a2 = RIG.cart_mass_kg + m
    expected = ((a2 - a1 * math.cos(th) ** 2) * a + a1 * g * math.sin(th) * math.cos(th)
                - m * l * th_d**2 * math.sin(th))
    assert swing_up_force(RIG, PUMP, x, x_d, th, th_d) == pytest.approx(expected, rel=1e-13)


def test_energy_pump_gives_the_cart_the_acceleration_it_asks_for_and_pumps_towards_e_ref():
    """Through (3.3) the cart's acceleration is the law's a; without the track terms the
    pendulum's energy rises below E_ref and falls above it, at most at m l a_max |theta_dot|."""
    gains = SwingUpParams(law="energy_pump", pump_gain=50.0, pump_accel_mps2=2.0,
                          track_k_x=0.0, track_k_v=0.0, energy_target_j=0.0)
    rng = np.random.default_rng(5)
    states = rng.uniform([-0.2, -1, -7, -12], [0.1, 1, 7, 12], size=(2000, 4))
    x, x_d, th, th_d = states.T
    f = swing_up_force(RIG, gains, x, x_d, th, th_d)
    x_dd, th_dd = accelerations(RIG, th, th_d, f)
    j = RIG.pendulum_inertia_kgm2 + RIG.ml * RIG.pendulum_com_m
    e_dot = j * th_d * th_dd - RIG.mgl * np.sin(th) * th_d  # d/dt of pendulum_energy
    e_p = rig_pendulum_energy(RIG, th, th_d)
    assert np.all(np.abs(x_dd) <= 2.0 + 1e-9)
    assert np.all(np.sign(e_dot[np.abs(e_dot) > 1e-12]) == -np.sign(e_p)[np.abs(e_dot) > 1e-12])
    assert np.all(np.abs(e_dot) <= RIG.ml * 2.0 * np.abs(th_d) + 1e-12)


def test_energy_pump_leaves_a_rig_hanging_at_rest_at_its_target_alone():
    assert swing_up_force(RIG, PUMP, 0.02, 0.0, math.pi, 0.0) == pytest.approx(0.0, abs=1e-15)


def test_energy_pump_has_no_gain_condition():
    check_gain_condition(RIG, SwingUpParams(law="energy_pump", k_v=1e-6, k_e=10.0))
    with pytest.raises(ConfigError, match="swing_up.law"):
        from pisc_msgs_py.config import from_flat

        from_flat(SwingUpParams, {"swing_up.law": "bang_bang"}, "swing_up")


def test_the_track_guard_brakes_a_cart_that_would_stop_beyond_its_limits():
    """Guard limits (-0.225 + 0.02, 0.125 - 0.02): at x = 0.05 m a cart at +0.6 m/s
    braked at 3 m/s^2 stops at 0.05 + 0.36 / 6 = 0.11 m > 0.105 m: braked, whatever the
    pump asks; at +0.5 m/s it stops at 0.0917 m: the law's own acceleration."""
    gains = SwingUpParams(law="energy_pump", pump_gain=3.0, pump_accel_mps2=2.5,
                          track_k_x=6.0, track_k_v=2.5, guard_accel_mps2=3.0,
                          guard_margin_m=0.02)
    limits = (-0.225, 0.125)
    th, th_d = 2.0, 5.0
    for x_d, braked in ((0.6, True), (0.5, False), (-0.6, False)):
        f = swing_up_force(RIG, gains, 0.05, x_d, th, th_d, 0.0, limits)
        x_dd, _ = accelerations(RIG, th, th_d, f)
        free = accelerations(RIG, th, th_d, swing_up_force(
            RIG, SwingUpParams(**{**gains.__dict__, "guard_accel_mps2": 0.0}), 0.05, x_d, th,
            th_d, 0.0, limits))[0]
        if braked:
            assert x_dd == pytest.approx(-3.0, rel=1e-12)
        else:
            assert x_dd == pytest.approx(free, rel=1e-12)
    # at the far end, moving outwards: braked the other way
    f = swing_up_force(RIG, gains, -0.15, -0.6, th, th_d, 0.0, limits)  # stops at -0.21
    assert accelerations(RIG, th, th_d, f)[0] == pytest.approx(3.0, rel=1e-12)

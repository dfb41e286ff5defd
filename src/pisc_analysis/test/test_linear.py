"""Linear analysis against SPEC section 6 and python-control."""

import math

import numpy as np
import pytest
import sympy as sp

from pisc_analysis.linear import (
    ackermann_gain,
    bass_gura_gain,
    characteristic_coefficients,
    closed_loop_poles,
    controllability,
    equilibria,
    linearise,
    lqr_gain,
    place_gain,
)
from pisc_analysis.symbolic import cart_pole
from pisc_model.dynamics import linearise_upright
from pisc_model.params import RigParams

THESIS_POLES = [-15.0, -11.0, -2.0, -1.5]
SEED001_POLES = [-1 + math.sqrt(3) * 1j, -1 - math.sqrt(3) * 1j, -5.0, -5.0]


@pytest.fixture(scope="module")
def thesis():
    system, s = cart_pole(with_inertia=True)
    values = {s.M: 0.4735, s.m: 0.01055, s.l: 0.0865, s.I: 2.631524e-5, s.g: 9.81}
    return system, s, values


@pytest.fixture(scope="module")
def seed001():
    system, s = cart_pole(with_inertia=False)
    return system, s, {s.M: 2.0, s.m: 0.1, s.l: 0.5, s.g: 9.81}


def test_linearisation_reproduces_thesis_6_3_and_the_hand_model(thesis):
    system, _, values = thesis
    a, b = linearise(system, values)
    np.testing.assert_allclose([a[1, 2], a[3, 2], b[1, 0], b[3, 0]],
                               [-0.16302, 86.469, 2.1002, -18.210], rtol=5e-5)
    a_hand, b_hand = linearise_upright(RigParams())
    np.testing.assert_allclose(a, a_hand, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(b, b_hand, rtol=1e-13)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(a).real), [-9.2989, 0, 0, 9.2989],
                               atol=5e-5)


def test_equilibria_are_n_pi_with_any_x_and_none_under_a_constant_force(thesis):
    system, s, values = thesis
    eq = equilibria(system, values)
    x, theta = system.q
    assert eq.free == (x,)
    assert sorted(float(sol[theta]) for sol in eq.solutions) == [0.0, pytest.approx(math.pi)]
    # seed 000 solved each equation alone with F = 0.1 and found spurious angles
    assert equilibria(system, values, {s.f: 0.1}).solutions == []


def test_linearisation_at_hanging_flips_the_pendulum_rows(seed001):
    system, _, values = seed001
    a, b = linearise(system, values, state=[0.0, 0.0, math.pi, 0.0])
    # hanging: theta'' = -(M+m) g / (M l) dtheta + f / (M l)
    assert a[3, 2] == pytest.approx(-2.1 * 9.81 / 1.0)
    assert b[3, 0] == pytest.approx(1.0)
    assert a[1, 2] == pytest.approx(-0.1 * 9.81 / 2.0)


def test_seed_001_open_loop_and_its_feedback(seed001):
    system, _, values = seed001
    a, b = linearise(system, values)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(a).real), [-4.539, 0, 0, 4.539],
                               atol=5e-4)
    # seed 001 (21) for its numbers: s^4 - 20.601 s^2
    np.testing.assert_allclose(characteristic_coefficients(a), [0, -20.601, 0, 0], atol=1e-9)
    k = bass_gura_gain(a, b, SEED001_POLES)
    # F = -K z = 74.698 theta + 16.587 theta_dot + 10.194 x + 9.1743 x_dot
    np.testing.assert_allclose(-k, [10.194, 9.1743, 74.698, 16.587], rtol=5e-5)
    np.testing.assert_allclose(closed_loop_poles(a, b, k), np.sort_complex(SEED001_POLES),
                               atol=1e-8)


def test_three_pole_placements_agree_on_table_6_3(thesis):
    system, _, values = thesis
    a, b = linearise(system, values)
    gains = [f(a, b, THESIS_POLES) for f in (bass_gura_gain, ackermann_gain, place_gain)]
    for k in gains:
        np.testing.assert_allclose(k, [-2.7711, -3.6696, -19.291, -2.0432], rtol=5e-5)
        np.testing.assert_allclose(k, gains[2], rtol=1e-9)


def test_controllability_determinant_is_thesis_3_45(thesis):
    system, _, values = thesis
    a, b = linearise(system, values)
    c = controllability(a, b)
    rig = RigParams()
    expected = rig.gravity_mps2**2 * rig.a1**4 / (rig.ml**4 * (rig.a1 - rig.a2) ** 4)
    assert c.rank == 4
    assert c.determinant == pytest.approx(expected, rel=1e-9)


def test_lqr_gain_is_stabilising_and_matches_the_riccati_equation(thesis):
    from scipy.linalg import solve_continuous_are

    system, _, values = thesis
    a, b = linearise(system, values)
    q = np.diag([1.0, 1.0, 1.0, 1.0])
    k = lqr_gain(a, b, q, 1.0)
    p = solve_continuous_are(a, b, q, np.eye(1))
    np.testing.assert_allclose(k, (b.T @ p).ravel(), rtol=1e-8)
    assert np.all(closed_loop_poles(a, b, k).real < 0)


def test_refusals_name_what_is_wrong():
    a = np.diag([1.0, 2.0])
    with pytest.raises(ValueError, match="not controllable.*rank 1 < 2"):
        bass_gura_gain(a, np.array([1.0, 0.0]), [-1.0, -2.0])
    with pytest.raises(ValueError, match="expected 2 poles, got 3"):
        ackermann_gain(a, np.array([1.0, 1.0]), [-1.0, -2.0, -3.0])
    with pytest.raises(ValueError, match="conjugate pairs"):
        place_gain(a, np.array([1.0, 1.0]), [-1.0 + 1j, -2.0])
    system, s = cart_pole()
    with pytest.raises(ValueError, match="expected 4 states and 1 inputs, got 2 and 1"):
        linearise(system, {s.M: 1.0}, state=[0.0, 0.0])


def test_symbolic_jacobians_at_upright_are_seed_000s_24_and_25():
    from pisc_analysis.linear import jacobians

    system, s = cart_pole(with_inertia=False)
    a_sym, b_sym = jacobians(system)
    origin = {v: 0 for v in (*system.state(), s.f)}
    a0 = a_sym.subs(origin).applyfunc(sp.simplify)
    b0 = b_sym.subs(origin).applyfunc(sp.simplify)
    # seed 000 (24)-(25), M1 = M (cart), M2 = m (bob), order [x, x_dot, theta, theta_dot]
    assert sp.simplify(a0[3, 2] - s.g * (s.M + s.m) / (s.l * s.M)) == 0
    assert sp.simplify(a0[1, 2] + s.g * s.m / s.M) == 0
    assert sp.simplify(b0[3, 0] + 1 / (s.l * s.M)) == 0
    assert sp.simplify(b0[1, 0] - 1 / s.M) == 0
    assert a0[0, 1] == 1 and a0[2, 3] == 1
    assert sum(1 for e in a0 if e != 0) == 4

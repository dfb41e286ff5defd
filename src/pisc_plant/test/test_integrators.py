"""Exponential integrator: phi functions, exactness on linear problems, order, RK4 limit."""

import math

import numpy as np
import pytest

from pisc_plant.integrators import Etdrk4, phi_functions, rk4_step


@pytest.mark.parametrize("z", [-50.0, -7.0, -1.5, -1.0, -0.999, -0.3, -1e-4, 0.0, 1e-6, 0.5, 2.0])
def test_phi_functions_match_their_definitions(z):
    p1, p2, p3 = phi_functions(np.array(z))
    if abs(z) > 0.5:
        ez = math.exp(z)
        assert p1 == pytest.approx((ez - 1) / z, rel=1e-13)
        assert p2 == pytest.approx((ez - 1 - z) / z**2, rel=1e-13)
        assert p3 == pytest.approx((ez - 1 - z - z * z / 2) / z**3, rel=1e-12)
    else:  # Taylor series, computed independently with exact rational coefficients
        assert p1 == pytest.approx(sum(z**j / math.factorial(j + 1) for j in range(30)), rel=1e-15)
        assert p3 == pytest.approx(sum(z**j / math.factorial(j + 3) for j in range(30)), rel=1e-15)


def test_phi_functions_are_continuous_at_the_series_switch():
    below = phi_functions(np.array([-1.0 + 1e-12]))
    above = phi_functions(np.array([-1.0 - 1e-12]))
    for a, b in zip(below, above, strict=True):
        assert a[0] == pytest.approx(b[0], rel=1e-11)


def test_exact_for_a_stiff_linear_scalar_at_any_step():
    """y' = lam y + c has y(h) = e^(lam h) y0 + c (e^(lam h) - 1) / lam."""
    lam, c, y0 = -7000.0, 5735.0, 0.3
    for h in (1e-4, 1e-3, 5e-3):
        y = Etdrk4.for_step(np.array([lam]), h).step(lambda y: np.full_like(y, c), np.array([y0]))
        exact = math.exp(lam * h) * y0 + c * (math.exp(lam * h) - 1) / lam
        assert y[0] == pytest.approx(exact, rel=1e-14)


def test_reduces_to_classical_rk4_without_a_linear_part():
    def rhs(y):
        return np.array([y[1], -math.sin(y[0])])

    y0 = np.array([1.0, 0.3])
    etd = Etdrk4.for_step(np.zeros(2), 0.01).step(rhs, y0)
    np.testing.assert_allclose(etd, rk4_step(rhs, y0, 0.01), rtol=1e-15, atol=1e-16)


def _pendulum_with_fast_mode(lam_fast):
    lam = np.array([0.0, 0.0, lam_fast])

    def nonlinear(y):
        return np.array([y[1], -math.sin(y[0]) + 0.1 * y[2], -lam_fast * math.cos(y[0])])

    def solve(scheme_for, h, t_end=1.0):
        scheme = scheme_for(lam, h)
        y = np.array([1.0, 0.0, 0.5])
        for _ in range(round(t_end / h)):
            y = scheme.step(nonlinear, y)
        return y

    return solve


def test_fourth_order_when_the_fast_mode_is_resolved():
    solve = _pendulum_with_fast_mode(-20.0)
    reference = solve(Etdrk4.for_step, 1e-4)
    errors = [np.abs(solve(Etdrk4.for_step, h) - reference).max() for h in (0.02, 0.01, 0.005)]
    assert errors[0] / errors[1] > 12 and errors[1] / errors[2] > 12, errors


def test_stable_and_convergent_but_order_reduced_when_stiff():
    """Cox-Matthews loses order when the fast mode is slaved (h |lam| >> 1): documented
    in IntegratorParams; here the error still falls with h and nothing blows up."""
    solve = _pendulum_with_fast_mode(-2000.0)
    reference = solve(Etdrk4.for_step, 1e-4)
    errors = [np.abs(solve(Etdrk4.for_step, h) - reference)[:2].max()
              for h in (0.05, 0.02, 0.01, 0.005)]
    assert all(np.isfinite(errors)) and errors[0] < 1e-2
    assert errors[0] > errors[1] > errors[2] > errors[3]
    assert errors[2] / errors[3] < 8  # not fourth order in this regime

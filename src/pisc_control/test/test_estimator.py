"""Backward differences (4.7), (4.9) and the optional filter."""

import math

import numpy as np
import pytest

from pisc_control.estimator import EstimatorParams, EstimatorState, estimator_update

TS = 0.005


def test_first_sample_has_zero_velocity_then_backward_differences():
    p = EstimatorParams()
    s, xd, thd = estimator_update(p, TS, EstimatorState(), 0.10, math.pi)
    assert (xd, thd) == (0.0, 0.0)
    s, xd, thd = estimator_update(p, TS, s, 0.101, math.pi + 0.0015708)
    assert xd == pytest.approx((0.101 - 0.10) / TS, rel=1e-12)
    assert thd == pytest.approx(0.0015708 / TS, rel=1e-9)


def test_filtered_difference_is_a_first_order_low_pass():
    p = EstimatorParams(velocity_filter_hz=20.0)
    a = math.exp(-2 * math.pi * 20.0 * TS)
    s, _, _ = estimator_update(p, TS, EstimatorState(), 0.0, 0.0)
    s, xd1, _ = estimator_update(p, TS, s, 0.001, 0.0)
    s, xd2, _ = estimator_update(p, TS, s, 0.002, 0.0)
    assert xd1 == pytest.approx((1 - a) * 0.2)
    assert xd2 == pytest.approx(a * xd1 + (1 - a) * 0.2)


def test_broadcasts_over_a_batch():
    s, _, _ = estimator_update(EstimatorParams(), TS, EstimatorState(), np.zeros(3), np.zeros(3))
    s, xd, _ = estimator_update(EstimatorParams(), TS, s, np.array([0.0, 0.005, 0.01]),
                                np.zeros(3))
    np.testing.assert_allclose(xd, [0.0, 1.0, 2.0])


def test_difference_over_n_periods():
    """N = 3: (p(k) - p(k-3)) / (3 Ts) once three samples are past, (p(k) - p(0)) / (k Ts)
    before; the quantisation step's effect is a third of the plain difference's."""
    p = EstimatorParams(difference_periods=3)
    xs = [0.0, 0.001, 0.003, 0.006, 0.010, 0.010]
    expected = [0.0, 0.001 / TS, 0.003 / (2 * TS), 0.006 / (3 * TS), 0.009 / (3 * TS),
                0.007 / (3 * TS)]
    s = EstimatorState()
    for x, v in zip(xs, expected, strict=True):
        s, xd, thd = estimator_update(p, TS, s, x, 2 * x)
        assert float(xd) == pytest.approx(v, rel=1e-12, abs=1e-12)
        assert float(thd) == pytest.approx(2 * v, rel=1e-12, abs=1e-12)
    # one encoder count, once: the plain difference gives 0.314 rad/s, N = 4 a quarter
    count = 2 * math.pi / 4000
    for n, peak in ((1, count / TS), (4, count / (4 * TS))):
        s = EstimatorState()
        rates = []
        for theta in [0.0] * 5 + [count] * 6:
            s, _, thd = estimator_update(EstimatorParams(difference_periods=n), TS, s, 0.0,
                                         theta)
            rates.append(float(thd))
        assert max(rates) == pytest.approx(peak, rel=1e-12)
        assert rates[-1] == 0.0


def test_one_period_is_the_thesis_difference_bit_for_bit():
    rng = np.random.default_rng(2)
    xs = rng.normal(size=50)
    s1, s2 = EstimatorState(), EstimatorState()
    for x in xs:
        s1, v1, _ = estimator_update(EstimatorParams(), TS, s1, x, x)
        s2, v2, _ = estimator_update(EstimatorParams(velocity_filter_hz=0.0,
                                                     difference_periods=1), TS, s2, x, x)
        assert v1 == v2 and s2.x_past == ()
    assert float(v1) == (xs[-1] - xs[-2]) / TS

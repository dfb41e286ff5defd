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

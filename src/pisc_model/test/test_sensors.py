"""Sensor calibrations: the C++ program's conversions and their inverses (SPEC section 4)."""

import math

import numpy as np
import pytest

from pisc_model import sensors
from pisc_model.params import ActuatorParams, SensorParams

S = SensorParams()


def test_adc_conversion_is_the_cpp_formula():
    # vltIR = dataIR * (2.514 / 1024.0) + 0.595
    for code in (0, 1, 511, 780, 1023):
        assert sensors.adc_voltage(S, code) == code * (2.514 / 1024.0) + 0.595


def test_ir_range_matches_spec():
    """SPEC section 4: the IR sensor's useful range maps to about -0.225 .. +0.127 m."""
    lo = sensors.ir_position(S, sensors.adc_voltage(S, 0))
    hi = sensors.ir_position(S, sensors.adc_voltage(S, 1023))
    assert lo == pytest.approx(-0.2451 * 0.595**-1.069 + 0.20)
    assert lo == pytest.approx(-0.227, abs=1e-3)
    assert hi == pytest.approx(0.127, abs=1e-3)


def test_current_conversion_is_the_cpp_formula():
    # curr = (vltCR * 5.0) - 12.555
    for code in (0, 600, 780, 1023):
        v = code * (2.514 / 1024.0) + 0.595
        assert sensors.current_from_voltage(S, v) == pytest.approx(v * 5.0 - 12.555, abs=1e-15)
    zero_code = sensors.adc_code(S, sensors.current_sensor_voltage(S, 0.0))
    assert int(zero_code) == 780  # (12.555 / 5 - 0.595) * 1024 / 2.514 = 780.4


def test_encoder_conversion_is_the_cpp_formula():
    # theta = pi * count / 2000 + pi
    for count in (-40000, -1, 0, 1, 2000, 4000, 32767):
        assert sensors.encoder_angle(S, count) == pytest.approx(math.pi * count / 2000.0 + math.pi,
                                                                abs=1e-12)


def test_encoder_count_rounds_to_the_nearest_edge_and_counts_turns():
    step = 2 * math.pi / 4000
    assert sensors.encoder_count(S, math.pi) == 0
    assert sensors.encoder_count(S, math.pi + 0.49 * step) == 0
    assert sensors.encoder_count(S, math.pi + 0.51 * step) == 1
    assert sensors.encoder_count(S, math.pi - 0.51 * step) == -1
    assert sensors.encoder_count(S, math.pi + 3 * 2 * math.pi) == 12000


@pytest.mark.parametrize("x", np.linspace(-0.22, 0.12, 35))
def test_ir_round_trip_is_within_one_code(x):
    code = sensors.adc_code(S, sensors.ir_voltage(S, x))
    measured = sensors.ir_position(S, sensors.adc_voltage(S, code))
    # one code of the ADC in position at this x (the curve is steeper far from the sensor)
    next_up = sensors.ir_position(S, sensors.adc_voltage(S, code + 1))
    assert measured <= x + 1e-12
    assert x < next_up + 1e-12


def test_adc_saturates_and_truncates():
    assert sensors.adc_code(S, 0.0) == 0
    assert sensors.adc_code(S, 5.0) == 1023
    lsb = 2.514 / 1024
    assert sensors.adc_code(S, 0.595 + 10.999 * lsb) == 10
    assert sensors.adc_code(S, 0.595 + 11.0001 * lsb) == 11


def test_decode_raw_values():
    x, theta, i = sensors.decode(S, 0, 780, 2000)
    assert x == pytest.approx(-0.2451 * 0.595**-1.069 + 0.20)
    assert theta == pytest.approx(2 * math.pi)
    assert i == pytest.approx((780 * 2.514 / 1024 + 0.595) * 5 - 12.555)


class TestActuator:
    a = ActuatorParams()

    def test_full_scale_and_zero(self):
        assert self.a.magnitude(0.0) == 0
        assert self.a.magnitude(11.47) == 127
        assert self.a.magnitude(-11.47) == 127
        assert self.a.magnitude(20.0) == 127
        assert self.a.apply(-20.0) == -11.47

    def test_smallest_step_rounds_half_away_from_zero(self):
        step = 11.47 / 127
        assert self.a.magnitude(0.49 * step) == 0
        assert self.a.magnitude(0.5 * step) == 1
        assert self.a.magnitude(-0.5 * step) == 1
        assert self.a.apply(-0.6 * step) == pytest.approx(-step)

    def test_unquantised_when_levels_is_zero(self):
        ideal = ActuatorParams(command_levels=0)
        assert ideal.apply(3.3333) == 3.3333
        assert ideal.apply(12.0) == 11.47

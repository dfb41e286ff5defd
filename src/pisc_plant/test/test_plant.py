"""Full-fidelity plant: stability, conservation, armature, end stops, sampled interface."""

import dataclasses
import math

import numpy as np
import pytest

from pisc_msgs_py.config import ConfigError
from pisc_model import motor as motor_model
from pisc_model.dynamics import energy
from pisc_model.params import MotorParams, RigParams, TrackParams
from pisc_plant.plant import THETA, THETA_DOT, X_DOT, Plant, X
from pisc_plant.plant_config import IntegratorParams, PlantConfig
from pisc_plant.sampled import SampledPlant

DEFAULT = PlantConfig()
CURRENT = 4  # the armature current's place in the full-fidelity state


def test_default_integrator_is_exprk4_and_rk4_refuses_too_few_substeps():
    assert DEFAULT.integrator == IntegratorParams(method="exprk4", substeps=2)
    with pytest.raises(ConfigError, match=r"integrator.substeps = 5 is too few for rk4.*at least"):
        Plant(PlantConfig(integrator=IntegratorParams(method="rk4", substeps=5)))


@pytest.mark.parametrize("integrator", [IntegratorParams("exprk4", n) for n in (1, 2, 3, 5, 10)]
                         + [IntegratorParams("rk4", n) for n in (14, 20)])
def test_stable_with_the_armature_at_every_supported_step(integrator):
    """Hard case: bang-bang voltage at the 5 ms period for 2 s with the armature
    modelled (L/R = 0.14 ms), at every step the integrator allows up to the period:
    the state stays finite and the current within its physical bound."""
    plant = Plant(PlantConfig(integrator=integrator))
    y = plant.initial_state(0.0)
    for k in range(400):
        y = plant.advance(y, 11.47 if (k // 20) % 2 else -11.47, 0.005)
        assert np.all(np.isfinite(y))
        assert abs(y[CURRENT]) < 11.47 / 14.0 + 0.05


def test_energy_is_conserved_without_the_motor():
    """An open-circuit motor without rotor leaves a conservative cart-pole (2.54)."""
    motor = MotorParams(resistance_ohm=1e15, rotor_inertia_kgm2=0.0, viscous_friction_nms=0.0)
    plant = Plant(PlantConfig(motor=motor, integrator=IntegratorParams("exprk4", 20),
                              track=TrackParams(min_m=-100.0, max_m=100.0)))
    y = plant.initial_state(0.0, 0.1, math.pi / 2, 0.0)
    rig = RigParams()
    e0 = energy(rig, y[X_DOT], y[THETA], y[THETA_DOT])
    for _ in range(2000):  # 10 s
        y = plant.advance(y, 0.0, 0.005)
    e1 = energy(rig, y[X_DOT], y[THETA], y[THETA_DOT])
    assert abs(e1 - e0) / rig.mgl < 1e-9


def test_armature_settles_to_the_quasi_static_current():
    plant = Plant(DEFAULT)
    y = plant.initial_state(0.0)
    y = plant.advance(y, 5.0, 0.005)
    applied = float(DEFAULT.actuator.apply(5.0))
    expected = motor_model.quasi_static_current(DEFAULT.motor, applied, y[X_DOT])
    # L/R = 0.14 ms: after 5 ms only the lag behind the accelerating cart remains
    assert y[CURRENT] == pytest.approx(expected, abs=2e-4)


def test_end_stop_stops_the_cart_with_an_impulse_that_spares_the_pendulum_row():
    plant = Plant(DEFAULT)
    y = plant.initial_state(0.125, 1.0, 2.5, 3.0)
    y_before = y.copy()
    y = plant.end_stops(np.array([0.131, 1.0, 2.5, 3.0, 0.0, 1.0, 2.5]))
    assert (y[X], y[X_DOT]) == (0.13, 0.0)
    rig = RigParams()
    dx_dot = y[X_DOT] - 1.0
    dth_dot = y[THETA_DOT] - 3.0
    # second row of M(q) applied to the velocity change is zero: no impulse on the pendulum
    row2 = rig.ml * math.cos(2.5) * dx_dot + (rig.ml * rig.pendulum_com_m
                                              + rig.pendulum_inertia_kgm2) * dth_dot
    assert row2 == pytest.approx(0.0, abs=1e-15)
    assert y_before[X] == 0.125


def test_a_cart_moving_inwards_at_the_stop_keeps_its_speed():
    y = Plant(DEFAULT).end_stops(np.array([0.1305, -0.5, 3.0, 0.0, 0.0, 1.0, 2.5]))
    assert (y[X], y[X_DOT]) == (0.13, -0.5)


def test_measurement_of_a_settled_state_is_within_one_code():
    plant = Plant(DEFAULT)
    for x in (-0.2, -0.05, 0.0, 0.1):
        xm, theta_m, i_m = plant.measurement(plant.initial_state(x, theta=math.pi + 0.01))
        assert xm <= x and x - xm < 2e-3
        assert abs(theta_m - (math.pi + 0.01)) <= math.pi / 4000
        assert abs(i_m) < 0.013  # one code of the current ADC


def test_sampled_plant_applies_a_late_command_from_its_arrival():
    plant = Plant(DEFAULT)
    start = plant.initial_state(0.0)

    def run(delay):
        sp = SampledPlant(plant, start)
        sp.command(6.0)
        sp.advance()
        sp.command(-6.0, delay)
        sp.advance()
        return sp

    delayed = run(0.002)
    manual = plant.advance(plant.advance(plant.advance(start, 6.0, 0.005), 6.0, 0.002), -6.0, 0.003)
    np.testing.assert_array_equal(delayed.state, manual)
    missed = run(0.006)  # arrived after the next sample: the whole period at the old voltage
    np.testing.assert_array_equal(missed.state, plant.advance(plant.advance(start, 6.0, 0.005),
                                                              6.0, 0.005))
    assert missed.applied_v == -6.0 and missed.index == 2 and missed.time_ns == 10_000_000


def test_sampled_plant_refuses_non_finite_commands():
    sp = SampledPlant(Plant(DEFAULT), Plant(DEFAULT).initial_state())
    with pytest.raises(ValueError, match="not finite"):
        sp.command(float("nan"))


def test_batch_advance_matches_single_rigs():
    plant = Plant(DEFAULT)
    batch = plant.initial_state(np.array([-0.1, 0.0, 0.1]))
    out = plant.advance(batch, np.array([3.0, -2.0, 1.0]), 0.005)
    single = plant.advance(plant.initial_state(0.1), 1.0, 0.005)
    np.testing.assert_allclose(out[2], single, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("rigs", [3, 1000])  # one chunk; the parallel entry point
def test_advance_in_place_is_advance(rigs):
    """The batch's in-place step gives advance's bits, and refuses what it cannot take."""
    plant = Plant(DEFAULT)
    rng = np.random.default_rng(5)
    y = plant.initial_state(rng.uniform(-0.1, 0.1, rigs), 0.2, rng.uniform(0, 6, rigs), 1.0)
    command = rng.uniform(-14.0, 14.0, rigs)
    want = plant.advance(y, command, 0.005)
    want = plant.advance(want, command, 0.0031)
    ys = y.copy()
    for duration in (0.005, 0.0031, 0.0):
        plant.advance_in_place(ys, plant.applied(command), duration)
    np.testing.assert_array_equal(ys.view(np.int64), want.view(np.int64))
    for bad, message in ((y[:, :4].copy(), "float64 state of shape"),
                         (y[::2], "float64 state of shape"),
                         (y.astype(np.float32), "float64 state of shape")):
        with pytest.raises(ValueError, match=message):
            plant.advance_in_place(bad, np.zeros(len(bad)), 0.005)
    with pytest.raises(ValueError, match=r"input of shape \(%d,\)" % rigs):
        plant.advance_in_place(ys, np.zeros(rigs + 1), 0.005)
    for duration in (-0.001, math.nan, math.inf):
        with pytest.raises(ValueError, match="must be finite and not negative"):
            plant.advance_in_place(ys, np.zeros(rigs), duration)
    from pisc_plant.plant_config import plant_set
    rigs_set = Plant(plant_set(DEFAULT, {"motor.resistance_ohm": np.full(rigs, 14.0)}))
    with pytest.raises(ValueError, match="a plant set takes advance"):
        rigs_set.advance_in_place(ys, np.zeros(rigs), 0.005)


def test_scalar_actuator_matches_the_array_one_at_every_boundary():
    act = DEFAULT.actuator
    step = act.step_v
    values = np.concatenate([np.linspace(-13, 13, 20001), (np.arange(128) + 0.5) * step,
                             -(np.arange(128) + 0.5) * step, [0.0, -0.0, 11.47, -11.47]])
    array = act.apply(values)
    scalar = np.array([act.apply_scalar(v) for v in values])
    np.testing.assert_array_equal(scalar, array)


def test_one_rig_fast_path_is_the_batch_arithmetic():
    plant = Plant(DEFAULT)
    y = plant.initial_state(0.02, 0.1, 3.0, 0.5, 0.1)
    np.testing.assert_array_equal(plant.advance(y, 3.3, 0.005),
                                  plant.advance(y[None, :], np.array([3.3]), 0.005)[0])


def test_a_simulated_command_latency_applies_the_voltage_that_long_into_the_period():
    """actuator.command_delay_s = 2 ms: the same state as a command given 2 ms into the
    period on a plant without it, and unlike a command applied at once."""
    import dataclasses

    from pisc_model.params import ActuatorParams

    plain = Plant(PlantConfig())
    late = Plant(dataclasses.replace(PlantConfig(),
                                     actuator=ActuatorParams(command_delay_s=0.002)))
    a = SampledPlant(plain, plain.initial_state(0.0))
    b = SampledPlant(late, late.initial_state(0.0))
    c = SampledPlant(plain, plain.initial_state(0.0))
    for voltage in (5.0, -3.0, 8.0):
        a.command(voltage, 0.002)
        b.command(voltage)
        c.command(voltage)
        for s in (a, b, c):
            s.advance()
    np.testing.assert_array_equal(a.state, b.state)
    assert not np.array_equal(b.state, c.state)


@pytest.mark.parametrize("noisy", [False, True], ids=["exact", "noisy"])
def test_one_rig_measurement_has_the_arrays_bits(noisy):
    """The sampled plant's float measurement (measurement_one) equals measurement() to
    the bit over states spread across the track and many turns, sensor voltages across
    and beyond the ADC's range (saturated codes) and on its code edges, with and without
    noise; other sensor models take measurement() itself."""
    from pisc_model.params import NoiseParams

    noise = NoiseParams(x_std_m=1e-3, theta_std_rad=1e-3, current_std_a=0.02) if noisy \
        else NoiseParams()
    plant = Plant(dataclasses.replace(DEFAULT, noise=noise))
    s = plant.config.sensors
    rng = np.random.default_rng(11)
    n = 3000
    y = plant.initial_state(rng.uniform(-0.25, 0.15, n), rng.normal(0.0, 0.5, n),
                            rng.uniform(-30.0, 30.0, n), rng.normal(0.0, 5.0, n))
    ir, cur = plant.layout.ir_index, plant.layout.current_sensor_index
    y[:, ir] = rng.uniform(0.0, 4.0, n)  # below, across and above the ADC's 0.595-3.109 V
    y[:, cur] = rng.uniform(0.0, 4.0, n)
    edges = s.adc_ref_low_v + s.adc_lsb_v * rng.integers(0, s.adc_levels, 500)
    y[:500, ir] = edges
    y[500:1000, cur] = edges
    y[1000:1500, THETA] = s.encoder_zero_rad + s.encoder_rad_per_count * (
        rng.integers(-8000, 8000, 500) + 0.5)  # half a count: the rounding's edge
    draws = rng.standard_normal((n, 3))
    want = plant.measurement(y, 0.0, draws if noisy else None)
    for k in range(n):
        got = plant.measurement_one(y[k], 0.0, draws[k] if noisy else None)
        assert all(type(v) is float for v in got)
        assert np.array_equal(np.array(got).view(np.int64),
                              np.array([w[k] for w in want]).view(np.int64)), k
    ideal = Plant(dataclasses.replace(DEFAULT, models=dataclasses.replace(
        DEFAULT.models, sensors="ideal", sensor_filters=False)))
    assert ideal.measurement_one(ideal.initial_state(0.03, theta=0.2), 0.0) == (0.03, 0.2, 0.0)

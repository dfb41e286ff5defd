"""Hard cases of the plant's numerics, each a property that would break visibly.

(The stiff armature at every supported step is in test_plant.py and test_kernel.py.)
"""

import math

import numpy as np
import pytest

from pisc_model.dynamics import energy, wrap_to_upright
from pisc_model.params import ModelParams, MotorParams, NoiseParams, TrackParams
from pisc_plant.plant import Plant
from pisc_plant.plant_config import IntegratorParams, PlantConfig

CONSERVATIVE = ModelParams(armature="ideal_force", current_loop="ideal", sensors="ideal",
                           sensor_filters=False, end_stops=False)


def _energy(plant, y):
    return float(energy(plant.config.rig, y[1], y[2], y[3]))


def test_conservative_run_of_600_s_keeps_its_energy():
    """The conservative scene's setting (rk4, 8 steps per period) over 600 s: relative
    energy drift (2.54) below 1e-8 (measured 2.0e-10)."""
    plant = Plant(PlantConfig(models=CONSERVATIVE, integrator=IntegratorParams("rk4", 8)))
    y = plant.initial_state(0.0, 0.1, 2.0, 0.0)
    e0 = _energy(plant, y)
    worst = 0.0
    for _ in range(1200):  # 0.5 s at a time, the same 0.625 ms steps
        y = plant.advance(y, 0.0, 0.5)
        worst = max(worst, abs(_energy(plant, y) - e0) / abs(e0))
    assert worst < 1e-8
    # and horizontal momentum, the other invariant of the free cart-pole, within 1e-9
    rig = plant.config.rig
    p0 = rig.a2 * 0.1 + rig.ml * math.cos(2.0) * 0.0
    p = rig.a2 * y[1] + rig.ml * math.cos(y[2]) * y[3]
    assert p == pytest.approx(p0, abs=1e-9)


def test_angle_wraps_through_many_revolutions():
    """A pendulum spun at 40 rad/s goes round hundreds of times; the angle keeps
    counting, energy holds, the encoder counts every edge and the wrap maps onto
    [-pi, pi)."""
    plant = Plant(PlantConfig(models=ModelParams(armature="ideal_force", current_loop="ideal",
                                                 sensor_filters=False, end_stops=False),
                              integrator=IntegratorParams("rk4", 8)))
    y = plant.initial_state(0.0, 0.0, math.pi, 40.0)
    e0 = _energy(plant, y)
    for _ in range(200):
        y = plant.advance(y, 0.0, 0.5)
    revolutions = (y[2] - math.pi) / (2 * math.pi)
    assert revolutions > 500
    assert abs(_energy(plant, y) - e0) / abs(e0) < 1e-8
    _, theta_measured, _ = plant.measurement(y)
    assert abs(theta_measured - y[2]) <= math.pi / 4000 + 1e-9  # within half a count
    wrapped = wrap_to_upright(y[2])
    assert -math.pi <= wrapped < math.pi
    assert math.cos(wrapped) == pytest.approx(math.cos(y[2]), abs=1e-9)


@pytest.mark.parametrize("method,substeps", [("exprk4", 1), ("exprk4", 4), ("rk4", 20)])
def test_large_initial_velocities_stay_finite_and_on_the_track(method, substeps):
    """5 m/s into the end stop and 100 rad/s of spin with the motor short-circuited at
    0 V: the stops hold the cart, the motor only takes energy out."""
    plant = Plant(PlantConfig(integrator=IntegratorParams(method, substeps)))
    y = plant.initial_state(0.0, 5.0, 1.0, 100.0)
    e0 = _energy(plant, y)
    track = plant.config.track
    for _ in range(400):
        y = plant.advance(y, 0.0, 0.005)
        assert np.all(np.isfinite(y))
        assert track.min_m <= y[0] <= track.max_m
    assert _energy(plant, y) < e0


def test_quasi_static_armature_carries_no_electrical_state_and_matches_the_full_one():
    """A scene that needs no armature transient has no current state; the quasi-static
    current i = (u - k_e phi_dot) / R agrees with the full model once L/R has passed."""
    quasi = Plant(PlantConfig(models=ModelParams(armature="quasi_static")))
    full = Plant(PlantConfig())
    assert quasi.state_names == ("x", "x_dot", "theta", "theta_dot", "v_ir", "v_cur")
    assert full.state_names == ("x", "x_dot", "theta", "theta_dot", "i", "v_ir", "v_cur")
    yq, yf = quasi.initial_state(0.0), full.initial_state(0.0)
    for k in range(200):
        u = 6.0 if (k // 40) % 2 else -6.0
        yq, yf = quasi.advance(yq, u, 0.005), full.advance(yf, u, 0.005)
    # the full model's current lags by L/R = 0.14 ms: a small difference, not zero
    assert abs(yq[0] - yf[0]) < 2e-4 and abs(yq[0] - yf[0]) > 0
    assert quasi.current(yq, 6.0) == pytest.approx(
        (float(quasi.applied(6.0)) - 0.0637 * yq[1] / 0.032) / 14.0)


def test_states_of_the_wrong_size_are_refused():
    plant = Plant(PlantConfig(models=CONSERVATIVE))
    with pytest.raises(ValueError, match=r"state has 7 components, this scene's plant has 4"):
        plant.advance(np.zeros(7), 0.0, 0.005)


def test_open_circuit_motor_conserves_energy_with_the_armature_modelled():
    motor = MotorParams(resistance_ohm=1e15, rotor_inertia_kgm2=0.0, viscous_friction_nms=0.0)
    plant = Plant(PlantConfig(motor=motor, integrator=IntegratorParams("exprk4", 4),
                              track=TrackParams(min_m=-100.0, max_m=100.0)))
    y = plant.initial_state(0.0, 0.1, math.pi / 2, 0.0)
    e0 = _energy(plant, y)
    y = plant.advance(y, 0.0, 10.0)
    assert abs(_energy(plant, y) - e0) / plant.config.rig.mgl < 1e-9


@pytest.mark.parametrize("filters", [True, False])
def test_noise_reaches_every_measurement_with_its_standard_deviation(filters):
    """Seeded noise of 1 mm, 2 mrad, 20 mA shows in the decoded measurements with about
    that spread, with and without the RC filters (behind them it is noise at the ADC
    input, converted through the sensors' slopes)."""
    models = ModelParams(sensor_filters=filters)
    plant = Plant(PlantConfig(models=models, noise=NoiseParams(
        seed=1, x_std_m=1e-3, theta_std_rad=2e-3, current_std_a=0.02)))
    y = np.repeat(plant.initial_state(-0.05, theta=3.0)[None, :], 4000, axis=0)
    draws = np.random.default_rng(1).standard_normal((4000, 3))
    x, theta, current = plant.measurement(y, 0.0, draws)
    assert np.std(x) == pytest.approx(1e-3, rel=0.15)
    assert np.std(theta) == pytest.approx(2e-3, rel=0.1)
    assert np.std(current) == pytest.approx(0.02, rel=0.15)
    assert np.ptp(plant.measurement(y, 0.0, None)[0]) == 0.0  # no draws, no noise

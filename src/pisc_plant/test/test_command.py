"""The plant's command: the voltage for a motor armature, the set-point's force (4.2) for
an ideal force source."""

import dataclasses

import numpy as np
import pytest

from pisc_model.params import ModelParams, MotorParams
from pisc_plant.command import plant_command
from pisc_plant.plant_config import PlantConfig

VOLTAGE_PLANT = PlantConfig()
FORCE_PLANT = PlantConfig(models=ModelParams(armature="ideal_force", current_loop="ideal",
                                             sensors="ideal", sensor_filters=False))


def test_a_motor_armature_is_driven_by_the_voltage_and_ignores_the_setpoint():
    assert not VOLTAGE_PLANT.models.force_input
    assert plant_command(VOLTAGE_PLANT, setpoint_a=0.7, voltage_v=-3.25) == -3.25
    assert plant_command(VOLTAGE_PLANT, voltage_v=11.47) == 11.47


def test_an_ideal_force_source_is_driven_by_k_m_over_r_times_the_setpoint():
    assert FORCE_PLANT.models.force_input
    # (4.2): f = k_m i_d / r = 0.0637 / 0.032 * 0.5 N with the default motor
    assert plant_command(FORCE_PLANT, setpoint_a=0.5, voltage_v=9.0) == pytest.approx(
        0.0637 / 0.032 * 0.5, rel=1e-15)
    # the plant's own k_m / r, one per rig of a set
    plant = dataclasses.replace(FORCE_PLANT, motor=MotorParams(wheel_radius_m=0.064))
    np.testing.assert_allclose(plant_command(plant, setpoint_a=np.array([0.5, -0.9])),
                               [0.0637 / 0.064 * 0.5, -0.0637 / 0.064 * 0.9], rtol=1e-15)


def test_the_value_that_drives_the_plant_is_required():
    with pytest.raises(ValueError, match=r"ideal force source .* setpoint_a is required"):
        plant_command(FORCE_PLANT, voltage_v=3.0)
    with pytest.raises(ValueError, match=r"motor armature \(models.armature = full\) .* "
                                         r"voltage_v is required"):
        plant_command(VOLTAGE_PLANT, setpoint_a=0.5)

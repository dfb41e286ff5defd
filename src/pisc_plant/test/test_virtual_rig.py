"""The virtual rig's firmware: frames of the simulated state, command bytes applied on arrival."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from pisc_msgs_py.config import ConfigError
from pisc_plant.plant import Plant, PlantConfig
from pisc_plant.sampled import SampledPlant
from pisc_plant.virtual_rig import Firmware, RigFaults, load_plant


@pytest.fixture
def plant():
    config, _ = load_plant(None, {})
    return Plant(config)


def test_the_rig_integrates_with_the_plant_default_unless_told_otherwise():
    config, initial = load_plant(None, {"initial.x_m": 0.05})
    assert (config.integrator.method, config.integrator.substeps) == ("exprk4", 2)
    assert initial.x_m == 0.05
    config, _ = load_plant(None, {"integrator.method": "exprk4", "integrator.substeps": 2})
    assert config.integrator.method == "exprk4"
    with pytest.raises(ValueError, match="swing_up.k_v: not a parameter of the rig"):
        load_plant(None, {"swing_up.k_v": 0.1})


def test_frame_is_the_quantised_measurement_big_endian(plant):
    state = plant.initial_state(0.05, 0.0, math.pi - 0.1, 0.0, 0.2)
    fw = Firmware(plant, state)
    data = fw.frame()
    ir, cur, count = plant.raw_measurement(state)
    assert data == struct.pack(">BHHh", 0xAA, int(ir), int(cur), int(count))
    assert data[0] == 0xAA and data[1] <= 3 and data[3] <= 3
    assert int(count) == round(-0.1 / (2 * math.pi / 4000))  # -64 counts


def test_the_count_register_wraps_at_16_bits(plant):
    turns = 9.0  # 36000 counts: past the int16 range
    fw = Firmware(plant, plant.initial_state(0.0, 0.0, math.pi + turns * 2 * math.pi, 0.0))
    assert struct.unpack(">h", fw.frame()[5:])[0] == 36000 - 65536


@pytest.mark.parametrize("byte,volts", [
    (0x00, 0.0), (0x80, 0.0), (0x01, 11.47 / 127), (0x81, -11.47 / 127), (0x7F, 11.47),
    (0xFF, -11.47), (0x40, 64 * 11.47 / 127),
])
def test_command_byte_as_the_firmware_applies_it(plant, byte, volts):
    assert Firmware(plant, plant.initial_state()).voltage(byte) == pytest.approx(volts, abs=1e-12)


def test_a_byte_applies_where_it_arrives_in_the_period(plant):
    """One byte per period, 1.3 ms into it: the same as the plant node's delayed command."""
    state = plant.initial_state(0.0, 0.0, math.pi - 0.2, 0.0)
    fw = Firmware(plant, state.copy())
    ref = SampledPlant(plant, state.copy())
    for k, byte in enumerate([0x7F, 0x7F, 0xC0, 0x10, 0x00]):
        fw.receive(byte, 0.0013)
        fw.advance()
        ref.command(fw.applied_v, 0.0013)
        ref.advance()
        np.testing.assert_allclose(fw.state, ref.state, rtol=0, atol=1e-12)
    assert fw.time_s == pytest.approx(0.025)
    # two bytes in one period: each applies from its arrival
    fw2 = Firmware(plant, state.copy())
    fw2.receive(0x7F, 0.001)
    fw2.receive(0x00, 0.003)
    fw2.advance()
    expected = plant.advance(plant.advance(plant.advance(state, 0.0, 0.001), 11.47, 0.002),
                             0.0, 0.002)
    np.testing.assert_allclose(fw2.state, expected, rtol=0, atol=1e-12)


def test_fault_requests_are_checked():
    faults = RigFaults()
    faults.update({"drop_rate": 0.01, "silence_s": 0.1, "garbage": 3}, now=10.0)
    assert (faults.drop_rate, faults.silent_until, faults.garbage) == (0.01, 10.1, 3)
    with pytest.raises(ValueError, match="flip_rate = 2.0 must lie in"):
        faults.update({"flip_rate": 2.0}, now=0.0)


def test_default_config_is_the_thesis_rig():
    assert load_plant(None, {})[0].rig == PlantConfig().rig


def test_the_rig_refuses_a_plant_without_an_armature():
    with pytest.raises(ConfigError, match=r"models.armature = 'ideal_force': the rig takes "
                                          r"voltage bytes"):
        load_plant(None, {"models.armature": "ideal_force", "models.current_loop": "ideal"})
    config, _ = load_plant(None, {"noise.seed": 3, "noise.x_std_m": 1e-3})
    assert config.noise.x_std_m == 1e-3  # every plant section, noise included

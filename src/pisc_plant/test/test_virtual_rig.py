"""The virtual rig's firmware: frames of the simulated state, command bytes applied on arrival,
the command watchdog, and fault requests checked before anything is applied."""

from __future__ import annotations

import math
import re
import struct
import time

import numpy as np
import pytest

from pisc_msgs_py.config import ConfigError
from pisc_plant.plant import THETA, Plant
from pisc_plant.plant_config import PlantConfig
from pisc_plant.sampled import SampledPlant
from pisc_plant.firmware import Firmware
from pisc_plant.rig_faults import RequestError, RigFaults, check_request
from pisc_plant.rig_process import RigProcess
from pisc_plant.virtual_rig import load_plant
from pisc_plant.virtual_rig_cli import main


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


def test_frames_carry_the_parameter_files_measurement_noise():
    """noise.* of the rig's parameter file: each frame reads the sensors with fresh draws
    (the virtual rig ignored them before 2026-12-03, so its bags had none)."""
    from pisc_model import sensors

    config, _ = load_plant(None, {"noise.current_std_a": 0.05, "noise.theta_std_rad": 0.004,
                                  "noise.seed": 3, "models.sensor_filters": False})
    plant = Plant(config)
    state = plant.initial_state(0.0, 0.0, math.pi, 0.0, 0.2)
    fw = Firmware(plant, state.copy())
    frames = [struct.unpack(">BHHh", fw.frame()) for _ in range(4000)]
    _, _, cur, count = np.array(frames, dtype=float).T
    _, theta, current = sensors.decode(config.sensors, np.zeros_like(cur), cur, count)
    # the decoded reading scatters by the noise (plus a code's uniform quantisation error)
    s = config.sensors
    step = s.current_scale_a_per_v * s.adc_span_v / 2 ** s.adc_bits  # one code, 12.3 mA
    assert np.std(current) == pytest.approx(math.hypot(0.05, step / math.sqrt(12)), rel=0.05)
    assert np.mean(current) == pytest.approx(0.2, abs=step)
    assert np.std(theta - math.pi) == pytest.approx(0.004, rel=0.1)
    # the same seed draws the same frames; without noise every frame is the same
    again = Firmware(plant, state.copy())
    assert [struct.unpack(">BHHh", again.frame()) for _ in range(10)] == frames[:10]
    quiet = Plant(load_plant(None, {"models.sensor_filters": False})[0])
    quiet = Firmware(quiet, state.copy())
    assert len({quiet.frame() for _ in range(50)}) == 1


def test_a_quasi_static_armatures_current_is_read_with_the_voltage_applied():
    """With L di/dt = 0 (2.81) the current is (u - k_e x_dot / r) / R of the voltage held:
    the frame reads it as the sampled plant does, not the current of 0 V."""
    config, _ = load_plant(None, {"models.armature": "quasi_static",
                                  "models.sensor_filters": False})
    plant = Plant(config)
    state = plant.initial_state(0.0, 0.1, math.pi, 0.0)
    fw = Firmware(plant, state.copy())
    ref = SampledPlant(plant, state.copy())
    fw.receive(0x40, 0.0)
    fw.advance()
    ref.command(fw.applied_v, 0.0)
    ref.advance()
    cur = struct.unpack(">BHHh", fw.frame())[2]
    from pisc_model import sensors
    assert sensors.decode(config.sensors, 0, cur, 0)[2] == pytest.approx(
        ref.sample().current_a, abs=1e-12)
    assert ref.sample().current_a > 0.35  # 5.8 V over 14 ohm, less the back EMF


def test_the_count_register_wraps_at_16_bits(plant):
    turns = 9.0  # 36000 counts: past the int16 range
    fw = Firmware(plant, plant.initial_state(0.0, 0.0, math.pi + turns * 2 * math.pi, 0.0))
    assert struct.unpack(">h", fw.frame()[5:])[0] == 36000 - 65536


def test_a_held_rig_stays_put_until_a_nonzero_byte_lets_go_where_it_arrives(plant):
    """--hold: a hand on the pendulum. Time passes and 0 V bytes change nothing; the first
    nonzero byte releases the state from its arrival in the period, so the rest is the
    unheld rig's motion started there (the same plant steps)."""
    state = plant.initial_state(-0.05, 0.0, 0.05, 0.0)  # 0.05 rad from upright: it falls
    fw = Firmware(plant, state.copy(), held=True)
    for _ in range(200):  # a second of frames, the driver's 0 V among them
        fw.receive(0x00, 0.001)
        fw.advance()
    np.testing.assert_array_equal(fw.state, state)
    assert fw.held and fw.released_s is None and fw.time_s == pytest.approx(1.0)
    fw.receive(0x80, 0.0005)  # -0 V: still zero
    fw.receive(0x7F, 0.0013)
    fw.advance()
    assert not fw.held and fw.released_s == pytest.approx(1.0013)
    expected = plant.advance(state, 11.47, 0.005 - 0.0013)
    np.testing.assert_allclose(fw.state, expected, rtol=0, atol=1e-12)
    free = Firmware(plant, state.copy())  # unheld, the same second passes: it fell
    for _ in range(200):
        free.advance()
    assert abs(free.state[THETA] - state[THETA]) > 0.5


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


@pytest.mark.parametrize("request_,message", [
    # the first two killed the rig with a traceback, the last two were accepted
    ({"garbage": -5}, 'garbage = -5 must be a whole number from 0 to 1024'),
    ({"garbage": 1e20}, 'garbage = 1e+20 must be a whole number from 0 to 1024'),
    ({"silence_s": "nan"}, 'silence_s = "nan" must be a number (seconds without frames, '
                           '0 .. 3600), not a string'),
    ({"silence_s": -5}, 'silence_s = -5 must not be negative (seconds without frames, '
                        '0 .. 3600)'),
    ({"silence_s": 1e308}, 'silence_s = 1e+308 is too long (seconds without frames, '
                           '0 .. 3600)'),
    ({"silence_s": math.nan}, "silence_s = NaN must be a finite number"),
    ({"silence_s": math.inf}, "silence_s = Infinity must be a finite number"),
    ({"drop_rate": -0.1}, "drop_rate = -0.1 must lie in [0, 1] (a probability per byte"),
    ({"flip_rate": True}, "flip_rate = true must be a number (a probability per byte, 0 to "
                          "1), not true/false"),
    ({"drop_rate": None}, "drop_rate = null must be a number"),
    ({"drop_rate": 10 ** 400}, "must be a finite number (a probability per byte, 0 to 1)"),
    ({"garbage": 2.5}, "garbage = 2.5 must be a whole number"),
    ({"garbage": [5]}, "garbage = [5] must be a number (random bytes to send, a whole "
                       "number from 0 to 1024), not a list"),
    ({"status": 1}, "status = 1 must be true or false, not a number"),
    ({"quit": "yes"}, 'quit = "yes" must be true or false, not a string'),
    ({"silence": 0.1}, '"silence" is not a request (known: drop_rate, flip_rate, silence_s, '
                       'garbage, status, quit); did you mean silence_s?'),
    ([1, 2], "a request is a JSON object of drop_rate, flip_rate, silence_s, garbage, status, "
             "quit; got a list"),
])
def test_a_bad_request_is_refused_naming_the_key_and_the_rule(request_, message):
    with pytest.raises(RequestError, match=re.escape(message)):
        check_request(request_)


def test_a_request_is_applied_whole_or_not_at_all():
    faults = RigFaults()
    with pytest.raises(RequestError, match="garbage = -5"):
        faults.update({"drop_rate": 0.5, "silence_s": 1.0, "garbage": -5}, now=0.0)
    assert (faults.drop_rate, faults.silent_until, faults.garbage) == (0.0, -math.inf, 0)
    assert check_request({"garbage": 20.0, "silence_s": 0, "status": False}) == {
        "garbage": 20, "silence_s": 0.0, "status": False}
    faults.update({"garbage": 1000}, now=0.0)
    with pytest.raises(RequestError, match="1000 bytes are already waiting, and at most 1024"):
        faults.update({"garbage": 100}, now=0.0)
    assert faults.garbage == 1000


@pytest.mark.integration
def test_the_rig_refuses_bad_requests_on_stderr_and_keeps_running():
    """Found by a hostile test: {"garbage": -5} and {"garbage": 1e20} ended the rig with a
    traceback; {"silence_s": "nan"} and {"silence_s": -5} were accepted."""
    rig = RigProcess(["--watchdog-ms", "0"])
    try:
        lines = ['{"garbage": -5}', '{"garbage": 1e20}', '{"silence_s": "nan"}',
                 '{"silence_s": -5}', '{"nosuch": 1}', "not json", "[" * 3000, "x" * 10_000]
        for line in lines:
            rig.send_line(line)
            assert "error" in rig.reply(), line
        status = rig.status()
        assert status["refused_requests"] == len(lines)
        assert status["silence_start"] is None and rig.process.poll() is None
        frames = status["frames"]
        rig.request(garbage=3)  # a good request still works, and the frames go on
        deadline = time.monotonic() + 10.0
        while rig.status()["frames"] <= frames + 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert rig.status()["frames"] > frames + 2
        final = rig.stop()
        assert rig.process.returncode == 0 and final["refused_requests"] == len(lines)
        err = "\n".join(rig.stderr_lines())
        assert "Traceback" not in err
        for text in ["refused {\"garbage\": -5} (nothing of it applied): garbage = -5 must be a "
                     "whole number from 0 to 1024",
                     "refused {\"garbage\": 1e20} (nothing of it applied): garbage = 1e+20",
                     'silence_s = "nan" must be a number', "silence_s = -5 must not be negative",
                     '"nosuch" is not a request', "not JSON", "nested too deep",
                     "a request is one line of at most 4096 bytes"]:
            assert text in err, (text, err)
    finally:
        rig.stop()


# -- the command watchdog ------------------------------------------------------------------

def run_periods(fw: Firmware, n: int, bytes_at: dict[int, tuple[int, float]] = {}) -> list[float]:
    """Advance ``n`` periods, receiving ``bytes_at[k] = (byte, offset)`` in period k;
    returns the voltage applied at the end of each period (after its tick)."""
    applied = []
    for k in range(n):
        if k in bytes_at:
            fw.receive(*bytes_at[k])
        fw.advance()
        applied.append(fw.applied_v)
    return applied


def test_the_watchdog_applies_zero_volts_after_ten_periods_without_a_byte(plant):
    state = plant.initial_state(0.0, 0.0, math.pi - 0.2, 0.0)
    fw = Firmware(plant, state.copy())
    assert (fw.watchdog_s, fw.watchdog_periods) == (0.05, 10)
    applied = run_periods(fw, 12, {0: (0x7F, 0.001)})
    # ticks 1..10 (5..50 ms) hold the byte; the 11th tick (55 ms, 54 ms after it) is 0 V
    assert applied == pytest.approx([11.47] * 10 + [0.0, 0.0])
    assert (fw.trips, fw.tripped) == (1, True)
    assert fw.trip_delay_s == pytest.approx(0.054)
    expected = plant.advance(plant.advance(state, 0.0, 0.001), 11.47, 0.004)
    for _ in range(10):
        expected = plant.advance(expected, 11.47, 0.005)
    expected = plant.advance(expected, 0.0, 0.005)
    np.testing.assert_allclose(fw.state, expected, rtol=0, atol=1e-12)
    # the next byte is applied where it arrives, and the watchdog counts again
    applied = run_periods(fw, 12, {0: (0xC0, 0.002)})
    assert applied == pytest.approx([-64 * 11.47 / 127] * 10 + [0.0, 0.0])
    assert fw.trips == 2


@pytest.mark.parametrize("offset", [0.0, 0.001, 0.0049])
def test_zero_volts_comes_between_50_and_55_ms_after_the_last_byte(plant, offset):
    fw = Firmware(plant, plant.initial_state())
    run_periods(fw, 15, {2: (0x10, offset)})
    assert fw.trips == 1 and 0.050 < fw.trip_delay_s <= 0.055 + 1e-12


def test_a_byte_every_ten_periods_keeps_the_watchdog_quiet(plant):
    fw = Firmware(plant, plant.initial_state())
    run_periods(fw, 101, {k: (0x10, 0.001) for k in range(0, 101, 10)})
    assert fw.trips == 0 and fw.applied_v > 0
    fw = Firmware(plant, plant.initial_state())
    run_periods(fw, 101, {k: (0x10, 0.001) for k in range(0, 101, 11)})
    assert fw.trips == 9  # one each time 11 periods passed


def test_the_watchdog_waits_for_the_first_byte_and_can_be_switched_off(plant):
    fw = Firmware(plant, plant.initial_state())
    run_periods(fw, 40)
    assert (fw.trips, fw.armed, fw.applied_v) == (0, False, 0.0)
    thesis = Firmware(plant, plant.initial_state(), watchdog_s=0.0)  # NOWDT: held for ever
    assert run_periods(thesis, 200, {0: (0x7F, 0.001)})[-1] == pytest.approx(11.47)
    assert thesis.trips == 0
    assert Firmware(plant, plant.initial_state(), watchdog_s=0.012).watchdog_periods == 3
    with pytest.raises(ValueError, match="must be a finite number >= 0"):
        Firmware(plant, plant.initial_state(), watchdog_s=-0.05)


@pytest.mark.parametrize("value", ["-1", "nan", "inf", "1e9"])
def test_a_bad_watchdog_time_refuses_the_start(capsys, value):
    assert main(["--watchdog-ms", value]) == 2
    assert "--watchdog-ms" in capsys.readouterr().err


def test_default_config_is_the_thesis_rig():
    assert load_plant(None, {})[0].rig == PlantConfig().rig


def test_the_rig_refuses_a_plant_without_an_armature():
    with pytest.raises(ConfigError, match=r"models.armature = 'ideal_force': the rig takes "
                                          r"voltage bytes"):
        load_plant(None, {"models.armature": "ideal_force", "models.current_loop": "ideal"})
    config, _ = load_plant(None, {"noise.seed": 3, "noise.x_std_m": 1e-3})
    assert config.noise.x_std_m == 1e-3  # every plant section, noise included

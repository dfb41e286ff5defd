"""The compiled batch pass gives the bits of the laws it compiles as the nodes run them
(the one-rig controllers on Python floats), rig by rig, cycle by cycle; its measurement
and bookkeeping give the numpy path's outcomes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pisc_control.current_loop import CurrentLoopState, OneRigCurrentLoop, current_loop_cycle
from pisc_control.estimator import (
    EstimatorParams,
    EstimatorState,
    OneRigEstimator,
    estimator_update,
)
from pisc_control.supervisor import OneRigSupervisor, Supervisor, SupervisorState
from pisc_msgs_py.types import Mode
from pisc_plant.command import plant_command
from pisc_plant.plant import Plant
from pisc_plant.plant_config import plant_set
from pisc_sim.batch_controllers import BatchControllers, supported
from pisc_sim.closed_loop import simulate_batch
from pisc_sim.scene import load_scene

# the default configuration has every option on (energy pump with its guard, online
# estimates, N = 7 differences low-passed, governed and guarded catch with a settling
# reference, energy band, start-up distance); the others switch them off one by one or
# take the thesis's law (3.30)
CONFIGS = {
    "default": {},
    "fixed pump": {"adaptation.enabled": False, "catch.governor": False,
                   "catch.guard": False},
    "thesis law": {"swing_up.law": "lyapunov", "switching.energy_band_j": 0.0,
                   "adaptation.enabled": False, "catch.guard": False},
    "thesis scene": None,
    "plain differences": {"estimator.velocity_filter_hz": 0.0,
                          "estimator.difference_periods": 1},
    "no guard, no settling, no start-up": {"swing_up.guard_accel_mps2": 0.0,
                                            "catch.guard": False,
                                            "catch.settle_rate_mps": 0.0,
                                            "startup.distance_m": 0.0},
}


def _config(name: str):
    if CONFIGS[name] is None:
        return load_scene("thesis-gains").config
    return load_scene("thesis-rig", CONFIGS[name]).config


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=float).view(np.int64)


class _OneRigs:
    """The nodes' one-rig controllers, one set per rig of ``rigs``."""

    def __init__(self, config, rigs: list[int]) -> None:
        period = config.loop.period_s
        supervisor = Supervisor(config.supervisor)
        self.rigs = rigs
        self.each = [(OneRigEstimator(config.estimator, period), OneRigSupervisor(supervisor),
                      OneRigCurrentLoop(config.plant.motor, config.current_loop, period))
                     for _ in rigs]

    def step(self, x, theta, current):
        out = []
        for r, (estimator, supervisor, loop) in zip(self.rigs, self.each):
            x_dot, theta_dot = estimator.step(float(x[r]), float(theta[r]))
            force, mode = supervisor.step(float(x[r]), x_dot, float(theta[r]), theta_dot)
            i_d, voltage = loop.step(force, float(current[r]), mode == Mode.FAULT.code)
            assert all(type(v) is float for v in (x_dot, theta_dot, force, i_d, voltage))
            out.append((force, mode, i_d, voltage))
        return [np.array(column) for column in zip(*out)]


def _assert_same(k: int, want, got, rigs=slice(None)) -> None:
    for name, w, g in zip(("force", "mode", "i_d", "voltage"), want, got):
        g = np.asarray(g)[rigs]
        assert np.array_equal(_bits(w), _bits(g)), (
            f"cycle {k}: {name} differs in {np.sum(_bits(w) != _bits(g))} rigs")


def _compare(config, measurements, one_rigs: list[int]) -> dict[str, int]:
    """Feed the same measurements to the compiled pass and to the nodes' one-rig
    controllers on ``one_rigs``; assert every output's bits; count the modes."""
    rigs = len(measurements[0][0])
    compiled = BatchControllers(config, Supervisor(config.supervisor), rigs)
    single = _OneRigs(config, one_rigs)
    modes = {m: 0 for m in Mode}
    for k, (x, theta, current) in enumerate(measurements):
        got = compiled.step(x, theta, current)
        _assert_same(k, single.step(x, theta, current), got, one_rigs)
        for m in Mode:
            modes[m] += int(np.sum(got[1] == m.code))
    return modes


@pytest.mark.parametrize("name", list(CONFIGS))
def test_closed_loop_bit_for_bit(name):
    """50 rigs from spread starts through 3 s: every cycle's force, mode, i_d and voltage
    of the compiled pass equal, to the bit, those of the nodes' one-rig controllers (the
    same laws on Python floats)."""
    config = _config(name)
    rigs = 50
    plant = Plant(config.simulated_plant)
    # half hanging (the swing-up), half near upright (the catch, whatever the law)
    theta0 = np.concatenate([np.linspace(np.pi - 0.5, np.pi + 0.5, rigs // 2),
                             np.linspace(-0.4, 0.4, rigs - rigs // 2)])
    y = plant.initial_state(np.linspace(-0.12, 0.08, rigs), 0.0, theta0, 0.0)
    compiled = BatchControllers(config, Supervisor(config.supervisor), rigs)
    single = _OneRigs(config, list(range(rigs)))
    period = config.loop.period_s
    applied = np.zeros(rigs)
    seen = set()
    for k in range(int(3.0 / period)):
        x, theta, current = plant.measurement(y, applied)
        want = single.step(x, theta, current)
        got = compiled.step(x, theta, current)
        _assert_same(k, want, got)
        seen.update(int(m) for m in np.unique(got[1]))
        applied = plant_command(config.simulated_plant, setpoint_a=want[2], voltage_v=want[3])
        y = plant.advance(y, applied, period)
    # the runs cover both laws' branches: swing-up and catch both happened
    assert {Mode.SWING_UP.code, Mode.CATCH.code} <= seen


def test_hostile_measurements_bit_for_bit():
    """Random walks through every branch: NaN and infinite readings (faults that latch
    at different cycles), the safe range's edges and beyond, angles many turns away
    and at the wrap's boundary (+-pi), currents that wind the integral to its limits."""
    config = _config("default")
    rng = np.random.default_rng(7)
    rigs, cycles = 300, 400
    x = rng.uniform(-0.2, 0.1, rigs)
    theta = rng.uniform(-20.0, 20.0, rigs)
    theta[:10] = np.pi
    theta[10:20] = -np.pi
    theta[290:295] = 1e17  # no fraction: the wrap's floor must not overflow an integer
    theta[295:300] = -3e300
    current = np.zeros(rigs)
    measurements = []
    for k in range(cycles):
        x = x + rng.normal(0.0, 0.004, rigs)
        theta[:290] = theta[:290] + rng.normal(0.0, 0.05, 290)
        theta[20:60] = rng.normal(0.0, 0.02, 40)  # near upright: the catch and its exit
        current = rng.normal(0.0, 3.0, rigs) * (k % 50 < 25)
        xs, ts, cs = x.copy(), theta.copy(), current.copy()
        xs[60:70] = np.where(k == 100 + np.arange(10) * 20, np.nan, xs[60:70])
        ts[70:75] = np.where(k == 150, np.inf, ts[70:75])
        cs[75:80] = np.where(k >= 200, -np.inf, cs[75:80])
        xs[80:85] = config.supervisor.safety.x_max_m  # on the edge: in range
        xs[85:90] = np.nextafter(config.supervisor.safety.x_min_m, -1.0)  # just outside
        measurements.append((xs, ts, cs))
    modes = _compare(config, measurements, list(range(rigs)))
    assert all(n > 0 for n in modes.values()), modes


def test_primed_estimator_and_shapes_match_the_cores():
    """simulate_batch over a 2-D grid of starts with a primed estimator, per-rig command
    delays and sensor noise: the compiled pass and the laws over arrays (estimator_update's
    window, Supervisor.update, current_loop_cycle) give identical outcomes."""
    scene = load_scene("thesis-rig", {"noise.x_std_m": 1e-4, "noise.theta_std_rad": 1e-3,
                                      "noise.current_std_a": 0.01})
    config = scene.config
    x0 = np.linspace(-0.1, 0.05, 6)[:, None]
    theta0 = np.linspace(-0.3, 0.3, 5)[None, :]
    delay = np.linspace(0.0, 0.004, 30).reshape(6, 5)
    kwargs = dict(theta0_rad=theta0, theta_dot0_radps=0.5, prime_estimator=True,
                  command_delay_s=delay, hold_start_s=1.0)
    a = simulate_batch(config, x0, 2.0, controllers="compiled", **kwargs)
    b = simulate_batch(config, x0, 2.0, controllers="numpy", **kwargs)
    for field in dataclasses.fields(a):
        got, want = getattr(a, field.name), getattr(b, field.name)
        assert got.shape == (6, 5)
        assert np.array_equal(got, want), field.name
    assert np.isfinite(a.caught_at_s).sum() > 0


@pytest.mark.parametrize("case", ["pass measures", "noise", "ideal force and sensors",
                                  "plant set"])
def test_the_compiled_cycle_gives_the_numpy_outcomes(case):
    """simulate_batch's compiled cycle (the measurement, the controllers and the outcomes
    in one pass) against the numpy path, where the pass measures (quantised sensors
    behind their filters, with and without noise) and where numpy measures for it (ideal
    sensors, with the ideal force source's command; a plant set): every outcome equal."""
    scene = {"ideal force and sensors": "ideal-cart-pole"}.get(case, "thesis-rig")
    overrides = {"noise.x_std_m": 2e-4, "noise.theta_std_rad": 2e-3,
                 "noise.current_std_a": 0.05} if case == "noise" else {}
    config = load_scene(scene, overrides).config
    x0 = np.linspace(-0.12, 0.08, 40)
    kwargs = dict(theta0_rad=np.linspace(np.pi - 0.4, 0.2, 40), hold_start_s=0.5)
    if case == "plant set":
        kwargs["plant"] = plant_set(config.simulated_plant,
                                    {"motor.resistance_ohm": np.linspace(11.0, 17.0, 40)})
    a = simulate_batch(config, x0, 2.0, controllers="compiled", **kwargs)
    b = simulate_batch(config, x0, 2.0, controllers="numpy", **kwargs)
    for field in dataclasses.fields(a):
        got, want = getattr(a, field.name), getattr(b, field.name)
        assert np.array_equal(got, want, equal_nan=True), field.name
    assert np.isfinite(a.caught_at_s).sum() > 0


def test_the_pass_measures_hostile_states_as_the_plant_does():
    """States built to break the pass's measurement: filter voltages below the ADC's low
    reference and above its top (saturated codes), angles many turns away and at half
    a count, noise; then a cycle with a NaN voltage, an infinite angle and an angle too
    large for the count's integer, which the pass hands back to numpy's measurement.
    Each cycle's outputs and command equal the numpy measurement's through the pass."""
    config = load_scene("thesis-rig", {"noise.x_std_m": 1e-4, "noise.theta_std_rad": 1e-3,
                                       "noise.current_std_a": 0.02}).config
    plant = Plant(config.simulated_plant)
    s, rigs = config.simulated_plant.sensors, 64
    rng = np.random.default_rng(3)
    supervisor = Supervisor(config.supervisor)
    compiled = BatchControllers(config, supervisor, rigs)
    compiled.track(plant, np.zeros(rigs))
    reference = BatchControllers(config, supervisor, rigs)
    y = np.array(plant.initial_state(rng.uniform(-0.15, 0.15, rigs)))
    ir, cur = plant.layout.ir_index, plant.layout.current_sensor_index
    top = s.adc_ref_low_v + s.adc_span_v
    for k in range(6):
        y[:, 0] = rng.uniform(-0.2, 0.19, rigs)
        y[:, 2] = rng.uniform(-60.0, 60.0, rigs)
        y[:4, 2] = s.encoder_zero_rad + (np.arange(4) + 0.5) * s.encoder_rad_per_count
        y[:, ir] = rng.uniform(s.adc_ref_low_v - 0.3, top + 0.3, rigs)
        y[:, cur] = rng.uniform(s.adc_ref_low_v - 0.3, top + 0.3, rigs)
        if k == 4:
            y[10, ir], y[11, 2], y[12, 2] = np.nan, np.inf, 1e300
        draws = rng.standard_normal((rigs, 3))
        applied = rng.uniform(-10.0, 10.0, rigs)
        with np.errstate(invalid="ignore", over="ignore"):  # numpy's, on the bad cycle
            command, acts = compiled.cycle(y, applied, draws, 0.005 * k, True)
            measured = plant.measurement(y, applied, draws)
            want = reference.step(*measured)
        got = compiled._force, compiled._mode, compiled._setpoint, compiled._voltage
        _assert_same(k, want, got)
        assert np.array_equal(_bits(command), _bits(want[3]))
        assert np.array_equal(_bits(acts), _bits(plant.applied(want[3])))
        if k != 4:  # the pass's own measurement, not numpy's
            for mine, theirs in zip((compiled._x, compiled._theta, compiled._current),
                                    measured):
                assert np.array_equal(_bits(mine), _bits(theirs)), k
    assert want[1][10] == Mode.FAULT.code  # the NaN reading's fault, latched


def test_the_pass_applies_the_actuator_as_its_parameters_do():
    """The pass's actuator (saturated, quantised to the command byte) against
    ActuatorParams.apply, bit for bit, at every step boundary, beyond the supply, at
    the signed zeros and NaN; and the unquantised actuator (command_levels = 0)."""
    from pisc_sim.batch_controllers import _actuator

    for act in (load_scene("thesis-rig").config.plant.actuator,
                load_scene("thesis-rig", {"actuator.command_levels": 0}).config.plant.actuator):
        step = act.step_v or 0.1
        values = np.concatenate([np.linspace(-13, 13, 20001), (np.arange(128) + 0.5) * step,
                                 -(np.arange(128) + 0.5) * step,
                                 np.nextafter((np.arange(128) + 0.5) * step, 0.0),
                                 [0.0, -0.0, 11.47, -11.47, np.inf, -np.inf, np.nan]])
        with np.errstate(invalid="ignore"):  # numpy's cast of NaN
            want = act.apply(values)
        got = np.array([_actuator(act.full_scale_v, float(act.command_levels), act.step_v, v)
                        for v in values])
        assert np.array_equal(_bits(got), _bits(want)), act.command_levels


def test_the_compiled_cycle_refuses_what_it_cannot_index():
    """The pass reads the state by index without bounds checks: a cycle before track, or
    with a state, input or draws of another shape, is refused by name."""
    config = load_scene("thesis-rig").config
    plant = Plant(config.simulated_plant)
    compiled = BatchControllers(config, Supervisor(config.supervisor), 4)
    y = plant.initial_state(np.zeros(4))
    with pytest.raises(ValueError, match=r"call track\(plant, x0\) first"):
        compiled.cycle(y, np.zeros(4), None, 0.0, False)
    compiled.track(plant, np.zeros(4))
    for bad in ((y[:3], np.zeros(4), None), (y[:, :5], np.zeros(4), None),
                (y, np.zeros(3), None), (y, np.zeros(4), np.zeros((4, 2)))):
        with pytest.raises(ValueError, match=r"want \(4, %d\), \(4,\) and None or \(4, 3\)"
                           % plant.size):
            compiled.cycle(*bad, 0.0, False)
    command, acts = compiled.cycle(y, np.zeros(4), None, 0.0, False)
    assert command.shape == acts.shape == (4,)


def test_experiments_run_on_the_arrays():
    config = load_scene("excitation").config
    assert not supported(config)
    with pytest.raises(ValueError, match="experiment.kind = .*not in the compiled pass"):
        BatchControllers(config, Supervisor(config.supervisor), 3)
    compiled = simulate_batch(config, np.zeros(3), 0.5)
    numpy_cores = simulate_batch(config, np.zeros(3), 0.5, controllers="numpy")
    assert np.array_equal(compiled.x_max_m, numpy_cores.x_max_m)


def test_unknown_controllers_and_wrong_shapes_are_refused():
    config = _config("default")
    with pytest.raises(ValueError, match="controllers = 'fast': 'compiled' or 'numpy'"):
        simulate_batch(config, np.zeros(2), 0.1, controllers="fast")
    compiled = BatchControllers(config, Supervisor(config.supervisor), 4)
    with pytest.raises(ValueError, match=r"shape \(3,\), \(4,\), \(4,\): want \(4,\) each"):
        compiled.step(np.zeros(3), np.zeros(4), np.zeros(4))


def test_one_rig_forms_follow_a_parameter_change_as_the_cores_do():
    """A node's parameters change mid-run (N of the differences 7 -> 3 -> 9, the catch
    region, the PI gains): the one-rig forms carry their state over as the array forms'
    immutable states carry, to the bit."""
    config = load_scene("thesis-rig").config
    period = config.loop.period_s
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.normal(0.0, 0.002, 300)) * 0.2
    theta = np.cumsum(rng.normal(0.0, 0.02, 300)) * 0.3
    current = rng.normal(0.0, 0.5, 300)
    estimator = OneRigEstimator(config.estimator, period)
    est_state = EstimatorState()
    supervisor = Supervisor(config.supervisor)
    one_sup, sup_state = OneRigSupervisor(supervisor), SupervisorState()
    motor, params = config.plant.motor, config.current_loop
    one_loop, loop_state = OneRigCurrentLoop(motor, params, period), CurrentLoopState()
    est_params = config.estimator
    for k in range(300):
        if k in (100, 200):
            est_params = EstimatorParams(est_params.velocity_filter_hz, 3 if k == 100 else 9)
            estimator.configure(est_params, period)
            cfg = dataclasses.replace(config.supervisor, switching=dataclasses.replace(
                config.supervisor.switching, delta_s=0.3 if k == 100 else 0.25))
            supervisor = Supervisor(cfg)
            one_sup.configure(supervisor)
            params = dataclasses.replace(params, k_pi=params.k_pi * (1.5 if k == 100 else 0.5))
            one_loop.configure(motor, params, period)
        est_state, x_dot, theta_dot = estimator_update(est_params, period, est_state,
                                                       x[k], theta[k])
        sup_state, force, mode = supervisor.update(sup_state, x[k], x_dot, theta[k],
                                                   theta_dot)
        loop_state, i_d, voltage = current_loop_cycle(motor, params, period, loop_state,
                                                      force, current[k],
                                                      mode == Mode.FAULT.code)
        got_rates = estimator.step(float(x[k]), float(theta[k]))
        assert _bits(got_rates).tolist() == _bits([x_dot, theta_dot]).tolist(), k
        got_force, got_mode = one_sup.step(float(x[k]), got_rates[0], float(theta[k]),
                                           got_rates[1])
        assert (_bits(got_force), got_mode) == (_bits(force), int(mode)), k
        got = one_loop.step(got_force, float(current[k]), got_mode == Mode.FAULT.code)
        assert _bits(got).tolist() == _bits([i_d, voltage]).tolist(), k
    assert one_sup.fault == 0


def test_one_rig_supervisor_runs_an_experiment_as_the_arrays_do():
    config = load_scene("excitation").config
    supervisor = Supervisor(config.supervisor)
    one, state = OneRigSupervisor(supervisor), SupervisorState()
    for k in range(50):
        x = 0.001 * k
        state, force, mode = supervisor.update(state, x, 0.1, np.pi, 0.0)
        assert one.step(x, 0.1, np.pi, 0.0) == (float(force), int(mode))
    assert one.fault == int(state.fault)

"""Plant sets: every rig its own parameters and its own duration, each rig bit for bit
the plant of its own values (pisc_plant.plant_config.plant_set, the kernel's per-rig entry
points and its compiled operator tables)."""

import dataclasses

import numpy as np
import pytest

from pisc_msgs_py.config import ConfigError
from pisc_plant import kernel_batch
from pisc_plant import kernel_operators
from pisc_plant import kernel_sets
from pisc_model.params import FrictionParams, ModelParams, NoiseParams
from pisc_plant.plant import Plant
from pisc_plant.plant_config import IntegratorParams, PlantConfig, plant_set, rigs_of

PERIOD = 0.005
# full armature, RC filters, end stops, and every friction term
BASE = PlantConfig(models=ModelParams(friction="coulomb"),
                   friction=FrictionParams(cart_viscous_ns_per_m=0.2, pivot_viscous_nms=1e-5,
                                           cart_coulomb_n=0.03))
EXPRK4 = IntegratorParams("exprk4", 2)
RK4 = IntegratorParams("rk4", 40)  # resolves the stiffest rig below (R/L < 2.785 / h)


def _varied(rigs: int, seed: int) -> dict[str, np.ndarray]:
    """Draws of the parameters a robustness study varies, around the thesis rig."""
    rng = np.random.default_rng(seed)

    def around(value, spread):
        return value * rng.uniform(1.0 - spread, 1.0 + spread, rigs)

    return {
        "motor.resistance_ohm": around(14.0, 0.25),
        "motor.inductance_h": around(0.002, 0.3),
        "motor.rotor_inertia_kgm2": around(2e-6, 0.5),
        "motor.viscous_friction_nms": around(1e-6, 0.9),
        "rig.cart_mass_kg": around(0.4735, 0.2),
        "rig.pendulum_mass_kg": around(0.01055, 0.2),
        "rig.pendulum_com_m": around(0.0865, 0.1),
        "rig.pendulum_inertia_kgm2": around(2.631524e-5, 0.3),
        "friction.cart_coulomb_n": rng.uniform(0.0, 0.08, rigs),
        "friction.cart_viscous_ns_per_m": rng.uniform(0.0, 0.5, rigs),
        "friction.pivot_viscous_nms": rng.uniform(0.0, 3e-5, rigs),
    }


def _rig_config(base: PlantConfig, values: dict, k: int) -> PlantConfig:
    """Rig k of a set as a configuration of its own, from ``base`` by dataclasses.replace."""
    sections: dict[str, dict[str, float]] = {}
    for name, column in values.items():
        section, field = name.split(".")
        sections.setdefault(section, {})[field] = float(column[k] if np.ndim(column)
                                                        else column)
    return dataclasses.replace(base, **{
        section: dataclasses.replace(getattr(base, section), **fields)
        for section, fields in sections.items()})


def _starts(rigs: int, seed: int) -> tuple[np.ndarray, ...]:
    """x, x_dot, theta, theta_dot, i: some carts near a stop and moving towards it."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.2, 0.1, rigs)
    x[:2] = (0.125, -0.225)  # 5 mm from the stops (+0.13, -0.23 m)
    x_dot = np.where(x > 0.0, 1.0, -1.0) * rng.uniform(0.2, 0.8, rigs)
    return (x, x_dot, rng.uniform(0.0, 2.0 * np.pi, rigs), rng.uniform(-6.0, 6.0, rigs),
            rng.uniform(-0.5, 0.5, rigs))


def _own_states(singles: list[Plant], y: np.ndarray, starts: tuple) -> list[np.ndarray]:
    """Each rig's state as its own plant makes it: the same as the set's row. (From
    one-element arrays: numpy's power of an array, in the IR sensor's curve, can differ
    from that of a number in the last bit; of arrays it does not depend on the length.)"""
    ys = [single.initial_state(*(s[k:k + 1] for s in starts))[0]
          for k, single in enumerate(singles)]
    np.testing.assert_array_equal(np.array(ys), y)
    return ys


def _voltages(rigs: int, periods: int, seed: int) -> np.ndarray:
    """(periods, rigs): each rig's own sign, so that carts run into both stops, with
    steps every period."""
    rng = np.random.default_rng(seed)
    sign = np.where(np.arange(rigs) % 2 == 0, 1.0, -1.0)
    return np.clip(sign * 9.0 + rng.uniform(-4.0, 4.0, (periods, rigs)), -11.47, 11.47)


@pytest.mark.parametrize("integrator", [EXPRK4, RK4], ids=["exprk4", "rk4"])
@pytest.mark.parametrize("rigs", [7, kernel_batch.CHUNK + 44], ids=["serial", "parallel"])
def test_a_set_of_equal_rigs_steps_bit_for_bit_as_the_uniform_plant(rigs, integrator):
    """Values all equal to the base configuration: the per-rig entry points give the
    uniform plant's bits, in the serial path (7 rigs) and the parallel one (more than
    kernel_batch.CHUNK rigs), through filters, friction and end stops."""
    base = dataclasses.replace(BASE, integrator=integrator)
    uniform = Plant(base)
    values = {name: np.full(rigs, float(getattr(getattr(base, name.split(".")[0]),
                                                name.split(".")[1])))
              for name in _varied(1, 0)}
    plant = Plant(plant_set(base, values))
    assert plant.rigs == rigs and uniform.rigs is None
    assert np.array_equal(plant.lam, np.broadcast_to(uniform.lam, (rigs, plant.size)))
    starts = _starts(rigs, 1)
    y = plant.initial_state(*starts)
    y_uniform = uniform.initial_state(*starts)
    np.testing.assert_array_equal(y, y_uniform)
    at_stop = np.zeros(rigs, dtype=bool)
    for u in _voltages(rigs, 8, 2):
        y = plant.advance(y, u, PERIOD)
        y_uniform = uniform.advance(y_uniform, u, PERIOD)
        np.testing.assert_array_equal(y, y_uniform)
        at_stop |= (y[:, 0] == base.track.min_m) | (y[:, 0] == base.track.max_m)
    assert 0 < at_stop.sum() < rigs


@pytest.mark.parametrize("integrator", [EXPRK4, RK4], ids=["exprk4", "rk4"])
def test_each_rig_of_a_set_is_the_plant_of_its_own_values(integrator):
    """R, L, J_m, b_m, M, m, l, I and the cart's and pivot's friction drawn per rig: over
    40 periods of voltage steps (some carts at a stop) every rig's state equals, bit for
    bit, that of a plant built from its own values; then the same with every period
    split at a latency of the rig's own, the old voltage before it and the new after."""
    base = dataclasses.replace(BASE, integrator=integrator)
    rigs = 2 * kernel_sets.BLOCK + 5  # blocks of the kernel's layout, full and partial
    values = _varied(rigs, 3)
    plant = Plant(plant_set(base, values))
    singles = [Plant(_rig_config(base, values, k)) for k in range(rigs)]
    starts = _starts(rigs, 4)
    y = plant.initial_state(*starts)
    ys = _own_states(singles, y, starts)
    voltages = _voltages(rigs, 80, 5)
    at_stop = np.zeros(rigs, dtype=bool)
    for u in voltages[:40]:
        y = plant.advance(y, u, PERIOD)
        ys = [single.advance(one, float(u[k]), PERIOD)
              for k, (single, one) in enumerate(zip(singles, ys, strict=True))]
        np.testing.assert_array_equal(y, np.array(ys))
        at_stop |= (y[:, 0] == base.track.min_m) | (y[:, 0] == base.track.max_m)
    assert 0 < at_stop.sum() < rigs
    # one latency a rig, in [0, 2 ms], exactly 0 for some. Every rig takes the substeps
    # the longest duration needs: for rk4 (0.125 ms) the latencies share their number
    # (16, then 25 for the rest of the period) only in a narrow band, without zeros
    rng = np.random.default_rng(6)
    if integrator.method == "exprk4":
        delays = rng.uniform(0.0, 0.002, rigs)
        delays[::5] = 0.0
    else:
        delays = rng.uniform(0.00188, 0.00199, rigs)
    previous = voltages[39]
    for u in voltages[40:]:
        y = plant.advance(y, previous, delays)
        y = plant.advance(y, u, PERIOD - delays)
        ys = [single.advance(single.advance(one, float(previous[k]), float(delays[k])),
                             float(u[k]), PERIOD - float(delays[k]))
              for k, (single, one) in enumerate(zip(singles, ys, strict=True))]
        np.testing.assert_array_equal(y, np.array(ys))
        previous = u


def test_the_rigs_of_a_large_set_are_the_plants_of_their_own_values():
    """The parallel path (more than kernel_batch.CHUNK rigs), per-rig durations included: a
    few rigs across the chunks against plants of their own."""
    rigs = kernel_batch.CHUNK + 61
    values = _varied(rigs, 7)
    plant = Plant(plant_set(BASE, values))
    starts = _starts(rigs, 8)
    y = y_start = plant.initial_state(*starts)
    delays = np.random.default_rng(9).uniform(0.0, 0.002, rigs)
    delays[1::7] = 0.0
    voltages = _voltages(rigs, 12, 10)
    history = []
    for u_old, u in zip(voltages, voltages[1:], strict=False):
        y = plant.advance(y, u_old, delays)
        y = plant.advance(y, u, PERIOD - delays)
        history.append(y)
    for k in (0, 1, 15, 16, kernel_batch.CHUNK - 1, kernel_batch.CHUNK, rigs - 1):
        single = Plant(_rig_config(BASE, values, k))
        one = _own_states([single], y_start[k:k + 1], tuple(s[k:k + 1] for s in starts))[0]
        for (u_old, u), expected in zip(zip(voltages, voltages[1:], strict=False), history,
                                        strict=True):
            one = single.advance(one, float(u_old[k]), float(delays[k]))
            one = single.advance(one, float(u[k]), PERIOD - float(delays[k]))
            np.testing.assert_array_equal(one, expected[k])


@pytest.mark.parametrize("integrator", [EXPRK4, RK4], ids=["exprk4", "rk4"])
def test_one_duration_a_rig_on_a_uniform_plant(integrator):
    """A plant of one configuration takes one duration a rig too: each rig as if
    advanced alone; duration 0 leaves a rig as it was, even one past a stop."""
    plant = Plant(dataclasses.replace(BASE, integrator=integrator))
    rigs = 23
    y = plant.initial_state(*_starts(rigs, 11))
    y[3, 0] = BASE.track.max_m + 0.01  # past the stop: only a step puts it back
    # each rig moved needs as many substeps as the longest (2 for exprk4, 40 for rk4)
    low = 0.00251 if integrator.method == "exprk4" else 0.00488
    durations = np.random.default_rng(12).uniform(low, PERIOD, rigs)
    durations[[2, 3, 9]] = 0.0
    u = _voltages(rigs, 1, 13)[0]
    out = plant.advance(y, u, durations)
    assert out is not y
    for k in range(rigs):
        np.testing.assert_array_equal(out[k], plant.advance(y[k], float(u[k]),
                                                            float(durations[k])))
    np.testing.assert_array_equal(out[[2, 3, 9]], y[[2, 3, 9]])
    # a duration for every rig, as a number: the uniform path's bits
    np.testing.assert_array_equal(plant.advance(y, u, np.float64(PERIOD)),
                                  plant.advance(y, u, np.full(rigs, PERIOD)))


@pytest.mark.parametrize("case", [
    (64.5, 452.4, 90.5, -6990.0, 0.0025),     # the thesis rig, two steps a period
    (64.5, 452.4, 90.5, -6990.0, 0.005),
    (64.5, 452.4, 90.5, -6990.0, 1.3e-4),     # a short latency: series phi for lam h
    (64.5, 452.4, 90.5, 0.0, 0.0025),         # no armature (quasi-static, ideal force)
    (0.0, 0.0, 0.0, -6990.0, 0.0025),         # no filters
    (0.0, 0.0, 0.0, 0.0, 0.004),              # neither
    (64.5, 452.4, 90.5, -6990.0, 0.0),        # a rig that does not move
    (640.0, 4520.0, 900.0, -25000.0, 0.003),  # |z| > 2 for the filters' phi
])
def test_a_plant_sets_operator_tables_equal_one_rigs_exactly(case):
    """exp_tables (a table a rig) against exp_coefficients, which test_kernel.py pins
    to the sums in Python."""
    w_ir, w_cur, c_v, lam, h = case
    out = np.empty((1, kernel_sets.N_TABLE * kernel_sets.BLOCK))
    kernel_sets.exp_tables(w_ir, w_cur, c_v, np.array([lam]), np.array([h]), out)
    expected = kernel_operators.exp_coefficients(w_ir, w_cur, c_v, lam, h)
    np.testing.assert_array_equal(kernel_sets.from_lanes(out, 1)[:, 0],
                                  expected[:kernel_operators.N_OPERATORS].ravel())


def test_the_tables_of_many_rigs_equal_one_rigs_exactly():
    """Steps and rates of their own, repeated ones (which reuse the previous rig's work)
    and zeros, across blocks."""
    rigs = 3 * kernel_sets.BLOCK + 3
    rng = np.random.default_rng(14)
    lam = rng.uniform(-20000.0, -3000.0, rigs)
    steps = rng.uniform(0.0, 0.005, rigs)
    steps[5:9] = steps[4]
    lam[6:8] = lam[5]
    lam[8] = 0.0  # the step of the rig before it, without the armature
    steps[20] = 0.0
    lam[30] = 0.0
    tables = np.empty((-(-rigs // kernel_sets.BLOCK), kernel_sets.N_TABLE * kernel_sets.BLOCK))
    kernel_sets.exp_tables(64.5, 452.4, 90.5, lam, steps, tables)
    columns = kernel_sets.from_lanes(tables, rigs)
    for k in range(rigs):
        expected = kernel_operators.exp_coefficients(64.5, 452.4, 90.5, lam[k], steps[k])
        np.testing.assert_array_equal(columns[:, k],
                                      expected[:kernel_operators.N_OPERATORS].ravel())


def test_lanes_is_undone_by_from_lanes():
    a = np.arange(3 * 37, dtype=float).reshape(3, 37)
    blocked = kernel_sets.lanes(a)
    assert blocked.shape == (3, 3 * kernel_sets.BLOCK)
    assert blocked[2, 1 * kernel_sets.BLOCK + 4] == a[1, 2 * kernel_sets.BLOCK + 4]
    np.testing.assert_array_equal(kernel_sets.from_lanes(blocked, 37), a)


def test_measurement_and_the_other_methods_work_rig_by_rig():
    """initial_state, current, derivative, end_stops, measurement and raw_measurement
    with noise of each rig's own size: each rig as its own plant gives it."""
    rigs = 5
    values = _varied(rigs, 15) | {"noise.x_std_m": np.linspace(0.0, 2e-3, rigs),
                                  "noise.current_std_a": 0.01}
    config = plant_set(BASE, values)
    assert config.noise.any and not NoiseParams().any
    assert NoiseParams(x_std_m=np.zeros(3)).any is False
    plant = Plant(config)
    y = plant.initial_state(*_starts(rigs, 16))
    y[0, 0] = BASE.track.min_m - 0.01  # past a stop, moving outwards
    y[0, 1] = -0.5
    noise = np.random.default_rng(17).standard_normal((rigs, 3))
    u = np.linspace(-6.0, 6.0, rigs)
    derivative = plant.derivative(y, u)
    stopped = plant.end_stops(y)
    measured = plant.measurement(y, u, noise)
    raw = plant.raw_measurement(y, u, noise)
    for k in range(rigs):
        single = Plant(_rig_config(BASE, values, k))
        np.testing.assert_array_equal(derivative[k], single.derivative(y[k], u[k]))
        np.testing.assert_array_equal(
            derivative[k], plant.applied_derivative(y[k], plant.applied(u[k]), rig=k))
        np.testing.assert_array_equal(stopped[k], single.end_stops(y[k]))
        np.testing.assert_array_equal(plant.current(y, u)[k], single.current(y[k], u[k]))
        # one-element arrays, as in _own_states
        row = slice(k, k + 1)
        for got, expected in zip(measured, single.measurement(y[row], u[row], noise[row]),
                                 strict=True):
            assert got[k] == expected[0]
        for got, expected in zip(raw, single.raw_measurement(y[row], u[row], noise[row]),
                                 strict=True):
            assert got[k] == expected[0]
    assert stopped[0, 0] == BASE.track.min_m and stopped[0, 1] == 0.0


def test_the_quasi_static_armature_and_an_ideal_force_source_take_sets_too():
    """The other layouts' per-rig entry points: rigs as plants of their own values."""
    for models in (ModelParams(armature="quasi_static", sensor_filters=False,
                               sensors="ideal", friction="coulomb"),
                   ModelParams(armature="ideal_force", current_loop="ideal",
                               friction="coulomb")):
        base = dataclasses.replace(BASE, models=models)
        rigs = 9
        values = _varied(rigs, 18)
        plant = Plant(plant_set(base, values))
        starts = _starts(rigs, 19)
        y = plant.initial_state(*starts)
        command = np.linspace(-3.0, 3.0, rigs) if models.force_input else np.full(rigs, 5.0)
        for _ in range(4):
            y = plant.advance(y, command, PERIOD)
        for k in range(rigs):
            single = Plant(_rig_config(base, values, k))
            one = plant.initial_state(*starts)[k]
            for _ in range(4):
                one = single.advance(one, float(command[k]), PERIOD)
            np.testing.assert_array_equal(y[k], one)
            np.testing.assert_array_equal(plant.current(y, command)[k],
                                          single.current(one, command[k]))


def test_a_set_is_refused_what_it_cannot_be():
    with pytest.raises(ConfigError, match=r"^motor\.resistance: unknown parameter"):
        plant_set(BASE, {"motor.resistance": [14.0, 15.0]})
    with pytest.raises(ConfigError, match=r"^resistance_ohm: unknown parameter"):
        plant_set(BASE, {"resistance_ohm": [14.0, 15.0]})
    for name in ("sensors.ir_filter_hz", "loop.period_s", "noise.seed", "track.max_m"):
        with pytest.raises(ConfigError, match=rf"^{name}: not a parameter a plant set may "
                                              "vary"):
            plant_set(BASE, {name: [1.0, 2.0]})
    with pytest.raises(ConfigError, match=r"^rig\.cart_mass_kg: 3 values, but "
                                          r"motor\.resistance_ohm has 4"):
        plant_set(BASE, {"motor.resistance_ohm": [14.0] * 4, "rig.cart_mass_kg": [0.5] * 3})
    four = plant_set(BASE, {"motor.resistance_ohm": [14.0] * 4})
    with pytest.raises(ConfigError, match=r"^rig\.cart_mass_kg: 3 values, but "
                                          r"motor\.resistance_ohm has 4"):
        plant_set(four, {"rig.cart_mass_kg": [0.5] * 3})
    with pytest.raises(ConfigError, match=r"^motor\.resistance_ohm: must be positive "
                                          r"\(> 0\) \(rig 1: -2\.0\)"):
        plant_set(BASE, {"motor.resistance_ohm": [14.0, -2.0, 13.0]})
    with pytest.raises(ConfigError, match=r"^friction\.cart_coulomb_n: must be finite"):
        plant_set(BASE, {"friction.cart_coulomb_n": [0.0, np.nan]})
    with pytest.raises(ConfigError, match=r"^motor\.inductance_h: must be a number or a 1-D"):
        plant_set(BASE, {"motor.inductance_h": np.ones((2, 2))})
    with pytest.raises(ConfigError, match=r"^motor\.inductance_h: a plant set needs one "
                                          "value a rig"):
        plant_set(BASE, {"motor.inductance_h": 0.003})
    # numbers are broadcast; the fields hold read-only arrays
    config = plant_set(BASE, {"motor.inductance_h": 0.003, "rig.cart_mass_kg": [0.4, 0.5]})
    assert rigs_of(config) == 2 and rigs_of(BASE) is None
    np.testing.assert_array_equal(config.motor.inductance_h, [0.003, 0.003])
    assert config.motor.inductance_h.dtype == np.float64
    assert not config.rig.cart_mass_kg.flags.writeable
    # rk4 must resolve the stiffest rig
    with pytest.raises(ConfigError, match=r"integrator\.substeps = 40 is too few for rk4"):
        Plant(plant_set(dataclasses.replace(BASE, integrator=RK4),
                        {"motor.inductance_h": [0.002, 2e-4]}))


def test_a_set_refuses_states_and_durations_of_another_shape():
    plant = Plant(plant_set(BASE, {"motor.resistance_ohm": [13.0, 14.0, 15.0]}))
    y = plant.initial_state(0.0)
    assert y.shape == (3, plant.size)
    with pytest.raises(ValueError, match=r"set of 3 rigs: a state has shape \(3, 7\), not "
                                         r"\(2, 7\)"):
        plant.advance(y[:2], 0.0, PERIOD)
    with pytest.raises(ValueError, match=r"set of 3 rigs: a state has shape"):
        plant.advance(y[0], 0.0, PERIOD)
    with pytest.raises(ValueError, match=r"set of 3 rigs: the initial values"):
        plant.initial_state(np.zeros(4))
    with pytest.raises(ValueError, match=r"duration_s = -0\.001 \(rig 1\) must be finite and "
                                         "not negative"):
        plant.advance(y, 0.0, np.array([0.001, -0.001, 0.002]))
    with pytest.raises(ValueError, match=r"duration_s = nan \(rig 2\)"):
        plant.advance(y, 0.0, np.array([0.001, 0.0, np.nan]))
    with pytest.raises(ValueError, match=r"duration_s = -0\.005 \(rig 0\)"):
        plant.advance(y, 0.0, -0.005)
    with pytest.raises(ValueError, match=r"duration_s has shape \(2,\)"):
        plant.advance(y, 0.0, np.array([0.001, 0.002]))
    with pytest.raises(ValueError, match=r"say which"):
        plant.applied_derivative(y[0], 0.0)
    uniform = Plant(BASE)
    with pytest.raises(ValueError, match=r"duration_s = -0\.001 \(rig 0\)"):
        uniform.advance(uniform.initial_state(np.zeros(2)), 0.0, np.array([-0.001, 0.0]))
    with pytest.raises(ValueError, match=r"duration_s has shape \(3,\)"):
        uniform.advance(uniform.initial_state(np.zeros(2)), 0.0, np.zeros(3))

"""Identification: the experiments' cores, the fit on simulated recordings,
and pisc_identify on bags: what it writes, and how it refuses bad input."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from pisc_robust.identify import identify
from pisc_robust.identify_data import (
    IdentifyError,
    QUANTISATION_RMS,
    Recording,
    parse_fit,
    read_recording,
    recording_from_arrays,
    rig_ticks,
)
from pisc_robust.identify_model import HELD_SAMPLES, Problem
from pisc_robust.identify_report import format_report
from pisc_robust.identify_segments import make_segments
from pisc_robust.identify_stats import quantisation_meat, stalled, within_standard_error
from pisc_bag.bag import BagWriter
from pisc_sim.closed_loop import simulate
from pisc_sim.configuration import load_graph_config, load_run_config
from pisc_control.excitation import ExperimentParams, excitation_signal, experiment_force, prbs_bits
from pisc_control.supervisor import Supervisor, SupervisorConfig, SupervisorState
from pisc_model.params import RigParams
from pisc_msgs_py.config import ConfigError, from_flat
from pisc_msgs_py.topics import CLOCK, JOINT_STATES, MOTOR_CURRENT, VOLTAGE
from pisc_msgs_py.types import Mode

TS = get_typestore(Stores.ROS2_JAZZY)

# a plant the controllers do not assume: the unknowns the excitation identifies
TRUTH = {"models.friction": "coulomb", "motor.resistance_ohm": 16.1,
         "motor.rotor_inertia_kgm2": 2.9e-6, "friction.cart_coulomb_n": 0.06,
         "friction.cart_viscous_ns_per_m": 0.3, "friction.pivot_viscous_nms": 3e-5}


# -- the experiments -----------------------------------------------------------------------


def test_prbs_is_the_order_9_maximum_length_sequence():
    bits = prbs_bits(1)
    assert len(bits) == 511 and int(bits.sum()) == 256  # 2^(n-1) ones in a period
    assert not np.array_equal(bits, prbs_bits(2))
    # a maximum-length sequence visits every non-zero 9-bit window once a period
    windows = {tuple(np.roll(bits, -k)[:9]) for k in range(511)}
    assert len(windows) == 511


def test_excitation_signals_are_bounded_and_start_late():
    t = np.arange(0.0, 30.0, 0.005)
    for signal in ("prbs", "chirp", "steps"):
        p = ExperimentParams(kind="excitation", signal=signal, amplitude_n=1.5, start_s=0.5)
        u = excitation_signal(p, t)
        assert np.all(u[t < 0.5] == 0.0) and np.abs(u).max() <= 1.5 + 1e-12
        assert np.abs(u[t >= 0.5]).max() > 1.4
    prbs = excitation_signal(ExperimentParams(kind="excitation", amplitude_n=1.0, bit_s=0.05), t)
    held = prbs[(t >= 0.5)].reshape(-1, 10)  # 50 ms bits of 10 samples
    assert np.all(held == held[:, :1]) and set(np.unique(prbs[t >= 0.5])) == {-1.0, 1.0}
    assert np.all(excitation_signal(ExperimentParams(kind="free_swing"), t) == 0.0)
    with pytest.raises(ConfigError, match="experiment.chirp_end_hz"):
        ExperimentParams(kind="excitation", signal="chirp", chirp_start_hz=5.0,
                         chirp_end_hz=1.0)


def test_a_level_spread_varies_each_bits_magnitude_and_keeps_its_sign():
    t = np.arange(0.0, 60.5, 0.005)
    plain = excitation_signal(ExperimentParams(kind="excitation", amplitude_n=1.7), t)
    p = ExperimentParams(kind="excitation", amplitude_n=1.7, level_spread=0.4)
    spread = excitation_signal(p, t)
    on = t >= 0.5
    assert np.array_equal(np.sign(spread), np.sign(plain))  # the PRBS's signs, bit for bit
    held = np.abs(spread[on]).reshape(-1, 10)  # 50 ms bits of 10 samples
    assert np.all(held == held[:, :1])  # one magnitude a bit
    levels = held[:, 0]
    assert levels.min() >= 0.6 * 1.7 - 1e-12 and levels.max() <= 1.7
    # a uniform draw per bit (1,200 bits): spread over the range, no level repeated, and
    # the 511-bit sequence's second period does not repeat the first's magnitudes
    assert len(np.unique(levels)) == len(levels)
    assert np.mean(levels) == pytest.approx(0.8 * 1.7, abs=0.02)
    assert np.histogram(levels, bins=4, range=(1.02, 1.7))[0].min() > 0.2 * len(levels) / 4
    assert not np.allclose(levels[:511], levels[511:1022])
    # a pure function of the time (a replay asks the same) and of the seed
    assert np.array_equal(excitation_signal(p, t[::-1])[::-1], spread)
    other = excitation_signal(ExperimentParams(kind="excitation", amplitude_n=1.7,
                                               level_spread=0.4, seed=2), t)
    assert not np.array_equal(np.abs(other), np.abs(spread))
    with pytest.raises(ConfigError, match="experiment.level_spread"):
        from_flat(ExperimentParams, {"experiment.level_spread": 1.0}, "experiment")


def test_the_guard_brakes_a_cart_that_would_stop_beyond_the_safe_range():
    p = ExperimentParams(kind="excitation", amplitude_n=1.0, margin_m=0.05,
                         position_k_x=0.0, position_k_v=0.0, start_s=0.0)
    rig = RigParams()
    limits = (-0.225, 0.125)
    # moving fast towards the far end: braked whatever the sequence says
    f = experiment_force(p, rig, limits, np.arange(0.0, 1.0, 0.005), -0.12, -0.6, 0.0)
    assert np.all(f == 1.0)
    f = experiment_force(p, rig, limits, np.arange(0.0, 1.0, 0.005), 0.05, 0.6, 0.0)
    assert np.all(f == -1.0)
    # free swing: the position loop holds the cart where the run began
    hold = ExperimentParams(kind="free_swing", position_k_x=4.0, position_k_v=2.0)
    assert experiment_force(hold, rig, limits, 1.0, 0.03, 0.0, 0.01) == pytest.approx(
        -rig.a2 * 4.0 * 0.02)


def test_the_supervisor_runs_the_experiment_and_keeps_its_fault_rules():
    flat = {"experiment.kind": "excitation", "experiment.start_s": 0.0}
    cfg = SupervisorConfig(experiment=from_flat(ExperimentParams, flat, "experiment"))
    sup = Supervisor(cfg)
    state = SupervisorState()
    forces = []
    for _ in range(40):  # hanging at rest: never a catch, the sequence's forces
        state, force, mode = sup.update(state, 0.0, 0.0, math.pi, 0.0)
        assert mode == Mode.SWING_UP.code
        forces.append(float(force))
    assert int(state.sample) == 39 and len(set(np.round(forces, 9))) > 1
    assert sup.experiment_reason() == "experiment: excitation (prbs)"
    # upright and still: a swing-up supervisor would catch, the experiment does not
    _, _, mode = sup.update(state, 0.0, 0.0, 0.0, 0.0)
    assert mode == Mode.SWING_UP.code
    # out of the safe range: fault, no force, latched
    state, force, mode = sup.update(state, 0.2, 0.0, math.pi, 0.0)
    assert mode == Mode.FAULT.code and force == 0.0
    state, force, mode = sup.update(state, 0.0, 0.0, math.pi, 0.0)
    assert mode == Mode.FAULT.code and force == 0.0


@pytest.fixture(scope="module")
def excitation_log():
    config, _, _ = load_run_config("default", {"experiment.kind": "excitation",
                                               "experiment.amplitude_n": 1.5},
                                   plant_overrides=TRUTH)
    return config, simulate(config, 20.0)


def recording_of(log, **kwargs) -> Recording:
    return recording_from_arrays("sim", 0.005, log["x"], log["theta"], log["i"], log["u"],
                                 experiment="excitation", **kwargs)


def test_identify_recovers_the_plant_of_a_simulated_excitation(excitation_log):
    config, log = excitation_log
    fit = parse_fit("R,J_m,cart_coulomb,cart_viscous,pivot_viscous")
    result = identify([recording_of(log)], fit, config.plant)  # the nominal model's start
    print(format_report(result))
    got = {e.unknown.name: e for e in result.estimates}
    assert set(got) == {u.name for u in fit}
    for name, tolerance in (("motor.resistance_ohm", 0.01), ("motor.rotor_inertia_kgm2", 0.05),
                            ("friction.cart_coulomb_n", 0.05),
                            ("friction.cart_viscous_ns_per_m", 0.05),
                            ("friction.pivot_viscous_nms", 0.05)):
        e = got[name]
        assert abs(e.value - TRUTH[name]) <= tolerance * TRUTH[name], (name, e)
        assert e.low < e.value < e.high
    # the residual is the sensors' quantisation: nothing else is left
    assert np.all(result.residual_rms < 0.35)
    assert not result.segments.left_out


def test_l_with_an_unknown_delay_is_reported_not_identifiable(excitation_log):
    config, log = excitation_log
    result = identify([recording_of(log)], parse_fit("R,L,delay"), config.plant)
    assert "L" in [e.unknown.key for e in result.not_identifiable]
    assert "L" not in [e.unknown.key for e in result.estimates]
    assert "acts only as a delay" in format_report(result)


def test_segments_at_an_end_stop_or_after_a_gap_are_left_out_and_said_so(excitation_log):
    config, log = excitation_log
    x = log["x"].copy()
    s = config.plant.sensors
    from pisc_model import sensors

    # the IR code saturated at the sensor's end for 50 ms: the cart at the stop
    x[1000:1010] = sensors.ir_position(s, sensors.adc_voltage(s, s.adc_levels - 1))
    stamps_ok = recording_of({**{k: log[k] for k in ("theta", "i", "u")}, "x": x})
    segments = make_segments([stamps_ok], s, 0.005)
    reasons = {reason for *_, reason in segments.left_out}
    assert reasons == {"the cart at an end stop (IR reading saturated)"}
    # a missing sample breaks the run: no segment spans it
    rec = recording_of(log)
    keep = np.ones(len(rec.stamps_ns), dtype=bool)
    keep[2000] = False
    gap = Recording(rec.name, rec.stamps_ns[keep], rec.x[keep], rec.theta[keep],
                    rec.current[keep], rec.voltage[keep], rec.latency_s[keep], False)
    segments = make_segments([gap], s, 0.005)
    assert any(r == "a sample missing or out of time" for *_, r in segments.left_out)
    assert all(not (f < 2000 < f + n) for f, n in zip(segments.first, segments.size,
                                                      strict=True))


def test_a_fit_without_voltage_or_with_an_unknown_name_is_refused(excitation_log):
    config, log = excitation_log
    zero = recording_of({"x": log["x"], "theta": log["theta"], "i": log["i"],
                         "u": np.zeros_like(log["u"])})
    with pytest.raises(IdentifyError, match="the recorded voltage is zero throughout"):
        identify([zero], parse_fit("R"), config.plant)
    with pytest.raises(IdentifyError, match="--fit Rm: no such parameter"):
        parse_fit("R,Rm")


# -- pisc_identify on bags -------------------------------------------------------------


def _cdr(type_name: str, stamp_ns: int, names: list[str], frame_id: str = "",
         **fields) -> bytes:
    msg = TS.types[type_name]
    header = TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                      nanosec=stamp_ns % 10**9),
        frame_id=frame_id)
    empty = np.array([], dtype=float)
    values = {"position": empty, "velocity": empty, "effort": empty}
    values.update({k: np.asarray(v, dtype=float) for k, v in fields.items()})
    return bytes(TS.serialize_cdr(msg(header=header, name=names, **values), type_name))


def write_bag(path, log, topics=(JOINT_STATES, MOTOR_CURRENT, VOLTAGE), voltage=None):
    """A bag of a simulated run's measurements and voltages (lockstep stamps)."""
    writer = BagWriter(path, list(topics) + [CLOCK])
    js = "sensor_msgs/msg/JointState"
    u = log["u"] if voltage is None else voltage
    for k in range(len(log["x"])):
        stamp = k * 5_000_000
        wall = 1_800_000_000_000_000_000 + k * 2_000_000
        if JOINT_STATES in topics:
            writer.write(JOINT_STATES.name, _cdr(js, stamp, ["cart", "pendulum"],
                                                 position=[log["x"][k], log["theta"][k]]),
                         wall, wall)
        if MOTOR_CURRENT in topics:
            writer.write(MOTOR_CURRENT.name, _cdr(js, stamp, ["motor"], effort=[log["i"][k]]),
                         wall, wall)
        if VOLTAGE in topics:
            writer.write(VOLTAGE.name, _cdr(js, stamp, ["motor"], effort=[u[k]]), wall + 500,
                         wall + 500)
    writer.close()
    return path


def run_identify(*args):
    return subprocess.run([sys.executable, "-m", "pisc_robust.identify_cli", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def test_pisc_identify_writes_a_parameter_file_the_tools_accept(tmp_path, excitation_log):
    config, log = excitation_log
    bag = write_bag(tmp_path / "run", {k: log[k][:3001] for k in ("x", "theta", "i", "u")})
    out = tmp_path / "identified.yaml"
    done = run_identify(bag, "--config", "default", "--out", out, "--fit",
                        "R,J_m,cart_coulomb,cart_viscous,pivot_viscous")
    assert done.returncode == 0, done.stderr
    print(done.stdout)
    assert "95 % interval" in done.stdout and "residual RMS" in done.stdout
    assert out.with_suffix(".png").stat().st_size > 10_000
    graph, flat = load_graph_config(str(out))  # pisc_robustness and pisc_tune read it so
    assert graph.supervisor.experiment.kind == "none"  # a configuration that swings up
    assert graph.plant.models.friction == "coulomb"
    assert graph.plant.motor.resistance_ohm == pytest.approx(16.1, rel=0.01)
    run, _, _ = load_run_config("default", plant=str(out))  # ./pisc run --plant-config
    assert run.true_plant.friction.cart_coulomb_n == pytest.approx(0.06, rel=0.1)


@pytest.mark.parametrize("case", ["no measured topics", "zero voltage", "unknown parameter",
                                  "no convergence", "not a bag"])
def test_pisc_identify_refuses_bad_input_without_a_traceback_and_writes_nothing(
        tmp_path, excitation_log, case):
    config, log = excitation_log
    short = {k: log[k][:1001] for k in ("x", "theta", "i", "u")}
    args: list = ["--config", "default"]
    if case == "no measured topics":
        bag = write_bag(tmp_path / "run", short, topics=(VOLTAGE,))
        expect, status = "the bag has no /pisc/joint_states and no /pisc/motor/current", 2
    elif case == "zero voltage":
        bag = write_bag(tmp_path / "run", short, voltage=np.zeros(1001))
        expect, status = "the recorded voltage is zero throughout", 2
    elif case == "unknown parameter":
        bag = write_bag(tmp_path / "run", short)
        args += ["--fit", "R,inertia"]
        expect, status = "--fit inertia: no such parameter", 2
    elif case == "no convergence":
        bag = write_bag(tmp_path / "run", short)
        args += ["--fit", "R,J_m", "--max-evaluations", "1"]
        expect, status = "the fit did not converge within 1 evaluations", 1
    else:
        bag = tmp_path / "nothing"
        bag.mkdir()
        expect, status = "not a rosbag2 directory", 2
    out = tmp_path / "out" / "identified.yaml"
    done = run_identify(bag, *args, "--out", out)
    assert done.returncode == status, done.stdout + done.stderr
    assert expect in done.stderr and "nothing written" in done.stderr
    assert "Traceback" not in done.stderr + done.stdout
    assert not out.exists() and not out.with_suffix(".png").exists()


def test_the_quantisation_floor_adds_the_held_rows_of_one_code_coherently():
    # rows 0-2: the current held at code 512 (one shared error); rows 3-4: the encoder
    # held at two counts; row 5: the IR channel held; row 6: the IR passing through
    # code 300 (not held: its error is its own, the sandwich's). Each held group's error
    # is one uniform draw over its step, so its rows' Jacobian rows add before squaring.
    from types import SimpleNamespace

    jac = np.array([[1.0, 0.0], [1.0, 0.5], [1.0, -0.5], [0.0, 2.0], [0.0, -2.0], [3.0, 1.0],
                    [5.0, 5.0]])
    problem = SimpleNamespace(
        weights=np.array([2.0, 1.0, 0.5]),  # IR, encoder, current
        row_codes=lambda: (np.array([512, 512, 512, 7, 8, 300, 300]),
                           np.array([2, 2, 2, 1, 1, 0, 0]),
                           np.array([True] * 6 + [False])))
    meat = quantisation_meat(problem, jac)
    held = 0.5 * np.array([3.0, 0.0])  # the current's weight times its three rows' sum
    counts = [np.array([0.0, 2.0]), np.array([0.0, -2.0])]  # two counts: apart
    ir = 2.0 * np.array([3.0, 1.0])
    want = (np.outer(held, held) + sum(np.outer(c, c) for c in counts) + np.outer(ir, ir)) / 12
    assert meat == pytest.approx(want)
    # the held level's three rows count as one error: 9 times one row's share, not 3 times
    assert meat[0, 0] == pytest.approx((0.5 ** 2 * 9 + 2.0 ** 2 * 9) / 12)


def test_the_fit_stops_within_a_hundredth_of_a_standard_error_of_the_optimum():
    # a linear model y = J z + e: the optimum is z* = lstsq(J, y), Gauss-Newton's step
    # from z is z* - z, and each unknown's standard error is s sqrt((J^T J)^-1)_kk
    rng = np.random.default_rng(3)
    jac = rng.normal(size=(400, 3)) * np.array([1.0, 10.0, 0.1])
    y = jac @ np.array([1.0, -2.0, 3.0]) + rng.normal(size=400)
    best, *_ = np.linalg.lstsq(jac, y, rcond=None)
    s2 = float(np.sum((y - jac @ best) ** 2)) / (400 - 3)
    std = np.sqrt(np.diag(np.linalg.inv(jac.T @ jac)) * s2)
    wide = (np.full(3, -1e9), np.full(3, 1e9))

    def within(z, fraction=None):
        return within_standard_error(jac, jac @ z - y, z, *wide, fraction)

    assert within(best)
    for k in range(3):  # 0.005 of a standard error off in any one unknown: close enough
        assert within(best + 0.005 * std * np.eye(3)[k])
        assert not within(best + 0.02 * std * np.eye(3)[k])
        assert within(best + 0.02 * std * np.eye(3)[k], fraction=0.05)
    # an optimum beyond a bound: the step ends at the bound, so a point on it has arrived
    low = np.array([-1e9, -1e9, best[2] + 5 * std[2]])
    at_bound = best.copy()
    at_bound[2] = low[2]
    z = at_bound.copy()
    # (the other unknowns at their optimum given the bound: one linear solve)
    z[:2], *_ = np.linalg.lstsq(jac[:, :2], y - jac[:, 2] * z[2], rcond=None)
    assert within_standard_error(jac, jac @ z - y, z, low, np.full(3, 1e9))


def test_a_fit_whose_steps_gain_less_than_a_quarter_standard_error_has_stalled():
    # cost = sum of squares; s^2 = cost / dof = 1 here: a move of f standard errors
    # changes the cost by f^2, so five iterations gaining under 1/16 in all have stalled
    dof = 1000
    assert not stalled([1100.0, 1000.0], dof)  # too few iterations to tell
    crawl = [1000.0 + 0.012 * k for k in range(6)][::-1]  # 0.06 over the last five
    assert stalled(crawl, dof)
    assert not stalled([1000.0 + 0.014 * k for k in range(6)][::-1], dof)  # 0.07
    # only the last five count: an early drop does not keep a crawl going
    assert stalled([5000.0] + crawl, dof)
    # the threshold scales with the residuals' mean square: 0.07 with s^2 = 2 has stalled
    assert stalled([1000.0 + 0.014 * k for k in range(6)][::-1], dof // 2)


def test_a_fit_stops_by_the_rule_after_its_first_accepted_step(excitation_log, monkeypatch):
    # the rule wired into least_squares: with a rule that always holds, each pass stops
    # at its first accepted step, and says why
    config, log = excitation_log
    seen = []

    def always(jac, r, z, low, high, fraction=None):
        seen.append((jac.shape, r.shape, z.shape))
        return True

    import pisc_robust.identify as identify_module

    monkeypatch.setattr(identify_module, "within_standard_error", always)
    lines: list[str] = []
    result = identify([recording_of(log)], parse_fit("R,cart_viscous"), config.plant,
                      progress=lines.append)
    said = [line for line in lines if "evaluations" in line]
    assert len(said) == 2 and all("the next step under 0.01 of a standard error" in line
                                  for line in said), lines
    assert result.iterations <= 2 * 5  # each pass: its start, a rejected step or so, one kept
    # the rule saw the accepted point's Jacobian, residuals and unknowns
    assert seen and all(j[1] == 2 and r == (j[0],) and z == (2,) for j, r, z in seen)


def test_held_rows_are_runs_of_one_code(excitation_log):
    config, log = excitation_log
    segments = make_segments([recording_of(log)], config.plant.sensors, 0.005)
    fit = parse_fit("R")
    problem = Problem(segments, config.plant, fit, {"R": 14.0, "delay": 0.0,
                                                    "current_offset": 0.0})
    codes, channel, held = problem.row_codes()
    assert len(codes) == len(problem.rows) and held.any() and not held.all()
    # runs of one code at least HELD_SAMPLES long, rebuilt by hand along the first segment
    for c in (0, 1, 2):
        first = codes[channel == c][:segments.size[0]]
        runs = np.split(first, np.flatnonzero(np.diff(first)) + 1)
        want = np.concatenate([np.full(len(r), len(r) >= HELD_SAMPLES) for r in runs])
        assert np.array_equal(held[channel == c][:segments.size[0]], want)


def test_the_intervals_include_the_quantisation_floor(excitation_log):
    # noise-free quantised sensors: every estimate's variance is at least the floor's
    config, log = excitation_log
    fit = parse_fit("R,J_m,cart_coulomb,cart_viscous")
    calls = []
    result = identify([recording_of(log)], fit, config.plant,
                      on_evaluation=lambda *a: calls.append(a))
    # the hook: every evaluation of both passes (lockstep: no timing passes), in order
    assert calls[0] == (0, 2, 1) and {c[0] for c in calls} == {0, 1}
    assert all(c[1] == 2 for c in calls) and len(calls) >= result.iterations
    segments = result.segments
    problem = Problem(segments, config.plant, fit,
                      {**{e.unknown.key: e.value for e in result.fitted},
                           "delay": 0.0, "current_offset": 0.0})
    z = np.array([e.value / e.unknown.scale for e in result.fitted])
    problem.weights = 1.0 / np.maximum(result.residual_rms, QUANTISATION_RMS)
    jac = problem.jacobian(z)
    inverse = np.linalg.pinv(jac.T @ jac)
    floor = np.diag(inverse @ quantisation_meat(problem, jac) @ inverse)
    std = np.array([e.std / e.unknown.scale for e in result.fitted])
    assert np.all(std ** 2 >= 0.99 * floor), (std ** 2, floor)
    assert np.all(floor > 0.0)


def test_through_the_driver_the_bytes_as_written_time_each_voltage(tmp_path):
    """A bag with /pisc/motor/voltage_sent (the driver's record of each byte written):
    each voltage is the one its byte encodes and acts from the write's time, not the
    controllers' publication; a sample answered late (no byte) or in whose period the
    driver wrote 0 V of its own has no voltage and its period is left out; a hold (the
    last byte again) changes nothing."""
    from pisc_msgs_py.topics import VOLTAGE_SENT

    js = "sensor_msgs/msg/JointState"
    n, t0, period = 400, 1_800_000_000_000_000_000, 5_000_000

    def bag(with_sent: bool):
        path = tmp_path / f"driver-{with_sent}"
        writer = BagWriter(path, [JOINT_STATES, MOTOR_CURRENT, VOLTAGE, VOLTAGE_SENT])
        for k in range(n):
            stamp = t0 + k * period
            writer.write(JOINT_STATES.name, _cdr(js, stamp, ["cart", "pendulum"],
                                                 position=[0.0, math.pi]), stamp + 20_000,
                         stamp + 10_000)
            writer.write(MOTOR_CURRENT.name, _cdr(js, stamp, ["motor"], effort=[0.1]),
                         stamp + 20_000, stamp + 10_000)
            writer.write(VOLTAGE.name, _cdr(js, stamp, ["motor"], effort=[1.0]),
                         stamp + 900_000, stamp + 810_000)
            if with_sent and k != 100:  # sample 100: its answer came too late to send
                writer.write(VOLTAGE_SENT.name, _cdr(js, stamp, ["motor"], "answer",
                                                     effort=[0.993]),
                             stamp + 1_400_000, stamp + 1_310_000)
            if with_sent and k == 200:  # the driver's own 0 V in sample 200's period
                writer.write(VOLTAGE_SENT.name, _cdr(js, stamp, ["motor"], "zero",
                                                     effort=[0.0]),
                             stamp + 4_100_000, stamp + 4_000_000)
            if with_sent and k == 300:  # a hold: the last byte again, nothing changes
                writer.write(VOLTAGE_SENT.name, _cdr(js, stamp, ["motor"], "hold",
                                                     effort=[0.993]),
                             stamp + 200_000, stamp + 100_000)
        writer.close()
        return read_recording(path)

    plain, written = bag(False), bag(True)
    assert plain.wall_clock and written.wall_clock
    np.testing.assert_allclose(plain.latency_s, 0.8e-3, rtol=1e-9)
    np.testing.assert_array_equal(plain.voltage, 1.0)
    answered = np.ones(n, dtype=bool)
    answered[[100, 200]] = False
    np.testing.assert_allclose(written.latency_s[answered], 1.3e-3, rtol=1e-9)
    np.testing.assert_array_equal(written.voltage[answered], 0.993)
    assert np.isnan(written.voltage[[100, 200]]).all()
    config = load_run_config("default")[0].plant
    segments = make_segments([written], config.sensors, 0.005)
    gaps = [(a, b) for _, a, b, why in segments.left_out
            if why == "no answer written to the rig, or 0 V of the driver's own"]
    assert gaps == [(pytest.approx(0.5), pytest.approx(0.505)),
                    (pytest.approx(1.0), pytest.approx(1.005))], segments.left_out


def test_the_rigs_ticks_and_the_reads_delays_come_from_the_stamps():
    """A rig ticks every period on its own clock (here 20 ppm slow against the host's);
    the driver stamps each frame when it reads it. Stamps against the ticks' line give
    each read's delay (from the earliest) and each sample's tick, a lost frame skipping
    one, even when the reads around it were late; a stall longer than the estimate's
    window (one second) is not taken for lost frames: no estimate then."""
    rng = np.random.default_rng(4)
    n, period = 6000, 0.005
    ticks = np.arange(n + 3)
    delay = 0.0004 + rng.exponential(0.0008, n + 3)  # a floor, and late reads
    delay[rng.integers(0, n, 60)] += 0.012  # stalls past two periods
    delay[2995:3001] += np.linspace(0.0, 0.004, 6)  # late reads up to a lost frame

    def stamps(keep, drift=20e-6):
        t = ticks[keep] * period * (1 + drift) + delay[keep]
        return (1_800_000_000 * 10**9 + np.round(t * 1e9)).astype(np.int64)

    keep = np.delete(np.arange(n + 3), [3000, 4500, 4501])  # three frames lost
    # (300 ppm: 9 ms, almost two periods, in 30 s; it tilts each second's least stamp
    # by up to 0.3 ms, which biases the line by some 10 us)
    for drift, atol in ((20e-6, 2e-6), (-300e-6, 2e-5)):
        found, read = rig_ticks(stamps(keep, drift), period)
        np.testing.assert_array_equal(found, keep)
        np.testing.assert_allclose(read, delay[keep] - delay[keep].min(), atol=atol)
    delay[1000:1300] += 0.004  # every read of 1.5 s late by 4 ms
    assert rig_ticks(stamps(keep), period) is None
    assert rig_ticks(stamps(keep)[:300], period) is None  # shorter than two windows

"""The whole graph over ROS 2 topics: acceptance, exactness, clocks, processes."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from conftest import DomainClaim
from pisc_bag.bag import read_bag
from pisc_sim.closed_loop import simulate
from pisc_sim.configuration import load_graph_config, load_run_config
from pisc_bringup.graph import RunOptions, run_graph
from pisc_bringup.graph_cli import main
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError, load_params_file
from pisc_msgs_py.convert import mode_from_msg, motor_sample_from_msg
from pisc_msgs_py.topics import DIAGNOSTICS, GRAPH_TOPICS, JOINT_STATES, MODE, STATE, VOLTAGE
from pisc_msgs_py.types import Mode

pytestmark = pytest.mark.integration

STARTS = (-0.10, -0.05, 0.0, 0.05, 0.10)


def assert_acceptance(summary):
    """Caught within 3.0 s of sim time, held from 6 s, cart inside the safe range
    (which lies inside the IR sensor's)."""
    assert summary.caught_at_s is not None and summary.caught_at_s <= 3.0, summary.format()
    assert summary.held and summary.hold_theta_rad < 0.05 and summary.hold_x_m < 0.02
    assert summary.state_source == "true"
    # inside the safe range (safety.x_min_m, x_max_m), within the IR sensor's -0.225 .. +0.127 m
    assert -0.225 <= summary.x_range_m[0] and summary.x_range_m[1] <= 0.125, summary.format()
    assert summary.duration_s >= 10.0 and not summary.faults


@pytest.fixture(scope="module")
def lockstep_runs(tmp_path_factory):
    runs = {}
    for x0 in STARTS:
        claim = DomainClaim()
        try:
            runs[x0] = run_graph(RunOptions(
                overrides={"initial.x_m": x0}, duration_s=10.0, clock="lockstep",
                bag_dir=tmp_path_factory.mktemp("bags") / f"x0_{x0}",
                domain_id=claim.domain_id))
        finally:
            claim.release()
    return runs


@pytest.mark.parametrize("x0", STARTS)
def test_lockstep_graph_swings_up_and_holds(lockstep_runs, x0):
    assert_acceptance(lockstep_runs[x0].summary)


def test_every_topic_is_recorded_once_per_cycle(lockstep_runs):
    result = lockstep_runs[0.05]
    cycles = result.summary.cycles
    for topic in ("/pisc/joint_states", "/pisc/motor/current", "/pisc/state",
                  "/pisc/cart_force", "/pisc/motor/current_setpoint", "/pisc/motor/voltage"):
        # the plant may have published the sample after the last voltage: at most one more
        assert result.recorded[topic] in (cycles, cycles + 1), (topic, result.recorded)
    assert result.recorded[MODE.name] == 2  # swing_up at the start, catch once
    assert set(result.recorded) == {t.name for t in GRAPH_TOPICS}


def recorded_voltages(bag_dir):
    """The bag's voltages in the order of their stamps."""
    voltages = {}
    for m in read_bag(bag_dir, [VOLTAGE.name]):
        sample = motor_sample_from_msg(m.message)
        voltages[sample.stamp_ns] = sample.value
    return np.array([voltages[s] for s in sorted(voltages)])


def test_lockstep_graph_reproduces_the_pure_closed_loop_bit_for_bit(lockstep_runs):
    """Same cores, same order: every voltage of the ROS run equals the pure simulation's."""
    result = lockstep_runs[0.05]
    cfg, _ = load_graph_config("default", {"initial.x_m": 0.05})
    log = simulate(cfg, 10.0)
    recorded = recorded_voltages(result.bag_dir)
    assert len(recorded) == len(log["u"])
    assert np.array_equal(recorded, log["u"])


def test_a_plant_with_model_error_runs_its_own_parameters_bit_for_bit(tmp_path, domain_id,
                                                                      capfd):
    """pisc_graph --plant-set: the plant node runs R = 18.2 ohm, the controllers keep the
    14 ohm they were designed on; the bag keeps both files, the header says so, and the
    voltages are the pure simulation's of the same load_run_config, bit for bit."""
    bag = tmp_path / "model-error"
    status = main(["--x0", "0.05", "--duration", "3", "--bag", str(bag), "--domain-id",
                   str(domain_id), "--plant-set", "motor.resistance_ohm=18.2"])
    out = capfd.readouterr().out  # capfd: the EventsExecutor needs a real stderr
    assert status in (0, 1), out
    assert "; plant: default with motor.resistance_ohm=18.2" in out.splitlines()[0]
    assert load_params_file(bag / "plant_params.yaml")["motor.resistance_ohm"] == 18.2
    assert load_params_file(bag / "pisc_params.yaml")["motor.resistance_ohm"] == 14.0
    cfg, _, _ = load_run_config("default", {"initial.x_m": 0.05},
                                plant_overrides={"motor.resistance_ohm": 18.2})
    # the K the run used, to the bit, for a replay on another machine (catch.recorded_gain)
    assert load_params_file(bag / "pisc_params.yaml")["catch.recorded_gain"] == [
        float(k) for k in Supervisor(cfg.supervisor).gain]
    log = simulate(cfg, 3.0)
    recorded = recorded_voltages(bag)
    assert len(recorded) == len(log["u"])
    assert np.array_equal(recorded, log["u"])
    # the model error shows: the plant without it gives other voltages
    assert not np.array_equal(recorded, simulate(load_graph_config(
        "default", {"initial.x_m": 0.05})[0], 3.0)["u"])


@pytest.mark.parametrize("plant_set,named", [
    ("swing_up.k_v=1", ["swing_up.k_v", "the plant does not read section 'swing_up'"]),
    ("motor.nosuch=1", ["motor.nosuch", "unknown parameter"]),
    ("motor.resistance_ohm=-1", ["motor.resistance_ohm", "positive"]),
])
def test_a_bad_plant_override_exits_2_naming_it_and_leaves_no_bag(tmp_path, domain_id, capsys,
                                                                  plant_set, named):
    bag = tmp_path / "refused"
    status = main(["--duration", "1", "--bag", str(bag), "--domain-id", str(domain_id),
                   "--plant-set", plant_set])
    err = capsys.readouterr().err
    assert status == 2
    assert all(text in err for text in named), err
    assert "Traceback" not in err
    assert not bag.exists()


def test_plant_options_are_refused_with_the_driver(tmp_path, capsys):
    """Through the serial driver the plant is the device (the rig, or pisc_virtual_rig
    with a parameter file of its own): nothing here could set its parameters."""
    bag = tmp_path / "driver"
    assert main(["--driver", "/dev/null", "--bag", str(bag), "--plant-set",
                 "motor.resistance_ohm=18.2"]) == 2
    assert "the plant is the device: start pisc_virtual_rig" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="the plant is the device"):
        run_graph(RunOptions(clock="wall", driver_port="/dev/null", plant_config="thesis",
                             bag_dir=bag))
    assert not bag.exists()


def test_a_scenes_plant_block_and_plant_set_reach_the_run(tmp_path, monkeypatch):
    """pisc_graph --scene: the scene's plant: block goes to the plant, --plant-set after it."""
    import pisc_bringup.graph_cli as graph_cli

    scene = tmp_path / "scene.yaml"
    scene.write_text("scene:\n  plant: {motor: {resistance_ohm: 18.2, inductance_h: 0.02}}\n")
    seen = []

    def refuse(options):
        seen.append(options)
        raise ConfigError("stop here")

    monkeypatch.setattr(graph_cli, "run_graph", refuse)
    assert main(["--scene", str(scene), "--plant-set", "motor.inductance_h=0.03",
                 "--plant-config", "thesis"]) == 2
    assert seen[0].plant_overrides == {"motor.resistance_ohm": 18.2, "motor.inductance_h": 0.03}
    assert seen[0].plant_config == "thesis" and seen[0].config == "default"


@pytest.mark.realtime
def test_wall_clock_graph_in_one_process_catches(tmp_path, domain_id):
    result = run_graph(RunOptions(overrides={"initial.x_m": 0.0}, duration_s=10.0,
                                  clock="wall", bag_dir=tmp_path / "wall", domain_id=domain_id))
    assert_acceptance(result.summary)
    # a real-time run measures latency per cycle from the recorded send times
    assert result.summary.latency_ms["median"] < 5.0


def test_nodes_as_separate_processes_through_their_entry_points(tmp_path, env_for_domain):
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--processes", "--x0", "-0.05",
         "--duration", "10", "--bag", str(tmp_path / "procs")],
        env=env_for_domain, capture_output=True, text=True, timeout=240)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    assert "separate processes" in completed.stdout
    assert "entry points: estimator_node, supervisor_node, current_loop_node, plant_node" in (
        completed.stdout)
    assert "result                 CAUGHT" in completed.stdout
    # with --processes the runner counts nothing the nodes publish: a message of each
    # sample topic per sample is expected (run_start.expected_messages)
    assert "the bag misses" not in completed.stderr, completed.stderr


def test_a_lockstep_run_expects_a_message_of_each_sample_topic_per_sample():
    """What --processes is checked against: samples 0 .. duration / period, each with a
    message on each recorded sample topic; a bag with fewer says what it misses."""
    from pisc_bringup.graph import RunResult
    from pisc_bringup.run_start import SAMPLE_TOPICS, expected_messages
    from pisc_msgs_py.topics import SIM_STATE

    expected = expected_messages(1.0, 0.005, GRAPH_TOPICS)
    assert expected == {t.name: 201 for t in SAMPLE_TOPICS}
    assert SIM_STATE.name not in expected_messages(
        1.0, 0.005, [t for t in GRAPH_TOPICS if t is not SIM_STATE])
    assert expected_messages(10.0, 0.005, GRAPH_TOPICS)[VOLTAGE.name] == 2001
    recorded = {**expected, STATE.name: 180, VOLTAGE.name: 202}  # 202: one sent again
    result = RunResult(None, None, recorded, 0.0, [], expected)
    assert result.missing == {STATE.name: 21}


def test_a_run_that_does_not_finish_says_what_the_recorder_wrote():
    """A run stopped by its wall-time limit (one that stood still) names what the bag
    holds of each topic, so that it says which topic the recorder lacked."""
    from pisc_bringup.graph import not_finished

    said = not_finished(1.0, 60.0, 100_000_000, {JOINT_STATES.name: 21, STATE.name: 0})
    assert said == ("the run did not reach 1.0 s within 60 s of wall time (last voltage "
                    "stamp: 100000000); the recorder wrote /pisc/joint_states 21, "
                    "/pisc/state 0")
    assert not_finished(1.0, 60.0, None, {}).endswith(
        "(last voltage stamp: None); the recorder said nothing of what it wrote")


def test_a_run_is_stopped_at_its_wall_time_limit_even_while_busy(tmp_path, domain_id):
    """RunOptions.timeout_s holds for a lockstep run that keeps its executor busy (the
    EventsExecutor's own timeout did not: a 10 s run given 0.2 s ran to its end, about
    1 s of wall time at best here); the error says what the recorder wrote."""
    from pisc_bringup.graph import GraphError

    with pytest.raises(GraphError) as info:
        run_graph(RunOptions(duration_s=10.0, timeout_s=0.2, bag_dir=tmp_path / "limit",
                             domain_id=domain_id))
    said = str(info.value)
    assert said.startswith("the run did not reach 10.0 s within 0.2 s of wall time"), said
    wrote = dict(part.rsplit(" ", 1) for part in said.split("; the recorder wrote ")[1]
                 .split(", "))
    assert set(wrote) == {t.name for t in GRAPH_TOPICS}, said
    assert int(wrote[VOLTAGE.name]) < 2001, said
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ConfigError, match=f"timeout_s = {bad}: must be a finite number "
                           r"of seconds > 0 \(None: by the duration\)"):
            run_graph(RunOptions(duration_s=10.0, timeout_s=bad, bag_dir=tmp_path / "bad",
                                 domain_id=domain_id))


def test_leaving_the_safe_range_goes_to_zero_volts_and_says_why(tmp_path, domain_id):
    """A fault mid-run: no force, 0 V from the current loop, /diagnostics says why."""
    # the previous default: the default's track guard keeps the cart inside this range
    result = run_graph(RunOptions(
        config="lyapunov-tuned",
        overrides={"initial.x_m": 0.05, "safety.x_min_m": -0.03}, duration_s=2.0,
        bag_dir=tmp_path / "fault", domain_id=domain_id))
    fault_stamp = None
    voltages = []
    errors = []
    for m in read_bag(result.bag_dir, [MODE.name, VOLTAGE.name, DIAGNOSTICS.name]):
        if m.topic == MODE.name:
            report = mode_from_msg(m.message)
            if report.mode is Mode.FAULT:
                fault_stamp = report.stamp_ns
        elif m.topic == VOLTAGE.name:
            voltages.append(motor_sample_from_msg(m.message))
        else:
            errors += [s.message for s in m.message.status if s.level == 2]
    assert fault_stamp is not None
    after = [v.value for v in voltages if v.stamp_ns > fault_stamp]
    assert after and all(v == 0.0 for v in after)
    assert any("outside the safe range" in e and "safety.x_min_m" in e for e in errors), errors
    assert result.summary.faults and not result.summary.caught


def test_a_scene_runs_through_the_graph_with_an_ideal_force_source(tmp_path, env_for_domain):
    """pisc_graph --scene: the ideal cart-pole scene through ROS 2 topics; the plant node
    takes the force of the current set-point (the ideal current loop) and the lockstep run
    reproduces the pure closed loop of the same scene, set-point for set-point."""
    from pisc_sim.scene import load_scene

    bag = tmp_path / "ideal"
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_bringup.graph_cli", "--scene", "ideal-cart-pole", "--bag",
         str(bag)], env=env_for_domain, capture_output=True, text=True, timeout=240)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    assert "result                 CAUGHT" in completed.stdout
    log = simulate(load_scene("ideal-cart-pole").config, 10.0)
    setpoints = sorted((motor_sample_from_msg(m.message) for m in
                        read_bag(bag, ["/pisc/motor/current_setpoint"])),
                       key=lambda s: s.stamp_ns)
    stamps = np.array([s.stamp_ns for s in setpoints])
    recorded = np.array([s.value for s in setpoints])
    assert len(recorded) > 1000
    index = np.round(stamps / 5e6).astype(int)  # lockstep: sample k is stamped k * 5 ms
    assert np.array_equal(recorded, log["i_d"][index])


def test_pisc_graph_starts_what_its_launch_file_says(tmp_path, domain_id):
    """pisc_graph --launch FILE: a launch file naming the estimator 'estimator_b' runs a
    node of that name (its diagnostics say so; no node 'estimator' runs), and the graph
    still catches the pendulum in the same cycles as the shipped file's."""
    from test_launch import edited_launch

    path = edited_launch(tmp_path, "sim", 'name="estimator"', 'name="estimator_b"')
    result = run_graph(RunOptions(overrides={"initial.x_m": 0.05}, duration_s=2.5,
                                  bag_dir=tmp_path / "renamed", domain_id=domain_id,
                                  launch=str(path)))
    names = {s.name for m in read_bag(result.bag_dir, [DIAGNOSTICS.name])
             for s in m.message.status}
    assert names == {"pisc/estimator_b", "pisc/supervisor", "pisc/current_loop",
                     "pisc/plant"}, names
    cfg, _ = load_graph_config("default", {"initial.x_m": 0.05})
    assert np.array_equal(recorded_voltages(result.bag_dir), simulate(cfg, 2.5)["u"])

"""The identification benchmark: its excitation scene, how it reports each recording's
timing, and the hidden rigs it draws."""

from __future__ import annotations

import numpy as np

from pisc_sim.closed_loop import simulate
from pisc_sim.configuration import load_run_config
from pisc_msgs_py.types import Mode

# a plant the controllers do not assume: the unknowns the excitation identifies
TRUTH = {"models.friction": "coulomb", "motor.resistance_ohm": 16.1,
         "motor.rotor_inertia_kgm2": 2.9e-6, "friction.cart_coulomb_n": 0.06,
         "friction.cart_viscous_ns_per_m": 0.3, "friction.pivot_viscous_nms": 3e-5}


def test_the_excitation_scene_stays_inside_the_safe_range():
    from pisc_bench.identify_bench import scene_experiment

    experiment, duration = scene_experiment()  # the shipped scene: 60 s at +-1.02-1.7 N
    assert experiment["experiment.kind"] == "excitation" and duration == 60.0
    assert experiment["experiment.level_spread"] == 0.4
    for plant in (TRUTH, {**TRUTH, "motor.resistance_ohm": 9.8,
                          "motor.rotor_inertia_kgm2": 1.0e-6,
                          "friction.cart_coulomb_n": 0.0, "friction.cart_viscous_ns_per_m": 0.0}):
        config, _, _ = load_run_config("default", experiment, plant_overrides=plant)
        log = simulate(config, 20.0)
        assert not np.any(log["mode"] == Mode.FAULT.code)
        # inside the safe range, and off the end stops (the guard keeps 0.05 m inside it)
        assert -0.225 < log["true_x"].min() and log["true_x"].max() < 0.125
        assert np.abs(log["u"]).max() > 8.0  # the motor is driven hard
        # the set-point stops at the current loop's 0.9 A; the PI loop (3.47) overshoots
        # it at a reversal (1.03 A measured with these plants), briefly
        assert np.abs(log["i"]).max() < 1.1


# -- the fit ---------------------------------------------------------------------------


def test_the_bench_says_how_well_each_recording_kept_time():
    from types import SimpleNamespace

    from pisc_bench.identify_bench import Outcome, format_outcome

    def outcome(latency_s):
        result = SimpleNamespace(cycles=1000, residual_rms=np.array([0.3, 0.3, 0.4]),
                                 recordings=[SimpleNamespace(latency_s=latency_s)])
        return Outcome(3, {}, result, wall_s=12.0)

    wall = np.full(1000, 0.8e-3)
    wall[-20:] = 5e-3  # 2 % late: the 99th percentile is among them
    line = format_outcome(outcome(wall)).splitlines()[0]
    assert line.startswith("draw 3: identified in 12.0 s (1000 samples); residual 0.300 / ")
    assert line.endswith("; latency median 0.80 ms, p99 5.00 ms"), line
    # lockstep records no latency: nothing said
    assert "latency" not in format_outcome(outcome(np.zeros(1000)))


def test_the_benchs_hidden_rigs_draw_the_sensors_noise_when_asked():
    """The virtual rig reads its sensors with noise.*: the bench draws it from the
    distribution's ranges (thesis-rig: up to one step of each sensor) with a seed per draw."""
    from pisc_bench.identify_bench import DRAWN, NOISE, draw_truths

    plain = draw_truths(4, 5)
    noisy = draw_truths(4, 5, noise=True)
    assert all(set(t) == set(DRAWN) for t in plain)
    highs = {"noise.x_std_m": 0.00043, "noise.theta_std_rad": 0.00157,
             "noise.current_std_a": 0.0123}  # distributions/thesis-rig.yaml
    for k, (a, b) in enumerate(zip(plain, noisy)):
        assert {key: b[key] for key in DRAWN} == a  # the same rig
        assert b["noise.seed"] == 5 + k
        for key in NOISE:
            assert 0.0 <= b[key] <= highs[key], (key, b[key])
    assert len({t["noise.current_std_a"] for t in noisy}) == 4

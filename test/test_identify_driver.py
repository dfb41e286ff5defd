"""Identification from runs recorded as on the rig (issue 14 acceptance): the excitation
scene through the driver and ``pisc_virtual_rig`` on its pseudo-terminal, the rig's
plant hidden (drawn from the robustness benchmark's ranges, seeded, the sensors' noise
included), then pisc_identify.

R, J_m, the cart's Coulomb and viscous friction within 5 % (friction: 10 % or 0.005,
whichever is larger); L reported not identifiable (at 5 ms sampling it acts only as a
delay would, and each command's delay is not known to that precision); the 95 %
intervals cover the truth (the benchmark, ``python -m pisc_bringup.identify_bench``,
counts that over 20 draws); the identification's wall time for each recording is
printed. Each run is the ``excitation`` scene (60 s, each bit's magnitude between 1.02 and
1.7 N: J_m / r^2 is 0.2-0.8 % of the moving mass, and 30 s at 1.5 N left J_m's interval
too wide for 5 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from pisc_bringup import identify as idf
from pisc_bringup import identify_bench as bench
from pisc_sim.configuration import load_run_config

# three real-time runs of 60 s and their identification: about 5 minutes, so behind bench
# (./pisc test -m bench -s test/test_identify_driver.py prints every figure)
pytestmark = [pytest.mark.integration, pytest.mark.bench]

SEED = 1  # the benchmark's default seed (3 draws of it: not the 20-draw run's first three)
DRAWS = 3
IR_STEP_M = 0.00043  # one IR code near x = 0 (distributions/thesis-rig.yaml)
LEFT_OUT_FRACTION = 0.1  # of the run: more, and the machine did not keep the run in time


def recorded_and_identified(tmp_path, env, k: int, truth: dict) -> bench.Outcome:
    """Record draw ``k`` through the driver and identify it; a run the machine could
    not keep in time (more than LEFT_OUT_FRACTION of it left out for missing or late
    samples) is recorded again, once."""
    _, duration = bench.scene_experiment()
    for attempt in range(2):
        bag = bench.record_driver(truth, duration, {}, tmp_path / f"draw-{k}-{attempt}",
                                  env=env)
        recording = idf.read_recording(bag)
        outcome = bench.Outcome(k, truth, None)
        outcome.result, outcome.wall_s = bench.identify_one(recording)
        left = sum(b - a for _, a, b, reason in outcome.result.segments.left_out
                   if "sample missing" in reason or "late" in reason or "too short" in reason)
        if left <= LEFT_OUT_FRACTION * duration:
            break
        print(f"draw {k}: {left:.1f} s left out for timing; recording again")
    return outcome


def test_identified_from_driver_runs_within_the_issues_tolerances(tmp_path, env_for_domain):
    base = load_run_config("default")[0].plant
    truths = bench.draw_truths(DRAWS, SEED, noise=True)
    outcomes = []
    for k, truth in enumerate(truths):
        outcome = recorded_and_identified(tmp_path, env_for_domain, k, truth)
        bench.judge(outcome, base)
        print(bench.format_outcome(outcome))
        print(idf.format_report(outcome.result))
        outcomes.append(outcome)
    print(bench.summary(outcomes))
    for o in outcomes:
        checks = o.checks
        for key in ("R", "J_m", "cart_coulomb", "cart_viscous"):
            assert key in checks, (o.draw, key, "not identified")
            assert checks[key][5], (o.draw, key, checks[key])  # within the tolerance
        assert "L" in o.not_identifiable
        # within a step of the sensors' resolution, beyond the rig's own noise in steps
        noise = np.array([o.truth["noise.x_std_m"] / IR_STEP_M,
                          o.truth["noise.theta_std_rad"] / base.sensors.encoder_rad_per_count,
                          o.truth["noise.current_std_a"] / (base.sensors.adc_lsb_v
                                                            * base.sensors.current_scale_a_per_v)])
        assert np.all(o.result.residual_rms < np.hypot(1.0, noise)), (o.result.residual_rms,
                                                                      noise)
        print(f"draw {o.draw}: a {o.result.cycles * 0.005:.0f} s recording identified in "
              f"{o.wall_s:.1f} s")
    covered = [c[4] for o in outcomes for key, c in o.checks.items() if key in bench.COVERAGE]
    assert sum(covered) >= 0.8 * len(covered), covered

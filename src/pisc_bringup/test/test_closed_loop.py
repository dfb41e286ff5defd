"""The default design catches from the acceptance starts; the thesis gains do not all."""

import numpy as np

from pisc_bringup.closed_loop import simulate, simulate_batch
from pisc_bringup.configuration import load_graph_config
from pisc_msgs_py.types import Mode

STARTS = np.array([-0.10, -0.05, 0.0, 0.05, 0.10])


def accepted(o):
    return ((o.caught_at_s <= 3.0) & (o.x_min_m > -0.22) & (o.x_max_m < 0.12)
            & (o.hold_theta_rad < 0.05) & (o.hold_x_m < 0.02) & ~o.faulted)


def test_default_design_catches_from_every_acceptance_start_with_and_without_latency():
    cfg, _ = load_graph_config("default")
    for delay in (0.0, 0.002):
        outcome = simulate_batch(cfg, STARTS, 10.0, command_delay_s=delay)
        assert accepted(outcome).all(), (delay, outcome)


def test_thesis_gains_stall_from_rest_at_the_target():
    """SPEC section 3: from x0 = 0 at rest (3.30) gives f = 0 and the rig never moves; from
    x0 = +-0.05 it stalls with E below zero, short of the catch region."""
    cfg, _ = load_graph_config("thesis")
    outcome = simulate_batch(cfg, np.array([-0.05, 0.0, 0.05]), 6.0)
    assert not np.isfinite(outcome.caught_at_s).any()
    assert np.all(outcome.hold_theta_rad > 1.5)


def test_scalar_and_batch_runs_agree():
    cfg, _ = load_graph_config("default", {"initial.x_m": 0.05})
    log = simulate(cfg, 3.0)
    first_catch = log["t"][np.argmax(log["mode"] == Mode.CATCH.code)]
    batch = simulate_batch(cfg, np.array([0.05]), 3.0, hold_start_s=3.0)
    assert first_catch == batch.caught_at_s[0]

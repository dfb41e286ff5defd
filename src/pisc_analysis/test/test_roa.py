"""Region of attraction of the catch in the sampled, quantised, saturated loop."""

import os
import time

import numpy as np
import pytest

from pisc_analysis.roa import (
    CAUGHT_AT_ONCE,
    NOT_RECOVERED,
    plot_roa,
    region_of_attraction,
)
from pisc_sim.configuration import load_graph_config


@pytest.fixture(scope="module")
def default_config():
    # the previous default (the comments' numbers are its): a catch that this module's
    # criteria describe, without the default's energy band
    return load_graph_config("lyapunov-tuned")[0]


def test_starts_inside_the_criterion_near_upright_are_caught_at_once(default_config):
    theta = np.linspace(-0.1, 0.1, 5)
    rate = np.linspace(-0.5, 0.5, 5)
    m = region_of_attraction(default_config, theta, rate, label="default")
    assert m.inside_criterion.all()  # 0.01 + 0.00332 * 0.25 < 0.17 (4.1)
    assert np.all(m.outcome == CAUGHT_AT_ONCE)
    assert np.all(m.caught_at_s == 0.0)


def test_starts_far_outside_the_criterion_are_not_caught(default_config):
    # leaning 0.8-0.9 rad and still falling away from upright: (4.1) gives 0.76-1.6,
    # far above delta_s = 0.17
    theta = np.array([-0.9, -0.8, 0.8, 0.9])
    rate = np.array([-5.0, -3.0, 3.0, 5.0])
    m = region_of_attraction(default_config, theta, rate, label="default")
    away = np.sign(theta)[None, :] == np.sign(rate)[:, None]
    assert not m.inside_criterion.any()
    assert np.all(m.outcome[away] == NOT_RECOVERED)
    assert not np.any(m.outcome == CAUGHT_AT_ONCE)


def test_the_thesis_criterion_admits_starts_its_catch_cannot_hold():
    """delta_s = 0.6 admits theta = 0.5 rad moving away at 2 rad/s; the saturated loop
    (0.9 A, 1.79 N at the cart) cannot bring it back."""
    cfg, _ = load_graph_config("thesis")
    m = region_of_attraction(cfg, [0.05, 0.5], [0.0, 2.0], label="thesis")
    assert m.inside_criterion.all()
    assert m.outcome[0, 0] == CAUGHT_AT_ONCE
    assert m.outcome[1, 1] == NOT_RECOVERED


def test_a_grid_gives_the_same_map_as_its_rows_run_alone(default_config):
    """One batch for the whole grid; each row alone gives the same classes."""
    theta = np.linspace(-0.6, 0.6, 7)
    rate = np.linspace(-6.0, 6.0, 6)
    whole = region_of_attraction(default_config, theta, rate, duration_s=1.0,
                                 hold_window_s=0.3)
    for k in (0, 3):
        row = region_of_attraction(default_config, theta, rate[k:k + 1], duration_s=1.0,
                                   hold_window_s=0.3)
        np.testing.assert_array_equal(row.outcome[0], whole.outcome[k])
        np.testing.assert_array_equal(row.caught_at_s[0], whole.caught_at_s[k])
    assert whole.outcome.shape == (6, 7)
    assert (whole.outcome == CAUGHT_AT_ONCE).any() and (whole.outcome == NOT_RECOVERED).any()


def test_plot_is_a_png(default_config, tmp_path):
    m = region_of_attraction(default_config, [-0.1, 0.1], [-1.0, 1.0], duration_s=0.5,
                             hold_window_s=0.25, label="default")
    path = plot_roa([m, m], tmp_path / "roa.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_refusals_name_what_is_wrong(default_config):
    with pytest.raises(ValueError, match="non-empty 1-D grids"):
        region_of_attraction(default_config, [], [0.0])
    with pytest.raises(ValueError, match=r"hold_window_s = 2.0 must be in \(0, duration_s = "
                                         r"1.5\]"):
        region_of_attraction(default_config, [0.0], [0.0], hold_window_s=2.0)


@pytest.mark.bench
def test_bench_region_of_attraction_100_by_100(default_config):
    """Prints the time of the default configuration's 100 x 100 map (< 60 s)."""
    started_cpu = time.process_time()
    before = os.times()
    m = region_of_attraction(default_config, np.linspace(-1.0, 1.0, 100),
                             np.linspace(-8.0, 8.0, 100), label="default")
    after = os.times()
    cpu = (time.process_time() - started_cpu + after.children_user - before.children_user
           + after.children_system - before.children_system)
    print(f"\nROA 100 x 100, {m.duration_s} s each: wall "
          f"{m.elapsed_s:.1f} s, CPU {cpu:.1f} s, load average {os.getloadavg()[0]:.1f}\n"
          f"{m.summary()}")
    assert m.outcome.shape == (100, 100)

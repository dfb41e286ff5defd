"""The parameter files: both load, the thesis file holds exactly the thesis's values."""

import pytest

from pisc_sim.configuration import load_graph_config
from pisc_msgs_py.config import ConfigError


def test_thesis_configuration_holds_tables_6_2_to_6_5():
    cfg, _ = load_graph_config("thesis")
    s = cfg.supervisor
    assert (cfg.current_loop.k_pi, cfg.current_loop.k_ii) == (2.9, 1800.0)  # Table 6.2
    assert s.catch.poles == (-15.0, -11.0, -2.0, -1.5)  # Table 6.3's poles
    assert (s.swing_up.k_v, s.swing_up.k_x, s.swing_up.k_delta, s.swing_up.k_e) == (
        0.1, 55.5, 1.55, 8.1)  # Table 6.4
    assert s.swing_up.energy_target_j == 0.0
    assert (s.switching.k_va, s.switching.delta_s, s.switching.delta_exit) == (
        0.015, 0.6, 0.6)  # Table 6.5, no hysteresis
    assert s.startup.distance_m == 0.0
    assert (cfg.current_loop.current_limit_a, cfg.current_loop.voltage_limit_v,
            cfg.current_loop.integral_reset_fraction) == (0.9, 11.47, 0.95)  # C++ program


def test_default_configuration_is_the_thesis_rig():
    default, _ = load_graph_config("default")
    thesis, _ = load_graph_config("thesis")
    assert default.plant == thesis.plant
    assert default.current_loop == thesis.current_loop
    assert default.supervisor.rig == thesis.supervisor.rig


def test_overrides_are_validated_and_unknown_sections_refused():
    with pytest.raises(ConfigError, match="rig.cart_mass_kg = -1.0 must be positive"):
        load_graph_config("default", {"rig.cart_mass_kg": -1.0})
    with pytest.raises(ConfigError, match="rigg.cart_mass_kg: unknown parameter section"):
        load_graph_config("default", {"rigg.cart_mass_kg": 1.0})
    with pytest.raises(ConfigError, match="no such configuration"):
        load_graph_config("nonexistent")

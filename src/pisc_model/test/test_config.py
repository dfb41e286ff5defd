"""Parameter schema: typed loading, clear refusals naming the parameter."""

import math

import pytest

from pisc_msgs_py.config import ConfigError, describe, from_flat, load_params_file, to_flat
from pisc_model.params import RigParams, TrackParams


def test_round_trip_through_dotted_names():
    rig = RigParams(cart_mass_kg=2.0)
    assert from_flat(RigParams, to_flat(rig, "rig"), "rig") == rig


@pytest.mark.parametrize("name,value,message", [
    ("rig.cart_mass_kg", -0.47, r"rig.cart_mass_kg = -0.47 must be positive"),
    ("rig.pendulum_mass_kg", 0.0, r"rig.pendulum_mass_kg = 0.0 must be positive"),
    ("rig.pendulum_com_m", math.nan, r"rig.pendulum_com_m = nan must be finite"),
    ("rig.gravity_mps2", math.inf, r"rig.gravity_mps2 = inf must be finite"),
    ("rig.gravity_mps2", -9.81, r"rig.gravity_mps2 = -9.81 must not be negative"),
    ("rig.pendulum_inertia_kgm2", -1e-6, r"must not be negative"),
    ("rig.cart_mass_kg", "heavy", r"rig.cart_mass_kg: expected a number, got 'heavy'"),
    ("rig.cart_mas_kg", 0.5, r"rig.cart_mas_kg: unknown parameter"),
])
def test_bad_values_are_refused_with_the_parameter_named(name, value, message):
    with pytest.raises(ConfigError, match=message):
        from_flat(RigParams, {name: value}, "rig")


def test_integers_are_accepted_for_floats_and_cross_field_rules_apply():
    assert from_flat(RigParams, {"rig.cart_mass_kg": 1}, "rig").cart_mass_kg == 1.0
    with pytest.raises(ConfigError, match="track.min_m = 0.2 must be below track.max_m"):
        from_flat(TrackParams, {"track.min_m": 0.2}, "track")


def test_params_file_sections_and_errors(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    rig:\n      cart_mass_kg: 0.5\n"
                    "plant:\n  ros__parameters:\n    rig:\n      cart_mass_kg: 0.6\n")
    assert load_params_file(path)["rig.cart_mass_kg"] == 0.5
    assert load_params_file(path, ("/**", "plant"))["rig.cart_mass_kg"] == 0.6
    with pytest.raises(ConfigError, match="cannot read parameter file"):
        load_params_file(tmp_path / "missing.yaml")
    path.write_text("rig: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_params_file(path)
    path.write_text("other:\n  ros__parameters: {}\n")
    with pytest.raises(ConfigError, match="none of the sections"):
        load_params_file(path)


def test_every_field_is_described_with_a_unit_where_it_has_one():
    rows = describe(RigParams, "rig")
    assert ("rig.cart_mass_kg", 0.4735, "kg", "M, cart mass") in rows
    assert all(description for *_, description in rows)


def test_command_line_overrides_are_parsed_as_yaml_and_bad_ones_refused():
    from pisc_msgs_py.config import parse_overrides

    assert parse_overrides(["catch.poles=[-1, -2]", "swing_up.k_v=0.1", "models.end_stops=false",
                            "a.b=x=y"]) == {"catch.poles": [-1, -2], "swing_up.k_v": 0.1,
                                            "models.end_stops": False, "a.b": "x=y"}
    for bad in ("swing_up.k_v", "=3"):
        with pytest.raises(ConfigError, match=r"--set .*expected NAME=VALUE"):
            parse_overrides([bad])

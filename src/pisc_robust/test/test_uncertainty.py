"""Distribution files: what they may say, what is refused (with the parameter's name and
the rule), and draws that depend on the seed alone."""

from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from pisc_sim.configuration import load_graph_config
from pisc_robust.robustness_cli import main as robustness_main
from pisc_robust.uncertainty import load_distribution
from pisc_msgs_py.config import ConfigError


@pytest.fixture(scope="module")
def config():
    return load_graph_config("default")[0]


def write(tmp_path, text: str):
    path = tmp_path / "dist.yaml"
    path.write_text(textwrap.dedent(text))
    return path


# (file body, what the message must say: the parameter's name and the rule)
BAD = {
    "unknown parameter": (
        "distribution: {parameters: {motor.nosuch_ohm: {relative: 0.1}}}",
        ["motor.nosuch_ohm", "unknown parameter", "resistance_ohm"]),
    "unknown section": (
        "distribution: {parameters: {swing_up.k_x: {relative: 0.1}}}",
        ["swing_up.k_x", "cannot be varied"]),
    "the noise seed": (
        "distribution: {parameters: {noise.seed: {uniform: [1, 2]}}}",
        ["noise.seed", "cannot be varied"]),
    "negative width": (
        "distribution: {parameters: {motor.resistance_ohm: {relative: -0.1}}}",
        ["motor.resistance_ohm", "negative", "width"]),
    "lower above upper": (
        "distribution: {parameters: {friction.cart_coulomb_n: {uniform: [0.1, 0.0]}}}",
        ["friction.cart_coulomb_n", "lower bound 0.1 is above upper bound 0.0"]),
    "a range that breaks the parameter's rule": (
        "distribution: {parameters: {motor.resistance_ohm: {relative: [-1.5, 0.0]}}}",
        ["motor.resistance_ohm", "reaches -7", "must be positive"]),
    "a negative friction": (
        "distribution: {parameters: {friction.cart_coulomb_n: {offset: 0.1}}}",
        ["friction.cart_coulomb_n", "reaches -0.1", "must not be negative"]),
    "factor with a zero bound": (
        "distribution: {parameters: {motor.inductance_h: {factor: [0.0, 2.0]}}}",
        ["motor.inductance_h", "factor", "must be positive"]),
    "factor with a single width": (
        "distribution: {parameters: {motor.inductance_h: {factor: 2.0}}}",
        ["motor.inductance_h", "expected [low, high]"]),
    "an unknown kind of range": (
        "distribution: {parameters: {rig.cart_mass_kg: {normal: [0.4, 0.5]}}}",
        ["rig.cart_mass_kg", "expected one of uniform, offset, relative, factor"]),
    "a fixed override of a section the plant does not read": (
        "distribution: {plant: {swing_up: {k_v: 1}}, parameters: {rig.cart_mass_kg: "
        "{relative: 0.1}}}",
        ["swing_up.k_v", "the plant does not read section 'swing_up'"]),
    "a fixed override the plant does not have": (
        "distribution: {plant: {motor: {nosuch: 1}}, parameters: {rig.cart_mass_kg: "
        "{relative: 0.1}}}",
        ["motor.nosuch", "unknown parameter"]),
    "a fixed override that breaks its rule": (
        "distribution: {plant: {motor: {resistance_ohm: -1.0}}, parameters: "
        "{rig.cart_mass_kg: {relative: 0.1}}}",
        ["motor.resistance_ohm", "must be positive"]),
    "both fixed and varied": (
        "distribution: {plant: {motor: {resistance_ohm: 12.0}}, parameters: "
        "{motor.resistance_ohm: {relative: 0.1}}}",
        ["motor.resistance_ohm", "both fixed", "and varied"]),
    "a list as the document": (
        "- motor.resistance_ohm: {relative: 0.1}",
        ["one mapping under the key 'distribution'"]),
    "a number under distribution": (
        "distribution: 3", ["one mapping under the key 'distribution'"]),
    "an empty file": ("", ["one mapping under the key 'distribution'"]),
    "parameters as a list": (
        "distribution: {parameters: [motor.resistance_ohm]}",
        ["distribution.parameters must map parameter names to ranges"]),
    "plant as a list": (
        "distribution: {plant: [1], parameters: {rig.cart_mass_kg: {relative: 0.1}}}",
        ["distribution.plant must be a mapping"]),
    "an unknown key": (
        "distribution: {params: {rig.cart_mass_kg: {relative: 0.1}}}",
        ["distribution.params: unknown key"]),
    "not YAML": ("distribution: {parameters: [", ["not valid YAML"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_distribution_is_refused_with_its_name_and_the_rule(tmp_path, config, case):
    text, expected = BAD[case]
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as caught:
        load_distribution(str(path), config)
    for piece in expected:
        assert piece in str(caught.value), (piece, str(caught.value))


@pytest.mark.parametrize("case", ["unknown parameter", "negative width",
                                  "lower above upper",
                                  "a fixed override the plant does not have"])
def test_pisc_robustness_refuses_a_bad_distribution_with_exit_2(tmp_path, capsys, case):
    text, expected = BAD[case]
    path = write(tmp_path, text)
    assert robustness_main(["default", "--distribution", str(path), "--draws", "10",
                            "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pisc_robustness: ")
    for piece in expected:
        assert piece in err
    assert not (tmp_path / "out").exists()


def test_the_command_prints_no_traceback_for_a_bad_distribution(tmp_path):
    path = write(tmp_path, BAD["a range that breaks the parameter's rule"][0])
    completed = subprocess.run(
        [sys.executable, "-m", "pisc_robust.robustness_cli", "default", "--distribution",
         str(path), "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=60)
    assert completed.returncode == 2
    assert "Traceback" not in completed.stderr
    assert "motor.resistance_ohm: the range reaches -7, which must be positive" \
        in completed.stderr


@pytest.mark.parametrize("argv, expected", [
    (["nosuch"], "nosuch: no such configuration"),
    (["default", "--distribution", "nosuch"], "nosuch: no such distribution"),
    (["thesis", "--set", "swing_up.k_e=100"], "(3.29)"),
    (["default", "--set", "nosuch.x=1"], "nosuch.x: unknown parameter section"),
])
def test_pisc_robustness_refuses_other_bad_input_with_exit_2(tmp_path, capsys, argv,
                                                              expected):
    assert robustness_main([*argv, "--draws", "10", "--out", str(tmp_path)]) == 2
    assert expected in capsys.readouterr().err


def test_the_same_seed_gives_the_same_draws_and_another_seed_others(config):
    distribution = load_distribution("thesis-rig", config)
    first = distribution.draw(500, seed=7)
    again = distribution.draw(500, seed=7)
    other = distribution.draw(500, seed=8)
    assert first.values.keys() == again.values.keys() == other.values.keys()
    for name in first.values:
        np.testing.assert_array_equal(first.values[name], again.values[name])
        assert not np.array_equal(first.values[name], other.values[name])


def test_draws_stay_inside_their_ranges_and_slice_by_draw(config):
    distribution = load_distribution("thesis-rig", config)
    draws = distribution.draw(2000, seed=3)
    for r in distribution.ranges:
        low, high = r.value_range
        values = draws.values[r.name]
        assert values.shape == (2000,)
        assert np.all((values >= low) & (values <= high)), r.name
    part = draws[10:20]
    assert part.n == 10
    assert part.one(0) == draws.one(10)


def test_the_shipped_thesis_rig_distribution_has_the_ranges_its_file_says(config):
    distribution = load_distribution("thesis-rig", config)
    resistance = distribution.range("motor.resistance_ohm")
    assert resistance.value_range == pytest.approx((9.8, 18.2))
    theta = distribution.range("initial.theta_rad")
    assert theta.value_range == pytest.approx((math.pi - 0.5, math.pi + 0.5))
    assert distribution.range("motor.inductance_h").value_range == pytest.approx(
        (0.001, 0.004))
    assert distribution.range("friction.cart_coulomb_n").value_range == (0.0, 0.1)
    assert distribution.range("actuator.command_delay_s").value_range == (0.0, 0.002)
    assert distribution.plant == {"models.friction": "coulomb"}
    assert "9.8" in resistance.describe() and "-30 %" in resistance.describe()


def test_a_factor_range_is_log_uniform(config, tmp_path):
    path = write(tmp_path, "distribution: {parameters: {motor.inductance_h: "
                 "{factor: [0.5, 2.0]}}}")
    draws = load_distribution(str(path), config).draw(20000, seed=1)
    ratio = draws.values["motor.inductance_h"] / config.plant.motor.inductance_h
    # log-uniform on [0.5, 2]: half the draws below the nominal value
    assert np.mean(ratio < 1.0) == pytest.approx(0.5, abs=0.02)


def test_the_digest_follows_the_content_not_the_comments(config, tmp_path):
    a = write(tmp_path, "# one\ndistribution: {parameters: {rig.cart_mass_kg: "
              "{relative: 0.1}}}")
    first = load_distribution(str(a), config).digest
    a.write_text("# two\ndistribution:\n  parameters:\n    rig.cart_mass_kg: {relative: 0.1}\n")
    assert load_distribution(str(a), config).digest == first
    a.write_text("distribution: {parameters: {rig.cart_mass_kg: {relative: 0.2}}}")
    assert load_distribution(str(a), config).digest != first

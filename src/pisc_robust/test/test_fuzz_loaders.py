"""The parameter and distribution loaders, fuzzed (hypothesis): whatever a user writes in
``--set``, a parameter file or a distribution file, the answer is a configuration or a
:class:`ConfigError` naming what is wrong, never another exception (a traceback).

Bounded and derandomized: the same examples every run (the suite must pass three runs in
a row), no example database written.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pisc_robust.uncertainty import load_distribution
from pisc_control.supervisor import Supervisor
from pisc_msgs_py.config import ConfigError, load_params_file, parse_overrides
from pisc_sim.configuration import load_graph_config, load_run_config

BOUNDED = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                   suppress_health_check=[HealthCheck.too_slow])

_, FLAT = load_graph_config("default")
NAMES = sorted(FLAT)

# what a YAML value can be: numbers at and past every limit, strings that look like
# numbers, lists, mappings, nothing
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from([0, -1, 1e308, -1e308, 5e-324, 2**63, -(2**63) - 1]))
SCALARS = st.one_of(
    NUMBERS, st.booleans(), st.none(),
    st.text(max_size=12),
    st.sampled_from(["5e-1", "1E3", ".5", "nan", "inf", "-.inf", "0x10", "1_000", "~",
                     "[1, 2", "{a: 1", "yes", "on", "'1'", "!!python/object:os.system"]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=8)
PARAMETER_NAMES = st.one_of(st.sampled_from(NAMES), st.text(max_size=20),
                            st.sampled_from(NAMES).map(lambda n: n + "x"))


def _refused_or_loaded(call) -> None:
    try:
        call()
    except ConfigError as exc:
        assert str(exc), "a refusal names what is wrong"


@BOUNDED
@given(st.dictionaries(PARAMETER_NAMES, VALUES, max_size=4))
def test_overrides_give_a_configuration_or_a_config_error(overrides):
    def load() -> None:
        config, flat, plant = load_run_config("default", overrides)
        Supervisor(config.supervisor)  # pisc_graph builds it from what the user gave

    _refused_or_loaded(load)


@BOUNDED
@given(st.lists(st.one_of(
    st.text(max_size=30),
    st.sampled_from(NAMES).flatmap(lambda n: st.sampled_from(
        [f"{n}=[1, 2", f"{n}={{a: 1", f"{n}=\x1f", f"{n}=5e-1", f"{n}=*x", f"{n}=!!binary x"]))),
    max_size=4))
def test_set_items_parse_or_are_refused(items):
    def load() -> None:
        load_run_config("default", parse_overrides(items))

    _refused_or_loaded(load)


def _write(text: str) -> Path:
    handle = tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False, encoding="utf-8")
    with handle:
        handle.write(text)
    return Path(handle.name)


PARAMETER_FILES = st.one_of(
    st.text(max_size=200),
    st.dictionaries(st.sampled_from(["/**", "plant", "estimator", "x"]),
                    st.one_of(VALUES, st.fixed_dictionaries(
                        {"ros__parameters": st.dictionaries(PARAMETER_NAMES, VALUES,
                                                            max_size=5)})),
                    max_size=3).map(lambda d: yaml.safe_dump(d, allow_unicode=True)))


@BOUNDED
@given(PARAMETER_FILES)
def test_a_parameter_file_loads_or_is_refused(text):
    path = _write(text)
    try:
        _refused_or_loaded(lambda: load_graph_config(str(path)))
        _refused_or_loaded(lambda: load_params_file(path))
    finally:
        path.unlink()


RANGE_KINDS = ["relative", "factor", "uniform", "offset", "log_uniform", "normal", "x"]
RANGES = st.one_of(VALUES, st.dictionaries(st.sampled_from(RANGE_KINDS), VALUES,
                                           min_size=1, max_size=2))
VARIED = st.one_of(st.sampled_from([
    "motor.resistance_ohm", "rig.cart_mass_kg", "friction.cart_coulomb_n",
    "noise.x_std_m", "initial.theta_rad", "actuator.command_delay_s", "models.friction"]),
    PARAMETER_NAMES)
DISTRIBUTIONS = st.one_of(
    st.text(max_size=200),
    st.fixed_dictionaries({"distribution": st.one_of(VALUES, st.fixed_dictionaries(
        {"description": SCALARS,
         "plant": st.one_of(VALUES, st.dictionaries(
             st.sampled_from(["models", "friction", "motor", "rig"]),
             st.dictionaries(st.text(max_size=12), VALUES, max_size=2), max_size=2)),
         "parameters": st.dictionaries(VARIED, RANGES, max_size=4)}))}
    ).map(lambda d: yaml.safe_dump(d, allow_unicode=True)))

CONFIG, _ = load_graph_config("default")


@BOUNDED
@given(DISTRIBUTIONS, st.integers(min_value=0, max_value=2**32))
def test_a_distribution_file_loads_and_draws_or_is_refused(text, seed):
    path = _write(text)

    def load() -> None:
        distribution = load_distribution(str(path), CONFIG)
        draws = distribution.draw(8, seed)
        for k in range(8):
            assert all(isinstance(v, float) and not math.isnan(v) or not isinstance(v, float)
                       for v in draws.one(k).values())

    try:
        _refused_or_loaded(load)
    finally:
        path.unlink()

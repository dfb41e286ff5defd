"""The search space of a tuning (:mod:`pisc_robust.tune`): which of the controllers'
parameters it searches and over which ranges. A search space is a YAML file::

    space:
      description: what the search may change
      parameters:                       # one entry per searched parameter
        swing_up.k_x: {log: [1.0, 100.0]}         # log-uniform between the bounds
        switching.delta_s: {linear: [0.05, 0.6]}  # uniform between the bounds
        catch.poles[2]: {linear: [-6.0, -1.0]}    # one element of a list parameter

Each entry takes exactly one of ``linear: [low, high]`` and ``log: [low, high]`` (both
bounds positive), with low below high; both bounds must satisfy the parameter's own rule.
Parameters come from the controllers' sections (:data:`TUNABLE_SECTIONS`): a number, or
one element ``name[i]`` of a list of numbers. The plant's sections (the model the
controllers assume) and ``safety`` (the track's limits) are not searched, and neither is a
parameter the configuration's controllers do not read under its settings
(:data:`READ_ONLY_WHEN`: the energy pump's gains under the thesis's law, the governor's
with the governor off...): a search over it would change nothing.
:func:`space_for` picks the shipped space for a configuration.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import yaml

from pisc_sim.configuration import SECTIONS
from pisc_robust.uncertainty import file_kind
from pisc_msgs_py.config import (
    ConfigError,
    find_file,
    from_flat,
    load_keyed_yaml,
    package_dir,
    to_flat,
)

__all__ = ["READ_ONLY_WHEN", "SPACE_DIR", "TUNABLE_SECTIONS", "Dimension", "Space", "full_flat",
           "load_space", "space_for", "space_names", "unread"]

SPACE_DIR = package_dir("pisc_robust", "distributions")
DEFAULT_SPACE = "tuning-space"
SCALES = ("linear", "log")
TUNABLE_SECTIONS = ("estimator", "swing_up", "catch", "switching", "startup", "current_loop")
NAME = re.compile(r"^(?P<parameter>[a-z_]+\.[a-z0-9_]+)(\[(?P<index>\d+)\])?$")


#: Parameters the controllers read only under a setting of the configuration: (names, a
#: name ending in ``*`` standing for every name it begins, the settings that make the
#: controllers read them, as (parameter, the values that do)). Every other parameter of the
#: tunable sections is read whatever the settings (pisc_control's cores: the laws (3.30)
#: and the energy pump, :func:`pisc_control.swing_up.swing_up_constants`).
READ_ONLY_WHEN: tuple[tuple[tuple[str, ...], tuple[tuple[str, tuple[Any, ...]], ...]], ...] = (
    (("swing_up.k_v", "swing_up.k_x", "swing_up.k_delta", "swing_up.k_e"),
     (("swing_up.law", ("lyapunov",)),)),
    (("swing_up.pump_gain", "swing_up.pump_accel_mps2", "swing_up.track_k_x",
      "swing_up.track_k_v", "swing_up.guard_accel_mps2", "swing_up.guard_margin_m",
      "swing_up.track_quiet"), (("swing_up.law", ("energy_pump",)),)),
    (("swing_up.loss_gain",),
     (("swing_up.law", ("energy_pump",)), ("adaptation.enabled", (True,)))),
    (("catch.poles", "catch.poles_imag"), (("catch.design", ("poles",)),)),
    (("catch.lqr_q", "catch.lqr_r"), (("catch.design", ("lqr",)),)),
    (("catch.governor_*",), (("catch.governor", (True,)),)),
    (("catch.guard_*",), (("catch.guard", (True,)),)),
    (("adaptation.*",), (("adaptation.enabled", (True,)),)),
)


def unread(parameter: str, flat: Mapping[str, Any]) -> str:
    """Why the controllers of a configuration (``flat``: every parameter, defaults
    included) do not read ``parameter``; empty when they do (:data:`READ_ONLY_WHEN`)."""
    for names, settings in READ_ONLY_WHEN:
        if not any(parameter == n or (n.endswith("*") and parameter.startswith(n[:-1])
                                      and parameter not in (s for s, _ in settings))
                   for n in names):
            continue
        wrong = [(s, values) for s, values in settings if flat.get(s) not in values]
        if wrong:
            def show(v: Any) -> str:
                return str(v).lower() if isinstance(v, bool) else str(v)

            needs = " and ".join(f"{s}: {' or '.join(show(v) for v in values)}"
                                 for s, values in settings)
            has = ", ".join(f"{s}: {show(flat.get(s))}" for s, _ in wrong)
            return f"the controllers read it only with {needs}; the configuration has {has}"
    return ""


@dataclass(frozen=True)
class Dimension:
    """One searched value: a parameter, or element ``index`` of a list parameter."""

    name: str  # as in the space file, e.g. "catch.poles[2]"
    parameter: str  # "catch.poles"
    index: int | None
    low: float
    high: float
    log: bool

    def describe(self) -> str:
        return f"{self.name} in [{self.low:g}, {self.high:g}] ({'log' if self.log else 'linear'})"


@dataclass(frozen=True)
class Space:
    name: str
    description: str
    dimensions: tuple[Dimension, ...]

    @property
    def digest(self) -> str:
        canon = yaml.safe_dump([asdict(d) for d in self.dimensions], sort_keys=True)
        return hashlib.sha256(canon.encode()).hexdigest()[:16]

    def values(self, flat: Mapping[str, Any]) -> dict[str, float]:
        """Each dimension's value in the flat parameters of a configuration."""
        out = {}
        for d in self.dimensions:
            value = flat[d.parameter]
            out[d.name] = float(value if d.index is None else value[d.index])
        return out

    def overrides(self, flat: Mapping[str, Any], values: Mapping[str, float]) -> dict[str, Any]:
        """The flat overrides that set ``values`` (by dimension name) in ``flat``."""
        out: dict[str, Any] = {}
        for d in self.dimensions:
            if d.index is None:
                out[d.parameter] = float(values[d.name])
            else:
                current = list(out.get(d.parameter, flat[d.parameter]))
                current[d.index] = float(values[d.name])
                out[d.parameter] = current
        return out

    def contains(self, values: Mapping[str, float]) -> bool:
        return all(d.low <= values[d.name] <= d.high for d in self.dimensions)


def space_names() -> list[str]:
    """The shipped search spaces (beside the distributions)."""
    return sorted(p.stem for p in SPACE_DIR.glob("*.yaml") if file_kind(p) == "space")


def space_path(name_or_path: str) -> Path:
    return find_file(name_or_path, SPACE_DIR, "search space", space_names)


def full_flat(flat: Mapping[str, Any]) -> dict[str, Any]:
    """Every parameter of every section, the defaults included, as flat values."""
    out: dict[str, Any] = {}
    for section, cls in SECTIONS.items():
        out.update(to_flat(from_flat(cls, flat, section), section))
    return out


def _dimension(name: str, spec: Any, flat: Mapping[str, Any], where: str) -> Dimension:
    match = NAME.match(name)
    if not match:
        raise ConfigError(f"{where}{name}: expected a parameter name such as swing_up.k_x "
                          "or catch.poles[2]")
    parameter, index = match["parameter"], match["index"]
    section, _, leaf = parameter.partition(".")
    if section not in TUNABLE_SECTIONS:
        raise ConfigError(f"{where}{name}: cannot be searched (searched sections: "
                          f"{', '.join(TUNABLE_SECTIONS)}; the plant's sections are the model "
                          "and safety is the track)")
    field = next((f for f in fields(SECTIONS[section]) if f.name == leaf), None)
    if field is None:
        known = ", ".join(f.name for f in fields(SECTIONS[section]))
        raise ConfigError(f"{where}{name}: unknown parameter (known in '{section}': {known})")
    current = flat[parameter]
    if isinstance(current, (list, tuple)):
        if index is None:
            raise ConfigError(f"{where}{name}: a list of {len(current)} numbers; search one "
                              f"element, e.g. {parameter}[0]")
        if int(index) >= len(current):
            raise ConfigError(f"{where}{name}: index {index} beyond the {len(current)} "
                              f"elements of {parameter}")
    elif index is not None:
        raise ConfigError(f"{where}{name}: {parameter} is not a list")
    elif isinstance(current, bool) or not isinstance(current, float):
        raise ConfigError(f"{where}{name}: not a real number ({current!r}); only real "
                          "parameters can be searched")
    if (not isinstance(spec, Mapping) or len(spec) != 1 or next(iter(spec)) not in SCALES):
        raise ConfigError(f"{where}{name}: expected one of {', '.join(SCALES)} with [low, "
                          f"high] (e.g. {{log: [1.0, 100.0]}}), got {spec!r}")
    scale, bounds = next(iter(spec.items()))
    if (not isinstance(bounds, list) or len(bounds) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       for v in bounds)):
        raise ConfigError(f"{where}{name}: {scale}: expected [low, high], got {bounds!r}")
    low, high = float(bounds[0]), float(bounds[1])
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ConfigError(f"{where}{name}: {scale}: [{low}, {high}] must be finite")
    if not low < high:
        raise ConfigError(f"{where}{name}: {scale}: lower bound {low:g} must be below the "
                          f"upper bound {high:g}")
    if scale == "log" and low <= 0:
        raise ConfigError(f"{where}{name}: log: [{low:g}, {high:g}] must be positive "
                          "(log-uniform); use linear")
    for value in (low, high):
        problem = field.metadata["rule"](value)
        if problem:
            raise ConfigError(f"{where}{name}: the range reaches {value:g}, which {problem}")
    return Dimension(name, parameter, None if index is None else int(index), low, high,
                     scale == "log")


def load_space(name_or_path: str, flat: Mapping[str, Any]) -> Space:
    """Read and check a search space against a configuration's flat parameters;
    :class:`ConfigError` naming the entry and the rule on bad input."""
    path = space_path(name_or_path)
    body = load_keyed_yaml(path, "space", ("description", "parameters"), "search space")
    parameters = body.get("parameters")
    if not isinstance(parameters, Mapping) or not parameters:
        raise ConfigError(f"{path}: space.parameters must map parameter names to ranges")
    full = full_flat(flat)
    where = f"{path}: space.parameters."
    dimensions = tuple(_dimension(str(name), spec, full, where)
                       for name, spec in parameters.items())
    for d in dimensions:
        why = unread(d.parameter, full)
        if why:
            raise ConfigError(f"{where}{d.name}: not searched: {why} (a search over it "
                              "would change nothing; pisc_tune --space names a space for "
                              f"this configuration, e.g. {space_for(flat, default='')})"
                              .replace(", e.g. )", ")"))
    return Space(path.stem, str(body.get("description", "")), dimensions)


def space_for(flat: Mapping[str, Any], default: str | None = None) -> str:
    """The shipped search space for a configuration (``flat``): of the spaces whose every
    parameter its controllers read, the one with the most parameters (the first by name
    of equals). ``default`` when none fits, else :class:`ConfigError`."""
    full = full_flat(flat)
    fits = []
    for name in space_names():
        try:
            body = load_keyed_yaml(space_path(name), "space", ("description", "parameters"),
                                   "search space")
        except ConfigError:
            continue
        names = [NAME.match(str(n)) for n in body.get("parameters") or {}]
        if names and all(m and m["parameter"] in full and not unread(m["parameter"], full)
                         for m in names):
            fits.append((-len(names), name))
    if fits:
        return min(fits)[1]
    if default is not None:
        return default
    raise ConfigError("no shipped search space fits this configuration (each searches a "
                      "parameter its controllers do not read); give one with --space")

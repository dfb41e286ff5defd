"""What is not known about a rig, as a YAML file: ranges over plant parameters, the
initial state and the command latency, and the draws taken from them.

A distribution file::

    distribution:
      description: the thesis rig as far as the thesis does not pin it down
      plant:                          # fixed plant overrides (sections the plant reads)
        models: {friction: coulomb}
      parameters:                     # one entry per varied parameter, by its full name
        motor.resistance_ohm: {relative: 0.3}       # nominal x (1 + u), u in [-0.3, 0.3]
        motor.inductance_h: {factor: [0.5, 2.0]}    # nominal x f, f log-uniform in [0.5, 2]
        friction.cart_coulomb_n: {uniform: [0.0, 0.1]}
        initial.theta_rad: {offset: 0.5}            # nominal + u, u in [-0.5, 0.5]
        actuator.command_delay_s: {uniform: [0.0, 0.002]}

Each entry takes exactly one of ``uniform: [low, high]`` (absolute values), ``offset``
(added to the nominal value), ``relative`` (nominal times 1 + u) and ``factor`` (nominal
times f, drawn uniformly in log f); ``offset`` and ``relative`` take a width w (the
range [-w, w]) or ``[low, high]``. Every value is uniform over its range, independent of
the others. The nominal value is the configuration's (the plant the controllers assume).

A ``joint`` block holds rigs whose values go together (a posterior, ``pisc_calibrate``):
``names`` (parameters, none of them also in ``parameters``) and ``rows`` (one list of
values a rig, in the order of ``names``); each draw takes one row, uniformly, all its
values at once::

      joint:
        names: [motor.resistance_ohm, friction.pivot_viscous_nms]
        rows:
        - [14.3, 2.1e-06]
        - [12.9, 8.0e-06]

Parameters that can vary: every field of ``rig``, ``motor``, ``friction`` and ``noise``
(the standard deviations), ``initial.*`` and ``actuator.command_delay_s``. Both ends of
each range must satisfy the parameter's own rule, so no draw is a plant that a
parameter file could not describe.

:func:`draw` takes ``n`` draws from a seed: the same seed gives the same draws.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from pisc_sim.configuration import SECTIONS, GraphConfig, check_plant_overrides
from pisc_msgs_py.config import (
    ConfigError,
    find_file,
    flatten,
    from_flat,
    load_keyed_yaml,
    load_yaml,
    package_dir,
    to_flat,
)
from pisc_model.params import (
    ActuatorParams,
    FrictionParams,
    InitialParams,
    MotorParams,
    NoiseParams,
    RigParams,
    unused_by_models,
)

__all__ = ["DISTRIBUTION_DIR", "Distribution", "Draws", "Range", "distribution_names",
           "load_distribution", "unit_of", "VARIABLE_SECTIONS"]

DISTRIBUTION_DIR = package_dir("pisc_robust", "distributions")
KINDS = ("uniform", "offset", "relative", "factor")
KEYS = ("description", "plant", "parameters", "joint")

#: The sections whose fields a distribution may vary (plant parameters, one per rig),
#: and the single field of ``actuator`` it may vary.
VARIABLE_SECTIONS: dict[str, type] = {
    "rig": RigParams, "motor": MotorParams, "friction": FrictionParams, "noise": NoiseParams,
    "initial": InitialParams,
}
LATENCY = "actuator.command_delay_s"
NOT_VARIABLE = {"noise.seed"}


@dataclass(frozen=True)
class Range:
    """One varied parameter: values uniform over [low, high] (in log for ``factor``)."""

    name: str
    kind: str  # one of KINDS, or "joint" (a column of the joint rows: [low, high] its span)
    low: float  # of the kind's quantity (absolute value, offset, relative change or factor)
    high: float
    nominal: float

    @property
    def value_range(self) -> tuple[float, float]:
        """The parameter's smallest and largest value."""
        return self.value(self.low), self.value(self.high)

    def value(self, q: Any) -> Any:
        if self.kind in ("uniform", "joint"):
            return q
        if self.kind == "offset":
            return self.nominal + q
        if self.kind == "relative":
            return self.nominal * (1.0 + q)
        return self.nominal * q

    def sample(self, u: np.ndarray) -> np.ndarray:
        """Values for uniform draws ``u`` in [0, 1)."""
        if self.kind == "factor":
            lo, hi = math.log(self.low), math.log(self.high)
            return self.nominal * np.exp(lo + (hi - lo) * u)
        return self.value(self.low + (self.high - self.low) * u)

    def describe(self) -> str:
        lo, hi = self.value_range
        how = {"uniform": "", "offset": f" (nominal {self.nominal:.6g} {self.low:+.6g} .. "
               f"{self.high:+.6g})", "relative": f" (nominal {self.nominal:.6g} "
               f"{100 * self.low:+.0f} % .. {100 * self.high:+.0f} %)",
               "factor": f" (nominal {self.nominal:.6g} x{self.low:g} .. x{self.high:g}, "
               "log-uniform)", "joint": " (joint rows)"}[self.kind]
        return f"{self.name} in [{lo:.6g}, {hi:.6g}]{how}"


@dataclass(frozen=True)
class Draws:
    """``n`` draws: each varied parameter's values, one per draw."""

    values: dict[str, np.ndarray]
    n: int

    def __getitem__(self, index: Any) -> Draws:
        picked = {k: v[index] for k, v in self.values.items()}
        return Draws(picked, len(next(iter(picked.values()))) if picked else 0)

    def one(self, k: int) -> dict[str, float]:
        return {name: float(v[k]) for name, v in self.values.items()}


@dataclass(frozen=True)
class Distribution:
    name: str
    description: str
    plant: dict[str, Any]  # fixed flat plant overrides
    ranges: tuple[Range, ...]
    text: str  # the file as read, for provenance
    # the joint block's rows (rigs x the "joint" ranges, in the order of those ranges)
    rows: np.ndarray | None = None

    @property
    def digest(self) -> str:
        """A hash of the distribution's content (names, kinds, ranges, fixed overrides)."""
        content: dict[str, Any] = {"plant": self.plant, "ranges": [
            (r.name, r.kind, r.low, r.high, r.nominal) for r in self.ranges]}
        if self.rows is not None:
            content["rows"] = self.rows.tolist()
        canon = yaml.safe_dump(content, sort_keys=True)
        return hashlib.sha256(canon.encode()).hexdigest()[:16]

    def draw(self, n: int, seed: int) -> Draws:
        """``n`` draws from ``seed``; the same seed gives the same draws."""
        if n < 1:
            raise ConfigError(f"draws = {n}: at least one draw")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed = {seed!r}: an integer, 0 or more (numpy's generators "
                              "take non-negative seeds)")
        rng = np.random.default_rng(seed)
        free = [r for r in self.ranges if r.kind != "joint"]
        u = rng.random((len(free), n))
        values = {r.name: r.sample(u[j]) for j, r in enumerate(free)}
        if self.rows is not None:
            picked = self.rows[rng.integers(0, len(self.rows), n)]
            joint = [r for r in self.ranges if r.kind == "joint"]
            values.update({r.name: picked[:, j].copy() for j, r in enumerate(joint)})
        return Draws({r.name: values[r.name] for r in self.ranges}, n)

    def range(self, name: str) -> Range | None:
        return next((r for r in self.ranges if r.name == name), None)


def distribution_names() -> list[str]:
    """The shipped distributions (the directory also holds pisc_tune's search spaces)."""
    return sorted(p.stem for p in DISTRIBUTION_DIR.glob("*.yaml")
                  if file_kind(p) == "distribution")


def file_kind(path: Path) -> str | None:
    """The top-level key of a YAML file ('distribution', 'space'), None if it has none."""
    try:
        document = load_yaml(path.read_text())
    except yaml.YAMLError:
        return None
    return next(iter(document), None) if isinstance(document, Mapping) else None


def distribution_path(name_or_path: str) -> Path:
    return find_file(name_or_path, DISTRIBUTION_DIR, "distribution", distribution_names)


def _field(name: str) -> tuple[type, Any]:
    """The dataclass and field a variable parameter names; ConfigError otherwise."""
    section, _, leaf = name.partition(".")
    if name == LATENCY:
        cls = ActuatorParams
    elif section in VARIABLE_SECTIONS and name not in NOT_VARIABLE:
        cls = VARIABLE_SECTIONS[section]
    else:
        raise ConfigError(
            f"{name}: cannot be varied (varied parameters: the fields of "
            f"{', '.join(VARIABLE_SECTIONS)}, and {LATENCY})")
    for f in fields(cls):
        if f.name == leaf:
            return cls, f
    known = ", ".join(f.name for f in fields(cls))
    raise ConfigError(f"{name}: unknown parameter (known in '{section}': {known})")


def unit_of(name: str) -> str:
    """The unit of a parameter that can vary (empty when it has none)."""
    return str(_field(name)[1].metadata["unit"])


def _nominal(config: GraphConfig, name: str) -> float:
    section, _, leaf = name.partition(".")
    if section == "initial":
        return float(getattr(config.initial, leaf))
    return float(getattr(getattr(config.plant, section), leaf))


def _bounds(where: str, kind: str, spec: Any) -> tuple[float, float]:
    if isinstance(spec, bool):
        raise ConfigError(f"{where}: {kind}: expected a width or [low, high], got {spec!r}")
    if isinstance(spec, (int, float)):
        if kind not in ("offset", "relative"):
            raise ConfigError(f"{where}: {kind}: expected [low, high], got {spec!r}")
        if not math.isfinite(spec) or spec < 0:
            raise ConfigError(f"{where}: {kind}: {spec!r} is a negative or non-finite width "
                              "(the range is [-width, +width])")
        return -float(spec), float(spec)
    if (not isinstance(spec, list) or len(spec) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in spec)):
        raise ConfigError(f"{where}: {kind}: expected [low, high], got {spec!r}")
    low, high = float(spec[0]), float(spec[1])
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ConfigError(f"{where}: {kind}: [{low}, {high}] must be finite")
    if low > high:
        raise ConfigError(f"{where}: {kind}: lower bound {low} is above upper bound {high}")
    if kind == "factor" and low <= 0:
        raise ConfigError(f"{where}: factor: [{low}, {high}] must be positive (log-uniform)")
    return low, high


def parse_range(config: GraphConfig, name: str, spec: Any, where: str = "") -> Range:
    """One entry of ``parameters``; ConfigError naming the parameter and the rule."""
    try:
        cls, field = _field(name)
    except ConfigError as exc:
        raise ConfigError(f"{where}{exc}") from None
    where = f"{where}{name}"
    if not isinstance(spec, Mapping) or len(spec) != 1 or next(iter(spec)) not in KINDS:
        raise ConfigError(f"{where}: expected one of {', '.join(KINDS)} (e.g. "
                          f"{{relative: 0.3}}), got {spec!r}")
    kind, bounds = next(iter(spec.items()))
    low, high = _bounds(where, kind, bounds)
    r = Range(name, kind, low, high, _nominal(config, name))
    rule = field.metadata["rule"]
    for value in r.value_range:
        problem = rule(float(value))
        if problem:
            raise ConfigError(f"{where}: the range reaches {value:.6g}, which {problem}")
    return r


def _check_used(config: GraphConfig, plant: Mapping[str, Any], ranges: list[Range],
                path: Path) -> None:
    """Refuse a fixed value or a varied parameter that the plant's sub-models (the
    configuration's ``models`` with the distribution's ``plant:`` on top) leave out: its
    draws would all be the same plant."""
    models = {**to_flat(config.simulated_plant.models, "models"),
              **{k: v for k, v in plant.items() if k.startswith("models.")}}
    fixed = unused_by_models({**models, **plant})
    if fixed:
        raise ConfigError(f"{path}: distribution.plant: " + "; ".join(fixed))
    # a varied parameter is probed at the far end of its range from the default
    probe = {r.name: max(r.value_range, key=lambda v, r=r: abs(v - _default(r.name)))
             for r in ranges}
    varied = [text.replace(" is not used", " (varied) is not used", 1)
              for text in unused_by_models({**models, **probe})]
    if varied:
        raise ConfigError(f"{path}: distribution.parameters: " + "; ".join(varied))


def _default(name: str) -> float:
    return float(_field(name)[1].default)


def load_distribution(name_or_path: str, config: GraphConfig) -> Distribution:
    """Read and check a distribution around ``config``'s plant; ConfigError on bad input."""
    path = distribution_path(name_or_path)
    text = path.read_text()
    body = load_keyed_yaml(path, "distribution", KEYS, "distribution")
    plant = body.get("plant") or {}
    if not isinstance(plant, Mapping):
        raise ConfigError(f"{path}: distribution.plant must be a mapping of sections")
    plant = flatten(plant)
    check_plant_overrides(plant, f"{path}: distribution.plant:")
    for section in sorted({name.split(".", 1)[0] for name in plant}):
        try:
            from_flat(SECTIONS[section], plant, section)
        except ConfigError as exc:
            raise ConfigError(f"{path}: distribution.plant: {exc}") from None
    parameters = body.get("parameters") or {}
    if not isinstance(parameters, Mapping) or not parameters:
        raise ConfigError(f"{path}: distribution.parameters must map parameter names to "
                          "ranges")
    ranges = []
    for name in sorted(parameters):
        if name in plant:
            raise ConfigError(f"{path}: {name} is both fixed (distribution.plant) and varied "
                              "(distribution.parameters)")
        ranges.append(parse_range(config, str(name), parameters[name],
                                  f"{path}: distribution.parameters."))
    rows = None
    if "joint" in body:
        joint, rows = parse_joint(config, body["joint"], f"{path}: distribution.joint")
        for r in joint:
            if r.name in plant or r.name in parameters:
                raise ConfigError(f"{path}: {r.name} is both in distribution.joint and in "
                                  "distribution.plant or distribution.parameters")
        ranges += joint
        order = sorted(range(len(joint)), key=lambda j: joint[j].name)
        rows = rows[:, order]
    _check_used(config, plant, ranges, path)
    return Distribution(path.stem, str(body.get("description", "")), dict(plant),
                        tuple(sorted(ranges, key=lambda r: r.name)), text, rows)


def parse_joint(config: GraphConfig, spec: Any, where: str) -> tuple[list[Range], np.ndarray]:
    """A ``joint`` block: a "joint" range a name (its span) and the rows; ConfigError
    naming the parameter, or the row, that is wrong."""
    if not isinstance(spec, Mapping) or set(spec) != {"names", "rows"}:
        raise ConfigError(f"{where}: expected {{names: [...], rows: [[...], ...]}}")
    names, rows = spec["names"], spec["rows"]
    if (not isinstance(names, list) or not names or len(set(names)) != len(names)
            or not all(isinstance(n, str) for n in names)):
        raise ConfigError(f"{where}.names: expected a list of distinct parameter names")
    fields_ = []
    for name in names:
        try:
            fields_.append(_field(name)[1])
        except ConfigError as exc:
            raise ConfigError(f"{where}.names: {exc}") from None
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"{where}.rows: expected a list of rows, one a rig")
    for k, row in enumerate(rows):
        if (not isinstance(row, list) or len(row) != len(names) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                for v in row)):
            raise ConfigError(f"{where}.rows[{k}]: expected {len(names)} finite numbers "
                              f"(one a name), got {row!r}")
        for name, field, value in zip(names, fields_, row, strict=True):
            problem = field.metadata["rule"](float(value))
            if problem:
                raise ConfigError(f"{where}.rows[{k}]: {name} = {value!r}, which {problem}")
    table = np.array(rows, dtype=float)
    return [Range(name, "joint", float(table[:, j].min()), float(table[:, j].max()),
                  _nominal(config, name)) for j, name in enumerate(names)], table

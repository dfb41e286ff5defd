"""Typed configuration: frozen dataclasses that double as the ROS parameter schema.

Every configurable value of PISC is a field of a frozen dataclass declared with
:func:`param`. The field's metadata holds its description, unit and validity rule, so
one declaration serves three readers:

* the pure cores, which build the dataclass from a parameter file with
  :func:`from_flat` and get a :class:`ConfigError` naming the parameter on bad input;
* the rclpy shells, which declare one ROS parameter per field (with the description
  as the descriptor) and build the same dataclass from the values ROS hands back;
* the documentation, which lists the parameters with :func:`describe`.

Parameter files use the ROS 2 format (``<node or /**>: ros__parameters: {...}``) so a
file kept in the repository loads unchanged with ``--ros-args --params-file``.
Nested sections become dotted names (``rig.cart_mass_kg``), as ROS does.
"""

from __future__ import annotations

import array
import dataclasses
import difflib
import math
import re
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

__all__ = [
    "ConfigError",
    "Rule",
    "check_names",
    "closest",
    "any_value",
    "describe",
    "package_dir",
    "finite",
    "flatten",
    "from_flat",
    "in_range",
    "find_file",
    "load_keyed_yaml",
    "load_yaml",
    "load_params_file",
    "nonnegative",
    "one_of",
    "param",
    "positive",
    "to_flat",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or breaks a rule.

    The message always starts with the full parameter name, so a user can find the
    line of the parameter file to fix.
    """


# A rule returns None when the value is acceptable, otherwise the broken rule in words.
Rule = Callable[[Any], "str | None"]


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


# A list of numbers as ROS hands it over: a YAML list, a tuple, or the array.array('d')
# or array('q') that rclpy makes of a DOUBLE_ARRAY or INTEGER_ARRAY parameter value.
_SEQUENCES = (list, tuple, array.array)


def _numbers(value: Any) -> list[float]:
    if _is_number(value):
        return [float(value)]
    if isinstance(value, _SEQUENCES) and all(_is_number(v) for v in value):
        return [float(v) for v in value]
    return []


def any_value(value: Any) -> str | None:
    return None


def finite(value: Any) -> str | None:
    numbers = _numbers(value)
    if not all(math.isfinite(v) for v in numbers):
        return "must be finite"
    return None


def positive(value: Any) -> str | None:
    problem = finite(value)
    if problem:
        return problem
    if not all(v > 0.0 for v in _numbers(value)):
        return "must be positive (> 0)"
    return None


def nonnegative(value: Any) -> str | None:
    problem = finite(value)
    if problem:
        return problem
    if not all(v >= 0.0 for v in _numbers(value)):
        return "must not be negative (>= 0)"
    return None


def in_range(low: float, high: float) -> Rule:
    def rule(value: Any) -> str | None:
        problem = finite(value)
        if problem:
            return problem
        if not all(low <= v <= high for v in _numbers(value)):
            return f"must lie in [{low}, {high}]"
        return None

    return rule


def one_of(*choices: str) -> Rule:
    def rule(value: Any) -> str | None:
        if value not in choices:
            return "must be one of " + ", ".join(repr(c) for c in choices)
        return None

    return rule


def param(
    default: Any,
    description: str,
    unit: str = "",
    rule: Rule = finite,
) -> Any:
    """Declare a configuration field.

    Parameters
    ----------
    default
        The value used when a parameter file does not set it. Lists are stored as
        tuples so the dataclass stays hashable and immutable.
    description
        One line for the ROS parameter descriptor and the documentation; cite the
        thesis symbol or equation where there is one.
    unit
        SI unit, shown next to the description.
    rule
        Validity rule checked by :func:`from_flat`.
    """
    if isinstance(default, list):
        default = tuple(default)
    return dataclasses.field(
        default=default,
        metadata={"description": description, "unit": unit, "rule": rule},
    )


def _coerce(name: str, default: Any, value: Any) -> Any:
    """Convert a raw parameter value to the default's type, or raise ConfigError."""
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{name}: expected true or false, got {value!r}")
    if isinstance(default, float):
        if _is_number(value):
            return float(value)
        raise ConfigError(f"{name}: expected a number, got {value!r}")
    if isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{name}: expected an integer, got {value!r}")
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        raise ConfigError(f"{name}: expected a string, got {value!r}")
    if isinstance(default, tuple):
        if isinstance(value, _SEQUENCES) and all(_is_number(v) for v in value):
            return tuple(float(v) for v in value)
        raise ConfigError(f"{name}: expected a list of numbers, got {value!r}")
    raise TypeError(f"{name}: unsupported parameter type {type(default).__name__}")


def from_flat(cls: type[T], flat: Mapping[str, Any], section: str) -> T:
    """Build ``cls`` from dotted parameter names under ``section``.

    Missing names take the field default; unknown names under the section are an
    error (a typo must not be ignored in silence). Cross-field rules belong in the
    dataclass's ``__post_init__``, which raises :class:`ConfigError` itself.
    """
    prefix = section + "."
    check_names(cls, flat, section)
    values: dict[str, Any] = {}
    for field in dataclasses.fields(cls):  # type: ignore[arg-type]
        name = prefix + field.name
        if name not in flat:
            continue
        value = _coerce(name, field.default, flat[name])
        problem = field.metadata["rule"](value)
        if problem:
            raise ConfigError(f"{name} = {value!r} {problem}")
        values[field.name] = value
    instance = cls(**values)
    # Defaults are checked too: a default that breaks its own rule is a bug.
    for field in dataclasses.fields(cls):  # type: ignore[arg-type]
        value = getattr(instance, field.name)
        problem = field.metadata["rule"](value)
        if problem:
            raise ConfigError(f"{prefix}{field.name} = {value!r} {problem}")
    return instance


def closest(name: str, known: Iterable[str]) -> str:
    """'; did you mean X?' for the known name closest to ``name`` (difflib), else ''."""
    match = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f"; did you mean {match[0]}?" if match else ""


def check_names(cls: type, names: Iterable[str], section: str) -> None:
    """Raise :class:`ConfigError` for a name under ``section`` that ``cls`` does not have."""
    prefix = section + "."
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(n for n in names if n.startswith(prefix) and n[len(prefix):] not in known)
    if unknown:
        hint = closest(unknown[0], (prefix + k for k in known))
        raise ConfigError(
            f"{unknown[0]}: unknown parameter{hint} (known in '{section}': "
            f"{', '.join(sorted(known))})"
        )


def to_flat(obj: Any, section: str) -> dict[str, Any]:
    """The inverse of :func:`from_flat`: dotted names to plain values."""
    out: dict[str, Any] = {}
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        out[f"{section}.{field.name}"] = list(value) if isinstance(value, tuple) else value
    return out


def describe(cls: type, section: str) -> list[tuple[str, Any, str, str]]:
    """(name, default, unit, description) for each field, for docs and descriptors."""
    return [
        (f"{section}.{f.name}", f.default, f.metadata["unit"], f.metadata["description"])
        for f in dataclasses.fields(cls)
    ]


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings to dotted names, the way ROS 2 reads parameter files."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader (YAML 1.1), which reads ``5e-1`` as a string: a float's
    mantissa must have a dot there. ROS 2 reads parameter values as YAML 1.2 does (rcl's
    parser takes any number ``strtod`` takes), so such a value is a float here too."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+.0123456789"))


def load_yaml(text: Any) -> Any:
    """A YAML document (a string or a file) as ROS 2 reads parameters (:class:`_Loader`);
    raises yaml.YAMLError as ``yaml.safe_load`` does."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``NAME=VALUE`` command-line overrides to flat parameters, values read as YAML.

    Raises :class:`ConfigError` for an item without ``=`` or without a name, or whose
    value is not YAML.
    """
    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE")
        try:
            out[name.strip()] = load_yaml(value)
        except yaml.YAMLError as exc:
            problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
            raise ConfigError(f"--set {item!r}: the value is not valid YAML ({problem})"
                              ) from None
    return out


def package_dir(package: str, folder: str) -> Path:
    """A data folder of a PISC package (``config``, ``scenes``, ``distributions``,
    ``launch``): ``src/<package>/<folder>`` in a checkout or an editable install, else the
    package's ``share/<package>/<folder>`` in the ament index (``colcon build``), else under
    this interpreter's prefix (a plain pip install)."""
    source = Path(__file__).resolve().parents[2] / package / folder
    if source.is_dir():
        return source
    try:
        from ament_index_python.packages import (
            PackageNotFoundError,
            get_package_share_directory,
        )

        try:
            return Path(get_package_share_directory(package)) / folder
        except (PackageNotFoundError, ValueError, LookupError, OSError):
            pass
    except ImportError:
        pass
    return Path(sys.prefix) / "share" / package / folder


def find_file(name_or_path: str, directory: Path, what: str,
              shipped: Callable[[], Iterable[str]], suffixes: Sequence[str] = ()) -> Path:
    """``directory/<name>.yaml`` for a shipped name, else an existing path (with one of
    ``suffixes``, when given); :class:`ConfigError` naming what was not found."""
    candidate = directory / f"{name_or_path}.yaml"
    if candidate.exists():
        return candidate
    path = Path(name_or_path)
    if path.exists() and (not suffixes or path.suffix in suffixes):
        return path
    raise ConfigError(f"{name_or_path}: no such {what} (shipped: {', '.join(shipped())}) "
                      f"or {what} file")


def load_keyed_yaml(path: Path, key: str, keys: Iterable[str], what: str) -> Mapping[str, Any]:
    """The mapping under ``key`` of a YAML file whose keys under it are among ``keys``.

    Raises :class:`ConfigError` naming the file, and the key when one is unknown.
    """
    try:
        document = load_yaml(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(document, Mapping) or not isinstance(document.get(key), Mapping):
        raise ConfigError(f"{path}: a {what} file holds one mapping under the key '{key}'")
    body = document[key]
    known = list(keys)
    unknown = sorted(set(body) - set(known))
    if unknown:
        raise ConfigError(f"{path}: {key}.{unknown[0]}: unknown key (known: "
                          f"{', '.join(known)})")
    return body


def load_params_file(path: str | Path, node_names: Sequence[str] = ("/**",)) -> dict[str, Any]:
    """Read a ROS 2 parameter file into dotted names.

    Sections for ``/**`` come first and the named nodes override them, in order, as
    ``--params-file`` does. Raises :class:`ConfigError` naming the file when it is
    missing or not a ROS 2 parameter file.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read parameter file ({exc.strerror})") from exc
    try:
        tree = load_yaml(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(tree, Mapping):
        raise ConfigError(f"{path}: expected '<node>: ros__parameters: ...' at the top level")
    flat: dict[str, Any] = {}
    found = False
    for node in node_names:
        section = tree.get(node)
        if section is None:
            continue
        if not isinstance(section, Mapping) or "ros__parameters" not in section:
            raise ConfigError(f"{path}: section '{node}' has no 'ros__parameters' mapping")
        flat.update(flatten(section["ros__parameters"]))
        found = True
    if not found:
        raise ConfigError(
            f"{path}: none of the sections {', '.join(node_names)} is present"
        )
    return flat

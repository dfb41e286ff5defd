"""The parameters every PISC node reads besides its own, and the names it refuses.

Pure (no rclpy): :class:`StartParams` (``start.*``: what a node waits for before its
first input, which publisher it pins on each input); :func:`parse_ros_arguments`, the
parameters a process's ``--ros-args`` set, checked as rcl will read them, so that a
missing or broken parameter file and a malformed ``-p`` are a one-line refusal; and
:func:`check_overrides`, the refusal of a name a node would ignore
(:mod:`pisc_msgs_py.base_node`, "Names"), with :data:`PISC_SECTIONS`, the sections some
node reads.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import yaml

from pisc_msgs_py import config as cfg
from pisc_msgs_py.watchdog import parse_publishers

__all__ = ["PISC_SECTIONS", "SHARED_KEYS", "Override", "StartError", "StartParams",
           "await_entries", "check_overrides", "parse_ros_arguments"]


#: The sections some PISC node reads (plant, estimator, supervisor, current loop, driver,
#: markers); test_nodes checks this against the nodes' own lists.
PISC_SECTIONS = frozenset({
    "actuator", "adaptation", "catch", "current_loop", "driver", "estimator", "experiment",
    "friction", "initial", "integrator", "loop", "markers", "models", "motor", "noise", "rig",
    "safety", "sensors", "simulation", "start", "startup", "swing_up", "switching", "track"})


def await_entries(text: str) -> list[tuple[str, int]]:
    """``start.await_subscribers``' ``TOPIC=N,...`` as (topic, N); raises ConfigError
    with what is wrong (the rule's words, after the value)."""
    entries: list[tuple[str, int]] = []
    for item in text.split(","):
        topic, sep, count = (part.strip() for part in item.partition("="))
        if not sep or not topic.startswith("/") or not count.isdigit():
            raise cfg.ConfigError(f"must list TOPIC=N (an absolute topic name, a count "
                                  f">= 0): {item.strip()!r} is not")
        if any(topic == t for t, _ in entries):
            raise cfg.ConfigError(f"names {topic} twice")
        entries.append((topic, int(count)))
    return entries


def _await_rule(value: Any) -> str | None:
    if value:
        try:
            await_entries(value)
        except cfg.ConfigError as exc:
            return str(exc)
    return None


def _publishers_rule(value: Any) -> str | None:
    try:
        parse_publishers(value)
    except ValueError as exc:
        return str(exc)
    return None


@dataclass(frozen=True)
class StartParams:
    """What every PISC node waits for before it takes its first input."""

    await_subscribers: str = cfg.param(
        "", "TOPIC=N[,TOPIC=N...]: before its first subscription the node waits until each "
        "of these publications of its own has matched at least N subscribers, so that "
        "nothing it publishes is lost to a reader that matches it late (a DDS writer "
        "learns of a reader apart from the reader learning of it). pisc_graph sets it for "
        "the nodes it starts as processes (its recorder and the graph's other nodes); '': "
        "no wait", "", _await_rule)
    await_timeout_s: float = cfg.param(
        30.0, "the longest wait for start.await_subscribers; after it the node does not "
        "start (exit status 1), naming each publication still short of its subscribers",
        "s", cfg.in_range(0.01, 600.0))
    publishers: str = cfg.param(
        "", "TOPIC=NODE[|NODE...][,TOPIC=...]: the node that publishes each input topic of "
        "this node (and /clock); its publisher is pinned at the start, and while any other "
        "publisher is there the node uses none of its inputs and says so on /diagnostics. "
        "A topic not named keeps the graph's own name (the plant or the driver, estimator, "
        "supervisor, current_loop); pisc_graph sets it from the launch file", "",
        _publishers_rule)


class StartError(RuntimeError):
    """A node's start condition was not met in time (:class:`StartParams`)."""


# parameter file sections every node of the graph reads
SHARED_KEYS = ("/**", "/*")
# --ros-args options that take one argument, and those that take none (rcl's arguments.c)
_ROS_OPTIONS_WITH_VALUE = ("-r", "--remap", "-e", "--enclave", "--log-level",
                           "--log-config-file", "--log-file-name")


@dataclass(frozen=True)
class Override:
    """A parameter a process's command line sets, and for which nodes.

    ``target`` is None for ``-p NAME:=VALUE`` (every node of the process), a key of
    :data:`SHARED_KEYS` for a parameter file's shared section, else the node name or
    pattern a file section or ``-p NODE:NAME:=VALUE`` names.
    """

    target: str | None
    name: str
    origin: str  # the argument or file, for the message


def _yaml_problem(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}" if mark else problem


def _params_file_overrides(path: str) -> list[Override]:
    origin = f"--params-file {path}"
    try:
        with open(path, encoding="utf-8") as handle:
            tree = yaml.safe_load(handle)
    except OSError as exc:
        raise cfg.ConfigError(f"{origin}: cannot read it ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise cfg.ConfigError(f"{origin}: not valid YAML ({_yaml_problem(exc)})") from None
    rule = "a ROS 2 parameter file is '<node or /**>: ros__parameters: {...}'"
    if not isinstance(tree, Mapping):
        raise cfg.ConfigError(f"{origin}: {rule}")
    out = []
    for key, section in tree.items():
        if not isinstance(section, Mapping) or not isinstance(
                section.get("ros__parameters"), Mapping):
            raise cfg.ConfigError(f"{origin}: section '{key}' has no 'ros__parameters' mapping "
                                  f"({rule})")
        out += [Override(str(key), name, origin)
                for name in cfg.flatten(section["ros__parameters"])]
    return out


def parse_ros_arguments(argv: Sequence[str]) -> tuple[Override, ...]:
    """The parameters ``--ros-args`` set, checked as rcl will read them.

    Raises :class:`ConfigError` naming the argument or file: ``-p`` without
    ``NAME:=VALUE`` or with a value that is not YAML, a parameter file that cannot be
    read, is not YAML or is not a ROS 2 parameter file.
    """
    out: list[Override] = []
    inside = False
    items = list(argv)
    k = 0
    while k < len(items):
        arg = items[k]
        k += 1
        if arg == "--ros-args":
            inside = True
            continue
        if not inside:
            continue
        if arg == "--":
            inside = False
        elif arg in ("-p", "--param", "--params-file"):
            if k >= len(items):
                raise cfg.ConfigError(f"{arg}: expected "
                                      f"{'a file' if arg == '--params-file' else 'NAME:=VALUE'} "
                                      "after it")
            value = items[k]
            k += 1
            if arg == "--params-file":
                out += _params_file_overrides(value)
                continue
            origin = f"{arg} {value}"
            head, sep, text = value.partition(":=")
            if not sep or not head:
                raise cfg.ConfigError(f"{origin}: expected NAME:=VALUE "
                                      "(e.g. -p rig.cart_mass_kg:=0.4735)")
            try:
                yaml.safe_load(text)
            except yaml.YAMLError as exc:
                raise cfg.ConfigError(f"{origin}: the value is not valid YAML "
                                      f"({_yaml_problem(exc)})") from None
            node, colon, name = head.rpartition(":")
            out.append(Override(node if colon else None, name, origin))
        elif arg in _ROS_OPTIONS_WITH_VALUE:
            k += 1
    return tuple(out)


def aims_at(target: str, fully_qualified_name: str) -> bool:
    pattern = target if target.startswith("/") else "/" + target
    return fnmatch.fnmatchcase(fully_qualified_name, pattern.replace("/**", "*"))


def check_overrides(node_name: str, fully_qualified_name: str, declared: Sequence[str],
                    sections: Mapping[str, type], command_line: Sequence[Override],
                    overrides: Mapping[str, Any]) -> None:
    """Refuse a name node ``node_name`` would ignore (:mod:`pisc_msgs_py.base_node`,
    "Names"): raise ConfigError naming it and the closest known name.

    ``declared``: the node's parameters; ``sections``: what it reads; ``command_line``:
    what :func:`parse_ros_arguments` read from its process's arguments; ``overrides``:
    every value given to the node (rclpy's ``_parameter_overrides``).
    """
    for override in command_line:
        aimed = override.target is None or (
            override.target not in SHARED_KEYS and aims_at(override.target,
                                                           fully_qualified_name))
        if aimed and override.name not in declared:
            raise cfg.ConfigError(
                f"{override.name} ({override.origin}): not a parameter of node "
                f"'{node_name}'{cfg.closest(override.name, declared)} (it reads "
                f"{', '.join(sections)})")
    for section, cls in sections.items():
        cfg.check_names(cls, overrides, section)
    for name in sorted(overrides):
        section, _, rest = name.partition(".")
        if name in declared or section in PISC_SECTIONS:
            continue
        hint = cfg.closest(name, declared)
        match = cfg.closest(section, PISC_SECTIONS)
        if not hint and match and rest:
            hint = f"; did you mean {match[len('; did you mean '):-1]}.{rest}?"
        raise cfg.ConfigError(
            f"{name}: unknown parameter{hint} (not a parameter of node "
            f"'{node_name}', and '{section}' is no section of a PISC node)")

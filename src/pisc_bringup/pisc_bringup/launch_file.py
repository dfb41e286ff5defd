"""Read the graph's ROS 2 XML launch files, so that ``pisc_graph`` and ``ros2 launch`` start
the same nodes from one declaration.

    launch/sim.launch.xml    the plant and the controllers (ros2 launch pisc_bringup sim.launch.xml)
    launch/rig.launch.xml    the serial driver and the controllers (port:=/dev/ttyUSB0)

This reads the subset of ROS 2's XML launch format (``launch_xml``) those files use:
``<launch>`` holding ``<arg name default description>``, ``<node pkg exec name output>``
with ``<param from="FILE"/>`` and ``<param name value/>``, and ``<group if="..."/>`` (or
``unless``) holding nodes, started when the condition is true (``true``/``1``) or false
(``false``/``0``); values may hold the substitutions ``$(var NAME)`` and
``$(find-pkg-share PACKAGE)``. Anything else is refused
with the element and what is wrong, rather than half understood.

``$(find-pkg-share PACKAGE)`` is the package's ``share/PACKAGE`` in the ament index when the
packages are installed (``colcon build``), else the package's source directory, where the
same ``config/``, ``scenes/`` and ``launch/`` folders live.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


from pisc_msgs_py.config import ConfigError, load_yaml, package_dir

__all__ = ["LaunchArg", "LaunchError", "LaunchNode", "find_package_share", "launch_path",
           "read_launch"]

SUBSTITUTION = re.compile(r"\$\((\S+)(?:\s+([^)]*))?\)")


class LaunchError(ConfigError):
    """A launch file this reader cannot take, or arguments it lacks."""


@dataclass(frozen=True)
class LaunchArg:
    name: str
    default: str | None  # None: the caller must give it
    description: str


@dataclass(frozen=True)
class LaunchNode:
    package: str
    executable: str
    name: str
    param_files: tuple[Path, ...] = ()
    parameters: dict[str, Any] = field(default_factory=dict)  # values typed as YAML reads them


def find_package_share(package: str) -> Path:
    """``share/PACKAGE`` of an installed package, else its source directory
    (:func:`pisc_msgs_py.config.package_dir`)."""
    path = package_dir(package, ".").resolve()
    if not (path / "package.xml").is_file():
        raise LaunchError(f"$(find-pkg-share {package}): no package {package!r} installed or "
                          "in the source tree")
    return path


def launch_path(name: str) -> Path:
    """A launch file by name (``sim``, ``rig``) or path."""
    path = Path(name)
    if path.suffix == ".xml" or path.exists():
        if not path.is_file():
            raise LaunchError(f"{path}: no such launch file")
        return path
    path = find_package_share("pisc_bringup") / "launch" / f"{name}.launch.xml"
    if not path.is_file():
        known = sorted(p.name.removesuffix(".launch.xml")
                       for p in path.parent.glob("*.launch.xml"))
        raise LaunchError(f"launch file {name!r}: not one of {', '.join(known)}")
    return path


def _substitute(text: str, args: Mapping[str, str], where: str) -> str:
    def one(match: re.Match[str]) -> str:
        kind, value = match.group(1), (match.group(2) or "").strip()
        if kind == "var":
            if value not in args:
                raise LaunchError(f"{where}: $(var {value}): no argument {value!r} declared")
            return args[value]
        if kind == "find-pkg-share":
            return str(find_package_share(value))
        raise LaunchError(f"{where}: $({kind} ...): substitution not supported (only var "
                          "and find-pkg-share)")

    return SUBSTITUTION.sub(one, text)


def _attributes(element: ET.Element, allowed: set[str], required: set[str],
                where: str) -> dict[str, str]:
    extra = sorted(set(element.attrib) - allowed)
    if extra:
        raise LaunchError(f"{where}: attribute {extra[0]!r} not supported (allowed: "
                          f"{', '.join(sorted(allowed))})")
    missing = sorted(required - set(element.attrib))
    if missing:
        raise LaunchError(f"{where}: attribute {missing[0]!r} missing")
    return dict(element.attrib)


def declared_args(path: Path) -> list[LaunchArg]:
    """The ``<arg>`` declarations of a launch file, in order."""
    root = _root(path)
    out = []
    for k, element in enumerate(root.findall("arg")):
        a = _attributes(element, {"name", "default", "description"}, {"name"},
                        f"{path}: <arg> {k + 1}")
        out.append(LaunchArg(a["name"], a.get("default"), a.get("description", "")))
    return out


def _root(path: Path) -> ET.Element:
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise LaunchError(f"{path}: cannot read it as XML ({exc})") from None
    if root.tag != "launch":
        raise LaunchError(f"{path}: the root element is <{root.tag}>, not <launch>")
    return root


def read_launch(path: str | Path, args: Mapping[str, str] | None = None) -> list[LaunchNode]:
    """The nodes a launch file starts, in the file's order, with ``args`` (``name:
    value``) given as ``ros2 launch FILE name:=value`` would; :class:`LaunchError` names
    what is wrong. A group whose condition is false starts nothing, but what it holds is
    checked all the same (its parameter files must exist)."""
    path = Path(path)
    root = _root(path)
    given = dict(args or {})
    values: dict[str, str] = {}
    for declared in declared_args(path):
        if declared.name in given:
            values[declared.name] = given.pop(declared.name)
        elif declared.default is not None:
            values[declared.name] = _substitute(declared.default, values,
                                                f"{path}: <arg {declared.name}>")
        else:
            raise LaunchError(f"{path}: argument {declared.name!r} has no default and was "
                              f"not given ({declared.description})")
    if given:
        raise LaunchError(f"{path}: argument {sorted(given)[0]!r} is not declared (declared: "
                          f"{', '.join(values) or 'none'})")
    nodes: list[LaunchNode] = []
    _read_nodes(root, path, values, nodes, top=True)
    if not nodes:
        raise LaunchError(f"{path}: starts no node")
    return nodes


def _condition(text: str, values: Mapping[str, str], where: str) -> bool:
    """An ``if``/``unless`` value as launch evaluates it: true/1 or false/0, any case."""
    value = _substitute(text, values, where).strip().lower()
    if value in ("true", "1"):
        return True
    if value in ("false", "0"):
        return False
    raise LaunchError(f"{where}: condition {text!r} is {value!r}: expected true, false, 1 or 0")


def _read_nodes(parent: ET.Element, path: Path, values: Mapping[str, str],
                nodes: list[LaunchNode], top: bool) -> None:
    """The nodes under ``parent`` (``<launch>`` or a ``<group>``), in order."""
    for element in parent:
        if element.tag == "arg" and top:
            continue
        if element.tag == "group":
            where = f"{path}: <group>"
            a = _attributes(element, {"if", "unless"}, set(), where)
            if "if" in a and "unless" in a:
                raise LaunchError(f"{where}: both 'if' and 'unless' (give one)")
            run = (_condition(a["if"], values, f"{where} if") if "if" in a
                   else not _condition(a["unless"], values, f"{where} unless")
                   if "unless" in a else True)
            if run:
                _read_nodes(element, path, values, nodes, top=False)
            else:  # what it would start is still checked, as strictly
                _read_nodes(element, path, values, [], top=False)
            continue
        if element.tag != "node":
            raise LaunchError(f"{path}: element <{element.tag}> not supported (only <arg>, "
                              "<node> and <group if|unless> holding <node>s)"
                              if top else f"{path}: <group>: element <{element.tag}> not "
                              "supported (only <node> and <group>)")
        where = f"{path}: <node {element.get('name', '?')}>"
        a = _attributes(element, {"pkg", "exec", "name", "output"}, {"pkg", "exec", "name"},
                        where)
        files: list[Path] = []
        parameters: dict[str, Any] = {}
        for child in element:
            if child.tag != "param":
                raise LaunchError(f"{where}: element <{child.tag}> not supported (only "
                                  "<param>)")
            if "from" in child.attrib:
                p = _attributes(child, {"from"}, {"from"}, f"{where} <param from>")
                file = Path(_substitute(p["from"], values, where))
                if not file.is_file():
                    raise LaunchError(f"{where}: parameter file {file} does not exist")
                files.append(file)
            else:
                p = _attributes(child, {"name", "value"}, {"name", "value"},
                                f"{where} <param>")
                text = _substitute(p["value"], values, where)
                parameters[p["name"]] = load_yaml(text) if text else ""
        nodes.append(LaunchNode(_substitute(a["pkg"], values, where),
                                _substitute(a["exec"], values, where),
                                _substitute(a["name"], values, where), tuple(files),
                                parameters))

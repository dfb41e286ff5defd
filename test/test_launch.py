"""The launch files: they name only executables and files that exist, they declare the
same nodes pisc_graph starts, and a launch file the reader cannot take is refused with
what is wrong."""

from __future__ import annotations

from importlib.metadata import entry_points
from pathlib import Path

import pytest

from pisc_bringup.graph import CONTROLLERS, DRIVER, GRAPH
from pisc_bringup.launch_file import LaunchError, declared_args, launch_path, read_launch

LAUNCH = Path(__file__).resolve().parents[1] / "src" / "pisc_bringup" / "launch"


def _console_scripts() -> dict[str, str]:
    """executable -> the distribution (package) that installs it."""
    return {ep.name: ep.dist.name for ep in entry_points(group="console_scripts")
            if ep.dist is not None and ep.dist.name.startswith("pisc_")}


@pytest.mark.parametrize("name, args", [("sim", {}), ("rig", {"port": "/dev/ttyUSB0"})])
def test_launch_files_name_only_executables_and_files_that_exist(name, args):
    scripts = _console_scripts()
    nodes = read_launch(launch_path(name), args)
    for node in nodes:
        assert scripts.get(node.executable) == node.package, node
        assert node.param_files and all(f.is_file() for f in node.param_files), node
    assert len({n.name for n in nodes}) == len(nodes)


def test_launch_files_declare_the_nodes_pisc_graph_starts():
    sim = read_launch(launch_path("sim"))
    assert [(n.name, n.executable) for n in sim] == [
        (s.name, s.executable) for s in (GRAPH[-1], *GRAPH[:-1])]
    rig = read_launch(launch_path("rig"), {"port": "/dev/ttyUSB0"})
    assert [(n.name, n.executable) for n in rig] == [
        (s.name, s.executable) for s in (DRIVER, *CONTROLLERS)]
    # lockstep: the controllers follow the plant's /clock; the plant owns time
    assert all(n.parameters.get("use_sim_time") is True for n in sim[1:])
    assert "use_sim_time" not in sim[0].parameters
    wall = read_launch(launch_path("sim"), {"clock": "wall", "use_sim_time": "false"})
    assert wall[0].parameters["simulation.clock"] == "wall"
    assert all(n.parameters["use_sim_time"] is False for n in wall[1:])
    assert rig[0].parameters == {"driver.port": "/dev/ttyUSB0"}


def test_arguments_have_descriptions_and_the_rig_needs_a_port():
    for name in ("sim", "rig"):
        assert all(a.description for a in declared_args(launch_path(name)))
    with pytest.raises(LaunchError, match="argument 'port' has no default"):
        read_launch(launch_path("rig"))
    with pytest.raises(LaunchError, match="argument 'prot' is not declared"):
        read_launch(launch_path("rig"), {"port": "/dev/ttyUSB0", "prot": "x"})
    with pytest.raises(LaunchError, match="not one of rig, sim"):
        launch_path("simulation")


@pytest.mark.parametrize("body, message", [
    ("<node pkg='pisc_control' exec='estimator_node' name='e'><remap from='a' to='b'/></node>",
     "element <remap> not supported"),
    ("<include file='x.launch.xml'/>", "element <include> not supported"),
    ("<node pkg='pisc_control' exec='estimator_node'/>", "attribute 'name' missing"),
    ("<node pkg='pisc_control' exec='estimator_node' name='e' namespace='n'/>",
     "attribute 'namespace' not supported"),
    ("<node pkg='pisc_control' exec='estimator_node' name='e'><param from='/nonexistent.yaml'/>"
     "</node>", "parameter file /nonexistent.yaml does not exist"),
    ("<node pkg='pisc_control' exec='$(env HOME)' name='e'/>", "$(env ...): substitution not "
     "supported"),
    ("<node pkg='pisc_control' exec='$(var nothing)' name='e'/>", "no argument 'nothing'"),
    ("", "starts no node"),
])
def test_a_launch_file_the_reader_cannot_take_is_refused(tmp_path, body, message):
    path = tmp_path / "bad.launch.xml"
    path.write_text(f"<launch>{body}</launch>")
    with pytest.raises(LaunchError, match=message.replace("(", r"\(").replace(")", r"\)")
                       .replace("$", r"\$")):
        read_launch(path)
    broken = tmp_path / "broken.launch.xml"
    broken.write_text("<launch><node>")
    with pytest.raises(LaunchError, match="cannot read it as XML"):
        read_launch(broken)


def test_the_files_shipped_are_the_ones_in_the_source_tree():
    assert sorted(p.name for p in LAUNCH.glob("*.launch.xml")) == [
        "rig.launch.xml", "sim.launch.xml"]
    assert launch_path("sim") == LAUNCH / "sim.launch.xml"

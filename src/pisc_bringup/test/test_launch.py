"""The launch files: they name only executables and files that exist, they are the graph
pisc_graph starts (the nodes, their names, parameter files and parameters), a launch file
whose graph cannot run is refused naming the file and the node, and a launch file the
reader cannot take is refused with what is wrong."""

from __future__ import annotations

import ast
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from pisc_bringup import graph_cli, run_start
from pisc_bringup.graph import RunOptions
from pisc_bringup.launch_graph import NODE_KINDS, read_graph, recorded_topics
from pisc_bringup.launch_file import LaunchError, declared_args, launch_path, read_launch
from pisc_msgs_py.topics import MARKERS
from pisc_sim.configuration import load_run_config

SRC = Path(__file__).resolve().parents[3] / "src"
LAUNCH = SRC / "pisc_bringup" / "launch"


def _console_scripts() -> dict[str, str]:
    """executable -> the distribution (package) that installs it."""
    return {ep.name: ep.dist.name for ep in entry_points(group="console_scripts")
            if ep.dist is not None and ep.dist.name.startswith("pisc_")}


def _setup_console_scripts(package: str) -> dict[str, str]:
    """executable -> module of the console_scripts in ``src/PACKAGE/setup.py`` (read, not
    run)."""
    tree = ast.parse((SRC / package / "setup.py").read_text())
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "setup":
            entry = next(k.value for k in call.keywords if k.arg == "entry_points")
            out = {}
            for line in ast.literal_eval(entry)["console_scripts"]:
                name, _, target = line.partition("=")
                out[name.strip()] = target.strip().partition(":")[0]
            return out
    raise AssertionError(f"{package}/setup.py calls no setup()")


ALL = [("sim", {"markers": "true"}), ("rig", {"port": "/dev/ttyUSB0", "markers": "true"})]


@pytest.mark.parametrize("name, args", [("sim", {}), ("rig", {"port": "/dev/ttyUSB0"}), *ALL])
def test_launch_files_name_only_executables_and_files_that_exist(name, args):
    scripts = _console_scripts()
    nodes = read_launch(launch_path(name), args)
    for node in nodes:
        assert scripts.get(node.executable) == node.package, node
        assert node.param_files and all(f.is_file() for f in node.param_files), node
    assert len({n.name for n in nodes}) == len(nodes)


@pytest.mark.parametrize("name, args", ALL)
def test_every_exec_is_a_console_script_of_its_package_setup_py(name, args):
    """ros2 launch runs lib/PACKAGE/EXEC, which colcon makes from setup.py's console_scripts;
    pisc_graph instantiates the same module's class in one process."""
    nodes = read_launch(launch_path(name), args)
    assert {n.executable for n in nodes} >= {"estimator_node", "markers_node"}
    for node in nodes:
        scripts = _setup_console_scripts(node.package)
        assert node.executable in scripts, (node, sorted(scripts))
        assert scripts[node.executable] == NODE_KINDS[node.package, node.executable].module


def test_the_console_script_reader_reads_what_setup_py_says():
    scripts = _setup_console_scripts("pisc_bringup")
    assert scripts["pisc_graph"] == "pisc_bringup.graph_cli"
    assert "plant_node" not in scripts and "plant_node" in _setup_console_scripts("pisc_plant")


def test_launch_files_declare_the_nodes_pisc_graph_starts():
    sim = read_launch(launch_path("sim"))
    assert [(n.name, n.executable) for n in sim] == [
        ("plant", "plant_node"), ("estimator", "estimator_node"),
        ("supervisor", "supervisor_node"), ("current_loop", "current_loop_node")]
    rig = read_launch(launch_path("rig"), {"port": "/dev/ttyUSB0"})
    assert [(n.name, n.executable) for n in rig] == [
        ("driver", "driver_node"), ("estimator", "estimator_node"),
        ("supervisor", "supervisor_node"), ("current_loop", "current_loop_node")]
    # lockstep: the controllers follow the plant's /clock; the plant owns time
    assert all(n.parameters.get("use_sim_time") is True for n in sim[1:])
    assert "use_sim_time" not in sim[0].parameters
    # ros2 launch alone: the plant's own defaults (it waits for one reader, runs on)
    assert sim[0].parameters == {
        "simulation.clock": "lockstep", "simulation.duration_s": 0.0,
        "simulation.min_subscribers": 1, "simulation.min_true_state_subscribers": 0,
        "simulation.min_clock_subscribers": 0, "simulation.recorder_lag_samples": 0,
        "simulation.start_settle_s": 0.5}
    # model error: the plant's file is params unless plant_params says otherwise
    assert sim[0].param_files == sim[1].param_files
    thesis = SRC / "pisc_sim" / "config" / "thesis.yaml"
    split = read_launch(launch_path("sim"), {"plant_params": str(thesis)})
    assert split[0].param_files == (thesis,) and split[1].param_files == sim[1].param_files
    wall = read_launch(launch_path("sim"), {"clock": "wall", "use_sim_time": "false"})
    assert wall[0].parameters["simulation.clock"] == "wall"
    assert all(n.parameters["use_sim_time"] is False for n in wall[1:])
    assert rig[0].parameters == {"driver.port": "/dev/ttyUSB0", "driver.min_subscribers": 0}
    # markers on request, in either file, reading the controllers' parameter file
    for name, args in ALL:
        nodes = read_launch(launch_path(name), args)
        assert [(n.name, n.executable) for n in nodes][-1] == ("markers", "markers_node")
        assert nodes[-1].param_files == nodes[1].param_files and not nodes[-1].parameters


def _run_files(tmp_path, options):
    _, flat, plant = load_run_config(options.config, options.overrides, options.plant_config,
                                     options.plant_overrides)
    return run_start.write_params(tmp_path, flat, None if options.driver_port else plant)


@pytest.mark.parametrize("processes", [False, True])
def test_pisc_graph_gives_the_launch_file_what_it_gave_the_nodes_before(tmp_path, processes):
    """The arguments pisc_graph passes (its bag's files, the clock, the duration, what the
    plant waits for: the 3 controllers' clocks, the recorder and, with separate processes,
    the runner; how far it may run ahead of the recorder) reach the plant's and the
    controllers' parameters."""
    options = RunOptions(overrides={"initial.x_m": 0.05}, duration_s=3.0, processes=processes,
                         plant_overrides={"motor.resistance_ohm": 18.2})
    files = _run_files(tmp_path, options)
    first = read_graph("sim", run_start.launch_args(options, files))
    g = run_start.read_again(first, options, files, run_start.run_args(options, first))
    assert [n.name for n in g.nodes] == ["estimator", "supervisor", "current_loop", "plant"]
    clocks = 5 if processes else 4
    # in one process pisc_graph has seen every match before the plant starts: no settling
    assert g.source.parameters == {
        "simulation.clock": "lockstep", "simulation.duration_s": 3.0,
        "simulation.min_subscribers": 2, "simulation.min_true_state_subscribers": 1,
        "simulation.min_clock_subscribers": clocks, "simulation.recorder_lag_samples": 20,
        "simulation.start_settle_s": 0.5 if processes else 0.0}
    plant, estimator = g.source.flat(), g.controllers[0].flat()
    assert plant["motor.resistance_ohm"] == 18.2 and estimator["motor.resistance_ohm"] == 14.0
    assert estimator["initial.x_m"] == 0.05 and estimator["use_sim_time"] is True
    # as a process: the file's name, files and parameters on the command line
    command = g.source.command()
    assert command[0].endswith("plant_node") and command[1:] == [
        "--ros-args", "-r", "__node:=plant", "--params-file", str(tmp_path / "plant_params.yaml"),
        "-p", "simulation.clock:=lockstep", "-p", "simulation.duration_s:=3.0",
        "-p", "simulation.min_subscribers:=2", "-p", "simulation.min_true_state_subscribers:=1",
        "-p", f"simulation.min_clock_subscribers:={clocks}",
        "-p", "simulation.recorder_lag_samples:=20",
        "-p", f"simulation.start_settle_s:={0.5 if processes else 0.0}"]
    assert g.controllers[2].command()[-2:] == ["-p", "use_sim_time:=true"]


@pytest.mark.parametrize("lockstep", [True, False])
def test_node_processes_wait_until_their_publishers_have_matched_their_readers(lockstep):
    """With --processes each node is told, per publication, how many readers to match
    before it subscribes (start.await_subscribers): the next controller, the recorder, the
    runner's voltage tap and, in lockstep, where the plant starts with them, the plant.
    A publisher's match with the recorder can come long after the recorder's with it
    (docs/recording.md, "Late matches")."""
    g = read_graph("sim", {"markers": "true"})
    recorded = recorded_topics(None) + (MARKERS,)
    counted = [*g.controllers, *([g.source] if lockstep else [])]
    told = {n.name: run_start.awaiting(n, counted, recorded).parameters[
        "start.await_subscribers"] for n in (*g.controllers, *g.observers)}
    # supervisor and recorder; current loop and recorder (twice), the recorder alone for
    # the pendulum estimate; the recorder alone; the recorder, the tap and the plant; the
    # recorder
    assert told == {
        "estimator": "/pisc/state=2",
        "supervisor": "/pisc/cart_force=2,/pisc/mode=2,/pisc/pendulum_estimate=1",
        "current_loop": "/pisc/motor/current_setpoint=1,"
                        f"/pisc/motor/voltage={3 if lockstep else 2}",
        "markers": "/pisc/markers=1"}
    # on the command line, after the launch file's parameters
    command = run_start.awaiting(g.controllers[0], counted, recorded).command()
    assert command[-4:] == ["-p", "use_sim_time:=true", "-p",
                            "start.await_subscribers:=/pisc/state=2"]


def test_the_driver_waits_for_the_graphs_readers_and_the_recorder(tmp_path):
    options = RunOptions(clock="wall", driver_port="/dev/ttyUSB0", markers=True)
    files = _run_files(tmp_path, options)
    first = read_graph("rig", run_start.launch_args(options, files), driver=True)
    g = run_start.read_again(first, options, files, run_start.run_args(options, first))
    assert [n.name for n in g.nodes] == ["estimator", "supervisor", "current_loop", "markers",
                                         "driver"]
    assert g.source.parameters == {"driver.port": "/dev/ttyUSB0", "driver.min_subscribers": 2}
    assert g.source.param_files == (tmp_path / "pisc_params.yaml",)
    assert "use_sim_time" not in g.controllers[0].flat()


def edited_launch(tmp_path, name, old, new):
    """A copy of a shipped launch file with ``old`` (found once) replaced by ``new``."""
    text = (LAUNCH / f"{name}.launch.xml").read_text()
    assert text.count(old) == 1, old
    path = tmp_path / f"edited-{name}.launch.xml"
    path.write_text(text.replace(old, new))
    return path


ESTIMATOR = """<node pkg="pisc_control" exec="estimator_node" name="estimator" output="screen">
    <param from="$(var params)"/>
    <param name="use_sim_time" value="$(var use_sim_time)"/>
  </node>"""


@pytest.mark.parametrize("old, new, driver, message", [
    (ESTIMATOR, "", False, "no node publishes /pisc/state, which node 'supervisor' "
     "(pisc_control supervisor_node) reads"),
    ('exec="supervisor_node"', 'exec="supervisor"', False,
     "node 'supervisor' (pisc_control supervisor): pisc_graph does not know this executable"),
    ('name="supervisor"', 'name="estimator"', False, "two nodes are named 'estimator'"),
    ('name="plant"', 'name="plant"', True,
     "node 'plant' (pisc_plant plant_node) in a run through the serial driver"),
    ('<node pkg="pisc_plant" exec="plant_node"', '<node pkg="pisc_driver" exec="driver_node"',
     False, "node 'plant' (pisc_driver driver_node) in a run of the simulated plant"),
    (ESTIMATOR, ESTIMATOR + ESTIMATOR.replace('name="estimator"', 'name="estimator2"'), False,
     "nodes 'estimator' and 'estimator2' both publish /pisc/state"),
])
def test_a_launch_file_whose_graph_cannot_run_is_refused_naming_file_and_node(
        tmp_path, old, new, driver, message):
    path = edited_launch(tmp_path, "sim", old, new)
    with pytest.raises(LaunchError) as info:
        read_graph(path, {}, driver=driver)
    assert str(info.value).startswith(f"{path}: ") and message in str(info.value)


def test_a_graph_without_its_source_is_refused(tmp_path):
    plant = (LAUNCH / "sim.launch.xml").read_text()
    start = plant.index('  <node pkg="pisc_plant"')
    path = tmp_path / "no-plant.launch.xml"
    path.write_text(plant[:start] + plant[plant.index("</node>", start) + 8:])
    with pytest.raises(LaunchError, match="no node runs pisc_plant plant_node"):
        read_graph(path)


def test_pisc_graph_launch_refuses_a_file_without_the_nodes_or_arguments_it_needs(
        tmp_path, capsys):
    """pisc_graph --launch FILE: refused before anything starts, exit 2, naming the file
    and what is wrong, no traceback, no bag."""
    bag = tmp_path / "bag"
    path = edited_launch(tmp_path, "sim", ESTIMATOR, "")
    assert graph_cli.main(["--launch", str(path), "--duration", "1", "--bag", str(bag)]) == 2
    err = capsys.readouterr().err
    assert f"{path}: no node publishes /pisc/state, which node 'supervisor'" in err
    assert "Traceback" not in err and not bag.exists()
    # a file that does not declare an argument pisc_graph gives it
    path = edited_launch(tmp_path, "sim", '<arg name="duration"', '<arg name="length"')
    assert graph_cli.main(["--launch", str(path), "--duration", "1", "--bag", str(bag)]) == 2
    err = capsys.readouterr().err
    assert f"{path}: argument 'duration' is not declared" in err and not bag.exists()
    assert graph_cli.main(["--launch", str(tmp_path / "none.launch.xml"), "--bag", str(bag)]) == 2
    assert "none.launch.xml: no such launch file" in capsys.readouterr().err
    assert not bag.exists()


def test_arguments_have_descriptions_and_the_rig_needs_a_port():
    for name in ("sim", "rig"):
        assert all(a.description for a in declared_args(launch_path(name)))
    with pytest.raises(LaunchError, match="argument 'port' has no default"):
        read_launch(launch_path("rig"))
    with pytest.raises(LaunchError, match="argument 'prot' is not declared"):
        read_launch(launch_path("rig"), {"port": "/dev/ttyUSB0", "prot": "x"})
    with pytest.raises(LaunchError, match="not one of rig, sim"):
        launch_path("simulation")


@pytest.mark.parametrize("condition, started", [
    ("if='true'", ["a", "b", "c"]), ("if='False'", ["a", "c"]), ("if='1'", ["a", "b", "c"]),
    ("unless='true'", ["a", "c"]), ("unless='0'", ["a", "b", "c"]), ("", ["a", "b", "c"]),
    ("if='$(var on)'", ["a", "c"])])
def test_a_group_starts_its_nodes_when_its_condition_holds(tmp_path, condition, started):
    path = tmp_path / "group.launch.xml"
    node = "<node pkg='pisc_control' exec='estimator_node' name='{}'/>"
    path.write_text(f"<launch><arg name='on' default='false'/>{node.format('a')}<group "
                    f"{condition}>{node.format('b')}</group>{node.format('c')}</launch>")
    assert [n.name for n in read_launch(path)] == started
    if "var on" in condition:
        assert [n.name for n in read_launch(path, {"on": "TRUE"})] == ["a", "b", "c"]


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
    ("<group if='maybe'><node pkg='pisc_control' exec='estimator_node' name='e'/></group>",
     "<group> if: condition 'maybe' is 'maybe': expected true, false, 1 or 0"),
    ("<group if='1' unless='0'/>", "both 'if' and 'unless'"),
    ("<group scoped='false'/>", "attribute 'scoped' not supported"),
    ("<group if='false'><arg name='x'/></group>", "<group>: element <arg> not supported"),
    ("<group if='false'><node pkg='p' exec='e' name='e'><param from='/nonexistent.yaml'/>"
     "</node></group><node pkg='p' exec='e' name='f'/>", "/nonexistent.yaml does not exist"),
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

"""colcon builds the packages into the layout ros2 run expects."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = sorted(p.parent.name for p in (ROOT / "src").glob("*/package.xml"))


def _console_scripts(package: str) -> list[str]:
    """The console scripts ``src/PACKAGE/setup.py`` declares (read, not run)."""
    tree = ast.parse((ROOT / "src" / package / "setup.py").read_text())
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "setup":
            entry = next((k.value for k in call.keywords if k.arg == "entry_points"), None)
            if entry is None:
                return []
            return [line.partition("=")[0].strip()
                    for line in ast.literal_eval(entry)["console_scripts"]]
    raise AssertionError(f"{package}/setup.py calls no setup()")


EXECUTABLES = {package: _console_scripts(package) for package in PACKAGES}


def test_the_executables_are_read_from_every_setup_py():
    """The list the layout test walks is the packages' own: the graph's nodes and the
    commands users run are in it, each in one package."""
    every = [e for names in EXECUTABLES.values() for e in names]
    assert len(every) == len(set(every))
    assert {"plant_node", "driver_node", "estimator_node", "supervisor_node",
            "current_loop_node", "markers_node", "pisc_graph", "pisc_record", "pisc_bag",
            "pisc_robustness", "pisc_tune", "pisc_commission", "pisc_soak",
            "pisc_gym_learn"} <= set(every)
    assert "pisc_record" in EXECUTABLES["pisc_bag"] and "pisc_graph" in EXECUTABLES["pisc_bringup"]


@pytest.fixture(scope="module")
def install(tmp_path_factory) -> Path:
    colcon = str(Path(sys.executable).parent / "colcon")
    if not os.access(colcon, os.X_OK):
        colcon = shutil.which("colcon")
    assert colcon, "colcon is installed by the project's requirements"
    base = tmp_path_factory.mktemp("colcon")
    completed = subprocess.run(
        [colcon, "build", "--base-paths", str(ROOT / "src"), "--build-base",
         str(base / "build"), "--install-base", str(base / "install")],
        cwd=base, capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stdout + completed.stderr
    return base / "install"


@pytest.mark.parametrize("package", sorted(EXECUTABLES))
def test_every_node_executable_lands_where_ros2_run_looks(install, package):
    lib = install / package / "lib" / package
    for executable in EXECUTABLES[package]:
        assert os.access(lib / executable, os.X_OK), lib / executable
    share = install / package / "share"
    assert (share / package / "package.xml").is_file()
    assert (share / "ament_index" / "resource_index" / "packages" / package).is_file()


def test_installed_configuration_and_node_run_from_the_install(install, env_for_domain):
    config = install / "pisc_sim" / "share" / "pisc_sim" / "config"
    assert sorted(p.name for p in config.glob("*.yaml")) == [
        "default.yaml", "fixed-pump.yaml", "lyapunov-tuned.yaml", "thesis-calibrated-plant.yaml",
        "thesis.yaml"]
    robust = install / "pisc_robust" / "share" / "pisc_robust"
    distributions = robust / "distributions"
    assert {"thesis-rig.yaml", "thesis-calibrated.yaml"} <= {
        p.name for p in distributions.glob("*.yaml")}
    assert sorted(p.name for p in (distributions / "witnesses").glob("*.csv")) == [
        "thesis-rig-300-seed1-3s.csv", "thesis-rig-300-seed1-8s.csv"]
    assert (robust / "experiments" / "thesis-6.6.yaml").is_file()
    bringup = install / "pisc_bringup" / "share" / "pisc_bringup"
    launch = bringup / "launch"  # ros2 launch pisc_bringup sim.launch.xml
    assert sorted(p.name for p in launch.glob("*.launch.xml")) == [
        "rig.launch.xml", "sim.launch.xml"]
    assert (bringup / "config" / "fastdds.xml").read_bytes() == (
        ROOT / "src" / "pisc_bringup" / "config" / "fastdds.xml").read_bytes()
    env = dict(env_for_domain)
    env["PYTHONPATH"] = os.pathsep.join(
        str(p) for p in install.glob("*/lib/python3*/site-packages"))
    env["AMENT_PREFIX_PATH"] = os.pathsep.join(str(install / p) for p in EXECUTABLES)
    node = install / "pisc_control" / "lib" / "pisc_control" / "supervisor_node"
    completed = subprocess.run(
        [sys.executable, str(node), "--ros-args", "--params-file", str(config / "thesis.yaml"),
         "-p", "swing_up.k_e:=20.0"],  # (3.30) is the thesis's law, not the default's
        env=env, capture_output=True, text=True, timeout=60, cwd=install)
    assert completed.returncode == 2, completed.stderr
    assert "(3.29)" in completed.stderr

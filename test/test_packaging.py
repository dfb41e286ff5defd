"""colcon builds the packages into the layout ros2 run expects."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parent.parent
EXECUTABLES = {
    "pisc_plant": ["plant_node", "pisc_virtual_rig"],
    "pisc_control": ["estimator_node", "supervisor_node", "current_loop_node"],
    "pisc_bringup": ["pisc_graph", "pisc_record", "pisc_bag", "pisc_scene",
                     "pisc_integrators", "pisc_batch_bench", "pisc_robustness", "pisc_tune",
                     "markers_node", "pisc_parser_bench", "pisc_calibrate", "pisc_experiment"],
    "pisc_msgs_py": [],
    "pisc_driver": ["driver_node"],
    "pisc_model": [],
    "pisc_sim": [],
    "pisc_analysis": ["pisc_analysis"],
    "pisc_gym": ["pisc_gym_bench", "pisc_gym_catchable", "pisc_gym_learn"],
}


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
    bringup = install / "pisc_bringup" / "share" / "pisc_bringup"
    distributions = bringup / "distributions"
    assert {"thesis-rig.yaml", "thesis-calibrated.yaml"} <= {
        p.name for p in distributions.glob("*.yaml")}
    assert (bringup / "experiments" / "thesis-6.6.yaml").is_file()
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

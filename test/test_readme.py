"""The README stays true: it lists every parameter and topic, and CI runs its test command."""

from pathlib import Path

from pisc_bringup.configuration import SECTIONS
from pisc_driver.driver import DriverParams
from pisc_msgs_py.config import describe
from pisc_msgs_py.topics import GRAPH_TOPICS
from pisc_plant.plant_node import SimulationParams

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def test_every_parameter_is_listed():
    sections = {**SECTIONS, "simulation": SimulationParams, "driver": DriverParams}
    missing = [name for s, cls in sections.items() for name, *_ in describe(cls, s)
               if f"`{name}`" not in README]
    assert not missing


def test_every_topic_is_listed():
    assert not [t.name for t in GRAPH_TOPICS if f"`{t.name}`" not in README]


def test_ci_runs_exactly_the_readme_test_command():
    assert "    ./pisc run " in README and "    ./pisc test " in README
    commands = [line for line in (ROOT / ".ci" / "run").read_text().splitlines()
                if line and not line.startswith("#") and not line.startswith("set ")
                and not line.startswith("cd ")]
    assert commands == ["exec ./pisc test"]

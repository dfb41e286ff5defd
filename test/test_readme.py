"""The README stays a true front door: short, every topic listed, every link alive, CI
running its test command; docs/parameters.md is what the code's descriptors say."""

import re
from pathlib import Path

from pisc_bringup.param_docs import render
from pisc_msgs_py.topics import GRAPH_TOPICS

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
PARAMETERS = ROOT / "docs" / "parameters.md"


def test_readme_is_a_front_door():
    assert len(README.encode()) <= 12 * 1024  # at most about 12 KB
    assert "../shared" not in README  # nothing outside the repository


def test_every_topic_is_listed():
    assert not [t.name for t in GRAPH_TOPICS if f"`{t.name}`" not in README]


def test_every_link_of_the_readme_and_the_docs_exists():
    broken = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target:
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
    assert not broken


def test_parameters_doc_is_generated_from_the_descriptors():
    # regenerate with: .venv/bin/python -m pisc_bringup.param_docs_cli > docs/parameters.md
    assert PARAMETERS.read_text() == render()


def test_every_parameter_is_in_the_parameters_doc():
    from pisc_sim.configuration import SECTIONS
    from pisc_runs.markers import MarkersParams
    from pisc_driver.driver import DriverParams
    from pisc_msgs_py.config import describe
    from pisc_plant.plant_node import SimulationParams

    text = PARAMETERS.read_text()
    sections = {**SECTIONS, "simulation": SimulationParams, "driver": DriverParams,
                "markers": MarkersParams}
    missing = [name for s, cls in sections.items() for name, *_ in describe(cls, s)
               if f"| `{name}` |" not in text]
    assert not missing


def test_ci_runs_exactly_the_readme_test_command():
    assert "    ./pisc run " in README and "    ./pisc test " in README
    commands = [line for line in (ROOT / ".ci" / "run").read_text().splitlines()
                if line and not line.startswith("#") and not line.startswith("set ")
                and not line.startswith("cd ")]
    assert commands == ["exec ./pisc test"]

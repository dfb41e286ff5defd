"""The packages' boundaries show the architecture: every package declares in package.xml
what its code imports and says in its README what it holds and may import; the packages
stand in layers, each importing only layers below it (the controllers and the driver do
not depend on the simulator, the bag library on nothing but the shared vocabulary, the
analysis on nothing of the graph); a package's tests import only what the package may;
no package holds more than about a quarter of the code; and no module imports itself back
through another.

Imports are read from the source with ``ast`` (function-level imports included: a lazy
import is still a dependency); modules of the standard library are left out.
"""

from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / "package.xml").is_file())

#: Python module -> the package.xml key that provides it. ROS packages keep their names;
#: Python libraries take the rosdep/Debian key (python3-<name>).
KEYS = {
    "numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
    "control": "python3-control", "serial": "python3-serial", "numba": "python3-numba",
    "matplotlib": "python3-matplotlib", "sympy": "python3-sympy", "mcap": "python3-mcap",
    "rosbags": "python3-rosbags", "optuna": "python3-optuna", "dask": "python3-dask",
    "distributed": "python3-distributed", "tqdm": "python3-tqdm", "PIL": "python3-pil",
    "imageio_ffmpeg": "python3-imageio-ffmpeg", "llvmlite": "python3-llvmlite",
    "sqlalchemy": "python3-sqlalchemy", "gymnasium": "python3-gymnasium",
    "cmaes": "python3-cmaes", "foxglove": "python3-foxglove-sdk", "websockets": "python3-websockets",
    "google": "python3-protobuf",
}

#: Dependencies the architecture forbids: (package, package it must not use, why).
FORBIDDEN = [
    ("pisc_control", "pisc_plant", "the controllers run on a rig computer without the simulator"),
    ("pisc_driver", "pisc_plant", "the driver runs on a rig computer without the simulator"),
    ("pisc_model", "pisc_plant", "the model is what the simulator builds on"),
    ("pisc_analysis", "pisc_bringup", "the analysis needs no launch package"),
    ("pisc_gym", "rclpy", "the environments run where learning libraries do, without ROS"),
]


#: The packages in layers: a package imports only packages of the layers below its own.
LAYERS = [
    ["pisc_msgs_py"],
    ["pisc_model"],
    ["pisc_plant", "pisc_control", "pisc_driver"],
    ["pisc_sim", "pisc_bag"],
    ["pisc_analysis", "pisc_runs"],
    ["pisc_robust"],
    ["pisc_bringup", "pisc_gym"],
    ["pisc_bench"],
]
LAYER = {package: n for n, layer in enumerate(LAYERS) for package in layer}
#: Packages that may use only the ones named, whatever their layer.
ONLY = {"pisc_bag": {"pisc_msgs_py"}}


def _imports(path: Path) -> set[str]:
    """Absolute modules a file imports, anywhere in it."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def _modules(package: str) -> dict[str, Path]:
    root = SRC / package
    return {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p
            for p in (root / package).rglob("*.py")}


def _declared(package: str) -> set[str]:
    root = ET.parse(SRC / package / "package.xml").getroot()
    return {e.text.strip() for e in root if e.tag in ("depend", "exec_depend") and e.text}


def _needed(package: str) -> dict[str, set[str]]:
    """package.xml key -> the modules of ``package`` that need it."""
    need: dict[str, set[str]] = {}
    for module, path in _modules(package).items():
        for name in _imports(path):
            top = name.split(".")[0]
            if top in sys.stdlib_module_names or top == package or top == "__future__":
                continue
            key = KEYS.get(top, top)
            need.setdefault(key, set()).add(module)
    return need


@pytest.mark.parametrize("package", PACKAGES)
def test_package_xml_declares_what_the_code_imports(package):
    declared = _declared(package)
    missing = {key: sorted(mods) for key, mods in _needed(package).items()
               if key not in declared}
    assert not missing, f"{package}/package.xml lacks: {missing}"


@pytest.mark.parametrize("package, other, why", FORBIDDEN)
def test_forbidden_dependencies(package, other, why):
    users = sorted(_needed(package).get(other, ()))
    assert other not in _declared(package) and not users, f"{package} uses {other} ({users}): " + why


def test_no_import_circle():
    """No module reaches itself through the modules it imports (Tarjan's strongly
    connected components over every pisc module)."""
    modules = {m: p for package in PACKAGES for m, p in _modules(package).items()}
    edges = {m: sorted({i for name in _imports(p) for i in (name, name.rsplit(".", 1)[0])
                        if i in modules and i != m})
             for m, p in modules.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            # a package's __init__ importing its own modules is not a circle
            if len([c for c in component if "." in c]) > 1:
                circles.append(sorted(component))

    sys.setrecursionlimit(10000)
    for v in sorted(modules):
        if v not in index:
            visit(v)
    assert not circles, circles


def test_every_package_stands_in_a_layer():
    assert sorted(LAYER) == PACKAGES


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_imports_only_the_layers_below_it(package):
    used = {key for key in _needed(package) if key in LAYER} | {
        key for key in _declared(package) if key in LAYER}
    upward = sorted(other for other in used if LAYER[other] >= LAYER[package])
    assert not upward, (f"{package} (layer {LAYER[package]}) uses {upward} of its own layer "
                        "or above")
    if package in ONLY:
        assert used <= ONLY[package], f"{package} may use only {sorted(ONLY[package])}: {sorted(used)}"


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_s_tests_import_only_what_it_may(package):
    allowed = {key for key in _declared(package) if key in LAYER} | {package}
    wrong = {}
    for path in sorted((SRC / package / "test").glob("*.py")):
        used = {name.split(".")[0] for name in _imports(path)} & set(LAYER)
        if used - allowed:
            wrong[path.name] = sorted(used - allowed)
    assert not wrong, (f"tests of {package} import packages it may not (move them to test/ "
                       f"or to the package they test): {wrong}")


@pytest.mark.parametrize("package", PACKAGES)
def test_a_package_s_readme_says_what_it_holds_and_may_import(package):
    readme = SRC / package / "README.md"
    assert readme.is_file(), f"{package} has no README.md"
    text = readme.read_text()
    assert text.startswith(f"# {package}\n"), f"{readme}: the first line names the package"
    assert "may import" in text, f"{readme} does not say what the package may import"
    unnamed = sorted(key for key in _declared(package) if key in LAYER and key not in text)
    assert not unnamed, f"{readme} does not name the packages it imports: {unnamed}"


def test_no_package_holds_more_than_about_a_quarter_of_the_code():
    lines = {package: sum(len(path.read_text().splitlines())
                          for path in _modules(package).values()) for package in PACKAGES}
    total = sum(lines.values())
    assert total > 20000, lines  # the whole of src/ was counted
    big = {package: f"{n / total:.0%}" for package, n in lines.items() if n > 0.27 * total}
    assert not big, big


def test_no_library_file_over_600_lines():
    long = {str(path.relative_to(SRC)): n for package in PACKAGES
            for path in _modules(package).values()
            if (n := len(path.read_text().splitlines())) > 600}
    assert not long, long


# -- the command-line convention ---------------------------------------------------------

#: Modules that may define a top-level ``main`` without being a command module (``*_cli``,
#: ``*_node``) or ``__main__.py``, each with its reason. Empty: every entry point is one.
MAIN_ALLOWED: dict[str, str] = {}


def _console_scripts(package: str) -> dict[str, str]:
    """The console scripts of a package's setup.py: name -> ``module:function``."""
    scripts: dict[str, str] = {}
    tree = ast.parse((SRC / package / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values, strict=True):
                if (isinstance(key, ast.Constant) and key.value == "console_scripts"
                        and isinstance(value, (ast.List, ast.Tuple))):
                    for item in value.elts:
                        name, _, target = str(item.value).partition("=")
                        scripts[name.strip()] = target.strip()
    return scripts


def _defines_main(path: Path) -> bool:
    return any(isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == "main"
               for node in ast.parse(path.read_text(), str(path)).body)


def _kind(module: str) -> str:
    """``cli``, ``node``, ``cmd``, ``main`` (a ``__main__``) or ``library``."""
    leaf = module.rsplit(".", 1)[-1]
    for suffix in ("cli", "node", "cmd"):
        if leaf.endswith(f"_{suffix}"):
            return suffix
    return "main" if leaf == "__main__" else "library"


@pytest.mark.parametrize("package", PACKAGES)
def test_every_console_script_is_the_main_of_a_cli_or_node_module(package):
    """A command is ``<pkg>.<name>_cli:main``, a node executable ``<pkg>.<name>_node:main``:
    a reader finds every entry point by its module's name."""
    modules = _modules(package)
    wrong = {}
    for name, target in _console_scripts(package).items():
        module, _, function = target.partition(":")
        if _kind(module) not in ("cli", "node") or function != "main":
            wrong[name] = f"{target}: not the main of a *_cli or *_node module"
        elif module not in modules:
            wrong[name] = f"{target}: no such module in {package}"
        elif not _defines_main(modules[module]):
            wrong[name] = f"{target}: the module defines no main"
    assert not wrong, wrong


@pytest.mark.parametrize("package", PACKAGES)
def test_only_command_modules_define_main(package):
    """A library module defines no ``main``: what runs as a command is a ``*_cli``,
    ``*_node`` or ``__main__`` module (:data:`MAIN_ALLOWED` lists any other, with why)."""
    stray = sorted(module for module, path in _modules(package).items()
                   if _kind(module) == "library" and _defines_main(path)
                   and module not in MAIN_ALLOWED)
    assert not stray, f"move each main into a *_cli module (or name why in MAIN_ALLOWED): {stray}"


def test_no_module_imports_a_command_module():
    """Nothing imports a ``*_cli`` module, and only a ``*_cli`` module (a dispatcher of
    subcommands: ``pisc_bag``'s live in the packages whose code they run) imports a
    ``*_cmd`` module: a command's code is reached through the command, and what two
    commands share lives in a library module."""
    wrong = {}
    for package in PACKAGES:
        for module, path in _modules(package).items():
            for name in _imports(path):
                target = name if _kind(name) in ("cli", "cmd") else name.rsplit(".", 1)[0]
                kind = _kind(target)
                if kind == "cli" or (kind == "cmd" and _kind(module) != "cli"):
                    wrong.setdefault(module, set()).add(target)
    assert not wrong, {m: sorted(t) for m, t in wrong.items()}


#: Modules other than nodes (``*_node``) and commands (``*_cli``) that may import rclpy,
#: with why; every algorithm is a pure core without it.
RCLPY_ALLOWED = {
    "pisc_bringup": "the graph runner spins a watcher node and the nodes of its own process",
    "pisc_runs.play": "publishes a bag's messages on their topics",
}


def test_rclpy_is_imported_only_by_nodes_commands_and_the_graph_runner():
    users = sorted(module for package in PACKAGES for module, path in _modules(package).items()
                   if any(name.split(".")[0] == "rclpy" for name in _imports(path)))
    assert "pisc_bag.recorder_node" in users  # the reading sees the nodes' imports
    stray = [module for module in users if _kind(module) not in ("node", "cli")
             and module not in RCLPY_ALLOWED and module.split(".")[0] not in RCLPY_ALLOWED]
    assert not stray, f"import rclpy only in a *_node or *_cli module: {stray}"

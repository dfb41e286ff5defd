"""docs/ stays a set of pages a user can read: every relative link and anchor resolves,
no page over about 20 KB, the user pages under about 200 KB in all (dated measurement
logs apart, in docs/measurements/), behaviour named instead of issue numbers, every
console script and every node documented, each node page naming the topics its node
uses and linking the parameter sections it reads. Every list is read from the files."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MEASUREMENTS = DOCS / "measurements"
PAGE_LIMIT = 20 * 1024
USER_DOCS_LIMIT = 200 * 1024
#: Generated from the parameter descriptors (pisc_bringup.param_docs): one table per
#: section, as long as the code's parameters make it.
GENERATED = {DOCS / "parameters.md"}
IMAGES = {".png", ".gif", ".jpg", ".jpeg", ".svg", ".mp4"}

LINK = re.compile(r"\]\(([^)\s]*)\)")
ISSUE = re.compile(r"\b[Ii]ssues? \d+|(?<![\w&/])#\d+\b")


def _pages() -> list[Path]:
    pages = sorted(DOCS.rglob("*.md"))
    assert len(pages) > 10, pages  # docs/ is where this test looks
    return pages


def _user_pages() -> list[Path]:
    return [p for p in _pages() if MEASUREMENTS not in p.parents]


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but - and _ dropped,
    spaces to -."""
    text = re.sub(r"`|\*\*", "", heading.strip().lstrip("#").strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    in_code = False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            in_code = not in_code
        if in_code or not re.match(r"#{1,6} ", line):
            continue
        slug = _slug(line)
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return [t for t in LINK.findall(text) if "://" not in t and not t.startswith("mailto:")]


def test_every_relative_link_and_anchor_resolves():
    broken, checked = [], 0
    for page in [ROOT / "README.md", ROOT / "bags" / "README.md", *_pages()]:
        for target in _links(page):
            path, _, anchor = target.partition("#")
            dest = (page.parent / path) if path else page
            checked += 1
            if not dest.exists():
                broken.append(f"{page.relative_to(ROOT)} -> {target}")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{page.relative_to(ROOT)} -> {target} (no such heading)")
    assert checked > 100, checked
    assert not broken, "\n".join(broken)


def test_the_docs_files_the_code_names_exist():
    named = set()
    for source in [*ROOT.glob("src/*/*/*.py"), *ROOT.glob("src/*/test/*.py"),
                   *ROOT.glob("test/*.py")]:
        named |= {(source, m) for m in re.findall(r"docs/[\w./-]+\.md", source.read_text())}
    assert named
    assert not [f"{s.relative_to(ROOT)}: {m}" for s, m in named if not (ROOT / m).exists()]


def test_no_page_over_about_20_kb():
    big = {p.relative_to(ROOT).as_posix(): p.stat().st_size for p in _pages()
           if p.stat().st_size > PAGE_LIMIT and p not in GENERATED}
    assert not big


def test_user_docs_under_about_200_kb():
    # the written pages: images, dated measurement logs and the generated parameter
    # tables (as long as the code's parameters make them) apart
    files = [p for p in DOCS.rglob("*") if p.is_file() and MEASUREMENTS not in p.parents
             and p.suffix.lower() not in IMAGES and p not in GENERATED]
    total = sum(p.stat().st_size for p in files)
    assert len(files) > 10 and 0 < total <= USER_DOCS_LIMIT, total


def test_user_docs_name_behaviour_not_issue_numbers():
    found = [f"{p.relative_to(ROOT)}: {m.group(0)}" for p in [ROOT / "README.md",
             *_user_pages()] for m in ISSUE.finditer(p.read_text())]
    assert not found, found


def _console_scripts() -> dict[str, str]:
    """name -> 'module:function' of every console script of every src/*/setup.py."""
    scripts = {}
    for setup in sorted(ROOT.glob("src/*/setup.py")):
        for call in ast.walk(ast.parse(setup.read_text())):
            if isinstance(call, ast.Dict):
                for key, value in zip(call.keys, call.values):
                    if isinstance(key, ast.Constant) and key.value == "console_scripts":
                        for entry in ast.literal_eval(value):
                            name, target = (s.strip() for s in entry.split("="))
                            scripts[name] = target
    return scripts


def test_every_console_script_is_in_the_docs():
    scripts = _console_scripts()
    assert len(scripts) >= len(list(ROOT.glob("src/*/setup.py")))
    text = "\n".join(p.read_text() for p in [ROOT / "README.md", *_user_pages()])
    assert not [s for s in scripts if not re.search(rf"\b{re.escape(s)}\b", text)]


def _node_modules() -> list[Path]:
    """Every node executable's module (a console script whose module is a *_node)."""
    modules = [ROOT / "src" / t.split(".")[0] / (t.split(":")[0].replace(".", "/") + ".py")
               for t in _console_scripts().values() if t.split(":")[0].endswith("_node")]
    assert len(modules) >= 6, modules
    return modules


def _node_page(module: Path) -> Path:
    return DOCS / "nodes" / (module.stem.removesuffix("_node").replace("_", "-") + ".md")


def test_every_node_has_a_reference_page_naming_its_topics():
    from pisc_msgs_py import topics

    by_constant = {name: value.name for name, value in vars(topics).items()
                   if isinstance(value, topics.Topic)}
    missing = []
    for module in _node_modules():
        page = _node_page(module)
        if not page.exists():
            missing.append(f"{module.name}: no {page.relative_to(ROOT)}")
            continue
        text = page.read_text()
        used = set(re.findall(r"\b(?:publisher|subscription)\(\s*([A-Z_]+)\b",
                              module.read_text()))
        for constant in used & by_constant.keys():
            if f"`{by_constant[constant]}`" not in text:
                missing.append(f"{page.name}: {by_constant[constant]}")
    assert not missing, missing


def test_node_pages_link_the_parameter_sections_their_node_reads():
    parameters = (DOCS / "parameters.md").read_text()
    readers = re.findall(r"^## `(\w+)` \(read by: ([^)]*)\)$", parameters, flags=re.M)
    assert len(readers) > 10
    anchors = _anchors(DOCS / "parameters.md")
    missing = []
    for section, nodes in readers:
        anchor = next(a for a in anchors if a.startswith(f"{section}-read-by"))
        for node in nodes.split(", "):
            page = DOCS / "nodes" / (node.replace(" ", "-") + ".md")
            if f"parameters.md#{anchor}" not in page.read_text():
                missing.append(f"{page.name}: {section}")
    assert not missing, missing

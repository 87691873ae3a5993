"""The docs match the tree: every repository path they name exists, every module of the package is
named in docs/ARCHITECTURE.md, and docs/cli.md names exactly the command line's options.

A path is checked where the docs name it: in backquotes (`tools/bench/nerf_train.py`, also inside a
command in backquotes), in a fenced code block when it starts at the repository's root, and as the
target of a Markdown link. The notebook (docs/benchmarks-history.md) is left out: it keeps the paths
as they were when each figure was measured.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from fixtures import REPO

PACKAGE = REPO / "blender_nerf_deform"
DOCS = [REPO / "README.md", REPO / "BENCHMARKS.md"] + sorted(
    p for p in (REPO / "docs").glob("*.md") if p.name != "benchmarks-history.md"
)

# Where a backquoted path may start: the repository's root, the package, its halves, the tests,
# the tools. ARCHITECTURE names modules relative to their half (`engine/service/ops.py`,
# `data/paths.py`), the test pages relative to addon_tests/ (`fixtures/`).
BASES = (REPO, PACKAGE, PACKAGE / "engine", PACKAGE / "addon", REPO / "addon_tests", REPO / "tools")
# First path segments that name something of this repository (outputs such as demo_out/, dist/,
# build/, runs/ and placeholders such as DEMO_DIR/ are not checked).
ROOTS = ("blender_nerf_deform", "addon_tests", "tools", "docs", ".ci")
SEGMENTS = set(ROOTS) | {
    "engine",
    "addon",
    "fixtures",
    "smoke",
    "bench",
    *(p.name for p in (PACKAGE / "engine").iterdir() if p.is_dir() and p.name != "__pycache__"),
    *(p.name for p in (PACKAGE / "addon").iterdir() if p.is_dir() and p.name != "__pycache__"),
}
TOP_FILES = {
    "README.md",
    "BENCHMARKS.md",
    "RELIABILITY.md",
    "Makefile",
    "requirements.txt",
    "pyproject.toml",
    "pytest.ini",
    "blender_manifest.toml",
}
# Files of other projects the docs name in backquotes.
EXTERNAL = {"blender_ext.py"}

FENCE = re.compile(r"^[ \t]*```.*?^[ \t]*```", re.S | re.M)  # also fences indented in a list item
INLINE = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _candidates(token: str) -> bool:
    """Whether a word names a repository path the docs promise (and so must exist)."""
    if any(c in token for c in "<>*{}$~…") or "..." in token or token.startswith(("http", "../", "-")):
        return False
    if token in TOP_FILES:
        return True
    first = token.split("/", 1)[0]
    if "/" in token:
        return first in SEGMENTS
    return token.endswith(".py") and token not in EXTERNAL


def _exists(token: str) -> bool:
    path = token.rstrip("/")
    if "/" not in path and path.endswith(".py"):  # a bare module name: somewhere in the project
        return any(
            "__pycache__" not in p.parts and ".venv" not in p.parts
            for base in (PACKAGE, REPO / "tools", REPO / "addon_tests")
            for p in base.rglob(path)
        )
    return any((base / path).exists() for base in BASES)


def _words(span: str):
    for word in span.split():
        word = word.strip("\"'(),;")
        word = word.rstrip(":.")
        if word:
            yield word


def missing_paths(text: str, where: Path) -> list[str]:
    """The paths a Markdown page names that do not exist (`where` is the page, for relative links)."""
    problems = []
    fenced = FENCE.findall(text)
    for block in fenced:
        for word in _words(block):
            if word.split("/", 1)[0] in ROOTS and _candidates(word) and not _exists(word):
                problems.append(f"{where.name}: code block names {word}, which does not exist")
    prose = FENCE.sub("", text)
    for span in INLINE.findall(prose):
        for word in _words(span):
            if _candidates(word) and not _exists(word):
                problems.append(f"{where.name}: `{word}` does not exist")
    for target in LINK.findall(prose):
        target = target.split("#", 1)[0]
        if not target or target.startswith(("http://", "https://", "mailto:")):
            continue
        if not (where.parent / target).exists():
            problems.append(f"{where.name}: link to {target}, which does not exist")
    return problems


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_path_a_page_names_exists(page):
    assert missing_paths(page.read_text(encoding="utf-8"), page) == []


def test_the_check_catches_made_up_paths():
    page = REPO / "docs" / "made_up.md"
    text = (
        "Run `tools/bench/no_such_bench.py --help`, read `engine/service/no_such_module.py` and\n"
        "`worker_client.py`, see [the page](no_such_page.md).\n\n"
        "```sh\n.venv/bin/python tools/no_such_tool.py --out demo_out/x\n```\n"
        "1. a step:\n\n   ```sh\n   .venv/bin/python tools/indented_missing.py\n   ```\n\n"
        "These exist: `tools/bench/nerf_train.py`, `addon/worker/client.py`, `fixtures/`, "
        "[cli](cli.md), `demo_out/frames/`, `engine/cli/<command>.py`.\n"
    )
    problems = missing_paths(text, page)
    assert len(problems) == 6, problems
    made_up = ("no_such_bench.py", "no_such_module.py", "worker_client.py", "no_such_page.md", "no_such_tool.py")
    for name in made_up + ("indented_missing.py",):
        assert any(name in p for p in problems), (name, problems)


def test_architecture_names_every_module():
    """A module (or a tool) added without a word in ARCHITECTURE fails here: the map stays complete."""
    text = (REPO / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    named = set(re.findall(r"([\w]+\.py)\b", text))
    modules = sorted(
        p.relative_to(PACKAGE).as_posix()
        for p in PACKAGE.rglob("*.py")
        if "__pycache__" not in p.parts and p.name != "__init__.py"
    )
    assert modules, "no modules found"
    assert [m for m in modules if m.rsplit("/", 1)[-1] not in named] == []
    tools = sorted(p.name for p in (REPO / "tools").glob("*.py") if p.name != "__init__.py")
    assert [t for t in tools if t not in named] == [], "tools/ scripts missing from ARCHITECTURE section 6"


def _commands():
    from blender_nerf_deform.engine.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    return {
        name: {s for a in p._actions for s in a.option_strings if s.startswith("--")} - {"--help"}
        for name, p in sub.choices.items()
    }


# Options of other programs that the command pages show beside the engine's
# (`blender -b --python tools/vdb_from_npz.py -- DIR VDB_DIR --scale S`).
OTHER_OPTIONS = {"--help", "--python", "--python-expr", "--scale"}


def _sections(text: str) -> dict[str, str]:
    parts = re.split(r"^## ", text, flags=re.M)
    return {part.split("\n", 1)[0].strip(): part for part in parts[1:]}


def test_cli_reference_matches_the_parser():
    """docs/cli.md has a section per command naming every option it has, and none it has not."""
    commands = _commands()
    assert {"train", "eval", "render", "bake-volume", "extract", "cage", "prepare", "compile"} <= set(commands)
    sections = _sections((REPO / "docs" / "cli.md").read_text(encoding="utf-8"))
    shared = sections.get("Environment", "") + (REPO / "docs" / "cli.md").read_text(encoding="utf-8").split("## ")[0]
    problems = []
    for name, options in commands.items():
        section = sections.get(name)
        if section is None:
            problems.append(f"docs/cli.md has no section '## {name}'")
            continue
        for option in sorted(options):
            if not re.search(re.escape(option) + r"(?![\w-])", section + shared):
                problems.append(f"{name} {option} is not in docs/cli.md")
        for option in sorted(set(re.findall(r"--[a-z][a-z0-9-]*", section)) - options - OTHER_OPTIONS):
            problems.append(f"docs/cli.md names {name} {option}, which {name} does not have")
    assert problems == []

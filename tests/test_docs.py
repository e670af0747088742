"""The user docs (README.md, docs/*.md) stay docs: what is there and how to use it.

- Every repository path a doc names exists, so a user who follows it finds the file.
- README.md links every page in docs/, so no page is out of reach.
- No doc carries a lab notebook's stamps in its own prose: "this machine" (whose?), a
  commit hash, an issue number. A figure says what it needs ("a two-core PC", "the robot
  PC"); history goes to CHANGELOG.md. The bench's generated report (docs/benchmarks.md)
  and the blocks `deepxpalm bench --update-docs` writes into other pages
  (``<!-- NAME begin -->`` ... ``<!-- NAME end -->``, harness/bench/doc_block.py) keep the
  stamps of the run that made them.

Text only: no process, no import of the project.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: the repository's own top-level folders: a doc's path that starts with one is a repo path
REPO_FOLDERS = (
    "common",
    "robot_side",
    "operator_side",
    "router_side",
    "deploy",
    "harness",
    "docs",
    "tests",
    "scripts",
    ".ci",
)
#: top-level files a doc may name bare (a name of this kind that is not there is a stale one)
REPO_FILES = (
    "Makefile",
    "pyproject.toml",
    "README.md",
    "CHANGELOG.md",
    "setup.py",
    "setup.cfg",
    "requirements.txt",
    "tox.ini",
)
#: the packages whose dotted module names a doc gives (``python -m robot_side.lab``)
PACKAGES = ("common", "robot_side", "operator_side", "router_side", "deploy", "harness")

#: files a doc tells the reader to write: examples, not paths that must exist
EXAMPLE_FILES = {
    "robot_side/gripper/hande_tcp.py": "docs/architecture.md, 'Adding a device kind'",
    "harness/bench/codec.py": "docs/architecture.md, a bench section of your own",
}
#: a doc written whole by `deepxpalm bench` (harness/bench/report.py)
GENERATED_DOCS = {"docs/benchmarks.md"}


def either(names: tuple[str, ...]) -> str:
    """A regex alternation of the names, each taken literally."""
    return "|".join(map(re.escape, names))


#: a repo path inside prose, a code span or a link: from a repo folder to the next
#: space, quote, bracket or comma; `::test` and `#anchor` are cut off below
PATH = re.compile(r"(?<![\w./~$-])((?:" + either(REPO_FOLDERS) + r")/[^\s`'\"()\[\]<>,;|]*)")
TOP_FILE = re.compile(r"(?<![\w./-])(" + either(REPO_FILES) + r")(?![\w/-])")
LINK = re.compile(r"\]\(([^)\s]+)\)")
MODULE = re.compile(r"(?<![\w./-])((?:" + either(PACKAGES) + r")(?:\.[A-Za-z_]\w*)+)")
#: globs and placeholders stand for many paths (or one the reader picks)
PLACEHOLDER = re.compile(r"[*?{}<>]|\bNAME\b|\.\.\.|\bX\b")

BLOCK_BEGIN = re.compile(r"<!--.*\bbegin\b.*-->")
BLOCK_END = re.compile(r"<!--.*\bend\b.*-->")
THIS_MACHINE = re.compile(r"\bthis machine\b", re.IGNORECASE)
#: an inline code span: what the product prints or a command, quoted as it is
CODE_SPAN = re.compile(r"`[^`]*`")
HEX = r"(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}"
COMMIT = re.compile(
    rf"\bcommits?\b\W+(?:[\w'-]+\W+){{0,3}}?({HEX})\b|\b({HEX})\b\W+(?:[\w'-]+\W+){{0,3}}?commits?\b",
    re.IGNORECASE,
)
ISSUE = re.compile(r"\b(?:issues?|PR|pull request)\s+#?\d+\b|(?<![\w&/])#\d+\b", re.IGNORECASE)


def rel(doc: Path) -> str:
    return doc.relative_to(ROOT).as_posix()


def lines(doc: Path) -> Iterator[tuple[int, str]]:
    yield from enumerate(doc.read_text(encoding="utf-8").splitlines(), 1)


def prose_lines(doc: Path) -> Iterator[tuple[int, str]]:
    """The doc's lines outside the blocks the bench writes (none of a generated doc)."""
    if rel(doc) in GENERATED_DOCS:
        return
    inside = False
    for n, line in lines(doc):
        if BLOCK_BEGIN.search(line):
            inside = True
        elif BLOCK_END.search(line):
            inside = False
        elif not inside:
            yield n, line


def named_paths(doc: Path) -> Iterator[tuple[int, str, Path]]:
    """(line, as written, where it points) for every repo path and relative link of a doc."""
    for n, line in lines(doc):
        for m in PATH.finditer(line):
            written = m.group(1).split("::")[0].split("#")[0].rstrip(".,:;!?")
            yield n, written, ROOT / written
        for m in TOP_FILE.finditer(line):
            yield n, m.group(1), ROOT / m.group(1)
        for m in LINK.finditer(line):
            target = m.group(1).split("#")[0]
            if not target or re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("/"):
                continue  # an anchor on the same page, a URL, an absolute (runtime) path
            yield n, target, (doc.parent / target).resolve()


def test_every_repository_path_a_doc_names_exists() -> None:
    missing = []
    for doc in DOCS:
        for n, written, path in named_paths(doc):
            if PLACEHOLDER.search(written) or written in EXAMPLE_FILES:
                continue
            if not path.exists():
                missing.append(f"{rel(doc)}:{n}: {written} (no such file or folder)")
    assert not missing, "docs name paths that are not in the repository:\n" + "\n".join(
        sorted(set(missing))
    )


def module_exists(name: str) -> bool:
    """``a.b.c.attr``: some prefix of at least two names is a module or package of the repo."""
    parts = name.split(".")
    for end in range(len(parts), 1, -1):
        base = ROOT.joinpath(*parts[:end])
        if base.with_suffix(".py").is_file() or base.is_dir():
            return True
    return False


def test_every_module_a_doc_names_exists() -> None:
    """``python -m robot_side.jit_warm``, ``robot_side.arm.base.SAFETY_THREAD_NICE``: the
    module is where the doc says (a module moved to a subpackage leaves such names behind)."""
    missing = []
    for doc in DOCS:
        for n, line in lines(doc):
            for m in MODULE.finditer(line):
                name = m.group(1)
                if name.endswith((".py", ".md", ".toml", ".json")):
                    continue  # a file name, checked as a path
                if not module_exists(name):
                    missing.append(f"{rel(doc)}:{n}: {name} (no such module in the repository)")
    assert not missing, "docs name modules that are not in the repository:\n" + "\n".join(missing)


def test_the_readme_links_every_page_in_docs() -> None:
    readme = ROOT / "README.md"
    linked = {path for _, _, path in named_paths(readme) if path.suffix == ".md"}
    unlinked = [
        rel(page) for page in sorted((ROOT / "docs").glob("*.md")) if page.resolve() not in linked
    ]
    assert not unlinked, (
        "README.md, 'Documentation', has no link to: "
        + ", ".join(unlinked)
        + " (add a line: - [docs/PAGE.md](docs/PAGE.md): what it is for)"
    )


@pytest.mark.parametrize("doc", DOCS, ids=rel)
def test_a_doc_carries_no_lab_notebook_stamps(doc: Path) -> None:
    found = []
    for n, line in prose_lines(doc):
        if m := THIS_MACHINE.search(CODE_SPAN.sub("", line)):  # a span quotes the product
            found.append(
                f"{rel(doc)}:{n}: '{m.group(0)}': say which ('a two-core PC', 'the robot PC')"
            )
        if m := COMMIT.search(line):
            found.append(
                f"{rel(doc)}:{n}: commit {m.group(1) or m.group(2)}: the history goes to "
                "CHANGELOG.md"
            )
        if m := ISSUE.search(line):
            found.append(f"{rel(doc)}:{n}: '{m.group(0)}': say what it asked, not its number")
    assert not found, "\n".join(found)


def test_the_generated_blocks_are_closed() -> None:
    """An unclosed block would hide the rest of its page from the check above."""
    open_blocks = []
    for doc in DOCS:
        begun = None
        for n, line in lines(doc):
            if BLOCK_BEGIN.search(line):
                if begun is not None:
                    open_blocks.append(f"{rel(doc)}:{begun}: a block begins inside another")
                begun = n
            elif BLOCK_END.search(line):
                begun = None
        if begun is not None:
            open_blocks.append(f"{rel(doc)}:{begun}: a generated block never ends")
    assert not open_blocks, "\n".join(open_blocks)

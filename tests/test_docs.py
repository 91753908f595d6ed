"""Every command and code block of the newcomer's docs runs.

A doctest-like runner over README.md, docs/umrf-guide.md and docs/python-api.md: each fenced
``sh`` block runs with bash (``set -e``: every command of it must succeed) from the repository's
root, each ``python`` block as a script of its own (``json`` blocks are excerpts). A block
that needs hardware, a long time, the network or a package outside ``[dev]`` says so just
above its fence::

    <!-- docs-test: skip needs a CAN interface -->

and is reported as skipped with that reason (``pytest -ra`` lists them). ``<!-- docs-test:
exit N -->`` expects exit status N instead of 0; ``<!-- docs-test: traceback -->`` allows
the traceback a block shows on purpose. The commands' ``.venv/bin/temoto`` and
``.venv/bin/python`` run this interpreter (a bare ``temoto``, not on the PATH of a fresh
clone, fails), so the test checks the tree
under test, not an installation. A command must leave nothing behind in the repository.
"""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "docs/umrf-guide.md", "docs/python-api.md")
MARK = re.compile(r"<!--\s*docs-test:\s*(skip|exit|traceback)\s*(.*?)\s*-->")
ASSIGNMENT = re.compile(r"^[A-Z_][A-Z0-9_]*=\S+$")
FENCE = re.compile(r"^```(\w*)\s*$")
BOUND = 120.0  # seconds a block may take on a loaded machine


class Block(NamedTuple):
    doc: str
    line: int  # of the opening fence, counted from 1
    lang: str
    text: str
    skip: str  # the reason, or ""
    exit: int
    traceback: bool  # the block shows one on purpose (`temoto -v run`: an action's)


def blocks(doc: str) -> list[Block]:
    """The fenced blocks of a document, with the marks above them."""
    lines = (ROOT / doc).read_text(encoding="utf-8").splitlines()
    found = []
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m is None:
            i += 1
            continue
        start, lang = i, m.group(1)
        i += 1
        body = []
        while i < len(lines) and not lines[i].startswith("```"):
            body.append(lines[i])
            i += 1
        i += 1
        skip, code, shows = "", 0, False
        j = start - 1
        while j >= 0 and (not lines[j].strip() or MARK.search(lines[j])):
            mark = MARK.search(lines[j])
            if mark is not None:
                if mark.group(1) == "skip":
                    skip = mark.group(2) or "marked"
                elif mark.group(1) == "traceback":
                    shows = True
                else:
                    code = int(mark.group(2))
            j -= 1
        found.append(Block(doc, start + 1, lang, "\n".join(body) + "\n", skip, code, shows))
    return found


ALL = [b for doc in DOCS for b in blocks(doc) if b.lang in ("sh", "python")]


def _shell(text: str) -> str:
    """A block's commands, with the venv's programs replaced by this interpreter."""
    py = shlex.quote(sys.executable)
    RUN = {"temoto": f"{py} -m temoto", "python": py}  # noqa: N806
    out = []
    for line in text.splitlines():
        line = re.sub(r"(?<![\w/.])\.venv/bin/(temoto|python)\b", lambda m: RUN[m.group(1)], line)
        out.append(line)
    return "set -e\n" + "\n".join(out) + "\n"


def _top_level() -> set[str]:
    return {p.name for p in ROOT.iterdir() if p.name not in ("__pycache__",)}


@pytest.mark.slow
@pytest.mark.timeout(2 * BOUND)
@pytest.mark.parametrize("block", ALL, ids=[f"{b.doc}:{b.line}" for b in ALL])
def test_a_doc_block_runs(block: Block) -> None:
    if block.skip:
        pytest.skip(f"{block.doc}:{block.line}: {block.skip}")
    before = _top_level()
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    if block.lang == "sh":
        # the shell variables set by the document's earlier blocks (E=examples/umrf-guide)
        earlier = [b for b in ALL if b.doc == block.doc and b.lang == "sh" and b.line < block.line]
        assigned = [line for b in earlier for line in b.text.splitlines() if ASSIGNMENT.match(line)]
        argv = ["bash", "-c", "\n".join(assigned) + "\n" + _shell(block.text)]
    else:
        argv = [sys.executable, "-c", block.text]
    proc = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env=env,
        start_new_session=True,  # a command that outlives the bound is killed with its group
    )
    try:
        _, err = proc.communicate(timeout=BOUND)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    where = f"{block.doc}:{block.line}"
    assert proc.returncode == block.exit, f"{where}: exit {proc.returncode}\n{err[-3000:]}"
    assert block.traceback or "Traceback" not in err, f"{where}\n{err[-3000:]}"
    left = _top_level() - before
    assert not left, f"{where} left {sorted(left)} in the repository"


def test_the_runner_finds_the_blocks_and_their_marks() -> None:
    assert len(ALL) > 20
    assert any(b.skip for b in ALL)


# Every repository path that pyproject.toml and the docs name exists.


#: The documents whose paths are checked, relative to the repository's root: every Markdown
#: file but the CHANGELOG (a record of the past, which names files that are gone).
def _markdown_files() -> list[str]:
    """Every Markdown file of the repository but the CHANGELOG (not in hidden or build folders)."""
    found = []
    for folder, subfolders, names in os.walk(ROOT):
        subfolders[:] = [
            d
            for d in subfolders
            if not d.startswith(".") and d not in ("build", "dist", "__pycache__")
        ]
        rel = Path(folder).relative_to(ROOT)
        found += [str(rel / n) for n in names if n.endswith(".md") and n != "CHANGELOG.md"]
    return sorted(os.path.normpath(f) for f in found)


PATH_DOCS = ("pyproject.toml", *_markdown_files())

#: Mentions that look like repository paths but are not, each with its reason.
NOT_PATHS = {
    # Zenoh key expressions: the fleet's channels under the key prefix `temoto` (docs/zenoh.md).
    re.compile(r"temoto/TEMOTO_[A-Z_]+"): "a Zenoh key expression, not a file",
}

_LINK = re.compile(r"\[([^\]]*)\]\(([^)\s]+)\)")
_URL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)
_PLACEHOLDER = re.compile(r"<[^<>/]+>")
#: A `.py` path written relative to the package (`core/plan.py`), backticked.
_PACKAGE_PATH = re.compile(r"`((\w+)/[\w./-]*\.py)(?::[\d-]+)?`")


def _top_level_names() -> tuple[list[str], list[str]]:
    """The repository's top-level directories and files (not hidden, not build output)."""
    names = [
        p
        for p in sorted(ROOT.iterdir())
        if not p.name.startswith((".", "_"))
        and p.name not in ("build", "dist")
        and not p.name.endswith(".egg-info")
    ]
    return [p.name for p in names if p.is_dir()], [p.name for p in names if p.is_file()]


def _path_pattern(dirs: list[str], files: list[str]) -> re.Pattern[str]:
    """A mention of `<top-level dir>/...` or of a top-level file, not inside a longer path."""
    tops = "|".join([f"{re.escape(d)}/[\\w./*<>-]*" for d in dirs] + [re.escape(f) for f in files])
    return re.compile(rf"(?<![\w./~$<-])({tops})(?![\w/-])")


def mentioned_paths(
    text: str, doc: str, dirs: list[str], files: list[str]
) -> list[tuple[int, str]]:
    """The repository paths a document names, as (line, path from the root) pairs.

    Links to files (``[text](target)``, relative to the document) and mentions of a top-level
    entry (``docs/engine.md``, ``temoto/core/engine.py:140``, ``README.md``) anywhere in the
    text, and backticked ``.py`` paths relative to the package (```core/plan.py```). A link to
    a URL is left out with its text. A ``<placeholder>`` stands for one or more characters.
    """
    pattern = _path_pattern(dirs, files)
    packages = {p.name for p in (ROOT / "temoto").iterdir() if p.is_dir()}
    base = Path(doc).parent
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for m in _LINK.finditer(line):
            target = m.group(2).split("#")[0]
            if target and not _URL.match(m.group(2)):
                found.append((number, os.path.normpath(base / target)))
        line = _LINK.sub(lambda m: "" if _URL.match(m.group(2)) else m.group(1), line)
        for m in pattern.finditer(line):
            found.append((number, m.group(1).rstrip(".")))
        for m in _PACKAGE_PATH.finditer(line):
            if m.group(2) in packages:
                found.append((number, f"temoto/{m.group(1)}"))
    return [(n, p) for n, p in found if not any(rx.fullmatch(p) for rx in NOT_PATHS)]


def _slug(heading: str) -> str:
    """A Markdown heading's anchor, as GitHub makes it (punctuation dropped, spaces to hyphens)."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(doc: str) -> set[str]:
    """The anchors of a document's headings (outside fenced blocks)."""
    found, fenced = set(), False
    for line in (ROOT / doc).read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and line.startswith("#"):
            found.add(_slug(line.lstrip("#")))
    return found


def _exists(path: str) -> bool:
    glob = _PLACEHOLDER.sub("*", path)
    if "*" in glob:
        return any(ROOT.glob(glob))
    return (ROOT / path).exists()


def test_every_path_the_docs_and_pyproject_name_exists() -> None:
    dirs, files = _top_level_names()
    missing = [
        f"{doc}:{line}: {path}"
        for doc in PATH_DOCS
        for line, path in mentioned_paths(
            (ROOT / doc).read_text(encoding="utf-8"), doc, dirs, files
        )
        if not _exists(path)
    ]
    assert not missing, "paths that do not exist:\n" + "\n".join(missing)


def test_every_link_to_a_heading_finds_it() -> None:
    broken = []
    for doc in PATH_DOCS:
        if not doc.endswith(".md"):
            continue
        for number, line in enumerate((ROOT / doc).read_text(encoding="utf-8").splitlines(), 1):
            for m in _LINK.finditer(line):
                target, _, anchor = m.group(2).partition("#")
                if not anchor or _URL.match(target) or not (target or doc).endswith(".md"):
                    continue
                path = os.path.normpath(Path(doc).parent / target) if target else doc
                if (ROOT / path).exists() and anchor not in _anchors(path):
                    broken.append(f"{doc}:{number}: {m.group(2)}")
    assert not broken, "links to headings that do not exist:\n" + "\n".join(broken)


def test_the_path_finder_finds_paths_and_only_paths() -> None:
    dirs, files = ["docs", "temoto", "hw_profiles"], ["README.md"]
    text = (
        "See docs/drivers.md, `temoto/core/engine.py:140`, [the guide](umrf-guide.md#conditions).\n"
        "Not: [spec `docs/spec.md`](https://example.org/docs/spec.md), /dev/ttyUSB0, x/docs/a.md,\n"
        "`temoto/TEMOTO_NOTIFY`, `python -m temoto`. Placeholders: `hw_profiles/<robot>.yaml`.\n"
        "In the package: `core/plan.py`; not a package: `DIR/reliability.py`. Top file README.md.\n"
    )
    assert mentioned_paths(text, "docs/x.md", dirs, files) == [
        (1, "docs/umrf-guide.md"),
        (1, "docs/drivers.md"),
        (1, "temoto/core/engine.py"),
        (3, "hw_profiles/<robot>.yaml"),
        (4, "README.md"),
        (4, "temoto/core/plan.py"),
    ]
    assert _exists("hw_profiles/<robot>.yaml")
    assert not _exists("hw_profiles/<robot>.toml")
    assert not _exists("docs/drivers.md")


# Nothing points at design notes outside the repository: their facts are in docs/design.md and
# docs/development.md.

_OUTSIDE = re.compile(
    r"\b(?:STYLE|ARCHITECTURE|REFERENCE)\b(?:\.md)?\s*(?:§|\d|rule|part)|\b(?:STYLE|ARCHITECTURE|REFERENCE)\.md\b|\.\./shared/|shared/design"
)

#: Modules being reorganised on other branches, whose references are mended when they merge.
PENDING: set[str] = set()


def _sources() -> list[str]:
    """The code, build files and docs whose comments and docstrings may cite design notes."""
    found = [*PATH_DOCS, "setup.py", "Makefile"]
    for top in ("temoto", "tests", "tools", "bench"):
        for suffix in ("*.py", "*.pxd", "*.pyx", "*.lcm"):
            found += [str(p.relative_to(ROOT)) for p in (ROOT / top).rglob(suffix)]
    return sorted(set(found) - PENDING - {"tests/test_docs.py"})  # this file holds the pattern


def test_nothing_cites_a_design_note_outside_the_repository() -> None:
    cited = [
        f"{path}:{number}: {line.strip()}"
        for path in _sources()
        if (ROOT / path).exists()
        for number, line in enumerate((ROOT / path).read_text(encoding="utf-8").splitlines(), 1)
        if _OUTSIDE.search(line)
    ]
    assert not cited, "cite docs/design.md or docs/development.md instead:\n" + "\n".join(cited)


# A docstring's ``Raises:`` section lists what the function raises; one that raises nothing has
# none (docs/development.md), rather than a section that says "Nothing.".

_RAISES_NOTHING = re.compile(r"^[ \t]*Raises:[ \t]*\n[ \t]*Nothing\b", re.MULTILINE)

#: Modules being reorganised on other branches, mended when they merge.
RAISES_PENDING: set[str] = set()


def test_no_docstring_has_a_raises_section_that_says_nothing() -> None:
    found = []
    for top in ("temoto", "tools"):
        for file in sorted((ROOT / top).rglob("*.py")):
            path = str(file.relative_to(ROOT))
            if path in RAISES_PENDING:
                continue
            text = file.read_text(encoding="utf-8")
            for match in _RAISES_NOTHING.finditer(text):
                found.append(f"{path}:{text.count(chr(10), 0, match.start()) + 1}")
    assert not found, "drop the 'Raises: Nothing.' section:\n" + "\n".join(found)

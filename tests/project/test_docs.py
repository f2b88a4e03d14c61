"""What README.md, ARCHITECTURE.md and docs/ name exists: every file and folder of the repository they cite in backticks, every
relative link (and the heading it points at), every ``genre`` command and ``python -m`` module they tell the reader
to run, and every module they name by its dotted path.

A cited path counts when it starts with one of the repository's tracked top-level entries (``scripts/…``,
``genre_backend/…``, ``Makefile``); outputs (``out/…``, ``$GENRE_HOME/…``) and placeholders (``NAME``, ``<dir>``,
``…``) are not files to look for."""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import re
import subprocess
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "ARCHITECTURE.md", *sorted((ROOT / "docs").rglob("*.md"))]
# the words a path or a command uses for "any such": not names to look for
PLACEHOLDER = re.compile(r"[<>{}$~…]|\.\.\.|(?<![A-Za-z])(NAME|STAGE|RUN|PKG|FILE|DIR|ID|SUB|SPLIT|LABEL|CLASS|STEPS|X|N|K|W|P|M)(?![A-Za-z])")
SPAN = re.compile(r"`([^`\n]+)`")
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
COMMAND = re.compile(r"(?:^|[\s(])(?:\.venv/bin/)?genre ((?:[a-z][\w-]*)(?:\|[a-z][\w-]*)*)(?: ((?:[a-z][\w-]*)(?:\|[a-z][\w-]*)*))?")
MODULE_RUN = re.compile(r"python -m ((?:genre_backend|training|blender_addon|scripts|tests)[\w.]*)")
DOTTED = re.compile(r"^(genre_backend|training|blender_addon)(\.\w+)+$")


@cache
def top_level() -> frozenset[str]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return frozenset(line.split("/")[0] for line in out.splitlines())


def documents():
    for doc in DOCS:
        yield doc.relative_to(ROOT).as_posix(), doc.read_text(encoding="utf-8")


def cited_paths(text: str):
    """The repository paths a text cites in backticks (the first word of a span, trailing punctuation dropped)."""
    for span in SPAN.findall(text):
        words = span.split()
        if not words:
            continue
        word = words[0].rstrip(":,;.)").lstrip("(")
        if word.startswith(".venv/bin/") or PLACEHOLDER.search(word):
            continue
        head = word.split("/")[0]
        if head in top_level() and (word != head or "/" in span or head[:1].isupper() or "." in head):
            yield word


def path_exists(path: str) -> bool:
    """The path exists (a glob: something matches); ``FILE::test_name``: and the file defines that test."""
    path, _, test = path.partition("::")
    if "*" in path:
        return any(ROOT.glob(path))
    file = ROOT / path
    return file.exists() and (not test or re.search(rf"^\s*def {re.escape(test.split('[')[0])}\(", file.read_text(), re.M) is not None)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (but - and _), spaces to -."""
    text = re.sub(r"[`*]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(doc: Path) -> set[str]:
    text = FENCE.sub("", doc.read_text(encoding="utf-8"))
    return {slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", text, re.M)}


def broken_links(name: str, text: str):
    doc = ROOT / name
    for target in LINK.findall(FENCE.sub("", text)):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (doc.parent / path).resolve() if path else doc
        if not file.exists():
            yield f"{name}: link to {target}: no such file"
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            yield f"{name}: link to {target}: no such heading"


def commands_named(text: str):
    """(command, subcommand or None) for each ``genre …`` a text names in backticks or in a code block."""
    pieces = SPAN.findall(text) + FENCE.findall(text)
    for piece in pieces:
        for line in piece.splitlines():
            for m in COMMAND.finditer(line):
                for first in m.group(1).split("|"):
                    seconds = m.group(2).split("|") if m.group(2) else [None]
                    for second in seconds:
                        yield first, second


@cache
def genre_accepts(command: str, sub: str | None) -> bool:
    """Whether ``genre COMMAND [SUB] --help`` is accepted: SUB a subcommand (or a chain's name) of COMMAND."""
    from genre_backend.cli import commands, main

    if command not in commands():
        return False
    if sub is None:
        return True
    if command == "chain":  # the chain's name is a plain positional: argparse would take any word
        from training.chain import CHAINS

        return sub in CHAINS
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        try:
            code = main([command, sub, "--help"])
        except SystemExit as stop:
            code = stop.code
    return code == 0


def module_exists(dotted: str) -> bool:
    """A module, or an attribute of one (``training.data.corpus.data_dir``)."""
    parts = dotted.split(".")
    for n in range(len(parts), 1, -1):
        name = ".".join(parts[:n])
        try:
            found = importlib.util.find_spec(name)
        except ModuleNotFoundError:
            found = None
        if found is not None:
            obj = importlib.import_module(name)
            return all((obj := getattr(obj, attr, None)) is not None for attr in parts[n:])
    return False


def test_the_documents_are_found():
    names = [name for name, _ in documents()]
    assert "README.md" in names and "docs/protocol.md" in names and any(n.startswith("docs/lab/") for n in names)


def test_every_cited_file_exists():
    missing = [f"{name}: {path}" for name, text in documents() for path in cited_paths(text) if not path_exists(path)]
    assert not missing, "cited but not in the repository:\n" + "\n".join(sorted(set(missing)))


def test_every_relative_link_and_its_heading_exist():
    broken = [line for name, text in documents() for line in broken_links(name, text)]
    assert not broken, "\n".join(broken)


def test_every_genre_command_exists():
    named = {pair for _, text in documents() for pair in commands_named(text)}
    assert ("reconstruct", None) in named and ("bench", "reconstruct") in named  # the parse finds them
    unknown = sorted(f"genre {c} {s or ''}".strip() for c, s in named if not genre_accepts(c, s))
    assert not unknown, "named in the docs, but genre refuses: " + ", ".join(unknown)


def test_every_module_named_exists():
    named = {m for _, text in documents() for m in MODULE_RUN.findall(text)}
    named |= {s for _, text in documents() for s in SPAN.findall(text) if DOTTED.match(s)}
    assert "training.eval.install" in named
    missing = sorted(m for m in named if not module_exists(m))
    assert not missing, "named in the docs, but not importable: " + ", ".join(missing)


@pytest.mark.parametrize("text, found", [
    ("run `scripts/train_product.sh` first", ["scripts/train_product.sh"]),
    ("(`genre_backend/geometry/cleanup.py: clean_mesh`)", ["genre_backend/geometry/cleanup.py"]),
    ("`genre_backend/weights/NAME.safetensors`, `out/demo/sofa.obj`, `$GENRE_HOME/runs`", []),
    ("see `Makefile` and `pyproject.toml`", ["Makefile", "pyproject.toml"]),
])
def test_the_parse_finds_the_paths_a_reader_would_look_for(text, found):
    assert list(cited_paths(text)) == found
    assert not all(path_exists(p) for p in cited_paths("`scripts/train_default.sh`"))  # a deleted script is missed
    assert path_exists("tests/project/test_docs.py::test_the_parse_finds_the_paths_a_reader_would_look_for")
    assert not path_exists("tests/project/test_docs.py::test_gone")


def test_the_checks_fail_on_what_is_gone():
    assert not genre_accepts("bench", "bogus") and not genre_accepts("chain", "train_default")
    assert not genre_accepts("frobnicate", None) and genre_accepts("data", "fetch")
    assert list(commands_named("`genre data fetch|build` and\n```sh\n.venv/bin/genre bench geometry\n```")) == [
        ("data", "fetch"), ("data", "build"), ("bench", "geometry")]
    assert not module_exists("genre_backend.inference.nowhere") and module_exists("training.data.corpus.data_dir")
    assert list(broken_links("README.md", "[x](docs/nowhere.md) [y](docs/protocol.md#no-such-heading)")) == [
        "README.md: link to docs/nowhere.md: no such file", "README.md: link to docs/protocol.md#no-such-heading: no such heading"]


def test_the_options_table_is_the_records():
    """docs/protocol.md's table of options is generated from MeshOptions: a stale one fails here."""
    from genre_backend.inference.options import TABLE_BEGIN, TABLE_END, table

    text = (ROOT / "docs" / "protocol.md").read_text(encoding="utf-8")
    assert TABLE_BEGIN in text and TABLE_END in text
    shown = text.split(TABLE_BEGIN + "\n", 1)[1].split(TABLE_END, 1)[0]
    assert shown == table(), "docs/protocol.md's options table is stale: python -m genre_backend.inference.options docs/protocol.md"

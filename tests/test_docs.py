"""The documentation points at files that exist: every relative markdown link of README.md, docs/ and the results
folders, and every repository path written in backticks in README.md and docs/ (the results folders' own notes
are a record and may name scripts removed since, with the commit they lived at)."""

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
USER_DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
ALL_DOCS = USER_DOCS + sorted((REPO / "benchmarks" / "results").rglob("*.md"))
PATH_PREFIXES = ("benchmarks/", "examples/", "hyperparams/", "sb3_gocu/", "docs/", "tests/", ".ci/")


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


def broken_links(doc: Path) -> list[str]:
    """Relative link targets of ``doc`` (``[text](target)``, images included) that do not exist."""
    out = []
    for target in re.findall(r"\]\(([^)\s]+)\)", doc.read_text()):
        if target.startswith(("http://", "https://", "#", "mailto:")):
            continue
        if not (doc.parent / target.split("#")[0]).exists():
            out.append(target)
    return out


def missing_paths(doc: Path) -> list[str]:
    """Repository paths in backticks (``benchmarks/...``, ``tests/x.py::test_y``, ...) that do not exist;
    placeholders (``<dir>``, ``*``, ``{0,1}``, ``...``) are skipped."""
    out = []
    for code in re.findall(r"`([^`\s]+)`", doc.read_text()):
        if not code.startswith(PATH_PREFIXES) or any(c in code for c in "<>*{}$") or "..." in code:
            continue
        path, _, test = code.rstrip(",.;:").partition("::")
        if not (REPO / path).exists():
            out.append(code)
        elif test and not re.search(rf"^def {re.escape(test)}\(", (REPO / path).read_text(), re.M):
            out.append(code)
    return out


@pytest.mark.parametrize("doc", ALL_DOCS, ids=_rel)
def test_relative_links_resolve(doc):
    assert broken_links(doc) == []


@pytest.mark.parametrize("doc", USER_DOCS, ids=_rel)
def test_backticked_repository_paths_exist(doc):
    assert missing_paths(doc) == []


def test_the_checks_catch_what_they_look_for(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("[a](missing.png) [b](x.md) [c](https://example.org) `benchmarks/no_such.py` `README.md`\n"
                   "`tests/test_docs.py::test_relative_links_resolve` `tests/test_docs.py::no_such_test` `benchmarks/<dir>`")
    assert broken_links(doc) == ["missing.png"]
    assert missing_paths(doc) == ["benchmarks/no_such.py", "tests/test_docs.py::no_such_test"]

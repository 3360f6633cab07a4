"""The documentation points at files that exist: every relative markdown link of README.md, docs/ and the results
folders, and every repository path written in backticks in README.md and docs/ (the results folders' own notes
are a record and may name scripts removed since). And benchmarks/results/ holds what the documentation cites: every
``benchmarks/results/...`` path in README.md and docs/ exists, and every entry of benchmarks/results/ is cited there."""

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
USER_DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
ALL_DOCS = USER_DOCS + sorted((REPO / "benchmarks" / "results").rglob("*.md"))
PATH_PREFIXES = ("benchmarks/", "examples/", "hyperparams/", "sb3_gocu/", "docs/", "tests/", ".ci/")
RESULTS = REPO / "benchmarks" / "results"


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


def expand_braces(path: str) -> list[str]:
    """``a_{0,1}.csv`` -> ``a_0.csv``, ``a_1.csv`` (shell-style, any number of groups, not nested)."""
    match = re.search(r"\{([^{}]*)\}", path)
    if not match:
        return [path]
    head, tail = path[: match.start()], path[match.end():]
    return [p for alt in match.group(1).split(",") for p in expand_braces(head + alt + tail)]


def cited_results(docs: list[Path]) -> set[str]:
    """The paths under benchmarks/results/ that ``docs`` name anywhere (links, backticks, commands, prose), relative to
    the repository root, braces expanded; placeholders (``<dir>``, ``*``, ``$X``, ``...``) are skipped."""
    out = set()
    for doc in docs:
        for found in re.findall(r"benchmarks/results/[^\s`'\"()\[\]]*", doc.read_text()):
            path = found.rstrip(",.;:")
            if any(c in path for c in "<>*$") or "..." in path or path.rstrip("/") == "benchmarks/results":
                continue
            out.update(p.rstrip("/") for p in expand_braces(path))
    return out


def uncited_results(cited: set[str], results: Path = RESULTS) -> list[str]:
    """The entries (folders and files) directly under ``results`` that no cited path is, or lies in."""
    tops = {Path(p).relative_to("benchmarks/results").parts[0] for p in cited}
    return sorted(entry.name for entry in results.iterdir() if entry.name not in tops)


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


def test_every_cited_result_exists():
    cited = cited_results(USER_DOCS)
    assert cited, "README.md and docs/ cite benchmarks/results/"
    assert sorted(p for p in cited if not (REPO / p).exists()) == []


def test_every_result_is_cited():
    """Each folder or file directly under benchmarks/results/ is cited in README.md or docs/ (a file inside a folder
    counts for the folder): what nothing cites does not belong there (git history keeps removed runs)."""
    assert uncited_results(cited_results(USER_DOCS)) == []


def test_the_results_checks_read_what_they_look_for(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("![c](../benchmarks/results/a/curves.png) `benchmarks/results/b/ppo_seed{0,1}.csv`, and\n"
                   "python benchmarks/plot_curves.py benchmarks/results/c --per-seed; `benchmarks/results/<dir>` "
                   "`benchmarks/results/throughput_*` benchmarks/results/d.txt.")
    assert cited_results([doc]) == {"benchmarks/results/a/curves.png", "benchmarks/results/b/ppo_seed0.csv",
                                    "benchmarks/results/b/ppo_seed1.csv", "benchmarks/results/c",
                                    "benchmarks/results/d.txt"}
    assert expand_braces("x_{0,1}_{a,b}") == ["x_0_a", "x_0_b", "x_1_a", "x_1_b"]
    results = tmp_path / "results"
    for name in ("a", "b", "c", "e"):
        (results / name).mkdir(parents=True)
    (results / "d.txt").write_text("")
    assert uncited_results(cited_results([doc]), results) == ["e"]

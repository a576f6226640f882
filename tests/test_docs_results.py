"""The docs and the results files agree: every ``experiments/results/...`` path that README.md,
CONTRIBUTING.md, a page under ``docs/`` or a notebook names exists, and every file under
``experiments/results/`` is cited by one of them.

A citation may be a brace list (``x.{json,md}``) or a glob (``x_*.md``); citing a folder cites every
file in it, and citing ``x.md`` also cites the files beside it with the same stem (``x.json``,
``x.png``, and the figure's legend ``x_figure.txt``: one result in several forms). A path followed
by ``<`` is a template (``deform_benchmark_<preset>.md``) and names no file. Results of decided
studies, removed from the repository, are named in docs/decisions.md without the
``experiments/results/`` folder, with the commit that holds them."""

from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results"
PATH = re.compile(r"experiments/results/([A-Za-z0-9_.*{},/-]*)")


def _documents() -> list[Path]:
    docs = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return docs + sorted((ROOT / "notebooks").glob("*.ipynb"))


def _text(path: Path) -> str:
    if path.suffix == ".ipynb":  # the cells' sources (a committed notebook keeps no outputs)
        return "\n".join("".join(c["source"]) for c in json.loads(path.read_text())["cells"])
    return path.read_text()


def _expand(pattern: str) -> list[str]:
    """``a{b,c}d`` -> ``abd``, ``acd`` (nested braces are not used)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [x for alt in m.group(1).split(",") for x in _expand(pattern[:m.start()] + alt + pattern[m.end():])]


def citations() -> dict[str, list[str]]:
    """``{cited path relative to experiments/results: [documents naming it]}``."""
    out: dict[str, list[str]] = {}
    for doc in _documents():
        text = _text(doc)
        for m in PATH.finditer(text):
            rel = m.group(1).rstrip(".,;:")
            if text[m.end():m.end() + 1] == "<":
                continue
            for pattern in _expand(rel):
                out.setdefault(pattern.rstrip("/"), []).append(str(doc.relative_to(ROOT)))
    return out


def _matches(pattern: str) -> list[Path]:
    if not pattern:
        return [RESULTS]
    return sorted(RESULTS.glob(pattern)) if any(c in pattern for c in "*?[") else \
        ([RESULTS / pattern] if (RESULTS / pattern).exists() else [])


def test_every_cited_results_path_exists():
    missing = {p: docs for p, docs in citations().items() if not _matches(p)}
    assert not missing, f"cited but not in experiments/results/: {missing}"


def test_every_results_file_is_cited():
    cited: set[Path] = set()
    for pattern in citations():
        if not pattern:  # "experiments/results/" alone names the folder, not its files
            continue
        for hit in _matches(pattern):
            if hit.is_dir():
                cited.update(f for f in hit.rglob("*") if f.is_file())
            else:
                stem = hit.name.split(".")[0]
                cited.update(f for f in hit.parent.iterdir()
                             if f.is_file() and f.name.split(".")[0] in (stem, f"{stem}_figure"))
    files = {f for f in RESULTS.rglob("*") if f.is_file()}
    uncited = sorted(str(f.relative_to(RESULTS)) for f in files - cited)
    assert not uncited, f"results files no document cites: {uncited}"


def test_templates_and_braces_expand():
    assert _expand("x.{json,md}") == ["x.json", "x.md"]
    assert _expand("a{b,c}_{d,e}") == ["ab_d", "ab_e", "ac_d", "ac_e"]


def test_readme_tables_are_the_results_files():
    """README.md's results tables are what ``python -m experiments.readme_tables`` writes from the
    results files (run it after a results file changes)."""
    from experiments import readme_tables

    text = (ROOT / "README.md").read_text()
    assert readme_tables.render(text) == text, "README.md's tables differ: run python -m experiments.readme_tables"
    assert text.count("<!-- table:") == len(readme_tables.TABLES)


def test_readme_is_a_front_door():
    """At most 150 lines and no commit hashes (the results files keep the provenance)."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150
    assert not re.search(r"\bcommits? [0-9a-f]{7,40}\b", text)

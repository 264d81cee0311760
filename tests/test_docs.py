"""The repository is self-contained: its files cite its own docs, never documents beside it."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Built from parts so that this file does not match itself.
OUTSIDE = re.compile("|".join(["THESIS" + r"\.md", "DESIGN" + r"\.md"]))
SUFFIXES = {".py", ".md", ".toml", ".yaml", ".yml", ".cfg", ".txt"}
SKIP = {".git", ".venv", "__pycache__", "build", "dist"}


def _repository_files():
    for path in ROOT.rglob("*"):
        rel = path.relative_to(ROOT)
        if any(part in SKIP or part.endswith(".egg-info") for part in rel.parts):
            continue
        if path.is_file() and path.suffix in SUFFIXES:
            yield path


def test_no_file_cites_a_document_outside_the_repository():
    offenders = [
        f"{p.relative_to(ROOT)}:{i}"
        for p in _repository_files()
        for i, line in enumerate(p.read_text(encoding="utf-8", errors="replace").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not offenders, f"cite docs/theory.md or docs/design.md instead: {offenders[:10]}"


def test_cited_theory_sections_exist():
    headings = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)", (ROOT / "docs/theory.md").read_text(), re.M))
    cited = set()
    for p in _repository_files():
        for m in re.finditer(r"docs/theory\.md (?:section|§) ?(\d+(?:\.\d+)?)", p.read_text(errors="replace")):
            cited.add(m.group(1).rstrip("."))
    missing = sorted(cited - headings)
    assert not missing, f"docs/theory.md has no section {missing}"

"""The product's text says what the software is and does, never how it was
built: no work sessions, passes or rounds of development, issue numbers,
machine-load anecdotes, commits as narrative, paths outside the repository,
or limits of one machine given as design reasons. Scans the README, docs,
code, tests, benchmarks, examples and CI files of the repository.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SUFFIXES = {".py", ".md", ".toml", ".html", ".yml", ".yaml", ".cff", ".cfg", ".txt", ".json5", ".sh"}
TOP = ["README.md", "CITATION.cff", "pyproject.toml", "Dockerfile", ".ci/run"]
FOLDERS = ["docs", "diskf_mesh", "agents", "sim", "tests", "benchmarks", "examples", ".ci"]
SKIP_PARTS = {"__pycache__", ".venv", "build", "dist", ".pytest_cache", ".hypothesis"}

# Each pattern with what it catches. Words such as "session" or "round" have
# meanings in the product (a zenoh session, one exchange round per tick), so
# the patterns name the narrative forms, not the bare words.
PATTERNS = {
    "an issue number": r"\bissues? ?#?\d+",
    "the issue as a reader": r"\bthe issue'?s\b|\bas the issue\b|\bthis issue\b",
    "a work session": r"\b(this|that|previous|earlier|last|next) session\b|\(this session|"
                      r"\b(from|with|by) (\w+ )?other sessions\b|shared with other sessions",
    "a development pass or round": r"\b(this|previous|earlier|last|next) (pass|round)\b(?!-)|\bmid-pass\b|"
                                   r"\bend of the pass\b|\bbefore this (pass|round|change|work)\b|"
                                   r"\bat the start of this work\b",
    "a machine-load anecdote": r"\bload average (of )?(about |~|around )?\d|\(load( average)? \d|"
                               r"\bload \d+\s*[–-]\s*\d+|\bother jobs\b|\b(loaded|busy) (by|with) other\b|\bthis loaded\b",
    "a commit as narrative": r"\bgit archive [0-9a-f]{7,40}\b|\bbefore \(`[0-9a-f]{7,40}`\)|\bthe code before this\b",
    "a path outside the repository": r"\.\./shared/|\bshared/paper\b|\bdiskf\.tex\b",
    "a sandbox limit as a reason": r"(?<!no-)\bsandbox|cannot be served from this machine",
    "the team that built it": r"\bhelpers? [A-H]\b",
}
COMPILED = {what: re.compile(rx, re.IGNORECASE) for what, rx in PATTERNS.items()}


def product_files() -> list[Path]:
    files = [ROOT / p for p in TOP if (ROOT / p).is_file()]
    for folder in FOLDERS:
        for p in sorted((ROOT / folder).rglob("*")):
            if p.is_file() and p.suffix in SUFFIXES and not SKIP_PARTS & set(p.relative_to(ROOT).parts):
                files.append(p)
    here = Path(__file__).resolve()
    return sorted({p for p in files if p.resolve() != here})


def findings(text: str) -> list[tuple[int, str, str]]:
    """(line number, what, the line) of every narrative phrase in ``text``."""
    out = []
    for n, line in enumerate(text.splitlines(), 1):
        for what, rx in COMPILED.items():
            if rx.search(line):
                out.append((n, what, line.strip()[:160]))
    return out


def test_the_scan_covers_the_product():
    names = {p.relative_to(ROOT).as_posix() for p in product_files()}
    for expected in ("README.md", "docs/performance.md", "diskf_mesh/core/equations.py", "sim/world.py",
                     "agents/agent.py", "tests/test_layers.py", ".ci/run"):
        assert expected in names


@pytest.mark.parametrize("line", [
    "load 12–46 from other sessions", "What this pass changed", "(this session)", "in issue 21 we",
    "issue 11's process part", "`git archive 3fa7b78`", "DISKF (`../shared/paper/diskf.tex`)",
    "five other sessions (load average 18–130)", "mid-pass", "cannot be served from this machine",
    "the code before this round", "other jobs kept it busy", "as the issue asks",
])
def test_each_narrative_form_is_caught(line):
    assert findings(line)


@pytest.mark.parametrize("line", [
    "one zenoh session per process", "publishers reach other sessions only", "one exchange round per tick",
    "a payload passes the guard", "round-off depends on the batch size", "--no-sandbox",
    "the load of the agents", "each round runs the baseline", "messages that pass the range gate",
    "so that round-off in a sum", "git archive REV | tar -x", "a busy machine slows them alike",
])
def test_product_words_are_not_caught(line):
    assert not findings(line)


def test_no_narrative_in_readme_docs_code_tests_or_ci():
    found = []
    for p in product_files():
        try:
            text = p.read_text(encoding="utf-8")
        except (UnicodeDecodeError, OSError):
            continue
        found += [f"{p.relative_to(ROOT)}:{n}: {what}: {line}" for n, what, line in findings(text)]
    assert not found, "narrative in the product's text:\n" + "\n".join(found)

"""The README as a front page: short, every command in it parses with the
command line's own parser, its Python example runs, and every link in it and
in docs/ points to a file of the repository."""
from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from diskf_mesh.cli.main import COMMAND_MODULES, build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, re.S)


def test_the_readme_is_a_front_page():
    assert len(README.splitlines()) <= 300
    for heading in ("## Two commands", "## A short tour", "## Table II", "## How to cite", "## Documentation"):
        assert heading in README


def commands() -> list[str]:
    out = []
    for block in blocks("sh"):
        for line in block.splitlines():
            line = line.split(" #", 1)[0].strip()
            if line.startswith("diskf-mesh "):
                out.append(line)
    return out


@pytest.mark.parametrize("line", commands())
def test_every_command_of_the_readme_parses(line):
    args = build_parser(COMMAND_MODULES).parse_args(shlex.split(line)[1:])  # an unknown flag exits 2
    assert callable(args.func)


def test_the_two_commands_are_the_ci_commands():
    ci = (ROOT / ".ci" / "run").read_text()
    setup = "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]'"
    assert setup in ci and ".venv/bin/python -m pytest" in ci
    assert blocks("sh")[0].strip().startswith(setup) and blocks("sh")[1].strip().startswith(setup)


def test_the_python_example_runs(tmp_path):
    (code,) = blocks("python")
    code = code.replace('"trace.json"', repr(str(tmp_path / "trace.json")))
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "(2, 100, 9, 2)" in done.stdout and "MAE(state)" in done.stdout


def test_links_point_to_files():
    bad = []
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", doc.read_text()):
            if re.match(r"[a-z]+://", target) or target.startswith("mailto:"):
                continue
            if not (doc.parent / target).exists():
                bad.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not bad, "\n".join(bad)


def test_table_ii_is_the_reports():
    import json

    from diskf_mesh.studies.report import front_page_table

    table = front_page_table(json.loads((ROOT / "docs" / "results.json").read_text())["table_ii"])
    assert table in README  # regenerate: diskf-mesh report --out docs, then this table into the README


def test_the_demos_stated_error_is_the_runs(tmp_path):
    """The demo's state MAE and the paper's DISKF's beside it, as the README
    states them, are what the same run gives (the engine: a mesh run equals
    it bit for bit)."""
    said = re.search(r"state MAE (\d+\.\d+) \(the paper's DISKF on the same run, `--estimator diskf`: (\d+\.\d+)\)",
                     " ".join(README.split()))
    assert said is not None
    out = tmp_path / "r.json"
    done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "experiment", "--scenario", "dynamic",
                           "--ticks", "200", "--seeds", "1", "--estimators", "diskf-auto,diskf", "--json", str(out),
                           "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    got = json.loads(out.read_text())
    assert f"{got['diskf-auto']['range=120']['mae_state']:.2f}" == said[1]
    assert f"{got['diskf']['range=120']['mae_state']:.1f}" == said[2]

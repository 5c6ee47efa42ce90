"""Costs stated once: docs/costs.md is what ``benchmarks/costs.py`` renders
from docs/costs.json, every page that quotes a cost links to its entry with
that entry's figures, the README states how long the tests take and names
the quick subset, and the benchmarks have one entry point listing them all."""
from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _costs():
    spec = importlib.util.spec_from_file_location("costs", ROOT / "benchmarks" / "costs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["costs"] = module  # its dataclasses look themselves up there
    spec.loader.exec_module(module)
    return module


costs = _costs()
DOC = json.loads((ROOT / "docs" / "costs.json").read_text())


def test_the_page_is_rendered_from_its_numbers():
    assert (ROOT / "docs" / "costs.md").read_text() == costs.render(DOC)
    assert set(DOC) <= set(costs.BY_KEY)


def test_every_quoted_cost_is_the_pages():
    quoted = 0
    for page in costs.quoting():
        text = page.read_text()
        assert costs.relink(text, DOC) == text, f"{page.name}: run python benchmarks/costs.py --render"
        quoted += len(costs.LINK.findall(text))
    assert quoted >= 6


def test_links_name_their_entry():
    assert costs.relink("[x](docs/costs.md#report)", {"report": {"wall_s": 70.4, "cpu_s": 139.0}}) == \
        "[70 s, 2.3 min of CPU](docs/costs.md#report)"
    assert costs.relink("[x](costs.md#tests)", {"tests": {"wall_s": 2460, "cpu_s": None}}) == \
        "[about 41 min](costs.md#tests)"
    assert costs.relink("[docs/costs.md](docs/costs.md#report)", {}) == "[docs/costs.md](docs/costs.md#report)"
    assert costs.duration(270) == "4.5 min"


def test_no_page_states_the_old_costs():
    """The figures that disagreed before there was one page of costs."""
    stale = ["about 55 s of CPU", "4.5 minutes", "682 s of CPU", "570 s of CPU", "53–55 s CPU", "in 4 s after"]
    for page in costs.quoting():
        if page.name in ("costs.md", "reproduction.md"):  # reproduction.md: the run that made it, as it was
            continue
        text = " ".join(page.read_text().split())
        assert not [s for s in stale if s in text], page.name


def test_the_readme_says_how_long_the_tests_take_and_gives_a_quick_subset():
    readme = (ROOT / "README.md").read_text()
    assert "(docs/costs.md#tests)" in readme and "(docs/costs.md#tests-quick)" in readme
    assert ".venv/bin/python -m pytest -m quick" in readme
    quick = DOC.get("tests-quick")  # absent while benchmarks/costs.py measures it for the first time
    assert quick is None or (quick["exit"] == 0 and quick["cpu_s"] < 180)  # one process: wall = CPU when idle


def test_every_benchmark_is_listed_and_reachable():
    scripts = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_"))
    index = (ROOT / "benchmarks" / "README.md").read_text()
    assert [s for s in scripts if f"| `{s}` |" not in index] == []
    listed = subprocess.run([sys.executable, "-m", "benchmarks"], cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert listed.returncode == 0
    assert [line.split()[0] for line in listed.stdout.splitlines()[1:]] == scripts
    wrong = subprocess.run([sys.executable, "-m", "benchmarks", "enginebench"], cwd=ROOT, capture_output=True,
                           text=True, timeout=60)
    assert wrong.returncode == 2 and "did you mean engine_bench?" in wrong.stderr


def test_report_s_quoted_cost_names_its_command():
    row = DOC["report"]
    assert row["command"] == "diskf-mesh report --out DIR" and row["exit"] == 0
    assert re.search(r"\d+ cores", row["machine"]) or "cores" in row["machine"]


def test_the_tours_simulated_run_is_the_measured_one_and_takes_about_a_minute():
    """The README's simulated-network command is the entry ``tour`` measures,
    of a size that takes about a minute of CPU; the larger one is linked with
    its own cost."""
    readme = (ROOT / "README.md").read_text()
    command = costs.shown(costs.BY_KEY["tour"].argv).replace(" --json DIR/r.json", "")
    assert command in readme
    assert "(docs/costs.md#tour)" in readme and "(docs/costs.md#simulated-1000)" in readme
    tour = DOC["tour"]
    assert tour["exit"] == 0 and tour["cpu_s"] < 90

"""Every script in examples/ runs as its docstring says, on small sizes, from
a folder of its own, and does what it claims (a table, metrics, a figure)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def run(script: str, *args, cwd: Path) -> str:
    done = subprocess.run([sys.executable, str(EXAMPLES / script), *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_own_scenario_in_toml(tmp_path):
    out = run("own-scenario/run.py", "--seeds", "2", cwd=tmp_path)
    assert "corridor: 6 agents, 120 ticks" in out
    assert out.count("MAE(state)") >= 3  # one row per topology of the table, and the run's line
    mae_state = float(out.rsplit("MAE(state) ", 1)[1].split(",")[0])
    assert 0 < mae_state < 20


def test_own_data_as_a_trace(tmp_path):
    out = run("own-data/run.py", "--out", "t.json", "--ticks", "40", cwd=tmp_path)
    doc = json.loads((tmp_path / "t.json").read_text())
    assert doc["format"] == "diskf-trace/1" and len(doc["y"]) == 40
    rows = {line.split()[0]: [float(v) for v in line.split()[1:]] for line in out.splitlines()
            if line.split() and line.split()[0] in ("diskf", "diskf-r", "cdrkf", "kcf", "diffkf")}
    assert len(rows) == 5 and all(0 < v < 100 for r in rows.values() for v in r)
    assert "diskf-estimates/1" in out


def test_comparing_estimators_with_a_plot(tmp_path):
    out = run("compare-estimators/run.py", "--seeds", "1", "--ticks", "30", "--out", "cmp.svg", cwd=tmp_path)
    assert (tmp_path / "cmp.svg").read_text().lstrip().startswith("<?xml")
    assert sum(line.split()[0] in ("diskf", "diskf-r", "kcf") for line in out.splitlines() if line.split()) == 3


def test_streaming_loop_equals_the_engine(tmp_path):
    """The loop's network, its agents carrying bytes, and the batched engine
    on the logged data agree bit for bit (the script exits 1 otherwise)."""
    out = run("streaming/run.py", "--ticks", "40", "--seed", "5", cwd=tmp_path)
    assert "diskf-auto on 9 agents, 40 ticks" in out
    assert "the batched engine on the logged data: the same estimates, bit for bit" in out
    rows = [line.split() for line in out.splitlines() if line.split() and line.split()[0].isdigit()]
    assert [int(r[0]) for r in rows] == [20, 40] and all(0 < float(r[1]) < 100 for r in rows)


def test_every_example_has_a_test():
    scripts = {p.relative_to(EXAMPLES).as_posix() for p in EXAMPLES.glob("*/run.py")}
    assert scripts == {"own-scenario/run.py", "own-data/run.py", "compare-estimators/run.py", "streaming/run.py"}

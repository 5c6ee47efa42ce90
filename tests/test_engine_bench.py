"""The benchmark scripts run end to end (tiny sizes) and print their tables."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "engine_bench.py"


def test_engine_bench_smoke():
    args = ["--seeds", "1", "--ticks", "4", "--repeat", "1", "--oracle-seeds", "1",
            "--agents", "12", "--ratio-steps", "3", "--big", "diskf"]
    out = subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True).stdout
    assert "| DISKF |" in out and "Full Table II" in out and "peak RSS" in out


def test_agent_bench_smoke():
    script = SCRIPT.parent / "agent_bench.py"
    out = subprocess.run([sys.executable, str(script), "--ticks", "5", "--repeat", "1"], check=True,
                         capture_output=True, text=True).stdout
    row = next(line for line in out.splitlines() if line.startswith("| diskf |"))
    total, math, protocol = (float(c) for c in row.strip("|").split("|")[1:])
    assert total > 0 and math > 0 and total == pytest.approx(math + protocol, abs=1.0)


def test_random_models_smoke():
    """Three random models (62 among them: isolated velocity-only sensors,
    which diskf-auto lost while its model mixing counted the spread in
    full): a row per estimator; the DISKF family's own estimators and the
    input-free filters lose no run."""
    script = SCRIPT.parent / "random_models.py"
    out = subprocess.run([sys.executable, str(script), "--first", "60", "--models", "3"], check=True,
                         capture_output=True, text=True).stdout
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in out.splitlines()
            if line.startswith("| ") and not line.startswith("| estimator")}
    assert len(rows) == 9 and all(rows[name] == "0" for name in
                                  ("diskf-r", "diskf-auto", "diskf-none", "kcf", "diffkf", "gdkf"))

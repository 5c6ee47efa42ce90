"""The engine benchmark script runs end to end (tiny sizes) and prints its tables."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "engine_bench.py"


def test_engine_bench_smoke():
    args = ["--seeds", "1", "--steps", "4", "--repeat", "1", "--oracle-seeds", "1",
            "--agents", "12", "--ratio-steps", "3", "--big", "diskf"]
    out = subprocess.run([sys.executable, str(SCRIPT), *args], check=True, capture_output=True, text=True).stdout
    assert "| DISKF |" in out and "Full Table II" in out and "peak RSS" in out

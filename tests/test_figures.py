"""The figure and report commands write their files on a short run."""
from __future__ import annotations

import json
import re
from pathlib import Path

from cli_helpers import run_cli
from diskf_mesh.data import provenance

SHORT = ["--seeds", "2", "--ticks", "30", "--quiet"]
FIGURES = {
    "scenario_dynamic.png", "scenario_stationary.png", "trajectories_stationary_ring.png",
    "trajectories_dynamic_120.png", "inputs_stationary_ring.png", "inputs_dynamic_120.png",
    "states_stationary_ring.png", "states_dynamic_120.png", "error_vs_range.png", "dynamic_bars.png",
    "isolated_by_sensor.png", "window_stationary_ring.png", "window_dynamic_120.png",
}


def is_png(path: Path) -> bool:
    return path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figures_command_writes_every_png(tmp_path, capsys):
    out = tmp_path / "figs"
    code, stdout, err = run_cli(["figures", "--out", out, *SHORT], capsys)
    assert code == 0, err
    assert {p.name for p in out.iterdir()} == FIGURES
    assert all(is_png(p) and p.stat().st_size > 5000 for p in out.iterdir())
    assert "13 figures" in stdout


def test_report_command_writes_markdown_figures_and_json(tmp_path, capsys):
    code, stdout, err = run_cli(["report", "--out", tmp_path, *SHORT], capsys)
    assert code == 0, err
    md = (tmp_path / "reproduction.md").read_text()
    for heading in ("Table II", "Fig. 5", "Fig. 6", "Table I", "Fig. 3", "not the best", "Differences"):
        assert heading in md, heading
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert {Path(l).name for l in links} == FIGURES | {"auto_choice.png"}
    assert all((tmp_path / l).is_file() for l in links)
    doc = json.loads((tmp_path / "results.json").read_text())
    assert set(doc) >= {"table_ii", "dynamic", "sweep", "compensation", "window", "diagnostics"}
    assert list(doc["provenance"]) == list(provenance.KEYS) and doc["provenance"]["seeds"] == [0, 1]
    assert doc["compensation"]["dynamic"]["all-to-all"]["bit_identical"] is True
    assert "2 seeds" in md and "30 ticks" in md


def test_out_that_is_a_file_is_bad_input(tmp_path, capsys):
    f = tmp_path / "taken"
    f.write_text("x")
    code, _, err = run_cli(["figures", "--out", f, *SHORT], capsys)
    assert code == 2
    assert err.startswith("error: out:") and len(err.strip().splitlines()) == 1


def test_recording_figures_without_matplotlib_is_one_error_line(tmp_path, capsys):
    """``figures --from`` without the plotting packages: one line naming the
    README's own install command, exit 2, no folder made."""
    import subprocess
    import sys

    from diskf_mesh.cli.study_options import INSTALL_FIGURES

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert f"`{INSTALL_FIGURES}`" in readme
    code, _, err = run_cli(["up", "--network", "simulated", "--ticks", "5", "--record", tmp_path / "run.mcap",
                            "--quiet"], capsys)
    assert code == 0, err
    block = "import sys; sys.modules['matplotlib'] = None; from diskf_mesh.cli.main import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run([sys.executable, "-c", block, "figures", "--from", "run.mcap", "--out", "figs"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and f"{INSTALL_FIGURES} in the diskf-mesh folder" in done.stderr
    assert not (tmp_path / "figs").exists()

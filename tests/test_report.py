"""The report's runs and its held-out section: stacked runs give the numbers
of separate runs, every estimator runs once per setting, and the held-out
suite's results are kept with their own provenance."""
from __future__ import annotations

import json
import math

import numpy as np

from diskf_mesh.data.scenario import simulate
from diskf_mesh.engine import batch as engine
from diskf_mesh.engine import centralized
from diskf_mesh.studies import heldout, report
from diskf_mesh.studies import suite as studies

CFG = studies.StudyConfig(seeds=2, steps=20, algorithms=("diskf", "diskf-r", "kcf"), quiet=True)


def test_setting_runs_equal_runs_of_each_setting_alone():
    runs = studies.setting_runs(CFG, studies.STATIONARY, studies.PAPER_SETTINGS_1, keep=("ring",))
    for st in studies.PAPER_SETTINGS_1:
        scn = CFG.scenario(studies.STATIONARY, st)
        tr = simulate(scn, CFG.seed_range)
        for a in CFG.algorithms:
            alone = engine.run(tr, a, scn.params)
            assert runs.rows[st.label][a] == studies.metric_row(tr, alone), (st.label, a)
            if st.label == "ring":
                kept = runs.runs["ring"][2][a]
                assert all(np.array_equal(getattr(kept, f), getattr(alone, f)) for f in ("x", "P", "d", "d_valid"))
        assert runs.rows[st.label][centralized.NAME] == studies.metric_row(tr, centralized.run_centralized(tr))
    assert set(runs.runs) == {"ring"}


def test_each_estimator_runs_once_per_scenario(monkeypatch):
    calls = []
    real = engine.run_many

    def counting(traces, name, params=None, progress=None):
        calls.append((name, len(traces)))
        return real(traces, name, params, progress)

    monkeypatch.setattr(engine, "run_many", counting)
    studies.setting_runs(CFG, studies.DYNAMIC, studies.sweep_settings((0.0, 120.0)))
    assert sorted(calls) == sorted((a, 3) for a in CFG.algorithms)


def test_paper_rows_keep_the_references_asked_for():
    runs = studies.setting_runs(CFG, studies.STATIONARY, studies.PAPER_SETTINGS_1)
    rows = studies.paper_rows(runs, references=studies.TABLE_II_REFERENCES)
    assert list(rows) == [*CFG.algorithms, centralized.NAME, centralized.PERSIST_NAME]
    assert "nees_observed" not in rows["diskf"]["all"] and "nees_observed" in rows[centralized.NAME]["all"]
    assert list(studies.paper_rows(runs)) == [*CFG.algorithms, centralized.NAME]


def test_ablation_cells_stacked_equal_each_cell_alone():
    cells = (("stationary", "1-hop", studies.STATIONARY, studies.RING),
             ("stationary", "none", studies.STATIONARY, studies.NONE))
    got = studies._ablation(CFG, studies.window_variants, "window", cells=cells)
    for env, comm, name, st in cells:
        scn = CFG.scenario(name, st)
        rows, _ = studies.run_variants(scn, studies.window_variants(studies.scale_params(scn)), CFG)
        assert got[env][comm]["rows"] == rows


def _row(mae: float, diverged: bool = False) -> dict:
    return dict(mae_state=mae, mae_input=None if diverged else 1.0, nees=2.0, nees_band_share=0.9, diverged=diverged)


HELDOUT = {
    "seeds": 20, "steps": None, "cpu_seconds": 181.4, "processes": 2,
    "results": [
        {"case": "S1 ring, zero", "group": "inputs", "n": 2, "rows": {"kcf": _row(1.0), "diskf-r": _row(2.5)}},
        {"case": "S1 ring, step", "group": "inputs", "n": 2, "rows": {"kcf": _row(1.05), "diskf-r": _row(1.0)}},
        {"case": "CV all, zero", "group": "constant velocity", "n": 4,
         "rows": {"kcf": _row(3.0), "diskf-r": _row(float("nan"), diverged=True)}},
    ],
    "targets": {"cases": 3, "family_within_1pct": 1, "auto_within_10pct": 0, "auto_nees_in_band": 0,
                "auto_nees_cases": 0, "diverged_runs": 1, "misses": {"family": [], "auto": [], "nees": []}},
    "provenance": {"command": ["diskf-mesh", "report", "--heldout", "--out", "docs"], "git_commit": "abcdef0123456789",
                   "started": "2026-01-02T03:04:05+00:00"},
}


def test_where_each_estimator_is_right_counts_from_the_cases():
    kcf, dr = report.where_right(json.loads(json.dumps(HELDOUT)))
    assert "lowest state MAE in 2 of 3 cases" in kcf and "within 10 % of the lowest in 3" in kcf
    assert "more than twice the lowest in 0" in kcf and "zero (2)" in kcf
    assert "lowest state MAE in 1 of 3 cases" in dr and "within 10 % of the lowest in 1" in dr
    assert "more than twice the lowest in 1 (S1 ring, zero)" in dr and "diverged in 1" in dr


def test_heldout_results_are_kept_with_their_provenance(tmp_path):
    (tmp_path / "results.json").write_text(json.dumps({"table_ii": {}, heldout.REPORT_KEY: HELDOUT}).replace("NaN", "null"))
    kept = report.previous_heldout(tmp_path / "results.json")
    assert kept["provenance"]["git_commit"] == "abcdef0123456789"
    assert math.isnan(kept["results"][2]["rows"]["diskf-r"]["mae_state"])  # JSON's null read back as NaN
    text = report.section_heldout(report.Context(studies.Results(config={})), kept)
    assert "`diskf-mesh report --heldout --out docs`" in text and "2026-01-02T03:04:05+00:00" in text
    assert "commit abcdef0" in text and "| S1 ring, zero |" in text and "181 s of CPU" in text
    assert report.previous_heldout(tmp_path / "missing.json") is None
    none = report.section_heldout(report.Context(studies.Results(config={})), None)
    assert report.HELDOUT_COMMAND in none and "| case |" not in none


def test_front_page_table_shows_both_centralized_filters():
    row = {k: 1.0 for k in ("mae_state", "rmse_state", "mae_input", "rmse_input")}
    t2 = {a: {st: dict(row) for st in ("all", "ring", "none")} for a in ("diskf", "centralized", "centralized-persist")}
    t2["centralized-persist"]["all"]["mae_state"] = 0.5
    lines = report.front_page_table(t2).splitlines()
    assert lines[0].endswith("| Centralized (bound) | Centralized, persistent input |")
    assert lines[2].endswith("| 1.00 | 0.50 |")

"""Experiments: algorithms x topologies (or ranges) x seeds on a scenario.

Results are plain nested dicts ``{algorithm: {setting: {metric: value}}}``
(JSON-ready), with spreads over seeds under ``"<metric>_std"``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import engine, metrics
from .model import Params
from .scenario import Scenario, simulate

PAPER_LABELS = {"diskf": "DISKF", "cdrkf": "C-DRKF", "ldrkf": "L-DRKF", "kcf": "KCF", "diffkf": "DiffKF", "gdkf": "GDKF"}


@dataclass(frozen=True)
class Setting:
    """One column of an experiment: a topology, or a communication range."""

    label: str
    topology: str | None = None
    comm_range: float | None = None


def run_setting(scn: Scenario, setting: Setting, algorithms, seeds, steps=None, params: Params | None = None,
                progress=None):
    """{algorithm: {metric: pooled value, metric_std: spread over seeds}}"""
    s = scn.with_overrides(topology=setting.topology, comm_range=setting.comm_range, steps=steps)
    trace = simulate(s, seeds)
    out = {}
    for name in algorithms:
        est = engine.run(trace, name, params or s.params)
        row = metrics.compute(trace, est)
        spread = metrics.per_seed(trace, est)
        row.update({f"{k}_std": float(np.nanstd(v)) for k, v in spread.items()})
        out[name] = row
        if progress is not None:
            progress(1)
    return out


def run_experiment(scn: Scenario, settings, algorithms, seeds, steps=None, params: Params | None = None,
                   progress=None) -> dict:
    """{algorithm: {setting label: {metric: value}}} over all settings."""
    results = {a: {} for a in algorithms}
    for st in settings:
        rows = run_setting(scn, st, algorithms, seeds, steps, params, progress)
        for a, row in rows.items():
            results[a][st.label] = row
    return results


def format_table(results: dict, metric_keys=("mae_state", "rmse_state", "mae_input", "rmse_input")) -> str:
    """A text table shaped like the paper's Table II: settings x metrics rows,
    algorithms as columns, the best (lowest) value of each row marked *."""
    algs = list(results)
    settings = list(next(iter(results.values())))
    head = f"{'Comm.':<10}{'Metric':<14}" + "".join(f"{PAPER_LABELS.get(a, a):>10}" for a in algs)
    lines = [head, "-" * len(head)]
    for st in settings:
        for i, key in enumerate(metric_keys):
            vals = [results[a][st][key] for a in algs]
            finite = [v for v in vals if np.isfinite(v)]
            best = min(finite) if finite else None
            cells = "".join(
                f"{('-' if not np.isfinite(v) else f'{v:.2f}') + ('*' if v == best else ' '):>10}" for v in vals
            )
            label = key.replace("_state", "(state)").replace("_input", "(input)").upper().replace("MAE(", "MAE(").replace("RMSE(", "RMSE(")
            lines.append(f"{st if i == 0 else '':<10}{label:<14}{cells}")
        lines.append("")
    return "\n".join(lines)

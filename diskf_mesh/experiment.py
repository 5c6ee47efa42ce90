"""Experiments: algorithms x topologies (or ranges) x seeds on a scenario.

Results are plain nested dicts ``{algorithm: {setting: {metric: value}}}``
(JSON-ready), with spreads over seeds under ``"<metric>_std"``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import engine, metrics
from .errors import InputError
from .model import Params
from .scenario import TOPOLOGIES, Scenario, simulate

PAPER_LABELS = {"diskf": "DISKF", "cdrkf": "C-DRKF", "ldrkf": "L-DRKF", "kcf": "KCF", "diffkf": "DiffKF", "gdkf": "GDKF"}
TOPOLOGY_LABELS = {"all": "all-to-all", "ring": "1-hop", "none": "none"}
TABLE_METRICS = ("mae_state", "rmse_state", "mae_input", "rmse_input", "input_coverage")
HIGHER_IS_BETTER = frozenset({"input_coverage"})
METRIC_LABELS = {
    "mae_state": "MAE(state)", "rmse_state": "RMSE(state)", "mae_input": "MAE(input)",
    "rmse_input": "RMSE(input)", "input_coverage": "input cov.", "nees": "NEES",
}


@dataclass(frozen=True)
class Setting:
    """One column of an experiment: a topology, or a communication range."""

    label: str
    topology: str | None = None
    comm_range: float | None = None

    def apply(self, scn: Scenario, steps: int | None = None) -> Scenario:
        """The scenario with this setting's topology (and range) and horizon."""
        return scn.with_overrides(topology=self.topology, comm_range=self.comm_range, steps=steps)


def settings_for(topologies, comm_range: float | None = None) -> list[Setting]:
    """Settings for topology names (all, ring, none, range).

    ``comm_range`` is the radius of the ``range`` topology; giving it with
    static topologies only is an error (it would be silently ignored)."""
    topologies = list(topologies)
    if not topologies:
        raise InputError("topology", f"give at least one of {', '.join(TOPOLOGIES)}")
    for t in topologies:
        if t not in TOPOLOGIES:
            raise InputError("topology", f"must be one of {', '.join(TOPOLOGIES)}, got {t!r}")
    if comm_range is not None and "range" not in topologies:
        raise InputError("range", "applies only to the 'range' topology (add range to --topology)")
    out = []
    for t in topologies:
        if t == "range":
            label = "range" if comm_range is None else f"range={comm_range:g}"
            out.append(Setting(label, "range", comm_range))
        else:
            out.append(Setting(t, t))
    return out


def run_setting(scn: Scenario, setting: Setting, algorithms, seeds, steps=None, params: Params | None = None,
                progress=None):
    """{algorithm: {metric: pooled value, metric_std: spread over seeds}}"""
    s = setting.apply(scn, steps)
    trace = simulate(s, seeds)
    out = {}
    for name in algorithms:
        est = engine.run(trace, name, params or s.params)
        row = metrics.compute(trace, est)
        spread = metrics.per_seed(trace, est)
        row.update({f"{k}_std": float(np.nanstd(v)) if np.isfinite(v).any() else float("nan")
                    for k, v in spread.items()})
        out[name] = row
        if progress is not None:
            progress(1)
    return out


def run_experiment(scn: Scenario, settings, algorithms, seeds, steps=None, params: Params | None = None,
                   progress=None) -> dict:
    """{algorithm: {setting label: {metric: value}}} over all settings.

    ``progress``, if given, is called with 1 after every (setting, algorithm)."""
    results = {a: {} for a in algorithms}
    for st in settings:
        rows = run_setting(scn, st, algorithms, seeds, steps, params, progress)
        for a, row in rows.items():
            results[a][st.label] = row
    return results


def _cell(v: float, best: bool) -> str:
    text = "-" if not np.isfinite(v) else f"{v:.2f}"
    return f"{text}{'*' if best else ' '}"


def format_table(results: dict, metric_keys=TABLE_METRICS) -> str:
    """A text table shaped like the paper's Table II: a block of metric rows
    per setting, algorithms as columns. In every row the best value (lowest
    error, highest input coverage), as printed (two decimals, so ties are all
    marked), carries a ``*``; ``-`` means no value (e.g. no agent ever had an
    input estimate). Input coverage, not in the paper's table, is the share
    of agent-ticks over which MAE/RMSE(input) are taken."""
    algs = list(results)
    settings = list(next(iter(results.values())))
    width = max(10, *(len(PAPER_LABELS.get(a, a)) + 2 for a in algs))
    head = f"{'Comm.':<12}{'Metric':<13}" + "".join(f"{PAPER_LABELS.get(a, a):>{width}}" for a in algs)
    lines = [head, "-" * len(head)]
    for st in settings:
        for i, key in enumerate(metric_keys):
            vals = [round(float(results[a][st][key]), 2) for a in algs]
            finite = [v for v in vals if np.isfinite(v)]
            pick = max if key in HIGHER_IS_BETTER else min
            best = pick(finite) if finite else None
            cells = "".join(f"{_cell(v, v == best):>{width}}" for v in vals)
            comm = TOPOLOGY_LABELS.get(st, st) if i == 0 else ""
            lines.append(f"{comm:<12}{METRIC_LABELS.get(key, key):<13}{cells}")
        lines.append("-" * len(head))
    return "\n".join(lines)

"""Experiments: estimators x topologies (or ranges) x seeds on a scenario.

Results are plain nested dicts ``{estimator: {setting: {metric: value}}}``
(JSON-ready), with spreads over seeds under ``"<metric>_std"``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.engine import batch as engine
from diskf_mesh.engine import centralized
from diskf_mesh.data import metrics, provenance
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.scenario import TOPOLOGIES, Scenario, simulate
from diskf_mesh.estimators import Params
from diskf_mesh.mesh.wire import payloads as wire

# the label of every series a table or figure shows: each estimator's own
# (``Estimator.label``), and the centralized bound's
LABELS = {**{name: cls.label for name, cls in estimators.REGISTRY.items()}, centralized.NAME: centralized.LABEL}
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


DIVERGED = {"diverged": True, **{k: float("nan") for k in metrics.METRIC_KEYS + ("nees_observed",)}}


def diverged(est) -> bool:
    """Whether a run's estimates (``Estimates``) diverged: a value not
    finite, or a state or input estimate beyond ``wire.MAX_ABS`` (no message
    could carry it, and no target is there). A large but finite covariance
    alone is not divergence: an agent that never measures grows honestly
    uncertain."""
    with np.errstate(invalid="ignore"):
        return not (np.isfinite(est.P).all()
                    and all(bool((np.abs(a) <= wire.MAX_ABS).all()) for a in (est.x, est.d)))


def diverged_tick(est) -> int | None:
    """The first tick (from 1) at which a run's estimates diverged
    (``diverged``: in any seed or agent), or None."""
    if not diverged(est):
        return None
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(est.P).all(axis=(-2, -1))
        for a in (est.x, est.d):
            bad |= ~(np.abs(a) <= wire.MAX_ABS).all(axis=-1)
    return int(np.flatnonzero(bad.any(axis=(0, 2)))[0]) + 1


def run_or_none(trace, name: str, params: Params | None, lies=()):
    """``engine.run``, or None where the estimator diverged: its covariance
    lost positive definiteness (``numpy.linalg.LinAlgError``) or its
    estimates left the bounds of ``diverged``."""
    try:
        with np.errstate(all="ignore"):
            est = engine.run(trace, name, params, lies=lies)
    except (np.linalg.LinAlgError, FloatingPointError):
        return None
    return None if diverged(est) else est


def summarize(trace, est) -> dict:
    """{metric: pooled value, metric_std: spread over seeds} of one run."""
    return summarize_errors(*metrics.errors(trace, est))


def summarize_errors(e_state, e_in, nees) -> dict:
    """``summarize`` from the errors of a run (``metrics.errors``), computed once."""
    row = metrics.summarize(e_state, e_in, nees)
    spread = metrics.per_seed_errors(e_state, e_in, nees)
    row.update({f"{k}_std": float(np.nanstd(v)) if np.isfinite(v).any() else float("nan")
                for k, v in spread.items()})
    return row


def run_setting(scn: Scenario, setting: Setting, names, seeds, steps=None, params: Params | None = None,
                progress=None):
    """{estimator: {metric: pooled value, metric_std: spread over seeds}}"""
    return {a: rows[setting.label] for a, rows in
            run_experiment(scn, [setting], names, seeds, steps, params, progress).items()}


def batches(scns, seeds, params: Params | None = None):
    """[(params, setting indices)] that run as one batch: settings sharing
    estimator parameters, all together when their stacked links stay small
    (``engine.STACK_LINKS_MAX``), one at a time otherwise (large networks,
    whose ticks are not overhead-bound and whose traces are big)."""
    K, N = scns[0].steps, scns[0].N
    small = len(seeds) * len(scns) * K * N * N <= engine.STACK_LINKS_MAX
    groups = {}
    for i, s in enumerate(scns):
        p = params or s.params
        groups.setdefault((p, None if small else i), []).append(i)
    return [(p, idx) for (p, _), idx in groups.items()]


def run_experiment(scn: Scenario, settings, names, seeds, steps=None, params: Params | None = None,
                   progress=None, ticks=None) -> dict:
    """{estimator: {setting label: {metric: value}}} over all settings, for
    the estimators ``names``. With lies (``Scenario.lies``) the liars send
    them and the metrics cover the honest agents.

    Settings of one estimator run as one batch where they can (``batches``,
    ``engine.run_many``), so the per-tick overhead is paid once; the numbers
    are those of separate runs. ``progress``, if given, is called with 1
    after every (setting, estimator); ``ticks``, if given, with (estimator,
    ticks done) as each of its runs goes (a large network's run may take
    minutes)."""
    settings = list(settings)
    scns = [st.apply(scn, steps) for st in settings]
    for s in scns:  # before a list of the seeds is made
        s.check_size(len(seeds))
    seeds = list(seeds)
    liars = {lie.agent for lie in scn.lies}
    honest = [j for j, a in enumerate(scn.agents) if a.id not in liars]
    judged = (lambda est: est) if len(honest) == scn.N else (lambda est: est.agents(honest))
    rows = {}
    for p, idx in batches(scns, seeds, params):
        traces = [simulate(scns[i], seeds) for i in idx]
        for name in names:
            try:
                going = None if ticks is None else (lambda k, name=name: ticks(name, k))
                ests = [None if diverged(e) else e for e in engine.run_many(traces, name, p, going, lies=scn.lies)]
            except np.linalg.LinAlgError:  # diverged in one of them at least: each alone, to say which
                ests = [run_or_none(t, name, p, scn.lies) for t in traces]
            for i, trace, est in zip(idx, traces, ests):
                rows[name, i] = dict(DIVERGED) if est is None else summarize(trace, judged(est))
                if progress is not None:
                    progress(1)
    return {a: {st.label: rows[a, i] for i, st in enumerate(settings)} for a in names}


def _number(v) -> float:
    """A table value as a float; None, text or anything else is NaN (no value)."""
    if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool):
        return float(v)
    return float("nan")


def _cell(v: float, best: bool) -> str:
    text = "-" if not np.isfinite(v) else f"{v:.2f}"
    return f"{text}{'*' if best else ' '}"


def format_table(results: dict, metric_keys=TABLE_METRICS) -> str:
    """A text table shaped like the paper's Table II: a block of metric rows
    per setting, estimators as columns. In every row the best value (lowest
    error, highest input coverage), as printed (two decimals, so ties are all
    marked), carries a ``*``; ``-`` means no value (e.g. no agent ever had an
    input estimate, or a run that measured nothing: None, NaN or an absent
    key or setting all print ``-``); ``diverged``: the estimator's
    covariance diverged in that setting (``DIVERGED``). Input coverage, not in the paper's table,
    is the share of agent-ticks over which MAE/RMSE(input) are taken."""
    algs = [a for a in results if a != provenance.KEY]  # a results document's own provenance is no estimator
    settings = list(dict.fromkeys(st for a in algs for st in (results[a] or {})))
    width = max(10, *(len(LABELS.get(a, str(a))) + 2 for a in algs)) if algs else 10
    head = f"{'Comm.':<12}{'Metric':<13}" + "".join(f"{LABELS.get(a, str(a)):>{width}}" for a in algs)
    lines = [head, "-" * len(head)]
    for st in settings:
        gone = [bool(((results[a] or {}).get(st) or {}).get("diverged")) for a in algs]
        for i, key in enumerate(metric_keys):
            vals = [round(_number(((results[a] or {}).get(st) or {}).get(key)), 2) for a in algs]
            finite = [v for v in vals if np.isfinite(v)]
            pick = max if key in HIGHER_IS_BETTER else min
            best = pick(finite) if len(finite) > 1 else None  # one value is no comparison
            cells = "".join(f"{'diverged ' if g else _cell(v, v == best):>{width}}" for v, g in zip(vals, gone))
            comm = TOPOLOGY_LABELS.get(st, str(st)) if i == 0 else ""
            lines.append(f"{comm:<12}{METRIC_LABELS.get(key, key):<13}{cells}")
        lines.append("-" * len(head))
    return "\n".join(lines)

"""What the API's calls return: frozen dataclasses holding read-only numpy arrays,
each with ``to_dict()`` giving the JSON document the command line writes for
the same result (provenance included)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from diskf_mesh.data import provenance as _provenance
from diskf_mesh.data.outputs import json_safe
from diskf_mesh.data.trace import Trace, estimates_to_json
from diskf_mesh.engine.batch import Estimates


@dataclass(frozen=True)
class Run:
    """One estimator on one trace (every seed of it).

    ``x`` (B, K, N, n) fused states, ``P`` (B, K, N, n, n) their
    covariances, ``d`` (B, K, N, m) fused inputs, valid where ``d_valid``
    (B, K, N); B seeds, K ticks, N agents. ``metrics``: MAE and RMSE of
    state and input, input coverage and NEES pooled over seeds, ticks and
    agents (None when the trace has no truth). ``equal``: for the replay of
    a recording, whether it reproduced the whole recording bit for bit."""

    estimator: str
    trace: Trace
    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray
    metrics: dict[str, float] | None
    provenance: dict[str, Any]
    equal: bool | None = None

    def __post_init__(self):
        for name in ("x", "P", "d", "d_valid"):  # frozen to the arrays' elements: read-only views
            view = np.asarray(getattr(self, name)).view()
            view.flags.writeable = False
            object.__setattr__(self, name, view)

    @property
    def estimates(self) -> Estimates:
        """The arrays as the engine's ``Estimates``."""
        return Estimates(self.x, self.P, self.d, self.d_valid)

    @property
    def agents(self) -> tuple:
        """The agents' ids, in the order of the N axis."""
        return self.trace.agent_labels

    def to_dict(self, seed_index: int = 0) -> dict:
        """One seed as a ``diskf-estimates/1`` document (what ``replay --out``
        writes), with its provenance."""
        doc = estimates_to_json(self.estimates, self.estimator, seed_index, self.metrics, ids=self.agents)
        return json_safe(_provenance.attach(doc, self.provenance))


@dataclass(frozen=True)
class Experiment:
    """Estimators x settings x seeds: ``results[estimator][setting]`` is
    {metric: value pooled over the seeds, metric_std: spread over seeds}."""

    results: dict[str, dict[str, dict[str, float]]]
    provenance: dict[str, Any]

    def table(self) -> str:
        """The text table ``diskf-mesh experiment`` prints (Table II's shape)."""
        from diskf_mesh.studies.experiment import format_table

        return format_table(self.results)

    def metric(self, key: str = "mae_state") -> dict[str, dict[str, float]]:
        """{estimator: {setting: value}} of one metric."""
        return {a: {st: row.get(key) for st, row in rows.items()} for a, rows in self.results.items()}

    def to_dict(self) -> dict:
        """What ``experiment --json`` writes."""
        return json_safe(_provenance.attach(self.results, self.provenance))


@dataclass(frozen=True)
class MeshRun:
    """A ``diskf-mesh up`` run of real processes: its exit status, the
    results row (``results[estimator][setting]``), the estimates document
    (``diskf-mesh-estimates/1``) and what it printed on standard error."""

    exit_status: int
    results: dict[str, Any] | None
    estimates: dict[str, Any] | None
    stderr: str = field(repr=False, default="")

    @property
    def provenance(self) -> dict[str, Any] | None:
        return None if self.results is None else self.results.get(_provenance.KEY)

    @property
    def row(self) -> dict[str, Any] | None:
        """The run's one results row (metrics, counters, completeness)."""
        if not self.results:
            return None
        rest = _provenance.split(self.results)[1]
        return next(iter(next(iter(rest.values())).values()))

    def to_dict(self) -> dict:
        """The results document as ``up --json`` writes it."""
        return dict(self.results or {})

"""Recorded data: the ``Trace`` an engine runs on, and its JSON formats.

Every field, type and default: docs/formats.md; the JSON Schemas are
``diskf_mesh/data/schemas*.json``, and ``trace_from_json`` checks a document
against its schema before anything else.

``diskf-trace/1`` (input of ``replay``, output of ``simulate``)::

    {"format": "diskf-trace/1", "scenario": name (optional),
     "A": n x n  |  "A_seq": K x n x n,   "G": n x m,  "Q": n x n,
     "x0": n,  "P0": n x n,
     "agents": [{"id": 1, "H": p_i x n, "R": p_i x p_i}, ...],   (ids: distinct
                                                  integers in 0..2^63-1 or
                                                  names such as "drone-1")
     "y": K entries, each a list with one item per agent: p_i floats or null,
     "links": N x N (static) | K x N x N (dynamic), 0/1, diagonal 1,
     "truth": {"x": K x n, "d": K x m}          (optional; d[k-1] acts
                                                  between tick k-1 and k),
     "seed": S              (optional, >= 0; seeds GDKF's gossip draws),
     "position_dims": [0, 1] (optional; state components of the position),
     "estimator": {"window": 5, "reset": true, "eps": 0.05, ...}
                            (optional; the scenario's [estimator] settings,
                             replay's defaults)}

``diskf-estimates/1`` (output of ``replay``)::

    {"format": "diskf-estimates/1", "algorithm": ..., "ids": the trace's ids,
     "x": K x N x n, "P": K x N x n x n,
     "d": K x N x m with null where the agent has no fused input,
     "metrics": {...}                             (when truth was given)}
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np

from diskf_mesh.data import schemas
from diskf_mesh.core.errors import InputError
from diskf_mesh.core.model import LinearModel, Sensors
from diskf_mesh.estimators import SETTINGS, Params
from diskf_mesh.data.validate import agent_id, index_list, internal_ids, matrix, setting, spd, unique_ids, vector

TRACE_FORMAT = "diskf-trace/1"
ESTIMATES_FORMAT = "diskf-estimates/1"
MESH_ESTIMATES_FORMAT = "diskf-mesh-estimates/1"  # up/world --estimates: these fields and more


@dataclass(frozen=True)
class Trace:
    """Everything an estimator run needs, with a leading batch (seed) axis B.

    y:      (B, K, N, p_max) measurements, padded, zero where absent
    has:    (B, K, N) bool, agent i measured at tick k
    links:  (B or 1, K, N, N) bool, diagonal True
    truth_x (B, K, n), truth_d (B, K, m) or None
    positions (K, N, 2) agent positions, or None (not from a scenario)
    labels  the agents' ids as the user gave them (integers or names), or
            None: ``sensors.ids``. ``sensors.ids`` are the integer ids the
            run uses (``validate.internal_ids``); labels are what results,
            recordings and views show.
    """

    model: LinearModel
    sensors: Sensors
    y: np.ndarray
    has: np.ndarray
    links: np.ndarray
    truth_x: np.ndarray | None = None
    truth_d: np.ndarray | None = None
    positions: np.ndarray | None = None
    seeds: tuple = (0,)
    position_dims: tuple = (0, 1)
    labels: tuple | None = None

    @property
    def agent_labels(self) -> tuple:
        """Every agent's id as the user gave it, in the order of the N axis."""
        return tuple(self.sensors.ids) if self.labels is None else tuple(self.labels)

    @property
    def shape(self):
        """(B, K, N)"""
        return self.has.shape

    def with_links(self, links: np.ndarray) -> "Trace":
        from dataclasses import replace
        return replace(self, links=links)


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------
def read_json(path) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except OSError as e:
        raise InputError("file", f"cannot read {path}: {e.strerror or e}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError("file", f"{path} is not valid JSON: {e}") from None


def trace_from_json(doc: dict) -> Trace:
    """The ``Trace`` of a diskf-trace/1 document: its schema first (types,
    required fields), then what a schema cannot say (shapes that depend on
    each other, symmetric positive-definite covariances, distinct ids)."""
    schemas.check(doc, TRACE_FORMAT)
    G = matrix(doc.get("G"), "G")
    n, m = G.shape
    Q = spd(matrix(doc.get("Q"), "Q", (n, n)), "Q")
    P0 = spd(matrix(doc.get("P0"), "P0", (n, n)), "P0")
    x0 = vector(doc.get("x0"), "x0", n)

    ys = doc["y"]
    K = len(ys)
    if "A_seq" in doc:
        try:
            A = np.asarray(doc["A_seq"], dtype=float)
        except ValueError:
            raise InputError("A_seq", "must be K matrices of n x n numbers (a ragged array was given)") from None
        if A.shape != (K, n, n):
            raise InputError("A_seq", f"must be {K}x{n}x{n} (K ticks), got {'x'.join(map(str, A.shape))}")
        if not np.isfinite(A).all():
            raise InputError("A_seq", "contains NaN or infinity")
    else:
        A = np.broadcast_to(matrix(doc.get("A"), "A", (n, n)), (K, n, n))

    labels, Hs, Rs = [], [], []
    for i, a in enumerate(doc["agents"]):
        H = matrix(a.get("H"), f"agents[{i}].H", (None, n))
        R = spd(matrix(a.get("R"), f"agents[{i}].R", (H.shape[0], H.shape[0])), f"agents[{i}].R")
        labels.append(agent_id(a.get("id", i + 1), f"agents[{i}].id"))
        Hs.append(H)
        Rs.append(R)
    labels = unique_ids(labels, "agents.id")
    sensors = Sensors.from_list(internal_ids(labels), Hs, Rs)
    N, pmax = sensors.N, sensors.H.shape[1]

    y = np.zeros((1, K, N, pmax))
    has = np.zeros((1, K, N), dtype=bool)
    for k, row in enumerate(ys):
        if len(row) != N:
            raise InputError(f"y[{k}]", f"must be a list with one item per agent ({N})")
        for i, v in enumerate(row):
            if v is None:
                continue
            vv = vector(v, f"y[{k}][{i}]", int(sensors.p[i]))
            y[0, k, i, : sensors.p[i]] = vv
            has[0, k, i] = True

    try:
        L = np.asarray(doc["links"], dtype=float)
    except ValueError:
        raise InputError("links", "must be a 0/1 matrix (N x N) or K of them (a ragged array was given)") from None
    if L.shape == (N, N):
        L = np.broadcast_to(L, (K, N, N))
    elif L.shape != (K, N, N):
        raise InputError("links", f"must be {N}x{N} or {K}x{N}x{N}, got {'x'.join(map(str, L.shape)) or 'a scalar'}")
    if not (np.diagonal(L, axis1=-2, axis2=-1) == 1).all():
        raise InputError("links", "the diagonal must be 1 (every agent hears itself)")
    links = (L > 0)[None]

    truth_x = truth_d = None
    truth = doc.get("truth")
    if truth is not None:
        truth_x = matrix(truth.get("x"), "truth.x", (K, n))[None]
        truth_d = matrix(truth.get("d"), "truth.d", (K, m))[None]
    model = LinearModel(np.ascontiguousarray(A), G, Q, x0, P0)
    seed = setting(doc, "seed", "", int, 0, low=0)
    return Trace(model, sensors, y, has, links, truth_x, truth_d, None, (int(seed),),
                 index_list(doc.get("position_dims", list(range(min(n, 2)))), "position_dims", n), labels)


def estimator_from_json(doc: dict) -> Params:
    """The estimator settings a diskf-trace/1 document carries (its
    scenario's ``[estimator]``), ``Params()`` for the ones it does not."""
    given = dict(doc.get("estimator", {}))
    for key, value in given.items():
        s = SETTINGS.get(key)
        if s is not None and s.table and isinstance(value, dict):  # the schema made it an object of booleans
            given[key] = s.type(**value)
        elif s is not None and s.type is int and isinstance(value, float) and value.is_integer():
            given[key] = int(value)  # the schema allows 5.0 for an integer
    try:
        return Params(**given)
    except ValueError as e:
        field, _, msg = str(e).partition(": ")
        raise InputError(f"estimator.{field}", msg) from None


def read_trace_file(path) -> tuple[dict, Trace]:
    """(the document, its ``Trace``) of a diskf-trace/1 file; an error
    names the field, then the file (``error: G: is missing (in t.json)``)."""
    doc = read_json(path)
    try:
        return doc, trace_from_json(doc)
    except InputError as e:
        raise InputError(e.field, f"{e.message} (in {path})") from None


def load_trace(path) -> Trace:
    return read_trace_file(path)[1]


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------
def _json_id(i):
    """An agent id for JSON: a numpy integer as an int, a name as it is."""
    return int(i) if isinstance(i, (int, np.integer)) else i


def trace_to_json(tr: Trace, b: int = 0, scenario: str | None = None, params: Params | None = None) -> dict:
    """The ``b``-th seed of a trace as a diskf-trace/1 document, with the
    name of the ``scenario`` and the estimator ``params`` it came with."""
    s = tr.sensors
    K = tr.y.shape[1]
    A = tr.model.A
    doc = {"format": TRACE_FORMAT} | ({"scenario": scenario} if scenario is not None else {})
    doc["seed"] = int(tr.seeds[b])
    if np.all(A == A[0]):
        doc["A"] = A[0].tolist()
    else:
        doc["A_seq"] = A.tolist()
    doc.update(G=tr.model.G.tolist(), Q=tr.model.Q.tolist(), x0=tr.model.x0.tolist(), P0=tr.model.P0.tolist())
    doc["agents"] = [
        {"id": _json_id(i),
         "H": s.H[j, : s.p[j]].tolist(), "R": s.R[j, : s.p[j], : s.p[j]].tolist()}
        for j, i in enumerate(tr.agent_labels)
    ]
    doc["y"] = [
        [tr.y[b, k, i, : s.p[i]].tolist() if tr.has[b, k, i] else None for i in range(s.N)]
        for k in range(K)
    ]
    L = tr.links[min(b, tr.links.shape[0] - 1)].astype(int)
    doc["links"] = L[0].tolist() if np.all(L == L[0]) else L.tolist()
    doc["position_dims"] = list(tr.position_dims)
    if tr.truth_x is not None:
        doc["truth"] = {"x": tr.truth_x[b].tolist(), "d": tr.truth_d[b].tolist()}
    if params is not None:
        doc["estimator"] = asdict(params)
    return doc


def estimates_to_json(est, algorithm: str, b: int = 0, metrics: dict | None = None, ids=None) -> dict:
    """The ``b``-th seed of ``est`` as a diskf-estimates/1 document; ``ids``:
    the agents' ids as the user gave them (``Trace.agent_labels``)."""
    d = np.where(est.d_valid[b][..., None], est.d[b], np.nan)
    doc = {
        "format": ESTIMATES_FORMAT,
        "algorithm": algorithm,
        **({} if ids is None else {"ids": [_json_id(i) for i in ids]}),
        "x": est.x[b].tolist(),
        "P": est.P[b].tolist(),
        "d": [[None if np.isnan(row[0]) else row.tolist() for row in tick] for tick in d],
    }
    if metrics is not None:
        doc["metrics"] = metrics
    return doc

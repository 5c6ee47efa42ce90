"""What every estimator shares: its declaration, state, prediction and the
local step. The interface a new estimator implements is ``Estimator``
(docs/estimators.md).

An estimator is two pure functions per tick, split at the single exchange
round (Algorithm 1, step 2):

    local(state, k, y, has)          -> (state, Message)   before sending
    fuse(state, own, senders, nbhd)  -> (state, Output)    after receiving

Arrays carry leading batch axes (seeds, agents). The in-process engine calls
them on every agent at once; an agent process calls them on a batch of one,
with the messages it actually received as ``senders``.

Everything else the engine, the mesh and the studies need to know about an
estimator it declares on its class: ``name``, ``label``, ``color``, its
parameters (``settings``, a tuple of ``Setting``), what its message
carries (``exchanged``, a tuple of ``Exchanged``: the wire encoding and the
guard's checks follow from it), and the hooks
``draws`` (per-tick randomness), ``information_check`` (the guard's check of
a sender's update) and ``warning`` (a stability warning before a run).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.core import equations as eq
from diskf_mesh.core import input_models as im
from diskf_mesh.core import resilience as rs
from diskf_mesh.core.linalg import inv_spd, inv_spd_each
from diskf_mesh.core.messages import Message, Neighbourhood
from diskf_mesh.core.model import LinearModel, Sensors


@dataclass(frozen=True)
class Setting:
    """One parameter of an estimator, declared once on its class.

    It is read from the scenario's ``[estimator]`` table (key ``name``), from
    the command line (``--name`` with dashes, for scalar kinds) and from a
    trace's ``estimator`` object, and is a field of ``estimators.Params``
    (every registered estimator's settings; an estimator reads its own as
    ``self.params.<name>``). Estimators sharing a parameter share its
    ``Setting`` object (DISKF's window, eps, ... in diskf-r).

    kind:     bool, int, float, str, or a frozen dataclass of booleans
              (a sub-table ``[estimator.<name>]``); default: type(default)
    low:      numbers: the smallest value allowed (inclusive)
    choices:  strings: the values allowed
    optional: None is a value ("none" in TOML and on the command line)
    """

    name: str
    default: object
    doc: str
    kind: type | None = None
    low: float | None = None
    choices: tuple | None = None
    optional: bool = False

    @property
    def type(self) -> type:
        return self.kind or type(self.default)

    @property
    def table(self) -> bool:
        """A sub-table of switches (a dataclass), not a scalar."""
        return dataclasses.is_dataclass(self.type)

    @property
    def flag(self) -> str:
        return "--" + self.name.replace("_", "-")

    def check(self, value):
        """``value`` if it is allowed, else ValueError ``"name: must be ..."``."""
        kind, what = self.type, None
        if value is None:
            what = None if self.optional else "not None"
        elif self.table:
            what = None if isinstance(value, kind) else f"a {kind.__name__}"
        elif kind is bool:
            what = None if isinstance(value, (bool, np.bool_)) else "true or false"
        elif kind is str:
            what = None if isinstance(value, str) and (self.choices is None or value in self.choices) else (
                f"one of {', '.join(self.choices)}" if self.choices else "a string")
        else:
            number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
            if not number or not math.isfinite(value) or (kind is int and int(value) != value):
                what = "an integer" if kind is int else "a finite number"
            elif self.low is not None and value < self.low:
                what = f">= {self.low:g}"
            if what and self.low == 0:
                what = "a non-negative integer" if kind is int else "a finite non-negative number"
            if what and self.optional:
                what += " or None"
        if what:
            raise ValueError(f"{self.name}: must be {what}, got {value!r}")
        return value

    def from_text(self, text: str):
        """A command-line value (``none`` for None where optional)."""
        t = text.strip()
        if self.optional and t.lower() == "none":
            return None
        kind = self.type
        try:
            if kind is bool:
                value = {"true": True, "on": True, "1": True, "false": False, "off": False, "0": False}[t.lower()]
            elif kind in (int, float):
                value = kind(t)
            else:
                value = t
        except (KeyError, ValueError):
            value = t
        try:
            return self.check(value)
        except ValueError as e:
            raise ValueError(str(e).partition(": ")[2].replace("None", "'none'")) from None


@dataclass(frozen=True)
class Exchanged:
    """One array of the message an estimator's agents exchange (a field of
    ``Message``), declared once on its class (``Estimator.exchanged``).

    The wire (``diskf_mesh.mesh.wire.codec``) sends the declared arrays, in their
    order, as one float64 byte string, whole and row-major; the receiving
    agent's guard (``diskf_mesh.mesh.protocol.guard``) checks every value for
    finiteness and magnitude, and every covariance for symmetry, positive
    definiteness and conditioning. ``Message.d_valid`` always travels (a
    flag). A ``Message`` array an estimator does not declare does not travel:
    a receiving agent's senders hold zeros there.

    name:      the ``Message`` field
    shape:     "n", "n n", "m" or "m m": in the state (n) and input (m)
               dimensions; or a count ("8"): a vector of that many values
    update_of: a covariance that is the sender's information update of the
               named one (P~ of P^): the guard checks it is at least as
               certain (``Estimator.information_check``)
    weights:   a vector of probabilities: the guard checks every value is
               in [0, 1] and that they sum to 1
    """

    name: str
    shape: str
    update_of: str | None = None
    weights: bool = False

    @property
    def covariance(self) -> bool:
        """A square matrix: checked symmetric positive definite and conditioned."""
        return len(self.shape.split()) == 2

    def dims(self, n: int, m: int) -> tuple:
        """The array's shape for state dimension ``n`` and input dimension ``m``."""
        return tuple({"n": n, "m": m}[d] if d in ("n", "m") else int(d) for d in self.shape.split())


# Algorithm 1, step 2: what every built-in estimator exchanges (``Message``'s arrays)
EXCHANGED = (
    Exchanged("x_pred", "n"), Exchanged("P_pred", "n n"),
    Exchanged("x_upd", "n"), Exchanged("P_upd", "n n", update_of="P_pred"),
    Exchanged("d", "m"), Exchanged("S", "m m"),
)


def check_exchanged(cls) -> None:
    """ValueError unless ``cls.exchanged`` declares ``Message`` arrays, each
    once, in the shapes ``Exchanged`` knows, with an n and an m axis among
    them and every ``update_of`` a declared covariance."""
    ex = cls.exchanged
    if not isinstance(ex, tuple) or not ex or not all(isinstance(f, Exchanged) for f in ex):
        raise ValueError(f"{cls.name}: exchanged must be a non-empty tuple of Exchanged")
    names = [f.name for f in ex]
    bad = [n for n in names if n not in Message.ARRAY_FIELDS or names.count(n) > 1]
    if bad:
        raise ValueError(f"{cls.name}: exchanged {bad[0]!r}: each must be one of {', '.join(Message.ARRAY_FIELDS)}, once")
    if any(f.shape not in ("n", "n n", "m", "m m") and not (f.shape.isdigit() and 1 <= int(f.shape) <= 64)
           for f in ex):
        raise ValueError(f"{cls.name}: an exchanged shape is one of 'n', 'n n', 'm', 'm m' or a count 1 .. 64")
    if any(f.weights and not f.shape.isdigit() for f in ex):
        raise ValueError(f"{cls.name}: exchanged weights are a vector of a given count")
    axes = {d for f in ex for d in f.shape.split() if not d.isdigit()}
    if axes != {"n", "m"}:
        raise ValueError(f"{cls.name}: the exchanged arrays must have an n axis and an m axis among them")
    covs = {f.name: f.shape for f in ex if f.covariance}
    for f in ex:
        if f.update_of is not None and (not f.covariance or covs.get(f.update_of) != f.shape):
            raise ValueError(f"{cls.name}: {f.name} is an update of {f.update_of!r}, a declared covariance of its shape")


@dataclass(frozen=True)
class State:
    x: np.ndarray      # (..., n)   x_bar_{k|k}, the fused estimate
    P: np.ndarray      # (..., n, n)
    since: np.ndarray  # (...,) ticks since the observation window was refreshed
    # Set by ``local`` for the ``fuse`` of the same tick, which then need not
    # invert the agent's own P^ again: P^^-1 (None otherwise).
    # Keyword-only, so an estimator's own state (a subclass) lists its
    # fields positionally after ``since``.
    Y_pred: np.ndarray | None = field(default=None, kw_only=True)
    # The evidence against each agent of the run as a neighbour (..., N),
    # ``core.resilience.accumulate``; None until the first screened fusion
    # (``Estimator.screened_fuse``), as all zeros.
    evidence: np.ndarray | None = field(default=None, kw_only=True)


DEFENCE = Setting("defence", False, "screen every neighbour's message before fusing it (core.resilience): a "
                  "prediction more certain than Q, or far outside the chi-square gate around the receiver's own "
                  "prediction (or the median of three or more), is not fused, and evidence against its sender "
                  "accumulates and recovers slowly; off by default: on clean runs it cuts honest neighbours in "
                  "some held-out cases (docs/security.md)")


@dataclass(frozen=True)
class Local:
    """Quantities of the local step, shared by all estimators."""

    x_pred: np.ndarray
    P_pred: np.ndarray
    U: np.ndarray
    u: np.ndarray
    x_upd: np.ndarray
    P_upd: np.ndarray
    Y: np.ndarray   # P^^-1, computed once for the whole tick
    Ji: np.ndarray  # (P^^-1 + U)^-1, P~ before the "no measurement" mask


class Estimator:
    """Base class of every estimator, built-in or plugin: a subclass sets
    the declaration below and implements ``local`` and ``fuse``.

    ``params`` is an ``estimators.Params`` (the scenario's ``[estimator]``
    table); ``None``: every setting at its default."""

    name: str = ""            # the registry's key, the CLI's --estimator value
    label: str = ""           # in tables, legends and reports
    color: str | None = None  # a matplotlib colour for its curves (None: the cycle's)
    settings: tuple = ()      # its ``Setting``s
    exchanged: tuple = EXCHANGED  # its message's arrays (``Exchanged``), in wire order
    extends: str | None = None    # the estimator this one extends, if any (its family, in reports)
    # The guard checks that a sender's (x~, P~) is an information update of
    # its (x^, P^) (P~ <= P^); off for estimators whose x~ is something else
    # (L-DRKF sends its RKF estimate there).
    information_check: bool = True

    def __init__(self, model: LinearModel, sensors: Sensors, params=None):
        if params is None:
            from diskf_mesh.estimators import Params  # the registry's, with every registered setting
            params = Params()
        self.model = model
        self.sensors = sensors
        self.params = params
        self.sensor_info = eq.sensor_information(sensors.H, sensors.R)  # constant per agent

    # -- hooks -----------------------------------------------------------
    def draws(self, seed: int, agent_ids, steps: int) -> np.ndarray | None:
        """Per-tick randomness: (N, steps) uniform draws, one stream per
        agent seeded by (run seed, agent id), or None (the default). The
        engine and the agent process hand tick k's draw of each receiver to
        ``fuse`` as ``Neighbourhood.draws``; each agent process makes its own
        row, so both see the same numbers."""
        return None

    @classmethod
    def warning(cls, params, links: np.ndarray) -> str | None:
        """Why a run with ``params`` on ``links`` (..., N, N) may go wrong
        (printed as a warning before it starts), or None."""
        return None

    @classmethod
    def refuse(cls, params, model: LinearModel, sensors: Sensors) -> tuple | None:
        """A setting of ``params`` that cannot work with this model and
        these sensors, as (field, why), or None. Checked before any run
        (loading a scenario, ``engine.run``): one error line, exit 2."""
        return None

    # -- helpers ---------------------------------------------------------
    def init(self, batch: tuple) -> State:
        """Every agent starts from the common prior (x0, P0) (Algorithm 1)."""
        n = self.model.n
        x = np.broadcast_to(self.model.x0, batch + (n,)).astype(float).copy()
        P = np.broadcast_to(self.model.P0, batch + (n, n)).astype(float).copy()
        return State(x, P, np.zeros(batch, dtype=np.int64))

    def local_kf(self, state: State, k: int, y, has, weight=None) -> Local:
        """Prediction (info_kf_prediction0) and local update (info_kf_update0);
        ``weight`` (...,), if given, multiplies the measurement's information
        (a measurement noise taken as R / weight)."""
        x_pred, P_pred = eq.predict(state.x, state.P, self.model.A_at(k), self.model.Q)
        U, u = eq.measurement_information(self.sensor_info, y, has)
        if weight is not None:
            U, u = U * weight[..., None, None], u * weight[..., None]
        Y, Ji = eq.information_pair(P_pred, U)
        x_upd, P_upd = eq.local_update(x_pred, P_pred, Y, Ji, u, has)
        return Local(x_pred, P_pred, U, u, x_upd, P_upd, Y, Ji)

    @staticmethod
    def for_fuse(state: State, loc: Local) -> State:
        """``state`` after the local step: with the local step's P^^-1 for
        ``fusion_inverses``. An estimator with a state of its own (a subclass
        of ``State``) builds it with ``Y_pred``."""
        return State(state.x, state.P, state.since, Y_pred=loc.Y)

    @staticmethod
    def fusion_inverses(state: State, own: Message, senders: Message):
        """(P^*^-1 of each receiver, P^_j^-1 and P~_j^-1 of each sender),
        every one inverted once per tick.

        A receiver's own P^^-1 comes from its local step (``State.Y_pred``);
        when the senders are the receivers themselves (the engine's dense
        layout), so do theirs. Otherwise they are inverted, in one stacked
        call, from the messages (as an agent process receives them)."""
        Y = state.Y_pred
        if Y is None:
            if senders is own:
                Y, Yu = inv_spd_each(own.P_pred, own.P_upd)
                return Y, Y, Yu
            return inv_spd_each(own.P_pred, senders.P_pred, senders.P_upd)
        if senders is own:
            return Y, Y, inv_spd(own.P_upd)
        Yp, Yu = inv_spd_each(senders.P_pred, senders.P_upd)
        return Y, Yp, Yu

    def local_input(self, loc: Local, allowed=None):
        """The agent's own RKF input estimate (input_estimation)."""
        return eq.input_estimate(loc.x_pred, loc.Y, loc.Ji, loc.U, loc.u, self.model.G, allowed)

    @staticmethod
    def message(loc: Local, d, S, valid, x_upd=None, P_upd=None) -> Message:
        return Message(
            loc.x_pred, loc.P_pred,
            loc.x_upd if x_upd is None else x_upd,
            loc.P_upd if P_upd is None else P_upd,
            d, S, valid,
        )

    # -- screening the senders (``core.resilience``) ----------------------
    @property
    def defends(self) -> bool:
        """Whether this estimator screens its senders: it declares
        ``DEFENCE`` and the setting is on."""
        return DEFENCE in type(self).settings and bool(getattr(self.params, "defence", False))

    def screened_fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        """``fuse`` of the senders that pass the screen (``screen``), the
        evidence against each kept in the state; ``fuse`` itself where the
        estimator does not defend itself. The engine and the agent process
        call this."""
        if not self.defends:
            return self.fuse(state, own, senders, nb)
        weights, evidence = self.screen(state, own, senders, nb)
        if weights is not nb.adj:
            nb = Neighbourhood(weights, nb.self_mask, nb.draws, nb.columns)
        st, out = self.fuse(state, own, senders, nb)
        return dataclasses.replace(st, evidence=evidence), out

    def screen(self, state: State, own: Message, senders: Message, nb: Neighbourhood):
        """(the adjacency with every sender that fails the screen or is
        distrusted at 0, nb.adj itself when none is; the evidence after this
        tick): ``core.resilience``'s floor, gate and evidence on the state
        predictions and the input estimates. A sender passes the gate where
        it is close to the receiver's own prediction or, with three or more
        reporting, to their median."""
        adj = nb.adj
        linked = nb.linked
        evidence = state.evidence
        if evidence is None:
            evidence = np.zeros(state.x.shape[:-1] + (self.sensors.whole.N,))
        if not linked.any():
            return adj, evidence
        gate, allowance, limit, suspect = rs.thresholds()
        flat, si, ri = nb.linked_pairs  # the linked pairs, as flat indices into senders and receivers
        take = rs.take
        floor = take(rs.below_floor(senders.P_pred, self.model.Q), si, 0)
        P_send, P_own = take(senders.P_pred, si, 2), take(own.P_pred, ri, 2)
        x_send = take(senders.x_pred, si, 1)
        q_own, = rs.gate_statistics(x_send, P_send, (take(own.x_pred, ri, 1),), P_own)
        d_valid = take(senders.d_valid, si, 0) & take(own.d_valid, ri, 0)
        if d_valid.any():  # the input estimates, where both sides have one
            d_send, S_send, S_own = take(senders.d, si, 1), take(senders.S, si, 2), take(own.S, ri, 2)
            qd_own, = rs.input_gate_statistics(d_send, S_send, (take(own.d, ri, 1),), S_own, d_valid)
        else:
            qd_own = None
        if rs.nothing_grows(evidence, floor, q_own, qd_own, allowance):
            return adj, evidence  # the statistics against the medians are no larger: nothing changes
        before = rs.columns_of(evidence, nb.columns)
        median = rs.reference(adj > 0, senders.x_pred, own.x_pred)
        q_med, = rs.gate_statistics(x_send, P_send, (take(median, ri, 1),), P_own)
        q = np.minimum(q_own, q_med)
        failed = (q > gate) | floor
        if qd_own is not None:
            d_med = rs.reference((adj > 0) & np.expand_dims(senders.d_valid, -2), senders.d, own.d)
            qd_med, = rs.input_gate_statistics(d_send, S_send, (take(d_med, ri, 1),), S_own, d_valid)
            qd = np.minimum(qd_own, qd_med)
            failed |= qd > gate
            q = np.maximum(q, qd)
        step = np.zeros(linked.size)
        step[flat] = q
        step = step.reshape(linked.shape)
        hit = np.zeros(linked.size, dtype=bool)
        hit[flat] = failed
        hit = hit.reshape(linked.shape)
        after = rs.accumulate(before, step, hit, allowance, suspect)
        evidence = rs.put_columns(evidence, nb.columns, after, linked)
        cut = linked & (after >= limit)
        if not cut.any():
            return adj, evidence
        return np.where(cut, 0.0, adj), evidence

    # -- interface -------------------------------------------------------
    def local(self, state: State, k: int, y, has):  # pragma: no cover - abstract
        raise NotImplementedError

    def fuse(self, state: State, own: Message, senders: Message, nb: Neighbourhood):  # pragma: no cover
        raise NotImplementedError


def run_scales(model: LinearModel, sensors: Sensors) -> tuple:
    """``input_models.input_scales`` of ``model`` over every sensor of the
    run (``Sensors.whole``: an agent's own sensor takes the run's scales, as
    the engine does), computed once per run's sensors and model noise and
    kept with the sensors (``Sensors.derived``): a run of N agents builds N
    estimators."""
    run = sensors.whole
    key = ("input_scales", id(model.Q), id(model.G))
    hit = run.derived.get(key)
    if hit is None or hit[0] is not model.Q or hit[1] is not model.G:
        hit = run.derived[key] = (model.Q, model.G, im.input_scales(model.Q, model.G, run.H, run.R, run.p))
    return hit[2]


def uniform_weights(adj: np.ndarray) -> np.ndarray:
    """Row-normalised adjacency: equal weight to every fused neighbour."""
    deg = adj.sum(axis=-1, keepdims=True)
    return adj / np.where(deg > 0, deg, 1.0)

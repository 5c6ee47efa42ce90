"""DISKF one tick at a time, for loops that produce their own measurements
and links (a robot's node, a simulator's step).

Two levels, each calling the estimator functions the engine calls:

``Network``  every agent of a scenario in one object: one tick's measurements
             (and links) in, every agent's estimate with its covariance out.
             The engine's per-tick step (``engine.batch.Stepper``) on a batch
             of one seed.
``Agent``    one agent: ``local`` on its own measurement returns the one
             message it sends; ``fuse`` over the messages it received returns
             its estimate. What an agent process runs
             (``mesh.protocol.estimator.AgentEstimator``); the messages are
             yours to carry, as ``Message`` objects or as bytes
             (``Agent.encode``, the mesh's wire format).

On the same measurements and links both give what ``estimate`` (the batched
engine) gives, bit for bit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence, Union

import numpy as np

from diskf_mesh import estimators as _estimators
from diskf_mesh.core.errors import InputError
from diskf_mesh.core.messages import Message, Output
from diskf_mesh.data import scenario as _scenario
from diskf_mesh.engine.batch import Stepper
from diskf_mesh.estimators import Params
from diskf_mesh.mesh.protocol.estimator import AgentEstimator
from diskf_mesh.mesh.wire import codec

Measurement = Union[Sequence[float], np.ndarray, None]


@dataclass(frozen=True)
class Estimate:
    """The fused estimates after one tick (read-only arrays).

    For a ``Network``, one row per agent in the order of ``Network.ids``:
    ``x`` (N, n), ``P`` (N, n, n), ``d`` (N, m), ``d_valid`` (N,). For an
    ``Agent``, that agent's alone: ``x`` (n,), ``P`` (n, n), ``d`` (m,),
    ``d_valid`` a bool. ``d`` (the input estimate of tick k - 1) means
    something only where ``d_valid``."""

    tick: int
    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray | bool


def _frozen(out: Output, k: int, index) -> Estimate:
    parts = []
    for a in (out.x, out.P, out.d, out.d_valid):
        a = np.array(a[index])
        a.flags.writeable = False
        parts.append(a)
    if parts[3].ndim == 0:
        parts[3] = bool(parts[3])
    return Estimate(k, *parts)


def _setup(scenario, estimator: str, settings, ticks: int | None):
    """(scenario, estimator name, settings, horizon) checked, as the API's calls check them."""
    from diskf_mesh.api.calls import _estimator, _params, load_scenario

    scn = load_scenario(scenario)
    params = _params(scn.params, settings)
    name = _estimator(estimator)
    K = scn.steps if ticks is None else int(ticks)
    if K < 1:
        raise InputError("ticks", f"must be at least 1, got {ticks}")
    model = scn.model(K)
    refused = _estimators.get(name).refuse(params, model, scn.sensors())
    if refused:
        raise InputError(*refused)
    return scn, name, params, K, model


def _next_tick(k: int, K: int) -> int:
    if k >= K:
        raise InputError("ticks", f"the horizon of {K} ticks is reached; make the object with a larger ticks=")
    return k + 1


class Network:
    """Every agent of ``scenario`` (a shipped name, a TOML path or a
    ``Scenario``), one tick at a time.

    ``estimator``: a registered name; ``settings``: estimator settings to
    change (a mapping, or a whole ``Params``); ``seed``: the run's seed (an
    estimator's own draws, e.g. GDKF's gossip, follow it); ``ticks``: the
    horizon, at most this many ``step`` calls (default: the scenario's)::

        net = Network("quadrants", "diskf")
        est = net.step([[0.3], [0.1], None, [0.2]])   # agent 3 measured nothing
        est.x.shape, est.P.shape                      # (4, 2), (4, 2, 2)
    """

    def __init__(self, scenario, estimator: str = _estimators.DEFAULT, *,
                 settings: Params | Mapping[str, Any] | None = None, seed: int = 0, ticks: int | None = None,
                 neighbours: str = "auto"):
        self.scenario, self.estimator, self.settings, self.ticks, model = _setup(scenario, estimator, settings,
                                                                                 ticks)
        self.sensors = self.scenario.sensors()
        self._steps = Stepper(model, self.sensors, self.estimator, self.settings, [int(seed)], self.ticks,
                              neighbours)
        self._links = None

    @property
    def ids(self) -> tuple:
        """The agents' ids as the scenario gives them (integers or names), in
        the order of every per-agent row."""
        return self.scenario.labels

    @property
    def tick(self) -> int:
        """The last tick done (0 before the first ``step``)."""
        return self._steps.k

    def step(self, y, has=None, *, links=None, positions=None) -> Estimate:
        """One tick: every agent's local step on its measurement, the
        exchange, and fusion.

        ``y``: one row per agent (in ``ids`` order), each a vector of that
        agent's length p (its sensor's rows) or of the longest p (padded), or
        None for no measurement. ``has`` (N,) bool, if given, says which rows
        are measurements. ``links`` (N, N), truthy where agent i fuses agent
        j's message (itself always); else ``positions`` (N, 2) gate them by
        the scenario's topology and range; else the scenario's own links at
        this tick."""
        k = _next_tick(self.tick, self.ticks)
        yy, hh = self._measurements(y, has)
        links = self._links_at(k, links, positions)
        changed = self._links is None or not np.array_equal(links, self._links)
        if changed:
            self._links = links
        out = self._steps.step(yy[None], hh[None], links[None] if changed else None)
        return _frozen(out, k, 0)

    def _measurements(self, y, has) -> tuple:
        N, P = len(self.ids), self.sensors.H.shape[1]
        rows = list(y) if y is not None else [None] * N
        if len(rows) != N:
            raise InputError("y", f"one row per agent: {N} rows, got {len(rows)}")
        out = np.zeros((N, P))
        got = np.zeros(N, dtype=bool)
        for i, row in enumerate(rows):
            if row is None:
                continue
            v = np.asarray(row, dtype=float).reshape(-1)
            p = int(self.sensors.p[i])
            if v.size not in (p, P):
                raise InputError(f"y[{i}]", f"agent {self.ids[i]} measures {p} values, got {v.size}")
            if not np.isfinite(v[:p]).all():
                raise InputError(f"y[{i}]", "not finite")
            out[i, :p] = v[:p]
            got[i] = True
        if has is not None:
            has = np.asarray(has, dtype=bool).reshape(-1)
            if has.shape != (N,):
                raise InputError("has", f"one flag per agent: {N}, got {has.size}")
            if (has & ~got).any():
                raise InputError("has", f"agent {self.ids[int(np.argmax(has & ~got))]} has no measurement row")
            got = has
        return out, got

    def _links_at(self, k: int, links, positions) -> np.ndarray:
        N = len(self.ids)
        if links is not None:
            a = np.asarray(links)
            if a.shape != (N, N):
                raise InputError("links", f"must be {N} x {N}, got shape {a.shape}")
            return a.astype(bool) | np.eye(N, dtype=bool)
        scn = self.scenario
        if positions is None:
            positions = scn.positions_at([k])[0]
        positions = np.asarray(positions, dtype=float)
        if positions.shape != (N, 2):
            raise InputError("positions", f"must be {N} x 2, got shape {positions.shape}")
        return _scenario.links_for(scn, positions[None])[0]


class Agent:
    """One agent (``agent_id``, its id in ``scenario``: an integer or a name)
    of a network whose messages you carry: each tick, ``local`` then ``fuse``.

    The arguments are ``Network``'s. Messages are ``Message`` objects of
    unbatched arrays; ``encode`` makes bytes of one (the mesh's wire format,
    about 160 bytes for n = 2, m = 1) and ``fuse`` takes bytes as well::

        a = Agent("quadrants", 1, "diskf")
        msg = a.local([0.3])              # send msg (or a.encode(msg)) to your neighbours
        est = a.fuse({2: message_from_2})  # what you received this tick, by sender id
    """

    RUN_ID = "stream"  # the run id in the bytes of ``encode`` (the wire format names one)

    def __init__(self, scenario, agent_id: int | str, estimator: str = _estimators.DEFAULT, *,
                 settings: Params | Mapping[str, Any] | None = None, seed: int = 0, ticks: int | None = None):
        scn, name, params, self.ticks, _ = _setup(scenario, estimator, settings, ticks)
        self._internal = {a.name: a.id for a in scn.agents}  # the scenario's ids -> the run's integer ids
        if agent_id not in self._internal:
            raise InputError("agent_id", f"{agent_id!r} is not an agent of {scn.name!r} "
                                         f"(ids {', '.join(map(str, self._internal))})")
        self._agent = AgentEstimator(scn, self._internal[agent_id], _estimators.get(name), self.ticks, int(seed),
                                     params)
        self.scenario, self.estimator, self.settings = scn, name, params
        self.id = agent_id
        self._tick = 0
        self._own = None  # this tick's message, between ``local`` and ``fuse``

    @property
    def tick(self) -> int:
        """The last tick whose ``local`` step was done (0 before the first)."""
        return self._tick

    def local(self, y: Measurement = None) -> Message:
        """The next tick's local step on this agent's measurement (a vector of
        its p values, or None for none): the message to send."""
        if self._own is not None:
            raise InputError("local", f"tick {self._tick}: call fuse before the next local step")
        k = _next_tick(self._tick, self.ticks)
        p = self._agent.p
        if y is not None:
            y = np.asarray(y, dtype=float).reshape(-1)
            if y.size != p or not np.isfinite(y).all():
                raise InputError("y", f"agent {self.id} measures {p} finite values, got {y.tolist()}")
        self._own = self._agent.local(k, y is not None, y)
        self._tick = k
        return self._own.take((0, 0))

    def encode(self, msg: Message) -> bytes:
        """``msg`` (this agent's, of this tick) in the mesh's wire format."""
        return codec.encode(self.RUN_ID, self._agent.agent_id, self._tick, msg, self._agent.alg.exchanged)

    def fuse(self, received: Mapping[int, Message | bytes]) -> Estimate:
        """This tick's fusion over ``received`` {sender id: its message of
        this tick, as a ``Message`` or as ``encode``'s bytes} (this agent's
        own, if present, is ignored): this agent's estimate."""
        if self._own is None:
            raise InputError("fuse", f"tick {self._tick + 1}: call local first")
        msgs = {}
        for j, m in received.items():
            if j not in self._internal:
                raise InputError(f"received[{j!r}]", f"sender {j!r} is not an agent of {self.scenario.name!r}")
            msgs[self._internal[j]] = self._decode(j, m) if isinstance(m, (bytes, bytearray, memoryview)) else m
        out = self._agent.fuse(self._tick, self._own, msgs)
        self._own = None
        return _frozen(out, self._tick, (0, 0))

    def _decode(self, sender, data) -> Message:
        model = self._agent.alg.model
        try:
            wm = codec.decode(bytes(data), run_id=self.RUN_ID, sender=self._internal[sender], n=model.n, m=model.m,
                              exchanged=self._agent.alg.exchanged)
        except codec.Rejected as e:
            raise InputError(f"received[{sender}]", str(e)) from None
        if wm.tick != self._tick:
            raise InputError(f"received[{sender}]", f"a message of tick {wm.tick}, this is tick {self._tick}")
        return wm.message

"""One agent's share of ``engine.run``: the same estimator functions on a
batch of one.

The engine calls ``local`` and ``fuse`` on every agent at once with the full
(N x N) link matrix; an agent process calls them on itself alone, shape
(1, 1, ...), with ``senders`` holding only the messages it fuses (its own
included) in scenario order, and an all-ones adjacency over them. Neighbours
that are not linked contribute exact zeros in the engine, so both compute the
same numbers. No transport or timing here.
"""
from __future__ import annotations

from dataclasses import fields, replace
from operator import attrgetter

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.estimators.base import Estimator
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.data.scenario import Scenario, links_for


class AgentEstimator:
    """Agent ``agent_id``'s ``estimator`` (the class ``estimators.get``
    resolved) over a run of ``ticks`` ticks with ``seed`` (its draws), from
    the prior, or from ``start`` = (x, P) with a new observation window (a
    rejoin: ``mesh.protocol.rejoin``)."""

    def __init__(self, scn: Scenario, agent_id: int, estimator: type[Estimator], ticks: int, seed: int,
                 params=None, start=None):
        self.ids = scn.ids
        if agent_id not in self.ids:
            raise ValueError(f"agent {agent_id} is not in scenario {scn.name!r} (ids {', '.join(map(str, self.ids))})")
        self.agent_id = agent_id
        self.index = self.ids.index(agent_id)
        self.scenario = scn
        self.sensors = scn.sensors().select([self.index])   # this agent's H, R only
        self.alg = estimator(scn.model(ticks), self.sensors, params or scn.params)
        st = self.state = self.alg.init((1, 1))
        if start is not None:
            x, P = start
            self.state = replace(st, x=np.array(x, dtype=float).reshape(st.x.shape),
                                 P=np.array(P, dtype=float).reshape(st.P.shape), since=np.zeros_like(st.since))
        draws = self.alg.draws(seed, [agent_id], ticks)  # this agent's row of the engine's (Estimator.draws)
        self.draws = None if draws is None else draws[0]
        self._neighbourhoods = {}  # (senders, own position) -> Neighbourhood

    @property
    def p(self) -> int:
        return int(self.sensors.p[0])

    def neighbours(self, positions: np.ndarray) -> tuple:
        return neighbours(self.scenario, self.agent_id, positions)

    def local(self, k: int, has: bool, y) -> Message:
        """Step 1 on this agent's own measurement (length p, ignored when not has)."""
        y_pad = self.sensors.pad(y, 0) if has else np.zeros(self.sensors.H.shape[1])
        self.state, msg = self.alg.local(self.state, k, y_pad[None, None], np.array([[bool(has)]]))
        return msg

    def fuse(self, k: int, own: Message, received: dict) -> Output:
        """Steps 3 and 4 with ``received`` {sender id: unbatched Message},
        which may or may not hold this agent's own message (``own`` is used)."""
        me = self.agent_id
        order = sorted({j for j in received if j != me} | {me}, key=self.scenario.index)  # scenario order
        own_row = tuple(a[0, 0] for a in _row(own))
        columns = zip(*(own_row if j == me else _row(received[j]) for j in order))
        senders = Message(*(np.array([c]) for c in columns))  # (1, J, ...): Message.stack(rows)[None]
        nb = self._neighbourhood(len(order), order.index(me))
        draws = None if self.draws is None else np.array([[self.draws[k - 1]]])
        if draws is not None or self.alg.defends:
            columns = np.array([[[self.scenario.index(j) for j in order]]]) if self.alg.defends else None
            nb = Neighbourhood(nb.adj, nb.self_mask, draws, columns)
        self.state, out = self.alg.screened_fuse(self.state, own, senders, nb)
        return out

    def _neighbourhood(self, J: int, own: int) -> Neighbourhood:
        """All J senders fused, this agent the ``own``-th: made once per (J,
        own) and kept (read-only arrays), with its neighbour count."""
        nb = self._neighbourhoods.get((J, own))
        if nb is None:
            adj, self_mask = np.ones((1, 1, J)), np.zeros((1, 1, J), dtype=bool)
            self_mask[0, 0, own] = True
            adj.flags.writeable = self_mask.flags.writeable = False
            nb = self._neighbourhoods[(J, own)] = Neighbourhood(adj, self_mask)
        return nb


_row = attrgetter(*(f.name for f in fields(Message)))  # a message's fields, in ``Message`` order


def neighbours(scn: Scenario, agent_id: int, positions: np.ndarray) -> tuple:
    """Ids linked to ``agent_id`` at a tick (itself included), from every
    agent's position (N, 2) and the scenario's topology and range.

    Range links: this agent's row of ``scenario.range_links`` only, with the
    same arithmetic (bit for bit the same squared distances), not all N x N."""
    ids = scn.ids
    i = scn.index(agent_id)
    if scn.topology == "range":
        diff = positions[i] - positions
        row = np.einsum("...k,...k->...", diff, diff) <= scn.comm_range * scn.comm_range
    else:
        row = links_for(scn, positions[None])[0, i]
    return tuple(ids[j] for j in np.flatnonzero(row).tolist())


def lockstep(scn: Scenario, algorithm: str, trace, seed: int = 0):
    """Every agent of ``scn`` as an ``AgentEstimator`` (a batch of one, as in
    an agent process), in lockstep over seed 0 of ``trace``, each fusing the
    messages of the agents linked to it: what a fault-free mesh run computes,
    in one process. Yields (k, messages {id: Message}, outputs {id: Output})
    per tick; ``seed``: the run's seed (the estimator's draws)."""
    ids = [a.id for a in scn.agents]
    K = trace.has.shape[1]
    estimator = estimators.get(algorithm)
    agents = {i: AgentEstimator(scn, i, estimator, K, seed) for i in ids}
    for k in range(1, K + 1):
        msgs = {i: agents[i].local(k, bool(trace.has[0, k - 1, j]), trace.y[0, k - 1, j, :agents[i].p])
                for j, i in enumerate(ids)}
        outputs = {}
        for j, i in enumerate(ids):
            heard = {o: msgs[o].take((0, 0)) for jj, o in enumerate(ids) if trace.links[0, k - 1, j, jj] and o != i}
            outputs[i] = agents[i].fuse(k, msgs[i], heard)
        yield k, msgs, outputs

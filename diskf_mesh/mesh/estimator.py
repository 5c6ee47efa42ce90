"""One agent's share of ``engine.run``: the same algorithm functions on a
batch of one.

The engine calls ``local`` and ``fuse`` on every agent at once with the full
(N x N) link matrix; an agent process calls them on itself alone, shape
(1, 1, ...), with ``senders`` holding only the messages it fuses (its own
included) in scenario order, and an all-ones adjacency over them. Neighbours
that are not linked contribute exact zeros in the engine, so both compute the
same numbers. No transport or timing here.
"""
from __future__ import annotations

import numpy as np

from .. import algorithms
from ..messages import Message, Neighbourhood, Output
from ..scenario import Scenario, links_for


class AgentEstimator:
    def __init__(self, scn: Scenario, agent_id: int, algorithm: str, ticks: int, seed: int, params=None):
        self.ids = tuple(a.id for a in scn.agents)
        if agent_id not in self.ids:
            raise ValueError(f"agent {agent_id} is not in scenario {scn.name!r} (ids {', '.join(map(str, self.ids))})")
        self.agent_id = agent_id
        self.index = self.ids.index(agent_id)
        self.scenario = scn
        self.sensors = scn.sensors().select([self.index])   # this agent's H, R only
        self.algorithm = algorithm
        self.alg = algorithms.get(algorithm)(scn.model(ticks), self.sensors, params or scn.params)
        self.state = self.alg.init((1, 1))
        self.gossip = algorithms.gossip_draws(seed, [agent_id], ticks)[0] if algorithm == "gdkf" else None

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
        others = {j: m for j, m in received.items() if j != self.agent_id}
        order = sorted(set(others) | {self.agent_id}, key=self.ids.index)
        rows = [own.take((0, 0)) if j == self.agent_id else others[j] for j in order]
        senders = Message.stack(rows).take(np.newaxis)         # (1, J, ...)
        J = len(order)
        self_mask = np.zeros((1, 1, J), dtype=bool)
        self_mask[0, 0, order.index(self.agent_id)] = True
        u = None if self.gossip is None else np.array([[self.gossip[k - 1]]])
        nb = Neighbourhood(np.ones((1, 1, J)), self_mask, u)
        self.state, out = self.alg.fuse(self.state, own, senders, nb)
        return out


def neighbours(scn: Scenario, agent_id: int, positions: np.ndarray) -> tuple:
    """Ids linked to ``agent_id`` at a tick (itself included), from every
    agent's position (N, 2) and the scenario's topology and range."""
    ids = [a.id for a in scn.agents]
    row = links_for(scn, positions[None])[0, ids.index(agent_id)]
    return tuple(i for i, linked in zip(ids, row) if linked)


def fixed_neighbours(scn: Scenario, agent_id: int) -> tuple | None:
    """The agents ``agent_id`` can ever be linked to, when the links cannot
    change during a run (a static topology, or range links between agents
    that never move), else None. An agent process then listens to these
    agents' keys only, instead of every agent's: the per-message cost of the
    transport is what limits a large mesh."""
    if scn.topology == "all" or (scn.topology == "range" and any(a.mobile for a in scn.agents)):
        return None
    positions = np.stack([a.position_at(np.array([1]))[0] for a in scn.agents])
    return tuple(j for j in neighbours(scn, agent_id, positions) if j != agent_id)

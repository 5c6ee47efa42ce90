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
        others = {j: m for j, m in received.items() if j != self.agent_id}
        order = sorted(set(others) | {self.agent_id}, key=self.ids.index)
        rows = [own.take((0, 0)) if j == self.agent_id else others[j] for j in order]
        senders = Message.stack(rows).take(np.newaxis)         # (1, J, ...)
        nb = self._neighbourhood(len(order), order.index(self.agent_id))
        if self.gossip is not None:
            nb = Neighbourhood(nb.adj, nb.self_mask, np.array([[self.gossip[k - 1]]]))
        self.state, out = self.alg.fuse(self.state, own, senders, nb)
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


def neighbours(scn: Scenario, agent_id: int, positions: np.ndarray) -> tuple:
    """Ids linked to ``agent_id`` at a tick (itself included), from every
    agent's position (N, 2) and the scenario's topology and range.

    Range links: this agent's row of ``scenario.range_links`` only, with the
    same arithmetic (bit for bit the same squared distances), not all N x N."""
    ids = [a.id for a in scn.agents]
    i = ids.index(agent_id)
    if scn.topology == "range":
        diff = positions[i] - positions
        row = np.einsum("...k,...k->...", diff, diff) <= scn.comm_range * scn.comm_range
    else:
        row = links_for(scn, positions[None])[0, i]
    return tuple(j for j, linked in zip(ids, row.tolist()) if linked)


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


# a link is assumed possible up to this much beyond the range (relative), so
# that rounding in positions along a path can never hide a real link
RANGE_SLACK = 1e-6


def possible_neighbours(scn: Scenario, agent_id: int) -> tuple | None:
    """The agents ``agent_id`` may be linked to at some tick of a run (not
    itself), or None where that may be every agent (listen to them all).

    With range links between moving agents the links change, but an agent
    moves only along its path (a closed polyline; a static agent is a point),
    so two agents whose paths never come within the range of each other are
    never linked, whatever the ticks, periods and phases. This bound keeps
    every agent that might be linked (a superset of the real links, with
    ``RANGE_SLACK``); the range gate at each tick decides the rest. In
    Scenario 2 a static agent listens to the five moving agents only."""
    fixed = fixed_neighbours(scn, agent_id)
    if fixed is not None or scn.topology != "range":
        return fixed
    ids = [a.id for a in scn.agents]
    mine = _path_segments(scn.agents[ids.index(agent_id)])
    reach = scn.comm_range * (1.0 + RANGE_SLACK)
    out = tuple(a.id for a in scn.agents
                if a.id != agent_id and _segments_distance(mine, _path_segments(a)) <= reach)
    return None if len(out) == len(ids) - 1 else out


def _path_segments(agent) -> np.ndarray:
    """(S, 2, 2) the segments an agent's position can be on."""
    if agent.path is None:
        p = np.asarray(agent.position, dtype=float)
        return np.stack([p, p])[None]
    pts = np.asarray(agent.path, dtype=float)
    return np.stack([pts, np.roll(pts, -1, axis=0)], axis=1)


def _segments_distance(A: np.ndarray, B: np.ndarray) -> float:
    """Smallest distance between any segment of A (S, 2, 2) and of B (T, 2, 2)."""
    a0, a1 = A[:, None, 0], A[:, None, 1]
    b0, b1 = B[None, :, 0], B[None, :, 1]

    def to_segment(p, s0, s1):
        d = s1 - s0
        dd = np.einsum("...k,...k->...", d, d)
        t = np.clip(np.einsum("...k,...k->...", p - s0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
        return np.linalg.norm(s0 + t[..., None] * d - p, axis=-1)

    def cross(u, v):
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    dist = np.minimum(np.minimum(to_segment(a0, b0, b1), to_segment(a1, b0, b1)),
                      np.minimum(to_segment(b0, a0, a1), to_segment(b1, a0, a1)))
    crossing = ((cross(a1 - a0, b0 - a0) * cross(a1 - a0, b1 - a0) < 0)
                & (cross(b1 - b0, a0 - b0) * cross(b1 - b0, a1 - b0) < 0))
    return float(np.where(crossing, 0.0, dist).min())

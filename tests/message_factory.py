"""Real agent messages for tests of the receive path: every agent of Scenario 2
run in-process up to a tick, then one receiver's view of that tick."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from diskf_mesh import estimators as algorithms
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.estimators.base import State
from diskf_mesh.mesh.protocol.guard import GuardConfig
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.core.messages import Message, Neighbourhood
from diskf_mesh.data.scenario import load_scenario, simulate

RUN = "fuzz-run"


@dataclass
class TickView:
    """Receiver ``me``'s tick ``tick``: its state before fusion, its own
    message (batch of one), every agent's message, and who is linked."""

    alg: object
    run_id: str
    tick: int
    ticks: int
    ids: tuple
    me: int
    state: State          # batch of one
    own: Message          # batch of one
    messages: dict        # id -> unbatched Message of every agent at ``tick``
    linked: tuple         # ids linked to ``me`` at ``tick``, ``me`` excluded
    n: int
    m: int

    def key(self, sender) -> str:
        return Keys(self.run_id).msg(sender)

    def payload(self, sender: int, tick: int | None = None) -> bytes:
        return wire.encode(self.run_id, sender, self.tick if tick is None else tick, self.messages[sender])

    def guard_config(self, **kw) -> GuardConfig:
        return GuardConfig(self.run_id, self.me, frozenset(self.ids), self.n, self.m, ticks=self.ticks,
                           information_check=self.alg.information_check, **kw)

    def fuse(self, received):
        """Fuse own message with ``received`` [(sender, Message)] as an agent
        process does: senders stacked by id, self included."""
        rows = sorted([(self.me, self.own.take(0))] + list(received), key=lambda r: r[0])
        senders = Message.stack([m for _, m in rows])
        own_index = [s for s, _ in rows].index(self.me)
        S = len(rows)
        mask = np.zeros((1, S), dtype=bool)
        mask[0, own_index] = True
        return self.alg.fuse(self.state, self.own, senders, Neighbourhood(np.ones((1, S)), mask))


def tick_view(algorithm="diskf", scenario="dynamic", tick=30, me_index=None, seed=0) -> TickView:
    scn = load_scenario(scenario)
    trace = simulate(scn, [seed], steps=tick)
    alg = algorithms.get(algorithm)(trace.model, trace.sensors, scn.params)
    N = trace.sensors.N
    ids = trace.sensors.ids
    state = alg.init((1, N))
    eye = np.eye(N, dtype=bool)[None]
    for k in range(1, tick):
        state, msg = alg.local(state, k, trace.y[:, k - 1], trace.has[:, k - 1])
        nb = Neighbourhood(trace.links[:, k - 1].astype(float), eye, None)
        state, _ = alg.fuse(state, msg, msg, nb)
    state, msg = alg.local(state, tick, trace.y[:, tick - 1], trace.has[:, tick - 1])
    links = trace.links[0, tick - 1]
    if me_index is None:  # the agent with the most neighbours at this tick
        me_index = int(np.argmax(links.sum(axis=1)))
    one = lambda a: a[0, me_index:me_index + 1]  # noqa: E731
    return TickView(
        alg=alg, run_id=RUN, tick=tick, ticks=scn.steps, ids=ids, me=ids[me_index],
        state=replace(state, Y_pred=None, **{  # this agent's row of every field of the state
            f.name: one(v) for f in fields(state)
            if f.name != "Y_pred" and isinstance(v := getattr(state, f.name), np.ndarray)}),
        own=msg.take((0, slice(me_index, me_index + 1))),
        messages={ids[j]: msg.take((0, j)) for j in range(N)},
        linked=tuple(ids[j] for j in range(N) if links[me_index, j] and j != me_index),
        n=trace.model.n, m=trace.model.m,
    )

"""One agent's share of ``engine.run``: the same estimator functions on a
batch of one, or on the agents of one tick together (``Steps``).

The engine calls ``local`` and ``fuse`` on every agent at once with the full
(N x N) link matrix; an agent process calls them on itself alone, shape
(1, 1, ...), with ``senders`` holding only the messages it fuses (its own
included) in scenario order, and an all-ones adjacency over them. Neighbours
that are not linked contribute exact zeros in the engine, so both compute the
same numbers. No transport or timing here.

An agent machine hands its steps to its shell (``Work``, its result back as
``Worked``: ``mesh.protocol.events``). A process's shell carries out its one
agent's at once (``Work.alone``); the simulated network's collects those due
at one virtual instant and ``Steps.carry_out`` runs each step of one tick as
one call over the agents, laid out as the engine's gathered layout lays out
its agents (each receiver a row of its own, its senders in scenario order in
its slots, zero weights past them): the same bits as one by one
(``tests/test_simnet_steps.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from operator import attrgetter

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.estimators.base import Estimator
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.data.scenario import BLOCK_BYTES_MAX, Scenario, links_for
from diskf_mesh.engine.batch import per_receiver, slot_bytes


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
        self.scenario, self.ticks = scn, ticks
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




class Steps:
    """Carries out the steps (``Work``) of many agents together: those of
    one step, tick, estimator and run whose states have one layout run as
    one call of the estimator's ``local`` or ``screened_fuse`` over them
    (their sensors selected together, as the engine's), the others one by
    one. A batch whose call raises, or whose messages are not all finite
    (a zero weight times an infinity is not zero), runs one by one: each
    agent's step then raises or not as alone. Keeps one estimator object
    per set of agents stepped together."""

    def __init__(self):
        self._algs = {}  # (class, scenario, ticks, params, agent places) -> estimator over those agents
        # id(state) -> (state, its layout) of the states the last two calls made: a layout is found once per batch
        self._layouts, self._older = {}, {}

    def carry_out(self, works: list) -> list:
        """Each ``Work``'s result, in order (``Work.alone``'s)."""
        self._older, self._layouts = self._layouts, {}
        results = [None] * len(works)
        groups = {}
        for i, w in enumerate(works):
            groups.setdefault(self._group(w), []).append(i)
        for key, idx in groups.items():
            if key is None or len(idx) == 1:
                for i in idx:
                    results[i] = works[i].alone()
                continue
            batch = [works[i] for i in idx]
            try:
                out = self._local(batch) if key[0] == "local" else self._fuse(batch)
            except (np.linalg.LinAlgError, _NotFinite):
                out = [w.alone() for w in batch]
            for i, r in zip(idx, out):
                results[i] = r
        return results

    def _group(self, w) -> tuple | None:
        """What the works stepped together share: the step, the tick, the
        estimator and its run, the layout of the state (None: alone)."""
        e = w.est
        if w.step not in ("local", "fuse") or not isinstance(e, AgentEstimator):
            return None
        state = e.state
        known = self._older.get(id(state))
        layout = known[1] if known is not None and known[0] is state else _layout(state)
        if layout is None:
            return None
        return (w.step, w.args[0], type(e.alg), id(e.scenario), e.ticks, id(e.alg.params), e.draws is None,
                type(state), layout)

    def _share(self, ests: list, state) -> None:
        """Give agents ``ests`` their shares of the stacked ``state``, their
        layout noted once for all."""
        layout, made = _layout(state, stacked=True), self._layouts
        for b, e in enumerate(ests):
            e.state = mine = _state_of(state, b)
            made[id(mine)] = (mine, layout)

    def _alg(self, ests: list) -> Estimator:
        e = ests[0]
        places = tuple(x.index for x in ests)
        key = (type(e.alg), id(e.scenario), e.ticks, id(e.alg.params), places)
        alg = self._algs.get(key)
        if alg is None:
            if len(self._algs) > 64:
                self._algs.clear()
            alg = self._algs[key] = type(e.alg)(e.alg.model, e.scenario.sensors().select(list(places)), e.alg.params)
        return alg

    def _local(self, batch: list) -> list:
        ests = [w.est for w in batch]
        k = batch[0].args[0]
        y = np.array([[e.sensors.pad(w.args[2], 0) if w.args[1] else np.zeros(e.sensors.H.shape[1])
                       for e, w in zip(ests, batch)]])
        has = np.array([[bool(w.args[1]) for w in batch]])
        state, msg = self._alg(ests).local(_stack_states([e.state for e in ests]), k, y, has)
        self._share(ests, state)
        return [Message(*(a[:, b:b + 1] for a in _row(msg))) for b in range(len(ests))]

    def _fuse(self, batch: list) -> list:
        """``AgentEstimator.fuse`` of each, laid out as the engine's gathered
        layout lays out its agents (``engine.batch.GatheredLinks``): receiver
        b a batch row of its own, (1, B, 1, ...), its senders (its own
        message as it fuses it included) in scenario order in the slots
        (1, B, D, ...), the slots past its last sender zero weights (holding
        its own message). Every message object is laid out once for all its
        receivers, then taken into their slots: arrays, not a Python step per
        delivery. The receivers run in parts whose working set (about
        ``slot_bytes`` per receiver and slot) stays under ``BLOCK_BYTES_MAX``,
        as the engine's blocks."""
        ests = [w.est for w in batch]
        B, k = len(batch), batch[0].args[0]
        scn = ests[0].scenario
        owns = [w.args[1] for w in batch]
        # every (receiver, received message) pair but a receiver's own: one row per message object, in the order
        # first received
        senders, msgs, counts = [], [], []
        for w in batch:
            received = w.args[2]
            senders += received
            msgs += received.values()
            counts.append(len(received))
        at = np.fromiter(map(scn.places.__getitem__, senders), dtype=np.intp, count=len(senders))
        mine = np.array([e.index for e in ests], dtype=np.intp)
        recv = np.repeat(np.arange(B), counts)
        keep = np.flatnonzero(at != mine[recv])
        objects = np.fromiter(map(id, msgs), dtype=np.int64, count=len(msgs))[keep]
        _, first, inverse = np.unique(objects, return_index=True, return_inverse=True)
        by_first = np.argsort(first, kind="stable")
        rank = np.empty_like(by_first)
        rank[by_first] = np.arange(len(by_first))
        heads = keep[first[by_first]]
        rows = [_row(msgs[i]) for i in heads.tolist()]
        own_rows = np.arange(len(rows), len(rows) + B)  # each receiver's own message, as it fuses it (not as sent)
        rows += [tuple(a[0, 0] for a in _row(o)) for o in owns]
        columns = [np.array(c) for c in zip(*rows)]                          # (messages, ...) per field
        if not all(np.isfinite(a).all() for a in columns):
            raise _NotFinite
        row_place = np.concatenate([at[heads], mine])
        # the slots: each receiver's pairs (its own last) sorted by sender place
        pair_recv = np.concatenate([recv[keep], np.arange(B)])
        pair_row = np.concatenate([rank[inverse.reshape(-1)], own_rows])
        order = np.lexsort((row_place[pair_row], pair_recv))
        count = np.bincount(pair_recv, minlength=B)
        start = np.cumsum(count) - count
        slot = np.arange(len(order)) - np.repeat(start, count)
        at_slot = np.empty_like(order)
        at_slot[order] = slot
        own_slot = at_slot[len(keep):]                                       # the own pairs are the last B
        recv_sorted, row_sorted = pair_recv[order], pair_row[order]
        alg = self._alg(ests)
        draws = None if ests[0].draws is None else np.array([[e.draws[k - 1] for e in ests]])[..., None]
        own = Message(*(np.concatenate(f, axis=1)[:, :, None] for f in zip(*(_row(o) for o in owns))))
        state = _stack_states([e.state for e in ests])
        per_slot = slot_bytes(alg.model.n, owns[0])
        result, b0 = [], 0
        while b0 < B:  # a part of receivers b0 .. b1 - 1
            b1, D = b0 + 1, int(count[b0])
            while b1 < B and (b1 - b0 + 1) * max(D, int(count[b1])) * per_slot <= BLOCK_BYTES_MAX:
                D = max(D, int(count[b1]))
                b1 += 1
            R, cut = b1 - b0, slice(start[b0], start[b1 - 1] + count[b1 - 1])
            r, sl = recv_sorted[cut] - b0, slot[cut]
            idx = np.repeat(own_rows[b0:b1, None], D, axis=1)               # (R, D) message rows
            idx[r, sl] = row_sorted[cut]
            adj, self_mask = np.zeros((1, R, 1, D)), np.zeros((1, R, 1, D), dtype=bool)
            adj[0, r, 0, sl] = 1.0
            self_mask[0, np.arange(R), 0, own_slot[b0:b1]] = True
            place_of = row_place[idx][None, :, None] if alg.defends else None
            nb = Neighbourhood(adj, self_mask, None if draws is None else draws[:, b0:b1], place_of)
            part = slice(b0, b1)
            st, out = alg.screened_fuse(per_receiver(state, lambda a: a[:, part, None]),
                                        Message(*(a[:, part] for a in _row(own))),
                                        Message(*(np.take(a, idx, axis=0)[None] for a in columns)), nb)
            self._share(ests[b0:b1], per_receiver(st, lambda a: a[:, :, 0]))
            result += [Output(*(a[:, b:b + 1, 0] for a in (out.x, out.P, out.d, out.d_valid))) for b in range(R)]
            b0 = b1
        return result


class _NotFinite(Exception):
    """A batch's message holds an infinity or a NaN: its steps run one by one."""


def _layout(state, stacked: bool = False) -> tuple | None:
    """The layout of an agent's state: each array's shape and type, every
    other field (a tick) as it is; None where an array is not (1, 1, ...).
    ``stacked``: that of each agent's share of a stacked state (1, B, ...)
    (``_state_of``)."""
    layout = []
    for v in vars(state).values():
        if isinstance(v, np.ndarray):
            shape = v.shape[:1] + (1,) + v.shape[2:] if stacked else v.shape
            if shape[:2] != (1, 1):
                return None
            layout.append((shape, v.dtype.char))
        else:
            layout.append(v)
    return tuple(layout)


def _stack_states(states: list):
    """States of single agents (1, 1, ...) as one (1, B, ...); every other
    field (a tick) is the same in all (``Steps._group``)."""
    s0 = states[0]
    return replace(s0, **{name: np.concatenate([vars(s)[name] for s in states], axis=1)
                          for name, v in vars(s0).items() if isinstance(v, np.ndarray)})


def _state_of(state, b: int):
    """Agent ``b``'s (1, 1, ...) share of a stacked state: its fields as
    they are but the arrays (a frozen dataclass's ``__dict__`` filled as
    ``replace`` would, without its per-call look at the fields)."""
    out = object.__new__(type(state))
    vars(out).update({name: v[:, b:b + 1] if isinstance(v, np.ndarray) else v for name, v in vars(state).items()})
    return out

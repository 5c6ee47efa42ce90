"""The in-process engine: every agent of every seed at once, one tick at a time.

Per tick it calls the estimator's ``local`` on the whole (seeds x agents)
batch, lets every agent "hear" the messages allowed by the links, and calls
``fuse``. There is no Python loop over agents or seeds; the agent process
(``agents/``) calls the very same two functions on a batch of one.

Two ways to hand the messages to ``fuse``, the same numbers to round-off
(``tests/test_linalg_fast.py``):

dense    one (B, N, N) adjacency over all agents as senders. Best for small
         or densely linked networks (the paper's four agents).
gather   every receiver is a batch of one (as in an agent process) with its
         own padded list of D senders, D the largest neighbourhood: the work
         is O(N D) instead of O(N^2), for large sparse networks (a random
         geometric graph of 1,000 agents). Senders are listed in id order, so
         each receiver sums its neighbours in the same order as ``dense``;
         padding slots carry weight 0. Receivers with the same neighbours
         still get bit-identical sums. What a sender contributes (e.g. its
         P^-1) is recomputed in each of its receivers' slots: D times the
         per-sender work, still far below the dense O(N^2).

``run_many`` stacks several traces of one scenario (e.g. the three
topologies of Table II) into one batch, so the per-tick Python overhead is
paid once for all of them.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, fields, replace

import numpy as np

from diskf_mesh import estimators
from diskf_mesh.core.errors import InputError
from diskf_mesh.core.messages import Message, Neighbourhood, Output
from diskf_mesh.data.lies import Liars
from diskf_mesh.data.scenario import (
    BLOCK_BYTES_MAX, TICK_BYTES_MAX, TICK_BYTES_PER_SLOT, TICK_BYTES_PER_WEIGHT, gathers)
from diskf_mesh.data.trace import Trace
from diskf_mesh.estimators import Params

NEIGHBOURS = ("auto", "dense", "gather")


@dataclass(frozen=True)
class Estimates:
    """Per tick and agent: fused state and covariance, fused input and
    whether it exists. Shapes (B, K, N, ...)."""

    x: np.ndarray
    P: np.ndarray
    d: np.ndarray
    d_valid: np.ndarray

    def take(self, index) -> "Estimates":
        """Select seeds (the leading axis)."""
        return Estimates(self.x[index], self.P[index], self.d[index], self.d_valid[index])

    def agents(self, columns) -> "Estimates":
        """Select agents (by their place in the scenario)."""
        return Estimates(self.x[:, :, columns], self.P[:, :, columns], self.d[:, :, columns],
                         self.d_valid[:, :, columns])


def draw_stream(est, seeds, ticks: int) -> np.ndarray | None:
    """(B, K, N) the estimator's per-agent draws (``Estimator.draws``) for
    every seed of ``seeds`` over ``ticks`` ticks, or None if it draws nothing."""
    rows = [est.draws(s, est.sensors.ids, ticks) for s in seeds]
    return None if rows[0] is None else np.stack([r.T for r in rows])


# --------------------------------------------------------------------------
# who hears whom at one tick
# --------------------------------------------------------------------------
class DenseLinks:
    """All N agents as senders of every receiver, weighted by the links."""

    def __init__(self, links: np.ndarray, B: int):
        N = links.shape[-1]
        self.adj = np.broadcast_to(links, (B, N, N)).astype(float)
        self.self_mask = np.broadcast_to(np.eye(N, dtype=bool), (B, N, N))
        self.nb = Neighbourhood(self.adj, self.self_mask)  # one per link change: caches what it derives

    def fuse(self, est, state, msg: Message, draws):
        nb = self.nb if draws is None else Neighbourhood(self.adj, self.self_mask, draws)
        return est.screened_fuse(state, msg, msg, nb)


class GatheredLinks:
    """Each receiver a batch of one with its D senders gathered in id order.

    Given ``slot_bytes``, a tick's working set per (seed, receiver, sender
    slot), receivers fuse in blocks whose working set stays under
    ``BLOCK_BYTES_MAX`` (all at once otherwise): a tick of a large network
    (10,000 agents, D about 1,000) would hold its (B, N, D, n, n)
    temporaries at once, several GB, and blocks small enough for the
    allocator to reuse their arrays run faster. Every receiver is a batch of
    one whichever block holds it, so blocks give the same numbers."""

    def __init__(self, links: np.ndarray, B: int, slot_bytes: int = 0):
        N = links.shape[-1]
        D = int(links.sum(axis=-1).max())
        idx = senders_in_order(links, D)                               # (b, N, D), neighbours first, in id order
        linked = np.take_along_axis(links, idx, axis=-1)
        self.flat = np.arange(B)[:, None, None] * N + idx               # (B, N, D) into (B*N) rows
        self.adj = np.broadcast_to(linked[..., None, :].astype(float), (B, N, 1, D))
        is_self = linked & (idx == np.arange(N)[:, None])
        self.self_mask = np.broadcast_to(is_self[..., None, :], (B, N, 1, D))
        self.columns = idx[..., None, :]  # each slot's sender among the run's agents
        rows = N if not slot_bytes else int(np.clip(BLOCK_BYTES_MAX // (B * max(D, 1) * slot_bytes), 1, N))
        self.blocks = [slice(start, min(start + rows, N)) for start in range(0, N, rows)]
        self.nbs = [Neighbourhood(self.adj[:, b], self.self_mask[:, b], columns=self.columns[:, b])
                    for b in self.blocks]

    def gather(self, a: np.ndarray, block: slice = slice(None)) -> np.ndarray:
        """(B, N, ...) per sender -> (B, R, D, ...) per receiver of ``block`` and slot."""
        rows = a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:])
        return np.take(rows, self.flat[:, block], axis=0)

    def fuse(self, est, state, msg: Message, draws, sent: Message | None = None):
        """``sent``: what the agents sent, if not ``msg`` (a liar's message,
        ``data.lies``); each receiver fuses its own true message."""
        parts = [self._fuse_block(est, state, msg, draws, sent, b, nb) for b, nb in zip(self.blocks, self.nbs)]
        if len(parts) == 1:
            return parts[0]
        states, outs = zip(*parts)
        joined = lambda name, items: np.concatenate([getattr(i, name) for i in items], axis=1)  # noqa: E731
        st = replace(states[0], **{f.name: joined(f.name, states) for f in fields(states[0])
                                   if isinstance(getattr(states[0], f.name), np.ndarray)})
        return st, Output(*(joined(f.name, outs) for f in fields(Output)))

    def _fuse_block(self, est, state, msg: Message, draws, sent: Message | None, block: slice, nb: Neighbourhood):
        own = Message(**{f.name: getattr(msg, f.name)[:, block, None] for f in fields(Message)})
        if sent is None:
            senders = Message(**{f.name: self.gather(getattr(msg, f.name), block) for f in fields(Message)})
        else:
            mine = self.self_mask[:, block, 0]
            senders = Message(**{f.name: np.where(mine.reshape(mine.shape + (1,) * (getattr(own, f.name).ndim - 3)),
                                                  getattr(own, f.name), self.gather(getattr(sent, f.name), block))
                                 for f in fields(Message)})
        if draws is not None:
            nb = Neighbourhood(nb.adj, nb.self_mask, draws[:, block, None], nb.columns)
        st, out = est.screened_fuse(per_receiver(state, lambda a: a[:, block, None]), own, senders, nb)
        squeeze = lambda a: a[:, :, 0]  # noqa: E731
        return per_receiver(st, squeeze), Output(squeeze(out.x), squeeze(out.P), squeeze(out.d), squeeze(out.d_valid))


SORT_PAIRS_PER_BLOCK = 1 << 22  # receiver-sender pairs ``senders_in_order`` sorts at once


def senders_in_order(links: np.ndarray, D: int) -> np.ndarray:
    """(..., N, D) each receiver's senders in id order, then (padding, where
    it has fewer than D) the first agents it does not hear, in id order: a
    stable sort of its row of ``links`` (..., N, N), a block of receivers at a
    time (one sort of 10,000 x 10,000 links would take 800 MB of indices)."""
    N = links.shape[-1]
    out = np.empty(links.shape[:-1] + (D,), dtype=np.intp)
    rows = max(1, SORT_PAIRS_PER_BLOCK // max(N, 1))
    for start in range(0, N, rows):
        out[..., start:start + rows, :] = np.argsort(~links[..., start:start + rows, :], axis=-1, kind="stable")[..., :D]
    return out


def per_receiver(state, fn):
    """``state`` with ``fn`` applied to every array field (whatever fields the
    estimator's state carries), e.g. to add or drop the receiver-batch axis."""
    return replace(state, **{f.name: fn(v) for f in fields(state)
                             if isinstance(v := getattr(state, f.name), np.ndarray)})


def choose_links(links: np.ndarray, B: int, mode: str = "auto", slot_bytes: int = 0):
    """The neighbour representation for one tick's links ``(1 or B, N, N)``.

    ``auto`` gathers when the network is large and sparse
    (``data.scenario.gathers``). ``slot_bytes``: see ``GatheredLinks``."""
    if mode not in NEIGHBOURS:
        raise ValueError(f"neighbours: must be one of {', '.join(NEIGHBOURS)}, got {mode!r}")
    N = links.shape[-1]
    if mode == "auto":
        mode = "gather" if gathers(N, int(links.sum(axis=-1).max())) else "dense"
    return GatheredLinks(links, B, slot_bytes) if mode == "gather" else DenseLinks(links, B)


# --------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------
def run(trace: Trace, estimator: str, params: Params | None = None, progress=None,
        neighbours: str = "auto", lies=()) -> Estimates:
    """Run one estimator (by name) on every seed of ``trace``.

    ``progress``, if given, is called with the number of ticks done (counted
    over all seed chunks when a large run is split, see ``seeds_per_chunk``).
    ``neighbours`` picks the message layout (see the module docstring);
    all give the same estimates. ``lies``: ``data.lies.Lie``s the agents
    commit on their outgoing messages (and reports), with agents as the
    run's ids (``Scenario.lies``). A setting the estimator refuses
    (``Estimator.refuse``) raises ``InputError`` first; its ``warning``, if
    any, is issued as a RuntimeWarning."""
    refused = estimators.get(estimator).refuse(params or Params(), trace.model, trace.sensors)
    if refused:
        raise InputError(*refused)
    problem = estimators.get(estimator).warning(params or Params(), trace.links)
    if problem:
        warnings.warn(problem, RuntimeWarning, stacklevel=2)
    B = trace.has.shape[0]
    chunk = seeds_per_chunk(trace)
    if chunk >= B:
        return run_batch(trace, estimator, params, progress, neighbours, lies=lies)
    K = trace.has.shape[1]
    parts = []
    for c, start in enumerate(range(0, B, chunk)):
        report = None if progress is None else (lambda k, done=c * K: progress(done + k))
        parts.append(run_batch(take_seeds(trace, slice(start, start + chunk)), estimator, params, report, neighbours,
                               lies=lies))
    return Estimates(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(Estimates)))


def run_batch(trace: Trace, estimator: str, params: Params | None = None, progress=None,
              neighbours: str = "auto", restart=None, listen=None, lies=(), links_at=None) -> Estimates:
    """``run`` on all seeds of ``trace`` as one batch. ``restart(k, est,
    state) -> state``, if given, may replace agents' states before tick k's
    local step (a restarted agent, ``engine.verify``); ``listen(k, msg)`` is
    handed every tick's (true) messages. With ``lies`` every receiver is a
    batch of one (``gather``), so that each fuses its own true message and
    the others' as they were sent. ``links_at(k)``: tick k's links (1 or B,
    N, N), made a tick at a time, instead of the trace's."""
    B, K, N = trace.has.shape
    n, m = trace.model.n, trace.model.m
    steps = Stepper(trace.model, trace.sensors, estimator, params, trace.seeds, K, neighbours,
                    Liars(lies, trace.sensors.ids, n, trace.position_dims))
    # tick-major buffers: each tick writes one contiguous block
    xs = np.empty((K, B, N, n))
    Ps = np.empty((K, B, N, n, n))
    ds = np.empty((K, B, N, m))
    dv = np.empty((K, B, N), dtype=bool)
    y, has = np.moveaxis(trace.y, 1, 0), np.moveaxis(trace.has, 1, 0)
    changed = link_changes(trace.links) if links_at is None else None
    last = None
    for k in range(1, K + 1):
        if restart is not None:
            steps.state = restart(k, steps.est, steps.state)
        if links_at is None:
            links = trace.links[:, k - 1] if changed[k - 1] else None
        else:  # as ``link_changes`` says of an array: None where a tick's links are the tick before's
            links = links_at(k)
            links, last = (None, last) if last is not None and np.array_equal(links, last) else (links, links)
        out = steps.step(y[k - 1], has[k - 1], links, listen)
        xs[k - 1], Ps[k - 1], ds[k - 1], dv[k - 1] = out.x, out.P, out.d, out.d_valid
        if progress is not None:
            progress(k)
    return Estimates(*(np.moveaxis(a, 0, 1) for a in (xs, Ps, ds, dv)))


class Stepper:
    """One estimator on every agent of ``sensors`` for each seed of ``seeds``
    (a batch of B seeds x N agents), one tick at a time, at most ``ticks``:
    what ``run_batch`` does per tick, for callers that get each tick's data as
    it comes (``diskf_mesh.api.streaming``). ``state``: the agents' state
    after the last tick, ``k`` that tick. ``liars``: a ``data.lies.Liars``
    of the agents' lies (every receiver is then a batch of one, ``gather``,
    fusing its own true message and the others' as they were sent)."""

    def __init__(self, model, sensors, estimator: str, params: Params | None, seeds, ticks: int,
                 neighbours: str = "auto", liars: Liars | None = None):
        self.name = estimator
        self.est = estimators.get(estimator)(model, sensors, params)
        self.B = len(seeds)
        self.state = self.est.init((self.B, len(sensors.ids)))
        self.draws = draw_stream(self.est, seeds, ticks)
        self.liars = liars if liars else None
        self.neighbours = "gather" if self.liars else neighbours
        self.k = 0
        self.view = None

    def step(self, y: np.ndarray, has: np.ndarray, links: np.ndarray | None, listen=None) -> Output:
        """Tick k = ``self.k`` + 1: the local step on ``y`` (B, N, p_max) where
        ``has`` (B, N), then fusion over ``links`` (1 or B, N, N), or over the
        previous tick's when None. ``listen(k, msg)`` is handed the messages."""
        k = self.k = self.k + 1
        est = self.est
        try:
            self.state, msg = est.local(self.state, k, y, has)
            if listen is not None:
                listen(k, msg)
            if links is not None:
                self.view = choose_links(links, self.B, self.neighbours, slot_bytes(self.est.model.n, msg))
            draws = None if self.draws is None else self.draws[:, k - 1]
            if self.liars is None:
                self.state, out = self.view.fuse(est, self.state, msg, draws)
            else:
                self.state, out = self.view.fuse(est, self.state, msg, draws, self.liars.message(k, msg))
                out = self.liars.report(k, out)
        except np.linalg.LinAlgError as e:  # the same type, saying whose and when
            raise Diverged(f"{self.name}, tick {k}: {e} (its covariance diverged)", k) from None
        return out


class Diverged(np.linalg.LinAlgError):
    """An estimator's covariance stopped being positive definite at ``tick``
    (a ``LinAlgError`` that says whose and when)."""

    def __init__(self, message: str, tick: int):
        super().__init__(message)
        self.tick = tick




def slot_bytes(n: int, msg: Message) -> int:
    """A tick's working set per (seed, receiver, sender slot) for states of
    n and messages like ``msg``: ``TICK_BYTES_PER_SLOT`` n^2, and
    ``TICK_BYTES_PER_WEIGHT`` per model weight a message carries
    (``diskf-auto``'s bank; measured on 2,000 random-geometric agents: 300
    bytes per slot for DISKF, 943 for DISKF-auto)."""
    return TICK_BYTES_PER_SLOT * n * n + TICK_BYTES_PER_WEIGHT * msg.w.shape[-1]


def seeds_per_chunk(trace: Trace) -> int:
    """How many seeds run together so that one tick's working set, about
    ``TICK_BYTES_PER_SLOT`` n^2 bytes per (seed, receiver, sender slot), stays
    under ``TICK_BYTES_MAX``: all of them unless the network is large (1,000
    agents and 20 seeds would take ~700 MB in one batch)."""
    B, K, N = trace.has.shape
    per_slot = TICK_BYTES_PER_SLOT * trace.model.n ** 2
    if B * N * N * per_slot <= TICK_BYTES_MAX:  # even all-to-all fits
        return B
    links = trace.links[:, link_changes(trace.links)]
    slots = N * int(links.sum(axis=-1).max())
    return int(np.clip(TICK_BYTES_MAX // (slots * per_slot), 1, B))


def take_seeds(trace: Trace, index) -> Trace:
    """The trace restricted to some seeds (the leading axis)."""
    pick = lambda a: None if a is None else a[index]  # noqa: E731
    links = trace.links if trace.links.shape[0] == 1 else trace.links[index]
    return replace(trace, y=trace.y[index], has=trace.has[index], links=links, truth_x=pick(trace.truth_x),
                   truth_d=pick(trace.truth_d), seeds=tuple(np.asarray(trace.seeds)[index].tolist()))


def link_changes(links: np.ndarray) -> np.ndarray:
    """(K,) bool: the links of tick k differ from those of tick k-1 (True at k=1)."""
    K = links.shape[1]
    if links.strides[1] == 0:  # one matrix broadcast over the ticks (a static network)
        return np.arange(K) == 0
    out = np.ones(K, dtype=bool)
    out[1:] = (links[:, 1:] != links[:, :-1]).any(axis=(0, 2, 3))
    return out


STACK_LINKS_MAX = 1 << 26  # bytes of per-seed links a stacked batch may hold


def stackable(traces) -> bool:
    """Whether traces share model, sensors and horizon (only seeds, noise and
    links differ), so that ``run_many`` can batch them, and are small enough
    that the stacked per-seed links stay under ``STACK_LINKS_MAX`` (large
    networks gain nothing from stacking: their ticks are not overhead-bound)."""
    first = traces[0]
    B, (K, N) = sum(t.has.shape[0] for t in traces), first.has.shape[1:]
    if B * K * N * N > STACK_LINKS_MAX:
        return False
    for t in traces[1:]:
        if t.has.shape[1:] != first.has.shape[1:] or t.sensors.ids != first.sensors.ids:
            return False
        pairs = [(getattr(t.model, f), getattr(first.model, f)) for f in ("A", "G", "Q", "x0", "P0")]
        pairs += [(t.sensors.H, first.sensors.H), (t.sensors.R, first.sensors.R)]
        if not all(a.shape == b.shape and np.array_equal(a, b) for a, b in pairs):
            return False
    return True


def stack(traces) -> Trace:
    """One trace whose seed axis is the concatenation of the traces' seeds."""
    first = traces[0]
    K, N = first.has.shape[1:]
    cat = lambda f: np.concatenate([getattr(t, f) for t in traces])  # noqa: E731
    links = np.concatenate([np.broadcast_to(t.links, (t.has.shape[0], K, N, N)) for t in traces])
    has_truth = all(t.truth_x is not None for t in traces)
    return replace(
        first, y=cat("y"), has=cat("has"), links=links,
        truth_x=cat("truth_x") if has_truth else None,
        truth_d=cat("truth_d") if has_truth else None,
        seeds=tuple(s for t in traces for s in t.seeds),
    )


def run_many(traces, estimator: str, params: Params | None = None, progress=None, lies=()) -> list[Estimates]:
    """``run`` on each trace, batched into one run when they are ``stackable``.

    Returns one ``Estimates`` per trace, equal to running each alone."""
    traces = list(traces)
    if len(traces) == 1 or not stackable(traces):
        return [run(t, estimator, params, progress, lies=lies) for t in traces]
    est = run(stack(traces), estimator, params, progress, lies=lies)
    bounds = np.cumsum([0] + [t.has.shape[0] for t in traces])
    return [est.take(slice(a, b)) for a, b in zip(bounds[:-1], bounds[1:])]

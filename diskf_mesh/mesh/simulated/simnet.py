"""A deterministic simulated network: every mesh process in one Python
process, on a virtual clock, with the real protocol machines.

The processes are sans-I/O machines (``mesh.protocol.events``: ``start(now)``,
``handle(event, now)`` -> effects; a sample goes through ``read(key,
payload)`` first, as under zenoh). ``SimNet`` carries out their effects on
a virtual clock (``mesh.simulated.schedule``): what one publishes reaches every
process subscribed to a matching key expression (``keys.matcher``)
over a link with a delay, jitter, loss, duplication and reordering
(``Link``), under the access rules of the run's credentials
(``mesh.security.access``); liveliness tokens appear and go as zenoh's do (``Lease``);
queries reach the processes that declared a matching queryable and the
first answer comes back. Every random draw comes from one seeded
``numpy.random.Generator`` in event order, so one seed and one fault plan
give one run, event for event (``Outcome.digest``).

A fault plan (``Fault``) acts on a process at a virtual time or right after
the n-th event of the run:

    pause     as SIGSTOP: what reaches the process waits; when it runs again
              it first gets ``Woke(late)`` (a pause longer than
              ``events.FREEZE_S``, as its shell would), then what waited, in order. A
              pause longer than the lease drops the session: the others see
              its tokens go (and it sees theirs go), what reaches it after
              that is lost, and once it runs again it reconnects after
              ``Lease.reconnect``: the tokens come back both ways.
    crash     the process dies (kill -9): its timers and subscriptions go, its
              tokens go at once (a closed socket) or, with ``lease=True``,
              after the lease (a host that vanished).
    restart   a new machine of a crashed process, with the same id and
              identity and a new nonce (an incarnation).
    interrupt ``Interrupt(why)`` (SIGTERM, SIGINT) handed to the process.

A process that joins late is ``add``-ed with a later start time.

An estimator step a machine hands out (``Work``) takes no virtual time. The
network holds it and hands back its ``Worked`` before that machine's next
event, before anything else that is not a delivery or a timer (a fault, a
boot, a token's cast) and before the clock moves on; the steps held by then
run together (``protocol.estimator.Steps``: one call per step and tick over
the agents), or each alone with ``SimNet(batch_steps=False)``: one run,
event for event, either way.

Links are first in, first out between two processes (zenoh's reliable
sessions); a reordered copy is held back ``Link.hold`` longer and may be
overtaken. Loss, duplication and reordering act only on the samples whose
key matches ``Link.faulty`` (by default every sample; tokens, queries and
replies are never lost). A process does not hear its own samples (zenoh's
publishers reach other sessions only) but sees its own tokens.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import functools
import hashlib
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from diskf_mesh.mesh.protocol import events as ev
from diskf_mesh.mesh.protocol.estimator import Steps
from diskf_mesh.mesh.security.access import Access
from diskf_mesh.mesh.wire.keys import matcher
from diskf_mesh.mesh.simulated.schedule import Schedule, Trace, payload_digest

NO_LOSS = "**"
SUMS_KEPT = 1 << 13  # payload digests of a generation kept for the trace (two kept: a few ticks' samples; one
# evicted is made again)


@dataclass(frozen=True)
class Link:
    """What a link does to what crosses it (seconds, probabilities)."""

    delay: float = 0.0002     # one way
    jitter: float = 0.0       # each copy takes delay + jitter * u, u uniform in [0, 1)
    loss: float = 0.0         # a sample is lost
    duplicate: float = 0.0    # a second copy of a sample arrives (its own delay)
    reorder: float = 0.0      # a copy is held back ``hold`` longer, outside the link's order
    hold: float = 0.05
    faulty: str = NO_LOSS     # the samples loss, duplication and reordering act on (a key expression)

    def __post_init__(self):
        for name in ("delay", "jitter", "hold"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"link {name} must be a finite non-negative number of seconds, got {v!r}")
        for name in ("loss", "duplicate", "reorder"):
            v = getattr(self, name)
            if not 0 <= v <= 1:
                raise ValueError(f"link {name} must be a probability, got {v!r}")

    @property
    def faults(self) -> bool:
        return bool(self.loss or self.duplicate or self.reorder)


@dataclass(frozen=True)
class Lease:
    """zenoh's session lease: a peer silent this long (paused, or its host
    gone) is dropped with its tokens; the last keep-alive was up to
    ``keepalive`` before the silence began (zenoh: lease / 4)."""

    lease: float = 10.0
    keepalive: float = 2.5
    reconnect: float = 0.2    # a dropped process that runs again is back on the network after this


@dataclass(frozen=True)
class Fault:
    """One entry of a fault plan: ``kind`` (pause, crash, restart, start) on
    process ``pid`` at time ``at``, or right after the run's ``after_event``-th
    event."""

    kind: str
    pid: str
    at: float | None = None
    after_event: int | None = None
    duration: float = 0.0     # pause: how long
    lease: bool = False       # crash: its tokens go after the lease, not at once
    why: str = "SIGTERM"      # interrupt: the signal

    def __post_init__(self):
        if self.kind not in ("pause", "crash", "restart", "interrupt"):
            raise ValueError(f"unknown fault {self.kind!r}")
        if (self.at is None) == (self.after_event is None):
            raise ValueError("a fault is at a time or after an event, one of the two")


@dataclass(frozen=True)
class Boot:
    """What a machine factory gets to build one incarnation of a process."""

    pid: str
    identity: str | None
    incarnation: int          # 0 the first time, then one more per restart
    nonce: str                # its token suffix (``keys.new_nonce``'s shape: start time in ns, then random)
    seed: int                 # for any randomness of its own
    now: float


Factory = Callable[[Boot], Any]


@dataclass
class Outcome:
    """How a simulated run ended."""

    seed: int
    finishes: dict            # pid -> Finish of its last incarnation (absent: never finished)
    machines: dict            # pid -> the machine of its last incarnation
    end: float                # virtual time of the last event that happened
    events: int
    digest: str
    bounded: bool             # every process finished or died before the time limit
    lines: list | None = None
    refused: dict = field(default_factory=dict)  # what the access rules refused, by message kind
    lost: int = 0             # samples lost on links (Link.loss) or to a dropped session
    lost_samples: list = field(default_factory=list)  # (receiver pid, payload) of each of them


class SimError(RuntimeError):
    """A machine raised: the seed and the event say how to replay it."""


class _Proc:
    """One incarnation of a process."""

    __slots__ = ("pid", "identity", "inc", "factory", "machine", "state", "connected", "backlog", "watches",
                 "tokens", "timers", "counts", "paused_at", "pause_serial", "order", "name", "view", "arriving")

    def __init__(self, pid, identity, inc, factory, order):
        self.pid, self.identity, self.inc, self.factory, self.order = pid, identity, inc, factory, order
        self.name = f"{pid}#{inc}"  # in the trace of every event it handles
        self.machine = None
        self.state = "up"         # up, paused, dead, done
        self.connected = True
        self.backlog = []         # events that came while paused
        self.watches = []         # (key expression, matcher) of its token watches
        self.tokens = []          # keys of its declared tokens
        self.timers = {}          # name -> serial of the timer set last
        self.counts = {}          # token key -> declarations visible to it (keys its watches match)
        self.view = None          # the _View it shares (its counts are the view's), if any
        self.paused_at = 0.0
        self.pause_serial = 0
        self.arriving = ()        # the samples of the last Arrivals it was handed

    @property
    def attached(self) -> bool:
        return self.state in ("up", "paused") and self.connected

    def __repr__(self):
        return self.name


class _Routes:
    """Which subscriptions (queryables, watches) match a key: exact
    expressions in a dict, wildcard ones as compiled matchers; the answer
    kept per key, and per set of wildcard expressions a key matches, until
    the subscriptions change. A subscriber is a process or a ``_View``.

    An expression whose last chunk asks for one piece between two
    delimiters (``.../$*_7_$*``, an agent's messages addressed to it) is
    found by that piece: a key's last chunk is split once, not matched
    against every such expression."""

    def __init__(self):
        self.exact = {}       # expr -> {proc: how many times it declared it}
        self.wild = {}        # expr -> {proc: how many times}
        self.pieces = {}      # (head expr, delimiter) -> (matcher of the head, {piece: [expr]})
        self.scan = {}        # the other wildcard expressions -> matcher
        self.by_proc = {}     # proc -> its expressions
        self.memo = {}
        self.by_match = {}    # (exact expr or None, wildcard exprs matched) -> answer
        self.pairs = {}       # (proc, expr) -> that tuple: every answer holding it shares one

    def add(self, expr: str, proc) -> None:
        self.memo.clear()
        self.by_match.clear()
        if "*" in expr:
            fresh = expr not in self.wild
            ps = self.wild.setdefault(expr, {})
            ps[proc] = ps.get(proc, 0) + 1
            piece = _piece(expr)
            if fresh and piece is not None:
                head, d, x = piece
                self.pieces.setdefault((head, d), (matcher(head), {}))[1].setdefault(x, []).append(expr)
            elif fresh:
                self.scan[expr] = matcher(expr)
        else:
            ps = self.exact.setdefault(expr, {})
            ps[proc] = ps.get(proc, 0) + 1
        self.by_proc.setdefault(proc, []).append(expr)

    def remove(self, proc) -> None:
        exprs = self.by_proc.pop(proc, ())
        for e in exprs:
            self.pairs.pop((proc, e), None)
        if exprs:
            self.memo.clear()
            self.by_match.clear()
        for e in exprs:
            table = self.wild if "*" in e else self.exact
            ps = table.get(e)
            if ps is None:
                continue
            ps.pop(proc, None)
            if not ps:
                del table[e]
                self.scan.pop(e, None)
                piece = _piece(e) if table is self.wild else None
                if piece is not None:
                    head, d, x = piece
                    by_piece = self.pieces[(head, d)][1]
                    by_piece[x].remove(e)
                    if not by_piece[x]:
                        del by_piece[x]

    def match(self, key: str) -> list:
        """[(proc, expr)] in a fixed order (processes by start order, then expressions)."""
        hit = self.memo.get(key)
        if hit is None:
            wild = tuple(e for e, m in self.scan.items() if m(key))
            head, _, last = key.rpartition("/")
            for (_, d), (m, by_piece) in self.pieces.items():
                if by_piece and d in last and m(head):
                    wild += tuple(dict.fromkeys(e for x in last.split(d)[1:-1] for e in by_piece.get(x, ())))
            sig = (key if key in self.exact else None, wild)
            hit = self.by_match.get(sig)
            if hit is None:
                pair = lambda pe: self.pairs.setdefault(pe, pe)  # noqa: E731
                hit = [pair((p, key)) for p, n in self.exact.get(key, {}).items() for _ in range(n)]
                hit += [pair((p, e)) for e in wild for p, n in self.wild[e].items() for _ in range(n)]
                hit.sort(key=lambda pe: pe[0].order)
                self.by_match[sig] = hit
            if len(self.memo) > 100_000:
                self.memo.clear()
            self.memo[key] = hit
        return hit


_PIECE = re.compile(r"^(?P<head>.*)/\$\*(?P<d>[^A-Za-z0-9/*$])(?P<x>[A-Za-z0-9]*)(?P=d)\$\*$")


@functools.lru_cache(maxsize=1 << 16)
def _piece(expr: str):
    """(head, delimiter, piece) of an expression ``head/$*<d><piece><d>$*``
    whose head has no ``**`` (None otherwise): it matches a key whose head
    matches and whose last chunk has ``piece`` between two delimiters."""
    hit = _PIECE.match(expr)
    return None if hit is None or "**" in hit["head"] else (hit["head"], hit["d"], hit["x"])


class _View:
    """The token watches of processes that watch the same expressions and
    are on the network (attached): what each sees of the tokens is the
    same, so they share one count per key, and a token's coming or going
    reaches them as one ``TokenBatch`` (a cast), not one event each."""

    __slots__ = ("sig", "counts", "members", "joins", "order")

    def __init__(self, sig: tuple, order: int):
        self.sig = sig
        self.counts = {}
        self.members = {}     # proc -> the join serial it came in with
        self.joins = 0
        self.order = order    # where its casts go among the watchers of a key

    def __repr__(self):
        return f"view{self.sig}"


class _Cast:
    """Tokens that reach a view's members at one time, in one batch."""

    __slots__ = ("view", "t", "up", "keys", "serial")

    def __init__(self, view: _View, t: float, up: bool):
        self.view, self.t, self.up, self.keys, self.serial = view, t, up, [], view.joins


class _Fan:
    """Samples that arrive at one time, sent one after another with nothing
    else due at that time scheduled between them: what reaches one
    receiver goes to it as one batch (``Arrivals``), the receivers in the
    order they were first sent to, each one's samples in the order sent."""

    __slots__ = ("t", "sends")

    def __init__(self, t: float):
        self.t, self.sends = t, []  # (receivers, Sample, its tag in the trace), in the order sent


class _Batch:
    """A receiver's samples of one ``_Fan``, in order, until it handles
    them, with their tags in the trace (key and payload digest)."""

    __slots__ = ("samples", "tags")

    def __init__(self, samples: list, tags: list):
        self.samples, self.tags = samples, tags


class SimNet:
    """The world and agents of a run as machines on one virtual network."""

    def __init__(self, seed: int, link: Link = Link(), links: Callable[[str, str], Link | None] | None = None,
                 policy: dict | None = None, lease: Lease = Lease(), keep_lines: bool = False,
                 max_time: float = 3600.0, max_events: int = 50_000_000, views: bool = True,
                 batch_steps: bool = True, arrivals: bool = True):
        """``links(sender pid, receiver pid)``: a link other than ``link``
        (None: ``link``); ``policy``: the run's ``access_control``
        (``credentials.access_control``; None: no access control).
        ``views``: the machines that take ``TokenBatch`` (``batches_tokens``)
        and watch the same tokens share one view of them (``_View``) where
        every link has one constant delay; False: every process its own.
        ``batch_steps``: the estimator steps held at one instant run
        together (``Steps``); False: each alone. ``arrivals``: the samples
        that reach a machine taking ``Arrivals`` (``batches_arrivals``) at
        one instant come as one such event (``_Fan``); False: one event
        each."""
        self.seed = int(seed)
        ss = np.random.SeedSequence(self.seed)
        net, boots = ss.spawn(2)
        self.rng = np.random.default_rng(net)
        self._boot_rng = np.random.default_rng(boots)
        self.link, self._links = link, links
        self.access = Access(policy)
        self.lease = lease
        self.max_time, self.max_events = max_time, max_events
        self.sched = Schedule()
        self.trace = Trace(keep=keep_lines)
        self._procs = {}          # pid -> current incarnation
        self._all = []            # every incarnation, in start order
        self._factories = {}      # pid -> (identity, factory)
        self._subs, self._queryables, self._watches = _Routes(), _Routes(), _Routes()
        self._channel = {}        # (sender, receiver) -> time the last in-order copy arrives
        self._link_memo = {}
        self._by_event = {}       # event number -> [Fault]
        self._queries = {}        # network query id -> [asker proc, its qid, key] until answered
        self._next_query = 0
        self._timer_serial = 0
        self._finishes = {}
        self._running = 0         # incarnations neither dead nor done
        self._coming = 0          # boots and timed faults still in the queue
        self.refused = {}
        self.lost = 0
        self.lost_samples = []    # (receiver pid, payload): what the network lost, for the run's verdicts
        self._events = 0
        self._casting = views and links is None and not link.jitter
        self._views = {}          # watch expressions -> _View
        self._open = None         # the _Cast that may still take tokens
        self._holders = {}        # processes holding tokens (their order -> proc)
        self._labels = {}         # id(TokenBatch) -> (it, the digest of its keys for the trace)
        self._sums = {}           # id(Sample) -> (it, its payload's digest for the trace), while in flight
        self._sums_older = {}     # the generation before (``SUMS_KEPT``)
        self._steps = Steps() if batch_steps else None
        self._work = []           # (proc, Work) held at this instant, in the order they were handed out
        self._working = set()     # the processes waiting for their Worked
        self._fans = arrivals
        self._fan = None          # the _Fan that may still take samples
        self._put_memo = {}       # (sender identity, key) -> (the routes' match, [receivers the rules let it reach])

    # -- the run's processes and fault plan ---------------------------------
    def add(self, pid: str, factory: Factory, identity: str | None = None, at: float = 0.0) -> None:
        """Process ``pid`` (its credentials: ``identity``; default ``pid``),
        built by ``factory(Boot)``, started at time ``at``."""
        if pid in self._factories:
            raise ValueError(f"process {pid!r} is already in the run")
        self._factories[pid] = (pid if identity is None else identity, factory)
        self._coming += 1
        self._at(at, ("boot", pid))

    def plan(self, faults) -> None:
        for f in faults:
            if f.at is not None:
                self._coming += 1
                self._at(f.at, ("fault", f))
            else:
                self._by_event.setdefault(int(f.after_event), []).append(f)

    def _at(self, t: float, item) -> None:
        """Schedule ``item``; an open cast takes no more tokens once something
        else reaches one of its members at its time (each member's order stays)."""
        c = self._open
        if c is not None and max(t, self.sched.now) == c.t and item[0] != "fan" and (
                item[0] != "deliver" or item[1].view is c.view):
            self._open = None
        f = self._fan
        if f is not None and max(t, self.sched.now) == f.t:
            self._fan = None
        self.sched.at(t, item)

    # -- running --------------------------------------------------------------
    def run(self) -> Outcome:
        sched = self.sched
        while True:
            if self._work and self._due():
                self._carry_out()
            nxt = sched.pop()
            if nxt is None:
                break
            t, item = nxt
            if t > self.max_time or self._events >= self.max_events:
                break
            self._events += 1
            self._do(item)
            faults = self._by_event.pop(self._events, ())
            if faults and self._work:
                self._carry_out()
            for f in faults:
                self._fault(f)
            if self._all_over():
                break
        bounded = self._all_over()
        return Outcome(self.seed, dict(self._finishes), {pid: p.machine for pid, p in self._procs.items()},
                       self.trace.last, self.trace.events, self.trace.digest, bounded, self.trace.lines,
                       dict(self.refused), self.lost, self.lost_samples)

    def _due(self) -> bool:
        """The held steps must run before the next item: it is later, it is
        not a delivery or a timer, or it is for a process waiting for one."""
        head = self.sched.peek()
        if head is None or head[0] > self.sched.now:
            return True
        item = head[1]
        return item[0] not in ("deliver", "timer", "fan") or item[1] in self._working

    def _carry_out(self) -> None:
        """Run the held steps (together, or each alone) and hand each machine
        its ``Worked``, in the order they were handed out; the steps these
        hand out in turn run next, at the same instant."""
        while self._work:
            work, self._work = self._work, []
            works = [w for _, w in work]
            results = self._steps.carry_out(works) if self._steps is not None else [w.alone() for w in works]
            for (proc, w), result in zip(work, results):
                self._working.discard(proc)
                if proc.state == "up":
                    self._handle(proc, ev.Worked(w, result))

    def _all_over(self) -> bool:
        return bool(self._procs) and not self._running and not self._coming

    def _do(self, item) -> None:
        what = item[0]
        if what == "deliver":
            _, proc, event, local = item
            self._deliver(proc, event, local)
        elif what == "timer":
            _, proc, name, serial = item
            if proc.timers.get(name) == serial:
                self._deliver(proc, ev.Timer(name), True, serial)
        elif what == "boot":
            self._coming -= 1
            self._boot(item[1])
        elif what == "fault":
            self._coming -= 1
            self._fault(item[1])
        elif what == "resume":
            self._resume(item[1], item[2])
        elif what == "expire":
            self._expire(item[1], item[2])
        elif what == "reconnect":
            self._reconnect(item[1])
        elif what == "linger":
            self._tokens_gone(item[1])
        elif what == "query-timeout":
            self._query_timeout(item[1])
        elif what == "tokens-now":
            self._tokens_now(*item[1:])
        elif what == "cast":
            self._cast_out(item[1])
        elif what == "fan":
            self._fan_out(item[1])

    def _deliver(self, proc: _Proc, event, local: bool = False, timer: int | None = None) -> None:
        """``local``: from the process itself (a timer, its own token, a
        query's end), not over its session."""
        if proc.state == "paused" and (local or proc.connected):
            proc.backlog.append((event, timer))
            return
        if proc.state != "up" or not (local or proc.connected):
            if isinstance(event, ev.Sample):
                self._lose(proc, (event,))
            elif type(event) is _Batch:
                self._lose(proc, event.samples)
            return
        self._handle(proc, event)

    def _lose(self, proc: _Proc, samples) -> None:
        """``samples`` sent to ``proc`` never reach its machine."""
        self.lost += len(samples)
        self.lost_samples.extend((proc.pid, e.payload) for e in samples)

    def _handle(self, proc: _Proc, event) -> None:
        if proc in self._working:  # its step first (a backlog after a pause, a cast)
            self._carry_out()
        now = self.sched.now
        self._log(proc, event)
        try:
            machine = proc.machine
            kind = type(event)
            if kind is ev.Sample:
                event = machine.read(event.key, event.payload)
            elif kind is _Batch:
                proc.arriving = event.samples
                event = ev.Arrivals(machine.read_all(event.samples))
            effects = machine.handle(event, now)
        except Exception as e:
            raise SimError(f"seed {self.seed}: {proc!r} raised {type(e).__name__} at t={now:.6f} on "
                           f"{_describe(event)} (event {self._events}; SimNet(seed={self.seed}) with the same "
                           f"plan replays it)") from e
        if kind is _Batch and not getattr(machine, "waiting", 0):
            proc.arriving = ()  # all taken: nothing of it to lose
        self._apply(proc, effects or ())

    def _log(self, proc, event) -> None:
        t = self.sched.now
        who = proc.name
        if isinstance(event, ev.Sample):
            self.trace.add(t, who, "sample", event.key, event.payload, self._sum(event))
        elif isinstance(event, ev.Token):
            self.trace.add(t, who, "token+" if event.up else "token-", event.key)
        elif isinstance(event, ev.Timer):
            self.trace.add(t, who, "timer", event.name)
        elif isinstance(event, ev.Query):
            self.trace.add(t, who, "query", event.key, event.payload)
        elif isinstance(event, ev.Reply):
            self.trace.add(t, who, f"reply {event.qid}", "", event.payload)
        elif isinstance(event, ev.Woke):
            self.trace.add(t, who, f"woke {event.late!r}")
        elif isinstance(event, ev.Tokens):
            self.trace.add(t, who, f"tokens {event.qid}", " ".join(event.keys))
        elif isinstance(event, ev.TokenBatch):
            self.trace.add(t, who, "tokens+" if event.up else "tokens-", self._label(event))
        elif type(event) is _Batch:
            self.trace.add(t, who, f"samples {len(event.samples)}", "", b"".join(event.tags))
        else:
            self.trace.add(t, who, type(event).__name__)

    def _sum(self, event: ev.Sample) -> bytes:
        """The digest of a sample's payload, made once for all its receivers."""
        hit = self._sums.get(id(event)) or self._sums_older.get(id(event))
        return hit[1] if hit is not None and hit[0] is event else payload_digest(event.payload)

    # -- processes --------------------------------------------------------------
    def _boot(self, pid: str) -> None:
        old = self._procs.get(pid)
        if old is not None and old.state not in ("dead", "done"):
            return  # a restart of a process that is running: nothing to do
        identity, factory = self._factories[pid]
        inc = 0 if old is None else old.inc + 1
        now = self.sched.now
        proc = _Proc(pid, identity, inc, factory, len(self._all))
        self._running += 1
        self._procs[pid] = proc
        self._all.append(proc)
        r = self._boot_rng.integers(0, 2 ** 32, size=3)
        boot = Boot(pid, identity, inc, f"{int(round(now * 1e9)):016x}{int(r[0]):08x}",
                    int(r[1]) << 32 | int(r[2]), now)
        self.trace.add(now, repr(proc), "boot")
        try:
            proc.machine = factory(boot)
            effects = proc.machine.start(now)
        except Exception as e:
            raise SimError(f"seed {self.seed}: {proc!r} raised {type(e).__name__} starting at t={now:.6f}") from e
        self._apply(proc, effects or ())

    def _fault(self, f: Fault) -> None:
        now = self.sched.now
        proc = self._procs.get(f.pid)
        self.trace.add(now, f.pid, f"fault {f.kind}")
        if f.kind == "restart":
            if proc is not None and proc.state in ("dead", "done"):
                self._boot(f.pid)
            return
        if proc is None:
            return
        if f.kind == "pause" and proc.state == "up" and f.duration > 0:
            proc.state, proc.paused_at = "paused", now
            proc.pause_serial += 1
            self._at(now + f.duration, ("resume", proc, proc.pause_serial))
            # the last keep-alive went out up to ``keepalive`` before the pause
            expiry = self.lease.lease - self.lease.keepalive * float(self.rng.random())
            if f.duration > expiry:
                self._at(now + expiry, ("expire", proc, proc.pause_serial))
        elif f.kind == "interrupt":
            self._deliver(proc, ev.Interrupt(f.why), True)
        elif f.kind == "crash" and proc.state in ("up", "paused"):
            self._end(proc, "dead", lingering=f.lease)

    def _end(self, proc: _Proc, state: str, lingering: bool = False) -> None:
        """The process is gone (crashed, or finished): nothing reaches it any more."""
        was_attached = proc.attached
        self._running -= 1
        proc.state = state
        left = getattr(proc.machine, "waiting", 0)
        if left:  # the rest of its last Arrivals never reached it
            self._lose(proc, proc.arriving[-left:])
        proc.timers.clear()
        proc.backlog.clear()
        self._leave(proc)
        for routes in (self._subs, self._queryables, self._watches):
            routes.remove(proc)
        if not was_attached:
            self._drop_tokens(proc)  # already invisible to the others
        elif lingering:
            self._at(self.sched.now + self.lease.lease, ("linger", proc))
        else:
            self._tokens_gone(proc)

    def _tokens_gone(self, proc: _Proc) -> None:
        for key in proc.tokens:
            self._token_to_all(proc, key, -1)
        self._drop_tokens(proc)

    def _drop_tokens(self, proc: _Proc) -> None:
        proc.tokens.clear()
        self._holders.pop(proc.order, None)

    def _owners(self):
        """The processes holding tokens, in start order."""
        return [self._holders[o] for o in sorted(self._holders)]

    def _resume(self, proc: _Proc, serial: int) -> None:
        if proc.state != "paused" or proc.pause_serial != serial:
            return
        now = self.sched.now
        proc.state = "up"
        backlog, proc.backlog = proc.backlog, []
        if not proc.connected:
            self._at(now + self.lease.reconnect, ("reconnect", proc))
        if now - proc.paused_at > ev.FREEZE_S:  # as a shell: a shorter stop is a slow process
            self._handle(proc, ev.Woke(now - proc.paused_at))
        for event, timer in backlog:
            if proc.state != "up":
                break
            if timer is not None and proc.timers.get(event.name) != timer:
                continue  # set again or cancelled since
            if timer is not None:
                del proc.timers[event.name]
            self._handle(proc, event)

    def _expire(self, proc: _Proc, serial: int) -> None:
        """A paused process's lease ran out: the others drop its session, it drops theirs."""
        if proc.state != "paused" or proc.pause_serial != serial or not proc.connected:
            return
        self.trace.add(self.sched.now, repr(proc), "lease expired")
        self._leave(proc, own=True)
        self._session(proc, -1)
        proc.connected = False

    def _reconnect(self, proc: _Proc) -> None:
        if proc.state not in ("up", "paused") or proc.connected:
            return
        self.trace.add(self.sched.now, repr(proc), "reconnected")
        proc.connected = True
        self._session(proc, +1)

    def _session(self, proc: _Proc, delta: int) -> None:
        """``proc``'s links to every other process went down (-1) or came up (+1):
        the tokens across them go or come, both ways. A session that went
        down tells its own process (as zenoh's session does when it finds
        its transports closed): a paused process hears it when it wakes,
        after what had reached it before."""
        for key in proc.tokens:
            self._token_to_all(proc, key, delta, others_only=True)
        for owner in self._owners():
            if owner is not proc and self._visible(owner, proc, assume_attached=True):
                for key in owner.tokens:
                    self._token_to(owner, proc, key, delta, local=delta < 0)

    # -- effects ---------------------------------------------------------------
    def _apply(self, proc: _Proc, effects) -> None:
        now = self.sched.now
        for e in effects:
            if proc.state in ("dead", "done"):
                return
            kind = type(e)
            if kind is ev.Publish:
                self._publish(proc, e.key, e.payload)
            elif kind is ev.SetTimer:
                self._timer_serial += 1
                proc.timers[e.name] = self._timer_serial
                self._at(e.at, ("timer", proc, e.name, self._timer_serial))
            elif kind is ev.CancelTimer:
                proc.timers.pop(e.name, None)
            elif kind is ev.Subscribe:
                if self._may(proc, "declare_subscriber", e.key):
                    self._subs.add(e.key, proc)
            elif kind is ev.WatchTokens:
                if self._may(proc, "declare_liveliness_subscriber", e.key):
                    self._watch(proc, e.key)
            elif kind is ev.DeclareQueryable:
                if self._may(proc, "declare_queryable", e.key):
                    self._queryables.add(e.key, proc)
            elif kind is ev.DeclareToken:
                if self._may(proc, "liveliness_token", e.key):
                    proc.tokens.append(e.key)
                    self._holders[proc.order] = proc
                    self._own_token(proc, e.key, +1)
            elif kind is ev.DropToken:
                if e.key in proc.tokens:
                    proc.tokens.remove(e.key)
                    if not proc.tokens:
                        self._holders.pop(proc.order, None)
                    self._own_token(proc, e.key, -1)
            elif kind is ev.AskTokens:
                self._ask_tokens(proc, e)
            elif kind is ev.Ask:
                self._ask(proc, e)
            elif kind is ev.Answer:
                self._answer(proc, e)
            elif kind is ev.HandOver:
                e.carry_out()
            elif kind is ev.Work:
                self._work.append((proc, e))
                self._working.add(proc)
            elif kind is ev.Finish:
                self._finishes[proc.pid] = e
                self.trace.add(now, repr(proc), f"finish {e.status} {e.code}", e.reason)
                self._end(proc, "done")
                return
            else:
                raise SimError(f"seed {self.seed}: {proc!r} returned {e!r}, not an effect")

    def _own_token(self, proc: _Proc, key: str, delta: int) -> None:
        """``proc`` declared (+1) or dropped (-1) a token: everyone sees it, or,
        cut off from the network, itself alone."""
        if proc.connected:
            self._token_to_all(proc, key, delta)
        else:
            self._token_to(proc, proc, key, delta)

    def _may(self, proc: _Proc, message: str, key: str) -> bool:
        if self.access.allowed(proc.identity, message, key):
            return True
        self.refused[message] = self.refused.get(message, 0) + 1
        self.trace.add(self.sched.now, repr(proc), f"refused {message}", key)
        return False

    # -- samples -----------------------------------------------------------------
    def _link(self, a: _Proc, b: _Proc) -> Link:
        if self._links is None:
            return self.link
        k = (a.pid, b.pid)
        hit = self._link_memo.get(k)
        if hit is None:
            hit = self._links(a.pid, b.pid) or self.link
            self._link_memo[k] = hit
        return hit

    def _arrival(self, a: _Proc, b: _Proc, link: Link, held: bool = False) -> float:
        """When a copy sent now from a to b arrives: in the link's order, unless held back."""
        now = self.sched.now
        t = now + link.delay + (link.jitter * float(self.rng.random()) if link.jitter else 0.0)
        if held:
            return t + link.hold
        if not link.jitter:  # a constant delay keeps the link's order by itself (and no pair's entry is kept)
            return t
        ch = (a, b)
        t = max(t, self._channel.get(ch, 0.0))
        self._channel[ch] = t
        return t

    def _send(self, a: _Proc, b: _Proc, event, faulty: bool = False) -> None:
        link = self._link(a, b)
        if a is b:
            self._at(self.sched.now, ("deliver", b, event, True))
            return
        if faulty and link.faults:
            rng = self.rng
            if link.loss and rng.random() < link.loss:
                self.lost += 1
                self.lost_samples.append((b.pid, event.payload))
                return
            copies = 2 if link.duplicate and rng.random() < link.duplicate else 1
            for _ in range(copies):
                held = bool(link.reorder and rng.random() < link.reorder)
                self._reach(self._arrival(a, b, link, held), [b], event)
            return
        self._reach(self._arrival(a, b, link), [b], event)

    def _reach(self, t: float, receivers: list, event) -> None:
        """``event`` reaches each of ``receivers`` at ``t``: a sample in the
        open ``_Fan`` of that time (a new one if there is none)."""
        if not (self._fans and type(event) is ev.Sample):
            for b in receivers:
                self._at(t, ("deliver", b, event, False))
            return
        f = self._fan
        if f is None or f.t != t:
            f = _Fan(t)
            self._at(t, ("fan", f))
            self._fan = f
        c = self._open
        if c is not None and c.t == t and any(b.view is c.view for b in receivers):
            self._open = None  # the cast's members have this sample first
        f.sends.append((receivers, event, self._sum(event) + event.key.encode()))

    def _fan_out(self, f: _Fan) -> None:
        """A fan's samples arrive: each receiver's as one batch, if its
        machine takes ``Arrivals``; one by one otherwise."""
        if self._fan is f:
            self._fan = None
        by = {}
        for receivers, event, tag in f.sends:
            for b in receivers:
                got = by.get(b)
                if got is None:
                    by[b] = ([event], [tag])
                else:
                    got[0].append(event)
                    got[1].append(tag)
        for b, (samples, tags) in by.items():
            if len(samples) > 1 and getattr(b.machine, "batches_arrivals", False):
                self._deliver(b, _Batch(samples, tags))
            else:
                for e in samples:
                    self._deliver(b, e)

    def _publish(self, proc: _Proc, key: str, payload: bytes) -> None:
        if not proc.connected:
            return
        event = ev.Sample(key, bytes(payload))
        digest = payload_digest(event.payload)
        self.trace.add(self.sched.now, repr(proc), "put", key, event.payload, digest)
        if len(self._sums) > SUMS_KEPT:  # a new generation; the one before is kept for the samples still in flight
            self._sums_older, self._sums = self._sums, {}
        self._sums[id(event)] = (event, digest)
        hit = self._subs.match(key)
        if self._links is None and not self.link.faults and not self.link.jitter:  # one link for all: at once
            memo = self._put_memo.get((proc.identity, key))
            if memo is None or memo[0] is not hit:
                if len(self._put_memo) > 100_000:
                    self._put_memo.clear()
                access = self.access
                may = [access.put(proc.identity, q.identity, key, expr) if access.enabled else True for q, expr in hit]
                memo = self._put_memo[(proc.identity, key)] = (hit, [q for (q, _), ok in zip(hit, may) if ok],
                                                                [q for (q, _), ok in zip(hit, may) if not ok])
            refused = sum(1 for q in memo[2] if q is not proc and q.attached)
            if refused:
                self.refused["put"] = self.refused.get("put", 0) + refused
            receivers = [q for q in memo[1] if q is not proc and q.attached]
            if receivers:
                self._reach(self._arrival(proc, proc, self.link), receivers, event)
            return
        access = self.access
        for q, expr in hit:
            if q is proc or not q.attached:
                continue
            if access.enabled and not access.put(proc.identity, q.identity, key, expr):
                self.refused["put"] = self.refused.get("put", 0) + 1
                continue
            link = self._link(proc, q)
            self._send(proc, q, event, faulty=link.faults and _faulty(link, key))

    # -- liveliness ----------------------------------------------------------------
    def _watch(self, proc: _Proc, expr: str) -> None:
        """A new watch: the tokens visible now come first (zenoh's history)."""
        m = matcher(expr)
        older = [mm for _, mm in proc.watches]
        proc.watches.append((expr, m))
        if self._casting and getattr(proc.machine, "batches_tokens", False) and proc.attached \
                and (proc.view is not None or not older):
            self._join(proc)
        else:
            self._watches.add(expr, proc)
        owners = self._owners()
        news = {}  # key -> a process holding it (its link carries the news)
        for owner in owners:
            if self._visible(owner, proc):
                for key in owner.tokens:
                    if m(key):
                        if proc.view is None and not any(mm(key) for mm in older):  # not counted so far
                            proc.counts[key] = proc.counts.get(key, 0) + 1
                        news.setdefault(key, owner)
        for key, owner in news.items():
            if proc.counts.get(key, 0) > 0:
                self._send(owner, proc, ev.Token(key, True))

    def _join(self, proc: _Proc) -> None:
        """``proc`` (on the network, its watches just made) shares the view of
        whoever watches what it watches; the view's counts are what any of
        them sees."""
        self._leave(proc)
        sig = tuple(e for e, _ in proc.watches)
        view = self._views.get(sig)
        if view is None:
            view = self._views[sig] = _View(sig, proc.order)
            ms = [m for _, m in proc.watches]
            for owner in self._owners():
                if owner is proc or owner.attached or (owner.state == "dead" and owner.connected):
                    for key in owner.tokens:
                        if any(m(key) for m in ms):
                            view.counts[key] = view.counts.get(key, 0) + 1
            for e in sig:
                self._watches.add(e, view)
        view.joins += 1
        view.members[proc] = view.joins
        proc.view, proc.counts = view, view.counts
        if self._open is not None and self._open.view is view:
            self._open = None

    def _leave(self, proc: _Proc, own: bool = False) -> None:
        """``proc`` no longer shares its view (it left the network, or its
        watches change); ``own``: it keeps watching, with its own counts."""
        view = proc.view
        if view is None:
            return
        proc.view = None
        del view.members[proc]
        if own:
            proc.counts = dict(view.counts)
            for e, _ in proc.watches:
                self._watches.add(e, proc)
        if not view.members:
            self._watches.remove(view)
            del self._views[view.sig]

    def _visible(self, owner: _Proc, proc: _Proc, assume_attached: bool = False) -> bool:
        """Whether ``owner``'s tokens reach ``proc`` now (a crashed process's
        linger until its lease runs out)."""
        if owner is proc:
            return proc.state in ("up", "paused")
        owner_on = owner.attached or (owner.state == "dead" and owner.connected)
        return owner_on and (assume_attached or proc.attached)

    def _token_to_all(self, owner: _Proc, key: str, delta: int, others_only: bool = False) -> None:
        watchers = {}
        for q, _ in self._watches.match(key):
            watchers[q] = watchers.get(q, 0) + 1
        for q, n in watchers.items():
            if type(q) is _View:
                self._token_to_view(owner, q, key, delta, n, others_only)
            elif q is owner:
                if not others_only and q.state in ("up", "paused"):
                    self._token_to(owner, q, key, delta, n)
            elif q.attached:
                self._token_to(owner, q, key, delta, n)

    def _token_to_view(self, owner: _Proc, view: _View, key: str, delta: int, n: int, others_only: bool) -> None:
        """As ``_token_to`` for every member of ``view``: one count, one cast;
        an owner among them hears its own token at once too (its own session),
        and again in the batch (a machine that batches tokens counts a
        process's token once)."""
        before = view.counts.get(key, 0)
        after = max(0, before + delta)
        view.counts[key] = after
        if (before == 0) == (after == 0):
            return
        if owner.view is view and not others_only:
            for _ in range(n):
                self._at(self.sched.now, ("deliver", owner, ev.Token(key, after > 0), True))
        t = self.sched.now + self.link.delay
        for _ in range(n):
            c = self._open
            if c is None or c.view is not view or c.t != t or c.up != (after > 0):
                c = _Cast(view, t, after > 0)
                self._at(t, ("cast", c))
                self._open = c
            c.keys.append(key)

    def _cast_out(self, c: _Cast) -> None:
        """A cast arrives: one batch to every member of its view that was
        there when it was sent."""
        if self._open is c:
            self._open = None
        event = ev.TokenBatch(tuple(c.keys), c.up)
        for q, joined in list(c.view.members.items()):
            if joined <= c.serial:
                self._deliver(q, event)

    def _label(self, event: ev.TokenBatch) -> str:
        """The digest of a batch's keys, computed once for all its receivers."""
        hit = self._labels.get(id(event))
        if hit is None or hit[0] is not event:
            if len(self._labels) > 64:
                self._labels.clear()
            h = hashlib.blake2b(digest_size=16)
            for key in event.keys:
                h.update(key.encode() + b"\n")
            hit = self._labels[id(event)] = (event, f"{len(event.keys)} {h.hexdigest()}")
        return hit[1]

    def _token_to(self, owner: _Proc, q: _Proc, key: str, delta: int, watches: int | None = None,
                  local: bool = False) -> None:
        """One declaration of ``key`` became visible (+1) or invisible (-1) to
        ``q``; ``local``: ``q``'s own session says so (no link to cross)."""
        if watches is None:
            watches = sum(1 for _, m in q.watches if m(key))
        if not watches:
            return
        before = q.counts.get(key, 0)
        after = max(0, before + delta)
        q.counts[key] = after
        if (before == 0) != (after == 0):
            for _ in range(watches):
                if local:
                    self._at(self.sched.now, ("deliver", q, ev.Token(key, after > 0), True))
                else:
                    self._send(owner, q, ev.Token(key, after > 0))

    # -- queries -------------------------------------------------------------------
    def _ask(self, proc: _Proc, e: ev.Ask) -> None:
        self._next_query += 1
        nq = self._next_query
        self._queries[nq] = [proc, e.qid, e.key]
        self.trace.add(self.sched.now, repr(proc), f"ask {e.qid}", e.key, e.payload)
        targets = []
        if proc.connected and self._may(proc, "query", e.key):
            seen = []
            for q, _ in self._queryables.match(e.key):
                if q is not proc and q.attached and q not in seen:
                    seen.append(q)
            targets = seen
        for q in targets:
            self._send(proc, q, ev.Query(nq, e.key, bytes(e.payload)))
        # no queryable: the answer "none" comes after a round trip
        wait = e.timeout if targets else 2 * self.link.delay
        self._at(self.sched.now + wait, ("query-timeout", nq))

    def _ask_tokens(self, proc: _Proc, e: ev.AskTokens) -> None:
        """A liveliness query: the tokens held when it reaches the others
        (one link delay), back one delay later; none if the asker is cut off,
        and none of a holder whose round trip (``links``) exceeds the
        query's timeout."""
        self.trace.add(self.sched.now, repr(proc), f"ask-tokens {e.qid}", e.key)
        if not (proc.connected and self._may(proc, "liveliness_query", e.key)):
            self._at(self.sched.now + e.timeout, ("deliver", proc, ev.Tokens(e.qid, ()), True))
            return
        self._at(self.sched.now + self.link.delay, ("tokens-now", proc, e.qid, e.key, e.timeout))

    def _tokens_now(self, proc: _Proc, qid: int, expr: str, timeout: float) -> None:
        m = matcher(expr)
        keys = sorted({key for owner in self._owners() if self._visible(owner, proc)
                       and (owner is proc or self._link(proc, owner).delay + self._link(owner, proc).delay <= timeout)
                       for key in owner.tokens if m(key)})
        self._at(self.sched.now + self.link.delay, ("deliver", proc, ev.Tokens(qid, tuple(keys)), True))

    def _answer(self, proc: _Proc, e: ev.Answer) -> None:
        """The first answer goes back to the asker; later ones are dropped."""
        self.trace.add(self.sched.now, repr(proc), f"answer {e.qid}", "", e.payload)
        q = self._queries.get(e.qid)
        if q is None or not proc.connected or not self._may(proc, "reply", q[2]):
            return
        del self._queries[e.qid]
        self._send(proc, q[0], ev.Reply(q[1], bytes(e.payload)))

    def _query_timeout(self, nq: int) -> None:
        q = self._queries.pop(nq, None)
        if q is not None:
            self._deliver(q[0], ev.Reply(q[1], None), True)


def _faulty(link: Link, key: str) -> bool:
    return link.faulty == NO_LOSS or bool(matcher(link.faulty)(key))


def _describe(event) -> str:
    if isinstance(event, (ev.Sample, ev.Query)):
        return f"{type(event).__name__}({event.key!r}, {len(event.payload)} bytes)"
    return repr(event)

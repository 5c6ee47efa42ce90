"""The shell that runs one protocol machine over a ``Transport`` on the real clock.

A protocol machine (``mesh.protocol.world_machine``, ``mesh.protocol.agent_machine``) decides
everything and does nothing (``mesh.protocol.events``). ``Shell`` is all it needs to
run as a process:

    one lock      every event is handed to the machine under ``_cv`` (a
                  condition on a re-entrant lock), one at a time, with the
                  monotonic time ``now``; the effects it returns are carried
                  out right there, in order (a put, a token, a timer; an
                  estimator step, ``Work``, at once: its ``Worked`` goes
                  back to the machine with the same ``now``)
    callbacks     the transport's threads (zenoh's network thread) call in
                  with samples (each read by the machine into its event,
                  ``machine.read``), token changes, queries and replies: the
                  event goes to the machine on that thread, with no hop to
                  another (a report that completes a tick opens the next in
                  zenoh's callback)
    the main      thread starts the machine, does the liveliness work
                  (``AskTokens``, ``DeclareToken``, ``DropToken``, in order,
                  outside the lock and off the transport's thread: they wait
                  on the network, and a callback held up would stall every
                  sample behind it), fires the timers (``Timer``) when they are due,
                  and sleeps until the earliest one (at most ``POLL_S`` at a
                  time). Waking more than ``FREEZE_S`` later than planned,
                  or a callback finding the main thread that late, means the
                  process was not running (SIGSTOP, starved): ``Woke(late)``
    interrupt     ``interrupt(why)`` (a signal handler may call it) hands the
                  machine ``Interrupt(why)`` at the main thread's next look
    failures      whatever a callback raises is kept (the first one) and
                  raised by the main thread
    the end       ``run`` returns the machine's ``Finish``

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

import itertools
import math
import threading
import time

from diskf_mesh.mesh.protocol.events import (FREEZE_S, Answer, Ask, AskTokens, CancelTimer, DeclareQueryable, DeclareToken,
                                    DropToken, Finish, HandOver, Interrupt, Publish, Query, Reply, SetTimer, Subscribe,
                                    Timer, Token, Tokens, WatchTokens, Woke, Work, Worked)
from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.process.transport import Transport

POLL_S = 0.5  # the main thread looks at its timers at least this often
QUERIES_HELD = 1024  # unanswered queries kept for the machine to answer later


class Shell:
    """Runs ``machine`` over ``transport`` (module docstring); ``profile``
    counts the callbacks as "other" and the puts as "publish"; ``clock``
    is the monotonic clock (seconds)."""

    def __init__(self, machine, transport: Transport, profile: Phases = NO_PHASES, clock=time.monotonic):
        self.machine = machine
        self.transport = transport
        self.prof = profile
        self.clock = clock
        self._cv = threading.Condition(threading.RLock())
        self._timers = {}             # name -> at (``clock``)
        self._tokens = {}             # key -> the transport's token
        self._queries = {}            # qid -> reply function of a query the machine has not answered yet
        self._qids = itertools.count(1)
        self._asks = []               # AskTokens, DeclareToken, DropToken for the main thread, in order
        self._finish: Finish | None = None
        self._failure: BaseException | None = None
        self._interrupt = ""          # set by ``interrupt`` (no lock: a signal handler may call it)
        self._main_looks_at = math.inf  # when the main thread looks next (inf: awake, or a callback said Woke)

    # -- events into the machine (lock held) -----------------------------------
    def _handle(self, event, now: float | None = None) -> None:
        if self._finish is None:
            now = self.clock() if now is None else now
            self._do(self.machine.handle(event, now), now)

    def _feed(self, event) -> None:
        """A transport callback's event: first ``Woke`` if the main thread
        is overdue by more than ``FREEZE_S`` (the process was not running)."""
        self.prof.begin()
        try:
            with self._cv:
                now = self.clock()
                if now - self._main_looks_at > FREEZE_S:
                    late, self._main_looks_at = now - self._main_looks_at, math.inf  # said once, not by main again
                    self._handle(Woke(late), now)
                self._handle(event, now)
        except BaseException as e:  # noqa: BLE001 - a callback must not swallow a failure
            self._fail(e)
        finally:
            self.prof.end("other")

    def _fail(self, e: BaseException) -> None:
        with self._cv:
            if self._failure is None:
                self._failure = e
            self._cv.notify_all()

    def _on_sample(self, key: str, payload: bytes) -> None:
        """A sample, read by the machine (``machine.read``: an agent's is
        decoded there, once) into the event it handles."""
        try:
            event = self.machine.read(key, payload)
        except BaseException as e:  # noqa: BLE001 - a callback must not swallow a failure
            return self._fail(e)
        self._feed(event)

    def _on_query(self, key: str, payload: bytes, reply) -> None:
        with self._cv:
            qid = next(self._qids)
            self._queries[qid] = reply
            if len(self._queries) > QUERIES_HELD:  # a flood: the oldest unanswered goes (its asker times out)
                del self._queries[next(iter(self._queries))]
        self._feed(Query(qid, key, payload))

    # -- effects out of the machine (lock held) ----------------------------------
    def _do(self, effects, now: float) -> None:
        for e in effects:
            if isinstance(e, Work):
                self._handle(Worked(e, e.alone()), now)
            elif isinstance(e, Publish):
                self.prof.begin()
                self.transport.put(e.key, e.payload, express=e.express)
                self.prof.end("publish")
            elif isinstance(e, SetTimer):
                self._timers[e.name] = e.at
                if e.at < self._main_looks_at != math.inf:  # it sleeps past it (awake, it looks anyway)
                    self._cv.notify_all()
            elif isinstance(e, CancelTimer):
                self._timers.pop(e.name, None)
            elif isinstance(e, Answer):
                reply = self._queries.pop(e.qid, None)
                if reply is not None:
                    reply(e.payload)
            elif isinstance(e, Subscribe):
                self.transport.subscribe(e.key, self._on_sample)
            elif isinstance(e, WatchTokens):
                self.transport.watch_tokens(e.key, lambda key, up: self._feed(Token(key, bool(up))))
            elif isinstance(e, DeclareQueryable):
                self.transport.declare_queryable(e.key, self._on_query)
            elif isinstance(e, Ask):
                self.transport.query(e.key, e.payload, e.timeout, lambda p, qid=e.qid: self._feed(Reply(qid, p)))
            elif isinstance(e, (AskTokens, DeclareToken, DropToken)):  # the main thread, off the lock
                self._asks.append(e)
                self._cv.notify_all()
            elif isinstance(e, HandOver):
                e.carry_out()
            elif isinstance(e, Finish):
                self._finish = e
                self._cv.notify_all()
            else:  # pragma: no cover - a new effect without a shell
                raise TypeError(f"the shell cannot carry out {e!r}")

    # -- the main thread ------------------------------------------------------------
    def interrupt(self, why: str) -> None:
        """Hand the machine ``Interrupt(why)`` at the main thread's next look."""
        self._interrupt = why

    def start(self) -> None:
        """Start the machine: carry out its first effects (what it listens to)."""
        with self._cv:
            now = self.clock()
            self._do(self.machine.start(now), now)

    def run(self) -> Finish:
        """Start the machine and run it until its ``Finish``; a callback's
        failure is raised here."""
        self.start()
        while True:
            with self._cv:
                asks, self._asks = self._asks, []
            for a in asks:  # liveliness waits on the network: not under the lock, not on its thread
                if isinstance(a, DeclareToken):
                    self._tokens[a.key] = self.transport.declare_token(a.key)
                elif isinstance(a, DropToken):
                    token = self._tokens.pop(a.key, None)
                    if token is not None:
                        token.undeclare()
                else:
                    keys = tuple(self.transport.tokens(a.key, a.timeout))
                    with self._cv:
                        self._handle(Tokens(a.qid, keys))
            with self._cv:
                if self._failure is not None:
                    raise self._failure
                if self._finish is not None:
                    return self._finish
                if self._asks:
                    continue
                if self._interrupt:
                    why, self._interrupt = self._interrupt, ""
                    self._handle(Interrupt(why))
                    continue
                now = self.clock()
                name = min(self._timers, key=self._timers.__getitem__, default=None)
                if name is not None and self._timers[name] <= now:
                    del self._timers[name]
                    self._handle(Timer(name))
                    continue
                until = min(self._timers[name] if name is not None else math.inf, now + POLL_S)
                self._main_looks_at = until
                self._cv.wait(max(0.0, until - now))
                planned, self._main_looks_at = self._main_looks_at, math.inf
                late = self.clock() - planned
                if late > FREEZE_S:
                    self._handle(Woke(late))

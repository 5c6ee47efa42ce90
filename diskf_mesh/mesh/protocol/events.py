"""The sans-I/O boundary: events into a protocol machine, effects out of it.

A protocol machine (the world's, an agent's) holds the state of one mesh
process and nothing else: no thread, no socket, no clock read. Its shell
(zenoh and the wall clock in ``mesh.process.shell``, run by ``sim.world`` and
``agents.agent``, or the seeded
simulated network) reads the clock, hands it one event at a time with the
time ``now`` (seconds; monotonic or virtual), and carries out the effects
it returns, in order::

    effects = machine.start(now)
    effects = machine.handle(event, now)

Events (what happened to the process):

    Sample(key, payload)      a sample on a key the process subscribes to
    Token(key, up)            a liveliness token appeared (up) or went
    TokenBatch(keys, up)      the tokens of ``keys`` appeared (up) or went at
                              one instant: ``Token(key, up)`` for each key, in
                              order (a shell that delivers many tokens to many
                              machines at once: the simulated network)
    Arrivals(events)          samples that reached the process at one instant,
                              each as ``read`` made it, in order: each one
                              handled alone, in turn (a shell that delivers
                              many samples to many machines at once: the
                              simulated network). A machine that hands out
                              ``Work`` on one of them takes the rest once its
                              ``Worked`` is in, as it would take the next
                              samples; ``waiting`` says how many it holds
    Timer(name)               a timer the machine set (``SetTimer``) fired
    Query(qid, key, payload)  a query on a key this process answers
    Reply(qid, payload)       the answer to a query this process made
                              (payload None: no answer came)
    Woke(late)                the process ran again ``late`` seconds after it
                              should have (it was paused, e.g. SIGSTOP); a
                              shell reports a wake-up later than ``FREEZE_S``
    Tokens(qid, keys)         the answer to ``AskTokens``: the keys of the
                              tokens the network holds now
    Interrupt(why)            the process was told to stop (a signal's name)
    Worked(work, result)      the result of a ``Work`` (its step's value, or
                              the ``numpy.linalg.LinAlgError`` it raised),
                              before any other event

A shell reads every ``Sample`` through its machine first,
``machine.read(key, payload)``: the world handles the sample as it is; an
agent's comes back decoded once, at its edge (``mesh.protocol.intake``), as
one of

    TickArrived(tick)         the world's tick (a ``wire.Tick``)
    MeasurementArrived(measurement)   this agent's measurement (``wire.Measurement``)
    StopArrived(stop)         the world's stop (``wire.Stop``)
    MessageArrived(sender, message, problem)
                              a neighbour's message: the id its key names,
                              the decoded ``wire.WireMessage`` (or the
                              ``wire.Rejected`` its decode raised) and what
                              the checks of its own values found
                              (``guard.Guard.read``)
    Unreadable(kind, reason, detail)  a world's payload that does not decode

Effects (what the process does):

    Subscribe(key)                  deliver the samples of a key expression
                                    (``Sample`` events) from now on
    WatchTokens(key)                deliver the liveliness tokens of a key
                                    expression (``Token`` events), those
                                    already declared first
    DeclareQueryable(key)           deliver the queries on a key expression
                                    (``Query`` events)
    Publish(key, payload, express)  put bytes on a key
    DeclareToken(key) / DropToken(key)
    SetTimer(name, at) / CancelTimer(name)   ``at`` on the shell's clock
    Ask(qid, key, payload, timeout)          a query; its answer is a Reply
    AskTokens(qid, key, timeout)             a liveliness query (who holds a
                                             token now); its answer is Tokens
    Answer(qid, payload)                     the reply to a Query event
    Finish(status, code, reason)             the process is done: its exit
                                             status and one line
    Work(est, step, args)                    an estimator step, est.<step>(*args)
                                             (``mesh.protocol.estimator``); the
                                             last effect of its list: the machine
                                             waits for its ``Worked``. A shell of
                                             one process carries it out at once
                                             (``Work.alone``); the simulated network
                                             those of one instant together
    HandOver(check, record, tick)            the world's final reports of a tick
                                             to a check it hands ticks over to
                                             (``check.submit(record, tick)``),
                                             after the effects before it: the
                                             check's thread, woken, takes turns
                                             with this one, and the tick's puts
                                             go first

A machine reads nothing that differs between two runs of one seed: its
token nonce and any randomness come in through its constructor, so the
simulated network (``mesh.simulated.simnet``) replays a run event for event.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FREEZE_S = 2.0  # a process that runs again this late was not running (SIGSTOP, or starved): ``Woke``


# -- events -------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Sample:
    key: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class Token:
    key: str
    up: bool


@dataclass(frozen=True, slots=True, eq=False)
class TokenBatch:
    keys: tuple
    up: bool


@dataclass(frozen=True, slots=True, eq=False)
class Arrivals:
    events: tuple


@dataclass(frozen=True, slots=True)
class Timer:
    name: str


@dataclass(frozen=True, slots=True)
class Query:
    qid: int
    key: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class Reply:
    qid: int
    payload: bytes | None


@dataclass(frozen=True, slots=True)
class Woke:
    late: float


@dataclass(frozen=True, slots=True)
class Tokens:
    qid: int
    keys: tuple


@dataclass(frozen=True, slots=True)
class Interrupt:
    why: str


@dataclass(frozen=True, slots=True, eq=False)
class Worked:
    work: "Work"
    result: object            # the step's value, or the numpy.linalg.LinAlgError it raised


# -- an agent's samples, decoded at its edge (``mesh.protocol.intake``) ----------
@dataclass(frozen=True, slots=True)
class TickArrived:
    tick: object              # wire.Tick


@dataclass(frozen=True, slots=True)
class MeasurementArrived:
    measurement: object       # wire.Measurement


@dataclass(frozen=True, slots=True)
class StopArrived:
    stop: object              # wire.Stop


@dataclass(frozen=True, slots=True)
class MessageArrived:
    sender: int | None        # the id the key names (None: not an integer)
    message: object           # wire.WireMessage, the wire.Rejected of its decode, or None: not decoded
    problem: tuple | None     # (reason, detail) of the checks of its own values, or None


@dataclass(frozen=True, slots=True)
class Unreadable:
    kind: str                 # tick, meas, stop
    reason: str
    detail: str


Arrival = TickArrived | MeasurementArrived | StopArrived | MessageArrived | Unreadable
Event = Sample | Token | TokenBatch | Timer | Query | Reply | Woke | Tokens | Interrupt | Worked | Arrival


# -- effects ------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Subscribe:
    key: str


@dataclass(frozen=True, slots=True)
class WatchTokens:
    key: str


@dataclass(frozen=True, slots=True)
class DeclareQueryable:
    key: str


@dataclass(frozen=True, slots=True)
class Publish:
    key: str
    payload: bytes
    express: bool = True


@dataclass(frozen=True, slots=True)
class DeclareToken:
    key: str


@dataclass(frozen=True, slots=True)
class DropToken:
    key: str


@dataclass(frozen=True, slots=True)
class SetTimer:
    name: str
    at: float


@dataclass(frozen=True, slots=True)
class CancelTimer:
    name: str


@dataclass(frozen=True, slots=True)
class Ask:
    qid: int
    key: str
    payload: bytes
    timeout: float


@dataclass(frozen=True, slots=True)
class AskTokens:
    qid: int
    key: str
    timeout: float


@dataclass(frozen=True, slots=True)
class Answer:
    qid: int
    payload: bytes


@dataclass(frozen=True, slots=True)
class Finish:
    status: str
    code: int
    reason: str = ""


@dataclass(frozen=True, slots=True, eq=False)
class Work:
    est: object               # an ``AgentEstimator``
    step: str                 # "local" or "fuse"
    args: tuple

    def alone(self):
        """The step's value, or the ``numpy.linalg.LinAlgError`` it raised."""
        try:
            return getattr(self.est, self.step)(*self.args)
        except np.linalg.LinAlgError as e:
            return e


@dataclass(frozen=True, slots=True, eq=False)
class HandOver:
    check: object             # a check the world hands ticks over to (``mesh.process.checker.CheckThread``)
    record: object            # the world's record (``WorldRecord``)
    tick: int

    def carry_out(self) -> None:
        self.check.submit(self.record, self.tick)


Effect = (Subscribe | WatchTokens | DeclareQueryable | Publish | DeclareToken | DropToken | SetTimer | CancelTimer
          | Ask | AskTokens | Answer | Finish | Work | HandOver)


def at_once(machine, event, now: float) -> list:
    """``machine.handle(event, now)`` with every ``Work`` carried out at
    once, as a process's shell does: the other effects, in order."""
    out = []
    for e in machine.handle(event, now):
        if isinstance(e, Work):
            out += at_once(machine, Worked(e, e.alone()), now)
        else:
            out.append(e)
    return out

"""The wire format: what travels between the processes of a mesh run, as msgpack.

Every payload is one msgpack map with short keys. Common to all kinds:

    "v"   schema version (``SCHEMA``)
    "k"   kind: "msg" | "report" | "tick" | "meas" | "stop" | "join" | "start"
    "run" run id (the key prefix diskf/<run-id>/ carries it too)
    "t"   tick k >= 1 ("stop": the last tick)

Float arrays travel as one msgpack ``bin`` of little-endian float64
(``"dt": "<f8"``), concatenated in a fixed order and row-major; their shapes
follow from the state and input dimensions ``"n"`` and ``"m"`` carried in the
same map. Matrices are sent whole (not as triangles): a receiver then fuses
bit for bit what the sender computed.

kind "msg" (agent -> neighbours, one per agent and tick; ``Message``)::

    "s" sender id, "n", "m", "dt", "dv" d_valid (bool),
    "a" the arrays its estimator exchanges (``Estimator.exchanged``), in the
        order declared; every built-in estimator's: x_pred (n), P_pred
        (n x n), x_upd (n), P_upd (n x n), d (m), S (m x m)

  It never carries a raw measurement, an H or an R. For n = 2, m = 1 it is
  about 160 bytes. The byte layout of "a" for (exchanged, n, m) is
  ``layout``: the decoder reads the floats once (``WireMessage.values``, on
  which the guard's checks run too) and makes the arrays once.

kind "report" (agent -> world, the fused estimate after tick k; ``Report``)::

    "s", "n", "m", "dt", "dv", "a" x (n), P (n x n), d (m),
    "c" the agent's counters so far {name: int} (``mesh.wire.counters``),
    "f" the senders whose messages of tick k went into this estimate (ids,
        at most ``MAX_LINKS``; optional, default none),
    "nf" the other senders linked at tick k and why their message did not:
        [[sender, verdict], ...] with verdict "lost" (the link dropped it),
        "late" (no copy by the tick's close) or "rejected:<reason>"
        (at most ``MAX_LINKS`` entries of at most ``MAX_VERDICT`` characters;
        optional) - what a recording (``diskf_mesh.recording``) replays,
    "od" the ``digest`` of the agent's own message of tick k, as it
        published it (8 bytes; optional): a recording's "as sent" (the
        message itself never travels to the world: a report carries no
        message another agent could not hear otherwise),
    "fd" for each sender in "f", in order, the ``digest`` of its message as
        received and fused (8 bytes; optional): the end-of-run check
        (``engine.verify``) names a sender whose message the engine does not
        reproduce,
    "rj" the agent's latest (re)initialisation, [tick J, source]: the agent
        whose fused estimate of tick J - 1 it started from, -1 for its prior
        (optional; absent when it has worked since tick 1). Every report
        carries it, so whichever of an agent's reports reach the world tell
        it how the estimate started: the end-of-run check replays from it

kind "tick" (world -> everyone, opens tick k; ``Tick``)::

    "K" ticks in the run, "seed", "alg", "topo", "range" (float, may be inf),
    "pos" positions of every agent at tick k, (N x 2) float64 in scenario order,
    "live" ids of the agents the world counts as alive,
    "ho" for each id of "live", in order, the ``holder_tag`` (4 bytes) of the
        one process the world counts as that agent (optional): a process of
        that id with another tag leaves before it works on the tick, so two
        processes of one id never both publish, whatever each one's session
        has heard of the other

kind "meas" (world -> one agent on its own key; ``Measurement``)::

    "to" agent id, "has" bool, "y" p_i float64 (empty when has is false)

kind "stop" (world -> everyone): "why" a short text ("done" after the last tick).

kind "join" (agent -> world, the payload of its query on ``Keys.start``;
``Join``): "t" the tick J it (re)joins at, "s" sender.

kind "start" (world -> agent, the answer to its "join"; ``Start``): "t" the
tick J it joins at, "s" the agent it is for, "src" the agent whose fused
estimate of tick J - 1 it starts from, or -1 for the prior; "n", "m", "dt",
"dv", "a" x (n), P (n x n), d (m) of that estimate. ``decode_start`` checks
it as the guard checks a message: finite, P positive definite, no value
beyond ``max_abs``, P's condition number at most ``max_cond``.

The bytes are made and read by ``codec`` (``encode_*``, ``decode_*``); this module holds the
payloads as decoded (dataclasses), the bounds of the schema and the reasons a payload is refused.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diskf_mesh.core.messages import Message

SCHEMA = 1
DTYPE = "<f8"
MAX_DIM = 64  # largest n, m (or p) a decoder accepts
MAX_BYTES = 1 << 20  # largest payload a decoder looks at, whatever the kind
HEADER_BYTES = 256   # the fixed fields of a payload, generously (run id <= 32 characters, ints <= 9 bytes)
MAX_STR = 64         # longest string field or map key (run ids, algorithm and counter names)
HOLDER_BYTES = 4     # a tick's tag of the process it counts as an agent (``holder_tag``)
MAX_WHY = 1024       # longest "why" of a stop
MAX_COUNTERS = 64    # most counters a report may carry (there are about 30)
PER_TICK = 1 << 20   # most payloads one agent counts per tick of the run (``count_bound``)
MAX_LINKS = 1024     # most senders a report's "f" and "nf" may name (without the run's agent count)
MAX_VERDICT = 48     # longest verdict text in a report's "nf"
# what an estimate may hold (a message, a report, a starting estimate; ``guard.GuardConfig``): finite values
# beyond MAX_ABS overflow in products, a covariance conditioned worse than MAX_COND loses its inverse (two
# digits are left at 1e14). Honest estimators reach 8e12 and a condition of 4.5e13 within 200 ticks (an
# agent that never measures a constant-velocity target with an input walk: the held-out suite)
MAX_ABS = 1e15
MAX_COND = 1e14
DIGEST_BYTES = 8     # a fused message's digest in a report's "fd"

REASONS = (
    "not-msgpack",  # not a msgpack document at all
    "schema",       # wrong version, kind, or a missing or mistyped field
    "run",          # belongs to another run
    "sender",       # the key names another agent than the body, or an unknown one
    "shape",        # dimensions or array lengths not the expected ones
    "dtype",        # arrays not little-endian float64
    "non-finite",   # NaN or infinity
    "not-spd",      # a covariance that is not symmetric positive definite
    "size",         # larger than the schema allows: the payload, or a string, map, array or bin in it
    "magnitude",    # a starting estimate with a value beyond the guard's max_abs (``decode_start``)
    "ill-conditioned",  # a starting estimate whose P is worse conditioned than the guard's max_cond
)


class Rejected(ValueError):
    """A payload the decoder refuses; ``reason`` is one of ``REASONS``."""

    def __init__(self, reason: str, detail: str = "", tick: int | None = None):
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason
        self.detail = detail
        self.tick = tick  # the payload's tick where it was read before the rejection, else None


@dataclass(frozen=True)
class WireMessage:
    """A decoded "msg": ``message`` holds unbatched arrays, x_pred (n,) ...
    (None for a field its estimator does not exchange); ``values`` the same
    floats as the decoder read them (a tuple of Python floats for a small
    message, else a float64 array), laid out as ``layout`` says; ``digest``
    that of the payload as received (what a report says it fused)."""

    run_id: str
    sender: int
    tick: int
    message: Message
    values: tuple | np.ndarray = field(default=(), repr=False, compare=False)
    layout: "Layout | None" = field(default=None, repr=False, compare=False)
    digest: bytes = field(default=b"", repr=False, compare=False)  # ``digest`` of the payload as received


@dataclass(frozen=True)
class Report:
    run_id: str
    sender: int
    tick: int
    x: np.ndarray        # (n,)
    P: np.ndarray        # (n, n)
    d: np.ndarray        # (m,)
    d_valid: bool
    counters: dict = field(default_factory=dict)
    fused: tuple = ()      # sender ids fused into this estimate
    not_fused: tuple = ()  # ((sender, verdict), ...) the other linked senders
    sent_digest: bytes = b""  # ``digest`` of this agent's own message of the tick, as published
    digests: tuple = ()    # per sender of ``fused``, in order: ``message_digest`` of what was fused
    restart: tuple | None = None  # (tick J, source or None for the prior) of the latest (re)initialisation


@dataclass(frozen=True)
class Tick:
    run_id: str
    tick: int
    ticks: int
    seed: int
    algorithm: str
    topology: str
    comm_range: float
    positions: np.ndarray  # (N, 2)
    live: tuple
    holders: bytes = b""   # ``holder_tag`` of the process counted as each id of ``live``, in order (or empty)

    def holder(self, agent) -> bytes | None:
        """The tag of the process the world counts as ``agent`` (None: not
        live, or no tags sent)."""
        if not self.holders or agent not in self.live:
            return None
        j = self.live.index(agent)
        return self.holders[HOLDER_BYTES * j: HOLDER_BYTES * (j + 1)]


@dataclass(frozen=True)
class Measurement:
    run_id: str
    tick: int
    agent: int
    has: bool
    y: np.ndarray          # (p_i,), empty when not has


@dataclass(frozen=True)
class Stop:
    run_id: str
    tick: int
    why: str


@dataclass(frozen=True)
class Join:
    run_id: str
    sender: int
    tick: int           # the tick it (re)joins at


@dataclass(frozen=True)
class Start:
    run_id: str
    agent: int
    tick: int           # the tick the agent joins at; the estimate is of the tick before
    source: int | None  # whose fused estimate; None: the prior
    x: np.ndarray       # (n,)
    P: np.ndarray       # (n, n)
    d: np.ndarray       # (m,)
    d_valid: bool

"""The fusion guard: nothing an agent receives can corrupt its estimate.

Every payload that arrives on a neighbour's message key goes through the
guard before it can reach fusion, in two halves: ``Guard.read(sender,
payload)`` at the agent's edge (``mesh.protocol.intake``; ``sender``: the
id the key names, parsed once) decodes it and checks its own values, and
``Guard.judge(arrival, tick)`` in the agent's receive path checks the tick
window and counts (``screen`` is both). It returns the decoded
``wire.WireMessage`` or a refusal; it never raises. The payload is decoded
once (``wire.decode``), and every check below runs once, on the floats the
decoder read (``WireMessage.values``); what is checked follows from the
estimator's declaration (``Estimator.exchanged``: every value, every
covariance, every update of a covariance). A payload is rejected, with one
reason, when

    key             the key's id is not an integer (no decode)
    unknown-sender  the key names an agent that is not in this run's scenario
                    (no decode: a flood under random ids costs a set lookup)
    size, not-msgpack, schema, run, dtype, shape, non-finite, not-spd, sender
                    the decoder's checks (``wire.REASONS``): larger than the
                    schema allows (checked before any decode, and msgpack's
                    own limits), not msgpack, wrong schema version or kind
                    or a missing field, another run, arrays not float64 or
                    not of this run's (n, m), NaN or infinity, a covariance
                    (P_pred, P_upd, S) that is not symmetric positive
                    definite, a key naming another agent than the body
    tick-past       the tick is before 1 or more than ``max_lag`` ticks behind
                    the agent's current tick
    tick-future     the tick is beyond the run or more than ``max_lead``
                    ticks ahead
    magnitude       a value beyond ``max_abs`` (finite, but products of it
                    overflow in fusion)
    ill-conditioned a covariance whose condition number exceeds ``max_cond``
    weights         an array declared probabilities (``Exchanged.weights``:
                    ``diskf-auto``'s input-model probabilities) holds a value
                    outside [0, 1] or does not sum to 1 within ``WEIGHTS_ATOL``
    information     a covariance declared an update of another (P_upd of
                    P_pred) is not at least as certain: the update would
                    subtract information, and fusing it could leave the
                    fused information matrix indefinite (checked only for
                    estimators that fuse information, ``information_check``)
    error           anything else the checks raised (should never happen;
                    the fuzz test asserts it does not)
    fusion          (counted by the agent, per message of the tick) fusion of
                    messages that all passed failed anyway; the agent fused
                    its own message alone (``Agent._close``)
    constants       (counted by the agent) a world tick whose run constants
                    (K, seed, algorithm, topology, range) are not those of
                    the run's first tick

Each rejection is counted per reason in ``Counters.rejected`` and per
(sender, reason) in ``Guard.by_sender``, and logged (``logging``, logger
``diskf_mesh.mesh.protocol.guard``) once per sender and reason. Only the scenario's
agents have a row of their own: every other id (and a key without one)
shares the row ``None``, so neither table nor log grows with what an
intruder sends. A message from this agent's own id is ignored without
counting (a zenoh subscriber also hears its own session's publications).

A refusal whose payload named a tick inside the window (``Refused.tick``)
accounts for that sender at that tick: the agent does not wait the collect
timeout for a neighbour whose message was poisoned, and never fuses it.

Late and duplicate messages are not errors: they are well-formed, and the
inbox (``diskf_mesh.mesh.protocol.receive.Inbox``) counts and drops them.

The agent's ``_close`` is the last line: should fusion still fail on
messages that passed the guard (a well-formed but inconsistent set, e.g.
adversarial information that is individually plausible), the agent keeps
its own estimate for that tick instead of stopping.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

import numpy as np

from diskf_mesh.core import small
from diskf_mesh.estimators.base import EXCHANGED
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.counters import Counters
from diskf_mesh.mesh.protocol.events import MessageArrived
from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.protocol.shared import Shared

REASONS = wire.REASONS + tuple(r for r in ("key", "unknown-sender", "tick-past", "tick-future", "magnitude",
                                           "ill-conditioned", "weights", "information", "error", "fusion", "constants")
                                if r not in wire.REASONS)
LOGGER = logging.getLogger("diskf_mesh.mesh.protocol.guard")
ERROR = "error"    # what the decoder or a check raised (never expected: the fuzz test asserts it)
WEIGHTS_ATOL = 1e-6  # how far from 1 the sum of a message's probabilities may be (its sender normalised them)


@dataclass(frozen=True)
class GuardConfig:
    """What a well-formed message of this run looks like, for agent ``me``."""

    run_id: str
    me: int
    known: frozenset      # agent ids of the scenario
    n: int
    m: int
    ticks: int | None = None        # last tick of the run, if known
    max_lag: int = 16               # oldest accepted tick: current - max_lag
    max_lead: int = 2               # newest accepted tick: current + max_lead
    max_abs: float = wire.MAX_ABS   # what a report and a starting estimate may hold too
    max_cond: float = wire.MAX_COND
    information_rtol: float = 1e-6
    information_check: bool = True  # off for estimators that never invert a sender's P (L-DRKF)
    exchanged: tuple = EXCHANGED    # the arrays a message carries (``Estimator.exchanged``)


@dataclass(frozen=True)
class Refused:
    """A rejected payload: its reason, and the tick it accounts for (its
    sender's message of that tick came, poisoned) or None."""

    reason: str
    tick: int | None = None


class Guard:
    def __init__(self, config: GuardConfig, counters: Counters | None = None, logger: logging.Logger = LOGGER,
                 profile: Phases = NO_PHASES, shared: Shared | None = None):
        """``profile``: where the time of decoding and checking goes
        (``mesh.protocol.profile``, phases "decode" and "guard");
        ``shared``: the decodes and payload-only checks other receivers of
        the same payload made (``mesh.protocol.shared``; the simulated
        network), None: every payload decoded here."""
        self.config = config
        self.counters = counters if counters is not None else Counters()
        self.by_sender: Counter = Counter()  # (known sender or None, reason) -> count
        self.logger = logger
        self.profile = profile
        self.shared = shared
        self._how = (None, None)  # (config, its ``Shared.how``)

    # -- entry point -----------------------------------------------------
    def screen(self, sender, payload, tick: int):
        """``payload`` on the key of agent ``sender`` (an int, or None when
        the key's id is not one) at ``tick``, the agent's current tick: the
        decoded message if it may be fused at (or around) ``tick``, a
        ``Refused``, or None for the agent's own message (``read``, then
        ``judge``)."""
        return self.judge(self.read(sender, payload), tick)

    def read(self, sender, payload) -> MessageArrived:
        """What ``payload`` on the key of agent ``sender`` says by itself,
        before any receiver's state: its decode and the checks of its own
        values (``message_problem``), each once (with ``shared``: once for
        every receiver of the payload). Nothing is decoded for a key naming
        no agent of the run or this agent itself (``judge`` refuses or
        ignores it). Never raises: what the decoder or the checks raised is
        a refusal with reason "error"."""
        c = self.config
        if sender is None or sender not in c.known or sender == c.me:
            return MessageArrived(sender, None, None)
        shared = self.shared
        hit = None if shared is None else shared.entry(payload, (sender, self._shared_how(c)))
        if hit:
            return MessageArrived(sender, *hit)
        prof = self.profile
        problem = None
        prof.begin()
        try:
            wm = wire.decode(payload, run_id=c.run_id, sender=sender, n=c.n, m=c.m, exchanged=c.exchanged)
        except wire.Rejected as e:
            wm = e
        except Exception as e:  # noqa: BLE001 - a guard that raises would stop the agent
            wm, problem = None, (ERROR, f"{type(e).__name__}: {e}")
        finally:
            prof.end("decode")
        if isinstance(wm, wire.WireMessage):
            prof.begin()
            try:
                problem = message_problem(wm, c)
            except Exception as e:  # noqa: BLE001
                problem = ERROR, f"{type(e).__name__}: {e}"
            finally:
                prof.end("guard")
        if hit is not None:
            hit += (wm, problem)
        return MessageArrived(sender, wm, problem)

    def judge(self, arrival: MessageArrived, tick: int):
        """``arrival`` (``read``'s) at ``tick``, the agent's current tick:
        the decoded message if it may be fused at (or around) ``tick``, a
        ``Refused`` (counted), or None for the agent's own message."""
        c = self.config
        sender, wm = arrival.sender, arrival.message
        if sender is None or sender not in c.known:
            return self._reject(None, "key" if sender is None else "unknown-sender")
        if sender == c.me:
            return None
        if wm is None:  # its decode raised
            return self._reject(sender, *arrival.problem)
        if isinstance(wm, wire.Rejected):
            # a body naming another agent or run is not this sender's message of its tick (a copy, a
            # replay): it accounts for no tick, so it cannot stand in for the sender's real message
            mine = wm.reason not in ("sender", "run")
            return self._reject(sender, wm.reason, wm.detail,
                                wm.tick if mine and self.in_window(wm.tick, tick) else None)
        inside = self.in_window(wm.tick, tick)
        reason = arrival.problem if inside else self._off_window(wm.tick, tick)
        if reason is not None:
            # a check that raised says nothing of the message's tick
            return self._reject(sender, *reason, wm.tick if inside and reason[0] != ERROR else None)
        return wm

    def read_how(self) -> int:
        """The ``Shared.how`` of what ``read`` depends on besides the payload
        and the key (with ``shared`` only)."""
        return self._shared_how(self.config)

    def _shared_how(self, c: GuardConfig) -> int:
        """What a payload's decode and checks depend on besides the payload
        and its sender: this run's shapes and limits (not the receiver's
        window), as a ``Shared.how``."""
        if self._how[0] is not c:
            self._how = (c, self.shared.how(("msg", c.run_id, c.n, c.m, c.exchanged, c.max_abs, c.max_cond,
                                             c.information_rtol, c.information_check)))
        return self._how[1]

    # -- checks beyond the decoder's ---------------------------------------
    def in_window(self, t, tick: int) -> bool:
        """Whether a message of tick ``t`` may be fused around ``tick``."""
        c = self.config
        return t is not None and max(1, tick - c.max_lag) <= t <= tick + c.max_lead and (c.ticks is None
                                                                                          or t <= c.ticks)

    def _off_window(self, t: int, tick: int) -> tuple:
        """(reason, detail) of a message of tick ``t`` outside the window."""
        if t < 1 or t < tick - self.config.max_lag:
            return "tick-past", f"tick {t} at tick {tick}"
        return "tick-future", f"tick {t} at tick {tick}"

    # -- bookkeeping -----------------------------------------------------
    def reject(self, sender, reason: str, detail: str = "") -> None:
        """Count and log (once per known sender and reason) a rejection;
        ``sender`` None or not in the scenario: the shared row."""
        if sender not in self.config.known:
            sender = None
        self.counters.reject(reason)
        self.by_sender[(sender, reason)] += 1
        if self.by_sender[(sender, reason)] == 1:
            who = "an unknown sender" if sender is None else f"agent {sender}"
            self.logger.warning("agent %s: rejected a message from %s: %s%s (further ones are counted, not logged)",
                                self.config.me, who, reason, f" ({detail[:200]})" if detail else "")

    def _reject(self, sender, reason: str, detail: str = "", tick: int | None = None) -> Refused:
        self.reject(sender, reason, detail)
        return Refused(reason, tick)


def message_problem(wm: wire.WireMessage, c: GuardConfig):
    """The checks of one decoded message beyond the decoder's: None or
    (reason, detail).

    The decoder has checked dtype, shapes, finiteness and that every
    covariance has a Cholesky factor; these checks run on the floats it
    read (``wm.values``, laid out as ``wm.layout``). Covariances of size 1
    and 2 (the usual n, m) are checked in closed form on Python floats,
    which is ten times faster than numpy's LAPACK calls on such small
    matrices; larger ones with ``numpy.linalg``."""
    values, lay, msg = wm.values, wm.layout, wm.message
    small_values = type(values) is tuple
    big = wire.largest_abs(values)
    if big > c.max_abs:
        return "magnitude", f"a value of {big:.3g} (limit {c.max_abs:.3g})"
    for s in lay.weights:
        w = values[s.start:s.stop]
        if not (min(w) >= 0.0 and max(w) <= 1.0 and abs(sum(w) - 1.0) <= WEIGHTS_ATOL):
            return "weights", f"{s.name} are not probabilities (sum {sum(w):.6g}, range {min(w):.3g} .. {max(w):.3g})"
    for s in lay.covariances:
        ev = small.eigen_range(_rows(values, s) if small_values else getattr(msg, s.name))
        if not ev[0] > 0 or ev[-1] > c.max_cond * ev[0]:
            return "ill-conditioned", f"{s.name} eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}"
    if c.information_check:
        for s, of in lay.updates:
            low, scale = (small.information_gain(_rows(values, of), _rows(values, s)) if small_values else
                          small.information_gain(getattr(msg, of.name), getattr(msg, s.name)))
            if low < -c.information_rtol * scale:
                return "information", f"{s.name} adds negative information ({low:.3g})"
    return None


def _rows(values: tuple, s: wire.Slot):
    """The covariance at ``s`` as nested lists of Python floats (``k`` <= 2),
    else as a numpy array."""
    k = s.shape[-1]
    v = values[s.start:s.stop]
    if k == 1:
        return [[v[0]]]
    if k == 2:
        return [[v[0], v[1]], [v[2], v[3]]]
    return np.array(v, dtype=float).reshape(k, k)

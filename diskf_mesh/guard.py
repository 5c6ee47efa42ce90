"""The fusion guard: nothing an agent receives can corrupt its estimate.

Every payload that arrives on a neighbour's message key goes through
``Guard.admit(key, payload, tick)`` before it can reach fusion. It returns
the decoded ``wire.WireMessage`` or None; it never raises. A payload is
rejected, with one reason, when

    not-msgpack, schema, run, dtype, shape, non-finite, not-spd, sender
                    the decoder's checks (``wire.REASONS``): not msgpack, wrong
                    schema version or kind or a missing field, another run,
                    arrays not float64 or not of this run's (n, m), NaN or
                    infinity, a covariance (P_pred, P_upd, S) that is not
                    symmetric positive definite, a key naming another agent
                    than the body
    key             the key is not an agent message key of this run
    unknown-sender  the sender is not an agent of this run's scenario
    tick-past       the tick is before 1 or more than ``max_lag`` ticks behind
                    the agent's current tick
    tick-future     the tick is beyond the run or more than ``max_lead``
                    ticks ahead
    magnitude       a value beyond ``max_abs`` (finite, but products of it
                    overflow in fusion)
    ill-conditioned a covariance whose condition number exceeds ``max_cond``
    information     P_upd is not at least as certain as P_pred: the update
                    would subtract information, and fusing it could leave the
                    fused information matrix indefinite (checked only for
                    algorithms that fuse information, ``information_check``)
    error           anything else the checks raised (should never happen;
                    the fuzz test asserts it does not)
    fusion          (counted by the agent, per message of the tick) fusion of
                    messages that all passed failed anyway; the agent fused
                    its own message alone (see ``fuse_checked``)

Each rejection is counted per reason in ``Counters.rejected`` and per
(sender, reason) in ``Guard.by_sender``, and logged (``logging``, logger
``diskf_mesh.guard``) once per sender and reason. A message from this agent's
own id is ignored without counting (a zenoh subscriber also hears its own
session's publications).

Late and duplicate messages are not errors: they are well-formed, and the
inbox (``diskf_mesh.inbox``) counts and drops them.

``fuse_checked`` is the last line: should fusion still fail on messages that
passed the guard (a well-formed but inconsistent set, e.g. adversarial
information that is individually plausible), the agent keeps its own
estimate for that tick instead of stopping.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

import numpy as np

from . import wire
from .counters import Counters
from .messages import Message, Neighbourhood
from .mesh.keys import Keys

REASONS = wire.REASONS + ("key", "unknown-sender", "tick-past", "tick-future", "magnitude", "ill-conditioned",
                          "information", "error", "fusion")
LOGGER = logging.getLogger("diskf_mesh.guard")


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
    max_abs: float = 1e12
    max_cond: float = 1e10
    information_rtol: float = 1e-6
    information_check: bool = True  # off for algorithms that never invert a sender's P (L-DRKF)


class Guard:
    def __init__(self, config: GuardConfig, counters: Counters | None = None, logger: logging.Logger = LOGGER):
        self.config = config
        self.counters = counters if counters is not None else Counters()
        self.by_sender: Counter = Counter()  # (sender or None, reason) -> count
        self.logger = logger
        self._keys = Keys(config.run_id)

    # -- entry point -----------------------------------------------------
    def admit(self, key: str, payload, tick: int) -> wire.WireMessage | None:
        """The decoded message if it may be fused at (or around) ``tick``, the
        agent's current tick; None if rejected or the agent's own."""
        key_sender = None
        try:
            kind, key_sender = self._keys.parse(str(key))
            if kind != "msg" or key_sender is None:
                return self._reject(key_sender, "key", f"not an agent message key: {key!r}")
            if key_sender == self.config.me:
                return None
            c = self.config
            try:
                wm = wire.decode(payload, run_id=c.run_id, sender=key_sender, n=c.n, m=c.m)
            except wire.Rejected as e:
                return self._reject(key_sender, e.reason, e.detail)
            reason = self.check(wm, tick)
            if reason is not None:
                return self._reject(key_sender, *reason)
            return wm
        except Exception as e:  # noqa: BLE001 - a guard that raises would stop the agent
            return self._reject(key_sender, "error", f"{type(e).__name__}: {e}")

    # -- checks beyond the decoder's ---------------------------------------
    def check(self, wm: wire.WireMessage, tick: int):
        """None, or (reason, detail) for a decoded message."""
        c = self.config
        if wm.sender not in c.known:
            return "unknown-sender", f"agent {wm.sender} is not in this run"
        if wm.tick < 1 or wm.tick < tick - c.max_lag:
            return "tick-past", f"tick {wm.tick} at tick {tick}"
        if wm.tick > tick + c.max_lead or (c.ticks is not None and wm.tick > c.ticks):
            return "tick-future", f"tick {wm.tick} at tick {tick}"
        return message_problem(wm.message, c)

    # -- bookkeeping -----------------------------------------------------
    def _reject(self, sender, reason: str, detail: str = ""):
        self.counters.reject(reason)
        self.by_sender[(sender, reason)] += 1
        if self.by_sender[(sender, reason)] == 1:
            who = "an unnamed sender" if sender is None else f"agent {sender}"
            self.logger.warning("agent %s: rejected a message from %s: %s%s (further ones are counted, not logged)",
                                self.config.me, who, reason, f" ({detail})" if detail else "")
        return None


def message_problem(msg: Message, c: GuardConfig):
    """Numerical checks of one decoded message: None or (reason, detail).

    The decoder has checked dtype, shapes, finiteness and that every
    covariance has a Cholesky factor."""
    arrays = [np.asarray(getattr(msg, f)) for f in Message.ARRAY_FIELDS]
    big = max(float(np.abs(a).max()) for a in arrays)
    if big > c.max_abs:
        return "magnitude", f"a value of {big:.3g} (limit {c.max_abs:.3g})"
    for name in ("P_pred", "P_upd", "S"):
        ev = np.linalg.eigvalsh(getattr(msg, name))
        if not ev[0] > 0 or ev[-1] > c.max_cond * ev[0]:
            return "ill-conditioned", f"{name} eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}"
    if c.information_check:
        Yu = np.linalg.inv(msg.P_upd)
        dY = Yu - np.linalg.inv(msg.P_pred)
        low = np.linalg.eigvalsh(0.5 * (dY + dY.T))[0]
        if low < -c.information_rtol * np.abs(Yu).max():
            return "information", f"P_upd adds negative information ({low:.3g})"
    return None


def fuse_checked(alg, state, own: Message, senders: Message, nb: Neighbourhood, own_index: int):
    """``alg.fuse`` and whether it succeeded. Where fusion raises or gives a
    non-finite estimate, fuse the agent's own message alone instead (returns
    ok=False; the caller counts it). ``own_index``: own row among ``senders``."""
    try:
        new_state, out = alg.fuse(state, own, senders, nb)
        if np.isfinite(out.x).all() and np.isfinite(out.P).all():
            return new_state, out, True
    except (np.linalg.LinAlgError, FloatingPointError, ValueError):
        pass
    only = Message.stack([senders.take(own_index)])
    mask = np.ones((1, 1), dtype=bool)
    alone = Neighbourhood(np.ones((1, 1)), mask, nb.gossip_u)
    new_state, out = alg.fuse(state, own, only, alone)
    return new_state, out, False

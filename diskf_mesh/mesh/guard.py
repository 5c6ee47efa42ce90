"""The fusion guard: nothing an agent receives can corrupt its estimate.

Every payload that arrives on a neighbour's message key goes through
``Guard.screen(sender, payload, tick)`` (``sender``: the id the key names,
parsed once by the agent) before it can reach fusion. It returns the decoded
``wire.WireMessage`` or a refusal; it never raises. A payload is rejected,
with one reason, when

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
    information     P_upd is not at least as certain as P_pred: the update
                    would subtract information, and fusing it could leave the
                    fused information matrix indefinite (checked only for
                    algorithms that fuse information, ``information_check``)
    error           anything else the checks raised (should never happen;
                    the fuzz test asserts it does not)
    fusion          (counted by the agent, per message of the tick) fusion of
                    messages that all passed failed anyway; the agent fused
                    its own message alone (see ``fuse_checked``)
    constants       (counted by the agent) a world tick whose run constants
                    (K, seed, algorithm, topology, range) are not those of
                    the run's first tick

Each rejection is counted per reason in ``Counters.rejected`` and per
(sender, reason) in ``Guard.by_sender``, and logged (``logging``, logger
``diskf_mesh.mesh.guard``) once per sender and reason. Only the scenario's
agents have a row of their own: every other id (and a key without one)
shares the row ``None``, so neither table nor log grows with what an
intruder sends. A message from this agent's own id is ignored without
counting (a zenoh subscriber also hears its own session's publications).

A refusal whose payload named a tick inside the window (``Refused.tick``)
accounts for that sender at that tick: the agent does not wait the collect
timeout for a neighbour whose message was poisoned, and never fuses it.

Late and duplicate messages are not errors: they are well-formed, and the
inbox (``diskf_mesh.mesh.inbox``) counts and drops them.

``fuse_checked`` is the last line: should fusion still fail on messages that
passed the guard (a well-formed but inconsistent set, e.g. adversarial
information that is individually plausible), the agent keeps its own
estimate for that tick instead of stopping.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from diskf_mesh.mesh import wire
from diskf_mesh.mesh.counters import Counters
from diskf_mesh.core.messages import Message, Neighbourhood
from diskf_mesh.mesh.profile import NO_PHASES, Phases

REASONS = wire.REASONS + ("key", "unknown-sender", "tick-past", "tick-future", "magnitude", "ill-conditioned",
                          "information", "error", "fusion", "constants")
LOGGER = logging.getLogger("diskf_mesh.mesh.guard")


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


@dataclass(frozen=True)
class Refused:
    """A rejected payload: its reason, and the tick it accounts for (its
    sender's message of that tick came, poisoned) or None."""

    reason: str
    tick: int | None = None


class Guard:
    def __init__(self, config: GuardConfig, counters: Counters | None = None, logger: logging.Logger = LOGGER,
                 profile: Phases = NO_PHASES):
        """``profile``: where the time of decoding and checking goes
        (``mesh.profile``, phases "decode" and "guard")."""
        self.config = config
        self.counters = counters if counters is not None else Counters()
        self.by_sender: Counter = Counter()  # (known sender or None, reason) -> count
        self.logger = logger
        self.profile = profile

    # -- entry point -----------------------------------------------------
    def screen(self, sender, payload, tick: int):
        """``payload`` on the key of agent ``sender`` (an int, or None when
        the key's id is not one) at ``tick``, the agent's current tick: the
        decoded message if it may be fused at (or around) ``tick``, a
        ``Refused``, or None for the agent's own message."""
        c = self.config
        if sender is None or sender not in c.known:
            return self._reject(None, "key" if sender is None else "unknown-sender")
        if sender == c.me:
            return None
        try:
            prof = self.profile
            prof.begin()
            try:
                wm = wire.decode(payload, run_id=c.run_id, sender=sender, n=c.n, m=c.m)
            except wire.Rejected as e:
                # a body naming another agent or run is not this sender's message of its tick (a copy, a
                # replay): it accounts for no tick, so it cannot stand in for the sender's real message
                mine = e.reason not in ("sender", "run")
                return self._reject(sender, e.reason, e.detail,
                                    e.tick if mine and self.in_window(e.tick, tick) else None)
            finally:
                prof.end("decode")
            prof.begin()
            try:
                reason = self.check(wm, tick)
            finally:
                prof.end("guard")
            if reason is not None:
                return self._reject(sender, *reason, wm.tick if self.in_window(wm.tick, tick) else None)
            return wm
        except Exception as e:  # noqa: BLE001 - a guard that raises would stop the agent
            return self._reject(sender, "error", f"{type(e).__name__}: {e}")

    def admit(self, sender, payload, tick: int) -> wire.WireMessage | None:
        """``screen``'s message, or None (rejected, or the agent's own)."""
        out = self.screen(sender, payload, tick)
        return out if isinstance(out, wire.WireMessage) else None

    # -- checks beyond the decoder's ---------------------------------------
    def in_window(self, t, tick: int) -> bool:
        """Whether a message of tick ``t`` may be fused around ``tick``."""
        c = self.config
        return t is not None and max(1, tick - c.max_lag) <= t <= tick + c.max_lead and (c.ticks is None
                                                                                          or t <= c.ticks)

    def check(self, wm: wire.WireMessage, tick: int):
        """None, or (reason, detail) for a decoded message."""
        if not self.in_window(wm.tick, tick):
            c = self.config
            if wm.tick < 1 or wm.tick < tick - c.max_lag:
                return "tick-past", f"tick {wm.tick} at tick {tick}"
            return "tick-future", f"tick {wm.tick} at tick {tick}"
        return message_problem(wm.message, self.config)

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


def message_problem(msg: Message, c: GuardConfig):
    """Numerical checks of one decoded message: None or (reason, detail).

    The decoder has checked dtype, shapes, finiteness and that every
    covariance has a Cholesky factor. Covariances of size 1 and 2 (the
    usual n, m) are checked in closed form on Python floats, which is ten
    times faster than numpy's LAPACK calls on such small matrices; larger
    ones with ``numpy.linalg``."""
    arrays = [getattr(msg, f) for f in Message.ARRAY_FIELDS]
    if sum(a.size for a in arrays) <= 64:
        values = [v for a in arrays for v in a.ravel().tolist()]
        big = max(max(values), -min(values))  # the largest |v|, in C loops
    else:
        big = max(float(np.abs(a).max()) for a in arrays)
    if big > c.max_abs:
        return "magnitude", f"a value of {big:.3g} (limit {c.max_abs:.3g})"
    for name in ("P_pred", "P_upd", "S"):
        ev = _extreme_eigenvalues(getattr(msg, name))
        if not ev[0] > 0 or ev[-1] > c.max_cond * ev[0]:
            return "ill-conditioned", f"{name} eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}"
    if c.information_check:
        low, scale = _information_gain(msg.P_pred, msg.P_upd)
        if low < -c.information_rtol * scale:
            return "information", f"P_upd adds negative information ({low:.3g})"
    return None


def _extreme_eigenvalues(M: np.ndarray) -> tuple:
    """(smallest, largest) eigenvalue of a symmetric matrix (lower triangle,
    as ``eigvalsh``)."""
    k = M.shape[-1]
    if k == 1:
        v = float(M[0, 0])
        return v, v
    if k == 2:
        (p, _), (q, r) = M.tolist()
        hi = 0.5 * (p + r) + math.hypot(0.5 * (p - r), q)
        # the product of the eigenvalues is the determinant: accurate even
        # where hi - (the radius) would cancel (an ill-conditioned matrix)
        return ((p * r - q * q) / hi if hi > 0 else hi), hi
    ev = np.linalg.eigvalsh(M)
    return float(ev[0]), float(ev[-1])


def _information_gain(P_pred: np.ndarray, P_upd: np.ndarray) -> tuple:
    """(smallest eigenvalue of sym(inv(P_upd) - inv(P_pred)), max |inv(P_upd)|)."""
    k = P_upd.shape[-1]
    if k <= 2:
        Yu, Yp = _small_inverse(P_upd.tolist()), _small_inverse(P_pred.tolist())
        scale = max(abs(v) for row in Yu for v in row)
        if k == 1:
            return Yu[0][0] - Yp[0][0], scale
        a, c = Yu[0][0] - Yp[0][0], Yu[1][1] - Yp[1][1]
        b = 0.5 * ((Yu[0][1] - Yp[0][1]) + (Yu[1][0] - Yp[1][0]))
        return 0.5 * (a + c) - math.hypot(0.5 * (a - c), b), scale
    Yu = np.linalg.inv(P_upd)
    dY = Yu - np.linalg.inv(P_pred)
    return float(np.linalg.eigvalsh(0.5 * (dY + dY.T))[0]), float(np.abs(Yu).max())


def _small_inverse(a: list) -> list:
    """Inverse of a 1x1 or 2x2 matrix given as lists (adjugate over
    determinant); raises ``numpy.linalg.LinAlgError`` where it is singular,
    like ``numpy.linalg.inv``."""
    if len(a) == 1:
        if a[0][0] == 0.0:
            raise np.linalg.LinAlgError("Singular matrix")
        return [[1.0 / a[0][0]]]
    (p, q), (s, r) = a
    det = p * r - q * s
    if det == 0.0:
        raise np.linalg.LinAlgError("Singular matrix")
    return [[r / det, -q / det], [-s / det, p / det]]


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
    alone = Neighbourhood(np.ones((1, 1)), mask, nb.draws)
    new_state, out = alg.fuse(state, own, only, alone)
    return new_state, out, False

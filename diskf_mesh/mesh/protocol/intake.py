"""An agent's edge: a sample on one of its keys, read once into a typed event.

The agent's machine (``mesh.protocol.agent_machine``) handles typed events,
never bytes. Its shell (``mesh.process.shell``, the simulated network
``mesh.simulated.simnet``) hands every sample through ``Intake.read(key,
payload)`` first, as h11 turns bytes into events before its state machine
sees them::

    tick/...       -> TickArrived(wire.Tick)
    meas/<me>      -> MeasurementArrived(wire.Measurement)
    stop           -> StopArrived(wire.Stop)
    msg/<sender>   -> MessageArrived(sender, message, problem)   (``Guard.read``)
    a world's payload that does not decode -> Unreadable(kind, reason, detail)

The key is parsed once here, and each payload decoded once: on the
simulated network, where one publication reaches many agents in one
process, once for all its receivers (``mesh.protocol.shared``). What
depends on the receiver (its tick, the run's constants, the tick window,
every counter) is the machine's: ``Intake`` keeps nothing between samples.

May import: core, estimators, data, engine (the mesh layer).
"""
from __future__ import annotations

from operator import is_, itemgetter

from diskf_mesh.mesh.protocol.events import (MeasurementArrived, MessageArrived, Sample, StopArrived, TickArrived,
                                             Unreadable)
from diskf_mesh.mesh.protocol.guard import Guard
from diskf_mesh.mesh.protocol.profile import NO_PHASES, Phases
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys


_FIRST, _SECOND = itemgetter(0), itemgetter(1)


class Intake:
    """The samples of agent ``me`` (``p`` measurement rows) in the run of
    ``keys`` with ``agents`` agents; ``guard`` reads its neighbours'
    messages, and its ``shared`` (the decodes other receivers of the same
    payload made, or None) serves the world's ticks too; ``profile``: the
    time of decoding ("decode")."""

    def __init__(self, keys: Keys, me: int, p: int, agents: int, guard: Guard, profile: Phases = NO_PHASES):
        self.keys, self.me, self.p, self.agents = keys, me, p, agents
        self.guard = guard
        self.prof = profile
        self._tick_how = ("tick", keys.run_id, agents)

    def read(self, key: str, payload: bytes):
        """The event ``payload`` on ``key`` is (module docstring); a sample
        on a key no agent step reads comes back as it is."""
        kind, who = self.keys.parse(key)
        if kind == "msg":
            return self.guard.read(who, payload)
        if kind not in ("tick", "meas", "stop"):
            return Sample(key, payload)
        run_id = self.keys.run_id
        self.prof.begin()
        try:
            if kind == "tick":
                return TickArrived(self._tick(payload))
            if kind == "meas":
                return MeasurementArrived(wire.decode_measurement(payload, run_id=run_id, agent=self.me, p=self.p))
            return StopArrived(wire.decode_stop(payload, run_id=run_id))
        except wire.Rejected as e:
            return Unreadable(kind, e.reason, e.detail)
        finally:
            self.prof.end("decode")

    def read_all(self, samples) -> tuple:
        """``read`` of each of ``samples`` (``Sample`` events), in order. A
        neighbour's message reads the same at every receiver that shares
        this guard's ``shared`` (its sender, decode and checks: ``Guard.read``;
        the receiver's own id is ignored by ``Guard.judge`` before its decode
        is looked at), so its event is made once per ``Sample`` for all of
        them."""
        shared = self.guard.shared
        if shared is None:
            return tuple([self.read(s.key, s.payload) for s in samples])
        memo = shared.reads(self.guard.read_how())
        hits = list(map(memo.get, map(id, samples)))
        if None not in hits and all(map(is_, map(_FIRST, hits), samples)):  # every one read for another receiver
            return tuple(map(_SECOND, hits))
        out = []
        for s in samples:
            hit = memo.get(id(s))
            if hit is None or hit[0] is not s:
                e = self.read(s.key, s.payload)
                if type(e) is MessageArrived and e.sender != self.me:
                    shared.remember(memo, s, e)
                out.append(e)
            else:
                out.append(hit[1])
        return tuple(out)

    def _tick(self, payload: bytes):
        """The world's tick, decoded once per payload (with ``shared``: for every receiver)."""
        shared = self.guard.shared
        decode = lambda: wire.decode_tick(payload, run_id=self.keys.run_id, agents=self.agents)  # noqa: E731
        if shared is None:
            return decode()
        t = shared.once(payload, self._tick_how, decode)
        if isinstance(t, wire.Rejected):
            raise wire.Rejected(t.reason, t.detail, t.tick)
        return t

"""Insiders that lie, on the simulated network with the real machines
(docs/security.md): an agent holding only its own identity offsets the
estimates it sends and reports, after withholding one report or not.

    a lie after a withheld report   the agent-ticks built on it cannot be
                                    verified: ``unverifiable``, never
                                    accepted by ``--allow-missing``, only
                                    by ``--accept-unverifiable``
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.core import exits
from diskf_mesh.data.scenario import load_scenario, simulate
from diskf_mesh.mesh.protocol import events as ev
from diskf_mesh.mesh.protocol.run_status import accept
from diskf_mesh.mesh.simulated.simnet import Link
from diskf_mesh.mesh.simulated.simrun import SimPlan, agent_pid, simulate_run
from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.wire.keys import Keys

RUN = "sim"
KEYS = Keys(RUN)
EXCHANGED = estimators.get("diskf").exchanged
K, LIAR, WITHHELD, FROM, OFFSET = 80, 3, 49, 50, 200.0


class Liar:
    """Agent ``who``'s machine, whose messages and reports from tick
    ``start`` on carry its estimate offset by ``offset`` (consistently: what
    it reports is what it sent), and whose report of tick ``withhold`` never
    goes out."""

    def __init__(self, inner, who: int, start: int, offset: float, withhold: int | None = None):
        self.inner, self.who, self.start_tick, self.offset, self.withhold = inner, who, start, offset, withhold

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def start(self, now):
        return self._edit(self.inner.start(now))

    def handle(self, event, now):
        return self._edit(self.inner.handle(event, now))

    def _edit(self, effects) -> list:
        out = []
        for e in effects:
            kind = KEYS.parse(e.key)[0] if isinstance(e, ev.Publish) else None
            if kind == "report":
                r = wire.decode_report(e.payload, run_id=RUN, sender=self.who)
                if r.tick == self.withhold:
                    continue
                if r.tick >= self.start_tick:
                    e = dataclasses.replace(e, payload=wire.encode_report(
                        RUN, self.who, r.tick, r.x + self.offset, r.P, r.d, r.d_valid, r.counters, r.fused,
                        r.not_fused, r.sent_digest, r.digests))
            elif kind == "msg":
                m = wire.decode(e.payload, run_id=RUN, sender=self.who, exchanged=EXCHANGED)
                if m.tick >= self.start_tick:
                    lie = dataclasses.replace(m.message, x_pred=m.message.x_pred + self.offset,
                                              x_upd=m.message.x_upd + self.offset)
                    e = dataclasses.replace(e, payload=wire.encode(RUN, self.who, m.tick, lie, EXCHANGED))
            out.append(e)
        return out


@pytest.fixture(scope="module")
def dynamic():
    scn = load_scenario("dynamic").with_overrides(steps=K)  # Scenario 2: agent 3 meets agent 8 from tick 39 on
    return scn, simulate(scn, [0])


def run(dynamic, **liar):
    scn, trace = dynamic
    plan = SimPlan(Link(delay=0.002), wrap={agent_pid(LIAR): lambda m: Liar(m, LIAR, **liar)})
    return simulate_run(scn, trace, "diskf", 0, run_id=RUN, plan=plan)


def test_a_lie_after_a_withheld_report_is_unverifiable_and_never_exits_0(dynamic):
    r = run(dynamic, start=FROM, offset=OFFSET, withhold=WITHHELD)
    st = r.status
    assert not r.record.reported[WITHHELD - 1, LIAR - 1] and r.record.reported.sum() == r.record.reported.size - 1
    assert st.status == "unverifiable", st.reason
    un = st.evidence["unverifiable"]
    assert un["withheld"] == [{"agent": LIAR, "tick": WITHHELD}]
    assert un["listed"][0]["tick"] == FROM and st.evidence["unverified"] == un["agent_ticks"] > 0
    # an honest agent that fused the liar's message is itself unverifiable
    assert {"tick": FROM, "agent": 8, "senders": [LIAR]} in un["listed"]
    assert st.evidence["missing_fraction"] < 0.01
    for allow_missing in (0.0, 0.01, 1.0):
        for degraded in (False, True):
            code, level, line = accept(st, allow_missing=allow_missing, allow_degraded=degraded)
            assert code == exits.UNVERIFIABLE and level == "error", line
    code, level, line = accept(st, allow_missing=0.01, accept_unverifiable=True)
    assert code == exits.OK and level == "warning" and f"{un['agent_ticks']} reported agent-ticks" in line
    code, _, _ = accept(st, accept_unverifiable=True)  # the missing report still needs --allow-missing
    assert code == exits.UNVERIFIABLE


def test_a_withheld_report_alone_is_only_incomplete(dynamic):
    r = run(dynamic, start=K + 1, offset=0.0, withhold=WITHHELD)
    assert r.status.status == "incomplete", r.status.reason
    assert r.status.evidence["unverified"] == 0
    assert accept(r.status, allow_missing=0.01)[0] == exits.OK

"""Insiders that lie, on the simulated network with the real machines
(docs/security.md): an agent holding only its own identity offsets the
estimates it sends and reports, after withholding one report or not.

    a lie                           the world's check as the run goes names
                                    the liar at the tick an honest agent
                                    fused its lie and cuts it off from the
                                    next; the run ends ``diverged`` saying
                                    who, from which tick, and who fused it
    a lie after a withheld report   the agent-ticks built on it cannot be
                                    verified: ``unverifiable``, never
                                    accepted by ``--allow-missing``, only
                                    by ``--accept-unverifiable`` (the world
                                    cuts off no one it cannot prove lied:
                                    an honest agent whose report was lost
                                    looks the same)
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from diskf_mesh import estimators
from diskf_mesh.core import exits
from diskf_mesh.data import metrics
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

    def __init__(self, inner, who: int, start: int, offset: float, withhold: int | None = None,
                 exchanged=EXCHANGED):
        self.inner, self.who, self.start_tick, self.offset, self.withhold = inner, who, start, offset, withhold
        self.exchanged = exchanged

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
                m = wire.decode(e.payload, run_id=RUN, sender=self.who, exchanged=self.exchanged)
                if m.tick >= self.start_tick:
                    lie = dataclasses.replace(m.message, x_pred=m.message.x_pred + self.offset,
                                              x_upd=m.message.x_upd + self.offset)
                    e = dataclasses.replace(e, payload=wire.encode(RUN, self.who, m.tick, lie, self.exchanged))
            out.append(e)
        return out


@pytest.fixture(scope="module")
def dynamic():
    scn = load_scenario("dynamic").with_overrides(steps=K)  # Scenario 2: agent 3 meets agent 8 from tick 39 on
    return scn, simulate(scn, [0])


def run(dynamic, algorithm="diskf", online=True, recorder=None, **liar):
    scn, trace = dynamic
    ex = estimators.get(algorithm).exchanged
    plan = SimPlan(Link(delay=0.002), online=online,
                   wrap={agent_pid(LIAR): lambda m: Liar(m, LIAR, exchanged=ex, **liar)})
    return simulate_run(scn, trace, algorithm, 0, run_id=RUN, plan=plan, recorder=recorder)


def honest_mae(dynamic, rec, since: int) -> float:
    """The honest agents' position error from tick ``since`` on."""
    scn, trace = dynamic
    honest = np.arange(len(scn.agents)) != LIAR - 1
    e_state = metrics.errors(trace, rec.estimates(fill=True))[0][0]
    return float(e_state[since - 1:, honest][rec.reported[since - 1:, honest]].mean())


@pytest.mark.parametrize("algorithm", ["diskf", estimators.DEFAULT])
def test_the_world_names_a_liar_within_3_ticks_and_cuts_it_off(dynamic, algorithm):
    r = run(dynamic, algorithm, start=FROM, offset=OFFSET)
    rec, st = r.record, r.status
    assert len(rec.quarantined) == 1, rec.quarantined
    q = rec.quarantined[0]
    # named by the check of the first tick an honest agent fused the lie; cut off from the tick after next
    # at the latest (the check runs while the agents work on the next tick)
    assert q["agent"] == LIAR and q["why"] == "lied" and q["tick"] == FROM and FROM < q["from"] <= FROM + 2
    cut = q["from"] - 1
    # the ticks announce it: not live from then on, no honest agent fuses it, nothing of it is reported
    assert not rec.live[cut:, LIAR - 1].any() and not rec.fused[cut:, :, LIAR - 1].any()
    assert set(rec.why[cut:, LIAR - 1]) == {"quarantined"} and not rec.reported[cut:, LIAR - 1].any()
    assert rec.reported[:, np.arange(len(rec.ids)) != LIAR - 1].all()
    assert st.status == "diverged", st.reason
    ev = st.evidence["quarantined"]
    assert [(e["agent"], e["why"], e["named_at"], e["from"]) for e in ev] == [(LIAR, "lied", q["tick"], q["from"])]
    # agent 8 fused its lie until it was cut off
    assert ev[0]["fused_by"] == [{"tick": t, "agent": 8} for t in range(FROM, q["from"])]
    assert f"agent {LIAR} cut off from tick {q['from']}" in st.reason
    # cut off, the liar no longer moves the honest agents
    free = run(dynamic, algorithm, online=False, start=FROM, offset=OFFSET)
    assert not free.record.quarantined and free.status.status == "diverged"
    assert honest_mae(dynamic, rec, FROM + 10) < honest_mae(dynamic, free.record, FROM + 10)


@pytest.mark.parametrize("online", [True, False])
def test_a_lie_after_a_withheld_report_is_unverifiable_and_never_exits_0(dynamic, online):
    r = run(dynamic, online=online, start=FROM, offset=OFFSET, withhold=WITHHELD)
    st, rec = r.status, r.record
    assert not rec.reported[WITHHELD - 1, LIAR - 1]
    assert not rec.quarantined and rec.reported.sum() == rec.reported.size - 1
    assert st.status == "unverifiable", st.reason
    un = st.evidence["unverifiable"]
    assert un["withheld"] == [{"agent": LIAR, "tick": WITHHELD}]
    assert un["listed"][0]["tick"] == FROM and st.evidence["unverified"] == un["agent_ticks"] > 0
    # an honest agent that fused the liar's message is itself unverifiable
    assert {"tick": FROM, "agent": 8, "senders": [LIAR]} in un["listed"]
    for allow_missing in (0.0, 0.01, 1.0):
        for degraded in (False, True):
            code, level, line = accept(st, allow_missing=allow_missing, allow_degraded=degraded)
            assert code == exits.UNVERIFIABLE and level == "error", line
    code, level, line = accept(st, allow_missing=1.0, accept_unverifiable=True)
    assert code == exits.OK and level == "warning" and f"{un['agent_ticks']} reported agent-ticks" in line
    code, _, _ = accept(st, accept_unverifiable=True)  # the missing reports still need --allow-missing
    assert code == exits.UNVERIFIABLE


def test_a_withheld_report_alone_is_only_incomplete(dynamic):
    r = run(dynamic, start=K + 1, offset=0.0, withhold=WITHHELD)
    assert r.status.status == "incomplete", r.status.reason
    assert r.status.evidence["unverified"] == 0
    assert accept(r.status, allow_missing=0.01)[0] == exits.OK


@pytest.mark.parametrize("withhold", [None, WITHHELD])
def test_replay_of_a_recording_says_the_same_and_never_exits_0(dynamic, tmp_path, withhold, capsys):
    """The recording holds each tick's live set, so the engine applies the
    same quarantine from the same ticks: ``replay`` finds the run's status
    on what was delivered (diverged, or unverifiable), never exit 0 under
    ``--allow-missing``; ``--accept-unverifiable`` accepts the unverifiable
    one and its line gives the count."""
    from diskf_mesh.data.faults import FaultConfig
    from diskf_mesh.recording.command import replay_recording
    from diskf_mesh.recording.writer import Recorder

    scn, trace = dynamic
    path = tmp_path / "run.mcap"
    recorder = Recorder(path, trace, scn, scenario="dynamic", algorithm="diskf", seed=0, run_id=RUN,
                        faults=FaultConfig())
    r = run(dynamic, recorder=recorder, start=FROM, offset=OFFSET, withhold=withhold)
    assert bool(r.record.quarantined) == (withhold is None) and r.status.status in ("diverged", "unverifiable")
    assert recorder.finish("done", {}, r.status.to_json()) is None
    want = exits.DIVERGED if withhold is None else exits.UNVERIFIABLE
    for allow in (0.0, 0.2):
        assert replay_recording(str(path), allow_missing=allow, allow_degraded=True) == want
    err = capsys.readouterr().err
    assert ("diverged" if withhold is None else "unverifiable run") in err, err
    if withhold is not None:
        assert replay_recording(str(path), allow_missing=0.2, accept_unverifiable=True) == exits.OK
        n = r.status.evidence["unverified"]
        assert f"unverifiable run accepted (--accept-unverifiable): {n} reported agent-ticks" in capsys.readouterr().err


@pytest.mark.parametrize("withhold", [None, WITHHELD])
def test_the_check_as_the_run_goes_judges_each_tick_as_the_end_of_run_check(dynamic, withhold, monkeypatch):
    """``engine.verify.Online`` fed the record tick by tick finds the same
    diverged and unverifiable agent-ticks as the end-of-run replay."""
    from diskf_mesh.engine import verify
    from diskf_mesh.mesh.protocol.run_status import OnlineCheck

    scn, trace = dynamic
    r = run(dynamic, online=False, start=FROM, offset=OFFSET, withhold=withhold)
    ev = r.status.evidence  # the end-of-run check, before the online one is watched
    check = OnlineCheck(trace, estimators.get("diskf"), scn.params, run_id=RUN, seed=0)
    judged = []
    tick = verify.Judge.tick
    monkeypatch.setattr(verify.Judge, "tick", lambda judge, *a, **kw: judged.append(tick(judge, *a, **kw)) or judged[-1])
    named = [q for k in range(1, K + 1) for q in check.tick(r.record, k)]
    assert sum(int(j.diverged.sum()) for j in judged) == ev.get("diverged", {}).get("agent_ticks", 0)
    assert sum(int(j.unverified.sum()) for j in judged) == ev["unverified"] > 0
    assert [(q["agent"], q["tick"]) for q in named] == ([(LIAR, FROM)] if withhold is None else [])


def test_up_on_the_simulated_network_never_exits_0_on_a_lie_after_a_withheld_report(tmp_path):
    """``up --network simulated`` with the lie planned (``--lie ...,withhold=``):
    exit 8 whatever ``--allow-missing`` and ``--allow-degraded`` say; 0 only
    with ``--accept-unverifiable``, its line giving the count."""
    lie = f"agent={LIAR},kind=offset,size={OFFSET},from={FROM},reports=lying,withhold={WITHHELD}"

    def up(*flags):
        res = tmp_path / f"r{len(flags)}.json"
        done = subprocess.run([sys.executable, "-m", "diskf_mesh.cli.main", "up", "--network", "simulated",
                               "--scenario", "dynamic", "--algorithm", "diskf", "--ticks", str(K), "--lie", lie,
                               "--json", str(res), "--quiet", *flags], capture_output=True, text=True, cwd=tmp_path,
                              timeout=300, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
        return done, next(iter(json.loads(res.read_text())["diskf"].values()))

    done, row = up("--allow-missing", "1", "--allow-degraded")
    assert done.returncode == exits.UNVERIFIABLE and row["status"] == "unverifiable", done.stderr
    n = row["evidence"]["unverified"]
    assert f"unverifiable run: {n} reported agent-ticks cannot be verified" in done.stderr
    done, row = up("--allow-missing", "1", "--accept-unverifiable")
    assert done.returncode == exits.OK and f"accepted (--accept-unverifiable): {n} reported" in done.stderr


def test_in_real_time_the_world_names_a_liar_within_3_ticks_and_cuts_it_off(dynamic):
    """A real-time run (``--rate``): a tick's reports are final when they all
    came (or ``LEAD_TICKS`` later); the check of tick 50 names the liar and
    it is cut off within 3 ticks."""
    from diskf_mesh.mesh.protocol import clock as realtime
    from diskf_mesh.mesh.protocol.agent_machine import AgentTiming
    from diskf_mesh.mesh.protocol.world_machine import WorldTiming

    scn, trace = dynamic
    clock = realtime.Clock(rate_hz=20.0, deadline_s=0.02)
    plan = SimPlan(Link(delay=0.002), world_timing=WorldTiming(clock=clock), agent_timing=AgentTiming(clock=clock),
                   wrap={agent_pid(LIAR): lambda m: Liar(m, LIAR, start=FROM, offset=OFFSET)})
    r = simulate_run(scn, trace, "diskf", 0, run_id=RUN, plan=plan)
    [q] = r.record.quarantined
    assert q["agent"] == LIAR and q["tick"] == FROM and FROM < q["from"] <= FROM + 3, q
    assert not r.record.fused[q["from"] - 1:, :, LIAR - 1].any()
    assert r.status.status == "diverged", r.status.reason


@pytest.mark.parametrize("withhold", [None, WITHHELD])
def test_the_status_from_the_check_as_it_went_is_the_end_of_run_replays(dynamic, withhold):
    """A run with a liar the world cut off (and one that withheld a report
    first): its status, taken from the world's check as the run went
    (``replayed_online``), is the status a second replay of the whole run
    gives, reason and evidence."""
    from diskf_mesh.mesh.protocol.run_status import run_status

    r = run(dynamic, start=FROM, offset=OFFSET, withhold=withhold)
    again = run_status(r.record, r.trace, r.algorithm, r.scn.params, run_id=r.run_id, seed=r.seed, faults=r.faults,
                       deadline_s=r.deadline_s, labels=r.scn.labels)
    st = r.status
    assert st.evidence.pop("replayed_online") and not again.evidence.pop("replayed_online")
    assert (st.status, st.reason, st.evidence) == (again.status, again.reason, again.evidence)
    assert st.status == ("diverged" if withhold is None else "unverifiable"), st.reason

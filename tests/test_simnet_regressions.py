"""Schedules of the simulated network that once broke an invariant, each
with what it found; every one must keep the invariants now. They were found
with every watcher of a token hearing it as its own event (``views=False``)
and every sample as its own event (``arrivals=False``), and their faults
after the n-th event count those events: they replay so."""
from __future__ import annotations

import numpy as np
import pytest

import simnet_cases as cases
from simnet_cases import Case

from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.mesh.simulated.simnet import Fault, Link

FOUND = [
    # diskf-r's input model took its default scales from the sensors it was given: the engine's are every
    # agent's, an agent process's its own, so a mesh agent's covariance differed from the engine's at tick 1
    # (P 1e4 against 2e4) with no fault at all: "diverged"
    # (fixed: ``Sensors.whole``, the run's sensors an agent's own is selected from, give every agent the scales)
    pytest.param(Case(agents=3, ticks=20, algorithm="diskf-r", seed=0), id="diskf-r-own-sensor-scales"),
    # the same in diskf-auto (its input models' scales from Q, G and the sensors it is given): sweep seed 30
    pytest.param(Case(agents=3, ticks=20, algorithm="diskf-auto", seed=0), id="diskf-auto-own-sensor-scales"),
    # sweep seed 5502: the world and agent 4 paused 9.7 s, agent 4's lease ran out; it woke before its session
    # was back, resynced, asked the world for its start (no route: no answer), started from the prior and
    # said so on a session that reached no one; its report of tick 47 then reached the world, which never
    # heard of the re-initialisation: "diverged" at agent 4, tick 47
    # (fixed: every report carries its agent's latest (re)initialisation, so the report that reaches the
    # world says how the estimate started; no separate rejoin notice)
    pytest.param(Case(agents=4, ticks=56, algorithm="diskf-r", seed=44597, scenario="quadrants",
                      link=Link(delay=0.002, jitter=0.002), faults=(
                          Fault("crash", "agent-2", after_event=1424, lease=True),
                          Fault("restart", "agent-2", after_event=1557),
                          Fault("pause", "world", after_event=1140, duration=9.7),
                          Fault("pause", "agent-4", after_event=1205, duration=9.7))),
                 id="sweep-5502-rejoin-unheard"),
    # a process test (a second agent 3 started while the run goes): the twin's session had not heard the
    # first process's token when it confirmed its id (their link is slow: the liveliness query's round trip
    # exceeds its timeout), so it joined, started from a neighbour's estimate and published; where its
    # message reached a neighbour before the first process's (here: the first one's links are slower), that
    # neighbour fused the twin's as agent 3's: "diverged"
    # (fixed: the world's start answer names the processes it sees holding the id; the twin leaves at once)
    pytest.param(Case(agents=9, ticks=60, algorithm="diskf", seed=1, scenario="dynamic", twins=((3, 0.02),),
                      links=cases.apart("agent-3") + tuple((("agent-3", f"agent-{i}"), Link(delay=0.001)) for i in (1, 2, 4, 5, 6, 7, 8, 9))),
                 id="late-twin-unseen-by-its-session"),
    # sweep seeds 196 and 5084: two processes of one id whose sessions never hear each other (a 30 s link
    # between them), one started a moment after the other (196: while the run ticks; 5084: at once): each
    # took itself for the only one, both published and reported as the agent; the neighbours and the world
    # took whichever copy came first: "diverged" (agent 1 fused at tick 2 a message of agent 3 the engine
    # does not reproduce; agent 4's estimate of tick 25 differs from the replay)
    # (fixed: every tick names the process the world counts as each live id; any other leaves before working)
    pytest.param(Case(agents=4, ticks=29, algorithm="diskf-auto", seed=63630, scenario="quadrants",
                      link=Link(delay=0.0002, jitter=0.002),
                      faults=(Fault("crash", "agent-1", after_event=928), Fault("restart", "agent-1", after_event=1416),
                              Fault("pause", "agent-4", after_event=863, duration=4.7)),
                      twins=((3, 0.0058),), injected=FaultConfig(latency_ms=1.0, reorder=0.1),
                      links=cases.apart("agent-3")), id="sweep-196-twins-unheard-by-each-other"),
    pytest.param(Case(agents=9, ticks=29, algorithm="diskf", seed=15951, scenario="dynamic",
                      link=Link(delay=0.02, jitter=0.2, duplicate=0.1, reorder=0.5, hold=0.04,
                                faulty="diskf/sim/agent/*/msg/**"),
                      faults=(Fault("pause", "agent-4", after_event=436, duration=10.3),),
                      twins=((4, 0.0001),), links=cases.apart("agent-4")), id="sweep-5084-twins-at-once-unheard"),
    # sweep seeds 1906, 4079, 7045: an agent and the world both paused past the lease; the agent rejoined
    # (from its prior, or a neighbour's estimate) without missing a tick, since the world waited for it:
    # every agent-tick reported, every fused set nominal, every estimate the replay's, and the run said
    # "exact" though the rejoined agent's estimates are not the algorithm's own (max |dx| 2173, 25, 398)
    # (fixed: a run with a re-initialisation is "degraded", naming the first)
    pytest.param(Case(agents=5, ticks=40, algorithm="diskf-r", seed=38227, link=Link(delay=0.002, jitter=0.002),
                      faults=(Fault("pause", "agent-4", after_event=208, duration=29.99),
                              Fault("pause", "world", after_event=274, duration=5.3))), id="sweep-1906-rejoin-said-exact"),
    pytest.param(Case(agents=4, ticks=35, algorithm="ldrkf", seed=42190, scenario="quadrants",
                      link=Link(delay=0.002, jitter=0.002, duplicate=0.1, hold=0.004),
                      faults=(Fault("pause", "agent-1", after_event=915, duration=5.01),
                              Fault("pause", "world", after_event=885, duration=29.99))), id="sweep-4079-rejoin-said-exact"),
    pytest.param(Case(agents=7, ticks=37, algorithm="diskf", seed=34369, link=Link(delay=0.002, jitter=0.002),
                      faults=(Fault("pause", "world", after_event=589, duration=9.7),
                              Fault("pause", "agent-3", after_event=541, duration=30.01))), id="sweep-7045-rejoin-said-exact"),
    # sweep seed 15913: agent 6, frozen past the lease, rejoined and asked the world for its start while the
    # world was paused 10.3 s; no answer within ASK_S, and it started from its prior though agents 2, 5, 7
    # and 8, in range, had reported the tick before: invariant (e)
    # (fixed: no answer is asked again; the prior only when the world answers it)
    pytest.param(Case(agents=9, ticks=36, algorithm="diskf", seed=6405, link=Link(delay=0.002, jitter=0.02, hold=0.05),
                      faults=(Fault("pause", "agent-6", after_event=741, duration=9.7),
                              Fault("pause", "agent-4", after_event=1422, duration=29.7),
                              Fault("pause", "world", after_event=1736, duration=10.3)),
                      late=((1, 0.001),), injected=FaultConfig(loss=0.1, latency_ms=1.0, jitter_ms=1.0, duplicate=0.1,
                                                               reorder=0.1, reorder_ms=50.0),
                      scenario="dynamic"),
                 id="sweep-15913-rejoin-asked-a-frozen-world"),
]


@pytest.mark.parametrize("case", FOUND)
def test_found_schedules_keep_the_invariants(case):
    cases.check(case, cases.run(case, views=False, arrivals=False))


# a process test (a second agent 5 started while the run goes) left with exit 2 but the world never counted
# it: the twin's session had not heard the first process's token, so it left at the first tick that named
# the other process (holder tags) without the duplicate notice only its claim sent ("duplicate_ids" {} in a
# run whose twin left); here the twin of agent 3 is unheard by its own session's queries and leaves that way
# (fixed: every way a twin leaves tells the world first)
TWIN_LEAVES = [p for p in FOUND if p.id in ("sweep-196-twins-unheard-by-each-other", "sweep-5084-twins-at-once-unheard")]


@pytest.mark.parametrize("case", TWIN_LEAVES)
def test_a_twin_that_leaves_is_counted_by_the_world(case):
    r = cases.run(case, views=False, arrivals=False)
    (who, _), = case.twins
    left = [pid for pid, end in r.outcome.finishes.items() if "~" in pid and end.code == 2]
    assert left == [cases.agent_pid(who, 1)]
    assert r.record.duplicates == {who: 1}


# the 89 sweep seeds of 50,000-51,999 that ended with no status: the world gave up before any report came (an agent
# started after the startup timeout, or crashed, paused or was interrupted before it was ready; the world
# interrupted before tick 1; in 50371 a second world, and the run's world was taken for the one that left
# as a duplicate), and a run with no report had none; 50067, 50410 and 50431 with no fault but a late start
# (fixed: a world that ends before any report gives the run an incomplete status, its reason first; the
# world that stayed is the run's)
NO_STATUS = [50067, 50084, 50108, 50130, 50171, 50175, 50176, 50195, 50210, 50223, 50226, 50237, 50258, 50271, 50313,
             50325, 50342, 50364, 50371, 50405, 50408, 50410, 50420, 50431, 50442, 50466, 50487, 50518, 50526, 50529,
             50545, 50558, 50631, 50688, 50699, 50742, 50779, 50803, 50870, 50896, 50899, 50902, 50916, 50920, 50922,
             50930, 50940, 50975, 50976, 50988, 51002, 51008, 51072, 51082, 51112, 51121, 51141, 51169, 51189, 51191,
             51235, 51268, 51276, 51301, 51312, 51322, 51343, 51348, 51363, 51402, 51404, 51449, 51466, 51490, 51511,
             51555, 51642, 51649, 51655, 51681, 51682, 51706, 51724, 51726, 51750, 51754, 51914, 51954, 51957]


@pytest.mark.parametrize("seed", NO_STATUS)
def test_sweep_seeds_that_ended_with_no_status(seed):
    case = cases.from_seed(seed)
    r = cases.run(case, views=False, arrivals=False)
    cases.check(case, r)
    assert r.status.status == "incomplete" and not r.record.reported.any()
    assert r.status.reason.startswith(r.world.finish.reason), (r.status.reason, r.world.finish)


def test_a_late_start_past_the_startup_timeout():
    """Sweep seed 50067: agent 4 starts 60 s late, no other fault. The
    world gives up at 30 s: incomplete, naming agent 4. With allow_missing
    the world starts without it and the others report every tick."""
    from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run

    case = cases.from_seed(50067)
    assert case.late == ((4, 60.01),) and not case.faults and case.injected is None
    r = cases.run(case, views=False, arrivals=False)
    assert r.status.status == "incomplete"
    assert r.status.reason.startswith("after 30 s waiting for the agents: no agent process for id 4")
    scn, trace = cases.world(case.scenario, case.agents, case.ticks, case.seed)
    plan = SimPlan(case.link, late=dict(case.late), allow_missing=True, max_time=case.bound)
    r = simulate_run(scn, trace, case.algorithm, case.seed, plan=plan)
    j = list(r.record.ids).index(4)
    assert r.status.status == "incomplete" and r.status.evidence["missing_agent_ticks"] == case.ticks
    assert r.record.reported[:, j].sum() == 0 and np.delete(r.record.reported, j, axis=1).all()
    assert r.status.evidence["differing"] == 0


def test_a_late_agent_joins_a_run_that_started_without_it():
    """allow_missing: the world starts without agent 4 at 35 s (30 s and the
    others' 5 s to be ready); agent 4 starts at 40 s, while the run goes,
    and joins it from the prior; every estimate is the replay's."""
    from diskf_mesh.mesh.simulated.simnet import Link
    from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run

    scn, trace = cases.world("random-geometric", 5, 60, 14093)
    r = simulate_run(scn, trace, "diffkf", 14093, plan=SimPlan(Link(0.5), late={4: 40.0}, allow_missing=True,
                                                                max_time=900))
    rep = r.record.reported
    assert r.status.status == "incomplete" and r.status.evidence["differing"] == 0
    assert np.delete(rep, 3, axis=1).all() and not rep[0, 3] and rep[-1, 3]
    (joined,) = r.record.rejoins[4]
    assert rep[joined["tick"] - 1:, 3].all() and not rep[:joined["tick"] - 1, 3].any()


def test_a_late_start_within_the_startup_timeout_runs_exact():
    """A late start and no other fault: agent 4 starts 20 s late, within the
    world's 30 s start-up timeout; the world waits for it and the run is
    exact, every agent-tick reported."""
    from diskf_mesh.mesh.simulated.simrun import SimPlan, simulate_run

    scn, trace = cases.world("random-geometric", 5, 30, 50067)
    r = simulate_run(scn, trace, "diskf", 50067, plan=SimPlan(Link(0.5), late={4: 20.0}, max_time=900))
    assert r.status.status == "exact" and r.record.reported.all()

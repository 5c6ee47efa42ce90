"""Discovery and failure handling: a missing agent ends the world after its
timeout, naming the agent; the launcher stops everything and says which
child failed and why; the protocol itself, in-process."""
from __future__ import annotations

import re
import sys
import threading
import time

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from agents.agent import Agent
from diskf_mesh.core import exits
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.wire import keys as keys_module
from diskf_mesh.mesh.wire.keys import key_matches, matcher
from local_bus import LocalBus
from sim.launcher import Child, ChildFailed, Launcher
from sim.world import World, WorldTiming

from mesh_helpers import reference, start_mesh

pytestmark = pytest.mark.mesh


def test_world_names_the_missing_agent(tmp_path):
    spec = RunSpec("quadrants", "diskf", run_id="missing-4")
    mesh = start_mesh(spec, 10, 0, tmp_path, world_extra=["--startup-timeout", "3"],
                      agent_extra=["--world-timeout", "6"])
    mesh.agents = [a for a in mesh.agents if a.name != "agent 4"]  # agent 4 never starts
    mesh.children = [mesh.world, *mesh.agents]
    t0 = time.monotonic()
    try:
        mesh.start_agents()
        rc = mesh.world.proc.wait(20)
        # the agents notice the world is gone, wait --world-timeout for it to come back, and leave
        agent_rcs = [a.proc.wait(20) for a in mesh.agents]
    finally:
        mesh.stop_all()
    assert rc == exits.INCOMPLETE  # a run that ends with a status: incomplete, the world's reason first
    assert time.monotonic() - t0 < 20
    last = mesh.world.last_error_line()
    assert "no agent process for id 4" in last and "after 3 s" in last, last
    assert all(r == 1 for r in agent_rcs)
    assert "the world is gone" in mesh.agents[0].last_error_line()


def _child(tmp_path, name, code) -> Child:
    return Child(name, [sys.executable, "-c", code], tmp_path / f"{name.replace(' ', '-')}.log")


def test_launcher_reports_the_failed_child_and_stops_the_rest(tmp_path):
    """An agent that fails once the run ticked (the world said "tick 1";
    before it, the world gives up on a missing agent itself)."""
    world = _child(tmp_path, "world", "import time; print('tick 1 0.0', flush=True); time.sleep(60)")
    ok = _child(tmp_path, "agent 1", "import time; time.sleep(60)")
    bad = _child(tmp_path, "agent 2", "import sys, time; time.sleep(0.5); "
                                      "print('boom: no route to the world', file=sys.stderr); sys.exit(1)")
    launcher = Launcher(world, [ok, bad])
    launcher.start()
    with pytest.raises(ChildFailed) as e:
        launcher.wait(30)
    launcher.stop_all()
    msg = str(e.value)
    assert msg.startswith("agent 2 failed (exit code 1): boom: no route to the world")
    assert world.proc.poll() is not None and ok.proc.poll() is not None  # nothing left running


def test_launcher_lets_an_agent_that_stopped_go_and_runs_the_rest_to_the_end(tmp_path):
    """An agent that exits ``exits.STOPPED`` has told the world it left (its
    estimator diverged): not a failed child; the world's own status speaks
    for the run. Exit 1 is a failure (the test above)."""
    world = _child(tmp_path, "world", f"import sys, time; time.sleep(1.5); sys.exit({exits.INCOMPLETE})")
    ok = _child(tmp_path, "agent 1", "import time; time.sleep(60)")
    gone = _child(tmp_path, "agent 2", "import sys, time; time.sleep(0.2); "
                                       "print('error: agent 2: diverged at tick 3', file=sys.stderr); "
                                       f"sys.exit({exits.STOPPED})")
    launcher = Launcher(world, [ok, gone])
    launcher.start()
    try:
        assert launcher.wait(30) == exits.INCOMPLETE
        assert launcher.stopped() == [gone] and ok.proc.poll() is None
    finally:
        launcher.stop_all()


def test_up_rejects_bad_input_in_one_line(tmp_path):
    import subprocess

    done = subprocess.run([sys.executable, "-m", "sim.launcher", "--scenario", "no-such-scenario"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith("error: scenario: unknown scenario")


def test_key_expressions_and_key_space():
    k = Keys("run-1")
    assert k.parse(k.msg(7)) == ("msg", 7)
    assert k.parse(k.report(3)) == ("report", 3)
    assert k.parse(k.meas(2)) == ("meas", 2)
    assert k.parse(k.tick) == ("tick", None)
    assert k.parse(k.alive(5)) == ("alive", 5)
    assert k.parse(k.ready(5)) == ("ready", 5)
    assert k.parse(k.alive_world) == ("alive-world", None)
    assert k.parse("diskf/other-run/agent/7/msg") == (None, None)
    assert k.parse("diskf/run-1/agent/x/msg") == ("msg", None)
    assert key_matches("diskf/r/agent/*/msg", "diskf/r/agent/12/msg")
    assert not key_matches("diskf/r/agent/*/msg", "diskf/r/agent/12/report")
    assert key_matches("diskf/r/**", "diskf/r/alive/agent/3")
    # addressed messages: the receiver's subscription matches the agents named, no other
    assert k.msg(3, to=[7, 1]) == "diskf/run-1/agent/3/msg/_1_7_"
    assert k.parse(k.msg(3, to=[1, 7])) == ("msg", 3)
    assert k.parse(k.msg(3, to=[])) == ("msg", 3)
    assert k.parse("diskf/run-1/agent/3/msg/1_7") == (None, None)
    assert key_matches(k.msg_to(7), k.msg(3, to=[1, 7]))
    assert key_matches(k.msg_to(1), k.msg(3, to=[1, 7]))
    assert not key_matches(k.msg_to(17), k.msg(3, to=[1, 7]))
    assert not key_matches(k.msg_to(7), k.msg(3, to=[17]))
    assert not key_matches(k.msg_to(7), k.msg(3, to=[]))
    assert not key_matches(k.msg_to(7), k.msg(3))
    assert key_matches(k.msgs, k.msg(3)) and key_matches(k.msgs, k.msg(3, to=[7]))
    from diskf_mesh.core.errors import InputError
    with pytest.raises(InputError):
        Keys("has/slash")


def test_protocol_in_process_equals_engine():
    """World and agents as threads over the in-process bus: same numbers as
    the engine, without zenoh (a quick check of the lockstep protocol)."""
    spec = RunSpec("quadrants", "kcf", run_id="local", topology="ring")
    ticks, seed = 15, 2
    trace, ref = reference(spec, ticks, seed)
    scn = spec.load(ticks)
    bus, keys = LocalBus(), Keys(spec.run_id)
    agents = [Agent(scn, a.id, spec.algorithm, keys, bus.transport()) for a in scn.agents]
    threads = [threading.Thread(target=a.run, daemon=True) for a in agents]
    for t in threads:
        t.start()
    rec = World(scn, trace, spec.algorithm, seed, keys, bus.transport(), WorldTiming(5.0, 5.0, 1.0)).run()
    for t in threads:
        t.join(5)
    assert rec.reported.all()
    np.testing.assert_allclose(rec.x, ref.x[0], rtol=0, atol=1e-9)
    assert all(not t.is_alive() for t in threads)


@settings(max_examples=400, deadline=None)
@given(head=st.lists(st.sampled_from(["a", "b", "7", "x_1"]), min_size=1, max_size=3),
       key=st.lists(st.sampled_from(["a", "b", "7", "x_1", "", "**"]), min_size=0, max_size=5),
       last=st.sampled_from(["**", "*"]))
@example(head=["a"], key=["a", "", "a"], last="**")  # an empty chunk right after the head: a//a
def test_an_expression_below_a_head_matches_as_its_pattern(head, key, last):
    """``matcher("head/**")`` and ``matcher("head/*")`` (matched without a
    pattern) agree with the compiled pattern of the same expression on keys
    of any chunks, empty ones included."""
    expr = "/".join(head) + "/" + last
    k = "/".join(key)
    pattern = re.compile(keys_module._pattern(expr)).fullmatch
    assert (matcher(expr)(k) is not None) == (pattern(k) is not None), (expr, k)

"""Who may speak, tried as a hostile local user would: one default
``diskf-mesh up`` run (TLS, mutual authentication, access control; Scenario 2,
a fixed seed) while attackers who read its run id and port off the process
table (``/proc/<pid>/cmdline``, as ``ps`` does) try to hear it and to feed
it, all at once, from before the first tick to the end:

* three uncredentialed zenoh sessions: plain TCP to the world's port, TLS
  with a certificate named ``world`` of their own CA, and multicast
  scouting. Each subscribes to everything of the run and publishes forged
  agent messages (real arrays, false senders, this tick and the next),
  ``world/stop``, ticks, measurements, reports, and liveliness tokens
  (every agent alive and ready, the world alive and ticking);
* a credentialed agent: sessions with agent 3's certificate and key of the
  run's own CA, taken from agent 3's memory (agent 3 compromised: all it
  holds is its own identity, tests/test_identities.py).
  It publishes the same forgeries for every other agent and for the world,
  on its own key a report with x = 1e300 (refused by the world's decoder),
  and replays every message
  addressed to it with its tick rewritten (one ahead), on the real sender's
  key and on its own; and it subscribes to every measurement and every
  agent key, to hear what agent 3 may not.

The run must exit 0 with every agent-tick reported and its estimates equal
to the engine's bit for bit; the uncredentialed sessions hear nothing, the
credentialed one hears only what agent 3 may hear. A control run with
``up --insecure`` shows that the plain-TCP listener does hear a run
without credentials. Agent links carry 40 ms of latency (fault layer, far
below the collect timeout: every message still arrives in time) so that the
ticks last long enough for every attacker to be connected during them.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest

from diskf_mesh.mesh.wire import codec as wire
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.transport import MeshError, ZenohTransport
from diskf_mesh.mesh.process.zenoh_config import STDIN, ZenohOptions

from memory_probe import identity_of
from mesh_helpers import assert_same, reference
from message_factory import tick_view

pytestmark = pytest.mark.mesh

TICKS, SEED, LATENCY_MS = 60, 7, 40
SETTING = "range=120"
INSIDER = 3  # the compromised agent


def spec_of(run_id: str) -> RunSpec:
    return RunSpec("dynamic", "diskf", run_id=run_id)


def start_up(tmp: Path, run_id: str, *extra) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "sim.launcher", "--scenario", "dynamic", "--algorithm", "diskf",
           "--ticks", str(TICKS), "--seed", str(SEED), "--run-id", run_id, "--latency-ms", str(LATENCY_MS),
           "--estimates", str(tmp / "est.json"), "--json", str(tmp / "res.json"), "--logs", str(tmp / "logs"),
           "--quiet", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def from_process_table(run_id: str, timeout: float = 30.0) -> dict:
    """What ``ps`` shows of the run's world process (its flags) and the pid
    of agent ``INSIDER``."""
    deadline = time.monotonic() + timeout
    seen = {}
    while time.monotonic() < deadline:
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                argv = [a.decode() for a in (d / "cmdline").read_bytes().split(b"\0")]
            except OSError:
                continue
            if "sim.world" in argv and run_id in argv:
                flag = lambda f: argv[argv.index(f) + 1] if f in argv else None  # noqa: E731
                seen.update(listen=flag("--listen"), credentials=flag("--credentials"))
            if "agents.agent" in argv and run_id in argv and argv[argv.index("--id") + 1] == str(INSIDER):
                seen["insider"] = int(d.name)
        if len(seen) == 3:
            return seen
        time.sleep(0.05)
    raise AssertionError(f"no world and agent {INSIDER} of run {run_id} within {timeout} s: {seen}")


def stolen_identity(pid: int, run_id: str, ids, timeout: float = 30.0) -> ZenohOptions | None:
    """Agent ``INSIDER``'s identity, taken from its process's memory once it
    holds it, as zenoh options; None if this process may not read that
    memory (not root: the run's processes are closed to their user's others)."""
    name = credentials.agent_identity(INSIDER)
    deadline = time.monotonic() + timeout
    while True:
        try:
            ident = identity_of(pid, name, run_id, ids)
            break
        except PermissionError:
            return None
        except (KeyError, StopIteration, OSError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    return ZenohOptions(credentials=STDIN, held={name: ident})


class Attacker(threading.Thread):
    """One zenoh session: listens on ``listen`` key expressions (counting the
    samples and token changes it hears), declares ``tokens``, and publishes
    ``forge(k)`` every 50 ms until ``stop`` is set."""

    def __init__(self, name, options, listen, tokens, forge, on_sample=None):
        super().__init__(name=name, daemon=True)
        self.options, self.listen, self.tokens, self.forge = options, listen, tokens, forge
        self.on_sample = on_sample
        self.heard, self.puts, self.opened, self.error = [], 0, False, None
        self.stop = threading.Event()

    def _hear(self, key, payload):
        self.heard.append(key)
        if self.on_sample is not None and isinstance(payload, bytes):
            self.on_sample(self, key, payload)

    def run(self):
        try:
            with ZenohTransport(self.options) as t:
                self.opened, self.transport = True, t
                for expr in self.listen:
                    t.subscribe(expr, self._hear)
                    t.watch_tokens(expr, self._hear)
                for key in self.tokens:
                    t.declare_token(key)
                it = 0
                while not self.stop.is_set():
                    for key, payload in self.forge(it % TICKS + 1):
                        t.put(key, payload)
                        self.puts += 1
                    it += 1
                    self.stop.wait(0.05)
        except MeshError as e:  # a session that cannot even open hears and says nothing
            self.error = str(e)


def forgeries(run_id: str, ids, skip=()) -> callable:
    """forge(k): well-formed messages of run ``run_id`` that would change the
    run if any got in (senders in ``skip`` left out)."""
    keys = Keys(run_id)
    view = tick_view("diskf", scenario="dynamic", tick=5)  # real arrays of Scenario 2
    others = [i for i in ids if i not in skip]
    positions = np.zeros((len(ids), 2))

    def forge(k):
        out = []
        for i in others:
            to = [j for j in ids if j != i]
            for t in (k, k + 1):
                out.append((keys.msg(i, to=to), wire.encode(run_id, i, t, view.messages[i])))
            out.append((keys.report(i), wire.encode_report(run_id, i, k, np.full(2, 1e3), np.eye(2), np.ones(1),
                                                           True, {"sent": 2 ** 63 - 1})))
            out.append((keys.meas(i), wire.encode_measurement(run_id, k, i, True, np.full(1, 500.0))))
        out.append((keys.tick, wire.encode_tick(wire.Tick(run_id, k + 1, TICKS, SEED, "diskf", "range", 120.0,
                                                          positions, tuple(ids)))))
        out.append((keys.stop, wire.encode_stop(run_id, k, "done")))
        return out

    return forge


def rewrite_tick(payload: bytes, by: int = 1) -> bytes:
    doc = msgpack.unpackb(payload, raw=False)
    doc["t"] = int(doc["t"]) + by
    return msgpack.packb(doc, use_bin_type=True)


@pytest.fixture(scope="module")
def attacked(tmp_path_factory):
    """The default run under every attack at once; returns what happened."""
    tmp = tmp_path_factory.mktemp("attacked")
    run_id = f"attack{os.getpid()}"
    spec = spec_of(run_id)
    ids = [a.id for a in spec.load(TICKS).agents]
    keys = Keys(run_id)
    own_ca = credentials.make(tmp / "own-ca", run_id, ids)  # the attacker's own CA, same names
    proc = start_up(tmp, run_id)
    attackers = []
    try:
        seen = from_process_table(run_id)
        assert seen["listen"].startswith("tls/127.0.0.1:") and seen["credentials"] == STDIN  # TLS, loopback
        stolen = stolen_identity(seen["insider"], run_id, ids)
        port = seen["listen"].rsplit(":", 1)[1]
        everything = [f"{keys.root}/**"]
        forged = "0000000000000000deadbeef"  # the earliest nonce there can be: it would win every id's claim
        all_tokens = [keys.world(forged), keys.ticking] + [k for i in ids for k in (keys.alive(i, forged),
                                                                                    keys.ready(i, forged + ".1"))]
        forge_all = forgeries(run_id, ids)
        plain = ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True, insecure=True,
                             listen=("tcp/127.0.0.1:0",))
        own = ZenohOptions(connect=(f"tls/127.0.0.1:{port}",), listen=("tls/127.0.0.1:0",), no_multicast_scouting=True,
                           credentials=str(own_ca), identity=credentials.WORLD, run_id=run_id)
        # no endpoint of their own: the two find the run (if it answered scouting), never each other
        scout = ZenohOptions(insecure=True, cfg=("listen/endpoints:[]",))
        for name, opts in (("plain tcp", plain), ("own CA", own), ("multicast", scout)):
            # one session listens, another speaks: a session hears its own tokens
            attackers += [Attacker(name, opts, everything, [], lambda k: []),
                          Attacker(f"{name} speaking", opts, [], all_tokens, forge_all)]
        # agent 3's own certificate, from its memory: replays what it is sent, tick rewritten
        insider_keys = [k for k in all_tokens if k not in (keys.alive(INSIDER, forged), keys.ready(INSIDER, forged + ".1"))]

        def replay(att, key, payload):
            kind, sender = keys.parse(key)
            if kind == "msg" and sender != INSIDER and len(att.replays) < 500:
                forged = rewrite_tick(payload)
                att.replays.append(key)
                att.transport.put(key, forged)                                  # as the real sender
                att.transport.put(keys.msg(INSIDER, to=[sender]), forged)       # on its own key

        forge_others = forgeries(run_id, ids, skip=(INSIDER,))

        def forge(k):  # and on its own key, a report no honest agent could send (x = 1e300)
            return forge_others(k) + [(keys.report(INSIDER), wire.encode_report(
                run_id, INSIDER, k, np.array([1e300, 0.0]), 0.1 * np.eye(2), np.zeros(1), True))]

        insiders = []
        if stolen is not None:  # agent 3 speaking (and replaying), and listening for what it may not hear
            insiders = [("agent 3's certificate", [keys.msg_to(INSIDER)], insider_keys, forge, replay),
                        ("agent 3 eavesdropping", [keys.meas(i) for i in ids if i != INSIDER]
                         + [f"{keys.root}/world/meas/*", f"{keys.root}/agent/**"], [], lambda k: [], None)]
        for name, listen, tokens, forge_, on_sample in insiders:
            attackers.append(Attacker(name, replace(stolen, connect=(f"tls/127.0.0.1:{port}",),
                                                    listen=("tls/127.0.0.1:0",), no_multicast_scouting=True,
                                                    identity=credentials.agent_identity(INSIDER), run_id=run_id),
                                      listen, tokens, forge_, on_sample=on_sample))
            attackers[-1].replays = []
        for a in attackers:
            a.start()
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
        for a in attackers:
            a.stop.set()
        for a in attackers:
            a.join(10)
    return {"rc": proc.returncode, "stderr": err, "tmp": tmp, "spec": spec,
            "attackers": {a.name: a for a in attackers}}


def assert_run_intact(result) -> None:
    assert result["rc"] == 0, result["stderr"]
    tmp = result["tmp"]
    est = json.loads((tmp / "est.json").read_text())
    row = json.loads((tmp / "res.json").read_text())["diskf"][SETTING]
    assert np.array(est["reported"]).all() and row["missing_ticks"] == {}
    assert row.get("complete", True) is True
    assert_same(est, reference(result["spec"], TICKS, SEED)[1], tol=0.0)  # bit for bit


def test_the_attacked_run_equals_the_engine_and_is_complete(attacked):
    assert_run_intact(attacked)


@pytest.mark.parametrize("who", ["plain tcp", "own CA", "multicast"])
def test_an_uncredentialed_session_hears_nothing_and_gets_nothing_in(attacked, who):
    listener, speaker = attacked["attackers"][who], attacked["attackers"][f"{who} speaking"]
    assert listener.heard == [], (who, listener.heard[:5])
    assert speaker.error is not None or speaker.puts > 0  # it tried (or zenoh would not even open it)


def insider(attacked, name: str = "agent 3's certificate"):
    """The insider attacker ``name``; the test is skipped where agent 3's
    identity could not be taken (not root)."""
    if name not in attacked["attackers"]:
        pytest.skip("taking agent 3's identity from its memory needs root")
    return attacked["attackers"][name]


def test_a_forged_report_on_the_insiders_own_key_is_refused(attacked):
    insider(attacked)
    est = json.loads((attacked["tmp"] / "est.json").read_text())
    assert est["world_counters"].get("rejected:magnitude", 0) > 0  # they came, and every one was refused
    assert np.abs(np.array(est["x"], dtype=float)).max() < 1e6
    assert_run_intact(attacked)


def test_a_credentialed_agent_cannot_speak_or_listen_for_another(attacked):
    att = insider(attacked)
    assert att.opened and att.puts > 0
    # it was in the run: it heard the messages addressed to agent 3 (from the agents in range), and
    # replayed each with a new tick
    assert att.replays and len(att.replays) == min(len(att.heard), 500)
    assert {Keys(attacked["spec"].run_id).parse(k)[0] for k in att.heard} <= {"msg"}
    # subscribed to every measurement and every agent key, agent 3 hears nothing it may not hear: no
    # other agent's measurement (its own it may), no message addressed to others, no report (the world's and
    # the observer's alone)
    eavesdropper = insider(attacked, "agent 3 eavesdropping")
    keys = Keys(attacked["spec"].run_id)
    assert eavesdropper.opened
    for key in eavesdropper.heard:
        kind, _ = keys.parse(key)
        assert ((kind == "msg" and f"_{INSIDER}_" in key.rsplit("/", 1)[1])
                or key == keys.meas(INSIDER)), key  # its own measurement it may hear: it is agent 3
    # what a replay or a forgery did not do: the run is intact
    assert_run_intact(attacked)


def test_control_an_insecure_run_is_heard_by_anyone(tmp_path):
    """``up --insecure``: the same plain-TCP session hears the run (so
    hearing nothing above is the credentials' doing)."""
    run_id = f"insecure{os.getpid()}"
    proc = start_up(tmp_path, run_id, "--insecure")
    keys = Keys(run_id)
    try:
        port = from_process_table(run_id)["listen"].rsplit(":", 1)[1]
        sniffer = Attacker("sniffer", ZenohOptions(connect=(f"tcp/127.0.0.1:{port}",), listen=("tcp/127.0.0.1:0",),
                                                   no_multicast_scouting=True, insecure=True),
                           [f"{keys.root}/**"], [], lambda k: [])
        sniffer.start()
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
        sniffer.stop.set()
        sniffer.join(10)
    assert proc.returncode == 0, err
    assert len(sniffer.heard) > TICKS

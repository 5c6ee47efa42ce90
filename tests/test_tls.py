"""Credentials (``diskf_mesh.mesh.security.credentials``, docs/security.md): the files,
the refusal to start without them, and what zenoh enforces with them, on
sessions opened the way every mesh process opens them
(``ZenohTransport(ZenohOptions(credentials=DIR, identity=...))``):

* a session of one of the run's identities joins over TLS and samples flow;
* one with a certificate of another CA, with none, or over plain TCP
  delivers no sample and hears none;
* each identity may put and declare liveliness tokens on its own keys only
  and subscribe to what the protocol gives it; the observer only listens.
  The same forgeries with zenoh's access control switched off do get
  through (the control case);
* with multicast scouting (a by-hand run with no endpoints), the run's
  identities find each other over TLS, and a plain-TCP peer scouting the
  same group gets nothing in.

Whole mesh runs under attack: tests/test_attack_access.py.
"""
from __future__ import annotations

import contextlib
import json
import os
import stat
import threading
import time
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives.asymmetric import ec

from diskf_mesh.cli import main as cli
from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.wire.keys import Keys
from diskf_mesh.mesh.process.transport import MeshError, ZenohTransport
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from sim.launcher import free_port

RUN = "tls-test"
KEYS = Keys(RUN)
AGENTS = (1, 2, 7)
SETTLE_S = 1.0   # time given to sessions to connect before they publish
TRY_S = 1.0      # how long a publisher keeps trying


@pytest.fixture(scope="module")
def creds(tmp_path_factory):
    return credentials.make(tmp_path_factory.mktemp("creds") / "run", RUN, AGENTS)


@pytest.fixture(scope="module")
def other_ca(tmp_path_factory):
    """Credentials with the same names and run id, from another CA (an attacker's)."""
    return credentials.make(tmp_path_factory.mktemp("other") / "run", RUN, AGENTS)


def session(creds, who, listen=(), connect=(), cfg=(), multicast=False) -> ZenohOptions:
    return ZenohOptions(credentials=str(creds), identity=who, run_id=RUN, listen=tuple(listen),
                        connect=tuple(connect), no_multicast_scouting=not multicast, cfg=tuple(cfg))


def plain_config(path, listen=(), connect=(), tls=None, multicast=None) -> ZenohOptions:
    """A zenoh JSON5 file for sessions our credentials cannot make (no
    certificate at all, plain TCP)."""
    conf = {"mode": "peer", "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
            "scouting": {"multicast": {"enabled": multicast is not None, **({"address": multicast} if multicast
                                                                            else {})}}}
    if tls is not None:
        conf["transport"] = {"link": {"tls": tls}}
    path.write_text(json.dumps(conf))
    return ZenohOptions(config_file=str(path))


class Sink:
    """Samples and token changes a transport receives under ``expr``."""

    def __init__(self, transport, expr=f"{KEYS.root}/**"):
        self.got, self.event = [], threading.Event()
        transport.subscribe(expr, self._on)
        transport.watch_tokens(expr, self._on)

    def _on(self, key, payload):
        self.got.append((key, payload))
        self.event.set()

    def keys(self) -> set:
        return {k for k, _ in self.got}


def publish_for(t, items, seconds=TRY_S) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for key, payload in items:
            t.put(key, payload)
        time.sleep(0.1)


# --------------------------------------------------------------------------
# the files
# --------------------------------------------------------------------------
def test_one_private_self_contained_directory_per_identity(creds):
    assert stat.S_IMODE(creds.stat().st_mode) == 0o700
    names = credentials.identities(AGENTS)
    assert sorted(p.name for p in creds.iterdir()) == sorted(names)
    ca = x509.load_pem_x509_certificate((creds / "world" / "ca.pem").read_bytes())
    private_keys = 0
    for who in names:
        d = creds / who
        assert stat.S_IMODE(d.stat().st_mode) == 0o700
        assert stat.S_IMODE((d / "key.pem").stat().st_mode) == 0o600
        assert (d / "ca.pem").read_bytes() == (creds / "world" / "ca.pem").read_bytes()
        cert = x509.load_pem_x509_certificate((d / "cert.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value == who
        cert.verify_directly_issued_by(ca)
        assert isinstance(ca.public_key(), ec.EllipticCurvePublicKey)
        for f in d.iterdir():
            private_keys += b"PRIVATE KEY" in f.read_bytes()
        ident = credentials.load(creds, who, RUN)
        assert (ident.run_id, ident.agents, ident.dir) == (RUN, AGENTS, d)
        assert credentials.load(d, who, RUN).dir == d  # an identity's own directory will do
    assert private_keys == len(names)  # one per identity: the CA's key was not kept


def test_credentials_that_do_not_fit_are_refused(creds, tmp_path):
    with pytest.raises(InputError, match="run"):
        credentials.load(creds, "world", "another-run")
    with pytest.raises(InputError, match="agent-7"):
        credentials.load(creds / "agent-7", "agent-1", RUN)
    with pytest.raises(InputError, match="agent-9"):
        credentials.load(creds, "agent-9", RUN)
    loose = credentials.make(tmp_path / "loose", RUN, [1])
    (loose / "world" / "key.pem").chmod(0o644)
    with pytest.raises(InputError, match="0600"):
        credentials.load(loose, "world", RUN)


def test_the_credentials_command(tmp_path, capsys):
    out = tmp_path / "c"
    assert cli.main(["credentials", "--run-id", "r1", "--out", str(out), "--scenario", "quadrants"]) == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(credentials.identities([1, 2, 3, 4]))
    ca = (out / "world" / "ca.pem").read_bytes()
    assert cli.main(["credentials", "--run-id", "r1", "--out", str(out), "--ids", "5,6"]) == 2  # not empty
    assert cli.main(["credentials", "--run-id", "r1", "--out", str(out), "--ids", "5,6", "--replace"]) == 0
    assert (out / "agent-5" / "ca.pem").read_bytes() != ca  # a fresh CA
    assert credentials.load(out, "agent-6", "r1").agents == (5, 6)
    capsys.readouterr()


@pytest.mark.parametrize("command", ["world", "agent"])
def test_world_and_agent_refuse_to_start_without_credentials(command, creds, capsys):
    base = [command, "--scenario", "quadrants", "--run-id", RUN] + (["--id", "1"] if command == "agent" else [])
    for extra in ([], ["--insecure", "--credentials", str(creds)], ["--credentials", str(creds), "--run-id", "x"]):
        assert cli.main(base + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), err


def test_insecure_is_one_warning_line(capsys):
    ZenohOptions(insecure=True).as_identity("world", RUN)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ")


# --------------------------------------------------------------------------
# who can connect
# --------------------------------------------------------------------------
@pytest.fixture()
def world(creds):
    """The world's session, listening on tls/127.0.0.1:PORT."""
    port = free_port()
    with ZenohTransport(session(creds, "world", listen=[f"tls/127.0.0.1:{port}"])) as t:
        yield t, port, Sink(t, f"{KEYS.root}/agent/*/report")  # what the world may subscribe to


def test_the_runs_identities_join_and_exchange(creds, world):
    t, port, sink = world
    with ZenohTransport(session(creds, "agent-7", connect=[f"tls/127.0.0.1:{port}"])) as agent:
        back = Sink(agent, KEYS.tick)
        time.sleep(0.5)
        deadline = time.monotonic() + 5
        while not (sink.event.is_set() and back.event.is_set()) and time.monotonic() < deadline:
            agent.put(KEYS.report(7), b"from agent 7")
            t.put(KEYS.tick, b"from the world")
            time.sleep(0.1)
    assert (KEYS.report(7), b"from agent 7") in sink.got
    assert (KEYS.tick, b"from the world") in back.got


@pytest.mark.parametrize("who", ["another CA", "another CA, trusting the run's", "no certificate", "plain tcp"])
def test_a_session_without_the_runs_certificate_gets_nothing_in_or_out(creds, other_ca, world, tmp_path, who):
    t, port, sink = world
    tls = [f"tls/127.0.0.1:{port}"]
    opts = {
        "another CA": lambda: session(other_ca, "agent-7", connect=tls),
        "another CA, trusting the run's": lambda: session(
            other_ca, "agent-7", connect=tls,
            cfg=[f"transport/link/tls/root_ca_certificate:{json.dumps(str(creds / 'world' / 'ca.pem'))}"]),
        "no certificate": lambda: plain_config(tmp_path / "no-cert.json5", connect=tls,
                                               tls={"root_ca_certificate": str(creds / "world" / "ca.pem")}),
        "plain tcp": lambda: plain_config(tmp_path / "tcp.json5", connect=[f"tcp/127.0.0.1:{port}"]),
    }[who]()
    heard = []
    try:
        with ZenohTransport(opts) as intruder:
            heard = Sink(intruder).got
            time.sleep(SETTLE_S)
            publish_for(intruder, [(KEYS.report(7), b"intruder"), (KEYS.stop, b"intruder")])
            t.put(KEYS.tick, b"the world's tick")
            time.sleep(0.3)
    except MeshError:
        pass
    assert sink.got == [] and heard == []


def _listening() -> set:
    """The local addresses (``/proc/net/tcp`` hex) of this process's
    listening TCP sockets."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:["):-1])
    out = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                out.add(fields[1].rsplit(":", 1)[0])
    return out


LOOPBACK_HEX = {"0100007F", "00000000000000000000000001000000"}  # 127.0.0.1, ::1


@pytest.mark.skipif(not Path("/proc/self/net/tcp").exists(), reason="needs Linux's /proc/net/tcp")
@pytest.mark.parametrize("how", ["credentials", "insecure", "--listen (control)"])
def test_a_process_started_by_hand_listens_on_loopback_unless_told(creds, how):
    before = _listening()
    opts = {"credentials": session(creds, "agent-1"),
            "insecure": ZenohOptions(insecure=True, no_multicast_scouting=True),
            "--listen (control)": session(creds, "agent-1", listen=["tls/0.0.0.0:0"])}[how]
    with ZenohTransport(opts):
        time.sleep(0.3)
        opened = _listening() - before
    assert opened
    if how == "--listen (control)":
        assert opened == {"00000000"}
    else:
        assert opened <= LOOPBACK_HEX


# --------------------------------------------------------------------------
# who may say what (zenoh's access control)
# --------------------------------------------------------------------------
@contextlib.contextmanager
def four_sessions(creds, acl):
    """Sessions of the world (listening), agents 1 and 2 and the observer;
    ``acl`` "on", or off (the control)."""
    off = ["access_control/enabled:false"] if acl != "on" else []
    port = free_port()
    ep = dict(connect=[f"tls/127.0.0.1:{port}"], listen=["tls/127.0.0.1:0"], cfg=off)
    with ZenohTransport(session(creds, "world", listen=[f"tls/127.0.0.1:{port}"], cfg=off)) as w, \
            ZenohTransport(session(creds, "agent-1", **ep)) as a1, \
            ZenohTransport(session(creds, "agent-2", **ep)) as a2, \
            ZenohTransport(session(creds, "observer", **ep)) as obs:
        yield w, a1, a2, obs


@pytest.mark.parametrize("acl", ["on", "off (control)"])
def test_an_identity_speaks_for_itself_only(creds, acl):
    with four_sessions(creds, acl) as (w, a1, a2, obs):
        at_world = Sink(w, f"{KEYS.root}/agent/*/report")
        tokens = Sink(w, f"{KEYS.root}/*/agent/**")
        at_a1 = Sink(a1, KEYS.stop)
        own_meas, others_meas = Sink(a1, KEYS.meas(1)), Sink(a2, KEYS.meas(1))
        watching = Sink(obs)
        time.sleep(SETTLE_S)
        a2.declare_token(KEYS.ready(1, "n1"))    # agent 2 says agent 1 is ready
        a2.declare_token(KEYS.alive(2, "n2"))    # its own: allowed
        publish_for(a1, [(KEYS.report(1), b"agent 1")])
        publish_for(a2, [(KEYS.report(1), b"agent 2 as agent 1"), (KEYS.stop, b"agent 2 as the world")])
        publish_for(obs, [(KEYS.report(1), b"observer as agent 1"), (KEYS.stop, b"observer as the world")])
        publish_for(w, [(KEYS.meas(1), b"agent 1's measurement"), (KEYS.stop, b"the world's stop")])
        time.sleep(0.3)
    legit = {b"agent 1", b"agent 1's measurement", b"the world's stop"}
    if acl == "on":
        assert {p for _, p in at_world.got} == {b"agent 1"}
        assert tokens.keys() == {KEYS.alive(2, "n2")}
        assert {p for _, p in at_a1.got} == {b"the world's stop"}
        assert {p for _, p in own_meas.got} == {b"agent 1's measurement"} and others_meas.got == []
        assert {p for _, p in watching.got if isinstance(p, bytes)} == legit  # the observer hears all, says nothing
    else:  # the same forgeries without the access control: they get through
        assert b"agent 2 as agent 1" in {p for _, p in at_world.got}
        assert KEYS.ready(1, "n1") in tokens.keys()
        assert b"agent 2 as the world" in {p for _, p in at_a1.got}
        assert others_meas.got


def start_key(agent) -> str:
    """The key of an agent's query for its starting estimate (``Keys.start``)."""
    return f"{KEYS.root}/start/{agent}"


def _ask(t, key, seconds=2.0):
    """The first answer to a query on ``key`` (None: none in ``seconds``)."""
    got, done = [], threading.Event()
    t.query(key, b"", seconds, lambda payload: (got.append(payload), done.set()))
    done.wait(seconds + 1.0)
    return got[0] if got else None


@pytest.mark.parametrize("acl", ["on", "off (control)"])
def test_reports_and_starting_estimates_reach_only_whom_they_are_for(creds, acl):
    """An agent subscribed to every report hears none (the world and the
    observer do); an agent asks the world for its own starting estimate
    only, and only the world answers it (not the observer pretending to)."""
    with four_sessions(creds, acl) as (w, a1, a2, obs):
        at_world, at_observer = Sink(w, KEYS.report("*")), Sink(obs, KEYS.report("*"))
        eavesdropper = Sink(a2, KEYS.report("*"))
        w.declare_queryable(start_key("*"), lambda key, payload, reply: reply(b"the world's answer for " +
                                                                               key.encode()))
        obs.declare_queryable(start_key("*"), lambda key, payload, reply: reply(b"the observer as the world"))
        time.sleep(SETTLE_S)
        publish_for(a1, [(KEYS.report(1), b"agent 1's report")])
        own = _ask(a1, start_key(1))
        others = _ask(a2, start_key(1))
        time.sleep(0.3)
    assert {p for _, p in at_world.got} == {p for _, p in at_observer.got} == {b"agent 1's report"}
    if acl == "on":
        assert eavesdropper.got == []
        assert own == b"the world's answer for " + start_key(1).encode()
        assert others is None
    else:  # without the access control the same listening and asking succeed
        assert {p for _, p in eavesdropper.got} == {b"agent 1's report"}
        assert others is not None


def test_a_new_peer_is_not_sent_what_it_may_not_hear(creds):
    """Until a new peer's declarations arrive, zenoh sends it every put; the
    egress rules keep the world's measurement of agent 1 from agent 2 even
    then (agent 2, subscribed to every measurement, connecting again and
    again while the world publishes agent 1's)."""
    port = free_port()
    stop = threading.Event()
    with ZenohTransport(session(creds, "world", listen=[f"tls/127.0.0.1:{port}"])) as w:
        def pump():
            while not stop.is_set():
                w.put(KEYS.meas(1), b"agent 1's measurement")
                time.sleep(0.002)

        threading.Thread(target=pump, daemon=True).start()
        heard = []
        try:
            for _ in range(6):
                with ZenohTransport(session(creds, "agent-2", connect=[f"tls/127.0.0.1:{port}"],
                                            listen=["tls/127.0.0.1:0"])) as a2:
                    a2.subscribe(f"{KEYS.root}/world/meas/*", lambda k, p: heard.append(k))
                    time.sleep(0.4)
        finally:
            stop.set()
    assert heard == []


def test_multicast_scouting_finds_the_run_over_tls_only(creds, tmp_path):
    """A by-hand run with no endpoints: peers meet by multicast scouting and
    connect over TLS (credentials' default listen endpoint). A plain-TCP
    peer in the same scouting group is found, and nothing passes."""
    group = ["scouting/multicast/address:" + json.dumps(f"224.0.0.224:{free_port()}")]  # this test's group only
    plain = plain_config(tmp_path / "tcp.json5", listen=[f"tcp/127.0.0.1:{free_port()}"],
                         multicast=json.loads(group[0].split(":", 1)[1]))
    with ZenohTransport(session(creds, "world", cfg=group, multicast=True)) as w, \
            ZenohTransport(session(creds, "agent-1", cfg=group, multicast=True)) as a1, \
            ZenohTransport(plain) as intruder:
        at_world, heard = Sink(w, f"{KEYS.root}/agent/*/report"), Sink(intruder)
        deadline = time.monotonic() + 10
        while not at_world.event.is_set() and time.monotonic() < deadline:
            a1.put(KEYS.report(1), b"agent 1")
            intruder.put(KEYS.report(1), b"intruder")
            time.sleep(0.1)
        publish_for(intruder, [(KEYS.report(1), b"intruder")])
    if not at_world.got:  # pragma: no cover - depends on multicast on this host
        pytest.skip("multicast scouting does not work here")
    assert {p for _, p in at_world.got} == {b"agent 1"}
    assert heard.got == []

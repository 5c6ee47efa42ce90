"""Each process of ``up`` holds its own identity only, and no key outlives
the run (docs/security.md):

* ``up`` makes the run's identities in memory and hands each child its own
  alone, with the CA certificate, on its standard input; the router's
  identity exists only when a router runs;
* what each running child can read (its command line, environment, open
  files) holds no private key, its memory holds one key only, its own, and
  no key is on disk, before, during or after a run, however it ends
  (``kill -9`` of ``up`` included);
* a process holding a key is closed to its user's other processes: a
  sibling of the same user cannot open its files or read its memory.
"""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.zenoh_config import STDIN, ZenohOptions
from memory_probe import certificates, pems, public_key, usable_keys
from sim.launcher import Child, Launcher, hand_over, one_host_children, run_identities

RUN = "ident-test"
KEY_MARK = b"PRIVATE KEY"


def _key_matches_cert(ident: credentials.Identity) -> bool:
    key = serialization.load_pem_private_key(ident.key_pem, None)
    cert = x509.load_pem_x509_certificate(ident.cert_pem)
    der = serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    return key.public_key().public_bytes(*der) == cert.public_key().public_bytes(*der)


# --------------------------------------------------------------------------
# in memory
# --------------------------------------------------------------------------
def test_identities_in_memory_round_trip_and_pick_only_what_is_held():
    keys = credentials.issue(RUN, [3, 1], observer=False, router=False)
    assert sorted(keys) == ["agent-1", "agent-3", "world"]  # no router, no observer unless asked
    held = credentials.unbundle(credentials.bundle([keys["agent-3"]]))
    assert list(held) == ["agent-3"]
    mine = credentials.pick(held, "agent-3", RUN)
    assert (mine.run_id, mine.agents, mine.key_pem) == (RUN, (1, 3), keys["agent-3"].key_pem)
    assert _key_matches_cert(mine)
    with pytest.raises(InputError, match="agent-1"):
        credentials.pick(held, "agent-1", RUN)
    with pytest.raises(InputError, match="another"):
        credentials.pick(held, "agent-3", "another")
    with pytest.raises(InputError):
        credentials.unbundle(b"not a bundle")
    # a session of the identity names no file: zenoh gets the PEMs inline
    tls = dict(credentials.zenoh_settings(mine))["transport/link/tls"]
    assert "PRIVATE" not in tls and not any(k.endswith("_key") or k.endswith("certificate") for k in json.loads(tls))


def test_the_router_identity_exists_only_where_a_router_runs(tmp_path, monkeypatch):
    monkeypatch.setattr(credentials, "keep_private", lambda: None)  # (this test process stays as it is)
    spec = RunSpec(scenario="dynamic", run_id=RUN)
    ids = [a.id for a in spec.load().agents]
    opts = ZenohOptions(credentials=STDIN)
    for network, router in (("peers", False), ("router", True)):
        world, services, agents, _ = one_host_children(spec, 5, 0, ids, tmp_path, opts, network)
        keys = run_identities(RUN, ids, [world, *services, *agents], observer=False)
        assert (credentials.ROUTER in keys) is router
        assert credentials.OBSERVER not in keys
        held = [name for c in (world, *services, *agents) for name in c.identities]
        assert sorted(held) == sorted(keys)  # each identity handed to exactly one child
        acl = credentials.access_control(RUN, ids, observer=False, router=router)
        assert (credentials.ROUTER in {s["id"] for s in acl["subjects"]}) is router


REPORTER = textwrap.dedent("""
    import json, os, sys
    data = os.read(0, 1 << 20)
    print(json.dumps({"got": data.decode(errors="replace"), "fds": sorted(os.listdir("/proc/self/fd"))}))
""")


def test_the_launcher_hands_each_child_its_own_identity_alone(tmp_path):
    """Children that print what they were handed on standard input: each
    got its own identity, whole, and nothing else."""
    keys = credentials.issue(RUN, [1, 2], observer=False, router=False)
    names = ["world", "agent-1", "agent-2"]
    children = [Child(n, [sys.executable, "-c", REPORTER], tmp_path / f"{n}.log", identities=(n,)) for n in names]
    outs = {n: open(tmp_path / f"{n}.out", "wb") for n in names}
    launcher = Launcher(None, children, keys=keys)
    for c in children:
        launcher._spawn(c, outs[c.name])
    for c in children:
        assert c.proc.wait(30) == 0, c.last_error_line()
    for n in names:
        outs[n].close()
        got = json.loads((tmp_path / f"{n}.out").read_text())
        held = credentials.unbundle(got["got"].encode())
        assert list(held) == [n]
        assert held[n].key_pem == keys[n].key_pem and _key_matches_cert(held[n])
        assert got["got"].count("PRIVATE KEY-----") == 2  # one key: its BEGIN and END lines


def _memfd(data: bytes) -> int:
    fd = os.memfd_create("identity")
    os.write(fd, data)
    os.lseek(fd, 0, os.SEEK_SET)
    return fd


@pytest.mark.parametrize("how", ["hand_over", "memfd (control)"])
def test_what_a_child_is_handed_cannot_be_opened_by_another_process(tmp_path, how):
    """The child's end of the socket its identity comes through: no other
    process (not even root) can open it through ``/proc/PID/fd/0``. An
    in-memory file in its place can be (the control)."""
    secret = b"-----BEGIN PRIVATE KEY----- not yet read"
    fd = hand_over(secret) if how == "hand_over" else _memfd(secret)
    try:
        child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"], stdin=fd)
    finally:
        os.close(fd)
    try:
        time.sleep(0.2)
        if how != "hand_over":
            with open(f"/proc/{child.pid}/fd/0", "rb") as f:
                assert f.read() == secret
            return
        with pytest.raises(OSError) as e:
            open(f"/proc/{child.pid}/fd/0", "rb")
        assert e.value.errno == errno.ENXIO
    finally:
        child.kill()
        child.wait()


# --------------------------------------------------------------------------
# a whole run of up
# --------------------------------------------------------------------------
def _up(tmp_path, *args) -> subprocess.Popen:
    (tmp_path / "tmp").mkdir(exist_ok=True)
    env = {**os.environ, "TMPDIR": str(tmp_path / "tmp")}
    return subprocess.Popen([sys.executable, "-m", "sim.launcher", "--scenario", "quadrants", "--quiet",
                             "--logs", str(tmp_path / "logs"), "--json", str(tmp_path / "r.json"), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _descendants(pid: int) -> dict:
    """{pid: argv} of every descendant of ``pid`` (the zygote's children
    included), the zygote itself left out."""
    parents, argv = {}, {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            parents[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            argv[int(d.name)] = [a.decode() for a in (d / "cmdline").read_bytes().split(b"\0") if a]
        except (OSError, ValueError, IndexError):
            continue
    mine, grew = set(), True
    while grew:
        more = {p for p, parent in parents.items() if parent == pid or parent in mine} - mine
        grew, mine = bool(more), mine | more
    return {p: argv[p] for p in sorted(mine) if argv.get(p) and "sim.zygote" not in argv[p]}


def _parent(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _readable(pid: int) -> list:
    """(where, bytes) of what process ``pid`` has at hand: its command line,
    its environment and every open file that is not a socket or a pipe."""
    out = [(what, Path(f"/proc/{pid}/{what}").read_bytes()) for what in ("cmdline", "environ")]
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
            if target.startswith(("socket:", "pipe:", "anon_inode:")) or target.startswith("/dev/"):
                continue
            with open(fd, "rb") as f:
                out.append((target, f.read(1 << 20)))
        except (OSError, IsADirectoryError):
            continue
    return out


def _key_files(*roots) -> list:
    """Files under ``roots`` that hold a private key."""
    found = []
    for root in roots:
        for p in Path(root).rglob("*"):
            try:
                if p.is_file() and not p.is_symlink() and KEY_MARK in p.read_bytes():
                    found.append(p)
            except OSError:
                continue
    return found


def _wait_children(proc, n: int, timeout: float = 90.0) -> dict:
    deadline = time.monotonic() + timeout
    kids = {}
    while proc.poll() is None and time.monotonic() < deadline:
        kids = _descendants(proc.pid)
        if len(kids) >= n and (Path(proc.args[proc.args.index("--logs") + 1]) / "world.log").exists():
            time.sleep(1.0)  # every child has read its identity and started its session
            return _descendants(proc.pid)
        time.sleep(0.05)
    return kids


def _identity_name(argv) -> str:
    module = argv[argv.index("-m") + 1]
    if module == "agents.agent":
        return credentials.agent_identity(int(argv[argv.index("--id") + 1]))
    return {"sim.world": credentials.WORLD, "sim.router": credentials.ROUTER}[module]


@pytest.mark.mesh
@pytest.mark.skipif(os.geteuid() != 0, reason="reads the memory and files of up's processes, closed to their user "
                                                "(keep_private): needs root")
@pytest.mark.parametrize("network", ["peers", "router"])
def test_no_child_of_up_can_read_another_identity_and_no_key_is_on_disk(tmp_path, network):
    proc = _up(tmp_path, "--ticks", "3000", "--network", network)  # running when stopped, short enough to check
    try:
        n = 5 if network == "peers" else 6  # the world, four agents (and the router)
        kids = _wait_children(proc, n)
        assert len(kids) == n, kids
        assert any("sim.router" in argv for argv in kids.values()) is (network == "router")
        assert not [pid for pid in kids if _parent(pid) in kids], kids  # no child forks one of its own
        for pid, argv in kids.items():
            assert argv[argv.index("--credentials") + 1] == "-"  # handed over in memory, not a path
            for where, data in _readable(pid):
                assert KEY_MARK not in data, (argv[:3], where)
            assert os.readlink(f"/proc/{pid}/fd/0") == "/dev/null"  # the identity was read, and let go
            # all a compromised child finds in its memory: one key, its own, and no other identity's certificate
            found = pems(pid)
            certs = certificates(found)
            name = _identity_name(argv)
            assert usable_keys(found) == [public_key(certs[name])], name
            assert all(cn == name or c.subject == certs[name].issuer for cn, c in certs.items()), sorted(certs)
        assert _key_files(tmp_path, "/dev/shm") == []
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=10)
    assert proc.returncode == 130, err
    assert _key_files(tmp_path, "/dev/shm") == []


@pytest.mark.mesh
def test_kill_9_of_up_leaves_no_key_and_no_process(tmp_path):
    proc = _up(tmp_path, "--ticks", "3000")  # running when stopped, short enough for the end-of-run check
    try:
        kids = _wait_children(proc, 5)  # the world, four agents
        assert len(kids) == 5, kids
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=10)
        deadline = time.monotonic() + 30.0  # the children get SIGTERM when up (or the zygote) dies
        while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in kids):
            time.sleep(0.1)
        left = [p for p in kids if Path(f"/proc/{p}").exists()
                and Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"]
        assert left == []
    finally:
        if proc.poll() is None:
            proc.kill()
    assert _key_files(tmp_path, "/dev/shm") == []
    assert list(tmp_path.rglob("*.tmp")) == []  # no temporary file of an output either


# --------------------------------------------------------------------------
# closed to the user's other processes
# --------------------------------------------------------------------------
HOLDER = textwrap.dedent("""
    import os, sys, time
    from diskf_mesh.mesh.security import credentials
    fd = os.memfd_create("secret")
    os.write(fd, b"-----BEGIN PRIVATE KEY----- mine")
    secret = bytearray(b"-----BEGIN PRIVATE KEY----- in memory")
    if sys.argv[1] == "private":
        credentials.keep_private()
    print(fd, id(secret), flush=True)
    time.sleep(60)
""")
SIBLING = textwrap.dedent("""
    import sys
    pid, fd = sys.argv[1], sys.argv[2]
    try:
        print(open(f"/proc/{pid}/fd/{fd}", "rb").read().decode())
    except OSError as e:
        print("refused", e.errno)
""")
NOBODY = 65534


def _runs_as_nobody(python: str, as_nobody: dict) -> bool:
    try:
        return subprocess.run([python, "-c", "import diskf_mesh.mesh.security.credentials"], capture_output=True, timeout=60,
                              **as_nobody).returncode == 0
    except OSError:
        return False


@pytest.mark.skipif(os.geteuid() != 0, reason="runs two processes as another user (needs root)")
@pytest.mark.parametrize("mode", ["private", "control"])
def test_a_process_holding_a_key_is_closed_to_its_users_other_processes(mode):
    """Both processes run as one unprivileged user: the sibling reads the
    holder's in-memory file unless the holder called ``keep_private``."""
    as_nobody = dict(user=NOBODY, group=NOBODY, extra_groups=[], cwd="/",
                     env={"PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    python = next((p for p in (sys.executable, "/usr/bin/python3") if _runs_as_nobody(p, as_nobody)), None)
    if python is None:
        pytest.skip("no Python interpreter the unprivileged user may run")
    holder = subprocess.Popen([python, "-c", HOLDER, mode], stdout=subprocess.PIPE, text=True, **as_nobody)
    try:
        fd, _ = holder.stdout.readline().split()
        out = subprocess.run([python, "-c", SIBLING, str(holder.pid), fd], capture_output=True, text=True,
                             timeout=30, **as_nobody).stdout
    finally:
        holder.kill()
        holder.wait()
    if mode == "private":
        assert out.startswith("refused") and "PRIVATE KEY" not in out
    else:
        assert "PRIVATE KEY----- mine" in out

"""``diskf-mesh up``: a whole mesh run on this host, one process per agent.

It starts the world and every agent of the scenario as separate processes
(``python -m sim.world``, ``python -m agents.agent``), shows the ticks as a
progress bar, prints the metrics table and writes the results. If any child
fails, or on Ctrl-C, it stops every child it started and says which one
failed and why (exit code, last line of its stderr; full logs in --logs);
the world, stopped, still writes what it measured. With ``--allow-missing``
an agent that fails does not end the run: the world accounts its missing
ticks. Nor does an agent that fails before the first tick: the world gives
up on it after ``--startup-timeout`` (``incomplete``, exit 3, its reason
first), or with ``--allow-missing`` starts without it. An agent whose estimator diverges is not a failure of a process: it
tells the world and leaves (exit 3, ``exits.STOPPED``), the others run to
the end, ``up`` prints its line and the run ends ``incomplete``, its missing
ticks counted as "diverged".

Exit status: the world's, from the run's status (``diskf_mesh.engine.verify``:
the world replays the run on the engine before it says ``exact``;
``diskf_mesh.core.exits``): 0 exact or as planned; 3 with one line when
agent-ticks are missing (0 within ``--allow-missing``: a warning line says
what is missing); 4 a real-time run beyond ``--max-miss-rate``; 5 degraded
(``--allow-degraded`` accepts it); 6 diverged (never accepted); 8
unverifiable (only ``--accept-unverifiable`` accepts it); 1 when a child
failed once the run ticked; 2 on bad input.

Every run is authenticated: ``up`` makes a fresh certificate authority and
one certificate and key per process (``diskf_mesh.mesh.security.credentials``) in
memory, never on disk, and hands each child its own identity alone, with
the run's CA certificate, on its standard input (``--credentials -``: a
socket the child reads to its end and closes at once). The router's identity
is made only when a router runs (``--live``: the world serves the run). The
launcher and every child that holds a key are closed to the user's other
processes (``credentials.keep_private``), so a compromised child finds no
identity but its own, and a killed run leaves no key behind. ``--insecure``
runs plain zenoh instead.

Without zenoh flags the processes meet on loopback only: the world listens on
a free port of 127.0.0.1 (``tls/``, or ``tcp/`` with ``--insecure``) and
every agent connects to it (no multicast scouting). Up to ``PEERS_UP_TO``
agents they are peers, each linked to each other it talks to; above that
(or ``--network router``) one zenoh router on another free port carries
their traffic and every agent is its client (one link each: the shape of
one host of ``--hosts``, docs/hosts.md). Either way the estimates are the
engine's, bit for bit. With zenoh flags (``--mode``, ``--connect``,
``--listen``, ``--no-multicast-scouting``, ``--zenoh-config``, ``--cfg``)
every child gets exactly those.

``--hosts FILE`` runs over several hosts instead (``sim.hosts``,
docs/hosts.md): the world as a zenoh router, then per host a router
(``sim.router``) and a shard of agents (``sim.host``, which starts its
agents with this module's ``Launcher``), each behind the host's prefix.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import os
import queue
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path

from diskf_mesh import live
from diskf_mesh.data.argtypes import add_ticks, seed_value
from diskf_mesh.data.outputs import check_output, check_output_dir, make_folder
from diskf_mesh.core.errors import InputError
from diskf_mesh.data.faults import FaultConfig
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.data.faults import from_args as faults_from_args
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process import zenoh_config
from diskf_mesh.mesh.process.runspec import RunSpec
from diskf_mesh.mesh.process.stopping import terminated
from diskf_mesh.mesh.process.zenoh_config import ZenohOptions
from diskf_mesh.recording.writer import failure_line
from sim import simulated
from sim.child import Child
from sim import zygote as forks
from diskf_mesh.core import exits
from diskf_mesh.engine.verify import RunStatus
from sim.world import (add_allow_missing, add_timing_arguments, agent_world_timeout, exit_status, miss_line,
                       timing_argv)

STOP_GRACE_S = 3.0  # SIGTERM, then SIGKILL after this
WORLD_STOP_GRACE_S = 20.0  # the world, stopped, writes its results first


# an agent forked at once may try the world's port before the world listens: it tries again
# 50 ms later (zenoh's default: 1 s), then ever less often
CONNECT_RETRY = "connect/retry:{period_init_ms: 50, period_max_ms: 1000, period_increase_factor: 2}"
# up on one host: a peer mesh (one link per pair of processes) up to this many agents, above it every
# agent a client of one router (one link each): measured on 2 cores (benchmarks/scale_bench.py --single),
# 25 agents start in 1.1 s instead of 2.0 and tick 6 % faster, 50 agents in 2.8 s instead of 9.5
PEERS_UP_TO = 16
NETWORKS = ("auto", "peers", "router", "simulated")
# of two agents that learn of each other (the world gossips their endpoints), only the one with the
# greater zenoh id connects: one TLS handshake per pair instead of up to two (zenoh's default,
# "always", then closes the redundant link); on loopback every agent reaches every other
GOSSIP_ONE_WAY = 'scouting/gossip/autoconnect_strategy:{peer: {to_router: "always", to_peer: "greater-zid"}}'
# ... from zenoh 1.9 on. Before it a pair sometimes never connects: three runs of 9 agents at once, 30 each,
# left a pair unconnected (the run fails its start-up) in 5 of 60 starts on 1.5.1, 2 of 30 on 1.6.2, 1 of 30
# on 1.7.0, none of 60 on 1.9.0 and of 90 on 1.10.2; with zenoh's default ("always": both connect) none of
# 30 on 1.5.1. The default costs 0.05-0.2 s more to tick 1 at 9 agents.
GOSSIP_ONE_WAY_FROM = (1, 9)
PORTS_BELOW_EPHEMERAL = 12000  # how many ports below the ephemeral range to pick the world's from


def process_age() -> float:
    """Seconds since this process started (Linux: /proc/self/stat's start
    time, to 10 ms; elsewhere 0)."""
    try:
        start = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19]) / os.sysconf("SC_CLK_TCK")
        return max(time.clock_gettime(time.CLOCK_BOOTTIME) - start, 0.0)
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


def first_ephemeral_port() -> int:
    """The lowest port the OS hands out for binds to port 0."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def free_port(host: str = "127.0.0.1") -> int:
    """A port free now, for the world to listen on, picked at random below the
    ephemeral range: every other mesh process listens on port 0, and the OS
    could hand this port to one of them between our check and the world's
    bind if it were an ephemeral port (seen once in CI: "Address already in
    use"). Falls back to an OS-assigned port."""
    low = first_ephemeral_port()
    start = max(1024, low - PORTS_BELOW_EPHEMERAL)
    candidates = [start + secrets.randbelow(low - start) for _ in range(64)] if low > start else []
    for port in candidates + [0]:
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise OSError(f"no free port on {host}")


def free_ports(n: int, host: str = "127.0.0.1") -> list:
    """``n`` different ports free now (``free_port``)."""
    ports = []
    while len(ports) < n:
        p = free_port(host)
        if p not in ports:
            ports.append(p)
    return ports


def loopback_options(port: int, base: ZenohOptions = ZenohOptions()) -> tuple:
    """(world, agent) zenoh options for a run confined to 127.0.0.1, a peer
    mesh: over TLS if ``base`` has credentials, plain TCP otherwise."""
    proto = "tls" if base.credentials else "tcp"
    world = replace(base, listen=(f"{proto}/127.0.0.1:{port}",), no_multicast_scouting=True)
    one_way = (GOSSIP_ONE_WAY,) if zenoh_version() >= GOSSIP_ONE_WAY_FROM else ()
    agent = replace(base, connect=(f"{proto}/127.0.0.1:{port}",), listen=(f"{proto}/127.0.0.1:0",),
                    no_multicast_scouting=True, cfg=(*base.cfg, CONNECT_RETRY, *one_way))
    return world, agent


def zenoh_version() -> tuple:
    """(major, minor) of the installed eclipse-zenoh."""
    from importlib.metadata import version

    return tuple(int(p) for p in version("eclipse-zenoh").split(".")[:2])


def routed_loopback_options(world_port: int, router_port: int, base: ZenohOptions = ZenohOptions(),
                            wait_s: float = 30.0) -> tuple:
    """(world, router, agent) zenoh options for a run confined to 127.0.0.1
    through one router (``up --network router``): the shape of one host of
    ``up --hosts`` (docs/hosts.md), the world a zenoh router listening on
    ``world_port``, the router listening on ``router_port`` and connected to
    the world, every agent a client of the router. An agent forked before
    the router listens waits for it (at most ``wait_s``)."""
    proto = "tls" if base.credentials else "tcp"
    world_at, router_at = f"{proto}/127.0.0.1:{world_port}", f"{proto}/127.0.0.1:{router_port}"
    world = replace(base, mode="router", listen=(world_at,), no_multicast_scouting=True)
    router = replace(base, listen=(router_at,), connect=(world_at,), no_multicast_scouting=True,
                     cfg=(*base.cfg, CONNECT_RETRY))
    agent = replace(base, mode="client", connect=(router_at,), no_multicast_scouting=True,
                    cfg=(*base.cfg, CONNECT_RETRY, f"connect/timeout_ms:{int(1000 * wait_s)}"))
    return world, router, agent


def network_of(choice: str, agents: int) -> str:
    """``up --network``: "peers" or "router" ("auto": a peer mesh up to
    ``PEERS_UP_TO`` agents, a router above)."""
    return choice if choice != "auto" else ("peers" if agents <= PEERS_UP_TO else "router")


def hand_over(data: bytes) -> int:
    """A file descriptor, for a child's standard input, from which it reads
    ``data`` and then the end: one end of a socket pair whose other end a
    thread of this process writes and closes. Unlike a file or a pipe, a
    socket cannot be opened through ``/proc/PID/fd`` by another process, and
    what it holds is in no file system."""
    ours, theirs = socket.socketpair()

    def feed():
        with ours:
            try:
                ours.sendall(data)
            except OSError:  # the child is gone before reading
                pass

    threading.Thread(target=feed, name="identity", daemon=True).start()
    return theirs.detach()


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the launcher dies (Linux), so that a
    killed launcher never leaves processes behind."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


class Launcher:
    """Starts, watches and stops the children of one run: the world (None in
    a shard of agents without it: ``diskf-mesh host``), ``services`` that run
    until stopped (a run's zenoh routers) and the agents (or hosts' shards),
    which leave on the world's stop."""

    def __init__(self, world: Child | None, agents: list, progress=None, first_tick=None,
                 tolerate_agents: bool = False, services=(), zygote: "forks.Zygote | None" = None,
                 keys: dict | None = None):
        """``tolerate_agents``: an agent (or a service) that fails does not
        end the run (the world counts its missing ticks); nor does an agent
        that fails before the world's first tick (the world gives up on it
        after its ``--startup-timeout``, or starts without it: its status
        says so); ``failed_agents`` lists them. The children that are this
        interpreter's ``python -m`` of a mesh command are forked by a
        zygote (``sim.zygote``; ``zygote``,
        one started already, or one started at the first such child).
        ``keys``: the run's identities by name (``credentials.issue``); a
        child gets those its ``identities`` name on its standard input."""
        self.zygote = zygote
        self.keys = keys or {}
        self.world = world
        self.tolerate_agents = tolerate_agents
        self.failed_agents = []
        self.agents = agents
        self.services = list(services)
        self.children = [*([world] if world is not None else []), *self.services, *agents]
        self.progress = progress
        self.first_tick = first_tick
        self.ticked = False  # the world said it took tick 1
        self._lines = queue.SimpleQueue()

    def _spawn(self, child: Child, stdout) -> None:
        self._spawn_all([child], stdout)

    def _stdin(self, child: Child):
        """A file descriptor of ``child``'s identities (``hand_over``), or None."""
        if not child.identities or not self.keys:
            return None
        return hand_over(credentials.bundle([self.keys[name] for name in child.identities]))

    def _spawn_all(self, children, stdout) -> None:
        """Start ``children``: the ones a zygote can fork (``sim.zygote``) at
        once, the others with ``subprocess``."""
        logs = [open(c.log, "wb") for c in children]
        try:
            forked = [c for c in children if forks.forkable(c.argv)] if forks.enabled() else []
            if forked and self.zygote is None:
                self.zygote = forks.Zygote()
            if forked:
                ins = [self._stdin(c) for c in forked]
                try:
                    procs = self.zygote.spawn_all([(c.argv, stdout, logs[children.index(c)], fd)
                                                   for c, fd in zip(forked, ins)])
                finally:
                    for fd in ins:
                        if fd is not None:
                            os.close(fd)
                for c, proc in zip(forked, procs):
                    c.proc = proc
            for c, err in zip(children, logs):
                if c.proc is None:
                    fd = self._stdin(c)
                    try:
                        c.proc = subprocess.Popen(c.argv, stdin=subprocess.DEVNULL if fd is None else fd,
                                                  stdout=stdout, stderr=err, start_new_session=True,
                                                  preexec_fn=_die_with_parent)
                    finally:
                        if fd is not None:
                            os.close(fd)
        finally:
            for f in logs:
                f.close()

    def add_child(self, name: str, argv: list, log: Path, identities=()) -> Child:
        """Start one more child (e.g. the live view), stopped with the others;
        ``identities``: those it is handed (``keys``)."""
        child = Child(name, argv, log, identities=tuple(identities))
        self.start_more([child])
        return child

    def start_more(self, children) -> None:
        """Start more children as the others are (forked where they can be),
        stopped with the others."""
        self._spawn_all(list(children), subprocess.DEVNULL)
        self.children.extend(children)

    def start(self) -> None:
        if self.world is not None:
            self.start_world()
        self.start_services()
        self.start_agents()

    def start_world(self) -> None:
        self._spawn(self.world, subprocess.PIPE)
        threading.Thread(target=self._read_world, daemon=True).start()

    def start_services(self) -> None:
        self._spawn_all(self.services, subprocess.DEVNULL)

    def start_agents(self) -> None:
        self._spawn_all(self.agents, subprocess.DEVNULL)

    def _read_world(self) -> None:
        for line in self.world.proc.stdout:
            self._lines.put(line.decode(errors="replace"))

    def _drain(self) -> None:
        while True:
            try:
                line = self._lines.get_nowait()
            except queue.Empty:
                return
            parts = line.split()
            if len(parts) == 3 and parts[0] == "tick":
                k = int(parts[1])
                if not self.ticked and self.first_tick is not None:
                    self.first_tick()
                self.ticked = True
                if self.progress is not None:
                    self.progress(k, int(parts[2]))

    def wait(self, timeout: float) -> int:
        """Until the world ends; returns its exit status, one of ``WORLD_VERDICTS``
        (a run with missing agent-ticks: the world wrote its results and its
        verdict). Raises ``ChildFailed`` on the first failure (any other
        status of the world; an agent's once the world ticks, unless
        ``tolerate_agents``)."""
        deadline = time.monotonic() + timeout
        while True:
            self._drain()
            rc = self.world.proc.poll()
            if rc is not None:
                self._drain()
                if rc not in WORLD_VERDICTS:
                    raise ChildFailed(self.world, rc)
                return rc
            for a in (*self.services, *self.agents):
                rc = a.proc.poll()
                # an agent exits 0 only on the world's "done" (or ``exits.STOPPED``: it told the world it left);
                # a service never ends by itself
                if (rc or (rc is not None and a in self.services)) and not self._stopped(a) \
                        and a not in self.failed_agents:
                    if not self.tolerate_agents and (self.ticked or a in self.services):
                        raise ChildFailed(a, rc)
                    self.failed_agents.append(a)
            if time.monotonic() > deadline:
                raise ChildFailed(self.world, None, f"still running after {timeout:g} s")
            time.sleep(0.02)

    def _stopped(self, child: Child) -> bool:
        """An agent that ended with ``exits.STOPPED``: its estimator diverged and it
        told the world, which counts its missing ticks as "diverged" and
        whose status (``incomplete``) speaks for the run; not a failure of
        a process."""
        return child in self.agents and child.proc.poll() == exits.STOPPED

    def stopped(self) -> list:
        """The agents that ended with ``exits.STOPPED``."""
        return [a for a in self.agents if self._stopped(a)]

    def _ended_badly(self, child: Child) -> bool:
        return child.proc.poll() not in (None, 0) and not self._stopped(child)

    def wait_agents(self) -> list:
        """Without a world (a shard): until every agent has ended; the ones
        that failed (not 0, not ``exits.STOPPED``), in the order they ended."""
        bad = []
        while any(a.proc.poll() is None for a in self.agents):
            for a in self.agents:
                if self._ended_badly(a) and a not in bad:
                    bad.append(a)
            time.sleep(0.2)
        return bad + [a for a in self.agents if self._ended_badly(a) and a not in bad]

    def finish(self, timeout: float = 5.0) -> list:
        """After the world: agents leave on its stop. Returns the agents that
        did not exit 0 in time (they are stopped), those that failed during
        a tolerated run first."""
        deadline = time.monotonic() + timeout
        bad = [a for a in self.failed_agents if a in self.agents]
        for a in self.agents:
            if a in bad:
                continue
            try:
                a.proc.wait(max(deadline - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                pass
            if a.proc.poll() is None or self._ended_badly(a):
                bad.append(a)
        self.stop_all()
        return bad

    def stop_all(self) -> None:
        """SIGTERM every running child, SIGKILL what is left after a grace
        (the world's is longer: it writes what it measured)."""
        live = [c for c in self.children if c.proc is not None and c.proc.poll() is None]
        for c in live:
            _signal(c.proc, signal.SIGTERM)
        t0 = time.monotonic()
        for c in live:
            deadline = t0 + (WORLD_STOP_GRACE_S if c is self.world else STOP_GRACE_S)
            try:
                c.proc.wait(max(deadline - time.monotonic(), 0.01))
            except subprocess.TimeoutExpired:
                _signal(c.proc, signal.SIGKILL)
                c.proc.wait(STOP_GRACE_S)
        if self.world is not None and self.world.proc is not None and self.world.proc.stdout:
            self.world.proc.stdout.close()
        if self.zygote is not None:  # every child has ended: it can go (a later child gets a new one)
            self.zygote.close()
            self.zygote = None


def _signal(proc: subprocess.Popen, sig) -> None:
    try:
        proc.send_signal(sig)
    except ProcessLookupError:
        pass


class ChildFailed(RuntimeError):
    def __init__(self, child: Child, rc, why: str = ""):
        self.child, self.rc = child, rc
        how = why or (f"exit code {rc}" if rc is not None and rc >= 0 else f"killed by signal {-rc}")
        last = child.last_error_line()
        super().__init__(f"{child.name} failed ({how})" + (f": {last}" if last else "") + f" [log: {child.log}]")


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def build_children(spec: RunSpec, ticks: int, seed: int, ids, logs: Path, world_zenoh: ZenohOptions,
                   agent_zenoh: ZenohOptions, world_extra=(), agent_extra=()) -> tuple:
    world = Child("world", runspec.world_command(spec, ticks, seed, world_zenoh, world_extra), logs / "world.log",
                  identities=(credentials.WORLD,))
    agents = [Child(f"agent {i}", runspec.agent_command(spec, i, agent_zenoh, agent_extra), logs / f"agent-{i}.log",
                    identities=(credentials.agent_identity(i),)) for i in ids]
    return world, agents


def one_host_children(spec: RunSpec, ticks: int, seed: int, ids, logs: Path, zopts: ZenohOptions,
                      network: str = "auto", wait_s: float = 30.0, world_extra=(), agent_extra=()) -> tuple:
    """(world, services, agents, agents' zenoh options) of ``up`` on this
    host: with the user's zenoh flags every process gets them as given;
    without, on loopback, a peer mesh or (``network_of``) a router among
    the services and every agent its client."""
    services = []
    if not zopts.is_default:
        world_z = agent_z = zopts
    elif network_of(network, len(ids)) == "router":
        world_z, router_z, agent_z = routed_loopback_options(*free_ports(2), zopts, wait_s)
        services = [Child("router", runspec.router_command(spec.run_id, router_z), logs / "router.log",
                          identities=(credentials.ROUTER,))]
    else:
        world_z, agent_z = loopback_options(free_port(), zopts)
    world, agents = build_children(spec, ticks, seed, ids, logs, world_z, agent_z, world_extra, agent_extra)
    return world, services, agents, agent_z


def agent_flags(args: argparse.Namespace, scn, collect_timeout=None, world_timeout=None) -> list:
    """The flags every agent of a run gets from ``up`` or ``host`` (timeouts,
    ``--profile``, fault flags that differ from the scenario's ``[faults]``);
    ``host`` takes the same flags and passes them on."""
    out = []
    if collect_timeout is not None:
        out += ["--collect-timeout", str(collect_timeout)]
    if world_timeout is not None:
        out += ["--world-timeout", str(world_timeout)]
    if args.profile:
        out += ["--profile", args.profile]
    faults = faults_from_args(args, scn.faults)
    if faults != FaultConfig.from_mapping(scn.faults):  # flags given: every child gets them
        out += faults.to_argv()
    return out


def register(subparsers) -> None:
    p = subparsers.add_parser("up", help="run the world and every agent as separate processes over Zenoh",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    runspec.add_arguments(p, run_id_default=None)
    add_ticks(p, help="ticks to run (default: the scenario's)")
    p.add_argument("--seed", type=seed_value, default=0, metavar="S", help="simulation seed (default 0)")
    p.add_argument("--json", metavar="OUT", help="results file (default: results/up-<run-id>.json)")
    p.add_argument("--estimates", metavar="OUT", help="also write every agent's fused estimates")
    p.add_argument("--record", metavar="FILE.mcap", help="the world records the run as MCAP (diskf_mesh.recording)")
    p.add_argument("--logs", metavar="DIR", help="keep the children's stderr logs in DIR (default: a temporary folder, "
                                                 "removed when the run ends with 0, kept and named otherwise)")
    add_timing_arguments(p)
    add_allow_missing(p)
    realtime.add_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress (bar or lines)")
    p.add_argument("--profile", metavar="DIR",
                   help="world and agents measure where each tick's time goes: DIR/world.json, "
                        "DIR/agent-<id>.json (benchmarks/mesh_bench.py --profile prints them)")
    p.add_argument("--network", choices=NETWORKS, default="auto",
                   help=f"on one host: a peer mesh, or every agent a client of one zenoh router (default auto: "
                        f"peers up to {PEERS_UP_TO} agents, a router above; docs/hosts.md); simulated: every "
                        f"process in this one, on a simulated network (sim.simulated, docs/simnet.md)")
    p.add_argument("--hosts", metavar="FILE",
                   help="run over several hosts: the world, a router and a shard of agents per host, from a TOML "
                        "file naming them (sim.hosts, docs/hosts.md); no zenoh flags then")
    simulated.add_arguments(p)
    live.add_arguments(p)
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.credentials:
        raise InputError("credentials", "up makes fresh credentials for every run (--credentials is for world "
                                        "and agent started by hand; with --hosts, the file's credentials key)")
    # SIGTERM ends the run like Ctrl-C's path does: through the finally blocks (the children get
    # SIGTERM when up dies)
    previous = signal.signal(signal.SIGTERM, terminated)
    # the zygote (``sim.zygote``): started first thing by the command line (``prestart``), or here once the
    # input is checked; its imports go on while up makes the credentials
    zygote = [z for z in [forks.take_prestarted()] if z is not None]
    try:
        return _run(args, zygote)
    finally:
        for z in zygote:
            z.close()
        signal.signal(signal.SIGTERM, previous)


def run_identities(run_id: str, ids, children, observer: bool, world_routes: bool = False) -> dict:
    """The identities of one ``up`` run, in memory (``credentials.issue``):
    the world and every agent, the router only if one of ``children`` is
    handed it (a router runs), the observer only if ``observer`` (a
    listener on the mesh; ``--live`` needs none: the world feeds it). This process then holds every key: it is closed to the
    user's other processes (``credentials.keep_private``)."""
    routers = any(credentials.ROUTER in c.identities for c in children)
    credentials.keep_private()
    return credentials.issue(run_id, ids, observer=observer, router=routers, world_routes=world_routes)


def _run(args: argparse.Namespace, zygotes: list) -> int:
    from diskf_mesh.studies.experiment import format_table

    began = time.monotonic() - process_age()  # when `diskf-mesh up` started (its interpreter's start)
    spec = runspec.from_args(args, run_id=args.run_id or secrets.token_hex(4))
    if args.network == "simulated":
        simulated.check_arguments(args)  # before anything is written
    scn = spec.load(args.ticks)  # a bad scenario or fault value fails before anything is written
    out = Path(args.json or f"results/up-{spec.run_id}.json")
    check_output(out, "json", stdout=False, make_parent=args.json is None)  # before any work
    check_output(args.estimates, "estimates", stdout=False)
    check_output(args.record, "record", stdout=False)
    if args.live is not None:
        live.check_port(args.live)
    if args.logs:
        check_output_dir(args.logs, "logs", create=False)  # created once the input is checked
    ticks = scn.steps
    ids = [a.id for a in scn.agents]
    plan = None
    if args.hosts:
        from sim import hosts

        plan = hosts.load(args.hosts)
        plan.check(ids)
    zopts = zenoh_config.from_args(args)
    if plan is not None and not zopts.is_default:
        raise InputError("hosts", "the hosts file names every endpoint: no zenoh flags with --hosts")
    if args.network != "auto" and (plan is not None or not zopts.is_default):
        raise InputError("network", "chooses the shape of a run on one host: not with --hosts or zenoh flags")
    if args.network == "simulated":  # every process in this one (sim.simulated)
        make_folder(out, "json")
        code, row = simulated.run(args, spec, scn, out)
        if row is not None:
            verdict(row, args)
        return code
    if simulated.given(args):
        raise InputError("network", "the --net-* options need --network simulated")
    realtime.from_args(args)
    if plan is None and forks.enabled() and not zygotes:
        zygotes.append(forks.Zygote())
    world_routes = plan is not None and bool(plan.routerless)  # a host without a router: the world forwards for it
    keys = None
    if plan is not None and plan.credentials and not zopts.insecure:
        ident = credentials.load(plan.credentials, credentials.WORLD, spec.run_id)  # made for this run, or one line
        if world_routes and not ident.world_routes:
            raise InputError("hosts", f"host {plan.routerless[0]} has no router, so the world forwards its agents' "
                                      f"traffic, which {plan.credentials} does not allow (make them with "
                                      f"`diskf-mesh credentials --world-routes`)")
        zopts = replace(zopts, credentials=plan.credentials)
    elif not zopts.insecure:  # a fresh CA, one certificate per process, in memory (below): each child gets its own
        zopts = replace(zopts, credentials=zenoh_config.STDIN)
    else:
        print(f"warning: up: --insecure: plain zenoh; any process that reaches it can read and write run "
              f"{spec.run_id}", file=sys.stderr)
    # the input is checked: from here on the run writes
    make_folder(out, "json")
    logs = Path(args.logs or tempfile.mkdtemp(prefix=f"diskf-up-{spec.run_id}-"))
    try:
        logs.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError("logs", f"cannot create {logs}: {e.strerror or e}") from None
    world_extra = ["--progress", "lines", "--json", str(out), *timing_argv(args)]
    if args.estimates:
        world_extra += ["--estimates", args.estimates]
    if args.record:
        world_extra += ["--record", args.record]
    if args.live is not None:
        world_extra += ["--live", str(args.live)]
    if args.profile:
        world_extra += ["--profile", args.profile]
    if args.allow_missing:
        world_extra += ["--allow-missing", repr(args.allow_missing)]
    if args.allow_degraded:
        world_extra += ["--allow-degraded"]
    if args.accept_unverifiable:
        world_extra += ["--accept-unverifiable"]
    agent_extra = agent_flags(args, scn, args.collect_timeout, agent_world_timeout(args))
    world_extra, agent_extra = [a + b for a, b in zip((world_extra, agent_extra), realtime.argv(args))]
    faults = faults_from_args(args, scn.faults)
    if faults != FaultConfig.from_mapping(scn.faults):  # flags given: the world records them
        world_extra += faults.to_argv()
    if plan is not None:
        world, services, agents = hosts.children(plan, spec, ticks, args.seed, zopts, logs, world_extra,
                                                 agent_extra)
        for h in agents:  # each shard's agents' logs next to the run's
            h.argv += ["--logs", str(logs / h.name.replace(" ", "-"))]
    else:
        world, services, agents, _ = one_host_children(spec, ticks, args.seed, ids, logs, zopts,
                                                             args.network, args.startup_timeout, world_extra,
                                                             agent_extra)

    if zopts.credentials == zenoh_config.STDIN:
        keys = run_identities(spec.run_id, ids, [world, *services, *agents], False, world_routes)
    where = f" on {len(plan.shards)} hosts" if plan is not None else (" through a router" if services else "")
    bar = simulated.Stages(ticks, quiet=args.quiet)  # a bar on a terminal, else a line at about every tenth tick
    bar.say(f"{spec.algorithm} x {len(ids)} agents{where}, {ticks} ticks")
    t0 = time.monotonic()
    timing = {}

    def progress(k, K):
        bar.tick(k)

    launcher = Launcher(world, agents, progress, first_tick=lambda: timing.setdefault("first", time.monotonic()),
                        tolerate_agents=args.allow_missing > 0, services=services,
                        zygote=zygotes[0] if zygotes else None, keys=keys)
    if args.live is not None:
        from diskf_mesh.live.server import url

        print(f"live: {url(args.live)} (open it in Foxglove or Lichtblick)", file=sys.stderr, flush=True)
    try:
        launcher.start()
        world_rc = launcher.wait(args.startup_timeout + ticks * args.tick_timeout + 30.0)
    except ChildFailed as e:
        bar.close()
        launcher.stop_all()
        print(f"error: {e}; stopped {len(launcher.children)} processes", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        bar.close()
        launcher.stop_all()
        print(f"interrupted: stopped {len(launcher.children)} processes; logs: {logs}", file=sys.stderr)
        return 130
    bar.close()
    t_end = time.monotonic()
    # a shard ends once its agents have; a world that gave up before its first tick (its status says why) did
    # not wait for its agents to leave: they are stopped
    bad = launcher.finish(timeout=(5.0 if plan is None else 15.0) if launcher.ticked else 0.0)
    for a in bad if launcher.ticked else ():
        print(f"warning: {a.name} did not leave cleanly after the run: {a.last_error_line()}", file=sys.stderr)
    for a in launcher.stopped():
        print(a.last_error_line(), file=sys.stderr)  # "error: agent I: the estimator (...) diverged at tick K: ..."
    results = json.loads(out.read_text())
    run_line = (f"{scn.name}: {len(ids)} agent processes{where} + world, {ticks} ticks, seed {args.seed}, "
                f"run {spec.run_id}; ")
    if "first" in timing:
        print(run_line + f"first tick after {timing['first'] - t0:.2f} s ({timing['first'] - began:.2f} s after up "
                         f"started), {ticks / max(t_end - timing['first'], 1e-9):.0f} ticks/s")
    else:
        print(run_line + f"no tick ran: the world ended after {t_end - t0:.2f} s")
    print(format_table(results))
    row = next(iter(next(iter(results.values())).values()))
    verdict(row, args)
    keep = bool(args.logs) or world_rc != 0 or bool(bad)  # a run that went well leaves no temporary folder
    print(f"results: {out}" + (f", estimates: {args.estimates}" if args.estimates else "")
          + (f", recording: {args.record}" if args.record and not row.get("recording_failed") else "")
          + (f", logs: {logs}" if keep else ""))
    if not keep:
        shutil.rmtree(logs, ignore_errors=True)
    return world_rc  # up's exit status is the world's


# the world's exit statuses that carry a run's results (``core.exits``); any other is a failure
WORLD_VERDICTS = (exits.OK, exits.INCOMPLETE, exits.TOO_MANY_MISSES, exits.DEGRADED, exits.DIVERGED,
                  exits.RECORDING_FAILED, exits.UNVERIFIABLE)


def verdict(row: dict, args) -> None:
    """The lines of ``up``'s verdict on the run the world checked (its
    results ``row``, ``sim.world.exit_status`` under the same flags): the
    status, or one line on stderr when the run is not exact or as planned,
    a real-time run missed deadlines, or the recording could not be
    written whole. The exit status is the world's."""
    status = RunStatus(row["status"], row["reason"], row.get("evidence", {}))
    code, level, line = exit_status(status, row, args, realtime.from_args(args))
    if (row.get("deadline_misses") or {}).get("total") and code != exits.TOO_MANY_MISSES:
        print(f"warning: real time: {miss_line(row)}", file=sys.stderr)
    if level:
        print(f"{level}: {line}", file=sys.stderr)
    else:
        print(f"status: {status.status}: {status.reason}")
    if row.get("recording_failed"):
        print(f"error: {failure_line(row['recording_failed'])}", file=sys.stderr)


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("up", __spec__.name))

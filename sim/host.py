"""``diskf-mesh host``: the shard of a run's agents that runs on this host.

    diskf-mesh host --run-id r1 --agents 1-25 --connect tls/10.0.0.2:7447 \\
        --credentials creds [--scenario random-geometric --agent-count 100]

Starts one process per agent id of ``--agents`` (ranges and commas:
``1-20,31``), each with its own identity of the run's credentials
(``--credentials`` DIR holds at least theirs) and the same scenario flags as
the world (a generated scenario's agent count is ``--agent-count`` here,
``--agents`` is the ids). The agents are zenoh clients of ``--connect``: this
host's router (``diskf-mesh router``) or the world (docs/hosts.md);
a real-time run's ``--rate`` and ``--deadline-ms`` go to every agent
(``up --hosts --rate HZ`` gives them to every host);
``--mode peer`` with a ``--listen`` of their own makes them peers instead.
The shard waits (``--startup-timeout``) until an endpoint of ``--connect``
accepts connections, then starts the agents; a shard started after the run
began joins it (its agents rejoin as restarts do, from the tick after next).

It ends when every agent has: exit 0 if every one exited 0 (the world's
"done"), else 1 with one line naming the ones that failed (an agent that
fails does not stop the others: the world counts its missing ticks). SIGTERM
or Ctrl-C stops every agent. Bad input (``--agents 5-2``, an id not in the
scenario): one line, exit 2. ``up --hosts FILE`` starts one shard per host.
"""
from __future__ import annotations

import argparse
import re
import signal
import socket
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from diskf_mesh.core.errors import InputError
from diskf_mesh.data.argtypes import seconds
from diskf_mesh.data.faults import add_arguments as add_fault_arguments
from diskf_mesh.mesh.protocol import clock as realtime
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import runspec
from diskf_mesh.mesh.process import zenoh_config
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.process.stopping import terminated
from sim.launcher import Child, Launcher, agent_flags

STARTUP_TIMEOUT_S = 30.0


def register(subparsers) -> None:
    p = subparsers.add_parser("host", help="the shard of a run's agents on this host (docs/hosts.md)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--agents", required=True, metavar="IDS", dest="ids",
                   help="the agent ids this host runs: ranges and commas, e.g. 1-25 or 1-20,31")
    runspec.add_arguments(p, run_id_default=None, count_flag=runspec.HOST_COUNT_FLAG)
    p.add_argument("--collect-timeout", type=seconds, metavar="S", help="agents: seconds to wait for neighbours")
    p.add_argument("--world-timeout", type=seconds, metavar="S", help="agents: longest silence of the world")
    p.add_argument("--startup-timeout", type=seconds, default=STARTUP_TIMEOUT_S, metavar="S",
                   help="seconds to wait for the --connect endpoint to answer (default %(default)s)")
    p.add_argument("--logs", metavar="DIR", help="the agents' stderr logs (default: a temporary directory)")
    p.add_argument("--profile", metavar="DIR", help="agents: write DIR/agent-<id>.json (mesh.protocol.profile)")
    realtime.add_arguments(p, world=False)  # the run's --rate and --deadline-ms, as up gives them to every agent
    add_fault_arguments(p)
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


_ENDPOINT = re.compile(r"^[a-z]+/(\[[^\]]+\]|[^:/\[\]]+):(\d+)")


def address(endpoint: str):
    """(host, port) of a TCP-based endpoint (``tls/10.0.0.2:7447``), or None."""
    m = _ENDPOINT.match(endpoint)
    return (m.group(1).strip("[]"), int(m.group(2))) if m else None


def wait_for(endpoints, timeout: float) -> bool:
    """Until one of ``endpoints`` accepts a TCP connection (at most ``timeout``
    seconds); True at once if none is a TCP address."""
    addrs = [a for a in map(address, endpoints) if a is not None]
    deadline = time.monotonic() + timeout
    while addrs:
        for host, port in addrs:
            try:
                socket.create_connection((host, port), timeout=1.0).close()
                return True
            except OSError:
                pass
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.2)
    return True


def shard(args: argparse.Namespace):
    """(spec, scenario, ids, agents' zenoh options), checked (``InputError``)."""
    if not args.run_id:
        raise InputError("run-id", "give the run's --run-id (the world's)")
    ids = runspec.parse_ids(args.ids)
    spec = runspec.from_args(args)
    scn = spec.load()
    stray = sorted(set(ids) - {a.id for a in scn.agents})
    if stray:
        raise InputError("agents", f"agent {runspec.id_ranges(stray)} is not in scenario {scn.name!r} "
                                   f"(ids {runspec.id_ranges(a.id for a in scn.agents)})")
    z = zenoh_config.from_args(args)
    if not z.connect:
        raise InputError("connect", "give the endpoint of this host's router or of the world (--connect)")
    realtime.from_args(args)  # a bad --deadline-ms: one line now
    z = replace(z, mode=z.mode or "client", no_multicast_scouting=True)
    if z.credentials and not z.insecure:
        for i in ids:  # every agent's identity is there, for this run (else one line now, not N later)
            z.identity_of(credentials.agent_identity(i), spec.run_id)
    else:
        z.as_identity(f"host of agent {runspec.id_ranges(ids)}", spec.run_id)  # --insecure: one warning
    return spec, scn, ids, z


def agent_children(args: argparse.Namespace, spec, scn, ids, z, logs: Path) -> list:
    """The shard's agents as ``Child``\\ ren: the flags of ``agent_flags``
    and the real-time ones (``--rate``, ``--deadline-ms``)."""
    clock = realtime.from_args(args)
    extra = agent_flags(args, scn, args.collect_timeout, args.world_timeout) + (clock.to_argv() if clock else [])
    return [Child(f"agent {i}", runspec.agent_command(spec, i, z, extra), logs / f"agent-{i}.log",
                  identities=(credentials.agent_identity(i),)) for i in ids]


def run(args: argparse.Namespace) -> int:
    spec, scn, ids, z = shard(args)
    log = Log(f"host {runspec.id_ranges(ids)}")
    logs = Path(args.logs or tempfile.mkdtemp(prefix=f"diskf-host-{spec.run_id}-"))
    try:
        logs.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError("logs", f"cannot create {logs}: {e.strerror or e}") from None
    agents = agent_children(args, spec, scn, ids, z, logs)
    launcher = Launcher(None, agents, tolerate_agents=True, keys=z.held)  # each agent is handed its own
    previous = signal.signal(signal.SIGTERM, terminated)
    try:
        if not wait_for(z.connect, args.startup_timeout):
            log.error(f"no answer from {', '.join(z.connect)} after {args.startup_timeout:g} s")
            return 1
        launcher.start()
        print(f"host: {len(agents)} agent processes of run {spec.run_id} ({runspec.id_ranges(ids)}) "
              f"connecting to {', '.join(z.connect)}; logs: {logs}", flush=True)
        bad = launcher.wait_agents()
    except KeyboardInterrupt:
        return 130
    finally:
        launcher.stop_all()
        signal.signal(signal.SIGTERM, previous)
    if bad:
        first = bad[0]
        log.error(f"agent {', '.join(a.name.split()[-1] for a in bad)} failed (first: {first.name}, exit "
                  f"{first.proc.returncode}: {first.last_error_line()}) [logs: {logs}]")
        return 1
    return 0


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("host", __spec__.name))

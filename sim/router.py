"""``diskf-mesh router``: a zenoh router for the mesh runs of one host.

    diskf-mesh router --listen tls/10.0.0.2:7447 --connect tls/10.0.0.1:7447 \\
        --credentials creds [--run-id r1]

A router joins a host's agents to the rest of a run (docs/hosts.md): the
agents of the host connect to it as zenoh clients (``diskf-mesh host``), it
connects to the world (a router itself in a multi-host run) and to the other
hosts' routers, and zenoh's routers find the paths between them (link state;
a sample crosses each router once).

It authenticates as the run's ``router`` identity (``diskf-mesh credentials``
makes one; ``--credentials`` takes the run's directory or ``router/`` alone)
and enforces the run's access control on every process connected to it: an
agent speaks for itself only, and is sent only what it may hear. Other
routers and the world trust it with all of the run's traffic. Without the
run's CA nobody can connect (TLS only, mutual authentication).
``--insecure`` runs a plain zenoh router (anyone can use it).

It runs until SIGTERM or Ctrl-C (exit 0), after one line on stdout once it
is up: ``router <run> listening on <endpoints>``. Exit 2 on bad input, 1 if
the session cannot open (e.g. the port is taken).
"""
from __future__ import annotations

import argparse
import signal
import sys
import threading
from dataclasses import replace

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.process import zenoh_config
from diskf_mesh.mesh.wire.keys import check_run_id
from diskf_mesh.mesh.protocol.log import Log
from diskf_mesh.mesh.process.transport import MeshError, ZenohTransport


def register(subparsers) -> None:
    p = subparsers.add_parser("router", help="a zenoh router joining one host's agents to a run (docs/hosts.md)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run-id", help="the run it serves (default: the credentials' run)")
    zenoh_config.add_arguments(p)
    p.set_defaults(func=run)


def options(args: argparse.Namespace):
    """The router's zenoh options, checked (``InputError``)."""
    if args.mode not in (None, "router"):
        raise InputError("mode", f"a router runs in router mode, not {args.mode}")
    if not args.listen:
        raise InputError("listen", "give the endpoint this router listens on (--listen tls/ADDRESS:PORT)")
    run_id = args.run_id
    if run_id is not None:
        check_run_id(run_id)
    opts = zenoh_config.from_args(args)
    if run_id is None and opts.credentials and not opts.insecure:
        run_id = opts.identity_of(credentials.ROUTER).run_id
    return replace(opts.as_identity(credentials.ROUTER, run_id), mode="router"), run_id


def run(args: argparse.Namespace) -> int:
    opts, run_id = options(args)
    log = Log("router")
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set())
    try:
        with ZenohTransport(opts):
            print(f"router {run_id or '(any run)'} listening on {', '.join(opts.listen)}", flush=True)
            while not stop.wait(0.5):
                pass
    except MeshError as e:
        log.error(str(e))
        return e.status
    return 0


if __name__ == "__main__":
    from diskf_mesh.cli import main as cli

    sys.exit(cli.run_one("router", __spec__.name))

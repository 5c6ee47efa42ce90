"""``diskf-mesh credentials``: the certificates of one mesh run started by hand.

A fresh certificate authority for run ID, one certificate and key per
process (the world, every agent of the scenario, an observer that may only
listen), in DIR (0700), one self-contained directory per identity (keys
0600); the CA's own key is thrown away. Give every process the directory
and the run id:

    diskf-mesh credentials --run-id r1 --out creds --scenario dynamic
    diskf-mesh world --run-id r1 --credentials creds --listen tls/10.0.0.1:7447
    diskf-mesh agent --id 3 --run-id r1 --credentials creds --connect tls/10.0.0.1:7447

A run with a host whose agents connect straight to the world (no router
there, docs/hosts.md) needs ``--world-routes``: the world then forwards
their traffic, with a router's rights.

A host or a container needs only its own identity's directory
(``creds/agent-3``); ``--credentials`` takes either. The zenoh settings they
turn into and the access rules: docs/security.md.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials
from diskf_mesh.mesh.wire.keys import check_run_id
from diskf_mesh.data.scenario import load_scenario
from diskf_mesh.cli.options import add_command, positive_int


def id_list(text: str) -> list:
    try:
        ids = [int(t) for t in text.split(",") if t.strip()]
    except ValueError:
        ids = []
    if not ids or min(ids) < 0:
        raise argparse.ArgumentTypeError(f"must be a comma list of agent ids (integers >= 0), got {text!r}")
    return ids


def register(subparsers) -> None:
    p = add_command(subparsers, "credentials", "certificates for a mesh run started by hand", __doc__)
    p.add_argument("--run-id", required=True, help="the run they are for (world and agents get the same --run-id)")
    p.add_argument("--out", required=True, metavar="DIR", help="where to write them (created 0700)")
    who = p.add_mutually_exclusive_group()
    who.add_argument("--scenario", default="dynamic",
                     help="one certificate per agent of this scenario (a shipped name or a .toml; default: dynamic)")
    who.add_argument("--ids", type=id_list, metavar="LIST", help="or per agent id of this comma list")
    p.add_argument("--agents", type=positive_int, metavar="N", help="agent count of a generated --scenario")
    p.add_argument("--world-routes", action="store_true",
                   help="the world may forward the others' traffic (a host without a router; docs/hosts.md)")
    p.add_argument("--replace", action="store_true", help="replace the credentials already in DIR")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_run_id(args.run_id)
    out = Path(args.out)
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise InputError("out", f"{out} is not a directory")
    if out.is_dir() and any(out.iterdir()) and not args.replace:
        raise InputError("out", f"{out} is not empty (--replace to make new credentials there)")
    ids = args.ids if args.ids is not None else [a.id for a in load_scenario(args.scenario, agents=args.agents).agents]
    credentials.make(out, args.run_id, ids, world_routes=args.world_routes)
    names = credentials.identities(sorted(set(ids)))
    print(f"run {args.run_id}: {len(names)} identities ({', '.join(names)}) in {out}; the CA key is not kept")
    return 0

"""Zenoh session settings from the command line, as in zenoh-python's examples.

    --mode peer|client|router  session mode (zenoh's default: peer; docs/hosts.md)
    --connect ENDPOINT         endpoint to connect to, repeatable (tcp/10.0.0.1:7447)
    --listen ENDPOINT          endpoint to listen on, repeatable (tcp/0.0.0.0:7447)
    --no-multicast-scouting    do not discover peers by UDP multicast
    --zenoh-config FILE        a zenoh JSON5 configuration file; the flags above
                               are applied on top of it
    --cfg KEY:VALUE            any other setting, a config path and a JSON5 value
    --credentials DIR          this process's identity from a run's credentials
                               (``diskf-mesh credentials``): TLS links only, mutual
                               authentication, the run's access control
                               (``diskf_mesh.mesh.security.credentials``); the flags above are
                               applied on top. ``-``: read from standard input (how
                               ``up`` hands each process its own identity, in memory)
    --insecure                 run without credentials (plain zenoh): a world or an
                               agent refuses to start without one of the two

On one host, peers find each other with no flags (multicast scouting).
Without ``--listen`` (or a configuration file), a process listens on
loopback only (``LOOPBACK``: TLS with credentials, TCP with ``--insecure``),
so nothing off this host reaches it unless told where to listen.
Across hosts, or where multicast does not pass (Docker bridges), give the
world a ``--listen`` endpoint and every agent ``--connect`` to it plus a
``--listen`` of its own: peers learn each other's endpoints from the world
(gossip) and connect directly. Many agents, or several hosts: a zenoh
router per host and the agents its clients (``diskf-mesh router``,
``diskf-mesh host``, ``up --hosts``; docs/hosts.md).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, field, replace

from diskf_mesh.core.errors import InputError
from diskf_mesh.mesh.security import credentials as creds

MODES = ("peer", "client", "router")
STDIN = "-"  # --credentials -: the identities are on standard input (``credentials.bundle``)
# where a process listens without --listen (zenoh's own default is plain TCP on every interface)
LOOPBACK = {"tls": "tls/127.0.0.1:0", "tcp": "tcp/127.0.0.1:0"}


@dataclass(frozen=True)
class ZenohOptions:
    mode: str | None = None
    connect: tuple = ()
    listen: tuple = ()
    no_multicast_scouting: bool = False
    config_file: str | None = None
    cfg: tuple = ()
    credentials: str | None = None  # a run's credentials directory (or one identity's)
    insecure: bool = False
    identity: str | None = None     # whose credentials (not a flag: the process knows who it is)
    run_id: str | None = None       # the run they must be for
    held: dict = field(default_factory=dict, compare=False, repr=False)  # read from standard input: name -> Identity

    def to_argv(self) -> list:
        """The flags that reproduce these options (for child processes)."""
        out = []
        if self.config_file:
            out += ["--zenoh-config", self.config_file]
        if self.mode:
            out += ["--mode", self.mode]
        for e in self.connect:
            out += ["--connect", e]
        for e in self.listen:
            out += ["--listen", e]
        if self.no_multicast_scouting:
            out.append("--no-multicast-scouting")
        for c in self.cfg:
            out += ["--cfg", c]
        if self.credentials:
            out += ["--credentials", self.credentials]
        if self.insecure:
            out.append("--insecure")
        return out

    @property
    def is_default(self) -> bool:
        """No network setting given (credentials or not)."""
        return replace(self, credentials=None, insecure=False, identity=None, run_id=None) == ZenohOptions()

    def identity_of(self, name: str, run_id: str | None = None):
        """The ``credentials.Identity`` ``name`` of these options' credentials
        (a directory, or the identities read from standard input)."""
        if self.credentials == STDIN:
            return creds.pick(self.held, name, run_id)
        return creds.load(self.credentials, name, run_id)

    def as_identity(self, identity: str, run_id: str) -> "ZenohOptions":
        """These options for the mesh process ``identity`` of run ``run_id``:
        its credentials checked now (``InputError``), or, with ``--insecure``,
        one warning line on stderr. Neither: an ``InputError``."""
        opts = replace(self, identity=identity, run_id=run_id)
        if opts.credentials and opts.insecure:
            raise InputError("insecure", "give --credentials DIR or --insecure, not both")
        if opts.credentials:
            opts.identity_of(identity, run_id)
        elif opts.insecure:
            print(f"warning: {identity}: --insecure: no TLS, no access control; any process that reaches this "
                  f"zenoh network can read and write run {run_id}", file=sys.stderr, flush=True)
        else:
            raise InputError("credentials", "no credentials: give --credentials DIR (made by `diskf-mesh "
                                            "credentials`) or --insecure to run unauthenticated")
        return opts

    def to_config(self):
        """A ``zenoh.Config``; a bad file or value is an ``InputError``."""
        import zenoh

        try:
            conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        except (zenoh.ZError, OSError, ValueError) as e:
            raise InputError("zenoh-config", f"cannot load {self.config_file}: {e}") from None
        settings = []
        if self.credentials:
            if self.identity is None:
                raise InputError("credentials", "whose credentials? (no identity given)")
            settings += creds.zenoh_settings(self.identity_of(self.identity, self.run_id))
        if not self.listen and not self.config_file and self.mode != "client":
            settings.append(("listen/endpoints", json.dumps([LOOPBACK["tls" if self.credentials else "tcp"]])))
        if self.mode:
            settings.append(("mode", json.dumps(self.mode)))
        if self.connect:
            settings.append(("connect/endpoints", json.dumps(list(self.connect))))
        if self.listen:
            settings.append(("listen/endpoints", json.dumps(list(self.listen))))
        if self.no_multicast_scouting:
            settings.append(("scouting/multicast/enabled", "false"))
        for c in self.cfg:
            key, sep, value = c.partition(":")
            if not sep:
                raise InputError("cfg", f"expected KEY:VALUE, got {c!r}")
            settings.append((key, value))
        for key, value in settings:
            try:
                conf.insert_json5(key, value)
            except zenoh.ZError as e:
                raise InputError("zenoh", f"{key} = {value}: {e}") from None
        return conf


def add_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh")
    g.add_argument("--mode", "-m", choices=MODES, help="the zenoh session mode (default: peer; router: docs/hosts.md)")
    g.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", "-l", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; default: loopback only)")
    g.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    g.add_argument("--zenoh-config", metavar="FILE", help="a zenoh configuration file (JSON5)")
    g.add_argument("--cfg", metavar="KEY:VALUE", action="append", default=[],
                   help="any zenoh setting as a config path and a JSON5 value (repeatable)")
    g.add_argument("--credentials", metavar="DIR",
                   help="the run's credentials (diskf-mesh credentials): TLS, mutual authentication and access "
                        "control; this process reads its own identity's files only ('-': from standard input)")
    g.add_argument("--insecure", action="store_true",
                   help="run without credentials: plain zenoh, anyone on the network can read and write the run")


def from_args(args: argparse.Namespace, identity: str | None = None, run_id: str | None = None) -> ZenohOptions:
    """The options of the command line; with ``identity`` (a world or an
    agent), checked for that identity of run ``run_id`` (``as_identity``)."""
    opts = ZenohOptions(mode=args.mode, connect=tuple(args.connect), listen=tuple(args.listen),
                        no_multicast_scouting=args.no_multicast_scouting, config_file=args.zenoh_config,
                        cfg=tuple(args.cfg), credentials=args.credentials, insecure=args.insecure,
                        held=read_stdin() if args.credentials == STDIN and not args.insecure else {})
    return opts if identity is None else opts.as_identity(identity, run_id)


def read_stdin() -> dict:
    """The identities on standard input (``credentials.bundle``), read once,
    into a memory ``credentials.keep_private`` has closed to the user's
    other processes first; standard input then becomes /dev/null, so the
    only copy of the keys is this process's memory."""
    if os.isatty(0):
        raise InputError("credentials", "--credentials -: the identities are read from standard input, which is a "
                                        "terminal (give a directory made by `diskf-mesh credentials`)")
    creds.keep_private()
    chunks = []
    while True:
        chunk = os.read(0, 1 << 16)
        if not chunk:
            break
        chunks.append(chunk)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    return creds.unbundle(b"".join(chunks))

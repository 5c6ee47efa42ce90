"""Zenoh session settings from the command line, as in zenoh-python's examples.

    --mode peer|client         session mode (zenoh's default: peer)
    --connect ENDPOINT         endpoint to connect to, repeatable (tcp/10.0.0.1:7447)
    --listen ENDPOINT          endpoint to listen on, repeatable (tcp/0.0.0.0:7447)
    --no-multicast-scouting    do not discover peers by UDP multicast
    --zenoh-config FILE        a zenoh JSON5 configuration file; the flags above
                               are applied on top of it
    --cfg KEY:VALUE            any other setting, a config path and a JSON5 value

On one host, peers find each other with no flags (multicast scouting).
Across hosts, or where multicast does not pass (Docker bridges), give the
world a ``--listen`` endpoint and every agent ``--connect`` to it plus a
``--listen`` of its own: peers learn each other's endpoints from the world
(gossip) and connect directly.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass

from ..errors import InputError

MODES = ("peer", "client")


@dataclass(frozen=True)
class ZenohOptions:
    mode: str | None = None
    connect: tuple = ()
    listen: tuple = ()
    no_multicast_scouting: bool = False
    config_file: str | None = None
    cfg: tuple = ()

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
        return out

    @property
    def is_default(self) -> bool:
        return self == ZenohOptions()

    def to_config(self):
        """A ``zenoh.Config``; a bad file or value is an ``InputError``."""
        import zenoh

        try:
            conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        except (zenoh.ZError, OSError, ValueError) as e:
            raise InputError("zenoh-config", f"cannot load {self.config_file}: {e}") from None
        settings = []
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
    g.add_argument("--mode", "-m", choices=MODES, help="the zenoh session mode (default: peer)")
    g.add_argument("--connect", "-e", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to connect to, e.g. tcp/10.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", "-l", metavar="ENDPOINT", action="append", default=[],
                   help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    g.add_argument("--no-multicast-scouting", action="store_true", help="disable multicast scouting")
    g.add_argument("--zenoh-config", metavar="FILE", help="a zenoh configuration file (JSON5)")
    g.add_argument("--cfg", metavar="KEY:VALUE", action="append", default=[],
                   help="any zenoh setting as a config path and a JSON5 value (repeatable)")


def from_args(args: argparse.Namespace) -> ZenohOptions:
    return ZenohOptions(mode=args.mode, connect=tuple(args.connect), listen=tuple(args.listen),
                        no_multicast_scouting=args.no_multicast_scouting, config_file=args.zenoh_config,
                        cfg=tuple(args.cfg))
